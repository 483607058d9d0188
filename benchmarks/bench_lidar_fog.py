"""Fog benchmark: `simulate_fog` at α = 0.06 on a 35k-point nuScenes-like scan and on the real 109k-point Seeing
Through Fog scan (when ``../shared`` is present).

Run from the repository root: ``.venv/bin/python -m benchmarks.bench_lidar_fog [--runs 50]``. Writes (merging with
other workloads already there) ``reports/benchmarks/lidar.json``: a list of entries ``{workload, num_points,
seconds_median, peak_rss_mib, reference_seconds, ...}`` where ``reference_seconds`` is the published implementation's
time on the same machine (Hahner's per-point Python loop, `REFERENCE_SECONDS`).
Both workloads run through `FOG_LIDAR`: the synthetic HDL-32E with the fog model's pulse (τ_H = 20 ns,
`PulseSensor()`) and no detector floor, as in Hahner's fog code.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.common import merge_entries
from weatheralign.atomic import write_json
from weatheralign.config import LidarConfig
from weatheralign.data.frame import LidarScan
from weatheralign.data.rings import HDL32E_ELEVATIONS_DEG
from weatheralign.lidar.fog import FogResult, simulate_fog
from weatheralign.medium.fog import default_beta
from weatheralign.sensors import PulseSensor, lidar_model_from_params, with_overrides

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "lidar.json"
STF_ROOT = REPO.parent / "shared" / "data" / "real" / "stf"
STF_ID = "2019-09-11_19-13-44_00960"
WORLD_ROOT = REPO / "data" / "world"
ALPHA = 0.06
REFERENCE_SECONDS = {"fog_nuscenes_like_35k": 0.37, "fog_stf_hdl64_109k": 1.2}

SENSOR_HEIGHT_M = 1.84
SWEEP_S = 0.05
EGO_SPEED_M_S = 10.0
FOG_PULSE = PulseSensor()
FOG_LIDAR = with_overrides(lidar_model_from_params(LidarConfig(max_range_m=FOG_PULSE.max_range)),
                           {"pulse_half_width_s": FOG_PULSE.tau_h, "noise_floor": 0.0})
"""The benchmark's sensor: the fog model's pulse (τ_H = 20 ns, 120 m) and a zero detector floor (every return
kept, intensities being >= 0): what `simulate_fog` used by default before the sensor became explicit."""


def street_scan(seed: int = 0, rings: int = 32, columns: int = 1085) -> LidarScan:
    """A nuScenes-like HDL-32E sweep (rings x columns points, every beam returns) of a straight street.

    Geometry per beam (sensor 1.84 m above a flat road): the road for downward beams, façades 5-14 m to each side
    (piecewise per 10 m block) up to 6-25 m high, parked cars / poles / pedestrians on ~12 % of beams at 3-40 m, and
    trees or distant buildings at 40-100 m for beams above the façades or along the street. Intensities (0..255) are
    lognormal per material. Firing times cover a 50 ms clockwise sweep and the ego drives at 10 m/s, so every beam has
    its own origin (``time_offsets``, ``poses``).
    """
    rng = np.random.default_rng(seed)
    el = np.radians(np.repeat(HDL32E_ELEVATIONS_DEG, columns))
    az = np.tile(np.linspace(np.pi, -np.pi, columns, endpoint=False), rings)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    n = len(d)
    r = np.full(n, np.inf)
    material = np.zeros(n, dtype=np.int64)  # 0 road, 1 facade, 2 object, 3 far
    down = d[:, 2] < -1e-6
    r[down] = SENSOR_HEIGHT_M / -d[down, 2]
    side = np.abs(d[:, 1]) > 1e-6
    blocks = rng.uniform(5.0, 14.0, size=(2, 40))
    heights = rng.uniform(6.0, 25.0, size=(2, 40))
    left = (d[:, 1] > 0).astype(np.int64)
    for _ in range(2):  # iterate once to pick the block of the provisional hit
        along = np.abs(np.where(np.isfinite(r), r, 0.0) * d[:, 0])
        half = np.clip(along // 10.0, 0, 39).astype(np.int64)
        width = blocks[left, half]
        r_wall = np.where(side, width / np.maximum(np.abs(d[:, 1]), 1e-9), np.inf)
        z_wall = SENSOR_HEIGHT_M + r_wall * d[:, 2]
        wall = side & (r_wall < r) & (z_wall < heights[left, half]) & (z_wall > 0)
        r = np.where(wall, r_wall, r)
        material = np.where(wall, 1, material)
    obj = rng.random(n) < 0.12
    r_obj = rng.uniform(3.0, 40.0, n)
    take = obj & (r_obj < r)
    r[take] = r_obj[take]
    material[take] = 2
    far = ~np.isfinite(r) | (r > 100.0)
    r[far] = rng.uniform(40.0, 100.0, int(far.sum()))
    material[far] = 3
    r = r + rng.normal(0.0, 0.01, n)
    mu = np.array([2.3, 3.4, 3.6, 2.8])[material]
    intensity = np.clip(rng.lognormal(mu, 0.6), 0.0, 255.0)
    points = np.empty((n, 5), dtype=np.float32)
    points[:, :3] = d * r[:, None]
    points[:, 3] = intensity
    points[:, 4] = np.repeat(np.arange(rings), columns)
    column = np.tile(np.arange(columns), rings)
    time_offsets = (-(columns - 1 - column) / columns * SWEEP_S).astype(np.float32)
    T_ego_lidar = np.eye(4)
    T_ego_lidar[:3, 3] = (0.94, 0.0, SENSOR_HEIGHT_M)
    pose_times = np.array([-SWEEP_S, -SWEEP_S / 2, 0.0]) + 100.0
    poses = np.stack([np.eye(4)] * 3)
    for k, t in enumerate(pose_times - pose_times[-1]):
        poses[k, :3, :3] = Rotation.from_euler("z", 0.2 * t).as_matrix()
        poses[k, 0, 3] = EGO_SPEED_M_S * t
    return LidarScan(points=points, timestamp=float(pose_times[-1]), T_ego_lidar=T_ego_lidar,
                     T_global_ego=poses[-1], time_offsets=time_offsets, pose_times=pose_times, poses=poses)


def world_scan() -> LidarScan | None:
    """The first LIDAR_TOP keyframe of the synthetic world in ``data/world``, or None if there is none."""
    if not (WORLD_ROOT / "v1.0-mini" / "sample_data.json").is_file():
        return None
    from weatheralign.data.nuscenes import load_lidar, open_nuscenes

    nusc = open_nuscenes(WORLD_ROOT, "v1.0-mini")
    sample = nusc.sample[0]
    return load_lidar(nusc, sample["data"]["LIDAR_TOP"])


def stf_scan() -> LidarScan | None:
    """The real 109k-point Seeing Through Fog HDL-64 scan, or None when ``../shared`` is absent."""
    if not STF_ROOT.is_dir():
        return None
    from weatheralign.data.stf import load_stf_frame

    return load_stf_frame(STF_ROOT, STF_ID, camera_folder=None).lidar


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far [MiB] (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def time_runs(fn: Callable[[], Any], runs: int) -> list[float]:
    """Wall-clock seconds of ``runs`` calls of ``fn`` after one warm-up call (JIT, caches)."""
    fn()
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def bench(workload: str, scan: LidarScan, runs: int, source: str) -> dict[str, Any]:
    """One report entry for ``simulate_fog(scan, 0.06, 0.046 / MOR)``."""
    beta = default_beta(ALPHA)
    result: FogResult = simulate_fog(scan, ALPHA, beta, lidar=FOG_LIDAR)
    seconds = time_runs(lambda: simulate_fog(scan, ALPHA, beta, lidar=FOG_LIDAR), runs)
    median = statistics.median(seconds)
    reference = REFERENCE_SECONDS.get(workload)
    return {
        "workload": workload,
        "num_points": int(len(scan.points)),
        "seconds_median": median,
        "seconds_min": min(seconds),
        "runs": runs,
        "peak_rss_mib": peak_rss_mib(),
        "reference_seconds": reference,
        "speedup": None if reference is None else reference / median,
        "alpha": ALPHA,
        "beta": beta,
        "counts": result.counts,
        "source": source,
    }




def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=50, help="timed runs per workload (median reported, >= 20)")
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    runs = max(args.runs, 20)
    entries = []
    world = world_scan()
    if world is not None:
        entries.append(bench("fog_nuscenes_like_35k", world, runs, f"synthetic world {WORLD_ROOT}"))
    else:
        entries.append(bench("fog_nuscenes_like_35k", street_scan(seed=0), runs,
                             "street_scan(seed=0): 32 rings x 1085 columns, moving ego"))
    stf = stf_scan()
    if stf is not None:
        entries.append(bench("fog_stf_hdl64_109k", stf, runs, f"{STF_ROOT}/{STF_ID}"))
    for e in entries:
        print(f"{e['workload']:24s} {e['num_points']:7d} pts  median {e['seconds_median'] * 1e3:7.2f} ms  "
              f"(reference {e['reference_seconds']} s, {e['speedup']:.0f}x)  peak RSS {e['peak_rss_mib']:.0f} MiB  "
              f"{e['counts']}")
    write_json(args.out, merge_entries(args.out, entries), indent=2)
    print(f"wrote {args.out}")
    return entries


if __name__ == "__main__":
    main()
