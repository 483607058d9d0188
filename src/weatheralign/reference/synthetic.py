"""The embedded synthetic reference: a Seeing Through Fog-like dataset with hidden fog levels, snow and rain rates.

What it is. ``frames_per_split`` frames in each level (clear, light fog, dense fog, and snow and rain where
``reference.split_files`` names them), written in the STF layout (`weatheralign.reference.layout`) under
``<paths.data>/reference/synthetic``, from procedural streets of the synthetic world (`weatheralign.world.layout`)
whose seeds derive from ``reference.seed`` with a tag of their own (so they are never the simulation world's scenes,
whatever the seeds). Frame ``k`` of the clear and fog levels comes from scene ``k``, each level at its own time along
the drive (3 s apart, slot order drawn per scene): the levels never share a frame, and their scene statistics match,
as a reference recorded on the same roads in different weather. Snow and rain frames come from recordings of their
own (scene ``k`` of ``<level>``, drawn the same way: other days, other streets of the same kind).

Hidden truth. The light and dense levels' extinction α is drawn uniformly in ``alpha_light`` / ``alpha_dense`` and
the backscatter as ``β = 0.023 f / MOR`` (``f ~ U[beta_factor]``, ``MOR = ln 20 / α``), redrawn while α lies within
3 % of a point of the calibration grid `ALPHA_GRID` or ``f`` within 0.02 of the paper's β factors (so the truth is
never on a grid point). It is written only to ``<paths.data>/reference/sealed_truth.json`` as
``{level: {alpha, beta}}`` (outside the reference root; per-frame airlights go to ``sealed_details.json``): the
calibration never reads them, the tests and audits do.

Hidden snow and rain. One rate per split, drawn uniformly in ``precipitation.snow_rate_mm_h`` /
``rain_rate_mm_h`` and sealed beside the fog levels as ``{snow|rain: {rate_mm_h}}``. Each snow / rain frame has a
field of its own (`weatheralign.medium.field.ParticleField`, seed from ``reference.seed`` and the frame): the particle
positions come from the medium, as in the real world, and both sensors see the same particles.

Hidden ground. The rain split's road lies under a water film, the snow split's under lying snow with wheel tracks,
at one hidden depth per split (`weatheralign.reference.ground`: drawn in ``precipitation.wet_film_depth_m`` /
``snow_depth_m``, sealed as ``{rain: {film_depth_m}}``, ``{snow: {snow_depth_m}}``), on the scene's true surfaces,
seen by the LiDAR and the camera before the particles.

Hidden light. Snow and rain fall from a cloud deck: both splits are lit by an overcast sky of a hidden zenith
luminance and what the cloud leaves of the sun (`weatheralign.reference.overcast`: drawn per split in
``precipitation.overcast_sun_transmittance`` / ``overcast_zenith_luminance``, sealed as ``{snow|rain:
{sun_transmittance, zenith_luminance}}``); the clear and fog levels keep the clear sky and the sun.

Sensors (one instant per frame: every beam at the frame time, STF has no per-point times; the camera integrates its
exposure around it):
- LiDAR: an HDL-64-like sensor (64 lasers at the `weatheralign.data.rings` HDL-64E elevations, ``firings_per_ring``
  azimuths, roof mount 1.95 m above the ground), ray-cast against the scene; a hit's clear intensity is the world's
  ``255 ρ |cos θ| min(1, 10 m / R)`` on the textured reflectivity. Fog by the exact pulse integral of every beam
  (`weatheralign.reference.lidar_exact`: bi-static overlap, summed soft + hard echoes, strongest peak, no-return
  beams included), then the detector (noise floor, intensity noise, integer quantisation, range noise). The clear
  level goes through the same chain with α = β = 0. Snow and rain: Monte-Carlo sub-rays across each beam's cone
  through the frame's particles, the full waveform and its strongest peak
  (`weatheralign.reference.lidar_particles_exact`), then the same detector. Points: float32 N x 5 ``x, y, z, intensity
  0..255, channel`` in the LiDAR frame, channel = 63 - ring (STF: channel 0 is the lowest laser).
- Camera: a stereo-left-like pinhole with Seeing Through Fog's rectified intrinsics (f = 2355.7 px on 1920 x 1024)
  scaled by ``image_scale``, 0.7 m ahead of and 0.7 m below the LiDAR, looking forward; the world's shading in linear
  light, fog by per-pixel integration (`weatheralign.reference.camera_exact`) with the level's true α and an sRGB
  grey airlight drawn per frame in ``[airlight_min, airlight_max]``; snow and rain by per-pixel ray tracing of the
  particles with supersampling over the pixel and the exposure (`weatheralign.reference.camera_particles_exact`:
  flakes are Lambertian spheres of albedo 0.9 under the scene's sky and sun, drops show the environment they
  refract); sensor noise, PNG. Its exact ray length per pixel
  goes to ``range_cam_stereo_left/<id>.npy`` (float32, inf = sky). Calibration files in STF's form.

Files are written atomically; a finished frame leaves ``<paths.data>/reference/.progress/<id>.json`` tagged with a
hash of the parameters and of the code, so a rerun skips it (`render_or_resume`); `finalize` writes the split files,
calibration, manifest and sealed truth and removes files of frames no longer in the reference.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image
from scipy.spatial.transform import Rotation

from weatheralign import atomic
from weatheralign.camera.fog import srgb_to_linear
from weatheralign.config import ReferenceConfig
from weatheralign.data.rings import HDL64E_ELEVATIONS_DEG
from weatheralign.data.stf import CAMERA_CALIB_FILE, CAMERA_TF_FRAME, LIDAR_TF_FRAME, TF_TREE_FILE
from weatheralign.geometry import camera_rotation_from_yaw, make_transform
from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.edit import edit_image
from weatheralign.medium.distributions import RainSizeDistribution, SnowSizeDistribution
from weatheralign.medium.field import ParticleField
from weatheralign.medium.fog import LN20, PAPER_BETA_FACTORS
from weatheralign.provenance import read_resume_record, stage_code_digest, write_resume_record
from weatheralign.reference.camera_exact import encode_with_noise, fog_radiance
from weatheralign.reference.camera_particles_exact import particle_image
from weatheralign.reference.ground import draw_ground_truth, exact_surfaces, frame_ground_state, ground_hits
from weatheralign.reference.layout import (
    CAMERA_FOLDER,
    FOG_LEVELS,
    LEVELS,
    LIDAR_FOLDER,
    PRECIPITATION_LEVELS,
    RANGE_FOLDER,
    split_files_of,
)
from weatheralign.reference.lidar_exact import (
    FOG,
    TARGET,
    Detector,
    ExactSensor,
    exact_returns,
    fog_tables,
    read_out,
    system_constants,
)
from weatheralign.reference.lidar_particles_exact import PARTICLE, particle_returns
from weatheralign.reference.overcast import (
    OvercastTruth,
    draw_overcast_truth,
    drop_radiance,
    flake_radiance,
    overcast_radiance,
    visible_hemisphere,
)
from weatheralign.sensors import SYNTHETIC_INTENSITY
from weatheralign.world.layout import generate_layout
from weatheralign.world.raycast import WorldRaycaster
from weatheralign.world.render import pixel_directions, sun_lit
from weatheralign.world.rig import Camera
from weatheralign.world.shading import SUN_COLOUR, camera_radiance, lidar_intensity, texture

F64 = NDArray[np.float64]

SYNTHETIC_DIR = "synthetic"
PROGRESS_DIR = ".progress"
SEALED_TRUTH_FILE = "sealed_truth.json"
SEALED_DETAILS_FILE = "sealed_details.json"
MANIFEST_FILE = "reference.json"

ALPHA_GRID: tuple[float, ...] = (0.001, 0.005, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1)
"""The calibration's α grid [1/m]: the hidden truth keeps at least 3 % away from each point."""

