"""Benchmark dataset loaders on small fixtures written in the exact released layouts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from fastmac_exp.data.benchmarks import Kitti, ThreeDLoMatch, ThreeDMatch
from fastmac_exp.datasets.fragments import FCGF_EXCLUDED, Fragments3DMatch, KittiRaw, fcgf_pairs
from fastmac_exp.datasets.mac_layout import (
    SCENES_3DLOMATCH,
    SCENES_3DMATCH,
    KittiMAC,
    ThreeDLoMatchMAC,
    ThreeDMatchMAC,
)
from fastmac_exp.datasets.user_pairs import (
    OBJECT_RULES,
    REPO_ROOT,
    SharedRealPairs,
    UserPairs,
    resolve_shared_root,
)
from fastmac_exp.descriptors.precomputed import PrecomputedDescriptor
from fastmac_exp.errors import InputError
from fastmac_exp.geometry.resolution import pair_resolution
from fastmac_exp.geometry.transforms import random_rotation
from fastmac_exp.types import Correspondences, Pair

CONF = Path(__file__).resolve().parents[1] / "conf"


def rigid(seed: int, max_angle: float = 180.0, trans: float = 2.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.eye(4)
    t[:3, :3] = random_rotation(rng, max_angle)
    t[:3, 3] = rng.uniform(-trans, trans, 3)
    return t


def apply(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ t[:3, :3].T + t[:3, 3]


def save_matrix(path: Path, t: np.ndarray) -> None:
    np.savetxt(path, t, fmt="%.15e")


def make_corr(seed: int, gt: np.ndarray, n: int = 40, ratio: float = 0.25):
    """Correspondences whose first `ratio` rows are exact GT inliers; returns (array N x 6, labels)."""
    rng = np.random.default_rng(seed)
    src = rng.uniform(-2, 2, (n, 3))
    tgt = rng.uniform(-2, 2, (n, 3))
    k = int(n * ratio)
    tgt[:k] = apply(gt, src[:k])
    labels = np.zeros(n, dtype=int)
    labels[:k] = 1
    perm = rng.permutation(n)
    return np.c_[src, tgt][perm], labels[perm]


def write_mac_pair(
    folder: Path, name: str, seed: int, corr="@corr.txt", label="@label.txt", gtf="@GTmat.txt"
):
    gt = rigid(seed)
    arr, lab = make_corr(seed, gt)
    np.savetxt(folder / f"{name}{corr}", arr, fmt="%.10f")
    np.savetxt(folder / f"{name}{label}", lab, fmt="%d")
    save_matrix(folder / f"{name}{gtf}", gt)
    return gt, arr, lab


@pytest.fixture
def mac3dm(tmp_path):
    """Two 3DMatch scene folders in MAC's layout, with fpfh (plain) and fcgf (suffixed) files."""
    root = tmp_path / "3dmatch"
    truth = {}
    for s_i, scene in enumerate(SCENES_3DMATCH[:2]):
        d = root / scene
        d.mkdir(parents=True)
        names = [f"cloud_bin_{k}+cloud_bin_{k + 2}" for k in range(2 + s_i)]
        (d / "dataload.txt").write_text("\n".join(names) + "\n")
        (d / "dataload_fcgf.txt").write_text(names[0] + "\n")
        for k, n in enumerate(names):
            truth[f"{scene}/{n}"] = write_mac_pair(d, n, 100 * s_i + k)
        truth["fcgf:" + f"{scene}/{names[0]}"] = write_mac_pair(
            d, names[0], 7 + s_i, "@corr_fcgf.txt", "@label_fcgf.txt", "@GTmat_fcgf.txt"
        )
    return root, truth


def check_mac_pair(pair: Pair, truth, family: str) -> None:
    gt, arr, lab = truth
    assert pair.family == family
    np.testing.assert_allclose(pair.gt, gt, atol=1e-12)
    c = pair.correspondences
    np.testing.assert_allclose(c.src, arr[:, :3], atol=1e-9)
    np.testing.assert_allclose(c.tgt, arr[:, 3:], atol=1e-9)
    np.testing.assert_array_equal(c.labels, lab.astype(bool))
    # the GT maps the source points of the labelled inliers onto their targets (direction source -> target)
    err = np.linalg.norm(apply(pair.gt, c.src) - c.tgt, axis=1)
    assert (err[c.labels] < 1e-6).all() and (err[~c.labels] > 1e-3).all()
    assert pair.src_cloud is None and pair.tgt_cloud is None


