"""Numba kernel of the per-beam response of the snow / rain model (serial, ``nogil``; see
`weatheralign.lidar.particles` for the physics): `response_kernel` turns each beam's particle hits into its occlusion
ratios, summed pulse and outcome (a `WeatherLabel`, range and intensity).

The ratio of a disk overlapping nearer disks is counted on a grid (`_uncovered_count`: row by row, the grid points
inside a disk form an interval, found exactly) and the pulse maximum in closed form per segment (`_peak`). Both give
the same numbers, bit for bit, as the point-by-point count and the segment-by-segment evaluation they replace.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from weatheralign.lidar.labels import WeatherLabel
from weatheralign.medium.field import normal_pair
from weatheralign.sensors import floor_factor


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
def _keep_or_lost(val, floor, i0, clear, transmission):  # pragma: no cover
    """Outcome of a return kept at its range with intensity ``val`` (clear intensity ``i0``, both 0..255): LOST if
    there is a noise ``floor`` (>= 0) and the weather pushed the return below it (a return already below it in clear
    weather was detected nevertheless and stays), else ATTENUATED. The test reads the clear value ``clear`` the
    rounded ``i0`` stood for (`weatheralign.lidar.quantum.clear_readings`; ``i0`` itself when unrounded): ``val``
    plus the difference carried by the target's ``transmission`` (`quantum.attenuated_reading`)."""
    v = val + (clear - i0) * transmission
    return WeatherLabel.LOST if (floor >= 0.0 and v < floor and v < clear) else WeatherLabel.ATTENUATED


@njit(nogil=True, cache=True, inline="always")
def _continuum_at(length, continuum):  # pragma: no cover
    """``(P, R)``: the raw peak power of the unresolved particles' waveform for a beam ending at ``length`` [m] and
    its position on the receiver axis (`Continuum`, the entry at or below ``length``)."""
    n = continuum.peak.shape[0]
    i = int(length / continuum.step) if length > 0.0 else 0
    i = min(max(i, 0), n - 1)
    return continuum.peak[i], continuum.peak_r[i]


@njit(nogil=True, cache=True, inline="always")
def _reading(val, r_out, key, noise_std, noise_rel, range_noise, saturation, length):  # pragma: no cover
    """The detector's reading of a new echo of intensity ``val`` at range ``r_out``: noise from the beam's stream
    ``key`` on both (range noise clipped at ±2 σ), clipped to ``[0, saturation]`` and ``[0, length]``."""
    z_int, z_range = normal_pair(key)
    val = min(max(val + math.sqrt(noise_std * noise_std + (noise_rel * val) ** 2) * z_int, 0.0), saturation)
    r_out = min(max(r_out + range_noise * min(max(z_range, -2.0), 2.0), 0.0), length)
    return val, r_out


@njit(nogil=True, cache=True, inline="always")
def _pulse_sum_at(x, starts, amps, m, pulse_len):  # pragma: no cover
    """The first ``m`` summed pulses at ``x`` on the receiver axis (raw power)."""
    p = 0.0
    for j in range(m):
        d = x - starts[j]
        if amps[j] > 0.0 and 0.0 <= d <= pulse_len:
            p += amps[j] * math.sin(math.pi * d / pulse_len) ** 2
    return p


@njit(nogil=True, cache=True, inline="always")
def _target_crest(starts, amps, m, length, pulse_len, r_ref, falloff, saturation):  # pragma: no cover
    """The intensity (0..255) of the target's own echo, read at its crest ``length + c τ_H / 2`` of the first ``m``
    summed pulses: the return a receiver reports when the strongest crest is undetectable."""
    g0 = _gain(length, r_ref, falloff)
    return min(_pulse_sum_at(length + 0.5 * pulse_len, starts, amps, m, pulse_len) * length * length * g0, saturation)


@njit(nogil=True, cache=True, inline="always")
def _running(cum, x, step):  # pragma: no cover
    """``cum`` (M+1,) on nodes ``j · step``, linearly interpolated at ``x`` in ``[0, M step]``."""
    u = x / step
    i = min(int(u), cum.shape[0] - 2)
    f = u - i
    return cum[i] + f * (cum[i + 1] - cum[i])


