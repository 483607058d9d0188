"""Camera fog of the shared medium: Koschmieder's law on linear radiance (``docs/physics.md`` section 2.3).

A clear pixel of linear radiance ``J`` seen through homogeneous fog along a ray of length ``l`` [m] becomes
``I = J t + A (1 - t)`` with the one-way transmittance ``t = exp(-alpha l)``. ``alpha`` is the medium's extinction
(`weatheralign.medium.fog.FogMedium.camera_extinction`, the same number the LiDAR sees two-way), and ``l`` is the
**ray length** from the camera centre to the surface, not the z-depth: a pixel at the image corner with the same z as
the centre pixel lies farther away and receives more fog. Sky pixels (``l = inf``) have ``t = 0`` and show the
airlight.

Colour space. Koschmieder's law is additive in radiance, so it is applied to **linear** RGB: the sRGB input (uint8
code values, or floats in [0, 1]) is decoded with the exact sRGB transfer function, fogged, and re-encoded to uint8
sRGB (exactly rounded). The airlight ``A`` is given, like the images, as an **sRGB-encoded** colour in [0, 1] (what
the sky looks like in the image; a neutral ``0.8`` grey is 0.604 in linear radiance) and decoded before use.

Airlight. One value per scene, shared by all six cameras (per-camera estimates give visible seams between
neighbouring cameras): `estimate_airlight` pools the pixels of all cameras of a scene.

Transmission refinement. The per-pixel ``t`` from a depth map is smoothed with a guided filter (He et al. 2010/2013)
using the clear image as guide (window 41, ``eps = 1e-3`` on the [0, 1] sRGB guide): it follows the image's edges and
removes depth noise and holes. The filter is the colour-guide version computed with OpenCV box filters on the
coefficients at half the resolution (the "fast guided filter", He & Sun 2015; a quarter was measured to bias the
camera fog-severity estimate on small images by 12 %); `composite_image` then upsamples the coefficients, applies
them, composites and encodes in one compiled pass per image (instead of several full-image numpy passes; within 1
code value of the numpy composition of the same filter, mean 0.02 code values from the exact full-resolution filter).
``kornia.filters.guided_blur`` is not used: on the CPU it is far slower than this compiled pass
(`benchmarks/bench_camera.py` measures the camera path).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.kernels import (
    composite_guided_kernel,
    composite_plain_kernel,
    encode_srgb_kernel,
    guided_affine_edit_kernel,
)

F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]

NEUTRAL_AIRLIGHT = 0.8
"""Fallback airlight (sRGB-encoded grey in [0, 1]) for scenes without visible sky (docs/physics.md 2.3: 0.75-0.85)."""

SKY_MIN_PIXELS = 100
"""Fewest sky pixels (pooled over the cameras) for a sky-based airlight; fewer fall back to the neutral grey."""

CLIPPED = 250.0 / 255.0
"""A pixel with any channel at or above this (sRGB) is saturated: its radiance is unknown, so it never votes for the
airlight (an overexposed sky would otherwise give a pure-white airlight that whitens everything in fog)."""

DARK_CHANNEL_WINDOW = 15
"""Window [px] of the dark channel's minimum filter (He et al.)."""

DARK_CHANNEL_TOP_FRACTION = 1e-3
"""Fraction of pooled pixels with the brightest dark channel taken as airlight candidates (top 0.1 %)."""

DARK_CHANNEL_MIN_SKY = 0.5
"""Darkest dark-channel value [0, 1] (sRGB) that can still be sky/haze; below it the scene has no sky."""

GUIDED_RADIUS = 20
"""Guided-filter radius [px] (window ``2 r + 1 = 41``) at full resolution."""

GUIDED_EPS = 1e-3
"""Guided-filter regulariser in squared guide units (guide = sRGB in [0, 1])."""

GUIDED_SUBSAMPLE = 2
"""Resolution divisor of the guided-filter coefficients (the "fast guided filter"; 1 = exact)."""


# ------------------------------------------------------------------------------------------------ sRGB transfer


