"""The `simulate` stage: the weather copy of a dataroot, the LiDAR identities, determinism, resume, the
re-projection check (aligned snow sub-pixel, unaligned clearly worse) on the tiny full-resolution world, and the
mixed condition fog_snow as a composition of its media."""

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

from weatheralign import atomic
from weatheralign.camera.fog import CLIPPED, encode_srgb_u8, srgb_to_linear
from weatheralign.conditions import CONDITIONS, ParticlePart
from weatheralign.config import params_from_dict
from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import (
    compressed_extras_relpath,
    load_frame,
    load_lidar,
    open_nuscenes,
    read_point_extras,
)
from weatheralign.ground.edit import edit_scan, scan_surfaces, unseen_beams
from weatheralign.ground.snow import TireTracks
from weatheralign.lidar import simulate_fog, simulate_particle_scans
from weatheralign.lidar.labels import WeatherLabel
from weatheralign.manifest import DatasetManifest, dataset_digest, manifest_path, read_manifest, write_manifest
from weatheralign.medium.conditions import field_spec
from weatheralign.sensors import SensorRig, camera_models, ego_body_from_params, lidar_model_from_params
from weatheralign.simulate.media import (
    ConditionMedia,
    SceneMedia,
    calibrated_fog_levels,
    params_fog_levels,
    resolve_media,
)
from weatheralign.simulate.observe import (
    JOINT_DRIFT_MAX_M,
    ObserveOptions,
    joint_drift_m,
    observe,
    observe_lidar,
    observe_lidar_scans,
)
from weatheralign.simulate.plan import SampleJob, plan_jobs, sample_range_maps, scene_airlight
from weatheralign.simulate.weather_copy import (
    copy_outputs,
    finalize_copy,
    read_weather_record,
    run_sample,
    smallest_int_dtype,
    summarise,
    sweep_records,
    weather_relpath,
    written_list_path,
)

from .conftest import REPO, write_params_file

pytestmark = pytest.mark.usefixtures("shared_prefect_api")  # stages in subprocesses share one Prefect server

CFG = params_from_dict({}).simulate
OPTIONS = ObserveOptions(threads=2)
RUN = "test-run"


def _snapshot(root: Path) -> dict[str, tuple[int, str]]:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(root.rglob("*")) if p.is_file()}


def _files(root: Path, skip: tuple[str, ...]) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()
            and not str(p.relative_to(root)).startswith(skip)}


def _media(condition: str, scenes: list[str], fields: dict | None, cfg=CFG) -> ConditionMedia:
    return resolve_media(CONDITIONS[condition], cfg, scenes, params_fog_levels(cfg), fields)


def _inputs(frame):
    images = {ch: v.load_image() for ch, v in frame.cameras.items()}
    return images, {ch: v.load_range() for ch, v in frame.cameras.items()}


@pytest.fixture(scope="module")
def world(tiny_world):
    nusc = open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)
    fields = {c: [field_spec(tiny_world.params.particles, c, s["name"],
                             nusc.get("sample", s["first_sample_token"])["timestamp"] * 1e-6)
                  for s in nusc.scene] for c in ("snow", "rain")}
    scene = nusc.scene[0]
    frame = load_frame(nusc, scene["first_sample_token"])
    airlight = tuple(scene_airlight(nusc, frame.token))
    sensors = SensorRig(lidar_model_from_params(tiny_world.params.world.lidar),
                        camera_models(frame.cameras, tiny_world.params.world.camera.exposure_s))
    scenes = [s["name"] for s in nusc.scene]
    return tiny_world, nusc, fields, frame, airlight, sensors, scenes


def _job(world, condition: str, aligned: bool, cfg=CFG) -> SampleJob:
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    media = _media(condition, scenes, fields, cfg).for_scene(scenes[0], aligned)
    return SampleJob(frame.token, media, airlight)


@pytest.fixture(scope="module")
def snow_copy(world, tmp_path_factory):
    """Snow, aligned: the first sample simulated, the rest copied; the input's snapshot taken before."""
    tw, nusc, fields, frame, airlight, sensors, _ = world
    before = _snapshot(tw.dataroot)
    out = tmp_path_factory.mktemp("sim") / "snow-aligned"
    job = _job(world, "snow", True)
    record, now = run_sample(nusc, tw.dataroot, out, job, sensors, OPTIONS, RUN)
    assert now
    finalize_copy(nusc, tw.dataroot, out, tw.params.world.version, copy_outputs(nusc, [frame.token], 0))
    return out, before, record, job


def test_weather_copy_loads_with_identical_tables_and_file_set(world, snow_copy):
    tw, nusc, _, frame, *_ = world
    out, _, record, _ = snow_copy
    version = tw.params.world.version
    for table in sorted((tw.dataroot / version).iterdir()):
        assert (out / version / table.name).read_bytes() == table.read_bytes(), table.name
    lidar_file = copy_lidar = nusc.get("sample_data", nusc.get("sample", frame.token)["data"]["LIDAR_TOP"])["filename"]
    written = _files(out, ("extras/weather", ".progress"))
    # the same files as the input (the weather scan's per-point records compressed), range maps left out
    assert {f.replace(compressed_extras_relpath(copy_lidar), compressed_extras_relpath(copy_lidar)[:-1] + "y")
            for f in written} == _files(tw.dataroot, ("extras/range",))
    weather_files = copy_outputs(nusc, [frame.token], 0)
    for rel in written - weather_files:  # everything the weather did not touch is a hard link to the input
        assert (out / rel).samefile(tw.dataroot / rel), rel
    for rel in weather_files:
        assert (out / rel).stat().st_nlink == 1, rel
    copy = open_nuscenes(out, version)
    assert len(copy.sample) == len(nusc.sample) and len(copy.sample_data) == len(nusc.sample_data)
    for sample in copy.sample:
        f = load_frame(copy, sample["token"])
        lidar_file = copy.get("sample_data", sample["data"]["LIDAR_TOP"])["filename"]
        rec = read_weather_record(out, lidar_file, len(f.lidar.points))
        assert len(rec) == len(f.lidar.points) == len(read_point_extras(out, lidar_file))
    # the simulated sample changed: snow scattered points (with particle ids), the images differ
    wf = load_frame(copy, frame.token)
    rec = read_weather_record(out, copy_lidar, len(wf.lidar.points))
    # labels, ids and rows in the smallest exact dtypes
    assert rec.dtype["label"] == np.uint8 and rec.dtype["source_index"] == np.dtype(np.int32)
    assert rec.dtype["particle_id"] == smallest_int_dtype(rec["particle_id"]).newbyteorder("=")
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
    tw, nusc, fields, frame, _, sensors, scenes = world
    scan = frame.lidar
    snow = CONDITIONS["snow"]
    fog = observe_lidar(scan, SceneMedia(CONDITIONS["fog_light"], True, scenes[0]), sensors.lidar)
    np.testing.assert_array_equal(fog.scan.points, scan.points)
    assert fog.counts["UNCHANGED"] == len(scan.points) and np.all(fog.labels == 0)
    spec = replace(fields["snow"][0], rate_mm_h=0.0)
    none = observe_lidar(scan, SceneMedia(snow, True, scenes[0], field=spec), sensors.lidar)
    np.testing.assert_array_equal(none.scan.points, scan.points)
    assert np.all(none.particle_id == -1) and none.counts["UNCHANGED"] == len(scan.points)
    # and a real fog level does change it (the identities above are not vacuous)
    dense = observe_lidar(scan, _media("fog_dense", scenes, None).for_scene(scenes[0], True), sensors.lidar)
    assert dense.counts["UNCHANGED"] < 0.1 * len(scan.points)


