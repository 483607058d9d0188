"""Rendering of whole samples of the synthetic world: sensor files written into a nuScenes-style dataroot plus the
records the table writer needs. A sample is self-contained (its scene is regenerated from the seed; a process keeps
its last scenes, `scene_caster`), so samples can be rendered in any order, in parallel, on other machines, and skipped
when already done."""

from __future__ import annotations

import hashlib
import io
import json
import threading
from collections import OrderedDict
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from weatheralign import atomic
from weatheralign.config import WorldConfig
from weatheralign.data.float16 import to_float16
from weatheralign.data.nuscenes import extras_relpath
from weatheralign.geometry import apply, invert, project, quaternion_wxyz
from weatheralign.sensors import FiringPattern, ego_body_from_params, lidar_model_from_params
from weatheralign.world.layout import Actor, SceneLayout, generate_layout
from weatheralign.world.objects import ego_rear
from weatheralign.world.raster import pinhole_depth
from weatheralign.world.raycast import WorldRaycaster
from weatheralign.world.render import CameraFrame, LidarSweep, render_camera, render_lidar_sweep
from weatheralign.world.rig import Camera, camera_time_offset, make_cameras

SWEEP_PERIOD_US = 50_000
KEYFRAME_PERIOD_US = 500_000
BASE_TIME_US = 1_700_000_000_000_000
ANNOTATION_RADIUS_M = 75.0
VISIBILITY_STRIDE = 4
# extras per LiDAR point (not part of the nuScenes format): firing time, firing column, actor id, material
LIDAR_EXTRAS_DTYPE = np.dtype([("time_offset", "<f4"), ("column", "<i2"), ("instance", "<i4"), ("material", "u1")])


@dataclass(frozen=True)
class SceneSpec:
    """Everything needed to regenerate one scene (small and picklable)."""

    index: int
    name: str
    log_name: str
    split: str
    seed: int
    t_start_us: int
    origin: tuple[float, float]
    heading: float

    def layout(self, cfg: WorldConfig) -> SceneLayout:
        return generate_layout(self.name, self.seed, self.t_start_us * 1e-6, scene_duration_s(cfg),
                               (cfg.ego_speed_min, cfg.ego_speed_max), np.array(self.origin), self.heading)


@dataclass(frozen=True)
class SensorRecord:
    """One written sensor file (a future ``sample_data`` record) with its ego pose."""

    channel: str
    timestamp_us: int
    filename: str
    is_key_frame: bool
    width: int
    height: int
    ego_translation: list[float]
    ego_rotation: list[float]


@dataclass(frozen=True)
class AnnotationRecord:
    """One box of one sample (a future ``sample_annotation``); centre/size/yaw in the global frame."""

    instance: int
    category: str
    attribute: str
    center: list[float]
    size: list[float]
    yaw: float
    num_lidar_pts: int
    visibility: int  # nuScenes visibility token 1..4 (0-40, 40-60, 60-80, 80-100 % visible)


@dataclass(frozen=True)
class SampleResult:
    """What rendering one keyframe sample produced."""

    scene_index: int
    sample_index: int
    timestamp_us: int
    lidar: list[SensorRecord]  # earlier sweeps first, the keyframe last
    cameras: list[SensorRecord]
    annotations: list[AnnotationRecord]

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @staticmethod
    def from_json(text: str) -> SampleResult:
        d = json.loads(text)
        return SampleResult(d["scene_index"], d["sample_index"], d["timestamp_us"],
                            [SensorRecord(**r) for r in d["lidar"]], [SensorRecord(**r) for r in d["cameras"]],
                            [AnnotationRecord(**a) for a in d["annotations"]])


def scene_duration_s(cfg: WorldConfig) -> float:
    """Time span a scene must cover: the leading sweeps, all keyframes and one sweep of margin [s]."""
    return ((cfg.sweeps_per_sample + 1) * SWEEP_PERIOD_US + (cfg.samples_per_scene - 1) * KEYFRAME_PERIOD_US) * 1e-6


