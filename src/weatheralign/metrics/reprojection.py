"""The re-projection check: do the LiDAR and a camera see the same particles at the same places?

For every particle that produced a SCATTERED LiDAR return: its position known to the LiDAR side (the LiDAR field's
position at the beam's firing time) is propagated to the camera's timestamp with the field velocity
(``p + v (t_cam - t_fire)``), projected with the camera's K and pose, and compared with the particle's rasterised
position in that camera (the alpha-weighted centroid of its footprint, `weatheralign.camera.splat.SplatResult`).

- Aligned (the camera renders the LiDAR's field): pairs are the particles the camera drew unoccluded by the scene
  with their whole footprint inside the image; the rasterised centroid of the *same id* is compared.
- Unaligned (the camera renders an independent field): the LiDAR particle is paired with the *nearest* rendered
  particle (centroid) of the camera, for every LiDAR particle whose projection falls in the image, in front of the
  scene (ray length below the scene's at that pixel) and within the camera's splatting range.

Errors are in pixels (Euclidean in the image plane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from weatheralign.geometry import apply, invert
from weatheralign.medium.field import ParticleField

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class CameraParticles:
    """What one camera rendered, for the check.

    Attributes:
        channel: camera name; K: (3, 3) [px]; T_global_cam: (4, 4) at ``timestamp`` [s]; width, height [px].
        ids: (N,) int64 ids of the rendered particles (of the camera's field); centroids: (N, 2) (u, v) [px].
        usable: (N,) bool, drawn, unoccluded by the scene and wholly inside the image (centroid unbiased).
        range_map: (H, W) scene ray length [m] (inf = sky), or None (no occlusion test for unaligned pairs).
        max_range: farthest ray length [m] at which the camera splats particles at all.
    """

    channel: str
    K: F64
    T_global_cam: F64
    timestamp: float
    width: int
    height: int
    ids: NDArray[np.int64]
    centroids: F64
    usable: NDArray[np.bool_]
    range_map: NDArray | None = None
    max_range: float = math.inf


@dataclass(frozen=True, eq=False)
class ReprojectionResult:
    """Per pair: the camera, the LiDAR particle id and the error [px]."""

    channel: list[str]
    particle_id: NDArray[np.int64]
    error_px: F64

    def summary(self) -> dict:
        n = int(self.error_px.size)
        return {"reprojection_pairs": n,
                "reprojection_mean_px": float(self.error_px.mean()) if n else None,
                "reprojection_max_px": float(self.error_px.max()) if n else None}


def lidar_particles(particle_id: NDArray, times: NDArray, labels: NDArray, scattered: int = 2) -> tuple[NDArray, F64]:
    """Unique ids of the particles behind SCATTERED points and the firing time of each one's first such point."""
    pid = np.asarray(particle_id, dtype=np.int64)
    sel = (np.asarray(labels) == scattered) & (pid >= 0)
    ids, first = np.unique(pid[sel], return_index=True)
    return ids, np.asarray(times, dtype=np.float64)[sel][first]


def _project(K: F64, T_global_cam: F64, p_global: F64) -> tuple[F64, F64, F64]:
    pc = apply(invert(T_global_cam), p_global)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (K[0, 0] * pc[:, 0] + K[0, 1] * pc[:, 1]) / z + K[0, 2]
        v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    return np.column_stack([u, v]), z, np.linalg.norm(pc, axis=1)


def reprojection_check(lidar_field: ParticleField, lidar_ids: NDArray, fire_times: NDArray,
                       cameras: list[CameraParticles], aligned: bool, near_clip: float = 0.5) -> ReprojectionResult:
    """Re-projection errors of the LiDAR's scattering particles in every camera (see the module docstring).

    Args:
        lidar_field: the field the LiDAR observed; lidar_ids, fire_times: from `lidar_particles`.
        cameras: what each camera rendered; aligned: match by id (True) or nearest rendered particle (False).
    """
    ids = np.asarray(lidar_ids, dtype=np.int64)
    times = np.asarray(fire_times, dtype=np.float64)
    chans: list[str] = []
    out_ids, errs = [], []
    if ids.size == 0:
        return ReprojectionResult([], np.zeros(0, np.int64), np.zeros(0))
    # the position known to the LiDAR side: each particle at its own firing time
    p_fire = lidar_field.positions_at_times(ids, times)
    vel = lidar_field.velocity_array
    for cam in cameras:
        p_cam = p_fire + np.outer(cam.timestamp - times, vel)
        uv, z, ell = _project(cam.K, cam.T_global_cam, p_cam)
        if aligned:
            order = np.argsort(cam.ids[cam.usable], kind="stable")
            usable_ids = cam.ids[cam.usable][order]
            cents = cam.centroids[cam.usable][order]
            if usable_ids.size == 0:
                continue
            pos = np.clip(np.searchsorted(usable_ids, ids), 0, usable_ids.size - 1)
            hit = (usable_ids[pos] == ids) & (z > 0)
            if hit.any():
                errs.append(np.linalg.norm(uv[hit] - cents[pos[hit]], axis=1))
                out_ids.append(ids[hit])
                chans += [cam.channel] * int(hit.sum())
        else:
            cents = cam.centroids[cam.usable]
            if cents.shape[0] == 0:
                continue
            ok = (z > 0.25 * near_clip) & (ell >= near_clip) & (ell <= cam.max_range)
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
            if cam.range_map is not None and ok.any():
                iu = np.clip(np.rint(uv[ok, 0]).astype(int), 0, cam.width - 1)
                iv = np.clip(np.rint(uv[ok, 1]).astype(int), 0, cam.height - 1)
                front = ell[ok] < np.asarray(cam.range_map)[iv, iu]
                idx = np.flatnonzero(ok)
                ok[idx[~front]] = False
            if ok.any():
                d, _ = cKDTree(cents).query(uv[ok])
                errs.append(np.asarray(d, dtype=np.float64))
                out_ids.append(ids[ok])
                chans += [cam.channel] * int(ok.sum())
    if not errs:
        return ReprojectionResult([], np.zeros(0, np.int64), np.zeros(0))
    return ReprojectionResult(chans, np.concatenate(out_ids), np.concatenate(errs))
