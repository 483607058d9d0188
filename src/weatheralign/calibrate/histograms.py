"""Exact streaming intensity histograms, the two-sample KS statistic on them, and frame-bootstrap intervals.

LiDAR intensities are reported on a 0..255 scale (nuScenes, Seeing Through Fog; STF in steps of 0.05) or as 0..1
reflectances (KITTI). Every intensity is quantised to one of ``NUM_BINS = 256`` integer codes by the scan's declared
scale ``intensity_max`` (`weatheralign.data.frame.LidarScan.intensity_max`):

    code = value * 255 / intensity_max,    bin = floor(code + 0.5), clipped to 0..255

i.e. bin ``k`` collects the codes ``[k - 0.5, k + 0.5)`` (round half up), bin 255 everything from 254.5 up
(the sensor saturates there). Integer intensities on 0..255 map to their own bin exactly; a 0..1 scale maps to 256
bins of width 1/255 centred on ``k / 255``. Negative or non-finite intensities are errors. The simulated (float)
intensities of the fog model are rounded like the sensor's integer output; the 0.05 steps of STF are rounded too.

`IntensityHistograms` keeps one row of 256 integer counts per frame (memory ``O(frames x 256)``, independent of the
number of points), accumulated frame by frame. The ECDF of the pooled points is exact at every bin, so
`ks_statistic` (``sup_k |F_a(k) - F_b(k)|`` over the bin edges) is the exact two-sample Kolmogorov-Smirnov
statistic of the binned samples, computed in integers and rounded once: for integer intensities it equals
``scipy.stats.ks_2samp(a, b, method="exact").statistic`` bit for bit (scipy's asymptotic mode, used above 10 000
points, returns a float difference of ECDFs that can differ by an ulp). No p-value is reported: with millions of
points any p-value is ~0, however small the difference; D itself is reported with a **frame bootstrap**
(`bootstrap_ks`): whole frames are resampled with replacement on both sides (points within a frame are correlated,
so resampling points would understate the uncertainty), the statistic is recomputed per resample, and the
percentile interval is returned. Note that the bootstrap distribution of a sup-distance is biased upwards
(resampling noise adds to any difference): for two samples of one distribution (D near 0) the percentile interval
lies above D; for a real difference much larger than the sampling noise it brackets D.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from weatheralign.data.frame import LidarScan

NUM_BINS = 256
"""Number of intensity bins (codes 0..255)."""

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


def _check_scale(intensity_max: float, what: str) -> float:
    scale = float(intensity_max)
    if scale not in (1.0, 255.0):
        raise ValueError(f"{what}: intensity_max = {intensity_max!r}; expected 255.0 (0..255 intensities) or 1.0 "
                         f"(0..1 reflectances)")
    return scale


def intensity_bins(intensity: ArrayLike, intensity_max: float) -> I64:
    """Bin index (0..255) of every intensity (any shape -> same shape, int64): ``floor(v * 255 / intensity_max +
    0.5)`` clipped to 255.

    Args:
        intensity: intensities on ``0..intensity_max`` (float32 as stored in a point cloud, or any real dtype).
        intensity_max: the declared scale, 255.0 or 1.0.

    Raises:
        ValueError: a bad scale, or a negative / non-finite intensity.
    """
    scale = _check_scale(intensity_max, "intensity_bins")
    values = np.asarray(intensity)
    code = values.astype(np.float64) * (255.0 / scale)
    if code.size and not (np.isfinite(code).all() and code.min() >= 0.0):
        bad = values[~(np.isfinite(code) & (code >= 0.0))].ravel()[0]
        raise ValueError(f"intensity_bins: intensity {float(bad)!r} is invalid; expected finite values in "
                         f"0..{scale:g}")
    return np.minimum(np.floor(code + 0.5), NUM_BINS - 1).astype(np.int64)


def frame_counts(intensity: ArrayLike, intensity_max: float) -> I64:
    """(256,) int64 counts of one frame's intensities (see `intensity_bins`)."""
    return np.bincount(intensity_bins(np.ravel(intensity), intensity_max), minlength=NUM_BINS).astype(np.int64)


