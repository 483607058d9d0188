"""One scene's ground state applied to a LiDAR scan and to a camera image: the same surfaces, the same fields.

`GroundState` is what lies on the ground of a scene under a condition: a water film (`WetRoad`) or snow
(`SnowCover`, pressed down in `TireTracks`), its fields drawn from ``seed`` in world coordinates. Per scan the
surfaces are found once (`scan_surfaces`: the ground plane by RANSAC, the returns' normals); `edit_scan` changes
exactly the returns on them (wet: the ground's, intensity by the water film's optics, the weakest lost; snow: every
up-facing return, raised onto the snow and brightened). A camera (`edit_image`) finds its pixels on the same plane
and the same up-facing surfaces (its own normals where its range map is exact, the nearest LiDAR return's where it
is a dense depth from the LiDAR) and draws the wet road or the snow over them. `mask_agreement` (in
`weatheralign.ground.surfaces`) measures how well the two agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter

from weatheralign.camera.fog import affine_edit_u8, decode_srgb_u8, range_guided_upsample
from weatheralign.data.frame import LidarScan
from weatheralign.geometry import invert
from weatheralign.ground.camera import CameraGeometry, snow_cover_layers, wet_road_layer_pair, wet_road_layers
from weatheralign.ground.snow import SnowCover, TireTracks, snow_covered_ground, surface_snow
from weatheralign.ground.surfaces import (
    MAX_SURFACE_VARIATION,
    median_over_neighbours,
    nearest_neighbours,
    nearest_return_values,
    pixel_normals,
    pixel_points,
    point_normals,
)
from weatheralign.ground.wet import WetRoad, film_depth, incidence_angle, puddle_margin, water_depth, wet_ground
from weatheralign.lidar.beams import (
    beam_origins,
    beams_from_scan,
    detector_noise_keys,
    point_noise_keys,
    point_ranges,
    ray_plane_ranges,
)
from weatheralign.lidar.ground_plane import GroundPlane, fit_ground_plane
from weatheralign.lidar.quantum import reading_uniforms, scan_clear_readings

if TYPE_CHECKING:
    from weatheralign.sensors import IntensityModel, LidarModel

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

DENSE_DEPTH_SOFTEN_PX = 1.5
"""Gaussian blur [px] of the snow coverage of a camera whose surfaces come from a dense depth (the nearest return's
orientation is piecewise constant)."""

REFLECTION_STRIDE = 1
"""The mirror image is traced on every this-many rows and columns of the working grid (`strided_reflection`): a
puddle is a sharp mirror, and coarser blocks show as steps in its image."""

WORK_STRIDE = 4
"""The ground's camera layers are found on every this-many rows and columns (`edit_image`)."""

WET_NOISE_COUNTER = 3
"""The wet reading's missing noise takes draws 3 and 4 of each beam's detector-noise stream (`wet_reading_normals`):
the air's weather reads the same beam next with draws 0 and 1 (`weatheralign.medium.field.normal_pair`: intensity and
range noise) and places its clear reading with draw 2 (`weatheralign.lidar.quantum.DITHER_COUNTER`)."""


def wet_reading_normals(noise_keys: NDArray[np.uint64]) -> F64:
    """(N,) a standard normal per beam from draws `WET_NOISE_COUNTER` and the next of its detector-noise stream
    ``noise_keys`` (N,) (`weatheralign.lidar.beams.point_noise_keys`), by Box–Muller as `normal_pair` draws its
    first."""
    u1 = 1.0 - reading_uniforms(noise_keys, WET_NOISE_COUNTER)  # (0, 1]
    u2 = reading_uniforms(noise_keys, WET_NOISE_COUNTER + 1)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


SNOW_EDIT_MIN_COVERAGE = 0.5
"""A return or pixel counts as snow-covered (edited, for the agreement of the sensors) over this covered share."""


@dataclass(frozen=True)
class GroundState:
    """What lies on a scene's ground: a water film ``road`` or snow ``cover`` (with wheel ``tracks``), never both;
    the fields' ``seed``; returns and pixels within ``plane_tolerance_m`` of the ground plane are on the ground."""

    road: WetRoad | None = None
    cover: SnowCover | None = None
    tracks: TireTracks | None = None
    seed: int = 0
    plane_tolerance_m: float = 0.2

    def __post_init__(self) -> None:
        if (self.road is None) == (self.cover is None):
            raise ValueError("GroundState needs exactly one of road (wet) and cover (snow)")

    @property
    def kind(self) -> str:
        """``wet`` or ``snow``."""
        return "wet" if self.road is not None else "snow"