# ---------------------------------------------------------------------------------- 3DMatch / 3DLoMatch


def test_3dmatch_layout_every_field(mac3dm):
    root, truth = mac3dm
    scenes = list(SCENES_3DMATCH[:2])
    ds = ThreeDMatchMAC(root=root, descriptor="fpfh", scenes=scenes)
    expected = [f"{scenes[0]}/cloud_bin_{k}+cloud_bin_{k + 2}" for k in range(2)] + [
        f"{scenes[1]}/cloud_bin_{k}+cloud_bin_{k + 2}" for k in range(3)
    ]
    assert ds.names() == expected and len(ds) == 5 and ds.name == "3dmatch"
    for i, n in enumerate(expected):
        p = ds.load(i)
        assert p.name == n and p.scene == n.split("/")[0]
        check_mac_pair(p, truth[n], "3dmatch")
        assert (p.re_thresh_deg, p.te_thresh_m, p.inlier_threshold) == (15.0, 0.3, 0.1)
        assert p.resolution == 0.006
        assert p.meta["source"] == n.split("/")[1].split("+")[0] and p.meta["descriptor"] == "fpfh"
    with pytest.raises(IndexError):
        ds.load(5)


def test_3dmatch_fcgf_file_names(mac3dm):
    root, truth = mac3dm
    ds = ThreeDMatchMAC(root=root, descriptor="fcgf", scenes=SCENES_3DMATCH[:2], resolution=0.01)
    assert ds.names() == [f"{s}/cloud_bin_0+cloud_bin_2" for s in SCENES_3DMATCH[:2]]
    p = ds.load(1)
    check_mac_pair(p, truth["fcgf:" + ds.names()[1]], "3dmatch")
    assert p.resolution == 0.01 and p.meta["corr_file"].endswith("@corr_fcgf.txt")


def test_3dlomatch_suffix_and_family(tmp_path):
    root = tmp_path / "lo"
    scene = SCENES_3DLOMATCH[3]
    (root / scene).mkdir(parents=True)
    (root / scene / "dataload.txt").write_text("cloud_bin_5+cloud_bin_9\n")
    truth = write_mac_pair(root / scene, "cloud_bin_5+cloud_bin_9", 11)
    ds = ThreeDLoMatchMAC(root=root, scenes=[scene])
    p = ds.load(0)
    assert ds.name == "3dlomatch" and p.name == f"{scene}/cloud_bin_5+cloud_bin_9"
    check_mac_pair(p, truth, "3dlomatch")
    assert (p.re_thresh_deg, p.te_thresh_m, p.inlier_threshold) == (15.0, 0.3, 0.1)
    # a scene given without the suffix finds the suffixed folder
    assert ThreeDLoMatchMAC(root=root, scenes=[SCENES_3DMATCH[3]]).load(0).gt is not None
    assert ThreeDLoMatchMAC().scenes == list(SCENES_3DLOMATCH)


def test_predator_flat_layout(tmp_path):
    (tmp_path / "dataload.txt").write_text("a+b\nc+d\n")
    t1 = write_mac_pair(tmp_path, "a+b", 1)
    write_mac_pair(tmp_path, "c+d", 2)
    ds = ThreeDMatchMAC(root=tmp_path, descriptor="predator")
    assert ds.names() == ["a+b", "c+d"]
    check_mac_pair(ds.load(0), t1, "3dmatch")


