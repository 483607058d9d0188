"""Numba kernels of the snow / rain model that find the particle–beam intersections (serial, ``nogil``; see
`weatheralign.lidar.particles` for the physics; the per-beam response is `weatheralign.lidar.particles.response`).

The kernels take typed records (`weatheralign.lidar.particles.records`):

- `slices_kernel` and `reach_kernel` build the beam index (`beam_index.index_beams`): time slices with their
  direction bounds, the beams of each slice sorted by fine z-component bin and projection, the reach map;
- `cells_kernel` finds the field cells that some beam can reach;
- `field_hits_kernel` generates the particles of those cells (the field's own hash streams and expressions, cell by
  cell, never stored) and matches each cell's particles to the beams as one batch (`_match_batch`);
  `hits_kernel` does the same for an explicit particle list;
- `sort_hits_kernel` orders the hits by beam, then range.

A particle's candidate beams are narrowed by conservative bounds only (every bound carries a `_MARGIN`); whether it
hits is decided by the exact test (`_exact_hit`, the same expressions as ever), so the hits do not depend on the
index. The hot loops are written so that LLVM vectorises them (no branches, no gathers in the per-particle loops of
`_survivors` and of the cell generation), and the batch matcher is inlined into its callers (``inline="always"``: a
call per cell costs more than the work of a small cell far away).

The cell generation reimplements `weatheralign.medium.field` (``_fill_kernel`` and ``_count_kernel``) with its
own helpers: numba's cache does not see changes of another module, so after editing those helpers clear the cache
(``__pycache__``) — ``tests/test_particle_kernels_fast.py`` compares both.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from weatheralign.lidar.particles.records import Batch, Sizer
from weatheralign.medium.field import MAX_PER_CELL, U_RANK_BITS, cell_key, packed_cell, stream_uniform, wrap_height

_MARGIN = 1e-9
"""Relative slack [rad, or m per m of range] added to every prefilter bound (covers rounding; the exact test
decides)."""

_ANCHOR = 8
"""Every _ANCHOR-th rank of a cell gets its exact radius while the cell is generated (the next ranks' bound)."""

_LIST_BATCH = 64
"""Consecutive particles of an explicit list matched together."""


# ============================================================================================== geometry helpers


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


# ============================================================================================== beam index


@njit(nogil=True, cache=True)
def _largest_gap(az, idx):  # pragma: no cover
    """``(gap, first, last)``: the largest gap [rad] between the azimuths ``az[idx]`` (M,) [rad] on the circle and
    the azimuths just after and just before it (the range they cover runs from first to last). Linear time: between
    the smallest and the largest azimuth the largest gap is at least (hi - lo) / M, the width of M buckets, so it
    runs from the largest value of a bucket to the smallest of the next non-empty one (rounding at a bucket's edge
    can only make the gap found a smaller one, always a gap between consecutive azimuths)."""
    m = idx.shape[0]
    lo = hi = az[idx[0]]
    for i in idx:
        lo = min(lo, az[i])
        hi = max(hi, az[i])
    b_min = np.full(m, np.inf)
    b_max = np.full(m, -np.inf)
    width = (hi - lo) / m
    for i in idx:
        b = min(int((az[i] - lo) / width), m - 1) if width > 0.0 else 0
        b_min[b] = min(b_min[b], az[i])
        b_max[b] = max(b_max[b], az[i])
    gap, first, last = lo + 2.0 * math.pi - hi, lo, hi  # across ±π
    prev = b_max[0]
    for b in range(1, m):
        if b_min[b] <= b_max[b]:
            if b_min[b] - prev > gap:
                gap, first, last = b_min[b] - prev, b_min[b], prev
            prev = b_max[b]
    return gap, first, last


@njit(nogil=True, cache=True)
def slices_kernel(beams, slices, azimuths, s_beam, proj, inv_d_el, convex_span):  # pragma: no cover
    """Per time slice k (the `SweepBeams` ``order[bounds[k]:bounds[k+1]]``, ``bounds`` = ``slices.beam_base``), into
    the `TimeSlices` ``slices``: its reference origin ``orig`` (K, 3) and ``time`` (K,), their spreads ``e``, ``dt``,
    the z-component range ``z_lo``, ``z_hi``, the fine bins from ``z0`` (width ``1 / inv_d_el``; ``n_el`` of them,
    from ``el_base`` in the per-bin arrays), the ``tangent`` across its middle azimuth and the ``wedge`` (zeros if
    the span exceeds ``convex_span``), its runs of consecutive occupied bins (from ``run_base`` (K+1,)); into
    ``azimuths`` (`SliceAzimuths`) its azimuth range; its beams sorted by run, then projection on the tangent
    (``s_beam`` (B,), ``proj`` (B,)). Returns the per-bin arrays ``el_cum`` (beams of the slice in the bins below),
    ``run_at`` (first run of the slice not below the bin) and the per-run arrays ``run_lo`` (first bin),
    ``run_start`` (R+1,) (first row in the sorted beams), as in `SliceIndex`."""
    origins, d, az, times, order = beams.origins, beams.d, beams.az, beams.times, beams.order
    orig, time, e, dt, z_lo, z_hi = slices.orig, slices.time, slices.e, slices.dt, slices.z_lo, slices.z_hi
    tangent, wedge, z0, n_el, el_base = slices.tangent, slices.wedge, slices.z0, slices.n_el, slices.el_base
    bounds, run_base = slices.beam_base, slices.run_base
    az0, span = azimuths.az0, azimuths.span
    n_slices = bounds.shape[0] - 1
    total = 0
    for k in range(n_slices):
        lo_z, hi_z = 2.0, -2.0
        for jj in range(bounds[k], bounds[k + 1]):
            lo_z = min(lo_z, d[order[jj], 2])
            hi_z = max(hi_z, d[order[jj], 2])
        z_lo[k], z_hi[k] = lo_z, hi_z
        z0[k] = lo_z - 1e-9
        n_el[k] = int(math.floor((hi_z - z0[k]) * inv_d_el)) + 1
        el_base[k] = total
        total += n_el[k] + 1
    el_cum = np.zeros(total, dtype=np.int32)
    run_at = np.zeros(total, dtype=np.int32)
    run_lo = np.empty(total, dtype=np.int32)
    run_start = np.empty(total + 1, dtype=np.int32)
    n_runs = 0
    for k in range(n_slices):
        j0, j1 = bounds[k], bounds[k + 1]
        idx = order[j0:j1]
        m = j1 - j0
        for c in range(3):
            lo_c, hi_c = 1e300, -1e300
            for b in idx:
                lo_c = min(lo_c, origins[b, c])
                hi_c = max(hi_c, origins[b, c])
            orig[k, c] = 0.5 * (lo_c + hi_c)
        t_lo, t_hi = 1e300, -1e300
        for b in idx:
            t_lo = min(t_lo, times[b])
            t_hi = max(t_hi, times[b])
        time[k] = 0.5 * (t_lo + t_hi)
        e_k, dt_k = 0.0, 0.0
        for b in idx:
            ox, oy, oz = origins[b, 0] - orig[k, 0], origins[b, 1] - orig[k, 1], origins[b, 2] - orig[k, 2]
            e_k = max(e_k, math.sqrt(ox * ox + oy * oy + oz * oz))
            dt_k = max(dt_k, abs(times[b] - time[k]))
        e[k], dt[k] = e_k * (1.0 + 1e-12), dt_k
        # azimuth range: the complement of the largest gap between the azimuths (`_largest_gap`)
        gap, az0[k], az1 = _largest_gap(az, idx)
        span[k] = 2.0 * math.pi - gap
        mid = az0[k] + 0.5 * span[k]
        tangent[k, 0], tangent[k, 1] = -math.sin(mid), math.cos(mid)
        if span[k] > convex_span:
            wedge[k, :] = 0.0
        else:
            n0x, n0y, n1x, n1y = -math.sin(az0[k]), math.cos(az0[k]), math.sin(az1), -math.cos(az1)
            slack = 0.0
            for b in idx:
                slack = max(slack, -(d[b, 0] * n0x + d[b, 1] * n0y), -(d[b, 0] * n1x + d[b, 1] * n1y))
            wedge[k, 0], wedge[k, 1], wedge[k, 2], wedge[k, 3], wedge[k, 4] = n0x, n0y, n1x, n1y, slack
        # fine bins, their runs of consecutive occupied bins, the beams by run (counting sort), then by projection
        nb = n_el[k]
        base = el_base[k]
        cum = el_cum[base:base + nb + 1]
        fb = np.empty(m, dtype=np.int64)
        for i in range(m):
            fb[i] = min(int(math.floor((d[idx[i], 2] - z0[k]) * inv_d_el)), nb - 1)
            cum[fb[i] + 1] += 1
        run_base[k] = n_runs
        run_of_bin = np.full(nb, -1, dtype=np.int64)
        for f in range(nb):
            if cum[f + 1] > 0:
                if f == 0 or cum[f] == 0:  # (cum still holds the counts here)
                    run_lo[n_runs] = f
                    n_runs += 1
                run_of_bin[f] = n_runs - 1
        for f in range(nb):
            cum[f + 1] += cum[f]
        r = n_runs
        for f in range(nb, -1, -1):  # first run whose bins reach f (the slice's end if none)
            if f < nb and run_of_bin[f] >= 0:
                r = run_of_bin[f]
            run_at[base + f] = r
        for rr in range(run_base[k], n_runs):
            run_start[rr] = j0 + cum[run_lo[rr]]
        fill = run_start[run_base[k]:n_runs].copy()
        for i in range(m):
            rr = run_of_bin[fb[i]] - run_base[k]
            s_beam[fill[rr]] = idx[i]
            proj[fill[rr]] = d[idx[i], 0] * tangent[k, 0] + d[idx[i], 1] * tangent[k, 1]
            fill[rr] += 1
        for rr in range(run_base[k], n_runs):  # insertion sort by projection (a sweep's rings come nearly sorted,
            end = run_start[rr + 1] if rr + 1 < n_runs else j1  # in one order or the other)
            if proj[run_start[rr]] > proj[end - 1]:
                s_beam[run_start[rr]:end] = s_beam[run_start[rr]:end][::-1].copy()
                proj[run_start[rr]:end] = proj[run_start[rr]:end][::-1].copy()
            for jj in range(run_start[rr] + 1, end):
                b, p = s_beam[jj], proj[jj]
                q = jj
                while q > run_start[rr] and proj[q - 1] > p:
                    s_beam[q], proj[q] = s_beam[q - 1], proj[q - 1]
                    q -= 1
                s_beam[q], proj[q] = b, p
    run_base[n_slices] = n_runs
    run_start[n_runs] = bounds[n_slices]
    return el_cum, run_at, run_lo[:n_runs].copy(), run_start[:n_runs + 1].copy()


@njit(nogil=True, cache=True)
def reach_kernel(reach, re_b, ra_b, lengths):  # pragma: no cover
    """``reach[re_b[i], ra_b[i]] = max(reach[...], lengths[i])`` for every beam i (the reach map, in place)."""
    for i in range(lengths.shape[0]):
        reach[re_b[i], ra_b[i]] = max(reach[re_b[i], ra_b[i]], lengths[i])


# ============================================================================================== field cells


@njit(nogil=True, cache=True)
def cells_kernel(query, reach_map, grid, out, out_d):  # pragma: no cover
    """Co-moving cells (M, 3) holding particles that some beam can reach, with the distance [m] of each cell's
    nearest point from the sensor centre (``out_d``); written into ``out`` (capacity rows, int64) and ``out_d``
    (capacity,), returns the count (may exceed the capacity).

    ``query`` (`CellQuery`): the beams' reach ``s_max`` around the sensor centre (cx, cy, cz) and the cut-off
    ``s_cut`` of the cells' nearest points, ``e_all`` (origin
    spread + particle motion [m]), the largest particle radius and the beams' ``tanh``. ``reach_map`` (`ReachMap`):
    the longest beam per direction bin (z-component x azimuth); a cell is kept if a direction bin within its angular
    radius (widened by ``e_all``, the beam and the particle radius) holds a beam reaching its nearest possible axial
    distance; cells outside the elevation band ``[atan(tan_lo), atan(tan_hi)]`` of all beams are skipped first.
    ``grid`` (`FieldGrid`): a cell's world box at the query time is ``x in [ix cs, (ix+1) cs] + shift_x`` (same in
    y), z in ``z_min + ([iz cell_z, (iz+1) cell_z] + shift_z mod height)`` (split in two where it wraps) — the
    field's documented co-moving grid — for ``ix_lo <= ix <= ix_hi``, ``iy_lo <= iy <= iy_hi``, ``0 <= iz < nz``.
    """
    s_max, s_cut, cx, cy, cz = query.s_max, query.s_cut, query.cx, query.cy, query.cz
    e_all, r_max, tanh = query.e_all, query.r_max, query.tanh
    reach, d_reach = reach_map.reach, reach_map.d_reach
    n_re, n_ra = reach.shape[0], reach.shape[1]
    tan_lo, tan_hi = reach_map.tan_lo, reach_map.tan_hi
    cs, cell_z, nz, z_min, height, shift = grid.cs, grid.cell_z, grid.nz, grid.z_min, grid.height, grid.shift
    ix_lo, ix_hi, iy_lo, iy_hi = grid.ix_lo, grid.ix_hi, grid.iy_lo, grid.iy_hi
    n = 0
    half_xy = 0.5 * cs
    big = e_all + r_max + tanh * (s_max + e_all) + 2.0 * cs + cell_z
    d_az = _reach_az_bin(n_ra)
    b_of = np.empty(nz)  # bottom of each z cell in the layer at the query time
    for iz in range(nz):
        b = (iz * cell_z + shift[2]) % height
        b_of[iz] = 0.0 if b >= height else b
    for ix in range(ix_lo, ix_hi + 1):
        x0 = ix * cs + shift[0]
        dx_lo = max(x0 - cx, cx - (x0 + cs), 0.0)
        dx_hi = max(abs(x0 - cx), abs(x0 + cs - cx))
        for iy in range(iy_lo, iy_hi + 1):
            y0 = iy * cs + shift[1]
            dy_lo = max(y0 - cy, cy - (y0 + cs), 0.0)
            if dx_lo * dx_lo + dy_lo * dy_lo >= s_cut * s_cut:
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
                b = b_of[iz]
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
                    if dmin >= s_cut:
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


# ============================================================================================== matching


@njit(nogil=True, cache=True, inline="always")
def _exact_hit(px, py, pz, r, pid, jj, beams, rays, beam_of, vel, t_part, out, n):  # pragma: no cover
    """The exact test of the particle at local ``(px, py, pz)`` [m] (at ``t_part``, radius ``r`` [m], id ``pid``)
    against the beam ``beam_of[jj]`` of row ``jj`` of the `SliceIndex` (``rays`` (B, 14): its firing time, origin,
    direction, length, then e1, e2 of its cross-section) at its firing time, appended to ``out`` (`HitArrays`) at
    row ``n`` if it hits (counted, not written, past the capacity); returns the new row count. The expressions of
    the original hit kernel: the same ``s``, ``u1``, ``u2``, ``a`` to the bit."""
    dtb = rays[jj, 0] - t_part
    vx = px + vel[0] * dtb - rays[jj, 1]
    vy = py + vel[1] * dtb - rays[jj, 2]
    vz = pz + vel[2] * dtb - rays[jj, 3]
    s = vx * rays[jj, 4] + vy * rays[jj, 5] + vz * rays[jj, 6]
    if s <= 0.0 or s >= rays[jj, 7]:
        return n
    perp2 = vx * vx + vy * vy + vz * vz - s * s
    wb = beams.tanh * s
    lim = wb + r
    if perp2 >= lim * lim:
        return n
    if n < out.beam.shape[0]:
        b = beam_of[jj]
        out.beam[n] = b
        out.pid[n] = pid
        out.s[n] = s
        if wb > 0.0:
            out.u1[n] = (vx * rays[jj, 8] + vy * rays[jj, 9] + vz * rays[jj, 10]) / wb
            out.u2[n] = (vx * rays[jj, 11] + vy * rays[jj, 12] + vz * rays[jj, 13]) / wb
            out.a[n] = r / wb
        else:  # a pencil beam: any hit covers it
            out.u1[n] = 0.0
            out.u2[n] = 0.0
            out.a[n] = 1e300
    return n + 1


@njit(nogil=True, cache=True, inline="always")
def _slice_may_hit(k, cx, cy, cz, h, r_max, speed, slices, tanh):  # pragma: no cover
    """Whether a particle of radius <= ``r_max`` [m] within ``h`` [m] of ``(cx, cy, cz)`` (relative to the origin of
    slice ``k`` at the slice's time) can hit a beam of the slice: every hit ray passes within ``R`` of the centre,
    so the centre is within ``R`` of the slice's azimuth wedge and (seen from the origin) within ``asin(R / |c|)``
    of its z-component range."""
    rho = math.sqrt(cx * cx + cy * cy + cz * cz)
    eps = slices.e[k] + speed * slices.dt[k]
    big_r = h + tanh * (rho + h + eps) + r_max + eps + _MARGIN * (1.0 + rho)
    w = slices.wedge
    lim = -big_r - w[k, 4] * (rho + big_r)
    if cx * w[k, 0] + cy * w[k, 1] < lim or cx * w[k, 2] + cy * w[k, 3] < lim:
        return False
    if rho <= 2.0 * big_r:
        return True
    y = big_r / rho
    theta = y * (1.0 + y * y)  # >= asin(y) for y <= 0.5; a z-component changes by at most the angle
    sz = cz / rho
    return sz + theta >= slices.z_lo[k] and sz - theta <= slices.z_hi[k]


@njit(nogil=True, cache=True, inline="always")
def _candidate_slices(cx, cy, cz, h, r_max, motion, tanh, lookup, cand):  # pragma: no cover
    """The time slices (written to ``cand[0]``, their count returned; ``cand[1]`` (K,) marks them and must be zero
    on entry) that particles of radius <= ``r_max`` [m] within ``h`` [m] of the local ``(cx, cy, cz)`` [m], moving
    by at most ``motion`` [m] during the sweep, may hit: every beam origin is within ``e_origin`` of the local
    origin, so a hit beam's direction is within ``asin(R / |c|)`` of the centre's, ``R = h + e + tanh (|c| + h +
    e) + r_max`` with ``e = e_origin + motion``; the slices of the azimuth bins within that window (`_window`), or all
    of them."""
    n_slices = cand.shape[1]
    rho = math.sqrt(cx * cx + cy * cy + cz * cz)
    e = lookup.e_origin + motion
    big_r = h + e + tanh * (rho + h + e) + r_max + _MARGIN * (1.0 + rho)
    x = big_r / rho if rho > 0.0 else 1.0
    full = x >= 0.5
    if not full:
        _, ha, full = _window(x, cz / rho)
    if full:
        for k in range(n_slices):
            cand[0, k] = k
            cand[1, k] = 1
        return n_slices
    tb_off, tb_slices, d_tb = lookup.tb_off, lookup.tb_slices, lookup.d_tb
    n_tb = tb_off.shape[0] - 1
    az = math.atan2(cy, cx)
    t_lo = int(math.floor((az - ha + math.pi) / d_tb))
    t_hi = int(math.floor((az + ha + math.pi) / d_tb))
    if t_hi - t_lo + 1 >= n_tb:
        t_lo, t_hi = 0, n_tb - 1
    count = 0
    for tb in range(t_lo, t_hi + 1):
        tbm = _wrap_bin(tb, n_tb)
        for jj in range(tb_off[tbm], tb_off[tbm + 1]):
            k = tb_slices[jj]
            if cand[1, k] == 0:
                cand[1, k] = 1
                cand[0, count] = k
                count += 1
    return count


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _match_batch(batch, i0, m, sphere, floor, sizer, thresholds, beams, vel, t_part, slices, lookup, out,
                 n):  # pragma: no cover
    """Every intersection of the particles ``i0:m`` of ``batch`` (`Batch`: local centres at ``t_part``, radius
    bounds, ids; ideally close together: all within ``h`` of ``(bx, by, bz)`` [m] and of radius <= ``r_max`` [m],
    ``sphere = (bx, by, bz, h, r_max)``) with the beams, appended to ``out`` from row ``n``; returns the new row
    count. A particle whose radius is not known yet (-1) gets it from its rank variable (`Sizer` ``sizer``, diameter
    floor ``floor`` [m]) when it first reaches a beam's cone, and is dropped there if it is below the threshold of its
    shell (``thresholds`` (K,) [m]); the windows before use the radius bound.

    Candidate time slices (`TimeSlices`): those of the azimuth bins of the `SliceIndex` around the batch's bounding
    sphere (seen from the local origin: `_candidate_slices`) that the sphere can reach (`_slice_may_hit`). Per slice,
    a particle seen from the slice's origin at the slice's time as ``q`` (|q| = rk) can only hit a beam whose
    direction is within angle ``asin(x)`` of q: ``x = roff / rk``, ``roff = tanh (rk + eps) + r + eps``, ``eps`` the
    slice's origin spread plus the particle's motion over the slice's time spread (every hit ray passes within roff
    of q). `_survivors` keeps the particles within ``x (1 + x²) rk`` (>= asin(x) rk) of the slice's azimuth wedge
    whose z-component window ``±x (1 + x²)`` holds a beam of the slice (fine bins); `_match_survivors` tests their
    candidate beams.
    """
    if m <= i0:
        return n
    tanh = beams.tanh
    speed = math.sqrt(vel[0] * vel[0] + vel[1] * vel[1] + vel[2] * vel[2])
    bx, by, bz, h, r_max = sphere
    cand = batch.cand
    n_cand = _candidate_slices(bx, by, bz, h, r_max, speed * beams.t_half, tanh, lookup, cand)
    for ck in range(n_cand):
        k = cand[0, ck]
        cand[1, k] = 0
        dt = slices.time[k] - t_part
        shift = (vel[0] * dt - slices.orig[k, 0], vel[1] * dt - slices.orig[k, 1], vel[2] * dt - slices.orig[k, 2])
        if not _slice_may_hit(k, bx + shift[0], by + shift[1], bz + shift[2], h, r_max, speed, slices, tanh):
            continue
        count = _survivors(batch, i0, m, k, shift, slices.e[k] + speed * slices.dt[k], tanh, slices, lookup)
        n = _match_survivors(batch, count, k, shift, floor, sizer, thresholds, beams, vel, t_part, slices, lookup, out,
                             n)
    return n


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _survivors(batch, i0, m, k, shift, eps, tanh, slices, lookup):  # pragma: no cover
    """The particles ``i0:m`` of ``batch`` that may hit a beam of time slice ``k`` (see `_match_batch`; ``shift``:
    local position minus the slice's origin at the slice's time, ``eps`` [m]), listed in ``batch.bins[2]``; returns
    their count. Per particle (a vectorised loop) the window x (``batch.work[0]``), the range rk (``work[1]``) and the
    fine bins lo..hi of its z-component window (``bins[0]``, ``bins[1]``; hi < lo: outside the wedge; lo -1: a near
    particle, x >= 0.5, for every beam of the slice); then those inside the wedge, then those whose bins hold a beam
    (branch-free)."""
    px, py, pz, radius = batch.pos[0], batch.pos[1], batch.pos[2], batch.r_ub
    w_x, w_rk = batch.work[0], batch.work[1]
    c_lo, c_hi, surv, keep = batch.bins[0], batch.bins[1], batch.bins[2], batch.bins[3]
    sx, sy, sz_ = shift
    z0, top, eb0 = slices.z0[k], slices.n_el[k] - 1, slices.el_base[k]
    w = slices.wedge
    n0x, n0y, n1x, n1y, slack = w[k, 0], w[k, 1], w[k, 2], w[k, 3], w[k, 4]
    inv_d_el, el_cum = lookup.inv_d_el, lookup.el_cum
    for i in range(i0, m):
        qx = px[i] + sx
        qy = py[i] + sy
        qz = pz[i] + sz_
        rk = math.sqrt(qx * qx + qy * qy + qz * qz)
        inv = 1.0 / rk if rk > 0.0 else 0.0
        x = (tanh * (rk + eps) + radius[i] + eps) * inv
        near = not (x < 0.5) or rk <= 0.0
        xs = 0.0 if near else x
        delta = xs * (1.0 + xs * xs) + _MARGIN
        szq = qz * inv
        lo = min(max(int(math.floor((szq - delta - z0) * inv_d_el)), 0), top + 1)
        hi = min(max(int(math.floor((szq + delta - z0) * inv_d_el)), lo - 1), top)
        lim = -(delta + slack) * rk
        inside = (qx * n0x + qy * n0y >= lim) and (qx * n1x + qy * n1y >= lim)
        w_x[i] = x if rk > 0.0 else 1e300
        w_rk[i] = rk
        c_lo[i] = -1 if near else lo
        c_hi[i] = hi if inside else lo - 1
        keep[i] = near | (inside & (hi >= lo))
    count = 0  # the particles inside the wedge with bins (branch-free), then those whose bins hold a beam
    for i in range(i0, m):
        surv[count] = i
        count += keep[i]
    kept = count
    count = 0
    for c in range(kept):
        i = surv[c]
        lo = c_lo[i]
        go = (lo < 0) | (el_cum[eb0 + max(c_hi[i], lo) + 1] > el_cum[eb0 + max(lo, 0)])
        surv[count] = i
        count += go
    return count


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _match_survivors(batch, count, k, shift, floor, sizer, thresholds, beams, vel, t_part, slices, lookup, out,
                     n):  # pragma: no cover
    """The hits of the ``count`` particles listed by `_survivors` for time slice ``k`` appended to ``out`` from row
    ``n``; returns the new row count. Per particle: first its radius (from its rank variable, see `_match_batch`;
    dropped if below its shell's threshold); then its candidate beams: per run of its fine bins, those whose
    projection on the slice's tangent is within ``x (1 + x²)`` of q's (the projection is 1-Lipschitz; a run's beams
    are sorted by it, the first found by interpolation), for a near particle every beam of the slice; of these, those
    inside the cone ``d·q >= rk sqrt(1 - x²)`` get the exact test (`_exact_hit`) at their own firing time and
    origin."""
    px, py, pz, r_exact, e_rank, shell, ids = (batch.pos[0], batch.pos[1], batch.pos[2], batch.r, batch.e,
                                               batch.shell, batch.ids)
    w_x, w_rk, c_lo, c_hi, surv = batch.work[0], batch.work[1], batch.bins[0], batch.bins[1], batch.bins[2]
    rays, s_beam, s_a = lookup.rays, lookup.beam, lookup.proj
    run_at, run_lo, run_start = lookup.run_at, lookup.run_lo, lookup.run_start
    sx, sy, sz_ = shift
    tx, ty = slices.tangent[k, 0], slices.tangent[k, 1]
    eb0, b_lo, b_hi, r_end = slices.el_base[k], slices.beam_base[k], slices.beam_base[k + 1], slices.run_base[k + 1]
    for c in range(count):
        i = surv[c]
        r = r_exact[i]
        if r == -1.0:  # the diameter of a field particle (`weatheralign.medium.field`), then its threshold
            d = -math.log(sizer.exp_lam_dmax + e_rank[i] / sizer.scale) / sizer.lam
            r = 0.5 * min(max(d, floor), sizer.d_max)
            if 2.0 * r < thresholds[shell[i]]:
                r = -2.0
            r_exact[i] = r
        if r < 0.0:  # below its shell's threshold
            continue
        qx, qy, qz = px[i] + sx, py[i] + sy, pz[i] + sz_
        x = w_x[i]
        rk = w_rk[i]
        cthr = rk * math.sqrt(1.0 - x * x) - _MARGIN * (1.0 + rk) if x < 1.0 else -1e300
        lo = c_lo[i]
        if lo < 0:
            for jj in range(b_lo, b_hi):
                if rays[jj, 4] * qx + rays[jj, 5] * qy + rays[jj, 6] * qz >= cthr:
                    n = _exact_hit(px[i], py[i], pz[i], r, ids[i], jj, beams, rays, s_beam, vel, t_part, out, n)
            continue
        delta = x * (1.0 + x * x) + _MARGIN
        au = (qx * tx + qy * ty) / rk
        a_lo = au - delta
        a_hi = au + delta
        ru = run_at[eb0 + lo]
        hi = c_hi[i]
        while ru < r_end and run_lo[ru] <= hi:
            j0 = run_start[ru]
            j1 = run_start[ru + 1]
            ru += 1
            # first row with projection >= a_lo: interpolated (a ring's beams are about evenly spaced), then walked
            p0 = s_a[j0]
            p1 = s_a[j1 - 1]
            if a_lo > p1:
                continue
            if a_lo > p0:
                g = j0 + int((a_lo - p0) / (p1 - p0) * (j1 - 1 - j0))
                g = min(max(g, j0 + 1), j1 - 1)
                while s_a[g - 1] >= a_lo:
                    g -= 1
                while s_a[g] < a_lo:
                    g += 1
                j0 = g
            for jj in range(j0, j1):
                if s_a[jj] > a_hi:
                    break
                if rays[jj, 4] * qx + rays[jj, 5] * qy + rays[jj, 6] * qz >= cthr:
                    n = _exact_hit(px[i], py[i], pz[i], r, ids[i], jj, beams, rays, s_beam, vel, t_part, out, n)
    return n


@njit(nogil=True, cache=True)
def _bounding_sphere(batch, m):  # pragma: no cover
    """``(bx, by, bz, h, r_max)``: the centre and half diagonal [m] of the bounding box of the first ``m`` (>= 1)
    particles of ``batch`` and their largest radius bound [m]."""
    px, py, pz, radius = batch.pos[0], batch.pos[1], batch.pos[2], batch.r_ub
    lo_x, hi_x = px[0], px[0]
    lo_y, hi_y = py[0], py[0]
    lo_z, hi_z = pz[0], pz[0]
    r_max = radius[0]
    for i in range(1, m):
        lo_x = min(lo_x, px[i])
        hi_x = max(hi_x, px[i])
        lo_y = min(lo_y, py[i])
        hi_y = max(hi_y, py[i])
        lo_z = min(lo_z, pz[i])
        hi_z = max(hi_z, pz[i])
        r_max = max(r_max, radius[i])
    h = 0.5 * math.sqrt((hi_x - lo_x) ** 2 + (hi_y - lo_y) ** 2 + (hi_z - lo_z) ** 2) * (1.0 + _MARGIN) + _MARGIN
    return 0.5 * (lo_x + hi_x), 0.5 * (lo_y + hi_y), 0.5 * (lo_z + hi_z), h, r_max


@njit(nogil=True, cache=True)
def _new_batch(cap, n_slices):  # pragma: no cover
    """An empty `Batch` of capacity ``cap`` for ``n_slices`` time slices."""
    return Batch(np.empty((3, cap)), np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap, dtype=np.int64),
                 np.empty(cap, dtype=np.int64), np.empty((2, cap)), np.empty((4, cap), dtype=np.int64),
                 np.zeros((2, n_slices), dtype=np.int64))


