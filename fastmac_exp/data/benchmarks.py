"""dataset=3dmatch | 3dlomatch | kitti: the benchmark from `root` or, when root is unset, from the data
home, with the front end picked by what is there (front_end=auto):

- MAC's released correspondences (the `mac-*` data sets, or a root in MAC's layout) when the descriptor is
  `precomputed`, or is the default FPFH and MAC's FPFH correspondences are there (they are FPFH's, made by
  MAC's protocol): the pairs carry them and the run reads them (descriptor `precomputed`);
- else the raw fragments (scans) with their GT, through the configured descriptor (FPFH by default).

front_end=precomputed or front_end=raw forces one. Without data, the error names the one fetch command
and its size. The experiment asks `front_end_for(descriptor)` once, before the first pair.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastmac_exp.data.checks import mac_descriptors
from fastmac_exp.data.fetch import fetch_hint
from fastmac_exp.data.home import Manifest, data_home, dataset_dir
from fastmac_exp.data.kitti import fcgf_test_pairs
from fastmac_exp.data.sources import load_registry
from fastmac_exp.datasets.fragments import Fragments3DMatch, KittiRaw
from fastmac_exp.datasets.mac_layout import KittiMAC, ThreeDLoMatchMAC, ThreeDMatchMAC
from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES

log = logging.getLogger("fastmac_exp.data")
FRONT_ENDS = ("auto", "precomputed", "raw")


def _usable(name: str, home: Path) -> Path | None:
    """The data home's folder of data set `name` when a fetch or add finished it; an unfinished one is
    an error that says how to finish it."""
    folder = dataset_dir(name, home)
    man = Manifest(folder)
    if man.complete:
        return folder
    if man.data["sources"]:
        raise InputError(
            f"{name}: the fetch into {folder} did not finish; run `fastmac-exp data fetch {name}` again to "
            "complete it (it resumes where it stopped)"
        )
    return None


class _Benchmark:
    """What the three share: the choice of front end and the inner dataset it builds."""

    name = ""
    family = ""
    raw_set = ""  # the data set of raw scans in the home
    mac_set = ""  # MAC's released correspondences in the home

    def __init__(self, root=None, descriptor: str = "fpfh", front_end: str = "auto") -> None:
        self.root = root
        self.descriptor = descriptor  # the graph key: which released files (fpfh, fcgf, ...) are read
        self.front_end = front_end
        self._inner = None
        self.chosen: dict[str, str] = {}

    # -- subclasses --------------------------------------------------------------------------------------
    def _precomputed(self, root: Path):
        raise NotImplementedError

    def _raw(self, root: Path | None, home: Path):
        raise NotImplementedError

    def _root_is_mac(self, root: Path) -> bool:
        raise NotImplementedError

    # -- the choice --------------------------------------------------------------------------------------
    def front_end_for(self, descriptor):
        """The descriptor the run uses: `descriptor`, or the precomputed front end where the data carry
        correspondences (module docstring)."""
        from fastmac_exp.descriptors.precomputed import PrecomputedDescriptor

        if self.front_end not in FRONT_ENDS:
            raise InputError(
                f"dataset.front_end must be one of {', '.join(FRONT_ENDS)}, got {self.front_end!r}"
            )
        wants_pre = descriptor.name == "precomputed"
        key = descriptor.graph_key if wants_pre else "fpfh"
        mac_root = self._mac_root(key)
        if self.front_end == "precomputed" or wants_pre:
            if mac_root is None:
                raise self._no_mac(key)
            use_pre = True
        elif self.front_end == "raw" or descriptor.name != "fpfh":
            use_pre = False
        else:
            use_pre = mac_root is not None
        if use_pre:
            self.descriptor = key
            self._inner = self._precomputed(mac_root)
            self.chosen = {"front_end": "precomputed", "root": str(mac_root), "graph_key": key}
            if not wants_pre:
                log.info(
                    "%s: MAC's released %s correspondences in %s (dataset.front_end=raw computes them "
                    "from the fragments instead)",
                    self.name,
                    key,
                    mac_root,
                )
                descriptor = PrecomputedDescriptor(graph_key=key)
            return descriptor
        raw_root = self._raw_root()
        self._inner = self._raw(raw_root, data_home())
        self.chosen = {"front_end": "raw", "root": str(raw_root)}
        log.info(
            "%s: raw %s in %s through descriptor %s", self.name, self._what_raw(), raw_root, descriptor.name
        )
        return descriptor

    def _mac_root(self, key: str) -> Path | None:
        if self.root is not None:
            root = Path(self.root).expanduser()
            return root if root.is_dir() and self._root_is_mac(root) and self._has_key(root, key) else None
        folder = _usable(self.mac_set, data_home())
        return folder if folder is not None and self._has_key(folder, key) else None

    def _has_key(self, folder: Path, key: str) -> bool:
        found = mac_descriptors(folder, self.family == "kitti")
        return key in found or (key not in ("fpfh", "fcgf") and "fpfh" in found and self.family != "kitti")

    def _raw_root(self) -> Path:
        if self.root is not None:
            root = Path(self.root).expanduser()
            if not root.is_dir():
                raise InputError(f"{self.name}: dataset.root={self.root} is not a folder")
            return root
        home = data_home()
        folder = _usable(self.raw_set, home)
        if folder is None:
            raise self._no_data(home)
        return folder

    def _no_data(self, home: Path) -> InputError:
        reg = load_registry()
        need = [n for n in (self.raw_set, *reg.get(self.raw_set).needs) if _usable(n, home) is None]
        cmd = fetch_hint(reg.get(self.raw_set))
        extra = f" (it fetches {need[-1]} too)" if len(need) > 1 else ""
        return InputError(
            f"{self.name}: no data in {home} (the data home: $FASTMAC_DATA, else the user data folder); "
            f"{cmd}{extra}, or point to a copy with dataset.root=/path (docs/data.md)"
        )

    def _no_mac(self, key: str) -> InputError:
        where = self.root if self.root is not None else dataset_dir(self.mac_set, data_home())
        manual = load_registry().get(self.mac_set).manual
        return InputError(
            f"{self.name}: descriptor=precomputed needs MAC's released {key} correspondences, and {where} "
            "has "
            f"none. {manual}. Or drop descriptor=precomputed to compute FPFH from the raw data "
            f"(`fastmac-exp data fetch {self.raw_set}`)"
        )

    def _what_raw(self) -> str:
        return "scans" if self.family == "kitti" else "fragments"

    # -- the dataset protocol ----------------------------------------------------------------------------
    def _dataset(self):
        if self._inner is None:
            from fastmac_exp.descriptors.fpfh import FPFHDescriptor

            self.front_end_for(FPFHDescriptor())
        return self._inner

    def names(self) -> list[str]:
        return self._dataset().names()

    def __len__(self) -> int:
        return len(self._dataset())

    def load(self, index: int):
        return self._dataset().load(index)


class ThreeDMatch(_Benchmark):
    name = family = "3dmatch"
    raw_set, mac_set = "3dmatch", "mac-3dmatch"
    mac_class = ThreeDMatchMAC

    def __init__(
        self,
        root=None,
        descriptor: str = "fpfh",
        front_end: str = "auto",
        scenes=None,
        resolution: float | None = None,
        voxel_size: float = FAMILIES["3dmatch"].voxel_size,
        gt_root=None,
    ) -> None:
        super().__init__(root, descriptor, front_end)
        self.scenes = scenes
        self.resolution = resolution
        self.voxel_size = voxel_size
        self.gt_root = gt_root

    def _root_is_mac(self, root: Path) -> bool:
        return bool(mac_descriptors(root, False))

    def _precomputed(self, root: Path):
        return self.mac_class(
            root=root, descriptor=self.descriptor, scenes=self.scenes, resolution=self.resolution
        )

    def _gt_root(self, home: Path) -> Path | None:
        return None if self.gt_root is None else Path(self.gt_root)

    def _raw(self, root: Path, home: Path):
        scenes = None if self.scenes is None else [s.removesuffix("_3dlomatch") for s in self.scenes]
        return Fragments3DMatch(
            root=root,
            gt_root=self._gt_root(home),
            scenes=scenes,
            family=self.family,
            voxel_size=self.voxel_size,
            resolution=self.resolution,
        )


class ThreeDLoMatch(ThreeDMatch):
    """3DLoMatch: the 3DMatch fragments (data set 3dmatch) with 3DLoMatch's gt.log (data set 3dlomatch)."""

    name = family = "3dlomatch"
    raw_set, mac_set = "3dlomatch", "mac-3dlomatch"
    mac_class = ThreeDLoMatchMAC

    def _raw_root(self) -> Path:
        if self.root is not None:
            return super()._raw_root()
        logs = super()._raw_root()  # the 3dlomatch logs; the fragments are the 3dmatch data set's
        frags = _usable("3dmatch", data_home())
        if frags is None:
            raise InputError(
                f"3dlomatch: the logs are in {logs} but the fragments are not; "
                "fetch them with: fastmac-exp data fetch 3dmatch"
            )
        self._logs = logs
        return frags

    def _gt_root(self, home: Path) -> Path | None:
        if self.gt_root is not None:
            return Path(self.gt_root)
        return getattr(self, "_logs", None)


class Kitti(_Benchmark):
    name = family = "kitti"
    raw_set, mac_set = "kitti", "mac-kitti"

    def __init__(
        self,
        root=None,
        descriptor: str = "fpfh",
        front_end: str = "auto",
        voxel_size: float = FAMILIES["kitti"].voxel_size,
    ) -> None:
        super().__init__(root, descriptor, front_end)
        self.voxel_size = voxel_size

    def _root_is_mac(self, root: Path) -> bool:
        return bool(mac_descriptors(root, True))

    def _precomputed(self, root: Path):
        return KittiMAC(root=root, descriptor=self.descriptor)

    def _raw(self, root: Path, home: Path):
        dataset = root / "dataset" if (root / "dataset" / "poses").is_dir() else root
        return KittiRaw(
            root=dataset, pairs=[list(p) for p in fcgf_test_pairs(dataset)], voxel_size=self.voxel_size
        )