class ScanSurfaces(NamedTuple):
    """One scan's surfaces, found once for every sensor."""

    plane: GroundPlane  # in the scan's frame
    on_ground: Mask  # (N,)
    normals: F64  # (N, 3) unit, scan frame (the plane's on the ground)
    cos_up: F64  # (N,) of the normal with the world's vertical (median over 16 neighbours off the ground)
    world: F64  # (N, 3) the returns in the world frame [m]


def scan_surfaces(scan: LidarScan, tolerance_m: float = 0.2, off_ground: bool = True) -> ScanSurfaces:
    """The ground plane of ``scan`` (`fit_ground_plane`) and its returns' surface orientation: the plane's on the
    ground; elsewhere (``off_ground``) from the other off-ground returns around each (a car's flank is not levelled
    by the road beside it; the median over them of ``|n_z|``, 0 where the neighbourhood is no surface:
    `MAX_SURFACE_VARIATION`), else vertical (0: no snow lies there)."""
    xyz = scan.points[:, :3].astype(np.float64)
    plane = fit_ground_plane(xyz, tolerance_m=tolerance_m)
    on_ground = plane.contains(xyz)
    normals = np.zeros_like(xyz)
    normals[on_ground] = plane.normal
    T = scan.T_global_lidar
    off = np.nonzero(~on_ground)[0]
    cos_up = np.zeros(len(xyz))
    cos_up[on_ground] = abs(float((T[:3, :3] @ np.asarray(plane.normal))[2]))
    if off_ground and len(off) >= 16:
        neighbours = nearest_neighbours(xyz[off])  # one search for the normals and their median
        found = point_normals(xyz[off], np.zeros(3), neighbours)
        normals[off] = found.normals
        level = np.where(found.variation <= MAX_SURFACE_VARIATION, np.abs(found.normals @ T[2, :3]), 0.0)
        cos_up[off] = median_over_neighbours(level, neighbours)
    else:
        normals[off] = xyz[off] / np.maximum(np.linalg.norm(xyz[off], axis=1, keepdims=True), 1e-9)
    return ScanSurfaces(plane, on_ground, normals, cos_up, xyz @ T[:3, :3].T + T[:3, 3])


class EditedScan(NamedTuple):
    """A scan after the ground edit."""

    scan: LidarScan  # the returns left (lost ones removed), then the snow's returns from beams that had none
    source_index: NDArray[np.int64]  # (M,) row of the input scan of each; -1: a return the snow added
    changed: Mask  # (M,) the ground edit changed or added it (intensity, position)
    edited: Mask  # (N,) per input return: on a wet or snow-covered surface (lost ones included)
    lost: int  # returns pushed under the detector floor
    added: int = 0  # returns of snow on the road where the clear beam returned nothing


class UnseenBeams(NamedTuple):
    """The beams of a scan that returned nothing (`unseen_beams`), in the scan's frame."""

    origins: F64  # (K, 3) [m] the sensor at each beam's firing time
    directions: F64  # (K, 3) unit
    time_offsets: F64  # (K,) [s] after the scan's timestamp
    ring: F64  # (K,)
    noise_keys: NDArray[np.uint64]  # (K,) each beam's detector-noise stream (`detector_noise_keys`)
    max_range_m: float
    intensity: IntensityModel  # how the sensor reports a surface's reflectivity at a range
    azimuth_step_rad: float  # the firing grid's azimuth step: the scale of a beam's same-ring neighbourhood


def unseen_beams(scan: LidarScan, lidar: LidarModel) -> UnseenBeams:
    """The beams of ``scan`` without return as the particle simulation finds them
    (`weatheralign.lidar.beams.beams_from_scan`: the firing grid where the dataset stores columns, else reconstructed
    from the ring/azimuth gaps), moved to the scan's frame, with their detector-noise streams."""
    beams = beams_from_scan(scan, lidar=lidar)
    none = beams.select(~beams.has_return)
    T = invert(scan.T_global_lidar)
    return UnseenBeams(none.origins @ T[:3, :3].T + T[:3, 3], none.directions @ T[:3, :3].T,
                       none.times - scan.timestamp, none.ring.astype(np.float64),
                       detector_noise_keys(none.times, none.directions, none.ring), float(none.max_range),
                       lidar.intensity, 2.0 * np.pi / lidar.columns_per_ring)


