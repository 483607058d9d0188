"""Atomic file output: every file is written to a temporary sibling and renamed into place, so an interrupted run
never leaves a half-written file under its final name."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``, on error removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are meant to be read by others
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | Path, obj: Any, indent: int | None = 0) -> None:
    """Deterministic JSON (sorted keys are NOT forced: table record order matters for nuScenes)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=indent, allow_nan=False))


def save_npy(path: str | Path, array: np.ndarray) -> None:
    """``np.save`` atomically (byte-identical for identical arrays, unlike ``np.savez`` which stamps times)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)


def save_npz(path: str | Path, arrays: dict[str, np.ndarray], compress: bool) -> None:
    """The ``arrays`` as an ``.npz`` (one member per name, in order), deflate-compressed with ``compress`` (level 1:
    within 2 % of level 6's size on per-point records at a third of the time) or stored (15x faster to write and 3.5x
    to read, for caches read often), atomically and byte-identical for identical arrays: every zip member carries a
    fixed date (``np.savez`` stamps the current time)."""
    import io
    import zipfile

    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=method) as zf:
        for name, array in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info.external_attr = 0o644 << 16
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(array), allow_pickle=False)
            # the level must be given here: a ZipInfo written through ZipFile.open gets zlib's default level 6
            zf.writestr(info, buf.getbuffer(), compresslevel=1 if compress else None)
