"""`world` stage: the clean multi-sensor dataset in nuScenes format, handed on by its manifest.

Default: render the synthetic world into ``<paths.data>/world``. With ``world.source: nuscenes`` the stage checks a
real nuScenes(-mini) dataroot instead (loads every sample's frame once) and reports on it: the dataset is read in
place, nothing is copied. Either way it writes ``<paths.data>/manifests/world.json`` (`weatheralign.manifest`): the
dataroot, version, sensor models (from params for the synthetic world; estimated from the scans, with
``world.sensor_overrides``, for real data) and content digest, which every later stage reads. The manifest is removed
first and written last, so a failed run leaves none. It is the stage's DVC output, not the dataset folder: DVC would
hash every file of the rendered world (~11 GB, 13k files at the default, hashed again on every run) where the manifest's
digest already names every file by path and size.
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib.pyplot as plt
from PIL import Image
from prefect import flow

from flows.common import gather, parse_stage_args, run_stage, threads_per_task
from tasks.tracking import StageTracker
from tasks.world import render_samples_task
from weatheralign.config import Params
from weatheralign.data.check import check_dataset
from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.manifest import DatasetManifest, dataset_digest, display_path, manifest_path, write_manifest
from weatheralign.sensors import dataset_sensors
from weatheralign.viz import bev_figure, camera_mosaic
from weatheralign.world.dataset import claim_dataroot, finalize, sample_jobs


def synthetic_dataroot(params: Params) -> Path:
    return params.paths.data / "world"


def _render_synthetic(params: Params) -> tuple[Path, dict]:
    cfg = params.world
    dataroot = synthetic_dataroot(params)
    claim_dataroot(dataroot, cfg.version)  # before anything is written or removed
    jobs = sample_jobs(cfg)
    t0 = time.time()
    nthreads = threads_per_task(params)
    size = params.run.samples_per_task
    chunks = [jobs[i:i + size] for i in range(0, len(jobs), size)]
    futures = [render_samples_task.submit(chunk, cfg, dataroot, nthreads) for chunk in chunks]
    outcomes = [o for chunk in gather(futures, "world: rendering samples", params.run.show_progress,
                                      weights=[len(c) for c in chunks]) for o in chunk]
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
    check = check_dataset(nusc, params.run.max_workers)
    check.raise_if_bad(Path(cfg.nuscenes_dataroot))  # every bad file at once, before any later stage writes
    counts: dict[str, int] = {}
    for ann in nusc.sample_annotation:
        name = nusc.get("category", nusc.get("instance", ann["instance_token"])["category_token"])["name"]
        counts[name] = counts.get(name, 0) + 1
    return Path(cfg.nuscenes_dataroot), {
        "num_scenes": len(nusc.scene), "num_samples": len(nusc.sample),
        "num_sweeps": sum(1 for sd in nusc.sample_data if sd["channel"] == "LIDAR_TOP" and not sd["is_key_frame"]),
        "num_annotations": len(nusc.sample_annotation), "class_counts": dict(sorted(counts.items())),
        "lidar_files_checked": check.lidar_files, "images_checked": check.images,
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


HEADLINE = ("num_samples", "num_annotations")
"""The figures of reports/world/metrics.json, one ``dvc exp show`` column each (the rest, class counts included, in
details.json; MLflow logs every number of its top level)."""


def headline(details: dict) -> dict:
    """The `HEADLINE` figures of the stage's details (those it has)."""
    return {k: details[k] for k in HEADLINE if k in details}


@flow(name="world", log_prints=True)
def world_flow(params: Params) -> dict:
    """Build (or check) the clean dataset; returns the figures written to reports/world/details.json."""
    manifest_file = manifest_path(params.paths.data, "world")
    manifest_file.unlink(missing_ok=True)
    with StageTracker(params, "world") as tracker:
        tracker.log_params({"world": params.world.model_dump(mode="json")})
        if params.world.source == "synthetic":
            dataroot, summary = _render_synthetic(params)
        else:
            dataroot, summary = _summarise_real(params)
        root_rel = display_path(dataroot)
        metrics = {"dataroot": root_rel, "version": params.world.version, "source": params.world.source, **summary}
        write_figures(dataroot, params, tracker)
        nusc = open_nuscenes(dataroot, params.world.version)
        manifest = DatasetManifest(root_rel, params.world.version, params.world.source,
                                   dataset_sensors(params.world, nusc), dataset_digest(dataroot, params.world.version),
                                   tuple(s["name"] for s in nusc.scene))
        tracker.log_params({"sensors": manifest.sensors.to_dict()})
        if params.world.source != "synthetic":  # the user's dataroot, read in place
            tracker.log_dataset(f"{params.world.source}-{params.world.version}", manifest.content_digest, root_rel,
                                "source")
        tracker.finish(metrics, headline(metrics), logged={
            k: v for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)})
        write_manifest(manifest_file, manifest)
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("world", argv)
    return run_stage(world_flow, params)


if __name__ == "__main__":
    main()