def mini_scene_names(num_train: int, num_val: int) -> tuple[list[str], list[str]]:
    """Scene names: the nuScenes-mini names when the counts fit (so tools that hard-code the mini split work)."""
    mini_train = ["scene-0061", "scene-0553", "scene-0655", "scene-0757", "scene-0796", "scene-1077", "scene-1094",
                  "scene-1100"]
    mini_val = ["scene-0103", "scene-0916"]
    if num_train <= len(mini_train) and num_val <= len(mini_val):
        return mini_train[:num_train], mini_val[:num_val]
    return ([f"scene-synth-{i:04d}" for i in range(num_train)],
            [f"scene-synth-{num_train + i:04d}" for i in range(num_val)])


def scene_specs(cfg: WorldConfig) -> list[SceneSpec]:
    """The scenes of the dataset, train first then val, each with its own seed, log, start time and placement."""
    train, val = mini_scene_names(cfg.num_train_scenes, cfg.num_val_scenes)
    rng = np.random.default_rng(cfg.seed)
    specs = []
    for i, (name, split) in enumerate([(n, "train") for n in train] + [(n, "val") for n in val]):
        seed = int(rng.integers(0, 2**31 - 1))
        origin = (float(rng.uniform(250, 750)), float(rng.uniform(250, 750)))
        heading = float(rng.uniform(-np.pi, np.pi))
        t_start = BASE_TIME_US + i * 3_600_000_000 + int(rng.integers(0, 1_000_000))
        specs.append(SceneSpec(i, name, f"wa-{cfg.seed}-synthetic-log{i:03d}", split, seed, t_start, origin, heading))
    return specs


def keyframe_time_us(spec: SceneSpec, cfg: WorldConfig, sample_index: int) -> int:
    """Timestamp [us] of keyframe ``sample_index``: the end of its LiDAR sweep."""
    return spec.t_start_us + (cfg.sweeps_per_sample + 1) * SWEEP_PERIOD_US + sample_index * KEYFRAME_PERIOD_US


def sensor_filename(folder: str, log_name: str, channel: str, timestamp_us: int, ext: str) -> str:
    """nuScenes-style relative path, e.g. ``samples/LIDAR_TOP/<log>__LIDAR_TOP__<us>.pcd.bin``."""
    return f"{folder}/{channel}/{log_name}__{channel}__{timestamp_us}.{ext}"


def token(*parts: object) -> str:
    """A deterministic 32-hex-character token (nuScenes style) from its identifying parts."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def _pose_lists(T: NDArray) -> tuple[list[float], list[float]]:
    return [float(v) for v in T[:3, 3]], quaternion_wxyz(T[:3, :3])


def sensor_rng(seed: int, *parts: int) -> np.random.Generator:
    """The generator of one sensor capture: derived from the scene seed, the timestamp and the sensor index."""
    return np.random.default_rng([seed, *parts])


def write_sweep(dataroot: Path, filename: str, sweep: LidarSweep) -> None:
    """The sweep's points (``filename``, float32 N x 5) and its per-point extras (`LIDAR_EXTRAS_DTYPE`, .npy)."""
    atomic.write_bytes(dataroot / filename, sweep.points.astype("<f4").tobytes())
    extras = np.empty(len(sweep.points), LIDAR_EXTRAS_DTYPE)
    extras["time_offset"] = sweep.time_offsets
    extras["column"] = sweep.column
    extras["instance"] = sweep.instance
    extras["material"] = sweep.material
    atomic.save_npy(dataroot / extras_relpath(filename), extras)


JPEG_SUBSAMPLING = "4:2:0"  # chroma subsampling of the camera JPEGs, as nuScenes' own


def write_camera(dataroot: Path, filename: str, frame: CameraFrame, quality: int) -> None:
    """The image (``filename``, baseline JPEG at ``quality`` with 4:2:0 chroma subsampling, as nuScenes' cameras)
    and its exact range map (float16 .npy, uncompressed: later stages memory-map it)."""
    buf = io.BytesIO()
    Image.fromarray(frame.image).save(buf, format="JPEG", quality=quality, subsampling=JPEG_SUBSAMPLING)
    atomic.write_bytes(dataroot / filename, buf.getvalue())
    atomic.save_npy(dataroot / extras_relpath(filename), to_float16(frame.range))


