"""Checks of a materialised particle field against its size distribution, and expected counts per sensor volume."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from weatheralign.medium.field import ParticleField

F64 = NDArray[np.float64]
SIZE_BINS = 20


@dataclass(frozen=True)
class RegionCheck:
    """One materialised cube: expected vs realised count (Poisson z-score) and a chi-square test of the diameters
    over `SIZE_BINS` equal-probability bins (p-value; small p = sizes do not follow the distribution)."""

    centre: F64
    side: float
    expected: float
    realised: int
    z_score: float
    chi2_pvalue: float
    diameters: NDArray[np.float64]


def check_region(field: ParticleField, centre: F64, t: float, max_particles: int) -> RegionCheck:
    """Materialise all particles in a cube around ``centre`` (3,) [m] at time ``t`` [s]; the cube side is chosen so
    that about ``max_particles / 2`` particles are expected."""
    n = field.number_density()
    side = float(np.clip((0.5 * max_particles / n) ** (1 / 3), 0.5, 20.0))
    lo, hi = centre - side / 2, centre + side / 2
    particles = field.materialize(lo, hi, t)
    expected = field.expected_count(lo, hi)
    realised = len(particles)
    z = (realised - expected) / np.sqrt(max(expected, 1e-12))
    spec = field.spectrum
    edges = spec.ppf(np.linspace(0.0, 1.0, SIZE_BINS + 1))
    counts, _ = np.histogram(particles.diameters, bins=edges)
    pvalue = float(stats.chisquare(counts).pvalue) if realised >= 5 * SIZE_BINS else float("nan")
    return RegionCheck(np.asarray(centre, float), side, float(expected), realised, float(z), pvalue,
                       particles.diameters)


def lidar_air_volume(max_range: float, sensor_height: float, top: float, elevations_deg: tuple[float, float],
                     samples: int = 600) -> float:
    """Volume [m^3] of air a spinning LiDAR sees: its elevation band out to ``max_range``, above the ground (z = 0)
    and below the particle layer top ``top`` (z, m), for a sensor at ``sensor_height``."""
    r = (np.arange(samples) + 0.5) / samples * max_range
    e = np.deg2rad(np.linspace(*sorted(elevations_deg), samples))
    R, E = np.meshgrid(r, e, indexing="ij")
    z = sensor_height + R * np.sin(E)
    inside = (z >= 0.0) & (z <= top)
    dr, de = max_range / samples, abs(e[1] - e[0])
    return float(np.sum(2 * np.pi * R**2 * np.cos(E) * inside) * dr * de)


def camera_air_volume(K: F64, width: int, height: int, camera_height: float, depth: float, top: float,
                      samples: int = 200) -> float:
    """Volume [m^3] of air in a level camera's frustum out to optical depth ``depth`` [m], above the ground."""
    u = (np.arange(samples) + 0.5) / samples * width
    v = (np.arange(samples) + 0.5) / samples * height
    z = (np.arange(samples) + 0.5) / samples * depth
    U, V, Z = np.meshgrid(u, v, z, indexing="ij")
    up = -(V - K[1, 2]) / K[1, 1] * Z  # height above the camera (image y points down)
    inside = (camera_height + up >= 0.0) & (camera_height + up <= top)
    cell = (width / samples / K[0, 0]) * (height / samples / K[1, 1]) * (depth / samples)
    return float(np.sum(inside * Z**2) * cell)
