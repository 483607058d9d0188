"""Camera particles: the numba splatter against a brute-force reference, projection, streak energy, occlusion,
pre-fogged colour, opacity range, determinism, compositing order, and the resolution contract with the field.

Stated tolerances: fast vs ``_naive`` (numpy, float64, every Gaussian at every pixel, per-pixel sort) agree to
1e-6 in the image (the fast kernel accumulates colour and transmittance in float32; observed <= 1e-7 over 30 random
scenes) and to 1e-6 px in the centroids, with identical drawn flags.
"""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.spatial.transform import Rotation

from weatheralign.camera.splat import (
    APPEARANCES,
    DILATION_PX2,
    OPACITY_RANGE,
    RAIN,
    RAIN_WEATHER_EDIT,
    SNOW,
    ParticleAppearance,
    _naive,
    environment_radiance,
    focal_px,
    materialize_for_camera,
    max_splat_range,
    min_splat_diameter,
    particle_attributes,
    render_particles,
    unresolved_extinction_profile,
)
from weatheralign.conditions import CONDITIONS, RAIN_APPEARANCES
from weatheralign.config import SimulateConfig, params_from_dict
from weatheralign.geometry import camera_rotation_from_yaw, invert, make_transform
from weatheralign.medium import ParticleField, RainSizeDistribution, SnowSizeDistribution, fall_velocity
from weatheralign.medium.conditions import FieldSpec, field_spec
from weatheralign.metrics.reprojection import CameraParticles, reprojection_check

IMAGE_TOL = 1e-6
H, W = 36, 48
K_SMALL = np.array([[40.0, 0.0, 24.0], [0.0, 40.0, 18.0], [0.0, 0.0, 1.0]])


def _pose(yaw: float = 0.3, position=(2.0, -1.0, 1.5)) -> np.ndarray:
    """T_cam_global of an upright camera at ``position`` looking along ``yaw``."""
    return invert(make_transform(camera_rotation_from_yaw(yaw), np.asarray(position, dtype=np.float64)))


def _points_in_view(T_cam_global: np.ndarray, cam_points: np.ndarray) -> np.ndarray:
    """Global positions of camera-frame points (N, 3)."""
    T = invert(T_cam_global)
    return cam_points @ T[:3, :3].T + T[:3, 3]


