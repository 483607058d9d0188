"""The wet road: water-film optics against closed forms and photon tracing, the water-depth field's invariants, and
the effect on ground returns."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.ground.optics import (
    fresnel_reflectance,
    hemispherical_reflectance,
    refraction_angle,
    wet_albedo,
    wet_lidar_factor,
    wet_lidar_factor_naive,
)
from weatheralign.ground.wet import WetRoad, incidence_angle, water_depth, wet_ground, wetted_share

N = 1.33


def test_fresnel_closed_forms() -> None:
    assert fresnel_reflectance(0.0, 1.0, N) == pytest.approx(((N - 1) / (N + 1)) ** 2, rel=1e-12)
    brewster = np.arctan(N)  # p vanishes: the unpolarised reflectance is s / 2
    cos_i, cos_t = np.cos(brewster), np.cos(refraction_angle(brewster, 1.0, N))
    rs = ((cos_i - N * cos_t) / (cos_i + N * cos_t)) ** 2
    assert fresnel_reflectance(brewster, 1.0, N) == pytest.approx(rs / 2, rel=1e-12)
    assert fresnel_reflectance(np.pi / 2 - 1e-9, 1.0, N) == pytest.approx(1.0, abs=1e-6)
    critical = np.arcsin(1 / N)
    assert fresnel_reflectance(critical + 1e-6, N, 1.0) == 1.0  # total internal reflection
    # the same interface crossed either way reflects the same share (Stokes)
    theta = np.radians(35.0)
    assert fresnel_reflectance(theta, 1.0, N) == pytest.approx(
        fresnel_reflectance(refraction_angle(theta, 1.0, N), N, 1.0), rel=1e-12)


def test_hemispherical_reflectances_obey_reciprocity() -> None:
    r_e, r_i = hemispherical_reflectance(1.0, N), hemispherical_reflectance(N, 1.0)
    assert N**2 * (1 - r_i) == pytest.approx(1 - r_e, rel=1e-9)
    assert 0.06 < r_e < 0.07 and 0.46 < r_i < 0.48
    # slow reference: a plain midpoint sum over the angle
    theta = (np.arange(200_000) + 0.5) * (np.pi / 2) / 200_000
    slow = np.sum(2 * fresnel_reflectance(theta, 1.0, N) * np.cos(theta) * np.sin(theta)) * (np.pi / 2) / 200_000
    assert r_e == pytest.approx(slow, rel=1e-6)


@pytest.mark.parametrize("degrees", [60.0, 70.0, 80.0])
@pytest.mark.parametrize("rho", [0.1, 0.5])
def test_wet_lidar_factor_matches_photon_tracing(degrees: float, rho: float) -> None:
    theta = np.radians(degrees)
    traced = wet_lidar_factor_naive(theta, rho, photons=2_000_000, seed=1)
    assert float(wet_lidar_factor(theta, rho)) == pytest.approx(traced, rel=0.05)


def test_wet_lidar_factor_physics() -> None:
    theta = np.radians(np.arange(55, 89))
    w = wet_lidar_factor(theta, 0.1)
    assert np.all(np.diff(w) < 0) and np.all(w < 0.6)  # darker when wet, the more so the more grazing
    assert np.all(wet_lidar_factor(theta, 0.5) > w)  # a brighter pavement gets more of its light back
    assert np.all(wet_lidar_factor(theta, 0.1, 0.01) < w)  # a deeper layer absorbs more at 905 nm
    # normal incidence: (1 - R0)^2 / (n^2 (1 - rho r_i))
    r0, r_i = ((N - 1) / (N + 1)) ** 2, hemispherical_reflectance(N, 1.0)
    assert float(wet_lidar_factor(0.0, 0.2)) == pytest.approx((1 - r0) ** 2 / (N**2 * (1 - 0.2 * r_i)), rel=1e-12)
    assert float(wet_albedo(0.1)) == pytest.approx(0.0518, abs=5e-4)


def test_water_depth_is_one_field_of_world_position() -> None:
    road = WetRoad(film_depth_m=0.0005, puddle_share=0.1)
    xy = np.random.default_rng(0).uniform(-300, 300, (100_000, 2))
    depth = water_depth(xy, road, seed=4)
    assert np.array_equal(water_depth(xy[::7], road, seed=4), depth[::7])  # any subset, same values
    assert not np.array_equal(water_depth(xy, road, seed=5), depth)
    puddles = depth == road.puddle_depth_m
    assert puddles.mean() == pytest.approx(0.1, abs=0.02)
    assert depth[~puddles].mean() == pytest.approx(road.film_depth_m, rel=0.1)
    assert np.all(water_depth(xy, WetRoad(puddle_share=0.0), seed=4) < 2 * road.film_depth_m)


def test_wet_ground_effect() -> None:
    road = WetRoad(texture_depth_m=0.001)
    assert np.array_equal(wetted_share(np.array([0.0, 0.0005, 0.002]), 0.001), [0.0, 0.5, 1.0])
    theta = np.radians([60.0, 80.0, 88.0, 80.0])
    intensity = np.array([20.0, 20.0, 20.0, 0.3])
    effect = wet_ground(intensity, theta, np.full(4, 0.002), road, noise_floor=0.5)
    expected = intensity * wet_lidar_factor(theta, road.pavement_reflectivity, 0.002)
    assert effect.intensity[:2] == pytest.approx(expected[:2], rel=1e-12)
    assert effect.lost.tolist() == [False, False, True, False]  # 20 x 0.02 falls below the floor; 0.3 was below
    dry = wet_ground(intensity, theta, np.zeros(4), road, noise_floor=0.5)
    assert np.array_equal(dry.intensity, intensity) and not dry.lost.any()


def test_incidence_angle() -> None:
    points = np.array([[10.0, 0.0, -1.8], [0.0, 0.0, -1.8]])
    theta = incidence_angle(points, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    assert theta == pytest.approx([np.arctan2(10.0, 1.8), 0.0])


def test_bad_road_is_refused() -> None:
    with pytest.raises(ValueError, match="puddle_share"):
        WetRoad(puddle_share=1.5)
    with pytest.raises(ValueError, match="film_depth_m"):
        WetRoad(film_depth_m=0.0)


@pytest.mark.parametrize(("q", "depth_m"), [(1.0, 0.0001), (2.0, 0.0007)])
def test_a_rounded_reading_under_a_film_is_kept_with_the_closed_form_share(q: float, depth_m: float) -> None:
    """An integer reading q at a floor of 1 stood for a value uniform on [max(q - ½, 1), q + ½) (`clear_readings`);
    the film's factor f keeps it iff f x >= 1: a share (q + ½ - 1 / f) / (q + ½ - max(q - ½, 1)), its wet intensity
    f x. Read as exactly q (``clear=None``) every such reading is lost (q f < 1)."""
    from weatheralign.lidar.quantum import clear_readings, reading_uniforms

    n, floor = 20000, 1.0
    road = WetRoad()
    theta, depth, dry = np.full(n, np.radians(80.0)), np.full(n, depth_m), np.full(n, q)
    f = float(wet_ground(dry[:1], theta[:1], depth[:1], road, floor).factor[0])
    lo = max(q - 0.5, floor)
    want = (q + 0.5 - floor / f) / (q + 0.5 - lo)
    assert 0.1 < want < 0.95 and q * f < floor
    keys = np.arange(n, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(12345)
    x = clear_readings(dry, np.ones(n, bool), floor, reading_uniforms(keys))
    effect = wet_ground(dry, theta, depth, road, floor, clear=x)
    kept = 1.0 - effect.lost.mean()
    assert abs(kept - want) <= 4 * np.sqrt(want * (1 - want) / n)
    np.testing.assert_allclose(effect.intensity[~effect.lost], f * x[~effect.lost], rtol=1e-12)
    assert effect.intensity[~effect.lost].min() >= floor
    assert wet_ground(dry, theta, depth, road, floor).lost.all()
    # an unrounded reading passes through clear_readings as it is: the film dims that value
    same = wet_ground(dry, theta, depth, road, floor, clear=dry)
    assert same.intensity.tobytes() == wet_ground(dry, theta, depth, road, floor).intensity.tobytes()


def test_the_wet_reading_gets_the_detector_noise_the_film_took_from_the_clear_one() -> None:
    """A clear reading v carries the detector's noise σ_0; the film's factor f dims it with the signal, so the wet
    reading lacks σ_0² (1 - f²) of its variance: the wet readings of one value are N(v f, σ_0² (1 - f²)) (clipped
    at 0), lost below the floor with probability Φ((floor - v f) / (σ_0 sqrt(1 - f²))); without a film (f = 1)
    nothing is added; no noise without normals is refused."""
    from scipy.stats import norm

    n, v, s0, floor = 40000, 2.0, 0.5, 1.0
    road = WetRoad()
    theta, depth = np.full(n, np.radians(80.0)), np.full(n, 0.0005)
    z = np.random.default_rng(3).standard_normal(n)
    quiet = wet_ground(np.full(n, v), theta, depth, road, floor)
    f = float(quiet.factor[0])
    effect = wet_ground(np.full(n, v), theta, depth, road, floor, noise_std=s0, normals=z)
    sd = s0 * np.sqrt(1.0 - f * f)
    np.testing.assert_allclose(effect.intensity[~effect.lost], np.clip(v * f + sd * z, 0.0, 255.0)[~effect.lost],
                               rtol=1e-12)
    p_lost = norm.cdf((floor - v * f) / sd)
    assert abs(effect.lost.mean() - p_lost) < 4 * np.sqrt(p_lost * (1 - p_lost) / n)
    assert not quiet.lost.any()  # v f = 1.26: noise-free, every one is kept
    dry = wet_ground(np.full(n, v), theta, np.zeros(n), road, floor, noise_std=s0, normals=z)
    assert np.array_equal(dry.intensity, np.full(n, v)) and not dry.lost.any()
    with pytest.raises(ValueError, match="normals"):
        wet_ground(np.full(n, v), theta, depth, road, floor, noise_std=s0)
