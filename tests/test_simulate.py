"""The `simulate` stage: the weather copy of a dataroot, the LiDAR identities, determinism, resume, and the
re-projection check (aligned snow sub-pixel, unaligned clearly worse) on the tiny full-resolution world."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from weatheralign.config import params_from_dict
from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import extras_relpath, load_frame, open_nuscenes
from weatheralign.medium.conditions import field_spec
from weatheralign.simulate import (Weather, config_hash, finalize_copy, fog_level, load_finished, scene_airlight,
                                   simulate_frame, simulate_lidar, simulate_or_resume, summarise, sweep_records,
                                   weather_for_scene, weather_relpath, with_fog_levels)

from .conftest import REPO

CFG = params_from_dict({}).simulate


def _snapshot(root: Path) -> dict[str, tuple[int, str]]:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(root.rglob("*")) if p.is_file()}


def _files(root: Path, skip: tuple[str, ...]) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()
            and not str(p.relative_to(root)).startswith(skip)}


@pytest.fixture(scope="module")
def world(tiny_world):
    nusc = open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)
    fields = {c: [field_spec(tiny_world.params.particles, c, s["name"],
                             nusc.get("sample", s["first_sample_token"])["timestamp"] * 1e-6).to_dict()
                  for s in nusc.scene] for c in ("snow", "rain")}
    scene = nusc.scene[0]
    frame = load_frame(nusc, scene["first_sample_token"])
    airlight = scene_airlight(list(frame.cameras.values()))
    return tiny_world, nusc, fields, frame, airlight


@pytest.fixture(scope="module")
def snow_copy(world, tmp_path_factory):
    """Snow, aligned: the first sample simulated, the rest copied; the input's snapshot taken before."""
    tw, nusc, fields, frame, airlight = world
    before = _snapshot(tw.dataroot)
    out = tmp_path_factory.mktemp("sim") / "snow-aligned"
    weather = weather_for_scene(CFG, nusc.scene[0]["name"], fields, "snow", True)
    record, now = simulate_or_resume(nusc, tw.dataroot, out, frame.token, weather, CFG, airlight, nthreads=2)
    assert now
    finalize_copy(nusc, tw.dataroot, out, tw.params.world.version)
    return out, before, record, weather


def test_weather_copy_loads_with_identical_tables_and_file_set(world, snow_copy):
    tw, nusc, _, frame, _ = world
    out, _, record, _ = snow_copy
    version = tw.params.world.version
    for table in sorted((tw.dataroot / version).iterdir()):
        assert (out / version / table.name).read_bytes() == table.read_bytes(), table.name
    assert _files(out, ("extras/weather", ".progress")) == _files(tw.dataroot, ("extras/range",))
    copy = open_nuscenes(out, version)
    assert len(copy.sample) == len(nusc.sample) and len(copy.sample_data) == len(nusc.sample_data)
    for sample in copy.sample:
        f = load_frame(copy, sample["token"])
        lidar_file = copy.get("sample_data", sample["data"]["LIDAR_TOP"])["filename"]
        rec = np.load(out / weather_relpath(lidar_file))
        assert len(rec) == len(f.lidar.points) == len(np.load(out / extras_relpath(lidar_file)))
    # the simulated sample changed: snow scattered points (with particle ids), the images differ
    wf = load_frame(copy, frame.token)
    lidar_file = copy.get("sample_data", copy.get("sample", frame.token)["data"]["LIDAR_TOP"])["filename"]
    rec = np.load(out / weather_relpath(lidar_file))
    assert (rec["label"] == 2).sum() > 100 and np.all(rec["particle_id"][rec["label"] == 2] >= 0)
    assert np.all(rec["particle_id"][rec["label"] != 2] == -1)
    assert not np.array_equal(wf.lidar.points, frame.lidar.points)
    for ch, view in frame.cameras.items():
        assert wf.cameras[ch].image_path.read_bytes() != view.image_path.read_bytes(), ch
    assert record["counts"]["SCATTERED"] > 0 and record["particles_rendered"] > 0


