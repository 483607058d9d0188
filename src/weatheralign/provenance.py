"""Fingerprints that decide whether a finished piece of work (a resume record) is still valid.

A stage resumes by skipping jobs whose record carries the same fingerprint. The fingerprint must change whenever
the output would: the parameters (each stage hashes its own config), the code that computes the output
(`source_digest`) and the input files (`file_stamps`).
"""

from __future__ import annotations

import hashlib
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
