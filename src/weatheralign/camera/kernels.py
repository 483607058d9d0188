"""Compiled per-pixel kernels of the camera media: exact sRGB encoding and the fused guided-filter + Koschmieder
composite (one pass over a full-resolution image instead of a dozen numpy passes).

The numpy forms in `weatheralign.camera.fog` (`encode_srgb_u8`'s table, `guided_filter`, `composite`) define the
results; these kernels compute the same rule per pixel in float32 with the same operation order, so that
`fog_composite` equals ``encode(composite(decode(image), refine(t), A))`` up to the bilinear upsampling of the
guided-filter coefficients (OpenCV's half-pixel convention, reproduced here). The overcast light's kernels
(`light_front_kernel`, `relit_encode_kernel`) equal `weatheralign.camera.overcast`'s numpy forms bit for bit
(the blocks' mean luminance to float32 rounding). Nothing here allocates per pixel; all
kernels release the GIL, so cameras can run on threads.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]


@numba.njit(cache=True, nogil=True, inline="always")
def encode_one(x: np.float32, lut: NDArray, ambiguous: NDArray, thresholds: NDArray, bins: int) -> np.uint8:
    """sRGB code of one linear value ``x`` (clipped to [0, 1]), exactly rounded: the 65536-bin table, and a binary
    search of the exact code steps ``thresholds`` (255,) where the bin straddles one."""
    if x < np.float32(0.0):
        x = np.float32(0.0)
    elif x > np.float32(1.0):
        x = np.float32(1.0)
    idx = np.uint16(x * np.float32(bins - 1) + np.float32(0.5))
    if not ambiguous[idx]:
        return lut[idx]
    return np.uint8(np.searchsorted(thresholds, np.float64(x), side="right"))


@numba.njit(cache=True, nogil=True)
def encode_srgb_kernel(linear: NDArray, lut: NDArray, ambiguous: NDArray, thresholds: NDArray, bins: int) -> U8:
    """(N,) float32 linear values -> (N,) uint8 exactly rounded sRGB codes (see `encode_one`)."""
    out = np.empty(linear.shape[0], np.uint8)
    for i in range(linear.shape[0]):
        out[i] = encode_one(linear[i], lut, ambiguous, thresholds, bins)
    return out


@numba.njit(cache=True, nogil=True)
def relit_encode_kernel(image: U8, lit: F32, sky: NDArray, sin_elevation: F32, diffuse_gain: float,
                        sun_transmittance: float, direct_to_diffuse: float, zenith: float, ambient: F32, sun: F32,
                        clear_sun: F32, decode_lut: F32, lut: NDArray, ambiguous: NDArray, thresholds: NDArray,
                        bins: int) -> U8:
    """(H, W, 3) uint8 sRGB ``image`` relit under an overcast at the clear image's exposure and encoded exactly, in
    one pass: sky pixels (``sky`` (H, W)) the CIE overcast sky ``zenith (1 + 2 clip(sin γ, 0, 1)) / 3`` of
    ``sin_elevation`` (H, W), the others their decoded value times ``(Q + T s m sun_c) / (amb_c + s m clear_sun_c)``
    of lit share ``lit`` (H, W) (``ambient``, ``sun``, ``clear_sun`` (3,) float32); float32 in
    `weatheralign.camera.overcast.relight`'s operation order, so that it equals ``encode_srgb_u8(relight(...))``."""
    height, width = image.shape[0], image.shape[1]
    out = np.empty((height, width, 3), np.uint8)
    q, t, s = np.float32(diffuse_gain), np.float32(sun_transmittance), np.float32(direct_to_diffuse)
    for v in range(height):
        for u in range(width):
            if sky[v, u]:
                e = min(max(np.float64(sin_elevation[v, u]), 0.0), 1.0)
                code = encode_one(np.float32(zenith * (1.0 + 2.0 * e) / 3.0), lut, ambiguous, thresholds, bins)
                out[v, u, 0], out[v, u, 1], out[v, u, 2] = code, code, code
                continue
            sm = s * lit[v, u]
            for c in range(3):
                gain = (q + t * sm * sun[c]) / (ambient[c] + sm * clear_sun[c])
                out[v, u, c] = encode_one(decode_lut[image[v, u, c]] * gain, lut, ambiguous, thresholds, bins)
    return out


