"""LiDAR snow and rain: every beam of a scan through one 3-D particle field (Hahner et al. 2022, generalised).

Physics (``shared/docs/physics.md`` sections 1 and 3). Each beam is a cone from the sensor position at its own
firing time, of radius ``w(s) = s tan(θ/2)`` at axial distance ``s`` (θ: full divergence, ~3 mrad), up to its
measured range ``R_0`` (or the maximum range for beams without return). A particle (a sphere of diameter D, at
``P(t) = P(t_ref) + v (t - t_ref)`` at the beam's firing time t) intersects the beam if its centre lies in front of
the target and closer to the axis than ``w(s) + D/2``. Its occlusion ratio is the share of the beam cross-section it
covers — the circle–circle overlap of its disk with the beam disk in the plane at its range, over ``π w²`` — nearest
particle first: a disk overlapping no nearer disk inside the beam gets the closed form, otherwise its still uncovered
part is counted on a 48 x 48 grid over its box. The target keeps the rest; the ratios sum to 1.

Received signal: the sum of closed-form hard-target pulses (`weatheralign.lidar.pulse`: ``sin²(π (R - r_k) / (c τ_H))``
on ``[r_k, r_k + c τ_H]``), one per particle at its range and one for the target with its remaining ratio, all
attenuated by the bulk extinction of the unresolved particles (below). Between consecutive pulse starts/ends the sum
is a constant plus one sinusoid of period ``c τ_H``, so its maximum is found exactly (no receiver grid); the measured
range is the peak position minus ``c τ_H / 2`` (as in Hahner's code). A peak within ``keep_tolerance`` (0.2 m) of
``R_0`` keeps the point where it is with the peak intensity (ATTENUATED, or UNCHANGED if its float32 intensity is
bit-identical); otherwise the point moves along its beam to the measured range (SCATTERED, with the id of the particle
contributing most at the peak). A particle echo below the detector noise floor is not detected: the target's own
echo then decides, and a return the weather pushed below the floor is LOST (points that were below the floor in clear
weather were detected nevertheless and are kept, as in the fog model). Beams without return can return a particle:
SCATTERED clutter with ``source_index`` -1 (the reference code never simulates those beams).

Particle echo vs target echo (the calibration choice, `IntensityModel`). A clear measurement ``i_0`` at ``R_0`` fixes
only the product of the system constant and the target's (unknown) reflectivity; a particle's echo needs the system
constant alone. We calibrate it from the sensor's intensity model: a Lambertian target of reflectivity ρ filling the
beam at normal incidence reports ``i = scale ρ g(R)``, ``g(R) = min(1, (r_ref / R)^falloff)`` being the range
compensation the sensor applies to the raw ``1/R²`` power. In raw units (``i / (R² g(R))``) a particle — a disk of
reflectivity ρ_p covering ``ratio`` of the footprint at range r — gives ``scale ρ_p ratio ξ(r) / r²``, the target
``i_0 ratio_t / (R_0² g(R_0))``, and the detector reports ``P* R² g(R)`` at the measured range R, so a clear target
comes back as ``i_0`` exactly. The synthetic world's renderer is exactly ``scale = 255, r_ref = 10 m, falloff = 1``
(`SYNTHETIC_INTENSITY`, the default): there a flake filling the beam reports what a 0.9-reflectivity wall would.
Hahner's published code is the case ``r_ref = 1 m, falloff = 2`` (`HAHNER_INTENSITY`: a flake reports
``0.9 · 255 · ratio / r²`` while the target is normalised at its own range), and a reflectance-calibrated sensor
(KITTI) is ``falloff = 0`` (`CALIBRATED_INTENSITY`).

Dense fields. Physical densities (~166 flakes/m³ at 2 mm/h, ~4000 drops/m³ at 50 mm/h: ~10^8 particles within the
sensor's reach) cannot all be tested against every beam. A particle that would cover less than ``ratio_threshold``
of a beam even when centred on it is folded into the bulk extinction: space is cut into range shells ``[s_0, s_1)``
around the sensor path (``0, 1 m, then x1.25``) with thresholds ``D_k = 2 w(s_0) sqrt(ratio_threshold)``; the field
cells that some beam can reach (an angular reach map of beam lengths, widened by the sensor's motion, the beam and
the particle radius) are materialised once each, with the threshold of the shell of the cell's nearest point (the
field's nested ``min_diameter`` queries return exactly the particles ``D >= D_k`` of the one field), and a particle
counts as resolved iff ``D >= D_k`` of the shell holding its centre. The unresolved rest of shell k attenuates every
echo by ``exp(-2 · factor · ∫ field.unresolved_extinction(D_k) ds)``; ``factor = 1/4`` (default) is their geometric
shadow counted once, exactly how a resolved particle's ratio acts on the target (Q_ext = 2 counts diffraction too,
which the 3 mrad beam keeps; a monostatic beam is hidden where it is shadowed), which makes the results independent
of the threshold (measured in the benchmark). Resolved particles are matched to beams through a grid of beam
directions per time slice of the sweep (each slice with its own reference origin and time; the search window is
widened by their spread, the beam radius and the particle radius), and every candidate pair is tested exactly at the
beam's firing time. Kernels are serial numba (``nogil``): run frames in parallel threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.data.frame import LidarScan
from weatheralign.lidar.beams import Beams, beams_from_scan
from weatheralign.lidar.pulse import PulseSensor
from weatheralign.medium.field import DEFAULT_MAX_PARTICLES, ParticleField, Particles

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

SNOW_REFLECTIVITY = 0.9
"""Snowflake reflectivity (Hahner et al. 2022: 90 %)."""

RAIN_REFLECTIVITY = 0.02
"""Raindrop reflectance: water's normal-incidence Fresnel reflectance ((n - 1) / (n + 1))² with n = 1.33."""

SNOW_SENSOR = PulseSensor(tau_h=10e-9)
"""The snow model's pulse (τ_H = 10 ns, HDL-64 datasheet) with the default overlap, Γ and saturation."""

DEFAULT_DIVERGENCE = 3e-3
"""Full beam divergence [rad] of the HDL-32E / HDL-64E."""

DEFAULT_RATIO_THRESHOLD = 1e-3
"""Particles covering less than this share of a beam even when centred on it go into the bulk extinction."""

MAX_AUTO_RATIO_THRESHOLD = 1e-2
"""Cap of `auto_ratio_threshold` for dark particles (rain)."""

DEFAULT_NOISE_FLOOR = 0.5
"""Detector noise floor on the 0..255 scale (the synthetic world's minimum detectable intensity)."""

KEEP_TOLERANCE = 0.2
"""A peak within this distance [m] of the original range keeps the point where it is."""

SHELL_RATIO = 1.25
FIRST_SHELL = 1.0
SAMPLE_GRID = 48
_SLICE_BEAMS = 1024  # beams per time slice of the sweep
_MAX_SLICES = 64
_BIN = 3e-3  # angular bin [rad] of the beam-direction grid
_REACH_BIN = 0.0175  # reach-map bin: z-component of the direction, and azimuth [rad]
_SLICE_TABLE_BIN = math.radians(2.0)
_OCC_BIN = 1e-3  # sin-elevation bin of the beam-occupancy prefilter


class ParticleLabel(IntEnum):
    """What snow or rain did to a point."""

    UNCHANGED = 0  # bit-identical to the input
    ATTENUATED = 1  # same position, intensity changed (occluded and/or attenuated, or a particle echo merged in)
    SCATTERED = 2  # the echo of a particle: moved along its beam (or clutter on a beam without return)
    LOST = 3  # the return fell below the detector noise floor: dropped


