"""`simulate` stage: a weather copy of the clean dataset for one condition, aligned or unaligned.

``python -m flows.simulate --set simulate.condition=snow --set simulate.aligned=true`` reads the `world` output
(``reports/world/metrics.json`` names its dataroot) and, for snow/rain, ``<paths.data>/particles/fields.json``;
for fog with ``simulate.fog_levels: calibrated`` (default), the calibrate_fog stage's tuned levels
(``<paths.data>/calibrate_fog/fog_levels.json``); writes ``<paths.data>/simulate/<condition>-<aligned|unaligned>/``
(a complete nuScenes dataroot, see `weatheralign.simulate`) and ``reports/simulate/<condition>-<aligned|unaligned>/metrics.json`` plus a side-by-side
figure (clean vs weather: LiDAR BEV coloured by label, CAM_FRONT), also logged to an MLflow child run.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from PIL import Image, ImageDraw
from prefect import flow

from flows.common import gather, parse_stage_args, task_runner, threads_per_task
from tasks.simulate import simulate_sample_task
from tasks.tracking import StageTracker
from weatheralign.config import Params, SimulateConfig
from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.simulate import (FOG_LEVELS_FILE, condition_name, finalize_copy, fog_level, scene_airlight,
                                   summarise, weather_for_scene, weather_relpath, with_fog_levels)
from weatheralign.viz import bev_figure


def input_dataroot(params: Params) -> tuple[Path, str]:
    """(dataroot, version) of the `world` stage's output."""
    metrics_file = params.paths.reports / "world" / "metrics.json"
    if not metrics_file.is_file():
        raise DataFormatError(f"{metrics_file}: missing; run the world stage first (python -m flows.world)")
    world = json.loads(metrics_file.read_text())
    return Path(world["dataroot"]), world["version"]


def output_dataroot(params: Params) -> Path:
    return params.paths.data / "simulate" / condition_name(params.simulate.condition, params.simulate.aligned)


def load_fields(params: Params) -> dict | None:
    if params.simulate.condition.startswith("fog_"):
        return None
    path = params.paths.data / "particles" / "fields.json"
    if not path.is_file():
        raise DataFormatError(f"{path}: missing; run the particles stage first (python -m flows.particles)")
    return json.loads(path.read_text())


def _rel(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path.resolve())


def side_by_side(src_root: Path, out_root: Path, version: str, sample_token: str, title: str, path: Path) -> None:
    """Clean vs weather: LiDAR BEV (weather coloured by label) over CAM_FRONT, as one PNG."""
    tiles = []
    for root, name in ((src_root, "clean"), (out_root, title)):
        nusc = open_nuscenes(root, version)
        frame = load_frame(nusc, sample_token, cameras=("CAM_FRONT",))
        colour = None
        if root == out_root:
            lidar_file = nusc.get("sample_data", nusc.get("sample", sample_token)["data"]["LIDAR_TOP"])["filename"]
            colour = np.load(root / weather_relpath(lidar_file))["label"].astype(float)
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


def fog_metrics(cfg: SimulateConfig) -> dict:
    """For fog: the LiDAR's level (alpha [1/m], beta [1/(m sr)]) and where it came from; nothing otherwise."""
    if not cfg.condition.startswith("fog_"):
        return {}
    alpha, beta = fog_level(cfg, cfg.condition)
    return {"fog_alpha": alpha, "fog_beta": beta, "fog_levels": cfg.fog_levels}


@flow(name="simulate", log_prints=True)
def simulate_flow(params: Params) -> dict:
    """Write the weather copy of one condition; returns the metrics written to reports/simulate/<name>/."""
    cfg = params.simulate
    if cfg.condition.startswith("fog_") and cfg.fog_levels == "calibrated":
        cfg = with_fog_levels(cfg, params.paths.data / FOG_LEVELS_FILE)
    name = condition_name(cfg.condition, cfg.aligned)
    with StageTracker(params, f"simulate/{name}") as tracker:
        tracker.log_params({"simulate": cfg.model_dump(mode="json")})
        src_root, version = input_dataroot(params)
        out_root = output_dataroot(params)
        fields = load_fields(params)
        nusc = open_nuscenes(src_root, version)
        jobs, airlights = [], {}
        for scene in nusc.scene:
            weather = weather_for_scene(cfg, scene["name"], fields)
            first = load_frame(nusc, scene["first_sample_token"])
            airlights[scene["token"]] = scene_airlight(list(first.cameras.values()))
            token = scene["first_sample_token"]
            while token:
                jobs.append((token, weather, airlights[scene["token"]]))
                token = nusc.get("sample", token)["next"]
        if cfg.max_samples:
            jobs = jobs[:cfg.max_samples]
        t0 = time.time()
        nthreads = threads_per_task(params)
        futures = [simulate_sample_task.submit(nusc, src_root, out_root, tok, w, cfg, a,
                                               params.world.camera.jpeg_quality, nthreads) for tok, w, a in jobs]
        outcomes = gather(futures, f"simulate {name}: samples", params.run.show_progress)
        elapsed = time.time() - t0
        finalize_copy(nusc, src_root, out_root, version)
        records = [r for r, _ in outcomes]
        done_now = sum(1 for _, now in outcomes if now)
        metrics = {"dataroot": _rel(out_root), "source": _rel(src_root), "condition": cfg.condition,
                   "aligned": cfg.aligned, **fog_metrics(cfg), **summarise(records), "samples_simulated_this_run": done_now,
                   "wall_seconds_per_sample_this_run": round(elapsed / done_now, 3) if done_now else None}
        if records:
            fig_path = tracker.reports / "side_by_side.png"
            side_by_side(src_root, out_root, version, jobs[0][0], name, fig_path)
            tracker.log_artifact(fig_path, "figures")
        tracker.finish(metrics)
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("simulate", argv)
    return simulate_flow.with_options(task_runner=task_runner(params))(params)


if __name__ == "__main__":
    main()
