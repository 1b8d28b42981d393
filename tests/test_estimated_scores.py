"""The estimated sampler scores (anchors.cpp, fastmac_exp.graph.estimate) against the exact ones."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import spearmanr

from fastmac_exp import core
from fastmac_exp.errors import InputError
from fastmac_exp.graph import first_order, signals_from_graph
from fastmac_exp.graph.estimate import EXACT_BELOW, EstimateParams, choose_scores, estimate_signals
from fastmac_exp.params import GraphParams, mac_params_for
from fastmac_exp.samplers import GraphFilterSampler, NoSampler, RandomSampler
from fastmac_exp.samplers.base import count_from_samples
from tests.conftest import make_correspondences

pytestmark = pytest.mark.skipif(not core.available(), reason="C++ core not built")

GP = GraphParams(kernel="gaussian", alpha=0.06, tau=0.1, threshold=0.99)


def dense_w(corr, gp: GraphParams) -> np.ndarray:
    """W with W_ii = 0, from the numpy reference."""
    return first_order(corr.src, corr.tgt, gp).toarray()


def reference_estimate(w: np.ndarray, a: np.ndarray, inv_q: np.ndarray):
    """The estimator's formulas written out in numpy (anchors.cpp's header), on a dense W."""
    n, m = len(w), len(a)
    C = w[:, a].copy()  # W_{i a_r}; W_ii = 0 already removes a_r = i
    B = w[np.ix_(a, a)].copy()
    B[a[:, None] == a[None, :]] = 0.0
    V = C * inv_q
    d = (V * C).sum(1) / m
    T = ((V @ B) * V).sum(1) / (m * (m - 1))
    s = 1 + 3 * d + T
    sa = s[a]
    e = (V * C * sa).sum(1) / m
    g = (((V * sa) @ B) * V).sum(1) / (m * (m - 1))
    t = (1 + d) * s + 2 * e + g
    return s, s * s - t, s + t / s, n


QUADRATIC = GraphParams(kernel="quadratic", alpha=0.06, tau=0.1, threshold=0.9)


@pytest.mark.parametrize("gp", [GP, QUADRATIC], ids=["gaussian", "quadratic"])
def test_anchor_signals_follow_the_formulas(gp):
    """Rows with many compatible anchors take the vectorised pair sums, the others the scalar ones; the
    quadratic kernel its AVX-512 row where the CPU has it: every row against the formulas."""
    corr, _ = make_correspondences(n=150, inlier_ratio=0.4, noise=0.003, seed=3)
    w = dense_w(corr, gp)
    k = (w > 0).sum(1)
    assert k.max() >= 40 // 16 and k.min() < 40 // 16  # both kinds of row
    rng = np.random.default_rng(0)
    q = rng.uniform(0.2, 1.0, len(w))
    q /= q.sum()
    a = rng.choice(len(w), size=40, p=q)  # with repeats: duplicate draws must not pair with themselves
    assert len(np.unique(a)) < len(a)
    sig = core.anchor_signals(corr.src, corr.tgt, gp, a, 1.0 / q[a])
    s, f, low, _ = reference_estimate(w, a, 1.0 / q[a])
    # the core computes W in float: compare at float precision of the weights
    np.testing.assert_allclose(sig.degree, s, rtol=1e-5)
    np.testing.assert_allclose(sig.highpass, f, rtol=1e-4, atol=1e-4 * np.abs(f).max())
    np.testing.assert_allclose(sig.lowpass, low, rtol=1e-5)
    assert sig.anchors == 40 and sig.n_edges == -1


@pytest.mark.parametrize("uniform", [True, False])
def test_degree_estimate_is_unbiased(uniform):
    corr, _ = make_correspondences(n=120, inlier_ratio=0.3, noise=0.003, seed=5)
    exact = signals_from_graph(first_order(corr.src, corr.tgt, GP), self_loops=True).degree
    n, m, reps = len(exact), 24, 20_000
    rng = np.random.default_rng(1)
    q = np.full(n, 1.0 / n) if uniform else rng.uniform(0.1, 1.0, n)
    q /= q.sum()
    draws = np.stack(
        [
            core.anchor_signals(corr.src, corr.tgt, GP, a, 1.0 / q[a]).degree
            for a in (rng.choice(n, size=m, p=q) for _ in range(reps))
        ]
    )
    live = exact > 1  # isolated nodes have s = 1 exactly
    # the nodes' estimates share the draws, so test their total (one z) and each node separately; a
    # formula off by m^2 / (m (m - 1)) in the triangle term moves the total by ~5 standard errors
    total = draws[:, live].sum(1)
    z_total = (total.mean() - exact[live].sum()) / (total.std(ddof=1) / np.sqrt(reps))
    assert abs(z_total) < 4, z_total
    mean, se = draws.mean(0), draws.std(0, ddof=1) / np.sqrt(reps)
    assert np.max(np.abs(mean - exact)[live] / se[live]) < 5
    np.testing.assert_array_equal(draws[:, ~live], 1.0)


def test_estimate_does_not_depend_on_threads():
    corr, _ = make_correspondences(n=3000, inlier_ratio=0.1, noise=0.003, seed=2)
    rng = np.random.default_rng(4)
    a = rng.choice(len(corr), size=300)
    inv_q = np.full(300, float(len(corr)))
    one = core.anchor_signals(corr.src, corr.tgt, GP, a, inv_q, num_threads=1)
    two = core.anchor_signals(corr.src, corr.tgt, GP, a, inv_q, num_threads=2)
    np.testing.assert_array_equal(one.highpass, two.highpass)
    np.testing.assert_array_equal(
        core.anchor_degree(corr.src, corr.tgt, GP, a, num_threads=1),
        core.anchor_degree(corr.src, corr.tgt, GP, a, num_threads=3),
    )


_PORTABLE_CHILD = """
import sys, numpy as np
from fastmac_exp import core
from fastmac_exp.params import GraphParams
from tests.conftest import make_correspondences
gp = GraphParams(kernel="quadratic", alpha=0.06, tau=0.1, threshold=0.9)
corr, _ = make_correspondences(n=1500, inlier_ratio=0.3, noise=0.003, seed=5)
rng = np.random.default_rng(6)
a = rng.choice(len(corr), size=203)  # not a multiple of 16, with repeats and rows drawn as their own anchor
inv_q = rng.uniform(100.0, 3000.0, len(a))
sig = core.anchor_signals(corr.src, corr.tgt, gp, a, inv_q)
deg = core.anchor_degree(corr.src, corr.tgt, gp, a)
m = [core.anchors_within(corr.src, corr.tgt, gp, a, 32, b) for b in (1e4, 1e5, 1e6)]
np.savez(sys.argv[1], degree=sig.degree, highpass=sig.highpass, lowpass=sig.lowpass, pilot=deg, m=m)
"""


def test_the_vector_paths_give_the_portable_loops_bits(tmp_path):
    """The quadratic kernel's AVX-512 rows (fused distances and sums, compressed rows) against the portable
    loops (FASTMAC_ANCHORS=generic, read once a process): the same bits. On a CPU without AVX-512 both runs
    take the portable loops."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = {}
    for mode in ("auto", "generic"):
        env = {k: v for k, v in os.environ.items() if k != "FASTMAC_ANCHORS"}
        if mode == "generic":
            env["FASTMAC_ANCHORS"] = "generic"
        path = tmp_path / f"{mode}.npz"
        subprocess.run([sys.executable, "-c", _PORTABLE_CHILD, str(path)], check=True, cwd=repo, env=env)
        out[mode] = dict(np.load(path))
    for key, value in out["auto"].items():
        np.testing.assert_array_equal(value, out["generic"][key], err_msg=key)
    assert out["auto"]["pilot"].max() > 0 and np.isfinite(out["auto"]["highpass"]).all()


