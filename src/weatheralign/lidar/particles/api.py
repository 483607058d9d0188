"""Snow and rain on a LiDAR scan: the public API of `weatheralign.lidar.particles` (see the package docstring for the
physics): the result types, `simulate_particles` / `simulate_particle_list`, and the Python side
of the per-beam response (`_respond`, `_assemble`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from weatheralign.data.frame import LidarScan
from weatheralign.geometry import invert
from weatheralign.lidar.beams import (
    Beams,
    beams_from_scan,
    detector_noise_keys,
    scan_ground_plane,
    with_faint_surfaces,
    with_ground_plane,
)
from weatheralign.lidar.fog import reading_normals, soft_target_response
from weatheralign.lidar.labels import POINT_LABELS, WeatherLabel
from weatheralign.lidar.particles.beam_index import (
    empty_hits,
    field_hits,
    index_beams,
    list_hits,
    range_shells,
    rank_cutoffs,
    reachable_cells,
    shell_edges,
)
from weatheralign.lidar.particles.records import (
    BeamOutcome,
    BeamTargets,
    Continuum,
    HitArrays,
    Medium,
    ParticleBatch,
    PulseParams,
)
from weatheralign.lidar.particles.response import response_kernel
from weatheralign.lidar.quantum import attenuated_reading, clear_readings, reading_uniforms, rounded_readings
from weatheralign.medium.distributions import RAIN_REFLECTIVITY, SNOW_REFLECTIVITY  # noqa: F401  (re-exported)
from weatheralign.medium.field import DEFAULT_MAX_PARTICLES, ParticleField, Particles
from weatheralign.medium.fog import FogMedium
from weatheralign.sensors import IntensityModel, LidarModel, PulseSensor, floor_scale

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

DEFAULT_RATIO_THRESHOLD = 1e-3
"""Particles covering less than this share of a beam even when centred on it go into the bulk extinction."""

MAX_AUTO_RATIO_THRESHOLD = 1e-2
"""Cap of `auto_ratio_threshold` for dark particles (rain)."""

KEEP_TOLERANCE = 0.2
"""A peak within this distance [m] of the original range keeps the point where it is."""

SHELL_RATIO = 1.25
"""Growth of the range shells beyond the first."""

FIRST_SHELL = 1.0
"""Outer edge [m] of the first range shell."""

SAMPLE_GRID = 48
"""Side of the grid on which the uncovered part of a disk overlapping nearer disks is counted."""


ParticleLabel = WeatherLabel
"""What snow or rain did to a point (and, per beam, `WeatherLabel.NO_ECHO`): the shared `WeatherLabel`."""


@dataclass(frozen=True, eq=False)
class BeamHits:
    """Resolved particle–beam intersections, sorted by beam, then range.

    Attributes:
        beam: (H,) int64 index into the `Beams`.
        particle_id: (H,) int64 field id of the particle.
        range: (H,) float64 axial distance of the particle centre from the beam origin [m].
        ratio: (H,) float64 occlusion ratio (share of the beam cross-section this particle covers, nearest first).
        offset: (H, 2) float64 particle centre in the beam cross-section, in beam radii.
        size: (H,) float64 particle radius in beam radii.
    """

    beam: I64
    particle_id: I64
    range: F64
    ratio: F64
    offset: F64
    size: F64

    def __len__(self) -> int:
        return int(self.beam.shape[0])


@dataclass(frozen=True, eq=False)
class ParticleResult:
    """A scan through snow or rain.

    Attributes:
        points: (M, 5) float32 ``x, y, z, intensity, ring`` in the output frame (the scan's) and intensity scale: the
            kept input points in input order (LOST removed; SCATTERED moved along their beam), then clutter points
            from beams without return.
        labels: (M,) uint8 `WeatherLabel` of each output point (never LOST or NO_ECHO).
        particle_id: (M,) int64 id of the particle that produced a SCATTERED point, -1 otherwise.
        source_index: (M,) int64 row of the input point, -1 for clutter from beams without return.
        times: (M,) float64 firing time of each output point's beam [s].
        input_labels: (N,) uint8 `WeatherLabel` of every input point (LOST included, never NO_ECHO).
        counts: input points per label name (`POINT_LABELS`) plus ``"CLUTTER"`` (points added on beams without
            return).
        intensity_max: intensity scale of ``points``.
        hits: the resolved particle–beam intersections with their occlusion ratios.
        beam_index: (M,) int64 the beam (index into the `Beams`) of each output point.
        beam_range: (B,) measured range of each beam [m] (nan where nothing was detected).
        beam_intensity: (B,) intensity of each beam's detected echo on the 0..255 scale (0 where none).
        beam_particle: (B,) int64 id of the particle whose echo a beam detected, -1 otherwise.
        beam_label: (B,) uint8 `WeatherLabel` per beam: its point's label, SCATTERED for clutter, NO_ECHO for a
            beam without return that stays empty.
        stats: diagnostics (particles materialised per shell, thresholds, extinction).
    """

    points: NDArray[np.float32]
    labels: NDArray[np.uint8]
    particle_id: I64
    source_index: I64
    times: F64
    input_labels: NDArray[np.uint8]
    counts: dict[str, int]
    intensity_max: float
    hits: BeamHits
    beam_index: I64
    beam_range: F64
    beam_intensity: F64
    beam_particle: I64
    beam_label: NDArray[np.uint8]
    stats: dict = field(default_factory=dict)

    def apply_to(self, scan: LidarScan) -> LidarScan:
        """``scan`` with these points: per-point time offsets (from the beams' firing times) and sweep indices
        re-indexed (clutter: the reference sweep)."""
        if len(scan.points) != len(self.input_labels):
            raise ValueError(f"ParticleResult of {len(self.input_labels)} points applied to a scan of "
                             f"{len(scan.points)}")
        src = self.source_index
        offsets = None
        if scan.time_offsets is not None:
            offsets = (self.times - scan.timestamp).astype(np.float32)
            kept = src >= 0
            offsets[kept] = scan.time_offsets[src[kept]]
        sweep = None
        if scan.sweep_index is not None:
            sweep = np.zeros(len(src), dtype=np.int16)
            sweep[src >= 0] = scan.sweep_index[src[src >= 0]]
        return replace(scan, points=self.points, time_offsets=offsets, sweep_index=sweep)


@dataclass(frozen=True)
class _Options:
    reflectivity: float
    sensor: PulseSensor
    intensity_model: IntensityModel
    noise_floor: float | None
    keep_tolerance: float
    intensity_noise_std: float = 0.0
    intensity_noise_rel: float = 0.0
    range_noise_std: float = 0.0
    min_range: float = 0.0
    floor_range_m: float | None = None

    def floor_scale(self, r: ArrayLike) -> F64:
        """(any shape) the floor's (and a new echo's constant noise's) factor at reported ranges ``r`` [m]."""
        return floor_scale(r, self.intensity_model, self.floor_range_m)

    def floor_at(self, r: ArrayLike) -> F64 | None:
        """(any shape) the detector floor (0..255) at reported ranges ``r`` [m], or None: no floor."""
        return None if self.noise_floor is None else self.noise_floor * self.floor_scale(r)

    @staticmethod
    def of(lidar: LidarModel, reflectivity: float, keep_tolerance: float) -> _Options:
        """The options of ``lidar`` (its pulse, intensity model, detector floor and noise) for particles of
        ``reflectivity``."""
        return _Options(reflectivity, lidar.pulse, lidar.intensity, lidar.noise_floor, keep_tolerance,
                        lidar.intensity_noise_std, lidar.intensity_noise_rel, lidar.range_noise_std_m,
                        lidar.min_range_m, lidar.floor_range_m)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.reflectivity) and 0.0 <= self.reflectivity <= 1.0):
            raise ValueError(f"reflectivity = {self.reflectivity!r}; expected a value in [0, 1]")
        if self.noise_floor is not None and not (math.isfinite(self.noise_floor) and self.noise_floor >= 0.0):
            raise ValueError(f"noise_floor = {self.noise_floor!r}; expected None or a value >= 0 (0..255 scale)")
        if not (math.isfinite(self.keep_tolerance) and self.keep_tolerance >= 0.0):
            raise ValueError(f"keep_tolerance = {self.keep_tolerance!r}; expected a distance >= 0 m")


