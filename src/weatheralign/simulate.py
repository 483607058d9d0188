"""Per-sample weather simulation of one condition, and the weather copy of a nuScenes-format dataroot.

One condition (``fog_light``, ``fog_dense``, ``snow``, ``rain``), aligned or unaligned, observed by every sensor of a
sample:

- LiDAR (keyframe scan): fog with the level's (alpha, beta) (`weatheralign.lidar.simulate_fog`), or the scene's
  particle field ``spec.field()`` (`weatheralign.lidar.simulate_particles`, its default frame = the scan's).
- Cameras, each at its own timestamp and ego pose: fog by Koschmieder on the camera's ray-length map — exact for
  the synthetic world (`CameraView.load_range`), dense depth from the LiDAR for real data (`camera_range_map`:
  `weatheralign.camera.depth.dense_depth` on `DEPTH_SWEEPS` aggregated, ego-compensated sweeps) — with one airlight
  per scene; snow/rain by splatting the field's resolvable
  particles (`weatheralign.camera.splat`) over the background seen through the unresolved particles' extinction
  (the splat module's contract: transmission ``exp(-τ_u(ℓ))``, same airlight, pre-fogged particle colours), with
  exposure streaks from the ego velocity (finite difference of the scan's ego poses).
- Aligned vs unaligned: snow/rain — the cameras observe ``spec.field(aligned=False)`` (independent seed, identical
  statistics) while the LiDAR always observes ``spec.field()``; fog — the cameras' alpha is drawn uniformly in
  ``[fog_alpha_light, fog_alpha_dense]`` once per scene (seeded by ``fog_seed``, the condition and the scene) while
  the LiDAR keeps its level's alpha; the camera's beta is irrelevant (Koschmieder needs alpha only).

The weather copy (`simulate_or_resume` per sample, then `finalize_copy`) holds the input's tables and maps
byte-for-byte (tokens, ``num_lidar_pts`` untouched), new keyframe LiDAR files and camera JPEGs at the same relative
paths, ``extras/LIDAR_TOP/<stem>.npy`` (the input's per-point records re-indexed to the new points: weather points
get ``instance`` 0 and ``material`` `WEATHER_MATERIAL`; clutter ``column`` -1) and
``extras/weather/LIDAR_TOP/<stem>.npy`` (per point ``label`` (0 unchanged, 1 attenuated, 2 scattered), ``particle_id``
(-1 if none), ``source_index`` (input row, -1 for clutter)). LiDAR sweeps are copied unchanged (with identity
labels) unless ``simulate.sweeps`` is set, which runs every sweep through the same medium (LiDAR only, no camera
exists at sweep times); the ``points_*`` metrics count keyframe scans, ``sweep_points_*`` the sweeps. The cameras'
range maps are not copied (the geometry is the clean dataroot's). Every file is written
atomically; finished samples leave a record in ``<out>/.progress/`` tagged with a config hash, so a rerun skips them.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from weatheralign import atomic
from weatheralign.camera.fog import (decode_srgb_u8, encode_srgb_u8, estimate_airlight, fog_image,
                                     refine_transmission, srgb_to_linear)
from weatheralign.camera.depth import dense_depth
from weatheralign.camera.splat import (RAIN, RAIN_OPAQUE_DROPS, SNOW, focal_px, materialize_for_camera,
                                       render_particles, unresolved_extinction_profile)
from weatheralign.config import SimulateConfig
from weatheralign.data.errors import DataFormatError
from weatheralign.data.frame import CameraView, Frame, LidarScan
from weatheralign.data.nuscenes import extras_relpath, load_frame, load_lidar
from weatheralign.lidar import simulate_fog, simulate_particles
from weatheralign.lidar.particles import RAIN_REFLECTIVITY, SNOW_REFLECTIVITY
from weatheralign.medium.conditions import FieldSpec
from weatheralign.medium.fog import mor_from_alpha
from weatheralign.metrics.reprojection import CameraParticles, lidar_particles, reprojection_check
from weatheralign.provenance import file_stamps, source_digest

CONDITIONS = ("fog_light", "fog_dense", "snow", "rain")
LABEL_NAMES = ("UNCHANGED", "ATTENUATED", "SCATTERED", "LOST")
WEATHER_MATERIAL = 255
"""``material`` of a point that is a weather echo (scattered or clutter) in the copied per-point extras."""
WEATHER_DTYPE = np.dtype([("label", "u1"), ("particle_id", "<i8"), ("source_index", "<i8")])
PROGRESS_DIR = ".progress"
SIMULATE_CODE = ("simulate.py", "camera", "lidar", "medium", "metrics", "data", "geometry.py", "provenance.py")
"""The library code a weather copy depends on (its resume records are tagged with its `source_digest`)."""
DEPTH_SWEEPS = 3
"""LiDAR sweeps aggregated for a real camera's dense depth (nuScenes: 3 HDL-32E sweeps cover ~2 % of an image)."""