STF_FULL_SIZE = (1920, 1024)
STF_FOCAL_PX = 2355.722801
STF_PRINCIPAL_PX = (988.138054, 508.051838)
T_EGO_LIDAR = make_transform(np.eye(3), np.array([1.42, 0.0, 1.95]))
"""HDL-64 roof mount in the ego frame (x forward, y left, z up, origin on the ground)."""
T_EGO_CAMERA = make_transform(camera_rotation_from_yaw(0.0), np.array([2.12, 0.087, 1.25]))
"""Stereo-left camera (OpenCV optical axes) in the ego frame, looking forward."""

EGO_SPEED_RANGE = (5.0, 12.0)
FIRST_FRAME_S = 0.5
FRAME_GAP_S = 3.0
SCENE_DURATION_S = FIRST_FRAME_S + 2 * FRAME_GAP_S + 1.0
FRAME_RATE_HZ = 10.0

_SCENE_TAG, _TRUTH_TAG, _NOISE_TAG = 0x5EF5CE, 0x5EA1ED, 0x5E4503
_WEATHER_SCENE_TAG, _RATE_TAG, _FIELD_TAG = 0x5E5C0E, 0x5E7A7E, 0x5EF1E1
FOG_SCENE_LEVELS = ("clear", *FOG_LEVELS)
"""Levels that share scene ``k`` (three time slots of one drive)."""

SNOW_CELL_M, RAIN_CELL_M = 2.0, 1.0
"""Field cell sizes [m] (as the particles stage's defaults)."""
RAIN_FIELD_FALL_M_S = 4.0
"""Nominal fall speed [m/s] of the rain field's frame: it only translates the field (positions are taken at the frame
time); in the camera's exposure each drop falls at its own diameter's terminal speed."""


def reference_dir(data: Path) -> Path:
    """``<paths.data>/reference``: the stage's output folder."""
    return Path(data) / "reference"


def synthetic_root(data: Path) -> Path:
    """The synthetic reference root (STF layout) under ``<paths.data>``."""
    return reference_dir(data) / SYNTHETIC_DIR


def sealed_truth_path(data: Path) -> Path:
    """``<paths.data>/reference/sealed_truth.json`` (never read by the calibration)."""
    return reference_dir(data) / SEALED_TRUTH_FILE


