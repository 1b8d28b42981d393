"""Procedural scenes and simulated sensors for the synthetic dataset.

Scenes are triangle meshes made of simple parts (boxes, frusta, ellipsoids, walls with recessed
openings): an indoor room with furniture, or an outdoor street with facades, cars, poles and trees.
They are ray cast with Open3D's `RaycastingScene` from two sensor poses: a pinhole depth camera
(fragments fused from a few nearby frames, like 3DMatch) or a spinning 64-beam LiDAR (like KITTI's
HDL-64E). Every random choice comes from the numpy Generator passed in, so a seed fixes the output.

World frame: z up, metres. Camera frame (OpenCV): x right, y down, z forward. LiDAR frame: x forward,
y left, z up.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np

# ----------------------------------------------------------------------------------------------------
# small geometry helpers


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def make_pose(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = trans
    return t


def inv_pose(t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


def transform(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    return points @ t[:3, :3].T + t[:3, 3]


def rotation_angle_deg(r: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def random_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation about a uniformly random axis by an angle uniform in [0, max_deg]."""
    if max_deg <= 0:
        return np.eye(3)
    axis = rng.normal(size=3)
    return rot_axis_angle(axis, math.radians(rng.uniform(0.0, max_deg)))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid per occupied voxel, in the order of the sorted voxel keys (deterministic, float64)."""
    if len(points) == 0:
        return points.reshape(0, 3)
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    uniq, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    out = np.zeros((len(uniq), 3))
    np.add.at(out, inv, points)
    return out / counts[:, None]


# ----------------------------------------------------------------------------------------------------
# mesh building

_BOX_TRIS = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # bottom z-
        [4, 5, 6], [4, 6, 7],  # top z+
        [0, 1, 5], [0, 5, 4],  # y-
        [2, 3, 7], [2, 7, 6],  # y+
        [1, 2, 6], [1, 6, 5],  # x+
        [0, 4, 7], [0, 7, 3],  # x-
    ],
    dtype=np.int64,
)  # fmt: skip
_UNIT_BOX = (
    np.array(
        [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
        dtype=np.float64,
    )
    * 0.5
)


class MeshBuilder:
    """Accumulates triangles in numpy; `build()` gives float32 vertices and uint32 triangles."""

    def __init__(self) -> None:
        self._v: list[np.ndarray] = []
        self._t: list[np.ndarray] = []
        self._n = 0
        self._xf: np.ndarray | None = None

    @contextlib.contextmanager
    def transformed(self, pose: np.ndarray):
        """Within the block, every part added is moved by `pose` (composed with any outer block's)."""
        outer = self._xf
        self._xf = pose if outer is None else outer @ pose
        try:
            yield self
        finally:
            self._xf = outer

    def add(self, verts: np.ndarray, tris: np.ndarray) -> None:
        verts = np.asarray(verts, dtype=np.float64)
        if self._xf is not None:
            verts = verts @ self._xf[:3, :3].T + self._xf[:3, 3]
        self._v.append(verts)
        self._t.append(np.asarray(tris, dtype=np.int64) + self._n)
        self._n += len(verts)

    def box(self, center, size, yaw: float = 0.0, rot: np.ndarray | None = None) -> None:
        r = rot_z(yaw) if rot is None else rot
        v = (_UNIT_BOX * np.asarray(size, dtype=np.float64)) @ r.T + np.asarray(center, dtype=np.float64)
        self.add(v, _BOX_TRIS)

    def box_corners(self, lo, hi, yaw: float = 0.0, pivot=None) -> None:
        """An axis-aligned box [lo, hi] in a frame rotated by `yaw` about `pivot` (default: origin)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        center, size = (lo + hi) / 2, hi - lo
        if pivot is not None:
            pivot = np.asarray(pivot, float)
            center = rot_z(yaw) @ center + pivot
        self.box(center, size, yaw)

    def hexahedron(self, corners: np.ndarray) -> None:
        """Eight corners in the order of the unit box (bottom ring, then top ring)."""
        self.add(corners, _BOX_TRIS)

    def frustum(self, base, axis, r0: float, r1: float, height: float, segments: int = 16) -> None:
        """A capped cone frustum (a cylinder when r0 == r1) from `base` along `axis`."""
        axis = np.asarray(axis, float)
        axis = axis / np.linalg.norm(axis)
        helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(axis, helper)
        u /= np.linalg.norm(u)
        w = np.cross(axis, u)
        ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w
        base = np.asarray(base, float)
        v = np.vstack([base + r0 * ring, base + height * axis + r1 * ring, base, base + height * axis])
        i = np.arange(segments)
        j = (i + 1) % segments
        side = np.vstack([np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)])
        c0, c1 = 2 * segments, 2 * segments + 1
        caps = np.vstack(
            [
                np.stack([np.full(segments, c0), j, i], 1),
                np.stack([np.full(segments, c1), segments + i, segments + j], 1),
            ]
        )
        self.add(v, np.vstack([side, caps]))

    def cylinder_z(
        self, x: float, y: float, z0: float, radius: float, height: float, segments: int = 16
    ) -> None:
        self.frustum((x, y, z0), (0, 0, 1), radius, radius, height, segments)

    def ellipsoid(
        self,
        center,
        radii,
        rng: np.random.Generator | None = None,
        jitter: float = 0.0,
        n_lat: int = 8,
        n_lon: int = 12,
    ) -> None:
        """A UV ellipsoid; `jitter` > 0 scales each vertex radially by 1 + U(-jitter, jitter) (foliage)."""
        lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
        lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
        la, lo = np.meshgrid(lat, lon, indexing="ij")
        dirs = np.stack([np.sin(la) * np.cos(lo), np.sin(la) * np.sin(lo), np.cos(la)], -1).reshape(-1, 3)
        dirs = np.vstack([dirs, [[0, 0, 1.0], [0, 0, -1.0]]])
        if rng is not None and jitter > 0:
            dirs = dirs * (1 + rng.uniform(-jitter, jitter, size=(len(dirs), 1)))
        v = dirs * np.asarray(radii, float) + np.asarray(center, float)
        tris = []
        nr = n_lat - 1
        for a in range(nr - 1):
            for b in range(n_lon):
                p, q = a * n_lon + b, a * n_lon + (b + 1) % n_lon
                tris += [[p, p + n_lon, q], [q, p + n_lon, q + n_lon]]
        top, bot = nr * n_lon, nr * n_lon + 1
        for b in range(n_lon):
            tris.append([top, b, (b + 1) % n_lon])
            base = (nr - 1) * n_lon
            tris.append([bot, base + (b + 1) % n_lon, base + b])
        self.add(v, np.array(tris))

    def height_grid(self, x0, x1, y0, y1, nx: int, ny: int, heights: np.ndarray) -> None:
        xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        v = np.stack([gx, gy, heights.reshape(gx.shape)], -1).reshape(-1, 3)
        i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        a = (i * (ny + 1) + j).reshape(-1)
        b, c, d = a + ny + 1, a + ny + 2, a + 1
        self.add(v, np.vstack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))

    def wall(
        self,
        origin,
        yaw: float,
        length: float,
        height: float,
        thickness: float,
        openings: list[tuple[float, float, float, float, float]] = (),
    ) -> None:
        """A wall whose front face runs from `origin` along direction `yaw` (the front faces local -y,
        the wall body lies at local y in [0, thickness]); each opening (u0, u1, z0, z1, depth) is a hole
        with a recessed pane `depth` behind the front face (windows, doors, shop fronts)."""
        segs = []
        u = 0.0
        for u0, u1, z0, z1, depth in sorted(openings):
            if u0 < u or u1 > length or u1 <= u0:
                continue
            if u0 > u:
                segs.append(((u, 0.0, 0.0), (u0, thickness, height)))
            if z0 > 0:
                segs.append(((u0, 0.0, 0.0), (u1, thickness, z0)))
            if z1 < height:
                segs.append(((u0, 0.0, z1), (u1, thickness, height)))
            segs.append(((u0, depth, z0), (u1, depth + 0.05, z1)))  # the recessed pane
            u = u1
        if u < length:
            segs.append(((u, 0.0, 0.0), (length, thickness, height)))
        for lo, hi in segs:
            self.box_corners(lo, hi, yaw, pivot=origin)

    def build(self) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.vstack(self._v).astype(np.float32),
            np.vstack(self._t).astype(np.uint32),
        )

    def to_o3d(self):
        """The scene as a legacy `open3d.geometry.TriangleMesh` (for viewing or saving)."""
        from fastmac_exp._open3d import o3d

        v, t = self.build()
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(v.astype(np.float64)), o3d.utility.Vector3iVector(t.astype(np.int32))
        )
        mesh.compute_vertex_normals()
        return mesh


class RayCaster:
    """A `RaycastingScene` over one MeshBuilder's triangles; `cast(origins, dirs)` gives hit distances."""

    def __init__(self, mesh: MeshBuilder) -> None:
        from fastmac_exp._open3d import o3d

        self._o3d = o3d
        v, t = mesh.build()
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(t))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rays = np.hstack([np.broadcast_to(origins, dirs.shape), dirs]).astype(np.float32)
        out = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        return out["t_hit"].numpy().astype(np.float64)