@dataclass(frozen=True)
class IntensityModel:
    """How the sensor reports intensity: ``i = scale · ρ · cos θ · g(R)`` for a Lambertian target of reflectivity ρ
    covering the beam, with ``g(R) = min(1, (r_ref / R)^falloff)`` (see the module docstring).

    Attributes:
        scale: intensity (0..255) of ρ = 1 at normal incidence where ``g = 1``.
        r_ref: range [m] up to which the sensor compensates the raw ``1/R²`` fall-off fully.
        falloff: exponent of the residual fall-off beyond ``r_ref`` (2 = raw power, 0 = calibrated reflectance).
    """

    scale: float = 255.0
    r_ref: float = 10.0
    falloff: float = 1.0

    def __post_init__(self) -> None:
        for name in ("scale", "r_ref"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"IntensityModel.{name} = {v!r}; expected a finite value > 0")
        if not (math.isfinite(self.falloff) and 0.0 <= self.falloff <= 4.0):
            raise ValueError(f"IntensityModel.falloff = {self.falloff!r}; expected 0 <= falloff <= 4")

    def gain(self, r: NDArray | float) -> F64:
        """``g(R)`` (any shape) for ranges ``r`` [m]."""
        r = np.maximum(np.asarray(r, dtype=np.float64), 1e-9)
        return np.minimum(1.0, (self.r_ref / r) ** self.falloff)

    def intensity(self, reflectivity: NDArray | float, r: NDArray | float, ratio: NDArray | float = 1.0) -> F64:
        """Reported intensity (0..255, unclipped) of a disk of ``reflectivity`` covering ``ratio`` of the beam at range
        ``r`` [m], in clear air."""
        return self.scale * np.asarray(reflectivity) * np.asarray(ratio) * self.gain(r)


SYNTHETIC_INTENSITY = IntensityModel(255.0, 10.0, 1.0)
"""The synthetic world's HDL-32E: ``255 ρ cos θ min(1, 10 m / R)`` (`world.shading.lidar_intensity`)."""

HAHNER_INTENSITY = IntensityModel(255.0, 1.0, 2.0)
"""Hahner's published snow code: a particle reports ``255 ρ ratio / r²`` (raw power, calibrated at 1 m)."""

CALIBRATED_INTENSITY = IntensityModel(255.0, 1.0, 0.0)
"""A sensor reporting calibrated reflectance (KITTI's 0..1 reflectance): ``i = 255 ρ cos θ`` at any range."""


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
        labels: (M,) uint8 `ParticleLabel` of each output point (never LOST).
        particle_id: (M,) int64 id of the particle that produced a SCATTERED point, -1 otherwise.
        source_index: (M,) int64 row of the input point, -1 for clutter from beams without return.
        times: (M,) float64 firing time of each output point's beam [s].
        input_labels: (N,) uint8 `ParticleLabel` of every input point (LOST included).
        counts: input points per label name plus ``"CLUTTER"`` (points added on beams without return).
        intensity_max: intensity scale of ``points``.
        hits: the resolved particle–beam intersections with their occlusion ratios.
        beam_index: (M,) int64 the beam (index into the `Beams`) of each output point.
        beam_range: (B,) measured range of each beam [m] (nan where nothing was detected).
        beam_intensity: (B,) intensity of each beam's detected echo on the 0..255 scale (0 where none).
        beam_particle: (B,) int64 id of the particle whose echo a beam detected, -1 otherwise.
        beam_label: (B,) uint8 per beam: a `ParticleLabel`, or 255 for a beam without return that stays empty.
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


# ============================================================================================== numba kernels


@njit(nogil=True, cache=True, inline="always")
def _window(x, sz):  # pragma: no cover
    """Search window around a direction with z-component ``sz`` for beams within angle ``asin(x)`` (x < 0.5):
    ``(delta, ha, full_az)`` with ``delta >= asin(x)`` (also bounds the change of the z-component) and ``ha`` >= the
    largest azimuth difference of such beams, or ``full_az`` when every azimuth qualifies. No trigonometry: for two
    directions within angle δ, ``sin²(Δφ/2) <= sin²(δ/2) / (cos e1 cos(|e1| + δ))``, and ``asin(y) <= y (1 + y²)``
    for ``y <= 0.5``."""
    delta = x * (1.0 + x * x)
    cos_el = math.sqrt(max(0.0, 1.0 - sz * sz))
    cos_d = math.sqrt(1.0 - x * x)
    cmin = cos_el * cos_d - abs(sz) * x
    if cmin <= 1e-9:
        return delta, math.pi, True
    arg = math.sqrt(max(0.0, 0.5 * (1.0 - cos_d))) / math.sqrt(cos_el * cmin)
    if arg >= 0.5:
        return delta, math.pi, True
    return delta, 2.0 * arg * (1.0 + arg * arg), False


@njit(nogil=True, cache=True, inline="always")
def _wrap_bin(b, n):  # pragma: no cover
    """Azimuth bin index ``b`` (at most one turn outside ``[0, n)``) wrapped into ``[0, n)``."""
    if b < 0:
        return b + n
    if b >= n:
        return b - n
    return b


@njit(nogil=True, cache=True, inline="always")
def _reach_az_bin(n_ra):  # pragma: no cover
    """Azimuth bin width [rad] of a reach map with ``n_ra`` azimuth bins."""
    return 2.0 * math.pi / n_ra


@njit(nogil=True, cache=True)
def _cells_kernel(s_max, cx, cy, cz, e_all, r_max, tanh, reach, d_reach, n_re, n_ra, tan_lo, tan_hi,
                  cs, cell_z, nz, z_min, height, shift, ix_lo, ix_hi, iy_lo, iy_hi, out, out_d):  # pragma: no cover
    """Co-moving cells (M, 3) holding particles that some beam can reach, with the distance of each cell's nearest
    point from the sensor centre (cx, cy, cz) (``out_d``); written into ``out`` (capacity rows), returns the count
    (may exceed the capacity).

    ``e_all``: origin spread + particle motion [m]; ``reach`` (n_re, n_ra): the longest beam per direction bin
    (z-component x azimuth); a cell is kept if a direction bin within its angular radius (widened by ``e_all``, the
    beam and the particle radius) holds a beam reaching its nearest possible axial distance; cells outside the
    elevation band ``[atan(tan_lo), atan(tan_hi)]`` of all beams are skipped first. A cell's world box at the query
    time: ``x in [ix cs, (ix+1) cs] + shift_x`` (same in y), z in ``z_min + ([iz cell_z, (iz+1) cell_z] + shift_z
    mod height)`` (split in two where it wraps) — the field's documented co-moving grid.
    """
    n = 0
    half_xy = 0.5 * cs
    big = e_all + r_max + tanh * (s_max + e_all) + 2.0 * cs + cell_z
    d_az = _reach_az_bin(n_ra)
    for ix in range(ix_lo, ix_hi + 1):
        x0 = ix * cs + shift[0]
        dx_lo = max(x0 - cx, cx - (x0 + cs), 0.0)
        dx_hi = max(abs(x0 - cx), abs(x0 + cs - cx))
        for iy in range(iy_lo, iy_hi + 1):
            y0 = iy * cs + shift[1]
            dy_lo = max(y0 - cy, cy - (y0 + cs), 0.0)
            if dx_lo * dx_lo + dy_lo * dy_lo >= s_max * s_max:
                continue
            dy_hi = max(abs(y0 - cy), abs(y0 + cs - cy))
            h_lo = math.sqrt(dx_lo * dx_lo + dy_lo * dy_lo)
            h_hi = math.sqrt(dx_hi * dx_hi + dy_hi * dy_hi)
            # the elevation band of the beams bounds the reachable heights of this column
            z_top = cz + big + (tan_hi * (h_hi + big) if tan_hi >= 0.0 else tan_hi * max(h_lo - big, 0.0))
            z_bot = cz - big + (tan_lo * (h_hi + big) if tan_lo <= 0.0 else tan_lo * max(h_lo - big, 0.0))
            mx = x0 + half_xy - cx
            my = y0 + half_xy - cy
            az = math.atan2(my, mx)
            for iz in range(nz):
                b = (iz * cell_z + shift[2]) % height
                if b >= height:
                    b = 0.0
                pieces = 1 if b + cell_z <= height else 2
                take = False
                d_near = 1e300
                for piece in range(pieces):
                    if piece == 0:
                        za = z_min + b
                        zb = z_min + min(b + cell_z, height)
                    else:
                        za = z_min
                        zb = z_min + (b + cell_z - height)
                    if zb < z_bot or za > z_top:
                        continue
                    dz_lo = max(za - cz, cz - zb, 0.0)
                    dmin = math.sqrt(dx_lo * dx_lo + dy_lo * dy_lo + dz_lo * dz_lo)
                    if dmin >= s_max:
                        continue
                    mz = 0.5 * (za + zb) - cz
                    hz = 0.5 * (zb - za)
                    h = math.sqrt(2.0 * half_xy * half_xy + hz * hz)
                    d = math.sqrt(mx * mx + my * my + mz * mz)
                    margin = h + e_all + r_max + tanh * (d + h + e_all)
                    ok = False
                    if margin >= 0.5 * d:
                        ok = True
                    else:
                        need = d - margin
                        sz = mz / d
                        delta, ha, full = _window(margin / d, sz)
                        e_lo = max(int(math.floor((sz - delta + 1.0) / d_reach)), 0)
                        e_hi = min(int(math.floor((sz + delta + 1.0) / d_reach)), n_re - 1)
                        if full:
                            a_lo, a_hi = 0, n_ra - 1
                        else:
                            a_lo = int(math.floor((az - ha + math.pi) / d_az))
                            a_hi = int(math.floor((az + ha + math.pi) / d_az))
                            if a_hi - a_lo + 1 >= n_ra:
                                a_lo, a_hi = 0, n_ra - 1
                        for eb in range(e_lo, e_hi + 1):
                            for ab in range(a_lo, a_hi + 1):
                                abm = _wrap_bin(ab, n_ra)
                                if reach[eb, abm] >= need:
                                    ok = True
                                    break
                            if ok:
                                break
                    if ok:
                        take = True
                        d_near = min(d_near, dmin)
                if take:
                    if n < out.shape[0]:
                        out[n, 0] = ix
                        out[n, 1] = iy
                        out[n, 2] = iz
                        out_d[n] = d_near
                    n += 1
    return n