NEAR_ROAD_M = (3.0, 15.0)
"""Ranges [m] of the ground returns whose reflectivity stands for the bare road's (`snow_on_unseen_road`): near enough
that the detector sees all of it."""

MIN_NEAR_ROAD_RETURNS = 50
"""Fewer ground returns than this within `NEAR_ROAD_M`: the bare road is taken to read half the floor."""


NEIGHBOUR_WINDOW_STEPS = 2.0
"""The returns of a beam's own ring within this many azimuth steps of it are its neighbours (`dark_road_misses`)."""

BLOCKED_REACH_SHARE = 0.8
"""A neighbour nearer than this share of a beam's reach to the ground stands in front of the road: the beam most likely
met the same object (a dark car, a pole), not the road behind it."""

BRIGHT_ROAD_FLOORS = 4.0
"""A neighbour on the road reading this many detector floors: the road there is far brighter than a beam-to-beam
texture contrast can hide, so the beam's missing return is a dropout (no measurement), not a dark road."""


def dark_road_misses(scan: LidarScan, ring: F64, directions: F64, reach: F64, floor: F64,
                     azimuth_step_rad: float) -> Mask:
    """(K,) True for the beams without return (``ring`` (K,), unit ``directions`` (K, 3) in the scan's frame) whose
    missing return the dark road explains: every same-ring return of ``scan`` within `NEIGHBOUR_WINDOW_STEPS`
    azimuth steps (``azimuth_step_rad``) of the beam lies at `BLOCKED_REACH_SHARE` of its ground reach ``reach`` (K,)
    [m] or farther (else an object in front of the road blocked it) and reads under `BRIGHT_ROAD_FLOORS` times its
    floor ``floor`` (K,) (0..255; else the road there is bright: a dropout). A beam without neighbours (inside a long
    run of missing returns) is explained. Azimuths and ranges are taken from the scan frame's origin; a ring's ends
    do not wrap around."""
    explained = np.ones(len(ring), dtype=bool)
    if not len(ring) or not len(scan.points):
        return explained
    xyz = scan.points[:, :3].astype(np.float64)
    key = 8.0 * scan.points[:, 4].astype(np.float64) + np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi  # ring-major:
    order = np.argsort(key, kind="stable")  # azimuth + pi lies in [0, 2 pi] < 8
    key = key[order]
    ranges = np.linalg.norm(xyz[order], axis=1)
    reading = scan.intensity_255().astype(np.float64)[order]
    beam_key = 8.0 * ring + np.arctan2(directions[:, 1], directions[:, 0]) + np.pi
    window = NEIGHBOUR_WINDOW_STEPS * azimuth_step_rad
    low = np.searchsorted(key, beam_key - window, side="left")
    count = np.searchsorted(key, beam_key + window, side="right") - low
    for j in range(int(count.max())):  # a few neighbours at most: one pass per neighbour slot
        has = count > j
        at = low[has] + j
        explained[has] &= (ranges[at] >= BLOCKED_REACH_SHARE * reach[has]) & (
            reading[at] < BRIGHT_ROAD_FLOORS * floor[has])
    return explained


def road_reflectivity(scan: LidarScan, surfaces: ScanSurfaces, intensity: IntensityModel) -> float | None:
    """The bare road's reflectivity: the median over the returns on the fitted ground within `NEAR_ROAD_M` of their
    intensity divided by what a reflectivity of 1 reads there (``intensity``: ``scale cos θ g(R)``, θ the incidence
    on the plane); None with fewer than `MIN_NEAR_ROAD_RETURNS` of them."""
    xyz = scan.points[:, :3].astype(np.float64)
    r = np.linalg.norm(xyz, axis=1)
    near = surfaces.on_ground & (r >= NEAR_ROAD_M[0]) & (r <= NEAR_ROAD_M[1])
    if near.sum() < MIN_NEAR_ROAD_RETURNS:
        return None
    cos_in = np.cos(incidence_angle(xyz[near], np.zeros(3), np.asarray(surfaces.plane.normal)))
    unit = intensity.intensity(1.0, r[near]) * np.maximum(cos_in, 1e-3)
    return float(np.median(scan.intensity_255()[near].astype(np.float64) / unit))