# ----------------------------------------------------------------------------------------------------
# sensors


@dataclass(frozen=True)
class DepthCamera:
    """A pinhole depth camera (Kinect/Structure-like); noise follows Nguyen et al.'s axial model."""

    width: int = 224
    height: int = 168
    fov_deg: float = 65.0
    min_depth: float = 0.3
    max_depth: float = 3.5
    noise_scale: float = 1.0

    def unit_rays(self) -> np.ndarray:
        f = (self.width / 2) / math.tan(math.radians(self.fov_deg) / 2)
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d = np.stack([(u - self.width / 2) / f, (v - self.height / 2) / f, np.ones_like(u)], -1).reshape(
            -1, 3
        )
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def scan(self, caster: RayCaster, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Points (camera frame) seen from `pose` (world_from_camera)."""
        d_cam = self.unit_rays()
        t = caster.cast(pose[:3, 3][None], d_cam @ pose[:3, :3].T)
        z = t * d_cam[:, 2]
        ok = np.isfinite(z) & (z >= self.min_depth) & (z <= self.max_depth)
        z, d_cam, t = z[ok], d_cam[ok], t[ok]
        sigma = (0.0012 + 0.0019 * (z - 0.4) ** 2) * self.noise_scale
        z_noisy = z + rng.normal(size=len(z)) * sigma
        return d_cam * (t * z_noisy / z)[:, None]


@dataclass(frozen=True)
class SpinningLidar:
    """A 64-beam spinning LiDAR like KITTI's Velodyne HDL-64E (+2 .. -24.8 deg elevation)."""

    beams: int = 64
    elev_max_deg: float = 2.0
    elev_min_deg: float = -24.8
    az_step_deg: float = 0.25
    min_range: float = 3.0
    max_range: float = 80.0
    range_sigma: float = 0.02
    dropout: float = 0.05

    def elevations_deg(self) -> np.ndarray:
        """HDL-64E-like: the upper half of the beams spans the top third of the FOV (denser near the
        horizon, as the real sensor's upper block at ~1/3 deg and lower block at ~1/2 deg spacing)."""
        upper = self.beams // 2
        split = self.elev_max_deg + (self.elev_min_deg - self.elev_max_deg) * 0.38
        lower_start = split + (self.elev_min_deg - split) / (self.beams - upper)
        return np.concatenate(
            [
                np.linspace(self.elev_max_deg, split, upper),
                np.linspace(lower_start, self.elev_min_deg, self.beams - upper),
            ]
        )

    def unit_rays(self) -> np.ndarray:
        el = np.radians(self.elevations_deg())
        az = np.radians(np.arange(0.0, 360.0, self.az_step_deg))
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)

    def scan(self, caster: RayCaster, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        d = self.unit_rays()
        t = caster.cast(pose[:3, 3][None], d @ pose[:3, :3].T)
        ok = np.isfinite(t) & (t >= self.min_range) & (t <= self.max_range)
        ok &= rng.random(len(t)) >= self.dropout
        t, d = t[ok], d[ok]
        t = t + rng.normal(size=len(t)) * self.range_sigma
        return d * t[:, None]


def camera_pose(position, yaw: float, pitch: float, roll: float = 0.0) -> np.ndarray:
    """world_from_camera for a camera at `position` heading `yaw` (about z) and tilted by `pitch`."""
    f = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    rot = np.stack([r, d, f], 1)
    if roll:
        rot = rot @ rot_axis_angle(np.array([0.0, 0, 1]), roll)
    return make_pose(rot, np.asarray(position, float))


def lidar_pose(position, yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    rot = (
        rot_z(yaw)
        @ rot_axis_angle(np.array([0.0, 1, 0]), pitch)
        @ rot_axis_angle(np.array([1.0, 0, 0]), roll)
    )
    return make_pose(rot, np.asarray(position, float))


# ----------------------------------------------------------------------------------------------------
# indoor: a furnished room


class _Footprints:
    """Occupied floor rectangles (oriented), to keep furniture apart and clear of the camera path."""

    def __init__(self) -> None:
        self.items: list[tuple[np.ndarray, float, float, float]] = []  # center, radius-ish, height

    def free(self, center, half, keep_out: list[tuple[np.ndarray, float, float]], height: float) -> bool:
        c = np.asarray(center, float)
        rad = float(np.hypot(*half))
        for oc, orad, _ in self.items:
            if np.linalg.norm(c - oc) < 0.85 * (rad + orad):
                return False
        for kc, krad, kz in keep_out:
            if np.linalg.norm(c - kc[:2]) < rad + krad and height > kz - 0.35:
                return False
        return True

    def add(self, center, half, height) -> None:
        self.items.append((np.asarray(center, float), float(np.hypot(*half)), height))


def _table(m: MeshBuilder, rng, c, yaw, w, d, h) -> None:
    top = 0.03 + 0.02 * rng.random()
    m.box_corners((-w / 2, -d / 2, h - top), (w / 2, d / 2, h), yaw, pivot=(c[0], c[1], 0))
    leg = 0.04 + 0.03 * rng.random()
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - leg), sy * (d / 2 - leg)
            m.box_corners(
                (x - leg / 2, y - leg / 2, 0), (x + leg / 2, y + leg / 2, h - top), yaw, pivot=(c[0], c[1], 0)
            )
    if rng.random() < 0.5:  # apron under the top
        m.box_corners(
            (-w / 2 + leg, -d / 2 + leg, h - top - 0.08),
            (w / 2 - leg, d / 2 - leg, h - top),
            yaw,
            (c[0], c[1], 0),
        )
    _clutter(m, rng, c, yaw, w, d, h, n=int(rng.integers(1, 5)))


def _clutter(m: MeshBuilder, rng, c, yaw, w, d, z, n: int) -> None:
    """Small objects on a surface of size w x d at height z: books, boxes, cups, bottles, bowls, monitors."""
    r = rot_z(yaw)
    for _ in range(n):
        lx, ly = rng.uniform(-w / 2 + 0.1, w / 2 - 0.1), rng.uniform(-d / 2 + 0.1, d / 2 - 0.1)
        p = r @ np.array([lx, ly, 0]) + np.array([c[0], c[1], z])
        kind = rng.integers(0, 6)
        if kind == 0:  # box / books
            s = rng.uniform([0.1, 0.1, 0.03], [0.35, 0.3, 0.25])
            m.box(p + [0, 0, s[2] / 2], s, yaw + rng.uniform(-0.5, 0.5))
        elif kind == 1:  # cup / bottle / vase
            rad, hh = rng.uniform(0.03, 0.08), rng.uniform(0.08, 0.35)
            m.frustum(p, (0, 0, 1), rad, rad * rng.uniform(0.6, 1.2), hh, 12)
        elif kind == 2:  # bowl / ball / fruit
            rad = rng.uniform(0.06, 0.15)
            m.ellipsoid(p + [0, 0, rad * 0.7], (rad, rad, rad * 0.7))
        elif kind == 3:  # monitor / picture on a stand
            sw, sh = rng.uniform(0.35, 0.7), rng.uniform(0.25, 0.45)
            m.box(p + [0, 0, 0.01], (0.2, 0.15, 0.02), yaw)
            m.box(p + [0, 0, 0.08], (0.04, 0.03, 0.16), yaw)
            m.box(p + [0, 0, 0.12 + sh / 2], (sw, 0.03, sh), yaw)
        elif kind == 4:  # lamp
            m.cylinder_z(p[0], p[1], z, 0.08, 0.02, 12)
            m.cylinder_z(p[0], p[1], z, 0.012, 0.35, 8)
            m.frustum(p + [0, 0, 0.3], (0, 0, 1), 0.13, 0.07, 0.18, 14)
        else:  # stack of books
            hz = 0.0
            for _k in range(int(rng.integers(2, 6))):
                s = rng.uniform([0.15, 0.12, 0.02], [0.3, 0.24, 0.06])
                m.box(p + [0, 0, hz + s[2] / 2], s, yaw + rng.uniform(-0.3, 0.3))
                hz += s[2]


def _chair(m: MeshBuilder, rng, c, yaw) -> None:
    s, h = rng.uniform(0.4, 0.5), rng.uniform(0.42, 0.48)
    pv = (c[0], c[1], 0)
    m.box_corners((-s / 2, -s / 2, h - 0.05), (s / 2, s / 2, h), yaw, pv)
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (s / 2 - 0.03), sy * (s / 2 - 0.03)
            m.box_corners((x - 0.02, y - 0.02, 0), (x + 0.02, y + 0.02, h - 0.05), yaw, pv)
    bh = rng.uniform(0.35, 0.5)
    m.box_corners((-s / 2, s / 2 - 0.04, h), (s / 2, s / 2, h + bh), yaw, pv)


def _shelf(m: MeshBuilder, rng, c, yaw, w, d, h) -> None:
    pv = (c[0], c[1], 0)
    t = 0.02
    m.box_corners((-w / 2, -d / 2, 0), (-w / 2 + t, d / 2, h), yaw, pv)
    m.box_corners((w / 2 - t, -d / 2, 0), (w / 2, d / 2, h), yaw, pv)
    m.box_corners((-w / 2, d / 2 - t, 0), (w / 2, d / 2, h), yaw, pv)
    n = int(rng.integers(3, 6))
    for k in range(n + 1):
        z = 0.05 + k * (h - 0.07) / n
        m.box_corners((-w / 2 + t, -d / 2, z), (w / 2 - t, d / 2 - t, z + t), yaw, pv)
        if k < n and rng.random() < 0.8:  # books and boxes on the board
            x = -w / 2 + t
            while x < w / 2 - 0.1:
                bw = rng.uniform(0.02, 0.08) if rng.random() < 0.7 else rng.uniform(0.1, 0.3)
                bh = rng.uniform(0.12, min(0.32, (h - 0.07) / n - 0.03))
                bd = rng.uniform(0.15, d - 0.04)
                if rng.random() < 0.85:
                    m.box_corners(
                        (x, d / 2 - t - bd, z + t), (min(x + bw, w / 2 - t), d / 2 - t, z + t + bh), yaw, pv
                    )
                x += bw + (0.0 if rng.random() < 0.8 else rng.uniform(0.05, 0.25))


def _cabinet(m: MeshBuilder, rng, c, yaw, w, d, h) -> None:
    pv = (c[0], c[1], 0)
    m.box_corners((-w / 2, -d / 2 + 0.05, 0), (w / 2, d / 2, 0.1), yaw, pv)  # recessed plinth
    m.box_corners((-w / 2, -d / 2, 0.1), (w / 2, d / 2, h - 0.03), yaw, pv)
    m.box_corners((-w / 2 - 0.02, -d / 2 - 0.03, h - 0.03), (w / 2 + 0.02, d / 2, h), yaw, pv)  # top overhang
    nd = max(1, int(round(w / 0.5)))
    for k in range(nd):  # handles
        x = -w / 2 + (k + 0.5) * w / nd
        m.box_corners((x - 0.06, -d / 2 - 0.03, h - 0.18), (x + 0.06, -d / 2, h - 0.15), yaw, pv)
    if h < 1.2:
        _clutter(m, rng, c, yaw, w, d, h, n=int(rng.integers(0, 4)))


def _sofa(m: MeshBuilder, rng, c, yaw, w, d) -> None:
    pv = (c[0], c[1], 0)
    m.box_corners((-w / 2, -d / 2, 0.08), (w / 2, d / 2, 0.42), yaw, pv)
    m.box_corners((-w / 2, d / 2 - 0.2, 0.42), (w / 2, d / 2, 0.85), yaw, pv)
    for sx in (-1, 1):
        m.box_corners(
            (sx * w / 2 - 0.12 * (sx > 0), -d / 2, 0.42), (sx * w / 2 + 0.12 * (sx < 0), d / 2, 0.62), yaw, pv
        )
    for _ in range(int(rng.integers(0, 3))):  # cushions
        x = rng.uniform(-w / 3, w / 3)
        m.ellipsoid(rot_z(yaw) @ np.array([x, d / 2 - 0.3, 0.55]) + [c[0], c[1], 0], (0.2, 0.08, 0.18))


def _plant(m: MeshBuilder, rng, c) -> None:
    r = rng.uniform(0.12, 0.25)
    h = rng.uniform(0.25, 0.5)
    m.frustum((c[0], c[1], 0), (0, 0, 1), r * 0.75, r, h, 14)
    m.ellipsoid((c[0], c[1], h + r * 1.5), (r * 2, r * 2, r * 2.5), rng, jitter=0.3, n_lat=9, n_lon=14)


def _floor_lamp(m: MeshBuilder, rng, c) -> None:
    h = rng.uniform(1.3, 1.8)
    m.cylinder_z(c[0], c[1], 0, 0.15, 0.03, 14)
    m.cylinder_z(c[0], c[1], 0, 0.015, h, 8)
    m.frustum((c[0], c[1], h - 0.1), (0, 0, 1), 0.22, 0.12, 0.3, 16)


def room_size(rng: np.random.Generator) -> np.ndarray:
    return np.array([rng.uniform(3.0, 6.0), rng.uniform(3.0, 6.0), rng.uniform(2.5, 3.0)])


def furnish_room(
    rng: np.random.Generator,
    size: np.ndarray,
    keep_out: list[tuple[np.ndarray, float, float]],
    clutter: float = 1.0,
) -> MeshBuilder:
    lx, ly, lz = (float(s) for s in size)
    m = MeshBuilder()
    th = 0.15
    m.box((lx / 2, ly / 2, -th / 2), (lx + 2 * th, ly + 2 * th, th))  # floor
    m.box((lx / 2, ly / 2, lz + th / 2), (lx + 2 * th, ly + 2 * th, th))  # ceiling
    # walls: (origin of the front face, yaw, length); the front face looks into the room
    # walls run clockwise seen from above, so that each wall's local +y (its body) points out of
    # the room and its front face (local -y) looks in
    walls = [
        ((lx, 0.0, 0.0), math.pi, lx),
        ((0.0, 0.0, 0.0), math.pi / 2, ly),
        ((0.0, ly, 0.0), 0.0, lx),
        ((lx, ly, 0.0), -math.pi / 2, ly),
    ]
    for origin, yaw, length in walls:
        openings = []
        u = 0.3
        while u < length - 1.0 and len(openings) < 3:
            kind = rng.random()
            if kind < 0.25:  # door
                w = rng.uniform(0.8, 1.0)
                openings.append((u, u + w, 0.0, 2.05, rng.uniform(0.05, 0.6)))
            elif kind < 0.55:  # window
                w = rng.uniform(0.6, 1.6)
                openings.append(
                    (u, min(u + w, length - 0.2), rng.uniform(0.8, 1.0), rng.uniform(1.9, 2.3), 0.12)
                )
            elif kind < 0.7:  # alcove / niche
                w = rng.uniform(0.4, 1.2)
                openings.append(
                    (u, min(u + w, length - 0.2), rng.uniform(0.0, 1.0), rng.uniform(1.6, lz), 0.3)
                )
            u = (openings[-1][1] if openings and kind < 0.7 else u) + rng.uniform(0.4, 1.6)
        m.wall(origin, yaw, length, lz, th, openings)
        o = np.asarray(origin)
        # skirting board and wall fixtures (pictures, radiators, switches)
        m.box_corners((0, -0.012, 0), (length, 0, 0.08), yaw, o)
        for _ in range(int(rng.integers(0, 3))):
            w, h = rng.uniform(0.3, 1.0), rng.uniform(0.3, 0.8)
            uu, zz = rng.uniform(0, max(0.01, length - w)), rng.uniform(1.0, lz - h - 0.2)
            m.box_corners((uu, -rng.uniform(0.02, 0.08), zz), (uu + w, 0, zz + h), yaw, o)
        if rng.random() < 0.4:
            w = rng.uniform(0.6, 1.2)
            uu = rng.uniform(0, max(0.01, length - w))
            for k in range(int(w / 0.1)):
                m.box_corners((uu + k * 0.1, -0.1, 0.15), (uu + k * 0.1 + 0.05, -0.02, 0.75), yaw, o)
    fp = _Footprints()
    area = lx * ly
    n_items = int(round(clutter * rng.uniform(0.75, 1.35) * area))  # calibrated: ~1 item per m^2
    tries = 0
    while n_items > 0 and tries < 60 * max(1, n_items):
        tries += 1
        kind = int(rng.integers(0, 9))
        if kind in (0, 1):  # table / desk
            w, d, h = rng.uniform(0.8, 1.6), rng.uniform(0.6, 0.9), rng.uniform(0.7, 0.76)
        elif kind == 2:
            w, d, h = 0.5, 0.5, 0.9
        elif kind == 3:  # shelf
            w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.28, 0.4), rng.uniform(1.2, 2.0)
        elif kind == 4:  # cabinet / counter / fridge
            w, d, h = rng.uniform(0.5, 2.0), rng.uniform(0.45, 0.65), rng.choice([0.9, 0.9, 1.8, 0.75])
        elif kind == 5:  # sofa
            w, d, h = rng.uniform(1.4, 2.2), rng.uniform(0.8, 0.95), 0.85
        elif kind == 6:
            w, d, h = 0.6, 0.6, 1.2
        elif kind == 7:
            w, d, h = 0.5, 0.5, 1.8
        else:  # carton boxes
            w, d, h = rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.6), rng.uniform(0.3, 1.1)
        if rng.random() < 0.6 or kind in (3, 4, 5):  # against a wall
            origin, yaw, length = walls[int(rng.integers(0, 4))]
            if length < w + 0.2:
                continue
            u = rng.uniform(w / 2 + 0.05, length - w / 2 - 0.05)
            yaw_f = yaw  # the item's back (local +y) against the wall
            c = np.asarray(origin[:2]) + rot_z(yaw)[:2, :2] @ np.array([u, -d / 2 - 0.01])
        else:
            yaw_f = rng.uniform(0, 2 * math.pi)
            c = np.array([rng.uniform(0.5, lx - 0.5), rng.uniform(0.5, ly - 0.5)])
        if not fp.free(c, (w / 2, d / 2), keep_out, h):
            continue
        fp.add(c, (w / 2, d / 2), h)
        n_items -= 1
        if kind in (0, 1):
            _table(m, rng, c, yaw_f, w, d, h)
        elif kind == 2:
            _chair(m, rng, c, yaw_f)
        elif kind == 3:
            _shelf(m, rng, c, yaw_f, w, d, h)
        elif kind == 4:
            _cabinet(m, rng, c, yaw_f, w, d, h)
        elif kind == 5:
            _sofa(m, rng, c, yaw_f, w, d)
        elif kind == 6:
            _plant(m, rng, c)
        elif kind == 7:
            _floor_lamp(m, rng, c)
        else:
            z = 0.0
            while z < h:
                s = rng.uniform([0.3, 0.3, 0.2], [0.6, 0.5, 0.5])
                m.box((c[0], c[1], z + s[2] / 2), s, yaw_f + rng.uniform(-0.3, 0.3))
                z += s[2]
    return m


