"""Isolated returns (weather clutter) counted on points alone: surfaces have neighbours, lone particles do not."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.lidar.clutter import isolated_returns

from .conftest import REPO

STF_SCAN = REPO.parent / "shared" / "data" / "real" / "stf" / "lidar_hdl64_strongest_2019-09-11_19-13-44_00960.bin"


def _ground_rings(step: float) -> np.ndarray:
    """Rings of an HDL-64-like scan on flat ground (1.95 m below the sensor), one point per azimuth step."""
    az = np.arange(0.0, 2 * np.pi, step)
    out = []
    for el in np.deg2rad(np.linspace(-24.0, -4.0, 40)):
        r = 1.95 / np.sin(-el)
        out.append(np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), np.full_like(az, -1.95)], 1))
    return np.concatenate(out)


def test_surfaces_are_not_clutter_and_lone_points_are():
    step = 2 * np.pi / 1800
    ground = _ground_rings(step)
    assert isolated_returns(ground, azimuth_step_rad=step) == 0
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(50, 3))
    direction[:, 2] = np.abs(direction[:, 2])  # above the ground, far from each other
    flakes = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(2.0, 15.0, (50, 1))
    flakes = flakes[np.min(np.linalg.norm(flakes[:, None] - flakes[None], axis=2) + 1e9 * np.eye(50), axis=1) > 1.0]
    assert isolated_returns(np.concatenate([ground, flakes]), azimuth_step_rad=step) == len(flakes)
    far = flakes * (30.0 / np.linalg.norm(flakes, axis=1, keepdims=True))
    assert isolated_returns(np.concatenate([ground, far]), azimuth_step_rad=step) == 0  # beyond max_range
    pair = np.array([[5.0, 0.0, 0.0], [5.0, 0.05, 0.0]])  # two returns on neighbouring beams: a surface
    assert isolated_returns(pair, azimuth_step_rad=step) == 0
    assert isolated_returns(pair[:1], azimuth_step_rad=step) == 1
    assert isolated_returns(np.zeros((0, 3)), azimuth_step_rad=step) == 0


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"xyz must be \(N, 3\)"):
        isolated_returns(np.zeros((4, 2)), azimuth_step_rad=0.003)
    with pytest.raises(ValueError, match="azimuth_step_rad = 0"):
        isolated_returns(np.zeros((4, 3)), azimuth_step_rad=0)


def test_a_real_clear_scan_has_little_clutter():
    if not STF_SCAN.exists():
        pytest.skip(f"real sample not available: {STF_SCAN}")
    pts = np.fromfile(STF_SCAN, "<f4").reshape(-1, 5)
    n = isolated_returns(pts[:, :3], azimuth_step_rad=2 * np.pi / 2000)
    near = int((np.linalg.norm(pts[:, :3], axis=1) < 20.0).sum())
    assert n < 0.01 * near  # a clear HDL-64 scan: under 1 % of its near returns are isolated
