"""The synthetic reference's LiDAR in snow and rain: every beam traced through the particle field by sub-rays.

This is the reference's own process ("the real world" the fast particle simulator `weatheralign.lidar.particles` is
calibrated against). It shares no kernel with that simulator: each beam is sampled by Monte-Carlo sub-rays that are
intersected exactly with every particle near the beam, and the received waveform is searched numerically, for the
same physical sensor as `lidar_exact` (``docs/physics.md`` sections 1 and 3; pulse, exact bi-static overlap ξ and
detector from `lidar_exact`).

The beam. A cone of full divergence θ from the sensor origin along the beam's unit direction ``u``; one instant
``t`` for the whole scan (particle positions from `ParticleField.materialize` at ``t``; opaque spheres of diameter
``D``). The cone is sampled by ``K`` sub-rays (default 64) with a uniform (top-hat) profile: sub-ray ``k`` points
along ``u + tan(θ/2) sqrt((k + ½)/K) (cos φ_k e1 + sin φ_k e2)``, ``φ_k = φ_b + k · 137.5°`` (a sunflower pattern:
every sub-ray stands for 1/K of the cross-section), rotated per beam by ``φ_b`` hashed (SplitMix64) from ``seed``
and the beam's index. Every sub-ray carries 1/K of the power and stops at the nearest of: the exact ray–sphere entry
point of any resolved particle, or the target, taken at range ``r0`` along every sub-ray (``inf``: no target).

The waveform on the receiver axis ``R`` [m] (raw units of the `IntensityModel`)::

    P(R) = Σ_j (1/K) w_j ξ(r_j) T(r_j) / r_j² · k(R - r_j)                           (sub-ray echoes)
         + ∫_0^{min(R, r0)} scale ρ a_u(r) u(r) ξ(r) T(r) / r² · k(R - r) dr           (unresolved continuum)

with the pulse ``k(s) = sin²(π s / (c τ_H))`` on ``[0, c τ_H]`` (0 outside), ``r_j`` the hit distance along sub-ray
``j``, ``w_j = scale ρ`` for a particle (a Lambertian disc of reflectivity ρ facing the sensor; rain: the Fresnel
part 0.02 of an opaque drop, snow 0.9) and ``w = i0 / g(r0)`` for the target (so that a clear target at
``r0 >= r2`` reports exactly its clear intensity ``i0``). ``T(r) = exp(-∫_0^r a_u(s) ds)`` is the shadow of the
unresolved particles, ``a_u`` their geometric cross-section per m³ (``∫ N(D) π D² / 4 dD`` over the unresolved
sizes, Q = 1: the share of the beam they cover per metre), applied once: the out-and-back paths of a (nearly)
monostatic sensor are shadowed by the same particles. ``u(r)`` is the share of sub-rays not yet stopped by a
resolved particle at ``r``: the cloud behind a resolved flake is dark in that sub-ray (on beams without resolved
hits ``u = 1``, the plain continuum ``∫_0^{min(R, r0)} scale ρ a_u ξ T / r² k dr``).

The peak. The strongest maximum of ``P`` over the listening window ``(0, sensor.listen_end]`` on the grid
``R_m = m · grid_step`` (2 cm), refined through the best node's neighbours by the three-point fit
``a + b cos ω(R - R_m) + c sin ω(R - R_m)``, ω = 2π / (c τ_H): the pulse's own shape, so exact for hard echoes,
and of a parabola's order on smooth (continuum) peaks. Reported range ``R_rep = R_peak - c τ_H / 2`` (a hard echo
peaks at ``r_j + c τ_H / 2``); reported intensity ``P(R_peak) · R_rep² · g(R_rep)`` with ``g`` the intensity model's
gain (a disc covering the beam at ``r`` reports ``scale ρ g(r)``). `ExactReturns` carries that intensity as
``power`` and ``R_peak`` as ``r_peak``, so `lidar_exact.read_out` applies the detector unchanged. ``source``:
`TARGET`, `FOG` (the continuum) or `PARTICLE` (all resolved particles together), whichever contributes most at the
peak; `ParticleReturns.particle_id` names the particle contributing most to a `PARTICLE` peak.

The receiver reports the strongest *detected* echo. Where the strongest peak is not the target's, the waveform at
the target's own echo crest ``R = r0 + c τ_H / 2`` (intensity ``P · r0² · g(r0)``) is kept as the beam's second
return (`ExactReturns.target_power`); `lidar_exact.read_out` reports it when the strongest peak is too weak to be
detected. Without it a drop's echo near the sensor, strongest on the raw waveform (1/r²) but below the floor once
read as an intensity, would hide a detectable target behind it: 1,300 of the ~100,000 targets within 20 m per scan
at 78 mm/h of rain, five times what the fast simulator loses on the same scans and field (it reads the target's
own echo in that case).

Resolved and unresolved particles. A particle at range ``r`` is resolved when, centred in the beam, it would alone
reach ``resolve_fraction`` of the detector noise floor: ``scale ρ min(1, (D / (r θ))²) g(r) >= resolve_fraction ·
noise_floor``, i.e. ``D >= D_res(r)``. Space is cut into range shells by the particle centre's distance,
``[0.05, 0.071), [0.071, 0.1), ...`` (ratio √2; ``[0, 0.05)``, inside the sensor's housing, is all continuum): in
a shell the particles with ``D >= D_res(inner radius)`` are materialised (one box per shell and azimuth sector
around the beams' cones, which stop at their targets; the field's layer limits its height) and traced; the smaller
ones make that shell's continuum ``a_u``, from the field's size spectrum.

What is exact: the ray–sphere and ray–target intersections of every sub-ray with every resolved particle near the
beam (candidates from an angular index of the beams; each candidate pair passes an exact sphere–cone test, and
only sub-rays whose angle from the axis is within the sphere's angular radius of the centre's can hit it); the
overlap ξ (`lidar_exact`); the pulse shape; the sum of all echoes on the receiver axis; ``T`` (closed form,
piecewise exponential); the continuum integral (running integrals of ``f``, ``f cos ωr``, ``f sin ωr`` on a 1 mm
grid, trapezoid rule, with ``k = ½ - ½ cos ω(R - r)``; ``u`` enters in closed form because it is a step function);
the grid search: between consecutive echo starts and ends the echo sum is ``a + A cos(ωR - φ)`` and the continuum
is at most ``u · max G`` (``G`` the continuum with nothing in front, tabulated on the grid with range maxima), so
only nodes where that bound beats the best value so far are evaluated (the same nodes win as in a full sweep);
continuum-only gaps between echoes reduce to ``u · max G``.
What is approximated: the cross-section is sampled by ``K`` sub-rays (a particle covering a share ``f`` of the beam
stops ``≈ f K`` of them: its echo is quantised to multiples of 1/K, unbiased over the beam rotations); the
unresolved particles are a continuum whose density depends on range only (the layer's vertical limits are not
applied to it); ``D_res`` is taken at the shell's inner radius (more particles resolved, never fewer); particles
are discs facing the sensor (no incidence-angle term).

Units: lengths in metres, angles in radians, intensities on the 0..255 scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from weatheralign.medium.field import ParticleField, splitmix64_py
from weatheralign.reference.lidar_exact import (
    FOG,
    TARGET,
    ExactReturns,
    ExactSensor,
    _overlap_one,
    bistatic_overlap,
    sensor_optics,
)
from weatheralign.reference.records import (
    BeamEvents,
    BeamParticles,
    ContinuumIntegrals,
    ContinuumNodes,
    EchoGain,
    ExactBeams,
    ParticlePeaks,
    SensorOptics,
    Shadow,
    SubrayPattern,
    SubrayScratch,
)
from weatheralign.sensors import SYNTHETIC_INTENSITY, IntensityModel, floor_scale

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

PARTICLE = 3
"""`ExactReturns.source` value of a peak dominated by resolved particles (`TARGET` = 1 and `FOG` = 2, the
unresolved continuum, as in `lidar_exact`)."""

TABLE_STEP_M = 1e-3
"""Grid step [m] of the continuum's running integrals."""

SHELL_RATIO = math.sqrt(2.0)
"""Outer over inner radius of the range shells (from `FIRST_SHELL_M`)."""

FIRST_SHELL_M = 0.05
"""Outer radius [m] of the first shell ``[0, FIRST_SHELL_M)``: particles centred there (inside the sensor's housing)
are never resolved, they belong to the continuum."""

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
"""Angle [rad] between consecutive sub-rays of the sunflower pattern."""

_MASK64 = (1 << 64) - 1


