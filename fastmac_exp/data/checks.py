"""Structure checks of a data set in its folder, against the benchmark's protocol: every fragment, scan
and pair its GT names is there and readable, with a plausible point count. A check returns a one-line
summary, or raises InputError listing what is wrong (the first few problems and their count)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from fastmac_exp.data.kitti import KITTI_SEQUENCES, fcgf_test_pairs
from fastmac_exp.datasets.benchmark_files import read_gt_log_entries, read_kitti_poses, read_kitti_velo_to_cam
from fastmac_exp.datasets.mac_layout import SCENES_3DMATCH, KittiMAC, ThreeDLoMatchMAC, ThreeDMatchMAC
from fastmac_exp.errors import InputError

MIN_POINTS = 1000  # a 3DMatch fragment holds 10^5-10^6 points, a KITTI scan ~1.2 x 10^5
PLY_SIZES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}


def ply_points(path: Path) -> int:
    """The vertex count of a PLY file, checked against the file's length for binary PLY."""
    with open(path, "rb") as f:
        head = f.read(4096)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    lines = head[:end].decode("ascii", "replace").splitlines()
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ")), "")
    count, stride, element = None, 0, None
    for ln in lines:
        parts = ln.split()
        if parts[:1] == ["element"]:
            element = parts[1] if len(parts) > 1 else None
            if element == "vertex":
                count = int(parts[2])
        elif parts[:1] == ["property"] and element == "vertex" and len(parts) == 3:
            stride += PLY_SIZES.get(parts[1], 0)
    if count is None:
        raise InputError(f"{path}: PLY header without 'element vertex'")
    if fmt.startswith("binary") and stride and element == "vertex":
        body = path.stat().st_size - (end + len(b"end_header") + 1)
        if body < count * stride:
            raise InputError(f"{path}: truncated: {count} vertices need {count * stride} bytes, {body} there")
    return count


def _fail(what: str, problems: list[str]) -> None:
    if problems:
        more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
        raise InputError(f"{what}: {len(problems)} problem(s): " + "; ".join(problems[:5]) + more)


def _gt_log(folder: Path, scene: str) -> Path:
    for cand in (folder / f"{scene}-evaluation" / "gt.log", folder / scene / "gt.log"):
        if cand.is_file():
            return cand
    raise InputError(
        f"{folder}: no gt.log for scene {scene} (looked for {scene}-evaluation/gt.log, {scene}/gt.log)"
    )


def _fragments_named(log: Path, frag_dir: Path, problems: list[str], seen: dict[Path, int]) -> int:
    """Check the fragments a gt.log names (all n of its scene); the number of pairs it lists."""
    entries = read_gt_log_entries(log)
    if not entries:
        problems.append(f"{log}: no pairs")
        return 0
    n = max(e.n for e in entries)
    for k in range(n):
        f = frag_dir / f"cloud_bin_{k}.ply"
        if f in seen:
            continue
        if not f.is_file():
            problems.append(f"{f} missing (named by {log})")
            seen[f] = 0
            continue
        try:
            seen[f] = ply_points(f)
        except InputError as exc:
            problems.append(str(exc))
            seen[f] = 0
            continue
        if seen[f] < MIN_POINTS:
            problems.append(f"{f}: {seen[f]} points, fewer than a fragment has ({MIN_POINTS}+)")
    return len(entries)


def check_fragments(folder: Path, home: Path) -> str:
    problems: list[str] = []
    seen: dict[Path, int] = {}
    pairs = 0
    for scene in SCENES_3DMATCH:
        try:
            pairs += _fragments_named(_gt_log(folder, scene), folder / scene, problems, seen)
        except InputError as exc:
            problems.append(str(exc))
    _fail(f"3dmatch in {folder}", problems)
    return f"{len(SCENES_3DMATCH)} scenes, {len(seen)} fragments, {pairs} pairs"


