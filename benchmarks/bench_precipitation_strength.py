"""How strong are our snow and rain? Weather points per scan against rate and against the sensor's sensitivity, for
the fast simulator, the synthetic reference's exact Monte-Carlo process and the closed form
(`weatheralign.lidar.particles.strength`), beside the published simulators' figures on the same clouds and real
measurements (``docs/physics.md`` section 3.5).

Run from the repository root: ``.venv/bin/python -m benchmarks.bench_precipitation_strength [--quick]
[--peers PATH]``. Writes ``reports/benchmarks/precipitation_strength.json`` and ``precipitation_strength.png``.

Scenes (`street_scene`): a spinning LiDAR at its mounting height over flat asphalt (reflectivity 0.1) inside a ring of
facades (0.3) 30 m away and 6 m high, the sky above them; every beam's clear intensity from the sensor's own
intensity model (Lambertian, cos of the incidence), beams under the detector floor dropped from the clear scan:

- ``hdl32e``: the synthetic world's HDL-32E (32 rings x 1085 firings, 1.84 m, 100 m);
- ``hdl64``: an HDL-64 grid like the synthetic reference's (64 rings x 900 firings, 1.95 m, 120 m).

Sensors (`SENSORS`): what decides whether a particle echo is reported, the intensity model and the detector floor:

- ``world``: the synthetic world's HDL-32E (configs/world_rig.yaml): calibrated ``100 ρ``, a raw-power detector with
  a 10 % target at the floor at 35 m (floor ``10 (r / 35 m)²``);
- ``world_constant_floor``: the world's earlier sensor, ``255 ρ min(1, 10 m / r)`` with a constant floor 0.5;
- ``reference``: the synthetic reference's HDL-64 (`weatheralign.config.ReferenceLidarConfig`): the same intensity
  model with a raw-power detector, floor 5.1 at 50 m (the HDL-64E datasheet's 10 % target at 50 m; noise-free here);
- ``hahner_floor0.5``: Hahner's raw ``255 ρ (1 m / r)²`` with the floor 0.5 (the sensor of the issue's comparison);
- ``raw_rated<R>m``: raw power (``1 / r²``) with the floor at which a 10 % target is detected out to R m
  (`rated_intensity`, floor 1); the sensitivity sweep runs R = 12.5 … 200 m. Hahner's intensity with the floor 0.5
  is such a sensor rated 7.1 m.

Particles: snow at 1.5 m/s (Gunn-Marshall spectrum, reflectivity 0.9), rain at its rate's own fall speed
(Marshall-Palmer, 0.02); one field seed. Counts: ``scattered`` (a target beam reports a weather echo), ``clutter``
(a beam without target does), ``lost``, ``attenuated`` (fast only); ``weather_share`` = weather echoes / points of
the weather scan, as labelled real scans report it.

``--peers PATH``: a JSON list of the published simulators' runs on the clouds (entries ``{simulator, commit,
cloud, medium, rate_mm_h, counts}``), measured outside this repository with their own code; they are stored with
the results and drawn on the figure (the cloud workloads run our fast simulator on the same clouds, and count the
snow points DROR finds in CADC's box around the car, `dror_outliers`, to compare with CADC's per-drive counts). Real
measurements: `REAL_FIGURES`. ``--clouds-only`` reruns the cloud workloads alone; ``--sensors NAME ...`` reruns the
street-scene entries of those sensors (and the clouds), keeping the other entries of ``--out``; ``--replot`` redraws
the figure.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import REAL, STF_ID
from weatheralign.atomic import write_json
from weatheralign.config import LidarConfig, ReferenceLidarConfig
from weatheralign.lidar.particles.strength import EchoSensor, expected_weather_points, rated_intensity
from weatheralign.sensors import HAHNER_INTENSITY, SYNTHETIC_INTENSITY, lidar_model_from_params

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "precipitation_strength.json"
FIGURE = REPO / "reports" / "benchmarks" / "precipitation_strength.png"
WORLD_ROOT = REPO / "data" / "world"

SNOW_RATES = (0.5, 1.0, 2.0, 4.0, 8.0)
RAIN_RATES = (5.0, 10.0, 25.0, 50.0, 100.0)
RATED_RANGES = (12.5, 25.0, 50.0, 100.0, 200.0)
RATED_REFLECTIVITY = 0.1
SNOW_VELOCITY = 1.5
DIVERGENCE_RAD = 3e-3
PULSE_HALF_WIDTH_S = 10e-9
FIELD_SEED = 5
REFLECTIVITY = {"snow": 0.9, "rain": 0.02}

REAL_FIGURES: list[dict[str, Any]] = [
    {"medium": "snow", "rate_mm_h": None, "share_min": 0.0469, "share_max": 0.0838, "share_mean": 0.0668,
     "range_median_m": 6.55, "range_p10_m": 4.47, "range_p90_m": 9.80, "min_range_m": 2.02,
     "intensity_zero_share": 0.9835, "source": "WADS seq. 36",
     "sensor": "64-beam spinning LiDAR, -24.9 to +14.8 deg, 2048 columns (model not stated)",
     "note": "Kurup & Bos 2021 (WADS, DSOR paper) labels as released; 50 consecutive frames redistributed by "
             "github.com/dut-mdmu/CRFOR (sequences/36), counted by us: label 110 'active falling snow' per frame "
             "after dropping exact duplicate points (40 % of the raw points; 4.8 % share with them); no snowfall "
             "rate is published for it"},
    {"medium": "snow", "rate_mm_h": None, "dror_box_snow_min": 26, "dror_box_snow_median": 416,
     "dror_box_snow_max": 1443, "source": "CADC", "sensor": "Velodyne VLP-32C (roof)",
     "note": "Pitropov et al. 2020 devkit (github.com/mpitropov/cadc_devkit, cadc_dataset_route_stats.csv): per drive, "
             "the points DROR removes from the first frame inside CADC_BOX (other/filter_pointcloud.py), 75 drives; "
             "a filter's count, not labels; no snowfall rate"},
]
"""Real labelled measurements placed on the figure (see ``docs/physics.md`` section 3.5)."""


@dataclass(frozen=True)
class StreetScene:
    """A spinning LiDAR over flat ground inside a ring of facades (see the module docstring)."""

    name: str
    elevations_deg: tuple[float, ...]
    columns: int
    height_m: float
    max_range_m: float
    ground_reflectivity: float = 0.1
    wall_reflectivity: float = 0.3
    wall_radius_m: float = 30.0
    wall_height_m: float = 6.0


@dataclass(frozen=True)
class SceneBeams:
    """The beams of a `StreetScene` for one intensity model: (B, 3) unit directions from the origin (3,) [m], (B,)
    target ranges [m] (``inf``: none) and clear intensities (0..255, 0 without target)."""

    origin: np.ndarray
    directions: np.ndarray
    target_range: np.ndarray
    intensity0: np.ndarray


def scenes() -> dict[str, StreetScene]:
    from weatheralign.data.rings import HDL32E_ELEVATIONS_DEG, HDL64E_ELEVATIONS_DEG

    return {"hdl32e": StreetScene("hdl32e", tuple(map(float, HDL32E_ELEVATIONS_DEG)), 1085, 1.84, 100.0),
            "hdl64": StreetScene("hdl64", tuple(map(float, HDL64E_ELEVATIONS_DEG)), 900, 1.95, 120.0)}


def sensors(max_range_m: float) -> dict[str, EchoSensor]:
    """The sensor variants of the module docstring for a scene's maximum range."""
    world, ref = lidar_model_from_params(LidarConfig()), ReferenceLidarConfig()
    out = {"world": EchoSensor(world.intensity, world.noise_floor, DIVERGENCE_RAD, 1.0, max_range_m,
                               world.floor_range_m),
           "world_constant_floor": EchoSensor(SYNTHETIC_INTENSITY, 0.5, DIVERGENCE_RAD, 1.0, max_range_m),
           "reference": EchoSensor(SYNTHETIC_INTENSITY, ref.noise_floor, DIVERGENCE_RAD, 1.0, max_range_m,
                                   ref.floor_range_m),
           "hahner_floor0.5": EchoSensor(HAHNER_INTENSITY, 0.5, DIVERGENCE_RAD, 1.0, max_range_m)}
    for rated in RATED_RANGES:
        out[f"raw_rated{rated:g}m"] = EchoSensor(rated_intensity(RATED_REFLECTIVITY, rated, 1.0), 1.0, DIVERGENCE_RAD,
                                                 1.0, max_range_m)
    return out


