"""Sensor rendering: one rolling LiDAR sweep and one global-shutter camera image from the same geometry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.config import CameraConfig
from weatheralign.geometry import apply, invert
from weatheralign.sensors import FiringPattern, LidarModel
from weatheralign.world.layout import SceneLayout
from weatheralign.world.raster import SunGrid, sun_grid
from weatheralign.world.raycast import Hits, WorldRaycaster
from weatheralign.world.rig import T_EGO_LIDAR, Camera
from weatheralign.world.shading import SHADOW_EPS, camera_frame, lidar_returns, noise_key


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


@njit(nogil=True, cache=True)
def _beam_rays(directions: NDArray, times: NDArray, start: NDArray, velocity: NDArray, t_start: float,
               R_gl: NDArray, origins: NDArray, dirs: NDArray) -> None:
    """Global origins and unit directions (N, 3) of beams with sensor-frame ``directions`` (N, 3) fired at ``times``
    (N,) [s]: the sensor at ``start + velocity (t - t_start)`` ((3,) each), sensor -> global rotation ``R_gl``."""
    for i in range(len(times)):
        dt = times[i] - t_start
        for c in range(3):
            origins[i, c] = start[c] + velocity[c] * dt
            dirs[i, c] = R_gl[c, 0] * directions[i, 0] + R_gl[c, 1] * directions[i, 1] + R_gl[c, 2] * directions[i, 2]


@njit(nogil=True, cache=True)
def _sweep_points(origins: NDArray, dirs: NDArray, measured: NDArray, idx: NDArray, intensity: NDArray,
                  ring: NDArray, T: NDArray, out: NDArray) -> None:
    """Points (M, 5) float32 ``(x, y, z, intensity, ring)`` of beams ``idx`` at their ``measured`` range, in the
    frame ``T`` (4, 4) maps global points into."""
    for k in range(len(idx)):
        i = idx[k]
        p = (origins[i, 0] + dirs[i, 0] * measured[i], origins[i, 1] + dirs[i, 1] * measured[i],
             origins[i, 2] + dirs[i, 2] * measured[i])
        for c in range(3):
            out[k, c] = T[c, 0] * p[0] + T[c, 1] * p[1] + T[c, 2] * p[2] + T[c, 3]
        out[k, 3] = intensity[k]
        out[k, 4] = ring[i]


def render_lidar_sweep(caster: WorldRaycaster, pattern: FiringPattern, lidar: LidarModel, timestamp: float,
                       rng: np.random.Generator) -> LidarSweep:
    """Render the sweep of ``lidar`` (its firing ``pattern``) ending at ``timestamp`` [s]: each beam fires at its own
    time from where the sensor is then.

    Returns only beams with a detectable return within ``[min_range, max_range]`` (`lidar_returns`: the noise-free
    intensity at or above the floor at the measured range); range noise is Gaussian, clipped to +-2 sigma, so no
    point crosses the sensor or the maximum range by noise; the intensity is read with the detector's noise (its
    constant part scaled with the floor, `LidarModel.floor_scale`) and rounded to whole values.
    """
    layout = caster.layout
    times = timestamp + pattern.time_offsets
    R = layout.T_global_scene[:3, :3]  # ego -> global rotation (constant)
    start = apply(layout.T_global_scene, np.array([[0.0, layout.ego_lane_y, 0.0]]))[0] + R @ T_EGO_LIDAR[:3, 3]
    n = len(times)
    origins, dirs = np.empty((n, 3)), np.empty((n, 3))
    _beam_rays(pattern.directions, times, start, R[:, 0] * layout.ego_speed, layout.t_start,
               R @ T_EGO_LIDAR[:3, :3], origins, dirs)
    hits = caster.cast_rolling(origins, dirs, times)

    sigma = lidar.range_noise_std_m
    noise = np.clip(rng.normal(0.0, sigma, n), -2 * sigma, 2 * sigma) if sigma > 0 else np.zeros(n)
    idx, raw, surf_mat = lidar_returns(layout, origins, dirs, hits.range, noise, hits.normal, hits.material,
                                       hits.albedo, hits.reflectivity, lidar)
    std = lidar.intensity_noise_std * lidar.floor_scale(hits.range[idx] + noise[idx])
    intensity = np.clip(np.round(raw + std * rng.normal(0.0, 1.0, len(idx))), 0, 255)
    T_lidar_global = invert(layout.T_global_ego(timestamp) @ T_EGO_LIDAR)
    points = np.empty((len(idx), 5), np.float32)
    _sweep_points(origins, dirs, hits.range + noise, idx, intensity, pattern.ring, T_lidar_global, points)
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
                   sun: NDArray) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Hits whose surface faces the sun: their indices (M,) and shadow-ray origins (M, 3), ``SHADOW_EPS`` off the
    surface along the normal."""
    idx = np.empty(len(dirs), np.int64)
    starts = np.empty((len(dirs), 3), np.float64)
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
    sky, sky background, aerial perspective, sensor noise (keyed by ``rng``, `shading.camera_noise`).

    The visible triangle per pixel comes from `WorldRaycaster.camera_depth`; directions, hits, shadow rays, noise and
    shading then run in one pass (`shading.camera_frame`), byte for byte what `pixel_directions`,
    `WorldRaycaster.cast_camera`, `sun_lit`, `shading.camera_noise` and `shading.camera_pixels` give in turn."""
    layout = caster.layout
    T_global_cam = layout.T_global_ego(timestamp) @ camera.T_ego_cam
    inv_depth, gid, tris = caster.camera_depth(camera.K, T_global_cam, camera.width, camera.height, timestamp)
    key = noise_key(rng)
    if cfg.shadows:
        static_grid, moving_grid = caster.static_sun_grid, caster.moving_sun_grid(timestamp)
    else:
        static_grid, moving_grid = empty_sun_grid(layout.sun_direction), None
    image, rng_map, inst = camera_frame(layout, T_global_cam[:3, 3], T_global_cam[:3, :3], camera.K, inv_depth, gid,
                                        tris, static_grid, moving_grid, shadows=cfg.shadows, key=key,
                                        noise_std=cfg.noise_std, height=camera.height, width=camera.width)
    return CameraFrame(timestamp, image, rng_map, inst)


def empty_sun_grid(sun: NDArray) -> SunGrid:
    """A `SunGrid` without triangles (blocks nothing) for the unit ``sun`` (3,)."""
    return sun_grid(np.zeros((0, 3)), np.zeros((0, 3), np.int64), sun)
