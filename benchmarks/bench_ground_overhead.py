"""What the ground and the overcast light cost `simulate`: CPU seconds per sample with both on and both off, in one
process.

Run from the repository root after ``dvc repro media`` (the world and every condition's media under ``data/``):
``.venv/bin/python -m benchmarks.bench_ground_overhead [--variants snow-aligned rain-aligned] [--samples 3]
[--rounds 3] [--breakdown]``.

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

``--breakdown`` adds where the extra CPU goes: the samples once more on and off under `cProfile` (CPU clock), the
cameras run one after another in the calling thread (simulate's thread pool replaced for this pass only, as cProfile
sees one thread), and per part of `BREAKDOWN_PARTS` its cumulative CPU seconds per sample on, off and the
difference (``breakdown`` in the entry). Profiling slows Python code more than compiled kernels: read the parts'
shares, not their absolute seconds.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import shutil
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

from benchmarks.common import merge_entries
from weatheralign.atomic import write_json

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "ground_overhead.json"
TARGET_OVERHEAD = 0.20
"""Issue 39: simulate's CPU per sample grows by at most this share with the ground and the overcast on."""
BREAKDOWN_PARTS = {
    "camera overcast": "overcast_edit",
    "camera overcast: light layers of the clear image": "light_layers",
    "camera overcast: relighting": "relit_u8",
    "camera ground": "edit_image_u8",
    "camera ground: layers": "ground_layers",
    "camera ground: guided edit": "affine_edit_u8",
    "lidar ground: surfaces and normals": "scan_surfaces",
    "lidar ground: beams without return": "unseen_beams",
    "lidar ground: edit of the returns": "edit_scan",
    "lidar particles (the unseen beams join them)": "simulate_particle_scans",
    "mask agreement": "mask_agreement",
}
"""Part label -> function name (cumulative CPU time of every function of that name) of the ``--breakdown``."""


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


def measure(variant: str, samples: int, rounds: int, scratch: Path, sweeps: int,
            with_breakdown: bool = False) -> dict[str, Any]:
    """The entry of one variant: per-sample CPU and wall seconds with the ground on and off (means over the samples,
    medians over the rounds) and the overheads; the CPU overhead is the median of the rounds' own on / off ratios.
    With ``with_breakdown``, also `breakdown`'s parts (after the timed rounds, which it does not touch)."""
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
    parts = breakdown(nusc, jobs, world, scratch, sweeps) if with_breakdown else None
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
            "load_average_1min": round(os.getloadavg()[0], 2), "cpu_count": os.cpu_count(),
            **({"breakdown": parts} if parts is not None else {})}


class _CallingThreadPool:
    """`concurrent.futures.ThreadPoolExecutor`'s surface used by `weatheralign.simulate.observe.observe`, run in the
    calling thread: what cProfile needs to see the cameras' work."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __enter__(self) -> _CallingThreadPool:
        return self

    def __exit__(self, *exc: Any) -> None:
        return None

    def submit(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        from concurrent.futures import Future

        future: Future = Future()
        future.set_result(fn(*args, **kwargs))
        return future

    def map(self, fn: Any, items: Any) -> list[Any]:
        return [fn(item) for item in items]


@contextmanager
def _cameras_in_calling_thread() -> Iterator[None]:
    """simulate's per-frame thread pool replaced by `_CallingThreadPool` while the block runs."""
    from weatheralign.simulate import observe

    pool = observe.ThreadPoolExecutor
    observe.ThreadPoolExecutor = _CallingThreadPool  # type: ignore[misc,assignment]
    try:
        yield
    finally:
        observe.ThreadPoolExecutor = pool  # type: ignore[misc]


def part_seconds(stats: pstats.Stats, parts: dict[str, str]) -> dict[str, float]:
    """Per part label, the cumulative CPU seconds of the functions named ``parts[label]`` in ``stats`` (recursive
    calls counted once, as cProfile's cumulative time does)."""
    cumulative = stats.stats  # type: ignore[attr-defined]
    return {label: sum(v[3] for k, v in cumulative.items() if k[2] == name) for label, name in parts.items()}


def breakdown(nusc: Any, jobs: list[Any], world: Any, scratch: Path, sweeps: int) -> dict[str, Any]:
    """Per `BREAKDOWN_PARTS` label, CPU seconds per sample with the ground on, off and on - off, and the profiled
    totals, from one cProfile pass over ``jobs`` each way (cameras in the calling thread)."""
    totals, parts = {}, {}
    with _cameras_in_calling_thread():
        for ground in (True, False):
            profile = cProfile.Profile(time.process_time)
            profile.enable()
            for job in jobs:
                timed_sample(nusc, job, ground, world, scratch, sweeps)
            profile.disable()
            stats = pstats.Stats(profile)
            totals[ground] = stats.total_tt / len(jobs)  # type: ignore[attr-defined]
            parts[ground] = {k: v / len(jobs) for k, v in part_seconds(stats, BREAKDOWN_PARTS).items()}
    return {"profiled_cpu_s_per_sample_on": round(totals[True], 4),
            "profiled_cpu_s_per_sample_off": round(totals[False], 4),
            "parts_cpu_s_per_sample": {label: {"on": round(parts[True][label], 4), "off": round(parts[False][label], 4),
                                               "extra": round(parts[True][label] - parts[False][label], 4)}
                                       for label in BREAKDOWN_PARTS}}


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", nargs="+", default=["snow-aligned", "rain-aligned"])
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--sweeps", type=int, default=2, help="sweeps per keyframe (params.yaml's simulate.sweeps)")
    ap.add_argument("--breakdown", action="store_true",
                    help="also profile where the extra CPU goes (BREAKDOWN_PARTS), cameras in the calling thread")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/weatheralign-bench-ground-overhead"))
    args = ap.parse_args(argv)
    entries = []
    for variant in args.variants:
        entry = measure(variant, args.samples, args.rounds, args.scratch, args.sweeps, args.breakdown)
        entries.append(entry)
        print(f"{variant}: CPU per sample {entry['cpu_s_per_sample_ground_off']:.3f} s off, "
              f"{entry['cpu_s_per_sample_ground_on']:.3f} s on: {100 * entry['cpu_overhead']:+.1f} % "
              f"(target <= {100 * TARGET_OVERHEAD:+.0f} %); wall {entry['wall_s_per_sample_ground_off']:.3f} / "
              f"{entry['wall_s_per_sample_ground_on']:.3f} s ({100 * entry['wall_overhead']:+.1f} %)", flush=True)
        for label, cpu in entry.get("breakdown", {}).get("parts_cpu_s_per_sample", {}).items():
            print(f"  {label}: {cpu['extra']:+.3f} CPU s per sample ({cpu['off']:.3f} off, {cpu['on']:.3f} on)")
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    write_json(REPORT, merge_entries(REPORT, entries))
    return entries


if __name__ == "__main__":
    main()
