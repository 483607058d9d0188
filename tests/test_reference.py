"""The `reference` stage: the reference reader (real STF layout, errors, intensity scales), the exact fog processes of
the synthetic reference (pulse integral per beam, per-pixel camera integration), the synthetic reference itself
(layout, sealed truth, determinism, resume) and a real flow run.

Real-data tests use the shared Seeing Through Fog frame in ``../shared/data/real/stf`` and skip without it.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.integrate import quad

from weatheralign.config import ConfigError, params_from_dict
from weatheralign.data.errors import DataFormatError
from weatheralign.data.rings import elevation_deg
from weatheralign.geometry import apply, invert, project
from weatheralign.lidar.fog import fog_intensities, fog_point_arrays, soft_target_response
from weatheralign.medium.fog import LN20
from weatheralign.reference import check_reference, configured_reference, open_reference, reference_root
from weatheralign.reference.camera_exact import fog_radiance
from weatheralign.reference.lidar_exact import (
    FOG,
    TARGET,
    Detector,
    ExactSensor,
    bistatic_overlap,
    exact_returns,
    fog_tables,
    read_out,
    soft_response,
    system_constants,
)
from weatheralign.reference.synthetic import (
    ALPHA_GRID,
    MANIFEST_FILE,
    camera_calibration,
    draw_precipitation_truth,
    draw_truth,
    finalize,
    frame_specs,
    render_frame,
    render_or_resume,
    sealed_truth_path,
    stereo_left_camera,
    synthetic_root,
    tf_tree,
)
from weatheralign.sensors import SYNTHETIC_INTENSITY, PulseSensor

from .conftest import REPO

pytestmark = pytest.mark.usefixtures("shared_prefect_api")  # stages in subprocesses share one Prefect server

STF = REPO.parent / "shared" / "data" / "real" / "stf"
STF_ID = "2019-09-11_19-13-44_00960"
SPLITS = {"clear": "splits/clear.txt", "light": "splits/light_fog.txt", "dense": "splits/dense_fog.txt",
          "snow": "splits/snow.txt", "rain": "splits/rain.txt"}
FOG_SPLITS = {level: SPLITS[level] for level in ("clear", "light", "dense")}
SENSOR = ExactSensor()
L = SENSOR.pulse_length
FAST_SENSOR = PulseSensor(tau_h=SENSOR.tau_h, r1=SENSOR.r1, r2=SENSOR.r2, gamma=SENSOR.gamma,
                          max_range=SENSOR.max_range, saturation=SENSOR.saturation)
"""The fast fog simulator's pulse sensor with the reference LiDAR's pulse, overlap ends, Γ and limits (τ_H = 20 ns:
the fog model's `PulseSensor()`)."""


# ------------------------------------------------------------------------------------------------ small STF trees


def _write_splits(root: Path, levels: dict[str, list[str]], files: dict[str, str] = SPLITS) -> None:
    for level, ids in levels.items():
        path = root / files[level]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("".join(f"{i.rsplit('_', 1)[0]},{i.rsplit('_', 1)[1]}\n" for i in ids))


def _small_tree(root: Path, levels: dict[str, list[str]], scale: float = 255.0, seed: int = 0) -> Path:
    """A tree laid out like the real dataset (nested folders, calib/ files, split files) with small random scans
    (intensities on 0..``scale``) and 96 x 51 images."""
    rng = np.random.default_rng(seed)
    cam = stereo_left_camera(0.05)
    (root / "calib").mkdir(parents=True, exist_ok=True)
    (root / "calib" / "calib_cam_stereo_left.json").write_text(json.dumps(camera_calibration(cam)))
    (root / "calib" / "calib_tf_tree_full.json").write_text(json.dumps(tf_tree()))
    for ids in levels.values():
        for sample_id in ids:
            n = 600
            pts = np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(-2, 2, n),
                                   rng.uniform(0, scale, n), rng.integers(0, 64, n)]).astype("<f4")
            (root / "lidar_hdl64_strongest").mkdir(exist_ok=True)
            pts.tofile(root / "lidar_hdl64_strongest" / f"{sample_id}.bin")
            (root / "cam_stereo_left_lut").mkdir(exist_ok=True)
            Image.new("RGB", (cam.width, cam.height), (120, 120, 120)).save(
                root / "cam_stereo_left_lut" / f"{sample_id}.png")
    _write_splits(root, levels)
    return root


LEVEL_IDS = {"clear": ["rec-a_00001", "rec-a_00002"], "light": ["rec-b_00010"], "dense": ["rec-c_00020"]}


