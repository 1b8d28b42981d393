"""register() composes a configuration once per set of options (issue 50 item 5), and a kept one never
carries one call's options into another's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf.errors import ReadonlyConfigError

import fastmac_exp
from fastmac_exp import plans
from fastmac_exp.plans import options_key, plan_for
from tests.conftest import make_correspondences

PICKS = {"sampler": "highpass", "backend": "cpp"}


def test_the_same_options_give_the_kept_plan_and_its_config_is_read_only():
    a = plan_for(PICKS, {"scores": "exact"}, 0)
    assert plan_for(dict(PICKS), {"scores": "exact"}, 0) is a
    assert a.part("sampler") is a.part("sampler")  # built once
    with pytest.raises(ReadonlyConfigError):
        a.cfg.sampler.scores = "estimate"
    assert plan_for(PICKS, {"scores": "exact"}, 1) is not a  # another seed, another plan


def test_one_calls_options_do_not_reach_another_call():
    exact = plan_for(PICKS, {"scores": "exact", "keep": {"min_keep": 77}}, 0)
    plain = plan_for(PICKS, {}, 0)
    assert plain is not exact
    assert plain.cfg.sampler.scores == "auto" and plain.cfg.sampler.keep.min_keep != 77
    assert plain.part("sampler").score_mode == "auto"
    assert exact.cfg.sampler.scores == "exact" and exact.cfg.sampler.keep.min_keep == 77


def test_a_later_change_to_the_callers_dict_does_not_reach_the_kept_plan():
    estimate = {"anchors": 64}
    first = plan_for(PICKS, {"estimate": estimate}, 0)
    estimate["anchors"] = 128
    second = plan_for(PICKS, {"estimate": estimate}, 0)
    assert first.cfg.sampler.estimate.anchors == 64 and second.cfg.sampler.estimate.anchors == 128
    assert plan_for(PICKS, {"estimate": {"anchors": 64}}, 0) is first


def test_keys_tell_apart_what_a_config_tells_apart():
    keys = [options_key(v) for v in (1, 1.0, True, "1", None, [1], {"a": 1}, {"a": 1.0})]
    assert len(set(keys)) == len(keys)
    assert options_key({"a": 1, "b": [2]}) == options_key({"b": (2,), "a": 1})
    with pytest.raises(TypeError):
        options_key(object())


def test_an_option_without_a_key_is_composed_for_its_call_alone():
    model = Path("models/fcgf_lite.onnx")  # a value OmegaConf takes that has no key here: not kept
    picks = {"descriptor": "fcgf_lite"}
    a = plan_for(picks, {"model": model}, 0)
    assert a is not plan_for(picks, {"model": model}, 0) and a.cfg.descriptor.model == model


def test_register_in_a_loop_gives_each_call_its_own_options():
    corr, _ = make_correspondences(n=400, inlier_ratio=0.2, seed=5)
    plans._kept.cache_clear()
    base = fastmac_exp.register(corr, escalate="off", ratio=0.5)
    wide = fastmac_exp.register(corr, escalate="off", ratio=0.5, inlier_threshold=50.0)
    again = fastmac_exp.register(corr, escalate="off", ratio=0.5)  # the kept plan of the first call
    assert wide.inliers == len(corr) and base.inliers < len(corr)
    assert again.inliers == base.inliers and np.array_equal(again.pose, base.pose)
    assert plans._kept.cache_info().hits >= 1
