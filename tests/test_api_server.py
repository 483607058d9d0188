"""No orphaned Prefect servers: a stage's API server dies with the stage however the stage ends (SIGTERM, SIGKILL),
and `python -m flows.api_server <cmd>` gives a whole `dvc repro` one server."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil
import pytest

from .conftest import REPO, write_params_file


def _wait_for_server(pidfile: Path, owner: subprocess.Popen | None = None, timeout: float = 120.0) -> int:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if owner is not None and owner.poll() is not None:
            raise AssertionError(f"the stage ended before its server came up: {owner.stderr.read()[-2000:]}")
        if pidfile.is_file() and pidfile.read_text().strip():
            pid = int(pidfile.read_text())
            conns = [c for c in psutil.Process(pid).net_connections() if c.status == "LISTEN"] \
                if psutil.pid_exists(pid) else []
            if conns:
                return pid
        time.sleep(0.3)
    raise AssertionError("the stage's Prefect server did not come up")


def _gone(pid: int, timeout: float = 20.0) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
            return True
        time.sleep(0.2)
    return False


def _env(tmp_path: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    return {**env, "PYTHONPATH": str(REPO), "PREFECT_HOME": str(tmp_path / "prefect"),
            "WEATHERALIGN_SERVER_PIDFILE": str(tmp_path / "server.pid"), "PREFECT_LOGGING_LEVEL": "WARNING"}


@pytest.mark.slow
@pytest.mark.flow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_a_killed_stage_leaves_no_server(tmp_path: Path, sig: signal.Signals) -> None:
    params = write_params_file(tmp_path / "params.yaml", {
        "paths": {"data": str(tmp_path / "data"), "reports": str(tmp_path / "reports")},
        "tracking": {"enabled": False}, "run": {"show_progress": False},
        "world": {"num_train_scenes": 2, "num_val_scenes": 1, "samples_per_scene": 4, "sweeps_per_sample": 0}})
    stage = subprocess.Popen([sys.executable, "-m", "flows.world", "--params", str(params)], cwd=REPO,
                             env=_env(tmp_path), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        server = _wait_for_server(tmp_path / "server.pid", stage)
        stage.send_signal(sig)
        assert stage.wait(timeout=60) != 0
        assert _gone(server), f"the Prefect server {server} outlived its stage ({sig.name})"
    finally:
        if stage.poll() is None:
            stage.kill()


@pytest.mark.flow
def test_one_server_for_a_whole_command(tmp_path: Path) -> None:
    probe = ("import os, httpx; u = os.environ['PREFECT_API_URL']; "
             "print(u, httpx.get(u + '/health').status_code)")
    run = subprocess.run([sys.executable, "-m", "flows.api_server", sys.executable, "-c", probe], cwd=REPO,
                         env=_env(tmp_path), capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    url, status = run.stdout.split()
    assert url.startswith("http://127.0.0.1:") and status == "200"
    assert _gone(int((tmp_path / "server.pid").read_text()))
    with pytest.raises(httpx.HTTPError):
        httpx.get(url + "/health", timeout=2.0)


@pytest.mark.slow
@pytest.mark.flow
def test_one_dask_cluster_for_a_whole_command(tmp_path: Path) -> None:
    """``--dask``: the command gets the scheduler address of one local cluster of ``run.max_workers`` processes whose
    workers report to the run's Prefect server and stay the same from one client to the next (one per stage), and the
    cluster's processes end with the command; ``run.dask_address`` in params means no cluster of its own."""
    params = write_params_file(tmp_path / "params.yaml", {"run": {"max_workers": 2}})
    probe = ("import os\nfrom distributed import Client\n"
             "a = os.environ['WEATHERALIGN_DASK_ADDRESS']\n"
             "def ask():\n"
             "    with Client(a) as c:\n"
             "        info = c.run(lambda: (os.getpid(), os.environ.get('PREFECT_API_URL')))\n"
             "        return sorted(info.values())\n"
             "first, second = ask(), ask()\n"
             "assert first == second, (first, second)\n"
             "print(len(first), first[0][1] == os.environ['PREFECT_API_URL'], *[p for p, _ in first])\n")
    env = _env(tmp_path)
    run = subprocess.run([sys.executable, "-m", "flows.api_server", "--dask", sys.executable, "-c", probe],
                         cwd=tmp_path, env={**env, "PYTHONPATH": f"{REPO}{os.pathsep}{REPO / 'src'}"},
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    n, same_server, *pids = run.stdout.split()
    assert n == "2" and same_server == "True"
    assert all(_gone(int(p)) for p in pids), "a worker process outlived the command"
    write_params_file(params, {"run": {"dask_address": "tcp://127.0.0.1:1"}})
    run = subprocess.run([sys.executable, "-m", "flows.api_server", "--dask", sys.executable, "-c",
                          "import os; print(os.environ.get('WEATHERALIGN_DASK_ADDRESS'))"], cwd=tmp_path,
                         env={**env, "PYTHONPATH": f"{REPO}{os.pathsep}{REPO / 'src'}"}, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0 and run.stdout.split() == ["None"], run.stderr[-2000:]
