"""A small BEVFusion-style (Liu et al. 2023, MIT) LiDAR-camera 3-D detector in plain PyTorch, trainable on CPU.

Structure (every step runs on whatever device the model and batch are on; no custom operators):

1. LiDAR branch (`LidarBranch`): PointPillars-style pillar encoder on the BEV grid (`DetectorConfig.bev_grid`, default
   [-51.2, 51.2) m, 0.8 m cells -> 128 x 128): per keyframe point (``pillar_keyframe_only``; else every point) x, y,
   z, intensity, time lag, offsets to the pillar's mean and to the pillar's centre -> Linear + BN + ReLU -> max per
   pillar (``scatter_reduce(amax)``); beside them, per
   sweep (``motion_sweeps``) and cell the point count and the mean offset from the cell's centre
   (`sweep_statistics`): a max over a pillar's points cannot compare where a surface was in one sweep with where it
   was in another, the displacement that velocity and a symmetric box's heading rest on -> two conv blocks, the
   first at stride 2 -> (B, bev_channels, 64, 64).
2. Camera branch (`CameraBranch`, BEVDepth's LSS with LiDAR-supervised depth): frozen ImageNet features of each
   camera (`weatheralign.detect.image_features`, cached with the data) at strides 8 and 16 -> a trained FPN neck at
   stride 8; the depth net sees these features and each cell's ray direction in its camera (``K^-1 (u, v, 1)``: the
   cameras differ in focal length, and a ground point's depth follows from its ray) -> per cell a softmax over D
   depth bins and context features; the depth distributions are supervised by the nearest keyframe LiDAR point of
   each cell (`depth_loss`); frustum points (u, v, d) unprojected into the LiDAR frame; depth prob x context
   sum-pooled into the BEV grid with ``index_add_`` (points outside the grid or the z range dropped); a stride-2 conv
   block -> (B, bev_channels, 64, 64). The camera branch never sees the LiDAR's points (BEVFusion's projected-depth
   input is left out), so its BEV is the same whether the LiDAR is there or not.
3. `ConvFuser`: concat(camera BEV, LiDAR BEV) -> 3x3 conv + GroupNorm + ReLU. ``modality`` ("fused" | "lidar" |
   "camera") zeroes the other branch; in training, ``modality_dropout`` zeroes one branch of a sample with that
   probability, and with ``camera_only_loss`` every sample also goes through the fuser, encoder and head a second
   time with its LiDAR BEV zeroed, whose loss is added (an auxiliary camera-only pass: the camera learns to detect on
   its own on every sample, not only on the few a dropout makes camera-only). From here on the normalisation is per
   sample (GroupNorm), so a camera-only or LiDAR-only sample is normalised alike in mixed training batches and in a
   single-modality evaluation.
4. `BevEncoder`: two scales (stride 2 and 4 of the BEV grid), each brought to the head's stride and concatenated.
5. `CenterHead` (`weatheralign.detect.head`): CenterPoint heatmap + box regression + attribute logits at stride
   ``head_stride`` of the BEV grid (default 2: 1.6 m cells, 64 x 64). With ``position_channels`` the head also sees
   each cell's x, y (`position_map`), as the queries of BEVFusion's TransFusion head carry their BEV position.
6. Velocities (`with_sweep_motion`, ``sweep_velocity``): the head's velocity regression barely learns from a tenth
   of a second of sweeps on 0.8 m cells, so `detect` measures each detection's speed by scan matching its points
   across the sweeps (`weatheralign.detect.sweep_motion`) and turns around the boxes that move backwards; the
   static classes keep the head's output.

The training augmentation maps points, boxes and ``cam_to_lidar`` by one similarity (a scaled rotation and flips):
``cam_to_lidar`` is then not rigid, and the LiDAR -> camera map is its full inverse (`lidar_to_camera`), so a point
keeps its camera depth. Speeds are measured by ``benchmarks/bench_detect.py`` (``reports/benchmarks/detect.json``).

Depths of the camera branch are camera z [m] (not ray lengths); depth bin i covers
``[depth_min + i * step, depth_min + (i + 1) * step)`` and its frustum points lie at the bin's centre. Image pixel
centres are at integer (u, v) (OpenCV); feature cell (row, col) at stride s covers pixels ``[s col, s col + s)`` and
its rays go through pixel ``(s col + (s - 1) / 2, s row + (s - 1) / 2)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from weatheralign.detect.head import (
    BevGrid,
    CenterHead,
    HeadOutputs,
    LossWeights,
    center_head_loss,
    conv_bn_relu,
    conv_gn_relu,
    decode_detections,
    encode_targets,
)
from weatheralign.detect.image_features import STRIDE8_CHANNELS, STRIDE16_CHANNELS
from weatheralign.detect.sweep_motion import SweepMatching, apply_sweep_motion, sweep_velocities
from weatheralign.detect.types import DETECTION_CLASSES, DetectionBatch, SampleDetections

Modality = Literal["fused", "lidar", "camera"]
MODALITIES: tuple[str, ...] = ("fused", "lidar", "camera")
IMAGE_STRIDE = 8
RAY_CHANNELS = 2  # the depth net's ray input: x / z and y / z of each cell's ray in its camera
SWEEP_STATISTICS = 3  # per sweep and BEV cell: log(1 + points), mean x and y offset from the cell's centre [cells]
STATIC_CLASSES: tuple[str, ...] = ("traffic_cone", "barrier")
"""Classes that do not move (nuScenes scores no velocity for them): they keep the head's velocity and heading."""
STATIC_CLASS_INDICES: tuple[int, ...] = tuple(DETECTION_CLASSES.index(name) for name in STATIC_CLASSES)
PILLAR_POINT_FEATURES = 10  # x, y, z, intensity, time lag, 3 offsets to the pillar mean, 2 offsets to its centre