@numba.njit(cache=True, nogil=True)
def _axis_weights(n_out: int, n_in: int) -> tuple[NDArray, NDArray, NDArray]:
    """OpenCV ``INTER_LINEAR`` sampling of ``n_in`` cells onto ``n_out`` pixels (half-pixel centres, clamped):
    per output pixel the lower cell, the upper cell and the upper weight."""
    lo = np.empty(n_out, np.int64)
    hi = np.empty(n_out, np.int64)
    w = np.empty(n_out, np.float32)
    scale = n_in / n_out
    for i in range(n_out):
        f = (i + 0.5) * scale - 0.5
        if f < 0.0:
            f = 0.0
        j = int(np.floor(f))
        if j >= n_in - 1:
            lo[i], hi[i], w[i] = n_in - 1, n_in - 1, 0.0
        else:
            lo[i], hi[i], w[i] = j, j + 1, np.float32(f - j)
    return lo, hi, w


@numba.njit(cache=True, nogil=True)
def composite_guided_kernel(image: NDArray, coeffs: NDArray, airlight: NDArray, decode_lut: NDArray,
                            out_linear: NDArray, out_codes: NDArray, encode: bool, lut: NDArray, ambiguous: NDArray,
                            thresholds: NDArray, bins: int) -> None:
    """Koschmieder composite with the guided-filtered transmittance, in one pass.

    Per pixel: the coefficients (a_r, a_g, a_b, b) bilinearly upsampled (OpenCV's half-pixel convention), the
    refined transmittance ``t = clip(b + a · guide, 0, 1)`` with the sRGB image in [0, 1] as guide, then
    ``decode(image) t + A (1 - t)`` per channel, encoded to sRGB or kept linear.

    Args:
        image: (H, W, 3) uint8 sRGB clear image (also the guide). coeffs: (h, w, 4) float32 guided-filter
            coefficients at low resolution. airlight: (3,) float32 linear. decode_lut: (256,) float32.
        out_linear: (H, W, 3) float32 linear result (written when not ``encode``); out_codes: (H, W, 3) uint8 sRGB
            (written when ``encode``).
    """
    H, W = image.shape[0], image.shape[1]
    ylo, yhi, wys = _axis_weights(H, coeffs.shape[0])
    xlo, xhi, wxs = _axis_weights(W, coeffs.shape[1])
    one, zero = np.float32(1.0), np.float32(0.0)
    inv = np.float32(1.0 / 255.0)
    row = np.empty((coeffs.shape[1], 4), np.float32)
    for y in range(H):
        wy = wys[y]
        for j in range(coeffs.shape[1]):  # the coefficient row at this pixel row (vertical interpolation)
            for k in range(4):
                row[j, k] = coeffs[ylo[y], j, k] * (one - wy) + coeffs[yhi[y], j, k] * wy
        for x in range(W):
            x0, x1, wx = xlo[x], xhi[x], wxs[x]
            a0 = row[x0, 0] * (one - wx) + row[x1, 0] * wx
            a1 = row[x0, 1] * (one - wx) + row[x1, 1] * wx
            a2 = row[x0, 2] * (one - wx) + row[x1, 2] * wx
            b = row[x0, 3] * (one - wx) + row[x1, 3] * wx
            c0, c1, c2 = image[y, x, 0], image[y, x, 1], image[y, x, 2]
            t = b + a0 * (np.float32(c0) * inv) + a1 * (np.float32(c1) * inv)
            t += a2 * (np.float32(c2) * inv)
            t = min(max(t, zero), one)
            v0 = decode_lut[c0] * t + airlight[0] * (one - t)
            v1 = decode_lut[c1] * t + airlight[1] * (one - t)
            v2 = decode_lut[c2] * t + airlight[2] * (one - t)
            if encode:
                out_codes[y, x, 0] = encode_one(v0, lut, ambiguous, thresholds, bins)
                out_codes[y, x, 1] = encode_one(v1, lut, ambiguous, thresholds, bins)
                out_codes[y, x, 2] = encode_one(v2, lut, ambiguous, thresholds, bins)
            else:
                out_linear[y, x, 0], out_linear[y, x, 1], out_linear[y, x, 2] = v0, v1, v2