def weather_relpath(filename: str) -> str:
    """``extras/weather/<channel>/<stem>.npy``: per-point labels and particle ids of a weather scan."""
    parts = Path(filename).parts
    return f"extras/weather/{parts[1]}/{parts[-1].split('.')[0]}.npy"


def condition_name(condition: str, aligned: bool) -> str:
    return f"{condition}-{'aligned' if aligned else 'unaligned'}"


# ------------------------------------------------------------------------------------------------ the weather
@dataclass(frozen=True)
class Weather:
    """One condition over one scene, as each sensor sees it.

    Attributes:
        condition: ``fog_light`` | ``fog_dense`` | ``snow`` | ``rain``; aligned: see the module docstring.
        lidar_alpha, lidar_beta: the LiDAR's fog [1/m], [1/(m sr)] (0 for snow/rain).
        camera_alpha: the cameras' fog extinction [1/m] (aligned: = lidar_alpha).
        field: the scene's `FieldSpec` (snow/rain), None for fog.
    """

    condition: str
    aligned: bool
    lidar_alpha: float = 0.0
    lidar_beta: float = 0.0
    camera_alpha: float = 0.0
    field: FieldSpec | None = None

    @property
    def is_fog(self) -> bool:
        return self.field is None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["field"] = None if self.field is None else self.field.to_dict()
        return d


def fog_level(cfg: SimulateConfig, condition: str) -> tuple[float, float]:
    """(alpha, beta) of a fog level: ``beta = fog_beta_mor / MOR`` unless ``fog_beta_<level>`` is set."""
    level = condition.removeprefix("fog_")
    alpha = cfg.fog_alpha_light if level == "light" else cfg.fog_alpha_dense
    beta = cfg.fog_beta_light if level == "light" else cfg.fog_beta_dense
    return alpha, (cfg.fog_beta_mor / mor_from_alpha(alpha) if beta is None else beta)


FOG_LEVELS_FILE = "calibrate_fog/fog_levels.json"
"""Tuned fog levels written by the calibrate_fog stage, relative to ``paths.data``:
``{"light": {"alpha": .., "beta": ..}, "dense": {...}, ...}``."""


def with_fog_levels(cfg: SimulateConfig, path: Path) -> SimulateConfig:
    """``cfg`` with ``fog_alpha_*`` / ``fog_beta_*`` replaced by the tuned levels in ``path`` (`FOG_LEVELS_FILE`).

    Raises:
        DataFormatError: missing or unreadable file, a missing level or key, a non-positive alpha, a negative beta,
            or a light level denser than the dense one.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing; run the calibrate_fog stage first (dvc repro calibrate_fog) or set "
                              f"simulate.fog_levels=params to use the literature levels")
    try:
        levels = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: not valid JSON ({exc})") from exc
    values: dict[str, float] = {}
    for level in ("light", "dense"):
        for key in ("alpha", "beta"):
            v = levels.get(level, {}).get(key) if isinstance(levels.get(level), dict) else None
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise DataFormatError(f"{path}: {level}.{key} = {v!r}; expected a finite number")
            values[f"fog_{key}_{level}"] = float(v)
        if values[f"fog_alpha_{level}"] <= 0.0 or values[f"fog_beta_{level}"] < 0.0:
            raise DataFormatError(f"{path}: {level} must have alpha > 0 and beta >= 0, got "
                                  f"{values[f'fog_alpha_{level}']}, {values[f'fog_beta_{level}']}")
    if values["fog_alpha_light"] > values["fog_alpha_dense"]:
        raise DataFormatError(f"{path}: light.alpha {values['fog_alpha_light']} exceeds dense.alpha "
                              f"{values['fog_alpha_dense']}")
    return SimulateConfig.model_validate({**cfg.model_dump(), **values})


def unaligned_fog_alpha(cfg: SimulateConfig, condition: str, scene: str) -> float:
    """The cameras' alpha for unaligned fog: uniform in ``[fog_alpha_light, fog_alpha_dense]``, one per scene."""
    digest = hashlib.sha256(f"{cfg.fog_seed}/{condition}/{scene}/camera".encode()).digest()
    u = int.from_bytes(digest[:8], "little") / 2.0**64
    return cfg.fog_alpha_light + u * (cfg.fog_alpha_dense - cfg.fog_alpha_light)


