"""3DMatch, 3DLoMatch and KITTI in MAC's released precomputed layout (spec sections 1.2 and 1.3).

These pairs carry correspondences (with their GT inlier labels) and the GT, but no point clouds; run them
with the `precomputed` descriptor (`descriptor=precomputed descriptor.graph_key=fcgf` for FCGF inputs).

3DMatch / 3DLoMatch (scene folders; 3DLoMatch scenes carry the suffix `_3dlomatch`)::

    <root>/<scene>/dataload.txt          one pair `A+B` per line, A = source, B = target
    <root>/<scene>/A+B@corr.txt          N lines `px py pz qx qy qz` (source point first)
    <root>/<scene>/A+B@label.txt         N lines, 1 = GT inlier, 0 = outlier
    <root>/<scene>/A+B@GTmat.txt         4x4, maps A (source) into B (target)

For the fcgf descriptor the names are `dataload_fcgf.txt`, `@corr_fcgf.txt`, `@label_fcgf.txt`,
`@GTmat_fcgf.txt`; fpfh, spinnet, d3feat (and any other name) use the plain names, so each descriptor has
its own root. Predator's release is flat: `<root>/dataload.txt`, `<root>/A+B@corr.txt`, ...

KITTI (one numbered folder per pair, 0..554, taken in numeric order)::

    <root>/<i>/<desc>@corr.txt   <root>/<i>/<desc>@gtmat.txt   <root>/<i>/<desc>@gtlabel.txt

A root that holds `correspondence_<desc>/` (FastMAC's `Processed_KITTI/` default) is followed into it.
"""

from __future__ import annotations

from pathlib import Path

from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES, family
from fastmac_exp.geometry.resolution import FIXED_RESOLUTION
from fastmac_exp.io import file_resolution, read_correspondence_array, read_labels, read_matrix
from fastmac_exp.types import Correspondences, Pair

SCENES_3DMATCH = (
    "7-scenes-redkitchen",
    "sun3d-home_at-home_at_scan1_2013_jan_1",
    "sun3d-home_md-home_md_scan9_2012_sep_30",
    "sun3d-hotel_uc-scan3",
    "sun3d-hotel_umd-maryland_hotel1",
    "sun3d-hotel_umd-maryland_hotel3",
    "sun3d-mit_76_studyroom-76-1studyroom2",
    "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika",
)
LOMATCH_SUFFIX = "_3dlomatch"
SCENES_3DLOMATCH = tuple(s + LOMATCH_SUFFIX for s in SCENES_3DMATCH)

WHERE_TO_GET = (
    "Get the data: MAC's released benchmark correspondences (download links in the 'Datasets' section of "
    "https://github.com/zhangxy0517/3D-Registration-with-Maximal-Cliques; FastMAC's README, "
    "https://github.com/Forrest-110/FastMAC, points to the same release)."
)


def _file_names(descriptor: str) -> tuple[str, str, str, str]:
    """(dataload, corr, label, gt) file-name parts of the 3DMatch layout for a descriptor."""
    sfx = "_fcgf" if descriptor == "fcgf" else ""
    return f"dataload{sfx}.txt", f"@corr{sfx}.txt", f"@label{sfx}.txt", f"@GTmat{sfx}.txt"


def layout_3dmatch(descriptor: str, scenes: tuple[str, ...] | list[str]) -> str:
    dl, corr, lab, gt = _file_names(descriptor)
    if descriptor == "predator":
        return (
            "  <root>/\n"
            f"    {dl:<34} one pair name A+B per line (A = source, B = target)\n"
            f"    {'A+B' + corr:<34} N lines: px py pz qx qy qz\n"
            f"    {'A+B' + lab:<34} N lines: 1 (GT inlier) or 0\n"
            f"    {'A+B' + gt:<34} 4x4 matrix mapping A (source) into B (target)\n"
        )
    first = scenes[0] if scenes else SCENES_3DMATCH[0]
    more = "".join(f"    {s}/   (the same files)\n" for s in scenes[1:])
    return (
        "  <root>/\n"
        f"    {first}/\n"
        f"      {dl:<44} one pair name A+B per line (A = source, B = target)\n"
        f"      {'cloud_bin_0+cloud_bin_1' + corr:<44} N lines: px py pz qx qy qz\n"
        f"      {'cloud_bin_0+cloud_bin_1' + lab:<44} N lines: 1 (GT inlier) or 0\n"
        f"      {'cloud_bin_0+cloud_bin_1' + gt:<44} 4x4 matrix mapping A (source) into B (target)\n"
        f"{more}"
    )


