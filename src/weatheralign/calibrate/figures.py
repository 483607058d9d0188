"""Figures of the LiDAR calibration: the ECDF comparison of the paper's Fig. 3 and the KS heat map of the grid.

Both return a `matplotlib.figure.Figure` built without pyplot (no global figure registry; the Agg canvas is used when
the caller saves it: ``fig.savefig(path)``).
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from weatheralign.calibrate.histograms import NUM_BINS, IntensityHistograms, bootstrap_ecdf_band
from weatheralign.calibrate.lidar import GridResult, LevelCalibration

BAND = (0.05, 0.95)
"""Default bootstrap band of the reference ECDF (5-95 %)."""


def _new_figure(size: tuple[float, float]) -> Figure:
    fig = Figure(figsize=size, dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def ecdf_figure(
    reference: IntensityHistograms,
    simulated: IntensityHistograms,
    clear: IntensityHistograms | None = None,
    *,
    level: str = "",
    alpha: float = math.nan,
    beta: float = math.nan,
    ks: float = math.nan,
    ks_ci: tuple[float, float] = (math.nan, math.nan),
    band: tuple[float, float] = BAND,
    num_resamples: int = 200,
    seed: int = 0,
) -> Figure:
    """Intensity ECDFs: the reference (real fog) with its frame-bootstrap band, the tuned simulation, the clear scans.

    Args:
        reference: the level's real foggy scans; simulated: the clear scans fogged with the tuned medium;
            clear: the clear scans (context), or None.
        level: fog level name for the title (e.g. ``"light"``).
        alpha [1/m], beta [1/(m sr)], ks, ks_ci: the tuned values for the title.
        band: bootstrap quantiles of the reference band.
        num_resamples, seed: the band's bootstrap.
    """
    scale = reference.intensity_max
    x = np.arange(NUM_BINS) * (scale / 255.0)
    lo, hi = bootstrap_ecdf_band(reference, quantiles=band, num_resamples=num_resamples, rng=seed)
    fig = _new_figure((6.4, 4.2))
    ax = fig.add_subplot()
    ax.fill_between(x, lo, hi, step="post", color="tab:orange", alpha=0.35, linewidth=0,
                    label=f"reference {100 * band[0]:.0f}-{100 * band[1]:.0f} % (frame bootstrap)")
    ax.step(x, reference.ecdf(), where="post", color="tab:green", linewidth=2.6,
            label=f"reference fog ({reference.num_frames} scans)")
    ax.step(x, simulated.ecdf(), where="post", color="tab:red", linewidth=1.1,
            label=f"tuned simulation ({simulated.num_frames} scans)")
    if clear is not None:
        ax.step(x, clear.ecdf(), where="post", color="0.45", linewidth=1.0, linestyle="--", label="clear")
    ax.set_xlim(0.0, float(scale))
    ax.set_ylim(0.0, 1.0)
    ax.set_xlabel(f"intensity (0..{scale:g}, {NUM_BINS} bins)")
    ax.set_ylabel("ECDF")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    mor = math.log(20.0) / alpha if alpha > 0 else math.inf
    title = f"{level + ' fog: ' if level else ''}α* = {alpha:.4g} /m (MOR {mor:.0f} m), β* = {beta:.3g} /(m sr)\n" \
            f"D_KS = {ks:.3f} [{ks_ci[0]:.3f}, {ks_ci[1]:.3f}]"
    ax.set_title(title, fontsize=10)
    return fig


def ecdf_rows(sets: dict[str, IntensityHistograms]) -> list[dict[str, float]]:
    """The pooled intensity ECDFs of ``sets`` (name -> histograms of one scale) as DVC plot rows, one per bin:
    ``intensity`` (the bin's lower edge on the sets' scale) and each set's ECDF."""
    scales = {h.intensity_max for h in sets.values()}
    if len(scales) != 1:
        raise ValueError(f"ecdf_rows: the sets have different intensity scales {sorted(scales)}")
    x = np.arange(NUM_BINS) * (scales.pop() / 255.0)
    ecdfs = {name: h.ecdf() for name, h in sets.items()}
    return [{"intensity": float(x[i]), **{name: float(e[i]) for name, e in ecdfs.items()}} for i in range(NUM_BINS)]


def level_ecdf_figure(result: LevelCalibration, reference: IntensityHistograms, level: str = "",
                      **kwargs: object) -> Figure:
    """`ecdf_figure` of a `LevelCalibration` (its tuned and clear histograms, values in the title)."""
    return ecdf_figure(reference, result.simulated, result.clear, level=level, alpha=result.alpha, beta=result.beta,
                       ks=result.ks, ks_ci=(result.ks_ci_low, result.ks_ci_high), **kwargs)  # type: ignore[arg-type]


def ks_heatmap(grid: GridResult, *, level: str = "", refined: tuple[float, float] | None = None) -> Figure:
    """D_KS over the (α, β-factor) grid, values written in the cells, best cell outlined.

    Args:
        grid: the level's `GridResult`.
        level: fog level name for the title.
        refined: (α*, factor*) of the refinement, drawn as a cross (α placed on the grid's log scale).
    """
    fig = _new_figure((6.4, 4.6))
    ax = fig.add_subplot()
    img = ax.imshow(grid.ks.T, origin="lower", cmap="viridis_r", aspect="auto")
    fig.colorbar(img, ax=ax, label="D_KS")
    for i in range(len(grid.alphas)):
        for j in range(len(grid.beta_factors)):
            v = grid.ks[i, j]
            ax.text(i, j, f"{v:.3f}", ha="center", va="center", fontsize=7,
                    color="white" if v > np.nanmedian(grid.ks) else "black")
    bi, bj = grid.best_index
    ax.add_patch(Rectangle((bi - 0.5, bj - 0.5), 1.0, 1.0, fill=False, edgecolor="red", linewidth=2.0))
    if refined is not None and len(grid.alphas) > 1:
        a, f = refined
        xi = float(np.interp(math.log(a), np.log(grid.alphas), np.arange(len(grid.alphas))))
        yj = float(np.interp(f, grid.beta_factors, np.arange(len(grid.beta_factors))))
        ax.plot([xi], [yj], marker="x", color="red", markersize=10, markeredgewidth=2, label="refined")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xticks(range(len(grid.alphas)), [f"{a:g}" for a in grid.alphas])
    ax.set_yticks(range(len(grid.beta_factors)), [f"{f:.1f}" for f in grid.beta_factors])
    ax.set_xlabel("α [1/m]")
    ax.set_ylabel("β factor (β = 0.023·factor / MOR)")
    ax.set_title(f"{level + ' fog: ' if level else ''}D_KS over the grid (best {grid.best_ks:.3f} at "
                 f"α = {grid.best_alpha:g}, factor {grid.best_beta_factor:.1f})", fontsize=10)
    return fig

