"""Real Prefect flow runs of the `world` stage (thread pool and a Dask cluster), with MLflow tracking."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from flows.common import parse_stage_args

from .conftest import REPO

TINY = ["--set", "world.num_train_scenes=1", "--set", "world.num_val_scenes=1", "--set", "world.samples_per_scene=2",
        "--set", "world.sweeps_per_sample=1", "--set", "world.camera.image_scale=0.2",
        "--set", "run.show_progress=false"]


def test_cli_rejects_bad_override_naming_the_key(capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_stage_args("world", ["--params", str(REPO / "params.yaml"), "--set", "world.ego_speed_max=30"])
    assert exit_info.value.code == 2
    assert "world.ego_speed_max = 30 is invalid: Input should be less than or equal to 12" in capsys.readouterr().err


def _run_world(tmp: Path, extra: list[str], env: dict[str, str], stage: str = "world") -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", f"flows.{stage}", "--params", str(REPO / "params.yaml"), *TINY,
            "--set", f"paths.data={tmp / 'data'}", "--set", f"paths.reports={tmp / 'reports'}",
            "--set", f"tracking.mlflow_uri=sqlite:///{tmp / 'mlflow.db'}", *extra]
    return subprocess.run(args, cwd=tmp, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture
def prefect_server(monkeypatch):
    """A Prefect API server for the flow runs and for Dask workers (workers in other processes need a server they
    can reach; a flow's temporary in-process server is not visible to them)."""
    from prefect.server.api.server import SubprocessASGIServer

    server = SubprocessASGIServer()
    server.start(timeout=120)
    monkeypatch.setenv("PREFECT_API_URL", server.api_url)
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    yield server.api_url
    server.stop()


@pytest.mark.slow
@pytest.mark.flow
def test_world_flow_thread_pool_and_dask_with_mlflow(tmp_path, prefect_server):
    from distributed import LocalCluster
    from mlflow.tracking import MlflowClient

    env = {**os.environ, "PYTHONPATH": str(REPO), "WEATHERALIGN_PIPELINE_ID": "test-pipeline",
           "PREFECT_LOGGING_LEVEL": "WARNING", "PREFECT_API_URL": prefect_server}
    run = _run_world(tmp_path, [], env)
    assert run.returncode == 0, run.stderr[-3000:]
    metrics = json.loads((tmp_path / "reports" / "world" / "details.json").read_text())
    assert metrics["num_scenes"] == 2 and metrics["num_samples"] == 4 and metrics["num_sweeps"] == 4
    assert metrics["samples_rendered_this_run"] == 4 and metrics["seconds_per_sample"] > 0
    assert metrics["dataroot"] == "data/world" and sum(metrics["class_counts"].values()) == metrics["num_annotations"]
    headline = json.loads((tmp_path / "reports" / "world" / "metrics.json").read_text())  # what DVC compares
    assert headline == {k: metrics[k] for k in ("num_samples", "num_annotations")}
    assert (tmp_path / "reports" / "world" / "sample_bev.png").stat().st_size > 20_000
    assert (tmp_path / "reports" / "world" / "sample_cameras.jpg").stat().st_size > 20_000
    tables = sorted(p.name for p in (tmp_path / "data" / "world" / "v1.0-mini").glob("*.json"))
    assert len(tables) == 14  # 13 nuScenes tables + splits.json
    manifest = json.loads((tmp_path / "data" / "manifests" / "world.json").read_text())
    assert manifest["dataroot"] == "data/world" and manifest["scenes"] == ["scene-0061", "scene-0103"]
    assert manifest["sensors"]["lidar"]["columns_per_ring"] == 1085 and len(manifest["sensors"]["cameras"]) == 6
    assert "samples_rendered_this_run" not in json.dumps(manifest)  # no run-time counters in the handoff

    # the particles stage on the world just written
    run = _run_world(tmp_path, ["--set", "particles.validation_regions=2"], env, stage="particles")
    assert run.returncode == 0, run.stderr[-3000:]
    particles = json.loads((tmp_path / "reports" / "particles" / "details.json").read_text())
    fields = json.loads((tmp_path / "data" / "particles" / "fields.json").read_text())
    assert set(fields) == {"snow", "rain"} and [f["scene"] for f in fields["snow"]] == ["scene-0061", "scene-0103"]
    for condition in ("snow", "rain"):
        assert particles[condition]["max_abs_z_score"] < 5 and particles[condition]["min_size_chi2_pvalue"] > 1e-4
        assert particles[condition]["expected_particles_lidar_volume"] > 1e6
    for figure in ("size_histograms.png", "side_view_snow.png", "side_view_rain.png"):
        assert (tmp_path / "reports" / "particles" / figure).stat().st_size > 20_000

    # the same stage on an existing Dask cluster: everything already rendered is picked up, not redone
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, protocol="tcp", host="127.0.0.1",
                      dashboard_address=None) as cluster:
        run = _run_world(tmp_path, ["--set", f"run.dask_address={cluster.scheduler_address}",
                                    "--set", "world.samples_per_scene=3"], env)
    assert run.returncode == 0, run.stderr[-3000:]
    metrics = json.loads((tmp_path / "reports" / "world" / "details.json").read_text())
    assert metrics["num_samples"] == 6 and metrics["samples_rendered_this_run"] == 6  # config changed: all re-rendered

    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("weatheralign")
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if r.data.tags.get("pipeline_id") == "test-pipeline"
               and r.data.tags.get("kind") == "pipeline"]
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id]
    assert len(parents) == 1 and len(children) == 3
    assert sorted(c.data.tags["stage"] for c in children) == ["particles", "world", "world"]
    child = next(c for c in children if c.data.tags["stage"] == "world")
    assert child.data.tags["prefect.flow_run_id"] and child.data.tags["pipeline_id"] == "test-pipeline"
    assert {k: child.data.tags[k] for k in ("kind", "weather", "alignment", "severity", "model")} == {
        "kind": "stage", "weather": "none", "alignment": "none", "severity": "none", "model": "none"}
    assert len(child.data.tags["git_commit"]) == 40 or child.data.tags["git_commit"] == "none"
    # the particles stage: one child per kind, the same metric names in both, the kind a tag
    particles_run = next(c for c in children if c.data.tags["stage"] == "particles")
    kinds = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == particles_run.info.run_id]
    assert {r.data.tags["weather"]: r.data.tags["severity"] for r in kinds} == {"snow": "2 mm/h", "rain": "50 mm/h"}
    assert kinds[0].data.metrics.keys() == kinds[1].data.metrics.keys()
    assert "number_density_per_m3" in kinds[0].data.metrics
    assert not any("snow" in k or "rain" in k for k in particles_run.data.metrics)
    assert child.data.metrics["num_samples"] in (4, 6) and "world.lidar.firings_per_ring" in child.data.params
    artifacts = {a.path for a in client.list_artifacts(child.info.run_id, "figures")}
    assert artifacts == {"figures/sample_bev.png", "figures/sample_cameras.jpg"}


