"""Camera fog (Koschmieder on linear radiance, one airlight per scene, guided-filtered transmission) and dense camera
depth from LiDAR (against the synthetic world's exact range maps, and on the real STF / KITTI samples).

Pictures for a human check are written to ``/tmp/weatheralign_camera_fog/``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from weatheralign.camera.depth import (
    CameraPoints,
    DenseDepth,
    DepthParams,
    above_fov_mask,
    camera_points,
    complete_depth,
    consistent_sky,
    dense_depth,
    drop_parallax,
    drop_see_through,
    estimate_top_elevation_deg,
    morphological_fill,
    pixel_ray_norms,
    triangulate,
)
from weatheralign.camera.fog import (
    CLIPPED,
    NEUTRAL_AIRLIGHT,
    airlight_gains,
    airlight_luminance,
    composite,
    composite_image,
    decode_srgb_u8,
    encode_srgb_u8,
    estimate_airlight,
    fog_airlight,
    fog_image,
    linear_to_srgb,
    refine_transmission,
    sky_airlight,
    srgb_to_linear,
    transmission,
)
from weatheralign.data.kitti import load_kitti_frame
from weatheralign.data.nuscenes import load_camera, load_lidar, open_nuscenes
from weatheralign.data.stf import load_stf_frame
from weatheralign.medium.fog import FogMedium

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
STF_ID = "2019-09-11_19-13-44_00960"
PICTURES = Path("/tmp/weatheralign_camera_fog")
CHANNELS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real sample not available: {path}")
    return path


def _save(image: np.ndarray, name: str) -> Path:
    PICTURES.mkdir(parents=True, exist_ok=True)
    path = PICTURES / name
    Image.fromarray(image).save(path)
    return path


def _small_K(width: int = 160, height: int = 90, f: float = 80.0) -> np.ndarray:
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------------ colour space


def test_srgb_codes_round_trip_and_encoding_is_exactly_rounded():
    codes = np.arange(256, dtype=np.uint8)
    assert np.array_equal(encode_srgb_u8(decode_srgb_u8(codes)), codes)
    x = np.random.default_rng(3).random(200_000).astype(np.float32) ** 3
    exact = np.rint(255.0 * linear_to_srgb(x.astype(np.float64))).astype(np.uint8)
    assert np.array_equal(encode_srgb_u8(x), exact)
    # the decoding is the IEC 61966-2-1 curve: mid-grey code 128 is ~21.6 % linear radiance
    assert decode_srgb_u8(np.array([128], np.uint8))[0] == pytest.approx(0.2158605, abs=1e-6)


# ------------------------------------------------------------------------------------------------ Koschmieder


def test_koschmieder_closed_form_uses_ray_length_in_linear_radiance():
    """Uniform J on a fronto-parallel wall at z = 30 m: each pixel is J t + A (1 - t) in linear light with
    t = exp(-alpha * ray length); the corner pixel's ray is longer than the centre's, so it carries more fog."""
    W, H = 160, 90
    K = _small_K(W, H)
    ray = pixel_ray_norms(K, W, H).astype(np.float64) * 30.0
    J_code = np.array([60, 110, 170], np.uint8)
    image = np.broadcast_to(J_code, (H, W, 3)).copy()
    A = np.array([0.8, 0.8, 0.8])
    alpha = FogMedium.with_default_beta(0.03).camera_extinction
    out = fog_image(image, ray.astype(np.float32), alpha, A, refine=False)

    t = np.exp(-alpha * ray)[..., None]
    expected_lin = srgb_to_linear(J_code / 255.0) * t + srgb_to_linear(A) * (1.0 - t)
    expected = np.rint(255.0 * linear_to_srgb(expected_lin)).astype(int)
    assert np.abs(out.astype(int) - expected).max() <= 1
    # a naive sRGB-space blend is clearly different (the law is applied to radiance)
    naive = np.rint(255.0 * ((J_code / 255.0) * t + A * (1.0 - t))).astype(int)
    assert np.abs(naive - expected).max() >= 5

    centre, corner = out[H // 2, W // 2].astype(int), out[0, 0].astype(int)
    assert ray[0, 0] > 1.2 * ray[H // 2, W // 2]
    A_code = np.rint(255 * A).astype(int)
    assert np.abs(corner - A_code).sum() < np.abs(centre - A_code).sum() - 5
    # z-depth would give the same fog everywhere: the result is not uniform
    assert len({tuple(p) for p in out.reshape(-1, 3)}) > 5


def test_alpha_zero_returns_the_input_bitwise():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (90, 160, 3), dtype=np.uint8)
    ranges = rng.uniform(1.0, 300.0, (90, 160)).astype(np.float32)
    ranges[:20] = np.inf
    for refine in (False, True):
        out = fog_image(image, ranges, 0.0, [0.8, 0.8, 0.8], refine=refine)
        assert out.dtype == np.uint8 and np.array_equal(out, image) and out is not image
    assert np.array_equal(transmission(ranges, 0.0), np.ones_like(ranges))
    t = transmission(ranges, 0.02)
    assert np.all(t[:20] == 0.0) and np.all((t[20:] > 0) & (t[20:] < 1))


def test_transmission_rejects_bad_input():
    with pytest.raises(ValueError, match="alpha"):
        transmission(np.ones((2, 2)), -0.1)
    with pytest.raises(ValueError, match="NaN or negative"):
        transmission(np.array([[1.0, np.nan]]), 0.01)
    with pytest.raises(ValueError, match="shape"):
        fog_image(np.zeros((4, 4, 3), np.uint8), np.ones((3, 4)), 0.01, 0.8)
    with pytest.raises(ValueError, match="airlight"):
        fog_image(np.zeros((4, 4, 3), np.uint8), np.ones((4, 4)), 0.01, [0.8, 1.2, 0.8])


# ------------------------------------------------------------------------------------------------ airlight


def _scene(sky_colour: tuple[int, int, int], cameras_with_sky: tuple[int, ...], seed: int = 1):
    rng = np.random.default_rng(seed)
    images, ranges = [], []
    for k in range(6):
        img = rng.integers(20, 160, (90, 160, 3), dtype=np.uint8)
        rng_map = rng.uniform(2.0, 80.0, (90, 160)).astype(np.float32)
        if k in cameras_with_sky:
            img[:30] = sky_colour
            rng_map[:30] = np.inf
        images.append(img)
        ranges.append(rng_map)
    return images, ranges


def test_one_airlight_per_scene_equals_the_sky_colour():
    sky = (182, 201, 224)
    images, ranges = _scene(sky, cameras_with_sky=(0, 1, 3))
    A = estimate_airlight(images, ranges, neutral=False)
    assert A.shape == (3,)
    assert np.allclose(A, np.array(sky) / 255.0, atol=1 / 255)
    # pooled over all cameras: camera order does not matter
    order = [3, 5, 0, 2, 4, 1]
    assert np.array_equal(estimate_airlight([images[i] for i in order], [ranges[i] for i in order], neutral=False), A)
    # one value for every camera: in dense fog every camera's sky shows the same airlight, no seams
    fogged = [fog_image(img, rng_map, 0.05, A, refine=False) for img, rng_map in zip(images, ranges)]
    sky_pixels = np.concatenate([f[:30].reshape(-1, 3) for f, r in zip(fogged, ranges) if np.isinf(r[0, 0])])
    assert len(np.unique(sky_pixels, axis=0)) == 1
    assert np.array_equal(sky_pixels[0], np.rint(255 * A).astype(np.uint8))
    # no sky anywhere: neutral grey
    images_ns, ranges_ns = _scene(sky, cameras_with_sky=())
    assert np.allclose(estimate_airlight(images_ns, ranges_ns), NEUTRAL_AIRLIGHT)
    # neutral=True keeps the luminance, drops the colour
    grey = estimate_airlight(images, ranges, neutral=True)
    assert grey[0] == grey[1] == grey[2]
    lum = float(np.dot([0.2126, 0.7152, 0.0722], srgb_to_linear(A)))
    assert srgb_to_linear(grey[0]) == pytest.approx(lum, rel=1e-9)


def test_airlight_without_ranges_uses_the_dark_channel_of_the_sky():
    sky = (200, 212, 230)
    images, _ = _scene(sky, cameras_with_sky=(2,))
    A = estimate_airlight(images, neutral=False)  # no ranges: dark channel, top 0.1 %, median colour
    assert np.allclose(A, np.array(sky) / 255.0, atol=2 / 255)
    dark, _ = _scene(sky, cameras_with_sky=())
    assert np.allclose(estimate_airlight(dark), NEUTRAL_AIRLIGHT)  # nothing bright enough to be sky


def test_airlight_gains_are_the_foggy_skies_over_the_clear_sky():
    """Each foggy frame's sky luminance over the clear frames' median, in linear light, sorted; frames without sky
    do not vote; nothing to compare keeps the clear sky's airlight (1)."""
    clear_sky, fog_skies = (150, 170, 200), (170, 205, 230)
    clear = [_sky_of_one_camera(clear_sky) for _ in range(3)]
    fog = [_sky_of_one_camera((v, v, v)) for v in fog_skies]
    no_sky = _sky_of_one_camera(clear_sky, with_sky=False)
    assert no_sky is None
    gains = airlight_gains([fog[2], no_sky, fog[0], fog[1]], clear + [no_sky])
    base = airlight_luminance(np.array(clear_sky) / 255.0)
    expected = sorted(float(srgb_to_linear(v / 255.0)) / base for v in fog_skies)
    assert gains == pytest.approx(expected, abs=2e-3)
    assert airlight_gains([no_sky], clear) == airlight_gains(fog, [no_sky]) == (1.0,)
    # the fog's airlight: gain 1 is the clear sky's own, brighter gains stop short of white
    A = np.full(3, 0.7)
    assert np.array_equal(fog_airlight(A, 1.0), srgb_to_linear(A))
    assert fog_airlight(A, 10.0) == pytest.approx(np.full(3, srgb_to_linear(CLIPPED)))
    with pytest.raises(ValueError, match="gain"):
        fog_airlight(A, 0.0)


