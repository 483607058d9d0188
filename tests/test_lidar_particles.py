"""LiDAR snow and rain through one 3-D particle field: closed forms, a brute-force reference, motion during the sweep,
beams without return, determinism, and sanity on a synthetic-world scan and the real STF / KITTI scans.

The reference ``_naive`` is slow and obviously correct: per beam it propagates every particle to the beam's firing
time, casts ``N_SUB`` sub-rays spread uniformly over the beam cross-section (a sunflower pattern; sub-ray ``q`` runs
from the origin along ``d + tan(θ/2) (q1 e1 + q2 e2)``), intersects them with every particle sphere (ray–sphere), gives
each sub-ray to its nearest sphere, and sums the published closed-form pulses (`pulse.hard_target_power`) on a 1 mm
receiver grid, taking the largest sample. Stated tolerances (fast vs naive): occlusion ratios within 2 % (or 0.002
absolute), measured ranges within 0.05 m, intensities within 3 % (plus, for a particle echo, the relative effect of a
5e-4 error in the naive's share of that particle), identical labels except for beams whose decision
is within a stated margin of a boundary (keep tolerance ± 0.05 m, noise floor ± 5 %, the two strongest echoes within
5 %).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import make_lidar
from weatheralign.data.frame import LidarScan
from weatheralign.data.nuscenes import load_lidar, open_nuscenes
from weatheralign.lidar.beams import Beams, beams_from_scan, reconstruct_no_return_beams, synthetic_columns
from weatheralign.lidar.fog import FogLabel
from weatheralign.lidar.labels import POINT_LABELS, WeatherLabel
from weatheralign.lidar.particles import (
    RAIN_REFLECTIVITY,
    SNOW_REFLECTIVITY,
    ParticleLabel,
    auto_ratio_threshold,
    simulate_particle_list,
    simulate_particle_scans,
    simulate_particles,
)
from weatheralign.lidar.pulse import hard_target_power
from weatheralign.medium import (
    ExponentialSizeDistribution,
    ParticleField,
    Particles,
    RainSizeDistribution,
    SnowSizeDistribution,
    fall_velocity,
)
from weatheralign.medium.fog import FogMedium
from weatheralign.sensors import (
    CALIBRATED_INTENSITY,
    HAHNER_INTENSITY,
    SYNTHETIC_INTENSITY,
    IntensityModel,
    LidarModel,
    PulseSensor,
)
from weatheralign.world.shading import lidar_intensity

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
STF_ID = "2019-09-11_19-13-44_00960"
N_SUB = 50000
SHARE_RESOLUTION = 5e-4  # absolute share error of the naive's sub-ray count for a small disk (~ its boundary samples)
KEEP = 0.2
FLOOR = 0.5
LIDAR = make_lidar(noise_floor=FLOOR)
"""The snow model's sensor: 3 mrad, τ_H = 10 ns, 120 m, noise floor 0.5, the synthetic world's intensity model and
firing grid (the values the particle API used to default to; `Beams` inputs carry their own divergence and range)."""
SENSOR = LIDAR.pulse
LIDAR_100M = make_lidar(max_range_m=100.0)
"""The same sensor with the synthetic world's 100 m maximum range (the length of beams without return)."""


# ------------------------------------------------------------------------------------------------------ helpers


def _beams(origins, directions, lengths, intensity, *, times=None, has_return=None, divergence=3e-3,
           max_range=60.0) -> Beams:
    o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = len(d)
    o = np.broadcast_to(o, (n, 3)).copy()
    ret = np.ones(n, dtype=bool) if has_return is None else np.asarray(has_return, dtype=bool)
    lengths = np.where(ret, np.broadcast_to(np.asarray(lengths, dtype=np.float64), (n,)), max_range)
    pidx = np.full(n, -1, dtype=np.int64)
    pidx[ret] = np.arange(int(ret.sum()))
    return Beams(origins=o, directions=d, times=np.zeros(n) if times is None else np.asarray(times, np.float64),
                 lengths=lengths.astype(np.float64), has_return=ret,
                 intensity0=np.where(ret, np.broadcast_to(np.asarray(intensity, np.float64), (n,)), 0.0),
                 ring=np.arange(n, dtype=np.float32), point_index=pidx, divergence=divergence,
                 max_range=max_range)


def _particles(positions, diameters, ids=None, t=0.0) -> Particles:
    p = np.atleast_2d(np.asarray(positions, dtype=np.float64))
    dia = np.atleast_1d(np.asarray(diameters, dtype=np.float64))
    ids = np.arange(len(p), dtype=np.int64) + 100 if ids is None else np.asarray(ids, dtype=np.int64)
    return Particles(p, dia, ids, float(t), 0.0)


def _sunflower(n: int) -> np.ndarray:
    """(n, 2) points uniformly covering the unit disk (equal area each)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    a = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def _basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _naive(beams: Beams, particles: Particles, velocity, *, reflectivity=SNOW_REFLECTIVITY,
           sensor: PulseSensor = SENSOR, model: IntensityModel = SYNTHETIC_INTENSITY, extinction=0.0, floor=FLOOR,
           keep=KEEP, clear=None) -> dict:
    """Brute force per beam (see the module docstring): shares per particle id, measured range, intensity, label,
    and the margin flags that make a beam's decision borderline. ``clear`` (B,): the clear value each rounded
    ``intensity0`` stood for (`beam_clear_readings`), which decides whether a kept target fell under the floor: its
    difference from ``intensity0`` carried through the target's transmission; None: ``intensity0`` as read."""
    q = _sunflower(N_SUB)
    tanh = math.tan(0.5 * beams.divergence)
    length_pulse = sensor.pulse_length
    beta0 = sensor.beta_0
    out = {"label": [], "range": [], "intensity": [], "pid": [], "shares": [], "borderline": []}
    vel = np.asarray(velocity, dtype=np.float64)
    for b in range(len(beams)):
        o, d, L = beams.origins[b], beams.directions[b], beams.lengths[b]
        i0, ret = beams.intensity0[b], bool(beams.has_return[b])
        x = i0 if clear is None else float(clear[b])
        c = particles.positions + vel * (beams.times[b] - particles.t)
        rad = 0.5 * particles.diameters
        v = c - o
        s = v @ d
        perp = np.sqrt(np.maximum((v * v).sum(1) - s * s, 0.0))
        cand = np.flatnonzero((s > 0) & (s < L) & (perp < tanh * s + rad + 1e-9))
        e1, e2 = _basis(d)
        u = d[None, :] + tanh * (q[:, :1] * e1[None, :] + q[:, 1:] * e2[None, :])  # (N, 3) sub-ray directions
        best_t = np.full(N_SUB, np.inf)
        owner = np.full(N_SUB, -1)
        for j in cand:
            w = o - c[j]
            a = (u * u).sum(1)
            bq = 2.0 * (u @ w)
            cq = w @ w - rad[j] ** 2
            disc = bq * bq - 4 * a * cq
            hit = disc >= 0
            t_hit = np.where(hit, (-bq - np.sqrt(np.maximum(disc, 0.0))) / (2 * a), np.inf)
            t_hit = np.where(t_hit > 0, t_hit, np.where(hit, 0.0, np.inf))  # sub-ray starting inside: hit at once
            better = t_hit < best_t
            best_t[better] = t_hit[better]
            owner[better] = j
        shares = {int(particles.ids[j]): float(np.mean(owner == j)) for j in cand}
        remaining = float(np.mean(owner < 0))
        grid = np.arange(0.0, L + length_pulse + 0.01, 0.001)
        wave = np.zeros_like(grid)
        contrib = {}
        for j in cand:
            r_j = float(np.linalg.norm(c[j] - o))
            part = hard_target_power(grid, r_j, sensor, beta_ratio=reflectivity * shares[int(particles.ids[j])],
                                     alpha=extinction, c_a_p0=model.scale / beta0)
            contrib[int(particles.ids[j])] = part
            wave += part
        target = np.zeros_like(grid)
        if ret and L > 0:
            g0 = float(model.gain(L))
            target = hard_target_power(grid, L, sensor, beta_ratio=remaining, alpha=extinction,
                                       c_a_p0=i0 / (g0 * beta0))
            wave += target
        k = int(np.argmax(wave))
        p_star, r_star = wave[k], grid[k] - 0.5 * length_pulse
        label, rng, inten, pid, border = ParticleLabel.NO_ECHO, np.nan, 0.0, -1, False

        def kept(reading: float) -> tuple[ParticleLabel, bool]:  # the target's outcome and whether it is borderline
            seen = reading + (x - i0) * remaining * math.exp(-2.0 * extinction * L)
            label = ParticleLabel.LOST if seen < floor and seen < x else ParticleLabel.ATTENUATED
            return label, clear is not None and abs(seen - floor) < 0.05 * floor

        if p_star <= 0:
            if ret:
                label = ParticleLabel.ATTENUATED if remaining > 0 else ParticleLabel.LOST
        elif ret and abs(r_star - L) <= keep:
            inten = min(p_star * L * L * float(model.gain(L)), 255.0)
            label, near_floor = kept(inten)
            rng = L
            border = abs(abs(r_star - L) - keep) < 0.05 or near_floor
        else:
            pid = max(contrib, key=lambda key: contrib[key][k])
            inten = min(p_star * r_star ** 2 * float(model.gain(r_star)), 255.0)
            rng = r_star
            border = ret and abs(abs(r_star - L) - keep) < 0.05
            if inten < floor:
                border |= inten > floor * 0.95
                if ret:
                    kt = int(np.argmin(np.abs(grid - (L + 0.5 * length_pulse))))
                    inten = min(wave[kt] * L * L * float(model.gain(L)), 255.0)
                    label, near_floor = kept(inten)
                    border |= near_floor
                    rng, pid = L, -1
                else:
                    label, rng, pid = ParticleLabel.NO_ECHO, np.nan, -1
            else:
                border |= inten < floor * 1.05
                label = ParticleLabel.SCATTERED
        # the two strongest candidate echoes within 5 %: a 1 mm grid or a 2 % share error can flip them
        peaks = [float(np.max(p)) for p in contrib.values()] + ([float(np.max(target))] if ret else [])
        peaks.sort(reverse=True)
        if len(peaks) > 1 and peaks[1] > 0.95 * peaks[0]:
            border = True
        out["label"].append(label)
        out["range"].append(rng)
        out["intensity"].append(inten)
        out["pid"].append(pid)
        out["shares"].append(shares)
        out["borderline"].append(border)
    return out