@njit(nogil=True, cache=True)
def _hits_kernel(pos, radius, ids, vel, t_part, edges, thresholds,
                 b_orig, b_dir, b_e1, b_e2, b_time, b_len, tanh, e_all, t_half,
                 sl_orig, sl_time, sl_e, sl_dt, sl_az0, sl_span, sl_full, sl_z0, sl_nz, sl_naz, sl_base,
                 d_bin, bin_off, bin_beams, tb_off, tb_slices, d_tb, occ_cum, d_occ,
                 out_beam, out_pid, out_s, out_u1, out_u2, out_a):  # pragma: no cover
    """Every (beam, particle) intersection of the particles (local positions ``pos`` (P, 3) at ``t_part``, radii,
    ids) that are resolved at their range (diameter >= ``thresholds[k]`` for the shell ``edges[k] <= distance from
    the local origin < edges[k+1]``); returns the count (may exceed the capacity of
    the ``out_*`` arrays, which then hold the first ones).

    A particle at the beam's firing time ``t_b`` is at ``pos + vel (t_b - t_part)``; it intersects beam b if its
    axial distance ``s`` from the beam origin is in (0, length) and its distance to the axis is below
    ``s tan(θ/2) + radius``. Candidates: time slices from an azimuth table (seen from the local origin, window widened
    by the origin spread ``e_all``), then per slice the bins (z-component of the direction x azimuth) of beam
    directions within the exact bound of the slice (its origin spread, time spread, beam and particle radius).
    """
    n = 0
    speed = math.sqrt(vel[0] * vel[0] + vel[1] * vel[1] + vel[2] * vel[2])
    n_slices = sl_orig.shape[0]
    n_tb = tb_off.shape[0] - 1
    n_occ = occ_cum.shape[0] - 1
    n_shells = thresholds.shape[0]
    two_pi = 2.0 * math.pi
    stamp = np.full(n_slices, -1, dtype=np.int64)
    cand = np.empty(n_slices, dtype=np.int64)
    z_all_lo = 1e300
    z_all_hi = -1e300
    for k in range(n_slices):
        z_all_lo = min(z_all_lo, sl_z0[k])
        z_all_hi = max(z_all_hi, sl_z0[k] + sl_nz[k] * d_bin)
    for i in range(pos.shape[0]):
        px, py, pz = pos[i, 0], pos[i, 1], pos[i, 2]
        rho = math.sqrt(px * px + py * py + pz * pz)
        r = radius[i]
        shell = np.searchsorted(edges, rho, side="right") - 1
        if shell < 0 or shell >= n_shells or 2.0 * r < thresholds[shell]:
            continue  # beyond the reach, or folded into the bulk extinction at this range
        # --- global stage: seen from the local origin, every beam origin within e_all
        x_c = (tanh * (rho + e_all) + r + e_all + speed * t_half) / rho if rho > 0.0 else 1.0
        n_cand = 0
        if x_c >= 0.5:
            for k in range(n_slices):
                cand[n_cand] = k
                n_cand += 1
        else:
            sz_c = pz / rho
            delta_c, ha_c, full_c = _window(x_c, sz_c)
            if sz_c + delta_c < z_all_lo or sz_c - delta_c > z_all_hi:
                continue
            o_lo = min(max(int(math.floor((sz_c - delta_c + 1.0) / d_occ)), 0), n_occ)
            o_hi = min(max(int(math.floor((sz_c + delta_c + 1.0) / d_occ)) + 1, 0), n_occ)
            if occ_cum[o_hi] == occ_cum[o_lo]:
                continue
            if full_c:
                for k in range(n_slices):
                    cand[n_cand] = k
                    n_cand += 1
            else:
                az_c = math.atan2(py, px)
                t_lo = int(math.floor((az_c - ha_c + math.pi) / d_tb))
                t_hi = int(math.floor((az_c + ha_c + math.pi) / d_tb))
                for tb in range(t_lo, t_hi + 1):
                    tbm = _wrap_bin(tb, n_tb)
                    for jj in range(tb_off[tbm], tb_off[tbm + 1]):
                        k = tb_slices[jj]
                        if stamp[k] != i:
                            stamp[k] = i
                            cand[n_cand] = k
                            n_cand += 1
        # --- per slice: exact window around the direction seen from the slice's origin at the slice's time
        for ci in range(n_cand):
            k = cand[ci]
            dt = sl_time[k] - t_part
            qx = px + vel[0] * dt - sl_orig[k, 0]
            qy = py + vel[1] * dt - sl_orig[k, 1]
            qz = pz + vel[2] * dt - sl_orig[k, 2]
            rk = math.sqrt(qx * qx + qy * qy + qz * qz)
            roff = tanh * (rk + sl_e[k]) + r + sl_e[k] + speed * sl_dt[k]
            z0 = sl_z0[k]
            nzb = sl_nz[k]
            naz = sl_naz[k]
            wrap = False
            if rk <= 0.0 or roff >= 0.5 * rk:
                e_lo, e_hi = 0, nzb - 1
                a_lo, a_hi = 0, naz - 1
            else:
                sz = qz / rk
                delta, ha, full = _window(roff / rk, sz)
                e_lo = int(math.floor((sz - delta - z0) / d_bin))
                e_hi = int(math.floor((sz + delta - z0) / d_bin))
                if e_hi < 0 or e_lo >= nzb:
                    continue
                e_lo = max(e_lo, 0)
                e_hi = min(e_hi, nzb - 1)
                if full:
                    a_lo, a_hi = 0, naz - 1
                else:
                    rel = math.atan2(qy, qx) - sl_az0[k]
                    if rel < 0.0:
                        rel += two_pi
                    if rel >= two_pi:
                        rel -= two_pi
                    if sl_full[k]:
                        wrap = True
                    elif rel > sl_span[k] + ha:
                        rel -= two_pi
                    a_lo = int(math.floor((rel - ha) / d_bin))
                    a_hi = int(math.floor((rel + ha) / d_bin))
                    if wrap:
                        if a_hi - a_lo + 1 >= naz:
                            a_lo, a_hi = 0, naz - 1
                            wrap = False
                    else:
                        if a_hi < 0 or a_lo >= naz:
                            continue
                        a_lo = max(a_lo, 0)
                        a_hi = min(a_hi, naz - 1)
            base = sl_base[k]
            for eb in range(e_lo, e_hi + 1):
                row = base + eb * naz
                for ab in range(a_lo, a_hi + 1):
                    col = ab % naz if wrap else ab
                    cell = row + col
                    for jj in range(bin_off[cell], bin_off[cell + 1]):
                        b = bin_beams[jj]
                        dtb = b_time[b] - t_part
                        vx = px + vel[0] * dtb - b_orig[b, 0]
                        vy = py + vel[1] * dtb - b_orig[b, 1]
                        vz = pz + vel[2] * dtb - b_orig[b, 2]
                        s = vx * b_dir[b, 0] + vy * b_dir[b, 1] + vz * b_dir[b, 2]
                        if s <= 0.0 or s >= b_len[b]:
                            continue
                        perp2 = vx * vx + vy * vy + vz * vz - s * s
                        wb = tanh * s
                        lim = wb + r
                        if perp2 >= lim * lim:
                            continue
                        if n < out_beam.shape[0]:
                            out_beam[n] = b
                            out_pid[n] = ids[i]
                            out_s[n] = s
                            if wb > 0.0:
                                out_u1[n] = (vx * b_e1[b, 0] + vy * b_e1[b, 1] + vz * b_e1[b, 2]) / wb
                                out_u2[n] = (vx * b_e2[b, 0] + vy * b_e2[b, 1] + vz * b_e2[b, 2]) / wb
                                out_a[n] = r / wb
                            else:  # a pencil beam: any hit covers it
                                out_u1[n] = 0.0
                                out_u2[n] = 0.0
                                out_a[n] = 1e300
                        n += 1
    return n