@njit(nogil=True, cache=True, inline="always")
def _shell_of(px, py, pz, shells):  # pragma: no cover
    """The range shell (`Shells`) of the particle at local ``(px, py, pz)`` [m], -1 outside them: from the look-up
    table, corrected against the edges (``searchsorted(edges, rho, "right") - 1`` exactly)."""
    edges, lut = shells.edges, shells.lut
    n_shells = shells.thresholds.shape[0]
    rho = math.sqrt(px * px + py * py + pz * pz)
    inside = rho < edges[n_shells]  # false beyond the last shell (or for nan)
    t = rho * shells.inv_w if inside else 0.0
    shell = lut[int(t)] if t < lut.shape[0] else lut[lut.shape[0] - 1]
    while shell < n_shells - 1 and rho >= edges[shell + 1]:
        shell += 1
    while shell >= 0 and rho < edges[shell]:
        shell -= 1
    return shell if inside else -1


@njit(nogil=True, cache=True)
def hits_kernel(batch_in, order, shells, beams, slices, lookup, out):  # pragma: no cover
    """Every (beam, particle) intersection of the particles ``batch_in`` (`ParticleBatch`: local positions at
    ``t_part``, radii, ids, velocity) that are resolved at their range (diameter >= ``shells.thresholds[k]`` for the
    shell ``edges[k] <= distance from the local origin < edges[k+1]``), written to ``out`` (`HitArrays` of some
    capacity, which then hold the first ones); returns the count (may exceed the capacity). ``order`` (P,): the
    particles in an order that keeps consecutive ones close (they are matched in batches of `_LIST_BATCH`, whose
    bounding sphere decides which time slices they are tested against).

    A particle at the beam's firing time ``t_b`` is at ``pos + vel (t_b - t_part)``; it intersects beam b
    (`BeamRays`) if its axial distance ``s`` from the beam origin is in (0, length) and its distance to the axis is
    below ``s tan(θ/2) + radius`` (candidates: `_match_batch`). ``out.u1``, ``out.u2``, ``out.a``: the particle's
    centre in the beam's (e1, e2) cross-section and its radius, in beam radii.
    """
    batch = _new_batch(_LIST_BATCH, slices.orig.shape[0])
    dummy = Sizer(1.0, 0.0, 1.0, 0.0)
    thresholds = shells.thresholds
    n = 0
    m = 0
    for oi in range(order.shape[0]):
        i = order[oi]
        px, py, pz = batch_in.pos[i, 0], batch_in.pos[i, 1], batch_in.pos[i, 2]
        r = batch_in.radius[i]
        shell = _shell_of(px, py, pz, shells)
        if shell < 0 or 2.0 * r < thresholds[shell]:
            continue
        batch.pos[0, m] = px
        batch.pos[1, m] = py
        batch.pos[2, m] = pz
        batch.r_ub[m] = r
        batch.r[m] = r
        batch.shell[m] = shell
        batch.ids[m] = batch_in.ids[i]
        m += 1
        if m == _LIST_BATCH:
            n = _match_batch(batch, 0, m, _bounding_sphere(batch, m), 0.0, dummy, thresholds, beams, batch_in.vel,
                             batch_in.t_part, slices, lookup, out, n)
            m = 0
    if m == 0:
        return n
    return _match_batch(batch, 0, m, _bounding_sphere(batch, m), 0.0, dummy, thresholds, beams, batch_in.vel,
                        batch_in.t_part, slices, lookup, out, n)


