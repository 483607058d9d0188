"""LiDAR beams in the global frame: every return of a scan, plus the beams that returned nothing.

Snow and rain act on beams, not on points: a particle can block, weaken or replace the echo of a beam that hit
something, and it can create an echo on a beam that hit nothing (open sky, far ground). `beams_from_scan` turns a
`LidarScan` into `Beams`, each with its own origin, direction and firing time in the global frame (the sensor moves
during a 50 ms sweep and the particles fall, so both are evaluated per beam):

- every point is a beam from the sensor position at its firing time (`LidarScan` keeps the points ego-motion
  compensated to the scan timestamp, so a point's global position is ``T_global_lidar @ p``) to the point;
- beams without a return come, in order of preference, from
  1. explicit `NoReturnBeams` (e.g. kept by a renderer),
  2. the sensor's firing grid (`weatheralign.sensors.LidarModel.firing_pattern`, for datasets that store per-point
     firing columns, the synthetic world's extras; see `synthetic_columns`): the (ring, column) cells that have no
     point; each such beam fires at its
     grid time from the sensor position at that time, along the grid direction,
  3. a reconstruction from the ring/azimuth structure of a real scan (nuScenes, Seeing Through Fog, KITTI):
     per ring, azimuth gaps wider than ``gap_factor`` x the median azimuth step are filled with beams at that step,
     at the ring's median elevation; firing times follow the nuScenes convention of `derived_time_offsets`
     (clockwise from the ego's left, the sweep ending at the scan timestamp). A scan cropped to a camera's field of
     view (the shared KITTI sample) is only filled between a ring's own points: where a ring ends, the crop cannot be
     told from the sky (pass explicit beams or ``reconstruct=False`` for such scans if that matters).

Scans without per-point times (Seeing Through Fog, KITTI) get times from their azimuth by the same convention; their
ego is static (global = sensor frame), so their beams all start at the sensor origin.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from weatheralign.data.frame import LidarScan
from weatheralign.data.nuscenes import derived_time_offsets, read_point_extras
from weatheralign.geometry import invert
from weatheralign.lidar.ground_plane import GroundPlane, fit_ground_plane

if TYPE_CHECKING:
    from weatheralign.sensors import FiringPattern, LidarModel

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

DEFAULT_GAP_FACTOR = 1.5
"""Azimuth gaps wider than this many median steps hold beams without a return."""

MIN_RING_POINTS = 16
"""Rings with fewer points are not reconstructed (their elevation and azimuth step are unreliable)."""

MIN_AZIMUTH_STEP = 2 * math.pi / 10_000
"""Floor of the reconstructed azimuth step [rad]: no spinning LiDAR fires more than ~4,500 times per turn, and
near-duplicate points (a few µrad apart) must not turn one gap into a million beams."""


@dataclass(frozen=True, eq=False)
class Beams:
    """LiDAR beams in the global frame, each at its own firing time.

    Attributes:
        origins: (N, 3) float64 sensor position at each beam's firing time [m], global frame.
        directions: (N, 3) float64 unit beam directions, global frame.
        times: (N,) float64 absolute firing times [s].
        lengths: (N,) float64 measured range for beams with a return, ``max_range`` for the others [m] (or the range
            of a surface under the detector floor inferred there, `with_faint_surfaces`).
        has_return: (N,) bool, whether the beam produced a point in clear weather.
        intensity0: (N,) float64 clear intensity on the 0..255 scale (0 for beams without return; for an inferred
            faint surface its assumed clear intensity, under the floor).
        ring: (N,) float32 ring index, exactly as in the scan's ring column.
        point_index: (N,) int64 row of the beam's point in the scan, -1 for beams without return.
        divergence: full beam divergence angle [rad]; the beam radius grows as ``s tan(divergence / 2)``.
        max_range: the sensor's maximum range [m].
    """

    origins: F64
    directions: F64
    times: F64
    lengths: F64
    has_return: NDArray[np.bool_]
    intensity0: F64
    ring: F32
    point_index: I64
    divergence: float
    max_range: float

    def __post_init__(self) -> None:
        n = self.origins.shape[0]
        for name, shape in (("origins", (n, 3)), ("directions", (n, 3)), ("times", (n,)), ("lengths", (n,)),
                            ("has_return", (n,)), ("intensity0", (n,)), ("ring", (n,)), ("point_index", (n,))):
            arr = getattr(self, name)
            if not isinstance(arr, np.ndarray) or arr.shape != shape:
                raise ValueError(f"Beams.{name}: expected an array of shape {shape}, got "
                                 f"{getattr(arr, 'shape', type(arr).__name__)}")
        if not (math.isfinite(self.divergence) and 0.0 <= self.divergence < 0.5):
            raise ValueError(f"Beams.divergence = {self.divergence!r}; expected a full angle in [0, 0.5) rad")
        if not (math.isfinite(self.max_range) and self.max_range > 0.0):
            raise ValueError(f"Beams.max_range = {self.max_range!r}; expected a finite range > 0 m")

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    @property
    def num_returns(self) -> int:
        """Number of beams with a clear-weather return."""
        return int(np.count_nonzero(self.has_return))

    def select(self, mask: NDArray) -> Beams:
        """The beams where ``mask`` (N,) bool (or an index array) selects."""
        return Beams(self.origins[mask], self.directions[mask], self.times[mask], self.lengths[mask],
                     self.has_return[mask], self.intensity0[mask], self.ring[mask], self.point_index[mask],
                     self.divergence, self.max_range)

    def radius(self, s: NDArray | float) -> F64:
        """Beam radius [m] at axial distances ``s`` [m] (any shape)."""
        return np.asarray(s, dtype=np.float64) * math.tan(0.5 * self.divergence)


@dataclass(frozen=True, eq=False)
class NoReturnBeams:
    """Beams of a sweep that returned nothing, in the sensor's own frame at their firing times.

    Attributes:
        directions: (K, 3) unit directions in the LiDAR frame at each beam's firing time.
        time_offsets: (K,) firing times relative to the scan timestamp [s].
        ring: (K,) ring index of each beam (the scan's ring convention).
    """

    directions: F64
    time_offsets: F64
    ring: F32

    def __post_init__(self) -> None:
        k = self.directions.shape[0]
        if self.directions.shape != (k, 3) or self.time_offsets.shape != (k,) or self.ring.shape != (k,):
            raise ValueError(f"NoReturnBeams: expected directions (K, 3), time_offsets (K,), ring (K,); got "
                             f"{self.directions.shape}, {self.time_offsets.shape}, {self.ring.shape}")

    def __len__(self) -> int:
        return int(self.directions.shape[0])


def _empty_no_return() -> NoReturnBeams:
    return NoReturnBeams(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.float32))


# ------------------------------------------------------------------------------------------------ sensor motion


def _pose_knots(scan: LidarScan, times: F64, num_knots: int) -> tuple[F64, F64]:
    """Knot times (M,) spread over ``times`` (plus every pose time inside) and the exact ``T_global_lidar``
    (M, 4, 4) at each."""
    t_lo, t_hi = float(times.min()), float(times.max())
    pose_times = np.asarray(scan.pose_times, dtype=np.float64)
    knots = np.unique(np.concatenate([np.linspace(t_lo, t_hi, max(num_knots, 2)),
                                      pose_times[(pose_times > t_lo) & (pose_times < t_hi)]]))
    return knots, scan.global_poses_at(knots) @ scan.T_ego_lidar


def sensor_origins_at(scan: LidarScan, times: NDArray, num_knots: int = 64) -> F64:
    """Sensor origins (K, 3) [m] at absolute ``times`` (K,) [s]: the translation part of `sensor_poses_at`."""
    times = np.asarray(times, dtype=np.float64)
    if scan.poses is None or scan.pose_times is None or len(times) == 0:
        return np.broadcast_to(scan.T_global_lidar[:3, 3], (len(times), 3)).copy()
    knots, T_knots = _pose_knots(scan, times, num_knots)
    return np.stack([np.interp(times, knots, T_knots[:, c, 3]) for c in range(3)], axis=1)


def sensor_poses_at(scan: LidarScan, times: NDArray, num_knots: int = 64) -> tuple[F64, F64]:
    """Sensor origins (K, 3) [m] and rotations ``R_global_lidar`` (K, 3, 3) at absolute ``times`` (K,) [s].

    Poses come from the scan's ego poses (`LidarScan.global_poses_at`), evaluated exactly at ``num_knots`` times
    spread over ``times`` (plus every pose time inside) and interpolated linearly in between (the pose path is
    smooth between pose times; the error is far below a millimetre over a 50 ms sweep). Without poses the sensor is
    static at ``scan.T_global_lidar``.
    """
    times = np.asarray(times, dtype=np.float64)
    k = len(times)
    if scan.poses is None or scan.pose_times is None or k == 0:
        T = scan.T_global_lidar
        return np.broadcast_to(T[:3, 3], (k, 3)).copy(), np.broadcast_to(T[:3, :3], (k, 3, 3)).copy()
    knots, T_knots = _pose_knots(scan, times, num_knots)
    origins = np.stack([np.interp(times, knots, T_knots[:, c, 3]) for c in range(3)], axis=1)
    rot = np.empty((k, 3, 3))
    for a in range(3):
        for b in range(3):
            rot[:, a, b] = np.interp(times, knots, T_knots[:, a, b])
    # re-orthonormalise the interpolated rotations (columns through QR keep them proper to ~1e-16)
    q, r = np.linalg.qr(rot)
    sign = np.sign(np.einsum("kii->ki", r))
    sign[sign == 0] = 1.0
    return origins, q * sign[:, None, :]


def scan_times(scan: LidarScan) -> F64:
    """(N,) absolute firing time [s] of every point: the scan's own ``time_offsets``, else derived from azimuth with
    the nuScenes convention (`derived_time_offsets`)."""
    if scan.time_offsets is not None:
        return scan.point_times()
    return scan.timestamp + derived_time_offsets(scan.points, scan.T_ego_lidar).astype(np.float64)


_KEY_MULTIPLIERS = np.array([0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xD6E8FEB86659FD93,
                              0xA0761D6478BD642F], dtype=np.uint64)


KEY_DIRECTION_QUANTUM = 2.0 ** -16
"""Grid of the direction components in a beam's noise key (15 µrad, far below any beam spacing): a direction computed
a few ULPs differently (a reconstructed beam without return: measured up to 8.9e-16 apart between processes on the
same input) keeps its key, so its noise draws, and the copy's bytes, do not change from run to run."""


def detector_noise_keys(times: NDArray, directions: NDArray, ring: NDArray) -> NDArray[np.uint64]:
    """(B,) the detector-noise stream of each beam (`weatheralign.medium.field.normal_pair` draws from it): the bits of
    its firing time [s] (B,), its unit direction (B, 3) rounded to `KEY_DIRECTION_QUANTUM` and its ring (B,), each
    times an odd constant, summed (mod 2^64). A beam reads the same noise in every run and condition (the sensor's
    noise, not the weather's; a scan simulated alone or with its sweeps alike), and beams differ in one of them."""
    quantised = np.rint(np.ascontiguousarray(directions, dtype=np.float64) / KEY_DIRECTION_QUANTUM).astype(np.int64)
    parts = np.column_stack([np.ascontiguousarray(times, dtype=np.float64).view(np.uint64),
                             quantised.view(np.uint64).reshape(-1, 3),
                             np.asarray(ring).astype(np.uint64)])
    return (parts * _KEY_MULTIPLIERS).sum(axis=1, dtype=np.uint64)


def point_ranges(points: NDArray[np.float32], origins: NDArray | None) -> F64:
    """(N,) float64 range of each point (N, >=3) from its beam origin (N, 3) or the frame origin (None) [m],
    computed as the fog kernel does (float64 difference, then the Euclidean norm)."""
    d = np.asarray(points)[:, :3].astype(np.float64)
    if origins is not None:
        o = np.asarray(origins, dtype=np.float64)
        if o.shape != d.shape:
            raise ValueError(f"point_ranges: origins {o.shape} must match points ({len(d)}, 3)")
        d = d - o
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])