def test_anchor_degree_counts_weights_to_the_anchors():
    corr, _ = make_correspondences(n=200, inlier_ratio=0.5, noise=0.003, seed=7)
    w = dense_w(corr, GP)
    a = np.array([0, 5, 5, 17, 199])
    np.testing.assert_allclose(core.anchor_degree(corr.src, corr.tgt, GP, a), w[:, a].sum(1), rtol=1e-5)


def test_pair_budget_takes_a_prefix_of_the_draws():
    corr, _ = make_correspondences(n=2000, inlier_ratio=0.5, noise=0.003, seed=8)
    a = np.random.default_rng(0).choice(len(corr), size=512)
    assert core.anchors_within(corr.src, corr.tgt, GP, a, 32, 1e12) == 512
    assert core.anchors_within(corr.src, corr.tgt, GP, a, 32, 1.0) == 32  # the floor, whatever the budget
    mid = core.anchors_within(corr.src, corr.tgt, GP, a, 32, 2e5)
    assert mid in (32, 64, 128, 256)


def test_pair_budget_keeps_the_longest_prefix_within_it_for_any_thread_count():
    """The screen stops a block once the rows screened so far are over the budget (the counts only grow):
    the prefix kept is still exactly the longest one within it, for 1 to 3 threads. Budgets between two
    prefixes' pair work (numpy's count of compatible anchors per node), far from either."""
    corr, _ = make_correspondences(n=3000, inlier_ratio=0.5, noise=0.003, seed=9)
    a = np.random.default_rng(1).choice(len(corr), size=512)
    w = dense_w(corr, GP)
    sizes = (32, 64, 128, 256, 512)
    work = []
    for size in sizes:
        cnt = (w[:, a[:size]] > 0).sum(1)
        work.append(0.5 * float((cnt.astype(float) ** 2).sum()))
    assert all(b > 2 * x for x, b in zip(work, work[1:])), work  # prefixes far apart: no knife edge
    for k in range(1, len(sizes) - 1):
        budget = float(np.sqrt(work[k] * work[k + 1]))
        for nt in (1, 2, 3):
            got = core.anchors_within(corr.src, corr.tgt, GP, a, 32, budget, num_threads=nt)
            assert got == sizes[k], (budget, nt, got, work)


