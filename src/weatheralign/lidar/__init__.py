"""LiDAR observation of the weather medium: the shared pulse model and fog (snow and rain build on `pulse`)."""

from weatheralign.lidar.fog import (
    REFERENCE_CODE_BETA,
    FogLabel,
    FogResult,
    SoftTargetResponse,
    alpha_from_mor,
    beam_origins_fast,
    default_beta,
    fog_intensities,
    fog_point_arrays,
    mor_from_alpha,
    simulate_fog,
    soft_target_response,
)
from weatheralign.lidar.pulse import PulseSensor, c_a_p0_from_intensity, hard_target_power, overlap

__all__ = [
    "REFERENCE_CODE_BETA",
    "FogLabel",
    "FogResult",
    "PulseSensor",
    "SoftTargetResponse",
    "alpha_from_mor",
    "beam_origins_fast",
    "c_a_p0_from_intensity",
    "default_beta",
    "fog_intensities",
    "fog_point_arrays",
    "hard_target_power",
    "mor_from_alpha",
    "overlap",
    "simulate_fog",
    "soft_target_response",
]