def test_missing_root_explains_data_layout_and_override():
    for root in (None, "/nonexistent/3dmatch"):
        ds = ThreeDMatchMAC(root=root)  # constructing never fails: Hydra would wrap the error
        with pytest.raises(InputError) as e:
            ds.names()
        msg = str(e.value)
        for needle in (
            "dataset.root",
            "zhangxy0517/3D-Registration-with-Maximal-Cliques",
            "FastMAC",
            "7-scenes-redkitchen/",
            "dataload.txt",
            "@corr.txt",
            "@label.txt",
            "@GTmat.txt",
            "dataset.root=/path",
            "python run.py dataset=3dmatch",
        ):
            assert needle in msg, needle
        if root:
            assert root in msg
    with pytest.raises(InputError, match="@corr_fcgf.txt"):
        ThreeDMatchMAC(descriptor="fcgf").load(0)
    with pytest.raises(InputError, match=r"fpfh@gtmat\.txt"):
        len(KittiMAC())


def test_missing_scene_and_files(mac3dm):
    root, _ = mac3dm
    with pytest.raises(InputError, match="scene folder.*missing.*sun3d-home_md") as e:
        ThreeDMatchMAC(root=root).names()  # default: all 8 scenes, only 2 present
    assert "dataset.scenes" in str(e.value)
    scene = SCENES_3DMATCH[0]
    (root / scene / "cloud_bin_1+cloud_bin_3@label.txt").unlink()
    ds = ThreeDMatchMAC(root=root, scenes=[scene])
    assert ds.load(0).gt is not None
    with pytest.raises(InputError) as e:
        ds.load(1)
    msg = str(e.value)
    assert str(root / scene / "cloud_bin_1+cloud_bin_3@label.txt") in msg
    assert "label file missing" in msg and "Expected layout" in msg
    (root / scene / "dataload.txt").unlink()
    with pytest.raises(InputError, match="pair list missing.*dataload.txt"):
        ThreeDMatchMAC(root=root, scenes=[scene]).names()


def test_malformed_pair_fails_alone(mac3dm):
    root, _ = mac3dm
    scene = SCENES_3DMATCH[1]
    d = root / scene
    corr = d / "cloud_bin_1+cloud_bin_3@corr.txt"
    lines = corr.read_text().splitlines()
    lines[6] = "1 2 3 4 5"
    corr.write_text("\n".join(lines) + "\n")
    lines[6] = "1 2 3 4 5 1e9"
    (d / "cloud_bin_2+cloud_bin_4@corr.txt").write_text("\n".join(lines) + "\n")
    gt = rigid(3)
    gt[:3, :3] *= 1.05
    save_matrix(d / "cloud_bin_0+cloud_bin_2@GTmat.txt", gt)
    ds = ThreeDMatchMAC(root=root, scenes=[scene])
    with pytest.raises(InputError, match=r"@GTmat\.txt: the 3x3 block is not a rotation"):
        ds.load(0)
    with pytest.raises(InputError, match="line 7: expected 6 numbers") as e:
        ds.load(1)
    assert f"{corr}, line 7:" in str(e.value)
    with pytest.raises(InputError, match=r"line 7: a coordinate is beyond 1e\+06 m"):
        ds.load(2)
    (d / "dataload.txt").write_text("cloud_bin_0+cloud_bin_2\nbroken name\n")
    with pytest.raises(InputError, match=r"dataload\.txt, line 2: expected one pair name"):
        ThreeDMatchMAC(root=root, scenes=[scene]).names()


def test_label_count_mismatch(mac3dm):
    root, _ = mac3dm
    scene = SCENES_3DMATCH[0]
    lab = root / scene / "cloud_bin_0+cloud_bin_2@label.txt"
    lab.write_text("\n".join(lab.read_text().splitlines()[:-1]) + "\n")
    with pytest.raises(InputError, match="39 labels, but the correspondence file has 40 rows"):
        ThreeDMatchMAC(root=root, scenes=[scene]).load(0)


# ------------------------------------------------------------------------------------------------ KITTI