def street_beams(scene: StreetScene, sensor: EchoSensor) -> SceneBeams:
    """Every beam of ``scene`` with its target (ground or facade) and clear intensity under ``sensor``'s intensity
    model; targets under the floor or beyond the maximum range are left out of the clear scan (no target)."""
    el, az = np.meshgrid(np.deg2rad(np.asarray(scene.elevations_deg)),
                         np.linspace(-np.pi, np.pi, scene.columns, endpoint=False))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    horizontal = np.hypot(d[:, 0], d[:, 1])
    with np.errstate(divide="ignore"):
        r_ground = np.where(d[:, 2] < 0.0, scene.height_m / -d[:, 2], np.inf)
        r_wall = scene.wall_radius_m / horizontal
    wall_z = scene.height_m + r_wall * d[:, 2]
    hits_wall = (r_wall < r_ground) & (wall_z >= 0.0) & (wall_z <= scene.wall_height_m)
    r0 = np.where(hits_wall, r_wall, r_ground)
    rho_cos = np.where(hits_wall, scene.wall_reflectivity * horizontal, scene.ground_reflectivity * -d[:, 2])
    r0 = np.where(np.isfinite(r0) & (r0 <= scene.max_range_m), r0, np.inf)
    i0 = np.where(np.isfinite(r0), sensor.intensity.intensity(rho_cos, np.where(np.isfinite(r0), r0, 1.0)), 0.0)
    i0 = np.minimum(i0, 255.0)
    seen = i0 >= sensor.floor_at(np.where(np.isfinite(r0), r0, 1.0))
    return SceneBeams(np.array([0.0, 0.0, scene.height_m]), d, np.where(seen, r0, np.inf), np.where(seen, i0, 0.0))