class _Response(NamedTuple):
    """What `_respond` returns."""

    outcome: BeamOutcome  # per beam (B,)
    ratios: F64  # (H,) occlusion ratio of each hit
    n_sampled: int  # hits whose ratio was counted on the SAMPLE_GRID grid (of all scans of a joint run)


def beam_noise_keys(beams: Beams) -> NDArray[np.uint64]:
    """(B,) the detector-noise stream of each beam (`detector_noise_keys` of its firing time, direction and ring)."""
    return detector_noise_keys(beams.times, beams.directions, beams.ring)


def beam_floor(beams: Beams, lidar: LidarModel) -> F64 | float:
    """The detector floor (0..255) at each beam's length (B,), or the constant floor."""
    return lidar.noise_floor if lidar.floor_range_m is None else lidar.floor_at(beams.lengths)


def beam_clear_readings(beams: Beams, noise_floor: ArrayLike | None) -> F64 | None:
    """(B,) the clear value each beam's clear intensity stood for before the sensor rounded it (0..255,
    `weatheralign.lidar.quantum`): the returns' readings of an integer-quantised scan (`rounded_readings`) spread
    over their rounding intervals by their beams' noise streams, every other beam's ``intensity0`` as it is; None
    where the sensor rounded none."""
    ret = np.flatnonzero(beams.has_return)
    rounded = np.zeros(len(beams), dtype=bool)
    rounded[ret] = rounded_readings(beams.intensity0[ret])
    if not rounded.any():
        return None
    r = np.flatnonzero(rounded)
    uniforms = np.zeros(len(beams))
    uniforms[r] = reading_uniforms(detector_noise_keys(beams.times[r], beams.directions[r], beams.ring[r]))
    return clear_readings(beams.intensity0, rounded, noise_floor, uniforms)


def _joined_clear(parts: list[Beams], lidar: LidarModel) -> F64 | None:
    """`beam_clear_readings` of several scans' beams under ``lidar``'s floor, joined as `_joined_beams` joins them
    (None: none rounded)."""
    each = [beam_clear_readings(b, beam_floor(b, lidar)) for b in parts]
    if all(c is None for c in each):
        return None
    return np.concatenate([b.intensity0.astype(np.float64) if c is None else c for b, c in zip(parts, each)])


NO_CONTINUUM = Continuum(step=1.0, peak=np.zeros(1), peak_r=np.zeros(1), cum0=np.zeros(2), cumc=np.zeros(2),
                         cums=np.zeros(2))
"""No unresolved particles' echo (all particles resolved, or fog alone)."""

CONTINUUM_STEP = 0.02
"""Grid step [m] of the unresolved particles' waveform and of its table over beam lengths."""


def _medium(edges: F64, alphas: F64) -> Medium:
    return Medium(edges=edges, alphas=alphas, tau_edges=np.concatenate([[0.0], np.cumsum(alphas * np.diff(edges))]))


