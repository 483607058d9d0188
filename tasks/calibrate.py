"""Mapped tasks of the `calibrate_fog` stage: one (alpha, beta) grid cell; one reference camera frame."""

from __future__ import annotations

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.calibrate.histograms import IntensityHistograms
from weatheralign.calibrate.lidar import CellResult, FogFrames, evaluate_cell
from weatheralign.camera.depth import camera_range_map
from weatheralign.data.stf import CAMERA_CHANNEL
from weatheralign.lidar.pulse import PulseSensor
from weatheralign.reference import ReferenceDataset


@task(name="ks-grid-cell", cache_policy=NO_CACHE, retries=0)
def evaluate_cell_task(frames: FogFrames, reference: IntensityHistograms, alpha: float, beta_factor: float,
                       noise_floor: float | None, sensor: PulseSensor) -> CellResult:
    """D_KS of the clear reference scans fogged with one (alpha, beta_factor) cell against one fog level, through
    the reference LiDAR's pulse ``sensor`` and detector floor ``noise_floor`` (0..255)."""
    return evaluate_cell(frames, reference, alpha, beta_factor, noise_floor=noise_floor, sensor=sensor)


def reference_camera(ds: ReferenceDataset, sample_id: str) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) uint8 sRGB, ray length (H, W) float32 [m], inf = sky) of one reference frame's stereo-left
    camera: the exact range map where the reference has one (synthetic), else dense depth from the frame's own scan
    (real Seeing Through Fog).

    Raises:
        DataFormatError: the reference has no camera for ``sample_id``.
    """
    from weatheralign.data.errors import DataFormatError

    frame = ds.load_frame(sample_id)
    view = frame.cameras.get(CAMERA_CHANNEL)
    if view is None:
        raise DataFormatError(f"reference {ds.root}: frame {sample_id} has no {CAMERA_CHANNEL} image "
                              f"(expected {ds.camera_folder}/{sample_id}.png)")
    image = view.load_image()
    rng = camera_range_map(view, frame.lidar, image)
    return image, rng


@task(name="reference-camera", cache_policy=NO_CACHE, retries=0)
def reference_camera_task(ds: ReferenceDataset, sample_id: str) -> tuple[np.ndarray, np.ndarray]:
    """`reference_camera` as a mapped task."""
    return reference_camera(ds, sample_id)
