"""Frames from any nuScenes-format dataroot (real nuScenes, nuScenes-mini, or the synthetic world), via the devkit.

LiDAR timing convention (nuScenes): the sensor spins clockwise seen from above starting at the ego's left (+y), and
a sweep's timestamp is the end of its rotation; nuScenes scans are ego-motion compensated to that timestamp. Where a
dataset ships no per-point firing times (real nuScenes), they are derived from each point's azimuth.
"""

from __future__ import annotations

import io
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from nuscenes.nuscenes import NuScenes
from pyquaternion import Quaternion

from weatheralign.data.errors import DataFormatError, read_float32_records, resolve_inside
from weatheralign.data.frame import Box, CameraView, Frame, LidarScan
from weatheralign.geometry import NonRigidTransformError, apply, check_rigid, invert, transform_from_quaternion

CAMERA_CHANNELS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
SWEEP_START_AZIMUTH = np.pi / 2  # ego +y (left)
SWEEP_PERIOD_S = 0.05  # 20 Hz
TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
          "scene", "sample", "sample_data", "sample_annotation", "map")


def sweep_fraction_at_azimuth(azimuth: NDArray | float) -> NDArray:
    """Fraction (0..1) of a clockwise sweep starting at `SWEEP_START_AZIMUTH` at which it reaches ``azimuth``
    [rad, ego frame: 0 = forward, +pi/2 = left]."""
    return np.mod(SWEEP_START_AZIMUTH - np.asarray(azimuth), 2 * np.pi) / (2 * np.pi)


def open_nuscenes(dataroot: str | Path, version: str) -> NuScenes:
    """Open a dataroot with the devkit, first checking the layout so that errors name what is missing."""
    root = Path(dataroot)
    table_dir = root / version
    if not table_dir.is_dir():
        raise DataFormatError(f"{root}: no table folder {version}/ (expected <dataroot>/<version>/*.json)")
    missing = [t for t in TABLES if not (table_dir / f"{t}.json").is_file()]
    if missing:
        raise DataFormatError(f"{table_dir}: missing nuScenes tables {', '.join(m + '.json' for m in missing)}")
    with redirect_stdout(io.StringIO()):
        return NuScenes(version=version, dataroot=str(root), verbose=False)


def _transform(record: dict, what: str) -> NDArray[np.float64]:
    """``T`` (4, 4) of a record's ``rotation`` (unit quaternion w, x, y, z) and ``translation`` (3,) [m]."""
    try:
        q = np.asarray(record["rotation"], dtype=np.float64)
        t = np.asarray(record["translation"], dtype=np.float64)
        if q.shape != (4,) or t.shape != (3,) or not (np.isfinite(q).all() and np.isfinite(t).all()):
            raise ValueError(f"expected a finite rotation [w, x, y, z] and translation [x, y, z], got {q.tolist()}, "
                             f"{t.tolist()}")
        if abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise ValueError(f"rotation quaternion has norm {np.linalg.norm(q):.6f}, expected a unit quaternion "
                             "(a non-rigid calibration)")
        return check_rigid(transform_from_quaternion(q, t), what)
    except (KeyError, TypeError, ValueError, NonRigidTransformError) as err:
        raise DataFormatError(f"{what}: invalid rotation/translation: {err}") from None


def derived_time_offsets(points: NDArray, T_ego_lidar: NDArray, period: float = SWEEP_PERIOD_S) -> NDArray[np.float32]:
    """(N,) firing time relative to the scan timestamp [s] (<= 0), from each point's azimuth in the ego frame."""
    p = points[:, :3].astype(np.float64) @ T_ego_lidar[:3, :3].T  # directions from the sensor, ego axes
    frac = sweep_fraction_at_azimuth(np.arctan2(p[:, 1], p[:, 0]))
    return ((frac - 1.0) * period).astype(np.float32)


def extras_relpath(filename: str) -> str:
    """Relative path of the synthetic world's extras of a sensor file (not part of the nuScenes format):
    for a scan, per-point records (firing time, column, actor id, material) ``extras/<channel>/<stem>.npy``; for an
    image, the exact per-pixel ray length [m] (float16, inf = sky) ``extras/range/<channel>/<stem>.npy``."""
    parts = Path(filename).parts
    channel, stem = parts[1], parts[-1].split(".")[0]
    if channel.startswith("CAM"):
        return f"extras/range/{channel}/{stem}.npy"
    return f"extras/{channel}/{stem}.npy"


def _read_scan(nusc: NuScenes, sd: dict) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray, NDArray]:
    root = Path(nusc.dataroot)
    path = resolve_inside(root, sd["filename"], f"sample_data {sd['token']}")
    points = read_float32_records(path, 5)
    T_ego_lidar = _transform(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"]),
                             f"calibrated_sensor of {sd['filename']}")
    T_global_ego = _transform(nusc.get("ego_pose", sd["ego_pose_token"]), f"ego_pose of {sd['filename']}")
    extras = root / extras_relpath(sd["filename"])
    if extras.is_file():
        ex = np.load(extras)
        if len(ex) != len(points):
            raise DataFormatError(f"{extras}: {len(ex)} records for {len(points)} points in {path}")
        offsets = ex["time_offset"].astype(np.float32)
    else:
        offsets = derived_time_offsets(points, T_ego_lidar)
    return points, offsets, T_ego_lidar, T_global_ego


