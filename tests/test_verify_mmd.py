"""The MMD statistics of `verify` (weatheralign.verify.mmd): the unbiased estimator against a slow double loop and
against the closed-form population MMD of two Gaussians, the median heuristic, permutation p-values that are
calibrated under the null and small under a shift, and the paired difference test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from weatheralign.verify.mmd import (
    gaussian_kernel,
    median_bandwidth,
    member_kernels,
    member_weights,
    mmd2_unbiased,
    mmd_test,
    paired_mmd_difference,
    paired_mmd_test,
    pooled_kernel,
    standardise,
    weighted_kernel,
)


def slow_mmd2(x: np.ndarray, y: np.ndarray, bandwidth: float) -> float:
    def k(a, b):
        return math.exp(-float(np.sum((a - b) ** 2)) / (2 * bandwidth ** 2))
    m, n = len(x), len(y)
    xx = sum(k(x[i], x[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
    yy = sum(k(y[i], y[j]) for i in range(n) for j in range(n) if i != j) / (n * (n - 1))
    xy = sum(k(x[i], y[j]) for i in range(m) for j in range(n)) / (m * n)
    return xx + yy - 2 * xy


def test_unbiased_estimator_equals_the_double_loop() -> None:
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(9, 3)), rng.normal(0.5, 1.0, size=(12, 3))
    K = gaussian_kernel(np.concatenate([x, y]), 1.3)
    assert mmd2_unbiased(K, 9) == pytest.approx(slow_mmd2(x, y, 1.3), rel=1e-12)


def test_estimator_mean_matches_the_closed_form_for_two_gaussians() -> None:
    """X ~ N(0, s^2 I), Y ~ N(mu, s^2 I), kernel length l: MMD^2 = 2 c (1 - exp(-|mu|^2 / (2 (l^2 + 2 s^2)))) with
    c = (l^2 / (l^2 + 2 s^2))^(d/2)."""
    d, s, ell = 2, 1.0, 1.5
    mu = np.array([0.8, 0.0])
    c = (ell ** 2 / (ell ** 2 + 2 * s ** 2)) ** (d / 2)
    exact = 2 * c * (1 - math.exp(-float(mu @ mu) / (2 * (ell ** 2 + 2 * s ** 2))))
    rng = np.random.default_rng(1)
    estimates = []
    for _ in range(40):
        x, y = rng.normal(0, s, (150, d)), rng.normal(mu, s, (150, d))
        estimates.append(mmd2_unbiased(gaussian_kernel(np.concatenate([x, y]), ell), 150))
    assert np.mean(estimates) == pytest.approx(exact, abs=3 * np.std(estimates) / math.sqrt(40))


def test_median_heuristic_and_pooled_standardisation() -> None:
    rng = np.random.default_rng(2)
    z = rng.normal(size=(30, 4))
    d = [np.linalg.norm(z[i] - z[j]) for i in range(30) for j in range(i + 1, 30)]
    assert median_bandwidth(z) == pytest.approx(float(np.median(d)), rel=1e-12)
    a, b = standardise(np.column_stack([np.arange(4.0), np.ones(4)]),
                       np.column_stack([np.arange(4.0, 8.0), np.ones(4)]))
    pooled = np.concatenate([a, b])
    assert pooled[:, 0].mean() == pytest.approx(0.0) and pooled[:, 0].std() == pytest.approx(1.0)
    assert (pooled[:, 1] == 0).all()  # a constant dimension stays 0
    with pytest.raises(ValueError, match="NaN"):
        standardise(np.array([[np.nan]]), np.zeros((2, 1)))


def test_permutation_p_values_are_calibrated_under_the_null_and_small_under_a_shift() -> None:
    rng = np.random.default_rng(3)
    p_null = [mmd_test(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), permutations=200, resamples=0,
                       seed=k).p_value for k in range(60)]
    assert 0.0 <= np.mean(np.array(p_null) < 0.05) <= 0.15 and 0.35 < np.mean(p_null) < 0.65
    shifted = mmd_test(rng.normal(size=(40, 3)), rng.normal(1.0, 1.0, (40, 3)), permutations=500, resamples=200)
    assert shifted.p_value == pytest.approx(1 / 501) and shifted.ci[0] > 0 and shifted.ci[0] <= shifted.mmd2
    x, y = rng.normal(size=(10, 2)), rng.normal(size=(10, 2))
    assert mmd_test(x, y, 50, 20, seed=7) == mmd_test(x, y, 50, 20, seed=7)  # seeded: same result


def test_paired_difference_finds_the_closer_set() -> None:
    rng = np.random.default_rng(4)
    reference = rng.normal(size=(40, 3))
    close, far = rng.normal(size=(40, 3)), rng.normal(0.9, 1.0, (40, 3))
    result = paired_mmd_difference(reference, close, far, permutations=300, resamples=200)
    assert result.difference < 0 and result.mmd2_a < result.mmd2_b and result.p_value < 0.01
    assert result.ci[1] < 0
    twins = paired_mmd_difference(reference, rng.normal(size=(40, 3)), rng.normal(size=(40, 3)), permutations=300,
                                  resamples=0)
    assert twins.p_value > 0.05
    with pytest.raises(ValueError, match="paired"):
        paired_mmd_difference(reference, close, far[:-1])


def slow_paired_mmd2(x: np.ndarray, y: np.ndarray, bandwidth: float) -> float:
    def k(a, b):
        return math.exp(-float(np.sum((a - b) ** 2)) / (2 * bandwidth ** 2))
    n = len(x)
    return sum(k(x[i], x[j]) + k(y[i], y[j]) - k(x[i], y[j]) - k(x[j], y[i])
               for i in range(n) for j in range(n) if i != j) / (n * (n - 1))


def frames_with_a_shared_part(rng: np.random.Generator, n: int, shift: float) -> tuple[np.ndarray, np.ndarray]:
    """n frames, each seen twice (x_i, y_i) with a large per-frame part in common (the camera) and a small part of
    their own; y's own part moved by ``shift`` in every frame (the LiDAR)."""
    frame = rng.normal(0.0, 3.0, (n, 4))
    return frame + rng.normal(0.0, 0.3, (n, 4)), frame + rng.normal(0.0, 0.3, (n, 4)) + shift


