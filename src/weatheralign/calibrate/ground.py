"""Severity alignment of the ground (ReDAM for the wet road and the snow cover): the film or snow depth whose
simulated LiDAR ground matches the reference's.

The statistics, per scan, come from the ground the simulation itself finds (`weatheralign.ground.edit.scan_surfaces`:
the plane by RANSAC, refined by least squares):

- snow (`snow_ground_height`): the LiDAR's height [m] above its returns on the fitted ground between
  `GROUND_BAND_M`, their median (the road's, not the kerbs' or a least-squares plane's, which sidewalks tilt from scene
  to scene). Lying snow raises the surface the beams strike by its depth, wheel tracks less; the clear reference
  scans give the bare height.
- wet (`wet_ground_intensity`): the mean intensity (0..255) of the returns on the fitted ground between `GROUND_BAND_M`
  (a mean, not a median: intensities are integers, and a median moves in whole steps). A water film turns part of the
  pavement's diffuse answer into a mirror's, which sends it away: the ground dims as the film deepens (until it covers
  the texture), and the weakest returns fall under the floor.

`simulated_ground_statistics` edits the reference's clear scans with the simulation's ground (`edit_scan`, at each
depth of a grid, each scan's field seeded from its name), passes them through the split's tuned snowfall or rain (the
fast particle simulator: the drops dim the ground's echoes on their way) and measures them; the depth whose mean
statistic matches the weather split's is found on linear axes (both statistics change about linearly with the depth
over the grid) with a frame-bootstrap interval (`weatheralign.calibrate.precipitation.bootstrap_fit`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.calibrate.precipitation import bootstrap_fit
from weatheralign.config import ParticlesConfig
from weatheralign.data.frame import LidarScan
from weatheralign.ground.edit import GroundState, UnseenBeams, edit_scan, scan_surfaces, unseen_beams
from weatheralign.ground.snow import SnowCover, TireTracks
from weatheralign.ground.wet import WetRoad
from weatheralign.lidar.particles import RAIN_REFLECTIVITY, SNOW_REFLECTIVITY, simulate_particles
from weatheralign.medium.conditions import field_spec
from weatheralign.sensors import LidarModel

F64 = NDArray[np.float64]

GROUND_BAND_M = (3.0, 30.0)
"""Ranges [m] of the ground returns whose intensity is measured: nearer, the car's own body and the ring gaps; beyond,
too few returns per scan."""

GROUND_KINDS = {"rain": "wet", "snow": "snow"}
"""The ground each precipitation split leaves."""


def _ground_band(scan: LidarScan) -> tuple[NDArray[np.bool_], F64]:
    """The returns of ``scan`` on its fitted ground within `GROUND_BAND_M` (N,), and every return's height [m] below
    the sensor along the plane's normal (N,)."""
    surfaces = scan_surfaces(scan, off_ground=False)
    xyz = scan.points[:, :3].astype(np.float64)
    ranges = np.linalg.norm(xyz, axis=1)
    band = surfaces.on_ground & (ranges >= GROUND_BAND_M[0]) & (ranges <= GROUND_BAND_M[1])
    return band, -(xyz @ np.asarray(surfaces.plane.normal))


def snow_ground_height(scan: LidarScan) -> float:
    """The median height [m] of the LiDAR above its returns on the fitted ground within `GROUND_BAND_M` (nan
    without any)."""
    band, below = _ground_band(scan)
    return float(np.median(below[band])) if band.any() else float("nan")


def wet_ground_intensity(scan: LidarScan) -> float:
    """The mean intensity (0..255) of the returns of ``scan`` on its fitted ground within `GROUND_BAND_M` (nan
    without any)."""
    band, _ = _ground_band(scan)
    return float(np.mean(scan.intensity_255()[band])) if band.any() else float("nan")


def ground_statistic(scan: LidarScan, kind: str) -> float:
    """`snow_ground_height` (``kind`` ``snow``) or `wet_ground_intensity` (``rain``) of one scan."""
    if kind not in GROUND_KINDS:
        raise ValueError(f"kind = {kind!r}; expected one of {sorted(GROUND_KINDS)}")
    return snow_ground_height(scan) if kind == "snow" else wet_ground_intensity(scan)


def ground_seed(name: str, kind: str) -> int:
    """The ground field's seed of the scan ``name`` under ``kind``: a hash of both."""
    return int.from_bytes(hashlib.sha256(f"{name}/{kind}/ground".encode()).digest()[:4], "little") & 0x7FFFFFFF


def ground_state(kind: str, depth_m: float, seed: int, scan: LidarScan) -> GroundState:
    """The simulation's ground of ``kind`` at ``depth_m`` (the mean film depth of a wet road, with the default
    puddles, or the snow depth, with wheel tracks along the scan's heading)."""
    if kind == "rain":
        return GroundState(road=WetRoad(film_depth_m=depth_m), seed=seed)
    return GroundState(cover=SnowCover(depth_m=depth_m), tracks=TireTracks.along_heading(scan.T_global_lidar),
                       seed=seed)


@dataclass(frozen=True)
class TunedAir:
    """The split's snowfall or rain as the calibration tuned it: the particles' physics (``particles``, its
    ``<kind>.rate_mm_h`` the tuned rate) and the reference's LiDAR."""

    particles: ParticlesConfig
    lidar: LidarModel