def _random_scene(seed: int, n: int = 40):
    """A camera in a random orientation (all Jacobian terms non-zero) with random particles in front of it."""
    rng = np.random.default_rng(seed)
    T = invert(make_transform(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-5, 5, 3)))
    cam = np.stack([rng.uniform(-2.0, 2.0, n), rng.uniform(-1.5, 1.5, n), rng.uniform(0.3, 5.0, n)], axis=1)
    pos = _points_in_view(T, cam)
    dia = rng.uniform(0.005, 0.08, n)
    ids = rng.integers(0, 2**50, n)
    img = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    rmap = rng.uniform(0.8, 6.0, (H, W)).astype(np.float32)
    rmap[: H // 4] = np.inf
    return T, pos, dia, ids, img, rmap


def _single(cam_point, diameter=0.08, ident=7, T=None, img=None, rmap=None, **kw):
    T = _pose() if T is None else T
    pos = _points_in_view(T, np.atleast_2d(np.asarray(cam_point, dtype=np.float64)))
    n = pos.shape[0]
    img = np.full((H, W, 3), 0.2, np.float32) if img is None else img
    rmap = np.full((H, W), np.inf, np.float32) if rmap is None else rmap
    kw = {"exposure_s": 0.0, **kw}
    return render_particles(img, rmap, K_SMALL, T, pos, np.broadcast_to(diameter, (n,)),
                            np.broadcast_to(ident, (n,)) if np.ndim(ident) == 0 else ident, (0, 0, -1.5), (0, 0, 0),
                            **kw), pos


# ------------------------------------------------------------------------------------------------------ reference
@pytest.mark.parametrize("scene", [0, 1])
@pytest.mark.parametrize("appearance", [SNOW, RAIN], ids=["snow", "rain"])
@pytest.mark.parametrize("exposure_s", [0.0, 0.005, 0.02])
@pytest.mark.parametrize("fog_alpha", [0.0, 0.05, 0.3])
@pytest.mark.parametrize("with_unresolved", [False, True], ids=["resolved_only", "unresolved_profile"])
@pytest.mark.parametrize("skew", [0.0, 0.7])  # K[0, 1]: a skewed pixel grid
@pytest.mark.parametrize("max_footprint_px", [64.0, 2.0])  # 2 px: the footprint cap path
def test_fast_matches_naive(scene: int, appearance: ParticleAppearance, exposure_s: float, fog_alpha: float,
                            with_unresolved: bool, skew: float, max_footprint_px: float,
                            own_velocities: bool = False) -> None:
    T, pos, dia, ids, img, rmap = _random_scene(scene)
    prof = unresolved_extinction_profile(SnowSizeDistribution(2.0, 1.5).spectrum(), 40.0, appearance)
    kw = dict(exposure_s=exposure_s, appearance=appearance, fog_alpha=fog_alpha, airlight=(0.6, 0.7, 0.8),
              unresolved=prof if with_unresolved else None, near_clip=0.5, max_footprint_px=max_footprint_px)
    v_field, v_cam = (1.0, 0.5, -1.5), (8.0, -2.0, 0.0)
    if own_velocities:  # every particle its own velocity (rain drops falling at their own speeds)
        v_field = np.random.default_rng(scene).uniform(-9.0, 9.0, (len(ids), 3))
    K = K_SMALL.copy()
    K[0, 1] = skew
    fast = render_particles(img, rmap, K, T, pos, dia, ids, v_field, v_cam, **kw)
    ref, cent = _naive(img, rmap, K, T, pos, dia, ids, v_field, v_cam, **kw)
    assert fast.image.dtype == np.float32 and fast.image.shape == (H, W, 3)
    assert fast.counts["drawn"] >= 10
    if max_footprint_px < 64.0:
        assert fast.counts["capped"] > 0  # the cap path is exercised
    assert np.abs(fast.image - ref).max() <= IMAGE_TOL
    assert np.abs(fast.image - img).max() > 0.05  # particles are actually there
    np.testing.assert_array_equal(fast.drawn, ~np.isnan(cent[:, 0]))
    np.testing.assert_allclose(fast.centroids[fast.drawn], cent[fast.drawn], atol=1e-6)


@pytest.mark.parametrize("scene", [0, 1])
@pytest.mark.parametrize("appearance", [SNOW, RAIN], ids=["snow", "rain"])
@pytest.mark.parametrize("fog_alpha", [0.0, 0.3])
@pytest.mark.parametrize("max_footprint_px", [64.0, 2.0])
def test_fast_matches_naive_with_a_velocity_per_particle(scene: int, appearance: ParticleAppearance,
                                                         fog_alpha: float, max_footprint_px: float) -> None:
    test_fast_matches_naive(scene, appearance, 0.02, fog_alpha, True, 0.7, max_footprint_px, own_velocities=True)


def test_naive_detects_a_wrong_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    """The oracle has teeth: dropping the dilation changes the image far beyond the tolerance."""
    import weatheralign.camera.splat as splat

    T, pos, dia, ids, img, rmap = _random_scene(11)
    ref, _ = _naive(img, rmap, K_SMALL, T, pos, dia, ids, (0, 0, -1.5), (0, 0, 0))
    monkeypatch.setattr(splat, "DILATION_PX2", 0.0)
    wrong = render_particles(img, rmap, K_SMALL, T, pos, dia, ids, (0, 0, -1.5), (0, 0, 0))
    assert np.abs(wrong.image - ref).max() > 100 * IMAGE_TOL


# ------------------------------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize("exposure", [0.0, 0.01])
def test_single_gaussian_projects_to_pinhole(exposure: float) -> None:
    T = _pose(0.7, (10.0, 3.0, 1.2))
    p_cam = np.array([0.31, -0.17, 2.3])
    res, pos = _single(p_cam, diameter=0.08, T=T, exposure_s=exposure)
    assert res.drawn[0] and res.in_frame[0] and res.unoccluded[0]
    expected = (K_SMALL @ p_cam)[:2] / p_cam[2]
    assert np.abs(res.centroids[0] - expected).max() < 0.01
    assert res.ray_length[0] == pytest.approx(np.linalg.norm(p_cam), rel=1e-12)


def test_centroids_unbiased_for_faint_near_streaks() -> None:
    """Near flakes seen by a side camera of a moving car: long, faint (opacity ~0.01) lateral streaks. The centroid
    window does not depend on the opacity, so every centroid stays on the pinhole projection (a window cut at
    alpha = 1/255 put such centroids up to 0.8 px off)."""
    rng = np.random.default_rng(5)
    h, w, n = 300, 400, 1500
    K = np.array([[1266.0, 0.0, 200.0], [0.0, 1266.0, 150.0], [0.0, 0.0, 1.0]])
    z = rng.uniform(0.5, 6.0, n)
    uv = np.column_stack([rng.uniform(20, w - 20, n), rng.uniform(20, h - 20, n)])
    pos = np.column_stack([(uv[:, 0] - 200.0) * z / 1266.0, (uv[:, 1] - 150.0) * z / 1266.0, z])
    dia = rng.exponential(0.002, n) + 3e-4
    res = render_particles(np.zeros((h, w, 3), np.float32), np.full((h, w), np.inf, np.float32), K, np.eye(4), pos,
                           dia, np.arange(n, dtype=np.int64), (0.0, 1.5, 0.0), (-10.0, 0.0, -3.0))
    ok = res.drawn & res.unoccluded & res.in_frame
    assert ok.sum() > 0.8 * n
    assert np.nanmin(res.opacity[ok]) < 0.02  # the faint streaks are among them
    err = np.linalg.norm(res.centroids[ok] - uv[ok], axis=1)
    assert err.max() < 0.05 and err.mean() < 0.005


def test_streak_follows_relative_motion_and_conserves_energy() -> None:
    """A horizontal relative motion smears the footprint along u; its integrated alpha stays (small alpha)."""
    T = _pose(0.0, (0.0, 0.0, 0.0))  # camera looks along global +x, image u is global -y
    p_cam = np.array([0.0, 0.0, 1.5])
    pos = _points_in_view(T, p_cam[None])
    img = np.zeros((H, W, 3), np.float32)
    rmap = np.full((H, W), np.inf, np.float32)
    look = ParticleAppearance("test", opacity=0.9, grey=1.0)
    args = (img, rmap, K_SMALL, T, pos, [0.04], [5], (0.0, 0.0, 0.0))
    still = render_particles(*args, (0.0, 0.0, 0.0), exposure_s=0.04, appearance=look)
    moving = render_particles(*args, (0.0, 10.0, 0.0), exposure_s=0.04, appearance=look)  # 40 cm: ~11 px streak
    assert moving.opacity[0] < 0.3 * still.opacity[0]
    # equal energy up to the part below the 1/255 cut-off (1/(255 o) of it: 0.4 % still, ~2 % moving)
    assert moving.alpha_sum[0] == pytest.approx(still.alpha_sum[0], rel=0.03)
    assert moving.image.sum() == pytest.approx(still.image.sum(), rel=0.03)  # one particle: image = alpha * grey
    a_still, a_moving = still.image[..., 0], moving.image[..., 0]
    width = lambda a, axis: np.count_nonzero(a.max(axis=axis) > 1e-3)  # noqa: E731
    assert width(a_moving, 0) > width(a_still, 0) + 4  # longer along u
    assert width(a_moving, 1) <= width(a_still, 1)  # not along v
    # without the opacity scaling the energy would grow by the area ratio (the test would fail)
    assert still.opacity[0] / moving.opacity[0] > 3.0


def test_each_particle_streaks_with_its_own_velocity() -> None:
    """(N, 3) velocities: each particle is drawn exactly as alone with its velocity; a bad shape is refused."""
    T = _pose(0.0, (0.0, 0.0, 0.0))
    pos = _points_in_view(T, np.array([[-0.3, 0.0, 1.5], [0.3, 0.0, 1.5]]))
    img, rmap = np.zeros((H, W, 3), np.float32), np.full((H, W), np.inf, np.float32)
    look = ParticleAppearance("test", opacity=0.9, grey=1.0)
    velocities = np.array([[0.0, 0.0, -2.0], [0.0, 0.0, -9.0]])
    both = render_particles(img, rmap, K_SMALL, T, pos, [0.02, 0.02], [1, 2], velocities, (0, 0, 0),
                            exposure_s=0.02, appearance=look)
    for i in range(2):
        alone = render_particles(img, rmap, K_SMALL, T, pos[i:i + 1], [0.02], [i + 1], velocities[i], (0, 0, 0),
                                 exposure_s=0.02, appearance=look)
        assert both.opacity[i] == alone.opacity[0] and both.alpha_sum[i] == pytest.approx(alone.alpha_sum[0])
    assert both.opacity[1] < 0.5 * both.opacity[0]  # the faster drop: a longer, fainter streak
    with pytest.raises(ValueError, match="velocity_global"):
        render_particles(img, rmap, K_SMALL, T, pos, [0.02, 0.02], [1, 2], velocities[:1], (0, 0, 0))


@pytest.mark.parametrize("speed", [0.0, 2.0, 6.6, 12.0])  # m/s across the view: streaks of 0, 10, 33, 60 px
def test_rain_streak_alpha_is_the_drops_projected_area_for_any_streak(speed: float) -> None:
    """Garg & Nayar's streak: each pixel's alpha is the fraction of the exposure the drop covers it, so the alpha
    summed over the streak is the drop's projected area ``π a D²/4 (f/z)²`` [px²] whatever its length (the part of
    the Gaussian below the 1/255 cut-off, ``2π sqrt(det Σ'2D) / 255``, is not drawn). Closed form for an upright
    drop (no cant) on the optical axis: ``σ_u = f D / (2z)``, ``σ_v = a σ_u``, ``a = 1.03 - 62 D``."""
    h, w, f, z, d = 120, 160, 1000.0, 1.0, 0.002
    K = np.array([[f, 0.0, 80.0], [0.0, f, 60.0], [0.0, 0.0, 1.0]])
    T = _pose(0.0, (0.0, 0.0, 0.0))  # looks along global +x; image u is global -y
    pos = _points_in_view(T, np.array([[0.0, 0.0, z]]))
    look = dataclasses.replace(RAIN, tilt_max_deg=0.0)
    res = render_particles(np.zeros((h, w, 3), np.float32), np.full((h, w), np.inf, np.float32), K, T, pos, [d],
                           [3], (0.0, speed, 0.0), (0.0, 0.0, 0.0), exposure_s=0.005, appearance=look)
    a = 1.03 - 62.0 * d
    su, sv = f * d / (2 * z), a * f * d / (2 * z)
    length = f * speed * 0.005 / z  # streak length [px]
    area = math.pi / 4 * a * d**2 * (f / z) ** 2  # = 2π · 0.5 · σ_u σ_v
    det2 = (su**2 + DILATION_PX2 + length**2 / 12) * (sv**2 + DILATION_PX2)
    assert res.opacity[0] == pytest.approx(0.5 * su * sv / math.sqrt(det2), rel=1e-9)
    cut = 2 * math.pi * math.sqrt(det2) / 255  # 0.5 % of the area still, 8 % at 6.6 m/s, 16 % at 12 m/s
    assert res.alpha_sum[0] + cut == pytest.approx(area, rel=0.025)  # the pixel grid's truncation: <= 2 %
    # the image holds alpha x the drop's radiance (black scene: the environment is half the airlight)
    radiance = 0.94 * 0.5 * 0.8
    assert float(res.image[..., 0].sum()) == pytest.approx(radiance * res.alpha_sum[0], rel=1e-5)


def test_weather_edit_rain_draws_40_percent_of_the_area_and_the_dilation_more() -> None:
    """Weather-edit's look (opacity 0.2 ± 0.05) draws ~40 % of an opaque drop; without the dilation compensation its
    integrated alpha is that of the dilated footprint ``o 2π sqrt(det(Σ2D + 0.3 I))``."""
    h, w, f, z, d = 120, 160, 1000.0, 1.0, 0.002
    K = np.array([[f, 0.0, 80.0], [0.0, f, 60.0], [0.0, 0.0, 1.0]])
    T = _pose(0.0, (0.0, 0.0, 0.0))
    pos = _points_in_view(T, np.array([[0.0, 0.0, z]]))
    args = (np.zeros((h, w, 3), np.float32), np.full((h, w), np.inf, np.float32), K, T, pos, [d], [3], (0, 0, 0),
            (0, 0, 0))
    new = render_particles(*args, appearance=dataclasses.replace(RAIN, tilt_max_deg=0.0))
    old = render_particles(*args, appearance=dataclasses.replace(RAIN_WEATHER_EDIT, tilt_max_deg=0.0))
    o_old = particle_attributes(np.array([3]), np.array([d]), RAIN_WEATHER_EDIT)[1][0]
    a = 1.03 - 62.0 * d
    su, sv = f * d / (2 * z), a * f * d / (2 * z)
    dilated = 2 * math.pi * math.sqrt((su**2 + DILATION_PX2) * (sv**2 + DILATION_PX2))
    assert old.alpha_sum[0] == pytest.approx(o_old * dilated - dilated / 255, rel=5e-3)
    assert new.alpha_sum[0] / old.alpha_sum[0] == pytest.approx(0.5 * su * sv / (o_old * dilated / (2 * math.pi)),
                                                                rel=0.05)


def test_drop_radiance_follows_the_environment() -> None:
    """A drop's radiance is 0.94 x (half the image's mean radiance + half the airlight): it brightens a dark road and
    darkens a bright sky (a constant grey 0.7 brightens both); it scales with the scene's light."""
    h, w = 80, 120
    K = np.array([[800.0, 0.0, 60.0], [0.0, 800.0, 40.0], [0.0, 0.0, 1.0]])
    T = _pose(0.0, (0.0, 0.0, 0.0))
    img = np.full((h, w, 3), 0.05, np.float32)
    img[: h // 2] = 0.9  # sky
    rmap = np.full((h, w), 20.0, np.float32)
    rmap[: h // 2] = np.inf
    cam = np.array([[0.0, -0.025, 1.0], [0.0, 0.025, 1.0]])  # one drop over the sky (row 20), one over the road
    pos = _points_in_view(T, cam)
    air = np.array([0.85, 0.85, 0.85])
    env = environment_radiance(img, air)
    np.testing.assert_allclose(env, 0.5 * img.astype(np.float64).reshape(-1, 3).mean(0) + 0.5 * air, rtol=1e-12)

    def drops(image, airlight, look=RAIN):
        return render_particles(image, rmap, K, T, pos, [0.003, 0.003], [1, 2], (0, 0, 0), (0, 0, 0),
                                appearance=look, airlight=airlight)

    res = drops(img, air)
    top, bottom = res.image[: h // 2] - img[: h // 2], res.image[h // 2:] - img[h // 2:]
    assert top.min() < -0.1 and top.max() <= 1e-7  # darker than the sky
    assert bottom.max() > 0.1 and bottom.min() >= -1e-7  # brighter than the road
    # the drop's colour: out = bg + alpha (c - bg) at its peak pixel
    centre = (20, 60)  # the sky drop's centre pixel
    alpha = float(res.max_alpha[0])
    c = img[centre] + (res.image[centre] - img[centre]) / alpha
    np.testing.assert_allclose(c, 0.94 * env, rtol=1e-4)
    brighter = drops(2 * img, 2 * air)
    np.testing.assert_allclose(brighter.image - 2 * img, 2 * (res.image - img), atol=1e-6)  # linear in the light
    old = drops(img, air, RAIN_WEATHER_EDIT)
    assert (old.image[h // 2:] - img[h // 2:]).max() > 0.05 and (old.image[: h // 2] - img[: h // 2]).min() > -0.1


def test_rain_appearances_are_named_consistently() -> None:
    """``simulate.rain_appearance`` offers exactly `RAIN_APPEARANCES`, each a rain look of `APPEARANCES`; the rain
    condition switches between them and names the choices when given another."""
    assert set(RAIN_APPEARANCES) == set(SimulateConfig.model_fields["rain_appearance"].annotation.__args__)
    assert all(APPEARANCES[n].name == n and APPEARANCES[n].oblate_drops for n in RAIN_APPEARANCES)
    assert APPEARANCES["rain"] is RAIN and APPEARANCES["rain_weather_edit"] is RAIN_WEATHER_EDIT
    assert CONDITIONS["rain"].with_rain_appearance("rain_weather_edit").particles.camera_appearance == \
        "rain_weather_edit"
    assert CONDITIONS["snow"].with_rain_appearance("rain_weather_edit") is CONDITIONS["snow"]
    with pytest.raises(ValueError, match=r"simulate.rain_appearance = 'rain_opaque_drops' is invalid: expected one "
                                         r"of \['rain', 'rain_weather_edit'\]"):
        CONDITIONS["rain"].with_rain_appearance("rain_opaque_drops")
    with pytest.raises(ValueError, match="ParticleAppearance.radiance = 'sky' is invalid"):
        ParticleAppearance("x", radiance="sky")


# ------------------------------------------------------------------------------------------------------ occlusion
def test_occlusion_against_scene_depth() -> None:
    img = np.full((H, W, 3), 0.2, np.float32)
    p = [0.0, 0.0, 2.0]
    behind, _ = _single(p, img=img, rmap=np.full((H, W), 1.5, np.float32))
    front, _ = _single(p, img=img, rmap=np.full((H, W), 2.5, np.float32))
    assert not behind.drawn[0] and not behind.unoccluded[0] and behind.counts["occluded_fully"] == 1
    assert np.array_equal(behind.image, img)
    assert front.drawn[0] and front.unoccluded[0] and np.abs(front.image - img).max() > 0.1
    half = np.full((H, W), 2.5, np.float32)
    half[:, : W // 2] = 1.0  # a wall in front of the left half of the footprint
    partial, _ = _single(p, img=img, rmap=half)
    assert partial.drawn[0] and not partial.unoccluded[0]
    assert np.array_equal(partial.image[:, : W // 2], img[:, : W // 2])
    assert np.abs(partial.image[:, W // 2:] - img[:, W // 2:]).max() > 0.1


def test_near_clip_and_behind_camera() -> None:
    res, _ = _single(np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -2.0], [0.0, 0.0, 2.0]]), ident=np.array([1, 2, 3]))
    assert res.counts["near_clipped"] == 2 and res.drawn.tolist() == [False, False, True]
    assert np.isnan(res.centroids[:2]).all()


# ------------------------------------------------------------------------------------------------------ colour
def test_prefog_gives_the_airlight() -> None:
    air = (0.3, 0.5, 0.7)
    img = np.broadcast_to(np.asarray(air, np.float32), (H, W, 3)).copy()
    p = [0.0, 0.0, 2.0]
    clear, _ = _single(p, img=img, airlight=air, fog_alpha=0.0)
    dense, _ = _single(p, img=img, airlight=air, fog_alpha=50.0)
    assert np.abs(clear.image - img).max() > 0.1  # a grey flake on a coloured background
    assert dense.drawn[0]
    assert np.abs(dense.image - img).max() < 1e-6  # fully fogged flake = the airlight
    # intermediate: colour c t + A (1 - t) at the flake's ray length
    half, _ = _single(p, img=np.zeros((H, W, 3), np.float32), airlight=air, fog_alpha=math.log(2) / 2.0,
                      appearance=ParticleAppearance("flat", opacity=0.99, grey=0.8))
    centre = half.image[int(round(half.centroids[0, 1])), int(round(half.centroids[0, 0]))]
    np.testing.assert_allclose(centre / centre.max(), (0.4 + 0.5 * np.array(air)) / 0.75, atol=0.01)


def test_opacity_within_unit_interval() -> None:
    T, pos, dia, ids, img, rmap = _random_scene(3, n=200)
    for look in (SNOW, RAIN, ParticleAppearance("extreme", opacity=1.0, opacity_spread=1.0)):
        _, o, g = particle_attributes(ids, dia, look)
        assert (o >= OPACITY_RANGE[0]).all() and (o <= OPACITY_RANGE[1]).all() and o.min() > 0 and o.max() < 1
        assert (g >= 0).all() and (g <= 1).all()
        res = render_particles(img, rmap, K_SMALL, T, pos, dia, ids, (0, 0, -1.5), (10, 0, 0), appearance=look,
                               exposure_s=0.01)
        o_eff = res.opacity[np.isfinite(res.opacity)]
        assert (o_eff > 0).all() and (o_eff < 1).all()
        assert res.max_alpha.max() <= 0.99 + 1e-7
    _, o, _ = particle_attributes(ids, dia, SNOW)
    assert 0.3 <= o.min() < 0.35 and 0.65 < o.max() <= 0.7  # 0.5 ± 0.2


def test_empty_input_returns_image_unchanged() -> None:
    img = np.random.default_rng(0).uniform(0, 1, (H, W, 3)).astype(np.float32)
    res = render_particles(img, np.full((H, W), np.inf, np.float32), K_SMALL, _pose(), np.zeros((0, 3)),
                           np.zeros(0), np.zeros(0, np.int64), (0, 0, -1), (5, 0, 0))
    assert res.image.tobytes() == img.tobytes() and res.image is not img
    assert res.counts["drawn"] == 0 and res.centroids.shape == (0, 2)
    # particles that all miss the image also leave it bitwise unchanged
    miss, _ = _single([0.0, 0.0, -3.0], img=img)
    assert miss.image.tobytes() == img.tobytes()


# ------------------------------------------------------------------------------------------------------ determinism
def test_deterministic_and_order_independent() -> None:
    T, pos, dia, ids, img, rmap = _random_scene(5, n=120)
    args = (K_SMALL, T)
    kw = dict(exposure_s=0.005, fog_alpha=0.02, appearance=SNOW)
    a = render_particles(img, rmap, *args, pos, dia, ids, (0, 0, -1.5), (6, 1, 0), **kw)
    b = render_particles(img, rmap, *args, pos, dia, ids, (0, 0, -1.5), (6, 1, 0), **kw)
    perm = np.random.default_rng(1).permutation(len(ids))
    c = render_particles(img, rmap, *args, pos[perm], dia[perm], ids[perm], (0, 0, -1.5), (6, 1, 0), **kw)
    assert a.image.tobytes() == b.image.tobytes() == c.image.tobytes()
    assert a.centroids[perm].tobytes() == c.centroids.tobytes()
    with ThreadPoolExecutor(4) as pool:
        outs = list(pool.map(lambda _: render_particles(img, rmap, *args, pos, dia, ids, (0, 0, -1.5), (6, 1, 0),
                                                        **kw).image.tobytes(), range(8)))
    assert all(o == outs[0] for o in outs)
    # attributes come from the id, not from the position in the array
    cov, o, g = particle_attributes(ids, dia, SNOW)
    cov_p, o_p, g_p = particle_attributes(ids[perm], dia[perm], SNOW)
    assert cov[perm].tobytes() == cov_p.tobytes() and o[perm].tobytes() == o_p.tobytes()
    assert g[perm].tobytes() == g_p.tobytes()


def test_front_to_back_order() -> None:
    look = ParticleAppearance("bw", opacity=0.99, grey=0.5, grey_spread=0.5)
    ids = np.arange(1000)
    _, _, grey = particle_attributes(ids, np.full(1000, 0.01), look)
    bright, dark = int(ids[np.argmax(grey)]), int(ids[np.argmin(grey)])
    assert grey[bright] > 0.95 and grey[dark] < 0.05
    img = np.full((H, W, 3), 0.5, np.float32)
    centre = (int(round(K_SMALL[1, 2])), int(round(K_SMALL[0, 2])))

    def render(z_bright: float, z_dark: float) -> float:
        pts = np.array([[0.0, 0.0, z_bright], [0.0, 0.0, z_dark]])
        res, _ = _single(pts, diameter=0.2 * np.array([z_bright, z_dark]) / 2.0, ident=np.array([bright, dark]),
                         img=img, appearance=look)
        return float(res.image[centre][0])

    assert render(2.0, 2.2) > 0.8  # bright in front
    assert render(2.2, 2.0) < 0.2  # dark in front


# ------------------------------------------------------------------------------------------------------ contract
def _snow_field() -> ParticleField:
    return ParticleField(5, SnowSizeDistribution(2.0, 1.5), velocity=fall_velocity(1.5, (1.0, 0.0)), t_ref=100.0)


def test_min_splat_diameter_matches_the_dilation() -> None:
    f = 1266.0
    r = np.array([0.4, 0.5, 1.0, 7.0, 30.0])
    d = min_splat_diameter(r, f, SNOW, near_clip=0.5, max_range=20.0)
    assert np.isinf(d[0]) and np.isinf(d[-1])
    sigma_px = f * SNOW.sigma_per_diameter * d[1:4] / r[1:4]
    np.testing.assert_allclose(sigma_px**2, 0.3, rtol=1e-12)
    assert max_splat_range(0.02, f, SNOW) == pytest.approx(0.02 * f * 0.5 / math.sqrt(0.3))


def test_materialize_for_camera_is_the_exact_resolvable_subset() -> None:
    fld = _snow_field()
    K = np.array([[600.0, 0.0, 159.5], [0.0, 600.0, 99.5], [0.0, 0.0, 1.0]])
    w, h = 320, 200
    T_global_cam = make_transform(camera_rotation_from_yaw(0.4), np.array([5.0, -3.0, 1.6]))
    t, max_range, near = 101.3, 8.0, 0.5
    got = materialize_for_camera(fld, K, w, h, T_global_cam, t, SNOW, near_clip=near, max_range=max_range,
                                 max_footprint_px=8.0)
    assert len(got) > 50 and np.all(np.diff(got.ids) > 0)
    # brute force: everything within max_range at the smallest threshold, filtered per particle
    c = T_global_cam[:3, 3]
    f = focal_px(K)
    all_p = fld.materialize(c - max_range, c + max_range, t, min_diameter=float(min_splat_diameter(near, f, SNOW)))
    pc = (all_p.positions - c) @ T_global_cam[:3, :3]
    ell = np.linalg.norm(pc, axis=1)
    ok = (ell >= near) & (ell <= max_range) & (pc[:, 2] >= 0.25 * near)
    ok &= all_p.diameters >= min_splat_diameter(ell, f, SNOW, near, max_range)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
    inside = ok & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    assert set(all_p.ids[inside]) <= set(got.ids)  # every resolvable particle projecting into the image
    assert set(got.ids) <= set(all_p.ids[ok])  # and only resolvable ones (plus the footprint margin)
    np.testing.assert_array_equal(fld.positions_at(got.ids, t), got.positions)


def test_unresolved_profile_integrates_the_field() -> None:
    """The camera's unresolved medium is the particles' geometric shadow: half the beam extinction (Q_ext = 2) of
    the field's particles below the splatting threshold."""
    fld = _snow_field()
    f = 1266.0
    prof = unresolved_extinction_profile(fld, f, SNOW, near_clip=0.5)
    total = 0.5 * fld.extinction()
    for ell in (0.3, 2.0, 9.0, 20.0):
        expected = quad(lambda r: 0.5 * fld.unresolved_extinction(float(min_splat_diameter(r, f, SNOW, 0.5)))
                        if r >= 0.5 else total, 0.0, ell, points=[0.5], limit=200)[0]
        assert float(prof.optical_depth(ell)) == pytest.approx(expected, rel=2e-3, abs=1e-7)
    r_end = max_splat_range(fld.spectrum.d_max, f, SNOW)
    assert prof.r_end == pytest.approx(r_end)
    slope = (float(prof.optical_depth(r_end + 50.0)) - float(prof.optical_depth(r_end + 10.0))) / 40.0
    assert slope == pytest.approx(total, rel=1e-9)
    assert float(prof.transmission(np.inf)) == 0.0
    assert 0.0 < prof.resolved_optical_depth < total * r_end
    rmap = np.array([[1.0, 10.0, np.inf]], np.float32)
    tr = prof.transmission(rmap, fog_alpha=0.01)
    assert tr.dtype == np.float32
    np.testing.assert_allclose(tr[0, :2], np.exp(-0.01 * rmap[0, :2] - prof.optical_depth(rmap[0, :2])), rtol=1e-6)


@pytest.mark.parametrize("distribution", [SnowSizeDistribution(2.0, 1.5), RainSizeDistribution(50.0)])
def test_unresolved_profile_matches_the_exact_cameras_medium(distribution) -> None:
    """The fast camera and the synthetic reference's exact camera (`camera_particles_exact.UnresolvedMedium`, closed
    form) see the same unresolved medium when they resolve the same particles: splatting from ``D = k ℓ`` on, the
    optical depth gained between two ray lengths agrees, and beyond the last resolved range both grow at the bulk
    geometric shadow."""
    from weatheralign.reference.camera_particles_exact import UnresolvedMedium

    fld = ParticleField(5, distribution, velocity=(0.0, 0.0, -1.0), t_ref=0.0)
    f, near = 1266.0, 0.5
    prof = unresolved_extinction_profile(fld, f, SNOW, near_clip=near, samples=4096)
    k = float(min_splat_diameter(1.0, f, SNOW, near))  # the splatting threshold per metre of ray length
    exact = UnresolvedMedium.of(fld, resolve_px=k * f, focal_px=f, max_distance=prof.r_end)
    for a, b in ((near, 2.0), (2.0, 7.0), (near, prof.r_end)):
        gained = float(prof.optical_depth(b) - prof.optical_depth(a))
        assert gained == pytest.approx(float(exact.optical_depth_to(b) - exact.optical_depth_to(a)), rel=1e-4)
    beyond = float(prof.optical_depth(prof.r_end + 30.0) - prof.optical_depth(prof.r_end + 10.0)) / 20.0
    assert beyond == pytest.approx(exact.alpha_total, rel=1e-9)
    assert beyond == pytest.approx(0.5 * fld.extinction(), rel=1e-9)


@pytest.mark.parametrize("appearance", [RAIN, RAIN_WEATHER_EDIT], ids=["rain", "weather_edit"])
def test_rain_field_end_to_end_small_camera(appearance: ParticleAppearance) -> None:
    """The default rain field (params' 50 mm/h, falling at its median-volume drop's 6.6 m/s) materialised for a
    small camera and splatted: drawn streaks, fast == naive; the same spec gives the same bytes."""
    spec = field_spec(params_from_dict({}).particles, "rain", "scene-0061", 0.0)
    fld = spec.field()
    assert fld.velocity_array[2] == pytest.approx(-6.613, abs=1e-3)
    w, h = 240, 180
    K = np.array([[600.0, 0.0, 120.0], [0.0, 600.0, 90.0], [0.0, 0.0, 1.0]])
    T_global_cam = make_transform(camera_rotation_from_yaw(1.0), np.array([0.0, 0.0, 1.5]))
    parts = materialize_for_camera(fld, K, w, h, T_global_cam, 0.01, appearance)
    assert len(parts) > 3
    assert max_splat_range(fld.spectrum.d_max, 600.0, appearance) < 4.0  # rain is resolved only near the lens
    T = invert(T_global_cam)
    img = np.full((h, w, 3), 0.1, np.float32)
    rmap = np.full((h, w), np.inf, np.float32)
    kw = dict(appearance=appearance, exposure_s=0.005)
    fast = render_particles(img, rmap, K, T, parts.positions, parts.diameters, parts.ids, fld.velocity_array,
                            (8.0, 0.0, 0.0), **kw)
    ref, _ = _naive(img, rmap, K, T, parts.positions, parts.diameters, parts.ids, fld.velocity_array,
                    (8.0, 0.0, 0.0), **kw)
    assert fast.counts["drawn"] > 0
    assert np.abs(fast.image - ref).max() <= IMAGE_TOL
    again = FieldSpec.from_dict(spec.to_dict()).field()
    p2 = materialize_for_camera(again, K, w, h, T_global_cam, 0.01, appearance)
    twice = render_particles(img, rmap, K, T, p2.positions, p2.diameters, p2.ids, again.velocity_array,
                             (8.0, 0.0, 0.0), **kw)
    assert twice.image.tobytes() == fast.image.tobytes() and twice.centroids.tobytes() == fast.centroids.tobytes()
    # aligned with what a LiDAR knows: the drawn drops 30 ms earlier, moved by the one field velocity, land on their
    # streaks' rasterised centroids
    usable = fast.drawn & fast.unoccluded & fast.in_frame
    cam = CameraParticles("cam", K, T_global_cam, 0.01, w, h, parts.ids, fast.centroids, usable, rmap)
    check = reprojection_check(fld, parts.ids[usable], np.full(int(usable.sum()), 0.01 - 0.03), [cam], True)
    assert check.error_px.size == usable.sum() > 3 and check.error_px.max() < 0.01