@njit(nogil=True, cache=True, inline="always")
def _disk_share(cx, cy, a):  # pragma: no cover
    """Share of the unit disk covered by the disk of radius ``a`` centred at (cx, cy)."""
    c = math.sqrt(cx * cx + cy * cy)
    if c >= 1.0 + a:
        return 0.0
    if c <= abs(1.0 - a):
        m = min(a, 1.0)
        return m * m
    c2 = c * c
    a2 = a * a
    t1 = a2 * math.acos(max(-1.0, min(1.0, (c2 + a2 - 1.0) / (2.0 * c * a))))
    t2 = math.acos(max(-1.0, min(1.0, (c2 + 1.0 - a2) / (2.0 * c))))
    k = (-c + a + 1.0) * (c + a - 1.0) * (c - a + 1.0) * (c + a + 1.0)
    t3 = 0.5 * math.sqrt(max(k, 0.0))
    return min(max((t1 + t2 - t3) / math.pi, 0.0), 1.0)


@njit(nogil=True, cache=True, inline="always")
def _optical_depth(s, edges, alphas, tau_edges):  # pragma: no cover
    """One-way optical depth ∫_0^s α for the piecewise-constant α on ``edges`` (K+1,) (extended past the ends)."""
    if s <= edges[0]:
        return 0.0
    k = np.searchsorted(edges, s, side="right") - 1
    if k >= alphas.shape[0]:
        k = alphas.shape[0] - 1
    return tau_edges[k] + alphas[k] * (s - edges[k])


@njit(nogil=True, cache=True)
def _peak(starts, amps, m, length, bp, cs, sn):  # pragma: no cover
    """Maximum ``(R*, P*)`` of ``sum_k amps[k] sin²(π (R - starts[k]) / length)`` (each term on
    ``[starts[k], starts[k] + length]``) over the first ``m`` pulses; exact: between consecutive pulse starts/ends the
    sum is a constant plus one sinusoid of period ``length``. ``bp``, ``cs``, ``sn``: work arrays (>= 2m, m, m)."""
    nb = 0
    r0 = 1e300
    for k in range(m):
        if amps[k] > 0.0:
            r0 = min(r0, starts[k])
    if r0 == 1e300:
        return 0.0, 0.0
    omega = 2.0 * math.pi / length
    for k in range(m):
        if amps[k] > 0.0:
            phi = omega * (starts[k] - r0)
            cs[k] = amps[k] * math.cos(phi)
            sn[k] = amps[k] * math.sin(phi)
            # insertion into the sorted breakpoints
            for v in (starts[k], starts[k] + length):
                j = nb
                while j > 0 and bp[j - 1] > v:
                    bp[j] = bp[j - 1]
                    j -= 1
                bp[j] = v
                nb += 1
    best_r = r0
    best_p = -1.0
    for i in range(nb - 1):
        lo = bp[i]
        hi = bp[i + 1]
        if hi <= lo:
            continue
        mid = 0.5 * (lo + hi)
        a_sum = 0.0
        c_sum = 0.0
        s_sum = 0.0
        for k in range(m):
            if amps[k] > 0.0 and starts[k] <= mid and mid < starts[k] + length:
                a_sum += amps[k]
                c_sum += cs[k]
                s_sum += sn[k]
        if a_sum <= 0.0:
            continue
        # f(x) = a/2 - (c cos(ωx) + s sin(ωx)) / 2 with x = R - r0
        x_lo = lo - r0
        x_hi = hi - r0
        for x in (x_lo, x_hi):
            val = 0.5 * a_sum - 0.5 * (c_sum * math.cos(omega * x) + s_sum * math.sin(omega * x))
            if val > best_p:
                best_p = val
                best_r = x + r0
        psi = math.atan2(s_sum, c_sum)
        nturn = math.ceil((omega * x_lo - psi - math.pi) / (2.0 * math.pi))
        x_star = (psi + math.pi + 2.0 * math.pi * nturn) / omega
        if x_lo <= x_star <= x_hi:
            val = 0.5 * a_sum + 0.5 * math.sqrt(c_sum * c_sum + s_sum * s_sum)
            if val > best_p:
                best_p = val
                best_r = x_star + r0
    return best_r, best_p