class IntensityHistograms:
    """Per-frame 256-bin intensity counts of one set of scans (one sensor, one intensity scale).

    Build it frame by frame (`add_scan`, `add_intensities`, `add_counts`) or at once (`from_scans`, `from_counts`).
    Plain numpy inside: picklable, cheap to pass between processes (``8 x 256`` bytes per frame).

    Attributes:
        intensity_max: the scale of the binned intensities (255.0 or 1.0); histograms of different scales are not
            compared (`ks_statistic` raises).
    """

    def __init__(self, intensity_max: float, counts: ArrayLike | None = None) -> None:
        """Empty histograms of scale ``intensity_max`` or, with ``counts`` (F, 256) non-negative integers, these."""
        self.intensity_max = _check_scale(intensity_max, "IntensityHistograms")
        self._rows: list[I64] = []
        self._stacked: I64 | None = None
        if counts is not None:
            c = np.asarray(counts)
            if c.ndim != 2 or c.shape[1] != NUM_BINS:
                raise ValueError(f"IntensityHistograms: counts must be (frames, {NUM_BINS}), got {c.shape}")
            for row in c:
                self.add_counts(row)

    # ------------------------------------------------------------------------------------------------ building

    @classmethod
    def from_scans(cls, scans: Iterable[LidarScan], intensity_max: float | None = None) -> IntensityHistograms:
        """One row per scan (streamed: each scan's points are binned and released).

        Args:
            scans: LiDAR scans of one intensity scale.
            intensity_max: the expected scale; None takes the first scan's.

        Raises:
            ValueError: scans of different scales, or no scan and no ``intensity_max``.
        """
        hist: IntensityHistograms | None = None if intensity_max is None else cls(intensity_max)
        for scan in scans:
            if hist is None:
                hist = cls(scan.intensity_max)
            hist.add_scan(scan)
        if hist is None:
            raise ValueError("IntensityHistograms.from_scans: no scans (and no intensity_max given)")
        return hist

    @classmethod
    def from_counts(cls, counts: ArrayLike, intensity_max: float) -> IntensityHistograms:
        """Histograms of given per-frame counts (F, 256)."""
        return cls(intensity_max, counts)

    def add_intensities(self, intensity: ArrayLike) -> None:
        """Append one frame: its intensities (N,) on this object's scale."""
        self._append(frame_counts(intensity, self.intensity_max))

    def add_scan(self, scan: LidarScan) -> None:
        """Append one frame: ``scan.points[:, 3]`` (the scan's scale must be this object's).

        Raises:
            ValueError: the scan's ``intensity_max`` differs.
        """
        if float(scan.intensity_max) != self.intensity_max:
            raise ValueError(f"IntensityHistograms.add_scan: scan intensity_max = {scan.intensity_max} but these "
                             f"histograms are on 0..{self.intensity_max:g}")
        self.add_intensities(scan.points[:, 3])

    def add_counts(self, counts: ArrayLike) -> None:
        """Append one frame given as its (256,) counts (non-negative integers)."""
        row = np.asarray(counts)
        if row.shape != (NUM_BINS,):
            raise ValueError(f"IntensityHistograms.add_counts: expected ({NUM_BINS},) counts, got {row.shape}")
        if not np.issubdtype(row.dtype, np.integer):
            if not (np.isfinite(row).all() and np.array_equal(row, np.round(row))):
                raise ValueError("IntensityHistograms.add_counts: counts must be integers")
        row = row.astype(np.int64)
        if (row < 0).any():
            raise ValueError("IntensityHistograms.add_counts: counts must be >= 0")
        self._append(row)

    def extend(self, other: IntensityHistograms) -> None:
        """Append all frames of ``other`` (same scale)."""
        _check_same_scale(self, other, "IntensityHistograms.extend")
        for row in other.counts:
            self._append(row.copy())

    def _append(self, row: I64) -> None:
        self._rows.append(row)
        self._stacked = None

    # ------------------------------------------------------------------------------------------------ reading

    @property
    def counts(self) -> I64:
        """(F, 256) int64 counts per frame (read-only)."""
        if self._stacked is None:
            stacked = np.stack(self._rows) if self._rows else np.zeros((0, NUM_BINS), np.int64)
            stacked.setflags(write=False)
            self._stacked = stacked
        return self._stacked

    @property
    def num_frames(self) -> int:
        """Number of frames F."""
        return len(self._rows)

    @property
    def num_points(self) -> int:
        """Number of binned points over all frames."""
        return int(self.counts.sum())

    def total(self) -> I64:
        """(256,) int64 counts pooled over all frames."""
        return self.counts.sum(axis=0)

    def ecdf(self) -> F64:
        """(256,) pooled ECDF at the bins: ``F(k)`` = fraction of points in bins ``<= k`` (``F(255) = 1``).

        Raises:
            ValueError: no points.
        """
        return _ecdf(self.total()[None], "IntensityHistograms.ecdf")[0]

    def frames(self, index: ArrayLike) -> IntensityHistograms:
        """A new object with the frames ``index`` (any integer index array; repeats allowed)."""
        return IntensityHistograms(self.intensity_max, self.counts[np.asarray(index, dtype=np.int64)])

    def __len__(self) -> int:
        return self.num_frames

    def __repr__(self) -> str:
        return (f"IntensityHistograms(frames={self.num_frames}, points={self.num_points}, "
                f"intensity_max={self.intensity_max:g})")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, IntensityHistograms):
            return NotImplemented
        return self.intensity_max == other.intensity_max and np.array_equal(self.counts, other.counts)

    __hash__ = None  # mutable

    def __getstate__(self) -> dict:
        return {"intensity_max": self.intensity_max, "counts": np.array(self.counts)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["intensity_max"], state["counts"])


