"""Mapped tasks of the `verify` stage: one real reference frame; one clear reference frame through a condition."""

from __future__ import annotations

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.conditions import Condition
from weatheralign.reference import ReferenceDataset
from weatheralign.reference.frames import reference_frame
from weatheralign.sensors import LidarModel
from weatheralign.verify.frames import (
    Severity,
    SimulatedPair,
    displaced_particle_channels,
    frame_fused_input,
    simulated_pair,
)


@task(name="reference-frame", cache_policy=NO_CACHE, retries=0)
def reference_frame_task(ds: ReferenceDataset, sample_id: str, out_hw: tuple[int, int],
                         displaced_step_rad: float | None, seed: int
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(fused input (6, h, w), image (H, W, 3) uint8, ray length (H, W) [m], LiDAR channels with the particle echoes
    displaced (3, h, w) or None) of one real reference frame; the displaced channels only when
    ``displaced_step_rad`` (the LiDAR's azimuth step [rad]) is given (`displaced_particle_channels`, ``seed``)."""
    frame, image, range_map = reference_frame(ds, sample_id)
    points = frame.lidar.points
    displaced = None if displaced_step_rad is None else displaced_particle_channels(
        frame, points, ds.intensity_max, out_hw, displaced_step_rad, seed)
    return frame_fused_input(frame, image, points, ds.intensity_max, out_hw), image, range_map, displaced


@task(name="simulated-reference-frame", cache_policy=NO_CACHE, retries=0)
def simulated_pair_task(ds: ReferenceDataset, sample_id: str, condition: Condition, severity: Severity,
                        lidar: LidarModel, exposure_s: float, out_hw: tuple[int, int], seed: int) -> SimulatedPair:
    """`simulated_pair` as a mapped task."""
    return simulated_pair(ds, sample_id, condition, severity, lidar, exposure_s, out_hw, seed)
