"""LiDAR fog (Hahner 2021 for any α): pulse closed forms, fast response vs a brute-force integral, the published
crossover ranges, α → 0 identity, the fixes of the published code's traps, and real STF / KITTI scans.

The reference ``_naive_response`` integrates ``P_soft(R)`` per target range with Simpson's rule over the pulse time
(1201 samples) on every receiver range ``R <= R_0`` of a 5 mm grid and takes the brute-force maximum. Stated
tolerances (fast vs naive): ``|ΔI| <= 5e-4 · I_peak(α)`` and ``|ΔR_fog| <= 1 cm`` (the naive rule itself is accurate
to ~1e-4 because ξ's kinks fall between its nodes; the fast table agrees with adaptive quadrature to ~1e-5).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import simpson
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from tests.conftest import make_lidar
from weatheralign.data.frame import LidarScan
from weatheralign.lidar import FogLabel, c_a_p0_from_intensity, hard_target_power, overlap
from weatheralign.lidar.beams import beam_origins, point_noise_keys
from weatheralign.lidar.fog import (
    REFERENCE_CODE_BETA,
    fog_intensities,
    fog_point_arrays,
    intensity_normals,
    simulate_fog,
    soft_target_response,
)
from weatheralign.medium.fog import default_beta, mor_from_alpha
from weatheralign.sensors import HAHNER_INTENSITY as RAW
from weatheralign.sensors import SPEED_OF_LIGHT, LidarModel, PulseSensor

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
STF_ID = "2019-09-11_19-13-44_00960"
SENSOR = PulseSensor()
"""The fog model's sensor (Hahner 2021): τ_H = 20 ns, ξ from 0.9 m to 1.0 m, Γ = 1e-6, 120 m, saturating at 255."""

# physics.md: fog wins for R_0 >~ these ranges [m] (published code, whose β stays 9.21e-4 whatever α)
PUBLISHED_CROSSOVER = {0.005: 138.0, 0.01: 101.0, 0.02: 70.0, 0.03: 55.0, 0.06: 36.0}


# ---------------------------------------------------------------------------------------------------- references


def _lidar(noise_floor: float = 0.0, sensor: PulseSensor = SENSOR, range_noise: float = 0.0,
           floor_range_m: float | None = None) -> LidarModel:
    """A `LidarModel` with the fog model's pulse ``sensor``, detector ``noise_floor`` (0..255; 0 keeps every
    return, like ``noise_floor=None`` of the array functions, since intensities are >= 0; at ``floor_range_m`` when
    given: a raw-power detector) and Gaussian ``range_noise`` [m] of a new echo."""
    return make_lidar(pulse=sensor, max_range_m=sensor.max_range, noise_floor=noise_floor,
                      range_noise_std_m=range_noise, floor_range_m=floor_range_m)


def _reported(alpha: float, sensor: PulseSensor = SENSOR) -> float:
    """Where a noise-free receiver reports the fog echo of a far target: the power peak minus c τ_H / 2."""
    return soft_target_response(alpha, sensor).r_peak - sensor.pulse_length / 2.0


FOG_LIDAR = _lidar()


def _naive_response(r0: float, alpha: float, sensor: PulseSensor = SENSOR, dr: float = 0.005,
                    n_t: int = 1201) -> tuple[float, float]:
    """``(I(R_0), R_fog)`` straight from the formula: Simpson over t of
    ``sin²(πt/2τ_H) e^{-2αr} ξ(r)/r² U(R_0 - r)``, ``r = R - ct/2``, for every ``R`` in ``0..R_0`` (step ``dr``),
    then the largest value. Slow and obviously correct."""
    tau = sensor.tau_h
    t = np.linspace(0.0, 2.0 * tau, n_t)
    pulse = np.sin(np.pi * t / (2.0 * tau)) ** 2
    receiver = np.arange(0.0, r0 + dr / 2, dr)
    best, best_r = 0.0, 0.0
    for start in range(0, len(receiver), 1000):
        big_r = receiver[start:start + 1000, None]
        r = big_r - SPEED_OF_LIGHT * t[None, :] / 2.0
        xi = np.clip((r - sensor.r1) / (sensor.r2 - sensor.r1), 0.0, 1.0)
        safe_r = np.where(r > sensor.r1, r, 1.0)
        integrand = np.where((r > sensor.r1) & (r <= r0), pulse * np.exp(-2.0 * alpha * r) * xi / safe_r**2, 0.0)
        power = simpson(integrand, x=t, axis=1)
        j = int(np.argmax(power))
        if power[j] > best:
            best, best_r = float(power[j]), float(receiver[start + j])
    return best, best_r


def _crossover(alpha: float, beta: float, r0: np.ndarray, labels: np.ndarray) -> float:
    """First range of ``r0`` (ascending) labelled SCATTERED, checking that all farther ones are too."""
    fog = labels == FogLabel.SCATTERED
    assert fog.any(), f"alpha={alpha}: no fog return up to {r0[-1]} m"
    first = int(np.argmax(fog))
    assert fog[first:].all(), f"alpha={alpha}: fog and target alternate beyond {r0[first]} m"
    return float(r0[first])