def test_kitti_numeric_order_and_fields(tmp_path):
    root = tmp_path / "Processed_KITTI" / "correspondence_fcgf"
    truth = {}
    for i in (0, 1, 2, 10, 100):
        d = root / str(i)
        d.mkdir(parents=True)
        truth[str(i)] = write_mac_pair(d, "fcgf", i, "@corr.txt", "@gtlabel.txt", "@gtmat.txt")
    (root / "notes").mkdir()  # not a pair folder
    ds = KittiMAC(root=root, descriptor="fcgf")
    assert ds.names() == ["0", "1", "2", "10", "100"]  # numeric, not string order
    for i, n in enumerate(ds.names()):
        p = ds.load(i)
        assert p.name == n
        check_mac_pair(p, truth[n], "kitti")
        assert (p.re_thresh_deg, p.te_thresh_m, p.inlier_threshold, p.voxel_size) == (5.0, 0.6, 0.6, 0.3)
    # FastMAC's Processed_KITTI/ default is followed into correspondence_<desc>/
    assert KittiMAC(root=tmp_path / "Processed_KITTI", descriptor="fcgf").names() == ds.names()
    with pytest.raises(InputError, match=r"fpfh@corr\.txt"):
        KittiMAC(root=root, descriptor="fpfh").load(0)
    with pytest.raises(InputError, match="no numbered pair folders"):
        KittiMAC(root=tmp_path, descriptor="fcgf").names()


# ------------------------------------------------------------------------------------ raw 3DMatch fragments


def write_ply(path: Path, pts: np.ndarray) -> None:
    from fastmac_exp._open3d import o3d

    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))


def write_gt_log(path: Path, entries, n: int) -> None:
    with open(path, "w") as f:
        for i, j, t in entries:
            f.write(f"{i}\t {j}\t {n}\t\n")
            for row in t:
                f.write("\t".join(f"{v: .12e}" for v in row) + "\t\n")


@pytest.fixture
def fragments(tmp_path):
    """Three fragments of one world cloud; fragment k = world in frame P_k (same rows in every fragment)."""
    root = tmp_path / "frag"
    scene = SCENES_3DMATCH[0]
    (root / scene).mkdir(parents=True)
    world = np.random.default_rng(0).uniform(-1.5, 1.5, (300, 3))
    poses = [rigid(30 + k, 60, 1.0) for k in range(3)]
    frags = [apply(np.linalg.inv(p), world) for p in poses]
    for k, f in enumerate(frags):
        write_ply(root / scene / f"cloud_bin_{k}.ply", f)
    # official convention: entry `i j` holds inv(P_i) P_j, mapping fragment j into fragment i
    entries = [(0, 1, np.linalg.inv(poses[0]) @ poses[1]), (0, 2, np.linalg.inv(poses[0]) @ poses[2]),
               (1, 2, np.linalg.inv(poses[1]) @ poses[2])]  # fmt: skip
    write_gt_log(root / scene / "gt.log", entries, 3)
    return root, scene, frags


def test_fragments_pairs_and_gt_direction(fragments):
    root, scene, frags = fragments
    ds = Fragments3DMatch(root=root, scenes=[scene])
    assert ds.names() == [f"{scene}/cloud_bin_1+cloud_bin_0", f"{scene}/cloud_bin_2+cloud_bin_0",
                          f"{scene}/cloud_bin_2+cloud_bin_1"]  # fmt: skip
    for idx, (i, j) in enumerate([(0, 1), (0, 2), (1, 2)]):
        p = ds.load(idx)
        np.testing.assert_allclose(p.src_cloud, frags[j], atol=1e-12)  # source = fragment j
        np.testing.assert_allclose(p.tgt_cloud, frags[i], atol=1e-12)  # target = fragment i
        np.testing.assert_allclose(apply(p.gt, p.src_cloud), p.tgt_cloud, atol=1e-9)
        assert p.correspondences is None and p.family == "3dmatch" and p.scene == scene
        assert (p.voxel_size, p.re_thresh_deg, p.te_thresh_m, p.inlier_threshold) == (0.05, 15.0, 0.3, 0.1)
        # the resolution is computed from the two fragments, as MAC does (spec 1.5)
        assert p.resolution == pytest.approx(pair_resolution(frags[j], frags[i]), rel=1e-12)
        assert p.meta["source"] == f"cloud_bin_{j}" and p.meta["target"] == f"cloud_bin_{i}"


