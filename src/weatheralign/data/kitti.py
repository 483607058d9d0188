"""KITTI object-detection frame reader (Velodyne HDL-64E + left colour camera ``image_2``).

Inputs: ``<id>.bin`` raw little-endian float32 N x 4 ``(x, y, z, reflectance)`` with reflectance on 0..1 and no
ring column; ``image_2/<id>.png``; a calibration either as the standard object calib text file (``P2: ...``,
``R0_rect: ...``, ``Tr_velo_to_cam: ...``) or as the JSON of the shared sample (``P2_3x4``, ``R0_rect_3x3``,
``Tr_velo_to_cam_3x4``, optional ``image_size_wh`` and ``lidar_to_image_4x4``).

Output conventions (`Frame`): ego := Velodyne frame (``T_ego_lidar`` = identity); reflectance kept on 0..1 with
``intensity_max = 1.0``; ring derived from the point elevation with the nominal HDL-64E table. The camera pose
folds the stereo-baseline column of ``P2`` into the extrinsics, so that ``K @ inv(T_ego_cam)[:3]`` equals
``P2 @ R0_rect @ Tr_velo_to_cam`` exactly.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from weatheralign.data.errors import DataFormatError, read_float32_records, require_file, validate_scan
from weatheralign.data.frame import CameraView, Frame, LidarScan, read_image_size
from weatheralign.data.rings import HDL64E_ELEVATIONS_DEG, rings_from_elevation
from weatheralign.geometry import NonRigidTransformError, check_rigid

F64 = NDArray[np.float64]

_JSON_KEYS = {"P2": "P2_3x4", "R0_rect": "R0_rect_3x3", "Tr_velo_to_cam": "Tr_velo_to_cam_3x4"}
_SHAPES = {"P2": (3, 4), "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4)}


@dataclass(frozen=True)
class KittiCalib:
    """KITTI object calibration for camera 2.

    Attributes:
        P2: (3, 4) projection rectified camera-0 coordinates -> image_2 pixels (4th column = stereo baseline).
        R0_rect: (3, 3) rotation camera 0 -> rectified camera 0.
        T_cam0_velo: (4, 4) rigid Velodyne -> (unrectified) camera 0, from ``Tr_velo_to_cam`` [m].
        image_size: (width, height) [px] when the calibration states it, else None.
        path: the calibration file.
    """

    P2: F64
    R0_rect: F64
    T_cam0_velo: F64
    image_size: tuple[int, int] | None
    path: Path

    @property
    def K(self) -> F64:
        """(3, 3) intrinsics of image_2 [px] (the left 3x3 block of ``P2``)."""
        return intrinsics_and_offset(self.P2, f"{self.path}: P2")[0]

    @property
    def T_cam_velo(self) -> F64:
        """(4, 4) rigid Velodyne -> image_2 camera (OpenCV axes), baseline of ``P2`` folded in [m]."""
        _, T_cam_rect = intrinsics_and_offset(self.P2, f"{self.path}: P2")
        R0 = np.eye(4)
        R0[:3, :3] = self.R0_rect
        return T_cam_rect @ R0 @ self.T_cam0_velo

    @property
    def lidar_to_image(self) -> F64:
        """(3, 4) ``P2 @ R0_rect @ Tr_velo_to_cam``: homogeneous Velodyne point -> homogeneous pixel."""
        R0 = np.eye(4)
        R0[:3, :3] = self.R0_rect
        return self.P2 @ R0 @ self.T_cam0_velo


def intrinsics_and_offset(P: NDArray, what: str) -> tuple[F64, F64]:
    """Split a pinhole projection ``P = K [I | t]`` (3, 4) into ``K`` (3, 3) and the rigid shift ``[I | t]`` (4, 4).

    ``t = K^-1 P[:, 3]`` [m] is the camera position offset of a rectified stereo camera (KITTI ``P2``/``P3``,
    ROS ``CameraInfo.P``), so ``K @ [I | t] = P`` exactly.

    Raises:
        DataFormatError: ``P`` is not (3, 4), not finite, or its left block is not an upper-triangular ``K`` with
            ``K[2] = [0, 0, 1]`` and positive focal lengths.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (3, 4) or not np.all(np.isfinite(P)):
        raise DataFormatError(f"{what}: expected a finite 3x4 projection matrix, got shape {P.shape}")
    K = P[:, :3].copy()
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[1, 0]) > 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataFormatError(
            f"{what}: expected K [I | t] with K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]], fx, fy > 0; got {P.tolist()}"
        )
    T = np.eye(4)
    T[:3, 3] = np.linalg.solve(K, P[:, 3])
    return K, T