@njit(nogil=True, cache=True)
def _response_kernel(hit_off, h_s, h_u1, h_u2, h_a, h_ratio, has_ret, lengths, i0,
                     pulse_len, r1, r2, part_gain, r_ref, falloff, edges, alphas, tau_edges,
                     keep_tol, floor, saturation, grid_n,
                     out_state, out_range, out_int, out_dom):  # pragma: no cover
    """Per beam: occlusion ratios (written to ``h_ratio``), the summed pulse, its peak and the outcome.

    ``out_state``: 0 keep the input bit for bit, 1 keep the position with ``out_int``, 2 scattered to
    ``out_range`` (dominant hit ``out_dom``), 3 lost, 4 nothing detected (beam without return).
    Intensities are on the 0..255 scale.
    """
    n_beams = lengths.shape[0]
    max_k = 0
    for b in range(n_beams):
        max_k = max(max_k, hit_off[b + 1] - hit_off[b])
    starts = np.empty(max_k + 1)
    amps = np.empty(max_k + 1)
    over = np.empty(max_k + 1, dtype=np.int64)
    work_bp = np.empty(2 * max_k + 2)
    work_c = np.empty(max_k + 1)
    work_s = np.empty(max_k + 1)
    n_sampled = 0
    for b in range(n_beams):
        h0 = hit_off[b]
        k_hits = hit_off[b + 1] - h0
        length = lengths[b]
        ret = has_ret[b]
        out_dom[b] = -1
        out_range[b] = np.nan
        out_int[b] = 0.0
        tau_target = _optical_depth(length, edges, alphas, tau_edges) if ret else 0.0
        if k_hits == 0:
            if not ret:
                out_state[b] = 4
                continue
            if tau_target == 0.0 or length <= 0.0:
                out_state[b] = 0
                out_range[b] = length
                out_int[b] = i0[b]
                continue
            val = min(i0[b] * math.exp(-2.0 * tau_target), saturation)
            out_range[b] = length
            out_int[b] = val
            out_state[b] = 3 if (floor >= 0.0 and val < floor and val < i0[b]) else 1
            continue
        # --- occlusion ratios, nearest first: closed form for a disk that overlaps no nearer disk inside the beam,
        # else the uncovered part of its disk is counted on a grid_n x grid_n grid over its box ∩ the beam's box
        blocked = False
        for j in range(k_hits):
            h = h0 + j
            cx, cy, a = h_u1[h], h_u2[h], h_a[h]
            share = 0.0 if blocked else _disk_share(cx, cy, a)
            if share > 0.0:
                n_over = 0
                for i in range(j):
                    hi = h0 + i
                    if h_ratio[hi] <= 0.0:
                        continue
                    dx = cx - h_u1[hi]
                    dy = cy - h_u2[hi]
                    rr = a + h_a[hi]
                    if dx * dx + dy * dy < rr * rr:
                        over[n_over] = hi
                        n_over += 1
                if n_over > 0:
                    n_sampled += 1
                    x_lo = max(cx - a, -1.0)
                    x_hi = min(cx + a, 1.0)
                    y_lo = max(cy - a, -1.0)
                    y_hi = min(cy + a, 1.0)
                    step_x = (x_hi - x_lo) / grid_n
                    step_y = (y_hi - y_lo) / grid_n
                    count = 0
                    for gi in range(grid_n):
                        x = x_lo + (gi + 0.5) * step_x
                        for gj in range(grid_n):
                            y = y_lo + (gj + 0.5) * step_y
                            if x * x + y * y >= 1.0:
                                continue
                            if (x - cx) * (x - cx) + (y - cy) * (y - cy) >= a * a:
                                continue
                            free = True
                            for q in range(n_over):
                                hq = over[q]
                                ex = x - h_u1[hq]
                                ey = y - h_u2[hq]
                                if ex * ex + ey * ey < h_a[hq] * h_a[hq]:
                                    free = False
                                    break
                            if free:
                                count += 1
                    share = count * step_x * step_y / math.pi
            h_ratio[h] = share
            if math.sqrt(cx * cx + cy * cy) + 1.0 <= a:  # this particle covers the whole beam
                blocked = True
        covered = 0.0
        for j in range(k_hits):
            covered += h_ratio[h0 + j]
        remaining = max(0.0, 1.0 - covered)
        # --- pulse amplitudes in raw power units (intensity / (R² g(R)))
        for j in range(k_hits):
            h = h0 + j
            s = h_s[h]
            xi = min(max((s - r1) / (r2 - r1), 0.0), 1.0)
            starts[j] = s
            amps[j] = part_gain * h_ratio[h] * xi / (s * s) * math.exp(
                -2.0 * _optical_depth(s, edges, alphas, tau_edges))
        m = k_hits
        if ret and length > 0.0:
            g0 = min(1.0, (r_ref / length) ** falloff)
            starts[m] = length
            amps[m] = i0[b] / (length * length * g0) * remaining * math.exp(-2.0 * tau_target)
            m += 1
        r_peak, p_peak = _peak(starts, amps, m, pulse_len, work_bp, work_c, work_s)
        if p_peak <= 0.0:
            if ret and remaining > 0.0:  # a zero-intensity target, no visible particle: stays at zero
                out_state[b] = 1
                out_range[b] = length
                out_int[b] = 0.0
            else:  # fully blocked by particles too close to be seen (no overlap ξ), or nothing at all
                out_state[b] = 3 if ret else 4
            continue
        r_meas = r_peak - 0.5 * pulse_len
        if ret and abs(r_meas - length) <= keep_tol:
            g0 = min(1.0, (r_ref / length) ** falloff)
            val = min(p_peak * length * length * g0, saturation)
            out_range[b] = length
            out_int[b] = val
            out_state[b] = 3 if (floor >= 0.0 and val < floor and val < i0[b]) else 1
            continue
        # the particle contributing most at the peak
        best = -1.0
        dom = -1
        for j in range(k_hits):
            x = r_peak - starts[j]
            if amps[j] > 0.0 and 0.0 <= x <= pulse_len:
                c = amps[j] * math.sin(math.pi * x / pulse_len) ** 2
                if c > best:
                    best = c
                    dom = j
        r_out = min(max(r_meas, 0.0), length)
        g1 = min(1.0, (r_ref / max(r_out, 1e-9)) ** falloff)
        val = min(p_peak * r_out * r_out * g1, saturation)
        if dom < 0 or (floor >= 0.0 and val < floor):
            if not ret:
                out_state[b] = 4
                continue
            # the strongest echo is a particle's but undetectable: the target's own echo decides (summed waveform
            # at the target's pulse peak), lost only if the weather pushed it below the floor
            x_t = length + 0.5 * pulse_len
            p_t = 0.0
            for j in range(m):
                x = x_t - starts[j]
                if amps[j] > 0.0 and 0.0 <= x <= pulse_len:
                    p_t += amps[j] * math.sin(math.pi * x / pulse_len) ** 2
            g0 = min(1.0, (r_ref / length) ** falloff)
            val_t = min(p_t * length * length * g0, saturation)
            out_range[b] = length
            out_int[b] = val_t
            out_state[b] = 3 if (floor >= 0.0 and val_t < floor and val_t < i0[b]) else 1
            continue
        out_state[b] = 2
        out_range[b] = r_out
        out_int[b] = val
        out_dom[b] = h0 + dom
    return n_sampled


# ============================================================================================== geometry set-up


@dataclass(frozen=True, eq=False)
class _BeamIndex:
    """Beams in local coordinates (global minus ``center``) with their time slices and direction grid."""

    center: F64
    origins: F64
    directions: F64
    e1: F64
    e2: F64
    times: F64
    lengths: F64
    tanh: float
    t_ref: float
    e_origin: float  # max |origin - center| [m]
    t_half: float  # max |t_b - t_ref| [s]
    sl_orig: F64
    sl_time: F64
    sl_e: F64
    sl_dt: F64
    sl_az0: F64
    sl_span: F64
    sl_full: NDArray[np.bool_]
    sl_el0: F64
    sl_nel: I64
    sl_naz: I64
    sl_base: I64
    bin_off: I64
    bin_beams: I64
    tb_off: I64
    tb_slices: I64
    occ_cum: I64
    reach: F64
    tan_lo: float  # tangent of the lowest beam elevation (clamped to ±1e3)
    tan_hi: float


def _perpendicular_basis(d: F64) -> tuple[F64, F64]:
    """Two unit vectors (N, 3) completing each unit direction ``d`` (N, 3) to an orthonormal basis."""
    helper = np.zeros_like(d)
    use_z = np.abs(d[:, 2]) < 0.9
    helper[use_z, 2] = 1.0
    helper[~use_z, 0] = 1.0
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(d, e1)