def _fast_beam_view(res, beams: Beams) -> dict:
    """Per-beam label / range / intensity (0..255) / particle id / shares of a fast result."""
    shares = [{} for _ in range(len(beams))]
    for b, p, r in zip(res.hits.beam, res.hits.particle_id, res.hits.ratio):
        shares[int(b)][int(p)] = float(r)
    return {"label": [ParticleLabel(int(x)) for x in res.beam_label], "range": res.beam_range,
            "intensity": res.beam_intensity, "pid": res.beam_particle, "shares": shares}


def _compare(fast: dict, naive: dict) -> None:
    n = len(naive["label"])
    for b in range(n):
        for pid, share in naive["shares"][b].items():
            got = fast["shares"][b].get(pid, 0.0)
            assert abs(got - share) <= max(0.02 * share, 0.002), (b, pid, got, share)
        extra = set(fast["shares"][b]) - set(naive["shares"][b])
        assert all(fast["shares"][b][p] <= 0.002 for p in extra), (b, extra)
        if naive["borderline"][b]:
            continue
        lf, ln = fast["label"][b], naive["label"][b]
        if ln == ParticleLabel.ATTENUATED:  # UNCHANGED is ATTENUATED without a bit of change
            assert lf in (ParticleLabel.ATTENUATED, ParticleLabel.UNCHANGED), (b, lf, ln)
        else:
            assert lf == ln, (b, lf, ln)
        if ln in (ParticleLabel.SCATTERED, ParticleLabel.ATTENUATED):
            assert abs(fast["range"][b] - naive["range"][b]) <= 0.05, (b, fast["range"][b], naive["range"][b])
            tol = 0.03
            if ln == ParticleLabel.SCATTERED:  # an echo ∝ its particle's share: allow the naive's share resolution
                tol += SHARE_RESOLUTION / max(naive["shares"][b][naive["pid"][b]], 1e-9)
            assert abs(fast["intensity"][b] - naive["intensity"][b]) <= tol * naive["intensity"][b] + 1e-6, \
                (b, fast["intensity"][b], naive["intensity"][b])
        if ln == ParticleLabel.SCATTERED:
            assert fast["pid"][b] == naive["pid"][b], (b, fast["pid"][b], naive["pid"][b])


# ------------------------------------------------------------------------------------------------- closed forms


def test_intensity_models_match_their_sources():
    rho = np.array([0.1, 0.5, 0.9])
    r = np.array([3.0, 10.0, 55.0])
    # the renderer (the reference's and the world's), exactly, for any intensity model
    for model in (SYNTHETIC_INTENSITY, IntensityModel(100.0, 1.0, 0.0)):
        np.testing.assert_allclose(model.intensity(rho, r), lidar_intensity(rho, np.ones(3), r, model), rtol=1e-6)
    # Hahner's published snow code: a flake reports 0.9 * 255 * ratio / r²
    np.testing.assert_allclose(HAHNER_INTENSITY.intensity(0.9, r, 0.01), 0.9 * 255 * 0.01 / r ** 2)
    np.testing.assert_allclose(CALIBRATED_INTENSITY.intensity(rho, r), 255 * rho)
    assert auto_ratio_threshold(SNOW_REFLECTIVITY) == pytest.approx(1e-3)
    assert auto_ratio_threshold(RAIN_REFLECTIVITY) == pytest.approx(1e-2)


@pytest.mark.parametrize("offset", [0.0, 0.4])
def test_one_particle_inside_the_beam_occludes_its_area_share_and_returns_at_its_range(offset):
    divergence = 3e-3
    s_p, diameter = 10.0, 6e-3
    w = s_p * math.tan(divergence / 2)
    ratio = (diameter / 2) ** 2 / w ** 2  # 0.04: fully inside the beam
    off = offset * (w - diameter / 2)  # stays inside the beam
    beams = _beams([0, 0, 0], [1, 0, 0], 30.0, 20.0, divergence=divergence)
    parts = _particles([s_p, off, 0.0], diameter, ids=[7])
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    assert len(res.hits) == 1
    assert res.hits.ratio[0] == pytest.approx(ratio, rel=1e-9)
    assert res.hits.range[0] == pytest.approx(s_p, abs=1e-9)
    # the flake's echo (255 · 0.9 · 0.04 at 10 m, g = 1) beats the 20-intensity target at 30 m: scattered there
    assert res.input_labels[0] == ParticleLabel.SCATTERED
    assert res.particle_id[0] == 7
    assert np.linalg.norm(res.points[0, :3]) == pytest.approx(s_p, abs=1e-4)
    assert res.points[0, 3] == pytest.approx(255 * SNOW_REFLECTIVITY * ratio, rel=1e-6)
    assert res.points[0, 4] == beams.ring[0]


def test_small_particle_only_occludes_the_target():
    beams = _beams([0, 0, 0], [0, 1, 0], 30.0, 20.0)
    w = 10.0 * math.tan(1.5e-3)
    parts = _particles([0.0, 10.0, 0.0], 2 * 0.1 * w)  # covers 1 %: its echo is weaker than the target's
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    assert res.hits.ratio[0] == pytest.approx(0.01, rel=1e-9)
    assert res.input_labels[0] == ParticleLabel.ATTENUATED
    # the target keeps 99 % of the beam; pulses 20 m apart do not overlap: exactly 0.99 i0
    assert res.points[0, 3] == pytest.approx(0.99 * 20.0, rel=1e-6)
    np.testing.assert_array_equal(res.points[0, :3], np.float32([0.0, 30.0, 0.0]))


def test_partial_overlap_matches_the_lens_area():
    beams = _beams([0, 0, 0], [0, 0, 1], 30.0, 20.0)
    w = 10.0 * math.tan(1.5e-3)
    a, c = 0.5 * w, 1.0 * w  # radius w/2 centred on the beam edge
    parts = _particles([c, 0.0, 10.0], 2 * a)
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    # circle–circle intersection of radii 1 and 0.5 at distance 1, over π
    r1, r2, dist = 1.0, 0.5, 1.0
    lens = (r1 ** 2 * math.acos((dist ** 2 + r1 ** 2 - r2 ** 2) / (2 * dist * r1))
            + r2 ** 2 * math.acos((dist ** 2 + r2 ** 2 - r1 ** 2) / (2 * dist * r2))
            - 0.5 * math.sqrt((-dist + r1 + r2) * (dist + r1 - r2) * (dist - r1 + r2) * (dist + r1 + r2)))
    assert res.hits.ratio[0] == pytest.approx(lens / math.pi, rel=1e-9)


def test_nearest_particle_shadows_the_ones_behind():
    beams = _beams([0, 0, 0], [1, 0, 0], 40.0, 20.0)
    w5 = 5.0 * math.tan(1.5e-3)
    parts = _particles([[5.0, 0, 0], [8.0, 0, 0]], [4 * w5, 1e-2], ids=[1, 2])  # the first covers everything
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    assert dict(zip(res.hits.particle_id, res.hits.ratio)) == {1: 1.0, 2: 0.0}
    assert res.input_labels[0] == ParticleLabel.SCATTERED and res.particle_id[0] == 1


def test_particle_behind_the_target_changes_nothing():
    beams = _beams([0, 0, 0], [1, 0, 0], 30.0, 20.0)
    parts = _particles([[30.5, 0, 0], [45.0, 0, 0]], [0.02, 0.02])
    pts = np.array([[30.0, 0, 0, 20.0, 0.0]], dtype=np.float32)
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    assert len(res.hits) == 0
    assert res.points.tobytes() == pts.tobytes()
    assert res.input_labels.tolist() == [ParticleLabel.UNCHANGED]


