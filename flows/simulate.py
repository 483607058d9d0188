"""`simulate` stage: a weather copy of the clean dataset for one condition, aligned or unaligned.

``python -m flows.simulate --set simulate.condition=snow --set simulate.aligned=true`` reads the world's manifest
(dataroot, sensors, content digest) and the condition's media (``<paths.data>/media/<condition>.json``, the media
stage); plans the jobs (`weatheralign.simulate.plan`), maps one task per chunk of ``run.samples_per_task`` samples of a
scene (`weatheralign.simulate.weather_copy.run_chunk` around the pure core `weatheralign.simulate.observe`) onto the
Dask workers, completes the copy with hard links and tracks. An unaligned copy hard-links the LiDAR files of its aligned
twin (``<condition>-aligned``, run first by dvc.yaml's matrix order) where the twin finished a sample with the same
LiDAR fingerprint, and computes them otherwise: the LiDAR sees the condition's own media in both copies. Writes
``<paths.data>/simulate/<condition>-<aligned|unaligned>/`` (a complete nuScenes dataroot) and
``reports/simulate/<condition>-<aligned|unaligned>/details.json`` (its headline in ``metrics.json``) plus a
side-by-side figure (clean vs weather: LiDAR BEV coloured by label, CAM_FRONT), also logged to an MLflow child run,
and hands the copy on by its manifest ``<paths.data>/manifests/simulate-<condition>-<aligned|unaligned>.json`` (the
stage's DVC output, written last).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from PIL import Image, ImageDraw
from prefect import flow

from flows.common import RunLabel, gather, parse_stage_args, run_stage, threads_per_task
from tasks.simulate import simulate_chunk_task
from tasks.tracking import StageTracker, numeric_leaves
from weatheralign.conditions import ALIGNMENTS, condition_named, condition_tags, variant_name
from weatheralign.config import Params
from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.manifest import (
    DatasetManifest,
    dataset_digest,
    display_path,
    manifest_path,
    read_manifest,
    write_manifest,
)
from weatheralign.provenance import stage_fingerprint
from weatheralign.simulate.media import ConditionMedia, media_path, read_media
from weatheralign.simulate.observe import ObserveOptions
from weatheralign.simulate.plan import chunk_jobs, plan_jobs
from weatheralign.simulate.weather_copy import DatasetRef, copy_outputs, finalize_copy, read_weather_record, summarise
from weatheralign.viz import bev_figure


def output_dataroot(params: Params) -> Path:
    return params.paths.data / "simulate" / variant_name(params.simulate.condition, params.simulate.aligned)


def side_by_side(src_root: Path, out_root: Path, version: str, sample_token: str, title: str, path: Path) -> None:
    """Clean vs weather: LiDAR BEV (weather coloured by label) over CAM_FRONT, as one PNG."""
    tiles = []
    for root, name in ((src_root, "clean"), (out_root, title)):
        nusc = open_nuscenes(root, version)
        frame = load_frame(nusc, sample_token, cameras=("CAM_FRONT",))
        colour = None
        if root == out_root:
            lidar_file = nusc.get("sample_data", nusc.get("sample", sample_token)["data"]["LIDAR_TOP"])["filename"]
            colour = read_weather_record(root, lidar_file, len(frame.lidar.points))["label"].astype(float)
        fig = bev_figure(frame, title=f"{name}: LIDAR_TOP" + (" (label: 0 unchanged, 1 attenuated, 2 scattered)"
                                                               if colour is not None else ""),
                         point_colour=colour, cmap="plasma")
        fig.canvas.draw()
        bev = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
        cam = Image.open(frame.cameras["CAM_FRONT"].image_path).convert("RGB")
        cam = cam.resize((bev.width, round(cam.height * bev.width / cam.width)))
        ImageDraw.Draw(cam).text((10, 10), f"{name}: CAM_FRONT", fill=(255, 0, 0))
        col = Image.new("RGB", (bev.width, bev.height + cam.height), "white")
        col.paste(bev, (0, 0))
        col.paste(cam, (0, bev.height))
        tiles.append(col)
    out = Image.new("RGB", (sum(t.width for t in tiles), max(t.height for t in tiles)), "white")
    x = 0
    for t in tiles:
        out.paste(t, (x, 0))
        x += t.width
    out.save(path)


def fog_metrics(media: ConditionMedia, aligned: bool) -> dict:
    """With fog: the LiDAR's level (alpha [1/m], beta [1/(m sr)]), where it came from, and the cameras' alpha (mean
    over scenes when unaligned); nothing otherwise."""
    if media.fog is None:
        return {}
    cam = media.fog["alpha"] if aligned else float(np.mean(list(media.fog["camera_alpha_unaligned"].values())))
    return {"fog_alpha": media.fog["alpha"], "fog_beta": media.fog["beta"], "fog_levels": media.fog["source"],
            "camera_fog_alpha": cam}


def particle_metrics(media: ConditionMedia, aligned: bool) -> dict:
    """With particles: the LiDAR's rate [mm/h] and the cameras' (mean over scenes when unaligned); nothing
    otherwise."""
    if not media.fields:
        return {}
    rate = float(np.mean([spec.rate_mm_h for spec in media.fields.values()]))
    cam = rate if aligned or not media.camera_rate_unaligned else float(np.mean(list(
        media.camera_rate_unaligned.values())))
    return {"rate_mm_h": rate, "camera_rate_mm_h": cam}


PER_KEYFRAME = ("points_scattered", "points_clutter", "points_lost")
"""Keyframe LiDAR point counts that the simulate run logs to MLflow per keyframe."""

HEADLINE_PER_KEYFRAME = ("points_scattered", "points_lost")
"""Of those, the ones reports/simulate/<condition>-aligned/metrics.json gives (the severity curves read them)."""


def figures(details: dict) -> dict:
    """The `PER_KEYFRAME` counts divided by the keyframes, and the 99th percentile of the LiDAR particles'
    re-projection error [px] (logged to MLflow)."""
    n = details.get("num_samples") or 0
    return {**{f"{k}_per_keyframe": round(details[k] / n, 2) if n else None for k in PER_KEYFRAME},
            "reprojection_p99_px": details.get("reprojection_p99_px")}


def headline(details: dict) -> dict:
    """reports/simulate/<variant>/metrics.json, what the variant adds (the rest in details.json and MLflow): aligned,
    the LiDAR's weather (`HEADLINE_PER_KEYFRAME`; the unaligned twin's LiDAR is the same); unaligned, how far the
    cameras' particles lie from the LiDAR's (``reprojection_p99_px``, None without particles: no column)."""
    shown = figures(details)
    keys = [f"{k}_per_keyframe" for k in HEADLINE_PER_KEYFRAME] if details["aligned"] else ["reprojection_p99_px"]
    return {k: shown[k] for k in keys}


@flow(name="simulate", log_prints=True)
def simulate_flow(params: Params) -> dict:
    """Write the weather copy of one condition; returns the figures written to reports/simulate/<name>/details.json."""
    cfg = params.simulate
    name = variant_name(condition_named(cfg.condition).name, cfg.aligned)  # an unknown condition: named first
    media = read_media(media_path(params.paths.data, cfg.condition))
    handoff = manifest_path(params.paths.data, f"simulate-{name}")
    handoff.unlink(missing_ok=True)  # written last: a failed run leaves no handoff behind
    with StageTracker(params, "simulate", name=f"simulate/{name}",
                      tags=condition_tags(cfg.condition, cfg.aligned, *media.rates(params.particles))) as tracker:
        tracker.log_params({"simulate": cfg.model_dump(mode="json")})
        world = read_manifest(manifest_path(params.paths.data, "world"))
        tracker.log_dataset("world", world.content_digest, world.dataroot, "source")
        src_root, out_root = Path(world.dataroot), output_dataroot(params)
        nusc = open_nuscenes(src_root, world.version)
        jobs = plan_jobs(nusc, media, cfg.aligned, cfg.rain_appearance, cfg.max_samples)
        options = ObserveOptions(cfg.near_clip_m, cfg.refine_transmission, threads_per_task(params))
        run_digest = stage_fingerprint("simulate", params, world.content_digest)
        dataset = DatasetRef(str(src_root), world.version, world.content_digest)
        chunks = chunk_jobs(jobs, params.run.samples_per_task)
        t0 = time.time()
        twin = None if cfg.aligned else params.paths.data / "simulate" / variant_name(cfg.condition, True)
        futures = [simulate_chunk_task.submit(dataset, out_root, chunk, world.sensors, options, run_digest,
                                              cfg.jpeg_quality, cfg.sweeps, twin) for chunk in chunks]
        outcomes = [o for chunk in gather(futures, f"simulate {name}: samples", params.run.show_progress,
                                          weights=[len(c) for c in chunks]) for o in chunk]
        elapsed = time.time() - t0
        completed = finalize_copy(nusc, src_root, out_root, world.version,
                                  copy_outputs(nusc, [j.sample_token for j in jobs], cfg.sweeps))
        records = [r for r, _ in outcomes]
        done_now = sum(1 for _, now in outcomes if now)
        metrics = {"dataroot": display_path(out_root), "source": display_path(src_root), "condition": cfg.condition,
                   "aligned": cfg.aligned, **fog_metrics(media, cfg.aligned), **particle_metrics(media, cfg.aligned),
                   **summarise(records),
                   "samples_simulated_this_run": done_now, "files_linked_this_run": completed["linked"],
                   "files_copied_this_run": completed["copied"],
                   "wall_seconds_per_sample_this_run": round(elapsed / done_now, 3) if done_now else None}
        if records:
            fig_path = tracker.reports / "side_by_side.png"
            side_by_side(src_root, out_root, world.version, jobs[0].sample_token, name, fig_path)
            tracker.log_artifact(fig_path, "figures")
        tracker.finish(metrics, headline(metrics), logged=numeric_leaves(figures(metrics)))
        write_manifest(handoff, DatasetManifest(display_path(out_root), world.version, "simulate", world.sensors,
                                                dataset_digest(out_root, world.version), world.scenes))
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("simulate", argv)
    try:
        condition_named(params.simulate.condition)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    cfg = params.simulate
    return run_stage(simulate_flow, params, label=RunLabel.of_stage(
        "simulate", condition=cfg.condition, alignment=ALIGNMENTS[0] if cfg.aligned else ALIGNMENTS[1]))


if __name__ == "__main__":
    main()
