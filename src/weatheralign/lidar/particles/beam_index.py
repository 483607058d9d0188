"""Beam geometry set up once per scan for the snow / rain kernels: the beams in local coordinates, their time slices,
the beams of each slice sorted for the search and the reach map (`BeamIndex`, `index_beams`); the range shells and
the reachable-cells query against a `ParticleField`; the drivers of the hit kernels (`field_hits`: the particles of
the field, generated and matched cell by cell; `list_hits`: an explicit particle list).

Local coordinates: global minus `BeamIndex.center` (the centre of the beam origins' bounding box) [m].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.lidar.beams import Beams
from weatheralign.lidar.particles.kernels import (
    cells_kernel,
    field_hits_kernel,
    hits_kernel,
    reach_kernel,
    slices_kernel,
    sort_hits_kernel,
)
from weatheralign.lidar.particles.records import (
    BeamRays,
    CellQuery,
    FieldGrid,
    FieldSource,
    HitArrays,
    ParticleBatch,
    ReachMap,
    Shells,
    Sizer,
    SliceAzimuths,
    SliceIndex,
    SweepBeams,
    TimeSlices,
)
from weatheralign.medium.field import MAX_PER_CELL, ParticleField, field_seed_key

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_SLICE_BEAMS = 1024  # beams per time slice of the sweep
_MAX_SLICES = 64
_REACH_BIN = 0.0175  # reach-map bin: z-component of the direction, and azimuth [rad]
_EL_BIN = 1e-3  # fine z-component bin of the slices' beams
_LIST_CELL = 1.0  # grid [m] that orders an explicit particle list into compact batches
_CONVEX_SPAN = math.pi - 1e-3  # a slice's azimuths within this span get a wedge [rad]
_MIN_TABLE_BINS = 180  # azimuth bins of the slice table, at least
_MAX_LUT = 1 << 16  # largest shell look-up table


@dataclass(frozen=True, eq=False)
class BeamIndex:
    """Beams in local coordinates (global minus ``center``) with their time slices, sorted beams and reach map."""

    center: F64  # (3,) global position of the local origin [m]
    beams: BeamRays
    slices: TimeSlices
    lookup: SliceIndex
    reach: ReachMap
    t_ref: float  # reference time of the particles: the median firing time [s]
    e_origin: float  # max |origin - center| [m]


def perpendicular_basis(d: F64) -> tuple[F64, F64]:
    """Two unit vectors (N, 3) completing each unit direction ``d`` (N, 3) to an orthonormal basis."""
    helper = np.zeros_like(d)
    use_z = np.abs(d[:, 2]) < 0.9
    helper[use_z, 2] = 1.0
    helper[~use_z, 0] = 1.0
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(d, e1)


def _slices(origins: F64, d: F64, e1: F64, e2: F64, az: F64, times: F64, lengths: F64, order: I64,
            bounds: I64) -> tuple[TimeSlices, F64, F64, dict]:
    """The time slices of the beams ``order[bounds[k]:bounds[k+1]]`` (`slices_kernel`; local ``origins`` (B, 3) [m],
    unit directions ``d`` (B, 3), azimuths ``az`` (B,) [rad], ``times`` (B,) [s], ``lengths`` (B,) [m]): the
    `TimeSlices`, each slice's first azimuth and azimuth span (K,) [rad], and the per-bin, per-run and sorted-beam
    arrays of the `SliceIndex` (by field name)."""
    k, n = len(bounds) - 1, len(order)
    slices = TimeSlices(orig=np.empty((k, 3)), time=np.empty(k), e=np.empty(k), dt=np.empty(k), z_lo=np.empty(k),
                        z_hi=np.empty(k), tangent=np.empty((k, 2)), wedge=np.empty((k, 5)), z0=np.empty(k),
                        n_el=np.empty(k, np.int64), el_base=np.empty(k, np.int64), beam_base=bounds,
                        run_base=np.empty(k + 1, np.int64))
    azimuths = SliceAzimuths(az0=np.empty(k), span=np.empty(k))
    beam, proj = np.empty(n, np.int64), np.empty(n)
    el_cum, run_at, run_lo, run_start = slices_kernel(SweepBeams(origins, d, az, times, order), slices, azimuths,
                                                      beam, proj, 1.0 / _EL_BIN, _CONVEX_SPAN)
    rays = np.ascontiguousarray(np.column_stack([times[beam], origins[beam], d[beam], lengths[beam], e1[beam],
                                                 e2[beam]]))
    return slices, azimuths.az0, azimuths.span, dict(el_cum=el_cum, run_at=run_at, run_lo=run_lo,
                                                     run_start=run_start, beam=beam, rays=rays, proj=proj)


def _slice_table(az0: F64, span: F64, n_bins: int) -> tuple[I64, I64]:
    """The slices (CSR ``offsets`` (n_bins+1,), ``slices``, ascending within a bin) whose azimuth range
    ``[az0, az0 + span]`` [rad] reaches each of ``n_bins`` azimuth bins over ``[-π, π)`` (one bin of margin on each
    side; a slice wider than `_CONVEX_SPAN` reaches every bin)."""
    d_tb = 2 * math.pi / n_bins
    wide = np.asarray(span) > _CONVEX_SPAN
    b0 = np.floor((az0 + math.pi) / d_tb).astype(np.int64) - 1
    b1 = np.floor((az0 + span + math.pi) / d_tb).astype(np.int64) + 1
    start = np.where(wide, 0, b0)
    count = np.where(wide, n_bins, np.minimum(b1 - b0 + 1, n_bins))  # consecutive bins, each once (mod n_bins)
    first = np.cumsum(count) - count
    slice_of = np.repeat(np.arange(len(az0), dtype=np.int64), count)
    bins = (np.repeat(start - first, count) + np.arange(int(count.sum()))) % n_bins
    offsets = np.zeros(n_bins + 1, dtype=np.int64)
    np.cumsum(np.bincount(bins, minlength=n_bins), out=offsets[1:])
    return offsets, slice_of[np.lexsort((slice_of, bins))]


def index_beams(beams: Beams, t_ref: float | None = None) -> BeamIndex:
    """Cut the beams into time slices of `_SLICE_BEAMS` (by firing time; beams fired together by azimuth), each with
    its reference origin and time, direction bounds (z-component range, azimuth wedge) and its beams sorted by run
    of fine z-component bins (`_EL_BIN`) and projection on the slice's tangent; the slices per azimuth bin; the reach
    map (longest beam per direction bin)."""
    n = len(beams)
    lo, hi = beams.origins.min(axis=0), beams.origins.max(axis=0)
    center = 0.5 * (lo + hi)
    origins = np.ascontiguousarray(beams.origins - center)
    d = np.ascontiguousarray(beams.directions, dtype=np.float64)
    e1, e2 = perpendicular_basis(d)
    times = np.ascontiguousarray(beams.times, dtype=np.float64)
    if t_ref is None:
        t_ref = float(np.median(times))
    el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
    az = np.arctan2(d[:, 1], d[:, 0])

    order = np.lexsort((az, times))  # by firing time; beams fired together: by azimuth
    n_slices = int(np.clip(n // _SLICE_BEAMS, 1, _MAX_SLICES))
    bounds = np.linspace(0, n, n_slices + 1).astype(np.int64)
    lengths = np.ascontiguousarray(beams.lengths, dtype=np.float64)
    slices, az0, span, sorted_beams = _slices(origins, d, e1, e2, az, times, lengths, order, bounds)
    e_origin = float(np.linalg.norm(origins, axis=1).max()) if n else 0.0
    n_tb = max(_MIN_TABLE_BINS, 4 * n_slices)
    tb_off, tb_slices = _slice_table(az0, span, n_tb)
    n_re, n_ra = int(math.ceil(2.0 / _REACH_BIN)) + 1, int(round(2 * math.pi / _REACH_BIN))
    reach = np.full((n_re, n_ra), -1.0)
    re_b = np.clip(np.floor((d[:, 2] + 1.0) / _REACH_BIN).astype(np.int64), 0, n_re - 1)
    ra_b = np.mod(np.floor((az + np.pi) / _REACH_BIN).astype(np.int64), n_ra)
    reach_kernel(reach, re_b, ra_b, lengths)
    return BeamIndex(
        center=center,
        beams=BeamRays(origins=origins, directions=d, e1=e1, e2=e2, times=times, lengths=lengths,
                       tanh=math.tan(0.5 * beams.divergence),
                       t_half=float(np.abs(times - t_ref).max()) if n else 0.0),
        slices=slices,
        lookup=SliceIndex(e_origin=e_origin, d_tb=2 * math.pi / n_tb, tb_off=tb_off, tb_slices=tb_slices,
                          inv_d_el=1.0 / _EL_BIN, **sorted_beams),
        reach=ReachMap(reach=reach, d_reach=_REACH_BIN,
                       tan_lo=float(np.clip(np.tan(el.min()), -1e3, 1e3)) if n else 0.0,
                       tan_hi=float(np.clip(np.tan(el.max()), -1e3, 1e3)) if n else 0.0),
        t_ref=float(t_ref),
        e_origin=e_origin)


# =================================================================================== shells and field cells


def range_shells(edges: F64, thresholds: F64) -> Shells:
    """The range shells ``edges`` (K+1,) [m] with minimum resolved diameters ``thresholds`` (K,) [m] and their
    look-up table (bins of half the narrowest finite shell, at most `_MAX_LUT` of them)."""
    edges = np.ascontiguousarray(edges, dtype=np.float64)
    widths = np.diff(edges[np.isfinite(edges)])
    top = float(edges[np.isfinite(edges)].max()) if np.isfinite(edges).any() else 0.0
    w = 0.5 * float(widths.min()) if len(widths) and widths.min() > 0.0 else math.inf
    n_lut = int(min(_MAX_LUT, math.floor(top / w) + 2)) if math.isfinite(w) else 1
    inv_w = (n_lut - 1) / top if n_lut > 1 and top > 0.0 else 0.0
    lut = np.searchsorted(edges, np.arange(n_lut) / inv_w if inv_w > 0.0 else np.zeros(1), side="right") - 1
    return Shells(edges=edges, thresholds=np.ascontiguousarray(thresholds, dtype=np.float64), inv_w=inv_w,
                  lut=lut.astype(np.int64))


def shell_edges(reach: float, first: float, ratio: float) -> F64:
    """Range-shell edges ``[0, first, first·ratio, ...]`` up to and including ``reach`` [m]."""
    edges = [0.0, first]
    while edges[-1] < reach:
        edges.append(edges[-1] * ratio)
    return np.array(edges)


def reachable_cells(fld: ParticleField, index: BeamIndex, t_ref: float, s_max: float, e_all: float,
                    r_max: float, s_cut: float | None = None) -> tuple[I64, F64]:
    """Co-moving cells (M, 3) of ``fld`` holding particles within ``s_max`` of the sensor centre at ``t_ref`` that some
    beam can reach, and the distance (M,) [m] of each cell's nearest point from the centre; only those nearer than
    ``s_cut`` (default ``s_max``; the others' order and distances are unchanged)."""
    s_cut = s_max if s_cut is None else min(s_cut, s_max)
    shift = fld.velocity_array * (t_ref - fld.t_ref)
    c = index.center
    cs = fld.cell_size
    ix_lo = math.floor((c[0] - s_cut - shift[0]) / cs) - 1
    ix_hi = math.floor((c[0] + s_cut - shift[0]) / cs) + 1
    iy_lo = math.floor((c[1] - s_cut - shift[1]) / cs) - 1
    iy_hi = math.floor((c[1] + s_cut - shift[1]) / cs) + 1
    query = CellQuery(s_max, s_cut, float(c[0]), float(c[1]), float(c[2]), e_all, r_max, index.beams.tanh)
    grid = FieldGrid(cs, fld.cell_z, fld.nz, fld.z_min, fld.z_max - fld.z_min, shift, ix_lo, ix_hi, iy_lo, iy_hi)
    cap = int(min((ix_hi - ix_lo + 1) * (iy_hi - iy_lo + 1) * fld.nz, 1 << 20))
    while True:
        out = np.empty((cap, 3), dtype=np.int64)
        out_d = np.empty(cap)
        n = cells_kernel(query, index.reach, grid, out, out_d)
        if n <= cap:
            return out[:n], out_d[:n]
        cap = n


def _sizer(fld: ParticleField) -> Sizer:
    """The diameter of a particle of ``fld`` from its rank variable (`weatheralign.medium.field`)."""
    spec = fld.spectrum
    return Sizer(lam=spec.lam, exp_lam_dmax=math.exp(-spec.lam * spec.d_max),
                 scale=spec.n0 * fld.cell_volume / spec.lam, d_max=spec.d_max)


def rank_cutoffs(fld: ParticleField, min_diameters: F64) -> tuple[F64, F64]:
    """Per minimum diameter (K,) [m]: the smallest diameter a query materialises (the field's floor) and the rank
    cut-off (the expected count per cell of particles at least that large): a cell holds particle j iff its
    ``E_j <= cut-off``, so a negative cut-off means no particle at all (`ParticleField.materialize_cells`)."""
    sizer = _sizer(fld)
    floors = np.array([fld._floor(m) for m in min_diameters])
    return floors, np.array([sizer.scale * (math.exp(-sizer.lam * m) - sizer.exp_lam_dmax) for m in floors])


# ============================================================================================== hits


def _run_hits(kernel, cap: int, *args) -> tuple[HitArrays, tuple]:
    """Run a hit ``kernel`` (its last argument the `HitArrays` output, its first return value the hit count) with
    room for ``cap`` hits, again with room for all if they did not fit; the hits sorted by beam, then range (stable:
    `sort_hits_kernel`), and the kernel's other return values."""
    while True:
        out = HitArrays(np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap), np.empty(cap),
                        np.empty(cap), np.empty(cap))
        ret = kernel(*args, out)
        n, rest = (ret[0], ret[1:]) if isinstance(ret, tuple) else (ret, ())
        if n <= cap:
            break
        cap = n
    sorted_hits = HitArrays(*(np.empty(n, a.dtype) for a in out))
    sort_hits_kernel(out, n, int(out.beam[:n].max()) + 1 if n else 0, sorted_hits)
    return sorted_hits, rest


