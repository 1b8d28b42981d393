"""Readers of fastmac_exp.io: formats, rigidity check, row-level errors naming file and line."""

from __future__ import annotations

import numpy as np
import pytest

from fastmac_exp import io
from fastmac_exp.datasets import benchmark_files as bf
from fastmac_exp.errors import InputError
from fastmac_exp.geometry import transforms
from fastmac_exp.geometry.transforms import random_rotation


def _rigid(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.eye(4)
    t[:3, :3] = random_rotation(rng)
    t[:3, 3] = rng.uniform(-2, 2, 3)
    return t


def _write_matrix(path, m, fmt="%.10f"):
    np.savetxt(path, m, fmt=fmt)
    return path


# ---------------------------------------------------------------------------------------------- clouds


@pytest.fixture
def cloud():
    return np.random.default_rng(1).uniform(-3, 3, (200, 3))


def test_read_points_every_format(tmp_path, cloud):
    from fastmac_exp._open3d import o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    for ext in ("ply", "pcd"):
        o3d.io.write_point_cloud(str(tmp_path / f"c.{ext}"), pcd)
    o3d.io.write_point_cloud(str(tmp_path / "c_ascii.ply"), pcd, write_ascii=True)
    np.save(tmp_path / "c.npy", cloud)
    np.save(tmp_path / "c4.npy", np.c_[cloud, np.ones(len(cloud))])
    np.savetxt(tmp_path / "c.xyz", cloud, fmt="%.9f")
    np.savetxt(tmp_path / "c.txt", np.c_[cloud, np.arange(len(cloud))], fmt="%.9f", header="x y z i")
    np.c_[cloud, np.zeros(len(cloud))].astype("<f4").tofile(tmp_path / "c.bin")

    tol = {"c.bin": 1e-6, "c_ascii.ply": 1e-5, "c.xyz": 1e-8, "c.txt": 1e-8}  # Open3D's ASCII: 6 digits
    for name in ("c.ply", "c_ascii.ply", "c.pcd", "c.npy", "c4.npy", "c.xyz", "c.txt", "c.bin"):
        pts = io.read_points(tmp_path / name)
        assert pts.dtype == np.float64 and pts.shape == (200, 3), name
        np.testing.assert_allclose(pts, cloud, atol=tol.get(name, 1e-12), err_msg=name)


def test_read_points_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        io.read_points(tmp_path / "nope.ply")
    (tmp_path / "a.obj").write_text("v 0 0 0\n")
    with pytest.raises(InputError, match="unknown point cloud extension"):
        io.read_points(tmp_path / "a.obj")
    (tmp_path / "bad.bin").write_bytes(b"\0" * 18)
    with pytest.raises(InputError, match="multiple of 16"):
        io.read_points(tmp_path / "bad.bin")
    (tmp_path / "headerless.ply").write_text("0 0 0\n1 1 1\n")
    with pytest.raises(InputError, match="not a PLY"):
        io.read_points(tmp_path / "headerless.ply")
    (tmp_path / "bad.xyz").write_text("0 0 0\n1 1 oops\n")
    with pytest.raises(InputError, match=r"bad\.xyz, line 2: 'oops' is not a number"):
        io.read_points(tmp_path / "bad.xyz")
    (tmp_path / "short.txt").write_text("0 0 0\n1 1\n")
    with pytest.raises(InputError, match=r"short\.txt, line 2: expected at least 3"):
        io.read_points(tmp_path / "short.txt")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object))
    with pytest.raises(InputError, match="obj.npy"):
        io.read_points(tmp_path / "obj.npy")  # allow_pickle=False refuses object arrays
    np.save(tmp_path / "flat.npy", np.zeros(9))
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        io.read_points(tmp_path / "flat.npy")


def _cut(path, keep_bytes_of_body: int) -> None:
    """Truncate a PLY's body after `keep_bytes_of_body` bytes (the header stays whole)."""
    data = path.read_bytes()
    start = data.index(b"end_header") + len(b"end_header\n")
    path.write_bytes(data[: start + keep_bytes_of_body])


def test_a_truncated_binary_ply_is_refused_with_its_name(tmp_path):
    """5,000 vertices declared, 1,000 present: Open3D would fill the rest with uninitialised rows."""
    from fastmac_exp._open3d import o3d

    pts = np.random.default_rng(0).uniform(-3, 3, (5000, 3))
    path = tmp_path / "cut.ply"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    np.testing.assert_allclose(io.read_points(path), pts)  # whole: read as written
    assert io.check_ply_body(path) == 5000
    _cut(path, 1000 * 3 * 8)
    with pytest.raises(InputError, match=r"cut\.ply: truncated: its header declares 5000 vertices"):
        io.read_points(path)
    ascii_path = tmp_path / "cut_ascii.ply"
    o3d.io.write_point_cloud(
        str(ascii_path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)), write_ascii=True
    )
    text = ascii_path.read_text().splitlines()
    ascii_path.write_text("\n".join(text[: len(text) - 4000]) + "\n")
    with pytest.raises(InputError, match=r"cut_ascii\.ply: truncated: .* 5000 vertices, .* 1000 data lines"):
        io.read_points(ascii_path)