def test_bulk_extinction_is_two_way_on_the_target():
    beams = _beams([0, 0, 0], [[1, 0, 0], [0, 1, 0]], [10.0, 40.0], 50.0)
    res = simulate_particle_list(beams, _particles(np.zeros((0, 3)), np.zeros(0)), (0, 0, 0), lidar=LIDAR,
                                 reflectivity=SNOW_REFLECTIVITY, extinction=0.01)
    np.testing.assert_allclose(res.points[:, 3], 50.0 * np.exp(-2 * 0.01 * np.array([10.0, 40.0])), rtol=1e-6)
    assert res.input_labels.tolist() == [ParticleLabel.ATTENUATED] * 2


def test_empty_field_and_zero_density_give_the_input_back_exactly(tiny_scan):
    scan = tiny_scan
    empty = ParticleField(1, ExponentialSizeDistribution(0.0, 500.0, 0.0, 0.02))
    for fld in (None, empty):
        res = simulate_particles(scan, fld, lidar=LIDAR_100M, reflectivity=SNOW_REFLECTIVITY)
        assert res.points.tobytes() == scan.points.tobytes()
        assert res.labels.tolist() == [ParticleLabel.UNCHANGED] * len(scan.points)
        assert res.counts["UNCHANGED"] == len(scan.points) and res.counts["CLUTTER"] == 0
        assert np.array_equal(res.source_index, np.arange(len(scan.points)))
    none = simulate_particle_list(scan, _particles(np.zeros((0, 3)), np.zeros(0)), (0, 0, 0), lidar=LIDAR_100M,
                                  reflectivity=SNOW_REFLECTIVITY)
    assert none.points.tobytes() == scan.points.tobytes()


# ----------------------------------------------------------------------------------------------- brute force


