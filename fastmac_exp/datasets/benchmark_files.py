"""Readers of the benchmarks' own files: 3DMatch's gt.log and KITTI odometry's poses and calib.txt.

Formats:
- 3DMatch gt.log: `i j n` then four lines of a 4x4 T mapping fragment j (source) into fragment i (target);
- KITTI poses: one line of 12 numbers per frame (row-major 3x4 camera-0 pose in the frame of frame 0);
- KITTI calib.txt: `KEY: v1 ... v12` lines; `Tr` is the Velodyne -> camera-0 transform.
Errors are fastmac_exp.errors.InputError naming the file and the line.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.geometry.transforms import RIGID_TOL, check_rigid, rotation_deviation
from fastmac_exp.io import file_path, loadtxt, parse_floats, text_lines


# -- 3DMatch gt.log ---------------------------------------------------------------------------------------
class GtLogEntry(NamedTuple):
    i: int  # target fragment
    j: int  # source fragment
    n: int  # fragment count of the scene
    T: np.ndarray  # 4x4, maps fragment j into fragment i
    line: int  # 1-based line of the entry header


def read_gt_log_entries(path: str | Path, rigid: bool = True) -> list[GtLogEntry]:
    """The entries of a 3DMatch gt.log with their line numbers; `rigid=False` defers the rigidity check
    (to `check_rigid`) so that one bad matrix fails only its own pair."""
    p = file_path(path, "gt.log")
    lines = list(text_lines(p))
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
            vals = parse_floats(s2.split(), p, k2)
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


# -- KITTI odometry ---------------------------------------------------------------------------------------
def read_kitti_poses(path: str | Path) -> np.ndarray:
    """(M, 4, 4) camera-0 poses from a KITTI poses/<seq>.txt (12 numbers a line); frame k is row k."""
    p = file_path(path, "KITTI poses file")
    try:
        arr = loadtxt(p, ndmin=2, comments=None)
        ok = arr.shape[1] == 12 and np.isfinite(arr).all()
    except ValueError:
        ok = False
    if not ok:
        rows = []
        for k, s in text_lines(p):
            vals = parse_floats(s.split(), p, k)
            if len(vals) != 12:
                raise InputError(f"{p}, line {k}: expected 12 numbers (a 3x4 pose), got {len(vals)}")
            if not all(math.isfinite(v) for v in vals):
                raise InputError(f"{p}, line {k}: NaN or inf")
            rows.append(vals)
        arr = np.asarray(rows, dtype=np.float64).reshape(-1, 12)
    poses = np.tile(np.eye(4), (len(arr), 1, 1))
    poses[:, :3, :] = arr.reshape(-1, 3, 4)
    dev, det = rotation_deviation(poses[:, :3, :3])
    bad = (dev > RIGID_TOL) | (det <= 0)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{p}, line {f + 1} (frame {f}): the pose's 3x3 block is not a rotation (dev {dev[f]:.2e})"
        )
    return poses


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """`KEY: numbers` lines of a KITTI calib.txt, as flat float64 arrays keyed by KEY."""
    p = file_path(path, "KITTI calib file")
    out = {}
    for k, s in text_lines(p):
        if ":" not in s:
            raise InputError(f"{p}, line {k}: expected 'KEY: v1 v2 ...', got {s!r}")
        key, rest = s.split(":", 1)
        out[key.strip()] = np.asarray(parse_floats(rest.split(), p, k), dtype=np.float64)
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
