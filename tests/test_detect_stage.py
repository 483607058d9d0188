"""The `detect` stage end to end on the tiny world, with every weather copy a hard-linked replica of the clean
world (so that each evaluation on a copy must equal the clean one exactly): metrics layout, tables, figures, MLflow
child runs with their tags, and a resumed rerun that trains and evaluates nothing again."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from flows.detect import camera_weather_set
from flows.detect import headline as headline_of
from weatheralign.conditions import CONDITIONS, variant_name
from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.manifest import DatasetManifest, dataset_digest, manifest_path, read_manifest, write_manifest
from weatheralign.sensors import SensorRig, camera_models, lidar_model_from_params

from .conftest import HANG_GUARD_S, REPO, write_params_file

pytestmark = pytest.mark.slow  # whole detect stages, every training and evaluation of the protocol: make test-all

DETECT = {"finetune_conditions": ["snow"], "seeds": [0, 1], "image_size": [32, 64], "batch_size": 1,
          "pretrain_steps": 4, "finetune_steps": 2, "eval_every": 2, "num_bootstrap": 10, "score_threshold": 0.0,
          "max_detections": 50}


def _stage_env(tiny_world, tmp: Path, root: Path, source: str):
    """A detect stage set up in ``tmp`` on the nuScenes dataroot ``root`` (its manifest says ``source``), every
    weather copy a hard-linked replica of it; returns (data, reports, run), ``run()`` running the stage."""
    data, reports = tmp / "data", tmp / "reports"
    version = tiny_world.params.world.version
    nusc = open_nuscenes(root, version)
    frame = load_frame(nusc, nusc.scene[0]["first_sample_token"])
    sensors = SensorRig(lidar_model_from_params(tiny_world.params.world.lidar),
                        camera_models(frame.cameras, tiny_world.params.world.camera.exposure_s))
    write_manifest(manifest_path(data, "world"), DatasetManifest(
        str(root), version, source, sensors, dataset_digest(root, version), tuple(s["name"] for s in nusc.scene)))
    for condition in CONDITIONS:
        for aligned in (True, False):
            name = variant_name(condition, aligned)
            copy = data / "simulate" / name
            shutil.copytree(root, copy, copy_function=os.link)
            write_manifest(manifest_path(data, f"simulate-{name}"), DatasetManifest(
                str(copy), version, "simulate", sensors, dataset_digest(copy, version),
                tuple(s["name"] for s in nusc.scene)))
    params = write_params_file(tmp / "params.yaml", {
        "paths": {"data": str(data), "reports": str(reports)},
        "tracking": {"enabled": True, "mlflow_uri": f"sqlite:///{tmp / 'mlflow.db'}"},
        "run": {"show_progress": False, "max_workers": 1},
        "world": tiny_world.params.world.model_dump(mode="json"), "simulate": {"sweeps": 1}, "detect": DETECT})
    env = {**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING"}

    def run() -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "flows.detect", "--params", str(params)], cwd=REPO,
                              capture_output=True, text=True, timeout=HANG_GUARD_S, env=env)

    return data, reports, run


@pytest.fixture(scope="module")
def stage_run(tiny_world, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("detect")
    data, reports, run = _stage_env(tiny_world, tmp, tiny_world.dataroot, "synthetic")
    first = run()
    assert first.returncode == 0, first.stderr[-4000:]
    metrics = json.loads((reports / "detect" / "details.json").read_text())
    return tmp, data, reports, metrics, run


def test_a_real_layout_dataroot_goes_through_the_same_stage(tiny_world, tmp_path):
    """``world.source: nuscenes``: a dataroot with nuScenes' files only (no extras: no exact depth, no per-point
    records) trains and evaluates like the world."""
    real = tmp_path / "my_nuscenes"
    shutil.copytree(tiny_world.dataroot, real, ignore=shutil.ignore_patterns("extras", ".progress", ".weatheralign*"),
                    copy_function=os.link)
    _, reports, run = _stage_env(tiny_world, tmp_path / "stage", real, "nuscenes")
    done = run()
    assert done.returncode == 0, done.stderr[-4000:]
    metrics = json.loads((reports / "detect" / "details.json").read_text())
    variants = [variant_name(c, a) for c in CONDITIONS for a in (True, False)]
    assert set(metrics["models"]["pretrained"]) == {"clean", *variants, *map(camera_weather_set, variants)}
    assert 0.0 <= metrics["models"]["pretrained"]["clean"]["map"] <= 1.0
    assert not (real / "extras").exists()


def test_metrics_layout_and_reports(stage_run):
    _, data, reports, metrics, _ = stage_run
    variants = [variant_name(c, a) for c in CONDITIONS for a in (True, False)]
    assert set(metrics["models"]) == {"pretrained", "pretrained-lidar_only", "pretrained-camera_only",
                                      "pretrained-shuffled_images", "finetuned-snow", "finetuned-snow-mix",
                                      "finetuned-snow-unaligned"}
    assert set(metrics["models"]["pretrained"]) == {"clean", *variants, *map(camera_weather_set, variants)}
    assert metrics["models"]["pretrained"]["clean"]["seeds"] == [0, 1]
    assert metrics["models"]["finetuned-snow"]["clean"]["seeds"] == [0]
    assert set(metrics["models"]["finetuned-snow"]) == {"clean", "snow-aligned", "snow-unaligned"}
    for evals in metrics["models"].values():
        for m in evals.values():
            assert 0.0 <= m["map"] <= 1.0 and 0.0 <= m["nds"] <= 1.0
            assert m["map"] == pytest.approx(sum(m["map_per_seed"]) / len(m["map_per_seed"]), abs=1e-12)
            assert m["map_ci"][0] <= max(m["map_per_seed"]) + 1e-12
            assert min(m["map_per_seed"]) <= m["map_ci"][1] + 1e-12
            assert set(m["per_class_ap"]) == {"car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
                                              "motorcycle", "bicycle", "traffic_cone", "barrier"}
    assert set(metrics["modality_ablation"]) == {"fused", "lidar_only", "camera_only", "shuffled_images"}
    for other, ablated in (("lidar", "lidar_only"), ("camera", "camera_only"), ("shuffled_images", "shuffled_images")):
        d = metrics["differences"][f"pretrained:clean:fused-{other}:map"]  # fused minus the ablated model on clean val
        assert d["difference"] == pytest.approx(metrics["modality_ablation"]["fused"]["map"]
                                                - metrics["modality_ablation"][ablated]["map"], abs=1e-12)
    assert "Modality ablation" in (reports / "detect" / "table_alignment.md").read_text()
    assert {s: [p["step"] for p in curve] for s, curve in metrics["learning_curve"].items()} == {"0": [2, 4],
                                                                                                 "1": [2, 4]}
    results = json.loads((data / "detect" / "results" / "seed1" / "pretrained-camera_only" / "clean.json").read_text())
    assert results["meta"]["use_camera"] and not results["meta"]["use_lidar"]
    for name in ("table_alignment.md", "table_finetune.md", "learning_curve.png", "predictions_bev.png"):
        assert (reports / "detect" / name).stat().st_size > 0
    assert "paper" in (reports / "detect" / "table_alignment.md").read_text()
    names = ["world", *(f"simulate-{v}" for v in variants)]
    assert metrics["input_digests"] == {name: read_manifest(manifest_path(data, name)).content_digest
                                        for name in names}


def test_headline_metrics_and_plot_data(stage_run):
    """metrics.json (what ``dvc exp show`` compares) is the headline of details.json; the learning curve and the
    per-class AP are written as DVC plot data."""
    _, _, reports, metrics, _ = stage_run
    headline = json.loads((reports / "detect" / "metrics.json").read_text())
    assert headline == headline_of(metrics, ["snow"])
    assert headline["clean"] == {"map": metrics["models"]["pretrained"]["clean"]["map"],
                                 "nds": metrics["models"]["pretrained"]["clean"]["nds"]}
    assert set(headline["map"]) == {variant_name(c, a) for c in CONDITIONS for a in (True, False)}
    assert set(headline["finetuned_map"]) == {"snow"}
    # the rest stays in details.json (not a dvc exp show column): the ablation and the differences with intervals
    assert metrics["modality_ablation"]["camera_only"]["map"] is not None
    assert "ci" in metrics["differences"]["pretrained:snow:unaligned-aligned:map"]
    curve = json.loads((reports / "detect" / "learning_curve.json").read_text())
    assert [r["step"] for r in curve] == [2, 4]
    for row in curve:
        maps = [p["map"] for s in ("0", "1") for p in metrics["learning_curve"][s] if p["step"] == row["step"]]
        assert row["map_mean"] == pytest.approx(sum(maps) / 2) and (row["map_min"], row["map_max"]) == (min(maps),
                                                                                                       max(maps))
    per_class = json.loads((reports / "detect" / "per_class_ap.json").read_text())
    assert {r["class"]: r["ap"] for r in per_class} == metrics["models"]["pretrained"]["clean"]["per_class_ap"]


def test_identical_copies_score_identically(stage_run):
    """Every weather copy here is the clean world: same detections, same scores, RA 1, paired difference 0."""
    _, _, _, metrics, _ = stage_run
    pre = metrics["models"]["pretrained"]
    for name, m in pre.items():
        assert (m["map"], m["nds"], m["per_class_ap"]) == (pre["clean"]["map"], pre["clean"]["nds"],
                                                          pre["clean"]["per_class_ap"]), name
        assert m["ra"] == pytest.approx(1.0) or pre["clean"]["nds"] == 0.0
    d = metrics["differences"]["pretrained:snow:unaligned-aligned:map"]
    assert d["difference"] == 0.0 and d["ci"] == [0.0, 0.0] and not d["exceeds_noise"]


def test_mlflow_runs_are_tagged_for_the_ablation(stage_run):
    from mlflow.tracking import MlflowClient

    tmp = stage_run[0]
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp / 'mlflow.db'}")
    exp = client.get_experiment_by_name("weatheralign")
    runs = client.search_runs([exp.experiment_id], "tags.kind = 'eval' AND tags.alignment = 'unaligned'")
    assert {r.data.tags["weather"] for r in runs} == set(CONDITIONS)
    assert all("map" in r.data.metrics and "nds" in r.data.metrics for r in runs)
    assert {r.data.tags["severity"] for r in runs if r.data.tags["weather"] == "snow"} == {"2 mm/h"}
    trains = client.search_runs([exp.experiment_id], "tags.kind = 'train'")
    assert {r.data.tags["model"] for r in trains} == {"seed0/pretrained", "seed1/pretrained", "seed0/finetuned-snow",
                                                      "seed0/finetuned-snow-mix", "seed0/finetuned-snow-unaligned"}
    # one metric name across conditions: the stage run holds no per-condition metric, the differences are runs
    stage = client.search_runs([exp.experiment_id], "tags.stage = 'detect' AND tags.kind = 'stage'")[0]
    assert "parameters" in stage.data.metrics and not any("snow" in k or "clean" in k for k in stage.data.metrics)
    diffs = client.search_runs([exp.experiment_id], "tags.kind = 'difference' AND tags.comparison = "
                               "'unaligned-aligned' AND tags.metric = 'map'")
    assert {r.data.tags["weather"] for r in diffs} == set(CONDITIONS)
    assert all(r.data.metrics["difference"] == 0.0 for r in diffs)  # every copy here is the clean world
    inputs = {d.dataset.name: d for d in stage.inputs.dataset_inputs}
    assert {"clean/train", "clean/val", "snow-unaligned/train", "fog_light-aligned/val"} <= set(inputs)
    assert inputs["clean/val"].tags[0].value == "evaluation" and len(inputs["clean/val"].dataset.digest) == 16


def test_detector_checkpoints_are_registered_mlflow_models(stage_run):
    """Each trained model is a logged MLflow model, registered as a version of its model name with its seed as an
    alias; the version carries its evaluations, whose metrics link to it; loaded from the registry it predicts on
    its input example exactly as the stage's checkpoint."""
    import mlflow
    import torch
    from mlflow.tracking import MlflowClient

    from tasks.detector_model import predict_frame
    from weatheralign.config import load_params
    from weatheralign.detect.protocol import detector_config, load_checkpoint

    tmp, data = stage_run[0], stage_run[1]
    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    names = {m.name for m in client.search_registered_models()}
    assert {"weatheralign-detector-pretrained", "weatheralign-detector-finetuned-snow-mix"} <= names
    assert {"seed0", "seed1"} <= set(client.get_registered_model("weatheralign-detector-pretrained").aliases)
    version = client.get_model_version_by_alias("weatheralign-detector-finetuned-snow", "seed0")
    assert version.tags["map.snow-aligned"] and version.tags["nds.clean"]
    run = client.get_run(version.run_id)
    assert run.data.tags["kind"] == "train" and run.data.tags["model"] == "seed0/finetuned-snow"
    linked = [m for m in client.get_logged_model(version.source.removeprefix("models:/")).metrics if m.key == "map"]
    assert {m.dataset_name for m in linked} >= {"clean/val", "snow-aligned/val"}  # its evaluations
    mlflow.set_tracking_uri(uri)
    try:
        loaded = mlflow.pyfunc.load_model("models:/weatheralign-detector-finetuned-snow@seed0")
        inputs = loaded.input_example
    finally:
        mlflow.set_tracking_uri(None)
    checkpoint, _ = load_checkpoint(data / "detect" / "models" / "seed0" / "finetuned-snow.pt",
                                    detector_config(load_params(tmp / "params.yaml").detect))
    expected = predict_frame(checkpoint.eval(), inputs)
    got = loaded.predict(inputs)
    assert len(got) == len(expected) and torch.allclose(torch.tensor(got.iloc[:, :10].to_numpy()),
                                                        torch.tensor(expected.iloc[:, :10].to_numpy()), atol=1e-5)