# ---------------------------------------------------------------------------------------------------- KS


def _check_same_scale(a: IntensityHistograms, b: IntensityHistograms, what: str) -> None:
    if a.intensity_max != b.intensity_max:
        raise ValueError(f"{what}: intensity scales differ (0..{a.intensity_max:g} vs 0..{b.intensity_max:g}); "
                         f"bin both sets on one declared scale")


def _ecdf(totals: NDArray, what: str) -> F64:
    """(B, 256) ECDFs of (B, 256) pooled counts."""
    cum = np.cumsum(np.asarray(totals, dtype=np.int64), axis=1)
    n = cum[:, -1]
    if (n <= 0).any():
        raise ValueError(f"{what}: empty histogram (no points); expected at least one point")
    return cum / n[:, None]


def ks_from_totals(a: ArrayLike, b: ArrayLike) -> F64:
    """KS statistics of pooled counts: ``a`` and ``b`` (256,) or (B, 256) (broadcast) -> (B,) or scalar array.

    ``D = max_k |F_a(k) - F_b(k)|`` with ``F(k) = cumsum(counts)[k] / n``.
    """
    a2, b2 = np.atleast_2d(a), np.atleast_2d(b)
    if a2.shape[-1] != NUM_BINS or b2.shape[-1] != NUM_BINS:
        raise ValueError(f"ks_from_totals: expected (..., {NUM_BINS}) counts, got {a2.shape} and {b2.shape}")
    d = np.abs(_ecdf(a2, "ks_statistic (first sample)") - _ecdf(b2, "ks_statistic (second sample)")).max(axis=1)
    return d if (np.ndim(a) == 2 or np.ndim(b) == 2) else d[0]


def ks_statistic(a: IntensityHistograms, b: IntensityHistograms) -> float:
    """Exact two-sample KS statistic of the pooled binned intensities of ``a`` and ``b``: ``sup_k |F_a(k) -
    F_b(k)|`` over the 256 bin edges (the ECDFs only step at bins).

    Computed in integers, ``max_k |C_a(k) n_b - C_b(k) n_a| / (n_a n_b)`` with ``C`` the cumulative counts, and one
    correctly rounded division: the exact rational D to the nearest float (as ``scipy.stats.ks_2samp`` in its exact
    mode, which rounds ``h / lcm(n_a, n_b)``).

    Raises:
        ValueError: different intensity scales, or an empty side.
    """
    _check_same_scale(a, b, "ks_statistic")
    ca, cb = np.cumsum(a.total()), np.cumsum(b.total())
    na, nb = int(ca[-1]), int(cb[-1])
    if na == 0 or nb == 0:
        raise ValueError(f"ks_statistic: empty histogram ({na} and {nb} points); expected at least one point a side")
    if max(na, nb) < 2**31:  # |C_a n_b - C_b n_a| < 2**62: exact in int64
        num = int(np.abs(ca * nb - cb * na).max())
    else:
        num = max(abs(int(x) * nb - int(y) * na) for x, y in zip(ca, cb))
    return num / (na * nb)  # Python int division: correctly rounded


def _resample_totals(counts: I64, num: int, gen: np.random.Generator) -> F64:
    """(num, 256) pooled counts of ``num`` frame resamples (with replacement, as many frames as ``counts`` has)."""
    f = len(counts)
    idx = gen.integers(0, f, size=(num, f))
    flat = (np.arange(num, dtype=np.int64)[:, None] * f + idx).ravel()
    mult = np.bincount(flat, minlength=num * f).reshape(num, f).astype(np.float64)
    return mult @ counts.astype(np.float64)  # exact: integer sums far below 2**53