# ------------------------------------------------------------------------------------------------ truth and frames


@dataclass(frozen=True)
class FogLevel:
    """A fog level: extinction ``alpha`` [1/m], backscatter ``beta`` [1/(m sr)] (both 0: clear)."""

    alpha: float
    beta: float

    @property
    def mor(self) -> float:
        """Visibility ``ln 20 / alpha`` [m] (inf for clear air)."""
        return math.inf if self.alpha == 0.0 else LN20 / self.alpha


CLEAR = FogLevel(0.0, 0.0)


def _away_from(value: float, grid: tuple[float, ...], relative: float | None, absolute: float | None) -> bool:
    for g in grid:
        if relative is not None and abs(value / g - 1.0) < relative:
            return False
        if absolute is not None and abs(value - g) < absolute:
            return False
    return True


def draw_truth(cfg: ReferenceConfig) -> dict[str, FogLevel]:
    """The hidden fog levels ``{"clear": CLEAR, "light": ..., "dense": ...}`` drawn from ``cfg.seed`` (see the
    module docstring); deterministic."""
    rng = np.random.default_rng([cfg.seed, _TRUTH_TAG])
    out = {"clear": CLEAR}
    for level, (lo, hi) in (("light", cfg.alpha_light), ("dense", cfg.alpha_dense)):
        for _ in range(1000):
            alpha = float(rng.uniform(lo, hi))
            if _away_from(alpha, ALPHA_GRID, 0.03, None):
                break
        for _ in range(1000):
            factor = float(rng.uniform(*cfg.beta_factor))
            if _away_from(factor, PAPER_BETA_FACTORS, None, 0.02):
                break
        out[level] = FogLevel(alpha, 0.023 * factor * alpha / LN20)
    return out


def draw_precipitation_truth(cfg: ReferenceConfig) -> dict[str, float]:
    """The hidden rates ``{"snow": mm/h water equivalent, "rain": mm/h}``, uniform in
    ``cfg.precipitation.snow_rate_mm_h`` / ``rain_rate_mm_h``, drawn from ``cfg.seed``; deterministic."""
    rng = np.random.default_rng([cfg.seed, _RATE_TAG])
    pc = cfg.precipitation
    return {"snow": float(rng.uniform(*pc.snow_rate_mm_h)), "rain": float(rng.uniform(*pc.rain_rate_mm_h))}


@dataclass(frozen=True)
class FrameSpec:
    """One reference frame (small, picklable): level, index ``k`` (= scene), time slot along the drive, the scene's
    seed / placement / start time [s], and the frame's airlight (sRGB grey, used in fog)."""

    level: str
    index: int
    slot: int
    recording: str
    scene_seed: int
    origin: tuple[float, float]
    heading: float
    t_start: float
    airlight: float

    @property
    def time(self) -> float:
        """Capture time [s]."""
        return self.t_start + FIRST_FRAME_S + self.slot * FRAME_GAP_S

    @property
    def frame_number(self) -> int:
        """STF frame index: the capture time in 10 Hz frames since the recording started."""
        return int(round((FIRST_FRAME_S + self.slot * FRAME_GAP_S) * FRAME_RATE_HZ))

    @property
    def sample_id(self) -> str:
        """``<recording>_<frame:05d>``."""
        return f"{self.recording}_{self.frame_number:05d}"


def frame_specs(cfg: ReferenceConfig) -> list[FrameSpec]:
    """Every frame of the reference, level by level (`LEVELS` order; snow and rain only where ``cfg.split_files``
    names them), index ascending. Frame ``k`` of any level depends only on ``cfg.seed``, the level and ``k`` (not on
    ``frames_per_split`` or on which other levels exist)."""
    specs = []
    weather = [level for level in PRECIPITATION_LEVELS if level in split_files_of(cfg.split_files)]
    for k in range(cfg.frames_per_split):
        rng = np.random.default_rng([cfg.seed, _SCENE_TAG, k])
        scene_seed = int(rng.integers(0, 2**31 - 1))
        origin = (float(rng.uniform(-2000.0, 2000.0)), float(rng.uniform(-2000.0, 2000.0)))
        heading = float(rng.uniform(-np.pi, np.pi))
        slots = rng.permutation(len(FOG_SCENE_LEVELS))
        airlights = rng.uniform(cfg.camera.airlight_min, cfg.camera.airlight_max, len(FOG_SCENE_LEVELS))
        recording = f"synref-{cfg.seed}-{k:04d}"
        for j, level in enumerate(FOG_SCENE_LEVELS):
            specs.append(FrameSpec(level, k, int(slots[j]), recording, scene_seed, origin, heading,
                                   1000.0 + 3600.0 * k, float(airlights[j])))
        for level in weather:
            wrng = np.random.default_rng([cfg.seed, _WEATHER_SCENE_TAG, LEVELS.index(level), k])
            specs.append(FrameSpec(level, k, int(wrng.integers(0, len(FOG_SCENE_LEVELS))),
                                   f"synref-{cfg.seed}-{level}-{k:04d}", int(wrng.integers(0, 2**31 - 1)),
                                   (float(wrng.uniform(-2000.0, 2000.0)), float(wrng.uniform(-2000.0, 2000.0))),
                                   float(wrng.uniform(-np.pi, np.pi)), 1000.0 + 3600.0 * k, 0.0))
    order = {level: i for i, level in enumerate(LEVELS)}
    return sorted(specs, key=lambda s: (order[s.level], s.index))


