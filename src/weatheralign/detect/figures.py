"""Figures of the detect stage: the learning curve and bird's-eye views of detections against the ground truth."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from weatheralign.detect.types import DETECTION_CLASSES, SampleDetections  # noqa: E402


def learning_curve_figure(curve: Sequence[dict[str, float]], losses: Sequence[float]) -> Figure:
    """Left: training loss per step (and its 50-step running mean). Right: val mAP, NDS and mAP over the classes
    present against training steps (``curve``: dicts with ``step``, ``map``, ``nds``, ``map_present``)."""
    fig, (ax_l, ax_r) = plt.subplots(1, 2, figsize=(12, 4.2))
    if losses:
        x = np.arange(1, len(losses) + 1)
        ax_l.plot(x, losses, color="0.75", lw=0.6, label="step")
        k = min(50, len(losses))
        ax_l.plot(x[k - 1:], np.convolve(losses, np.ones(k) / k, mode="valid"), color="C0", label=f"mean of {k}")
        ax_l.set_yscale("log")
    ax_l.set(xlabel="training step", ylabel="loss (total)", title="training loss")
    ax_l.legend()
    if curve:
        steps = [p["step"] for p in curve]
        for key, label in (("map", "mAP (10 classes)"), ("map_present", "mAP (classes present)"), ("nds", "NDS")):
            ax_r.plot(steps, [p[key] if p[key] is not None else np.nan for p in curve], marker="o", label=label)
    ax_r.set(xlabel="training step", ylabel="val score", title="clean val during pretraining", ylim=(0, 1))
    ax_r.grid(alpha=0.3)
    ax_r.legend()
    fig.tight_layout()
    return fig


def learning_curve_rows(curves: Sequence[Sequence[dict[str, float]]]) -> list[dict[str, float]]:
    """The learning curves of several seeds as DVC plot rows, one per evaluated step the seeds share: ``step``, the
    val mAP's mean, min and max over the seeds, and the NDS's mean (``curves``: per seed the dicts of
    `learning_curve_figure`)."""
    by_step: dict[int, list[dict[str, float]]] = {}
    for curve in curves:
        for point in curve:
            by_step.setdefault(int(point["step"]), []).append(point)
    rows = []
    for step, points in sorted(by_step.items()):
        if len(points) != len(curves):
            continue
        maps = [float(p["map"]) for p in points]
        rows.append({"step": step, "map_mean": float(np.mean(maps)), "map_min": min(maps), "map_max": max(maps),
                     "nds_mean": float(np.mean([float(p["nds"]) for p in points]))})
    return rows


def per_class_rows(per_class_ap: dict[str, float]) -> list[dict[str, float | str]]:
    """Per-class AP as DVC plot rows ``{"class", "ap"}`` in `DETECTION_CLASSES` order."""
    return [{"class": name, "ap": float(per_class_ap[name])} for name in DETECTION_CLASSES if name in per_class_ap]


def _box_corners(row: np.ndarray) -> np.ndarray:
    """(5, 2) closed outline in x, y of a box row (x, y, z, w, l, h, yaw, ...): length along yaw."""
    x, y, w, length, yaw = row[0], row[1], row[3], row[4], row[6]
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[length, w], [length, -w], [-length, -w], [-length, w], [length, w]]) / 2.0
    return local @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def detections_bev_figure(evalsets: Sequence, detections: Sequence[Sequence[SampleDetections]], extent_m: float,
                          sample_index: int = 0, min_score: float = 0.3) -> Figure:
    """One panel per evaluation set: the sample's aggregated LiDAR points (keyframe LiDAR frame), ground-truth
    boxes (green) and detections scoring at least ``min_score`` (red, labelled with class and score)."""
    fig, axes = plt.subplots(1, len(evalsets), figsize=(7 * len(evalsets), 7), squeeze=False)
    for ax, evalset, dets in zip(axes[0], evalsets, detections):
        item = evalset.dataset[sample_index]
        pts = item["points"].numpy()
        ax.scatter(pts[:, 0], pts[:, 1], s=0.3, c=pts[:, 3], cmap="viridis", linewidths=0)
        for row in item["boxes"].numpy():
            ax.plot(*_box_corners(row).T, color="limegreen", lw=1.2)
        det = next(d for d in dets if d.token == item["token"])
        for row, sc, lab in zip(det.boxes, det.scores, det.labels):
            if sc >= min_score:
                ax.plot(*_box_corners(row).T, color="red", lw=1.0)
                ax.text(row[0], row[1], f"{DETECTION_CLASSES[lab]} {sc:.2f}", color="red", fontsize=6)
        ax.set(xlim=(-extent_m, extent_m), ylim=(-extent_m, extent_m), aspect="equal",
               title=f"{evalset.name}: GT (green), detections >= {min_score} (red)",
               xlabel="LiDAR x [m]", ylabel="LiDAR y [m]")
    fig.tight_layout()
    return fig