@pytest.fixture(scope="module")
def real_tree(tmp_path_factory) -> Path:
    """The shared real STF frame copied into a nested real-layout tree under six ids, with split files for every
    level (fog, snow and rain)."""
    if not STF.exists():
        pytest.skip(f"real sample not available: {STF}")
    root = tmp_path_factory.mktemp("stf_real_tree")
    levels = {"clear": ["2019-09-11_19-13-44_00960", "2019-09-11_19-13-44_00961"],
              "light": ["2018-02-12_15-39-23_00100"], "dense": ["2018-02-12_15-39-23_00200"],
              "snow": ["2018-02-07_10-40-11_00300"], "rain": ["2018-10-29_14-30-05_00400"]}
    for d in ("lidar_hdl64_strongest", "cam_stereo_left_lut", "calib"):
        (root / d).mkdir()
    for name in ("calib_cam_stereo_left.json", "calib_tf_tree_full.json"):
        shutil.copy(STF / name, root / "calib" / name)
    for ids in levels.values():
        for sample_id in ids:
            shutil.copy(STF / f"lidar_hdl64_strongest_{STF_ID}.bin",
                        root / "lidar_hdl64_strongest" / f"{sample_id}.bin")
            shutil.copy(STF / f"cam_stereo_left_lut_{STF_ID}.png", root / "cam_stereo_left_lut" / f"{sample_id}.png")
    _write_splits(root, levels)
    return root


def test_real_stf_tree_through_the_reference_reader(real_tree):
    ds = open_reference(real_tree, SPLITS, 255.0)
    assert ds.levels == ("clear", "light", "dense", "snow", "rain") and ds.range_folder is None
    assert ds.ids("clear") == ("2019-09-11_19-13-44_00960", "2019-09-11_19-13-44_00961")
    frame = ds.load_frame(ds.ids("light")[0])
    assert frame.source == "stf" and frame.token == "2018-02-12_15-39-23_00100"
    assert frame.lidar.points.shape == (109_431, 5) and frame.lidar.intensity_max == 255.0
    cam = frame.cameras["cam_stereo_left"]
    assert (cam.width, cam.height) == (1792, 768) and cam.range_path is None  # the known crop, no exact range
    np.testing.assert_allclose(cam.K[:2, 2], [988.138054 - 64, 508.051838 - 192])
    assert ds.load_range(ds.ids("dense")[0]) is None  # real data: the caller estimates depth (dense_depth)
    summary = check_reference(ds)
    assert summary["clear"].frames == 2 and summary["clear"].points_per_scan == 109_431
    assert 100 < summary["dense"].mean_intensity_255 < 160 and summary["dense"].with_range == 0
    assert len(ds.intensities("clear")) == 2 * 109_431
    assert summary["snow"].frames == summary["rain"].frames == 1
    assert ds.load_frame(ds.ids("snow")[0]).token == "2018-02-07_10-40-11_00300"
    fog_only = open_reference(real_tree, FOG_SPLITS, 255.0)
    assert fog_only.levels == ("clear", "light", "dense")
    with pytest.raises(KeyError, match="no split 'snow'"):
        fog_only.ids("snow")


def test_real_stf_tree_declared_unit_scale_is_refused(real_tree):
    ds = open_reference(real_tree, SPLITS, 1.0)  # split files and files are fine; the scans are 0..255
    with pytest.raises(DataFormatError, match=r"intensities outside 0\.\.1 .*declared intensity_max = 1"):
        ds.load_scan(ds.ids("clear")[0])


def test_configured_synthetic_reference_not_rendered_yet(tmp_path):
    params = params_from_dict({"paths": {"data": str(tmp_path)}})
    with pytest.raises(DataFormatError, match=r"reference/synthetic does not exist: render .*flows\.reference"):
        configured_reference(params)


def test_configured_stf_source(real_tree, tmp_path):
    params = params_from_dict({"paths": {"data": str(tmp_path)},
                               "reference": {"source": "stf", "stf_root": str(real_tree)}})
    assert reference_root(params) == real_tree
    ds = configured_reference(params)
    assert [len(ds.ids(lv)) for lv in ds.levels] == [2, 1, 1, 1, 1]
    fog_only = params_from_dict({"paths": {"data": str(tmp_path)},
                                 "reference": {"source": "stf", "stf_root": str(real_tree),
                                               "split_files": {"snow": None, "rain": None}}})
    assert configured_reference(fog_only).levels == ("clear", "light", "dense")
    (real_tree / "splits" / "rain.txt").rename(real_tree / "splits" / "rain_moved.txt")
    try:
        with pytest.raises(DataFormatError, match=r"split 'rain': split file .*rain\.txt not found.*"
                                                  r"reference\.split_files\.rain: null"):
            configured_reference(params)
        assert configured_reference(params, ("clear", "light", "dense")).levels == ("clear", "light", "dense")
    finally:
        (real_tree / "splits" / "rain_moved.txt").rename(real_tree / "splits" / "rain.txt")


