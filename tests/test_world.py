"""The synthetic world: cross-sensor consistency, nuScenes format, round trip, determinism, resume."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import matplotlib
import numpy as np
import pytest

from weatheralign.data.nuscenes import CAMERA_CHANNELS, extras_relpath, load_frame, open_nuscenes
from weatheralign.data.rings import HDL32E_ELEVATIONS_DEG
from weatheralign.geometry import apply, invert, project
from weatheralign.sensors import ego_body_from_params
from weatheralign.world.build import SWEEP_PERIOD_US, render_sample, scene_specs
from weatheralign.world.dataset import finalize, render_or_resume, sample_jobs
from weatheralign.world.raycast import WorldRaycaster
from weatheralign.world.rig import make_cameras

from .conftest import tiny_params

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def nusc(tiny_world):
    return open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)


@pytest.fixture(scope="module")
def layouts(tiny_world):
    return {s.index: s.layout(tiny_world.params.world) for s in scene_specs(tiny_world.params.world)}


def _scene_index(nusc, sample) -> int:
    return [s["token"] for s in nusc.scene].index(sample["scene_token"])


def test_devkit_loads_and_renders(tiny_world, nusc, tmp_path):
    w = tiny_world.params.world
    assert len(nusc.scene) == 2 and len(nusc.sample) == 4
    for table in ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose",
                  "log", "scene", "sample", "sample_data", "sample_annotation", "map"):
        assert (tiny_world.dataroot / w.version / f"{table}.json").is_file()
    sample = nusc.sample[0]
    assert set(sample["data"]) == {"LIDAR_TOP", *CAMERA_CHANNELS}
    nusc.render_sample_data(sample["data"]["LIDAR_TOP"], out_path=str(tmp_path / "lidar.png"), nsweeps=2)
    nusc.render_sample_data(sample["data"]["CAM_FRONT"], out_path=str(tmp_path / "cam.png"))
    assert (tmp_path / "lidar.png").stat().st_size > 10_000 and (tmp_path / "cam.png").stat().st_size > 10_000
    splits = json.loads((tiny_world.dataroot / w.version / "splits.json").read_text())
    assert splits == {"weatheralign_train": ["scene-0061"], "weatheralign_val": ["scene-0103"]}


def test_lidar_prev_chain_holds_the_sweeps(tiny_world, nusc):
    w = tiny_world.params.world
    for sample in nusc.sample:
        sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        chain = []
        while sd["prev"] and len(chain) < w.sweeps_per_sample:
            sd = nusc.get("sample_data", sd["prev"])
            chain.append(sd)
        assert len(chain) == w.sweeps_per_sample
        assert all(not c["is_key_frame"] and c["filename"].startswith("sweeps/LIDAR_TOP/") for c in chain)
        times = [sample["timestamp"]] + [c["timestamp"] for c in chain]
        assert np.all(np.diff(times) == -SWEEP_PERIOD_US)


def test_scan_format_and_sensor_timing(tiny_world, nusc):
    sample = nusc.sample[0]
    frame = load_frame(nusc, sample["token"])
    pts = frame.lidar.points
    assert pts.dtype == np.float32 and pts.shape[1] == 5 and len(pts) > 15_000
    assert set(np.unique(pts[:, 4]).astype(int)) <= set(range(32)) and len(np.unique(pts[:, 4])) >= 28
    assert pts[:, 3].min() >= 0 and pts[:, 3].max() <= 255 and np.all(pts[:, 3] == np.round(pts[:, 3]))
    r = np.linalg.norm(pts[:, :3], axis=1)
    assert r.max() <= 100.5 and r.min() >= 1.0 - 0.05
    off = frame.lidar.time_offsets
    assert off.min() >= -0.05 - 1e-6 and off.max() < 0 and np.ptp(off) > 0.049  # every firing has its own time
    for ch, view in frame.cameras.items():
        dt = view.timestamp - frame.timestamp
        assert -0.05 <= dt <= 0, ch
    # CAM_FRONT is exposed when the clockwise sweep from the left crosses forward: a quarter into the sweep
    assert frame.cameras["CAM_FRONT"].timestamp - frame.timestamp == pytest.approx(-0.0375, abs=2e-6)


def test_the_world_lidar_reports_calibrated_reflectivity_through_a_raw_power_floor(tiny_world, nusc):
    """The world's HDL-32E (configs/world_rig.yaml): every stored reading passed the floor at its range, which grows
    as R² (a 10 % target at the floor at 35 m), read with noise that scales alike; intensities do not fall with
    range (a calibrated reflectivity), so far returns are the bright ones and near ones span the whole scale."""
    from weatheralign.sensors import lidar_model_from_params

    lidar = lidar_model_from_params(tiny_world.params.world.lidar)
    assert lidar.floor_range_m == 35.0 and lidar.intensity.falloff == 0.0
    pts = load_frame(nusc, nusc.sample[0]["token"]).lidar.points
    r = np.linalg.norm(pts[:, :3].astype(np.float64), axis=1)
    sigma = lidar.intensity_noise_std * lidar.floor_scale(r)
    assert np.all(pts[:, 3] + 0.5 + 5.0 * sigma >= lidar.floor_at(r))  # nothing clearly under the floor
    near, far = pts[r < 10.0, 3], pts[r > 40.0, 3]
    assert len(far) > 100 and np.median(far) > 3.0 * np.median(near)
    assert np.mean(near < lidar.noise_floor) > 0.5  # near the sensor, returns under the floor at 35 m are detected


def test_each_beam_leaves_the_sensor_where_it_was_at_its_firing_time(tiny_world, nusc):
    """Points are stored ego-motion compensated; from the sensor position at each firing time, every point lies
    exactly on its ring's elevation: the rolling sweep is geometrically consistent."""
    frame = load_frame(nusc, nusc.sample[1]["token"])
    scan = frame.lidar
    origins = scan.beam_origins()
    d = scan.points[:, :3].astype(np.float64) - origins
    elev = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    expected = HDL32E_ELEVATIONS_DEG[scan.points[:, 4].astype(int)]
    assert np.abs(elev - expected).max() < 2e-3
    moved = np.linalg.norm(origins[:, :2] - origins[:, :2].mean(0), axis=1).max()
    assert moved > 0.1  # the ego really moved during the sweep (>= 5 m/s x 50 ms / 2)
    naive = scan.points[:, :3].astype(np.float64)  # pretending every beam left from the sweep-end origin
    naive_elev = np.degrees(np.arctan2(naive[:, 2], np.hypot(naive[:, 0], naive[:, 1])))
    assert np.abs(naive_elev - expected).max() > 0.05


