"""Ray casting by rasterisation for the two big coherent ray sets of a camera image, without tracing single rays.

- Pixel rays share one origin (a pinhole camera): every triangle is projected and the pixels it may cover are tested
  with an exact ray/triangle test (the three edge planes through the camera centre), keeping the nearest.
- Shadow rays share one direction (the sun): triangles are projected along it onto a grid of cells once per scene;
  a shadow ray only tests the triangles of its cell, exactly (edge functions and depth along the sun).

Both give the same answers as ray casting (edge tests are inclusive and computed from shared vertices in the same
way for the two triangles of a shared edge, so surfaces are watertight) at a fraction of the cost; where two surfaces
coincide (a tyre flush with a body side), the pinhole rasteriser consistently shows the later triangle instead of
whichever rounding favours.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.world.meshes import Mesh

Vec3 = tuple[float, float, float]

NEAR_PLANE_M = 1e-3  # camera-frame depth below which the pinhole rasteriser ignores geometry
COPLANAR_TOLERANCE = 1e-6  # relative depth within which two surfaces are taken as one (the later one is seen)


@njit(nogil=True, cache=True, inline="always")
def _cross(a: Vec3, b: Vec3) -> Vec3:
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


@njit(nogil=True, cache=True, inline="always")
def _grow_box(box: tuple[float, float, float, float], p: Vec3, fx: float, fy: float, cx: float,
              cy: float) -> tuple[float, float, float, float]:
    """``box`` (u_min, u_max, v_min, v_max) grown by the projection of camera-frame ``p`` (z > 0)."""
    u, v = fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy
    return min(box[0], u), max(box[1], u), min(box[2], v), max(box[3], v)


@njit(nogil=True, cache=True, inline="always")
def _clipped_box(a: Vec3, b: Vec3, c: Vec3, fx: float, fy: float, cx: float,
                 cy: float) -> tuple[float, float, float, float]:
    """Image bounding box (u_min, u_max, v_min, v_max) of the camera-frame triangle clipped to z >= the near plane."""
    box = (np.inf, -np.inf, np.inf, -np.inf)
    for p, q in ((a, b), (b, c), (c, a)):
        if p[2] >= NEAR_PLANE_M:
            box = _grow_box(box, p, fx, fy, cx, cy)
        if (p[2] >= NEAR_PLANE_M) != (q[2] >= NEAR_PLANE_M):
            f = (NEAR_PLANE_M - p[2]) / (q[2] - p[2])
            box = _grow_box(box, (p[0] + f * (q[0] - p[0]), p[1] + f * (q[1] - p[1]), NEAR_PLANE_M), fx, fy, cx, cy)
    return box


@njit(nogil=True, cache=True, inline="always")
def _span(lo: float, hi: float, w: Vec3, s: float, dy: float, fx: float, cx: float) -> tuple[float, float]:
    """Narrow the pixel column range [lo, hi] of one image row (``dy`` = (v - cy) / fy) to where the edge function
    ``s w . ((u - cx) / fx, dy, 1)`` may be >= 0, with a small slack (exact per-pixel tests follow)."""
    alpha = s * w[0] / fx
    beta = s * (w[1] * dy + w[2] - w[0] * cx / fx)
    slack = 1e-9 * (abs(w[0]) * (1.0 + (abs(cx) + hi) / fx) + abs(w[1] * dy) + abs(w[2]))
    if alpha > 0:
        return max(lo, -(beta + slack) / alpha), hi
    if alpha < 0:
        return lo, min(hi, -(beta + slack) / alpha)
    return (lo, hi) if beta >= -slack else (1.0, 0.0)


TALL_BOX_ROWS = 8  # triangles whose image box is taller than this have their rows bound by `_row_range` first


@njit(nogil=True, cache=True, inline="always")
def _clip_polygon(us: NDArray, vs: NDArray, m: int, w: Vec3, s: float, fx: float, fy: float, cx: float, cy: float,
                  out_u: NDArray, out_v: NDArray) -> int:
    """Clip the convex pixel-space polygon ``us[:m], vs[:m]`` to the half-plane where the edge function
    ``s w . ((u - cx) / fx, (v - cy) / fy, 1)`` is >= 0 (Sutherland-Hodgman); returns the vertex count written to
    ``out_u``, ``out_v``."""
    n = 0
    for i in range(m):
        j = i + 1 if i + 1 < m else 0
        ei = s * (w[0] * (us[i] - cx) / fx + w[1] * (vs[i] - cy) / fy + w[2])
        ej = s * (w[0] * (us[j] - cx) / fx + w[1] * (vs[j] - cy) / fy + w[2])
        if ei >= 0:
            out_u[n], out_v[n] = us[i], vs[i]
            n += 1
        if (ei >= 0) != (ej >= 0):
            f = ei / (ei - ej)
            out_u[n], out_v[n] = us[i] + f * (us[j] - us[i]), vs[i] + f * (vs[j] - vs[i])
            n += 1
    return n


@njit(nogil=True, cache=True, inline="always")
def _row_range(u0: float, u1: float, v0: float, v1: float, w0: Vec3, w1: Vec3, w2: Vec3, s: float, fx: float,
               fy: float, cx: float, cy: float, buf: NDArray) -> tuple[float, float]:
    """The rows (v0, v1) of the pixel box [u0, u1] x [v0, v1] that the three edge half-planes of a triangle may leave
    pixels in: the box clipped to them, widened by a row either way (conservative: the per-row spans decide);
    empty: v0 > v1. ``buf`` (4, 8) is scratch."""
    buf[0, 0], buf[0, 1], buf[0, 2], buf[0, 3] = u0, u1, u1, u0
    buf[1, 0], buf[1, 1], buf[1, 2], buf[1, 3] = v0, v0, v1, v1
    m = _clip_polygon(buf[0], buf[1], 4, w0, s, fx, fy, cx, cy, buf[2], buf[3])
    m = _clip_polygon(buf[2], buf[3], m, w1, s, fx, fy, cx, cy, buf[0], buf[1])
    m = _clip_polygon(buf[0], buf[1], m, w2, s, fx, fy, cx, cy, buf[2], buf[3])
    if m == 0:
        return 1.0, 0.0
    lo, hi = np.inf, -np.inf
    for i in range(m):
        lo, hi = min(lo, buf[3, i]), max(hi, buf[3, i])
    return max(v0, np.floor(lo) - 1.0), min(v1, np.ceil(hi) + 1.0)


@njit(nogil=True, cache=True)
def _raster_kernel(verts: NDArray, tris: NDArray, fx: float, fy: float, cx: float, cy: float, width: int,
                   height: int, inv_depth: NDArray, gid: NDArray) -> None:
    """Nearest triangle along each pixel-centre ray of a pinhole camera: camera-frame ``verts`` (V, 3) (x right,
    y down, z forward), ``tris`` (T, 3); updates ``inv_depth`` (H*W,) [1/m, 1 / camera z; 0: nothing] and ``gid``
    (H*W,) triangle index where a triangle is nearer. A pixel's ray meets a triangle when the three edge planes
    through the camera centre agree in sign (exact, watertight for shared edges); the rows of tall triangles are
    bound by clipping their image box to the edge planes, spans per row bound the pixels tested."""
    dxs = (np.arange(width) - cx) / fx
    buf = np.empty((4, 8))
    for k in range(len(tris)):
        a = (verts[tris[k, 0], 0], verts[tris[k, 0], 1], verts[tris[k, 0], 2])
        b = (verts[tris[k, 1], 0], verts[tris[k, 1], 1], verts[tris[k, 1], 2])
        c = (verts[tris[k, 2], 0], verts[tris[k, 2], 1], verts[tris[k, 2], 2])
        if a[2] < NEAR_PLANE_M and b[2] < NEAR_PLANE_M and c[2] < NEAR_PLANE_M:
            continue
        w0, w1, w2 = _cross(a, b), _cross(b, c), _cross(c, a)
        det = a[0] * w1[0] + a[1] * w1[1] + a[2] * w1[2]
        # 1 / z along the ray (dx, dy, 1) is linear: n . (dx, dy, 1) / n . a, with n the plane normal
        n = _cross((b[0] - a[0], b[1] - a[1], b[2] - a[2]), (c[0] - a[0], c[1] - a[1], c[2] - a[2]))
        na = n[0] * a[0] + n[1] * a[1] + n[2] * a[2]
        if det == 0.0 or na == 0.0:
            continue  # degenerate, or the plane passes through the camera centre: seen edge-on
        s = 1.0 if det > 0 else -1.0
        iz = (n[0] / na, n[1] / na, n[2] / na)
        box = _clipped_box(a, b, c, fx, fy, cx, cy)
        u0, u1 = max(0.0, np.ceil(box[0] - 1e-6)), min(width - 1.0, np.floor(box[1] + 1e-6))
        v0, v1 = max(0.0, np.ceil(box[2] - 1e-6)), min(height - 1.0, np.floor(box[3] + 1e-6))
        if u0 > u1:
            continue
        if v1 - v0 > TALL_BOX_ROWS:
            v0, v1 = _row_range(u0, u1, v0, v1, w0, w1, w2, s, fx, fy, cx, cy, buf)
        a_z = iz[0]
        for v in range(int(v0), int(v1) + 1):
            dy = (v - cy) / fy
            lo, hi = _span(u0, u1, w0, s, dy, fx, cx)
            lo, hi = _span(lo, hi, w1, s, dy, fx, cx)
            lo, hi = _span(lo, hi, w2, s, dy, fx, cx)
            if lo > hi:
                continue
            e0, e1, e2 = w0[1] * dy + w0[2], w1[1] * dy + w1[2], w2[1] * dy + w2[2]
            iz_row = iz[1] * dy + iz[2]
            ua, ub = int(max(u0, np.floor(lo))), int(min(u1, np.ceil(hi))) + 1
            row = v * width
            inv_row, gid_row, dx_row = inv_depth[row + ua:row + ub], gid[row + ua:row + ub], dxs[ua:ub]
            for j in range(ub - ua):
                # branch-free with unsigned indices (the loop vectorises): inside all three edge planes and nearer.
                # Coplanar faces (a tyre flush with a body side): the later triangle wins, so a mesh's later parts
                # show consistently instead of fighting
                jj = np.uint64(j)
                dx = dx_row[jj]
                z_inv = a_z * dx + iz_row
                nearest = inv_row[jj]
                closer = ((s * (w0[0] * dx + e0) >= 0) & (s * (w1[0] * dx + e1) >= 0) & (s * (w2[0] * dx + e2) >= 0)
                          & (z_inv > 0) & (z_inv >= nearest * (1.0 - COPLANAR_TOLERANCE)))
                inv_row[jj] = z_inv if closer else nearest
                gid_row[jj] = k if closer else gid_row[jj]


@njit(nogil=True, cache=True)
def _pixel_ranges(inv_depth: NDArray, fx: float, fy: float, cx: float, cy: float, width: int) -> NDArray:
    """Ray lengths (H*W,) [m] from inverse camera-frame depths (H*W,) (0: inf)."""
    out = np.empty(len(inv_depth))
    for v in range(len(inv_depth) // width):
        dy = (v - cy) / fy
        for u in range(width):
            i = v * width + u
            dx = (u - cx) / fx
            out[i] = np.sqrt(dx * dx + dy * dy + 1.0) / inv_depth[i] if inv_depth[i] > 0 else np.inf
    return out


@njit(nogil=True, cache=True)
def gather_rows(table: NDArray, idx: NDArray) -> NDArray:
    """``table[idx]`` for (T, 3) ``table`` and (N,) ``idx``, zeros where ``idx`` < 0."""
    out = np.zeros((len(idx), 3), table.dtype)
    for i in range(len(idx)):
        if idx[i] >= 0:
            out[i, 0], out[i, 1], out[i, 2] = table[idx[i], 0], table[idx[i], 1], table[idx[i], 2]
    return out


def triangle_normals(mesh: Mesh) -> NDArray[np.float64]:
    """(T, 3) unit geometric normals of ``mesh`` (right-handed winding)."""
    v = mesh.vertices[mesh.triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def pinhole_depth(verts_cam: NDArray, triangles: NDArray, K: NDArray, width: int,
                  height: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Nearest triangle along each pixel-centre ray (row-major, u = col, v = row) of a pinhole camera with intrinsics
    ``K`` (3, 3): camera-frame vertices ``verts_cam`` (V, 3) (x right, y down, z forward) and ``triangles`` (T, 3).

    Returns the inverse camera-frame depth per pixel (H*W,) [1/m] (0: nothing) and the triangle index (H*W,) (-1:
    nothing).
    """
    inv_depth, tri = np.zeros(width * height), np.full(width * height, -1, np.int64)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    _raster_kernel(np.ascontiguousarray(verts_cam, np.float64), triangles, fx, fy, cx, cy, width, height, inv_depth,
                   tri)
    return inv_depth, tri