# ------------------------------------------------------------------------------------------------ unresolved medium
@dataclass(frozen=True)
class Unresolved:
    """The unresolved particles as a continuum: geometric cross-section per volume, piecewise constant in range.

    Attributes:
        edges: (S + 1,) shell edges [m], ``0 = e_0 < e_1 < ... < e_S = inf``.
        area: (S,) ``a_u`` [1/m] in each shell: ``∫ N(D) π D² / 4 dD`` over the unresolved sizes (>= 0).
    """

    edges: F64
    area: F64

    def __post_init__(self) -> None:
        e = np.ascontiguousarray(self.edges, dtype=np.float64)
        a = np.ascontiguousarray(self.area, dtype=np.float64)
        if (e.ndim != 1 or len(e) < 2 or e[0] != 0.0 or e[-1] != np.inf or not np.all(np.isfinite(e[:-1]))
                or not np.all(np.diff(e) > 0)):
            raise ValueError(f"Unresolved.edges = {self.edges!r}; expected (S + 1,) increasing shell edges [m] from "
                             "0 to inf")
        if a.shape != (len(e) - 1,) or not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ValueError(f"Unresolved.area: expected ({len(e) - 1},) finite cross-sections >= 0 [1/m], got "
                             f"{self.area!r}")
        e.setflags(write=False)
        a.setflags(write=False)
        object.__setattr__(self, "edges", e)
        object.__setattr__(self, "area", a)

    @staticmethod
    def none() -> Unresolved:
        """Clear air between the resolved particles."""
        return Unresolved(np.array([0.0, np.inf]), np.zeros(1))

    @staticmethod
    def homogeneous(area: float) -> Unresolved:
        """One cross-section ``area`` [1/m] at every range."""
        return Unresolved(np.array([0.0, np.inf]), np.array([float(area)]))

    @property
    def tau_edges(self) -> F64:
        """(S,) optical depth ``∫_0^{e_k} a_u`` at each shell's inner edge."""
        widths = np.diff(self.edges[:-1])
        return np.concatenate([[0.0], np.cumsum(self.area[:-1] * widths)])

    def area_at(self, r: ArrayLike) -> F64:
        """``a_u(r)`` [1/m] (any shape)."""
        r = np.asarray(r, dtype=np.float64)
        k = np.clip(np.searchsorted(self.edges, r, side="right") - 1, 0, len(self.area) - 1)
        return self.area[k]

    def transmission(self, r: ArrayLike) -> F64:
        """``T(r) = exp(-∫_0^r a_u)`` (any shape), r >= 0 [m]."""
        r = np.asarray(r, dtype=np.float64)
        k = np.clip(np.searchsorted(self.edges, r, side="right") - 1, 0, len(self.area) - 1)
        return np.exp(-(self.tau_edges[k] + self.area[k] * (r - self.edges[k])))


# ------------------------------------------------------------------------------------------------ result
@dataclass(frozen=True)
class ParticleReturns:
    """The strongest peak of every beam (B,) and what made it.

    Attributes:
        returns: `ExactReturns`: ``power`` the peak's intensity (0..255 scale, before the detector), ``r_peak`` the
            peak on the receiver axis [m] (reported range ``r_peak - c τ_H / 2``), ``source`` `TARGET`, `FOG`
            (unresolved continuum), `PARTICLE` or 0 (nothing received).
        particle_id: (B,) field id of the particle contributing most at the peak where ``source == PARTICLE``,
            else -1.
        particle_hits: (B,) number of sub-rays stopped by a resolved particle.
        n_resolved: resolved particles materialised (or given).
        n_pairs: beam–particle pairs whose sphere touches the cone (each tested against the sub-rays that can hit
            it).
        n_hits: sub-rays stopped by a resolved particle, all beams.
        unresolved: the continuum used (range shells and their ``a_u``).
        min_diameter: (S,) ``D_res`` of each shell [m] (``inf``: nothing resolved there), empty if particles were
            given explicitly.
    """

    returns: ExactReturns
    particle_id: I64
    particle_hits: NDArray[np.int32]
    n_resolved: int
    n_pairs: int
    n_hits: int
    unresolved: Unresolved
    min_diameter: F64


# ------------------------------------------------------------------------------------------------ public helpers
def resolved_diameter(r: ArrayLike, reflectivity: float, noise_floor: float, *, divergence_rad: float = 3e-3,
                      resolve_fraction: float = 0.05,
                      intensity_model: IntensityModel = SYNTHETIC_INTENSITY,
                      floor_range_m: float | None = None) -> F64:
    """``D_res(r)`` [m] (shape of ``r`` [m]): the smallest diameter that, centred in the beam at range ``r``, reaches
    ``resolve_fraction`` of the floor at ``r`` alone: ``scale ρ min(1, (D / (r θ))²) g(r) >= resolve_fraction ·
    floor(r)`` (``noise_floor``, scaled as ``R² g(R)`` from ``floor_range_m`` for a raw-power detector); ``inf``
    where even full coverage does not (or ρ = 0)."""
    r = np.asarray(r, dtype=np.float64)
    need = resolve_fraction * noise_floor * floor_scale(r, intensity_model, floor_range_m)
    full = intensity_model.scale * reflectivity * intensity_model.gain(r)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = r * divergence_rad * np.sqrt(need / full)
    return np.where((full > 0) & (need <= full), d, np.inf)


def range_shells(listen_end: float) -> F64:
    """Shell edges [m] ``0, 0.05, 0.05·√2, 0.1, ..., inf``: every finite edge below ``listen_end``, rounded to 1 mm."""
    edges = [0.0]
    e = FIRST_SHELL_M
    while e < listen_end:
        edges.append(round(e, 3))
        e *= SHELL_RATIO
    edges.append(math.inf)
    return np.asarray(edges)


def beam_rotations(n_beams: int, seed: int) -> F64:
    """(n,) rotation ``φ_b`` [rad] in ``[0, 2π)`` of every beam's sub-ray pattern: SplitMix64 of ``(seed, b)``."""
    key = splitmix64_py(splitmix64_py((int(seed) + 0x9E3779B97F4A7C15) & _MASK64) ^ 0x5B0_7A7E)
    idx = np.arange(n_beams, dtype=np.uint64)
    z = np.uint64(key) + (idx + np.uint64(1)) * np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * (2.0 * math.pi * 2.0**-53)


def subray_directions(directions: ArrayLike, *, sub_rays: int = 64, divergence_rad: float = 3e-3,
                      seed: int = 0) -> F64:
    """(B, K, 3) unit directions of the sub-rays of beams ``directions`` (B, 3) (the kernel's own pattern)."""
    d = _directions(directions)
    k = _check_int("sub_rays", sub_rays, 1, 4096)
    phi = beam_rotations(len(d), _check_int("seed", seed, 0, 2**63 - 1))
    out = np.empty((len(d), k, 3))
    px, py, pn = _pattern(k, math.tan(0.5 * _check_divergence(divergence_rad)))
    for b in range(len(d)):
        _subrays(d[b, 0], d[b, 1], d[b, 2], phi[b], px, py, pn, out[b])
    return out


def _pattern(k_sub: int, tan_a: float) -> tuple[F64, F64, F64]:
    """The unrotated sunflower pattern: offsets (K,) ``x, y`` on the disc of radius ``tan(θ/2)`` at unit distance and
    the normalisation ``1 / sqrt(1 + x² + y²)`` of each sub-ray."""
    k = np.arange(k_sub)
    rr = tan_a * np.sqrt((k + 0.5) / k_sub)
    ang = k * GOLDEN_ANGLE
    return rr * np.cos(ang), rr * np.sin(ang), 1.0 / np.sqrt(1.0 + rr * rr)


# ------------------------------------------------------------------------------------------------ entry points
def particle_returns(origin: ArrayLike, directions: ArrayLike, r0: ArrayLike, i0: ArrayLike, field: ParticleField,
                     t: float, reflectivity: float, sensor: ExactSensor, *, noise_floor: float,
                     divergence_rad: float = 3e-3, sub_rays: int = 64, resolve_fraction: float = 0.05,
                     intensity_model: IntensityModel = SYNTHETIC_INTENSITY, grid_step: float = 0.02,
                     seed: int = 0, floor_range_m: float | None = None) -> ParticleReturns:
    """The strongest peak of every beam of one scan through ``field`` at time ``t`` (see the module docstring).

    Args:
        origin: (3,) sensor origin [m] (world frame of ``field``).
        directions: (B, 3) unit beam directions.
        r0: (B,) target range [m] along each beam, ``inf`` where there is none.
        i0: (B,) clear intensity (0..255) of each target (with full overlap), 0 where ``r0`` is ``inf``.
        field: the snow / rain field; its particles at ``t`` [s] are the medium.
        reflectivity: particle reflectivity ρ in [0, 1] (snow 0.9, rain 0.02).
        sensor: pulse, overlap and listening window (`ExactSensor`).
        noise_floor: detector noise floor (0..255, > 0) that sets ``D_res`` (at ``floor_range_m`` for a raw-power
            detector: `resolved_diameter`).
        divergence_rad: full beam divergence θ [rad].
        sub_rays: sub-rays per beam K.
        resolve_fraction: share of the noise floor a resolved particle must reach alone.
        intensity_model: the sensor's intensity model (``scale``, gain ``g``).
        grid_step: receiver-axis step [m] of the peak search, rounded to whole millimetres.
        seed: seed of the per-beam sub-ray rotations.

    Raises:
        ValueError: naming the argument and the expected form.
    """
    o, d, r0a, i0a = _beam_inputs(origin, directions, r0, i0)
    if not isinstance(field, ParticleField):
        raise ValueError(f"particle_returns: field = {type(field).__name__}; expected a ParticleField")
    t = float(t)
    if not math.isfinite(t):
        raise ValueError(f"particle_returns: t = {t!r}; expected a finite time [s]")
    rho = _check_reflectivity(reflectivity)
    nf = float(noise_floor)
    if not (math.isfinite(nf) and 0.0 < nf <= 255.0):
        raise ValueError(f"particle_returns: noise_floor = {noise_floor!r}; expected 0 < noise_floor <= 255")
    frac = float(resolve_fraction)
    if not (math.isfinite(frac) and 0.0 < frac <= 1e3):
        raise ValueError(f"particle_returns: resolve_fraction = {resolve_fraction!r}; "
                         "expected 0 < resolve_fraction <= 1000")
    theta = _check_divergence(divergence_rad)
    _check_sensor(sensor, intensity_model)
    _check_search(sub_rays, grid_step, seed)
    spec = field.spectrum
    edges = range_shells(sensor.listen_end)
    d_res = resolved_diameter(edges[:-1], rho, nf, divergence_rad=theta, resolve_fraction=frac,
                              intensity_model=intensity_model, floor_range_m=floor_range_m)
    d_res[0] = np.inf  # the first shell, inside the housing, is continuum
    area = np.array([0.5 * spec.extinction(d_hi=float(min(dr, spec.d_max))) for dr in d_res])
    unresolved = Unresolved(edges, area)
    reach = np.minimum(r0a, sensor.listen_end)
    if len(d) == 0:
        pos, diam, ids = np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    else:
        pos, diam, ids = _materialize_resolved(field, t, o, d, reach, edges, d_res, 0.5 * theta)
    out = _run(o, d, r0a, i0a, pos, diam, ids, rho, sensor, unresolved, theta, sub_rays, intensity_model,
               grid_step, seed)
    return ParticleReturns(out.returns, out.particle_id, out.particle_hits, out.n_resolved, out.n_pairs, out.n_hits,
                           unresolved, d_res)


