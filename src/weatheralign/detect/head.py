"""CenterPoint-style detection head on a BEV grid: the grid, target encoding, the losses and the decoding.

Conventions: a BEV map is ``(B, channels, H, W)`` with the row index along LiDAR y and the column index along LiDAR x;
cell ``(row, col)`` covers ``x in [-R + col * cell, -R + (col + 1) * cell)`` and likewise y. Flat cell indices are
``b * H * W + row * W + col``.

Regression channels at an object's centre cell (`REGRESSION_CHANNELS`): the centre's offset inside its cell (in
cells, in [0, 1)), z [m], log of (w, l, h) [log m], sin / cos of yaw, velocity (vx, vy) [m/s]. Heatmap targets are
CenterPoint's: a Gaussian per object, peak 1 at the centre cell, radius from the box's footprint in cells
(``gaussian_radius``, min overlap 0.1, at least ``min_radius`` cells), one channel per class, max where they overlap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from weatheralign.detect.types import ATTRIBUTES, BOX_DIM, DETECTION_CLASSES

NUM_CLASSES = len(DETECTION_CLASSES)
NUM_ATTRIBUTES = len(ATTRIBUTES)
REGRESSION_CHANNELS: tuple[str, ...] = ("offset_x", "offset_y", "z", "log_w", "log_l", "log_h", "sin_yaw", "cos_yaw",
                                        "vx", "vy")
#: regression channel slices by loss name
REGRESSION_GROUPS: dict[str, slice] = {"offset": slice(0, 2), "z": slice(2, 3), "size": slice(3, 6),
                                       "yaw": slice(6, 8), "velocity": slice(8, 10)}
#: which attribute family (prefix of `ATTRIBUTES`) each class may carry; absent: no attribute (cone, barrier)
CLASS_ATTRIBUTE_FAMILY: dict[str, str] = {"car": "vehicle", "truck": "vehicle", "bus": "vehicle",
                                          "trailer": "vehicle", "construction_vehicle": "vehicle",
                                          "pedestrian": "pedestrian", "motorcycle": "cycle", "bicycle": "cycle"}
HEATMAP_BIAS_INIT = -2.19  # sigmoid(-2.19) ~ 0.1 (CenterNet / CenterPoint)
_LOGIT_CLAMP = 9.21  # sigmoid clamped to [1e-4, 1 - 1e-4] as in CenterPoint's focal loss
_MASKED_LOGIT = -1e4


@dataclass(frozen=True)
class BevGrid:
    """A square BEV grid over ``[-range_m, range_m)^2`` [m] in the LiDAR x / y plane, cells of ``cell_m`` [m]."""

    range_m: float
    cell_m: float

    def __post_init__(self) -> None:
        cells = 2.0 * self.range_m / self.cell_m
        if self.range_m <= 0 or self.cell_m <= 0 or abs(cells - round(cells)) > 1e-6:
            raise ValueError(f"BEV range {self.range_m} m is not a positive whole number of {self.cell_m} m cells")

    @property
    def size(self) -> int:
        """Cells per side (H = W)."""
        return int(round(2.0 * self.range_m / self.cell_m))

    def coarsened(self, stride: int) -> BevGrid:
        """The same extent with cells ``stride`` times larger."""
        return BevGrid(self.range_m, self.cell_m * stride)

    def cell_of(self, xy: Tensor) -> Tensor:
        """(..., 2) x, y [m] -> (..., 2) int64 (col, row); may lie outside ``[0, size)``."""
        return torch.floor((xy + self.range_m) / self.cell_m).long()

    def contains(self, cells: Tensor) -> Tensor:
        """(..., 2) int64 (col, row) -> (...) bool: inside the grid."""
        return ((cells >= 0) & (cells < self.size)).all(dim=-1)


@dataclass
class HeadOutputs:
    """Raw head maps at the head's grid. heatmap: (B, K, H, W) logits; regression: (B, 10, H, W) in
    `REGRESSION_CHANNELS` order; attributes: (B, 8, H, W) logits."""

    heatmap: Tensor
    regression: Tensor
    attributes: Tensor
    #: (B, C, D, h, w) the camera branch's depth distributions (None when it did not run), for `depth_loss`
    camera_depth: Tensor | None = None
    #: training only: the same batch's outputs with the LiDAR BEV zeroed (the auxiliary camera-only pass)
    camera_only: HeadOutputs | None = None

    def split(self, size: int) -> tuple[HeadOutputs, HeadOutputs]:
        """The first ``size`` samples' maps and the rest's (``camera_depth`` and ``camera_only`` are not split)."""
        first = HeadOutputs(self.heatmap[:size], self.regression[:size], self.attributes[:size])
        rest = HeadOutputs(self.heatmap[size:], self.regression[size:], self.attributes[size:])
        return first, rest


@dataclass
class CenterTargets:
    """Training targets of a batch. heatmap: (B, K, H, W) in [0, 1]; for the N objects whose centre is in the grid:
    indices (N,) flat cell indices into B * H * W, regression (N, 10), labels (N,) class indices, attributes (N,)
    attribute indices (-1: none)."""

    heatmap: Tensor
    indices: Tensor
    regression: Tensor
    labels: Tensor
    attributes: Tensor


@dataclass(frozen=True)
class LossWeights:
    """Weights of the total loss: ``heatmap * L_heatmap + regression * sum_g group_g * L_g + attribute * L_attr``
    (CenterPoint: regression 0.25, velocity code weight 0.2)."""

    heatmap: float = 1.0
    regression: float = 0.25
    offset: float = 1.0
    z: float = 1.0
    size: float = 1.0
    yaw: float = 1.0
    velocity: float = 0.2
    attribute: float = 0.2


def valid_attribute_mask(device: torch.device | str | None = None) -> Tensor:
    """(10, 8) bool: which attributes each class may carry (`CLASS_ATTRIBUTE_FAMILY`)."""
    rows = [[name in CLASS_ATTRIBUTE_FAMILY and attribute.startswith(CLASS_ATTRIBUTE_FAMILY[name] + ".")
             for attribute in ATTRIBUTES] for name in DETECTION_CLASSES]
    return torch.tensor(rows, dtype=torch.bool, device=device)


def conv_bn_relu(in_channels: int, out_channels: int, stride: int = 1, kernel_size: int = 3) -> nn.Sequential:
    """Conv (no bias) + BatchNorm + ReLU, 'same' padding; output stride ``stride``."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel_size, stride, kernel_size // 2, bias=False),
                         nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))


