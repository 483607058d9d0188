"""Snow lying on the ground as one depth field in world ground coordinates, and what it does to the LiDAR's ground
returns: the surface rises by the snow's depth and answers with snow's reflectivity.

The depth (`snow_depth`) is a function of the world position (x, y) and a seed alone, so every frame, the LiDAR and
every camera of a scene see the same drifts and the same wheel tracks (`TireTracks`: lines along the road where
traffic has pressed the snow down to a thin slush). Snow stays on surfaces that face up: on a surface tilted by
``phi`` from the vertical it lies ``w = clip((cos phi - cos phi_max) / (1 - cos phi_max), 0, 1)`` times as deep
(nothing beyond ``max_slope_deg``), and hides the surface under it over the share
``c = w (1 - exp(-w d / hiding_depth_m))`` (`snow_coverage`); the LiDAR and the cameras use the same ``c``.

A return at range ``r`` on a surface of normal ``n`` now comes from the snow surface ``d`` above it, along the same
beam: ``r' = r - d / cos(theta)``, ``theta`` the incidence angle from the normal. Both surfaces are taken as
Lambertian at the same incidence, so over the covered share of the beam's footprint the intensity scales by the
ratio of their reflectivities at the LiDAR's wavelength (fresh snow about 0.8 at 905 nm, asphalt 0.1-0.2), up to
the sensor's saturation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from weatheralign.ground.kernels import tracks_factor_kernel
from weatheralign.ground.wet import fractal_noise, value_noise

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SnowCover:
    """Snow on the ground: ``depth_m`` on average, between ``(1 - variation)`` and ``(1 + variation)`` times it over
    features about ``cell_m`` wide; its reflectivity and the bare pavement's at the LiDAR's wavelength. Off the ground
    plane (a roof, a car top, a kerb) a beam runs at most ``edge_run_m`` over the snow before it reaches the surface's
    edge (`snow_covered_ground`)."""

    depth_m: float = 0.05
    variation: float = 0.5
    cell_m: float = 6.0
    snow_reflectivity: float = 0.8
    pavement_reflectivity: float = 0.15
    visible_albedo: float = 0.85  # fresh snow in the visible (Warren 1982: 0.8-0.95)
    hiding_depth_m: float = 0.01  # the depth that hides all but 1/e of the surface under it
    max_slope_deg: float = 50.0  # steeper surfaces hold no snow
    edge_run_m: float = 0.5  # an off-ground surface's extent towards the sensor: a car top's, a roof's half width

    def __post_init__(self) -> None:
        if not self.depth_m > 0 or not self.cell_m > 0 or not self.hiding_depth_m > 0 or not self.edge_run_m > 0:
            raise ValueError(f"SnowCover.depth_m, cell_m, hiding_depth_m and edge_run_m must be > 0, got "
                             f"{self.depth_m}, {self.cell_m}, {self.hiding_depth_m}, {self.edge_run_m}")
        if not 0.0 < self.max_slope_deg < 90.0:
            raise ValueError(f"SnowCover.max_slope_deg must be in (0, 90), got {self.max_slope_deg}")
        if not 0.0 <= self.variation < 1.0:
            raise ValueError(f"SnowCover.variation must be in [0, 1), got {self.variation}")
        for name in ("snow_reflectivity", "pavement_reflectivity", "visible_albedo"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"SnowCover.{name} must be in (0, 1], got {getattr(self, name)}")


class SnowCoverEffect(NamedTuple):
    """What lying snow does to N ground returns."""

    points: F64  # (N, 3) the returns on the snow surface [m], same frame as the input
    intensity: F64  # (N,) new intensity (0..saturation)
    depth_m: F64  # (N,) snow depth at the return [m]


@dataclass(frozen=True)
class TireTracks:
    """Wheel tracks in the snow along a road running in the world direction ``direction`` (x, y) through the world
    point ``origin`` (x, y) [m] (e.g. the ego's position and heading): per lane centre at the lateral offsets
    ``lane_offsets_m`` (left positive) two tracks ``gauge_m`` apart, each ``width_m`` wide, that wander sideways by up
    to ``wander_m`` over ``wander_cell_m`` along the road; in them only ``remaining_share`` of the snow is left."""

    direction: tuple[float, float]
    origin: tuple[float, float]
    lane_offsets_m: tuple[float, ...] = (-3.5, 0.0, 3.5)
    gauge_m: float = 1.6
    width_m: float = 0.45
    remaining_share: float = 0.3
    wander_m: float = 0.15
    wander_cell_m: float = 25.0

    def __post_init__(self) -> None:
        if not np.hypot(*self.direction) > 0:
            raise ValueError(f"TireTracks.direction must be a non-zero (x, y) vector, got {self.direction}")
        if not self.width_m > 0 or not self.gauge_m > self.width_m:
            raise ValueError(f"TireTracks needs gauge_m > width_m > 0, got {self.gauge_m}, {self.width_m}")
        if not 0.0 <= self.remaining_share <= 1.0:
            raise ValueError(f"TireTracks.remaining_share must be in [0, 1], got {self.remaining_share}")

    @staticmethod
    def along_heading(T_world_sensor: F64) -> TireTracks:
        """Tracks along the heading (x axis) of a sensor at pose ``T_world_sensor`` (4, 4), centred on its lane:
        anchored at the foot of the perpendicular from the world origin onto that line, so that frames of one
        straight drive share the tracks' wander."""
        T = np.asarray(T_world_sensor, dtype=np.float64)
        heading = T[:2, 0] / np.hypot(T[0, 0], T[1, 0])
        position = T[:2, 3]
        foot = position - (position @ heading) * heading
        return TireTracks(direction=(float(heading[0]), float(heading[1])), origin=(float(foot[0]), float(foot[1])))

    def depth_factor(self, xy_world: F64, seed: int) -> F64:
        """(N,) the share of the snow left at world positions (N, 2): ``remaining_share`` at a track's centre
        line, rising as a raised cosine to 1 at its edges, 1 off the tracks (compiled: `depth_factor_naive`'s rule
        in `weatheralign.ground.kernels.tracks_factor_kernel`)."""
        along_unit = np.asarray(self.direction, dtype=np.float64) / np.hypot(*self.direction)
        return tracks_factor_kernel(np.ascontiguousarray(np.asarray(xy_world, dtype=np.float64).reshape(-1, 2)),
                                    np.asarray(self.origin, dtype=np.float64), along_unit,
                                    np.asarray(self.lane_offsets_m, dtype=np.float64), float(self.gauge_m),
                                    float(self.width_m), float(self.remaining_share), float(self.wander_m),
                                    float(self.wander_cell_m), int(seed))

    def depth_factor_naive(self, xy_world: F64, seed: int) -> F64:
        """`depth_factor` in numpy: the oracle of its kernel."""
        xy = np.asarray(xy_world, dtype=np.float64) - np.asarray(self.origin, dtype=np.float64)
        along_unit = np.asarray(self.direction, dtype=np.float64) / np.hypot(*self.direction)
        along = xy @ along_unit
        lateral = xy @ np.array([-along_unit[1], along_unit[0]])
        shift = self.wander_m * (2.0 * value_noise(np.column_stack([along, np.zeros_like(along)]),
                                                   self.wander_cell_m, seed + 7) - 1.0)
        factor = np.ones(len(xy))
        half = 0.5 * self.width_m
        for lane in self.lane_offsets_m:
            for wheel in (-0.5 * self.gauge_m, 0.5 * self.gauge_m):
                distance = np.abs(lateral - shift - lane - wheel)
                dip = np.where(distance < half, 0.5 * (1.0 + np.cos(np.pi * distance / half)), 0.0)
                factor = np.minimum(factor, 1.0 - (1.0 - self.remaining_share) * dip)
        return factor


def snow_depth(xy_world: F64, cover: SnowCover, seed: int, tracks: TireTracks | None = None) -> F64:
    """Snow depth [m] on level ground at world positions (N, 2): ``depth_m (1 + variation (2 u - 1))``, ``u``
    fractal noise, pressed down in the ``tracks``."""
    u = fractal_noise(xy_world, cover.cell_m, seed)
    depth = cover.depth_m * (1.0 + cover.variation * (2.0 * u - 1.0))
    return depth if tracks is None else depth * tracks.depth_factor(xy_world, seed)


def snow_coverage(depth_m: F64, cos_up: F64, cover: SnowCover) -> tuple[F64, F64]:
    """(covered share ``c``, depth [m]) of surfaces whose unit normals make ``cos_up`` (N,) with the vertical, under
    level-ground snow ``depth_m`` (N,) (module docstring): both 0 on surfaces steeper than ``max_slope_deg``."""
    cos_max = np.cos(np.radians(cover.max_slope_deg))
    weight = np.clip((np.asarray(cos_up, dtype=np.float64) - cos_max) / (1.0 - cos_max), 0.0, 1.0)
    depth = weight * np.asarray(depth_m, dtype=np.float64)
    return weight * (1.0 - np.exp(-depth / cover.hiding_depth_m)), depth


def surface_snow(xy_world: F64, cos_up: F64, cover: SnowCover, seed: int, tracks: TireTracks | None = None
                 ) -> tuple[F64, F64]:
    """`snow_coverage` (covered share, depth [m]) of `snow_depth` at world positions (N, 2) on surfaces whose normals
    make ``cos_up`` (N,) with the vertical, the depth field asked only where the surface is level enough to hold
    snow (elsewhere both are 0 whatever the field says)."""
    cos_up = np.asarray(cos_up, dtype=np.float64)
    holds = cos_up > np.cos(np.radians(cover.max_slope_deg))
    level = np.zeros(len(cos_up))
    level[holds] = snow_depth(np.asarray(xy_world, dtype=np.float64).reshape(-1, 2)[holds], cover, seed, tracks)
    return snow_coverage(level, cos_up, cover)


def snow_covered_ground(points: F64, origins: F64, normals: F64, intensity: F64, depth_m: F64, cover: SnowCover,
                        saturation: float = 255.0, coverage: F64 | None = None,
                        max_run_m: F64 | float = np.inf) -> SnowCoverEffect:
    """Returns (N, 3) seen from ``origins`` (N, 3) or (3,) on surfaces of unit ``normals`` (N, 3) or (3,), under
    snow ``depth_m`` (N,) [m]: each moved along its beam onto the snow, ``d / cos θ`` nearer (the top of a layer
    ``d`` thick over the surface, ``θ`` the incidence), or, where that would take the beam more than ``max_run_m``
    (N,) or scalar [m] across the surface (``d tan θ``: a grazing beam over a roof or a car top), through the layer's
    side at that run: ``max_run_m / sin θ`` nearer, inside the layer (default: no edge, the ground plane). Over the
    ``coverage`` (N,) share of its footprint (default all) the intensity scaled by ``snow_reflectivity /
    pavement_reflectivity``, clipped at ``saturation``."""
    points = np.asarray(points, dtype=np.float64)
    rays = points - origins
    ranges = np.linalg.norm(rays, axis=-1, keepdims=True)
    directions = rays / ranges
    normals = np.broadcast_to(np.asarray(normals, dtype=np.float64), points.shape)
    cos_incidence = np.clip(np.abs(np.sum(directions * normals, axis=-1, keepdims=True)), 1e-9, 1.0)
    sin_incidence = np.sqrt(1.0 - cos_incidence**2)
    depth = np.asarray(depth_m, dtype=np.float64)[:, None]
    run = np.broadcast_to(np.asarray(max_run_m, dtype=np.float64), depth.shape[:1])[:, None]
    with np.errstate(divide="ignore"):
        through_side = np.where(sin_incidence > 0.0, run / sin_incidence, np.inf)
    moved = points - directions * np.minimum(depth / cos_incidence, through_side)
    ratio = cover.snow_reflectivity / cover.pavement_reflectivity
    dry = np.asarray(intensity, dtype=np.float64)
    snowy = np.minimum(dry * ratio, saturation)
    new = snowy if coverage is None else (1.0 - coverage) * dry + coverage * snowy
    return SnowCoverEffect(moved, new, depth)


__all__ = ["snow_coverage", "snow_covered_ground", "snow_depth", "SnowCover", "SnowCoverEffect", "surface_snow",
           "TireTracks"]
