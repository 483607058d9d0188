"""Velocity from the sweeps (weatheralign.detect.sweep_motion): the FFT correlation against direct sums, known
motions recovered from a moving synthetic car, static clutter left at rest, the heading turned by the motion."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.detect.sweep_motion import (
    SweepMatching,
    apply_sweep_motion,
    correlate_profiles,
    correlate_profiles_naive,
    peak_shift,
    sweep_velocities,
)

LAGS = (0.0, 0.05, 0.1)


def car_surface(rng: np.random.Generator, n: int) -> np.ndarray:
    """(~4/3 n, 3) points on the visible side and rear of a 4.5 x 1.8 m car with a cabin behind its centre,
    car frame (x forward) [m]."""
    along = rng.uniform(-2.25, 2.25, n)
    cabin = np.abs(along + 0.2) < 1.2
    side = np.column_stack([along, np.full(n, -0.9), rng.uniform(-0.7, 0.3 + 0.4 * cabin, n)])
    across = rng.uniform(-0.9, 0.9, n // 3)
    rear = np.column_stack([np.full(n // 3, -2.25), across, rng.uniform(-0.7, 0.2, n // 3)])
    return np.vstack([side, rear])


def moving_car_points(speed: float, yaw: float, centre: tuple[float, float, float], seed: int = 0) -> np.ndarray:
    """(N, 5) points ``x, y, z, intensity, lag`` of one car seen in three sweeps while it drives at ``speed`` [m/s]
    along ``yaw``: each sweep samples the surface anew, ``speed * lag`` behind the keyframe's position."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    sweeps = []
    for lag in LAGS:
        local = car_surface(rng, 300)
        local[:, 0] -= speed * lag
        xyz = local @ rotation.T + np.asarray(centre)
        sweeps.append(np.column_stack([xyz, np.zeros(len(xyz)), np.full(len(xyz), lag)]))
    return np.vstack(sweeps)


def box_row(yaw: float, centre: tuple[float, float, float]) -> np.ndarray:
    return np.array([*centre, 1.8, 4.5, 1.5, yaw, 0.0, 0.0])


def test_fft_correlation_equals_direct_sums() -> None:
    rng = np.random.default_rng(1)
    keyframe, earlier = rng.random((4, 37, 5)), rng.random((4, 37, 5))
    for max_shift in (0, 3, 12):
        np.testing.assert_allclose(correlate_profiles(keyframe, earlier, max_shift),
                                   correlate_profiles_naive(keyframe, earlier, max_shift), atol=1e-9)


def test_peak_shift_refines_a_parabola_exactly() -> None:
    shifts = np.arange(-5, 6) * 0.1
    scores = -((shifts - 0.237) ** 2)[None, :]
    assert peak_shift(scores, 0.1)[0] == pytest.approx(0.237, abs=1e-9)


@pytest.mark.parametrize("speed", [-9.0, -2.5, 0.0, 4.0, 13.0])
@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.4])
def test_known_speed_recovered(speed: float, yaw: float) -> None:
    centre = (12.0, -6.0, -1.0)
    motion = sweep_velocities(moving_car_points(speed, yaw, centre), box_row(yaw, centre)[None])
    assert motion.speed_along[0] == pytest.approx(speed, abs=0.4)
    np.testing.assert_allclose(motion.lags, [0.05, 0.1])


def test_reversed_box_measures_the_opposite_speed_and_is_turned_around() -> None:
    centre, yaw = (8.0, 3.0, -1.0), 0.4
    boxes = np.stack([box_row(yaw, centre), box_row(yaw + np.pi, centre)])
    motion = sweep_velocities(moving_car_points(7.0, yaw, centre), boxes)
    assert motion.speed_along[0] == pytest.approx(7.0, abs=0.4)
    assert motion.speed_along[1] == pytest.approx(-motion.speed_along[0])
    out = apply_sweep_motion(boxes, motion)
    np.testing.assert_allclose(out[:, 6], [yaw, yaw], atol=1e-12)  # the reversed one turned around
    np.testing.assert_allclose(out[0, 7:9], out[1, 7:9], atol=1e-12)  # one velocity, whichever way the box faced
    np.testing.assert_allclose(np.hypot(*out[0, 7:9]), motion.speed_along[0], rtol=1e-12)
    never = apply_sweep_motion(boxes, motion, SweepMatching(flip_speed_mps=np.inf))
    np.testing.assert_allclose(never[:, 6], boxes[:, 6])
    np.testing.assert_allclose(never[:, 7:9], out[:, 7:9], atol=1e-12)
    assert boxes[1, 6] == pytest.approx(yaw + np.pi)  # the input is not modified


def test_static_car_beside_a_moving_one_stays_at_rest() -> None:
    static = moving_car_points(0.0, 0.0, (10.0, 4.0, -1.0), seed=3)
    moving = moving_car_points(10.0, 0.0, (10.0, -4.0, -1.0), seed=4)
    boxes = np.stack([box_row(0.0, (10.0, 4.0, -1.0)), box_row(0.0, (10.0, -4.0, -1.0))])
    motion = sweep_velocities(np.vstack([static, moving]), boxes)
    assert motion.speed_along[0] == pytest.approx(0.0, abs=0.3)
    assert motion.speed_along[1] == pytest.approx(10.0, abs=0.4)


