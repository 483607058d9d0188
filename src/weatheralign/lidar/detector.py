"""The detector floor inside the numba kernels (`weatheralign.sensors.LidarModel.detector`).

A real receiver detects on the received raw power and reports that power times its range compensation at the range
it measured (``docs/physics.md`` section 3.5), so on the reported scale its floor grows with the reported range ``R``
as ``R² g(R)``; a constant floor on the reported scale is the case ``comp_ref = 0``. The scalar here is the kernels'
form of `LidarModel.floor_scale` (the tests check they agree).
"""

from __future__ import annotations

from numba import njit


@njit(nogil=True, cache=True, inline="always")
def compensation(r, r_ref, falloff):  # pragma: no cover
    """``R² g(R)`` [m²] at range ``r`` [m], ``g(R) = min(1, (r_ref / R)^falloff)`` (the scalar form of
    `IntensityModel.compensation`): a raw power times it is the reported value, up to the sensor's scale."""
    r = max(r, 1e-9)
    return r * r * min(1.0, (r_ref / r) ** falloff)


@njit(nogil=True, cache=True, inline="always")
def floor_scale(r, r_ref, falloff, comp_ref):  # pragma: no cover
    """``floor(R) / floor`` at reported range ``r`` [m] (the fields of a `DetectorFloor`): 1 for a constant floor
    (``comp_ref`` 0), else ``R² g(R) / comp_ref`` (the scalar form of `LidarModel.floor_scale`)."""
    if comp_ref <= 0.0:
        return 1.0
    return compensation(r, r_ref, falloff) / comp_ref
