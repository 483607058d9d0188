"""Sensors as data: the LiDAR model's firing grid, its estimation from real scans, serialisation, and no-return
beams on worlds with other firing grids (900 / 1800 firings per ring)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.lidar.beams import beams_from_scan, grid_no_return_beams
from weatheralign.manifest import DatasetManifest, dataset_digest, read_manifest, write_manifest
from weatheralign.sensors import (
    DEFAULT_NOISE_FLOOR,
    CameraModel,
    EgoBody,
    SensorRig,
    camera_models,
    ego_body_from_params,
    estimate_lidar_model,
    estimate_noise_floor,
    lidar_model_from_params,
)
from weatheralign.world.dataset import finalize, render_or_resume, sample_jobs

from .conftest import SHARED_REAL, tiny_params


def test_firing_pattern_covers_the_grid_once_in_time_order(tiny_world):
    model = lidar_model_from_params(tiny_world.params.world.lidar)
    pattern = model.firing_pattern()
    n = model.num_rings * model.columns_per_ring
    assert len(pattern.ring) == n and len(np.unique(pattern.column.astype(int) * 32 + pattern.ring)) == n
    assert np.all((pattern.time_offsets >= -model.period) & (pattern.time_offsets < 0.0))
    az = np.arctan2(pattern.directions[pattern.ring == 0, 1], pattern.directions[pattern.ring == 0, 0])
    step = np.angle(np.exp(1j * np.diff(az)))
    assert np.allclose(step, -2 * np.pi / model.columns_per_ring)  # clockwise
    ccw = replace(model, clockwise=False).firing_pattern()
    az2 = np.arctan2(ccw.directions[ccw.ring == 0, 1], ccw.directions[ccw.ring == 0, 0])
    assert np.allclose(np.angle(np.exp(1j * np.diff(az2))), 2 * np.pi / model.columns_per_ring)


def test_model_and_manifest_round_trip(tiny_world, tmp_path):
    nusc = open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)
    frame = load_frame(nusc, nusc.sample[0]["token"])
    rig = SensorRig(lidar_model_from_params(tiny_world.params.world.lidar), camera_models(frame.cameras, 0.005))
    assert SensorRig.from_dict(json.loads(json.dumps(rig.to_dict()))) == rig
    digest = dataset_digest(tiny_world.dataroot, tiny_world.params.world.version)
    manifest = DatasetManifest(str(tiny_world.dataroot), "v1.0-mini", "synthetic", rig, digest, ("a", "b"))
    path = tmp_path / "m.json"
    write_manifest(path, manifest)
    first = path.read_bytes()
    assert read_manifest(path) == manifest
    write_manifest(path, read_manifest(path))
    assert path.read_bytes() == first  # same manifest, same bytes
    broken = json.loads(first)
    del broken["sensors"]["lidar"]["pulse"]
    path.write_text(json.dumps(broken))
    with pytest.raises(Exception, match="m.json.*lidar"):
        read_manifest(path)
    with pytest.raises(ValueError, match="exposure_s"):
        CameraModel("CAM_FRONT", ((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0)), 10, 10, -1.0)


def test_dataset_digest_follows_content(tiny_world, tmp_path):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(tiny_world.dataroot, root)
    version = tiny_world.params.world.version
    d0 = dataset_digest(root, version)
    assert d0 == dataset_digest(tiny_world.dataroot, version)  # location-independent
    scan = next((root / "samples" / "LIDAR_TOP").iterdir())
    scan.write_bytes(scan.read_bytes()[:-20])  # one point fewer
    assert dataset_digest(root, version) != d0


def test_estimated_model_recovers_the_synthetic_sensor(tiny_world):
    """Estimated from the world's scans alone (as for real data), the model matches the declared one."""
    nusc = open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)
    scans = [load_frame(nusc, s["token"]).lidar for s in nusc.sample]
    truth = lidar_model_from_params(tiny_world.params.world.lidar)
    est = estimate_lidar_model(scans, rotation_hz=None)
    assert est.num_rings == 32 and est.clockwise and est.origin == "estimated"
    assert abs(est.columns_per_ring - truth.columns_per_ring) <= 0.01 * truth.columns_per_ring
    assert np.max(np.abs(np.subtract(est.elevations_deg, truth.elevations_deg))) < 0.1
    assert est.rotation_hz == 20.0 and est.noise_floor >= 0.0
    over = estimate_lidar_model(scans, overrides={"divergence_rad": 2e-3, "pulse_half_width_s": 5e-9})
    assert over.divergence_rad == 2e-3 and over.pulse.tau_h == 5e-9
    with pytest.raises(ValueError, match="unknown override"):
        estimate_lidar_model(scans, overrides={"beam_width": 1.0})


