"""Severity alignment for snow and rain (ReDAM beyond fog): the rate whose simulated LiDAR clutter matches the
reference's.

The statistic, per scan, is the **open-path echo rate**: the isolated returns within ``max_range`` (20 m) of the
sensor (`weatheralign.lidar.clutter.isolated_mask`, the DROR test: particles light one beam, surfaces light
neighbours) divided by the beams whose first ``max_range`` metres are open (no other return within it): a street
canyon has fewer open beams than an open road, and only open beams can see a particle, so the ratio is far less
scene-dependent than the raw count (measured on the synthetic reference, 10 frames: raw snow counts of the reference
and the fast simulator at the hidden rate differ by 10 %, the rates by 0.5 %).

`simulated_statistics` runs the fast simulator (`simulate_particles`, the reference's LiDAR with its detector noise)
on the reference's clear scans at a grid of rates; `fit_rate` interpolates the mean statistic against the rate on
log-log axes (the count grows like a power of the rate) to the reference's mean, and bootstraps whole frames of both
sides (the same simulated frames at every rate) for a percentile interval.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.config import ParticlesConfig
from weatheralign.data.frame import LidarScan
from weatheralign.lidar.clutter import isolated_mask
from weatheralign.lidar.particles import RAIN_REFLECTIVITY, SNOW_REFLECTIVITY, simulate_particles
from weatheralign.medium.conditions import field_spec
from weatheralign.sensors import LidarModel

F64 = NDArray[np.float64]


def open_path_echo_rate(points: NDArray, *, azimuth_step_rad: float, num_rings: int, max_range: float = 20.0
                        ) -> float:
    """Isolated returns within ``max_range`` [m] per open beam, for one scan ``points`` (N, >=5) [x, y, z [m],
    intensity, ring] in the sensor frame: the beams are the (ring, azimuth bin of ``azimuth_step_rad``) cells of a
    LiDAR with ``num_rings`` rings, a beam is open unless a non-isolated return within ``max_range`` falls in its
    cell (counted on the scan itself, so a real scan whose firing grid is estimated works the same)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 5:
        raise ValueError(f"open_path_echo_rate: points must be (N, >=5) [x, y, z, intensity, ring], got {pts.shape}")
    xyz = pts[:, :3]
    isolated = isolated_mask(xyz, azimuth_step_rad=azimuth_step_rad, max_range=max_range)
    surface = (np.linalg.norm(xyz, axis=1) < max_range) & ~isolated
    columns = max(1, int(round(2.0 * np.pi / azimuth_step_rad)))
    azimuth = np.mod(np.arctan2(xyz[surface, 1], xyz[surface, 0]), 2.0 * np.pi)
    cells = pts[surface, 4].astype(np.int64) * columns + np.minimum((azimuth / azimuth_step_rad).astype(np.int64),
                                                                    columns - 1)
    open_beams = num_rings * columns - len(np.unique(cells))
    return int(np.count_nonzero(isolated)) / max(open_beams, 1)


def reference_statistics(scans: Sequence[LidarScan], lidar: LidarModel) -> F64:
    """(F,) `open_path_echo_rate` of each reference scan through ``lidar``'s firing grid."""
    step = 2.0 * np.pi / lidar.columns_per_ring
    return np.array([open_path_echo_rate(s.points, azimuth_step_rad=step, num_rings=lidar.num_rings) for s in scans])


def simulated_statistics(scans: Sequence[LidarScan], kind: str, rates: Sequence[float], lidar: LidarModel,
                         particles: ParticlesConfig, scene_names: Sequence[str]) -> F64:
    """(R, F) `open_path_echo_rate` of each clear scan through the fast simulator at each rate [mm/h] of ``kind``
    (``snow`` or ``rain``; the field physics of ``particles``, the field of scan f seeded from ``scene_names[f]``:
    the same particles' positions scale with the rate, so the rates are compared on the same draws)."""
    if kind not in ("snow", "rain"):
        raise ValueError(f"kind = {kind!r}; expected 'snow' or 'rain'")
    step = 2.0 * np.pi / lidar.columns_per_ring
    reflectivity = SNOW_REFLECTIVITY if kind == "snow" else RAIN_REFLECTIVITY
    out = np.empty((len(rates), len(scans)))
    for r, rate in enumerate(rates):
        cfg = particles.model_copy(update={kind: getattr(particles, kind).model_copy(update={"rate_mm_h": rate})})
        for f, (scan, name) in enumerate(zip(scans, scene_names)):
            field = field_spec(cfg, kind, name, scan.timestamp).field()
            result = simulate_particles(scan, field, lidar=lidar, reflectivity=reflectivity)
            out[r, f] = open_path_echo_rate(result.points, azimuth_step_rad=step, num_rings=lidar.num_rings)
    return out


EXTRAPOLATION = 2.0
"""A tuned rate is extrapolated at most this factor beyond the grid's ends (and flagged ``beyond_grid``)."""


