"""LiDAR observation of the weather medium: the shared pulse model, fog (`simulate_fog`) and snow / rain
(`simulate_particles`), each one call on a `LidarScan`."""

from weatheralign.lidar.beams import Beams, beams_from_scan
from weatheralign.lidar.fog import (
    REFERENCE_CODE_BETA,
    FogLabel,
    FogResult,
    SoftTargetResponse,
    beam_origins_fast,
    fog_intensities,
    fog_point_arrays,
    simulate_fog,
    soft_target_response,
)
from weatheralign.lidar.particles import ParticleLabel, ParticleResult, simulate_particles
from weatheralign.lidar.pulse import PulseSensor, c_a_p0_from_intensity, hard_target_power, overlap

__all__ = [
    "Beams",
    "ParticleLabel",
    "ParticleResult",
    "beams_from_scan",
    "simulate_particles",
    "REFERENCE_CODE_BETA",
    "FogLabel",
    "FogResult",
    "PulseSensor",
    "SoftTargetResponse",
    "beam_origins_fast",
    "c_a_p0_from_intensity",
    "fog_intensities",
    "fog_point_arrays",
    "hard_target_power",
    "overlap",
    "simulate_fog",
    "soft_target_response",
]
