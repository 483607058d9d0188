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

    Only the byte count and the coordinates are checked here; a reader then runs `validate_scan` with the file's
    declared intensity scale and ring count (empty scans, intensities, rings).

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


def check_finite_xyz(points: NDArray, source: Path | str, fields: tuple[str, ...] = ("x", "y", "z")) -> None:
    """Raise if any x, y, z (first three columns) is NaN or inf, naming the first bad row and its field."""
    finite = np.isfinite(points[:, :3])
    bad = ~finite.all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        col = int(np.flatnonzero(~finite[first])[0])
        raise DataFormatError(
            f"{source}: {int(bad.sum())} points with NaN/inf coordinates (first at row {first}, field "
            f"{fields[col]!r}: {points[first, :3].tolist()}); expected finite x, y, z in metres"
        )


SCALE_CHECK_MIN_POINTS = 100
"""A 0..255 scan of more than this many points whose every intensity is <= 1.0 is a 0..1 scan on the wrong scale."""

_SCALE_NAMES = {255.0: "0..255", 1.0: "0..1"}


def _plural(name: str) -> str:
    return name[:-1] + "ies" if name.endswith("y") else name + "s"


def validate_scan(
    points: NDArray,
    source: Path | str,
    *,
    intensity_max: float,
    num_rings: int | None = None,
    fields: tuple[str, ...] = ("x", "y", "z", "intensity", "ring"),
) -> None:
    """Check a scan as read from ``source``; the one validation every LiDAR reader (nuScenes, STF, KITTI) runs.

    Args:
        points: (N, C) records as stored: ``x, y, z`` [m], the intensity in column 4 and, with ``num_rings``, the
            ring in column 5.
        source: the file, named in every error.
        intensity_max: the declared intensity scale, 255.0 (``0..255``) or 1.0 (``0..1``, e.g. KITTI reflectance).
        num_rings: the sensor's ring count; rings must be integers ``0..num_rings-1``. None: the file has no ring
            column to check (KITTI, rings derived from elevation).
        fields: the column names used in the messages (e.g. ``reflectance`` for KITTI, ``channel`` for STF).

    Raises:
        DataFormatError: naming ``source``, the field (column), the first bad row and its value and the expected form,
            for an empty scan, NaN/inf coordinates, NaN/inf intensities or intensities outside ``0..intensity_max``,
            a 0..255 scan of more than `SCALE_CHECK_MIN_POINTS` points whose every intensity is <= 1.0 (a 0..1 scan
            declared 0..255), and rings that are not integers ``0..num_rings-1``.
    """
    if intensity_max not in _SCALE_NAMES:
        raise DataFormatError(f"{source}: declared intensity scale {intensity_max!r}; expected 255.0 or 1.0")
    scale = _SCALE_NAMES[intensity_max]
    n_cols = 5 if num_rings is not None else 4
    if points.ndim != 2 or points.shape[1] < n_cols:
        raise DataFormatError(f"{source}: points have shape {points.shape}; expected (N, {n_cols}) records "
                              f"({', '.join(fields[:n_cols])})")
    if len(points) == 0:
        raise DataFormatError(f"{source}: empty scan (0 points); expected at least one point "
                              f"({', '.join(fields[:n_cols])} per record)")
    check_finite_xyz(points, source, fields[:3])
    name = fields[3]
    value = points[:, 3]
    finite = np.isfinite(value)
    if not finite.all():
        first = int(np.flatnonzero(~finite)[0])
        raise DataFormatError(
            f"{source}: {int((~finite).sum())} NaN/inf {_plural(name)} (field {name!r}, column 4; first at row "
            f"{first}: {float(value[first])}); expected a finite {name} on {scale} (declared intensity_max = "
            f"{intensity_max:g})")
    bad = (value < 0) | (value > intensity_max)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataFormatError(
            f"{source}: {int(bad.sum())} {_plural(name)} outside {scale} (field {name!r}, column 4; first at row "
            f"{first}: {float(value[first])}); expected {name} on {scale} (declared intensity_max = "
            f"{intensity_max:g})")
    if intensity_max == 255.0 and len(points) > SCALE_CHECK_MIN_POINTS:
        top = float(value.max())
        if top <= 1.0:
            row = int(np.argmax(value))
            raise DataFormatError(
                f"{source}: every {name} of the {len(points)} points is <= 1.0 (field {name!r}, column 4; largest "
                f"at row {row}: {top}): a 0..1 scan declared 0..255; expected {name} on 0..255 (rescale it, or "
                f"declare intensity_max = 1.0)")
    if num_rings is not None:
        name = fields[4]
        ring = points[:, 4]
        bad = ~np.isfinite(ring) | (ring < 0) | (ring > num_rings - 1) | (ring != np.round(ring))
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise DataFormatError(
                f"{source}: {int(bad.sum())} invalid {_plural(name)} (field {name!r}, column 5; first at row {first}: "
                f"{float(ring[first])}); expected integers 0..{num_rings - 1} in column 5")
