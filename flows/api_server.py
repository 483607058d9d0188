"""One Prefect API server (and optionally one Dask cluster) for a whole command such as `dvc repro`.

``python -m flows.api_server <command ...>`` runs a command with one server of `flows.prefect_server` for all of its
stages (``PREFECT_API_URL`` exported to it), which also saves starting a server per stage. With ``--dask``
(`make reproduce`) it also starts one local Dask cluster of ``run.max_workers`` worker processes for the whole
command (``WEATHERALIGN_DASK_ADDRESS`` exported; unless params set ``run.dask_address``): each stage sends its tasks
there instead of starting and stopping a cluster of its own, and the workers keep their imports and compiled kernels
from stage to stage.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

from flows.common import SHARED_DASK_ENV, local_cluster_kwargs, worker_environment
from flows.prefect_server import install_signal_handlers, prefect_api
from weatheralign.config import ConfigError, load_params


@contextlib.contextmanager
def shared_dask_cluster(params_file: str = "params.yaml") -> Iterator[str | None]:
    """The scheduler address of a local Dask cluster for a whole run (closed on exit), as `flows.common.task_runner`
    would start per stage (``run.max_workers`` processes, one thread each, the same worker environment); None when
    params set ``run.dask_address`` (the stages use that) or cannot be read (the stages report why)."""
    try:
        params = load_params(params_file)
    except (ConfigError, OSError):
        yield None
        return
    if params.run.dask_address:
        yield None
        return
    from distributed import LocalCluster

    with worker_environment(), LocalCluster(**local_cluster_kwargs(params)) as cluster:
        yield cluster.scheduler_address


def main(argv: list[str] | None = None) -> int:
    """Run a command with one Prefect API server for all of it: ``python -m flows.api_server [--dask] dvc repro``."""
    args = list(sys.argv[1:] if argv is None else argv)
    dask = bool(args) and args[0] == "--dask"
    args = args[1:] if dask else args
    if not args:
        print("usage: python -m flows.api_server [--dask] <command> [args ...]", file=sys.stderr)
        return 2
    install_signal_handlers()
    with prefect_api() as url:
        if url:  # the shared cluster's workers report their task runs to this server too
            os.environ["PREFECT_API_URL"] = url
        with shared_dask_cluster() if dask else contextlib.nullcontext(None) as address:
            env = {**os.environ, **({SHARED_DASK_ENV: address} if address else {})}
            child = subprocess.Popen(args, env=env)
            try:
                return child.wait()
            except SystemExit:
                child.terminate()
                child.wait()
                raise


if __name__ == "__main__":
    sys.exit(main())
