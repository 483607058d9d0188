"""Numba kernels of the snow / rain model (serial, ``nogil``; see `weatheralign.lidar.particles` for the physics).

The kernels take typed records (`weatheralign.lidar.particles.records`): `cells_kernel` finds the field cells that
some beam can reach, `hits_kernel` matches particles to beams, `response_kernel` turns each beam's hits into its
outcome (a `WeatherLabel`, range and intensity). Each kernel binds the record fields it uses to local names once at
the top: LLVM then keeps them in registers in the hot loops (attribute access inside the loops measured ~2 % slower).
Small helpers are inlined into the kernels (``inline="always"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from weatheralign.lidar.labels import WeatherLabel


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
def cells_kernel(query, reach_map, grid, out, out_d):  # pragma: no cover
    """Co-moving cells (M, 3) holding particles that some beam can reach, with the distance [m] of each cell's
    nearest point from the sensor centre (``out_d``); written into ``out`` (capacity rows, int64) and ``out_d``
    (capacity,), returns the count (may exceed the capacity).

    ``query`` (`CellQuery`): the query radius ``s_max`` around the sensor centre (cx, cy, cz), ``e_all`` (origin
    spread + particle motion [m]), the largest particle radius and the beams' ``tanh``. ``reach_map`` (`ReachMap`):
    the longest beam per direction bin (z-component x azimuth); a cell is kept if a direction bin within its angular
    radius (widened by ``e_all``, the beam and the particle radius) holds a beam reaching its nearest possible axial
    distance; cells outside the elevation band ``[atan(tan_lo), atan(tan_hi)]`` of all beams are skipped first.
    ``grid`` (`FieldGrid`): a cell's world box at the query time is ``x in [ix cs, (ix+1) cs] + shift_x`` (same in
    y), z in ``z_min + ([iz cell_z, (iz+1) cell_z] + shift_z mod height)`` (split in two where it wraps) — the
    field's documented co-moving grid — for ``ix_lo <= ix <= ix_hi``, ``iy_lo <= iy <= iy_hi``, ``0 <= iz < nz``.
    """
    s_max, cx, cy, cz = query.s_max, query.cx, query.cy, query.cz
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
def hits_kernel(batch, shells, beams, e_all, slices, grid, out):  # pragma: no cover
    """Every (beam, particle) intersection of the particles ``batch`` (`ParticleBatch`: local positions at
    ``t_part``, radii, ids, velocity) that are resolved at their range (diameter >= ``shells.thresholds[k]`` for the
    shell ``edges[k] <= distance from the local origin < edges[k+1]``), written to ``out`` (`HitArrays` of some
    capacity, which then hold the first ones); returns the count (may exceed the capacity).

    A particle at the beam's firing time ``t_b`` is at ``pos + vel (t_b - t_part)``; it intersects beam b
    (`BeamRays`) if its axial distance ``s`` from the beam origin is in (0, length) and its distance to the axis is
    below ``s tan(θ/2) + radius``. Candidates: time slices (`TimeSlices`) from the azimuth table of the
    `DirectionGrid` (seen from the local origin, window widened by ``e_all``: the origin spread plus the particles'
    motion during the sweep [m]), then per slice the direction cells (z-component x azimuth) within the exact bound
    of the slice (its origin spread, time spread, beam and particle radius). ``out.u1``, ``out.u2``, ``out.a``: the
    particle's centre in the beam's (e1, e2) cross-section and its radius, in beam radii.
    """
    pos, radius, ids, vel, t_part = batch.pos, batch.radius, batch.ids, batch.vel, batch.t_part
    edges, thresholds = shells.edges, shells.thresholds
    b_orig, b_dir, b_e1, b_e2 = beams.origins, beams.directions, beams.e1, beams.e2
    b_time, b_len, tanh, t_half = beams.times, beams.lengths, beams.tanh, beams.t_half
    sl_orig, sl_time, sl_e, sl_dt = slices.orig, slices.time, slices.e, slices.dt
    sl_az0, sl_span, sl_full = slices.az0, slices.span, slices.full
    sl_z0, sl_nz, sl_naz, sl_base = slices.z0, slices.nz, slices.naz, slices.base
    d_bin, bin_off, bin_beams = grid.d_bin, grid.bin_off, grid.bin_beams
    d_tb, tb_off, tb_slices = grid.d_tb, grid.tb_off, grid.tb_slices
    d_occ, occ_cum = grid.d_occ, grid.occ_cum
    out_beam, out_pid, out_s, out_u1, out_u2, out_a = out.beam, out.pid, out.s, out.u1, out.u2, out.a
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
def _optical_depth(s, medium):  # pragma: no cover
    """One-way optical depth ∫_0^s α for the piecewise-constant α of ``medium`` (`Medium`: ``alphas`` (K,) on
    ``edges`` (K+1,), extended past the ends; ``tau_edges`` (K+1,) the depth at each edge)."""
    edges, alphas = medium.edges, medium.alphas
    if s <= edges[0]:
        return 0.0
    k = np.searchsorted(edges, s, side="right") - 1
    if k >= alphas.shape[0]:
        k = alphas.shape[0] - 1
    return medium.tau_edges[k] + alphas[k] * (s - edges[k])


@njit(nogil=True, cache=True, inline="always")
def _gain(r, r_ref, falloff):  # pragma: no cover
    """The sensor's range compensation ``g(R) = min(1, (r_ref / R)^falloff)`` at range ``r`` > 0 [m] (the scalar
    form of `IntensityModel.gain`)."""
    return min(1.0, (r_ref / r) ** falloff)


@njit(nogil=True, cache=True, inline="always")
def _keep_or_lost(val, floor, i0):  # pragma: no cover
    """Outcome of a return kept at its range with intensity ``val`` (clear intensity ``i0``, both 0..255): LOST if
    there is a noise ``floor`` (>= 0) and the weather pushed the return below it (a return already below it in clear
    weather was detected nevertheless and stays), else ATTENUATED."""
    return WeatherLabel.LOST if (floor >= 0.0 and val < floor and val < i0) else WeatherLabel.ATTENUATED


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
def response_kernel(hits, hit_off, beams, pulse, medium, ratio, out):  # pragma: no cover
    """Per beam: occlusion ratios of its hits (written to ``ratio`` (H,)), the summed pulse, its peak and the outcome.

    ``hits`` (`HitArrays`, sorted by beam then range; beam b's are rows ``hit_off[b]:hit_off[b+1]``, ``hit_off``
    (B+1,)), ``beams`` (`BeamTargets`), ``pulse`` (`PulseParams`), ``medium`` (`Medium`). ``out`` (`BeamOutcome`):
    ``state`` a `WeatherLabel`: UNCHANGED keep the input bit for bit, ATTENUATED keep the position with
    ``out.intensity``, SCATTERED moved to ``out.range`` (dominant hit ``out.dom``), LOST, NO_ECHO nothing detected
    (beam without return). Intensities are on the 0..255 scale. Returns the number of hits whose ratio was sampled on
    the grid.
    """
    h_s, h_u1, h_u2, h_a, h_ratio = hits.s, hits.u1, hits.u2, hits.a, ratio
    has_ret, lengths, i0 = beams.has_ret, beams.lengths, beams.i0
    pulse_len, r1, r2, part_gain = pulse.pulse_len, pulse.r1, pulse.r2, pulse.part_gain
    r_ref, falloff = pulse.r_ref, pulse.falloff
    keep_tol, floor, saturation, grid_n = pulse.keep_tol, pulse.floor, pulse.saturation, pulse.grid_n
    out_state, out_range, out_int, out_dom = out.state, out.range, out.intensity, out.dom
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
        tau_target = _optical_depth(length, medium) if ret else 0.0
        if k_hits == 0:
            if not ret:
                out_state[b] = WeatherLabel.NO_ECHO
                continue
            if tau_target == 0.0 or length <= 0.0:
                out_state[b] = WeatherLabel.UNCHANGED
                out_range[b] = length
                out_int[b] = i0[b]
                continue
            val = min(i0[b] * math.exp(-2.0 * tau_target), saturation)
            out_range[b] = length
            out_int[b] = val
            out_state[b] = _keep_or_lost(val, floor, i0[b])
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
                -2.0 * _optical_depth(s, medium))
        m = k_hits
        if ret and length > 0.0:
            g0 = _gain(length, r_ref, falloff)
            starts[m] = length
            amps[m] = i0[b] / (length * length * g0) * remaining * math.exp(-2.0 * tau_target)
            m += 1
        r_peak, p_peak = _peak(starts, amps, m, pulse_len, work_bp, work_c, work_s)
        if p_peak <= 0.0:
            if ret and remaining > 0.0:  # a zero-intensity target, no visible particle: stays at zero
                out_state[b] = WeatherLabel.ATTENUATED
                out_range[b] = length
                out_int[b] = 0.0
            else:  # fully blocked by particles too close to be seen (no overlap ξ), or nothing at all
                out_state[b] = WeatherLabel.LOST if ret else WeatherLabel.NO_ECHO
            continue
        r_meas = r_peak - 0.5 * pulse_len
        if ret and abs(r_meas - length) <= keep_tol:
            g0 = _gain(length, r_ref, falloff)
            val = min(p_peak * length * length * g0, saturation)
            out_range[b] = length
            out_int[b] = val
            out_state[b] = _keep_or_lost(val, floor, i0[b])
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
        g1 = _gain(max(r_out, 1e-9), r_ref, falloff)
        val = min(p_peak * r_out * r_out * g1, saturation)
        if dom < 0 or (floor >= 0.0 and val < floor):
            if not ret:
                out_state[b] = WeatherLabel.NO_ECHO
                continue
            # the strongest echo is a particle's but undetectable: the target's own echo decides (summed waveform
            # at the target's pulse peak), lost only if the weather pushed it below the floor
            x_t = length + 0.5 * pulse_len
            p_t = 0.0
            for j in range(m):
                x = x_t - starts[j]
                if amps[j] > 0.0 and 0.0 <= x <= pulse_len:
                    p_t += amps[j] * math.sin(math.pi * x / pulse_len) ** 2
            g0 = _gain(length, r_ref, falloff)
            val_t = min(p_t * length * length * g0, saturation)
            out_range[b] = length
            out_int[b] = val_t
            out_state[b] = _keep_or_lost(val_t, floor, i0[b])
            continue
        out_state[b] = WeatherLabel.SCATTERED
        out_range[b] = r_out
        out_int[b] = val
        out_dom[b] = h0 + dom
    return n_sampled
