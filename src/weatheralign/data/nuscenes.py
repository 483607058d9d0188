"""Frames from any nuScenes-format dataroot (real nuScenes, nuScenes-mini, or the synthetic world), via the devkit.

LiDAR timing convention (nuScenes): the sensor spins clockwise seen from above starting at the ego's left (+y), and
a sweep's timestamp is the end of its rotation; nuScenes scans are ego-motion compensated to that timestamp. Where a
dataset ships no per-point firing times (real nuScenes), they are derived from each point's azimuth.
"""

from __future__ import annotations

import functools
import io
import json
import math
import zipfile
from collections.abc import Callable
from contextlib import redirect_stdout
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from nuscenes.nuscenes import NuScenes
from pyquaternion import Quaternion

from weatheralign.data.errors import DataFormatError, read_float32_records, resolve_inside, validate_scan
from weatheralign.data.frame import Box, CameraView, Frame, LidarScan
from weatheralign.geometry import NonRigidTransformError, apply, check_rigid, invert, transform_from_quaternion

CAMERA_CHANNELS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
SWEEP_START_AZIMUTH = np.pi / 2  # ego +y (left)
LIDAR_TOP_YAW = -np.pi / 2
"""nuScenes' LIDAR_TOP mounting about the ego's z axis [rad]: its x axis points right, its y axis forward (every
nuScenes log; the synthetic world mounts it the same way)."""
SWEEP_PERIOD_S = 0.05  # 20 Hz
TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
          "scene", "sample", "sample_data", "sample_annotation", "map")
NUSCENES_INTENSITY_MAX = 255.0
"""Declared intensity scale of nuScenes ``.pcd.bin`` scans (0..255)."""
NUSCENES_NUM_RINGS = 32
"""Rings of the nuScenes ``LIDAR_TOP`` (HDL-32E; the synthetic world's too): ring column 0..31."""
NUSCENES_FIELDS = ("x", "y", "z", "intensity", "ring")
"""The five float32 columns of a nuScenes scan."""

# Fields the devkit reads while indexing the tables (`NuScenes.__make_reverse_index__`), and its token references.
_INDEX_FIELDS: dict[str, tuple[str, ...]] = {
    "category": ("name",), "instance": ("category_token",), "sensor": ("modality", "channel"),
    "calibrated_sensor": ("sensor_token",), "sample_data": ("calibrated_sensor_token", "is_key_frame", "sample_token"),
    "sample_annotation": ("instance_token", "sample_token"), "map": ("log_tokens", "filename"),
}
_INDEX_REFERENCES: tuple[tuple[str, str, str], ...] = (
    ("instance", "category_token", "category"), ("calibrated_sensor", "sensor_token", "sensor"),
    ("sample_data", "calibrated_sensor_token", "calibrated_sensor"), ("sample_data", "sample_token", "sample"),
    ("sample_annotation", "instance_token", "instance"), ("sample_annotation", "sample_token", "sample"),
)


def sweep_fraction_at_azimuth(azimuth: NDArray | float) -> NDArray:
    """Fraction (0..1) of a clockwise sweep starting at `SWEEP_START_AZIMUTH` at which it reaches ``azimuth``
    [rad, ego frame: 0 = forward, +pi/2 = left]."""
    return np.mod(SWEEP_START_AZIMUTH - np.asarray(azimuth), 2 * np.pi) / (2 * np.pi)


def open_nuscenes(dataroot: str | Path, version: str) -> NuScenes:
    """Open a dataroot with the devkit, first checking the layout so that errors name what is missing.

    Raises:
        DataFormatError: a missing table folder or table; or, where the devkit fails, the first problem
            `check_tables` finds (invalid JSON with its position, a record without a ``token`` or a field the devkit
            indexes, a dangling token), else the devkit's own error with the table folder.
    """
    root = Path(dataroot)
    table_dir = root / version
    if not table_dir.is_dir():
        raise DataFormatError(f"{root}: no table folder {version}/ (expected <dataroot>/<version>/*.json)")
    missing = [t for t in TABLES if not (table_dir / f"{t}.json").is_file()]
    if missing:
        raise DataFormatError(f"{table_dir}: missing nuScenes tables {', '.join(m + '.json' for m in missing)}")
    try:
        with redirect_stdout(io.StringIO()):
            return NuScenes(version=version, dataroot=str(root), verbose=False)
    except Exception as exc:  # the devkit raises JSONDecodeError, KeyError, TypeError, IndexError, AssertionError...
        check_tables(root, version)
        raise DataFormatError(f"{table_dir}: the nuScenes devkit cannot load these tables "
                              f"({type(exc).__name__}: {exc})") from exc