# ----------------------------------------------------------------------------------------------------
# outdoor: a street


def _car(m: MeshBuilder, rng, x, y, yaw) -> None:
    length, width = rng.uniform(3.8, 4.8), rng.uniform(1.65, 1.9)
    r = rot_z(yaw)
    base = np.array([x, y, 0.0])
    clear, body = 0.25, rng.uniform(0.6, 0.8)
    # lower body with bevelled ends (a hexahedron narrower at the top corners)
    lo = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * [length / 2, width / 2, 1.0] + [
        0,
        0,
        clear,
    ]
    hi = lo.copy()
    hi[:, 2] = clear + body
    hi[:, 0] *= 0.96
    hi[:, 1] *= 0.95
    lo[:, 0] *= 0.97
    m.hexahedron(np.vstack([lo, hi]) @ r.T + base)
    # cabin: a frustum-shaped hexahedron (slanted windscreens)
    cl = length * rng.uniform(0.45, 0.6)
    off = rng.uniform(-0.1, 0.25) * length / 2
    ch = rng.uniform(0.45, 0.65)
    z0, z1 = clear + body, clear + body + ch
    cb = np.array([[-cl / 2, -width * 0.46, z0], [cl / 2, -width * 0.46, z0], [cl / 2, width * 0.46, z0],
                   [-cl / 2, width * 0.46, z0]])  # fmt: skip
    ct = cb.copy()
    ct[:, 2] = z1
    ct[:, 0] = ct[:, 0] * 0.62 - 0.1 * cl
    ct[:, 1] *= 0.85
    cab = np.vstack([cb, ct]) + [off, 0, 0]
    m.hexahedron(cab @ r.T + base)
    wheel = rng.uniform(0.3, 0.36)
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = r @ np.array([sx * length * 0.32, sy * (width / 2 - 0.12), wheel]) + base
            m.frustum(c - r[:, 1] * 0.12, r[:, 1], wheel, wheel, 0.24, 14)
    for sy in (-1, 1):  # mirrors
        c = r @ np.array([off + cl / 2 - 0.1, sy * (width / 2 + 0.08), z0 + 0.1]) + base
        m.box(c, (0.1, 0.15, 0.12), yaw)


