"""One ground state edits a LiDAR scan and a camera image on the same surfaces: the scan's rows map back to the
input, the wet film's losses are the ones under the floor, snow raises exactly the up-facing returns, and the camera
edits the pixels the LiDAR's edited returns land on."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from weatheralign.data.frame import LidarScan
from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.edit import (
    BLOCKED_REACH_SHARE,
    BRIGHT_ROAD_FLOORS,
    NEIGHBOUR_WINDOW_STEPS,
    GroundState,
    UnseenBeams,
    dark_road_misses,
    edit_image,
    edit_scan,
    road_reflectivity,
    scan_surfaces,
    unseen_beams,
)
from weatheralign.ground.snow import SnowCover, TireTracks, snow_coverage
from weatheralign.ground.surfaces import mask_agreement
from weatheralign.ground.wet import WetRoad, incidence_angle, water_depth, wet_ground
from weatheralign.lidar.beams import detector_noise_keys
from weatheralign.sensors import SYNTHETIC_INTENSITY

HEIGHT_M = 1.8


def street_scan(seed: int = 0) -> LidarScan:
    """A LiDAR 1.8 m above flat ground (world z = 0) with a wall 15 m ahead (x = 15, 4 m tall) and a flat box roof
    (1.5 m high, x 4..9, y 2..4): rings of returns, sensor at world (100, 50) heading +x."""
    rng = np.random.default_rng(seed)
    azimuth = np.repeat(np.linspace(-np.pi, np.pi, 720, endpoint=False), 32)
    elevation = np.tile(np.radians(np.linspace(-25, 2, 32)), 720)
    d = np.column_stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -HEIGHT_M / d[:, 2], np.inf)
        t_wall = np.where(d[:, 0] > 0, 15.0 / d[:, 0], np.inf)
        t_wall = np.where(HEIGHT_M + t_wall * d[:, 2] <= 4.0, t_wall, np.inf)
        t_roof = np.where(d[:, 2] < 0, -(HEIGHT_M - 1.5) / d[:, 2], np.inf)
    with np.errstate(invalid="ignore"):
        roof_xy = t_roof[:, None] * d[:, :2]
    on_roof = (roof_xy[:, 0] > 4) & (roof_xy[:, 0] < 9) & (roof_xy[:, 1] > 2) & (roof_xy[:, 1] < 4)
    t_roof = np.where(on_roof, t_roof, np.inf)
    t = np.minimum(np.minimum(t_ground, t_wall), t_roof)
    hit = np.isfinite(t) & (t < 60)
    xyz = d[hit] * t[hit, None] + rng.normal(0, 0.005, (int(hit.sum()), 3))
    intensity = rng.uniform(5, 60, int(hit.sum()))
    points = np.column_stack([xyz, intensity, np.zeros(len(xyz))]).astype(np.float32)
    T = np.eye(4)
    T[:3, 3] = [100.0, 50.0, HEIGHT_M]
    return LidarScan(points, 0.0, np.eye(4), T)


def on_box_roof(world: np.ndarray) -> np.ndarray:
    """(N,) the world points (N, 3) on `street_scan`'s box roof."""
    x, y = world[:, 0] - 100.0, world[:, 1] - 50.0
    return (np.abs(world[:, 2] - 1.5) < 0.05) & (x > 4) & (x < 9) & (y > 2) & (y < 4)


def test_the_scans_ground_and_roofs_are_found() -> None:
    scan = street_scan()
    surfaces = scan_surfaces(scan)
    world_z = surfaces.world[:, 2]
    clear_cut = np.abs(np.abs(world_z) - 0.2) > 0.01  # the wall's foot straddles the tolerance
    np.testing.assert_array_equal(surfaces.on_ground[clear_cut], np.abs(world_z[clear_cut]) < 0.2)
    roof = on_box_roof(surfaces.world)
    assert roof.sum() > 50 and np.median(surfaces.cos_up[roof]) > 0.95
    wall = (surfaces.world[:, 0] > 114.9) & (world_z > 0.5)
    assert np.median(surfaces.cos_up[wall]) < 0.1