def test_paired_test_is_the_pair_u_statistic_and_sees_what_the_unpaired_test_cannot() -> None:
    rng = np.random.default_rng(6)
    x, y = frames_with_a_shared_part(rng, 9, 0.0)
    result = paired_mmd_test(x, y, permutations=50, resamples=20)
    (xs, ys), = [standardise(x, y)]
    assert result.mmd2 == pytest.approx(slow_paired_mmd2(xs, ys, result.bandwidth), rel=1e-12)
    # a small shift of every frame's second view: invisible between frames, obvious within them
    x, y = frames_with_a_shared_part(rng, 20, 0.5)
    paired, unpaired = paired_mmd_test(x, y, permutations=500, resamples=200), mmd_test(x, y, permutations=500)
    assert paired.p_value < 0.01 < 0.2 < unpaired.p_value and paired.ci[0] > 0
    p_null = [paired_mmd_test(*frames_with_a_shared_part(rng, 20, 0.0), permutations=200, resamples=0,
                              seed=k).p_value for k in range(40)]
    assert np.mean(np.array(p_null) < 0.05) <= 0.15 and 0.3 < np.mean(p_null) < 0.7
    assert paired_mmd_test(x, y, 50, 20, seed=3) == paired_mmd_test(x, y, 50, 20, seed=3)
    with pytest.raises(ValueError, match="paired"):
        paired_mmd_test(x, y[:-1])


