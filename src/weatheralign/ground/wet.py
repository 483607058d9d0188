"""A wet road as one water-depth field in world ground coordinates, and what it does to the LiDAR's ground returns.

The field (`water_depth`) is a function of the world position (x, y) and a seed alone, so every frame, the LiDAR and
every camera of a scene see the same wet patches and puddles. Water first fills the pavement's macrotexture (the
valleys between the stones, ``texture_depth_m`` deep): with a 45-degree (triangular) texture profile a depth ``h``
covers the share ``min(h / texture_depth_m, 1)`` of the surface (`wetted_share`); where the water rises above the
texture the surface is a flat puddle. The covered share answers as water over pavement
(`weatheralign.ground.optics.wet_lidar_factor`), the rest as dry pavement. Returns that fall below the detector's
noise floor are lost (`WetGroundEffect.lost`): the film dims the value an integer reading stood for before the sensor
rounded it (`weatheralign.lidar.quantum`), which the wet return then reports.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from weatheralign.ground.kernels import fractal_noise_kernel, value_noise_kernel
from weatheralign.ground.optics import WATER_ABSORPTION_905_PER_M, WATER_INDEX, wet_lidar_factor

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class WetRoad:
    """A wet road's water: a film of ``film_depth_m`` on average, varying over ``cell_m``, with puddles of
    ``puddle_depth_m`` over the share ``puddle_share`` of the ground; the pavement's macrotexture depth, its
    reflectivity at the LiDAR's wavelength and water's optics. Lengths in metres."""

    film_depth_m: float = 0.0005
    texture_depth_m: float = 0.001
    puddle_share: float = 0.08
    puddle_depth_m: float = 0.01
    cell_m: float = 4.0
    pavement_reflectivity: float = 0.15
    refractive_index: float = WATER_INDEX
    absorption_per_m: float = WATER_ABSORPTION_905_PER_M

    def __post_init__(self) -> None:
        for name in ("film_depth_m", "texture_depth_m", "puddle_depth_m", "cell_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"WetRoad.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.puddle_share < 1.0:
            raise ValueError(f"WetRoad.puddle_share must be in [0, 1), got {self.puddle_share}")
        if not 0.0 < self.pavement_reflectivity <= 1.0:
            raise ValueError(f"WetRoad.pavement_reflectivity must be in (0, 1], got {self.pavement_reflectivity}")


class WetGroundEffect(NamedTuple):
    """What a wet road does to N ground returns."""

    intensity: F64  # (N,) new intensity (0..255 scale), 0 where lost
    lost: NDArray[np.bool_]  # (N,) below the detector's floor: the return is gone
    depth_m: F64  # (N,) water depth at the point [m]
    factor: F64  # (N,) intensity wet / dry


def _hash01(ix: NDArray[np.int64], iy: NDArray[np.int64], seed: int) -> F64:
    """A pseudo-random value in [0, 1) per integer lattice point and seed (an integer hash; identical on every
    machine)."""
    h = (ix * 73856093) ^ (iy * 19349663) ^ (np.int64(seed) * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(1 << 24)


def value_noise(xy: F64, cell_m: float, seed: int) -> F64:
    """Smooth value noise in [0, 1) at world positions ``xy`` (N, 2) [m], features about ``cell_m`` wide: the
    compiled `weatheralign.ground.kernels.value_noise_kernel` of `value_noise_naive`'s rule."""
    xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    return value_noise_kernel(xy, float(cell_m), int(seed))


def value_noise_naive(xy: F64, cell_m: float, seed: int) -> F64:
    """`value_noise` in numpy: the oracle of its kernel."""
    g = np.asarray(xy, dtype=np.float64) / cell_m
    i = np.floor(g)
    f = g - i
    f = f * f * (3.0 - 2.0 * f)
    ix, iy = i[:, 0].astype(np.int64), i[:, 1].astype(np.int64)
    n00, n10 = _hash01(ix, iy, seed), _hash01(ix + 1, iy, seed)
    n01, n11 = _hash01(ix, iy + 1, seed), _hash01(ix + 1, iy + 1, seed)
    fx, fy = f[:, 0], f[:, 1]
    return (n00 * (1 - fx) + n10 * fx) * (1 - fy) + (n01 * (1 - fx) + n11 * fx) * fy


def fractal_noise(xy: F64, cell_m: float, seed: int, octaves: int = 4) -> F64:
    """Value noise summed over ``octaves`` halving scales (weights 1/2, 1/4, ...), rescaled to [0, 1): the compiled
    `weatheralign.ground.kernels.fractal_noise_kernel` of `fractal_noise_naive`'s rule."""
    xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    return fractal_noise_kernel(xy, float(cell_m), int(seed), int(octaves))


def fractal_noise_naive(xy: F64, cell_m: float, seed: int, octaves: int = 4) -> F64:
    """`fractal_noise` in numpy: the oracle of its kernel."""
    total, weight, norm = np.zeros(len(xy)), 1.0, 0.0
    for octave in range(octaves):
        total += weight * value_noise_naive(xy, cell_m / 2**octave, seed * 31 + octave)
        norm += weight
        weight *= 0.5
    return total / norm