def load_lidar(nusc: NuScenes, sample_data_token: str, nsweeps: int = 1) -> LidarScan:
    """A LiDAR scan with ``nsweeps`` sweeps (the given one and earlier ones via ``prev``), every earlier sweep
    transformed into this scan's sensor frame through the global frame (ego-motion compensation)."""
    if nsweeps < 1:
        raise ValueError(f"nsweeps must be >= 1, got {nsweeps}")
    sd = nusc.get("sample_data", sample_data_token)
    points, offsets, T_ego_lidar, T_global_ego = _read_scan(nusc, sd)
    t_ref = sd["timestamp"] * 1e-6
    T_lidar_global = invert(T_global_ego @ T_ego_lidar)
    all_pts, all_off, all_idx = [points], [offsets], [np.zeros(len(points), np.int16)]
    pose_times, poses = [t_ref], [T_global_ego]
    cur = sd
    for k in range(1, nsweeps + 1):
        if not cur["prev"]:
            break
        cur = nusc.get("sample_data", cur["prev"])
        pose_times.insert(0, cur["timestamp"] * 1e-6)
        if k >= nsweeps:  # only its pose is needed, for per-point poses within the oldest sweep
            poses.insert(0, _transform(nusc.get("ego_pose", cur["ego_pose_token"]), f"ego_pose of {cur['filename']}"))
            break
        p_k, off_k, T_el_k, T_ge_k = _read_scan(nusc, cur)
        poses.insert(0, T_ge_k)
        T = T_lidar_global @ T_ge_k @ T_el_k
        xyz = apply(T, p_k[:, :3])
        p_k = np.column_stack([xyz, p_k[:, 3:]]).astype(np.float32)
        all_pts.append(p_k)
        all_off.append((off_k + np.float32(cur["timestamp"] * 1e-6 - t_ref)).astype(np.float32))
        all_idx.append(np.full(len(p_k), k, np.int16))
    return LidarScan(
        points=np.concatenate(all_pts), timestamp=t_ref, T_ego_lidar=T_ego_lidar, T_global_ego=T_global_ego,
        intensity_max=255.0, num_rings=32, time_offsets=np.concatenate(all_off),
        sweep_index=np.concatenate(all_idx) if nsweeps > 1 else None,
        pose_times=np.array(pose_times), poses=np.stack(poses), path=Path(nusc.dataroot) / sd["filename"])


def load_camera(nusc: NuScenes, sample_data_token: str) -> CameraView:
    """A camera view: image path, intrinsics, extrinsics and ego pose at its own timestamp."""
    sd = nusc.get("sample_data", sample_data_token)
    root = Path(nusc.dataroot)
    path = resolve_inside(root, sd["filename"], f"sample_data {sd['token']}")
    if not path.is_file():
        raise DataFormatError(f"sample_data {sd['token']}: missing sensor file {path}")
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    K = np.asarray(cs.get("camera_intrinsic") or [], dtype=np.float64)
    if K.shape != (3, 3):
        raise DataFormatError(f"calibrated_sensor {cs['token']}: camera_intrinsic must be 3x3, got shape {K.shape}")
    channel = path.parent.name
    rng_file = root / extras_relpath(sd["filename"])
    return CameraView(channel=channel, image_path=path, K=K, width=int(sd["width"]), height=int(sd["height"]),
                      T_ego_cam=_transform(cs, f"calibrated_sensor of {sd['filename']}"),
                      T_global_ego=_transform(nusc.get("ego_pose", sd["ego_pose_token"]), f"ego_pose of {sd['filename']}"),
                      timestamp=sd["timestamp"] * 1e-6, range_path=rng_file if rng_file.is_file() else None)


def load_boxes(nusc: NuScenes, sample: dict) -> tuple[Box, ...]:
    """The sample's annotations as global-frame `Box` es (velocity from the devkit's neighbouring annotations)."""
    boxes = []
    for ann_token in sample["anns"]:
        ann = nusc.get("sample_annotation", ann_token)
        inst = nusc.get("instance", ann["instance_token"])
        category = nusc.get("category", inst["category_token"])["name"]
        attrs = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
        q = Quaternion(ann["rotation"])
        boxes.append(Box(token=ann_token, instance_token=ann["instance_token"], category=category,
                         center=np.asarray(ann["translation"], float), size=np.asarray(ann["size"], float),
                         yaw=float(q.yaw_pitch_roll[0]), velocity=np.asarray(nusc.box_velocity(ann_token), float),
                         num_lidar_pts=int(ann["num_lidar_pts"]), attribute=attrs[0] if attrs else "",
                         visibility=str(ann["visibility_token"])))
    return tuple(boxes)


def load_frame(nusc: NuScenes, sample_token: str, nsweeps: int = 1,
               cameras: tuple[str, ...] = CAMERA_CHANNELS) -> Frame:
    """The `Frame` of one sample: LiDAR (``nsweeps`` aggregated), the requested cameras, the boxes."""
    sample = nusc.get("sample", sample_token)
    lidar = load_lidar(nusc, sample["data"]["LIDAR_TOP"], nsweeps)
    views = {}
    for ch in cameras:
        if ch not in sample["data"]:
            raise DataFormatError(f"sample {sample_token}: no {ch} sample_data (channels: {sorted(sample['data'])})")
        views[ch] = load_camera(nusc, sample["data"][ch])
    return Frame(token=sample_token, timestamp=sample["timestamp"] * 1e-6, lidar=lidar, cameras=views,
                 boxes=load_boxes(nusc, sample), source="nuscenes")