def visible_fraction(layout: SceneLayout, actor: Actor, camera: Camera, frame: CameraFrame) -> tuple[int, int]:
    """(visible, unoccluded) pixel counts of ``actor`` in one camera on a stride-4 pixel grid: pixels where the actor
    is the nearest surface vs pixels its mesh covers when nothing else exists (the pixel rays of that grid tested
    against the actor's triangles alone, by the camera's exact rasteriser `raster.pinhole_depth`)."""
    T_global_cam = layout.T_global_ego(frame.timestamp) @ camera.T_ego_cam
    T_cam_body = invert(T_global_cam) @ actor.T_global_body(frame.timestamp)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (0, 1)], float)
    corners *= np.array([actor.size[1] / 2, actor.size[0] / 2, actor.size[2]])
    pc = apply(T_cam_body, corners)
    if (pc[:, 2] <= 0.1).all():
        return 0, 0
    uv, z = project(pc[pc[:, 2] > 0.1], camera.K)
    if (pc[:, 2] <= 0.1).any():
        u0, v0, u1, v1 = 0, 0, camera.width, camera.height
    else:
        u0, v0 = np.floor(uv.min(0)).astype(int)
        u1, v1 = np.ceil(uv.max(0)).astype(int) + 1
    u0, v0 = max(u0, 0), max(v0, 0)
    u1, v1 = min(u1, camera.width), min(v1, camera.height)
    if u0 >= u1 or v0 >= v1:
        return 0, 0
    us, vs = np.arange(u0, u1, VISIBILITY_STRIDE), np.arange(v0, v1, VISIBILITY_STRIDE)
    visible = int((frame.instance[np.ix_(vs, us)] == actor.instance).sum())
    # the grid's pixels as a camera of their own: pixel (i, j) is (u0 + 4 i, v0 + 4 j) of the full image
    K = camera.K
    K_grid = np.array([[K[0, 0] / VISIBILITY_STRIDE, 0.0, (K[0, 2] - u0) / VISIBILITY_STRIDE],
                       [0.0, K[1, 1] / VISIBILITY_STRIDE, (K[1, 2] - v0) / VISIBILITY_STRIDE], [0.0, 0.0, 1.0]])
    _, tri = pinhole_depth(apply(T_cam_body, actor.mesh.vertices), actor.mesh.triangles.astype(np.int64), K_grid,
                           len(us), len(vs))
    return visible, int((tri >= 0).sum())


def visibility_token(visible: int, unoccluded: int) -> int:
    """nuScenes visibility token (1..4) of a visible fraction."""
    frac = visible / unoccluded if unoccluded else 0.0
    return 1 + int(frac > 0.4) + int(frac > 0.6) + int(frac > 0.8)


SCENE_CACHE_SIZE = 2
"""Scenes whose ray caster a process keeps for its next samples (`scene_caster`)."""
_scene_cache: OrderedDict[tuple, WorldRaycaster] = OrderedDict()
_pattern_cache: dict[str, FiringPattern] = {}
_cache_lock = threading.Lock()


def scene_caster(spec: SceneSpec, cfg: WorldConfig, nthreads: int = 0) -> WorldRaycaster:
    """The `WorldRaycaster` of ``spec``'s layout. The process keeps the last `SCENE_CACHE_SIZE` scenes' casters
    (layout, BVHs, triangle tables, the static sun grid once built), so a worker rendering consecutive samples of a
    scene generates it once instead of once per sample; a caster is safe to share between threads (read only after
    construction)."""
    key = (spec, scene_duration_s(cfg), cfg.ego_speed_min, cfg.ego_speed_max, cfg.ego_body, nthreads)
    with _cache_lock:
        caster = _scene_cache.get(key)
        if caster is not None:
            _scene_cache.move_to_end(key)
            return caster
    body = ego_body_from_params(cfg.ego_body)
    caster = WorldRaycaster(spec.layout(cfg), nthreads=nthreads,
                            ego_body=None if body is None else ego_rear(body.corners()))
    with _cache_lock:
        caster = _scene_cache.setdefault(key, caster)
        _scene_cache.move_to_end(key)
        while len(_scene_cache) > SCENE_CACHE_SIZE:
            _scene_cache.popitem(last=False)
    return caster