# ============================================================================================== field particles


@njit(nogil=True, cache=True)
def _cell_ranks(key, c_max, floor, lam, exp_lam_dmax, scale, d_max, e_rank, r_ub):  # pragma: no cover
    """The rank variables ``E_j <= c_max`` of the cell with hash ``key`` (`weatheralign.medium.field`: the same
    stream and sums) into ``e_rank`` and an upper bound of each rank's radius [m] into ``r_ub``: the exact radius of
    every `_ANCHOR`-th rank (diameter floor ``floor`` [m]) bounds the next ones' (larger E_j, smaller diameter).
    Returns their count, -1 if it reaches the field's rank bits."""
    e = 0.0
    j = 0
    r_anchor = 0.0
    while True:
        e -= math.log(1.0 - stream_uniform(key, np.uint64(4 * j)))
        if e > c_max:
            return j
        if j + 1 >= MAX_PER_CELL:
            return -1
        if j % _ANCHOR == 0:
            r_anchor = 0.5 * min(max(-math.log(exp_lam_dmax + e / scale) / lam, floor), d_max)
        e_rank[j] = e
        r_ub[j] = r_anchor
        j += 1


@njit(nogil=True, cache=True)
def _box_shells(bx, by, bz, half_xy, half_z, edges):  # pragma: no cover
    """The range shells ``(first, last)`` (``searchsorted(edges, ., "right") - 1``) of the nearest and farthest point
    of the box of half sides ``half_xy``, ``half_xy``, ``half_z`` centred at ``(bx, by, bz)`` [m], widened to cover
    rounding: every point of the box lies in one of them."""
    near = 0.0
    far = 0.0
    for c, half in ((bx, half_xy), (by, half_xy), (bz, half_z)):
        lo = max(abs(c) - half, 0.0)
        hi = abs(c) + half
        near += lo * lo
        far += hi * hi
    near = math.sqrt(near) * (1.0 - _MARGIN) - _MARGIN
    far = math.sqrt(far) * (1.0 + _MARGIN) + _MARGIN
    return np.searchsorted(edges, near, side="right") - 1, np.searchsorted(edges, far, side="right") - 1