def unresolved_continuum(edges: F64, cross_section: F64, alphas: F64, opt: _Options,
                         step: float = CONTINUUM_STEP) -> Continuum:
    """The echo of the unresolved particles as a beam receives it, tabulated over the beam's length.

    The particles a range shell leaves unresolved cover ``cross_section[k]`` (K,) [m²/m³ = 1/m] of the beam per metre
    in shell k (``edges`` (K+1,) [m]): their geometric cross-section density, ``field.unresolved_extinction / 2``. As
    the resolved particles' pulses, each reflects ``scale ρ`` per unit share (`IntensityModel`), so their raw
    amplitude density at axial distance s is ``a(s) = scale ρ cross_section(s) ξ(s) / s² · exp(-2 τ(s))`` (``τ``:
    the one-way depth of the bulk extinction ``alphas`` (K,), as on every echo), and a beam ending at L receives
    the smooth waveform ``W_L(R) = ∫_0^{min(R, L)} a(s) sin²(π (R - s) / (c τ_H)) ds`` (on ``[R - c τ_H, R]``),
    the continuum the exact process (`weatheralign.reference.lidar_particles_exact`) sums with its sub-ray echoes.
    Returns ``C(L) = max_R W_L(R)`` and its position on ``L = i · step``, ``i = 0 ..`` until L passes the position of
    the untruncated waveform's maximum (beyond it ``C`` is that maximum: ``W_L <= W``). Midpoint rule on ``step``
    cells, sums of ``a``, ``a cos ωs``, ``a sin ωs`` (``sin² = (1 - cos ω(R - s)) / 2``, ω = 2π / (c τ_H)).
    """
    pl = opt.sensor.pulse_length
    top = float(edges[-1]) if math.isfinite(edges[-1]) else float(edges[-2])
    n = max(int(math.ceil(top / step)), 1)
    mid = (np.arange(n) + 0.5) * step
    k = np.clip(np.searchsorted(edges, mid, side="right") - 1, 0, len(cross_section) - 1)
    medium = _medium(edges, alphas)
    tau = medium.tau_edges[k] + alphas[k] * (mid - edges[k])
    xi = np.clip((mid - opt.sensor.r1) / (opt.sensor.r2 - opt.sensor.r1), 0.0, 1.0)
    amp = (opt.intensity_model.scale * opt.reflectivity) * cross_section[k] * xi / (mid * mid) * np.exp(-2.0 * tau)
    if not np.any(amp > 0.0):
        return NO_CONTINUUM
    omega = 2.0 * math.pi / pl
    cum = [np.concatenate([[0.0], np.cumsum(amp * w * step)]) for w in (1.0, np.cos(omega * mid), np.sin(omega * mid))]

    def between(a: F64, b: F64) -> list[F64]:  # ∫_a^b of a, a cos, a sin (a <= b on [0, n step], interpolated)
        return [np.interp(b, np.arange(n + 1) * step, c) - np.interp(a, np.arange(n + 1) * step, c) for c in cum]

    def wave(R: F64, L: F64) -> F64:
        lo, hi = np.clip(R - pl, 0.0, n * step), np.clip(np.minimum(R, L), 0.0, n * step)
        s0, sc, ss = between(lo, np.maximum(hi, lo))
        return 0.5 * s0 - 0.5 * (np.cos(omega * R) * sc + np.sin(omega * R) * ss)

    R = np.arange(int(math.ceil((n * step + pl) / step)) + 1) * step
    W = wave(R, np.full(len(R), np.inf))  # untruncated
    count = int(np.argmax(W)) + 2  # L = R[i]: up to just past the untruncated maximum
    run_max = np.maximum.accumulate(W[:count])  # max over R <= L: untouched by the truncation at L
    run_at = R[np.maximum.accumulate(np.where(W[:count] >= run_max, np.arange(count), 0))]
    L = R[:count, None]
    taps = np.arange(1, int(math.ceil(pl / step)) + 1) * step  # R in (L, L + c τ_H]
    after = wave(L + taps[None, :], L)
    j = np.argmax(after, axis=1)
    tail = after[np.arange(count), j]
    peak = np.maximum(run_max, tail)
    peak_r = np.where(tail > run_max, R[:count] + taps[j], run_at)
    return Continuum(step=float(step), peak=np.maximum(peak, 0.0), peak_r=peak_r, cum0=cum[0], cumc=cum[1],
                     cums=cum[2])


def _respond(beams: Beams, hits: HitArrays, edges: F64, alphas: F64, opt: _Options,
             continuum: Continuum = NO_CONTINUUM, clear: F64 | None = None) -> _Response:
    """Run the response kernel on the sorted ``hits`` with the bulk extinction ``alphas`` (K,) [1/m] on the range
    shells ``edges`` (K+1,) [m] and the unresolved particles' echo ``continuum``; ``clear`` (B,): the clear value
    each beam's intensity stood for before rounding (`beam_clear_readings`), None: as read."""
    n = len(beams)
    hit_off = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(hits.beam, minlength=n), out=hit_off[1:])
    medium = _medium(edges, alphas)
    ratios = np.zeros(len(hits.beam))
    outcome = BeamOutcome(state=np.empty(n, dtype=np.uint8), range=np.empty(n), intensity=np.empty(n),
                          dom=np.empty(n, dtype=np.int64))
    model = opt.intensity_model
    noisy = opt.intensity_noise_std > 0.0 or opt.intensity_noise_rel > 0.0 or opt.range_noise_std > 0.0
    targets = BeamTargets(has_ret=beams.has_return, lengths=beams.lengths.astype(np.float64),
                          i0=beams.intensity0.astype(np.float64),
                          noise_key=beam_noise_keys(beams) if noisy else np.zeros(0, dtype=np.uint64),
                          clear=np.zeros(0) if clear is None else np.ascontiguousarray(clear, dtype=np.float64))
    pulse = PulseParams(pulse_len=opt.sensor.pulse_length, r1=opt.sensor.r1, r2=opt.sensor.r2,
                        part_gain=model.scale * opt.reflectivity, r_ref=model.r_ref, falloff=model.falloff,
                        keep_tol=opt.keep_tolerance, floor=-1.0 if opt.noise_floor is None else float(opt.noise_floor),
                        saturation=opt.sensor.saturation, grid_n=SAMPLE_GRID, noise_std=opt.intensity_noise_std,
                        noise_rel=opt.intensity_noise_rel, range_noise=opt.range_noise_std, min_range=opt.min_range,
                        comp_ref=0.0 if opt.floor_range_m is None else float(model.compensation(opt.floor_range_m)))
    n_sampled = response_kernel(hits, hit_off, targets, pulse, medium, continuum, ratios, outcome)
    return _Response(outcome, ratios, int(n_sampled))


def _particle_of(h_pid: I64, dom: I64) -> I64:
    """The particle id of each dominant hit ``dom`` (-1: no particle, e.g. a fog echo)."""
    return np.where(dom >= 0, h_pid[np.maximum(dom, 0)] if len(h_pid) else -1, -1).astype(np.int64)