def _random_scene(seed: int, n_beams: int = 160):
    """A moving sensor (10 m/s over a 50 ms sweep) firing random beams into a thin, dense field of big particles."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(100.0, 100.05, n_beams))
    origins = np.stack([10.0 * (t - 100.0), np.zeros(n_beams), np.full(n_beams, 1.0)], axis=1)
    az = rng.uniform(-np.pi, np.pi, n_beams)
    el = rng.uniform(-0.12, 0.12, n_beams)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    has_ret = rng.random(n_beams) < 0.8
    lengths = rng.uniform(3.0, 14.0, n_beams)
    intensity = rng.uniform(2.0, 120.0, n_beams)
    beams = _beams(origins, d, lengths, intensity, times=t, has_return=has_ret, divergence=0.01, max_range=14.0)
    # ~40 particles per m³ of 4..30 mm (mean 10.7 mm): about 1.4 resolved hits per beam
    dist = ExponentialSizeDistribution(n0=40.0 * 150.0 * math.exp(150.0 * 4e-3), lam=150.0, d_min=4e-3, d_max=0.03)
    fld = ParticleField(seed, dist, velocity=(0.7, -0.3, -2.0), t_ref=100.0, z_min=-1.0, z_max=3.0, cell_size=1.0)
    return beams, fld


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_kernel_agrees_with_brute_force_on_random_scenes(seed):
    beams, fld = _random_scene(seed)
    # the field path (shells, reachable cells, time slices), everything resolved
    res = simulate_particles(beams, fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.0,
                             attenuation=False)
    fast = _fast_beam_view(res, beams)
    everything = fld.materialize([-15, -15, -1], [15.5, 15, 3], res.stats["t_ref"], min_diameter=0.0)
    naive = _naive(beams, everything, fld.velocity)
    _compare(fast, naive)
    # the explicit-list path on the same particles
    res2 = simulate_particle_list(beams, everything, fld.velocity, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    _compare(_fast_beam_view(res2, beams), naive)
    # enough happened to make the comparison meaningful
    labels = [x for x in naive["label"] if x != ParticleLabel.NO_ECHO]
    assert sum(x == ParticleLabel.SCATTERED for x in naive["label"]) >= 5
    assert sum(x == ParticleLabel.ATTENUATED for x in labels) >= 20
    assert sum(len(s) for s in naive["shares"]) >= 50
    assert sum(not b for b in naive["borderline"]) >= 0.9 * len(beams)


def test_thresholded_field_keeps_exactly_the_particles_above_each_shell_threshold():
    beams, fld = _random_scene(5)
    res = simulate_particles(beams, fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.03,
                             attenuation=False)
    full = simulate_particles(beams, fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.0,
                              attenuation=False)
    shells = res.stats["shells"]
    edges = np.array([s["s0"] for s in shells] + [shells[-1]["s1"]])
    thr = np.array([s["min_diameter"] for s in shells])
    assert thr.max() > fld.spectrum.d_min  # the threshold does drop particles here
    # every hit of the thresholded run is a hit of the full run, and the missing ones are below their threshold
    key = set(zip(res.hits.beam.tolist(), res.hits.particle_id.tolist()))
    key_full = set(zip(full.hits.beam.tolist(), full.hits.particle_id.tolist()))
    assert key <= key_full and len(key) < len(key_full)
    ids = np.array(sorted({p for _, p in key_full - key}), dtype=np.int64)
    center = 0.5 * (beams.origins.min(0) + beams.origins.max(0))
    pos = fld.positions_at(ids, res.stats["t_ref"])
    rho = np.linalg.norm(pos - center, axis=1)
    shell = np.searchsorted(edges, rho, side="right") - 1
    dia = fld.materialize(pos.min(0) - 1e-6, pos.max(0) + 1e-6, res.stats["t_ref"])
    dmap = dict(zip(dia.ids.tolist(), dia.diameters.tolist()))
    assert all(dmap[i] < thr[k] for i, k in zip(ids.tolist(), shell.tolist()))



def _later_scans(beams: Beams, n: int, dt: float = 0.05, speed: float = 10.0) -> list[Beams]:
    """``beams`` and ``n - 1`` copies fired ``dt`` [s] apart each by a sensor moving at ``speed`` [m/s] along x."""
    return [replace(beams, times=beams.times + k * dt, origins=beams.origins + [k * dt * speed, 0.0, 0.0])
            for k in range(n)]


@pytest.mark.parametrize("fog", [None, FogMedium(0.02, 0.002)])
def test_joint_scans_equal_separate_runs_when_every_particle_is_resolved(fog):
    beams, fld = _random_scene(3)
    scans = _later_scans(beams, 3)
    kw = dict(lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.0, attenuation=False, fog=fog)
    joint = simulate_particle_scans(scans, fld, **kw)
    assert len(joint) == 3
    for scan, res in zip(scans, joint):
        alone = simulate_particles(scan, fld, **kw)
        np.testing.assert_array_equal(res.hits.beam, alone.hits.beam)
        np.testing.assert_array_equal(res.hits.particle_id, alone.hits.particle_id)
        np.testing.assert_allclose(res.hits.range, alone.hits.range, atol=1e-9)
        np.testing.assert_array_equal(res.beam_label, alone.beam_label)
        np.testing.assert_array_equal(res.beam_particle, alone.beam_particle)
        np.testing.assert_array_equal(res.source_index, alone.source_index)
        np.testing.assert_allclose(res.points, alone.points, atol=1e-5)
        assert res.counts == alone.counts and res.stats["scans_joined"] == 3
    # the scans saw different particles at their own times, and something happened in each
    assert all(r.counts["SCATTERED"] + r.counts["CLUTTER"] > 0 for r in joint)
    assert joint[0].hits.particle_id.tolist() != joint[2].hits.particle_id.tolist()


def test_joint_scans_with_thresholds_resolve_each_scan_like_a_run_of_its_own():
    beams, fld = _random_scene(4, n_beams=400)
    scans = _later_scans(beams, 3)
    kw = dict(lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.01)
    joint = simulate_particle_scans(scans, fld, **kw)
    for scan, res in zip(scans, joint):
        alone = simulate_particles(scan, fld, **kw)
        # the same particles on the same beams, but the joint run's shells (centred on all scans' origins, with
        # thresholds for their wider spread) resolve more of the small ones, which the single run folds into the
        # bulk extinction: the echoes agree, the faint attenuation of the other beams differs slightly
        pairs = set(zip(res.hits.beam.tolist(), res.hits.particle_id.tolist()))
        alone_pairs = set(zip(alone.hits.beam.tolist(), alone.hits.particle_id.tolist()))
        assert len(pairs & alone_pairs) > 0.95 * len(alone_pairs) and len(pairs) >= len(alone_pairs)
        scattered = res.beam_label == ParticleLabel.SCATTERED
        assert scattered.sum() >= 40 and np.mean(scattered == (alone.beam_label == ParticleLabel.SCATTERED)) > 0.98
        kept = (res.beam_label != ParticleLabel.NO_ECHO) & (alone.beam_label != ParticleLabel.NO_ECHO)
        i_joint, i_alone = res.beam_intensity[kept & ~scattered], alone.beam_intensity[kept & ~scattered]
        assert np.mean(np.abs(i_joint / i_alone - 1.0) > 0.05) < 0.02


def test_joint_scans_must_come_from_one_sensor():
    beams, fld = _random_scene(0, n_beams=20)
    other = replace(beams, divergence=2 * beams.divergence)
    with pytest.raises(ValueError, match="scan 1: beams of divergence"):
        simulate_particle_scans([beams, other], fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)
    with pytest.raises(ValueError, match="no scans"):
        simulate_particle_scans([], fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY)


# ---------------------------------------------------------------------------------------------------- motion


def test_a_field_particle_is_hit_where_it_is_at_the_beams_firing_time():
    dist = ExponentialSizeDistribution(n0=2.0e3 * 300.0, lam=300.0, d_min=8e-3, d_max=0.03)
    fld = ParticleField(3, dist, velocity=(1.0, 0.5, -2.0), t_ref=0.0, z_min=-1.0, z_max=3.0, cell_size=1.0)
    t0, t1 = 0.0, 0.04
    near = fld.materialize([4, -1, 0.5], [6, 1, 1.5], t0)
    pid = int(near.ids[0])
    p0, p1 = fld.positions_at(np.array([pid]), t0)[0], fld.positions_at(np.array([pid]), t1)[0]
    np.testing.assert_allclose(p1 - p0, np.asarray(fld.velocity) * (t1 - t0), atol=1e-12)
    origin = np.array([0.0, 0.0, 1.0])
    # two beams aimed at where the particle is at t1; one fires at t1, the other at t0
    d = (p1 - origin) / np.linalg.norm(p1 - origin)
    beams = _beams([origin, origin], [d, d], 20.0, 30.0, times=[t1, t0], divergence=1e-3, max_range=20.0)
    res = simulate_particles(beams, fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.0,
                             attenuation=False)
    hit_ids = {int(b): set() for b in range(2)}
    for b, p in zip(res.hits.beam, res.hits.particle_id):
        hit_ids[int(b)].add(int(p))
    assert pid in hit_ids[0]
    assert pid not in hit_ids[1]  # at t0 the particle is 4 cm away from that line
    r = res.hits.range[(res.hits.beam == 0) & (res.hits.particle_id == pid)][0]
    assert r == pytest.approx(np.linalg.norm(p1 - origin), abs=1e-9)


# ---------------------------------------------------------------------------------------- beams without return


def test_clutter_on_a_beam_without_return():
    beams = _beams([0, 0, 0], [[1, 0, 0], [0, 1, 0]], 0.0, 0.0, has_return=[False, False], max_range=50.0)
    w = 6.0 * math.tan(1.5e-3)
    parts = _particles([[6.0, 0.0, 0.0]], [2 * w], ids=[42])  # fills the first beam at 6 m
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY,
                                 intensity_max=255.0)
    assert res.counts["CLUTTER"] == 1 and len(res.points) == 1
    assert res.source_index.tolist() == [-1] and res.particle_id.tolist() == [42]
    assert res.labels.tolist() == [ParticleLabel.SCATTERED]
    np.testing.assert_allclose(res.points[0, :3], [6.0, 0.0, 0.0], atol=1e-5)
    assert res.points[0, 3] == pytest.approx(255 * SNOW_REFLECTIVITY, rel=1e-6)  # full coverage, g(6 m) = 1
    assert res.points[0, 4] == beams.ring[0]
    assert res.beam_label.tolist() == [ParticleLabel.SCATTERED, ParticleLabel.NO_ECHO]  # the second stays empty


def test_one_label_enum_for_fog_snow_and_rain():
    assert ParticleLabel is WeatherLabel and FogLabel is WeatherLabel
    assert [(x.name, int(x)) for x in WeatherLabel] == [("UNCHANGED", 0), ("ATTENUATED", 1), ("SCATTERED", 2),
                                                        ("LOST", 3), ("NO_ECHO", 4), ("GROUND", 5)]
    assert WeatherLabel.NO_ECHO not in POINT_LABELS and WeatherLabel.GROUND not in POINT_LABELS
    assert len(POINT_LABELS) == 4


def test_rain_scatters_less_than_snow():
    beams, fld = _random_scene(7, n_beams=300)
    snow = simulate_particles(beams, fld, lidar=LIDAR, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=0.0)
    rain = simulate_particles(beams, fld, lidar=LIDAR, reflectivity=RAIN_REFLECTIVITY, ratio_threshold=0.0)
    scattered = [r.counts["SCATTERED"] + r.counts["CLUTTER"] for r in (snow, rain)]
    assert scattered[0] > 2 * scattered[1] > 0
    # the occlusion is the same geometry; only the echoes differ
    np.testing.assert_allclose(snow.hits.ratio, rain.hits.ratio)


def test_determinism_same_seed_same_bytes_other_seed_differs(tiny_scan):
    f = ParticleField(5, SnowSizeDistribution(2.0, 1.5), velocity=fall_velocity(1.5), t_ref=tiny_scan.timestamp)
    a = simulate_particles(tiny_scan, f, lidar=LIDAR_100M, reflectivity=SNOW_REFLECTIVITY, ratio_threshold=3e-3)
    b = simulate_particles(tiny_scan, replace(f), lidar=LIDAR_100M, reflectivity=SNOW_REFLECTIVITY,
                           ratio_threshold=3e-3)
    c = simulate_particles(tiny_scan, replace(f, seed=6), lidar=LIDAR_100M, reflectivity=SNOW_REFLECTIVITY,
                           ratio_threshold=3e-3)
    assert a.points.tobytes() == b.points.tobytes() and a.particle_id.tobytes() == b.particle_id.tobytes()
    assert a.points.tobytes() != c.points.tobytes()


# ------------------------------------------------------------------------------------------ the sensor, explicit


def test_no_default_sensor_a_missing_lidar_is_a_type_error():
    beams, fld = _random_scene(0, n_beams=10)
    parts = _particles([[6.0, 0.0, 0.0]], [0.01])
    scan = LidarScan(points=np.array([[10.0, 0.0, 0.0, 20.0, 0.0]], np.float32), timestamp=0.0,
                     T_ego_lidar=np.eye(4), T_global_ego=np.eye(4))
    with pytest.raises(TypeError, match="lidar"):
        simulate_particles(beams, fld, reflectivity=SNOW_REFLECTIVITY)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="lidar"):
        simulate_particles(scan, fld, reflectivity=SNOW_REFLECTIVITY)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="lidar"):
        simulate_particle_list(beams, parts, (0, 0, 0), reflectivity=SNOW_REFLECTIVITY)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="lidar"):
        beams_from_scan(scan)  # type: ignore[call-arg]
    # nor a default particle reflectivity
    with pytest.raises(TypeError, match="reflectivity"):
        simulate_particles(beams, fld, lidar=LIDAR)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="reflectivity"):
        simulate_particle_list(beams, parts, (0, 0, 0), lidar=LIDAR)  # type: ignore[call-arg]


def test_the_explicit_sensor_is_honoured(tiny_scan):
    """Every sensor fact comes from the `LidarModel` passed in: maximum range (the length of beams without return),
    divergence, firing grid, pulse saturation, intensity model and noise floor."""
    scan = tiny_scan
    near = beams_from_scan(scan, lidar=make_lidar(max_range_m=100.0))
    far = beams_from_scan(scan, lidar=make_lidar(max_range_m=150.0, divergence_rad=1e-3))
    none_n, none_f = ~near.has_return, ~far.has_return
    assert none_n.sum() > 1000 and np.array_equal(near.has_return, far.has_return)
    assert (near.lengths[none_n] == 100.0).all() and (far.lengths[none_f] == 150.0).all()  # longer beams
    np.testing.assert_array_equal(near.lengths[~none_n], far.lengths[~none_f])  # returns keep their range
    assert (near.max_range, far.max_range) == (100.0, 150.0)
    assert (near.divergence, far.divergence) == (3e-3, 1e-3)
    # the firing grid is the sensor's (used where it stores per-point columns); otherwise ring gaps are reconstructed
    assert len(near) == 32 * 1085
    assert len(beams_from_scan(scan, lidar=make_lidar(columns_per_ring=2 * 1085))) == 32 * 2 * 1085
    rebuilt = beams_from_scan(scan, lidar=make_lidar(firing_columns_stored=False))
    assert len(rebuilt) == len(scan.points) + len(reconstruct_no_return_beams(scan))
    # pulse, intensity model and floor: a flake filling a beam without return at 6 m
    beams = _beams([0, 0, 0], [1, 0, 0], 0.0, 0.0, has_return=[False], max_range=50.0)
    parts = _particles([[6.0, 0.0, 0.0]], [2 * 6.0 * math.tan(1.5e-3)], ids=[42])

    def clutter(lidar: LidarModel):
        return simulate_particle_list(beams, parts, (0, 0, 0), lidar=lidar, reflectivity=SNOW_REFLECTIVITY)

    assert clutter(LIDAR).points[0, 3] == pytest.approx(255 * SNOW_REFLECTIVITY, rel=1e-6)  # g(6 m) = 1
    saturated = clutter(make_lidar(pulse=PulseSensor(tau_h=10e-9, saturation=100.0)))
    assert saturated.points[0, 3] == pytest.approx(100.0)
    hahner = clutter(make_lidar(intensity=HAHNER_INTENSITY))
    assert hahner.points[0, 3] == pytest.approx(255 * SNOW_REFLECTIVITY / 36.0, rel=1e-6)  # raw 1/r² at 6 m
    floored = clutter(make_lidar(intensity=HAHNER_INTENSITY, noise_floor=10.0))  # 5.7 < 10: not detected
    assert floored.counts["CLUTTER"] == 0 and floored.beam_label.tolist() == [ParticleLabel.NO_ECHO]


# ---------------------------------------------------------------------------------------------- scans


@pytest.fixture(scope="module")
def tiny_scan(tiny_world) -> LidarScan:
    nusc = open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)
    return load_lidar(nusc, nusc.sample[0]["data"]["LIDAR_TOP"])


def _check_sane(res, scan: LidarScan, beams: Beams) -> None:
    pts = res.points
    assert pts.dtype == np.float32 and pts.shape[1] == 5 and np.isfinite(pts).all()
    n_kept = int((res.source_index >= 0).sum())
    assert n_kept + res.counts["LOST"] == len(scan.points)
    assert sum(res.counts[k] for k in ("UNCHANGED", "ATTENUATED", "SCATTERED", "LOST")) == len(scan.points)
    # ring column intact; clutter rings are rings of the sensor
    src = res.source_index
    np.testing.assert_array_equal(pts[src >= 0, 4], scan.points[src[src >= 0], 4])
    assert set(np.unique(pts[src < 0, 4]).tolist()) <= set(np.unique(beams.ring).tolist())
    # intensities on the scan's scale
    assert pts[:, 3].min() >= 0.0 and pts[:, 3].max() <= scan.intensity_max
    # every point on its beam, in front of the sensor and within the maximum range
    T = scan.T_global_lidar
    p_g = pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    beam_of = {int(p): i for i, p in enumerate(beams.point_index) if p >= 0}
    rows = np.flatnonzero(src >= 0)
    b = np.array([beam_of[int(s)] for s in src[rows]])
    rel = p_g[rows] - beams.origins[b]
    along = (rel * beams.directions[b]).sum(1)
    assert along.min() > 0.0 and along.max() <= beams.max_range + 1e-3
    moved = res.labels[rows] == ParticleLabel.SCATTERED
    assert (along[moved] <= beams.lengths[b[moved]] + 1e-3).all()  # moved towards the sensor only
    kept = ~moved
    np.testing.assert_array_equal(pts[rows[kept], :3], scan.points[src[rows[kept]], :3])
    clutter = np.flatnonzero(src < 0)
    assert (res.particle_id[clutter] >= 0).all() and (res.particle_id[rows[moved]] >= 0).all()
    r_c = np.linalg.norm(p_g[clutter] - T[:3, 3], axis=1)
    assert (r_c <= beams.max_range + 1.0).all()


def test_synthetic_world_scan_beams_and_weather(tiny_scan):
    scan = tiny_scan
    cols = synthetic_columns(scan)
    assert cols is not None and len(cols) == len(scan.points)
    beams = beams_from_scan(scan, lidar=LIDAR_100M)
    assert len(beams) == 32 * 1085  # every cell of the firing grid, returns and no-returns
    rc = set(zip(scan.points[:, 4].astype(int).tolist(), cols.tolist()))
    assert len(rc) == len(scan.points)
    # returns: from the origin at firing time through the point; directions unit
    np.testing.assert_allclose(np.linalg.norm(beams.directions, axis=1), 1.0, atol=1e-12)
    assert (np.diff(beams.times[beams.has_return]) != 0).any()
    snow = ParticleField(2, SnowSizeDistribution(2.0, 1.5), velocity=fall_velocity(1.5), t_ref=scan.timestamp)
    rain = ParticleField(2, RainSizeDistribution(50.0), velocity=fall_velocity(2.0), t_ref=scan.timestamp,
                         cell_size=1.0)
    res_s = simulate_particles(scan, snow, lidar=LIDAR_100M, reflectivity=SNOW_REFLECTIVITY)
    res_r = simulate_particles(scan, rain, lidar=LIDAR_100M, reflectivity=RAIN_REFLECTIVITY)
    for res in (res_s, res_r):
        _check_sane(res, scan, beams)
        assert res.counts["ATTENUATED"] > 0.5 * len(scan.points)
    assert res_s.counts["SCATTERED"] + res_s.counts["CLUTTER"] > res_r.counts["SCATTERED"] + res_r.counts["CLUTTER"]
    assert res_s.counts["CLUTTER"] > 0
    out = res_s.apply_to(scan)
    assert len(out.points) == len(res_s.points) and out.time_offsets is not None
    assert (out.time_offsets <= 0).all() and (out.time_offsets >= -0.051).all()


def test_reconstructed_no_return_beams_fill_the_ring_gaps():
    """A 360° 8-ring scan with every 9th column missing on ring 3 and a 20-column gap on ring 5."""
    rings, cols = 8, 720
    el = np.radians(np.linspace(2.0, -12.0, rings))
    az = np.pi / 2 - 2 * np.pi * (np.arange(cols) + 0.5) / cols
    ring = np.repeat(np.arange(rings), cols)
    column = np.tile(np.arange(cols), rings)
    d = np.stack([np.cos(el[ring]) * np.cos(az[column]), np.cos(el[ring]) * np.sin(az[column]), np.sin(el[ring])], 1)
    drop = ((ring == 3) & (column % 9 == 4)) | ((ring == 5) & (column >= 100) & (column < 120))
    pts = np.concatenate([d * 20.0, np.full((len(d), 1), 30.0), ring[:, None]], axis=1).astype(np.float32)
    scan = LidarScan(points=pts[~drop], timestamp=5.0, T_ego_lidar=np.eye(4), T_global_ego=np.eye(4),
                     num_rings=rings)
    nr = reconstruct_no_return_beams(scan)
    assert len(nr) == int(drop.sum())
    expect = d[drop]
    cos = nr.directions @ expect.T
    assert (cos.max(axis=1) > math.cos(1e-4)).all()  # each reconstructed beam is a dropped one
    assert sorted(nr.ring.tolist()) == sorted(ring[drop].astype(np.float32).tolist())
    assert (nr.time_offsets <= 0).all() and (nr.time_offsets >= -0.05).all()


# ---------------------------------------------------------------------------------------------- real scans


def _real_scans():
    out = []
    if (REAL / "stf").is_dir():
        from weatheralign.data.stf import load_stf_frame

        out.append(("stf", load_stf_frame(REAL / "stf", STF_ID, camera_folder=None).lidar, HAHNER_INTENSITY))
    if (REAL / "kitti").is_dir():
        from weatheralign.data.kitti import load_kitti_frame

        out.append(("kitti", load_kitti_frame(REAL / "kitti" / "000008.bin", None, REAL / "kitti" / "calib.json").lidar,
                    CALIBRATED_INTENSITY))
    return out


@pytest.mark.parametrize("scale", [255.0, 1.0])
def test_real_stf_and_kitti_scans_sane_in_either_intensity_scale(scale):
    scans = _real_scans()
    if not scans:
        pytest.skip("../shared/data/real is absent")
    for name, scan, model in scans:
        if scan.intensity_max != scale:  # the same scan on the other scale
            pts = scan.points.copy()
            pts[:, 3] *= np.float32(scale / scan.intensity_max)
            scan = replace(scan, points=pts, intensity_max=scale)
        # 120 m, 3 mrad, τ_H = 10 ns, floor 0.5, the scan's intensity model; no stored firing columns (real data):
        # the beams without return are reconstructed from the ring structure
        lidar = make_lidar(intensity=model, firing_columns_stored=False)
        beams = beams_from_scan(scan, lidar=lidar)
        assert len(beams) > len(scan.points)  # the sky and the dark gaps hold beams without return
        snow = ParticleField(4, SnowSizeDistribution(2.0, 1.5), velocity=fall_velocity(1.5), t_ref=0.0)
        rain = ParticleField(4, RainSizeDistribution(50.0), velocity=fall_velocity(2.0), t_ref=0.0, cell_size=1.0)
        for fld, refl in ((snow, SNOW_REFLECTIVITY), (rain, RAIN_REFLECTIVITY)):
            res = simulate_particles(scan, fld, lidar=lidar, reflectivity=refl)
            _check_sane(res, scan, beams)
            assert res.counts["ATTENUATED"] + res.counts["UNCHANGED"] > 0.8 * len(scan.points), name
        # either scale gives the same geometry and labels
        if scale == 1.0:
            other = replace(scan, points=np.column_stack([scan.points[:, :3], scan.points[:, 3] * 255.0,
                                                          scan.points[:, 4]]).astype(np.float32), intensity_max=255.0)
            a = simulate_particles(scan, snow, lidar=lidar, reflectivity=SNOW_REFLECTIVITY)
            b = simulate_particles(other, snow, lidar=lidar, reflectivity=SNOW_REFLECTIVITY)
            same = lambda x: np.where(x == ParticleLabel.UNCHANGED, ParticleLabel.ATTENUATED, x)  # noqa: E731
            np.testing.assert_array_equal(same(a.input_labels), same(b.input_labels))
            np.testing.assert_allclose(a.points[:, 3] * 255.0, b.points[:, 3], rtol=1e-5, atol=1e-4)


def _slice_table_loop(az0, span, n_bins):
    """The slice look-up table by its definition, one slice and bin at a time (the slow reference)."""
    from weatheralign.lidar.particles.beam_index import _CONVEX_SPAN

    d_tb = 2 * math.pi / n_bins
    lists: list[list[int]] = [[] for _ in range(n_bins)]
    for k in range(len(az0)):
        if span[k] > _CONVEX_SPAN:
            bins = range(n_bins)
        else:
            b0 = int(math.floor((az0[k] + math.pi) / d_tb)) - 1
            b1 = int(math.floor((az0[k] + span[k] + math.pi) / d_tb)) + 1
            bins = sorted({b % n_bins for b in range(b0, b1 + 1)})
        for b in bins:
            lists[b].append(k)
    offsets = np.zeros(n_bins + 1, dtype=np.int64)
    np.cumsum([len(x) for x in lists], out=offsets[1:])
    return offsets, np.array([k for x in lists for k in x], dtype=np.int64)


def test_slice_table_equals_its_definition():
    """The vectorised azimuth look-up table equals the per-slice loop: wrap-around at ±π, wide (convex) slices in
    every bin, spans covering more bins than there are, slices ascending within each bin."""
    from weatheralign.lidar.particles.beam_index import _slice_table

    rng = np.random.default_rng(0)
    for _ in range(100):
        n, n_bins = int(rng.integers(1, 300)), int(rng.integers(4, 2000))
        az0 = rng.uniform(-math.pi, math.pi, n)
        span = rng.choice([0.0, 0.01, 0.5, 3.0, 3.2, 6.0], n) * rng.uniform(0, 1, n)
        span[rng.uniform(size=n) < 0.05] = 4.0
        got, want = _slice_table(az0, span, n_bins), _slice_table_loop(az0, span, n_bins)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_detector_noise_decides_weak_particle_echoes_with_the_gaussian_probability():
    """A particle echo of peak v (0..255) under detector noise σ and floor f is detected with probability
    Φ((v - f) / σ); the detected intensities are v + σ z truncated at f, the ranges carry the clipped range noise, and
    a beam without a particle keeps its clear return bit for bit (its noise is in the clear measurement already)."""
    from scipy.stats import norm

    n, s_p, floor, sigma, sigma_r = 4000, 10.0, 2.0, 1.0, 0.05
    w = s_p * math.tan(1.5e-3)
    v = 3.0  # the echo's noise-free peak: 255 · 0.9 · ratio at 10 m (g = 1)
    ratio = v / (255.0 * SNOW_REFLECTIVITY)
    beams = _beams([0, 0, 0], np.tile([1.0, 0, 0], (n, 1)), 60.0, 0.0, times=np.arange(n) * 1e-5,
                   has_return=np.zeros(n, bool))
    parts = _particles([s_p, 0.0, 0.0], 2 * w * math.sqrt(ratio))
    quiet = simulate_particle_list(beams, parts, (0, 0, 0), lidar=make_lidar(noise_floor=floor),
                                   reflectivity=SNOW_REFLECTIVITY)
    assert len(quiet.points) == quiet.counts["CLUTTER"] == n  # beams without return: the echoes are clutter
    np.testing.assert_allclose(quiet.points[:, 3], v, rtol=1e-6)  # every beam: the same noise-free echo
    noisy_lidar = make_lidar(noise_floor=floor, intensity_noise_std=sigma, range_noise_std_m=sigma_r)
    res = simulate_particle_list(beams, parts, (0, 0, 0), lidar=noisy_lidar, reflectivity=SNOW_REFLECTIVITY)
    p_detect = norm.sf((floor - v) / sigma)
    detected = len(res.points) / n
    assert abs(detected - p_detect) < 4 * math.sqrt(p_detect * (1 - p_detect) / n)
    inten = res.points[:, 3].astype(np.float64)
    assert inten.min() >= floor
    z0 = (floor - v) / sigma  # E[v + σ z | z >= z0] = v + σ φ(z0) / (1 - Φ(z0))
    expected_mean = v + sigma * norm.pdf(z0) / norm.sf(z0)
    assert abs(inten.mean() - expected_mean) < 4 * inten.std() / math.sqrt(len(inten))
    ranges = np.linalg.norm(res.points[:, :3].astype(np.float64), axis=1)
    assert np.all(np.abs(ranges - s_p) <= 2 * sigma_r + 1e-4)
    clipped_std = sigma_r * math.sqrt(1 - 4 * norm.pdf(2) / (norm.cdf(2) - norm.cdf(-2)))  # N(0, 1) within ±2
    assert abs(ranges.std() - clipped_std) < 0.1 * clipped_std
    again = simulate_particle_list(beams, parts, (0, 0, 0), lidar=noisy_lidar, reflectivity=SNOW_REFLECTIVITY)
    np.testing.assert_array_equal(again.points, res.points)  # the noise is the beam's: same beams, same bytes
    target = _beams([0, 0, 0], np.tile([1.0, 0, 0], (3, 1)), 30.0, 20.0, times=np.arange(3) * 1e-5)
    clear = simulate_particle_list(target, _particles([5.0, 5.0, 5.0], 1e-3), (0, 0, 0), lidar=noisy_lidar,
                                   reflectivity=SNOW_REFLECTIVITY)
    assert np.all(clear.input_labels == ParticleLabel.UNCHANGED)


# ------------------------------------------------------------------------------ the unresolved particles' echo


def _brute_continuum(length: float, cross_section: float, extinction: float, lidar: LidarModel, rho: float
                     ) -> tuple[float, float]:
    """(peak, position on the receiver axis) of ``∫_0^{min(R, L)} a(s) sin²(π (R - s) / c τ_H) ds`` by direct sums
    on a 0.5 mm grid in s and a 1 mm grid in R (the slow reference of `unresolved_continuum`)."""
    sensor, model = lidar.pulse, lidar.intensity
    pl = sensor.pulse_length
    h = 5e-4
    s = np.arange(h / 2, min(length, 40.0), h)
    xi = np.clip((s - sensor.r1) / (sensor.r2 - sensor.r1), 0.0, 1.0)
    a = model.scale * rho * cross_section * xi / s ** 2 * np.exp(-2.0 * extinction * s)
    R = np.arange(0.0, min(length, 40.0) + pl, 1e-3)
    best, at = -1.0, 0.0
    for r in R:
        m = (s <= r) & (s >= r - pl)
        w = float(np.sum(a[m] * np.sin(np.pi * (r - s[m]) / pl) ** 2) * h)
        if w > best:
            best, at = w, r
    return best, at


@pytest.mark.parametrize("length", [0.95, 1.6, 3.0, 6.5, 60.0])
def test_unresolved_continuum_is_the_peak_of_the_brute_force_waveform(length):
    from weatheralign.lidar.particles.api import _Options, unresolved_continuum

    opt = _Options.of(LIDAR, RAIN_REFLECTIVITY, KEEP)
    cont = unresolved_continuum(np.array([0.0, 100.0]), np.array([3e-3]), np.array([0.02]), opt)
    i = min(int(length / cont.step), len(cont.peak) - 1)
    want, at = _brute_continuum(cont.step * i, 3e-3, 0.02, LIDAR, RAIN_REFLECTIVITY)
    assert cont.peak[i] == pytest.approx(want, rel=5e-3)  # 2 cm cells on the 10 cm overlap ramp
    assert cont.peak_r[i] == pytest.approx(at, abs=0.03)
    # the table ends past the untruncated peak: longer beams take its last entry, the global maximum
    full, _ = _brute_continuum(60.0, 3e-3, 0.02, LIDAR, RAIN_REFLECTIVITY)
    assert cont.peak[-1] == pytest.approx(full, rel=2e-3) and cont.peak.max() == cont.peak[-1]


def test_the_unresolved_echo_masks_a_fainter_far_particle_and_is_read_like_one():
    """A strongest-return receiver reports the strongest crest of everything it receives: behind the unresolved
    particles' continuum (peak a few metres out) a faint particle at 12 m is not reported; without the continuum it
    is; a bright target beats the continuum. The continuum's echo carries no particle id and the table's intensity."""
    lidar = make_lidar(noise_floor=0.0)
    beams = _beams([0, 0, 0], [[1, 0, 0], [0, 1, 0], [0, -1, 0]], [0.0, 0.0, 30.0], [0.0, 0.0, 40.0],
                   has_return=[False, False, True], max_range=50.0)
    w = 12.0 * math.tan(1.5e-3)
    parts = _particles([[12.0, 0.0, 0.0]], [2 * w * 0.3], ids=[7])  # 9 % of the first beam at 12 m
    bare = simulate_particle_list(beams, parts, lidar=lidar, reflectivity=RAIN_REFLECTIVITY, intensity_max=255.0)
    assert bare.beam_particle.tolist() == [7, -1, -1]
    assert bare.beam_range[0] == pytest.approx(12.0, abs=1e-6)
    res = simulate_particle_list(beams, parts, lidar=lidar, reflectivity=RAIN_REFLECTIVITY, intensity_max=255.0,
                                 unresolved_cross_section=0.02)
    from weatheralign.lidar.particles.api import _Options, unresolved_continuum

    cont = unresolved_continuum(np.array([0.0, 31.0]), np.array([0.02]), np.array([0.0]),
                                _Options.of(lidar, RAIN_REFLECTIVITY, KEEP))
    r_c = cont.peak_r[-1] - 0.5 * lidar.pulse.pulse_length
    assert res.beam_label.tolist() == [ParticleLabel.SCATTERED, ParticleLabel.SCATTERED, ParticleLabel.UNCHANGED]
    assert res.beam_particle.tolist() == [-1, -1, -1]
    np.testing.assert_allclose(res.beam_range[:2], r_c, atol=1e-9)
    want = cont.peak[-1] * r_c ** 2 * float(lidar.intensity.gain(r_c))
    # the particle's pulse (12..18 m on the receiver axis) does not reach the continuum's crest (~7 m)
    np.testing.assert_allclose(res.beam_intensity[:2], want, rtol=1e-9)
    assert res.beam_range[2] == 30.0


def test_weather_echoes_nearer_than_the_minimum_range_are_not_reported():
    """A particle filling the beam at 0.95 m, inside a 1 m minimum range: the sensor reports nothing there (the
    target behind it decides); with a 0.5 m minimum range the particle is reported."""
    beams = _beams([0, 0, 0], [[1, 0, 0], [0, 1, 0]], [20.0, 0.0], [30.0, 0.0], has_return=[True, False],
                   max_range=50.0)
    w = 0.95 * math.tan(1.5e-3)
    parts = _particles([[0.95, 0.0, 0.0], [0.0, 0.95, 0.0]], [0.6 * w, 2.2 * w], ids=[1, 2])
    out = {}
    for min_range in (1.0, 0.5):
        lidar = make_lidar(noise_floor=0.5, min_range_m=min_range)
        out[min_range] = simulate_particle_list(beams, parts, lidar=lidar, reflectivity=SNOW_REFLECTIVITY,
                                                intensity_max=255.0)
    near = out[0.5]
    assert near.beam_label.tolist() == [ParticleLabel.SCATTERED, ParticleLabel.SCATTERED]
    assert np.all(near.beam_range < 1.0)
    far = out[1.0]
    assert far.beam_label.tolist() == [ParticleLabel.ATTENUATED, ParticleLabel.NO_ECHO]
    assert far.beam_range[0] == 20.0


def _ring_beams(ranges, intensities, rings=None) -> Beams:
    """Beams of consecutive firings along +x..+y (0.2° apart) from the origin; nan range = no return."""
    r = np.asarray(ranges, dtype=np.float64)
    n = len(r)
    az = np.radians(0.2 * np.arange(n))
    d = np.stack([np.cos(az), np.sin(az), np.zeros(n)], 1)
    has = np.isfinite(r)
    pidx = np.full(n, -1)
    pidx[has] = np.arange(int(has.sum()))
    ring = np.zeros(n, np.float32) if rings is None else np.asarray(rings, np.float32)
    return Beams(np.zeros((n, 3)), d, 1e-4 * np.arange(n), np.where(has, r, 100.0), has,
                 np.where(has, np.asarray(intensities, np.float64), 0.0), ring, pidx, 3e-3, 100.0)


def test_faint_surfaces_fill_short_runs_between_returns_of_a_surface_at_the_floor():
    from weatheralign.lidar.beams import MAX_FAINT_RUN, with_faint_surfaces

    nan = np.nan
    #            surface at the floor, 3 missing       | bright | far apart | run too long             | other ring
    ranges = [30.0, 30.2, nan, nan, nan, 31.0, 20.0, nan, 20.0, 10.0, nan, 14.0, 15.0] + [nan] * (MAX_FAINT_RUN + 1) \
        + [15.0, 15.0, nan]
    inten = [1.2, 1.5, 0, 0, 0, 2.0, 50.0, 0, 50.0, 1.0, 0, 1.0, 1.0] + [0] * (MAX_FAINT_RUN + 1) + [1.0, 1.0, 0]
    rings = [0] * (len(ranges) - 1) + [1]
    beams = _ring_beams(ranges, inten, rings)
    out = with_faint_surfaces(beams, noise_floor=1.0)
    np.testing.assert_allclose(out.lengths[2:5], [30.4, 30.6, 30.8])
    np.testing.assert_allclose(out.intensity0[2:5], 0.5)
    untouched = np.r_[7, 10, np.arange(13, 13 + MAX_FAINT_RUN + 1), len(ranges) - 1]
    np.testing.assert_array_equal(out.lengths[untouched], 100.0)
    np.testing.assert_array_equal(out.intensity0[untouched], 0.0)
    np.testing.assert_array_equal(out.has_return, beams.has_return)
    assert with_faint_surfaces(beams, noise_floor=None) is beams


def test_a_faint_surface_hides_a_weaker_particle_echo_in_front_of_it():
    """A strongest-return receiver whose strongest echo is an undetectable surface reports nothing: a faint drop
    echo in front of it stays unreported, while on an open beam the same drop is the echo (floor 0, noise-free)."""
    lidar = make_lidar(noise_floor=0.0)
    hidden = _beams([0, 0, 0], [[1, 0, 0]], 30.0, 0.5, has_return=[False], max_range=50.0)
    hidden = Beams(hidden.origins, hidden.directions, hidden.times, np.array([30.0]), hidden.has_return,
                   np.array([0.5]), hidden.ring, hidden.point_index, hidden.divergence, hidden.max_range)
    w = 12.0 * math.tan(1.5e-3)
    parts = _particles([[12.0, 0.0, 0.0]], [2 * w * math.sqrt(0.02)], ids=[3])  # 2 % of the beam at 12 m
    sky = simulate_particle_list(replace(hidden, lengths=np.array([50.0]), intensity0=np.array([0.0])), parts,
                                 lidar=lidar, reflectivity=RAIN_REFLECTIVITY, intensity_max=255.0)
    assert sky.beam_label.tolist() == [ParticleLabel.SCATTERED] and sky.beam_particle.tolist() == [3]
    res = simulate_particle_list(hidden, parts, lidar=lidar, reflectivity=RAIN_REFLECTIVITY, intensity_max=255.0)
    assert res.beam_label.tolist() == [ParticleLabel.NO_ECHO] and len(res.points) == 0


def test_noise_keys_ignore_ulp_differences_of_a_direction_and_tell_beams_apart():
    """A beam's detector-noise key survives its direction being computed a few ULPs differently (reconstructed beams
    without return differed by up to 8.9e-16 between processes on the same input, which had changed their noise
    draws and the copy's bytes); beams that differ in direction, ring or time get different keys."""
    from weatheralign.lidar.beams import detector_noise_keys
    rng = np.random.default_rng(5)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    times = np.full(len(d), 1.5e9 + 0.25)
    ring = rng.integers(0, 64, len(d)).astype(np.float32)
    keys = detector_noise_keys(times, d, ring)
    wobbled = d.copy()
    for _ in range(4):
        wobbled = np.nextafter(wobbled, np.where(rng.random(d.shape) < 0.5, -np.inf, np.inf))
    assert np.abs(wobbled - d).max() > 0.0
    assert np.array_equal(detector_noise_keys(times, wobbled, ring), keys)
    assert len(np.unique(keys)) == len(keys)
    step = d.copy()
    step[:, 0] += 1e-3  # a neighbouring beam of the same laser at the same time
    assert not np.any(detector_noise_keys(times, step, ring) == keys)
    assert not np.any(detector_noise_keys(times, d, ring + 1) == keys)
    assert not np.any(detector_noise_keys(np.nextafter(times, np.inf), d, ring) == keys)


