"""The per-family rules, one record each, against the spec's tables (sections 2.2 and 6)."""

from __future__ import annotations

import dataclasses

import pytest

from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES, FIXED_RESOLUTION, GAUSSIAN, QUADRATIC, family
from fastmac_exp.params import mac_params_for


@pytest.mark.parametrize(
    ("name", "descriptor", "graph", "tau", "success"),
    [
        ("3dmatch", "fpfh", (GAUSSIAN, 0.995), 0.1, (15.0, 0.30)),
        ("3dmatch", "fcgf", (GAUSSIAN, 0.999), 0.1, (15.0, 0.30)),
        ("3dlomatch", "fpfh", (GAUSSIAN, 0.99), 0.1, (15.0, 0.30)),
        ("3dlomatch", "predator", (QUADRATIC, 0.999), 0.1, (15.0, 0.30)),
        ("kitti", "fpfh", (QUADRATIC, 0.9), 0.6, (5.0, 0.60)),
        ("kitti", "fcgf", (QUADRATIC, 0.999), 0.6, (5.0, 0.60)),  # no entry: the family default
    ],
)
def test_family_rules_match_the_spec(name, descriptor, graph, tau, success):
    fam = family(name)
    assert fam.graph(descriptor) == graph
    assert fam.inlier_threshold == tau and (fam.re_thresh_deg, fam.te_thresh_m) == success
    params = mac_params_for(name, descriptor, resolution=0.01)
    assert (params.graph.kernel, params.graph.threshold) == graph
    assert params.graph.alpha == pytest.approx(0.1) and params.graph.tau == tau
    assert params.inlier_threshold == tau and params.min_clique_size == fam.min_clique_size


def test_family_records_are_frozen_and_unknown_names_are_refused():
    fam = FAMILIES["3dmatch"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        fam.voxel_size = 1.0
    with pytest.raises(TypeError):
        fam.graph_by_descriptor["fpfh"] = (GAUSSIAN, 0.5)
    with pytest.raises(InputError, match="3dmatch, 3dlomatch, kitti"):
        family("kiti")
    assert FIXED_RESOLUTION == 0.006
    assert {f.kind for f in FAMILIES.values()} == {"indoor", "outdoor"}
    assert sorted(f.code for f in FAMILIES.values()) == [1, 2, 3]  # the synthetic data's seeds


def test_every_dataset_takes_its_rules_from_the_record(tmp_path):
    """The user-pairs and shared-real datasets stamp pairs with the family record's values."""
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    for category, name in (("indoor", "3dmatch"), ("outdoor", "kitti")):
        rules = SharedRealPairs.rules({"id": "x", "category": category, "dataset": "3DMatch"})
        fam = FAMILIES[name]
        assert rules == {"family": name, "voxel_size": fam.voxel_size, **fam.thresholds()}
