"""Materials of the synthetic world, shared by the LiDAR and the cameras.

Each triangle carries a `Material` id, an RGB albedo and a LiDAR reflectivity. Procedural detail (lane markings,
facade windows, paving seams, stripes) is a function of the hit position in the scene frame, applied identically to
the camera albedo and the LiDAR reflectivity (retro-reflective paint is bright in both).
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numpy.typing import NDArray


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


def _hash2(a: NDArray, b: NDArray) -> NDArray[np.float32]:
    """Deterministic pseudo-random value in [0, 1) from two integer grids (same shape)."""
    h = (a.astype(np.int64) * 73856093) ^ (b.astype(np.int64) * 19349663)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h & 0xFFFF).astype(np.float32)) / np.float32(65536.0)


def value_noise(x: NDArray, y: NDArray, cell: float) -> NDArray[np.float32]:
    """Smooth value noise in [0, 1) of 2-D positions (metres) with feature size ``cell`` metres."""
    gx, gy = x / cell, y / cell
    ix, iy = np.floor(gx), np.floor(gy)
    fx, fy = (gx - ix).astype(np.float32), (gy - iy).astype(np.float32)
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    n00, n10 = _hash2(ix, iy), _hash2(ix + 1, iy)
    n01, n11 = _hash2(ix, iy + 1), _hash2(ix + 1, iy + 1)
    return (n00 * (1 - fx) + n10 * fx) * (1 - fy) + (n01 * (1 - fx) + n11 * fx) * fy


def road_marking_mask(x: NDArray, y: NDArray, road_half_width: float, lane_width: float,
                      lanes_per_direction: int, crossing_x: float | None,
                      crossing_half_width: float) -> NDArray[np.bool_]:
    """Where road paint is, for scene-frame positions ``x`` (along the road), ``y`` (lateral), in metres.

    Marks: dashed white lane dividers, a double solid centre line, solid edge lines at the outermost lane, zebra
    crossings either side of a cross street at ``crossing_x`` (or none), and the cross street's dashed centre line.
    """
    ay = np.abs(y)
    paint = np.zeros(x.shape, dtype=bool)
    on_road = ay <= road_half_width
    # double centre line
    paint |= on_road & (np.abs(ay - 0.15) < 0.06)
    for k in range(1, lanes_per_direction):
        dashed = np.mod(x, 9.0) < 3.0
        paint |= on_road & dashed & (np.abs(ay - k * lane_width) < 0.075)
    edge = lanes_per_direction * lane_width
    paint |= on_road & (np.abs(ay - edge) < 0.09)
    if crossing_x is not None:
        dx = x - crossing_x
        in_cross = np.abs(dx) < crossing_half_width
        paint &= ~in_cross  # no lane lines inside the junction
        for side in (-1.0, 1.0):
            zebra_centre = side * (crossing_half_width + 2.0)
            zebra = on_road & (np.abs(dx - zebra_centre) < 1.6) & (np.mod(y, 1.2) < 0.6)
            paint |= zebra
        cross_centre = (np.abs(dx) < 0.08) & (ay > road_half_width + 1.0) & (np.mod(y, 9.0) < 3.0)
        paint |= cross_centre
    return paint


def facade_window_mask(u: NDArray, z: NDArray, window_pitch: float, floor_height: float,
                       phase: NDArray) -> NDArray[np.bool_]:
    """Window pattern on a facade: ``u`` along the wall, ``z`` height above ground [m]; ``phase`` per hit shifts the
    grid per building. Ground floors carry wide shop windows."""
    fu = np.mod(u + phase, window_pitch) / window_pitch
    floor = np.floor(z / floor_height)
    fz = np.mod(z, floor_height) / floor_height
    upper = (floor >= 1) & (fu > 0.25) & (fu < 0.75) & (fz > 0.28) & (fz < 0.82)
    shop = (floor == 0) & (fu > 0.08) & (fu < 0.92) & (fz > 0.12) & (fz < 0.78)
    return upper | shop