# ------------------------------------------------------------------------------------------------ sensors


def sensor_of(cfg: ReferenceConfig) -> tuple[ExactSensor, Detector]:
    """The reference LiDAR (pulse, overlap, ranges) and its detector from the config."""
    lc = cfg.lidar
    sensor = ExactSensor(tau_h=lc.tau_h_s, r1=lc.overlap_r1_m, r2=lc.overlap_r2_m, fov_ratio=lc.overlap_fov_ratio,
                         min_range=lc.min_range_m, max_range=lc.max_range_m)
    return sensor, Detector(lc.intensity_noise_std, lc.intensity_noise_rel, lc.noise_floor, lc.range_noise_std_m,
                            SYNTHETIC_INTENSITY, lc.floor_range_m)


@dataclass(frozen=True)
class FiringGrid:
    """HDL-64-like beams in the LiDAR frame: ``directions`` (64 F, 3) unit, ``ring`` (64 F,) 0 = highest laser,
    column-major (index = column * 64 + ring)."""

    directions: F64
    ring: NDArray[np.int16]


def hdl64_grid(firings_per_ring: int) -> FiringGrid:
    """64 lasers at the HDL-64E elevations x ``firings_per_ring`` azimuths over a full turn (clockwise from behind)."""
    elev = np.deg2rad(HDL64E_ELEVATIONS_DEG)
    rings = len(elev)
    col = np.repeat(np.arange(firings_per_ring), rings)
    ring = np.tile(np.arange(rings), firings_per_ring)
    azimuth = np.pi - 2.0 * np.pi * (col + 0.5) / firings_per_ring
    e = elev[ring]
    d = np.stack([np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.sin(e)], 1)
    return FiringGrid(d, ring.astype(np.int16))


def stereo_left_camera(image_scale: float) -> Camera:
    """The stereo-left-like camera at ``image_scale`` of 1920 x 1024 (STF's rectified intrinsics, scaled)."""
    width, height = (int(round(STF_FULL_SIZE[0] * image_scale)), int(round(STF_FULL_SIZE[1] * image_scale)))
    sx, sy = width / STF_FULL_SIZE[0], height / STF_FULL_SIZE[1]
    K = np.array([[STF_FOCAL_PX * sx, 0.0, STF_PRINCIPAL_PX[0] * sx],
                  [0.0, STF_FOCAL_PX * sy, STF_PRINCIPAL_PX[1] * sy], [0.0, 0.0, 1.0]])
    return Camera("cam_stereo_left", K, width, height, T_EGO_CAMERA, 0.0)


