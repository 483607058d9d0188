"""Object velocity from the LiDAR sweeps by kernel-correlation scan matching, and the heading's direction from it.

A detection's points in an earlier sweep (time lag ``t`` behind the keyframe, ego motion already compensated) are the
same surface ``v t`` metres further back along the heading. Per detected box, the points of every sweep are put
into an occupancy profile over (along the heading, height) in the box's frame, blurred by a Gaussian kernel; the
shift ``s_k`` of sweep ``k`` maximises the correlation of its profile, slid along the axis, with the keyframe's
(kernel correlation, Tsin & Kanade, ECCV 2004), refined by a parabola through the peak and its neighbours. The speed
along the axis is the least-squares slope ``v = sum(s_k t_k) / sum(t_k^2)``; a box whose shifts disagree with one
speed by more than ``max_residual_m`` (a neighbour, clutter or weather in the window) keeps the network's velocity.
The velocity is ``v`` times the heading's unit vector (objects move along their heading). A box whose points move
backwards along its heading faster than ``flip_speed_mps`` is turned around: the network sees the heading's axis
well and its direction poorly, and the motion shows the direction.

Coordinates: points and boxes in the keyframe LiDAR frame [m]; box rows ``x, y, z, w, l, h, yaw, vx, vy``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SweepMatching:
    """Settings of `sweep_velocities`."""

    #: the fastest object searched for [m/s]: the shift range of a sweep with lag t is +-max_speed * t
    max_speed_mps: float = 20.0
    #: bin of the profiles along the axis [m] (the shift's resolution before the parabola's refinement)
    bin_m: float = 0.05
    #: standard deviation of the Gaussian kernel along the axis [m]
    kernel_m: float = 0.1
    #: height bins of the profile (over the box's height and the margin)
    height_bins: int = 8
    #: growth of the box on every side when its points are gathered [m]
    margin_m: float = 0.25
    #: fewer points than this in the keyframe or an earlier sweep: that sweep gives no shift
    min_points: int = 8
    #: largest disagreement between a sweep's shift and the fitted speed's [m]; larger: no velocity from the sweeps
    max_residual_m: float = 0.15
    #: a box whose points move backwards along its heading faster than this is turned around [m/s]; inf: never
    flip_speed_mps: float = 1.0
    #: detections scoring below this keep the head's velocity (`weatheralign.detect.model.with_sweep_motion`)
    min_score: float = 0.2

    def __post_init__(self) -> None:
        if not (self.max_speed_mps > 0 and self.bin_m > 0 and self.kernel_m > 0 and self.height_bins > 0
                and self.margin_m >= 0 and self.max_residual_m > 0):
            raise ValueError(f"SweepMatching needs positive speeds, bins, kernel and residual, got {self}")


@dataclass(frozen=True)
class SweepMotion:
    """What `sweep_velocities` found, per box: ``speed_along`` (K,) [m/s] along the box's (input) heading, NaN where
    the sweeps gave none; ``shifts`` (K, S) [m] per earlier sweep, NaN where it had too few points; ``lags`` (S,)
    [s] of the earlier sweeps."""

    speed_along: F64
    shifts: F64
    lags: F64


def box_local(points_xyz: F64, boxes: F64) -> F64:
    """(N, 3) points and (N, >= 7) boxes (one per point) -> (N, 3) ``along, across, up`` relative to the box centre
    and heading [m]."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    d = points_xyz - boxes[:, :3]
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])


def correlate_profiles(keyframe: F64, earlier: F64, max_shift_bins: int) -> F64:
    """Correlation of (K, A, Z) keyframe profiles with (K, A, Z) earlier ones slid by ``-m .. m`` bins along A:
    ``out[k, j] = sum_{a, z} keyframe[k, a, z] * earlier[k, a - s_j, z]`` with ``s_j = j - m`` (zero outside) ->
    (K, 2 m + 1). Computed with real FFTs of length >= A + m."""
    length = keyframe.shape[1]
    n = 1 << int(np.ceil(np.log2(length + max_shift_bins + 1)))
    spectrum = np.fft.rfft(keyframe, n, axis=1) * np.conj(np.fft.rfft(earlier, n, axis=1))
    circular = np.fft.irfft(spectrum, n, axis=1).sum(axis=2)  # (K, n): lag s at index s mod n
    lags = np.arange(-max_shift_bins, max_shift_bins + 1)
    return circular[:, lags % n]


def correlate_profiles_naive(keyframe: F64, earlier: F64, max_shift_bins: int) -> F64:
    """`correlate_profiles` by direct sums, shift by shift (the test oracle)."""
    k, length, _ = keyframe.shape
    out = np.zeros((k, 2 * max_shift_bins + 1))
    for j, s in enumerate(range(-max_shift_bins, max_shift_bins + 1)):
        for a in range(length):
            if 0 <= a - s < length:
                out[:, j] += (keyframe[:, a, :] * earlier[:, a - s, :]).sum(axis=1)
    return out


def peak_shift(scores: F64, bin_m: float) -> F64:
    """(K, 2 m + 1) correlation scores over shifts ``-m .. m`` bins -> (K,) the best shift [m], refined by a parabola
    through the peak and its neighbours."""
    m = (scores.shape[1] - 1) // 2
    best = np.argmax(scores, axis=1)
    inner = (best > 0) & (best < scores.shape[1] - 1)
    i = np.clip(best, 1, scores.shape[1] - 2)
    rows = np.arange(len(scores))
    left, mid, right = scores[rows, i - 1], scores[rows, i], scores[rows, i + 1]
    curvature = left - 2 * mid + right
    offset = np.where(inner & (curvature < 0), 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0), 0.0)
    return (best - m + offset) * bin_m


