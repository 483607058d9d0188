"""Figures of the fused-feature check (`verify`): the embeddings of reference / aligned / unaligned frames in a
common 2-D PCA (scikit-learn), permutation histograms with the observed MMD^2, the LiDAR intensity ECDFs of the
reference and the simulation per condition, and the weather classifier's held-out confusion matrix."""

from __future__ import annotations

from collections.abc import Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from sklearn.decomposition import PCA  # noqa: E402

from weatheralign.calibrate.histograms import IntensityHistograms  # noqa: E402
from weatheralign.verify.classifier import ClassifierReport  # noqa: E402
from weatheralign.verify.mmd import MmdTest, standardise  # noqa: E402

SET_COLOURS = {"reference": "black", "aligned": "tab:blue", "unaligned": "tab:orange", "control": "tab:red"}


def embedding_figure(features: Mapping[str, NDArray], title: str) -> Figure:
    """The feature sets (name -> (n, d)), standardised together, projected on the first two principal components of
    their pool; one colour per set (`SET_COLOURS` where named)."""
    names = list(features)
    scaled = standardise(*[features[k] for k in names])
    pca = PCA(n_components=2, random_state=0).fit(np.concatenate(scaled))
    fig, ax = plt.subplots(figsize=(6, 5))
    for name, z in zip(names, scaled):
        xy = pca.transform(z)
        ax.scatter(xy[:, 0], xy[:, 1], s=14, alpha=0.7, color=SET_COLOURS.get(name), label=f"{name} ({len(z)})",
                   linewidths=0)
    ratio = pca.explained_variance_ratio_
    ax.set(xlabel=f"PC 1 ({ratio[0]:.0%} of the variance)", ylabel=f"PC 2 ({ratio[1]:.0%})", title=title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def permutation_figure(tests: Mapping[str, MmdTest], title: str) -> Figure:
    """One panel per test (name -> `MmdTest`): the permuted MMD^2 histogram and the observed value with its p-value."""
    fig, axes = plt.subplots(1, len(tests), figsize=(4.5 * len(tests), 3.6), squeeze=False)
    for ax, (name, test) in zip(axes[0], tests.items()):
        ax.hist(test.null, bins=40, color="0.6", label=f"{len(test.null)} permutations")
        ax.axvline(test.mmd2, color=SET_COLOURS.get(name, "tab:blue"), lw=2,
                   label=f"observed {test.mmd2:.4f} (p = {test.p_value:.3g})")
        ax.set(xlabel="MMD² (unbiased)", ylabel="count", title=name)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def ecdf_figure(histograms: Mapping[str, Mapping[str, IntensityHistograms]], ks: Mapping[str, float]) -> Figure:
    """One panel per condition (name -> {set name -> histograms}): the pooled intensity ECDF of each set on the
    0..255 code scale, titled with the condition's D_KS (``ks``, reference vs simulated)."""
    fig, axes = plt.subplots(1, len(histograms), figsize=(4.2 * len(histograms), 3.5), squeeze=False)
    styles = {"reference": ("black", "-"), "simulated (aligned)": ("tab:blue", "-"), "clear": ("0.6", "--")}
    codes = np.arange(256)
    for ax, (name, sets) in zip(axes[0], histograms.items()):
        for label, hist in sets.items():
            colour, line = styles.get(label, (None, "-"))
            ax.step(codes, hist.ecdf(), where="post", color=colour, ls=line, lw=1.3,
                    label=f"{label} ({hist.num_frames} frames)")
        ax.set(xscale="symlog", xlim=(0, 255), ylim=(0, 1.01), xlabel="intensity code (0..255)", ylabel="ECDF",
               title=f"{name}: D_KS = {ks.get(name, float('nan')):.3f}")
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def confusion_rows(report: ClassifierReport) -> list[dict[str, str]]:
    """The held-out confusion matrix as DVC confusion-plot rows, one ``{"actual", "predicted"}`` per held-out frame
    (rows of the same pair in a row)."""
    return [{"actual": report.classes[i], "predicted": report.classes[j]}
            for i in range(len(report.classes)) for j in range(len(report.classes))
            for _ in range(int(report.confusion[i, j]))]


def confusion_figure(report: ClassifierReport) -> Figure:
    """The held-out confusion matrix (counts; rows true, columns predicted) with the accuracy in the title."""
    fig, ax = plt.subplots(figsize=(4.2, 3.8))
    ax.imshow(report.confusion, cmap="Blues")
    n = len(report.classes)
    for i in range(n):
        for j in range(n):
            ax.text(j, i, str(report.confusion[i, j]), ha="center", va="center", fontsize=10)
    ax.set(xticks=range(n), yticks=range(n), xticklabels=report.classes, yticklabels=report.classes,
           xlabel="predicted", ylabel="true",
           title=f"weather classifier, held out: {report.accuracy:.0%} of {report.confusion.sum()}")
    fig.tight_layout()
    return fig


__all__ = ["SET_COLOURS", "confusion_figure", "confusion_rows", "ecdf_figure", "embedding_figure", "permutation_figure"]