def test_reprojection_aligned_subpixel_unaligned_clearly_worse(world, snow_copy):
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    aligned = np.asarray(snow_copy[2]["reprojection_px"])
    assert aligned.size >= 10
    assert aligned.mean() < 0.1 and aligned.max() < 0.5, (aligned.mean(), aligned.max())
    images, ranges = _inputs(frame)
    unaligned = observe(frame, images, ranges, _job(world, "snow", False).media, sensors, np.asarray(airlight),
                        OPTIONS).reprojection_px
    assert unaligned.size >= 10
    assert unaligned.mean() > max(1.0, 20 * aligned.mean()), unaligned.mean()
    stats = summarise([snow_copy[2]])
    assert stats["reprojection_pairs"] == aligned.size and stats["reprojection_max_px"] == aligned.max()


def test_same_params_same_bytes(world, snow_copy, tmp_path):
    tw, nusc, _, frame, airlight, sensors, _ = world
    out, _, _, job = snow_copy
    again = tmp_path / "again"
    run_sample(nusc, tw.dataroot, again, job, sensors, ObserveOptions(threads=1), RUN)
    written = _files(again, (".progress",))
    assert len(written) == 9  # LiDAR + its extras + labels + 6 cameras
    for rel in written:
        assert (again / rel).read_bytes() == (out / rel).read_bytes(), rel


def test_resume_skips_finished_samples(world, snow_copy):
    tw, nusc, _, frame, airlight, sensors, _ = world
    out, _, record, job = snow_copy
    stamps = {rel: (out / rel).stat().st_mtime_ns for rel in _files(out, ())}
    again, now = run_sample(nusc, tw.dataroot, out, job, sensors, OPTIONS, RUN)
    assert not now and again == record
    assert {rel: (out / rel).stat().st_mtime_ns for rel in _files(out, ())} == stamps
    assert not (out / ".progress").exists()  # records live beside the copy: the copy holds only data
    # a truncated output is not a finished one: the sample is redone, to the same bytes
    jpeg = next(out / rel for rel in _files(out, ()) if rel.endswith(".jpg") and "CAM_FRONT" in rel
                and (out / rel).read_bytes() != (tw.dataroot / rel).read_bytes())
    good = jpeg.read_bytes()
    jpeg.write_bytes(good[:1000])
    again, now = run_sample(nusc, tw.dataroot, out, job, sensors, OPTIONS, RUN)
    assert now and jpeg.read_bytes() == good
    # leftover temporaries of a killed run's writes are removed when the copy is completed; a user's file is not
    leftover = jpeg.with_name(f".{jpeg.name}.ab12cd34.tmp")  # named as `atomic.atomic_path` names them
    users = out / "samples" / "CAM_FRONT" / ".x.jpg.abc123.tmp"
    leftover.write_bytes(b"x")
    users.write_bytes(b"x")
    finalize_copy(nusc, tw.dataroot, out, tw.params.world.version, copy_outputs(nusc, [frame.token], 0))
    assert not leftover.exists() and users.exists()
    users.unlink()
    # another sensor (a different exposure), another run fingerprint: not a finished sample
    other = SensorRig(sensors.lidar, {k: replace(v, exposure_s=0.004) for k, v in sensors.cameras.items()})
    assert run_sample(nusc, tw.dataroot, out / "x", job, other, OPTIONS, RUN)[1]
    assert run_sample(nusc, tw.dataroot, out / "y", job, sensors, OPTIONS, "another-run")[1]


def test_fog_levels_and_unaligned_camera_alpha():
    scenes = [f"scene-{i:04d}" for i in range(50)]
    dense = _media("fog_dense", scenes, None)
    aligned = dense.for_scene(scenes[0], True)
    assert aligned.lidar_alpha == aligned.camera_alpha == 0.04
    assert aligned.lidar_beta == pytest.approx(0.046 * 0.04 / np.log(20.0))
    light = _media("fog_light", scenes, None)
    cams = [light.for_scene(s, False).camera_alpha for s in scenes]
    assert all(0.01 <= a <= 0.04 for a in cams) and np.std(cams) > 0.005
    assert light.for_scene(scenes[1], False).lidar_alpha == 0.01
    # media round-trip through their JSON form
    assert ConditionMedia.from_dict(json.loads(json.dumps(dense.to_dict()))) == dense


