"""The overcast light of snowfall and rain on any clear image (``docs/physics.md`` section 4.3).

Weather-edit's first stage is a background edit: a snowy scene is whitish, a rainy one cloudy. Physically, snow and
rain fall from a cloud deck that hides the sun: the scene is lit by a grey overcast sky instead of a blue sky and the
sun. This module turns a clear image into that light, for synthetic and real images alike:

- **Sky**: the CIE standard overcast sky (Moon & Spencer 1942; CIE S 011/E:2003 type 1),
  ``L(γ) = L_z (1 + 2 sin γ) / 3`` at elevation γ, neutral grey; ``L_z`` the zenith luminance in the image's linear
  units (`Overcast.zenith_luminance`). The sky pixels (ray length inf: the project's rig-consistent sky,
  `weatheralign.camera.depth.camera_range_map`) become it.
- **Surfaces**: a clear pixel is lit by the clear sky and, where the sun reaches it, by the sun:
  ``E = E_d (c_sky + s m c_sun)``, with ``s = DIRECT_TO_DIFFUSE`` the clear day's direct-to-diffuse ratio, ``m`` in
  [0, 1] the pixel's lit share (sun visibility times its cosine relative to the lit level), ``c_sky`` / ``c_sun`` the
  two lights' colours at unit luminance. Under the cloud the sky light becomes grey and ``diffuse_gain`` (``Q``)
  times as strong, the sun keeps ``sun_transmittance`` (``T``) of its beam: ``E' = E_d (Q + T s m c_sun)``. The
  albedo is untouched, so each channel is multiplied by ``E'_c / E_c``: shadows and lit areas come together (their
  ratio drops from ``1 + s`` to ``1 + T s / Q``), the blue of the shadows and the warmth of the sunlit areas go
  neutral, the surface's texture stays.
- **The lit share** ``m`` comes from the image: the base layer of the log-luminance (He's guided filter, edge-aware,
  the same filter the fog uses; the detail layer, the texture, is never changed) against its local upper envelope
  (the lit level nearby): a base ``1 + s`` times darker than the envelope is in full shadow (``m = 0``), one at the
  envelope fully lit (``m = 1``). A dark surface in the sun reads as partly shadowed: it is lifted by at most
  ``(1 + s) / (1 + T s / Q)`` relative to its lit neighbours, the limit of telling albedo from light in one image.
- **The clear image's own sun**: ``s`` is the clear day's only where the image's sky is a cloudless one. A cloudless
  sky is blue (Rayleigh scattering, ``λ^-4``), a cloud deck neutral (droplets scatter all wavelengths alike): the
  image's sky colour gives the share of the sky that is cloud (`cloud_share`), and the image's own direct-to-diffuse
  ratio is ``s (1 - cloud share)`` (`image_direct_to_diffuse`): a frame shot under cloud (the shared Seeing Through
  Fog frame) has no sun to take away and its surfaces keep their relative light.
- **Exposure**: ``Q`` and ``L_z`` are in the clear image's linear units, known for the synthetic world (whose fixed
  exposure the reference shares: `Exposure.FIXED`). A real camera meters: its auto-exposure keeps the median
  log-luminance of what it meters (`Exposure.AUTO`: the surfaces above the horizon, which the ground edit leaves
  alone, `metering_mask`), and its sky is then ``zenith_over_surface`` (``ζ``, the overcast sky's zenith luminance
  over the metered surfaces' 90th percentile, calibrated on the reference's weather frames) times that percentile
  (`auto_expose`).

All arithmetic is vectorised numpy on float32 images (the guided filter on OpenCV box filters);
`relight_naive` is the per-pixel oracle of `relight`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.fog import SRGB_TABLES, decode_srgb_u8, encode_srgb_u8, guided_coefficients, guided_filter
from weatheralign.camera.kernels import light_front_kernel, lit_share_kernel, relit_encode_kernel

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

REC709 = (0.2126, 0.7152, 0.0722)
"""Luminance weights of linear sRGB (Rec. 709 primaries)."""

DIRECT_TO_DIFFUSE = 4.0
"""``s``: the clear day's direct over diffuse irradiance on a sunlit surface. Under a cloudless sky the diffuse share
of the global horizontal irradiance is 0.15-0.25 (Erbs, Klein & Duffie 1982, clearness index above 0.75): s = 4 at
0.2. The world's own shading has 3.5 for a level surface under a sun 40° high."""

SUN_COLOUR = (1.0, 0.96, 0.9)
"""The direct sun's colour in linear sRGB (as `weatheralign.world.shading`: a sun 25-60° high, about 5500 K)."""

GROUND_ALBEDO = 0.15
"""The ground's albedo for the light it reflects onto surfaces that face down (asphalt 0.05-0.2, concrete 0.3)."""

HORIZONTAL_FACTOR = 7.0 / 9.0
"""Horizontal irradiance of the CIE overcast sky over π L_z: ``∫ L(γ) sin γ dω / (π L_z) = 7/9``."""

MIN_SKY_PIXELS = 50
"""Fewer sky pixels than this give no clear-sky colour (the light is taken as neutral)."""

SKY_SATURATED = 0.98
"""A sky pixel whose brightest linear channel reaches this is clipped and tells nothing of the sky's colour."""

BASE_RADIUS_FRACTION = 0.025
"""The base layer's guided-filter radius as a share of the image width (24 px at 960 px)."""