def grounded_scans(scans: Sequence[LidarScan], names: Sequence[str], kind: str, depth_m: float,
                   noise_floor: float, noise_std: float = 0.0,
                   floor_scale: Callable[[F64], F64] | None = None,
                   lidar: LidarModel | None = None) -> list[LidarScan]:
    """Each clear scan with the simulation's ground of ``kind`` at ``depth_m`` [m] (`edit_scan` on the scan's own
    surfaces, read by a detector of intensity noise ``noise_std`` and floor ``noise_floor`` (0..255; returns under
    it lost), the field seeded from the scan's name): what the weather split's air falls onto, so the rate's
    statistic is measured over the ground the split has. ``floor_scale``: a raw-power detector's floor factor
    (`weatheralign.sensors.LidarModel.floor_scale`; None: constant). ``lidar``: the sensor whose beams without return
    meet the snow on a dark road (`unseen_beams`, as `simulate` does); None: no return added."""
    return [edit_scan(scan, scan_surfaces(scan, off_ground=kind == "snow"),
                      ground_state(kind, float(depth_m), ground_seed(name, kind), scan), noise_floor, noise_std,
                      floor_scale, _unseen(scan, kind, lidar)).scan
            for scan, name in zip(scans, names)]


def _unseen(scan: LidarScan, kind: str, lidar: LidarModel | None) -> UnseenBeams | None:
    """The beams without return of ``scan`` where snow may add returns (`unseen_beams`), else None."""
    return unseen_beams(scan, lidar) if kind == "snow" and lidar is not None else None


def simulated_ground_statistics(scans: Sequence[LidarScan], names: Sequence[str], kind: str,
                                depths_m: Sequence[float], noise_floor: float, air: TunedAir | None = None,
                                noise_std: float = 0.0, floor_scale: Callable[[F64], F64] | None = None) -> F64:
    """(D, F) `ground_statistic` of each clear scan with the simulation's ground of ``kind`` at each depth [m]
    (`edit_scan` on the scan's own surfaces, read by a detector of intensity noise ``noise_std`` and floor
    ``noise_floor`` (0..255; returns under it lost); the fields seeded from ``names``: the same wet patches and
    tracks at every depth), then through ``air``'s particles (the same field per scan at every depth) where given."""
    out = np.empty((len(depths_m), len(scans)))
    for f, (scan, name) in enumerate(zip(scans, names)):
        surfaces = scan_surfaces(scan, off_ground=kind == "snow")
        unseen = _unseen(scan, kind, None if air is None else air.lidar)
        for d, depth in enumerate(depths_m):
            state = ground_state(kind, float(depth), ground_seed(name, kind), scan)
            edited = edit_scan(scan, surfaces, state, noise_floor, noise_std, floor_scale, unseen).scan
            if air is not None:
                weather = simulate_particles(edited, field_spec(air.particles, kind, name, scan.timestamp).field(),
                                               lidar=air.lidar,
                                               reflectivity=SNOW_REFLECTIVITY if kind == "snow" else RAIN_REFLECTIVITY)
                edited = weather.apply_to(edited)
            out[d, f] = ground_statistic(edited, kind)
    return out


@dataclass(frozen=True)
class DepthFit:
    """The tuned depth [m] with its frame-bootstrap interval; the reference's mean statistic, the simulated means per
    grid depth, the grid and the statistic's name."""

    depth_m: float
    ci_low: float
    ci_high: float
    reference_mean: float
    simulated_means: tuple[float, ...]
    depths_m: tuple[float, ...]
    statistic: str

    @property
    def beyond_grid(self) -> bool:
        """The reference's mean lies outside the simulated means: the depth is extrapolated (or clipped)."""
        return not min(self.simulated_means) <= self.reference_mean <= max(self.simulated_means)

    def metrics(self) -> dict[str, object]:
        return {"depth_m": self.depth_m, "depth_ci_low": self.ci_low, "depth_ci_high": self.ci_high,
                "beyond_grid": self.beyond_grid, "statistic": self.statistic,
                "statistic_reference": self.reference_mean,
                "statistic_grid": dict(zip((f"{d:g}" for d in self.depths_m), self.simulated_means))}


STATISTICS = {"snow": "LiDAR height above its ground returns within 3-30 m, median [m]",
              "rain": "mean intensity of the ground returns within 3-30 m (0..255)"}


def fit_depth(reference: NDArray, simulated: NDArray, depths_m: Sequence[float], kind: str, *,
              num_bootstrap: int = 1000, confidence: float = 0.95, seed: int = 0) -> DepthFit:
    """The depth at which the simulated mean statistic (``simulated`` (D, F) at ``depths_m`` (D,), increasing)
    equals the reference's mean (``reference`` (F_ref,), nan frames left out), on linear axes, with a frame-bootstrap
    interval (`bootstrap_fit`)."""
    ref = np.asarray(reference, dtype=np.float64)
    sim = np.asarray(simulated, dtype=np.float64)
    ref, sim = ref[np.isfinite(ref)], sim[:, np.all(np.isfinite(sim), axis=0)]
    if len(ref) == 0 or sim.shape[1] == 0:
        raise ValueError(f"fit_depth {kind}: no frame has a ground to measure")
    estimate, low, high, means = bootstrap_fit(ref, sim, depths_m, log_axes=False, num_bootstrap=num_bootstrap,
                                               confidence=confidence, seed=seed)
    return DepthFit(estimate, low, high, float(ref.mean()), tuple(float(m) for m in means),
                    tuple(float(d) for d in depths_m), STATISTICS[kind])


__all__ = ["DepthFit", "GROUND_BAND_M", "GROUND_KINDS", "STATISTICS", "fit_depth", "ground_seed", "ground_state",
           "grounded_scans", "TunedAir", "ground_statistic", "simulated_ground_statistics", "snow_ground_height",
           "wet_ground_intensity"]