@numba.njit(cache=True, nogil=True)
def composite_plain_kernel(image: NDArray, t: NDArray, airlight: NDArray, decode_lut: NDArray, out_linear: NDArray,
                           out_codes: NDArray, encode: bool, lut: NDArray, ambiguous: NDArray, thresholds: NDArray,
                           bins: int) -> None:
    """`composite_guided_kernel` with a full-resolution transmittance ``t`` (H, W) float32 in [0, 1] as is."""
    H, W = image.shape[0], image.shape[1]
    one = np.float32(1.0)
    for y in range(H):
        for x in range(W):
            tt = t[y, x]
            for k in range(3):
                v = decode_lut[image[y, x, k]] * tt + airlight[k] * (one - tt)
                if encode:
                    out_codes[y, x, k] = encode_one(v, lut, ambiguous, thresholds, bins)
                else:
                    out_linear[y, x, k] = v


@numba.njit(cache=True, nogil=True, inline="always")
def range_weight(coarse: np.float64, fine: np.float64, sigma: float) -> np.float64:
    """Weight of a coarse sample at ray length ``coarse`` [m] for a pixel at ``fine`` [m]: 1 for both infinite (sky),
    0 for one infinite, else ``exp(-(|coarse - fine| / (sigma fine))^2)`` (`range_guided_weights_naive`)."""
    if np.isinf(coarse) or np.isinf(fine):
        return 1.0 if np.isinf(coarse) and np.isinf(fine) else 0.0
    d = (coarse - fine) / (sigma * max(fine, 1e-6))
    return np.exp(-d * d)


@numba.njit(cache=True, nogil=True, inline="always")
def _bilinear(corners: NDArray, w0: np.float64, w1: np.float64, w2: np.float64, w3: np.float64) -> np.float64:
    """The weighted sum of a coarse cell's four samples ``corners`` (4,): (y0, x0), (y0, x1), (y1, x0), (y1, x1),
    in the order of `range_guided_weights_naive`."""
    return 0.0 + w0 * corners[0] + w1 * corners[1] + w2 * corners[2] + w3 * corners[3]


@numba.njit(cache=True, nogil=True, inline="always")
def _bilinear_channel(corners: NDArray, ch: int, w0: np.float64, w1: np.float64, w2: np.float64,
                      w3: np.float64) -> np.float64:
    """`_bilinear` of channel ``ch`` of a cell's four samples ``corners`` (4, C)."""
    return 0.0 + w0 * corners[0, ch] + w1 * corners[1, ch] + w2 * corners[2, ch] + w3 * corners[3, ch]


@numba.njit(cache=True, nogil=True, inline="always")
def _edge_weights(w0: np.float64, w1: np.float64, w2: np.float64, w3: np.float64, c0: np.float64, c1: np.float64,
                  c2: np.float64, c3: np.float64, r: np.float64, sigma: float
                  ) -> tuple[np.float64, np.float64, np.float64, np.float64, np.float64]:
    """The bilinear weights (w0..w3) of a pixel at ray length ``r`` [m] whose coarse samples lie at ``c0..c3`` [m],
    off the surface they span: each times `range_weight`; where they all vanish, the sample of nearest ray length
    alone (none: all 0). Returns the weights and their sum (`range_guided_weights_naive`, in the kernel's order)."""
    r_inf = np.isinf(r)
    best, best_k = np.inf, -1
    for k, c in enumerate((c0, c1, c2, c3)):
        if np.isinf(c) == r_inf:
            miss = 0.0 if r_inf else abs(c - r)
            if miss < best:
                best, best_k = miss, k
    w0 *= range_weight(c0, r, sigma)
    w1 *= range_weight(c1, r, sigma)
    w2 *= range_weight(c2, r, sigma)
    w3 *= range_weight(c3, r, sigma)
    total = 0.0 + w0 + w1 + w2 + w3
    if total <= 1e-12:
        w0, w1, w2, w3 = (1.0 if best_k == 0 else 0.0), (1.0 if best_k == 1 else 0.0), \
            (1.0 if best_k == 2 else 0.0), (1.0 if best_k == 3 else 0.0)
        total = 1.0 if best_k >= 0 else 0.0
    return w0, w1, w2, w3, total


