"""Surface appearance shared by the sensors: procedural textures (albedo + LiDAR reflectivity) and camera shading.

Camera colours are computed in linear RGB and encoded to sRGB; LiDAR intensity uses the textured reflectivity, so a
lane marking is bright in the image and in the scan. Texturing and shading run per hit point in numba kernels (one
fused pass per camera image); they release the GIL, so concurrent samples render in parallel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.world.layout import LANE_WIDTH, SceneLayout
from weatheralign.world.materials import SPECULAR, Material, facade_window, road_marking, value_noise, wrap

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

# Clear-air extinction for the camera's aerial perspective: meteorological optical range 30 km.
CLEAR_AIR_EXTINCTION = float(np.log(20.0) / 30000.0)
SUN_COLOUR = (1.0, 0.96, 0.9)
SUN_GLOW_COLOUR = (1.0, 0.95, 0.85)


@dataclass(frozen=True)
class Surface:
    """Textured surface properties at hit points: material (N,) uint8, albedo (N, 3) linear RGB, reflectivity (N,)."""

    material: NDArray[np.uint8]
    albedo: F32
    reflectivity: F32


Vec3 = tuple[float, float, float]


class Look(NamedTuple):
    """What texturing and shading need from a `SceneLayout`, as plain numbers (tuples) for the kernels.

    ``scene_rows`` (3 x 3) and ``scene_offset`` (3) map global points to the scene frame (``R p + t``, R by rows);
    road geometry in metres (``crossing_x`` NaN: no cross street); ``sun`` global unit vector towards the sun; sky
    colours in linear RGB."""

    scene_rows: tuple[Vec3, Vec3, Vec3]
    scene_offset: Vec3
    road_half_width: float
    sidewalk_width: float
    lanes_per_direction: int
    crossing_x: float
    crossing_half_width: float
    sun: Vec3
    sky_zenith: Vec3
    sky_horizon: Vec3


def _vec3(v: NDArray) -> Vec3:
    return float(v[0]), float(v[1]), float(v[2])


def scene_look(layout: SceneLayout) -> Look:
    """The `Look` of ``layout``."""
    T = layout.T_scene_global
    road = layout.road
    crossing_x = np.nan if road.crossing_x is None else float(road.crossing_x)
    rows = (_vec3(T[0, :3]), _vec3(T[1, :3]), _vec3(T[2, :3]))
    return Look(rows, _vec3(T[:3, 3]), float(road.road_half_width), float(road.sidewalk_width),
                int(road.lanes_per_direction), crossing_x, float(road.crossing_half_width),
                _vec3(layout.sun_direction), _vec3(layout.sky_zenith), _vec3(layout.sky_horizon))


@njit(nogil=True, cache=True, inline="always")
def _dot(a: Vec3, b: Vec3) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(nogil=True, cache=True, inline="always")
def _scale(a: Vec3, s: float) -> Vec3:
    return a[0] * s, a[1] * s, a[2] * s


@njit(nogil=True, cache=True, inline="always")
def _texture_point(look: Look, p: Vec3, normal: Vec3, material: int, albedo: Vec3,
                   reflectivity: float) -> tuple[int, Vec3, float]:
    """Procedural detail at one global hit point ``p`` with unit ``normal``, for the triangle's ``material``,
    ``albedo`` and ``reflectivity``: returns the textured (material, albedo, reflectivity). Facade and bus windows
    turn into `Material.GLASS`."""
    rows, off = look.scene_rows, look.scene_offset
    x, y, z = _dot(rows[0], p) + off[0], _dot(rows[1], p) + off[1], _dot(rows[2], p) + off[2]
    if material == Material.ROAD:
        n = 0.75 + 0.35 * value_noise(x, y, 0.9) + 0.15 * value_noise(x, y, 0.07)
        if road_marking(x, y, look.road_half_width, LANE_WIDTH, look.lanes_per_direction, look.crossing_x,
                        look.crossing_half_width):
            return material, _scale((0.78, 0.78, 0.74), 0.85 + 0.15 * n), 0.85
        if abs(y) > look.road_half_width + look.sidewalk_width:  # parking lot
            return material, _scale((0.3, 0.29, 0.27), n), reflectivity
        return material, _scale(albedo, n), reflectivity
    if material == Material.SIDEWALK:
        n = 0.85 + 0.25 * value_noise(x, y, 0.5)
        if wrap(x, 1.5) < 0.04 or wrap(y, 1.5) < 0.04:  # paving seam
            n *= 0.6
        return material, _scale(albedo, n), reflectivity
    if material == Material.FACADE:
        u, across = (y, x) if abs(_dot(rows[0], normal)) > 0.7 else (x, y)
        if facade_window(u, z, 3.0, 3.3, 0.37 * np.floor(abs(across))):
            return Material.GLASS.value, (0.05, 0.06, 0.08), 0.08
        return material, _scale(albedo, 0.85 + 0.25 * value_noise(u, z, 0.35)), reflectivity
    if material == Material.BUS_BODY and 1.15 < z < 2.5:
        return Material.GLASS.value, (0.05, 0.06, 0.07), 0.1
    if material == Material.CONE and 0.38 < wrap(z, 1.0) < 0.52:
        return material, (0.85, 0.85, 0.85), 0.95
    if material == Material.BARRIER and wrap(x + y + z, 0.8) < 0.4:
        return material, (0.85, 0.85, 0.85), 0.8
    if material == Material.FOLIAGE:
        return material, _scale(albedo, 0.6 + 0.8 * value_noise(x + z, y - z, 0.25)), reflectivity
    return material, albedo, reflectivity


@njit(nogil=True, cache=True)
def _texture_kernel(look: Look, positions: NDArray, normals: NDArray, material: NDArray, albedo: NDArray,
                    reflectivity: NDArray, mat_out: NDArray, alb_out: NDArray, refl_out: NDArray) -> None:
    for i in range(len(positions)):
        m, alb, r = _texture_point(look, (positions[i, 0], positions[i, 1], positions[i, 2]),
                                   (float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])),
                                   int(material[i]), (float(albedo[i, 0]), float(albedo[i, 1]), float(albedo[i, 2])),
                                   float(reflectivity[i]))
        mat_out[i], refl_out[i] = m, r
        alb_out[i, 0], alb_out[i, 1], alb_out[i, 2] = alb


def texture(layout: SceneLayout, positions: NDArray, normals: NDArray, material: NDArray, albedo: NDArray,
            reflectivity: NDArray) -> Surface:
    """Apply procedural detail at global hit ``positions`` (N, 3) with unit ``normals`` (N, 3) to the per-hit triangle
    ``material`` (N,), ``albedo`` (N, 3) and ``reflectivity`` (N,).

    Returns new arrays; facade windows and bus windows turn into `Material.GLASS`.
    """
    n = len(positions)
    out = Surface(np.empty(n, np.uint8), np.empty((n, 3), np.float32), np.empty(n, np.float32))
    _texture_kernel(scene_look(layout), np.asarray(positions, np.float64), normals, material, albedo, reflectivity,
                    out.material, out.albedo, out.reflectivity)
    return out


@njit(nogil=True, cache=True, inline="always")
def _sky_point(look: Look, d: Vec3) -> Vec3:
    """Linear RGB of the sky along the global unit direction ``d``: horizon-to-zenith gradient plus a sun glow."""
    hor, zen = look.sky_horizon, look.sky_zenith
    if d[2] < 0:
        return _scale(hor, 0.8)
    w = np.sqrt(min(d[2], 1.0))
    r, g, b = hor[0] + (zen[0] - hor[0]) * w, hor[1] + (zen[1] - hor[1]) * w, hor[2] + (zen[2] - hor[2]) * w
    cos_sun = _dot(d, look.sun)
    if cos_sun > 0.6:
        c2 = cos_sun * cos_sun
        c8 = (c2 * c2) * (c2 * c2)
        c64 = c8 * c8
        c64 = c64 * c64
        c64 = c64 * c64
        glow = 0.6 * c64 + 0.15 * c8
        r, g, b = r + glow * SUN_GLOW_COLOUR[0], g + glow * SUN_GLOW_COLOUR[1], b + glow * SUN_GLOW_COLOUR[2]
    return r, g, b


@njit(nogil=True, cache=True, inline="always")
def _shade_point(look: Look, material: int, albedo: Vec3, normal: Vec3, d: Vec3, lit: bool, ray_length: float,
                 specular: float) -> Vec3:
    """Linear RGB of a textured surface point seen along the unit view direction ``d`` at ``ray_length`` [m]: sky
    ambient + sun (Lambert, zero unless ``lit``) + sky reflection (weight ``specular``, Fresnel-like) on glass/paint,
    then clear-air aerial perspective."""
    zen, hor = look.sky_zenith, look.sky_horizon
    lambert = min(max(_dot(normal, look.sun), 0.0), 1.0) if lit else 0.0
    ambient = 0.55 + 0.45 * normal[2]
    light = (ambient * 0.9 * (0.55 * zen[0] + 0.45 * hor[0]) + 2.4 * lambert * SUN_COLOUR[0],
             ambient * 0.9 * (0.55 * zen[1] + 0.45 * hor[1]) + 2.4 * lambert * SUN_COLOUR[1],
             ambient * 0.9 * (0.55 * zen[2] + 0.45 * hor[2]) + 2.4 * lambert * SUN_COLOUR[2])
    r, g, b = albedo[0] * light[0], albedo[1] * light[1], albedo[2] * light[2]
    if specular > 0:
        dn = _dot(d, normal)
        sky = _sky_point(look, (d[0] - 2.0 * dn * normal[0], d[1] - 2.0 * dn * normal[1], d[2] - 2.0 * dn * normal[2]))
        q = 1.0 - abs(dn)
        fresnel = specular + (1.0 - specular) * (q * q) * (q * q) * q * 0.5
        r, g, b = (r * (1.0 - fresnel) + fresnel * sky[0], g * (1.0 - fresnel) + fresnel * sky[1],
                   b * (1.0 - fresnel) + fresnel * sky[2])
    if material == Material.LAMP:
        r, g, b = r + 0.3 * albedo[0], g + 0.3 * albedo[1], b + 0.3 * albedo[2]
    transmit = np.exp(-CLEAR_AIR_EXTINCTION * ray_length)
    haze = 1.0 - transmit
    return r * transmit + hor[0] * haze, g * transmit + hor[1] * haze, b * transmit + hor[2] * haze


def _srgb_root_table(size: int = 4096) -> F64:
    """``x ** (1 / 2.4)`` sampled uniformly in ``sqrt(x)`` over [0, 1] (smooth there, so linear interpolation of
    ``size`` samples is exact to ~1e-7)."""
    table = np.linspace(0.0, 1.0, size) ** (2 / 2.4)
    table.flags.writeable = False
    return table


SRGB_ROOT_TABLE = _srgb_root_table()


@njit(nogil=True, cache=True, inline="always")
def _encode(linear: float, noise: float, table: NDArray) -> int:
    """sRGB code value 0..255 of a linear value in [0, ~1] plus ``noise`` in encoded units (0..1)."""
    x = min(max(linear, 0.0031308), 1.0)  # x <= 0.0031 is below 1/255
    t = np.sqrt(x) * (len(table) - 1)
    k = min(int(t), len(table) - 2)
    root = table[k] + (t - k) * (table[k + 1] - table[k])
    return int(min(max(np.rint((1.055 * root - 0.055 + noise) * 255.0), 0.0), 255.0))


@njit(nogil=True, cache=True, inline="always")
def _ray_radiance(look: Look, origin: Vec3, dirs: NDArray, ranges: NDArray, normals: NDArray, material: NDArray,
                  albedo: NDArray, reflectivity: NDArray, lit: NDArray, specular: NDArray, i: int) -> Vec3:
    """Linear RGB of camera ray ``i``: the sky where its range is inf, else the textured and shaded surface."""
    d = (float(dirs[i, 0]), float(dirs[i, 1]), float(dirs[i, 2]))
    t = ranges[i]
    if not np.isfinite(t):
        return _sky_point(look, d)
    p = (origin[0] + d[0] * t, origin[1] + d[1] * t, origin[2] + d[2] * t)
    normal = (float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2]))
    m, alb, _ = _texture_point(look, p, normal, int(material[i]),
                               (float(albedo[i, 0]), float(albedo[i, 1]), float(albedo[i, 2])),
                               float(reflectivity[i]))
    return _shade_point(look, m, alb, normal, d, lit[i], t, float(specular[m]))


@njit(nogil=True, cache=True)
def _camera_kernel(look: Look, origin: Vec3, dirs: NDArray, ranges: NDArray, normals: NDArray, material: NDArray,
                   albedo: NDArray, reflectivity: NDArray, lit: NDArray, specular: NDArray, noise: NDArray,
                   noise_std: float, table: NDArray, out: NDArray) -> None:
    for i in range(len(dirs)):
        colour = _ray_radiance(look, origin, dirs, ranges, normals, material, albedo, reflectivity, lit, specular, i)
        for c in range(3):
            out[i, c] = _encode(colour[c], noise_std * noise[i, c] if len(noise) else 0.0, table)


@njit(nogil=True, cache=True)
def _radiance_kernel(look: Look, origin: Vec3, dirs: NDArray, ranges: NDArray, normals: NDArray, material: NDArray,
                     albedo: NDArray, reflectivity: NDArray, lit: NDArray, specular: NDArray, out: NDArray) -> None:
    for i in range(len(dirs)):
        colour = _ray_radiance(look, origin, dirs, ranges, normals, material, albedo, reflectivity, lit, specular, i)
        for c in range(3):
            out[i, c] = colour[c]


def camera_radiance(layout: SceneLayout, origin: NDArray, dirs: NDArray, ranges: NDArray, normals: NDArray,
                    material: NDArray, albedo: NDArray, reflectivity: NDArray, lit: NDArray) -> NDArray[np.float64]:
    """(N, 3) linear RGB of camera rays (arguments as `camera_pixels`): what `camera_pixels` encodes, before the
    sRGB encoding and the sensor noise."""
    out = np.empty((len(dirs), 3))
    _radiance_kernel(scene_look(layout), _vec3(origin), dirs, ranges, normals, material, albedo, reflectivity, lit,
                     SPECULAR, out)
    return out


def camera_pixels(layout: SceneLayout, origin: NDArray, dirs: NDArray, ranges: NDArray, normals: NDArray,
                  material: NDArray, albedo: NDArray, reflectivity: NDArray, lit: NDArray, noise: NDArray | None,
                  noise_std: float) -> NDArray[np.uint8]:
    """sRGB (N, 3) uint8 of camera rays from the global ``origin`` (3,) along unit ``dirs`` (N, 3): the sky where
    ``ranges`` (N,) [m] is inf, else the textured (`texture`) and shaded surface with hit ``normals`` (N, 3), triangle
    ``material`` (N,), ``albedo`` (N, 3), ``reflectivity`` (N,), and ``lit`` (N,) bool: the sun reaches it. Colours
    are computed in linear RGB; sensor noise ``noise_std * noise`` ((N, 3) standard normal, or None) is added in
    encoded units."""
    out = np.empty((len(dirs), 3), np.uint8)
    noise = np.zeros((0, 3), np.float32) if noise is None else noise
    _camera_kernel(scene_look(layout), _vec3(origin), dirs, ranges, normals, material, albedo, reflectivity, lit,
                   SPECULAR, noise, float(noise_std), SRGB_ROOT_TABLE, out)
    return out


def lidar_intensity(reflectivity: NDArray, cos_incidence: NDArray, ranges: NDArray) -> F32:
    """Raw intensity on the 0..255 scale from reflectivity (N,), |cos incidence| (N,) and range (N,) [m].

    Lambertian return ``rho cos(theta)`` with the sensor's partial range compensation, modelled as a 1/R fall-off
    beyond 10 m (raw power falls as 1/R^2; the HDL-32E reports a range-compensated value).
    """
    falloff = np.minimum(1.0, 10.0 / np.maximum(ranges, 1e-3))
    return (255.0 * reflectivity * np.abs(cos_incidence) * falloff).astype(np.float32)