# ------------------------------------------------------------------- readings at the floor, the road under it


def test_fast_kernel_agrees_with_brute_force_on_rounded_readings_at_the_floor():
    """Integer clear readings of 1..3 at a floor of 1 behind rain drops: the kernel's kept-or-lost decisions on the
    clear values the readings stood for (`beam_clear_readings`) are the brute force's on the same values."""
    from weatheralign.lidar.particles.api import beam_clear_readings

    beams, fld = _random_scene(7)
    rng = np.random.default_rng(7)
    beams = replace(beams, intensity0=np.where(beams.has_return, rng.integers(1, 4, len(beams)), 0.0).astype(float))
    lidar = make_lidar(noise_floor=1.0)
    clear = beam_clear_readings(beams, 1.0)
    assert clear is not None and np.all(clear[beams.has_return] != beams.intensity0[beams.has_return])
    res = simulate_particles(beams, fld, lidar=lidar, reflectivity=RAIN_REFLECTIVITY, ratio_threshold=0.0,
                             attenuation=False)
    everything = fld.materialize([-15, -15, -1], [15.5, 15, 3], res.stats["t_ref"], min_diameter=0.0)
    naive = _naive(beams, everything, fld.velocity, reflectivity=RAIN_REFLECTIVITY, floor=1.0, clear=clear)
    _compare(_fast_beam_view(res, beams), naive)
    as_read = _naive(beams, everything, fld.velocity, reflectivity=RAIN_REFLECTIVITY, floor=1.0)
    lost = sum(x == ParticleLabel.LOST for x in naive["label"])
    # the drops' occlusion makes the decisions: as read, every attenuated reading of 1 is lost
    assert sum(x == ParticleLabel.LOST for x in as_read["label"]) > lost + 10
    assert sum(not b for b in naive["borderline"]) >= 0.8 * len(beams)