def weather_for_scene(cfg: SimulateConfig, scene: str, fields: dict | None = None, condition: str | None = None,
                      aligned: bool | None = None) -> Weather:
    """The `Weather` of ``scene`` (condition/aligned from ``cfg`` unless given; ``fields``: parsed fields.json)."""
    condition = cfg.condition if condition is None else condition
    aligned = cfg.aligned if aligned is None else aligned
    if condition.startswith("fog_"):
        alpha, beta = fog_level(cfg, condition)
        cam = alpha if aligned else unaligned_fog_alpha(cfg, condition, scene)
        return Weather(condition, aligned, alpha, beta, cam, None)
    if condition not in ("snow", "rain"):
        raise ValueError(f"condition = {condition!r} is invalid: expected one of {CONDITIONS}")
    if not fields or condition not in fields:
        raise ValueError(f"no {condition} fields given (run the particles stage: data/particles/fields.json)")
    specs = [FieldSpec.from_dict(d) for d in fields[condition]]
    for spec in specs:
        if spec.scene == scene:
            return Weather(condition, aligned, field=spec)
    raise ValueError(f"fields.json has no {condition} field for scene {scene!r} (has {[s.scene for s in specs]})")


# ------------------------------------------------------------------------------------------------ LiDAR
@dataclass(frozen=True, eq=False)
class LidarWeather:
    """A weather scan: ``scan`` (new points), per output point ``labels``, ``particle_id``, ``source_index``,
    ``times`` (firing time [s]); ``counts`` of the input points per label plus ``CLUTTER``."""

    scan: LidarScan
    labels: NDArray[np.uint8]
    particle_id: NDArray[np.int64]
    source_index: NDArray[np.int64]
    times: NDArray[np.float64]
    counts: dict[str, int]


def simulate_lidar(scan: LidarScan, weather: Weather, cfg: SimulateConfig) -> LidarWeather:
    """The scan through the weather's LiDAR medium (fog level, or the LiDAR's field ``spec.field()``)."""
    if weather.is_fog:
        res = simulate_fog(scan, weather.lidar_alpha, weather.lidar_beta, noise_floor=cfg.noise_floor)
        counts = {k: int(res.counts.get(k, 0)) for k in LABEL_NAMES}
        counts["CLUTTER"] = 0
        times = scan.point_times()[res.source_index]
        return LidarWeather(res.apply_to(scan), res.labels.astype(np.uint8), np.full(len(res.labels), -1, np.int64),
                            res.source_index.astype(np.int64), times, counts)
    spec = weather.field
    fld = None if spec.rate_mm_h <= 0.0 else spec.field()
    refl = SNOW_REFLECTIVITY if spec.condition == "snow" else RAIN_REFLECTIVITY
    res = simulate_particles(scan, fld, reflectivity=refl, noise_floor=cfg.noise_floor)
    counts = {k: int(res.counts.get(k, 0)) for k in (*LABEL_NAMES, "CLUTTER")}
    return LidarWeather(res.apply_to(scan), res.labels.astype(np.uint8), res.particle_id.astype(np.int64),
                        res.source_index.astype(np.int64), res.times.astype(np.float64), counts)


# ------------------------------------------------------------------------------------------------ cameras
def ego_velocity(scan: LidarScan) -> NDArray[np.float64]:
    """(3,) ego velocity [m/s] in the global frame from the scan's ego poses (finite difference), 0 if unknown."""
    if scan.poses is None or scan.pose_times is None or len(scan.pose_times) < 2:
        return np.zeros(3)
    dt = float(scan.pose_times[-1] - scan.pose_times[0])
    if dt <= 0.0:
        return np.zeros(3)
    return (scan.poses[-1][:3, 3] - scan.poses[0][:3, 3]) / dt