@functools.lru_cache(maxsize=2)
def open_nuscenes_cached(dataroot: str, version: str, content_digest: str) -> NuScenes:
    """`open_nuscenes`, memoised per process: the read-only tables of a dataset opened once per worker process
    however many tasks it runs; ``content_digest`` (the dataset's manifest digest) is part of the key, so a changed
    dataset is opened anew."""
    del content_digest  # only keys the cache
    return open_nuscenes(dataroot, version)


def _load_table_json(path: Path, table: str) -> list[dict]:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno} "
                              f"(char {exc.pos}); expected a JSON list of {table} records") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path}: cannot read the {table} table ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, list):
        raise DataFormatError(f"{path}: the top level is a JSON {type(data).__name__}; expected a JSON list of "
                              f"{table} records")
    for i, record in enumerate(data):
        if not isinstance(record, dict):
            raise DataFormatError(f"{path}: {table} record {i} is a JSON {type(record).__name__}; expected an object")
        if not isinstance(record.get("token"), str):
            raise DataFormatError(f"{path}: {table} record {i}: missing field 'token' (or not a string); expected "
                                  f"every record to have a string token")
    return data


def check_tables(dataroot: str | Path, version: str) -> None:
    """Check what the devkit needs to index a dataroot's tables, naming the first problem.

    Every table must be valid JSON, a list of objects with a string ``token``; the fields the devkit indexes
    (`_INDEX_FIELDS`) must be present and their tokens must resolve; every log must have a map, whose mask file
    exists. Called by `open_nuscenes` when the devkit fails (it parses every table once more).

    Raises:
        DataFormatError: naming the table file, the record's token and the field (or the JSON error position).
    """
    root = Path(dataroot)
    table_dir = root / version
    tables = {t: _load_table_json(table_dir / f"{t}.json", t) for t in TABLES}
    tokens = {t: {r["token"] for r in records} for t, records in tables.items()}
    for table, fields in _INDEX_FIELDS.items():
        for record in tables[table]:
            for key in fields:
                if key not in record:
                    raise DataFormatError(f"{table_dir / (table + '.json')}: {table} {record['token']}: missing field "
                                          f"{key!r}")
    for table, key, target in _INDEX_REFERENCES:
        for record in tables[table]:
            value = record[key]
            if not isinstance(value, str) or value not in tokens[target]:
                raise DataFormatError(f"{table_dir / (table + '.json')}: {table} {record['token']}: {key} {value!r} "
                                      f"matches no record of {target}.json")
    map_path = table_dir / "map.json"
    if not tables["map"]:
        raise DataFormatError(f"{map_path}: no map records; expected at least one map with log_tokens")
    mapped: set = set()
    for record in tables["map"]:
        if not isinstance(record["log_tokens"], list):
            raise DataFormatError(f"{map_path}: map {record['token']}: field 'log_tokens' = "
                                  f"{record['log_tokens']!r}; expected a list of log tokens")
        mapped.update(t for t in record["log_tokens"] if isinstance(t, str))
        if not isinstance(record["filename"], str) or not (root / record["filename"]).is_file():
            raise DataFormatError(f"{map_path}: map {record['token']}: mask file {record['filename']!r} is missing "
                                  f"under {root}")
    for record in tables["log"]:
        if record["token"] not in mapped:
            raise DataFormatError(f"{table_dir / 'log.json'}: log {record['token']}: no map record lists it in "
                                  f"log_tokens ({map_path})")


# ------------------------------------------------------------------------------------------------ record access

_Check = tuple[Callable[[Any], bool], str]
IS_STRING: _Check = (lambda v: isinstance(v, str), "a string")
_TOKEN_OR_EMPTY: _Check = (lambda v: v is None or isinstance(v, str), "a token string ('' for none)")
_TIMESTAMP: _Check = (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
                      "a finite timestamp [microseconds]")
_PIXELS: _Check = (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                   and v == int(v) and v > 0, "a positive whole number of pixels")
IS_LIST: _Check = (lambda v: isinstance(v, list), "a JSON list")
IS_COUNT: _Check = (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                  and v == int(v) and v >= 0, "a non-negative integer")


def table_path(nusc: NuScenes, table: str) -> Path:
    return Path(nusc.table_root) / f"{table}.json"