def _matches_depth_map(view, uv: np.ndarray, z: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether points at sub-pixel ``uv`` with optical depth ``z`` and ray length ``dist`` lie on the range map
    within 1 %: by bilinear interpolation of inverse optical depth over the 4 surrounding pixel centres (exact for a
    plane), or at one of those centres. ``undecidable``: the 4 centres disagree by more than 2 % among themselves
    (a silhouette, or a surface so oblique that one pixel spans more than the tolerance)."""
    depth = view.load_range().astype(np.float64)
    K = view.K
    u0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, view.width - 2)
    v0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, view.height - 2)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    corners, inv_z, weights = [], [], []
    for a, b, w in ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)), (1, 0, (1 - fu) * fv), (1, 1, fu * fv)):
        r = depth[v0 + a, u0 + b]
        ray_z = 1.0 / np.sqrt(((u0 + b - K[0, 2]) / K[0, 0]) ** 2 + ((v0 + a - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
        corners.append(r)
        inv_z.append(1.0 / (r * ray_z))
        weights.append(w)
    corners_arr = np.array(corners)
    z_interp = 1.0 / np.sum(np.array(inv_z) * np.array(weights), axis=0)
    ok = (np.abs(z_interp - z) <= 0.01 * z) | (np.min(np.abs(corners_arr - dist) / dist, axis=0) <= 0.01)
    spread = (corners_arr.max(0) - corners_arr.min(0)) / corners_arr.min(0)
    return ok, ~ok & ~(spread <= 0.02)


def test_every_lidar_point_lands_on_the_camera_depth(tiny_world, nusc, layouts):
    """Each keyframe point seen by a camera (at the camera's own timestamp and ego pose; points on moving actors
    propagated by their velocity) lies on that camera's exact range map within 1 % of its range."""
    checked = 0
    body = ego_body_from_params(tiny_world.params.world.ego_body)
    for sample in nusc.sample:
        layout = layouts[_scene_index(nusc, sample)]
        caster = WorldRaycaster(layout)
        frame = load_frame(nusc, sample["token"])
        scan = frame.lidar
        extras = np.load(tiny_world.dataroot
                         / extras_relpath(nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["filename"]))
        p_global = apply(scan.T_global_lidar, scan.points[:, :3])  # where each beam hit, at its firing time
        fire_t = scan.point_times()
        velocity = np.zeros((len(p_global), 3))
        for actor in layout.actors:
            velocity[extras["instance"] == actor.instance] = actor.velocity
        for ch, view in frame.cameras.items():
            p_now = p_global + velocity * (view.timestamp - fire_t)[:, None]
            pc = apply(invert(view.T_global_cam), p_now)
            uv, z = project(pc, view.K)
            inside = (z > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] <= view.width - 1) & (uv[:, 1] >= 0) & (
                uv[:, 1] <= view.height - 1)
            idx = np.flatnonzero(inside)
            dist = np.linalg.norm(pc[idx], axis=1)
            # independent visibility: nothing in front of the point along the camera ray at the camera's time
            origin = view.T_global_cam[:3, 3]
            dirs = (p_now[idx] - origin) / dist[:, None]
            hits = caster.cast_at_time(np.broadcast_to(origin, dirs.shape), dirs, view.timestamp)
            # a point is seen when the camera ray meets a surface at it (within the range noise, 2 sigma = 1.6 cm);
            # range noise pushes a few silhouette points off their object, so the camera ray passes them
            tol = np.maximum(0.005 * dist, 2.5 * tiny_world.params.world.lidar.range_noise_std_m)
            seen = np.abs(hits.range - dist) <= tol
            assert (hits.range > dist + tol).mean() < 0.02, f"{ch}: camera rays pass behind LiDAR points"
            # the ego's own body, which only the cameras see, hides what lies behind it (CAM_BACK's bottom rows)
            dirs_ego = dirs @ view.T_global_ego[:3, :3]
            seen &= ~(body.ray_distances(np.broadcast_to(view.T_ego_cam[:3, 3], dirs.shape), dirs_ego) < dist)
            idx, dist, uvs = idx[seen], dist[seen], uv[idx[seen]]
            ok, undecidable = _matches_depth_map(view, uvs, pc[idx, 2], dist)
            assert np.all(ok | undecidable), f"{ch}: {(~ok & ~undecidable).sum()} points off the depth map"
            assert ok.mean() > 0.99 and undecidable.mean() < 0.01, f"{ch}: {ok.mean():.4f} match"
            checked += len(idx)
    assert checked > 5000