@dataclass(frozen=True, eq=False)
class CameraWeather:
    """A weather image (``image`` uint8 sRGB, or None = the input file unchanged), the particles it drew
    (`CameraParticles` for the re-projection check, None for fog) and ``drawn`` (number of particles drawn)."""

    image: NDArray[np.uint8] | None
    particles: CameraParticles | None
    drawn: int


def camera_range_map(view: CameraView, lidar: LidarScan, image: NDArray | None = None) -> NDArray[np.float32]:
    """(H, W) float32 ray length [m] of ``view`` (inf = sky): the exact map where the dataset has one (synthetic
    world), else dense depth from ``lidar`` (aggregate `DEPTH_SWEEPS` sweeps first for nuScenes)."""
    if view.range_path is not None:
        return view.load_range()
    return dense_depth(lidar, view, image).range


def simulate_camera(view: CameraView, weather: Weather, cfg: SimulateConfig, airlight: NDArray,
                    ego_vel: NDArray, depth_lidar: LidarScan) -> CameraWeather:
    """One camera through the weather (see the module docstring). ``airlight``: the scene's sRGB airlight (3,);
    ``depth_lidar``: the LiDAR for a dense ray-length map where the view has no exact one (`camera_range_map`)."""
    spec = weather.field
    if weather.is_fog:
        if weather.camera_alpha <= 0.0:
            return CameraWeather(None, None, 0)
        img = view.load_image()
        return CameraWeather(fog_image(img, camera_range_map(view, depth_lidar, img), weather.camera_alpha, airlight,
                                       refine=cfg.refine_transmission), None, 0)
    if spec.rate_mm_h <= 0.0:
        return CameraWeather(None, None, 0)
    img = view.load_image()
    rng = camera_range_map(view, depth_lidar, img)
    fld = spec.field(aligned=weather.aligned)
    look = SNOW if spec.condition == "snow" else (RAIN if cfg.rain_appearance == "rain" else RAIN_OPAQUE_DROPS)
    near = cfg.near_clip_m
    profile = unresolved_extinction_profile(fld, focal_px(view.K), look, near_clip=near)
    t = profile.transmission(rng)
    if cfg.refine_transmission:
        t = refine_transmission(t, img)
    a_lin = srgb_to_linear(np.asarray(airlight, dtype=np.float64))
    t3 = t[..., None]
    background = decode_srgb_u8(img) * t3 + a_lin.astype(np.float32) * (np.float32(1.0) - t3)
    T_global_cam = view.T_global_cam
    v_rel = fld.velocity_array - np.asarray(ego_vel, dtype=np.float64)
    parts = materialize_for_camera(fld, view.K, view.width, view.height, T_global_cam, view.timestamp, look,
                                   near_clip=near, streak_m=float(np.linalg.norm(v_rel)) * cfg.exposure_s)
    res = render_particles(background.astype(np.float32), rng, view.K, np.linalg.inv(T_global_cam), parts.positions,
                           parts.diameters, parts.ids, fld.velocity_array, ego_vel, exposure_s=cfg.exposure_s,
                           appearance=look, fog_alpha=0.0, airlight=a_lin, unresolved=profile, near_clip=near)
    cp = CameraParticles(view.channel, view.K, T_global_cam, view.timestamp, view.width, view.height, parts.ids,
                         res.centroids, res.drawn & res.unoccluded & res.in_frame, rng, profile.r_end)
    return CameraWeather(encode_srgb_u8(res.image), cp, int(res.drawn.sum()))


def scene_airlight(views: list[CameraView]) -> NDArray[np.float64]:
    """One airlight for a scene from its cameras (e.g. its first sample's six): `estimate_airlight`, neutral grey."""
    return estimate_airlight([v.load_image() for v in views], [v.load_range() if v.range_path else None for v in views])


# ------------------------------------------------------------------------------------------------ one frame
@dataclass(frozen=True, eq=False)
class FrameWeather:
    """Everything the weather did to one frame."""

    lidar: LidarWeather
    cameras: dict[str, CameraWeather]
    reprojection_px: NDArray[np.float64]
    reprojection_channels: list[str] = field(default_factory=list)

    @property
    def particles_rendered(self) -> int:
        return sum(c.drawn for c in self.cameras.values())


