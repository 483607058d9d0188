"""The frames the fused-feature check compares: real reference frames and the reference's clear frames through the
fast simulator, aligned and unaligned (`verify`).

A reference frame (Seeing Through Fog layout: HDL-64 scan + stereo-left image, `weatheralign.reference`) becomes one
(6, h, w) fused input (`weatheralign.verify.features.fused_input`): the image area-resized to (h, w) above the LiDAR
projected into the same cells. A *simulated* frame is a clear reference frame observed through a condition's media by
the same observation core as `simulate` (`weatheralign.simulate.observe.observe`): the LiDAR through the reference
sensor (`reference_lidar_model`, with its detector noise), the camera through the simulation's fog compositing and
particle splatting. Aligned: the camera sees the LiDAR's media; unaligned: the fog's camera extinction drawn in
[α_light, α_dense] and the particle field's independent twin at a rate of its own, exactly as a
`simulate@<condition>-unaligned` copy (`weatheralign.conditions`); for particles also the twin at the LiDAR's rate
(positions alone misaligned). The LiDAR sees the condition's own media in both, so one LiDAR scan serves both.

Each clear frame is its own "scene": its particle field is seeded from (``seed``, condition, frame id) and starts at
the frame's time (0 for STF).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from weatheralign.calibrate.histograms import frame_counts
from weatheralign.camera.fog import estimate_airlight
from weatheralign.camera.overcast import Overcast
from weatheralign.conditions import Condition, FogPart, GroundPart, ParticlePart
from weatheralign.config import ParticlesConfig
from weatheralign.data.frame import Frame
from weatheralign.data.stf import CAMERA_CHANNEL
from weatheralign.geometry import invert
from weatheralign.lidar.clutter import isolated_mask
from weatheralign.medium.conditions import field_spec
from weatheralign.reference import ReferenceDataset
from weatheralign.reference.frames import reference_frame
from weatheralign.sensors import CameraModel, LidarModel, SensorRig
from weatheralign.simulate.media import FogLevels, SceneGround, SceneMedia, ground_seed
from weatheralign.simulate.observe import ObserveOptions, observe
from weatheralign.verify.features import fused_input, lidar_image_channels


@dataclass(frozen=True)
class Severity:
    """What a simulated condition is made of: the fog ``levels`` in use and the snow / rain rates [mm/h] (water
    equivalent) of the particle fields, with the field physics of ``particles`` (``particles.<kind>.rate_mm_h`` is
    replaced by the rate given here); ``unaligned_rate_factor``: the unaligned cameras' rate spread
    (`ParticlePart.camera_rate`, ``simulate.unaligned_rate_factor``; 1: positions alone misaligned); the ground of
    each kind, its puddles' share and fields' seed (``simulate.wet_puddle_share``, ``ground_seed``); the overcast
    light of each sky (``snow`` / ``rain``, `Overcast.to_dict`, as `weatheralign.simulate.media.resolve_overcast`
    gives it)."""

    levels: FogLevels
    snow_rate_mm_h: float
    rain_rate_mm_h: float
    particles: ParticlesConfig
    unaligned_rate_factor: float = 1.0
    ground_depth_m: dict[str, float] = field(default_factory=dict)
    """The ground each kind leaves (``rain``: the mean film depth, ``snow``: the snow depth [m]); a kind absent
    leaves none."""
    wet_puddle_share: float = 0.08
    ground_seed: int = 11
    overcast: dict[str, dict[str, float]] = field(default_factory=dict)
    """The light each sky split (``snow`` / ``rain``) falls under; a split absent: the clear day's light."""

    def particles_at_rates(self) -> ParticlesConfig:
        """``particles`` with the snow and rain rates of this severity."""
        return self.particles.model_copy(update={
            "snow": self.particles.snow.model_copy(update={"rate_mm_h": self.snow_rate_mm_h}),
            "rain": self.particles.rain.model_copy(update={"rate_mm_h": self.rain_rate_mm_h})})


def camera_from_lidar(frame: Frame) -> NDArray[np.float64]:
    """(4, 4) LiDAR -> stereo-left camera (OpenCV axes) of ``frame``."""
    view = frame.cameras[CAMERA_CHANNEL]
    return invert(np.asarray(view.T_ego_cam, dtype=np.float64)) @ np.asarray(frame.lidar.T_ego_lidar)


