"""Outdoor scenes: a street with facades, front gardens, cars, poles and trees."""

from __future__ import annotations

import math

import numpy as np

from fastmac_exp.datasets.scenes.geometry import make_pose, rot_z
from fastmac_exp.datasets.scenes.meshes import MeshBuilder


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
