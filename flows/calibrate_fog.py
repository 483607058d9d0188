"""`calibrate_fog` stage: ReDAM — the fog levels of the simulation tuned to a reference with real fog.

``python -m flows.calibrate_fog`` opens the reference of the `reference` stage (``params.reference``: the embedded
synthetic reference, or a Seeing Through Fog root) and, per fog level (``light``, ``dense``):

1. LiDAR: fogs the reference's clear scans with every cell of the paper's (alpha, beta) grid (one mapped Prefect
   task per cell, `weatheralign.calibrate.lidar.evaluate_cell`), refines around the best cell and bootstraps D_KS
   over frames (`finish_level`); the detector floor and pulse are the reference LiDAR's (`reference_lidar_model`);
2. camera: the fog's airlight. Fog scatters the day's ambient light, so its brightness is not the clear scene's sky:
   each foggy reference image's sky over the clear reference images' median sky (linear luminance) gives the
   level's airlight gains (`weatheralign.camera.fog.airlight_gains`), from which `simulate` draws one per scene;
3. camera check: fogs the reference's clear images at the tuned alpha with the simulation's camera fog (`fog_image`,
   each frame's clear-sky airlight times a drawn gain, as in `simulate`) and compares the visibility estimated from
   image + depth with that of the reference's foggy images (`camera_visibility_ratio`), plus KID on features of a
   pretrained CNN (EfficientNet-Lite0 from the package registry, or ``calibrate_fog.inception_path``: a local
   TorchScript Inception).

Writes ``<paths.data>/calibrate_fog/fog_levels.json`` (``{level: {alpha, beta, mor, ks, airlight_gains}}``: what
the fog conditions of `simulate` read), ``reports/calibrate_fog/details.json`` (per level ``alpha, beta, mor, ks,
ks_ci_low, ks_ci_high, camera_visibility_ratio, kid, kid_std, kid_backbone, airlight_gain_median``, ...) and figures
(ECDF with the reference's bootstrap band, KS over the grid, reference vs simulated images), also logged to MLflow. The
synthetic reference's sealed truth is never read here.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from prefect import flow  # noqa: E402

from flows.common import gather, parse_stage_args, run_stage  # noqa: E402
from tasks.calibrate import evaluate_cell_task, reference_camera_task  # noqa: E402
from tasks.tracking import StageTracker  # noqa: E402
from weatheralign import atomic  # noqa: E402
from weatheralign.calibrate.camera import camera_visibility_ratio  # noqa: E402
from weatheralign.calibrate.figures import ecdf_rows, ks_heatmap, level_ecdf_figure  # noqa: E402
from weatheralign.calibrate.histograms import IntensityHistograms  # noqa: E402
from weatheralign.calibrate.kid import feature_extractor, kid_from_features  # noqa: E402
from weatheralign.calibrate.lidar import GridResult, LevelCalibration, finish_level, fog_frames, grid_cells  # noqa: E402
from weatheralign.camera.fog import (  # noqa: E402
    airlight_gains,
    estimate_airlight,
    fog_airlight,
    fog_image,
    linear_to_srgb,
    sky_airlight,
)
from weatheralign.conditions import FogPart  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.manifest import FOG_LEVELS_FILE  # noqa: E402
from weatheralign.reference import FOG_LEVELS, ReferenceDataset, configured_reference, reference_lidar_model  # noqa: E402
from weatheralign.sensors import LidarModel  # noqa: E402


def lidar_level(ds: ReferenceDataset, frames, level: str, params: Params,
                sensor: LidarModel) -> tuple[LevelCalibration, IntensityHistograms]:
    """Grid (mapped tasks), refinement and bootstrap of one fog level through the reference's LiDAR ``sensor``;
    returns it and the level's histograms."""
    cfg = params.calibrate_fog
    reference = IntensityHistograms.from_scans((ds.load_scan(i) for i in ds.ids(level)), ds.intensity_max)
    floor = sensor.noise_floor
    futures = [evaluate_cell_task.submit(frames, reference, a, f, floor, sensor.pulse) for a, f in grid_cells()]
    grid = GridResult.from_cells(gather(futures, f"calibrate_fog {level}: (alpha, beta) grid",
                                        params.run.show_progress))
    result = finish_level(frames, reference, grid, noise_floor=floor, sensor=sensor.pulse, fine_points=cfg.fine_points,
                          max_nelder_mead=cfg.max_nelder_mead, num_bootstrap=cfg.num_bootstrap,
                          confidence=cfg.confidence, seed=cfg.seed)
    return result, reference