def outdoor(n: int, inliers: float, seed: int = 1):
    """bench_core's outdoor-like scene: a 60 x 60 x 4 m box, 0.1 m noise, KITTI's FPFH kernel."""
    from fastmac_exp.datasets.planted import OUTDOOR_ROOM, planted

    return planted(n, inlier_ratio=inliers, noise=0.1, seed=seed, room=OUTDOOR_ROOM)[0]


def kept_inlier_ratio(sampler, corr, gp, seeds, ratio=0.05, family="kitti"):
    return np.mean(
        [
            corr.labels[sampler.sample(corr, ratio, gp, family, np.random.default_rng(s)).indices].mean()
            for s in seeds
        ]
    )


def test_estimate_samples_as_well_as_exact_on_a_dense_graph():
    corr = outdoor(6000, 0.1)
    gp = mac_params_for("kitti", "fpfh").graph
    exact = kept_inlier_ratio(GraphFilterSampler(scores="exact"), corr, gp, range(4))
    est = kept_inlier_ratio(GraphFilterSampler(scores="estimate"), corr, gp, range(4))
    assert exact > 0.5  # the filter works here (10 % inliers in)
    assert est > exact - 0.1, (est, exact)
    random = kept_inlier_ratio(RandomSampler(), corr, gp, range(4))
    assert est > 3 * random


def test_estimate_finds_the_inliers_without_the_graph_at_scale():
    corr = outdoor(100_000, 0.02)
    gp = mac_params_for("kitti", "fpfh").graph
    sampler = GraphFilterSampler(scores="estimate")
    res = sampler.sample(corr, 0.05, gp, "kitti", np.random.default_rng(0), samples=2000)
    assert len(res.indices) == 2000 and res.scores_used == "estimate" and res.anchors >= 32
    assert corr.labels[res.indices].mean() > 0.2  # 10x the input's 2 %


def test_auto_keeps_the_exact_sample_where_exact_is_cheap():
    corr, _ = make_correspondences(n=EXACT_BELOW + 500, inlier_ratio=0.05, noise=0.003, seed=9)
    gp = mac_params_for("3dmatch", "fpfh").graph
    mode, _ = choose_scores(corr.src, corr.tgt, gp, EstimateParams(), np.random.default_rng(0))
    assert mode == "exact"
    auto = GraphFilterSampler(scores="auto").sample(corr, 0.2, gp, "3dmatch", np.random.default_rng(3))
    exact = GraphFilterSampler(scores="exact").sample(corr, 0.2, gp, "3dmatch", np.random.default_rng(3))
    assert auto.scores_used == "exact" and auto.anchors == 0
    np.testing.assert_array_equal(auto.indices, exact.indices)


def test_auto_estimates_a_dense_graph():
    corr = outdoor(5000, 0.2)
    gp = mac_params_for("kitti", "fpfh").graph
    res = GraphFilterSampler(scores="auto").sample(corr, 0.2, gp, "kitti", np.random.default_rng(0))
    assert res.scores_used == "estimate"


def test_estimate_is_reproducible_from_the_seed():
    corr = outdoor(8000, 0.05)
    gp = mac_params_for("kitti", "fpfh").graph
    s = GraphFilterSampler(scores="estimate")
    a = s.sample(corr, 0.1, gp, "kitti", np.random.default_rng(11)).indices
    b = s.sample(corr, 0.1, gp, "kitti", np.random.default_rng(11)).indices
    c = s.sample(corr, 0.1, gp, "kitti", np.random.default_rng(12)).indices
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_estimate_lowpass_and_allpass_follow_the_exact_ones():
    corr = outdoor(5000, 0.2)
    gp = mac_params_for("kitti", "fpfh").graph
    exact = core.graph_signals(corr.src, corr.tgt, gp)
    est = estimate_signals(corr.src, corr.tgt, gp, np.random.default_rng(0))
    inl = corr.labels
    # the inliers' (the ones the draw favours): degree and low-pass within 25 % on the median; the
    # high-pass, a difference of two such terms, is noisier (docs/estimated_scores.md) but ranks alike
    for name, bound in (("degree", 0.25), ("lowpass", 0.25), ("highpass", 1.0)):
        e, x = np.abs(getattr(est, name)), np.abs(getattr(exact, name))
        assert np.median(np.abs(e[inl] - x[inl]) / x[inl]) < bound, name
    assert spearmanr(np.abs(est.highpass), np.abs(exact.highpass))[0] > 0.5


