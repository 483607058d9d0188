"""The Prefect pipeline flow: dvc.yaml's stages in dependency order, stage selection, and a served deployment that a
user (here: the API, as the UI's Run button does) starts and that completes with its outputs."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from flows.pipeline import StageRun, select, stage_runs, up_to_date
from weatheralign.conditions import ALIGNMENTS, CONDITIONS

REPO = Path(__file__).resolve().parents[1]


def test_stage_runs_are_dvc_yamls_stages_with_the_matrix_expanded():
    runs = stage_runs()
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    simulate = [r for r in runs if r.base == "simulate"]
    assert [r.name for r in simulate] == [f"simulate@{c}-{a}" for c in CONDITIONS for a in ALIGNMENTS]
    assert simulate[0].argv == ("--set", f"simulate.condition={list(CONDITIONS)[0]}", "--set",
                                f"simulate.aligned={ALIGNMENTS[0]}")
    assert list(dict.fromkeys(r.base for r in runs)) == list(stages)
    assert all(r.module == f"flows.{r.base}" for r in runs)


def _paths(entries: list) -> set[str]:
    return {next(iter(e)) if isinstance(e, dict) else e for e in entries}


def _filled(spec: dict, name: str, keys: tuple[str, ...]) -> set[str]:
    """The paths under ``keys`` of a stage (``deps``: the data ones) with its matrix entry's ``${item.x}`` filled."""
    item = dict(zip(spec["matrix"], name.split("@")[1].split("-", 1))) if "@" in name else {}
    return {re.sub(r"\$\{item\.(\w+)\}", lambda m: item[m.group(1)], p)
            for key in keys for p in _paths(spec.get(key, [])) if key != "deps" or p.startswith("${paths.")}


def test_every_stage_runs_after_the_stages_that_make_its_inputs():
    """An input is made once the stage writing it (or a folder above it) ran; a folder input, once every stage
    writing inside it ran."""
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    runs = stage_runs()
    written = {run.name: _filled(stages[run.base], run.name, ("outs", "metrics", "plots")) for run in runs}
    every_output = set().union(*written.values())
    made: set[str] = set()
    for run in runs:
        inputs = _filled(stages[run.base], run.name, ("deps",))
        missing = {d for d in inputs
                   if not any(d == m or d.startswith(m + "/") for m in made)
                   and not ((inside := {o for o in every_output if o.startswith(d + "/")}) and inside <= made)}
        assert not missing, f"{run.name} runs before the stage that makes {sorted(missing)}"
        made |= written[run.name]


def test_select_by_stage_or_matrix_entry_keeps_the_pipeline_order():
    runs = stage_runs()
    picked = select(runs, ["simulate@snow-aligned", "world"])
    assert [r.name for r in picked] == ["world", "simulate@snow-aligned"]
    assert len(select(runs, ["simulate"])) == len(CONDITIONS) * len(ALIGNMENTS)
    assert select(runs, None) == runs
    with pytest.raises(ValueError, match=r"unknown stage\(s\) \['simulat'\]"):
        select(runs, ["simulat"])
    assert StageRun("simulate@snow-aligned", "flows.simulate", ()).base == "simulate"


def test_up_to_date_follows_dvc_status(tmp_path: Path):
    """A stage is up to date after it ran and until its input changes; a stage dvc cannot answer for runs."""
    dvc = [str(Path(sys.executable).parent / "dvc")]
    (tmp_path / "in.txt").write_text("1")
    (tmp_path / "dvc.yaml").write_text("stages:\n  copy:\n    cmd: cp in.txt out.txt\n    deps: [in.txt]\n"
                                       "    outs: [out.txt]\n")
    for args in (["init", "--no-scm", "-q"], ["repro", "-q"]):
        subprocess.run(dvc + args, cwd=tmp_path, check=True, capture_output=True)
    assert up_to_date("copy", tmp_path) is True
    (tmp_path / "in.txt").write_text("2")
    assert up_to_date("copy", tmp_path) is False
    assert up_to_date("no-such-stage", tmp_path) is False


@pytest.fixture()
def api_url(tmp_path: Path):
    from flows.prefect_server import ApiServer

    server = ApiServer()
    env = {"PREFECT_HOME": str(tmp_path / "prefect")}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield server.start()
    finally:
        server.stop()
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.mark.slow
def test_a_served_stage_deployment_runs_from_the_api_and_completes(tmp_path: Path, api_url: str):
    """What the UI's Run button does: a run of ``pipeline/world`` created through the API, picked up by the served
    process, completes with the stage's outputs and the pipeline's artifact."""
    from prefect.client.orchestration import get_client
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    env = {**os.environ, "PREFECT_API_URL": api_url, "PREFECT_LOGGING_LEVEL": "WARNING"}
    serving = subprocess.Popen([sys.executable, "-m", "flows.serve"], cwd=REPO, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    data = tmp_path / "data"
    overrides = [f"paths.data={data}", f"paths.reports={tmp_path / 'reports'}", "tracking.enabled=false",
                 "world.num_train_scenes=1", "world.num_val_scenes=1", "world.samples_per_scene=2",
                 "world.sweeps_per_sample=1", "world.camera.image_scale=0.1"]
    try:
        with temporary_settings(updates={PREFECT_API_URL: api_url}):
            expected = {"all", *(r.base for r in stage_runs())}
            deadline = time.monotonic() + 120
            names: list[str] = []
            while time.monotonic() < deadline and not expected <= set(names):
                assert serving.poll() is None, serving.stdout.read()
                with get_client(sync_client=True) as client:
                    names = [d.name for d in client.read_deployments()]
                time.sleep(1.0)
            assert expected <= set(names) and {"world", "simulate", "detect"} <= expected
            run = run_deployment("pipeline/world", parameters={"overrides": overrides, "record_in_dvc": False},
                                 timeout=600, poll_interval=2)
            assert run.state.is_completed(), run.state
            with get_client(sync_client=True) as client:
                children = client.read_flow_runs()
                artifacts = client.read_artifacts()
        assert any(r.parent_task_run_id is not None and r.name != run.name for r in children)  # world, as a subflow
        assert any(a.key == "pipeline-stages" and "| world |" in (a.data or "") for a in artifacts)
        assert (data / "manifests" / "world.json").is_file()
    finally:
        serving.send_signal(signal.SIGINT)
        try:
            serving.wait(timeout=30)
        except subprocess.TimeoutExpired:
            serving.kill()


def test_serve_without_a_server_says_how_to_start_one():
    env = {**os.environ, "PREFECT_API_URL": "http://127.0.0.1:9/api"}
    proc = subprocess.run([sys.executable, "-m", "flows.serve"], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert "no Prefect API answers at http://127.0.0.1:9/api" in proc.stderr and "make prefect-ui" in proc.stderr
