"""Check a user's nuScenes-format dataset up front, in one pass, and report every bad file at once.

Later stages read every keyframe's frame (the LiDAR with its sweeps, six cameras, boxes) and copy or simulate every
sweep; a bad file found midway through `simulate` would leave a half-written weather copy. `check_dataset` reads
everything they will read — each sample's frame (tables, poses, calibrations, boxes), every LiDAR file (keyframes and
sweeps: decoded and validated, `weatheralign.data.errors.validate_scan` through the reader) and every camera image
(decoded in full) — in a thread pool, and collects the errors instead of stopping at the first.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from weatheralign.data.errors import DataFormatError, resolve_inside
from weatheralign.data.frame import read_image_size
from weatheralign.data.nuscenes import load_frame, load_lidar

MAX_REPORTED = 20
"""Errors listed in the raised message (the count covers all of them)."""


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


def _check_image(root: Path, sd: dict) -> None:
    what = f"{sd.get('channel', 'camera')} image"
    read_image_size(resolve_inside(root, str(sd.get("filename", "")), what), what)


def check_dataset(nusc, dataroot: Path, workers: int = 2) -> DatasetCheck:
    """Read every sample's frame, every LiDAR file and every image of ``nusc`` (see the module docstring).

    Returns:
        `DatasetCheck` with one error line per bad sample or file (empty when everything loads).
    """
    root = Path(dataroot)
    jobs = [(load_frame, nusc, s["token"]) for s in nusc.sample]
    n_lidar = n_img = 0
    for sd in nusc.sample_data:
        if sd.get("sensor_modality") == "lidar" or "LIDAR" in str(sd.get("filename", "")):
            jobs.append((load_lidar, nusc, sd["token"]))
            n_lidar += 1
        elif sd.get("sensor_modality") == "camera" or "/CAM" in str(sd.get("filename", "")):
            jobs.append((_check_image, root, sd))
            n_img += 1
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        errors = [e for e in pool.map(lambda job: _error_of(*job), jobs) if e is not None]
    return DatasetCheck(len(nusc.sample), n_lidar, n_img, tuple(dict.fromkeys(errors)))


__all__ = ["DatasetCheck", "check_dataset"]