def beam_origins(scan: LidarScan, frame: str = "global") -> F64 | None:
    """(N, 3) position [m] of the sensor at each point's firing time: the origin of the point's beam.

    ``frame="global"``: in the global frame (every scan; a static sensor gives ``T_global_lidar``'s position);
    ``frame="scan"``: in the scan's own frame, or None where every beam starts at the frame origin (no per-point
    times or no ego poses). Poses come from `sensor_poses_at` (exact at knots, linear in between); the exact
    per-point definition is `LidarScan.beam_origins` (slow, the tests' oracle). The one fast beam-origin function
    of fog, snow/rain and the calibration.
    """
    moving = scan.poses is not None and scan.pose_times is not None and scan.time_offsets is not None
    if frame == "scan":
        if not moving or len(scan.points) == 0:
            return None
        origins = sensor_origins_at(scan, scan.point_times())
        T = invert(scan.T_global_lidar)
        return origins @ T[:3, :3].T + T[:3, 3]
    if frame != "global":
        raise ValueError(f"beam_origins: frame = {frame!r}; expected 'global' or 'scan'")
    times = scan_times(scan)
    if not moving:
        return np.broadcast_to(scan.T_global_lidar[:3, 3], (len(times), 3)).copy()
    return sensor_origins_at(scan, times)