def pixel_ranges(inv_depth: NDArray, K: NDArray, width: int) -> NDArray[np.float64]:
    """Ray lengths (H*W,) [m] of the pixel-centre rays from their inverse camera-frame depths (H*W,) (0: inf)."""
    return _pixel_ranges(inv_depth, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width)


def pinhole_hits(verts_cam: NDArray, triangles: NDArray, K: NDArray, width: int,
                 height: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """`pinhole_depth` as the ray length per pixel (H*W,) [m] (inf: nothing) and the triangle index (H*W,) (-1:
    nothing)."""
    inv_depth, tri = pinhole_depth(verts_cam, triangles, K, width, height)
    return pixel_ranges(inv_depth, K, width), tri


class TriangleTable(NamedTuple):
    """Per-triangle attributes of a scene posed at one instant (the rows `raster.pinhole_depth` indexes): unit
    geometric ``normal`` (T, 3) float32 (global frame, right-handed winding), ``material`` (T,) uint8, ``albedo``
    (T, 3) float32, ``reflectivity`` (T,) float32, ``instance`` (T,) int32."""

    normal: NDArray[np.float32]
    material: NDArray[np.uint8]
    albedo: NDArray[np.float32]
    reflectivity: NDArray[np.float32]
    instance: NDArray[np.int32]


class SunGrid(NamedTuple):
    """Triangles projected along the sun direction onto the plane across it, binned into square cells.

    ``axes`` (3, 3) rows: two unit axes (a, b) of the plane and the sun direction (depth h). Grid: corner ``origin``
    (a0, b0), ``cell`` [m], ``cols`` x ``rows`` cells (cell index = col * rows + row); the triangles of cell c are the
    records ``cells[cell_start[c]:cell_start[c + 1]]``, highest first (`SUN_RECORD`); ``occupied`` (ceil(cells / 8),)
    uint8: bit c % 8 of byte c // 8 set when cell c holds any (most cells hold none: a compact first test). ``wide``
    triangles, too big to bin, are tested for every ray (records, highest first)."""

    axes: NDArray[np.float64]
    origin: tuple[float, float]
    cell: float
    cols: int
    rows: int
    cell_start: NDArray[np.int64]
    cells: NDArray[np.float64]
    wide: NDArray[np.float64]
    occupied: NDArray[np.uint8]


# One projected triangle per row of SunGrid.cells/wide (copied per cell: a shadow ray reads its cell's records in
# sequence): its highest vertex z [m] (inf unless the sun is above the horizon), bounds (a_min, a_max, b_min, b_max),
# winding +-1, corners (a, b) x 3, depth plane (h = p0 a + p1 b + p2).
SUN_RECORD = ("z_top", "a_min", "a_max", "b_min", "b_max", "winding", "a0", "b0", "a1", "b1", "a2", "b2", "p0", "p1",
              "p2", "unused")
SUN_CELL_M = 1.0  # grid cell size along the plane across the sun
MAX_SUN_CELLS = 4_000_000  # cells grow beyond SUN_CELL_M when the scene is larger
MAX_MOVING_SUN_CELLS = 65_536  # the moving actors' grid (built per exposure, spread along the street): fewer cells
WIDE_CELLS = 50_000  # triangles larger than this many cells are tested for every ray instead of binned


def sun_axes(sun: NDArray) -> NDArray[np.float64]:
    """(3, 3) rows: two unit axes across the unit ``sun`` direction (3,) and ``sun`` itself (right-handed)."""
    s = np.asarray(sun, np.float64)
    helper = np.array([1.0, 0.0, 0.0]) if abs(s[2]) > 0.9 else np.array([0.0, 0.0, 1.0])
    a = np.cross(helper, s)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(s, a), s])


