"""ReDAM for the overcast light of snow and rain: the sky's zenith luminance, the metering camera's sky-over-surface
ratio and the overcast's diffuse gain of `weatheralign.camera.overcast` recovered from a reference's clear and weather
images (``docs/physics.md`` section 4.3). The cloud's sun transmittance ``T`` is **not identified** by these images
(physics 4.3 gives the statistics tried and what they measured): the fit reports the diffuse gain as a curve over
``T`` and the simulation takes ``T`` from its params.

Per frame (`frame_light`): the light on the pixels the weather's other edits leave alone: surfaces within
`SURFACE_RANGE_M` whose normal is within 60° of horizontal (facades, sides of cars and poles: no lying snow, no wet
road, little veil) at least `MIN_HEIGHT_M` above the ground (the 10th percentile height of the level pixels within
`GROUND_RANGE_M`); and the sky pixels.

- ``L_z``: each weather frame's sky gives ``3 Y / (1 + 2 sin γ)`` (the CIE overcast sky inverted at each pixel's
  elevation), its median is the frame's estimate; the split's is the mean over frames. In falling snow the far sky is
  veiled by the flakes' own light, which under the overcast is that of the horizon sky within a few per cent
  (`weatheralign.reference.overcast.flake_radiance`), so the low sky reads the same.
- ``ζ`` (the sky's zenith over the metered surfaces' bright percentile, what a metering camera's sky keeps): each
  weather frame's ``L_z`` estimate over the 90th percentile luminance of its surfaces above the horizon
  (`weatheralign.camera.overcast.metering_mask`), averaged over frames.
- ``Q(T)``: simulate and compare. The clear frames through the operator's light at (T, Q) (each facade pixel's
  log-luminance raised by the log of its gain ``(Q + T s m) / (1 + s m)``, ``m`` its lit share) against the weather
  frames: the mean over frames of the facades' median log-luminance. Per T of `SUN_GRID` the Q that matches
  (`diffuse_gain_curve`: each frame's brightness tabulated on `GAIN_GRID`, the frames' mean interpolated).

Intervals: percentile frame bootstrap of both sides (`fit_overcast`).
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
"""Surfaces lower than this above the ground [m] are left out (the wet or snowy ground)."""

MAX_NORMAL_Z = 0.5
"""Surfaces whose normal's vertical component exceeds this are left out (snow lies on them)."""

GROUND_RANGE_M = 30.0
"""The ground's height is read from the level pixels within this range [m]."""

MIN_GROUND_NORMAL_Z = 0.9
"""Level pixels: normal within 25° of vertical."""

MIN_PIXELS = 50
"""A frame with fewer sky (surface) pixels gives no sky (surface) statistic."""

MAX_SURFACE_PIXELS = 4000
"""A frame's surface pixels are thinned to at most this many (every k-th in raster order): the median of 4000
samples is within about 2 % of the image's (its standard error ``1.25 σ / sqrt(n)`` at σ = 0.5 in log)."""

SUN_GRID: tuple[float, ...] = tuple(round(0.05 * k, 2) for k in range(11))
"""The sun transmittances T over which the diffuse gain Q(T) is reported (0 to 0.5)."""

GAIN_GRID: F64 = np.exp(np.linspace(-2.0, 3.0, 201))
"""The diffuse gains Q on which each clear frame's simulated brightness is tabulated (e^-2 to e^3, 2.5 % steps)."""


@dataclass(frozen=True, eq=False)
class FrameLight:
    """One frame's light: ``zenith`` (its sky's L_z estimate, nan without sky), ``metered_bright`` (the 90th percentile
    log-luminance of its metered surfaces), over its facade pixels (thinned to `MAX_SURFACE_PIXELS`) ``log_y`` (P,)
    the log-luminance and ``lit`` (P,) the lit share; ``direct_to_diffuse`` the image's own."""

    zenith: float
    metered_bright: float
    log_y: F64
    lit: F64
    direct_to_diffuse: float = DIRECT_TO_DIFFUSE

    @property
    def brightness(self) -> float:
        """Median log-luminance of the facades (nan with too few)."""
        return float(np.median(self.log_y)) if len(self.log_y) >= MIN_PIXELS else np.nan

    @property
    def zenith_over_surface(self) -> float:
        """``ζ``: the sky's zenith luminance over the metered surfaces' bright percentile (nan without sky)."""
        return float(self.zenith / np.exp(self.metered_bright))