def layout_kitti(descriptor: str) -> str:
    d = descriptor
    return (
        "  <root>/                (or a folder holding correspondence_" + d + "/, as Processed_KITTI/)\n"
        "    0/\n"
        f"      {d}@corr.txt       N lines: px py pz qx qy qz\n"
        f"      {d}@gtlabel.txt    N lines: 1 (GT inlier) or 0\n"
        f"      {d}@gtmat.txt      4x4 matrix mapping source into target\n"
        "    1/  2/  ...  554/     one folder per pair, read in numeric order\n"
    )


def _missing_root(title: str, layout: str, config: str, root: str | Path | None) -> InputError:
    what = "is not set" if root is None else f"points to {root}, which does not exist or is not a folder"
    return InputError(
        f"{title}: dataset.root {what}.\n"
        f"{WHERE_TO_GET}\n"
        f"Expected layout:\n{layout}"
        f"Point to it: python run.py dataset={config} dataset.root=/path/to/data descriptor=precomputed "
        "(add descriptor.graph_key=fcgf for FCGF correspondences)."
    )


def _check_descriptor(descriptor: str) -> str:
    if not isinstance(descriptor, str) or not descriptor or "/" in descriptor:
        raise InputError(f"descriptor must be a name such as 'fpfh' or 'fcgf', got {descriptor!r}")
    return descriptor


class _PairFiles:
    """The three files of one precomputed pair, read into a Pair."""

    @staticmethod
    def read(name: str, corr: Path, label: Path, gt: Path, layout: str, family: str, **pair_kwargs) -> Pair:
        for path, what in ((corr, "correspondence"), (label, "label"), (gt, "GT matrix")):
            if not path.is_file():
                raise InputError(
                    f"pair {name!r}: {what} file missing: {path} (expected {path.name} in {path.parent}).\n"
                    f"Expected layout:\n{layout}"
                )
        arr = read_correspondence_array(corr)
        if len(arr) == 0:
            raise InputError(f"pair {name!r}: {corr} holds no correspondences")
        labels = read_labels(label, len(arr))
        t = read_matrix(gt)
        c = Correspondences(src=arr[:, :3], tgt=arr[:, 3:], labels=labels)
        meta = {"corr_file": str(corr), "label_file": str(label), "gt_file": str(gt)}
        meta.update(pair_kwargs.pop("meta", {}))
        return Pair(name=name, family=family, gt=t, correspondences=c, meta=meta, **pair_kwargs)