def returns_from_particles(origin: ArrayLike, directions: ArrayLike, r0: ArrayLike, i0: ArrayLike,
                           positions: ArrayLike, diameters: ArrayLike, ids: ArrayLike | None, reflectivity: float,
                           sensor: ExactSensor, *, unresolved: Unresolved | None = None,
                           divergence_rad: float = 3e-3, sub_rays: int = 64,
                           intensity_model: IntensityModel = SYNTHETIC_INTENSITY, grid_step: float = 0.02,
                           seed: int = 0) -> ParticleReturns:
    """The same process with explicit resolved particles (N, 3) positions [m], (N,) diameters [m], (N,) int ids
    (None: 0..N-1) and an explicit continuum (`Unresolved`, None: clear air); arguments as `particle_returns`."""
    o, d, r0a, i0a = _beam_inputs(origin, directions, r0, i0)
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or not np.all(np.isfinite(pos)):
        raise ValueError(f"returns_from_particles: positions {pos.shape}; expected (N, 3) finite positions [m]")
    diam = np.ascontiguousarray(diameters, dtype=np.float64)
    if diam.shape != (len(pos),) or not np.all(np.isfinite(diam)) or np.any(diam <= 0):
        raise ValueError(f"returns_from_particles: diameters {diam.shape}; expected ({len(pos)},) finite diameters "
                         "> 0 [m]")
    idv = np.arange(len(pos), dtype=np.int64) if ids is None else np.ascontiguousarray(ids, dtype=np.int64)
    if idv.shape != (len(pos),):
        raise ValueError(f"returns_from_particles: ids {idv.shape}; expected ({len(pos)},) integer ids")
    rho = _check_reflectivity(reflectivity)
    theta = _check_divergence(divergence_rad)
    _check_sensor(sensor, intensity_model)
    if unresolved is None:
        unresolved = Unresolved.none()
    elif not isinstance(unresolved, Unresolved):
        raise ValueError(f"returns_from_particles: unresolved = {type(unresolved).__name__}; expected Unresolved")
    return _run(o, d, r0a, i0a, pos, diam, idv, rho, sensor, unresolved, theta, sub_rays, intensity_model,
                grid_step, seed)


def beam_waveform(R: ArrayLike, beam: int, origin: ArrayLike, directions: ArrayLike, r0: ArrayLike, i0: ArrayLike,
                  positions: ArrayLike, diameters: ArrayLike, reflectivity: float, sensor: ExactSensor, *,
                  unresolved: Unresolved | None = None, divergence_rad: float = 3e-3, sub_rays: int = 64,
                  intensity_model: IntensityModel = SYNTHETIC_INTENSITY, seed: int = 0) -> tuple[F64, F64]:
    """The received waveform of beam ``beam`` (its index in ``directions``) at receiver ranges ``R`` [m] (any shape),
    raw units: (sub-ray echoes, unresolved continuum), each of ``R``'s shape; the other arguments as
    `returns_from_particles`. The peak search of `returns_from_particles` samples exactly this function."""
    o, d, r0a, i0a = _beam_inputs(origin, directions, r0, i0)
    b = _check_int("beam", beam, 0, len(d) - 1)
    pos = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
    diam = np.ascontiguousarray(diameters, dtype=np.float64).ravel()
    if diam.shape != (len(pos),) or not np.all(np.isfinite(diam)) or np.any(diam <= 0):
        raise ValueError(f"beam_waveform: diameters {diam.shape}; expected ({len(pos)},) finite diameters > 0 [m]")
    rho = _check_reflectivity(reflectivity)
    theta = _check_divergence(divergence_rad)
    _check_sensor(sensor, intensity_model)
    unresolved = Unresolved.none() if unresolved is None else unresolved
    prep = _prepare(o, d, r0a, i0a, pos, diam, rho, sensor, unresolved, theta, sub_rays, intensity_model, 0.02, seed)
    Rv = np.ascontiguousarray(R, dtype=np.float64)
    flat = Rv.ravel()
    pulses, cont = np.empty(flat.size), np.empty(flat.size)
    _waveform_kernel(flat, b, prep.beams, prep.particles, prep.pattern, prep.sensor, prep.gain, prep.shadow,
                     prep.integrals, pulses, cont)
    return pulses.reshape(Rv.shape), cont.reshape(Rv.shape)


