"""The sensor-agnostic `Frame`: one LiDAR scan, its cameras and its boxes, from any dataset.

Conventions (see docs/architecture.md): points are float32 (N, 5) ``(x, y, z, intensity, ring)`` in the LiDAR frame
at the scan timestamp; times are float64 seconds; transforms are 4x4 float64 ``T_<to>_<from>``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from weatheralign.data.errors import DataFormatError, require_file
from weatheralign.data.float16 import from_float16
from weatheralign.geometry import apply, interpolate_poses, invert

F64 = NDArray[np.float64]

_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, Image.DecompressionBombError)
"""What Pillow raises for a truncated, corrupt or unidentifiable image (``UnidentifiedImageError`` is an OSError)."""


def _image_error(path: Path, what: str, exc: BaseException) -> DataFormatError:
    return DataFormatError(f"{path}: {what} is truncated or not a valid JPEG/PNG image ({type(exc).__name__}: {exc})")


def read_image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) [px] of an image file, decoded in full so that a truncated or corrupt file fails here.

    Raises:
        DataFormatError: a missing file, or one that is truncated or not a valid JPEG/PNG (naming the file).
    """
    path = require_file(Path(path), what)
    try:
        with Image.open(path) as im:
            im.load()
            return int(im.width), int(im.height)
    except _IMAGE_ERRORS as exc:
        raise _image_error(path, what, exc) from None


