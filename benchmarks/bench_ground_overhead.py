"""What the ground and the overcast light cost `simulate`: CPU seconds per sample with both on and both off, in one
process.

Run from the repository root after ``dvc repro media`` (the world and every condition's media under ``data/``):
``.venv/bin/python -m benchmarks.bench_ground_overhead [--variants snow-aligned rain-aligned] [--samples 3]
[--rounds 3]``.

For each variant, ``--samples`` keyframes spread over the world's first scene go through simulate's per-sample work
(`weatheralign.simulate.weather_copy.run_sample`: load the frame, the images and range maps, the keyframe and its
``simulate.sweeps`` sweeps through the media, every camera, the JPEG and LiDAR files written into a scratch folder
that is emptied between calls, outside the timing) with the scene's media as the media stage resolved them (the
ground and the overcast light on) and the same media without either (off): issue 39's whole change to the cameras
and the LiDAR. The two alternate within every round, their order swapped
from round to round, after one untimed warm-up call of each (numba's compiled code loaded), so that a machine shared
with other work slows both alike. Reported per variant: CPU seconds (``time.process_time``, every thread of this
process) and wall seconds per sample, on and off, and the overhead ``on / off - 1`` (CPU: the median over the rounds
of each round's ratio, as the machine's speed drifts from round to round) against the target
`TARGET_OVERHEAD`; CPU is the figure to read on a busy machine, wall the one a run waits for. Results are merged into
``reports/benchmarks/ground_overhead.json`` (one entry per variant).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from benchmarks.common import merge_entries
from weatheralign.atomic import write_json

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "ground_overhead.json"
TARGET_OVERHEAD = 0.20
"""Issue 39: simulate's CPU per sample grows by at most this share with the ground and the overcast on."""


def sample_jobs(nusc: Any, variant: str, samples: int) -> list[Any]:
    """``samples`` jobs of ``variant`` (``<condition>-<aligned|unaligned>``) spread evenly over the first scene's
    keyframes, with the media stage's media for that condition."""
    from weatheralign.simulate.media import media_path, read_media
    from weatheralign.simulate.plan import plan_jobs

    condition, alignment = variant.rsplit("-", 1)
    jobs = plan_jobs(nusc, read_media(media_path(REPO / "data", condition)), alignment == "aligned",
                     max_samples=int(nusc.scene[0]["nbr_samples"]))
    step = max(len(jobs) // samples, 1)
    return jobs[::step][:samples]


def timed_sample(nusc: Any, job: Any, ground: bool, world: Any, scratch: Path, sweeps: int) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of `run_sample` of ``job`` with its ground and overcast light (``ground``) or
    without either, written into an emptied ``scratch``."""
    from weatheralign.simulate.observe import ObserveOptions
    from weatheralign.simulate.weather_copy import run_sample

    if not ground:
        job = replace(job, media=replace(job.media, ground=None, overcast=None))
    shutil.rmtree(scratch, ignore_errors=True)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    run_sample(nusc, Path(world.dataroot), scratch, job, world.sensors, ObserveOptions(threads=1), "bench", 92,
               sweeps)
    return time.process_time() - cpu0, time.perf_counter() - wall0


def measure(variant: str, samples: int, rounds: int, scratch: Path, sweeps: int) -> dict[str, Any]:
    """The entry of one variant: per-sample CPU and wall seconds with the ground on and off (means over the samples,
    medians over the rounds) and the overheads; the CPU overhead is the median of the rounds' own on / off ratios."""
    from weatheralign.data.nuscenes import open_nuscenes
    from weatheralign.manifest import manifest_path, read_manifest

    world = read_manifest(manifest_path(REPO / "data", "world"))
    world = replace(world, dataroot=str((REPO / world.dataroot).resolve()))
    nusc = open_nuscenes(Path(world.dataroot), world.version)
    jobs = sample_jobs(nusc, variant, samples)
    for ground in (True, False):  # warm-up: compiled kernels loaded, caches filled
        timed_sample(nusc, jobs[0], ground, world, scratch, sweeps)
    rounds_of: dict[bool, list[tuple[float, float]]] = {True: [], False: []}
    for k in range(rounds):
        for ground in ((False, True) if k % 2 == 0 else (True, False)):
            times = [timed_sample(nusc, job, ground, world, scratch, sweeps) for job in jobs]
            rounds_of[ground].append((statistics.fmean(t[0] for t in times), statistics.fmean(t[1] for t in times)))
    shutil.rmtree(scratch, ignore_errors=True)
    cpu = {g: statistics.median(r[0] for r in rounds_of[g]) for g in rounds_of}
    wall = {g: statistics.median(r[1] for r in rounds_of[g]) for g in rounds_of}
    per_round = [on[0] / off[0] - 1.0 for on, off in zip(rounds_of[True], rounds_of[False])]
    overhead = statistics.median(per_round)  # each round's pair ran back to back: robust to the machine's drift
    return {"workload": f"ground_overhead_{variant}", "variant": variant, "samples": len(jobs), "rounds": rounds,
            "sweeps": sweeps, "sample_tokens": [j.sample_token for j in jobs],
            "cpu_s_per_sample_ground_off": round(cpu[False], 4), "cpu_s_per_sample_ground_on": round(cpu[True], 4),
            "wall_s_per_sample_ground_off": round(wall[False], 4), "wall_s_per_sample_ground_on": round(wall[True], 4),
            "cpu_overhead": round(overhead, 4), "wall_overhead": round(wall[True] / wall[False] - 1.0, 4),
            "cpu_overhead_per_round": [round(x, 4) for x in per_round],
            "target_overhead": TARGET_OVERHEAD, "meets_target": overhead <= TARGET_OVERHEAD,
            "load_average_1min": round(os.getloadavg()[0], 2), "cpu_count": os.cpu_count()}


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", nargs="+", default=["snow-aligned", "rain-aligned"])
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--sweeps", type=int, default=2, help="sweeps per keyframe (params.yaml's simulate.sweeps)")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/weatheralign-bench-ground-overhead"))
    args = ap.parse_args(argv)
    entries = []
    for variant in args.variants:
        entry = measure(variant, args.samples, args.rounds, args.scratch, args.sweeps)
        entries.append(entry)
        print(f"{variant}: CPU per sample {entry['cpu_s_per_sample_ground_off']:.3f} s off, "
              f"{entry['cpu_s_per_sample_ground_on']:.3f} s on: {100 * entry['cpu_overhead']:+.1f} % "
              f"(target <= {100 * TARGET_OVERHEAD:+.0f} %); wall {entry['wall_s_per_sample_ground_off']:.3f} / "
              f"{entry['wall_s_per_sample_ground_on']:.3f} s ({100 * entry['wall_overhead']:+.1f} %)", flush=True)
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    write_json(REPORT, merge_entries(REPORT, entries))
    return entries


if __name__ == "__main__":
    main()