def check_lomatch(folder: Path, home: Path) -> str:
    frags = home / "3dmatch"
    problems: list[str] = []
    seen: dict[Path, int] = {}
    pairs = 0
    for scene in SCENES_3DMATCH:
        log = folder / scene / "gt.log"
        if not log.is_file():
            problems.append(f"{log} missing")
            continue
        pairs += _fragments_named(log, frags / scene, problems, seen)
    _fail(f"3dlomatch in {folder} (fragments in {frags})", problems)
    return f"{len(SCENES_3DMATCH)} scenes, {pairs} pairs over {len(seen)} fragments of {frags}"


def check_kitti(folder: Path, home: Path) -> str:
    root = folder / "dataset"
    problems: list[str] = []
    for seq in KITTI_SEQUENCES:
        try:
            read_kitti_velo_to_cam(root / "sequences" / f"{seq:02d}" / "calib.txt")
            read_kitti_poses(root / "poses" / f"{seq:02d}.txt")
        except InputError as exc:
            problems.append(str(exc))
    _fail(f"kitti in {folder}", problems)
    pairs = fcgf_test_pairs(root)
    scans = {(s, f) for s, a, b in pairs for f in (a, b)}
    for s, f in sorted(scans):
        p = root / "sequences" / f"{s:02d}" / "velodyne" / f"{f:06d}.bin"
        if not p.is_file():
            problems.append(f"{p} missing")
        elif p.stat().st_size % 16 or p.stat().st_size // 16 < MIN_POINTS:
            problems.append(
                f"{p}: {p.stat().st_size} bytes, not a scan of {MIN_POINTS}+ float32 x y z r points"
            )
    _fail(f"kitti in {folder}", problems)
    seqs = ", ".join(f"{s:02d}" for s in KITTI_SEQUENCES)
    return f"sequences {seqs}: {len(pairs)} pairs over {len(scans)} scans"


def _check_mac(dataset, folder: Path) -> str:
    names = dataset.names()  # raises on a missing scene folder or pair list
    problems = []
    for i in sorted({0, len(names) - 1} - {-1}):  # the first and the last pair read in full
        try:
            dataset.load(i)
        except InputError as exc:
            problems.append(str(exc))
    _fail(f"{dataset.name} in {folder}", problems)
    return f"{len(names)} pairs (descriptor {dataset.descriptor})"


def mac_descriptors(folder: Path, kitti: bool) -> list[str]:
    """The descriptors whose released correspondences a MAC-layout folder holds."""
    if kitti:
        sub = next((p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()), None)
        found = {p.name.split("@")[0] for p in sub.glob("*@corr.txt")} if sub else set()
        found |= {
            p.name.removeprefix("correspondence_") for p in folder.glob("correspondence_*") if p.is_dir()
        }
        return sorted(found)
    scenes = [p for p in sorted(folder.iterdir()) if p.is_dir()]
    out = []
    if any((p / "dataload.txt").is_file() for p in scenes):
        out.append("fpfh")
    if any((p / "dataload_fcgf.txt").is_file() for p in scenes):
        out.append("fcgf")
    return out


def _mac_checker(cls) -> Callable[[Path, Path], str]:
    def check(folder: Path, home: Path) -> str:
        kitti = cls is KittiMAC
        descs = mac_descriptors(folder, kitti)
        if not descs:
            raise InputError(
                f"{folder}: no MAC-layout correspondences (dataload.txt / <desc>@corr.txt) found"
            )
        return "; ".join(_check_mac(cls(root=folder, descriptor=d), folder) for d in descs)

    return check


CHECKS: dict[str, Callable[[Path, Path], str]] = {
    "fragments": check_fragments,
    "lomatch": check_lomatch,
    "kitti": check_kitti,
    "mac-3dmatch": _mac_checker(ThreeDMatchMAC),
    "mac-3dlomatch": _mac_checker(ThreeDLoMatchMAC),
    "mac-kitti": _mac_checker(KittiMAC),
}


def run_check(kind: str, folder: Path, home: Path) -> str:
    if kind not in CHECKS:
        raise InputError(f"no structure check named {kind!r} (known: {', '.join(CHECKS)})")
    return CHECKS[kind](folder, home)
