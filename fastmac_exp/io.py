"""File readers for benchmark data: point clouds, 4x4 matrices, correspondences, labels, gt.log, KITTI.

Every reader raises fastmac_exp.errors.InputError naming the file (and the line, for row-level problems)
when the file is missing or malformed. Points come back as float64 arrays; numpy files are always read
with allow_pickle=False.

Formats (spec section 1.1):
- correspondences: one per line, `px py pz qx qy qz` (source point first), whitespace-separated, no header;
- labels: one value per line, 1 = ground-truth inlier, 0 = outlier (float spellings such as `1.0e+00`
  are accepted, as FastMAC writes them with numpy);
- matrices: four lines of four numbers (row-major, source -> target), or a (4, 4) .npy;
- 3DMatch gt.log: `i j n` then four lines of a 4x4 T mapping fragment j (source) into fragment i (target);
- KITTI poses: one line of 12 numbers per frame (row-major 3x4 camera-0 pose in the frame of frame 0);
- KITTI calib.txt: `KEY: v1 ... v12` lines; `Tr` is the Velodyne -> camera-0 transform.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.transforms import RIGID_TOL, check_rigid, nearest_rigid  # noqa: F401 - re-exported
from fastmac_exp.types import MAX_COORD, Correspondences

CLOUD_EXTENSIONS = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt", ".npy", ".bin")
MATRIX_EXTENSIONS = (".txt", ".npy", ".log", ".mat", "")


# ----------------------------------------------------------------------------------------------------------
# helpers


def _loadtxt(p: Path, **kw) -> np.ndarray:
    """np.loadtxt without the empty-file warning (an empty file gives an empty array)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(p, dtype=np.float64, **kw)


def _path(path: str | Path, what: str) -> Path:
    p = Path(path).expanduser()
    if not p.exists():
        raise InputError(f"{what} not found: {p}")
    if p.is_dir():
        raise InputError(f"{what} is a directory, expected a file: {p}")
    return p


def _lines(p: Path):
    """(1-based line number, stripped text) of the non-blank lines of a text file."""
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: not a text file ({e})") from None
    for k, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s:
            yield k, s


def _parse_floats(tokens: list[str], p: Path, lineno: int) -> list[float]:
    out = []
    for tok in tokens:
        try:
            out.append(float(tok))
        except ValueError:
            raise InputError(f"{p}, line {lineno}: {tok!r} is not a number") from None
    return out


def check_points(points: np.ndarray, where: str, allow_nonfinite: bool = False) -> None:
    """Raise InputError on NaN/inf (unless allowed) or on coordinates beyond 1e6 m, naming the first row."""
    if not allow_nonfinite:
        bad = ~np.isfinite(points).all(axis=1)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise InputError(f"{where}: point {row} is not finite: {points[row].tolist()}")
    huge = (np.isfinite(points) & (np.abs(np.nan_to_num(points)) > MAX_COORD)).any(axis=1)
    if huge.any():
        row = int(np.flatnonzero(huge)[0])
        raise InputError(
            f"{where}: point {row} has a coordinate beyond {MAX_COORD:g} m ({points[row].tolist()}); "
            "are the units metres?"
        )


# ----------------------------------------------------------------------------------------------------------
# point clouds


def _read_text_points(p: Path) -> np.ndarray:
    """x y z [extra columns...] per line; '#' comments and blank lines are skipped."""
    try:
        arr = _loadtxt(p, ndmin=2, comments="#")
        if arr.size == 0:
            return np.zeros((0, 3))
        if arr.shape[1] >= 3:
            return arr[:, :3]
    except ValueError:
        pass
    # slow path: find the offending line
    rows = []
    ncols = None
    for k, s in _lines(p):
        if s.startswith("#"):
            continue
        vals = _parse_floats(s.split(), p, k)
        if len(vals) < 3:
            raise InputError(f"{p}, line {k}: expected at least 3 numbers (x y z), got {len(vals)}")
        if ncols is None:
            ncols = len(vals)
        elif len(vals) != ncols:
            raise InputError(f"{p}, line {k}: {len(vals)} columns, but the first data line has {ncols}")
        rows.append(vals[:3])
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def _read_npy(p: Path) -> np.ndarray:
    try:
        arr = np.load(p, allow_pickle=False)
    except ValueError as e:
        raise InputError(f"{p}: cannot read as a plain numpy array ({e})") from None
    except OSError as e:
        raise InputError(f"{p}: not a valid .npy file ({e})") from None
    if not isinstance(arr, np.ndarray):
        raise InputError(f"{p}: expected a single array (.npy), got {type(arr).__name__}")
    return arr


