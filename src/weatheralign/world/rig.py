"""The nuScenes-like sensor rig: a Velodyne HDL-32E-like LIDAR_TOP and six cameras.

Sweep timing follows nuScenes: the LiDAR spins clockwise seen from above, starting at the left (+y of the ego), and
a sweep's timestamp is the end of its rotation. Each camera is exposed when the sweep crosses its optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.config import LidarConfig
from weatheralign.data.nuscenes import SWEEP_START_AZIMUTH, sweep_fraction_at_azimuth
from weatheralign.data.rings import HDL32E_ELEVATIONS_DEG
from weatheralign.geometry import camera_rotation_from_yaw, make_transform

F64 = NDArray[np.float64]

# Laser firing within one column: 32 lasers fire 1.152 us apart (HDL-32E datasheet timing).
LASER_FIRING_STEP_S = 1.152e-6
T_EGO_LIDAR = make_transform(np.eye(3), np.array([0.943, 0.0, 1.84]))


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
        K = np.array([[spec.focal * sx, 0.0, (FULL_WIDTH / 2) * sx], [0.0, spec.focal * sy, (FULL_HEIGHT / 2 + 20) * sy],
                      [0.0, 0.0, 1.0]])
        yaw = np.deg2rad(spec.yaw_deg)
        T = make_transform(camera_rotation_from_yaw(yaw), np.array(spec.position))
        cams.append(Camera(spec.channel, K, width, height, T, yaw))
    return tuple(cams)


def camera_time_offset(camera: Camera, period: float) -> float:
    """Exposure time of ``camera`` relative to the end of the sweep [s] (negative): when the sweep crosses its axis."""
    return float((sweep_fraction_at_azimuth(camera.yaw) - 1.0) * period)


@dataclass(frozen=True)
class FiringPattern:
    """All beams of one sweep, in the LiDAR frame.

    Attributes:
        directions: (R*C, 3) unit beam directions; ring-major order is NOT used: index = column * R + ring.
        ring: (R*C,) ring index (0 = highest elevation); column: (R*C,) firing column 0..C-1.
        time_offsets: (R*C,) firing time relative to the sweep end [s], in [-period, 0).
    """

    directions: NDArray[np.float64]
    ring: NDArray[np.int16]
    column: NDArray[np.int16]
    time_offsets: NDArray[np.float64]
    elevations_deg: NDArray[np.float64]
    period: float


def firing_pattern(cfg: LidarConfig) -> FiringPattern:
    """The HDL-32E-like firing grid: 32 rings x ``cfg.firings_per_ring`` columns over one clockwise turn."""
    elev = np.deg2rad(HDL32E_ELEVATIONS_DEG)
    rings = len(elev)
    columns = cfg.firings_per_ring
    period = 1.0 / cfg.frequency_hz
    col = np.repeat(np.arange(columns), rings)
    ring = np.tile(np.arange(rings), columns)
    azimuth = SWEEP_START_AZIMUTH - 2 * np.pi * (col + 0.5) / columns
    e = elev[ring]
    d = np.stack([np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.sin(e)], 1)
    t = (col / columns - 1.0) * period + ring * LASER_FIRING_STEP_S  # < 0: 32 lasers fit in one column period
    return FiringPattern(d, ring.astype(np.int16), col.astype(np.int16), t, HDL32E_ELEVATIONS_DEG, period)