def conv_gn_relu(in_channels: int, out_channels: int, stride: int = 1, groups: int = 8) -> nn.Sequential:
    """3x3 conv (no bias) + GroupNorm + ReLU: normalised per sample, so that a sample whose camera or LiDAR branch
    is zero is normalised the same way in training (mixed batches) and in a single-modality evaluation."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False),
                         nn.GroupNorm(groups, out_channels), nn.ReLU(inplace=True))


class CenterHead(nn.Module):
    """CenterPoint's head, slim: a shared 3x3 conv-GroupNorm-ReLU, then a final 3x3 conv to the K heatmap logits (bias
    -2.19) and one to the 10 regression channels + 8 attribute logits. (B, in_channels, H, W) -> `HeadOutputs` at
    (H, W)."""

    def __init__(self, in_channels: int, channels: int = 64) -> None:
        super().__init__()
        self.shared = conv_gn_relu(in_channels, channels)
        self.heatmap = nn.Conv2d(channels, NUM_CLASSES, 3, padding=1)
        self.box = nn.Conv2d(channels, len(REGRESSION_CHANNELS) + NUM_ATTRIBUTES, 3, padding=1)
        nn.init.constant_(self.heatmap.bias, HEATMAP_BIAS_INIT)

    def forward(self, bev: Tensor) -> HeadOutputs:
        x = self.shared(bev)
        box = self.box(x)
        n_reg = len(REGRESSION_CHANNELS)
        return HeadOutputs(self.heatmap(x), box[:, :n_reg], box[:, n_reg:])


# --- targets ---------------------------------------------------------------------------------------------------


def gaussian_radius(length_cells: Tensor, width_cells: Tensor, min_overlap: float = 0.1) -> Tensor:
    """CenterPoint's (CornerNet's) Gaussian radius [cells] for a box footprint of ``length x width`` cells: the
    smallest of the three corner-shift radii keeping IoU >= ``min_overlap`` (with CenterPoint's ``(b + sq) / 2``)."""
    h, w = length_cells, width_cells
    b1 = h + w
    c1 = w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + torch.sqrt((b1 ** 2 - 4 * c1).clamp_min(0))) / 2
    b2 = 2 * (h + w)
    c2 = (1 - min_overlap) * w * h
    r2 = (b2 + torch.sqrt((b2 ** 2 - 16 * c2).clamp_min(0))) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (h + w)
    c3 = (min_overlap - 1) * w * h
    r3 = (b3 + torch.sqrt((b3 ** 2 - 4 * a3 * c3).clamp_min(0))) / 2
    return torch.minimum(torch.minimum(r1, r2), r3)