def test_a_wet_ground_edit_is_the_film_on_the_ground_returns() -> None:
    scan = street_scan()
    surfaces = scan_surfaces(scan)
    road = WetRoad(film_depth_m=0.001)
    state = GroundState(road=road, seed=3)
    edited = edit_scan(scan, surfaces, state, noise_floor=8.0)
    ground = surfaces.on_ground
    effect = wet_ground(scan.intensity_255()[ground].astype(np.float64),
                        incidence_angle(scan.points[ground, :3].astype(np.float64), np.zeros(3),
                                        np.asarray(surfaces.plane.normal)),
                        water_depth(surfaces.world[ground, :2], road, 3), road, 8.0)
    assert edited.lost == int(effect.lost.sum()) > 0
    kept_in = np.ones(len(scan.points), bool)
    kept_in[np.nonzero(ground)[0][effect.lost]] = False
    np.testing.assert_array_equal(edited.source_index, np.nonzero(kept_in)[0])
    new = np.zeros(len(scan.points))
    new[ground] = effect.intensity
    np.testing.assert_allclose(edited.scan.points[:, 3], np.where(ground, new, scan.points[:, 3])[kept_in],
                               rtol=1e-6)
    np.testing.assert_array_equal(edited.scan.points[:, :3], scan.points[kept_in, :3])  # nothing moves
    assert not edited.changed[~ground[kept_in]].any()
    assert np.array_equal(edited.edited, ground)


def test_snow_raises_exactly_the_up_facing_returns() -> None:
    scan = street_scan()
    surfaces = scan_surfaces(scan)
    state = GroundState(cover=SnowCover(depth_m=0.1, variation=0.0),
                        tracks=TireTracks((1.0, 0.0), (100.0, 50.0), lane_offsets_m=(0.0,), wander_m=0.0), seed=1)
    edited = edit_scan(scan, surfaces, state, noise_floor=0.5)
    assert edited.lost == 0 and np.array_equal(edited.source_index, np.arange(len(scan.points)))
    rise = edited.scan.points[:, 2] - scan.points[:, 2]  # the world's z axis is the scan's
    ground = surfaces.on_ground
    in_track = np.abs(np.abs(surfaces.world[:, 1] - 50.0) - 0.8) < 0.02
    clear = ground & ~in_track & (np.abs(np.abs(surfaces.world[:, 1] - 50.0) - 0.8) > 0.5)
    np.testing.assert_allclose(rise[clear], 0.1, atol=0.015)  # on level ground: the snow's depth
    np.testing.assert_allclose(rise[ground & in_track], 0.1 * state.tracks.remaining_share, atol=0.015)
    wall = (surfaces.world[:, 0] > 114.9) & (surfaces.world[:, 2] > 0.5)
    assert not edited.changed[wall].any()  # walls hold no snow
    roof = on_box_roof(surfaces.world)
    assert edited.edited[roof].mean() > 0.9
    assert (edited.scan.points[clear, 3] > scan.points[clear, 3]).all()  # snow is brighter than asphalt