# ------------------------------------------------------------------------------------------------ one frame


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered frame: ``points`` (N, 5) float32 (STF columns), ``image`` (H, W, 3) uint8 sRGB, ``range`` (H, W)
    float32 ray length [m] (inf = sky), and ``stats`` (beams, returns, target / fog returns, mean intensity)."""

    points: NDArray[np.float32]
    image: NDArray[np.uint8]
    range: NDArray[np.float32]
    stats: dict


def _noise_rng(cfg: ReferenceConfig, spec: FrameSpec, sensor: int) -> np.random.Generator:
    return np.random.default_rng([cfg.seed, _NOISE_TAG, LEVELS.index(spec.level), spec.index, sensor])


def frame_field(spec: FrameSpec, cfg: ReferenceConfig) -> ParticleField:
    """The particle field of a snow or rain frame: the split's hidden rate, a seed of the frame's own, the reference
    time at the frame (so the field is what the frame sees at its capture time).

    Raises:
        ValueError: ``spec`` is not a snow or rain frame.
    """
    if spec.level not in PRECIPITATION_LEVELS:
        raise ValueError(f"frame {spec.sample_id} is a {spec.level!r} frame; particle fields exist for "
                         f"{list(PRECIPITATION_LEVELS)}")
    pc = cfg.precipitation
    rate = draw_precipitation_truth(cfg)[spec.level]
    seed = int(np.random.default_rng([cfg.seed, _FIELD_TAG, LEVELS.index(spec.level), spec.index])
               .integers(0, 2**62))
    if spec.level == "snow":
        dist = SnowSizeDistribution(rate, pc.snow_terminal_velocity_m_s, model=pc.snow_size_distribution)
        fall, cell = pc.snow_terminal_velocity_m_s, SNOW_CELL_M
    else:
        dist, fall, cell = RainSizeDistribution(rate), RAIN_FIELD_FALL_M_S, RAIN_CELL_M
    return ParticleField(seed=seed, distribution=dist, velocity=(0.0, 0.0, -fall), t_ref=spec.time,
                         z_min=pc.layer_bottom_m, z_max=pc.layer_top_m, cell_size=cell)


def frame_medium(spec: FrameSpec, cfg: ReferenceConfig) -> FogLevel | ParticleField:
    """What frame ``spec`` is seen through: its level's `FogLevel` (`CLEAR` for the clear level) or its particle
    field (`frame_field`)."""
    return frame_field(spec, cfg) if spec.level in PRECIPITATION_LEVELS else draw_truth(cfg)[spec.level]


def frame_overcast(spec: FrameSpec, cfg: ReferenceConfig) -> OvercastTruth | None:
    """The hidden overcast light of a snow or rain frame (`weatheralign.reference.overcast`); None for the clear and
    fog levels or with ``cfg.precipitation.overcast`` off."""
    if not cfg.precipitation.overcast or spec.level not in PRECIPITATION_LEVELS:
        return None
    return draw_overcast_truth(cfg)[spec.level]


def _lambert_sphere(view: F64, sun: F64, n: int = 4096) -> float:
    """Mean ``max(n·sun, 0)`` over the visible half of a Lambertian sphere seen from unit direction ``view`` (towards
    the camera), weighted by projected area (``n·view``): the sun term of a flake's radiance. Fixed quadrature
    (``n`` points of a Fibonacci hemisphere, `visible_hemisphere`)."""
    normals, w = visible_hemisphere(np.asarray(view, dtype=np.float64), n)
    return float(w @ np.maximum(normals @ sun, 0.0))


def particle_radiance(level: str, layout, J: F64, view: F64) -> F64:
    """Linear RGB (3,) of a resolved particle seen along ``view`` (unit, world, camera to scene).

    - snow: a Lambertian sphere of albedo 0.9 under the scene's light (`weatheralign.world.shading`: sky ambient
      ``0.9 (0.55 zenith + 0.45 horizon)`` at a vertical-average normal, and the sun ``2.4 SUN_COLOUR`` times the
      sun term of the visible hemisphere, `_lambert_sphere`);
    - rain: a drop refracts a wide cone of its environment (Garg and Nayar 2004): 0.94 of the mean of the frame's
      clear radiance and the sky's.
    """
    zen, hor = np.asarray(layout.sky_zenith, float), np.asarray(layout.sky_horizon, float)
    if level == "snow":
        sun = np.asarray(layout.sun_direction, float)
        lam = _lambert_sphere(-np.asarray(view, float), sun) if sun[2] > 0.0 else 0.0
        return 0.9 * (0.55 * 0.9 * (0.55 * zen + 0.45 * hor) + 2.4 * lam * np.asarray(SUN_COLOUR))
    return 0.94 * (0.5 * np.asarray(J, float).reshape(-1, 3).mean(0) + 0.25 * (zen + hor))


def _ego_velocity(layout, t: float) -> F64:
    """World velocity (3,) [m/s] of the ego at ``t`` (central difference over 10 ms)."""
    h = 0.005
    return (layout.T_global_ego(t + h)[:3, 3] - layout.T_global_ego(t - h)[:3, 3]) / (2.0 * h)


def render_frame(spec: FrameSpec, cfg: ReferenceConfig, medium: FogLevel | ParticleField,
                 nthreads: int = 1) -> RenderedFrame:
    """Render frame ``spec`` through ``medium`` (`frame_medium`: the level's true fog, `CLEAR`, or its particle
    field)."""
    layout = generate_layout(spec.recording, spec.scene_seed, spec.t_start, SCENE_DURATION_S, EGO_SPEED_RANGE,
                             np.array(spec.origin), spec.heading)
    caster = WorldRaycaster(layout, nthreads=nthreads)
    T_global_ego = layout.T_global_ego(spec.time)
    particles = isinstance(medium, ParticleField)

    # LiDAR: clear hits, system constants, exact pulse integral (fog) or sub-rays through the particles, detector
    grid = hdl64_grid(cfg.lidar.firings_per_ring)
    T_global_lidar = T_global_ego @ T_EGO_LIDAR
    R = T_global_lidar[:3, :3]
    dirs = grid.directions @ R.T
    origins = np.broadcast_to(T_global_lidar[:3, 3], dirs.shape).copy()
    hits = caster.cast_at_time(origins, dirs, spec.time)
    r_true = hits.range.copy()
    hit = np.flatnonzero(np.isfinite(r_true))
    i0 = np.zeros(len(r_true))
    if len(hit):
        pos = origins[hit] + dirs[hit] * r_true[hit, None]
        surf = texture(layout, pos, hits.normal[hit], hits.material[hit], hits.albedo[hit], hits.reflectivity[hit])
        cos_inc = np.einsum("ij,ij->i", hits.normal[hit].astype(np.float64), dirs[hit])
        i0[hit] = lidar_intensity(surf.reflectivity, cos_inc, r_true[hit], SYNTHETIC_INTENSITY)
    ground = frame_ground_state(spec.level, spec.index, cfg, T_global_lidar)
    surfaces = None
    if ground is not None and len(hit):  # the wet or snowy ground under the air's weather (module docstring)
        surfaces = exact_surfaces(grid.directions[hit] * r_true[hit, None], hits.normal[hit], T_global_lidar)
        r_true[hit], i0[hit] = ground_hits(grid.directions[hit] * r_true[hit, None], i0[hit], surfaces, ground,
                                           spec.time, T_EGO_LIDAR, T_global_ego)
    sensor, detector = sensor_of(cfg)
    has_target = np.isfinite(r_true) & (i0 > 0.0)
    r_echo = np.where(has_target & (r_true < sensor.listen_end), r_true, np.inf)
    if particles:
        pc = cfg.precipitation
        reflectivity = pc.snow_reflectivity if spec.level == "snow" else pc.rain_reflectivity
        returns = particle_returns(T_global_lidar[:3, 3], dirs, r_echo, np.where(np.isfinite(r_echo), i0, 0.0),
                                   medium, spec.time, reflectivity, sensor, noise_floor=detector.noise_floor,
                                   floor_range_m=detector.floor_range_m, sub_rays=pc.lidar_sub_rays,
                                   grid_step=cfg.lidar.receiver_step_m,
                                   seed=int(_noise_rng(cfg, spec, 3).integers(0, 2**31 - 1))).returns
    else:
        c = system_constants(np.where(has_target, r_true, np.inf), i0, grid.ring, sensor)
        returns = exact_returns(r_echo, c, medium.alpha, medium.beta, sensor, tables=fog_tables(medium.alpha, sensor),
                                grid_step=cfg.lidar.receiver_step_m)
    out = read_out(returns, sensor, detector, _noise_rng(cfg, spec, 1))
    xyz = grid.directions[out.index] * out.range[:, None]
    channel = (len(HDL64E_ELEVATIONS_DEG) - 1) - grid.ring[out.index].astype(np.float64)
    points = np.column_stack([xyz, out.intensity, channel]).astype(np.float32)

    # camera: clear radiance, exact fog integral or particle ray tracing, noise
    cam = stereo_left_camera(cfg.camera.image_scale)
    T_global_cam = T_global_ego @ cam.T_ego_cam
    pdirs = pixel_directions(cam, T_global_cam)
    origin = T_global_cam[:3, 3]
    chits = caster.cast_camera(cam.K, T_global_cam, cam.width, cam.height, spec.time, pdirs)
    lit = sun_lit(caster, origin, pdirs, chits, spec.time, cfg.camera.shadows)
    sky = frame_overcast(spec, cfg)
    if sky is None:
        J = camera_radiance(layout, origin, pdirs, chits.range, chits.normal, chits.material, chits.albedo,
                           chits.reflectivity, lit)
        sky_light = np.asarray(layout.sky_horizon, dtype=np.float64)
    else:  # snow and rain fall from a cloud deck: the overcast sky and what is left of the sun light the scene
        J = overcast_radiance(layout, origin, pdirs, chits.range, chits.normal, chits.material, chits.albedo,
                              chits.reflectivity, lit, sky)
        sky_light = np.full(3, sky.zenith_luminance / 3.0)
    if surfaces is not None:
        J = edit_image(J.reshape(cam.height, cam.width, 3), chits.range.reshape(cam.height, cam.width),
                       CameraGeometry(cam.K, T_global_cam), True, surfaces, T_global_lidar, ground,
                       sky_light, work_stride=1).linear.reshape(-1, 3)
    coverage = 0.0
    if particles:
        pc = cfg.precipitation
        view = T_global_cam[:3, 2]
        if sky is None:
            radiance = particle_radiance(spec.level, layout, J, view)
        else:
            radiance = flake_radiance(layout, view, sky) if spec.level == "snow" else drop_radiance(J, sky)
        seen = particle_image(J.reshape(cam.height, cam.width, 3), chits.range.reshape(cam.height, cam.width),
                              cam.K, T_global_cam, spec.time, medium,
                              radiance, v_cam=_ego_velocity(layout, spec.time),
                              exposure_s=pc.exposure_s, samples=pc.camera_samples,
                              per_diameter_fall=spec.level == "rain",
                              seed=int(_noise_rng(cfg, spec, 4).integers(0, 2**31 - 1)))
        J = seen.radiance.reshape(-1, 3)
        coverage = float(np.mean(seen.coverage))
    elif medium.alpha > 0.0:
        A = srgb_to_linear(np.full(3, spec.airlight))
        J = fog_radiance(J, chits.range, medium.alpha, A, cfg.camera.sky_distance_m)
    image = encode_with_noise(J.reshape(cam.height, cam.width, 3), cfg.camera.noise_std, _noise_rng(cfg, spec, 2))
    range_map = chits.range.astype(np.float32).reshape(cam.height, cam.width)
    stats = {"beams": int(len(r_true)), "returns": int(len(points)),
             "target_returns": int((out.source == TARGET).sum()), "fog_returns": int((out.source == FOG).sum()),
             "particle_returns": int((out.source == PARTICLE).sum()), "camera_particle_coverage": round(coverage, 6),
             "mean_intensity": float(points[:, 3].astype(np.float64).mean()) if len(points) else 0.0}
    return RenderedFrame(points, image, range_map, stats)


def frame_files(spec: FrameSpec) -> tuple[str, str, str]:
    """Relative paths of the frame's scan, image and range map inside the reference root."""
    sid = spec.sample_id
    return f"{LIDAR_FOLDER}/{sid}.bin", f"{CAMERA_FOLDER}/{sid}.png", f"{RANGE_FOLDER}/{sid}.npy"