@njit(nogil=True, cache=True)
def _sun_records(vertices: NDArray, triangles: NDArray, axes: NDArray, sun_up: bool, records: NDArray,
                 corners: NDArray, area2: NDArray) -> None:
    """Per triangle (T, 3) over ``vertices`` (V, 3): its `SUN_RECORD` row of ``records`` (T, 16), its corners (a, b)
    ``corners`` (T, 3, 2) on the plane across the sun (``axes`` (3, 3) rows: a, b, sun) and twice its signed
    projected area ``area2`` (T,)."""
    for t in range(len(triangles)):
        q = np.empty((3, 3))
        z_top = -np.inf
        for k in range(3):
            v = triangles[t, k]
            px, py, pz = vertices[v, 0], vertices[v, 1], vertices[v, 2]
            z_top = max(z_top, pz)
            for r in range(3):
                q[k, r] = axes[r, 0] * px + axes[r, 1] * py + axes[r, 2] * pz
        e1 = (q[1, 0] - q[0, 0], q[1, 1] - q[0, 1], q[1, 2] - q[0, 2])
        e2 = (q[2, 0] - q[0, 0], q[2, 1] - q[0, 1], q[2, 2] - q[0, 2])
        n = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
        records[t, 0] = z_top if sun_up else np.inf
        records[t, 1], records[t, 2] = min(q[0, 0], q[1, 0], q[2, 0]), max(q[0, 0], q[1, 0], q[2, 0])
        records[t, 3], records[t, 4] = min(q[0, 1], q[1, 1], q[2, 1]), max(q[0, 1], q[1, 1], q[2, 1])
        records[t, 5] = np.sign(n[2])
        for k in range(3):
            records[t, 6 + 2 * k], records[t, 7 + 2 * k] = q[k, 0], q[k, 1]
            corners[t, k, 0], corners[t, k, 1] = q[k, 0], q[k, 1]
        # the plane n . (a, b, h) = n . corner0 solved for h
        div = n[2] if n[2] != 0 else 1.0
        records[t, 12] = -n[0] / div
        records[t, 13] = -n[1] / div
        records[t, 14] = (n[0] * q[0, 0] + n[1] * q[0, 1] + n[2] * q[0, 2]) / div
        records[t, 15] = 0.0
        area2[t] = n[2]


