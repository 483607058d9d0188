"""The synthetic reference's LiDAR in fog: the full pulse integral of every beam, evaluated exactly.

This is the reference's own process, independent of the fast simulator (`weatheralign.lidar.fog`), for the same
physical sensor (``docs/physics.md`` sections 1 and 2.5, Rasshofer et al. 2011). A beam with system constant ``C``
(``C_A P_0``) that hits a hard target at ``R_0`` through homogeneous fog (extinction α, backscatter β) receives

    P(R) = C [ β (2/c) ∫_0^{c τ_H} k(s) h(R - s) U(R_0 - R + s) ds  +  β_0 ξ(R_0) e^{-2α R_0} / R_0² · k(R - R_0) ]

on the receiver's range axis ``R = c t / 2``, with the pulse ``k(s) = sin²(π s / (c τ_H))`` on ``[0, c τ_H]``
(0 outside) and the soft-target channel ``h(r) = ξ(r) e^{-2α r} / r²``. The hard-target term is the published
closed form (pulse.py's unit convention, without the 2/c Jacobian of a delta target) so that the two processes
describe one sensor; beams without a hard return (open sky, or a target beyond the maximum range) see the soft term
alone out to the end of the listening window.

What is exact here and approximated by the fast simulator:
- **overlap**: the exact bi-static overlap of a biaxial sensor, not a linear ramp. The transmitted beam and the
  receiver's field of view are discs in the plane normal to the axis, of radii ``ρ_b`` and ``ρ_r = κ ρ_b``
  (``κ = fov_ratio``, default 2); the receiver axis is tilted towards the beam so that their centre distance falls
  linearly from ``ρ_b + ρ_r`` at ``r1`` (first contact, ξ = 0) to ``ρ_r - ρ_b`` at ``r2`` (beam inside the field of
  view, ξ = 1). ``ξ(r)`` is the intersection area of the two discs over the beam's area ``π ρ_b²`` (an S-shaped
  rise between ``r1`` and ``r2``; 0 before, 1 after).
- **sum, not maximum**: the soft and hard echoes add on the receiver axis and the sensor reports the strongest peak
  of their sum over the whole window (a strongest-return sensor), instead of comparing two separate maxima.
- **range**: the reported range is the peak position minus ``c τ_H / 2`` (the sensor's timing is calibrated on hard
  targets, which therefore come back at ``R_0``); a fog echo peaking at ``R* ≈ 4.6 m`` (α = 0.06) is reported at
  ``≈ 1.6 m``, where its dominant scatterers are.
- **no-return beams** produce fog echoes too.
- the detector: saturation, Gaussian intensity noise, a noise floor (nothing below it is reported), integer
  quantisation, Gaussian range noise (clipped at ±2σ) — see `read_out`.

How the integral is evaluated (exactly, for any α, vectorised): ``k(R - r) = ½ - ½ cos(ω (R - r))`` with
``ω = 2π / (c τ_H)`` turns the soft integral into

    (2/c) ∫_a^b k(R - r) h(r) dr = (1/c) [ ΔH_0 - cos(ωR) ΔH_c - sin(ωR) ΔH_s ],
    a = max(R - c τ_H, r1),   b = min(R, R_0),

with ``H_0, H_c, H_s`` the running integrals of ``h``, ``h cos(ωr)``, ``h sin(ωr)``, tabulated once per α on a 1 mm
grid (trapezoid rule, relative error ~1e-6; checked against `scipy.integrate.quad` in the tests). On ``R <= R_0``
the soft term does not depend on the target, so its maximum over ``[r1, R_0]`` is a prefix maximum of the
unobstructed response tabulated on the same 1 mm grid; on ``[R_0, R_0 + c τ_H]`` (hard pulse plus the truncated
soft tail) the sum is evaluated on a grid of ``step`` (2 cm) centred on the hard peak ``R_0 + c τ_H / 2`` and the
maximum refined by a parabola through its neighbours. One fused numba loop over the beams.

System constant per beam (the clear sensor's intensity calibration, as the fast simulator's): the sensor chooses the
strongest peak on raw power and reports it through its range compensation at the reported range ``R_e`` (``R_e²
g(R_e)``, `IntensityModel.compensation`), so a target with clear intensity ``i_0`` (the intensity it would report
with full overlap) at ``R_0`` has ``C = i_0 / (β_0 g(R_0))`` (a raw-power sensor's ``i_0 R_0² / β_0``). A beam
without a hard target has no clear measurement to calibrate from; it gets its laser's typical constant, the median
``C`` of the returns of the same ring in the same scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import cumulative_trapezoid

from weatheralign.reference.records import FogGrid, FogMedium, FogPeaks, SensorOptics
from weatheralign.sensors import SPEED_OF_LIGHT, SYNTHETIC_INTENSITY, IntensityModel, PulseSensor, floor_scale

F64 = NDArray[np.float64]

TABLE_STEP_M = 1e-3
"""Grid step [m] of the running integrals and of the unobstructed response."""

TARGET, FOG = 1, 2
"""`ExactReturns.source` values: the peak is the hard target's echo (with any fog added to it), or a fog echo."""


