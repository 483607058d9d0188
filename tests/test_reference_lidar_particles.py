"""The reference's exact LiDAR process in snow and rain (`weatheralign.reference.lidar_particles_exact`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import minimize_scalar
from scipy.signal import fftconvolve

import weatheralign.reference.lidar_particles_exact as lpe
from weatheralign.medium.distributions import ExponentialSizeDistribution, RainSizeDistribution, SnowSizeDistribution
from weatheralign.medium.field import ParticleField, Particles
from weatheralign.reference.lidar_exact import FOG, TARGET, Detector, ExactSensor, bistatic_overlap, read_out
from weatheralign.reference.lidar_particles_exact import (
    PARTICLE,
    Unresolved,
    beam_rotations,
    beam_waveform,
    particle_returns,
    range_shells,
    resolved_diameter,
    returns_from_particles,
    subray_directions,
)
from weatheralign.sensors import SYNTHETIC_INTENSITY, IntensityModel

SENSOR = ExactSensor()
L = SENSOR.pulse_length
THETA = 3e-3
TAN_A = math.tan(THETA / 2)
SCALE = SYNTHETIC_INTENSITY.scale
ORIGIN = np.array([0.0, 0.0, 1.5])


def gain(r: float) -> float:
    return min(1.0, (SYNTHETIC_INTENSITY.r_ref / max(r, 1e-9)) ** SYNTHETIC_INTENSITY.falloff)


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def transmission(r: float, edges, area) -> float:
    """exp(-∫_0^r a), piecewise by hand."""
    tau = 0.0
    for lo, hi, a in zip(edges[:-1], edges[1:], area):
        if r <= lo:
            break
        tau += a * (min(r, hi) - lo)
    return math.exp(-tau)


def no_field() -> ParticleField:
    """A field that holds (practically) nothing: ~1e-9 particles per m³."""
    return ParticleField(1, ExponentialSizeDistribution(1e-6, 500.0, 0.0, 0.02))


# ------------------------------------------------------------------------------------------------ 1. clear air


def test_clear_target_returns_its_clear_intensity_at_its_range():
    r0 = np.array([1.0, 1.5, 7.3, 10.0, 42.0, 119.0])
    i0 = np.array([5.0, 80.0, 33.0, 12.0, 2.5, 250.0])
    rng = np.random.default_rng(0)
    d = unit(rng.normal(size=(len(r0), 3)))
    empty = np.zeros((0, 3)), np.zeros(0), None
    for model in (SYNTHETIC_INTENSITY, IntensityModel(255.0, 1.0, 2.0)):
        ret = returns_from_particles(ORIGIN, d, r0, i0, *empty, 0.9, SENSOR, intensity_model=model).returns
        np.testing.assert_allclose(ret.power, i0, rtol=1e-7)
        np.testing.assert_allclose(ret.r_peak - L / 2, r0, atol=1e-5)
        assert np.all(ret.source == TARGET)
    # through a field that holds nothing, snow or black particles: the same
    for rho in (0.9, 0.0):
        res = particle_returns(ORIGIN, d, r0, i0, no_field(), 0.0, rho, SENSOR, noise_floor=1.0)
        np.testing.assert_allclose(res.returns.power, i0, rtol=1e-7)
        np.testing.assert_allclose(res.returns.r_peak - L / 2, r0, atol=1e-5)
        assert np.all(res.returns.source == TARGET) and res.n_resolved == 0 and res.n_hits == 0
        assert np.all(res.particle_id == -1)
    # no target, nothing in the air: nothing received
    none = returns_from_particles(ORIGIN, d[:1], [np.inf], [0.0], *empty, 0.9, SENSOR)
    assert none.returns.source[0] == 0 and none.returns.power[0] == 0.0


# ------------------------------------------------------------------------------------------------ 2. one big particle


@pytest.mark.parametrize("r", [2.0, 7.5, 10.0, 25.0, 80.0])
def test_particle_covering_the_beam_reports_scale_rho_g(r):
    rho = 0.9
    rad = 3.0 * r * TAN_A  # covers the whole cone
    d = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    pos = ORIGIN + d[0] * (r + rad)  # near surface at r on the axis
    res = returns_from_particles(ORIGIN, d, np.array([r + 10.0, np.inf]), np.array([200.0, 0.0]), pos[None],
                                 [2 * rad], [77], rho, SENSOR)
    ret = res.returns
    assert ret.source[0] == PARTICLE and res.particle_id[0] == 77 and res.particle_hits[0] == 64
    assert ret.power[0] == pytest.approx(SCALE * rho * gain(r), rel=2e-4)
    # a sphere, not a disc: the outer sub-rays hit it up to (r tan(θ/2))² / (2 rad) behind r
    rays = subray_directions(d, seed=0)[0]
    c = pos - ORIGIN
    bb = rays @ c
    s = bb - np.sqrt(rad**2 - (c @ c - bb**2))
    assert np.all(s >= r - 1e-9) and s.max() - r <= 1.1 * (r * TAN_A) ** 2 / (2 * rad)
    assert ret.r_peak[0] - L / 2 == pytest.approx(s.mean(), abs=2e-4)
    assert ret.source[1] == 0 and res.particle_id[1] == -1  # the other beam sees nothing


def test_big_particle_through_the_field_path(monkeypatch):
    """`particle_returns` asks the field per shell and box; a particle inside a queried box is used once."""
    r, rho = 12.0, 0.9
    rad = 2.0 * r * TAN_A
    d = np.array([[1.0, 0.0, 0.0]])
    centre = ORIGIN + d[0] * (r + rad)
    field = no_field()
    asked = []

    def materialize(self, lo, hi, t, min_diameter=0.0, max_particles=0):
        asked.append(min_diameter)
        inside = np.all((centre >= lo) & (centre <= hi)) and 2 * rad >= min_diameter
        n = int(inside)
        return Particles(np.tile(centre, (n, 1)), np.full(n, 2 * rad), np.full(n, 5, dtype=np.int64), t, min_diameter)

    monkeypatch.setattr(ParticleField, "materialize", materialize)
    res = particle_returns(ORIGIN, d, [60.0], [100.0], field, 0.0, rho, SENSOR, noise_floor=1.0)
    assert len(asked) > 3 and res.n_resolved == 1 and res.particle_hits[0] == 64
    assert res.returns.source[0] == PARTICLE and res.particle_id[0] == 5
    assert res.returns.power[0] == pytest.approx(SCALE * rho * gain(r), rel=2e-4)


# ------------------------------------------------------------------------------------------------ 3. coverage


def circle_overlap(r1: float, r2: float, d: float) -> float:
    """Intersection area of two circles of radii r1, r2 with centres d apart."""
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        return math.pi * min(r1, r2) ** 2
    a1 = r1 * r1 * math.acos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
    a2 = r2 * r2 * math.acos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
    a3 = 0.5 * math.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2))
    return a1 + a2 - a3


def test_centred_particle_stops_its_share_of_sub_rays():
    dist = 10.0
    d = np.array([[1.0, 0.0, 0.0]])
    for f in (0.05, 0.2, 0.5, 0.9):
        beta = math.atan(math.sqrt(f) * TAN_A)  # angular radius of the silhouette
        rad = dist * math.sin(beta)
        for k in (16, 64, 200):
            res = returns_from_particles(ORIGIN, d, [30.0], [50.0], (ORIGIN + d[0] * dist)[None], [2 * rad], None,
                                         0.9, SENSOR, sub_rays=k)
            assert abs(res.particle_hits[0] / k - f) <= 1.0 / k


def test_random_positions_block_the_circle_overlap_share():
    rng = np.random.default_rng(11)
    n, k, dist, f = 600, 64, 10.0, 0.3
    tb = math.sqrt(f) * TAN_A  # silhouette radius on the unit-distance plane, beam radius TAN_A
    az = 2 * np.pi * np.arange(n) / n  # beams 10 mrad apart: no cross-talk
    d = np.stack([np.cos(az), np.sin(az), np.zeros(n)], 1)
    side = np.stack([-np.sin(az), np.cos(az), np.zeros(n)], 1)
    up = np.array([0.0, 0.0, 1.0])
    # centre offsets uniform over the disc where the circles can overlap
    off = (TAN_A + tb) * np.sqrt(rng.uniform(0, 1, n))
    ang = rng.uniform(0, 2 * np.pi, n)
    centre_dir = unit(d + off[:, None] * (np.cos(ang)[:, None] * side + np.sin(ang)[:, None] * up))
    rad = dist * math.sin(math.atan(tb))
    pos = ORIGIN + centre_dir * dist
    res = returns_from_particles(ORIGIN, d, np.full(n, 30.0), np.full(n, 50.0), pos, np.full(n, 2 * rad), None,
                                 0.9, SENSOR, sub_rays=k, seed=4)
    expected = np.array([circle_overlap(TAN_A, tb, o) / (math.pi * TAN_A**2) for o in off])
    blocked = res.particle_hits / k
    sigma = math.sqrt(np.sum(expected * (1 - expected) / k)) / n  # binomial; the stratified pattern does better
    assert abs(blocked.mean() - expected.mean()) < 4 * sigma
    assert np.all(np.abs(blocked - expected) <= 0.2)  # every single beam is close, too


# ------------------------------------------------------------------------------------------------ 4. continuum


EDGES = np.array([0.0, 3.0, 20.0, np.inf])
AREA = np.array([2e-3, 5e-3, 1e-2])


def continuum_quad(R: float, r0: float, rho: float) -> float:
    def f(r):
        return (SCALE * rho * float(Unresolved(EDGES, AREA).area_at(r)) * float(bistatic_overlap(r))
                * transmission(r, EDGES, AREA) / r**2 * math.sin(math.pi * (R - r) / L) ** 2)

    a, b = max(R - L, SENSOR.r1), min(R, r0)
    if b <= a:
        return 0.0
    cuts = [a] + [p for p in (1.0, 3.0, 20.0) if a + 1e-9 < p < b - 1e-9] + [b]  # smooth between the cuts
    return sum(quad(f, lo, hi, limit=200, epsrel=1e-10)[0] for lo, hi in zip(cuts[:-1], cuts[1:]))


def test_continuum_backscatter_against_quad():
    rho = 0.9
    d = unit([[1.0, 0.2, -0.05], [0.0, 1.0, 0.0], [0.3, -1.0, 0.1]])
    r0 = np.array([np.inf, 12.0, 2.5])
    i0 = np.zeros(3)
    unres = Unresolved(EDGES, AREA)
    empty = np.zeros((0, 3)), np.zeros(0)
    for b in range(3):
        R = np.array([1.0, 2.2, 4.0, 6.5, 11.0, 14.0, 17.9, 30.0, 100.0])
        pulses, cont = beam_waveform(R, b, ORIGIN, d, r0, i0, *empty, rho, SENSOR, unresolved=unres)
        assert np.all(pulses == 0.0)
        ref = np.array([continuum_quad(x, r0[b], rho) for x in R])
        np.testing.assert_allclose(cont, ref, rtol=2e-5, atol=1e-7 * ref.max())  # 1 mm running integrals
    ret = returns_from_particles(ORIGIN, d, r0, i0, *empty, None, rho, SENSOR, unresolved=unres).returns
    assert np.all(ret.source == FOG)
    for b in range(3):
        r_grid = np.arange(1.0, min(r0[b] + L, SENSOR.listen_end), 0.05)
        j = int(np.argmax([continuum_quad(x, r0[b], rho) for x in r_grid]))
        opt = minimize_scalar(lambda x: -continuum_quad(x, r0[b], rho), bounds=(r_grid[j] - 0.05, r_grid[j] + 0.05),
                              method="bounded", options={"xatol": 1e-6})
        r_rep = ret.r_peak[b] - L / 2
        raw = ret.power[b] / (max(r_rep, 0.0) ** 2 * gain(r_rep))
        assert raw == pytest.approx(-opt.fun, rel=1e-5)
        assert ret.r_peak[b] == pytest.approx(opt.x, abs=2e-3)


# ------------------------------------------------------------------------------------------------ 5. brute force


def brute_force(origin, d, r0, i0, pos, diam, ids, rho, sensor, unres, k_sub, seed, h=5e-4):
    """All particles x all sub-rays in numpy, the waveform on an ``h`` grid (continuum by direct convolution)."""
    length, listen = sensor.pulse_length, sensor.listen_end
    rays = subray_directions(d, sub_rays=k_sub, divergence_rad=THETA, seed=seed)
    grid = np.arange(0.0, listen + length + h, h)
    kern = np.sin(np.pi * np.arange(0.0, length, h) / length) ** 2
    a = unres.area_at(grid)
    tau = np.concatenate([[0.0], np.cumsum(0.5 * h * (a[1:] + a[:-1]))])
    trans = np.exp(-tau)
    xi = bistatic_overlap(grid, sensor)
    with np.errstate(divide="ignore", invalid="ignore"):
        f_cont = np.where(grid > 0, SCALE * rho * a * xi * trans / grid**2, 0.0)
    out = []
    c = pos - origin
    rad = diam / 2
    for b in range(len(d)):
        bb = rays[b] @ c.T  # (K, N)
        perp2 = np.sum((c[None, :, :] - bb[:, :, None] * rays[b][:, None, :]) ** 2, axis=2)
        inside = perp2 < rad[None] ** 2
        half = np.sqrt(np.where(inside, rad[None] ** 2 - perp2, 0.0))
        s = np.where(inside & (bb + half > 0), np.maximum(bb - half, 0.0), np.inf)
        j = np.argmin(s, axis=1) if len(pos) else np.zeros(k_sub, dtype=int)
        s_hit = s[np.arange(k_sub), j] if len(pos) else np.full(k_sub, np.inf)
        particle = s_hit < r0[b]
        echoes = []  # (range, amplitude, particle id or -1)
        for k in np.flatnonzero(particle):
            r = s_hit[k]
            amp = SCALE * rho * float(bistatic_overlap(r, sensor)) * transmission(r, unres.edges, unres.area) / r**2
            echoes.append((r, amp / k_sub if r > sensor.r1 else 0.0, ids[j[k]]))
        n_t = int(np.sum(~particle))
        if np.isfinite(r0[b]):
            amp = (n_t / k_sub * i0[b] / gain(r0[b]) * float(bistatic_overlap(r0[b], sensor))
                   * transmission(r0[b], unres.edges, unres.area) / r0[b] ** 2)
            echoes.append((r0[b], amp, -1))
        # continuum: f u on [0, r0), convolved with the pulse
        blocked = np.searchsorted(np.sort(s_hit[particle]), grid, side="right") / k_sub
        g = f_cont * (1.0 - blocked) * (grid < r0[b])
        cont = fftconvolve(g, kern)[: len(grid)] * h
        parts = np.zeros((len(echoes), len(grid)))
        for e, (r, amp, _) in enumerate(echoes):
            x = grid - r
            parts[e] = np.where((x >= 0) & (x <= length), amp * np.sin(np.pi * x / length) ** 2, 0.0)
        total = parts.sum(0) + cont
        window = (grid > 0) & (grid <= listen)
        m = int(np.argmax(np.where(window, total, -1.0)))
        r_rep = grid[m] - length / 2
        power = total[m] * max(r_rep, 0.0) ** 2 * gain(r_rep)
        tgt = sum(parts[e, m] for e, ech in enumerate(echoes) if ech[2] == -1)
        by_id = {}
        for e, ech in enumerate(echoes):
            if ech[2] != -1:
                by_id[ech[2]] = by_id.get(ech[2], 0.0) + parts[e, m]
        part = sum(by_id.values())
        shares = sorted([tgt, part, cont[m]])
        src = PARTICLE if part > max(tgt, cont[m]) else (TARGET if tgt >= cont[m] and tgt > 0 else FOG)
        top = max(by_id, key=by_id.get) if src == PARTICLE else -1
        # second-best local peak, to skip ties
        others = np.where(np.abs(grid - grid[m]) > 0.5 * length, total, 0.0)
        out.append(dict(power=power, r_peak=grid[m], source=src, id=top, hits=int(particle.sum()),
                        clear=shares[-1] > 1.02 * shares[-2], unique=others.max() < 0.98 * total[m],
                        wave=(grid, parts.sum(0), cont)))
    return out


def test_fast_path_matches_brute_force():
    rng = np.random.default_rng(21)
    sensor = ExactSensor(max_range=30.0)
    nb, n = 16, 90
    d = unit(np.column_stack([np.ones(nb), rng.uniform(-0.01, 0.01, nb), rng.uniform(-0.01, 0.01, nb)]))
    r0 = rng.uniform(3.0, 28.0, nb)
    r0[[2, 7, 11]] = np.inf
    i0 = np.where(np.isfinite(r0), rng.uniform(5.0, 80.0, nb), 0.0)
    # particles near the beams: random beam, range, offset within 1.5 beam radii, 0.3..8 mm
    which = rng.integers(0, nb, n)
    dist = rng.uniform(1.5, 30.0, n)
    lateral = unit(np.cross(d[which], rng.normal(size=(n, 3))))
    off = 1.5 * TAN_A * dist * np.sqrt(rng.uniform(0, 1, n))
    pos = ORIGIN + d[which] * dist[:, None] + lateral * off[:, None]
    diam = np.exp(rng.uniform(math.log(3e-4), math.log(8e-3), n))
    ids = rng.permutation(10 * n)[:n].astype(np.int64)
    unres = Unresolved(np.array([0.0, 2.0, 8.0, np.inf]), np.array([1e-4, 5e-4, 2e-3]))
    res = returns_from_particles(ORIGIN, d, r0, i0, pos, diam, ids, 0.9, sensor, unresolved=unres, seed=9)
    ref = brute_force(ORIGIN, d, r0, i0, pos, diam, ids, 0.9, sensor, unres, 64, seed=9)
    assert res.n_hits > 50
    checked, sources = 0, set()
    for b, want in enumerate(ref):
        assert res.particle_hits[b] == want["hits"]
        grid, pulses_ref, cont_ref = want["wave"]
        sel = slice(0, None, 997)
        pulses, cont = beam_waveform(grid[sel], b, ORIGIN, d, r0, i0, pos, diam, 0.9, sensor, unresolved=unres, seed=9)
        np.testing.assert_allclose(pulses, pulses_ref[sel], rtol=1e-9, atol=1e-15)
        # the brute force's continuum is a 0.5 mm Riemann sum (O(h) at r0 and behind each blocking particle)
        np.testing.assert_allclose(cont, cont_ref[sel], rtol=2e-3, atol=1e-5 * cont_ref.max() + 1e-15)
        if not want["unique"]:
            continue
        checked += 1
        assert res.returns.power[b] == pytest.approx(want["power"], rel=1e-3)
        assert res.returns.r_peak[b] == pytest.approx(want["r_peak"], abs=1.5e-3)
        if want["clear"]:
            assert res.returns.source[b] == want["source"]
            assert res.particle_id[b] == want["id"]
            sources.add(want["source"])
    assert checked >= nb - 2 and sources == {TARGET, FOG, PARTICLE}


def test_particle_returns_uses_every_resolved_particle_once():
    """The shells and boxes of `particle_returns` against every particle of a big box, resolved by hand."""
    sensor = ExactSensor(max_range=20.0)
    field = ParticleField(3, ExponentialSizeDistribution(2e5, 400.0, 0.0, 0.02), cell_size=2.0)  # ~500 per m³
    el = np.deg2rad(np.array([-6.0, -2.0, 1.0]))
    az = np.linspace(0.0, 0.3, 40)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        r0 = np.where(d[:, 2] < 0, ORIGIN[2] / -d[:, 2], np.inf)
    r0[r0 > 20.0] = np.inf
    i0 = np.where(np.isfinite(r0), 20.0, 0.0)
    rho, floor, t = 0.9, 1.0, 0.7
    res = particle_returns(ORIGIN, d, r0, i0, field, t, rho, sensor, noise_floor=floor, seed=5)
    # D_res per shell and the continuum
    edges = range_shells(sensor.listen_end)
    assert np.array_equal(res.unresolved.edges, edges) and np.isinf(res.min_diameter[0])
    inner = edges[1:-1]
    dres = res.min_diameter[1:]
    np.testing.assert_allclose(dres, resolved_diameter(inner, rho, floor), rtol=1e-12)
    cover = SCALE * rho * (dres / (inner * THETA)) ** 2 * np.array([gain(r) for r in inner])
    np.testing.assert_allclose(cover[np.isfinite(dres)], 0.05 * floor, rtol=1e-9)
    spec = field.spectrum
    for kk in (0, 6, len(dres)):
        hi = min(float(res.min_diameter[kk]), spec.d_max)
        ref = quad(lambda x: spec.n0 * math.exp(-spec.lam * x) * math.pi * x * x / 4, spec.d_min, hi)[0]
        assert res.unresolved.area[kk] == pytest.approx(ref, rel=1e-8)
    # every particle of a box around all beams, resolved by its centre's shell
    got = field.materialize([-1.0, -1.0, -2.0], [24.0, 8.0, 4.0], t, 0.0)
    c = got.positions - ORIGIN
    shell = np.searchsorted(edges, np.linalg.norm(c, axis=1), side="right") - 1
    keep = got.diameters >= res.min_diameter[shell]
    ref = returns_from_particles(ORIGIN, d, r0, i0, got.positions[keep], got.diameters[keep], got.ids[keep], rho,
                                 sensor, unresolved=res.unresolved, seed=5)
    assert ref.n_pairs == res.n_pairs and ref.n_hits == res.n_hits and res.n_hits > 20
    np.testing.assert_array_equal(ref.returns.power, res.returns.power)
    np.testing.assert_array_equal(ref.returns.r_peak, res.returns.r_peak)
    np.testing.assert_array_equal(ref.returns.source, res.returns.source)
    np.testing.assert_array_equal(ref.particle_id, res.particle_id)
    assert np.any(res.returns.source == PARTICLE)
    # the grid search's pruning by upper bounds is exact: every node evaluated gives the same peaks, bit for bit
    beams = lpe._beam_inputs(ORIGIN, d, r0, i0)  # validated (normalised) as the entry points do
    full = lpe._run(*beams, got.positions[keep], got.diameters[keep], got.ids[keep], rho, sensor, res.unresolved,
                    THETA, 64, SYNTHETIC_INTENSITY, 0.02, 5, prune=False)
    for x, y in [(full.returns.power, res.returns.power), (full.returns.r_peak, res.returns.r_peak),
                 (full.returns.source, res.returns.source), (full.particle_id, res.particle_id)]:
        assert x.tobytes() == y.tobytes()
    # the detector applies unchanged
    det = read_out(res.returns, sensor, Detector(), np.random.default_rng(0))
    assert len(det.index) > 0 and np.all(det.intensity >= 1.0)


# ------------------------------------------------------------------------------------------------ 6. determinism


def small_scan():
    el = np.deg2rad(np.array([-10.0, -3.0, 0.5]))
    az = np.linspace(-0.5, 0.5, 60)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        r0 = np.where(d[:, 2] < 0, ORIGIN[2] / -d[:, 2], np.inf)
    r0[r0 > 40.0] = np.inf
    return d, r0, np.where(np.isfinite(r0), 10.0, 0.0)


def test_undetectable_drop_echo_leaves_the_target_to_the_receiver():
    """A drop near the sensor whose raw echo (1/r²) beats a faint target's but whose intensity is under the floor:
    the strongest peak is the drop's, the target's own echo crest is kept as the second return (the waveform there,
    read as an intensity at the target's range) and a strongest-return receiver reports the target."""
    r_drop, r_target, i_target, rho = 2.0, 15.0, 3.0, 0.02
    d = np.array([[1.0, 0.0, 0.0]])
    diam = 2.0 * 0.4 * r_drop * TAN_A  # covers ~16 % of the cone
    pos = ORIGIN + d[0] * (r_drop + diam / 2)
    res = returns_from_particles(ORIGIN, d, [r_target], [i_target], pos[None], [diam], [9], rho, SENSOR)
    ret = res.returns
    assert ret.source[0] == PARTICLE and ret.power[0] < 1.0 and res.particle_hits[0] > 0
    R_t = r_target + L / 2
    pulses, cont = beam_waveform(np.array([R_t]), 0, ORIGIN, d, [r_target], [i_target], pos[None], [diam], rho,
                                 SENSOR)
    assert ret.target_r_peak[0] == pytest.approx(R_t)
    assert ret.target_power[0] == pytest.approx((pulses[0] + cont[0]) * r_target**2 * gain(r_target), rel=1e-9)
    unblocked = 1.0 - res.particle_hits[0] / 64
    assert ret.target_power[0] == pytest.approx(i_target * unblocked, rel=1e-6)  # the drop's echo ended long before
    exact = Detector(intensity_noise_std=0.0, intensity_noise_rel=0.0, noise_floor=1.0, range_noise_std=0.0)
    out = read_out(ret, SENSOR, exact, np.random.default_rng(0))
    assert out.index.tolist() == [0] and out.source[0] == TARGET
    assert out.range[0] == pytest.approx(r_target) and out.intensity[0] == round(i_target * unblocked)
    # without the second return (a receiver that only reads the strongest peak) the target would be lost
    first_only = type(ret)(ret.power, ret.r_peak, ret.source)
    assert len(read_out(first_only, SENSOR, exact, np.random.default_rng(0)).index) == 0
    # a detectable drop echo is reported instead of the target (the strongest detected echo)
    loud = returns_from_particles(ORIGIN, d, [r_target], [i_target], pos[None], [diam], [9], 0.9, SENSOR).returns
    assert loud.source[0] == PARTICLE and loud.power[0] > 1.0
    out = read_out(loud, SENSOR, exact, np.random.default_rng(0))
    assert out.source[0] == PARTICLE and out.range[0] == pytest.approx(loud.r_peak[0] - L / 2)


def test_deterministic_bytes_and_seeded_pattern():
    d, r0, i0 = small_scan()
    field = ParticleField(8, SnowSizeDistribution(2.5, 1.5))
    sensor = ExactSensor(max_range=40.0)
    a = particle_returns(ORIGIN, d, r0, i0, field, 1.0, 0.9, sensor, noise_floor=1.0, seed=3)
    b = particle_returns(ORIGIN, d, r0, i0, field, 1.0, 0.9, sensor, noise_floor=1.0, seed=3)
    for x, y in [(a.returns.power, b.returns.power), (a.returns.r_peak, b.returns.r_peak),
                 (a.returns.source, b.returns.source), (a.particle_id, b.particle_id),
                 (a.particle_hits, b.particle_hits)]:
        assert x.tobytes() == y.tobytes()
    assert a.n_resolved > 0 and a.n_hits > 0
    assert not np.array_equal(beam_rotations(50, 3), beam_rotations(50, 4))
    rays = subray_directions(d[:2], sub_rays=64, seed=3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=2), 1.0, atol=1e-12)
    cos = np.einsum("bkj,bj->bk", rays, d[:2])
    assert np.all(cos >= math.cos(THETA / 2) - 1e-15)  # inside the cone
    c = particle_returns(ORIGIN, d, r0, i0, field, 1.0, 0.9, sensor, noise_floor=1.0, seed=4)
    assert c.n_resolved == a.n_resolved and c.n_pairs == a.n_pairs  # same particles, other sub-rays
    none = particle_returns(ORIGIN, np.zeros((0, 3)), [], [], field, 1.0, 0.9, sensor, noise_floor=1.0)
    assert none.returns.power.shape == (0,) and none.n_resolved == 0