def encode_box_regression(boxes: Tensor, cells: Tensor, grid: BevGrid) -> Tensor:
    """(N, 9) boxes and their (N, 2) int64 (col, row) centre cells -> (N, 10) regression targets
    (`REGRESSION_CHANNELS`); a non-finite velocity stays NaN (the loss skips it)."""
    offset = (boxes[:, :2] + grid.range_m) / grid.cell_m - cells.to(boxes.dtype)
    yaw = boxes[:, 6:7]
    return torch.cat([offset, boxes[:, 2:3], torch.log(boxes[:, 3:6].clamp_min(1e-3)), torch.sin(yaw),
                      torch.cos(yaw), boxes[:, 7:9]], dim=1)


def decode_box_regression(regression: Tensor, cells: Tensor, grid: BevGrid) -> Tensor:
    """(N, 10) regression at (N, 2) int64 (col, row) cells -> (N, 9) boxes; yaw = atan2(sin, cos) in (-pi, pi]."""
    xy = (cells.to(regression.dtype) + regression[:, 0:2]) * grid.cell_m - grid.range_m
    size = torch.exp(regression[:, 3:6].clamp(max=6.0))
    yaw = torch.atan2(regression[:, 6:7], regression[:, 7:8])
    return torch.cat([xy, regression[:, 2:3], size, yaw, regression[:, 8:10]], dim=1)


def draw_gaussians(centres: Tensor, radii: Tensor, channels: Tensor, num_channels: int, size: int) -> Tensor:
    """CenterPoint's ``draw_heatmap_gaussian`` for N objects at once: a Gaussian of sigma ``(2 r + 1) / 6`` peaking
    at 1 on each integer (col, row) centre (N, 2), cut to the ``(2 r + 1)^2`` window, max-combined into channel
    ``channels`` (N,) of a (num_channels, size, size) map."""
    heat = torch.zeros(num_channels, size * size, device=centres.device)
    if len(centres) == 0:
        return heat.view(num_channels, size, size)
    coords = torch.arange(size, device=centres.device, dtype=torch.float32)
    dx = coords[None, None, :] - centres[:, 0, None, None].float()  # (N, 1, W)
    dy = coords[None, :, None] - centres[:, 1, None, None].float()  # (N, H, 1)
    r = radii.float()[:, None, None]
    sigma = (2 * r + 1) / 6
    g = torch.exp(-(dx ** 2 + dy ** 2) / (2 * sigma ** 2)) * ((dx.abs() <= r) & (dy.abs() <= r))
    index = channels[:, None].expand(-1, size * size)
    return heat.scatter_reduce(0, index, g.reshape(len(centres), -1), reduce="amax").view(num_channels, size, size)


def encode_targets(boxes: list[Tensor], labels: list[Tensor], attributes: list[Tensor], grid: BevGrid,
                   min_radius: int = 2, min_overlap: float = 0.1) -> CenterTargets:
    """Targets on ``grid`` (the head's grid) for B samples of (M_b, 9) boxes, (M_b,) labels and attributes.

    Objects whose centre lies outside the grid are left out; attributes that the class cannot carry become -1.
    """
    device = boxes[0].device if boxes else torch.device("cpu")
    size = grid.size
    heatmaps, indices, regressions, all_labels, all_attributes = [], [], [], [], []
    valid_attrs = valid_attribute_mask(device)
    for b, (box, label, attribute) in enumerate(zip(boxes, labels, attributes)):
        box = box.float()
        cells = grid.cell_of(box[:, :2])
        inside = grid.contains(cells)
        box, label, attribute, cells = box[inside], label[inside].long(), attribute[inside].long(), cells[inside]
        radius = gaussian_radius(box[:, 4] / grid.cell_m, box[:, 3] / grid.cell_m, min_overlap)
        radius = torch.clamp(torch.floor(radius), min=min_radius)
        heatmaps.append(draw_gaussians(cells, radius, label, NUM_CLASSES, size))
        indices.append(b * size * size + cells[:, 1] * size + cells[:, 0])
        regressions.append(encode_box_regression(box, cells, grid))
        all_labels.append(label)
        allowed = (attribute >= 0) & valid_attrs[label, attribute.clamp_min(0)]
        all_attributes.append(torch.where(allowed, attribute, torch.full_like(attribute, -1)))
    return CenterTargets(torch.stack(heatmaps), torch.cat(indices), torch.cat(regressions), torch.cat(all_labels),
                         torch.cat(all_attributes))


# --- losses ------------------------------------------------------------------------------------------------------