def frame_fused_input(frame: Frame, image: NDArray[np.uint8], points: NDArray, intensity_max: float,
                      out_hw: tuple[int, int]) -> NDArray[np.float32]:
    """(6, h, w) fused input of ``frame``'s stereo-left ``image`` and the LiDAR ``points`` (N, >=4) [m, intensity in
    0..``intensity_max``] in the LiDAR frame."""
    view = frame.cameras[CAMERA_CHANNEL]
    T_cam_lidar = camera_from_lidar(frame)
    lidar = lidar_image_channels(points[:, :3], points[:, 3] / intensity_max, view.K, T_cam_lidar,
                                 (view.height, view.width), out_hw)
    return fused_input(image, lidar)


def displaced_particle_channels(frame: Frame, points: NDArray, intensity_max: float, out_hw: tuple[int, int],
                                azimuth_step_rad: float, seed: int, min_in_view: int = 30
                                ) -> NDArray[np.float32] | None:
    """(3, h, w) LiDAR channels of ``frame`` with its particle echoes elsewhere, or None when fewer than
    ``min_in_view`` of them fall in the camera's image: the echoes are the scan's isolated returns within 20 m
    (`isolated_mask`, the DROR test), each turned about the LiDAR's vertical axis by ±(5..20)° (same range and
    height: the right scene with the wrong particles). ``seed``: the turns."""
    mask = isolated_mask(points[:, :3], azimuth_step_rad=azimuth_step_rad)
    view = frame.cameras[CAMERA_CHANNEL]
    T_cam_lidar = camera_from_lidar(frame)
    echoes = points[mask]
    cam = echoes[:, :3] @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3]
    uvw = cam @ np.asarray(view.K).T
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    in_view = (cam[:, 2] > 0.5) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
    if int(in_view.sum()) < min_in_view:
        return None
    rng = np.random.default_rng(seed)
    turn = np.radians(rng.uniform(5.0, 20.0, len(echoes))) * rng.choice([-1.0, 1.0], len(echoes))
    c, s = np.cos(turn), np.sin(turn)
    moved = points.copy()
    moved[mask, 0] = c * echoes[:, 0] - s * echoes[:, 1]
    moved[mask, 1] = s * echoes[:, 0] + c * echoes[:, 1]
    return lidar_image_channels(moved[:, :3], moved[:, 3] / intensity_max, view.K, T_cam_lidar,
                                (view.height, view.width), out_hw)


def reference_fused_input(ds: ReferenceDataset, sample_id: str, out_hw: tuple[int, int]) -> NDArray[np.float32]:
    """(6, h, w) fused input of one real reference frame."""
    frame, image, _ = reference_frame(ds, sample_id)
    return frame_fused_input(frame, image, frame.lidar.points, ds.intensity_max, out_hw)


def scene_media(condition: Condition, aligned: bool, sample_id: str, severity: Severity, seed: int) -> SceneMedia:
    """The media of ``condition`` over the clear frame ``sample_id`` as `simulate` builds them for a scene: the fog
    at its level (unaligned cameras: `FogPart.camera_alpha` from ``seed``) with its airlight gain
    (`FogPart.airlight_gain`, both cameras), the particle field seeded from
    (``severity.particles.seed``, kind, frame id) (unaligned cameras: its twin at `ParticlePart.camera_rate`), the
    ground at ``severity``'s depth with fields seeded from the frame id (unaligned cameras: its twin,
    `GroundPart.camera_amount`), the overcast of the condition's sky (aligned and unaligned alike)."""
    kw: dict = {}
    if condition.fog is not None:
        levels = severity.levels
        alpha = levels.alpha[condition.fog.level]
        kw.update(lidar_alpha=alpha, lidar_beta=levels.beta[condition.fog.level],
                  camera_alpha=FogPart.camera_alpha(aligned, alpha, levels.alpha["light"], levels.alpha["dense"],
                                                    seed, condition.name, sample_id),
                  airlight_gain=FogPart.airlight_gain(levels.airlight_gains[condition.fog.level], seed,
                                                      condition.name, sample_id))
    if condition.particles is not None:
        spec = field_spec(severity.particles_at_rates(), condition.particles.kind, sample_id, 0.0)
        kw["field"] = spec
        if not aligned:
            kw["camera_rate_mm_h"] = ParticlePart.camera_rate(False, spec.rate_mm_h, severity.unaligned_rate_factor,
                                                              spec.seed)
    if condition.ground is not None:
        depth = severity.ground_depth_m.get("rain" if condition.ground.kind == "wet" else "snow")
        if depth is not None:
            lidar_seed = ground_seed(severity.ground_seed, condition.name, sample_id, camera=False)
            camera_seed = lidar_seed if aligned else ground_seed(severity.ground_seed, condition.name, sample_id,
                                                                 camera=True)
            kw["ground"] = SceneGround(condition.ground.kind, depth, lidar_seed, GroundPart.camera_amount(
                aligned, depth, severity.unaligned_rate_factor, lidar_seed), camera_seed,
                severity.wet_puddle_share if condition.ground.kind == "wet" else 0.0)
    if condition.sky is not None and condition.sky.split in severity.overcast:
        kw["overcast"] = Overcast(**severity.overcast[condition.sky.split])
    return SceneMedia(condition, aligned, sample_id, **kw)


