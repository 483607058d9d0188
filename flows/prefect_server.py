"""A Prefect API server that cannot outlive its owner.

Without ``PREFECT_API_URL`` Prefect starts a temporary server per process and stops it at interpreter exit, which a
SIGTERM skips and a SIGKILL cannot run: the server (uvicorn, its memory, an open port) then lives on under PID 1.
`prefect_api()` starts the server itself instead, with the kernel's parent-death signal set (Linux
``PR_SET_PDEATHSIG``), so it is terminated however its owner ends; `install_signal_handlers` turns SIGTERM / SIGHUP
into a normal exit so that cleanup code runs. The server binds to 127.0.0.1. `flows.common.run_stage` (every stage)
and `flows.api_server` (one server for a whole command) use it.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import httpx

PR_SET_PDEATHSIG = 1
STARTUP_TIMEOUT_S = float(os.environ.get("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90"))


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """In the server process: receive SIGTERM when the process that started it dies (Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() == 1:  # the owner died before the signal was armed
        os._exit(0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ApiServer:
    """One Prefect API server process on 127.0.0.1 owned by this process (`start` / `stop`)."""

    def __init__(self) -> None:
        self.port = _free_port()
        self.process: subprocess.Popen | None = None

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    def start(self, timeout: float = STARTUP_TIMEOUT_S) -> str:
        """Start the server and wait until its health endpoint answers; returns the API URL.

        Raises:
            RuntimeError: the server exited or did not answer within ``timeout`` seconds.
        """
        env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
        env.pop("PREFECT_API_URL", None)
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "prefect.server.api.server:create_app", "--host",
             "127.0.0.1", "--port", str(self.port), "--log-level", "error", "--lifespan", "on"],
            env=env, preexec_fn=_die_with_parent, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        if os.environ.get("WEATHERALIGN_SERVER_PIDFILE"):  # for tests that check nothing outlives its owner
            with open(os.environ["WEATHERALIGN_SERVER_PIDFILE"], "w") as f:
                f.write(str(self.process.pid))
        t_end = time.monotonic() + timeout
        with httpx.Client() as client:
            while time.monotonic() < t_end:
                if self.process.poll() is not None:
                    err = self.process.stderr.read().decode(errors="replace")[-2000:] if self.process.stderr else ""
                    raise RuntimeError(f"the Prefect API server exited with code {self.process.returncode}: {err}")
                with contextlib.suppress(httpx.HTTPError):
                    if client.get(f"{self.api_url}/health", timeout=2.0).status_code == 200:
                        return self.api_url
                time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"the Prefect API server did not answer within {timeout:.0f} s (raise "
                           f"PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS)")

    def stop(self) -> None:
        """Terminate the server (kill it after 10 s)."""
        proc, self.process = self.process, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def install_signal_handlers() -> None:
    """SIGTERM and SIGHUP end the process like Ctrl-C's SystemExit does, so ``finally`` blocks and context managers
    (the server's `stop`) run; SIGKILL is left to the server's parent-death signal."""
    def _exit(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _exit)


@contextlib.contextmanager
def prefect_api() -> Iterator[str | None]:
    """The API URL to use: ``PREFECT_API_URL`` when set (a user's server, or the shared server of `main`), else a
    server of our own, stopped when the process ends, however it ends."""
    if os.environ.get("PREFECT_API_URL"):
        yield None
        return
    server = ApiServer()
    url = server.start()
    # stopped at interpreter exit, after Prefect's log worker has sent the run's last lines (atexit runs in reverse
    # order of registration, and Prefect registers its drain later, at the first log); a SIGTERM exits through
    # SystemExit (`install_signal_handlers`), a SIGKILL through the parent-death signal
    atexit.register(server.stop)
    yield url
