"""The shared weather medium: fog (homogeneous) and snow/rain particle fields in world coordinates.

One medium, observed by every sensor: `FogMedium` gives the LiDAR its (alpha, beta) and the camera its one-way
extinction; `ParticleField` gives every sensor the same particles at its own capture time. `unaligned_seed` derives
an independent field of identical statistics for the "unaligned" ablation.
"""

from weatheralign.medium.distributions import (
    Q_EXT_GEOMETRIC,
    ExponentialSizeDistribution,
    RainSizeDistribution,
    SizeDistribution,
    SnowSizeDistribution,
    gunn_marshall_lambda,
    marshall_palmer_lambda,
    rain_field_fall_speed,
    rain_median_volume_diameter,
    rain_terminal_velocity,
    sekhon_srivastava_lambda,
    snow_equivalent_rain_rate,
    snow_occupancy,
)
from weatheralign.medium.field import ParticleField, Particles, fall_velocity, unaligned_seed
from weatheralign.medium.fog import (
    FogMedium,
    alpha_from_mor,
    default_beta,
    mor_from_alpha,
    paper_beta_grid,
)

__all__ = [
    "Q_EXT_GEOMETRIC",
    "ExponentialSizeDistribution",
    "FogMedium",
    "ParticleField",
    "Particles",
    "RainSizeDistribution",
    "SizeDistribution",
    "SnowSizeDistribution",
    "alpha_from_mor",
    "default_beta",
    "fall_velocity",
    "gunn_marshall_lambda",
    "marshall_palmer_lambda",
    "mor_from_alpha",
    "paper_beta_grid",
    "rain_field_fall_speed",
    "rain_median_volume_diameter",
    "rain_terminal_velocity",
    "sekhon_srivastava_lambda",
    "snow_equivalent_rain_rate",
    "snow_occupancy",
    "unaligned_seed",
]