def snow_on_unseen_road(scan: LidarScan, surfaces: ScanSurfaces, state: GroundState, unseen: UnseenBeams,
                        noise_floor: float, noise_std: float = 0.0,
                        floor_scale: Callable[[F64], F64] | None = None) -> tuple[NDArray[np.float32], F64]:
    """The snow's returns from beams that returned nothing on a dark road: (M, 5) points (x, y, z [m], intensity on
    ``scan``'s scale, ring) in the scan's frame and their firing-time offsets (M,) [s].

    A beam of ``unseen`` that points below the horizon onto the fitted ground plane within the maximum range, and whose
    same-ring neighbours neither stand in front of the road nor read it bright (`dark_road_misses`), met the bare road
    under the detector floor: at grazing incidence and long range the road reads ``scale ρ cos θ g(R)``
    (``unseen.intensity``) with ``ρ`` the near road's (`road_reflectivity`; unknown: half the floor), capped at the
    floor at the beam's range (it returned nothing). Under ``state``'s snow the beam's footprint is covered over the
    share `surface_snow` gives there, the surface raised and brightened as for a seen return (`snow_covered_ground`),
    and read by a detector of intensity noise ``noise_std`` (0..255; the beam's `wet_reading_normals`): the returns
    at or over the floor ``noise_floor`` (0..255) are kept. ``floor_scale``: the floor's and the noise's factor at a
    range (None: constant)."""
    empty = (np.zeros((0, 5), dtype=np.float32), np.zeros(0))
    if state.cover is None or not len(unseen.origins):
        return empty
    normal = np.asarray(surfaces.plane.normal, dtype=np.float64)
    reach = ray_plane_ranges(unseen.origins, unseen.directions, surfaces.plane)
    on = np.flatnonzero(reach < unseen.max_range_m)
    floor = noise_floor * (np.ones(len(on)) if floor_scale is None else floor_scale(reach[on]))
    on = on[dark_road_misses(scan, unseen.ring[on], unseen.directions[on], reach[on], floor,
                             unseen.azimuth_step_rad)]
    if not len(on):
        return empty
    hits = unseen.origins[on] + unseen.directions[on] * reach[on, None]
    T = scan.T_global_lidar
    world_xy = (hits @ T[:3, :3].T + T[:3, 3])[:, :2]
    cos_up = np.full(len(on), abs(float((T[:3, :3] @ normal)[2])))
    coverage, depth = surface_snow(world_xy, cos_up, state.cover, state.seed, state.tracks)
    covered = coverage > 0.0
    on, hits, coverage, depth = on[covered], hits[covered], coverage[covered], depth[covered]
    reach = reach[on]
    descent = -(unseen.directions[on] @ normal)  # cos of the incidence on the plane
    scale = np.ones(len(on)) if floor_scale is None else floor_scale(reach)
    floor = noise_floor * scale
    rho = road_reflectivity(scan, surfaces, unseen.intensity)
    bare = 0.5 * floor if rho is None else np.minimum(unseen.intensity.intensity(rho, reach) * descent, floor)
    effect = snow_covered_ground(hits, unseen.origins[on], normal, bare, depth, state.cover, coverage=coverage)
    reading = effect.intensity
    if noise_std > 0.0:
        reading = np.clip(reading + noise_std * scale * wet_reading_normals(unseen.noise_keys[on]), 0.0, 255.0)
    seen = reading >= floor
    points = np.column_stack([effect.points[seen], reading[seen] * (scan.intensity_max / 255.0),
                              unseen.ring[on][seen]]).astype(np.float32)
    return points, unseen.time_offsets[on][seen]