class ThreeDMatchMAC:
    """3DMatch pairs in MAC's released layout; pair names are `<scene>/<A>+<B>` in dataload order.

    `scenes=None` takes the 8 benchmark scenes in the spec's order. `resolution` is the mesh resolution of
    the graph's Gaussian kernel (alpha = 10 res): None (the default) computes it as MAC does, from the
    scene's `<A>.ply` and `<B>.ply` (spec 1.2, 1.5), and falls back to 0.006 (FastMAC's fixed value) when
    they are absent, saying so in the pair's meta; a number fixes it. The same class reads ETH (same
    layout, 3DMatch rules) with `scenes=[gazebo_summer, ...]`.
    """

    name = "3dmatch"
    family = "3dmatch"
    config = "3dmatch"
    default_scenes: tuple[str, ...] = SCENES_3DMATCH

    def __init__(
        self,
        root: str | Path | None = None,
        descriptor: str = "fpfh",
        scenes: list[str] | tuple[str, ...] | None = None,
        resolution: float | None = None,
    ) -> None:
        # Nothing is read or checked against the disk here: Hydra wraps constructor errors in its own
        # exception type, so data problems surface as InputError from names()/load()/len().
        self.root = root
        self.descriptor = descriptor
        self.scenes = list(scenes) if scenes is not None else list(self.default_scenes)
        self.resolution = None if resolution is None else float(resolution)
        self._entries: list[tuple[str, str, Path]] | None = None

    def _resolution(self, scene_dir: Path, src: str, tgt: str) -> tuple[float, str]:
        """(resolution, where it came from): the fixed value, the two clouds, or FastMAC's 0.006."""
        if self.resolution is not None:
            return self.resolution, "fixed"
        plys = [scene_dir / f"{src}.ply", scene_dir / f"{tgt}.ply"]
        if all(p.is_file() for p in plys):
            return 0.5 * (file_resolution(plys[0]) + file_resolution(plys[1])), "clouds"
        return FIXED_RESOLUTION, f"{FIXED_RESOLUTION} (no .ply clouds in the scene folder)"

    # -- index -----------------------------------------------------------------------------------------
    def _title(self) -> str:
        return f"{self.name} (MAC's precomputed correspondences, descriptor {self.descriptor!r})"

    def _layout(self) -> str:
        return layout_3dmatch(self.descriptor, self.scenes)

    def _root(self) -> Path:
        if self.root is None or not Path(self.root).expanduser().is_dir():
            raise _missing_root(self._title(), self._layout(), self.config, self.root)
        return Path(self.root).expanduser()

    def _scene_dir(self, root: Path, scene: str) -> Path:
        d = root / scene
        if not d.is_dir() and self.family == "3dlomatch" and not scene.endswith(LOMATCH_SUFFIX):
            alt = root / (scene + LOMATCH_SUFFIX)
            if alt.is_dir():
                return alt
        return d

    def _read_dataload(self, path: Path) -> list[str]:
        if not path.is_file():
            raise InputError(
                f"{self._title()}: pair list missing: {path} (expected {path.name} in {path.parent}).\n"
                f"Expected layout:\n{self._layout()}"
            )
        names = []
        for k, line in enumerate(path.read_text().splitlines(), start=1):
            s = line.strip()
            if not s:
                continue
            if "+" not in s or s.startswith("+") or s.endswith("+") or len(s.split()) != 1:
                raise InputError(f"{path}, line {k}: expected one pair name 'A+B' (source+target), got {s!r}")
            names.append(s)
        return names

    def _index(self) -> list[tuple[str, str, Path]]:
        if self._entries is not None:
            return self._entries
        _check_descriptor(self.descriptor)
        root = self._root()
        dataload = _file_names(self.descriptor)[0]
        entries: list[tuple[str, str, Path]] = []
        if self.descriptor == "predator":
            entries = [("", n, root) for n in self._read_dataload(root / dataload)]
        else:
            if not self.scenes:
                raise InputError(f"{self._title()}: scenes is empty; pass null for all 8 or a list of names")
            missing = [s for s in self.scenes if not self._scene_dir(root, s).is_dir()]
            if missing:
                present = sorted(p.name for p in root.iterdir() if p.is_dir())
                raise InputError(
                    f"{self._title()}: scene folder(s) missing under {root}: {', '.join(missing)}.\n"
                    f"Folders present: {', '.join(present) or '(none)'}.\n"
                    f"Expected layout:\n{self._layout()}"
                    "Choose scenes with dataset.scenes=[name,...]."
                )
            for s in self.scenes:
                d = self._scene_dir(root, s)
                entries += [(s, n, d) for n in self._read_dataload(d / dataload)]
        self._entries = entries
        return entries

    def names(self) -> list[str]:
        return [f"{s}/{n}" if s else n for s, n, _ in self._index()]

    def __len__(self) -> int:
        return len(self._index())

    def load(self, index: int) -> Pair:
        entries = self._index()
        if not 0 <= index < len(entries):
            raise IndexError(f"{self.name}: pair index {index} out of range (0..{len(entries) - 1})")
        scene, pname, d = entries[index]
        _, corr, lab, gt = _file_names(self.descriptor)
        src, tgt = pname.split("+", 1)
        resolution, res_from = self._resolution(d, src, tgt)
        return _PairFiles.read(
            f"{scene}/{pname}" if scene else pname,
            d / f"{pname}{corr}",
            d / f"{pname}{lab}",
            d / f"{pname}{gt}",
            self._layout(),
            self.family,
            voxel_size=FAMILIES[self.family].voxel_size,
            resolution=resolution,
            scene=scene,
            meta={"source": src, "target": tgt, "descriptor": self.descriptor, "resolution_from": res_from},
            **family(self.family).thresholds(),
        )


