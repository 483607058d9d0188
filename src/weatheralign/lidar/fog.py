"""LiDAR fog (Hahner et al., ICCV 2021) for any extinction α, vectorised.

Model (``docs/physics.md`` section 2.2). A homogeneous fog of extinction α [1/m] and backscatter β [1/(m sr)]
attenuates every hard-target return two-way, ``i_hard = exp(-2 α R_0) i_0``, and returns a soft-target echo of its own:

    P_soft(R) / (C_A P_0 β) = ∫_0^{2τ_H} sin²(π t / 2τ_H) · exp(-2α r) ξ(r) / r² · U(R_0 - r) dt,   r = R - c t / 2.

Its maximum over the receiver's range axis ``R <= R_0`` (the published table generator searches only there) is the
fog response ``I(R_0)`` [s/m²] at ``R_fog``. The receiver reports the stronger echo, compared on raw power in units
of the target's clear reading: the fog's ``I(R_0) i_0 R_0² β / β_0`` against ``i_hard``. If the fog's is larger the
point becomes a fog return along its ray, reported at ``R_e = R_fog - c τ_H / 2`` (below) through the sensor's range
compensation there: ``i_soft = min(I(R_0) i_0 β / β_0 · R_e² g(R_e) / g(R_0), saturation)`` with ``g`` the
`IntensityModel` gain (Hahner's published form, without the last factor, is that of a raw-power sensor,
``g = (1 m / R)²``, and reports the echo of a range-compensating sensor ``R_0² g(R_0) / (R_e² g(R_e))`` times too
bright: about 150x for a 40 m target of the reference's ``min(1, 10 m / R)``); else it keeps its position with
``i_hard``. With a raw-power detector (`LidarModel.floor_range_m`) the floor and the constant part of the noise are
those at each reading's reported range. A sensor with intensity noise (``LidarModel.intensity_noise_std`` σ_0 and
``intensity_noise_rel``) reads each changed return again: a fog echo is a new reading (std
``sqrt(σ_0² + (rel · i_soft)²)``); an attenuated target's
``i_0`` already carries its clear reading's noise, scaled by ``T² = exp(-2 α R_0)``, and lacks ``σ_0² (1 - T⁴)`` of
the fogged reading's variance (the proportional part scales exactly), which is added - without it the returns near the
detector floor are cut too sharply (on the synthetic reference this biased α* up and doubled the KS distance of light
fog). The floor then decides on the reading. Normals come from each beam's noise stream (`point_noise_keys`). ``R_fog``
is the peak on the receiver axis ``R = c t / 2`` as in physics.md (about 4.6 m for α = 0.06), not shifted by the ``c τ_H
/ 2`` between pulse start and pulse peak.

How ``I(R_0)`` is computed for any α (no tables snapped to 9 values): for ``R <= R_0`` every scatterer ``r <= R``
lies in front of the target, so ``U`` is 1 and the integrand does not depend on ``R_0``:
``I(R_0) = max_{R <= R_0} G(R)`` with ``G`` the response of an unobstructed fog, ``G(R) = (2/c) (k * h)(R)``, the
convolution of the log-concave pulse ``k(s) = sin²(π s / (c τ_H))`` on ``[0, c τ_H]`` with the unimodal
``h(r) = exp(-2αr) ξ(r) / r²`` (log-concave on the ξ ramp, decreasing after it, for every α >= 0). A convolution
of a log-concave with a unimodal function is unimodal (Ibragimov), so with ``R*`` the peak of ``G``: ``R_fog = min(R_0,
R*)``, ``I(R_0) = G(min(R_0, R*))``. ``G`` is evaluated once per α on a 5 mm grid that has ``r1`` and ``r2`` (the kinks
of ξ) on nodes, by a discrete convolution (trapezoid rule), over ``[r1, r2 + c τ_H]`` (beyond it ``h`` is decreasing on
the whole window, so ``G`` is too), and ``R*`` is refined by a parabola through the three nodes around the maximum: a
cost paid once per α, not per point. The per-point part (range from the beam origin, interpolation on the uniform grid,
comparison, new point) is one fused numba loop.

Traps of the published code, fixed here:
- intensity scale: the model is homogeneous of degree 1 in intensity; it is evaluated in the scan's own units with the
  saturation and the noise floor converted from the 0..255 scale, and nothing is rounded (the published code rounds
  ``i_hard`` to integers, which zeroes 0..1 intensities and turns almost every KITTI point into fog);
- one range convention for every echo: the receiver is calibrated on hard targets (whose power peaks at
  ``R_0 + c τ_H / 2`` and which it reports at ``R_0``), so a fog echo is reported at its power peak minus ``c τ_H / 2``
  too (≈ 1.64 m for α = 0.06, not the published code's raw 4.64 m), with the sensor's Gaussian range noise
  (``LidarModel.range_noise_std_m``, clipped at ±2σ, from each beam's own counter-based stream, as the particle echoes
  get it): no perfect shell, never inside the receiver's blind zone (``r1``), beyond the target or the maximum range;
- β is an explicit argument (the published parameter object keeps β = 0.046 / MOR(α = 0.06) = 9.21e-4 whatever α);
- an optional detector noise floor drops returns that the weather pushed below it (label LOST), decided on the value
  an integer reading stood for before the sensor rounded it (`weatheralign.lidar.quantum`: a reading of 1 at a floor
  of 1 stood for a value in ``[1, 1.5)`` and is not lost to any fog).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from weatheralign.data.frame import LidarScan
from weatheralign.lidar.beams import beam_origins, point_noise_keys, point_ranges
from weatheralign.lidar.labels import POINT_LABELS, WeatherLabel
from weatheralign.lidar.pulse import SPEED_OF_LIGHT, PulseSensor, overlap
from weatheralign.lidar.quantum import on_scale, scan_clear_readings
from weatheralign.lidar.records import FogEchoRange, FogResponse
from weatheralign.medium.field import normal_pair
from weatheralign.medium.fog import DEFAULT_BETA_MOR, LN20
from weatheralign.sensors import compensation_at, floor_factor

if TYPE_CHECKING:
    from weatheralign.sensors import IntensityModel, LidarModel

F64 = NDArray[np.float64]


REFERENCE_CODE_BETA = DEFAULT_BETA_MOR * 0.06 / LN20
"""β = 9.21e-4 /(m sr): what the published code actually uses for every α (computed from its default α = 0.06)."""

TABLE_STEP_M = 0.005
"""Target grid step [m] of the per-α response table."""


FogLabel = WeatherLabel
"""What fog did to a point: the shared `WeatherLabel` (one enum for fog, snow and rain). UNCHANGED: bit-identical to
the input (α = 0, or zero intensity); ATTENUATED: same position, intensity ``exp(-2 α R_0) i_0``; SCATTERED: replaced
by the fog return at ``R_fog`` on its ray; LOST: the weather pushed the return below the detector noise floor
(dropped). NO_ECHO (beams without return) does not occur in the fog model."""


def _check_medium(alpha: float, beta: float) -> None:
    if not (math.isfinite(alpha) and alpha >= 0.0):
        raise ValueError(f"fog: alpha = {alpha!r}; expected a finite extinction >= 0 [1/m]")
    if not (math.isfinite(beta) and beta >= 0.0):
        raise ValueError(f"fog: beta = {beta!r}; expected a finite backscatter >= 0 [1/(m sr)]")


# ------------------------------------------------------------------------------------------- soft-target response


@dataclass(frozen=True)
class SoftTargetResponse:
    """The fog response of one extinction α: ``I(R_0)`` [s/m²] and ``R_fog`` [m] for any target range.

    Attributes:
        alpha: extinction [1/m].
        r_grid: (K,) receiver ranges [m], uniform from ``sensor.r1``.
        g: (K,) ``G(R) = P_soft(R) / (C_A P_0 β)`` of an unobstructed fog at ``r_grid`` [s/m²].
        r_peak: ``R*`` [m], the maximum of ``G`` (refined between nodes).
        g_peak: ``G(R*)`` [s/m²].
    """

    alpha: float
    r_grid: F64
    g: F64
    r_peak: float
    g_peak: float

    def __call__(self, r0: ArrayLike) -> tuple[F64, F64]:
        """``(I(R_0), R_fog)`` for target ranges ``r0`` (any shape) [m]: ``R_fog = min(R_0, R*)``, and
        ``I = G(R_fog)`` (0 where ``R_0 <= r1``: no overlap, no fog echo)."""
        r0 = np.asarray(r0, dtype=np.float64)
        r_fog = np.minimum(r0, self.r_peak)
        value = np.interp(r_fog, self.r_grid, self.g, left=0.0)
        value = np.where(r0 >= self.r_peak, self.g_peak, np.minimum(value, self.g_peak))
        return value, r_fog


def soft_target_response(
    alpha: float, sensor: PulseSensor, *, step: float = TABLE_STEP_M
) -> SoftTargetResponse:
    """Tabulate the fog response of extinction ``alpha`` [1/m] on a grid of ``step`` (default 5 mm), once per α.

    Raises:
        ValueError: ``alpha`` negative or not finite, or ``step`` not in (0, 0.1] m.
    """
    _check_medium(alpha, 0.0)
    if not 0.0 < step <= 0.1:
        raise ValueError(f"soft_target_response: step = {step!r}; expected 0 < step <= 0.1 m")
    length = sensor.pulse_length
    ramp = sensor.r2 - sensor.r1
    dr = ramp / math.ceil(ramp / step)  # r1 and r2 (the kinks of ξ) fall on nodes
    n = int(math.ceil((ramp + length) / dr)) + 3
    r = sensor.r1 + dr * np.arange(n)
    h = np.exp(-2.0 * alpha * r) * overlap(r, sensor) / (r * r)
    s = dr * np.arange(int(math.floor(length / dr)) + 1)
    k = np.sin(np.pi * s / length) ** 2  # zero with zero slope at both ends: the plain sum is the trapezoid rule
    g = np.convolve(h, k)[:n] * (dr * 2.0 / SPEED_OF_LIGHT)
    j = int(np.argmax(g))
    r_peak, g_peak = float(r[j]), float(g[j])
    if 0 < j < n - 1:
        a, b, c = g[j - 1], g[j], g[j + 1]
        curv = a - 2.0 * b + c
        if curv < 0.0:
            shift = 0.5 * (a - c) / curv
            r_peak = float(r[j] + shift * dr)
            g_peak = float(b - 0.25 * (a - c) * shift)
    for arr in (r, g):
        arr.setflags(write=False)
    return SoftTargetResponse(alpha=float(alpha), r_grid=r, g=g, r_peak=r_peak, g_peak=g_peak)


# ------------------------------------------------------------------------------------------------ per-point model


@dataclass(frozen=True)
class FogIntensities:
    """Per-point fog outcome without geometry.

    Attributes:
        intensity: (N,) float64 output intensity, in the input's units (LOST points: the undetected value).
        labels: (N,) uint8 `FogLabel` values.
        r_fog: (N,) float64 receiver-axis range [m] of each point's fog-echo power peak (meaningful where SCATTERED);
            the sensor reports it at ``r_fog - c τ_H / 2`` (`fog_point_arrays`).
    """

    intensity: F64
    labels: NDArray[np.uint8]
    r_fog: F64


def fog_intensities(
    r0: ArrayLike,
    i0: ArrayLike,
    alpha: float,
    beta: float,
    *,
    intensity_max: float = 255.0,
    sensor: PulseSensor,
    noise_floor: float | None,
    response: SoftTargetResponse | None = None,
    noise_std: float = 0.0,
    noise_rel: float = 0.0,
    noise_normals: ArrayLike | None = None,
    clear_values: ArrayLike | None = None,
    intensity: IntensityModel,
    floor_range_m: float | None = None,
) -> FogIntensities:
    """Hard attenuation vs fog echo for points at ranges ``r0`` (N,) [m] with clear intensities ``i0`` (N,).

    Args:
        r0: range of each point from its beam origin [m].
        i0: clear intensity on ``0..intensity_max`` (compared as float32, the point-cloud dtype).
        alpha, beta: extinction [1/m] and backscatter [1/(m sr)].
        intensity_max: the intensity scale of ``i0`` (255 or 1); the sensor saturation and the noise floor, given on
            the 0..255 scale, are converted to it, so a 0..1 scan behaves exactly like the same scan on 0..255.
        noise_floor: detector floor on the 0..255 scale, or None. A return is LOST when its output intensity is below
            the floor and (as float32) below its clear intensity: points already under the floor in clear weather were
            detected nevertheless, so only a return the weather weakened further is dropped.
        response: a precomputed `soft_target_response` of this ``alpha`` (e.g. when sweeping β), or None.
        noise_std, noise_rel: the detector's intensity noise (`weatheralign.sensors.LidarModel.intensity_noise_std`
            on the 0..255 scale, ``intensity_noise_rel``); 0, 0: a noise-free reading. A fog echo is a new reading:
            Gaussian noise of std ``sqrt(noise_std² + (noise_rel · i_soft)²)``. An attenuated target's clear
            intensity carries its clear reading's noise, scaled by the two-way transmission ``T² = exp(-2 α R_0)``;
            the reading in fog lacks the variance ``noise_std² (1 - T⁴)`` (the signal-proportional part scales
            exactly), which is added. Readings are clipped to ``[0, intensity_max]`` before the floor decides.
        noise_normals: (N,) the standard normal of each point's reading (`intensity_normals` of its beam's
            `point_noise_keys`, as `simulate_fog` draws it); required when a noise is on.
        clear_values: (N,) on ``0..intensity_max``, the clear value each ``i0`` stood for before the sensor rounded
            it (`weatheralign.lidar.quantum.scan_clear_readings`, as `simulate_fog` finds them): whether an
            attenuated return fell under the floor is decided on ``clear_values · T²`` (plus its noise), so a
            reading at the floor is not lost to any fog; None: every ``i0`` as read.
        intensity: the sensor's `IntensityModel`: a fog echo is reported through its range compensation at the
            echo's noise-free reported range ``R_fog - c τ_H / 2`` (Hahner's form ``I(R_0) i_0 R_0² β / β_0`` is the
            raw-power sensor's, `HAHNER_INTENSITY`).
        floor_range_m: the detector floor's reference range (`LidarModel.floor_range_m`), or None: a constant
            floor.

    Returns:
        `FogIntensities`. The label of a non-scattered point is UNCHANGED when its float32 intensity is bit-identical
        to the input's, else ATTENUATED.
    """
    params = _kernel_params(alpha, beta, intensity_max, sensor, noise_floor, response, noise_std, noise_rel,
                            intensity=intensity, floor_range_m=floor_range_m)
    r0 = np.ascontiguousarray(r0, dtype=np.float64).ravel()
    i0 = np.ascontiguousarray(i0, dtype=np.float32).ravel()
    if r0.shape != i0.shape:
        raise ValueError(f"fog_intensities: r0 {r0.shape} and i0 {i0.shape} differ")
    if noise_std > 0.0 or noise_rel > 0.0:
        if noise_normals is None or np.shape(noise_normals) != r0.shape:
            raise ValueError(f"fog_intensities: intensity noise needs noise_normals of shape {r0.shape} "
                             f"(intensity_normals), got {None if noise_normals is None else np.shape(noise_normals)}")
        normals = np.ascontiguousarray(noise_normals, dtype=np.float64)
    else:
        normals = np.zeros(0)
    labels = np.empty(len(r0), dtype=np.uint8)
    r_fog = np.empty(len(r0))
    echo = FogEchoRange(sensor.pulse_length / 2.0, 0.0, float(sensor.r1), float(sensor.max_range))
    out = np.empty(len(r0))
    _intensity_kernel(r0, i0, _clear_values(clear_values, len(r0)), params, echo, normals, out, labels, r_fog)
    return FogIntensities(intensity=out, labels=labels, r_fog=r_fog)


def _kernel_params(
    alpha: float,
    beta: float,
    intensity_max: float,
    sensor: PulseSensor,
    noise_floor: float | None,
    response: SoftTargetResponse | None,
    noise_std: float = 0.0,
    noise_rel: float = 0.0,
    *,
    intensity: IntensityModel,
    floor_range_m: float | None = None,
) -> FogResponse:
    """The per-return model the numba kernels share, validated (the saturation, floor and noise std given on the
    0..255 scale converted to the scan's; the floor and the noise std at ``floor_range_m`` when given, see
    `weatheralign.sensors.LidarModel.floor_range_m`)."""
    _check_medium(alpha, beta)
    if intensity_max not in (1.0, 255.0):
        raise ValueError(f"fog: intensity_max must be 1.0 or 255.0, got {intensity_max!r}")
    if noise_floor is not None and not (math.isfinite(noise_floor) and noise_floor >= 0.0):
        raise ValueError(f"fog: noise_floor = {noise_floor!r}; expected None or a finite value >= 0 (0..255 scale)")
    for name, value in (("intensity noise std", noise_std), ("intensity noise rel", noise_rel)):
        if not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f"fog: {name} = {value!r}; expected a finite value >= 0")
    if response is None:
        response = soft_target_response(alpha, sensor)
    elif response.alpha != alpha:
        raise ValueError(f"fog: response is for alpha = {response.alpha}, not {alpha}")
    grid = response.r_grid
    scale = intensity_max / 255.0
    saturation = sensor.saturation * scale
    floor = -1.0 if noise_floor is None else noise_floor * scale
    if floor_range_m is not None and not (math.isfinite(floor_range_m) and floor_range_m > 0.0):
        raise ValueError(f"fog: floor_range_m = {floor_range_m!r}; expected None or a finite range > 0 m")
    comp_ref = 0.0 if floor_range_m is None else float(intensity.compensation(floor_range_m))
    return FogResponse(float(grid[0]), float(grid[1] - grid[0]), response.g, response.r_peak, response.g_peak,
                       float(alpha), float(beta) / sensor.beta_0, saturation, floor, float(noise_std) * scale,
                       float(noise_rel), float(intensity_max), float(intensity.r_ref), float(intensity.falloff),
                       comp_ref)


def _clear_values(clear_values: ArrayLike | None, n: int) -> F64:
    """The clear values as the kernels take them: (n,) float64, or (0,) for every intensity as read.

    Raises:
        ValueError: ``clear_values`` given and not (n,).
    """
    if clear_values is None:
        return np.zeros(0)
    if np.shape(clear_values) != (n,):
        raise ValueError(f"fog: clear_values must be of shape ({n},), got {np.shape(clear_values)}")
    return np.ascontiguousarray(clear_values, dtype=np.float64)


def _noise_keys(noise_keys: NDArray | None, n: int, needed: bool) -> NDArray[np.uint64]:
    """The beams' noise streams as the kernels take them: (n,) uint64 when a noise is on, else (0,).

    Raises:
        ValueError: a noise is on and ``noise_keys`` is not (n,).
    """
    if not needed:
        return np.zeros(0, dtype=np.uint64)
    if noise_keys is None or np.shape(noise_keys) != (n,):
        raise ValueError(f"fog: detector noise needs noise_keys of shape ({n},) (detector_noise_keys), got "
                         f"{None if noise_keys is None else np.shape(noise_keys)}")
    return np.ascontiguousarray(noise_keys, dtype=np.uint64)


@njit(cache=True, nogil=True)
def _fog_peak(r0, model):  # pragma: no cover
    """``(I(R_0), R_fog)`` of a target at ``r0`` [m] under the `FogResponse` ``model`` (`SoftTargetResponse`'s scalar
    form: the response interpolated on its grid, capped at its peak)."""
    r_start, dr, g, r_peak, g_peak = model.r_start, model.dr, model.g, model.r_peak, model.g_peak
    if r0 >= r_peak:
        return g_peak, r_peak
    pos = (r0 - r_start) / dr
    if pos <= 0.0:
        return 0.0, r0
    j = int(pos)
    if j >= len(g) - 1:
        integral = g[len(g) - 1]
    else:
        integral = g[j] + (pos - j) * (g[j + 1] - g[j])
    return min(integral, g_peak), r0


@njit(cache=True, nogil=True)
def _fog_one(r0, i0, clear, model, z, integral, r_echo):  # pragma: no cover
    """(intensity, label) of one return at range ``r0`` [m] with clear intensity ``i0`` (float32) under the
    `FogResponse` ``model`` (float64): ``integral`` its `_fog_peak` response, ``r_echo`` [m] the range the receiver
    would report its fog echo at without noise (`_echo_range`), ``z`` the standard normal of its intensity reading,
    ``clear`` (float64) the clear value the rounded ``i0`` stood for, which decides whether the attenuated target
    fell under the floor (`weatheralign.lidar.quantum`; ``i0`` itself when unrounded).

    Which echo the receiver reports is decided on raw power, in units of the target's clear reading: the fog's
    ``I(R_0) i_0 R_0² β / β_0`` against the target's ``T² i_0``. A fog echo is reported through the sensor's range
    compensation at its own range, ``× R_e² g(R_e) / (R_0² g(R_0))`` (Hahner's raw-power sensor: 1); the floor and the
    constant part of the noise of each reading are those at its reported range."""
    alpha, soft_gain, saturation, floor = model.alpha, model.soft_gain, model.saturation, model.floor
    noise_std, noise_rel, full_scale = model.noise_std, model.noise_rel, model.full_scale
    r_ref, falloff, comp_ref = model.r_ref, model.falloff, model.comp_ref
    i0_64 = np.float64(i0)
    two_way = math.exp(-2.0 * alpha * r0)
    i_hard = two_way * i0_64
    soft_raw = integral * i0_64 * r0 * r0 * soft_gain
    if soft_raw > i_hard:
        label = 2
        scale_here = floor_factor(r_echo, r_ref, falloff, comp_ref)
        out = min(soft_raw * compensation_at(r_echo, r_ref, falloff) / compensation_at(r0, r_ref, falloff), saturation)
        std = math.sqrt((noise_std * scale_here) ** 2 + (noise_rel * out) ** 2)
    else:
        scale_here = floor_factor(r0, r_ref, falloff, comp_ref)
        out = i_hard
        label = 0 if np.float32(i_hard) == i0 else 1
        std = noise_std * scale_here * math.sqrt(max(1.0 - two_way * two_way, 0.0))
    if label != 0 and std > 0.0:
        out = min(max(out + std * z, 0.0), full_scale)
    seen, ref = out, i0_64
    if label == 1:  # the attenuated target: its clear value carried through the two-way transmission
        seen, ref = out + (clear - i0_64) * two_way, clear
    if label != 0 and floor >= 0.0 and seen < floor * scale_here and np.float32(seen) < np.float32(ref):
        label = 3
    return out, label


@njit(cache=True, nogil=True)
def _intensity_kernel(r0, i0, clear, model, echo, normals, intensity, labels, r_fog):  # pragma: no cover
    """`_fog_one` of every return (``clear`` (N,) or (0,): each ``i0`` as read; ``normals`` (N,) or (0,):
    noise-free; a fog echo reported at ``echo``'s noise-free range) into ``intensity``, ``labels``, ``r_fog``."""
    noisy = normals.shape[0] > 0
    rounded = clear.shape[0] > 0
    for n in range(len(r0)):
        x = clear[n] if rounded else np.float64(i0[n])
        integral, r_fog[n] = _fog_peak(r0[n], model)
        r_echo = _echo_range(r_fog[n], r0[n], echo)
        intensity[n], labels[n] = _fog_one(r0[n], i0[n], x, model, normals[n] if noisy else 0.0, integral, r_echo)


@njit(cache=True, nogil=True)
def _normals_kernel(keys, out):  # pragma: no cover
    for n in range(len(keys)):
        out[n, 0], out[n, 1] = normal_pair(keys[n])


def reading_normals(noise_keys: ArrayLike) -> F64:
    """(N, 2) the standard normals of each beam's reading from its noise stream ``noise_keys`` (N,): intensity, range
    (`normal_pair`, as every weather echo draws them)."""
    keys = np.ascontiguousarray(noise_keys, dtype=np.uint64).ravel()
    out = np.empty((len(keys), 2))
    _normals_kernel(keys, out)
    return out


def intensity_normals(noise_keys: ArrayLike) -> F64:
    """(N,) the standard normal of each beam's intensity reading (`reading_normals`' first, as `simulate_fog` draws
    it): `fog_intensities`' ``noise_normals``."""
    return np.ascontiguousarray(reading_normals(noise_keys)[:, 0])


@njit(cache=True, nogil=True)
def _echo_range(r_fog, r0, echo):  # pragma: no cover
    """The noise-free range [m] of a fog echo whose power peaks at ``r_fog``: ``r_fog - c τ_H / 2`` inside ``[r1,
    min(r0, max_range)]``; the range the sensor's compensation is applied at (its range noise, a timing jitter of
    the reading, moves the point, not its intensity, so the fog's histograms do not depend on it)."""
    return min(max(r_fog - echo.half_length, echo.r1), min(r0, echo.max_range))


@njit(cache=True, nogil=True)
def _reported_range(r_fog, r0, key, echo):  # pragma: no cover
    """Range [m] the receiver reports for a fog echo whose power peaks at ``r_fog`` (`FogEchoRange` ``echo``):
    ``r_fog - c τ_H / 2`` plus the range noise ``range_sigma · z`` (``z`` the beam's second normal of `normal_pair`
    from ``key``, clipped at ±2), inside ``[r1, min(r0, max_range)]`` (nothing nearer than the receiver's blind zone,
    nothing past the target)."""
    half_length, range_sigma, r1, max_range = echo.half_length, echo.range_sigma, echo.r1, echo.max_range
    r = r_fog - half_length
    if range_sigma > 0.0:
        z = normal_pair(key)[1]
        r += range_sigma * min(max(z, -2.0), 2.0)
    return min(max(r, r1), min(r0, max_range))


@njit(cache=True, nogil=True)
def _points_kernel(points, origins, keys, clear, model, echo, out, labels, r0_out, r_fog_out):  # pragma: no cover
    """Fog every row of ``points`` (N, 5) float32 into ``out`` (a copy of ``points``) by the `FogResponse` ``model``,
    a fog echo moved to the range of `FogEchoRange` ``echo``; origins (N, 3) or (0, 3); keys (N,) the beams' noise
    streams, or (0,) for a noise-free detector; clear (N,) the clear values the rounded intensities stood for, or
    (0,): as read; per point its label, range ``r0_out`` and ``r_fog_out``."""
    noise_std, noise_rel = model.noise_std, model.noise_rel
    has_origin = origins.shape[0] > 0
    noisy = keys.shape[0] > 0
    rounded = clear.shape[0] > 0
    for n in range(points.shape[0]):
        ox = oy = oz = 0.0
        if has_origin:
            ox, oy, oz = origins[n, 0], origins[n, 1], origins[n, 2]
        dx = np.float64(points[n, 0]) - ox
        dy = np.float64(points[n, 1]) - oy
        dz = np.float64(points[n, 2]) - oz
        r0 = math.sqrt(dx * dx + dy * dy + dz * dz)
        key = keys[n] if noisy else np.uint64(0)
        z = normal_pair(key)[0] if noisy and (noise_std > 0.0 or noise_rel > 0.0) else 0.0
        x = clear[n] if rounded else np.float64(points[n, 3])
        integral, r_fog = _fog_peak(r0, model)
        value, label = _fog_one(r0, points[n, 3], x, model, z, integral, _echo_range(r_fog, r0, echo))
        labels[n] = label
        r0_out[n] = r0
        r_fog_out[n] = r_fog
        if label == 1:
            out[n, 3] = value
        elif label == 2:
            f = _reported_range(r_fog, r0, key, echo) / r0
            out[n, 0] = ox + dx * f
            out[n, 1] = oy + dy * f
            out[n, 2] = oz + dz * f
            out[n, 3] = value
        elif label == 3:
            out[n, 3] = value


# -------------------------------------------------------------------------------------------------- point clouds


@dataclass(frozen=True)
class FogResult:
    """A fogged scan.

    Attributes:
        points: (M, 5) float32 ``x, y, z, intensity, ring`` in the input's frame and intensity scale; the kept input
            points in input order (LOST ones removed), SCATTERED ones moved to their fog echo.
        labels: (M,) uint8 `FogLabel` of each output point (never LOST).
        source_index: (M,) int64 row of each output point in the input.
        input_labels: (N,) uint8 `FogLabel` of every input point, LOST included.
        alpha, beta: the medium [1/m], [1/(m sr)].
        intensity_max: intensity scale of ``points`` (255 or 1), that of the input.
        counts: number of input points per label name: ``{"UNCHANGED": n0, "ATTENUATED": n1, "SCATTERED": n2,
            "LOST": n3}``.
    """

    points: NDArray[np.float32]
    labels: NDArray[np.uint8]
    source_index: NDArray[np.int64]
    input_labels: NDArray[np.uint8]
    alpha: float
    beta: float
    intensity_max: float
    counts: dict[str, int] = field(default_factory=dict)

    def apply_to(self, scan: LidarScan) -> LidarScan:
        """``scan`` with these points (per-point times and sweep indices re-indexed to the kept points)."""
        if len(scan.points) != len(self.input_labels):
            raise ValueError(f"FogResult of {len(self.input_labels)} points applied to a scan of {len(scan.points)}")
        pick = self.source_index
        return replace(
            scan,
            points=self.points,
            time_offsets=None if scan.time_offsets is None else scan.time_offsets[pick],
            sweep_index=None if scan.sweep_index is None else scan.sweep_index[pick],
        )


def fog_point_arrays(
    points: NDArray[np.float32],
    origins: NDArray | None,
    alpha: float,
    beta: float,
    *,
    intensity_max: float = 255.0,
    sensor: PulseSensor,
    noise_floor: float | None,
    range_noise_std: float = 0.0,
    noise_keys: NDArray[np.uint64] | None = None,
    response: SoftTargetResponse | None = None,
    noise_std: float = 0.0,
    noise_rel: float = 0.0,
    clear_values: ArrayLike | None = None,
    intensity: IntensityModel,
    floor_range_m: float | None = None,
) -> FogResult:
    """Fog on a bare point array (the array-level core of `simulate_fog`).

    Args:
        points: (N, 5) float32 ``x, y, z`` [m], intensity on ``0..intensity_max``, ring; never modified.
        origins: (N, 3) beam origin of each point [m] in the same frame, or None for the frame origin.
        alpha, beta: extinction [1/m] and backscatter [1/(m sr)].
        intensity_max: 255 or 1, the scale of ``points[:, 3]`` (kept in the output).
        sensor: pulse parameters (τ_H, overlap, β_0, max range, saturation).
        noise_floor: detector floor on the 0..255 scale, or None (see `fog_intensities`).
        range_noise_std: the sensor's Gaussian range noise [m] of a new (fog) echo, clipped at ±2σ; 0: none.
        noise_keys: (N,) each point's beam noise stream (`point_noise_keys`); required when a noise is on.
        response: precomputed `soft_target_response` of ``alpha``, or None.
        noise_std, noise_rel: the detector's intensity noise (see `fog_intensities`).
        clear_values: (N,) the clear value each intensity stood for before rounding, or None (see
            `fog_intensities`).
        intensity, floor_range_m: the sensor's intensity model and floor range (see `fog_intensities`).

    A SCATTERED point moves along its ray to the range the receiver reports for the fog echo: the power peak
    ``R_fog`` minus ``c τ_H / 2`` (the hard targets' convention), plus the range noise, inside
    ``[r1, min(R_0, max_range)]``.

    Returns:
        `FogResult`; with ``alpha == 0`` and ``beta == 0`` the points are the input's, bit for bit.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 5 or points.dtype != np.float32:
        raise ValueError(f"fog: points must be float32 (N, 5), got {points.dtype} {points.shape}")
    n = len(points)
    if not (math.isfinite(range_noise_std) and range_noise_std >= 0.0):
        raise ValueError(f"fog: range_noise_std = {range_noise_std!r}; expected a finite standard deviation >= 0 m")
    keys = _noise_keys(noise_keys, n, range_noise_std > 0.0 or noise_std > 0.0 or noise_rel > 0.0)
    params = _kernel_params(alpha, beta, intensity_max, sensor, noise_floor, response, noise_std, noise_rel,
                            intensity=intensity, floor_range_m=floor_range_m)
    if origins is None:
        origins = np.zeros((0, 3))
    else:
        origins = np.ascontiguousarray(origins, dtype=np.float64)
        if origins.shape != (n, 3):
            raise ValueError(f"fog: origins must be (N, 3) = ({n}, 3), got {origins.shape}")
    out = np.array(points, dtype=np.float32, order="C", copy=True)
    labels = np.empty(n, dtype=np.uint8)
    r0 = np.empty(n)
    r_fog = np.empty(n)
    echo = FogEchoRange(sensor.pulse_length / 2.0, float(range_noise_std), float(sensor.r1), float(sensor.max_range))
    _points_kernel(np.ascontiguousarray(points), origins, keys, _clear_values(clear_values, n), params, echo, out,
                   labels, r0, r_fog)
    counts = np.bincount(labels, minlength=len(POINT_LABELS))
    if counts[FogLabel.LOST]:
        keep = np.flatnonzero(labels != FogLabel.LOST)
        out, kept_labels = out[keep], labels[keep]
    else:
        keep, kept_labels = np.arange(n, dtype=np.int64), labels
    return FogResult(
        points=out,
        labels=kept_labels,
        source_index=keep.astype(np.int64, copy=False),
        input_labels=labels,
        alpha=float(alpha),
        beta=float(beta),
        intensity_max=float(intensity_max),
        counts={label.name: int(counts[label]) for label in POINT_LABELS},
    )


def simulate_fog(
    scan: LidarScan,
    alpha: float,
    beta: float,
    *,
    lidar: LidarModel,
) -> FogResult:
    """Fog a LiDAR scan (Hahner et al. 2021 for any α), each beam from its own origin (moving ego).

    Args:
        scan: the clear scan (any intensity scale; the result keeps it).
        alpha: extinction [1/m] (``MOR = ln 20 / α``); 0 returns the input unchanged when ``beta`` is 0 too.
        beta: backscatter [1/(m sr)], e.g. `default_beta` (0.046 / MOR).
        lidar: the sensor (`weatheralign.sensors.LidarModel`): its pulse, its detector noise floor (0..255), its
            intensity noise (``intensity_noise_std``, ``intensity_noise_rel``; see `fog_intensities`) and the range
            noise of a new echo (``range_noise_std_m``); each beam's noise from its own stream (`point_noise_keys`:
            firing time, direction and ring), so the same scan gives the same bytes. An integer-quantised scan's
            readings are spread over their rounding intervals by the same streams in the floor test
            (`weatheralign.lidar.quantum.scan_clear_readings`).

    Returns:
        `FogResult` (use ``result.apply_to(scan)`` for a `LidarScan`).
    """
    origins = beam_origins(scan, "scan")
    noisy = lidar.range_noise_std_m > 0.0 or lidar.intensity_noise_std > 0.0 or lidar.intensity_noise_rel > 0.0
    keys = point_noise_keys(scan) if noisy else None
    floor = lidar.noise_floor
    if lidar.floor_range_m is not None:
        floor = lidar.floor_at(point_ranges(scan.points, origins))
    clear = scan_clear_readings(scan, floor)
    return fog_point_arrays(scan.points, origins, alpha, beta, intensity_max=scan.intensity_max, sensor=lidar.pulse,
                            noise_floor=lidar.noise_floor, range_noise_std=lidar.range_noise_std_m, noise_keys=keys,
                            noise_std=lidar.intensity_noise_std, noise_rel=lidar.intensity_noise_rel,
                            clear_values=None if clear is None else on_scale(clear, scan.points[:, 3],
                                                                             scan.intensity_max),
                            intensity=lidar.intensity, floor_range_m=lidar.floor_range_m)
