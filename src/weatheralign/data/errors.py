"""Input validation shared by every reader: errors name the file, the field and the expected form."""

from __future__ import annotations

import json

import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


class DataFormatError(ValueError):
    """Bad input data: the message names the file (or table/record), the field, and what was expected."""


def resolve_inside(root: Path, relative: str, what: str) -> Path:
    """``root / relative``, refusing absolute paths and ``..`` components that climb out of ``root``.

    The check is on the path's components, not on where symlinks point: a dataroot whose ``samples/`` is a link to
    another disk is fine.

    Raises:
        DataFormatError: the path leaves the dataroot.
    """
    root = Path(root)
    rel = Path(relative)
    if rel.is_absolute():
        raise DataFormatError(f"{what}: path {relative!r} is absolute; expected a path relative to {root}")
    normal = os.path.normpath(rel)
    if normal == ".." or normal.startswith(".." + os.sep):
        raise DataFormatError(f"{what}: path {relative!r} escapes the dataroot {root}")
    return root / normal


def require_file(path: Path, what: str) -> Path:
    """Return ``path`` if it is an existing file, else raise naming ``what``."""
    if not Path(path).is_file():
        raise DataFormatError(f"{what}: missing sensor file {path}")
    return Path(path)


def read_json_file(path: Path, missing_hint: str) -> Any:
    """The parsed JSON of ``path``.

    Raises:
        DataFormatError: the file is missing (the message ends with ``missing_hint``, e.g. which stage writes it) or
            is not valid JSON.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing; {missing_hint}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: not valid JSON ({exc})") from None


def read_float32_records(path: Path, columns: int, what: str = "point cloud") -> NDArray[np.float32]:
    """Read a raw little-endian float32 file of ``columns`` values per record -> (N, columns).

    Raises:
        DataFormatError: missing file, byte count not a multiple of ``4 * columns``, or NaN/inf coordinates.
    """
    path = require_file(Path(path), what)
    size = path.stat().st_size
    record = 4 * columns
    if size % record != 0:
        raise DataFormatError(
            f"{path}: {size} bytes is not a multiple of the record size {record} "
            f"(expected float32 x {columns} per point)"
        )
    data = np.fromfile(path, dtype="<f4").reshape(-1, columns)
    check_finite_xyz(data, path)
    return data


def check_finite_xyz(points: NDArray, source: Path | str) -> None:
    """Raise if any x, y, z (first three columns) is NaN or inf, naming the first bad row."""
    bad = ~np.isfinite(points[:, :3]).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataFormatError(
            f"{source}: {int(bad.sum())} points with NaN/inf coordinates (first at row {first}: "
            f"{points[first, :3].tolist()}); expected finite x, y, z in metres"
        )
