"""Lying snow: the returns move along their beams onto the raised surface; one depth field of world position."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.ground.snow import SnowCover, snow_covered_ground, snow_depth


def test_returns_move_along_their_beams_onto_the_snow_surface() -> None:
    rng = np.random.default_rng(0)
    origin = np.array([0.3, -0.2, 1.8])
    normal = np.array([0.02, -0.03, 1.0])
    normal /= np.linalg.norm(normal)
    xy = rng.uniform(-40, 40, (500, 2))
    ground = np.column_stack([xy, -(normal[0] * xy[:, 0] + normal[1] * xy[:, 1]) / normal[2]])  # plane through 0
    depth = rng.uniform(0.01, 0.2, 500)
    effect = snow_covered_ground(ground, origin, normal, np.full(500, 10.0), depth, SnowCover())
    np.testing.assert_allclose((effect.points - ground) @ normal, depth, atol=1e-9)  # on the raised plane
    before, after = ground - origin, effect.points - origin
    np.testing.assert_allclose(np.cross(before, after), 0.0, atol=1e-9)  # on the same beam
    assert np.all(np.linalg.norm(after, axis=1) < np.linalg.norm(before, axis=1))  # nearer the sensor
    # the range shortens by d / cos(theta)
    cos_theta = np.abs(before @ normal) / np.linalg.norm(before, axis=1)
    np.testing.assert_allclose(np.linalg.norm(before, axis=1) - np.linalg.norm(after, axis=1), depth / cos_theta,
                               rtol=1e-9)


def test_snow_answers_with_its_reflectivity_up_to_saturation() -> None:
    cover = SnowCover(snow_reflectivity=0.8, pavement_reflectivity=0.2)
    effect = snow_covered_ground(np.array([[10.0, 0, -1.8], [20.0, 0, -1.8]]), np.zeros(3), np.array([0, 0, 1.0]),
                                 np.array([30.0, 100.0]), np.array([0.05, 0.05]), cover)
    assert effect.intensity.tolist() == [120.0, 255.0]


def test_snow_depth_is_one_field_of_world_position() -> None:
    cover = SnowCover(depth_m=0.1, variation=0.5)
    xy = np.random.default_rng(1).uniform(-500, 500, (50_000, 2))
    depth = snow_depth(xy, cover, seed=2)
    assert np.array_equal(snow_depth(xy[::5], cover, seed=2), depth[::5])
    assert depth.min() >= 0.05 and depth.max() <= 0.15
    assert depth.mean() == pytest.approx(0.1, rel=0.05)
    assert not np.array_equal(snow_depth(xy, cover, seed=3), depth)


def test_bad_cover_is_refused() -> None:
    with pytest.raises(ValueError, match="variation"):
        SnowCover(variation=1.0)
    with pytest.raises(ValueError, match="snow_reflectivity"):
        SnowCover(snow_reflectivity=0.0)
