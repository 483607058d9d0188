"""`reference` stage: the real-weather reference dataset that ReDAM calibrates against and `verify` compares with.

Default (``reference.source: synthetic``): render the embedded synthetic reference — Seeing Through Fog layout, other
scenes than the world, clear / light-fog / dense-fog splits through hidden fog levels and snow / rain splits through
hidden rates, by exact processes — into
``<paths.data>/reference/synthetic`` (hidden truth in ``<paths.data>/reference/sealed_truth.json``), one mapped task
per frame, resumable. With ``reference.source: stf`` the stage checks a real Seeing Through Fog root in place
(every split file read, every listed frame loaded) and copies nothing.

Both write ``reports/reference/details.json`` (frames, points per scan, mean intensity on 0..255, share of returns
within 3 m, isolated returns per scan (snow / rain clutter, `weatheralign.lidar.clutter`), per split; seconds) and
``reports/reference/overview.png`` (intensity histograms and one image per split), and log them to MLflow.
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from prefect import flow  # noqa: E402

from flows.common import gather, parse_stage_args, run_stage, threads_per_task  # noqa: E402
from tasks.reference import render_reference_frame_task  # noqa: E402
from tasks.tracking import StageTracker  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.data.stf import CAMERA_CHANNEL  # noqa: E402
from weatheralign.reference import ReferenceDataset, check_reference, configured_reference, reference_lidar_model  # noqa: E402
from weatheralign.reference.synthetic import finalize, frame_specs  # noqa: E402

FIGURE = "overview.png"


def _render_synthetic(params: Params) -> dict:
    cfg = params.reference
    specs = frame_specs(cfg)
    t0 = time.time()
    nthreads = threads_per_task(params)
    futures = [render_reference_frame_task.submit(spec, cfg, params.paths.data, nthreads) for spec in specs]
    outcomes = gather(futures, "reference: rendering frames", params.run.show_progress)
    elapsed = time.time() - t0
    rendered = sum(1 for _, now in outcomes if now)
    summary = finalize(cfg, params.paths.data, [rec for rec, _ in outcomes])
    return {"frames_rendered_this_run": rendered, "render_seconds": round(elapsed, 2),
            "seconds_per_frame": round(elapsed / rendered, 3) if rendered else None,
            **{f"{kind}_returns_per_scan": {
                level: round(float(np.mean([r.stats.get(f"{kind}_returns", 0) for r, _ in outcomes
                                            if r.level == level])), 1)
                for level in summary["frames"] if summary["frames"][level]} for kind in ("fog", "particle")}}


def overview_figure(ds: ReferenceDataset, path: Path) -> None:
    """Intensity histograms (0..255 scale, log counts) of every split and the first image of each split."""
    levels = ds.levels
    fig, axes = plt.subplots(1, 1 + len(levels), figsize=(5 + 4.5 * len(levels), 3.6),
                             gridspec_kw={"width_ratios": [1.2] + [1.6] * len(levels)})
    bins = np.arange(0, 257) - 0.5
    for level in levels:
        values = ds.intensities(level, scale=255.0)
        axes[0].hist(values, bins=bins, histtype="step", density=True, label=f"{level} ({len(ds.ids(level))})")
    axes[0].set_yscale("log")
    axes[0].set_xlim(0, 255)
    axes[0].set_xlabel("intensity (0..255)")
    axes[0].set_title("LiDAR intensity per split")
    axes[0].legend(fontsize=8)
    for ax, level in zip(axes[1:], levels):
        frame = ds.load_frame(ds.ids(level)[0])
        view = frame.cameras.get(CAMERA_CHANNEL)
        if view is not None:
            ax.imshow(view.load_image())
        ax.set_title(f"{level}: {frame.token}", fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def split_tags(split: str) -> dict[str, str]:
    """The MLflow ``weather`` / ``severity`` tags of a reference split (severity: the fog level, else none)."""
    if split in ("light", "dense"):
        return {"weather": "fog", "severity": split}
    return {"weather": split, "severity": "none"}


def _root_for_report(root: Path) -> str:
    try:
        return str(root.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(root.resolve())


def headline(details: dict) -> dict:
    """reports/reference/metrics.json: per split the weather's returns per scan, those it has (the rest, frames,
    points and isolated returns per split included, in details.json and the MLflow child run of each split)."""
    per_split: dict = {}
    for key in ("fog_returns_per_scan", "particle_returns_per_scan"):
        for split, value in details.get(key, {}).items():
            if split in details["splits"] and value:
                per_split.setdefault(split, {})[key] = value
    return {"splits": per_split}


@flow(name="reference", log_prints=True)
def reference_flow(params: Params) -> dict:
    """Render (synthetic) or check (real STF) the reference; returns the figures written to
    reports/reference/details.json."""
    cfg = params.reference
    t0 = time.time()
    with StageTracker(params, "reference") as tracker:
        tracker.log_params({"reference": cfg.model_dump(mode="json")})
        extra = _render_synthetic(params) if cfg.source == "synthetic" else {}
        ds = configured_reference(params)
        lidar = reference_lidar_model(params, ds)
        splits = check_reference(ds, progress=params.run.show_progress,
                                 azimuth_step_rad=2.0 * np.pi / lidar.columns_per_ring)
        metrics = {"source": cfg.source, "root": _root_for_report(ds.root), "intensity_max": ds.intensity_max,
                   "splits": {level: s.as_dict() for level, s in splits.items()},
                   "frames_total": sum(s.frames for s in splits.values()), **extra}
        figure = tracker.reports / FIGURE
        overview_figure(ds, figure)
        tracker.log_artifact(figure, "figures")
        metrics["seconds"] = round(time.time() - t0, 2)
        per_scan = {key: metrics.get(key, {}) for key in ("fog_returns_per_scan", "particle_returns_per_scan")}
        logged = {k: v for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        tracker.finish(metrics, headline(metrics), logged=logged, children={
            split: (split_tags(split),
                    {**values, **{key: table[split] for key, table in per_scan.items() if split in table}})
            for split, values in metrics["splits"].items()})
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("reference", argv)
    return run_stage(reference_flow, params)


if __name__ == "__main__":
    main()
