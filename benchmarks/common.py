"""Helpers shared by the benchmark scripts: result-file merging and isolated worker processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def merge_entries(path: Path, entries: list[dict[str, Any]]) -> Any:
    """The content of ``path`` with the entries of the same ``workload`` replaced by ``entries``; every other
    workload's entry is kept. A JSON list, or an object holding the list under ``"entries"``."""
    data: Any = json.loads(path.read_text()) if path.is_file() else []
    old = data.get("entries", []) if isinstance(data, dict) else list(data)
    ours = {e["workload"] for e in entries}
    merged = [e for e in old if not (isinstance(e, dict) and e.get("workload") in ours)] + entries
    return {**data, "entries": merged} if isinstance(data, dict) else merged


def run_worker(module: str, spec: dict) -> dict:
    """Run ``python -m <module> --worker <spec json>`` in a fresh process (clean peak-memory figures) and return
    the JSON object it prints last."""
    proc = subprocess.run([sys.executable, "-m", module, "--worker", json.dumps(spec)],
                          cwd=REPO, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"worker failed for {spec['workload']}:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
