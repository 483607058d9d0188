"""The real-weather reference ReDAM calibrates against, read in the Seeing Through Fog layout.

A reference root holds (`weatheralign.data.stf` reads each frame):
    ``lidar_hdl64_strongest/<recording>_<frame>.bin``  float32 N x 5: x, y, z [m], intensity (0..intensity_max),
                                                        channel (STF convention: channel 0 = lowest laser);
    ``cam_stereo_left_lut/<recording>_<frame>.png``    the rectified stereo-left image;
    ``calib_cam_stereo_left.json``, ``calib_tf_tree_full.json`` (in the root, ``calib/`` or ``calibs/``);
    one split file per level (``clear``, ``light``, ``dense`` fog; ``snow`` and ``rain`` where the root has them) of
    ``recording,frame`` lines;
    optionally ``range_cam_stereo_left/<recording>_<frame>.npy``: the exact ray length per pixel [m] (float32 H x W,
    ``inf`` = sky) — the synthetic reference has it; a real root has none (use `weatheralign.camera.depth.dense_depth`).

The intensity scale is declared, never guessed (``intensity_max`` 255 or 1.0): a scan with intensities above the
declared maximum is an error, and so is a whole split of intensities within 0..1 declared as 0..255 (the published fog
code's trap: almost every point would turn into fog).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np
from numpy.typing import NDArray

from weatheralign.data.errors import DataFormatError, require_file
from weatheralign.data.frame import Frame, LidarScan
from weatheralign.data.stf import CAMERA_CHANNEL, find_sensor_file, load_stf_frame, read_stf_split
from weatheralign.lidar.clutter import isolated_returns

LEVELS: tuple[str, ...] = ("clear", "light", "dense", "snow", "rain")
"""Levels (splits) of a reference, clear first: the two fog levels, then the precipitation splits."""

FOG_LEVELS: tuple[str, ...] = ("light", "dense")
PRECIPITATION_LEVELS: tuple[str, ...] = ("snow", "rain")

LIDAR_FOLDER = "lidar_hdl64_strongest"
CAMERA_FOLDER = "cam_stereo_left_lut"
RANGE_FOLDER = "range_cam_stereo_left"

UNIT_SCALE_SUSPECT_POINTS = 1000
"""A split declared 0..255 whose scans (at least this many points in all) never exceed 1.0 is refused as 0..1 data."""


@dataclass(frozen=True)
class ReferenceSplit:
    """One level: its split file and sample ids (``<recording>_<frame>``, in file order)."""

    level: str
    split_file: Path
    ids: tuple[str, ...]


@dataclass(frozen=True)
class ReferenceDataset:
    """An opened reference root (see the module docstring); frames load lazily.

    Attributes:
        root: the reference root.
        splits: level -> `ReferenceSplit`, for the levels of `LEVELS` that were given.
        intensity_max: the declared intensity scale (255 or 1.0) of every scan.
        lidar_folder, camera_folder: the sensor folders (``camera_folder`` None: no camera).
        range_folder: folder of exact per-pixel range maps, or None where the root has none.
        crop_offset: (x0, y0) of the stored images in the calibrated image, or None (derived from the size).
    """

    root: Path
    splits: Mapping[str, ReferenceSplit]
    intensity_max: float
    lidar_folder: str = LIDAR_FOLDER
    camera_folder: str | None = CAMERA_FOLDER
    range_folder: str | None = None
    crop_offset: tuple[int, int] | None = None

    @property
    def levels(self) -> tuple[str, ...]:
        """The levels present, in `LEVELS` order."""
        return tuple(level for level in LEVELS if level in self.splits)

    def ids(self, level: str) -> tuple[str, ...]:
        """Sample ids of ``level``.

        Raises:
            KeyError: the reference has no such level.
        """
        if level not in self.splits:
            raise KeyError(f"reference {self.root}: no split {level!r} (levels: {list(self.levels)})")
        return self.splits[level].ids

    def range_path(self, sample_id: str) -> Path | None:
        """The exact range map of ``sample_id`` (``<range_folder>/<id>.npy``), or None where the root has none."""
        if self.range_folder is None:
            return None
        path = self.root / self.range_folder / f"{sample_id}.npy"
        return path if path.is_file() else None

    def load_frame(self, sample_id: str) -> Frame:
        """The frame ``sample_id`` (`load_stf_frame` with the declared scale); its camera's ``range_path`` is set
        when the reference has an exact range map for it.

        Raises:
            DataFormatError: missing or corrupt files (the message names the file and the expected form).
        """
        frame = load_stf_frame(self.root, sample_id, lidar_folder=self.lidar_folder,
                               camera_folder=self.camera_folder, crop_offset=self.crop_offset,
                               intensity_max=self.intensity_max)
        path = self.range_path(sample_id)
        if path is None or CAMERA_CHANNEL not in frame.cameras:
            return frame
        cameras = dict(frame.cameras)
        cameras[CAMERA_CHANNEL] = replace(cameras[CAMERA_CHANNEL], range_path=path)
        return replace(frame, cameras=cameras)

    def load_scan(self, sample_id: str) -> LidarScan:
        """The LiDAR scan of ``sample_id`` alone (no camera files read)."""
        return load_stf_frame(self.root, sample_id, lidar_folder=self.lidar_folder, camera_folder=None,
                              intensity_max=self.intensity_max).lidar

    def load_range(self, sample_id: str) -> NDArray[np.float32] | None:
        """(H, W) float32 exact ray length per pixel [m] (``inf`` = sky), or None where the reference has none
        (real data: estimate it with `weatheralign.camera.depth.dense_depth`)."""
        frame = self.load_frame(sample_id)
        view = frame.cameras.get(CAMERA_CHANNEL)
        if view is None or view.range_path is None:
            return None
        return view.load_range()

    def frames(self, level: str) -> Iterator[Frame]:
        """The frames of ``level`` in split order."""
        for sample_id in self.ids(level):
            yield self.load_frame(sample_id)

    def intensities(self, level: str, scale: float | None = None) -> NDArray[np.float32]:
        """All LiDAR intensities of ``level`` concatenated (M,), on ``0..scale`` (default: the declared scale)."""
        parts = [self.load_scan(i).points[:, 3] for i in self.ids(level)]
        values = np.concatenate(parts) if parts else np.zeros(0, np.float32)
        if scale is not None and scale != self.intensity_max:
            values = values * np.float32(scale / self.intensity_max)
        return values


def _split_path(root: Path, level: str, relpath: str | Path) -> Path:
    path = Path(relpath)
    return path if path.is_absolute() else Path(root) / path


def open_reference(
    root: Path,
    split_files: Mapping[str, str | Path],
    intensity_max: float,
    *,
    lidar_folder: str = LIDAR_FOLDER,
    camera_folder: str | None = CAMERA_FOLDER,
    range_folder: str | None = RANGE_FOLDER,
    crop_offset: tuple[int, int] | None = None,
) -> ReferenceDataset:
    """Open a reference root: read every split file and check that each listed frame has a LiDAR scan (and an image
    when ``camera_folder`` is set). Scans are read (and fully checked) when loaded, or by `check_reference`.

    Args:
        root: the reference root (Seeing Through Fog layout, nested or flat file names).
        split_files: level (of `LEVELS`; any subset) -> split file, relative to ``root`` or absolute.
        intensity_max: the declared intensity scale of the scans, 255 or 1.0.
        lidar_folder, camera_folder: sensor folders (``camera_folder`` None: LiDAR only).
        range_folder: folder of exact per-pixel range maps (used where present, else None for every frame).
        crop_offset: (x0, y0) of stored images in the calibrated image, or None to derive it from the image size.

    Raises:
        DataFormatError: root missing, unknown level, no split at all, scale not 255 / 1.0, a missing / empty /
            malformed split file, a frame listed twice or in two levels, or a listed frame without its scan / image.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataFormatError(f"reference root {root} does not exist (expected a Seeing Through Fog root with "
                              f"{lidar_folder}/ and the split files)")
    if intensity_max not in (1.0, 255.0):
        raise DataFormatError(f"reference {root}: intensity_max = {intensity_max!r}; expected the declared scale "
                              f"255 or 1.0")
    unknown = sorted(set(split_files) - set(LEVELS))
    if unknown:
        raise DataFormatError(f"reference {root}: unknown split level(s) {unknown}; expected some of {list(LEVELS)}")
    if not split_files:
        raise DataFormatError(f"reference {root}: no split files given; expected {list(LEVELS)}")
    splits: dict[str, ReferenceSplit] = {}
    owner: dict[str, str] = {}
    for level in LEVELS:
        if level not in split_files:
            continue
        path = _split_path(root, level, split_files[level])
        if not path.is_file():
            hint = (f"; a root without {level} recordings: set reference.split_files.{level}: null"
                    if level in PRECIPITATION_LEVELS else "")
            raise DataFormatError(f"reference split {level!r}: split file {path} not found (expected "
                                  f"'recording,frame' lines){hint}")
        ids = read_stf_split(path)
        for sample_id in ids:
            if sample_id in owner:
                where = "twice" if owner[sample_id] == level else f"also in split {owner[sample_id]!r}"
                raise DataFormatError(f"{path}: frame {sample_id} is listed {where}; a frame belongs to one level")
            owner[sample_id] = level
            try:
                find_sensor_file(root, lidar_folder, sample_id, ".bin", "STF LiDAR scan")
                if camera_folder is not None:
                    find_sensor_file(root, camera_folder, sample_id, ".png", "STF stereo-left image")
            except DataFormatError as exc:
                raise DataFormatError(f"{path}: split {level!r} lists frame {sample_id} but {exc}") from None
        splits[level] = ReferenceSplit(level, path, tuple(ids))
    return ReferenceDataset(root=root, splits=MappingProxyType(splits), intensity_max=float(intensity_max),
                            lidar_folder=lidar_folder, camera_folder=camera_folder,
                            range_folder=range_folder if range_folder and (root / range_folder).is_dir() else None,
                            crop_offset=crop_offset)