def write_frame(root: Path, spec: FrameSpec, frame: RenderedFrame) -> None:
    """The frame's scan (float32 little-endian N x 5), PNG image and range map (.npy), each written atomically."""
    scan, image, rng = frame_files(spec)
    atomic.write_bytes(root / scan, frame.points.astype("<f4").tobytes())
    buf = io.BytesIO()
    Image.fromarray(frame.image).save(buf, format="PNG", compress_level=6)
    atomic.write_bytes(root / image, buf.getvalue())
    atomic.save_npy(root / rng, frame.range)


# ------------------------------------------------------------------------------------------------ resume


@dataclass(frozen=True)
class FrameRecord:
    """What rendering a frame produced (kept in the resume record): level, sample id and its `RenderedFrame.stats`."""

    level: str
    index: int
    sample_id: str
    stats: dict


def config_hash(cfg: ReferenceConfig) -> str:
    """Hash of everything that changes a rendered frame: the synthetic reference's parameters (not the frame count,
    the split file names or the source switch) and the library code it runs."""
    relevant = cfg.model_dump(mode="json", exclude={"source", "stf_root", "split_files", "frames_per_split",
                                                    "intensity_max"})
    text = json.dumps(relevant, sort_keys=True) + stage_code_digest("reference")
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _progress_file(data: Path, spec: FrameSpec) -> Path:
    return reference_dir(data) / PROGRESS_DIR / f"{spec.sample_id}.json"