def _invert(mean_ref: float, means: F64, grid: F64, log_axes: bool = True) -> float:
    """The grid value whose interpolated mean statistic is ``mean_ref``: on log-log axes (``log_axes``) or linear
    ones, extrapolated along the end segments, at most `EXTRAPOLATION` times beyond the grid's ends."""
    forward = np.log if log_axes else (lambda v: np.asarray(v, dtype=np.float64))
    x_all = forward(np.maximum(means, 1e-12) if log_axes else means)
    y_all = forward(grid)
    order = np.argsort(x_all)
    x, y = x_all[order], y_all[order]
    target = float(forward(max(mean_ref, 1e-12) if log_axes else mean_ref))
    k = int(np.clip(np.searchsorted(x, target), 1, len(x) - 1))
    slope = (y[k] - y[k - 1]) / (x[k] - x[k - 1]) if x[k] > x[k - 1] else 0.0
    value = y[k - 1] + slope * (target - x[k - 1])
    if log_axes:
        limit = np.log(EXTRAPOLATION)
        return float(np.exp(np.clip(value, y_all[0] - limit, y_all[-1] + limit)))
    return float(np.clip(value, grid[0] / EXTRAPOLATION, grid[-1] * EXTRAPOLATION))


def bootstrap_fit(reference: NDArray, simulated: NDArray, grid: Sequence[float], *, log_axes: bool = True,
                  num_bootstrap: int = 1000, confidence: float = 0.95, seed: int = 0
                  ) -> tuple[float, float, float, F64]:
    """The grid value (``grid`` (R,) increasing, positive) at which the simulated mean statistic (``simulated``
    (R, F)) equals the reference's mean (``reference`` (F_ref,)) by `_invert`, with a percentile interval over
    ``num_bootstrap`` resamples of the reference frames and of the simulated frames (one draw of frame indices for
    every grid value). Returns (estimate, low, high, simulated means (R,))."""
    ref = np.asarray(reference, dtype=np.float64)
    sim = np.asarray(simulated, dtype=np.float64)
    values = np.asarray(grid, dtype=np.float64)
    if sim.ndim != 2 or sim.shape[0] != len(values) or len(values) < 2 or len(ref) < 1:
        raise ValueError(f"simulated must be (R, F) with R = {len(values)} >= 2 grid values, got {sim.shape}")
    if not np.all(np.diff(values) > 0) or not values[0] > 0:
        raise ValueError(f"the grid must be positive and increase, got {list(grid)}")
    means = sim.mean(axis=1)
    estimate = _invert(float(ref.mean()), means, values, log_axes)
    rng = np.random.default_rng(seed)
    boot = np.array([_invert(float(ref[rng.integers(0, len(ref), len(ref))].mean()),
                             sim[:, rng.integers(0, sim.shape[1], sim.shape[1])].mean(axis=1), values, log_axes)
                     for _ in range(num_bootstrap)])
    tail = (1.0 - confidence) / 2.0
    return estimate, float(np.quantile(boot, tail)), float(np.quantile(boot, 1.0 - tail)), means


@dataclass(frozen=True)
class RateFit:
    """The tuned rate [mm/h] with its frame-bootstrap interval; the reference's mean statistic, the simulated means
    per grid rate, and the grid."""

    rate_mm_h: float
    ci_low: float
    ci_high: float
    reference_mean: float
    simulated_means: tuple[float, ...]
    rates: tuple[float, ...]

    @property
    def beyond_grid(self) -> bool:
        """The reference's mean lies outside the simulated means: the rate is extrapolated (or clipped)."""
        return not min(self.simulated_means) <= self.reference_mean <= max(self.simulated_means)

    def metrics(self) -> dict[str, object]:
        return {"rate_mm_h": self.rate_mm_h, "rate_ci_low": self.ci_low, "rate_ci_high": self.ci_high,
                "beyond_grid": self.beyond_grid,
                "open_path_echo_rate_reference": self.reference_mean,
                "open_path_echo_rate_grid": dict(zip((f"{r:g}" for r in self.rates), self.simulated_means))}


def fit_rate(reference: NDArray, simulated: NDArray, rates: Sequence[float], *, num_bootstrap: int = 1000,
             confidence: float = 0.95, seed: int = 0) -> RateFit:
    """The rate at which the simulated mean statistic (``simulated`` (R, F) at ``rates`` (R,), increasing) equals the
    reference's mean (``reference`` (F_ref,)), interpolated on log-log axes, with a frame-bootstrap interval
    (`bootstrap_fit`)."""
    estimate, low, high, means = bootstrap_fit(reference, simulated, rates, num_bootstrap=num_bootstrap,
                                               confidence=confidence, seed=seed)
    return RateFit(estimate, low, high, float(np.mean(reference)), tuple(float(m) for m in means),
                   tuple(float(r) for r in rates))


__all__ = ["EXTRAPOLATION", "RateFit", "bootstrap_fit", "fit_rate", "open_path_echo_rate", "reference_statistics",
           "simulated_statistics"]