def checked_get(nusc: NuScenes, table: str, token: Any, referrer: str) -> dict:
    """``nusc.get(table, token)``, or an error naming the table, the token and who refers to it."""
    try:
        return nusc.get(table, token)
    except (KeyError, TypeError):
        raise DataFormatError(f"{table_path(nusc, table)}: no {table} record with token {token!r} (referenced by "
                              f"{referrer})") from None


def checked_field(nusc: NuScenes, table: str, record: dict, key: str, check: _Check | None = None) -> Any:
    """``record[key]``, or an error naming the table, the record's token and the missing or malformed field."""
    if key not in record:
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {record.get('token', '?')}: missing field {key!r}")
    value = record[key]
    if check is not None and not check[0](value):
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {record.get('token', '?')}: field {key!r} = "
                              f"{value!r}; expected {check[1]}")
    return value


def checked_vector(nusc: NuScenes, table: str, record: dict, key: str, n: int) -> NDArray[np.float64]:
    value = checked_field(nusc, table, record, key)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.full(0, np.nan)
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {record.get('token', '?')}: field {key!r} = "
                              f"{value!r}; expected {n} finite numbers")
    return arr


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
    except KeyError as err:
        raise DataFormatError(f"{what}: missing field {err.args[0]!r}; expected a rotation [w, x, y, z] and a "
                              f"translation [x, y, z]") from None
    except (TypeError, ValueError, NonRigidTransformError) as err:
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


def compressed_extras_relpath(filename: str) -> str:
    """``extras/<channel>/<stem>.npz``: a scan's per-point records as a compressed ``.npz`` (one member per field),
    the form weather copies write; `read_point_extras` reads either form."""
    return str(Path(extras_relpath(filename)).with_suffix(".npz"))


def read_point_extras(root: Path, filename: str) -> NDArray | None:
    """A scan's per-point records (structured (N,) array: ``time_offset`` and whatever else the writer stored) from
    ``extras/<channel>/<stem>.npy`` or its compressed ``.npz`` form; None where the dataset has neither.

    Raises:
        DataFormatError: a file that is truncated or not a valid array (naming it).
    """
    for rel in (extras_relpath(filename), compressed_extras_relpath(filename)):
        path = Path(root) / rel
        if path.is_file():
            try:
                return read_record_file(path)
            except (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile) as exc:
                raise DataFormatError(f"{path}: not a valid per-point records file ({type(exc).__name__}: {exc}); "
                                      f"expected a structured .npy or an .npz of equal-length fields") from None
    return None


def read_record_file(path: Path) -> NDArray:
    """(N,) structured array from a ``.npy`` or from an ``.npz`` whose members are its fields (equal lengths)."""
    loaded = np.load(path, allow_pickle=False)
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        return loaded
    with loaded:
        fields = {name: loaded[name] for name in loaded.files}
    lengths = {len(a) for a in fields.values()}
    if len(lengths) != 1 or any(a.ndim != 1 for a in fields.values()):
        raise ValueError(f"members of unequal lengths or shapes: { {k: a.shape for k, a in fields.items()} }")
    out = np.empty(lengths.pop(), dtype=[(k, a.dtype) for k, a in fields.items()])
    for name, a in fields.items():
        out[name] = a
    return out


def _pose_record(nusc: NuScenes, sd: dict, table: str, key: str) -> tuple[dict, str]:
    """The ``calibrated_sensor`` / ``ego_pose`` record of ``sd`` and the label its transform's errors carry."""
    token = checked_field(nusc, "sample_data", sd, key, IS_STRING)
    record = checked_get(nusc, table, token, f"sample_data {sd['token']}.{key}")
    return record, f"{table} of {sd['filename']} ({table_path(nusc, table)}, token {token})"


def _read_scan(nusc: NuScenes, sd: dict) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray, NDArray]:
    root = Path(nusc.dataroot)
    filename = checked_field(nusc, "sample_data", sd, "filename", IS_STRING)
    path = resolve_inside(root, filename, f"sample_data {sd['token']}")
    points = read_float32_records(path, 5)
    validate_scan(points, path, intensity_max=NUSCENES_INTENSITY_MAX, num_rings=NUSCENES_NUM_RINGS,
                  fields=NUSCENES_FIELDS)
    T_ego_lidar = _transform(*_pose_record(nusc, sd, "calibrated_sensor", "calibrated_sensor_token"))
    T_global_ego = _transform(*_pose_record(nusc, sd, "ego_pose", "ego_pose_token"))
    extras = read_point_extras(root, filename)
    if extras is not None:
        where = root / extras_relpath(filename)
        if extras.dtype.names is None or "time_offset" not in extras.dtype.names:
            raise DataFormatError(f"{where} (.npy or .npz): no 'time_offset' field; expected per-point records "
                                  f"with a 'time_offset' field per point of {path}")
        offsets = extras["time_offset"].astype(np.float32)
        if len(extras) != len(points):
            raise DataFormatError(f"{where} (.npy or .npz): {len(extras)} records for {len(points)} points in "
                                  f"{path}")
        bad = ~np.isfinite(offsets)
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise DataFormatError(f"{where}: {int(bad.sum())} NaN/inf time offsets (field 'time_offset', first at "
                                  f"row {first}: {float(offsets[first])}); expected finite firing times [s] relative "
                                  f"to the scan timestamp")
    else:
        offsets = derived_time_offsets(points, T_ego_lidar)
    return points, offsets, T_ego_lidar, T_global_ego


