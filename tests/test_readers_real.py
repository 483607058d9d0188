"""Readers for real sensor data: Seeing Through Fog (STF), KITTI, and the Velodyne ring tables.

Real-sample tests read ``../shared/data/real`` next to the repository and skip when it is absent; error-case and
layout tests build their own small files under ``tmp_path``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage
from scipy.spatial.transform import Rotation

from weatheralign.data.errors import DataFormatError
from weatheralign.data.kitti import load_kitti_frame, read_kitti_calib
from weatheralign.data.rings import (
    HDL32E_ELEVATIONS_DEG,
    HDL64E_ELEVATIONS_DEG,
    elevation_deg,
    rings_from_elevation,
)
from weatheralign.data.stf import crop_intrinsics, load_stf_frame, read_stf_split
from weatheralign.geometry import apply, check_rigid, invert, project

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
STF = REAL / "stf"
KITTI = REAL / "kitti"
STF_ID = "2019-09-11_19-13-44_00960"


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real sample not available: {path}")
    return path


@pytest.fixture(scope="module")
def stf_frame():
    return load_stf_frame(_need(STF), STF_ID)


@pytest.fixture(scope="module")
def kitti_frame():
    _need(KITTI)
    return load_kitti_frame(KITTI / "000008.bin", KITTI / "000008.png", KITTI / "calib.json")


def _camera_points(frame, channel):
    cam = frame.cameras[channel]
    pc = apply(np.linalg.inv(cam.T_ego_cam), frame.lidar.points[:, :3])
    uv, z = project(pc, cam.K)
    return cam, uv, z


# ----------------------------------------------------------------------------------------------- ring tables


def test_ring_tables_match_datasheet_layout():
    assert HDL32E_ELEVATIONS_DEG.shape == (32,)
    assert HDL32E_ELEVATIONS_DEG[0] == pytest.approx(10.67) and HDL32E_ELEVATIONS_DEG[-1] == pytest.approx(-30.67)
    np.testing.assert_allclose(np.diff(HDL32E_ELEVATIONS_DEG), -4 / 3, atol=2e-3)
    assert HDL64E_ELEVATIONS_DEG.shape == (64,)
    upper, lower = HDL64E_ELEVATIONS_DEG[:32], HDL64E_ELEVATIONS_DEG[32:]
    assert upper[0] == pytest.approx(2.0) and upper[-1] == pytest.approx(-8.33)
    assert lower[0] == pytest.approx(-8.83) and lower[-1] == pytest.approx(-24.33)
    np.testing.assert_allclose(np.diff(upper), -1 / 3, atol=1e-3)
    np.testing.assert_allclose(np.diff(lower), -0.5, atol=1e-9)
    assert np.all(np.diff(HDL64E_ELEVATIONS_DEG) < 0)
    with pytest.raises(ValueError):
        HDL64E_ELEVATIONS_DEG[0] = 5.0  # constants are read-only


@pytest.mark.parametrize("table", [HDL32E_ELEVATIONS_DEG, HDL64E_ELEVATIONS_DEG])
def test_rings_from_elevation_exact_and_nearest(table):
    rng = np.random.default_rng(0)
    n = len(table)
    azimuth = rng.uniform(-np.pi, np.pi, n)
    dist = rng.uniform(3.0, 60.0, n)

    def points(elev_deg):
        e = np.radians(elev_deg)
        return np.stack([dist * np.cos(e) * np.cos(azimuth), dist * np.cos(e) * np.sin(azimuth), dist * np.sin(e)], 1)

    rings = rings_from_elevation(points(table), table)
    assert rings.dtype == np.float32 and rings.shape == (n,)
    np.testing.assert_array_equal(rings, np.arange(n))
    gaps = np.abs(np.diff(table))
    # 30 % of the way towards the next (lower) laser still belongs to this laser; 70 % belongs to the next one
    np.testing.assert_array_equal(rings_from_elevation(points(np.r_[table[:-1] - 0.3 * gaps, table[-1]]), table),
                                  np.arange(n))
    np.testing.assert_array_equal(rings_from_elevation(points(np.r_[table[:-1] - 0.7 * gaps, table[-1]]), table),
                                  np.r_[np.arange(1, n), n - 1])
    # beyond the table: clamp to the extreme rings
    far = rings_from_elevation(np.array([[10.0, 0.0, 10.0], [10.0, 0.0, -10.0]]), table)
    np.testing.assert_array_equal(far, [0, n - 1])


def test_rings_from_elevation_any_table_order_and_bad_input():
    table = np.array([-10.0, 5.0, 0.0])  # unsorted: ring index = table position
    xyz = np.array([[10.0, 0.0, np.tan(np.radians(4.0)) * 10], [0.0, 10.0, -np.tan(np.radians(9.0)) * 10],
                    [-5.0, 0.0, 0.1]])
    np.testing.assert_array_equal(rings_from_elevation(xyz, table), [1, 0, 2])
    assert rings_from_elevation(np.zeros((0, 3)), table).shape == (0,)
    with pytest.raises(DataFormatError):
        rings_from_elevation(np.zeros((4, 2)), table)
    with pytest.raises(DataFormatError):
        rings_from_elevation(xyz, np.array([]))


# ------------------------------------------------------------------------------------------------ STF, real


def test_stf_real_scan(stf_frame):
    lidar = stf_frame.lidar
    assert stf_frame.source == "stf" and stf_frame.token == STF_ID
    assert lidar.points.shape == (109_431, 5) and lidar.points.dtype == np.float32
    ring = lidar.points[:, 4]
    assert ring.min() == 0 and ring.max() == 63 and np.all(ring == np.round(ring))
    assert len(np.unique(ring)) == 64 and lidar.num_rings == 64
    intensity = lidar.points[:, 3]
    assert intensity.min() >= 0 and intensity.max() <= 255 and lidar.intensity_max == 255.0
    assert np.any(intensity != np.round(intensity))  # kept as stored, not rounded or rescaled
    raw = np.fromfile(STF / f"lidar_hdl64_strongest_{STF_ID}.bin", dtype="<f4").reshape(-1, 5)
    np.testing.assert_array_equal(lidar.points, raw)
    np.testing.assert_array_equal(lidar.T_ego_lidar, np.eye(4))
    np.testing.assert_array_equal(lidar.T_global_ego, np.eye(4))


def test_stf_real_channel_order_counts_upwards(stf_frame):
    # documented in weatheralign.data.stf: ring = raw channel, which rises with elevation (unlike rings.py tables)
    p = stf_frame.lidar.points
    far = np.linalg.norm(p[:, :3], axis=1) > 8
    elev = elevation_deg(p)
    medians = [np.median(elev[far & (p[:, 4] == c)]) for c in range(64) if np.sum(far & (p[:, 4] == c)) >= 10]
    assert len(medians) >= 45 and np.all(np.diff(medians) > 0)
    assert medians[0] < -20 and medians[-1] > 2


def test_stf_real_camera_calibration(stf_frame):
    cam = stf_frame.cameras["cam_stereo_left"]
    assert (cam.width, cam.height) == (1792, 768)
    assert cam.load_image().shape == (768, 1792, 3)
    # rectified P of the 1920 x 1024 camera, shifted by the (64, 192) crop of the shipped image
    f, cx, cy = 2355.722801, 988.138054, 508.051838
    np.testing.assert_allclose(cam.K, [[f, 0, cx - 64], [0, f, cy - 192], [0, 0, 1]])
    T = check_rigid(cam.T_ego_cam, "T_lidar_cam")
    # body offsets in the tf tree: camera (2.117, 0.087, 0.891) vs LiDAR (1.4185, -0.001, 1.302): ~0.7 m ahead,
    # 0.09 m left, 0.41 m below the LiDAR
    np.testing.assert_allclose(T[:3, 3], [0.69, 0.09, -0.42], atol=0.03)
    optical_axis, image_right, image_down = T[:3, 2], T[:3, 0], T[:3, 1]
    assert optical_axis @ [1, 0, 0] > 0.999 and image_right @ [0, -1, 0] > 0.999 and image_down @ [0, 0, -1] > 0.999


def test_stf_real_points_in_front_land_in_image(stf_frame):
    cam, uv, z = _camera_points(stf_frame, "cam_stereo_left")
    # in front: 10..80 m deep and inside the horizontal field of view of the image
    front = (z > 10) & (z < 80) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width)
    assert front.sum() > 3000
    inside = front & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert inside.sum() / front.sum() > 0.8


def test_stf_real_ground_depth_increases_upward(stf_frame):
    cam, uv, z = _camera_points(stf_frame, "cam_stereo_left")
    p = stf_frame.lidar.points
    road = (p[:, 2] < -1.5) & (np.abs(p[:, 1]) < 1.5) & (p[:, 0] > 8) & (p[:, 0] < 40)
    assert road.sum() > 500
    u, v = uv[road, 0], uv[road, 1]
    assert np.all((u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height))  # the road ahead is in the picture
    edges = np.arange(8.0, 41.0, 4.0)
    bins = np.digitize(z[road], edges)
    mean_v = [v[bins == b].mean() for b in range(1, len(edges)) if np.any(bins == b)]
    assert len(mean_v) >= 6 and np.all(np.diff(mean_v) < 0)  # farther road -> higher in the image
    left = (p[:, 1] > 3) & (z > 5) & (z < 40)
    right = (p[:, 1] < -3) & (z > 5) & (z < 40)
    assert np.all(uv[left, 0] < cam.K[0, 2]) and np.all(uv[right, 0] > cam.K[0, 2])


def _edge_alignment(points, image, T_cam_lidar, K, width, height):
    """Mean image-gradient magnitude (relative to the image mean) under LiDAR depth-discontinuity points."""
    r = np.linalg.norm(points[:, :3], axis=1)
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    jump = np.zeros(len(points))
    for ring in np.unique(points[:, 4]):
        idx = np.flatnonzero(points[:, 4] == ring)
        idx = idx[np.argsort(azimuth[idx])]
        rr = r[idx]
        jump[idx] = np.maximum(np.r_[0.0, rr[:-1] - rr[1:]], np.r_[rr[1:] - rr[:-1], 0.0])
    edge = (jump > 0.25) & (r > 2.5)
    weight = np.sqrt(np.clip(jump[edge], 0, 10))
    gray = image.astype(np.float64).mean(axis=2)
    grad = ndimage.gaussian_filter(np.hypot(ndimage.sobel(gray, 0), ndimage.sobel(gray, 1)), 2.0)
    uv, z = project(apply(T_cam_lidar, points[edge, :3]), K)
    ok = (z > 1) & (uv[:, 0] >= 0) & (uv[:, 0] < width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < height - 1)
    sampled = grad[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
    return float((weight[ok] * sampled).sum() / weight[ok].sum() / grad.mean())


def test_stf_real_crop_offset_aligns_depth_edges_with_image_edges(stf_frame):
    cam = stf_frame.cameras["cam_stereo_left"]
    image = cam.load_image()
    T_cam_lidar = invert(cam.T_ego_cam)

    def score(K):
        return _edge_alignment(stf_frame.lidar.points, image, T_cam_lidar, K, cam.width, cam.height)

    ours = score(cam.K)
    uncropped = crop_intrinsics(cam.K, -64, -192)  # K of the full 1920 x 1024 image, used as if not cropped
    rivals = [score(uncropped)] + [score(crop_intrinsics(cam.K, dx, dy)) for dx, dy in
                                   [(0, 64), (0, -64), (64, 0), (-64, 0)]]
    assert ours > 1.4
    assert all(ours > 1.05 * s for s in rivals), (ours, rivals)


def test_stf_explicit_crop_offset(stf_frame):
    frame = load_stf_frame(STF, STF_ID, crop_offset=(0, 0))
    np.testing.assert_allclose(frame.cameras["cam_stereo_left"].K[:2, 2], [988.138054, 508.051838])
    with pytest.raises(DataFormatError, match="does not fit"):
        load_stf_frame(STF, STF_ID, crop_offset=(200, 0))
    no_cam = load_stf_frame(STF, STF_ID, camera_folder=None)
    assert no_cam.cameras == {} and len(no_cam.lidar.points) == 109_431


# ---------------------------------------------------------------------------------------------- KITTI, real


def test_kitti_real_scan(kitti_frame):
    lidar = kitti_frame.lidar
    assert kitti_frame.source == "kitti" and kitti_frame.token == "000008"
    assert lidar.points.shape == (17_238, 5) and lidar.points.dtype == np.float32
    raw = np.fromfile(KITTI / "000008.bin", dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(lidar.points[:, :4], raw)
    assert lidar.intensity_max == 1.0 and 0 <= lidar.points[:, 3].min() and lidar.points[:, 3].max() <= 1.0
    assert lidar.intensity_255().max() == pytest.approx(255 * raw[:, 3].max(), rel=1e-6)
    assert lidar.num_rings == 64
    np.testing.assert_array_equal(lidar.T_ego_lidar, np.eye(4))


def test_kitti_real_projection_reproduces_calibration(kitti_frame):
    calib = json.loads((KITTI / "calib.json").read_text())
    cam, uv, z = _camera_points(kitti_frame, "image_2")
    assert (cam.width, cam.height) == tuple(calib["image_size_wh"])
    np.testing.assert_allclose(cam.K, np.asarray(calib["P2_3x4"])[:, :3])
    hom = np.c_[kitti_frame.lidar.points[:, :3].astype(np.float64), np.ones(len(uv))]
    R0, Tr = np.eye(4), np.eye(4)
    R0[:3, :3] = calib["R0_rect_3x3"]
    Tr[:3] = calib["Tr_velo_to_cam_3x4"]
    product = hom @ (np.asarray(calib["P2_3x4"]) @ R0 @ Tr).T
    stated = hom @ np.asarray(calib["lidar_to_image_4x4"]).T
    assert np.all(z > 0)
    # exact: K and the baseline-folded T_cam_velo reproduce P2 @ R0_rect @ Tr_velo_to_cam
    np.testing.assert_allclose(uv, product[:, :2] / product[:, 2:], rtol=0, atol=1e-6)
    # the stored lidar_to_image_4x4 differs from the product of the stored matrices by up to 2e-5 in its entries
    # (rounding where it was computed), i.e. ~1.5e-5 px; agreement to 1e-4 px is the best this reference allows
    np.testing.assert_allclose(uv, stated[:, :2] / stated[:, 2:3], rtol=0, atol=1e-4)
    # a rigid (transpose) inverse is good to ~5e-5 px only (Tr_velo_to_cam is orthonormal to ~1e-7)
    rigid_uv, _ = project(apply(invert(cam.T_ego_cam), kitti_frame.lidar.points[:, :3]), cam.K)
    np.testing.assert_allclose(rigid_uv, uv, rtol=0, atol=1e-4)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert inside.mean() > 0.99  # the sample scan was cropped to the camera view


def test_kitti_real_rings_from_elevation(kitti_frame):
    points = kitti_frame.lidar.points
    rings = points[:, 4].astype(int)
    distinct = np.unique(rings)
    # the sample is cropped to the camera view (elevations about -14.7..+3.4 deg), so only the upper ~45 of the 64
    # lasers are present; the ones present must form one contiguous block starting at ring 0
    assert len(distinct) >= 40 and distinct[0] == 0
    np.testing.assert_array_equal(distinct, np.arange(distinct[-1] + 1))
    elev = elevation_deg(points)
    mean_elev = np.array([elev[rings == r].mean() for r in distinct])
    assert np.all(np.diff(mean_elev) < 0)  # ring 0 highest, monotonically downwards
    far = np.linalg.norm(points[:, :3], axis=1) > 10  # beyond the laser-offset parallax
    assert np.median(np.abs(elev[far] - HDL64E_ELEVATIONS_DEG[rings[far]])) < 0.2


def test_kitti_txt_calibration_matches_json(tmp_path):
    calib = json.loads((_need(KITTI) / "calib.json").read_text())
    txt = tmp_path / "000008.txt"
    fmt = lambda m: " ".join(repr(float(v)) for v in np.ravel(m))  # noqa: E731
    txt.write_text(
        f"P0: {fmt(np.zeros(12))}\nP2: {fmt(calib['P2_3x4'])}\nR0_rect: {fmt(calib['R0_rect_3x3'])}\n"
        f"Tr_velo_to_cam: {fmt(calib['Tr_velo_to_cam_3x4'])}\nTr_imu_to_velo: {fmt(np.eye(3, 4))}\n"
    )
    from_txt = read_kitti_calib(txt)
    from_json = read_kitti_calib(KITTI / "calib.json")
    np.testing.assert_array_equal(from_txt.T_cam_velo, from_json.T_cam_velo)
    np.testing.assert_array_equal(from_txt.K, from_json.K)
    assert from_txt.image_size is None and from_json.image_size == (1242, 375)
    frame = load_kitti_frame(KITTI / "000008.bin", KITTI / "000008.png", txt)
    assert frame.cameras["image_2"].width == 1242
    # the baseline column of P2 is a real translation: the image_2 centre is ~6 cm left of camera 0
    assert from_json.T_cam_velo[0, 3] - from_json.T_cam0_velo[0, 3] == pytest.approx(44.85728 / 721.5377, rel=0.05)


# ------------------------------------------------------------------------------------ error cases (tmp_path)


def _kitti_json(tmp_path: Path, **overrides) -> Path:
    calib = {
        "image_size_wh": [64, 32],
        "P2_3x4": [[50.0, 0.0, 32.0, 5.0], [0.0, 50.0, 16.0, 0.0], [0.0, 0.0, 1.0, 0.0]],
        "R0_rect_3x3": np.eye(3).tolist(),
        "Tr_velo_to_cam_3x4": [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, -0.3]],
    }
    calib.update(overrides)
    calib = {k: v for k, v in calib.items() if v is not None}
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(calib))
    return path


def _kitti_bin(tmp_path: Path, points=None) -> Path:
    pts = np.array([[10.0, 0.5, -1.0, 0.3], [20.0, -2.0, 0.5, 0.9]], np.float32) if points is None else points
    path = tmp_path / "000001.bin"
    np.asarray(pts, dtype="<f4").tofile(path)
    return path


def test_kitti_small_frame_loads(tmp_path):
    Image.new("RGB", (64, 32)).save(tmp_path / "000001.png")
    frame = load_kitti_frame(_kitti_bin(tmp_path), tmp_path / "000001.png", _kitti_json(tmp_path))
    cam = frame.cameras["image_2"]
    # point straight ahead at 10 m, 0.5 m left, 1 m down -> camera (-0.5, 1.0, 9.7), then the 0.1 m baseline shift
    uv, z = project(apply(invert(cam.T_ego_cam), frame.lidar.points[:1, :3]), cam.K)
    np.testing.assert_allclose(uv[0], [32 + 50 * (-0.5 + 0.1) / 9.7, 16 + 50 * 1.0 / 9.7], atol=1e-9)
    assert load_kitti_frame(_kitti_bin(tmp_path), None, _kitti_json(tmp_path)).cameras == {}


def test_kitti_truncated_bin(tmp_path):
    path = tmp_path / "000001.bin"
    path.write_bytes(np.zeros(4 * 4 + 3, np.uint8).tobytes())
    with pytest.raises(DataFormatError, match=r"000001\.bin.*not a multiple of the record size 16"):
        load_kitti_frame(path, None, _kitti_json(tmp_path))


def test_kitti_nan_point(tmp_path):
    path = _kitti_bin(tmp_path, [[1.0, 2.0, 3.0, 0.5], [np.nan, 0.0, 0.0, 0.5]])
    with pytest.raises(DataFormatError, match=r"000001\.bin.*NaN/inf.*row 1"):
        load_kitti_frame(path, None, _kitti_json(tmp_path))


def test_kitti_reflectance_out_of_range(tmp_path):
    path = _kitti_bin(tmp_path, [[1.0, 2.0, 3.0, 0.5], [4.0, 0.0, 0.0, 17.0]])
    with pytest.raises(DataFormatError, match=r"reflectances outside 0\.\.1.*row 1"):
        load_kitti_frame(path, None, _kitti_json(tmp_path))


def test_kitti_missing_files(tmp_path):
    with pytest.raises(DataFormatError, match=r"missing sensor file .*nope\.bin"):
        load_kitti_frame(tmp_path / "nope.bin", None, _kitti_json(tmp_path))
    with pytest.raises(DataFormatError, match=r"missing sensor file .*nope\.png"):
        load_kitti_frame(_kitti_bin(tmp_path), tmp_path / "nope.png", _kitti_json(tmp_path))
    with pytest.raises(DataFormatError, match=r"missing sensor file .*calib\.txt"):
        load_kitti_frame(_kitti_bin(tmp_path), None, tmp_path / "calib.txt")


def test_kitti_non_rigid_tr(tmp_path):
    sheared = [[0.0, -1.0, 0.2, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, -0.3]]
    with pytest.raises(DataFormatError, match=r"calib\.json: Tr_velo_to_cam_3x4: rotation part is not orthonormal"):
        load_kitti_frame(_kitti_bin(tmp_path), None, _kitti_json(tmp_path, Tr_velo_to_cam_3x4=sheared))
    txt = tmp_path / "calib.txt"
    txt.write_text(f"P2: 50 0 32 0 0 50 16 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
                   f"Tr_velo_to_cam: {' '.join(str(v) for v in np.ravel(sheared))}\n")
    with pytest.raises(DataFormatError, match=r"calib\.txt: Tr_velo_to_cam: rotation part is not orthonormal"):
        read_kitti_calib(txt)


def test_kitti_missing_and_malformed_keys(tmp_path):
    with pytest.raises(DataFormatError, match=r"calib\.json: missing calibration key 'R0_rect_3x3'"):
        read_kitti_calib(_kitti_json(tmp_path, R0_rect_3x3=None))
    with pytest.raises(DataFormatError, match=r"P2_3x4 has 11 values"):
        read_kitti_calib(_kitti_json(tmp_path, P2_3x4=list(range(11))))
    txt = tmp_path / "calib.txt"
    txt.write_text("P2: 50 0 32 0 0 50 16 0 0 0 1 0\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n")
    with pytest.raises(DataFormatError, match=r"calib\.txt: missing calibration key 'R0_rect'"):
        read_kitti_calib(txt)
    txt.write_text("P2: 50 0 32 zero 0 50 16 0 0 0 1 0\n")
    with pytest.raises(DataFormatError, match=r"calib\.txt:1: P2 has a non-numeric value"):
        read_kitti_calib(txt)


def test_kitti_inconsistent_stated_product_and_image_size(tmp_path):
    wrong = np.eye(4).tolist()
    with pytest.raises(DataFormatError, match="lidar_to_image_4x4 disagrees"):
        read_kitti_calib(_kitti_json(tmp_path, lidar_to_image_4x4=wrong))
    Image.new("RGB", (60, 32)).save(tmp_path / "000001.png")
    with pytest.raises(DataFormatError, match=r"image is 60x32.*image_size_wh \(64, 32\)"):
        load_kitti_frame(_kitti_bin(tmp_path), tmp_path / "000001.png", _kitti_json(tmp_path))


# --------------------------------------------------------------------------- STF layout + errors (tmp_path)

_OPTICAL_IN_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: image x, y, z in body


def _tf(parent: str, child: str, t, R) -> dict:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return {"header": {"frame_id": parent, "stamp": {"secs": 0, "nsecs": 0}, "seq": 0}, "child_frame_id": child,
            "transform": {"translation": {"x": t[0], "y": t[1], "z": t[2]},
                          "rotation": {"x": x, "y": y, "z": z, "w": w}}}


def _stf_tree(root: Path, ids: list[str], size=(1920, 1024), tf_entries=None) -> None:
    """Nested STF layout: lidar/camera folders, calib/ with a synthetic camera info and tf tree."""
    (root / "lidar_hdl64_strongest").mkdir(parents=True)
    (root / "cam_stereo_left_lut").mkdir()
    (root / "calib").mkdir()
    pts = np.array([[11.0, 0.0, -1.0, 12.5, 3.0], [20.0, 2.0, -1.5, 255.0, 40.0], [-5.0, 1.0, 0.0, 0.0, 63.0]],
                   dtype="<f4")
    for sample_id in ids:
        pts.tofile(root / "lidar_hdl64_strongest" / f"{sample_id}.bin")
        Image.new("RGB", size, (90, 90, 90)).save(root / "cam_stereo_left_lut" / f"{sample_id}.png")
    camera = {"width": 1920, "height": 1024, "K": [2000.0, 0, 960, 0, 2000, 512, 0, 0, 1],
              "P": [1000.0, 0, 960, 0, 0, 1000, 512, 0, 0, 0, 1, 0], "D": [0.1, 0, 0, 0, 0],
              "R": np.eye(3).ravel().tolist()}
    (root / "calib" / "calib_cam_stereo_left.json").write_text(json.dumps(camera))
    if tf_entries is None:
        tf_entries = [
            _tf("base_link", "body", [0.0, 0.0, 0.35], np.eye(3)),
            _tf("body", "lidar_hdl64_s3_roof", [1.0, 0.0, 2.0], np.eye(3)),
            _tf("body", "cam_stereo_left_optical", [2.0, 0.0, 1.0], _OPTICAL_IN_BODY),
            _tf("body", "radar_ars300", [3.9, 0.0, 0.3], np.eye(3)),
        ]
    (root / "calib" / "calib_tf_tree_full.json").write_text(json.dumps(tf_entries))


def test_stf_nested_layout_with_split(tmp_path):
    ids = ["2018-02-12_15-39-23_00100", "2018-10-29_14-30-29_02460"]
    _stf_tree(tmp_path, ids)
    split = tmp_path / "splits" / "test_clear.txt"
    split.parent.mkdir()
    split.write_text("2018-02-12_15-39-23,00100\n\n# comment\n2018-10-29_14-30-29,2460\n")
    assert read_stf_split(split) == ids
    for sample_id in read_stf_split(split):
        frame = load_stf_frame(tmp_path, sample_id)
        assert frame.token == sample_id and frame.lidar.points.shape == (3, 5)
        np.testing.assert_array_equal(frame.lidar.points[:, 4], [3, 40, 63])
        cam = frame.cameras["cam_stereo_left"]
        assert (cam.width, cam.height) == (1920, 1024)
        np.testing.assert_allclose(cam.K, [[1000, 0, 960], [0, 1000, 512], [0, 0, 1]])  # from P, not K
        # LiDAR point (11, 0, -1) is body (12, 0, 1): 10 m straight ahead of the camera at body (2, 0, 1)
        pc = apply(invert(cam.T_ego_cam), frame.lidar.points[:2, :3])
        np.testing.assert_allclose(pc[0], [0.0, 0.0, 10.0], atol=1e-9)
        uv, _ = project(pc, cam.K)
        np.testing.assert_allclose(uv[0], [960.0, 512.0], atol=1e-6)
        assert uv[1, 0] < 960 and uv[1, 1] > 512  # 2 m left, 0.5 m below the camera -> left of and below centre
        np.testing.assert_allclose(cam.T_ego_cam[:3, 3], [1.0, 0.0, -1.0], atol=1e-9)


def test_stf_unknown_crop_needs_explicit_offset(tmp_path):
    _stf_tree(tmp_path, ["rec_00001"], size=(1000, 600))
    with pytest.raises(DataFormatError, match=r"1000x600.*not a known crop.*crop_offset"):
        load_stf_frame(tmp_path, "rec_00001")
    cam = load_stf_frame(tmp_path, "rec_00001", crop_offset=(460, 212)).cameras["cam_stereo_left"]
    np.testing.assert_allclose(cam.K[:2, 2], [500.0, 300.0])


def test_stf_missing_files(tmp_path):
    _stf_tree(tmp_path, ["rec_00001"])
    with pytest.raises(DataFormatError, match=r"missing sensor file for sample 'rec_00002'.*rec_00002\.bin"):
        load_stf_frame(tmp_path, "rec_00002")
    (tmp_path / "cam_stereo_left_lut" / "rec_00001.png").unlink()
    with pytest.raises(DataFormatError, match=r"stereo-left image: missing sensor file.*rec_00001\.png"):
        load_stf_frame(tmp_path, "rec_00001")
    assert load_stf_frame(tmp_path, "rec_00001", camera_folder=None).cameras == {}
    Image.new("RGB", (1920, 1024)).save(tmp_path / "cam_stereo_left_lut" / "rec_00001.png")
    (tmp_path / "calib" / "calib_tf_tree_full.json").unlink()
    with pytest.raises(DataFormatError, match=r"missing calib_tf_tree_full\.json"):
        load_stf_frame(tmp_path, "rec_00001")
    with pytest.raises(DataFormatError, match="escapes the dataroot"):
        load_stf_frame(tmp_path, "../../etc/passwd")


def test_stf_truncated_and_nan_and_bad_channel(tmp_path):
    _stf_tree(tmp_path, ["rec_00001"])
    path = tmp_path / "lidar_hdl64_strongest" / "rec_00001.bin"
    path.write_bytes(path.read_bytes()[:-4])
    with pytest.raises(DataFormatError, match=r"rec_00001\.bin: 56 bytes is not a multiple of the record size 20"):
        load_stf_frame(tmp_path, "rec_00001")
    pts = np.array([[1, 2, 3, 50, 0], [4, 5, np.inf, 50, 1]], dtype="<f4")
    pts.tofile(path)
    with pytest.raises(DataFormatError, match=r"rec_00001\.bin: 1 points with NaN/inf coordinates"):
        load_stf_frame(tmp_path, "rec_00001")
    np.array([[1, 2, 3, 50, 0], [4, 5, 6, 50, 64]], dtype="<f4").tofile(path)
    with pytest.raises(DataFormatError, match=r"invalid channels.*row 1: 64\.0.*0\.\.63"):
        load_stf_frame(tmp_path, "rec_00001")
    np.array([[1, 2, 3, 300, 0]], dtype="<f4").tofile(path)
    with pytest.raises(DataFormatError, match=r"intensities outside 0\.\.255"):
        load_stf_frame(tmp_path, "rec_00001")


def test_stf_bad_tf_tree(tmp_path):
    missing_cam = [_tf("body", "lidar_hdl64_s3_roof", [1.0, 0.0, 2.0], np.eye(3))]
    _stf_tree(tmp_path / "a", ["rec_00001"], tf_entries=missing_cam)
    with pytest.raises(DataFormatError, match=r"calib_tf_tree_full\.json: missing calibration key: tf frame "
                                              r"'cam_stereo_left_optical'"):
        load_stf_frame(tmp_path / "a", "rec_00001")
    entry = _tf("body", "cam_stereo_left_optical", [2.0, 0.0, 1.0], _OPTICAL_IN_BODY)
    entry["transform"]["rotation"]["w"] += 0.3
    _stf_tree(tmp_path / "b", ["rec_00001"], tf_entries=missing_cam + [entry])
    with pytest.raises(DataFormatError, match=r"cam_stereo_left_optical\): rotation quaternion norm"):
        load_stf_frame(tmp_path / "b", "rec_00001")
    entry = _tf("body", "cam_stereo_left_optical", [2.0, 0.0, 1.0], _OPTICAL_IN_BODY)
    del entry["transform"]["translation"]["z"]
    _stf_tree(tmp_path / "c", ["rec_00001"], tf_entries=missing_cam + [entry])
    with pytest.raises(DataFormatError, match=r"entry 1 \(cam_stereo_left_optical\)\.translation: "
                                              r"missing calibration key 'z'"):
        load_stf_frame(tmp_path / "c", "rec_00001")
    disconnected = missing_cam + [_tf("car", "cam_stereo_left_optical", [2.0, 0.0, 1.0], _OPTICAL_IN_BODY)]
    _stf_tree(tmp_path / "d", ["rec_00001"], tf_entries=disconnected)
    with pytest.raises(DataFormatError, match="are not connected"):
        load_stf_frame(tmp_path / "d", "rec_00001")


def test_stf_split_errors(tmp_path):
    with pytest.raises(DataFormatError, match=r"missing sensor file .*missing\.txt"):
        read_stf_split(tmp_path / "missing.txt")
    empty = tmp_path / "empty.txt"
    empty.write_text("\n  \n# only a comment\n")
    with pytest.raises(DataFormatError, match=r"empty\.txt: empty split"):
        read_stf_split(empty)
    bad = tmp_path / "bad.txt"
    for line in ["2018-02-12_15-39-23,00100,extra", "2018-02-12_15-39-23;00100", "2018-02-12_15-39-23,frame7",
                 ",00100", "../x,00100", "2018-02-12_15-39-23,123456"]:
        bad.write_text(f"2018-02-12_15-39-23,00100\n{line}\n")
        with pytest.raises(DataFormatError, match=r"bad\.txt:2: malformed split line"):
            read_stf_split(bad)
