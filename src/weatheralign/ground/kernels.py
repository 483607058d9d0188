"""Compiled per-point kernels of the ground: the value and fractal noise that the water-depth and snow-depth fields
and the snow's grain are made of, evaluated at every LiDAR return and every camera pixel; the surfaces they lie on
(the returns' PCA normals and their neighbours' median, a range map's normals); the mirror image's march.

`weatheralign.ground.wet.fractal_noise_naive` (numpy) defines the result; `fractal_noise_kernel` computes the same
rule point by point (the same integer hash, the same operation order). Nothing here allocates per point; the kernels
release the GIL.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@numba.njit(cache=True, nogil=True, inline="always")
def hash01(ix: np.int64, iy: np.int64, seed: np.int64) -> np.float64:
    """A value in [0, 1) per integer lattice point and seed (`weatheralign.ground.wet._hash01`, wrapping int64)."""
    h = (ix * np.int64(73856093)) ^ (iy * np.int64(19349663)) ^ (seed * np.int64(83492791))
    h = (h ^ (h >> np.int64(13))) * np.int64(1274126177)
    h = h ^ (h >> np.int64(16))
    return np.float64(h & np.int64(0xFFFFFF)) / np.float64(1 << 24)


@numba.njit(cache=True, nogil=True, inline="always")
def value_noise_one(x: np.float64, y: np.float64, cell_m: np.float64, seed: np.int64) -> np.float64:
    """Smooth value noise in [0, 1) at one world position [m] (`weatheralign.ground.wet.value_noise`)."""
    gx, gy = x / cell_m, y / cell_m
    fx0, fy0 = np.floor(gx), np.floor(gy)
    fx, fy = gx - fx0, gy - fy0
    fx = fx * fx * (3.0 - 2.0 * fx)
    fy = fy * fy * (3.0 - 2.0 * fy)
    ix, iy = np.int64(fx0), np.int64(fy0)
    n00, n10 = hash01(ix, iy, seed), hash01(ix + 1, iy, seed)
    n01, n11 = hash01(ix, iy + 1, seed), hash01(ix + 1, iy + 1, seed)
    return (n00 * (1 - fx) + n10 * fx) * (1 - fy) + (n01 * (1 - fx) + n11 * fx) * fy


@numba.njit(cache=True, nogil=True)
def value_noise_kernel(xy: F64, cell_m: float, seed: int) -> F64:
    """(N,) value noise in [0, 1) at world positions ``xy`` (N, 2) [m] (`weatheralign.ground.wet.value_noise`)."""
    out = np.empty(xy.shape[0])
    for i in range(xy.shape[0]):
        out[i] = value_noise_one(xy[i, 0], xy[i, 1], cell_m, np.int64(seed))
    return out


@numba.njit(cache=True, nogil=True)
def tracks_factor_kernel(xy: F64, origin: F64, along_unit: F64, lanes: F64, gauge_m: float, width_m: float,
                         remaining_share: float, wander_m: float, wander_cell_m: float, seed: int) -> F64:
    """(N,) the share of the snow left at world positions ``xy`` (N, 2) by wheel tracks
    (`weatheralign.ground.snow.TireTracks.depth_factor_naive`'s rule)."""
    out = np.empty(xy.shape[0])
    half = 0.5 * width_m
    for i in range(xy.shape[0]):
        dx, dy = xy[i, 0] - origin[0], xy[i, 1] - origin[1]
        along = dx * along_unit[0] + dy * along_unit[1]
        lateral = -dx * along_unit[1] + dy * along_unit[0]
        shift = wander_m * (2.0 * value_noise_one(along, 0.0, wander_cell_m, np.int64(seed + 7)) - 1.0)
        factor = 1.0
        for lane in lanes:
            for wheel in (-0.5 * gauge_m, 0.5 * gauge_m):
                distance = abs(lateral - shift - lane - wheel)
                if distance < half:
                    dip = 0.5 * (1.0 + np.cos(np.pi * distance / half))
                    factor = min(factor, 1.0 - (1.0 - remaining_share) * dip)
        out[i] = factor
    return out


@numba.njit(cache=True, nogil=True)
def fractal_noise_kernel(xy: F64, cell_m: float, seed: int, octaves: int) -> F64:
    """(N,) fractal noise in [0, 1) at world positions ``xy`` (N, 2) [m] (`weatheralign.ground.wet.fractal_noise`)."""
    out = np.empty(xy.shape[0])
    for i in range(xy.shape[0]):
        total, weight, norm = 0.0, 1.0, 0.0
        for octave in range(octaves):
            total += weight * value_noise_one(xy[i, 0], xy[i, 1], cell_m / 2.0**octave, np.int64(seed * 31 + octave))
            norm += weight
            weight *= 0.5
        out[i] = total / norm
    return out





@numba.njit(cache=True, nogil=True, inline="always")
def smallest_eigenvector(a00: float, a01: float, a02: float, a11: float, a12: float,
                         a22: float) -> tuple[float, float, float]:
    """Unit eigenvector of the smallest eigenvalue of the symmetric 3x3 matrix ``[[a00, a01, a02], [., a11, a12],
    [., ., a22]]``: the eigenvalue in closed form (the trigonometric solution of the characteristic cubic), the vector
    the largest cross product of two rows of ``A - lambda I``; (0, 0, 1) where the matrix is a multiple of I, and a
    vector across the largest row where the two smallest eigenvalues are equal (collinear points)."""
    scale = max(abs(a00), abs(a01), abs(a02), abs(a11), abs(a12), abs(a22))
    if scale <= 0.0:
        return 0.0, 0.0, 1.0
    a00, a01, a02, a11, a12, a22 = a00 / scale, a01 / scale, a02 / scale, a11 / scale, a12 / scale, a22 / scale
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0)
    if p <= 0.0:
        return 0.0, 0.0, 1.0
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = min(max(det / (2.0 * p * p * p), -1.0), 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    r0 = (a00 - smallest, a01, a02)
    r1 = (a01, a11 - smallest, a12)
    r2 = (a02, a12, a22 - smallest)
    best, bx, by, bz = -1.0, 0.0, 0.0, 1.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        cx, cy, cz = u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]
        n2 = cx * cx + cy * cy + cz * cz
        if n2 > best:
            best, bx, by, bz = n2, cx, cy, cz
    if best <= 1e-24:  # a double smallest eigenvalue: any vector across the largest row
        big, size = r0, r0[0] * r0[0] + r0[1] * r0[1] + r0[2] * r0[2]
        for row in (r1, r2):
            if row[0] * row[0] + row[1] * row[1] + row[2] * row[2] > size:
                big, size = row, row[0] * row[0] + row[1] * row[1] + row[2] * row[2]
        if abs(big[0]) > abs(big[2]):
            bx, by, bz = -big[1], big[0], 0.0
        else:
            bx, by, bz = 0.0, -big[2], big[1]
        best = bx * bx + by * by + bz * bz
        if best <= 0.0:
            return 0.0, 0.0, 1.0
    norm = np.sqrt(best)
    return bx / norm, by / norm, bz / norm


