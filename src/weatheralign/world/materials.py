"""Materials of the synthetic world, shared by the LiDAR and the cameras.

Each triangle carries a `Material` id, an RGB albedo and a LiDAR reflectivity. Procedural detail (lane markings,
facade windows, paving seams, stripes) is a function of the hit position in the scene frame, applied identically to
the camera albedo and the LiDAR reflectivity (retro-reflective paint is bright in both). The pattern functions are
scalar numba kernels, called per hit point from the fused texturing/shading kernels in `shading`.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numba import njit


class Material(IntEnum):
    """Surface kinds. The value is stored per triangle (uint8) and per LiDAR point as its material label."""

    NONE = 0
    ROAD = 1
    SIDEWALK = 2
    CURB = 3
    FACADE = 4
    ROOF = 5
    TRUNK = 6
    FOLIAGE = 7
    METAL = 8
    PAINT = 9
    GLASS = 10
    TYRE = 11
    LAMP = 12
    CLOTH = 13
    SKIN = 14
    CONE = 15
    BARRIER = 16
    PLATE = 17
    SIGN = 18
    BUS_BODY = 19


# Specular weight (camera: Fresnel-ish mirror of the sky) per material; glass and paint shine.
SPECULAR = np.zeros(32, dtype=np.float32)
SPECULAR[Material.GLASS] = 0.2
SPECULAR[Material.PAINT] = 0.10
SPECULAR[Material.BUS_BODY] = 0.08
SPECULAR[Material.LAMP] = 0.2


@njit(nogil=True, cache=True, inline="always")
def wrap(x: float, period: float) -> float:
    """``x`` modulo ``period`` in [0, period] (floor-based; cheaper than the exact ``fmod``)."""
    return x - period * np.floor(x * (1.0 / period))


@njit(nogil=True, cache=True, inline="always")
def _hash2(a: float, b: float) -> float:
    """Deterministic pseudo-random value in [0, 1) from two integer grid coordinates (given as whole floats)."""
    h = (np.int64(a) * 73856093) ^ (np.int64(b) * 19349663)
    h = (h ^ (h >> 13)) * 1274126177
    return float(h & 0xFFFF) / 65536.0


@njit(nogil=True, cache=True, inline="always")
def value_noise(x: float, y: float, cell: float) -> float:
    """Smooth value noise in [0, 1) of a 2-D position (metres) with feature size ``cell`` metres."""
    inv = 1.0 / cell
    gx, gy = x * inv, y * inv
    ix, iy = np.floor(gx), np.floor(gy)
    fx, fy = gx - ix, gy - iy
    fx, fy = fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy)
    n00, n10 = _hash2(ix, iy), _hash2(ix + 1.0, iy)
    n01, n11 = _hash2(ix, iy + 1.0), _hash2(ix + 1.0, iy + 1.0)
    return (n00 * (1.0 - fx) + n10 * fx) * (1.0 - fy) + (n01 * (1.0 - fx) + n11 * fx) * fy


@njit(nogil=True, cache=True, inline="always")
def road_marking(x: float, y: float, road_half_width: float, lane_width: float, lanes_per_direction: int,
                 crossing_x: float, crossing_half_width: float) -> bool:
    """Whether road paint is at scene-frame position ``x`` (along the road), ``y`` (lateral), in metres.

    Marks: dashed white lane dividers, a double solid centre line, solid edge lines at the outermost lane, zebra
    crossings either side of a cross street at ``crossing_x`` (NaN: none), and the cross street's dashed centre line.
    """
    ay = abs(y)
    on_road = ay <= road_half_width
    if not np.isnan(crossing_x):
        dx = x - crossing_x
        for side in (-1.0, 1.0):
            if on_road and abs(dx - side * (crossing_half_width + 2.0)) < 1.6 and wrap(y, 1.2) < 0.6:
                return True  # zebra
        if abs(dx) < 0.08 and ay > road_half_width + 1.0 and wrap(y, 9.0) < 3.0:
            return True  # the cross street's centre line
        if abs(dx) < crossing_half_width:
            return False  # no lane lines inside the junction
    if not on_road:
        return False
    if abs(ay - 0.15) < 0.06:
        return True  # double centre line
    if wrap(x, 9.0) < 3.0:
        for k in range(1, lanes_per_direction):
            if abs(ay - k * lane_width) < 0.075:
                return True  # dashed lane divider
    return abs(ay - lanes_per_direction * lane_width) < 0.09  # edge line


@njit(nogil=True, cache=True, inline="always")
def facade_window(u: float, z: float, window_pitch: float, floor_height: float, phase: float) -> bool:
    """Window pattern on a facade: ``u`` along the wall, ``z`` height above ground [m]; ``phase`` shifts the grid per
    building. Ground floors carry wide shop windows."""
    fu = wrap(u + phase, window_pitch) / window_pitch
    floor = np.floor(z / floor_height)
    fz = wrap(z, floor_height) / floor_height
    if floor >= 1:
        return 0.25 < fu < 0.75 and 0.28 < fz < 0.82
    return floor == 0 and 0.08 < fu < 0.92 and 0.12 < fz < 0.78
