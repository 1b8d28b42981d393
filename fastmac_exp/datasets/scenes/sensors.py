"""The simulated sensors: a pinhole depth camera and a spinning 64-beam LiDAR, with their poses."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fastmac_exp.datasets.scenes.geometry import make_pose, rot_z
from fastmac_exp.datasets.scenes.meshes import RayCaster
from fastmac_exp.geometry.transforms import rot_axis_angle


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
