"""Atomic file output: every file is written to a temporary sibling and renamed into place, so an interrupted run
never leaves a half-written file under its final name. A write that finds the disk full raises `DiskFullError`
naming the file and the space left, not a bare ``[Errno 28] No space left on device``."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

TEMPORARY_NAME = re.compile(r"^\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp$")
"""The name of an `atomic_path` temporary: ``.<target name>.<8 random characters>.tmp`` (`tempfile.mkstemp`'s)."""


class DiskFullError(OSError):
    """A write found the disk full (``ENOSPC``). Built as ``DiskFullError(errno.ENOSPC, message)``; its text is the
    message alone (the file, the space left and what to do), one line."""

    def __str__(self) -> str:
        return str(self.strerror)


def free_bytes(folder: Path) -> int | None:
    """Bytes [B] an unprivileged user may still write on the file system of ``folder`` (its nearest existing
    ancestor); None if it cannot be asked."""
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def disk_full_error(path: Path) -> DiskFullError:
    """The `DiskFullError` of a write of ``path`` that found no space left: names the file and the free space [MiB]
    on its file system."""
    free = free_bytes(Path(path).parent)
    left = "unknown" if free is None else f"{free / 2**20:.1f} MiB"
    return DiskFullError(errno.ENOSPC, f"{path}: no space left on the device while writing it ({left} free on "
                                       f"{Path(path).parent}'s file system); free some space there and rerun")


def temporary_target(path: Path) -> Path | None:
    """The file that the `atomic_path` temporary ``path`` was to become (beside it); None when ``path`` is not named
    like one (`TEMPORARY_NAME`)."""
    match = TEMPORARY_NAME.fullmatch(Path(path).name)
    return None if match is None else Path(path).with_name(match["target"])


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``, on error removed.

    Raises:
        DiskFullError: the disk filled up while the folder or the temporary was created or written (naming
            ``path``).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            raise disk_full_error(path) from None
        raise
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are meant to be read by others
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC and not isinstance(exc, DiskFullError):
            raise disk_full_error(path) from None
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
    within 2 % of level 6's size on per-point records for much less compression work) or stored (no deflate work to
    write or to read, for caches read often), atomically and byte-identical for identical arrays: every zip member
    carries a fixed date (``np.savez`` stamps the current time)."""
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
