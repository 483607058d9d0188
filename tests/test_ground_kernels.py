"""The ground's compiled kernels against their numpy oracles: the noise fields, a range map's normals, the LiDAR
returns' normals and their neighbours' median, RANSAC's inlier counts, the screen-space reflection's march."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.ground.camera import (
    CameraGeometry,
    screen_space_reflection,
    screen_space_reflection_naive,
    strided_reflection,
)
from weatheralign.ground.surfaces import (
    median_over_neighbours,
    nearest_neighbours,
    pixel_normals,
    pixel_normals_naive,
    pixel_points,
    point_normals,
    point_normals_naive,
)
from weatheralign.ground.wet import fractal_noise, fractal_noise_naive
from weatheralign.lidar.ground_plane import plane_inliers, plane_inliers_naive


def test_fractal_noise_is_its_oracle_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    for cell, seed, octaves in ((4.0, 0, 4), (0.4, 11, 3), (25.0, -7, 1)):
        xy = rng.uniform(-2e5, 2e5, (20_000, 2))
        assert np.array_equal(fractal_noise(xy, cell, seed, octaves), fractal_noise_naive(xy, cell, seed, octaves))


def scene() -> tuple[np.ndarray, np.ndarray, CameraGeometry]:
    """A camera 1.5 m over a road with a striped wall 20 m ahead and a box 8 m ahead: (linear image, range map,
    camera)."""
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = [0.0, 0.0, 1.5]
    camera = CameraGeometry(K, T)
    rays = camera.rays_world(240, 320)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(rays[..., 2] < 0, -1.5 / rays[..., 2], np.inf)
        t_wall = np.where(rays[..., 0] > 0, 20.0 / rays[..., 0], np.inf)
        t_wall = np.where(1.5 + t_wall * rays[..., 2] <= 5.0, t_wall, np.inf)
        t_box = np.where(rays[..., 0] > 0, 8.0 / rays[..., 0], np.inf)
        box_y = t_box * rays[..., 1]
        box_z = 1.5 + t_box * rays[..., 2]
    t_box = np.where((np.abs(box_y) < 1.0) & (box_z > 0) & (box_z < 1.2), t_box, np.inf)
    range_map = np.minimum(np.minimum(t_ground, t_wall), t_box)
    stripes = (np.arange(320) // 8 % 2)[None, :, None] * np.array([0.6, 0.1, 0.1])
    image = np.where(np.isfinite(range_map)[..., None], 0.2 + stripes, np.array([0.5, 0.6, 0.9]))
    return image, range_map, camera


def test_pixel_normals_are_their_oracle() -> None:
    image, range_map, camera = scene()
    points = pixel_points(range_map, camera)
    for smooth_px in (5, 1):  # 1: the working grid's window, no averaging
        fast = pixel_normals(range_map, camera, smooth_px=smooth_px)
        slow = pixel_normals_naive(range_map, camera, smooth_px=smooth_px)
        for a, b in ((fast.points_world, slow.points_world), (fast.normals_world, slow.normals_world),
                     (points, slow.points_world)):
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
            np.testing.assert_allclose(a[~np.isnan(a)], b[~np.isnan(b)], atol=1e-9)


def test_the_reflection_march_is_its_oracle_and_strides_share_it() -> None:
    image, range_map, camera = scene()
    rays = camera.rays_world(240, 320)
    pixels = np.argwhere(np.isfinite(range_map) & (rays[..., 2] < -0.01) & (range_map * -rays[..., 2] > 1.49))
    normal, sky = np.array([0.0, 0, 1]), np.array([0.5, 0.6, 0.9])
    r = rays[pixels[:, 0], pixels[:, 1]]
    fast = screen_space_reflection(image, range_map, camera, pixels, r, normal, sky)
    np.testing.assert_array_equal(fast, screen_space_reflection_naive(image, range_map, camera, pixels, r, normal, sky))
    assert (fast != sky).any(axis=1).mean() > 0.3  # the wall and the box are mirrored, not just the sky
    strided = strided_reflection(image, range_map, camera, pixels, r, normal, sky, 2)
    corner = (pixels[:, 0] % 2 == 0) & (pixels[:, 1] % 2 == 0)
    np.testing.assert_array_equal(strided[corner], fast[corner])  # traced where the block's corner is
    lookup = {tuple(p): i for i, p in enumerate(pixels)}
    for i in np.nonzero(~corner)[0][::97]:
        j = lookup.get((pixels[i, 0] // 2 * 2, pixels[i, 1] // 2 * 2), i)
        np.testing.assert_array_equal(strided[i], fast[j])  # the others share their corner's (or trace their own)


def test_value_noise_is_its_oracle_bit_for_bit() -> None:
    from weatheralign.ground.wet import value_noise, value_noise_naive

    xy = np.random.default_rng(3).uniform(-1e5, 1e5, (20_000, 2))
    assert np.array_equal(value_noise(xy, 25.0, 18), value_noise_naive(xy, 25.0, 18))


def test_tire_tracks_are_their_oracle() -> None:
    from weatheralign.ground.snow import TireTracks

    tracks = TireTracks(direction=(0.6, 0.8), origin=(12.0, -7.0))
    xy = np.random.default_rng(5).uniform(-60, 60, (50_000, 2))
    np.testing.assert_allclose(tracks.depth_factor(xy, 9), tracks.depth_factor_naive(xy, 9), atol=1e-12)
    assert (tracks.depth_factor(xy, 9) < 1.0).mean() > 0.02  # some points lie in the tracks


def test_the_range_guided_edit_is_its_numpy_oracle_encoded() -> None:
    from weatheralign.camera.fog import affine_edit_u8, decode_srgb_u8, encode_srgb_u8, range_guided_upsample

    rng = np.random.default_rng(0)
    height, width, stride = 61, 83, 4  # sizes that cut the last blocks
    range_map = 10.0 + rng.normal(0.0, 0.2, (height, width))
    range_map[:20] = np.inf  # sky
    range_map[30:50, 40:60] = 5.0  # a car before the road
    range_map[35:45, 10] = 3.0  # a pole thinner than a block: no sample of its own
    h, w = -(-height // stride), -(-width // stride)
    gain = rng.uniform(0.5, 1.5, (h, w, 3))
    offset = rng.uniform(0.0, 0.2, (h, w, 3))
    edited = (rng.uniform(size=(h, w)) > 0.5).astype(np.float64)
    gain[:3], offset[:3] = 1.0, 0.0  # untouched rows: copied as they are
    image = rng.integers(0, 256, (height, width, 3)).astype(np.uint8)
    coded, mask = affine_edit_u8(image, gain, offset, edited, range_map, stride)
    up_gain = range_guided_upsample(gain, range_map, stride, fill=1.0)
    up_offset = range_guided_upsample(offset, range_map, stride)
    expected = encode_srgb_u8((decode_srgb_u8(image) * up_gain + up_offset).astype(np.float32))
    assert np.array_equal(coded, expected)
    assert np.array_equal(mask, range_guided_upsample(edited, range_map, stride) > 0.5)
    assert np.array_equal(coded[:8], image[:8])
    assert np.array_equal(up_gain[::stride, ::stride], gain)  # a pixel with a sample of its own reads it
    assert np.allclose(up_gain[29, 44], gain[7, 11])  # the road above the car reads the road's row only
    assert np.allclose(up_gain[19, 21], 0.75 * gain[4, 5] + 0.25 * gain[4, 6])  # the sky's edge reads the sky only
    assert any(np.allclose(up_gain[40, 10], gain[10, k]) for k in (2, 3))  # the pole: its nearest sample alone


def test_the_range_guided_edit_switches_layers_where_the_brought_field_is_positive() -> None:
    """A puddle's layers replace the film's where the smooth shoreline field, brought to the pixel, is > 0: the
    boundary is found per pixel (a curve), not per coarse cell (steps)."""
    from weatheralign.camera.fog import affine_edit_u8, decode_srgb_u8, encode_srgb_u8, range_guided_upsample

    rng = np.random.default_rng(1)
    height, width, stride = 57, 90, 4
    range_map = 10.0 + rng.normal(0.0, 0.02, (height, width))
    range_map[:12] = np.inf
    range_map[30:45, 50:70] = 5.0
    h, w = -(-height // stride), -(-width // stride)
    gain, alt_gain = rng.uniform(0.5, 1.5, (2, h, w, 3))
    offset, alt_offset = rng.uniform(0.0, 0.2, (2, h, w, 3))
    rows, cols = np.mgrid[0:h, 0:w]
    switch = (cols - 0.6 * rows - 5.33) / 10.0  # a slanted shoreline: a staircase on the coarse grid
    edited = np.ones((h, w))
    image = rng.integers(0, 256, (height, width, 3)).astype(np.uint8)
    coded, mask = affine_edit_u8(image, gain, offset, edited, range_map, stride, alternative=(alt_gain, alt_offset),
                                 switch=switch)
    inside = (range_guided_upsample(switch, range_map, stride, fill=-1.0) > 0)[..., None]
    up_gain = np.where(inside, range_guided_upsample(alt_gain, range_map, stride, fill=1.0),
                       range_guided_upsample(gain, range_map, stride, fill=1.0))
    up_offset = np.where(inside, range_guided_upsample(alt_offset, range_map, stride),
                         range_guided_upsample(offset, range_map, stride))
    expected = encode_srgb_u8((decode_srgb_u8(image) * up_gain + up_offset).astype(np.float32))
    assert np.array_equal(coded, expected)
    # on the road the boundary is the slanted line itself, found per pixel: s = (j - 0.6 i - 5.33 stride) / (10 stride)
    for i in range(16, 28):
        assert np.nonzero(inside[i, :, 0])[0].min() == int(np.floor(0.6 * i + 5.33 * stride)) + 1
    with pytest.raises(ValueError, match="both alternative and switch"):
        affine_edit_u8(image, gain, offset, edited, range_map, stride, switch=switch)


def test_point_normals_and_the_neighbour_median_are_their_oracles() -> None:
    """A road, a facade, a sphere and a line of returns (collinear neighbours: no plane): the neighbours are a k-d
    tree's, the compiled PCA normals numpy's eigenvectors up to rounding, the median numpy's bit for bit."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    road = np.column_stack([rng.uniform(-20, 20, (3000, 2)), rng.normal(-1.8, 0.02, 3000)])
    facade = np.column_stack([np.full(1000, 9.0), rng.uniform(-10, 10, 1000), rng.uniform(-1.8, 3, 1000)])
    sphere = rng.normal(0, 1, (1000, 3))
    sphere = sphere / np.linalg.norm(sphere, axis=1, keepdims=True) + [4.0, 4.0, 0.0]
    line = np.column_stack([np.linspace(-5, 5, 200), np.full(200, -6.0), np.full(200, 2.0)])
    points = np.concatenate([road, facade, sphere, line])
    neighbours = nearest_neighbours(points)
    distance, _ = cKDTree(points).query(points, k=16)  # the line's equal spacing ties: compare distances
    found = np.sort(np.linalg.norm(points[neighbours] - points[:, None], axis=2), axis=1)
    np.testing.assert_allclose(found, distance, atol=1e-12)
    fast, variation = point_normals(points, np.zeros(3), neighbours)
    slow, slow_variation = point_normals_naive(points, np.zeros(3), neighbours)
    np.testing.assert_allclose(np.linalg.norm(fast, axis=1), 1.0, atol=1e-12)
    planar = slice(0, len(points) - len(line))
    np.testing.assert_allclose(np.sum(fast[planar] * slow[planar], axis=1), 1.0, atol=1e-9)
    across = fast[-len(line):] @ np.array([1.0, 0, 0])  # the line's: any direction across it
    np.testing.assert_allclose(across, 0.0, atol=1e-6)
    np.testing.assert_allclose(variation, slow_variation, atol=1e-9)
    assert variation[-len(line):].max() < 1e-12  # a line has no variance across it
    values = rng.uniform(size=len(points))
    assert np.array_equal(median_over_neighbours(values, neighbours), np.median(values[neighbours], axis=1))
    odd = neighbours[:, :15]
    assert np.array_equal(median_over_neighbours(values, odd), np.median(values[odd], axis=1))


def test_plane_inliers_are_their_oracle() -> None:
    rng = np.random.default_rng(6)
    points = np.column_stack([rng.uniform(-30, 30, (4096, 2)), rng.normal(-1.8, 0.1, 4096)])
    normals = rng.normal(0, 1, (512, 3)) * [0.05, 0.05, 1.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.uniform(1.5, 2.1, 512)
    fast, slow = plane_inliers(points, normals, offsets, 0.2), plane_inliers_naive(points, normals, offsets, 0.2)
    assert np.abs(fast - slow).max() <= 1  # a point exactly at the tolerance may round either way
    assert np.argmax(fast) == np.argmax(slow) and slow.max() > 1000