def _as_generator(rng: np.random.Generator | int) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise ValueError(f"rng = {rng!r}; expected an int seed or a numpy Generator")


@dataclass(frozen=True)
class KsBootstrap:
    """The KS statistic with its frame-bootstrap percentile interval.

    Attributes:
        statistic: D of the full samples.
        ci_low, ci_high: percentile interval of the bootstrap D's at ``confidence``.
        confidence: e.g. 0.95 (the 2.5 % and 97.5 % percentiles).
        num_resamples: bootstrap resamples B.
        resampled: (B,) the bootstrap statistics.
    """

    statistic: float
    ci_low: float
    ci_high: float
    confidence: float
    num_resamples: int
    resampled: F64


def _check_bootstrap_args(num_resamples: int, confidence: float) -> None:
    if not (isinstance(num_resamples, (int, np.integer)) and num_resamples >= 10):
        raise ValueError(f"num_resamples = {num_resamples!r}; expected an integer >= 10")
    if not (0.0 < confidence < 1.0):
        raise ValueError(f"confidence = {confidence!r}; expected a fraction in (0, 1), e.g. 0.95")


def bootstrap_ks(
    a: IntensityHistograms,
    b: IntensityHistograms,
    *,
    num_resamples: int = 1000,
    confidence: float = 0.95,
    rng: np.random.Generator | int = 0,
    chunk: int = 256,
) -> KsBootstrap:
    """KS statistic of ``a`` vs ``b`` with a frame-bootstrap percentile interval.

    Each resample draws ``a.num_frames`` frames of ``a`` and ``b.num_frames`` frames of ``b`` with replacement
    (independently), pools their counts and recomputes D. Cost ``O(B x F x 256)``, vectorised in blocks of ``chunk``
    resamples.

    Args:
        a, b: histograms of one scale, each with at least one point.
        num_resamples: B (>= 10).
        confidence: central coverage of the interval (0.95: 2.5 % and 97.5 % percentiles).
        rng: seed or Generator (the only randomness).
        chunk: resamples per vectorised block (memory ``chunk x F`` floats).

    Raises:
        ValueError: different scales, an empty side, or bad arguments.
    """
    _check_bootstrap_args(num_resamples, confidence)
    statistic = ks_statistic(a, b)
    gen = _as_generator(rng)
    ca, cb = a.counts, b.counts
    out = np.empty(num_resamples)
    for start in range(0, num_resamples, max(1, int(chunk))):
        num = min(int(chunk), num_resamples - start)
        ta, tb = _resample_totals(ca, num, gen), _resample_totals(cb, num, gen)
        ok = (ta.sum(axis=1) > 0) & (tb.sum(axis=1) > 0)  # a resample of only empty frames has no ECDF
        d = np.full(num, np.nan)
        if ok.any():
            d[ok] = ks_from_totals(ta[ok], tb[ok])
        out[start:start + num] = d
    tail = 50.0 * (1.0 - confidence)
    lo, hi = np.nanpercentile(out, [tail, 100.0 - tail])
    out.setflags(write=False)
    return KsBootstrap(statistic=statistic, ci_low=float(lo), ci_high=float(hi), confidence=float(confidence),
                       num_resamples=int(num_resamples), resampled=out)


def bootstrap_ecdf_band(
    hist: IntensityHistograms,
    *,
    quantiles: Sequence[float] = (0.05, 0.95),
    num_resamples: int = 200,
    rng: np.random.Generator | int = 0,
) -> F64:
    """(len(quantiles), 256) pointwise quantiles of the frame-bootstrap ECDFs of ``hist`` (e.g. a 5-95 % band).

    Raises:
        ValueError: no points, or quantiles outside [0, 1].
    """
    q = np.asarray(quantiles, dtype=np.float64)
    if q.ndim != 1 or len(q) == 0 or not ((q >= 0.0) & (q <= 1.0)).all():
        raise ValueError(f"bootstrap_ecdf_band: quantiles = {quantiles!r}; expected fractions in [0, 1]")
    _check_bootstrap_args(num_resamples, 0.5)
    if hist.num_points == 0:
        raise ValueError("bootstrap_ecdf_band: empty histogram (no points)")
    totals = _resample_totals(hist.counts, int(num_resamples), _as_generator(rng))
    totals = totals[totals.sum(axis=1) > 0]
    return np.quantile(_ecdf(totals, "bootstrap_ecdf_band"), q, axis=0)