@numba.njit(cache=True, nogil=True)
def guided_affine_edit_kernel(image: U8, gain: NDArray, offset: NDArray, edited: NDArray, range_map: NDArray,
                              stride: int, sigma: float, alt_gain: NDArray, alt_offset: NDArray, switch: NDArray,
                              decode_lut: NDArray, lut: NDArray, ambiguous: NDArray, thresholds: NDArray,
                              bins: int) -> tuple[U8, NDArray]:
    """(H, W, 3) uint8 sRGB ``image`` edited in linear light as ``decode(image) * gain + offset`` and encoded back
    exactly (`encode_one`), with ``gain``, ``offset`` (h, w, 3) and ``edited`` (h, w) float given on every ``stride``-th
    row and column of ``range_map`` (H, W) [m] and brought to each pixel by bilinear weights, guided by the ray lengths
    across a depth edge (`weatheralign.camera.fog.range_guided_weights_naive`); returns the image and the (H, W) pixels
    whose interpolated ``edited`` exceeds 0.5. Where ``switch`` (h, w) is given (else (0, 0)), a pixel whose
    interpolated ``switch`` exceeds 0 takes the interpolated ``alt_gain``, ``alt_offset`` (h, w, 3) instead. Pixels
    whose four samples change nothing are copied as they are (the identity round-trips every code). One pass, coarse
    cell by cell (its four samples read once for its pixels); nothing full-size allocated but the outputs."""
    height, width = image.shape[0], image.shape[1]
    h, w = gain.shape[0], gain.shape[1]
    switching = switch.shape[0] > 0
    touched = np.zeros((h, w), np.bool_)
    for y in range(h):
        for x in range(w):
            touched[y, x] = edited[y, x] != 0.0 or gain[y, x, 0] != 1.0 or gain[y, x, 1] != 1.0 or \
                gain[y, x, 2] != 1.0 or offset[y, x, 0] != 0.0 or offset[y, x, 1] != 0.0 or offset[y, x, 2] != 0.0
            if switching and not touched[y, x]:
                touched[y, x] = alt_gain[y, x, 0] != 1.0 or alt_gain[y, x, 1] != 1.0 or alt_gain[y, x, 2] != 1.0 or \
                    alt_offset[y, x, 0] != 0.0 or alt_offset[y, x, 1] != 0.0 or alt_offset[y, x, 2] != 0.0
    out = image.copy()  # untouched pixels stay as they are
    mask = np.zeros((height, width), np.bool_)
    corner_gain, corner_offset = np.empty((4, 3)), np.empty((4, 3))  # one coarse cell's four samples
    corner_alt_gain, corner_alt_offset = np.empty((4, 3)), np.empty((4, 3))
    corner_edited, corner_switch, corner_range = np.empty(4), np.zeros(4), np.empty(4)
    for y0 in range(h):  # cell by cell: its four samples read once for its stride x stride pixels
        y1 = min(y0 + 1, h - 1)
        for x0 in range(w):
            x1 = min(x0 + 1, w - 1)
            if not (touched[y0, x0] or touched[y0, x1] or touched[y1, x0] or touched[y1, x1]):
                continue
            for k in range(4):
                yy, xx = (y0 if k < 2 else y1), (x0 if k % 2 == 0 else x1)
                for ch in range(3):
                    corner_gain[k, ch], corner_offset[k, ch] = gain[yy, xx, ch], offset[yy, xx, ch]
                    if switching:
                        corner_alt_gain[k, ch], corner_alt_offset[k, ch] = alt_gain[yy, xx, ch], alt_offset[yy, xx, ch]
                corner_edited[k] = edited[yy, xx]
                if switching:
                    corner_switch[k] = switch[yy, xx]
                corner_range[k] = np.float64(range_map[yy * stride, xx * stride])
            c0, c1, c2, c3 = corner_range[0], corner_range[1], corner_range[2], corner_range[3]
            for i in range(y0 * stride, min((y0 + 1) * stride, height)):
                fy = (i - y0 * stride) / stride
                for j in range(x0 * stride, min((x0 + 1) * stride, width)):
                    fx = (j - x0 * stride) / stride
                    w0, w1 = (1.0 - fy) * (1.0 - fx), (1.0 - fy) * fx
                    w2, w3 = fy * (1.0 - fx), fy * fx
                    r = np.float64(range_map[i, j])
                    spanned = 0.0 + w0 * c0 + w1 * c1 + w2 * c2 + w3 * c3  # the samples' surface here, bilinearly
                    if np.isfinite(spanned) and np.isfinite(r) and abs(spanned - r) <= sigma * r:
                        total = 0.0 + w0 + w1 + w2 + w3
                    else:
                        w0, w1, w2, w3, total = _edge_weights(w0, w1, w2, w3, c0, c1, c2, c3, r, sigma)
                    if total <= 0.0:  # no sample counts: gain 1, offset 0, the pixel as it is
                        continue
                    e = _bilinear(corner_edited, w0, w1, w2, w3)
                    mask[i, j] = e > 0.5 * total
                    alternative = switching and _bilinear(corner_switch, w0, w1, w2, w3) > 0.0
                    for ch in range(3):  # (no array variable chosen per pixel: numba would count its references)
                        if alternative:
                            g = _bilinear_channel(corner_alt_gain, ch, w0, w1, w2, w3) / total
                            o = _bilinear_channel(corner_alt_offset, ch, w0, w1, w2, w3) / total
                        else:
                            g = _bilinear_channel(corner_gain, ch, w0, w1, w2, w3) / total
                            o = _bilinear_channel(corner_offset, ch, w0, w1, w2, w3) / total
                        x = np.float64(decode_lut[image[i, j, ch]]) * g + o
                        out[i, j, ch] = encode_one(np.float32(x), lut, ambiguous, thresholds, bins)
    return out, mask