def test_annotations_match_the_rendered_scan(tiny_world, nusc, layouts):
    """num_lidar_pts counts the points on the object; all of them lie inside its box (at their firing time, within
    the range noise), no other point lies well inside it, and velocities are the actors' own."""
    margin = 2.5 * tiny_world.params.world.lidar.range_noise_std_m
    for sample in nusc.sample:
        layout = layouts[_scene_index(nusc, sample)]
        frame = load_frame(nusc, sample["token"])
        sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        instance = np.load(tiny_world.dataroot / extras_relpath(sd["filename"]))["instance"]
        p_global = apply(frame.lidar.T_global_lidar, frame.lidar.points[:, :3])
        fire_t = frame.lidar.point_times()
        assert len(frame.boxes) > 5
        for box in frame.boxes:
            actor = next(a for a in layout.actors if np.allclose(a.box_center_at(frame.timestamp), box.center))
            assert actor.category == box.category and np.allclose(box.size, actor.size)
            mine = instance == actor.instance
            assert box.num_lidar_pts == mine.sum()
            # box frame of each point at its own firing time (the box moves during the sweep)
            rel = p_global - (actor.position_at(fire_t) + [0.0, 0.0, actor.size[2] / 2])
            c, s = np.cos(actor.yaw), np.sin(actor.yaw)
            local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
            half = np.array([actor.size[1], actor.size[0], actor.size[2]]) / 2
            assert np.all(np.abs(local[mine]) <= half + margin), box.category
            deep_inside = np.all(np.abs(local) <= half - 0.05, axis=1)
            assert np.all(mine[deep_inside]), f"{box.category}: foreign points inside the box"
            if actor.moving and not np.isnan(box.velocity).any():
                assert np.allclose(box.velocity, actor.velocity, atol=1e-6)
    assert sum(tiny_world.summary["class_counts"].values()) == tiny_world.summary["num_annotations"]