def _fog_backscatter(beams: Beams, response: _Response, fog: FogMedium, opt: _Options) -> None:
    """Let the fog's soft-target echo compete with each beam's strongest echo (in place on ``response.outcome``).

    The fog model's backscatter (`weatheralign.lidar.fog`: peak ``I(R_0)`` at ``R_fog = min(R_0, R*)``, scaled by the
    beam's clear ``i_0 R_0²`` and ``β / β_0``) is a smooth waveform peaking a few metres from the sensor; the pulse
    sum of the particles and the target peaks at their ranges. The detector reports the larger peak: where the fog's
    exceeds the beam's echo (attenuated target, particle echo, or an echo pushed below the floor), the beam becomes a
    fog echo (SCATTERED, no particle id), read as `simulate_fog` reads it (the detector's intensity noise; reported at
    ``R_fog - c τ_H / 2`` plus the range noise, inside ``[r1, min(R_0, max_range)]``), LOST if that reading is under
    the floor and below ``i_0`` — the fog model's rule, so with no particles and a noise-free detector this is exactly
    `simulate_fog` (with noise: the same model, each beam's draws from its own stream). Beams without return have no
    ``i_0`` and get none, as in the fog model. The two waveforms are compared by their peaks, not summed: exact where
    they do not overlap in range (a particle within ~1.5 m of the fog peak, or a target nearer than R*, is the only
    case they do).
    """
    out = response.outcome
    ret = np.flatnonzero(beams.has_return & (beams.lengths > 0.0))
    if not len(ret) or fog.beta <= 0.0:
        return
    r0 = beams.lengths[ret]
    i0 = beams.intensity0[ret]
    sensor = opt.sensor
    comp = opt.intensity_model.compensation
    table = soft_target_response(fog.alpha, sensor)
    value, r_fog = table(r0)
    # raw powers (a reported value over R² g(R) at its range): the fog's against the beam's current echo
    soft_raw = value * i0 * (fog.beta / sensor.beta_0) / opt.intensity_model.gain(r0)
    state = out.state[ret]
    unchanged = state == WeatherLabel.UNCHANGED
    current = np.where(unchanged, i0, out.intensity[ret]) / comp(np.where(unchanged, r0, out.range[ret]))
    wins = np.flatnonzero(soft_raw > current)
    if not len(wins):
        return
    b = ret[wins]
    r_echo = np.clip(r_fog[wins] - 0.5 * sensor.pulse_length, sensor.r1, np.minimum(r0[wins], sensor.max_range))
    reading, reported = np.minimum(soft_raw[wins] * comp(r_echo), sensor.saturation), r_echo
    at_echo = opt.floor_scale(r_echo)
    noisy = opt.intensity_noise_std > 0.0 or opt.intensity_noise_rel > 0.0 or opt.range_noise_std > 0.0
    if noisy:
        z = reading_normals(beam_noise_keys(beams)[b])
        std = np.sqrt((opt.intensity_noise_std * at_echo) ** 2 + (opt.intensity_noise_rel * reading) ** 2)
        reading = np.clip(reading + std * z[:, 0], 0.0, sensor.saturation)
        reported = reported + opt.range_noise_std * np.clip(z[:, 1], -2.0, 2.0)
    reported = np.clip(reported, sensor.r1, np.minimum(r0[wins], sensor.max_range))
    floor = -1.0 if opt.noise_floor is None else float(opt.noise_floor)
    lost = (floor >= 0.0) & (reading < floor * at_echo) & (reading.astype(np.float32) < i0[wins].astype(np.float32))
    out.state[b] = np.where(lost, WeatherLabel.LOST, WeatherLabel.SCATTERED)
    out.range[b] = reported
    out.intensity[b] = reading
    out.dom[b] = -1


def _read_attenuated(beams: Beams, response: _Response, opt: _Options, clear: F64 | None = None) -> None:
    """The detector's reading of each target kept at its range (in place on ``response.outcome``: the kernel's
    ATTENUATED, and its LOST whose noise-free value it left at the target's range): its clear intensity ``i_0``
    carries its clear reading's noise, scaled with the signal by the transmission ``k = i / i_0``; the reading lacks
    ``σ_0² (1 - k²)`` of its variance (``intensity_noise_std`` σ_0; the proportional part scales exactly), added from
    the beam's noise stream (the first normal, unused by a kept target), as `weatheralign.lidar.fog` does. The floor
    then decides on the reading, as in fog: LOST if the weather pushed it below the floor at the target (and below
    ``i_0``), else ATTENUATED, tested on the clear value ``clear`` (B,) the rounded ``i_0`` stood for
    (`beam_clear_readings`; None: ``i_0``) carried through ``k`` (`weatheralign.lidar.quantum.attenuated_reading`).
    A noise-free detector keeps the kernel's decision (the same test on the same value)."""
    if opt.intensity_noise_std <= 0.0:
        return
    out = response.outcome
    at_range = (out.state == WeatherLabel.ATTENUATED) | ((out.state == WeatherLabel.LOST) & np.isfinite(out.range))
    b = np.flatnonzero(at_range & beams.has_return & (beams.intensity0 > 0.0))
    if not len(b):
        return
    i0 = beams.intensity0[b]
    k = np.minimum(out.intensity[b] / i0, 1.0)
    at_target = opt.floor_scale(beams.lengths[b])
    std = opt.intensity_noise_std * at_target * np.sqrt(np.maximum(1.0 - k * k, 0.0))
    reading = np.clip(out.intensity[b] + std * reading_normals(beam_noise_keys(beams)[b])[:, 0], 0.0,
                      opt.sensor.saturation)
    out.intensity[b] = reading
    if opt.noise_floor is not None:
        x = i0 if clear is None else clear[b]
        seen = attenuated_reading(reading, i0, x, k)
        lost = (seen < opt.noise_floor * at_target) & (seen.astype(np.float32) < x.astype(np.float32))
        out.state[b] = np.where(lost, WeatherLabel.LOST, WeatherLabel.ATTENUATED)


