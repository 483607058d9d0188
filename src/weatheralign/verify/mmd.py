"""Maximum mean discrepancy (MMD) between two sets of feature vectors, with permutation p-values, frame-bootstrap
intervals and a paired test of two MMDs against one reference: the statistics of the `verify` stage (the paper's
"verification using fused features").

Conventions (stated once, used everywhere here):

* The feature sets that are compared together are standardised together: pooled mean and standard deviation per
  dimension (a dimension that is constant over the pool is left at 0). Tests that must be comparable (a condition's
  reference vs aligned, vs unaligned, and their paired difference) share the pool (``scale``) and so one kernel.
* Gaussian kernel ``k(x, y) = exp(-|x - y|^2 / (2 l^2))`` with ``l`` the median Euclidean distance between distinct
  pooled, standardised vectors (the median heuristic; Gretton et al. 2012), computed with scikit-learn's
  ``pairwise_distances`` / ``rbf_kernel`` once per comparison: every permutation and resample reuses that matrix.
* Several feature extractors (M independently trained classifiers, sets given as (M, n, d)): each member is
  standardised and given its bandwidth on its own, and the kernel is the mean of the members' kernels
  (`pooled_kernel`), so every statistic is the mean of the members' statistics under one shared permutation or
  resample: training noise averages out, the features are not widened.
* MMD^2 is the unbiased U-statistic (Gretton et al. 2012, eq. 3): the within-set means exclude the diagonal. It can be
  slightly negative when the distributions agree.
* Permutation p-value: ``(1 + #{permuted >= observed}) / (1 + permutations)`` (never 0).
* Bootstrap: frames resampled with replacement within each set, the statistic recomputed from the same kernel
  matrices; percentile interval. (A resampled frame that appears twice adds kernel value 1 pairs: the interval is a
  little wide of the estimator's own spread when sets are small.) With M feature extractors the members are
  resampled with replacement too (`member_weights`, a generator of their own, so the frames' draws are those of one
  member): the interval holds the training noise of the classifiers as well as the sampling of the frames. The
  permutation nulls keep the members' mean kernel (a test given the trained classifiers).

Shapes: feature sets are (n, d) float arrays, one row per frame, or (M, n, d) for M feature extractors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from sklearn.metrics.pairwise import pairwise_distances, rbf_kernel

F64 = NDArray[np.float64]


def standardise(*sets: NDArray, using: Sequence[NDArray] | None = None) -> list[F64]:
    """The feature sets (n_i, d) standardised with the pooled per-dimension mean and standard deviation of ``using``
    (default: of the sets themselves)."""
    scale_sets = tuple(sets) if using is None else tuple(using)
    if not sets or any(np.ndim(s) != 2 for s in (*sets, *scale_sets)) or \
            len({np.shape(s)[1] for s in (*sets, *scale_sets)}) != 1:
        raise ValueError(f"feature sets must be 2-D with one width, got shapes {[np.shape(s) for s in sets]}")
    pooled = np.concatenate([np.asarray(s, dtype=np.float64) for s in scale_sets])
    everything = np.concatenate([np.asarray(s, dtype=np.float64) for s in sets])
    if not (np.isfinite(pooled).all() and np.isfinite(everything).all()):
        raise ValueError("feature sets hold NaN or infinite values")
    std = pooled.std(axis=0)
    scaled = (everything - pooled.mean(axis=0)) / np.where(std > 0, std, 1.0)
    bounds = np.cumsum([0] + [len(s) for s in sets])
    return [scaled[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


def _scale_and_bandwidth(sets: Sequence[NDArray], scale: Sequence[NDArray] | None) -> tuple[list[F64], float]:
    """``sets`` standardised with ``scale``'s pooled statistics (default: their own) and the median-heuristic
    bandwidth of the standardised ``scale`` pool."""
    scale = tuple(sets) if scale is None else tuple(scale)
    return standardise(*sets, using=scale), median_bandwidth(np.concatenate(standardise(*scale)))


def _members(sets: Sequence[NDArray]) -> list[F64]:
    """Feature sets as (M, n_i, d) arrays of one member count M: an (n, d) set is one member."""
    out = [np.asarray(s, dtype=np.float64) for s in sets]
    out = [s[None] if s.ndim == 2 else s for s in out]
    if any(s.ndim != 3 for s in out) or len({s.shape[0] for s in out}) != 1:
        raise ValueError(f"feature sets must be (n, d), or (M, n, d) for M feature extractors alike, got shapes "
                         f"{[np.shape(s) for s in sets]}")
    return out


def member_kernels(sets: Sequence[NDArray], scale: Sequence[NDArray] | None = None) -> tuple[F64, float]:
    """(M, N, N) the Gaussian kernel matrix of each of M feature extractors over the rows of ``sets`` (concatenated
    in order) and their mean length scale. A set is (n, d) features (M = 1), or (M, n, d): the same frames through
    M feature extractors (independently trained classifiers), whose members are standardised and given a
    median-heuristic bandwidth each, with ``scale``'s members (default: ``sets``')."""
    members = _members(sets)
    scale_members = members if scale is None else _members(scale)
    if scale_members[0].shape[0] != members[0].shape[0]:
        raise ValueError("scale must have as many feature extractors as the sets")
    kernels, widths = [], []
    for m in range(members[0].shape[0]):
        scaled, width = _scale_and_bandwidth([s[m] for s in members], [s[m] for s in scale_members])
        kernels.append(gaussian_kernel(np.concatenate(scaled), width))
        widths.append(width)
    return np.stack(kernels), float(np.mean(widths))


def pooled_kernel(sets: Sequence[NDArray], scale: Sequence[NDArray] | None = None) -> tuple[F64, float]:
    """The (N, N) mean of `member_kernels` (itself a kernel, so every MMD^2 on it is the mean of the members' MMD^2
    under one permutation) and the members' mean length scale."""
    kernels, width = member_kernels(sets, scale)
    return kernels.mean(axis=0), width


