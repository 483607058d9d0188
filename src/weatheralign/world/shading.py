"""Surface appearance shared by the sensors: procedural textures (albedo + LiDAR reflectivity) and camera shading.

Camera colours are computed in linear RGB and encoded to sRGB; LiDAR intensity uses the textured reflectivity, so a
lane marking is bright in the image and in the scan. Texturing and shading run per hit point in numba kernels; a
camera image is one pass over its pixels (`camera_frame`: ray directions, hit attributes, sun shadow rays, texture,
shading, sensor noise and sRGB encoding per pixel, float64 arithmetic), the same bytes as the step-by-step functions
(`camera_pixels` and the functions of `render` it follows). They release the GIL.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.sensors import DetectorFloor, IntensityModel, LidarModel, floor_factor
from weatheralign.world.layout import LANE_WIDTH, SceneLayout
from weatheralign.world.materials import SPECULAR, Material, facade_window, road_marking, value_noise, wrap
from weatheralign.world.raster import SunGrid, TriangleTable, blocked_at, sun_cells

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

# Clear-air extinction for the camera's aerial perspective: meteorological optical range 30 km.
CLEAR_AIR_EXTINCTION = float(np.log(20.0) / 30000.0)
SUN_COLOUR = (1.0, 0.96, 0.9)
SUN_GLOW_COLOUR = (1.0, 0.95, 0.85)
SHADOW_EPS = 0.02  # m, shadow ray start offset along the normal


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


def _srgb_code_table(size: int = 4096) -> F64:
    """(size + 1,) 255 x the exact sRGB encoding (IEC 61966-2-1: ``12.92 x`` up to x = 0.0031308, then
    ``1.055 x^(1/2.4) - 0.055``) of the linear values ``k / size``: linear interpolation between entries is exact to
    0.005 code values (the curve's largest curvature, just above the knee, is ~2400 per unit^2)."""
    x = np.linspace(0.0, 1.0, size + 1)
    table = 255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)
    table.flags.writeable = False
    return table


SRGB_CODE_TABLE = _srgb_code_table()

NOISE_BITS = 16


def _gauss_table(bits: int = NOISE_BITS) -> F32:
    """(2**bits,) float32 standard normal quantiles at the midpoints ``(k + 0.5) / 2**bits`` (rescaled to unit
    variance): indexed by a uniform random ``bits``-bit integer, a normal variate quantised to 2**bits equally likely
    values and truncated at +-4.32 sigma (P = 1.6e-5 beyond), far finer than the 8-bit image it perturbs."""
    from scipy.special import ndtri

    z = ndtri((np.arange(1 << bits) + 0.5) / (1 << bits))
    table = (z / np.sqrt(np.mean(z * z))).astype(np.float32)
    table.flags.writeable = False
    return table


GAUSS_TABLE = _gauss_table()


@njit(nogil=True, cache=True, inline="always")
def _mix64(key: np.uint64, i: int) -> np.uint64:
    """64 random bits of counter ``i`` under ``key``: the SplitMix64 finaliser of ``key + (i + 1) * golden``."""
    z = key + np.uint64(i + 1) * np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(nogil=True, cache=True, inline="always")
def _pixel_noise(key: np.uint64, i: int, gauss: NDArray) -> Vec3:
    """Three standard normal variates (R, G, B) of pixel ``i``: 16-bit fields of one `_mix64` draw into ``gauss``."""
    h = _mix64(key, i)
    return (float(gauss[int(h & np.uint64(0xFFFF))]), float(gauss[int((h >> np.uint64(16)) & np.uint64(0xFFFF))]),
            float(gauss[int((h >> np.uint64(32)) & np.uint64(0xFFFF))]))


@njit(nogil=True, cache=True)
def _noise_kernel(key: np.uint64, gauss: NDArray, out: NDArray) -> None:
    for i in range(len(out)):
        z = _pixel_noise(key, i, gauss)
        out[i, 0], out[i, 1], out[i, 2] = z[0], z[1], z[2]


def noise_key(rng: np.random.Generator) -> int:
    """The key of one exposure's sensor noise, drawn from its generator (`camera_noise`)."""
    return int(rng.integers(0, 2**63))


def camera_noise(key: int, n: int) -> F32:
    """(n, 3) float32 standard normal sensor noise of the pixels 0..n-1 (row-major) of the exposure with ``key``
    (`noise_key`): a counter-based generator, so pixel i's noise depends on (key, i) only. Each pixel's 64 hashed bits
    (SplitMix64) give three 16-bit uniform integers, each mapped to a normal variate by `GAUSS_TABLE`."""
    out = np.empty((n, 3), np.float32)
    _noise_kernel(np.uint64(key), GAUSS_TABLE, out)
    return out


