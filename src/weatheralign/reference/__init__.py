"""The real-weather reference of ReDAM: a Seeing Through Fog root (real, or the embedded synthetic one) read per level
(clear, light and dense fog, snow, rain).

- `layout`: `open_reference` / `ReferenceDataset` (split files, frames as `weatheralign.data.frame.Frame`, exact range
  maps where the reference has them), `check_reference`.
- `synthetic`: the embedded synthetic reference (other scenes than the world, HDL-64-like LiDAR, stereo-left camera,
  hidden fog levels in ``<paths.data>/reference/sealed_truth.json``).
- `lidar_exact`, `camera_exact`: its exact fog processes (full pulse integral per beam; per-pixel integration).
- `lidar_particles_exact`, `camera_particles_exact`: its exact snow and rain processes (Monte-Carlo sub-rays per beam
  through the particles; per-pixel ray tracing of the particles with supersampling and exposure-time integration).

`configured_reference(params, levels)` opens the reference that ``params.reference`` names (or those of its levels).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from weatheralign.data.errors import DataFormatError
from weatheralign.reference.layout import (
    FOG_LEVELS,
    LEVELS,
    PRECIPITATION_LEVELS,
    ReferenceDataset,
    ReferenceSplit,
    SplitSummary,
    check_reference,
    open_reference,
    split_files_of,
)

if TYPE_CHECKING:
    from weatheralign.config import Params
    from weatheralign.sensors import LidarModel

__all__ = ["FOG_LEVELS", "LEVELS", "PRECIPITATION_LEVELS", "ReferenceDataset", "ReferenceSplit", "SplitSummary",
           "check_reference", "configured_reference", "open_reference", "reference_lidar_model", "reference_root",
           "split_files_of"]


def reference_root(params: Params) -> Path:
    """The reference root of ``params.reference``: ``stf_root`` for ``source: stf``, else the synthetic reference
    under ``<paths.data>/reference/synthetic``."""
    cfg = params.reference
    if cfg.source == "stf":
        assert cfg.stf_root is not None  # checked by the config
        return Path(cfg.stf_root)
    from weatheralign.reference.synthetic import synthetic_root

    return synthetic_root(params.paths.data)


def configured_reference(params: Params, levels: Sequence[str] = LEVELS) -> ReferenceDataset:
    """`open_reference` of the reference ``params.reference`` describes (root, split files, declared scale),
    restricted to ``levels`` (the fog calibration opens only clear and the fog levels, so a root needs no snow / rain
    split files for it).

    Raises:
        DataFormatError: the synthetic reference has not been rendered yet, or see `open_reference`.
    """
    cfg = params.reference
    root = reference_root(params)
    if cfg.source == "synthetic" and not root.is_dir():
        raise DataFormatError(f"reference root {root} does not exist: render the synthetic reference first "
                              f"(python -m flows.reference)")
    files = {level: rel for level, rel in split_files_of(cfg.split_files).items() if level in levels}
    return open_reference(root, files, cfg.intensity_max)


def reference_lidar_model(params: Params, reference: ReferenceDataset) -> LidarModel:
    """The reference's LiDAR as a `weatheralign.sensors.LidarModel`: the synthetic reference's HDL-64-like sensor
    from ``reference.lidar`` (its pulse, overlap, range limits, detector floor and noise), or for a real root the model
    estimated from the clear split's scans with ``reference.sensor_overrides`` applied.

    The calibration fast-simulates fog on the reference's clear scans through this sensor, so the detector floor and
    pulse are the reference sensor's, not the world's.
    """
    from weatheralign.data.rings import HDL64E_ELEVATIONS_DEG
    from weatheralign.sensors import SYNTHETIC_INTENSITY, LidarModel, PulseSensor, estimate_lidar_model

    cfg = params.reference
    if cfg.source == "synthetic":
        lc = cfg.lidar
        return LidarModel(
            elevations_deg=tuple(float(e) for e in HDL64E_ELEVATIONS_DEG), columns_per_ring=lc.firings_per_ring,
            rotation_hz=10.0, clockwise=True, start_azimuth_rad=float(np.pi), laser_step_s=0.0, divergence_rad=3e-3,
            max_range_m=lc.max_range_m, min_range_m=lc.min_range_m, noise_floor=lc.noise_floor, intensity_max=255.0,
            intensity=SYNTHETIC_INTENSITY,
            pulse=PulseSensor(tau_h=lc.tau_h_s, r1=lc.overlap_r1_m, r2=lc.overlap_r2_m, max_range=lc.max_range_m),
            origin="params", intensity_noise_std=lc.intensity_noise_std, intensity_noise_rel=lc.intensity_noise_rel,
            range_noise_std_m=lc.range_noise_std_m, floor_range_m=lc.floor_range_m)
    scans = [reference.load_frame(sample_id).lidar for sample_id in reference.ids("clear")[:8]]
    return estimate_lidar_model(scans, rotation_hz=10.0, overrides=cfg.sensor_overrides.as_dict())
