"""The surfaces that receive water or snow: one ground plane in every frame, normals of an exact range map, the
nearest return's values, and the agreement of a LiDAR's and a camera's edits."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_dilation, binary_erosion

from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.surfaces import (
    mask_agreement,
    median_over_neighbours,
    nearest_neighbours,
    nearest_return_values,
    pixel_normals,
    point_normals,
)
from weatheralign.lidar.ground_plane import GroundPlane, fit_ground_plane


def tilted_ground(n: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """Returns on a slightly tilted road 1.8 m under the sensor plus a facade and clutter above it: (points (N, 3),
    the road's unit normal, its offset)."""
    rng = np.random.default_rng(seed)
    normal = np.array([0.03, -0.02, 1.0])
    normal /= np.linalg.norm(normal)
    offset = 1.8 * normal[2]
    xy = rng.uniform(-30, 30, (n, 2))
    road = np.column_stack([xy, -(normal[0] * xy[:, 0] + normal[1] * xy[:, 1] + offset) / normal[2]])
    road += rng.normal(0, 0.02, road.shape)
    facade = np.column_stack([np.full(n // 4, 12.0), rng.uniform(-20, 20, n // 4), rng.uniform(-1.2, 4, n // 4)])
    return np.concatenate([road, facade]), normal, offset


def test_the_ground_plane_is_found_and_moves_between_frames() -> None:
    points, normal, offset = tilted_ground()
    plane = fit_ground_plane(points)
    np.testing.assert_allclose(plane.normal, normal, atol=2e-3)
    assert plane.offset == pytest.approx(offset, abs=0.02)
    assert plane.contains(points[:4000]).mean() > 0.99 and not plane.contains(points[4000:]).any()
    T = np.eye(4)
    angle = 0.7
    T[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    T[:3, 3] = [100.0, -50.0, 3.0]
    moved = points @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(plane.transformed(T).height(moved), plane.height(points), atol=1e-9)


def test_a_cloud_without_low_returns_is_refused() -> None:
    with pytest.raises(ValueError, match="below the sensor"):
        fit_ground_plane(np.random.default_rng(0).uniform(0, 5, (500, 3)))


def test_point_normals_face_the_sensor_and_stray_values_are_outvoted() -> None:
    points, normal, _ = tilted_ground()
    neighbours = nearest_neighbours(points)
    normals = point_normals(points, np.zeros(3), neighbours).normals
    assert np.median(normals[:4000] @ normal) > 0.99  # the road's, turned up towards the sensor
    assert np.median(normals[4000:] @ np.array([-1.0, 0, 0])) > 0.95  # the facade's, turned back to the sensor
    values = np.where(np.arange(len(points)) == 7, 5.0, 1.0)
    assert median_over_neighbours(values, neighbours)[7] == 1.0


def test_pixel_normals_of_an_exact_range_map() -> None:
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # OpenCV axes: x forward, z up in the world
    T[:3, 3] = [0.0, 0.0, 1.5]
    camera = CameraGeometry(K, T)
    rays = camera.rays_world(240, 320)
    with np.errstate(divide="ignore"):
        t_ground = np.where(rays[..., 2] < 0, -1.5 / rays[..., 2], np.inf)
        t_wall = np.where(rays[..., 0] > 0, 20.0 / rays[..., 0], np.inf)
    t_wall = np.where(1.5 + t_wall * rays[..., 2] <= 5.0, t_wall, np.inf)  # a wall 5 m tall, the sky above
    range_map = np.minimum(t_ground, t_wall)
    surfaces = pixel_normals(range_map, camera)
    on_ground = t_ground < t_wall
    crease = binary_dilation(on_ground ^ binary_erosion(on_ground), iterations=3)  # where the road meets the wall
    known = np.isfinite(surfaces.normals_world[..., 0]) & ~crease
    ground, wall = on_ground & known, ~on_ground & np.isfinite(t_wall) & known
    assert ground.sum() > 10_000 and wall.sum() > 10_000
    np.testing.assert_allclose(surfaces.normals_world[ground], np.broadcast_to([0, 0, 1.0], (ground.sum(), 3)),
                               atol=1e-6)
    np.testing.assert_allclose(surfaces.normals_world[wall], np.broadcast_to([-1.0, 0, 0], (wall.sum(), 3)),
                               atol=1e-6)
    np.testing.assert_allclose(surfaces.points_world[ground][:, 2], 0.0, atol=1e-6)
    top = np.isfinite(t_wall) & ~on_ground & binary_dilation(~np.isfinite(range_map))  # the wall's top, the sky
    assert top.any() and np.isnan(surfaces.normals_world[top, 0]).all()


def test_nearest_return_values() -> None:
    returns = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    got = nearest_return_values(np.array([[0.1, 0, 0], [9.8, 0, 0], [5.0, 0, 0], [np.nan, 0, 0]]), returns,
                                np.array([1.0, 2.0]))
    assert got[:2].tolist() == [1.0, 2.0] and np.isnan(got[2:]).all()


def test_mask_agreement_counts_pixels_the_returns_land_on() -> None:
    camera = CameraGeometry(np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]), np.eye(4))
    u, v = np.meshgrid(np.arange(100), np.arange(100))
    points = np.column_stack([(u.ravel() - 50) / 100 * 10, (v.ravel() - 50) / 100 * 10, np.full(u.size, 10.0)])
    edited = v.ravel() >= 60
    camera_mask = np.zeros((100, 100), bool)
    camera_mask[60:] = True
    same = mask_agreement(points, edited, camera, camera_mask)
    assert same.iou == 1.0 and same.pixels == 10_000
    camera_mask[50:60] = True  # the camera edits 10 more rows
    wider = mask_agreement(points, edited, camera, camera_mask)
    assert wider.iou == pytest.approx(40 / 50) and wider.lidar_on_camera == 1.0
    assert wider.camera_on_lidar == pytest.approx(40 / 50)
    # a nearer return hides a farther one in its pixel: the nearer one's label counts
    both = mask_agreement(np.concatenate([points, points * 0.5]), np.concatenate([edited, ~edited]), camera,
                          camera_mask)
    assert both.iou == pytest.approx(10 / 100)


def test_ground_plane_record() -> None:
    plane = GroundPlane((0.0, 0.0, 1.0), 1.8)
    assert plane.height(np.array([[0.0, 0, -1.8], [0, 0, -1.0]])).tolist() == pytest.approx([0.0, 0.8])


def test_the_plane_fit_is_reproducible() -> None:
    points, _, _ = tilted_ground(seed=4)
    planes = {fit_ground_plane(points, seed=3) for _ in range(3)}
    assert len(planes) == 1


def test_returns_hidden_from_the_camera_do_not_count() -> None:
    camera = CameraGeometry(np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]), np.eye(4))
    u, v = np.meshgrid(np.arange(100), np.arange(100))
    points = np.column_stack([(u.ravel() - 50) / 100 * 10, (v.ravel() - 50) / 100 * 10, np.full(u.size, 10.0)])
    edited = np.ones(u.size, bool)
    camera_mask = np.zeros((100, 100), bool)
    camera_mask[:, 50:] = True
    range_map = np.hypot(np.hypot(points[:, 0], points[:, 1]), points[:, 2]).reshape(100, 100)
    range_map[:, :50] = 2.0  # something near the camera hides the left half's returns
    visible = mask_agreement(points, edited, camera, camera_mask, range_map=range_map)
    assert visible.iou == 1.0 and visible.pixels == 5000
    assert mask_agreement(points, edited, camera, camera_mask).iou == pytest.approx(0.5)


def test_surface_variation_tells_a_roof_from_foliage_and_only_the_roof_holds_snow() -> None:
    """A level roof and a tree crown (returns scattered through a ball) beside a road, under 1 cm range noise: the
    roof's neighbourhoods are surfaces (Pauly's variation ~0, under `MAX_SURFACE_VARIATION`), the crown's are not
    (an isotropic blob: 1/3 in the limit), and `scan_surfaces` gives the roof snow's orientation (|n_z| ~ 1) and the
    crown none, whatever its PCA normals say."""
    from weatheralign.data.frame import LidarScan
    from weatheralign.ground.edit import scan_surfaces
    from weatheralign.ground.surfaces import MAX_SURFACE_VARIATION

    rng = np.random.default_rng(11)
    road = np.column_stack([rng.uniform(-25, 25, (6000, 2)), rng.normal(-1.8, 0.02, 6000)])
    roof = np.column_stack([rng.uniform(6, 8, 800), rng.uniform(-1, 1, 800), rng.normal(-0.3, 0.01, 800)])
    ball = rng.normal(0, 1, (800, 3))
    ball *= (rng.uniform(0, 1, 800) ** (1 / 3) / np.linalg.norm(ball, axis=1))[:, None] * 1.5
    crown = ball + [4.0, -7.0, 2.5]
    points = np.concatenate([road, roof, crown])
    found = point_normals(points, np.zeros(3), nearest_neighbours(points))
    roof_rows, crown_rows = slice(6000, 6800), slice(6800, 7600)
    assert np.median(found.variation[roof_rows]) < MAX_SURFACE_VARIATION / 2
    assert np.quantile(found.variation[crown_rows], 0.05) > 2 * MAX_SURFACE_VARIATION
    scan = LidarScan(np.column_stack([points, np.full(len(points), 10.0), np.zeros(len(points))]).astype(np.float32),
                     0.0, np.eye(4), np.eye(4))
    surfaces = scan_surfaces(scan, tolerance_m=0.2)
    assert np.median(surfaces.cos_up[roof_rows]) > 0.95
    assert surfaces.cos_up[crown_rows].max() == 0.0