# ------------------------------------------------------------------------------------------------ beams without return


def synthetic_columns(scan: LidarScan) -> NDArray[np.int16] | None:
    """The synthetic world's firing column (N,) of every point, read from the world's extras next to ``scan.path``
    (``<dataroot>/extras/LIDAR_TOP/<stem>.npy``), or None where there are none (real data, aggregated sweeps)."""
    path = scan.path
    if path is None or scan.sweep_index is not None:
        return None
    path = Path(path)
    if len(path.parts) < 3:
        return None
    dataroot = path.parents[2]
    try:
        rel = str(path.relative_to(dataroot))
    except ValueError:  # the scan is not inside a dataroot
        return None
    records = read_point_extras(dataroot, rel)
    if records is None:
        return None
    if records.dtype.names is None or "column" not in records.dtype.names or len(records) != len(scan.points):
        return None
    return np.asarray(records["column"], dtype=np.int16)


def grid_no_return_beams(scan: LidarScan, columns: NDArray, pattern: FiringPattern) -> NoReturnBeams:
    """The cells of a firing grid that produced no point: ``pattern`` is the sensor's grid
    (`weatheralign.sensors.LidarModel.firing_pattern`), ``columns`` (N,) the firing column of each point.

    Raises:
        ValueError: columns/rings outside the grid (the scan was not recorded with this sensor's grid).
    """
    columns = np.asarray(columns).astype(np.int64)
    if columns.shape != (len(scan.points),):
        raise ValueError(f"columns: expected shape ({len(scan.points)},), got {columns.shape}")
    rings = np.asarray(pattern.ring, dtype=np.int64)
    n_rings = int(rings.max()) + 1
    n_cols = int(np.asarray(pattern.column).max()) + 1
    point_rings = scan.points[:, 4].astype(np.int64)
    if len(columns) and (columns.min() < 0 or columns.max() >= n_cols or point_rings.min() < 0
                         or point_rings.max() >= n_rings):
        raise ValueError(f"{scan.path or 'scan'}: columns/rings outside the sensor's firing grid ({n_rings} rings x "
                         f"{n_cols} columns): the dataset's LiDAR model does not describe this scan")
    occupied = np.zeros(n_rings * n_cols, dtype=bool)
    occupied[columns * n_rings + point_rings] = True
    cell = np.asarray(pattern.column, dtype=np.int64) * n_rings + rings
    missing = np.flatnonzero(~occupied[cell])
    return NoReturnBeams(np.asarray(pattern.directions, dtype=np.float64)[missing],
                         np.asarray(pattern.time_offsets, dtype=np.float64)[missing],
                         rings[missing].astype(np.float32))


