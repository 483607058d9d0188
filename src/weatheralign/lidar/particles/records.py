"""Typed records passed to the numba kernels (`weatheralign.lidar.particles.kernels`, `.response`).

Each record is a `typing.NamedTuple` of arrays and scalars: numba compiles them in nopython mode as typed tuples
(``cache=True`` works because the classes are importable), so a kernel takes a handful of named records instead of
dozens of positional arrays. Lengths: B beams, K time slices (`TimeSlices`) or range shells (`Shells`, `Medium`),
P particles, H hits, R runs of fine z-component bins. Positions are local: global minus `BeamIndex.center` [m].
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# ---------------------------------------------------------------------------------------------- beams and index


class BeamRays(NamedTuple):
    """The beams as cones in local coordinates."""

    origins: F64  # (B, 3) beam origin at its firing time [m]
    directions: F64  # (B, 3) unit axis
    e1: F64  # (B, 3) unit vector perpendicular to the axis
    e2: F64  # (B, 3) unit vector completing (direction, e1, e2) to an orthonormal basis
    times: F64  # (B,) firing time [s]
    lengths: F64  # (B,) measured range, or the maximum range for beams without return [m]
    tanh: float  # tan(θ/2), θ the full beam divergence: the cone's radius at axial distance s is s tanh
    t_half: float  # max |times - t_ref| [s]


class TimeSlices(NamedTuple):
    """Consecutive beams by firing time, each slice with its own reference origin and time, the bounds of its beam
    directions (z-component range, azimuth wedge) and its fine z-component bins (their beams: `SliceIndex`)."""

    orig: F64  # (K, 3) reference origin: centre of the slice's beam origins [m]
    time: F64  # (K,) reference time: middle of the slice's firing times [s]
    e: F64  # (K,) largest distance of a beam origin from ``orig`` [m]
    dt: F64  # (K,) largest |firing time - time| [s]
    z_lo: F64  # (K,) smallest z-component of the slice's beam directions
    z_hi: F64  # (K,) largest z-component
    tangent: F64  # (K, 2) horizontal unit vector across the slice's middle azimuth
    wedge: F64  # (K, 5) horizontal unit normals n_lo, n_hi (x, y each) and a slack: every beam direction d of
    # the slice has d·n >= -slack for both normals (all zero where the slice's azimuths span more than π)
    z0: F64  # (K,) lower edge of the slice's first fine z-component bin
    n_el: I64  # (K,) number of fine z-component bins of the slice
    el_base: I64  # (K,) first entry of the slice's cumulative bin counts in `SliceIndex.el_cum`
    beam_base: I64  # (K+1,) the beams of slice k are rows beam_base[k]:beam_base[k+1] of `SliceIndex`
    run_base: I64  # (K+1,) the runs of slice k are runs run_base[k]:run_base[k+1] of `SliceIndex`


class SweepBeams(NamedTuple):
    """The beams as `kernels.slices_kernel` cuts them into time slices (`TimeSlices`)."""

    origins: F64  # (B, 3) local origin at the firing time [m]
    d: F64  # (B, 3) unit direction
    az: F64  # (B,) azimuth of the direction [rad]
    times: F64  # (B,) firing time [s]
    order: I64  # (B,) by firing time: the beams of slice k are order[beam_base[k]:beam_base[k+1]]


class SliceAzimuths(NamedTuple):
    """Each time slice's azimuth range (the complement of the largest gap between its beams' azimuths)."""

    az0: F64  # (K,) first azimuth [rad]
    span: F64  # (K,) azimuth span from az0 [rad]


class SliceIndex(NamedTuple):
    """Where to look for beams near a direction: the time slices per azimuth bin (seen from the local origin); per
    slice its fine z-component bins (``floor((d_z - z0[k]) inv_d_el)``) and their runs (maximal sequences of
    consecutive bins holding a beam: a ring of a spinning LiDAR); the beams sorted by slice, run and projection."""

    e_origin: float  # largest distance of a beam origin from the local origin [m]
    d_tb: float  # azimuth bin of the slice table [rad]
    tb_off: I64  # (T+1,) the slices reaching azimuth bin t are tb_slices[tb_off[t]:tb_off[t+1]]
    tb_slices: I64  # slice indices sorted by azimuth bin
    inv_d_el: float  # inverse width of a fine z-component bin
    el_cum: NDArray[np.int32]  # per slice k, (n_el[k]+1,) from el_base[k]: beams of the slice in its bins < f
    run_at: NDArray[np.int32]  # per slice k, (n_el[k]+1,) from el_base[k]: the first run not below bin f
    run_lo: NDArray[np.int32]  # (R,) first fine bin of each run of consecutive occupied bins of a slice
    run_start: NDArray[np.int32]  # (R+1,) the beams of run r are rows run_start[r]:run_start[r+1]
    beam: I64  # (B,) beam indices sorted by slice, run, then projection on the slice's tangent
    rays: F64  # (B, 14) firing time [s], local origin (x, y, z) [m], unit direction (x, y, z), length [m], e1, e2
    proj: F64  # (B,) their projection on their slice's tangent (ascending within a run)


class ReachMap(NamedTuple):
    """The longest beam per direction bin (z-component of the direction x azimuth) and the elevation band."""

    reach: F64  # (n_re, n_ra) longest beam length in the bin [m], -1 where the bin holds no beam
    d_reach: float  # z-component bin width; the azimuth bin is 2π / n_ra [rad]
    tan_lo: float  # tangent of the lowest beam elevation (clamped to ±1e3)
    tan_hi: float  # tangent of the highest beam elevation (clamped to ±1e3)


# ---------------------------------------------------------------------------------------------- field queries


class CellQuery(NamedTuple):
    """The sensor side of the reachable-cells query."""

    s_max: float  # radius around the sensor centre that the beams reach [m]
    s_cut: float  # only cells whose nearest point is closer than this to the sensor centre (<= s_max) [m]
    cx: float  # sensor centre (global) [m]
    cy: float
    cz: float
    e_all: float  # origin spread + particle motion during the sweep [m]
    r_max: float  # largest particle radius [m]
    tanh: float  # tan(θ/2) of the beams


class FieldGrid(NamedTuple):
    """The particle field's co-moving cell grid at the query time and the (x, y) cell range to scan."""

    cs: float  # horizontal cell size [m]
    cell_z: float  # vertical cell size [m]
    nz: int  # cells per column
    z_min: float  # bottom of the field's layer [m]
    height: float  # z_max - z_min [m]
    shift: F64  # (3,) grid displacement at the query time (velocity x (t - field.t_ref)) [m]
    ix_lo: int
    ix_hi: int
    iy_lo: int
    iy_hi: int