def _index_beams(beams: Beams, t_ref: float | None = None) -> _BeamIndex:
    """Slice the beams by firing time and bin each slice's beam directions on a grid of (z-component of the
    direction, azimuth) cells of ``_BIN``; also the azimuth table of the slices, the elevation occupancy and the reach
    map (longest beam per direction bin)."""
    n = len(beams)
    lo, hi = beams.origins.min(axis=0), beams.origins.max(axis=0)
    center = 0.5 * (lo + hi)
    origins = np.ascontiguousarray(beams.origins - center)
    d = np.ascontiguousarray(beams.directions, dtype=np.float64)
    e1, e2 = _perpendicular_basis(d)
    times = np.ascontiguousarray(beams.times, dtype=np.float64)
    if t_ref is None:
        t_ref = float(np.median(times))
    el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
    az = np.arctan2(d[:, 1], d[:, 0])

    order = np.lexsort((az, times))  # by firing time; beams fired together: by azimuth
    n_slices = int(np.clip(n // _SLICE_BEAMS, 1, _MAX_SLICES))
    bounds = np.linspace(0, n, n_slices + 1).astype(np.int64)
    sl = {k: [] for k in ("orig", "time", "e", "dt", "az0", "span", "full", "el0", "nel", "naz", "base")}
    flat = np.empty(n, dtype=np.int64)
    base = 0
    for k in range(n_slices):
        idx = order[bounds[k]:bounds[k + 1]]
        o = origins[idx]
        o_k = 0.5 * (o.min(axis=0) + o.max(axis=0))
        t = times[idx]
        t_k = 0.5 * (t.min() + t.max())
        a = np.sort(az[idx])
        gaps = np.diff(np.concatenate([a, [a[0] + 2 * np.pi]]))
        g = int(np.argmax(gaps))
        az0 = a[(g + 1) % len(a)]
        span = 2 * np.pi - gaps[g]
        full = span >= 2 * np.pi - 4 * _BIN
        if full:
            az0, span = -np.pi, 2 * np.pi
            naz = int(math.ceil(2 * np.pi / _BIN))
        else:
            naz = int(math.floor(span / _BIN)) + 1
        el0 = float(d[idx, 2].min()) - 1e-9  # bins in the z-component (sine of the elevation)
        nel = int(math.floor((float(d[idx, 2].max()) - el0) / _BIN)) + 1
        eb = np.minimum(np.floor((d[idx, 2] - el0) / _BIN).astype(np.int64), nel - 1)
        rel = np.mod(az[idx] - az0, 2 * np.pi)
        ab = np.floor(rel / _BIN).astype(np.int64)
        ab = np.mod(ab, naz) if full else np.clip(ab, 0, naz - 1)
        flat[idx] = base + eb * naz + ab
        for key, val in (("orig", o_k), ("time", t_k), ("e", float(np.linalg.norm(o - o_k, axis=1).max())),
                         ("dt", float(np.abs(t - t_k).max())), ("az0", az0), ("span", span), ("full", full),
                         ("el0", el0), ("nel", nel), ("naz", naz), ("base", base)):
            sl[key].append(val)
        base += nel * naz
    n_tb = int(round(2 * math.pi / _SLICE_TABLE_BIN))
    tb_lists: list[list[int]] = [[] for _ in range(n_tb)]
    for k in range(n_slices):
        if sl["full"][k]:
            bins = range(n_tb)
        else:
            b0 = int(math.floor((sl["az0"][k] + math.pi) / _SLICE_TABLE_BIN))
            b1 = int(math.floor((sl["az0"][k] + sl["span"][k] + math.pi) / _SLICE_TABLE_BIN))
            bins = sorted({b % n_tb for b in range(b0, b1 + 1)})
        for b in bins:
            tb_lists[b].append(k)
    tb_off = np.zeros(n_tb + 1, dtype=np.int64)
    np.cumsum([len(x) for x in tb_lists], out=tb_off[1:])
    tb_slices = np.array([k for x in tb_lists for k in x], dtype=np.int64)
    bin_beams = np.argsort(flat, kind="stable").astype(np.int64)
    bin_off = np.zeros(base + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=base), out=bin_off[1:])

    n_occ = int(math.ceil(2.0 / _OCC_BIN)) + 1
    occ = np.zeros(n_occ, dtype=np.int64)
    occ_b = np.clip(np.floor((d[:, 2] + 1.0) / _OCC_BIN).astype(np.int64), 0, n_occ - 1)
    occ[np.unique(occ_b)] = 1
    occ_cum = np.zeros(n_occ + 1, dtype=np.int64)
    np.cumsum(occ, out=occ_cum[1:])
    n_re, n_ra = int(math.ceil(2.0 / _REACH_BIN)) + 1, int(round(2 * math.pi / _REACH_BIN))
    reach = np.full((n_re, n_ra), -1.0)
    re_b = np.clip(np.floor((d[:, 2] + 1.0) / _REACH_BIN).astype(np.int64), 0, n_re - 1)
    ra_b = np.mod(np.floor((az + np.pi) / _REACH_BIN).astype(np.int64), n_ra)
    np.maximum.at(reach, (re_b, ra_b), beams.lengths)
    return _BeamIndex(
        center=center, origins=origins, directions=d, e1=e1, e2=e2, times=times,
        lengths=np.ascontiguousarray(beams.lengths, dtype=np.float64), tanh=math.tan(0.5 * beams.divergence),
        t_ref=float(t_ref), e_origin=float(np.linalg.norm(origins, axis=1).max()) if n else 0.0,
        t_half=float(np.abs(times - t_ref).max()) if n else 0.0,
        sl_orig=np.ascontiguousarray(np.array(sl["orig"]).reshape(-1, 3)), sl_time=np.array(sl["time"]),
        sl_e=np.array(sl["e"]), sl_dt=np.array(sl["dt"]), sl_az0=np.array(sl["az0"]), sl_span=np.array(sl["span"]),
        sl_full=np.array(sl["full"], dtype=bool), sl_el0=np.array(sl["el0"]),
        sl_nel=np.array(sl["nel"], dtype=np.int64), sl_naz=np.array(sl["naz"], dtype=np.int64),
        sl_base=np.array(sl["base"], dtype=np.int64), bin_off=bin_off, bin_beams=bin_beams, tb_off=tb_off,
        tb_slices=tb_slices, occ_cum=occ_cum, reach=reach,
        tan_lo=float(np.clip(np.tan(el.min()), -1e3, 1e3)) if n else 0.0,
        tan_hi=float(np.clip(np.tan(el.max()), -1e3, 1e3)) if n else 0.0)


class _HitBuffer:
    """Growable hit arrays filled shell by shell."""

    def __init__(self) -> None:
        self.parts: list[tuple] = []

    def add(self, index: _BeamIndex, pos: F64, radius: F64, ids: I64, vel: F64, t_part: float, edges: F64,
            thresholds: F64) -> int:
        if len(pos) == 0:
            return 0
        cap = max(4096, len(pos) // 8)
        while True:
            out = (np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap), np.empty(cap), np.empty(cap),
                   np.empty(cap))
            n = _hits_kernel(pos, radius, ids, vel, t_part, edges, thresholds, index.origins, index.directions,
                             index.e1, index.e2, index.times, index.lengths, index.tanh,
                             index.e_origin + float(np.linalg.norm(vel)) * index.t_half, index.t_half,
                             index.sl_orig, index.sl_time, index.sl_e, index.sl_dt, index.sl_az0, index.sl_span,
                             index.sl_full, index.sl_el0, index.sl_nel, index.sl_naz, index.sl_base, _BIN,
                             index.bin_off, index.bin_beams, index.tb_off, index.tb_slices, _SLICE_TABLE_BIN,
                             index.occ_cum, _OCC_BIN, *out)
            if n <= cap:
                break
            cap = n
        self.parts.append(tuple(a[:n].copy() for a in out))
        return n

    def collect(self) -> tuple:
        if not self.parts:
            return (np.zeros(0, np.int64), np.zeros(0, np.int64)) + tuple(np.zeros(0) for _ in range(4))
        cols = tuple(np.concatenate([p[c] for p in self.parts]) for c in range(6))
        order = np.lexsort((cols[2], cols[0]))
        return tuple(c[order] for c in cols)


# ============================================================================================== field queries


def _shell_edges(reach: float, first: float, ratio: float) -> F64:
    """Range-shell edges ``[0, first, first·ratio, ...]`` up to and including ``reach`` [m]."""
    edges = [0.0, first]
    while edges[-1] < reach:
        edges.append(edges[-1] * ratio)
    return np.array(edges)


def _reachable_cells(fld: ParticleField, index: _BeamIndex, t_ref: float, s_max: float, e_all: float,
                     r_max: float) -> tuple[I64, F64]:
    """Co-moving cells (M, 3) of ``fld`` holding particles within ``s_max`` of the sensor centre at ``t_ref`` that some
    beam can reach, and the distance (M,) [m] of each cell's nearest point from the centre."""
    shift = fld.velocity_array * (t_ref - fld.t_ref)
    c = index.center
    cs = fld.cell_size
    ix_lo = math.floor((c[0] - s_max - shift[0]) / cs) - 1
    ix_hi = math.floor((c[0] + s_max - shift[0]) / cs) + 1
    iy_lo = math.floor((c[1] - s_max - shift[1]) / cs) - 1
    iy_hi = math.floor((c[1] + s_max - shift[1]) / cs) + 1
    n_re, n_ra = index.reach.shape
    cap = int(min((ix_hi - ix_lo + 1) * (iy_hi - iy_lo + 1) * fld.nz, 1 << 20))
    while True:
        out = np.empty((cap, 3), dtype=np.int64)
        out_d = np.empty(cap)
        n = _cells_kernel(s_max, float(c[0]), float(c[1]), float(c[2]), e_all, r_max, index.tanh, index.reach,
                          _REACH_BIN, n_re, n_ra, index.tan_lo, index.tan_hi, cs, fld.cell_z, fld.nz, fld.z_min,
                          fld.z_max - fld.z_min, shift, ix_lo, ix_hi, iy_lo, iy_hi, out, out_d)
        if n <= cap:
            return out[:n], out_d[:n]
        cap = n


@dataclass(frozen=True)
class _Options:
    reflectivity: float
    sensor: PulseSensor
    intensity_model: IntensityModel
    noise_floor: float | None
    keep_tolerance: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.reflectivity) and 0.0 <= self.reflectivity <= 1.0):
            raise ValueError(f"reflectivity = {self.reflectivity!r}; expected a value in [0, 1]")
        if self.noise_floor is not None and not (math.isfinite(self.noise_floor) and self.noise_floor >= 0.0):
            raise ValueError(f"noise_floor = {self.noise_floor!r}; expected None or a value >= 0 (0..255 scale)")
        if not (math.isfinite(self.keep_tolerance) and self.keep_tolerance >= 0.0):
            raise ValueError(f"keep_tolerance = {self.keep_tolerance!r}; expected a distance >= 0 m")