def test_fragments_gt_root_and_evaluation_folder(fragments, tmp_path):
    root, scene, _ = fragments
    log = (root / scene / "gt.log").read_text()
    (root / scene / "gt.log").unlink()
    with pytest.raises(InputError, match="no gt.log for scene") as e:
        Fragments3DMatch(root=root, scenes=[scene]).names()
    assert "dataset.gt_root" in str(e.value)
    (root / f"{scene}-evaluation").mkdir()
    (root / f"{scene}-evaluation" / "gt.log").write_text(log)
    assert len(Fragments3DMatch(root=root, scenes=[scene])) == 3
    gt_root = tmp_path / "benchmarks" / "3DLoMatch"
    (gt_root / scene).mkdir(parents=True)
    (gt_root / scene / "gt.log").write_text("\n".join(log.splitlines()[:5]) + "\n")
    ds = Fragments3DMatch(root=root, gt_root=gt_root, scenes=[scene], family="3dlomatch")
    assert ds.names() == [f"{scene}/cloud_bin_1+cloud_bin_0"] and ds.load(0).family == "3dlomatch"


def test_fragments_errors(fragments):
    root, scene, _ = fragments
    with pytest.raises(InputError, match="dataset.root is not set") as e:
        Fragments3DMatch().names()
    assert "cloud_bin_0.ply" in str(e.value) and "gt.log" in str(e.value)
    (root / scene / "cloud_bin_2.ply").unlink()
    ds = Fragments3DMatch(root=root, scenes=[scene])
    ds.load(0)
    with pytest.raises(InputError, match=r"fragment missing: .*cloud_bin_2\.ply"):
        ds.load(1)
    lines = (root / scene / "gt.log").read_text().splitlines()
    lines[7] = lines[7].replace("e-", "e+1")  # corrupt one rotation entry of the second entry
    (root / scene / "gt.log").write_text("\n".join(lines) + "\n")
    ds = Fragments3DMatch(root=root, scenes=[scene])
    assert len(ds) == 3  # the index still reads; only that pair fails
    with pytest.raises(InputError, match=r"gt\.log, entry '0 2 3' \(line 6\)"):
        ds.load(1)
    with pytest.raises(InputError, match="family must be 3dmatch or 3dlomatch"):
        Fragments3DMatch(root=root, scenes=[scene], family="kitti").names()


# ------------------------------------------------------------------------------------------------ KITTI raw


@pytest.fixture
def kitti_raw(tmp_path):
    """Sequence 08: 30 frames driving 1.5 m a frame along camera z, one shared world of 120 points."""
    root = tmp_path / "dataset"
    seq = root / "sequences" / "08"
    (seq / "velodyne").mkdir(parents=True)
    (root / "poses").mkdir()
    tr = np.eye(4)
    tr[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)  # KITTI's axis swap
    tr = tr @ rigid(5, 2, 0.3)
    (seq / "calib.txt").write_text(
        "P0: " + " ".join(["1"] * 12) + "\nTr: " + " ".join(f"{v:.15e}" for v in tr[:3].ravel()) + "\n"
    )
    poses = []
    for k in range(30):
        p = rigid(200 + k, 3, 0.1)
        p[2, 3] += 1.5 * k
        poses.append(p)
    np.savetxt(root / "poses" / "08.txt", np.array([p[:3].ravel() for p in poses]), fmt="%.15e")
    world = np.random.default_rng(3).uniform(-15, 15, (120, 3)) + [0, 0, 20]
    scans = []
    for k, p in enumerate(poses):
        velo = apply(np.linalg.inv(p @ tr), world)
        np.c_[velo, np.zeros(len(velo))].astype("<f4").tofile(seq / "velodyne" / f"{k:06d}.bin")
        scans.append(velo)
    return root, poses, scans