def camera_sets(ds: ReferenceDataset, params: Params) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Per level (clear, light, dense): (image, ray length) of up to ``calibrate_fog.camera_frames`` frames."""
    limit = params.calibrate_fog.camera_frames
    out: dict[str, list] = {}
    for level in ("clear", *FOG_LEVELS):
        ids = ds.ids(level)[:limit] if limit else ds.ids(level)
        futures = [reference_camera_task.submit(ds, i) for i in ids]
        out[level] = gather(futures, f"calibrate_fog: {level} camera frames", params.run.show_progress)
    return out


def simulated_fog_images(clear: list[tuple[np.ndarray, np.ndarray]], alpha: float, gains: tuple[float, ...],
                         seed: int, level: str, exact_ranges: bool) -> list[np.ndarray]:
    """The clear reference images fogged at ``alpha`` by the simulation's camera fog: each frame's clear-sky airlight
    times a gain of the level's ``gains`` drawn per frame (`FogPart.airlight_gain`), as `simulate` does per scene;
    the transmission edge-refined only where the ray lengths are estimated (not ``exact_ranges``), as in
    `simulate` (on exact depth the guided filter would only blur the fog across depth edges)."""
    out = []
    for k, (img, rng) in enumerate(clear):
        gain = FogPart.airlight_gain(gains, seed, level, str(k))
        airlight = linear_to_srgb(fog_airlight(estimate_airlight([img], [rng]), gain))
        out.append(fog_image(img, rng, alpha, airlight, refine=not exact_ranges))
    return out


def level_airlight_gains(clear: list[tuple[np.ndarray, np.ndarray]], foggy: list[tuple[np.ndarray, np.ndarray]],
                         exact_ranges: bool) -> tuple[float, ...]:
    """The fog level's airlight gains (`airlight_gains`): each foggy reference image's sky over the clear
    reference images' median sky, in linear light. The foggy images' sky comes from their exact range maps
    (``exact_ranges``: the synthetic reference), else from the dark channel (`sky_airlight` without ranges): a
    LiDAR in fog loses its far returns, so the sky of a dense depth from a foggy scan would take in fogged
    buildings."""
    return airlight_gains([sky_airlight([img], [rng] if exact_ranges else None) for img, rng in foggy],
                          [sky_airlight([img], [rng]) for img, rng in clear])


def camera_figure(ref: list[np.ndarray], sim: list[np.ndarray], level: str, alpha: float, path: Path) -> None:
    """Two reference foggy images above two clear reference images fogged by the simulation at the tuned alpha."""
    n = min(2, len(ref), len(sim))
    fig, axes = plt.subplots(2, n, figsize=(6.5 * n, 7), squeeze=False)
    for k in range(n):
        axes[0, k].imshow(ref[k])
        axes[0, k].set_title(f"reference {level} fog #{k}", fontsize=9)
        axes[1, k].imshow(sim[k])
        axes[1, k].set_title(f"simulated at tuned alpha = {alpha:.4f} /m (clear frame #{k})", fontsize=9)
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def reference_digest(ds: ReferenceDataset) -> str:
    """16 hex digits over the reference's split lists (which frames of which recordings it holds)."""
    text = "\n".join(f"{split}:{','.join(map(str, ds.ids(split)))}" for split in ("clear", *FOG_LEVELS))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


HEADLINE = ("alpha", "beta", "ks")
"""Per fog level, the figures of reports/calibrate_fog/metrics.json: the tuned level and its fit (the rest,
intervals and camera checks included, in details.json and the MLflow child run of each level)."""


def headline(details: dict) -> dict:
    """Per fog level its `HEADLINE` figures."""
    return {level: {k: details[level].get(k) for k in HEADLINE} for level in FOG_LEVELS if level in details}


