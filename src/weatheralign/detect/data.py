"""The detector's data pipeline over any nuScenes-format dataroot (the synthetic world, its weather copies, real
nuScenes): split reading, a preprocessed per-sample cache, a torch `Dataset` with sensor-consistent BEV augmentation,
collation into a `DetectionBatch`, and mixing two dataroots at the data-loader level.

Frames: every geometric quantity is in the keyframe's LiDAR frame (``LIDAR_TOP`` at the keyframe timestamp), whatever
way the sensor is mounted (nuScenes and the synthetic world: x right, y forward; KITTI, STF: x forward). Box rows follow
`weatheralign.detect.types`: ``(x, y, z, w, l, h, yaw, vx, vy)``.

Cache layout (`build_cache`)::

    <cache_dir>/<dataroot name>-<digest>/     digest of CACHE_VERSION, the dataroot path, version, tokens,
                                             image size, sweeps and `file_stamps` of the tables and sensor files read
        index.json                           written last: settings, tokens in order, build statistics
        <sample token>.npz                   one stored (uncompressed) archive per sample (members: `SAMPLE_MEMBERS`)

A sample's points are stored as (3, N) int16 centimetres (``points_xyz_cm``; points farther than 327 m on any axis are
dropped), uint8 intensities (0..255, rounded) and uint8 sweep indices with a per-sweep time lag table; images as uint8
(C, H, W, 3) in `CAMERA_ORDER`.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from nuscenes.eval.detection.utils import category_to_detection_name
from nuscenes.nuscenes import NuScenes
from PIL import Image
from torch.utils.data import Dataset, Sampler

from weatheralign import atomic
from weatheralign.data.errors import DataFormatError
from weatheralign.data.frame import Box
from weatheralign.data.nuscenes import (
    TABLES,
    compressed_extras_relpath,
    extras_relpath,
    load_boxes,
    load_camera,
    load_lidar,
    open_nuscenes_cached,
)
from weatheralign.detect.image_features import BACKBONE_NAME, image_features
from weatheralign.detect.types import ATTRIBUTES, DETECTION_CLASSES, DetectionBatch
from weatheralign.geometry import invert
from weatheralign.provenance import file_stamps

F64 = NDArray[np.float64]

CACHE_VERSION = 2
"""Bump when the cached content or layout changes: every cache folder name changes with it."""
CAMERA_ORDER: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                                 "CAM_BACK_RIGHT")
DEFAULT_IMAGE_SIZE: tuple[int, int] = (128, 352)
"""(H, W) [px] of cached images: nuScenes' 1600x900 scaled by 0.22 to 352x198, 70 rows (mostly sky) cropped off the
top. Both sides are multiples of 16 (`weatheralign.detect.image_features`)."""
DEFAULT_SWEEPS = 9
"""Earlier sweeps aggregated with the keyframe (BEVFusion: 9, i.e. 10 sweeps, 0.45 s)."""
XYZ_QUANTUM_M = 0.01
"""Storage step of cached point coordinates [m] (int16 centimetres: +-327.67 m)."""
INDEX_FILE = "index.json"
SAMPLE_MEMBERS: dict[str, str] = {
    "token": "0-d unicode sample token",
    "points_xyz_cm": "(3, N) int16 x, y, z in the keyframe LiDAR frame [cm] (column-major: compresses better)",
    "points_intensity": "(N,) uint8 intensity on 0..255 (rounded)",
    "points_sweep": "(N,) uint8 sweep index (0 = keyframe, k = k-th earlier sweep)",
    "sweep_lags": "(S + 1,) float32 time lag of sweep k behind the keyframe [s] (>= 0)",
    "images": "(C, H, W, 3) uint8 RGB in CAMERA_ORDER",
    "features_s8": "(C, 40, H/8, W/8) float16 frozen image features at stride 8 (weatheralign.detect.image_features)",
    "features_s16": "(C, 112, H/16, W/16) float16 frozen image features at stride 16",
    "intrinsics": "(C, 3, 3) float64 pinhole matrices of the cached images [px]",
    "cam_to_lidar": "(C, 4, 4) float64 camera (at its own timestamp) -> keyframe LiDAR frame",
    "T_global_lidar": "(4, 4) float64 keyframe LiDAR frame -> global",
    "boxes": "(M, 9) float64 box rows in the keyframe LiDAR frame (velocity 0 where unknown)",
    "velocity_valid": "(M,) bool whether the devkit knew the box velocity",
    "labels": "(M,) int64 indices into DETECTION_CLASSES",
    "attributes": "(M,) int64 indices into ATTRIBUTES (-1: none)",
    "num_lidar_pts": "(M,) int64 the annotation's num_lidar_pts",
}
_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, Image.DecompressionBombError)
_XYZ_LIMIT_CM = 32767


# ------------------------------------------------------------------------------------------------------- splits


def _splits_file(dataroot: str | Path, version: str) -> Path:
    return Path(dataroot) / version / "splits.json"


def _scenes_from_splits_json(path: Path, split: str) -> list[str]:
    """The scene names of ``split`` in a ``splits.json`` (exactly one key ending in ``_<split>``).

    Raises:
        DataFormatError: invalid JSON, not an object, no or several keys ending in ``_<split>``, or a value that is
            not a list of scene names (naming the file and the key).
    """
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno}); "
                              f"expected an object like {{'<name>_train': [scene names], '<name>_val': [...]}}") \
            from None
    if not isinstance(data, dict):
        raise DataFormatError(f"{path}: the top level is a JSON {type(data).__name__}; expected an object like "
                              f"{{'<name>_train': [scene names], '<name>_val': [...]}}")
    keys = [k for k in data if k.endswith(f"_{split}")]
    if len(keys) != 1:
        raise DataFormatError(f"{path}: {'no key' if not keys else 'several keys'} ending in '_{split}' "
                              f"({sorted(data)}); expected exactly one, e.g. 'weatheralign_{split}'")
    scenes = data[keys[0]]
    if not isinstance(scenes, list) or not all(isinstance(s, str) for s in scenes):
        raise DataFormatError(f"{path}: key {keys[0]!r} = {scenes!r}; expected a list of scene names")
    return scenes


def _devkit_split_name(version: str, split: str) -> str | None:
    if version == "v1.0-mini":
        return f"mini_{split}"
    if version == "v1.0-trainval":
        return split
    return None


def scene_split(nusc: NuScenes, dataroot: str | Path, version: str, split: str) -> list[str]:
    """The sample tokens of ``split``'s scenes, in scene-table order and, within a scene, in time order.

    The split's scene names come from ``<dataroot>/<version>/splits.json`` (the one key ending in ``_train`` /
    ``_val``) if it exists and names scenes of this dataset, else from the devkit's ``create_splits_scenes()``
    (``mini_train`` / ``mini_val`` for v1.0-mini, ``train`` / ``val`` for v1.0-trainval).

    Raises:
        ValueError: ``split`` is neither ``"train"`` nor ``"val"``.
        DataFormatError: a malformed splits.json, or neither source names a scene of this dataset (naming the file
            and what was expected).
    """
    if split not in ("train", "val"):
        raise ValueError(f"split must be 'train' or 'val', got {split!r}")
    present = [scene["name"] for scene in nusc.scene]
    path = _splits_file(dataroot, version)
    wanted: set[str] = set()
    if path.is_file():
        wanted = set(_scenes_from_splits_json(path, split)) & set(present)
    devkit_name = _devkit_split_name(version, split)
    if not wanted and devkit_name is not None:
        from nuscenes.utils.splits import create_splits_scenes

        wanted = set(create_splits_scenes()[devkit_name]) & set(present)
    if not wanted:
        file_state = "names no scene of this dataset" if path.is_file() else "missing"
        devkit = (f"the devkit's split {devkit_name!r} names none either" if devkit_name else
                  f"the devkit has no split for version {version!r}")
        raise DataFormatError(f"{path}: {file_state}, and {devkit}; expected {path} with a key '<name>_{split}' "
                              f"listing scene names of {Path(nusc.table_root) / 'scene.json'} (present: "
                              f"{present[:5]}{'...' if len(present) > 5 else ''})")
    tokens: list[str] = []
    for scene in nusc.scene:
        if scene["name"] not in wanted:
            continue
        token = scene["first_sample_token"]
        while token:
            tokens.append(token)
            token = nusc.get("sample", token)["next"]
    return tokens


# ------------------------------------------------------------------------------------------------------- geometry


def boxes_to_lidar(boxes: Sequence[Box], T_global_lidar: F64) -> tuple[F64, NDArray[np.bool_]]:
    """Global-frame boxes as rows ``(x, y, z, w, l, h, yaw, vx, vy)`` in the LiDAR frame ``T_global_lidar`` (4, 4).

    The heading vector (cos yaw, sin yaw, 0) and the velocity are rotated (not the yaw subtracted), so that any
    mounting of the sensor works; NaN velocities become 0.

    Returns:
        rows (M, 9) float64; velocity_valid (M,) bool.
    """
    rows = np.zeros((len(boxes), 9))
    valid = np.zeros(len(boxes), bool)
    if not boxes:
        return rows, valid
    T = invert(T_global_lidar)
    R = T[:3, :3]
    centers = np.stack([b.center for b in boxes])
    yaws = np.array([b.yaw for b in boxes])
    vel = np.stack([np.asarray(b.velocity, float) for b in boxes])
    valid = np.isfinite(vel[:, :2]).all(axis=1)
    vel = np.where(np.isfinite(vel), vel, 0.0)
    heading = np.stack([np.cos(yaws), np.sin(yaws), np.zeros_like(yaws)], axis=1) @ R.T
    rows[:, :3] = centers @ R.T + T[:3, 3]
    rows[:, 3:6] = np.stack([b.size for b in boxes])
    rows[:, 6] = np.arctan2(heading[:, 1], heading[:, 0])
    rows[:, 7:9] = (vel @ R.T)[:, :2]
    return rows, valid


def boxes_to_global(rows: NDArray, T_global_lidar: F64) -> tuple[F64, F64, F64]:
    """Inverse of `boxes_to_lidar`: box rows (M, 9) in the LiDAR frame -> global centres (M, 3) [m], yaws (M,)
    [rad, about global z] and velocities (M, 3) [m/s] (the LiDAR-frame velocity has no z component)."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 9)
    R = T_global_lidar[:3, :3]
    centers = rows[:, :3] @ R.T + T_global_lidar[:3, 3]
    heading = np.stack([np.cos(rows[:, 6]), np.sin(rows[:, 6]), np.zeros(len(rows))], axis=1) @ R.T
    vel = np.column_stack([rows[:, 7:9], np.zeros(len(rows))]) @ R.T
    return centers, np.arctan2(heading[:, 1], heading[:, 0]), vel