def front_camera() -> CameraGeometry:
    """A 400 x 240 camera 1.6 m above `street_scan`'s road, 0.5 m ahead of its LiDAR, looking along +x."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # OpenCV axes: x forward, z up in the world
    T[:3, 3] = [100.5, 50.0, 1.6]
    return CameraGeometry(np.array([[300.0, 0, 200], [0, 300.0, 120], [0, 0, 1]]), T)


def test_the_camera_edits_the_pixels_the_lidars_edited_returns_land_on() -> None:
    scan = street_scan()
    surfaces = scan_surfaces(scan)
    camera = front_camera()
    rays = camera.rays_world(240, 400)
    origin = camera.T_world_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(rays[..., 2] < 0, -origin[2] / rays[..., 2], np.inf)
        t_wall = np.where(rays[..., 0] > 0, (115.0 - origin[0]) / rays[..., 0], np.inf)
        t_wall = np.where(origin[2] + t_wall * rays[..., 2] <= 4.0, t_wall, np.inf)
        t_roof = np.where(rays[..., 2] < 0, -(origin[2] - 1.5) / rays[..., 2], np.inf)
    with np.errstate(invalid="ignore"):
        roof_xy = origin[:2] + t_roof[..., None] * rays[..., :2]
    on_roof = (roof_xy[..., 0] > 104) & (roof_xy[..., 0] < 109) & (roof_xy[..., 1] > 52) & (roof_xy[..., 1] < 54)
    range_map = np.minimum(np.minimum(t_ground, t_wall), np.where(on_roof, t_roof, np.inf))
    image = np.full((240, 400, 3), 0.2)
    sky = np.array([0.6, 0.65, 0.7])
    for state in (GroundState(road=WetRoad(), seed=2), GroundState(cover=SnowCover(), seed=2)):
        lidar = edit_scan(scan, surfaces, state, noise_floor=0.5)
        out = edit_image(image, range_map, camera, True, surfaces, scan.T_global_lidar, state, sky)
        agreement = mask_agreement(surfaces.world, lidar.edited, camera, out.edited)
        assert agreement.pixels > 500 and agreement.iou > 0.95, (state.kind, agreement)
        assert np.array_equal(out.linear[~out.edited & np.isinf(range_map)], image[np.isinf(range_map)][
            ~out.edited[np.isinf(range_map)]])  # the sky unchanged


def test_a_ground_state_is_wet_or_snowy() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        GroundState()
    with pytest.raises(ValueError, match="exactly one"):
        GroundState(road=WetRoad(), cover=SnowCover())
    assert GroundState(road=WetRoad()).kind == "wet" and GroundState(cover=SnowCover()).kind == "snow"


# the same coarse grid in angle; the coarser one smooths more of the snow's 5 % grain between its samples
@pytest.mark.parametrize(("scale", "stride", "tolerance"), [(1, 2, 0.01), (2, 4, 0.015)])
def test_a_coarser_working_grid_gives_nearly_the_same_image(scale: int, stride: int, tolerance: float) -> None:
    scan = street_scan()
    surfaces = scan_surfaces(scan)
    front = front_camera()
    camera = CameraGeometry(np.diag([scale, scale, 1.0]) @ front.K, front.T_world_cam)
    height, width = 240 * scale, 400 * scale
    rays = camera.rays_world(height, width)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(rays[..., 2] < 0, -1.6 / rays[..., 2], np.inf)
        t_wall = np.where(rays[..., 0] > 0, 14.5 / rays[..., 0], np.inf)
    range_map = np.minimum(t_ground, np.where(1.6 + t_wall * rays[..., 2] <= 4.0, t_wall, np.inf))
    stripes = 0.15 + 0.1 * (np.arange(width) // (10 * scale) % 2)[None, :, None] * np.ones(3)
    image = np.where(np.isfinite(range_map)[..., None], stripes, 0.6)
    sky = np.array([0.6, 0.65, 0.7])
    for state in (GroundState(road=WetRoad(puddle_share=0.0), seed=2), GroundState(cover=SnowCover(), seed=2)):
        fine = edit_image(image, range_map, camera, True, surfaces, scan.T_global_lidar, state, sky, work_stride=1)
        coarse = edit_image(image, range_map, camera, True, surfaces, scan.T_global_lidar, state, sky,
                            work_stride=stride)
        both = fine.edited | coarse.edited
        assert (fine.edited & coarse.edited).sum() / both.sum() > 0.97, state.kind
        assert np.abs(fine.linear - coarse.linear)[fine.edited & coarse.edited].mean() < tolerance, state.kind
        assert np.array_equal(coarse.linear[np.isinf(range_map)], image[np.isinf(range_map)])  # the sky untouched


def test_the_uint8_path_is_the_linear_edit_encoded() -> None:
    from weatheralign.camera.fog import decode_srgb_u8, encode_srgb_u8
    from weatheralign.ground.edit import edit_image_u8

    scan = street_scan()
    surfaces = scan_surfaces(scan)
    camera = front_camera()
    rays = camera.rays_world(241, 401)  # odd sizes: the last block is cut
    with np.errstate(divide="ignore", invalid="ignore"):
        range_map = np.where(rays[..., 2] < 0, -1.6 / rays[..., 2], np.inf)
    image = np.random.default_rng(0).integers(20, 120, (241, 401, 3)).astype(np.uint8)
    sky = np.array([0.6, 0.65, 0.7])
    for state in (GroundState(road=WetRoad(), seed=2), GroundState(cover=SnowCover(), seed=2)):
        linear = edit_image(decode_srgb_u8(image).astype(np.float64), range_map, camera, True, surfaces,
                            scan.T_global_lidar, state, sky)
        coded, mask = edit_image_u8(image, range_map, camera, True, surfaces, scan.T_global_lidar, state, sky)
        assert np.array_equal(mask, linear.edited) and mask.mean() > 0.3
        expected = encode_srgb_u8(linear.linear.astype(np.float32))
        assert np.abs(coded.astype(int) - expected.astype(int)).max() <= 1
        assert (coded == expected).mean() > 0.999


def test_an_integer_scans_ground_readings_are_spread_before_the_film_dims_them() -> None:
    """A scan of integer readings at the floor (1 and 2, floor 1): each ground return's reading q stood for a value
    uniform on [max(q - ½, 1), q + ½); the film's factor f keeps it with probability (q + ½ - 1 / f) / (q + ½ -
    max(q - ½, 1)), so the edit loses their complement in expectation (not every return with q f < 1, as a reading
    taken for exactly q would), reports the kept ones at f x >= 1 and leaves the off-ground readings whole."""
    scan = street_scan()
    rng = np.random.default_rng(8)
    q = rng.integers(1, 3, len(scan.points)).astype(np.float64)
    scan = LidarScan(np.column_stack([scan.points[:, :3], q, scan.points[:, 4]]).astype(np.float32), 0.0, np.eye(4),
                     scan.T_global_ego)
    surfaces = scan_surfaces(scan)
    road = WetRoad(film_depth_m=0.0002)
    edited = edit_scan(scan, surfaces, GroundState(road=road, seed=3), noise_floor=1.0)
    ground = surfaces.on_ground
    f = wet_ground(q[ground], incidence_angle(scan.points[ground, :3].astype(np.float64), np.zeros(3),
                                              np.asarray(surfaces.plane.normal)),
                   water_depth(surfaces.world[ground, :2], road, 3), road, 1.0).factor
    qg = q[ground]
    lo = np.maximum(qg - 0.5, 1.0)
    p_keep = np.clip((qg + 0.5 - 1.0 / f) / (qg + 0.5 - lo), 0.0, 1.0)
    expected = float((1.0 - p_keep).sum())
    assert abs(edited.lost - expected) < 4 * np.sqrt((p_keep * (1 - p_keep)).sum())
    assert int((qg * f < 1.0).sum()) > expected + 200
    out = edited.scan.points[:, 3]
    on_ground = ground[edited.source_index]
    assert out[on_ground & edited.changed].min() >= 1.0
    np.testing.assert_array_equal(out[~on_ground], q[edited.source_index][~on_ground])


def test_the_wet_edits_noise_is_each_beams_own_and_apart_from_the_airs_draws() -> None:
    """`edit_scan` with a detector's noise reads each wet ground return again from its beam's stream
    (`wet_reading_normals`: draws 3 and 4): the same scan gives the same bytes, the added noise is σ_0 sqrt(1 - f²)
    times that normal, and it is uncorrelated with the normals the air's weather then draws from the same stream
    (`normal_pair`, draws 0 and 1)."""
    from weatheralign.ground.edit import wet_reading_normals
    from weatheralign.lidar.beams import point_noise_keys
    from weatheralign.medium.field import normal_pair

    scan = street_scan()
    surfaces = scan_surfaces(scan)
    road = WetRoad(film_depth_m=0.0005)
    state = GroundState(road=road, seed=3)
    quiet = edit_scan(scan, surfaces, state, noise_floor=0.0)
    loud = edit_scan(scan, surfaces, state, noise_floor=0.0, noise_std=0.5)
    assert loud.scan.points.tobytes() == edit_scan(scan, surfaces, state, 0.0, 0.5).scan.points.tobytes()
    ground = surfaces.on_ground
    keys = point_noise_keys(scan)[ground]
    z = wet_reading_normals(keys)
    f = wet_ground(scan.intensity_255()[ground].astype(np.float64),
                   incidence_angle(scan.points[ground, :3].astype(np.float64), np.zeros(3),
                                   np.asarray(surfaces.plane.normal)),
                   water_depth(surfaces.world[ground, :2], road, 3), road, 0.0).factor
    added = loud.scan.intensity_255()[ground].astype(np.float64) - quiet.scan.intensity_255()[ground]
    inside = quiet.scan.intensity_255()[ground] > 3.0  # away from the clip at 0
    np.testing.assert_allclose(added[inside], (0.5 * np.sqrt(1.0 - f * f) * z)[inside], atol=2e-5)
    assert abs(z.mean()) < 4 / np.sqrt(len(z)) and abs(z.std() - 1.0) < 0.05
    air = np.array([normal_pair(k) for k in keys])
    for c in range(2):
        assert abs(np.corrcoef(z, air[:, c])[0, 1]) < 4 / np.sqrt(len(z))


def dark_ring_beams(elevations_deg: tuple[float, ...], columns: int = 360) -> UnseenBeams:
    """Beams without return from `street_scan`'s sensor (the scan's frame, origin at the sensor), ``columns`` per
    ring at each elevation, reported by the synthetic reference's intensity model."""
    az = np.tile(np.linspace(-np.pi, np.pi, columns, endpoint=False), len(elevations_deg))
    el = np.radians(np.repeat(elevations_deg, columns))
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    times = np.linspace(0.0, 0.1, len(d))
    ring = np.repeat(np.arange(len(elevations_deg), dtype=np.float64), columns) + 40.0
    return UnseenBeams(np.zeros_like(d), d, times, ring, detector_noise_keys(times, d, ring), 120.0,
                       SYNTHETIC_INTENSITY, 2.0 * np.pi / columns)


