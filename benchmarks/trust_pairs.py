"""Every real pair ../shared/data can make, for the trust test's calibration and the escalation benchmark.

- given: the 13 pairs of pairs.json;
- same scene: every other ordered pair of one scene's scans whose GT follows from the given GTs (the
  redkitchen fragments 0, 4, 6, 7 through fragment 0; KITTI 00's frames 94, 95, 198, 199 through the
  sequence's poses and calibration, checked against the given GT files, frames 5 and 15 through their GT
  to frame 0, frame 0 through the poses), at any overlap: KITTI frames
  hundreds of metres apart share nothing, and a pose for them is wrong by GT; each given pair reversed;
- unrelated: each pair's target with the source of every pair of the same category scanned elsewhere
  (GT: none; any pose is wrong);
- synthetic: the embedded benchmark's 3DMatch-, 3DLoMatch- and KITTI-like pairs.

Each pair has a `group`: the unordered set of scans it is made of, so both directions of one pair and
the re-uses of one scan never fall in different halves of a split (`half`).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fastmac_exp.datasets.user_pairs import SharedRealPairs
from fastmac_exp.geometry.resolution import resolution_for
from fastmac_exp.types import Pair

KITTI_FRAMES = {
    0: "kitti_seq00_overlaptransformer/000000.bin",
    5: "kitti_seq00_overlaptransformer/000005.bin",
    15: "kitti_seq00_overlaptransformer/000015.bin",
    94: "kitti_seq00_scancontext/000094.bin",
    95: "kitti_seq00_scancontext/000095.bin",
    198: "kitti_seq00_scancontext/000198.bin",
    199: "kitti_seq00_scancontext/000199.bin",
}  # fmt: skip
# redkitchen fragment -> the given pair whose source it is (its GT maps it into fragment 0)
KITCHEN = {4: "3dm_redkitchen_4_to_0_teaser_fullres", 6: "3dm_redkitchen_6_to_0_geotransformer",
           7: "3dlm_redkitchen_7_to_0_mac_fullres"}  # fmt: skip


@dataclass
class Case:
    kind: str  # given | same_scene | unrelated | synthetic
    pair: Pair
    group: str  # the scans it is made of, unordered: the unit of the split
    stratum: str = ""  # the place (or kind) whose groups are dealt alternately into the two halves
    half: str = ""  # calibration | held_out (assign_halves)

    @property
    def name(self) -> str:
        return self.pair.name


def assign_halves(cases: list[Case]) -> list[Case]:
    """Deal each stratum's groups, in a fixed hash order (no draw), alternately into 'calibration' and
    'held_out': every place has pairs in both halves, both directions of one pair stay together."""
    by: dict[str, list[str]] = {}
    for c in cases:
        c.stratum = c.stratum or c.kind
        if c.group not in by.setdefault(c.stratum, []):
            by[c.stratum].append(c.group)
    side = {}
    for groups in by.values():
        for i, g in enumerate(sorted(groups, key=lambda g: hashlib.sha1(g.encode()).hexdigest())):
            side[g] = ("calibration", "held_out")[i % 2]
    for c in cases:
        c.half = side[c.group]
    return cases


def kitti_poses(root: Path) -> dict[int, np.ndarray]:
    """Velodyne-frame poses of KITTI 00's frames: Tr^-1 P_k Tr (P_k the camera poses, Tr velo -> cam0)."""
    poses = np.loadtxt(root / "kitti_seq00_scancontext/KITTI_00_gt.txt").reshape(-1, 3, 4)
    tr = np.eye(4)
    for line in (root / "kitti_seq00_scancontext/calib_Tr_velo_to_cam0_seq00.txt").read_text().splitlines():
        vals = line.replace("Tr:", "").split()
        if len(vals) == 12:
            tr[:3] = np.array(vals, float).reshape(3, 4)
    out = {}
    for k in KITTI_FRAMES:
        p = np.eye(4)
        p[:3] = poses[k]
        out[k] = np.linalg.inv(tr) @ p @ tr
    return out


def _pair(name: str, like: Pair, src: np.ndarray, tgt: np.ndarray, gt: np.ndarray | None) -> Pair:
    res = resolution_for(like.family, src, tgt) if like.scene != "object" else like.resolution
    return dataclasses.replace(like, name=name, src_cloud=src, tgt_cloud=tgt, gt=gt, correspondences=None,
                               resolution=res)  # fmt: skip