def test_too_few_points_or_disagreeing_sweeps_give_no_speed() -> None:
    centre, yaw = (20.0, 0.0, -1.0), 0.0
    points = moving_car_points(6.0, yaw, centre)
    sparse = points[::60]  # 5 points per sweep
    assert np.isnan(sweep_velocities(sparse, box_row(yaw, centre)[None]).speed_along[0])
    # the second earlier sweep moved as if the car went the other way: no single speed fits both
    contradicting = points.copy()
    last = contradicting[:, 4] == 0.1
    contradicting[last, 0] += 2 * 6.0 * 0.1
    motion = sweep_velocities(contradicting, box_row(yaw, centre)[None])
    assert np.isnan(motion.speed_along[0])
    assert np.isfinite(motion.shifts[0]).all()
    kept = apply_sweep_motion(np.array([[*box_row(yaw, centre)[:7], 1.5, 0.0]]), motion)
    np.testing.assert_allclose(kept[0, 7:9], [1.5, 0.0])  # the network's velocity stays


def test_no_earlier_sweep_or_no_boxes() -> None:
    points = moving_car_points(5.0, 0.0, (10.0, 0.0, -1.0))
    keyframe_only = points[points[:, 4] == 0]
    assert np.isnan(sweep_velocities(keyframe_only, box_row(0.0, (10.0, 0.0, -1.0))[None]).speed_along).all()
    assert sweep_velocities(points, np.zeros((0, 9))).speed_along.shape == (0,)


def test_apply_to_limits_the_boxes_changed() -> None:
    centre, yaw = (8.0, 3.0, -1.0), 0.4
    boxes = np.stack([box_row(yaw + np.pi, centre)] * 2)
    motion = sweep_velocities(moving_car_points(7.0, yaw, centre), boxes)
    out = apply_sweep_motion(boxes, motion, apply_to=np.array([True, False]))
    assert out[0, 6] == pytest.approx(yaw)
    np.testing.assert_array_equal(out[1], boxes[1])


def test_detector_measures_movers_and_leaves_static_classes() -> None:
    import torch

    from weatheralign.detect.model import STATIC_CLASSES, sample_points, with_sweep_motion
    from weatheralign.detect.types import DETECTION_CLASSES, SampleDetections

    centre, yaw = (8.0, 3.0, -1.0), 0.4
    points = moving_car_points(7.0, yaw, centre)
    batched = torch.cat([torch.cat([torch.full((len(points), 1), 1.0), torch.from_numpy(points)], 1),
                         torch.zeros(5, 6)]).float()
    mine = sample_points(batched, 1)
    assert mine.shape == (len(points), 5)
    np.testing.assert_allclose(mine, points, atol=1e-5)
    reversed_box = np.array([[*box_row(yaw + np.pi, centre)[:7], 0.1, 0.2]] * 2)
    labels = np.array([DETECTION_CLASSES.index("car"), DETECTION_CLASSES.index(STATIC_CLASSES[1])])
    out = with_sweep_motion(SampleDetections("t", reversed_box, np.array([0.9, 0.8]), labels, np.array([-1, -1])),
                            mine)
    assert out.boxes[0, 6] == pytest.approx(yaw, abs=1e-6)
    assert np.hypot(*out.boxes[0, 7:9]) == pytest.approx(7.0, abs=0.4)
    np.testing.assert_array_equal(out.boxes[1], reversed_box[1])
    np.testing.assert_array_equal(out.scores, [0.9, 0.8])


def test_position_map_spans_the_grid() -> None:
    import torch

    from weatheralign.detect.model import position_map

    grid = position_map(torch.zeros(2, 3, 4, 8))
    assert grid.shape == (2, 2, 4, 8)
    torch.testing.assert_close(grid[0, 0, 0], (torch.arange(8) + 0.5) / 8 * 2 - 1)
    torch.testing.assert_close(grid[1, 1, :, 5], (torch.arange(4) + 0.5) / 4 * 2 - 1)


def test_low_scoring_detections_keep_the_heads_velocity() -> None:
    from weatheralign.detect.model import with_sweep_motion
    from weatheralign.detect.types import DETECTION_CLASSES, SampleDetections

    centre, yaw = (8.0, 3.0, -1.0), 0.4
    boxes = np.array([[*box_row(yaw, centre)[:7], 0.1, 0.2]] * 2)
    car = DETECTION_CLASSES.index("car")
    settings = SweepMatching(min_score=0.5)
    out = with_sweep_motion(SampleDetections("t", boxes, np.array([0.6, 0.4]), np.array([car, car]),
                                             np.array([-1, -1])), moving_car_points(7.0, yaw, centre), settings)
    assert np.hypot(*out.boxes[0, 7:9]) == pytest.approx(7.0, abs=0.4)
    np.testing.assert_array_equal(out.boxes[1], boxes[1])
