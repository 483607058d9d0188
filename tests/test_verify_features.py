"""The fused input of the weather classifier (weatheralign.verify.features): the LiDAR lands in the image plane where
the camera sees it (nearest return wins a cell), and early fusion sees alignment where a late-fusion control of the
same data cannot."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from weatheralign.verify.features import FUSED_CHANNELS, WeatherClassifier, fused_input, lidar_image_channels

# camera looking along LiDAR +x: camera z = LiDAR x, camera x = -LiDAR y, camera y = -LiDAR z
T_CAM_LIDAR = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
K = np.array([[100.0, 0.0, 99.5], [0.0, 100.0, 49.5], [0.0, 0.0, 1.0]])  # 200 x 100 pixels


def test_lidar_lands_in_its_cell_and_the_nearest_return_wins() -> None:
    points = np.array([[10.0, 0.0, 0.0], [5.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [10.0, -30.0, 0.0], [20.0, 2.0, 0.0]])
    intensity = np.array([0.2, 0.7, 0.9, 0.9, 0.4])
    out = lidar_image_channels(points, intensity, K, T_CAM_LIDAR, (100, 200), (10, 20))
    # the two points on the optical axis: pixel (99.5, 49.5) -> cell (row 4 or 5, col 9 or 10) of 10 px cells
    row, col = int((49.5 + 0.5) * 10 / 100), int((99.5 + 0.5) * 20 / 200)
    assert out[0, row, col] == pytest.approx(1 / 5.0) and out[1, row, col] == pytest.approx(0.7)
    assert out[2, row, col] == pytest.approx(math.log(3.0))
    # (20, 2, 0): u = 99.5 - 100 * 2 / 20 = 89.5 -> col 9; behind (-10) and outside (y = -30 -> u = 249.5) dropped
    assert out[0, row, 9] == pytest.approx(1 / 20.0) and out[1, row, 9] == pytest.approx(0.4)
    assert np.count_nonzero(out[2]) == 2
    with pytest.raises(ValueError, match="points"):
        lidar_image_channels(points[:, :2], intensity, K, T_CAM_LIDAR, (100, 200), (10, 20))


def test_fused_input_stacks_the_resized_image_over_the_lidar() -> None:
    image = np.zeros((100, 200, 3), np.uint8)
    image[:, :100] = 255
    lidar = np.zeros((3, 10, 20), np.float32)
    lidar[0, 2, 3] = 0.5
    fused = fused_input(image, lidar)
    assert fused.shape == (FUSED_CHANNELS, 10, 20)
    assert fused[:3, :, :10] == pytest.approx(1.0) and fused[:3, :, 10:] == pytest.approx(0.0)
    assert fused[3, 2, 3] == 0.5


def toy_pairs(n: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 6, 16, 16): a bright camera blob at a random cell and a LiDAR echo at the same cell (label 1, aligned) or
    at another random cell (label 0): every channel's marginal is the same in both classes."""
    x = np.zeros((n, FUSED_CHANNELS, 16, 16), np.float32)
    labels = rng.integers(0, 2, n)
    for i in range(n):
        r, c = rng.integers(1, 15, 2)
        x[i, :3, r - 1:r + 2, c - 1:c + 2] = 1.0
        if labels[i] == 0:
            while True:
                r2, c2 = rng.integers(1, 15, 2)
                if abs(r2 - r) + abs(c2 - c) > 4:
                    r, c = r2, c2
                    break
        x[i, 3:, r - 1:r + 2, c - 1:c + 2] = 1.0
    return torch.from_numpy(x), torch.from_numpy(labels)


class LateFusion(nn.Module):
    """Control: camera and LiDAR channels through separate CNNs, each globally pooled, then concatenated."""

    def __init__(self) -> None:
        super().__init__()
        self.camera, self.lidar = WeatherClassifier(2, 8, 16), WeatherClassifier(2, 8, 16)
        self.head = nn.Linear(32, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        zeros = torch.zeros_like(x[:, :3])
        cam = self.camera.embed(torch.cat([x[:, :3], zeros], 1))
        lid = self.lidar.embed(torch.cat([zeros, x[:, 3:]], 1))
        return self.head(torch.cat([cam, lid], 1))


def accuracy_after_training(model: nn.Module, steps: int = 250) -> float:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    x, y = toy_pairs(512, rng)
    xt, yt = toy_pairs(256, rng)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for step in range(steps):
        idx = torch.from_numpy(rng.integers(0, len(x), 32))
        loss = nn.functional.cross_entropy(model(x[idx]), y[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        return float((model(xt).argmax(1) == yt).float().mean())


def test_early_fusion_sees_alignment_that_late_fusion_cannot() -> None:
    torch.set_num_threads(1)
    early = accuracy_after_training(WeatherClassifier(2, 8, 16))
    late = accuracy_after_training(LateFusion())
    assert early > 0.9 and late < 0.65, (early, late)
    embedding = WeatherClassifier(4, 8, 16).embed(torch.zeros(2, FUSED_CHANNELS, 16, 16))
    assert embedding.shape == (2, 16)