def _respond(beams: Beams, hits: tuple, edges: F64, alphas: F64, opt: _Options) -> tuple:
    """Run the response kernel; returns (state, range, intensity_255, dominant hit, ratios)."""
    h_beam, h_pid, h_s, h_u1, h_u2, h_a = hits
    n = len(beams)
    hit_off = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(h_beam, minlength=n), out=hit_off[1:])
    tau_edges = np.concatenate([[0.0], np.cumsum(alphas * np.diff(edges))])
    ratios = np.zeros(len(h_beam))
    state = np.empty(n, dtype=np.uint8)
    rng = np.empty(n)
    inten = np.empty(n)
    dom = np.empty(n, dtype=np.int64)
    model = opt.intensity_model
    n_sampled = _response_kernel(
        hit_off, h_s, h_u1, h_u2, h_a, ratios, beams.has_return, beams.lengths.astype(np.float64),
        beams.intensity0.astype(np.float64), opt.sensor.pulse_length, opt.sensor.r1, opt.sensor.r2,
        model.scale * opt.reflectivity, model.r_ref, model.falloff, edges, alphas, tau_edges, opt.keep_tolerance,
        -1.0 if opt.noise_floor is None else float(opt.noise_floor), opt.sensor.saturation, SAMPLE_GRID,
        state, rng, inten, dom)
    return state, rng, inten, dom, ratios, int(n_sampled)


def _assemble(beams: Beams, points: NDArray[np.float32], T_global_out: F64, intensity_max: float, hits: tuple,
              response: tuple, stats: dict) -> ParticleResult:
    """Output points, labels and ids from the per-beam outcome."""
    state, rng, inten, dom, ratios, n_sampled = response
    stats["beams_sampled_occlusion"] = n_sampled
    h_beam, h_pid, h_s, h_u1, h_u2, h_a = hits
    n_in = len(points)
    T_out_global = np.linalg.inv(T_global_out)

    ret = np.flatnonzero(beams.has_return)
    pidx = beams.point_index[ret]
    input_labels = np.zeros(n_in, dtype=np.uint8)
    out = points.copy()
    pid_in = np.full(n_in, -1, dtype=np.int64)

    st = state[ret]
    keep_pos = st == 1
    rows = pidx[keep_pos]
    new_i = (inten[ret][keep_pos] * (intensity_max / 255.0)).astype(np.float32)
    out[rows, 3] = new_i
    input_labels[rows] = np.where(new_i == points[rows, 3], ParticleLabel.UNCHANGED, ParticleLabel.ATTENUATED)
    scat = st == 2
    b_sc = ret[scat]
    rows = pidx[scat]
    p_g = beams.origins[b_sc] + beams.directions[b_sc] * rng[b_sc, None]
    out[rows, :3] = (p_g @ T_out_global[:3, :3].T + T_out_global[:3, 3]).astype(np.float32)
    out[rows, 3] = (inten[b_sc] * (intensity_max / 255.0)).astype(np.float32)
    input_labels[rows] = ParticleLabel.SCATTERED
    pid_in[rows] = h_pid[dom[b_sc]]
    input_labels[pidx[st == 3]] = ParticleLabel.LOST

    kept = np.flatnonzero(input_labels != ParticleLabel.LOST)
    clutter = np.flatnonzero(~beams.has_return & (state == 2))
    p_c = beams.origins[clutter] + beams.directions[clutter] * rng[clutter, None]
    c_pts = np.empty((len(clutter), 5), dtype=np.float32)
    c_pts[:, :3] = p_c @ T_out_global[:3, :3].T + T_out_global[:3, 3]
    c_pts[:, 3] = (inten[clutter] * (intensity_max / 255.0)).astype(np.float32)
    c_pts[:, 4] = beams.ring[clutter]

    beam_of_point = np.full(n_in, -1, dtype=np.int64)
    beam_of_point[pidx] = ret
    times_in = np.where(beam_of_point >= 0, beams.times[np.maximum(beam_of_point, 0)], np.nan)
    counts = np.bincount(input_labels, minlength=len(ParticleLabel))
    beam_label = np.full(len(beams), 255, dtype=np.uint8)
    beam_label[ret] = input_labels[pidx]
    beam_label[clutter] = ParticleLabel.SCATTERED
    detected = (state != 4) & (state != 3)
    beam_range = np.where(detected, rng, np.nan)
    beam_intensity = np.where(detected, inten, 0.0)
    beam_particle = np.full(len(beams), -1, dtype=np.int64)
    sc = np.flatnonzero(state == 2)
    beam_particle[sc] = h_pid[dom[sc]]
    return ParticleResult(
        points=np.concatenate([out[kept], c_pts]),
        labels=np.concatenate([input_labels[kept], np.full(len(clutter), ParticleLabel.SCATTERED, np.uint8)]),
        particle_id=np.concatenate([pid_in[kept], h_pid[dom[clutter]]]),
        source_index=np.concatenate([kept.astype(np.int64), np.full(len(clutter), -1, dtype=np.int64)]),
        times=np.concatenate([times_in[kept], beams.times[clutter]]),
        input_labels=input_labels,
        counts={**{label.name: int(counts[label]) for label in ParticleLabel}, "CLUTTER": int(len(clutter))},
        intensity_max=float(intensity_max),
        hits=BeamHits(h_beam, h_pid, h_s, ratios, np.stack([h_u1, h_u2], axis=1) if len(h_u1) else np.zeros((0, 2)),
                      h_a),
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
    beam_label = np.full(len(beams), 255, dtype=np.uint8)
    beam_label[ret] = ParticleLabel.UNCHANGED
    beam_range = np.where(beams.has_return, beams.lengths, np.nan)
    beam_of_point = np.full(n, -1, dtype=np.int64)
    beam_of_point[beams.point_index[ret]] = ret
    empty_i = np.zeros(0, dtype=np.int64)
    return ParticleResult(
        points=points.copy(), labels=np.zeros(n, dtype=np.uint8), particle_id=np.full(n, -1, dtype=np.int64),
        source_index=np.arange(n, dtype=np.int64), times=times, input_labels=np.zeros(n, dtype=np.uint8),
        counts={**{label.name: 0 for label in ParticleLabel}, "UNCHANGED": n, "CLUTTER": 0},
        intensity_max=float(intensity_max),
        hits=BeamHits(empty_i, empty_i.copy(), np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros(0)),
        beam_index=beam_of_point, beam_range=beam_range,
        beam_intensity=np.where(beams.has_return, beams.intensity0, 0.0),
        beam_particle=np.full(len(beams), -1, dtype=np.int64), beam_label=beam_label, stats=stats)


def _inputs(scan: LidarScan | Beams, *, divergence: float, max_range: float, T_global_lidar: F64 | None,
            intensity_max: float | None, columns: object, reconstruct: bool) -> tuple[Beams, NDArray, F64, float]:
    """(beams, input points (N, 5) float32, output frame T_global_out, intensity scale)."""
    if isinstance(scan, LidarScan):
        beams = beams_from_scan(scan, max_range=max_range, divergence=divergence, columns=columns,
                                reconstruct=reconstruct)
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
    T_inv = np.linalg.inv(T)
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
    reflectivity: float = SNOW_REFLECTIVITY,
    divergence: float = DEFAULT_DIVERGENCE,
    sensor: PulseSensor = SNOW_SENSOR,
    intensity_model: IntensityModel = SYNTHETIC_INTENSITY,
    ratio_threshold: float | None = None,
    noise_floor: float | None = DEFAULT_NOISE_FLOOR,
    attenuation: bool = True,
    keep_tolerance: float = KEEP_TOLERANCE,
    max_range: float | None = None,
    T_global_lidar: F64 | None = None,
    intensity_max: float | None = None,
    columns: object = "auto",
    reconstruct: bool = True,
    unresolved_extinction_factor: float = 0.25,
    shell_ratio: float = SHELL_RATIO,
    first_shell: float = FIRST_SHELL,
    max_particles_per_shell: int = DEFAULT_MAX_PARTICLES,
) -> ParticleResult:
    """Snow or rain on a LiDAR scan: every beam through the one 3-D particle ``field`` (see the module docstring).

    Args:
        scan: a `LidarScan` (its beams are built with `beams_from_scan`, beams without return included) or `Beams`.
        field: the shared particle field (global coordinates); None or zero density returns the input exactly.
        reflectivity: particle reflectivity: `SNOW_REFLECTIVITY` (0.9) or `RAIN_REFLECTIVITY` (0.02).
        divergence: full beam divergence [rad] (used when ``scan`` is a `LidarScan`; `Beams` carry their own).
        sensor: pulse model (τ_H = 10 ns for the snow model), overlap ξ and saturation (0..255).
        intensity_model: how the sensor reports intensity, which calibrates particle echoes (`IntensityModel`).
        ratio_threshold: particles covering less than this share of a beam even when centred on it are folded into
            the bulk extinction instead of being materialised (0 materialises everything: feasible for thin fields).
            None: `auto_ratio_threshold` (1e-3 for snow; scaled by 0.9 / reflectivity, at most 1e-2, for darker
            particles, whose echoes are that much weaker: rain gets 1e-2).
        noise_floor: detector floor on the 0..255 scale (None: every echo is detected, no point is lost).
        attenuation: apply the bulk extinction of the unresolved particles (two-way).
        keep_tolerance: a peak within this distance [m] of a point's range keeps the point in place.
        max_range: length of beams without return [m] (default: ``sensor.max_range``).
        T_global_lidar: the output frame (default: the scan's sensor frame; identity for `Beams`).
        intensity_max: intensity scale of the output for `Beams` input (255 or 1; a scan keeps its own).
        columns, reconstruct: how beams without return are found (`beams_from_scan`).
        unresolved_extinction_factor: the unresolved particles attenuate every echo at range s by
            ``exp(-2 · factor · ∫_0^s field.unresolved_extinction(threshold) ds)``. 0.25 (default) is their
            geometric shadow counted once — exactly how a resolved particle's occlusion ratio acts on the target
            (a monostatic beam is hidden where it is shadowed) — so the result does not depend on
            ``ratio_threshold`` (measured: mean intensity change and counts stay put from 3e-4 to 3e-2); 1.0 is
            two-way Beer–Lambert with the medium's Q_ext = 2 extinction (the fog model's convention).
        shell_ratio, first_shell: geometric range shells (``[0, first, first·ratio, ...]`` [m]).
        max_particles_per_shell: refuse a shell query expecting more particles (raise ``ratio_threshold``).

    Returns:
        `ParticleResult` in the scan's frame and intensity scale.
    """
    beams, points, T_out, imax = _inputs(scan, divergence=divergence,
                                         max_range=sensor.max_range if max_range is None else max_range,
                                         T_global_lidar=T_global_lidar, intensity_max=intensity_max,
                                         columns=columns, reconstruct=reconstruct)
    opt = _Options(reflectivity, sensor, intensity_model, noise_floor, keep_tolerance)
    if ratio_threshold is None:
        ratio_threshold = auto_ratio_threshold(reflectivity)
    if not (math.isfinite(ratio_threshold) and 0.0 <= ratio_threshold < 1.0):
        raise ValueError(f"ratio_threshold = {ratio_threshold!r}; expected 0 <= ratio_threshold < 1")
    if not (math.isfinite(unresolved_extinction_factor) and unresolved_extinction_factor >= 0.0):
        raise ValueError(f"unresolved_extinction_factor = {unresolved_extinction_factor!r}; expected a value >= 0")
    if not (shell_ratio > 1.0 and first_shell > 0.0):
        raise ValueError(f"shell_ratio = {shell_ratio!r} must exceed 1 and first_shell = {first_shell!r} be > 0")
    stats: dict = {"num_beams": len(beams), "num_beams_without_return": len(beams) - beams.num_returns,
                   "ratio_threshold": float(ratio_threshold)}
    if field is None or field.number_density() <= 0.0 or len(beams) == 0:
        return _identity(beams, points, imax, stats)

    index = _index_beams(beams)
    vel = field.velocity_array
    speed = float(np.linalg.norm(vel))
    e_all = index.e_origin + speed * index.t_half
    r_max = 0.5 * field.spectrum.d_max
    reach = float(beams.lengths.max()) + e_all + r_max + 0.01
    edges = _shell_edges(reach, first_shell, shell_ratio)
    sq = math.sqrt(ratio_threshold)
    s_near = np.maximum(0.0, edges[:-1] - e_all - r_max - 0.05)
    thresholds = 2.0 * index.tanh * s_near * sq  # min diameter per shell [m]
    if attenuation:
        alphas = np.array([field.unresolved_extinction(m) for m in thresholds]) * unresolved_extinction_factor
    else:
        alphas = np.zeros(len(thresholds))
    cells, d_near = _reachable_cells(field, index, index.t_ref, float(edges[-1]), e_all, r_max)
    # each cell is materialised once, with the threshold of the shell of its nearest point (<= that of any of its
    # particles' own shell, which the hit kernel then applies per particle)
    cell_shell = np.clip(np.searchsorted(edges, d_near, side="right") - 1, 0, len(thresholds) - 1)
    order = np.argsort(cell_shell, kind="stable")
    bounds = np.searchsorted(cell_shell[order], np.arange(len(thresholds) + 1))
    buffer = _HitBuffer()
    shells = []
    for k in range(len(thresholds)):
        group = cells[order[bounds[k]:bounds[k + 1]]]
        n_part = n_hits = 0
        if len(group):
            parts = field.materialize_cells(group, index.t_ref, min_diameter=float(thresholds[k]),
                                            max_particles=max_particles_per_shell)
            n_part = len(parts)
            pos = np.ascontiguousarray(parts.positions - index.center)
            n_hits = buffer.add(index, pos, 0.5 * parts.diameters, parts.ids, vel, index.t_ref, edges, thresholds)
        shells.append({"s0": float(edges[k]), "s1": float(edges[k + 1]), "min_diameter": float(thresholds[k]),
                       "cells": int(len(group)), "particles": n_part, "hits": n_hits,
                       "unresolved_extinction": float(alphas[k])})
    hits = buffer.collect()
    response = _respond(beams, hits, edges, alphas, opt)
    stats.update({"shells": shells, "t_ref": index.t_ref, "particles": sum(s["particles"] for s in shells),
                  "origin_spread": index.e_origin})
    return _assemble(beams, points, T_out, imax, hits, response, stats)


