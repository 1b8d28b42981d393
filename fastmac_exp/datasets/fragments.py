"""Raw benchmark inputs: 3DMatch/3DLoMatch fragments with the official gt.log, and KITTI odometry scans.

These pairs carry point clouds and a GT but no correspondences: the configured descriptor front end
(fpfh, onnx, ...) computes them.

3DMatch / 3DLoMatch fragments (the 3DMatch geometric-registration test set)::

    <root>/<scene>/cloud_bin_<k>.ply
    <root>/<scene>/gt.log   or  <gt_root>/<scene>/gt.log  or  <root>/<scene>-evaluation/gt.log

Each gt.log entry `i j n` + T gives one pair: source = cloud_bin_j, target = cloud_bin_i, GT = T (it maps
fragment j into fragment i). 3DLoMatch uses the same fragments with its own gt.log (`gt_root` pointing at
e.g. GeoTransformer's `metadata/benchmarks/3DLoMatch`, and `family=3dlomatch`).

KITTI odometry (the official `dataset/` folder)::

    <root>/sequences/<seq>/velodyne/<frame>.bin   float32 (N, 4) x y z reflectance, Velodyne frame
    <root>/sequences/<seq>/calib.txt              line `Tr:` = Velodyne -> camera 0 (3x4)
    <root>/poses/<seq>.txt                        camera-0 pose of every frame (3x4 a line)

GT of source -> target in the Velodyne frame: inv(Tr) inv(P_tgt) P_src Tr. These are the raw odometry poses;
FCGF (whose pairs MAC's KITTI release uses) additionally refines each GT with ICP, so expect raw-pose GTs
to be off by up to a few tens of centimetres on some pairs.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fastmac_exp.datasets.benchmark_files import (
    GtLogEntry,
    gt_log_where,
    kitti_velo_gt,
    read_gt_log_entries,
    read_kitti_poses,
    read_kitti_velo_to_cam,
)
from fastmac_exp.datasets.mac_layout import (
    LOMATCH_SUFFIX,
    SCENES_3DMATCH,
)
from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES, check_family, family
from fastmac_exp.geometry.resolution import COMPUTED_FAMILIES, FIXED_RESOLUTION
from fastmac_exp.geometry.transforms import check_rigid
from fastmac_exp.io import file_resolution, load_cloud
from fastmac_exp.types import Pair

FRAGMENTS_WHERE = (
    "Get the data: the 3DMatch geometric-registration test fragments (https://3dmatch.cs.princeton.edu, "
    "'Geometric Registration Benchmark': <scene>/cloud_bin_*.ply and <scene>-evaluation/gt.log); the "
    "3DLoMatch gt.log files ship with Predator/GeoTransformer (metadata/benchmarks/3DLoMatch/<scene>/gt.log)."
)
KITTI_WHERE = (
    "Get the data: the KITTI odometry benchmark (https://www.cvlibs.net/datasets/kitti/eval_odometry.php): "
    "'velodyne laser data', 'calibration files' and 'ground truth poses', unpacked into one dataset/ folder."
)

# FCGF's test protocol drops this pair as wrong (and MAC's 555 KITTI pairs follow FCGF's list).
FCGF_EXCLUDED = ((8, 15, 58),)


def _layout_fragments(scenes: Sequence[str]) -> str:
    s = scenes[0] if scenes else SCENES_3DMATCH[0]
    return (
        "  <root>/\n"
        f"    {s}/\n"
        "      cloud_bin_0.ply  cloud_bin_1.ply  ...\n"
        "      gt.log           entries 'i j n' + 4x4 T mapping cloud_bin_j (source) into cloud_bin_i\n"
        f"  (or the gt.log in <gt_root>/{s}/gt.log or <root>/{s}-evaluation/gt.log)\n"
    )


LAYOUT_KITTI_RAW = (
    "  <root>/\n"
    "    sequences/08/velodyne/000000.bin ...   float32 x y z reflectance\n"
    "    sequences/08/calib.txt                 with a line 'Tr: <12 numbers>' (Velodyne -> camera 0)\n"
    "    poses/08.txt                           one 3x4 camera-0 pose (12 numbers) per frame\n"
)


def _missing(title: str, where: str, layout: str, config: str, root) -> InputError:
    what = "is not set" if root is None else f"points to {root}, which does not exist or is not a folder"
    return InputError(
        f"{title}: dataset.root {what}.\n{where}\nExpected layout:\n{layout}"
        f"Point to it: python run.py dataset={config} dataset.root=/path/to/data"
    )


class Fragments3DMatch:
    """3DMatch (or 3DLoMatch) fragment pairs from gt.log; names `<scene>/cloud_bin_<j>+cloud_bin_<i>`
    (source first, as MAC names pairs), in scene order then gt.log order."""

    def __init__(
        self,
        root: str | Path | None = None,
        gt_root: str | Path | None = None,
        scenes: Sequence[str] | None = None,
        family: str = "3dmatch",
        voxel_size: float = FAMILIES["3dmatch"].voxel_size,
        resolution: float | None = None,
    ) -> None:
        self.root = root
        self.gt_root = gt_root
        self.scenes = list(scenes) if scenes is not None else list(SCENES_3DMATCH)
        self.family = family
        self.name = f"fragments_{family}"
        self.voxel_size = float(voxel_size)
        self.resolution = None if resolution is None else float(resolution)  # None: from the clouds
        self._entries: list[tuple[str, Path, Path, GtLogEntry]] | None = None

    def _title(self) -> str:
        return f"{self.name} (raw 3DMatch fragments + gt.log)"

    def _resolution(self, files: list[Path]) -> float:
        """As MAC: the mean of the two fragments' mesh resolutions (each computed once per file)."""
        if self.resolution is not None:
            return self.resolution
        if self.family not in COMPUTED_FAMILIES:
            return FIXED_RESOLUTION
        return 0.5 * (file_resolution(files[0]) + file_resolution(files[1]))

    def _gt_log(self, root: Path, scene: str) -> Path:
        bases = [Path(self.gt_root).expanduser()] if self.gt_root is not None else []
        bases.append(root)
        names = [scene]
        if self.family == "3dlomatch" and not scene.endswith(LOMATCH_SUFFIX):
            names.append(scene + LOMATCH_SUFFIX)
        cands = [b / n / "gt.log" for b in bases for n in names] + [root / f"{scene}-evaluation" / "gt.log"]
        for c in cands:
            if c.is_file():
                return c
        raise InputError(
            f"{self._title()}: no gt.log for scene {scene!r}; looked at:\n  "
            + "\n  ".join(str(c) for c in cands)
            + f"\n{FRAGMENTS_WHERE}\nExpected layout:\n{_layout_fragments(self.scenes)}"
            "Set dataset.gt_root=/path/to/benchmark/gt/folders if the logs live elsewhere."
        )

    def _index(self) -> list[tuple[str, Path, Path, GtLogEntry]]:
        if self._entries is not None:
            return self._entries
        check_family(self.family)
        if self.family == "kitti":
            raise InputError("fragments: family must be 3dmatch or 3dlomatch (use kitti_raw for KITTI)")
        if self.root is None or not Path(self.root).expanduser().is_dir():
            raise _missing(
                self._title(), FRAGMENTS_WHERE, _layout_fragments(self.scenes), "fragments_3dmatch", self.root
            )
        root = Path(self.root).expanduser()
        if not self.scenes:
            raise InputError(f"{self._title()}: scenes is empty; pass null for all 8 or a list of names")
        missing = [s for s in self.scenes if not (root / s).is_dir()]
        if missing:
            raise InputError(
                f"{self._title()}: scene folder(s) missing under {root}: {', '.join(missing)}.\n"
                f"Expected layout:\n{_layout_fragments(self.scenes)}"
                "Choose scenes with dataset.scenes=[name,...]."
            )
        out = []
        for s in self.scenes:
            log = self._gt_log(root, s)
            out += [(s, root / s, log, e) for e in read_gt_log_entries(log, rigid=False)]
        self._entries = out
        return out

    def names(self) -> list[str]:
        return [f"{s}/cloud_bin_{e.j}+cloud_bin_{e.i}" for s, _, _, e in self._index()]

    def __len__(self) -> int:
        return len(self._index())

    def load(self, index: int) -> Pair:
        entries = self._index()
        if not 0 <= index < len(entries):
            raise IndexError(f"{self.name}: pair index {index} out of range (0..{len(entries) - 1})")
        scene, d, log, e = entries[index]
        name = f"{scene}/cloud_bin_{e.j}+cloud_bin_{e.i}"
        gt = check_rigid(e.T, gt_log_where(log, e.i, e.j, e.n, e.line))
        clouds, files = [], []
        for k in (e.j, e.i):
            f = d / f"cloud_bin_{k}.ply"
            files.append(f)
            if not f.is_file():
                raise InputError(
                    f"pair {name!r}: fragment missing: {f} (expected cloud_bin_{k}.ply in {d}, named by "
                    f"{log} line {e.line}).\nExpected layout:\n{_layout_fragments(self.scenes)}"
                )
            clouds.append(load_cloud(f))
        return Pair(
            name=name,
            family=self.family,
            gt=gt,
            src_cloud=clouds[0],
            tgt_cloud=clouds[1],
            voxel_size=self.voxel_size,
            resolution=self._resolution(files),
            scene=scene,
            meta={"source": f"cloud_bin_{e.j}", "target": f"cloud_bin_{e.i}", "gt_log": str(log)},
            **family(self.family).thresholds(),
        )