def simulate_frame(frame: Frame, weather: Weather, cfg: SimulateConfig, airlight: NDArray,
                   nthreads: int = 1, depth_lidar: LidarScan | None = None) -> FrameWeather:
    """LiDAR and cameras of ``frame`` through ``weather``; for snow/rain also the re-projection errors [px].

    ``depth_lidar``: LiDAR for the dense depth of cameras without an exact range map (default: ``frame.lidar``).
    """
    vel = ego_velocity(frame.lidar)
    depth_src = frame.lidar if depth_lidar is None else depth_lidar
    with ThreadPoolExecutor(max_workers=max(1, nthreads)) as pool:
        lidar_future = pool.submit(simulate_lidar, frame.lidar, weather, cfg)
        cams = dict(zip(frame.cameras, pool.map(lambda v: simulate_camera(v, weather, cfg, airlight, vel, depth_src),
                                                frame.cameras.values())))
        lidar = lidar_future.result()
    errors, channels = np.zeros(0), []
    if not weather.is_fog and weather.field.rate_mm_h > 0.0:
        ids, times = lidar_particles(lidar.particle_id, lidar.times, lidar.labels)
        rendered = [c.particles for c in cams.values() if c.particles is not None]
        check = reprojection_check(weather.field.field(), ids, times, rendered, weather.aligned, cfg.near_clip_m)
        errors, channels = check.error_px, check.channel
    return FrameWeather(lidar, cams, errors, channels)