def test_real_nuscenes_dataroot_is_checked_in_place(tiny_world):
    """world.source=nuscenes: the stage reads a given dataroot (here the tiny world standing in for nuScenes-mini)
    and reports it without writing into it."""
    from flows.world import _summarise_real
    from weatheralign.config import params_from_dict

    before = sorted(p.stat().st_mtime_ns for p in tiny_world.dataroot.rglob("*") if p.is_file())
    params = params_from_dict({"world": {"source": "nuscenes", "nuscenes_dataroot": str(tiny_world.dataroot),
                                         "version": tiny_world.params.world.version}})
    root, summary = _summarise_real(params)
    assert root == tiny_world.dataroot
    for key in ("num_scenes", "num_samples", "num_sweeps", "num_annotations", "class_counts"):
        assert summary[key] == tiny_world.summary[key]
    # its sensors are estimated from the scans (no params describe a real LiDAR) and agree with the truth
    from weatheralign.data.nuscenes import open_nuscenes
    from weatheralign.sensors import dataset_sensors, lidar_model_from_params

    nusc = open_nuscenes(root, params.world.version)
    rig = dataset_sensors(params.world, nusc)
    truth = lidar_model_from_params(tiny_world.params.world.lidar)
    assert rig.lidar.origin == "estimated" and rig.lidar.num_rings == 32 and not rig.lidar.firing_columns_stored
    assert abs(rig.lidar.columns_per_ring - truth.columns_per_ring) <= 11 and len(rig.cameras) == 6
    over = dataset_sensors(params_from_dict({"world": {**params.world.model_dump(mode="json"),
                                                       "sensor_overrides": {"divergence_rad": 0.002}}}).world, nusc)
    assert over.lidar.divergence_rad == 0.002
    assert sorted(p.stat().st_mtime_ns for p in tiny_world.dataroot.rglob("*") if p.is_file()) == before


def test_dvc_pipeline_definition_parses():
    dvc = Path(sys.executable).with_name("dvc")
    out = subprocess.run([str(dvc), "stage", "list"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == "world"
