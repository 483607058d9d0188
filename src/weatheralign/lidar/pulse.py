"""The LiDAR pulse model shared by fog, snow and rain (Rasshofer et al. 2011, as used by Hahner et al. 2021/2022).

Received power ``P_R(R) = C_A ∫_0^{2R/c} P_T(t) H(R - ct/2) dt`` with the pulse ``P_T(t) = P_0 sin²(π t / (2 τ_H))`` on
``0 <= t <= 2 τ_H`` and the channel ``H_C(r) = ξ(r) / r² · exp(-2 α r)``. ``R = c t / 2`` is the range coordinate of the
receiver's time axis (time since the start of the emitted pulse). See ``docs/physics.md`` section 1.

Unit convention: the closed-form hard-target response below is the published one (Hahner et al.): a target of
reflectivity ``β_0`` at ``R_0`` gives ``C_A P_0 β_0 ξ(R_0) / R_0² sin²(π (R - R_0) / (c τ_H))``, i.e. without the
``2 / c`` Jacobian of a delta target. The fog code and its published crossover ranges use the same convention, so the
unknown ``C_A P_0`` recovered from a clear measurement (`c_a_p0_from_intensity`) turns every weather effect into
intensity units consistently.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from weatheralign.sensors import SPEED_OF_LIGHT, PulseSensor  # noqa: F401  (the sensor description lives there)

F64 = NDArray[np.float64]


def overlap(r: ArrayLike, sensor: PulseSensor) -> F64:
    """Overlap ξ(r) (same shape as ``r``): 0 for ``r <= r1``, 1 for ``r >= r2``, linear in between. ``r`` in m."""
    r = np.asarray(r, dtype=np.float64)
    return np.clip((r - sensor.r1) / (sensor.r2 - sensor.r1), 0.0, 1.0)


def hard_target_power(
    r: ArrayLike,
    r0: ArrayLike,
    sensor: PulseSensor,
    *,
    beta_ratio: ArrayLike = 1.0,
    alpha: float = 0.0,
    c_a_p0: ArrayLike = 1.0,
) -> F64:
    """Closed-form received power of a hard target at ``r0`` on the receiver's range axis ``r`` (broadcast).

    ``P_R(R) = C_A P_0 · β_0 · beta_ratio · ξ(R_0) / R_0² · sin²(π (R - R_0) / (c τ_H)) · exp(-2 α R_0)`` for
    ``R_0 <= R <= R_0 + c τ_H``, else 0; the peak is at ``R = R_0 + c τ_H / 2``.

    Args:
        r: receiver range coordinate(s) ``c t / 2`` [m].
        r0: target range(s) [m], > 0.
        sensor: pulse and overlap parameters.
        beta_ratio: target reflectivity relative to ``β_0`` (for particles: reflectivity × occluded beam share).
        alpha: extinction of the medium in front of the target [1/m] (two-way attenuation).
        c_a_p0: the system constant ``C_A P_0`` (per point, see `c_a_p0_from_intensity`); 1 gives ``P / (C_A P_0)``.

    Returns:
        Received power, broadcast shape of the inputs, in units of ``c_a_p0`` × 1/(m² sr).
    """
    r = np.asarray(r, dtype=np.float64)
    r0 = np.asarray(r0, dtype=np.float64)
    length = sensor.pulse_length
    x = r - r0
    inside = (x >= 0.0) & (x <= length)
    with np.errstate(divide="ignore", invalid="ignore"):
        peak = sensor.beta_0 * np.asarray(beta_ratio) * overlap(r0, sensor) / (r0 * r0) * np.exp(-2.0 * alpha * r0)
    shape = np.sin(np.pi * x / length) ** 2
    return np.where(inside, np.asarray(c_a_p0) * peak * shape, 0.0)


def c_a_p0_from_intensity(i0: ArrayLike, r0: ArrayLike, sensor: PulseSensor) -> F64:
    """``C_A P_0 = i_0 R_0² / β_0`` (broadcast): the system constant that makes the clear hard-target peak equal the
    measured intensity ``i0`` (0..255 scale) at range ``r0`` [m] (ξ = 1 assumed, as in the published model)."""
    r0 = np.asarray(r0, dtype=np.float64)
    return np.asarray(i0, dtype=np.float64) * r0 * r0 / sensor.beta_0