@pytest.mark.parametrize(("q", "k"), [(1.0, 0.99), (2.0, 0.45)])
def test_a_rounded_reading_attenuated_a_little_is_kept_with_the_closed_form_share(q, k):
    """A clear reading q of an integer-quantised scan stood for a value uniform on [max(q - ½, floor), q + ½); a
    weather of two-way transmission k (bulk extinction, no particle, noise-free) keeps it iff k x >= floor: a share
    (q + ½ - floor / k) / (q + ½ - max(q - ½, floor)). Read as exactly q it is lost every time (k q < floor); an
    unrounded reading (q + 0.001) is read as it is."""
    n, length, floor = 20000, 10.0, 1.0
    lidar = make_lidar(noise_floor=floor)
    alpha = -math.log(k) / (2.0 * length)
    lo = max(q - 0.5, floor)
    want = (q + 0.5 - floor / k) / (q + 0.5 - lo)
    none = _particles(np.zeros((0, 3)), np.zeros(0))
    for value, expected in ((q, want), (q + 1e-3, 0.0)):
        beams = _beams([0, 0, 0], np.tile([1.0, 0.0, 0.0], (n, 1)), length, value, times=np.arange(n) * 1e-6)
        res = simulate_particle_list(beams, none, lidar=lidar, reflectivity=RAIN_REFLECTIVITY, extinction=alpha,
                                     intensity_max=255.0)
        kept = np.mean(res.input_labels != ParticleLabel.LOST)
        assert abs(kept - expected) <= 4 * math.sqrt(max(expected * (1 - expected), 1e-9) / n), (value, kept)
        # the kept ones report the attenuated reading as read
        np.testing.assert_allclose(res.points[:, 3], value * k, rtol=1e-9)


