"""Seeing Through Fog (DENSE) frame reader: Velodyne HDL-64E S3 + rectified stereo-left camera.

Layouts (both accepted, nested first):
    nested (the real dataset): ``<root>/lidar_hdl64_strongest/<recording>_<frame>.bin``,
        ``<root>/cam_stereo_left_lut/<recording>_<frame>.png``;
    flat (the shared sample): ``<root>/lidar_hdl64_strongest_<recording>_<frame>.bin``,
        ``<root>/cam_stereo_left_lut_<recording>_<frame>.png``.
Calibration: ``calib_cam_stereo_left.json`` (ROS CameraInfo of the 1920 x 1024 camera) and ``calib_tf_tree_full.json``
(list of ROS ``TransformStamped``), in ``<root>``, ``<root>/calib`` or ``<root>/calibs``.

Extrinsics: a tf entry with ``header.frame_id = parent`` and ``child_frame_id = child`` holds the pose of the child
in the parent (ROS convention), i.e. ``T_parent_child`` with ``p_parent = R p_child + t``; the rotation is stored as a
named quaternion ``{x, y, z, w}``. Both sensors hang off ``body``:
``T_lidar_cam = inv(T_body_lidar_hdl64_s3_roof) @ T_body_cam_stereo_left_optical``.

Intrinsics: the ``_lut`` images are rectified, so ``K`` is the left 3x3 block of ``P`` (ROS convention for rectified
images, as in the dataset's own projection tools); the raw ``K``/``D`` and the rectifying rotation ``R`` are not used.

Ring order: the stored channel is kept as the ring, and STF channels count *upwards*: for points beyond 8 m the
median elevation rises monotonically with the channel (channel 1 ~ -24 deg ... channel 63 ~ +2.7 deg on the shared
sample). This is the reverse of the ring-0-is-highest order of `weatheralign.data.rings`; use ``63 - ring`` where
that order is needed.

Crops: the calibration describes the full 1920 x 1024 image. A stored image of another size is a crop, and ``K`` is
shifted by the crop origin ``(x0, y0)``: ``cx' = cx - x0``, ``cy' = cy - y0``. The origin is either given by the caller
(``crop_offset``) or looked up by image size in `STF_KNOWN_CROP_OFFSETS`; an unknown size is an error, never guessed.
The one known crop, 1792 x 768 (the image shipped with the dataset's foggification example), is ``(64, 192)``:
64 px cut from the left, right and bottom and 192 px from the top. It was measured on that sample by projecting the
scan: tram-rail and curb points land on the rails and curb in the image, and a depth-edge / image-gradient alignment
score peaks within ~15 px of that origin (and drops clearly at ``y0`` = 128 or 256).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from weatheralign.data.errors import DataFormatError, read_float32_records, require_file, resolve_inside, validate_scan
from weatheralign.data.frame import CameraView, Frame, LidarScan
from weatheralign.data.kitti import image_size, intrinsics_and_offset
from weatheralign.geometry import NonRigidTransformError, check_rigid, invert

F64 = NDArray[np.float64]

CAMERA_CALIB_FILE = "calib_cam_stereo_left.json"
TF_TREE_FILE = "calib_tf_tree_full.json"
CALIB_DIRS = ("", "calib", "calibs")
LIDAR_TF_FRAME = "lidar_hdl64_s3_roof"
CAMERA_TF_FRAME = "cam_stereo_left_optical"
CAMERA_CHANNEL = "cam_stereo_left"
HDL64_RINGS = 64
STF_FIELDS = ("x", "y", "z", "intensity", "channel")

STF_CALIBRATED_SIZE: tuple[int, int] = (1920, 1024)
"""(width, height) [px] of the stereo-left image that ``calib_cam_stereo_left.json`` describes."""

STF_KNOWN_CROP_OFFSETS: Mapping[tuple[int, int], tuple[int, int]] = MappingProxyType({(1792, 768): (64, 192)})
"""Stored image (width, height) -> crop origin (x0, y0) [px] inside the 1920 x 1024 calibrated image."""

_FRAME_RE = re.compile(r"^\d{1,5}$")
_RECORDING_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")


@dataclass(frozen=True)
class StfCameraCalib:
    """Stereo-left calibration.

    Attributes:
        K: (3, 3) rectified intrinsics [px] for the full calibrated image.
        width, height: calibrated image size [px].
        T_lidar_cam: (4, 4) rigid camera (OpenCV optical axes) -> HDL-64 LiDAR [m].
    """

    K: F64
    width: int
    height: int
    T_lidar_cam: F64


def _key(obj: Any, key: str, path: Path, where: str) -> Any:
    if not isinstance(obj, dict) or key not in obj:
        raise DataFormatError(f"{path}: {where}: missing calibration key {key!r}")
    return obj[key]


def _number(obj: Any, key: str, path: Path, where: str) -> float:
    value = _key(obj, key, path, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise DataFormatError(f"{path}: {where}.{key} = {value!r}; expected a finite number")
    return float(value)


def _load_json(path: Path, what: str) -> Any:
    path = require_file(path, what)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: {what} is not valid JSON ({exc})") from exc


def find_stf_calibration(root: Path) -> tuple[Path, Path]:
    """(camera calib, tf tree) JSON paths, searched in ``root``, ``root/calib`` and ``root/calibs``.

    Raises:
        DataFormatError: a file is in none of those folders.
    """
    found: list[Path] = []
    for name in (CAMERA_CALIB_FILE, TF_TREE_FILE):
        candidates = [Path(root) / d / name for d in CALIB_DIRS]
        hit = next((c for c in candidates if c.is_file()), None)
        if hit is None:
            raise DataFormatError(f"STF calibration: missing {name}; looked for {', '.join(map(str, candidates))}")
        found.append(hit)
    return found[0], found[1]


def read_tf_tree(path: Path) -> dict[str, tuple[str, F64]]:
    """Parse a tf-tree JSON (list of ROS TransformStamped) -> ``{child: (parent, T_parent_child (4, 4))}``.

    Raises:
        DataFormatError: not a list, missing keys, non-unit quaternion, a child listed twice.
    """
    path = Path(path)
    data = _load_json(path, "tf tree")
    if not isinstance(data, list):
        raise DataFormatError(
            f"{path}: expected a JSON list of transforms (header.frame_id, child_frame_id, transform)"
        )
    tree: dict[str, tuple[str, F64]] = {}
    for i, entry in enumerate(data):
        where = f"entry {i}"
        parent = _key(_key(entry, "header", path, where), "frame_id", path, f"{where}.header")
        child = _key(entry, "child_frame_id", path, where)
        transform = _key(entry, "transform", path, where)
        tr = _key(transform, "translation", path, f"{where}.transform")
        rot = _key(transform, "rotation", path, f"{where}.transform")
        t = [_number(tr, k, path, f"{where} ({child}).translation") for k in "xyz"]
        q = np.array([_number(rot, k, path, f"{where} ({child}).rotation") for k in "xyzw"])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise DataFormatError(f"{path}: {where} ({parent} -> {child}): rotation quaternion norm {norm:.6f}; "
                                  f"expected a unit quaternion {{x, y, z, w}}")
        if child in tree:
            raise DataFormatError(f"{path}: frame {child!r} has two parents ({tree[child][0]!r}, {parent!r})")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
        T[:3, 3] = t
        tree[str(child)] = (str(parent), T)
    return tree


def _chain_to_root(tree: Mapping[str, tuple[str, F64]], frame: str, path: Path) -> tuple[str, F64]:
    """(root frame, ``T_root_frame``) by composing parent transforms up the tree."""
    T = np.eye(4)
    seen = {frame}
    while frame in tree:
        parent, T_parent_frame = tree[frame]
        T = T_parent_frame @ T
        if parent in seen:
            raise DataFormatError(f"{path}: the tf tree has a cycle through {parent!r}")
        seen.add(parent)
        frame = parent
    return frame, T


def tf_transform(tree: Mapping[str, tuple[str, F64]], target: str, source: str, path: Path) -> F64:
    """``T_target_source`` (4, 4): maps points in ``source`` coordinates to ``target`` coordinates.

    Raises:
        DataFormatError: a frame is missing, the frames are not connected, or the result is not rigid.
    """
    known = set(tree) | {parent for parent, _ in tree.values()}
    for frame in (target, source):
        if frame not in known:
            raise DataFormatError(f"{path}: missing calibration key: tf frame {frame!r} (known: {sorted(known)})")
    root_t, T_root_target = _chain_to_root(tree, target, path)
    root_s, T_root_source = _chain_to_root(tree, source, path)
    if root_t != root_s:
        raise DataFormatError(f"{path}: tf frames {target!r} (root {root_t!r}) and {source!r} (root {root_s!r}) "
                              f"are not connected")
    try:
        return check_rigid(invert(T_root_target) @ T_root_source, f"{path}: T_{target}_{source}")
    except NonRigidTransformError as exc:
        raise DataFormatError(f"{exc}; expected a rigid transform") from exc


def read_stf_camera_calib(camera_json: Path, tf_tree_json: Path) -> StfCameraCalib:
    """Stereo-left intrinsics (from ``P``) and the camera -> LiDAR transform (from the tf tree).

    Raises:
        DataFormatError: missing files/keys, bad ``P``, non-rigid or disconnected transforms.
    """
    camera_json = Path(camera_json)
    cam = _load_json(camera_json, "STF camera calibration")
    P_values = _key(cam, "P", camera_json, "camera info")
    try:
        P = np.asarray(P_values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{camera_json}: P is not numeric ({exc}); expected 12 numbers (3x4 row-major)") from exc
    if P.size != 12:
        raise DataFormatError(f"{camera_json}: P has {P.size} values; expected 12 (3x4 row-major)")
    K, T_cam_rect = intrinsics_and_offset(P.reshape(3, 4), f"{camera_json}: P")
    width = int(_number(cam, "width", camera_json, "camera info"))
    height = int(_number(cam, "height", camera_json, "camera info"))
    if width <= 0 or height <= 0:
        raise DataFormatError(f"{camera_json}: image size {width}x{height}; expected positive width and height")
    tf_tree_json = Path(tf_tree_json)
    tree = read_tf_tree(tf_tree_json)
    T_cam_lidar = T_cam_rect @ tf_transform(tree, CAMERA_TF_FRAME, LIDAR_TF_FRAME, tf_tree_json)
    return StfCameraCalib(K=K, width=width, height=height, T_lidar_cam=invert(T_cam_lidar))


def stf_crop_offset(stored_size: tuple[int, int], calibrated_size: tuple[int, int]) -> tuple[int, int]:
    """Crop origin (x0, y0) [px] of a stored image of ``stored_size`` (w, h) inside the calibrated image.

    (0, 0) when the sizes agree; otherwise the entry of `STF_KNOWN_CROP_OFFSETS` (valid for the 1920 x 1024
    calibration only).

    Raises:
        DataFormatError: the size is not a known crop of this calibration (pass ``crop_offset`` explicitly).
    """
    if tuple(stored_size) == tuple(calibrated_size):
        return (0, 0)
    if tuple(calibrated_size) == STF_CALIBRATED_SIZE and tuple(stored_size) in STF_KNOWN_CROP_OFFSETS:
        return STF_KNOWN_CROP_OFFSETS[tuple(stored_size)]
    raise DataFormatError(
        f"STF image is {stored_size[0]}x{stored_size[1]} but the calibration is for "
        f"{calibrated_size[0]}x{calibrated_size[1]} and this is not a known crop "
        f"({dict(STF_KNOWN_CROP_OFFSETS)}); pass crop_offset=(x0, y0) explicitly"
    )


def crop_intrinsics(K: F64, x0: float, y0: float) -> F64:
    """(3, 3) intrinsics of a crop whose top-left pixel is ``(x0, y0)`` of the image ``K`` (3, 3) describes."""
    out = np.array(K, dtype=np.float64)
    out[0, 2] -= x0
    out[1, 2] -= y0
    return out


def find_sensor_file(root: Path, folder: str, sample_id: str, suffix: str, what: str) -> Path:
    """``root/<folder>/<sample_id><suffix>`` (nested layout) or else ``root/<folder>_<sample_id><suffix>`` (flat).

    Raises:
        DataFormatError: neither exists, or the name escapes ``root``.
    """
    nested = resolve_inside(root, f"{folder}/{sample_id}{suffix}", what)
    flat = resolve_inside(root, f"{folder}_{sample_id}{suffix}", what)
    for candidate in (nested, flat):
        if candidate.is_file():
            return candidate
    raise DataFormatError(f"{what}: missing sensor file for sample {sample_id!r}; looked for {nested} and {flat}")


def read_stf_points(path: Path, num_rings: int = HDL64_RINGS, intensity_max: float = 255.0) -> NDArray[np.float32]:
    """(N, 5) float32 ``x, y, z`` [m], intensity, ring (= laser channel, float) from an STF LiDAR ``.bin``.

    Args:
        path: the ``.bin`` file (float32 x 5 per point).
        num_rings: number of laser channels (64 for the HDL-64).
        intensity_max: the declared intensity scale of the file, 255 (Seeing Through Fog) or 1.0 (a 0..1 copy);
            intensities are returned as stored, on ``0..intensity_max``.

    Raises:
        DataFormatError: missing file, size not a multiple of 20 bytes, an empty scan, NaN/inf coordinates or
            intensities, intensity outside ``0..intensity_max`` (e.g. a 0..255 scan declared as 0..1), every intensity
            <= 1.0 in a scan declared 0..255 (a 0..1 scan on the wrong scale), or a channel that is not an integer in
            ``0..num_rings-1`` (`weatheralign.data.errors.validate_scan`).
    """
    if intensity_max not in (1.0, 255.0):
        raise DataFormatError(f"{path}: intensity_max = {intensity_max!r}; expected the declared scale 255 or 1.0")
    points = read_float32_records(Path(path), 5, "STF LiDAR scan")
    validate_scan(points, path, intensity_max=float(intensity_max), num_rings=num_rings, fields=STF_FIELDS)
    return np.ascontiguousarray(points, dtype=np.float32)


def read_stf_split(path: Path) -> list[str]:
    """Sample ids ``<recording>_<frame>`` (frame zero-padded to 5 digits) from a split file of ``recording,frame``
    lines; blank lines and ``#`` comments are skipped.

    Raises:
        DataFormatError: missing file, no sample at all, or a malformed line (file and line number named).
    """
    path = require_file(Path(path), "STF split file")
    ids: list[str] = []
    for lineno, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 2 or not _RECORDING_RE.match(fields[0]) or not _FRAME_RE.match(fields[1]):
            raise DataFormatError(
                f"{path}:{lineno}: malformed split line {line[:80]!r}; expected 'recording,frame' "
                f"(e.g. '2018-02-12_15-39-23,00100', frame = up to 5 digits)"
            )
        ids.append(f"{fields[0]}_{int(fields[1]):05d}")
    if not ids:
        raise DataFormatError(f"{path}: empty split (no 'recording,frame' lines)")
    return ids


def load_stf_frame(
    root: Path,
    sample_id: str,
    *,
    lidar_folder: str = "lidar_hdl64_strongest",
    camera_folder: str | None = "cam_stereo_left_lut",
    crop_offset: tuple[int, int] | None = None,
    intensity_max: float = 255.0,
) -> Frame:
    """Load one Seeing Through Fog frame as a `Frame` (``source="stf"``; ego := LiDAR frame).

    Args:
        root: dataset root (nested layout) or the folder of the flat sample files.
        sample_id: ``<recording>_<frame>``, e.g. ``2019-09-11_19-13-44_00960``.
        lidar_folder: an HDL-64 folder (``lidar_hdl64_strongest``, ``lidar_hdl64_last``, ...).
        camera_folder: a rectified stereo-left image folder (``cam_stereo_left_lut``...), or None for no camera.
        crop_offset: (x0, y0) [px] of the stored image inside the calibrated 1920 x 1024 image; None = derive it
            from the image size (full size -> (0, 0); a size in `STF_KNOWN_CROP_OFFSETS`; otherwise an error).
        intensity_max: declared intensity scale of the scans (255 for the dataset as shipped, 1.0 for a 0..1 copy).

    Returns:
        Frame with ``LidarScan(points (N, 5) float32 [x, y, z, intensity 0..intensity_max, ring = channel],
        num_rings=64, identity poses, timestamp 0)`` and a `CameraView` ``cam_stereo_left`` (K for the stored
        image, its actual width/height, ``T_ego_cam`` = camera -> LiDAR).

    Raises:
        DataFormatError: unsupported folder, missing sensor/calibration file, bad data or calibration.
    """
    root = Path(root)
    if not lidar_folder.startswith("lidar_hdl64"):
        raise DataFormatError(f"STF: unsupported lidar_folder {lidar_folder!r}; expected an HDL-64 folder "
                              f"(lidar_hdl64_strongest or lidar_hdl64_last)")
    bin_path = find_sensor_file(root, lidar_folder, sample_id, ".bin", "STF LiDAR scan")
    lidar = LidarScan(
        points=read_stf_points(bin_path, HDL64_RINGS, intensity_max),
        timestamp=0.0,
        T_ego_lidar=np.eye(4),
        T_global_ego=np.eye(4),
        intensity_max=float(intensity_max),
        num_rings=HDL64_RINGS,
        path=bin_path,
    )
    cameras: dict[str, CameraView] = {}
    if camera_folder is not None:
        if not camera_folder.startswith("cam_stereo_left_lut"):
            raise DataFormatError(f"STF: unsupported camera_folder {camera_folder!r}; expected the rectified "
                                  f"stereo-left images (cam_stereo_left_lut)")
        image_path = find_sensor_file(root, camera_folder, sample_id, ".png", "STF stereo-left image")
        calib = read_stf_camera_calib(*find_stf_calibration(root))
        width, height = image_size(image_path, "STF stereo-left image")
        x0, y0 = crop_offset if crop_offset is not None else stf_crop_offset((width, height),
                                                                             (calib.width, calib.height))
        if x0 < 0 or y0 < 0 or x0 + width > calib.width or y0 + height > calib.height:
            raise DataFormatError(f"{image_path}: a {width}x{height} crop at ({x0}, {y0}) does not fit in the "
                                  f"calibrated {calib.width}x{calib.height} image")
        cameras[CAMERA_CHANNEL] = CameraView(
            channel=CAMERA_CHANNEL,
            image_path=image_path,
            K=crop_intrinsics(calib.K, x0, y0),
            width=width,
            height=height,
            T_ego_cam=calib.T_lidar_cam,
            T_global_ego=np.eye(4),
            timestamp=0.0,
        )
    return Frame(token=sample_id, timestamp=0.0, lidar=lidar, cameras=cameras, source="stf")