@dataclass(frozen=True)
class ExactSensor(PulseSensor):
    """The reference LiDAR: pulse, bi-static overlap and detector limits.

    Attributes:
        tau_h: half-power pulse width τ_H [s] (20 ns, the fast fog simulator's value).
        r1, r2: overlap end points [m]: ξ = 0 up to ``r1``, 1 from ``r2``.
        fov_ratio: receiver field-of-view radius over beam radius κ (>= 1) of the disc-overlap model.
        gamma: reflectivity Γ of the reference hard target, ``β_0 = Γ / π`` [1/sr] (1e-6, as the fast simulator).
        min_range, max_range: reported ranges outside ``[min_range, max_range]`` [m] are dropped.
        saturation: largest received peak the detector reports (0..255 scale).
    """

    fov_ratio: float = 2.0
    min_range: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()  # pulse, overlap, Γ, saturation
        checks = {
            "fov_ratio": (self.fov_ratio, self.fov_ratio >= 1.0, "fov_ratio >= 1"),
            "min_range": (self.min_range, self.min_range >= self.r2, f"min_range >= r2 = {self.r2} m"),
            "max_range": (self.max_range, self.max_range > self.min_range, "max_range > min_range"),
        }
        for name, (value, ok, allowed) in checks.items():
            if not (math.isfinite(value) and ok):
                raise ValueError(f"ExactSensor.{name} = {value!r}; expected {allowed}")

    @property
    def listen_end(self) -> float:
        """Last receiver-axis position [m] whose peak is still reported: ``max_range + c τ_H / 2``."""
        return self.max_range + 0.5 * self.pulse_length


def sensor_optics(sensor: ExactSensor) -> SensorOptics:
    """``sensor`` as the kernels take it."""
    return SensorOptics(sensor.pulse_length, sensor.listen_end, sensor.r1, sensor.r2, sensor.fov_ratio, sensor.beta_0)


@njit(cache=True, nogil=True)
def _overlap_one(r: float, r1: float, r2: float, kappa: float) -> float:  # pragma: no cover
    """ξ(r) of the disc-overlap model (beam radius 1, field of view radius ``kappa``)."""
    if r <= r1:
        return 0.0
    if r >= r2:
        return 1.0
    d = (1.0 + kappa) - 2.0 * (r - r1) / (r2 - r1)  # centre distance in beam radii
    if d <= kappa - 1.0:
        return 1.0
    if d >= kappa + 1.0:
        return 0.0
    c1 = min(1.0, max(-1.0, (d * d + 1.0 - kappa * kappa) / (2.0 * d)))
    c2 = min(1.0, max(-1.0, (d * d + kappa * kappa - 1.0) / (2.0 * d * kappa)))
    q = (-d + 1.0 + kappa) * (d + 1.0 - kappa) * (d - 1.0 + kappa) * (d + 1.0 + kappa)
    area = math.acos(c1) + kappa * kappa * math.acos(c2) - 0.5 * math.sqrt(max(q, 0.0))
    return min(1.0, max(0.0, area / math.pi))


@njit(cache=True, nogil=True)
def _overlap_array(r: NDArray, r1: float, r2: float, kappa: float) -> NDArray:  # pragma: no cover
    out = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        out[i] = _overlap_one(r[i], r1, r2, kappa)
    return out


def bistatic_overlap(r: ArrayLike, sensor: ExactSensor = ExactSensor()) -> F64:
    """Exact disc-overlap ξ(r) (same shape as ``r`` [m]): 0 up to ``r1``, 1 from ``r2``, S-shaped in between."""
    r = np.asarray(r, dtype=np.float64)
    return _overlap_array(np.ascontiguousarray(r.ravel()), sensor.r1, sensor.r2, sensor.fov_ratio).reshape(r.shape)


