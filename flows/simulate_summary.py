"""`simulate_summary` stage: one table of every simulate condition, aligned vs unaligned side by side.

``python -m flows.simulate_summary`` reads ``reports/simulate/<condition>-<alignment>/details.json`` of every
condition of the `simulate` matrix and writes ``reports/simulate_summary/details.json`` (per condition:
`SUMMARY_KEYS`; no DVC metrics of its own: the variants' are) and ``reports/simulate_summary/summary.png`` (LiDAR
point labels per condition; aligned vs unaligned re-projection error), also logged to an MLflow child run. A condition
without a metrics file is an error naming the stage to run.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from prefect import flow  # noqa: E402

from flows.common import parse_stage_args, run_stage  # noqa: E402
from tasks.tracking import StageTracker  # noqa: E402
from weatheralign.conditions import ALIGNMENTS, CONDITIONS, variant_name  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.data.errors import read_json_file  # noqa: E402

SUMMARY_KEYS = ("dataroot", "points_unchanged", "points_attenuated", "points_scattered", "points_lost",
                "points_clutter", "particles_rendered", "reprojection_mean_px", "reprojection_max_px",
                "reprojection_p99_px", "reprojection_pairs", "seconds_per_sample", "num_samples")
"""Keys copied per condition into ``reports/simulate_summary/details.json``."""


def condition_names() -> list[str]:
    """``fog_light-aligned``, ``fog_light-unaligned``, ... for every condition of `CONDITIONS` (the dvc.yaml
    matrix's order)."""
    return [variant_name(c, a == ALIGNMENTS[0]) for c in CONDITIONS for a in ALIGNMENTS]


def collect(reports: Path, names: list[str]) -> dict[str, dict]:
    """Per condition name the `SUMMARY_KEYS` of its metrics file (missing keys -> None)."""
    out: dict[str, dict] = {}
    for name in names:
        path = reports / "simulate" / name / "details.json"
        metrics = read_json_file(path, f"run the stage simulate@{name} first (dvc repro simulate@{name})")
        out[name] = {k: metrics.get(k) for k in SUMMARY_KEYS}
    return out


def summary_figure(summary: dict[str, dict]) -> Figure:
    """Left: keyframe LiDAR points per label and condition (stacked, log-free shares). Right: mean and max
    re-projection error [px] of snow and rain, aligned vs unaligned (log scale)."""
    names = list(summary)
    fig, (ax_l, ax_r) = plt.subplots(1, 2, figsize=(14, 4.8), gridspec_kw={"width_ratios": [1.6, 1.0]})
    labels = ("points_unchanged", "points_attenuated", "points_scattered", "points_lost")
    colours = ("#9e9e9e", "#1f77b4", "#ff7f0e", "#d62728")
    bottom = np.zeros(len(names))
    for key, colour in zip(labels, colours):
        vals = np.array([float(summary[n][key] or 0) for n in names])
        total = np.array([sum(float(summary[n][k] or 0) for k in labels) for n in names])
        share = np.divide(vals, total, out=np.zeros_like(vals), where=total > 0)
        ax_l.bar(names, share, bottom=bottom, color=colour, label=key.removeprefix("points_"))
        bottom += share
    ax_l.set_ylabel("share of keyframe LiDAR points")
    ax_l.set_title("what the weather did to the LiDAR points")
    ax_l.tick_params(axis="x", rotation=35)
    ax_l.legend(loc="lower left", fontsize=8)
    particle = [n for n in names if summary[n]["reprojection_pairs"]]
    x = np.arange(len(particle))
    for offset, key, colour in ((-0.2, "reprojection_mean_px", "#2ca02c"), (0.2, "reprojection_max_px", "#9467bd")):
        ax_r.bar(x + offset, [summary[n][key] for n in particle], width=0.4, color=colour,
                 label=key.removeprefix("reprojection_").replace("_px", ""))
    ax_r.axhline(0.5, color="k", lw=0.8, ls="--", label="0.5 px")
    ax_r.set_yscale("log")
    ax_r.set_xticks(x, particle, rotation=35)
    ax_r.set_ylabel("re-projection error [px]")
    ax_r.set_title("LiDAR particle vs its rasterised centroid")
    ax_r.legend(fontsize=8)
    fig.tight_layout()
    return fig


@flow(name="simulate_summary", log_prints=True)
def simulate_summary_flow(params: Params) -> dict:
    """Write reports/simulate_summary/details.json and summary.png; returns the summary."""
    with StageTracker(params, "simulate_summary") as tracker:
        summary = collect(params.paths.reports, condition_names())
        fig = summary_figure(summary)
        fig_path = tracker.reports / "summary.png"
        fig.savefig(fig_path, dpi=110)
        plt.close(fig)
        tracker.log_artifact(fig_path, "figures")
        # the figures per condition are the simulate runs' own
        tracker.finish(summary, {"variants": len(summary)}, logged={"conditions": len(summary)}, metrics_file=False)
    return summary


def main(argv: list[str] | None = None) -> dict:
    return run_stage(simulate_summary_flow, parse_stage_args("simulate_summary", argv), runner=None)


if __name__ == "__main__":
    main()