def test_heavier_precipitation_scatters_more_and_dims_the_targets():
    d, r0, i0 = small_scan()
    sensor = ExactSensor(max_range=40.0)
    for dist, rho, cell in ((SnowSizeDistribution, 0.9, 2.0), (RainSizeDistribution, 0.02, 1.0)):
        shares, dims = [], []
        for rate in ((0.5, 4.0) if dist is SnowSizeDistribution else (10.0, 100.0)):
            field = ParticleField(2, dist(rate, 1.5) if dist is SnowSizeDistribution else dist(rate), cell_size=cell)
            res = particle_returns(ORIGIN, d, r0, i0, field, 0.0, rho, sensor, noise_floor=1.0)
            target = res.returns.source == TARGET
            shares.append(np.mean(res.returns.source == PARTICLE))
            dims.append(np.mean(res.returns.power[target] / i0[target]))
        assert shares[1] > shares[0] and dims[1] < dims[0]


def test_bad_inputs_are_refused_with_the_expected_form():
    d, r0, i0 = small_scan()
    field = no_field()

    def call(**kw):
        args = dict(origin=ORIGIN, directions=d, r0=r0, i0=i0, field=field, t=0.0, reflectivity=0.9, sensor=SENSOR)
        opts = dict(noise_floor=1.0)
        for k, v in kw.items():
            (args if k in args else opts)[k] = v
        return particle_returns(**args, **opts)

    cases = [
        (dict(origin=[0.0, 1.0]), r"origin = .*expected 3 finite numbers"),
        (dict(directions=d[:, :2]), r"directions \(180, 2\); expected \(B, 3\) finite unit vectors"),
        (dict(directions=2 * d), r"directions\[0\] has norm 2; expected \(B, 3\) unit vectors"),
        (dict(r0=r0[:5]), r"r0 \(5,\); expected \(180,\) target ranges > 0"),
        (dict(r0=np.where(np.arange(180) == 3, np.nan, r0)), r"r0 \(180,\); expected"),
        (dict(r0=-np.ones(180)), r"r0 .*> 0 \[m\] \(inf: no target\)"),
        (dict(i0=-i0 - 1), r"i0 \(180,\); expected \(180,\) finite clear intensities >= 0"),
        (dict(i0=np.ones(180)), r"i0: expected 0 where r0 is inf"),
        (dict(field="snow"), r"field = str; expected a ParticleField"),
        (dict(t=float("nan")), r"t = nan; expected a finite time"),
        (dict(reflectivity=1.5), r"reflectivity = 1.5; expected a particle reflectivity in \[0, 1\]"),
        (dict(noise_floor=0.0), r"noise_floor = 0.0; expected 0 < noise_floor <= 255"),
        (dict(resolve_fraction=-1.0), r"resolve_fraction = -1.0; expected 0 < resolve_fraction <= 1000"),
        (dict(divergence_rad=0.0), r"divergence_rad = 0.0; expected a full divergence"),
        (dict(sub_rays=0), r"sub_rays = 0; expected an integer in \[1, 4096\]"),
        (dict(sub_rays=8.5), r"sub_rays = 8.5; expected an integer"),
        (dict(grid_step=0.5), r"grid_step = 0.5; expected 0.001 <= grid_step <= 0.1 m"),
        (dict(seed=-1), r"seed = -1; expected an integer in \[0, "),
        (dict(sensor=object()), r"sensor = object; expected an ExactSensor"),
        (dict(intensity_model=None), r"intensity_model = NoneType; expected an IntensityModel"),
    ]
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            call(**kw)
    with pytest.raises(ValueError, match=r"positions \(2, 2\); expected \(N, 3\) finite positions"):
        returns_from_particles(ORIGIN, d, r0, i0, np.zeros((2, 2)), np.ones(2), None, 0.9, SENSOR)
    with pytest.raises(ValueError, match=r"diameters \(3,\); expected \(2,\) finite diameters > 0"):
        returns_from_particles(ORIGIN, d, r0, i0, np.zeros((2, 3)), np.ones(3), None, 0.9, SENSOR)
    with pytest.raises(ValueError, match=r"Unresolved.edges = .*expected \(S \+ 1,\) increasing shell edges"):
        Unresolved(np.array([0.0, 5.0, 2.0, np.inf]), np.zeros(3))
    with pytest.raises(ValueError, match=r"Unresolved.area: expected \(2,\) finite cross-sections >= 0"):
        Unresolved(np.array([0.0, 5.0, np.inf]), np.array([1e-3, -1.0]))
