"""Dense camera depth from sparse LiDAR for real data (docs/physics.md 2.4; the synthetic world has exact depth).

The result is the per-pixel **ray length** [m] (distance from the camera centre, as `CameraView.load_range` gives for
the synthetic world and as Koschmieder's law needs), ``inf`` for sky. Stages (`dense_depth`):

1. **Projection** (`camera_points`): the aggregated, ego-motion-compensated scan (every point in the LiDAR frame at
   the scan timestamp) goes to the global frame with the scan's pose and into the camera with the camera's pose at
   its *own* timestamp (``CameraView.T_global_cam``); static points land exactly. Each point keeps its firing time
   relative to the exposure (``LidarScan.point_times``), so points of older sweeps are known as older.
2. **Z-buffer, ghost, parallax and glass filters** (`sparse_depth`, `drop_occluded`, `drop_see_through`): the
   nearest point per pixel (pixel centres at integer ``(u, v)``). Points fired within ``stale_s`` of the exposure
   are fresh; an older point whose depth disagrees with the fresh points around it is a moving object's ghost and
   is dropped (older sweeps only fill where the fresh sweep has no points). Points that have nearer points both
   above and below (or left and right) lie behind a foreground surface that the LiDAR, mounted elsewhere, saw past:
   the camera cannot see them. Points framed on all four sides, within many ring gaps, by one nearer surface were
   seen through it (a car's windows pass the pulse; the camera sees the window): dropped, so the window is filled
   across from the car body around it. Far points just above the top ring of a nearer upright surface, within the
   parallax of a LiDAR mounted above the camera, were seen over it (`drop_parallax`): dropped too.
3. **Planar interpolation** (`triangulate`): a Delaunay triangulation of the projected points in the image;
   inverse depth is linear in the image over a planar patch, so each triangle whose corners lie on one surface
   (similar depths, or a near-horizontal patch such as the road) is filled exactly for planes. Triangles across
   depth edges or spanning more than a few LiDAR ring gaps are dropped.
4. **Morphological fill** (`morphological_fill`, IP-Basic, Ku et al. 2018, with OpenCV): inverted depth so that
   dilation keeps the nearest surface, multiscale diamond dilation by depth bin, hole closing, masked hole fill,
   median and bilateral blur. It fills what the triangles left (depth edges, thin objects). Kernel sizes follow the
   measured point spacing in the image, so one setting serves a 32-beam LiDAR at 1600 x 900 and a 64-beam at KITTI
   resolution.
5. **Image-guided refinement** (`refine_edges`): every pixel not covered by a surface triangle picks, among the
   confident depths of its neighbourhood, the near or the far surface by a joint-bilateral vote (colour similarity
   to the image, spatial distance) and takes that surface's weighted inverse depth: depth edges snap to image edges
   instead of the dilation's nearest-wins halo.
6. **Sky and holes**: nothing above the LiDAR's top elevation ever returns, so a pixel whose viewing ray (taken to
   the LiDAR frame, `above_fov_mask`) points above ``lidar_top_elevation_deg`` and has no LiDAR support nearby is
   sky (with an image: no point within reach on its own side of an image boundary, `lidar_support`); with an image,
   only where the image agrees (`image_sky`: bright, bluish or neutral, smooth, above the horizon, connected to the
   top border, not continuing a LiDAR-hit surface; or of that sky's colour at its height, as the sky between the
   branches of a crown) - and then also below the top
   elevation where the LiDAR had no return (sky at the end of a street). Unsupported pixels above the field of view
   that the image shows as structure (facades above the top ring) keep the camera z of the highest known pixel of
   their column (a vertical surface continued upwards), with low confidence: "sky is far only where it really is
   sky". Where the image separates a region there from the surface below it (a tree crown or a lamp head above its
   trunk or pole), the region takes the near side of the depths it rests on (`_overhangs`), not the facade behind.
   Holes below it without returns are filled across when one surface surrounds them (dark paint, glass), else from
   the farthest surface around (beyond range, or in the LiDAR's shadow behind a foreground object).
7. **One sky for all cameras** (`consistent_sky`, called by `weatheralign.simulate.plan.sample_range_maps` on the
   six completed maps): a direction is sky only where every camera that sees it agrees; otherwise the sky pixel
   takes the ray length of the camera that sees a surface there (no seam of white sky beside fogged structure).

``DenseDepth.confidence`` is 1 for planar interpolation between LiDAR points and for sky decided by both the LiDAR
and the image, 0.5 for the morphological fill / refined edges, 0.25 for upward continuation and nearest fill; it is
0.5 for sky without an image. ``valid`` is ``confidence >= 0.5``.

Accuracy and cost (`benchmarks/bench_depth.py`: 12 samples x 6 cameras of the synthetic world, 1600 x 900, against
the exact ray length, the ego's body from its geometry, after `consistent_sky`): AbsRel 0.029 with the keyframe alone,
0.028 with 3 HDL-32E sweeps (0.18 / 0.17 within 10 px of depth edges); 95 % of the true sky is inf, 0.33 % of the
structure is taken for sky. The same benchmark times the completion (CPU and wall seconds per camera).

`benchmarks/bench_depth.py` measures the whole image against the world's exact range maps (depth near edges, sky,
the dense-fog halo, seams between neighbouring cameras; `reports/benchmarks/depth.json`).

Known limits: buildings beyond the LiDAR's range (100 m) get the farthest depth around, not theirs; a pale, smooth
facade entirely above the top ring, meeting the sky without a visible edge, can be taken for sky; a window whose
frame the LiDAR misses on one side (a side window at the image border) keeps the depth behind it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.ndimage import median_filter, minimum_filter1d
from scipy.spatial import Delaunay, QhullError

from weatheralign.data.frame import CameraView, LidarScan
from weatheralign.geometry import invert

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
BoolA = NDArray[np.bool_]

CONF_PLANAR = 1.0
CONF_FILL = 0.5
CONF_EXTENDED = 0.25


@dataclass(frozen=True)
class DepthParams:
    """Settings of `dense_depth` (defaults tuned on the synthetic world against its exact range maps).

    Attributes:
        min_depth_m: points closer than this camera z [m] are ignored (returns from the ego vehicle and the sensor
            mounts, e.g. 79 points at z ~0.5 m on the top rows of the STF sample).
        same_surface_ratio: a triangle is one surface if its corner depths differ by at most this factor.
        ground_tilt_deg: ... or if its 3-D normal is within this angle of the ego's up axis (road, pavement)
        ground_height_range_m: ... and its corners differ in height by at most this [m] ...
        ground_depth_ratio: ... and in camera z by at most this factor (a level triangle from a car's top to a
            surface far behind it, seen over the car, is no road).
        max_edge_gaps: longest triangle edge, in measured vertical point gaps.
        occlusion_ratio: a point is hidden if nearer points (depth below ``z / ratio``) flank it on both sides.
        see_through_reach_gaps: a point is seen through a surface (a car window) if within this many vertical point
            gaps it has nearer points above, below, left and right (`drop_see_through`) ...
        see_through_ratio: ... each nearer than ``z / ratio`` ...
        see_through_rim_spread: ... with the points above and below within this factor of each other, and those
            left and right too (one surface around it: a road below a facade, or branches above it, do not count).
        support_gaps: a pixel within this many point gaps of a LiDAR point has LiDAR support (never sky); with an
            image, only along a path inside the point's own image segment (`lidar_support`).
        sky_margin_deg: a ray is above the LiDAR's field of view if its elevation exceeds the top elevation by this.
        stale_s: points fired more than this before/after the exposure [s] are stale: dropped where fresh points
            around disagree with their depth (moving objects of older sweeps), and second to fresh ones per pixel.
        refine_radius_gaps: half-window of the image-guided refinement, in point gaps.
        refine_sigma_colour: colour scale of the refinement's joint-bilateral weight (sRGB in [0, 1]).
        edge_ratio: neighbourhood depth spread above which the refinement chooses between near and far surfaces.
        hole_spread: a hole without returns whose rim depths span at most this factor is one surface (filled
            across); other holes are filled from the farthest surface around.
        overhang_scale: resolution divisor of the image segmentation above the LiDAR's field of view (`_overhangs`).
        overhang_chroma, overhang_brightness: blurred chromaticity / brightness gradients [1/px, sRGB] that
            separate two segments there (`_image_edges`).
        overhang_reach_gaps: how far below a segment [point gaps] the surface it rests on is looked for (at least 8
            pixels of the segmentation's resolution: across the edge band).
        overhang_quantile: quantile of the depths below a separate segment it takes (the near side).
        overhang_colour_tol: a pixel of the edge band around a separate segment within this colour distance of the
            segment's mean colour (largest sRGB channel) belongs to it.
    """

    min_depth_m: float = 1.0
    same_surface_ratio: float = 1.15
    ground_tilt_deg: float = 12.0
    ground_height_range_m: float = 0.5
    ground_depth_ratio: float = 2.0
    max_edge_gaps: float = 2.8
    occlusion_ratio: float = 1.1
    see_through_reach_gaps: float = 25.0
    see_through_ratio: float = 1.5
    see_through_rim_spread: float = 1.5
    support_gaps: float = 1.2
    sky_margin_deg: float = 0.0
    stale_s: float = 0.03
    refine_radius_gaps: float = 0.6
    refine_sigma_colour: float = 0.08
    edge_ratio: float = 1.1
    hole_spread: float = 1.3
    overhang_scale: int = 4
    overhang_chroma: float = 0.02
    overhang_brightness: float = 0.1
    overhang_reach_gaps: float = 1.5
    overhang_quantile: float = 0.05
    overhang_colour_tol: float = 0.1


@dataclass(frozen=True)
class DenseDepth:
    """Dense depth of one camera image.

    Attributes:
        range: (H, W) float32 ray length from the camera centre [m]; ``inf`` = sky.
        confidence: (H, W) float32 in [0, 1] (see the module docstring).
        valid: (H, W) bool, ``confidence >= 0.5`` (depth backed by nearby LiDAR points, or decided sky).
        sky: (H, W) bool, pixels declared sky (``range == inf``).
        above_fov: (H, W) bool, pixels whose ray points above the LiDAR's top elevation.
        num_points: LiDAR points used (after z-buffer and parallax filter).
    """

    range: F32
    confidence: F32
    valid: BoolA
    sky: BoolA
    above_fov: BoolA
    num_points: int


@dataclass(frozen=True)
class CameraPoints:
    """LiDAR points in a camera frame at the camera's exposure time.

    Attributes:
        xyz: (N, 3) float64 camera-frame coordinates [m] (OpenCV axes).
        dt: (N,) float64 firing time minus exposure time [s] (0 where unknown).
        R_lidar_cam: (3, 3) rotation camera -> LiDAR frame (for the field-of-view test).
        up_cam: (3,) the ego's up axis in camera coordinates.
        lidar_origin_cam: (3,) the LiDAR's origin in camera coordinates [m] (for `drop_parallax`); None: unknown,
            no parallax filter.
    """

    xyz: F64
    dt: F64
    R_lidar_cam: F64
    up_cam: F64
    lidar_origin_cam: F64 | None = None


# ------------------------------------------------------------------------------------------------ geometry


def camera_points(scan: LidarScan, camera: CameraView) -> CameraPoints:
    """Project a (multi-sweep, ego-motion-compensated) scan into ``camera`` at the camera's own timestamp.

    A point ``p`` of the scan lies at ``T_global_lidar(t_scan) p`` in the world (the scan's compensation); the
    camera sees it at ``inv(T_global_cam(t_cam))`` of that. Firing times come from ``scan.point_times()``.
    """
    T_cam_lidar = invert(camera.T_global_cam) @ scan.T_global_lidar
    return _points_in_camera(scan.points[:, :3].astype(np.float64), scan.point_times() - camera.timestamp,
                             T_cam_lidar, camera)


def _points_in_camera(xyz_lidar: F64, dt: F64, T_cam_lidar: F64, camera: CameraView) -> CameraPoints:
    """`CameraPoints` of LiDAR-frame points ``xyz_lidar`` (N, 3) [m] with firing-time offsets ``dt`` (N,) [s], through
    the 4x4 ``T_cam_lidar``."""
    return CameraPoints(xyz=xyz_lidar @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3], dt=dt,
                        R_lidar_cam=T_cam_lidar[:3, :3].T.copy(),
                        up_cam=camera.T_ego_cam[:3, :3].T @ np.array([0.0, 0.0, 1.0]),
                        lidar_origin_cam=T_cam_lidar[:3, 3].copy())


def estimate_top_elevation_deg(scan: LidarScan, min_range_m: float = 8.0) -> float:
    """The scan's top beam elevation [deg] in its sensor frame, from its reference sweep's points beyond
    ``min_range_m`` (nearer points spread in elevation: the lasers sit a few cm apart): the highest per-ring median
    elevation where rings are stored (synthetic HDL-32E: 10.67; STF HDL-64: 2.72), else the 99.5 % quantile.

    Raises:
        ValueError: no point beyond ``min_range_m``.
    """
    p = scan.points
    if scan.sweep_index is not None:
        p = p[scan.sweep_index == 0]
    xyz = p[:, :3].astype(np.float64)
    horiz = np.hypot(xyz[:, 0], xyz[:, 1])
    far = np.hypot(horiz, xyz[:, 2]) > min_range_m
    if not far.any():
        raise ValueError(f"estimate_top_elevation_deg: no points beyond {min_range_m} m")
    elev = np.degrees(np.arctan2(xyz[far, 2], horiz[far]))
    rings = p[far, 4].astype(np.int64)
    counts = np.bincount(rings)
    top = None
    for ring in np.flatnonzero(counts >= 20):
        med = float(np.median(elev[rings == ring]))
        top = med if top is None else max(top, med)
    return top if top is not None else float(np.quantile(elev, 0.995))


def pixel_ray_norms(K: F64, width: int, height: int) -> F32:
    """(H, W) float32 ``|K^-1 (u, v, 1)|``: ray length per unit camera z at pixel centres (integer u, v)."""
    x = (np.arange(width) - K[0, 2]) / K[0, 0]
    y = (np.arange(height) - K[1, 2]) / K[1, 1]
    x = x - K[0, 1] * y[:, None] / K[0, 0] if K[0, 1] != 0 else np.broadcast_to(x, (height, width))
    return np.sqrt(x * x + (y * y)[:, None] + 1.0).astype(np.float32)


def above_fov_mask(K: F64, width: int, height: int, R_lidar_cam: F64, top_elevation_deg: float) -> BoolA:
    """(H, W) bool: the pixel's viewing direction, rotated into the LiDAR frame, is above ``top_elevation_deg``."""
    M = (R_lidar_cam @ np.linalg.inv(K)).astype(np.float32)  # pixel (u, v, 1) -> LiDAR-frame direction
    u = np.arange(width, dtype=np.float32)
    v = np.arange(height, dtype=np.float32)[:, None]
    d = [M[i, 0] * u + M[i, 1] * v + M[i, 2] for i in range(3)]
    tan_top = np.float32(math.tan(math.radians(top_elevation_deg)))
    return d[2] > tan_top * np.sqrt(d[0] * d[0] + d[1] * d[1])


def above_horizon_mask(K: F64, width: int, height: int, up_cam: F64, margin_deg: float = 1.0) -> BoolA:
    """(H, W) bool: the pixel's viewing direction is above the ego's horizontal plane minus ``margin_deg``."""
    M = np.linalg.inv(K).astype(np.float32)
    u = np.arange(width, dtype=np.float32)
    v = np.arange(height, dtype=np.float32)[:, None]
    d = [M[i, 0] * u + M[i, 1] * v + M[i, 2] for i in range(3)]
    up = np.asarray(up_cam, dtype=np.float32)
    along = d[0] * up[0] + d[1] * up[1] + d[2] * up[2]
    norm = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return along > np.float32(math.sin(math.radians(-margin_deg))) * norm


# ------------------------------------------------------------------------------------------------ sparse depth


@dataclass(frozen=True)
class SparseDepth:
    """The z-buffered projection. ``z``: (H, W) float32 camera z [m], 0 where empty; ``index``: (M,) indices of the
    kept points; ``uv``: (M, 2) their sub-pixel image positions; ``pix``: (M, 2) int (v, u) pixels."""

    z: F32
    index: NDArray[np.int64]
    uv: F64
    pix: NDArray[np.int64]


def _zbuffer(lin: NDArray[np.int64], z: F64, stale: NDArray[np.int8]) -> NDArray[np.int64]:
    """Positions (into ``lin``) of the winner of each pixel ``lin``: fresh before stale, then nearest."""
    order = np.lexsort((z, stale, lin))
    lin_s = lin[order]
    first = np.ones(len(order), bool)
    first[1:] = lin_s[1:] != lin_s[:-1]
    return order[first]


def sparse_depth(points: CameraPoints, K: F64, width: int, height: int, params: DepthParams) -> SparseDepth:
    """Nearest point per pixel, with older sweeps checked against the fresh one.

    Points fired within ``stale_s`` of the exposure are *fresh*; older (stale) points of static surfaces land
    exactly, but those of moving objects are ghosts at old positions. A stale point is dropped where fresh points
    surround it (a window of about one ring gap) and its depth lies outside their depth range (by more than
    ``occlusion_ratio``); where no fresh point is near, stale points fill the gaps (the purpose of aggregation).
    In a pixel shared by a fresh and a stale point, the fresh one wins.
    """
    xyz = points.xyz
    z = xyz[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * xyz[:, 0] / z + K[0, 1] * xyz[:, 1] / z + K[0, 2]
        v = K[1, 1] * xyz[:, 1] / z + K[1, 2]
    ui, vi = np.rint(u), np.rint(v)
    ok = (z > params.min_depth_m) & (ui >= 0) & (ui < width) & (vi >= 0) & (vi < height)
    idx = np.flatnonzero(ok)
    pv_all, pu_all = vi[idx].astype(np.int64), ui[idx].astype(np.int64)
    lin = pv_all * width + pu_all
    stale = (np.abs(points.dt[idx]) > params.stale_s).astype(np.int8)
    zi = z[idx]
    fresh = stale == 0
    if stale.any() and fresh.sum() >= 3:
        win = _zbuffer(lin[fresh], zi[fresh], stale[fresh])
        zf = np.zeros((height, width), np.float32)
        zf[pv_all[fresh][win], pu_all[fresh][win]] = zi[fresh][win]
        gap_v, gap_h = point_gaps(zf > 0)
        k = np.ones((int(round(1.5 * gap_v)) | 1, int(round(2 * gap_h)) | 1), np.uint8)
        fmax = cv2.dilate(zf, k)
        fmin = cv2.erode(np.where(zf > 0, zf, np.float32(1e30)).astype(np.float32), k)
        r = params.occlusion_ratio
        s_v, s_u = pv_all[~fresh], pu_all[~fresh]
        zs = zi[~fresh]
        ghost = (fmax[s_v, s_u] > 0) & ((zs < fmin[s_v, s_u] / r) | (zs > fmax[s_v, s_u] * r))
        keep = np.ones(len(idx), bool)
        keep[np.flatnonzero(~fresh)[ghost]] = False
        idx, pv_all, pu_all, lin, stale, zi = idx[keep], pv_all[keep], pu_all[keep], lin[keep], stale[keep], zi[keep]
    win = _zbuffer(lin, zi, stale)
    sel = idx[win]
    out = np.zeros((height, width), np.float32)
    pv, pu = pv_all[win], pu_all[win]
    out[pv, pu] = z[sel]
    return SparseDepth(z=out, index=sel, uv=np.column_stack([u[sel], v[sel]]), pix=np.column_stack([pv, pu]))


def point_gaps(mask: BoolA) -> tuple[float, float]:
    """(vertical, horizontal) typical gap [px] between neighbouring LiDAR points in the image.

    Horizontal: the median distance between consecutive occupied pixels of a row (points along a ring).
    Vertical: rings are first joined into curves by a horizontal dilation over that gap; then the 75th percentile of
    the distances between consecutive occupied pixels of a column (the ring spacing; denser on the ground where
    several sweeps interleave). Both at least 2.
    """

    def gaps(m: BoolA, q: float) -> float:
        r, c = np.nonzero(m)  # row-major: consecutive entries of one row are neighbours along the row
        if len(r) < 2:
            return 2.0
        d = np.diff(c)[(r[1:] == r[:-1])]
        d = d[d > 1]
        return float(max(2.0, np.percentile(d, q))) if len(d) else 2.0

    gap_h = gaps(mask, 50.0)
    k = int(round(gap_h)) | 1
    joined = cv2.dilate(mask.astype(np.uint8), np.ones((1, k), np.uint8)) > 0
    return gaps(joined.T, 75.0), gap_h


def _one_sided_minima(zz: F32, reach: int, across: int, axis: int) -> tuple[F32, F32]:
    """Minima of ``zz`` (H, W) over windows ``across`` pixels wide (centred) and ``reach`` pixels long along
    ``axis`` (0: rows, 1: columns), ending at each pixel (up / left) and starting there (down / right); outside
    the image counts as inf. Running minima (`scipy.ndimage.minimum_filter1d`): the cost does not grow with reach."""
    band = minimum_filter1d(zz, across, axis=1 - axis, mode="constant", cval=np.inf)
    before = minimum_filter1d(band, reach, axis=axis, origin=(reach - 1) // 2, mode="constant", cval=np.inf)
    after = minimum_filter1d(band, reach, axis=axis, origin=-(reach // 2), mode="constant", cval=np.inf)
    return before, after


def drop_occluded(z: F32, gap_v: float, gap_h: float, ratio: float) -> F32:
    """Remove points that nearer points flank above and below (or left and right): seen by the LiDAR past a
    foreground surface that hides them from the camera. ``z`` (H, W) float32, 0 = empty; returns a filtered copy."""
    zz = np.where(z > 0, z, np.inf).astype(np.float32)
    up, down = _one_sided_minima(zz, int(round(1.5 * gap_v)) + 1, int(round(gap_h)) | 1, axis=0)
    left, right = _one_sided_minima(zz, int(round(1.5 * gap_h)) + 1, int(round(0.5 * gap_v)) | 1, axis=1)
    lim = zz / np.float32(ratio)
    hidden = (z > 0) & (((up < lim) & (down < lim)) | ((left < lim) & (right < lim)))
    out = z.copy()
    out[hidden] = 0.0
    return out


@njit(cache=True, nogil=True)
def _first_point_below(z: NDArray, v: int, u: int, z_max: float, half_width: int, max_rows: int
                       ) -> tuple[int, float]:
    """(row, z) of the first row below (``v``, ``u``), within ``max_rows`` rows and ``half_width`` columns either
    side, holding a point of ``z`` (H, W) (0 = empty) nearer than ``z_max`` (its nearest such point); (-1, 0) if
    none."""
    H, W = z.shape
    for r in range(v + 1, min(H, v + 1 + max_rows)):
        best = 0.0
        for c in range(max(0, u - half_width), min(W, u + half_width + 1)):
            zq = z[r, c]
            if 0.0 < zq < z_max and (best == 0.0 or zq < best):
                best = zq
        if best > 0.0:
            return r, best
    return -1, 0.0


@njit(cache=True, nogil=True)
def _parallax_hidden(z: NDArray, shift_v: float, fy: float, cy: float, ratio: float, half_width: int,
                     min_depth: float, ring_rows: int, out: NDArray) -> None:
    """Mark in ``out`` (H, W) bool the points of ``z`` (H, W) float32 (0 = empty) whose first nearer point below
    (nearer than ``z / ratio``) lies within their parallax distance ``shift_v (1 / z_q - 1 / z_p)`` [px] and on an
    upright surface: the next point below it (within ``ring_rows``) rises at least as much as it comes nearer."""
    H, W = z.shape
    for v in range(H):
        for u in range(W):
            zp = z[v, u]
            if zp <= 0.0:
                continue
            reach = int(shift_v * (1.0 / min_depth - 1.0 / zp)) + 1
            rq, zq = _first_point_below(z, v, u, zp / ratio, half_width, reach)
            if rq < 0 or rq - v > shift_v * (1.0 / zq - 1.0 / zp):
                continue
            r2, z2 = _first_point_below(z, rq, u, np.inf, half_width, ring_rows)
            if r2 >= 0 and abs((r2 - cy) * z2 - (rq - cy) * zq) / fy >= abs(zq - z2):
                out[v, u] = True


def drop_parallax(z: F32, origin_cam: F64, K: F64, gap_v: float, gap_h: float, ratio: float,
                  min_depth_m: float) -> F32:
    """Remove far points just above the top edge of a nearer upright surface, where the LiDAR, mounted above the
    camera, looks over the surface and the camera cannot. ``z`` (H, W) float32 camera z, 0 = empty; ``origin_cam``
    (3,) the LiDAR's origin in camera coordinates [m]; returns a filtered copy.

    A LiDAR ray passing over the top of a surface at depth ``z_q`` reaches the background at ``z_p``; in the camera
    that point lands ``f h (1 / z_q - 1 / z_p)`` pixels below the ray's image at ``z_q`` (``h``: the LiDAR's height
    above the camera; nuScenes CAM_FRONT: 0.33 m, so the road 40 m ahead seen over a car roof at 14 m lands 12 px
    below the roof's edge, on the car's rear window). The surface's top lies between that ray and the first ring
    that hits the surface, so where that ring is nearer in the image than the parallax distance the point is more
    likely hidden than seen: dropped, and the image-guided fill decides where the edge lies. Only an upright surface
    (the point below the ring's point rises at least as much as it comes nearer) can hide it: the ground before a
    wall keeps the wall's foot. Only the vertical offset is modelled: older sweeps were fired from elsewhere along
    the road, which changes the horizontal parallax. `drop_occluded` needs nearer points on both sides; this needs
    one, at a known distance."""
    shift_v = -float(K[1, 1]) * float(np.asarray(origin_cam, dtype=np.float64)[1])
    out = z.copy()
    if shift_v < 1e-3:
        return out
    hidden = np.zeros(z.shape, np.bool_)
    _parallax_hidden(np.ascontiguousarray(z, dtype=np.float32), shift_v, float(K[1, 1]), float(K[1, 2]),
                     float(ratio), max(0, int(round(gap_h / 2))), float(min_depth_m),
                     max(2, int(round(2 * gap_v))), hidden)
    out[hidden] = 0.0
    return out


def drop_see_through(z: F32, gap_v: float, gap_h: float, reach_gaps: float, ratio: float, spread: float) -> F32:
    """Remove points that the LiDAR saw through a surface the camera sees (glass: a car's windows pass the pulse
    to whatever lies behind, while the camera sees the window): points with a nearer point (depth below ``z /
    ratio``) above, below, left and right within ``reach_gaps`` vertical point gaps, where the nearest depths above
    and below lie within a factor ``spread`` of each other, and those left and right too (one surface frames the
    point). `drop_occluded` only looks one or two gaps away; a window spans many. ``z`` (H, W) float32, 0 = empty;
    returns a filtered copy. The holes left are filled across from the frame (`complete_depth`)."""
    zz = np.where(z > 0, z, np.inf).astype(np.float32)
    reach = int(round(reach_gaps * gap_v)) + 1
    up, down = _one_sided_minima(zz, reach, int(round(gap_h)) | 1, axis=0)
    left, right = _one_sided_minima(zz, reach, int(round(0.5 * gap_v)) | 1, axis=1)
    frame_far = np.maximum(np.maximum(up, down), np.maximum(left, right))
    with np.errstate(invalid="ignore"):  # inf / inf where a side has no point: not framed
        one_surface = (np.maximum(up, down) <= spread * np.minimum(up, down)) & (
            np.maximum(left, right) <= spread * np.minimum(left, right))
    hidden = (z > 0) & (frame_far < zz / np.float32(ratio)) & one_surface
    out = z.copy()
    out[hidden] = 0.0
    return out


# ------------------------------------------------------------------------------------------------ triangles


@njit(cache=True, nogil=True)
def _raster_inverse_depth(tri: NDArray, uv: NDArray, inv_z: NDArray, keep: NDArray, out: NDArray) -> None:
    """Rasterise kept triangles (T, 3) of image points ``uv`` (N, 2) into ``out`` (H, W), linearly interpolating
    ``inv_z`` (N,) at integer pixel centres (inclusive edges; nearest surface where two triangles overlap)."""
    H, W = out.shape
    for t in range(tri.shape[0]):
        if not keep[t]:
            continue
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        x0, y0, x1, y1, x2, y2 = uv[a, 0], uv[a, 1], uv[b, 0], uv[b, 1], uv[c, 0], uv[c, 1]
        den = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if abs(den) < 1e-9:
            continue
        umin = max(0, int(math.ceil(min(x0, x1, x2))))
        umax = min(W - 1, int(math.floor(max(x0, x1, x2))))
        vmin = max(0, int(math.ceil(min(y0, y1, y2))))
        vmax = min(H - 1, int(math.floor(max(y0, y1, y2))))
        for v in range(vmin, vmax + 1):
            for u in range(umin, umax + 1):
                l0 = ((y1 - y2) * (u - x2) + (x2 - x1) * (v - y2)) / den
                l1 = ((y2 - y0) * (u - x2) + (x0 - x2) * (v - y2)) / den
                l2 = 1.0 - l0 - l1
                if l0 >= -1e-7 and l1 >= -1e-7 and l2 >= -1e-7:
                    val = l0 * inv_z[a] + l1 * inv_z[b] + l2 * inv_z[c]
                    if val > out[v, u]:
                        out[v, u] = val


def triangulate(uv: F64, xyz: F64, up_cam: F64, height: int, width: int, max_edge_px: float,
                params: DepthParams) -> F32:
    """(H, W) float32 inverse camera z [1/m] (0 = not covered) from planar triangles of the projected points.

    Args:
        uv: (M, 2) sub-pixel image positions; xyz: (M, 3) their camera-frame points [m]; up_cam: (3,) ego up axis.
        max_edge_px: longest allowed triangle edge [px].
    """
    out = np.zeros((height, width), np.float32)
    if len(uv) < 3:
        return out
    try:
        tri = Delaunay(uv).simplices.astype(np.int64)
    except QhullError:
        return out
    z = xyz[:, 2]
    zt = z[tri]
    same = zt.max(axis=1) <= params.same_surface_ratio * zt.min(axis=1)
    e = uv[tri[:, [1, 2, 0]]] - uv[tri]
    longest = np.sqrt((e * e).sum(axis=2)).max(axis=1)
    P = xyz[tri]
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    n_norm = np.linalg.norm(n, axis=1)
    h = P @ up_cam
    flat = (np.abs(n @ up_cam) >= math.cos(math.radians(params.ground_tilt_deg)) * np.maximum(n_norm, 1e-12)) & (
        h.max(axis=1) - h.min(axis=1) <= params.ground_height_range_m) & (
        zt.max(axis=1) <= params.ground_depth_ratio * zt.min(axis=1))
    keep = (longest <= max_edge_px) & (same | flat)
    _raster_inverse_depth(tri, uv, (1.0 / z).astype(np.float64), keep, out)
    return out


# ------------------------------------------------------------------------------------------------ IP-Basic fill


def _diamond(width: int, height: int) -> NDArray[np.uint8]:
    """A (height, width) diamond (rhombus) kernel, odd sizes."""
    w, h = max(1, width | 1), max(1, height | 1)
    y, x = np.mgrid[0:h, 0:w]
    return ((np.abs(x - w // 2) / max(w // 2, 1) + np.abs(y - h // 2) / max(h // 2, 1)) <= 1.0).astype(np.uint8)


def morphological_fill(z: F32, gap_v: float, gap_h: float) -> F32:
    """IP-Basic-style completion of a sparse z image (H, W) float32 (0 = empty) -> (H, W) float32 z [m], 0 where
    still empty. Kernels are scaled to the point gaps ``gap_v``, ``gap_h`` [px] (KITTI's IP-Basic: ~5 px gaps).

    Inverted depth (``max - z``) makes dilation prefer the nearest surface; near points (< 15 m) get the largest
    diamond, far ones (> 30 m) the smallest; then hole closing, masked hole fill below the top of each column,
    median blur (outliers) and bilateral blur (smooths while keeping edges), and back to depth.
    """
    valid = z > 0
    if not valid.any():
        return np.zeros_like(z)
    # the farthest point's inverted value (5 m) stays many bilateral colour scales (0.5) above the empty pixels' 0,
    # which would otherwise pull the far rim of a blob towards the empty value (farther than any point)
    z_max = float(z[valid].max()) + 5.0
    inv = np.where(valid, np.float32(z_max) - z, 0.0).astype(np.float32)
    kv, kh = 1.2 * gap_v, 1.2 * gap_h
    out = inv.copy()
    for lo, hi, scale in ((30.0, np.inf, 0.6), (15.0, 30.0, 0.8), (0.0, 15.0, 1.0)):
        part = np.where(valid & (z > lo) & (z <= hi), inv, 0.0).astype(np.float32)
        dil = cv2.dilate(part, _diamond(int(round(kh * scale)) + 2, int(round(kv * scale)) + 2))
        out[dil > 0.1] = dil[dil > 0.1]
    out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    med = cv2.medianBlur(out, 5)
    filled = out > 0.1
    out[filled] = med[filled]
    top = np.cumsum(out > 0.1, axis=0) > 0  # at or below the highest filled pixel of each column
    k = np.ones((5, 5), np.uint8)
    for _ in range(max(3, int(round(gap_v / 4)))):
        empty = (out < 0.1) & top
        if not empty.any():
            break
        dil = cv2.dilate(out, k)
        out[empty] = dil[empty]
    filled = out > 0.1
    med = cv2.medianBlur(out, 5)
    smooth = filled & (med > 0.1)  # a pixel whose window is mostly empty keeps its value (the median would empty
    out[smooth] = med[smooth]      # it, and an empty pixel marked filled came back as the farthest depth, z_max)
    bil = cv2.bilateralFilter(out, 5, 0.5, 2.0)
    out[filled] = bil[filled]
    return np.where(filled, np.float32(z_max) - out, 0.0).astype(np.float32)


# ------------------------------------------------------------------------------------------------ refinement


@njit(cache=True, nogil=True)
def _refine_kernel(inv_fill: NDArray, conf_inv: NDArray, todo: NDArray, image: NDArray, radius: int, step: int,
                   sigma_c: float, sigma_s: float, out: NDArray) -> None:
    """Joint-bilateral near/far vote (see `refine_edges`) at pixels with ``todo`` > 0, which holds the inverse depth
    splitting near from far there; ``out`` comes pre-filled with ``inv_fill`` and is changed where the vote flips.
    Single-threaded and GIL-free: Prefect's thread pool runs several images at once (numba's parallel workqueue
    layer is not safe for concurrent callers)."""
    H, W = inv_fill.shape
    ic = 1.0 / (2.0 * sigma_c * sigma_c)
    isq = 1.0 / (2.0 * sigma_s * sigma_s)
    for v in range(H):
        for u in range(W):
            mid = todo[v, u]
            if mid <= 0.0:
                continue
            v0, v1 = max(0, v - radius), min(H - 1, v + radius)
            u0, u1 = max(0, u - radius), min(W - 1, u + radius)
            wn, wf, sn, sf = 0.0, 0.0, 0.0, 0.0
            for q in range(v0, v1 + 1, step):
                for r in range(u0, u1 + 1, step):
                    c = conf_inv[q, r]
                    if c <= 0.0:
                        continue
                    d0 = image[v, u, 0] - image[q, r, 0]
                    d1 = image[v, u, 1] - image[q, r, 1]
                    d2 = image[v, u, 2] - image[q, r, 2]
                    w = math.exp(-(d0 * d0 + d1 * d1 + d2 * d2) * ic - ((q - v) ** 2 + (r - u) ** 2) * isq)
                    if c >= mid:
                        wn += w
                        sn += w * c
                    else:
                        wf += w
                        sf += w * c
            if wn + wf <= 1e-12:
                continue
            fill_near = inv_fill[v, u] >= mid
            if wn >= wf and not fill_near:
                out[v, u] = sn / wn
            elif wf > wn and fill_near:
                out[v, u] = sf / wf


def refine_edges(inv_fill: F32, conf_inv: F32, todo: BoolA, image: NDArray, radius: int,
                 params: DepthParams) -> F32:
    """Image-guided choice of the surface at uncertain pixels near depth edges (joint-bilateral near/far vote).

    For a ``todo`` pixel whose window holds confident inverse depths spreading by more than ``params.edge_ratio``
    (a depth edge), the confident samples split at the geometric mean of the extremes into a near and a far
    surface; each sample votes with ``exp(-|c_p - c_q|^2 / 2 sigma_c^2 - |p - q|^2 / 2 radius^2)``. If the winner is
    not the surface the fill chose, the pixel takes the winner's weighted mean inverse depth.

    Args:
        inv_fill: (H, W) inverse z [1/m] of the fill (0 = none); conf_inv: (H, W) inverse z of confident pixels
            (LiDAR points and planar triangles; 0 = none); todo: (H, W) pixels to refine; image: (H, W, 3) float32
            sRGB in [0, 1]; radius: half-window [px] (sampled on an ~11 x 11 grid).

    Returns:
        (H, W) float32 refined inverse z.
    """
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    near = cv2.dilate(conf_inv, k)
    far = cv2.erode(np.where(conf_inv > 0, conf_inv, np.float32(1e30)).astype(np.float32), k)
    edge = todo & (near > np.float32(params.edge_ratio) * far) & (inv_fill > 0)
    mid = np.where(edge, np.sqrt(near * np.where(edge, far, 0.0)), 0.0).astype(np.float32)
    out = inv_fill.copy()
    step = max(1, int(round((2 * radius + 1) / 11)))  # ~11 x 11 samples per window
    _refine_kernel(inv_fill, conf_inv, mid, image, int(radius), step, float(params.refine_sigma_colour),
                   float(max(radius, 1)), out)
    return out


# ------------------------------------------------------------------------------------------------ sky


def image_sky(image: NDArray, lidar_pixels: BoolA | None = None, allowed: BoolA | None = None,
              point_gap_px: float = 8.0, scale: int = 4, max_gradient: float = 0.04, min_brightness: float = 0.75,
              max_contact: float = 0.3, min_patch_px: int = 6, patch_tol: float = 0.05) -> BoolA:
    """(H, W) bool: pixels that look like sky: smooth (blurred largest per-channel gradient below ``max_gradient``
    per px at 1/``scale``), bright (max channel >= ``min_brightness`` x the 99th percentile of the upper third),
    bluish or neutral (blue >= red - 0.03) and connected (4-neighbourhood) to the image's top border through such
    pixels.

    ``allowed`` (H, W) restricts the sky to where it can be (above the horizon: far pale ground fades into the sky
    through the haze at the horizon and would otherwise join it). The sky returns nothing to a LiDAR: the smooth
    region is cut along the LiDAR points (``lidar_pixels`` (H, W); each point extended sideways by its horizontal
    spacing ``point_gap_px`` so a ring becomes a line), and a region that meets those cuts over more than
    ``max_contact`` of its columns continues a LiDAR-hit surface (a pale facade above the top ring): not sky.
    Sky seen through a gap (between the branches of a crown, under a bridge) is neither smooth nor connected to the
    top border: bright pixels within ``patch_tol`` of the connected sky's colour at their height (`_sky_coloured`),
    in regions of ``min_patch_px`` or more (at 1/``scale``) framed by texture (`_framed_by_texture`: foliage, not a
    smooth facade with a pale patch) that do not continue a LiDAR-hit surface, are sky too. A window reflects the
    sky far dimmer than the sky itself.
    Finally the skyline is sharpened at full resolution by colour (`_grow_sky`).
    """
    f = _as_float_rgb(image)
    h, w = f.shape[:2]
    s = max(1, min(scale, h // 8, w // 8))
    fs = cv2.resize(f, (max(1, w // s), max(1, h // s)), interpolation=cv2.INTER_AREA) if s > 1 else f
    gx = cv2.Sobel(fs, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(fs, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = cv2.GaussianBlur(np.sqrt(gx * gx + gy * gy).max(axis=2), (5, 5), 0)  # colour edges too
    V = fs.max(axis=2)
    ref = float(np.percentile(V[: max(1, len(V) // 3)], 99))
    like = (mag < max_gradient) & (V >= min_brightness * ref) & (fs[..., 2] >= fs[..., 0] - 0.03)
    if allowed is not None:
        like &= cv2.resize(allowed.astype(np.uint8), like.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    if lidar_pixels is not None and lidar_pixels.any():
        # LiDAR points are surfaces: cut the smooth region along them (short horizontal runs join a ring's points)
        pv, pu = np.nonzero(lidar_pixels)
        pts = np.zeros(like.shape, np.uint8)
        pts[np.minimum(pv // s, like.shape[0] - 1), np.minimum(pu // s, like.shape[1] - 1)] = 1
        run = max(3, int(round(2 * point_gap_px / s)) | 1)
        cut = (cv2.dilate(pts, np.ones((1, run), np.uint8)) > 0) & like
        like &= ~cut
    else:
        cut = np.zeros_like(like)
    n, lab = cv2.connectedComponents(like.astype(np.uint8), connectivity=4)
    top_labels = np.unique(lab[0][like[0]])
    top_labels = top_labels[top_labels > 0]
    if cut.any() and len(top_labels):
        # a region that continues smoothly into LiDAR-hit surface along much of its width (a pale facade above the
        # top ring) is that surface; real sky meets LiDAR points only at a few columns (a pale pole or wall edge)
        solid = _continues_a_surface(lab, n, cut, max_contact)
        top_labels = top_labels[~solid[top_labels]]
    sky = np.isin(lab, top_labels) & like
    if sky.any():  # the sky through gaps: its colour at that height, bright, and not a LiDAR-hit surface
        hue = (V >= min_brightness * ref) & (fs[..., 2] >= fs[..., 0] - 0.03) & ~cut & ~sky
        if allowed is not None:
            hue &= cv2.resize(allowed.astype(np.uint8), hue.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
        hue &= _sky_coloured(fs, sky, patch_tol)
        m, gaps = cv2.connectedComponents(hue.astype(np.uint8), connectivity=4)
        if m > 1:
            keep = np.bincount(gaps.ravel(), minlength=m) >= min_patch_px
            keep &= _framed_by_texture(gaps, m, mag, 2.0 * max_gradient)
            if cut.any():
                keep &= ~_continues_a_surface(gaps, m, cut, max_contact)
            keep[0] = False
            sky |= keep[gaps]
    if s > 1:
        sky_full = cv2.resize(sky.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        sky = _grow_sky(sky_full, sky, f, fs, grow_px=3 * s)
        if allowed is not None:
            sky &= allowed
    return sky


def _continues_a_surface(labels: NDArray, count: int, cut: BoolA, max_contact: float) -> BoolA:
    """(count,) per region of ``labels`` (0: none): whether it touches the LiDAR's ``cut`` (h, w) pixels (8-neighbours)
    along more than ``max_contact`` of the columns it spans: it continues a LiDAR-hit surface."""
    hl, wl = labels.shape
    cv, cu = np.nonzero(cut)
    keys = []
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
        nv, nu = cv + dv, cu + du
        ok = (nv >= 0) & (nv < hl) & (nu >= 0) & (nu < wl)
        touch = labels[nv[ok], nu[ok]]
        keys.append(touch[touch > 0] * wl + cu[ok][touch > 0])  # every region beside a cut pixel touches it
    contact = np.bincount(np.unique(np.concatenate(keys)) // wl, minlength=count)
    lv, lu = np.nonzero(labels > 0)
    span = np.bincount(np.unique(labels[lv, lu] * wl + lu) // wl, minlength=count)
    return contact[:count] > max_contact * np.maximum(span[:count], 1)


def _framed_by_texture(labels: NDArray, count: int, gradient: F32, min_gradient: float, width: int = 2) -> BoolA:
    """(count,) per region of ``labels`` (0: none): whether the ``width``-pixel frame around it is textured (mean
    ``gradient`` over it above ``min_gradient``): foliage around a gap, not a smooth facade around a pale patch."""
    kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    grown = cv2.dilate(labels.astype(np.float32), kernel).astype(np.int64)  # the largest label nearby
    frame = (labels == 0) & (grown > 0)
    total = np.bincount(grown[frame], weights=gradient[frame], minlength=count)[:count]
    size = np.bincount(grown[frame], minlength=count)[:count]
    return total > min_gradient * np.maximum(size, 1)


def _sky_coloured(rgb: F32, sky: BoolA, tol: float) -> BoolA:
    """(h, w) pixels of ``rgb`` (h, w, 3) within ``tol`` (every channel) of the mean colour of the ``sky`` pixels in
    the nearest row that has some (the sky's colour changes with height, little along a row)."""
    h = sky.shape[0]
    in_row = sky.sum(axis=1)
    have = np.nonzero(in_row > 0)[0]
    row_colour = np.stack([(rgb[..., c] * sky).sum(axis=1) for c in range(3)], axis=1) / np.maximum(in_row, 1)[:, None]
    rows = np.arange(h)
    after = np.clip(np.searchsorted(have, rows), 0, len(have) - 1)
    before = np.clip(after - 1, 0, len(have) - 1)
    nearest = np.where(np.abs(have[before] - rows) < np.abs(have[after] - rows), have[before], have[after])
    return np.abs(rgb - row_colour[nearest][:, None, :]).max(axis=2) <= tol


def _grow_sky(sky: BoolA, sky_small: BoolA, rgb: F32, rgb_small: F32, grow_px: int, tol: float = 0.04) -> BoolA:
    """Extend ``sky`` (H, W) by up to ``grow_px`` into pixels whose colour is within ``tol`` (every channel) of the
    local mean sky colour (from the downsampled ``sky_small`` / ``rgb_small``): the gradient blur of `image_sky`
    leaves a few pixels at the skyline undecided."""
    if not sky.any():
        return sky
    m = sky_small.astype(np.float32)
    k = (5, 5)
    weight = cv2.boxFilter(m, -1, k, normalize=False)
    local = cv2.boxFilter(rgb_small * m[..., None], -1, k, normalize=False) / np.maximum(weight, 1e-6)[..., None]
    h, w = sky.shape
    local = cv2.resize(local, (w, h), interpolation=cv2.INTER_NEAREST)
    ring = cv2.dilate(sky.astype(np.uint8), np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8)) > 0
    vv, uu = np.nonzero(ring & ~sky)
    close = np.abs(rgb[vv, uu] - local[vv, uu]).max(axis=1) <= tol
    out = sky.copy()
    out[vv[close], uu[close]] = True
    return out


def _as_float_rgb(image: NDArray) -> F32:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"image: expected (H, W, 3) RGB, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float32) * np.float32(1.0 / 255.0)
    return np.clip(a, 0.0, 1.0).astype(np.float32)


# ------------------------------------------------------------------------------------------------ main


def _enclosed_holes(z: F32, holes: BoolA, spread: float) -> BoolA:
    """(H, W) bool: the connected ``holes`` (8-neighbourhood) not touching the image border whose surrounding known
    depths (``z > 0`` on their 1-px rim) span at most a factor ``spread``: one surface all around."""
    n, lab = cv2.connectedComponents(holes.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(holes)
    grown = cv2.dilate(lab.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int64)
    rim = (grown > 0) & ~holes & (z > 0)
    lbl, val = grown[rim], z[rim]
    zmin = np.full(n, np.inf)
    zmax = np.zeros(n)
    np.minimum.at(zmin, lbl, val)
    np.maximum.at(zmax, lbl, val)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    ok = np.isfinite(zmin) & (zmax <= spread * zmin)
    ok[border] = False
    ok[0] = False
    return ok[lab]


def _far_fill(z: F32, holes: BoolA, gap_v: float, gap_h: float, iterations: int = 12) -> F32:
    """Fill ``holes`` of ``z`` (H, W) (0 = unknown) from their surroundings, farthest value first: repeated
    ``gap``-sized max filters (dilation of z itself) written only into still-empty hole pixels."""
    out = z.copy()
    todo = holes & (out <= 0)
    k = np.ones((max(3, int(round(gap_v)) | 1), max(3, int(round(2 * gap_h)) | 1)), np.uint8)
    for _ in range(iterations):
        if not todo.any():
            break
        dil = cv2.dilate(out, k)
        fill = todo & (dil > 0)
        out[fill] = dil[fill]
        todo &= ~fill
    return out


def _nearest_fill(z: F32, known: BoolA, todo: BoolA) -> F32:
    """Copy into ``todo`` pixels the value of the nearest ``known`` pixel (L2 distance transform labels)."""
    if not todo.any() or not known.any():
        return z
    _, labels = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    kv, ku = np.nonzero(known)  # label k (1-based) = k-th zero pixel of the input in row-major order
    lut = np.zeros(len(kv) + 1, np.float32)
    lut[1:] = z[kv, ku]
    out = z.copy()
    out[todo] = lut[labels[todo]]
    return out


def lidar_support(points: BoolA, image: F32, radius_px: float, params: DepthParams, scale: int = 2) -> BoolA:
    """(H, W) bool: pixels within ``radius_px`` of a LiDAR point (``points`` (H, W)) along a path that crosses no
    object boundary of the ``image`` (H, W, 3) float sRGB (`_image_edges`, at 1/``scale`` resolution): a point
    vouches for the surface it lies on, not for the sky beyond that surface's outline. A plain distance let a
    facade's points claim a band of sky one ring gap wide beside its skyline (that band then took the facade's depth:
    a fog halo and a seam with the neighbouring camera). Seeds on a boundary support only themselves."""
    H, W = points.shape
    s = max(1, min(scale, H // 8, W // 8))
    size = (max(1, W // s), max(1, H // s))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA) if s > 1 else image
    free = ~_image_edges(small, params.overhang_chroma, params.overhang_brightness)
    seeds = cv2.resize(cv2.dilate(points.astype(np.uint8), np.ones((s, s), np.uint8)), size,
                       interpolation=cv2.INTER_NEAREST) > 0
    grown = (seeds & free).astype(np.uint8)
    free_u8 = free.astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    for _ in range(max(1, int(math.ceil(radius_px / s)))):
        grown = cv2.dilate(grown, k) & free_u8
    out = cv2.resize(grown, (W, H), interpolation=cv2.INTER_NEAREST) > 0
    return out | points


def _gradient(x: F32) -> F32:
    """(h, w) largest per-channel Sobel gradient magnitude [1/px] of ``x`` (h, w) or (h, w, c), 3 x 3
    Gaussian-blurred (closes gaps in a boundary, so segments do not leak into each other)."""
    gx = cv2.Sobel(x, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(x, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    g = np.sqrt(gx * gx + gy * gy)
    return cv2.GaussianBlur(g.max(axis=2) if g.ndim == 3 else g, (3, 3), 0)


def _image_edges(rgb: F32, chroma_gradient: float, brightness_gradient: float) -> BoolA:
    """(h, w) bool object boundaries of ``rgb`` (h, w, 3) sRGB in [0, 1]: the chromaticity (r, g, b over their sum)
    changes by ``chroma_gradient`` per px, or the brightness (largest channel) by ``brightness_gradient``. Shading
    (a crown's facets, a facade's lit and shaded sides) changes the brightness a little and the hue hardly at all."""
    total = rgb.sum(axis=2, keepdims=True) + np.float32(0.05)
    chroma = np.ascontiguousarray(rgb / total)
    brightness = np.ascontiguousarray(rgb.max(axis=2))
    return (_gradient(chroma) >= chroma_gradient) | (_gradient(brightness) >= brightness_gradient)


def _label_quantile(labels: NDArray[np.int64], values: F32, q: float, which: BoolA, n: int) -> F32:
    """(n,) float32: per label ``k`` with ``which[k]``, the ``q`` quantile (lower order statistic) of the ``values``
    (M,) whose ``labels`` (M,) are ``k``; 0 for other labels."""
    out = np.zeros(n, np.float32)
    pick = which[labels]
    if not pick.any():
        return out
    order = np.lexsort((values[pick], labels[pick]))
    ls, vs = labels[pick][order], values[pick][order]
    starts = np.flatnonzero(np.r_[True, ls[1:] != ls[:-1]])
    counts = np.diff(np.r_[starts, len(ls)])
    idx = starts + np.minimum(counts - 1, (q * counts).astype(np.int64))
    out[ls[starts]] = vs[idx]
    return out


def _grow_into_edges(z: F32, lab: NDArray[np.int64], band: BoolA, rgb: F32, tol: float, steps: int = 3) -> None:
    """Extend each labelled segment's value of ``z`` (h, w) (in place) into the edge ``band`` around it, pixel ring by
    pixel ring (``steps`` rings), where the pixel's colour is within ``tol`` (largest channel) of the segment's mean
    colour: the blurred boundary of a crown is crown, not the facade behind. ``lab`` (h, w): segment labels (0 =
    none); ``rgb`` (h, w, 3) the image at that resolution."""
    n = int(lab.max()) + 1
    if n <= 1:
        return
    flat = lab.ravel()
    count = np.maximum(np.bincount(flat, minlength=n), 1)
    mean = np.stack([np.bincount(flat, rgb[..., k].ravel(), minlength=n) / count for k in range(3)], axis=1)
    cur = lab.astype(np.float32)
    todo = band & (lab == 0)
    for _ in range(steps):
        grown = cv2.dilate(cur, np.ones((3, 3), np.uint8)).astype(np.int64)
        vv, uu = np.nonzero(todo & (grown > 0))
        g = grown[vv, uu]
        ok = np.abs(rgb[vv, uu] - mean[g]).max(axis=1) <= tol
        if not ok.any():
            break
        vv, uu, g = vv[ok], uu[ok], g[ok]
        src = cv2.dilate(np.where(cur > 0, z, 0.0).astype(np.float32), np.ones((3, 3), np.uint8))
        z[vv, uu] = src[vv, uu]
        cur[vv, uu] = g
        todo[vv, uu] = False


def _overhangs(z: F32, z_cont: F32, up: BoolA, image: F32, gap_h: float, params: DepthParams) -> F32:
    """Camera z (H, W) [m] of the unknown pixels above the LiDAR's field of view (``up``), image segment by segment.

    The column rule (``z_cont``: each column's highest known z continued upwards) is right for a surface that
    continues upwards (a facade above the top ring) and wrong for an object that starts above it: a tree crown or a
    lamp head above its trunk or pole would take the depth of the facade behind. At 1/``params.overhang_scale``
    resolution, ``up`` is cut along object boundaries in the image (`_image_edges`) into segments. A segment touching
    known depth (``z > 0``) or an already decided segment without an edge between continues that surface: it keeps
    ``z_cont`` where that lies within ``params.same_surface_ratio`` of the depths it touches, else takes their median
    (the side columns of a crown whose middle the LiDAR hit, over a facade). A segment the image separates from
    everything below it is a separate object resting on, or hanging from, what lies under it: it takes the
    ``params.overhang_quantile`` quantile (the near side) of the z directly below it (within
    ``params.overhang_reach_gaps`` point gaps), so a crown over a 10 % wide trunk gets the trunk's depth and a facade
    over a thin pole keeps its own. Segments are decided bottom-up; edge pixels of the
    colour of a separate segment beside them join it (`_grow_into_edges`); the rest keeps ``z_cont``.

    Args:
        z: (H, W) camera z [m] before the column rule (0 = unknown); z_cont: (H, W) after it; up: (H, W) the pixels
            the column rule filled; image: (H, W, 3) float sRGB in [0, 1]; gap_h: horizontal point gap [px].

    Returns:
        (H, W) float32 camera z [m] (``z_cont`` where no segment decides otherwise).
    """
    H, W = z.shape
    s = max(1, min(int(params.overhang_scale), H // 8, W // 8))
    size = (max(1, W // s), max(1, H // s))
    fs = cv2.resize(image, size, interpolation=cv2.INTER_AREA) if s > 1 else image
    us = cv2.resize(up.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    zs = np.where(us, 0.0, cv2.resize(z, size, interpolation=cv2.INTER_NEAREST)).astype(np.float32)
    zc = cv2.resize(z_cont, size, interpolation=cv2.INTER_NEAREST)
    edge = _image_edges(fs, params.overhang_chroma, params.overhang_brightness)
    n, lab = cv2.connectedComponents((us & ~edge).astype(np.uint8), connectivity=4)
    if n <= 1:
        return z_cont
    reach = max(8, int(round(params.overhang_reach_gaps * gap_h / s)))  # beyond the edge band
    decided = np.zeros(n, bool)
    decided[0] = True
    separate = np.zeros(n, bool)
    fixed = np.zeros(zs.shape, bool)  # pixels whose value overrides the column rule
    tol = np.float32(params.same_surface_ratio)
    for _ in range(64):  # bottom-up: each pass decides the segments resting on what is known so far
        known = zs > 0
        c_lab, c_z = [], []
        for a, b in (((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
                     ((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
                     ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                     ((slice(None), slice(1, None)), (slice(None), slice(None, -1)))):
            m = (lab[a] > 0) & known[b] & ~edge[b]
            c_lab.append(lab[a][m])
            c_z.append(zs[b][m])
        b_lab, b_z = [], []
        for d in range(1, reach + 1):
            m = (lab[:-d] > 0) & known[d:]
            b_lab.append(lab[:-d][m])
            b_z.append(zs[d:][m])
        cl, cz = np.concatenate(c_lab), np.concatenate(c_z)
        bl, bz = np.concatenate(b_lab), np.concatenate(b_z)
        touch = np.zeros(n, bool)
        touch[cl] = True
        new_touch = touch & ~decided
        new_sep = np.zeros(n, bool)
        new_sep[bl] = True
        new_sep &= ~touch & ~decided
        if not (new_touch.any() or new_sep.any()):
            break
        # a continuing segment keeps the column rule where it gives a depth of the surface it touches (within the
        # same-surface ratio of the contacts' range), else the contacts' median: a crown whose lower part the LiDAR
        # hit must not take, in its side columns, the facade below it
        lo, hi, med = (_label_quantile(cl, cz, q, new_touch, n) for q in (0.0, 1.0, 0.5))
        off = new_touch[lab] & ((zc < lo[lab] / tol) | (zc > hi[lab] * tol))
        sep_z = _label_quantile(bl, bz, params.overhang_quantile, new_sep, n)
        zs = np.where(new_sep[lab], sep_z[lab], np.where(off, med[lab], np.where(new_touch[lab], zc, zs)))
        zs = zs.astype(np.float32)
        fixed |= new_sep[lab] | off
        separate |= new_sep
        decided |= new_touch | new_sep
    out_small = np.where(fixed, zs, 0.0).astype(np.float32)
    _grow_into_edges(out_small, np.where(separate[lab], lab, 0), us & edge, fs, params.overhang_colour_tol)
    out = cv2.resize(out_small, (W, H), interpolation=cv2.INTER_NEAREST) if s > 1 else out_small
    return np.where(up & (out > 0), out, z_cont).astype(np.float32)


def complete_depth(points: CameraPoints, K: F64, width: int, height: int, image: NDArray | None,
                   top_elevation_deg: float, params: DepthParams = DepthParams()) -> DenseDepth:
    """Dense ray length (H, W) for camera-frame LiDAR points (see the module docstring for the stages).

    Args:
        points: LiDAR points in the camera frame at the exposure (`camera_points`).
        K: (3, 3) intrinsics [px]; width, height: image size [px].
        image: (H, W, 3) uint8 sRGB or float [0, 1] clear image (guides refinement and sky), or None.
        top_elevation_deg: the LiDAR's highest beam elevation [deg] in its own frame.
    """
    H, W = int(height), int(width)
    if image is not None and np.asarray(image).shape[:2] != (H, W):
        raise ValueError(f"image shape {np.asarray(image).shape[:2]} != camera size {(H, W)}")
    norms = pixel_ray_norms(K, W, H)
    above = above_fov_mask(K, W, H, points.R_lidar_cam, top_elevation_deg + params.sky_margin_deg)
    sp, z_sparse, gap_v, gap_h = _filtered_sparse_depth(points, K, W, H, params)
    kept = z_sparse[sp.pix[:, 0], sp.pix[:, 1]] > 0
    num = int(kept.sum())
    if num < 3:
        raise ValueError(f"complete_depth: only {num} LiDAR points project into the {W}x{H} image (nearer than "
                         f"{params.min_depth_m} m excluded); check the camera/LiDAR calibration and timestamps")
    img = _as_float_rgb(image) if image is not None else None
    inv, conf, planar = _interpolated_inverse_depth(sp, kept, z_sparse, points, img, gap_v, gap_h, params)
    sky = _sky_mask(z_sparse, planar, img, above, K, points.up_cam, gap_v, gap_h, params)
    sky_conf = CONF_PLANAR if img is not None else CONF_FILL
    z = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-9), 0.0).astype(np.float32)
    z[sky] = 0.0
    have = z > 0
    if not have.any():
        sky = np.ones((H, W), bool)
    else:
        z = _fill_without_return(z, sky, above, img, gap_v, gap_h, params)
        conf[(conf == 0) & ~sky] = CONF_EXTENDED
    conf[sky] = sky_conf
    rng = np.where(sky, np.float32(np.inf), z * norms).astype(np.float32)
    return DenseDepth(range=rng, confidence=conf, valid=conf >= 0.5, sky=sky, above_fov=above, num_points=num)


def _filtered_sparse_depth(points: CameraPoints, K: F64, width: int, height: int,
                           params: DepthParams) -> tuple[SparseDepth, F32, float, float]:
    """The points' `SparseDepth` in the image, its depth map (H, W) [m] without the points seen through a nearer
    surface (occluded, see-through, parallax between LiDAR and camera; 0: none) and the vertical and horizontal
    spacing of the points [px] (`point_gaps`)."""
    sp = sparse_depth(points, K, width, height, params)
    occupied = sp.z > 0
    gap_v, gap_h = point_gaps(occupied)
    z_sparse = drop_occluded(sp.z, gap_v, gap_h, params.occlusion_ratio)
    z_sparse = drop_see_through(z_sparse, gap_v, gap_h, params.see_through_reach_gaps, params.see_through_ratio,
                                params.see_through_rim_spread)
    if points.lidar_origin_cam is not None:
        z_sparse = drop_parallax(z_sparse, points.lidar_origin_cam, K, gap_v, gap_h, params.occlusion_ratio,
                                 params.min_depth_m)
    return sp, z_sparse, gap_v, gap_h


def _interpolated_inverse_depth(sp: SparseDepth, kept: BoolA, z_sparse: F32, points: CameraPoints, img: F32 | None,
                                gap_v: float, gap_h: float, params: DepthParams) -> tuple[F32, F32, BoolA]:
    """Inverse depth (H, W) [1/m] between the ``kept`` points of ``sp`` (depth map ``z_sparse`` (H, W) [m]): planar
    patches of their triangulation, a morphological fill elsewhere, whose edges are refined against the image
    ``img`` (H, W, 3) float [0, 1] when given; its confidence (H, W) (`CONF_PLANAR`, `CONF_FILL`, 0) and the planar
    pixels."""
    H, W = z_sparse.shape
    conf = np.zeros((H, W), np.float32)
    gap = max(gap_v, gap_h)
    inv_tri = triangulate(sp.uv[kept], points.xyz[sp.index[kept]], points.up_cam, H, W,
                          params.max_edge_gaps * gap, params)
    z_fill = morphological_fill(z_sparse, gap_v, gap_h)
    planar = inv_tri > 0
    inv = np.where(planar, inv_tri, np.where(z_fill > 0, 1.0 / np.maximum(z_fill, 1e-6), 0.0)).astype(np.float32)
    conf[planar] = CONF_PLANAR
    conf[~planar & (z_fill > 0)] = CONF_FILL
    if img is not None:
        conf_inv = np.where(planar, inv_tri, 0.0).astype(np.float32)
        conf_inv[z_sparse > 0] = 1.0 / z_sparse[z_sparse > 0]
        todo = ~planar & (inv > 0)
        inv = refine_edges(inv, conf_inv, todo, img, int(round(params.refine_radius_gaps * gap)), params)
    return inv, conf, planar


def _sky_mask(z_sparse: F32, planar: BoolA, img: F32 | None, above: BoolA, K: F64, up_cam: F64, gap_v: float,
              gap_h: float, params: DepthParams) -> BoolA:
    """(H, W) the sky: pixels without LiDAR support (no point within `DepthParams.support_gaps` point spacings, nor
    a planar patch) that the image shows as sky (connected to its top border; below the field of view too) or, with
    no image, that lie above the LiDAR's field of view (``above``)."""
    H, W = z_sparse.shape
    gap = max(gap_v, gap_h)
    if img is None:
        dist = cv2.distanceTransform((z_sparse <= 0).astype(np.uint8), cv2.DIST_L2, 3)
        supported = (dist <= params.support_gaps * gap) | planar
    else:
        supported = lidar_support(z_sparse > 0, img, params.support_gaps * gap, params) | planar
    if img is not None:
        # no return and sky in the image; below the field of view too (sky behind the end of a street), where the
        # image's sky region (connected to the top border) reaches down unsupported
        return ~supported & image_sky(img, z_sparse > 0, above_horizon_mask(K, W, H, up_cam, 0.0), gap_h)
    return above & ~supported


def _fill_without_return(z: F32, sky: BoolA, above: BoolA, img: F32 | None, gap_v: float, gap_h: float,
                         params: DepthParams) -> F32:
    """``z`` (H, W) [m] (0: unknown) filled everywhere but the ``sky``: holes without return inside the field of
    view, then structures above it (``above``), then whatever is left by the nearest depth."""
    H, W = z.shape
    # holes inside the field of view had no return. Enclosed by one surface (max/min boundary depth within
    # `hole_spread`): that surface absorbed or passed the pulse (dark paint, glass), so it continues across
    # (nearest fill). Otherwise a surface beyond the LiDAR's range or in its shadow behind a foreground object:
    # the farthest depth around (not the nearest) fills it.
    holes = (z <= 0) & ~sky & ~above
    enclosed = _enclosed_holes(z, holes, params.hole_spread)
    z = _nearest_fill(z, z > 0, enclosed)
    z = _far_fill(z, holes & ~enclosed, gap_v, gap_h)
    # structures above the field of view: the column's highest known camera z continued upwards (a vertical
    # surface in an upright camera keeps its z along an image column); the top values are median-filtered
    # along the row over a few point spacings so a thin pole does not paint a streak up to the image top
    have = z > 0
    first = np.argmax(have, axis=0)
    has_col = have.any(axis=0)
    rows = np.arange(H)[:, None]
    z_top = z[first, np.arange(W)]
    if has_col.sum() >= 3:
        cols = np.flatnonzero(has_col)
        size = max(3, int(round(4 * gap_h)) | 1)
        z_top[cols] = median_filter(z_top[cols], size=size, mode="nearest")
    up = (rows < first[None, :]) & has_col[None, :] & ~sky
    z_cont = np.where(up, z_top[None, :], z)
    z = z_cont if img is None else np.where(up, _overhangs(z, z_cont, up, img, gap_h, params), z)
    rest = (z <= 0) & ~sky
    return _nearest_fill(z, z > 0, rest)


def dense_depth(
    lidar: LidarScan | NDArray,
    camera: CameraView,
    image: NDArray | None = None,
    lidar_top_elevation_deg: float | None = None,
    *,
    T_ego_lidar: F64 | None = None,
    params: DepthParams = DepthParams(),
) -> DenseDepth:
    """Dense ray-length map of ``camera`` from LiDAR.

    Args:
        lidar: a `LidarScan` (aggregate sweeps first, e.g. ``load_lidar(nusc, token, nsweeps=3)``), or an (N, 3)
            array of points in the LiDAR frame **at the camera's timestamp** (then ``T_ego_lidar`` is needed, and
            the ego's up axis is taken from the camera's extrinsics).
        camera: the view (K, size, ``T_ego_cam``, ``T_global_ego`` at its own timestamp).
        image: (H, W, 3) clear image (uint8 sRGB or float [0, 1]); None = ``camera.load_image()``.
        lidar_top_elevation_deg: the LiDAR's top beam elevation [deg]; None = `estimate_top_elevation_deg` of the scan
            (required for an array).
        T_ego_lidar: (4, 4) LiDAR -> ego, for an array input.
        params: `DepthParams`.

    Returns:
        `DenseDepth`: ``range`` (H, W) float32 ray length [m], inf = sky, plus confidence/validity/sky masks.
        `benchmarks/bench_depth.py` measures its time per camera.

    Raises:
        ValueError: fewer than 3 LiDAR points in the image; a point array without ``T_ego_lidar`` or top elevation.
    """
    if isinstance(lidar, LidarScan):
        pts = camera_points(lidar, camera)
        top = (estimate_top_elevation_deg(lidar) if lidar_top_elevation_deg is None
               else float(lidar_top_elevation_deg))
    else:
        xyz = np.asarray(lidar, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] < 3:
            raise ValueError(f"lidar points: expected (N, 3), got {xyz.shape}")
        if T_ego_lidar is None or lidar_top_elevation_deg is None:
            raise ValueError("dense_depth with a point array needs T_ego_lidar and lidar_top_elevation_deg")
        T_cam_lidar = invert(camera.T_ego_cam) @ np.asarray(T_ego_lidar, dtype=np.float64)
        pts = _points_in_camera(xyz[:, :3], np.zeros(len(xyz)), T_cam_lidar, camera)
        top = float(lidar_top_elevation_deg)
    img = camera.load_image() if image is None else image
    return complete_depth(pts, camera.K, camera.width, camera.height, img, top, params)



def pixels_in_view(view_a: CameraView, view_b: CameraView, v: NDArray, u: NDArray
                   ) -> tuple[BoolA, NDArray[np.int64], NDArray[np.int64]]:
    """Where the viewing directions of pixels (``v``, ``u``) (N,) of ``view_a`` land in ``view_b`` (rotation only:
    the same direction from both camera centres, each at its own timestamp's pose): (N,) bool inside ``view_b``'s
    image and in front of it, and the (vb, ub) pixels (rounded) of those inside."""
    pix = np.stack([u, v, np.ones(len(u))], axis=1).astype(np.float64)
    d = pix @ np.linalg.inv(np.asarray(view_a.K)).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    db = d @ (view_b.T_global_cam[:3, :3].T @ view_a.T_global_cam[:3, :3]).T
    z = db[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        p = db @ np.asarray(view_b.K).T
        ub, vb = np.rint(p[:, 0] / z), np.rint(p[:, 1] / z)
    ok = (z > 0.05) & (ub >= 0) & (ub < view_b.width) & (vb >= 0) & (vb < view_b.height)
    return ok, vb[ok].astype(np.int64), ub[ok].astype(np.int64)


def consistent_sky(views: Mapping[str, CameraView], ranges: Mapping[str, F32]) -> dict[str, F32]:
    """The range maps (H, W) float32 [m], inf = sky, of cameras that see one another's directions, with sky where
    they agree: a sky pixel of one camera whose viewing direction (rotation only: the cameras' baselines are
    negligible against sky and far surfaces) another camera sees as a surface takes that camera's ray length there.
    Each camera completes its depth alone, so the image cues could call the same facade sky in one camera and not in
    its neighbour: a seam of white sky against fogged structure. Agreement removes those seams and takes less structure
    for sky, at the cost of some true sky given a surface (`benchmarks.bench_depth` measures all three on the synthetic
    world's six cameras). Decisions use the input maps (order-independent); the inputs are not modified."""
    out = {ch: np.array(r, dtype=np.float32, copy=True) for ch, r in ranges.items()}
    for a, view_a in views.items():
        sky_v, sky_u = np.nonzero(np.isposinf(ranges[a]))
        if not len(sky_v):
            continue
        for b, view_b in views.items():
            if b == a:
                continue
            ok, vb, ub = pixels_in_view(view_a, view_b, sky_v, sky_u)
            if not ok.any():
                continue
            rb = ranges[b][vb, ub]
            surface = np.isfinite(rb)
            out[a][sky_v[ok][surface], sky_u[ok][surface]] = rb[surface]
    return out


def camera_range_map(view: CameraView, lidar: LidarScan, image: NDArray | None = None) -> F32:
    """(H, W) float32 ray length [m] of ``view`` (inf = sky): the exact map where the dataset stores one (the
    synthetic world, the synthetic reference), else `dense_depth` from ``lidar`` (aggregate sweeps first for
    nuScenes). The one place that makes this choice: simulate, calibrate and the reference checks call it."""
    if view.range_path is not None:
        return view.load_range()
    return dense_depth(lidar, view, image).range
