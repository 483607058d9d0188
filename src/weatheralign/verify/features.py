"""The fused input and the auxiliary weather classifier of the fused-feature check (`verify`).

The classifier must see *where* each sensor's weather is: a globally pooled concatenation of a LiDAR embedding and a
camera embedding cannot tell whether the particles the LiDAR saw are the ones the camera shows (aligned) or others
of the same density (unaligned). So the LiDAR is projected into the camera's image plane and stacked with the RGB
image before the first convolution (early fusion): a particle echo and the flake it hit fall on the same cells.

`lidar_image_channels` -> (3, h, w): per cell of the downsized image the inverse depth and the intensity of the
nearest return projected there, and ``log(1 + returns)``; `fused_input` stacks them under the RGB image (6, h, w).
`WeatherClassifier` is a small CNN over that stack; its penultimate layer (`embed`) is the fused feature whose MMD
`weatheralign.verify.mmd` measures.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from torch import Tensor, nn

LIDAR_CHANNELS = 3  # inverse depth [1/m] of the nearest return, its intensity (0..1), log(1 + returns)
FUSED_CHANNELS = 3 + LIDAR_CHANNELS


def lidar_image_channels(points: NDArray, intensity: NDArray, K: NDArray, T_cam_lidar: NDArray,
                         image_hw: tuple[int, int], out_hw: tuple[int, int], min_depth_m: float = 0.5
                         ) -> NDArray[np.float32]:
    """The LiDAR in the image plane of one camera: (3, h, w) float32 for ``out_hw`` = (h, w) cells over the
    ``image_hw`` = (H, W) pixel image. ``points`` (N, 3) [m] in the LiDAR frame, ``intensity`` (N,) in 0..1, ``K``
    (3, 3) the camera's intrinsics at ``image_hw``, ``T_cam_lidar`` (4, 4) LiDAR -> camera (OpenCV axes). Per cell:
    channel 0 the inverse camera depth of the nearest return projected into it, channel 1 that return's intensity,
    channel 2 ``log(1 + returns in the cell)``; 0 where no return falls. Returns closer than ``min_depth_m`` or
    outside the image are dropped."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(intensity) != len(points):
        raise ValueError(f"points must be (N, 3) with N intensities, got {points.shape} and {len(intensity)}")
    (height, width), (h, w) = image_hw, out_hw
    cam = points @ np.asarray(T_cam_lidar)[:3, :3].T + np.asarray(T_cam_lidar)[:3, 3]
    z = cam[:, 2]
    front = z >= min_depth_m
    uvw = cam[front] @ np.asarray(K, dtype=np.float64).T
    u, v, z, value = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2], z[front], np.asarray(intensity)[front]
    inside = (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    col = np.minimum(((u[inside] + 0.5) * w / width).astype(np.int64), w - 1)
    row = np.minimum(((v[inside] + 0.5) * h / height).astype(np.int64), h - 1)
    z, value = z[inside], value[inside]
    out = np.zeros((LIDAR_CHANNELS, h, w), dtype=np.float32)
    cell = row * w + col
    order = np.lexsort((-z, cell))  # per cell, the nearest return last: its write wins
    out[0].reshape(-1)[cell[order]] = 1.0 / z[order]
    out[1].reshape(-1)[cell[order]] = value[order]
    out[2].reshape(-1)[:] = np.log1p(np.bincount(cell, minlength=h * w))
    return out


def fused_input(image: NDArray[np.uint8], lidar_channels: NDArray[np.float32]) -> NDArray[np.float32]:
    """(6, h, w): the RGB image (H, W, 3) uint8 area-resized to the LiDAR channels' (h, w), in 0..1, on top of
    them."""
    h, w = lidar_channels.shape[1:]
    rgb = torch.from_numpy(np.array(image, dtype=np.uint8, copy=True)).permute(2, 0, 1)[None].float() / 255.0
    rgb = F.interpolate(rgb, size=(h, w), mode="area")[0].numpy()
    return np.concatenate([rgb, lidar_channels]).astype(np.float32)


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(c_out),
                         nn.ReLU(inplace=True), nn.Conv2d(c_out, c_out, 3, padding=1, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class WeatherClassifier(nn.Module):
    """Early-fusion CNN: (B, 6, h, w) fused input -> four stride-2 blocks -> global average pool -> ``embedding``-d
    fused feature (`embed`) -> class logits (clear / fog / snow / rain by default, `forward`), and one
    correspondence logit (`correspondence`: do the LiDAR channels belong to this image, at this registration?) that
    trains the embedding to carry the cross-sensor alignment a weather label alone does not need."""

    def __init__(self, num_classes: int = 4, width: int = 16, embedding: int = 64) -> None:
        super().__init__()
        self.features = nn.Sequential(_block(FUSED_CHANNELS, width), _block(width, 2 * width),
                                      _block(2 * width, 4 * width), _block(4 * width, 4 * width))
        self.embedding = nn.Sequential(nn.Linear(4 * width, embedding), nn.ReLU(inplace=True))
        self.logits = nn.Linear(embedding, num_classes)
        self.pair = nn.Linear(embedding, 1)

    def embed(self, x: Tensor) -> Tensor:
        """(B, 6, h, w) -> (B, embedding) fused features."""
        return self.embedding(self.features(x).mean(dim=(2, 3)))

    def forward(self, x: Tensor) -> Tensor:
        return self.logits(self.embed(x))

    def correspondence(self, x: Tensor) -> Tensor:
        """(B, 6, h, w) -> (B,) logit that the LiDAR channels are the image's own, registered."""
        return self.pair(self.embed(x))[:, 0]


__all__ = ["FUSED_CHANNELS", "LIDAR_CHANNELS", "WeatherClassifier", "fused_input", "lidar_image_channels"]