def test_kitti_raw_fcgf_protocol_and_gt(kitti_raw):
    root, poses, scans = kitti_raw
    ds = KittiRaw(root=root, sequences=[8])
    # first frame beyond 10 m from 0 is 7 (10.5 m): FCGF pairs 0 with 7 - 1 = 6, then restarts at 7
    assert ds.names() == ["08/000000+000006", "08/000007+000013", "08/000014+000020", "08/000021+000027"]
    p = ds.load(1)
    assert p.family == "kitti" and p.scene == "08" and p.correspondences is None
    assert (p.voxel_size, p.re_thresh_deg, p.te_thresh_m, p.inlier_threshold) == (0.3, 5.0, 0.6, 0.6)
    np.testing.assert_allclose(p.src_cloud, scans[7], atol=1e-5)
    np.testing.assert_allclose(p.tgt_cloud, scans[13], atol=1e-5)
    np.testing.assert_allclose(apply(p.gt, p.src_cloud), p.tgt_cloud, atol=1e-4)  # source -> target, Velodyne
    assert 8.5 < p.meta["distance_m"] <= 10.0


def test_kitti_raw_explicit_pairs_and_errors(kitti_raw):
    root, _, scans = kitti_raw
    ds = KittiRaw(root=root, pairs=[[8, 3, 1], ["8", "29", "0"]])
    assert ds.names() == ["08/000003+000001", "08/000029+000000"]
    p = ds.load(1)
    np.testing.assert_allclose(apply(p.gt, scans[29]), scans[0], atol=1e-4)
    (root / "sequences" / "08" / "velodyne" / "000005.bin").unlink()
    with pytest.raises(InputError, match=r"scan missing: .*000005\.bin"):
        KittiRaw(root=root, pairs=[[8, 5, 0]]).load(0)
    with pytest.raises(InputError, match="frame 31 has no pose"):
        KittiRaw(root=root, pairs=[[8, 31, 0]]).load(0)
    with pytest.raises(InputError, match=r"velodyne"):
        KittiRaw(root=root, sequences=[9]).names()
    with pytest.raises(InputError, match="dataset.root is not set") as e:
        KittiRaw().names()
    assert "poses/08.txt" in str(e.value) and "calib.txt" in str(e.value)
    with pytest.raises(InputError, match=r"\[seq, source frame, target frame\]"):
        KittiRaw(root=root, pairs=[[8, 1]]).names()
    (root / "sequences" / "08" / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match="no 'Tr:' line"):
        KittiRaw(root=root, pairs=[[8, 1, 0]]).load(0)


def test_fcgf_pairs_rule():
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, 0, 3] = [0, 4, 8, 9.9, 10.1, 12, 15, 19, 21, 25, 26, 27]
    assert fcgf_pairs(poses, range(12)) == [(0, 3), (4, 7)]
    # frame 3 is missing on disk: FCGF would loop forever at frame 0, we move on to frame 1
    assert fcgf_pairs(poses, [0, 1, 2, 4, 5, 6, 7, 8]) == [(1, 5)]
    assert (8, 15, 58) in FCGF_EXCLUDED


# ------------------------------------------------------------------------------------- user pairs, shared


def test_user_pairs(tmp_path):
    rng = np.random.default_rng(4)
    src = rng.uniform(-1, 1, (100, 3))
    gt = rigid(6)
    write_ply(tmp_path / "s.ply", np.r_[src, np.zeros((3, 3))])
    np.save(tmp_path / "t.npy", apply(gt, src))
    save_matrix(tmp_path / "gt.txt", gt)
    p = UserPairs(tmp_path / "s.ply", str(tmp_path / "t.npy"), str(tmp_path / "gt.txt")).load(0)
    assert p.name == "s+t" and p.family == "3dmatch" and p.voxel_size == 0.05
    assert p.meta["dropped_points"] == (3, 0)
    np.testing.assert_allclose(apply(p.gt, p.src_cloud), p.tgt_cloud, atol=1e-9)
    q = UserPairs(tmp_path / "s.ply", tmp_path / "t.npy", family="kitti").load(0)
    assert q.gt is None and q.voxel_size == 0.3 and (q.re_thresh_deg, q.te_thresh_m) == (5.0, 0.6)
    assert UserPairs(tmp_path / "s.ply", tmp_path / "t.npy", voxel_size=0.01).load(0).voxel_size == 0.01
    many = UserPairs([tmp_path / "s.ply", tmp_path / "t.npy"], [tmp_path / "t.npy", tmp_path / "s.ply"])
    assert many.names() == ["s+t", "t+s"]
    with pytest.raises(InputError, match="dataset.source=src.ply"):
        UserPairs().names()
    with pytest.raises(InputError, match="point cloud file not found"):
        UserPairs(tmp_path / "nope.pcd", tmp_path / "t.npy").load(0)
    with pytest.raises(InputError, match="unknown dataset family"):
        UserPairs(tmp_path / "s.ply", tmp_path / "t.npy", family="eth").names()
    np.save(tmp_path / "far.npy", src + 5e6)
    with pytest.raises(InputError, match="beyond 1e\\+06 m"):
        UserPairs(tmp_path / "far.npy", tmp_path / "t.npy").load(0)