def test_snow_on_a_road_the_clear_beams_missed_returns_where_its_reading_clears_the_floor() -> None:
    """A road of reflectivity 0.1 (read exactly by the near returns) under 0.1 m of even snow: a beam 4 deg down
    meets it at 25.8 m, where the bare road reads 0.69 (under the floor of 1) and the snow 5.3x that: every such beam
    returns, from the snow's top, (h - d) / sin 4 deg away; 2 deg down (51.6 m) the snow reads 0.92: none; beams
    above the horizon and a wet road add nothing."""
    scan = street_scan()
    surfaces = scan_surfaces(scan, off_ground=False)
    xyz = scan.points[:, :3].astype(np.float64)
    r = np.linalg.norm(xyz, axis=1)
    cos_in = np.cos(incidence_angle(xyz, np.zeros(3), np.asarray(surfaces.plane.normal)))
    points = scan.points.copy()
    points[:, 3] = np.where(surfaces.on_ground, SYNTHETIC_INTENSITY.intensity(0.1, r) * cos_in, points[:, 3])
    scan = replace(scan, points=points)
    assert road_reflectivity(scan, surfaces, SYNTHETIC_INTENSITY) == pytest.approx(0.1, rel=1e-5)
    cover = SnowCover(depth_m=0.1, variation=0.0)
    state = GroundState(cover=cover, seed=1)
    unseen = dark_ring_beams((-4.0, -2.0, 1.0))
    edited = edit_scan(scan, surfaces, state, noise_floor=1.0, unseen=unseen)
    n = len(scan.points)
    added = edited.scan.points[n:]
    assert edited.added == len(added) == 360 and set(added[:, 4].tolist()) == {40.0}
    np.testing.assert_array_equal(edited.source_index[n:], -1)
    assert edited.changed[n:].all() and len(edited.edited) == n
    ring = unseen.directions[:360]
    descent = -(ring @ np.asarray(surfaces.plane.normal))  # cos of the incidence on the fitted plane
    reach = surfaces.plane.offset / descent  # the plane lies offset (about 1.8 m) under the sensor
    np.testing.assert_allclose(np.linalg.norm(added[:, :3], axis=1), reach - 0.1 / descent, rtol=1e-5)
    bare = SYNTHETIC_INTENSITY.intensity(0.1, reach) * descent
    coverage, _ = snow_coverage(np.array([0.1]), np.array([1.0]), cover)
    ratio = cover.snow_reflectivity / cover.pavement_reflectivity
    np.testing.assert_allclose(added[:, 3], bare * (1.0 - coverage[0] + coverage[0] * ratio), rtol=1e-5)
    bare = bare[0]
    assert 0.6 < bare < 1.0 < added[0, 3]
    wet = edit_scan(scan, surfaces, GroundState(road=WetRoad(), seed=1), noise_floor=1.0, unseen=unseen)
    assert wet.added == 0 and len(wet.scan.points) <= n