def _sky_of_one_camera(sky: tuple[int, int, int], with_sky: bool = True) -> np.ndarray | None:
    """`sky_airlight` of one 60 x 80 camera whose top 30 rows are sky of colour ``sky`` (or a wall) over a grey
    road."""
    img = np.full((60, 80, 3), 90, np.uint8)
    rng = np.full((60, 80), 12.0, np.float32)
    if with_sky:
        img[:30] = sky
        rng[:30] = np.inf
    return sky_airlight([img], [rng])


@pytest.mark.parametrize("with_ranges", [True, False])
def test_overexposed_clouds_never_make_the_airlight_white(with_ranges):
    """Real cameras clip bright clouds at 255: those pixels say nothing about the sky's radiance and never vote, so the
    airlight is the unsaturated sky's colour (range maps: the sky pixels; without: the dark channel); a sky clipped
    everywhere falls back to the neutral grey."""
    sky = (170, 176, 182)
    images, ranges = _scene(sky, cameras_with_sky=(0, 1, 3))
    for k in (0, 1, 3):  # two thirds of every sky band blown out, more pixels than the grey part
        images[k][:20] = 255
    A = estimate_airlight(images, ranges if with_ranges else None, neutral=False)
    assert np.allclose(A, np.array(sky) / 255.0, atol=2 / 255)
    for k in (0, 1, 3):
        images[k][:30] = (255, 255, 254)
    assert np.allclose(estimate_airlight(images, ranges if with_ranges else None), NEUTRAL_AIRLIGHT)


