"""Dataset manifests: how one stage names the dataset it hands to the next.

A manifest (``<paths.data>/manifests/<name>.json``) holds the dataroot, the nuScenes version, the source, the sensor
models (`weatheralign.sensors.SensorRig`) and a content digest. Downstream stages depend on the manifest, never on
another stage's metrics: it carries no run-time counters, so a rerun that changes nothing rewrites the same bytes
and DVC keeps every downstream stage up to date. The content digest covers the version folder's tables (bytes) and
every sensor file the tables reference (relative path and size) — cheap (one ``stat`` per file) and enough to tell
a re-rendered or replaced dataset; a producer removes its manifest before it starts and writes it only when it has
finished, so a failed run leaves no stale handoff behind.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from weatheralign import atomic
from weatheralign.data.errors import DataFormatError, read_json_file
from weatheralign.sensors import SensorRig

MANIFEST_DIR = "manifests"
FOG_LEVELS_FILE = "calibrate_fog/fog_levels.json"
PRECIPITATION_RATES_FILE = "calibrate_precipitation/rates.json"
"""Tuned fog levels written by the calibrate_fog stage, relative to ``paths.data``:
``{"light": {"alpha": .., "beta": ..}, "dense": {...}, ...}``."""
FIELDS_FILE = "particles/fields.json"
"""Particle fields written by the particles stage, relative to ``paths.data``: ``{kind: [FieldSpec dict, ...]}``."""


@dataclass(frozen=True)
class DatasetManifest:
    """A dataset handed between stages.

    Attributes:
        dataroot: the nuScenes dataroot (relative to the working directory where it lies inside it, else absolute).
        version: the table folder (e.g. ``v1.0-mini``); source: ``synthetic``, ``nuscenes``, or ``simulate``.
        sensors: the dataset's LiDAR and camera models.
        content_digest: `dataset_digest` of the dataroot.
        scenes: the scene names in table order.
    """

    dataroot: str
    version: str
    source: str
    sensors: SensorRig
    content_digest: str
    scenes: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"dataroot": self.dataroot, "version": self.version, "source": self.source,
                "content_digest": self.content_digest, "scenes": list(self.scenes), "sensors": self.sensors.to_dict()}


def manifest_path(data: Path, name: str) -> Path:
    """``<data>/manifests/<name>.json``."""
    return Path(data) / MANIFEST_DIR / f"{name}.json"


def dataset_digest(dataroot: Path, version: str) -> str:
    """16 hex digits over the bytes of ``<dataroot>/<version>/*.json`` and (path, size) of every file its
    ``sample_data`` table names.

    Raises:
        DataFormatError: no table folder, or a referenced file is missing.
    """
    root = Path(dataroot)
    tables = root / version
    if not tables.is_dir():
        raise DataFormatError(f"{tables}: no table folder; expected a nuScenes dataroot with {version}/*.json")
    h = hashlib.sha256()
    for path in sorted(tables.glob("*.json")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    try:
        records = json.loads((tables / "sample_data.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataFormatError(f"{tables / 'sample_data.json'}: unreadable ({exc})") from None
    for rec in sorted(records, key=lambda r: r["filename"]):
        path = root / rec["filename"]
        if not path.is_file():
            raise DataFormatError(f"{path}: missing (named by {tables / 'sample_data.json'})")
        h.update(f"{rec['filename']}\0{path.stat().st_size}\0".encode())
    return h.hexdigest()[:16]


def display_path(path: Path) -> str:
    """``path`` relative to the working directory where it lies inside it, else absolute."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(Path(path).resolve())


def write_manifest(path: Path, manifest: DatasetManifest) -> None:
    """Write ``manifest`` atomically (same manifest, same bytes)."""
    atomic.write_json(Path(path), manifest.to_dict(), indent=1)


def read_manifest(path: Path) -> DatasetManifest:
    """The manifest at ``path``.

    Raises:
        DataFormatError: missing (naming the stage to run), unreadable, or a field of the wrong form.
    """
    path = Path(path)
    d = read_json_file(path, "run the stage that produces it first (dvc repro, or python -m flows.world for the "
                             "world's manifest)")
    try:
        return DatasetManifest(str(d["dataroot"]), str(d["version"]), str(d["source"]),
                               SensorRig.from_dict(d["sensors"], f"{path}: sensors"), str(d["content_digest"]),
                               tuple(str(s) for s in d["scenes"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: not a dataset manifest ({exc})") from None


__all__ = ["FIELDS_FILE", "FOG_LEVELS_FILE", "PRECIPITATION_RATES_FILE", "DatasetManifest", "dataset_digest",
           "display_path", "manifest_path", "read_manifest", "write_manifest"]