def test_bad_settings_are_refused():
    with pytest.raises(InputError, match="sampler.scores"):
        GraphFilterSampler(scores="approx")
    with pytest.raises(InputError, match="min_anchors"):
        GraphFilterSampler(estimate={"anchors": 16, "min_anchors": 32})
    with pytest.raises(InputError, match="sampler.estimate"):
        GraphFilterSampler(estimate={"anchor": 16})
    with pytest.raises(InputError, match="self_loops"):
        GraphFilterSampler(scores="estimate", self_loops=False).sample(
            *make_correspondences(n=3000, seed=1)[:1], 0.1, GP, "3dmatch", np.random.default_rng(0)
        )
    with pytest.raises(InputError, match="samples"):
        count_from_samples(100, 2)
    with pytest.raises(InputError, match="samples"):
        count_from_samples(100, 10.5)


def test_samples_is_a_count_beside_ratio():
    corr, _ = make_correspondences(n=400, seed=2)
    s = RandomSampler().sample(corr, 0.5, GP, "3dmatch", np.random.default_rng(0), samples=50)
    assert len(s.indices) == 50 and s.ratio == pytest.approx(50 / 400)
    s = RandomSampler().sample(corr, 0.5, GP, "3dmatch", np.random.default_rng(0), samples=5000)
    assert len(s.indices) == 400 and s.ratio == 1.0  # at most everything
    s = NoSampler().sample(corr, 0.5, GP, "3dmatch", np.random.default_rng(0), samples=50)
    assert len(s.indices) == 400


def test_object_pairs_sample_on_their_own_rescaled_resolution():
    """Issue 29, item 5: the bunny's sampling graph at 0.006 m linked nearly every pair (1.4 s a pair)."""
    from fastmac_exp.backends.python_mac import PythonBackend
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.oracle import OracleDescriptor
    from fastmac_exp.families import FIXED_RESOLUTION
    from fastmac_exp.pipeline import run_pair
    from fastmac_exp.types import Pair

    rules = SharedRealPairs.rules({"category": "object"})
    assert rules["sampler_resolution"] == pytest.approx(FIXED_RESOLUTION / 25)
    assert SharedRealPairs.rules({"category": "indoor"}).get("sampler_resolution", FIXED_RESOLUTION) == (
        FIXED_RESOLUTION
    )

    seen = []

    class Spy(RandomSampler):
        def sample(self, corr, ratio, gp, family, rng, samples=None):
            seen.append(gp)
            return super().sample(corr, ratio, gp, family, rng, samples=samples)

    corr, gt = make_correspondences(n=200, inlier_ratio=0.5, noise=0.001, seed=4)
    pair = Pair(name="obj", gt=gt, correspondences=corr, **{k: v for k, v in rules.items()})
    run_pair(pair, OracleDescriptor(), Spy(), PythonBackend(), 0.5, np.random.default_rng(0))
    assert seen[0].alpha == pytest.approx(10 * FIXED_RESOLUTION / 25)  # alpha = 10 res (Gaussian kernel)


ESTIMATE_SETUP = """
import numpy as np
from fastmac_exp.graph.estimate import estimate_signals
from fastmac_exp.params import mac_params_for
from tests.test_estimated_scores import outdoor
corr = outdoor(1_000_000, 0.05)
gp = mac_params_for("kitti", "fpfh").graph
t0 = time.process_time()
estimate_signals(corr.src, corr.tgt, gp, np.random.default_rng(0))
one_call_cpu = time.process_time() - t0
"""
ESTIMATE_LOOP = """
    for s in range(1, 100):  # minutes in all: the signal lands inside one of the calls
        estimate_signals(corr.src, corr.tgt, gp, np.random.default_rng(s))
"""


@pytest.mark.signals
def test_ctrl_c_stops_the_estimate():
    import os

    from tests.children import interrupt_child

    if os.name != "posix":
        pytest.skip("sends SIGINT")
    rc, word, after_cpu, one_call = interrupt_child(ESTIMATE_SETUP, ESTIMATE_LOOP)
    assert rc == 130 and word == "interrupted"
    # half a call's CPU time in: a core that ignored the signal would spend the other half first
    assert after_cpu < one_call / 4, f"{after_cpu:.2f} CPU s to stop, one call {one_call:.2f} s"