def test_unaligned_particles_see_the_twin_at_a_rate_of_their_own(world):
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    media = _media("snow", scenes, fields)
    assert ConditionMedia.from_dict(json.loads(json.dumps(media.to_dict()))) == media
    for scene in scenes:
        aligned, unaligned = media.for_scene(scene, True), media.for_scene(scene, False)
        rate = aligned.field.rate_mm_h
        assert aligned.camera_rate_mm_h is None and aligned.camera_field() == aligned.field.field()
        assert rate / 3.0 <= unaligned.camera_rate_mm_h <= rate * 3.0  # simulate.unaligned_rate_factor: 3
        assert unaligned.camera_field().seed == aligned.field.field(aligned=False).seed
        assert unaligned.camera_field().distribution.snowfall_rate == pytest.approx(unaligned.camera_rate_mm_h)
        assert unaligned.field == aligned.field  # the LiDAR sees the condition's own field either way
    spread = [ParticlePart.camera_rate(False, 2.0, 3.0, seed) for seed in range(400)]
    logs = np.log(np.array(spread) / 2.0) / np.log(3.0)  # ~ U[-1, 1]
    assert abs(float(logs.mean())) < 0.1 and logs.min() < -0.9 and logs.max() > 0.9
    assert ParticlePart.camera_rate(True, 2.0, 3.0, 5) == ParticlePart.camera_rate(False, 2.0, 1.0, 5) == 2.0
    positions_only = _media("snow", scenes, fields, CFG.model_copy(update={"unaligned_rate_factor": 1.0}))
    assert positions_only.for_scene(scenes[0], False).camera_rate_mm_h == positions_only.fields[scenes[0]].rate_mm_h


def test_plan_walks_every_sample_with_its_scene_media(world):
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    jobs = plan_jobs(nusc, _media("fog_snow", scenes, fields), aligned=False)
    assert [j.sample_token for j in jobs] == [s["token"] for s in sorted(nusc.sample, key=lambda s: (
        [sc["token"] for sc in nusc.scene].index(s["scene_token"]), s["timestamp"]))]
    for job in jobs:
        scene = nusc.get("scene", nusc.get("sample", job.sample_token)["scene_token"])
        assert job.media.scene == scene["name"] and not job.media.aligned
        assert job.media.field.scene == scene["name"]
    assert jobs[0].airlight == airlight
    assert len(plan_jobs(nusc, _media("snow", scenes, fields), True, max_samples=3)) == 3


def test_every_condition_resolves_to_its_media(world):
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    for name, condition in CONDITIONS.items():
        media = _media(name, scenes, fields).for_scene(scenes[0], True)
        assert (media.lidar_alpha > 0) == (condition.fog is not None), name
        assert (media.field is not None) == (condition.particles is not None), name
    with pytest.raises(DataFormatError, match="needs snow fields"):
        _media("fog_snow", scenes, None)