def particle_field(medium: str, rate: float):
    from weatheralign.medium import ParticleField, RainSizeDistribution, SnowSizeDistribution, fall_velocity
    from weatheralign.medium.distributions import rain_field_fall_speed

    if medium == "snow":
        return ParticleField(FIELD_SEED, SnowSizeDistribution(rate, SNOW_VELOCITY),
                             velocity=fall_velocity(SNOW_VELOCITY), cell_size=2.0)
    return ParticleField(FIELD_SEED, RainSizeDistribution(rate), velocity=fall_velocity(rain_field_fall_speed(rate)),
                         cell_size=1.0)


def _share(scattered: float, clutter: float, lost: float, targets: int) -> float:
    points = targets - lost + clutter
    return (scattered + clutter) / points if points > 0 else 0.0


def _echo_shape(ranges: np.ndarray, intensities: np.ndarray, floor_at: Any) -> dict[str, Any]:
    """Range quantiles [m] of the weather echoes and the share of them reading under twice the floor at their range
    (``floor_at(ranges)``; labelled real snow reads at the floor: `REAL_FIGURES`)."""
    if len(ranges) == 0:
        return {"range_p10_m": None, "range_median_m": None, "range_p90_m": None, "near_floor_share": None}
    p10, p50, p90 = np.quantile(ranges, [0.1, 0.5, 0.9])
    return {"range_p10_m": float(p10), "range_median_m": float(p50), "range_p90_m": float(p90),
            "near_floor_share": float(np.mean(intensities < 2.0 * floor_at(ranges)))}


def _fast_counts(result: Any, origin: np.ndarray | None, floor_at: Any, clear_points: int) -> dict[str, Any]:
    """Scattered, clutter, lost and attenuated points of a `simulate_particles` result, the weather share of a scan
    of ``clear_points`` and the echoes' shape (ranges from ``origin`` [m], None: the output frame's origin,
    `_echo_shape`)."""
    from weatheralign.lidar.labels import WeatherLabel

    weather = result.labels == WeatherLabel.SCATTERED
    scattered = int((weather & (result.source_index >= 0)).sum())
    clutter = int((weather & (result.source_index < 0)).sum())
    lost = int(result.counts.get("LOST", 0))
    echoes = result.points[weather]
    return {"scattered": scattered, "clutter": clutter, "lost": lost,
            "attenuated": int((result.labels == WeatherLabel.ATTENUATED).sum()),
            "weather_share": _share(scattered, clutter, lost, clear_points),
            **_echo_shape(np.linalg.norm(echoes[:, :3] if origin is None else echoes[:, :3] - origin, axis=1),
                          echoes[:, 3], floor_at)}