@njit(nogil=True, cache=True, inline="always")
def _encode(linear: float, noise: float, table: NDArray) -> int:
    """sRGB code value 0..255 of a linear value (clipped to [0, 1]) plus ``noise`` in code values, rounded: by linear
    interpolation in ``table`` (`SRGB_CODE_TABLE`)."""
    x = min(max(linear, 0.0), 1.0) * (len(table) - 1)
    k = min(int(x), len(table) - 2)
    code = table[k] + (x - k) * (table[k + 1] - table[k]) + noise
    return int(min(max(np.rint(code), 0.0), 255.0))


@njit(nogil=True, cache=True, inline="always")
def _point_radiance(look: Look, origin: Vec3, d: Vec3, t: float, normal: Vec3, material: int, albedo: Vec3,
                    reflectivity: float, lit: bool, specular: NDArray) -> Vec3:
    """Linear RGB seen along the unit global direction ``d`` from ``origin``: the sky where the ray length ``t`` [m] is
    inf, else the surface hit there (triangle ``normal`` facing the ray, ``material``, ``albedo``, ``reflectivity``;
    ``lit``: the sun reaches it), textured and shaded."""
    if not np.isfinite(t):
        return _sky_point(look, d)
    p = (origin[0] + d[0] * t, origin[1] + d[1] * t, origin[2] + d[2] * t)
    m, alb, _ = _texture_point(look, p, normal, material, albedo, reflectivity)
    return _shade_point(look, m, alb, normal, d, lit, t, float(specular[m]))


@njit(nogil=True, cache=True, inline="always")
def _ray_radiance(look: Look, origin: Vec3, dirs: NDArray, ranges: NDArray, normals: NDArray, material: NDArray,
                  albedo: NDArray, reflectivity: NDArray, lit: NDArray, specular: NDArray, i: int) -> Vec3:
    """`_point_radiance` of camera ray ``i`` of the arrays."""
    return _point_radiance(look, origin, (float(dirs[i, 0]), float(dirs[i, 1]), float(dirs[i, 2])), ranges[i],
                           (float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])), int(material[i]),
                           (float(albedo[i, 0]), float(albedo[i, 1]), float(albedo[i, 2])), float(reflectivity[i]),
                           lit[i], specular)


