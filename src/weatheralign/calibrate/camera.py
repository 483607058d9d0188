"""ReDAM for the camera: fog severity (extinction, visibility) of foggy images from the image and its range map.

The camera sees the fog through Koschmieder's law on linear radiance, ``I = J t + A (1 - t)``, ``t = exp(-α ℓ)``
with ``ℓ`` the ray length (`weatheralign.camera.fog`). For a real reference image only the foggy image and a range
map are known (its clear version ``J`` is not), so the estimator uses nothing else.

Estimator (`estimate_fog_severity`): **local contrast decay with distance**. ``I - A = (J - A) exp(-α ℓ)``, so on
a surface of uniform albedo, ``ln|A - I|`` falls linearly with ``ℓ`` at slope ``-α``, whatever the albedo.
1. Airlight ``A`` (linear RGB): the median colour of the sky pixels (``ℓ = inf`` or the sky mask) when there are at
   least `SKY_MIN_PIXELS`, else a given (e.g. pooled per set, `severity_of_set`) value, else the median colour of
   the brightest 0.1 % of the dark channel (unreliable without sky: bright objects then pass for fog).
2. The image is reduced to `WORK_WIDTH` columns (area average in linear light, where Koschmieder's law is linear;
   the range map by nearest sampling).
3. In every ``(2r+1)²`` window (r = `WINDOW_RADIUS`, stride r) and colour channel, ``ln|A_c - I_c|`` is fitted by
   least squares against ``ℓ`` (`window_slopes`). A window is used only where it is fully valid (no sky, no unknown
   depth, ``ℓ >=`` `MIN_RANGE_M`, no saturated pixel, ``|A - I| >`` `NOISE_FRACTION` · A everywhere: 8-bit
   quantisation), lies on one surface (``max ℓ / min ℓ <=`` `MAX_RANGE_RATIO`: no depth edge; the inverse ray
   length affine in the pixel coordinates to `MAX_PLANE_RESIDUAL`: no crease such as a road-facade junction, where
   two albedos meet at systematically different depths), spans some depth (std ``ℓ >=`` `MIN_RANGE_STD_M`) and is
   homogeneous (residual std ``<=`` `MAX_RESIDUAL`: no albedo edge). Both ``ln``-based tests are invariant to the
   fog (it scales ``A - I`` by ``t``), so the same windows qualify at every density.
4. ``α̂`` is the median of the fits' ``-slope`` (channels pooled; at least `MIN_WINDOWS`), visibility
   ``V = ln 20 / α̂``. A set of images pools the fits of all its images before the median (`aggregate_severity`):
   more robust than a median of per-image estimates, which scatter by ~20 % on single street images.

Accuracy (median over a set, fog by `weatheralign.camera.fog.fog_image` with the guided filter, one airlight):
18 synthetic-world images of all six cameras, α = 0.005 / 0.01 / 0.02 / 0.04 / 0.08: 1.18 / 1.09 / 1.04 / 1.01 /
1.00 x α; 8 procedural street images (tests): 1.00 / 1.01 / 0.97 / 0.94 / 0.93 x α. The floor: clear images give
``|α̂| <~ 0.0015 /m`` (texture and shading that happen to correlate with depth), so light fog (α <~ 0.01, MOR
>~ 300 m, which changes a street image little) is estimated less precisely than dense fog.

Why not the dark-channel prior: ``t = 1 - dark(I / A)`` followed by a regression of ``-ln t`` (or of a per-distance
quantile of ``ln(A - dark(I))``) on ``ℓ`` assumes that the darkest surfaces do not depend on distance. On the
synthetic world's street images (asphalt and pale pavements near, dark windows and trees far) it returned
0.4-0.77 x the true α (median over 10 images, α = 0.005-0.08).

Agreement of a simulated and a reference fog level (`camera_visibility_ratio`): ``V_sim / V_ref`` with ``V`` from
each set's pooled ``α̂`` (the target is within 20 % of 1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.fog import decode_srgb_u8, linear_to_srgb, srgb_to_linear
from weatheralign.medium.fog import LN20

F64 = NDArray[np.float64]

WORK_WIDTH = 400
"""Columns of the working image [px] (the window sizes below refer to it)."""

WINDOW_RADIUS = 8
"""Window radius r [working px]: (2r+1)² windows, placed every r pixels."""

MIN_RANGE_M = 3.0
"""Nearest ray length used [m]."""

NOISE_FRACTION = 0.03
"""Smallest usable ``|A - I| / A`` (below it 8-bit quantisation dominates the logarithm)."""

MAX_RANGE_RATIO = 1.6
"""Largest ``max ℓ / min ℓ`` in a window (larger: a depth edge)."""

MIN_RANGE_STD_M = 0.3
"""Smallest standard deviation of ``ℓ`` in a window [m] (smaller: no slope to measure)."""

MAX_RESIDUAL = 0.15
"""Largest residual standard deviation of ``ln|A - I|`` about a window's line (larger: an albedo edge)."""