@flow(name="calibrate_fog", log_prints=True)
def calibrate_fog_flow(params: Params) -> dict:
    """ReDAM per fog level; returns the figures written to reports/calibrate_fog/details.json."""
    cfg = params.calibrate_fog
    t0 = time.time()
    with StageTracker(params, "calibrate_fog") as tracker:
        torch.set_num_threads(params.run.torch_threads)
        ds = configured_reference(params, ("clear", *FOG_LEVELS))
        sensor = reference_lidar_model(params, ds)
        tracker.log_params({"calibrate_fog": cfg.model_dump(mode="json"), "reference.source": params.reference.source,
                            "reference_lidar": sensor.to_dict()})
        frames = fog_frames((ds.load_scan(i) for i in ds.ids("clear")), noise_std=sensor.intensity_noise_std,
                            noise_rel=sensor.intensity_noise_rel, intensity=sensor.intensity,
                            floor_range_m=sensor.floor_range_m)
        extractor = feature_extractor(cfg.inception_path, device=cfg.device)
        cams = camera_sets(ds, params)
        clear_features = extractor([img for img, _ in cams["clear"]])
        metrics: dict = {"reference_root": str(ds.root), "reference_source": params.reference.source,
                         "kid_backbone": extractor.backbone}
        levels: dict = {}
        for level in FOG_LEVELS:
            t_level = time.time()
            result, reference = lidar_level(ds, frames, level, params, sensor)
            ref_images = [img for img, _ in cams[level]]
            gains = level_airlight_gains(cams["clear"], cams[level], ds.load_range(ds.ids(level)[0]) is not None)
            sim_images = simulated_fog_images(cams["clear"], result.alpha, gains, cfg.seed, level,
                                              ds.load_range(ds.ids("clear")[0]) is not None)
            visibility = camera_visibility_ratio(sim_images, [r for _, r in cams["clear"]], ref_images,
                                                 [r for _, r in cams[level]])
            ref_features = extractor(ref_images)
            kid = kid_from_features(extractor(sim_images), ref_features, backbone=extractor.backbone, rng=cfg.seed)
            kid_clear = kid_from_features(clear_features, ref_features, backbone=extractor.backbone, rng=cfg.seed)
            metrics[level] = {**result.metrics(), "beta_identified": result.beta_identified,
                              **visibility.metrics(), "kid": kid.mean, "kid_std": kid.std,
                              "kid_backbone": kid.backbone, "kid_clear_vs_reference": kid_clear.mean,
                              "airlight_gain_median": float(np.median(gains)), "airlight_gain_min": min(gains),
                              "airlight_gain_max": max(gains),
                              "airlight_frames": len(gains) if gains != (1.0,) else 0,
                              "seconds": round(time.time() - t_level, 2)}
            levels[level] = {"alpha": result.alpha, "beta": result.beta, "mor": result.mor, "ks": result.ks,
                             "airlight_gains": list(gains)}
            for name, fig in ((f"ecdf_{level}.png", level_ecdf_figure(result, reference, level=level)),
                              (f"ks_grid_{level}.png", ks_heatmap(result.grid, level=level,
                                                                   refined=(result.alpha, result.beta_factor)))):
                fig.savefig(tracker.reports / name, dpi=110)
                plt.close(fig)
                tracker.log_artifact(tracker.reports / name, "figures")
            atomic.write_json(tracker.reports / f"ecdf_{level}.json", ecdf_rows(
                {"reference": reference, "simulated": result.simulated, "clear": result.clear}), indent=1)
            camera_figure(ref_images, sim_images, level, result.alpha, tracker.reports / f"camera_{level}.png")
            tracker.log_artifact(tracker.reports / f"camera_{level}.png", "figures")
            print(f"calibrate_fog {level}: alpha* = {result.alpha:.5f} /m (MOR {result.mor:.0f} m), beta* = "
                  f"{result.beta:.3g}, D_KS = {result.ks:.4f} [{result.ks_ci_low:.4f}, {result.ks_ci_high:.4f}], "
                  f"camera visibility ratio {visibility.ratio:.3f}, KID ({kid.backbone}) {kid.mean:.4f}")
        atomic.write_json(params.paths.data / FOG_LEVELS_FILE,
                          {**levels, "reference_root": str(ds.root), "reference_source": params.reference.source},
                          indent=2)
        metrics["seconds"] = round(time.time() - t0, 2)
        tracker.log_dataset(f"reference-{params.reference.source}", reference_digest(ds), str(ds.root), "reference")
        tracker.finish(metrics, headline(metrics), logged={"seconds": metrics["seconds"]}, children={
            level: ({"weather": "fog", "severity": level}, metrics[level]) for level in FOG_LEVELS})
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("calibrate_fog", argv)
    return run_stage(calibrate_fog_flow, params, runner="threads")  # cells share the frames in memory


if __name__ == "__main__":
    main()