def _covered_arc(az: F64, bin_deg: float = 1.0, full_fraction: float = 0.9) -> tuple[float, float] | None:
    """The azimuth arc ``(start, width)`` [rad] covered by a cropped scan, or None for a 360° scan (at least
    ``full_fraction`` of the ``bin_deg`` azimuth bins hold a point)."""
    n_bins = int(round(360.0 / bin_deg))
    idx = np.floor(np.mod(az, 2 * np.pi) / (2 * np.pi) * n_bins).astype(np.int64) % n_bins
    filled = np.zeros(n_bins, dtype=bool)
    filled[idx] = True
    if filled.mean() >= full_fraction:
        return None
    # the largest circular run of empty bins is outside the scan
    doubled = np.concatenate([~filled, ~filled])
    best_len, best_end, run = 0, 0, 0
    for i, empty in enumerate(doubled):
        run = run + 1 if empty else 0
        if run > best_len and run <= n_bins:
            best_len, best_end = run, i
    start_bin = (best_end + 1) % n_bins
    width_bins = n_bins - best_len
    # tighten to the actual extreme azimuths of the points
    rel = np.mod(az - start_bin * 2 * np.pi / n_bins, 2 * np.pi)
    inside = rel <= (width_bins + 1) * 2 * np.pi / n_bins
    lo = float(rel[inside].min()) if inside.any() else 0.0
    hi = float(rel[inside].max()) if inside.any() else 0.0
    return float(start_bin * 2 * np.pi / n_bins + lo), hi - lo


