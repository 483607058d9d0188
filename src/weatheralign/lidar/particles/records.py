"""Typed records passed to the numba kernels (`weatheralign.lidar.particles.kernels`).

Each record is a `typing.NamedTuple` of arrays and scalars: numba compiles them in nopython mode as typed tuples
(``cache=True`` works because the classes are importable), so a kernel takes a handful of named records instead of
dozens of positional arrays. Lengths: B beams, K time slices (`TimeSlices`) or range shells (`Shells`, `Medium`),
P particles, H hits, C direction-grid cells. Positions are local: global minus `BeamIndex.center` [m].
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
    """Consecutive beams by firing time, each slice with its own reference origin and time and its own grid of beam
    directions (z-component of the direction x azimuth from ``az0``) inside the `DirectionGrid`."""

    orig: F64  # (K, 3) reference origin: centre of the slice's beam origins [m]
    time: F64  # (K,) reference time: middle of the slice's firing times [s]
    e: F64  # (K,) largest distance of a beam origin from ``orig`` [m]
    dt: F64  # (K,) largest |firing time - time| [s]
    az0: F64  # (K,) azimuth where the slice's azimuth range starts [rad]
    span: F64  # (K,) azimuth range covered [rad]
    full: NDArray[np.bool_]  # (K,) the slice covers every azimuth (its azimuth bins wrap)
    z0: F64  # (K,) lower edge of the first z-component bin
    nz: I64  # (K,) number of z-component bins
    naz: I64  # (K,) number of azimuth bins
    base: I64  # (K,) first cell of the slice's grid in `DirectionGrid.bin_off`


class DirectionGrid(NamedTuple):
    """Where to look for beams near a direction: per-slice direction cells (CSR), the slices per azimuth bin (CSR),
    and the occupied sin-elevation bins of all beams."""

    d_bin: float  # width of a direction cell, in z-component and in azimuth [rad]
    bin_off: I64  # (C+1,) the beams of cell c are bin_beams[bin_off[c]:bin_off[c+1]]
    bin_beams: I64  # (B,) beam indices sorted by cell
    d_tb: float  # azimuth bin of the slice table [rad]
    tb_off: I64  # (T+1,) the slices reaching azimuth bin t are tb_slices[tb_off[t]:tb_off[t+1]]
    tb_slices: I64  # slice indices sorted by azimuth bin
    d_occ: float  # sin-elevation bin of the occupancy prefilter
    occ_cum: I64  # (O+1,) cumulative count of the sin-elevation bins holding a beam


class ReachMap(NamedTuple):
    """The longest beam per direction bin (z-component of the direction x azimuth) and the elevation band."""

    reach: F64  # (n_re, n_ra) longest beam length in the bin [m], -1 where the bin holds no beam
    d_reach: float  # z-component bin width; the azimuth bin is 2π / n_ra [rad]
    tan_lo: float  # tangent of the lowest beam elevation (clamped to ±1e3)
    tan_hi: float  # tangent of the highest beam elevation (clamped to ±1e3)


# ---------------------------------------------------------------------------------------------- field queries


class CellQuery(NamedTuple):
    """The sensor side of the reachable-cells query."""

    s_max: float  # query radius around the sensor centre [m]
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


class Shells(NamedTuple):
    """Range shells around the local origin with the smallest resolved diameter in each."""

    edges: F64  # (K+1,) shell edges [m]
    thresholds: F64  # (K,) minimum diameter of a resolved particle [m]


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