BASE_EPS = 0.1
"""The guided filter's ε on the log-luminance: a step of 0.3 in log (a factor 1.35) is an edge; a sun shadow's
edge (a factor 1 + s = 5) is kept, most texture goes to the detail layer."""

ENVELOPE_FRACTION = 1.0
"""The lit level's neighbourhood: a window of this share of the image width (a building's shadow can cover half the
street, so every pixel's window reaches half an image width to each side)."""

LOG_FLOOR = 1e-4
"""Linear luminance floor before the logarithm."""

CLEAR_SKY_BLUE_RED = 1.3
"""Blue over red (linear sRGB) of the least blue cloudless sky: a hazy horizon (the world's clear horizon
``(0.62, 0.7, 0.8)`` has 1.29, its zenith 3.4; Rayleigh's ``λ^-4`` gives 3.6 from 610 to 465 nm). A sky as blue or
bluer has no cloud in it; a neutral one (1.0) is all cloud."""

ZENITH_OVER_SURFACE = 4.5
"""``ζ``'s default: the overcast zenith luminance over the metered surfaces' `BRIGHT_PERCENTILE` luminance. Those
surfaces are mostly vertical (irradiance 0.308 of ``π L_z`` from the sky, 0.03 from the ground,
`irradiance_factor`); their bright tenth are light walls and car paint of albedo about 0.6: ``0.22 L_z``."""

SKY_VIEW_FACTOR = 0.6
"""``V``: the share of a street surface's view that is sky (a suburban street: the rest is facades, cars, trees and
the ground); the rest sends it the light its surroundings reflect."""

SURROUND_ALBEDO = 0.25
"""``ρ``: the mean albedo of a street's surroundings (asphalt 0.1, foliage 0.2, light facades 0.6)."""

SUN_WHITE_PERCENTILE = 95.0
"""The lit, unclipped surfaces above this luminance percentile are the image's whites in the sun (white walls and
paint): their colour is the sun's plus the ambient's as the camera records them (`image_sun_colour`)."""

SKY_MATCH_LOG = 0.25
"""Colour evidence of the sky seen through gaps (`sky_from_colour`): a pixel within this of the open sky's log blue
over red and log green over red."""

SKY_MATCH_BRIGHTNESS = 0.5
"""... and at least this share of the open sky's luminance at its elevation: a surface in a shadow sees at most half
the sky (a vertical one) and reflects part of it, so it is darker than ``ρ V`` of the sky it sees."""

BRIGHT_PERCENTILE = 90.0
"""The metered surfaces' percentile the sky's zenith is tied to: light walls and paint, whose albedo varies less
between scenes than the median's (a street of trees is darker than one of houses)."""


class Exposure(StrEnum):
    """How the camera exposes the overcast scene: ``fixed`` (the clear image's exposure: the synthetic world's
    camera, the reference's) or ``auto`` (the camera meters: a real camera)."""

    FIXED = "fixed"
    AUTO = "auto"