def _read_kitti_bin(p: Path) -> np.ndarray:
    size = p.stat().st_size
    if size % 16:
        raise InputError(
            f"{p}: {size} bytes is not a multiple of 16; a KITTI .bin holds float32 rows "
            "(x, y, z, reflectance)"
        )
    return np.fromfile(p, dtype="<f4").reshape(-1, 4)[:, :3].astype(np.float64)


def _read_o3d(p: Path) -> np.ndarray:
    with open(p, "rb") as f:
        head = f.read(64)
    if p.suffix.lower() == ".ply" and not head.lstrip().lower().startswith(b"ply"):
        raise InputError(
            f"{p}: not a PLY file (it does not start with 'ply'); "
            "for headerless 'x y z' text use the .xyz or .txt extension"
        )
    from fastmac_exp._open3d import o3d

    pcd = o3d.io.read_point_cloud(str(p))
    pts = np.asarray(pcd.points, dtype=np.float64)
    if len(pts) == 0 and p.stat().st_size > 0:
        raise InputError(
            f"{p}: Open3D read no points; is it a valid {p.suffix.lower()[1:].upper()} point cloud?"
        )
    return pts


def read_points(path: str | Path) -> np.ndarray:
    """Read a point cloud file into an (N, 3) float64 array (no cleaning; see `load_cloud`).

    .ply / .pcd via Open3D; .xyz / .txt / .pts as text (first three columns); .npy (N, >=3) float array,
    first three columns; .bin as KITTI Velodyne float32 (N, 4).
    """
    p = _path(path, "point cloud file")
    ext = p.suffix.lower()
    if ext in (".ply", ".pcd"):
        pts = _read_o3d(p)
    elif ext in (".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt"):
        pts = _read_text_points(p)
    elif ext == ".npy":
        arr = _read_npy(p)
        if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
            raise InputError(f"{p}: expected a numeric (N, 3) array, got dtype {arr.dtype} shape {arr.shape}")
        pts = np.asarray(arr[:, :3], dtype=np.float64)
    elif ext == ".bin":
        pts = _read_kitti_bin(p)
    else:
        raise InputError(
            f"{p}: unknown point cloud extension {ext!r}; supported: {', '.join(CLOUD_EXTENSIONS)}"
        )
    return np.ascontiguousarray(pts, dtype=np.float64)


def clean_cloud(points: np.ndarray, where: str, drop_zeros: bool = True) -> tuple[np.ndarray, int]:
    """Drop non-finite rows (missing returns in organised clouds) and, if asked, points exactly at (0, 0, 0)
    (invalid LiDAR returns, e.g. small_gicp's scans); raise on coordinates beyond 1e6 m or an empty result.

    Returns (points, number dropped).
    """
    check_points(points, where, allow_nonfinite=True)
    keep = np.isfinite(points).all(axis=1)
    if drop_zeros:
        keep &= np.any(points != 0.0, axis=1)
    n_drop = int(len(points) - keep.sum())
    out = np.ascontiguousarray(points[keep]) if n_drop else points
    if len(out) == 0:
        raise InputError(f"{where}: no valid points (read {len(points)}, all NaN/inf or exactly zero)")
    return out, n_drop


def load_cloud(path: str | Path, drop_zeros: bool = True) -> np.ndarray:
    """`read_points` then `clean_cloud`: a finite, non-empty (N, 3) float64 cloud."""
    return clean_cloud(read_points(path), str(path), drop_zeros)[0]


# ----------------------------------------------------------------------------------------------------------
# matrices