def _tree(m: MeshBuilder, rng, x, y, z0=0.0) -> None:
    trunk_h, tr = rng.uniform(1.8, 4.0), rng.uniform(0.12, 0.3)
    m.frustum((x, y, z0), (rng.normal(0, 0.05), rng.normal(0, 0.05), 1), tr, tr * 0.7, trunk_h + 0.5, 10)
    crown = rng.uniform(1.5, 3.2)
    for _ in range(int(rng.integers(2, 5))):
        c = np.array([x, y, z0 + trunk_h + crown * 0.8]) + rng.normal(0, crown * 0.35, 3)
        rr = crown * rng.uniform(0.6, 1.0, 3)
        m.ellipsoid(c, rr, rng, jitter=0.25, n_lat=8, n_lon=12)


def _pole(m: MeshBuilder, rng, x, y, z0, side: int) -> None:
    kind = rng.integers(0, 3)
    if kind == 0:  # street lamp
        h = rng.uniform(6.0, 9.0)
        m.frustum((x, y, z0), (0, 0, 1), 0.12, 0.07, h, 10)
        arm = rng.uniform(1.0, 2.5)
        m.box((x, y - side * arm / 2, z0 + h), (0.08, arm, 0.08))
        m.box((x, y - side * arm, z0 + h - 0.1), (0.3, 0.6, 0.15))
    elif kind == 1:  # sign
        h = rng.uniform(2.2, 3.0)
        m.cylinder_z(x, y, z0, 0.04, h, 8)
        if rng.random() < 0.5:
            m.box((x, y, z0 + h), (0.05, 0.65, 0.65))
        else:
            m.frustum((x - 0.03, y, z0 + h), (1, 0, 0), 0.35, 0.35, 0.04, 16)
    else:  # bollard / post box / bin
        m.frustum(
            (x, y, z0), (0, 0, 1), rng.uniform(0.1, 0.35), rng.uniform(0.1, 0.35), rng.uniform(0.8, 1.4), 12
        )


