"""Every rule that depends on the dataset family, one frozen record per family (spec sections 2.2, 6).

A family says whose rules a pair is judged by: 3DMatch (indoor RGB-D fragments), 3DLoMatch (the same
scenes at 10-30 % overlap) or KITTI (outdoor LiDAR sweeps). Datasets stamp their pairs with these
values, `params.mac_params_for` takes MAC's defaults from here, and the library API (`register`) does
the same, so a family's numbers live in exactly one place.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from fastmac_exp.errors import InputError

GAUSSIAN = "gaussian"
QUADRATIC = "quadratic"

# FastMAC's and the spec's 3DMatch point-cloud resolution (a full-resolution fragment measures ~0.00604):
# the sampler's graph always uses it, and so does MAC where it is not computed from the clouds.
FIXED_RESOLUTION = 0.006


@dataclass(frozen=True)
class Family:
    """One family's rules. Graph entries are (kernel, threshold) of MAC's first-order graph (spec 2.2)."""

    name: str
    kind: (
        str  # "indoor" (depth camera fragments) or "outdoor" (LiDAR sweeps): what the synthetic set simulates
    )
    code: int  # part of the synthetic family's random streams: changing it changes the generated data
    voxel_size: float  # the descriptor's voxel (m)
    inlier_threshold: float  # MAC's tau (hypothesis score, refinement) and the GT inlier label distance (m)
    re_thresh_deg: float  # success: rotation error below this ...
    te_thresh_m: float  # ... and translation error below this
    min_clique_size: int  # 4 for KITTI in igraph>=0.10 builds of the reference code (spec 9.5)
    graph_default: tuple[str, float]  # descriptors without an entry of their own
    graph_by_descriptor: MappingProxyType  # descriptor graph key -> (kernel, threshold)
    resolution_from_clouds: bool  # MAC computes the resolution from the two clouds (else FIXED_RESOLUTION)
    sampler_normalize: str  # the reference code's high-pass score normalisation: "minmax" or "none"
    up_axis: str  # the sensor frame's up direction, for viewers: "-y" (camera frames) or "+z" (LiDAR)
    buffer_model: str  # which published weights (BUFFER, SpinNet: 3dmatch | kitti) fit this data
    # TurboReg's defaults (backend=turboreg): max_N, tau_length_consis, num_pivot (K1), radiu_nms, tau_inlier,
    # from TurboReg's README (3DMatch + FPFH) and its demo script demo_py/o3d_fpfh.py (KITTI-like)
    turboreg: tuple[int, float, int, float, float] = (7000, 0.012, 2000, 0.15, 0.1)

    def graph(self, descriptor: str) -> tuple[str, float]:
        return self.graph_by_descriptor.get(descriptor, self.graph_default)

    def thresholds(self) -> dict[str, Any]:
        """The Pair fields every dataset of this family sets the same way (besides `family` itself)."""
        return {
            "inlier_threshold": self.inlier_threshold,
            "re_thresh_deg": self.re_thresh_deg,
            "te_thresh_m": self.te_thresh_m,
        }


def _table(**entries: tuple[str, float]) -> MappingProxyType:
    return MappingProxyType(dict(entries))


_INDOOR = dict(kind="indoor", voxel_size=0.05, inlier_threshold=0.1, re_thresh_deg=15.0, te_thresh_m=0.30,
               min_clique_size=3, resolution_from_clouds=True, sampler_normalize="minmax", up_axis="-y",
               buffer_model="3dmatch")  # fmt: skip

FAMILIES: dict[str, Family] = {
    "3dmatch": Family(
        name="3dmatch", code=1, graph_default=(GAUSSIAN, 0.995),
        graph_by_descriptor=_table(fcgf=(GAUSSIAN, 0.999), fpfh=(GAUSSIAN, 0.995), spinnet=(GAUSSIAN, 0.85),
                                   d3feat=(GAUSSIAN, 0.85), predator=(QUADRATIC, 0.999)),
        **_INDOOR,
    ),
    "3dlomatch": Family(
        name="3dlomatch", code=2, graph_default=(GAUSSIAN, 0.99),
        graph_by_descriptor=_table(fcgf=(GAUSSIAN, 0.99), fpfh=(GAUSSIAN, 0.99), spinnet=(GAUSSIAN, 0.85),
                                   d3feat=(GAUSSIAN, 0.85), predator=(QUADRATIC, 0.999)),
        **_INDOOR,
    ),
    "kitti": Family(
        name="kitti", kind="outdoor", code=3, voxel_size=0.3, inlier_threshold=0.6, re_thresh_deg=5.0,
        te_thresh_m=0.60, min_clique_size=3, graph_default=(QUADRATIC, 0.999),
        graph_by_descriptor=_table(fpfh=(QUADRATIC, 0.9)), resolution_from_clouds=False,
        sampler_normalize="none", up_axis="+z", buffer_model="kitti", turboreg=(6000, 0.1, 2500, 0.15, 0.4),
    ),
}  # fmt: skip


def family(name: str) -> Family:
    """The family record; an unknown name is an InputError that lists the known ones."""
    try:
        return FAMILIES[name]
    except (KeyError, TypeError):
        raise InputError(f"unknown dataset family {name!r}; expected one of {', '.join(FAMILIES)}") from None


def check_family(name: str) -> str:
    return family(name).name