def read_matrix(path: str | Path, rigid: bool = True) -> np.ndarray:
    """A 4x4 matrix from a text file (four lines of four numbers) or a .npy; rigidity-checked by default."""
    p = _path(path, "matrix file")
    if p.suffix.lower() == ".npy":
        m = _read_npy(p)
        if m.shape != (4, 4):
            raise InputError(f"{p}: expected a (4, 4) array, got shape {m.shape}")
        try:
            m = m.astype(np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{p}: expected a numeric array, got dtype {m.dtype}") from None
    else:
        rows = []
        for k, s in _lines(p):
            vals = _parse_floats(s.split(), p, k)
            if len(vals) != 4:
                raise InputError(
                    f"{p}, line {k}: expected 4 numbers (a row of a 4x4 matrix), got {len(vals)}"
                )
            rows.append(vals)
        if len(rows) != 4:
            raise InputError(f"{p}: expected 4 rows of 4 numbers (a 4x4 matrix), got {len(rows)} rows")
        m = np.asarray(rows, dtype=np.float64)
    return check_rigid(m, str(p)) if rigid else m


# ----------------------------------------------------------------------------------------------------------
# correspondences and labels


def _scan_corr(p: Path) -> np.ndarray:
    """Line-by-line parse that names the first bad line (wrong column count, non-numeric, NaN/inf, absurd)."""
    rows = []
    for k, s in _lines(p):
        toks = s.split()
        if len(toks) != 6:
            raise InputError(f"{p}, line {k}: expected 6 numbers (px py pz qx qy qz), got {len(toks)}")
        vals = _parse_floats(toks, p, k)
        if not all(math.isfinite(v) for v in vals):
            raise InputError(f"{p}, line {k}: NaN or inf in {s!r}")
        if any(abs(v) > MAX_COORD for v in vals):
            raise InputError(
                f"{p}, line {k}: a coordinate is beyond {MAX_COORD:g} m in {s!r}; are the units metres?"
            )
        rows.append(vals)
    return np.asarray(rows, dtype=np.float64).reshape(-1, 6)


def read_correspondence_array(path: str | Path) -> np.ndarray:
    """The (N, 6) float64 array of a correspondence text file, validated row by row."""
    p = _path(path, "correspondence file")
    try:
        arr = _loadtxt(p, ndmin=2, comments=None)
        ok = (
            (arr.size == 0 or arr.shape[1] == 6)
            and np.isfinite(arr).all()
            and not (np.abs(arr) > MAX_COORD).any()
        )
    except ValueError:
        ok = False
    if not ok:
        arr = _scan_corr(p)  # raises with the line number
    return np.ascontiguousarray(arr.reshape(-1, 6))


def read_labels(path: str | Path, n: int | None = None) -> np.ndarray:
    """A (N,) bool array from a 0/1-per-line file; `n` checks the count against the correspondences."""
    p = _path(path, "label file")
    try:
        vals = _loadtxt(p, ndmin=1, comments=None)
        ok = vals.ndim == 1 and np.isin(vals, (0.0, 1.0)).all()
    except ValueError:
        ok = False
    if not ok:
        out = []
        for k, s in _lines(p):
            toks = s.split()
            if len(toks) != 1:
                raise InputError(f"{p}, line {k}: expected one label (0 or 1), got {len(toks)} values")
            v = _parse_floats(toks, p, k)[0]
            if v not in (0.0, 1.0):
                raise InputError(f"{p}, line {k}: label {toks[0]!r} is not 0 or 1")
            out.append(v)
        vals = np.asarray(out, dtype=np.float64)
    labels = vals.reshape(-1) == 1.0
    if n is not None and len(labels) != n:
        raise InputError(f"{p}: {len(labels)} labels, but the correspondence file has {n} rows")
    return labels


def read_correspondences(path: str | Path, labels_path: str | Path | None = None) -> Correspondences:
    """Correspondences (source, target, labels) from `px py pz qx qy qz` text and an optional label file."""
    arr = read_correspondence_array(path)
    labels = read_labels(labels_path, len(arr)) if labels_path is not None else None
    return Correspondences(src=arr[:, :3], tgt=arr[:, 3:], labels=labels)


# ----------------------------------------------------------------------------------------------------------
# 3DMatch gt.log


class GtLogEntry(NamedTuple):
    i: int  # target fragment
    j: int  # source fragment
    n: int  # fragment count of the scene
    T: np.ndarray  # 4x4, maps fragment j into fragment i
    line: int  # 1-based line of the entry header


def read_gt_log_entries(path: str | Path, rigid: bool = True) -> list[GtLogEntry]:
    """The entries of a 3DMatch gt.log with their line numbers; `rigid=False` defers the rigidity check
    (to `check_rigid`) so that one bad matrix fails only its own pair."""
    p = _path(path, "gt.log")
    lines = list(_lines(p))
    if len(lines) % 5:
        raise InputError(
            f"{p}: {len(lines)} non-blank lines, not a multiple of 5 "
            "(each entry is a line 'i j n' then 4 matrix rows)"
        )
    out = []
    for e in range(0, len(lines), 5):
        k, s = lines[e]
        head = s.split()
        if len(head) != 3 or not all(h.lstrip("-").isdigit() for h in head):
            raise InputError(f"{p}, line {k}: expected an entry header 'i j n' (three integers), got {s!r}")
        i, j, n = (int(h) for h in head)
        rows = []
        for k2, s2 in lines[e + 1 : e + 5]:
            vals = _parse_floats(s2.split(), p, k2)
            if len(vals) != 4:
                raise InputError(
                    f"{p}, line {k2}: expected 4 numbers (a row of a 4x4 matrix), got {len(vals)}"
                )
            rows.append(vals)
        t = np.asarray(rows, dtype=np.float64)
        if rigid:
            t = check_rigid(t, gt_log_where(p, i, j, n, k))
        out.append(GtLogEntry(i, j, n, t, k))
    return out


def gt_log_where(path: str | Path, i: int, j: int, n: int, line: int) -> str:
    return f"{path}, entry '{i} {j} {n}' (line {line})"


def read_gt_log(path: str | Path) -> list[tuple[int, int, int, np.ndarray]]:
    """Entries (i, j, n_fragments, T) of a 3DMatch gt.log, rigidity-checked.

    T maps fragment j (the source) into fragment i (the target).
    """
    return [(e.i, e.j, e.n, e.T) for e in read_gt_log_entries(path)]


# ----------------------------------------------------------------------------------------------------------
# KITTI odometry


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """(M, 4, 4) camera-0 poses from a KITTI poses/<seq>.txt (12 numbers a line); frame k is row k."""
    p = _path(path, "KITTI poses file")
    try:
        arr = _loadtxt(p, ndmin=2, comments=None)
        ok = arr.shape[1] == 12 and np.isfinite(arr).all()
    except ValueError:
        ok = False
    if not ok:
        rows = []
        for k, s in _lines(p):
            vals = _parse_floats(s.split(), p, k)
            if len(vals) != 12:
                raise InputError(f"{p}, line {k}: expected 12 numbers (a 3x4 pose), got {len(vals)}")
            if not all(math.isfinite(v) for v in vals):
                raise InputError(f"{p}, line {k}: NaN or inf")
            rows.append(vals)
        arr = np.asarray(rows, dtype=np.float64).reshape(-1, 12)
    poses = np.tile(np.eye(4), (len(arr), 1, 1))
    poses[:, :3, :] = arr.reshape(-1, 3, 4)
    r = poses[:, :3, :3]
    dev = np.abs(np.einsum("nji,njk->nik", r, r) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(r) if len(r) else np.zeros(0)
    bad = (dev > RIGID_TOL) | (det <= 0)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{p}, line {f + 1} (frame {f}): the pose's 3x3 block is not a rotation (dev {dev[f]:.2e})"
        )
    return poses


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """`KEY: numbers` lines of a KITTI calib.txt, as flat float64 arrays keyed by KEY."""
    p = _path(path, "KITTI calib file")
    out = {}
    for k, s in _lines(p):
        if ":" not in s:
            raise InputError(f"{p}, line {k}: expected 'KEY: v1 v2 ...', got {s!r}")
        key, rest = s.split(":", 1)
        out[key.strip()] = np.asarray(_parse_floats(rest.split(), p, k), dtype=np.float64)
    return out


def read_kitti_velo_to_cam(path: str | Path) -> np.ndarray:
    """The 4x4 Velodyne -> camera-0 transform `Tr` of a KITTI calib.txt (key `Tr` or `Tr_velo_to_cam`)."""
    calib = read_kitti_calib(path)
    for key in ("Tr", "Tr_velo_to_cam", "Tr_velo_cam"):
        if key in calib:
            v = calib[key]
            if v.size != 12:
                raise InputError(f"{path}: '{key}' has {v.size} numbers, expected 12 (a 3x4 matrix)")
            t = np.eye(4)
            t[:3, :] = v.reshape(3, 4)
            return check_rigid(t, f"{path}: {key}")
    raise InputError(f"{path}: no 'Tr:' line (Velodyne -> camera 0); keys present: {sorted(calib)}")


def kitti_velo_gt(p_src: np.ndarray, p_tgt: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """Source -> target transform in the Velodyne frame: inv(Tr) inv(P_tgt) P_src Tr."""
    return np.linalg.inv(tr) @ np.linalg.inv(p_tgt) @ p_src @ tr
