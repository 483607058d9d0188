"""The synthetic reference's ground: the rain split's road under a water film, the snow split's under lying snow, at
hidden depths, drawn on the scene's true surfaces by the physics the simulation applies (`weatheralign.ground.edit`).

Hidden truth. One mean film depth for the rain split, one snow depth for the snow split, drawn uniformly in
``reference.precipitation.wet_film_depth_m`` / ``snow_depth_m`` from ``reference.seed`` (`draw_ground_truth`) and
sealed beside the rates; each frame's fields (wet patches and puddles, snow depth and wheel tracks) come from a seed
of the frame's own. The puddles cover `weatheralign.ground.wet.WetRoad`'s default share.

True surfaces. Where the simulation finds the ground plane by RANSAC and the returns' orientation from their
neighbours (`weatheralign.ground.edit.scan_surfaces`), the reference knows them: the world's ground is the plane
``z = 0`` (the ego origin lies on it) and every LiDAR hit carries the normal of the face it struck
(`exact_surfaces`). The LiDAR's clear echoes are edited before the weather's processes and the detector (a wet
return the detector cannot see is dropped by its noise floor, not by the edit), the camera's clear radiance before
the particles, at every pixel (the simulation finds its layers on a coarser grid).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from weatheralign.config import ReferenceConfig
from weatheralign.data.frame import LidarScan
from weatheralign.ground.edit import GroundState, ScanSurfaces, edit_scan
from weatheralign.ground.snow import SnowCover, TireTracks
from weatheralign.ground.wet import WetRoad
from weatheralign.lidar.ground_plane import GroundPlane
from weatheralign.reference.layout import LEVELS, PRECIPITATION_LEVELS

F64 = NDArray[np.float64]

_GROUND_TAG = 0x5E6D0D

GROUND_TOLERANCE_M = 0.2
"""Hits within this height [m] of the world's ground plane are on the ground (kerbs and sidewalks included), as
`weatheralign.ground.edit.GroundState.plane_tolerance_m`."""


def draw_ground_truth(cfg: ReferenceConfig) -> dict[str, float]:
    """The hidden ground ``{"rain": mean film depth [m], "snow": snow depth [m]}``, uniform in
    ``cfg.precipitation.wet_film_depth_m`` / ``snow_depth_m``, drawn from ``cfg.seed``; deterministic."""
    rng = np.random.default_rng([cfg.seed, _GROUND_TAG])
    pc = cfg.precipitation
    return {"rain": float(rng.uniform(*pc.wet_film_depth_m)), "snow": float(rng.uniform(*pc.snow_depth_m))}


def frame_ground_state(level: str, index: int, cfg: ReferenceConfig, T_global_lidar: F64) -> GroundState | None:
    """The ground of frame ``index`` of ``level`` (None for the clear and fog levels, or with
    ``cfg.precipitation.ground`` off): the split's hidden depth, the frame's own field seed, for snow wheel tracks
    along the LiDAR's heading ``T_global_lidar`` (4, 4)."""
    if not cfg.precipitation.ground or level not in PRECIPITATION_LEVELS:
        return None
    amount = draw_ground_truth(cfg)[level]
    seed = int(np.random.default_rng([cfg.seed, _GROUND_TAG, LEVELS.index(level), index]).integers(0, 2**31 - 1))
    if level == "rain":
        return GroundState(road=WetRoad(film_depth_m=amount), seed=seed, plane_tolerance_m=GROUND_TOLERANCE_M)
    return GroundState(cover=SnowCover(depth_m=amount), tracks=TireTracks.along_heading(T_global_lidar), seed=seed,
                       plane_tolerance_m=GROUND_TOLERANCE_M)


def exact_surfaces(points: F64, normals_world: F64, T_global_lidar: F64) -> ScanSurfaces:
    """The true `ScanSurfaces` of LiDAR hits ``points`` (N, 3) [m, LiDAR frame] on faces of world normals
    ``normals_world`` (N, 3): the ground plane ``z = 0`` of the world in the LiDAR's frame, the hits within
    `GROUND_TOLERANCE_M` of it on the ground (the plane's normal), the others their face's normal."""
    T = np.asarray(T_global_lidar, dtype=np.float64)
    xyz = np.asarray(points, dtype=np.float64)
    plane = GroundPlane((0.0, 0.0, 1.0), 0.0, GROUND_TOLERANCE_M).transformed(np.linalg.inv(T))
    on_ground = plane.contains(xyz)
    normals = np.asarray(normals_world, dtype=np.float64) @ T[:3, :3]  # world -> LiDAR: R^T n, row-wise
    normals[on_ground] = plane.normal
    cos_up = np.abs(np.asarray(normals_world, dtype=np.float64)[:, 2])
    cos_up[on_ground] = 1.0
    return ScanSurfaces(plane, on_ground, normals, cos_up, xyz @ T[:3, :3].T + T[:3, 3])


def ground_hits(points: F64, intensity: F64, surfaces: ScanSurfaces, state: GroundState, timestamp: float,
                T_ego_lidar: F64, T_global_ego: F64) -> tuple[F64, F64]:
    """Clear LiDAR hits ``points`` (N, 3) [m] of ``intensity`` (N,) (0..255) under ``state``'s ground
    (`weatheralign.ground.edit.edit_scan` on ``surfaces``, no return dropped: the detector decides which it sees).
    Returns the hits' new ranges [m] (N,) along their beams and new intensities (N,)."""
    xyz = np.asarray(points, dtype=np.float64)
    cloud = np.column_stack([xyz, np.clip(intensity, 0.0, 255.0), np.zeros(len(xyz))]).astype(np.float32)
    scan = LidarScan(cloud, timestamp, np.asarray(T_ego_lidar, dtype=np.float64),
                     np.asarray(T_global_ego, dtype=np.float64), num_rings=64)
    edited = edit_scan(scan, surfaces, state, noise_floor=0.0)
    if edited.lost:
        raise AssertionError("ground_hits: a zero noise floor loses no return")
    moved = edited.scan.points[:, :3].astype(np.float64)
    ranges = np.where(edited.changed, np.linalg.norm(moved, axis=1), np.linalg.norm(xyz, axis=1))
    return ranges, np.where(edited.changed, edited.scan.points[:, 3].astype(np.float64), intensity)


__all__ = ["GROUND_TOLERANCE_M", "draw_ground_truth", "exact_surfaces", "frame_ground_state", "ground_hits"]
