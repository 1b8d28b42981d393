"""MAC on the C++ core (`fastmac_exp._mac_core`, built by `pip install -e .`).

Same algorithm and the same deterministic choices as `fastmac_exp.backends.python_mac` (canonical
clique order, node-guided selection, earliest hypothesis on score ties), so both backends select the
same cliques and return the same pose up to floating-point rounding.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from fastmac_exp.errors import BackendUnavailable, RegistrationFailed
from fastmac_exp.params import GraphParams, MacParams
from fastmac_exp.types import Correspondences, RegistrationResult


def _import_core() -> tuple[Any, str]:
    """Import the extension with OpenMP's passive wait policy unless the user chose one.

    Only matters for cores built with -DFASTMAC_OPENMP=ON (the default build uses its own thread
    pool and no OpenMP).

    libgomp reads OMP_WAIT_POLICY once, when it is loaded. Its default spins at every barrier for
    milliseconds; on a small shared machine (or next to OpenBLAS's spinning threads) that turns a
    1 ms MAC into 100+ ms. The variable is restored right after the import, so nothing else in the
    process sees it. (If another library loaded libgomp first, e.g. torch, its setting stays.)
    """
    keys = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
    set_here = not any(k in os.environ for k in keys)
    if set_here:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    try:
        from fastmac_exp import _mac_core
    except ImportError as exc:  # pragma: no cover - depends on the build
        return None, str(exc)
    finally:
        if set_here:
            os.environ.pop("OMP_WAIT_POLICY", None)
    return _mac_core, ""


_core, _IMPORT_ERROR = _import_core()

BUILD_HINT = (
    "the C++ core fastmac_exp._mac_core is not built ({why}). Build it from the repository root with "
    "`pip install --no-build-isolation -e .` (or `pip install -e .`); this needs a C++17 compiler and "
    "CMake >= 3.18. Meanwhile backend=python runs the same algorithm in pure Python."
)


def available() -> bool:
    """True when the compiled extension can be imported."""
    return _core is not None


def core() -> Any:
    """The extension module; raises BackendUnavailable with build instructions when it is missing."""
    if _core is None:
        raise BackendUnavailable(BUILD_HINT.format(why=_IMPORT_ERROR or "import failed"))
    return _core


def _points(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _graph_args(gp: GraphParams) -> tuple[str, float, float, float]:
    return gp.kernel, float(gp.alpha), float(gp.tau), float(gp.threshold)


def graph_edges(
    src: np.ndarray, tgt: np.ndarray, gp: GraphParams, num_threads: int = 0
) -> dict[str, np.ndarray]:
    """Upper-triangle edges of W: `i < j`, weights `w = W_ij` and second-order weights `g = G_ij`."""
    return core().graph_edges(_points(src), _points(tgt), *_graph_args(gp), num_threads=num_threads)


def graph_signals(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    self_loops: bool = True,
    single: bool = True,
    num_threads: int = 0,
) -> dict[str, Any]:
    """Node signals of the SOG for the samplers (spec 7.2-7.3).

    Returns `degree` (generalized degree s), `highpass` (signed; samplers take |.|), `lowpass`, `n_edges`
    (first-order edges) and `dense_core` (nodes whose second-order products ran as a dense matrix
    product; 0: all sparse). self_loops=True is FastMAC's graph (W_ii = 1), False is MAC's. single: the
    dense core's products in float32, as FastMAC's torch code computes this graph (relative error ~1e-6,
    about twice as fast on outdoor graphs); False: float64 throughout.
    """
    return core().graph_signals(
        _points(src), _points(tgt), *_graph_args(gp), self_loops=self_loops, single=single,
        num_threads=num_threads,
    )  # fmt: skip


def maximal_cliques(
    n: int,
    i: np.ndarray,
    j: np.ndarray,
    min_size: int = 3,
    max_cliques: int = 0,
    time_limit_s: float = 0.0,
    num_threads: int = 0,
) -> tuple[list[np.ndarray], str]:
    """Maximal cliques of size >= min_size of the graph with edges (i, j), in canonical order."""
    return core().maximal_cliques(
        int(n),
        np.ascontiguousarray(i, dtype=np.int64),
        np.ascontiguousarray(j, dtype=np.int64),
        min_size=int(min_size),
        max_cliques=int(max_cliques),
        time_limit_s=float(time_limit_s),
        num_threads=num_threads,
    )


class CppBackend:
    """MAC (graph, cliques, selection, pose) in the C++ core, multi-threaded.

    num_threads: 0 = automatic (OMP_NUM_THREADS if set, else all cores; one thread below 1,500
    correspondences). Results do not depend on the thread count.

    timings (ms, wall clock): graph = W and G; cliques = reduction check, clique search and, streamed
    into it, each clique's weight and the per-node choice of node-guided selection (so no clique list
    is ever stored); selection = merging those choices and deduplicating; pose = hypotheses, scores,
    refinement. The Python backend's `selection` also contains the clique weights.

    max_cliques keeps the first cliques of a serial search in degeneracy order (the Python backend
    keeps igraph's first ones), so capped runs can differ between the backends; time_limit_s is
    honoured here only.
    """

    name = "cpp"

    def __init__(self, num_threads: int = 0) -> None:
        self._core = core()
        self.num_threads = int(num_threads)

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        n = len(corr)
        if n < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {n}")
        # The core raises fastmac_exp.errors.RegistrationFailed itself (no edge, no clique, no pose).
        r = self._core.mac(
            _points(corr.src),
            _points(corr.tgt),
            *_graph_args(params.graph),
            inlier_threshold=float(params.inlier_threshold),
            min_clique_size=int(params.min_clique_size),
            refine_iters=int(params.refine_iters),
            reduction=bool(params.reduction),
            search=str(params.search),
            max_cliques=int(params.max_cliques),
            max_nodes=int(params.max_nodes),
            time_limit_s=float(params.time_limit_s),
            num_threads=self.num_threads,
        )
        return RegistrationResult(
            pose=r["pose"],
            pose_unrefined=r["pose_unrefined"],
            kept=np.arange(n),
            clique=r["clique"],
            score=float(r["score"]),
            n_cliques=int(r["n_cliques"]),
            n_selected=int(r["n_selected"]),
            n_edges=int(r["n_edges"]),
            reduced=bool(r["reduced"]),
            cap_hit=str(r["cap_hit"]),
            search=str(params.search),
            search_nodes=int(r["search_nodes"]),
            timings=dict(r["timings"]),
        )