# ------------------------------------------------------------------------------------------------ the copy
def config_hash(cfg: SimulateConfig, weather: Weather, source: Path, jpeg_quality: int) -> str:
    """Hash of the parameters and the code that change a sample's weather files (the input files are stamped per
    sample by `simulate_or_resume`)."""
    blob = json.dumps({"cfg": cfg.model_dump(mode="json", exclude={"max_samples"}), "weather": weather.to_dict(),
                       "source": str(Path(source).resolve()), "jpeg_quality": jpeg_quality,
                       "code": source_digest(*SIMULATE_CODE)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _sample_files(nusc, sample_token: str) -> tuple[str, list[str]]:
    sample = nusc.get("sample", sample_token)
    lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["filename"]
    cams = [nusc.get("sample_data", tok)["filename"] for ch, tok in sorted(sample["data"].items())
            if ch.startswith("CAM")]
    return lidar, cams


def sweep_records(nusc, sample_token: str) -> list[dict]:
    """The LiDAR sweeps (non-keyframe sample_data) between the previous keyframe and this sample's, oldest first."""
    sd = nusc.get("sample_data", nusc.get("sample", sample_token)["data"]["LIDAR_TOP"])
    out = []
    while sd["prev"]:
        sd = nusc.get("sample_data", sd["prev"])
        if sd["is_key_frame"]:
            break
        out.append(sd)
    return out[::-1]


def _outputs(nusc, sample_token: str, sweeps: bool = False) -> list[str]:
    lidar, cams = _sample_files(nusc, sample_token)
    scans = [lidar] + ([sd["filename"] for sd in sweep_records(nusc, sample_token)] if sweeps else [])
    return [rel for f in scans for rel in (f, extras_relpath(f), weather_relpath(f))] + cams


def _progress_file(out_root: Path, sample_token: str) -> Path:
    return out_root / PROGRESS_DIR / f"{sample_token}.json"


def load_finished(nusc, sample_token: str, out_root: Path, digest: str, sweeps: bool = False) -> dict | None:
    """The record of a sample finished by an earlier run with the same config hash, if all its files exist."""
    marker = _progress_file(out_root, sample_token)
    if not marker.is_file():
        return None
    record = json.loads(marker.read_text())
    if record.get("config") != digest:
        return None
    if not all((out_root / rel).is_file() for rel in _outputs(nusc, sample_token, sweeps)):
        return None
    return record


def _copy_file(src: Path, dst: Path) -> None:
    with atomic.atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def _new_extras(src_extras: Path, lw: LidarWeather, scan_timestamp: float) -> NDArray | None:
    """The input's per-point records re-indexed to the weather points (None if the input has none)."""
    if not src_extras.is_file():
        return None
    ex = np.load(src_extras)
    src = lw.source_index
    out = np.zeros(len(src), dtype=ex.dtype)
    kept = src >= 0
    out[kept] = ex[src[kept]]
    out["time_offset"] = (lw.times - scan_timestamp).astype(np.float32)
    out["time_offset"][kept] = ex["time_offset"][src[kept]]
    if "column" in ex.dtype.names:
        out["column"][~kept] = -1
    weather_pt = lw.labels == 2
    if "instance" in ex.dtype.names:
        out["instance"][weather_pt] = 0
    if "material" in ex.dtype.names:
        out["material"][weather_pt] = WEATHER_MATERIAL
    return out


def write_scan(src_root: Path, out_root: Path, rel: str, lw: LidarWeather, timestamp: float) -> None:
    """A weather scan at ``rel``: the points, the re-indexed per-point extras and the weather labels (atomically)."""
    atomic.write_bytes(out_root / rel, lw.scan.points.astype("<f4").tobytes())
    extras = _new_extras(Path(src_root) / extras_relpath(rel), lw, timestamp)
    if extras is None:  # no input extras: per-point firing times alone, so the reader gets exact times
        extras = np.zeros(len(lw.labels), dtype=[("time_offset", "<f4")])
        extras["time_offset"] = (lw.times - timestamp).astype(np.float32)
    atomic.save_npy(out_root / extras_relpath(rel), extras)
    rec = np.zeros(len(lw.labels), dtype=WEATHER_DTYPE)
    rec["label"], rec["particle_id"], rec["source_index"] = lw.labels, lw.particle_id, lw.source_index
    atomic.save_npy(out_root / weather_relpath(rel), rec)


def write_sample(src_root: Path, out_root: Path, nusc, sample_token: str, fw: FrameWeather, frame: Frame,
                 jpeg_quality: int) -> None:
    """Write one sample's weather files (atomically) at the input's relative paths."""
    lidar_rel, _ = _sample_files(nusc, sample_token)
    write_scan(src_root, out_root, lidar_rel, fw.lidar, frame.lidar.timestamp)
    sample = nusc.get("sample", sample_token)
    for ch, view in frame.cameras.items():
        rel = nusc.get("sample_data", sample["data"][ch])["filename"]
        cw = fw.cameras[ch]
        if cw.image is None:
            _copy_file(view.image_path, out_root / rel)
        else:
            buf = io.BytesIO()
            Image.fromarray(cw.image).save(buf, format="JPEG", quality=jpeg_quality, subsampling=0)
            atomic.write_bytes(out_root / rel, buf.getvalue())


def simulate_or_resume(nusc, src_root: Path, out_root: Path, sample_token: str, weather: Weather,
                       cfg: SimulateConfig, airlight: NDArray, jpeg_quality: int = 92,
                       nthreads: int = 1) -> tuple[dict, bool]:
    """Simulate and write one sample unless an identical earlier run finished it. Returns (record, done_now).

    The record holds the LiDAR counts, the particles rendered, the re-projection errors and the seconds taken.
    """
    src_root, out_root = Path(src_root), Path(out_root)
    if src_root.resolve() == out_root.resolve():
        raise ValueError(f"the weather copy must not overwrite its input {src_root}")
    digest = config_hash(cfg, weather, src_root, jpeg_quality) + file_stamps(src_root, _outputs(nusc, sample_token,
                                                                                                cfg.sweeps))
    done = load_finished(nusc, sample_token, out_root, digest, cfg.sweeps)
    if done is not None:
        return done, False
    t0 = time.time()
    frame = load_frame(nusc, sample_token)
    exact = all(v.range_path is not None for v in frame.cameras.values())
    depth_lidar = None if exact else load_lidar(nusc, nusc.get("sample", sample_token)["data"]["LIDAR_TOP"],
                                                DEPTH_SWEEPS)
    fw = simulate_frame(frame, weather, cfg, airlight, nthreads, depth_lidar)
    write_sample(src_root, out_root, nusc, sample_token, fw, frame, jpeg_quality)
    sweep_counts = {k: 0 for k in (*LABEL_NAMES, "CLUTTER")}
    if cfg.sweeps:  # the same medium through every sweep of the sample (LiDAR only)
        for sd in sweep_records(nusc, sample_token):
            scan = load_lidar(nusc, sd["token"])
            lw = simulate_lidar(scan, weather, cfg)
            write_scan(src_root, out_root, sd["filename"], lw, scan.timestamp)
            for k, v in lw.counts.items():
                sweep_counts[k] += v
    record = {"config": digest, "sample": sample_token, "counts": fw.lidar.counts, "sweep_counts": sweep_counts,
              "particles_rendered": fw.particles_rendered,
              "reprojection_px": [float(e) for e in fw.reprojection_px],
              "reprojection_channels": list(fw.reprojection_channels), "seconds": round(time.time() - t0, 3)}
    atomic.write_json(_progress_file(out_root, sample_token), record)
    return record, True


def finalize_copy(nusc, src_root: Path, out_root: Path, version: str) -> int:
    """Complete the weather copy: every sensor file not simulated (sweeps) copied unchanged with its LiDAR extras,
    identity labels for keyframe scans left clear, then the ``<version>/`` tables and ``maps/`` byte-for-byte
    (last, so the copy loads only once complete).
    Returns the number of files copied now."""
    src_root, out_root = Path(src_root), Path(out_root)
    copied = 0
    for sd in nusc.sample_data:
        rels = [sd["filename"]]
        if not sd["filename"].split("/")[1].startswith("CAM"):
            rels.append(extras_relpath(sd["filename"]))
        for rel in rels:
            src, dst = src_root / rel, out_root / rel
            if src.is_file() and not dst.is_file():
                _copy_file(src, dst)
                copied += 1
        label_file = out_root / weather_relpath(sd["filename"])
        if sd["sensor_modality"] == "lidar" and not label_file.is_file():
            # a scan left clear (sweeps by default, samples beyond ``max_samples``): identity labels, so every
            # scan of the copy has its record
            n = (out_root / sd["filename"]).stat().st_size // 20
            rec = np.zeros(n, dtype=WEATHER_DTYPE)
            rec["particle_id"], rec["source_index"] = -1, np.arange(n)
            atomic.save_npy(label_file, rec)
    for top in ("maps", version):
        for src in sorted((src_root / top).rglob("*")):
            if src.is_file():
                dst = out_root / src.relative_to(src_root)
                if not (dst.is_file() and dst.read_bytes() == src.read_bytes()):
                    _copy_file(src, dst)
                    copied += 1
    return copied


def summarise(records: list[dict]) -> dict:
    """Stage metrics from the per-sample records."""
    counts = {k: sum(r["counts"].get(k, 0) for r in records) for k in (*LABEL_NAMES, "CLUTTER")}
    errors = np.array([e for r in records for e in r["reprojection_px"]], dtype=np.float64)
    return {
        "points_unchanged": counts["UNCHANGED"], "points_attenuated": counts["ATTENUATED"],
        "points_scattered": counts["SCATTERED"] + counts["CLUTTER"], "points_clutter": counts["CLUTTER"],
        "points_lost": counts["LOST"], "particles_rendered": sum(r["particles_rendered"] for r in records),
        "reprojection_mean_px": float(errors.mean()) if errors.size else None,
        "reprojection_max_px": float(errors.max()) if errors.size else None,
        "reprojection_p99_px": float(np.percentile(errors, 99)) if errors.size else None,
        "reprojection_pairs": int(errors.size), "num_samples": len(records),
        "sweep_points_scattered": sum(r.get("sweep_counts", {}).get("SCATTERED", 0)
                                      + r.get("sweep_counts", {}).get("CLUTTER", 0) for r in records),
        "sweep_points_lost": sum(r.get("sweep_counts", {}).get("LOST", 0) for r in records),
        "seconds_per_sample": round(float(np.mean([r["seconds"] for r in records])), 3) if records else None,
    }


__all__ = ["CONDITIONS", "FOG_LEVELS_FILE", "CameraWeather", "FrameWeather", "LidarWeather", "Weather",
           "camera_range_map", "condition_name", "config_hash", "ego_velocity", "finalize_copy", "fog_level",
           "scene_airlight", "simulate_camera", "simulate_frame", "simulate_lidar", "simulate_or_resume",
           "summarise", "sweep_records", "unaligned_fog_alpha", "weather_for_scene", "weather_relpath",
           "with_fog_levels", "write_sample", "write_scan"]