def srgb_to_linear(encoded: NDArray) -> NDArray[np.float64]:
    """Exact sRGB decoding (IEC 61966-2-1) of encoded values in [0, 1] (any shape) -> linear values in [0, 1]."""
    c = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: NDArray) -> NDArray[np.float64]:
    """Exact sRGB encoding of linear values (any shape, clipped to [0, 1]) -> encoded values in [0, 1]."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


def _read_only(a: NDArray) -> NDArray:
    a.setflags(write=False)
    return a


_DECODE_LUT: F32 = _read_only(srgb_to_linear(np.arange(256) / 255.0).astype(np.float32))
"""(256,) linear value of every uint8 sRGB code."""

_ENCODE_THRESHOLDS: NDArray[np.float64] = _read_only(srgb_to_linear((np.arange(255) + 0.5) / 255.0))
"""(255,) linear value at which the rounded sRGB code steps from ``k`` to ``k + 1``."""

_ENC_BINS = 1 << 16
_ENC_EDGES = (np.arange(_ENC_BINS + 1, dtype=np.float64) - 0.5) / (_ENC_BINS - 1)
_ENC_SLACK = 0.01 / (_ENC_BINS - 1)  # float32 index rounding can move a value across a bin edge by far less
_ENCODE_LUT: U8 = _read_only(np.rint(255.0 * linear_to_srgb(np.arange(_ENC_BINS) / (_ENC_BINS - 1))).astype(np.uint8))
"""(65536,) sRGB code of the centre of each 1/65535-wide bin of linear values."""

_ENCODE_AMBIGUOUS: NDArray[np.bool_] = _read_only(
    np.searchsorted(_ENCODE_THRESHOLDS, _ENC_EDGES[:-1] - _ENC_SLACK, side="right")
    != np.searchsorted(_ENCODE_THRESHOLDS, _ENC_EDGES[1:] + _ENC_SLACK, side="right")
)
"""(65536,) bins that contain (or nearly touch) a code step: their pixels are rounded exactly, one by one."""


class SrgbTables(NamedTuple):
    """The exact sRGB tables a compiled kernel decodes and encodes with (`encode_srgb_u8`'s rule)."""

    decode: F32  # (256,) linear value of every code
    encode: U8  # (65536,) code of each linear bin
    ambiguous: NDArray[np.bool_]  # (65536,) bins rounded exactly, by the thresholds
    thresholds: NDArray[np.float64]  # (255,) linear code steps
    bins: int


SRGB_TABLES = SrgbTables(_DECODE_LUT, _ENCODE_LUT, _ENCODE_AMBIGUOUS, _ENCODE_THRESHOLDS, _ENC_BINS)


def decode_srgb_u8(image: U8) -> F32:
    """(H, W, 3) uint8 sRGB -> float32 linear RGB in [0, 1] (exact, by table)."""
    return _DECODE_LUT[image]


def encode_srgb_u8(linear: NDArray) -> U8:
    """Linear RGB (any shape, clipped to [0, 1]) -> uint8 sRGB codes, exactly rounded.

    A 65536-entry table gives the code; the few values in table bins that straddle a code step are rounded by
    comparing with the exact step thresholds, so the result equals ``round(255 * srgb(x))`` everywhere and every
    decoded code round-trips to itself (compiled: `weatheralign.camera.kernels.encode_srgb_kernel`).
    """
    x = np.ascontiguousarray(np.asarray(linear, dtype=np.float32))
    codes = encode_srgb_kernel(x.reshape(-1), _ENCODE_LUT, _ENCODE_AMBIGUOUS, _ENCODE_THRESHOLDS, _ENC_BINS)
    return codes.reshape(x.shape)


RANGE_SIGMA = 0.05
"""Relative ray-length difference over which a coarse layer sample stops counting for a pixel
(`range_guided_weights_naive`): a layer found for the road does not bleed onto the car in front of it."""


def range_guided_weights_naive(range_map: NDArray, stride: int, sigma: float = RANGE_SIGMA
                               ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """How each pixel of ``range_map`` (H, W) [m] (inf: sky) reads values given on its every ``stride``-th row and
    column: its 4 bilinear neighbours' (rows, cols) on the coarse grid (H, W, 4) and their weights (H, W, 4). Where the
    pixel lies on the surface its neighbours span (its ray length within ``sigma`` of their bilinear interpolation: a
    road seen at a grazing angle, whose ray length changes fast from row to row) the bilinear weights; across a depth
    edge they are times `weatheralign.camera.kernels.range_weight` (1 for sky to sky, 0 for sky to surface, ``exp(-(dl /
    (sigma l))^2)`` else), normalised; where they all vanish, the neighbour of nearest ray length alone; all 0 where no
    neighbour is sky for a sky pixel or surface for a surface pixel. The numpy oracle of
    `weatheralign.camera.kernels.guided_affine_edit_kernel`."""
    rng = np.asarray(range_map, dtype=np.float64)
    height, width = rng.shape
    h, w = -(-height // stride), -(-width // stride)
    iy, ix = np.arange(height), np.arange(width)
    y0, x0 = np.broadcast_arrays((iy // stride)[:, None], (ix // stride)[None, :])
    fy, fx = np.broadcast_arrays((iy % stride / stride)[:, None], (ix % stride / stride)[None, :])
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    rows = np.stack([y0, y0, y1, y1], axis=-1)
    cols = np.stack([x0, x1, x0, x1], axis=-1)
    weights = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=-1)
    coarse = rng[rows * stride, cols * stride]
    fine = rng[..., None]
    with np.errstate(invalid="ignore"):
        spanned = (weights * coarse).sum(axis=-1, keepdims=True)
        smooth = np.isfinite(spanned) & np.isfinite(fine) & (np.abs(spanned - fine) <= sigma * fine)
    same_kind = np.isinf(coarse) == np.isinf(fine)
    with np.errstate(invalid="ignore"):
        miss = np.where(np.isinf(fine), 0.0, np.abs(coarse - fine))
        ratio = np.where(np.isinf(fine), 0.0, miss / (sigma * np.maximum(fine, 1e-6)))
    weights = weights * np.where(smooth, 1.0, np.where(same_kind, np.exp(-ratio**2), 0.0))
    total = weights.sum(axis=-1, keepdims=True)
    miss = np.where(same_kind, miss, np.inf)
    nearest = np.argmin(miss, axis=-1)  # first of equals, as the kernel
    fallback = (np.arange(4) == nearest[..., None]) & np.isfinite(np.min(miss, axis=-1))[..., None]
    weights = np.where(total > 1e-12, weights / np.where(total > 1e-12, total, 1.0), fallback.astype(np.float64))
    return rows, cols, weights


def range_guided_upsample(values: NDArray, range_map: NDArray, stride: int, sigma: float = RANGE_SIGMA,
                          fill: float = 0.0) -> NDArray[np.float64]:
    """``values`` (h, w, ...) given on every ``stride``-th row and column of ``range_map`` (H, W) brought to every
    pixel (H, W, ...) by `range_guided_weights_naive`; ``fill`` where no neighbour counts."""
    rows, cols, weights = range_guided_weights_naive(range_map, stride, sigma)
    v = np.asarray(values, dtype=np.float64)[rows, cols]  # (H, W, 4, ...)
    wts = weights.reshape(weights.shape + (1,) * (v.ndim - 3))
    none = weights.sum(axis=-1) == 0
    out = (v * wts).sum(axis=2)
    out[none] = fill
    return out


def affine_edit_u8(image: U8, gain: NDArray, offset: NDArray, edited: NDArray, range_map: NDArray, stride: int = 1,
                   sigma: float = RANGE_SIGMA, alternative: tuple[NDArray, NDArray] | None = None,
                   switch: NDArray | None = None) -> tuple[U8, NDArray[np.bool_]]:
    """``encode_srgb_u8(decode_srgb_u8(image) * G + O)`` for a uint8 sRGB ``image`` (H, W, 3), with ``gain`` and
    ``offset`` (ceil(H / stride), ceil(W / stride), 3) in linear light and ``edited`` (same h, w) given on every
    ``stride``-th row and column of ``range_map`` (H, W) [m] and brought to each pixel as G, O and E by
    `range_guided_upsample` (gain 1 and offset 0 where no neighbour counts), in one compiled pass
    (`weatheralign.camera.kernels.guided_affine_edit_kernel`); returns the image and the pixels where E > 0.5.
    With ``alternative`` layers (gain, offset) and a finite ``switch`` field (h, w), the pixels where the brought
    ``switch`` exceeds 0 take the brought alternative instead (a boundary each pixel finds for itself)."""
    if (alternative is None) != (switch is None):
        raise ValueError("affine_edit_u8: give both alternative and switch, or neither")
    empty = np.zeros((0, 0, 3))
    alt_gain, alt_offset = alternative if alternative is not None else (empty, empty)
    return guided_affine_edit_kernel(np.ascontiguousarray(image, dtype=np.uint8),
                                     np.ascontiguousarray(gain, dtype=np.float64),
                                     np.ascontiguousarray(offset, dtype=np.float64),
                                     np.ascontiguousarray(edited, dtype=np.float64),
                                     _float_map(range_map), int(stride), float(sigma),
                                     np.ascontiguousarray(alt_gain, dtype=np.float64),
                                     np.ascontiguousarray(alt_offset, dtype=np.float64),
                                     np.ascontiguousarray(np.zeros((0, 0)) if switch is None else switch,
                                                          dtype=np.float64),
                                     _DECODE_LUT, _ENCODE_LUT, _ENCODE_AMBIGUOUS, _ENCODE_THRESHOLDS, _ENC_BINS)


def _float_map(values: NDArray) -> NDArray[np.floating]:
    """``values`` as a contiguous float32 or float64 array, not copied where it already is one."""
    a = np.asarray(values)
    return np.ascontiguousarray(a if a.dtype in (np.float32, np.float64) else a.astype(np.float64))


def _as_srgb_float(image: NDArray, what: str = "image") -> F32:
    """(H, W, 3) uint8 or float sRGB in [0, 1] -> float32 sRGB in [0, 1]."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{what}: expected an (H, W, 3) RGB image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float32) * np.float32(1.0 / 255.0)
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{what}: expected uint8 or float RGB, got {a.dtype}")
    return np.clip(a, 0.0, 1.0).astype(np.float32)


# ------------------------------------------------------------------------------------------------ airlight


def _check_airlight(airlight: NDArray | Sequence[float] | float) -> NDArray[np.float64]:
    A = np.broadcast_to(np.asarray(airlight, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(A)) or np.any(A < 0.0) or np.any(A > 1.0):
        raise ValueError(f"airlight {A.tolist()} is invalid: expected an sRGB colour (3,) with values in [0, 1]")
    return A


def dark_channel(image: NDArray, window: int = DARK_CHANNEL_WINDOW) -> F32:
    """(H, W) float32 dark channel of an sRGB image (uint8 or float [0, 1]): channel minimum, then a ``window``-px
    square minimum filter (He et al. 2009)."""
    rgb = _as_srgb_float(image)
    return cv2.erode(rgb.min(axis=2), np.ones((window, window), np.uint8), borderType=cv2.BORDER_REPLICATE)


def estimate_airlight(
    images: Sequence[NDArray],
    ranges: Sequence[NDArray | None] | None = None,
    *,
    neutral: bool = True,
) -> NDArray[np.float64]:
    """One airlight for a whole scene, pooled over all its cameras: `sky_airlight`, or the neutral grey
    `NEUTRAL_AIRLIGHT` where the scene shows no sky.

    Args:
        images: the scene's camera images, each (H, W, 3) uint8 sRGB or float sRGB in [0, 1] (sizes may differ).
        ranges: None, or one entry per image: (H, W) ray length [m] with ``inf`` for sky, or None where unknown.
        neutral: (default) return a grey of the estimate's luminance (Rec. 709 weights in linear light), not its colour
            (fog's airlight is ambient light scattered by droplets: nearly neutral even under a blue sky).

    Returns:
        (3,) float64 sRGB-encoded airlight in [0, 1] (decode with `srgb_to_linear` for radiance).
    """
    A = sky_airlight(images, ranges, neutral=neutral)
    return np.full(3, NEUTRAL_AIRLIGHT) if A is None else A


def sky_airlight(
    images: Sequence[NDArray],
    ranges: Sequence[NDArray | None] | None = None,
    *,
    neutral: bool = True,
) -> NDArray[np.float64] | None:
    """The airlight of a scene's visible sky, or None where it shows none.

    Rules, in order:
      1. Where a range map is known (synthetic world: exact; real data: `weatheralign.camera.depth.dense_depth`),
         its unsaturated sky pixels (``+inf``, every channel below `CLIPPED`) of **all** cameras are pooled and the
         airlight is their per-channel median colour, if there are at least `SKY_MIN_PIXELS` of them.
      2. Otherwise, over the images without a range map: the dark channel (`dark_channel`) of the upper half of every
         image (sky is above the horizon of a level camera) is pooled over its unsaturated pixels, the top 0.1 %
         brightest are the candidates and the airlight is their per-channel median colour; if even those are dark
         (dark channel below `DARK_CHANNEL_MIN_SKY`) the scene shows no sky.
      3. No sky (range maps without enough unsaturated sky pixels, or rule 2's dark candidates): None.

    Saturated pixels never vote, so the airlight is never clipped white: an overexposed sky (real cameras' clouds)
    says only that the sky is brighter than the sensor's range, not how bright fog would be.

    Args and the returned colour: as `estimate_airlight`.
    """
    if len(images) == 0:
        raise ValueError("estimate_airlight: no images")
    if ranges is not None and len(ranges) != len(images):
        raise ValueError(f"estimate_airlight: {len(ranges)} range maps for {len(images)} images")
    rngs: list[NDArray | None] = list(ranges) if ranges is not None else [None] * len(images)
    sky_colours: list[F32] = []
    unknown: list[F32] = []
    for k, (img, rng) in enumerate(zip(images, rngs)):
        rgb = _as_srgb_float(img, f"image {k}")
        if rng is None:
            unknown.append(rgb)
            continue
        r = np.asarray(rng)
        if r.shape != rgb.shape[:2]:
            raise ValueError(f"estimate_airlight: range map {k} has shape {r.shape}, image {rgb.shape[:2]}")
        sky = rgb[np.isposinf(r)]
        sky_colours.append(sky[sky.max(axis=1) < CLIPPED])
    sky = np.concatenate(sky_colours) if sky_colours else np.zeros((0, 3), np.float32)
    if len(sky) >= SKY_MIN_PIXELS:
        A = np.median(sky, axis=0).astype(np.float64)
    elif unknown:
        A = _dark_channel_airlight(unknown)
    else:
        A = None
    if A is None:
        return None
    if neutral:
        A = np.full(3, float(linear_to_srgb(airlight_luminance(A))))
    return A


def airlight_luminance(airlight: NDArray | Sequence[float]) -> float:
    """Linear-light luminance (Rec. 709 weights) of an sRGB-encoded airlight (3,)."""
    return float(np.dot([0.2126, 0.7152, 0.0722], srgb_to_linear(_check_airlight(airlight))))


def airlight_gains(fog_airlights: Sequence[NDArray | None], clear_airlights: Sequence[NDArray | None]
                   ) -> tuple[float, ...]:
    """How bright a fog's airlight is relative to the clear sky of the same camera: each foggy frame's airlight
    luminance over the median clear-sky luminance, in linear light (sorted ascending).

    Airlight is the ambient light that the droplets scatter: it depends on the day's illumination, not on the clear
    scene's sky, and a reference recorded in fog shows how it spreads from frame to frame. Frames without visible
    sky (None) do not vote; no vote on either side gives ``(1.0,)`` (the clear sky's own airlight).

    Args:
        fog_airlights: per foggy reference frame, `sky_airlight` of its image (or None).
        clear_airlights: per clear reference frame of the same camera, `sky_airlight` (or None).
    """
    fog = [airlight_luminance(a) for a in fog_airlights if a is not None]
    clear = [airlight_luminance(a) for a in clear_airlights if a is not None]
    if not fog or not clear or float(np.median(clear)) <= 0.0:
        return (1.0,)
    base = float(np.median(clear))
    return tuple(sorted(y / base for y in fog))


def fog_airlight(airlight: NDArray | Sequence[float], gain: float) -> NDArray[np.float64]:
    """(3,) linear-light airlight of a fog whose airlight is ``gain`` times the scene's sRGB ``airlight``
    (`airlight_gains`), capped at the sRGB code `CLIPPED` so that fog is never white."""
    if not (math.isfinite(gain) and gain > 0.0):
        raise ValueError(f"fog_airlight: gain = {gain!r}; expected a finite factor > 0")
    return np.minimum(srgb_to_linear(_check_airlight(airlight)) * float(gain), float(srgb_to_linear(CLIPPED)))


def _dark_channel_airlight(images: Sequence[F32]) -> NDArray[np.float64] | None:
    """Median colour of the top 0.1 % dark-channel pixels pooled over the unsaturated pixels of the upper halves of
    ``images``; None = no sky."""
    dcs, cols = [], []
    for rgb in images:
        top = rgb[: max(1, rgb.shape[0] // 2)]
        unsaturated = top.max(axis=2).ravel() < CLIPPED
        dcs.append(dark_channel(top).ravel()[unsaturated])
        cols.append(top.reshape(-1, 3)[unsaturated])
    dc, col = np.concatenate(dcs), np.concatenate(cols)
    if len(dc) == 0:
        return None
    n = max(1, int(math.ceil(DARK_CHANNEL_TOP_FRACTION * len(dc))))
    top_idx = np.argpartition(-dc, n - 1)[:n]
    if float(np.median(dc[top_idx])) < DARK_CHANNEL_MIN_SKY:
        return None
    return np.median(col[top_idx], axis=0).astype(np.float64)


# ------------------------------------------------------------------------------------------------ transmission


def transmission(range_map: NDArray, alpha: float) -> F32:
    """(H, W) float32 one-way transmittance ``exp(-alpha * l)`` of ray lengths ``range_map`` (H, W) [m].

    ``l = inf`` (sky) gives 0 for ``alpha > 0``; ``alpha = 0`` gives exactly 1 everywhere (also for the sky).

    Raises:
        ValueError: ``alpha`` negative or not finite; a NaN or negative range.
    """
    a = float(alpha)
    if not math.isfinite(a) or a < 0.0:
        raise ValueError(f"alpha = {alpha!r} [1/m] is invalid: must be finite and >= 0 (0 means no fog)")
    r = np.asarray(range_map, dtype=np.float32)
    if r.ndim != 2:
        raise ValueError(f"range map: expected (H, W), got shape {r.shape}")
    if np.isnan(r).any() or (r < 0).any():
        raise ValueError("range map: NaN or negative ray lengths; expected lengths >= 0 [m] with inf for sky")
    if a == 0.0:
        return np.ones(r.shape, np.float32)
    return np.exp(np.float32(-a) * r)


def _box(x: NDArray, radius: int) -> NDArray:
    k = 2 * radius + 1
    return cv2.boxFilter(x, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def guided_coefficients(I: F32, p: F32, r: int, eps: float) -> F32:
    """He's guided-filter coefficients of ``p`` (h, w) with guide ``I`` (h, w) grey or (h, w, 3) colour: the
    box-averaged local linear model, (h, w, 2) ``(a, b)`` or (h, w, 4) ``(a_r, a_g, a_b, b)``, radius ``r`` [px]."""
    mean_p = _box(p, r)
    if I.ndim == 2:
        mean_I = _box(I, r)
        a = (_box(I * p, r) - mean_I * mean_p) / (_box(I * I, r) - mean_I * mean_I + np.float32(eps))
        return np.dstack([_box(a, r), _box(mean_p - a * mean_I, r)])
    m = _box(I, r)
    cov = [_box(I[..., k] * p, r) - m[..., k] * mean_p for k in range(3)]

    def var(i: int, j: int) -> F32:
        return _box(I[..., i] * I[..., j], r) - m[..., i] * m[..., j]

    e = np.float32(eps)
    s11, s12, s13 = var(0, 0) + e, var(0, 1), var(0, 2)
    s22, s23, s33 = var(1, 1) + e, var(1, 2), var(2, 2) + e
    # inverse of the symmetric 3x3 covariance by cofactors (vectorised over pixels)
    c11, c12, c13 = s22 * s33 - s23 * s23, s13 * s23 - s12 * s33, s12 * s23 - s13 * s22
    c22, c23, c33 = s11 * s33 - s13 * s13, s12 * s13 - s11 * s23, s11 * s22 - s12 * s12
    det = s11 * c11 + s12 * c12 + s13 * c13
    ax = (c11 * cov[0] + c12 * cov[1] + c13 * cov[2]) / det
    ay = (c12 * cov[0] + c22 * cov[1] + c23 * cov[2]) / det
    az = (c13 * cov[0] + c23 * cov[1] + c33 * cov[2]) / det
    b = mean_p - ax * m[..., 0] - ay * m[..., 1] - az * m[..., 2]
    return np.dstack([_box(ax, r), _box(ay, r), _box(az, r), _box(b, r)])


def _downsampled(I_full: NDArray, p_full: F32, radius: int, subsample: int) -> tuple[NDArray, F32, int, int]:
    """Guide, source and radius at the coefficient resolution (area-averaged by ``subsample``), and the divisor
    actually used (1 for images smaller than ``4 * subsample``)."""
    h, w = p_full.shape
    s = max(1, int(subsample))
    if s > 1 and min(h, w) >= 4 * s:
        size = (max(1, w // s), max(1, h // s))
        I = cv2.resize(I_full, size, interpolation=cv2.INTER_AREA)
        p = cv2.resize(p_full, size, interpolation=cv2.INTER_AREA)
        return I, p, max(1, int(round(radius / s))), s
    return I_full, p_full, int(radius), 1


def guided_filter(guide: NDArray, src: NDArray, radius: int, eps: float, subsample: int = 1) -> F32:
    """He's guided filter of ``src`` (H, W) with a grey (H, W) or colour (H, W, 3) float ``guide``.

    ``radius`` [px] is the full-resolution radius (window ``2 r + 1``); ``eps`` is in squared guide units.
    ``subsample`` > 1 computes the local linear coefficients on an area-downsampled copy (radius ``r / s``) and
    upsamples them bilinearly (He & Sun 2015, "fast guided filter"). Box means use OpenCV, reflected borders.

    Returns:
        (H, W) float32 filtered ``src``.
    """
    I_full = np.asarray(guide, dtype=np.float32)
    p_full = np.asarray(src, dtype=np.float32)
    h, w = p_full.shape
    if I_full.shape[:2] != (h, w):
        raise ValueError(f"guided_filter: guide {I_full.shape} and src {p_full.shape} differ in size")
    I, p, r, s = _downsampled(I_full, p_full, radius, subsample)
    coeffs = guided_coefficients(I, p, r, eps)
    if s > 1:
        coeffs = cv2.resize(coeffs, (w, h), interpolation=cv2.INTER_LINEAR)
    if I_full.ndim == 2:
        return (coeffs[..., 0] * I_full + coeffs[..., 1]).astype(np.float32)
    out = coeffs[..., 3] + coeffs[..., 0] * I_full[..., 0] + coeffs[..., 1] * I_full[..., 1]
    out += coeffs[..., 2] * I_full[..., 2]
    return out.astype(np.float32)


def refine_transmission(
    t: NDArray,
    guide_image: NDArray,
    radius: int = GUIDED_RADIUS,
    eps: float = GUIDED_EPS,
    subsample: int = GUIDED_SUBSAMPLE,
) -> F32:
    """Guided-filter transmittance ``t`` (H, W) with the clear image as guide, clipped to [0, 1].

    Args:
        t: (H, W) transmittance in [0, 1].
        guide_image: (H, W, 3) clear image, uint8 sRGB or float sRGB in [0, 1] (colour guide).
        radius: window radius [px] at full resolution (20: a 41 x 41 window).
        eps: regulariser in squared guide units (1e-3: edges with a guide contrast above ~0.03 are kept).
        subsample: coefficient resolution divisor (1 = exact filter; 2 = default, see module docstring).

    Returns:
        (H, W) float32 refined transmittance in [0, 1].
    """
    guide = _as_srgb_float(guide_image, "guide image")
    return np.clip(guided_filter(guide, t, radius, eps, subsample), 0.0, 1.0)


# ------------------------------------------------------------------------------------------------ fog


def fog_image(
    image: NDArray,
    range_map: NDArray,
    alpha: float,
    airlight: NDArray | Sequence[float] | float,
    refine: bool = True,
    *,
    linear_input: bool = False,
) -> U8:
    """Koschmieder fog on a clear image.

    ``I = J t + A (1 - t)`` in linear RGB with ``t = exp(-alpha l)``, ``l`` the ray length per pixel.

    Args:
        image: (H, W, 3) clear image: uint8 sRGB, or float in [0, 1] (sRGB-encoded, or linear with
            ``linear_input=True``).
        range_map: (H, W) ray length from the camera centre [m], ``inf`` for sky (not z-depth).
        alpha: extinction [1/m] of the fog medium (``FogMedium.camera_extinction``), >= 0.
        airlight: sRGB-encoded airlight in [0, 1], (3,) or a grey scalar: the scene's one value from
            `estimate_airlight`.
        refine: smooth ``t`` with the guided filter (`refine_transmission`, clear image as guide).
        linear_input: the float ``image`` holds linear radiance instead of sRGB code values.

    Returns:
        (H, W, 3) uint8 sRGB fogged image. With ``alpha = 0`` a uint8 input is returned unchanged (a bitwise copy).
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image: expected (H, W, 3) RGB, got shape {img.shape}")
    rng = np.asarray(range_map)
    if rng.shape != img.shape[:2]:
        raise ValueError(f"range map shape {rng.shape} != image {img.shape[:2]}")
    A_lin = srgb_to_linear(_check_airlight(airlight)).astype(np.float32)
    t = transmission(rng, alpha)
    if float(alpha) == 0.0:
        if img.dtype == np.uint8:
            return img.copy()
        return encode_srgb_u8(img if linear_input else srgb_to_linear(_as_srgb_float(img)))
    if img.dtype == np.uint8:
        J = decode_srgb_u8(img)
    elif linear_input:
        J = np.clip(img, 0.0, 1.0).astype(np.float32)
    else:
        J = srgb_to_linear(_as_srgb_float(img)).astype(np.float32)
    if refine:
        t = refine_transmission(t, img if not linear_input else encode_srgb_u8(J), GUIDED_RADIUS, GUIDED_EPS)
    return encode_srgb_u8(composite(J, t, A_lin))


def composite(linear: F32, t: F32, airlight_linear: NDArray) -> F32:
    """Koschmieder compositing in linear light: ``J t + A (1 - t)``.

    Args:
        linear: (H, W, 3) float32 linear radiance of the clear scene.
        t: (H, W) float32 transmittance in [0, 1] (fog, unresolved particles, or their product).
        airlight_linear: (3,) linear airlight.

    Returns:
        (H, W, 3) float32 linear radiance seen through the medium. The one compositing rule of every camera medium.
    """
    t3 = t[..., None]
    return linear * t3 + np.asarray(airlight_linear).astype(np.float32) * (np.float32(1.0) - t3)


def composite_image(image: U8, t: F32, airlight_linear: NDArray, refine: bool = True, *,
                    subsample: int = GUIDED_SUBSAMPLE, encode: bool = True) -> NDArray:
    """The one camera-medium step of the simulator, compiled: Koschmieder compositing of a clear uint8 sRGB
    ``image`` (H, W, 3) through the transmittance ``t`` (H, W) float32, with ``t`` guided-filtered first (the image
    as guide, `refine_transmission`'s window and ``eps``) when ``refine``.

    Equals ``encode_srgb_u8(composite(decode_srgb_u8(image), refine_transmission(t, image, subsample=subsample),
    A))`` (or the linear result before encoding when not ``encode``) up to float32 rounding: the coefficients come
    from `guided_coefficients` at ``1 / subsample`` resolution and one kernel upsamples them, applies them,
    composites and encodes per pixel (`weatheralign.camera.kernels`), instead of a dozen full-resolution passes.

    Returns:
        (H, W, 3) uint8 sRGB when ``encode``, else float32 linear radiance.
    """
    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image: expected (H, W, 3) uint8 sRGB, got {img.dtype} {img.shape}")
    t32 = np.ascontiguousarray(t, dtype=np.float32)
    if t32.shape != img.shape[:2]:
        raise ValueError(f"transmittance shape {t32.shape} != image {img.shape[:2]}")
    A = np.asarray(airlight_linear, dtype=np.float32).reshape(3)
    codes = np.empty(img.shape, np.uint8) if encode else np.empty((0, 0, 3), np.uint8)
    linear = np.empty((0, 0, 3), np.float32) if encode else np.empty(img.shape, np.float32)
    tables = (_ENCODE_LUT, _ENCODE_AMBIGUOUS, _ENCODE_THRESHOLDS, _ENC_BINS)
    if refine:
        I, p, r, _ = _downsampled(_as_srgb_float(img, "guide image"), t32, GUIDED_RADIUS, subsample)
        coeffs = np.ascontiguousarray(guided_coefficients(I, p, r, GUIDED_EPS), dtype=np.float32)
        composite_guided_kernel(img, coeffs, A, _DECODE_LUT, linear, codes, encode, *tables)
    else:
        composite_plain_kernel(img, t32, A, _DECODE_LUT, linear, codes, encode, *tables)
    return codes if encode else linear