def test_small_tree_reads_and_unit_scale_works(tmp_path):
    root = _small_tree(tmp_path / "r255", LEVEL_IDS)
    ds = open_reference(root, FOG_SPLITS, 255)
    frame = ds.load_frame("rec-b_00010")
    assert frame.lidar.points.shape == (600, 5) and frame.cameras["cam_stereo_left"].width == 96
    unit = _small_tree(tmp_path / "r1", LEVEL_IDS, scale=1.0)
    ds1 = open_reference(unit, FOG_SPLITS, 1.0)
    scan = ds1.load_scan("rec-a_00001")
    assert scan.intensity_max == 1.0 and scan.points[:, 3].max() <= 1.0
    np.testing.assert_allclose(ds1.intensities("clear", scale=255.0), 255.0 * ds1.intensities("clear"), rtol=1e-6)
    raw = np.fromfile(unit / "lidar_hdl64_strongest" / "rec-a_00001.bin", "<f4").reshape(-1, 5)
    np.testing.assert_array_equal(scan.points, raw)  # kept as stored, scale explicit
    assert check_reference(ds1)["clear"].frames == 2
    # the same 0..1 data declared as 0..255 is the published code's trap: refused for the whole split
    ds_wrong = open_reference(unit, FOG_SPLITS, 255.0)
    with pytest.raises(DataFormatError,
                       match=r"rec-a_00001\.bin: every intensity of the 600 points is <= 1\.0"
                             r".*declare intensity_max = 1\.0"):
        check_reference(ds_wrong, images=False)


def test_small_tree_errors_name_file_and_form(tmp_path):
    root = _small_tree(tmp_path, LEVEL_IDS)
    with pytest.raises(DataFormatError, match=r"split 'light': split file .*light_fog_missing\.txt not found"):
        open_reference(root, {**FOG_SPLITS, "light": "splits/light_fog_missing.txt"}, 255.0)
    (root / "splits" / "empty.txt").write_text("# nothing\n\n")
    with pytest.raises(DataFormatError, match=r"empty\.txt: empty split"):
        open_reference(root, {**FOG_SPLITS, "dense": "splits/empty.txt"}, 255.0)
    (root / "splits" / "ghost.txt").write_text("rec-z,00007\n")
    with pytest.raises(DataFormatError, match=r"ghost\.txt: split 'dense' lists frame rec-z_00007 but .*missing "
                                              r"sensor file.*rec-z_00007\.bin"):
        open_reference(root, {**FOG_SPLITS, "dense": "splits/ghost.txt"}, 255.0)
    (root / "splits" / "twice.txt").write_text("rec-a,00001\n")
    with pytest.raises(DataFormatError, match=r"rec-a_00001 is listed also in split 'clear'"):
        open_reference(root, {**FOG_SPLITS, "dense": "splits/twice.txt"}, 255.0)
    with pytest.raises(DataFormatError, match=r"unknown split level\(s\) \['fog'\]"):
        open_reference(root, {"fog": "splits/clear.txt"}, 255.0)
    with pytest.raises(DataFormatError, match=r"intensity_max = 100.*255 or 1\.0"):
        open_reference(root, FOG_SPLITS, 100.0)
    with pytest.raises(DataFormatError, match="does not exist"):
        open_reference(tmp_path / "nowhere", FOG_SPLITS, 255.0)
    ds = open_reference(root, FOG_SPLITS, 255.0)
    scan = root / "lidar_hdl64_strongest" / "rec-a_00002.bin"
    scan.write_bytes(scan.read_bytes()[:-8])
    with pytest.raises(DataFormatError, match=r"rec-a_00002\.bin: 11992 bytes is not a multiple of the record size 20 "
                                              r"\(expected float32 x 5 per point\)"):
        check_reference(ds)
    np.array([[1, 2, np.nan, 10, 3]], "<f4").tofile(scan)
    with pytest.raises(DataFormatError, match=r"rec-a_00002\.bin: 1 points with NaN/inf coordinates"):
        ds.load_scan("rec-a_00002")
    np.array([[1, 2, 3, 300, 3]], "<f4").tofile(scan)
    with pytest.raises(DataFormatError, match=r"intensities outside 0\.\.255.*declared intensity_max = 255"):
        ds.load_scan("rec-a_00002")
    np.zeros((0, 5), "<f4").tofile(scan)
    with pytest.raises(DataFormatError, match=r"rec-a_00002\.bin: empty scan \(0 points\)"):
        check_reference(ds)


