"""The ``weatheralign`` command: run the pipeline's stages, score results files, open the UIs and check the machine,
on a weatheralign project directory found the way ``dvc`` finds its repository (the current directory or the nearest
parent holding ``dvc.yaml``, ``params.yaml`` and ``flows/``; or ``--project``).

The command drives the project's own entry points as subprocesses in the project directory (``python -m
flows.<...>``, ``dvc``, ``prefect``, ``mlflow``), with the environment ``make`` sets up (the project's Prefect home and
MLflow store), so it imports none of the pipeline's tools itself and works from a plain library install too (then only
``doctor`` and ``--help`` are useful).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

PROJECT_MARKERS: tuple[str, ...] = ("dvc.yaml", "params.yaml", "flows")
DEFAULT_RUN_DISK_GB = 28.0
"""Free disk the default pipeline needs under ``paths.data`` (the world, the reference, ten weather copies)."""


class ProjectNotFound(RuntimeError):
    """No weatheralign project at or above the given directory."""


def find_project(start: Path) -> Path:
    """The nearest directory at or above ``start`` holding every one of `PROJECT_MARKERS`."""
    start = start.resolve()
    for folder in (start, *start.parents):
        if all((folder / name).exists() for name in PROJECT_MARKERS):
            return folder
    raise ProjectNotFound(f"{start}: no weatheralign project here or above (a folder with "
                          f"{', '.join(PROJECT_MARKERS)}); cd into one or pass --project DIR")


def project_env(project: Path) -> dict[str, str]:
    """The environment of the project's commands, as the Makefile sets it: the project's Prefect home and MLflow
    store (unless already set), Prefect's console quiet (its runs' logs still reach the API), this interpreter's
    scripts first on PATH."""
    env = dict(os.environ)
    env.setdefault("PREFECT_HOME", str(project / ".prefect"))
    env.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    env.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")
    env.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "WARNING")
    env.setdefault("MLFLOW_TRACKING_URI", f"sqlite:///{project / 'mlflow.db'}")
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def run_command(stages: list[str], overrides: list[str], params: str | None) -> list[str]:
    """The command line of ``weatheralign run``: ``dvc repro`` (what is out of date, under one Prefect server and Dask
    cluster) when no stage, override or params file is given, else the pipeline flow on those stages."""
    if not stages and not overrides and params is None:
        return [sys.executable, "-m", "flows.api_server", "--dask", "dvc", "repro"]
    cmd = [sys.executable, "-m", "flows.pipeline"]
    if stages:
        cmd += ["--stages", *stages]
    if params is not None:
        cmd += ["--params", params]
    for override in overrides:
        cmd += ["--set", override]
    return cmd


@dataclass(frozen=True)
class Check:
    """One line of ``weatheralign doctor``: what was checked, whether it passed, what was found or what to do."""

    name: str
    ok: bool
    detail: str


def _module_check(name: str, module: str, hint: str) -> Check:
    try:
        mod = importlib.import_module(module)
    except Exception as err:  # noqa: BLE001 -- any import failure is the finding (open3d raises OSError)
        return Check(name, False, f"{type(err).__name__}: {err}; {hint}")
    return Check(name, True, str(getattr(mod, "__version__", "installed")))


def free_disk_check(folder: Path, need_gb: float) -> Check:
    """Free space on the file system of ``folder`` (or its nearest existing parent) against ``need_gb``."""
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    free_gb = shutil.disk_usage(existing).free / 1e9
    return Check("free disk", free_gb >= need_gb, f"{free_gb:.1f} GB free at {existing}, the default run needs "
                 f"about {need_gb:.0f} GB")


def prefect_server_check(env: dict[str, str]) -> Check:
    """A Prefect server at ``PREFECT_API_URL`` answers its health check (none set: each run starts its own)."""
    url = env.get("PREFECT_API_URL")
    if not url:
        return Check("Prefect server", True, "PREFECT_API_URL unset: each run starts and stops its own server")
    try:
        with urllib.request.urlopen(url.rstrip("/") + "/health", timeout=5) as response:
            return Check("Prefect server", response.status == 200, f"{url} answered {response.status}")
    except OSError as err:
        return Check("Prefect server", False, f"{url} unreachable ({err}); start it (weatheralign ui) or unset "
                     "PREFECT_API_URL")


def doctor_checks(project: Path | None) -> list[Check]:
    """Everything a run needs: Python, torch, open3d (with libusb), the nuScenes devkit, the pipeline's tools, free
    disk for the default run, the Prefect server."""
    checks = [Check("python", sys.version_info[:2] == (3, 11), sys.version.split()[0] + " (3.11 expected)"),
              _module_check("torch", "torch", "run `make setup`"),
              _module_check("open3d", "open3d", "open3d needs Debian's libusb-1.0-0 (apt-get install libusb-1.0-0)"),
              _module_check("nuscenes-devkit", "nuscenes", "run `make setup`")]
    for tool in ("prefect", "mlflow", "dvc", "distributed"):
        checks.append(_module_check(tool, tool, "install the pipeline extra: pip install -e '.[pipeline]'"))
    try:
        import torch

        device = "cuda available" if torch.cuda.is_available() else "CPU only (detect.device: cpu)"
        checks.append(Check("torch device", True, device))
    except ImportError:
        pass
    if project is not None:
        data = project / "data"
        checks.append(free_disk_check(data, DEFAULT_RUN_DISK_GB))
        checks.append(prefect_server_check(project_env(project)))
    return checks


def _doctor(project: Path | None) -> int:
    checks = doctor_checks(project)
    width = max(len(c.name) for c in checks)
    for c in checks:
        print(f"{'ok  ' if c.ok else 'FAIL'} {c.name:<{width}}  {c.detail}")
    if project is None:
        print("(no project found here: the disk and server checks need one, see --project)")
    return 0 if all(c.ok for c in checks) else 1


def mlflow_runs_url(base: str, experiment: str, timeout_s: float = 90.0) -> str:
    """The address that opens ``experiment`` on its runs table in the MLflow UI at ``base`` (asked through the
    server's REST API once it answers); ``base`` itself when the experiment is not there or the server does not
    answer within ``timeout_s``. The address names the model-training workflow: MLflow 3's UI otherwise shows a
    browser that never chose one the GenAI sidebar, whatever the experiment's kind (that choice lives in the
    browser's local storage; mlflow/mlflow#24498)."""
    query = urllib.parse.urlencode({"experiment_name": experiment})
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"{base}/api/2.0/mlflow/experiments/get-by-name?{query}", timeout=5) as r:
                experiment_id = json.load(r)["experiment"]["experiment_id"]
            return f"{base}/#/experiments/{experiment_id}/runs?workflowType=machine_learning"
        except urllib.error.HTTPError:
            return base  # the server answers: no such experiment
        except OSError:
            time.sleep(1.0)  # not up yet
    return base