@pytest.fixture
def shared(tmp_path):
    root = tmp_path / "shared" / "data"
    root.mkdir(parents=True)
    rng = np.random.default_rng(5)
    entries = []
    for k, (cat, ds) in enumerate(
        [("indoor", "3DMatch test"), ("indoor", "3DLoMatch test"), ("outdoor", "KITTI"), ("object", "bunny")]
    ):
        np.save(root / f"s{k}.npy", rng.uniform(-1, 1, (50, 3)))
        np.save(root / f"t{k}.npy", rng.uniform(-1, 1, (50, 3)))
        save_matrix(root / f"gt{k}.txt", rigid(k))
        entries.append({"id": f"p{k}", "category": cat, "dataset": ds, "source": f"s{k}.npy",
                        "target": f"t{k}.npy", "gt": f"gt{k}.txt"})  # fmt: skip
    (root / "pairs.json").write_text(json.dumps({"pairs": entries}))
    return root


def test_shared_real_pairs_rules(shared):
    ds = SharedRealPairs(root=shared)
    assert ds.names() == ["p0", "p1", "p2", "p3"]
    fam = [(p.family, p.voxel_size, p.inlier_threshold, p.re_thresh_deg, p.te_thresh_m)
           for p in (ds.load(i) for i in range(4))]  # fmt: skip
    assert fam == [
        ("3dmatch", 0.05, 0.1, 15.0, 0.3),
        ("3dlomatch", 0.05, 0.1, 15.0, 0.3),
        ("kitti", 0.3, 0.6, 5.0, 0.6),
        ("3dmatch", 0.002, 0.005, 15.0, 0.01),
    ]
    assert ds.load(3).resolution == OBJECT_RULES["resolution"]
    p = ds.load(2)
    np.testing.assert_array_equal(p.src_cloud, np.load(shared / "s2.npy"))
    np.testing.assert_allclose(p.gt, rigid(2), atol=1e-14)
    assert SharedRealPairs(root=shared, category="indoor").names() == ["p0", "p1"]
    assert SharedRealPairs(root=shared, ids=["p3", "p0"]).names() == ["p0", "p3"]
    with pytest.raises(InputError, match="unknown id"):
        SharedRealPairs(root=shared, category="outdoor", ids=["p0"]).names()
    with pytest.raises(InputError, match="category must be"):
        SharedRealPairs(root=shared, category="forest").names()


def test_shared_root_resolution(tmp_path):
    assert REPO_ROOT == Path(__file__).resolve().parents[1]
    assert resolve_shared_root("../shared/data") == (REPO_ROOT.parent / "shared" / "data").resolve()
    assert resolve_shared_root(tmp_path) == tmp_path
    with pytest.raises(InputError, match=r"pairs\.json not found.*dataset\.root="):
        SharedRealPairs(root=tmp_path / "absent").names()