# ------------------------------------------------------------------------------------------------ exact LiDAR


def test_bistatic_overlap_is_exact_disc_overlap():
    r = np.linspace(0.8, 1.1, 301)
    xi = bistatic_overlap(r)
    assert np.all(xi[r <= 0.9] == 0.0) and np.all(xi[r >= 1.0] == 1.0)
    assert np.all(np.diff(xi) >= 0.0)
    # midway the disc centres are kappa = 2 beam radii apart: intersection of radius-1 and radius-2 discs at d = 2
    a = math.acos(1 / 4) + 4 * math.acos(7 / 8) - 0.5 * math.sqrt(1 * 1 * 3 * 5)
    assert bistatic_overlap(0.95) == pytest.approx(a / math.pi, rel=1e-12)


@pytest.mark.parametrize("alpha", [0.0, 0.012, 0.06])
def test_soft_integral_against_quad(alpha):
    tables = fog_tables(alpha)

    def h(r):
        return float(bistatic_overlap(r)) * math.exp(-2 * alpha * r) / r**2

    for R, r0 in [(4.6, np.inf), (1.7, np.inf), (3.0, 2.5), (9.0, 7.0), (40.0, 41.0), (100.0, 97.0), (0.95, 5.0)]:
        a, b = max(R - L, SENSOR.r1), min(R, r0)
        ref = 2 / 299_792_458.0 * quad(lambda r: math.sin(math.pi * (R - r) / L) ** 2 * h(r), a, b,
                                       points=[p for p in (0.9, 1.0) if a < p < b], limit=200, epsrel=1e-12)[0]
        assert float(soft_response(R, r0, tables)) == pytest.approx(ref, rel=5e-5, abs=1e-20)


def test_clear_air_gives_the_clean_intensity_at_the_target():
    r0 = np.array([1.0, 1.5, 7.3, 42.0, 119.0])
    i0 = np.array([5.0, 80.0, 33.0, 2.5, 250.0])
    c = system_constants(r0, i0, np.zeros(5))
    ret = exact_returns(r0, c, 0.0, 0.0)
    np.testing.assert_allclose(ret.power, i0, rtol=1e-12)
    np.testing.assert_allclose(ret.r_peak - L / 2, r0, atol=1e-9)
    assert np.all(ret.source == TARGET)
    none = exact_returns(np.array([np.inf]), np.array([1e9]), 0.0, 0.0)
    assert none.source[0] == 0 and none.power[0] == 0.0


def test_peak_search_against_brute_force_receiver_axis():
    rng = np.random.default_rng(3)
    for alpha, beta in [(0.012, 1.7e-4), (0.055, 7e-4), (0.1, 1.5e-3)]:
        tables = fog_tables(alpha)
        r0 = np.concatenate([rng.uniform(1.0, 110.0, 60), [np.inf, 1.2, 3.0, 4.7, 6.5]])
        c = rng.uniform(1e6, 5e9, len(r0))
        ret = exact_returns(r0, c, alpha, beta, tables=tables)
        for i in range(len(r0)):
            R = np.arange(SENSOR.r1, min(r0[i] + L, SENSOR.listen_end), 2e-4)
            power = beta * soft_response(R, r0[i], tables)
            if np.isfinite(r0[i]):
                inside = (R >= r0[i]) & (R <= r0[i] + L)
                power += np.where(inside, SENSOR.beta_0 * math.exp(-2 * alpha * r0[i]) / r0[i] ** 2
                                  * np.sin(np.pi * (R - r0[i]) / L) ** 2, 0.0)
            j = int(np.argmax(power))
            # the peak is chosen on raw power and reported through R_e² g(R_e) at its reported range
            raw = ret.power[i] / SYNTHETIC_INTENSITY.compensation(max(ret.r_peak[i] - L / 2, SENSOR.r1))
            assert raw == pytest.approx(c[i] * power[j], rel=1e-5)
            assert abs(ret.r_peak[i] - R[j]) < 2e-3


