"""A clear reading's rounding interval (`weatheralign.lidar.quantum`): which readings a sensor rounded, the interval
each stood for, the beam's uniform draw that places it there (kernel against its Python-integer oracle), and the
same bytes for the same scan."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from weatheralign.data.frame import LidarScan
from weatheralign.lidar.beams import detector_noise_keys, point_noise_keys
from weatheralign.lidar.quantum import (
    clear_readings,
    on_scale,
    reading_uniforms,
    reading_uniforms_naive,
    rounded_readings,
    rounding_interval,
    scan_clear_readings,
)
from weatheralign.medium.field import normal_pair


def _keys(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return detector_noise_keys(1.5e9 + rng.uniform(0.0, 0.05, n), d, rng.integers(0, 64, n).astype(np.float32))


def _scan(intensity: np.ndarray, intensity_max: float = 255.0) -> LidarScan:
    n = len(intensity)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(-2, 1, n), intensity,
                           rng.integers(0, 32, n)]).astype(np.float32)
    return LidarScan(pts, 1.5e9, np.eye(4), np.eye(4), intensity_max=intensity_max)


def test_reading_uniforms_are_the_streams_third_draw_bit_for_bit_and_uniform():
    keys = _keys(20000)
    u = reading_uniforms(keys)
    assert np.array_equal(u, reading_uniforms_naive(keys))
    for counter in (3, 4):  # any draw of the stream (the wet reading's noise takes 3 and 4)
        other = reading_uniforms(keys[:2000], counter)
        assert np.array_equal(other, reading_uniforms_naive(keys[:2000], counter))
        assert abs(np.corrcoef(other, u[:2000])[0, 1]) < 4 / math.sqrt(2000)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert abs(u.mean() - 0.5) < 4 * math.sqrt(1 / 12 / len(u))
    assert abs(np.mean(u < 0.25) - 0.25) < 4 * math.sqrt(0.25 * 0.75 / len(u))
    # independent of the intensity and range noise the same stream gives (draws 0 and 1)
    z = np.array([normal_pair(k)[0] for k in keys[:5000]])
    assert abs(np.corrcoef(z, u[:5000])[0, 1]) < 4 / math.sqrt(5000)


def test_rounding_interval_stops_at_the_floor():
    lo, hi = rounding_interval(np.array([1.0, 2.0, 5.0, 0.0]), 1.0)
    np.testing.assert_array_equal(lo, [1.0, 1.5, 4.5, 1.0])
    np.testing.assert_array_equal(hi, [1.5, 2.5, 5.5, 0.5])  # 0: under the floor, reported nevertheless: empty
    lo, hi = rounding_interval(np.array([0.0, 3.0]), None)
    np.testing.assert_array_equal(lo, [0.0, 2.5])
    np.testing.assert_array_equal(hi, [0.5, 3.5])


def test_which_readings_were_rounded_is_read_from_the_data():
    rng = np.random.default_rng(1)
    whole = rng.integers(1, 200, 1000).astype(np.float64)
    assert rounded_readings(whole).all()
    assert not rounded_readings(whole + rng.uniform(0.01, 0.99, 1000)).any()  # unrounded readings
    edited = whole.copy()
    edited[:700] *= 0.37  # a ground edit changed 70 % of them: the rest are still the sensor's integers
    got = rounded_readings(edited)
    np.testing.assert_array_equal(got, edited == np.rint(edited))
    assert got[700:].all()
    # 0 and saturation are not counted, an empty scan has none
    assert not rounded_readings(np.array([0.0, 255.0, 0.0])).any()
    assert rounded_readings(np.zeros(0)).shape == (0,)
    # a 0..1 scan's q / 255, stored as float32, comes back as q
    q = np.arange(1, 255)
    assert rounded_readings((q / 255.0).astype(np.float32) * np.float32(255.0)).all()


def test_clear_readings_spread_uniformly_over_the_interval_and_leave_the_rest_bit_for_bit():
    n = 40000
    keys = _keys(n, seed=2)
    i0 = np.where(np.arange(n) % 2 == 0, 1.0, 7.0)
    rounded = np.arange(n) % 5 != 0
    x = clear_readings(i0, rounded, 1.0, reading_uniforms(keys))
    np.testing.assert_array_equal(x[~rounded], i0[~rounded])
    lo, hi = rounding_interval(i0, 1.0)
    assert np.all((x[rounded] >= lo[rounded]) & (x[rounded] < hi[rounded]))
    at_floor = rounded & (i0 == 1.0)
    share = (x[at_floor] - 1.0) / 0.5  # uniform on [1, 1.5)
    assert abs(share.mean() - 0.5) < 4 * math.sqrt(1 / 12 / at_floor.sum())
    assert abs(x[rounded & (i0 == 7.0)].mean() - 7.0) < 4 * math.sqrt(1 / 12 / (rounded & (i0 == 7.0)).sum())


def test_a_scans_clear_readings_are_its_beams_and_the_same_bytes_every_time():
    rng = np.random.default_rng(4)
    scan = _scan(rng.integers(1, 60, 3000).astype(np.float64))
    x = scan_clear_readings(scan, 1.0)
    assert x is not None
    np.testing.assert_array_equal(x, scan_clear_readings(scan, 1.0))
    i0 = scan.intensity_255().astype(np.float64)
    np.testing.assert_array_equal(x, clear_readings(i0, np.ones(len(i0), bool), 1.0,
                                                    reading_uniforms(point_noise_keys(scan))))
    # unrounded readings: none spread
    assert scan_clear_readings(_scan(rng.uniform(1.0, 60.0, 3000)), 1.0) is None


@pytest.mark.parametrize("intensity_max", [255.0, 1.0])
def test_clear_values_on_the_scans_own_scale(intensity_max):
    rng = np.random.default_rng(5)
    q = rng.integers(1, 60, 2000).astype(np.float64)
    scan = _scan(q)
    other = replace(scan, points=np.column_stack([scan.points[:, :3], (q / 255.0).astype(np.float32),
                                                  scan.points[:, 4]]).astype(np.float32), intensity_max=1.0)
    use = scan if intensity_max == 255.0 else other
    x = scan_clear_readings(use, 1.0)
    np.testing.assert_array_equal(x, scan_clear_readings(scan, 1.0))  # the same values on 0..255 from either scale
    own = on_scale(x, use.points[:, 3], intensity_max)
    np.testing.assert_allclose(own * (255.0 / intensity_max), x, rtol=1e-12)
    unspread = on_scale(use.intensity_255().astype(np.float64), use.points[:, 3], intensity_max)
    assert unspread.tobytes() == use.points[:, 3].astype(np.float64).tobytes()