# ------------------------------------------------------------------------------------------------ tables per alpha


@dataclass(frozen=True)
class FogTables:
    """Running integrals of one extinction α and the unobstructed soft response (units of ``C β``).

    Attributes:
        alpha: extinction [1/m].
        r_start, step: grid ``r_j = r_start + j step`` [m] (``r_start = r1``).
        h0, hc, hs: (K,) running integrals of ``h``, ``h cos(ωr)``, ``h sin(ωr)`` from ``r1`` to ``r_j``.
        g: (K,) unobstructed soft response ``G(R_j)`` [s/m²] (every scatterer in front: ``R_0 = inf``).
        gmax, gmax_at: (K,) prefix maximum of ``g`` over ``R <= R_j`` and where it is reached [m].
        g_peak, r_peak: maximum of ``g`` over the listening window and its position [m].
    """

    alpha: float
    r_start: float
    step: float
    h0: F64
    hc: F64
    hs: F64
    g: F64
    gmax: F64
    gmax_at: F64
    g_peak: float
    r_peak: float

    def grid(self) -> FogGrid:
        """The tables as the kernels take them."""
        return FogGrid(self.r_start, self.step, self.h0, self.hc, self.hs, self.gmax, self.gmax_at, self.g_peak,
                       self.r_peak)


def fog_tables(alpha: float, sensor: ExactSensor = ExactSensor(), *, step: float = TABLE_STEP_M) -> FogTables:
    """Tabulate the running integrals and the unobstructed response of extinction ``alpha`` [1/m] (once per α).

    Raises:
        ValueError: ``alpha`` negative or not finite, or ``step`` not in (0, 0.01] m.
    """
    if not (math.isfinite(alpha) and alpha >= 0.0):
        raise ValueError(f"fog_tables: alpha = {alpha!r}; expected a finite extinction >= 0 [1/m]")
    if not 0.0 < step <= 0.01:
        raise ValueError(f"fog_tables: step = {step!r}; expected 0 < step <= 0.01 m")
    length = sensor.pulse_length
    omega = 2.0 * math.pi / length
    ramp = sensor.r2 - sensor.r1
    dr = ramp / math.ceil(ramp / step)  # r1 and r2 on nodes
    n = int(math.ceil((sensor.listen_end + length - sensor.r1) / dr)) + 2
    r = sensor.r1 + dr * np.arange(n)
    h = bistatic_overlap(r, sensor) * np.exp(-2.0 * alpha * r) / (r * r)
    h0 = cumulative_trapezoid(h, dx=dr, initial=0.0)
    hc = cumulative_trapezoid(h * np.cos(omega * r), dx=dr, initial=0.0)
    hs = cumulative_trapezoid(h * np.sin(omega * r), dx=dr, initial=0.0)
    g = np.empty(n)
    _soft_grid(r, np.inf, sensor.r1, dr, h0, hc, hs, length, omega, g)
    gmax = np.maximum.accumulate(g)
    arg = np.zeros(n, dtype=np.int64)
    _prefix_argmax(g, arg)
    listen = r <= sensor.listen_end
    j = int(np.argmax(np.where(listen, g, -np.inf)))
    for a in (h0, hc, hs, g, gmax):
        a.setflags(write=False)
    gmax_at = r[arg]
    gmax_at.setflags(write=False)
    return FogTables(float(alpha), float(sensor.r1), float(dr), h0, hc, hs, g, gmax, gmax_at, float(g[j]), float(r[j]))


@njit(cache=True, nogil=True)
def _prefix_argmax(g: NDArray, out: NDArray) -> None:  # pragma: no cover
    best = 0
    for j in range(g.shape[0]):
        if g[j] > g[best]:
            best = j
        out[j] = best


@njit(cache=True, nogil=True, inline="always")
def _interp(table: NDArray, x: float, r_start: float, step: float) -> float:  # pragma: no cover
    pos = (x - r_start) / step
    if pos <= 0.0:
        return table[0]
    j = int(pos)
    if j >= table.shape[0] - 1:
        return table[table.shape[0] - 1]
    f = pos - j
    return table[j] + f * (table[j + 1] - table[j])


