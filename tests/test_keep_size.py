"""samples=auto (docs/keep_size.md): the estimated dense core, the keep that covers it, the config keys."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from fastmac_exp.backends.product_bound import densest_within
from fastmac_exp.datasets.planted import planted
from fastmac_exp.errors import InputError
from fastmac_exp.params import mac_params_for
from fastmac_exp.run.checks import check_run_keys, run_ratio, run_samples
from fastmac_exp.samplers import GraphFilterSampler, RandomSampler, draw_proportional
from fastmac_exp.samplers.keep_size import (
    KeepParams,
    auto_keep,
    dense_core,
    expected_inclusion,
    keep_covering,
)


def test_dense_core_of_planted_cliques_is_the_largest_consistent_group():
    # generalized degrees of disjoint all-ones cliques with self-loops: s = m^2 for a clique of m
    sizes = [60, 10, 5, 1, 1, 1]
    degree = np.concatenate([np.full(m, float(m * m)) for m in sizes])
    core = dense_core(degree, share=0.5)
    assert core.sum() == 60 and core[:60].all()
    # share 1/8: r / share = 8 sqrt(s - 1) ~ 80 for the ten, so they join (80 >= 70 = 60 + 10)
    assert dense_core(degree, share=1 / 8).sum() == 70
    assert dense_core(np.ones(50)).sum() == 0  # no edge at all: no core


def test_keep_covering_with_equal_scores_is_the_uniform_fraction():
    # equal scores: every node is kept with the same probability, so covering T of m core nodes needs
    # k = N T / m; the rule's Poisson approximation gives exactly that
    n, m, target = 10_000, 2_000, 200
    members = np.zeros(n, bool)
    members[:m] = True
    k = keep_covering(np.ones(n), members, target)
    assert abs(k - n * target / m) <= 1
    assert keep_covering(np.ones(n), members, m + 1) is None  # more than the members: no keep does


def test_keep_covering_matches_the_draws_it_predicts():
    # unequal scores (the core scored 20x higher): the predicted keep holds ~target core members in the
    # Gumbel-top-k draws themselves (mean over 400 draws; the approximation is Rosen's, error < 5 %)
    rng = np.random.default_rng(3)
    n, m, target = 5_000, 400, 150
    scores = rng.uniform(0.5, 1.5, n)
    scores[:m] *= 20
    members = np.zeros(n, bool)
    members[:m] = True
    k = keep_covering(scores, members, target)
    held = [members[draw_proportional(scores, k, np.random.default_rng(s))[0]].sum() for s in range(400)]
    assert abs(np.mean(held) - target) < 0.05 * target
    # and the expected inclusion it solved for sums to k over all nodes (lambda monotone)
    assert expected_inclusion(np.array([0.0, 1.0]), 2.0)[0] == 0.0


def _degrees(core_size: int, n: int) -> np.ndarray:
    return np.r_[np.full(core_size, float(core_size) ** 2), np.ones(n - core_size)]


def test_auto_keep_plentiful_small_scarce_large():
    kp = KeepParams()
    n = 20_000
    scores = np.ones(n)
    k, core = auto_keep(scores, _degrees(4_000, n), kp)
    assert core == 4_000 and abs(k - n * kp.core_inliers / 4_000) <= 1  # 1,000 (over min_keep)
    k, core = auto_keep(scores, _degrees(50, n), kp)
    assert core == 50 and k >= n * kp.scarce_ratio * kp.core_inliers / 50  # 80 % of N at least
    k, core = auto_keep(scores, _degrees(35, n), kp)
    assert k == n  # a core under scarce_ratio * core_inliers: every node (plain MAC)
    assert auto_keep(np.ones(300), _degrees(100, 300), kp)[0] == 300  # N under min_keep


def test_auto_keep_extends_ratio_02_where_scarce():
    # the Gumbel-top-k draw of a larger keep starts with the smaller one's: where auto keeps >= 0.2 N, its
    # keep holds ratio 0.2's keep whole (same stream)
    rng = np.random.default_rng(0)
    scores = rng.uniform(0, 1, 5_000)
    k, _ = auto_keep(scores, _degrees(120, 5_000))
    assert k >= 1_000
    small, _ = draw_proportional(scores, 1_000, np.random.default_rng(9))
    large, _ = draw_proportional(scores, k, np.random.default_rng(9))
    assert np.array_equal(large[:1_000], small)


@pytest.mark.parametrize("bad", [{"core_inliers": 1}, {"min_keep": 2}, {"core_share": 0},
                                 {"scarce_cover": 1.5}, {"scarce_ratio": -1}, {"colour": 1}])  # fmt: skip
def test_keep_params_are_checked(bad):
    with pytest.raises(InputError, match="sampler.keep"):
        GraphFilterSampler(keep=bad)


def test_sampler_auto_draws_the_sized_keep_from_the_same_stream():
    corr, _ = planted(3_000, inlier_ratio=0.3, noise=0.05, seed=2, room=(20.0, 20.0, 4.0))
    gp = mac_params_for("kitti", "fpfh").graph
    s = GraphFilterSampler(scores="exact")
    res = s.sample(corr, "auto", gp, "kitti", np.random.default_rng(5))
    same = s.sample(corr, 0.2, gp, "kitti", np.random.default_rng(5), samples="auto")
    assert np.array_equal(res.indices, same.indices)
    k, core = auto_keep(res.scores, s.signals(corr, gp, np.random.default_rng(5))[0].degree, s.keep)
    assert len(res.indices) == k and res.core == core and res.ratio == k / len(corr)
    assert core > 500 and k < 1_000  # 900 consistent inliers: a small keep
    fixed = s.sample(corr, 0.2, gp, "kitti", np.random.default_rng(5), samples=k)
    assert np.array_equal(fixed.indices, res.indices)  # the same draw as samples=k
    assert corr.labels[res.indices].mean() > 0.6  # from 0.3: the scores concentrate the inliers


def test_auto_needs_a_scoring_sampler():
    corr, _ = planted(500, seed=1)
    with pytest.raises(InputError, match="samples=auto"):
        RandomSampler().sample(corr, 0.2, mac_params_for("3dmatch", "fpfh").graph, "3dmatch",
                               np.random.default_rng(0), samples="auto")  # fmt: skip


def _cfg(**kw):
    base = {"protocol": "honest", "ratio": 0.2, "samples": None, "seed": 0, "limit": None, "workers": 1}
    return OmegaConf.create({**base, **kw})


def test_run_keys_accept_auto():
    for kw in ({"ratio": "auto"}, {"samples": "auto"}):
        check_run_keys(_cfg(**kw))
        assert run_samples(_cfg(**kw)) == "auto"
    assert np.isnan(run_ratio(_cfg(ratio="auto"))) and run_ratio(_cfg()) == 0.2
    assert run_samples(_cfg(samples=300)) == 300 and run_samples(_cfg()) is None
    with pytest.raises(InputError, match="samples must be null, auto"):
        check_run_keys(_cfg(samples="most"))
    with pytest.raises(InputError, match="ratio must be a number in"):
        check_run_keys(_cfg(ratio="half"))


# ---- MAC bounded before its products (fastmac_exp/backends/product_bound.py) ----------------------------


def test_densest_within_is_the_largest_prefix_in_budget():
    rng = np.random.default_rng(4)
    degree = rng.uniform(0, 400, 700)
    order = np.argsort(-degree, kind="stable")
    for budget in (1e4, 3e5, 2e6, 1e7, 1e12):
        sub = densest_within(degree, budget)

        def work(k):
            return np.sum(np.minimum(degree[order[:k]], k) ** 2)

        k = len(sub)
        assert np.array_equal(sub, np.sort(order[:k]))
        assert k == 700 or (work(k) <= budget or k == 3) and work(k + 1) > budget


def _near_clique(n=1_500, seed=3):
    corr, gt = planted(n, inlier_ratio=0.7, noise=0.05, seed=seed, room=(30.0, 30.0, 4.0))
    return corr, gt, mac_params_for("kitti", "fpfh")


def test_bounded_mac_is_exact_within_budget():
    from dataclasses import replace

    from fastmac_exp.backends.cpp import CppBackend

    corr, _, params = _near_clique()
    exact = CppBackend().register(corr, replace(params, max_product_work=0))
    same = CppBackend().register(corr, params)  # the default budget: this graph is well within it
    assert "product work" not in same.cap_hit
    assert np.array_equal(same.pose, exact.pose) and np.array_equal(same.clique, exact.clique)


def test_bounded_mac_gives_the_exact_pose_on_a_near_clique():
    from dataclasses import replace

    from fastmac_exp.backends.cpp import CppBackend
    from fastmac_exp.backends.product_bound import estimated_degrees, product_work
    from fastmac_exp.geometry.transforms import rotation_error_deg

    for seed in (3, 5):
        corr, gt, params = _near_clique(seed=seed)
        work = product_work(estimated_degrees(corr.src, corr.tgt, params))
        exact = CppBackend().register(corr, replace(params, max_product_work=0))
        bounded = CppBackend().register(corr, replace(params, max_product_work=work / 20))
        assert "product work: MAC on the" in bounded.cap_hit
        k = int(bounded.cap_hit.split("MAC on the ")[1].split()[0])
        assert 3 <= k < len(corr) // 2  # a twentieth of the work: well under half the nodes
        assert len(bounded.kept) == len(corr) and bounded.clique.max() < len(corr)
        assert corr.labels[bounded.clique].mean() == 1.0  # the consensus: inliers only
        assert rotation_error_deg(bounded.pose[:3, :3], exact.pose[:3, :3]) < 0.5
        assert np.linalg.norm(bounded.pose[:3, 3] - exact.pose[:3, 3]) < 0.05
        assert rotation_error_deg(bounded.pose[:3, :3], gt[:3, :3]) < 1.0


def test_product_bound_skips_its_estimate_only_where_it_cannot_pass_the_budget(monkeypatch):
    """The predicted work is at most n (n - 1)^2 (every estimated degree <= n - 1): on the densest input there
    is (every pair compatible) the estimate stays within it, and bounded_subset skips the estimate exactly
    where that bound is within the budget."""
    from dataclasses import replace

    from fastmac_exp import core
    from fastmac_exp.backends import product_bound as pb

    corr, _, params = _near_clique(n=1_200)
    tight = replace(corr, tgt=corr.src.copy())  # every pair consistent: the largest degrees there are
    n = len(corr)
    assert pb.product_work(pb.estimated_degrees(tight.src, tight.tgt, params)) <= n * (n - 1) ** 2
    calls = []
    real = core.anchor_degree
    monkeypatch.setattr(core, "anchor_degree", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert pb.bounded_subset(tight.src, tight.tgt, replace(params, max_product_work=n * (n - 1) ** 2)) is None
    assert not calls  # skipped: it could not have passed
    sub = pb.bounded_subset(tight.src, tight.tgt, replace(params, max_product_work=n * (n - 1) ** 2 / 8))
    assert calls and sub is not None and len(sub) < n  # just past the bound: estimated, and bounded


def test_max_product_work_is_checked():
    with pytest.raises(InputError, match="mac.max_product_work must be >= 0"):
        mac_params_for("kitti", "fpfh", mac_overrides={"max_product_work": -1})
    assert mac_params_for("kitti", "fpfh", mac_overrides={"max_product_work": 0}).max_product_work == 0


def test_cli_run_with_samples_auto_records_the_keep(tmp_path):
    import pandas as pd

    from tests.test_cli import run

    p = run(
        "limit=1", "samples=auto", "dataset.family=kitti", f"cache.dir={tmp_path / 'cache'}", tmp=tmp_path
    )
    assert p.returncode == 0, p.stderr[-2000:]
    row = pd.read_csv(tmp_path / "run" / "results.csv").iloc[0]
    assert row["samples"] == "auto" and row["core"] > 0
    assert row["n_kept"] < row["n_in"] and np.isclose(row["ratio"], row["n_kept"] / row["n_in"])
    bad = run("limit=1", "samples=auto", "sampler=random", tmp=tmp_path / "bad")
    assert bad.returncode != 0 and "samples=auto sizes the keep" in bad.stdout + bad.stderr


def test_register_facade_takes_ratio_auto():
    from fastmac_exp.api import register

    corr, gt = planted(3_000, inlier_ratio=0.3, noise=0.05, seed=2, room=(20.0, 20.0, 4.0))
    res = register(corr, family="kitti", ratio="auto")
    assert res.ok and len(res.kept) < len(corr)
    assert np.linalg.norm(res.pose[:3, 3] - gt[:3, 3]) < 0.3