def test_input_is_unchanged(world, snow_copy):
    tw = world[0]
    assert _snapshot(tw.dataroot) == snow_copy[1]


def test_no_medium_gives_the_lidar_input_back(world):
    _, nusc, fields, frame, _ = world
    scan = frame.lidar
    fog = simulate_lidar(scan, Weather("fog_light", True, 0.0, 0.0, 0.0), CFG)
    np.testing.assert_array_equal(fog.scan.points, scan.points)
    assert fog.counts["UNCHANGED"] == len(scan.points) and np.all(fog.labels == 0)
    spec = weather_for_scene(CFG, nusc.scene[0]["name"], fields, "snow", True).field
    snow = simulate_lidar(scan, Weather("snow", True, field=replace(spec, rate_mm_h=0.0)), CFG)
    np.testing.assert_array_equal(snow.scan.points, scan.points)
    assert np.all(snow.particle_id == -1) and snow.counts["UNCHANGED"] == len(scan.points)
    # and a real fog level does change it (the identities above are not vacuous)
    dense = simulate_lidar(scan, weather_for_scene(CFG, nusc.scene[0]["name"], None, "fog_dense", True), CFG)
    assert dense.counts["UNCHANGED"] < 0.1 * len(scan.points)


def test_reprojection_aligned_subpixel_unaligned_clearly_worse(world, snow_copy):
    _, nusc, fields, frame, airlight = world
    aligned = np.asarray(snow_copy[2]["reprojection_px"])
    assert aligned.size >= 10
    assert aligned.mean() < 0.1 and aligned.max() < 0.5, (aligned.mean(), aligned.max())
    unaligned = simulate_frame(frame, weather_for_scene(CFG, nusc.scene[0]["name"], fields, "snow", False), CFG,
                               airlight, nthreads=2).reprojection_px
    assert unaligned.size >= 10
    assert unaligned.mean() > max(1.0, 20 * aligned.mean()), unaligned.mean()
    stats = summarise([snow_copy[2]])
    assert stats["reprojection_pairs"] == aligned.size and stats["reprojection_max_px"] == aligned.max()


def test_same_params_same_bytes(world, snow_copy, tmp_path):
    tw, nusc, _, frame, airlight = world
    out, _, _, weather = snow_copy
    again = tmp_path / "again"
    simulate_or_resume(nusc, tw.dataroot, again, frame.token, weather, CFG, airlight, nthreads=1)
    written = _files(again, (".progress",))
    assert len(written) == 9  # LiDAR + its extras + labels + 6 cameras
    for rel in written:
        assert (again / rel).read_bytes() == (out / rel).read_bytes(), rel


def test_resume_skips_finished_samples(world, snow_copy):
    tw, nusc, _, frame, airlight = world
    out, _, record, weather = snow_copy
    stamps = {rel: (out / rel).stat().st_mtime_ns for rel in _files(out, ())}
    again, now = simulate_or_resume(nusc, tw.dataroot, out, frame.token, weather, CFG, airlight)
    assert not now and again == record
    assert {rel: (out / rel).stat().st_mtime_ns for rel in _files(out, ())} == stamps
    # a different config is not a finished sample
    other = CFG.model_copy(update={"exposure_s": 0.004})
    assert load_finished(nusc, frame.token, out, config_hash(other, weather, tw.dataroot, 92)) is None


def test_fog_levels_and_unaligned_camera_alpha():
    aligned = weather_for_scene(CFG, "scene-0061", None, "fog_dense", True)
    assert aligned.lidar_alpha == aligned.camera_alpha == 0.04
    assert aligned.lidar_beta == pytest.approx(0.046 * 0.04 / np.log(20.0))
    cams = [weather_for_scene(CFG, f"scene-{i:04d}", None, "fog_light", False).camera_alpha for i in range(50)]
    assert all(0.01 <= a <= 0.04 for a in cams) and np.std(cams) > 0.005
    assert weather_for_scene(CFG, "scene-0001", None, "fog_light", False).lidar_alpha == 0.01


