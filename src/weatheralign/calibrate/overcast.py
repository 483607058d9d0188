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
- ``T`` and ``Q``: the clear frames' surfaces through the operator's light at (T, Q) (`simulated_light`: the lit
  share ``m`` of each clear pixel, its luminance times ``(Q + T s m) / (1 + s m)``) against the weather frames'
  surfaces: the mean over frames of the median log-luminance (how bright) and of the spread (90th - 10th percentile)
  of the base layer of log-luminance (how much sun-and-shadow contrast is left). For each T of a grid, Q matches the
  brightness; T then matches the spread (`fit_overcast`). Frame bootstrap of both sides for the intervals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.overcast import DIRECT_TO_DIFFUSE, LOG_FLOOR, light_layers, luminance
from weatheralign.ground.camera import CameraGeometry
from weatheralign.ground.surfaces import pixel_normals

F64 = NDArray[np.float64]

SURFACE_RANGE_M = 40.0
"""Surfaces farther than this [m] are left out (the precipitation's veil grows with distance)."""

MIN_HEIGHT_M = 0.3
"""Surfaces lower than this above the ego's ground plane [m] are left out (the wet or snowy ground)."""

MAX_NORMAL_Z = 0.5
"""Surfaces whose normal's vertical component exceeds this are left out (snow lies on them)."""

MIN_PIXELS = 50
"""A frame with fewer sky (surface) pixels gives no sky (surface) statistic."""

SUN_GRID: tuple[float, ...] = tuple(float(t) for t in np.linspace(0.0, 0.6, 61))
"""The sun transmittances T the fit evaluates."""


@dataclass(frozen=True, eq=False)
class FrameLight:
    """One frame's light: ``zenith`` (its sky's L_z estimate, nan without sky), over its surface pixels ``log_y``
    (P,) the log-luminance, ``base`` (P,) its base layer, ``lit`` (P,) the lit share."""

    zenith: float
    log_y: F64
    base: F64
    lit: F64

    @property
    def brightness(self) -> float:
        """Median log-luminance of the surfaces (nan with too few)."""
        return float(np.median(self.log_y)) if len(self.log_y) >= MIN_PIXELS else np.nan

    @property
    def spread(self) -> float:
        """90th minus 10th percentile of the surfaces' base log-luminance (nan with too few)."""
        if len(self.base) < MIN_PIXELS:
            return np.nan
        lo, hi = np.percentile(self.base, (10, 90))
        return float(hi - lo)


def surface_mask(range_map: NDArray, K: NDArray, T_ego_cam: NDArray) -> NDArray[np.bool_]:
    """(H, W) the pixels the statistics read (module docstring), from the ray lengths ``range_map`` (H, W) [m] of
    the pinhole ``K`` (3, 3) mounted at ``T_ego_cam`` (4, 4; the ego frame's origin on the ground, z up)."""
    rng = np.asarray(range_map, dtype=np.float64)
    surf = pixel_normals(rng, CameraGeometry(np.asarray(K, dtype=np.float64), np.asarray(T_ego_cam, dtype=np.float64)))
    height = surf.points_world[..., 2]
    nz = np.abs(surf.normals_world[..., 2])
    with np.errstate(invalid="ignore"):
        return np.isfinite(rng) & (rng <= SURFACE_RANGE_M) & (height >= MIN_HEIGHT_M) & (nz <= MAX_NORMAL_Z)


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
    mask = surface_mask(range_map, K, T_ego_cam)
    log_y = np.log(np.maximum(y[mask], LOG_FLOOR)).astype(np.float64)
    return FrameLight(zenith, log_y, layers.base[mask].astype(np.float64), layers.lit[mask].astype(np.float64))


def _log_gain(lit: F64, sun_transmittance: float, diffuse_gain: float) -> F64:
    s = DIRECT_TO_DIFFUSE
    return np.log((diffuse_gain + sun_transmittance * s * lit) / (1.0 + s * lit))


def simulated_light(frames: Sequence[FrameLight], sun_transmittance: float, diffuse_gain: float
                    ) -> tuple[F64, F64]:
    """(F,) brightness and (F,) spread of the clear ``frames``' surfaces under the operator's light at
    (``sun_transmittance``, ``diffuse_gain``): each pixel's log-luminance and base layer raised by the log of its
    luminance gain ``(Q + T s m) / (1 + s m)`` (the base layer moves with the smooth gain)."""
    bright, spread = np.full(len(frames), np.nan), np.full(len(frames), np.nan)
    for f, fr in enumerate(frames):
        g = _log_gain(fr.lit, sun_transmittance, diffuse_gain)
        moved = FrameLight(fr.zenith, fr.log_y + g, fr.base + g, fr.lit)
        bright[f], spread[f] = moved.brightness, moved.spread
    return bright, spread


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


def _fit_point(clear: Sequence[FrameLight], weather: Sequence[FrameLight]) -> tuple[float, float, float]:
    """(L_z, T, Q) of one (re)sample of frames."""
    zenith = float(np.nanmean([fr.zenith for fr in weather]))
    target_bright = float(np.nanmean([fr.brightness for fr in weather]))
    target_spread = float(np.nanmean([fr.spread for fr in weather]))
    gains = [_diffuse_gain_for(clear, t, target_bright) for t in SUN_GRID]
    spreads = np.array([np.nanmean(simulated_light(clear, t, q)[1]) for t, q in zip(SUN_GRID, gains)])
    grid = np.asarray(SUN_GRID)
    order = np.argsort(spreads)
    t = float(np.interp(target_spread, spreads[order], grid[order]))
    return zenith, t, float(np.interp(t, grid, gains))


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
    reference_spread: float
    frames: int

    def metrics(self) -> dict[str, float | int]:
        return {"zenith_luminance": self.zenith_luminance, "zenith_ci_low": self.zenith_ci[0],
                "zenith_ci_high": self.zenith_ci[1], "sun_transmittance": self.sun_transmittance,
                "sun_ci_low": self.sun_ci[0], "sun_ci_high": self.sun_ci[1], "diffuse_gain": self.diffuse_gain,
                "gain_ci_low": self.gain_ci[0], "gain_ci_high": self.gain_ci[1],
                "reference_brightness": self.reference_brightness, "reference_spread": self.reference_spread,
                "frames": self.frames}


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
                       float(np.nanmean([fr.spread for fr in weather])), len(weather))


__all__ = ["MAX_NORMAL_Z", "MIN_HEIGHT_M", "MIN_PIXELS", "SUN_GRID", "SURFACE_RANGE_M", "FrameLight", "OvercastFit",
           "fit_overcast", "frame_light", "simulated_light", "surface_mask"]