def test_compare_reads_the_same_numbers_back_from_mlflow(stage_run, capsys):
    """``python -m flows.compare``: the aligned-vs-unaligned table from ``search_runs`` equals the stage's metrics."""
    from flows.compare import main

    tmp, _, _, metrics, _ = stage_run
    assert main(["--tracking-uri", f"sqlite:///{tmp / 'mlflow.db'}"]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()[2:]]
    pre = {r[1]: (float(r[2]), float(r[3])) for r in rows if r[0] == "| pretrained"}
    assert set(pre) == set(CONDITIONS)
    for weather, (aligned, unaligned) in pre.items():
        models = metrics["models"]["pretrained"]
        assert aligned == pytest.approx(models[f"{weather}-aligned"]["map"], abs=5e-4)
        assert unaligned == pytest.approx(models[f"{weather}-unaligned"]["map"], abs=5e-4)
    assert main(["--tracking-uri", f"sqlite:///{tmp / 'nothing.db'}"]) == 2
    assert "no MLflow experiment 'weatheralign'" in capsys.readouterr().err


def test_rerun_resumes_without_training_or_evaluating(stage_run):
    _, data, reports, metrics, run = stage_run
    checkpoints = {p: p.stat().st_mtime_ns for p in (data / "detect" / "models").rglob("*.pt")}
    evals = {p: p.stat().st_mtime_ns for p in (data / "detect" / "evals").rglob("*.json")}
    assert len(checkpoints) == 2 + 3 and len(evals) == 2 * (11 + 2 + 1 + 10) + 3 * 3
    assert not list((data / "detect" / "models").rglob("*.state.pt"))  # training states are removed when done
    again = run()
    assert again.returncode == 0, again.stderr[-4000:]
    assert {p: p.stat().st_mtime_ns for p in checkpoints} == checkpoints
    assert {p: p.stat().st_mtime_ns for p in evals} == evals
    rerun = json.loads((reports / "detect" / "details.json").read_text())
    assert rerun["models"] == metrics["models"] and rerun["learning_curve"] == metrics["learning_curve"]