def run_fast(scene: StreetScene, sensor: EchoSensor, beams: SceneBeams, medium: str, rate: float) -> dict[str, Any]:
    """The fast simulator (`simulate_particles`) on the scene's beams, noise-free detector."""
    from weatheralign.lidar.beams import Beams
    from weatheralign.lidar.particles import simulate_particles
    from weatheralign.sensors import LidarModel, PulseSensor

    n = len(beams.directions)
    has = np.isfinite(beams.target_range)
    lidar = LidarModel(elevations_deg=scene.elevations_deg, columns_per_ring=scene.columns, rotation_hz=10.0,
                       clockwise=True, start_azimuth_rad=math.pi, laser_step_s=0.0, divergence_rad=DIVERGENCE_RAD,
                       max_range_m=scene.max_range_m, min_range_m=sensor.min_range_m, noise_floor=sensor.noise_floor,
                       intensity_max=255.0, intensity=sensor.intensity,
                       pulse=PulseSensor(tau_h=PULSE_HALF_WIDTH_S, max_range=scene.max_range_m), origin="params",
                       intensity_noise_std=0.0, intensity_noise_rel=0.0, range_noise_std_m=0.0,
                       floor_range_m=sensor.floor_range_m)
    b = Beams(np.tile(beams.origin, (n, 1)), beams.directions, np.zeros(n),
              np.where(has, beams.target_range, scene.max_range_m), has, beams.intensity0, np.zeros(n, np.float32),
              np.where(has, np.cumsum(has) - 1, -1), DIVERGENCE_RAD, scene.max_range_m)
    t0, c0 = time.perf_counter(), time.process_time()
    result = simulate_particles(b, particle_field(medium, rate), lidar=lidar, reflectivity=REFLECTIVITY[medium],
                                intensity_max=255.0, faint_surfaces=False)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {**_fast_counts(result, beams.origin, sensor.floor_at, int(has.sum())), "seconds": seconds,
            "cpu_seconds": cpu}


def run_exact(scene: StreetScene, sensor: EchoSensor, beams: SceneBeams, medium: str, rate: float,
              sub_rays: int) -> dict[str, Any]:
    """The synthetic reference's exact process (`particle_returns` + `read_out`, noise-free detector) on the beams."""
    from weatheralign.reference.lidar_exact import Detector, ExactSensor, read_out
    from weatheralign.reference.lidar_particles_exact import FOG, PARTICLE, TARGET, particle_returns

    has = np.isfinite(beams.target_range)
    exact_sensor = ExactSensor(tau_h=PULSE_HALF_WIDTH_S, max_range=scene.max_range_m, min_range=sensor.min_range_m)
    t0, c0 = time.perf_counter(), time.process_time()
    returns = particle_returns(beams.origin, beams.directions, beams.target_range, beams.intensity0,
                               particle_field(medium, rate), 0.0, REFLECTIVITY[medium], exact_sensor,
                               noise_floor=sensor.noise_floor, divergence_rad=DIVERGENCE_RAD, sub_rays=sub_rays,
                               intensity_model=sensor.intensity, floor_range_m=sensor.floor_range_m)
    out = read_out(returns.returns, exact_sensor,
                   Detector(0.0, 0.0, sensor.noise_floor, 0.0, sensor.intensity, sensor.floor_range_m),
                   np.random.default_rng(0))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    weather = (out.source == PARTICLE) | (out.source == FOG)
    on_target = has[out.index]
    scattered = int((weather & on_target).sum())
    clutter = int((weather & ~on_target).sum())
    lost = int(has.sum()) - scattered - int(((out.source == TARGET) & on_target).sum())
    shape = _echo_shape(out.range[weather], out.intensity[weather], sensor.floor_at)
    return {"scattered": scattered, "clutter": clutter, "lost": lost,
            "weather_share": _share(scattered, clutter, lost, int(has.sum())), **shape, "seconds": seconds,
            "cpu_seconds": cpu}