# ---------------------------------------------------------------------------------------------- particles and hits


class ParticleBatch(NamedTuple):
    """Particles to test against every beam."""

    pos: F64  # (P, 3) local centres at ``t_part`` [m]
    radius: F64  # (P,) [m]
    ids: I64  # (P,) field ids
    vel: F64  # (3,) common velocity [m/s]
    t_part: float  # time of ``pos`` [s]


class FieldSource(NamedTuple):
    """The particle field side of `kernels.field_hits_kernel`: the reachable co-moving cells grouped by range shell
    and the field's generator constants (`weatheralign.medium.field`: the same hash streams, expressions and ids as
    `ParticleField.materialize_cells`)."""

    seed_key: np.uint64  # the field's hashed seed
    cells: I64  # (M, 3) co-moving cells (ix, iy, iz), grouped by shell
    shell_off: I64  # (K+1,) the cells of shell k are rows shell_off[k]:shell_off[k+1]
    c_max: F64  # (K,) rank cut-off per shell: particle j of a cell exists iff E_j <= c_max[k]
    e_cut: F64  # (K,) a particle in shell k with E_j > e_cut[k] is below the shell's threshold (never resolved)
    cut_pad: F64  # (K+4,) e_cut followed by -inf (beyond the last shell)
    edge_pad: F64  # (K+5,) the shell edges followed by +inf
    d_floor: F64  # (K,) smallest materialised diameter per shell [m]
    cell_size: float  # horizontal cell size [m]
    cell_z: float  # vertical cell size [m]
    z_min: float  # bottom of the field's layer [m]
    height: float  # z_max - z_min [m]
    shift: F64  # (3,) world minus co-moving position at the particles' time (before the z wrap) [m]
    center: F64  # (3,) global position of the local origin (`BeamIndex.center`) [m]
    sizer: Sizer  # the diameter of a particle from its rank variable
    max_particles: int  # refuse a shell holding more particles


class Sizer(NamedTuple):
    """A field particle's diameter from its rank variable E_j: ``min(max(-log(exp_lam_dmax + e / scale) / lam,
    floor), d_max)`` (`weatheralign.medium.field`; the floor is the query's)."""

    lam: float  # slope of the size spectrum [1/m]
    exp_lam_dmax: float  # exp(-lam d_max)
    scale: float  # expected count per cell above D is scale (exp(-lam D) - exp_lam_dmax)
    d_max: float  # largest diameter [m]


class Batch(NamedTuple):
    """Particles matched together (capacity P) and the scratch of `kernels._match_batch` (K time slices)."""

    pos: F64  # (3, P) local centres [m]
    r_ub: F64  # (P,) upper bound of the radius [m]
    r: F64  # (P,) the radius [m]; -1 until computed from ``e`` (field particles)
    e: F64  # (P,) rank variable E_j of a field particle
    shell: I64  # (P,) range shell of the particle
    ids: I64  # (P,) particle ids
    work: F64  # (2, P) scratch
    bins: I64  # (4, P) scratch
    cand: I64  # (2, K) scratch, second row zero


