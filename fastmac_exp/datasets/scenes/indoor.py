"""Indoor scenes: a furnished room (tables, chairs, shelves, cabinets, sofas, plants, lamps)."""

from __future__ import annotations

import math

import numpy as np

from fastmac_exp.datasets.scenes.geometry import rot_z
from fastmac_exp.datasets.scenes.meshes import MeshBuilder


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