def _building(m: MeshBuilder, rng, x0, x1, y_face, side: int) -> None:
    """A facade between x0 and x1 whose front face is at y = y_face, facing the street (-side * y)."""
    length = x1 - x0
    height = rng.uniform(5.0, 20.0)
    floor_h = rng.uniform(2.8, 3.4)
    nf = max(1, int(height // floor_h))
    openings = []
    detailed = rng.random() < 0.8
    if detailed:
        win_w = rng.uniform(0.8, 1.6)
        pitch = win_w + rng.uniform(0.6, 2.0)
        depth = rng.uniform(0.12, 0.35)
        shop = rng.random() < 0.4
        for f in range(nf):
            z0 = f * floor_h + (0.3 if shop and f == 0 else rng.uniform(0.8, 1.0))
            z1 = f * floor_h + (2.6 if shop and f == 0 else 2.2)
            if z1 > height - 0.3:
                break
            u = rng.uniform(0.5, pitch)
            while u + win_w < length - 0.5:
                if shop and f == 0:
                    w = min(rng.uniform(2.0, 5.0), length - 0.5 - u)
                    openings.append((u, u + w, z0, z1, rng.uniform(0.3, 1.5)))
                    u += w + rng.uniform(0.5, 1.5)
                else:
                    openings.append((u, u + win_w, z0, z1, depth))
                    u += pitch
    # the wall's front face must look at the street: yaw 0 faces -y (side=+1), yaw pi faces +y (side=-1)
    if side > 0:
        m.wall((x0, y_face, 0.0), 0.0, length, height, 0.4, _in_order(openings, length))
    else:
        m.wall((x1, y_face, 0.0), math.pi, length, height, 0.4, _mirror(openings, length))
    m.box(((x0 + x1) / 2, y_face + side * 6.1, height / 2), (length, 9.0, height))  # the building's body
    if detailed:
        for f in range(1, nf):  # cornices between floors
            z = f * floor_h
            m.box(((x0 + x1) / 2, y_face - side * 0.1, z), (length, 0.2, 0.18))
        if rng.random() < 0.4:  # balconies
            for f in range(1, nf):
                u = rng.uniform(0.5, max(0.6, length - 3.5))
                m.box((x0 + u + 1.5, y_face - side * 0.6, f * floor_h + 0.05), (3.0, 1.2, 0.12))
                m.box((x0 + u + 1.5, y_face - side * 1.18, f * floor_h + 0.55), (3.0, 0.05, 1.0))
    m.box(((x0 + x1) / 2, y_face - side * 0.02, height + 0.15), (length + 0.2, 0.5, 0.3))  # roof edge


def _in_order(openings, length):
    return [o for o in openings if o[1] <= length]


def _mirror(openings, length):
    return [(length - u1, length - u0, z0, z1, d) for u0, u1, z0, z1, d in openings]


def _front_garden(m: MeshBuilder, rng, x0, x1, edge, depth, side) -> None:
    """Between the pavement's back edge and a facade `depth` behind it: a low wall, fence or hedge,
    bushes and a path."""
    k = rng.random()
    y = side * (edge + 0.2)
    if k < 0.35:
        m.box(((x0 + x1) / 2, y, 0.4), (x1 - x0 - 1.2, 0.3, rng.uniform(0.5, 1.2)))
    elif k < 0.65:
        h = rng.uniform(0.9, 1.4)
        m.box(((x0 + x1) / 2, y, h / 2 + 0.05), (x1 - x0 - 1.2, 0.04, h * 0.8))
        for u in np.arange(x0 + 0.6, x1 - 0.6, 2.0):
            m.box((u, y, h / 2), (0.12, 0.12, h))
    elif k < 0.9:
        for u in np.arange(x0 + 0.8, x1 - 0.8, 1.2):
            m.ellipsoid((u, y, 0.6), (0.8, 0.6, rng.uniform(0.6, 1.1)), rng, jitter=0.3, n_lat=6, n_lon=10)
    for _ in range(int(rng.integers(0, 4))):  # bushes / bins / bikes in the garden
        u = rng.uniform(x0 + 0.5, x1 - 0.5)
        yy = side * (edge + rng.uniform(0.8, max(1.0, depth - 0.5)))
        r = rng.uniform(0.3, 0.9)
        m.ellipsoid((u, yy, r * 0.8), (r, r, r * 0.9), rng, jitter=0.3, n_lat=6, n_lon=10)


def _in_gaps(x0: float, x1: float, gaps: list[tuple[float, float]]) -> bool:
    return any(x1 > g0 and x0 < g1 for g0, g1 in gaps)


def _street_side(
    m: MeshBuilder,
    rng: np.random.Generator,
    xa: float,
    xb: float,
    road: float,
    walk: float,
    kerb: float,
    side: int,
    clutter: float,
    gaps: list[tuple[float, float]],
) -> None:
    """One side (y > 0 for side=+1) of a street along +x over [xa, xb], leaving `gaps` (crossings) free."""
    edge = road + walk  # back of the pavement
    # kerb and pavement, interrupted at the crossings
    cuts = sorted(g for g in gaps if g[1] > xa and g[0] < xb)
    x = xa
    for g0, g1 in [*cuts, (xb, xb)]:
        if g0 > x:
            m.box(((x + g0) / 2, side * (road + walk / 2), kerb / 2 - 0.05), (g0 - x, walk, kerb + 0.1))
        x = max(x, g1)
    # plots of random length: a building (often behind a front garden), a garden with a house set
    # back, a parking lot, or nothing (an open lot); each plot slightly rotated at times
    x = xa
    while x < xb:
        seg = min(rng.uniform(8.0, 25.0), xb - x)
        kind = rng.random()
        setback = rng.uniform(0.0, 0.5) if rng.random() < 0.5 else rng.uniform(1.5, 6.0)
        yaw = math.radians(rng.normal(0, 5.0)) if rng.random() < 0.4 else 0.0
        if _in_gaps(x, x + seg, gaps) or seg < 3.0:
            x += seg
            continue
        with m.transformed(
            make_pose(rot_z(yaw), np.zeros(3)) if yaw == 0 else _about(yaw, x + seg / 2, side * edge)
        ):
            if kind < 0.55:
                _building(m, rng, x, x + seg, side * (edge + setback), side)
                if setback > 1.0:
                    _front_garden(m, rng, x, x + seg, edge, setback, side)
            elif kind < 0.8:
                _front_garden(m, rng, x, x + seg, edge, setback + 4.0, side)
                for _ in range(int(rng.integers(0, 3))):
                    _tree(m, rng, x + rng.uniform(0, seg), side * (edge + rng.uniform(2, setback + 4)))
                hx = rng.uniform(7, 14)
                m.box(
                    (x + seg / 2, side * (edge + setback + 4 + hx / 2), 0),
                    (seg * rng.uniform(0.5, 0.9), hx, 2 * rng.uniform(4, 9)),
                )
            elif kind < 0.92:  # parking lot: a row of cars, a low wall behind
                for k in range(int(seg / 2.6)):
                    if rng.random() < 0.7:
                        y = side * (edge + 3.0 + rng.normal(0, 0.2))
                        _car(m, rng, x + 1.3 + k * 2.6, y, math.pi / 2 + rng.normal(0, 0.05))
                m.box((x + seg / 2, side * (edge + 6.5), 0.4), (seg, 0.3, 0.8))
        x += seg
    # parked cars along the kerb
    x = xa + rng.uniform(0, 6)
    while x < xb:
        if rng.random() < min(0.95, 0.7 * clutter) and not _in_gaps(x - 3, x + 3, gaps):
            _car(m, rng, x, side * (road - 1.1), rng.normal(0, 0.03) + (0 if rng.random() < 0.5 else math.pi))
            x += rng.uniform(4.8, 6.5)
        else:
            x += rng.uniform(3.0, 12.0)
    # poles, trees and street furniture on the pavement
    x = xa + rng.uniform(0, 10)
    while x < xb:
        k = rng.random()
        if _in_gaps(x - 1, x + 1, gaps):
            pass
        elif k < 0.4:
            _tree(m, rng, x, side * (road + walk * rng.uniform(0.4, 0.7)), kerb)
        elif k < 0.8:
            _pole(m, rng, x, side * (road + 0.4), kerb, side)
        else:  # bench / bin / bike rack / electrical box
            y = side * (road + walk * rng.uniform(0.5, 0.9))
            m.box((x, y, kerb + 0.5), rng.uniform([0.4, 0.3, 0.5], [1.8, 0.7, 1.3]), rng.normal(0, 0.05))
        x += rng.uniform(4.0, 14.0) / max(clutter, 0.1)


def _about(yaw: float, x: float, y: float) -> np.ndarray:
    """A rotation by `yaw` about the vertical axis through (x, y)."""
    p = np.array([x, y, 0.0])
    return make_pose(rot_z(yaw), p - rot_z(yaw) @ p)


def build_street(
    rng: np.random.Generator, x_range: tuple[float, float], clutter: float = 1.0
) -> tuple[MeshBuilder, dict]:
    """A street along +x over `x_range` (sensors near x in [0, 10]): uneven ground, kerbs and
    pavements, facades with recessed windows, gardens, parking lots, parked cars, poles and trees;
    often a crossing street near the sensors. Returns the mesh and {'road_half_width': ...}."""
    m = MeshBuilder()
    xa, xb = x_range
    road = rng.uniform(3.5, 6.0)
    walk = rng.uniform(1.5, 3.5)
    kerb = rng.uniform(0.1, 0.18)
    # ground: a gently uneven grid (1.5% cross-fall, a few cm of relief)
    nx, ny = int((xb - xa) / 4) + 1, 40
    gy = np.linspace(-80, 80, ny + 1)[None, :]
    h = -0.015 * np.minimum(np.abs(gy), road) + rng.normal(0, 0.02, (nx + 1, ny + 1))
    m.height_grid(xa, xb, -80, 80, nx, ny, h)
    crossings = []
    for _ in range(int(rng.choice([0, 1, 1, 2]))):
        xc = rng.uniform(-40.0, 45.0)
        if all(abs(xc - c[0]) > 30 for c in crossings):
            crossings.append(
                (xc, rng.uniform(3.5, 5.5), rng.uniform(1.5, 3.0), math.radians(rng.normal(0, 8)))
            )
    gaps = [(xc - wc - wk, xc + wc + wk) for xc, wc, wk, _ in crossings]
    for side in (-1, 1):
        _street_side(m, rng, xa, xb, road, walk, kerb, side, clutter, gaps)
    for xc, wc, wk, tilt in crossings:
        for side in (-1, 1):  # the crossing street's two arms, each with its two sides
            with m.transformed(make_pose(rot_z(side * math.pi / 2 + tilt), np.array([xc, 0.0, 0.0]))):
                for arm_side in (-1, 1):
                    _street_side(m, rng, road + walk, 75.0, wc, wk, kerb, arm_side, clutter, [])
    return m, {"road_half_width": road}