def reconstruct_no_return_beams(scan: LidarScan, *, gap_factor: float = DEFAULT_GAP_FACTOR,
                                min_ring_points: int = MIN_RING_POINTS) -> NoReturnBeams:
    """Beams without return of a real scan, reconstructed from its ring/azimuth grid (see the module docstring).

    Per ring (only the reference sweep of an aggregated scan), the points' directions from their beam origins give
    azimuths; gaps wider than ``gap_factor`` x the scan's median azimuth step get ``round(gap / step) - 1`` evenly
    spaced beams at the ring's median elevation. A 360° scan also fills the gap across ±π; a cropped scan (less than
    90 % of the 1° azimuth bins hold a point) fills only between a ring's own points. Rings with fewer than
    ``min_ring_points`` points are skipped. Directions are in the scan frame's orientation (the ego's rotation
    during the sweep is neglected for these beams); times follow `derived_time_offsets`.
    """
    pts = scan.points
    keep = np.ones(len(pts), dtype=bool) if scan.sweep_index is None else scan.sweep_index == 0
    idx = np.flatnonzero(keep)
    if len(idx) < min_ring_points:
        return _empty_no_return()
    p = pts[idx, :3].astype(np.float64)
    T_lg = invert(scan.T_global_lidar)
    o = beam_origins(scan)[idx] @ T_lg[:3, :3].T + T_lg[:3, 3]
    v = p - o
    r = np.linalg.norm(v, axis=1)
    ok = r > 1e-6
    v, r, ring = v[ok], r[ok], pts[idx[ok], 4]
    az = np.arctan2(v[:, 1], v[:, 0])
    el = np.arcsin(np.clip(v[:, 2] / r, -1.0, 1.0))
    arc = _covered_arc(az)
    ring_ids, inverse, counts = np.unique(ring, return_inverse=True, return_counts=True)
    # the median azimuth step over all rings (every laser of a spinning LiDAR fires at the same azimuth rate)
    order = np.lexsort((az, inverse))
    az_sorted, ring_sorted = az[order], inverse[order]
    same = ring_sorted[1:] == ring_sorted[:-1]
    steps = np.diff(az_sorted)[same]
    steps = steps[steps > 1e-7]
    if not len(steps):
        return _empty_no_return()
    step = max(float(np.median(steps)), MIN_AZIMUTH_STEP)
    out_az, out_el, out_ring = [], [], []
    starts = np.concatenate([[0], np.cumsum(counts)])
    for k, ring_value in enumerate(ring_ids):
        if counts[k] < min_ring_points:
            continue
        sel = order[starts[k]:starts[k + 1]]
        a = az[sel]
        near = r[sel] > 2.0
        elev = float(np.median(el[sel][near] if near.sum() >= min_ring_points else el[sel]))
        if arc is None:
            left = a
            right = np.concatenate([a[1:], [a[0] + 2 * np.pi]])
        else:  # cropped scan: only gaps between a ring's own points (its ends may be the crop, not the sky)
            start, _ = arc
            rel = np.sort(np.mod(a - start, 2 * np.pi))
            left = rel[:-1] + start
            right = rel[1:] + start
        gap = right - left
        big = gap > gap_factor * step
        n_fill = np.maximum(np.rint(gap[big] / step).astype(np.int64) - 1, 1)
        base = np.repeat(left[big], n_fill)
        inc = np.repeat(gap[big] / (n_fill + 1), n_fill)
        j = np.arange(int(n_fill.sum())) - np.repeat(np.cumsum(n_fill) - n_fill, n_fill) + 1
        out_az.append(base + j * inc)
        out_el.append(np.full(int(n_fill.sum()), elev))
        out_ring.append(np.full(int(n_fill.sum()), ring_value, dtype=np.float32))
    if not out_az:
        return _empty_no_return()
    a = np.concatenate(out_az)
    e = np.concatenate(out_el)
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
    offsets = derived_time_offsets(d.astype(np.float32), scan.T_ego_lidar).astype(np.float64)
    # the directions above are in the scan frame's orientation: express them in the LiDAR frame at firing time
    if scan.poses is not None and scan.pose_times is not None and scan.time_offsets is not None:
        _, R_fire = sensor_poses_at(scan, scan.timestamp + offsets)
        d_global = d @ scan.T_global_lidar[:3, :3].T
        d = np.einsum("kji,kj->ki", R_fire, d_global)
    return NoReturnBeams(d, offsets, np.concatenate(out_ring))