def _matrix(values: object, shape: tuple[int, int], path: Path, key: str) -> F64:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: {key} is not numeric ({exc}); expected {shape[0]}x{shape[1]} numbers") from exc
    if arr.size != shape[0] * shape[1] or not np.all(np.isfinite(arr)):
        raise DataFormatError(
            f"{path}: {key} has {arr.size} values (finite: {bool(np.all(np.isfinite(arr)))}); "
            f"expected {shape[0] * shape[1]} finite numbers ({shape[0]}x{shape[1]} row-major)"
        )
    return arr.reshape(shape)


def _rigid(T3x4: F64, path: Path, key: str) -> F64:
    T = np.eye(4)
    T[:3] = T3x4
    try:
        return check_rigid(T, f"{path}: {key}")
    except NonRigidTransformError as exc:
        raise DataFormatError(f"{exc}; expected a rigid [R | t] with R orthonormal, det +1") from exc


def _read_txt_entries(path: Path) -> dict[str, list[float]]:
    entries: dict[str, list[float]] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DataFormatError(f"{path}:{lineno}: expected 'KEY: v1 v2 ...', got {line.strip()[:80]!r}")
        try:
            entries[key.strip()] = [float(v) for v in rest.split()]
        except ValueError as exc:
            raise DataFormatError(f"{path}:{lineno}: {key.strip()} has a non-numeric value ({exc})") from exc
    return entries


def read_kitti_calib(path: Path) -> KittiCalib:
    """Read a KITTI object calibration (``.txt`` ``KEY: values`` lines, or the ``.json`` of the shared sample).

    Returns:
        `KittiCalib` with ``P2`` (3, 4), ``R0_rect`` (3, 3) and the rigid ``T_cam0_velo`` (4, 4).

    Raises:
        DataFormatError: missing file or key, wrong value count, non-rigid ``Tr_velo_to_cam``/``R0_rect``, or a
            JSON ``lidar_to_image_4x4`` that disagrees with ``P2 @ R0_rect @ Tr_velo_to_cam``.
    """
    path = require_file(Path(path), "KITTI calibration")
    image_size: tuple[int, int] | None = None
    stated_l2i: object = None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(data, dict):
            raise DataFormatError(f"{path}: expected a JSON object with keys {sorted(_JSON_KEYS.values())}")
        raw: dict[str, object] = {}
        for name, key in _JSON_KEYS.items():
            if key not in data:
                raise DataFormatError(f"{path}: missing calibration key {key!r} (expected a {_SHAPES[name]} matrix)")
            raw[name] = data[key]
        if "image_size_wh" in data:
            wh = _matrix(data["image_size_wh"], (1, 2), path, "image_size_wh")[0]
            image_size = (int(wh[0]), int(wh[1]))
        stated_l2i = data.get("lidar_to_image_4x4")
        names = dict(_JSON_KEYS)
    else:
        entries = _read_txt_entries(path)
        raw = {}
        for name in _JSON_KEYS:
            if name not in entries:
                raise DataFormatError(
                    f"{path}: missing calibration key {name!r} (expected a line '{name}: ' + "
                    f"{_SHAPES[name][0] * _SHAPES[name][1]} numbers)"
                )
            raw[name] = entries[name]
        names = {name: name for name in _JSON_KEYS}
    P2 = _matrix(raw["P2"], _SHAPES["P2"], path, names["P2"])
    intrinsics_and_offset(P2, f"{path}: {names['P2']}")
    R0 = _matrix(raw["R0_rect"], _SHAPES["R0_rect"], path, names["R0_rect"])
    _rigid(np.hstack([R0, np.zeros((3, 1))]), path, names["R0_rect"])
    T_cam0_velo = _rigid(_matrix(raw["Tr_velo_to_cam"], (3, 4), path, names["Tr_velo_to_cam"]), path,
                         names["Tr_velo_to_cam"])
    calib = KittiCalib(P2=P2, R0_rect=R0, T_cam0_velo=T_cam0_velo, image_size=image_size, path=path)
    if stated_l2i is not None:
        stated = _matrix(stated_l2i, (4, 4), path, "lidar_to_image_4x4")
        ours = calib.lidar_to_image
        # The sample's stored product carries float32-level rounding (~3e-8 relative); anything larger is a mismatch.
        if not np.allclose(stated[:3], ours, rtol=0.0, atol=1e-6 * float(np.abs(ours).max())):
            raise DataFormatError(
                f"{path}: lidar_to_image_4x4 disagrees with P2 @ R0_rect @ Tr_velo_to_cam "
                f"(max abs difference {float(np.abs(stated[:3] - ours).max()):.3g}); expected their product"
            )
    return calib