def tracked_experiment(project: Path) -> str:
    """The MLflow experiment of the project's params (``tracking.experiment``); the default name when the params do
    not load (the stages report why; the UIs still start)."""
    from weatheralign.config import ConfigError, TrackingConfig, load_params

    try:
        return load_params(project / "params.yaml").tracking.experiment
    except ConfigError:
        return TrackingConfig().experiment


def _ui(project: Path, prefect_port: int, mlflow_port: int) -> int:
    """The Prefect UI and the MLflow UI on the project's stores, until Ctrl-C (or SIGTERM); both stop together."""
    def _stop(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    # explicit: a process started in the background by a shell inherits SIGINT ignored
    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    env = project_env(project)
    procs = [subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port",
                               str(prefect_port)], cwd=project, env=env),
             subprocess.Popen([sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", env["MLFLOW_TRACKING_URI"],
                               "--host", "127.0.0.1", "--port", str(mlflow_port)], cwd=project, env=env)]
    try:
        mlflow_url = mlflow_runs_url(f"http://127.0.0.1:{mlflow_port}", tracked_experiment(project))
        print(f"Prefect UI: http://127.0.0.1:{prefect_port}   MLflow UI: {mlflow_url}   (Ctrl-C stops both)")
        while all(p.poll() is None for p in procs):
            try:
                procs[0].wait(timeout=1)
            except subprocess.TimeoutExpired:
                pass
    except KeyboardInterrupt:
        pass
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="weatheralign", description="Aligned fog, snow and rain for LiDAR + camera data in the nuScenes format.",
        epilog="Run inside a weatheralign project (or pass --project). `weatheralign <command> --help` for details.")
    parser.add_argument("--project", type=Path, default=None,
                        help="the project directory (default: the current directory or the nearest parent with "
                             "dvc.yaml, params.yaml and flows/)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="command")
    run = sub.add_parser("run", help="run stages (none given: `dvc repro` of everything out of date)",
                         description="Run pipeline stages. No stage, --set or --params: `dvc repro` (what is out of "
                                     "date). Otherwise the pipeline flow on the stages given (all if none).")
    run.add_argument("stages", nargs="*", help="stages, e.g. world simulate or simulate@snow-aligned")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a params key for this run (repeatable), e.g. world.num_train_scenes=2")
    run.add_argument("--params", default=None, help="params YAML file (default: params.yaml)")
    score = sub.add_parser("score", help="score nuScenes results files on a dataroot (python -m flows.score)",
                           add_help=False)
    score.add_argument("args", nargs=argparse.REMAINDER)
    ui = sub.add_parser("ui", help="the Prefect UI and the MLflow UI on the project's stores")
    ui.add_argument("--prefect-port", type=int, default=4200)
    ui.add_argument("--mlflow-port", type=int, default=5000)
    sub.add_parser("doctor", help="check torch, open3d, the pipeline tools, free disk and the Prefect server")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        project = find_project(args.project or Path.cwd())
    except ProjectNotFound as err:
        if args.command == "doctor":
            return _doctor(None)
        print(f"weatheralign: {err}", file=sys.stderr)
        return 2
    if args.command == "doctor":
        return _doctor(project)
    if args.command == "ui":
        return _ui(project, args.prefect_port, args.mlflow_port)
    if args.command == "score":
        cmd = [sys.executable, "-m", "flows.score", *args.args]
    else:
        cmd = run_command(args.stages, args.overrides, args.params)
    try:
        return subprocess.run(cmd, cwd=project, env=project_env(project)).returncode
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