# ------------------------------------------------------------------------------------------------ beams


MAX_FAINT_RUN = 8
"""`with_faint_surfaces`: at most this many consecutive beams without return between two returns of one surface."""

FAINT_RANGE_TOLERANCE = 0.05
"""`with_faint_surfaces`: the two returns' ranges agree within this share of their mean."""

FAINT_INTENSITY_FACTOR = 3.0
"""`with_faint_surfaces`: both returns at most this many times the detector floor (a surface at the floor)."""


def with_faint_surfaces(beams: Beams, noise_floor: float | None,
                        floor_scale: Callable[[F64], F64] | None = None) -> Beams:
    """``beams`` where runs of beams without return lie on a surface too faint to be detected: a surface under the
    detector floor is still there, and its echo, though undetectable, is the strongest a strongest-return receiver
    gets, so weaker weather echoes behind or beside it are never reported (measured against the reference's exact
    process on 12 of its rain frames: treated as open sky, such beams raise the isolated rain echoes per open beam
    by 12 %; with the true surfaces by 0.5 %; this rule recovers about half of the difference).

    In each ring, in firing order (ring, then time), a run of at most `MAX_FAINT_RUN` beams without return between
    two returns whose ranges agree within `FAINT_RANGE_TOLERANCE` of their mean and whose clear intensities are both
    at most `FAINT_INTENSITY_FACTOR` x ``noise_floor`` (0..255 scale; the surface is at the floor, so some of its
    beams fall under it), spanning no more than 1.5 x the ring's median beam spacing per step, gets the range
    interpolated between them and the clear intensity ``noise_floor / 2`` (the mean of a uniform prior on
    ``(0, floor)``). On the synthetic reference's clear frames this finds 46 % of the beams whose surface was under
    the floor (the rest are long runs: far dark ground) and puts no open-sky beam on a surface (14 of 6,493 beams).
    The beams keep ``has_return`` False: they report nothing unless the weather puts a detectable echo on them.
    None or a zero floor: ``beams`` unchanged. ``floor_scale``: the floor's factor at a range (a raw-power
    detector's, `weatheralign.sensors.LidarModel.floor_scale`), so that both tests use the floor at the surface's
    range; None: a constant floor.
    """
    if noise_floor is None or noise_floor <= 0.0 or len(beams) < 3:
        return beams
    order = np.lexsort((beams.times, beams.ring))
    ring, ret = beams.ring[order], beams.has_return[order]
    d = beams.directions[order]
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", d[1:], d[:-1]), -1.0, 1.0))
    pairs = (ring[1:] == ring[:-1]) & ret[1:] & ret[:-1]
    if not pairs.any():
        return beams
    step = float(np.median(angle[pairs]))
    idx = np.flatnonzero(ret)
    a, b = idx[:-1], idx[1:]
    run = b - a - 1
    r_a, r_b = beams.lengths[order][a], beams.lengths[order][b]
    span = np.arccos(np.clip(np.einsum("ij,ij->i", d[a], d[b]), -1.0, 1.0))
    bright = np.maximum(beams.intensity0[order][a], beams.intensity0[order][b])
    fill = ((run >= 1) & (run <= MAX_FAINT_RUN) & (ring[a] == ring[b]) & (span <= 1.5 * step * (run + 1))
            & (np.abs(r_a - r_b) <= FAINT_RANGE_TOLERANCE * 0.5 * (r_a + r_b))
            & (bright <= FAINT_INTENSITY_FACTOR * noise_floor * _scaled(floor_scale, 0.5 * (r_a + r_b))))
    if not fill.any():
        return beams
    a, run, r_a, r_b = a[fill], run[fill], r_a[fill], r_b[fill]
    k = np.arange(int(run.sum())) - np.repeat(np.cumsum(run) - run, run) + 1  # 1..run within each run
    frac = k / np.repeat(run + 1, run)
    rows = order[np.repeat(a, run) + k]
    lengths, intensity0 = beams.lengths.copy(), beams.intensity0.copy()
    lengths[rows] = np.repeat(r_a, run) + frac * np.repeat(r_b - r_a, run)
    intensity0[rows] = 0.5 * noise_floor * _scaled(floor_scale, lengths[rows])
    return Beams(beams.origins, beams.directions, beams.times, lengths, beams.has_return, intensity0, beams.ring,
                 beams.point_index, beams.divergence, beams.max_range)