def test_member_weights_draw_members_with_replacement() -> None:
    w = member_weights(5, 4000, seed=2)
    assert w.shape == (4000, 5) and np.allclose(w.sum(axis=1), 1.0)
    assert set(np.unique(w * 5)) <= set(range(6))  # counts of 5 draws
    assert np.allclose(w.mean(axis=0), 0.2, atol=0.01)  # each member equally likely
    assert np.allclose(np.var(w * 5, axis=0), 5 * 0.2 * 0.8, rtol=0.1)  # multinomial's variance
    np.testing.assert_array_equal(member_weights(1, 7, seed=2), np.ones((7, 1)))
    np.testing.assert_array_equal(w, member_weights(5, 4000, seed=2))


def test_the_bootstrap_of_several_feature_extractors_is_a_weighted_sum_over_members() -> None:
    """The interval's resamples against a slow loop: per resample, the frames drawn as one member's test draws them
    and the members' own statistics weighted by `member_weights` (MMD^2 is linear in the kernel)."""
    rng = np.random.default_rng(4)
    x, y = rng.normal(size=(3, 10, 4)), rng.normal(0.3, 1.0, (3, 12, 4))
    kernels, _ = member_kernels((x, y))
    assert np.allclose(kernels.mean(axis=0), pooled_kernel((x, y))[0], rtol=0, atol=1e-15)
    weights = member_weights(3, 40, seed=9)
    fast = mmd_test(x, y, permutations=100, resamples=40, seed=9, confidence=0.9)
    replay = np.random.default_rng(9)
    replay.random((100, 22))  # the permutations' draws come first (one batch of 100)
    slow = []
    for r in range(40):
        idx = np.concatenate([replay.integers(0, 10, 10), 10 + replay.integers(0, 12, 12)])
        slow.append(sum(weights[r, m] * mmd2_unbiased(kernels[m][np.ix_(idx, idx)], 10) for m in range(3)))
    lo, hi = np.quantile(slow, [0.05, 0.95])
    assert fast.ci == pytest.approx((lo, hi), rel=1e-10)
    assert np.allclose(weighted_kernel(kernels, [1.0, 0.0, 0.0]), kernels[0])


def test_training_noise_widens_the_interval_of_several_feature_extractors() -> None:
    """Members that disagree (each sees y shifted by its own amount) widen the interval beyond that of members
    that agree (five copies of one): the training noise is in it; five copies give the one member's interval."""
    rng = np.random.default_rng(11)
    x, y = rng.normal(size=(30, 3)), rng.normal(size=(30, 3))
    copies = mmd_test(np.stack([x] * 5), np.stack([y] * 5), permutations=100, resamples=400, seed=1)
    alone = mmd_test(x, y, permutations=100, resamples=400, seed=1)
    assert copies.ci == pytest.approx(alone.ci, rel=1e-9, abs=1e-12)
    shifts = np.array([0.0, 0.2, 0.6, 1.0, 1.5])[:, None, None]
    disagree = mmd_test(np.stack([x] * 5), np.stack([y] * 5) + shifts, permutations=100, resamples=400, seed=1)
    each = [mmd_test(x, y + s[0], permutations=100, resamples=0).mmd2 for s in shifts]
    assert disagree.mmd2 == pytest.approx(np.mean(each), rel=1e-9)
    assert disagree.ci[1] - disagree.ci[0] > 2.0 * (copies.ci[1] - copies.ci[0])
    assert disagree.ci[0] <= disagree.mmd2 <= disagree.ci[1]
    paired_copies = paired_mmd_test(np.stack([x] * 5), np.stack([y] * 5), permutations=50, resamples=300, seed=1)
    paired_disagree = paired_mmd_test(np.stack([x] * 5), np.stack([y] * 5) + shifts, permutations=50,
                                      resamples=300, seed=1)
    assert np.diff(paired_disagree.ci)[0] > 2.0 * np.diff(paired_copies.ci)[0]
    diff_copies = paired_mmd_difference(np.stack([x] * 5), np.stack([y] * 5), np.stack([y] * 5) + 0.3,
                                        permutations=20, resamples=300, seed=1)
    diff_disagree = paired_mmd_difference(np.stack([x] * 5), np.stack([y] * 5), np.stack([y] * 5) + shifts,
                                          permutations=20, resamples=300, seed=1)
    assert np.diff(diff_disagree.ci)[0] > 2.0 * np.diff(diff_copies.ci)[0]