@numba.njit(cache=True, nogil=True)
def neighbour_normals_kernel(points: F64, index: NDArray[np.int64], origin: F64) -> tuple[F64, F64]:
    """(N, 3) unit normals of ``points`` (N, 3): the direction of least variance of each point's neighbours
    ``index`` (N, k) (their covariance about their mean, `smallest_eigenvector`), turned towards ``origin`` (3,)
    (`weatheralign.ground.surfaces.point_normals_naive`'s rule); and (N,) the share of the variance along it
    (``nᵀ C n / tr C``, the least eigenvalue over their sum; 0 where the neighbours coincide)."""
    n, k = index.shape
    out = np.empty((n, 3))
    variation = np.empty(n)
    for i in range(n):
        mx = my = mz = 0.0
        for m in range(k):
            j = index[i, m]
            mx += points[j, 0]
            my += points[j, 1]
            mz += points[j, 2]
        mx, my, mz = mx / k, my / k, mz / k
        sxx = sxy = sxz = syy = syz = szz = 0.0
        for m in range(k):
            j = index[i, m]
            dx, dy, dz = points[j, 0] - mx, points[j, 1] - my, points[j, 2] - mz
            sxx += dx * dx
            sxy += dx * dy
            sxz += dx * dz
            syy += dy * dy
            syz += dy * dz
            szz += dz * dz
        nx, ny, nz = smallest_eigenvector(sxx / k, sxy / k, sxz / k, syy / k, syz / k, szz / k)
        if nx * (origin[0] - points[i, 0]) + ny * (origin[1] - points[i, 1]) + nz * (origin[2] - points[i, 2]) < 0:
            nx, ny, nz = -nx, -ny, -nz
        out[i, 0], out[i, 1], out[i, 2] = nx, ny, nz
        trace = sxx + syy + szz
        along = (sxx * nx * nx + syy * ny * ny + szz * nz * nz
                 + 2.0 * (sxy * nx * ny + sxz * nx * nz + syz * ny * nz))
        variation[i] = min(max(along / trace, 0.0), 1.0) if trace > 0.0 else 0.0
    return out, variation