def scan_ground_plane(scan: LidarScan) -> GroundPlane | None:
    """The ground plane of ``scan`` in the global frame: `fit_ground_plane` on its
    points (sensor frame, z up; the ground edit's plane), moved by ``scan.T_global_lidar``; None where too few
    returns lie below the sensor to fit one."""
    try:
        plane = fit_ground_plane(scan.points[:, :3].astype(np.float64))
    except ValueError:
        return None
    return plane.transformed(scan.T_global_lidar)


def plane_ranges(beams: Beams, plane: GroundPlane) -> F64:
    """(N,) the range [m] at which each beam meets ``plane`` (global frame, normal up) from above, going down: the
    beams that point below the plane's horizon from an origin above it; inf for the others."""
    return ray_plane_ranges(beams.origins, beams.directions, plane)


def ray_plane_ranges(origins: F64, directions: F64, plane: GroundPlane) -> F64:
    """(N,) the range [m] at which rays from ``origins`` (N, 3) [m] along unit ``directions`` (N, 3) meet ``plane``
    (the same frame, normal up) from above, going down; inf for the others."""
    normal = np.asarray(plane.normal, dtype=np.float64)
    height = origins @ normal + plane.offset  # the origins' height above the plane
    descent = -(directions @ normal)  # the height lost per metre along the ray
    down = (height > 0.0) & (descent > 0.0)
    return np.where(down, height / np.where(down, descent, 1.0), np.inf)


def _scaled(floor_scale: Callable[[F64], F64] | None, r: F64) -> F64 | float:
    """The floor's factor at ranges ``r`` [m]: ``floor_scale(r)``, or 1 for a constant floor (None)."""
    return 1.0 if floor_scale is None else floor_scale(r)


def with_ground_plane(beams: Beams, plane: GroundPlane | None, noise_floor: float | None,
                      floor_scale: Callable[[F64], F64] | None = None) -> Beams:
    """``beams`` whose beams without return and still open (no surface inferred yet: ``lengths == max_range``) that
    point below the horizon onto the fitted ground ``plane`` (global frame: `scan_ground_plane`) within the maximum
    range hit the road under the detector floor: a dark or wet road returns nothing over much of its extent (on the
    synthetic reference's rain frames about 6,700 beams a scan, most beyond the short runs `with_faint_surfaces`
    bridges). Such a beam gets the range of its intersection with the plane (`plane_ranges`) and the clear intensity
    ``noise_floor / 2`` (the mean of a uniform prior on ``(0, floor)``, as `with_faint_surfaces` gives): its
    undetectable echo is the strongest a strongest-return receiver gets unless the weather puts a detectable echo in
    front of it, and it ends the beam (no drop behind the road). The beams keep ``has_return`` False. None for the
    plane or the floor (or a zero floor): ``beams`` unchanged. ``floor_scale``: as for `with_faint_surfaces`."""
    if plane is None or noise_floor is None or noise_floor <= 0.0 or len(beams) == 0:
        return beams
    reach = plane_ranges(beams, plane)
    on = ~beams.has_return & (beams.lengths >= beams.max_range) & (reach < beams.max_range)
    if not on.any():
        return beams
    lengths, intensity0 = beams.lengths.copy(), beams.intensity0.copy()
    lengths[on] = reach[on]
    intensity0[on] = 0.5 * noise_floor * _scaled(floor_scale, reach[on])
    return Beams(beams.origins, beams.directions, beams.times, lengths, beams.has_return, intensity0, beams.ring,
                 beams.point_index, beams.divergence, beams.max_range)