def test_frame_round_trip_matches_written_files(tiny_world, nusc):
    sample = nusc.sample[2]
    frame = load_frame(nusc, sample["token"], nsweeps=3)
    sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
    raw = np.fromfile(tiny_world.dataroot / sd["filename"], dtype=np.float32).reshape(-1, 5)
    key = frame.lidar.sweep_index == 0
    assert np.array_equal(frame.lidar.points[key], raw)
    assert set(np.unique(frame.lidar.sweep_index)) == {0, 1, 2}
    older = frame.lidar.time_offsets[frame.lidar.sweep_index == 2]
    assert older.max() < -0.1 + 1e-6 and older.min() >= -0.15 - 1e-6
    cams = {c.channel: c for c in make_cameras(tiny_world.params.world.camera.image_scale)}
    sky = []
    for ch, view in frame.cameras.items():
        assert np.allclose(view.K, cams[ch].K) and np.allclose(view.T_ego_cam, cams[ch].T_ego_cam)
        img = view.load_image()
        assert img.shape == (view.height, view.width, 3) and img.std() > 10
        rng = view.load_range()
        assert rng.dtype == np.float32 and np.isfinite(rng).mean() > 0.5 and np.nanmin(rng) > 0
        sky.append(np.isinf(rng).mean())
    assert max(sky) > 0.05  # some camera looks along the street at the sky


def test_same_seed_same_bytes_and_different_seed_differs(tiny_world, tmp_path):
    w = tiny_world.params.world
    spec = scene_specs(w)[0]
    render_sample(spec, 1, w, tmp_path)
    for path in sorted(p for p in tmp_path.rglob("*") if p.is_file()):
        rel = path.relative_to(tmp_path)
        assert path.read_bytes() == (tiny_world.dataroot / rel).read_bytes(), rel
    other = tiny_params(tmp_path / "o", seed=w.seed + 1).world
    assert scene_specs(other)[0].seed != spec.seed


def test_tables_are_deterministic(tiny_world, tmp_path):
    digests = []
    for k in range(2):
        root = tmp_path / f"copy{k}"
        shutil.copytree(tiny_world.dataroot, root)
        finalize(tiny_world.params.world, root, tiny_world.results)
        digests.append({p.name: hashlib.md5(p.read_bytes()).hexdigest()
                        for p in (root / tiny_world.params.world.version).glob("*.json")})
    assert digests[0] == digests[1]
    original = {p.name: hashlib.md5(p.read_bytes()).hexdigest()
                for p in (tiny_world.dataroot / tiny_world.params.world.version).glob("*.json")}
    assert original == digests[0]


def test_world_refuses_a_folder_it_did_not_write(tiny_world, tmp_path):
    """A real dataset (or anything else) at the world's output path: the stage refuses before writing or removing a
    single file; its own folder (the marker, its own file names) is accepted."""
    from weatheralign.data.errors import DataFormatError
    from weatheralign.world.dataset import OWNER_FILE, claim_dataroot

    version = tiny_world.params.world.version
    root = tmp_path / "nuscenes"
    shutil.copytree(tiny_world.dataroot, root)
    claim_dataroot(root, version)  # only the stage's own files: adopted (an existing world from an earlier release)
    assert (root / OWNER_FILE).is_file()
    real = root / "samples" / "CAM_FRONT" / "n008-2018-08-01-15-16-36-0400__CAM_FRONT__1533151603512404.jpg"
    real.write_bytes(b"a real nuScenes image")
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    with pytest.raises(DataFormatError, match="n008-2018-08-01.*refusing"):
        claim_dataroot(root, version)
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before
    empty = tmp_path / "new"
    claim_dataroot(empty, version)
    assert [p.name for p in empty.iterdir()] == [OWNER_FILE]