KITTI_INTENSITY_MAX = 1.0
"""KITTI's declared reflectance scale (0..1)."""

KITTI_FIELDS = ("x", "y", "z", "reflectance")


def read_kitti_points(path: Path) -> NDArray[np.float32]:
    """(N, 5) float32 ``x, y, z`` [m], reflectance on 0..1, ring (from elevation, HDL-64E table) of a KITTI ``.bin``.

    Raises:
        DataFormatError: missing file, size not a multiple of 16 bytes, an empty scan, NaN/inf coordinates or
            reflectances, reflectance outside 0..1 (`weatheralign.data.errors.validate_scan` with KITTI's scale).
    """
    raw = read_float32_records(Path(path), 4, "KITTI velodyne scan")
    validate_scan(raw, path, intensity_max=KITTI_INTENSITY_MAX, num_rings=None, fields=KITTI_FIELDS)
    points = np.empty((len(raw), 5), dtype=np.float32)
    points[:, :4] = raw
    points[:, 4] = rings_from_elevation(raw[:, :3], HDL64E_ELEVATIONS_DEG)
    return points


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) [px] of an image file, decoded in full (`weatheralign.data.frame.read_image_size`).

    Raises:
        DataFormatError: missing file, or truncated / not a valid JPEG/PNG image.
    """
    return read_image_size(Path(path), what)


def load_kitti_frame(velodyne_bin: Path, image: Path | None, calib_json: Path) -> Frame:
    """Load one KITTI object frame as a `Frame` (``source="kitti"``).

    Args:
        velodyne_bin: float32 N x 4 scan ``(x, y, z, reflectance 0..1)``.
        image: the ``image_2`` PNG, or None for a LiDAR-only frame (no camera).
        calib_json: calibration, ``.json`` (shared-sample keys) or standard ``.txt``.

    Returns:
        Frame with ``LidarScan(points (N, 5), intensity_max=1.0, num_rings=64, T_ego_lidar=I)`` and, with an image,
        one `CameraView` ``image_2`` (K from ``P2``, ``T_ego_cam = inv(T_cam_velo)``, size of the actual image), so that
        ``K @ inv(T_ego_cam)[:3] == P2 @ R0_rect @ Tr_velo_to_cam`` up to float64 rounding.

    Raises:
        DataFormatError: bad scan, missing image, calibration errors, image size differing from the calibration.
    """
    velodyne_bin = Path(velodyne_bin)
    calib = read_kitti_calib(Path(calib_json))
    points = read_kitti_points(velodyne_bin)
    lidar = LidarScan(
        points=points,
        timestamp=0.0,
        T_ego_lidar=np.eye(4),
        T_global_ego=np.eye(4),
        intensity_max=KITTI_INTENSITY_MAX,
        num_rings=64,
        path=velodyne_bin,
    )
    cameras: dict[str, CameraView] = {}
    if image is not None:
        width, height = image_size(Path(image), "KITTI image_2")
        if calib.image_size is not None and calib.image_size != (width, height):
            raise DataFormatError(
                f"{image}: image is {width}x{height}, {calib.path} says image_size_wh {calib.image_size}"
            )
        cameras["image_2"] = CameraView(
            channel="image_2",
            image_path=Path(image),
            K=calib.K,
            width=width,
            height=height,
            # exact matrix inverse: Tr_velo_to_cam is only orthonormal to ~1e-7 (float32 values), and the transpose
            # inverse would shift projections by ~1e-6 px against P2 @ R0_rect @ Tr_velo_to_cam
            T_ego_cam=np.linalg.inv(calib.T_cam_velo),
            T_global_ego=np.eye(4),
            timestamp=0.0,
        )
    return Frame(token=velodyne_bin.stem, timestamp=0.0, lidar=lidar, cameras=cameras, source="kitti")