def water_depth(xy_world: F64, road: WetRoad, seed: int) -> F64:
    """Water depth [m] at world positions (N, 2): a film ``film_depth_m * 2 u`` (``u`` fractal noise in [0, 1), so
    ``film_depth_m`` on average) and, where a second, coarser noise exceeds its ``1 - puddle_share`` level
    (`puddle_margin` > 0), puddles of ``puddle_depth_m``."""
    film = film_depth(xy_world, road, seed)
    if road.puddle_share == 0:
        return film
    return np.where(puddle_margin(xy_world, road, seed) > 0, road.puddle_depth_m, film)


def film_depth(xy_world: F64, road: WetRoad, seed: int) -> F64:
    """The film's depth [m] at world positions (N, 2), puddles aside (`water_depth`)."""
    return road.film_depth_m * 2.0 * fractal_noise(xy_world, road.cell_m, seed)


def puddle_margin(xy_world: F64, road: WetRoad, seed: int) -> F64:
    """How far the puddle noise at world positions (N, 2) lies above its puddle level: a puddle where > 0 (-inf
    everywhere without puddles). A smooth field, so its zero level is a smooth shoreline at any resolution."""
    if road.puddle_share == 0:
        return np.full(len(np.asarray(xy_world).reshape(-1, 2)), -np.inf)
    return fractal_noise(xy_world, 2.0 * road.cell_m, seed + 1) - _puddle_level(road.puddle_share)


@lru_cache(maxsize=32)
def _puddle_level(share: float, samples: int = 1 << 16) -> float:
    """The fractal-noise level that ``share`` of the plane exceeds (from its distribution on a fixed lattice, so it
    does not depend on which points are asked)."""
    g = (np.arange(samples, dtype=np.float64) * 0.6180339887498949) % 1.0
    xy = np.stack([np.arange(samples) * 0.7548776662466927 % 1.0, g], axis=1) * 4096.0
    return float(np.quantile(fractal_noise(xy, 8.0, 12345), 1.0 - share))


def wetted_share(depth_m: F64, texture_depth_m: float) -> F64:
    """Share of the surface under water for a water depth (45-degree texture profile): ``min(h / texture, 1)``."""
    return np.clip(np.asarray(depth_m, dtype=np.float64) / texture_depth_m, 0.0, 1.0)


def incidence_angle(points: F64, origins: F64, normals: F64) -> F64:
    """Angle [rad] between the ray from ``origins`` to ``points`` (N, 3) and the surface ``normals`` (N, 3) (or
    (3,)): 0 at normal incidence."""
    rays = np.asarray(points, dtype=np.float64) - origins
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    normals = np.broadcast_to(np.asarray(normals, dtype=np.float64), rays.shape)
    return np.arccos(np.clip(np.abs(np.sum(rays * normals, axis=-1)), 0.0, 1.0))


def wet_ground(intensity: F64, incidence: F64, depth_m: F64, road: WetRoad, noise_floor: float | F64,
               clear: F64 | None = None, noise_std: float | F64 = 0.0, normals: F64 | None = None) -> WetGroundEffect:
    """Ground returns' intensities (N,) (0..255) at incidence angles (N,) [rad] under water ``depth_m`` (N,) [m]: the
    wetted share answers with `wet_lidar_factor`, the rest dry; returns the water takes below ``noise_floor``
    (0..255; a scalar or (N,) the floor at each return's range) are lost (a return already below it dry, which a real
    sensor may still report, is kept, scaled).

    ``clear`` (N,): the clear value each rounded intensity stood for before the sensor rounded it
    (`weatheralign.lidar.quantum.scan_clear_readings`; None: every intensity as read). The water dims that value:
    it decides the loss (a reading at the floor is not lost to any film) and is the wet return's intensity, so the
    air's weather that reads the wet scan next tests the same value.

    ``noise_std`` (0..255; a scalar or (N,) at each return's range): the detector's signal-independent intensity
    noise σ_0. The clear reading carries its own
    noise, which the film dims with the signal by the factor f; the wet reading lacks ``σ_0² (1 - f²)`` of its
    variance (a signal-proportional part scales exactly), added with the standard ``normals`` (N,) of the beams'
    streams and clipped to 0..255 before the floor decides, as the fog and the particles read a weakened target."""
    share = wetted_share(depth_m, road.texture_depth_m)
    water = wet_lidar_factor(incidence, road.pavement_reflectivity, depth_m, road.refractive_index,
                             road.absorption_per_m)
    factor = 1.0 - share + share * water
    dry = np.asarray(intensity, dtype=np.float64)
    new = (dry if clear is None else np.where(factor < 1.0, np.asarray(clear, dtype=np.float64), dry)) * factor
    if np.any(np.asarray(noise_std) > 0.0):
        if normals is None or np.shape(normals) != dry.shape:
            raise ValueError(f"wet_ground: a noise_std > 0 needs normals of shape {dry.shape}, got "
                             f"{None if normals is None else np.shape(normals)}")
        missing = noise_std * np.sqrt(np.maximum(1.0 - factor * factor, 0.0))
        new = np.clip(new + missing * np.asarray(normals, dtype=np.float64), 0.0, 255.0)
    lost = (new < noise_floor) & (np.asarray(intensity) >= noise_floor)
    return WetGroundEffect(np.where(lost, 0.0, new), lost, np.asarray(depth_m, dtype=np.float64), factor)


__all__ = ["film_depth", "fractal_noise", "fractal_noise_naive", "incidence_angle", "puddle_margin", "value_noise",
           "value_noise_naive", "water_depth", "wet_ground", "WetGroundEffect", "WetRoad", "wetted_share"]
