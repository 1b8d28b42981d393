"""The C++ extension's Python face: loading `fastmac_exp._mac_core` and typed wrappers of its functions.

The extension is built by the package's install (`pip install -e .`). FASTMAC_CORE_SO=<path> loads a
copy of it from elsewhere instead (the studies pin one copy for a whole run, since a reinstall rewrites
the installed file in place and crashes a process that has it loaded). The MAC backend on top of it is
`fastmac_exp.backends.cpp`.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from fastmac_exp.errors import BackendUnavailable
from fastmac_exp.params import GraphParams
from fastmac_exp.types import GraphSignals

MODULE = "fastmac_exp._mac_core"
CORE_ENV = "FASTMAC_CORE_SO"

BUILD_HINT = (
    "the C++ core fastmac_exp._mac_core is not built ({why}). Build it from the repository root with "
    "`pip install --no-build-isolation -e .` (or `pip install -e .`); this needs a C++17 compiler and "
    "CMake >= 3.18. Meanwhile backend=python runs the same algorithm in pure Python."
)


def _load_from(path: str) -> Any:
    """The extension from a file of the user's choosing (FASTMAC_CORE_SO), registered under its name."""
    spec = importlib.util.spec_from_file_location(MODULE, path) if os.path.isfile(path) else None
    if spec is None or spec.loader is None:
        raise ImportError(f"{CORE_ENV}={path}: not an extension module file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules[MODULE] = module
    return module


def _import_core() -> tuple[Any, str]:
    """Import the extension with OpenMP's passive wait policy unless the user chose one.

    Only matters for cores built with -DFASTMAC_OPENMP=ON (the default build uses its own std::thread
    pool and no OpenMP). libgomp reads OMP_WAIT_POLICY once, when it is loaded; its default spins at
    every barrier for milliseconds, which on a small shared machine turns a 1 ms MAC into 100+ ms. The
    variable is restored right after the import, so nothing else in the process sees it.
    """
    keys = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
    set_here = not any(k in os.environ for k in keys)
    if set_here:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    try:
        pinned = os.environ.get(CORE_ENV)
        if pinned:
            return _load_from(pinned), ""
        from fastmac_exp import _mac_core

        return _mac_core, ""
    except ImportError as exc:  # pragma: no cover - depends on the build
        return None, str(exc)
    finally:
        if set_here:
            os.environ.pop("OMP_WAIT_POLICY", None)


_core, _IMPORT_ERROR = _import_core()


def available() -> bool:
    """True when the compiled extension could be imported."""
    return _core is not None


def core() -> Any:
    """The extension module; raises BackendUnavailable with build instructions when it is missing."""
    if _core is None:
        raise BackendUnavailable(BUILD_HINT.format(why=_IMPORT_ERROR or "import failed"))
    return _core


@dataclass
class GraphEdges:
    """The upper triangle of W (i < j) with its weights w = W_ij and second-order weights g = G_ij."""

    i: np.ndarray
    j: np.ndarray
    w: np.ndarray
    g: np.ndarray
    dense_core: int = 0  # nodes whose second-order products ran as a dense matrix product


class CliqueSearch(NamedTuple):
    """Maximal cliques in canonical order, and which cap stopped the search ("" when none did)."""

    cliques: list[np.ndarray]
    cap_hit: str


def points(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def graph_args(gp: GraphParams) -> tuple[str, float, float, float]:
    return gp.kernel, float(gp.alpha), float(gp.tau), float(gp.threshold)


def graph_edges(src: np.ndarray, tgt: np.ndarray, gp: GraphParams, num_threads: int = 0) -> GraphEdges:
    """MAC's graph as an edge list (float64 throughout, so that it agrees with the Python backend)."""
    out = core().graph_edges(points(src), points(tgt), *graph_args(gp), num_threads=num_threads)
    return GraphEdges(i=out["i"], j=out["j"], w=out["w"], g=out["g"], dense_core=int(out["dense_core"]))


def graph_signals(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    self_loops: bool = True,
    single: bool = True,
    num_threads: int = 0,
) -> GraphSignals:
    """The samplers' node signals. self_loops=True is FastMAC's graph (W_ii = 1), False is MAC's.
    single: the dense core's products in float32, as FastMAC's torch code computes this graph (relative
    error ~1e-6, about twice as fast on outdoor graphs); False: float64 throughout."""
    out = core().graph_signals(
        points(src),
        points(tgt),
        *graph_args(gp),
        self_loops=self_loops,
        single=single,
        num_threads=num_threads,
    )
    return GraphSignals(
        degree=np.asarray(out["degree"]),
        highpass=np.asarray(out["highpass"]),
        lowpass=np.asarray(out["lowpass"]),
        n_edges=int(out["n_edges"]),
        dense_core=int(out["dense_core"]),
    )


def maximal_cliques(
    n: int,
    i: np.ndarray,
    j: np.ndarray,
    min_size: int = 3,
    max_cliques: int = 0,
    time_limit_s: float = 0.0,
    num_threads: int = 0,
) -> CliqueSearch:
    """Maximal cliques of size >= min_size of the graph with edges (i, j), in canonical order."""
    cliques, cap_hit = core().maximal_cliques(
        int(n),
        np.ascontiguousarray(i, dtype=np.int64),
        np.ascontiguousarray(j, dtype=np.int64),
        min_size=int(min_size),
        max_cliques=int(max_cliques),
        time_limit_s=float(time_limit_s),
        num_threads=num_threads,
    )
    return CliqueSearch(list(cliques), str(cap_hit))


def anchor_degree(
    src: np.ndarray, tgt: np.ndarray, gp: GraphParams, anchors: np.ndarray, num_threads: int = 0
) -> np.ndarray:
    """sum_r W_{i a_r} over the anchors (a_r != i) for every node: the estimate's pilot (anchors.cpp)."""
    return np.asarray(
        core().anchor_degree(
            points(src), points(tgt), *graph_args(gp), np.ascontiguousarray(anchors, dtype=np.int64),
            num_threads=num_threads,
        )
    )  # fmt: skip


def anchors_within(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    anchors: np.ndarray,
    min_anchors: int,
    pair_budget: float,
    num_threads: int = 0,
) -> int:
    """How many of the anchor draws (a prefix) keep the estimate's pair work within pair_budget."""
    return int(
        core().anchors_within(
            points(src), points(tgt), *graph_args(gp), np.ascontiguousarray(anchors, dtype=np.int64),
            int(min_anchors), float(pair_budget), num_threads=num_threads,
        )
    )  # fmt: skip


def anchor_signals(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    anchors: np.ndarray,
    inv_q: np.ndarray,
    num_threads: int = 0,
) -> GraphSignals:
    """FastMAC's signals estimated from anchors drawn i.i.d. with probabilities q (inv_q = 1 / q of each
    draw): unbiased for the generalized degree (anchors.cpp, docs/estimated_scores.md)."""
    out = core().anchor_signals(
        points(src), points(tgt), *graph_args(gp), np.ascontiguousarray(anchors, dtype=np.int64),
        np.ascontiguousarray(inv_q, dtype=np.float64), num_threads=num_threads,
    )  # fmt: skip
    return GraphSignals(
        degree=np.asarray(out["degree"]),
        highpass=np.asarray(out["highpass"]),
        lowpass=np.asarray(out["lowpass"]),
        n_edges=-1,
        anchors=len(anchors),
    )
