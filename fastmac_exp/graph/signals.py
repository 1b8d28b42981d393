"""The samplers' node signals and the one place that picks the engine computing them (spec 7.2-7.3).

Three engines give the same signals: the C++ core (`fastmac_exp.core`, the default once built), torch
(`graph.torch_graph`, FastMAC's own formulation, on CPU or CUDA) and numpy/scipy (`graph.numpy_graph`,
the reference the others are tested against).
"""

from __future__ import annotations

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.params import GraphParams
from fastmac_exp.types import GraphSignals

ENGINES = ("auto", "cpp", "torch", "python")


def compute_signals(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    self_loops: bool = True,
    impl: str = "auto",
    device: str = "cpu",
) -> GraphSignals:
    """The signals from the engine `impl`: auto = cpp when built, else torch on a non-CPU device, else
    numpy; cpp raises BackendUnavailable (with build instructions) when the core is missing."""
    if impl not in ENGINES:
        raise InputError(f"sampler.impl must be one of {', '.join(ENGINES)}, got {impl!r}")
    if impl in ("auto", "cpp"):
        from fastmac_exp import core

        if impl == "cpp" or core.available():
            return core.graph_signals(src, tgt, gp, self_loops=self_loops)
    if impl == "torch" or device != "cpu":
        from fastmac_exp.graph.torch_graph import graph_signals_torch

        return graph_signals_torch(src, tgt, gp, self_loops=self_loops, device=device)
    from fastmac_exp.graph.numpy_graph import graph_signals

    return graph_signals(src, tgt, gp, self_loops=self_loops)