@njit(cache=True, nogil=True)
def _soft(R: float, r0: float, r_start: float, step: float, h0: NDArray, hc: NDArray, hs: NDArray, length: float,
          omega: float) -> float:  # pragma: no cover
    """``(2/c) ∫ k(R - r) h(r) U(r0 - r) dr`` [s/m²]: the soft response at ``R`` of fog in front of ``r0``."""
    a = max(R - length, r_start)
    b = min(R, r0)
    if b <= a:
        return 0.0
    d0 = _interp(h0, b, r_start, step) - _interp(h0, a, r_start, step)
    dc = _interp(hc, b, r_start, step) - _interp(hc, a, r_start, step)
    ds = _interp(hs, b, r_start, step) - _interp(hs, a, r_start, step)
    value = (d0 - math.cos(omega * R) * dc - math.sin(omega * R) * ds) / SPEED_OF_LIGHT
    return max(value, 0.0)


@njit(cache=True, nogil=True)
def _soft_grid(R: NDArray, r0: float, r_start: float, step: float, h0: NDArray, hc: NDArray, hs: NDArray,
               length: float, omega: float, out: NDArray) -> None:  # pragma: no cover
    for j in range(R.shape[0]):
        out[j] = _soft(R[j], r0, r_start, step, h0, hc, hs, length, omega)


def soft_response(R: ArrayLike, r0: float, tables: FogTables, sensor: ExactSensor = ExactSensor()) -> F64:
    """Soft-target response ``P_soft(R) / (C β)`` [s/m²] at receiver ranges ``R`` (any shape) of fog in front of a
    target at ``r0`` [m] (``inf``: no target), from the tables."""
    R = np.asarray(R, dtype=np.float64)
    out = np.empty(R.size)
    _soft_grid(np.ascontiguousarray(R.ravel()), float(r0), tables.r_start, tables.step, tables.h0, tables.hc,
               tables.hs, sensor.pulse_length, 2.0 * math.pi / sensor.pulse_length, out)
    return out.reshape(R.shape)


# ------------------------------------------------------------------------------------------------ per beam


@dataclass(frozen=True)
class ExactReturns:
    """The strongest peak of every beam's received power.

    Attributes:
        power: (N,) peak power in intensity units (``C`` times the response), before the detector.
        r_peak: (N,) peak position on the receiver axis [m] (the reported range is ``r_peak - c τ_H / 2``).
        source: (N,) uint8 `TARGET` or `FOG` (0: nothing received, e.g. β = 0 on a beam without target).
        target_power: (N,) where the strongest peak is not the target's: the received power at the target's own
            echo crest (``r_peak`` ``r0 + c τ_H / 2``, in intensity units at the target's range), 0 elsewhere; the
            return `read_out` reports when the strongest peak is too weak to be detected. None: no such second
            return (the fog process, whose continuum has no separate echo).
        target_r_peak: (N,) that crest's position on the receiver axis [m] (0 where ``target_power`` is 0), or None.
    """

    power: F64
    r_peak: F64
    source: NDArray[np.uint8]
    target_power: F64 | None = None
    target_r_peak: F64 | None = None