def read_rgb_image(path: Path, what: str) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB of an image file, decoded in full.

    Raises:
        DataFormatError: a missing file, or one that is truncated or not a valid JPEG/PNG (naming the file).
    """
    path = require_file(Path(path), what)
    try:
        with Image.open(path) as im:
            im.load()  # decode everything now: Pillow reports truncation only when the pixels are read
            return np.asarray(im if im.mode == "RGB" else im.convert("RGB"))
    except _IMAGE_ERRORS as exc:
        raise _image_error(path, what, exc) from None


@dataclass(frozen=True)
class LidarScan:
    """A LiDAR scan in its sensor frame at ``timestamp``.

    Attributes:
        points: (N, 5) float32 ``x, y, z`` [m], intensity (on ``0..intensity_max``), ring index (float).
        timestamp: scan reference time [s] (nuScenes: end of the rotation).
        time_offsets: (N,) float32 firing time of each point relative to ``timestamp`` [s] (<= 0), or None.
        T_ego_lidar: (4, 4) sensor -> ego.
        T_global_ego: (4, 4) ego -> global at ``timestamp``.
        intensity_max: 255.0 for 0..255 intensities (nuScenes, STF), 1.0 for 0..1 reflectances (KITTI).
        num_rings: number of laser rings of the sensor (32 for the HDL-32E, 64 for the HDL-64).
        sweep_index: (N,) int16, 0 for the reference sweep, k for the k-th earlier aggregated sweep; None = single.
        pose_times: (K,) times [s] of ego poses ``poses`` (K, 4, 4) covering the scan, for per-point ego poses.
        path: file the points were read from, if any.
    """

    points: NDArray[np.float32]
    timestamp: float
    T_ego_lidar: F64
    T_global_ego: F64
    intensity_max: float = 255.0
    num_rings: int = 32
    time_offsets: NDArray[np.float32] | None = None
    sweep_index: NDArray[np.int16] | None = None
    pose_times: F64 | None = None
    poses: F64 | None = None
    path: Path | None = None

    def __post_init__(self) -> None:
        pts = self.points
        where = self.path or "LidarScan"
        if pts.ndim != 2 or pts.shape[1] != 5 or pts.dtype != np.float32:
            raise DataFormatError(f"{where}: points must be float32 (N, 5), got {pts.dtype} {pts.shape}")
        if self.intensity_max not in (1.0, 255.0):
            raise DataFormatError(f"{where}: intensity_max must be 1.0 or 255.0, got {self.intensity_max}")
        n = len(pts)
        for name in ("time_offsets", "sweep_index"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != (n,):
                raise DataFormatError(f"{where}: {name} must have shape ({n},), got {arr.shape}")

    @property
    def T_global_lidar(self) -> F64:
        """(4, 4) sensor -> global at ``timestamp``."""
        return self.T_global_ego @ self.T_ego_lidar

    def intensity_255(self) -> NDArray[np.float32]:
        """(N,) intensities on the 0..255 scale whatever the stored scale."""
        return self.points[:, 3] * np.float32(255.0 / self.intensity_max)

    def point_times(self) -> F64:
        """(N,) absolute firing time of every point [s] (the scan timestamp where unknown)."""
        if self.time_offsets is None:
            return np.full(len(self.points), self.timestamp)
        return self.timestamp + self.time_offsets.astype(np.float64)

    def global_poses_at(self, times: NDArray) -> F64:
        """(N, 4, 4) ``T_global_ego`` at ``times`` (N,) [s], interpolated over ``poses`` (constant if none)."""
        if self.poses is None or self.pose_times is None:
            return np.broadcast_to(self.T_global_ego, (len(times), 4, 4)).copy()
        return interpolate_poses(times, self.pose_times, self.poses)

    def beam_origins(self) -> F64:
        """(N, 3) position of the sensor, in this scan's frame, at each point's firing time [m].

        A point's beam runs from its origin to the point; for a moving ego the origin moves during the sweep.
        """
        times = self.point_times()
        T_global_lidar_t = self.global_poses_at(times) @ self.T_ego_lidar
        origins_global = T_global_lidar_t[:, :3, 3]
        return apply(invert(self.T_global_lidar), origins_global)


@dataclass(frozen=True)
class CameraView:
    """One camera image with its calibration and pose at its own timestamp.

    Attributes:
        channel: e.g. ``CAM_FRONT``.
        image_path: the image file (JPEG/PNG, RGB).
        K: (3, 3) intrinsics in pixels for the stored image size ``width`` x ``height``.
        T_ego_cam: (4, 4) camera (OpenCV axes) -> ego.
        T_global_ego: (4, 4) ego -> global at ``timestamp``.
        timestamp: exposure time [s].
        range_path: optional per-pixel ray length [m] (H, W) ``.npy`` (synthetic world only; inf = sky).
    """

    channel: str
    image_path: Path
    K: F64
    width: int
    height: int
    T_ego_cam: F64
    T_global_ego: F64
    timestamp: float
    range_path: Path | None = None

    @property
    def T_global_cam(self) -> F64:
        """(4, 4) camera -> global at ``timestamp``."""
        return self.T_global_ego @ self.T_ego_cam

    def load_image(self) -> NDArray[np.uint8]:
        """(H, W, 3) uint8 RGB.

        Raises:
            DataFormatError: missing, truncated or undecodable file, or a size other than the calibration's.
        """
        rgb = read_rgb_image(self.image_path, f"{self.channel} image")
        if rgb.shape[:2] != (self.height, self.width):
            raise DataFormatError(
                f"{self.image_path}: image is {rgb.shape[1]}x{rgb.shape[0]}, "
                f"calibration says {self.width}x{self.height}"
            )
        return rgb

    def load_range(self) -> NDArray[np.float32]:
        """(H, W) float32 ray length per pixel [m], inf where the ray hits nothing (sky)."""
        if self.range_path is None:
            raise DataFormatError(f"{self.channel}: this dataset has no exact per-pixel range (real data)")
        path = require_file(self.range_path, f"{self.channel} range map")
        try:
            rng = np.load(path)
            rng = from_float16(rng) if rng.dtype == np.float16 else rng.astype(np.float32)
        except (OSError, ValueError, EOFError) as exc:
            raise DataFormatError(f"{path}: {self.channel} range map is truncated or not a valid .npy array "
                                  f"({type(exc).__name__}: {exc}); expected (H, W) float ray lengths [m]") from None
        if rng.shape != (self.height, self.width):
            raise DataFormatError(f"{self.range_path}: range map shape {rng.shape} != image {self.height}x{self.width}")
        return rng


@dataclass(frozen=True)
class Box:
    """An annotated 3-D box in the global frame.

    Attributes:
        center: (3,) [m]; size: (3,) width, length, height [m] (nuScenes order); yaw: heading about +z [rad];
        velocity: (3,) [m/s] (nan where unknown); category: nuScenes category name; attribute: name or "".
    """

    token: str
    instance_token: str
    category: str
    center: F64
    size: F64
    yaw: float
    velocity: F64
    num_lidar_pts: int = 0
    attribute: str = ""
    visibility: str = ""


@dataclass(frozen=True)
class Frame:
    """One multi-sensor frame (a nuScenes sample, or one STF/KITTI recording frame)."""

    token: str
    timestamp: float
    lidar: LidarScan
    cameras: dict[str, CameraView] = field(default_factory=dict)
    boxes: tuple[Box, ...] = ()
    source: str = "nuscenes"