def member_weights(members: int, resamples: int, seed: int) -> F64:
    """(resamples, members) the weight of each feature extractor in each bootstrap resample: how often it is drawn
    when ``members`` are drawn with replacement, over ``members`` (rows sum to 1; all 1 for a single member). From a
    generator of their own (``seed`` and a fixed stream number), so that the frames' resamples do not depend on it."""
    rng = np.random.default_rng([seed, MEMBER_STREAM])
    return rng.multinomial(members, np.full(members, 1.0 / members), size=resamples) / members


MEMBER_STREAM = 1
"""The stream number of `member_weights`' generator beside the tests' own ``seed``."""


def weighted_kernel(kernels: F64, weights: NDArray) -> F64:
    """(N, N) the members' kernels (M, N, N) weighted by ``weights`` (M,) (a row of `member_weights`)."""
    return np.tensordot(np.asarray(weights, dtype=np.float64), kernels, axes=1)


def median_bandwidth(z: NDArray) -> float:
    """Median Euclidean distance between the distinct rows of ``z`` (n, d), n >= 2 (the kernel's length scale)."""
    if len(z) < 2:
        raise ValueError(f"the median heuristic needs two vectors or more, got {len(z)}")
    distances = pairwise_distances(z)
    median = float(np.median(distances[np.triu_indices(len(z), k=1)]))
    return median if median > 0 else 1.0


def gaussian_kernel(z: NDArray, bandwidth: float) -> F64:
    """(n, n) Gaussian kernel matrix ``exp(-|z_i - z_j|^2 / (2 bandwidth^2))``."""
    return rbf_kernel(z, gamma=1.0 / (2.0 * bandwidth * bandwidth))


def _set_sums(K: F64, member: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """For (P, n) 0/1 ``member`` rows (x = 1, y = 0): the sums of K over x-x pairs, y-y pairs and x-y pairs, each
    (P,), diagonals included."""
    KA = member @ K
    other = 1.0 - member
    return (KA * member).sum(axis=1), ((other @ K) * other).sum(axis=1), (KA * other).sum(axis=1)


def _mmd2(K: F64, member: NDArray) -> NDArray:
    """Unbiased MMD^2 for each (P, n) membership row of ``member`` over the kernel matrix ``K`` (n, n)."""
    m = member.sum(axis=1)
    n = member.shape[1] - m
    diag = np.diag(K)
    sxx, syy, sxy = _set_sums(K, member)
    txx, tyy = member @ diag, (1.0 - member) @ diag
    return (sxx - txx) / (m * (m - 1)) + (syy - tyy) / (n * (n - 1)) - 2.0 * sxy / (m * n)


def mmd2_unbiased(K: NDArray, m: int) -> float:
    """Unbiased MMD^2 between the first ``m`` rows (x) and the rest (y) of the pooled kernel matrix ``K`` (n, n)."""
    n = len(K)
    if not 2 <= m <= n - 2:
        raise ValueError(f"each set needs two frames or more: {m} and {n - m}")
    member = np.zeros((1, n))
    member[0, :m] = 1.0
    return float(_mmd2(np.asarray(K, dtype=np.float64), member)[0])


def percentile_interval(stats: NDArray, confidence: float, estimate: float) -> tuple[float, float]:
    """The central ``confidence`` percentile interval of bootstrap ``stats``; ``(estimate, estimate)`` without any."""
    if len(stats) == 0:
        return estimate, estimate
    tail = (1.0 - confidence) / 2.0
    return float(np.quantile(stats, tail)), float(np.quantile(stats, 1.0 - tail))


@dataclass(frozen=True, eq=False)
class MmdTest:
    """MMD^2 of x against y with its permutation p-value, bootstrap interval, the kernel's length scale (in
    standardised units) and the permuted statistics ``null`` (permutations,); ``each``: with M feature extractors,
    each one's own MMD^2 (`mmd_test`; empty where not computed)."""

    mmd2: float
    p_value: float
    ci: tuple[float, float]
    bandwidth: float
    null: NDArray[np.float64]
    each: tuple[float, ...] = ()

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, MmdTest) and (self.mmd2, self.p_value, self.ci, self.bandwidth)
                == (other.mmd2, other.p_value, other.ci, other.bandwidth) and np.array_equal(self.null, other.null))


