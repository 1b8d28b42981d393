"""File readers: point clouds, 4x4 matrices, correspondences, labels (the benchmark-specific gt.log and
KITTI files are read in fastmac_exp/datasets/benchmark_files.py).

Every reader raises fastmac_exp.errors.InputError naming the file (and the line, for row-level problems)
when the file is missing or malformed. Points come back as float64 arrays; numpy files are always read
with allow_pickle=False.

Formats (spec section 1.1):
- correspondences: one per line, `px py pz qx qy qz` (source point first), whitespace-separated, no header;
- labels: one value per line, 1 = ground-truth inlier, 0 = outlier (float spellings such as `1.0e+00`
  are accepted, as FastMAC writes them with numpy);
- matrices: four lines of four numbers (row-major, source -> target), or a (4, 4) .npy.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import stat
import warnings
from pathlib import Path

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.geometry.resolution import mesh_resolution
from fastmac_exp.geometry.transforms import check_rigid
from fastmac_exp.types import MAX_COORD, Correspondences

log = logging.getLogger(__name__)

CLOUD_EXTENSIONS = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt", ".npy", ".bin")
MATRIX_EXTENSIONS = (".txt", ".npy", ".log", ".mat", "")


# ----------------------------------------------------------------------------------------------------------
# helpers


def loadtxt(p: Path, **kw) -> np.ndarray:
    """np.loadtxt without the empty-file warning (an empty file gives an empty array)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(p, dtype=np.float64, **kw)


def file_path(path: str | Path, what: str) -> Path:
    p = Path(path).expanduser()
    if not p.exists():
        raise InputError(f"{what} not found: {p}")
    if p.is_dir():
        raise InputError(f"{what} is a directory, expected a file: {p}")
    return p


def text_lines(p: Path):
    """(1-based line number, stripped text) of the non-blank lines of a text file."""
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: not a text file ({e})") from None
    for k, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s:
            yield k, s


def parse_floats(tokens: list[str], p: Path, lineno: int) -> list[float]:
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
        arr = loadtxt(p, ndmin=2, comments="#")
        if arr.size == 0:
            return np.zeros((0, 3))
        if arr.shape[1] >= 3:
            return arr[:, :3]
    except ValueError:
        pass
    # slow path: find the offending line
    rows = []
    ncols = None
    for k, s in text_lines(p):
        if s.startswith("#"):
            continue
        vals = parse_floats(s.split(), p, k)
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
    xyz = np.fromfile(p, dtype="<f4").reshape(-1, 4)[:, :3]
    # Another dtype read as float32 (int16, uint8 ...) gives mostly subnormal or absurd values, where a
    # scan's non-zero coordinates are ordinary floats.
    nonzero = xyz[xyz != 0]
    odd = ~np.isfinite(nonzero) | (np.abs(nonzero) < 1e-30) | (np.abs(nonzero) > MAX_COORD)
    if len(nonzero) and odd.mean() > 0.05:
        raise InputError(
            f"{p}: {100 * odd.mean():.0f}% of its coordinates are no plausible float32 values (subnormal, "
            "non-finite or beyond 1e6); a KITTI .bin holds float32 rows (x, y, z, reflectance): is the file "
            "another dtype (int16, float64)?"
        )
    return xyz.astype(np.float64)


PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2,
             "uint16": 2, "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4,
             "double": 8, "float64": 8}  # fmt: skip


def ply_header(p: Path) -> tuple[str, list[tuple[str, int, int | None]], int]:
    """(format, [(element, count, bytes a row or None when it has list properties)], header bytes)."""
    with open(p, "rb") as f:
        head = f.read(1 << 16)
    end = head.find(b"end_header")
    if end < 0:
        raise InputError(f"{p}: PLY header without end_header")
    body = head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head)
    fmt, elements = "", []
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            try:
                elements.append([words[1], int(words[2]), 0])
            except ValueError:
                raise InputError(f"{p}: PLY header line {line!r}: the count is not a number") from None
        elif words[:1] == ["property"] and elements and elements[-1][2] is not None:
            if words[1:2] == ["list"] or len(words) < 3 or words[1] not in PLY_SIZES:
                elements[-1][2] = None
            else:
                elements[-1][2] += PLY_SIZES[words[1]]
    return fmt, [tuple(e) for e in elements], body