def test_fog_effects_are_monotonic_and_match_the_fast_model():
    rng = np.random.default_rng(5)
    n = 20_000
    r0 = rng.uniform(2.0, 100.0, n)
    r0[:500] = np.inf  # beams without a hard return
    i0 = np.where(np.isfinite(r0), rng.uniform(2, 120, n), 0.0)
    ring = rng.integers(0, 64, n)
    c = system_constants(r0, i0, ring)
    means, fog_share = [], []
    for alpha in (0.0, 0.01, 0.03, 0.06):
        ret = exact_returns(r0, c, alpha, 0.046 * alpha / LN20)
        target = ret.source == TARGET
        means.append(float(ret.power[target].mean()))
        fog_share.append(float((ret.source == FOG).mean()))
        if alpha == 0.06:
            reported = ret.r_peak[ret.source == FOG] - L / 2
            assert np.all(reported < 3.0) and np.median(reported) > 1.0  # fog echoes near the sensor
            # same sensor as the fast simulator: its fog peak and where fog wins agree with ours
            assert FAST_SENSOR == PulseSensor()  # the fog model's sensor, as before
            fast = soft_target_response(alpha, FAST_SENSOR)
            assert ret.r_peak[~np.isfinite(r0)][0] == pytest.approx(fast.r_peak, abs=0.02)
            # one range convention: the fast model reports its fog echo where the exact receiver does (peak - cτ_H/2)
            far = fog_point_arrays(np.array([[100.0, 0.0, 0.0, 50.0, 0.0]], np.float32), None, alpha,
                                   0.046 * alpha / LN20, intensity=SYNTHETIC_INTENSITY, sensor=FAST_SENSOR,
                                   noise_floor=None)
            assert far.labels[0] == 2
            assert float(far.points[0, 0]) == pytest.approx(ret.r_peak[~np.isfinite(r0)][0] - L / 2, abs=0.02)
            exact_tables = fog_tables(alpha)
            assert exact_tables.g_peak == pytest.approx(fast.g_peak, rel=0.01)
            hard_r = r0[np.isfinite(r0)]
            fast_fog = fog_intensities(hard_r, i0[np.isfinite(r0)], alpha, 0.046 * alpha / LN20,
                                       intensity=SYNTHETIC_INTENSITY, sensor=FAST_SENSOR, noise_floor=None).labels == 2
            agree = np.mean(fast_fog == (ret.source[np.isfinite(r0)] == FOG))
            assert agree > 0.99
    assert means[0] > means[1] > means[2] > means[3]
    assert fog_share[0] == 0.0 and fog_share[1] < fog_share[2] < fog_share[3]
    # a beam without return takes its ring's median constant
    sky = np.flatnonzero(~np.isfinite(r0))[0]
    same = np.isfinite(r0) & (ring == ring[sky])
    assert c[sky] == pytest.approx(np.median(i0[same] / (SENSOR.beta_0 * SYNTHETIC_INTENSITY.gain(r0[same]))))


def test_read_out_floor_quantisation_and_seed():
    ret = exact_returns(np.array([5.0, 30.0, 60.0, np.inf] * 500), np.full(2000, 3e6), 0.04, 6e-4)
    det = Detector(intensity_noise_std=0.5, intensity_noise_rel=0.03, noise_floor=1.0, range_noise_std=0.01)
    a = read_out(ret, SENSOR, det, np.random.default_rng(1))
    b = read_out(ret, SENSOR, det, np.random.default_rng(1))
    np.testing.assert_array_equal(a.intensity, b.intensity)
    np.testing.assert_array_equal(a.range, b.range)
    assert a.intensity.min() >= 1.0 and np.all(a.intensity == np.round(a.intensity)) and a.intensity.max() <= 255
    assert np.all((a.range >= SENSOR.min_range) & (a.range <= SENSOR.max_range))


# ------------------------------------------------------------------------------------------------ exact camera


@pytest.mark.parametrize("alpha", [0.004, 0.012, 0.05, 0.2])
def test_camera_integral_matches_koschmieder(alpha):
    rng = np.random.default_rng(7)
    n = 5000
    J = rng.uniform(0, 1, (n, 3))
    ell = rng.uniform(0.0, 400.0, n)
    ell[:50] = np.inf
    A = np.array([0.55, 0.6, 0.65])
    out = fog_radiance(J, ell, alpha, A, sky_distance=2000.0)
    length = np.where(np.isfinite(ell), ell, 2000.0)
    t = np.exp(-alpha * length)[:, None]
    np.testing.assert_allclose(out, J * t + A * (1 - t), atol=1e-9)
    np.testing.assert_array_equal(fog_radiance(J, ell, 0.0, A), J)


# ------------------------------------------------------------------------------------------------ synthetic reference

TINY = {"frames_per_split": 2, "lidar": {"firings_per_ring": 360}, "camera": {"image_scale": 0.1}}


def _tiny_params(data: Path, **reference: object):
    return params_from_dict({"paths": {"data": str(data)}, "tracking": {"enabled": False},
                             "reference": {**TINY, **reference}})


def _render_all(params) -> list:
    cfg = params.reference
    outcomes = [render_or_resume(spec, cfg, params.paths.data) for spec in frame_specs(cfg)]
    finalize(cfg, params.paths.data, [rec for rec, _ in outcomes])
    return outcomes