# ------------------------------------------------------------------------------------------------ validation
def _check_int(name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= int(value) <= hi:
        raise ValueError(f"{name} = {value!r}; expected an integer in [{lo}, {hi}]")
    return int(value)


def _check_search(sub_rays: int, grid_step: float, seed: int) -> tuple[int, float, int]:
    k_sub = _check_int("sub_rays", sub_rays, 1, 4096)
    gs = float(grid_step)
    if not (math.isfinite(gs) and TABLE_STEP_M <= gs <= 0.1):
        raise ValueError(f"grid_step = {grid_step!r}; expected {TABLE_STEP_M} <= grid_step <= 0.1 m")
    return k_sub, gs, _check_int("seed", seed, 0, 2**63 - 1)


def _check_divergence(divergence_rad: float) -> float:
    v = float(divergence_rad)
    if not (math.isfinite(v) and 0.0 < v <= 0.2):
        raise ValueError(f"divergence_rad = {divergence_rad!r}; expected a full divergence 0 < θ <= 0.2 rad")
    return v


def _check_reflectivity(reflectivity: float) -> float:
    v = float(reflectivity)
    if not (math.isfinite(v) and 0.0 <= v <= 1.0):
        raise ValueError(f"reflectivity = {reflectivity!r}; expected a particle reflectivity in [0, 1]")
    return v


def _check_sensor(sensor: ExactSensor, intensity_model: IntensityModel) -> None:
    if not isinstance(sensor, ExactSensor):
        raise ValueError(f"sensor = {type(sensor).__name__}; expected an ExactSensor")
    if not isinstance(intensity_model, IntensityModel):
        raise ValueError(f"intensity_model = {type(intensity_model).__name__}; expected an IntensityModel")


def _directions(directions: ArrayLike) -> F64:
    d = np.ascontiguousarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or not np.all(np.isfinite(d)):
        raise ValueError(f"directions {d.shape}; expected (B, 3) finite unit vectors")
    norm = np.linalg.norm(d, axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-6):
        bad = int(np.argmax(np.abs(norm - 1.0)))
        raise ValueError(f"directions[{bad}] has norm {norm[bad]:.9g}; expected (B, 3) unit vectors (|d| = 1 "
                         "within 1e-6)")
    return np.ascontiguousarray(d / norm[:, None])


def _beam_inputs(origin: ArrayLike, directions: ArrayLike, r0: ArrayLike,
                 i0: ArrayLike) -> tuple[F64, F64, F64, F64]:
    o = np.ascontiguousarray(origin, dtype=np.float64)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise ValueError(f"origin = {origin!r}; expected 3 finite numbers (x, y, z) [m]")
    d = _directions(directions)
    n = len(d)
    r = np.ascontiguousarray(r0, dtype=np.float64)
    if r.shape != (n,) or np.any(np.isnan(r)) or np.any(r <= 0):
        raise ValueError(f"r0 {r.shape}; expected ({n},) target ranges > 0 [m] (inf: no target)")
    i = np.ascontiguousarray(i0, dtype=np.float64)
    if i.shape != (n,) or not np.all(np.isfinite(i)) or np.any(i < 0):
        raise ValueError(f"i0 {i.shape}; expected ({n},) finite clear intensities >= 0")
    if np.any((i > 0) & np.isinf(r)):
        raise ValueError("i0: expected 0 where r0 is inf (no target, nothing to calibrate)")
    return o, d, r, i


# ------------------------------------------------------------------------------------------------ materialisation
def _materialize_resolved(field: ParticleField, t: float, origin: F64, d: F64, reach: F64, edges: F64, d_res: F64,
                          alpha: float) -> tuple[F64, F64, I64]:
    """The resolved particles of every shell near the beams: per shell and azimuth sector, a box around the beams'
    cone pieces (beams end at ``reach``), queried with ``min_diameter = D_res``; each particle kept once (by its
    centre's range shell and azimuth sector)."""
    spec = field.spectrum
    rho_max = 0.5 * spec.d_max
    az = np.arctan2(d[:, 1], d[:, 0])
    reach_max = float(reach.max())
    el_max = float(np.max(np.abs(np.arcsin(np.clip(d[:, 2], -1.0, 1.0))))) + alpha
    cos_a, sin_a = math.cos(alpha), math.sin(alpha)
    parts_p, parts_d, parts_i = [], [], []
    n_shells = len(edges) - 1
    for k in range(n_shells):
        if not d_res[k] < spec.d_max:
            continue
        ra, rb = float(edges[k]), float(edges[k + 1])
        if ra >= reach_max + rho_max:
            break
        n_sec = _sectors(ra, field.cell_size)
        delta = math.inf  # largest azimuth difference between a touching particle's centre and its beam
        if ra > 0:
            psi = alpha + math.asin(min(1.0, rho_max / ra))
            if el_max + psi < 0.5 * math.pi:
                ratio = math.sin(0.5 * psi) / math.cos(el_max + psi)
                delta = 2.0 * math.asin(ratio) + 1e-9 if ratio < 1.0 else math.inf
        width = 2.0 * math.pi / n_sec
        if n_sec > 1 and delta >= 0.25 * width:
            n_sec, width = 1, 2.0 * math.pi
        lo_s, hi_s, n_in = _sector_boxes(origin, d, reach, az, ra, min(rb, reach_max + rho_max), rho_max, cos_a,
                                         sin_a, n_sec, width, delta if n_sec > 1 else 0.0)
        for j in range(n_sec):
            if n_in[j] == 0:
                continue
            lo, hi = lo_s[j], hi_s[j]
            got = field.materialize(lo, hi, t, float(d_res[k]))
            if len(got) == 0:
                continue
            keep = _shell_sector(got.positions, origin, ra, rb, n_sec, j, width)
            parts_p.append(got.positions[keep])
            parts_d.append(got.diameters[keep])
            parts_i.append(got.ids[keep])
    if not parts_p:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    return (np.ascontiguousarray(np.concatenate(parts_p)), np.ascontiguousarray(np.concatenate(parts_d)),
            np.ascontiguousarray(np.concatenate(parts_i)))


def _sectors(r_inner: float, cell_size: float) -> int:
    """Azimuth sectors of a shell: about one per 2.5 cells of the inner circumference, a power of 2, at most 32."""
    n = 2.0 * math.pi * r_inner / (2.5 * cell_size)
    return int(min(32, 2 ** max(0, int(math.floor(math.log2(n))))) if n >= 2 else 1)


# ------------------------------------------------------------------------------------------------ core
@dataclass(frozen=True)
class _Prepared:
    """Everything the kernels take besides the output arrays (`weatheralign.reference.records`)."""

    beams: ExactBeams
    particles: BeamParticles
    pattern: SubrayPattern
    sensor: SensorOptics
    gain: EchoGain
    shadow: Shadow
    integrals: ContinuumIntegrals
    nodes: ContinuumNodes


def _prepare(o: F64, d: F64, r0: F64, i0: F64, pos: F64, diam: F64, rho: float, sensor: ExactSensor,
             unresolved: Unresolved, theta: float, sub_rays: int, im: IntensityModel, grid_step: float,
             seed: int) -> _Prepared:
    k_sub, gs, seed = _check_search(sub_rays, grid_step, seed)
    stride = max(1, int(round(gs / TABLE_STEP_M)))
    step = stride * TABLE_STEP_M
    alpha = 0.5 * theta
    reach = np.minimum(r0, sensor.listen_end)
    pair_start, pair_part = _pairs(o, d, reach, pos, diam, alpha)
    integrals, nodes = _tables(unresolved, rho, sensor, im, step, stride)
    px, py, pn = _pattern(k_sub, math.tan(alpha))
    e = unresolved
    shadow = Shadow(np.ascontiguousarray(e.edges[:-1]), np.ascontiguousarray(e.area), np.ascontiguousarray(e.tau_edges))
    return _Prepared(ExactBeams(o, d, r0, i0, beam_rotations(len(d), seed)),
                     BeamParticles(pos, diam, pair_start, pair_part), SubrayPattern(px, py, pn, math.tan(alpha)),
                     sensor_optics(sensor), EchoGain(im.scale * rho, im.r_ref, im.falloff), shadow, integrals, nodes)


def _run(o: F64, d: F64, r0: F64, i0: F64, pos: F64, diam: F64, ids: I64, rho: float, sensor: ExactSensor,
         unresolved: Unresolved, theta: float, sub_rays: int, im: IntensityModel, grid_step: float,
         seed: int, prune: bool = True) -> ParticleReturns:
    """The kernels on explicit particles. ``prune=False`` evaluates every grid node of every echo (the pruning by
    upper bounds is exact: same peaks, for the tests)."""
    prep = _prepare(o, d, r0, i0, pos, diam, rho, sensor, unresolved, theta, sub_rays, im, grid_step, seed)
    if len(d) == 0:
        return ParticleReturns(ExactReturns(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.uint8), np.zeros(0),
                                            np.zeros(0)),
                               np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int32), len(pos), 0, 0, unresolved,
                               np.zeros(0))
    n = len(d)
    peaks = ParticlePeaks(power=np.zeros(n), r_peak=np.zeros(n), source=np.zeros(n, dtype=np.uint8),
                          dominant=np.full(n, -1, dtype=np.int64), hits=np.zeros(n, dtype=np.int32),
                          target_power=np.zeros(n), target_r=np.zeros(n))
    _beams_kernel(prep.beams, prep.particles, prep.pattern, prep.sensor, prep.gain, prep.shadow, prep.integrals,
                  prep.nodes, bool(prune), peaks)
    pid = np.full(n, -1, dtype=np.int64)
    sel = peaks.dominant >= 0
    pid[sel] = ids[peaks.dominant[sel]]
    return ParticleReturns(ExactReturns(peaks.power, peaks.r_peak, peaks.source, peaks.target_power, peaks.target_r),
                           pid, peaks.hits, len(pos), int(prep.particles.pair_start[-1]), int(peaks.hits.sum()),
                           unresolved, np.zeros(0))