def _assemble(beams: Beams, points: NDArray[np.float32], T_global_out: F64, intensity_max: float, hits: HitArrays,
              response: _Response, stats: dict) -> ParticleResult:
    """Output points, labels and ids from the per-beam outcome."""
    outcome = response.outcome
    state, rng, inten, dom = outcome.state, outcome.range, outcome.intensity, outcome.dom
    stats["beams_sampled_occlusion"] = response.n_sampled
    h_pid = hits.pid
    n_in = len(points)
    T_out_global = invert(T_global_out)

    ret = np.flatnonzero(beams.has_return)
    pidx = beams.point_index[ret]
    input_labels = np.zeros(n_in, dtype=np.uint8)
    out = points.copy()
    pid_in = np.full(n_in, -1, dtype=np.int64)

    st = state[ret]
    keep_pos = st == WeatherLabel.ATTENUATED
    rows = pidx[keep_pos]
    new_i = (inten[ret][keep_pos] * (intensity_max / 255.0)).astype(np.float32)
    out[rows, 3] = new_i
    input_labels[rows] = np.where(new_i == points[rows, 3], WeatherLabel.UNCHANGED, WeatherLabel.ATTENUATED)
    scat = st == WeatherLabel.SCATTERED
    b_sc = ret[scat]
    rows = pidx[scat]
    p_g = beams.origins[b_sc] + beams.directions[b_sc] * rng[b_sc, None]
    out[rows, :3] = (p_g @ T_out_global[:3, :3].T + T_out_global[:3, 3]).astype(np.float32)
    out[rows, 3] = (inten[b_sc] * (intensity_max / 255.0)).astype(np.float32)
    input_labels[rows] = WeatherLabel.SCATTERED
    pid_in[rows] = _particle_of(h_pid, dom[b_sc])
    input_labels[pidx[st == WeatherLabel.LOST]] = WeatherLabel.LOST

    kept = np.flatnonzero(input_labels != WeatherLabel.LOST)
    clutter = np.flatnonzero(~beams.has_return & (state == WeatherLabel.SCATTERED))
    p_c = beams.origins[clutter] + beams.directions[clutter] * rng[clutter, None]
    c_pts = np.empty((len(clutter), 5), dtype=np.float32)
    c_pts[:, :3] = p_c @ T_out_global[:3, :3].T + T_out_global[:3, 3]
    c_pts[:, 3] = (inten[clutter] * (intensity_max / 255.0)).astype(np.float32)
    c_pts[:, 4] = beams.ring[clutter]

    beam_of_point = np.full(n_in, -1, dtype=np.int64)
    beam_of_point[pidx] = ret
    times_in = np.where(beam_of_point >= 0, beams.times[np.maximum(beam_of_point, 0)], np.nan)
    counts = np.bincount(input_labels, minlength=len(POINT_LABELS))
    beam_label = np.full(len(beams), WeatherLabel.NO_ECHO, dtype=np.uint8)
    beam_label[ret] = input_labels[pidx]
    beam_label[clutter] = WeatherLabel.SCATTERED
    detected = (state != WeatherLabel.NO_ECHO) & (state != WeatherLabel.LOST)
    beam_range = np.where(detected, rng, np.nan)
    beam_intensity = np.where(detected, inten, 0.0)
    beam_particle = np.full(len(beams), -1, dtype=np.int64)
    sc = np.flatnonzero(state == WeatherLabel.SCATTERED)
    beam_particle[sc] = _particle_of(h_pid, dom[sc])
    return ParticleResult(
        points=np.concatenate([out[kept], c_pts]),
        labels=np.concatenate([input_labels[kept], np.full(len(clutter), WeatherLabel.SCATTERED, np.uint8)]),
        particle_id=np.concatenate([pid_in[kept], _particle_of(h_pid, dom[clutter])]),
        source_index=np.concatenate([kept.astype(np.int64), np.full(len(clutter), -1, dtype=np.int64)]),
        times=np.concatenate([times_in[kept], beams.times[clutter]]),
        input_labels=input_labels,
        counts={**{label.name: int(counts[label]) for label in POINT_LABELS}, "CLUTTER": int(len(clutter))},
        intensity_max=float(intensity_max),
        hits=BeamHits(hits.beam, h_pid, hits.s, response.ratios,
                      np.stack([hits.u1, hits.u2], axis=1) if len(hits.u1) else np.zeros((0, 2)), hits.a),
        beam_index=np.concatenate([beam_of_point[kept], clutter.astype(np.int64)]),
        beam_range=beam_range,
        beam_intensity=beam_intensity,
        beam_particle=beam_particle,
        beam_label=beam_label,
        stats=stats,
    )


def _identity(beams: Beams, points: NDArray[np.float32], intensity_max: float, stats: dict) -> ParticleResult:
    """The input returned unchanged (no particles, no extinction)."""
    n = len(points)
    ret = np.flatnonzero(beams.has_return)
    times = np.full(n, np.nan)
    times[beams.point_index[ret]] = beams.times[ret]
    beam_label = np.full(len(beams), WeatherLabel.NO_ECHO, dtype=np.uint8)
    beam_label[ret] = WeatherLabel.UNCHANGED
    beam_range = np.where(beams.has_return, beams.lengths, np.nan)
    beam_of_point = np.full(n, -1, dtype=np.int64)
    beam_of_point[beams.point_index[ret]] = ret
    empty_i = np.zeros(0, dtype=np.int64)
    return ParticleResult(
        points=points.copy(), labels=np.zeros(n, dtype=np.uint8), particle_id=np.full(n, -1, dtype=np.int64),
        source_index=np.arange(n, dtype=np.int64), times=times, input_labels=np.zeros(n, dtype=np.uint8),
        counts={**{label.name: 0 for label in POINT_LABELS}, "UNCHANGED": n, "CLUTTER": 0},
        intensity_max=float(intensity_max),
        hits=BeamHits(empty_i, empty_i.copy(), np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros(0)),
        beam_index=beam_of_point, beam_range=beam_range,
        beam_intensity=np.where(beams.has_return, beams.intensity0, 0.0),
        beam_particle=np.full(len(beams), -1, dtype=np.int64), beam_label=beam_label, stats=stats)


def _inputs(scan: LidarScan | Beams, *, lidar: LidarModel, T_global_lidar: F64 | None, intensity_max: float | None,
            columns: object, reconstruct: bool, faint_surfaces: bool = False) -> tuple[Beams, NDArray, F64, float]:
    """(beams, input points (N, 5) float32, output frame T_global_out, intensity scale); a scan's beams with its
    surfaces under the floor if ``faint_surfaces``: `with_faint_surfaces`, then the fitted ground plane for the beams
    still open (`with_ground_plane`)."""
    if isinstance(scan, LidarScan):
        beams = beams_from_scan(scan, lidar=lidar, columns=columns, reconstruct=reconstruct)
        if faint_surfaces:
            scale = None if lidar.floor_range_m is None else lidar.floor_scale
            beams = with_faint_surfaces(beams, lidar.noise_floor, scale)
            beams = with_ground_plane(beams, scan_ground_plane(scan), lidar.noise_floor, scale)
        T = scan.T_global_lidar if T_global_lidar is None else np.asarray(T_global_lidar, dtype=np.float64)
        return beams, scan.points, T, float(scan.intensity_max)
    if not isinstance(scan, Beams):
        raise TypeError(f"expected a LidarScan or Beams, got {type(scan).__name__}")
    beams = scan
    T = np.eye(4) if T_global_lidar is None else np.asarray(T_global_lidar, dtype=np.float64)
    imax = 255.0 if intensity_max is None else float(intensity_max)
    if imax not in (1.0, 255.0):
        raise ValueError(f"intensity_max = {intensity_max!r}; expected 1.0 or 255.0")
    ret = np.flatnonzero(beams.has_return)
    order = np.argsort(beams.point_index[ret])
    ret = ret[order]
    T_inv = invert(T)
    p_g = beams.origins[ret] + beams.directions[ret] * beams.lengths[ret, None]
    pts = np.empty((len(ret), 5), dtype=np.float32)
    pts[:, :3] = p_g @ T_inv[:3, :3].T + T_inv[:3, 3]
    pts[:, 3] = beams.intensity0[ret] * (imax / 255.0)
    pts[:, 4] = beams.ring[ret]
    if len(ret) and not np.array_equal(beams.point_index[ret], np.arange(len(ret))):
        raise ValueError("Beams.point_index of the beams with a return must be 0..M-1")
    return beams, pts, T, imax