@dataclass(frozen=True)
class DetectorConfig:
    """Sizes of the detector. Lengths in metres; ``head_stride`` (1 or 2) is relative to the BEV grid's cells."""

    bev_range_m: float = 51.2
    bev_cell_m: float = 0.8
    z_range_m: tuple[float, float] = (-5.0, 3.0)
    pillar_channels: int = 32
    #: sweeps whose per-cell statistics (`sweep_statistics`) join the pillar features, so that the convolutions see
    #: how a surface moved between sweeps (velocity and heading); 0: none
    motion_sweeps: int = 3
    #: the LiDAR's sweep period [s] (nuScenes: 20 Hz), which maps a point's time lag to its sweep index
    sweep_period_s: float = 0.05
    #: the pillar features (the per-point MLP and the max per pillar) from the keyframe's points alone; the earlier
    #: sweeps reach the detector through their `sweep_statistics` (a third of the points through the MLP)
    pillar_keyframe_only: bool = True
    image_channels: int = 64
    depth_min_m: float = 1.0
    depth_max_m: float = 60.0
    depth_bins: int = 48
    camera_context_channels: int = 32
    bev_channels: int = 64
    head_stride: int = 2
    head_channels: int = 64
    #: the head also sees each cell's position (x, y in [-1, 1] of the BEV range), as TransFusion's queries do
    position_channels: bool = True
    #: detections' velocities (and the direction of movers) from scan matching the sweeps
    #: (`weatheralign.detect.sweep_motion`), except for the static classes; False: the head's regression
    sweep_velocity: bool = True
    #: training only: probability that a sample loses one branch (the LiDAR with probability ``lidar_drop_share``,
    #: else the camera)
    modality_dropout: float = 0.2
    #: training only: the share of the dropped samples that lose the LiDAR (camera-only samples)
    lidar_drop_share: float = 0.0
    #: training only: add the loss of an auxiliary camera-only pass of every sample (see the module docstring)
    camera_only_loss: bool = True
    #: weight of the camera depth loss (BEVDepth's LiDAR-supervised depth bins) in the total loss
    depth_loss_weight: float = 1.0
    min_radius: int = 2
    gaussian_overlap: float = 0.1
    loss_weights: LossWeights = field(default_factory=LossWeights)

    def __post_init__(self) -> None:
        if self.head_stride not in (1, 2):
            raise ValueError(f"head_stride must be 1 or 2, got {self.head_stride}")
        if not 0.0 <= self.modality_dropout <= 1.0:
            raise ValueError(f"modality_dropout must be a probability, got {self.modality_dropout}")
        self.bev_grid  # validates range / cell

    @property
    def bev_grid(self) -> BevGrid:
        return BevGrid(self.bev_range_m, self.bev_cell_m)

    @property
    def head_grid(self) -> BevGrid:
        return self.bev_grid.coarsened(self.head_stride)

    @property
    def depth(self) -> DepthBins:
        return DepthBins(self.depth_min_m, self.depth_max_m, self.depth_bins)


@dataclass(frozen=True)
class DepthBins:
    """``count`` uniform camera-depth bins over ``[min_m, max_m)``."""

    min_m: float
    max_m: float
    count: int

    @property
    def step_m(self) -> float:
        return (self.max_m - self.min_m) / self.count

    def centres(self, device: torch.device | str | None = None) -> Tensor:
        """(count,) bin centres [m]."""
        return self.min_m + (torch.arange(self.count, device=device, dtype=torch.float32) + 0.5) * self.step_m

    def index_of(self, depth: Tensor) -> Tensor:
        """Bin index (int64, same shape) of depths [m]; only meaningful inside ``[min_m, max_m)``."""
        return torch.floor((depth - self.min_m) / self.step_m).long().clamp(0, self.count - 1)


# --- geometry ----------------------------------------------------------------------------------------------------


def bev_cell_indices(xyz: Tensor, batch_index: Tensor, grid: BevGrid, z_range_m: tuple[float, float]) -> Tensor:
    """Flat BEV cell indices ``b * H * W + row * W + col`` (int64, shape of ``batch_index``) of points ``xyz`` (..., 3)
    [m] in the LiDAR frame; -1 for points outside the grid or outside ``[z_min, z_max)``."""
    cells = grid.cell_of(xyz[..., :2])
    inside = grid.contains(cells) & (xyz[..., 2] >= z_range_m[0]) & (xyz[..., 2] < z_range_m[1])
    size = grid.size
    flat = batch_index * (size * size) + cells[..., 1] * size + cells[..., 0]
    return torch.where(inside, flat, torch.full_like(flat, -1))


def bev_sum_pool(features: Tensor, flat_cells: Tensor, batch_size: int, grid: BevGrid) -> Tensor:
    """Sum of (N, F) ``features`` per flat cell index (N,) (-1: dropped) with ``index_add_`` -> (B, F, H, W)."""
    size = grid.size
    dump = batch_size * size * size
    index = torch.where(flat_cells >= 0, flat_cells, torch.full_like(flat_cells, dump))
    pooled = features.new_zeros(dump + 1, features.shape[1]).index_add_(0, index, features)
    return pooled[:dump].view(batch_size, size, size, -1).permute(0, 3, 1, 2).contiguous()