def _pairs(o: F64, d: F64, reach: F64, pos: F64, diam: F64, alpha: float) -> tuple[I64, I64]:
    """CSR (B + 1,) start, (P,) particle index: the particles whose sphere touches each beam's cone in front of its
    target (``|c| - D/2 < reach``). Beams are binned by (sine of elevation, azimuth); only rows holding beams are
    indexed."""
    n = len(d)
    if len(pos) == 0 or n == 0:
        return np.zeros(n + 1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    sz = d[:, 2]
    az = np.arctan2(d[:, 1], d[:, 0])
    d_s = max(0.5 * alpha, 1e-5)
    s_lo = float(sz.min()) - 1e-9
    row = ((sz - s_lo) / d_s).astype(np.int64)
    n_rows = int(row.max()) + 1
    used, compact = np.unique(row, return_inverse=True)
    row_id = np.full(n_rows, -1, dtype=np.int64)
    row_id[used] = np.arange(len(used))
    n_az = max(1, int(2.0 * math.pi / max(2.0 * alpha, 2e-4)))
    while len(used) * n_az > 4_000_000 and n_az > 1:  # keep the index small for odd beam sets
        n_az = max(1, n_az // 2)
    d_az = 2.0 * math.pi / n_az
    ia = np.minimum(((az + math.pi) / d_az).astype(np.int64), n_az - 1)
    key = compact.ravel() * n_az + ia
    bin_beams = np.argsort(key, kind="stable").astype(np.int64)
    bin_start = np.zeros(len(used) * n_az + 1, dtype=np.int64)
    np.cumsum(np.bincount(key, minlength=len(used) * n_az), out=bin_start[1:])
    cap = max(1024, 2 * len(pos))
    while True:
        pb = np.empty(cap, dtype=np.int64)
        pp = np.empty(cap, dtype=np.int64)
        count = _pairs_kernel(o, d, reach, pos, diam, alpha, float(reach.max()), s_lo, d_s, row_id, d_az, n_az,
                              bin_start, bin_beams, pb, pp)
        if count <= cap:
            break
        cap = count
    start = np.zeros(n + 1, dtype=np.int64)
    part = np.empty(count, dtype=np.int64)
    _csr(pb[:count], pp[:count], start, part)
    return start, part


def _tables(unresolved: Unresolved, rho: float, sensor: ExactSensor, im: IntensityModel, step: float,
            stride: int) -> tuple[ContinuumIntegrals, ContinuumNodes]:
    """Beam-independent tables: running integrals (1 mm) of the continuum's ``f = scale ρ a_u ξ T / r²`` times
    1, cos ωr, sin ωr; the same on the receiver grid ``m step`` and lagged by ``c τ_H``; cos/sin ωR on the grid; the
    unobstructed continuum response G on the grid and its sparse table of range maxima."""
    length = sensor.pulse_length
    omega = 2.0 * math.pi / length
    h = TABLE_STEP_M
    m_hi = int(math.floor(sensor.listen_end / step))
    n_tab = m_hi * stride + int(math.ceil(length / h)) + 4
    r = h * np.arange(n_tab)
    has_cont = rho > 0.0 and im.scale > 0.0 and bool(np.any(unresolved.area > 0))
    if has_cont:
        with np.errstate(divide="ignore", invalid="ignore"):
            phi = np.where(r > 0, im.scale * rho * bistatic_overlap(r, sensor) * unresolved.transmission(r)
                           / (r * r), 0.0)
        a_mid = unresolved.area_at(r[:-1] + 0.5 * h)
        c, s = np.cos(omega * r), np.sin(omega * r)
        tabs = []
        for w in (1.0, c, s):
            fw = phi * w
            inc = 0.5 * h * a_mid * (fw[:-1] + fw[1:])
            tabs.append(np.concatenate([[0.0], np.cumsum(inc)]))
        H0, Hc, Hs = tabs
    else:
        H0 = Hc = Hs = np.zeros(n_tab)
    nodes = np.arange(m_hi + 1)
    R = nodes * step
    idx = nodes * stride
    H0n, Hcn, Hsn = H0[idx].copy(), Hc[idx].copy(), Hs[idx].copy()
    H0l, Hcl, Hsl = np.empty(m_hi + 1), np.empty(m_hi + 1), np.empty(m_hi + 1)
    _lagged(R, length, h, H0, Hc, Hs, H0l, Hcl, Hsl)
    cosn, sinn = np.cos(omega * R), np.sin(omega * R)
    G = np.maximum(0.5 * (H0n - H0l) - 0.5 * (cosn * (Hcn - Hcl) + sinn * (Hsn - Hsl)), 0.0)
    sp = _sparse_table(G)
    return (ContinuumIntegrals(bool(has_cont), h, H0, Hc, Hs),
            ContinuumNodes(step, H0n, Hcn, Hsn, H0l, Hcl, Hsl, cosn, sinn, G, sp))


# ------------------------------------------------------------------------------------------------ numba kernels
@njit(cache=True, nogil=True)
def _interp(table, x, h):  # pragma: no cover
    if x <= 0.0:
        return 0.0
    pos = x / h
    j = int(pos)
    n = table.shape[0]
    if j >= n - 1:
        return table[n - 1]
    f = pos - j
    return table[j] + f * (table[j + 1] - table[j])


@njit(cache=True, nogil=True)
def _lagged(R, length, h, H0, Hc, Hs, H0l, Hcl, Hsl):  # pragma: no cover
    for m in range(R.shape[0]):
        a = R[m] - length
        H0l[m] = _interp(H0, a, h)
        Hcl[m] = _interp(Hc, a, h)
        Hsl[m] = _interp(Hs, a, h)


@njit(cache=True, nogil=True)
def _sparse_table(G):  # pragma: no cover
    n = G.shape[0]
    levels = 1
    while (1 << levels) <= n:
        levels += 1
    sp = np.empty((levels, n), dtype=np.int64)
    for i in range(n):
        sp[0, i] = i
    for k in range(1, levels):
        half = 1 << (k - 1)
        for i in range(n - (1 << k) + 1):
            a, b = sp[k - 1, i], sp[k - 1, i + half]
            sp[k, i] = a if G[a] >= G[b] else b
    return sp


@njit(cache=True, nogil=True)
def _range_argmax(G, sp, lo, hi):  # pragma: no cover
    k = 0
    while (1 << (k + 1)) <= hi - lo + 1:
        k += 1
    a, b = sp[k, lo], sp[k, hi - (1 << k) + 1]
    return a if G[a] >= G[b] else b


@njit(cache=True, nogil=True)
def _subrays(u0, u1, u2, phi, px, py, pn, out):  # pragma: no cover
    """Sub-ray directions (K, 3) of the beam ``u``: the sunflower pattern ``px, py`` rotated by ``phi`` on the basis
    ``e1 = u x (least aligned axis)``, ``e2 = u x e1``."""
    a0, a1, a2 = abs(u0), abs(u1), abs(u2)
    if a0 <= a1 and a0 <= a2:  # e1 = u x ex
        e0, e1_, e2 = 0.0, u2, -u1
    elif a1 <= a2:  # u x ey
        e0, e1_, e2 = -u2, 0.0, u0
    else:  # u x ez
        e0, e1_, e2 = u1, -u0, 0.0
    ne = math.sqrt(e0 * e0 + e1_ * e1_ + e2 * e2)
    e0, e1_, e2 = e0 / ne, e1_ / ne, e2 / ne
    f0 = u1 * e2 - u2 * e1_
    f1 = u2 * e0 - u0 * e2
    f2 = u0 * e1_ - u1 * e0
    cp, sp = math.cos(phi), math.sin(phi)
    for k in range(out.shape[0]):
        c = px[k] * cp - py[k] * sp
        s = px[k] * sp + py[k] * cp
        w = pn[k]
        out[k, 0] = (u0 + c * e0 + s * f0) * w
        out[k, 1] = (u1 + c * e1_ + s * f1) * w
        out[k, 2] = (u2 + c * e2 + s * f2) * w


@njit(cache=True, nogil=True)
def _asin_upper(x):  # pragma: no cover
    """An upper bound of ``asin(x)`` for 0 <= x < 1 (``x / sqrt(1 - x²)``), trig-free."""
    return x / math.sqrt(1.0 - x * x)


@njit(cache=True, nogil=True)
def _pairs_kernel(o, dirs, reach, pos, diam, alpha, reach_max, s_lo, d_s, row_id, d_az, n_az, bin_start, bin_beams,
                  out_b, out_p):  # pragma: no cover
    """Every (beam, particle) pair whose sphere touches the beam's cone (exact sphere–cone test) in front of the
    beam's reach, written while they fit; returns the count. Candidates: beams of the bins within the particle's
    angular radius ``ψ = θ/2 + asin(D / 2L)`` (rows by the sine of the elevation, which moves by at most ψ; azimuth
    within ``2 asin(sin(ψ/2) / cos e_max)``, bounded above without trigonometry)."""
    cos_a, sin_a = math.cos(alpha), math.sin(alpha)
    n_rows = row_id.shape[0]
    cap = out_b.shape[0]
    count = 0
    for p in range(pos.shape[0]):
        cx, cy, cz = pos[p, 0] - o[0], pos[p, 1] - o[1], pos[p, 2] - o[2]
        L = math.sqrt(cx * cx + cy * cy + cz * cz)
        rad = 0.5 * diam[p]
        if L - rad >= reach_max:
            continue
        full = L <= 1.01 * rad
        sp_ = 0.0
        if full:
            psi = math.pi
        else:
            psi = alpha + _asin_upper(rad / L) + 1e-12
            sp_ = cz / L
        r_lo = int(math.floor((sp_ - psi - s_lo) / d_s))
        r_hi = int(math.floor((sp_ + psi - s_lo) / d_s))
        if full or r_lo < 0:
            r_lo = 0
        if full or r_hi > n_rows - 1:
            r_hi = n_rows - 1
        full_az = full or psi > 0.5
        da = 0.0
        if not full_az:
            cos_el = math.sqrt(cx * cx + cy * cy) / L
            cos_max = cos_el * (1.0 - 0.5 * psi * psi) - abs(sp_) * psi  # <= cos(|el| + psi)
            if cos_max < 0.05:
                full_az = True
            else:
                x = 0.5 * psi / cos_max  # >= sin(psi / 2) / cos(e_max)
                if x >= 0.9:
                    full_az = True
                else:
                    da = 2.0 * _asin_upper(x) + 1e-12
        if full_az:
            j_lo, n_j = 0, n_az
        else:
            az = math.atan2(cy, cx)
            j_lo = int(math.floor((az - da + math.pi) / d_az))
            j_hi = int(math.floor((az + da + math.pi) / d_az))
            n_j = min(j_hi - j_lo + 1, n_az)
        for r in range(r_lo, r_hi + 1):
            ri = row_id[r]
            if ri < 0:
                continue
            for jj in range(n_j):
                j = (j_lo + jj) % n_az
                cell = ri * n_az + j
                for q in range(bin_start[cell], bin_start[cell + 1]):
                    b = bin_beams[q]
                    if L - rad >= reach[b]:
                        continue
                    bb = dirs[b, 0] * cx + dirs[b, 1] * cy + dirs[b, 2] * cz
                    perp = math.sqrt(max(L * L - bb * bb, 0.0))
                    if bb * cos_a + perp * sin_a >= 0.0:
                        hit = perp * cos_a - bb * sin_a <= rad
                    else:
                        hit = L <= rad
                    if hit:
                        if count < cap:
                            out_b[count] = b
                            out_p[count] = p
                        count += 1
    return count


@njit(cache=True, nogil=True)
def _csr(pb, pp, start, part):  # pragma: no cover
    """Counting sort of the pairs by beam (stable: particles of a beam in discovery order)."""
    n = start.shape[0] - 1
    for q in range(pb.shape[0]):
        start[pb[q] + 1] += 1
    for b in range(n):
        start[b + 1] += start[b]
    cursor = start[:-1].copy()
    for q in range(pb.shape[0]):
        b = pb[q]
        part[cursor[b]] = pp[q]
        cursor[b] += 1


@njit(cache=True, nogil=True)
def _sector_boxes(o, d, reach, az, ra, rb, rho_max, cos_a, sin_a, n_sec, width, delta):  # pragma: no cover
    """Per azimuth sector, the box around the pieces of the beams' cones (up to each beam's reach) whose cone points
    lie within ``rho_max`` of a centre in the shell ``[ra, rb)``: the cone points at distance ``[ra - rho_max,
    min(rb, reach) + rho_max]`` lie along the axis in ``[(ra - rho_max) cos(θ/2), ...]`` and within ``d2 sin(θ/2)``
    of it; every beam joins the sectors within ``delta`` of its azimuth. Returns (lo, hi, beams per sector)."""
    lo = np.full((n_sec, 3), np.inf)
    hi = np.full((n_sec, 3), -np.inf)
    n_in = np.zeros(n_sec, dtype=np.int64)
    d1 = max(0.0, ra - rho_max) * cos_a
    for b in range(d.shape[0]):
        if reach[b] + rho_max <= ra:
            continue
        d2 = min(rb, reach[b] + rho_max) + rho_max
        lat = d2 * sin_a + rho_max
        if n_sec == 1:
            j0, j1 = 0, 0
        else:
            j0 = int(math.floor((az[b] - delta + math.pi) / width))
            j1 = int(math.floor((az[b] + delta + math.pi) / width))
        for jj in range(j0, j1 + 1):
            j = jj % n_sec
            n_in[j] += 1
            for c in range(3):
                x1 = o[c] + d[b, c] * d1
                x2 = o[c] + d[b, c] * d2
                lo[j, c] = min(lo[j, c], min(x1, x2) - lat)
                hi[j, c] = max(hi[j, c], max(x1, x2) + lat)
    return lo, hi, n_in


@njit(cache=True, nogil=True)
def _shell_sector(positions, o, ra, rb, n_sec, j, width):  # pragma: no cover
    """Mask (N,) of the particles whose centre lies in the shell ``[ra, rb)`` and, with ``n_sec > 1``, in azimuth
    sector ``j`` of width ``width``: every particle is kept by exactly one (shell, sector)."""
    n = positions.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        cx, cy, cz = positions[i, 0] - o[0], positions[i, 1] - o[1], positions[i, 2] - o[2]
        dist = math.sqrt(cx * cx + cy * cy + cz * cz)
        if dist < ra or dist >= rb:
            continue
        if n_sec > 1:
            sec = int((math.atan2(cy, cx) + math.pi) / width)
            if sec > n_sec - 1:
                sec = n_sec - 1
            if sec != j:
                continue
        keep[i] = True
    return keep


@njit(cache=True, nogil=True)
def _node_at_or_after(x, step, m_hi):  # pragma: no cover
    """Smallest node m with ``m step >= x`` (at most ``m_hi + 1``)."""
    if x > (m_hi + 1) * step:
        return m_hi + 1
    m = int(math.ceil(x / step))
    while (m - 1) * step >= x:
        m -= 1
    while m * step < x:
        m += 1
    return m


@njit(cache=True, nogil=True)
def _node_after(x, step, m_hi):  # pragma: no cover
    """Smallest node m with ``m step > x`` (at most ``m_hi + 1``)."""
    if x >= (m_hi + 1) * step:
        return m_hi + 1
    m = int(math.floor(x / step)) + 1
    while (m - 1) * step > x:
        m -= 1
    while m * step <= x:
        m += 1
    return m


@njit(cache=True, nogil=True)
def _gain(r, r_ref, falloff):  # pragma: no cover
    r = max(r, 1e-9)
    if r <= r_ref:
        return 1.0
    return (r_ref / r) ** falloff


@njit(cache=True, nogil=True)
def _transmission(s, edges, area, tau):  # pragma: no cover
    k = np.searchsorted(edges, s, side="right") - 1
    if k < 0:
        k = 0
    return math.exp(-(tau[k] + area[k] * (s - edges[k])))


@njit(cache=True, nogil=True)
def _evaluate(R, n_ev, ev, r0, length, omega, integrals, hr0, parts):  # pragma: no cover
    """Waveform at ``R`` [m] from the first ``n_ev`` of the beam's events ``ev`` (`BeamEvents`; target at ``r0``
    [m], pulse ``length`` c τ_H [m], ω = 2π / length): (sub-ray echoes, continuum), the continuum from the running
    `ContinuumIntegrals` (``hr0``: H0, Hc, Hs at ``r0``); ``parts`` (n_ev,) each event's echo."""
    ev_s, ev_amp, ev_q, ev_h0, ev_hc, ev_hs = ev.s, ev.amp, ev.q, ev.h0, ev.hc, ev.hs
    has_cont, h, H0, Hc, Hs = integrals.has_cont, integrals.h, integrals.H0, integrals.Hc, integrals.Hs
    hr0_0, hr0_c, hr0_s = hr0
    pul = 0.0
    ub, pb0, pbc, pbs = 1.0, 0.0, 0.0, 0.0
    ua, pa0, pac, pas = 1.0, 0.0, 0.0, 0.0
    for e in range(n_ev):
        s = ev_s[e]
        x = R - s
        c = 0.0
        if 0.0 <= x <= length:
            sn = math.sin(math.pi * x / length)
            c = ev_amp[e] * sn * sn
        parts[e] = c
        pul += c
        q = ev_q[e]
        if s <= R:
            ub -= q
            pb0 += q * ev_h0[e]
            pbc += q * ev_hc[e]
            pbs += q * ev_hs[e]
        if s + length < R:
            ua -= q
            pa0 += q * ev_h0[e]
            pac += q * ev_hc[e]
            pas += q * ev_hs[e]
    cont = 0.0
    if has_cont and R - length < r0:
        if R <= r0:
            hb0, hbc, hbs = _interp(H0, R, h), _interp(Hc, R, h), _interp(Hs, R, h)
        else:
            hb0, hbc, hbs = hr0_0, hr0_c, hr0_s
        a = R - length
        ha0, hac, has_ = _interp(H0, a, h), _interp(Hc, a, h), _interp(Hs, a, h)
        d0 = ub * hb0 + pb0 - (ua * ha0 + pa0)
        dc = ub * hbc + pbc - (ua * hac + pac)
        ds = ub * hbs + pbs - (ua * has_ + pas)
        cont = max(0.5 * d0 - 0.5 * (math.cos(omega * R) * dc + math.sin(omega * R) * ds), 0.0)
    return pul, cont


@njit(cache=True, nogil=True)
def _events(b, beams, particles, pattern, sensor, gain, shadow, integrals, omega, scratch,
            ev):  # pragma: no cover
    """Beam ``b``'s events sorted by range into ``ev`` (`BeamEvents`): every sub-ray's nearest hit (exact ray–sphere
    against the beam's candidate particles, else the target at ``r0``), the target's sub-rays merged into one event.
    Per event: range, echo amplitude ``(n/K) w ξ T / r²``, share of sub-rays ``q``, particle index (-1: target),
    ``amp cos/sin ωr`` and the continuum's running integrals at its range. Returns (events, sub-rays stopped by
    particles). The records: `ExactBeams`, `BeamParticles`, `SubrayPattern`, `SensorOptics`, `EchoGain`, `Shadow`,
    `ContinuumIntegrals`, `SubrayScratch`."""
    o, dirs, r0s, i0s, phis = beams.origin, beams.dirs, beams.r0, beams.i0, beams.phi
    pos, diam, pair_start, pair_part = particles.pos, particles.diam, particles.pair_start, particles.pair_part
    px, py, pn, tan_a = pattern.px, pattern.py, pattern.pn, pattern.tan_a
    r1, r2, kappa = sensor.r1, sensor.r2, sensor.kappa
    w_part, r_ref, falloff = gain.w_part, gain.r_ref, gain.falloff
    u_edges, u_area, u_tau = shadow.edges, shadow.area, shadow.tau
    has_cont, h, H0, Hc, Hs = integrals.has_cont, integrals.h, integrals.H0, integrals.Hc, integrals.Hs
    rays, best_s, best_p = scratch.rays, scratch.best_s, scratch.best_p
    ev_s, ev_amp, ev_q, ev_p, ev_cs, ev_sn = ev.s, ev.amp, ev.q, ev.p, ev.cs, ev.sn
    ev_h0, ev_hc, ev_hs = ev.h0, ev.hc, ev.hs
    k_sub = px.shape[0]
    inv_k = 1.0 / k_sub
    r0 = r0s[b]
    # ---- sub-rays: nearest hit
    p0, p1 = pair_start[b], pair_start[b + 1]
    for k in range(k_sub):
        best_s[k] = r0
        best_p[k] = -1
    if p1 > p0:
        u0, u1, u2 = dirs[b, 0], dirs[b, 1], dirs[b, 2]
        _subrays(u0, u1, u2, phis[b], px, py, pn, rays)
        for q in range(p0, p1):
            p = pair_part[q]
            cx, cy, cz = pos[p, 0] - o[0], pos[p, 1] - o[1], pos[p, 2] - o[2]
            rad = 0.5 * diam[p]
            rad2 = rad * rad
            # sub-rays at angle γ_k from the axis (tan γ_k = tan(θ/2) sqrt((k + ½)/K)) can only hit where
            # |γ_k - ψ_c| <= asin(rad / L) (ψ_c: the centre's angle from the axis)
            L2 = cx * cx + cy * cy + cz * cz
            k_lo, k_hi = 0, k_sub - 1
            if L2 > rad2 * 1.0001:
                L = math.sqrt(L2)
                bb = u0 * cx + u1 * cy + u2 * cz
                psi_c = math.atan2(math.sqrt(max(L2 - bb * bb, 0.0)), bb)
                beta = math.asin(rad / L)
                g_hi = psi_c + beta + 1e-9
                if g_hi < 1.5:
                    x = k_sub * (math.tan(g_hi) / tan_a) ** 2 - 0.5
                    if x < k_sub:
                        k_hi = int(math.floor(x)) + 1
                        if k_hi > k_sub - 1:
                            k_hi = k_sub - 1
                g_lo = psi_c - beta - 1e-9
                if g_lo > 0.0:
                    if g_lo >= 1.5:
                        continue
                    x = k_sub * (math.tan(g_lo) / tan_a) ** 2 - 0.5
                    if x >= k_sub:
                        continue
                    k_lo = max(int(math.ceil(x)) - 1, 0)
            for k in range(k_lo, k_hi + 1):
                dx, dy, dz = rays[k, 0], rays[k, 1], rays[k, 2]
                bb = dx * cx + dy * cy + dz * cz
                wx, wy, wz = cx - bb * dx, cy - bb * dy, cz - bb * dz
                perp2 = wx * wx + wy * wy + wz * wz
                if perp2 < rad2:
                    half = math.sqrt(rad2 - perp2)
                    s = bb - half
                    if s < 0.0:
                        if bb + half <= 0.0:
                            continue  # behind the sensor
                        s = 0.0  # the sensor is inside the particle
                    if s < best_s[k]:
                        best_s[k] = s
                        best_p[k] = p
    # ---- events
    n_ev = 0
    n_hit = 0
    n_t = 0
    for k in range(k_sub):
        if best_p[k] >= 0:
            s = best_s[k]
            ev_s[n_ev] = s
            amp = 0.0
            if s > r1:
                amp = inv_k * w_part * _overlap_one(s, r1, r2, kappa) * _transmission(s, u_edges, u_area, u_tau) \
                    / (s * s)
            ev_amp[n_ev] = amp
            ev_q[n_ev] = inv_k
            ev_p[n_ev] = best_p[k]
            n_ev += 1
            n_hit += 1
        else:
            n_t += 1
    if r0 < math.inf:
        ev_s[n_ev] = r0
        amp = 0.0
        if r0 > r1 and i0s[b] > 0.0:
            amp = n_t * inv_k * i0s[b] / _gain(r0, r_ref, falloff) * _overlap_one(r0, r1, r2, kappa) \
                * _transmission(r0, u_edges, u_area, u_tau) / (r0 * r0)
        ev_amp[n_ev] = amp
        ev_q[n_ev] = n_t * inv_k
        ev_p[n_ev] = -1
        n_ev += 1
    # insertion sort by range (the target, at r0, stays last)
    for e in range(1, n_ev):
        j = e
        while j > 0 and ev_s[j - 1] > ev_s[j]:
            ev_s[j - 1], ev_s[j] = ev_s[j], ev_s[j - 1]
            ev_amp[j - 1], ev_amp[j] = ev_amp[j], ev_amp[j - 1]
            ev_q[j - 1], ev_q[j] = ev_q[j], ev_q[j - 1]
            ev_p[j - 1], ev_p[j] = ev_p[j], ev_p[j - 1]
            j -= 1
    for e in range(n_ev):
        s = ev_s[e]
        ev_cs[e] = ev_amp[e] * math.cos(omega * s)
        ev_sn[e] = ev_amp[e] * math.sin(omega * s)
        if has_cont:
            ev_h0[e] = _interp(H0, s, h)
            ev_hc[e] = _interp(Hc, s, h)
            ev_hs[e] = _interp(Hs, s, h)
        else:
            ev_h0[e] = ev_hc[e] = ev_hs[e] = 0.0
    return n_ev, n_hit


@njit(cache=True, nogil=True)
def _beams_kernel(beams, particles, pattern, sensor, gain, shadow, integrals, nodes, prune, out):  # pragma: no cover
    """Per beam: sub-rays against the candidate particles and the target, the events sorted by range, the waveform
    swept over the grid nodes inside the echoes' supports (running sums: every node O(1)), the continuum alone in
    the gaps between them by range maxima of G times the unblocked share, a three-point fit through the best node's
    neighbours, attribution at the refined peak; where that peak is not the target's, the waveform at the target's
    own echo crest (``target_power``, ``target_r``; 0 where the target's echo is fully blocked). The records
    (`weatheralign.reference.records`): `ExactBeams`, `BeamParticles`, `SubrayPattern`, `SensorOptics`, `EchoGain`,
    `Shadow`, `ContinuumIntegrals`, `ContinuumNodes`; the result into ``out`` (`ParticlePeaks`). ``prune=False``
    evaluates every node."""
    dirs, r0s = beams.dirs, beams.r0
    length = sensor.length
    r_ref, falloff = gain.r_ref, gain.falloff
    has_cont, h, H0, Hc, Hs = integrals.has_cont, integrals.h, integrals.H0, integrals.Hc, integrals.Hs
    step, H0n, Hcn, Hsn, H0l, Hcl, Hsl = nodes.step, nodes.H0n, nodes.Hcn, nodes.Hsn, nodes.H0l, nodes.Hcl, nodes.Hsl
    cosn, sinn, G, sp = nodes.cosn, nodes.sinn, nodes.G, nodes.sp
    power, r_out, source, dominant = out.power, out.r_peak, out.source, out.dominant
    hits, target_power, target_r = out.hits, out.target_power, out.target_r
    omega = 2.0 * math.pi / length
    k_sub = pattern.px.shape[0]
    sin_w = math.sin(omega * step)
    one_m_cos = 2.0 * math.sin(0.5 * omega * step) ** 2  # 1 - cos ω step
    half_w = 0.5 * omega * step
    m_lo = 1
    m_hi = H0n.shape[0] - 1
    scratch = SubrayScratch(np.empty((k_sub, 3)), np.empty(k_sub), np.empty(k_sub, dtype=np.int64))
    n_max = k_sub + 1
    ev = BeamEvents(np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max, dtype=np.int64),
                    np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max))
    ev_s, ev_amp, ev_q, ev_p, ev_cs, ev_sn = ev.s, ev.amp, ev.q, ev.p, ev.cs, ev.sn
    ev_h0, ev_hc, ev_hs = ev.h0, ev.hc, ev.hs
    parts = np.empty(n_max)
    ev_m0 = np.empty(n_max, dtype=np.int64)  # first node with R >= s (the echo has started)
    ev_m1 = np.empty(n_max, dtype=np.int64)  # first node with R > s + c τ_H (it has ended)
    g_i, g_j = np.empty(n_max, dtype=np.int64), np.empty(n_max, dtype=np.int64)
    g_ms, g_me = np.empty(n_max, dtype=np.int64), np.empty(n_max, dtype=np.int64)
    g_u, g_p0, g_pc, g_ps = np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max)
    g_bound = np.empty(n_max)
    slack = 1e-12 * H0[H0.shape[0] - 1]  # rounding of the continuum from the running integrals
    for b in range(dirs.shape[0]):
        r0 = r0s[b]
        n_ev, n_hit = _events(b, beams, particles, pattern, sensor, gain, shadow, integrals, omega, scratch, ev)
        hits[b] = n_hit
        hr0_0 = hr0_c = hr0_s = 0.0
        if has_cont and r0 < math.inf:
            hr0_0, hr0_c, hr0_s = _interp(H0, r0, h), _interp(Hc, r0, h), _interp(Hs, r0, h)
        hr0 = (hr0_0, hr0_c, hr0_s)
        # ---- groups of overlapping echoes; the gaps between them (continuum alone: u · max G)
        for e in range(n_ev):
            ev_m0[e] = _node_at_or_after(ev_s[e], step, m_hi)
            ev_m1[e] = _node_after(ev_s[e] + length, step, m_hi)
        best_v = 0.0
        best_m = -1
        cur = m_lo
        u_prev, P0, Pc, Ps = 1.0, 0.0, 0.0, 0.0
        n_g = 0
        i = 0
        while i < n_ev:
            j = i + 1
            while j < n_ev and ev_s[j] <= ev_s[j - 1] + length:
                j += 1
            ms = max(ev_m0[i], m_lo)
            me = min(ev_m1[j - 1] - 1, m_hi)
            if has_cont:
                gr = min(ms - 1, m_hi)
                if gr >= cur:
                    m = _range_argmax(G, sp, cur, gr)
                    v = u_prev * G[m]
                    if v > best_v:
                        best_v, best_m = v, m
            if ms <= me:
                bound = 0.0
                for e in range(i, j):
                    bound += ev_amp[e]
                if has_cont:
                    bound += u_prev * G[_range_argmax(G, sp, ms, me)] * (1.0 + 1e-9) + slack
                g_i[n_g], g_j[n_g], g_ms[n_g], g_me[n_g] = i, j, ms, me
                g_u[n_g], g_p0[n_g], g_pc[n_g], g_ps[n_g], g_bound[n_g] = u_prev, P0, Pc, Ps, bound
                n_g += 1
            if me + 1 > cur:
                cur = me + 1
            for e in range(i, j):
                q = ev_q[e]
                u_prev -= q
                P0 += q * ev_h0[e]
                Pc += q * ev_hc[e]
                Ps += q * ev_hs[e]
            i = j
        if has_cont and not (r0 < math.inf) and cur <= m_hi:
            m = _range_argmax(G, sp, cur, m_hi)
            v = u_prev * G[m]
            if v > best_v:
                best_v, best_m = v, m
        # ---- the groups, most promising first; inside, pieces of constant state (no echo starts or ends)
        for _ in range(n_g):
            g = -1
            for gg in range(n_g):
                if g_bound[gg] >= 0.0 and (g < 0 or g_bound[gg] > g_bound[g]):
                    g = gg
            if g < 0 or (prune and g_bound[g] <= best_v):
                break
            g_bound[g] = -1.0
            i, j, ms, me = g_i[g], g_j[g], g_ms[g], g_me[g]
            ub, pb0, pbc, pbs = g_u[g], g_p0[g], g_pc[g], g_ps[g]
            ua, pa0, pac, pas = ub, pb0, pbc, pbs
            A0, Ac, As = 0.0, 0.0, 0.0
            ps, pe = i, i
            m = ms
            while m <= me:
                while ps < j and ev_m0[ps] <= m:
                    A0 += ev_amp[ps]
                    Ac += ev_cs[ps]
                    As += ev_sn[ps]
                    q = ev_q[ps]
                    ub -= q
                    pb0 += q * ev_h0[ps]
                    pbc += q * ev_hc[ps]
                    pbs += q * ev_hs[ps]
                    ps += 1
                while pe < ps and ev_m1[pe] <= m:
                    A0 -= ev_amp[pe]
                    Ac -= ev_cs[pe]
                    As -= ev_sn[pe]
                    q = ev_q[pe]
                    ua -= q
                    pa0 += q * ev_h0[pe]
                    pac += q * ev_hc[pe]
                    pas += q * ev_hs[pe]
                    pe += 1
                mb = me
                if ps < j and ev_m0[ps] - 1 < mb:
                    mb = ev_m0[ps] - 1
                if pe < ps and ev_m1[pe] - 1 < mb:
                    mb = ev_m1[pe] - 1
                ma = m
                m = mb + 1
                # the piece [ma, mb]: echoes a + amp cos(ωR - φ0), continuum <= ua · max G
                pa_ = 0.5 * A0
                bc, bs = -0.5 * Ac, -0.5 * As
                amp_ = math.sqrt(bc * bc + bs * bs)
                cub = 0.0
                if has_cont:
                    cub = ua * G[_range_argmax(G, sp, ma, mb)] * (1.0 + 1e-9) + slack
                phi0 = math.atan2(bs, bc)
                mm = ma
                if amp_ > 0.0:
                    rp = phi0 / omega
                    rp += length * math.floor(((ma + mb) * 0.5 * step - rp) / length + 0.5)
                    mm = min(max(int(math.floor(rp / step + 0.5)), ma), mb)
                for rep in range(2):  # the seed node (the echoes' crest), then every node that can beat the best
                    mode = 0  # 0: the seed, 1: every node, 2: where a + amp cos(ωR - φ0) > best - cub
                    n_lo, n_hi = 0, 0
                    base_lo, base_hi = 0.0, 0.0
                    if rep == 1:
                        thr = best_v - cub - pa_ - 1e-12 * (abs(pa_) + amp_ + cub)
                        if not prune or (amp_ > 0.0 and thr < -amp_) or (amp_ <= 0.0 and thr < 0.0):
                            mode = 1
                        elif amp_ <= 0.0 or thr >= amp_:
                            break
                        else:
                            mode = 2
                            dl = math.acos(thr / amp_)
                            base_lo, base_hi = (phi0 - dl) / omega, (phi0 + dl) / omega
                            n_lo = int(math.floor((ma * step - base_hi) / length))
                            n_hi = int(math.ceil((mb * step - base_lo) / length))
                    for n in range(n_lo, n_hi + 1):
                        if mode == 0:
                            lo, hi = mm, mm
                        elif mode == 1:
                            lo, hi = ma, mb
                        else:
                            lo = max(int(math.floor((base_lo + n * length) / step)) - 1, ma)
                            hi = min(int(math.ceil((base_hi + n * length) / step)) + 1, mb)
                        for mq in range(lo, hi + 1):
                            R = mq * step
                            v = pa_ - 0.5 * (cosn[mq] * Ac + sinn[mq] * As)
                            if has_cont and R - length < r0:
                                if R <= r0:
                                    hb0, hbc, hbs = H0n[mq], Hcn[mq], Hsn[mq]
                                else:
                                    hb0, hbc, hbs = hr0_0, hr0_c, hr0_s
                                d0 = ub * hb0 + pb0 - (ua * H0l[mq] + pa0)
                                dc = ub * hbc + pbc - (ua * Hcl[mq] + pac)
                                ds = ub * hbs + pbs - (ua * Hsl[mq] + pas)
                                cont = 0.5 * d0 - 0.5 * (cosn[mq] * dc + sinn[mq] * ds)
                                if cont > 0.0:
                                    v += cont
                            if v > best_v:
                                best_v, best_m = v, mq
        if best_m < 0 or not best_v > 0.0:
            power[b], r_out[b], source[b], dominant[b] = 0.0, 0.0, 0, -1
            continue
        # ---- parabola through the neighbours
        R_best = best_m * step
        vb = best_v
        if m_lo < best_m < m_hi:
            pa, ca = _evaluate((best_m - 1) * step, n_ev, ev, r0, length, omega, integrals, hr0, parts)
            pm, cm = _evaluate(best_m * step, n_ev, ev, r0, length, omega, integrals, hr0, parts)
            pc, cc = _evaluate((best_m + 1) * step, n_ev, ev, r0, length, omega, integrals, hr0, parts)
            va, vm, vc = pa + ca, pm + cm, pc + cc
            # three-point fit a + b cos ω(R - R_m) + c sin ω(R - R_m): exact for hard echoes, a parabola's equal on
            # smooth ones (second order)
            bq = (vm - 0.5 * (va + vc)) / one_m_cos
            if bq > 0.0:
                cq = 0.5 * (vc - va) / sin_w
                phi = min(max(math.atan2(cq, bq), -half_w), half_w)
                R_best = best_m * step + phi / omega
                vb = vm - bq + bq * math.cos(phi) + cq * math.sin(phi)
        # ---- attribution at the peak
        pul, cont = _evaluate(R_best, n_ev, ev, r0, length, omega, integrals, hr0, parts)
        tgt = 0.0
        part_total = 0.0
        top_p, top_v = -1, 0.0
        for e in range(n_ev):
            if parts[e] <= 0.0:
                continue
            if ev_p[e] < 0:
                tgt += parts[e]
                continue
            part_total += parts[e]
            if ev_p[e] == top_p:
                continue
            acc = 0.0  # this particle's echo: all its sub-rays
            for f in range(n_ev):
                if ev_p[f] == ev_p[e]:
                    acc += parts[f]
            if acc > top_v:
                top_p, top_v = ev_p[e], acc
        if part_total > tgt and part_total > cont:
            source[b] = PARTICLE
            dominant[b] = top_p
        elif tgt >= cont and tgt > 0.0:
            source[b] = TARGET
            dominant[b] = -1
        else:
            source[b] = FOG
            dominant[b] = -1
        r_rep = R_best - 0.5 * length
        power[b] = vb * r_rep * r_rep * _gain(r_rep, r_ref, falloff) if r_rep > 0.0 else 0.0
        r_out[b] = R_best
        # ---- the target's own return where the strongest peak is not it (the receiver's second choice)
        if source[b] != TARGET and r0 < math.inf and r0 > 0.0:
            R_t = r0 + 0.5 * length
            pul_t, cont_t = _evaluate(R_t, n_ev, ev, r0, length, omega, integrals, hr0, parts)
            own = 0.0
            for e in range(n_ev):
                if ev_p[e] < 0 and parts[e] > 0.0:
                    own += parts[e]
            if own > 0.0:
                target_power[b] = (pul_t + cont_t) * r0 * r0 * _gain(r0, r_ref, falloff)
                target_r[b] = R_t