def load_lidar(nusc: NuScenes, sample_data_token: str, nsweeps: int = 1) -> LidarScan:
    """A LiDAR scan with ``nsweeps`` sweeps (the given one and earlier ones via ``prev``), every earlier sweep
    transformed into this scan's sensor frame through the global frame (ego-motion compensation).

    Every sweep read is validated (`weatheralign.data.errors.validate_scan`: not empty, finite coordinates,
    intensities on 0..255 and not a 0..1 scan, rings 0..31).

    Raises:
        DataFormatError: a bad scan file (naming it, the field and the first bad row), or a missing or malformed
            table record or field (naming the table, the token and the field).
    """
    if nsweeps < 1:
        raise ValueError(f"nsweeps must be >= 1, got {nsweeps}")
    sd = checked_get(nusc, "sample_data", sample_data_token, "load_lidar")
    points, offsets, T_ego_lidar, T_global_ego = _read_scan(nusc, sd)
    t_ref = checked_field(nusc, "sample_data", sd, "timestamp", _TIMESTAMP) * 1e-6
    T_lidar_global = invert(T_global_ego @ T_ego_lidar)
    all_pts, all_off, all_idx = [points], [offsets], [np.zeros(len(points), np.int16)]
    pose_times, poses = [t_ref], [T_global_ego]
    cur = sd
    for k in range(1, nsweeps + 1):
        prev = checked_field(nusc, "sample_data", cur, "prev", _TOKEN_OR_EMPTY)
        if not prev:
            break
        cur = checked_get(nusc, "sample_data", prev, f"sample_data {cur['token']}.prev")
        pose_times.insert(0, checked_field(nusc, "sample_data", cur, "timestamp", _TIMESTAMP) * 1e-6)
        if k >= nsweeps:  # only its pose is needed, for per-point poses within the oldest sweep
            checked_field(nusc, "sample_data", cur, "filename", IS_STRING)
            poses.insert(0, _transform(*_pose_record(nusc, cur, "ego_pose", "ego_pose_token")))
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
        intensity_max=NUSCENES_INTENSITY_MAX, num_rings=NUSCENES_NUM_RINGS, time_offsets=np.concatenate(all_off),
        sweep_index=np.concatenate(all_idx) if nsweeps > 1 else None,
        pose_times=np.array(pose_times), poses=np.stack(poses), path=Path(nusc.dataroot) / sd["filename"])


def load_camera(nusc: NuScenes, sample_data_token: str) -> CameraView:
    """A camera view: image path, intrinsics, extrinsics and ego pose at its own timestamp.

    Raises:
        DataFormatError: a missing image file, or a missing or malformed table record or field (naming the table,
            the token and the field).
    """
    sd = checked_get(nusc, "sample_data", sample_data_token, "load_camera")
    root = Path(nusc.dataroot)
    filename = checked_field(nusc, "sample_data", sd, "filename", IS_STRING)
    path = resolve_inside(root, filename, f"sample_data {sd['token']}")
    if not path.is_file():
        raise DataFormatError(f"sample_data {sd['token']}: missing sensor file {path}")
    cs, cs_what = _pose_record(nusc, sd, "calibrated_sensor", "calibrated_sensor_token")
    try:
        K = np.asarray(cs.get("camera_intrinsic") or [], dtype=np.float64)
    except (TypeError, ValueError):
        K = np.zeros(0)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        detail = "" if K.shape != (3, 3) else " with NaN/inf"
        raise DataFormatError(f"calibrated_sensor {cs['token']}: camera_intrinsic must be 3x3, got shape {K.shape}"
                              f"{detail} ({table_path(nusc, 'calibrated_sensor')})")
    channel = path.parent.name
    rng_file = root / extras_relpath(filename)
    width = int(checked_field(nusc, "sample_data", sd, "width", _PIXELS))
    height = int(checked_field(nusc, "sample_data", sd, "height", _PIXELS))
    timestamp = checked_field(nusc, "sample_data", sd, "timestamp", _TIMESTAMP) * 1e-6
    return CameraView(channel=channel, image_path=path, K=K, width=width, height=height,
                      T_ego_cam=_transform(cs, cs_what),
                      T_global_ego=_transform(*_pose_record(nusc, sd, "ego_pose", "ego_pose_token")),
                      timestamp=timestamp, range_path=rng_file if rng_file.is_file() else None)


