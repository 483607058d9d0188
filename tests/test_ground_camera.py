"""The wet road in a camera: the Fresnel mirror image found where geometry puts it, the pavement seen through the
water, nothing changed off the ground or where it is dry."""

from __future__ import annotations

import numpy as np

from weatheralign.ground.camera import CameraGeometry, wet_road_image
from weatheralign.ground.optics import fresnel_reflectance, hemispherical_reflectance
from weatheralign.ground.wet import WetRoad

HEIGHT_M, WALL_X_M, WALL_TOP_M = 1.5, 20.0, 5.0
GREY, RED, SKY = np.array([0.1, 0.1, 0.1]), np.array([0.8, 0.1, 0.1]), np.array([0.5, 0.6, 0.9])


def street() -> tuple[np.ndarray, np.ndarray, CameraGeometry, np.ndarray]:
    """A camera 1.5 m above flat ground looking along +x at a red wall 20 m ahead (5 m tall), sky above: (image,
    range map, camera, ground x [m] per pixel, nan off the ground)."""
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # OpenCV camera axes in the world (x fwd, z up)
    T[:3, 3] = [0.0, 0.0, HEIGHT_M]
    camera = CameraGeometry(K, T)
    rays = camera.rays_world(240, 320)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(rays[..., 2] < 0, -HEIGHT_M / rays[..., 2], np.inf)
        t_wall = np.where(rays[..., 0] > 0, WALL_X_M / rays[..., 0], np.inf)
    wall_z = HEIGHT_M + t_wall * rays[..., 2]
    t_wall = np.where((wall_z >= 0) & (wall_z <= WALL_TOP_M), t_wall, np.inf)
    range_map = np.minimum(t_ground, t_wall)
    on_ground = t_ground <= t_wall
    image = np.where(on_ground[..., None], GREY, np.where(np.isfinite(t_wall)[..., None], RED, SKY))
    ground_x = np.where(on_ground & np.isfinite(t_ground), t_ground * rays[..., 0], np.nan)
    return image, range_map, camera, ground_x


def test_a_puddle_mirrors_the_wall_where_geometry_puts_it_and_the_sky_beyond() -> None:
    image, range_map, camera, ground_x = street()
    road = WetRoad()
    ground = np.isfinite(ground_x)
    depth = np.where(ground, road.puddle_depth_m, 0.0)  # everything a puddle
    out = wet_road_image(image, range_map, camera, ground, depth, road, np.array([0.0, 0, 1]), SKY)
    rays = camera.rays_world(240, 320)
    theta = np.arccos(np.abs(rays[..., 2]))
    n = road.refractive_index
    r_e, r_i = hemispherical_reflectance(1.0, n), hemispherical_reflectance(n, 1.0)
    reflectance = fresnel_reflectance(theta, 1.0, n)[..., None]
    through = (1 - r_e) * (1 - reflectance) / (n**2 * (1 - road.pavement_reflectivity * r_i))
    # the mirrored ray from ground x rises 1.5 / x per metre: it meets the wall below its top when x > 20 * 1.5 / 6.5
    columns = np.arange(320)[None, :]
    central = (columns > 40) & (columns < 280)  # near the image's sides a mirrored ray leaves the image first
    sees_wall = ground & (ground_x > 5.5) & (ground_x < 18.0) & central
    sees_sky = ground & (ground_x < 4.0)
    expected_wall = through * GREY + reflectance * RED
    expected_sky = through * GREY + reflectance * SKY
    np.testing.assert_allclose(out[sees_wall], expected_wall[sees_wall], rtol=1e-9)
    np.testing.assert_allclose(out[sees_sky], expected_sky[sees_sky], rtol=1e-9)
    assert sees_wall.sum() > 500 and sees_sky.sum() > 500
    np.testing.assert_array_equal(out[~ground], image[~ground])  # the wall and the sky are not edited
    assert np.all(out[ground].mean(axis=1) < image[ground].mean(axis=1) + reflectance[ground][:, 0])