@njit(cache=True, nogil=True)
def _waveform_kernel(Rs, b, beams, particles, pattern, sensor, gain, shadow, integrals, out_pulses,
                     out_cont):  # pragma: no cover
    """Beam ``b``'s waveform at the receiver ranges ``Rs`` [m]: sub-ray echoes and continuum, separately (the records
    as `_beams_kernel`'s)."""
    length = sensor.length
    omega = 2.0 * math.pi / length
    k_sub = pattern.px.shape[0]
    scratch = SubrayScratch(np.empty((k_sub, 3)), np.empty(k_sub), np.empty(k_sub, dtype=np.int64))
    n_max = k_sub + 1
    ev = BeamEvents(np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max, dtype=np.int64),
                    np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max), np.empty(n_max))
    parts = np.empty(n_max)
    n_ev, _ = _events(b, beams, particles, pattern, sensor, gain, shadow, integrals, omega, scratch, ev)
    r0 = beams.r0[b]
    has_cont, h, H0, Hc, Hs = integrals.has_cont, integrals.h, integrals.H0, integrals.Hc, integrals.Hs
    hr0_0 = hr0_c = hr0_s = 0.0
    if has_cont and r0 < math.inf:
        hr0_0, hr0_c, hr0_s = _interp(H0, r0, h), _interp(Hc, r0, h), _interp(Hs, r0, h)
    hr0 = (hr0_0, hr0_c, hr0_s)
    for i in range(Rs.shape[0]):
        out_pulses[i], out_cont[i] = _evaluate(Rs[i], n_ev, ev, r0, length, omega, integrals, hr0, parts)