@njit(nogil=True, cache=True, inline="always")
def _continuum_wave(R, length, continuum, pulse_len):  # pragma: no cover
    """The unresolved particles' waveform at ``R`` on the receiver axis for a beam ending at ``length`` [m]:
    ``∫_{max(0, R - c τ_H)}^{min(R, length)} a(s) sin²(π (R - s) / (c τ_H)) ds`` from the running integrals of
    `Continuum` (``sin² = (1 - cos ω(R - s)) / 2``)."""
    top = (continuum.cum0.shape[0] - 1) * continuum.step
    lo = min(max(R - pulse_len, 0.0), top)
    hi = min(max(min(R, length), 0.0), top)
    if hi <= lo:
        return 0.0
    step = continuum.step
    s0 = _running(continuum.cum0, hi, step) - _running(continuum.cum0, lo, step)
    sc = _running(continuum.cumc, hi, step) - _running(continuum.cumc, lo, step)
    ss = _running(continuum.cums, hi, step) - _running(continuum.cums, lo, step)
    omega = 2.0 * math.pi / pulse_len
    return max(0.5 * s0 - 0.5 * (math.cos(omega * R) * sc + math.sin(omega * R) * ss), 0.0)


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
    last_x = math.nan  # the cos / sin of the last segment end (the next segment's start)
    last_cos = last_sin = 0.0
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
        # no value of this segment exceeds a_sum (|(c_sum, s_sum)| <= a_sum up to rounding): it cannot win
        if a_sum <= 0.0 or a_sum * (1.0 + 1e-9) < best_p:
            continue
        # f(x) = a/2 - (c cos(ωx) + s sin(ωx)) / 2 with x = R - r0
        x_lo = lo - r0
        x_hi = hi - r0
        for x in (x_lo, x_hi):
            if x == last_x:
                cos_x, sin_x = last_cos, last_sin
            else:
                cos_x, sin_x = math.cos(omega * x), math.sin(omega * x)
                last_x, last_cos, last_sin = x, cos_x, sin_x
            val = 0.5 * a_sum - 0.5 * (c_sum * cos_x + s_sum * sin_x)
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


@njit(nogil=True, cache=True, inline="always")
def _inside(y0, step, g, uy, exx, r2):  # pragma: no cover
    """Whether grid point ``g`` of a row (``y = y0 + (g + 0.5) step``) is inside the disk of squared radius ``r2``
    centred at y ``uy``, ``exx`` the squared x offset of the row: ``exx + (y - uy)² < r2``, evaluated exactly as the
    point-by-point count does."""
    ey = (y0 + (g + 0.5) * step) - uy
    return exx + ey * ey < r2


@njit(nogil=True, cache=True)
def _row_interval(y0, step, n, exx, uy, r2):  # pragma: no cover
    """The grid points ``g`` in [0, n) of a row inside a disk (`_inside`), as ``(first, last)`` (empty if last <
    first). Exact: y - uy is non-decreasing in g, so the evaluated ``exx + (y - uy)²`` does not increase before the
    first g with y - uy >= 0 (c) and does not decrease from it (rounding is monotone): the inside points are an
    interval holding c - 1 or c if any, whose ends are estimated from the circle and then walked to exactly."""
    if not exx < r2:  # no point of this row is inside
        return 0, -1
    t = 0.0
    if step > 0.0:
        t = min(max((uy - y0) / step - 0.5, -1.0), n + 1.0)
    c = min(max(int(math.ceil(t)), 0), n)
    while c > 0 and (y0 + ((c - 1) + 0.5) * step) - uy >= 0.0:
        c -= 1
    while c < n and (y0 + (c + 0.5) * step) - uy < 0.0:
        c += 1
    in_left = c > 0 and _inside(y0, step, c - 1, uy, exx, r2)
    in_right = c < n and _inside(y0, step, c, uy, exx, r2)
    if not (in_left or in_right):
        return 0, -1
    w = math.sqrt(r2 - exx) / step if step > 0.0 else 0.0
    first = c
    if in_left:  # the inside points of [0, c) are a suffix ending at c - 1
        first = min(max(int(math.ceil(max(t - w, -1.0))), 0), c - 1)
        if _inside(y0, step, first, uy, exx, r2):
            while first > 0 and _inside(y0, step, first - 1, uy, exx, r2):
                first -= 1
        else:
            while not _inside(y0, step, first, uy, exx, r2):
                first += 1
    last = c - 1
    if in_right:  # the inside points of [c, n) are a prefix starting at c
        last = min(max(int(math.floor(min(t + w, n + 1.0))), c), n - 1)
        if _inside(y0, step, last, uy, exx, r2):
            while last < n - 1 and _inside(y0, step, last + 1, uy, exx, r2):
                last += 1
        else:
            while not _inside(y0, step, last, uy, exx, r2):
                last -= 1
    return first, last


