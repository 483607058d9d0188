"""`world` stage: the clean multi-sensor dataset in nuScenes format.

Default: render the synthetic world into ``<paths.data>/world``. With ``world.source: nuscenes`` the stage checks a
real nuScenes(-mini) dataroot instead (loads every sample's frame once) and reports on it.
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib.pyplot as plt
from PIL import Image
from prefect import flow

from flows.common import gather, parse_stage_args, task_runner, threads_per_task
from tasks.tracking import StageTracker
from tasks.world import render_sample_task
from weatheralign.config import Params
from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.viz import bev_figure, camera_mosaic
from weatheralign.world.dataset import finalize, sample_jobs


def synthetic_dataroot(params: Params) -> Path:
    return params.paths.data / "world"


def _render_synthetic(params: Params) -> tuple[Path, dict]:
    cfg = params.world
    dataroot = synthetic_dataroot(params)
    jobs = sample_jobs(cfg)
    t0 = time.time()
    nthreads = threads_per_task(params)
    futures = [render_sample_task.submit(spec, k, cfg, dataroot, nthreads) for spec, k in jobs]
    outcomes = gather(futures, "world: rendering samples", params.run.show_progress)
    elapsed = time.time() - t0
    rendered = sum(1 for _, now in outcomes if now)
    summary = finalize(cfg, dataroot, [r for r, _ in outcomes])
    summary["samples_rendered_this_run"] = rendered
    summary["seconds_per_sample"] = round(elapsed / rendered, 3) if rendered else None
    return dataroot, summary


def _summarise_real(params: Params) -> tuple[Path, dict]:
    cfg = params.world
    assert cfg.nuscenes_dataroot is not None
    nusc = open_nuscenes(cfg.nuscenes_dataroot, cfg.version)
    t0 = time.time()
    for sample in nusc.sample:
        load_frame(nusc, sample["token"])
    counts: dict[str, int] = {}
    for ann in nusc.sample_annotation:
        name = nusc.get("category", nusc.get("instance", ann["instance_token"])["category_token"])["name"]
        counts[name] = counts.get(name, 0) + 1
    return Path(cfg.nuscenes_dataroot), {
        "num_scenes": len(nusc.scene), "num_samples": len(nusc.sample),
        "num_sweeps": sum(1 for sd in nusc.sample_data if sd["channel"] == "LIDAR_TOP" and not sd["is_key_frame"]),
        "num_annotations": len(nusc.sample_annotation), "class_counts": dict(sorted(counts.items())),
        "samples_rendered_this_run": 0, "seconds_per_sample": round((time.time() - t0) / max(1, len(nusc.sample)), 3),
    }


def write_figures(dataroot: Path, params: Params, tracker: StageTracker) -> None:
    """A camera mosaic and a BEV of the first sample, to reports/world/ and MLflow."""
    nusc = open_nuscenes(dataroot, params.world.version)
    frame = load_frame(nusc, nusc.scene[0]["first_sample_token"])
    mosaic = tracker.reports / "sample_cameras.jpg"
    Image.fromarray(camera_mosaic(frame)).save(mosaic, quality=88)
    fig = bev_figure(frame, title=f"{nusc.scene[0]['name']}: first sample, LIDAR_TOP + boxes")
    bev = tracker.reports / "sample_bev.png"
    fig.savefig(bev, dpi=110)
    plt.close(fig)
    tracker.log_artifact(mosaic, "figures")
    tracker.log_artifact(bev, "figures")


@flow(name="world", log_prints=True)
def world_flow(params: Params) -> dict:
    """Build (or check) the clean dataset; returns the metrics written to reports/world/metrics.json."""
    with StageTracker(params, "world") as tracker:
        tracker.log_params({"world": params.world.model_dump(mode="json")})
        if params.world.source == "synthetic":
            dataroot, summary = _render_synthetic(params)
        else:
            dataroot, summary = _summarise_real(params)
        try:
            root_rel = str(dataroot.resolve().relative_to(Path.cwd().resolve()))
        except ValueError:
            root_rel = str(dataroot.resolve())
        metrics = {"dataroot": root_rel, "version": params.world.version, "source": params.world.source, **summary}
        write_figures(dataroot, params, tracker)
        tracker.finish(metrics)
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("world", argv)
    return world_flow.with_options(task_runner=task_runner(params))(params)


if __name__ == "__main__":
    main()
