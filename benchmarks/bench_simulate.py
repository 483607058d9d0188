"""Whole-stage benchmark: the `simulate` flow on the default world, per condition, on this machine.

Run from the repository root after ``dvc repro media`` (world, fields, fog calibration, every condition's media):
``.venv/bin/python -m benchmarks.bench_simulate [--conditions snow-aligned ...]`` (default: every condition of
`weatheralign.conditions.CONDITIONS`, aligned and unaligned).

Each condition runs ``python -m flows.simulate`` as DVC would (Prefect flow on a local Dask cluster), writing
into a scratch folder (``--scratch``, default ``/tmp/weatheralign-bench-simulate``) that links the real world's
manifest and the media, so ``data/simulate`` is left alone; the scratch copy is deleted after each condition. Reported
per condition: wall seconds of the whole command (Python and Prefect start-up included), samples per minute, and the
stage's own counts and re-projection figures; plus the total over the conditions run (target: all ten <= 20 min for ~400
samples on 2 cores). ``--from-reports`` collects the same figures from the last ``dvc repro`` instead (no rerun). The
peer figure for LiDAR snow is MultiCorrupt: 12 h for nuScenes on 32 CPUs. With ``../shared/data/real`` present, the
re-projection check is also run on the real STF and KITTI frames (dense depth from their scans). Results go to
``reports/benchmarks/simulate.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import merge_entries, real_frames
from weatheralign.atomic import write_json
from weatheralign.conditions import ALIGNMENTS, CONDITIONS, variant_name

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "simulate.json"
ALL = [variant_name(c, a == ALIGNMENTS[0]) for c in CONDITIONS for a in ALIGNMENTS]
TARGET_ALL_SECONDS = 20 * 60
MULTICORRUPT = "MultiCorrupt: 12 h of LiDAR snow for nuScenes (34,149 samples) on 32 CPUs"


def _scratch(scratch: Path) -> tuple[Path, Path]:
    """(data, reports) folders in ``scratch`` with the real world's manifest (absolute dataroot) and the media."""
    data, reports = scratch / "data", scratch / "reports"
    shutil.rmtree(scratch, ignore_errors=True)
    (data / "manifests").mkdir(parents=True)
    reports.mkdir(parents=True)
    (data / "media").symlink_to(REPO / "data" / "media")
    world = json.loads((REPO / "data" / "manifests" / "world.json").read_text())
    world["dataroot"] = str((REPO / world["dataroot"]).resolve())
    (data / "manifests" / "world.json").write_text(json.dumps(world))
    return data, reports


def own_bytes(root: Path) -> int:
    """Bytes of the files under ``root`` that are not hard links shared with another dataset (what the copy costs)."""
    return sum(st.st_size for p in root.rglob("*") if p.is_file() and (st := p.stat()).st_nlink == 1)


def run_condition(name: str, scratch: Path, extra: list[str] | None = None) -> dict[str, Any]:
    """``python -m flows.simulate`` for the variant ``name`` into ``scratch`` (``extra``: more ``--set`` args)."""
    condition, alignment = name.rsplit("-", 1)
    data, reports = _scratch(scratch)
    cmd = [sys.executable, "-m", "flows.simulate", "--set", f"simulate.condition={condition}",
           "--set", f"simulate.aligned={alignment}", "--set", f"paths.data={data}", "--set", f"paths.reports={reports}",
           "--set", "tracking.enabled=false", "--set", "run.show_progress=false", *(extra or [])]
    t0, c0 = time.perf_counter(), os.times()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env={**os.environ}, check=False)
    wall, c1 = time.perf_counter() - t0, os.times()
    if proc.returncode != 0:
        raise RuntimeError(f"simulate {name} failed:\n{proc.stderr[-4000:]}")
    m = json.loads((reports / "simulate" / name / "details.json").read_text())
    m["own_bytes"] = own_bytes(data / "simulate" / name)
    shutil.rmtree(scratch, ignore_errors=True)
    entry = entry_from_metrics(name, m, wall)
    entry["cpu_seconds_command"] = (c1.children_user + c1.children_system) - (c0.children_user + c0.children_system)
    return entry


def entry_from_metrics(name: str, m: dict[str, Any], wall: float | None) -> dict[str, Any]:
    """One condition's benchmark entry from its stage metrics (``wall``: the whole command's seconds, if timed)."""
    n = m["num_samples"]
    return {"workload": f"simulate_{name}", "num_samples": n, "sweeps_simulated": m.get("sweeps_simulated"),
            "wall_seconds": wall, "samples_per_minute": 60.0 * n / wall if wall else None,
            "seconds_per_sample": m["seconds_per_sample"], "cpu_seconds_per_sample": m.get("cpu_seconds_per_sample"),
            "bytes_per_sample": m.get("bytes_written_per_sample"), "copy_own_bytes": m.get("own_bytes"),
            "points_scattered": m["points_scattered"], "points_lost": m["points_lost"],
            "particles_rendered": m["particles_rendered"], "reprojection_mean_px": m["reprojection_mean_px"],
            "reprojection_max_px": m["reprojection_max_px"], "reprojection_pairs": m["reprojection_pairs"],
            "cores": os.cpu_count(), "reference": MULTICORRUPT if name.startswith("snow") else None}