def data_lines(p: Path, start: int) -> int:
    """Non-empty lines of p after byte `start` (an ascii body's rows)."""
    with open(p, "rb") as f:
        f.seek(start)
        return sum(1 for line in f if line.strip())


def check_ply_body(p: Path) -> int | None:
    """The vertex count a PLY header declares (None: no vertex element); a body too short for the vertices
    (a truncated file, which Open3D fills with uninitialised rows) is an InputError."""
    fmt, elements, start = ply_header(p)
    need_bytes = need_lines = 0
    for name, count, row in elements:
        need_lines += count  # ascii: a line a row
        need_bytes = None if row is None or need_bytes is None else need_bytes + count * row
        if name != "vertex":
            continue
        if fmt == "ascii":
            if (have := data_lines(p, start)) < need_lines:
                raise InputError(
                    f"{p}: truncated: its header declares {count} vertices, the file has {have} data lines"
                )
        elif need_bytes is not None and (have := p.stat().st_size - start) < need_bytes:
            raise InputError(
                f"{p}: truncated: its header declares {count} vertices ({need_bytes} bytes of body up to "
                f"them), the file has {have} bytes after the header"
            )
        return count
    return None


def check_pcd_body(p: Path) -> int | None:
    """The point count a PCD header declares; a body too short for it (binary: bytes, ascii: lines) is an
    InputError. binary_compressed bodies are left to Open3D (their size is not fixed by the header)."""
    with open(p, "rb") as f:
        head = f.read(1 << 16)
    fields: dict[str, list[str]] = {}
    pos = 0
    for raw in head.split(b"\n"):
        pos += len(raw) + 1
        words = raw.decode("ascii", errors="replace").split()
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
        if words[:1] == ["DATA"]:
            break
    else:
        return None
    try:
        points = int(fields["POINTS"][0])
        row = sum(int(a) * int(b) for a, b in zip(fields["SIZE"], fields.get("COUNT", ["1"] * 99)))
    except (KeyError, IndexError, ValueError):
        return None
    kind = fields["DATA"][0].lower() if fields["DATA"] else ""
    if kind == "binary" and (have := p.stat().st_size - pos) < points * row:
        raise InputError(
            f"{p}: truncated: its header declares {points} points ({points * row} bytes), the file has "
            f"{have} bytes after the header"
        )
    if kind == "ascii" and (have := data_lines(p, pos)) < points:
        raise InputError(f"{p}: truncated: its header declares {points} points, the file has {have} lines")
    return points


def _read_o3d(p: Path) -> np.ndarray:
    with open(p, "rb") as f:
        head = f.read(64)
    if p.suffix.lower() == ".ply" and not head.lstrip().lower().startswith(b"ply"):
        raise InputError(
            f"{p}: not a PLY file (it does not start with 'ply'); "
            "for headerless 'x y z' text use the .xyz or .txt extension"
        )
    declared = check_ply_body(p) if p.suffix.lower() == ".ply" else check_pcd_body(p)
    from fastmac_exp._open3d import o3d

    pcd = o3d.io.read_point_cloud(str(p))
    pts = np.asarray(pcd.points, dtype=np.float64)
    if declared is not None and len(pts) != declared:
        raise InputError(
            f"{p}: its header declares {declared} vertices, {len(pts)} could be read (truncated?)"
        )
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
    p = file_path(path, "point cloud file")
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


