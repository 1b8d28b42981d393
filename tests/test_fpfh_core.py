"""The C++ core's FPFH front end against Open3D, its reference, and the exact feature matcher against the
float64 brute force (fastmac_exp/_cpp/fpfh.cpp, feature_match.cpp; docs/fpfh_core.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fastmac_exp import core
from fastmac_exp.descriptors.fpfh import FPFHDescriptor, fpfh_features, match_features
from fastmac_exp.descriptors.matching import correspondences_from_features
from fastmac_exp.errors import InputError
from fastmac_exp.types import Pair

pytestmark = pytest.mark.skipif(not core.available(), reason="C++ core not built")
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def scan(seed: int = 0, n: int = 6000) -> np.ndarray:
    """A small scan-like cloud: a floor, two walls and a box, with noise."""
    rng = np.random.default_rng(seed)
    k = n // 4
    floor = np.c_[rng.uniform(-2, 2, k), rng.uniform(-2, 2, k), rng.normal(0, 0.003, k)]
    wall = np.c_[rng.uniform(-2, 2, k), np.full(k, 2.0) + rng.normal(0, 0.003, k), rng.uniform(0, 1.5, k)]
    side = np.c_[np.full(k, -2.0) + rng.normal(0, 0.003, k), rng.uniform(-2, 2, k), rng.uniform(0, 1.5, k)]
    u = rng.uniform(-0.3, 0.3, (k, 3))
    face = rng.integers(0, 3, k)
    u[np.arange(k), face] = np.sign(rng.normal(size=k)) * 0.3
    return np.vstack([floor, wall, side, u + [0.5, 0.5, 0.3]]) + [0.3, -0.1, 0.2]


def kitti_cloud() -> tuple[np.ndarray, float]:
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    if not (SHARED / "pairs.json").is_file():
        pytest.skip("shared real data absent")
    pair = SharedRealPairs(root=SHARED, ids=["kitti00_95_to_94"]).load(0)
    return pair.src_cloud, pair.voxel_size


def open3d_reference(kp: np.ndarray, voxel: float, orient: str) -> tuple[np.ndarray, np.ndarray]:
    from fastmac_exp._open3d import o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kp))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    if orient == "origin":
        pcd.orient_normals_towards_camera_location(np.zeros(3))
    f = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    )
    return np.asarray(pcd.normals), np.asarray(f.data).T


def _pair_bins(p1, n1, p2, n2, swap):
    """Open3D's three pair features (ComputePairFeatures) with the frame chosen by `swap`, as continuous
    bin positions (11 bins each), for arrays of pairs."""
    d = p2 - p1
    length = np.linalg.norm(d, axis=1, keepdims=True)
    a1 = np.einsum("ij,ij->i", n1, d) / length[:, 0]
    a2 = np.einsum("ij,ij->i", n2, d) / length[:, 0]
    s = swap[:, None]
    u, w2, d = np.where(s, n2, n1), np.where(s, n1, n2), np.where(s, -d, d)
    f2 = np.where(swap, -a2, a1)
    v = np.cross(d, u)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    w = np.cross(u, v)
    f1 = np.einsum("ij,ij->i", v, w2)
    f0 = np.arctan2(np.einsum("ij,ij->i", w, w2), np.einsum("ij,ij->i", u, w2))
    return np.c_[11 * (f0 + np.pi) / (2 * np.pi), 11 * (f1 + 1) * 0.5, 11 * (f2 + 1) * 0.5]


def tie_rows(kp: np.ndarray, normals: np.ndarray, radius: float, max_nn: int) -> np.ndarray:
    """Rows whose FPFH depends on a pair that rounding decides, through the row's own SPFH or a neighbour's:
    the two normals make angles with the line between the points that are equal to 1e-12 (Open3D compares
    their acos to pick the frame) and the bins differ between the two frames, or a feature lies within 1e-9
    of a bin edge (e.g. f0 = atan2(~0, -1) for opposite normals: bin 0 or 10 by the sign of a rounding
    error)."""
    nb = core.core().radius_neighbours(kp, radius, max_nn)
    ptr, idx = nb["ptr"], nb["idx"]
    owner = np.repeat(np.arange(len(kp)), np.diff(ptr))
    first = np.zeros(len(idx), dtype=bool)
    first[ptr[:-1][np.diff(ptr) > 0]] = True  # position 0 is the point itself
    i, j = owner[~first], idx[~first]
    p1, p2, n1, n2 = kp[i], kp[j], normals[i], normals[j]
    d = p2 - p1
    length = np.linalg.norm(d, axis=1)
    gap = np.abs(np.einsum("ij,ij->i", n2, d)) / length - np.abs(np.einsum("ij,ij->i", n1, d)) / length
    with np.errstate(invalid="ignore", divide="ignore"):
        t_keep = _pair_bins(p1, n1, p2, n2, np.zeros(len(i), dtype=bool))
        t_swap = _pair_bins(p1, n1, p2, n2, np.ones(len(i), dtype=bool))
    bins = lambda t: np.clip(np.floor(t), 0, 10)  # noqa: E731
    frame_tie = (np.abs(gap) <= 1e-12) & np.any(bins(t_keep) != bins(t_swap), axis=1)
    t = np.where((gap > 0)[:, None], t_swap, t_keep)
    edge = np.any(np.abs(t - np.round(t)) <= 1e-9, axis=1) | ~np.isfinite(t).all(axis=1)
    bad_spfh = np.zeros(len(kp), dtype=bool)
    bad_spfh[i[frame_tie | edge]] = True
    reach = bad_spfh.copy()
    np.logical_or.at(reach, owner, bad_spfh[idx])
    return reach


# -- keypoints and neighbourhoods ------------------------------------------------------------------------


@pytest.mark.parametrize("voxel", [0.05, 0.13])
def test_voxel_keypoints_are_open3ds_points(voxel):
    from fastmac_exp._open3d import o3d

    pts = scan(1)
    ours = core.core().voxel_downsample(pts, voxel)
    ref = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(voxel).points)
    assert ours.shape == ref.shape
    # the same centroids to the last bit (sums in input order), in another order
    np.testing.assert_array_equal(ours[np.lexsort(ours.T)], ref[np.lexsort(ref.T)])


def _scramble(x: np.ndarray) -> np.ndarray:
    """point_grid.hpp's scramble (splitmix64's finaliser) in numpy."""
    x = x.astype(np.uint64)
    with np.errstate(over="ignore"):
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return x


def test_voxel_keypoints_in_scrambled_voxel_order_and_deterministic():
    pts = scan(2)
    a = core.core().voxel_downsample(pts, 0.1, num_threads=1)
    b = core.core().voxel_downsample(pts, 0.1, num_threads=2)
    np.testing.assert_array_equal(a, b)
    cells = np.floor((a - (pts.min(0) - 0.05)) / 0.1).astype(np.int64)
    keys = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
    assert np.all(_scramble(keys)[1:] > _scramble(keys)[:-1])
    # no spatial run: the first tenth of the keypoints spans (nearly) the whole cloud
    head = a[: len(a) // 10]
    assert np.all(np.ptp(head, axis=0) > 0.8 * np.ptp(a, axis=0))


@pytest.mark.parametrize("loops", ["auto", "generic"])
@pytest.mark.parametrize("max_nn", [5, 30, 1000])
def test_radius_neighbours_are_the_nearest_within_the_radius(monkeypatch, max_nn, loops):
    """Each query's max_nn nearest by (squared distance, index), by the AVX-512 loop and the portable one
    (~36 hits a query: the cap cuts the slices at 5 and 30, and every hit is kept at 1000)."""
    monkeypatch.setenv("FASTMAC_FPFH_LOOPS", loops)
    pts = core.core().voxel_downsample(scan(3), 0.05)
    r = 0.17
    nb = core.core().radius_neighbours(pts, r, max_nn)
    d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
    for q in range(0, len(pts), 7):
        inside = np.flatnonzero(d2[q] < r * r)
        want = inside[np.lexsort((inside, d2[q, inside]))][:max_nn]
        got = nb["idx"][nb["ptr"][q] : nb["ptr"][q + 1]]
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(nb["d2"][nb["ptr"][q] : nb["ptr"][q + 1]], d2[q, want])


# -- normals and FPFH against Open3D ---------------------------------------------------------------------


@pytest.mark.parametrize("orient", ["origin", "open3d"])
def test_normals_and_fpfh_equal_open3d_on_a_scan(orient):
    voxel = 0.05
    kp = core.core().voxel_downsample(scan(4), voxel)
    ref_n, ref_f = open3d_reference(kp, voxel, orient)
    viewpoint = np.zeros(3) if orient == "origin" else None
    n, f = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, viewpoint)
    np.testing.assert_array_equal(n, ref_n)  # the same arithmetic as Open3D's eigensolver
    diff = np.abs(f - ref_f).max(axis=1)
    ties = tie_rows(kp, n, 5 * voxel, 100)
    assert np.all(diff[~ties] < 1e-9)


def test_fpfh_equals_open3d_on_a_real_kitti_scan_but_for_rounding_ties():
    pts, voxel = kitti_cloud()
    kp = core.core().voxel_downsample(pts, voxel)
    ref_n, ref_f = open3d_reference(kp, voxel, "origin")
    n, f = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3))
    np.testing.assert_array_equal(n, ref_n)
    diff = np.abs(f - ref_f).max(axis=1)
    ties = tie_rows(kp, n, 5 * voxel, 100)
    assert np.all(diff[~ties] < 1e-9), np.flatnonzero((diff >= 1e-9) & ~ties)[:10]
    # Open3D's frame choice at a tie follows its compiled arithmetic, not the pair: few rows differ
    assert (diff >= 1e-9).sum() <= 0.005 * len(kp)


def test_fpfh_of_chosen_rows_equals_those_rows_of_all():
    voxel = 0.05
    kp = core.core().voxel_downsample(scan(5), voxel)
    rows = np.sort(np.random.default_rng(0).choice(len(kp), 200, replace=False))
    _, every = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3))
    _, some = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3), rows)
    np.testing.assert_array_equal(some, every[rows])
    _, one_thread = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3), num_threads=1)
    np.testing.assert_array_equal(one_thread, every)


def test_unit_rows_in_the_core_equal_numpys_bit_for_bit():
    # the core divides each FPFH row by its norm as np.linalg.norm sums it (pairwise, eight running sums);
    # a plain sum of the squares differs in the last bit on many rows, and isolated points give zero rows
    voxel = 0.05
    kp = core.core().voxel_downsample(scan(5), voxel)
    kp = np.vstack([kp, [[50.0, 50.0, 50.0], [-50.0, 50.0, 50.0]]])  # no neighbours: zero rows
    _, raw = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3))
    _, unit = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3), normalize=True)
    norm = np.linalg.norm(raw, axis=1, keepdims=True)
    assert (norm[-2:] == 0).all() and (norm[:-2] > 0).all()
    np.testing.assert_array_equal(unit, raw / np.where(norm > 0, norm, 1.0))
    plain = np.sqrt(np.array([sum(float(x) * float(x) for x in row) for row in raw[:-2]]))
    assert (plain != norm[:-2, 0]).any()  # so the test can tell the two sums apart
    for dim in (5, 33, 200, 300):  # under eight terms, one block of eight sums, halves above 128 and 256
        x = np.random.default_rng(dim).normal(size=(700, dim))
        x[3] = 0.0
        norm = np.linalg.norm(x, axis=1, keepdims=True)
        np.testing.assert_array_equal(core.core().unit_rows(x), x / np.where(norm > 0, norm, 1.0))


def test_radius_neighbours_refuse_a_cloud_too_wide_for_the_grid():
    with pytest.raises(ValueError, match="2\\^19 radii"):
        core.core().radius_neighbours(np.array([[0.0, 0, 0], [1e7, 0, 0]]), 0.01, 10)


@pytest.mark.parametrize("case", ["scan", "kitti"])
def test_fpfh_is_the_same_by_the_avx512_and_the_portable_loops(monkeypatch, case):
    """Bit for bit, normals and features: the AVX-512 radius search against the portable loop."""
    if case == "kitti":
        pts, voxel = kitti_cloud()
    else:
        pts, voxel = scan(13, 8000), 0.05
    kp = core.core().voxel_downsample(pts, voxel)
    out = {}
    for loops in ("auto", "generic"):
        monkeypatch.setenv("FASTMAC_FPFH_LOOPS", loops)
        out[loops] = core.core().fpfh_describe(kp, 2 * voxel, 30, 5 * voxel, 100, np.zeros(3))
    np.testing.assert_array_equal(out["auto"][0], out["generic"][0])
    np.testing.assert_array_equal(out["auto"][1], out["generic"][1])
    assert np.count_nonzero(out["auto"][1]) > 0.2 * out["auto"][1].size


def test_fpfh_hand_case_two_points():
    # two points 1 m apart along x with normals z and (0.6, 0, 0.8). Either way the frame is the tilted
    # normal's (|n.d| 0.6 > 0: acos is smaller), so both pairs give f2 = -0.6 (bin 2), v = (0, 1, 0),
    # f1 = v.n = 0 (bin 5), f0 = atan2(0.6, 0.8) (bin 6): each SPFH is 100 in bins 6, 11 + 5, 22 + 2, and each
    # FPFH its SPFH plus the other's, scaled to 100 a third.
    kp = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    normals = np.array([[0.0, 0, 1], [0.6, 0, 0.8]])
    want = np.zeros(33)
    want[[int(np.floor(11 * (np.arctan2(0.6, 0.8) + np.pi) / (2 * np.pi))), 16, 24]] = 200.0
    assert int(np.floor(11 * (np.arctan2(0.6, 0.8) + np.pi) / (2 * np.pi))) == 6
    _, f = core.core().fpfh_describe(kp, 0.5, 30, 2.0, 10, None, normals=normals)
    np.testing.assert_allclose(f, [want, want], atol=1e-12)
    from fastmac_exp._open3d import o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kp))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    ref = o3d.pipelines.registration.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(2.0, 10))
    np.testing.assert_allclose(np.asarray(ref.data).T, f, atol=1e-12)


# -- the matcher --------------------------------------------------------------------------------------------


def _features(seed: int, n: int, dim: int = 33) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = rng.gamma(0.3, 1.0, (n, dim)) * (rng.random((n, dim)) < 0.4)
    norm = np.linalg.norm(f, axis=1, keepdims=True)
    return f / np.where(norm > 0, norm, 1)


@pytest.mark.parametrize("generic", [False, True])
def test_fast_matcher_equals_float64_brute_force(monkeypatch, generic):
    if generic:
        monkeypatch.setenv("FASTMAC_FM", "generic")
    a, b = _features(0, 700), _features(1, 1500)
    # near-ties and exact ties: duplicated targets, a zero row, queries equal to targets
    b[100] = b[7]
    b[200] = 0.0
    a[:20] = b[300:320]
    a[20] = 0.0
    a[21] = b[7]
    ref = core.core().nearest_rows(a, b)
    idx, second, settled = core.core().nearest_rows_fast(a, b)
    np.testing.assert_array_equal(idx, ref)
    assert idx[21] == 7  # the lower of two equal targets
    assert settled >= 2
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    np.testing.assert_allclose(second, np.sort(d2, axis=1)[:, 1], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(core.core().nearest_rows_fast(a, b, num_threads=1)[0], idx)


@pytest.mark.parametrize("prune", ["on", "off"])
@pytest.mark.parametrize(
    "case", ["duplicates", "scaled_up", "scaled_down", "points_3d", "one_column", "wide", "few_rows"]
)
def test_fast_matcher_pruned_tiles_equal_float64_brute_force(monkeypatch, case, prune):
    """The tiles of similar targets that the triangle bound skips never hold the nearest or the runner-up:
    the same indices as the float64 brute force (ties to the lowest index, also across tiles) and the
    runner-up's squared distance in float64, with the bound on and off."""
    monkeypatch.setenv("FASTMAC_FM_PRUNE", prune)
    rng = np.random.default_rng(7)
    if case == "duplicates":  # 60 distinct features, each repeated across the tree's leaves
        base = _features(2, 60)
        b = base[rng.integers(0, 60, 3000)]
        a = np.vstack([base[rng.integers(0, 60, 200)], _features(3, 200)])
    elif case.startswith("scaled"):
        k = 1e4 if case == "scaled_up" else 1e-4
        a, b = k * _features(4, 300), k * _features(5, 2500)
    elif case == "points_3d":
        a, b = rng.normal(size=(400, 3)), rng.normal(size=(5000, 3))
    elif case == "one_column":
        a, b = rng.integers(0, 50, (300, 1)).astype(float), rng.integers(0, 50, (2000, 1)).astype(float)
    elif case == "wide":
        a, b = rng.normal(size=(100, 96)), rng.normal(size=(1500, 96))
    else:
        a, b = _features(6, 33), _features(7, 4000)
    ref = core.core().nearest_rows(a, b)
    idx, second, _ = core.core().nearest_rows_fast(a, b)
    np.testing.assert_array_equal(idx, ref)
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    scale = max(1.0, float((a**2).sum(1).max()), float((b**2).sum(1).max()))
    np.testing.assert_allclose(second, np.sort(d2, axis=1)[:, 1], rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_fast_matcher_refuses_a_non_finite_target(bad):
    a, b = _features(8, 50), _features(9, 2000)
    b[1234, 5] = bad  # a NaN once slipped past the norm's maximum
    with pytest.raises(ValueError, match="row 1234 of b has a non-finite value"):
        core.core().nearest_rows_fast(a, b)


def test_fast_matcher_equals_brute_force_on_real_fpfh():
    pts, voxel = kitti_cloud()
    kp, f = fpfh_features(pts, voxel, impl="core")
    a, b = f[::3], f[1::2]
    np.testing.assert_array_equal(core.core().nearest_rows_fast(a, b)[0], core.core().nearest_rows(a, b))


def test_match_features_mutual_and_ratio_test_by_hand():
    src = np.array([[1.0, 0, 0], [0, 1.0, 0], [0.7, 0.7, 0]])
    tgt = np.array([[0.9, 0.1, 0], [0.0, 0.95, 0.05], [0.71, 0.7, 0.0]])
    si, ti, _ = match_features(src, tgt)
    np.testing.assert_array_equal(ti, [0, 1, 2])
    # nearest / second nearest distance: row 0 0.141 / 0.758 = 0.19, row 1 0.071 / 0.771 = 0.09,
    # row 2 0.01 / 0.745 = 0.013
    si, ti, _ = match_features(src, tgt, ratio_test=0.1)
    np.testing.assert_array_equal(si, [1, 2])
    si, ti, _ = match_features(src, tgt, ratio_test=0.05)
    np.testing.assert_array_equal(si, [2])
    si, _, _ = match_features(src, np.array([[1.0, 0, 0], [0.99, 0.01, 0]]), mutual=True)
    np.testing.assert_array_equal(si, [0])
    with pytest.raises(InputError, match="ratio_test"):
        match_features(src, tgt, ratio_test=1.5)


# -- the front end ----------------------------------------------------------------------------------------


def _pair(seed: int = 6) -> Pair:
    src = scan(seed)
    angle = 0.3
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    gt = np.eye(4)
    gt[:3, :3], gt[:3, 3] = R, [0.2, -0.1, 0.05]
    tgt = src @ R.T + gt[:3, 3] + np.random.default_rng(seed).normal(0, 0.002, src.shape)
    return Pair(name="scan", src_cloud=src, tgt_cloud=tgt, gt=gt, voxel_size=0.05, family="3dmatch")


def test_describing_only_the_kept_sources_gives_the_same_correspondences():
    pair = _pair()
    desc = FPFHDescriptor(impl="core", max_correspondences=300)
    kept = desc(pair, np.random.default_rng(3))
    plain = correspondences_from_features(desc, pair, np.random.default_rng(3), desc._match)
    np.testing.assert_array_equal(kept.src, plain.src)
    np.testing.assert_array_equal(kept.tgt, plain.tgt)
    np.testing.assert_array_equal(kept.scores, plain.scores)


def test_core_and_open3d_front_ends_give_the_same_matches():
    pair = _pair(7)
    c = FPFHDescriptor(impl="core", max_correspondences=0)(pair, np.random.default_rng(0))
    o = FPFHDescriptor(impl="open3d", max_correspondences=0)(pair, np.random.default_rng(0))
    assert len(c.src) == len(o.src)
    key = lambda corr: np.lexsort(np.c_[corr.src, corr.tgt].T)  # noqa: E731
    same = np.all(np.c_[c.src, c.tgt][key(c)] == np.c_[o.src, o.tgt][key(o)], axis=1)
    assert same.mean() > 0.995
    assert abs(c.labels.mean() - o.labels.mean()) <= 0.01 * o.labels.mean()


def test_bad_impl_and_voxel_say_what():
    with pytest.raises(InputError, match="impl"):
        FPFHDescriptor(impl="pcl")
    with pytest.raises(InputError, match="after voxel downsampling"):
        fpfh_features(scan(0)[:50], 10.0, impl="core", what="pair 'x': source cloud")
    with pytest.raises(InputError, match="2\\^21 voxels"):
        fpfh_features(np.array([[0.0, 0, 0], [1e9, 0, 0]] * 10), 1e-3, impl="core")


def test_voxel_grid_of_a_large_cloud_is_the_same_for_any_thread_count():
    """From 65,536 points the grid's radix passes run in parallel chunks: stable, so the voxels' points keep
    input order and the centroids (sums in that order) come out bit for bit as with one thread."""
    pts = np.vstack([scan(21, 60000), scan(22, 60000) + 0.0013])  # 120,000 points, many to a voxel
    one = core.core().voxel_downsample(pts, 0.05, num_threads=1)
    assert len(one) < len(pts) // 4
    for threads in (2, 3):
        np.testing.assert_array_equal(core.core().voxel_downsample(pts, 0.05, num_threads=threads), one)


# -- mesh resolution ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("loops", ["auto", "generic"])
@pytest.mark.parametrize(
    "case", ["scan", "duplicates", "outliers", "line", "two", "lattice", "georeferenced"]
)
def test_nearest_other_distances_equal_a_kd_tree(monkeypatch, case, loops):
    """Bitwise the k-d tree's distances, by the AVX-512 minimum and the portable loops."""
    monkeypatch.setenv("FASTMAC_RESOLUTION_MIN", loops)
    rng = np.random.default_rng(8)
    pts = {
        "scan": scan(9, 20000),
        # repeated points contribute 0; a lattice has many equal distances
        "duplicates": np.vstack([scan(10, 4000), scan(10, 4000)[:500]]),
        # far outliers force the ring search outwards and, past 64 rings, the fallback over every point
        "outliers": np.vstack([scan(11, 5000), rng.uniform(-1e4, 1e4, (5, 3)), [[3e5, 0, 0]]]),
        "line": np.c_[np.arange(1000) * 0.01, np.zeros(1000), np.zeros(1000)],
        "two": np.array([[0.0, 0, 0], [0.3, 0.4, 0]]),
        # points on a lattice sit on the cells' sides, where a query skips a column only when its side is
        # farther than the best so far; georeferenced: the same far from the origin, where the coordinates'
        # rounding is a larger share of a cell
        "lattice": np.stack(np.meshgrid(*[np.arange(24.0) * 0.01] * 3), -1).reshape(-1, 3),
        "georeferenced": scan(12, 20000) + [4.5e6, 5.6e5, 30.0],
    }[case]
    ref = cKDTree(pts).query(pts, k=2)[0][:, 1]
    for threads in (1, 2):
        np.testing.assert_array_equal(core.core().nearest_other_distances(pts, num_threads=threads), ref)


def test_mesh_resolution_rejects_bad_clouds():
    from fastmac_exp.geometry.resolution import mesh_resolution

    with pytest.raises(InputError, match="N >= 2"):
        mesh_resolution(np.zeros((1, 3)))
    with pytest.raises(InputError, match="non-finite"):
        mesh_resolution(np.array([[0.0, 0, 0], [np.nan, 0, 0], [1, 1, 1]]))


def test_nearest_other_distances_rejects_non_finite_points():
    with pytest.raises(ValueError, match="not finite"):
        core.core().nearest_other_distances(np.array([[0.0, 0, 0], [np.nan, 0, 0], [1, 1, 1]]))


def test_voxel_keypoints_drop_non_finite_rows():
    pts = scan(12)
    bad = pts.copy()
    bad[::7] = np.nan
    bad[3, 1] = np.inf
    keep = np.isfinite(bad).all(axis=1)
    np.testing.assert_array_equal(
        core.core().voxel_downsample(bad, 0.05), core.core().voxel_downsample(pts[keep], 0.05)
    )
    kp, _ = fpfh_features(bad, 0.05, impl="core")
    ref, _ = fpfh_features(pts[keep], 0.05, impl="open3d")
    np.testing.assert_array_equal(kp[np.lexsort(kp.T)], ref[np.lexsort(ref.T)])


# -- counts within a radius (the trust test's chance) ------------------------------------------------------


@pytest.mark.parametrize("case", ["scan", "lattice", "huge_radius", "far_queries"])
def test_count_within_equals_a_kd_tree(case):
    """Both ways of counting a cell's queries: each run in place (the lattice: one query a cell) and one
    gathered candidate list (huge_radius: every query in one cell); the scan mixes them."""
    rng = np.random.default_rng(12)
    lattice = np.stack(np.meshgrid(*[np.arange(6.0)] * 3), -1).reshape(-1, 3)
    pts, queries, r = {
        "scan": (scan(13, 6000), scan(14, 3000) + 0.01, 0.1),
        # points exactly at the radius count (<=), as in cKDTree
        "lattice": (lattice, lattice, 1.0),
        "huge_radius": (rng.uniform(0, 1, (300, 3)), rng.uniform(0, 1, (200, 3)), 10.0),
        "far_queries": (rng.uniform(0, 1, (300, 3)), rng.uniform(-50, 50, (400, 3)), 0.3),
    }[case]
    ref = cKDTree(pts).query_ball_point(queries, r, return_length=True)
    for threads in (1, 2):
        np.testing.assert_array_equal(core.core().count_within(queries, pts, r, num_threads=threads), ref)


def test_count_within_refuses_bad_input_and_counts_nan_queries_zero():
    pts = np.array([[0.0, 0, 0], [0.1, 0, 0]])
    assert list(core.core().count_within(np.array([[np.nan, 0, 0], [0.0, 0, 0]]), pts, 0.5)) == [0, 2]
    with pytest.raises(ValueError, match="radius"):
        core.core().count_within(pts, pts, 0.0)
    with pytest.raises(ValueError, match="not finite"):
        core.core().count_within(pts, np.array([[np.inf, 0, 0]]), 0.5)
