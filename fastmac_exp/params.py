"""Per-dataset and per-descriptor parameters of the compatibility graph and of MAC (spec sections 2.2, 3, 5).

Every value here is the reference code's default; `mac_params_for` resolves them for one pair, and
explicit overrides (the `graph:`/`mac:` config keys) win over the table.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from fastmac_exp.errors import InputError
from fastmac_exp.families import FIXED_RESOLUTION, GAUSSIAN, QUADRATIC
from fastmac_exp.families import family as family_record


@dataclass(frozen=True)
class GraphParams:
    """First-order compatibility: d_ij = | |p_i - p_j| - |q_i - q_j| |, s = kernel(d), edge iff s >= thr.

    gaussian: s = exp(-d^2 / (2 alpha^2)); quadratic: s = 1 - d^2 / tau^2. Surviving weights keep their value.
    """

    kernel: str = GAUSSIAN
    alpha: float = 0.06
    tau: float = 0.1
    threshold: float = 0.995

    def __post_init__(self) -> None:
        if self.kernel not in (GAUSSIAN, QUADRATIC):
            raise InputError(f"graph.kernel must be '{GAUSSIAN}' or '{QUADRATIC}', got {self.kernel!r}")
        if not 0.0 < self.threshold <= 1.0:
            raise InputError(f"graph.threshold must be in (0, 1], got {self.threshold}")
        if self.alpha <= 0 or self.tau <= 0:
            raise InputError(f"graph.alpha and graph.tau must be positive, got {self.alpha}, {self.tau}")

    @property
    def max_distance(self) -> float:
        """The largest inconsistency d that still makes an edge."""
        if self.kernel == GAUSSIAN:
            import math

            return self.alpha * math.sqrt(-2.0 * math.log(self.threshold)) if self.threshold < 1 else 0.0
        return self.tau * (1.0 - self.threshold) ** 0.5


SEARCHES = ("auto", "bnb", "enumerate")
# Branch-and-bound budget (search-tree nodes of one selection), ~1 s of work (1-4 us per node), so that no
# input can hang a run. Real pairs need <= 2e5 nodes; near-cliques with hundreds of evenly weighted conflicts
# need more than any budget a run can afford (synthetic KITTI-like pair 3 at 20 %: 187 nodes after the
# spec-2.5 reduction, 342 missing edges, 8e6 nodes / 9 s exactly; capped at 1e6 its pose is 0.0008 deg and
# 8 um from the exact one). A run that spends it says so in `cap_hit` (the same on every machine).
DEFAULT_MAX_NODES = 1_000_000
# The branch and bound's work budget, in units of about a nanosecond of one core (counted steps of its
# greedy cliques, set-ups, branches and bounds; 0.8-1.4 ns a unit measured): about a quarter of a second
# whatever the graph's size. The 13 real pairs at 5,000 FPFH correspondences take at most 39M units (MAC@100,
# search=bnb); a node costs ~100 units there and up to ~10^6 on a dense 2,500-node graph, where the
# 1,000,000-node cap alone allowed minutes. Near-cliques spend any budget proving what the greedy cliques
# found: on the 5,000-node near-clique samples=5000 keeps of 200,000 correspondences (10 % inliers), 2.5e8,
# 1e9 and 1e10 units give cliques of 1,195, 1,195 and 1,219 nodes and poses within 7e-6 deg and 4 um, in
# ~0.25, ~1 and ~10 s (it was 1e9 until FastMAC's 2-s target at 200,000 asked for the second back).
DEFAULT_MAX_WORK = 250_000_000
# search="auto" enumerates the maximal cliques while the enumeration's work stays within this budget per
# node that can be in a clique, else runs the branch and bound. Work is counted in units of about a
# nanosecond of one core (measured on real pairs): 160 a search node, 1 a member pair of each clique found
# weighed from a root's local weights (12 from the global rows, roots of 96 or more candidates). Sparse
# graphs (real 3DMatch and the sparser real KITTI and Apollo FPFH graphs: 2,000-3,000 units a node, 23k-35k
# maximal cliques among 5,000 nodes) enumerate 2-3x faster than the branch and bound bounds them, and graphs
# of ~100k maximal cliques (10,000-13,000 units a node) still about 2x faster; a graph over budget pays that
# much enumeration first (at most ~80 ms of a core on 5,000 nodes, ~16 ms on FastMAC@20's 1,000). Whether
# it is over budget is a property of the graph, not of threads or timing.
DEFAULT_ENUMERATE_BUDGET = 16_000
# MAC's second-order products cost ~sum_i deg_i^2 multiply-adds each (the wedges; m^3 on a dense core of m);
# past this, predicted before the products from an anchor estimate of the degrees, MAC runs on the densest
# part of the keep that fits and refines on all of it (fastmac_exp/backends/product_bound.py).
DEFAULT_MAX_PRODUCT_WORK = 3_000_000_000


@dataclass(frozen=True)
class MacParams:
    """Everything MAC needs besides the correspondences."""

    graph: GraphParams = field(default_factory=GraphParams)
    inlier_threshold: float = 0.1  # tau of the hypothesis score (MAE) and refinement
    min_clique_size: int = 3
    refine_iters: int = 20
    reduction: bool = True  # the dense-graph reduction of spec section 2.5
    # How node-guided selection finds its cliques: "bnb" = each node's heaviest clique by branch and
    # bound (exact: the same selection as enumerating every maximal clique); "enumerate" = every maximal
    # clique (the reference; the only search of the Python backend); "auto" = the enumeration while its
    # work stays within `enumerate_budget` a node, else the branch and bound (the same selection either
    # way; the row's `search` says which ran: "auto:enumerate" or "auto:bnb"). max_cliques applies to
    # "enumerate".
    search: str = "auto"
    # Work budgets (0 = off): a capped result is the same on any machine and thread count, and says so
    # in `cap_hit`. max_cliques bounds the enumeration; max_work (units of ~1 ns of one core) and
    # max_nodes (search nodes) bound the branch and bound, whichever is spent first.
    max_cliques: int = 0
    max_nodes: int = DEFAULT_MAX_NODES
    max_work: int = DEFAULT_MAX_WORK
    enumerate_budget: int = DEFAULT_ENUMERATE_BUDGET  # auto only, work units a node; 0 = always bnb
    # predicted multiply-adds of the second-order products (sum of squared degrees) past which MAC runs on
    # the densest nodes that fit (C++ backend; 0 = off: always the exact products)
    max_product_work: float = DEFAULT_MAX_PRODUCT_WORK
    time_limit_s: float = 0.0  # wall-clock safety net on the clique search, 0 = off (not reproducible)
    family: str = ""  # the dataset family the defaults came from (mac_params_for); peers take theirs by it

    def __post_init__(self) -> None:
        if self.search not in SEARCHES:
            raise InputError(f"mac.search must be one of {', '.join(SEARCHES)}, got {self.search!r}")
        for name in ("max_cliques", "max_nodes", "max_work", "max_product_work"):
            if getattr(self, name) < 0:
                raise InputError(f"mac.{name} must be >= 0 (0 = no cap), got {getattr(self, name)}")
        if self.enumerate_budget < 0:
            raise InputError(
                "mac.enumerate_budget must be >= 0 (0 = the branch and bound at once), "
                f"got {self.enumerate_budget}"
            )
        if self.time_limit_s < 0:
            raise InputError(f"mac.time_limit_s must be >= 0 (0 = no limit), got {self.time_limit_s}")
        if self.inlier_threshold <= 0:
            raise InputError(f"inlier_threshold must be positive, got {self.inlier_threshold}")
        if self.min_clique_size < 3:
            raise InputError(
                f"min_clique_size must be at least 3 (a pose needs 3 points), got {self.min_clique_size}"
            )


def graph_params_for(family: str, descriptor: str, resolution: float = FIXED_RESOLUTION) -> GraphParams:
    """The reference graph parameters (spec table 2.2) for a dataset family and a descriptor."""
    fam = family_record(family)
    kernel, thr = fam.graph(descriptor)
    return GraphParams(kernel=kernel, alpha=10.0 * resolution, tau=fam.inlier_threshold, threshold=thr)


def mac_params_for(
    family: str,
    descriptor: str,
    resolution: float = FIXED_RESOLUTION,
    graph_overrides: dict[str, Any] | None = None,
    mac_overrides: dict[str, Any] | None = None,
) -> MacParams:
    """Resolve MAC's parameters for one pair; `None` values in the overrides mean 'use the table'."""
    graph = graph_params_for(family, descriptor, resolution)
    fam = family_record(family)
    g = {k: v for k, v in (graph_overrides or {}).items() if v is not None}
    unknown = set(g) - {"kernel", "alpha", "tau", "threshold"}
    if unknown:
        raise InputError(
            f"unknown graph parameter(s) {sorted(unknown)}; known: kernel, alpha, tau, threshold"
        )
    graph = replace(graph, **g)
    base = MacParams(
        graph=graph,
        inlier_threshold=fam.inlier_threshold,
        min_clique_size=fam.min_clique_size,
        family=fam.name,
    )
    m = {k: v for k, v in (mac_overrides or {}).items() if v is not None}
    known = {
        "inlier_threshold",
        "min_clique_size",
        "refine_iters",
        "reduction",
        "search",
        "max_cliques",
        "max_nodes",
        "max_work",
        "enumerate_budget",
        "max_product_work",
        "time_limit_s",
    }
    if set(m) - known:
        raise InputError(f"unknown mac parameter(s) {sorted(set(m) - known)}; known: {sorted(known)}")
    return replace(base, **m)
