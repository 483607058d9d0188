"""Helpers shared by the benchmark scripts: result-file merging, isolated worker processes, the shared real
frames."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real"
STF_ID = "2019-09-11_19-13-44_00960"
"""The clear Seeing Through Fog frame of ``../shared/data/real/stf``."""


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


def real_frames(root: Path = REAL) -> dict[str, Callable[[], Any]]:
    """Loaders of the shared real frames under ``root`` that exist: ``stf`` (HDL-64 + stereo-left camera) and
    ``kitti`` (HDL-64 + left colour camera), each giving a `weatheralign.data.frame.Frame`."""
    from weatheralign.data.kitti import load_kitti_frame
    from weatheralign.data.stf import load_stf_frame

    k = root / "kitti"
    frames: dict[str, Callable[[], Any]] = {}
    if (root / "stf").is_dir():
        frames["stf"] = lambda: load_stf_frame(root / "stf", STF_ID)
    if k.is_dir():
        frames["kitti"] = lambda: load_kitti_frame(k / "000008.bin", k / "000008.png", k / "calib.json")
    return frames
