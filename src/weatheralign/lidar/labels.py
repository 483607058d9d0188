"""What the weather did to a LiDAR point or beam: one label set shared by fog (`weatheralign.lidar.fog`) and snow /
rain (`weatheralign.lidar.particles`), stored as uint8 in label arrays.

The same values are the per-beam outcome states of the snow / rain numba kernels, which use the members as
compile-time constants (numba types `IntEnum` members in nopython code).
"""

from __future__ import annotations

from enum import IntEnum


class WeatherLabel(IntEnum):
    """What the weather did to a point (``UNCHANGED`` .. ``LOST``) or a beam (any member)."""

    UNCHANGED = 0
    """Bit-identical to the input (no effect, α = 0, zero intensity, or a new intensity equal in float32)."""
    ATTENUATED = 1
    """Same position, intensity changed (attenuated and/or occluded, or a particle echo merged into the target's)."""
    SCATTERED = 2
    """The echo of the medium (a fog return or a particle): moved along its beam, or clutter on a beam without
    return."""
    LOST = 3
    """The weather pushed the return below the detector noise floor: dropped."""
    NO_ECHO = 4
    """A beam without return that stays empty (nothing detected). Per-beam only: never the label of a point."""
    GROUND = 5
    """Changed by the ground's weather alone (a wet road's film, lying snow: `weatheralign.ground`), not by the air's;
    a label of the simulate stage's scans, never of the air's simulators (not in `POINT_LABELS`)."""


POINT_LABELS: tuple[WeatherLabel, ...] = (WeatherLabel.UNCHANGED, WeatherLabel.ATTENUATED, WeatherLabel.SCATTERED,
                                          WeatherLabel.LOST)
"""The labels an input point can get, in value order (the keys of the results' ``counts``)."""
