"""ReDAM for the ground: the statistics answer to the depth as the physics says, and the fit finds a depth back."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.calibrate.ground import (
    fit_depth,
    ground_statistic,
    simulated_ground_statistics,
    snow_ground_height,
)
from weatheralign.calibrate.precipitation import _invert

from .test_ground_edit import HEIGHT_M, street_scan


def test_the_bare_ground_height_is_the_sensors() -> None:
    assert snow_ground_height(street_scan()) == pytest.approx(HEIGHT_M, abs=0.01)


def test_snow_raises_the_ground_by_its_depth_and_a_film_dims_it() -> None:
    scans = [street_scan(seed) for seed in range(3)]
    names = [f"scan-{seed}" for seed in range(3)]
    depths = (0.02, 0.08)
    height = simulated_ground_statistics(scans, names, "snow", depths, noise_floor=1.0)
    bare = np.array([snow_ground_height(s) for s in scans])
    lift = bare[None, :] - height  # (D, F): wheel tracks hold less snow, the variation averages out
    assert np.all(lift > 0.6 * np.asarray(depths)[:, None]) and np.all(lift < 1.1 * np.asarray(depths)[:, None])
    films = (0.0001, 0.0004, 0.0008)
    intensity = simulated_ground_statistics(scans, names, "rain", films, noise_floor=1.0)
    dry = np.array([ground_statistic(s, "rain") for s in scans])
    assert np.all(np.diff(intensity, axis=0) < 0) and np.all(intensity < dry[None, :])
    # the same scans at the same depth: the same statistic (the fields are seeded from the names)
    again = simulated_ground_statistics(scans, names, "rain", films[:1], noise_floor=1.0)
    np.testing.assert_array_equal(again[0], intensity[0])


def test_fit_depth_inverts_a_linear_statistic_and_brackets_it() -> None:
    rng = np.random.default_rng(0)
    depths = (0.01, 0.04, 0.16)
    truth = 0.07
    simulated = 1.9 - np.asarray(depths)[:, None] + rng.normal(0, 0.01, (3, 40))
    reference = 1.9 - truth + rng.normal(0, 0.01, 30)
    fit = fit_depth(reference, simulated, depths, "snow", num_bootstrap=300)
    assert fit.depth_m == pytest.approx(truth, abs=0.006)
    assert fit.ci_low < truth < fit.ci_high and not fit.beyond_grid
    assert fit.metrics()["statistic"].startswith("LiDAR height")
    # frames without a ground (nan) are left out, not averaged in
    with_nan = np.concatenate([reference, [np.nan]])
    assert fit_depth(with_nan, simulated, depths, "snow", num_bootstrap=50).depth_m == pytest.approx(fit.depth_m)


def test_linear_inversion_is_exact_on_a_line_and_clipped_beyond() -> None:
    grid = np.array([1.0, 2.0, 4.0])
    means = 10.0 - 2.0 * grid
    assert _invert(5.0, means, grid, log_axes=False) == pytest.approx(2.5)
    assert _invert(-100.0, means, grid, log_axes=False) == pytest.approx(8.0)  # at most 2x beyond the grid
