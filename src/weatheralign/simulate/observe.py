"""The pure observation core: one frame through one condition's media, as every sensor sees it. No file I/O.

`observe(frame, images, ranges, media, sensors, airlight, options, lidar)` returns `FrameWeather`: the weather LiDAR
scan with per-point labels, particle ids and source rows; each camera's weather image and the particles it drew; the
re-projection errors of the particles the LiDAR saw. The caller (`weatheralign.simulate.weather_copy`) loads the
inputs (decoded images, ray-length maps from `weatheralign.camera.depth.camera_range_map`) and writes the outputs.

How media compose (see `weatheralign.conditions`):

- LiDAR (`observe_lidar`, `observe_lidar_scans` for a keyframe and its sweeps): fog alone through
  `weatheralign.lidar.simulate_fog`; a particle field (with or without fog) through
  `weatheralign.lidar.simulate_particle_scans` (all scans at once), which adds the fog's extinction to every echo
  and lets the fog's backscatter compete with the strongest echo of each beam. The sensor is the dataset's `LidarModel`.
- Cameras (`observe_camera`), each at its own timestamp and ego pose: under snow and rain first the overcast light
  (`weatheralign.camera.overcast`: grey sky, the sun's shadows lifted, neutral light; the background edit), then the
  ground (its wet road mirrors the relit scene and the overcast horizon), then one transmission per pixel, the fog's
  ``exp(-α ℓ)`` times the unresolved particles' ``exp(-τ_u(ℓ))``, guided-filtered where the ray lengths are estimated
  (real cameras' dense depth; an exact range map is used as it is) and composited with the fog's
  airlight (the scene's clear-sky airlight times the scene's calibrated gain, `SceneMedia.airlight_gain`; under
  the overcast its horizon, the light the droplets and unresolved particles scatter) in linear
  light in one compiled pass (`weatheralign.camera.fog.composite_image`); then the field's
  resolvable particles splatted with exposure streaks (`weatheralign.camera.splat`), pre-fogged by the same fog.
  Unaligned cameras see the media's twins (`SceneMedia.camera_alpha`, `SceneMedia.camera_field`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.fog import composite_image, encode_srgb_u8, fog_airlight, linear_to_srgb, srgb_to_linear
from weatheralign.camera.fog import transmission as fog_transmission
from weatheralign.camera.overcast import Exposure, overcast_edit
from weatheralign.camera.splat import (
    APPEARANCES,
    focal_px,
    materialize_for_camera,
    render_particles,
    unresolved_extinction_profile,
)
from weatheralign.data.frame import CameraView, Frame, LidarScan
from weatheralign.geometry import invert
from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.edit import (
    EditedScan,
    GroundState,
    ScanSurfaces,
    edit_image_u8,
    edit_scan,
    scan_surfaces,
    unseen_beams,
)
from weatheralign.ground.snow import TireTracks
from weatheralign.ground.surfaces import mask_agreement
from weatheralign.lidar import simulate_fog, simulate_particle_scans
from weatheralign.lidar.labels import POINT_LABELS, WeatherLabel
from weatheralign.medium.fog import FogMedium
from weatheralign.metrics.reprojection import CameraParticles, lidar_particles, reprojection_check
from weatheralign.sensors import CameraModel, LidarModel, SensorRig
from weatheralign.simulate.media import SceneMedia

COUNT_KEYS: tuple[str, ...] = (*(label.name for label in POINT_LABELS), "CLUTTER", "GROUND", "GROUND_LOST",
                               "GROUND_ADDED")
"""Keys of `LidarWeather.counts`: points per label, clutter points added on beams without return, points the ground
alone changed or added (`WeatherLabel.GROUND`), points the ground pushed under the detector floor and returns the
snow added on a road the clear beams missed (`weatheralign.ground.edit.snow_on_unseen_road`; they are counted under
their label as well)."""


@dataclass(frozen=True)
class ObserveOptions:
    """Rendering choices that are neither sensor nor medium: ``near_clip_m`` (no particle nearer to a camera [m]),
    ``refine_transmission`` (guided-filter the transmission of cameras whose ray lengths are estimated from the LiDAR;
    an exact range map, as the synthetic world's, is used as it is), ``threads`` (cameras in parallel)."""

    near_clip_m: float = 0.5
    refine_transmission: bool = True
    threads: int = 1


@dataclass(frozen=True, eq=False)
class LidarWeather:
    """A weather scan: ``scan`` (new points), per output point ``labels`` (`WeatherLabel`), ``particle_id`` (-1: none),
    ``source_index`` (input row, -1: clutter), ``times`` (firing time [s]); ``counts`` per `COUNT_KEYS`;
    ``stored_offsets``: the (N,) float32 firing times relative to ``scan.timestamp`` as a weather copy stores them,
    where the scan was read back from one (None: computed here); with a ground, the input scan's surfaces and which of
    its returns the ground edited (None where not computed here)."""

    scan: LidarScan
    labels: NDArray[np.uint8]
    particle_id: NDArray[np.int64]
    source_index: NDArray[np.int64]
    times: NDArray[np.float64]
    counts: dict[str, int]
    stored_offsets: NDArray[np.float32] | None = None
    ground_surfaces: ScanSurfaces | None = None
    ground_edited: NDArray[np.bool_] | None = None

    def fire_times(self) -> NDArray[np.float64]:
        """(N,) firing time [s] at the precision a weather copy stores it (a float32 offset from the scan's
        timestamp), so a scan computed here and the same scan read back from a copy give the same times."""
        ts = self.scan.timestamp
        offsets = self.stored_offsets if self.stored_offsets is not None else (self.times - ts).astype(np.float32)
        return ts + offsets.astype(np.float64)


@dataclass(frozen=True, eq=False)
class CameraWeather:
    """A weather image (``image`` uint8 sRGB, or None = the input unchanged), the particles it drew
    (`CameraParticles` for the re-projection check, None without particles), ``drawn`` (their number) and the pixels
    its ground edit changed (``ground_mask`` (H, W), None without a ground)."""

    image: NDArray[np.uint8] | None
    particles: CameraParticles | None
    drawn: int
    ground_mask: NDArray[np.bool_] | None = None


@dataclass(frozen=True, eq=False)
class FrameWeather:
    """Everything the weather did to one frame: the LiDAR, each camera, the re-projection errors [px] and their
    cameras."""

    lidar: LidarWeather
    cameras: dict[str, CameraWeather]
    reprojection_px: NDArray[np.float64]
    reprojection_channels: list[str] = field(default_factory=list)
    ground_iou: dict[str, float] = field(default_factory=dict)
    """Per camera: the LiDAR's ground-edited returns projected into it against its ground-edited pixels (IoU,
    `weatheralign.ground.surfaces.mask_agreement`)."""

    @property
    def particles_rendered(self) -> int:
        return sum(c.drawn for c in self.cameras.values())


# ------------------------------------------------------------------------------------------------ LiDAR


def observe_lidar(scan: LidarScan, media: SceneMedia, lidar: LidarModel) -> LidarWeather:
    """``scan`` through the media the LiDAR sees (its fog level and/or the LiDAR's field ``field.field()``)."""
    return observe_lidar_scans([scan], media, lidar)[0]


JOINT_DRIFT_MAX_M = 0.5
"""Scans of one sample are matched against a particle field together while the field drifts at most this far [m]
over their joint time span; beyond it each scan runs alone. A joint run generates each field cell once for all scans
but widens every beam's reach by the drift, so slow snow gains from it and fast rain loses;
`benchmarks/bench_lidar_particles.py` measures both (its ``*_keyframe_2sweeps_joint`` workloads against
``separate_*``)."""


def joint_drift_m(scans: list[LidarScan], lidar: LidarModel, speed_m_s: float) -> float:
    """How far [m] a field moving at ``speed_m_s`` drifts over the time ``scans`` span together (first timestamp to
    the end of the last sweep, one rotation ``1 / lidar.rotation_hz`` each)."""
    stamps = [scan.timestamp for scan in scans]
    return speed_m_s * (max(stamps) - min(stamps) + 1.0 / lidar.rotation_hz)


def observe_lidar_scans(scans: list[LidarScan], media: SceneMedia, lidar: LidarModel) -> list[LidarWeather]:
    """Several scans of the LiDAR (a keyframe and the sweeps before it, each at its own times) through the media it
    sees: fog alone scan by scan; a particle field for all scans at once (`simulate_particle_scans`: each field cell
    generated once for all of them) unless the field drifts more than `JOINT_DRIFT_MAX_M` over their span (fast
    rain), then scan by scan."""
    grounded = None
    if media.ground is not None:  # the ground first: the air's weather sees the wet or snowy returns
        state = media.ground.state(camera=False, tracks=TireTracks.along_heading(scans[0].T_global_lidar))
        surfaces = [scan_surfaces(scan, off_ground=state.kind == "snow") for scan in scans]
        grounded = [edit_scan(scan, found, state, lidar.noise_floor, lidar.intensity_noise_std,
                              None if lidar.floor_range_m is None else lidar.floor_scale,
                              unseen_beams(scan, lidar) if state.kind == "snow" else None)
                     for scan, found in zip(scans, surfaces)]
        scans = [g.scan for g in grounded]
    fog = FogMedium(media.lidar_alpha, media.lidar_beta) if media.lidar_alpha > 0.0 else None
    if media.field is None:
        out = [_fog_weather(scan, media, lidar) for scan in scans]
    else:
        fld = media.field.field() if media.has_particles else None
        kw = {"lidar": lidar, "reflectivity": media.condition.particles.lidar_reflectivity, "fog": fog}
        speed = 0.0 if fld is None else float(np.linalg.norm(fld.velocity_array))
        if len(scans) > 1 and joint_drift_m(scans, lidar, speed) > JOINT_DRIFT_MAX_M:
            results = [simulate_particle_scans([scan], fld, **kw)[0] for scan in scans]
        else:
            results = simulate_particle_scans(scans, fld, **kw)
        out = [LidarWeather(res.apply_to(scan), res.labels.astype(np.uint8), res.particle_id.astype(np.int64),
                            res.source_index.astype(np.int64), res.times.astype(np.float64),
                            {k: int(res.counts.get(k, 0)) for k in COUNT_KEYS})
               for scan, res in zip(scans, results)]
    return out if grounded is None else [_with_ground(lw, g, found) for lw, g, found in zip(out, grounded, surfaces)]


def _with_ground(lw: LidarWeather, grounded: EditedScan, surfaces: ScanSurfaces) -> LidarWeather:
    """The air's weather ``lw`` of a ground-edited scan, told in the rows of the scan before the ground edit: source
    rows mapped back (-1 for the returns the ground added), points the ground alone changed or added labelled
    `WeatherLabel.GROUND`, the ground's counts added."""
    src = lw.source_index
    kept = src >= 0
    source = np.where(kept, grounded.source_index[np.where(kept, src, 0)], -1)
    ground_only = kept & (lw.labels == WeatherLabel.UNCHANGED) & grounded.changed[np.where(kept, src, 0)]
    labels = np.where(ground_only, np.uint8(WeatherLabel.GROUND), lw.labels).astype(np.uint8)
    counts = dict(lw.counts)
    counts["UNCHANGED"] -= int(ground_only.sum())
    counts["GROUND"] = int(ground_only.sum())
    counts["GROUND_LOST"] = grounded.lost
    counts["GROUND_ADDED"] = grounded.added
    return replace(lw, labels=labels, source_index=source.astype(np.int64), counts=counts, ground_surfaces=surfaces,
                   ground_edited=grounded.edited)


def _fog_weather(scan: LidarScan, media: SceneMedia, lidar: LidarModel) -> LidarWeather:
    """``scan`` through the fog alone (`simulate_fog`)."""
    res = simulate_fog(scan, media.lidar_alpha, media.lidar_beta, lidar=lidar)
    times = scan.point_times()[res.source_index]
    counts = {k: int(res.counts.get(k, 0)) for k in COUNT_KEYS}
    return LidarWeather(res.apply_to(scan), res.labels.astype(np.uint8), np.full(len(res.labels), -1, np.int64),
                        res.source_index.astype(np.int64), times, counts)


# ------------------------------------------------------------------------------------------------ cameras


MIN_POSE_SPAN_S = 1e-3
"""Ego poses spread over less time than this [s] give no velocity (0)."""


def ego_velocity(frame: Frame) -> NDArray[np.float64]:
    """(3,) ego velocity [m/s] in the global frame: the least-squares slope of ego position against time over every
    ego pose of the frame (the scan's per-firing poses, the scan's own and each camera's at its exposure), so a
    keyframe without sweeps still moves (nuScenes: seven sensor poses over ~45 ms); 0 when the poses span less than
    `MIN_POSE_SPAN_S`."""
    times = [frame.lidar.timestamp, *(v.timestamp for v in frame.cameras.values())]
    positions = [frame.lidar.T_global_ego[:3, 3], *(v.T_global_ego[:3, 3] for v in frame.cameras.values())]
    scan = frame.lidar
    if scan.poses is not None and scan.pose_times is not None:
        times += [float(t) for t in scan.pose_times]
        positions += [p[:3, 3] for p in scan.poses]
    t = np.asarray(times, dtype=np.float64)
    xyz = np.asarray(positions, dtype=np.float64)
    if len(t) < 2 or float(t.max() - t.min()) < MIN_POSE_SPAN_S:
        return np.zeros(3)
    dt = t - t.mean()
    return (dt @ (xyz - xyz.mean(axis=0))) / float(dt @ dt)


@dataclass(frozen=True, eq=False)
class FrameGround:
    """A frame's ground for its cameras: the keyframe scan's surfaces (found once), the pose that maps the scan to
    the world, and the `GroundState` the cameras see."""

    surfaces: ScanSurfaces
    T_world_scan: NDArray[np.float64]
    state: GroundState


def observe_camera(image: NDArray[np.uint8], range_map: NDArray[np.float32], view: CameraView, media: SceneMedia,
                   camera: CameraModel, airlight: NDArray, ego_vel: NDArray, options: ObserveOptions,
                   ground: FrameGround | None = None) -> CameraWeather:
    """One camera through the media it sees (see the module docstring), on the ``ground`` first when there is one.

    Args:
        image: (H, W, 3) uint8 sRGB clear image; range_map: (H, W) float32 ray length [m], inf = sky.
        view: the camera's geometry at its timestamp (K, size, pose); camera: its model (exposure).
        airlight: (3,) sRGB airlight of the scene's clear sky (the fog's: times ``media.airlight_gain``,
            `fog_airlight`); ego_vel: (3,) ego velocity [m/s] (streaks).
    """
    alpha = media.camera_alpha
    fld = media.camera_field()
    ground_mask = None
    relit = media.overcast is not None
    horizon = None
    if relit:  # the background edit first: the scene under the cloud, whose grey horizon the air then scatters
        # the synthetic world's camera (exact range map) has the reference's fixed exposure; a real one meters
        exposure = Exposure.FIXED if view.range_path is not None else Exposure.AUTO
        image, horizon = overcast_edit(image, range_map, np.asarray(view.K, dtype=np.float64), view.T_global_cam,
                                       media.overcast, exposure)
        airlight = linear_to_srgb(np.minimum(horizon, 1.0))
    if ground is not None:  # the wet or snowy ground under the clear air, lit by the sky (under the cloud: its horizon)
        image, ground_mask = edit_image_u8(image, range_map, CameraGeometry(
            np.asarray(view.K, dtype=np.float64), view.T_global_cam), view.range_path is not None, ground.surfaces,
            ground.T_world_scan, ground.state, srgb_to_linear(airlight))
    if alpha <= 0.0 and fld is None:
        return CameraWeather(image if ground_mask is not None or relit else None, None, 0, ground_mask)
    near = options.near_clip_m
    look = APPEARANCES[media.condition.particles.camera_appearance] if fld is not None else None
    t = fog_transmission(range_map, alpha) if alpha > 0.0 else None
    profile = None
    if fld is not None:
        profile = unresolved_extinction_profile(fld, focal_px(view.K), look, near_clip=near)
        t_particles = profile.transmission(range_map)
        t = t_particles if t is None else t * t_particles
    a_lin = horizon if horizon is not None else fog_airlight(airlight, media.airlight_gain)
    refine = options.refine_transmission and view.range_path is None  # exact depth needs no edge-aware smoothing
    if fld is None:
        return CameraWeather(composite_image(image, t, a_lin, refine), None, 0, ground_mask)
    background = composite_image(image, t, a_lin, refine, encode=False)
    T_global_cam = view.T_global_cam
    spec = media.field
    # the fastest streak: the field's velocity, or the extremes of the drops' own (speed is monotone in diameter)
    extremes = spec.drop_velocities(np.array([spec.min_diameter_m, fld.spectrum.d_max]))
    v_rel = np.linalg.norm(extremes - np.asarray(ego_vel, dtype=np.float64), axis=1).max()
    parts = materialize_for_camera(fld, view.K, view.width, view.height, T_global_cam, view.timestamp, look,
                                   near_clip=near, streak_m=float(v_rel) * camera.exposure_s)
    res = render_particles(background, range_map, view.K, invert(T_global_cam), parts.positions,
                           parts.diameters, parts.ids, spec.drop_velocities(parts.diameters), ego_vel,
                           exposure_s=camera.exposure_s,
                           appearance=look, fog_alpha=alpha, airlight=a_lin, unresolved=profile, near_clip=near)
    cp = CameraParticles(view.channel, view.K, T_global_cam, view.timestamp, view.width, view.height, parts.ids,
                         res.centroids, res.drawn & res.unoccluded & res.in_frame, range_map, profile.r_end)
    return CameraWeather(encode_srgb_u8(res.image), cp, int(res.drawn.sum()), ground_mask)


# ------------------------------------------------------------------------------------------------ one frame


def observe(frame: Frame, images: dict[str, NDArray[np.uint8]], ranges: dict[str, NDArray[np.float32]],
            media: SceneMedia, sensors: SensorRig, airlight: NDArray,
            options: ObserveOptions = ObserveOptions(), lidar: LidarWeather | None = None) -> FrameWeather:
    """``frame`` through ``media``: its LiDAR scan and the cameras in ``images`` (decoded clear images, with their
    ray-length maps in ``ranges``), each through the media it sees; with particles, also the re-projection errors
    [px] of the particles the LiDAR saw in every camera. ``lidar``: the LiDAR's weather scan when it is already known
    (an unaligned copy's LiDAR is its aligned twin's: the LiDAR sees the condition's own media either way); computed
    here when None. Pure: reads and writes no file."""
    missing = sorted(set(images) - set(sensors.cameras))
    if missing:
        raise ValueError(f"observe: no camera model for {missing} (the dataset's sensors have "
                         f"{sorted(sensors.cameras)})")
    vel = ego_velocity(frame)
    ground = None
    if media.ground is not None:  # the keyframe's surfaces and edits: the LiDAR's own where it was computed here
        tracks = TireTracks.along_heading(frame.lidar.T_global_lidar)
        known = lidar is not None and lidar.ground_surfaces is not None
        surfaces = lidar.ground_surfaces if known else scan_surfaces(frame.lidar,
                                                                     off_ground=media.ground.kind == "snow")
        ground = FrameGround(surfaces, frame.lidar.T_global_lidar, media.ground.state(camera=True, tracks=tracks))
        lidar_edited = lidar.ground_edited if known else edit_scan(
            frame.lidar, surfaces, media.ground.state(camera=False, tracks=tracks), sensors.lidar.noise_floor,
            sensors.lidar.intensity_noise_std,
            None if sensors.lidar.floor_range_m is None else sensors.lidar.floor_scale).edited

    def one_camera(channel: str) -> CameraWeather:
        return observe_camera(images[channel], ranges[channel], frame.cameras[channel], media,
                              sensors.cameras[channel], airlight, vel, options, ground)

    with ThreadPoolExecutor(max_workers=max(1, options.threads)) as pool:
        lidar_future = pool.submit(observe_lidar, frame.lidar, media, sensors.lidar) if lidar is None else None
        cams = dict(zip(images, pool.map(one_camera, images)))
        lidar = lidar_future.result() if lidar_future is not None else lidar
    errors, channels = np.zeros(0), []
    if media.has_particles:
        ids, times = lidar_particles(lidar.particle_id, lidar.fire_times(), lidar.labels, WeatherLabel.SCATTERED)
        rendered = [c.particles for c in cams.values() if c.particles is not None]
        check = reprojection_check(media.field.field(), ids, times, rendered, media.aligned, options.near_clip_m)
        errors, channels = check.error_px, check.channel
    iou = {}
    if ground is not None:
        for channel, cam in cams.items():
            view = frame.cameras[channel]
            iou[channel] = mask_agreement(ground.surfaces.world, lidar_edited, CameraGeometry(
                np.asarray(view.K, dtype=np.float64), view.T_global_cam), cam.ground_mask,
                range_map=ranges[channel]).iou
    return FrameWeather(lidar, cams, errors, channels, iou)


__all__ = ["COUNT_KEYS", "JOINT_DRIFT_MAX_M", "CameraWeather", "FrameGround", "FrameWeather", "LidarWeather",
           "ObserveOptions",
           "ego_velocity", "joint_drift_m", "observe", "observe_camera", "observe_lidar", "observe_lidar_scans"]
