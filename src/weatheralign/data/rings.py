"""Velodyne laser elevation tables and ring assignment for scans stored without a ring column.

Ring convention (as in ``LidarScan.points[:, 4]``): ring 0 is the laser with the highest elevation, the index grows
downwards. Elevations are in degrees, positive above the sensor's horizontal plane; the tables are nominal
datasheet values (real units deviate by a few hundredths of a degree and the HDL-64E lasers sit a few cm apart, so
points closer than a few metres may be assigned a neighbouring ring).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from weatheralign.data.errors import DataFormatError


def _read_only(values: NDArray[np.float64]) -> NDArray[np.float64]:
    values.setflags(write=False)
    return values


HDL32E_ELEVATIONS_DEG: NDArray[np.float64] = _read_only(np.linspace(10.67, -30.67, 32))
"""(32,) Velodyne HDL-32E laser elevations [deg], ring 0 = +10.67 down to ring 31 = -30.67 in steps of ~4/3 deg."""

HDL64E_ELEVATIONS_DEG: NDArray[np.float64] = _read_only(
    np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)])
)
"""(64,) Velodyne HDL-64E laser elevations [deg], ring 0 = highest: upper block rings 0..31 from +2.0 to -8.33 in
~1/3 deg steps, lower block rings 32..63 from -8.83 to -24.33 in 0.5 deg steps."""


def elevation_deg(xyz: NDArray) -> NDArray[np.float64]:
    """(N,) elevation ``atan2(z, hypot(x, y))`` in degrees of points ``xyz`` (N, >=3) given in the sensor frame."""
    p = np.asarray(xyz, dtype=np.float64)
    return np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))


def rings_from_elevation(xyz: NDArray, elevations_deg: NDArray) -> NDArray[np.float32]:
    """Assign every point the ring whose table elevation is nearest to the point's elevation.

    Args:
        xyz: (N, 3) points in the LiDAR sensor frame [m] (extra columns beyond the third are ignored).
        elevations_deg: (R,) laser elevation table [deg], e.g. `HDL64E_ELEVATIONS_DEG`; any order, index = ring.

    Returns:
        (N,) float32 ring index in ``0..R-1`` (float, as stored in ``LidarScan.points[:, 4]``).

    Raises:
        DataFormatError: ``xyz`` is not (N, >=3), or the table is empty, not 1-D or not finite.
    """
    table = np.asarray(elevations_deg, dtype=np.float64)
    if table.ndim != 1 or table.size == 0 or not np.all(np.isfinite(table)):
        raise DataFormatError(f"elevation table: expected a non-empty finite (R,) array in degrees, got {table.shape}")
    p = np.asarray(xyz)
    if p.ndim != 2 or p.shape[1] < 3:
        raise DataFormatError(f"rings_from_elevation: expected points of shape (N, 3), got {p.shape}")
    if len(p) == 0:
        return np.zeros(0, dtype=np.float32)
    order = np.argsort(table, kind="stable")
    ascending = table[order]
    elev = elevation_deg(p)
    upper = np.clip(np.searchsorted(ascending, elev), 1, max(len(ascending) - 1, 1))
    lower = upper - 1
    if len(ascending) == 1:
        nearest = np.zeros(len(elev), dtype=np.intp)
    else:
        take_upper = np.abs(ascending[upper] - elev) < np.abs(elev - ascending[lower])
        nearest = np.where(take_upper, upper, lower)
    return order[nearest].astype(np.float32)
