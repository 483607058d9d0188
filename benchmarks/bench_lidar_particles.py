"""Snow and rain benchmark: `simulate_particles` on a 35k-point synthetic-world scan (a rendered HDL-32E sweep of
the synthetic world, moving ego) and on the real 109k-point Seeing Through Fog scan (when ``../shared`` is present).

Run from the repository root: ``.venv/bin/python -m benchmarks.bench_lidar_particles [--runs 7] [--quick]``.
Every workload runs in a fresh worker process (so ``peak_rss_mib`` is that workload's own peak, numba and numpy
included): one warm-up call (JIT, caches), then ``--runs`` timed calls of the whole ``simulate_particles(scan, field)``
(beams without return, shells, materialisation, matching, pulses); the median is reported, with the median process
CPU time of the same calls. Entries ``{workload, num_points, seconds_median, cpu_seconds_median, peak_rss_mib,
reference_seconds, ...}`` are merged into
``reports/benchmarks/lidar.json`` (other workloads' entries, e.g. fog's, are kept), each with the 1-minute load
average before and after it (other processes on the machine slow the timings down).

Workloads:
- ``snow_2mmh_keyframe_2sweeps_joint``, ``rain_50mmh_keyframe_2sweeps_joint``: the first sample's keyframe and its two
  sweeps (as `simulate` runs them) in one `simulate_particle_scans` run, against `simulate_particles` on each scan
  (``separate_*``), same field;
- ``snow_2mmh_35k`` (against Hahner's published code, `SNOW_REFERENCE_35K`), ``rain_50mmh_35k`` (against LISA,
  `RAIN_REFERENCE_25MMH`, timed at half our rate), the same on the 109k STF scan (snow against
  `SNOW_REFERENCE_120K`, Hahner's code on a 120k HDL-64 scan);
- growth with rate (snow 0.5/1/2/4 mm/h, rain 10/25/50/100 mm/h) and with points (the STF scan with 16/32/64 of its
  rings);
- the ratio threshold: 3e-4 … 3e-2 for snow and rain (counts, mean intensity change of the kept points).

Fields: snow falls at 1.5 m/s; rain at the default fall speed of its rate (the Marshall-Palmer median-volume drop's,
`rain_field_fall_speed`: 6.6 m/s at 50 mm/h), so the joint keyframe + sweeps workload shows why `simulate` runs fast
rain scan by scan (`weatheralign.simulate.observe.JOINT_DRIFT_MAX_M`).

The sensor (`_lidar`): an HDL-32E-like `LidarModel` (3 mrad divergence, τ_H = 10 ns, a constant detector floor 0.5 on
0..255, the world's 32 x 1085 firing grid) with each workload's maximum range and intensity model (the synthetic
world's for its scan, Hahner's raw ``1/r²`` for STF); beams without return come from the stored firing columns of the
synthetic scan and are reconstructed from the ring structure otherwise (STF, ring subsets).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import merge_entries, run_worker
from weatheralign.atomic import write_json
from weatheralign.data.frame import LidarScan

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "lidar.json"
STF_ROOT = REPO.parent / "shared" / "data" / "real" / "stf"
STF_ID = "2019-09-11_19-13-44_00960"
WORLD_ROOT = REPO / "data" / "world"

SNOW_REFERENCE_35K = 30.0  # Hahner et al. 2022 code per 35k-point scan, the middle of its timed runs
SNOW_REFERENCE_120K = 88.0  # ... and per 120k-point HDL-64 scan
RAIN_REFERENCE_25MMH = 4.2  # LISA per 35k-point scan at 25 mm/h, the middle of its timed runs
SNOW_VELOCITY = 1.5
DIVERGENCE_RAD = 3e-3
PULSE_HALF_WIDTH_S = 10e-9
NOISE_FLOOR = 0.5


# ------------------------------------------------------------------------------------------------------ scans


def _render_world(base: Path) -> tuple[LidarScan, np.ndarray]:
    """A tiny synthetic world (one rendered sample with its two preceding sweeps, small cameras) -> its first
    LIDAR_TOP keyframe scan and the per-point firing columns."""
    from weatheralign.config import params_from_dict
    from weatheralign.world.dataset import finalize, render_or_resume, sample_jobs

    params = params_from_dict({"paths": {"data": str(base), "reports": str(base / "reports")},
                               "tracking": {"enabled": False},
                               "world": {"num_train_scenes": 1, "num_val_scenes": 1, "samples_per_scene": 2,
                                         "sweeps_per_sample": 2, "camera": {"image_scale": 0.1}}})
    root = base / "world"
    results = [render_or_resume(spec, k, params.world, root)[0] for spec, k in sample_jobs(params.world)]
    finalize(params.world, root, results)
    return _first_world_scan(root, params.world.version)


def _first_world_scan(root: Path, version: str = "v1.0-mini") -> tuple[LidarScan, np.ndarray]:
    from weatheralign.data.nuscenes import load_lidar, open_nuscenes
    from weatheralign.lidar.beams import synthetic_columns

    nusc = open_nuscenes(root, version)
    scan = load_lidar(nusc, nusc.sample[0]["data"]["LIDAR_TOP"])
    cols = synthetic_columns(scan)
    if cols is None:
        raise RuntimeError(f"{root}: no per-point firing columns in the extras")
    return scan, cols


def _save_scan(path: Path, scan: LidarScan, columns: np.ndarray | None) -> None:
    arrays: dict[str, Any] = {"points": scan.points, "timestamp": np.float64(scan.timestamp),
                              "T_ego_lidar": scan.T_ego_lidar, "T_global_ego": scan.T_global_ego,
                              "intensity_max": np.float64(scan.intensity_max), "num_rings": np.int64(scan.num_rings)}
    for name in ("time_offsets", "pose_times", "poses"):
        if getattr(scan, name) is not None:
            arrays[name] = getattr(scan, name)
    if columns is not None:
        arrays["columns"] = columns
    np.savez(path, **arrays)


def _load_scan(path: str) -> tuple[LidarScan, np.ndarray | None]:
    z = np.load(path)
    opt = {k: z[k] for k in ("time_offsets", "pose_times", "poses") if k in z.files}
    scan = LidarScan(points=z["points"], timestamp=float(z["timestamp"]), T_ego_lidar=z["T_ego_lidar"],
                     T_global_ego=z["T_global_ego"], intensity_max=float(z["intensity_max"]),
                     num_rings=int(z["num_rings"]), **opt)
    return scan, (z["columns"] if "columns" in z.files else None)


def _ring_subset(scan: LidarScan, keep_rings: int) -> LidarScan:
    """The scan with ``keep_rings`` of its rings (every k-th): fewer beams with the sensor's ring structure."""
    from dataclasses import replace

    rings = scan.points[:, 4].astype(np.int64)
    step = max(1, scan.num_rings // keep_rings)
    sel = rings % step == 0
    return replace(scan, points=scan.points[sel], num_rings=keep_rings)


# ------------------------------------------------------------------------------------------------------ worker


def _field(spec: dict, t_ref: float):
    from weatheralign.medium import ParticleField, RainSizeDistribution, SnowSizeDistribution, fall_velocity
    from weatheralign.medium.distributions import rain_field_fall_speed

    if spec["medium"] == "snow":
        return ParticleField(spec.get("seed", 11), SnowSizeDistribution(spec["rate"], SNOW_VELOCITY),
                             velocity=fall_velocity(SNOW_VELOCITY), t_ref=t_ref, cell_size=2.0)
    return ParticleField(spec.get("seed", 11), RainSizeDistribution(spec["rate"]),
                         velocity=fall_velocity(rain_field_fall_speed(spec["rate"])), t_ref=t_ref, cell_size=1.0)


def _lidar(spec: dict, columns_stored: bool):
    """The workload's `LidarModel` (see the module docstring); ``columns_stored``: the scan comes with its per-point
    firing columns (else beams without return are reconstructed)."""
    from weatheralign.config import LidarConfig
    from weatheralign.sensors import HAHNER_INTENSITY, SYNTHETIC_INTENSITY, lidar_model_from_params, with_overrides

    model = {"synthetic": SYNTHETIC_INTENSITY, "hahner": HAHNER_INTENSITY}[spec["intensity_model"]]
    return with_overrides(lidar_model_from_params(LidarConfig(floor_range_m=None)), {
        "max_range_m": float(spec["max_range"]), "divergence_rad": DIVERGENCE_RAD, "noise_floor": NOISE_FLOOR,
        "pulse_half_width_s": PULSE_HALF_WIDTH_S, "intensity": model, "firing_columns_stored": columns_stored})


def _keyframe_and_sweeps(dataroot: str, version: str, sweeps: int) -> list[LidarScan]:
    """The first sample's LIDAR_TOP keyframe scan and the ``sweeps`` sweeps before it (newest first), read from the
    dataroot (so that their stored firing columns are found)."""
    from weatheralign.data.nuscenes import load_lidar, open_nuscenes

    nusc = open_nuscenes(dataroot, version)
    sd = nusc.get("sample_data", nusc.sample[0]["data"]["LIDAR_TOP"])
    scans = [load_lidar(nusc, sd["token"])]
    while len(scans) <= sweeps and sd["prev"]:
        sd = nusc.get("sample_data", sd["prev"])
        scans.append(load_lidar(nusc, sd["token"]))
    if len(scans) <= sweeps:
        raise RuntimeError(f"{dataroot}: the first sample has {len(scans) - 1} sweeps before it, {sweeps} needed")
    return scans


def _joint_worker(spec: dict) -> dict:
    """A keyframe and its sweeps: `simulate_particle_scans` (one run) against `simulate_particles` per scan."""
    from weatheralign.lidar.particles import (
        RAIN_REFLECTIVITY,
        SNOW_REFLECTIVITY,
        simulate_particle_scans,
        simulate_particles,
    )

    scans = _keyframe_and_sweeps(spec["dataroot"], spec["version"], spec["sweeps"])
    fld = _field(spec, scans[0].timestamp)
    kwargs = dict(lidar=_lidar(spec, True), reflectivity=SNOW_REFLECTIVITY if spec["medium"] == "snow"
                  else RAIN_REFLECTIVITY, ratio_threshold=spec.get("ratio_threshold"))
    joint = simulate_particle_scans(scans, fld, **kwargs)  # warm-up
    seconds, cpu_seconds, sep_seconds, sep_cpu = [], [], [], []
    for _ in range(spec["runs"]):
        t0, c0 = time.perf_counter(), time.process_time()
        joint = simulate_particle_scans(scans, fld, **kwargs)
        seconds.append(time.perf_counter() - t0)
        cpu_seconds.append(time.process_time() - c0)
        t0, c0 = time.perf_counter(), time.process_time()
        alone = [simulate_particles(scan, fld, **kwargs) for scan in scans]
        sep_seconds.append(time.perf_counter() - t0)
        sep_cpu.append(time.process_time() - c0)
    return {
        "num_points": int(sum(len(s.points) for s in scans)),
        "num_beams": int(sum(r.stats["num_beams"] for r in joint)),
        "seconds": seconds, "cpu_seconds": cpu_seconds,
        "separate_seconds": sep_seconds, "separate_cpu_seconds": sep_cpu,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "counts": {k: sum(r.counts[k] for r in joint) for k in joint[0].counts},
        "separate_counts": {k: sum(r.counts[k] for r in alone) for k in alone[0].counts},
        "particles_materialized": int(joint[0].stats["particles"]),
        "separate_particles_materialized": int(sum(r.stats["particles"] for r in alone)),
        "resolved_hits": int(sum(len(r.hits) for r in joint)),
        "ratio_threshold": float(joint[0].stats["ratio_threshold"]),
        "mean_intensity_ratio_kept": None, "fraction_kept_dropped_10pct": None,
    }


def _worker(spec: dict) -> dict:
    """Run one workload in this process and return its measurements."""
    from weatheralign.lidar.particles import RAIN_REFLECTIVITY, SNOW_REFLECTIVITY, simulate_particles

    if "sweeps" in spec:
        return _joint_worker(spec)

    scan, columns = _load_scan(spec["scan"])
    if spec.get("rings"):
        scan = _ring_subset(scan, spec["rings"])
        columns = None
    fld = _field(spec, scan.timestamp)
    kwargs = dict(lidar=_lidar(spec, columns is not None),
                  reflectivity=SNOW_REFLECTIVITY if spec["medium"] == "snow" else RAIN_REFLECTIVITY,
                  ratio_threshold=spec.get("ratio_threshold"), columns=columns if columns is not None else "auto")
    result = simulate_particles(scan, fld, **kwargs)  # warm-up: JIT (cached on disk), page faults
    seconds, cpu_seconds = [], []
    for _ in range(spec["runs"]):
        t0, c0 = time.perf_counter(), time.process_time()
        result = simulate_particles(scan, fld, **kwargs)
        seconds.append(time.perf_counter() - t0)
        cpu_seconds.append(time.process_time() - c0)
    i0 = scan.points[:, 3].astype(np.float64)
    out_i = np.full(len(i0), np.nan)
    kept = result.source_index >= 0
    out_i[result.source_index[kept]] = result.points[kept, 3]
    stay = (result.input_labels <= 1) & (i0 > 0)
    ratio = out_i[stay] / i0[stay]
    return {
        "num_points": int(len(scan.points)),
        "num_beams": int(result.stats["num_beams"]),
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "counts": result.counts,
        "particles_materialized": int(result.stats["particles"]),
        "resolved_hits": int(len(result.hits)),
        "ratio_threshold": float(result.stats["ratio_threshold"]),
        "mean_intensity_ratio_kept": float(ratio.mean()) if len(ratio) else None,
        "fraction_kept_dropped_10pct": float(np.mean(ratio < 0.9)) if len(ratio) else None,
    }




# ------------------------------------------------------------------------------------------------------ main




def _specs(world_npz: Path, stf_npz: Path | None, runs: int, quick: bool, world: tuple[str, str]) -> list[dict]:
    base_w = {"scan": str(world_npz), "max_range": 100.0, "intensity_model": "synthetic", "runs": runs}
    base_j = {"dataroot": world[0], "version": world[1], "sweeps": 2, "max_range": 100.0,
              "intensity_model": "synthetic", "runs": runs, "reference_seconds": None}
    specs = [
        {**base_j, "workload": "snow_2mmh_keyframe_2sweeps_joint", "medium": "snow", "rate": 2.0,
         "note": "a keyframe and its 2 sweeps in one simulate_particle_scans run; separate_*: simulate_particles "
                 "on each scan"},
        {**base_j, "workload": "rain_50mmh_keyframe_2sweeps_joint", "medium": "rain", "rate": 50.0,
         "note": "as the snow workload"},
        {**base_w, "workload": "snow_2mmh_35k", "medium": "snow", "rate": 2.0, "reference_seconds": SNOW_REFERENCE_35K,
         "source": "synthetic world, HDL-32E sweep (32 x 1085 beams incl. no-return), ego moving"},
        {**base_w, "workload": "rain_50mmh_35k", "medium": "rain", "rate": 50.0,
         "reference_seconds": RAIN_REFERENCE_25MMH,
         "note": "reference (LISA) is at 25 mm/h; default (auto) ratio threshold: 1e-2 for rain"},
        {**base_w, "workload": "rain_50mmh_35k_tau1e-3", "medium": "rain", "rate": 50.0, "ratio_threshold": 1e-3,
         "reference_seconds": RAIN_REFERENCE_25MMH, "note": "ratio threshold forced to snow's 1e-3"},
    ]
    if stf_npz is not None:
        base_s = {"scan": str(stf_npz), "max_range": 120.0, "intensity_model": "hahner", "runs": runs}
        specs += [
            {**base_s, "workload": "snow_2mmh_stf_hdl64_109k", "medium": "snow", "rate": 2.0,
             "reference_seconds": SNOW_REFERENCE_120K, "note": "reference measured on a 120k HDL-64 scan"},
            {**base_s, "workload": "rain_50mmh_stf_hdl64_109k", "medium": "rain", "rate": 50.0,
             "reference_seconds": None},
        ]
    if quick:
        return specs
    growth_runs = max(5, runs // 2)
    for rate in (0.5, 1.0, 2.0, 4.0):
        specs.append({**base_w, "runs": growth_runs, "workload": f"growth_snow_{rate:g}mmh_35k", "medium": "snow",
                      "rate": rate, "reference_seconds": SNOW_REFERENCE_35K if rate == 2.0 else None})
    for rate in (10.0, 25.0, 50.0, 100.0):
        specs.append({**base_w, "runs": growth_runs, "workload": f"growth_rain_{rate:g}mmh_35k", "medium": "rain",
                      "rate": rate, "reference_seconds": RAIN_REFERENCE_25MMH if rate == 25.0 else None})
    if stf_npz is not None:
        for rings in (16, 32):
            specs.append({"scan": str(stf_npz), "max_range": 120.0, "intensity_model": "hahner", "runs": growth_runs,
                          "workload": f"growth_snow_2mmh_stf_{rings}rings", "medium": "snow", "rate": 2.0,
                          "rings": rings, "reference_seconds": None})
    for medium, rate in (("snow", 2.0), ("rain", 50.0)):
        for tau in (3e-4, 1e-3, 3e-3, 1e-2, 3e-2):
            specs.append({**base_w, "runs": 5, "workload": f"threshold_{medium}_{tau:g}_35k", "medium": medium,
                          "rate": rate, "ratio_threshold": tau, "reference_seconds": None})
    return specs


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="timed runs per main workload (median, >= 5)")
    parser.add_argument("--quick", action="store_true", help="only the main workloads")
    parser.add_argument("--only", type=str, default=None,
                        help="comma-separated substrings: run only the workloads whose name contains one")
    parser.add_argument("--out", type=Path, default=REPORT)
    parser.add_argument("--worker", type=str, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        print(json.dumps(_worker(json.loads(args.worker))))
        return []
    runs = max(args.runs, 5)
    entries = []
    with tempfile.TemporaryDirectory(prefix="bench_particles_") as tmp:
        tmp_path = Path(tmp)
        if (WORLD_ROOT / "v1.0-mini" / "sample_data.json").is_file():
            scan, cols = _first_world_scan(WORLD_ROOT)
            world = (str(WORLD_ROOT), "v1.0-mini")
        else:
            scan, cols = _render_world(tmp_path / "render")
            world = (str(tmp_path / "render" / "world"), "v1.0-mini")
        world_npz = tmp_path / "world.npz"
        _save_scan(world_npz, scan, cols)
        stf_npz = None
        if STF_ROOT.is_dir():
            from weatheralign.data.stf import load_stf_frame

            stf_npz = tmp_path / "stf.npz"
            _save_scan(stf_npz, load_stf_frame(STF_ROOT, STF_ID, camera_folder=None).lidar, None)
        specs = _specs(world_npz, stf_npz, runs, args.quick, world)
        if args.only:
            keys = [k for k in args.only.split(",") if k]
            specs = [sp for sp in specs if any(k in sp["workload"] for k in keys)]
        for spec in specs:
            load_before = os.getloadavg()[0]
            m = run_worker("benchmarks.bench_lidar_particles", spec)
            median = statistics.median(m["seconds"])
            ref = spec.get("reference_seconds")
            entry = {"workload": spec["workload"], "num_points": m["num_points"], "seconds_median": median,
                     "cpu_seconds_median": statistics.median(m["cpu_seconds"]),
                     "peak_rss_mib": m["peak_rss_mib"], "reference_seconds": ref,
                     "speedup": None if ref is None else ref / median, "seconds_min": min(m["seconds"]),
                     "runs": len(m["seconds"]), "medium": spec["medium"], "rate_mm_h": spec["rate"],
                     **{k: m[k] for k in ("num_beams", "counts", "particles_materialized", "resolved_hits",
                                          "ratio_threshold", "mean_intensity_ratio_kept",
                                          "fraction_kept_dropped_10pct")},
                     "intensity_model": spec["intensity_model"],
                     "load_avg_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)]}
            for key in ("source", "note", "rings", "sweeps"):
                if key in spec:
                    entry[key] = spec[key]
            if "separate_seconds" in m:
                entry.update({"separate_seconds_median": statistics.median(m["separate_seconds"]),
                              "separate_cpu_seconds_median": statistics.median(m["separate_cpu_seconds"]),
                              "separate_counts": m["separate_counts"],
                              "separate_particles_materialized": m["separate_particles_materialized"]})
            entries.append(entry)
            speed = "" if ref is None else f" ({ref / median:5.0f}x vs {ref} s)"
            print(f"{entry['workload']:34s} {entry['num_points']:7d} pts  median {median:6.3f} s "
                  f"(cpu {entry['cpu_seconds_median']:6.3f} s){speed}  "
                  f"peak {entry['peak_rss_mib']:5.0f} MiB  tau {entry['ratio_threshold']:.0e}  "
                  f"particles {entry['particles_materialized']:9d}  {entry['counts']}", flush=True)
    write_json(args.out, merge_entries(args.out, entries), indent=2)
    print(f"wrote {args.out}")
    return entries


if __name__ == "__main__":
    main()