@njit(nogil=True, cache=True)
def _camera_kernel(look: Look, origin: Vec3, dirs: NDArray, ranges: NDArray, normals: NDArray, material: NDArray,
                   albedo: NDArray, reflectivity: NDArray, lit: NDArray, specular: NDArray, noise: NDArray,
                   noise_code_std: float, table: NDArray, out: NDArray) -> None:
    for i in range(len(dirs)):
        colour = _ray_radiance(look, origin, dirs, ranges, normals, material, albedo, reflectivity, lit, specular, i)
        for c in range(3):
            out[i, c] = _encode(colour[c], noise_code_std * noise[i, c] if len(noise) else 0.0, table)


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
    are computed in linear RGB and encoded by the exact sRGB curve; sensor noise ``noise_std * noise`` ((N, 3)
    standard normal, e.g. `camera_noise`, or None) is added in encoded units [0, 1] before rounding.

    The step by step form of what `camera_frame` computes in one pass (the same bytes for the same inputs)."""
    out = np.empty((len(dirs), 3), np.uint8)
    noise = np.zeros((0, 3), np.float32) if noise is None else noise
    _camera_kernel(scene_look(layout), _vec3(origin), dirs, ranges, normals, material, albedo, reflectivity, lit,
                   SPECULAR, noise, 255.0 * float(noise_std), SRGB_CODE_TABLE, out)
    return out


@njit(nogil=True, cache=True)
def _camera_frame_kernel(look: Look, origin: Vec3, R: NDArray, K: NDArray, inv_depth: NDArray, gid: NDArray,
                         tris: TriangleTable, specular: NDArray, shadows: bool, static_grid: SunGrid,
                         moving_grid: SunGrid, has_moving: bool, noise_key: np.uint64, noise_code_std: float,
                         gauss: NDArray, table: NDArray, image: NDArray, range_out: NDArray,
                         instance_out: NDArray) -> None:
    """One pass per pixel of the steps `render.pixel_directions`, `raycast.WorldRaycaster.cast_camera` (from the
    rasterised depth), `render.sun_lit`, `camera_noise` and `camera_pixels` take in turn, in the same arithmetic (the
    float32 directions and normals of those steps included), without their per-pixel arrays."""
    width = image.shape[1]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    sun = look.sun
    # arrays out of their tuples once (read from a tuple per pixel, each access costs reference counting)
    tri_normal, tri_material, tri_albedo = tris.normal, tris.material, tris.albedo
    tri_reflectivity, tri_instance = tris.reflectivity, tris.instance
    static_cells, s_axes, s_start = sun_cells(static_grid), static_grid.axes, static_grid.cell_start
    s_cells, s_wide, s_occ = static_grid.cells, static_grid.wide, static_grid.occupied
    moving_cells, m_axes, m_start = sun_cells(moving_grid), moving_grid.axes, moving_grid.cell_start
    m_cells, m_wide, m_occ = moving_grid.cells, moving_grid.wide, moving_grid.occupied
    static_hint = moving_hint = -1  # the last blocking records: shadows are coherent from pixel to pixel
    xs = (np.arange(width) - cx) / fx
    for v in range(image.shape[0]):
        y = (v - cy) / fy
        for u in range(width):
            i = v * width + u
            x = xs[u]
            root = np.sqrt(x * x + y * y + 1.0)
            inv = 1.0 / root
            d32 = (np.float32((R[0, 0] * x + R[0, 1] * y + R[0, 2]) * inv),
                   np.float32((R[1, 0] * x + R[1, 1] * y + R[1, 2]) * inv),
                   np.float32((R[2, 0] * x + R[2, 1] * y + R[2, 2]) * inv))
            d = (float(d32[0]), float(d32[1]), float(d32[2]))
            g = gid[i]
            if g < 0:
                colour = _sky_point(look, d)
                range_out[i] = np.inf
                instance_out[i] = 0
            else:
                t = root / inv_depth[i]
                n0, n1, n2 = tri_normal[g, 0], tri_normal[g, 1], tri_normal[g, 2]
                if n0 * d32[0] + n1 * d32[1] + n2 * d32[2] > 0:  # float32, as `_finish_kernel`
                    n0, n1, n2 = -n0, -n1, -n2
                lit = False
                if n0 * sun[0] + n1 * sun[1] + n2 * sun[2] > 0:
                    lit = True
                    if shadows:  # the shadow ray's origin, as `_shadow_starts`
                        px = origin[0] + d32[0] * t + SHADOW_EPS * n0
                        py = origin[1] + d32[1] * t + SHADOW_EPS * n1
                        pz = origin[2] + d32[2] * t + SHADOW_EPS * n2
                        blocked, static_hint = blocked_at(static_cells, s_axes, s_start, s_cells, s_wide, s_occ, px,
                                                          py, pz, static_hint)
                        if not blocked and has_moving:
                            blocked, moving_hint = blocked_at(moving_cells, m_axes, m_start, m_cells, m_wide, m_occ,
                                                              px, py, pz, moving_hint)
                        lit = not blocked
                colour = _point_radiance(look, origin, d, t, (float(n0), float(n1), float(n2)),
                                         int(tri_material[g]), (float(tri_albedo[g, 0]), float(tri_albedo[g, 1]),
                                                                float(tri_albedo[g, 2])),
                                         float(tri_reflectivity[g]), lit, specular)
                range_out[i] = t
                instance_out[i] = tri_instance[g]
            if noise_code_std > 0.0:
                z = _pixel_noise(noise_key, i, gauss)
                for c in range(3):
                    image[v, u, c] = _encode(colour[c], noise_code_std * z[c], table)
            else:
                for c in range(3):
                    image[v, u, c] = _encode(colour[c], 0.0, table)


def camera_frame(layout: SceneLayout, origin: NDArray, R: NDArray, K: NDArray, inv_depth: NDArray, gid: NDArray,
                 tris: TriangleTable, static_grid: SunGrid, moving_grid: SunGrid | None, *, shadows: bool, key: int,
                 noise_std: float, height: int, width: int) -> tuple[NDArray[np.uint8], F32, NDArray[np.int32]]:
    """A camera image in one pass: the pinhole camera at ``origin`` (3,) with rotation ``R`` (3, 3) (camera -> global)
    and intrinsics ``K`` (3, 3), whose pixel rays (row-major, ``height`` x ``width``) meet triangle ``gid`` (H*W,)
    of ``tris`` (-1: sky) at inverse camera depth ``inv_depth`` (H*W,) [1/m] (`raster.pinhole_depth`); sun shadows
    (with ``shadows``) from ``static_grid`` and ``moving_grid`` (the moving actors posed at the exposure; None: none);
    sensor noise of ``noise_std`` (encoded units) from ``key`` (`camera_noise`).

    Returns the (H, W, 3) uint8 sRGB image, the ray length per pixel (H, W) float32 [m] (inf = sky) and the
    instance per pixel (H, W) int32 (0 = background): the same as `camera_pixels` of the step-by-step hits, lit
    flags and `camera_noise`, byte for byte.
    """
    image = np.empty((height, width, 3), np.uint8)
    range_out = np.empty(height * width, np.float32)
    instance_out = np.empty(height * width, np.int32)
    _camera_frame_kernel(scene_look(layout), _vec3(origin), np.ascontiguousarray(R, np.float64),
                         np.asarray(K, np.float64), inv_depth, gid, tris, SPECULAR, bool(shadows), static_grid,
                         static_grid if moving_grid is None else moving_grid, moving_grid is not None,
                         np.uint64(key), 255.0 * float(noise_std), GAUSS_TABLE, SRGB_CODE_TABLE, image, range_out,
                         instance_out)
    return image, range_out.reshape(height, width), instance_out.reshape(height, width)


def lidar_intensity(reflectivity: NDArray, cos_incidence: NDArray, ranges: NDArray, model: IntensityModel) -> F32:
    """Noise-free reported intensity on the 0..255 scale from reflectivity (N,), |cos incidence| (N,) and range (N,)
    [m]: a Lambertian return ``ρ |cos θ|`` through the sensor's intensity ``model`` (``scale ρ cos θ g(R)``)."""
    gain = np.minimum(1.0, (model.r_ref / np.maximum(ranges, 1e-3)) ** model.falloff)
    return (model.scale * reflectivity * np.abs(cos_incidence) * gain).astype(np.float32)