def edit_scan(scan: LidarScan, surfaces: ScanSurfaces, state: GroundState, noise_floor: float,
              noise_std: float = 0.0, floor_scale: Callable[[F64], F64] | None = None,
              unseen: UnseenBeams | None = None) -> EditedScan:
    """``scan`` with ``state``'s ground: wet ground returns dimmed by the film (`wet_ground`: an integer-quantised
    scan's readings spread over their rounding intervals, `weatheralign.lidar.quantum.scan_clear_readings`; read
    again by a detector of intensity noise ``noise_std`` (0..255), each with its beam's `wet_reading_normals`), the
    ones under ``noise_floor`` (0..255) lost; snow-covered returns raised onto the snow along their beams and
    brightened over the covered share (`snow_covered_ground`), and with ``unseen`` (the scan's beams without return)
    the snow's returns on the road those beams met under the floor appended (`snow_on_unseen_road`; not for a scan of
    aggregated sweeps). ``floor_scale``: the factor of the floor and of the noise's constant part at a range (a
    raw-power detector's, `weatheralign.sensors.LidarModel.floor_scale`), taken at each return's range from its beam
    origin; None: both constant."""
    points = scan.points.copy()
    intensity = scan.intensity_255().astype(np.float64)
    keep = np.ones(len(points), dtype=bool)
    if state.road is not None:
        ground = surfaces.on_ground
        xyz = points[ground, :3].astype(np.float64)
        depth = water_depth(surfaces.world[ground, :2], state.road, state.seed)
        keys = point_noise_keys(scan)
        scale = (np.ones(len(points)) if floor_scale is None
                 else floor_scale(point_ranges(scan.points, beam_origins(scan, "scan"))))
        clear = scan_clear_readings(scan, noise_floor * scale if floor_scale is not None else noise_floor, keys)
        normals = wet_reading_normals(keys[ground]) if noise_std > 0.0 else None
        effect = wet_ground(intensity[ground], incidence_angle(xyz, np.zeros(3), np.asarray(surfaces.plane.normal)),
                            depth, state.road, noise_floor * scale[ground], None if clear is None else clear[ground],
                            noise_std * scale[ground], normals)
        intensity[ground] = effect.intensity
        keep[np.nonzero(ground)[0][effect.lost]] = False
        edited = ground.copy()
        changed = ground.copy()
        changed[ground] = effect.factor != 1.0
    else:
        coverage, depth = surface_snow(surfaces.world[:, :2], surfaces.cos_up, state.cover, state.seed, state.tracks)
        covered = coverage > 0.0
        run = np.where(surfaces.on_ground[covered], np.inf, state.cover.edge_run_m)  # the plane has no near edge
        effect = snow_covered_ground(points[covered, :3].astype(np.float64), np.zeros(3), surfaces.normals[covered],
                                     intensity[covered], depth[covered], state.cover, coverage=coverage[covered],
                                     max_run_m=run)
        points[covered, :3] = effect.points.astype(np.float32)
        intensity[covered] = effect.intensity
        edited = coverage > SNOW_EDIT_MIN_COVERAGE
        changed = covered
    points[:, 3] = (intensity * (scan.intensity_max / 255.0)).astype(np.float32)
    rows = np.nonzero(keep)[0]
    new, new_offsets = (np.zeros((0, 5), dtype=np.float32), np.zeros(0))
    if unseen is not None and scan.sweep_index is None:
        new, new_offsets = snow_on_unseen_road(scan, surfaces, state, unseen, noise_floor, noise_std, floor_scale)
    offsets = None
    if scan.time_offsets is not None:
        offsets = np.concatenate([scan.time_offsets[rows], new_offsets.astype(scan.time_offsets.dtype)])
    out = replace(scan, points=np.ascontiguousarray(np.concatenate([points[rows], new])), time_offsets=offsets,
                  sweep_index=None if scan.sweep_index is None else scan.sweep_index[rows])
    return EditedScan(out, np.concatenate([rows, np.full(len(new), -1)]).astype(np.int64),
                      np.concatenate([changed[rows], np.ones(len(new), dtype=bool)]), edited, int((~keep).sum()),
                      len(new))


class EditedImage(NamedTuple):
    """A camera image after the ground edit."""

    linear: F64  # (H, W, 3) linear light
    edited: Mask  # (H, W) pixels on a wet or snow-covered surface