def _road_scan(road_z: float = -1.5, dark_elevation_deg: float = -6.0) -> LidarScan:
    """A static sensor over a flat road ``z = road_z`` (sensor frame = global): three steep rings return all round
    (0.5° steps, intensity 20), a shallow ring at ``dark_elevation_deg`` returns only from a bright marking (azimuth
    0..10°, intensity 30) and nothing from the dark road elsewhere."""
    rows = []
    for ring, el_deg in enumerate((-30.0, -24.0, -18.0, dark_elevation_deg)):
        az = np.radians(np.arange(0.0, 360.0, 0.5) if ring < 3 else np.arange(0.0, 10.0, 0.5))
        el = math.radians(el_deg)
        r = road_z / math.sin(el)
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(len(az), math.sin(el))], axis=1)
        rows.append(np.column_stack([d * r, np.full(len(az), 20.0 if ring < 3 else 30.0), np.full(len(az), ring)]))
    return LidarScan(np.concatenate(rows).astype(np.float32), 100.0, np.eye(4), np.eye(4), num_rings=4)


def test_beams_without_return_below_the_horizon_end_on_the_fitted_road():
    """The dark road's beams without return (a whole ring's worth, far beyond the short runs `with_faint_surfaces`
    bridges) get their surface from the fitted ground plane: range ``h / sin(-elevation)`` and intensity floor / 2;
    beams above the horizon stay open, the returns are untouched; no plane or no floor: nothing changes."""
    from weatheralign.lidar.beams import (
        NoReturnBeams,
        plane_ranges,
        scan_ground_plane,
        with_faint_surfaces,
        with_ground_plane,
    )

    scan = _road_scan()
    lidar = make_lidar(noise_floor=1.0)
    up = np.radians(np.arange(0.0, 360.0, 5.0))
    sky = np.stack([np.cos(up), np.sin(up), np.full(len(up), 0.05)], axis=1)
    sky /= np.linalg.norm(sky, axis=1, keepdims=True)
    beams = beams_from_scan(scan, lidar=lidar)
    beams = with_faint_surfaces(beams, lidar.noise_floor)
    n_ret, n_dark = beams.num_returns, len(beams) - beams.num_returns
    assert n_dark > 600  # the reconstructed dark road: the ring's 700 gaps
    plane = scan_ground_plane(scan)
    assert plane is not None and plane.normal[2] == pytest.approx(1.0, abs=1e-6)
    out = with_ground_plane(beams, plane, lidar.noise_floor)
    dark = ~beams.has_return
    np.testing.assert_allclose(out.lengths[dark], 1.5 / np.sin(np.radians(6.0)), rtol=1e-4)
    np.testing.assert_array_equal(out.intensity0[dark], 0.5)
    np.testing.assert_array_equal(out.lengths[:n_ret], beams.lengths[:n_ret])
    np.testing.assert_array_equal(out.intensity0[:n_ret], beams.intensity0[:n_ret])
    np.testing.assert_array_equal(out.has_return, beams.has_return)
    both = beams_from_scan(scan, lidar=lidar, no_return_directions=NoReturnBeams(
        sky, np.zeros(len(sky)), np.full(len(sky), 3, np.float32)))
    assert np.all(np.isinf(plane_ranges(both, plane)[~both.has_return]))  # above the horizon: never on the road
    assert with_ground_plane(both, plane, 1.0).lengths.tobytes() == both.lengths.tobytes()
    assert with_ground_plane(beams, None, 1.0) is beams and with_ground_plane(beams, plane, 0.0) is beams


