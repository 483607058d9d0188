"""Prefect flows, one module per pipeline stage: ``python -m flows.<stage> [--params FILE] [--set key=value ...]``."""

import os

# Offline, 2-core friendly defaults for a Prefect process without a server (set before prefect is imported).
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")
os.environ.setdefault("PREFECT_HOME", os.path.join(os.getcwd(), ".prefect"))