@njit(cache=True, nogil=True)
def _beams_kernel(r0s, cs, fog, sensor, tables, stride, out):  # pragma: no cover
    """Per beam of targets at ``r0s`` (N,) [m] (inf: none) with system constants ``cs`` (N,) through ``fog``
    (`FogMedium`), seen by ``sensor`` (`SensorOptics`), from the `FogGrid` ``tables``: the strongest peak into
    ``out`` (`FogPeaks`). Region A by prefix maximum, region B on nodes ``R_m = r0 + c τ_H / 2 + (m - M) stride
    step`` up to the end of the listening window: the lower integration limit ``R_m - c τ_H`` then moves by whole
    table steps, so every node shares one interpolation fraction, and ``cos/sin(ω R_m)`` follow by rotation."""
    alpha, beta = fog.alpha, fog.beta
    beta0, r1, r2, kappa = sensor.beta0, sensor.r1, sensor.r2, sensor.kappa
    listen_end, length = sensor.listen_end, sensor.length
    r_start, step, h0, hc, hs = tables.r_start, tables.step, tables.h0, tables.hc, tables.hs
    gmax, gmax_at, g_peak, r_peak = tables.gmax, tables.gmax_at, tables.g_peak, tables.r_peak
    power, r_out, source = out.power, out.r_peak, out.source
    omega = 2.0 * math.pi / length
    half = 0.5 * length
    grid_step = stride * step
    m_half = int(math.floor(half / grid_step))
    n_nodes = 2 * m_half + 1
    values = np.empty(n_nodes)
    n_tab = gmax.shape[0]
    cos_d, sin_d = math.cos(omega * grid_step), math.sin(omega * grid_step)
    cos_h, sin_h = math.cos(0.5 * omega * grid_step), math.sin(0.5 * omega * grid_step)
    for i in range(r0s.shape[0]):
        r0, c = r0s[i], cs[i]
        if not (r0 < listen_end):  # no hard echo in the window: fog alone
            power[i] = c * beta * g_peak
            r_out[i] = r_peak
            source[i] = FOG if power[i] > 0.0 else 0
            continue
        # region A: R in [r1, r0], soft only (independent of the target): prefix maximum + the end point
        va, ra = 0.0, r0
        if beta > 0.0 and r0 > r_start:
            j0 = min(int((r0 - r_start) / step), n_tab - 1)
            va, ra = gmax[j0], gmax_at[j0]
            v_end = _soft(r0, r0, r_start, step, h0, hc, hs, length, omega)
            if v_end > va:
                va, ra = v_end, r0
        va *= beta
        # region B: R in [r0, r0 + c tau_H]: hard pulse + truncated soft tail
        hard = beta0 * _overlap_one(r0, r1, r2, kappa) * math.exp(-2.0 * alpha * r0) / (r0 * r0)
        R_first = r0 + half - m_half * grid_step
        if beta > 0.0:
            b0 = _interp(h0, r0, r_start, step)
            bc = _interp(hc, r0, r_start, step)
            bs = _interp(hs, r0, r_start, step)
            pos = (R_first - length - r_start) / step
            j_first = int(math.floor(pos))
            frac = pos - j_first
        cw, sw = math.cos(omega * R_first), math.sin(omega * R_first)  # cos/sin(ω R_m)
        x = 0.5 * omega * (R_first - r0)
        ch, sh = math.cos(x), math.sin(x)  # cos/sin(π (R_m - r0) / (c τ_H))
        n_valid = min(n_nodes, int(math.floor((listen_end - R_first) / grid_step)) + 1)  # the window's end
        best = 0
        values[0] = 0.0
        for m in range(n_valid):
            v = hard * sh * sh
            if beta > 0.0:
                j = j_first + m * stride
                if j < 0:  # a = r1
                    a0, ac, as_ = h0[0], hc[0], hs[0]
                elif j >= n_tab - 1:
                    a0, ac, as_ = h0[n_tab - 1], hc[n_tab - 1], hs[n_tab - 1]
                else:
                    a0 = h0[j] + frac * (h0[j + 1] - h0[j])
                    ac = hc[j] + frac * (hc[j + 1] - hc[j])
                    as_ = hs[j] + frac * (hs[j + 1] - hs[j])
                soft = ((b0 - a0) - cw * (bc - ac) - sw * (bs - as_)) / SPEED_OF_LIGHT
                if soft > 0.0:
                    v += beta * soft
            values[m] = v
            if v > values[best]:
                best = m
            cw, sw = cw * cos_d - sw * sin_d, sw * cos_d + cw * sin_d
            ch, sh = ch * cos_h - sh * sin_h, sh * cos_h + ch * sin_h
        vb = values[best] if n_valid > 0 else 0.0
        rb = R_first + best * grid_step
        if 0 < best < n_valid - 1:
            a, b, cc = values[best - 1], vb, values[best + 1]
            curv = a - 2.0 * b + cc
            if curv < 0.0:
                shift = 0.5 * (a - cc) / curv
                rb += shift * grid_step
                vb = b - 0.25 * (a - cc) * shift
        if va >= vb:
            power[i], r_out[i] = c * va, ra
            source[i] = FOG if va > 0.0 else 0
        else:
            power[i], r_out[i] = c * vb, rb
            source[i] = TARGET