def test_only_beams_whose_neighbours_leave_the_road_dark_and_unblocked_are_dark_road_misses() -> None:
    """Beams without return between same-ring returns: the road's neighbours at the beam's reach reading under the
    bright-road bar explain the miss; one neighbour standing nearer than `BLOCKED_REACH_SHARE` of the reach (the beam
    met that object) or reading the road bright (a dropout) does not; neighbours farther than the window, or on
    another ring at the same azimuth, do not count."""
    step = np.radians(0.2)
    reach, floor = 30.0, 2.0
    ring_of = {0: 0.0, 1: 1.0, 2: 2.0, 3: 3.0, 4: 4.0, 5: 5.0}

    def ret(ring: float, az: float, r: float, reading: float) -> list[float]:
        return [r * np.cos(az), r * np.sin(az), -1.0, reading, ring]

    beams_az = np.radians([10.0, 20.0, 30.0, 40.0, 50.0, 60.0])
    points = [
        ret(0, beams_az[0] - step, reach, 0.5 * floor), ret(0, beams_az[0] + step, reach * 1.05, 3.9 * floor),
        ret(1, beams_az[1] - step, reach, floor), ret(1, beams_az[1] + step, 0.7 * reach, floor),  # a car in front
        ret(2, beams_az[2] + step, reach, 4.1 * floor),  # bright road beside: a dropout
        ret(3, beams_az[3] - (NEIGHBOUR_WINDOW_STEPS + 0.5) * step, 0.1 * reach, floor),  # outside the window
        ret(4, beams_az[4], 0.1 * reach, 10 * floor),  # another ring's return in front, same azimuth
        ret(5, beams_az[5] + step, BLOCKED_REACH_SHARE * reach, BRIGHT_ROAD_FLOORS * floor - 1e-3),  # at the bars
    ]
    scan = LidarScan(np.array(points, dtype=np.float32), 0.0, np.eye(4), np.eye(4))
    ring = np.array([ring_of[k] for k in range(6)])
    ring[4] = 6.0  # the beam of "ring 4"'s azimuth lies on ring 6: ring 4's return is not its neighbour
    directions = np.column_stack([np.cos(beams_az), np.sin(beams_az), np.full(6, -0.06)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    explained = dark_road_misses(scan, ring, directions, np.full(6, reach), np.full(6, floor), step)
    assert explained.tolist() == [True, False, False, True, True, True]
    brighter = dark_road_misses(scan, ring, directions, np.full(6, reach), np.full(6, floor / 2), step)
    assert brighter.tolist() == [False, False, False, True, True, False]  # a lower floor makes the same road bright
    assert dark_road_misses(scan, ring[:0], directions[:0], np.zeros(0), np.zeros(0), step).shape == (0,)


def test_snow_on_a_real_scan_adds_returns_only_on_its_dark_road() -> None:
    """The shared Seeing Through Fog HDL-64 scan under 5 cm of snow: its beams without return (reconstructed from the
    ring gaps, about 11 % of its low rings) lie almost all beside returns of nearer objects or of a road read far
    above the floor, so the snow adds under 0.1 % of the scan's returns, not one per gap."""
    from tests.conftest import SHARED_REAL
    from weatheralign.data.stf import load_stf_frame
    from weatheralign.lidar.beams import ray_plane_ranges
    from weatheralign.sensors import estimate_lidar_model

    stf = SHARED_REAL / "stf"
    if not stf.exists():
        pytest.skip(f"real sample not available: {stf}")
    scan = load_stf_frame(stf, "2019-09-11_19-13-44_00960", camera_folder=None).lidar
    lidar = estimate_lidar_model([scan], rotation_hz=10.0, overrides={"noise_floor": 1.0})
    surfaces = scan_surfaces(scan, off_ground=True)
    unseen = unseen_beams(scan, lidar)
    reach = ray_plane_ranges(unseen.origins, unseen.directions, surfaces.plane)
    assert (reach < unseen.max_range_m).sum() > 0.05 * len(scan.points)  # gaps on the ground: 11 % of the returns
    edited = edit_scan(scan, surfaces, GroundState(cover=SnowCover(depth_m=0.05), seed=2), lidar.noise_floor,
                       unseen=unseen)
    assert 0 <= edited.added < 0.001 * len(scan.points)