@njit(nogil=True, cache=True)
def field_hits_kernel(src, t_part, vel, shells, beams, slices, lookup, per_shell, out):  # pragma: no cover
    """`hits_kernel` on the particles of a field, generated cell by cell and matched cell by cell (never stored).

    ``src`` (`FieldSource`): the cells of shell k (rows ``shell_off[k]:shell_off[k+1]``) hold the particles
    ``D >= d_floor[k]`` of the field, exactly those `ParticleField.materialize_cells` returns for them at
    ``t_part`` (same hash streams and expressions, ranks in order, ids ``packed cell << 16 | rank``), moving with
    ``vel`` (3,) [m/s]. Hits go to ``out`` as in `hits_kernel`; ``per_shell`` (K, 2) int64 receives the particles
    generated and the hits found per shell. Returns ``(hits, status)``: status 0 ok, ``1 + k`` shell k holds more
    than ``src.max_particles`` particles, ``-1 - k`` a cell of shell k exceeds the rank bits.
    """
    seed_key, cells, shell_off, c_max, d_floor = src.seed_key, src.cells, src.shell_off, src.c_max, src.d_floor
    cell_size, cell_z, z_min, height, shift = src.cell_size, src.cell_z, src.z_min, src.height, src.shift
    cx, cy, cz = src.center[0], src.center[1], src.center[2]
    sizer, e_cut, thresholds = src.sizer, src.e_cut, shells.thresholds
    lam, exp_lam_dmax, scale, d_max = sizer.lam, sizer.exp_lam_dmax, sizer.scale, sizer.d_max
    edges, edge_pad, cut_pad = shells.edges, src.edge_pad, src.cut_pad
    batch = _new_batch(MAX_PER_CELL, slices.orig.shape[0])
    pos, r_ub, r_exact, e_rank, shell_of, ids = batch.pos, batch.r_ub, batch.r, batch.e, batch.shell, batch.ids
    n = 0
    for k in range(shell_off.shape[0] - 1):
        n_shell = n
        n_part = 0
        c_k = c_max[k]
        floor_k = d_floor[k]
        for ci in range(shell_off[k], shell_off[k + 1]):
            ix, iy, iz = cells[ci, 0], cells[ci, 1], cells[ci, 2]
            packed = packed_cell(ix, iy, iz)
            key = cell_key(seed_key, packed)
            id_base = np.int64(packed << U_RANK_BITS)
            # the cell's z before the wrap lies in [v_lo, v_hi]: inside the layer, the wrap is the identity and the
            # cell's box bounds its particles; else their bounding box does
            v_lo = iz * cell_z + shift[2]
            v_hi = (iz + 1) * cell_z + shift[2]
            no_wrap = v_lo > 0.0 and v_hi < height
            box_x = (ix + 0.5) * cell_size + shift[0] - cx
            box_y = (iy + 0.5) * cell_size + shift[1] - cy
            box_z = z_min + 0.5 * (v_lo + v_hi) - cz
            box_h = (0.5 * math.sqrt(2.0 * cell_size * cell_size + cell_z * cell_z) * (1.0 + _MARGIN)
                     + _MARGIN * (1.0 + abs(box_x) + abs(box_y) + abs(box_z)))
            # pass 1 (sequential): the rank variables E_j <= c_k and a radius bound per rank
            j = _cell_ranks(key, c_k, floor_k, lam, exp_lam_dmax, scale, d_max, e_rank, r_ub)
            if j < 0:
                return n, -1 - k
            if j == 0:
                continue
            # pass 2 (vectorised): positions at t_part in local coordinates, exactly as the field computes them
            if no_wrap:
                for i in range(j):
                    c = np.uint64(4 * i)
                    pos[0, i] = (ix + stream_uniform(key, c + np.uint64(1))) * cell_size + shift[0] - cx
                    pos[1, i] = (iy + stream_uniform(key, c + np.uint64(2))) * cell_size + shift[1] - cy
                    pos[2, i] = z_min + ((iz + stream_uniform(key, c + np.uint64(3))) * cell_z + shift[2]) - cz
                    ids[i] = id_base + i
            else:
                for i in range(j):
                    c = np.uint64(4 * i)
                    pos[0, i] = (ix + stream_uniform(key, c + np.uint64(1))) * cell_size + shift[0] - cx
                    pos[1, i] = (iy + stream_uniform(key, c + np.uint64(2))) * cell_size + shift[1] - cy
                    z_cell = (iz + stream_uniform(key, c + np.uint64(3))) * cell_z + shift[2]
                    pos[2, i] = z_min + wrap_height(z_cell, height) - cz
                    ids[i] = id_base + i
            # pass 3: range shells, and the particles certainly below their shell's threshold (radius -2)
            k_lo = -1
            if no_wrap:
                k_lo, k_hi = _box_shells(box_x, box_y, box_z, 0.5 * cell_size, 0.5 * cell_z, edges)
                k_lo = k_lo if k_hi - k_lo <= 3 else -1
            if k_lo >= 0:  # vectorised: at most three edges inside the cell's range
                e1, e2, e3 = edge_pad[k_lo + 1], edge_pad[k_lo + 2], edge_pad[k_lo + 3]
                c0, c1, c2, c3 = cut_pad[k_lo], cut_pad[k_lo + 1], cut_pad[k_lo + 2], cut_pad[k_lo + 3]
                for i in range(j):
                    qx, qy, qz = pos[0, i], pos[1, i], pos[2, i]
                    rho = math.sqrt(qx * qx + qy * qy + qz * qz)
                    up1, up2, up3 = rho >= e1, rho >= e2, rho >= e3
                    shell_of[i] = k_lo + up1 + up2 + up3
                    cut = c3 if up3 else (c2 if up2 else (c1 if up1 else c0))
                    r_exact[i] = -1.0 if e_rank[i] <= cut else -2.0
            else:
                for i in range(j):
                    shell = _shell_of(pos[0, i], pos[1, i], pos[2, i], shells)
                    shell_of[i] = shell
                    r_exact[i] = -1.0 if shell >= 0 and e_rank[i] <= e_cut[shell] else -2.0
            sphere = (box_x, box_y, box_z, box_h, r_ub[0]) if no_wrap else _bounding_sphere(batch, j)
            n = _match_batch(batch, 0, j, sphere, floor_k, sizer, thresholds, beams, vel, t_part, slices, lookup, out,
                             n)
            n_part += j
            if n_part > src.max_particles:
                return n, 1 + k
        per_shell[k, 0] = n_part
        per_shell[k, 1] = n - n_shell
    return n, 0


