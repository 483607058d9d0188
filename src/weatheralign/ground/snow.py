"""Snow lying on the ground as one depth field in world ground coordinates, and what it does to the LiDAR's ground
returns: the surface rises by the snow's depth and answers with snow's reflectivity.

The depth (`snow_depth`) is a function of the world position (x, y) and a seed alone, so every frame, the LiDAR and
every camera of a scene see the same drifts. A ground return at range ``r`` on a surface of normal ``n`` now comes from
the snow surface ``d`` above it, along the same beam: ``r' = r - d / cos(theta)``, ``theta`` the incidence angle from
the normal. Both surfaces are taken as Lambertian at the same incidence, so the intensity scales by the ratio of
their reflectivities at the LiDAR's wavelength (fresh snow about 0.8 at 905 nm, asphalt 0.1-0.2), up to the
sensor's saturation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from weatheralign.ground.wet import fractal_noise

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SnowCover:
    """Snow on the ground: ``depth_m`` on average, between ``(1 - variation)`` and ``(1 + variation)`` times it over
    features about ``cell_m`` wide; its reflectivity and the bare pavement's at the LiDAR's wavelength."""

    depth_m: float = 0.05
    variation: float = 0.5
    cell_m: float = 6.0
    snow_reflectivity: float = 0.8
    pavement_reflectivity: float = 0.15

    def __post_init__(self) -> None:
        if not self.depth_m > 0 or not self.cell_m > 0:
            raise ValueError(f"SnowCover.depth_m and cell_m must be > 0, got {self.depth_m}, {self.cell_m}")
        if not 0.0 <= self.variation < 1.0:
            raise ValueError(f"SnowCover.variation must be in [0, 1), got {self.variation}")
        for name in ("snow_reflectivity", "pavement_reflectivity"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"SnowCover.{name} must be in (0, 1], got {getattr(self, name)}")


class SnowCoverEffect(NamedTuple):
    """What lying snow does to N ground returns."""

    points: F64  # (N, 3) the returns on the snow surface [m], same frame as the input
    intensity: F64  # (N,) new intensity (0..saturation)
    depth_m: F64  # (N,) snow depth at the return [m]


def snow_depth(xy_world: F64, cover: SnowCover, seed: int) -> F64:
    """Snow depth [m] at world positions (N, 2): ``depth_m (1 + variation (2 u - 1))``, ``u`` fractal noise."""
    u = fractal_noise(xy_world, cover.cell_m, seed)
    return cover.depth_m * (1.0 + cover.variation * (2.0 * u - 1.0))


def snow_covered_ground(points: F64, origins: F64, normals: F64, intensity: F64, depth_m: F64, cover: SnowCover,
                        saturation: float = 255.0) -> SnowCoverEffect:
    """Ground returns (N, 3) seen from ``origins`` (N, 3) or (3,) on surfaces of unit ``normals`` (N, 3) or (3,),
    under snow ``depth_m`` (N,) [m]: each moved along its beam onto the snow surface, its intensity scaled by
    ``snow_reflectivity / pavement_reflectivity`` and clipped at ``saturation``."""
    points = np.asarray(points, dtype=np.float64)
    rays = points - origins
    ranges = np.linalg.norm(rays, axis=-1, keepdims=True)
    directions = rays / ranges
    normals = np.broadcast_to(np.asarray(normals, dtype=np.float64), points.shape)
    cos_incidence = np.abs(np.sum(directions * normals, axis=-1, keepdims=True))
    depth = np.asarray(depth_m, dtype=np.float64)
    moved = points - directions * (depth[:, None] / np.maximum(cos_incidence, 1e-6))
    ratio = cover.snow_reflectivity / cover.pavement_reflectivity
    new = np.minimum(np.asarray(intensity, dtype=np.float64) * ratio, saturation)
    return SnowCoverEffect(moved, new, depth)


__all__ = ["snow_covered_ground", "snow_depth", "SnowCover", "SnowCoverEffect"]