def _scan(n: int = 4000, seed: int = 0, intensity_max: float = 255.0, moving: bool = False) -> LidarScan:
    """Random points 0.5-150 m around the sensor, intensities on ``0..intensity_max`` (some exactly 0)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.5, 150.0, n)
    pts = np.empty((n, 5), np.float32)
    pts[:, :3] = d * r[:, None]
    pts[:, 3] = rng.uniform(0.0, 1.0, n) * intensity_max
    pts[::50, 3] = 0.0
    pts[:, 4] = rng.integers(0, 32, n)
    if not moving:
        return LidarScan(points=pts, timestamp=0.0, T_ego_lidar=np.eye(4), T_global_ego=np.eye(4),
                         intensity_max=intensity_max)
    T_el = np.eye(4)
    T_el[:3, :3] = Rotation.from_euler("z", 0.3).as_matrix()
    T_el[:3, 3] = (0.9, 0.1, 1.8)
    times = np.array([9.95, 9.975, 10.0])
    poses = np.stack([np.eye(4)] * 3)
    for k, t in enumerate(times - 10.0):
        poses[k, :3, :3] = Rotation.from_euler("z", 0.5 * t).as_matrix()
        poses[k, :3, 3] = (12.0 * t, 1.0 * t, 0.0)
    return LidarScan(points=pts, timestamp=10.0, T_ego_lidar=T_el, T_global_ego=poses[-1], intensity_max=intensity_max,
                     time_offsets=-rng.uniform(0.0, 0.05, n).astype(np.float32), pose_times=times, poses=poses)


def _check_sane(scan: LidarScan, res, sensor: PulseSensor = SENSOR, origins: np.ndarray | None = None) -> None:
    """No NaN, intensities in range, ring and unscattered points kept, fog echoes on their ray between r1 and
    min(R_0, max_range)."""
    src = scan.points[res.source_index]
    out = res.points
    assert out.dtype == np.float32 and out.shape[1] == 5 and np.isfinite(out).all()
    assert (out[:, 3] >= 0).all() and (out[:, 3] <= scan.intensity_max).all()
    assert np.array_equal(out[:, 4], src[:, 4])
    np.testing.assert_array_equal(res.labels, res.input_labels[res.source_index])
    assert not (res.labels == FogLabel.LOST).any()
    stay = res.labels != FogLabel.SCATTERED
    assert np.array_equal(out[stay, :3], src[stay, :3])
    fog = ~stay
    o = np.zeros((fog.sum(), 3)) if origins is None else origins[res.source_index][fog]
    ray_in = src[fog, :3].astype(np.float64) - o
    ray_out = out[fog, :3].astype(np.float64) - o
    r_in, r_out = np.linalg.norm(ray_in, axis=1), np.linalg.norm(ray_out, axis=1)
    assert (r_out >= sensor.r1 - 1e-4).all()
    assert (r_out <= np.minimum(r_in, sensor.max_range) + 1e-4).all()
    cos = np.einsum("ij,ij->i", ray_in, ray_out) / (r_in * r_out)
    assert (cos > 1 - 1e-9).all(), "a fog echo left its ray (or went behind the sensor)"
    assert sum(res.counts.values()) == len(scan.points)


# ---------------------------------------------------------------------------------------------------- pulse model


def test_overlap_and_hard_target_closed_form() -> None:
    np.testing.assert_allclose(overlap([0.0, 0.9, 0.95, 1.0, 5.0], SENSOR), [0.0, 0.0, 0.5, 1.0, 1.0])
    r0, L = 20.0, SENSOR.pulse_length
    assert L == pytest.approx(5.99584916)
    r = np.linspace(r0 - 1, r0 + L + 1, 20001)
    p = hard_target_power(r, r0, SENSOR, alpha=0.03, beta_ratio=0.5)
    assert p[(r < r0) | (r > r0 + L)].max() == 0.0
    j = int(np.argmax(p))
    assert r[j] == pytest.approx(r0 + L / 2, abs=1e-3)
    assert p[j] == pytest.approx(SENSOR.beta_0 * 0.5 / r0**2 * math.exp(-0.06 * r0), rel=1e-9)
    # the recovered system constant turns the clear peak back into the measured intensity
    i0 = np.array([7.0, 200.0])
    c_a_p0 = c_a_p0_from_intensity(i0, [5.0, 80.0], SENSOR)
    peak = hard_target_power([5.0 + L / 2, 80.0 + L / 2], [5.0, 80.0], SENSOR, c_a_p0=c_a_p0)
    np.testing.assert_allclose(peak, i0, rtol=1e-12)
    # half-power width: sin² is above 1/2 for exactly τ_H of the 2τ_H pulse
    above = r[p > p[j] / 2]
    assert above[-1] - above[0] == pytest.approx(L / 2, abs=2e-3)


def test_pulse_sensor_validation() -> None:
    assert PulseSensor(tau_h=10e-9).pulse_length == pytest.approx(2.99792458)
    for bad in ({"tau_h": 0.0}, {"r2": 0.5}, {"gamma": -1.0}, {"max_range": 0.5}, {"saturation": 300.0},
                {"tau_h": float("nan")}):
        with pytest.raises(ValueError):
            PulseSensor(**bad)


# ------------------------------------------------------------------------------------------ fast vs naive integral


@pytest.mark.parametrize("alpha", [0.005, 0.023, 0.06, 0.137])  # 0.023, 0.137: on no published table
def test_fast_response_matches_naive_integral(alpha: float) -> None:
    resp = soft_target_response(alpha, SENSOR)
    r0s = [0.5, 0.95, 1.5, 3.0, 4.2, 4.65, 6.0, 12.0, 50.0] + ([200.0] if alpha in (0.005, 0.137) else [])
    fast_i, fast_r = resp(np.array(r0s))
    for r0, fi, fr in zip(r0s, fast_i, fast_r):
        ni, nr = _naive_response(r0, alpha)
        assert abs(fi - ni) <= 5e-4 * resp.g_peak, (alpha, r0, fi, ni)
        if ni > 0:
            assert abs(fr - nr) <= 0.01, (alpha, r0, fr, nr)
    # the fused kernel used on point clouds evaluates the same I(R_0) as the table
    r0 = np.array(r0s)
    beta = 0.05 / r0.max() ** 2  # keeps i_soft below saturation
    got = fog_intensities(r0, np.full(len(r0), 100.0, np.float32), alpha, beta, intensity=RAW, sensor=SENSOR,
                          noise_floor=None)
    soft = fast_i * 100.0 * r0**2 * beta / SENSOR.beta_0
    hard = np.exp(-2 * alpha * r0) * 100.0
    assert soft.max() < 255.0
    np.testing.assert_allclose(got.intensity, np.maximum(soft, hard), rtol=1e-12)
    np.testing.assert_allclose(got.r_fog, fast_r, rtol=1e-12)
    np.testing.assert_array_equal(got.labels == FogLabel.SCATTERED, soft > hard)


def test_response_is_continuous_in_alpha() -> None:
    """Any α works and nothing is snapped: I and R* move smoothly between (and beyond) the published alphas."""
    alphas = np.linspace(0.0, 0.3, 61)
    peaks = np.array([soft_target_response(a, SENSOR).g_peak for a in alphas])
    r_peaks = np.array([soft_target_response(a, SENSOR).r_peak for a in alphas])
    assert (np.diff(peaks) < 0).all() and (np.diff(r_peaks) < 0).all()
    assert np.abs(np.diff(peaks, 2)).max() < 1e-3 * peaks[0]


def test_alpha_006_fog_peak_saturates_near_4_6_m() -> None:
    resp = soft_target_response(0.06, SENSOR)
    assert 4.55 <= resp.r_peak <= 4.7
    r0 = np.array([4.7, 5.0, 8.0, 36.0, 100.0, 200.0, 1000.0])
    value, r_fog = resp(r0)
    np.testing.assert_allclose(r_fog, resp.r_peak)
    np.testing.assert_allclose(value, resp.g_peak)
    below_value, below_r = resp(np.array([2.0, 4.0]))
    np.testing.assert_allclose(below_r, [2.0, 4.0])
    assert (below_value < resp.g_peak).all()
    ni, nr = _naive_response(10.0, 0.06)
    assert nr == pytest.approx(4.64, abs=0.05)


# ------------------------------------------------------------------------------------------------ crossover ranges


@pytest.mark.parametrize("alpha", sorted(PUBLISHED_CROSSOVER))
def test_published_crossover_ranges(alpha: float) -> None:
    """The published figures come from the published code, i.e. β = 9.21e-4 for every α (its trap)."""
    r0 = np.arange(0.5, 300.0, 0.01)
    res = fog_intensities(r0, np.full(len(r0), 100.0, np.float32), alpha, REFERENCE_CODE_BETA, intensity=RAW,
                          sensor=SENSOR,
                          noise_floor=None)
    cross = _crossover(alpha, REFERENCE_CODE_BETA, r0, res.labels)
    assert abs(cross - PUBLISHED_CROSSOVER[alpha]) <= 0.75, cross
    # independent of the fast table: the naive saturated response solves G* R² β / β_0 = exp(-2 α R)
    g_star, _ = _naive_response(10.0, alpha)
    gap = lambda r: g_star * r * r * REFERENCE_CODE_BETA / SENSOR.beta_0 - math.exp(-2.0 * alpha * r)  # noqa: E731
    assert brentq(gap, 10.0, 400.0) == pytest.approx(cross, abs=0.05)
    # the crossover does not depend on the intensity (below saturation)
    res_dim = fog_intensities(r0, np.full(len(r0), 3.0, np.float32), alpha, REFERENCE_CODE_BETA, intensity=RAW,
                              sensor=SENSOR,
                              noise_floor=None)
    assert _crossover(alpha, REFERENCE_CODE_BETA, r0, res_dim.labels) == cross


def test_beta_follows_the_caller() -> None:
    """With β = 0.046 / MOR of the given α (not stuck at α = 0.06), thin fog backscatters less: the crossover moves
    out (about 260 / 151 / 86.5 / 62.4 m at α = 0.005 / 0.01 / 0.02 / 0.03), and equals the published one at 0.06."""
    r0 = np.arange(0.5, 400.0, 0.01)
    i0 = np.full(len(r0), 100.0, np.float32)
    expected = {0.005: 259.8, 0.01: 150.6, 0.02: 86.5, 0.03: 62.4, 0.06: 35.6}
    for alpha, want in expected.items():
        beta = default_beta(alpha)
        assert beta == pytest.approx(0.046 / mor_from_alpha(alpha))
        labels = fog_intensities(r0, i0, alpha, beta, intensity=RAW, sensor=SENSOR, noise_floor=None).labels
        cross = _crossover(alpha, beta, r0, labels)
        assert cross == pytest.approx(want, abs=0.3)
        if alpha < 0.06:
            assert cross > PUBLISHED_CROSSOVER[alpha] + 5
    scan = _scan(seed=3)
    fog_counts = [simulate_fog(scan, 0.03, b, lidar=FOG_LIDAR).counts["SCATTERED"]
                  for b in (0.5e-4, 2e-4, 8e-4, 3.2e-3)]
    assert fog_counts == sorted(fog_counts) and fog_counts[0] < fog_counts[-1]
    lo, hi = (simulate_fog(scan, 0.03, b, lidar=FOG_LIDAR) for b in (1e-4, 2e-4))
    both = (lo.labels == FogLabel.SCATTERED) & (hi.labels == FogLabel.SCATTERED) & (hi.points[:, 3] < 255)
    np.testing.assert_allclose(hi.points[both, 3], 2 * lo.points[both, 3], rtol=1e-6)  # i_soft ∝ β


# ------------------------------------------------------------------------------------------------ point clouds


@pytest.mark.parametrize("moving", [False, True])
@pytest.mark.parametrize("intensity_max", [255.0, 1.0])
def test_alpha_zero_gives_the_input_back_exactly(moving: bool, intensity_max: float) -> None:
    scan = _scan(intensity_max=intensity_max, moving=moving)
    before = scan.points.copy()
    for alpha, beta in ((0.0, 0.0), (0.0, default_beta(0.0)), (1e-12, default_beta(1e-12))):
        res = simulate_fog(scan, alpha, beta, lidar=_lidar(10.0, range_noise=0.05))
        assert res.points.tobytes() == scan.points.tobytes()
        assert (res.labels == FogLabel.UNCHANGED).all()
        np.testing.assert_array_equal(res.source_index, np.arange(len(scan.points)))
    assert scan.points.tobytes() == before.tobytes()


def test_labels_and_attenuation() -> None:
    scan = _scan(seed=1)
    res = simulate_fog(scan, 0.06, default_beta(0.06), lidar=FOG_LIDAR)
    _check_sane(scan, res)
    src = scan.points
    r0 = np.linalg.norm(src[:, :3].astype(np.float64), axis=1)
    att = res.labels == FogLabel.ATTENUATED
    np.testing.assert_allclose(res.points[att, 3], np.exp(-0.12 * r0[att]) * src[att, 3], rtol=1e-6)
    zero = src[:, 3] == 0
    assert (res.labels[zero] == FogLabel.UNCHANGED).all()
    fog = res.labels == FogLabel.SCATTERED
    assert fog.sum() > 0 and (r0[fog] > 30).all() and (r0[~fog & ~zero & (r0 > 40)].size == 0)
    np.testing.assert_allclose(np.linalg.norm(res.points[fog, :3], axis=1), _reported(0.06), rtol=1e-5)
    # the receiver picks the stronger echo on raw power (reported value over the compensation R² g(R) at its range)
    comp = FOG_LIDAR.intensity.compensation
    assert (res.points[fog, 3] / comp(_reported(0.06)) > np.exp(-0.12 * r0[fog]) * src[fog, 3] / comp(r0[fog])).all()


def test_intensity_scale_0_1_behaves_like_0_255() -> None:
    scan255 = _scan(seed=2)
    pts1 = scan255.points.copy()
    pts1[:, 3] /= np.float32(255.0)
    scan1 = replace(scan255, points=pts1, intensity_max=1.0)
    for kwargs in ({"lidar": FOG_LIDAR}, {"lidar": _lidar(0.5, floor_range_m=100.0)},
                   {"lidar": _lidar(range_noise=0.05)}):
        a = simulate_fog(scan255, 0.1, default_beta(0.1), **kwargs)
        b = simulate_fog(scan1, 0.1, default_beta(0.1), **kwargs)
        assert b.intensity_max == 1.0 and a.intensity_max == 255.0
        np.testing.assert_array_equal(a.input_labels, b.input_labels)
        np.testing.assert_array_equal(a.points[:, [0, 1, 2, 4]], b.points[:, [0, 1, 2, 4]])
        np.testing.assert_allclose(b.points[:, 3] * 255.0, a.points[:, 3], rtol=1e-6, atol=1e-4)
        assert a.counts["SCATTERED"] > 0
        assert b.points[:, 3].max() <= 1.0
    # the sensor saturation applies on the input's scale: 255 on 0..255, 1 on 0..1
    sat = fog_intensities([150.0], [255.0], 0.3, 1.0, intensity=RAW, sensor=SENSOR,
                          noise_floor=None).intensity[0], fog_intensities(
        [150.0], [1.0], 0.3, 1.0, intensity=RAW, sensor=SENSOR, noise_floor=None, intensity_max=1.0).intensity[0]
    assert sat == (255.0, 1.0)


def test_fog_echoes_get_the_sensors_range_noise_bounded_and_deterministic() -> None:
    """One range convention with the hard targets (peak - c τ_H / 2) and the sensor's Gaussian range noise (σ, clipped
    at ±2σ) from each beam's own stream: the echoes form no perfect shell, the same scan gives the same bytes, and no
    echo lands behind the sensor, past its target or beyond the maximum range."""
    scan = _scan(n=20000, seed=4, moving=True)
    origins = beam_origins(scan, "scan")
    sensor = PulseSensor(max_range=60.0)
    sigma = 0.05
    res = simulate_fog(scan, 0.1, default_beta(0.1), lidar=_lidar(sensor=sensor, range_noise=sigma))
    _check_sane(scan, res, sensor, origins)
    fog = res.labels == FogLabel.SCATTERED
    dev = np.linalg.norm(res.points[fog, :3].astype(np.float64) - origins[res.source_index[fog]], axis=1) - _reported(
        0.1, sensor)
    assert fog.sum() > 1000 and np.abs(dev).max() <= 2 * sigma + 1e-5
    # a normal clamped at ±2 has standard deviation 0.959 (a shell: 0; a uniform ±2σ jitter: 1.155)
    assert 0.93 * sigma < dev.std() < 0.99 * sigma and abs(dev.mean()) < 0.05 * sigma
    again = simulate_fog(scan, 0.1, default_beta(0.1), lidar=_lidar(sensor=sensor, range_noise=sigma))
    assert again.points.tobytes() == res.points.tobytes()
    quiet = simulate_fog(scan, 0.1, default_beta(0.1), lidar=_lidar(sensor=sensor))
    np.testing.assert_array_equal(quiet.input_labels, res.input_labels)  # noise moves echoes, decides nothing
    np.testing.assert_array_equal(quiet.points[:, 3:], res.points[:, 3:])
    wild = simulate_fog(scan, 0.1, default_beta(0.1), lidar=_lidar(sensor=sensor, range_noise=1.0))
    _check_sane(scan, wild, sensor, origins)  # 2σ = 2 m > the reported 1.6 m: clipped at the blind zone's edge r1
    r_wild = np.linalg.norm(wild.points[:, :3].astype(np.float64) - origins[wild.source_index], axis=1)
    assert r_wild[wild.labels == FogLabel.SCATTERED].min() == pytest.approx(sensor.r1, abs=1e-5)
    with pytest.raises(ValueError, match="noise_keys"):
        fog_point_arrays(scan.points, origins, 0.1, default_beta(0.1), intensity=FOG_LIDAR.intensity, sensor=sensor,
                         noise_floor=None,
                         range_noise_std=0.05)
    with pytest.raises(ValueError, match="range_noise_std"):
        fog_point_arrays(scan.points, origins, 0.1, default_beta(0.1), intensity=FOG_LIDAR.intensity, sensor=sensor,
                         noise_floor=None,
                         range_noise_std=-1.0)
    with pytest.raises(ValueError):
        simulate_fog(scan, -0.1, 0.0, lidar=_lidar(sensor=sensor))
    with pytest.raises(ValueError):
        simulate_fog(scan, 0.1, float("nan"), lidar=_lidar(sensor=sensor))


def test_detector_intensity_noise_has_the_missing_variance_of_each_reading() -> None:
    """A noisy detector (σ_0, rel) reads every changed return again. A fog echo is a new reading: mean ``i_soft``,
    variance ``σ_0² + (rel · i_soft)²``. An attenuated target carries its clear reading's noise scaled by ``T²`` and
    gets the missing ``σ_0² (1 - T⁴)``, so its total variance is a fogged reading's. Unchanged points (α = 0) and a
    noise-free detector give the exact old values; the floor decides on the reading."""
    n = 40_000
    keys = np.random.default_rng(7).integers(0, 2**63, n, dtype=np.uint64)
    z = intensity_normals(keys)
    assert abs(z.mean()) < 4.0 / math.sqrt(n) and abs(z.std() - 1.0) < 0.02
    s0, rel = 2.0, 0.05
    for r, i0, alpha, beta in ((100.0, 250.0, 0.06, default_beta(0.06)),  # dense fog: the fog echo wins
                               (20.0, 80.0, 0.03, 0.0)):  # no backscatter: the attenuated target
        r0, i0s = np.full(n, r), np.full(n, i0, np.float32)
        quiet = fog_intensities(r0, i0s, alpha, beta, intensity=RAW, sensor=SENSOR, noise_floor=None)
        loud = fog_intensities(r0, i0s, alpha, beta, intensity=RAW, sensor=SENSOR, noise_floor=None, noise_std=s0,
                               noise_rel=rel,
                               noise_normals=z)
        np.testing.assert_array_equal(quiet.labels, loud.labels)
        mean = quiet.intensity[0]
        if beta > 0.0:
            assert (quiet.labels == FogLabel.SCATTERED).all()
            var = s0 ** 2 + (rel * mean) ** 2
        else:
            assert (quiet.labels == FogLabel.ATTENUATED).all()
            var = s0 ** 2 * (1.0 - math.exp(-4.0 * alpha * r))
        assert loud.intensity.mean() == pytest.approx(mean, abs=4.0 * math.sqrt(var / n))
        assert loud.intensity.std() == pytest.approx(math.sqrt(var), rel=0.02)
        expected = mean + math.sqrt(var) * z
        assert (expected > 0.0).all()  # nothing clipped at 0 here
        np.testing.assert_allclose(loud.intensity, expected, rtol=1e-12)
    # α = 0: the clear reading stands, bit for bit; a noise-free detector is the old model
    clear = fog_intensities(np.full(n, 30.0), np.full(n, 50.0, np.float32), 0.0, 0.0, intensity=RAW, sensor=SENSOR,
                            noise_floor=None,
                            noise_std=s0, noise_rel=rel, noise_normals=z)
    assert (clear.labels == FogLabel.UNCHANGED).all() and (clear.intensity == 50.0).all()
    # the floor decides on the reading: attenuated to the floor itself, about half the readings fall below it
    r = 40.0
    floor = float(np.float32(math.exp(-2.0 * 0.03 * r) * 10.0))
    weak = fog_intensities(np.full(n, r), np.full(n, 10.0, np.float32), 0.03, 0.0, intensity=RAW, sensor=SENSOR,
                           noise_floor=floor,
                           noise_std=s0, noise_rel=rel, noise_normals=z)
    assert 0.45 < np.mean(weak.labels == FogLabel.LOST) < 0.55
    assert (weak.intensity[weak.labels != FogLabel.LOST] >= floor).all()
    with pytest.raises(ValueError, match="noise_normals"):
        fog_intensities(np.full(3, r), np.full(3, 10.0, np.float32), 0.03, 0.0, intensity=RAW, sensor=SENSOR,
                        noise_floor=None,
                        noise_std=s0)
    with pytest.raises(ValueError, match="noise"):
        fog_intensities(np.full(3, r), np.full(3, 10.0, np.float32), 0.03, 0.0, intensity=RAW, sensor=SENSOR,
                        noise_floor=None,
                        noise_std=-1.0)


def test_simulate_fog_reads_through_the_sensors_intensity_noise_deterministically() -> None:
    """`simulate_fog` draws each beam's reading from its own noise stream (`point_noise_keys`): the same scan gives
    the same bytes, and the array-level model with those normals gives the same intensities and decisions."""
    scan = _scan(n=20000, seed=11, moving=True)
    origins = beam_origins(scan, "scan")
    lidar = make_lidar(pulse=SENSOR, max_range_m=SENSOR.max_range, noise_floor=2.0, intensity_noise_std=1.5,
                       intensity_noise_rel=0.03)
    alpha, beta = 0.06, default_beta(0.06)
    res = simulate_fog(scan, alpha, beta, lidar=lidar)
    _check_sane(scan, res, SENSOR, origins)
    assert simulate_fog(scan, alpha, beta, lidar=lidar).points.tobytes() == res.points.tobytes()
    quiet = simulate_fog(scan, alpha, beta, lidar=replace(lidar, intensity_noise_std=0.0, intensity_noise_rel=0.0))
    changed = res.input_labels != FogLabel.UNCHANGED
    assert changed.sum() > 10_000
    both = np.intersect1d(res.source_index, quiet.source_index)
    assert not np.array_equal(res.points[np.searchsorted(res.source_index, both), 3],
                              quiet.points[np.searchsorted(quiet.source_index, both), 3])
    r0 = np.linalg.norm(scan.points[:, :3].astype(np.float64) - origins, axis=1)
    arr = fog_intensities(r0, scan.points[:, 3], alpha, beta, intensity=FOG_LIDAR.intensity, sensor=SENSOR,
                          noise_floor=2.0, noise_std=1.5,
                          noise_rel=0.03, noise_normals=intensity_normals(point_noise_keys(scan)))
    np.testing.assert_array_equal(arr.labels, res.input_labels)
    np.testing.assert_array_equal(arr.intensity[res.source_index].astype(np.float32), res.points[:, 3])


def test_noise_floor_drops_undetectable_returns() -> None:
    scan = _scan(n=20000, seed=5)
    full = simulate_fog(scan, 0.06, default_beta(0.06), lidar=FOG_LIDAR)
    floored = simulate_fog(scan, 0.06, default_beta(0.06), lidar=_lidar(20.0))
    _check_sane(scan, floored)
    lost = floored.input_labels == FogLabel.LOST
    assert lost.sum() == floored.counts["LOST"] > 0
    assert len(floored.points) == len(scan.points) - lost.sum()
    assert not np.isin(np.flatnonzero(lost), floored.source_index).any()
    i0 = scan.points[:, 3]
    assert (full.points[lost, 3] < 20.0).all() and (full.points[lost, 3] < i0[lost]).all()
    kept = floored.source_index
    weak = floored.points[:, 3] < 20.0  # only kept below the floor when the clear return was at least as weak
    assert (floored.points[weak, 3] >= i0[kept][weak]).all()
    assert np.array_equal(floored.points, full.points[kept])
    assert full.counts["LOST"] == 0  # a floor of 0 drops nothing ...
    no_floor = fog_point_arrays(scan.points, None, 0.06, default_beta(0.06), intensity=FOG_LIDAR.intensity,
                                sensor=SENSOR, noise_floor=None)
    assert no_floor.points.tobytes() == full.points.tobytes()  # ... exactly like no floor at all


def test_simulate_fog_takes_pulse_and_floor_from_the_explicit_lidar_model() -> None:
    """No default sensor: the pulse (τ_H moves the fog peak) and the detector floor come from the `LidarModel`."""
    scan = _scan(n=20000, seed=5)
    with pytest.raises(TypeError, match="lidar"):
        simulate_fog(scan, 0.06, default_beta(0.06))  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="sensor"):
        soft_target_response(0.06)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="sensor"):
        fog_intensities([10.0], [100.0], 0.06, 1e-3, intensity=RAW, noise_floor=None)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="noise_floor"):
        fog_point_arrays(scan.points, None, 0.06, 1e-3, intensity=RAW, sensor=SENSOR)  # type: ignore[call-arg]
    short = PulseSensor(tau_h=10e-9)
    peaks = {}
    for sensor in (SENSOR, short):
        res = simulate_fog(scan, 0.06, default_beta(0.06), lidar=_lidar(sensor=sensor))
        fog = res.labels == FogLabel.SCATTERED
        peaks[sensor.tau_h] = soft_target_response(0.06, sensor).r_peak
        assert fog.sum() > 0
        np.testing.assert_allclose(np.linalg.norm(res.points[fog, :3], axis=1), _reported(0.06, sensor), rtol=1e-5)
        same = fog_point_arrays(scan.points, None, 0.06, default_beta(0.06), intensity=FOG_LIDAR.intensity,
                                sensor=sensor, noise_floor=None)
        assert same.points.tobytes() == res.points.tobytes()
    assert abs(peaks[10e-9] - peaks[20e-9]) > 0.5  # the pulse really is the model's
    floored = simulate_fog(scan, 0.06, default_beta(0.06), lidar=_lidar(20.0))
    assert floored.counts["LOST"] > 0
    same = fog_point_arrays(scan.points, None, 0.06, default_beta(0.06), intensity=FOG_LIDAR.intensity, sensor=SENSOR,
                            noise_floor=20.0)
    assert same.points.tobytes() == floored.points.tobytes()


def test_beam_origins_and_moving_ego() -> None:
    scan = _scan(n=5000, seed=6, moving=True)
    fast = beam_origins(scan, "scan")
    np.testing.assert_allclose(fast, scan.beam_origins(), atol=1e-7)
    assert np.ptp(fast[:, 0]) > 0.4  # the sensor moved ~0.6 m during the sweep
    assert beam_origins(_scan(n=10), "scan") is None
    res = simulate_fog(scan, 0.08, default_beta(0.08), lidar=FOG_LIDAR)
    _check_sane(scan, res, origins=fast)
    fog = res.labels == FogLabel.SCATTERED
    r_fog = np.linalg.norm(res.points[fog, :3].astype(np.float64) - fast[fog], axis=1)
    np.testing.assert_allclose(r_fog, _reported(0.08), rtol=1e-5)
    # the array-level function with explicit origins is what simulate_fog runs
    arr = fog_point_arrays(scan.points, fast, 0.08, default_beta(0.08), intensity=FOG_LIDAR.intensity, sensor=SENSOR,
                           noise_floor=None)
    assert arr.points.tobytes() == res.points.tobytes()
    fogged = res.apply_to(scan)
    assert isinstance(fogged, LidarScan) and fogged.points is res.points
    np.testing.assert_array_equal(fogged.time_offsets, scan.time_offsets[res.source_index])


def test_array_level_many_points_many_betas() -> None:
    """The calibration use: one response per α reused across β on a million returns."""
    rng = np.random.default_rng(9)
    r0 = rng.uniform(0.5, 120.0, 1_000_000)
    i0 = rng.uniform(0.0, 255.0, 1_000_000).astype(np.float32)
    resp = soft_target_response(0.04, SENSOR)
    fractions = []
    for k in (1.0, 1.4, 2.0):
        beta = 0.023 * k / mor_from_alpha(0.04)
        res = fog_intensities(r0, i0, 0.04, beta, intensity=RAW, sensor=SENSOR, noise_floor=None, response=resp)
        assert res.intensity.shape == r0.shape and (res.intensity <= 255.0).all()
        fractions.append(float((res.labels == FogLabel.SCATTERED).mean()))
    assert fractions == sorted(fractions) and fractions[0] > 0
    with pytest.raises(ValueError, match="alpha"):
        fog_intensities(r0[:5], i0[:5], 0.05, 1e-3, intensity=RAW, sensor=SENSOR, noise_floor=None, response=resp)


# ------------------------------------------------------------------------------------------------------ real scans


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real sample not available: {path}")
    return path


@pytest.fixture(scope="module")
def stf_scan() -> LidarScan:
    from weatheralign.data.stf import load_stf_frame

    return load_stf_frame(_need(REAL / "stf"), STF_ID, camera_folder=None).lidar


@pytest.fixture(scope="module")
def kitti_scan() -> LidarScan:
    from weatheralign.data.kitti import load_kitti_frame

    kitti = _need(REAL / "kitti")
    return load_kitti_frame(kitti / "000008.bin", None, kitti / "calib.json").lidar


@pytest.mark.parametrize("which", ["stf", "kitti"])
def test_real_scans_give_sane_output(which: str, request: pytest.FixtureRequest) -> None:
    scan: LidarScan = request.getfixturevalue(f"{which}_scan")
    assert scan.intensity_max == (255.0 if which == "stf" else 1.0)
    before = scan.points.copy()
    scattered = []
    for alpha in (0.005, 0.03, 0.06, 0.1):
        res = simulate_fog(scan, alpha, default_beta(alpha), lidar=FOG_LIDAR)
        _check_sane(scan, res)
        scattered.append(res.counts["SCATTERED"])
        noisy = simulate_fog(scan, alpha, default_beta(alpha), lidar=_lidar(5.0, range_noise=0.5))
        _check_sane(scan, noisy)
    assert scattered == sorted(scattered) and 0 < scattered[-1] < 0.2 * len(scan.points)
    assert scan.points.tobytes() == before.tobytes()
    # fog echoes sit in the sensor's near field (power peak 4.64 m, reported c τ_H / 2 = 3.0 m nearer), never at the
    # original far range
    res = simulate_fog(scan, 0.06, default_beta(0.06), lidar=FOG_LIDAR)
    fog = res.labels == FogLabel.SCATTERED
    np.testing.assert_allclose(np.linalg.norm(res.points[fog, :3], axis=1), 4.64 - 3.0, atol=0.01)
    # the same scan on the other intensity scale gives the same result
    factor = np.float32(1 / 255.0 if which == "stf" else 255.0)
    pts = scan.points.copy()
    pts[:, 3] *= factor
    other = replace(scan, points=pts, intensity_max=1.0 if which == "stf" else 255.0)
    res_other = simulate_fog(other, 0.06, default_beta(0.06), lidar=_lidar(5.0))
    res_same = simulate_fog(scan, 0.06, default_beta(0.06), lidar=_lidar(5.0))
    np.testing.assert_array_equal(res_other.input_labels, res_same.input_labels)
    np.testing.assert_allclose(res_other.points[:, 3], res_same.points[:, 3] * factor, rtol=1e-5, atol=1e-6)
    assert simulate_fog(scan, 0.0, 0.0, lidar=FOG_LIDAR).points.tobytes() == scan.points.tobytes()


@pytest.mark.parametrize(("q", "k"), [(1.0, 0.99), (2.0, 0.45)])
def test_a_rounded_reading_in_light_fog_is_kept_with_the_closed_form_share(q: float, k: float) -> None:
    """A clear reading q of an integer-quantised scan stood for a value uniform on [max(q - ½, floor), q + ½); a fog
    of two-way transmission T² = k (no backscatter, noise-free) keeps the target iff k x >= floor: a share
    (q + ½ - floor / k) / (q + ½ - max(q - ½, floor)), where a reading taken for exactly q is lost every time. The
    kept ones report k q; an unrounded reading (q + 0.001) is read as it is; `fog_intensities` given the scan's clear
    values (`scan_clear_readings`) decides the same."""
    n, r0, floor = 20000, 20.0, 1.0
    alpha = -np.log(k) / (2.0 * r0)
    want = (q + 0.5 - floor / k) / (q + 0.5 - max(q - 0.5, floor))
    d = np.random.default_rng(9).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for value, expected in ((q, want), (q + 1e-3, 0.0)):
        pts = np.column_stack([d * r0, np.full(n, value), np.zeros(n)]).astype(np.float32)
        scan = LidarScan(points=pts, timestamp=0.0, T_ego_lidar=np.eye(4), T_global_ego=np.eye(4))
        res = simulate_fog(scan, alpha, 0.0, lidar=_lidar(floor))
        kept = np.mean(res.input_labels != FogLabel.LOST)
        assert abs(kept - expected) <= 4 * np.sqrt(max(expected * (1 - expected), 1e-9) / n), (value, kept)
        np.testing.assert_allclose(res.points[:, 3], np.float32(value) * k, rtol=1e-6)
        from weatheralign.lidar.quantum import on_scale, scan_clear_readings

        clear = scan_clear_readings(scan, floor)
        arr = fog_intensities(np.full(n, r0), pts[:, 3], alpha, 0.0, intensity=RAW, sensor=SENSOR, noise_floor=floor,
                              clear_values=None if clear is None else on_scale(clear, pts[:, 3], 255.0))
        np.testing.assert_array_equal(arr.labels, res.input_labels)


def test_a_fog_echo_is_reported_through_the_compensation_at_its_own_range() -> None:
    """The receiver picks the echo on raw power and reports it as ``P R_e² g(R_e)``: for any intensity model the fog
    echo reads ``I(R_0) i_0 β / β_0 · R_e² g(R_e) / g(R_0)`` (closed form from the tabulated response), which is
    Hahner's ``I(R_0) i_0 R_0² β / β_0`` for the raw-power sensor; which points scatter does not depend on it."""
    from weatheralign.sensors import CALIBRATED_INTENSITY, SYNTHETIC_INTENSITY

    alpha, beta = 0.06, default_beta(0.06)
    r0 = np.linspace(20.0, 110.0, 400)
    i0 = np.full(len(r0), 100.0, np.float32)
    integral, r_fog = soft_target_response(alpha, SENSOR)(r0)
    r_e = np.clip(r_fog - SENSOR.pulse_length / 2.0, SENSOR.r1, np.minimum(r0, SENSOR.max_range))
    labels = None
    for model in (RAW, SYNTHETIC_INTENSITY, CALIBRATED_INTENSITY):
        res = fog_intensities(r0, i0, alpha, beta, intensity=model, sensor=SENSOR, noise_floor=None)
        fog = res.labels == FogLabel.SCATTERED
        assert fog.sum() > 100
        expected = integral * 100.0 * beta / SENSOR.beta_0 * model.compensation(r_e) / model.gain(r0)
        np.testing.assert_allclose(res.intensity[fog], np.minimum(expected[fog], SENSOR.saturation), rtol=1e-9)
        labels = res.labels if labels is None else labels
        np.testing.assert_array_equal(res.labels, labels)
    hahner = integral * 100.0 * r0 * r0 * beta / SENSOR.beta_0
    raw = fog_intensities(r0, i0, alpha, beta, intensity=RAW, sensor=SENSOR, noise_floor=None)
    fog = raw.labels == FogLabel.SCATTERED
    np.testing.assert_allclose(raw.intensity[fog], np.minimum(hahner[fog], SENSOR.saturation), rtol=1e-9)