def points_in_boxes(xyz: NDArray | torch.Tensor, rows: NDArray | torch.Tensor) -> NDArray[np.bool_]:
    """(N, M) whether point n (xyz (N, 3) [m]) lies inside box m (rows (M, >= 7), see the module docstring)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.float64)
    d = xyz[:, None, :3] - rows[None, :, :3]
    c, s = np.cos(rows[:, 6]), np.sin(rows[:, 6])
    along = d[..., 0] * c + d[..., 1] * s  # along the length axis
    across = -d[..., 0] * s + d[..., 1] * c
    return ((np.abs(along) <= rows[:, 4] / 2) & (np.abs(across) <= rows[:, 3] / 2)
            & (np.abs(d[..., 2]) <= rows[:, 5] / 2))


def _labels(boxes: Sequence[Box], where: str) -> tuple[NDArray[np.bool_], NDArray[np.int64], NDArray[np.int64]]:
    """(keep (M,) bool: category maps to a detection class, labels (K,), attributes (K,) (-1: none))."""
    keep, labels, attrs = [], [], []
    for box in boxes:
        name = category_to_detection_name(box.category)
        keep.append(name is not None)
        if name is None:
            continue
        labels.append(DETECTION_CLASSES.index(name))
        if box.attribute and box.attribute not in ATTRIBUTES:
            raise DataFormatError(f"{where}: sample_annotation {box.token}: attribute {box.attribute!r} is not a "
                                  f"nuScenes attribute; expected one of {ATTRIBUTES}")
        attrs.append(ATTRIBUTES.index(box.attribute) if box.attribute else -1)
    return np.array(keep, bool), np.array(labels, np.int64), np.array(attrs, np.int64)


# ------------------------------------------------------------------------------------------------------- images


def resize_crop_params(width: int, height: int, image_size: tuple[int, int]) -> tuple[float, float, float]:
    """(scale, crop_x, crop_y) mapping a ``width`` x ``height`` image onto ``image_size`` (H, W): scale so that both
    sides cover the target, centre horizontally, keep the bottom (crop the top, mostly sky). A pixel coordinate
    ``u`` (pixel edges at integers) maps to ``u * scale - crop_x``."""
    H, W = image_size
    scale = max(W / width, H / height)
    return scale, (width * scale - W) / 2.0, height * scale - H


def decode_camera(path: Path, width: int, height: int,
                  image_size: tuple[int, int]) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """Decode an image at reduced size (libjpeg's DCT scaling via ``Image.draft``), then resize and crop it to
    ``image_size`` (H, W) in one resampling step.

    Returns:
        image (H, W, 3) uint8 RGB; A (3, 3) the pixel map full-size -> cached image (``K_cached = A @ K``).

    Raises:
        DataFormatError: a truncated or invalid image, or one whose size is not ``width`` x ``height`` (the
            calibration's), naming the file.
    """
    H, W = image_size
    scale, crop_x, crop_y = resize_crop_params(width, height, image_size)
    try:
        with Image.open(path) as im:
            if im.size != (width, height):
                raise DataFormatError(f"{path}: image is {im.size[0]}x{im.size[1]}, its sample_data record says "
                                      f"{width}x{height}")
            drafted = im.draft("RGB", (math.ceil(width * scale), math.ceil(height * scale)))
            fx = drafted[1][2] / width if drafted is not None else 1.0  # drafted pixels per full-size pixel
            fy = drafted[1][3] / height if drafted is not None else 1.0
            rgb = im if im.mode == "RGB" else im.convert("RGB")
            box = (max(crop_x / scale * fx, 0.0), max(crop_y / scale * fy, 0.0),
                   min((crop_x + W) / scale * fx, rgb.size[0]), min((crop_y + H) / scale * fy, rgb.size[1]))
            out = np.asarray(rgb.resize((W, H), Image.BILINEAR, box=box))
    except DataFormatError:
        raise
    except _IMAGE_ERRORS as exc:
        raise DataFormatError(f"{path}: camera image is truncated or not a valid JPEG/PNG image "
                              f"({type(exc).__name__}: {exc})") from None
    A = np.array([[scale, 0.0, -crop_x], [0.0, scale, -crop_y], [0.0, 0.0, 1.0]])
    return out, A


# ------------------------------------------------------------------------------------------------------- cache


def _sweep_chain(nusc: NuScenes, lidar_token: str, sweeps: int) -> list[dict]:
    """The keyframe's LiDAR sample_data record and up to ``sweeps`` earlier ones (newest first), as `load_lidar`
    aggregates them."""
    chain = [nusc.get("sample_data", lidar_token)]
    while len(chain) <= sweeps and chain[-1]["prev"]:
        chain.append(nusc.get("sample_data", chain[-1]["prev"]))
    return chain


def _sample_files(nusc: NuScenes, token: str, sweeps: int) -> list[str]:
    """Relative paths of every file caching ``token`` reads (scans, their point extras, camera images)."""
    sample = nusc.get("sample", token)
    files = []
    for sd in _sweep_chain(nusc, sample["data"]["LIDAR_TOP"], sweeps):
        files += [sd["filename"], extras_relpath(sd["filename"]), compressed_extras_relpath(sd["filename"])]
    files += [nusc.get("sample_data", sample["data"][ch])["filename"] for ch in CAMERA_ORDER if ch in sample["data"]]
    return files


def _cache_digest(root: Path, version: str, nusc: NuScenes, tokens: Sequence[str], image_size: tuple[int, int],
                  sweeps: int) -> str:
    tables = [f"{version}/{t}.json" for t in TABLES]
    files = [f for token in tokens for f in _sample_files(nusc, token, sweeps)]
    blob = json.dumps({"cache_version": CACHE_VERSION, "backbone": BACKBONE_NAME, "dataroot": str(root.resolve()),
                       "version": version, "tokens": list(tokens), "image_size": list(image_size), "sweeps": sweeps,
                       "tables": file_stamps(root, tables), "files": file_stamps(root, files)})
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _tables_key(root: Path, version: str) -> str:
    return file_stamps(root, [f"{version}/{t}.json" for t in TABLES])


def _check_cache_args(tokens: Sequence[str], image_size: tuple[int, int], sweeps: int) -> None:
    if len(image_size) != 2 or min(image_size) < 16 or image_size[0] % 16 or image_size[1] % 16:
        raise ValueError(f"image_size must be (H, W) with both multiples of 16 px, got {image_size}")
    if not 0 <= sweeps <= 255:
        raise ValueError(f"sweeps must be in 0..255, got {sweeps}")
    if not tokens:
        raise ValueError("sample_tokens is empty: nothing to cache")


def cache_path(dataroot: str | Path, version: str, sample_tokens: Sequence[str], cache_dir: str | Path,
               image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE, sweeps: int = DEFAULT_SWEEPS) -> Path:
    """The folder `build_cache` writes for these arguments (nothing is written): ``<cache_dir>/<dataroot name>-
    <digest>``, the digest over CACHE_VERSION, the resolved dataroot, version, tokens, image size, sweeps and the
    `file_stamps` (size, mtime) of the tables and of every sensor file the samples read.

    Raises:
        DataFormatError: the dataroot's tables cannot be opened (see `open_nuscenes`); KeyError: an unknown token.
    """
    root = Path(dataroot)
    _check_cache_args(sample_tokens, image_size, sweeps)
    nusc = open_nuscenes_cached(str(root), version, _tables_key(root, version))
    digest = _cache_digest(root, version, nusc, sample_tokens, tuple(image_size), sweeps)
    return Path(cache_dir) / f"{root.resolve().name}-{digest}"


def stale_caches(cache_dir: str | Path, dataroots: Iterable[str | Path], current: Iterable[str]) -> list[Path]:
    """The cache folders under ``cache_dir`` that `cache_path` made for one of ``dataroots`` (``<dataroot
    name>-<16 hex digits>``) but whose name is not among ``current`` (the folder names of their splits as they are
    now): caches of an earlier version of a dataset, which nothing reads again. Other folders are not listed."""
    names = {Path(root).resolve().name for root in dataroots}
    keep = set(current)
    out = []
    for folder in sorted(Path(cache_dir).glob("*-*")):
        name, _, digest = folder.name.rpartition("-")
        if folder.is_dir() and folder.name not in keep and name in names and re.fullmatch(r"[0-9a-f]{16}", digest):
            out.append(folder)
    return out


def cache_sample(nusc: NuScenes, token: str, image_size: tuple[int, int], sweeps: int) -> tuple[dict, dict]:
    """One sample's cache arrays (see `SAMPLE_MEMBERS`) and timings ``{lidar_s, cameras_s, boxes_s}`` [s, CPU].

    Raises:
        DataFormatError: a missing or malformed record, sensor file or image (naming it).
    """
    sample = nusc.get("sample", token)
    missing = [ch for ch in ("LIDAR_TOP", *CAMERA_ORDER) if ch not in sample["data"]]
    if missing:
        raise DataFormatError(f"{Path(nusc.table_root) / 'sample.json'}: sample {token}: no {', '.join(missing)} "
                              f"sample_data; expected LIDAR_TOP and the six cameras {CAMERA_ORDER}")
    t0 = time.process_time()
    chain = _sweep_chain(nusc, sample["data"]["LIDAR_TOP"], sweeps)
    scan = load_lidar(nusc, chain[0]["token"], nsweeps=sweeps + 1)
    sweep_idx = scan.sweep_index if scan.sweep_index is not None else np.zeros(len(scan.points), np.int16)
    xyz_cm = np.round(scan.points[:, :3].astype(np.float64) / XYZ_QUANTUM_M)
    near = np.all(np.abs(xyz_cm) <= _XYZ_LIMIT_CM, axis=1)
    lags = np.array([(chain[0]["timestamp"] - sd["timestamp"]) * 1e-6 for sd in chain[:int(sweep_idx.max()) + 1]],
                    np.float32)
    T_global_lidar = scan.T_global_lidar
    T_lidar_global = invert(T_global_lidar)
    t1 = time.process_time()
    images, intrinsics, cam_to_lidar = [], [], []
    for ch in CAMERA_ORDER:
        view = load_camera(nusc, sample["data"][ch])
        image, A = decode_camera(view.image_path, view.width, view.height, image_size)
        images.append(image)
        intrinsics.append(A @ view.K)
        cam_to_lidar.append(T_lidar_global @ view.T_global_cam)
    features_s8, features_s16 = image_features(np.stack(images))
    t2 = time.process_time()
    boxes = load_boxes(nusc, sample)
    keep, labels, attributes = _labels(boxes, str(Path(nusc.table_root) / "sample_annotation.json"))
    kept = [b for b, k in zip(boxes, keep) if k]
    rows, valid = boxes_to_lidar(kept, T_global_lidar)
    arrays = {
        "token": np.array(token),
        "points_xyz_cm": np.ascontiguousarray(xyz_cm[near].T).astype(np.int16),
        "points_intensity": np.clip(np.round(scan.intensity_255()[near]), 0, 255).astype(np.uint8),
        "points_sweep": sweep_idx[near].astype(np.uint8),
        "sweep_lags": lags,
        "images": np.stack(images),
        "features_s8": features_s8,
        "features_s16": features_s16,
        "intrinsics": np.stack(intrinsics),
        "cam_to_lidar": np.stack(cam_to_lidar),
        "T_global_lidar": T_global_lidar,
        "boxes": rows,
        "velocity_valid": valid,
        "labels": labels,
        "attributes": attributes,
        "num_lidar_pts": np.array([b.num_lidar_pts for b in kept], np.int64),
    }
    t3 = time.process_time()
    return arrays, {"lidar_s": t1 - t0, "cameras_s": t2 - t1, "boxes_s": t3 - t2,
                    "dropped_far_points": int((~near).sum())}


def _cache_one(dataroot: str, version: str, tables_key: str, token: str, out: str, image_size: tuple[int, int],
               sweeps: int) -> dict:
    """Cache one sample into ``out`` (atomically); its timings [s, CPU of this process] and size [bytes]."""
    nusc = open_nuscenes_cached(dataroot, version, tables_key)
    arrays, stats = cache_sample(nusc, token, image_size, sweeps)
    t0 = time.process_time()
    atomic.save_npz(out, arrays, compress=False)  # read at every training step
    return {**stats, "write_s": time.process_time() - t0, "bytes": Path(out).stat().st_size}


def build_cache(dataroot: str | Path, version: str, sample_tokens: Sequence[str], cache_dir: str | Path,
                image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE, sweeps: int = DEFAULT_SWEEPS,
                progress: bool = True, workers: int = 1) -> Path:
    """Cache ``sample_tokens`` of a dataroot (one ``<token>.npz`` each, atomically; see the module docstring) and
    return the cache folder (`cache_path`). Resumable: samples already cached are skipped; ``index.json`` is written
    last, with per-sample CPU timings of the samples built by this call.

    Args:
        image_size: (H, W) [px] of the cached images; sweeps: earlier sweeps aggregated with the keyframe;
        progress: a tqdm bar; workers: processes (1: this one).

    Raises:
        DataFormatError: a malformed dataroot (naming the file, record and field).
    """
    root = Path(dataroot)
    image_size = (int(image_size[0]), int(image_size[1]))
    folder = cache_path(root, version, sample_tokens, cache_dir, image_size, sweeps)
    folder.mkdir(parents=True, exist_ok=True)
    todo = [t for t in dict.fromkeys(sample_tokens) if not (folder / f"{t}.npz").is_file()]
    tables_key = _tables_key(root, version)
    args = [(str(root), version, tables_key, t, str(folder / f"{t}.npz"), image_size, sweeps) for t in todo]
    stats: dict[str, dict] = {}
    start = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc=f"cache {root.name}", unit="sample", disable=not progress or not todo)
    if workers <= 1:
        for a in args:
            stats[a[3]] = _cache_one(*a)
            bar.update()
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=torch.set_num_threads, initargs=(1,)) as pool:
            for a, result in zip(args, pool.map(_cache_one, *zip(*args))):
                stats[a[3]] = result
                bar.update()
    bar.close()
    totals = {k: float(sum(s[k] for s in stats.values())) for k in ("lidar_s", "cameras_s", "boxes_s", "write_s")}
    index = {
        "cache_version": CACHE_VERSION, "dataroot": str(root.resolve()), "version": version,
        "image_size": list(image_size), "sweeps": sweeps, "camera_order": list(CAMERA_ORDER),
        "tokens": list(dict.fromkeys(sample_tokens)), "members": SAMPLE_MEMBERS,
        "last_build": {"built": len(todo), "skipped": len(set(sample_tokens)) - len(todo),
                       "wall_s": time.perf_counter() - start, "cpu_s_totals": totals, "per_sample": stats},
    }
    atomic.write_json(folder / INDEX_FILE, index, indent=1)
    return folder


def read_index(folder: str | Path) -> dict:
    """A cache folder's ``index.json``.

    Raises:
        DataFormatError: no index (an unfinished build: run `build_cache` again) or another CACHE_VERSION.
    """
    path = Path(folder) / INDEX_FILE
    if not path.is_file():
        raise DataFormatError(f"{path}: missing; the cache is unfinished or not a cache (run build_cache)")
    index = json.loads(path.read_text())
    if index.get("cache_version") != CACHE_VERSION:
        raise DataFormatError(f"{path}: cache_version {index.get('cache_version')!r}; expected {CACHE_VERSION} "
                              f"(rebuild with build_cache)")
    return index


def load_cached_sample(folder: str | Path, token: str) -> dict[str, np.ndarray]:
    """The arrays of one cached sample (`SAMPLE_MEMBERS`).

    Raises:
        DataFormatError: a missing or unreadable sample file (naming it).
    """
    path = Path(folder) / f"{token}.npz"
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise DataFormatError(f"{path}: missing or unreadable cached sample ({type(exc).__name__}: {exc}); "
                              f"rebuild with build_cache") from None


# ------------------------------------------------------------------------------------------------------- dataset


@dataclass(frozen=True)
class Augmentation:
    """Global BEV augmentation applied consistently to points, boxes and cameras (training only).

    Attributes:
        rotation_rad: rotation about the LiDAR z axis drawn uniformly in +-``rotation_rad``.
        scale: range of the global scale factor (uniform).
        flip_x_prob: probability of flipping across the LiDAR x axis (y -> -y).
        flip_y_prob: probability of flipping across the LiDAR y axis (x -> -x).
    """

    rotation_rad: float = math.pi / 8
    scale: tuple[float, float] = (0.95, 1.05)
    flip_x_prob: float = 0.5
    flip_y_prob: float = 0.5

    def matrix(self, generator: torch.Generator) -> F64:
        """(4, 4) float64 ``A = flip @ (scale * rot_z)`` drawn with ``generator`` (4 uniforms)."""
        u = torch.rand(4, generator=generator, dtype=torch.float64).numpy()
        angle = (2.0 * u[0] - 1.0) * self.rotation_rad
        s = self.scale[0] + u[1] * (self.scale[1] - self.scale[0])
        c, sn = math.cos(angle), math.sin(angle)
        A = np.eye(4)
        A[:3, :3] = s * np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        flip = np.diag([-1.0 if u[3] < self.flip_y_prob else 1.0, -1.0 if u[2] < self.flip_x_prob else 1.0, 1.0, 1.0])
        return flip @ A


def augment_boxes(rows: NDArray, A: F64) -> F64:
    """Box rows (M, 9) under the similarity-with-reflection ``A`` (4, 4): centre and velocity mapped, sizes scaled,
    yaw from the mapped heading vector."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 9)
    L = A[:3, :3]
    scale = abs(np.linalg.det(L)) ** (1.0 / 3.0)
    out = rows.copy()
    out[:, :3] = rows[:, :3] @ L.T + A[:3, 3]
    out[:, 3:6] = rows[:, 3:6] * scale
    heading = np.stack([np.cos(rows[:, 6]), np.sin(rows[:, 6]), np.zeros(len(rows))], axis=1) @ L.T
    out[:, 6] = np.arctan2(heading[:, 1], heading[:, 0])
    out[:, 7:9] = rows[:, 7:9] @ L[:2, :2].T
    return out


def seeded_generator(*keys: int) -> torch.Generator:
    """A torch.Generator seeded from non-negative integer ``keys`` (through numpy's SeedSequence): the same draws
    whatever process asks. The dataset uses (seed, epoch, 0, index), the mixed sampler (seed, epoch, 1)."""
    state = np.random.SeedSequence([int(k) for k in keys]).generate_state(1, dtype=np.uint64)
    return torch.Generator().manual_seed(int(state[0]))


def derangement(n: int, seed: int) -> list[int]:
    """A seeded permutation of range(n) (n >= 2) without fixed points: sample i takes the images of another
    sample (the shuffled-image control)."""
    if n < 2:
        raise ValueError(f"a derangement needs at least 2 samples, got {n}")
    generator = seeded_generator(seed, 2)
    while True:
        order = torch.randperm(n, generator=generator).tolist()
        if all(i != j for i, j in enumerate(order)):
            return order


class DetectionDataset(Dataset):
    """The samples of one cache folder (`build_cache`) as dicts of tensors.

    A sample: ``points`` (N, 5) float32 ``x, y, z, intensity / 255, time lag [s]``; ``images`` (C, 3, H, W) uint8;
    ``features_s8`` (C, 40, H/8, W/8) and ``features_s16`` (C, 112, H/16, W/16) float16 frozen image features;
    ``intrinsics`` (C, 3, 3) float32; ``cam_to_lidar`` (C, 4, 4) float32; ``boxes`` (M, 9) float32; ``labels``,
    ``attributes``, ``num_lidar_pts`` (M,) int64; ``T_global_lidar`` (4, 4) float64; ``aug`` (4, 4) float64 the
    augmentation (identity without); ``token`` str.

    With an `Augmentation` the points, boxes and ``cam_to_lidar`` (left-multiplied: ``A @ cam_to_lidar``, then no
    longer rigid) are mapped by one matrix ``A`` drawn from (seed, epoch, index): deterministic, and different per
    epoch (call `set_epoch`; with DataLoader workers use ``persistent_workers=False`` so they see the new epoch).
    ``T_global_lidar`` stays that of the unaugmented frame.

    Args:
        min_lidar_pts: boxes with fewer annotated LiDAR points are dropped (mmdet3d drops those with none).
        point_range: optional ``(x_min, y_min, z_min, x_max, y_max, z_max)`` [m]: after augmentation, points outside
            and boxes whose centre lies outside (in x, y) are dropped.
        camera_cache: another cache folder of the same samples (e.g. a weather copy's) whose camera images and
            features replace this one's: the "clean LiDAR + weather cameras" evaluation sets.
        image_source: optional (N,) sample indices: sample i gets the camera images and features of sample
            ``image_source[i]`` (its own calibration stays): the shuffled-image control (`derangement`).
    """

    def __init__(self, cache: str | Path, augmentation: Augmentation | None = None, seed: int = 0,
                 min_lidar_pts: int = 1, point_range: Sequence[float] | None = None,
                 camera_cache: str | Path | None = None, image_source: Sequence[int] | None = None) -> None:
        self.folder = Path(cache)
        self.index = read_index(self.folder)
        self.tokens: list[str] = list(self.index["tokens"])
        self.image_size: tuple[int, int] = tuple(self.index["image_size"])
        self.camera_folder = Path(camera_cache) if camera_cache is not None else self.folder
        if camera_cache is not None:
            camera_index = read_index(self.camera_folder)
            if camera_index["tokens"] != self.tokens or tuple(camera_index["image_size"]) != self.image_size:
                raise ValueError(f"camera_cache {self.camera_folder} holds other samples or another image size than "
                                 f"{self.folder}")
        if image_source is not None and (len(image_source) != len(self.tokens)
                                         or not all(0 <= int(i) < len(self.tokens) for i in image_source)):
            raise ValueError(f"image_source must hold {len(self.tokens)} sample indices in 0..{len(self.tokens) - 1}")
        self.image_source = None if image_source is None else [int(i) for i in image_source]
        self.augmentation = augmentation
        self.seed = seed
        self.epoch = 0
        self.min_lidar_pts = min_lidar_pts
        if point_range is not None and len(point_range) != 6:
            raise ValueError(f"point_range must be (x_min, y_min, z_min, x_max, y_max, z_max), got {point_range}")
        self.point_range = None if point_range is None else np.asarray(point_range, np.float64)

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation draws of ``epoch``."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.tokens)

    def __getitem__(self, index: int) -> dict[str, Any]:
        raw = load_cached_sample(self.folder, self.tokens[index])
        camera_index = index if self.image_source is None else self.image_source[index]
        if camera_index != index or self.camera_folder != self.folder:
            camera = load_cached_sample(self.camera_folder, self.tokens[camera_index])
            raw.update({k: camera[k] for k in ("images", "features_s8", "features_s16")})
        xyz = raw["points_xyz_cm"].T.astype(np.float64) * XYZ_QUANTUM_M
        intensity = raw["points_intensity"].astype(np.float32) / np.float32(255.0)
        lag = raw["sweep_lags"][raw["points_sweep"]]
        boxes = raw["boxes"]
        keep = raw["num_lidar_pts"] >= self.min_lidar_pts
        A = np.eye(4)
        if self.augmentation is not None:
            A = self.augmentation.matrix(seeded_generator(self.seed, self.epoch, 0, index))
        xyz = xyz @ A[:3, :3].T + A[:3, 3]
        boxes = augment_boxes(boxes, A)
        cam_to_lidar = A @ raw["cam_to_lidar"]
        points = np.column_stack([xyz, intensity, lag]).astype(np.float32)
        if self.point_range is not None:
            lo, hi = self.point_range[:3], self.point_range[3:]
            points = points[np.all((xyz >= lo) & (xyz <= hi), axis=1)]
            keep &= np.all((boxes[:, :2] >= lo[:2]) & (boxes[:, :2] <= hi[:2]), axis=1)
        return {
            "token": str(raw["token"].reshape(-1)[0]),
            "points": torch.from_numpy(points),
            "images": torch.from_numpy(raw["images"]).permute(0, 3, 1, 2).contiguous(),
            "features_s8": torch.from_numpy(raw["features_s8"]),
            "features_s16": torch.from_numpy(raw["features_s16"]),
            "intrinsics": torch.from_numpy(raw["intrinsics"].astype(np.float32)),
            "cam_to_lidar": torch.from_numpy(cam_to_lidar.astype(np.float32)),
            "boxes": torch.from_numpy(boxes[keep].astype(np.float32)),
            "labels": torch.from_numpy(raw["labels"][keep]),
            "attributes": torch.from_numpy(raw["attributes"][keep]),
            "num_lidar_pts": torch.from_numpy(raw["num_lidar_pts"][keep]),
            "T_global_lidar": torch.from_numpy(raw["T_global_lidar"]),
            "aug": torch.from_numpy(A),
        }


def collate(samples: Sequence[dict[str, Any]]) -> DetectionBatch:
    """Samples of `DetectionDataset` -> a `DetectionBatch`: points concatenated with a leading batch-index column,
    images stacked as float32 in [0, 1]."""
    points = [torch.cat([torch.full((len(s["points"]), 1), float(b)), s["points"]], dim=1)
              for b, s in enumerate(samples)]
    return DetectionBatch(
        points=torch.cat(points), images=torch.stack([s["images"] for s in samples]).float().div_(255.0),
        features_s8=torch.stack([s["features_s8"] for s in samples]).float(),
        features_s16=torch.stack([s["features_s16"] for s in samples]).float(),
        intrinsics=torch.stack([s["intrinsics"] for s in samples]),
        cam_to_lidar=torch.stack([s["cam_to_lidar"] for s in samples]),
        boxes=[s["boxes"] for s in samples], labels=[s["labels"] for s in samples],
        attributes=[s["attributes"] for s in samples], tokens=[s["token"] for s in samples],
        T_global_lidar=torch.stack([s["T_global_lidar"] for s in samples]))


# ------------------------------------------------------------------------------------------------------- mixing


class MixedDataset(Dataset):
    """Two datasets side by side without merging their databases: indices ``0..len(first)-1`` are ``first``'s,
    the rest ``second``'s. `set_epoch` reaches both."""

    def __init__(self, first: Dataset, second: Dataset) -> None:
        sizes = [getattr(d, "image_size", None) for d in (first, second)]
        if None not in sizes and sizes[0] != sizes[1]:
            raise ValueError(f"cannot mix caches of image sizes {sizes[0]} and {sizes[1]}")
        self.first, self.second = first, second

    def set_epoch(self, epoch: int) -> None:
        for d in (self.first, self.second):
            if hasattr(d, "set_epoch"):
                d.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.first) + len(self.second)

    def __getitem__(self, index: int) -> dict[str, Any]:
        n = len(self.first)
        return self.first[index] if index < n else self.second[index - n]


class MixedSampler(Sampler[int]):
    """Indices into a `MixedDataset` of (``n_first``, ``n_second``) samples: an epoch is ``num_samples`` draws,
    exactly ``round(first_fraction * num_samples)`` of them from the first dataset, in a shuffled order. Each source
    is drawn without replacement, cycling through fresh permutations when an epoch needs more than it has, so its
    samples are used equally often. Deterministic for (seed, epoch); `set_epoch` selects the epoch."""

    def __init__(self, n_first: int, n_second: int, first_fraction: float, num_samples: int, seed: int = 0) -> None:
        if not 0.0 <= first_fraction <= 1.0:
            raise ValueError(f"first_fraction must be in [0, 1], got {first_fraction}")
        self.n_take = round(first_fraction * num_samples)
        if (self.n_take and n_first <= 0) or (num_samples - self.n_take and n_second <= 0) or num_samples <= 0:
            raise ValueError(f"cannot draw {num_samples} samples, {self.n_take} of them from the first, out of "
                             f"datasets of {n_first} and {n_second} samples")
        self.n_first, self.n_second = n_first, n_second
        self.num_samples, self.seed, self.epoch = num_samples, seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.num_samples

    @staticmethod
    def _cycle(n: int, count: int, generator: torch.Generator) -> torch.Tensor:
        """``count`` indices of range(n): concatenated fresh permutations, cut."""
        perms = [torch.randperm(n, generator=generator) for _ in range(-(-count // n) if count else 0)]
        return torch.cat([torch.zeros(0, dtype=torch.long), *perms])[:count]

    def __iter__(self) -> Iterator[int]:
        g = seeded_generator(self.seed, self.epoch, 1)
        first = self._cycle(self.n_first, self.n_take, g)
        second = self._cycle(self.n_second, self.num_samples - self.n_take, g) + self.n_first
        order = torch.cat([first, second])[torch.randperm(self.num_samples, generator=g)]
        return iter(order.tolist())


def mixed_dataset(weather_ds: Dataset, clean_ds: Dataset, weather_fraction: float = 0.3,
                  num_samples: int | None = None, seed: int = 0) -> tuple[MixedDataset, MixedSampler]:
    """The paper's weather / clean finetuning mix at the data-loader level (two dataroots, never merged): use as
    ``DataLoader(dataset, sampler=sampler, collate_fn=collate)`` and call ``set_epoch`` on both each epoch.

    An epoch is ``num_samples`` draws, by default ``len(weather_ds)``: the same number of steps as an epoch of
    finetuning on the weather data alone, ``round(weather_fraction * num_samples)`` of them weather samples.
    """
    n = len(weather_ds) if num_samples is None else num_samples
    sampler = MixedSampler(len(weather_ds), len(clean_ds), weather_fraction, n, seed)
    return MixedDataset(weather_ds, clean_ds), sampler


__all__ = ["Augmentation", "CACHE_VERSION", "CAMERA_ORDER", "DEFAULT_IMAGE_SIZE", "DEFAULT_SWEEPS",
           "DetectionDataset", "MixedDataset", "derangement", "MixedSampler", "SAMPLE_MEMBERS", "augment_boxes",
           "boxes_to_global",
           "boxes_to_lidar", "build_cache", "cache_path", "cache_sample", "collate", "decode_camera",
           "load_cached_sample", "mixed_dataset", "points_in_boxes", "read_index", "resize_crop_params",
           "scene_split", "seeded_generator", "stale_caches"]