def test_an_ensemble_of_feature_extractors_averages_their_statistics() -> None:
    """(M, n, d) sets: every statistic is the mean over the members' own (each standardised with its own bandwidth),
    under one shared permutation; one member is the plain test."""
    rng = np.random.default_rng(8)
    x, y = rng.normal(size=(3, 12, 4)), rng.normal(0.4, 1.0, (3, 12, 4))
    members = [mmd_test(x[m], y[m], permutations=100, resamples=0) for m in range(3)]
    ensemble = mmd_test(x, y, permutations=100, resamples=0)
    assert ensemble.mmd2 == pytest.approx(np.mean([t.mmd2 for t in members]), rel=1e-12)
    assert ensemble.bandwidth == pytest.approx(np.mean([t.bandwidth for t in members]), rel=1e-12)
    one = mmd_test(x[:1], y[:1], permutations=100, resamples=30)
    assert one == mmd_test(x[0], y[0], permutations=100, resamples=30)
    paired = [paired_mmd_test(x[m], y[m], permutations=50, resamples=0).mmd2 for m in range(3)]
    assert paired_mmd_test(x, y, permutations=50, resamples=0).mmd2 == pytest.approx(np.mean(paired), rel=1e-12)
    diffs = [paired_mmd_difference(x[m, :6], x[m, 6:], y[m, :6], permutations=20, resamples=0).difference
             for m in range(3)]
    assert paired_mmd_difference(x[:, :6], x[:, 6:], y[:, :6], permutations=20,
                                 resamples=0).difference == pytest.approx(np.mean(diffs), rel=1e-12)
    K, _ = pooled_kernel((x, y))
    assert K.shape == (24, 24) and np.allclose(np.diag(K), 1.0) and np.allclose(K, K.T)
    with pytest.raises(ValueError, match="feature extractors"):
        pooled_kernel((x, y[:2]))


def test_figures_render(tmp_path) -> None:
    from weatheralign.verify.figures import embedding_figure, permutation_figure

    rng = np.random.default_rng(5)
    sets = {"reference": rng.normal(size=(30, 5)), "aligned": rng.normal(size=(30, 5)),
            "unaligned": rng.normal(0.8, 1.0, (30, 5))}
    embedding_figure(sets, "snow: fused features").savefig(tmp_path / "pca.png")
    tests = {k: mmd_test(sets["reference"], sets[k], permutations=200, resamples=0) for k in ("aligned", "unaligned")}
    assert tests["unaligned"].p_value < tests["aligned"].p_value and len(tests["aligned"].null) == 200
    permutation_figure(tests, "snow: MMD² against the reference").savefig(tmp_path / "perm.png")
    assert (tmp_path / "pca.png").stat().st_size > 10_000 and (tmp_path / "perm.png").stat().st_size > 10_000


def test_tests_sharing_a_scale_share_one_kernel_so_their_difference_is_the_paired_one() -> None:
    rng = np.random.default_rng(5)
    ref, a, b = rng.normal(0, 1, (20, 4)), rng.normal(0.2, 1, (15, 4)), rng.normal(0.8, 1, (15, 4))
    scale = (ref, a, b)
    ta, tb = mmd_test(ref, a, 100, 10, scale=scale), mmd_test(ref, b, 100, 10, scale=scale)
    paired = paired_mmd_difference(ref, a, b, 100, 10)
    assert ta.bandwidth == tb.bandwidth == paired.bandwidth
    assert ta.mmd2 == pytest.approx(paired.mmd2_a) and tb.mmd2 == pytest.approx(paired.mmd2_b)
    assert ta.mmd2 - tb.mmd2 == pytest.approx(paired.difference)
    assert mmd_test(ref, a, 100, 10).bandwidth != ta.bandwidth  # its own pool by default