def real_cases(root: str | Path) -> Iterator[Case]:
    root = Path(root)
    ds = SharedRealPairs(root=root)
    given = {ds.names()[i]: ds.load(i) for i in range(len(ds))}
    entries = {e["id"]: e for e in ds._index()}
    for name, p in given.items():
        group = "+".join(sorted((entries[name]["source"], entries[name]["target"])))
        yield Case("given", p, group, stratum(entries[name]))
        back = np.linalg.inv(p.gt)
        yield Case("same_scene", _pair(f"{name}_reversed", p, p.tgt_cloud, p.src_cloud, back), group,
                   stratum(entries[name]))  # fmt: skip
    # redkitchen fragments through fragment 0
    for a, pa in KITCHEN.items():
        for b, pb in KITCHEN.items():
            if a == b:
                continue
            gt = np.linalg.inv(given[pb].gt) @ given[pa].gt  # a -> 0 -> b
            yield Case("same_scene", _pair(f"3dm_redkitchen_{a}_to_{b}", given[pa], given[pa].src_cloud,
                                           given[pb].src_cloud, gt), f"kitchen{min(a, b)}+{max(a, b)}",
                       "indoor")  # fmt: skip
    # KITTI 00 through the sequence's poses (checked against the given GT files of frames 94-199); frames
    # 0, 5, 15 through their own (refined) GT files: the raw poses put frame 5 0.7 m off its GT
    poses = kitti_poses(root)
    for k, name in ((5, "kitti00_5_to_0"), (15, "kitti00_15_to_0")):
        poses[k] = poses[0] @ given[name].gt
    for name in ("kitti00_95_to_94", "kitti00_199_to_198"):
        a, b = (int(x) for x in name.removeprefix("kitti00_").split("_to_"))
        rel = np.linalg.inv(poses[b]) @ poses[a]
        assert np.abs(rel - given[name].gt).max() < 1e-3, f"KITTI poses disagree with {name}'s GT"
    clouds = {}
    for k, path in KITTI_FRAMES.items():
        for p, e in zip(given.values(), entries.values()):
            if e["source"] == path:
                clouds[k] = p.src_cloud
            elif e["target"] == path:
                clouds[k] = p.tgt_cloud
    template = given["kitti00_95_to_94"]
    done = {
        (95, 94),
        (199, 198),
        (198, 94),
        (5, 0),
        (15, 0),
        (94, 95),
        (198, 199),
        (94, 198),
        (0, 5),
        (0, 15),
    }
    for a in KITTI_FRAMES:
        for b in KITTI_FRAMES:
            if a == b or (a, b) in done:
                continue
            gt = np.linalg.inv(poses[b]) @ poses[a]
            yield Case("same_scene", _pair(f"kitti00_{a}_to_{b}", template, clouds[a], clouds[b], gt),
                       f"kitti{min(a, b)}+{max(a, b)}", "kitti")  # fmt: skip
    # unrelated: each target with the sources of the same category scanned at another place
    loaded = list(given.values())
    ents = list(entries.values())
    for i, p in enumerate(loaded):
        for j, s in enumerate(loaded):
            if ents[j]["category"] != ents[i]["category"] or place(ents[j]) == place(ents[i]):
                continue
            name = f"{s.name}(src)+{p.name}(tgt)"
            mixed = dataclasses.replace(p, name=name, src_cloud=s.src_cloud, gt=None, correspondences=None)
            yield Case("unrelated", mixed,
                       "+".join(sorted((ents[j]["source"], ents[i]["target"]))),
                       f"unrelated-{ents[i]['category']}")  # fmt: skip


def stratum(entry: dict) -> str:
    """Scenes with one pair are pooled by kind, so that each half has some of every kind."""
    p = place(entry)
    return p if p == "kitti" else {"indoor": "indoor", "object": "object"}.get(entry["category"], "lidar")


def place(entry: dict) -> str:
    """The place a pair was scanned: pairs of one place are not unrelated."""
    text = f"{entry['id']} {entry['dataset']}".lower()
    for p in ("redkitchen", "kitti", "home_at", "bunny", "dragon", "apollo"):
        if p in text:
            return p
    return entry["source"].split("/")[0]


def synthetic_cases(n: int = 8, seed: int = 0) -> Iterator[Case]:
    """The embedded benchmark's pairs of each family (the 3DLoMatch-like ones fail often)."""
    from fastmac_exp.datasets.synthetic import SyntheticDataset

    for fam in ("3dmatch", "3dlomatch", "kitti"):
        ds = SyntheticDataset(family=fam, num_pairs=n, seed=seed)
        for i in range(len(ds)):
            p = ds.load(i)
            p = dataclasses.replace(p, name=f"synthetic-{fam}/{p.name}")
            yield Case("synthetic", p, p.name, f"synthetic-{fam}")


def all_cases(root: str | Path, synthetic: int = 8) -> list[Case]:
    cases = list(real_cases(root))
    if synthetic:
        cases += list(synthetic_cases(synthetic))
    return assign_halves(cases)
