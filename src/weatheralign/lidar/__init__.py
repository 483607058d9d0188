"""LiDAR observation of the weather medium: the shared pulse model, fog (`simulate_fog`) and snow / rain (alone or
inside fog: `simulate_particles`; a keyframe and its sweeps together: `simulate_particle_scans`), each one call on a
`LidarScan` with the sensor's `weatheralign.sensors.LidarModel` (its description, `PulseSensor` and `IntensityModel`
included, lives in `weatheralign.sensors`)."""

from weatheralign.lidar.beams import Beams, beam_origins, beams_from_scan
from weatheralign.lidar.fog import (
    REFERENCE_CODE_BETA,
    FogLabel,
    FogResult,
    SoftTargetResponse,
    fog_intensities,
    fog_point_arrays,
    simulate_fog,
    soft_target_response,
)
from weatheralign.lidar.labels import WeatherLabel
from weatheralign.lidar.particles import ParticleLabel, ParticleResult, simulate_particle_scans, simulate_particles
from weatheralign.lidar.pulse import c_a_p0_from_intensity, hard_target_power, overlap

__all__ = [
    "Beams",
    "ParticleLabel",
    "ParticleResult",
    "beams_from_scan",
    "simulate_particle_scans",
    "simulate_particles",
    "REFERENCE_CODE_BETA",
    "FogLabel",
    "FogResult",
    "SoftTargetResponse",
    "WeatherLabel",
    "beam_origins",
    "c_a_p0_from_intensity",
    "fog_intensities",
    "fog_point_arrays",
    "hard_target_power",
    "overlap",
    "simulate_fog",
    "soft_target_response",
]