@pytest.fixture(scope="module")
def tiny_reference(tmp_path_factory):
    data = tmp_path_factory.mktemp("reference_data")
    params = _tiny_params(data)
    outcomes = _render_all(params)
    return params, outcomes


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_synthetic_reference_layout_is_readable(tiny_reference):
    params, outcomes = tiny_reference
    assert all(now for _, now in outcomes) and len(outcomes) == 10
    ds = configured_reference(params)
    assert ds.root == synthetic_root(params.paths.data) and ds.range_folder == "range_cam_stereo_left"
    assert ds.levels == ("clear", "light", "dense", "snow", "rain")
    ids = {level: ds.ids(level) for level in ds.levels}
    assert [len(v) for v in ids.values()] == [2, 2, 2, 2, 2]
    assert len(set(sum(map(list, ids.values()), []))) == 10  # no frame in two levels
    summary = check_reference(ds)
    assert all(s.with_range == 2 for s in summary.values())
    means = [summary[level].mean_intensity_255 for level in ("clear", "light", "dense")]
    assert means[0] > means[1] > means[2]
    # dense fog loses the far returns (a 16 % drop here; the near-return fraction depends on what passes the ego in two
    # frames of different scenes and is no test of fog)
    assert summary["dense"].points_per_scan < 0.95 * summary["clear"].points_per_scan
    assert all(0.0 <= s.near_fraction <= 1.0 for s in summary.values())
    # the clear frame that sees sky (a truck may fill the other's view)
    token = max(ids["clear"], key=lambda t: int(np.isinf(ds.load_range(t)).sum()))
    frame = ds.load_frame(token)
    pts = frame.lidar.points
    assert frame.lidar.intensity_max == 255.0 and pts[:, 3].min() >= 1.0 and np.all(pts[:, 3] == np.round(pts[:, 3]))
    # STF channel order: channel 0 is the lowest laser
    far = np.linalg.norm(pts[:, :2], axis=1) > 3.5
    elev = elevation_deg(pts[far])
    assert np.median(elev[pts[far, 4] == 63]) > np.median(elev[pts[far, 4] == 40]) > np.median(elev[pts[far, 4] == 0])
    # the camera calibration and range map agree with the scan: projected points land on their own range
    cam = frame.cameras["cam_stereo_left"]
    rng_map = ds.load_range(frame.token)
    assert rng_map.shape == (cam.height, cam.width) == (102, 192) and np.isinf(rng_map).any()
    pc = apply(invert(cam.T_ego_cam), pts[:, :3])
    front = pc[:, 2] > 1.0
    uv, _ = project(pc[front], cam.K)
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    ray = np.linalg.norm(pc[front][inside], axis=1)
    rel = np.abs(rng_map[v[inside], u[inside]] / ray - 1.0)
    assert inside.sum() > 200 and np.median(rel) < 0.02
    manifest = json.loads((ds.root / MANIFEST_FILE).read_text())
    assert manifest["intensity_max"] == 255.0 and "alpha" not in json.dumps(manifest)


def test_sealed_truth_is_outside_the_root_and_off_grid(tiny_reference):
    from weatheralign.reference.ground import draw_ground_truth
    from weatheralign.reference.overcast import draw_overcast_truth

    params, _ = tiny_reference
    path = sealed_truth_path(params.paths.data)
    truth = json.loads(path.read_text())
    assert set(truth) == {"light", "dense", "snow", "rain"} and set(truth["light"]) == {"alpha", "beta"}
    root = synthetic_root(params.paths.data)
    assert root not in path.parents
    assert not any(b"alpha" in data or b"rate_mm_h" in data for data in _files(root).values())
    cfg = params.reference
    pc = cfg.precipitation
    for level, (lo, hi), depth, (d_lo, d_hi) in (
            ("snow", pc.snow_rate_mm_h, "snow_depth_m", pc.snow_depth_m),
            ("rain", pc.rain_rate_mm_h, "film_depth_m", pc.wet_film_depth_m)):
        light = {"sun_transmittance", "zenith_luminance"} if pc.overcast else set()
        assert set(truth[level]) == {"rate_mm_h", depth} | light and lo <= truth[level]["rate_mm_h"] <= hi
        assert d_lo <= truth[level][depth] <= d_hi and draw_ground_truth(cfg)[level] == truth[level][depth]
        if light:
            sky = draw_overcast_truth(cfg)[level]
            assert (truth[level]["sun_transmittance"], truth[level]["zenith_luminance"]) == (
                sky.sun_transmittance, sky.zenith_luminance)
            assert pc.overcast_sun_transmittance[0] <= sky.sun_transmittance <= pc.overcast_sun_transmittance[1]
            assert pc.overcast_zenith_luminance[0] <= sky.zenith_luminance <= pc.overcast_zenith_luminance[1]
    assert not any(b"depth_m" in data for data in _files(root).values())
    assert draw_precipitation_truth(cfg)["snow"] == truth["snow"]["rate_mm_h"]
    for level, (lo, hi) in (("light", cfg.alpha_light), ("dense", cfg.alpha_dense)):
        alpha, beta = truth[level]["alpha"], truth[level]["beta"]
        assert lo <= alpha <= hi and min(abs(alpha / g - 1) for g in ALPHA_GRID) >= 0.03
        factor = beta * (LN20 / alpha) / 0.023
        assert 1.0 <= factor <= 2.0
    assert draw_truth(cfg)["dense"].alpha == truth["dense"]["alpha"]
    assert draw_truth(cfg.model_copy(update={"seed": cfg.seed + 1}))["dense"].alpha != truth["dense"]["alpha"]


