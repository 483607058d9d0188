"""The surfaces that receive water or snow, found once per frame so that the LiDAR and every camera edit the same ones.

The ground is the dominant plane under the sensor (`weatheralign.lidar.ground_plane.fit_ground_plane`); a LiDAR
return is on it within its ``tolerance_m``. The
up-facing surfaces elsewhere (car roofs, ledges, wall tops) come from surface normals: the LiDAR's from its points'
neighbourhoods (`point_normals`; a neighbourhood that is no surface, such as real foliage or the returns behind a
car's window, holds no snow: `MAX_SURFACE_VARIATION`), a camera's from the 3-D points of an exact range map
(`pixel_normals`: the synthetic world's). A dense depth interpolated from a LiDAR's rings is no such map: between
rings it spans flat facets, and its normals on facades, cars and people point anywhere; there a pixel takes the
orientation of the LiDAR return nearest its surface point (`nearest_return_values`), so both sensors read one set of
normals. Both sensors then ask the same questions of the same world positions (`weatheralign.ground.snow.snow_coverage`,
`weatheralign.ground.wet.water_depth`), and `mask_agreement` measures how well they agree: the LiDAR's edited
returns projected into a camera against the camera's edited pixels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter

from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.kernels import (
    neighbour_median_kernel,
    neighbour_normals_kernel,
    pixel_normals_kernel,
    pixel_points_kernel,
)

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]


MAX_SURFACE_VARIATION = 0.02
"""Largest surface variation (`point_normals_naive`) of a LiDAR return's 16 neighbours that still makes a surface
snow can lie on. A roof, a car's bonnet or a wall top under a range noise of about 1 cm (an HDL-64's) stays below it
(a plane's variation is about the noise's variance over the neighbourhood's extent's); foliage, the
returns seen through a car's window and scattered clutter lie well above (up to 1/3), and their PCA normal points
anywhere, so an orientation read from it would put snow on a tree's side or a car's door."""


def nearest_neighbours(points: F64, neighbours: int = 16) -> NDArray[np.int64]:
    """(N, k) the rows of each of ``points``' (N, 3) ``neighbours`` nearest points (k = min(neighbours, N)), itself
    included, in any order among equals (open3d's nanoflann search): one search for the normals and the median over
    the same neighbours."""
    import open3d as o3d

    cloud = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float64))
    search = o3d.core.nns.NearestNeighborSearch(cloud)
    search.knn_index()
    index, _ = search.knn_search(cloud, min(int(neighbours), len(points)))
    return np.ascontiguousarray(index.numpy(), dtype=np.int64)


class PointNormals(NamedTuple):
    """LiDAR returns' surface orientation from their neighbourhoods."""

    normals: F64  # (N, 3) unit, turned towards the sensor
    variation: F64  # (N,) the neighbours' variance share along the normal: ~0 on a surface, 1/3 for a scattered blob


def point_normals(points: F64, origin: F64, index: NDArray[np.int64]) -> PointNormals:
    """`point_normals_naive`, compiled (`weatheralign.ground.kernels.neighbour_normals_kernel`)."""
    return PointNormals(*neighbour_normals_kernel(np.ascontiguousarray(points, dtype=np.float64),
                                                  np.ascontiguousarray(index), np.asarray(origin, dtype=np.float64)))


def point_normals_naive(points: F64, origin: F64, index: NDArray[np.int64]) -> PointNormals:
    """Unit normals (N, 3) of LiDAR returns (N, 3) from their neighbours ``index`` (N, k) (`nearest_neighbours`):
    the eigenvector of the least eigenvalue of their covariance (PCA), turned towards the sensor at ``origin`` (3,);
    and their surface variation (N,), the least eigenvalue over the eigenvalues' sum (Pauly, Gross & Kobbelt 2002):
    near 0 on a road, a roof or a facade, up to 1/3 where the neighbours scatter in every direction (foliage)."""
    points = np.asarray(points, dtype=np.float64)
    around = points[index] - points[index].mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", around, around) / index.shape[1]
    values, vectors = np.linalg.eigh(covariance)
    normals = vectors[:, :, 0]
    facing = np.sum(normals * (np.asarray(origin) - points), axis=1) < 0
    normals[facing] *= -1.0
    total = values.sum(axis=1)
    variation = np.where(total > 0.0, np.clip(values[:, 0], 0.0, None) / np.where(total > 0.0, total, 1.0), 0.0)
    return PointNormals(normals, variation)


def median_over_neighbours(values: F64, index: NDArray[np.int64]) -> F64:
    """(N,) the median of ``values`` (N,) over each point's neighbours ``index`` (N, k) (`nearest_neighbours`, itself
    included): a lone odd normal among its neighbours' is outvoted (`neighbour_median_kernel`, compiled
    ``np.median(values[index], axis=1)``)."""
    return neighbour_median_kernel(np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(index))


class PixelSurfaces(NamedTuple):
    """A camera's surfaces from its dense range map."""

    points_world: F64  # (H, W, 3) world position of each pixel's surface [m]; nan for the sky
    normals_world: F64  # (H, W, 3) unit normals turned towards the camera; nan where unknown (sky, depth edges)


def pixel_normals(range_map: F64, camera: CameraGeometry, smooth_px: int = 5, edge_ratio: float = 0.05
                  ) -> PixelSurfaces:
    """World points and normals of a camera's pixels from its range map (H, W) [m] (inf: sky): the compiled
    `weatheralign.ground.kernels.pixel_normals_kernel` of `pixel_normals_naive`'s rule."""
    points, normals = pixel_normals_kernel(np.ascontiguousarray(range_map, dtype=np.float64),
                                           np.linalg.inv(camera.K), np.ascontiguousarray(camera.T_world_cam[:3, :3]),
                                           np.ascontiguousarray(camera.T_world_cam[:3, 3]), int(smooth_px),
                                           float(edge_ratio))
    return PixelSurfaces(points, normals)


def pixel_points(range_map: F64, camera: CameraGeometry) -> F64:
    """(H, W, 3) world position [m] of each pixel's surface from a camera's range map (H, W) [m]; nan for the sky
    (`pixel_normals`' points, without the normals)."""
    points, _, finite = pixel_points_kernel(np.ascontiguousarray(range_map, dtype=np.float64), np.linalg.inv(camera.K),
                                            np.ascontiguousarray(camera.T_world_cam[:3, :3]),
                                            np.ascontiguousarray(camera.T_world_cam[:3, 3]))
    points[~finite] = np.nan
    return points


def pixel_normals_naive(range_map: F64, camera: CameraGeometry, smooth_px: int = 5, edge_ratio: float = 0.05
                        ) -> PixelSurfaces:
    """World points and normals of a camera's pixels from its range map (H, W) [m] (inf: sky): the points averaged
    over ``smooth_px`` x ``smooth_px`` (a real map's noise would scatter its normals), the normal the cross product
    of the central differences along the rows and the columns. Pixels beside a depth edge (a neighbour's range
    differs by more than ``edge_ratio`` of its own) get nan: their differences span two surfaces."""
    height, width = range_map.shape
    finite = np.isfinite(range_map)
    rays = camera.rays_world(height, width)
    points = camera.T_world_cam[:3, 3] + rays * np.where(finite, range_map, 0.0)[..., None]
    weight = uniform_filter(finite.astype(np.float64), smooth_px)
    smooth = uniform_filter(points * finite[..., None], (smooth_px, smooth_px, 1)) / np.maximum(weight, 1e-9)[..., None]
    d_col = np.zeros_like(smooth)
    d_row = np.zeros_like(smooth)
    d_col[:, 1:-1] = smooth[:, 2:] - smooth[:, :-2]
    d_row[1:-1] = smooth[2:] - smooth[:-2]
    normals = np.cross(d_col, d_row)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = normals / np.maximum(length, 1e-12)
    normals *= np.where(np.sum(normals * rays, axis=-1, keepdims=True) > 0, -1.0, 1.0)
    r = np.asarray(range_map, dtype=np.float64)  # a sky neighbour (inf) is a jump
    jump = np.zeros(range_map.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        jump[:, 1:-1] |= np.abs(r[:, 2:] - r[:, :-2]) > edge_ratio * r[:, 1:-1]
        jump[1:-1] |= np.abs(r[2:] - r[:-2]) > edge_ratio * r[1:-1]
    border = np.zeros_like(jump)
    border[[0, -1], :] = border[:, [0, -1]] = True
    unknown = ~finite | jump | border | (weight < 0.999) | (length[..., 0] < 1e-12)
    normals[unknown] = np.nan
    points[~finite] = np.nan
    return PixelSurfaces(points, normals)


def nearest_return_values(points_world: F64, returns_world: F64, values: F64, max_distance_m: float = 0.3) -> F64:
    """(M,) for surface points (M, 3) the ``values`` (N,) of the nearest LiDAR return (N, 3) within
    ``max_distance_m``; nan where none is that near (and for nan points)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points_world, dtype=np.float64)
    out = np.full(len(points), np.nan)
    finite = np.all(np.isfinite(points), axis=1)
    distance, index = cKDTree(np.asarray(returns_world, dtype=np.float64)).query(
        points[finite], distance_upper_bound=max_distance_m)
    near = np.isfinite(distance)
    found = np.full(int(finite.sum()), np.nan)
    found[near] = np.asarray(values, dtype=np.float64)[index[near]]
    out[finite] = found
    return out


class MaskAgreement(NamedTuple):
    """The LiDAR's edited returns projected into a camera against the camera's edited pixels, over the pixels some
    return projects to."""

    iou: float  # |L and C| / |L or C| over those pixels
    lidar_on_camera: float  # share of the pixels the LiDAR edits that the camera edits too
    camera_on_lidar: float  # share of the pixels the camera edits that the LiDAR edits too
    pixels: int  # pixels some return projects to


def mask_agreement(points_world: F64, edited: Mask, camera: CameraGeometry, camera_mask: Mask,
                   max_range_m: float = 60.0, range_map: F64 | None = None,
                   visible_tolerance: float = 0.05) -> MaskAgreement:
    """How well a LiDAR's edits (``edited`` (N,) of its returns at ``points_world`` (N, 3)) and a camera's
    (``camera_mask`` (H, W)) agree: per pixel some return within ``max_range_m`` projects to, the LiDAR's label
    (the nearest such return's) against the camera's. With the camera's ``range_map`` (H, W) [m], only returns the
    camera sees count: within ``visible_tolerance`` (relative, at least 0.3 m) of the surface its pixel shows (a
    return behind the ego's body, or hidden from the camera by parallax, is not on that pixel's surface)."""
    height, width = camera_mask.shape
    u, v, length = camera.project(np.asarray(points_world, dtype=np.float64))
    col, row = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    seen = (length > 0) & (length < max_range_m) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    if range_map is not None:
        shown = np.full(len(length), np.inf)
        shown[seen] = np.asarray(range_map)[row[seen], col[seen]]
        seen &= np.abs(length - shown) <= np.maximum(visible_tolerance * shown, 0.3)
    index = np.nonzero(seen)[0]
    pixel = row[index] * width + col[index]
    order = np.lexsort((-index, length[index], pixel))  # by pixel, the nearest (the last of equals) first: it wins
    pixel, index = pixel[order], index[order]
    first = np.ones(len(pixel), dtype=bool)
    first[1:] = pixel[1:] != pixel[:-1]
    pixel, index = pixel[first], index[first]  # the pixels some return projects to, once each
    lidar = np.asarray(edited, dtype=bool)[index]
    cam = np.asarray(camera_mask, dtype=bool).reshape(-1)[pixel]
    union = int(np.count_nonzero(lidar | cam))
    both = int(np.count_nonzero(lidar & cam))
    return MaskAgreement(both / union if union else 1.0, both / max(int(lidar.sum()), 1),
                         both / max(int(cam.sum()), 1), len(pixel))


__all__ = ["mask_agreement", "MaskAgreement", "MAX_SURFACE_VARIATION",
           "median_over_neighbours", "PointNormals",
           "nearest_neighbours", "nearest_return_values", "pixel_normals", "pixel_normals_naive", "pixel_points",
           "PixelSurfaces", "point_normals", "point_normals_naive"]