def mmd_test(x: NDArray, y: NDArray, permutations: int = 1000, resamples: int = 1000, seed: int = 0,
             confidence: float = 0.95, batch: int = 250, scale: Sequence[NDArray] | None = None) -> MmdTest:
    """Two-sample MMD test of feature sets ``x`` (m, d) and ``y`` (n, d) under the module's conventions; ``scale``:
    the sets whose pool sets the standardisation and the bandwidth (default: x and y), so that several tests share
    one kernel. Sets of M feature extractors (M, m, d) and (M, n, d): the members' mean kernel, the bootstrap over
    frames and members."""
    kernels, bandwidth = member_kernels((x, y), scale)
    K = kernels.mean(axis=0)
    m = _members((x,))[0].shape[1]
    n = len(K) - m
    observed = mmd2_unbiased(K, m)
    rng = np.random.default_rng(seed)
    null = np.empty(permutations)
    for start in range(0, permutations, batch):
        rows = min(batch, permutations - start)
        member = np.zeros((rows, m + n))
        picks = np.argsort(rng.random((rows, m + n)), axis=1)[:, :m]
        np.put_along_axis(member, picks, 1.0, axis=1)
        null[start:start + rows] = _mmd2(K, member)
    exceed = int((null >= observed - 1e-15).sum())
    stats = np.empty(resamples)
    weights = member_weights(len(kernels), resamples, seed)
    for r in range(resamples):
        idx = np.concatenate([rng.integers(0, m, m), m + rng.integers(0, n, n)])
        stats[r] = mmd2_unbiased(weighted_kernel(kernels[:, idx[:, None], idx[None, :]], weights[r]), m)
    ci = percentile_interval(stats, confidence, observed)
    each = tuple(mmd2_unbiased(kernel, m) for kernel in kernels)
    return MmdTest(observed, (1 + exceed) / (1 + permutations), ci, bandwidth, null, each)


def _paired_mmd2(K: F64, x_idx: NDArray, y_idx: NDArray) -> NDArray:
    """Unbiased MMD^2 for paired sets of equal size n (Gretton et al. 2012, eq. 4: the U-statistic over pairs
    i != j, so the matched cross terms k(x_i, y_i) are left out) for each (P, n) row of indices into ``K``."""
    n = x_idx.shape[1]
    kxx = K[x_idx[:, :, None], x_idx[:, None, :]]
    kyy = K[y_idx[:, :, None], y_idx[:, None, :]]
    kxy = K[x_idx[:, :, None], y_idx[:, None, :]]
    off = ~np.eye(n, dtype=bool)
    return ((kxx + kyy - kxy - kxy.transpose(0, 2, 1)) * off).sum(axis=(1, 2)) / (n * (n - 1))