# ============================================================================================== public API


def auto_ratio_threshold(reflectivity: float) -> float:
    """The default occlusion-ratio threshold for particles of ``reflectivity``: `DEFAULT_RATIO_THRESHOLD` (1e-3) for
    snow (0.9), scaled by ``0.9 / reflectivity`` for darker particles and capped at `MAX_AUTO_RATIO_THRESHOLD`.

    A resolved particle matters through its occlusion (∝ ratio), which the bulk term reproduces on average, and its
    echo (∝ reflectivity x ratio), which it cannot: the same echo resolution for every medium means a threshold
    inversely proportional to the reflectivity. Measured on a 35k-point synthetic-world scan
    (``benchmarks/bench_lidar_particles.py``): rain at 50 mm/h gives identical counts from 3e-4 to 3e-2, the same
    mean intensity change (0.978), and a share of points losing > 10 % that drifts from 3.6 % (3e-4) to 3.5 % (1e-2)
    and 3.2 % (3e-2) — hence the cap; snow's scattered count moves by < 0.5 % up to 3e-3 but by -8 % at 1e-2.
    """
    rho = float(reflectivity)
    if not (math.isfinite(rho) and 0.0 <= rho <= 1.0):
        raise ValueError(f"reflectivity = {reflectivity!r}; expected a value in [0, 1]")
    if rho <= 0.0:
        return MAX_AUTO_RATIO_THRESHOLD
    return float(min(MAX_AUTO_RATIO_THRESHOLD, DEFAULT_RATIO_THRESHOLD * max(1.0, SNOW_REFLECTIVITY / rho)))


def simulate_particles(
    scan: LidarScan | Beams,
    field: ParticleField | None,
    *,
    lidar: LidarModel,
    reflectivity: float,
    fog: FogMedium | None = None,
    ratio_threshold: float | None = None,
    attenuation: bool = True,
    keep_tolerance: float = KEEP_TOLERANCE,
    T_global_lidar: F64 | None = None,
    intensity_max: float | None = None,
    columns: object = "auto",
    reconstruct: bool = True,
    unresolved_extinction_factor: float = 0.25,
    unresolved_echo: bool = True,
    faint_surfaces: bool = True,
    shell_ratio: float = SHELL_RATIO,
    first_shell: float = FIRST_SHELL,
    max_particles_per_shell: int = DEFAULT_MAX_PARTICLES,
) -> ParticleResult:
    """Snow or rain (optionally inside fog) on a LiDAR scan: every beam through the one 3-D particle ``field`` (see
    the package docstring).

    Args:
        scan: a `LidarScan` (its beams are built with `beams_from_scan`, beams without return included) or `Beams`.
        field: the shared particle field (global coordinates); None or zero density (and no fog) returns the input
            exactly.
        lidar: the sensor (`weatheralign.sensors.LidarModel`): divergence and maximum range (of a `LidarScan`'s
            beams; `Beams` carry their own), firing grid, pulse (τ_H, overlap ξ, saturation), intensity model (which
            calibrates particle echoes) and detector noise floor (0..255).
        reflectivity: particle reflectivity: `SNOW_REFLECTIVITY` (0.9) or `RAIN_REFLECTIVITY` (0.02).
        fog: a fog medium in the same air (mixed weather): its extinction attenuates every echo two-way (added to the
            particles' bulk extinction) and its backscatter competes with each beam's strongest echo
            (`_fog_backscatter`); None for none.
        ratio_threshold: particles covering less than this share of a beam even when centred on it are folded into
            the bulk extinction instead of being materialised (0 materialises everything: feasible for thin fields).
            None: `auto_ratio_threshold` (1e-3 for snow; scaled by 0.9 / reflectivity, at most 1e-2, for darker
            particles, whose echoes are that much weaker: rain gets 1e-2).
        attenuation: apply the bulk extinction of the unresolved particles (two-way).
        keep_tolerance: a peak within this distance [m] of a point's range keeps the point in place.
        T_global_lidar: the output frame (default: the scan's sensor frame; identity for `Beams`).
        intensity_max: intensity scale of the output for `Beams` input (255 or 1; a scan keeps its own).
        columns, reconstruct: how beams without return are found (`beams_from_scan`).
        unresolved_extinction_factor: the unresolved particles attenuate every echo at range s by
            ``exp(-2 · factor · ∫_0^s field.unresolved_extinction(threshold) ds)``. 0.25 (default) is their
            geometric shadow counted once — exactly how a resolved particle's occlusion ratio acts on the target
            (a monostatic beam is hidden where it is shadowed) — so the result does not depend on
            ``ratio_threshold`` (measured: mean intensity change and counts stay put from 3e-4 to 3e-2); 1.0 is
            two-way Beer–Lambert with the medium's Q_ext = 2 extinction (the fog model's convention).
        unresolved_echo: the unresolved particles also return light, as a smooth waveform peaking a few metres out
            (`unresolved_continuum`); where its peak beats the pulse sum's, the beam reads it (a SCATTERED point
            without particle id, or nothing if it is under the floor: then the target's own echo decides). Weak and
            rarely detected, it matters because a strongest-return receiver never reports a weaker echo behind it:
            without it rain's faint far drops on open beams come back 2-3x too often (against the reference's exact
            waveform). False: particle and target pulses alone.
        faint_surfaces: a scan's beams without return that lie between two returns of a surface at the detector
            floor are taken to hit that surface under the floor (`weatheralign.lidar.beams.with_faint_surfaces`),
            and those still open that point below the horizon hit the scan's fitted ground plane under the floor
            (`weatheralign.lidar.beams.with_ground_plane`): an undetectable echo still outshines weaker weather
            echoes, and the surface ends the beam. False: every beam without return is open to ``max_range``.
            (`Beams` inputs are used as given.)
        shell_ratio, first_shell: geometric range shells (``[0, first, first·ratio, ...]`` [m]).
        max_particles_per_shell: refuse a shell query expecting more particles (raise ``ratio_threshold``).

    Returns:
        `ParticleResult` in the scan's frame and intensity scale.
    """
    return simulate_particle_scans(
        [scan], field, lidar=lidar, reflectivity=reflectivity, fog=fog, ratio_threshold=ratio_threshold,
        attenuation=attenuation, keep_tolerance=keep_tolerance, T_global_lidar=T_global_lidar,
        intensity_max=intensity_max, columns=columns, reconstruct=reconstruct,
        unresolved_extinction_factor=unresolved_extinction_factor, unresolved_echo=unresolved_echo,
        faint_surfaces=faint_surfaces, shell_ratio=shell_ratio, first_shell=first_shell,
        max_particles_per_shell=max_particles_per_shell)[0]