def test_reference_scenes_are_not_the_worlds(tiny_reference):
    from weatheralign.world.build import scene_specs

    params, _ = tiny_reference
    world_seeds = {s.seed for s in scene_specs(params.world.model_copy(update={"seed": params.reference.seed}))}
    world_seeds |= {s.seed for s in scene_specs(params.world)}
    assert not world_seeds & {s.scene_seed for s in frame_specs(params.reference)}


def test_synthetic_reference_is_deterministic_and_resumes(tiny_reference, tmp_path):
    params, _ = tiny_reference
    root = synthetic_root(params.paths.data)
    again = _tiny_params(tmp_path)
    outcomes = _render_all(again)
    assert all(now for _, now in outcomes)
    assert _files(root) == _files(synthetic_root(tmp_path))  # same params, same bytes
    assert sealed_truth_path(tmp_path).read_bytes() == sealed_truth_path(params.paths.data).read_bytes()
    # resume: nothing is redone; a deleted file or a changed parameter redoes what it affects
    before = {p: p.stat().st_mtime_ns for p in synthetic_root(tmp_path).rglob("*.bin")}
    assert not any(now for _, now in _render_all(again))
    assert before == {p: p.stat().st_mtime_ns for p in synthetic_root(tmp_path).rglob("*.bin")}
    victim = sorted(before)[0]
    victim.unlink()
    assert sum(now for _, now in _render_all(again)) == 1 and victim.is_file()
    more = _tiny_params(tmp_path, frames_per_split=3)
    assert sum(now for _, now in _render_all(more)) == 5  # frame k does not depend on the frame count
    assert len(list((synthetic_root(tmp_path) / "lidar_hdl64_strongest").iterdir())) == 15
    assert sum(now for _, now in _render_all(again)) == 0  # back to 2 per split: stale frames removed
    assert len(list((synthetic_root(tmp_path) / "lidar_hdl64_strongest").iterdir())) == 10
    fog_only = _tiny_params(tmp_path, split_files={"snow": None, "rain": None})
    assert sum(now for _, now in _render_all(fog_only)) == 0  # the fog frames do not depend on the weather splits
    assert len(list((synthetic_root(tmp_path) / "lidar_hdl64_strongest").iterdir())) == 6
    assert set(json.loads(sealed_truth_path(tmp_path).read_text())) == {"light", "dense"}
    changed = _tiny_params(tmp_path, camera={"image_scale": 0.1, "noise_std": 0.02})
    assert sum(now for _, now in _render_all(changed)) == 10


def test_render_frame_fog_physics(tiny_reference):
    """Fog dims and removes returns; its own echo (a few metres out) stays under the floor of the reference's
    raw-power detector (a 10 % target at the floor at 50 m) and is reported by one 100x more sensitive, more often
    the denser the fog (docs/physics.md 3.5)."""
    params, _ = tiny_reference
    cfg = params.reference
    spec = next(s for s in frame_specs(cfg) if s.level == "dense")
    truth = draw_truth(cfg)
    clear = render_frame(spec, cfg, truth["clear"])
    dense = render_frame(spec, cfg, truth["dense"])
    light = render_frame(spec, cfg, truth["light"])
    np.testing.assert_array_equal(clear.range, dense.range)  # the same geometry
    assert clear.stats["fog_returns"] == light.stats["fog_returns"] == dense.stats["fog_returns"] == 0
    assert len(clear.points) > len(light.points) > len(dense.points)
    assert clear.stats["mean_intensity"] > light.stats["mean_intensity"] > dense.stats["mean_intensity"]
    keen = cfg.model_copy(update={"lidar": cfg.lidar.model_copy(update={"noise_floor": cfg.lidar.noise_floor / 100})})
    clear, light, dense = (render_frame(spec, keen, truth[k]) for k in ("clear", "light", "dense"))
    assert clear.stats["fog_returns"] == 0 < light.stats["fog_returns"] < dense.stats["fog_returns"]
    near = lambda f: int((np.linalg.norm(f.points[:, :3], axis=1) < 3.0).sum())  # noqa: E731
    assert near(dense) > near(clear)
    # the camera: fog lowers contrast and brightens dark pixels towards the airlight
    assert dense.image.astype(float).std() < light.image.astype(float).std() < clear.image.astype(float).std()