def test_dry_ground_and_partial_wetting() -> None:
    image, range_map, camera, ground_x = street()
    road = WetRoad(texture_depth_m=0.001)
    ground = np.isfinite(ground_x)
    out = wet_road_image(image, range_map, camera, ground, np.zeros(range_map.shape), road, np.array([0.0, 0, 1]),
                         SKY)
    np.testing.assert_array_equal(out, image)
    half = wet_road_image(image, range_map, camera, ground, np.full(range_map.shape, 0.0005), road,
                          np.array([0.0, 0, 1]), SKY, film_blur_px=(1, 1))
    full = wet_road_image(image, range_map, camera, ground, np.full(range_map.shape, 0.001), road,
                          np.array([0.0, 0, 1]), SKY)
    np.testing.assert_allclose(half[ground], 0.5 * (image[ground] + full[ground]), rtol=1e-9)


def test_wet_asphalt_is_darker_and_more_saturated() -> None:
    image, range_map, camera, ground_x = street()
    brown = np.array([0.12, 0.09, 0.06])
    image[np.isfinite(ground_x)] = brown
    ground = np.isfinite(ground_x) & (ground_x < 4.0)  # near the camera: steep view, weak reflection of the sky
    out = wet_road_image(image, range_map, camera, ground, np.where(ground, 0.01, 0.0), WetRoad(),
                         np.array([0.0, 0, 1]), np.zeros(3))  # a black sky: the pavement alone
    wet = out[ground]
    assert np.all(wet.sum(axis=1) < 0.6 * brown.sum())
    saturation = (wet.max(axis=1) - wet.min(axis=1)) / wet.max(axis=1)
    assert np.all(saturation > (brown.max() - brown.min()) / brown.max())


def test_snow_cover_is_sky_lit_snow_that_keeps_the_shading() -> None:
    from weatheralign.ground.camera import LUMINANCE, snow_cover_image
    from weatheralign.ground.optics import wet_albedo
    from weatheralign.ground.snow import SnowCover

    image, range_map, camera, ground_x = street()
    ground = np.isfinite(ground_x)
    points = camera.T_world_cam[:3, 3] + camera.rays_world(240, 320) * np.where(
        np.isfinite(range_map), range_map, 0.0)[..., None]
    shadow = ground & (ground_x < 6.0)  # the near road lies in a shadow: half as bright
    lit = np.where(shadow[..., None], 0.5 * image, image)
    cover = SnowCover(visible_albedo=0.8, pavement_reflectivity=0.15)
    coverage = np.where(ground, 1.0, 0.0)
    out = snow_cover_image(lit, coverage, points, ground, cover, SKY, seed=0, grain=0.0)
    assert np.array_equal(out[~ground], lit[~ground])  # the wall and the sky unchanged
    sky_luminance = SKY @ LUMINANCE
    expected = 0.8 * sky_luminance * (0.75 + 0.25 * SKY / sky_luminance)
    far = ground & (ground_x > 9.0) & (ground_x < 18.0)
    assert far.sum() > 500
    np.testing.assert_allclose(out[far], np.broadcast_to(expected, (far.sum(), 3)), rtol=1e-9)
    deep = shadow & (ground_x < 3.0)  # away from the shadow's edge (the shading is smoothed over 31 px)
    assert deep.sum() > 500
    np.testing.assert_allclose(out[deep], np.broadcast_to(0.75 * expected, (deep.sum(), 3)), rtol=1e-9)  # half of 0.5
    half = snow_cover_image(lit, 0.5 * coverage, points, ground, cover, SKY, seed=0, grain=0.0)
    melt = wet_albedo(0.15) / 0.15
    np.testing.assert_allclose(half[far], 0.5 * melt * lit[far] + 0.5 * expected, rtol=1e-9)
    grainy = snow_cover_image(lit, coverage, points, ground, cover, SKY, seed=0, grain=0.05)
    ratio = grainy[far][:, 1] / out[far][:, 1]
    assert 0.95 <= ratio.min() < 0.99 and 1.01 < ratio.max() <= 1.05