def _profiles(local: F64, owner: NDArray[np.int64], boxes: F64, n_boxes: int, half_bins: int,
              settings: SweepMatching) -> F64:
    """Occupancy profiles (K, 2 half_bins + 1, Z) of box-local points owned by box ``owner``, blurred along the axis."""
    along = np.rint(local[:, 0] / settings.bin_m).astype(np.int64) + half_bins
    top = boxes[owner, 5] / 2 + settings.margin_m
    height = np.clip(((local[:, 2] + top) / (2 * top) * settings.height_bins).astype(np.int64), 0,
                     settings.height_bins - 1)
    keep = (along >= 0) & (along <= 2 * half_bins)
    size = (2 * half_bins + 1) * settings.height_bins
    flat = owner[keep] * size + along[keep] * settings.height_bins + height[keep]
    counts = np.bincount(flat, minlength=n_boxes * size).astype(np.float64)
    profile = counts.reshape(n_boxes, 2 * half_bins + 1, settings.height_bins)
    return gaussian_filter1d(profile, settings.kernel_m / settings.bin_m, axis=1, mode="constant")


def sweep_velocities(points: NDArray, boxes: NDArray, settings: SweepMatching = SweepMatching()) -> SweepMotion:
    """Each box's speed along its heading from the sweeps (module docstring).

    Args:
        points: (N, 5) ``x, y, z [m], intensity, time lag [s]`` in the keyframe LiDAR frame (lag 0: keyframe).
        boxes: (K, >= 7) box rows ``x, y, z, w, l, h, yaw, ...``.
    """
    points = np.asarray(points, np.float64)
    boxes = np.asarray(boxes, np.float64)
    lags = np.unique(points[:, 4]) if len(points) else np.zeros(0)
    earlier_lags = lags[lags > 0]
    n_boxes = len(boxes)
    shifts = np.full((n_boxes, len(earlier_lags)), np.nan)
    speed = np.full(n_boxes, np.nan)
    if n_boxes == 0 or len(earlier_lags) == 0 or not np.any(lags == 0):
        return SweepMotion(speed, shifts, earlier_lags)
    reach_m = settings.max_speed_mps * float(earlier_lags[-1])
    half_length = boxes[:, 4] / 2 + settings.margin_m
    radius = np.hypot(boxes[:, 3] / 2 + settings.margin_m, half_length + reach_m)
    neighbours = cKDTree(points[:, :2]).query_ball_point(boxes[:, :2], radius)
    owner = np.repeat(np.arange(n_boxes), [len(n) for n in neighbours])
    index = np.concatenate([np.asarray(n, np.int64) for n in neighbours])
    near = points[index]
    local = box_local(near[:, :3], boxes[owner])
    in_slab = ((np.abs(local[:, 1]) <= boxes[owner, 3] / 2 + settings.margin_m)
               & (np.abs(local[:, 2]) <= boxes[owner, 5] / 2 + settings.margin_m))
    half_bins = int(np.ceil((half_length.max() + reach_m) / settings.bin_m))
    key = in_slab & (near[:, 4] == 0) & (np.abs(local[:, 0]) <= half_length[owner])
    key_count = np.bincount(owner[key], minlength=n_boxes)
    keyframe = _profiles(local[key], owner[key], boxes, n_boxes, half_bins, settings)
    for j, lag in enumerate(earlier_lags):
        reach = settings.max_speed_mps * float(lag)
        sweep = in_slab & (near[:, 4] == lag) & (np.abs(local[:, 0]) <= half_length[owner] + reach)
        count = np.bincount(owner[sweep], minlength=n_boxes)
        profile = _profiles(local[sweep], owner[sweep], boxes, n_boxes, half_bins, settings)
        scores = correlate_profiles(keyframe, profile, int(np.ceil(reach / settings.bin_m)))
        enough = (count >= settings.min_points) & (key_count >= settings.min_points) & (scores.max(axis=1) > 0)
        shifts[enough, j] = peak_shift(scores[enough], settings.bin_m)
    known = np.isfinite(shifts)
    t = np.where(known, earlier_lags[None, :], 0.0)
    s = np.where(known, shifts, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        fitted = (s * t).sum(axis=1) / (t * t).sum(axis=1)
    residual = np.where(known, np.abs(s - fitted[:, None] * t), 0.0).max(axis=1, initial=0.0)
    good = known.any(axis=1) & (residual <= settings.max_residual_m)
    speed[good] = fitted[good]
    return SweepMotion(speed, shifts, earlier_lags)


def apply_sweep_motion(boxes: F64, motion: SweepMotion, settings: SweepMatching = SweepMatching(),
                       apply_to: NDArray[np.bool_] | None = None) -> F64:
    """(K, 9) box rows with the velocity from ``motion`` where it has one (and ``apply_to``, (K,) bool, allows), turned
    around where the points move backwards along the heading faster than ``settings.flip_speed_mps``; the input is
    not modified."""
    out = np.array(boxes, np.float64, copy=True)
    known = np.isfinite(motion.speed_along)
    if apply_to is not None:
        known &= np.asarray(apply_to, bool)
    flip = known & (motion.speed_along < -settings.flip_speed_mps)
    out[flip, 6] = np.mod(out[flip, 6] + 2 * np.pi, 2 * np.pi) - np.pi
    heading = np.column_stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6])])
    out[known, 7:9] = motion.speed_along[known, None] * heading[known]
    return out


__all__ = ["apply_sweep_motion", "box_local", "correlate_profiles", "correlate_profiles_naive", "peak_shift",
           "sweep_velocities", "SweepMatching", "SweepMotion"]