def exact_returns(r0: ArrayLike, c: ArrayLike, alpha: float, beta: float, sensor: ExactSensor = ExactSensor(), *,
                  tables: FogTables | None = None, grid_step: float = 0.02,
                  intensity: IntensityModel = SYNTHETIC_INTENSITY) -> ExactReturns:
    """The strongest peak of the received power of every beam (N,), reported through the sensor's range
    compensation at its reported range.

    Args:
        r0: (N,) hard-target range [m] of each beam, ``inf`` where there is none (or it lies beyond the window).
        c: (N,) system constant ``C`` of each beam (`system_constants` of the same ``intensity``).
        alpha, beta: the fog's extinction [1/m] and backscatter [1/(m sr)] (0, 0: clear air).
        sensor: the reference sensor.
        tables: `fog_tables` of ``alpha`` (computed when None).
        grid_step: receiver-axis step [m] of the search around the hard echo (refined by a parabola); rounded to a
            whole number of table steps.
        intensity: the sensor's `IntensityModel`: the strongest peak is chosen on raw power ``C P(R)`` and reported
            as ``C P(R) R_e² g(R_e)``, ``R_e = R_peak - c τ_H / 2`` the range it is reported at (section 3.5 of
            ``docs/physics.md``; the raw-power sensor's ``R² g(R)`` is 1).

    Returns:
        `ExactReturns` (``power``: the reported intensity before the detector). With ``alpha = beta = 0`` a target
        at ``R_0 >= r2`` returns its clear intensity at ``R_0 + c τ_H / 2``.
    """
    if not (math.isfinite(beta) and beta >= 0.0):
        raise ValueError(f"exact_returns: beta = {beta!r}; expected a finite backscatter >= 0 [1/(m sr)]")
    if not 0.0 < grid_step <= 0.1:
        raise ValueError(f"exact_returns: grid_step = {grid_step!r}; expected 0 < grid_step <= 0.1 m")
    if tables is None:
        tables = fog_tables(alpha, sensor)
    elif tables.alpha != alpha:
        raise ValueError(f"exact_returns: tables are for alpha = {tables.alpha}, not {alpha}")
    r0 = np.ascontiguousarray(r0, dtype=np.float64).ravel()
    c = np.ascontiguousarray(c, dtype=np.float64).ravel()
    if r0.shape != c.shape:
        raise ValueError(f"exact_returns: r0 {r0.shape} and c {c.shape} differ")
    n = len(r0)
    power, r_peak, source = np.empty(n), np.empty(n), np.empty(n, dtype=np.uint8)
    stride = max(1, int(round(grid_step / tables.step)))
    _beams_kernel(r0, c, FogMedium(float(alpha), float(beta)), sensor_optics(sensor), tables.grid(), stride,
                  FogPeaks(power, r_peak, source))
    power *= intensity.compensation(np.maximum(r_peak - 0.5 * sensor.pulse_length, sensor.r1))
    return ExactReturns(power, r_peak, source)


def system_constants(r0: ArrayLike, i0: ArrayLike, ring: ArrayLike, sensor: ExactSensor = ExactSensor(), *,
                     intensity: IntensityModel = SYNTHETIC_INTENSITY) -> F64:
    """(N,) system constant ``C`` of every beam: ``i_0 / (β_0 g(R_0))`` where the beam has a target (finite ``r0``
    [m], ``i0`` > 0 its clear intensity on 0..255 with full overlap, ``g`` the gain of ``intensity``: the clear
    target's raw peak ``C β_0 / R_0²`` reported through ``R_0² g(R_0)`` is ``i_0``; the raw-power sensor's
    ``i_0 R_0² / β_0``), else the median ``C`` of the targets of its ``ring`` (all rings' median if the ring has
    none; 0 if the scan has no target at all)."""
    r0 = np.asarray(r0, dtype=np.float64)
    i0 = np.asarray(i0, dtype=np.float64)
    ring = np.asarray(ring)
    has = np.isfinite(r0) & (i0 > 0.0)
    c = np.zeros(len(r0))
    c[has] = i0[has] * r0[has] ** 2 / (sensor.beta_0 * intensity.compensation(r0[has]))
    if not has.any():
        return c
    overall = float(np.median(c[has]))
    for k in np.unique(ring[~has]):
        sel = ring == k
        ref = c[sel & has]
        c[sel & ~has] = float(np.median(ref)) if len(ref) else overall
    return c