# ============================================================================================== hit order


@njit(nogil=True, cache=True)
def sort_hits_kernel(hits, n, n_beams, out):  # pragma: no cover
    """The first ``n`` rows of ``hits`` (`HitArrays`, beams < ``n_beams``) sorted by beam, then range ``s``, ties in
    their original order (``np.lexsort((s, beam))``), written to ``out`` (`HitArrays` of n rows): a counting sort by
    beam, then an insertion sort by range within each beam."""
    beam, s = hits.beam, hits.s
    start = np.zeros(n_beams + 1, dtype=np.int64)
    for i in range(n):
        start[beam[i] + 1] += 1
    for b in range(n_beams):
        start[b + 1] += start[b]
    fill = start[:n_beams].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[beam[i]]] = i
        fill[beam[i]] += 1
    for b in range(n_beams):
        for j in range(start[b] + 1, start[b + 1]):
            i = order[j]
            p = j
            while p > start[b] and s[order[p - 1]] > s[i]:
                order[p] = order[p - 1]
                p -= 1
            order[p] = i
    for j in range(n):
        i = order[j]
        out.beam[j] = hits.beam[i]
        out.pid[j] = hits.pid[i]
        out.s[j] = hits.s[i]
        out.u1[j] = hits.u1[i]
        out.u2[j] = hits.u2[i]
        out.a[j] = hits.a[i]