def test_a_changed_weather_copy_retrains_what_used_it(stage_run):
    """A weather copy simulated again (one train-split scan rewritten: new mtime) is not the data the finished models
    were trained on: the models trained on it (and their evaluations) are redone; the pretrained model and the
    finetune on the untouched unaligned copy are resumed."""
    from weatheralign.detect.data import scene_split

    _, data, _, _, run = stage_run
    root = data / "simulate" / "snow-aligned"
    version = next(p.name for p in root.iterdir() if p.is_dir() and (p / "sample.json").is_file())
    nusc = open_nuscenes(root, version)
    token = scene_split(nusc, root, version, "train")[0]
    scan = root / nusc.get("sample_data", nusc.get("sample", token)["data"]["LIDAR_TOP"])["filename"]
    models = data / "detect" / "models"
    before = {p.relative_to(models).as_posix(): p.stat().st_mtime_ns for p in models.rglob("*.pt")}
    content = scan.read_bytes()
    scan.unlink()  # a hard link to the world's file: replace it by a file of its own, not the world's
    scan.write_bytes(content)
    again = run()
    assert again.returncode == 0, again.stderr[-4000:]
    after = {p.relative_to(models).as_posix(): p.stat().st_mtime_ns for p in models.rglob("*.pt")}
    changed = {name for name in before if after[name] != before[name]}
    assert len(before) == 5 and changed == {"seed0/finetuned-snow.pt", "seed0/finetuned-snow-mix.pt"}