def simulate_particle_list(
    scan: LidarScan | Beams,
    particles: Particles,
    velocity: F64 | tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    extinction: float = 0.0,
    reflectivity: float = SNOW_REFLECTIVITY,
    divergence: float = DEFAULT_DIVERGENCE,
    sensor: PulseSensor = SNOW_SENSOR,
    intensity_model: IntensityModel = SYNTHETIC_INTENSITY,
    noise_floor: float | None = DEFAULT_NOISE_FLOOR,
    keep_tolerance: float = KEEP_TOLERANCE,
    max_range: float | None = None,
    T_global_lidar: F64 | None = None,
    intensity_max: float | None = None,
    columns: object = "auto",
    reconstruct: bool = True,
) -> ParticleResult:
    """The same beam model with an explicit particle list (all resolved) and a homogeneous bulk ``extinction``
    [1/m] applied two-way (``exp(-2 α s)`` on every echo): ``particles`` (global positions at ``particles.t``) move
    with ``velocity`` (3,) [m/s]. For tests, hand-placed scenes, or particles from elsewhere; other arguments as in
    `simulate_particles`."""
    beams, points, T_out, imax = _inputs(scan, divergence=divergence,
                                         max_range=sensor.max_range if max_range is None else max_range,
                                         T_global_lidar=T_global_lidar, intensity_max=intensity_max,
                                         columns=columns, reconstruct=reconstruct)
    opt = _Options(reflectivity, sensor, intensity_model, noise_floor, keep_tolerance)
    if not (math.isfinite(extinction) and extinction >= 0.0):
        raise ValueError(f"extinction = {extinction!r}; expected a finite value >= 0 [1/m]")
    stats: dict = {"num_beams": len(beams), "num_beams_without_return": len(beams) - beams.num_returns,
                   "particles": len(particles)}
    if (len(particles) == 0 and extinction == 0.0) or len(beams) == 0:
        return _identity(beams, points, imax, stats)
    vel = np.asarray(velocity, dtype=np.float64).reshape(3)
    index = _index_beams(beams)
    buffer = _HitBuffer()
    if len(particles):
        pos = np.ascontiguousarray(np.asarray(particles.positions, dtype=np.float64) - index.center)
        buffer.add(index, pos, 0.5 * np.asarray(particles.diameters, dtype=np.float64),
                   np.asarray(particles.ids, dtype=np.int64), vel, float(particles.t), np.array([0.0, math.inf]),
                   np.zeros(1))
    hits = buffer.collect()
    response = _respond(beams, hits, np.array([0.0, 1e300]), np.array([float(extinction)]), opt)
    return _assemble(beams, points, T_out, imax, hits, response, stats)
