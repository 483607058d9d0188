"""The small BEVFusion-style detector (weatheralign.detect.model / head) on synthetic tensors: target encoding round
trip, LSS geometry and pooling, pillar scatter, modality switches, overfitting one batch, device placement."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
import torch

from weatheralign.detect.head import (
    NUM_ATTRIBUTES,
    BevGrid,
    HeadOutputs,
    decode_detections,
    encode_targets,
    valid_attribute_mask,
)
from weatheralign.detect.model import (
    BEVFusionDetector,
    DepthBins,
    DetectorConfig,
    PillarEncoder,
    bev_cell_indices,
    bev_max_pool,
    cell_rays,
    count_parameters,
    depth_loss,
    depth_targets,
    frustum_points,
    lift_splat,
    modality_masks,
    project_into_cells,
    sweep_statistics,
    sweep_statistics_naive,
    train_step,
)
from weatheralign.detect.types import ATTRIBUTES, DETECTION_CLASSES, DetectionBatch, SampleDetections

CLS = {name: k for k, name in enumerate(DETECTION_CLASSES)}
ATTR = {name: a for a, name in enumerate(ATTRIBUTES)}
SMALL = DetectorConfig(bev_range_m=16.0, bev_cell_m=0.8, depth_bins=16, depth_max_m=33.0, image_channels=32,
                       pillar_channels=16, camera_context_channels=16, bev_channels=32, head_channels=32,
                       modality_dropout=0.0)


@pytest.fixture(autouse=True)
def one_torch_thread() -> Iterator[None]:
    """These models are tiny: one thread is faster than two, and does not stall when the cores are shared."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def yaw_rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_pose(yaw: float, position: tuple[float, float, float], pitch_down: float = 0.0) -> np.ndarray:
    """(4, 4) camera (OpenCV: x right, y down, z forward) -> LiDAR, the camera looking along LiDAR azimuth ``yaw``."""
    forward = np.array([1.0, 0.0, 0.0])
    right = np.array([0.0, -1.0, 0.0])
    down = np.array([0.0, 0.0, -1.0])
    c, s = math.cos(pitch_down), math.sin(pitch_down)
    forward, down = c * forward + s * down, c * down - s * forward
    T = np.eye(4)
    T[:3, :3] = yaw_rotation(yaw) @ np.stack([right, down, forward], axis=1)
    T[:3, 3] = position
    return T


def pinhole(height: int, width: int, focal: float) -> np.ndarray:
    return np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])


def camera_rig(batch_size: int, cameras: int, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, C, 3, 3) intrinsics and (B, C, 4, 4) cam_to_lidar of cameras evenly around the car at 1.5 m."""
    K = pinhole(height, width, width / 2 / math.tan(math.radians(60)))
    poses = np.stack([camera_pose(2 * math.pi * c / cameras, (0.0, 0.0, 1.5)) for c in range(cameras)])
    return (torch.tensor(K, dtype=torch.float32).expand(batch_size, cameras, 3, 3).clone(),
            torch.tensor(poses, dtype=torch.float32).expand(batch_size, cameras, 4, 4).clone())


def box_points(box: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points on the four vertical faces of a box row (x, y, z, w, l, h, yaw, ...)."""
    w, l, h = box[3:6]
    face = rng.integers(0, 4, count)
    t = rng.uniform(-0.5, 0.5, count)
    along_l = np.where(face < 2, t * l, np.where(face == 2, l / 2, -l / 2))
    along_w = np.where(face < 2, np.where(face == 0, w / 2, -w / 2), t * w)
    z = rng.uniform(-h / 2, h / 2, count)
    local = np.stack([along_l, along_w, z], axis=1)
    return local @ yaw_rotation(box[6]).T + box[:3]