@pytest.mark.parametrize("ascii", [False, True])
def test_a_truncated_pcd_is_refused_with_its_name(tmp_path, ascii):
    from fastmac_exp._open3d import o3d

    pts = np.random.default_rng(0).uniform(-3, 3, (5000, 3))
    path = tmp_path / "cut.pcd"
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii, compressed=False)
    np.testing.assert_allclose(io.read_points(path), pts, atol=1e-5)
    assert io.check_pcd_body(path) == 5000
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 3 // 10])
    with pytest.raises(InputError, match=r"cut\.pcd: truncated: its header declares 5000 points"):
        io.read_points(path)


def test_a_bin_of_another_dtype_is_refused_with_the_dtype_advice(tmp_path):
    scan = np.random.default_rng(0).uniform(-40, 40, (1000, 4)).astype("<f4")
    scan.tofile(tmp_path / "ok.bin")
    np.testing.assert_allclose(io.read_points(tmp_path / "ok.bin"), scan[:, :3])
    (scan * 100).astype("<i2").tofile(tmp_path / "int16.bin")  # 8,000 bytes: a multiple of 16
    with pytest.raises(InputError, match=r"int16\.bin: .* no plausible float32 values.*another dtype"):
        io.read_points(tmp_path / "int16.bin")


def test_clean_cloud_drops_invalid_and_rejects_absurd(cloud):
    pts = cloud.copy()
    pts[3] = np.nan
    pts[5] = 0.0
    pts[7, 1] = np.inf
    out, n = io.clean_cloud(pts, "c")
    assert n == 3 and len(out) == 197 and np.isfinite(out).all()
    out, n = io.clean_cloud(pts, "c", drop_zeros=False)
    assert n == 2
    pts[9, 2] = 2e6
    with pytest.raises(InputError, match=r"c: point 9 .*beyond 1e\+06 m"):
        io.clean_cloud(pts, "c")
    with pytest.raises(InputError, match="no valid points"):
        io.clean_cloud(np.zeros((4, 3)), "z")


# -------------------------------------------------------------------------------------------- matrices


def test_read_matrix_text_and_npy(tmp_path):
    t = _rigid()
    np.testing.assert_allclose(io.read_matrix(_write_matrix(tmp_path / "T.txt", t)), t, atol=1e-9)
    np.save(tmp_path / "T.npy", t)
    np.testing.assert_array_equal(io.read_matrix(tmp_path / "T.npy"), t)
    # numpy's %.18e (as FastMAC writes) and no trailing newline both parse
    (tmp_path / "T2.txt").write_text("\n".join(" ".join(f"{v:.18e}" for v in row) for row in t))
    np.testing.assert_array_equal(io.read_matrix(tmp_path / "T2.txt"), t)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda t: t.__setitem__((slice(0, 3), slice(0, 3)), 1.01 * t[:3, :3]), "not a rotation"),
        (lambda t: t.__setitem__((slice(0, 3), 0), -t[:3, 0]), "det"),  # a reflection
        (lambda t: t.__setitem__((3, 0), 0.5), "last row"),
        (lambda t: t.__setitem__((0, 1), t[0, 1] + 0.01), "not a rotation"),  # shear
        (lambda t: t.__setitem__((1, 3), np.nan), "NaN"),
    ],
)
def test_rigidity_check_names_file(tmp_path, mutate, message):
    t = _rigid(3)
    mutate(t)
    path = _write_matrix(tmp_path / "bad_gt.txt", t, fmt="%.12g")
    with pytest.raises(InputError, match=message) as e:
        io.read_matrix(path)
    assert str(path) in str(e.value)
    np.testing.assert_allclose(io.read_matrix(path, rigid=False), t, equal_nan=True)


def test_rigidity_tolerance_accepts_3dmatch_precision(tmp_path):
    # gt.log matrices deviate from orthonormal by up to ~5e-4 (see transforms.RIGID_TOL); they must pass
    t = _rigid(4)
    t[:3, :3] *= 1 + 2e-4
    transforms.check_rigid(t, "x")
    t[:3, :3] *= 1 + 2e-3
    with pytest.raises(InputError):
        transforms.check_rigid(t, "x")


