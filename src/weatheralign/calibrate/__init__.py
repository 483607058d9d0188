"""ReDAM calibration of the fog medium against a reference dataset (library only: no Prefect / DVC / MLflow).

- `histograms`: exact 256-bin streaming intensity histograms, the KS statistic on them, frame bootstrap.
- `lidar`: KS grid search over (α, β) + bounded continuous refinement per fog level (`calibrate_level`, or the
  mapped pieces `fog_frames` / `evaluate_cell` / `GridResult.from_cells` / `finish_level`).
- `camera`: fog severity (α̂, visibility) of foggy images from the image + range map; simulated vs reference ratio.
- `kid`: KID with EfficientNet-Lite0 features (or a local TorchScript Inception), named after the backbone.
- `figures`: the ECDF figure (paper's Fig. 3) and the KS heat map.

`kid` imports torch and `figures` matplotlib: import them explicitly (``weatheralign.calibrate.kid``).
"""

from weatheralign.calibrate.camera import (
    FogSeverity,
    SetSeverity,
    VisibilityComparison,
    aggregate_severity,
    camera_visibility_ratio,
    compare_severity,
    estimate_fog_severity,
    severity_of_set,
)
from weatheralign.calibrate.histograms import (
    NUM_BINS,
    IntensityHistograms,
    KsBootstrap,
    bootstrap_ecdf_band,
    bootstrap_ks,
    intensity_bins,
    ks_statistic,
)
from weatheralign.calibrate.lidar import (
    PAPER_ALPHAS,
    CellResult,
    FogFrames,
    GridResult,
    LevelCalibration,
    Refinement,
    beta_from_factor,
    calibrate_level,
    evaluate_cell,
    finish_level,
    fog_frames,
    grid_cells,
    grid_search,
    refine,
    simulated_histograms,
)

__all__ = [
    "NUM_BINS",
    "PAPER_ALPHAS",
    "CellResult",
    "FogFrames",
    "FogSeverity",
    "GridResult",
    "IntensityHistograms",
    "KsBootstrap",
    "LevelCalibration",
    "Refinement",
    "SetSeverity",
    "VisibilityComparison",
    "aggregate_severity",
    "beta_from_factor",
    "bootstrap_ecdf_band",
    "bootstrap_ks",
    "calibrate_level",
    "camera_visibility_ratio",
    "compare_severity",
    "estimate_fog_severity",
    "evaluate_cell",
    "finish_level",
    "fog_frames",
    "grid_cells",
    "grid_search",
    "intensity_bins",
    "ks_statistic",
    "refine",
    "severity_of_set",
    "simulated_histograms",
]