@njit(nogil=True, cache=True)
def _uncovered_count(cx, cy, a, x_lo, step_x, y_lo, step_y, grid_n, over, n_over, h_u1, h_u2, h_a, iv_lo,
                     iv_hi):  # pragma: no cover
    """The points ``(x_lo + (i + 0.5) step_x, y_lo + (j + 0.5) step_y)`` of a ``grid_n`` x ``grid_n`` grid inside
    the unit disk and the disk of radius ``a`` at ``(cx, cy)`` but in none of the disks ``over[:n_over]`` (centres
    ``h_u1``, ``h_u2``, radii ``h_a``): the same count, point for point, as testing every grid point, from the
    rows' intervals (`_row_interval`). ``iv_lo``, ``iv_hi``: scratch (>= n_over)."""
    count = 0
    a2 = a * a
    for gi in range(grid_n):
        x = x_lo + (gi + 0.5) * step_x
        lo_u, hi_u = _row_interval(y_lo, step_y, grid_n, x * x, 0.0, 1.0)
        ex = x - cx
        lo_o, hi_o = _row_interval(y_lo, step_y, grid_n, ex * ex, cy, a2)
        lo = max(lo_u, lo_o)
        hi = min(hi_u, hi_o)
        if hi < lo:
            continue
        n_iv = 0  # the covered intervals within [lo, hi], sorted by start
        for q in range(n_over):
            hq = over[q]
            ex = x - h_u1[hq]
            q_lo, q_hi = _row_interval(y_lo, step_y, grid_n, ex * ex, h_u2[hq], h_a[hq] * h_a[hq])
            q_lo = max(q_lo, lo)
            q_hi = min(q_hi, hi)
            if q_hi < q_lo:
                continue
            p = n_iv
            while p > 0 and iv_lo[p - 1] > q_lo:
                iv_lo[p] = iv_lo[p - 1]
                iv_hi[p] = iv_hi[p - 1]
                p -= 1
            iv_lo[p] = q_lo
            iv_hi[p] = q_hi
            n_iv += 1
        covered = 0
        end = lo - 1  # last covered point so far
        for p in range(n_iv):
            start = max(iv_lo[p], end + 1)
            if iv_hi[p] >= start:
                covered += iv_hi[p] - start + 1
                end = iv_hi[p]
        count += hi - lo + 1 - covered
    return count


