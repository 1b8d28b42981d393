"""Procedural scenes and simulated sensors for the synthetic dataset.

Scenes are triangle meshes made of simple parts (boxes, frusta, ellipsoids, walls with recessed
openings): an indoor room with furniture, or an outdoor street with facades, cars, poles and trees.
They are ray cast with Open3D's `RaycastingScene` from two sensor poses: a pinhole depth camera
(fragments fused from a few nearby frames, like 3DMatch) or a spinning 64-beam LiDAR (like KITTI's
HDL-64E). Every random choice comes from the numpy Generator passed in, so a seed fixes the output.

World frame: z up, metres. Camera frame (OpenCV): x right, y down, z forward. LiDAR frame: x forward,
y left, z up.
"""

from fastmac_exp.datasets.scenes.geometry import (
    inv_pose,
    make_pose,
    rot_z,
    rotation_angle_deg,
    transform,
    voxel_downsample,
)
from fastmac_exp.datasets.scenes.indoor import furnish_room, room_size
from fastmac_exp.datasets.scenes.meshes import MeshBuilder, RayCaster
from fastmac_exp.datasets.scenes.outdoor import build_street
from fastmac_exp.datasets.scenes.sensors import DepthCamera, SpinningLidar, camera_pose, lidar_pose
from fastmac_exp.geometry.transforms import random_rotation, rot_axis_angle

__all__ = [
    "DepthCamera",
    "MeshBuilder",
    "RayCaster",
    "SpinningLidar",
    "build_street",
    "camera_pose",
    "furnish_room",
    "inv_pose",
    "lidar_pose",
    "make_pose",
    "random_rotation",
    "room_size",
    "rot_axis_angle",
    "rot_z",
    "rotation_angle_deg",
    "transform",
    "voxel_downsample",
]