@pytest.mark.slow
@pytest.mark.flow
def test_flow_writes_copy_and_metrics(world, tmp_path):
    """The media and simulate flows end to end on one fog sample (tables, metrics keys, figure), tracked in MLflow:
    the runs of the unaligned condition are found by their tags and carry the metrics under their plain names."""
    tw, nusc, fields, frame, _, sensors, scenes = world
    data, reports = tmp_path / "data", tmp_path / "reports"
    version = tw.params.world.version
    write_manifest(manifest_path(data, "world"), DatasetManifest(str(tw.dataroot), version, "synthetic", sensors,
                                                                 dataset_digest(tw.dataroot, version), tuple(scenes)))
    (data / "particles").mkdir(parents=True)
    (data / "particles" / "fields.json").write_text(
        json.dumps({k: [f.to_dict() for f in v] for k, v in fields.items()}))
    params = write_params_file(tmp_path / "params.yaml", {
        "paths": {"data": str(data), "reports": str(reports)},
        "tracking": {"enabled": True, "mlflow_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"},
        "run": {"show_progress": False}, "world": tw.params.world.model_dump(mode="json")})
    levels = data / "calibrate_fog" / "fog_levels.json"
    levels.parent.mkdir(parents=True)
    levels.write_text(json.dumps({"light": {"alpha": 0.012, "beta": 0.0001}, "dense": {"alpha": 0.05, "beta": 0.0007}}))
    rates = data / "calibrate_precipitation" / "rates.json"
    rates.parent.mkdir(parents=True)
    rates.write_text(json.dumps({"snow": {"rate_mm_h": 3.0}}))  # a reference without a rain split: rain keeps params
    env = {**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING"}
    run = subprocess.run([sys.executable, "-m", "flows.media", "--params", str(params)], cwd=REPO,
                         capture_output=True, text=True, timeout=600, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    assert sorted(p.stem for p in (data / "media").glob("*.json")) == sorted(CONDITIONS)
    run = subprocess.run([sys.executable, "-m", "flows.simulate", "--params", str(params), "--set",
                          "simulate.condition=fog_dense", "--set", "simulate.aligned=unaligned", "--set",
                          "simulate.max_samples=1"], cwd=REPO, capture_output=True, text=True, timeout=600, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    out = data / "simulate" / "fog_dense-unaligned"
    metrics = json.loads((reports / "simulate" / "fog_dense-unaligned" / "details.json").read_text())
    assert metrics["samples_simulated_this_run"] == 1 and metrics["condition"] == "fog_dense"
    assert (metrics["fog_alpha"], metrics["fog_beta"], metrics["fog_levels"]) == (0.05, 0.0007, "calibrated")
    assert 0.012 <= metrics["camera_fog_alpha"] <= 0.05
    for key in ("dataroot", "points_unchanged", "points_attenuated", "points_scattered", "points_lost",
                "particles_rendered", "reprojection_mean_px", "reprojection_max_px", "reprojection_pairs",
                "seconds_per_sample"):
        assert key in metrics
    assert metrics["points_lost"] + metrics["points_scattered"] > 0 and metrics["reprojection_pairs"] == 0
    assert (reports / "simulate" / "fog_dense-unaligned" / "side_by_side.png").is_file()
    assert len(open_nuscenes(out, version).sample) == len(nusc.sample)
    handoff = read_manifest(manifest_path(data, "simulate-fog_dense-unaligned"))  # the stage's DVC output
    assert Path(handoff.dataroot).resolve() == out.resolve() and handoff.source == "simulate"
    assert handoff.content_digest == dataset_digest(out, version) != dataset_digest(tw.dataroot, version)
    assert handoff.sensors == sensors and handoff.scenes == tuple(scenes)
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("weatheralign")
    unaligned = client.search_runs([exp.experiment_id], "tags.alignment = 'unaligned'")
    assert [r.data.tags["mlflow.runName"] for r in unaligned] == ["simulate/fog_dense-unaligned"]
    tags = unaligned[0].data.tags
    assert ((tags["stage"], tags["kind"], tags["weather"], tags["severity"])
            == ("simulate", "stage", "fog_dense", "dense"))
    assert unaligned[0].data.metrics["points_lost_per_keyframe"] == round(metrics["points_lost"]
                                                                          / metrics["num_samples"], 2)
    assert "reprojection_p99_px" not in unaligned[0].data.metrics  # fog: no particle to re-project (None: not logged)
    assert [d.dataset.digest for d in unaligned[0].inputs.dataset_inputs] == [dataset_digest(tw.dataroot, version)]
    media_runs = client.search_runs([exp.experiment_id], "tags.stage = 'media' AND tags.kind = 'condition'")
    assert {r.data.tags["weather"]: r.data.tags["severity"] for r in media_runs} == {
        "fog_light": "light", "fog_dense": "dense", "snow": "3 mm/h", "rain": "50 mm/h", "fog_snow": "light + 3 mm/h"}
    media_metrics = json.loads((reports / "media" / "details.json").read_text())
    assert media_metrics["precipitation_rates"] == {"snow": {"rate_mm_h": 3.0, "source": "calibrated"}, "rain": {
        "rate_mm_h": 50.0, "source": "params (no rain split in the reference)"}}
    snow = json.loads((data / "media" / "snow.json").read_text())
    assert {f["rate_mm_h"] for f in snow["fields"].values()} == {3.0}
    assert {r.data.metrics.get("fog_alpha") for r in media_runs if r.data.tags["weather"] == "fog_dense"} == {0.05}
    bad = subprocess.run([sys.executable, "-m", "flows.simulate", "--params", str(params), "--set",
                          "simulate.condition=hail"], cwd=REPO, capture_output=True, text=True, timeout=600, env=env)
    assert bad.returncode == 2 and "simulate.condition = 'hail' is invalid" in bad.stderr


def test_fog_levels_from_the_calibration_file(tmp_path):
    path = tmp_path / "fog_levels.json"
    path.write_text(json.dumps({"light": {"alpha": 0.008, "beta": 0.0002}, "dense": {"alpha": 0.03, "beta": 0.001},
                                "note": "extra keys are ignored"}))
    tuned = calibrated_fog_levels(path)
    assert (tuned.alpha, tuned.beta) == ({"light": 0.008, "dense": 0.03}, {"light": 0.0002, "dense": 0.001})
    media = resolve_media(CONDITIONS["fog_dense"], CFG, ["scene-0001"], tuned, None)
    assert media.for_scene("scene-0001", True).camera_alpha == 0.03
    with pytest.raises(DataFormatError, match="run the calibrate_fog stage"):
        calibrated_fog_levels(tmp_path / "absent.json")
    for bad, match in (({"light": {"alpha": 0.01}, "dense": {"alpha": 0.04, "beta": 0.001}}, "light.beta"),
                       ({"light": {"alpha": 0.05, "beta": 0.0}, "dense": {"alpha": 0.04, "beta": 0.0}}, "exceeds"),
                       ({"light": {"alpha": -0.01, "beta": 0.0}, "dense": {"alpha": 0.04, "beta": 0.0}}, "alpha > 0"),
                       ({"light": {"alpha": "x", "beta": 0.0}, "dense": {"alpha": 0.04, "beta": 0.0}}, "light.alpha")):
        path.write_text(json.dumps(bad))
        with pytest.raises(DataFormatError, match=match):
            calibrated_fog_levels(path)
    path.write_text("{not json")
    with pytest.raises(DataFormatError, match="not valid JSON"):
        calibrated_fog_levels(path)


def test_calibrated_airlight_gains_reach_each_scene_alike_for_both_cameras(tmp_path):
    """The calibration's airlight gains: read and validated, one drawn per scene (deterministic, every gain used),
    the same for the aligned and the unaligned cameras; a file without them keeps the clear sky's airlight."""
    path = tmp_path / "fog_levels.json"
    gains = [0.8, 1.0, 1.25]
    path.write_text(json.dumps({"light": {"alpha": 0.008, "beta": 0.0002},
                                "dense": {"alpha": 0.03, "beta": 0.001, "airlight_gains": gains}}))
    tuned = calibrated_fog_levels(path)
    assert tuned.airlight_gains == {"light": (1.0,), "dense": (0.8, 1.0, 1.25)}
    scenes = [f"scene-{i:04d}" for i in range(60)]
    media = resolve_media(CONDITIONS["fog_dense"], CFG, scenes, tuned, None)
    drawn = [media.for_scene(s, True).airlight_gain for s in scenes]
    assert set(drawn) == set(gains)
    assert drawn == [media.for_scene(s, False).airlight_gain for s in scenes]
    assert drawn == [resolve_media(CONDITIONS["fog_dense"], CFG, scenes, tuned, None).for_scene(s, True).airlight_gain
                     for s in scenes]
    assert {media.for_scene(s, True).airlight_gain for s in scenes} != {1.0}
    light = resolve_media(CONDITIONS["fog_light"], CFG, scenes, tuned, None)
    assert {light.for_scene(s, True).airlight_gain for s in scenes} == {1.0}
    assert ConditionMedia.from_dict(json.loads(json.dumps(media.to_dict()))) == media
    for bad in ([], [0.0], ["x"], 1.2):
        path.write_text(json.dumps({"light": {"alpha": 0.008, "beta": 0.0002},
                                    "dense": {"alpha": 0.03, "beta": 0.001, "airlight_gains": bad}}))
        with pytest.raises(DataFormatError, match="dense.airlight_gains"):
            calibrated_fog_levels(path)


def test_the_fogs_sky_is_the_clear_sky_times_the_airlight_gain(world):
    """Where the camera sees sky (infinite ray length), dense fog shows its airlight alone: the scene's clear-sky
    airlight times the scene's gain, in linear light (and a gain of 1 is the clear sky's own)."""
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    images, ranges = _inputs(frame)
    fog = _media("fog_dense", scenes, None).for_scene(scenes[0], True)
    ch = next(c for c in images if np.isinf(ranges[c]).sum() > 1000)
    sky = np.isinf(ranges[ch])
    for gain in (1.0, 0.7, 1.3):
        out = observe(frame, images, ranges, replace(fog, airlight_gain=gain), sensors, np.asarray(airlight), OPTIONS)
        expected = encode_srgb_u8(np.minimum(srgb_to_linear(np.asarray(airlight)) * gain, srgb_to_linear(CLIPPED)))
        assert np.abs(out.cameras[ch].image[sky].astype(int) - expected.astype(int)).max() <= 1, gain


def test_the_nearest_sweeps_through_the_same_medium(world, tmp_path):
    """``sweeps=1``: the sweep nearest before the keyframe gets the weather (its own records), the older one stays
    clear (a hard link after completion); asking for fewer sweeps later turns a stale weather sweep back into a link."""
    tw, nusc, _, frame, airlight, sensors, _ = world
    job = _job(world, "fog_dense", True)
    sweeps = sweep_records(nusc, frame.token)
    assert len(sweeps) == tw.params.world.sweeps_per_sample == 2
    record, now = run_sample(nusc, tw.dataroot, tmp_path, job, sensors, OPTIONS, RUN, sweeps=1)
    assert now and record["sweeps_simulated"] == 1
    new = np.fromfile(tmp_path / sweeps[-1]["filename"], dtype="<f4").reshape(-1, 5)
    old = np.fromfile(tw.dataroot / sweeps[-1]["filename"], dtype="<f4").reshape(-1, 5)
    assert not np.array_equal(new, old)
    assert len(read_weather_record(tmp_path, sweeps[-1]["filename"], len(new))) == len(new)
    assert len(read_point_extras(tmp_path, sweeps[-1]["filename"])) == len(new)
    assert not (tmp_path / sweeps[0]["filename"]).exists()
    assert record["sweep_counts"]["LOST"] + record["sweep_counts"]["SCATTERED"] > 0
    assert run_sample(nusc, tw.dataroot, tmp_path, job, sensors, OPTIONS, RUN, sweeps=1)[1] is False
    version = tw.params.world.version
    stray = tmp_path / "samples" / "LIDAR_TOP" / "an-earlier-input__LIDAR_TOP__1.pcd.bin"  # no table lists it
    stray.write_bytes(b"\0" * 20)  # placed by a run over an earlier input, which recorded it:
    atomic.write_json(written_list_path(tmp_path), {"files": [str(stray.relative_to(tmp_path))]})
    users = tmp_path / "samples" / "LIDAR_TOP" / "my-own-scan.pcd.bin"  # not the stage's: stays
    users.write_bytes(b"\0" * 20)
    finalize_copy(nusc, tw.dataroot, tmp_path, version, copy_outputs(nusc, [frame.token], 1))
    assert not stray.exists() and users.exists()
    assert (tmp_path / sweeps[0]["filename"]).samefile(tw.dataroot / sweeps[0]["filename"])
    finalize_copy(nusc, tw.dataroot, tmp_path, version, copy_outputs(nusc, [frame.token], 0))
    assert (tmp_path / sweeps[-1]["filename"]).samefile(tw.dataroot / sweeps[-1]["filename"])
    assert not (tmp_path / weather_relpath(sweeps[-1]["filename"])).exists()
    assert not (tmp_path / compressed_extras_relpath(sweeps[-1]["filename"])).exists()


def test_smallest_int_dtype_is_exact() -> None:
    """Particle ids are 64-bit hashes: with -1 (no particle) beside them the dtype must stay an exact integer type
    (numpy promotes int8 with uint64 to float64, which rounds ids above 2**53)."""
    ids = np.array([-1, 4614232489362325784, 4614223693260915629], dtype=np.int64)
    dtype = smallest_int_dtype(ids)
    assert dtype.kind == "i" and np.array_equal(ids.astype(dtype).astype(np.int64), ids)
    for values in ([-1, 5], [0, 300], [-1, 70000], [0, 2**40]):
        a = np.array(values, dtype=np.int64)
        dtype = smallest_int_dtype(a)
        assert dtype.kind in "iu" and dtype.itemsize <= 8 and np.array_equal(a.astype(dtype).astype(np.int64), a)
    assert smallest_int_dtype(np.array([0, 300])).itemsize == 2


def test_unaligned_copy_takes_its_aligned_twins_lidar(world, tmp_path):
    """The LiDAR sees the condition's own media in both copies: the unaligned copy hard-links its aligned twin's LiDAR
    files (keyframe and sweep) and gets exactly what computing them gives (files, counts, re-projection errors,
    images); a twin of another LiDAR fingerprint, or with a damaged file, is not used."""
    tw, nusc, _, frame, airlight, sensors, _ = world
    twin, alone, linked = tmp_path / "snow-aligned", tmp_path / "alone", tmp_path / "snow-unaligned"
    run_sample(nusc, tw.dataroot, twin, _job(world, "snow", True), sensors, OPTIONS, RUN, sweeps=1)
    job = _job(world, "snow", False)
    rec_alone, _ = run_sample(nusc, tw.dataroot, alone, job, sensors, OPTIONS, RUN, sweeps=1)
    rec_linked, _ = run_sample(nusc, tw.dataroot, linked, job, sensors, OPTIONS, RUN, sweeps=1, lidar_twin=twin)
    assert rec_linked["lidar_from_twin"] and not rec_alone["lidar_from_twin"]
    lidar_rels = [r for r in rec_alone["files"] if "LIDAR_TOP" in r]
    assert len(lidar_rels) == 6  # keyframe and one sweep: scan, extras, weather record each
    for rel in rec_alone["files"]:
        assert (linked / rel).read_bytes() == (alone / rel).read_bytes(), rel
    for rel in lidar_rels:
        assert (linked / rel).samefile(twin / rel), rel
    for key in ("counts", "sweep_counts", "reprojection_px", "reprojection_channels", "particles_rendered"):
        assert rec_linked[key] == rec_alone[key], key
    assert len(rec_alone["reprojection_px"]) >= 10
    # another run fingerprint: the twin is not used
    rec_other, _ = run_sample(nusc, tw.dataroot, tmp_path / "other", job, sensors, OPTIONS, "another-run", sweeps=1,
                              lidar_twin=twin)
    assert not rec_other["lidar_from_twin"]
    # a damaged twin file: not used either, and the result is still the computed one
    sweep_rel = next(r for r in lidar_rels if r.startswith("sweeps/") and r.endswith(".pcd.bin"))
    damaged = (twin / sweep_rel).read_bytes()
    (twin / sweep_rel).unlink()
    (twin / sweep_rel).write_bytes(damaged[:-20])
    again = tmp_path / "again"
    rec_again, _ = run_sample(nusc, tw.dataroot, again, job, sensors, OPTIONS, RUN, sweeps=1, lidar_twin=twin)
    assert not rec_again["lidar_from_twin"]
    assert (again / sweep_rel).read_bytes() == (alone / sweep_rel).read_bytes()


# ------------------------------------------------------------------------------------------------ mixed weather
def test_fast_fields_run_each_scan_alone_slow_ones_jointly(world):
    """A keyframe and its 2 sweeps: snow (1.5 m/s, 0.2 m of drift over the three) goes through one joint run, rain
    at its drop-size fall speed (~6.7 m/s, 1 m) scan by scan, exactly as a run on each scan alone would give it."""
    tw, nusc, fields, frame, _, sensors, scenes = world
    scans = [frame.lidar, *(load_lidar(nusc, sd["token"]) for sd in sweep_records(nusc, frame.token))]
    assert len(scans) == 3
    for condition, joint_expected in (("snow", True), ("rain", False)):
        media = replace(_media(condition, scenes, fields).for_scene(scenes[0], True), ground=None)  # the air alone
        fld = media.field.field()
        drift = joint_drift_m(scans, sensors.lidar, float(np.linalg.norm(fld.velocity_array)))
        assert (drift <= JOINT_DRIFT_MAX_M) == joint_expected, drift
        got = observe_lidar_scans(scans, media, sensors.lidar)
        kw = {"lidar": sensors.lidar, "reflectivity": media.condition.particles.lidar_reflectivity}
        want = (simulate_particle_scans(scans, fld, **kw) if joint_expected
                else [simulate_particle_scans([scan], fld, **kw)[0] for scan in scans])
        for lw, res, scan in zip(got, want, scans):
            np.testing.assert_array_equal(lw.scan.points, res.apply_to(scan).points)
            np.testing.assert_array_equal(lw.particle_id, res.particle_id)
        assert sum(lw.counts["SCATTERED"] for lw in got) > 0


def test_fog_snow_lidar_is_the_composition_of_its_media(world):
    """fog_snow's LiDAR: fog's attenuation and backscatter plus the flakes' echoes in one response. With the field
    emptied it is exactly fog (same labels and points as simulate_fog); with the fog removed, exactly snow; with
    both, flakes still scatter (with ids), dimmer than in snow alone (the fog attenuates their echoes), and fog echoes
    appear (without ids). Dense fog's echoes land where `simulate_fog` puts them (the particle path
    once reported them at the raw power peak, 1.5 m farther). The world's sensor with its intensity noise (both paths
    decide the floor on the noisy reading), at its own floor and 100x lower where fog echoes are wanted (under its own
    floor they are never reported: docs/physics.md 3.5)."""
    tw, nusc, fields, frame, _, sensors, scenes = world
    assert sensors.lidar.intensity_noise_std > 0.0
    scan = frame.lidar
    mixed = replace(_media("fog_snow", scenes, fields).for_scene(scenes[0], True), ground=None)  # the air alone
    snow = replace(_media("snow", scenes, fields).for_scene(scenes[0], True), ground=None)
    no_field = replace(mixed, field=replace(mixed.field, rate_mm_h=0.0))
    a = observe_lidar(scan, no_field, sensors.lidar)
    fog = simulate_fog(scan, mixed.lidar_alpha, mixed.lidar_beta, lidar=sensors.lidar)
    assert fog.counts["LOST"] > 100  # returns lost to the fog, on noisy readings
    assert np.array_equal(a.labels, fog.labels) and np.array_equal(a.scan.points, fog.points)
    sensors = replace(sensors, lidar=replace(sensors.lidar, noise_floor=sensors.lidar.noise_floor / 100))
    # dense fog: its echoes too, reported by both paths at the peak minus c tau_H / 2 with each beam's range noise
    dense = replace(no_field, lidar_alpha=0.06, lidar_beta=0.046 * 0.06 / np.log(20.0))
    a = observe_lidar(scan, dense, sensors.lidar)
    fog = simulate_fog(scan, dense.lidar_alpha, dense.lidar_beta, lidar=sensors.lidar)
    assert (fog.labels == 2).sum() > 100
    assert np.array_equal(a.labels, fog.labels) and np.array_equal(a.scan.points, fog.points)
    no_fog = replace(mixed, lidar_alpha=0.0, lidar_beta=0.0, camera_alpha=0.0)
    b, c = observe_lidar(scan, no_fog, sensors.lidar), observe_lidar(scan, snow, sensors.lidar)
    assert np.array_equal(b.scan.points, c.scan.points) and np.array_equal(b.particle_id, c.particle_id)
    both = observe_lidar(scan, replace(mixed, lidar_alpha=0.04, lidar_beta=0.046 * 0.04 / np.log(20.0)),
                         sensors.lidar)
    scattered = both.labels == 2
    assert (scattered & (both.particle_id >= 0)).sum() > 50 and (scattered & (both.particle_id < 0)).sum() > 20
    # the fog dims the flakes' echoes (their targets more: behind the fog more flakes beat them)
    flakes_fog, flakes = scattered & (both.particle_id >= 0), (c.labels == 2) & (c.particle_id >= 0)
    assert np.median(both.scan.points[flakes_fog, 3]) < np.median(c.scan.points[flakes, 3])


def test_fog_snow_cameras_see_fog_and_prefogged_flakes(world):
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    images, ranges = _inputs(frame)
    mixed = _media("fog_snow", scenes, fields).for_scene(scenes[0], True)
    fw = observe(frame, images, ranges, mixed, sensors, np.asarray(airlight), OPTIONS)
    fog_only = observe(frame, images, ranges, replace(mixed, field=replace(mixed.field, rate_mm_h=0.0)), sensors,
                       np.asarray(airlight), OPTIONS)
    ch = "CAM_FRONT"
    far = ranges[ch] > 60.0
    # the far scene is washed towards the airlight in both; the flakes add detail on top of the fog
    for out in (fw, fog_only):
        contrast = np.std(out.cameras[ch].image[far].astype(float))
        assert contrast < np.std(images[ch][far].astype(float))
    assert fw.cameras[ch].drawn > 100 and fog_only.cameras[ch].drawn == 0
    assert not np.array_equal(fw.cameras[ch].image, fog_only.cameras[ch].image)
    assert fw.reprojection_px.size >= 10 and fw.reprojection_px.max() < 0.5


# ------------------------------------------------------------------------------------------------ the ground
def test_the_lidar_sees_the_ground_first_then_the_air(world):
    """With a ground, each scan is edited on its surfaces first (`edit_scan`) and the air's weather runs on what is
    left: the same points as the air alone on the edited scan, rows told in the input's numbering, the points the
    ground alone changed labelled GROUND, every input point and every return the snow adds on a road its clear beam
    missed (`unseen_beams`) counted once."""
    tw, nusc, fields, frame, _, sensors, scenes = world
    scans = [frame.lidar, *(load_lidar(nusc, sd["token"]) for sd in sweep_records(nusc, frame.token))]
    for condition in ("snow", "rain"):
        media = _media(condition, scenes, fields).for_scene(scenes[0], True)
        assert media.ground is not None and media.ground.kind == {"snow": "snow", "rain": "wet"}[condition]
        got = observe_lidar_scans(scans, media, sensors.lidar)
        state = media.ground.state(camera=False, tracks=TireTracks.along_heading(scans[0].T_global_lidar))
        lidar = sensors.lidar
        edited = [edit_scan(scan, scan_surfaces(scan, off_ground=state.kind == "snow"), state, lidar.noise_floor,
                            lidar.intensity_noise_std, None if lidar.floor_range_m is None else lidar.floor_scale,
                            unseen_beams(scan, lidar) if state.kind == "snow" else None)
                  for scan in scans]
        air = observe_lidar_scans([e.scan for e in edited], replace(media, ground=None), sensors.lidar)
        for lw, e, a, scan in zip(got, edited, air, scans):
            np.testing.assert_array_equal(lw.scan.points, a.scan.points)
            kept = a.source_index >= 0
            np.testing.assert_array_equal(lw.source_index[kept], e.source_index[a.source_index[kept]])
            ground_only = kept & (a.labels == 0) & e.changed[np.where(kept, a.source_index, 0)]
            assert ground_only.sum() > 0
            assert (lw.labels[ground_only] == WeatherLabel.GROUND).all()
            points = sum(lw.counts[k] for k in ("UNCHANGED", "ATTENUATED", "SCATTERED", "LOST", "GROUND",
                                                  "GROUND_LOST"))
            assert points == len(scan.points) + e.added and lw.counts["GROUND_LOST"] == e.lost
            assert lw.counts["GROUND_ADDED"] == e.added
        if condition == "snow":  # the snow on a road the HDL-32E's clear beams missed under the floor returns
            assert all(e.added > 0 for e in edited)
        if condition == "rain":
            assert sum(e.lost for e in edited) > 0  # the film pushes the weakest ground returns under the floor


def test_one_ground_for_the_lidar_and_the_cameras(world):
    """Aligned, the cameras edit the pixels the LiDAR's edited ground returns land on (IoU >= 0.9 in every camera);
    unaligned, they see another field at another depth on the same surfaces; with simulate.ground off, nothing of the
    ground is left."""
    tw, nusc, fields, frame, airlight, sensors, scenes = world
    images, ranges = _inputs(frame)
    for condition in ("snow", "rain"):
        aligned = observe(frame, images, ranges, _media(condition, scenes, fields).for_scene(scenes[0], True),
                          sensors, np.asarray(airlight), OPTIONS)
        assert set(aligned.ground_iou) == set(images) and min(aligned.ground_iou.values()) >= 0.9, aligned.ground_iou
        unaligned_media = _media(condition, scenes, fields).for_scene(scenes[0], False)
        assert (unaligned_media.ground.camera_seed != unaligned_media.ground.seed
                and unaligned_media.ground.camera_amount_m != unaligned_media.ground.amount_m)
        unaligned = observe(frame, images, ranges, unaligned_media, sensors, np.asarray(airlight), OPTIONS,
                            lidar=aligned.lidar)
        # the twin's film or snow lies on the same surfaces (the masks agree as well), drawn otherwise
        assert not np.array_equal(unaligned.cameras["CAM_FRONT"].image, aligned.cameras["CAM_FRONT"].image)
    off = _media("snow", scenes, fields, CFG.model_copy(update={"ground": False})).for_scene(scenes[0], True)
    assert off.ground is None and CONDITIONS["fog_dense"].ground is None
    plain = observe(frame, images, ranges, off, sensors, np.asarray(airlight), OPTIONS)
    assert plain.ground_iou == {} and all(c.ground_mask is None for c in plain.cameras.values())


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
    """A real scan + camera (dense depth from the scan, no exact range map, the LiDAR model estimated from the scan):
    the LiDAR's scattering snowflakes land on their rasterised centroids in the camera; with an independent camera
    field they do not."""
    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.fog import estimate_airlight
    from weatheralign.sensors import estimate_lidar_model

    frame = _real_frame(name)
    particles = params_from_dict({}).particles
    spec = field_spec(particles, "snow", f"real-{name}", frame.lidar.timestamp)
    sensors = SensorRig(estimate_lidar_model([frame.lidar], rotation_hz=10.0), camera_models(frame.cameras, 0.005))
    images = {ch: v.load_image() for ch, v in frame.cameras.items()}
    ranges = {ch: camera_range_map(v, frame.lidar, images[ch]) for ch, v in frame.cameras.items()}
    airlight = estimate_airlight(list(images.values()), list(ranges.values()))
    media = SceneMedia(CONDITIONS["snow"], True, f"real-{name}", field=spec)
    aligned = observe(frame, images, ranges, media, sensors, airlight, OPTIONS)
    err = aligned.reprojection_px
    assert aligned.lidar.counts["SCATTERED"] > 100 and err.size >= 10, (aligned.lidar.counts, err.size)
    assert err.mean() < 0.1 and err.max() < 0.5, (err.mean(), err.max())
    cam = next(iter(aligned.cameras.values()))
    view = next(iter(frame.cameras.values()))
    assert cam.drawn > 100 and cam.image.shape == (view.height, view.width, 3)
    unaligned = observe(frame, images, ranges, replace(media, aligned=False), sensors, airlight,
                        OPTIONS).reprojection_px
    assert unaligned.size >= 10 and unaligned.mean() > max(1.0, 20 * err.mean()), unaligned.mean()


def test_ego_velocity_from_every_sensor_pose(tmp_path):
    """A keyframe without sweeps (no per-firing poses): the seven sensor poses of a nuScenes sample, ~45 ms apart,
    give the ego's velocity; the scan's per-firing poses join the fit; poses all at one instant give 0."""
    from weatheralign.data.frame import CameraView, Frame, LidarScan
    from weatheralign.simulate.observe import ego_velocity

    v = np.array([9.0, -2.0, 0.1])

    def pose(t: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = np.array([100.0, 50.0, 1.0]) + v * t
        return T

    t0 = 1_700_000_000.0  # seconds of a nuScenes-like clock: the fit must not lose precision to the offset
    cams = {f"CAM_{k}": CameraView(f"CAM_{k}", tmp_path / f"{k}.jpg", np.eye(3), 16, 9, np.eye(4),
                                    pose(0.0075 * k - 0.04), t0 + 0.0075 * k - 0.04) for k in range(6)}
    scan = LidarScan(np.zeros((0, 5), np.float32), t0, np.eye(4), pose(0.0))
    assert np.allclose(ego_velocity(Frame("s", t0, scan, cams)), v, atol=1e-6)
    assert np.array_equal(ego_velocity(Frame("s", t0, scan, {})), np.zeros(3))  # one pose: unknown
    times = t0 + np.linspace(-0.05, 0.0, 11)
    swept = LidarScan(np.zeros((0, 5), np.float32), t0, np.eye(4), pose(0.0), pose_times=times,
                      poses=np.stack([pose(t - t0) for t in times]))
    assert np.allclose(ego_velocity(Frame("s", t0, swept, {})), v, atol=1e-6)
    still = {k: CameraView(c.channel, c.image_path, c.K, 16, 9, c.T_ego_cam, c.T_global_ego, t0)
             for k, c in cams.items()}
    assert np.array_equal(ego_velocity(Frame("s", t0, scan, still)), np.zeros(3))


def test_estimated_depth_puts_the_ego_body_at_its_own_distance(world, tmp_path):
    """Real data has no exact range maps and its LiDAR never sees the own car: the completion from the LiDAR gives the
    body's pixels the far scene (or sky), and fog or particles would be drawn on the car. With the rig's ego body the
    pixels whose rays meet it get its distance (exactly the synthetic world's rendered range there), the rest keeps
    the completion; the synthetic world's exact maps are left as they are."""
    import shutil

    tw, nusc, _, frame, _, _, _ = world
    body = ego_body_from_params(tw.params.world.ego_body)
    real = tmp_path / "real"  # the tiny world without its extras (exact range maps), as a real dataset comes
    shutil.copytree(tw.dataroot, real, ignore=shutil.ignore_patterns("extras", ".progress", ".weatheralign*"))
    real_nusc = open_nuscenes(real, tw.params.world.version)
    real_frame = load_frame(real_nusc, frame.token)
    images = {ch: v.load_image() for ch, v in real_frame.cameras.items()}
    plain = sample_range_maps(real_nusc, real_frame, images)
    masked = sample_range_maps(real_nusc, real_frame, images, body)
    view = real_frame.cameras["CAM_BACK"]
    on_body = body.camera_ranges(view.K, view.T_ego_cam, view.width, view.height)
    hit = np.isfinite(on_body)
    assert hit.mean() > 0.05 and (plain["CAM_BACK"][hit] > 2.0 * on_body[hit]).mean() > 0.9  # the defect
    np.testing.assert_array_equal(masked["CAM_BACK"][hit], on_body[hit])
    np.testing.assert_allclose(masked["CAM_BACK"][hit], frame.cameras["CAM_BACK"].load_range()[hit], rtol=2e-3)
    np.testing.assert_array_equal(masked["CAM_BACK"][~hit], plain["CAM_BACK"][~hit])
    for ch in ("CAM_FRONT", "CAM_BACK_LEFT"):
        np.testing.assert_array_equal(masked[ch], plain[ch])
    exact_images = {ch: v.load_image() for ch, v in frame.cameras.items()}
    exact = sample_range_maps(nusc, frame, exact_images, body)
    np.testing.assert_array_equal(exact["CAM_BACK"], frame.cameras["CAM_BACK"].load_range().astype(np.float32))


def test_calibrated_ground_depths_reach_the_media(tmp_path):
    from weatheralign.config import ParticlesConfig, SimulateConfig
    from weatheralign.data.errors import DataFormatError
    from weatheralign.simulate.media import calibrated_precipitation_rates, resolve_ground

    path = tmp_path / "rates.json"
    path.write_text(json.dumps({"snow": {"rate_mm_h": 2.0}, "rain": {"rate_mm_h": 40.0},
                                "ground": {"snow": {"depth_m": 0.07}}}))
    rates = calibrated_precipitation_rates(path, ParticlesConfig())
    assert rates.ground_depth_m == {"snow": 0.07}
    cfg = SimulateConfig()
    snow = resolve_ground(CONDITIONS["fog_snow"], cfg, ["s1"], rates.ground_depth_m)["s1"]
    rain = resolve_ground(CONDITIONS["rain"], cfg, ["s1"], rates.ground_depth_m)["s1"]
    assert snow.amount_m == 0.07 and rain.amount_m == cfg.wet_film_depth_m  # no rain ground calibrated: params
    path.write_text(json.dumps({"snow": {"rate_mm_h": 2.0}, "ground": {"snow": {"depth_m": -1}}}))
    with pytest.raises(DataFormatError, match=r"ground\.snow\.depth_m"):
        calibrated_precipitation_rates(path, ParticlesConfig())
