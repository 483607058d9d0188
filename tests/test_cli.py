"""The ``weatheralign`` command: project discovery, the commands it runs, ``doctor``'s checks, a real stage run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from weatheralign import cli

from .conftest import HANG_GUARD_S

REPO = Path(__file__).resolve().parents[1]
SCRIPT = Path(sys.executable).parent / "weatheralign"


def _fake_project(root: Path) -> Path:
    for name in ("dvc.yaml", "params.yaml"):
        (root / name).write_text("")
    (root / "flows").mkdir()
    return root


def test_project_is_found_from_any_folder_below_it(tmp_path: Path) -> None:
    (tmp_path / "proj").mkdir()
    project = _fake_project(tmp_path / "proj")
    nested = project / "data" / "simulate" / "snow-aligned"
    nested.mkdir(parents=True)
    assert cli.find_project(nested) == project.resolve()
    assert cli.find_project(project) == project.resolve()
    assert cli.find_project(REPO / "src" / "weatheralign") == REPO


def test_no_project_is_one_clear_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "dvc.yaml").write_text("")  # a DVC repository alone is not a weatheralign project
    with pytest.raises(cli.ProjectNotFound, match="no weatheralign project here or above"):
        cli.find_project(tmp_path)
    assert cli.main(["--project", str(tmp_path), "run", "world"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(tmp_path) in err and "--project" in err


def test_run_is_dvc_repro_or_the_pipeline_flow_on_the_stages_given() -> None:
    assert cli.run_command([], [], None)[1:] == ["-m", "flows.api_server", "--dask", "dvc", "repro"]
    assert cli.run_command(["world", "simulate@snow-aligned"], ["world.seed=7"], None)[1:] == [
        "-m", "flows.pipeline", "--stages", "world", "simulate@snow-aligned", "--set", "world.seed=7"]
    assert cli.run_command([], ["world.seed=7"], "my.yaml")[1:] == [
        "-m", "flows.pipeline", "--params", "my.yaml", "--set", "world.seed=7"]


def test_project_env_points_at_the_projects_stores(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.delenv("PREFECT_HOME", raising=False)
    env = cli.project_env(tmp_path)
    assert env["MLFLOW_TRACKING_URI"] == f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert env["PREFECT_HOME"] == str(tmp_path / ".prefect")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:////elsewhere.db")  # a user's own store wins
    assert cli.project_env(tmp_path)["MLFLOW_TRACKING_URI"] == "sqlite:////elsewhere.db"


def test_doctor_checks_fail_with_what_to_do(tmp_path: Path) -> None:
    assert cli.free_disk_check(tmp_path / "not" / "yet", 0.0).ok
    short = cli.free_disk_check(tmp_path, 1e9)
    assert not short.ok and "GB free" in short.detail
    down = cli.prefect_server_check({"PREFECT_API_URL": "http://127.0.0.1:9/api"})
    assert not down.ok and "unreachable" in down.detail and "weatheralign ui" in down.detail
    assert cli.prefect_server_check({}).ok
    broken = cli._module_check("missing", "weatheralign_no_such_module", "install it")
    assert not broken.ok and "ModuleNotFoundError" in broken.detail and "install it" in broken.detail


def test_help_works_from_any_directory(tmp_path: Path) -> None:
    if not SCRIPT.exists():
        pytest.skip("the console script is installed by `pip install -e .` (make setup)")
    for args in (["--help"], ["run", "--help"], ["doctor", "--help"]):
        done = subprocess.run([str(SCRIPT), *args], cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0 and "usage: weatheralign" in done.stdout, done.stderr


@pytest.mark.slow
@pytest.mark.flow
def test_weatheralign_run_world_with_overrides_runs_the_stage(tmp_path: Path) -> None:
    """``weatheralign run world --set ...`` from a folder inside a project copy renders a tiny world there."""
    from .test_stage_contracts import _project_repo

    if not SCRIPT.exists():
        pytest.skip("the console script is installed by `pip install -e .` (make setup)")
    repo = tmp_path / "repo"
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    _project_repo(repo, params)
    (repo / "reports").mkdir()
    sets = ["world.num_train_scenes=1", "world.num_val_scenes=1", "world.samples_per_scene=2",
            "world.sweeps_per_sample=0", "world.camera.image_scale=0.1"]
    cmd = [str(SCRIPT), "run", "world"] + [a for s in sets for a in ("--set", s)]
    done = subprocess.run(cmd, cwd=repo / "reports", capture_output=True, text=True, timeout=HANG_GUARD_S,
                          env={**cli.project_env(repo), "PYTHONPATH": f"{repo / 'src'}:{repo}"})
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    manifest = json.loads((repo / "data" / "manifests" / "world.json").read_text())
    assert len(manifest["scenes"]) == 2
    assert json.loads((repo / "reports" / "world" / "metrics.json").read_text())["num_samples"] == 4


@pytest.mark.slow
def test_ui_serves_both_uis_and_sigterm_stops_every_process(tmp_path: Path) -> None:
    """``weatheralign ui`` answers on both ports; SIGTERM (as Ctrl-C) stops the servers and their own children."""
    import signal
    import socket
    import time
    import urllib.request

    if not SCRIPT.exists():
        pytest.skip("the console script is installed by `pip install -e .` (make setup)")
    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    project = _fake_project(tmp_path)
    ui = subprocess.Popen([str(SCRIPT), "ui", "--prefect-port", str(ports[0]), "--mlflow-port", str(ports[1])],
                          cwd=project, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    urls = [f"http://127.0.0.1:{ports[0]}/api/health", f"http://127.0.0.1:{ports[1]}/"]
    up: set[str] = set()
    deadline = time.time() + 240
    while len(up) < 2 and time.time() < deadline and ui.poll() is None:
        for url in set(urls) - up:
            try:
                with urllib.request.urlopen(url, timeout=2) as response:
                    if response.status == 200:
                        up.add(url)
            except OSError:
                pass
        time.sleep(1)
    ui.send_signal(signal.SIGTERM)
    ui.wait(timeout=60)
    assert up == set(urls)
    time.sleep(2)
    left = [cmd for cmd in map(_cmdline, Path("/proc").glob("[0-9]*")) if any(str(port) in cmd for port in ports)]
    assert not left, left


def _cmdline(proc: Path) -> str:
    """A process's command line ('' once it has gone)."""
    try:
        return (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def test_mlflow_link_opens_the_experiment_on_its_runs(tmp_path: Path) -> None:
    """MLflow 3's UI opens an experiment on its GenAI overview unless the address names its runs table: the address
    comes from the server's REST API (a stub here); the UI's root when the experiment is not there or no server
    answers."""
    import http.server
    import json
    import threading

    class Stub(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (the http.server API)
            if self.path == "/api/2.0/mlflow/experiments/get-by-name?experiment_name=weatheralign":
                body = json.dumps({"experiment": {"experiment_id": "7", "name": "weatheralign"}}).encode()
                self.send_response(200)
                self.end_headers()
                self.wfile.write(body)
            else:
                self.send_error(404)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Stub)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        assert cli.mlflow_runs_url(base, "weatheralign") == f"{base}/#/experiments/7/runs?workflowType=machine_learning"
        assert cli.mlflow_runs_url(base, "another") == base
    finally:
        server.shutdown()
    assert cli.mlflow_runs_url(base, "weatheralign", timeout_s=1.5) == base  # nobody answers
    (tmp_path / "project").mkdir()
    assert cli.tracked_experiment(_fake_project(tmp_path / "project")) == "weatheralign"  # empty params: the default
    assert cli.tracked_experiment(REPO) == "weatheralign"
