"""Any two point clouds as a dataset, and the real scan pairs stored in ../shared/data.

`UserPairs`: source/target files in ply, pcd, xyz/txt, npy or KITTI .bin, with an optional 4x4 GT
(text or .npy, source -> target). Without a GT the pair still registers; its metrics stay empty.

`SharedRealPairs`: the pairs indexed by `pairs.json` (see shared/data/README.md and MANIFEST.md).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.families import FIXED_RESOLUTION, check_family, family
from fastmac_exp.geometry.resolution import timed_resolution_for
from fastmac_exp.io import check_input_file, clean_cloud, read_matrix, read_points
from fastmac_exp.types import Pair

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]  # the folder holding the fastmac_exp package

# The bunny (Stanford range scans, ~15 cm across, scan spacing ~0.5 mm) runs under the 3DMatch rules
# rescaled to its size. The indoor pairs run at voxel 0.05 m with a 0.1 m inlier threshold (2 voxels),
# 0.3 m TE (6 voxels) and resolution 0.006 m; rooms are ~3 m across, so the bunny is ~20-25x smaller.
# Scaling by 1/25 gives voxel 0.002 m (~4 scan spacings, so FPFH still sees a few hundred keypoints,
# and inside the 1-2 mm the data README recommends), an inlier threshold of 0.005 m (2.5 voxels; the
# GT is exact to ~0.4 mm, so this is loose enough for FPFH keypoint noise and tight enough to reject
# wrong matches on a 15 cm object), TE 0.01 m (the 30 cm/3 m ratio would give 1.5 cm; 1 cm keeps a
# success meaningful on a 5 cm GT translation) and resolution 0.006/25 = 0.00024 m, so that the Gaussian
# kernel (alpha = 10 res) keeps the same ratio to the voxel as indoors. Rotation error is scale-free:
# 15 deg stays.
OBJECT_RULES = {
    "family": "3dmatch",
    "voxel_size": 0.002,
    "inlier_threshold": 0.005,
    "re_thresh_deg": 15.0,
    "te_thresh_m": 0.01,
    "resolution": FIXED_RESOLUTION / 25,
    # the sampler's fixed resolution rescaled the same way: at 0.006 m (alpha 6 cm on a 15 cm object) the
    # sampling graph was nearly complete and its exact scores took ~1.4 s a pair (issue 29)
    "sampler_resolution": FIXED_RESOLUTION / 25,
}


def _load(path: Path, what: str, drop_zeros: bool, keep_zeros: str = "") -> tuple[np.ndarray, int]:
    """(cleaned points, number of points dropped)."""
    return clean_cloud(read_points(path), f"{what} {path}", drop_zeros, keep_zeros)


KEEP_ZEROS = "dataset.drop_zeros=false keeps them"


def _as_list(v, what: str) -> list:
    if v is None:
        return []
    if isinstance(v, str | Path):
        return [v]
    try:
        return list(v)
    except TypeError:
        raise InputError(f"{what} must be a path or a list of paths, got {v!r}") from None


# Clouds wider than this (the larger bounding-box side of either) under the indoor rules get a warning: a
# 3DMatch fragment is 3-6 m across, a KITTI scan ~100 m.
OUTDOOR_EXTENT_M = 30.0


def infer_family(src_file: Path, tgt_file: Path, src: np.ndarray, tgt: np.ndarray) -> tuple[str, str]:
    """family=auto: (family, why, for the log line). KITTI .bin files are Velodyne scans: kitti; anything
    else takes the indoor rules (3dmatch), and the reason says so, with a warning's word where the clouds
    look like outdoor scans."""
    if src_file.suffix.lower() == ".bin" or tgt_file.suffix.lower() == ".bin":
        return "kitti", "the files are KITTI Velodyne .bin scans; dataset.family=3dmatch for the indoor rules"
    extent = max(float(np.ptp(src, axis=0).max()), float(np.ptp(tgt, axis=0).max()))
    if extent > OUTDOOR_EXTENT_M:
        return "3dmatch", (
            f"the indoor rules, but the clouds span {extent:.0f} m: outdoor scans? dataset.family=kitti "
            "for the outdoor rules"
        )
    return "3dmatch", f"the clouds span {extent:.1f} m: indoor rules; dataset.family=kitti for outdoor scans"


class UserPairs:
    """One pair (or several, given lists of equal length) of point-cloud files.

    `source`/`target`: paths (relative ones to the working directory); `gt`: a 4x4 file mapping source into
    target, or None. `family` picks the thresholds ("3dmatch", "3dlomatch", "kitti"; "auto", the default:
    kitti for KITTI .bin files, else 3dmatch, said on the log with the reason); `voxel_size=None`
    takes the family's (0.05 m indoors, 0.3 m for KITTI). Points exactly at the origin (invalid LiDAR
    returns) and non-finite points are dropped unless `drop_zeros=False` (then only non-finite ones).
    """

    name = "pairs"

    def __init__(
        self,
        source: str | Path | Sequence[str | Path] | None = None,
        target: str | Path | Sequence[str | Path] | None = None,
        gt: str | Path | Sequence[str | Path | None] | None = None,
        family: str = "auto",
        voxel_size: float | None = None,
        resolution: float | None = None,
        drop_zeros: bool = True,
    ) -> None:
        self.source = source
        self.target = target
        self.gt = gt
        self.family = family
        self.voxel_size = voxel_size
        self.resolution = None if resolution is None else float(resolution)
        self.drop_zeros = bool(drop_zeros)
        self._entries: list[tuple[str, Path, Path, Path | None]] | None = None

    def _index(self) -> list[tuple[str, Path, Path, Path | None]]:
        if self._entries is not None:
            return self._entries
        if self.family != "auto":
            check_family(self.family)
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise InputError(f"pairs: voxel_size must be positive or null, got {self.voxel_size}")
        src, tgt = _as_list(self.source, "source"), _as_list(self.target, "target")
        if not src or not tgt:
            raise InputError(
                "pairs: give the two clouds: python run.py dataset=pairs dataset.source=src.ply "
                "dataset.target=tgt.ply [dataset.gt=gt.txt] (ply, pcd, xyz/txt, npy or KITTI .bin; the GT is "
                "a 4x4 text or .npy matrix mapping source into target)"
            )
        gts = _as_list(self.gt, "gt")
        if len(src) != len(tgt):
            raise InputError(f"pairs: {len(src)} source(s) but {len(tgt)} target(s)")
        if not gts:
            gts = [None] * len(src)
        if len(gts) != len(src):
            raise InputError(f"pairs: {len(gts)} GT file(s) for {len(src)} pair(s)")
        out = []
        for s, t, g in zip(src, tgt, gts):
            s, t = Path(s).expanduser(), Path(t).expanduser()
            out.append((f"{s.stem}+{t.stem}", s, t, None if g is None else Path(g).expanduser()))
        names = [n for n, *_ in out]
        for k, n in enumerate(names):  # disambiguate equal stems
            if names.count(n) > 1:
                out[k] = (f"{k}:{n}",) + out[k][1:]
        self._entries = out
        return out

    def names(self) -> list[str]:
        return [n for n, *_ in self._index()]

    def check_inputs(self) -> None:
        """Every named file exists, is readable and not empty (a run checks this before it starts, not pair
        by pair)."""
        for _, *paths in self._index():
            for key, path in zip(("source", "target", "gt"), paths):
                if path is not None and (problem := check_input_file(path)):
                    raise InputError(f"dataset.{key}: {problem}: {path.resolve()}")

    def __len__(self) -> int:
        return len(self._index())

    def load(self, index: int) -> Pair:
        entries = self._index()
        if not 0 <= index < len(entries):
            raise IndexError(f"pairs: pair index {index} out of range (0..{len(entries) - 1})")
        name, s, t, g = entries[index]
        src, ds = _load(s, "source cloud", self.drop_zeros, KEEP_ZEROS)
        tgt, dt = _load(t, "target cloud", self.drop_zeros, KEEP_ZEROS)
        gt = read_matrix(g) if g is not None else None
        fam = self.family
        if fam == "auto":
            fam, why = infer_family(s, t, src, tgt)
            (log.warning if "outdoor scans?" in why else log.info)("%s: family=%s (%s)", name, fam, why)
        voxel = self.voxel_size if self.voxel_size is not None else family(fam).voxel_size
        res, timed = (self.resolution, {}) if self.resolution is not None else timed_resolution_for(
            fam, src, tgt)  # fmt: skip
        return Pair(
            name=name,
            family=fam,
            gt=gt,
            src_cloud=src,
            tgt_cloud=tgt,
            voxel_size=float(voxel),
            resolution=res,
            meta={
                **timed,
                "source_file": str(s),
                "target_file": str(t),
                "gt_file": None if g is None else str(g),
                "dropped_points": (ds, dt),
            },
            **family(fam).thresholds(),
        )


def resolve_shared_root(root: str | Path) -> Path:
    """A relative root is taken relative to the repository root (the parent of the fastmac_exp package)."""
    p = Path(root).expanduser()
    return p if p.is_absolute() else (REPO_ROOT / p).resolve()


CATEGORIES = ("indoor", "outdoor", "object")


class SharedRealPairs:
    """The real scan pairs of `<root>/pairs.json` (root default: `<repo>/../shared/data`); names are the ids.

    indoor -> 3DMatch rules at voxel 0.05 m (the 3DLoMatch pair gets the 3dlomatch family, which differs
    only in its graph threshold); outdoor -> KITTI rules at voxel 0.3 m; object (the bunny) -> 3DMatch rules
    rescaled to a 15 cm object (see OBJECT_RULES). `category` and `ids` filter, keeping pairs.json's order.
    """

    name = "shared_real"

    def __init__(
        self,
        root: str | Path = "../shared/data",
        category: str | None = None,
        ids: Sequence[str] | None = None,
    ) -> None:
        self.root = root
        self.category = category
        self.ids = ids
        self._entries: list[dict] | None = None

    def _root(self) -> Path:
        return resolve_shared_root(self.root)

    def _index(self) -> list[dict]:
        if self._entries is not None:
            return self._entries
        if self.category is not None and self.category not in CATEGORIES:
            raise InputError(
                f"shared_real: category must be null or one of {CATEGORIES}, got {self.category!r}"
            )
        root = self._root()
        index = root / "pairs.json"
        if not index.is_file():
            raise InputError(
                f"shared_real: {index} not found (root {self.root!r} resolves to {root}). "
                "The real pairs live in the shared data folder next to the repository "
                "(<repo>/../shared/data with pairs.json, README.md and MANIFEST.md); "
                "point to it with dataset.root=/path/to/shared/data."
            )
        try:
            pairs = json.loads(index.read_text())["pairs"]
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(f"{index}: not a pairs index with a 'pairs' list ({e})") from None
        for k, p in enumerate(pairs):
            missing = [key for key in ("id", "category", "source", "target", "gt") if key not in p]
            if missing:
                raise InputError(f"{index}: pair {k} lacks {', '.join(missing)}")
        sel = [p for p in pairs if self.category is None or p["category"] == self.category]
        if self.ids is not None:
            want = [str(i) for i in self.ids]
            known = {p["id"] for p in sel}
            unknown = [i for i in want if i not in known]
            if unknown:
                raise InputError(
                    f"shared_real: unknown id(s) {unknown}"
                    + (f" in category {self.category!r}" if self.category else "")
                    + f"; known: {sorted(known)}"
                )
            sel = [p for p in sel if p["id"] in want]
        self._entries = sel
        return sel

    def names(self) -> list[str]:
        return [p["id"] for p in self._index()]

    def __len__(self) -> int:
        return len(self._index())

    @staticmethod
    def rules(entry: dict) -> dict:
        """Family, voxel and thresholds of one pairs.json entry."""
        cat = entry["category"]
        if cat == "object":
            return dict(OBJECT_RULES)
        if cat == "outdoor":
            name = "kitti"
        elif cat == "indoor":
            name = "3dlomatch" if "3dlomatch" in str(entry.get("dataset", "")).lower() else "3dmatch"
        else:
            raise InputError(f"pair {entry['id']!r}: unknown category {cat!r}; expected one of {CATEGORIES}")
        fam = family(name)
        return {"family": name, "voxel_size": fam.voxel_size, **fam.thresholds()}

    def load(self, index: int) -> Pair:
        entries = self._index()
        if not 0 <= index < len(entries):
            raise IndexError(f"shared_real: pair index {index} out of range (0..{len(entries) - 1})")
        e = entries[index]
        root = self._root()
        src, ds = _load(root / e["source"], "source cloud", True)
        tgt, dt = _load(root / e["target"], "target cloud", True)
        gt = read_matrix(root / e["gt"])
        rules = self.rules(e)
        timed = {}
        if "resolution" not in rules:  # computed from the clouds where MAC computes it (indoor families)
            rules["resolution"], timed = timed_resolution_for(rules["family"], src, tgt)
        return Pair(
            name=e["id"],
            gt=gt,
            src_cloud=src,
            tgt_cloud=tgt,
            scene=e["category"],
            meta={
                **timed,
                "category": e["category"],
                "dataset": e.get("dataset", ""),
                "note": e.get("note", ""),
                "check_voxel_m": e.get("check_voxel_m"),
                "source_file": str(root / e["source"]),
                "target_file": str(root / e["target"]),
                "gt_file": str(root / e["gt"]),
                "dropped_points": (ds, dt),
            },
            **rules,
        )