def load_finished(spec: FrameSpec, cfg: ReferenceConfig, data: Path, digest: str | None = None) -> FrameRecord | None:
    """The record of ``spec`` from an earlier run with the same parameters and code, if every file it wrote is still
    there with the size and SHA-256 recorded at write time."""
    record = read_resume_record(_progress_file(data, spec), digest or config_hash(cfg), synthetic_root(data))
    return None if record is None else FrameRecord(**record["record"])


def render_or_resume(spec: FrameSpec, cfg: ReferenceConfig, data: Path, nthreads: int = 1) -> tuple[FrameRecord, bool]:
    """Render and write frame ``spec`` unless an identical earlier run finished it. Returns (record, rendered_now)."""
    digest = config_hash(cfg)
    done = load_finished(spec, cfg, data, digest)
    if done is not None:
        return done, False
    frame = render_frame(spec, cfg, frame_medium(spec, cfg), nthreads=nthreads)
    write_frame(synthetic_root(data), spec, frame)
    record = FrameRecord(spec.level, spec.index, spec.sample_id, frame.stats)
    write_resume_record(_progress_file(data, spec), digest, synthetic_root(data), frame_files(spec),
                        {"record": asdict(record)})
    return record, True


# ------------------------------------------------------------------------------------------------ the dataset


def camera_calibration(cam: Camera) -> dict:
    """``calib_cam_stereo_left.json`` content (ROS CameraInfo form, rectified: ``P = [K | 0]``)."""
    K = cam.K
    return {
        "header": {"frame_id": CAMERA_TF_FRAME, "seq": 0, "stamp": {"secs": 0, "nsecs": 0}},
        "width": cam.width, "height": cam.height, "distortion_model": "plumb_bob",
        "D": [0.0, 0.0, 0.0, 0.0, 0.0],
        "K": [float(v) for v in K.ravel()],
        "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "P": [float(K[0, 0]), 0.0, float(K[0, 2]), 0.0, 0.0, float(K[1, 1]), float(K[1, 2]), 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0, "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "width": 0, "height": 0, "do_rectify": False},
    }


def _tf_entry(parent: str, child: str, T: F64) -> dict:
    x, y, z, w = (float(v) for v in Rotation.from_matrix(T[:3, :3]).as_quat())
    tx, ty, tz = (float(v) for v in T[:3, 3])
    return {"header": {"frame_id": parent, "seq": 0, "stamp": {"secs": 0, "nsecs": 0}}, "child_frame_id": child,
            "transform": {"translation": {"x": tx, "y": ty, "z": tz}, "rotation": {"x": x, "y": y, "z": z, "w": w}}}


def tf_tree() -> list[dict]:
    """``calib_tf_tree_full.json`` content: ``body`` (the ego frame) -> HDL-64 and stereo-left optical frame."""
    return [_tf_entry("base_link", "body", np.eye(4)),
            _tf_entry("body", LIDAR_TF_FRAME, T_EGO_LIDAR),
            _tf_entry("body", CAMERA_TF_FRAME, T_EGO_CAMERA)]


