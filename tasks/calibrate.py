"""Mapped tasks of the `calibrate_fog` stage: one (alpha, beta) grid cell; one reference camera frame."""

from __future__ import annotations

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.calibrate.histograms import IntensityHistograms
from weatheralign.calibrate.lidar import CellResult, FogFrames, evaluate_cell
from weatheralign.lidar.pulse import PulseSensor
from weatheralign.reference import ReferenceDataset
from weatheralign.reference.frames import reference_frame


@task(name="ks-grid-cell", cache_policy=NO_CACHE, retries=0)
def evaluate_cell_task(frames: FogFrames, reference: IntensityHistograms, alpha: float, beta_factor: float,
                       noise_floor: float | None, sensor: PulseSensor) -> CellResult:
    """D_KS of the clear reference scans fogged with one (alpha, beta_factor) cell against one fog level, through
    the reference LiDAR's pulse ``sensor`` and detector floor ``noise_floor`` (0..255)."""
    return evaluate_cell(frames, reference, alpha, beta_factor, noise_floor=noise_floor, sensor=sensor)


def reference_camera(ds: ReferenceDataset, sample_id: str) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) uint8 sRGB, ray length (H, W) float32 [m], inf = sky) of one reference frame's stereo-left
    camera (`reference_frame`)."""
    _, image, range_map = reference_frame(ds, sample_id)
    return image, range_map


@task(name="reference-camera", cache_policy=NO_CACHE, retries=0)
def reference_camera_task(ds: ReferenceDataset, sample_id: str) -> tuple[np.ndarray, np.ndarray]:
    """`reference_camera` as a mapped task."""
    return reference_camera(ds, sample_id)
