"""The fast snow / rain kernels against slow references that compute the same numbers the plain way, bit for bit:

- the particles generated inside `field_hits_kernel` and the hits it finds, against `ParticleField.materialize_cells`
  and the exact test of every resolved particle against every beam (a spinning sensor that moves during its sweep,
  beams without return, random extra beams, a thin wrapping layer, wind);
- the count of a disk's uncovered grid points (`_uncovered_count`, interval per row) against testing every point;
- the pulse maximum (`_peak`, with its shortcuts) against the summed pulses sampled densely;
- the hit order (`sort_hits_kernel`) against ``np.lexsort``; the largest azimuth gap (`_largest_gap`) against
  sorting; the shell look-up (`_shell_of`) against ``np.searchsorted``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from weatheralign.lidar.beams import Beams
from weatheralign.lidar.particles.beam_index import field_hits, index_beams, range_shells, reachable_cells, shell_edges
from weatheralign.lidar.particles.kernels import _largest_gap, _shell_of, sort_hits_kernel
from weatheralign.lidar.particles.records import HitArrays
from weatheralign.lidar.particles.response import _peak, _uncovered_count
from weatheralign.medium import ExponentialSizeDistribution, ParticleField

# ------------------------------------------------------------------------------------------ field particles and hits


def _sweep(seed: int) -> Beams:
    """A 16-ring sensor turning once in 50 ms while moving at 10 m/s (returns at 2..12 m, a third without return),
    plus 60 beams in random directions at random times."""
    rng = np.random.default_rng(seed)
    rings, cols = 16, 180
    el = np.radians(np.linspace(-25.0, 8.0, rings))
    az = np.linspace(-math.pi, math.pi, cols, endpoint=False)
    e, a = np.meshgrid(el, az, indexing="ij")
    t = np.broadcast_to((a + math.pi) / (2 * math.pi) * 0.05, e.shape)
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    t = t.reshape(-1)
    d_rand = rng.normal(size=(60, 3))
    d = np.concatenate([d, d_rand / np.linalg.norm(d_rand, axis=1, keepdims=True)])
    t = np.concatenate([t, rng.uniform(0.0, 0.05, 60)]) + 100.0
    origins = np.stack([10.0 * (t - 100.0), np.zeros_like(t), np.full_like(t, 1.8)], axis=1)
    n = len(d)
    ret = rng.uniform(size=n) > 0.33
    lengths = np.where(ret, rng.uniform(2.0, 12.0, n), 15.0)
    pidx = np.full(n, -1, dtype=np.int64)
    pidx[ret] = np.arange(int(ret.sum()))
    return Beams(origins=origins, directions=d, times=t, lengths=lengths, has_return=ret,
                 intensity0=np.where(ret, 50.0, 0.0), ring=np.zeros(n, dtype=np.float32), point_index=pidx,
                 divergence=0.01, max_range=15.0)


def _field(seed: int) -> ParticleField:
    """~5 particles per m³ of 3..30 mm in a 4 m layer (cells wrap), falling with wind."""
    dist = ExponentialSizeDistribution(n0=5.0 * 150.0 * math.exp(150.0 * 3e-3), lam=150.0, d_min=3e-3, d_max=0.03)
    return ParticleField(seed, dist, velocity=(1.5, -0.7, -2.0), t_ref=99.0, z_min=-1.0, z_max=3.0, cell_size=1.0)


def _brute_force_hits(beams: Beams, index, particles, shells, vel: np.ndarray) -> dict[str, np.ndarray]:
    """Every (beam, resolved particle) intersection by the exact test, with the hit kernel's expressions, sorted by
    beam, then range."""
    pos = particles.positions - index.center
    r = 0.5 * particles.diameters
    rho = np.sqrt(pos[:, 0] * pos[:, 0] + pos[:, 1] * pos[:, 1] + pos[:, 2] * pos[:, 2])
    shell = np.searchsorted(shells.edges, rho, side="right") - 1
    ok = (shell >= 0) & (shell < len(shells.thresholds))
    ok[ok] = ~(2.0 * r[ok] < shells.thresholds[shell[ok]])
    rays = index.beams
    d, o, dtb = rays.directions, rays.origins, rays.times - index.t_ref
    cols: dict[str, list] = {k: [] for k in ("beam", "pid", "s", "u1", "u2", "a")}
    for chunk in np.array_split(np.flatnonzero(ok), max(1, int(ok.sum()) // 256)):
        p, rc = pos[chunk, None, :], r[chunk, None]  # (C, 1, 3), (C, 1) against (B,) beams
        vx = p[..., 0] + vel[0] * dtb - o[:, 0]
        vy = p[..., 1] + vel[1] * dtb - o[:, 1]
        vz = p[..., 2] + vel[2] * dtb - o[:, 2]
        s = vx * d[:, 0] + vy * d[:, 1] + vz * d[:, 2]
        wb = rays.tanh * s
        lim = wb + rc
        ci, hit = np.nonzero((s > 0.0) & (s < rays.lengths) & ~(vx * vx + vy * vy + vz * vz - s * s >= lim * lim))
        e1, e2 = rays.e1[hit], rays.e2[hit]
        x, y, z, sh, w = vx[ci, hit], vy[ci, hit], vz[ci, hit], s[ci, hit], wb[ci, hit]
        cols["beam"].append(hit)
        cols["pid"].append(particles.ids[chunk][ci])
        cols["s"].append(sh)
        cols["u1"].append((x * e1[:, 0] + y * e1[:, 1] + z * e1[:, 2]) / w)
        cols["u2"].append((x * e2[:, 0] + y * e2[:, 1] + z * e2[:, 2]) / w)
        cols["a"].append(r[chunk][ci] / w)
    out = {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}
    order = np.lexsort((out["s"], out["beam"]))
    return {k: v[order] for k, v in out.items()}


@pytest.mark.parametrize("seed, ratio_threshold", [(0, 0.0), (1, 3e-3), (2, 3e-2)])
def test_field_hits_are_the_materialised_particles_exact_hits(seed, ratio_threshold):
    beams = _sweep(seed)
    fld = _field(seed)
    index = index_beams(beams)
    vel = fld.velocity_array
    e_all = index.e_origin + float(np.linalg.norm(vel)) * index.beams.t_half
    r_max = 0.5 * fld.spectrum.d_max
    edges = shell_edges(float(beams.lengths.max()) + e_all + r_max + 0.01, 1.0, 1.25)
    s_near = np.maximum(0.0, edges[:-1] - e_all - r_max - 0.05)
    thresholds = 2.0 * index.beams.tanh * s_near * math.sqrt(ratio_threshold)
    cells, d_near = reachable_cells(fld, index, index.t_ref, float(edges[-1]), e_all, r_max)
    cell_shell = np.clip(np.searchsorted(edges, d_near, side="right") - 1, 0, len(thresholds) - 1)
    order = np.argsort(cell_shell, kind="stable")
    shell_off = np.searchsorted(cell_shell[order], np.arange(len(thresholds) + 1))
    shells = range_shells(edges, thresholds)
    hits, per_shell = field_hits(fld, index, cells[order], shell_off, shells, 10**8)

    parts = [fld.materialize_cells(cells[order[shell_off[k]:shell_off[k + 1]]], index.t_ref,
                                   min_diameter=float(thresholds[k])) for k in range(len(thresholds))]
    assert per_shell[:, 0].tolist() == [len(p) for p in parts]
    everything = parts[0]
    for p in parts[1:]:
        everything = type(p)(np.concatenate([everything.positions, p.positions]),
                             np.concatenate([everything.diameters, p.diameters]),
                             np.concatenate([everything.ids, p.ids]), p.t, 0.0)
    ref = _brute_force_hits(beams, index, everything, shells, vel)
    assert len(ref["beam"]) >= 50  # enough happened
    assert int(per_shell[:, 1].sum()) == len(hits.beam) == len(ref["beam"])
    for name in ("beam", "pid", "s", "u1", "u2", "a"):
        np.testing.assert_array_equal(getattr(hits, name), ref[name], err_msg=name)


# ------------------------------------------------------------------------------------------ response helpers


@njit(cache=False)
def _uncovered_count_reference(cx, cy, a, x_lo, step_x, y_lo, step_y, grid_n, over, h_u1, h_u2, h_a):
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
            for hq in over:
                ex = x - h_u1[hq]
                ey = y - h_u2[hq]
                if ex * ex + ey * ey < h_a[hq] * h_a[hq]:
                    free = False
                    break
            if free:
                count += 1
    return count


def test_uncovered_count_equals_the_point_by_point_count():
    rng = np.random.default_rng(7)
    checked = 0
    for trial in range(4000):
        grid_n = int(rng.choice([48, 48, 7, 2, 1]))
        a = float(rng.choice([rng.uniform(0.0, 0.3), rng.uniform(0.0, 2.0), 10.0 ** rng.uniform(-6, 1)]))
        cx, cy = rng.uniform(-1.5, 1.5, 2)
        if trial % 3 == 0:  # centres on round values, over-disks through the own disk's centre and edge
            cx, cy = round(cx, 2), round(cy, 1)
        k = int(rng.integers(1, 6))
        u1, u2, ha = rng.uniform(-1.5, 1.5, k), rng.uniform(-1.5, 1.5, k), rng.uniform(0.0, 1.0, k)
        if trial % 2 == 0:
            u1[0], u2[0] = cx, cy + float(rng.choice([0.0, a, -a]))
        x_lo, x_hi, y_lo, y_hi = max(cx - a, -1.0), min(cx + a, 1.0), max(cy - a, -1.0), min(cy + a, 1.0)
        if x_hi < x_lo or y_hi < y_lo:
            continue
        step_x, step_y = (x_hi - x_lo) / grid_n, (y_hi - y_lo) / grid_n
        over = np.arange(k, dtype=np.int64)
        expected = _uncovered_count_reference(cx, cy, a, x_lo, step_x, y_lo, step_y, grid_n, over, u1, u2, ha)
        got = _uncovered_count(cx, cy, a, x_lo, step_x, y_lo, step_y, grid_n, over, k, u1, u2, ha,
                               np.empty(k, np.int64), np.empty(k, np.int64))
        assert got == expected, (trial, cx, cy, a, grid_n)
        checked += 1
    assert checked > 2500


def _pulse_sum(r: np.ndarray, starts: np.ndarray, amps: np.ndarray, length: float) -> np.ndarray:
    """``sum_k amps[k] sin²(π (r - starts[k]) / length)`` over the pulses covering each range ``r`` (R,)."""
    x = r[:, None] - starts[None, :]
    on = (x >= 0.0) & (x < length) & (amps[None, :] > 0.0)
    return np.where(on, amps[None, :] * np.sin(np.pi * x / length) ** 2, 0.0).sum(axis=1)


def test_peak_is_the_maximum_of_the_summed_pulses():
    """Oracle: the summed pulses sampled densely (step h = length / 4000). The exact maximum is never below a
    sample, exceeds the sampled maximum by at most the curvature bound sum(amps) (π h / length)², and its value is
    the sum evaluated at its own range."""
    rng = np.random.default_rng(11)
    length = 2.998
    h = length / 4000.0
    for trial in range(600):
        m = int(rng.integers(1, 40))
        starts = np.sort(rng.uniform(0.0, 30.0, m)) if trial % 2 else rng.uniform(0.0, 6.0, m)
        amps = rng.exponential(1.0, m) * 10.0 ** rng.uniform(-6, 0, m)
        amps[rng.uniform(size=m) < 0.1] = 0.0
        if trial % 5 == 0:  # a dominant target pulse, coincident starts
            amps[-1] *= 1e4
            starts[0] = starts[-1]
        r_star, p_star = _peak(starts, amps, m, length, np.empty(2 * m + 2), np.empty(m + 1), np.empty(m + 1))
        if not (amps > 0).any():
            assert (r_star, p_star) == (0.0, 0.0)
            continue
        grid = np.arange(starts.min(), starts.max() + length, h)
        sampled = _pulse_sum(grid, starts, amps, length).max()
        scale = amps.sum()
        assert p_star >= sampled - 1e-12 * scale, trial
        assert p_star <= sampled + scale * (np.pi * h / length) ** 2 + 1e-12 * scale, trial
        assert _pulse_sum(np.array([r_star]), starts, amps, length)[0] == pytest.approx(p_star, rel=1e-9,
                                                                                        abs=1e-12 * scale), trial


# ------------------------------------------------------------------------------------------ index helpers


def test_sort_hits_kernel_is_a_stable_lexsort_by_beam_then_range():
    rng = np.random.default_rng(3)
    n = 5000
    beam = rng.integers(0, 300, n)
    s = rng.choice(rng.uniform(0.0, 50.0, 800), n)  # ties in range within a beam
    hits = HitArrays(beam, np.arange(n, dtype=np.int64), s, rng.normal(size=n), rng.normal(size=n), rng.uniform(size=n))
    out = HitArrays(*(np.empty(n, a.dtype) for a in hits))
    sort_hits_kernel(hits, n, 300, out)
    order = np.lexsort((s, beam))
    for name in HitArrays._fields:
        np.testing.assert_array_equal(getattr(out, name), getattr(hits, name)[order], err_msg=name)


def test_largest_gap_of_azimuths():
    rng = np.random.default_rng(5)
    for trial in range(500):
        m = int(rng.integers(1, 300))
        az = rng.uniform(-math.pi, math.pi, m) if trial % 3 else rng.uniform(0.3, 0.5, m)
        idx = rng.permutation(m).astype(np.int64)
        gap, first, last = _largest_gap(az, idx)
        a = np.sort(az)
        gaps = np.diff(np.concatenate([a, [a[0] + 2 * math.pi]]))
        assert gap == gaps.max()
        g = int(np.argmax(gaps))
        assert (first, last) == (a[(g + 1) % m], a[g])
    # evenly spaced: any largest gap will do, and the arc from first to last still holds every azimuth
    az = np.linspace(-3.0, 3.0, 1001)
    gap, first, last = _largest_gap(az, np.arange(1001, dtype=np.int64))
    assert gap >= np.diff(az).min() and np.all(np.mod(az - first, 2 * math.pi) <= np.mod(last - first, 2 * math.pi))


@njit(cache=False)
def _shells_of(p, shells):
    out = np.empty(p.shape[0], dtype=np.int64)
    for i in range(p.shape[0]):
        out[i] = _shell_of(p[i, 0], p[i, 1], p[i, 2], shells)
    return out


@pytest.mark.parametrize("edges", [shell_edges(108.0, 1.0, 1.25), shell_edges(40.0, 0.01, 1.02),
                                   np.array([0.0, np.inf])])
def test_shell_lookup_is_searchsorted(edges):
    shells = range_shells(edges, np.zeros(len(edges) - 1))
    rng = np.random.default_rng(9)
    finite = edges[np.isfinite(edges)]
    below = np.nextafter(finite[finite > 0.0], -1.0)  # (a particle's range is never negative)
    rho = np.concatenate([rng.uniform(0.0, 1.2 * finite.max() + 1.0, 20000), finite, below,
                          np.nextafter(finite, np.inf), [np.inf, np.nan]])
    p = np.zeros((len(rho), 3))
    p[:, 0] = rho
    shell = np.searchsorted(edges, rho, side="right") - 1
    expected = np.where((shell >= 0) & (shell < len(edges) - 1) & ~np.isnan(rho), shell, -1)
    np.testing.assert_array_equal(_shells_of(p, shells), expected)