__all__ = ["composite_guided_kernel", "composite_plain_kernel", "encode_one", "encode_srgb_kernel",
           "guided_affine_edit_kernel", "range_weight", "relit_encode_kernel"]


@numba.njit(cache=True, nogil=True, inline="always")
def _log_luminance(image: U8, v: int, u: int, decode_lut: F32, log_floor: np.float32) -> np.float32:
    """``log(max(Y, log_floor))`` of the Rec. 709 luminance ``Y`` (float32, `weatheralign.camera.overcast.luminance`'s
    operation order) of pixel (``v``, ``u``) of the uint8 sRGB ``image``."""
    y = (np.float32(0.2126) * decode_lut[image[v, u, 0]] + np.float32(0.7152) * decode_lut[image[v, u, 1]]
         + np.float32(0.0722) * decode_lut[image[v, u, 2]])
    return np.log(max(y, log_floor))


@numba.njit(cache=True, nogil=True)
def light_front_kernel(image: U8, range_map: NDArray, fx: float, cx: float, fy: float, cy: float, up: NDArray,
                       decode_lut: F32, saturated: float, log_floor: float
                       ) -> tuple[NDArray, F32, NDArray, F32, F32, F32]:
    """One pass over a clear ``image`` (H, W, 3) uint8 sRGB (H, W >= 2) and its ray lengths ``range_map`` (H, W)
    [m] (inf = sky) seen by a pinhole (``fx``, ``cx``, ``fy``, ``cy`` [px]) whose camera frame has the global up
    ``up`` (3,): the sky (H, W) bool; each pixel ray's sine of elevation (H, W) float32, operation for operation
    `weatheralign.camera.overcast.pixel_sin_elevation` (float64), so equal bit for bit; (3, 256) int64 per-channel
    code histograms of the sky pixels whose brightest decoded channel is below ``saturated``; and on the
    (H // 2, W // 2) grid of 2 x 2 blocks (the odd last row and column join the last block) the mean
    log-luminance (`_log_luminance`) and the share of surface (not sky) pixels, float32; each pixel's
    log-luminance (H, W) float32 (`lit_share_kernel` reads it)."""
    height, width = image.shape[0], image.shape[1]
    h2, w2 = height // 2, width // 2
    sky = np.empty((height, width), np.bool_)
    sin_el = np.empty((height, width), np.float32)
    log_lum = np.empty((height, width), np.float32)
    hist = np.zeros((3, 256), np.int64)
    log_sum = np.zeros((h2, w2), np.float64)
    surface = np.zeros((h2, w2), np.float64)
    count = np.zeros((h2, w2), np.float64)
    floor = np.float32(log_floor)
    for v in range(height):
        y = (v - cy) / fy
        bv = min(v // 2, h2 - 1)
        for u in range(width):
            x = (u - cx) / fx
            dot = up[0] * x + up[1] * y + up[2]
            sin_el[v, u] = np.float32(dot / np.sqrt(x * x + y * y + 1.0))
            bu = min(u // 2, w2 - 1)
            log_y = _log_luminance(image, v, u, decode_lut, floor)
            log_lum[v, u] = log_y
            log_sum[bv, bu] += log_y
            count[bv, bu] += 1.0
            is_sky = not np.isfinite(range_map[v, u])
            sky[v, u] = is_sky
            if not is_sky:
                surface[bv, bu] += 1.0
            elif max(decode_lut[image[v, u, 0]], decode_lut[image[v, u, 1]], decode_lut[image[v, u, 2]]) < saturated:
                hist[0, image[v, u, 0]] += 1
                hist[1, image[v, u, 1]] += 1
                hist[2, image[v, u, 2]] += 1
    return (sky, sin_el, hist, (log_sum / count).astype(np.float32), (surface / count).astype(np.float32),
            log_lum)


@numba.njit(cache=True, nogil=True)
def lit_share_kernel(log_luminance: F32, sky: NDArray, coeffs: F32, envelope: F32, direct_to_diffuse: float
                     ) -> F32:
    """(H, W) float32 lit share of a clear image in one pass: each pixel's base log-luminance ``a L + b`` (``L``
    its `_log_luminance`, given as ``log_luminance`` (H, W) by `light_front_kernel`; ``(a, b)`` the guided-filter
    coefficients ``coeffs``
    (h, w, 2) upsampled bilinearly) against the ``envelope`` (hs, ws) upsampled bilinearly (and at least the base):
    ``m = clip(((1 + s) exp(base - envelope) - 1) / s, 0, 1)``, 0 on the ``sky`` (H, W)
    (`weatheralign.camera.overcast.lit_share` of `weatheralign.camera.overcast.log_base`)."""
    height, width = log_luminance.shape[0], log_luminance.shape[1]
    ylo, yhi, wys = _axis_weights(height, coeffs.shape[0])
    xlo, xhi, wxs = _axis_weights(width, coeffs.shape[1])
    eylo, eyhi, ewys = _axis_weights(height, envelope.shape[0])
    exlo, exhi, ewxs = _axis_weights(width, envelope.shape[1])
    out = np.empty((height, width), np.float32)
    one = np.float32(1.0)
    s = np.float32(direct_to_diffuse)
    for v in range(height):
        y0, y1, wy = ylo[v], yhi[v], wys[v]
        ey0, ey1, ewy = eylo[v], eyhi[v], ewys[v]
        for u in range(width):
            if sky[v, u]:
                out[v, u] = 0.0
                continue
            x0, x1, wx = xlo[u], xhi[u], wxs[u]
            ab = ((one - wy) * ((one - wx) * coeffs[y0, x0, 0] + wx * coeffs[y0, x1, 0])
                  + wy * ((one - wx) * coeffs[y1, x0, 0] + wx * coeffs[y1, x1, 0]))
            bb = ((one - wy) * ((one - wx) * coeffs[y0, x0, 1] + wx * coeffs[y0, x1, 1])
                  + wy * ((one - wx) * coeffs[y1, x0, 1] + wx * coeffs[y1, x1, 1]))
            base = ab * log_luminance[v, u] + bb
            ex0, ex1, ewx = exlo[u], exhi[u], ewxs[u]
            env = ((one - ewy) * ((one - ewx) * envelope[ey0, ex0] + ewx * envelope[ey0, ex1])
                   + ewy * ((one - ewx) * envelope[ey1, ex0] + ewx * envelope[ey1, ex1]))
            m = (np.exp(base - max(env, base)) * (one + s) - one) / s
            out[v, u] = min(max(m, np.float32(0.0)), one)
    return out