def test_the_road_under_the_floor_ends_its_beam_no_drop_under_it_is_reported():
    """A flake on a dark-road beam: 1 m behind the road (under it) it returns nothing once the beam ends on the
    fitted plane; on the open beam (as before) it came back as clutter; 1 m in front of the road it is reported."""
    from weatheralign.lidar.beams import scan_ground_plane, with_ground_plane

    scan = _road_scan()
    lidar = make_lidar(noise_floor=1.0)
    beams = beams_from_scan(scan, lidar=lidar)
    b = int(np.flatnonzero(~beams.has_return)[100])
    one = beams.select(np.array([b]))
    road = with_ground_plane(one, scan_ground_plane(scan), lidar.noise_floor)
    L = float(road.lengths[0])
    assert L == pytest.approx(1.5 / math.sin(math.radians(6.0)), rel=1e-4)
    for s, on_road, open_beam in ((L + 1.0, ParticleLabel.NO_ECHO, ParticleLabel.SCATTERED),
                                  (L - 1.0, ParticleLabel.SCATTERED, ParticleLabel.SCATTERED)):
        w = s * math.tan(0.5 * lidar.divergence_rad)
        flake = _particles(one.origins[0] + one.directions[0] * s, [2 * w * 0.5])  # a quarter of the beam
        got = [simulate_particle_list(x, flake, lidar=lidar, reflectivity=SNOW_REFLECTIVITY,
                                      intensity_max=255.0).beam_label[0] for x in (road, one)]
        assert got == [on_road, open_beam], s


def test_a_scan_through_snow_reports_no_echo_from_under_its_road():
    """`simulate_particles` on a scan over a dark road in a snow layer reaching 3 m under it: with the faint
    surfaces (the fitted plane among them) no weather echo lies under the road; every beam open, many did."""
    scan = _road_scan()
    lidar = make_lidar(noise_floor=1.0)
    dist = ExponentialSizeDistribution(n0=60.0 * 150.0 * math.exp(150.0 * 4e-3), lam=150.0, d_min=4e-3, d_max=0.03)
    fld = ParticleField(11, dist, velocity=(0.0, 0.0, 0.0), t_ref=100.0, z_min=-4.5, z_max=3.0, cell_size=1.0)
    res = {faint: simulate_particles(scan, fld, lidar=lidar, reflectivity=SNOW_REFLECTIVITY, faint_surfaces=faint)
           for faint in (True, False)}
    under = {k: int(np.count_nonzero((r.source_index < 0) & (r.points[:, 2] < -1.5 - 0.05))) for k, r in res.items()}
    assert under[False] > 20 and under[True] == 0, under
    assert res[True].counts["CLUTTER"] > 20  # the snow in front of the road still is