@pytest.mark.flow
def test_flow_writes_copy_and_metrics(world, tmp_path):
    """The Prefect flow end to end on one fog sample (tables, metrics keys, figure)."""
    tw, nusc, fields, _, _ = world
    reports = tmp_path / "reports"
    (reports / "world").mkdir(parents=True)
    (reports / "world" / "metrics.json").write_text(json.dumps({"dataroot": str(tw.dataroot),
                                                               "version": tw.params.world.version}))
    params = tmp_path / "params.yaml"
    params.write_text(json.dumps({"paths": {"data": str(tmp_path / "data"), "reports": str(reports)},
                                  "tracking": {"enabled": False}, "run": {"show_progress": False},
                                  "world": tw.params.world.model_dump(mode="json")}))
    levels = tmp_path / "data" / "calibrate_fog" / "fog_levels.json"
    levels.parent.mkdir(parents=True)
    levels.write_text(json.dumps({"light": {"alpha": 0.012, "beta": 0.0001}, "dense": {"alpha": 0.05, "beta": 0.0007}}))
    run = subprocess.run([sys.executable, "-m", "flows.simulate", "--params", str(params), "--set",
                          "simulate.condition=fog_dense", "--set", "simulate.aligned=unaligned", "--set",
                          "simulate.max_samples=1"], cwd=REPO, capture_output=True, text=True, timeout=600,
                         env={**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING"})
    assert run.returncode == 0, run.stderr[-3000:]
    out = tmp_path / "data" / "simulate" / "fog_dense-unaligned"
    metrics = json.loads((reports / "simulate" / "fog_dense-unaligned" / "metrics.json").read_text())
    assert metrics["samples_simulated_this_run"] == 1 and metrics["condition"] == "fog_dense"
    assert (metrics["fog_alpha"], metrics["fog_beta"], metrics["fog_levels"]) == (0.05, 0.0007, "calibrated")
    for key in ("dataroot", "points_unchanged", "points_attenuated", "points_scattered", "points_lost",
                "particles_rendered", "reprojection_mean_px", "reprojection_max_px", "reprojection_pairs",
                "seconds_per_sample"):
        assert key in metrics
    assert metrics["points_lost"] + metrics["points_scattered"] > 0 and metrics["reprojection_pairs"] == 0
    assert (reports / "simulate" / "fog_dense-unaligned" / "side_by_side.png").is_file()
    assert len(open_nuscenes(out, tw.params.world.version).sample) == len(nusc.sample)


def test_fog_levels_from_the_calibration_file(tmp_path):
    path = tmp_path / "fog_levels.json"
    path.write_text(json.dumps({"light": {"alpha": 0.008, "beta": 0.0002}, "dense": {"alpha": 0.03, "beta": 0.001},
                                "note": "extra keys are ignored"}))
    tuned = with_fog_levels(CFG, path)
    assert fog_level(tuned, "fog_light") == (0.008, 0.0002) and fog_level(tuned, "fog_dense") == (0.03, 0.001)
    assert weather_for_scene(tuned, "scene-0001", None, "fog_dense", True).camera_alpha == 0.03
    assert tuned.exposure_s == CFG.exposure_s and CFG.fog_alpha_light == 0.01  # the rest unchanged, input intact
    with pytest.raises(DataFormatError, match="run the calibrate_fog stage"):
        with_fog_levels(CFG, tmp_path / "absent.json")
    for bad, match in (({"light": {"alpha": 0.01}, "dense": {"alpha": 0.04, "beta": 0.001}}, "light.beta"),
                       ({"light": {"alpha": 0.05, "beta": 0.0}, "dense": {"alpha": 0.04, "beta": 0.0}}, "exceeds"),
                       ({"light": {"alpha": -0.01, "beta": 0.0}, "dense": {"alpha": 0.04, "beta": 0.0}}, "alpha > 0"),
                       ({"light": {"alpha": "x", "beta": 0.0}, "dense": {"alpha": 0.04, "beta": 0.0}}, "light.alpha")):
        path.write_text(json.dumps(bad))
        with pytest.raises(DataFormatError, match=match):
            with_fog_levels(CFG, path)
    path.write_text("{not json")
    with pytest.raises(DataFormatError, match="not valid JSON"):
        with_fog_levels(CFG, path)


def test_sweeps_through_the_same_medium_when_asked(world, tmp_path):
    tw, nusc, _, frame, airlight = world
    cfg = CFG.model_copy(update={"sweeps": True})
    weather = weather_for_scene(cfg, nusc.scene[0]["name"], None, "fog_dense", True)
    record, now = simulate_or_resume(nusc, tw.dataroot, tmp_path, frame.token, weather, cfg, airlight)
    sweeps = sweep_records(nusc, frame.token)
    assert now and len(sweeps) == tw.params.world.sweeps_per_sample
    for sd in sweeps:
        new = np.fromfile(tmp_path / sd["filename"], dtype="<f4").reshape(-1, 5)
        old = np.fromfile(tw.dataroot / sd["filename"], dtype="<f4").reshape(-1, 5)
        assert not np.array_equal(new, old)
        assert len(np.load(tmp_path / weather_relpath(sd["filename"]))) == len(new)
        assert len(np.load(tmp_path / extras_relpath(sd["filename"]))) == len(new)
    assert record["sweep_counts"]["LOST"] + record["sweep_counts"]["SCATTERED"] > 0
    assert simulate_or_resume(nusc, tw.dataroot, tmp_path, frame.token, weather, cfg, airlight)[1] is False


# ------------------------------------------------------------------------------------------------ real frames
REAL = REPO.parent / "shared" / "data" / "real"


def _real_frame(name: str):
    from weatheralign.data.kitti import load_kitti_frame
    from weatheralign.data.stf import load_stf_frame
    root = REAL / name
    if not root.exists():
        pytest.skip(f"real sample not available: {root}")
    if name == "stf":
        return load_stf_frame(root, "2019-09-11_19-13-44_00960")
    return load_kitti_frame(root / "000008.bin", root / "000008.png", root / "calib.json")


@pytest.mark.parametrize("name", ["stf", "kitti"])
def test_reprojection_on_real_frames(name: str) -> None:
    """A real scan + camera (dense depth from the scan, no exact range map): the LiDAR's scattering snowflakes land
    on their rasterised centroids in the camera; with an independent camera field they do not."""
    frame = _real_frame(name)
    particles = params_from_dict({}).particles
    spec = field_spec(particles, "snow", f"real-{name}", frame.lidar.timestamp)
    airlight = scene_airlight(list(frame.cameras.values()))
    aligned = simulate_frame(frame, Weather("snow", True, field=spec), CFG, airlight, nthreads=2)
    err = aligned.reprojection_px
    assert aligned.lidar.counts["SCATTERED"] > 100 and err.size >= 10, (aligned.lidar.counts, err.size)
    assert err.mean() < 0.1 and err.max() < 0.5, (err.mean(), err.max())
    cam = next(iter(aligned.cameras.values()))
    assert cam.drawn > 100 and cam.image.shape == (frame.cameras[next(iter(frame.cameras))].height,
                                                   frame.cameras[next(iter(frame.cameras))].width, 3)
    unaligned = simulate_frame(frame, Weather("snow", False, field=spec), CFG, airlight, nthreads=2).reprojection_px
    assert unaligned.size >= 10 and unaligned.mean() > max(1.0, 20 * err.mean()), unaligned.mean()
