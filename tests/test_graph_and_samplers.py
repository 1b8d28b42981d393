"""Graph signals and samplers checked against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from fastmac_exp.errors import InputError
from fastmac_exp.graph import first_order, second_order, signals_from_graph
from fastmac_exp.params import GraphParams, graph_params_for
from fastmac_exp.samplers import (
    FPSSampler,
    GraphFilterSampler,
    NoSampler,
    RandomSampler,
    XYZSampler,
    draw_proportional,
    minmax,
    sample_count,
    xyz_response,
)
from tests.conftest import make_correspondences

# A triangle 0-1-2 with a pendant node 3 hanging off node 2, all weights 1.
HAND_W = sp.csr_matrix(np.array([[0, 1, 1, 0], [1, 0, 1, 0], [1, 1, 0, 1], [0, 0, 1, 0]], dtype=float))


def test_mac_second_order_graph_hand_case():
    g = second_order(HAND_W).toarray()
    # each triangle edge has exactly one common neighbour; the pendant edge 2-3 has none and vanishes
    expected = np.array([[0, 1, 1, 0], [1, 0, 1, 0], [1, 1, 0, 0], [0, 0, 0, 0]], dtype=float)
    np.testing.assert_allclose(g, expected)


def test_fastmac_signals_hand_case():
    # self loops: SOG_ij = W_ij (2 W_ij + common), SOG_ii = 1 + sum_k W_ik^2
    # SOG01 = SOG02 = SOG12 = 3, SOG23 = 2; diag = 3, 3, 4, 2 -> s = 9, 9, 12, 4
    sig = signals_from_graph(HAND_W, self_loops=True)
    np.testing.assert_allclose(sig.degree, [9, 9, 12, 4])
    # f_i = sum_j SOG_ij (s_i - s_j): f0 = 3 (9 - 12) = -9, f2 = 3*3 + 3*3 + 2*8 = 34, f3 = 2 (4 - 12) = -16
    np.testing.assert_allclose(sig.highpass, [-9, -9, 34, -16])
    # l_i = s_i + sum_j SOG_ij s_j / s_i: l0 = 9 + 90/9, l2 = 12 + 110/12, l3 = 4 + 32/4
    np.testing.assert_allclose(sig.lowpass, [19, 19, 12 + 110 / 12, 12])
    assert sig.n_edges == 4


def test_mac_convention_signals_hand_case():
    sig = signals_from_graph(HAND_W, self_loops=False)
    np.testing.assert_allclose(sig.degree, [2, 2, 2, 0])
    np.testing.assert_allclose(sig.highpass, [0, 0, 0, 0])


@pytest.mark.parametrize("kernel", ["gaussian", "quadratic"])
def test_sparse_graph_equals_dense(kernel):
    corr, _ = make_correspondences(n=120, inlier_ratio=0.3, noise=0.003, seed=1)
    gp = GraphParams(kernel=kernel, alpha=0.06, tau=0.1, threshold=0.99)
    w = first_order(corr.src, corr.tgt, gp, block=37).toarray()
    dp = np.linalg.norm(corr.src[:, None] - corr.src[None], axis=2)
    dq = np.linalg.norm(corr.tgt[:, None] - corr.tgt[None], axis=2)
    d = np.abs(dp - dq)
    s = np.exp(-(d**2) / (2 * 0.06**2)) if kernel == "gaussian" else 1 - d**2 / 0.1**2
    dense = np.where(s >= 0.99, s, 0.0)
    np.fill_diagonal(dense, 0.0)
    np.testing.assert_allclose(w, dense, atol=1e-12)
    np.testing.assert_allclose(second_order(sp.csr_matrix(w)).toarray(), dense * (dense @ dense), atol=1e-12)
    # FastMAC's self-loop signals against the dense formula
    wl = dense + np.eye(len(dense))
    sog = wl * (wl @ wl)
    s_deg = sog.sum(1)
    f = (np.diag(s_deg) - sog) @ s_deg
    sig = signals_from_graph(sp.csr_matrix(w), self_loops=True)
    np.testing.assert_allclose(sig.degree, s_deg, rtol=1e-12)
    np.testing.assert_allclose(sig.highpass, f, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(sig.lowpass, s_deg + (sog @ s_deg) / s_deg, rtol=1e-12)


def test_torch_signals_match_numpy():
    pytest.importorskip("torch")
    from fastmac_exp.graph import graph_signals
    from fastmac_exp.graph.torch_graph import graph_signals_torch

    corr, _ = make_correspondences(n=200, inlier_ratio=0.2, noise=0.003, seed=2)
    gp = graph_params_for("3dmatch", "fpfh")
    for loops in (True, False):
        a = graph_signals(corr.src, corr.tgt, gp, self_loops=loops)
        b = graph_signals_torch(corr.src, corr.tgt, gp, self_loops=loops)
        np.testing.assert_allclose(b.degree, a.degree, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(b.highpass, a.highpass, rtol=1e-6, atol=1e-6)
        assert a.n_edges == b.n_edges


@pytest.mark.parametrize(
    ("n", "ratio", "k"), [(1000, 0.2, 200), (1000, 1.0, 1000), (999, 0.05, 49), (10, 0.3, 3)]
)
def test_sample_count(n, ratio, k):
    assert sample_count(n, ratio) == k


@pytest.mark.parametrize("ratio", [0.0, -0.1, 1.5, float("nan"), "0.2"])
def test_impossible_ratio_is_rejected(ratio):
    with pytest.raises(InputError, match="ratio"):
        sample_count(100, ratio)


def test_ratio_too_small_for_a_clique():
    with pytest.raises(InputError, match="fewer than the 3"):
        sample_count(100, 0.01)


def test_draw_is_proportional_and_without_replacement():
    rng = np.random.default_rng(0)
    scores = np.array([0.0, 1.0, 3.0])
    firsts = [draw_proportional(scores, 1, rng)[0][0] for _ in range(4000)]
    frac = np.bincount(firsts, minlength=3) / len(firsts)
    assert frac[0] == 0.0
    assert abs(frac[2] - 0.75) < 0.03
    idx, zero_filled = draw_proportional(scores, 3, rng)
    assert sorted(idx.tolist()) == [0, 1, 2] and zero_filled == 1
    assert idx[-1] == 0  # zero-score nodes come last


def test_zero_score_fill_is_uniform():
    """With 3 positive and 7 zero-score nodes, k = 5 takes the 3 and 2 of the 7, each pair equally often."""
    scores = np.array([0, 2.0, 0, 0, 1.0, 0, 0, 3.0, 0, 0])
    zeros = np.flatnonzero(scores == 0)
    counts = np.zeros(len(scores))
    trials = 7000
    rng = np.random.default_rng(1)
    for _ in range(trials):
        idx, filled = draw_proportional(scores, 5, rng)
        assert filled == 2 and set(idx[:3].tolist()) == {1, 4, 7}
        counts[idx[3:]] += 1
    # each zero-score node is one of the 2 fill-ins with probability 2/7 (binomial sd ~ 0.0054)
    np.testing.assert_allclose(counts[zeros] / trials, 2 / 7, atol=0.025)
    assert counts[zeros].min() > 0.2 * trials


def test_minmax_gives_zero_to_the_minimum():
    np.testing.assert_allclose(minmax(np.array([2.0, 4.0, 3.0])), [0.0, 1.0, 0.5])


def _ctx():
    return graph_params_for("3dmatch", "fpfh"), "3dmatch"


@pytest.mark.parametrize(
    "sampler",
    [
        GraphFilterSampler("highpass", impl="python"),
        GraphFilterSampler("lowpass", impl="python"),
        GraphFilterSampler("allpass", impl="python"),
        XYZSampler("111", impl="python"),
        RandomSampler(),
        FPSSampler(),
    ],
    ids=lambda s: s.name,
)
def test_samplers_return_k_distinct_indices_and_are_seeded(sampler):
    corr, _ = make_correspondences(n=400, inlier_ratio=0.1, seed=4)
    gp, fam = _ctx()
    a = sampler.sample(corr, 0.1, gp, fam, np.random.default_rng(7))
    b = sampler.sample(corr, 0.1, gp, fam, np.random.default_rng(7))
    assert len(a.indices) == 40 and len(set(a.indices.tolist())) == 40
    np.testing.assert_array_equal(a.indices, b.indices)
    assert "sampling" in a.timings


def test_none_sampler_keeps_everything():
    corr, _ = make_correspondences(n=50)
    gp, fam = _ctx()
    assert NoSampler().sample(corr, 0.1, gp, fam, np.random.default_rng(0)).indices.tolist() == list(
        range(50)
    )


def test_highpass_prefers_inliers_over_random():
    """On a FastMAC-style graph the high-pass score concentrates on the consistent (inlier) cluster."""
    corr, _ = make_correspondences(n=1000, inlier_ratio=0.05, noise=0.002, seed=5)
    gp, fam = _ctx()
    hp = GraphFilterSampler("highpass", impl="python").sample(corr, 0.1, gp, fam, np.random.default_rng(0))
    rnd = RandomSampler().sample(corr, 0.1, gp, fam, np.random.default_rng(0))
    assert corr.labels[hp.indices].mean() > 3 * corr.labels[rnd.indices].mean()


def test_kitti_scores_are_not_normalised():
    corr, _ = make_correspondences(n=200, inlier_ratio=0.2, seed=6)
    gp = graph_params_for("kitti", "fpfh")
    s = GraphFilterSampler("highpass", impl="python").scores(corr, gp, "kitti", np.random.default_rng(0))
    assert s.max() > 1.0  # raw |f|, as the reference code on KITTI


def test_xyz_response_hand_case():
    # two points 1 m apart, sigma 1: Wx = [[1, e^-1], [e^-1, 1]]; (L X)_0 = (1 + e^-1) x0 - (x0 + e^-1 x1)
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    r = xyz_response(pts, sigma=1.0)
    np.testing.assert_allclose(r, [np.exp(-1), np.exp(-1)])


def test_xyz_code_validation():
    with pytest.raises(InputError, match="three 0/1 digits"):
        XYZSampler("12")


def test_deterministic_sampler_greedy_hand_case():
    from fastmac_exp.samplers.deterministic import greedy_e_optimal

    # rows: e1, e2, (e1+e2)/sqrt2 scaled down; picking e1 then e2 maximises sigma_min of the 2 x 2 block
    v = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5], [0.9, 0.1]])
    assert sorted(greedy_e_optimal(v, 2).tolist()) == [0, 1]


def test_deterministic_sampler_refuses_beyond_caps():
    from fastmac_exp.samplers.deterministic import DeterministicSampler

    corr, _ = make_correspondences(n=300)
    gp, fam = _ctx()
    with pytest.raises(InputError, match="caps"):
        DeterministicSampler(max_n=100).sample(corr, 0.2, gp, fam, np.random.default_rng(0))
    res = DeterministicSampler().sample(corr, 0.05, gp, fam, np.random.default_rng(0))
    assert len(set(res.indices.tolist())) == 15


def test_torch_and_cpp_samplers_draw_the_same_samples():
    corr, _ = make_correspondences(n=500, inlier_ratio=0.1, seed=8)
    gp, fam = _ctx()
    a = GraphFilterSampler(impl="cpp").sample(corr, 0.1, gp, fam, np.random.default_rng(3))
    b = GraphFilterSampler(impl="torch").sample(corr, 0.1, gp, fam, np.random.default_rng(3))
    c = GraphFilterSampler(impl="python").sample(corr, 0.1, gp, fam, np.random.default_rng(3))
    np.testing.assert_allclose(b.scores, a.scores, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(c.scores, a.scores, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.indices, c.indices)


def test_squared_option_squares_the_response():
    corr, _ = make_correspondences(n=300, inlier_ratio=0.2, seed=5)
    gp, fam = _ctx()
    rng = np.random.default_rng(0)
    plain = GraphFilterSampler("highpass", normalize="none").scores(corr, gp, fam, rng)
    sq = GraphFilterSampler("highpass", normalize="none", squared=True).scores(corr, gp, fam, rng)
    np.testing.assert_allclose(sq, plain**2, rtol=1e-12)
    assert (plain > 1).any()  # so that squaring changes the ranking weights, not only the scale


def test_deterministic_band_option():
    from fastmac_exp.samplers.deterministic import DeterministicSampler

    with pytest.raises(InputError, match="band"):
        DeterministicSampler(band="middle")
    corr, _ = make_correspondences(n=200, inlier_ratio=0.3, seed=2)
    gp, fam = _ctx()
    hi = DeterministicSampler(band="high").sample(corr, 0.05, gp, fam, np.random.default_rng(0)).indices
    lo = DeterministicSampler(band="low").sample(corr, 0.05, gp, fam, np.random.default_rng(0)).indices
    assert len(hi) == len(lo) == 10 and set(hi.tolist()) != set(lo.tolist())


def test_sample_result_carries_its_ratio_and_stage_timings():
    """What the pipeline and the timing study read instead of re-deriving: the ratio a sampler used
    (`none` keeps everything) and, for the scoring samplers, preparation and draw times within the total."""
    from fastmac_exp.params import GraphParams
    from fastmac_exp.samplers import make_sampler, ratio_used
    from tests.conftest import make_correspondences

    corr, _ = make_correspondences(300, 0.3, seed=2)
    gp = GraphParams()
    rng = np.random.default_rng(0)
    hp = make_sampler("highpass").sample(corr, 0.2, gp, "3dmatch", rng)
    assert hp.ratio == 0.2 and len(hp.indices) == 60
    assert {"sampling", "sampling_prep", "sampling_draw"} <= set(hp.timings)
    assert hp.timings["sampling_prep"] + hp.timings["sampling_draw"] <= hp.timings["sampling"] + 1e-6
    none = make_sampler("none").sample(corr, 0.2, gp, "3dmatch", rng)
    assert none.ratio == 1.0 and len(none.indices) == 300 and ratio_used("none", 0.2) == 1.0
    assert ratio_used("random", 0.2) == 0.2