def point_rays(scan: LidarScan) -> tuple[F64, F64, F64]:
    """Each point's beam in the global frame: origins (N, 3) [m] (`beam_origins`), unit directions (N, 3) and lengths
    (N,) [m]; a point at its beam origin gets direction +x and length 0."""
    T_gl = scan.T_global_lidar
    origins = beam_origins(scan)
    p_global = scan.points[:, :3].astype(np.float64) @ T_gl[:3, :3].T + T_gl[:3, 3]
    v = p_global - origins
    lengths = np.linalg.norm(v, axis=1)
    good = lengths > 1e-9
    directions = np.zeros((len(v), 3))
    directions[:, 0] = 1.0
    directions[good] = v[good] / lengths[good, None]
    return origins, directions, np.where(good, lengths, 0.0)


def point_noise_keys(scan: LidarScan) -> NDArray[np.uint64]:
    """(N,) the detector-noise stream of each point's beam: `detector_noise_keys` of its firing time, its global
    direction (`point_rays`) and its ring, exactly the keys `beams_from_scan`'s beams carry, so the fog alone and the
    particle model read a beam with the same draws."""
    return detector_noise_keys(scan_times(scan), point_rays(scan)[1], scan.points[:, 4])


def beams_from_scan(scan: LidarScan, *, lidar: LidarModel, no_return_directions: NoReturnBeams | None = None,
                    columns: NDArray | str | None = "auto", reconstruct: bool = True,
                    gap_factor: float = DEFAULT_GAP_FACTOR) -> Beams:
    """All beams of a scan in the global frame: its points first (``point_index`` = row), then the beams without
    return.

    Args:
        scan: any `LidarScan` (synthetic world, nuScenes, Seeing Through Fog, KITTI).
        lidar: the sensor (`weatheralign.sensors.LidarModel`): its maximum range is the length of beams without
            return, its divergence the beams', its firing grid the source of beams without return where the
            dataset stores per-point firing columns (``lidar.firing_columns_stored``).
        no_return_directions: explicit beams without return; if given, nothing is derived.
        columns: per-point firing columns (N,), None, or ``"auto"`` (read them with `synthetic_columns` when the
            sensor stores them).
        reconstruct: without explicit beams or columns, reconstruct the beams without return from the ring/azimuth
            grid (`reconstruct_no_return_beams`); False adds none.
        gap_factor: see `reconstruct_no_return_beams`.

    Returns:
        `Beams`: points with a degenerate direction (at the sensor origin) get direction +x and length 0.
    """
    max_range = float(lidar.max_range_m)
    pts = scan.points
    n = len(pts)
    times = scan_times(scan)
    origins, directions, lengths = point_rays(scan)

    if no_return_directions is None:
        if isinstance(columns, str) and columns == "auto":
            cols = synthetic_columns(scan) if lidar.firing_columns_stored else None
        elif isinstance(columns, str):
            raise ValueError(f"beams_from_scan: columns = {columns!r}; expected an array, None or 'auto'")
        else:
            cols = columns
        if cols is not None:
            no_return_directions = grid_no_return_beams(scan, np.asarray(cols), lidar.firing_pattern())
        elif reconstruct:
            no_return_directions = reconstruct_no_return_beams(scan, gap_factor=gap_factor)
        else:
            no_return_directions = _empty_no_return()
    nr = no_return_directions
    k = len(nr)
    nr_times = scan.timestamp + np.asarray(nr.time_offsets, dtype=np.float64)
    nr_origins, nr_rot = sensor_poses_at(scan, nr_times)
    nr_dirs = np.einsum("kij,kj->ki", nr_rot, np.asarray(nr.directions, dtype=np.float64))
    nr_dirs /= np.maximum(np.linalg.norm(nr_dirs, axis=1, keepdims=True), 1e-300)
    return Beams(
        origins=np.concatenate([origins, nr_origins]),
        directions=np.concatenate([directions, nr_dirs]),
        times=np.concatenate([times, nr_times]),
        lengths=np.concatenate([lengths, np.full(k, max_range)]),
        has_return=np.concatenate([np.ones(n, dtype=bool), np.zeros(k, dtype=bool)]),
        intensity0=np.concatenate([scan.intensity_255().astype(np.float64), np.zeros(k)]),
        ring=np.concatenate([pts[:, 4], np.asarray(nr.ring, dtype=np.float32)]),
        point_index=np.concatenate([np.arange(n, dtype=np.int64), np.full(k, -1, dtype=np.int64)]),
        divergence=float(lidar.divergence_rad),
        max_range=max_range,
    )