def gaussian_focal_loss(logits: Tensor, target: Tensor) -> Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4) summed over all cells and divided by the number of
    peaks (cells with target 1, at least 1). logits, target: (B, K, H, W)."""
    x = logits.float().clamp(-_LOGIT_CLAMP, _LOGIT_CLAMP)
    p = torch.sigmoid(x)
    positive = target.eq(1).float()
    pos_loss = F.logsigmoid(x) * (1 - p) ** 2 * positive
    neg_loss = F.logsigmoid(-x) * p ** 2 * (1 - target) ** 4 * (1 - positive)
    return -(pos_loss.sum() + neg_loss.sum()) / positive.sum().clamp_min(1.0)


def gather_cells(maps: Tensor, indices: Tensor) -> Tensor:
    """(B, C, H, W) maps at (N,) flat cell indices into B * H * W -> (N, C)."""
    b, c, h, w = maps.shape
    return maps.permute(0, 2, 3, 1).reshape(b * h * w, c)[indices]


def center_head_loss(outputs: HeadOutputs, targets: CenterTargets, weights: LossWeights = LossWeights()
                     ) -> dict[str, Tensor]:
    """Named losses: ``heatmap`` (focal), L1 ``offset`` / ``z`` / ``size`` / ``yaw`` / ``velocity`` (summed over the
    group's channels, averaged over objects; NaN velocity targets skipped), ``attribute`` (cross-entropy over the
    class's valid attributes, objects with an attribute only), and ``total`` weighted by ``weights``."""
    losses = {"heatmap": gaussian_focal_loss(outputs.heatmap, targets.heatmap)}
    regression = gather_cells(outputs.regression, targets.indices).float()
    for name, channels in REGRESSION_GROUPS.items():
        target = targets.regression[:, channels]
        valid = torch.isfinite(target).all(dim=1, keepdim=True)
        error = (regression[:, channels] - torch.nan_to_num(target)).abs() * valid
        losses[name] = error.sum() / valid.sum().clamp_min(1.0)
    with_attribute = targets.attributes >= 0
    logits = gather_cells(outputs.attributes, targets.indices).float()
    logits = logits.masked_fill(~valid_attribute_mask(logits.device)[targets.labels], _MASKED_LOGIT)
    ce = F.cross_entropy(logits, targets.attributes.clamp_min(0), reduction="none") * with_attribute
    losses["attribute"] = ce.sum() / with_attribute.sum().clamp_min(1)
    losses["total"] = (weights.heatmap * losses["heatmap"] + weights.attribute * losses["attribute"]
                       + weights.regression * sum(getattr(weights, name) * losses[name] for name in REGRESSION_GROUPS))
    return losses


# --- decoding ----------------------------------------------------------------------------------------------------


@dataclass
class DecodedBoxes:
    """One sample's decoded detections as tensors: boxes (K, 9), scores (K,), labels (K,), attributes (K,) (-1:
    none), sorted by decreasing score."""

    boxes: Tensor
    scores: Tensor
    labels: Tensor
    attributes: Tensor


def decode_detections(outputs: HeadOutputs, grid: BevGrid, score_threshold: float = 0.1,
                      max_per_sample: int = 300) -> list[DecodedBoxes]:
    """Max-pool (3x3) NMS on the sigmoid heatmap, the top ``max_per_sample`` peaks over all classes with score >=
    ``score_threshold``, boxes decoded at their cells on ``grid`` (the head's grid); attribute = argmax over the
    class's valid attributes, -1 for classes without attributes."""
    heat = torch.sigmoid(outputs.heatmap.float())
    peaks = heat * (heat == F.max_pool2d(heat, 3, stride=1, padding=1))
    b, k, h, w = peaks.shape
    top = min(max_per_sample, k * h * w)
    scores, flat = peaks.reshape(b, -1).topk(top, dim=1)
    valid_attrs = valid_attribute_mask(heat.device)
    decoded = []
    for i in range(b):
        keep = scores[i] >= score_threshold
        score, index = scores[i][keep], flat[i][keep]
        label, cell = index // (h * w), index % (h * w)
        cells = torch.stack([cell % w, cell // w], dim=1)
        sample_cells = i * h * w + cell
        box = decode_box_regression(gather_cells(outputs.regression, sample_cells).float(), cells, grid)
        attr_logits = gather_cells(outputs.attributes, sample_cells).float()
        attr_logits = attr_logits.masked_fill(~valid_attrs[label], -math.inf)
        has_attr = valid_attrs[label].any(dim=1)
        attribute = torch.where(has_attr, attr_logits.argmax(dim=1), torch.full_like(label, -1))
        decoded.append(DecodedBoxes(box.reshape(-1, BOX_DIM), score, label, attribute))
    return decoded


__all__ = ["BevGrid", "CenterHead", "CenterTargets", "DecodedBoxes", "HeadOutputs", "LossWeights", "NUM_ATTRIBUTES",
           "NUM_CLASSES", "REGRESSION_CHANNELS", "center_head_loss", "conv_bn_relu", "decode_detections",
           "encode_targets", "gaussian_focal_loss", "valid_attribute_mask"]
