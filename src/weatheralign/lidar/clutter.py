"""Weather clutter in a LiDAR scan, measured on the points alone (real or simulated, no labels needed).

Snowflakes and raindrops come back as isolated returns: a surface lights up neighbouring beams at neighbouring ranges,
a particle lights one beam. `isolated_mask` marks (`isolated_returns` counts), within ``max_range`` of the sensor, the
returns whose nearest other return is farther than the dynamic radius ``max(min_radius, factor · r · azimuth_step)`` —
the test of the dynamic radius outlier removal filter (DROR, Charron et al. 2018, the usual snow de-noiser) with one
neighbour. The radius grows with range because the beams spread: ``r · azimuth_step`` is the spacing of a ring's points
at range ``r``. On the synthetic reference (HDL-64-like, 1800 azimuths): clear scans ~4 per scan, rain at ~80 mm/h ~130,
snow at ~3 mm/h ~3800.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree


def isolated_mask(xyz: ArrayLike, *, azimuth_step_rad: float, max_range: float = 20.0, min_radius: float = 0.3,
                  factor: float = 3.0) -> NDArray[np.bool_]:
    """(N,) True for the returns within ``max_range`` [m] of the sensor (the origin of ``xyz`` (N, 3) [m]) whose
    nearest other return lies farther than ``max(min_radius, factor · r · azimuth_step_rad)`` [m] (r: the return's
    range).

    Raises:
        ValueError: ``xyz`` is not (N, 3) finite, or a parameter is not positive.
    """
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"isolated_returns: xyz must be (N, 3) finite coordinates [m], got shape {pts.shape}")
    for name, value in (("azimuth_step_rad", azimuth_step_rad), ("max_range", max_range),
                        ("min_radius", min_radius), ("factor", factor)):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"isolated_returns: {name} = {value!r}; expected a finite value > 0")
    mask = np.zeros(len(pts), dtype=bool)
    r = np.linalg.norm(pts, axis=1)
    near = np.flatnonzero(r < max_range)
    if len(near) == 0 or len(pts) == 1:
        mask[near] = True
        return mask
    distance, _ = cKDTree(pts).query(pts[near], k=2)
    radius = np.maximum(min_radius, factor * r[near] * azimuth_step_rad)
    mask[near[distance[:, 1] > radius]] = True
    return mask


def isolated_returns(xyz: ArrayLike, *, azimuth_step_rad: float, max_range: float = 20.0, min_radius: float = 0.3,
                     factor: float = 3.0) -> int:
    """Number of `isolated_mask` returns of ``xyz`` (N, 3) [m].

    Raises:
        ValueError: ``xyz`` is not (N, 3) finite, or a parameter is not positive.
    """
    return int(np.count_nonzero(isolated_mask(xyz, azimuth_step_rad=azimuth_step_rad, max_range=max_range,
                                              min_radius=min_radius, factor=factor)))
