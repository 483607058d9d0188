"""Check a user's nuScenes-format dataset up front, in one pass, and report every bad file at once.

Later stages read every keyframe's frame (the LiDAR with its sweeps, six cameras, boxes) and copy or simulate every
sweep; a bad file found midway through `simulate` would leave a half-written weather copy. `check_dataset` reads
everything they will read — each sample's frame (tables, poses, calibrations, boxes), every LiDAR file (keyframes and
sweeps: decoded and validated, `weatheralign.data.errors.validate_scan` through the reader) and every camera image
(decoded in full, its size checked against its ``sample_data`` record's ``width`` x ``height`` and against its
calibrated intrinsics, `intrinsics_mismatch`) — in a thread pool, and collects the errors instead of stopping at the
first.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from weatheralign.data.errors import DataFormatError
from weatheralign.data.frame import read_image_size
from weatheralign.data.nuscenes import load_camera, load_frame, load_lidar

MAX_REPORTED = 20
"""Errors listed in the raised message (the count covers all of them)."""
PRINCIPAL_POINT_TOLERANCE = 0.2
"""How far the principal point may lie from the image centre, as a fraction of the image's width (x) or height (y).
A real camera's lies within a few percent (nuScenes <= 6 %, KITTI <= 4 %); resizing an image by a factor s without
scaling its intrinsics moves it to |1/s - 1| / 2 of the size (a half-size image: 50 %), so 0.2 catches every
resize by s <= 0.71 or s >= 1.67."""


@dataclass(frozen=True)
class DatasetCheck:
    """What `check_dataset` read: ``samples``, ``lidar_files``, ``images`` checked, and ``errors`` (one line each)."""

    samples: int
    lidar_files: int
    images: int
    errors: tuple[str, ...]

    def raise_if_bad(self, dataroot: Path) -> None:
        """Raise one DataFormatError listing the errors (at most `MAX_REPORTED`, with the total)."""
        if self.errors:
            shown = "\n  ".join(self.errors[:MAX_REPORTED])
            more = f"\n  ... and {len(self.errors) - MAX_REPORTED} more" if len(self.errors) > MAX_REPORTED else ""
            raise DataFormatError(f"{dataroot}: {len(self.errors)} problem(s) in the dataset; nothing was written:\n  "
                                  f"{shown}{more}")


def _error_of(fn, *args) -> str | None:
    try:
        fn(*args)
    except DataFormatError as exc:
        return str(exc)
    return None


def intrinsics_mismatch(K: NDArray[np.float64], width: int, height: int) -> str | None:
    """Why the intrinsics ``K`` (3, 3) [px] do not fit an image of ``width`` x ``height`` [px]: a principal point
    farther than `PRINCIPAL_POINT_TOLERANCE` of the size from the image centre (the image was resized and ``K`` was
    not); None when they fit."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if (abs(cx - width / 2) <= PRINCIPAL_POINT_TOLERANCE * width
            and abs(cy - height / 2) <= PRINCIPAL_POINT_TOLERANCE * height):
        return None
    return (f"the principal point ({cx:.1f}, {cy:.1f}) px is the centre of a {2 * cx:.0f}x{2 * cy:.0f} image, "
            f"expected within {PRINCIPAL_POINT_TOLERANCE:.0%} of the size from ({width / 2:g}, {height / 2:g})")


def _check_image(nusc, sd: dict) -> None:
    """Decode the camera image of ``sd`` in full and check its size against its ``sample_data`` record and the
    intrinsics of its ``calibrated_sensor`` record.

    Raises:
        DataFormatError: naming the file, its size and the expected one.
    """
    view = load_camera(nusc, sd["token"])
    width, height = read_image_size(view.image_path, f"{view.channel} image")
    if (width, height) != (view.width, view.height):
        raise DataFormatError(f"{view.image_path}: {view.channel} image is {width}x{height}, its sample_data record "
                              f"{sd['token']} says {view.width}x{view.height}; expected the image's own size there")
    why = intrinsics_mismatch(view.K, width, height)
    if why is not None:
        raise DataFormatError(f"{view.image_path}: {view.channel} image is {width}x{height} as its sample_data record "
                              f"says, but its calibrated_sensor {sd['calibrated_sensor_token']} camera_intrinsic does "
                              f"not fit it: {why}; rescale camera_intrinsic with the image")


def check_dataset(nusc, workers: int = 2) -> DatasetCheck:
    """Read every sample's frame, every LiDAR file and every image of ``nusc`` (see the module docstring).

    Returns:
        `DatasetCheck` with one error line per bad sample or file (empty when everything loads).
    """
    jobs = [(load_frame, nusc, s["token"]) for s in nusc.sample]
    n_lidar = n_img = 0
    for sd in nusc.sample_data:
        if sd.get("sensor_modality") == "lidar" or "LIDAR" in str(sd.get("filename", "")):
            jobs.append((load_lidar, nusc, sd["token"]))
            n_lidar += 1
        elif sd.get("sensor_modality") == "camera" or "/CAM" in str(sd.get("filename", "")):
            jobs.append((_check_image, nusc, sd))
            n_img += 1
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        errors = [e for e in pool.map(lambda job: _error_of(*job), jobs) if e is not None]
    return DatasetCheck(len(nusc.sample), n_lidar, n_img, tuple(dict.fromkeys(errors)))


__all__ = ["PRINCIPAL_POINT_TOLERANCE", "DatasetCheck", "check_dataset", "intrinsics_mismatch"]
