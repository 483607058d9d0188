"""The overcast light (weatheralign.camera.overcast): the CIE overcast sky's irradiances against their closed forms,
the vectorised relighting against its per-pixel oracle, a sun shadow lifted and the sky greyed on a made-up street,
and the conditions / media that carry it (calibrated, configured, switched off, the same for unaligned cameras)."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.camera.fog import decode_srgb_u8, encode_srgb_u8
from weatheralign.camera.overcast import (
    DIRECT_TO_DIFFUSE,
    SKY_IRRADIANCE_TABLE,
    Overcast,
    clear_sky_colour,
    irradiance_factor,
    light_layers,
    light_layers_naive,
    luminance,
    overcast_image,
    overcast_sky_luminance,
    pixel_sin_elevation,
    relight,
    relight_naive,
    relit_u8,
    up_in_camera,
)


def test_the_cie_overcast_sky_irradiances_match_their_closed_forms() -> None:
    # horizontal: 2π ∫ (1 + 2 sin γ)/3 sin γ cos γ dγ = 7π/9; vertical: 2 ∫ (1 + 2 sin γ)/3 cos² γ dγ = (π/4 + 2/3) 2/3
    assert SKY_IRRADIANCE_TABLE[-1] == pytest.approx(7.0 / 9.0, rel=1e-3)
    assert SKY_IRRADIANCE_TABLE[len(SKY_IRRADIANCE_TABLE) // 2] == pytest.approx((np.pi / 4 + 2 / 3) * 2 / 3 / np.pi,
                                                                                  rel=1e-3)
    assert SKY_IRRADIANCE_TABLE[0] == pytest.approx(0.0, abs=1e-9)
    assert irradiance_factor(-1.0, ground_albedo=0.2) == pytest.approx(0.2 * 7.0 / 9.0, rel=1e-3)
    assert overcast_sky_luminance(np.array([0.0, 1.0, -0.5]), 3.0) == pytest.approx([1.0, 3.0, 1.0])


def _street(h: int = 48, w: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A made-up clear image: a blue sky above row 12, a grey textured street below, the right half of it in a sun
    shadow (1 + s times darker and bluer); its ray lengths, intrinsics and a level camera pose."""
    rng = np.random.default_rng(0)
    lin = np.empty((h, w, 3), np.float32)
    lin[:12] = (0.3, 0.35, 0.45)  # the sky light's colour: the shadows'
    texture = 0.3 * (1.0 + 0.1 * rng.standard_normal((h - 12, w)))
    lit = texture[..., None] * np.array([1.0, 0.97, 0.92])
    shadow = texture[..., None] / (1.0 + DIRECT_TO_DIFFUSE) * np.array([0.85, 1.0, 1.3])
    lin[12:] = np.where((np.arange(w) < w // 2)[None, :, None], lit, shadow)
    ranges = np.full((h, w), 20.0, np.float32)
    ranges[:12] = np.inf
    K = np.array([[80.0, 0.0, w / 2], [0.0, 80.0, 12.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]).T  # OpenCV camera, global z up
    return encode_srgb_u8(lin), ranges, K, T


def _tilted_camera(h: int, w: int, even: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random image under a sky of 10 rows (and 1 or 2 pixels) whose corner is clipped, its ray lengths, an
    off-centre pinhole and a camera tilted 0.3 rad up (the sky's usable pixel count odd or even)."""
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    image[:2, :7] = 255  # clipped: left out of the sky's colour
    ranges = np.full((h, w), 15.0, np.float32)
    ranges[:10] = np.inf
    image[10, :2] = 100  # two more sky pixels, unclipped: one or both make the count odd or even
    usable = int((~np.isfinite(ranges) & (decode_srgb_u8(image).max(axis=2) < 0.98)).sum())
    ranges[10, : 1 if (usable + 1) % 2 == (0 if even else 1) else 2] = np.inf
    K = np.array([[61.3, 0.0, 27.9], [0.0, 60.7, 11.2], [0.0, 0.0, 1.0]])
    tilt = 0.3
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -np.sin(tilt), np.cos(tilt)], [-1.0, 0.0, 0.0], [0.0, -np.cos(tilt), -np.sin(tilt)]])
    return image, ranges, K, T


@pytest.mark.parametrize("even", [False, True])
def test_the_compiled_layers_equal_their_numpy_definitions(even) -> None:
    """`light_layers`' compiled passes against `pixel_sin_elevation` and `clear_sky_colour` bit for bit, on a
    tilted, off-centre camera of odd size whose sky holds clipped pixels and an odd or even count of usable ones
    (the median of an even count is the mean of the two middle codes)."""
    h, w = 31, 53
    image, ranges, K, T = _tilted_camera(h, w, even)
    layers = light_layers(image, ranges, K, T)
    sky = ~np.isfinite(ranges)
    usable = int((sky & (decode_srgb_u8(image).max(axis=2) < 0.98)).sum())
    assert usable % 2 == (0 if even else 1)
    assert np.array_equal(layers.sky, sky)
    assert np.array_equal(layers.sin_elevation, pixel_sin_elevation(K, w, h, up_in_camera(T)))
    assert np.array_equal(layers.sky_colour, clear_sky_colour(decode_srgb_u8(image), sky))
    assert np.array_equal(layers.linear, decode_srgb_u8(image))


def test_the_compiled_lit_share_follows_its_full_resolution_definition() -> None:
    """The lit share from the compiled passes (coefficients on the 2 x 2 block grid, base and envelope brought to
    every pixel) against `light_layers_naive` (numpy `log_base` and `lit_share` at full resolution) on a sunlit and
    shadowed street, and on its shadow's edge: equal where the light is even, within a few hundredths at edges."""
    image, ranges, K, T = _street(96, 192)
    fast = light_layers(image, ranges, K, T)
    colour, slow = light_layers_naive(image, ranges, K, T)
    assert np.array_equal(fast.sky_colour, colour)
    diff = np.abs(fast.lit - slow)
    assert diff[np.isinf(ranges)].max() == 0.0
    assert np.median(diff) < 1e-3 and np.percentile(diff, 99) < 0.05, (np.median(diff), np.percentile(diff, 99))
    street = fast.lit[30:, :]
    assert street[:, :80].mean() > 0.9 and street[:, 112:].mean() < 0.1  # the sunlit half and the shadowed half


@pytest.mark.parametrize("real", [False, True])
def test_the_compiled_relight_encodes_exactly_what_relight_gives(real) -> None:
    """The fixed-exposure path's one-pass kernel against the numpy `relight` then `encode_srgb_u8`, code for code, on
    the synthetic model and on a real street's (its shadows' and sun's own colours)."""
    image, ranges, K, T = _street(40, 64)
    layers = light_layers(image, ranges, K, T, real)
    sky = Overcast(0.15, 1.8, 2.5)
    slow = encode_srgb_u8(relight(layers.linear, layers.sky, layers.sin_elevation, layers.lit, sky, layers.ambient,
                                  layers.direct_to_diffuse, layers.sun_colour))
    fast = relit_u8(image, layers, sky)
    assert np.array_equal(fast, slow) and not np.array_equal(fast, image)


def test_relight_equals_its_per_pixel_oracle() -> None:
    image, ranges, K, T = _street(20, 30)
    layers = light_layers(image, ranges, K, T)
    assert layers.sin_elevation.shape == (20, 30) and layers.lit.min() >= 0.0 and layers.lit.max() <= 1.0
    sky = Overcast(0.15, 1.8, 2.5)
    fast = relight(layers.linear, layers.sky, layers.sin_elevation, layers.lit, sky, layers.sky_colour)
    slow = relight_naive(layers.linear, layers.sky, layers.sin_elevation, layers.lit, sky, layers.sky_colour)
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-6)


def test_a_sun_shadow_is_lifted_the_light_goes_neutral_and_the_sky_grey() -> None:
    image, ranges, K, T = _street()
    sky = Overcast(0.1, 1.5, 3.0)
    out = decode_srgb_u8(overcast_image(image, ranges, K, T, sky))
    before, after = luminance(decode_srgb_u8(image)), luminance(out)
    lit, shade = (slice(20, None), slice(8, 40)), (slice(20, None), slice(56, 88))
    assert before[shade].mean() / before[lit].mean() < 0.25  # the clear day: a sun shadow, 1 / (1 + s)
    assert after[shade].mean() / after[lit].mean() > 0.7  # under the cloud: nearly gone
    texture = np.corrcoef(before[lit].ravel(), after[lit].ravel())[0, 1]
    assert texture > 0.95  # the surface's texture stays
    blue = out[shade][..., 2].mean() / out[shade][..., 0].mean()
    assert abs(blue - 1.0) < 0.1  # the shadow's blue skylight went neutral
    h, w = ranges.shape
    expected = overcast_sky_luminance(pixel_sin_elevation(K, w, h, T[2, :3])[:12], 1.5)
    np.testing.assert_allclose(out[:12, :, 0], expected, rtol=0.02)
    np.testing.assert_allclose(out[:12, :, 0], out[:12, :, 2], rtol=0.02)  # grey
    with pytest.raises(ValueError, match="sun_transmittance"):
        Overcast(1.5, 1.0, 1.0)


def test_a_metering_camera_keeps_its_exposure_and_a_clouded_frame_its_surfaces() -> None:
    from weatheralign.camera.overcast import (
        Exposure,
        cloud_share,
        metered_log_luminance,
        metering_mask,
        overcast_linear,
    )

    image, ranges, K, T = _street()
    layers = light_layers(image, ranges, K, T)
    assert cloud_share(layers.sky_colour) == 0.0 and layers.direct_to_diffuse == DIRECT_TO_DIFFUSE
    sky = Overcast(0.1, 1.5, 3.0, zenith_over_surface=4.0)
    out, zenith = overcast_linear(layers, sky, Exposure.AUTO)
    meter = metering_mask(layers.sky, layers.sin_elevation)
    assert metered_log_luminance(out, meter) == pytest.approx(metered_log_luminance(layers.linear, meter), abs=1e-4)
    assert zenith == pytest.approx(4.0 * np.exp(metered_log_luminance(out, meter, 90.0)), rel=1e-4)
    np.testing.assert_allclose(out[:12, :, 1], overcast_sky_luminance(layers.sin_elevation[:12], zenith), rtol=1e-5)
    # the same street shot under cloud: a neutral sky, no sun in it: its surfaces keep their relative light
    lin = decode_srgb_u8(image)
    lin[:12] = 0.4
    grey = light_layers(encode_srgb_u8(lin), ranges, K, T)
    assert cloud_share(grey.sky_colour) == 1.0 and grey.direct_to_diffuse == 0.0
    out, _ = overcast_linear(grey, sky, Exposure.AUTO)
    ratio = luminance(out)[12:] / np.maximum(luminance(grey.linear)[12:], 1e-6)
    assert ratio.max() / ratio.min() < 1.01


def test_snow_rain_and_fog_snow_carry_the_light_calibrated_or_configured() -> None:
    from weatheralign.conditions import CONDITIONS
    from weatheralign.config import SimulateConfig
    from weatheralign.simulate.media import CalibratedLight, ConditionMedia, PrecipitationRates, resolve_overcast

    cfg = SimulateConfig()
    assert [n for n, c in CONDITIONS.items() if c.sky is not None] == ["snow", "rain", "fog_snow"]
    assert resolve_overcast(CONDITIONS["fog_light"], cfg) is None
    configured = resolve_overcast(CONDITIONS["rain"], cfg)
    assert configured == Overcast(cfg.overcast_sun_transmittance, cfg.overcast_zenith_luminance,
                                  cfg.overcast_diffuse_gain, cfg.overcast_zenith_over_surface).to_dict()
    tuned = PrecipitationRates({"snow": 2.0, "rain": 40.0}, {},
                               overcast={"snow": CalibratedLight.of(Overcast(0.1, 2.2, 3.3))})
    assert resolve_overcast(CONDITIONS["fog_snow"], cfg, tuned) == Overcast(0.1, 2.2, 3.3).to_dict()
    assert resolve_overcast(CONDITIONS["rain"], cfg, tuned) == configured  # no rain light calibrated
    assert resolve_overcast(CONDITIONS["snow"], cfg.model_copy(update={"overcast": False}), tuned) is None
    media = ConditionMedia("snow", None, None, overcast=Overcast(0.1, 2.2, 3.3).to_dict())
    back = ConditionMedia.from_dict(media.to_dict())
    assert back.overcast == media.overcast
    for aligned in (True, False):
        assert ConditionMedia("fog_light", None, None, overcast=media.overcast).for_scene(
            "s", aligned).overcast == Overcast(0.1, 2.2, 3.3)


@pytest.fixture(scope="module")
def overcast_reference(tmp_path_factory):
    """The smallest synthetic reference that shows the light: its clear, snow and rain splits only (no fog frames),
    4 frames each at 0.15 of STF's image size, the coarsest LiDAR (only the cameras are read); its sealed truth."""
    import json

    from weatheralign.config import params_from_dict
    from weatheralign.reference import configured_reference
    from weatheralign.reference.synthetic import finalize, frame_specs, render_or_resume, sealed_truth_path

    data = tmp_path_factory.mktemp("overcast_reference")
    params = params_from_dict({"paths": {"data": str(data)}, "tracking": {"enabled": False},
                               "reference": {"frames_per_split": 4, "lidar": {"firings_per_ring": 90},
                                             "camera": {"image_scale": 0.15},
                                             "precipitation": {"lidar_sub_rays": 4, "camera_samples": 2}}})
    cfg = params.reference
    specs = [spec for spec in frame_specs(cfg) if spec.level in ("clear", "snow", "rain")]
    finalize(cfg, data, [render_or_resume(spec, cfg, data)[0] for spec in specs])
    return configured_reference(params, ("clear", "snow", "rain")), json.loads(sealed_truth_path(data).read_text())


def _light(ds, sample_id: str):
    from tasks.calibrate import overcast_light_task

    return overcast_light_task.fn(ds, sample_id)


@pytest.fixture(scope="module")
def overcast_fits(overcast_reference):
    """``{snow|rain: OvercastFit}`` of the small reference, and its sealed truth."""
    from weatheralign.calibrate.overcast import fit_overcast

    ds, truth = overcast_reference
    clear = [_light(ds, i) for i in ds.ids("clear")]
    return {kind: fit_overcast(clear, [_light(ds, i) for i in ds.ids(kind)], num_bootstrap=50)
            for kind in ("snow", "rain")}, truth


@pytest.mark.parametrize("kind", ["snow", "rain"])
def test_the_hidden_zenith_luminance_is_recovered(overcast_fits, kind) -> None:
    fits, truth = overcast_fits
    fit = fits[kind]
    hidden = truth[kind]["zenith_luminance"]
    assert abs(fit.zenith_luminance / hidden - 1.0) < 0.1, (fit.zenith_luminance, hidden)
    assert fit.zenith_ci[0] <= fit.zenith_luminance <= fit.zenith_ci[1]
    assert fit.frames == 4 and 1.0 < fit.zenith_over_surface < 10.0


def test_the_diffuse_gain_falls_as_the_sun_it_leaves_rises(overcast_fits) -> None:
    # more of the sun on the lit facades leaves less of their brightness to the diffuse light
    fits, _ = overcast_fits
    for fit in fits.values():
        q = np.asarray(fit.diffuse_gains)
        assert np.all(np.diff(q) < 0.0) and q[-1] < q[0]
        assert np.all(np.asarray(fit.gain_ci_low) <= q) and np.all(q <= np.asarray(fit.gain_ci_high))
        assert fit.diffuse_gain(0.5 * (fit.sun_grid[1] + fit.sun_grid[2])) == pytest.approx(0.5 * (q[1] + q[2]))


def test_the_media_read_the_fit_with_the_params_sun(overcast_fits, tmp_path) -> None:
    import json

    from weatheralign.conditions import CONDITIONS
    from weatheralign.config import ParticlesConfig, SimulateConfig
    from weatheralign.data.errors import DataFormatError
    from weatheralign.simulate.media import calibrated_precipitation_rates, resolve_overcast

    fits, _ = overcast_fits
    path = tmp_path / "rates.json"
    path.write_text(json.dumps({"snow": {"rate_mm_h": 2.0}, "overcast": {"snow": fits["snow"].rates_entry()}}))
    rates = calibrated_precipitation_rates(path, ParticlesConfig())
    cfg = SimulateConfig()
    light = Overcast(**resolve_overcast(CONDITIONS["snow"], cfg, rates))
    assert light.sun_transmittance == cfg.overcast_sun_transmittance  # not identified: the params' T
    assert light.zenith_luminance == fits["snow"].zenith_luminance
    assert light.diffuse_gain == pytest.approx(fits["snow"].diffuse_gain(cfg.overcast_sun_transmittance))
    assert resolve_overcast(CONDITIONS["rain"], cfg, rates) == resolve_overcast(CONDITIONS["rain"], cfg)
    broken = {**fits["snow"].rates_entry(), "diffuse_gain_by_sun": [1.0]}
    path.write_text(json.dumps({"overcast": {"snow": broken}}))
    with pytest.raises(DataFormatError, match="sun_grid"):
        calibrated_precipitation_rates(path, ParticlesConfig())


@pytest.mark.xfail(reason="not identified: T needs each weather pixel's sun visibility, which one image of a "
                          "different scene does not give (docs/physics.md 4.3: the statistics tried and their "
                          "numbers); the fit reports Q over T and the simulation takes T from its params",
                   strict=True)
@pytest.mark.parametrize("kind", ["snow", "rain"])
def test_the_hidden_sun_transmittance_is_recovered(overcast_fits, kind) -> None:
    fits, truth = overcast_fits
    recovered = fits[kind].rates_entry()["sun_transmittance"]
    assert recovered is not None and abs(recovered / truth[kind]["sun_transmittance"] - 1.0) < 0.25


def _level_camera(w: int, horizon_row: float) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[80.0, 0.0, w / 2], [0.0, 80.0, horizon_row], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # camera x, -z, y: global z up
    return K, T


def test_a_real_streets_shadow_lit_by_warm_surroundings_comes_out_neutral() -> None:
    from weatheralign.camera.overcast import (
        SUN_COLOUR,
        Exposure,
        bounce_share,
        light_layers,
        overcast_linear,
        unit_colour,
    )

    # a blue sky, a sunlit red-brick wall, a neutral grey road half in the sun; the shadow is lit by the sky and by
    # what the sunlit wall and road reflect (bounce_share of its light), as on a real street
    h, w, s = 48, 96, DIRECT_TO_DIFFUSE
    rng = np.random.default_rng(1)
    sky_c, sun_c = unit_colour((0.3, 0.45, 0.6)), unit_colour(SUN_COLOUR)
    lit_light = sky_c + s * sun_c
    wall = np.array([0.35, 0.18, 0.12]) * lit_light
    road = 0.3 * lit_light
    reflected = unit_colour(0.25 * wall + 0.5 * road + 0.25 * 0.3 * sky_c)  # the sunlit surroundings' mean colour
    k = bounce_share(s)
    shade_light = (1.0 - k) * sky_c + k * reflected
    texture = (1.0 + 0.08 * rng.standard_normal((h, w)))[..., None]
    lin = np.empty((h, w, 3))
    lin[:12] = 0.45 * np.array([0.3, 0.45, 0.6]) / 0.45
    lin[12:24] = wall * 0.2 * texture[12:24]
    lin[24:] = np.where((np.arange(w) < w // 2)[None, :, None], road, 0.3 * shade_light) * 0.2 * texture[24:]
    image = encode_srgb_u8(lin.astype(np.float32))
    ranges = np.full((h, w), 20.0, np.float32)
    ranges[:12] = np.inf
    K, T = _level_camera(w, 12.0)
    light = Overcast(0.1, 1.5, 3.0)
    shade = (slice(30, None), slice(60, 90))
    for real, cast in ((False, 0.15), (True, 0.06)):
        layers = light_layers(image, ranges, K, T, real=real)
        out, _ = overcast_linear(layers, light, Exposure.AUTO)
        px = out[shade].reshape(-1, 3).mean(axis=0)
        r_g, b_g = px[0] / px[1], px[2] / px[1]
        if real:  # the road's grey albedo under the grey cloud: neutral
            assert abs(r_g - 1.0) < cast and abs(b_g - 1.0) < cast, (r_g, b_g)
        else:  # divided by the blue sky alone: the shadow turns warm (the flaw seen on KITTI)
            assert r_g - 1.0 > cast, (r_g, b_g)


def test_blue_sky_between_leaves_becomes_the_overcast_sky() -> None:
    from weatheralign.camera.overcast import Exposure, light_layers, overcast_linear

    # a blue sky above row 10, a tree crown (dark textured green) down to the horizon at row 30 with a gap of blue
    # sky in it that the LiDAR's range map calls surface (it hits the branches around it), a road below
    h, w = 48, 96
    rng = np.random.default_rng(2)
    blue = np.array([0.3, 0.5, 0.75])
    lin = np.empty((h, w, 3))
    lin[:10] = blue
    lin[10:30] = np.array([0.04, 0.09, 0.03]) * (1.0 + 0.3 * rng.standard_normal((20, w, 1))).clip(0.2)
    lin[16:22, 40:46] = blue  # the gap
    lin[30:] = 0.15 * (1.0 + 0.05 * rng.standard_normal((18, w, 1)))
    image = encode_srgb_u8(lin.astype(np.float32))
    ranges = np.full((h, w), 15.0, np.float32)
    ranges[:10] = np.inf
    K, T = _level_camera(w, 30.0)
    light = Overcast(0.1, 1.5, 3.0)
    sky_out = {}
    for real in (False, True):
        layers = light_layers(image, ranges, K, T, real=real)
        out, zenith = overcast_linear(layers, light, Exposure.AUTO)
        gap = out[17:21, 41:45].reshape(-1, 3)
        sky_out[real] = gap[:, 2].mean() / gap[:, 0].mean()
        if real:
            expected = overcast_sky_luminance(layers.sin_elevation[17:21, 41:45], zenith).ravel()
            np.testing.assert_allclose(gap[:, 1], expected, rtol=1e-4)  # the overcast sky at its elevation
            assert layers.sky[10:30].sum() <= 8 * 8  # the gap and its rim, not the leaves
            assert not layers.sky[30:].any()  # nothing below the horizon
    assert sky_out[False] > 1.2 and sky_out[True] == pytest.approx(1.0, abs=1e-4)  # relit as a surface: blue