def from_reports() -> list[dict[str, Any]]:
    """Entries of the last ``dvc repro`` (``reports/simulate/*/details.json``, the copies under ``data/simulate``):
    per-sample seconds as the stage measured them, the stage's wall time from its samples and rate."""
    entries = []
    for name in ALL:
        path = REPO / "reports" / "simulate" / name / "details.json"
        if not path.is_file():
            continue
        m = json.loads(path.read_text())
        copy = REPO / "data" / "simulate" / name
        m["own_bytes"] = own_bytes(copy) if copy.is_dir() else None
        rate = m.get("wall_seconds_per_sample_this_run")
        entries.append(entry_from_metrics(name, m, rate * m["num_samples"] if rate else None))
    return entries


def real_reprojection() -> list[dict[str, Any]]:
    """Snow through the real STF and KITTI frames, aligned and unaligned: re-projection figures (the LiDAR model
    estimated from the frame's scan, dense depth from it)."""
    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.fog import estimate_airlight
    from weatheralign.config import params_from_dict
    from weatheralign.medium.conditions import field_spec
    from weatheralign.sensors import SensorRig, camera_models, estimate_lidar_model
    from weatheralign.simulate.media import SceneMedia
    from weatheralign.simulate.observe import ObserveOptions, observe

    params = params_from_dict({})
    out = []
    for name, load in real_frames().items():
        frame = load()
        spec = field_spec(params.particles, "snow", f"real-{name}", frame.lidar.timestamp)
        sensors = SensorRig(estimate_lidar_model([frame.lidar], rotation_hz=10.0),
                            camera_models(frame.cameras, params.world.camera.exposure_s))
        images = {ch: v.load_image() for ch, v in frame.cameras.items()}
        ranges = {ch: camera_range_map(v, frame.lidar, images[ch]) for ch, v in frame.cameras.items()}
        airlight = estimate_airlight(list(images.values()), list(ranges.values()))
        for aligned in (True, False):
            t0 = time.perf_counter()
            media = SceneMedia(CONDITIONS["snow"], aligned, f"real-{name}", field=spec)
            fw = observe(frame, images, ranges, media, sensors, airlight, ObserveOptions(threads=2))
            e = fw.reprojection_px
            out.append({"workload": f"reprojection_real_{name}_snow_{'aligned' if aligned else 'unaligned'}",
                        "reprojection_pairs": int(e.size), "reprojection_mean_px": float(e.mean()),
                        "reprojection_max_px": float(e.max()), "points_scattered": fw.lidar.counts["SCATTERED"],
                        "particles_rendered": fw.particles_rendered, "seconds": time.perf_counter() - t0,
                        "depth": "dense depth from the frame's own scan (no exact range map)"})
    return out


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--conditions", nargs="*", default=ALL, choices=ALL)
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/weatheralign-bench-simulate"))
    parser.add_argument("--out", type=Path, default=REPORT)
    parser.add_argument("--from-reports", action="store_true",
                        help="collect the figures of the last dvc repro instead of running the stage again")
    args = parser.parse_args(argv)
    if args.from_reports:
        entries = from_reports()
        for e in entries:
            print(f"{e['workload']:30s} {e['num_samples']} samples, {e['cpu_seconds_per_sample']} CPU-s/sample, "
                  f"{e['bytes_per_sample']} B/sample, copy {e['copy_own_bytes']} B")
        write_json(args.out, merge_entries(args.out, entries), indent=2)
        return entries
    entries = []
    for name in args.conditions:
        e = run_condition(name, args.scratch)
        entries.append(e)
        print(f"{name:22s} {e['num_samples']:3d} samples in {e['wall_seconds']:6.1f} s = "
              f"{e['samples_per_minute']:5.1f} samples/min  reprojection mean/max "
              f"{e['reprojection_mean_px']} / {e['reprojection_max_px']} px", flush=True)
    if set(args.conditions) == set(ALL):
        total = float(np.sum([e["wall_seconds"] for e in entries]))
        entries.append({"workload": "simulate_all_conditions_default_world", "wall_seconds": total,
                        "target_seconds": TARGET_ALL_SECONDS, "pass": total <= TARGET_ALL_SECONDS,
                        "cores": os.cpu_count()})
        print(f"all {len(ALL)} variants: {total / 60:.1f} min (target 20 min)")
    for e in real_reprojection():
        entries.append(e)
        print(f"{e['workload']:40s} pairs {e['reprojection_pairs']:5d}  mean {e['reprojection_mean_px']:.4f} px  "
              f"max {e['reprojection_max_px']:.4f} px")
    write_json(args.out, merge_entries(args.out, entries), indent=2)
    print(f"wrote {args.out}")
    return entries


if __name__ == "__main__":
    main()