def _joined_beams(parts: list[Beams]) -> tuple[Beams, I64]:
    """The beams of several scans of one sensor as one `Beams` (``point_index`` kept per scan) and the first beam of
    each scan (S+1,)."""
    first = parts[0]
    for k, b in enumerate(parts[1:], start=1):
        if b.divergence != first.divergence or b.max_range != first.max_range:
            raise ValueError(f"scan {k}: beams of divergence {b.divergence} rad / max_range {b.max_range} m, but scan "
                             f"0 has {first.divergence} rad / {first.max_range} m (one sensor expected)")
    offsets = np.zeros(len(parts) + 1, dtype=np.int64)
    np.cumsum([len(b) for b in parts], out=offsets[1:])
    if len(parts) == 1:
        return first, offsets

    def cat(name: str) -> NDArray:
        return np.concatenate([getattr(b, name) for b in parts])

    return Beams(cat("origins"), cat("directions"), cat("times"), cat("lengths"), cat("has_return"),
                 cat("intensity0"), cat("ring"), cat("point_index"), first.divergence, first.max_range), offsets


def _scan_part(beams: Beams, b0: int, hits: HitArrays, response: _Response) -> tuple[HitArrays, _Response]:
    """The hits and per-beam response of the beams ``b0 .. b0 + len(beams)`` of a joined run, re-indexed to them
    (``n_sampled`` stays the joint run's)."""
    h0, h1 = np.searchsorted(hits.beam, [b0, b0 + len(beams)])
    part = HitArrays(hits.beam[h0:h1] - b0, *(a[h0:h1] for a in hits[1:]))
    out = response.outcome
    sl = slice(b0, b0 + len(beams))
    dom = out.dom[sl]
    outcome = BeamOutcome(out.state[sl], out.range[sl], out.intensity[sl], np.where(dom >= 0, dom - h0, -1))
    return part, _Response(outcome, response.ratios[h0:h1], response.n_sampled)


def simulate_particle_scans(
    scans: list[LidarScan | Beams],
    field: ParticleField | None,
    *,
    lidar: LidarModel,
    reflectivity: float,
    fog: FogMedium | None = None,
    ratio_threshold: float | None = None,
    attenuation: bool = True,
    keep_tolerance: float = KEEP_TOLERANCE,
    T_global_lidar: F64 | None = None,
    intensity_max: float | None = None,
    columns: object = "auto",
    reconstruct: bool = True,
    unresolved_extinction_factor: float = 0.25,
    unresolved_echo: bool = True,
    faint_surfaces: bool = True,
    shell_ratio: float = SHELL_RATIO,
    first_shell: float = FIRST_SHELL,
    max_particles_per_shell: int = DEFAULT_MAX_PARTICLES,
) -> list[ParticleResult]:
    """`simulate_particles` on several scans of one sensor at once (a keyframe and the sweeps before it): the beams of
    all scans are matched against the one ``field`` together, so each field cell is generated once for all of them
    (the scans of a 20 Hz LiDAR 50 ms apart reach nearly the same cells). Each beam still meets the particles at its
    own firing time, so a scan's result differs from `simulate_particles` on it alone only through the range shells'
    resolution thresholds, which are set for the joint spread of beam origins (a little lower: more of the field is
    resolved; with ``ratio_threshold=0`` the results are the same). One result per scan, in that scan's own frame
    (``T_global_lidar``: one output frame for all) and intensity scale; ``stats`` are the joint run's, with the scan's
    own beam counts. Arguments as in `simulate_particles`.
    """
    if not scans:
        raise ValueError("simulate_particle_scans: no scans given")
    inputs = [_inputs(s, lidar=lidar, T_global_lidar=T_global_lidar, intensity_max=intensity_max, columns=columns,
                      reconstruct=reconstruct, faint_surfaces=faint_surfaces) for s in scans]
    beams, offsets = _joined_beams([i[0] for i in inputs])
    clear = _joined_clear([i[0] for i in inputs], lidar)
    opt = _Options.of(lidar, reflectivity, keep_tolerance)
    if ratio_threshold is None:
        ratio_threshold = auto_ratio_threshold(reflectivity)
    if not (math.isfinite(ratio_threshold) and 0.0 <= ratio_threshold < 1.0):
        raise ValueError(f"ratio_threshold = {ratio_threshold!r}; expected 0 <= ratio_threshold < 1")
    if not (math.isfinite(unresolved_extinction_factor) and unresolved_extinction_factor >= 0.0):
        raise ValueError(f"unresolved_extinction_factor = {unresolved_extinction_factor!r}; expected a value >= 0")
    if not (shell_ratio > 1.0 and first_shell > 0.0):
        raise ValueError(f"shell_ratio = {shell_ratio!r} must exceed 1 and first_shell = {first_shell!r} be > 0")

    def scan_stats(b: Beams) -> dict:
        return {"num_beams": len(b), "num_beams_without_return": len(b) - b.num_returns,
                "ratio_threshold": float(ratio_threshold), "scans_joined": len(scans)}

    fog_alpha = 0.0 if fog is None else fog.alpha
    empty = field is None or field.number_density() <= 0.0
    if len(beams) == 0 or (empty and fog_alpha <= 0.0):
        return [_identity(b, pts, imax, scan_stats(b)) for b, pts, _, imax in inputs]
    if empty:  # fog alone, through the same response: no hits, the fog's extinction everywhere
        hits = empty_hits()
        response = _respond(beams, hits, np.array([0.0, 1e300]), np.array([fog_alpha]), opt, clear=clear)
        _fog_backscatter(beams, response, fog, opt)
        _read_attenuated(beams, response, opt, clear)
        joint: dict = {}
    else:
        hits, response, joint = _field_response(beams, field, opt, fog, float(ratio_threshold), attenuation,
                                                unresolved_extinction_factor, unresolved_echo, shell_ratio,
                                                first_shell, max_particles_per_shell, clear)
    results = []
    for (b, pts, T_out, imax), b0 in zip(inputs, offsets[:-1]):
        part_hits, part_response = _scan_part(b, int(b0), hits, response)
        results.append(_assemble(b, pts, T_out, imax, part_hits, part_response, {**scan_stats(b), **joint}))
    return results