def finalize(cfg: ReferenceConfig, data: Path, records: list[FrameRecord]) -> dict:
    """Write the split files, calibration, manifest and the sealed truth; remove sensor files and resume records of
    frames not in ``records``. Returns the public summary (frames per level and the files written).

    Raises:
        ValueError: a split file path is absolute or leaves the reference root, or two levels share a split file.
    """
    root = synthetic_root(data)
    specs = {s.sample_id: s for s in frame_specs(cfg)}
    by_level: dict[str, list[FrameRecord]] = {level: [] for level in LEVELS}
    for rec in sorted(records, key=lambda r: (LEVELS.index(r.level), r.index)):
        by_level[rec.level].append(rec)
    split_files = split_files_of(cfg.split_files)
    if len(set(split_files.values())) != len(split_files):
        raise ValueError(f"reference.split_files: levels must have distinct files, got {split_files}")
    for level, rel in split_files.items():
        path = Path(rel)
        if path.is_absolute() or ".." in path.parts:
            raise ValueError(f"reference.split_files.{level} = {rel!r}: the synthetic reference writes its split "
                             f"files inside its root; expected a relative path without '..'")
        lines = [f"{specs[r.sample_id].recording},{specs[r.sample_id].frame_number:05d}" for r in by_level[level]]
        atomic.write_bytes(root / path, ("\n".join(lines) + "\n").encode())
    cam = stereo_left_camera(cfg.camera.image_scale)
    atomic.write_json(root / CAMERA_CALIB_FILE, camera_calibration(cam), indent=2)
    atomic.write_json(root / TF_TREE_FILE, tf_tree(), indent=2)
    sensor, detector = sensor_of(cfg)
    manifest = {
        "layout": "seeing_through_fog", "generator": "weatheralign synthetic reference",
        "config_hash": config_hash(cfg), "intensity_max": 255.0,
        "lidar_folder": LIDAR_FOLDER, "camera_folder": CAMERA_FOLDER, "range_folder": RANGE_FOLDER,
        "split_files": split_files, "frames": {level: len(by_level[level]) for level in split_files},
        "lidar": {"model": "HDL-64-like", "rings": int(len(HDL64E_ELEVATIONS_DEG)),
                  "firings_per_ring": cfg.lidar.firings_per_ring, "channel_order": "channel 0 = lowest laser",
                  "min_range_m": sensor.min_range, "max_range_m": sensor.max_range, "intensity_quantum": 1.0,
                  "tau_h_s": sensor.tau_h},
        "camera": {"width": cam.width, "height": cam.height, "range_maps": "float32 ray length [m], inf = sky"},
    }
    atomic.write_json(root / MANIFEST_FILE, manifest, indent=2)
    truth = draw_truth(cfg)
    rates = {level: rate for level, rate in draw_precipitation_truth(cfg).items() if level in split_files}
    sealed: dict[str, dict] = {level: {"alpha": truth[level].alpha, "beta": truth[level].beta} for level in FOG_LEVELS}
    sealed.update({level: {"rate_mm_h": rate} for level, rate in rates.items()})
    if cfg.precipitation.ground:
        depth_key = {"rain": "film_depth_m", "snow": "snow_depth_m"}
        for level, depth in draw_ground_truth(cfg).items():
            if level in sealed:
                sealed[level][depth_key[level]] = depth
    if cfg.precipitation.overcast:
        for level, sky in draw_overcast_truth(cfg).items():
            if level in sealed:
                sealed[level].update(sun_transmittance=sky.sun_transmittance, zenith_luminance=sky.zenith_luminance)
    atomic.write_json(sealed_truth_path(data), sealed, indent=2)
    details: dict[str, dict] = {
        level: {"alpha": truth[level].alpha, "beta": truth[level].beta, "mor_m": truth[level].mor,
                "beta_times_mor": truth[level].beta * truth[level].mor,
                "airlight_srgb": {r.sample_id: specs[r.sample_id].airlight for r in by_level[level]}}
        for level in FOG_LEVELS}
    for level, rate in rates.items():
        field_seeds = {r.sample_id: frame_field(specs[r.sample_id], cfg).seed for r in by_level[level]}
        details[level] = {"rate_mm_h": rate, "field_seed": field_seeds,
                          "particle_returns": {r.sample_id: r.stats.get("particle_returns", 0)
                                               for r in by_level[level]},
                          "camera_particle_coverage": {r.sample_id: r.stats.get("camera_particle_coverage", 0.0)
                                                       for r in by_level[level]}}
    details["detector"] = asdict(detector)
    atomic.write_json(reference_dir(data) / SEALED_DETAILS_FILE, details, indent=2)
    _remove_stale(data, {r.sample_id for r in records})
    return {"root": str(root), "frames": {level: len(by_level[level]) for level in split_files}}


def _remove_stale(data: Path, keep: set[str]) -> None:
    root = synthetic_root(data)
    for folder, suffix in ((LIDAR_FOLDER, ".bin"), (CAMERA_FOLDER, ".png"), (RANGE_FOLDER, ".npy")):
        d = root / folder
        if d.is_dir():
            for path in d.iterdir():
                if path.is_file() and (path.suffix != suffix or path.stem not in keep):
                    path.unlink()
    progress = reference_dir(data) / PROGRESS_DIR
    if progress.is_dir():
        for path in progress.iterdir():
            if path.is_file() and path.stem not in keep:
                path.unlink()