def surface_mask(range_map: NDArray, K: NDArray, T_ego_cam: NDArray) -> NDArray[np.bool_]:
    """(H, W) the facade pixels (module docstring) of the ray lengths ``range_map`` (H, W) [m] (inf = sky) of the
    pinhole ``K`` (3, 3) mounted at ``T_ego_cam`` (4, 4; ego z up; its origin need not lie on the ground)."""
    rng = np.asarray(range_map, dtype=np.float64)
    surf = pixel_normals(rng, CameraGeometry(np.asarray(K, dtype=np.float64), np.asarray(T_ego_cam, dtype=np.float64)))
    z = surf.points_world[..., 2]
    nz = np.abs(surf.normals_world[..., 2])
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(rng)
        level = finite & (rng <= GROUND_RANGE_M) & (nz >= MIN_GROUND_NORMAL_Z)
        ground = float(np.nanpercentile(z[level], 10.0)) if int(level.sum()) >= MIN_PIXELS else 0.0
        return finite & (rng <= SURFACE_RANGE_M) & (z - ground >= MIN_HEIGHT_M) & (nz <= MAX_NORMAL_Z)


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
    facade = np.flatnonzero(surface_mask(range_map, K, T_ego_cam))
    facade = facade[:: max(1, -(-len(facade) // MAX_SURFACE_PIXELS))]
    log_y = np.log(np.maximum(y.ravel()[facade], LOG_FLOOR)).astype(np.float64)
    return FrameLight(zenith, bright, log_y, layers.lit.ravel()[facade].astype(np.float64), layers.direct_to_diffuse)


def log_gain(lit: NDArray, sun_transmittance: float, diffuse_gain: NDArray, direct_to_diffuse: float) -> F64:
    """Log of the operator's luminance gain ``(Q + T s m) / (1 + s m)`` of lit shares ``lit`` (P,) at the diffuse
    gains ``diffuse_gain`` (G,): (G, P)."""
    s = float(direct_to_diffuse)
    m = np.asarray(lit, dtype=np.float64)[None, :]
    q = np.asarray(diffuse_gain, dtype=np.float64).reshape(-1, 1)
    return np.log((q + sun_transmittance * s * m) / (1.0 + s * m))


def simulated_brightness(frames: Sequence[FrameLight], sun_transmittance: float) -> F64:
    """(F, len(GAIN_GRID)) each clear frame's facade brightness (median log-luminance) under the operator's light at
    ``sun_transmittance`` and every Q of `GAIN_GRID` (rows of nan for frames with too few facade pixels)."""
    out = np.full((len(frames), len(GAIN_GRID)), np.nan)
    for f, fr in enumerate(frames):
        if len(fr.log_y) >= MIN_PIXELS:
            moved = fr.log_y[None, :] + log_gain(fr.lit, sun_transmittance, GAIN_GRID, fr.direct_to_diffuse)
            out[f] = np.median(moved, axis=1)
    return out


def gain_for(table: F64, target: float) -> float:
    """The Q at which the mean over frames of ``table`` (F, len(GAIN_GRID)) (`simulated_brightness`: rising with Q)
    is ``target``, log-linearly interpolated (clamped to the grid's ends; nan without a frame)."""
    curve = np.nanmean(table, axis=0) if np.isfinite(table).any() else np.full(len(GAIN_GRID), np.nan)
    if not np.isfinite(curve).all() or not np.isfinite(target):
        return np.nan
    return float(np.exp(np.interp(target, curve, np.log(GAIN_GRID))))


@dataclass(frozen=True)
class OvercastFit:
    """The recovered overcast of one weather split with frame-bootstrap intervals ``(low, high)``: the zenith
    luminance L_z, ζ, and the diffuse gain Q at each sun transmittance of ``sun_grid`` (T itself is not identified);
    the reference's facade brightness and frame count."""

    zenith_luminance: float
    zenith_ci: tuple[float, float]
    zenith_over_surface: float
    zeta_ci: tuple[float, float]
    sun_grid: tuple[float, ...]
    diffuse_gains: tuple[float, ...]
    gain_ci_low: tuple[float, ...]
    gain_ci_high: tuple[float, ...]
    reference_brightness: float
    frames: int

    def diffuse_gain(self, sun_transmittance: float) -> float:
        """Q at ``sun_transmittance`` (interpolated on ``sun_grid``, clamped to its ends)."""
        return float(np.interp(sun_transmittance, self.sun_grid, self.diffuse_gains))

    def rates_entry(self) -> dict[str, object]:
        """The split's entry of ``rates.json["overcast"]`` (read by `weatheralign.simulate.media`):
        ``sun_transmittance`` null (not identified: the simulation's params give it, Q then read off the curve)."""
        return {"zenith_luminance": self.zenith_luminance, "zenith_ci_low": self.zenith_ci[0],
                "zenith_ci_high": self.zenith_ci[1], "zenith_over_surface": self.zenith_over_surface,
                "zeta_ci_low": self.zeta_ci[0], "zeta_ci_high": self.zeta_ci[1], "sun_transmittance": None,
                "sun_ci_low": None, "sun_ci_high": None, "sun_grid": list(self.sun_grid),
                "diffuse_gain_by_sun": list(self.diffuse_gains), "gain_ci_low": list(self.gain_ci_low),
                "gain_ci_high": list(self.gain_ci_high)}

    def metrics(self) -> dict[str, object]:
        return {**self.rates_entry(), "reference_brightness": self.reference_brightness, "frames": self.frames}


def _point(tables: Sequence[F64], weather: Sequence[FrameLight], clear_idx: NDArray, weather_idx: NDArray) -> F64:
    """(2 + len(SUN_GRID),) L_z, ζ and Q at every T of `SUN_GRID` of one (re)sample of frames (``tables`` the clear
    frames' `simulated_brightness` per T)."""
    w = [weather[i] for i in weather_idx]
    with np.errstate(invalid="ignore"):
        zenith = float(np.nanmean([fr.zenith for fr in w])) if any(np.isfinite(fr.zenith) for fr in w) else np.nan
        zetas = [fr.zenith_over_surface for fr in w if np.isfinite(fr.zenith)]
        target = [fr.brightness for fr in w if np.isfinite(fr.brightness)]
    zeta = float(np.mean(zetas)) if zetas else np.nan
    goal = float(np.mean(target)) if target else np.nan
    return np.array([zenith, zeta, *(gain_for(t[clear_idx], goal) for t in tables)])


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
    tables = [simulated_brightness(clear, t) for t in SUN_GRID]
    nc, nw = len(clear), len(weather)
    estimate = _point(tables, weather, np.arange(nc), np.arange(nw))
    rng = np.random.default_rng(seed)
    boot = np.array([_point(tables, weather, rng.integers(0, nc, nc), rng.integers(0, nw, nw))
                     for _ in range(num_bootstrap)]) if num_bootstrap > 0 else estimate[None, :]
    tail = (1.0 - confidence) / 2.0
    with np.errstate(invalid="ignore"):
        low, high = np.nanquantile(boot, tail, axis=0), np.nanquantile(boot, 1.0 - tail, axis=0)
    brightness = [fr.brightness for fr in weather if np.isfinite(fr.brightness)]
    return OvercastFit(float(estimate[0]), (float(low[0]), float(high[0])), float(estimate[1]),
                       (float(low[1]), float(high[1])), SUN_GRID, tuple(float(q) for q in estimate[2:]),
                       tuple(float(q) for q in low[2:]), tuple(float(q) for q in high[2:]),
                       float(np.mean(brightness)) if brightness else np.nan, nw)


__all__ = ["GAIN_GRID", "GROUND_RANGE_M", "MAX_NORMAL_Z", "MAX_SURFACE_PIXELS", "MIN_GROUND_NORMAL_Z", "MIN_HEIGHT_M",
           "MIN_PIXELS", "SUN_GRID", "SURFACE_RANGE_M", "FrameLight", "OvercastFit", "fit_overcast", "frame_light",
           "gain_for", "log_gain", "simulated_brightness", "surface_mask"]
