"""Surface appearance shared by the sensors: procedural textures (albedo + LiDAR reflectivity) and camera shading.

Camera colours are computed in linear RGB and encoded to sRGB; LiDAR intensity uses the textured reflectivity, so a
lane marking is bright in the image and in the scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.world.layout import SceneLayout
from weatheralign.world.materials import (SPECULAR, Material, facade_window_mask, road_marking_mask, value_noise)

F32 = NDArray[np.float32]

# Clear-air extinction for the camera's aerial perspective: meteorological optical range 30 km.
CLEAR_AIR_EXTINCTION = float(np.log(20.0) / 30000.0)


@dataclass(frozen=True)
class Surface:
    """Textured surface properties at hit points: material (N,) uint8, albedo (N, 3) linear RGB, reflectivity (N,)."""

    material: NDArray[np.uint8]
    albedo: F32
    reflectivity: F32


def texture(layout: SceneLayout, positions: NDArray, normals: NDArray, material: NDArray, albedo: NDArray,
            reflectivity: NDArray) -> Surface:
    """Apply procedural detail at global hit ``positions`` (N, 3) with unit ``normals`` (N, 3).

    Returns new arrays; facade windows and bus windows turn into `Material.GLASS`.
    """
    mat = material.copy()
    alb = albedo.astype(np.float32, copy=True)
    refl = reflectivity.astype(np.float32, copy=True)
    T = layout.T_scene_global
    p = positions @ T[:3, :3].T + T[:3, 3]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    road = layout.road

    sel = np.flatnonzero(material == Material.ROAD)
    if len(sel):
        xs, ys = x[sel], y[sel]
        n = 0.75 + 0.35 * value_noise(xs, ys, 0.9) + 0.15 * value_noise(xs, ys, 0.07)
        alb[sel] *= n[:, None]
        paint = road_marking_mask(xs, ys, road.road_half_width, 3.5, road.lanes_per_direction, road.crossing_x,
                                  road.crossing_half_width)
        alb[sel[paint]] = np.array([0.78, 0.78, 0.74], np.float32) * (0.85 + 0.15 * n[paint, None])
        refl[sel[paint]] = 0.85
        lot = (np.abs(ys) > road.road_half_width + road.sidewalk_width) & ~paint
        alb[sel[lot]] = np.array([0.3, 0.29, 0.27], np.float32) * n[lot, None]

    sel = np.flatnonzero(material == Material.SIDEWALK)
    if len(sel):
        xs, ys = x[sel], y[sel]
        seam = (np.mod(xs, 1.5) < 0.04) | (np.mod(ys, 1.5) < 0.04)
        n = 0.85 + 0.25 * value_noise(xs, ys, 0.5)
        alb[sel] *= (n * np.where(seam, 0.6, 1.0))[:, None]

    sel = np.flatnonzero(material == Material.FACADE)
    if len(sel):
        nx = np.abs(normals[sel] @ T[:3, :3].T)[:, 0]
        u = np.where(nx > 0.7, y[sel], x[sel])
        phase = 0.37 * np.floor(np.abs(np.where(nx > 0.7, x[sel], y[sel])))
        win = facade_window_mask(u, z[sel], 3.0, 3.3, phase)
        n = 0.85 + 0.25 * value_noise(u, z[sel], 0.35)
        alb[sel] *= n[:, None]
        w = sel[win]
        alb[w] = np.array([0.05, 0.06, 0.08], np.float32)
        refl[w] = 0.08
        mat[w] = Material.GLASS

    sel = np.flatnonzero(material == Material.BUS_BODY)
    if len(sel):
        band = (z[sel] > 1.15) & (z[sel] < 2.5)
        w = sel[band]
        alb[w] = np.array([0.05, 0.06, 0.07], np.float32)
        refl[w] = 0.1
        mat[w] = Material.GLASS

    sel = np.flatnonzero(material == Material.CONE)
    if len(sel):
        band = (np.mod(z[sel], 1.0) > 0.38) & (np.mod(z[sel], 1.0) < 0.52)
        alb[sel[band]] = np.array([0.85, 0.85, 0.85], np.float32)
        refl[sel[band]] = 0.95

    sel = np.flatnonzero(material == Material.BARRIER)
    if len(sel):
        stripe = np.mod(x[sel] + y[sel] + z[sel], 0.8) < 0.4
        alb[sel[stripe]] = np.array([0.85, 0.85, 0.85], np.float32)
        refl[sel[stripe]] = 0.8

    sel = np.flatnonzero(material == Material.FOLIAGE)
    if len(sel):
        alb[sel] *= (0.6 + 0.8 * value_noise(x[sel] + z[sel], y[sel] - z[sel], 0.25))[:, None]
    return Surface(mat, alb, refl)


def sky_colour(layout: SceneLayout, directions: NDArray) -> F32:
    """Linear RGB (N, 3) of the sky seen along global unit ``directions`` (N, 3): horizon-to-zenith gradient plus a
    sun glow."""
    d = directions.astype(np.float32, copy=False)
    horizon = layout.sky_horizon.astype(np.float32)
    zenith = layout.sky_zenith.astype(np.float32)
    w = np.sqrt(np.clip(d[:, 2], 0.0, 1.0))[:, None]
    base = horizon[None] + (zenith - horizon)[None] * w
    cos_sun = d @ layout.sun_direction.astype(np.float32)
    near = np.flatnonzero(cos_sun > 0.6)
    if len(near):
        c = cos_sun[near]
        c8 = (c * c) ** 4
        glow = 0.6 * (c8 * c8) ** 4 + 0.15 * c8
        base[near] += glow[:, None] * np.array([1.0, 0.95, 0.85], np.float32)
    base[d[:, 2] < 0] = horizon * 0.8
    return base


def shade(layout: SceneLayout, surface: Surface, normals: NDArray, view_dirs: NDArray, in_shadow: NDArray,
          ranges: NDArray) -> F32:
    """Linear RGB (N, 3) of lit surfaces: sky ambient + sun (Lambert, shadowed) + sky reflection on glass/paint,
    then clear-air aerial perspective over the ray length ``ranges`` (N,) [m]."""
    sun = layout.sun_direction.astype(np.float32)
    n = normals.astype(np.float32, copy=False)
    lambert = np.clip(n @ sun, 0.0, 1.0) * (~in_shadow)
    sky_ambient = (0.9 * (0.55 * layout.sky_zenith + 0.45 * layout.sky_horizon)).astype(np.float32)
    light = (0.55 + 0.45 * n[:, 2])[:, None] * sky_ambient[None] + (2.4 * lambert)[:, None] * np.array(
        [1.0, 0.96, 0.9], np.float32)
    colour = surface.albedo * light
    spec = SPECULAR[surface.material]
    shiny = np.flatnonzero(spec > 0)
    if len(shiny):
        d = view_dirs[shiny]
        nn = n[shiny]
        refl_dir = d - 2 * np.einsum("ij,ij->i", d, nn)[:, None] * nn
        cos_i = np.abs(np.einsum("ij,ij->i", d, nn))
        fresnel = spec[shiny] + (1 - spec[shiny]) * (1 - cos_i) ** 5 * 0.5
        colour[shiny] = colour[shiny] * (1 - fresnel[:, None]) + fresnel[:, None] * sky_colour(layout, refl_dir)
    lamps = surface.material == Material.LAMP
    colour[lamps] += 0.3 * surface.albedo[lamps]
    t = np.exp(np.float32(-CLEAR_AIR_EXTINCTION) * ranges.astype(np.float32))[:, None]
    return colour * t + layout.sky_horizon.astype(np.float32)[None] * (1 - t)


def encode_srgb(linear: NDArray, noise: NDArray | None = None) -> NDArray[np.uint8]:
    """uint8 sRGB from linear RGB (..., 3) in [0, ~1]; optional additive ``noise`` in encoded units (0..1)."""
    x = np.clip(linear.astype(np.float32, copy=False), np.float32(0.0031308), np.float32(1.0))
    s = np.float32(1.055) * np.power(x, np.float32(1 / 2.4)) - np.float32(0.055)  # x <= 0.0031 is below 1/255
    if noise is not None:
        s = s + noise
    return np.clip(np.round(s * 255.0), 0, 255).astype(np.uint8)


def lidar_intensity(reflectivity: NDArray, cos_incidence: NDArray, ranges: NDArray) -> F32:
    """Raw intensity on the 0..255 scale from reflectivity (N,), |cos incidence| (N,) and range (N,) [m].

    Lambertian return ``rho cos(theta)`` with the sensor's partial range compensation, modelled as a 1/R fall-off
    beyond 10 m (raw power falls as 1/R^2; the HDL-32E reports a range-compensated value).
    """
    falloff = np.minimum(1.0, 10.0 / np.maximum(ranges, 1e-3))
    return (255.0 * reflectivity * np.abs(cos_incidence) * falloff).astype(np.float32)
