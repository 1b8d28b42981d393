"""Triangle meshes from simple parts (boxes, frusta, ellipsoids, walls with openings) and their ray caster."""

from __future__ import annotations

import contextlib

import numpy as np

from fastmac_exp.datasets.scenes.geometry import rot_z

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
