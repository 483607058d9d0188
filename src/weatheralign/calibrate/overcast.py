"""ReDAM for the overcast light of snow and rain: the sky's zenith luminance, the cloud's sun transmittance and the
overcast's diffuse gain of `weatheralign.camera.overcast` recovered from a reference's clear and weather images
(``docs/physics.md`` section 4.3).

Per frame (`frame_light`): the images' light on the pixels the weather's other edits leave alone: surfaces within
`SURFACE_RANGE_M` whose normal is within 60° of horizontal (facades, sides of cars and poles: no lying snow, no wet
road, little veil) at least `MIN_HEIGHT_M` above the ego's ground plane; and the sky pixels.

- ``L_z``: each weather frame's sky gives ``3 Y / (1 + 2 sin γ)`` (the CIE overcast sky inverted at each pixel's
  elevation), its median is the frame's estimate; the split's is the mean over frames. In falling snow the far sky is
  veiled by the flakes' own light, which under the overcast is that of the horizon sky within a few per cent
  (`weatheralign.reference.overcast.flake_radiance`), so the low sky reads the same.
- ``ζ`` (the sky's zenith over the metered surfaces' bright percentile, what a metering camera's sky keeps): each
  weather frame's ``L_z`` estimate over the 90th percentile luminance of its surfaces above the horizon
  (`weatheralign.camera.overcast.metering_mask`), averaged over frames.
- ``T`` and ``Q``: the clear frames through the operator's light at (T, Q) (`simulated_light`: the lit share ``m``
  of each clear pixel, its luminance times ``(Q + T s m) / (1 + s m)``) against the weather frames: the mean over
  frames of the surfaces' median log-luminance (how bright; facades and sides, as above) and of the **road's sun
  contrast**, the 95th minus the 5th percentile of the base layer of log-luminance over the level ground within
  `ROAD_RANGE_M` (one material: its albedo cancels, what is left is the light, sunlit over shadowed:
  ``log(1 + s)`` on a clear day, ``log(1 + T s / Q)`` under the cloud where the road has shadows). For each T of a
  grid, Q matches the brightness; T then matches the road contrast (`fit_overcast`). Frame bootstrap of both sides
  for the intervals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.overcast import (
    BRIGHT_PERCENTILE,
    DIRECT_TO_DIFFUSE,
    LOG_FLOOR,
    Overcast,
    light_layers,
    luminance,
    metered_log_luminance,
    metering_mask,
)
from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.surfaces import pixel_normals

F64 = NDArray[np.float64]

SURFACE_RANGE_M = 40.0
"""Surfaces farther than this [m] are left out (the precipitation's veil grows with distance)."""

MIN_HEIGHT_M = 0.3
"""Surfaces lower than this above the ego's ground plane [m] are left out (the wet or snowy ground)."""

MAX_NORMAL_Z = 0.5
"""Surfaces whose normal's vertical component exceeds this are left out (snow lies on them)."""

ROAD_RANGE_M = 30.0
"""Road pixels farther than this [m] are left out (the veil, and too few pixels per metre to resolve a shadow)."""

MAX_ROAD_HEIGHT_M = 0.15
"""Road pixels are level surfaces (normal within 25° of vertical) lower than this above the ego's ground [m]."""

MIN_ROAD_NORMAL_Z = 0.9
"""The road's normals' least vertical component."""

ROAD_PERCENTILES = (5.0, 95.0)
"""The shadowed and the sunlit road: percentiles of the road's base log-luminance (a road shaded over a twentieth of
its pixels shows its shadows)."""

MIN_PIXELS = 50
"""A frame with fewer sky (surface) pixels gives no sky (surface) statistic."""

SUN_GRID: tuple[float, ...] = tuple(float(t) for t in np.linspace(0.0, 0.6, 61))
"""The sun transmittances T the fit evaluates."""


@dataclass(frozen=True, eq=False)
class FrameLight:
    """One frame's light: ``zenith`` (its sky's L_z estimate, nan without sky), ``metered_bright`` (the 90th percentile
    log-luminance of its metered surfaces), over its facade pixels ``log_y`` (P,) the log-luminance and ``lit`` (P,)
    the lit share, over its road pixels ``road_base`` (R,) the base layer and ``road_lit`` (R,) the lit share;
    ``direct_to_diffuse`` the image's own."""

    zenith: float
    metered_bright: float
    log_y: F64
    lit: F64
    road_base: F64
    road_lit: F64
    direct_to_diffuse: float = DIRECT_TO_DIFFUSE

    @property
    def brightness(self) -> float:
        """Median log-luminance of the facades (nan with too few)."""
        return float(np.median(self.log_y)) if len(self.log_y) >= MIN_PIXELS else np.nan

    @property
    def road_contrast(self) -> float:
        """The road's sun contrast: `ROAD_PERCENTILES` spread of its base log-luminance (nan with too few)."""
        if len(self.road_base) < MIN_PIXELS:
            return np.nan
        lo, hi = np.percentile(self.road_base, ROAD_PERCENTILES)
        return float(hi - lo)

    @property
    def zenith_over_surface(self) -> float:
        """``ζ``: the sky's zenith luminance over the metered surfaces' bright percentile (nan without sky)."""
        return float(self.zenith / np.exp(self.metered_bright))


def surface_mask(range_map: NDArray, K: NDArray, T_ego_cam: NDArray) -> NDArray[np.bool_]:
    """(H, W) the facade pixels the brightness reads (module docstring), from the ray lengths ``range_map`` (H, W)
    [m] of the pinhole ``K`` (3, 3) mounted at ``T_ego_cam`` (4, 4; the ego frame's origin on the ground, z up)."""
    return _masks(range_map, K, T_ego_cam)[0]


def road_mask(range_map: NDArray, K: NDArray, T_ego_cam: NDArray) -> NDArray[np.bool_]:
    """(H, W) the level ground within `ROAD_RANGE_M` (arguments as `surface_mask`)."""
    return _masks(range_map, K, T_ego_cam)[1]


def _masks(range_map: NDArray, K: NDArray, T_ego_cam: NDArray) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(facade, road) masks (H, W): heights above the ground, the 10th percentile height of the level pixels within
    `ROAD_RANGE_M` (the ego frame's origin need not lie on the ground)."""
    rng = np.asarray(range_map, dtype=np.float64)
    surf = pixel_normals(rng, CameraGeometry(np.asarray(K, dtype=np.float64), np.asarray(T_ego_cam, dtype=np.float64)))
    z = surf.points_world[..., 2]
    nz = np.abs(surf.normals_world[..., 2])
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(rng)
        level = finite & (rng <= ROAD_RANGE_M) & (nz >= MIN_ROAD_NORMAL_Z)
        ground = float(np.nanpercentile(z[level], 10.0)) if int(level.sum()) >= MIN_PIXELS else 0.0
        height = z - ground
        facade = finite & (rng <= SURFACE_RANGE_M) & (height >= MIN_HEIGHT_M) & (nz <= MAX_NORMAL_Z)
        road = level & (np.abs(height) <= MAX_ROAD_HEIGHT_M)
    return facade, road


def frame_light(image: NDArray, range_map: NDArray, K: NDArray, T_ego_cam: NDArray,
                T_global_cam: NDArray) -> FrameLight:
    """`FrameLight` of one camera image (H, W, 3) uint8 sRGB with its ray lengths (H, W) [m] (inf = sky), pinhole
    ``K``, mount ``T_ego_cam`` and pose ``T_global_cam`` (global z up)."""
    layers = light_layers(image, range_map, K, T_global_cam)
    y = luminance(layers.linear)
    sky = layers.sky & (y < 0.98)  # a saturated sky says nothing of its luminance
    zenith = np.nan
    if int(sky.sum()) >= MIN_PIXELS:
        zenith = float(np.median(3.0 * y[sky] / (1.0 + 2.0 * np.clip(layers.sin_elevation[sky], 0.0, 1.0))))
    bright = metered_log_luminance(layers.linear, metering_mask(layers.sky, layers.sin_elevation), BRIGHT_PERCENTILE)
    facade, road = _masks(range_map, K, T_ego_cam)
    log_y = np.log(np.maximum(y[facade], LOG_FLOOR)).astype(np.float64)
    return FrameLight(zenith, bright, log_y, layers.lit[facade].astype(np.float64),
                      layers.base[road].astype(np.float64), layers.lit[road].astype(np.float64),
                      layers.direct_to_diffuse)


def _log_gain(lit: F64, sun_transmittance: float, diffuse_gain: float, direct_to_diffuse: float) -> F64:
    s = direct_to_diffuse
    return np.log((diffuse_gain + sun_transmittance * s * lit) / (1.0 + s * lit))


def simulated_light(frames: Sequence[FrameLight], sun_transmittance: float, diffuse_gain: float
                    ) -> tuple[F64, F64]:
    """(F,) brightness and (F,) road contrast of the clear ``frames`` under the operator's light at
    (``sun_transmittance``, ``diffuse_gain``): each pixel's log-luminance and base layer raised by the log of its
    luminance gain ``(Q + T s m) / (1 + s m)`` (the base layer moves with the smooth gain)."""
    bright, contrast = np.full(len(frames), np.nan), np.full(len(frames), np.nan)
    for f, fr in enumerate(frames):
        s = fr.direct_to_diffuse
        moved = FrameLight(fr.zenith, fr.metered_bright, fr.log_y + _log_gain(fr.lit, sun_transmittance,
                                                                             diffuse_gain, s), fr.lit,
                           fr.road_base + _log_gain(fr.road_lit, sun_transmittance, diffuse_gain, s), fr.road_lit, s)
        bright[f], contrast[f] = moved.brightness, moved.road_contrast
    return bright, contrast


def _diffuse_gain_for(frames: Sequence[FrameLight], sun_transmittance: float, target: float) -> float:
    """The Q at which the clear frames' mean brightness under (``sun_transmittance``, Q) is ``target``
    (bisection on log Q in [e^-4, e^4]: the brightness rises with Q)."""
    lo, hi = -4.0, 4.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if np.nanmean(simulated_light(frames, sun_transmittance, float(np.exp(mid)))[0]) < target:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def _fit_point(clear: Sequence[FrameLight], weather: Sequence[FrameLight]) -> tuple[float, float, float, float]:
    """(L_z, T, Q, ζ) of one (re)sample of frames."""
    zenith = float(np.nanmean([fr.zenith for fr in weather]))
    zeta = float(np.nanmean([fr.zenith_over_surface for fr in weather]))
    target_bright = float(np.nanmean([fr.brightness for fr in weather]))
    target_contrast = float(np.nanmean([fr.road_contrast for fr in weather]))
    gains = [_diffuse_gain_for(clear, t, target_bright) for t in SUN_GRID]
    contrasts = np.array([np.nanmean(simulated_light(clear, t, q)[1]) for t, q in zip(SUN_GRID, gains)])
    grid = np.asarray(SUN_GRID)
    order = np.argsort(contrasts)
    t = float(np.interp(target_contrast, contrasts[order], grid[order]))
    return zenith, t, float(np.interp(t, grid, gains)), zeta


@dataclass(frozen=True)
class OvercastFit:
    """The recovered overcast of one weather split with frame-bootstrap intervals ``(low, high)``; the reference's
    statistics."""

    zenith_luminance: float
    sun_transmittance: float
    diffuse_gain: float
    zenith_ci: tuple[float, float]
    sun_ci: tuple[float, float]
    gain_ci: tuple[float, float]
    reference_brightness: float
    reference_road_contrast: float
    frames: int
    zenith_over_surface: float = np.nan
    zeta_ci: tuple[float, float] = (np.nan, np.nan)

    def overcast(self) -> Overcast:
        """The operator's light (`weatheralign.camera.overcast.Overcast`) of this fit."""
        return Overcast(float(np.clip(self.sun_transmittance, 0.0, 1.0)), self.zenith_luminance, self.diffuse_gain,
                        self.zenith_over_surface)

    def metrics(self) -> dict[str, float | int]:
        return {"zenith_luminance": self.zenith_luminance, "zenith_ci_low": self.zenith_ci[0],
                "zenith_ci_high": self.zenith_ci[1], "sun_transmittance": self.sun_transmittance,
                "sun_ci_low": self.sun_ci[0], "sun_ci_high": self.sun_ci[1], "diffuse_gain": self.diffuse_gain,
                "gain_ci_low": self.gain_ci[0], "gain_ci_high": self.gain_ci[1],
                "zenith_over_surface": self.zenith_over_surface, "zeta_ci_low": self.zeta_ci[0],
                "zeta_ci_high": self.zeta_ci[1], "reference_brightness": self.reference_brightness,
                "reference_road_contrast": self.reference_road_contrast, "frames": self.frames}


def fit_overcast(clear: Sequence[FrameLight], weather: Sequence[FrameLight], *, num_bootstrap: int = 200,
                 confidence: float = 0.95, seed: int = 0) -> OvercastFit:
    """The overcast of a weather split from its frames' light ``weather`` and the clear split's ``clear`` (module
    docstring), with percentile intervals over ``num_bootstrap`` resamples of both sides' frames.

    Raises:
        ValueError: a side has no frame, or no weather frame shows sky.
    """
    if not clear or not weather:
        raise ValueError(f"fit_overcast: {len(clear)} clear and {len(weather)} weather frames; need both")
    if all(np.isnan(fr.zenith) for fr in weather):
        raise ValueError("fit_overcast: no weather frame shows unsaturated sky; the zenith luminance is unknown")
    estimate = _fit_point(clear, weather)
    rng = np.random.default_rng(seed)
    boot = []
    for _ in range(num_bootstrap):
        c = [clear[i] for i in rng.integers(0, len(clear), len(clear))]
        w = [weather[i] for i in rng.integers(0, len(weather), len(weather))]
        if not all(np.isnan(fr.zenith) for fr in w):
            boot.append(_fit_point(c, w))
    tail = (1.0 - confidence) / 2.0
    b = np.asarray(boot) if boot else np.asarray([estimate])

    def ci(k: int) -> tuple[float, float]:
        return float(np.nanquantile(b[:, k], tail)), float(np.nanquantile(b[:, k], 1.0 - tail))

    return OvercastFit(estimate[0], estimate[1], estimate[2], ci(0), ci(1), ci(2),
                       float(np.nanmean([fr.brightness for fr in weather])),
                       float(np.nanmean([fr.road_contrast for fr in weather])), len(weather), estimate[3], ci(3))


__all__ = ["MAX_NORMAL_Z", "MAX_ROAD_HEIGHT_M", "MIN_HEIGHT_M", "MIN_PIXELS", "MIN_ROAD_NORMAL_Z", "ROAD_PERCENTILES",
           "ROAD_RANGE_M", "SUN_GRID", "SURFACE_RANGE_M", "FrameLight", "OvercastFit", "fit_overcast", "frame_light",
           "road_mask", "simulated_light", "surface_mask"]