def test_resume_skips_finished_samples_and_cleans_stale_files(tmp_path):
    params = tiny_params(tmp_path, num_train_scenes=1, num_val_scenes=1, samples_per_scene=2, sweeps_per_sample=0,
                         camera={"image_scale": 0.1})
    root = tmp_path / "world"
    jobs = sample_jobs(params.world)
    first = [render_or_resume(s, k, params.world, root) for s, k in jobs[:3]]  # "interrupted" after 3 of 4
    assert all(now for _, now in first)
    stamp = {p: p.stat().st_mtime_ns for p in root.rglob("*.jpg")}
    second = [render_or_resume(s, k, params.world, root) for s, k in jobs]
    assert [now for _, now in second] == [False, False, False, True]
    assert all(p.stat().st_mtime_ns == t for p, t in stamp.items())
    # resume verifies what it keeps: a truncated output re-renders its job (and only that one)
    victim = root / second[1][0].cameras[0].filename
    good = victim.read_bytes()
    victim.write_bytes(good[: len(good) // 2])
    again = [render_or_resume(s, k, params.world, root) for s, k in jobs]
    assert [now for _, now in again] == [False, True, False, False] and victim.read_bytes() == good
    stale = root / "samples" / "CAM_FRONT" / "wa-2026-synthetic-log009__CAM_FRONT__1.jpg"  # ours, of another config
    stale.write_bytes(b"x")
    tmp_leftover = root / "samples" / "LIDAR_TOP" / ".wa-2026-synthetic-log000__LIDAR_TOP__1.pcd.bin.123.tmp"
    tmp_leftover.write_bytes(b"x")
    foreign = root / "samples" / "CAM_FRONT" / "n008-2018-08-01__CAM_FRONT__1533151603512404.jpg"
    foreign.write_bytes(b"a user's image")
    finalize(params.world, root, [r for r, _ in second])
    assert not stale.exists() and not tmp_leftover.exists() and not (root / ".progress").exists()
    assert foreign.read_bytes() == b"a user's image"  # not the stage's: never removed
    # a config change invalidates the finished records
    changed = tiny_params(tmp_path, num_train_scenes=1, num_val_scenes=1, samples_per_scene=2, sweeps_per_sample=0,
                          camera={"image_scale": 0.1}, seed=5).world
    assert render_or_resume(*sample_jobs(changed)[0], changed, root)[1]


def _footprints(layout, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Scene-frame centres (A + 1, T, 2) of every actor's box and of the ego at ``times`` (T,) [s from the scene
    start], the half extents (A + 1, 2) of their axis-aligned bounds, and names."""
    from weatheralign.world.layout import EGO_LENGTH, EGO_WIDTH, box_half_extents

    T = layout.T_scene_global
    heading = np.arctan2(layout.T_global_scene[1, 0], layout.T_global_scene[0, 0])
    centres, halves, names = [], [], []
    for a in layout.actors:
        p = a.position_at(layout.t_start + times)
        centres.append((p @ T[:3, :3].T + T[:3, 3])[:, :2])
        halves.append(box_half_extents(a.size, a.yaw - heading))
        names.append(f"{a.category}#{a.instance}")
    centres.append(np.stack([layout.ego_speed * times, np.full_like(times, layout.ego_lane_y)], 1))
    halves.append((EGO_LENGTH / 2, EGO_WIDTH / 2))
    names.append("ego")
    return np.array(centres), np.array(halves), names


def test_a_20_second_scene_is_built_for_the_whole_drive_and_no_boxes_ever_overlap():
    """nuScenes-length scenes (40 keyframes, ~20 s) at the fastest ego speed, from the layout alone: the street,
    its buildings and furniture reach far beyond the drive; road users fill the window around the ego at the start,
    middle and end alike and stay on the built street; the cross street lies along the drive; no two boxes (nor a box
    and the ego) overlap at any of 4001 instants of the scene."""
    from weatheralign.world.build import scene_duration_s
    from weatheralign.world.layout import USERS_AHEAD_M, USERS_BEHIND_M
    from weatheralign.world.materials import Material

    w = tiny_params(Path("/unused"), samples_per_scene=40, sweeps_per_sample=9, ego_speed_min=11.5,
                    ego_speed_max=12.0).world
    duration = scene_duration_s(w)
    assert duration == pytest.approx(20.0)
    times = np.linspace(0.0, duration, 4001)  # 5 ms apart: < 15 cm between samples at the largest relative speed
    for spec in scene_specs(w)[:3]:
        layout = spec.layout(w)
        drive = layout.ego_speed * duration
        assert drive > 229.0
        lo, hi = layout.road.x_extent
        b_lo, b_hi = layout.road.built_extent
        assert lo <= -300.0 and hi >= drive + 300.0  # ground, road, sidewalks
        assert b_lo <= -250.0 and b_hi >= drive + 300.0  # buildings: beyond the LiDAR's and the cameras' reach
        T = layout.T_scene_global
        v = layout.static_mesh.vertices @ T[:3, :3].T + T[:3, 3]
        facade = v[layout.static_mesh.triangles[layout.static_mesh.material == Material.FACADE].ravel()]
        furniture = v[layout.static_mesh.triangles[np.isin(layout.static_mesh.material, [Material.TRUNK,
                                                                                         Material.METAL])].ravel()]
        assert facade[:, 0].min() < -240.0 and facade[:, 0].max() > drive + 290.0
        assert furniture[:, 0].min() < -180.0 and furniture[:, 0].max() > drive + 230.0
        if layout.road.crossing_x is not None:
            assert 25.0 <= layout.road.crossing_x <= drive + 40.0
        centres, halves, names = _footprints(layout, times)
        # every road user stays on the built street, all the time
        assert centres[:-1, :, 0].min() > lo and centres[:-1, :, 0].max() < hi
        # as many road users around the ego at the end of the drive as at its start
        rel = centres[:-1, :, 0] - centres[-1, None, :, 0]
        around = ((rel > -USERS_BEHIND_M) & (rel < USERS_AHEAD_M)).sum(0)
        assert around.min() >= 10 and around[-1] >= 0.5 * around[0], around[[0, 2000, 4000]]
        # no overlap at any instant (axis-aligned bounds of the boxes: conservative)
        for i in range(len(centres) - 1):
            apart = np.abs(centres[i + 1:] - centres[i, None])
            touch = (apart < halves[i + 1:, None, :] + halves[i]).all(axis=2).any(axis=1)
            others = [names[i + 1 + j] for j in np.flatnonzero(touch)]
            assert not touch.any(), f"{spec.name}: {names[i]} overlaps {others}"


def test_occupancy_is_exact_in_continuous_time():
    """Two fast road users whose footprints meet for 54 ms only (they pass through each other between two of 25
    samples of the scene) are in conflict; one a centimetre to the side is not."""
    from weatheralign.world.layout import _Occupancy

    occ = _Occupancy(20.0)
    occ.add(occ.footprint(0.0, 0.0, 12.0, 0.0, 0.5, 0.5))
    # head-on at 37 m/s relative: overlapping while |384.8 - 37 t| < 1, i.e. 10.4 s +- 27 ms
    samples = np.linspace(0.0, 20.0, 25)
    assert np.all(np.abs(384.8 - 37.0 * samples) >= 1.0)  # a sampled check would miss it
    assert not occ.free(occ.footprint(384.8, 0.0, -25.0, 0.0, 0.5, 0.5))
    assert occ.free(occ.footprint(384.8, 1.01, -25.0, 0.0, 0.5, 0.5))
    assert occ.free(occ.footprint(-5.0, 0.0, 12.0, 0.0, 0.5, 0.5))  # same speed, behind: never meets
    assert not occ.free(occ.footprint(0.5, 0.5, 0.0, 0.0, 0.2, 0.2))  # overlapping at t = 0
    assert occ.free(occ.footprint(-1.0, 0.0, 0.0, 0.0, 0.4, 0.4))  # behind the first, which drives away


def test_one_pass_camera_equals_the_step_by_step_camera(tiny_world, layouts):
    """`render_camera` (rasterised depth, then one pass for directions, hits, shadows, noise and sRGB) gives the very
    bytes of the step-by-step functions (`pixel_directions`, `cast_camera`, `sun_lit`, `camera_noise`,
    `camera_pixels`), and its range map is stored as numpy's own float16."""
    from weatheralign.data.float16 import to_float16
    from weatheralign.world.render import pixel_directions, render_camera, sun_lit
    from weatheralign.world.shading import camera_noise, camera_pixels, noise_key

    w = tiny_world.params.world
    layout = layouts[0]
    caster = WorldRaycaster(layout)
    sky = []
    for cam in make_cameras(0.25):
        t = layout.t_start + 0.7
        frame = render_camera(caster, cam, w.camera, t, np.random.default_rng(7))
        T_global_cam = layout.T_global_ego(t) @ cam.T_ego_cam
        dirs = pixel_directions(cam, T_global_cam)
        hits = caster.cast_camera(cam.K, T_global_cam, cam.width, cam.height, t, dirs)
        lit = sun_lit(caster, T_global_cam[:3, 3], dirs, hits, t, w.camera.shadows)
        noise = camera_noise(noise_key(np.random.default_rng(7)), len(dirs))
        image = camera_pixels(layout, T_global_cam[:3, 3], dirs, hits.range, hits.normal, hits.material, hits.albedo,
                              hits.reflectivity, lit, noise, w.camera.noise_std)
        assert np.array_equal(frame.image.reshape(-1, 3), image), cam.channel
        assert np.array_equal(frame.range.ravel(), hits.range.astype(np.float32))
        assert np.array_equal(frame.instance.ravel(), hits.instance)
        assert lit.any() and not lit.all()
        assert np.array_equal(to_float16(frame.range).view(np.uint16), frame.range.astype(np.float16).view(np.uint16))
        sky.append(np.isinf(frame.range).mean())
    assert max(sky) > 0.01
    z = camera_noise(12345, 200_000)
    assert abs(z.mean()) < 0.01 and abs(z.std() - 1.0) < 0.01 and np.abs(z).max() < 4.33
    assert np.array_equal(z, camera_noise(12345, 200_000)) and not np.array_equal(z, camera_noise(12346, 200_000))


def test_the_ego_body_fills_the_bottom_of_cam_back_only(tiny_world, nusc):
    """The cameras see the ego's own body where nuScenes' do (the bottom of CAM_BACK, none of the others): its exact
    range map equals the body's closed-form distance on every pixel whose ray meets it, nothing nearer, and the LiDAR
    never reports it (no point within the body)."""
    body = ego_body_from_params(tiny_world.params.world.ego_body)
    frame = load_frame(nusc, nusc.sample[0]["token"])
    for ch, view in frame.cameras.items():
        on_body = body.camera_ranges(view.K, view.T_ego_cam, view.width, view.height)
        hit = np.isfinite(on_body)
        if ch != "CAM_BACK":
            assert not hit.any(), ch
            continue
        rows = np.flatnonzero(hit.any(axis=1))
        assert 0.08 < hit.mean() < 0.25 and rows[-1] == view.height - 1  # a band along the bottom edge
        exact = view.load_range().astype(np.float64)
        np.testing.assert_allclose(exact[hit], on_body[hit], rtol=2e-3)  # float16 storage
        assert not np.isnan(exact).any()
        assert not (exact[~hit] < on_body[hit].min() - 1e-3).any()  # nothing else that near
    pts = apply(frame.lidar.T_ego_lidar, frame.lidar.points[:, :3].astype(np.float64))
    inside = ((pts[:, 0] > body.rear_x) & (pts[:, 0] < body.front_x) & (np.abs(pts[:, 1]) < body.width / 2)
              & (pts[:, 2] < body.roof_z))
    assert not inside.any()