def empty_hits() -> HitArrays:
    """No hits."""
    return HitArrays(np.zeros(0, np.int64), np.zeros(0, np.int64), *(np.zeros(0) for _ in range(4)))


def list_hits(index: BeamIndex, batch: ParticleBatch, shells: Shells) -> HitArrays:
    """The hits of the explicit particles ``batch`` on every beam of ``index`` (`hits_kernel`), sorted by beam, then
    range."""
    if len(batch.pos) == 0:
        return empty_hits()
    cell = np.floor(batch.pos / _LIST_CELL).astype(np.int64)  # consecutive particles close together
    order = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0]))
    hits, _ = _run_hits(hits_kernel, max(4096, len(batch.pos) // 8), batch, order, shells, index.beams,
                        index.slices, index.lookup)
    return hits


def field_hits(fld: ParticleField, index: BeamIndex, cells: I64, shell_off: I64, shells: Shells,
               max_particles: int) -> tuple[HitArrays, I64]:
    """The hits of the particles of ``fld`` in the co-moving ``cells`` (M, 3), grouped by shell (the cells of shell
    k are rows ``shell_off[k]:shell_off[k+1]``, materialised with ``min_diameter = shells.thresholds[k]``, exactly
    as `ParticleField.materialize_cells` would at ``index.t_ref``), on every beam of ``index``
    (`field_hits_kernel`: generated and matched cell by cell, never stored), sorted by beam, then range; and the
    particles and hits per shell (K, 2).

    Raises:
        ValueError: a shell expects or holds more than ``max_particles`` particles, or a cell more than the field's
            rank bits allow (as `ParticleField.materialize_cells`).
    """
    floors, c_max = rank_cutoffs(fld, shells.thresholds)
    n_cells = np.diff(shell_off)
    for k in np.flatnonzero(n_cells):
        fld._check_cells(cells[shell_off[k]:shell_off[k + 1]])
        if c_max[k] * n_cells[k] > max_particles:
            raise ValueError(f"query expects {c_max[k] * n_cells[k]:.3g} particles in its cells (> max_particles = "
                             f"{max_particles}): raise min_diameter (now {floors[k]} m) or shrink the region")
    vel = fld.velocity_array
    # a particle of shell k whose rank variable exceeds the cut-off of a slightly smaller diameter is certainly below
    # the shell's threshold (the margin covers the rounding of its diameter; the kernel decides the others exactly)
    _, e_cut = rank_cutoffs(fld, shells.thresholds * (1.0 - 1e-6))
    src = FieldSource(seed_key=field_seed_key(fld.seed), cells=np.ascontiguousarray(cells, dtype=np.int64),
                      shell_off=np.ascontiguousarray(shell_off, dtype=np.int64), c_max=c_max, e_cut=e_cut,
                      cut_pad=np.concatenate([e_cut, np.full(4, -np.inf)]),
                      edge_pad=np.concatenate([shells.edges, np.full(4, np.inf)]),
                      d_floor=floors, cell_size=fld.cell_size, cell_z=fld.cell_z, z_min=fld.z_min,
                      height=fld.z_max - fld.z_min, shift=fld._shift(index.t_ref), center=index.center,
                      sizer=_sizer(fld),
                      max_particles=int(max_particles))
    per_shell = np.zeros((len(n_cells), 2), dtype=np.int64)
    cap = max(4096, int(np.dot(c_max, n_cells)) // 8)
    hits, (status,) = _run_hits(field_hits_kernel, cap, src, index.t_ref, vel, shells, index.beams, index.slices,
                                index.lookup, per_shell)
    if status > 0:
        raise ValueError(f"shell {status - 1} holds more than max_particles = {max_particles} particles in its cells")
    if status < 0:
        raise ValueError(f"a cell exceeds {MAX_PER_CELL} particles: use a smaller cell_size")
    return hits, per_shell