def test_precomputed_descriptor():
    c = Correspondences(np.zeros((4, 3)), np.ones((4, 3)), labels=[1, 0, 0, 1])
    d = PrecomputedDescriptor(graph_key="fcgf")
    assert d.name == "precomputed" and d.graph_key == "fcgf"
    assert d(Pair(name="x", correspondences=c), np.random.default_rng(0)) is c
    with pytest.raises(InputError, match="descriptor=fpfh"):
        d(Pair(name="x"), np.random.default_rng(0))
    gt = np.eye(4)
    unl = Correspondences(np.zeros((2, 3)), np.array([[0, 0, 0.01], [1, 1, 1]]))
    out = d(Pair(name="y", gt=gt, correspondences=unl), np.random.default_rng(0))
    np.testing.assert_array_equal(out.labels, [True, False])


# ---------------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize(
    "config, cls, extra",
    [
        (
            "3dmatch",
            ThreeDMatch,
            {"descriptor": "fcgf", "scenes": None, "resolution": None, "front_end": "auto"},
        ),
        ("3dlomatch", ThreeDLoMatch, {"descriptor": "fcgf", "front_end": "auto"}),
        ("kitti", Kitti, {"descriptor": "fcgf", "front_end": "auto"}),
        ("fragments_3dmatch", Fragments3DMatch, {"family": "3dmatch", "gt_root": None}),
        ("kitti_raw", KittiRaw, {"pairs": None, "sequences": [8, 9, 10], "min_distance": 10.0}),
        ("pairs", UserPairs, {"source": None, "target": None, "gt": None, "family": "auto"}),
        ("shared_real", SharedRealPairs, {"root": "../shared/data", "category": None, "ids": None}),
    ],
)
def test_dataset_configs_instantiate(config, cls, extra):
    from hydra.utils import instantiate

    node = OmegaConf.load(CONF / "dataset" / f"{config}.yaml")
    cfg = OmegaConf.create({"descriptor": {"graph_key": "fcgf"}, "dataset": node})
    ds_cfg = OmegaConf.to_container(cfg.dataset, resolve=True)
    assert "limit" not in ds_cfg and ("root" in ds_cfg or config == "pairs")  # limit is a run key
    for k, v in extra.items():
        assert ds_cfg[k] == v, k
    ds = instantiate(cfg.dataset)  # the node as it stands, as the experiment builds it
    assert isinstance(ds, cls)


def test_precomputed_config_and_run_config_error():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    d = instantiate(OmegaConf.load(CONF / "descriptor" / "precomputed.yaml"))
    assert isinstance(d, PrecomputedDescriptor) and d.graph_key == "fpfh"
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(
            "config", overrides=["dataset=3dmatch", "descriptor=precomputed", "descriptor.graph_key=fcgf"]
        )
    from fastmac_exp.run.experiment import Components

    with pytest.raises(InputError, match=r"needs MAC's released fcgf correspondences(.|\n)*data add NAME"):
        Components(cfg)  # the experiment's own builder: an empty data home has no MAC correspondences


def test_pairs_family_auto_says_which_rules_and_warns_on_outdoor_sized_clouds(tmp_path, caplog):
    """Issue 49 item 6: family=auto (dataset=pairs' default) takes the indoor rules for clouds that are no
    .bin scans and says so, with a warning where they span more than a room."""
    from fastmac_exp.datasets.user_pairs import UserPairs

    rng = np.random.default_rng(0)
    room = rng.uniform(0, 4, (2000, 3))
    np.save(tmp_path / "room.npy", room)
    np.save(tmp_path / "street.npy", room * 20)
    with caplog.at_level("INFO", logger="fastmac_exp.datasets.user_pairs"):
        indoor = UserPairs(tmp_path / "room.npy", tmp_path / "room.npy").load(0)
        outdoor = UserPairs(tmp_path / "street.npy", tmp_path / "street.npy").load(0)
    assert indoor.family == outdoor.family == "3dmatch" and indoor.voxel_size == 0.05
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert said[0][0] == "INFO" and said[0][1].startswith("room+room: family=3dmatch (the clouds span 4.0 m")
    assert (
        said[1][0] == "WARNING" and "the clouds span 80 m: outdoor scans? dataset.family=kitti" in said[1][1]
    )
    assert UserPairs(tmp_path / "room.npy", tmp_path / "room.npy", family="kitti").load(0).family == "kitti"