# ------------------------------------------------------------------------------------------------ guided filter


def test_guided_filter_keeps_edges_and_follows_smooth_transmission():
    H, W = 120, 200
    rng = np.random.default_rng(5)
    guide = np.full((H, W, 3), 0.25, np.float32)
    guide[:, W // 2:] = 0.8
    t = np.where(np.arange(W) < W // 2, 0.3, 0.75).astype(np.float32)[None].repeat(H, 0)
    t_noisy = (t + rng.normal(0, 0.03, t.shape)).astype(np.float32)
    for subsample in (1, 2):
        ref = refine_transmission(t_noisy, guide, radius=20, eps=1e-3, subsample=subsample)
        # the step of the guide stays sharp in t: two pixels either side of the edge keep ~all of the 0.45 jump
        assert ref[:, W // 2 + 1].mean() - ref[:, W // 2 - 2].mean() > 0.4
        # the noise is gone on the flat parts and the level kept
        flat = ref[30:90, 20:70]
        assert abs(flat.mean() - 0.3) < 0.01 and flat.std() < 0.01
    # a smooth transmission under a uniform guide is left (almost) as it was
    ramp = np.linspace(0.2, 0.9, W, dtype=np.float32)[None].repeat(H, 0)
    out = refine_transmission(ramp, np.full((H, W, 3), 128, np.uint8))
    assert np.abs(out - ramp)[:, 25:-25].max() < 0.01
    assert out.min() >= 0.0 and out.max() <= 1.0


def test_compiled_composite_equals_the_numpy_composition():
    """`composite_image` (one compiled pass) against decode -> guided filter -> composite -> encode in numpy: the
    unrefined path is bit-exact, the refined one within one code value (float32 order of the coefficient upsampling),
    with the linear output matching the encoded one."""
    rng = np.random.default_rng(8)
    H, W = 90, 161  # not divisible by the subsample: the upsampling's clamped borders are exercised
    image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    image[:, : W // 3] //= 4  # a dark region and an edge
    rng_map = np.where(np.arange(W)[None] < W // 2, 8.0, 60.0) + rng.uniform(0, 2, (H, W))
    rng_map[:10] = np.inf  # sky
    t = transmission(rng_map.astype(np.float32), 0.04)
    A = srgb_to_linear(np.array([0.78, 0.8, 0.83])).astype(np.float32)
    plain = encode_srgb_u8(composite(decode_srgb_u8(image), t, A))
    assert np.array_equal(composite_image(image, t, A, refine=False), plain)
    for s in (1, 2, 4):
        ref = encode_srgb_u8(composite(decode_srgb_u8(image), refine_transmission(t, image, subsample=s), A))
        fast = composite_image(image, t, A, subsample=s)
        assert np.abs(ref.astype(int) - fast).max() <= 1 and (ref != fast).mean() < 1e-3
        linear = composite_image(image, t, A, subsample=s, encode=False)
        assert np.array_equal(encode_srgb_u8(linear), fast)
    with pytest.raises(ValueError, match="uint8"):
        composite_image(image.astype(np.float32), t, A)
    with pytest.raises(ValueError, match="transmittance shape"):
        composite_image(image, t[:-1], A)


# ------------------------------------------------------------------------------------------------ synthetic world


@pytest.fixture(scope="module")
def world_frame(tiny_world):
    nusc = open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)
    sample = nusc.sample[0]
    scan = load_lidar(nusc, sample["data"]["LIDAR_TOP"], nsweeps=3)
    cams = {ch: load_camera(nusc, sample["data"][ch]) for ch in CHANNELS}
    return scan, cams


def _errors(dd: DenseDepth, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    below = ~dd.above_fov & np.isfinite(gt)
    rel = np.abs(dd.range[below].astype(np.float64) - gt[below]) / gt[below]
    rel[~np.isfinite(rel)] = np.inf  # ground truth finite but we said sky: counts as a total miss
    return rel, below


def test_dense_depth_matches_the_exact_range_of_the_synthetic_world(world_frame, capsys):
    scan, cams = world_frame
    assert scan.sweep_index is not None and int(scan.sweep_index.max()) == 2  # 3 sweeps aggregated
    top = estimate_top_elevation_deg(scan)
    assert top == pytest.approx(10.67, abs=0.1)  # HDL-32E
    cam = cams["CAM_FRONT"]
    image = cam.load_image()
    gt = cam.load_range().astype(np.float64)
    dense_depth(scan, cam, image, top)  # warm-up (numba)
    t0 = time.perf_counter()
    dd = dense_depth(scan, cam, image, top)
    seconds = time.perf_counter() - t0
    assert dd.range.shape == (900, 1600) and dd.range.dtype == np.float32
    assert not np.isnan(dd.range).any() and np.all(dd.range > 0)
    rel, below = _errors(dd, gt)
    median, p90 = float(np.median(rel)), float(np.percentile(rel, 90))
    # sky: above the LiDAR's top elevation, inf in the ground truth -> inf here
    sky_gt = dd.above_fov & np.isposinf(gt)
    sky_hit = float(np.isinf(dd.range[sky_gt]).mean()) if sky_gt.any() else float("nan")
    valid = dd.valid & below
    rel_valid = np.abs(dd.range[valid] - gt[valid]) / gt[valid]
    with capsys.disabled():
        print(f"\n[dense depth CAM_FRONT, 3 sweeps, {dd.num_points} points] median rel err {median:.4f}, "
              f"p90 {p90:.4f} over {below.sum()} px below the LiDAR top elevation; valid px ({valid.mean():.2f} "
              f"of image) median {np.median(rel_valid):.4f}, p90 {np.percentile(rel_valid, 90):.4f}; sky above top "
              f"elevation inf in both: {sky_hit:.3f} of {sky_gt.sum()} px; {seconds:.3f} s per 1600x900 image")
    assert median < 0.05
    # the world's HDL-32E detects on raw power: its dark asphalt at grazing incidence is under the floor beyond about
    # 18 m, so the far road is extrapolated from the nearer returns (p90 0.38; under 0.25 while the far ground returned)
    assert p90 < 0.45
    assert np.percentile(rel_valid, 90) < 0.05  # pixels flagged valid are trustworthy
    assert sky_gt.sum() > 1000 and sky_hit > 0.9
    # the LiDAR never returns from above its top elevation: no finite-range LiDAR support marks sky there
    pts = camera_points(scan, cam)
    assert np.array_equal(dd.above_fov, above_fov_mask(cam.K, cam.width, cam.height, pts.R_lidar_cam, top))


def test_dense_depth_other_cameras_and_lidar_only(world_frame):
    scan, cams = world_frame
    top = estimate_top_elevation_deg(scan)
    for ch in ("CAM_BACK", "CAM_FRONT_LEFT"):
        cam = cams[ch]
        dd = dense_depth(scan, cam, cam.load_image(), top)
        rel, _ = _errors(dd, cam.load_range().astype(np.float64))
        assert np.median(rel) < 0.05, ch
    # without an image, every unsupported pixel above the top elevation is sky, nothing below it is
    cam = cams["CAM_FRONT"]
    pts = camera_points(scan, cam)
    dd = complete_depth(pts, cam.K, cam.width, cam.height, None, top)
    assert not (dd.sky & ~dd.above_fov).any()
    gt = cam.load_range()
    sky_gt = dd.above_fov & np.isposinf(gt)
    assert np.isinf(dd.range[sky_gt]).mean() > 0.95
    assert np.median(_errors(dd, gt.astype(np.float64))[0]) < 0.05


def test_dense_depth_from_a_point_array_matches_the_scan_path(world_frame):
    scan, cams = world_frame
    cam = cams["CAM_FRONT"]
    image = cam.load_image()
    top = estimate_top_elevation_deg(scan)
    a = dense_depth(scan, cam, image, top)
    # the same points given as an array in the LiDAR frame at the camera's time (static world: exact)
    T_lidar_cam_time = np.linalg.inv(cam.T_global_ego @ scan.T_ego_lidar) @ scan.T_global_lidar
    xyz = scan.points[:, :3].astype(np.float64) @ T_lidar_cam_time[:3, :3].T + T_lidar_cam_time[:3, 3]
    b = dense_depth(xyz, cam, image, top, T_ego_lidar=scan.T_ego_lidar)
    both = np.isfinite(a.range) & np.isfinite(b.range)
    assert both.mean() > 0.7 and np.median(np.abs(a.range[both] - b.range[both])) < 1e-3
    with pytest.raises(ValueError, match="T_ego_lidar"):
        dense_depth(xyz, cam, image, top)


def test_fogged_synthetic_camera_looks_like_fog(world_frame):
    """Exact ranges of the synthetic world, one airlight from its six cameras, alpha = 0.01 and 0.04."""
    _, cams = world_frame
    images = {ch: cams[ch].load_image() for ch in CHANNELS}
    ranges = {ch: cams[ch].load_range() for ch in CHANNELS}
    A = estimate_airlight([images[ch] for ch in CHANNELS], [ranges[ch] for ch in CHANNELS])
    img, rng_map = images["CAM_FRONT"], ranges["CAM_FRONT"]
    near, far = rng_map < 15.0, np.isfinite(rng_map) & (rng_map > 120.0)
    A_code = 255.0 * A
    contrast = {}
    for alpha in (0.01, 0.04):
        t0 = time.perf_counter()
        out = fog_image(img, rng_map, alpha, A, refine=True)
        seconds = time.perf_counter() - t0
        _save(out, f"synthetic_CAM_FRONT_alpha{alpha}.png")
        dist = np.abs(out.astype(np.float64) - A_code).sum(axis=2)
        contrast[alpha] = (dist[near].mean(), dist[far].mean())
        assert seconds < 5.0
    _save(img, "synthetic_CAM_FRONT_clear.png")
    # far things fade into the airlight, near things stay clear; more so in denser fog
    clear = np.abs(img.astype(np.float64) - A_code).sum(axis=2)
    for alpha, (d_near, d_far) in contrast.items():
        assert d_near > 0.6 * clear[near].mean()
    assert contrast[0.04][1] < 0.1 * clear[far].mean()
    assert contrast[0.04][1] < contrast[0.01][1]


# ------------------------------------------------------------------------------------------------ real data


@pytest.fixture(scope="module")
def stf_frame():
    return load_stf_frame(_need(REAL / "stf"), STF_ID)


@pytest.fixture(scope="module")
def kitti_frame():
    k = _need(REAL / "kitti")
    return load_kitti_frame(k / "000008.bin", k / "000008.png", k / "calib.json")


def _check_real(frame, channel: str, expected_top: float) -> tuple[DenseDepth, np.ndarray]:
    cam = frame.cameras[channel]
    image = cam.load_image()
    top = estimate_top_elevation_deg(frame.lidar)
    assert top == pytest.approx(expected_top, abs=0.5)
    dd = dense_depth(frame.lidar, cam, image, top)
    rng = dd.range
    assert rng.shape == image.shape[:2] and rng.dtype == np.float32
    assert not np.isnan(rng).any() and np.all(rng > 0)
    finite = np.isfinite(rng)
    assert 0.8 < finite.mean() < 1.0  # some sky, mostly scene
    assert dd.sky.sum() > 0 and np.array_equal(dd.sky, ~finite)
    rows = np.nonzero(dd.sky)[0]
    assert rows.max() < image.shape[0] // 2  # sky only in the upper half
    assert 5.0 < float(np.median(rng[finite])) < 60.0
    # at the LiDAR points themselves the dense map agrees with the points
    pts = camera_points(frame.lidar, cam)
    z = pts.xyz[:, 2]
    u = np.rint(cam.K[0, 0] * pts.xyz[:, 0] / z + cam.K[0, 2]).astype(int)
    v = np.rint(cam.K[1, 1] * pts.xyz[:, 1] / z + cam.K[1, 2]).astype(int)
    ok = (z > 1.0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    ray = np.linalg.norm(pts.xyz[ok], axis=1)
    rel = np.abs(rng[v[ok], u[ok]] - ray) / ray
    assert np.median(rel) < 0.02
    # completion never invents a surface farther than every point (an emptied pixel once came back as the farthest
    # depth + 1 m, and the hole fill spread it over car windows as black patches)
    cam_z = dd.range / pixel_ray_norms(cam.K, cam.width, cam.height)
    assert float(cam_z[finite].max()) <= float(z[ok].max()) * 1.005  # rasterised triangles: slight overshoot
    return dd, image


def test_dense_depth_and_fog_on_seeing_through_fog(stf_frame):
    dd, image = _check_real(stf_frame, "cam_stereo_left", expected_top=2.72)
    A = estimate_airlight([image], [dd.range])
    assert np.all((A > 0.6) & (A < 0.95))  # the overcast sky of the sample, near-neutral
    for alpha in (0.01, 0.04):
        out = fog_image(image, dd.range, alpha, A)
        _save(out, f"stf_{STF_ID}_alpha{alpha}.png")
        assert out.shape == image.shape and not np.array_equal(out, image)
    _save(image, f"stf_{STF_ID}_clear.png")


def test_dense_depth_on_kitti(kitti_frame):
    dd, image = _check_real(kitti_frame, "image_2", expected_top=2.0)
    _save(fog_image(image, dd.range, 0.04, estimate_airlight([image], [dd.range], neutral=True)),
          "kitti_000008_alpha0.04.png")


def test_morphological_fill_stays_within_the_input_depths():
    """Isolated points (their blobs' rims have mostly empty 5 x 5 windows, which the final median empties) next to
    one far point: every filled pixel keeps a depth between the nearest and the farthest point."""
    z = np.zeros((120, 200), np.float32)
    z[60:120:6, 0:200:3] = 8.0  # ground-like rows
    for v, u in ((10, 20), (14, 120), (30, 170)):
        z[v, u] = 5.0  # isolated near points
    z[40, 60] = 40.0  # one far point
    out = morphological_fill(z, gap_v=6.0, gap_h=3.0)
    filled = out > 0
    assert filled[60:].all()
    assert float(out[filled].min()) >= 5.0 - 1e-3 and float(out[filled].max()) <= 40.0 + 1e-3
    near_blobs = np.zeros_like(filled)
    for v, u in ((10, 20), (14, 120), (30, 170)):
        near_blobs[v - 3:v + 4, u - 3:u + 4] = True
    assert np.all(out[near_blobs & filled] < 8.5)  # never the far point's depth


def _window_scene(gap_between: bool = False) -> tuple:
    """A 320 x 180 camera (f = 160 px) and LiDAR rings every 6 rows, points every 3 px, on a wall at z = 15 m with
    a car body at z = 4 m (rows 70-169, columns 60-259) in front. With a window (rows 90-129, columns 100-219) the
    LiDAR passed the glass and hit the wall; ``gap_between``: instead of the window, two cars (columns 60-139 and
    180-259) with the wall visible between them, above the cars too. Returns (points, K, window or gap mask)."""
    W, H, f = 320, 180, 160.0
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    vv, uu = np.mgrid[2:H:6, 0:W:3].astype(np.float64)
    car = (vv >= 70) & (vv < 170) & (uu >= 60) & (uu < 260)
    region = np.zeros((H, W), bool)
    if gap_between:
        through = car & (uu >= 140) & (uu < 180)
        region[70:170, 140:180] = True
    else:
        through = (vv >= 90) & (vv < 130) & (uu >= 100) & (uu < 220)
        region[90:130, 100:220] = True
    z = np.where(car & ~through, 4.0, 15.0)
    xyz = np.column_stack([((uu - K[0, 2]) / f * z).ravel(), ((vv - K[1, 2]) / f * z).ravel(), z.ravel()])
    R_lidar_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pts = CameraPoints(xyz=xyz, dt=np.zeros(len(xyz)), R_lidar_cam=R_lidar_cam, up_cam=np.array([0.0, -1.0, 0.0]))
    return pts, K, region


def test_a_car_window_takes_the_cars_depth_not_the_wall_the_lidar_saw_through_it():
    pts, K, window = _window_scene()
    z = complete_depth(pts, K, 320, 180, None, top_elevation_deg=30.0).range / pixel_ray_norms(K, 320, 180)
    assert np.all(np.abs(z[window] - 4.0) < 0.5)  # was the wall's 15 m: a white fog patch on the car
    assert np.all(np.abs(z[10:60, :] - 15.0) < 0.5)  # the wall above the car is untouched
    # a real gap between two cars (the wall continues above them) keeps the wall's depth
    pts, K, gap = _window_scene(gap_between=True)
    z = complete_depth(pts, K, 320, 180, None, top_elevation_deg=30.0).range / pixel_ray_norms(K, 320, 180)
    inner = np.zeros_like(gap)
    inner[75:165, 148:172] = True
    assert np.all(np.abs(z[inner] - 15.0) < 0.5)


def test_drop_see_through_needs_one_surface_on_both_sides():
    """A far point framed by near points above and below at different depths (branches above, road below) is not
    seen through glass and stays; framed by one surface on all four sides it goes."""
    z = np.zeros((100, 100), np.float32)
    z[50, 50] = 30.0
    z[50, 40] = z[50, 60] = 6.0  # left and right
    z[40, 50] = 6.0  # above
    z[60, 50] = 12.0  # below: another surface
    assert drop_see_through(z, 6.0, 3.0, 8.0, 1.5, 1.5)[50, 50] == 30.0
    z[60, 50] = 6.5
    out = drop_see_through(z, 6.0, 3.0, 8.0, 1.5, 1.5)
    assert out[50, 50] == 0.0 and np.count_nonzero(out) == 4 and np.count_nonzero(z) == 5  # input unchanged


def _yawed_view(channel: str, yaw_deg: float, K: np.ndarray, width: int, height: int):
    """An upright camera (OpenCV axes: x right, y down, z forward) at the ego origin, looking along the ego's x axis
    turned by ``yaw_deg`` to the left."""
    from weatheralign.data.frame import CameraView

    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    forward, left = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([-left, [0.0, 0.0, -1.0], forward])  # camera axes in the ego frame
    return CameraView(channel, Path("/nonexistent.jpg"), K, width, height, T, np.eye(4), 0.0)


def test_neighbouring_cameras_agree_on_the_sky():
    """Two cameras 60 deg apart (90 deg fields of view: yaw -45..45 and 15..105 deg, 30 deg shared). Where one calls
    a direction sky and the other a surface, the sky pixel takes the surface's ray length; sky both agree on stays
    sky; nothing outside the shared field of view changes, and the inputs are not modified."""
    W, H = 200, 100
    K = np.array([[100.0, 0.0, 100.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
    views = {"A": _yawed_view("A", 0.0, K, W, H), "B": _yawed_view("B", 60.0, K, W, H)}
    a = np.full((H, W), 30.0, np.float32)
    a[:50] = np.inf  # A: the upper half is sky
    b = np.full((H, W), 30.0, np.float32)
    b[:30] = np.inf  # B: sky high up; lower, a 30 m facade in its right half (the directions it shares with A)
    b[30:50, :100] = np.inf
    ranges = {"A": a, "B": b}
    before = {k: v.copy() for k, v in ranges.items()}
    out = consistent_sky(views, ranges)
    assert all(np.array_equal(ranges[k], before[k]) for k in ranges)
    assert np.isposinf(out["A"][5, 0])  # yaw 45 deg, high: B's row ~17, sky in both
    assert out["A"][40, 0] == 30.0  # yaw 45 deg, low: B's row ~43, column ~127: B sees the facade there
    assert np.isposinf(out["A"][40, W - 1])  # yaw -45 deg: outside B's field of view
    changed = out["A"] != a
    assert changed.sum() > 100 and np.all(out["A"][changed] == 30.0) and not changed[50:].any()
    assert np.array_equal(out["B"], b)  # B's sky is sky for A too, or outside A's view


def _crown_scene(with_crown: bool = True) -> tuple:
    """A 320 x 180 upright camera (f = 160 px) level with a LiDAR whose top beam is the horizon (row 90): a pale
    facade at z = 20 m behind a tree whose 20 px trunk (z = 8 m) the LiDAR hits below the horizon and whose green
    crown (rows 30-79, columns 100-219, z = 8 m) lies wholly above it. Returns (points, K, image, crown mask)."""
    W, H, f = 320, 180, 160.0
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    image = np.empty((H, W, 3), np.float32)
    image[:] = (0.72, 0.72, 0.74)
    image[:, ::16] = (0.55, 0.55, 0.57)  # facade joints: texture, not sky
    trunk = np.zeros((H, W), bool)
    trunk[80:, 150:170] = True
    crown = np.zeros((H, W), bool)
    if with_crown:
        crown[30:80, 100:220] = True
    image[trunk] = (0.35, 0.22, 0.1)
    image[crown] = (0.15, 0.45, 0.12)
    vv, uu = np.mgrid[90:H:4, 0:W:2].astype(np.float64)
    z = np.where((uu >= 150) & (uu < 170), 8.0, 20.0)
    xyz = np.column_stack([((uu - K[0, 2]) / f * z).ravel(), ((vv - K[1, 2]) / f * z).ravel(), z.ravel()])
    R_lidar_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pts = CameraPoints(xyz=xyz, dt=np.zeros(len(xyz)), R_lidar_cam=R_lidar_cam, up_cam=np.array([0.0, -1.0, 0.0]))
    return pts, K, image, crown


def test_a_crown_above_the_lidar_takes_its_trunks_depth_not_the_facade_behind():
    pts, K, image, crown = _crown_scene()
    dd = complete_depth(pts, K, 320, 180, image, top_elevation_deg=0.0)
    z = dd.range / pixel_ray_norms(K, 320, 180)
    assert not dd.sky.any()
    assert abs(float(np.median(z[crown])) - 8.0) < 0.8  # the column rule gave the facade's 20 m
    assert np.mean(np.abs(z[crown] - 8.0) < 1.0) > 0.9
    facade_above = np.zeros_like(crown)
    facade_above[5:85, 10:90] = True  # facade above the top beam, away from the tree: continued upwards
    assert np.all(np.abs(z[facade_above] - 20.0) < 1.0)
    # without a crown the facade above the trunk is the facade (the trunk does not paint a streak upwards)
    pts, K, image, _ = _crown_scene(with_crown=False)
    z = complete_depth(pts, K, 320, 180, image, top_elevation_deg=0.0).range / pixel_ray_norms(K, 320, 180)
    assert np.all(np.abs(z[5:60, 100:220] - 20.0) < 1.0)


def test_sky_beside_a_facade_edge_is_sky_and_its_fog_has_no_halo():
    """A facade (z = 15 m, columns 0-159) against a blue sky (right half above the horizon, row 90) and a far wall
    (z = 60 m) below it; LiDAR rings every 12 px reach the facade's edge. A plain support radius (1.2 ring gaps)
    gave the sky a 14 px band of facade depth beside the edge: in dense fog a bright band along the skyline."""
    W, H, f = 320, 180, 160.0
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    image = np.empty((H, W, 3), np.float32)
    image[:, :160] = (0.55, 0.3, 0.25)
    image[:90, 160:] = (0.7, 0.8, 0.95)
    image[90:, 160:] = (0.5, 0.5, 0.5)
    uu, vv = np.meshgrid(np.arange(0, W, 2.0), np.arange(2, H, 12.0))
    z = np.where(uu < 160, 15.0, 60.0)
    keep = (uu < 160) | (vv >= 90)
    uu, vv, z = uu[keep], vv[keep], z[keep]
    xyz = np.column_stack([(uu - K[0, 2]) / f * z, (vv - K[1, 2]) / f * z, z])
    pts = CameraPoints(xyz=xyz, dt=np.zeros(len(xyz)),
                       R_lidar_cam=np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
                       up_cam=np.array([0.0, -1.0, 0.0]))
    dd = complete_depth(pts, K, W, H, image, top_elevation_deg=40.0)
    sky = np.zeros((H, W), bool)
    sky[:88, 161:] = True
    assert dd.sky[sky].mean() > 0.99
    assert not dd.sky[:, :158].any()  # the facade stays a surface
    exact = np.where(sky, np.inf, 15.0).astype(np.float32)
    dt = np.abs(transmission(dd.range, 0.05) - transmission(exact, 0.05))
    halo_cols = np.flatnonzero((dt[10:80] > 0.05).any(axis=0))
    assert halo_cols.size == 0 or halo_cols.max() - 159 <= 3


def test_a_pale_facade_above_the_top_ring_is_not_sky():
    """A smooth, pale facade (z = 20 m) fills a 320 x 180 upright camera; LiDAR rings every 8 px from the top beam
    (row 40, 17.4 deg above the horizon at row 90) down. The facade above the top ring looks like sky (smooth, the
    brightest thing in view, connected to the top border), but it continues the LiDAR-hit facade along its whole
    width. The rings above the horizon (a nuScenes HDL-32E's top beam is at +10.7 deg) cut the smooth region into
    stripes whose labels are larger than the top region's; the contact count once gave each cut pixel only its
    largest neighbouring label, so the top region never touched a cut and became sky (the synthetic
    world: 1.46 % of the structure taken for sky on keyframes, 0.33 % after)."""
    W, H, f = 320, 180, 160.0
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    image = np.empty((H, W, 3), np.float32)
    image[:] = (0.8, 0.8, 0.82)
    image[150:] = (0.35, 0.35, 0.35)  # road
    uu, vv = np.meshgrid(np.arange(0, W, 2.0), np.arange(40, 150, 8.0))
    z = np.full(uu.shape, 20.0)
    xyz = np.column_stack([((uu - K[0, 2]) / f * z).ravel(), ((vv - K[1, 2]) / f * z).ravel(), z.ravel()])
    pts = CameraPoints(xyz=xyz, dt=np.zeros(len(xyz)),
                       R_lidar_cam=np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
                       up_cam=np.array([0.0, -1.0, 0.0]))
    dd = complete_depth(pts, K, W, H, image, top_elevation_deg=float(np.degrees(np.arctan(50 / f))))
    assert not dd.sky.any()
    z_est = dd.range / pixel_ray_norms(K, W, H)
    assert np.all(np.abs(z_est[:40] - 20.0) < 0.5)  # continued upwards


def test_far_points_the_lidar_saw_over_an_upright_surface_are_dropped_not_those_over_the_ground():
    """The LiDAR 0.33 m above the camera (nuScenes CAM_FRONT) sees over a car's rear (z = 14 m, rings at rows 512,
    524, 536) to a facade at 40 m; in the camera (f = 1266 px) the facade's points land f h (1/14 - 1/40) = 19.4 px
    below the ray's image at the car, so a facade ring 12 px above the car's top ring is more likely on the car than
    beside it, one 36 px above is seen. Over the ground (rings at the road's rows for 14 m and 12 m) nothing
    hides it."""
    K = np.array([[1266.0, 0.0, 800.0], [0.0, 1266.0, 450.0], [0.0, 0.0, 1.0]])
    origin = np.array([0.0, -0.33, 0.0])
    z = np.zeros((900, 1600), np.float32)
    z[500, 790:811:4] = 40.0  # 12 px above the car's top ring
    z[476, 790:811:4] = 40.0  # 36 px above
    for row in (512, 524, 536):
        z[row, 790:811:2] = 14.0
    out = drop_parallax(z, origin, K, gap_v=12.0, gap_h=2.0, ratio=1.1, min_depth_m=1.0)
    assert not out[500].any() and np.array_equal(out[476], z[476])
    assert np.array_equal(out[512:], z[512:]) and np.count_nonzero(z) == 6 + 6 + 3 * 11  # input unchanged
    # the same facade ring above the road: the road's rings come nearer as fast as they drop, no surface rises
    ground = np.zeros_like(z)
    ground[500, 790:811:4] = 40.0
    for depth in (14.0, 12.0, 10.0):
        ground[int(round(450 + 1266.0 * 1.5 / depth)), 790:811:2] = depth
    assert np.array_equal(drop_parallax(ground, origin, K, 12.0, 2.0, 1.1, 1.0), ground)
    # no offset, no filter
    assert np.array_equal(drop_parallax(z, np.zeros(3), K, 12.0, 2.0, 1.1, 1.0), z)


def test_a_level_triangle_spanning_a_depth_jump_is_not_ground():
    """Three points at one height 0.3 m below the camera, two on a car's top at 14 m and one on a surface 44 m
    away (seen over the car): a level triangle, but no road rises so fast in depth between neighbouring rings
    (ratio 3.1 > ``ground_depth_ratio`` 2): not filled. The same triangle at 14 / 20 m (ratio 1.4) is road-like."""
    K = np.array([[1266.0, 0.0, 800.0], [0.0, 1266.0, 450.0], [0.0, 0.0, 1.0]])
    up = np.array([0.0, -1.0, 0.0])

    def filled(far: float) -> int:
        xyz = np.array([[-0.4, 0.3, 14.0], [0.4, 0.3, 14.0], [0.0, 0.3, far]])
        uv = (xyz / xyz[:, 2:]) @ K.T
        return int(np.count_nonzero(triangulate(uv[:, :2], xyz, up, 900, 1600, 200.0, DepthParams())))

    assert filled(44.0) == 0
    assert filled(20.0) > 100


def test_sky_through_a_gap_in_a_crown_is_sky_a_window_reflecting_it_is_not():
    """A 320 x 180 upright camera: sky (a vertical gradient) above the horizon, a dark textured crown (rows 10-80,
    columns 40-160) with a 20 x 20 px gap through which the sky shows, and a pale facade (columns 200-320, rows
    0-150) with a window reflecting the sky at a tenth of its brightness and one painted the sky's colour but
    cut by the LiDAR's rings. The gap is not connected to the top border through sky; it is sky all the same. The
    windows are not."""
    from weatheralign.camera.depth import image_sky

    W, H = 320, 180
    rows = np.arange(H, dtype=np.float32)[:, None, None]
    sky_colour = np.array([0.55, 0.7, 0.95], np.float32) + 0.1 * (rows / H) * np.array([1.0, 0.6, 0.0], np.float32)
    image = np.broadcast_to(sky_colour, (H, W, 3)).copy()
    image[150:] = 0.3  # road
    rng = np.random.default_rng(0)
    image[10:80, 40:160] = (0.1, 0.25, 0.08) + rng.uniform(0.0, 0.12, (70, 120, 1))  # foliage
    image[80:150, 95:105] = (0.25, 0.2, 0.15)  # the trunk
    image[35:55, 90:110] = sky_colour[35:55]  # the gap
    image[:150, 200:] = (0.75, 0.74, 0.72)  # facade
    image[30:50, 230:260] = 0.1 * sky_colour[30:50]  # a window reflecting the sky
    image[80:100, 230:260] = sky_colour[80:100]  # a sky-coloured panel on the hit facade
    lidar = np.zeros((H, W), bool)
    lidar[60:150:8, 200::2] = True  # the facade's rings
    lidar[100:150:8, 96:105:2] = True  # the trunk
    lidar[152::8, ::2] = True  # the street
    allowed = np.zeros((H, W), bool)
    allowed[:150] = True
    sky = image_sky(image, lidar, allowed)
    assert sky[38:52, 93:107].all()  # the gap
    assert sky[:, :30].mean() > 0.75 and not sky[12:30, 45:85].any()  # the sky beside the crown, not the foliage
    assert not sky[30:50, 230:260].any() and not sky[80:100, 230:260].any()  # the windows
