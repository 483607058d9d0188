"""Beam geometry set up once per scan for the snow / rain kernels: the beams in local coordinates, their time slices,
direction grid and reach map (`BeamIndex`), the reachable-cells query against a `ParticleField`, and the buffer that
collects the particle–beam hits shell by shell (`HitBuffer`).

Local coordinates: global minus `BeamIndex.center` (the centre of the beam origins' bounding box) [m].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.lidar.beams import Beams
from weatheralign.lidar.particles.kernels import cells_kernel, hits_kernel
from weatheralign.lidar.particles.records import (BeamRays, CellQuery, DirectionGrid, FieldGrid, HitArrays,
                                                  ParticleBatch, ReachMap, Shells, TimeSlices)
from weatheralign.medium.field import ParticleField

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_SLICE_BEAMS = 1024  # beams per time slice of the sweep
_MAX_SLICES = 64
_BIN = 3e-3  # angular bin [rad] of the beam-direction grid
_REACH_BIN = 0.0175  # reach-map bin: z-component of the direction, and azimuth [rad]
_SLICE_TABLE_BIN = math.radians(2.0)
_OCC_BIN = 1e-3  # sin-elevation bin of the beam-occupancy prefilter


@dataclass(frozen=True, eq=False)
class BeamIndex:
    """Beams in local coordinates (global minus ``center``) with their time slices, direction grid and reach map."""

    center: F64  # (3,) global position of the local origin [m]
    beams: BeamRays
    slices: TimeSlices
    grid: DirectionGrid
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


def index_beams(beams: Beams, t_ref: float | None = None) -> BeamIndex:
    """Slice the beams by firing time and bin each slice's beam directions on a grid of (z-component of the
    direction, azimuth) cells of ``_BIN``; also the azimuth table of the slices, the elevation occupancy and the reach
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
    sl = {k: [] for k in ("orig", "time", "e", "dt", "az0", "span", "full", "z0", "nz", "naz", "base")}
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
        z0 = float(d[idx, 2].min()) - 1e-9  # bins in the z-component (sine of the elevation)
        nz = int(math.floor((float(d[idx, 2].max()) - z0) / _BIN)) + 1
        eb = np.minimum(np.floor((d[idx, 2] - z0) / _BIN).astype(np.int64), nz - 1)
        rel = np.mod(az[idx] - az0, 2 * np.pi)
        ab = np.floor(rel / _BIN).astype(np.int64)
        ab = np.mod(ab, naz) if full else np.clip(ab, 0, naz - 1)
        flat[idx] = base + eb * naz + ab
        for key, val in (("orig", o_k), ("time", t_k), ("e", float(np.linalg.norm(o - o_k, axis=1).max())),
                         ("dt", float(np.abs(t - t_k).max())), ("az0", az0), ("span", span), ("full", full),
                         ("z0", z0), ("nz", nz), ("naz", naz), ("base", base)):
            sl[key].append(val)
        base += nz * naz
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
    return BeamIndex(
        center=center,
        beams=BeamRays(origins=origins, directions=d, e1=e1, e2=e2, times=times,
                       lengths=np.ascontiguousarray(beams.lengths, dtype=np.float64),
                       tanh=math.tan(0.5 * beams.divergence),
                       t_half=float(np.abs(times - t_ref).max()) if n else 0.0),
        slices=TimeSlices(orig=np.ascontiguousarray(np.array(sl["orig"]).reshape(-1, 3)), time=np.array(sl["time"]),
                          e=np.array(sl["e"]), dt=np.array(sl["dt"]), az0=np.array(sl["az0"]),
                          span=np.array(sl["span"]), full=np.array(sl["full"], dtype=bool), z0=np.array(sl["z0"]),
                          nz=np.array(sl["nz"], dtype=np.int64), naz=np.array(sl["naz"], dtype=np.int64),
                          base=np.array(sl["base"], dtype=np.int64)),
        grid=DirectionGrid(d_bin=_BIN, bin_off=bin_off, bin_beams=bin_beams, d_tb=_SLICE_TABLE_BIN, tb_off=tb_off,
                           tb_slices=tb_slices, d_occ=_OCC_BIN, occ_cum=occ_cum),
        reach=ReachMap(reach=reach, d_reach=_REACH_BIN,
                       tan_lo=float(np.clip(np.tan(el.min()), -1e3, 1e3)) if n else 0.0,
                       tan_hi=float(np.clip(np.tan(el.max()), -1e3, 1e3)) if n else 0.0),
        t_ref=float(t_ref),
        e_origin=float(np.linalg.norm(origins, axis=1).max()) if n else 0.0)


class HitBuffer:
    """Growable hit arrays filled shell by shell."""

    def __init__(self) -> None:
        self.parts: list[HitArrays] = []

    def add(self, index: BeamIndex, batch: ParticleBatch, shells: Shells) -> int:
        """Match ``batch`` against every beam of ``index`` (`hits_kernel`); returns the number of hits added."""
        if len(batch.pos) == 0:
            return 0
        e_all = index.e_origin + float(np.linalg.norm(batch.vel)) * index.beams.t_half
        cap = max(4096, len(batch.pos) // 8)
        while True:
            out = HitArrays(np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap), np.empty(cap),
                            np.empty(cap), np.empty(cap))
            n = hits_kernel(batch, shells, index.beams, e_all, index.slices, index.grid, out)
            if n <= cap:
                break
            cap = n
        self.parts.append(HitArrays(*(a[:n].copy() for a in out)))
        return n

    def collect(self) -> HitArrays:
        """All hits so far, sorted by beam, then range."""
        if not self.parts:
            return HitArrays(np.zeros(0, np.int64), np.zeros(0, np.int64), *(np.zeros(0) for _ in range(4)))
        cols = HitArrays(*(np.concatenate(col) for col in zip(*self.parts)))
        order = np.lexsort((cols.s, cols.beam))
        return HitArrays(*(c[order] for c in cols))


# ============================================================================================== field queries


def shell_edges(reach: float, first: float, ratio: float) -> F64:
    """Range-shell edges ``[0, first, first·ratio, ...]`` up to and including ``reach`` [m]."""
    edges = [0.0, first]
    while edges[-1] < reach:
        edges.append(edges[-1] * ratio)
    return np.array(edges)


def reachable_cells(fld: ParticleField, index: BeamIndex, t_ref: float, s_max: float, e_all: float,
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
    query = CellQuery(s_max, float(c[0]), float(c[1]), float(c[2]), e_all, r_max, index.beams.tanh)
    grid = FieldGrid(cs, fld.cell_z, fld.nz, fld.z_min, fld.z_max - fld.z_min, shift, ix_lo, ix_hi, iy_lo, iy_hi)
    cap = int(min((ix_hi - ix_lo + 1) * (iy_hi - iy_lo + 1) * fld.nz, 1 << 20))
    while True:
        out = np.empty((cap, 3), dtype=np.int64)
        out_d = np.empty(cap)
        n = cells_kernel(query, index.reach, grid, out, out_d)
        if n <= cap:
            return out[:n], out_d[:n]
        cap = n
