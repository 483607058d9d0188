"""Sensor rendering: one rolling LiDAR sweep and one global-shutter camera image from the same geometry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.config import CameraConfig, LidarConfig
from weatheralign.geometry import invert
from weatheralign.world.layout import SceneLayout
from weatheralign.world.raycast import WorldRaycaster
from weatheralign.world.rig import T_EGO_LIDAR, Camera, FiringPattern
from weatheralign.world.shading import encode_srgb, lidar_intensity, shade, sky_colour, texture

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
    return local @ T[:3, :3].T + T[:3, 3]


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
    p_lidar = p_global @ T_lidar_global[:3, :3].T + T_lidar_global[:3, 3]
    points = np.column_stack([p_lidar, intensity, pattern.ring[idx]]).astype(np.float32)
    return LidarSweep(timestamp, points, pattern.time_offsets[idx].astype(np.float32), pattern.column[idx],
                      hits.instance[idx], surf_mat)


def render_camera(caster: WorldRaycaster, camera: Camera, rays_cam: NDArray[np.float32], cfg: CameraConfig,
                  timestamp: float, rng: np.random.Generator) -> CameraFrame:
    """Render ``camera`` exposed at ``timestamp`` [s]; ``rays_cam`` (H*W, 3) are its unit pixel rays
    (`Camera.pixel_rays`). Colour: textured materials lit by sun (with cast shadows) and sky, sky background,
    aerial perspective, sensor noise."""
    layout = caster.layout
    T_global_cam = layout.T_global_ego(timestamp) @ camera.T_ego_cam
    dirs = rays_cam @ T_global_cam[:3, :3].T.astype(np.float32)
    origin = T_global_cam[:3, 3]
    origins = np.broadcast_to(origin.astype(np.float32), dirs.shape)
    hits = caster.cast_at_time(origins, dirs, timestamp)
    hit = np.flatnonzero(np.isfinite(hits.range))
    rgb = np.empty((len(dirs), 3), np.float32)
    miss = np.flatnonzero(~np.isfinite(hits.range))
    rgb[miss] = sky_colour(layout, dirs[miss])
    if len(hit):
        pos = origin + dirs[hit] * hits.range[hit, None]
        normals = hits.normal[hit]
        surf = texture(layout, pos, normals, hits.material[hit], hits.albedo[hit], hits.reflectivity[hit])
        if cfg.shadows:
            start = (pos + SHADOW_EPS * normals).astype(np.float32)
            sun = np.broadcast_to(layout.sun_direction.astype(np.float32), start.shape)
            facing = (normals @ layout.sun_direction) > 0
            shadow = np.ones(len(hit), bool)
            shadow[facing] = caster.occluded_at_time(start[facing], sun[facing], timestamp)
        else:
            shadow = (normals @ layout.sun_direction) <= 0
        rgb[hit] = shade(layout, surf, normals, dirs[hit], shadow, hits.range[hit])
    noise = rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(cfg.noise_std) if cfg.noise_std else None
    image = encode_srgb(rgb, noise).reshape(camera.height, camera.width, 3)
    rng_map = hits.range.astype(np.float32).reshape(camera.height, camera.width)
    inst = hits.instance.reshape(camera.height, camera.width)
    return CameraFrame(timestamp, image, rng_map, inst)