def sun_grid(vertices: NDArray, triangles: NDArray, sun: NDArray, max_cells: int = MAX_SUN_CELLS) -> SunGrid:
    """A `SunGrid` of the triangles (T, 3) over ``vertices`` (V, 3) (global frame) for the unit ``sun`` (3,) (T may
    be 0: a grid that blocks nothing), with cells of `SUN_CELL_M` or larger, at most about ``max_cells``."""
    axes = sun_axes(sun)
    n = len(triangles)
    records, corners, area2 = np.empty((n, len(SUN_RECORD))), np.empty((n, 3, 2)), np.empty(n)
    _sun_records(np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(triangles, np.int64), axes,
                 bool(sun[2] > 0), records, corners, area2)
    order = np.argsort(-records[:, 0], kind="stable")
    order = order[records[order, 5] != 0]  # edge-on triangles never block
    wide = np.abs(area2[order]) / 2 > WIDE_CELLS * SUN_CELL_M**2
    binned = order[~wide]
    if len(binned):
        lo = np.array([records[binned, 1].min(), records[binned, 3].min()])
        hi = np.array([records[binned, 2].max(), records[binned, 4].max()])
    else:
        lo = hi = np.zeros(2)
    cell = max(SUN_CELL_M, float(np.sqrt((hi - lo).prod() / max_cells)))
    cols, rows = int((hi[0] - lo[0]) // cell) + 1, int((hi[1] - lo[1]) // cell) + 1
    cell_start, cell_tris = _bin_triangles(corners, binned, float(lo[0]), float(lo[1]), cell, cols, rows)
    return SunGrid(axes, (float(lo[0]), float(lo[1])), float(cell), int(cols), int(rows), cell_start,
                   records[cell_tris], np.ascontiguousarray(records[order[wide]]),
                   np.packbits(np.diff(cell_start) > 0, bitorder="little"))


@njit(nogil=True, cache=True, inline="always")
def _strip_span(corners: NDArray, t: int, b0: float, b1: float) -> tuple[float, float]:
    """The a-range (a_min, a_max) of projected triangle ``t`` within the strip b0 <= b <= b1 (empty: a_min > a_max)."""
    a_min, a_max = np.inf, -np.inf
    for k in range(3):
        pa, pb = corners[t, k, 0], corners[t, k, 1]
        qa, qb = corners[t, (k + 1) % 3, 0], corners[t, (k + 1) % 3, 1]
        if max(pb, qb) < b0 or min(pb, qb) > b1:
            continue
        if pb == qb:
            a_min, a_max = min(a_min, pa, qa), max(a_max, pa, qa)
            continue
        for bb in (max(min(pb, qb), b0), min(max(pb, qb), b1)):  # the edge clipped to the strip
            a = pa + (qa - pa) * (bb - pb) / (qb - pb)
            a_min, a_max = min(a_min, a), max(a_max, a)
    return a_min, a_max


@njit(nogil=True, cache=True, inline="always")
def _row_cells(corners: NDArray, t: int, r: int, a0: float, b0: float, cell: float,
               cols: int) -> tuple[int, int]:
    """Columns (c0, c1) of row ``r`` that projected triangle ``t`` may overlap (conservative; none: c0 > c1)."""
    margin = 1e-9 * cell
    a_min, a_max = _strip_span(corners, t, b0 + r * cell - margin, b0 + (r + 1) * cell + margin)
    if a_min > a_max:
        return 0, -1
    return max(0, int((a_min - margin - a0) // cell)), min(cols - 1, int((a_max + margin - a0) // cell))


@njit(nogil=True, cache=True, inline="always")
def _rows_of(corners: NDArray, t: int, b0: float, cell: float, rows: int) -> tuple[int, int]:
    """Rows (r0, r1) that projected triangle ``t`` spans."""
    b_lo = min(corners[t, 0, 1], corners[t, 1, 1], corners[t, 2, 1])
    b_hi = max(corners[t, 0, 1], corners[t, 1, 1], corners[t, 2, 1])
    return max(0, int((b_lo - b0) // cell)), min(rows - 1, int((b_hi - b0) // cell))


@njit(nogil=True, cache=True)
def _bin_triangles(corners: NDArray, order: NDArray, a0: float, b0: float, cell: float, cols: int,
                   rows: int) -> tuple[NDArray[np.int64], NDArray[np.int32]]:
    """Cell lists of the triangles ``order`` (kept in that order within each cell): (cols*rows + 1,) starts and the
    concatenated triangle indices. Each triangle goes into the cells it may overlap, found row by row."""
    start = np.zeros(cols * rows + 1, np.int64)
    for t in order:
        r0, r1 = _rows_of(corners, t, b0, cell, rows)
        for r in range(r0, r1 + 1):
            c0, c1 = _row_cells(corners, t, r, a0, b0, cell, cols)
            for c in range(c0, c1 + 1):
                start[c * rows + r + 1] += 1
    start = np.cumsum(start)
    fill = start[:-1].copy()
    out = np.empty(start[-1], np.int32)
    for t in order:
        r0, r1 = _rows_of(corners, t, b0, cell, rows)
        for r in range(r0, r1 + 1):
            c0, c1 = _row_cells(corners, t, r, a0, b0, cell, cols)
            for c in range(c0, c1 + 1):
                out[fill[c * rows + r]] = t
                fill[c * rows + r] += 1
    return start, out


@njit(nogil=True, cache=True, inline="always")
def _blocks(records: NDArray, e: int, pa: float, pb: float, ph: float) -> bool:
    """Whether the projected triangle of record ``e`` covers the point (pa, pb) beyond depth ``ph`` towards the sun."""
    r = records
    if pa < r[e, 1] or pa > r[e, 2] or pb < r[e, 3] or pb > r[e, 4]:
        return False
    w = r[e, 5]
    a0, b0 = r[e, 6] - pa, r[e, 7] - pb
    a1, b1 = r[e, 8] - pa, r[e, 9] - pb
    a2, b2 = r[e, 10] - pa, r[e, 11] - pb
    if w * (a0 * b1 - b0 * a1) < 0 or w * (a1 * b2 - b1 * a2) < 0 or w * (a2 * b0 - b2 * a0) < 0:
        return False
    return r[e, 12] * pa + r[e, 13] * pb + r[e, 14] > ph


@njit(nogil=True, cache=True, inline="always")
def _any_blocks(records: NDArray, lo: int, hi: int, pa: float, pb: float, ph: float, pz: float) -> bool:
    """Whether a record in ``lo:hi`` (highest first) blocks the ray from (pa, pb, ph) at height ``pz``."""
    for e in range(lo, hi):
        if records[e, 0] <= pz:  # the ray rises above all that is left
            return False
        if _blocks(records, e, pa, pb, ph):
            return True
    return False


class SunCells(NamedTuple):
    """The cell layout of a `SunGrid` as a shadow ray's test reads it (`sun_cells`): scalars only, free to pass per
    ray. The grid's arrays go to `blocked_at` on their own, taken out of the grid once by the caller: an array read
    from a tuple inside a per-ray loop costs reference counting on every access."""

    a0: float  # grid corner along the plane's axis a [m]
    b0: float  # grid corner along its axis b [m]
    inv_cell: float  # 1 / cell size [1/m]
    cols: int  # cells along a
    rows: int  # cells along b (cell index = col * rows + row)


@njit(nogil=True, cache=True, inline="always")
def sun_cells(grid: SunGrid) -> SunCells:
    """The `SunCells` of ``grid``."""
    return SunCells(grid.origin[0], grid.origin[1], 1.0 / grid.cell, grid.cols, grid.rows)


@njit(nogil=True, cache=True, inline="always")
def blocked_at(layout: SunCells, axes: NDArray, cell_start: NDArray, cells: NDArray, wide: NDArray, occupied: NDArray,
               px: float, py: float, pz: float, hint: int) -> tuple[bool, int]:
    """`point_blocked` on a `SunGrid` given as its `SunCells` ``layout`` and its arrays (``axes``, ``cell_start``,
    ``cells``, ``wide``, ``occupied``), taken out of the grid once by the caller."""
    pa = axes[0, 0] * px + axes[0, 1] * py + axes[0, 2] * pz
    pb = axes[1, 0] * px + axes[1, 1] * py + axes[1, 2] * pz
    ph = axes[2, 0] * px + axes[2, 1] * py + axes[2, 2] * pz
    if hint >= 0 and _blocks(cells, hint, pa, pb, ph):
        return True, hint
    if len(wide) and _any_blocks(wide, 0, len(wide), pa, pb, ph, pz):
        return True, hint
    # the triangles are binned with a margin: a product instead of the quotient may only pick an equally good cell
    fa, fb = (pa - layout.a0) * layout.inv_cell, (pb - layout.b0) * layout.inv_cell
    if 0.0 <= fa < layout.cols and 0.0 <= fb < layout.rows:
        c = int(fa) * layout.rows + int(fb)
        if not (occupied[c >> 3] >> (c & 7)) & 1:
            return False, hint
        for e in range(cell_start[c], cell_start[c + 1]):
            if cells[e, 0] <= pz:  # the ray rises above all that is left
                break
            if _blocks(cells, e, pa, pb, ph):
                return True, e
    return False, hint


@njit(nogil=True, cache=True, inline="always")
def point_blocked(grid: SunGrid, px: float, py: float, pz: float, hint: int) -> tuple[bool, int]:
    """Whether the ray from the global point (px, py, pz) towards the sun meets a triangle of ``grid``, and the record
    of ``grid.cells`` that blocked it (else ``hint``). ``hint`` (-1: none) is tested first: the blocker of a nearby
    ray, which usually blocks this one too (any blocker decides, so the answer is the same without it)."""
    return blocked_at(sun_cells(grid), grid.axes, grid.cell_start, grid.cells, grid.wide, grid.occupied, px, py, pz,
                      hint)


@njit(nogil=True, cache=True)
def _sun_blocked_kernel(grid: SunGrid, points: NDArray, out: NDArray) -> None:
    hint = -1
    layout = sun_cells(grid)
    axes, cell_start, cells, wide, occupied = grid.axes, grid.cell_start, grid.cells, grid.wide, grid.occupied
    for i in range(len(points)):
        out[i], hint = blocked_at(layout, axes, cell_start, cells, wide, occupied, float(points[i, 0]),
                                  float(points[i, 1]), float(points[i, 2]), hint)


def sun_blocked(grid: SunGrid, points: NDArray) -> NDArray[np.bool_]:
    """(N,) whether the ray from each global point (N, 3) towards the sun meets a triangle of ``grid``."""
    out = np.empty(len(points), bool)
    _sun_blocked_kernel(grid, points, out)
    return out