def paired_mmd_test(x: NDArray, y: NDArray, permutations: int = 1000, resamples: int = 1000, seed: int = 0,
                    confidence: float = 0.95, batch: int = 250, scale: Sequence[NDArray] | None = None) -> MmdTest:
    """Two-sample MMD test of paired feature sets ``x`` and ``y`` (n, d), n >= 2, row i of both from one frame (the
    control: a frame's camera with its own LiDAR and with another frame's). The statistic is the unbiased MMD^2 for
    paired samples (`_paired_mmd2`: the matched pairs' own cross terms left out, since a frame's two rows share its
    camera); the null swaps x_i and y_i at random (exchangeable within a pair when the features are blind to what
    differs); the bootstrap resamples pairs. An unpaired permutation would put both rows of a frame in one set and so
    inflate its null with the frame's self-similarity. Kernel and standardisation as `mmd_test` (``scale``)."""
    if np.shape(x) != np.shape(y) or np.shape(x)[-2] < 2:
        raise ValueError(f"paired sets need the same shape and two frames or more, got {np.shape(x)} and "
                         f"{np.shape(y)}")
    kernels, bandwidth = member_kernels((x, y), scale)
    K = kernels.mean(axis=0)
    n = len(K) // 2
    x_rows, y_rows = np.arange(n), n + np.arange(n)
    observed = float(_paired_mmd2(K, x_rows[None], y_rows[None])[0])
    rng = np.random.default_rng(seed)
    null = np.empty(permutations)
    for start in range(0, permutations, batch):
        swap = rng.random((min(batch, permutations - start), n)) < 0.5
        null[start:start + len(swap)] = _paired_mmd2(K, np.where(swap, y_rows, x_rows), np.where(swap, x_rows, y_rows))
    exceed = int((null >= observed - 1e-15).sum())
    stats = np.empty(resamples)
    weights = member_weights(len(kernels), resamples, seed)
    for start in range(0, resamples, batch):
        pick = rng.integers(0, n, (min(batch, resamples - start), n))
        each = np.stack([_paired_mmd2(Km, x_rows[pick], y_rows[pick]) for Km in kernels])  # (M, rows): linear in K
        stats[start:start + len(pick)] = np.einsum("rm,mr->r", weights[start:start + len(pick)], each)
    ci = percentile_interval(stats, confidence, observed)
    return MmdTest(observed, (1 + exceed) / (1 + permutations), ci, bandwidth, null)


@dataclass(frozen=True)
class PairedMmdDifference:
    """MMD^2(reference, a) - MMD^2(reference, b) for paired frames a_i, b_i (the same clear frame simulated two ways),
    with a two-sided sign-flip permutation p-value (a_i and b_i swapped at random) and a frame-bootstrap interval."""

    mmd2_a: float
    mmd2_b: float
    difference: float
    p_value: float
    ci: tuple[float, float]
    bandwidth: float


def paired_mmd_difference(reference: NDArray, a: NDArray, b: NDArray, permutations: int = 1000,
                          resamples: int = 1000, seed: int = 0, confidence: float = 0.95) -> PairedMmdDifference:
    """Is ``a`` (n, d) closer to ``reference`` (r, d) than its paired set ``b`` (n, d)? All three standardised
    together, one kernel (median heuristic over the three) for both MMDs: ``mmd2_a`` and ``mmd2_b`` equal
    `mmd_test` of each against the reference with ``scale=(reference, a, b)``. Sets of M feature extractors: the
    members' mean kernel, the bootstrap over frames and members."""
    if np.shape(a) != np.shape(b):
        raise ValueError(f"paired sets need one row per frame in both: {np.shape(a)} vs {np.shape(b)}")
    kernels, bandwidth = member_kernels((reference, a, b))
    K = kernels.mean(axis=0)
    n = np.shape(a)[-2]
    r = len(K) - 2 * n
    ref_idx = np.arange(r)

    def to_reference(rows: NDArray, ref: NDArray = ref_idx, kernel: F64 = K) -> float:
        pool = np.concatenate([ref, rows])
        return mmd2_unbiased(kernel[np.ix_(pool, pool)], len(ref))

    def difference(a_idx: NDArray, b_idx: NDArray, ref: NDArray = ref_idx, kernel: F64 = K) -> float:
        return to_reference(a_idx, ref, kernel) - to_reference(b_idx, ref, kernel)

    a_rows, b_rows = r + np.arange(n), r + n + np.arange(n)
    mmd_a, mmd_b = to_reference(a_rows), to_reference(b_rows)
    observed = mmd_a - mmd_b
    rng = np.random.default_rng(seed)
    exceed = 0
    for _ in range(permutations):
        swap = rng.random(n) < 0.5
        if abs(difference(np.where(swap, b_rows, a_rows), np.where(swap, a_rows, b_rows))) >= abs(observed) - 1e-15:
            exceed += 1
    stats = np.empty(resamples)
    weights = member_weights(len(kernels), resamples, seed)
    for k in range(resamples):
        pick, ref = rng.integers(0, n, n), rng.integers(0, r, r)
        stats[k] = difference(a_rows[pick], b_rows[pick], ref, weighted_kernel(kernels, weights[k]))
    ci = percentile_interval(stats, confidence, observed)
    return PairedMmdDifference(mmd_a, mmd_b, observed, (1 + exceed) / (1 + permutations), ci, bandwidth)


__all__ = ["MEMBER_STREAM", "MmdTest", "PairedMmdDifference", "gaussian_kernel", "median_bandwidth", "member_kernels",
           "member_weights", "mmd2_unbiased", "mmd_test", "paired_mmd_difference", "paired_mmd_test",
           "percentile_interval", "pooled_kernel", "standardise", "weighted_kernel"]
