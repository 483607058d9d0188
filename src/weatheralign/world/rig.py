"""The nuScenes-like sensor rig: the LIDAR_TOP's mounting (as nuScenes': x right, y forward) and six cameras (the
LiDAR's firing grid is its `weatheralign.sensors.LidarModel`'s).

Sweep timing follows nuScenes: the LiDAR spins clockwise seen from above, starting at the left (+y of the ego), and
a sweep's timestamp is the end of its rotation. Each camera is exposed when the sweep crosses its optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.data.nuscenes import LIDAR_TOP_YAW, sweep_fraction_at_azimuth
from weatheralign.geometry import camera_rotation_from_yaw, make_transform, yaw_matrix

F64 = NDArray[np.float64]

T_EGO_LIDAR = make_transform(yaw_matrix(LIDAR_TOP_YAW), np.array([0.943, 0.0, 1.84]))


@dataclass(frozen=True)
class CameraSpec:
    """A camera at full nuScenes resolution (1600 x 900): focal length [px], mounting position [m], yaw [rad]."""

    channel: str
    focal: float
    position: tuple[float, float, float]
    yaw_deg: float


# Intrinsics and mounting in the spirit of the nuScenes rig (focal lengths and positions rounded from it).
CAMERAS: tuple[CameraSpec, ...] = (
    CameraSpec("CAM_FRONT", 1266.4, (1.70, 0.016, 1.51), 0.0),
    CameraSpec("CAM_FRONT_RIGHT", 1260.8, (1.55, -0.49, 1.50), -55.0),
    CameraSpec("CAM_FRONT_LEFT", 1272.6, (1.52, 0.49, 1.51), 55.0),
    CameraSpec("CAM_BACK", 809.2, (0.03, 0.0, 1.57), 180.0),
    CameraSpec("CAM_BACK_LEFT", 1256.7, (1.04, 0.48, 1.56), 110.0),
    CameraSpec("CAM_BACK_RIGHT", 1259.5, (1.03, -0.48, 1.55), -110.0),
)
FULL_WIDTH, FULL_HEIGHT = 1600, 900


@dataclass(frozen=True)
class Camera:
    """A camera of the rig at a given image scale: intrinsics ``K`` (3, 3), size, ``T_ego_cam`` (4, 4)."""

    channel: str
    K: F64
    width: int
    height: int
    T_ego_cam: F64
    yaw: float


def make_cameras(image_scale: float) -> tuple[Camera, ...]:
    """The six cameras at ``image_scale`` of 1600 x 900 (intrinsics scaled accordingly)."""
    width, height = int(round(FULL_WIDTH * image_scale)), int(round(FULL_HEIGHT * image_scale))
    sx, sy = width / FULL_WIDTH, height / FULL_HEIGHT
    cams = []
    for spec in CAMERAS:
        K = np.array([[spec.focal * sx, 0.0, (FULL_WIDTH / 2) * sx],
                      [0.0, spec.focal * sy, (FULL_HEIGHT / 2 + 20) * sy],
                      [0.0, 0.0, 1.0]])
        yaw = np.deg2rad(spec.yaw_deg)
        T = make_transform(camera_rotation_from_yaw(yaw), np.array(spec.position))
        cams.append(Camera(spec.channel, K, width, height, T, yaw))
    return tuple(cams)


def camera_time_offset(camera: Camera, period: float) -> float:
    """Exposure time of ``camera`` relative to the end of the sweep [s] (negative): when the sweep crosses its axis."""
    return float((sweep_fraction_at_azimuth(camera.yaw) - 1.0) * period)