@numba.njit(cache=True, nogil=True)
def neighbour_median_kernel(values: F64, index: NDArray[np.int64]) -> F64:
    """(N,) the median of ``values`` over each row of ``index`` (N, k) (``np.median(values[index], axis=1)``, the
    two middle values averaged for an even k)."""
    n, k = index.shape
    out = np.empty(n)
    window = np.empty(k)
    for i in range(n):
        for m in range(k):  # insertion sort: k is small
            v = values[index[i, m]]
            slot = m
            while slot > 0 and window[slot - 1] > v:
                window[slot] = window[slot - 1]
                slot -= 1
            window[slot] = v
        out[i] = window[k // 2] if k % 2 else (window[k // 2 - 1] + window[k // 2]) / 2.0
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def reflect_index(k: np.int64, n: np.int64) -> np.int64:
    """``k`` folded into ``0..n-1`` as scipy.ndimage's ``reflect`` mode does (``d c b a | a b c d | d c b a``)."""
    while k < 0 or k >= n:
        k = -k - 1 if k < 0 else 2 * n - k - 1
    return k


@numba.njit(cache=True, nogil=True)
def pixel_points_kernel(range_map: F64, K_inv: F64, R: F64, origin: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """World points (H, W, 3) of a camera's pixels from its range map (H, W) [m] (0 along the ray for the sky), the
    unit rays (H, W, 3) through the pixel centres and where the range is finite (H, W); ``K_inv`` (3, 3) the inverse
    intrinsics, ``R`` (3, 3) and ``origin`` (3,) the camera's rotation and position in the world."""
    height, width = range_map.shape
    points = np.empty((height, width, 3))
    rays = np.empty((height, width, 3))
    finite = np.empty((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            cx = K_inv[0, 0] * j + K_inv[0, 1] * i + K_inv[0, 2]
            cy = K_inv[1, 0] * j + K_inv[1, 1] * i + K_inv[1, 2]
            cz = K_inv[2, 0] * j + K_inv[2, 1] * i + K_inv[2, 2]
            norm = np.sqrt(cx * cx + cy * cy + cz * cz)
            cx, cy, cz = cx / norm, cy / norm, cz / norm
            r = range_map[i, j]
            ok = np.isfinite(r)
            finite[i, j] = ok
            length = r if ok else 0.0
            for c in range(3):
                d = R[c, 0] * cx + R[c, 1] * cy + R[c, 2] * cz
                rays[i, j, c] = d
                points[i, j, c] = origin[c] + d * length
    return points, rays, finite


@numba.njit(cache=True, nogil=True)
def _box_mean(points: F64, finite: NDArray[np.bool_], smooth_px: int) -> tuple[F64, F64]:
    """The mean (H, W, 3) of the finite ``points`` (H, W, 3) over ``smooth_px`` x ``smooth_px`` (scipy's reflected
    border) and the finite share of that window (H, W)."""
    height, width = finite.shape
    half = smooth_px // 2
    rows = np.zeros((height, width, 4))  # the horizontal box sums of (x, y, z) * finite and finite
    for i in range(height):
        for j in range(width):
            for dj in range(-half, smooth_px - half):
                jj = reflect_index(j + dj, width)
                if finite[i, jj]:
                    for c in range(3):
                        rows[i, j, c] += points[i, jj, c]
                    rows[i, j, 3] += 1.0
    smooth = np.zeros((height, width, 3))
    weight = np.zeros((height, width))
    for i in range(height):
        for j in range(width):
            sx = sy = sz = sw = 0.0
            for di in range(-half, smooth_px - half):
                ii = reflect_index(i + di, height)
                sx += rows[ii, j, 0]
                sy += rows[ii, j, 1]
                sz += rows[ii, j, 2]
                sw += rows[ii, j, 3]
            weight[i, j] = sw / (smooth_px * smooth_px)
            scale = max(sw, 1e-9 * smooth_px * smooth_px)
            smooth[i, j, 0] = sx / scale
            smooth[i, j, 1] = sy / scale
            smooth[i, j, 2] = sz / scale
    return smooth, weight


@numba.njit(cache=True, nogil=True)
def pixel_normals_kernel(range_map: F64, K_inv: F64, R: F64, origin: F64, smooth_px: int,
                         edge_ratio: float) -> tuple[F64, F64]:
    """World points (H, W, 3) and unit normals (H, W, 3) of a camera's pixels from its range map
    (`weatheralign.ground.surfaces.pixel_normals_naive`'s rule: points averaged over ``smooth_px`` x ``smooth_px``
    finite pixels, normals from the central differences, nan at depth edges, on the border and for the sky)."""
    height, width = range_map.shape
    points, rays, finite = pixel_points_kernel(range_map, K_inv, R, origin)
    if smooth_px <= 1:  # no averaging: the points themselves (0 for the sky), each its own weight
        smooth = np.zeros((height, width, 3))
        weight = np.zeros((height, width))
        for i in range(height):
            for j in range(width):
                if finite[i, j]:
                    for c in range(3):
                        smooth[i, j, c] = points[i, j, c]
                    weight[i, j] = 1.0
    else:
        smooth, weight = _box_mean(points, finite, smooth_px)
    normals = np.full((height, width, 3), np.nan)
    for i in range(1, height - 1):
        for j in range(1, width - 1):
            r = range_map[i, j]
            if not finite[i, j] or weight[i, j] < 0.999:
                continue
            if (abs(range_map[i, j + 1] - range_map[i, j - 1]) > edge_ratio * r
                    or abs(range_map[i + 1, j] - range_map[i - 1, j]) > edge_ratio * r):
                continue  # a depth edge (or a sky neighbour: inf) between its neighbours
            ax = smooth[i, j + 1, 0] - smooth[i, j - 1, 0]
            ay = smooth[i, j + 1, 1] - smooth[i, j - 1, 1]
            az = smooth[i, j + 1, 2] - smooth[i, j - 1, 2]
            bx = smooth[i + 1, j, 0] - smooth[i - 1, j, 0]
            by = smooth[i + 1, j, 1] - smooth[i - 1, j, 1]
            bz = smooth[i + 1, j, 2] - smooth[i - 1, j, 2]
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
            if length < 1e-12:
                continue
            sign = -1.0 if nx * rays[i, j, 0] + ny * rays[i, j, 1] + nz * rays[i, j, 2] > 0 else 1.0
            normals[i, j, 0] = sign * nx / length
            normals[i, j, 1] = sign * ny / length
            normals[i, j, 2] = sign * nz / length
    for i in range(height):
        for j in range(width):
            if not finite[i, j]:
                points[i, j, 0] = points[i, j, 1] = points[i, j, 2] = np.nan
    return points, normals




@numba.njit(cache=True, nogil=True, inline="always")
def _look(cx: np.float64, cy: np.float64, cz: np.float64, K: tuple, range_map: F64,
          thickness_m: float) -> tuple[bool, bool, np.int64, np.int64]:
    """A point (camera frame) seen by the camera: (inside the image, behind the surface its pixel shows by less than
    ``thickness_m``, row, col) (`weatheralign.ground.camera.screen_space_reflection_naive`'s ``look``); ``K`` the
    top two rows of the intrinsics, row-major as scalars (held in registers over the march)."""
    if cz <= 1e-6:
        return False, False, np.int64(0), np.int64(0)
    u = (K[0] * cx + K[1] * cy + K[2] * cz) / cz
    v = (K[3] * cx + K[4] * cy + K[5] * cz) / cz
    col, row = np.int64(np.rint(u)), np.int64(np.rint(v))
    height, width = range_map.shape
    if col < 0 or col >= width or row < 0 or row >= height:
        return False, False, row, col
    length = np.sqrt(cx * cx + cy * cy + cz * cz)
    seen = range_map[row, col]
    return True, (length > seen) and (length < seen + thickness_m), row, col


@numba.njit(cache=True, nogil=True)
def screen_space_reflection_kernel(image: F64, range_map: F64, K: F64, start: F64, step: F64, sky: F64,
                                   distances: F64, thickness_m: float, bisections: int) -> F64:
    """(P, 3) radiance along the mirrored rays from ``start`` (P, 3) along ``step`` (P, 3), both in the camera's
    frame (`weatheralign.ground.camera.mirrored_rays`; `screen_space_reflection_naive`'s march: the first step
    behind a surface, bisected ``bisections`` times; the sky once a ray leaves the image or passes every surface)."""
    Kr = (K[0, 0], K[0, 1], K[0, 2], K[1, 0], K[1, 1], K[1, 2])
    out = np.empty((start.shape[0], 3))
    for p in range(start.shape[0]):
        out[p, 0], out[p, 1], out[p, 2] = sky[0], sky[1], sky[2]
        sx, sy, sz = start[p, 0], start[p, 1], start[p, 2]
        mx, my, mz = step[p, 0], step[p, 1], step[p, 2]
        previous = 0.0
        for k in range(distances.shape[0]):
            distance = distances[k]
            inside, hit, row, col = _look(sx + mx * distance, sy + my * distance, sz + mz * distance, Kr, range_map,
                                          thickness_m)
            if not inside:
                break
            if hit:
                low, high = previous, distance
                for _ in range(bisections):
                    middle = 0.5 * (low + high)
                    if _look(sx + mx * middle, sy + my * middle, sz + mz * middle, Kr, range_map, thickness_m)[1]:
                        high = middle
                    else:
                        low = middle
                _, _, row, col = _look(sx + mx * high, sy + my * high, sz + mz * high, Kr, range_map, thickness_m)
                out[p, 0], out[p, 1], out[p, 2] = image[row, col, 0], image[row, col, 1], image[row, col, 2]
                break
            previous = distance
    return out


__all__ = ["fractal_noise_kernel", "hash01", "neighbour_median_kernel", "neighbour_normals_kernel",
           "pixel_normals_kernel", "pixel_points_kernel", "reflect_index",
           "screen_space_reflection_kernel", "smallest_eigenvector", "tracks_factor_kernel", "value_noise_kernel",
           "value_noise_one"]