MAX_PLANE_RESIDUAL = 0.01
"""Largest residual std of an affine fit of the inverse ray length in a window, relative to its mean (larger: not
one plane)."""

MIN_WINDOWS = 10
"""Fewest accepted windows for an estimate (fewer: NaN)."""

SKY_MIN_PIXELS = 100
"""Fewest sky pixels (full resolution) for a sky airlight."""

DARK_CHANNEL_WINDOW = 15
"""Minimum-filter window [working px] of the dark-channel airlight fallback."""


@dataclass(frozen=True)
class FogSeverity:
    """Fog severity estimated from one image.

    Attributes:
        alpha: estimated extinction α̂ [1/m] (NaN: too few usable windows).
        visibility: ``ln 20 / α̂`` [m] (inf for α̂ <= 0, NaN when α̂ is).
        airlight: (3,) sRGB-encoded airlight in [0, 1] used.
        airlight_source: ``"sky"``, ``"given"`` or ``"dark_channel"``.
        window_alphas: (K,) the accepted (window, channel) fits' ``-slope`` [1/m] (α̂ is their median; a set pools
            them, `aggregate_severity`).
    """

    alpha: float
    visibility: float
    airlight: F64
    airlight_source: str
    window_alphas: F64

    @property
    def num_windows(self) -> int:
        """Accepted (window, channel) fits."""
        return len(self.window_alphas)


def _visibility(alpha: float) -> float:
    if not math.isfinite(alpha):
        return math.nan
    return math.inf if alpha <= 0.0 else LN20 / alpha


def _check_inputs(image: NDArray, range_map: NDArray, sky_mask: NDArray | None) -> tuple[NDArray, F64, NDArray]:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image: expected (H, W, 3) uint8 sRGB, got {img.dtype} {img.shape}")
    rng = np.asarray(range_map, dtype=np.float64)
    if rng.shape != img.shape[:2]:
        raise ValueError(f"range_map: shape {rng.shape} != image {img.shape[:2]}; expected the (H, W) ray length [m]")
    if (rng < 0).any():
        raise ValueError("range_map: negative ray lengths; expected lengths >= 0 [m], inf for sky, NaN for unknown")
    sky = np.isposinf(rng)
    if sky_mask is not None:
        m = np.asarray(sky_mask)
        if m.shape != img.shape[:2]:
            raise ValueError(f"sky_mask: shape {m.shape} != image {img.shape[:2]}; expected an (H, W) boolean mask")
        sky = sky | m.astype(bool)
    return img, rng, sky


def _dark_channel_airlight(lin: NDArray) -> F64:
    """(3,) linear median colour of the brightest 0.1 % of the dark channel."""
    dc = cv2.erode(lin.min(axis=2).astype(np.float32), np.ones((DARK_CHANNEL_WINDOW,) * 2, np.uint8),
                   borderType=cv2.BORDER_REPLICATE)
    n = max(1, int(math.ceil(1e-3 * dc.size)))
    top = np.argpartition(-dc.ravel(), n - 1)[:n]
    return np.median(lin.reshape(-1, 3)[top], axis=0).astype(np.float64)


