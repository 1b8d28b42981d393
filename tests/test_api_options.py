"""The library facade reaches every option of the config groups by the CLI's names (issue 42, item 1)."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from omegaconf import OmegaConf

import fastmac_exp
from fastmac_exp.errors import InputError
from fastmac_exp.options import choices, compose_run, option_names
from fastmac_exp.resources import config_dir
from tests.conftest import make_correspondences


@pytest.fixture(scope="module")
def corr_gt():
    return make_correspondences(n=600, inlier_ratio=0.15, seed=3)


def test_register_takes_a_sample_count(corr_gt):
    corr, gt = corr_gt
    res = fastmac_exp.register(corr, samples=150)
    assert len(res.kept) == 150 and np.allclose(res.pose, gt, atol=0.05)


def test_register_passes_the_samplers_options_through(corr_gt):
    corr, gt = corr_gt
    assert np.allclose(fastmac_exp.register(corr, scores="exact").pose, gt, atol=0.05)
    with pytest.raises(InputError, match="sampler.scores must be one of"):
        fastmac_exp.register(corr, scores="nosuch")
    with pytest.raises(InputError, match="unknown option 'sampler.estimate.nosuch'"):
        fastmac_exp.register(corr, estimate={"nosuch": 1})


@pytest.mark.parametrize("backend", ["turboreg", "ransac", "fgr", "python", "cpp"])
def test_register_runs_every_backend_the_cli_offers(corr_gt, backend):
    corr, gt = corr_gt
    res = fastmac_exp.register(corr, backend=backend, ratio=1.0, sampler="none")
    assert res.ok and np.allclose(res.pose, gt, atol=0.1)


def test_register_reaches_a_backends_option_and_asks_to_qualify_a_shared_name(corr_gt):
    corr, _ = corr_gt
    with pytest.raises(InputError, match="turboreg num_pivot must be >= 1"):
        fastmac_exp.register(corr, backend="turboreg", num_pivot=0)
    with pytest.raises(InputError, match=r"'tau' is an option of several parts.*'backend.tau'.*'graph.tau'"):
        fastmac_exp.register(corr, backend="turboreg", tau=0.1)
    with pytest.raises(InputError, match="turboreg tau must be positive"):
        fastmac_exp.register(corr, backend="turboreg", **{"backend.tau": -1.0})
    with pytest.raises(InputError, match="unknown option 'num_pivots'; did you mean 'num_pivot'"):
        fastmac_exp.register(corr, backend="turboreg", num_pivots=3)
    with pytest.raises(InputError, match="unknown backend 'turboregg'; did you mean 'turboreg'"):
        fastmac_exp.register(corr, backend="turboregg")


def test_every_group_option_is_documented_in_the_docstring():
    """The registry is conf/: each key a sampler or backend file offers is reachable and documented."""
    doc = inspect.getdoc(fastmac_exp.register)
    for group in ("sampler", "backend"):
        for option in choices(group):
            assert option in doc, f"{group}={option} missing from register's docstring"
            cfg = compose_run({group: option})
            node = OmegaConf.to_container(cfg[group])
            names = option_names(cfg, (group,))
            for key in node:
                if key.startswith("_"):
                    continue
                assert f"{group}.{key}" in names[key], (group, option, key)
                assert key in doc, f"{group}={option}'s option {key!r} missing from register's docstring"
    for key in OmegaConf.to_container(compose_run({}).mac):
        assert key in doc
    assert sorted(choices("backend")) == sorted(p.stem for p in (config_dir() / "backend").glob("*.yaml"))


def test_a_right_pose_is_trusted_and_one_of_unrelated_clouds_is_not():
    """Issue 42 item 2: the GT-free check (geometry.trust) on correspondences with 10 % inliers and on
    two unrelated random clouds (a pose with about its clique's support)."""
    good, gt = make_correspondences(n=1000, inlier_ratio=0.1, seed=1)
    res = fastmac_exp.register(good, ratio=0.2)
    assert res.trusted and res.confidence > 0.999 and np.allclose(res.pose, gt, atol=0.05)
    rng = np.random.default_rng(0)
    unrelated = fastmac_exp.register(rng.uniform(0, 3, (20000, 3)), rng.uniform(0, 3, (20000, 3)))
    assert unrelated.ok and not unrelated.trusted and unrelated.confidence < 0.5


def test_a_pose_that_explains_only_its_clique_is_not_trusted():
    from fastmac_exp.geometry.trust import assess

    rng = np.random.default_rng(0)
    src = rng.uniform(0, 10, (2000, 3))
    tgt = rng.uniform(0, 10, (2000, 3))
    # a clique of 8 and 4 more within the threshold: chance's share
    assert not assess(src, tgt, np.eye(4), 0.1, inliers=12, clique=8).trusted
    # 300 of 2000 explained: 15 %, far beyond what chance and structure give
    verdict = assess(src, tgt, np.eye(4), 0.1, inliers=300, clique=8)
    assert verdict.trusted and verdict.confidence > 0.999
    assert not assess(src, tgt, np.full((4, 4), np.nan), 0.1, inliers=300, clique=8).trusted