def _box(nusc: NuScenes, ann_token: str, sample_token: str) -> Box:
    ann = checked_get(nusc, "sample_annotation", ann_token, f"sample {sample_token}")
    table = "sample_annotation"
    inst_token = checked_field(nusc, table, ann, "instance_token", IS_STRING)
    inst = checked_get(nusc, "instance", inst_token, f"sample_annotation {ann_token}.instance_token")
    cat = checked_get(nusc, "category", checked_field(nusc, "instance", inst, "category_token", IS_STRING),
                      f"instance {inst_token}.category_token")
    category = checked_field(nusc, "category", cat, "name", IS_STRING)
    attrs = [checked_field(nusc, "attribute",
                           checked_get(nusc, "attribute", t, f"sample_annotation {ann_token}.attribute_tokens"),
                           "name", IS_STRING)
             for t in checked_field(nusc, table, ann, "attribute_tokens", IS_LIST)]
    center = checked_vector(nusc, table, ann, "translation", 3)
    size = checked_vector(nusc, table, ann, "size", 3)
    q = checked_vector(nusc, table, ann, "rotation", 4)
    if np.linalg.norm(q) < 1e-6:
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {ann_token}: field 'rotation' = {q.tolist()}; "
                              f"expected a unit quaternion [w, x, y, z]")
    num_lidar_pts = int(checked_field(nusc, table, ann, "num_lidar_pts", IS_COUNT))
    visibility = checked_field(nusc, table, ann, "visibility_token")
    try:
        velocity = np.asarray(nusc.box_velocity(ann_token), float)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {ann_token}: cannot derive its velocity from "
                              f"its prev/next annotations ({type(exc).__name__}: {exc}); expected 'prev'/'next' "
                              f"tokens ('' for none) of annotations whose samples have timestamps") from None
    return Box(token=ann_token, instance_token=inst_token, category=category, center=center, size=size,
               yaw=float(Quaternion(q).yaw_pitch_roll[0]), velocity=velocity, num_lidar_pts=num_lidar_pts,
               attribute=attrs[0] if attrs else "", visibility=str(visibility))


def load_boxes(nusc: NuScenes, sample: dict) -> tuple[Box, ...]:
    """The sample's annotations as global-frame `Box` es (velocity from the devkit's neighbouring annotations).

    Raises:
        DataFormatError: a missing or malformed annotation record or field (naming the table, token and field).
    """
    return tuple(_box(nusc, ann_token, sample["token"]) for ann_token in sample["anns"])


def channel_token(nusc: NuScenes, sample: dict, channel: str) -> str:
    if channel not in sample["data"]:
        raise DataFormatError(
            f"{table_path(nusc, 'sample')}: sample {sample['token']}: no {channel} sample_data (no key-frame record "
            f"of {table_path(nusc, 'sample_data')} with this sample_token on a {channel} sensor; channels: "
            f"{sorted(sample['data'])})")
    return sample["data"][channel]


def load_frame(nusc: NuScenes, sample_token: str, nsweeps: int = 1,
               cameras: tuple[str, ...] = CAMERA_CHANNELS) -> Frame:
    """The `Frame` of one sample: LiDAR (``nsweeps`` aggregated), the requested cameras, the boxes.

    Raises:
        DataFormatError: a bad sensor file, or a missing or malformed table record or field (a sample without a
            LIDAR_TOP or a requested camera, a sample_data without ``filename``...), naming the table, the token
            and the field.
    """
    sample = checked_get(nusc, "sample", sample_token, "load_frame")
    lidar = load_lidar(nusc, channel_token(nusc, sample, "LIDAR_TOP"), nsweeps)
    views = {ch: load_camera(nusc, channel_token(nusc, sample, ch)) for ch in cameras}
    timestamp = checked_field(nusc, "sample", sample, "timestamp", _TIMESTAMP) * 1e-6
    return Frame(token=sample_token, timestamp=timestamp, lidar=lidar, cameras=views,
                 boxes=load_boxes(nusc, sample), source="nuscenes")