@pytest.mark.parametrize("name,rings", [("stf", 64), ("kitti", 64)])
def test_estimated_model_of_real_scans(name: str, rings: int) -> None:
    from weatheralign.data.kitti import load_kitti_frame
    from weatheralign.data.stf import load_stf_frame

    root = SHARED_REAL / name
    if not root.exists():
        pytest.skip(f"real sample not available: {root}")
    frame = (load_stf_frame(root, "2019-09-11_19-13-44_00960") if name == "stf" else
             load_kitti_frame(root / "000008.bin", root / "000008.png", root / "calib.json"))
    model = estimate_lidar_model([frame.lidar], rotation_hz=10.0)
    assert model.num_rings == rings
    assert 1000 <= model.columns_per_ring <= 5000  # HDL-64E: ~2000-4500 firings per turn
    assert model.intensity_max == frame.lidar.intensity_max
    assert model.elevations_deg[0] > model.elevations_deg[-1] or name == "stf"  # STF's channel 0 is the lowest
    # STF clamps weak returns to 24 (15 % of its points), KITTI's reflectance starts at 0: neither is a floor
    assert model.noise_floor == DEFAULT_NOISE_FLOOR


def test_noise_floor_is_the_smallest_intensity_only_when_it_is_a_tail() -> None:
    rng = np.random.default_rng(0)
    smooth = 3.0 + rng.exponential(20.0, 10_000)
    assert estimate_noise_floor(smooth) == pytest.approx(smooth.min())
    clamped = np.concatenate([np.full(500, 24.0), 24.0 + rng.exponential(50.0, 9_500)])
    assert estimate_noise_floor(clamped) == DEFAULT_NOISE_FLOOR
    assert estimate_noise_floor(np.concatenate([[0.0], smooth])) == DEFAULT_NOISE_FLOOR
    assert estimate_noise_floor(np.array([])) == DEFAULT_NOISE_FLOOR


@pytest.mark.parametrize("firings", [900, 1800])
def test_other_firing_grids_get_their_own_no_return_beams(firings: int, tmp_path) -> None:
    """A world rendered with 900 or 1800 firings per ring: every cell of its own grid is a beam (a point or a
    no-return beam), none twice; the default grid would have failed (1800) or been silently wrong (900)."""
    params = tiny_params(tmp_path, num_train_scenes=1, num_val_scenes=1, samples_per_scene=2, sweeps_per_sample=0,
                         camera={"image_scale": 0.1}, lidar={"firings_per_ring": firings})
    dataroot = tmp_path / "world"
    results = [render_or_resume(spec, k, params.world, dataroot)[0] for spec, k in sample_jobs(params.world)]
    finalize(params.world, dataroot, results)
    nusc = open_nuscenes(dataroot, params.world.version)
    scan = load_frame(nusc, nusc.sample[0]["token"]).lidar
    model = lidar_model_from_params(params.world.lidar)
    beams = beams_from_scan(scan, lidar=model)
    assert len(beams) == 32 * firings and beams.num_returns == len(scan.points)
    default = lidar_model_from_params(params.world.lidar.model_copy(update={"firings_per_ring": 1085}))
    from weatheralign.lidar.beams import synthetic_columns
    if firings > 1085:
        with pytest.raises(ValueError, match="firing grid"):
            grid_no_return_beams(scan, synthetic_columns(scan), default.firing_pattern())
    else:  # the wrong grid silently gives wrong beams: far more "missing" cells than the true grid
        wrong = grid_no_return_beams(scan, synthetic_columns(scan), default.firing_pattern())
        assert len(wrong) != 32 * firings - len(scan.points)
    from weatheralign.lidar import simulate_particles
    from weatheralign.medium.conditions import field_spec

    spec = field_spec(params.particles, "snow", nusc.scene[0]["name"], scan.timestamp)
    res = simulate_particles(scan, spec.field(), lidar=model, reflectivity=0.9)
    assert res.counts["CLUTTER"] > 0 and res.counts["SCATTERED"] > 0


