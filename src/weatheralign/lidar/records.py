"""Typed records passed to the numba kernels of the LiDAR fog model (`weatheralign.lidar.fog`; the snow / rain
kernels have theirs in `weatheralign.lidar.particles.records`).

Each record is a `typing.NamedTuple` of arrays and scalars: numba compiles them in nopython mode as typed tuples
(``cache=True`` works because the classes are importable), so a kernel takes a handful of named records instead of
dozens of positional arrays. Intensities are on the scan's own scale (0..255 or 0..1).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class FogResponse(NamedTuple):
    """One fog's per-return model (`fog._kernel_params`): the soft-target response on a uniform range grid and the
    detector."""

    r_start: float  # first node of the range grid [m]
    dr: float  # grid step [m]
    g: F64  # (T,) response G of an unobstructed fog at the nodes [s/m²] (`fog.SoftTargetResponse`)
    r_peak: float  # where G peaks [m]
    g_peak: float  # its peak [s/m²]
    alpha: float  # extinction [1/m]
    soft_gain: float  # β / β_0: the fog's backscatter over the hard target's
    saturation: float  # largest intensity the detector reports
    floor: float  # detector noise floor (at the floor's reference range, if any), < 0 for none
    noise_std: float  # intensity noise std of a new reading (at the same range: it scales with the floor)
    noise_rel: float  # and its part proportional to the reading
    full_scale: float  # the scale's maximum intensity (255 or 1): readings are clipped to [0, full_scale]
    r_ref: float  # the sensor's range compensation g(R) = min(1, (r_ref / R)^falloff) (`IntensityModel`)
    falloff: float
    comp_ref: float  # r_f² g(r_f) of the floor's reference range [m²]; 0: a constant floor (`DetectorFloor`)


class FogEchoRange(NamedTuple):
    """Where the receiver reports a fog echo (`fog._reported_range`)."""

    half_length: float  # c τ_H / 2 between the pulse's start and its peak [m]
    range_sigma: float  # range noise std of a new echo [m], clipped at ±2 σ
    r1: float  # nothing is reported nearer than the receiver's blind zone [m]
    max_range: float  # the sensor's maximum range [m]