def _box_sum(x: NDArray, r: int) -> NDArray:
    return cv2.boxFilter(x, -1, (2 * r + 1, 2 * r + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)


def _reduce(img: NDArray, rng: F64, sky: NDArray, width: int) -> tuple[F64, F64, NDArray, NDArray]:
    """Working-resolution linear image (h, w, 3), range (h, w), sky and saturation masks."""
    h0, w0 = rng.shape
    lin = decode_srgb_u8(img).astype(np.float32)
    saturated = (img == 255).any(axis=2).astype(np.float32)
    if w0 > width:
        size = (int(width), max(1, int(round(h0 * width / w0))))
        lin = cv2.resize(lin, size, interpolation=cv2.INTER_AREA)
        saturated = cv2.resize(saturated, size, interpolation=cv2.INTER_AREA)
        sky_f = cv2.resize(sky.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        rows = ((np.arange(size[1]) + 0.5) * h0 / size[1]).astype(np.int64).clip(0, h0 - 1)
        cols = ((np.arange(size[0]) + 0.5) * w0 / size[0]).astype(np.int64).clip(0, w0 - 1)
        rng = rng[np.ix_(rows, cols)]
        sky = sky_f > 0.0
    return lin.astype(np.float64), rng, sky, saturated > 0.0


def _plane_residual(inv: F64, r: int) -> F64:
    """Per window: residual std of an affine fit of ``inv`` (inverse ray length) in the pixel coordinates, relative
    to the window's mean (one plane: ~0; a crease such as a road-facade junction or a kerb: larger)."""
    h, w = inv.shape
    area = float((2 * r + 1) ** 2)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    s = _box_sum(inv, r) / area
    su = _box_sum(inv * u, r) / area - s * u  # centred first moments (full windows: mean of u - u_c is 0)
    sv = _box_sum(inv * v, r) / area - s * v
    var_c = r * (r + 1) / 3.0  # variance of the centred coordinate over a (2r+1)² window
    var = _box_sum(inv * inv, r) / area - s * s
    resid = np.maximum(var - (su * su + sv * sv) / var_c, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(resid) / s


@dataclass(frozen=True)
class WindowSlopes:
    """The accepted (window, channel) fits of one working image.

    Attributes:
        slope: (K,) ``-d ln|A - I| / d ℓ`` per fit [1/m] (each an estimate of α).
        range_m: (K,) mean ray length of the window [m].
        row, col: (K,) window centre [working px]; channel: (K,) 0, 1, 2.
    """

    slope: F64
    range_m: F64
    row: NDArray[np.int64]
    col: NDArray[np.int64]
    channel: NDArray[np.int64]


def window_slopes(lin: F64, range_map: F64, excluded: NDArray, airlight_linear: F64, radius: int = WINDOW_RADIUS,
                  min_range: float = MIN_RANGE_M) -> WindowSlopes:
    """Fit ``ln|A_c - I_c|`` against ``ℓ`` in every accepted window (module docstring, step 3).

    Args:
        lin: (h, w, 3) linear RGB image; range_map: (h, w) ray lengths [m] (non-finite: unusable);
        excluded: (h, w) bool, pixels never used (sky, saturated); airlight_linear: (3,) linear airlight;
        radius: window radius r [px] (windows every r px); min_range: nearest usable ray length [m].
    """
    A = np.asarray(airlight_linear, dtype=np.float64)
    r = int(radius)
    ok = np.isfinite(range_map) & (range_map >= float(min_range)) & ~excluded
    ell = np.where(ok, range_map, 0.0)
    area = float((2 * r + 1) ** 2)
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    l_max = cv2.dilate(ell.astype(np.float32), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    l_min = cv2.erode(np.where(ok, ell, np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_CONSTANT,
                      borderValue=np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        base = (_box_sum(ok.astype(np.float64), r) > area - 0.5) & (l_max <= MAX_RANGE_RATIO * l_min)
        s_l = _box_sum(ell, r) / area
        var_l = _box_sum(ell * ell, r) / area - s_l * s_l
        base &= var_l >= MIN_RANGE_STD_M ** 2
        base &= _plane_residual(np.where(ok, 1.0 / np.maximum(ell, 1e-6), 0.0), r) <= MAX_PLANE_RESIDUAL
    grid = np.zeros(ok.shape, bool)
    grid[::r, ::r] = True
    out: list[tuple[F64, F64, NDArray, NDArray, NDArray]] = []
    for c in range(3):
        diff = np.abs(A[c] - lin[..., c])
        okc = ok & (diff > NOISE_FRACTION * A[c])
        y = np.where(okc, np.log(np.maximum(diff, 1e-12)), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_y = _box_sum(y, r) / area
            cov = _box_sum(y * ell, r) / area - s_y * s_l
            var_y = _box_sum(y * y, r) / area - s_y * s_y
            slope = cov / var_l
            resid = var_y - slope * cov
            accept = base & (_box_sum(okc.astype(np.float64), r) > area - 0.5) & (resid <= MAX_RESIDUAL ** 2)
        rows, cols = np.nonzero(accept & grid)
        out.append((-slope[rows, cols], s_l[rows, cols], rows, cols, np.full(len(rows), c)))
    return WindowSlopes(*(np.concatenate([o[k] for o in out]) for k in range(5)))


def estimate_fog_severity(
    image: NDArray,
    range_map: NDArray,
    *,
    sky_mask: NDArray | None = None,
    airlight: NDArray | Sequence[float] | float | None = None,
    work_width: int = WORK_WIDTH,
    window_radius: int = WINDOW_RADIUS,
    min_range: float = MIN_RANGE_M,
) -> FogSeverity:
    """Extinction and visibility of the fog in one image (module docstring: local contrast decay with distance).

    Args:
        image: (H, W, 3) uint8 sRGB foggy image.
        range_map: (H, W) ray length per pixel [m]: ``inf`` for sky, NaN where unknown (not z-depth).
        sky_mask: optional (H, W) bool, True on sky (in addition to ``inf`` ranges).
        airlight: sRGB-encoded airlight ((3,) or grey scalar in [0, 1]) to use when the image shows fewer than
            `SKY_MIN_PIXELS` sky pixels; None: dark-channel fallback there. Sky pixels, when present, always win.
        work_width: columns of the working resolution.
        window_radius: r of the (2r+1)² fitting windows at the working resolution.
        min_range: nearest usable ray length [m].

    Raises:
        ValueError: not a uint8 RGB image, range map / sky mask of another shape, negative ranges, bad airlight.
    """
    img, rng, sky = _check_inputs(image, range_map, sky_mask)
    if int(sky.sum()) >= SKY_MIN_PIXELS:
        A = np.median(decode_srgb_u8(img[sky]).astype(np.float64), axis=0)
        source = "sky"
    elif airlight is not None:
        a = np.broadcast_to(np.asarray(airlight, dtype=np.float64), (3,))
        if not (np.isfinite(a).all() and (a > 0).all() and (a <= 1).all()):
            raise ValueError(f"airlight = {airlight!r}; expected an sRGB colour (3,) or grey with values in (0, 1]")
        A = srgb_to_linear(a)
        source = "given"
    else:
        A = None
        source = "dark_channel"
    lin, rng, sky, saturated = _reduce(img, rng, sky, int(work_width))
    if A is None:
        A = _dark_channel_airlight(lin)
    slopes = window_slopes(lin, rng, sky | saturated, A, int(window_radius), float(min_range)).slope
    alpha = float(np.median(slopes)) if len(slopes) >= MIN_WINDOWS else math.nan
    return FogSeverity(alpha=alpha, visibility=_visibility(alpha), airlight=linear_to_srgb(A),
                       airlight_source=source, window_alphas=slopes)


# ------------------------------------------------------------------------------------------------ sets of images


@dataclass(frozen=True)
class SetSeverity:
    """Fog severity of a set of images (one fog level of one dataset).

    Attributes:
        alpha: median of the window fits pooled over all images with an estimate [1/m] (NaN if none; more robust
            than the median of per-image medians); visibility: ``ln 20 / alpha`` [m].
        images: per-image `FogSeverity`.
        airlight: the pooled sky airlight of the set (sRGB) given to images without sky, or None.
    """

    alpha: float
    visibility: float
    images: tuple[FogSeverity, ...]
    airlight: F64 | None

    @property
    def num_estimated(self) -> int:
        """Images with a finite α̂."""
        return sum(math.isfinite(s.alpha) for s in self.images)


def aggregate_severity(severities: Sequence[FogSeverity], airlight: F64 | None = None) -> SetSeverity:
    """`SetSeverity` of per-image estimates (the flow may map `estimate_fog_severity` per image)."""
    pooled = [s.window_alphas for s in severities if math.isfinite(s.alpha)]
    alpha = float(np.median(np.concatenate(pooled))) if pooled else math.nan
    return SetSeverity(alpha=alpha, visibility=_visibility(alpha), images=tuple(severities), airlight=airlight)


def pooled_sky_airlight(images: Sequence[NDArray], ranges: Sequence[NDArray],
                        sky_masks: Sequence[NDArray | None] | None = None) -> F64 | None:
    """(3,) sRGB median colour of the sky pixels pooled over a set (subsampled to <= 20 000 per image), or None."""
    masks = [None] * len(images) if sky_masks is None else list(sky_masks)
    pooled = []
    for img, rng, m in zip(images, ranges, masks):
        im, _, sky = _check_inputs(img, rng, m)
        px = im[sky]
        if len(px) > 20_000:
            px = px[:: int(math.ceil(len(px) / 20_000))]
        pooled.append(px)
    px = np.concatenate(pooled) if pooled else np.zeros((0, 3), np.uint8)
    if len(px) < SKY_MIN_PIXELS:
        return None
    return linear_to_srgb(np.median(decode_srgb_u8(px).astype(np.float64), axis=0))


def severity_of_set(
    images: Sequence[NDArray],
    ranges: Sequence[NDArray],
    sky_masks: Sequence[NDArray | None] | None = None,
    **kwargs: object,
) -> SetSeverity:
    """Per-image `estimate_fog_severity` with the set's pooled sky airlight for images without sky.

    Raises:
        ValueError: no images, or different numbers of images, range maps and sky masks.
    """
    if len(images) == 0:
        raise ValueError("severity_of_set: no images")
    if len(ranges) != len(images) or (sky_masks is not None and len(sky_masks) != len(images)):
        raise ValueError(f"severity_of_set: {len(images)} images, {len(ranges)} range maps"
                         f"{'' if sky_masks is None else f', {len(sky_masks)} sky masks'}; expected one per image")
    masks = [None] * len(images) if sky_masks is None else list(sky_masks)
    A = pooled_sky_airlight(images, ranges, masks)
    per = [estimate_fog_severity(img, rng, sky_mask=m, airlight=A, **kwargs)  # type: ignore[arg-type]
           for img, rng, m in zip(images, ranges, masks)]
    return aggregate_severity(per, A)


@dataclass(frozen=True)
class VisibilityComparison:
    """Camera fog severity of a simulated vs a reference fog level.

    Attributes:
        ratio: ``V_sim / V_ref`` (= ``α_ref / α_sim``): 1 is perfect agreement, target within 0.8-1.2.
        simulated, reference: the two sets' `SetSeverity`.
    """

    ratio: float
    simulated: SetSeverity
    reference: SetSeverity

    def metrics(self) -> dict[str, float | str | None]:
        """Flat numbers for details.json / MLflow; a figure that could not be estimated is None (JSON null) and
        ``camera_check`` says why (``ok``, or how many images of each set gave an estimate)."""
        values = {"camera_visibility_ratio": self.ratio,
                  "camera_alpha_sim": self.simulated.alpha, "camera_alpha_ref": self.reference.alpha,
                  "camera_visibility_sim": self.simulated.visibility,
                  "camera_visibility_ref": self.reference.visibility}
        out: dict[str, float | str | None] = {k: v if math.isfinite(v) else None for k, v in values.items()}
        n_sim, n_ref = self.simulated.num_estimated, self.reference.num_estimated
        out["camera_images_sim"], out["camera_images_ref"] = float(n_sim), float(n_ref)
        out["camera_check"] = ("ok" if math.isfinite(self.ratio) else
                               f"not estimable: fog severity from {n_sim} of {len(self.simulated.images)} simulated "
                               f"and {n_ref} of {len(self.reference.images)} reference images (too few fog windows: "
                               f"images too small or too little depth range)")
        return out


def compare_severity(simulated: SetSeverity, reference: SetSeverity) -> VisibilityComparison:
    """`VisibilityComparison` of two sets' severities (NaN ratio when either is not estimable)."""
    vs, vr = simulated.visibility, reference.visibility
    if not (math.isfinite(vs) and math.isfinite(vr)) or vr <= 0.0:
        ratio = math.nan
    else:
        ratio = vs / vr
    return VisibilityComparison(ratio=ratio, simulated=simulated, reference=reference)


def camera_visibility_ratio(
    sim_images: Sequence[NDArray],
    sim_ranges: Sequence[NDArray],
    ref_images: Sequence[NDArray],
    ref_ranges: Sequence[NDArray],
    *,
    sim_sky_masks: Sequence[NDArray | None] | None = None,
    ref_sky_masks: Sequence[NDArray | None] | None = None,
    **kwargs: object,
) -> VisibilityComparison:
    """Visibility of the simulated foggy images over that of the reference foggy images of one level.

    Args:
        sim_images, ref_images: (H, W, 3) uint8 sRGB images (sizes may differ between and within sets).
        sim_ranges, ref_ranges: their (H, W) ray lengths [m] (inf sky, NaN unknown).
        sim_sky_masks, ref_sky_masks: optional per-image sky masks (None entries allowed).
        kwargs: passed to `estimate_fog_severity` (work_width, window_radius, min_range).

    Returns:
        `VisibilityComparison` (``ratio`` = median-α̂ visibility of the simulated set / of the reference set).
    """
    sim = severity_of_set(sim_images, sim_ranges, sim_sky_masks, **kwargs)
    ref = severity_of_set(ref_images, ref_ranges, ref_sky_masks, **kwargs)
    return compare_severity(sim, ref)
