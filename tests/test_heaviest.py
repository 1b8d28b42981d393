"""The branch-and-bound search (mac.search=bnb) selects exactly what node-guided selection over every
maximal clique selects (mac.search=enumerate and the Python reference), ties included, on random graphs
of every kind; its work budget is reproducible for any thread count; Ctrl-C stops it."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import igraph
import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fastmac_exp import core as cpp
from fastmac_exp.backends import python_mac
from tests.children import interrupt_child

core = cpp.core()
REPO = Path(__file__).resolve().parents[1]


def reference(n: int, i: np.ndarray, j: np.ndarray, w: np.ndarray, k: int) -> list[tuple[int, ...]]:
    """The Python reference: igraph's maximal cliques, canonical order, node-guided selection."""
    g = sp.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    cliques = python_mac.canonical_cliques(
        igraph.Graph(n=n, edges=list(zip(i.tolist(), j.tolist()))).maximal_cliques(min=k)
    )
    return [tuple(c) for c in python_mac.select_cliques(cliques, g, n)] if cliques else []


def selection(n, i, j, w, k, search, threads=1, **caps):
    out = core.select_cliques(n, i, j, w, k, search=search, num_threads=threads, **caps)
    return [tuple(c.tolist()) for c in out["cliques"]], out


def graph(kind: str, n: int, seed: int, integer_weights: bool):
    """Edges (i < j) and positive weights of a random graph of the given kind."""
    rng = np.random.default_rng(seed)
    a = np.zeros((n, n), dtype=bool)
    if kind == "sparse":
        a = rng.random((n, n)) < rng.uniform(0.05, 0.2)
    elif kind == "dense":
        a = rng.random((n, n)) < rng.uniform(0.5, 0.8)
    elif kind == "near_clique":  # a clique with a few missing edges, plus sparse outliers
        core_n = int(rng.integers(min(6, n), min(n, 40) + 1))
        a = rng.random((n, n)) < 0.05
        a[:core_n, :core_n] = rng.random((core_n, core_n)) > rng.uniform(0.01, 0.1)
    elif kind == "planted":  # several overlapping planted cliques in a sparse graph
        a = rng.random((n, n)) < 0.08
        for _ in range(int(rng.integers(2, 5))):
            members = rng.choice(n, size=int(rng.integers(4, max(5, n // 3))), replace=False)
            a[np.ix_(members, members)] = True
    a = np.triu(a | a.T, 1)
    i, j = np.nonzero(a)
    if integer_weights:  # many cliques of exactly equal weight: the tie rule decides
        w = rng.integers(1, 4, len(i)).astype(float)
    else:  # like G: positive reals in a narrow band
        w = rng.uniform(0.8, 1.2, len(i)) * 100.0
    return i.astype(np.int64), j.astype(np.int64), w


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["sparse", "dense", "near_clique", "planted"]),
    n=st.integers(6, 60),
    seed=st.integers(0, 2**31 - 1),
    k=st.sampled_from([3, 3, 4, 5]),
    integer_weights=st.booleans(),
)
def test_branch_and_bound_selects_what_enumeration_selects(kind, n, seed, k, integer_weights):
    i, j, w = graph(kind, n, seed, integer_weights)
    want = reference(n, i, j, w, k)
    enum, _ = selection(n, i, j, w, k, "enumerate")
    assert enum == want
    for threads in (1, 2):
        got, out = selection(n, i, j, w, k, "bnb", threads)
        assert got == want, (kind, n, seed, k, integer_weights, threads)
        assert out["cap_hit"] == ""
    for step3 in ("pernode", "shared"):  # the core picks one by density; both must hold on any graph
        with pruning("on", "on", step3):
            got, out = selection(n, i, j, w, k, "bnb")
        assert got == want, (kind, n, seed, k, integer_weights, step3)


def second_order_weights(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """G = W * (W @ W) on the upper-triangle edges of a, with W in [0.9, 1] as MAC's KITTI kernel gives."""
    full = a | a.T
    w1 = np.triu(rng.uniform(0.9, 1.0, a.shape), 1)
    w1 = (w1 + w1.T) * full
    g = w1 * (w1 @ w1)
    i, j = np.nonzero(a)
    return g[i, j]


@pytest.mark.parametrize("missing", [0, 3, 12, pytest.param(24, marks=pytest.mark.slow)])  # 24: 8 s
def test_near_clique_of_hundred_nodes(missing):
    """The shape high-pass sampling produces: a near-clique whose maximal cliques explode in number."""
    rng = np.random.default_rng(missing)
    n = 100
    a = np.triu(np.ones((n, n), dtype=bool), 1)
    pairs = np.argwhere(a)
    drop = pairs[rng.choice(len(pairs), size=missing, replace=False)]
    a[drop[:, 0], drop[:, 1]] = False
    i, j = np.nonzero(a)
    w = second_order_weights(a, rng)
    got, out = selection(n, i, j, w, 3, "bnb", 2)
    assert got == reference(n, i, j, w, 3)
    if missing == 0:
        assert got == [tuple(range(n))]


SWITCHES = ("FASTMAC_DOMINANCE", "FASTMAC_MATCHING", "FASTMAC_STEP3", "FASTMAC_GLOBAL_GRAPH")


@contextlib.contextmanager
def pruning(dominance: str, matching: str, step3: str | None = None, global_graph: str | None = None):
    """The near-clique switches of the branch and bound (read by the core at each call): dominance and
    the matching colouring on or off, step 3 per node or shared (None: the core's choice by density),
    one graph for every root or one per root (global_graph 'off'; None: the core's choice)."""
    old = {k: os.environ.get(k) for k in SWITCHES}
    os.environ["FASTMAC_DOMINANCE"], os.environ["FASTMAC_MATCHING"] = dominance, matching
    if step3:
        os.environ["FASTMAC_STEP3"] = step3
    if global_graph:
        os.environ["FASTMAC_GLOBAL_GRAPH"] = global_graph
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def sparse_conflicts(n: int, rng: np.random.Generator, kind: str) -> np.ndarray:
    """Upper-triangle adjacency of a clique on n nodes minus a sparse conflict graph of the given kind:
    the structure of the reduced outdoor graphs (a core adjacent to all, conflicts in small components)."""
    a = np.triu(np.ones((n, n), dtype=bool), 1)
    nodes = rng.permutation(n)
    if kind == "pairs":  # isolated conflicting pairs: one end of each in every maximal clique
        k = int(rng.integers(1, min(n // 2, 9) + 1))
        conflicts = nodes[: 2 * k].reshape(k, 2)
    elif kind == "paths":  # paths and stars of 3-5 nodes
        conflicts, at = [], 0
        while at + 3 <= n and len(conflicts) < 16 and rng.random() < 0.9:
            size = int(rng.integers(3, 6))
            part = nodes[at : at + size]
            at += size
            hub = rng.random() < 0.3
            conflicts += [(part[0], x) for x in part[1:]] if hub else list(zip(part[:-1], part[1:]))
        conflicts = np.array(conflicts, dtype=np.int64).reshape(-1, 2)
    else:  # "random": a sparse random conflict graph, about one conflict a node at most
        m = int(rng.integers(1, min(n // 2, 16) + 1))
        conflicts = rng.integers(0, n, (m, 2))
        conflicts = conflicts[conflicts[:, 0] != conflicts[:, 1]]
    lo, hi = np.minimum(conflicts[:, 0], conflicts[:, 1]), np.maximum(conflicts[:, 0], conflicts[:, 1])
    a[lo, hi] = False
    return a


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["pairs", "paths", "random"]),
    n=st.integers(8, 48),
    seed=st.integers(0, 2**31 - 1),
    k=st.sampled_from([3, 4]),
    integer_weights=st.booleans(),
)
def test_near_clique_pruning_keeps_the_selection_exact(kind, n, seed, k, integer_weights):
    """Near-cliques with sparse conflicts are where the branch and bound drops dominated candidates,
    colours by a matching of the conflicts and runs step 3 per node (heaviest.cpp): with any of them on or
    off (FASTMAC_DOMINANCE, FASTMAC_MATCHING, FASTMAC_STEP3), the selection is the enumeration's, ties
    included."""
    rng = np.random.default_rng(seed)
    a = sparse_conflicts(n, rng, kind)
    i, j = np.nonzero(a)
    w = rng.integers(1, 4, len(i)).astype(float) if integer_weights else second_order_weights(a, rng)
    keep = w > 0  # G is 0 on an edge without a common neighbour: no edge of the clique graph
    i, j, w = i[keep], j[keep], w[keep]
    want = reference(n, i, j, w, k)
    for dominance in ("on", "off"):
        for matching in ("on", "off"):
            for step3 in ("pernode", "shared"):
                with pruning(dominance, matching, step3):
                    got, out = selection(n, i, j, w, k, "bnb", 1 + (dominance == matching))
                assert got == want, (kind, n, seed, k, integer_weights, dominance, matching, step3)
                assert out["cap_hit"] == ""
    for step3 in ("pernode", "shared"):  # the near-cliques' one graph (the default here) against per root
        with pruning("on", "on", step3, "off"):
            got, out = selection(n, i, j, w, k, "bnb")
        assert got == want, (kind, n, seed, k, integer_weights, step3, "per-root graphs")


def test_near_cliques_are_searched_on_one_graph(capfd):
    """On a near-clique steps 1-3 share one graph and its weight matrix (Searcher::make_global) instead of
    building one per root; elsewhere, and with FASTMAC_GLOBAL_GRAPH=off, one per root. The same cliques
    either way, with the same search nodes (the bits run in the same rank order)."""
    rng = np.random.default_rng(3)
    a = sparse_conflicts(120, rng, "paths")
    i, j = np.nonzero(a)
    w = second_order_weights(a, rng)
    sparse_i, sparse_j, sparse_w = graph("sparse", 60, 1, False)
    old = os.environ.get("FASTMAC_DEBUG_SEARCH")
    os.environ["FASTMAC_DEBUG_SEARCH"] = "1"
    try:
        capfd.readouterr()
        got, out = selection(120, i, j, w, 4, "bnb")
        assert "one global graph" in capfd.readouterr().err
        with pruning("on", "on", None, "off"):
            per_root, out_off = selection(120, i, j, w, 4, "bnb")
        assert "per-root graph" in capfd.readouterr().err
        selection(60, sparse_i, sparse_j, sparse_w, 3, "bnb")
        assert "per-root graph" in capfd.readouterr().err
    finally:
        if old is None:
            os.environ.pop("FASTMAC_DEBUG_SEARCH", None)
        else:
            os.environ["FASTMAC_DEBUG_SEARCH"] = old
    assert got == per_root == reference(120, i, j, w, 4)
    assert out["search_nodes"] == out_off["search_nodes"] > 0


def test_near_clique_pruning_cuts_the_search():
    """A near-clique of 80 nodes whose conflicts are 8 paths of 6 nodes: a greedy colouring pairs them
    badly (each path split into two pairs and two single classes), a matching pairs them perfectly; and many
    candidates are dominated. Each cuts the search nodes, and the selection stays the same."""
    rng = np.random.default_rng(7)
    n = 80
    a = np.triu(np.ones((n, n), dtype=bool), 1)
    for path in rng.permutation(n)[:48].reshape(8, 6):
        for x, y in zip(path[:-1], path[1:]):
            a[min(x, y), max(x, y)] = False
    i, j = np.nonzero(a)
    w = second_order_weights(a, rng)
    nodes_used = {}
    for dominance, matching in (("off", "off"), ("on", "off"), ("off", "on"), ("on", "on")):
        with pruning(dominance, matching):
            got, out = selection(n, i, j, w, 3, "bnb", max_nodes=5_000_000)
        nodes_used[dominance, matching] = out["search_nodes"]
        if (dominance, matching) == ("off", "off"):
            want = got
        assert got == want and out["cap_hit"] == ""
    base = nodes_used["off", "off"]
    assert nodes_used["on", "off"] < base * 0.75, nodes_used
    assert nodes_used["off", "on"] * 20 < base, nodes_used
    assert nodes_used["on", "on"] <= nodes_used["off", "on"], nodes_used


def test_node_budget_is_reproducible_across_threads():
    i, j, w = graph("dense", 60, seed=4, integer_weights=False)
    full, out = selection(60, i, j, w, 3, "bnb")
    assert out["cap_hit"] == "" and out["search_nodes"] > 50
    budget = max(5, out["search_nodes"] // 20)
    runs = [selection(60, i, j, w, 3, "bnb", t, max_nodes=budget) for t in (1, 2, 2)]
    assert all(r[1]["cap_hit"] == f"max_nodes={budget}" for r in runs)
    assert runs[0][0] == runs[1][0] == runs[2][0]
    assert runs[0][1]["search_nodes"] == runs[1][1]["search_nodes"] == runs[2][1]["search_nodes"]
    # the cap stops every search at once (the roots left used to pay a set-up and a node each)
    assert runs[0][1]["search_nodes"] == budget + 1


def test_work_budget_is_reproducible_across_threads():
    """mac.max_work caps the branch and bound by counted work (about a nanosecond a unit), not by nodes:
    the same capped selection and the same count for any thread count, on a sparse graph (steps 2 and 3
    counted) and on a dense one (its serial greedy step counted too)."""
    for kind, n, seed in (("sparse", 120, 3), ("dense", 60, 4)):
        i, j, w = graph(kind, n, seed=seed, integer_weights=False)
        full, out = selection(n, i, j, w, 3, "bnb")
        assert out["cap_hit"] == "" and out["search_work"] > 1000, out["search_work"]
        budget = out["search_work"] // 10
        runs = [selection(n, i, j, w, 3, "bnb", t, max_work=budget) for t in (1, 2, 3)]
        assert all(r[1]["cap_hit"] == f"max_work={budget}" for r in runs), [r[1]["cap_hit"] for r in runs]
        assert runs[0][0] == runs[1][0] == runs[2][0] and runs[0][0]
        works = {r[1]["search_work"] for r in runs}
        assert len(works) == 1 and budget < works.pop() < out["search_work"]
        assert runs[0][0] != full or kind == "dense"  # a tenth of the work does not finish a sparse search


def test_work_budget_bounds_a_dense_graphs_greedy_step():
    """On a dense graph each greedy clique of step 1 costs ~degree x clique size (a 2,476-node graph
    without the reduction took 19 s there before any search node); the work budget covers that step: a
    tiny budget stops it after its first cliques, with no search node, and still selects."""
    rng = np.random.default_rng(5)
    n = 400
    a = np.triu(rng.random((n, n)) < 0.7, 1)
    i, j = np.nonzero(a)
    w = rng.uniform(0.8, 1.2, len(i)) * 100.0
    got, out = selection(n, i, j, w, 3, "bnb", max_work=10_000)
    assert out["cap_hit"] == "max_work=10000" and out["search_nodes"] == 0 and got
    assert out["search_work"] < 10 * 10_000  # stopped at the first greedy clique past the budget


def test_mac_default_search_is_auto_and_all_searches_agree():
    from tests.test_cpp_core import clustered

    src, tgt, _, _ = clustered(400, 0.3, 0.002, seed=9, extent=3.0)
    args = (src, tgt, "quadratic", 0.06, 0.1, 0.9, 0.1)
    auto = core.mac(*args, return_selected=True)  # few maximal cliques: the enumeration runs
    bnb = core.mac(*args, search="bnb", return_selected=True)
    enum = core.mac(*args, search="enumerate", return_selected=True)
    forced = core.mac(*args, enumerate_budget=0, return_selected=True)  # auto straight to the bnb
    assert auto["search_used"] == "enumerate" and auto["n_cliques"] == enum["n_cliques"]
    assert forced["search_used"] == bnb["search_used"] == "bnb"
    for r in (bnb, enum, forced):
        assert [tuple(c) for c in r["selected"]] == [tuple(c) for c in auto["selected"]]
        np.testing.assert_array_equal(r["pose"], auto["pose"])
    assert bnb["search_nodes"] == forced["search_nodes"] > 0 and enum["search_nodes"] == 0
    with pytest.raises(ValueError, match="search"):
        core.mac(*args, search="fast")


def test_auto_gives_the_enumeration_up_exactly_above_its_budget():
    """2^12 maximal cliques on 40 nodes: the enumeration's work is the same number for 1, 2 and 3 threads (a
    property of the graph); auto enumerates while the budget a node times the 40 nodes covers it and switches
    to the branch and bound just below, with the same selection either way."""
    n, pairs = 40, 12
    a = np.triu(np.ones((n, n), dtype=bool), 1)
    a[np.arange(0, 2 * pairs, 2), np.arange(1, 2 * pairs + 1, 2)] = False
    i, j = np.nonzero(a)
    w = second_order_weights(a, np.random.default_rng(1))
    ref, _ = selection(n, i, j, w, 3, "enumerate")
    works = {
        t: selection(n, i, j, w, 3, "auto", t, enumerate_budget=10**9)[1]["enumerate_work"] for t in (1, 2, 3)
    }
    work = works[1]
    assert works == {1: work, 2: work, 3: work} and work > 160 * 2**pairs  # a search node per clique
    enough, short = -(-work // n), (work - 1) // n  # n * enough >= work > n * short
    for threads in (1, 2, 3):
        for budget, used in ((enough, "enumerate"), (short, "bnb"), (0, "bnb")):
            got, out = selection(n, i, j, w, 3, "auto", threads, enumerate_budget=budget)
            assert out["search_used"] == used and out["cap_hit"] == ""
            if used == "enumerate":
                assert out["n_cliques"] == 2**pairs and out["search_nodes"] == 0
            else:
                assert out["search_nodes"] > 0
            assert got == ref


def test_weights_must_be_positive():
    with pytest.raises(ValueError, match="positive"):
        core.select_cliques(3, np.array([0, 1, 0]), np.array([1, 2, 2]), np.array([1.0, 0.0, 1.0]), 3)


# a graph with ~2^40 maximal cliques: 40 disjoint missing edges in a clique of 100 (the enumeration
# cannot finish; the default branch and bound takes milliseconds)
EXPLODING_SETUP = """
import numpy as np
from fastmac_exp import core as cpp
n = 100
a = np.triu(np.ones((n, n), dtype=bool), 1)
a[np.arange(0, 80, 2), np.arange(1, 81, 2)] = False
i, j = np.nonzero(a)
w = np.random.default_rng(0).uniform(300, 500, len(i))
one_call_cpu = 0  # the call cannot finish
"""
EXPLODING_CALL = """
    cpp.core().select_cliques(n, i, j, w, 3, search="enumerate")
"""


@pytest.mark.signals
@pytest.mark.skipif(os.name != "posix", reason="sends SIGINT")
def test_ctrl_c_stops_a_long_clique_search_at_once():
    rc, word, after_cpu, _ = interrupt_child(EXPLODING_SETUP, EXPLODING_CALL)
    assert rc == 130 and word == "interrupted"
    assert after_cpu < 0.5, f"{after_cpu:.2f} CPU s to stop"  # ~0.02 s


def test_exploding_graph_is_fast_with_branch_and_bound():
    """2^16 maximal cliques (16 disjoint missing edges in a clique of 100): a few thousand search nodes."""
    n, pairs = 100, 16
    a = np.triu(np.ones((n, n), dtype=bool), 1)
    a[np.arange(0, 2 * pairs, 2), np.arange(1, 2 * pairs + 1, 2)] = False
    i, j = np.nonzero(a)
    w = second_order_weights(a, np.random.default_rng(0))
    got, out = selection(n, i, j, w, 3, "bnb", 2)
    enum, eout = selection(n, i, j, w, 3, "enumerate", 2)
    auto, aout = selection(n, i, j, w, 3, "auto", 2)  # the default budget: far less than 2^16 big cliques
    assert eout["n_cliques"] == 2**pairs
    assert got == enum == auto
    assert out["cap_hit"] == "" and out["search_nodes"] < 20_000
    assert aout["search_used"] == "bnb" and aout["search_nodes"] == out["search_nodes"]
    for c in got:  # one endpoint of each missing pair and every other vertex
        members = set(c)
        assert set(range(2 * pairs, n)) <= members
        assert all((2 * p in members) != (2 * p + 1 in members) for p in range(pairs))


def test_enumerate_budget_is_a_checked_mac_parameter():
    from fastmac_exp.backends import cpp as cpp_backend
    from fastmac_exp.errors import InputError
    from fastmac_exp.params import mac_params_for
    from fastmac_exp.types import Correspondences
    from tests.test_cpp_core import clustered

    with pytest.raises(InputError, match="enumerate_budget"):
        mac_params_for("3dmatch", "fpfh", mac_overrides={"enumerate_budget": -1})
    with pytest.raises(InputError, match="search"):
        mac_params_for("3dmatch", "fpfh", mac_overrides={"search": "fast"})
    src, tgt, _, _ = clustered(400, 0.3, 0.002, seed=9, extent=3.0)
    corr = Correspondences(src, tgt)
    results = {
        budget: cpp_backend.CppBackend().register(
            corr, mac_params_for("3dmatch", "fpfh", mac_overrides={"enumerate_budget": budget})
        )
        for budget in (None, 0)
    }
    assert results[None].search == "auto:enumerate" and results[0].search == "auto:bnb"
    np.testing.assert_array_equal(results[None].pose, results[0].pose)