@dataclass(frozen=True)
class Overcast:
    """The overcast light: ``sun_transmittance`` T (the share of the direct sun's beam the cloud lets through, 0..1),
    ``zenith_luminance`` L_z (the overcast sky's zenith luminance in the image's linear units, the camera's exposure
    of the clear image), ``diffuse_gain`` Q (the overcast sky's irradiance over the clear sky's, in those units)."""

    sun_transmittance: float
    zenith_luminance: float
    diffuse_gain: float
    zenith_over_surface: float = ZENITH_OVER_SURFACE
    """``ζ``: with `Exposure.AUTO`, the sky's zenith luminance over the metered surfaces' `BRIGHT_PERCENTILE`."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.sun_transmittance <= 1.0:
            raise ValueError(f"sun_transmittance = {self.sun_transmittance}; expected 0..1")
        if not (self.zenith_luminance > 0.0 and self.diffuse_gain > 0.0 and self.zenith_over_surface > 0.0):
            raise ValueError(f"zenith_luminance = {self.zenith_luminance}, diffuse_gain = {self.diffuse_gain}, "
                             f"zenith_over_surface = {self.zenith_over_surface}; expected positive numbers")

    def to_dict(self) -> dict[str, float]:
        return {"sun_transmittance": self.sun_transmittance, "zenith_luminance": self.zenith_luminance,
                "diffuse_gain": self.diffuse_gain, "zenith_over_surface": self.zenith_over_surface}


# ------------------------------------------------------------------------------------------------ the overcast sky


def overcast_sky_luminance(sin_elevation: NDArray, zenith_luminance: float) -> F64:
    """CIE standard overcast sky ``L_z (1 + 2 sin γ) / 3`` at ``sin_elevation`` (any shape; clipped at the
    horizon: below it the sky's horizon value)."""
    return zenith_luminance * (1.0 + 2.0 * np.clip(np.asarray(sin_elevation, dtype=np.float64), 0.0, 1.0)) / 3.0


def _sky_irradiance_table(size: int = 201, n_theta: int = 256, n_phi: int = 512) -> F64:
    """(size,) irradiance of the CIE overcast sky of unit zenith luminance on a surface whose normal has vertical
    component ``n_z = linspace(-1, 1, size)``, over π: midpoint quadrature over the upper hemisphere."""
    theta = (np.arange(n_theta) + 0.5) * (0.5 * np.pi / n_theta)  # from the zenith
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    weight = (1.0 + 2.0 * ct) / 3.0 * st * (0.5 * np.pi / n_theta) * (2.0 * np.pi / n_phi)  # L dω
    out = np.empty(size)
    for k, nz in enumerate(np.linspace(-1.0, 1.0, size)):
        nx = np.sqrt(max(0.0, 1.0 - nz * nz))
        cos_inc = nx * st * np.cos(phi)[None, :] + nz * ct
        out[k] = float(np.sum(weight * np.maximum(cos_inc, 0.0))) / np.pi
    out.flags.writeable = False
    return out


SKY_IRRADIANCE_TABLE = _sky_irradiance_table()
"""`_sky_irradiance_table`: 7/9 at n_z = 1, 0.308 on a vertical surface (the CIE sky's vertical over horizontal
illuminance, 0.396), 0 facing down."""


def irradiance_factor(n_z: NDArray, ground_albedo: float = GROUND_ALBEDO) -> F64:
    """Irradiance over π L_z of a surface of unit normal vertical component ``n_z`` (any shape) under the CIE
    overcast sky: the sky it sees (`SKY_IRRADIANCE_TABLE`) plus the level ground's reflection, a Lambertian plane of
    ``ground_albedo`` lit by the horizontal ``7/9 π L_z``, over the share ``(1 - n_z) / 2`` of its view."""
    nz = np.clip(np.asarray(n_z, dtype=np.float64), -1.0, 1.0)
    sky = np.interp(nz, np.linspace(-1.0, 1.0, len(SKY_IRRADIANCE_TABLE)), SKY_IRRADIANCE_TABLE)
    return sky + ground_albedo * HORIZONTAL_FACTOR * (1.0 - nz) / 2.0


def pixel_sin_elevation(K: NDArray, width: int, height: int, up_cam: NDArray) -> F32:
    """(H, W) sine of the elevation of each pixel-centre ray of the pinhole ``K`` (3, 3), ``up_cam`` (3,) the unit
    up direction in the camera frame (OpenCV axes)."""
    Kf = np.asarray(K, dtype=np.float64)
    u = (np.arange(width) - Kf[0, 2]) / Kf[0, 0]
    v = (np.arange(height) - Kf[1, 2]) / Kf[1, 1]
    up = np.asarray(up_cam, dtype=np.float64)
    dot = up[0] * u[None, :] + up[1] * v[:, None] + up[2]
    norm = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
    return (dot / norm).astype(np.float32)


def up_in_camera(T_global_cam: NDArray) -> F64:
    """(3,) the global up direction (z) in the camera frame of ``T_global_cam`` (4, 4)."""
    return np.asarray(T_global_cam, dtype=np.float64)[2, :3].copy()


# ------------------------------------------------------------------------------------------------ the light


def luminance(linear: NDArray) -> F32:
    """(H, W) Rec. 709 luminance of linear RGB (H, W, 3)."""
    x = np.asarray(linear, dtype=np.float32)
    return (REC709[0] * x[..., 0] + REC709[1] * x[..., 1] + REC709[2] * x[..., 2]).astype(np.float32)


def unit_colour(rgb: NDArray) -> F64:
    """(3,) ``rgb`` scaled to unit Rec. 709 luminance."""
    c = np.asarray(rgb, dtype=np.float64)
    return c / max(float(np.dot(REC709, c)), 1e-9)


def clear_sky_colour(linear: NDArray, sky: NDArray) -> F64:
    """(3,) the clear sky's light colour at unit luminance: the per-channel median of the unsaturated sky pixels
    (``sky`` (H, W) bool) of ``linear`` (H, W, 3); neutral with fewer than `MIN_SKY_PIXELS` of them."""
    px = np.asarray(linear, dtype=np.float64)[np.asarray(sky, dtype=bool)]
    px = px[px.max(axis=1) < SKY_SATURATED] if len(px) else px
    if len(px) < MIN_SKY_PIXELS:
        return np.ones(3)
    return unit_colour(np.median(px, axis=0))


def sky_colour_from_histogram(hist: NDArray) -> F64:
    """(3,) `clear_sky_colour` from (3, 256) per-channel sRGB code counts of the unsaturated sky pixels
    (`weatheralign.camera.kernels.light_front_kernel`): the decoding is monotonic, so each channel's median is the
    decoded median code (the mean of the two middle ones for an even count), equal to the median of the decoded
    pixels."""
    counts = np.asarray(hist, dtype=np.int64)
    n = int(counts[0].sum())
    if n < MIN_SKY_PIXELS:
        return np.ones(3)
    lut = SRGB_TABLES.decode.astype(np.float64)
    cum = np.cumsum(counts, axis=1)
    lower = np.array([lut[np.searchsorted(cum[c], (n - 1) // 2, side="right")] for c in range(3)])
    upper = np.array([lut[np.searchsorted(cum[c], n // 2, side="right")] for c in range(3)])
    return unit_colour((lower + upper) / 2.0)


def log_base(log_y: NDArray, radius: int, eps: float = BASE_EPS) -> F32:
    """(H, W) base layer of the log-luminance ``log_y`` (H, W): self-guided He filter of ``radius`` [px] and ``eps``
    (computed at half resolution on images of 64 px and more)."""
    ly = np.asarray(log_y, dtype=np.float32)
    return guided_filter(ly, ly, radius, eps, subsample=2 if min(ly.shape) >= 64 else 1)


def envelope_grid(height: int, width: int, window: int) -> tuple[tuple[int, int], int]:
    """The coarse grid of `lit_share`'s envelope for an image of ``height`` x ``width`` px: its (width, height) in
    cells (a 1/f-size copy, f = 8 from 256 px on, 1/64 of the smaller side beyond 512 px) and the dilation window in
    cells for a ``window`` [px] at full size."""
    f = max(1, min(height, width) // 64, 8 if min(height, width) >= 256 else 1)
    return (max(1, width // f), max(1, height // f)), max(3, int(round(window / f)) | 1)


def coarse_envelope(base: NDArray, weight: NDArray, small: tuple[int, int], k: int) -> F32:
    """(small[1], small[0]) upper envelope of the base log-luminance ``base`` (h, w) weighted by ``weight`` (h, w)
    in [0, 1] (the share of surface in each pixel): the area-averaged surface mean on the ``small`` grid (cells
    under a quarter surface take the lowest surface base, so a lone bright pixel does not set it), its maximum over
    ``k`` x ``k`` cells, smoothed by a box a quarter of that size."""
    b = np.asarray(base, dtype=np.float32)
    wt = np.asarray(weight, dtype=np.float32)
    floor = float(b[wt > 0].min())
    area = cv2.resize(wt, small, interpolation=cv2.INTER_AREA)
    mean = cv2.resize(b * wt, small, interpolation=cv2.INTER_AREA) / np.maximum(area, 1e-6)
    mean = np.where(area > 0.25, mean, floor).astype(np.float32)
    env = cv2.dilate(mean, np.ones((k, k), np.uint8))
    soft = max(3, (k // 4) | 1)
    return cv2.blur(env, (soft, soft), borderType=cv2.BORDER_REFLECT)


def lit_share(base: NDArray, valid: NDArray, window: int, direct_to_diffuse: float = DIRECT_TO_DIFFUSE) -> F32:
    """(H, W) lit share ``m`` in [0, 1] of each pixel: its base log-luminance ``base`` (H, W) against the upper
    envelope over ``window`` px of the ``valid`` (H, W) pixels (surfaces, not sky): ``exp(base - envelope) =
    (1 + s m) / (1 + s)``. The envelope is `coarse_envelope` on the `envelope_grid`, brought back bilinearly. The
    numpy form of `light_layers`' compiled pass (`weatheralign.camera.kernels.lit_share_kernel`)."""
    b = np.asarray(base, dtype=np.float32)
    ok = np.asarray(valid, dtype=bool)
    h, w = b.shape
    if not ok.any():
        return np.zeros((h, w), np.float32)
    env = coarse_envelope(b, ok.astype(np.float32), *envelope_grid(h, w, window))
    env = np.maximum(cv2.resize(env, (w, h), interpolation=cv2.INTER_LINEAR), b)
    s = float(direct_to_diffuse)
    m = (np.exp(b - env) * (1.0 + s) - 1.0) / s
    return np.where(ok, np.clip(m, 0.0, 1.0), 0.0).astype(np.float32)


def relight_gain(m: NDArray, overcast: Overcast, ambient_colour: NDArray,
                 direct_to_diffuse: float = DIRECT_TO_DIFFUSE, sun_colour: NDArray | None = None) -> F32:
    """(H, W, 3) per-channel gain ``E'_c / E_c = (Q + T s m c_sun) / (c_amb + s m c'_sun)`` of lit share ``m``
    (H, W) (module docstring; ``ambient_colour`` (3,) the clear shadows' light colour at unit luminance: the sky's,
    plus the surroundings' reflection on a real street, `ambient_colour`; ``sun_colour`` (3,) the clear sun's as
    the camera recorded it, `image_sun_colour`, the world's `SUN_COLOUR` by default; the overcast's remaining sun
    is the world's sun)."""
    s = float(direct_to_diffuse)
    sun = unit_colour(SUN_COLOUR).astype(np.float32)
    clear_sun = sun if sun_colour is None else np.asarray(sun_colour, dtype=np.float32)
    amb = np.asarray(ambient_colour, dtype=np.float32)
    sm = (s * np.asarray(m, dtype=np.float32))[..., None]
    return ((np.float32(overcast.diffuse_gain) + np.float32(overcast.sun_transmittance) * sm * sun)
            / (amb + sm * clear_sun)).astype(np.float32)


def relight(linear: NDArray, sky: NDArray, sin_elevation: NDArray, m: NDArray, overcast: Overcast,
            ambient_colour: NDArray, direct_to_diffuse: float = DIRECT_TO_DIFFUSE,
            sun_colour: NDArray | None = None) -> F32:
    """(H, W, 3) float32 linear image under ``overcast`` at the clear image's exposure: the ``sky`` (H, W) pixels the
    CIE overcast sky at their ``sin_elevation`` (H, W), the others ``linear`` (H, W, 3) times `relight_gain` of their
    lit share ``m`` (H, W), the clear ``ambient_colour`` and ``sun_colour`` and the image's ``direct_to_diffuse``."""
    lin = np.asarray(linear, dtype=np.float32)
    out = lin * relight_gain(m, overcast, ambient_colour, direct_to_diffuse, sun_colour)
    grey = overcast_sky_luminance(sin_elevation, overcast.zenith_luminance).astype(np.float32)
    return np.where(np.asarray(sky, dtype=bool)[..., None], grey[..., None], out).astype(np.float32)


def relight_naive(linear: NDArray, sky: NDArray, sin_elevation: NDArray, m: NDArray, overcast: Overcast,
                  ambient_colour: NDArray, direct_to_diffuse: float = DIRECT_TO_DIFFUSE,
                  sun_colour: NDArray | None = None) -> F64:
    """`relight` pixel by pixel in float64: the oracle of the vectorised form."""
    s, t, q = float(direct_to_diffuse), overcast.sun_transmittance, overcast.diffuse_gain
    sun = unit_colour(SUN_COLOUR)
    clear_sun = sun if sun_colour is None else np.asarray(sun_colour, dtype=np.float64)
    h, w = np.asarray(sky).shape
    out = np.empty((h, w, 3))
    for v in range(h):
        for u in range(w):
            if sky[v, u]:
                out[v, u] = overcast.zenith_luminance * (1.0 + 2.0 * min(max(float(sin_elevation[v, u]), 0.0), 1.0)
                                                         ) / 3.0
                continue
            for c in range(3):
                sm = s * float(m[v, u])
                out[v, u, c] = float(linear[v, u, c]) * (q + t * sm * sun[c]) / (float(ambient_colour[c])
                                                                                  + sm * float(clear_sun[c]))
    return out


def cloud_share(sky_colour: NDArray) -> float:
    """The share of the image's sky that is cloud, from its light colour ``sky_colour`` (3,): 0 at a blue over red
    of `CLEAR_SKY_BLUE_RED` or more (cloudless), 1 at a neutral sky, linear between."""
    c = np.asarray(sky_colour, dtype=np.float64)
    ratio = float(c[2] / max(c[0], 1e-9))
    return float(np.clip((CLEAR_SKY_BLUE_RED - ratio) / (CLEAR_SKY_BLUE_RED - 1.0), 0.0, 1.0))


def image_direct_to_diffuse(sky_colour: NDArray, sky_pixels: int,
                            direct_to_diffuse: float = DIRECT_TO_DIFFUSE) -> float:
    """The clear image's own direct-to-diffuse ratio: ``direct_to_diffuse (1 - cloud_share)`` of its ``sky_colour``
    (3,); the clear day's without `MIN_SKY_PIXELS` ``sky_pixels`` (no sky to tell)."""
    if sky_pixels < MIN_SKY_PIXELS:
        return float(direct_to_diffuse)
    return float(direct_to_diffuse) * (1.0 - cloud_share(sky_colour))


def bounce_share(direct_to_diffuse: float, sky_view: float = SKY_VIEW_FACTOR,
                 surround_albedo: float = SURROUND_ALBEDO) -> float:
    """The share of a shadow's light that its sunlit surroundings reflect: a street surface sees the sky over
    ``sky_view`` (``V``) of its view and, over the rest, surroundings of albedo ``surround_albedo`` (``ρ``) lit by the
    sky and the sun, ``1 + s`` times the sky's light (``s`` = ``direct_to_diffuse``): ``(1 - V) ρ (1 + s) / (V +
    (1 - V) ρ (1 + s))``, 0.45 under a cloudless sky (``s = 4``), 0.22 at ``s = 1``, 0.14 without sun."""
    reflected = (1.0 - float(sky_view)) * float(surround_albedo) * (1.0 + float(direct_to_diffuse))
    return reflected / (float(sky_view) + reflected)


def ambient_colour(linear: NDArray, surfaces: NDArray, sky_colour: NDArray, share: float) -> F64:
    """(3,) the clear shadows' light colour at unit luminance: ``1 - share`` of the sky's ``sky_colour`` (3,) and
    ``share`` (`bounce_share`) of the light the surroundings reflect, whose colour is the mean colour of the
    ``surfaces`` (H, W) of ``linear`` (H, W, 3) (radiance-weighted: the sunlit ones dominate)."""
    sky = unit_colour(sky_colour)
    px = np.asarray(linear, dtype=np.float64)[np.asarray(surfaces, dtype=bool)]
    if share <= 0.0 or len(px) < MIN_SKY_PIXELS:
        return sky
    return unit_colour((1.0 - share) * sky + share * unit_colour(px.mean(axis=0)))


def image_sun_colour(linear: NDArray, surfaces: NDArray, lit: NDArray, ambient: NDArray,
                     direct_to_diffuse: float, spread: float = 0.3) -> F64:
    """(3,) the clear sun's colour at unit luminance as the camera recorded it (its white balance): the lit
    (``lit`` > 0.5), unclipped ``surfaces`` (H, W) of ``linear`` (H, W, 3) above the `SUN_WHITE_PERCENTILE`
    luminance are whites in the sun, lit by ``ambient + s c_sun`` (``ambient`` (3,) at unit luminance, ``s`` =
    ``direct_to_diffuse``), so ``c_sun = ((1 + s) white - ambient) / s``, kept within ``spread`` of the world's
    `SUN_COLOUR` per channel (a camera's white balance moves it by tens of per cent at most); the world's with
    little sun (``s`` < 0.5) or too few such pixels."""
    world = unit_colour(SUN_COLOUR)
    s = float(direct_to_diffuse)
    lin = np.asarray(linear, dtype=np.float64)
    ok = np.asarray(surfaces, dtype=bool) & (lin.max(axis=2) < 0.98) & (np.asarray(lit) > 0.5)
    if s < 0.5 or int(ok.sum()) < MIN_SKY_PIXELS:
        return world
    y = luminance(lin)
    white = lin[ok & (y >= np.percentile(y[ok], SUN_WHITE_PERCENTILE))]
    if len(white) < MIN_SKY_PIXELS // 5:
        return world
    sun = ((1.0 + s) * unit_colour(white.mean(axis=0)) - np.asarray(ambient, dtype=np.float64)) / s
    return unit_colour(np.clip(sun, (1.0 - spread) * world, (1.0 + spread) * world))


def sky_from_colour(linear: NDArray, sky: NDArray, sin_elevation: NDArray) -> NDArray[np.bool_]:
    """(H, W) ``sky`` (H, W) and the blue sky seen through gaps that the range map misses (between leaves, where the
    LiDAR hits the branches around it): pixels above the horizon (``sin_elevation`` (H, W) > 0) at least as blue as
    the open sky as the camera recorded it (clipped channels and all: a bright blue sky clips green and blue), within
    `SKY_MATCH_LOG`, in log blue over red and log blue over green (a leaf is greener than blue; the sky is bluer
    higher up, where the gaps in a crown are), and at least `SKY_MATCH_BRIGHTNESS` of its luminance (the median of
    the open sky at the same elevation, in bins of 0.05 in ``sin γ``); then the pixels next to them (3 x 3) as blue
    as a cloudless sky (blue over red above `CLEAR_SKY_BLUE_RED`: a leaf's edge mixed with the sky). Only a
    cloudless sky (`cloud_share` 0) is told from the surfaces by its colour; ``sky`` unchanged otherwise."""
    lin = np.asarray(linear, dtype=np.float64)
    sky = np.asarray(sky, dtype=bool)
    if int(sky.sum()) < MIN_SKY_PIXELS or cloud_share(np.median(lin[sky], axis=0)) > 0.0:
        return sky
    eps = 1e-4
    log_br = np.log((lin[..., 2] + eps) / (lin[..., 0] + eps))
    log_bg = np.log((lin[..., 2] + eps) / (lin[..., 1] + eps))
    y = luminance(lin)
    sin_el = np.asarray(sin_elevation, dtype=np.float64)
    bins = np.clip((sin_el / 0.05).astype(np.int64), 0, 20)
    filled = np.bincount(bins[sky], minlength=21) > 0
    have = np.nonzero(filled)[0]
    ref = np.interp(np.arange(21), have, [float(np.median(y[sky & (bins == b)])) for b in have])
    above = ~sky & (sin_el > 0.0)
    gap = above & (log_br >= np.median(log_br[sky]) - SKY_MATCH_LOG)
    gap &= log_bg >= np.median(log_bg[sky]) - SKY_MATCH_LOG
    gap &= y >= SKY_MATCH_BRIGHTNESS * ref[bins]
    near = cv2.dilate((gap | sky).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    fringe = near & above & (log_br > np.log(CLEAR_SKY_BLUE_RED))
    return sky | gap | fringe


def metering_mask(sky: NDArray, sin_elevation: NDArray) -> NDArray[np.bool_]:
    """(H, W) what the camera meters: the surfaces (not ``sky`` (H, W)) above the horizon (``sin_elevation`` (H, W)
    above 0); all surfaces where fewer than `MIN_SKY_PIXELS` are above it."""
    surf = ~np.asarray(sky, dtype=bool)
    above = surf & (np.asarray(sin_elevation) > 0.0)
    return above if int(above.sum()) >= MIN_SKY_PIXELS else surf


def metered_log_luminance(linear: NDArray, meter: NDArray, percentile: float = 50.0) -> float:
    """``percentile`` (the median by default) of the log-luminance of ``linear`` (H, W, 3) over the ``meter``
    (H, W) pixels (0 without any)."""
    m = np.asarray(meter, dtype=bool)
    if not m.any():
        return 0.0
    return float(np.percentile(np.log(np.maximum(luminance(linear)[m], LOG_FLOOR)), percentile))


def auto_expose(clear: NDArray, relit: NDArray, sky: NDArray, sin_elevation: NDArray,
                zenith_over_surface: float) -> tuple[F32, float]:
    """The relit surfaces ``relit`` (H, W, 3) re-exposed so their metered median log-luminance is the ``clear``
    (H, W, 3) image's (`metering_mask`), the ``sky`` (H, W) the CIE overcast sky of zenith ``zenith_over_surface``
    times the re-exposed metered surfaces' `BRIGHT_PERCENTILE` luminance; (the image float32, that zenith)."""
    meter = metering_mask(sky, sin_elevation)
    shift = metered_log_luminance(clear, meter) - metered_log_luminance(relit, meter)
    k = np.float32(np.exp(shift))
    zenith = float(zenith_over_surface) * float(np.exp(metered_log_luminance(relit, meter, BRIGHT_PERCENTILE)
                                                       + shift))
    grey = overcast_sky_luminance(sin_elevation, zenith).astype(np.float32)
    out = np.where(np.asarray(sky, dtype=bool)[..., None], grey[..., None], np.asarray(relit, np.float32) * k)
    return out.astype(np.float32), zenith


@dataclass(frozen=True, eq=False)
class LightLayers:
    """What `light_layers` finds in a clear image: ``image`` (H, W, 3) the clear uint8 sRGB image, ``sky`` (H, W)
    bool, ``sin_elevation`` (H, W), ``lit`` (H, W) lit share,
    ``sky_colour`` (3,) the clear sky's light colour at unit luminance, ``direct_to_diffuse`` the image's own
    (`image_direct_to_diffuse`), ``ambient_colour`` (3,) the clear shadows' light (`ambient_colour`; the sky's when
    None) and ``sun_colour`` (3,) the clear sun's as recorded (`image_sun_colour`; the world's when None)."""

    image: U8
    sky: NDArray[np.bool_]
    sin_elevation: F32
    lit: F32
    sky_colour: F64
    direct_to_diffuse: float = DIRECT_TO_DIFFUSE
    ambient_colour: F64 | None = None
    sun_colour: F64 | None = None

    @cached_property
    def linear(self) -> F32:
        """(H, W, 3) float32 linear RGB of ``image`` (decoded on first use: the fixed-exposure relight reads the
        codes)."""
        return decode_srgb_u8(self.image)

    @property
    def ambient(self) -> F64:
        """(3,) the clear shadows' light colour at unit luminance."""
        return self.sky_colour if self.ambient_colour is None else self.ambient_colour


def light_layers(image: U8, range_map: NDArray, K: NDArray, T_global_cam: NDArray,
                 real: bool = False) -> LightLayers:
    """The layers of a clear ``image`` (H, W, 3) uint8 sRGB with ray lengths ``range_map`` (H, W) [m] (inf = sky)
    seen by the pinhole ``K`` (3, 3) posed at ``T_global_cam`` (4, 4; global z up).

    ``real``: a real street seen by a real camera. Its sky's gaps between leaves are found by colour
    (`sky_from_colour`: a dense depth's sky misses them), its shadows are lit by the sky and by the light their
    sunlit surroundings reflect (`ambient_colour`, `bounce_share`), and its camera's white balance gives the sun its
    own colour (`image_sun_colour`). Otherwise the synthetic world's exact model: the range map's sky, the sky alone
    in the shadows (the world renders no interreflection), the world's sun.

    The layers come from two compiled passes: `weatheralign.camera.kernels.light_front_kernel` (the sky, the
    elevation, the sky pixels' code histograms of `clear_sky_colour`, each pixel's log-luminance and its mean on
    the 2 x 2 block grid where `log_base` finds its coefficients) and `weatheralign.camera.kernels.lit_share_kernel`
    (`log_base` and `lit_share` at every pixel; the envelope from the block grid)."""
    img = np.ascontiguousarray(image, dtype=np.uint8)
    h, w = img.shape[:2]
    if h < 4 or w < 4:
        raise ValueError(f"light_layers: image of {h} x {w} px; expected at least 4 x 4")
    Kf = np.asarray(K, dtype=np.float64)
    sky, sin_el, hist, log_half, surface_half, log_lum = light_front_kernel(
        img, np.ascontiguousarray(range_map), float(Kf[0, 0]), float(Kf[0, 2]), float(Kf[1, 1]), float(Kf[1, 2]),
        up_in_camera(T_global_cam), SRGB_TABLES.decode, SKY_SATURATED, LOG_FLOOR)
    colour = sky_colour_from_histogram(hist)
    lin = decode_srgb_u8(img) if real else None
    if lin is not None:  # the gaps between leaves are sky too
        sky = sky_from_colour(lin, sky, sin_el)
        surface_half = cv2.resize((~sky).astype(np.float32), log_half.shape[::-1], interpolation=cv2.INTER_AREA)
    s = image_direct_to_diffuse(colour, int(sky.sum()))
    lit = np.zeros((h, w), np.float32)
    if surface_half.max() > 0.0:
        coeffs = guided_coefficients(log_half, log_half, max(1, int(round(base_radius(w) / 2))), BASE_EPS)
        base_half = coeffs[..., 0] * log_half + coeffs[..., 1]
        envelope = coarse_envelope(base_half, surface_half, *envelope_grid(h, w, envelope_window(w)))
        lit = lit_share_kernel(log_lum, sky, np.ascontiguousarray(coeffs), envelope, max(s, 1e-3))
    if lin is None:
        return LightLayers(img, sky, sin_el, lit, colour, s)
    ambient = ambient_colour(lin, ~sky, colour, bounce_share(s))
    sun = image_sun_colour(lin, ~sky, lit, ambient, s)
    out = LightLayers(img, sky, sin_el, lit, colour, s, ambient, sun)
    out.__dict__["linear"] = lin  # the cached_property's slot: decoded once
    return out


def base_radius(width: int) -> int:
    """`log_base`'s radius [px] for an image ``width`` px wide."""
    return max(2, int(round(BASE_RADIUS_FRACTION * width)))


def envelope_window(width: int) -> int:
    """`lit_share`'s envelope window [px] for an image ``width`` px wide."""
    return max(3, int(round(ENVELOPE_FRACTION * width)))


def light_layers_naive(image: U8, range_map: NDArray, K: NDArray, T_global_cam: NDArray) -> tuple[F32, F32]:
    """(sky's colour (3,), lit share (H, W)) of the synthetic path of `light_layers` in numpy at full resolution:
    `clear_sky_colour`, then `lit_share` of `log_base` of the log-luminance. Its oracle."""
    lin = decode_srgb_u8(np.asarray(image, dtype=np.uint8))
    sky = ~np.isfinite(np.asarray(range_map))
    colour = clear_sky_colour(lin, sky)
    log_y = np.log(np.maximum(luminance(lin), LOG_FLOOR)).astype(np.float32)
    base = log_base(log_y, base_radius(lin.shape[1]))
    s = image_direct_to_diffuse(colour, int(sky.sum()))
    return colour, lit_share(base, ~sky, envelope_window(lin.shape[1]), max(s, 1e-3))


def overcast_linear(layers: LightLayers, overcast: Overcast, exposure: Exposure = Exposure.FIXED
                    ) -> tuple[F32, float]:
    """(H, W, 3) float32 linear image of `light_layers` under ``overcast`` (`relight`; `auto_expose` with
    `Exposure.AUTO`) and its sky's zenith luminance in that image's units."""
    relit = relight(layers.linear, layers.sky, layers.sin_elevation, layers.lit, overcast, layers.ambient,
                    layers.direct_to_diffuse, layers.sun_colour)
    if Exposure(exposure) is Exposure.FIXED:
        return relit, overcast.zenith_luminance
    return auto_expose(layers.linear, relit, layers.sky, layers.sin_elevation, overcast.zenith_over_surface)


def overcast_edit(image: U8, range_map: NDArray, K: NDArray, T_global_cam: NDArray, overcast: Overcast,
                  exposure: Exposure = Exposure.FIXED, real: bool | None = None) -> tuple[U8, F64]:
    """(H, W, 3) uint8 sRGB: the clear ``image`` (arguments as `light_layers`) under ``overcast`` exposed by
    ``exposure``; and (3,) its overcast horizon ``L_z / 3`` grey, linear in its units (the airlight under the
    cloud). ``real`` (`light_layers`): a real street, by default where the camera meters (`Exposure.AUTO`: a real
    camera; the synthetic world's has `Exposure.FIXED`)."""
    real = Exposure(exposure) is Exposure.AUTO if real is None else bool(real)
    layers = light_layers(image, range_map, K, T_global_cam, real)
    if Exposure(exposure) is Exposure.FIXED:
        return relit_u8(image, layers, overcast), np.full(3, overcast.zenith_luminance / 3.0)
    lin, zenith = overcast_linear(layers, overcast, exposure)
    return encode_srgb_u8(lin), np.full(3, zenith / 3.0)


def relit_u8(image: U8, layers: LightLayers, overcast: Overcast) -> U8:
    """(H, W, 3) uint8 sRGB: ``encode_srgb_u8(relight(...))`` of the clear ``image`` and its `light_layers` under
    ``overcast`` at a fixed exposure, in one compiled pass (`weatheralign.camera.kernels.relit_encode_kernel`)."""
    sun = unit_colour(SUN_COLOUR).astype(np.float32)
    clear_sun = sun if layers.sun_colour is None else np.asarray(layers.sun_colour, dtype=np.float32)
    return relit_encode_kernel(np.ascontiguousarray(image, dtype=np.uint8),
                               np.ascontiguousarray(layers.lit, dtype=np.float32),
                               np.ascontiguousarray(layers.sky, dtype=np.bool_),
                               np.ascontiguousarray(layers.sin_elevation, dtype=np.float32),
                               float(overcast.diffuse_gain), float(overcast.sun_transmittance),
                               float(layers.direct_to_diffuse), float(overcast.zenith_luminance),
                               np.ascontiguousarray(layers.ambient, dtype=np.float32), sun,
                               np.ascontiguousarray(clear_sun, dtype=np.float32), *SRGB_TABLES)


def overcast_image(image: U8, range_map: NDArray, K: NDArray, T_global_cam: NDArray, overcast: Overcast,
                   exposure: Exposure = Exposure.FIXED, real: bool | None = None) -> U8:
    """(H, W, 3) uint8 sRGB: the clear ``image`` under ``overcast`` (`overcast_edit`)."""
    return overcast_edit(image, range_map, K, T_global_cam, overcast, exposure, real)[0]


__all__ = ["BASE_EPS", "BASE_RADIUS_FRACTION", "BRIGHT_PERCENTILE", "CLEAR_SKY_BLUE_RED", "DIRECT_TO_DIFFUSE",
           "ENVELOPE_FRACTION", "GROUND_ALBEDO", "HORIZONTAL_FACTOR", "REC709", "SKY_IRRADIANCE_TABLE",
           "SKY_MATCH_BRIGHTNESS", "SKY_MATCH_LOG", "SKY_SATURATED", "SKY_VIEW_FACTOR", "SUN_COLOUR",
           "SUN_WHITE_PERCENTILE", "SURROUND_ALBEDO", "ZENITH_OVER_SURFACE", "Exposure", "LightLayers", "Overcast",
           "ambient_colour", "auto_expose", "base_radius", "bounce_share", "clear_sky_colour", "cloud_share",
           "coarse_envelope", "envelope_grid", "envelope_window", "image_direct_to_diffuse", "image_sun_colour",
           "irradiance_factor", "light_layers", "light_layers_naive", "lit_share", "log_base", "luminance",
           "metered_log_luminance", "metering_mask", "overcast_edit", "overcast_image", "overcast_linear",
           "overcast_sky_luminance", "pixel_sin_elevation", "relight", "relight_gain", "relight_naive", "relit_u8",
           "sky_colour_from_histogram", "sky_from_colour", "unit_colour", "up_in_camera"]