@njit(nogil=True, cache=True)
def response_kernel(hits, hit_off, beams, pulse, medium, continuum, ratio, out):  # pragma: no cover
    """Per beam: occlusion ratios of its hits (written to ``ratio`` (H,)), the summed pulse, its peak and the outcome.

    ``hits`` (`HitArrays`, sorted by beam then range; beam b's are rows ``hit_off[b]:hit_off[b+1]``, ``hit_off``
    (B+1,)), ``beams`` (`BeamTargets`), ``pulse`` (`PulseParams`), ``medium`` (`Medium`), ``continuum``
    (`Continuum`: the unresolved particles' echo, which competes with the pulse sum's peak by its own peak and, when
    stronger, is read like a particle echo, without particle id). ``out`` (`BeamOutcome`):
    ``state`` a `WeatherLabel`: UNCHANGED keep the input bit for bit, ATTENUATED keep the position with
    ``out.intensity``, SCATTERED moved to ``out.range`` (dominant hit ``out.dom``), LOST, NO_ECHO nothing detected
    (beam without return). Intensities are on the 0..255 scale. Returns the number of hits whose ratio was sampled on
    the grid.

    A particle echo is a new measurement: the detector's noise (``pulse.noise_std``, ``noise_rel``, ``range_noise``;
    the beam's stream ``beams.noise_key``) is added to its peak and range before the floor decides whether it is
    detected; an echo measured nearer than ``pulse.min_range`` is not. A target kept at its range keeps the noise of
    its clear measurement (scaled with it) here; the reading's missing variance is added afterwards
    (`weatheralign.lidar.particles.api._read_attenuated`, which decides again on the noisy reading). Whether the
    weather pushed a kept target under the floor is decided on the clear value its rounded reading stood for
    (``beams.clear``, `_keep_or_lost`; LOST keeps the noise-free value at the target's range). Every floor test
    uses the floor at the echo's noise-free reported range (``pulse.comp_ref``: a raw-power detector's grows with
    range, `weatheralign.sensors.LidarModel.floor_range_m`), and a new echo's constant noise scales with it.
    """
    h_s, h_u1, h_u2, h_a, h_ratio = hits.s, hits.u1, hits.u2, hits.a, ratio
    has_ret, lengths, i0, clear = beams.has_ret, beams.lengths, beams.i0, beams.clear
    rounded = clear.shape[0] > 0
    pulse_len, r1, r2, part_gain = pulse.pulse_len, pulse.r1, pulse.r2, pulse.part_gain
    r_ref, falloff = pulse.r_ref, pulse.falloff
    keep_tol, floor, saturation, grid_n = pulse.keep_tol, pulse.floor, pulse.saturation, pulse.grid_n
    noise_std, noise_rel, range_noise, noise_key = pulse.noise_std, pulse.noise_rel, pulse.range_noise, beams.noise_key
    min_range, comp_ref = pulse.min_range, pulse.comp_ref
    noisy = noise_std > 0.0 or noise_rel > 0.0 or range_noise > 0.0
    out_state, out_range, out_int, out_dom = out.state, out.range, out.intensity, out.dom
    n_beams = lengths.shape[0]
    max_k = 0
    for b in range(n_beams):
        max_k = max(max_k, hit_off[b + 1] - hit_off[b])
    starts = np.empty(max_k + 1)
    amps = np.empty(max_k + 1)
    over = np.empty(max_k + 1, dtype=np.int64)
    iv_lo = np.empty(max_k + 1, dtype=np.int64)
    iv_hi = np.empty(max_k + 1, dtype=np.int64)
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
        hidden = (not ret) and i0[b] > 0.0 and length > 0.0  # a surface under the floor in clear weather
        tau_target = _optical_depth(length, medium) if (ret or hidden) else 0.0
        x0 = clear[b] if rounded else i0[b]  # the clear value the reading i0 stood for
        # the floor where the target is reported (a raw-power detector's grows with range; < 0: none)
        floor_t = floor * floor_factor(length, r_ref, falloff, comp_ref) if floor >= 0.0 else -1.0
        c_peak, c_r = _continuum_at(length, continuum)
        if c_peak > 0.0 and k_hits == 0 and (ret or hidden) and length > 0.0:  # the target beats the continuum?
            if c_peak <= i0[b] * math.exp(-2.0 * tau_target) / (length * length * _gain(length, r_ref, falloff)):
                c_peak = 0.0
        if k_hits == 0 and c_peak <= 0.0:  # no echo competes with the target's
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
            out_state[b] = _keep_or_lost(val, floor_t, i0[b], x0, math.exp(-2.0 * tau_target))
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
                    count = _uncovered_count(cx, cy, a, x_lo, step_x, y_lo, step_y, grid_n, over, n_over, h_u1,
                                             h_u2, h_a, iv_lo, iv_hi)
                    share = count * step_x * step_y / math.pi
            h_ratio[h] = share
            if math.sqrt(cx * cx + cy * cy) + 1.0 <= a:  # this particle covers the whole beam
                blocked = True
        covered = 0.0
        for j in range(k_hits):
            covered += h_ratio[h0 + j]
        remaining = max(0.0, 1.0 - covered)
        t_target = remaining * math.exp(-2.0 * tau_target)  # the share of the clear echo that comes back
        # --- pulse amplitudes in raw power units (intensity / (R² g(R)))
        for j in range(k_hits):
            h = h0 + j
            s = h_s[h]
            xi = min(max((s - r1) / (r2 - r1), 0.0), 1.0)
            starts[j] = s
            amps[j] = part_gain * h_ratio[h] * xi / (s * s) * math.exp(
                -2.0 * _optical_depth(s, medium))
        m = k_hits
        if (ret or hidden) and length > 0.0:
            g0 = _gain(length, r_ref, falloff)
            starts[m] = length
            amps[m] = i0[b] / (length * length * g0) * remaining * math.exp(-2.0 * tau_target)
            m += 1
        r_peak, p_peak = _peak(starts, amps, m, pulse_len, work_bp, work_c, work_s)
        continuum_wins = False
        if c_peak > 0.0:  # the received waveform is the pulse sum plus the unresolved particles' continuum
            if p_peak > 0.0:
                p_peak += _continuum_wave(r_peak, length, continuum, pulse_len)
            c_peak += _pulse_sum_at(c_r, starts, amps, m, pulse_len)
            continuum_wins = c_peak > p_peak
        if continuum_wins:  # the continuum's crest is the strongest: read it
            r_c = max(c_r - 0.5 * pulse_len, 1e-9)
            val = min(c_peak * r_c * r_c * _gain(r_c, r_ref, falloff), saturation)
            at_echo = floor_factor(r_c, r_ref, falloff, comp_ref)
            if noisy:
                val, r_c = _reading(val, r_c, noise_key[b], noise_std * at_echo, noise_rel, range_noise, saturation,
                                    length)
            if (floor < 0.0 or val >= floor * at_echo) and r_c >= min_range:
                out_state[b] = WeatherLabel.SCATTERED
                out_range[b] = r_c
                out_int[b] = val
                continue
            if not ret:
                out_state[b] = WeatherLabel.NO_ECHO
                continue
            if length <= 0.0:
                out_state[b] = WeatherLabel.UNCHANGED
                out_range[b] = length
                out_int[b] = i0[b]
                continue
            # undetected: the target's own echo decides (as behind an undetectable particle echo)
            val_t = _target_crest(starts, amps, m, length, pulse_len, r_ref, falloff, saturation)
            out_range[b] = length
            out_int[b] = val_t
            out_state[b] = _keep_or_lost(val_t, floor_t, i0[b], x0, t_target)
            continue
        if p_peak <= 0.0:
            if ret and remaining > 0.0:  # a zero-intensity target, no visible particle: stays at zero
                out_state[b] = WeatherLabel.ATTENUATED
                out_range[b] = length
                out_int[b] = 0.0
            else:  # fully blocked by particles too close to be seen (no overlap ξ), or nothing at all
                out_state[b] = WeatherLabel.LOST if ret else WeatherLabel.NO_ECHO
            continue
        r_meas = r_peak - 0.5 * pulse_len
        if hidden and abs(r_meas - length) <= keep_tol:  # the undetectable surface is the strongest echo
            out_state[b] = WeatherLabel.NO_ECHO
            continue
        if ret and abs(r_meas - length) <= keep_tol:
            g0 = _gain(length, r_ref, falloff)
            val = min(p_peak * length * length * g0, saturation)
            out_range[b] = length
            out_int[b] = val
            out_state[b] = _keep_or_lost(val, floor_t, i0[b], x0, t_target)
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
        at_echo = floor_factor(r_out, r_ref, falloff, comp_ref)
        if noisy and dom >= 0:  # the detector's reading of the particle echo
            val, r_out = _reading(val, r_out, noise_key[b], noise_std * at_echo, noise_rel, range_noise, saturation,
                                  length)
        if dom < 0 or (floor >= 0.0 and val < floor * at_echo) or r_out < min_range:
            if not ret:
                out_state[b] = WeatherLabel.NO_ECHO
                continue
            # the strongest echo is a particle's but undetectable: the target's own echo decides (summed waveform
            # at the target's pulse peak), lost only if the weather pushed it below the floor
            val_t = _target_crest(starts, amps, m, length, pulse_len, r_ref, falloff, saturation)
            out_range[b] = length
            out_int[b] = val_t
            out_state[b] = _keep_or_lost(val_t, floor_t, i0[b], x0, t_target)
            continue
        out_state[b] = WeatherLabel.SCATTERED
        out_range[b] = r_out
        out_int[b] = val
        out_dom[b] = h0 + dom
    return n_sampled