class Shells(NamedTuple):
    """Range shells around the local origin with the smallest resolved diameter in each (`beam_index.shells`)."""

    edges: F64  # (K+1,) shell edges [m]
    thresholds: F64  # (K,) minimum diameter of a resolved particle [m]
    inv_w: float  # inverse width of the bins of ``lut`` [1/m]
    lut: I64  # (L,) the shell holding the start i / inv_w of bin i (searchsorted(edges, ., "right") - 1)


class HitArrays(NamedTuple):
    """Particle–beam intersections (H rows): output of the hit kernel (capacity rows), input of the response kernel
    (sorted by beam, then range)."""

    beam: I64  # (H,) beam index
    pid: I64  # (H,) particle id
    s: F64  # (H,) axial distance of the particle centre from the beam origin [m]
    u1: F64  # (H,) centre offset along e1, in beam radii (s tanh)
    u2: F64  # (H,) centre offset along e2, in beam radii
    a: F64  # (H,) particle radius in beam radii (1e300 for a pencil beam)


# ---------------------------------------------------------------------------------------------- beam response


class BeamTargets(NamedTuple):
    """Each beam's clear measurement."""

    has_ret: NDArray[np.bool_]  # (B,) the beam has a return
    lengths: F64  # (B,) its range R_0, or the maximum range [m]
    i0: F64  # (B,) its clear intensity on the 0..255 scale
    noise_key: NDArray[np.uint64]  # (B,) each beam's detector-noise stream (`api.beam_noise_keys`); (0,) noise-free
    clear: F64  # (B,) the clear value each i0 stood for before the sensor rounded it, 0..255
    # (`weatheralign.lidar.quantum.clear_readings`: i0 itself where unrounded); (0,): every i0 as read


class PulseParams(NamedTuple):
    """Pulse, intensity calibration and detection parameters of the response kernel (0..255 intensity scale)."""

    pulse_len: float  # c τ_H [m]
    r1: float  # overlap ξ(r) ramps from 0 at r1 ...
    r2: float  # ... to 1 at r2 [m]
    part_gain: float  # scale x particle reflectivity (`IntensityModel`)
    r_ref: float  # g(R) = min(1, (r_ref / R)^falloff)
    falloff: float
    keep_tol: float  # a peak within this distance of R_0 keeps the point in place [m]
    floor: float  # detector noise floor, < 0 for none
    saturation: float
    grid_n: int  # side of the sampling grid for overlapping disks
    noise_std: float  # detector intensity noise of a new echo: std sqrt(noise_std² + (noise_rel · peak)²) (0..255)
    noise_rel: float
    range_noise: float  # range noise std of a new echo [m], clipped at ±2 σ
    min_range: float  # a new echo measured nearer than this [m] is not reported (the sensor's minimum range)
    comp_ref: float  # r_f² g(r_f) of the floor's reference range [m²]; 0: a constant floor (`DetectorFloor`): the
    # floor and noise_std are those at r_f, scaled by R² g(R) / comp_ref at an echo's noise-free reported range R


class Continuum(NamedTuple):
    """The unresolved particles' backscatter as a beam receives it (`api.unresolved_continuum`): the strongest peak
    of their smooth waveform for a beam ending at range ``L = i · step`` (entry i; longer beams take the last entry),
    in raw power units, and that peak's position on the receiver axis [m]; and the running integrals of their
    amplitude density ``a(s)`` on the cells ``[j step, (j+1) step)`` (``cum0[j] = ∫_0^{j step} a``, ``cumc``,
    ``cums`` the same of ``a cos ωs``, ``a sin ωs``, ω = 2π / (c τ_H)), from which the waveform anywhere follows.
    ``peak`` all 0: no continuum."""

    step: float  # [m]
    peak: F64  # (N,) raw peak power
    peak_r: F64  # (N,) its position on the receiver axis [m] (the measured range is this minus c τ_H / 2)
    cum0: F64  # (M+1,) running integrals on the s grid
    cumc: F64  # (M+1,)
    cums: F64  # (M+1,)


class Medium(NamedTuple):
    """Piecewise-constant bulk extinction of the unresolved particles on range shells."""

    edges: F64  # (K+1,) [m]
    alphas: F64  # (K,) extinction in each shell [1/m]
    tau_edges: F64  # (K+1,) one-way optical depth at each edge


class BeamOutcome(NamedTuple):
    """Per-beam result of the response kernel."""

    state: NDArray[np.uint8]  # (B,) `WeatherLabel` (ATTENUATED: kept in place with ``intensity``)
    range: F64  # (B,) range of the detected echo [m] (nan where none)
    intensity: F64  # (B,) its intensity on the 0..255 scale (0 where none)
    dom: I64  # (B,) hit (row of `HitArrays`) of a SCATTERED beam's dominant particle, -1 otherwise