class GroundLayers(NamedTuple):
    """The ground's camera layers on one grid: the image becomes ``image * gain + offset`` (H, W, 3), its ``edited``
    pixels (H, W) on a wet or snow-covered surface; with ``puddle`` layers (gain, offset), the pixels whose
    ``shoreline`` (H, W, finite: `weatheralign.ground.wet.puddle_margin` on the ground, -1 off it) is > 0 take
    those instead."""

    gain: F64
    offset: F64
    edited: Mask
    puddle: tuple[F64, F64] | None = None
    shoreline: F64 | None = None

    def combined(self) -> tuple[F64, F64]:
        """(gain, offset) with the puddle's where the shoreline says so, on this grid."""
        if self.puddle is None or self.shoreline is None:
            return self.gain, self.offset
        inside = (self.shoreline > 0)[..., None]
        return np.where(inside, self.puddle[0], self.gain), np.where(inside, self.puddle[1], self.offset)


def edit_image(linear: F64, range_map: NDArray, camera: CameraGeometry, exact_range: bool,
               surfaces: ScanSurfaces, T_world_scan: F64, state: GroundState, sky: F64,
               work_stride: int = WORK_STRIDE) -> EditedImage:
    """The linear image (H, W, 3) of ``camera`` with ``state``'s ground over the pixels on the scan's ground plane
    and up-facing surfaces (``surfaces`` of the scan whose frame ``T_world_scan`` (4, 4) maps to the world);
    ``range_map`` (H, W) [m] (inf: sky) is exact (the synthetic world's) or a dense depth from that scan; ``sky``
    (3,) the sky's linear radiance. The ground's layers (`ground_layers`) are found on every ``work_stride``-th row
    and column (their fields vary over decimetres, their filters over tens of pixels) and brought to every pixel of
    the full image by range-guided bilinear weights (`weatheralign.camera.fog.range_guided_upsample`: a layer found
    on the road does not bleed onto the car before it); a puddle's shoreline is found per pixel from the brought
    smooth field, so it does not follow the coarse grid's steps."""
    stride = max(int(work_stride), 1)
    layers = _coarse_layers(np.asarray(linear, dtype=np.float64)[::stride, ::stride], range_map, camera, exact_range,
                            surfaces, T_world_scan, state, sky, stride)
    if stride > 1:
        layers = _brought_to_every_pixel(layers, range_map, stride)
    gain, offset = layers.combined()
    return EditedImage(np.asarray(linear, dtype=np.float64) * gain + offset, layers.edited)


def _brought_to_every_pixel(layers: GroundLayers, range_map: NDArray, stride: int) -> GroundLayers:
    """``layers`` given on every ``stride``-th row and column of ``range_map`` (H, W), at every pixel
    (`weatheralign.camera.fog.range_guided_upsample`)."""
    def up(values: NDArray, fill: float = 0.0) -> F64:
        return range_guided_upsample(values, range_map, stride, fill=fill)

    return GroundLayers(up(layers.gain, 1.0), up(layers.offset), up(layers.edited.astype(np.float64)) > 0.5,
                        None if layers.puddle is None else (up(layers.puddle[0], 1.0), up(layers.puddle[1])),
                        None if layers.shoreline is None else up(layers.shoreline, -1.0))


def edit_image_u8(image: NDArray[np.uint8], range_map: NDArray, camera: CameraGeometry, exact_range: bool,
                  surfaces: ScanSurfaces, T_world_scan: F64, state: GroundState, sky: F64,
                  work_stride: int = WORK_STRIDE) -> tuple[NDArray[np.uint8], Mask]:
    """`edit_image` of a uint8 sRGB ``image`` (H, W, 3), returned as uint8 sRGB with its edited pixels (H, W): the
    layers brought to every pixel, applied and encoded in one compiled pass
    (`weatheralign.camera.fog.affine_edit_u8`)."""
    stride = max(int(work_stride), 1)
    linear = decode_srgb_u8(np.asarray(image)[::stride, ::stride]).astype(np.float64)
    layers = _coarse_layers(linear, range_map, camera, exact_range, surfaces, T_world_scan, state, sky, stride)
    return affine_edit_u8(image, layers.gain, layers.offset, layers.edited, range_map, stride,
                          alternative=layers.puddle, switch=layers.shoreline)


