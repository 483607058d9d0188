"""Lying snow: the returns move along their beams onto the raised surface; one depth field of world position."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.ground.snow import SnowCover, TireTracks, snow_coverage, snow_covered_ground, snow_depth


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


def test_tire_tracks_press_the_snow_where_the_wheels_ran() -> None:
    tracks = TireTracks(direction=(0.0, 2.0), origin=(10.0, 5.0), lane_offsets_m=(0.0,), gauge_m=1.6, width_m=0.4,
                        remaining_share=0.2, wander_m=0.0)
    along = np.linspace(-50, 50, 101)
    # the road runs along +y through (10, 5): the wheels run at x = 10 -+ 0.8 (left of +y is -x)
    for x, expected in ((9.2, 0.2), (10.8, 0.2), (10.0, 1.0), (9.2 + 0.2, 1.0), (13.0, 1.0)):
        xy = np.column_stack([np.full(101, x), 5.0 + along])
        np.testing.assert_allclose(tracks.depth_factor(xy, seed=0), expected, atol=1e-12)
    xy = np.column_stack([np.full(101, 9.2 + 0.1), 5.0 + along])  # half-way to the track's edge: raised cosine
    np.testing.assert_allclose(tracks.depth_factor(xy, seed=0), 1.0 - 0.8 * 0.5, atol=1e-12)
    cover = SnowCover(depth_m=0.1, variation=0.0)
    on_track = np.column_stack([np.full(3, 9.2), [0.0, 20.0, 40.0]])
    np.testing.assert_allclose(snow_depth(on_track, cover, seed=1, tracks=tracks), 0.02, atol=1e-12)
    wandering = TireTracks(direction=(0.0, 1.0), origin=(10.0, 5.0), lane_offsets_m=(0.0,), wander_m=0.15)
    factor = wandering.depth_factor(np.column_stack([np.full(2000, 9.2), np.linspace(-500, 500, 2000)]), seed=0)
    assert factor.min() < 0.35 and factor.max() > 0.75  # the track wanders off the straight line and back
    with pytest.raises(ValueError, match="direction"):
        TireTracks(direction=(0.0, 0.0), origin=(0.0, 0.0))


def test_snow_stays_on_surfaces_that_face_up() -> None:
    cover = SnowCover(hiding_depth_m=0.01, max_slope_deg=60.0)
    depth = np.full(4, 0.05)
    cos_up = np.array([1.0, 0.75, 0.5, 0.0])
    coverage, on_surface = snow_coverage(depth, cos_up, cover)
    weight = np.array([1.0, 0.5, 0.0, 0.0])  # (cos - cos 60) / (1 - cos 60)
    np.testing.assert_allclose(on_surface, weight * 0.05, atol=1e-12)
    np.testing.assert_allclose(coverage, weight * (1 - np.exp(-weight * 5.0)), atol=1e-12)


def test_partly_covered_footprints_mix_the_intensities() -> None:
    cover = SnowCover(snow_reflectivity=0.8, pavement_reflectivity=0.2)
    effect = snow_covered_ground(np.array([[10.0, 0, -1.8]] * 3), np.zeros(3), np.array([0, 0, 1.0]),
                                 np.full(3, 30.0), np.full(3, 0.05), cover, coverage=np.array([0.0, 0.5, 1.0]))
    assert effect.intensity.tolist() == [30.0, 75.0, 120.0]


def test_a_grazing_beam_enters_an_off_ground_layer_through_its_side() -> None:
    """On the ground plane the return moves d / cos(theta) (however grazing the beam); off it, a beam that would run
    more than the surface's edge run across the snow enters the layer through its side: run / sin(theta) nearer,
    inside the layer, never past the sensor."""
    cover = SnowCover(edge_run_m=0.5)
    cos_theta = np.array([0.9, 0.2, 0.01, 1e-7])  # a roof (normal +z) hit from the side ever more grazingly
    sin_theta = np.sqrt(1.0 - cos_theta**2)
    hits = np.column_stack([10.0 * sin_theta, np.zeros(4), -10.0 * cos_theta])  # 10 m from the sensor
    depth = np.full(4, 0.1)
    plane = snow_covered_ground(hits, np.zeros(3), np.array([0, 0, 1.0]), np.full(4, 10.0), depth, cover)
    np.testing.assert_allclose(10.0 - np.linalg.norm(plane.points[:3], axis=1), 0.1 / cos_theta[:3], rtol=1e-9)
    roof = snow_covered_ground(hits, np.zeros(3), np.array([0, 0, 1.0]), np.full(4, 10.0), depth, cover,
                               max_run_m=cover.edge_run_m)
    moved = 10.0 - np.linalg.norm(roof.points, axis=1)
    expected = np.minimum(0.1 / cos_theta, 0.5 / sin_theta)
    np.testing.assert_allclose(moved, expected, rtol=1e-9)
    assert moved[0] == pytest.approx(0.1 / 0.9) and moved[3] == pytest.approx(0.5)  # the top; the side
    height = (roof.points - hits) @ np.array([0, 0, 1.0])
    assert np.all(height <= 0.1 + 1e-12) and np.all(np.sum(roof.points * hits, axis=1) > 0)  # in the layer, ahead
    np.testing.assert_allclose(np.cross(hits, roof.points), 0.0, atol=1e-9)  # on the same beams
    with pytest.raises(ValueError, match="edge_run_m"):
        SnowCover(edge_run_m=0.0)


def test_the_depth_field_asked_only_where_snow_can_lie_changes_nothing() -> None:
    from weatheralign.ground.snow import surface_snow

    rng = np.random.default_rng(2)
    xy = rng.uniform(-40, 40, (5000, 2))
    cos_up = rng.uniform(0.0, 1.0, 5000)
    cover, tracks = SnowCover(), TireTracks(direction=(1.0, 0.2), origin=(3.0, -1.0))
    expected = snow_coverage(snow_depth(xy, cover, 5, tracks), cos_up, cover)
    found = surface_snow(xy, cos_up, cover, 5, tracks)
    for a, b in zip(found, expected, strict=True):
        assert np.array_equal(a, b)
    assert (found[0] == 0).any() and (found[0] > 0).any()