def bev_max_pool(features: Tensor, flat_cells: Tensor, batch_size: int, grid: BevGrid) -> Tensor:
    """Max of non-negative (N, F) ``features`` per flat cell index (N,) (-1: dropped) with ``scatter_reduce(amax)``
    -> (B, F, H, W); empty cells are 0."""
    size = grid.size
    dump = batch_size * size * size
    index = torch.where(flat_cells >= 0, flat_cells, torch.full_like(flat_cells, dump))
    pooled = features.new_zeros(dump + 1, features.shape[1])
    pooled = pooled.scatter_reduce(0, index[:, None].expand_as(features), features, reduce="amax", include_self=True)
    return pooled[:dump].view(batch_size, size, size, -1).permute(0, 3, 1, 2).contiguous()


def cell_centres(flat_cells: Tensor, grid: BevGrid, dtype: torch.dtype) -> Tensor:
    """(P, 2) x, y [m] in the LiDAR frame of the centres of flat cell indices (P,) >= 0 (`bev_cell_indices`)."""
    cell = flat_cells % (grid.size * grid.size)
    return (torch.stack([cell % grid.size, cell // grid.size], dim=1).to(dtype) + 0.5) * grid.cell_m - grid.range_m


def sweep_statistics(points: Tensor, flat_cells: Tensor, batch_size: int, grid: BevGrid, sweeps: int,
                     sweep_period_s: float) -> Tensor:
    """Per sweep and BEV cell: ``log(1 + count)`` and the mean x and y offset of the sweep's points from the cell's
    centre [cells, in [-0.5, 0.5]], 0 in empty cells -> (B, SWEEP_STATISTICS * sweeps, H, W), sweep-major.

    Args:
        points: (P, 6) ``batch index, x, y, z [m], intensity, time lag [s]`` of in-grid points.
        flat_cells: (P,) their flat cell indices (`bev_cell_indices`, all >= 0).
        sweeps: sweeps kept; a point's sweep is ``round(lag / sweep_period_s)``, later sweeps dropped.
    """
    size = grid.size
    num_cells = batch_size * size * size
    sweep = torch.round(points[:, 5] / sweep_period_s).long()
    keep = (sweep >= 0) & (sweep < sweeps)
    sweep, cells, xy = sweep[keep], flat_cells[keep], points[keep, 1:3]
    index = sweep * num_cells + cells
    counts = xy.new_zeros(sweeps * num_cells).index_add_(0, index, torch.ones_like(xy[:, 0]))
    offsets = xy.new_zeros(sweeps * num_cells, 2).index_add_(0, index,
                                                             (xy - cell_centres(cells, grid, xy.dtype)) / grid.cell_m)
    mean = offsets / counts.clamp_min(1.0)[:, None]
    stats = torch.cat([torch.log1p(counts)[:, None], mean], dim=1)  # (S * B * H * W, 3)
    return stats.view(sweeps, batch_size, size, size, SWEEP_STATISTICS).permute(1, 0, 4, 2, 3).reshape(
        batch_size, sweeps * SWEEP_STATISTICS, size, size)


def sweep_statistics_naive(points: Tensor, batch_size: int, grid: BevGrid, z_range_m: tuple[float, float],
                           sweeps: int, sweep_period_s: float) -> Tensor:
    """`sweep_statistics` point by point (the test oracle): (P, 6) points -> (B, 3 * sweeps, H, W)."""
    size = grid.size
    out = torch.zeros(batch_size, sweeps * SWEEP_STATISTICS, size, size, dtype=torch.float64)
    count = torch.zeros(batch_size, sweeps, size, size, dtype=torch.float64)
    for b, x, y, z, _, lag in points.double().tolist():
        col, row = int((x + grid.range_m) // grid.cell_m), int((y + grid.range_m) // grid.cell_m)
        k = round(lag / sweep_period_s)
        if not (0 <= col < size and 0 <= row < size and z_range_m[0] <= z < z_range_m[1] and 0 <= k < sweeps):
            continue
        count[int(b), k, row, col] += 1
        out[int(b), 3 * k + 1, row, col] += (x + grid.range_m) / grid.cell_m - col - 0.5
        out[int(b), 3 * k + 2, row, col] += (y + grid.range_m) / grid.cell_m - row - 0.5
    for k in range(sweeps):
        out[:, 3 * k + 1:3 * k + 3] /= count[:, k:k + 1].clamp_min(1.0)
        out[:, 3 * k] = torch.log1p(count[:, k])
    return out.float()


def lidar_to_camera(cam_to_lidar: Tensor) -> Tensor:
    """(..., 4, 4) camera -> LiDAR transforms -> (..., 3, 4) the top rows of their inverses (LiDAR -> camera).

    The transforms need not be rigid: the training augmentation left-multiplies a scaled rotation (and a flip), and
    the inverse undoes exactly that, so a point keeps its camera depth whatever the augmentation's scale."""
    return torch.linalg.inv(cam_to_lidar.double())[..., :3, :].to(cam_to_lidar.dtype)


def project_points(xyz: Tensor, intrinsics: Tensor, cam_to_lidar: Tensor) -> Tensor:
    """Points (P, 3) [m] in one sample's LiDAR frame into each of its C cameras (intrinsics (C, 3, 3), camera ->
    LiDAR (C, 4, 4)): (P, C, 3) homogeneous image coordinates (u z, v z, camera depth z [m])."""
    projection = intrinsics.float() @ lidar_to_camera(cam_to_lidar.float())  # (C, 3, 4)
    homogeneous = torch.cat([xyz, torch.ones_like(xyz[:, :1])], dim=1)
    return (homogeneous @ projection.reshape(-1, 4).T).view(len(xyz), len(intrinsics), 3)


def project_into_cells(points: Tensor, intrinsics: Tensor, cam_to_lidar: Tensor, image_hw: tuple[int, int],
                       feature_hw: tuple[int, int], depth: DepthBins) -> tuple[Tensor, Tensor]:
    """Where points (P, 6) as in `DetectionBatch` fall in the image-feature cells of their own sample's C cameras:
    (flat cell indices ``((b * C + c) * h + row) * w + col`` (Q,) int64, camera depths z (Q,) [m]) of the (point,
    camera) pairs inside the image and the depth range (a point lies in front of one or two of six cameras). The image
    is ``image_hw`` pixels, the feature map ``feature_hw`` cells of `IMAGE_STRIDE` pixels."""
    cameras = intrinsics.shape[1]
    (height, width), (h, w) = image_hw, feature_hw
    batch_index = points[:, 0].long()
    flats, depths = [], []
    for sample in range(intrinsics.shape[0]):
        rows = torch.nonzero(batch_index == sample).squeeze(1)
        projected = project_points(points[rows, 1:4].float(), intrinsics[sample], cam_to_lidar[sample])
        z = projected[..., 2]
        point, camera = torch.nonzero((z >= depth.min_m) & (z < depth.max_m), as_tuple=True)
        projected = projected[point, camera]
        z = projected[:, 2]
        u, v = projected[:, 0] / z, projected[:, 1] / z
        valid = (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
        u, v, z, camera = u[valid], v[valid], z[valid], camera[valid]
        col = torch.floor((u + 0.5) / IMAGE_STRIDE).long().clamp(0, w - 1)
        row = torch.floor((v + 0.5) / IMAGE_STRIDE).long().clamp(0, h - 1)
        flats.append(((sample * cameras + camera) * h + row) * w + col)
        depths.append(z)
    if not flats:
        return torch.zeros(0, dtype=torch.long, device=points.device), torch.zeros(0, device=points.device)
    return torch.cat(flats), torch.cat(depths)


def depth_targets(points: Tensor, intrinsics: Tensor, cam_to_lidar: Tensor, image_hw: tuple[int, int],
                  feature_hw: tuple[int, int], depth: DepthBins) -> Tensor:
    """BEVDepth's depth supervision: per image-feature cell the depth bin of the nearest keyframe point (time lag
    0) projected into it, -1 where none: (B, C, h, w) int64. Earlier sweeps are left out: moving objects smear."""
    batch_size, cameras = intrinsics.shape[:2]
    h, w = feature_hw
    with torch.no_grad():
        keyframe = points[points[:, 5] == 0]
        flat, z = project_into_cells(keyframe, intrinsics, cam_to_lidar, image_hw, feature_hw, depth)
        nearest = torch.full((batch_size * cameras * h * w,), float("inf"), device=points.device)
        nearest = nearest.scatter_reduce(0, flat, z, reduce="amin", include_self=True)
        target = torch.full(nearest.shape, -1, dtype=torch.long, device=points.device)
        found = torch.isfinite(nearest)
        target[found] = depth.index_of(nearest[found])
        return target.view(batch_size, cameras, h, w)


def depth_loss(depth_prob: Tensor, target: Tensor) -> Tensor:
    """Mean negative log-likelihood of the target bins (B, C, h, w) (-1: no target) under the depth distributions
    (B, C, D, h, w); 0 when no cell has a target."""
    valid = target >= 0
    if not bool(valid.any()):
        return depth_prob.sum() * 0.0
    picked = depth_prob.gather(2, target.clamp_min(0).unsqueeze(2)).squeeze(2)
    return -(picked[valid].clamp_min(1e-6).log()).mean()


def cell_rays(intrinsics: Tensor, feature_hw: tuple[int, int]) -> Tensor:
    """Rays through the centre pixel of each image-feature cell in camera coordinates, at camera depth z = 1:
    intrinsics (B, C, 3, 3) -> (B, C, h, w, 3) ``K^-1 (u, v, 1)``."""
    h, w = feature_hw
    device = intrinsics.device
    half = (IMAGE_STRIDE - 1) / 2
    v = torch.arange(h, device=device, dtype=torch.float32) * IMAGE_STRIDE + half
    u = torch.arange(w, device=device, dtype=torch.float32) * IMAGE_STRIDE + half
    pixels = torch.stack([u[None, :].expand(h, w), v[:, None].expand(h, w), torch.ones(h, w, device=device)], dim=-1)
    return torch.einsum("bcij,hwj->bchwi", torch.linalg.inv(intrinsics.float()), pixels)


def frustum_points(intrinsics: Tensor, cam_to_lidar: Tensor, feature_hw: tuple[int, int], depth_centres: Tensor
                   ) -> Tensor:
    """LSS frustum in the LiDAR frame: (B, C, D, h, w, 3) [m], the point at camera depth ``depth_centres[d]`` on the
    ray through the centre pixel of feature cell (row, col)."""
    return frustum_from_rays(cell_rays(intrinsics, feature_hw), cam_to_lidar, depth_centres)


def frustum_from_rays(rays: Tensor, cam_to_lidar: Tensor, depth_centres: Tensor) -> Tensor:
    """`frustum_points` from the cells' rays (B, C, h, w, 3) (`cell_rays`) -> (B, C, D, h, w, 3) [m]."""
    directions = torch.einsum("bcij,bchwj->bchwi", cam_to_lidar[..., :3, :3].float(), rays)
    origins = cam_to_lidar[..., :3, 3].float()[:, :, None, None, None, :]
    return depth_centres.view(1, 1, -1, 1, 1, 1) * directions[:, :, None] + origins


def lift_splat(depth_prob: Tensor, context: Tensor, geometry: Tensor, grid: BevGrid, z_range_m: tuple[float, float]
               ) -> Tensor:
    """LSS lift and splat: depth_prob (B, C, D, h, w) x context (B, C, F, h, w) at the frustum points geometry
    (B, C, D, h, w, 3) [m], sum-pooled into the BEV grid (points outside dropped) -> (B, F, H, W)."""
    batch_size, cameras, bins, h, w = depth_prob.shape
    channels = context.shape[2]
    with torch.no_grad():  # only the frustum points inside the grid are multiplied out (about half of them)
        batch_index = torch.arange(batch_size, device=geometry.device).view(-1, 1, 1, 1, 1).expand(
            geometry.shape[:-1])
        cells = bev_cell_indices(geometry, batch_index, grid, z_range_m).reshape(-1)
        inside = torch.nonzero(cells >= 0).squeeze(1)  # flat (b, c, d, row, col) indices, in order
        pixels = h * w
        ray = (inside // (bins * pixels)) * pixels + inside % pixels  # flat (b, c, row, col) of each point's ray
    context_rows = context.permute(0, 1, 3, 4, 2).reshape(-1, channels)  # (B C h w, F)
    features = depth_prob.reshape(-1)[inside, None] * context_rows[ray]  # (points inside, F)
    return bev_sum_pool(features, cells[inside], batch_size, grid)


# --- branches ----------------------------------------------------------------------------------------------------


class PillarEncoder(nn.Module):
    """Points (P, 6) -> pillar features (B, out_channels, H, W) on ``grid``: per point the 10 `PILLAR_POINT_FEATURES`
    (positions scaled by the grid's range, offsets by the cell size), Linear + BatchNorm + ReLU, max per pillar;
    then the `sweep_statistics` of ``motion_sweeps`` sweeps. Points outside the grid or ``z_range_m`` are
    dropped."""

    def __init__(self, grid: BevGrid, z_range_m: tuple[float, float], channels: int = 32, motion_sweeps: int = 0,
                 sweep_period_s: float = 0.05, keyframe_only: bool = False) -> None:
        super().__init__()
        self.grid, self.z_range_m = grid, z_range_m
        self.motion_sweeps, self.sweep_period_s, self.keyframe_only = motion_sweeps, sweep_period_s, keyframe_only
        self.linear = nn.Linear(PILLAR_POINT_FEATURES, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels)

    @property
    def out_channels(self) -> int:
        return self.linear.out_features + SWEEP_STATISTICS * self.motion_sweeps

    def point_features(self, points: Tensor, flat_cells: Tensor, batch_size: int) -> Tensor:
        """(P, 10) features of in-grid points (P, 6) in their (P,) cells."""
        grid = self.grid
        xyz = points[:, 1:4]
        num_cells = batch_size * grid.size * grid.size
        counts = xyz.new_zeros(num_cells).index_add_(0, flat_cells, torch.ones_like(xyz[:, 0]))
        sums = xyz.new_zeros(num_cells, 3).index_add_(0, flat_cells, xyz)
        mean = sums[flat_cells] / counts[flat_cells, None]
        z_scale = max(abs(self.z_range_m[0]), abs(self.z_range_m[1]))
        return torch.cat([xyz[:, :2] / grid.range_m, xyz[:, 2:3] / z_scale, points[:, 4:6],
                          (xyz - mean) / grid.cell_m, (xyz[:, :2] - cell_centres(flat_cells, grid, xyz.dtype))
                          / grid.cell_m], dim=1)

    def forward(self, points: Tensor, batch_size: int) -> Tensor:
        points = points.float()
        flat = bev_cell_indices(points[:, 1:4], points[:, 0].long(), self.grid, self.z_range_m)
        keep = flat >= 0
        points, flat = points[keep], flat[keep]
        mlp = points[:, 5] < 0.5 * self.sweep_period_s if self.keyframe_only else None
        mlp_points, mlp_flat = (points, flat) if mlp is None else (points[mlp], flat[mlp])
        if len(mlp_points) < 2:  # BatchNorm needs two values in training; a (nearly) empty cloud gives an empty BEV
            size = self.grid.size
            return points.new_zeros(batch_size, self.out_channels, size, size)
        features = F.relu(self.norm(self.linear(self.point_features(mlp_points, mlp_flat, batch_size))))
        pillars = bev_max_pool(features, mlp_flat, batch_size, self.grid)
        if self.motion_sweeps == 0:
            return pillars
        motion = sweep_statistics(points, flat, batch_size, self.grid, self.motion_sweeps, self.sweep_period_s)
        return torch.cat([pillars, motion], dim=1)


class LidarBranch(nn.Module):
    """Pillars -> conv block at stride 2 -> conv block: (P, 6) points -> (B, out_channels, ceil(H/2), ceil(W/2))."""

    def __init__(self, config: DetectorConfig) -> None:
        super().__init__()
        self.pillars = PillarEncoder(config.bev_grid, config.z_range_m, config.pillar_channels, config.motion_sweeps,
                                     config.sweep_period_s, config.pillar_keyframe_only)
        self.convs = nn.Sequential(conv_bn_relu(self.pillars.out_channels, config.bev_channels, stride=2),
                                   conv_bn_relu(config.bev_channels, config.bev_channels))

    def forward(self, points: Tensor, batch_size: int) -> Tensor:
        return self.convs(self.pillars(points, batch_size))


class CameraNeck(nn.Module):
    """The frozen trunk's two levels -> (N, channels, H/8, W/8), an FPN level: 1x1 conv-BN-ReLU laterals, the
    stride-16 level upsampled (bilinear) onto the stride-8 one and added, a 3x3 conv-BN-ReLU."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.lateral8 = conv_bn_relu(STRIDE8_CHANNELS, channels, kernel_size=1)
        self.lateral16 = conv_bn_relu(STRIDE16_CHANNELS, channels, kernel_size=1)
        self.out = conv_bn_relu(channels, channels)

    def forward(self, stride8: Tensor, stride16: Tensor) -> Tensor:
        up = F.interpolate(self.lateral16(stride16), size=stride8.shape[-2:], mode="bilinear", align_corners=False)
        return self.out(self.lateral8(stride8) + up)


class CameraBranch(nn.Module):
    """BEVDepth's LSS, small, on frozen ImageNet features: trunk features (B, C, F, h, w) at strides 8 and 16 and the
    cameras' intrinsics -> camera BEV (B, bev_channels, ceil(H_bev/2), ceil(W_bev/2)) and the per-cell depth
    distributions (B, C, D, h, w) that `depth_loss` supervises. No LiDAR input: see the module docstring."""

    def __init__(self, config: DetectorConfig) -> None:
        super().__init__()
        self.grid, self.z_range_m, self.depth = config.bev_grid, config.z_range_m, config.depth
        self.context_channels = config.camera_context_channels
        self.neck = CameraNeck(config.image_channels)
        self.depth_net = nn.Sequential(conv_gn_relu(config.image_channels + RAY_CHANNELS, config.image_channels),
                                       conv_gn_relu(config.image_channels, config.image_channels),
                                       nn.Conv2d(config.image_channels, config.depth_bins + self.context_channels, 1))
        self.downsample = conv_bn_relu(self.context_channels, config.bev_channels, stride=2)

    def depth_and_context(self, stride8: Tensor, stride16: Tensor, rays: Tensor) -> tuple[Tensor, Tensor]:
        """trunk features (B, C, 40, h, w), (B, C, 112, h/2, w/2), the cells' rays (B, C, h, w, 3) (`cell_rays`)
        -> depth probabilities (B, C, D, h, w) and context (B, C, F, h, w)."""
        batch_size, cameras = stride8.shape[:2]
        features = self.neck(stride8.flatten(0, 1), stride16.flatten(0, 1))
        directions = rays[..., :RAY_CHANNELS].flatten(0, 1).permute(0, 3, 1, 2)
        out = self.depth_net(torch.cat([features, directions], dim=1))
        bins = self.depth.count
        depth_prob = out[:, :bins].softmax(dim=1)
        context = out[:, bins:]
        return (depth_prob.view(batch_size, cameras, bins, *out.shape[2:]),
                context.reshape(batch_size, cameras, self.context_channels, *out.shape[2:]))

    def forward(self, batch: DetectionBatch) -> tuple[Tensor, Tensor]:
        """The camera BEV and the depth probabilities of the batch's cameras."""
        feature_hw = tuple(batch.features_s8.shape[-2:])
        rays = cell_rays(batch.intrinsics, feature_hw)
        depth_prob, context = self.depth_and_context(batch.features_s8, batch.features_s16, rays)
        with torch.no_grad():
            geometry = frustum_from_rays(rays, batch.cam_to_lidar, self.depth.centres(batch.features_s8.device))
        bev = lift_splat(depth_prob, context, geometry, self.grid, self.z_range_m)
        return self.downsample(bev), depth_prob


class ConvFuser(nn.Module):
    """BEVFusion's ConvFuser: concat(camera BEV, LiDAR BEV) on channels -> 3x3 conv + GroupNorm + ReLU (per-sample
    normalisation: a dropped branch is zero, see `conv_gn_relu`)."""

    def __init__(self, camera_channels: int, lidar_channels: int, out_channels: int) -> None:
        super().__init__()
        self.fuse = conv_gn_relu(camera_channels + lidar_channels, out_channels)

    def forward(self, camera_bev: Tensor, lidar_bev: Tensor) -> Tensor:
        return self.fuse(torch.cat([camera_bev, lidar_bev], dim=1))


class BevEncoder(nn.Module):
    """Two-scale BEV encoder + FPN (SECOND / SECONDFPN-like, GroupNorm: see `conv_gn_relu`): (B, C, h, w) at stride 2
    of the BEV grid -> a block at
    stride 2 (C channels) and a block at stride 4 (2 C), each brought to ``head_stride`` with C / 2 channels
    (transposed conv, or 1x1 conv at scale 1), concatenated -> (B, C, H / head_stride, W / head_stride)."""

    def __init__(self, channels: int, head_stride: int) -> None:
        super().__init__()
        self.block1 = conv_gn_relu(channels, channels)
        self.block2 = nn.Sequential(conv_gn_relu(channels, 2 * channels, stride=2),
                                    conv_gn_relu(2 * channels, 2 * channels))
        self.up1 = self._upsample(channels, channels // 2, 2 // head_stride)
        self.up2 = self._upsample(2 * channels, channels - channels // 2, 4 // head_stride)

    @staticmethod
    def _upsample(in_channels: int, out_channels: int, scale: int) -> nn.Sequential:
        conv = (nn.ConvTranspose2d(in_channels, out_channels, scale, stride=scale, bias=False) if scale > 1
                else nn.Conv2d(in_channels, out_channels, 1, bias=False))
        return nn.Sequential(conv, nn.GroupNorm(8, out_channels), nn.ReLU(inplace=True))

    def forward(self, bev: Tensor) -> Tensor:
        x1 = self.block1(bev)
        x2 = self.block2(x1)
        up1, up2 = self.up1(x1), self.up2(x2)
        h, w = up1.shape[-2:]
        return torch.cat([up1, up2[..., :h, :w]], dim=1)


# --- the detector ------------------------------------------------------------------------------------------------


def position_map(features: Tensor) -> Tensor:
    """(B, C, H, W) -> (B, 2, H, W): each cell centre's x (columns) and y (rows) scaled to [-1, 1]."""
    b, _, h, w = features.shape
    xs = (torch.arange(w, device=features.device, dtype=features.dtype) + 0.5) / w * 2 - 1
    ys = (torch.arange(h, device=features.device, dtype=features.dtype) + 0.5) / h * 2 - 1
    grid = torch.stack([xs.view(1, w).expand(h, w), ys.view(h, 1).expand(h, w)])
    return grid.unsqueeze(0).expand(b, -1, -1, -1)


def modality_masks(modality: Modality, batch_size: int, dropout: float, training: bool,
                   device: torch.device | str, lidar_drop_share: float = 0.5) -> tuple[Tensor, Tensor]:
    """(B,) bool masks (use LiDAR, use camera) for ``modality``; when ``training`` and fused, each sample loses one
    branch with probability ``dropout``: the LiDAR with probability ``lidar_drop_share`` (the sample is camera-only),
    else the camera (torch's RNG on ``device``)."""
    if modality not in MODALITIES:
        raise ValueError(f"modality must be one of {MODALITIES}, got {modality!r}")
    use_lidar = torch.full((batch_size,), modality != "camera", dtype=torch.bool, device=device)
    use_camera = torch.full((batch_size,), modality != "lidar", dtype=torch.bool, device=device)
    if training and modality == "fused" and dropout > 0:
        drop = torch.rand(batch_size, device=device) < dropout
        drop_camera = torch.rand(batch_size, device=device) >= lidar_drop_share
        use_camera &= ~(drop & drop_camera)
        use_lidar &= ~(drop & ~drop_camera)
    return use_lidar, use_camera


class BEVFusionDetector(nn.Module):
    """The detector: `DetectionBatch` -> `HeadOutputs` (forward), named losses (`loss`), `SampleDetections`
    (`detect`). See the module docstring."""

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or DetectorConfig()
        self.lidar = LidarBranch(config)
        self.camera = CameraBranch(config)
        self.fuser = ConvFuser(config.bev_channels, config.bev_channels, config.bev_channels)
        self.encoder = BevEncoder(config.bev_channels, config.head_stride)
        self.head = CenterHead(config.bev_channels + 2 * config.position_channels, config.head_channels)

    @property
    def head_grid(self) -> BevGrid:
        return self.config.head_grid

    def aux_camera_pass(self, modality: Modality) -> bool:
        """Whether a forward pass adds the auxiliary camera-only outputs (training, fused, ``camera_only_loss``)."""
        return self.training and modality == "fused" and self.config.camera_only_loss

    def fused_bev(self, batch: DetectionBatch, modality: Modality = "fused") -> tuple[Tensor, Tensor | None]:
        """The fused BEV features (B, bev_channels, ceil(H/2), ceil(W/2)) and the camera's depth distributions
        (B, C, D, h, w) (None for "lidar"); the branch a sample does not use is zero (and not computed at all for
        "lidar" / "camera"). With `aux_camera_pass`, the B camera-only fused maps follow: (2 B, ...)."""
        batch_size, device = batch.batch_size, batch.images.device
        use_lidar, use_camera = modality_masks(modality, batch_size, self.config.modality_dropout, self.training,
                                               device, self.config.lidar_drop_share)
        half = (self.config.bev_grid.size + 1) // 2
        zeros = torch.zeros(batch_size, self.config.bev_channels, half, half, device=device)
        lidar_bev = zeros if modality == "camera" else self.lidar(batch.points, batch_size)
        camera_bev, depth_prob = (zeros, None) if modality == "lidar" else self.camera(batch)
        lidar_bev = lidar_bev * use_lidar.view(-1, 1, 1, 1).to(lidar_bev.dtype)
        masked_camera_bev = camera_bev * use_camera.view(-1, 1, 1, 1).to(camera_bev.dtype)
        if self.aux_camera_pass(modality):
            return self.fuser(torch.cat([masked_camera_bev, camera_bev]), torch.cat([lidar_bev, zeros])), depth_prob
        return self.fuser(masked_camera_bev, lidar_bev), depth_prob

    def forward(self, batch: DetectionBatch, modality: Modality = "fused") -> HeadOutputs:
        bev, depth_prob = self.fused_bev(batch, modality)
        features = self.encoder(bev)
        if self.config.position_channels:
            features = torch.cat([features, position_map(features)], dim=1)
        outputs = self.head(features)
        if self.aux_camera_pass(modality):
            outputs, camera_only = outputs.split(batch.batch_size)
            outputs.camera_only = camera_only
        outputs.camera_depth = depth_prob
        return outputs

    def loss(self, batch: DetectionBatch, outputs: HeadOutputs) -> dict[str, Tensor]:
        """Named losses of ``outputs`` against the batch's boxes (`center_head_loss`); ``camera_only``, the total
        loss of the auxiliary camera-only outputs, when they are there; and, when the camera branch ran, ``depth``
        (`depth_loss` against the batch's keyframe points, weighted by ``depth_loss_weight``); ``total`` includes
        them all."""
        targets = encode_targets(batch.boxes, batch.labels, batch.attributes, self.head_grid, self.config.min_radius,
                                 self.config.gaussian_overlap)
        losses = center_head_loss(outputs, targets, self.config.loss_weights)
        if outputs.camera_only is not None:
            losses["camera_only"] = center_head_loss(outputs.camera_only, targets, self.config.loss_weights)["total"]
            losses["total"] = losses["total"] + losses["camera_only"]
        if outputs.camera_depth is not None:
            target = depth_targets(batch.points, batch.intrinsics, batch.cam_to_lidar, tuple(batch.images.shape[-2:]),
                                   tuple(batch.features_s8.shape[-2:]), self.config.depth)
            losses["depth"] = depth_loss(outputs.camera_depth, target)
            losses["total"] = losses["total"] + self.config.depth_loss_weight * losses["depth"]
        return losses

    @torch.no_grad()
    def detect(self, batch: DetectionBatch, score_threshold: float = 0.1, max_per_sample: int = 300,
               modality: Modality = "fused") -> list[SampleDetections]:
        """Detections per sample (in eval mode; the module's mode is restored afterwards)."""
        was_training = self.training
        self.eval()
        try:
            outputs = self(batch, modality)
        finally:
            self.train(was_training)
        decoded = decode_detections(outputs, self.head_grid, score_threshold, max_per_sample)
        detections = [SampleDetections(token, d.boxes.double().cpu().numpy(), d.scores.double().cpu().numpy(),
                                       d.labels.cpu().numpy().astype("int64"),
                                       d.attributes.cpu().numpy().astype("int64"))
                      for token, d in zip(batch.tokens, decoded)]
        if self.config.sweep_velocity and modality != "camera":
            detections = [with_sweep_motion(d, sample_points(batch.points, b))
                          for b, d in enumerate(detections)]
        return detections


def sample_points(points: Tensor, sample: int) -> np.ndarray:
    """(P, 6) batched points ``batch index, x, y, z, intensity, lag`` -> sample ``sample``'s (N, 5) as float64."""
    mine = points[points[:, 0] == sample, 1:]
    return mine.double().cpu().numpy()


def with_sweep_motion(detections: SampleDetections, points: np.ndarray,
                      settings: SweepMatching = SweepMatching()) -> SampleDetections:
    """``detections`` with velocities (and movers' directions) from scan matching the sweeps' ``points`` (N, 5)
    (`weatheralign.detect.sweep_motion`); static classes (`STATIC_CLASSES`) and detections scoring below
    ``settings.min_score`` keep the head's."""
    chosen = ~np.isin(detections.labels, STATIC_CLASS_INDICES) & (detections.scores >= settings.min_score)
    boxes = detections.boxes.copy()
    motion = sweep_velocities(points, boxes[chosen], settings)
    boxes[chosen] = apply_sweep_motion(boxes[chosen], motion, settings)
    return SampleDetections(detections.token, boxes, detections.scores, detections.labels, detections.attributes)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


# --- training ----------------------------------------------------------------------------------------------------


def train_step(model: BEVFusionDetector, batch: DetectionBatch, optimizer: torch.optim.Optimizer,
               scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, max_grad_norm: float = 35.0,
               modality: Modality = "fused") -> dict[str, float]:
    """One optimisation step in train mode: forward, loss, backward, gradient clipping, step (and the scheduler's).
    Returns the losses and ``grad_norm`` (before clipping) as floats."""
    model.train()
    optimizer.zero_grad(set_to_none=True)
    losses = model.loss(batch, model(batch, modality))
    losses["total"].backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm)
    optimizer.step()
    if scheduler is not None:
        scheduler.step()
    return {**{name: float(value.detach()) for name, value in losses.items()}, "grad_norm": float(grad_norm)}


__all__ = ["bev_cell_indices", "bev_max_pool", "bev_sum_pool", "BevEncoder", "BEVFusionDetector", "CameraBranch",
           "CameraNeck", "cell_centres", "cell_rays", "ConvFuser", "count_parameters", "depth_loss", "depth_targets",
           "DepthBins", "DetectorConfig", "frustum_from_rays", "frustum_points", "IMAGE_STRIDE", "LidarBranch",
           "lift_splat", "MODALITIES", "Modality", "modality_masks", "PillarEncoder", "project_into_cells",
           "position_map", "project_points", "RAY_CHANNELS", "sample_points", "STATIC_CLASSES", "sweep_statistics",
           "SWEEP_STATISTICS", "sweep_statistics_naive", "train_step", "with_sweep_motion"]