def test_a_raw_power_detector_has_a_floor_that_grows_with_the_reported_range() -> None:
    """`LidarModel.floor_range_m`: the floor on the reported scale is ``f R² g(R) / (r_f² g(r_f))`` (the kernels'
    scalar agrees with `LidarModel.floor_at`); attenuated targets are lost against the floor at their own range."""
    from weatheralign.sensors import floor_factor

    lidar = _lidar(5.0, floor_range_m=35.0)
    r = np.array([0.5, 1.6, 10.0, 35.0, 80.0])
    g = lidar.intensity.gain(r)
    np.testing.assert_allclose(lidar.floor_at(r), 5.0 * r * r * g / (35.0 ** 2 * float(lidar.intensity.gain(35.0))))
    det = lidar.detector()
    np.testing.assert_allclose([5.0 * floor_factor(x, det.r_ref, det.falloff, det.comp_ref) for x in r],
                               lidar.floor_at(r), rtol=1e-12)
    np.testing.assert_array_equal(_lidar(5.0).floor_at(r), 5.0)
    assert LidarModel.from_dict(lidar.to_dict()) == lidar and "floor_range_m" not in _lidar(5.0).to_dict()
    with pytest.raises(ValueError, match="floor_range_m"):
        _lidar(5.0, floor_range_m=-1.0)
    # targets of reading 3 between 10 and 100 m in a thin fog: kept exactly where T² · 3 reaches the floor there
    r0 = np.linspace(10.0, 100.0, 901)
    res = fog_intensities(r0, np.full(len(r0), 3.0, np.float32), 1e-4, 0.0, intensity=lidar.intensity,
                          sensor=SENSOR, noise_floor=5.0, floor_range_m=35.0)
    below = np.exp(-2e-4 * r0) * 3.0 < lidar.floor_at(r0)
    np.testing.assert_array_equal(res.labels == FogLabel.LOST, below)
    assert 0 < below.sum() < len(r0)