def test_read_matrix_shape_errors(tmp_path):
    (tmp_path / "three.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(InputError, match="expected 4 rows"):
        io.read_matrix(tmp_path / "three.txt")
    (tmp_path / "cols.txt").write_text("1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(InputError, match=r"cols\.txt, line 2: expected 4 numbers"):
        io.read_matrix(tmp_path / "cols.txt")
    np.save(tmp_path / "m.npy", np.eye(3))
    with pytest.raises(InputError, match=r"m\.npy: expected a \(4, 4\)"):
        io.read_matrix(tmp_path / "m.npy")


# ------------------------------------------------------------------------------- correspondences, labels


def test_read_correspondences_and_labels(tmp_path):
    rng = np.random.default_rng(2)
    arr = rng.uniform(-5, 5, (50, 6))
    np.savetxt(tmp_path / "c.txt", arr, fmt="%.8f")
    lab = (rng.random(50) < 0.3).astype(int)
    np.savetxt(tmp_path / "l.txt", lab, fmt="%d")
    c = io.read_correspondences(tmp_path / "c.txt", tmp_path / "l.txt")
    np.testing.assert_allclose(c.src, arr[:, :3], atol=1e-8)
    np.testing.assert_allclose(c.tgt, arr[:, 3:], atol=1e-8)
    np.testing.assert_array_equal(c.labels, lab.astype(bool))
    np.savetxt(tmp_path / "lf.txt", lab, fmt="%.18e")  # FastMAC writes labels as floats
    np.testing.assert_array_equal(io.read_labels(tmp_path / "lf.txt", 50), lab.astype(bool))
    (tmp_path / "single.txt").write_text("1 2 3 4 5 6")
    assert io.read_correspondence_array(tmp_path / "single.txt").shape == (1, 6)
    (tmp_path / "empty.txt").write_text("")
    assert io.read_correspondence_array(tmp_path / "empty.txt").shape == (0, 6)


@pytest.mark.parametrize(
    "bad_line, message",
    [
        ("1 2 3 4 5", "expected 6 numbers"),
        ("1 2 3 4 5 6 7", "expected 6 numbers"),
        ("1 2 3 x 5 6", "'x' is not a number"),
        ("1 2 nan 4 5 6", "NaN or inf"),
        ("1 2 3 4 inf 6", "NaN or inf"),
        ("1 2 3 4 5 3e7", "beyond 1e\\+06 m"),
    ],
)
def test_correspondence_row_errors_name_file_and_line(tmp_path, bad_line, message):
    good = "0.1 0.2 0.3 0.4 0.5 0.6"
    path = tmp_path / "pair@corr.txt"
    path.write_text(f"{good}\n{good}\n\n{bad_line}\n{good}\n")
    with pytest.raises(InputError, match=message) as e:
        io.read_correspondence_array(path)
    assert f"{path}, line 4:" in str(e.value)


def test_label_errors(tmp_path):
    (tmp_path / "l.txt").write_text("1\n0\n2\n")
    with pytest.raises(InputError, match=r"l\.txt, line 3: label '2' is not 0 or 1"):
        io.read_labels(tmp_path / "l.txt")
    (tmp_path / "l2.txt").write_text("1\nyes\n")
    with pytest.raises(InputError, match=r"l2\.txt, line 2: 'yes' is not a number"):
        io.read_labels(tmp_path / "l2.txt")
    (tmp_path / "l3.txt").write_text("1\n0\n1\n")
    with pytest.raises(InputError, match="3 labels, but the correspondence file has 4 rows"):
        io.read_labels(tmp_path / "l3.txt", 4)


# ------------------------------------------------------------------------------------------- gt.log


def write_gt_log(path, entries, n=10):
    with open(path, "w") as f:
        for i, j, t in entries:
            f.write(f"{i}\t {j}\t {n}\t\n")
            for row in t:
                f.write("\t".join(f"{v: .8e}" for v in row) + "\t\n")


def test_read_gt_log(tmp_path):
    ents = [(0, 1, _rigid(5)), (2, 7, _rigid(6))]
    write_gt_log(tmp_path / "gt.log", ents)
    got = bf.read_gt_log(tmp_path / "gt.log")
    assert [(i, j, n) for i, j, n, _ in got] == [(0, 1, 10), (2, 7, 10)]
    for (_, _, t), (_, _, _, g) in zip(ents, got):
        np.testing.assert_allclose(g, t, atol=1e-7)
    assert [e.line for e in bf.read_gt_log_entries(tmp_path / "gt.log")] == [1, 6]


def test_gt_log_errors(tmp_path):
    bad = _rigid(7)
    bad[:3, :3] *= 1.1
    write_gt_log(tmp_path / "gt.log", [(0, 1, _rigid(5)), (0, 2, bad)])
    with pytest.raises(InputError, match=r"gt\.log, entry '0 2 10' \(line 6\).*not a rotation"):
        bf.read_gt_log(tmp_path / "gt.log")
    assert len(bf.read_gt_log_entries(tmp_path / "gt.log", rigid=False)) == 2
    (tmp_path / "short.log").write_text("0 1 3\n1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(InputError, match="not a multiple of 5"):
        bf.read_gt_log(tmp_path / "short.log")
    (tmp_path / "head.log").write_text("0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(InputError, match=r"head\.log, line 1: expected an entry header"):
        bf.read_gt_log(tmp_path / "head.log")


# -------------------------------------------------------------------------------------------- KITTI


def test_kitti_poses_calib_and_velodyne_gt(tmp_path):
    poses = np.stack([_rigid(10 + k) for k in range(5)])
    np.savetxt(tmp_path / "00.txt", poses[:, :3, :].reshape(5, 12), fmt="%.12e")
    np.testing.assert_allclose(bf.read_kitti_poses(tmp_path / "00.txt"), poses, atol=1e-11)
    tr = _rigid(20)
    calib = "P0: " + " ".join(["0"] * 12) + "\nTr: " + " ".join(f"{v:.12e}" for v in tr[:3].ravel()) + "\n"
    (tmp_path / "calib.txt").write_text(calib)
    np.testing.assert_allclose(bf.read_kitti_velo_to_cam(tmp_path / "calib.txt"), tr, atol=1e-11)
    # GT maps source Velodyne points into the target Velodyne frame: same world point both ways
    p_velo_src = np.array([1.0, 2.0, 3.0, 1.0])
    world = poses[3] @ tr @ p_velo_src
    p_velo_tgt = np.linalg.inv(poses[1] @ tr) @ world
    np.testing.assert_allclose(bf.kitti_velo_gt(poses[3], poses[1], tr) @ p_velo_src, p_velo_tgt, atol=1e-9)


def test_kitti_errors(tmp_path):
    (tmp_path / "p.txt").write_text(" ".join(["1"] * 12) + "\n" + " ".join(["0"] * 11) + "\n")
    with pytest.raises(InputError, match=r"p\.txt, line 2: expected 12 numbers"):
        bf.read_kitti_poses(tmp_path / "p.txt")
    (tmp_path / "q.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"q\.txt, line 2 \(frame 1\).*not a rotation"):
        bf.read_kitti_poses(tmp_path / "q.txt")
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match="no 'Tr:' line"):
        bf.read_kitti_velo_to_cam(tmp_path / "calib.txt")
    (tmp_path / "calib2.txt").write_text("garbage line\n")
    with pytest.raises(InputError, match=r"calib2\.txt, line 1"):
        bf.read_kitti_calib(tmp_path / "calib2.txt")


def test_register_says_what_it_dropped(caplog):
    """Issue 49 item 4: register() drops NaN/inf rows and points at the origin with a warning that counts
    them (it dropped them without a word, even at DEBUG)."""
    import fastmac_exp

    rng = np.random.default_rng(0)
    tgt = rng.uniform(0, 2, (3000, 3))
    src = tgt.copy()
    src[:4] = np.nan
    src[4] = np.inf
    src[5:7] = 0.0
    with caplog.at_level("WARNING", logger="fastmac_exp.io"):
        fastmac_exp.register(src, tgt, backend="python")
    (said,) = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    assert said == (
        "source cloud: read 3000 points, dropped 7: 5 not finite (NaN/inf); 2 exactly at (0, 0, 0), "
        "taken for invalid LiDAR returns"
    )


def test_the_public_loader_reads_what_the_cli_reads_and_open3d_imports_after_the_package(tmp_path):
    """Issue 49 item 5: fastmac_exp.load_cloud is public, and after `import fastmac_exp` a user's own
    `import open3d` works on a machine without a system libusb (it failed: libusb-1.0.so.0)."""
    import subprocess
    import sys

    import fastmac_exp

    cloud = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    np.save(tmp_path / "c.npy", cloud)
    np.c_[cloud, np.ones(200)].astype("<f4").tofile(tmp_path / "c.bin")
    np.savetxt(tmp_path / "c.txt", cloud, fmt="%.9f")
    for name in ("c.npy", "c.txt"):
        np.testing.assert_allclose(fastmac_exp.load_cloud(tmp_path / name), cloud, atol=1e-9)
    np.testing.assert_allclose(fastmac_exp.load_cloud(tmp_path / "c.bin"), cloud, atol=1e-6)
    assert "load_cloud" in fastmac_exp.__all__
    code = "import fastmac_exp, open3d; print(open3d.geometry.PointCloud().is_empty())"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and p.stdout.strip() == "True", p.stderr[-2000:]
