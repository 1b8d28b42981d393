"""MAC on the C++ core (loaded by `fastmac_exp.core`, built by `pip install -e .`).

Same algorithm and the same deterministic choices as `fastmac_exp.backends.python_mac` (canonical
clique order, node-guided selection, earliest hypothesis on score ties), so both backends select the
same cliques and return the same pose up to floating-point rounding.
"""

from __future__ import annotations

import time

import numpy as np

from fastmac_exp import core
from fastmac_exp.backends.product_bound import bounded_subset, refine_on
from fastmac_exp.core import graph_args, points
from fastmac_exp.errors import RegistrationFailed
from fastmac_exp.params import MacParams
from fastmac_exp.types import Correspondences, RegistrationResult


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
        self._core = core.core()
        self.num_threads = int(num_threads)

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        """MAC on every correspondence, or, where the second-order products' predicted work passes
        mac.max_product_work, on the densest that fit, refined on all (product_bound.py)."""
        n = len(corr)
        if n < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {n}")
        t0 = time.perf_counter()
        sub = bounded_subset(corr.src, corr.tgt, params)
        counted = (time.perf_counter() - t0) * 1e3  # the work count belongs to the graph stage
        if sub is None:
            res = self._mac(corr, params)
            res.timings["graph"] += counted
            return res
        res = self._mac(corr.subset(sub), params)
        res.timings["graph"] += counted
        t1 = time.perf_counter()
        res.pose, res.score = refine_on(res.pose_unrefined, corr.src, corr.tgt, params)
        res.kept = np.arange(n)
        res.clique = sub[res.clique]
        res.cap_hit = "; ".join(
            c for c in (res.cap_hit, f"product work: MAC on the {len(sub)} densest of {n}") if c
        )
        res.timings["pose"] = res.timings.get("pose", 0.0) + (time.perf_counter() - t1) * 1e3
        return res

    def _mac(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        n = len(corr)
        # The core raises fastmac_exp.errors.RegistrationFailed itself (no edge, no clique, no pose).
        r = self._core.mac(
            points(corr.src),
            points(corr.tgt),
            *graph_args(params.graph),
            inlier_threshold=float(params.inlier_threshold),
            min_clique_size=int(params.min_clique_size),
            refine_iters=int(params.refine_iters),
            reduction=bool(params.reduction),
            search=str(params.search),
            max_cliques=int(params.max_cliques),
            max_nodes=int(params.max_nodes),
            max_work=int(params.max_work),
            time_limit_s=float(params.time_limit_s),
            enumerate_budget=int(params.enumerate_budget),
            num_threads=self.num_threads,
            return_hypotheses=True,
        )
        search = str(params.search)
        if search == "auto":
            search = f"auto:{r['search_used']}"  # which of the two searches ran
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
            search=search,
            search_nodes=int(r["search_nodes"]),
            timings=dict(r["timings"]),
            hypothesis_poses=r["hypothesis_poses"],
            hypothesis_scores=r["hypothesis_scores"],
        )