def _coarse_layers(linear: F64, range_map: NDArray, camera: CameraGeometry, exact_range: bool,
                   surfaces: ScanSurfaces, T_world_scan: F64, state: GroundState, sky: F64,
                   stride: int) -> GroundLayers:
    """`ground_layers` on every ``stride``-th row and column of the full-size ``range_map`` (``linear`` already
    taken there), the camera's intrinsics scaled to that grid."""
    small = CameraGeometry(np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(camera.K, dtype=np.float64),
                           camera.T_world_cam)
    return ground_layers(linear, np.asarray(range_map)[::stride, ::stride].astype(np.float64), small, exact_range,
                         surfaces, T_world_scan, state, sky, stride)


def odd_px(size: float) -> int:
    """The odd window [px] nearest ``size`` (at least 1)."""
    return max(1, int(round(size)) // 2 * 2 + 1)


def ground_layers(linear: F64, range_map: F64, camera: CameraGeometry, exact_range: bool, surfaces: ScanSurfaces,
                  T_world_scan: F64, state: GroundState, sky: F64, stride: int = 1) -> GroundLayers:
    """The layers of `edit_image` at the resolution of ``range_map``, ``stride`` times coarser than the full image
    (its filters' windows scaled); a wet road's puddles as layers of their own with their shoreline field."""
    finite = np.isfinite(range_map)
    plane = surfaces.plane.transformed(T_world_scan)
    pixels = None if state.road is not None else pixel_normals(range_map, camera, smooth_px=odd_px(5 / stride))
    points = pixel_points(range_map, camera) if pixels is None else pixels.points_world  # water needs no normals
    ground = finite & plane.contains(points)  # the sky's nan points are on no plane
    if state.road is not None:
        road, xy = state.road, points[ground][:, :2]
        film = np.zeros(range_map.shape)
        film[ground] = film_depth(xy, road, state.seed)
        shoreline = np.full(range_map.shape, -1.0)
        shoreline[ground] = puddle_margin(xy, road, state.seed)
        args = (linear, np.where(finite, range_map, np.inf), camera, ground, film, road, np.asarray(plane.normal), sky,
                (odd_px(31 / stride), odd_px(5 / stride)), REFLECTION_STRIDE)
        if road.puddle_share == 0:
            return GroundLayers(*wet_road_layers(*args), ground & (film > 0))
        layers = wet_road_layer_pair(*args)
        return GroundLayers(*layers.film, ground & ((film > 0) | (shoreline > 0)), layers.puddle, shoreline)
    if exact_range:
        cos_up = np.abs(np.nan_to_num(pixels.normals_world[..., 2]))
        known = np.isfinite(pixels.normals_world[..., 2])
    else:  # a dense depth between the LiDAR's rings has no normals of its own off the ground
        near = nearest_return_values(pixels.points_world.reshape(-1, 3), surfaces.world, surfaces.cos_up)
        near = near.reshape(range_map.shape)
        cos_up, known = np.nan_to_num(near), np.isfinite(near)
    cos_up = np.where(ground, plane.normal[2], cos_up)
    known |= ground
    coverage = np.zeros(range_map.shape)
    coverage[known] = surface_snow(pixels.points_world[known][:, :2], cos_up[known], state.cover, state.seed,
                                   state.tracks)[0]
    if not exact_range:  # the nearest return's orientation is constant over each return's cell: soften the edges
        coverage = gaussian_filter(coverage, DENSE_DEPTH_SOFTEN_PX / stride)
    gain, offset = snow_cover_layers(linear, coverage, pixels.points_world, ground, state.cover, sky, state.seed,
                                     shading_px=odd_px(31 / stride))
    return GroundLayers(gain, offset, coverage > SNOW_EDIT_MIN_COVERAGE)


__all__ = ["EditedImage", "EditedScan", "GroundLayers", "GroundState", "MIN_NEAR_ROAD_RETURNS", "NEAR_ROAD_M",
           "SNOW_EDIT_MIN_COVERAGE", "ScanSurfaces", "UnseenBeams", "WET_NOISE_COUNTER", "WORK_STRIDE", "edit_image",
           "edit_image_u8", "edit_scan", "ground_layers", "odd_px", "road_reflectivity", "scan_surfaces",
           "snow_on_unseen_road", "unseen_beams", "wet_reading_normals"]