def fcgf_pairs(
    poses: np.ndarray, frames: Sequence[int], min_distance: float = 10.0, window: int = 100
) -> list[tuple[int, int]]:
    """FCGF's KITTI pair rule for one sequence, as its code behaves.

    From the first frame: look at frames curr..curr+window-1 for the first whose camera position lies more
    than `min_distance` from curr's; the pair is (curr, that frame - 1) -- the last frame still within
    `min_distance`, so pairs end up just under 10 m apart -- and the search resumes after it. If no frame in
    the window is far enough, curr advances by one. The walk stops at the first frame missing on disk.
    """
    have = set(int(f) for f in frames)
    if not have:
        return []
    pos = poses[:, :3, 3]
    out = []
    curr = min(have)
    while curr in have:
        seg = pos[curr : curr + window]
        far = np.flatnonzero(np.linalg.norm(seg - pos[curr], axis=1) > min_distance)
        if len(far) == 0:
            curr += 1
            continue
        nxt = curr + int(far[0]) - 1
        if nxt in have:
            out.append((curr, nxt))
            curr = nxt + 1
        else:  # FCGF leaves curr unchanged here and loops forever; move on instead
            curr += 1
    return out


class KittiRaw:
    """KITTI odometry scan pairs; names `<seq>/<src>+<tgt>` (e.g. `08/000000+000011`), source first.

    `pairs`: an explicit list of [seq, source frame, target frame]; when None, FCGF's test protocol over
    `sequences` (default 8, 9, 10; see `fcgf_pairs`, minus FCGF's excluded (8, 15, 58)).
    """

    name = "kitti_raw"
    family = "kitti"

    def __init__(
        self,
        root: str | Path | None = None,
        pairs: Sequence[Sequence[int]] | None = None,
        sequences: Sequence[int] = (8, 9, 10),
        min_distance: float = 10.0,
        voxel_size: float = FAMILIES["kitti"].voxel_size,
    ) -> None:
        self.root = root
        self.pairs = pairs
        self.sequences = sequences
        self.min_distance = float(min_distance)
        self.voxel_size = float(voxel_size)
        self._entries: list[tuple[int, int, int]] | None = None
        self._poses: dict[int, np.ndarray] = {}
        self._tr: dict[int, np.ndarray] = {}

    def _title(self) -> str:
        return "kitti_raw (KITTI odometry scans + poses + calib)"

    def _root(self) -> Path:
        if self.root is None or not Path(self.root).expanduser().is_dir():
            raise _missing(self._title(), KITTI_WHERE, LAYOUT_KITTI_RAW, "kitti_raw", self.root)
        return Path(self.root).expanduser()

    def _file(self, path: Path, what: str) -> Path:
        if not path.is_file():
            raise InputError(
                f"{self._title()}: {what} missing: {path}.\nExpected layout:\n{LAYOUT_KITTI_RAW}"
            )
        return path

    def _velo(self, seq: int, frame: int) -> Path:
        return self._root() / "sequences" / f"{seq:02d}" / "velodyne" / f"{frame:06d}.bin"

    def poses(self, seq: int) -> np.ndarray:
        if seq not in self._poses:
            self._poses[seq] = read_kitti_poses(
                self._file(self._root() / "poses" / f"{seq:02d}.txt", "poses")
            )
        return self._poses[seq]

    def velo_to_cam(self, seq: int) -> np.ndarray:
        if seq not in self._tr:
            f = self._root() / "sequences" / f"{seq:02d}" / "calib.txt"
            self._tr[seq] = read_kitti_velo_to_cam(self._file(f, "calibration"))
        return self._tr[seq]

    @staticmethod
    def _ints(v, what: str) -> list[int]:
        try:
            return [int(x) for x in v]
        except (TypeError, ValueError):
            raise InputError(f"kitti_raw: {what} must be integers, got {v!r}") from None

    def _index(self) -> list[tuple[int, int, int]]:
        if self._entries is not None:
            return self._entries
        root = self._root()
        if self.pairs is not None:
            out = []
            for p in self.pairs:
                t = self._ints(p, "each pair [seq, source, target]")
                if len(t) != 3 or min(t) < 0:
                    raise InputError(
                        f"kitti_raw: each pair must be [seq, source frame, target frame], got {p!r}"
                    )
                out.append((t[0], t[1], t[2]))
        else:
            out = []
            for seq in self._ints(self.sequences, "sequences"):
                vdir = root / "sequences" / f"{seq:02d}" / "velodyne"
                if not vdir.is_dir():
                    raise InputError(
                        f"{self._title()}: scan folder missing: {vdir}.\n{KITTI_WHERE}\n"
                        f"Expected layout:\n{LAYOUT_KITTI_RAW}"
                    )
                frames = sorted(int(f.stem) for f in vdir.glob("*.bin") if f.stem.isdigit())
                poses = self.poses(seq)
                frames = [f for f in frames if f < len(poses)]
                out += [
                    (seq, a, b)
                    for a, b in fcgf_pairs(poses, frames, self.min_distance)
                    if (seq, a, b) not in FCGF_EXCLUDED
                ]
            if not out:
                raise InputError(f"{self._title()}: no pairs found in sequences {list(self.sequences)}")
        self._entries = out
        return out

    def names(self) -> list[str]:
        return [f"{s:02d}/{a:06d}+{b:06d}" for s, a, b in self._index()]

    def __len__(self) -> int:
        return len(self._index())

    def load(self, index: int) -> Pair:
        entries = self._index()
        if not 0 <= index < len(entries):
            raise IndexError(f"kitti_raw: pair index {index} out of range (0..{len(entries) - 1})")
        seq, a, b = entries[index]
        name = f"{seq:02d}/{a:06d}+{b:06d}"
        poses = self.poses(seq)
        for f in (a, b):
            if f >= len(poses):
                raise InputError(
                    f"pair {name!r}: frame {f} has no pose (poses/{seq:02d}.txt has {len(poses)})"
                )
        tr = self.velo_to_cam(seq)
        gt = check_rigid(kitti_velo_gt(poses[a], poses[b], tr), f"pair {name!r}: GT from poses and calib")
        src = load_cloud(self._file(self._velo(seq, a), "scan"))
        tgt = load_cloud(self._file(self._velo(seq, b), "scan"))
        return Pair(
            name=name,
            family="kitti",
            gt=gt,
            src_cloud=src,
            tgt_cloud=tgt,
            voxel_size=self.voxel_size,
            scene=f"{seq:02d}",
            meta={
                "source": f"{a:06d}",
                "target": f"{b:06d}",
                "distance_m": float(np.linalg.norm(poses[a][:3, 3] - poses[b][:3, 3])),
            },
            **FAMILIES["kitti"].thresholds(),
        )
