"""Fingerprints that decide whether a finished piece of work (a resume record) is still valid.

A stage resumes by skipping jobs whose record carries the same fingerprint. The fingerprint must change whenever
the output would: the parameters (each stage hashes its own config), the code that computes the output
(`source_digest`) and the input files (`file_stamps`).
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Iterable
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parent


def source_digest(*parts: str, root: Path = PACKAGE_ROOT) -> str:
    """16 hex digits of SHA-256 over every ``*.py`` file of the package ``parts`` (modules or sub-packages relative
    to ``root``, e.g. ``"world", "geometry.py"``; none = the whole package), hashed as relative path and bytes in
    path order.

    An edit of the code a stage runs invalidates its resume records, so a changed algorithm never mixes with
    results of the old one (a few ms).

    Raises:
        FileNotFoundError: a part does not exist.
    """
    files: set[Path] = set()
    for part in parts or (".",):
        path = Path(root) / part
        if path.is_dir():
            files.update(path.rglob("*.py"))
        elif path.is_file():
            files.add(path)
        else:
            raise FileNotFoundError(f"source_digest: {path} does not exist")
    h = hashlib.sha256()
    for path in sorted(files):
        h.update(str(path.relative_to(root)).encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


def file_stamps(root: Path, relpaths: Iterable[str]) -> str:
    """16 hex digits of SHA-256 over (relative path, size, mtime ns) of input files under ``root``.

    Cheap (one ``stat`` per file) and conservative: an input rewritten with identical bytes also invalidates.
    A missing file stamps as ``missing``.
    """
    h = hashlib.sha256()
    for rel in sorted(relpaths):
        path = Path(root) / rel
        st = path.stat() if path.is_file() else None
        h.update(f"{rel}\0{st.st_size if st else 'missing'}\0{st.st_mtime_ns if st else ''}\0".encode())
    return h.hexdigest()[:16]


REPO_ROOT = PACKAGE_ROOT.parents[1]
"""The repository root when the package runs from its source tree (``src/weatheralign`` -> the root)."""
CODE_DIRS = ("src/", "flows/", "tasks/")


def stage_code(stage: str, dvc_file: Path | None = None) -> list[str]:
    """The code dependencies ``stage`` declares in ``dvc.yaml`` (entries under ``src/``, ``flows/``, ``tasks/``),
    relative to the repository root: the one declaration of what code a stage runs.

    Raises:
        FileNotFoundError: no dvc.yaml; KeyError: no such stage.
    """
    import yaml

    path = Path(dvc_file) if dvc_file is not None else REPO_ROOT / "dvc.yaml"
    stages = yaml.safe_load(path.read_text())["stages"]
    if stage not in stages:
        raise KeyError(f"{path}: no stage {stage!r} (has {sorted(stages)})")
    deps = stages[stage].get("deps", [])
    return [d for d in deps if isinstance(d, str) and d.startswith(CODE_DIRS)]


def stage_params(stage: str, dvc_file: Path | None = None) -> list[str]:
    """The params keys ``stage`` depends on in ``dvc.yaml`` (section names or dotted keys): those it declares, and
    every key of each setup file it declares as a dependency (``${detect.setup}``: ``detect.batch_size``, ...;
    `weatheralign.config.SETUP_FILES`), since those values reach the stage as params."""
    import yaml

    from weatheralign.config import SETUP_FILES

    path = Path(dvc_file) if dvc_file is not None else REPO_ROOT / "dvc.yaml"
    stage_def = yaml.safe_load(path.read_text())["stages"][stage]
    out: list[str] = []
    for p in stage_def.get("params", []):
        out.extend([p] if isinstance(p, str) else [str(k) for v in p.values() for k in v])
    for dep in stage_def.get("deps", []):
        named = re.fullmatch(r"\$\{\s*(\w+)\.(\w+)\s*\}", dep) if isinstance(dep, str) else None
        if named and (named[1], named[2]) in SETUP_FILES:
            out.extend(f"{named[1]}.{field}" for field in SETUP_FILES[(named[1], named[2])])
    return out


def stage_code_digest(stage: str) -> str:
    """`source_digest` of the code ``stage`` declares in dvc.yaml (`stage_code`); outside a source tree (no dvc.yaml
    beside the package) the whole package's code."""
    if (REPO_ROOT / "dvc.yaml").is_file():
        return source_digest(*stage_code(stage), root=REPO_ROOT)
    return source_digest()  # pragma: no cover - installed without the repository


def stage_fingerprint(stage: str, params: object, *extra: str) -> str:
    """16 hex digits over the code (`stage_code`) and the params values (`stage_params`) ``stage`` declares in
    dvc.yaml, plus ``extra`` strings (e.g. an input dataset's content digest): what a resume record must match.

    Outside a source tree (no dvc.yaml beside the package) the whole package's code is hashed instead.
    """
    import json

    code = stage_code_digest(stage)
    keys = stage_params(stage) if (REPO_ROOT / "dvc.yaml").is_file() else []
    tree = params.model_dump(mode="json") if hasattr(params, "model_dump") else {}
    values = {}
    for key in keys:
        node = tree
        for part in key.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        values[key] = node
    blob = json.dumps({"code": code, "params": values, "extra": list(extra)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def file_digests(root: Path, relpaths: Iterable[str]) -> dict[str, list]:
    """``{relpath: [size, sha256 hex]}`` of files under ``root``: what a resume record stores at write time."""
    out = {}
    for rel in sorted(relpaths):
        data = (Path(root) / rel).read_bytes()
        out[rel] = [len(data), hashlib.sha256(data).hexdigest()]
    return out


def files_intact(root: Path, digests: dict[str, list]) -> bool:
    """Whether every file of ``digests`` (`file_digests`) is present under ``root`` with its size and digest: a
    truncated or replaced output is not a finished one."""
    for rel, (size, sha) in digests.items():
        path = Path(root) / rel
        if not path.is_file() or path.stat().st_size != size:
            return False
        if hashlib.sha256(path.read_bytes()).hexdigest() != sha:
            return False
    return True


def write_resume_record(path: Path, fingerprint: str, root: Path, relpaths: Iterable[str], payload: dict) -> dict:
    """Write (atomically) the resume record of a finished job: its ``fingerprint``, the `file_digests` of the files
    it wrote under ``root`` and its ``payload`` (merged in); returns the record."""
    from weatheralign import atomic

    record = {"config": fingerprint, "files": file_digests(root, relpaths), **payload}
    atomic.write_json(path, record)
    return record


def read_resume_record(path: Path, fingerprint: str, root: Path) -> dict | None:
    """The record at ``path`` (`write_resume_record`) if it carries ``fingerprint`` and every file it lists is still
    under ``root`` with its recorded size and SHA-256; None otherwise (absent, unreadable, another fingerprint, a
    missing, truncated or replaced file): the job is done again."""
    record = read_record_json(path)
    if record is None or record.get("config") != fingerprint or not isinstance(record.get("files"), dict):
        return None
    return record if files_intact(root, record["files"]) else None


def read_record_json(path: Path) -> dict | None:
    """The JSON object of a resume record at ``path``; None if absent, unreadable or not an object."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except (json.JSONDecodeError, OSError):
        return None
    return record if isinstance(record, dict) else None