def run_closed_form(sensor: EchoSensor, beams: SceneBeams, medium: str, rate: float) -> dict[str, Any]:
    """The closed form's expected scattered and clutter points (`expected_weather_points`)."""
    t0, c0 = time.perf_counter(), time.process_time()
    expected = expected_weather_points(beams.target_range, beams.intensity0, particle_field(medium, rate).distribution,
                                       REFLECTIVITY[medium], sensor)
    has = int(np.isfinite(beams.target_range).sum())
    return {**expected, "weather_share": _share(expected["scattered"], expected["clutter"], 0.0, has),
            "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}


def _rate_entries(scene: StreetScene, sensor_names: list[str], rates: dict[str, tuple[float, ...]],
                  exact: bool, sub_rays: int) -> list[dict[str, Any]]:
    entries = []
    table = sensors(scene.max_range_m)
    for sensor_name in sensor_names:
        sensor = table[sensor_name]
        beams = street_beams(scene, sensor)
        for medium, medium_rates in rates.items():
            for rate in medium_rates:
                entry = {"workload": f"{scene.name}_{sensor_name}_{medium}_{rate:g}mmh", "scene": scene.name,
                         "sensor": sensor_name, "noise_floor": sensor.noise_floor,
                         "floor_range_m": sensor.floor_range_m,
                         "intensity_model": vars(sensor.intensity), "medium": medium, "rate_mm_h": rate,
                         "targets": int(np.isfinite(beams.target_range).sum()),
                         "beams": int(len(beams.directions)),
                         "fast": run_fast(scene, sensor, beams, medium, rate),
                         "closed_form": run_closed_form(sensor, beams, medium, rate)}
                if exact:
                    entry["exact"] = run_exact(scene, sensor, beams, medium, rate, sub_rays)
                entries.append(entry)
                shares = "  ".join(f"{k} {entry[k]['weather_share']:.4f}" for k in ("fast", "exact", "closed_form")
                                   if k in entry)
                shares += f"  median range {entry['fast']['range_median_m'] or float('nan'):.1f} m"
                print(f"{entry['workload']:40s} {shares}", flush=True)
    return entries


def cloud_scans() -> dict[str, Any]:
    """The clouds the published simulators ran on: the synthetic world's first keyframe (HDL-32E, 34,267 points,
    rendered if ``data/world`` is absent) with its sensor, and the shared STF HDL-64 scan (109,431 points, when
    ``../shared`` is present) with the sensor the pipeline estimates for real data (`estimate_lidar_model`)."""
    import tempfile

    from benchmarks.bench_lidar_particles import _first_world_scan, _render_world
    from weatheralign.sensors import estimate_lidar_model

    if (WORLD_ROOT / "v1.0-mini" / "sample_data.json").is_file():
        scan, columns = _first_world_scan(WORLD_ROOT)
    else:
        with tempfile.TemporaryDirectory(prefix="bench_strength_") as tmp:
            scan, columns = _render_world(Path(tmp))
    clouds = {"world_hdl32e_35k": (scan, columns, lidar_model_from_params(LidarConfig()))}
    stf_root = REAL / "stf"
    if stf_root.is_dir():
        from weatheralign.data.stf import load_stf_frame

        stf = load_stf_frame(stf_root, STF_ID, camera_folder=None).lidar
        clouds["stf_hdl64_109k"] = (stf, None, estimate_lidar_model([stf]))
    return clouds


CADC_BOX = ((-4.0, 4.0), (-4.0, 4.0), (-3.0, 10.0))
"""The box around the car (LiDAR frame, m) in which the CADC devkit counts DROR's snow points."""


def dror_outliers(xyz: np.ndarray, radius_multiplier: float = 3.0, azimuth_angle_deg: float = 0.16,
                  min_neighbors: int = 3, min_search_radius: float = 0.04) -> int:
    """Points of (N, 3) ``xyz`` [m] inside `CADC_BOX` that DROR (Charron et al. 2018, with the CADC devkit's
    parameters) calls snow: fewer than ``min_neighbors`` of their nearest points within
    ``max(min_search_radius, radius_multiplier · azimuth_angle · horizontal range)``."""
    from scipy.spatial import cKDTree

    inside = np.ones(len(xyz), dtype=bool)
    for axis, (lo, hi) in enumerate(CADC_BOX):
        inside &= (xyz[:, axis] >= lo) & (xyz[:, axis] <= hi)
    box = np.asarray(xyz[inside], dtype=np.float64)
    if len(box) <= min_neighbors:
        return int(len(box))
    radius = np.maximum(min_search_radius, radius_multiplier * np.radians(azimuth_angle_deg)
                        * np.hypot(box[:, 0], box[:, 1]))
    distances, _ = cKDTree(box).query(box, k=min_neighbors + 1)
    neighbours = (distances[:, 1:] < radius[:, None]).sum(axis=1)
    return int((neighbours < min_neighbors).sum())


def run_cloud(name: str, scan: Any, columns: np.ndarray | None, lidar: Any, medium: str,
              rate: float) -> dict[str, Any]:
    """Our fast simulator on one of `cloud_scans` (as `simulate` runs it: beams without return reconstructed or
    from the stored firing columns, faint surfaces)."""
    from weatheralign.lidar.particles import simulate_particles

    fld = particle_field(medium, rate)
    t0, c0 = time.perf_counter(), time.process_time()
    result = simulate_particles(scan, fld, lidar=lidar, reflectivity=REFLECTIVITY[medium],
                                columns=columns if columns is not None else "auto")
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    dror = dror_outliers(result.points[:, :3]) - dror_outliers(scan.points[:, :3])
    counts = _fast_counts(result, None, lidar.floor_at, int(len(scan.points)))
    return {"workload": f"cloud_{name}_{medium}_{rate:g}mmh", "cloud": name, "medium": medium, "rate_mm_h": rate,
            "points": int(len(scan.points)), "noise_floor": float(lidar.noise_floor),
            "floor_range_m": lidar.floor_range_m,
            "intensity_model": vars(lidar.intensity),
            "fast": {**counts, "dror_box_snow": dror, "seconds": seconds, "cpu_seconds": cpu}}


SENSOR_STYLE = {"world": ("tab:blue", "world HDL-32E (raw-power floor: 10 % at 35 m)"),
                "world_constant_floor": ("tab:cyan", "earlier world sensor (constant floor 0.5)"),
                "reference": ("tab:green", "reference HDL-64 (raw floor, 10 % at 50 m)"),
                "hahner_floor0.5": ("tab:red", "Hahner's 1/r² intensity, floor 0.5 (rated 7 m)"),
                "raw_rated100m": ("tab:purple", "raw power, rated 100 m on 10 %")}


def _plain_log_axes(ax: Any) -> None:
    """Log axes labelled with plain numbers (1, 2, 5, 10, ...)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def _rate_panel(ax: Any, entries: list[dict], peers: list[dict], clouds: list[dict], scene: str, medium: str,
                cloud: str) -> None:
    for sensor, (color, label) in SENSOR_STYLE.items():
        rows = sorted((e for e in entries if e["scene"] == scene and e["medium"] == medium and e["sensor"] == sensor),
                      key=lambda e: e["rate_mm_h"])
        if not rows:
            continue
        x = [e["rate_mm_h"] for e in rows]
        ax.plot(x, [100 * e["closed_form"]["weather_share"] for e in rows], "-", color=color, lw=1.2, label=label)
        ax.plot(x, [100 * e["fast"]["weather_share"] for e in rows], "o", color=color, ms=4)
        if "exact" in rows[0]:
            ax.plot(x, [100 * e["exact"]["weather_share"] for e in rows], "s", color=color, ms=6, mfc="none")
    ours = sorted((c for c in clouds if c["cloud"] == cloud and c["medium"] == medium), key=lambda c: c["rate_mm_h"])
    if ours:
        ax.plot([c["rate_mm_h"] for c in ours], [100 * c["fast"]["weather_share"] for c in ours], "k+--", ms=8,
                lw=0.8, label="ours on the published code's cloud, that cloud's sensor (HDL-32E row: the world's "
                               "first keyframe; HDL-64 row: the STF scan)")
    theirs = sorted((p for p in peers if p.get("cloud") == cloud and p.get("medium") == medium),
                    key=lambda p: p["rate_mm_h"])
    if theirs:
        ax.plot([p["rate_mm_h"] for p in theirs], [100 * p["weather_share"] for p in theirs], "x:", color="0.3",
                ms=8, label="published code on the same cloud (snow: Hahner et al. 2022; rain: LISA)")
    for real in REAL_FIGURES:
        if real["medium"] == medium and "share_min" in real:
            ax.axhspan(100 * real["share_min"], 100 * real["share_max"], color="gold", alpha=0.35,
                       label=f"real labelled snow: {real['source']}, share per scan (rate unknown)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    _plain_log_axes(ax)
    ax.set_xlabel(f"{medium} rate [mm/h]")
    ax.set_ylabel("weather echoes [% of the scan's points]")
    ax.set_title(f"{medium}, {scene} street scene")
    ax.grid(True, which="both", alpha=0.3)


def _sensitivity_panel(ax: Any, entries: list[dict]) -> None:
    for scene, style in (("hdl32e", "-"), ("hdl64", "--")):
        for medium, rate, color in (("snow", 2.0, "tab:blue"), ("rain", 50.0, "tab:orange")):
            rows = sorted((e for e in entries if e["scene"] == scene and e["medium"] == medium and
                           e["rate_mm_h"] == rate and e["sensor"].startswith("raw_rated")),
                          key=lambda e: float(e["sensor"][9:-1]))
            x = [float(e["sensor"][9:-1]) for e in rows]
            per_beam = [1000.0 / e["beams"] for e in rows]
            ax.plot(x, [k * (e["closed_form"]["scattered"] + e["closed_form"]["clutter"])
                        for k, e in zip(per_beam, rows, strict=True)], style, color=color,
                    label=f"{medium} {rate:g} mm/h, {scene}")
            exact = [k * (e["exact"]["scattered"] + e["exact"]["clutter"]) for k, e in zip(per_beam, rows, strict=True)]
            ax.plot(x, exact, "s", color=color, mfc="none", ms=6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    _plain_log_axes(ax)
    ax.set_xlabel("sensor sensitivity: range [m] at which a 10 % target meets the floor")
    ax.set_ylabel("weather echoes per 1,000 beams")
    ax.set_title("strength against the detector floor (raw power)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)


def _range_panel(ax: Any, entries: list[dict], clouds: list[dict], peers: list[dict]) -> None:
    rows = []  # (label, median, p10 or None, p90, colour)
    for e in entries:
        if e["scene"] == "hdl64" and e["medium"] == "snow" and e["rate_mm_h"] == 2.0 and "exact" in e:
            ex = e["exact"]
            if ex.get("range_median_m") is not None:
                rows.append((f"HDL-64 scene, {e['sensor']}", ex["range_median_m"], ex["range_p10_m"],
                             ex["range_p90_m"], "k"))
    rows.sort(key=lambda row: row[1])
    for c in clouds:
        if c["medium"] == "snow" and c["rate_mm_h"] == 2.0 and c["fast"].get("range_median_m") is not None:
            f = c["fast"]
            rows.append((f"{c['cloud'].split('_')[0]} cloud, ours", f["range_median_m"], f["range_p10_m"],
                         f["range_p90_m"], "tab:blue"))
    for p in peers:
        if p.get("medium") == "snow" and p.get("rate_mm_h") == 2.0 and p.get("scattered_range_median_m"):
            rows.append((f"{p['cloud'].split('_')[0]} cloud, Hahner's code", p["scattered_range_median_m"], None,
                         p["scattered_range_p90_m"], "0.4"))
    for real in REAL_FIGURES:
        if real.get("range_median_m") is not None:
            rows.append((f"real: {real['source']}", real["range_median_m"], real["range_p10_m"],
                         real["range_p90_m"], "goldenrod"))
    for i, (_, median, p10, p90, colour) in enumerate(rows):
        low = 0.0 if p10 is None else median - p10
        ax.errorbar(median, i, xerr=[[low], [p90 - median]], fmt="D" if colour == "goldenrod" else "o", color=colour)
    ax.set_yticks(range(len(rows)), [row[0] for row in rows], fontsize=7)
    ax.set_xlabel("snow echo range [m]: median, 10th-90th percentile (Hahner's: median-90th)")
    ax.set_title("where the snow echoes are (2 mm/h; scene rows: exact process)")
    ax.grid(True, axis="x", alpha=0.3)


def draw_figure(result: dict[str, Any], path: Path) -> None:
    """One figure: weather share against rate (rows: the two scenes; columns: snow, rain), against the sensor's
    sensitivity, and the snow echoes' ranges beside the real ones."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    entries, peers, clouds = result["entries"], result["peers"], result["clouds"]
    fig, axes = plt.subplots(2, 3, figsize=(19, 11.5), gridspec_kw={"width_ratios": [1.0, 1.0, 1.25]})
    for row, (scene, cloud) in enumerate((("hdl32e", "world_hdl32e_35k"), ("hdl64", "stf_hdl64_109k"))):
        for col, medium in enumerate(("snow", "rain")):
            _rate_panel(axes[row, col], entries, peers, clouds, scene, medium, cloud)
    handles: dict[str, Any] = {}
    for ax in axes[:, :2].ravel():
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, handle)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=2, fontsize=8, frameon=False)
    _sensitivity_panel(axes[0, 2], entries)
    _range_panel(axes[1, 2], entries, clouds, peers)
    fig.suptitle("How strong is our snow and rain? Lines: closed form; dots: fast simulator; squares: exact "
                 "Monte-Carlo; crosses: published simulators; gold: real labelled scans", fontsize=11)
    fig.tight_layout(rect=(0, 0.09, 1, 0.97))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one rate per medium, no sensitivity sweep")
    parser.add_argument("--sub-rays", type=int, default=256, help="sub-rays per beam of the exact process")
    parser.add_argument("--peers", type=Path, default=None, help="published simulators' runs (JSON list)")
    parser.add_argument("--out", type=Path, default=REPORT)
    parser.add_argument("--figure", type=Path, default=FIGURE)
    parser.add_argument("--clouds-only", action="store_true",
                        help="rerun only the cloud workloads and merge them into --out")
    parser.add_argument("--sensors", nargs="+", default=None, metavar="NAME",
                        help="rerun only these sensors' street-scene entries (and the clouds), merged into --out")
    parser.add_argument("--replot", action="store_true",
                        help="only redraw the figure from --out (with --peers: store those peers first)")
    args = parser.parse_args(argv)
    if args.replot:
        result = json.loads(args.out.read_text())
        if args.peers is not None:
            result["peers"] = json.loads(args.peers.read_text())
            write_json(args.out, result, indent=2)
        draw_figure(result, args.figure)
        print(f"wrote {args.figure}")
        return result
    unknown = sorted(set(args.sensors or ()) - set(sensors(100.0)))
    if unknown:
        parser.error(f"--sensors: unknown {unknown}; expected some of {sorted(sensors(100.0))}")
    rates = ({"snow": (2.0,), "rain": (50.0,)} if args.quick else {"snow": SNOW_RATES, "rain": RAIN_RATES})
    entries = []
    chosen = (lambda names: names) if args.sensors is None else (lambda names: [n for n in names if n in args.sensors])
    for scene in ([] if args.clouds_only else scenes().values()):
        entries += _rate_entries(scene, chosen(["world", "world_constant_floor", "reference", "hahner_floor0.5",
                                                "raw_rated100m"]), rates, exact=True, sub_rays=args.sub_rays)
        if not args.quick:
            entries += _rate_entries(scene, chosen([f"raw_rated{r:g}m" for r in RATED_RANGES if r != 100.0]),
                                     {"snow": (2.0,), "rain": (50.0,)}, exact=True, sub_rays=args.sub_rays)
    clouds = []
    for name, (scan, columns, lidar) in cloud_scans().items():
        for medium, medium_rates in rates.items():
            for rate in medium_rates:
                clouds.append(run_cloud(name, scan, columns, lidar, medium, rate))
                print(f"{clouds[-1]['workload']:40s} fast {clouds[-1]['fast']['weather_share']:.4f}", flush=True)
    previous = json.loads(args.out.read_text()) if args.clouds_only or args.sensors is not None else {}
    if args.sensors is not None:  # the other sensors' entries as they were, these sensors' in their place
        entries = [e for e in previous.get("entries", []) if e["sensor"] not in args.sensors] + entries
    else:
        entries = previous.get("entries", entries)
    peers = json.loads(args.peers.read_text()) if args.peers is not None else previous.get("peers", [])
    result = {"entries": entries, "clouds": clouds, "peers": peers, "real": REAL_FIGURES,
              "settings": {"divergence_rad": DIVERGENCE_RAD, "pulse_half_width_s": PULSE_HALF_WIDTH_S,
                           "snow_velocity_m_s": SNOW_VELOCITY, "field_seed": FIELD_SEED,
                           "rated_reflectivity": RATED_REFLECTIVITY, "sub_rays": args.sub_rays}}
    write_json(args.out, result, indent=2)
    draw_figure(result, args.figure)
    print(f"wrote {args.out} and {args.figure}")
    return result


if __name__ == "__main__":
    main()
