"""Mapped tasks of the calibration stages: one (alpha, beta) grid cell and one reference camera frame
(`calibrate_fog`); one grid rate of snow or rain over the clear scans and one reference frame's light
(`calibrate_precipitation`)."""

from __future__ import annotations

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.calibrate.ground import TunedAir, grounded_scans, simulated_ground_statistics
from weatheralign.calibrate.histograms import IntensityHistograms
from weatheralign.calibrate.lidar import CellResult, FogFrames, evaluate_cell
from weatheralign.calibrate.overcast import FrameLight, frame_light
from weatheralign.calibrate.precipitation import simulated_statistics
from weatheralign.config import ParticlesConfig
from weatheralign.lidar.pulse import PulseSensor
from weatheralign.reference import ReferenceDataset
from weatheralign.reference.frames import reference_frame
from weatheralign.sensors import LidarModel


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


@task(name="ground-depth", cache_policy=NO_CACHE, retries=0)
def ground_statistics_task(ds: ReferenceDataset, kind: str, depth_m: float, air: TunedAir) -> np.ndarray:
    """(F,) ground statistic of every clear reference scan under ``kind``'s ground at ``depth_m`` and the tuned
    ``air`` (`weatheralign.calibrate.ground.simulated_ground_statistics`; the worker reads the scans itself)."""
    ids = ds.ids("clear")
    return simulated_ground_statistics([ds.load_scan(i) for i in ids], ids, kind, (depth_m,),
                                       air.lidar.noise_floor, air, air.lidar.intensity_noise_std,
                                       None if air.lidar.floor_range_m is None else air.lidar.floor_scale)[0]


@task(name="precipitation-rate", cache_policy=NO_CACHE, retries=0)
def precipitation_statistics_task(ds: ReferenceDataset, kind: str, rate_mm_h: float, lidar: LidarModel,
                                  particles: ParticlesConfig, ground_depth_m: float) -> np.ndarray:
    """(F,) open-path echo rate of every clear reference scan, its ground under ``kind``'s at ``ground_depth_m`` [m]
    (`grounded_scans`), through ``kind`` at ``rate_mm_h`` (the worker reads the scans itself; each frame's fields are
    seeded from its id)."""
    ids = ds.ids("clear")
    scans = grounded_scans([ds.load_scan(i) for i in ids], ids, kind, ground_depth_m, lidar.noise_floor,
                           lidar.intensity_noise_std, None if lidar.floor_range_m is None else lidar.floor_scale,
                           lidar)
    return simulated_statistics(scans, kind, (rate_mm_h,), lidar, particles, ids)[0]


@task(name="overcast-light", cache_policy=NO_CACHE, retries=0)
def overcast_light_task(ds: ReferenceDataset, sample_id: str) -> FrameLight:
    """The light of one reference frame's stereo-left camera (`weatheralign.calibrate.overcast.frame_light`)."""
    frame, image, range_map = reference_frame(ds, sample_id)
    view = next(iter(frame.cameras.values()))
    return frame_light(image, range_map, view.K, view.T_ego_cam, view.T_global_cam)