class ThreeDLoMatchMAC(ThreeDMatchMAC):
    """3DLoMatch: the 3DMatch layout with scene folders `<scene>_3dlomatch` (a name without the suffix is
    accepted when only the suffixed folder exists)."""

    name = "3dlomatch"
    family = "3dlomatch"
    config = "3dlomatch"
    default_scenes = SCENES_3DLOMATCH


class KittiMAC:
    """KITTI pairs in MAC's released layout: `<root>/<i>/<desc>@{corr,gtmat,gtlabel}.txt`, numeric order.

    Pair names are the folder names ("0", "1", ...). MAC hard-codes 555 pairs; here every numbered folder
    is taken.
    """

    name = "kitti"
    family = "kitti"

    def __init__(self, root: str | Path | None = None, descriptor: str = "fpfh") -> None:
        self.root = root
        self.descriptor = descriptor
        self._entries: list[Path] | None = None

    def _title(self) -> str:
        return f"kitti (MAC's precomputed correspondences, descriptor {self.descriptor!r})"

    def _root(self) -> Path:
        if self.root is None or not Path(self.root).expanduser().is_dir():
            raise _missing_root(self._title(), layout_kitti(self.descriptor), "kitti", self.root)
        return Path(self.root).expanduser()

    def _index(self) -> list[Path]:
        if self._entries is not None:
            return self._entries
        _check_descriptor(self.descriptor)
        root = self._root()
        dirs = [p for p in root.iterdir() if p.is_dir() and p.name.isdigit()]
        if not dirs and (root / f"correspondence_{self.descriptor}").is_dir():
            root = root / f"correspondence_{self.descriptor}"
            dirs = [p for p in root.iterdir() if p.is_dir() and p.name.isdigit()]
        if not dirs:
            raise InputError(
                f"{self._title()}: no numbered pair folders (0/, 1/, ...) in {root}.\n"
                f"Expected layout:\n{layout_kitti(self.descriptor)}"
            )
        self._entries = sorted(dirs, key=lambda p: int(p.name))
        return self._entries

    def names(self) -> list[str]:
        return [p.name for p in self._index()]

    def __len__(self) -> int:
        return len(self._index())

    def load(self, index: int) -> Pair:
        entries = self._index()
        if not 0 <= index < len(entries):
            raise IndexError(f"kitti: pair index {index} out of range (0..{len(entries) - 1})")
        d = entries[index]
        desc = self.descriptor
        return _PairFiles.read(
            d.name,
            d / f"{desc}@corr.txt",
            d / f"{desc}@gtlabel.txt",
            d / f"{desc}@gtmat.txt",
            layout_kitti(desc),
            "kitti",
            voxel_size=FAMILIES["kitti"].voxel_size,
            scene="kitti",
            meta={"descriptor": desc},
            **FAMILIES["kitti"].thresholds(),
        )