def test_reference_config_validation():
    with pytest.raises(ConfigError, match=r"reference.frames_per_split = 0 is invalid"):
        params_from_dict({"reference": {"frames_per_split": 0}})
    with pytest.raises(ConfigError, match=r"alpha_light \[0\.02, 0\.05\] must lie below alpha_dense"):
        params_from_dict({"reference": {"alpha_light": [0.02, 0.05], "alpha_dense": [0.03, 0.07]}})
    with pytest.raises(ConfigError, match=r"source 'stf' needs stf_root"):
        params_from_dict({"reference": {"source": "stf"}})
    with pytest.raises(ConfigError, match=r"reference.intensity_max = 100 is invalid"):
        params_from_dict({"reference": {"intensity_max": 100}})
    with pytest.raises(ConfigError, match=r"overlap_r1_m .* < overlap_r2_m"):
        params_from_dict({"reference": {"lidar": {"overlap_r1_m": 1.0, "overlap_r2_m": 0.9}}})
    p = params_from_dict({"reference": {"source": "stf", "stf_root": "/data/stf", "intensity_max": 1}})
    assert p.reference.intensity_max == 1.0


# ------------------------------------------------------------------------------------------------ the flow


@pytest.mark.slow
@pytest.mark.flow
def test_reference_flow_writes_metrics_figure_and_resumes(tmp_path):
    from mlflow.tracking import MlflowClient

    env = {**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING",
           "WEATHERALIGN_PIPELINE_ID": "test-reference"}
    args = [sys.executable, "-m", "flows.reference", "--params", str(REPO / "params.yaml"),
            "--set", f"paths.data={tmp_path / 'data'}", "--set", f"paths.reports={tmp_path / 'reports'}",
            "--set", f"tracking.mlflow_uri=sqlite:///{tmp_path / 'mlflow.db'}", "--set", "run.show_progress=false",
            "--set", "reference.frames_per_split=2", "--set", "reference.lidar.firings_per_ring=360",
            "--set", "reference.camera.image_scale=0.1"]
    run = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    metrics = json.loads((tmp_path / "reports" / "reference" / "details.json").read_text())
    assert metrics["source"] == "synthetic" and metrics["root"] == "data/reference/synthetic"
    assert metrics["frames_total"] == 10 and metrics["frames_rendered_this_run"] == 10
    assert metrics["particle_returns_per_scan"]["snow"] > 0 and metrics["particle_returns_per_scan"]["clear"] == 0
    assert (metrics["splits"]["snow"]["isolated_per_scan"]
            > 10 * max(1.0, metrics["splits"]["clear"]["isolated_per_scan"]))
    splits = metrics["splits"]
    assert splits["clear"]["mean_intensity"] > splits["light"]["mean_intensity"] > splits["dense"]["mean_intensity"]
    assert all(s["points_per_scan"] > 10_000 for s in splits.values())
    assert (tmp_path / "reports" / "reference" / "overview.png").stat().st_size > 20_000
    assert (tmp_path / "data" / "reference" / "sealed_truth.json").is_file()
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("weatheralign")
    child = next(r for r in client.search_runs([exp.experiment_id], "tags.stage = 'reference' AND tags.kind = 'stage'"))
    assert child.data.metrics["frames_total"] == 10 and "reference.seed" in child.data.params
    snow = client.search_runs([exp.experiment_id], "tags.weather = 'snow' AND tags.stage = 'reference'")
    assert len(snow) == 1 and snow[0].data.metrics["particle_returns_per_scan"] > 0
    dense = client.search_runs([exp.experiment_id], "tags.weather = 'fog' AND tags.severity = 'dense'")
    assert len(dense) == 1 and dense[0].data.metrics["frames"] == 2
    assert {a.path for a in client.list_artifacts(child.info.run_id, "figures")} == {"figures/overview.png"}
    run = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    again = json.loads((tmp_path / "reports" / "reference" / "details.json").read_text())
    assert again["frames_rendered_this_run"] == 0 and again["splits"] == splits