def firing_pattern(cfg: WorldConfig) -> FiringPattern:
    """The LiDAR's `FiringPattern` (kept per LiDAR config)."""
    key = cfg.lidar.model_dump_json()
    with _cache_lock:
        pattern = _pattern_cache.get(key)
    if pattern is None:
        pattern = lidar_model_from_params(cfg.lidar).firing_pattern()
        for array in (pattern.directions, pattern.ring, pattern.column, pattern.time_offsets, pattern.elevations_deg):
            array.flags.writeable = False  # shared by every sample of the process
        with _cache_lock:
            _pattern_cache[key] = pattern
    return pattern


def render_sample(spec: SceneSpec, sample_index: int, cfg: WorldConfig, dataroot: Path,
                  nthreads: int = 0) -> SampleResult:
    """Render keyframe ``sample_index`` of scene ``spec``: its preceding LiDAR sweeps, the keyframe sweep, the six
    cameras and the annotations; write the files under ``dataroot``; return the records."""
    caster = scene_caster(spec, cfg, nthreads)
    layout = caster.layout
    pattern = firing_pattern(cfg)
    t_key = keyframe_time_us(spec, cfg, sample_index)
    lidar_records: list[SensorRecord] = []
    key_sweep: LidarSweep | None = None
    for j in range(cfg.sweeps_per_sample, -1, -1):
        t_us = t_key - j * SWEEP_PERIOD_US
        sweep = render_lidar_sweep(caster, pattern, lidar_model_from_params(cfg.lidar), t_us * 1e-6,
                                   sensor_rng(spec.seed, t_us % 2**31, 1))
        folder = "samples" if j == 0 else "sweeps"
        fname = sensor_filename(folder, spec.log_name, "LIDAR_TOP", t_us, "pcd.bin")
        write_sweep(dataroot, fname, sweep)
        tr, rot = _pose_lists(layout.T_global_ego(t_us * 1e-6))
        lidar_records.append(SensorRecord("LIDAR_TOP", t_us, fname, j == 0, 0, 0, tr, rot))
        if j == 0:
            key_sweep = sweep
    assert key_sweep is not None

    cameras = make_cameras(cfg.camera.image_scale)
    period_us = int(round(1e6 / cfg.lidar.frequency_hz))
    camera_records: list[SensorRecord] = []
    frames: list[tuple[Camera, CameraFrame]] = []
    for c, cam in enumerate(cameras):
        t_us = t_key + int(round(camera_time_offset(cam, period_us * 1e-6) * 1e6))
        frame = render_camera(caster, cam, cfg.camera, t_us * 1e-6, sensor_rng(spec.seed, t_us % 2**31, 2 + c))
        fname = sensor_filename("samples", spec.log_name, cam.channel, t_us, "jpg")
        write_camera(dataroot, fname, frame, cfg.camera.jpeg_quality)
        tr, rot = _pose_lists(layout.T_global_ego(t_us * 1e-6))
        camera_records.append(SensorRecord(cam.channel, t_us, fname, True, cam.width, cam.height, tr, rot))
        frames.append((cam, frame))

    annotations = annotate(caster, key_sweep, frames, t_key * 1e-6)
    return SampleResult(spec.index, sample_index, t_key, lidar_records, camera_records, annotations)


def annotate(caster: WorldRaycaster, key_sweep: LidarSweep, frames: list[tuple[Camera, CameraFrame]],
             t_key: float) -> list[AnnotationRecord]:
    """Boxes of the actors near the ego at keyframe time ``t_key`` [s] that at least one sensor observes (the scene
    of ``caster``)."""
    layout = caster.layout
    ego_xy = layout.T_global_ego(t_key)[:2, 3]
    counts = np.bincount(key_sweep.instance, minlength=len(layout.actors) + 1)
    out = []
    for actor in layout.actors:
        centre = actor.box_center_at(t_key)
        if np.hypot(*(centre[:2] - ego_xy)) > ANNOTATION_RADIUS_M:
            continue
        visible = unoccluded = 0
        for cam, frame in frames:
            v, u = visible_fraction(layout, actor, cam, frame)
            visible, unoccluded = visible + v, unoccluded + u
        n_pts = int(counts[actor.instance])
        if n_pts == 0 and visible == 0:
            continue
        out.append(AnnotationRecord(actor.instance, actor.category, actor.attribute, [float(v) for v in centre],
                                    [float(s) for s in actor.size], float(actor.yaw), n_pts,
                                    visibility_token(visible, unoccluded)))
    return out