@dataclass(frozen=True)
class Detector:
    """The reference LiDAR's read-out (0..255 scale).

    Attributes:
        intensity_noise_std: electronic (signal-independent) Gaussian noise on the received peak.
        intensity_noise_rel: signal-proportional part: the noise std is ``sqrt(std² + (rel · P)²)`` at peak ``P``.
        noise_floor: a peak whose measured value (with its noise) is below the floor is not detected; with a constant
            floor, neither is one whose quantised intensity is (no point is reported below it), while a raw-power
            detector (``floor_range_m``) reports a detected reading that rounds under its floor, 0 included.
        range_noise_std: Gaussian range noise [m], clipped at ±2σ.
        intensity: the sensor's `IntensityModel` (the floor's range dependence).
        floor_range_m: None: the floor is ``noise_floor`` at every range. A range [m]: a raw-power detector, whose
            floor (and the constant part of the intensity noise) on the reported scale is ``noise_floor R² g(R) /
            (r_f² g(r_f))`` at the noise-free reported range ``R`` (`weatheralign.sensors.LidarModel.floor_range_m`).
    """

    intensity_noise_std: float = 0.5
    intensity_noise_rel: float = 0.03
    noise_floor: float = 1.0
    range_noise_std: float = 0.01
    intensity: IntensityModel = SYNTHETIC_INTENSITY
    floor_range_m: float | None = None

    def floor_scale(self, r: ArrayLike) -> F64:
        """(any shape) the floor's and the constant noise's factor at reported ranges ``r`` [m] (1 when constant)."""
        return floor_scale(r, self.intensity, self.floor_range_m)


@dataclass(frozen=True)
class Readout:
    """Detected returns: ``index`` (M,) beam index, ``range`` (M,) reported range [m], ``intensity`` (M,) integer
    0..255 (float64), ``source`` (M,) `TARGET` / `FOG`."""

    index: NDArray[np.int64]
    range: F64
    intensity: F64
    source: NDArray[np.uint8]


def _detect(power: F64, r_peak: F64, sensor: ExactSensor, detector: Detector,
            rng: np.random.Generator) -> tuple[NDArray[np.bool_], F64, F64]:
    """One reading of peaks ``power`` (N,) at ``r_peak`` (N,) [m]: (detected, reported range [m], integer
    intensity 0..255), the noise drawn for all N in a fixed order."""
    n = len(power)
    peak = np.minimum(power, sensor.saturation)
    scale = detector.floor_scale(r_peak - 0.5 * sensor.pulse_length)
    std = np.sqrt((detector.intensity_noise_std * scale) ** 2 + (detector.intensity_noise_rel * peak) ** 2)
    measured = peak + std * rng.standard_normal(n)
    sigma = detector.range_noise_std
    jitter = np.clip(rng.normal(0.0, sigma, n), -2 * sigma, 2 * sigma) if sigma > 0 else np.zeros(n)
    reported = r_peak - 0.5 * sensor.pulse_length + jitter
    quantised = np.clip(np.rint(measured), 0.0, 255.0)
    floor = detector.noise_floor * scale
    # a constant floor on the reported scale reports nothing under it; a raw-power detector's reading may round to a
    # value under its floor at that range (0 included: "one step above noise", the HDL-32E manual)
    rounded_ok = (quantised >= floor) if detector.floor_range_m is None else np.ones(n, dtype=bool)
    detected = ((measured >= floor) & rounded_ok & (reported >= sensor.min_range) & (reported <= sensor.max_range))
    return detected, reported, quantised


def read_out(returns: ExactReturns, sensor: ExactSensor, detector: Detector, rng: np.random.Generator) -> Readout:
    """Detector chain: saturate at ``sensor.saturation``, add intensity noise (`Detector`), round to integers
    0..255, keep the peaks whose measured and rounded intensities are at or above the noise floor and whose reported
    range ``r_peak - c τ_H / 2`` (+ range noise) lies in ``[min_range, max_range]``. A strongest-return receiver
    reports the strongest *detected* echo: where the strongest peak is not detected and the beam has a second
    return (``returns.target_power``, the target behind a particle's echo), that return is read the same way (its
    own noise) and reported if detected. Noise is drawn for every beam in a fixed order (the second returns' after
    the first): the same generator state gives the same bytes."""
    detected, reported, quantised = _detect(returns.power, returns.r_peak, sensor, detector, rng)
    keep = (returns.source > 0) & detected
    source = returns.source.copy()
    if returns.target_power is not None and returns.target_r_peak is not None:
        t_detected, t_reported, t_quantised = _detect(returns.target_power, returns.target_r_peak, sensor,
                                                      detector, rng)
        second = ~keep & (returns.target_power > 0.0) & t_detected
        reported = np.where(second, t_reported, reported)
        quantised = np.where(second, t_quantised, quantised)
        source[second] = TARGET
        keep |= second
    idx = np.flatnonzero(keep)
    return Readout(idx.astype(np.int64), reported[idx], quantised[idx], source[idx])