def synthetic_batch(boxes: list[np.ndarray], labels: list[list[int]], attributes: list[list[int]], cameras: int = 2,
                    image_hw: tuple[int, int] = (32, 64), points_per_box: int = 150, ground_points: int = 600,
                    seed: int = 0) -> DetectionBatch:
    """Points on the boxes' sides and on the ground (z = -1.8), uniform random images and image features."""
    rng = np.random.default_rng(seed)
    batch_size = len(boxes)
    rows = []
    for b, sample_boxes in enumerate(boxes):
        xyz = [box_points(box, points_per_box, rng) for box in sample_boxes]
        ground = np.column_stack([rng.uniform(-15, 15, (ground_points, 2)), np.full(ground_points, -1.8)])
        xyz = np.concatenate(xyz + [ground])
        rows.append(np.column_stack([np.full(len(xyz), b), xyz, rng.uniform(0, 1, len(xyz)),
                                     rng.uniform(0, 0.5, len(xyz))]))
    intrinsics, cam_to_lidar = camera_rig(batch_size, cameras, *image_hw)
    generator = torch.Generator().manual_seed(seed)
    h, w = image_hw
    return DetectionBatch(points=torch.tensor(np.concatenate(rows), dtype=torch.float32),
                          images=torch.rand(batch_size, cameras, 3, *image_hw, generator=generator),
                          features_s8=torch.rand(batch_size, cameras, 40, h // 8, w // 8, generator=generator),
                          features_s16=torch.rand(batch_size, cameras, 112, h // 16, w // 16, generator=generator),
                          intrinsics=intrinsics, cam_to_lidar=cam_to_lidar,
                          boxes=[torch.tensor(np.asarray(bx), dtype=torch.float32).reshape(-1, 9) for bx in boxes],
                          labels=[torch.tensor(lb, dtype=torch.int64) for lb in labels],
                          attributes=[torch.tensor(at, dtype=torch.int64) for at in attributes],
                          tokens=[f"sample{b}" for b in range(batch_size)])


def wrap_angle(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


# --- targets ---------------------------------------------------------------------------------------------------


def test_target_encoding_round_trip() -> None:
    grid = BevGrid(25.6, 0.8).coarsened(2)  # 1.6 m cells, 32 x 32
    boxes = [np.array([[3.3, -7.1, -0.9, 1.9, 4.6, 1.7, 3.5, 2.0, -1.0],  # yaw beyond pi: wraps
                       [-12.05, 10.4, -1.2, 0.7, 0.8, 1.8, -3.0, 0.3, 0.2],
                       [20.0, 20.0, -1.5, 0.4, 0.4, 0.9, 0.2, 0.0, 0.0],
                       [-25.0, -25.59, -0.5, 2.5, 10.0, 3.5, 1.2, -5.0, 0.5],  # centre in the first cell
                       [30.0, 0.0, -1.0, 1.9, 4.6, 1.7, 0.0, 0.0, 0.0]]),  # outside the grid: dropped
             np.array([[0.0, 0.0, -1.0, 0.6, 1.7, 1.4, -1.5, 4.0, 3.0]])]  # on cell corner 0, 0
    labels = [[CLS["car"], CLS["pedestrian"], CLS["traffic_cone"], CLS["bus"], CLS["car"]], [CLS["bicycle"]]]
    attributes = [[ATTR["vehicle.moving"], ATTR["pedestrian.standing"], -1, ATTR["vehicle.parked"], -1],
                  [ATTR["cycle.with_rider"]]]
    targets = encode_targets([torch.tensor(b, dtype=torch.float32) for b in boxes],
                             [torch.tensor(x) for x in labels], [torch.tensor(x) for x in attributes], grid)
    assert targets.heatmap.shape == (2, 10, 32, 32)
    assert len(targets.indices) == 5 and targets.heatmap.eq(1).sum() == 5
    offsets = targets.regression[:, :2]
    assert bool(((offsets >= 0) & (offsets < 1)).all())

    # the targets, written as if predicted
    b, k, h, w = targets.heatmap.shape
    heat_logits = torch.logit(targets.heatmap.clamp(1e-6, 1 - 1e-6))
    regression = torch.zeros(b * h * w, 10)
    regression[targets.indices] = targets.regression
    attr_logits = torch.zeros(b * h * w, NUM_ATTRIBUTES)
    has = targets.attributes >= 0
    attr_logits[targets.indices[has], targets.attributes[has]] = 5.0
    not_pedestrian = targets.indices[targets.labels != CLS["pedestrian"]]
    attr_logits[not_pedestrian, ATTR["pedestrian.moving"]] = 8.0  # the highest logit, but invalid for the class
    as_maps = lambda x: x.view(b, h, w, -1).permute(0, 3, 1, 2)  # noqa: E731
    outputs = HeadOutputs(heat_logits, as_maps(regression), as_maps(attr_logits))
    decoded = decode_detections(outputs, grid, score_threshold=0.9, max_per_sample=50)

    for sample, (gt_boxes, gt_labels, gt_attrs) in enumerate(zip(boxes, labels, attributes)):
        in_grid = np.abs(gt_boxes[:, :2]).max(axis=1) < 25.6
        gt_boxes, gt_labels = gt_boxes[in_grid], np.asarray(gt_labels)[in_grid]
        gt_attrs = np.asarray(gt_attrs)[in_grid]
        det = decoded[sample]
        assert sorted(det.labels.tolist()) == sorted(gt_labels.tolist())
        for label, box, attr in zip(det.labels.numpy(), det.boxes.numpy(), det.attributes.numpy()):
            i = int(np.flatnonzero(gt_labels == label)[0])
            gt = gt_boxes[i]
            np.testing.assert_allclose(box[[0, 1, 2, 3, 4, 5, 7, 8]], gt[[0, 1, 2, 3, 4, 5, 7, 8]], atol=1e-4)
            assert abs(wrap_angle(box[6] - gt[6])) < 1e-5 and -np.pi <= box[6] <= np.pi
            if DETECTION_CLASSES[label] == "traffic_cone":
                assert attr == -1
            else:
                assert attr == gt_attrs[i]
    assert decoded[0].scores.min() > 0.99


def test_invalid_attribute_targets_are_dropped() -> None:
    mask = valid_attribute_mask()
    assert mask[CLS["car"]].tolist() == [a.startswith("vehicle.") for a in ATTRIBUTES]
    assert mask[CLS["bicycle"]].sum() == 2 and mask[CLS["barrier"]].sum() == 0
    targets = encode_targets([torch.tensor([[1.0, 1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]] * 2)],
                             [torch.tensor([CLS["car"], CLS["barrier"]])],
                             [torch.tensor([ATTR["pedestrian.moving"], ATTR["vehicle.parked"]])], BevGrid(8.0, 1.0))
    assert targets.attributes.tolist() == [-1, -1]


# --- LSS -------------------------------------------------------------------------------------------------------


def lss_camera() -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """One camera looking 30 deg left of LiDAR x, pitched 5 deg down, 1.6 m up; 64 x 96 image."""
    return pinhole(64, 96, 40.0), camera_pose(math.radians(30), (1.0, 0.5, 1.6), math.radians(5)), (64, 96)


def test_lss_puts_a_cells_depth_bin_where_the_lidar_point_of_that_depth_lies() -> None:
    """A point at the centre of depth bin i on the ray of feature cell (row, col): `project_into_cells` finds it
    there at its camera depth, the frustum point (row, col, i) is the point, and all the mass of a depth distribution
    one-hot in bin i lands in the point's BEV cell."""
    K, T, image_hw = lss_camera()
    feature_hw = (8, 12)
    depth = DepthBins(1.0, 41.0, 20)  # 2 m bins, centres 2, 4, ..., 40
    grid = BevGrid(25.6, 0.8)
    row, col, bin_index = 3, 7, 6
    d = 1.0 + (bin_index + 0.5) * 2.0
    pixel = np.array([col * 8 + 3.5, row * 8 + 3.5, 1.0])
    point = T[:3, :3] @ (d * np.linalg.solve(K, pixel)) + T[:3, 3]
    points = torch.tensor([[0.0, *point, 0.5, 0.0]], dtype=torch.float32)
    Kt, Tt = (torch.tensor(x, dtype=torch.float32)[None, None] for x in (K, T))

    flat, z = project_into_cells(points, Kt, Tt, image_hw, feature_hw, depth)
    assert flat.tolist() == [row * 12 + col] and float(z[0]) == pytest.approx(d, rel=1e-5)

    geometry = frustum_points(Kt, Tt, feature_hw, depth.centres())
    np.testing.assert_allclose(geometry[0, 0, bin_index, row, col].numpy(), point, atol=1e-4)
    depth_prob = torch.zeros(1, 1, 20, *feature_hw)
    depth_prob[0, 0, bin_index, row, col] = 1.0
    context = torch.full((1, 1, 3, 8, 12), 7.0)
    bev = lift_splat(depth_prob, context, geometry, grid, (-5.0, 3.0))
    assert bev.shape == (1, 3, 64, 64)
    expected_col, expected_row = np.floor((point[:2] + 25.6) / 0.8).astype(int)
    occupied = torch.nonzero(bev[0, 0]).tolist()
    assert occupied == [[expected_row, expected_col]]
    assert torch.allclose(bev[0, :, expected_row, expected_col], torch.full((3,), 7.0))


def point_at(K: np.ndarray, T: np.ndarray, row: int, col: int, depth_m: float) -> np.ndarray:
    """(3,) the LiDAR-frame point at camera depth ``depth_m`` on the ray through feature cell (row, col)'s centre."""
    pixel = np.array([col * 8 + 3.5, row * 8 + 3.5, 1.0])
    return T[:3, :3] @ (depth_m * np.linalg.solve(K, pixel)) + T[:3, 3]


@pytest.mark.parametrize("scale", [0.95, 1.05])
def test_depth_targets_keep_camera_depth_under_the_scale_augmentation(scale: float) -> None:
    """The augmentation maps points and ``cam_to_lidar`` by one similarity ``A`` (a scaled rotation): the camera
    depth of a point is unchanged. Inverting ``cam_to_lidar`` as if it were rigid gave ``scale**2 * z``."""
    K, T, image_hw = lss_camera()
    depth = DepthBins(1.0, 41.0, 40)  # 1 m bins
    row, col, d = 3, 7, 30.5
    A = np.eye(4)
    A[:3, :3] = scale * yaw_rotation(0.3)
    point = A[:3, :3] @ point_at(K, T, row, col, d)
    points = torch.tensor([[0.0, *point, 0.5, 0.0]], dtype=torch.float32)
    Kt, Tt = torch.tensor(K, dtype=torch.float32)[None, None], torch.tensor(A @ T, dtype=torch.float32)[None, None]
    flat, z = project_into_cells(points, Kt, Tt, image_hw, (8, 12), depth)
    assert flat.tolist() == [row * 12 + col] and float(z[0]) == pytest.approx(d, rel=1e-5)
    target = depth_targets(points, Kt, Tt, image_hw, (8, 12), depth)
    assert int(target[0, 0, row, col]) == int(depth.index_of(torch.tensor(d)))


def test_depth_targets_take_the_nearest_keyframe_point_of_each_cell() -> None:
    K, T, image_hw = lss_camera()
    depth = DepthBins(1.0, 41.0, 20)
    rows = [[0.0, *point_at(K, T, 3, 7, 20.0), 0.5, 0.0],  # keyframe, far
            [0.0, *point_at(K, T, 3, 7, 10.0), 0.5, 0.0],  # keyframe, near: the target
            [0.0, *point_at(K, T, 3, 7, 5.0), 0.5, 0.05],  # an earlier sweep: no target
            [0.0, *point_at(K, T, 5, 2, 5.0), 0.5, 0.05],
            [1.0, *point_at(K, T, 1, 1, 8.0), 0.5, 0.0]]  # the second sample's camera
    points = torch.tensor(rows, dtype=torch.float32)
    Kt = torch.tensor(K, dtype=torch.float32).expand(2, 1, 3, 3)
    Tt = torch.tensor(T, dtype=torch.float32).expand(2, 1, 4, 4)
    target = depth_targets(points, Kt, Tt, image_hw, (8, 12), depth)
    assert target.shape == (2, 1, 8, 12)
    assert int(target[0, 0, 3, 7]) == 4 and int(target[1, 0, 1, 1]) == 3  # bins [9, 11) and [7, 9)
    assert int((target >= 0).sum()) == 2


def test_depth_loss_is_zero_at_the_target_and_log_bins_when_uniform() -> None:
    target = torch.full((1, 2, 3, 4), -1, dtype=torch.long)
    target[0, 1, 2, 3], target[0, 0, 0, 0] = 5, 0
    one_hot = torch.zeros(1, 2, 8, 3, 4)
    one_hot[0, 1, 5, 2, 3] = one_hot[0, 0, 0, 0, 0] = 1.0
    assert float(depth_loss(one_hot, target)) == pytest.approx(0.0, abs=1e-6)
    assert float(depth_loss(torch.full((1, 2, 8, 3, 4), 1 / 8), target)) == pytest.approx(math.log(8), rel=1e-6)
    assert float(depth_loss(one_hot, torch.full_like(target, -1))) == 0.0


def test_camera_only_training_learns_depth_from_the_lidar() -> None:
    """Camera-only steps lower the depth loss: the depth net learns depth from the image features and rays."""
    torch.manual_seed(0)
    model = BEVFusionDetector(SMALL)
    batch = two_sample_batch()
    batch.points[:, 5] = 0.0  # all keyframe points
    optimizer = torch.optim.AdamW(model.parameters(), lr=4e-3)
    history = [train_step(model, batch, optimizer, modality="camera")["depth"] for _ in range(40)]
    assert history[-1] < 0.7 * history[0], (history[0], history[-1])


def test_lss_pooling_drops_outside_points_and_conserves_mass() -> None:
    K, T, image_hw = lss_camera()
    feature_hw = (8, 12)
    depth = DepthBins(1.0, 41.0, 20)
    grid = BevGrid(12.8, 0.8)  # far bins leave the grid
    z_range = (-2.0, 3.0)  # and the 5 deg downward pitch takes rays below -2 m
    generator = torch.Generator().manual_seed(0)
    depth_prob = torch.rand(2, 1, 20, *feature_hw, generator=generator).softmax(dim=2)
    context = torch.rand(2, 1, 4, *feature_hw, generator=generator)
    Kt = torch.tensor(K, dtype=torch.float32).expand(2, 1, 3, 3)
    Tt = torch.tensor(T, dtype=torch.float32).expand(2, 1, 4, 4)
    geometry = frustum_points(Kt, Tt, feature_hw, depth.centres())
    bev = lift_splat(depth_prob, context, geometry, grid, z_range).numpy()

    # independently: numpy frustum and np.add.at
    centres = 1.0 + (np.arange(20) + 0.5) * 2.0
    v, u = np.meshgrid(np.arange(8) * 8 + 3.5, np.arange(12) * 8 + 3.5, indexing="ij")
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # (h, w, 3)
    pts = centres[:, None, None, None] * rays[None] @ T[:3, :3].T + T[:3, 3]  # (D, h, w, 3)
    cells = np.floor((pts[..., :2] + 12.8) / 0.8).astype(int)
    in_grid = (cells >= 0).all(-1) & (cells < 32).all(-1)
    in_z = (pts[..., 2] >= -2.0) & (pts[..., 2] < 3.0)
    inside = in_grid & in_z
    assert 0.1 < inside.mean() < 0.9 and (in_grid & ~in_z).any() and (in_z & ~in_grid).any()
    expected = np.zeros((2, 4, 32, 32))
    features = depth_prob.numpy()[:, 0, :, None] * context.numpy()[:, 0, None]  # (B, D, F, h, w)
    for b in range(2):
        for f in range(4):
            np.add.at(expected[b, f], (cells[..., 1][inside], cells[..., 0][inside]), features[b, :, f][inside])
    np.testing.assert_allclose(bev, expected, rtol=1e-4, atol=1e-5)
    in_grid_mass = (features * inside[None, :, None]).sum(axis=(1, 3, 4))
    np.testing.assert_allclose(bev.sum(axis=(2, 3)), in_grid_mass, rtol=1e-5)
    assert in_grid_mass.sum() < features.sum() * 0.95


def test_depth_targets_ignore_points_behind_the_camera_and_respect_the_batch() -> None:
    K, T, image_hw = lss_camera()
    Kt = torch.tensor(K, dtype=torch.float32).expand(2, 1, 3, 3)
    Tt = torch.tensor(T, dtype=torch.float32).expand(2, 1, 4, 4)
    forward = T[:3, 2]
    in_view = T[:3, 3] + 10.0 * forward
    behind = T[:3, 3] - 10.0 * forward
    points = torch.tensor([[1.0, *in_view, 0, 0], [0.0, *behind, 0, 0]], dtype=torch.float32)
    target = depth_targets(points, Kt, Tt, image_hw, (8, 12), DepthBins(1.0, 41.0, 20))
    assert int((target[0] >= 0).sum()) == 0  # sample 0's only point is behind its camera
    assert int((target[1] >= 0).sum()) == 1 and int(target[1].max()) == 4  # 10 m: bin 4 of 2 m bins


def test_cell_rays_reproject_onto_the_cell_centres() -> None:
    K, _, _ = lss_camera()
    Kt = torch.tensor(K, dtype=torch.float32)[None, None]
    rays = cell_rays(Kt, (8, 12))
    assert rays.shape == (1, 1, 8, 12, 3) and torch.allclose(rays[..., 2], torch.ones(1, 1, 8, 12))
    pixels = torch.einsum("ij,hwj->hwi", Kt[0, 0], rays[0, 0])
    v, u = torch.meshgrid(torch.arange(8) * 8 + 3.5, torch.arange(12) * 8 + 3.5, indexing="ij")
    assert torch.allclose(pixels[..., 0], u, atol=1e-4) and torch.allclose(pixels[..., 1], v, atol=1e-4)


# --- pillars ---------------------------------------------------------------------------------------------------


def test_pillar_cells_and_max_scatter_respect_cells_and_batch() -> None:
    grid = BevGrid(4.0, 1.0)  # 8 x 8
    xyz = torch.tensor([[0.5, -3.5, 0.0],  # col 4, row 0
                        [0.9, -3.1, 1.0],  # same cell
                        [-4.0, 3.99, 0.0],  # col 0, row 7
                        [4.0, 0.0, 0.0],  # x = R: outside
                        [0.0, 0.0, 3.5]])  # above the z range
    batch_index = torch.tensor([0, 0, 1, 0, 1])
    flat = bev_cell_indices(xyz, batch_index, grid, (-5.0, 3.0))
    assert flat.tolist() == [0 * 64 + 0 * 8 + 4, 4, 64 + 7 * 8 + 0, -1, -1]
    features = torch.tensor([[1.0, 5.0], [3.0, 2.0], [4.0, 4.0], [9.0, 9.0], [9.0, 9.0]])
    bev = bev_max_pool(features, flat, 2, grid)
    assert bev.shape == (2, 2, 8, 8)
    assert bev[0, :, 0, 4].tolist() == [3.0, 5.0] and bev[1, :, 7, 0].tolist() == [4.0, 4.0]
    assert bev.sum() == 3 + 5 + 4 + 4


def test_pillar_encoder_fills_exactly_the_occupied_pillars() -> None:
    torch.manual_seed(0)
    grid = BevGrid(4.0, 1.0)
    encoder = PillarEncoder(grid, (-5.0, 3.0), channels=16).eval()
    points = torch.tensor([[0, 0.5, -3.5, 0.0, 0.2, 0.0], [0, 0.7, -3.3, -1.0, 0.9, 0.1], [1, -3.5, 3.5, 0.5, 0.4, 0.0],
                           [1, 2.2, 1.7, -2.0, 0.1, 0.3], [0, 9.0, 0.0, 0.0, 0.5, 0.0]])
    bev = encoder(points, batch_size=2)
    occupied = sorted(map(tuple, torch.nonzero(bev.abs().sum(dim=1)).tolist()))
    assert occupied == [(0, 0, 4), (1, 5, 6), (1, 7, 0)]
    flat = bev_cell_indices(points[:4, 1:4], points[:4, 0].long(), grid, (-5.0, 3.0))
    features = encoder.point_features(points[:4], flat, 2)
    # offsets to the pillar mean [cells]: the two points of pillar (0, 0, 4) sit symmetric around their mean
    np.testing.assert_allclose(features[0, 5:8].numpy(), [-0.1, -0.1, 0.5], atol=1e-6)
    np.testing.assert_allclose(features[2, 5:8].numpy(), [0.0, 0.0, 0.0], atol=1e-6)
    # offsets to the pillar centre [cells]
    np.testing.assert_allclose(features[3, 8:10].numpy(), [2.2 - 2.5, 1.7 - 1.5], atol=1e-6)


def test_sweep_statistics_equal_the_point_by_point_oracle() -> None:
    generator = torch.Generator().manual_seed(3)
    grid, z_range = BevGrid(4.0, 0.8), (-2.0, 2.0)
    n = 400
    xyz = (torch.rand(n, 3, generator=generator) * 2 - 1) * torch.tensor([5.0, 5.0, 2.5])
    lag = torch.randint(0, 5, (n,), generator=generator).float() * 0.05 + 0.004 * torch.rand(n, generator=generator)
    points = torch.cat([torch.randint(0, 2, (n, 1), generator=generator).float(), xyz, torch.rand(n, 1), lag[:, None]],
                       dim=1)
    flat = bev_cell_indices(points[:, 1:4], points[:, 0].long(), grid, z_range)
    keep = flat >= 0
    fast = sweep_statistics(points[keep], flat[keep], 2, grid, 3, 0.05)
    assert fast.shape == (2, 9, grid.size, grid.size)
    torch.testing.assert_close(fast, sweep_statistics_naive(points, 2, grid, z_range, 3, 0.05), atol=1e-5, rtol=1e-5)
    assert fast[:, 0::3].gt(0).sum() > 50  # the counts are there, and later sweeps (lag >= 0.15 s) are left out
    assert fast[:, 0::3].exp().sub(1).sum().round() == ((lag.round(decimals=2) < 0.125) & keep).sum()


def test_sweep_statistics_show_a_surface_moving_between_sweeps() -> None:
    """A wall of points moving +x at 4 m/s: sweep k (0.05 k s earlier) lies 0.2 k m behind; the mean offsets from
    the cell centre [cells] differ by 0.25 cells per sweep, while a static wall's do not."""
    grid = BevGrid(4.0, 0.8)
    ys = torch.linspace(-0.35, 0.35, 8)
    rows = []
    for k in range(3):
        for y in ys:
            rows.append([0, 0.4 + 0.3 - 0.2 * k, y + 0.4, 0.0, 0.5, 0.05 * k])  # moving, cell (col 5, row 5)
            rows.append([1, 0.4 + 0.1, y + 0.4, 0.0, 0.5, 0.05 * k])  # static
    points = torch.tensor(rows)
    flat = bev_cell_indices(points[:, 1:4], points[:, 0].long(), grid, (-5.0, 3.0))
    stats = sweep_statistics(points, flat, 2, grid, 3, 0.05)[:, :, 5, 5]
    torch.testing.assert_close(stats[0, 1::3], torch.tensor([0.375, 0.125, -0.125]))
    torch.testing.assert_close(stats[1, 1::3], torch.tensor([0.125, 0.125, 0.125]))
    torch.testing.assert_close(stats[:, 0::3], torch.full((2, 3), math.log(9.0)))


def test_pillar_encoder_appends_the_sweep_statistics() -> None:
    grid = BevGrid(4.0, 1.0)
    encoder = PillarEncoder(grid, (-5.0, 3.0), channels=16, motion_sweeps=3).eval()
    points = torch.tensor([[0, 0.5, -3.5, 0.0, 0.2, 0.0], [0, 0.7, -3.3, -1.0, 0.9, 0.05]])
    bev = encoder(points, batch_size=1)
    assert bev.shape == (1, encoder.out_channels, 8, 8) and encoder.out_channels == 16 + 9
    torch.testing.assert_close(bev[0, 16:, 0, 4], torch.tensor([math.log(2.0), 0.0, 0.0, math.log(2.0), 0.2, 0.2,
                                                                 0.0, 0.0, 0.0]))


def test_keyframe_only_pillars_take_earlier_sweeps_through_their_statistics_alone() -> None:
    torch.manual_seed(0)
    grid = BevGrid(4.0, 1.0)
    both = PillarEncoder(grid, (-5.0, 3.0), channels=16, motion_sweeps=3, keyframe_only=True).eval()
    every = PillarEncoder(grid, (-5.0, 3.0), channels=16, motion_sweeps=3, keyframe_only=False).eval()
    every.load_state_dict(both.state_dict())
    keyframe = torch.tensor([[0, 0.5, -3.5, 0.0, 0.2, 0.0], [0, 2.5, 1.5, -1.0, 0.9, 0.0]])
    earlier = torch.tensor([[0, 0.7, -3.3, -1.0, 0.9, 0.05], [0, -2.5, 2.5, 0.5, 0.4, 0.1]])
    alone, with_sweeps = both(keyframe, 1), both(torch.cat([keyframe, earlier]), 1)
    torch.testing.assert_close(with_sweeps[:, :16], alone[:, :16])  # the MLP and max see the keyframe only
    assert not torch.equal(with_sweeps[:, 16:], alone[:, 16:])  # the earlier sweeps' statistics are there
    assert with_sweeps[0, :16, 6, 1].abs().sum() == 0  # a pillar of earlier sweeps alone has no MLP feature
    assert not torch.equal(every(torch.cat([keyframe, earlier]), 1)[:, :16], alone[:, :16])


# --- the model -------------------------------------------------------------------------------------------------


def two_sample_batch(seed: int = 0) -> DetectionBatch:
    return synthetic_batch([np.array([[5.0, 3.0, -1.0, 1.9, 4.5, 1.6, 0.3, 1.0, 0.0]]),
                            np.array([[-6.0, -4.0, -0.9, 0.7, 0.7, 1.8, 0.0, 0.5, 0.5]])],
                           [[CLS["car"]], [CLS["pedestrian"]]], [[ATTR["vehicle.moving"]], [ATTR["pedestrian.moving"]]],
                           seed=seed)


def outputs_equal(a: HeadOutputs, b: HeadOutputs) -> bool:
    return all(torch.equal(x, y) for x, y in ((a.heatmap, b.heatmap), (a.regression, b.regression),
                                              (a.attributes, b.attributes)))


def test_modality_switches_each_branch_off() -> None:
    torch.manual_seed(0)
    model = BEVFusionDetector(SMALL).eval()
    batch = two_sample_batch()
    other_images = replace(batch, features_s8=torch.rand_like(batch.features_s8),
                           features_s16=torch.rand_like(batch.features_s16))
    shifted = batch.points.clone()
    shifted[:, 1] += 1.5
    other_points = replace(batch, points=shifted)
    with torch.no_grad():
        run = {m: (model(batch, m), model(other_images, m), model(other_points, m))
               for m in ("fused", "lidar", "camera")}
    assert outputs_equal(run["lidar"][0], run["lidar"][1]) and not outputs_equal(run["lidar"][0], run["lidar"][2])
    assert outputs_equal(run["camera"][0], run["camera"][2]) and not outputs_equal(run["camera"][0], run["camera"][1])
    assert not outputs_equal(run["fused"][0], run["fused"][1]) and not outputs_equal(run["fused"][0], run["fused"][2])
    with pytest.raises(ValueError):
        model(batch, "radar")


def test_the_auxiliary_pass_is_the_camera_only_model_and_adds_its_loss() -> None:
    """In training, fused outputs carry ``camera_only``: exactly what the model gives with modality "camera" (no
    LiDAR anywhere in it), and its loss is part of the total. Evaluation and single-modality passes have none."""
    torch.manual_seed(0)
    model = BEVFusionDetector(SMALL).train()
    batch = two_sample_batch()
    with torch.no_grad():
        outputs = model(batch)
        camera = model(batch, "camera")
        assert outputs.camera_only is not None and camera.camera_only is None
        assert all(torch.allclose(x, y, atol=1e-5) for x, y in (
            (outputs.camera_only.heatmap, camera.heatmap), (outputs.camera_only.regression, camera.regression),
            (outputs.camera_only.attributes, camera.attributes)))
        assert not outputs_equal(outputs, camera)
        losses = model.loss(batch, outputs)
        alone = model.loss(batch, camera)
        assert float(losses["camera_only"]) == pytest.approx(float(alone["total"] - alone["depth"]), rel=1e-5)
        parts = (losses["heatmap"] + 0.25 * (losses["offset"] + losses["z"] + losses["size"] + losses["yaw"]
                                              + 0.2 * losses["velocity"]) + 0.2 * losses["attribute"])
        assert float(losses["total"]) == pytest.approx(float(parts + losses["camera_only"] + losses["depth"]),
                                                       rel=1e-5)
        assert model.eval()(batch).camera_only is None
    without = BEVFusionDetector(replace(SMALL, camera_only_loss=False)).train()
    assert without(batch).camera_only is None


def test_an_evaluation_during_training_leaves_the_training_unchanged() -> None:
    """`protocol.train` runs ``on_step`` (the learning curve's evaluations) under a fork of the random generators:
    random draws there (a data loader's base seed, say) must not change the trained weights."""
    from weatheralign.detect import protocol

    batch = two_sample_batch()
    samples = [{"points": batch.points[batch.points[:, 0] == b, 1:], "images": (batch.images[b] * 255).to(torch.uint8),
                "features_s8": batch.features_s8[b].half(), "features_s16": batch.features_s16[b].half(),
                "intrinsics": batch.intrinsics[b], "cam_to_lidar": batch.cam_to_lidar[b], "boxes": batch.boxes[b],
                "labels": batch.labels[b], "attributes": batch.attributes[b], "token": batch.tokens[b],
                "T_global_lidar": torch.eye(4, dtype=torch.float64)} for b in range(2)]

    def trained(on_step) -> dict[str, torch.Tensor]:
        torch.manual_seed(0)
        model = BEVFusionDetector(replace(SMALL, modality_dropout=0.5))
        protocol.train(model, samples, 4, 1e-3, 0.01, 1, 0, torch.device("cpu"), show_progress=False,
                       on_step=on_step)
        return model.state_dict()

    quiet, drawing = trained(None), trained(lambda step, record: torch.rand(100))
    assert all(torch.equal(quiet[k], drawing[k]) for k in quiet)
    assert not all(torch.equal(quiet[k], v) for k, v in BEVFusionDetector(SMALL).state_dict().items())


def test_modality_dropout_drops_one_branch_per_sample_in_training_only() -> None:
    torch.manual_seed(0)
    lidar, camera = modality_masks("fused", 1000, 1.0, True, "cpu")
    assert bool((lidar ^ camera).all()) and 400 < int(lidar.sum()) < 600
    lidar, camera = modality_masks("fused", 1000, 0.3, True, "cpu")
    assert 200 < int((~(lidar & camera)).sum()) < 400 and bool((lidar | camera).all())
    lidar, camera = modality_masks("fused", 1000, 1.0, True, "cpu", lidar_drop_share=0.8)
    assert 720 < int((~lidar).sum()) < 880 and bool((lidar ^ camera).all())
    lidar, camera = modality_masks("fused", 10, 1.0, False, "cpu")
    assert bool(lidar.all() and camera.all())
    lidar, camera = modality_masks("camera", 10, 1.0, True, "cpu")
    assert not bool(lidar.any()) and bool(camera.all())


def test_default_model_size_and_output_shapes() -> None:
    model = BEVFusionDetector()
    assert 0.4e6 < count_parameters(model) < 1.5e6
    batch = synthetic_batch([np.zeros((0, 9))], [[]], [[]], cameras=6, image_hw=(128, 352))
    with torch.no_grad():
        outputs = model.eval()(batch)
    assert outputs.heatmap.shape == (1, 10, 64, 64) and outputs.regression.shape == (1, 10, 64, 64)
    assert outputs.attributes.shape == (1, 8, 64, 64)
    losses = model.loss(batch, outputs)  # no objects: finite, heatmap only
    assert all(torch.isfinite(v) for v in losses.values()) and float(losses["offset"]) == 0.0


def test_overfits_one_small_batch_and_decodes_its_boxes() -> None:
    torch.manual_seed(0)
    boxes = [np.array([[5.0, 3.0, -1.0, 1.9, 4.5, 1.6, 0.3, 1.0, 0.0],
                       [-6.0, -4.0, -0.9, 0.7, 0.7, 1.8, 2.0, 0.5, 0.5],
                       [2.0, -9.0, -1.3, 2.5, 0.5, 1.0, -1.2, 0.0, 0.0]])]
    labels = [[CLS["car"], CLS["pedestrian"], CLS["barrier"]]]
    attributes = [[ATTR["vehicle.moving"], ATTR["pedestrian.moving"], -1]]
    batch = synthetic_batch(boxes, labels, attributes)
    batch = replace(batch, images=torch.zeros_like(batch.images), features_s8=torch.zeros_like(batch.features_s8),
                    features_s16=torch.zeros_like(batch.features_s16))  # blank images
    model = BEVFusionDetector(SMALL)
    optimizer = torch.optim.AdamW(model.parameters(), lr=4e-3, weight_decay=0.0)
    history = [train_step(model, batch, optimizer) for _ in range(150)]  # ~45 ms each on 2 idle CPU threads
    first, last = history[0]["total"], np.mean([h["total"] for h in history[-5:]])
    assert last < first / 10, (first, last)

    (detections,) = model.detect(batch, score_threshold=0.3, max_per_sample=20)
    assert isinstance(detections, SampleDetections) and detections.boxes.dtype == np.float64
    assert len(detections.scores) == 3, detections.scores
    for gt, label, attribute in zip(boxes[0], labels[0], attributes[0]):
        match = np.flatnonzero(detections.labels == label)
        assert len(match) == 1, (DETECTION_CLASSES[label], detections.labels)
        box = detections.boxes[match[0]]
        assert np.linalg.norm(box[:2] - gt[:2]) < 0.5
        np.testing.assert_allclose(box[3:6], gt[3:6], rtol=0.3)
        assert abs(wrap_angle(box[6] - gt[6])) < 0.2
        assert detections.attributes[match[0]] == attribute


def test_training_steps_handle_empty_clouds() -> None:
    torch.manual_seed(0)
    model = BEVFusionDetector(replace(SMALL, modality_dropout=0.5))
    batch = two_sample_batch()
    empty = replace(batch, points=batch.points[:0])
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    history = [train_step(model, b, optimizer) for b in (batch, empty, batch)]
    assert all(math.isfinite(h["total"]) for h in history)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_forward_backward_on_cuda() -> None:
    device = torch.device("cuda")
    model = BEVFusionDetector(SMALL).to(device)
    batch = two_sample_batch().to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    record = train_step(model, batch, optimizer)
    assert math.isfinite(record["total"])
    detections = model.detect(batch, score_threshold=0.0, max_per_sample=5)
    assert len(detections) == 2 and detections[0].boxes.shape == (5, 9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_forward_equals_cpu() -> None:
    """The GPU path computes the CPU model: the same weights and batch give the same head maps (TF32 off) in eval mode
    and after one identical training step on each device."""
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    torch.manual_seed(0)
    cpu_model = BEVFusionDetector(SMALL)
    gpu_model = BEVFusionDetector(SMALL)
    gpu_model.load_state_dict(cpu_model.state_dict())
    gpu_model = gpu_model.to("cuda")
    batch = two_sample_batch()
    for model in (cpu_model, gpu_model):
        model.eval()
    with torch.no_grad():
        a, b = cpu_model(batch), gpu_model(batch.to(torch.device("cuda")))
    for name in ("heatmap", "regression", "attributes"):
        torch.testing.assert_close(getattr(b, name).cpu(), getattr(a, name), rtol=1e-4, atol=1e-4)
    for model in (cpu_model, gpu_model):
        model.train()
    losses = []
    for model, device in ((cpu_model, torch.device("cpu")), (gpu_model, torch.device("cuda"))):
        optimizer = torch.optim.SGD(model.parameters(), lr=1e-3)
        torch.manual_seed(1)  # the same modality-dropout draws on both devices
        losses.append(train_step(model, batch.to(device), optimizer)["total"])
    assert losses[0] == pytest.approx(losses[1], rel=1e-4)


def _training_samples() -> list[dict]:
    batch = two_sample_batch()
    return [{"points": batch.points[batch.points[:, 0] == b, 1:], "images": (batch.images[b] * 255).to(torch.uint8),
             "features_s8": batch.features_s8[b].half(), "features_s16": batch.features_s16[b].half(),
             "intrinsics": batch.intrinsics[b], "cam_to_lidar": batch.cam_to_lidar[b], "boxes": batch.boxes[b],
             "labels": batch.labels[b], "attributes": batch.attributes[b], "token": batch.tokens[b],
             "T_global_lidar": torch.eye(4, dtype=torch.float64)} for b in range(2)]


def test_an_interrupted_training_resumes_to_the_same_weights(tmp_path) -> None:
    """Stopped after step 5 (its state saved at step 4), the training continues from step 4 and ends with the
    weights and losses of an uninterrupted run; the state file is removed at the end."""
    from weatheralign.detect import protocol

    samples = _training_samples()
    config = replace(SMALL, modality_dropout=0.5)

    def trained(resume, on_step=None) -> tuple[dict[str, torch.Tensor], list[dict[str, float]]]:
        torch.manual_seed(0)
        model = BEVFusionDetector(config)
        history = protocol.train(model, samples, 8, 1e-3, 0.01, 1, 0, torch.device("cpu"), show_progress=False,
                                 on_step=on_step, resume=resume)
        return model.state_dict(), history

    reference, reference_history = trained(None)

    def stop_at_5(step: int, record: dict[str, float]) -> None:
        if step == 5:
            raise KeyboardInterrupt

    resume = protocol.Resume(tmp_path / "model.state.pt", "fingerprint-1", every=2)
    with pytest.raises(KeyboardInterrupt):
        trained(resume, stop_at_5)
    assert resume.path.is_file()
    assert torch.load(resume.path, weights_only=True)["step"] == 4
    resumed, history = trained(resume)
    assert [h["total"] for h in history] == [h["total"] for h in reference_history]
    assert all(torch.equal(resumed[k], v) for k, v in reference.items())
    assert not resume.path.exists()
    other = protocol.Resume(tmp_path / "model.state.pt", "fingerprint-1", every=2)
    with pytest.raises(KeyboardInterrupt):
        trained(other, stop_at_5)
    fresh, _ = trained(protocol.Resume(other.path, "another fingerprint", every=2))  # a stale state is ignored
    assert all(torch.equal(fresh[k], v) for k, v in reference.items())


class _RunsCode:
    """Unpickling this runs a shell command (what a crafted checkpoint would do)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


def test_a_crafted_checkpoint_cannot_run_code(tmp_path) -> None:
    """Checkpoints and training states are read as tensors and plain data only: a file whose pickle would run a
    command is refused and the command never runs."""
    import pickle

    from weatheralign.detect import protocol

    marker = tmp_path / "ran"
    crafted = tmp_path / "pretrained.pt"
    torch.save({"state_dict": BEVFusionDetector(SMALL).state_dict(), "meta": _RunsCode(str(marker))}, crafted)
    with pytest.raises(pickle.UnpicklingError):
        protocol.load_checkpoint(crafted, SMALL)
    state = tmp_path / "model.state.pt"
    torch.save({"key": "k", "history": _RunsCode(str(marker))}, state)
    with pytest.raises(pickle.UnpicklingError):
        protocol.train(BEVFusionDetector(SMALL), _training_samples(), 2, 1e-3, 0.0, 1, 0, torch.device("cpu"),
                       show_progress=False, resume=protocol.Resume(state, "k"))
    assert not marker.exists()
