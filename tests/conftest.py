"""Shared fixtures: small correspondence sets with a known pose, a tiny in-memory dataset."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from fastmac_exp.geometry.transforms import random_rotation
from fastmac_exp.types import Correspondences, Pair

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _no_described_clouds_from_other_tests():
    """BUFFER and SpinNet keep described clouds process-wide: a test that counts descriptions starts cold."""
    buffer = sys.modules.get("fastmac_exp.descriptors.buffer")
    if buffer is not None:
        buffer.forget_described_clouds()


def make_correspondences(
    n: int = 500, inlier_ratio: float = 0.1, noise: float = 0.002, seed: int = 0, extent: float = 3.0
) -> tuple[Correspondences, np.ndarray]:
    """n correspondences in a room-sized box: round(n*ratio) inliers with Gaussian noise, the rest random."""
    rng = np.random.default_rng(seed)
    gt = np.eye(4)
    gt[:3, :3] = random_rotation(rng)
    gt[:3, 3] = rng.uniform(-1, 1, 3)
    src = rng.uniform(0, extent, (n, 3))
    tgt = src @ gt[:3, :3].T + gt[:3, 3]
    n_in = int(round(n * inlier_ratio))
    tgt[:n_in] += rng.normal(scale=noise, size=(n_in, 3))
    tgt[n_in:] = rng.uniform(0, extent, (n - n_in, 3)) @ gt[:3, :3].T + gt[:3, 3]
    perm = rng.permutation(n)
    labels = np.zeros(n, bool)
    labels[:n_in] = True
    return Correspondences(src[perm], tgt[perm], labels=labels[perm]), gt


class ListDataset:
    """A dataset of precomputed correspondence pairs held in memory (for loop tests)."""

    name = "list"

    def __init__(
        self, num_pairs: int = 4, n: int = 300, inlier_ratio: float = 0.2, bad: tuple[int, ...] = ()
    ):
        self.num_pairs, self.n, self.inlier_ratio, self.bad = num_pairs, n, inlier_ratio, set(bad)

    def names(self) -> list[str]:
        return [f"pair_{i:03d}" for i in range(self.num_pairs)]

    def __len__(self) -> int:
        return self.num_pairs

    def load(self, index: int) -> Pair:
        corr, gt = make_correspondences(self.n, self.inlier_ratio, seed=index)
        if index in self.bad:
            corr.src[5, 1] = np.nan
        return Pair(name=self.names()[index], gt=gt, correspondences=corr, family="3dmatch")


@pytest.fixture
def corr_95_outliers():
    return make_correspondences(n=600, inlier_ratio=0.05, noise=0.002, seed=3)


@pytest.fixture(autouse=True)
def _own_data_home(tmp_path_factory, monkeypatch):
    """No test reads or writes the user's data home (dataset=3dmatch|3dlomatch|kitti look there)."""
    monkeypatch.setenv("FASTMAC_DATA", str(tmp_path_factory.getbasetemp() / "empty-data-home"))
    monkeypatch.delenv("FASTMAC_DATA_SOURCES", raising=False)