def _field_response(beams: Beams, field: ParticleField, opt: _Options, fog: FogMedium | None, ratio_threshold: float,
                    attenuation: bool, unresolved_extinction_factor: float, unresolved_echo: bool,
                    shell_ratio: float, first_shell: float, max_particles_per_shell: int, clear: F64 | None = None
                    ) -> tuple[HitArrays, _Response, dict]:
    """The hits of the resolved particles of ``field`` on ``beams``, sorted by beam then range, the per-beam response
    (with the unresolved particles' and the fog's extinction, the unresolved particles' echo, and the fog's
    backscatter; ``clear``: `beam_clear_readings`) and the run's diagnostics (range shells, reference time,
    particles, origin spread)."""
    fog_alpha = 0.0 if fog is None else fog.alpha
    index = index_beams(beams)
    vel = field.velocity_array
    speed = float(np.linalg.norm(vel))
    e_all = index.e_origin + speed * index.beams.t_half
    r_max = 0.5 * field.spectrum.d_max
    reach = float(beams.lengths.max()) + e_all + r_max + 0.01
    edges = shell_edges(reach, first_shell, shell_ratio)
    sq = math.sqrt(ratio_threshold)
    s_near = np.maximum(0.0, edges[:-1] - e_all - r_max - 0.05)
    thresholds = 2.0 * index.beams.tanh * s_near * sq  # min diameter per shell [m]
    unresolved = np.array([field.unresolved_extinction(m) for m in thresholds])  # Q_ext = 2 [1/m]
    alphas = unresolved * unresolved_extinction_factor if attenuation else np.zeros(len(thresholds))
    alphas = alphas + fog_alpha if fog_alpha > 0.0 else alphas
    # shells whose threshold leaves no particle (rank cut-off < 0: beyond the largest diameter) need no cells
    empty_from = np.flatnonzero(rank_cutoffs(field, thresholds)[1] < 0.0)
    s_cut = float(edges[empty_from[0]]) if len(empty_from) else float(edges[-1])
    cells, d_near = reachable_cells(field, index, index.t_ref, float(edges[-1]), e_all, r_max, s_cut)
    # each cell is materialised once, with the threshold of the shell of its nearest point (<= that of any of its
    # particles' own shell, which the hit kernel then applies per particle)
    cell_shell = np.clip(np.searchsorted(edges, d_near, side="right") - 1, 0, len(thresholds) - 1)
    order = np.argsort(cell_shell, kind="stable")
    shell_off = np.searchsorted(cell_shell[order], np.arange(len(thresholds) + 1))
    hits, per_shell = field_hits(field, index, cells[order], shell_off, range_shells(edges, thresholds),
                                 max_particles_per_shell)
    shells = [{"s0": float(edges[k]), "s1": float(edges[k + 1]), "min_diameter": float(thresholds[k]),
               "cells": int(shell_off[k + 1] - shell_off[k]), "particles": int(per_shell[k, 0]),
               "hits": int(per_shell[k, 1]), "unresolved_extinction": float(alphas[k])}
              for k in range(len(thresholds))]
    continuum = unresolved_continuum(edges, 0.5 * unresolved, alphas, opt) if unresolved_echo else NO_CONTINUUM
    response = _respond(beams, hits, edges, alphas, opt, continuum, clear)
    if fog is not None and fog_alpha > 0.0:
        _fog_backscatter(beams, response, fog, opt)
    _read_attenuated(beams, response, opt, clear)
    return hits, response, {"shells": shells, "t_ref": index.t_ref, "particles": sum(x["particles"] for x in shells),
                            "origin_spread": index.e_origin}


def simulate_particle_list(
    scan: LidarScan | Beams,
    particles: Particles,
    velocity: F64 | tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    lidar: LidarModel,
    reflectivity: float,
    extinction: float = 0.0,
    unresolved_cross_section: float = 0.0,
    keep_tolerance: float = KEEP_TOLERANCE,
    T_global_lidar: F64 | None = None,
    intensity_max: float | None = None,
    columns: object = "auto",
    reconstruct: bool = True,
) -> ParticleResult:
    """The same beam model with an explicit particle list (all resolved) and a homogeneous bulk ``extinction``
    [1/m] applied two-way (``exp(-2 α s)`` on every echo): ``particles`` (global positions at ``particles.t``) move
    with ``velocity`` (3,) [m/s]. ``unresolved_cross_section`` [m²/m³]: unresolved particles of that geometric
    cross-section density everywhere, whose echo (`unresolved_continuum`) competes with the pulses (their extinction
    is ``extinction``'s to set). For tests, hand-placed scenes, or particles from elsewhere; other arguments as in
    `simulate_particles`."""
    beams, points, T_out, imax = _inputs(scan, lidar=lidar, T_global_lidar=T_global_lidar,
                                         intensity_max=intensity_max, columns=columns, reconstruct=reconstruct)
    opt = _Options.of(lidar, reflectivity, keep_tolerance)
    if not (math.isfinite(extinction) and extinction >= 0.0):
        raise ValueError(f"extinction = {extinction!r}; expected a finite value >= 0 [1/m]")
    if not (math.isfinite(unresolved_cross_section) and unresolved_cross_section >= 0.0):
        raise ValueError(f"unresolved_cross_section = {unresolved_cross_section!r}; expected a finite value >= 0 "
                         f"[m²/m³]")
    stats: dict = {"num_beams": len(beams), "num_beams_without_return": len(beams) - beams.num_returns,
                   "particles": len(particles)}
    if (len(particles) == 0 and extinction == 0.0 and unresolved_cross_section == 0.0) or len(beams) == 0:
        return _identity(beams, points, imax, stats)
    vel = np.asarray(velocity, dtype=np.float64).reshape(3)
    index = index_beams(beams)
    pos = np.ascontiguousarray(np.asarray(particles.positions, dtype=np.float64).reshape(-1, 3) - index.center)
    batch = ParticleBatch(pos=pos, radius=0.5 * np.asarray(particles.diameters, dtype=np.float64),
                          ids=np.asarray(particles.ids, dtype=np.int64), vel=vel, t_part=float(particles.t))
    hits = list_hits(index, batch, range_shells(np.array([0.0, math.inf]), np.zeros(1)))  # all resolved
    edges, alphas = np.array([0.0, float(beams.lengths.max()) + 1.0]), np.array([float(extinction)])
    continuum = (unresolved_continuum(edges, np.array([float(unresolved_cross_section)]), alphas, opt)
                 if unresolved_cross_section > 0.0 else NO_CONTINUUM)
    clear = beam_clear_readings(beams, beam_floor(beams, lidar))
    response = _respond(beams, hits, np.array([0.0, 1e300]), alphas, opt, continuum, clear)
    _read_attenuated(beams, response, opt, clear)
    return _assemble(beams, points, T_out, imax, hits, response, stats)