@njit(nogil=True, cache=True)
def _lidar_returns_kernel(look: Look, origins: NDArray, dirs: NDArray, true_range: NDArray, noise: NDArray,
                          normals: NDArray, material: NDArray, albedo: NDArray, reflectivity: NDArray,
                          min_range: float, max_range: float, scale: float, detector: DetectorFloor,
                          idx_out: NDArray, raw_out: NDArray, mat_out: NDArray) -> int:
    m = 0
    for i in range(len(true_range)):
        t = true_range[i]
        if not np.isfinite(t):
            continue
        measured = t + noise[i]
        if measured < min_range or measured > max_range:
            continue
        d = (dirs[i, 0], dirs[i, 1], dirs[i, 2])
        normal = (float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2]))
        mat, _, refl = _texture_point(look, (origins[i, 0] + d[0] * t, origins[i, 1] + d[1] * t,
                                             origins[i, 2] + d[2] * t), normal, int(material[i]),
                                      (float(albedo[i, 0]), float(albedo[i, 1]), float(albedo[i, 2])),
                                      float(reflectivity[i]))
        cos_inc = normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2]
        r_ref, falloff = detector.r_ref, detector.falloff
        raw = np.float32(scale * np.float32(refl) * abs(cos_inc) * min(1.0, (r_ref / max(measured, 1e-3)) ** falloff))
        if raw >= detector.floor * floor_factor(measured, r_ref, falloff, detector.comp_ref):
            idx_out[m], raw_out[m], mat_out[m] = i, raw, mat
            m += 1
    return m


def lidar_returns(layout: SceneLayout, origins: NDArray, dirs: NDArray, true_range: NDArray, noise: NDArray,
                  normals: NDArray, material: NDArray, albedo: NDArray, reflectivity: NDArray, lidar: LidarModel
                  ) -> tuple[NDArray[np.int64], F32, NDArray[np.uint8]]:
    """The beams (rays from ``origins`` (N, 3) along unit ``dirs`` (N, 3)) that return: a hit (``true_range`` (N,)
    [m] finite) whose measured range ``true_range + noise`` lies in ``lidar``'s [``min_range_m``, ``max_range_m``]
    and whose noise-free intensity (`lidar_intensity` of the textured reflectivity (`texture`), |cos incidence| with
    the hit ``normals`` and the measured range, through ``lidar.intensity``) reaches the detector floor at that range
    (`LidarModel.floor_at`). Returns their indices (M,), noise-free intensities (M,) float32 and textured materials
    (M,) uint8."""
    n = len(true_range)
    idx, raw, mat = np.empty(n, np.int64), np.empty(n, np.float32), np.empty(n, np.uint8)
    m = _lidar_returns_kernel(scene_look(layout), np.asarray(origins, np.float64), np.asarray(dirs, np.float64),
                              true_range, np.broadcast_to(np.asarray(noise, np.float64), (n,)), normals, material,
                              albedo, reflectivity, float(lidar.min_range_m), float(lidar.max_range_m),
                              float(lidar.intensity.scale), lidar.detector(), idx, raw, mat)
    return idx[:m], raw[:m], mat[:m]