# ------------------------------------------------------------------------------------------------ the ego body


def test_ego_body_ray_distances_against_closed_forms() -> None:
    """Entry distances into the prism: a vertical ray onto the flat roof, a ray onto the sloping hatch (the plane's
    closed form), a ray through the side wall; misses, rays starting inside and rays pointing away give inf."""
    body = EgoBody(rear_x=-0.66, front_x=-0.25, roof_z=1.47, hatch_z=1.02, bottom_z=0.25, width=1.73)
    down = body.ray_distances([[-0.4, 0.3, 3.0]], [[0.0, 0.0, -1.0]])[0]
    slope_z = 1.02 + (1.47 - 1.02) * (-0.4 + 0.66) / (-0.25 + 0.66)  # the hatch's height at x = -0.4
    assert down == pytest.approx(3.0 - slope_z, abs=1e-12)
    slope = 0.45 / 0.41  # the hatch: z = 1.47 + (x + 0.25) slope
    o, d = np.array([-0.3, 0.0, 2.0]), np.array([-0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0)
    t = (1.47 + (o[0] + 0.25) * slope - o[2]) / (d[2] - d[0] * slope)  # ray meets the hatch plane
    assert -0.66 < o[0] + t * d[0] < -0.25
    assert body.ray_distances(o[None], d[None])[0] == pytest.approx(t, rel=1e-12)
    # a ray from below the hatch's plane enters through the face at front_x, not the hatch
    o, d = np.array([0.03, 0.0, 1.57]), np.array([-0.884, 0.0, -0.468]) / np.hypot(0.884, 0.468)
    assert body.ray_distances(o[None], d[None])[0] == pytest.approx((-0.25 - 0.03) / d[0], rel=1e-12)
    side = body.ray_distances([[-0.5, 3.0, 0.5]], [[0.0, -1.0, 0.0]])[0]
    assert side == pytest.approx(3.0 - 0.865, abs=1e-12)
    inf = body.ray_distances([[-0.5, 3.0, 0.5], [-0.5, 0.0, 0.5], [-0.5, 0.0, 3.0], [-0.5, 3.0, 0.5]],
                             [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert np.isinf(inf).all()  # away from it; from inside; parallel above it; parallel beside it
    with pytest.raises(ValueError, match="rear_x < front_x"):
        EgoBody(rear_x=0.2, front_x=0.1, roof_z=1.4, hatch_z=1.4, bottom_z=0.2, width=1.7)


def test_ego_body_travels_in_the_manifest_and_comes_from_params(tiny_world) -> None:
    body = ego_body_from_params(tiny_world.params.world.ego_body)
    assert body is not None and body.corners().shape == (8, 3)
    rig = SensorRig(lidar_model_from_params(tiny_world.params.world.lidar), {}, body)
    assert SensorRig.from_dict(json.loads(json.dumps(rig.to_dict()))) == rig
    bare = replace(rig, ego_body=None)
    assert SensorRig.from_dict(json.loads(json.dumps(bare.to_dict()))) == bare
    assert ego_body_from_params(None) is None
    with pytest.raises(ValueError, match="sensors.ego_body"):
        SensorRig.from_dict({**rig.to_dict(), "ego_body": {"rear_x": 1.0}})