@dataclass(frozen=True, eq=False)
class SimulatedPair:
    """One clear reference frame through a condition: the ``aligned`` and ``unaligned`` fused inputs (6, h, w), the
    aligned camera image (H, W, 3) uint8 and the clear frame's ray lengths (H, W) [m] (for KID and the visibility
    estimate), the weather scan's intensity histogram row (256,) (`frame_counts`), its point counts per label, and
    the particles' re-projection errors [px] (aligned). ``unaligned_positions``: with particles and a rate spread,
    the unaligned camera at the LiDAR's rate (positions alone misaligned), else None."""

    aligned: NDArray[np.float32]
    unaligned: NDArray[np.float32]
    unaligned_positions: NDArray[np.float32] | None
    image: NDArray[np.uint8]
    range_map: NDArray[np.float32]
    intensity_counts: NDArray[np.int64]
    counts: dict[str, int]
    reprojection_px: NDArray[np.float64]


def simulated_pair(ds: ReferenceDataset, sample_id: str, condition: Condition, severity: Severity,
                   lidar: LidarModel, exposure_s: float, out_hw: tuple[int, int], seed: int,
                   options: ObserveOptions = ObserveOptions()) -> SimulatedPair:
    """The clear reference frame ``sample_id`` through ``condition`` at ``severity``, aligned and unaligned, seen
    by the reference LiDAR ``lidar`` and a camera of exposure ``exposure_s`` [s]."""
    frame, image, range_map = reference_frame(ds, sample_id)
    view = frame.cameras[CAMERA_CHANNEL]
    camera = CameraModel(CAMERA_CHANNEL, tuple(tuple(float(v) for v in row) for row in view.K), view.width,
                         view.height, exposure_s)
    rig = SensorRig(lidar=lidar, cameras={CAMERA_CHANNEL: camera})
    airlight = estimate_airlight([image], [range_map])
    images, ranges = {CAMERA_CHANNEL: image}, {CAMERA_CHANNEL: range_map}
    aligned = observe(frame, images, ranges, scene_media(condition, True, sample_id, severity, seed), rig, airlight,
                      options)
    unaligned_media = scene_media(condition, False, sample_id, severity, seed)
    unaligned = observe(frame, images, ranges, unaligned_media, rig, airlight, options, lidar=aligned.lidar)
    positions = None
    if unaligned_media.has_particles and unaligned_media.camera_rate_mm_h != unaligned_media.field.rate_mm_h:
        positions = observe(frame, images, ranges, replace(unaligned_media, camera_rate_mm_h=None), rig, airlight,
                            options, lidar=aligned.lidar)
    points = aligned.lidar.scan.points

    def fused(weather_image: NDArray[np.uint8] | None) -> NDArray[np.float32]:
        return frame_fused_input(frame, image if weather_image is None else weather_image, points,
                                 ds.intensity_max, out_hw)

    weather_image = aligned.cameras[CAMERA_CHANNEL].image
    weather_image = image if weather_image is None else weather_image
    return SimulatedPair(fused(weather_image), fused(unaligned.cameras[CAMERA_CHANNEL].image),
                         None if positions is None else fused(positions.cameras[CAMERA_CHANNEL].image), weather_image,
                         range_map, frame_counts(points[:, 3], ds.intensity_max), dict(aligned.lidar.counts),
                         np.asarray(aligned.reprojection_px, dtype=np.float64))


__all__ = ["Severity", "SimulatedPair", "displaced_particle_channels", "frame_fused_input", "reference_fused_input",
           "scene_media", "simulated_pair"]
