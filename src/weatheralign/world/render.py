"""Sensor rendering: one rolling LiDAR sweep and one global-shutter camera image from the same geometry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.config import CameraConfig, LidarConfig
from weatheralign.geometry import apply, invert
from weatheralign.world.layout import SceneLayout
from weatheralign.world.raycast import Hits, WorldRaycaster
from weatheralign.sensors import FiringPattern
from weatheralign.world.rig import T_EGO_LIDAR, Camera
from weatheralign.world.shading import camera_pixels, lidar_intensity, texture

SHADOW_EPS = 0.02  # m, shadow ray start offset along the normal


@dataclass(frozen=True)
class LidarSweep:
    """A rendered sweep. ``points`` (N, 5) float32 (x, y, z, intensity 0..255, ring) in the LiDAR frame at
    ``timestamp`` (ego motion compensated); per point: ``time_offsets`` (N,) float32 s (<= 0), ``column`` (N,) int16
    firing column, ``instance`` (N,) int32 actor id (0 = background), ``material`` (N,) uint8."""

    timestamp: float
    points: NDArray[np.float32]
    time_offsets: NDArray[np.float32]
    column: NDArray[np.int16]
    instance: NDArray[np.int32]
    material: NDArray[np.uint8]


@dataclass(frozen=True)
class CameraFrame:
    """A rendered image (H, W, 3) uint8 sRGB, its exact ray length per pixel ``range`` (H, W) float32 metres (inf =
    sky), and the actor id per pixel ``instance`` (H, W) int32."""

    timestamp: float
    image: NDArray[np.uint8]
    range: NDArray[np.float32]
    instance: NDArray[np.int32]


def ego_positions(layout: SceneLayout, times: NDArray) -> NDArray[np.float64]:
    """(N, 3) global ego positions at ``times`` (N,) [s] (the ego's heading is constant in a scene)."""
    T = layout.T_global_scene
    x = layout.ego_speed * (np.asarray(times) - layout.t_start)
    local = np.stack([x, np.full_like(x, layout.ego_lane_y), np.zeros_like(x)], 1)
    return apply(T, local)


def render_lidar_sweep(caster: WorldRaycaster, pattern: FiringPattern, cfg: LidarConfig, timestamp: float,
                       rng: np.random.Generator) -> LidarSweep:
    """Render the sweep ending at ``timestamp`` [s]: each beam fires at its own time from where the sensor is then.

    Returns only beams with a detectable return within ``[min_range, max_range]``; range noise is Gaussian,
    clipped to +-2 sigma, so no point crosses the sensor or the maximum range by noise.
    """
    layout = caster.layout
    times = timestamp + pattern.time_offsets
    R = layout.T_global_scene[:3, :3]  # ego -> global rotation (constant)
    R_gl = R @ T_EGO_LIDAR[:3, :3]
    origins = ego_positions(layout, times) + R @ T_EGO_LIDAR[:3, 3]
    dirs = pattern.directions @ R_gl.T
    hits = caster.cast_rolling(origins, dirs, times)

    sigma = cfg.range_noise_std_m
    noise = np.clip(rng.normal(0.0, sigma, len(times)), -2 * sigma, 2 * sigma) if sigma > 0 else 0.0
    measured = hits.range + noise
    valid = np.isfinite(hits.range) & (measured >= cfg.min_range_m) & (measured <= cfg.max_range_m)
    idx = np.flatnonzero(valid)
    pos = origins[idx] + dirs[idx] * hits.range[idx, None]
    surf = texture(layout, pos, hits.normal[idx], hits.material[idx], hits.albedo[idx], hits.reflectivity[idx])
    cos_inc = np.einsum("ij,ij->i", hits.normal[idx], dirs[idx])
    raw = lidar_intensity(surf.reflectivity, cos_inc, measured[idx])
    detectable = raw >= cfg.min_detectable_intensity
    idx, raw, surf_mat = idx[detectable], raw[detectable], surf.material[detectable]
    intensity = np.clip(np.round(raw + rng.normal(0.0, cfg.intensity_noise_std, len(idx))), 0, 255)

    p_global = origins[idx] + dirs[idx] * measured[idx, None]
    T_lidar_global = invert(layout.T_global_ego(timestamp) @ T_EGO_LIDAR)
    p_lidar = apply(T_lidar_global, p_global)
    points = np.column_stack([p_lidar, intensity, pattern.ring[idx]]).astype(np.float32)
    return LidarSweep(timestamp, points, pattern.time_offsets[idx].astype(np.float32), pattern.column[idx],
                      hits.instance[idx], surf_mat)


@njit(nogil=True, cache=True)
def _camera_dirs(K: NDArray, R: NDArray, width: int, height: int) -> NDArray[np.float32]:
    out = np.empty((height * width, 3), np.float32)
    for v in range(height):
        y = (v - K[1, 2]) / K[1, 1]
        for u in range(width):
            x = (u - K[0, 2]) / K[0, 0]
            inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
            i = v * width + u
            for c in range(3):
                out[i, c] = (R[c, 0] * x + R[c, 1] * y + R[c, 2]) * inv
    return out


def pixel_directions(camera: Camera, T_global_cam: NDArray) -> NDArray[np.float32]:
    """(H*W, 3) unit global directions of the rays through the pixel centres (row-major: u = col, v = row) of
    ``camera`` posed at ``T_global_cam`` (4, 4)."""
    return _camera_dirs(camera.K, np.ascontiguousarray(T_global_cam[:3, :3]), camera.width, camera.height)


@njit(nogil=True, cache=True)
def _shadow_starts(origin: NDArray, dirs: NDArray, ranges: NDArray, normals: NDArray,
                   sun: NDArray) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Hits whose surface faces the sun: their indices (M,) and shadow-ray origins (M, 3) float32, ``SHADOW_EPS``
    off the surface along the normal."""
    idx = np.empty(len(dirs), np.int64)
    starts = np.empty((len(dirs), 3), np.float32)
    m = 0
    for i in range(len(dirs)):
        if not np.isfinite(ranges[i]) or normals[i, 0] * sun[0] + normals[i, 1] * sun[1] + normals[i, 2] * sun[2] <= 0:
            continue
        for c in range(3):
            starts[m, c] = origin[c] + dirs[i, c] * ranges[i] + SHADOW_EPS * normals[i, c]
        idx[m] = i
        m += 1
    return idx[:m], starts[:m]


def sun_lit(caster: WorldRaycaster, origin: NDArray, dirs: NDArray, hits: Hits, timestamp: float,
            shadows: bool) -> NDArray[np.bool_]:
    """(N,) whether the sun lights each camera hit (rays from ``origin`` (3,) along ``dirs`` (N, 3)): the surface faces
    the sun and, with ``shadows``, nothing blocks the way to it at ``timestamp`` [s]."""
    idx, starts = _shadow_starts(np.asarray(origin, np.float64), dirs, hits.range, hits.normal,
                                 caster.layout.sun_direction)
    lit = np.zeros(len(dirs), bool)
    lit[idx] = ~caster.sun_blocked(starts, timestamp) if shadows else True
    return lit


def render_camera(caster: WorldRaycaster, camera: Camera, cfg: CameraConfig, timestamp: float,
                  rng: np.random.Generator) -> CameraFrame:
    """Render ``camera`` exposed at ``timestamp`` [s]. Colour: textured materials lit by sun (with cast shadows) and
    sky, sky background, aerial perspective, sensor noise."""
    layout = caster.layout
    T_global_cam = layout.T_global_ego(timestamp) @ camera.T_ego_cam
    dirs = pixel_directions(camera, T_global_cam)
    origin = T_global_cam[:3, 3]
    hits = caster.cast_camera(camera.K, T_global_cam, camera.width, camera.height, timestamp, dirs)
    lit = sun_lit(caster, origin, dirs, hits, timestamp, cfg.shadows)
    noise = rng.standard_normal(dirs.shape, dtype=np.float32) if cfg.noise_std else None
    image = camera_pixels(layout, origin, dirs, hits.range, hits.normal, hits.material, hits.albedo,
                          hits.reflectivity, lit, noise, cfg.noise_std).reshape(camera.height, camera.width, 3)
    rng_map = hits.range.astype(np.float32).reshape(camera.height, camera.width)
    inst = hits.instance.reshape(camera.height, camera.width)
    return CameraFrame(timestamp, image, rng_map, inst)