@dataclass(frozen=True)
class SplitSummary:
    """What `check_reference` found in one level: frame count, points per scan, mean intensity (0..255 scale),
    share of returns closer than 3 m, the frames that have exact range maps, and (when asked for) the mean and
    standard deviation over scans of the isolated returns within 20 m (`weatheralign.lidar.clutter`: snow and rain
    clutter)."""

    level: str
    frames: int
    points_per_scan: float
    mean_intensity_255: float
    near_fraction: float
    with_range: int
    isolated_per_scan: float | None = None
    isolated_std: float | None = None

    def as_dict(self) -> dict:
        out = {"frames": self.frames, "points_per_scan": round(self.points_per_scan, 1),
               "mean_intensity": round(self.mean_intensity_255, 4), "near_3m_fraction": round(self.near_fraction, 5),
               "frames_with_range": self.with_range}
        if self.isolated_per_scan is not None:
            out["isolated_per_scan"] = round(self.isolated_per_scan, 1)
            out["isolated_per_scan_std"] = round(float(self.isolated_std), 1)
        return out


def check_reference(ds: ReferenceDataset, *, images: bool = True, progress: bool = False,
                    azimuth_step_rad: float | None = None) -> dict[str, SplitSummary]:
    """Load every frame of every level (scans fully checked, images' sizes against the calibration, range maps
    against the images) and summarise each level; with ``azimuth_step_rad`` (the LiDAR's, [rad]) also count each
    scan's isolated returns (`weatheralign.lidar.clutter.isolated_returns`).

    Raises:
        DataFormatError: any bad file, an empty scan, or a split declared 0..255 whose intensities all lie in 0..1.
    """
    from tqdm import tqdm

    out: dict[str, SplitSummary] = {}
    for level in ds.levels:
        counts, sums, near, maxima, with_range, isolated = [], 0.0, 0, 0.0, 0, []
        for sample_id in tqdm(ds.ids(level), desc=f"reference: checking {level}", disable=not progress,
                              unit="frame"):
            frame = ds.load_frame(sample_id) if images else None
            scan = frame.lidar if frame is not None else ds.load_scan(sample_id)
            if len(scan.points) == 0:
                raise DataFormatError(f"{scan.path}: empty scan in split {level!r} (0 points)")
            if frame is not None and CAMERA_CHANNEL in frame.cameras:
                view = frame.cameras[CAMERA_CHANNEL]
                require_file(view.image_path, "STF stereo-left image")
                if view.range_path is not None:
                    view.load_range()
                    with_range += 1
            counts.append(len(scan.points))
            sums += float(scan.intensity_255().astype(np.float64).sum())
            near += int((np.linalg.norm(scan.points[:, :3], axis=1) < 3.0).sum())
            maxima = max(maxima, float(scan.points[:, 3].max()))
            if azimuth_step_rad is not None:
                isolated.append(isolated_returns(scan.points[:, :3], azimuth_step_rad=azimuth_step_rad))
        total = int(sum(counts))
        if ds.intensity_max == 255.0 and total >= UNIT_SCALE_SUSPECT_POINTS and maxima <= 1.0:
            raise DataFormatError(f"reference split {level!r} ({ds.splits[level].split_file}): all {total} "
                                  f"intensities lie in 0..1 but intensity_max = 255 was declared; set "
                                  f"intensity_max: 1.0 for a 0..1 reference")
        out[level] = SplitSummary(level, len(counts), total / max(1, len(counts)), sums / max(1, total),
                                  near / max(1, total), with_range,
                                  float(np.mean(isolated)) if isolated else None,
                                  float(np.std(isolated)) if isolated else None)
    return out


def split_files_of(cfg_split_files: object) -> dict[str, str]:
    """``{level: relpath}`` from a `weatheralign.config.ReferenceSplitFiles` (or any object with the level
    attributes); levels whose file is None (or missing) are left out."""
    files = {level: getattr(cfg_split_files, level, None) for level in LEVELS}
    return {level: str(rel) for level, rel in files.items() if rel is not None}
