"""The ground plane under a LiDAR: the dominant plane of its low returns (`fit_ground_plane`: a seeded RANSAC on the
returns more than ``min_drop_m`` below the sensor, refined by least squares) and the distance within which a return
lies on it. The LiDAR's beams end on it where they return nothing (`weatheralign.lidar.beams.with_ground_plane`);
the ground edit (`weatheralign.ground`) puts water and snow on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]


@dataclass(frozen=True)
class GroundPlane:
    """The plane ``normal . x + offset = 0`` in the frame of the points it was fitted to (unit ``normal`` (3,)
    pointing up), and the distance [m] within which a point is on it."""

    normal: tuple[float, float, float]
    offset: float
    tolerance_m: float = 0.15

    def height(self, points: F64) -> F64:
        """(N,) signed height [m] of points (N, 3) above the plane."""
        return np.asarray(points, dtype=np.float64) @ np.asarray(self.normal) + self.offset

    def contains(self, points: F64) -> Mask:
        """(N,) points within ``tolerance_m`` of the plane."""
        return np.abs(self.height(points)) < self.tolerance_m

    def transformed(self, T: F64) -> GroundPlane:
        """The same plane in the frame that the rigid transform ``T`` (4, 4) maps this frame into."""
        normal = np.asarray(T, dtype=np.float64)[:3, :3] @ np.asarray(self.normal)
        offset = self.offset - float(normal @ np.asarray(T, dtype=np.float64)[:3, 3])
        return GroundPlane((float(normal[0]), float(normal[1]), float(normal[2])), offset, self.tolerance_m)


def fit_ground_plane(points: F64, min_drop_m: float = 1.0, tolerance_m: float = 0.15, seed: int = 0,
                     hypotheses: int = 512, sample: int = 4096) -> GroundPlane:
    """The dominant plane among the LiDAR returns (N, 3) (sensor frame, z up) lying more than ``min_drop_m`` below
    the sensor: RANSAC over ``hypotheses`` planes through three returns, scored by the returns of a ``sample`` of the
    low ones within ``tolerance_m`` (all drawn from a generator seeded with ``seed``: same cloud, same plane; open3d's
    multithreaded ``segment_plane`` is not reproducible), then refined by least squares on the best plane's inliers
    among all the low returns, twice. Raises ``ValueError`` when fewer than 100 returns lie that low."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    low = xyz[xyz[:, 2] < -min_drop_m]
    if len(low) < 100:
        raise ValueError(f"fit_ground_plane: {len(low)} returns lie {min_drop_m} m below the sensor; need >= 100 "
                         "(is the cloud in the sensor frame, z up?)")
    rng = np.random.default_rng(seed)
    scored = low[rng.choice(len(low), min(sample, len(low)), replace=False)]
    triples = low[rng.integers(0, len(low), (hypotheses, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    length = np.linalg.norm(normals, axis=1)
    valid = length > 1e-9
    normals = normals[valid] / length[valid, None]
    normals *= np.where(normals[:, 2] < 0, -1.0, 1.0)[:, None]
    offsets = -np.sum(normals * triples[valid, 0], axis=1)
    best = int(np.argmax(plane_inliers(scored, normals, offsets, tolerance_m)))
    normal, offset = normals[best], float(offsets[best])
    for _ in range(2):  # least squares on the inliers: the plane through their centroid along their least variance
        near = low[np.abs(low @ normal + offset) < tolerance_m]
        if len(near) < 3:
            break
        centre = near.mean(axis=0)
        around = near - centre
        refined = np.linalg.eigh(around.T @ around)[1][:, 0]  # the scatter's least eigenvector
        normal = refined if refined[2] >= 0 else -refined
        offset = float(-normal @ centre)
    return GroundPlane((float(normal[0]), float(normal[1]), float(normal[2])), offset, tolerance_m)


@numba.njit(cache=True, nogil=True)
def plane_inliers_kernel(points: F64, normals: F64, offsets: F64, tolerance_m: float) -> NDArray[np.int64]:
    """(H,) per plane ``normals[h] . x + offsets[h] = 0`` (normals (H, 3), offsets (H,)) the number of ``points``
    (S, 3) closer to it than ``tolerance_m`` (`plane_inliers_naive`)."""
    x, y, z = points[:, 0].copy(), points[:, 1].copy(), points[:, 2].copy()  # contiguous: the loop vectorises
    counts = np.zeros(normals.shape[0], np.int64)
    for h in range(normals.shape[0]):
        nx, ny, nz, d = normals[h, 0], normals[h, 1], normals[h, 2], offsets[h]
        count = 0
        for i in range(x.shape[0]):
            count += abs(x[i] * nx + y[i] * ny + z[i] * nz + d) < tolerance_m
        counts[h] = count
    return counts



def plane_inliers(points: F64, normals: F64, offsets: F64, tolerance_m: float) -> NDArray[np.int64]:
    """`plane_inliers_naive`, compiled (`plane_inliers_kernel`)."""
    return plane_inliers_kernel(np.ascontiguousarray(points, dtype=np.float64),
                                np.ascontiguousarray(normals, dtype=np.float64),
                                np.ascontiguousarray(offsets, dtype=np.float64), float(tolerance_m))


def plane_inliers_naive(points: F64, normals: F64, offsets: F64, tolerance_m: float) -> NDArray[np.int64]:
    """(H,) per plane ``normals[h] . x + offsets[h] = 0`` (normals (H, 3) unit, offsets (H,)) the number of
    ``points`` (S, 3) closer to it than ``tolerance_m`` [m]."""
    return np.count_nonzero(np.abs(points @ normals.T + offsets) < tolerance_m, axis=0)


__all__ = ["fit_ground_plane", "GroundPlane", "plane_inliers", "plane_inliers_kernel", "plane_inliers_naive"]