def clean_cloud(
    points: np.ndarray, where: str, drop_zeros: bool = True, keep_zeros: str = ""
) -> tuple[np.ndarray, int]:
    """Drop non-finite rows (missing returns in organised clouds) and, if asked, points exactly at (0, 0, 0)
    (invalid LiDAR returns, e.g. small_gicp's scans); raise on coordinates beyond 1e6 m or an empty result.
    A drop is logged as a warning with its counts and reasons (`keep_zeros`: how to keep the zeros).

    Returns (points, number dropped).
    """
    check_points(points, where, allow_nonfinite=True)
    finite = np.isfinite(points).all(axis=1)
    keep = finite & np.any(points != 0.0, axis=1) if drop_zeros else finite
    n_drop = int(len(points) - keep.sum())
    out = np.ascontiguousarray(points[keep]) if n_drop else points
    if len(out) == 0:
        raise InputError(f"{where}: no valid points (read {len(points)}, all NaN/inf or exactly zero)")
    if n_drop:
        why = []
        if n_bad := int(len(points) - finite.sum()):
            why.append(f"{n_bad} not finite (NaN/inf)")
        if n_zero := n_drop - n_bad:
            why.append(f"{n_zero} exactly at (0, 0, 0), taken for invalid LiDAR returns" + (
                f" ({keep_zeros})" if keep_zeros else ""))  # fmt: skip
        log.warning("%s: read %d points, dropped %d: %s", where, len(points), n_drop, "; ".join(why))
    return out, n_drop


def check_input_file(path: Path) -> str | None:
    """What is wrong with an input file that can be told without reading it through (None: nothing):
    missing, a directory, empty, unreadable, or a .ply without the 'ply' magic. A FIFO or device is left
    alone: reading it would consume it."""
    if not path.exists():
        return "no such file"
    if path.is_dir():
        return "a directory, not a file"
    if not stat.S_ISREG(path.stat().st_mode):
        return None
    if path.stat().st_size == 0:
        return "an empty file (0 bytes)"
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as e:
        return f"cannot be read ({os.strerror(e.errno) if e.errno else e})"
    if path.suffix.lower() == ".ply" and not head.lstrip().lower().startswith(b"ply"):
        return "not a PLY file (it does not start with 'ply'; headerless 'x y z' text wants .xyz or .txt)"
    return None


def load_cloud(path: str | Path, drop_zeros: bool = True) -> np.ndarray:
    """A point-cloud file as the CLI reads it (`fastmac_exp.load_cloud`): .ply / .pcd (Open3D), .npy (N, 3+),
    KITTI .bin (float32 x y z reflectance), .xyz / .txt / .pts text (the first three columns); NaN/inf rows
    and, with `drop_zeros`, points exactly at the origin are dropped with a warning that counts them.
    Returns a finite, non-empty (N, 3) float64 array; a bad file raises InputError naming it."""
    return clean_cloud(read_points(path), str(path), drop_zeros)[0]


# ----------------------------------------------------------------------------------------------------------
# matrices


def read_matrix(path: str | Path, rigid: bool = True) -> np.ndarray:
    """A 4x4 matrix from a text file (four lines of four numbers) or a .npy; rigidity-checked by default."""
    p = file_path(path, "matrix file")
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
        for k, s in text_lines(p):
            vals = parse_floats(s.split(), p, k)
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
    for k, s in text_lines(p):
        toks = s.split()
        if len(toks) != 6:
            raise InputError(f"{p}, line {k}: expected 6 numbers (px py pz qx qy qz), got {len(toks)}")
        vals = parse_floats(toks, p, k)
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
    p = file_path(path, "correspondence file")
    try:
        arr = loadtxt(p, ndmin=2, comments=None)
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
    p = file_path(path, "label file")
    try:
        vals = loadtxt(p, ndmin=1, comments=None)
        ok = vals.ndim == 1 and np.isin(vals, (0.0, 1.0)).all()
    except ValueError:
        ok = False
    if not ok:
        out = []
        for k, s in text_lines(p):
            toks = s.split()
            if len(toks) != 1:
                raise InputError(f"{p}, line {k}: expected one label (0 or 1), got {len(toks)} values")
            v = parse_floats(toks, p, k)[0]
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


@functools.lru_cache(maxsize=512)
def _file_resolution(path: str, mtime_ns: int, size: int) -> float:
    return mesh_resolution(load_cloud(Path(path)))


def file_resolution(path: str | Path) -> float:
    """mr of a cloud file, remembered per (path, modification time, size): fragments recur across pairs."""
    st = Path(path).stat()
    return _file_resolution(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)
