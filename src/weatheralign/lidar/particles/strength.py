"""How strong snow and rain are in a LiDAR scan, in closed form (``docs/physics.md`` section 3.5).

Three quantities decide how many of a scan's points a particle field takes, for any simulator and any sensor:

1. **The echo of one particle.** A sphere of diameter ``D`` centred on a beam of full divergence ``θ`` at range
   ``r`` covers ``ratio = min(1, (D / 2)² / w(r)²)`` of it, ``w(r) = r tan(θ / 2)``; alone, it reports the intensity
   ``i_p = scale ρ ratio g(r)`` of the sensor's `IntensityModel` (0..255).
2. **How far it is detectable.** ``i_p`` falls with range (``ratio ∝ r⁻²`` once the particle is smaller than the beam,
   times the gain ``g``), so the particle is detected out to the range ``r_det(D)`` where ``i_p`` meets the detector
   floor. For a raw-power sensor (``g = (1 m / r)²``) whose floor lets it see a target of reflectivity ``ρ_ref``
   out to ``R_ref`` (`rated_intensity`), that is ``r_det = sqrt(D R_ref sqrt(ρ / ρ_ref) / (2 tan(θ / 2)))``: 10 m
   for a 2 mm flake in a 3 mrad beam of a sensor rated 50 m on 10 % pavement.
3. **Whether it beats the target.** A receiver that reports the strongest detected echo reports the particle when
   its raw echo ``scale ρ ratio / r²`` exceeds the target's ``i0 / (g(R0) R0²)``: in front of ``r_win(D)``, the range
   where the two are equal.

A beam meets on average ``λ = ∫ N(D) ∫_{r_min}^{R0} a(D, r) dr dD`` particles that pass both tests, ``a`` the area
of the centre positions from which a particle's disc still covers enough of the beam's (circle–circle lens,
`covered_fraction`; ``r_min`` the sensor's minimum range), so a share ``1 - exp(-λ)`` of its beams become weather
points (`expected_weather_points`). Faint echoes adding up within a pulse length, shadowing between particles,
merged echoes near the target and the unresolved particles' continuum are left out;
`tests/test_precipitation_strength.py` measures what that costs against the synthetic reference's exact process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from weatheralign.medium.distributions import SizeDistribution
from weatheralign.sensors import IntensityModel, floor_scale

F64 = NDArray[np.float64]

DIAMETER_NODES = 160
"""Size bins of the quadrature over the spectrum."""

RANGE_NODES = 240
"""Geometric range nodes of the quadrature along a beam."""

TARGET_LEVELS = 32
"""Geometric levels of the targets' raw echoes the per-beam integrals are interpolated between."""


@dataclass(frozen=True)
class EchoSensor:
    """What of a LiDAR decides whether a particle's echo is reported.

    Attributes:
        intensity: how the sensor reports intensity (`IntensityModel`: ``i = scale ρ ratio g(r)``).
        noise_floor: detector floor on the 0..255 scale: no echo is reported below it.
        divergence_rad: full beam divergence θ [rad].
        min_range_m: echoes nearer than this are not reported [m].
        max_range_m: the sensor's maximum range [m]: beams without a target listen out to it.
        floor_range_m: None: ``noise_floor`` at every range; a range [m]: a raw-power detector whose floor is
            ``noise_floor`` there and scales as ``R² g(R)`` (`weatheralign.sensors.LidarModel.floor_range_m`).
    """

    intensity: IntensityModel
    noise_floor: float
    divergence_rad: float = 3e-3
    min_range_m: float = 1.0
    max_range_m: float = 120.0
    floor_range_m: float | None = None

    def floor_at(self, r: ArrayLike) -> F64:
        """(any shape) the floor (0..255) at ranges ``r`` [m]."""
        return self.noise_floor * floor_scale(r, self.intensity, self.floor_range_m)

    def __post_init__(self) -> None:
        checks = {
            "noise_floor": (self.noise_floor, 0.0 < self.noise_floor <= 255.0, "0 < noise_floor <= 255"),
            "divergence_rad": (self.divergence_rad, 0.0 < self.divergence_rad < 0.1, "0 < divergence_rad < 0.1"),
            "min_range_m": (self.min_range_m, self.min_range_m >= 0.0, "min_range_m >= 0"),
            "max_range_m": (self.max_range_m, self.max_range_m > self.min_range_m, "max_range_m > min_range_m"),
        }
        for name, (value, ok, allowed) in checks.items():
            if not (math.isfinite(value) and ok):
                raise ValueError(f"EchoSensor.{name} = {value!r}; expected {allowed}")

    @property
    def half_tan(self) -> float:
        """``tan(θ / 2)``: the beam radius per metre of range."""
        return math.tan(0.5 * self.divergence_rad)


def rated_intensity(reflectivity: float, range_m: float, noise_floor: float, r_ref: float = 1.0,
                    falloff: float = 2.0) -> IntensityModel:
    """The `IntensityModel` (gain ``min(1, (r_ref / r)^falloff)``) whose scale puts a Lambertian target of
    ``reflectivity`` filling the beam at normal incidence at ``range_m`` [m] exactly on ``noise_floor``: a
    datasheet's "range at reflectivity" as a sensor. With the defaults (raw power, ``1 / r²`` from 1 m) the floor is
    a fixed received power; a floor of 1 keeps the reported intensities in the integer range an exact read-out
    quantises to."""
    for name, value in (("reflectivity", reflectivity), ("range_m", range_m), ("noise_floor", noise_floor)):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"rated_intensity: {name} = {value!r}; expected a finite value > 0")
    unit = IntensityModel(1.0, r_ref, falloff)
    return IntensityModel(noise_floor / float(unit.intensity(reflectivity, range_m)), r_ref, falloff)


def echo_intensity(diameter: ArrayLike, range_m: ArrayLike, reflectivity: float, sensor: EchoSensor) -> F64:
    """Intensity (0..255, unclipped) a lone particle of ``diameter`` [m] centred on the beam at ``range_m`` [m]
    reports (broadcast shapes)."""
    d = np.asarray(diameter, dtype=np.float64)
    r = np.maximum(np.asarray(range_m, dtype=np.float64), 1e-9)
    ratio = np.minimum(1.0, (0.5 * d / (r * sensor.half_tan)) ** 2)
    return sensor.intensity.intensity(reflectivity, r, ratio)


def detection_range(diameter: ArrayLike, reflectivity: float, sensor: EchoSensor, iterations: int = 60) -> F64:
    """``r_det(D)`` [m] (shape of ``diameter``): the largest range at which a lone particle's echo reaches the floor,
    capped at the sensor's maximum range; 0 where it never does. `echo_intensity` over the floor is non-increasing
    in range, so bisection in log-range (``iterations`` halvings of the ratio ``max_range / 1e-3 m``) finds it."""
    d = np.asarray(diameter, dtype=np.float64)
    lo = np.full(d.shape, math.log(1e-3))
    hi = np.full(d.shape, math.log(sensor.max_range_m))
    detected_far = echo_intensity(d, sensor.max_range_m, reflectivity, sensor) >= sensor.floor_at(sensor.max_range_m)
    detected_near = echo_intensity(d, 1e-3, reflectivity, sensor) >= sensor.floor_at(1e-3)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        ok = echo_intensity(d, np.exp(mid), reflectivity, sensor) >= sensor.floor_at(np.exp(mid))
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    r = np.exp(lo)
    return np.where(detected_far, sensor.max_range_m, np.where(detected_near, r, 0.0))


def winning_range(diameter: ArrayLike, reflectivity: float, sensor: EchoSensor, target_range_m: ArrayLike,
                  target_intensity: ArrayLike) -> F64:
    """``r_win`` [m] (broadcast shapes): in front of it a particle of ``diameter`` [m], smaller than the beam, has a
    stronger raw echo than a target of clear intensity ``target_intensity`` (0..255) at ``target_range_m`` [m]:
    ``scale ρ D² / (4 tan²(θ / 2) r⁴) = i0 / (g(R0) R0²)``. ``inf`` where there is no target (``i0 = 0``)."""
    d = np.asarray(diameter, dtype=np.float64)
    r0, i0 = np.broadcast_arrays(np.asarray(target_range_m, dtype=np.float64),
                                 np.asarray(target_intensity, dtype=np.float64))
    target_raw = _target_raw(r0, i0, sensor)
    with np.errstate(divide="ignore"):
        fourth = sensor.intensity.scale * reflectivity * d ** 2 / (4.0 * sensor.half_tan ** 2 * target_raw)
    return np.where(i0 > 0.0, fourth ** 0.25, np.inf)


def _target_raw(target_range_m: F64, target_intensity: F64, sensor: EchoSensor) -> F64:
    """Raw echo ``i0 / (g(R0) R0²)`` of each beam's target (0 without one)."""
    im = sensor.intensity
    r0 = np.where(target_intensity > 0.0, target_range_m, 1.0)
    return np.where(target_intensity > 0.0, target_intensity / (im.gain(r0) * r0 ** 2), 0.0)


def covered_fraction(offset: ArrayLike, radius_ratio: ArrayLike) -> F64:
    """Share of a beam's disc (radius 1) that a particle's disc of radius ``radius_ratio`` covers when its centre lies
    ``offset`` (beam radii) off the axis: the circle-circle lens area over π (broadcast shapes)."""
    b = np.asarray(offset, dtype=np.float64)
    a = np.asarray(radius_ratio, dtype=np.float64)
    b, a = np.broadcast_arrays(b, a)
    full = np.pi * np.minimum(1.0, a) ** 2
    bs = np.maximum(b, 1e-300)
    c1 = np.clip((bs ** 2 + 1.0 - a ** 2) / (2.0 * bs), -1.0, 1.0)
    c2 = np.clip((bs ** 2 + a ** 2 - 1.0) / (2.0 * bs * np.maximum(a, 1e-300)), -1.0, 1.0)
    kite = np.maximum((-b + 1.0 + a) * (b + 1.0 - a) * (b - 1.0 + a) * (b + 1.0 + a), 0.0)
    lens = np.arccos(c1) + a ** 2 * np.arccos(c2) - 0.5 * np.sqrt(kite)
    area = np.where(b <= np.abs(1.0 - a), full, np.where(b >= 1.0 + a, 0.0, lens))
    return area / np.pi


def offset_reaching(radius_ratio: ArrayLike, required: ArrayLike, iterations: int = 50) -> F64:
    """The largest centre offset (beam radii) at which a particle disc of ``radius_ratio`` still covers ``required``
    of the beam (broadcast shapes); 0 where it cannot even centred (`covered_fraction` falls monotonically with the
    offset, so bisection on ``[0, 1 + radius_ratio]`` finds it)."""
    a = np.asarray(radius_ratio, dtype=np.float64)
    need = np.asarray(required, dtype=np.float64)
    a, need = np.broadcast_arrays(a, need)
    lo, hi = np.zeros(a.shape), 1.0 + a
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        ok = covered_fraction(mid, a) >= need
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return np.where(np.minimum(1.0, a) ** 2 >= need, lo, 0.0)


def _diameter_nodes(distribution: SizeDistribution, nodes: int) -> tuple[F64, F64]:
    """Midpoints [m] of ``nodes`` equal bins over the spectrum's support (cut where ``exp(-Λ D)`` < 1e-13) and the
    number of particles per m³ in each bin."""
    spectrum = distribution.spectrum()
    top = min(spectrum.d_max, spectrum.d_min + 30.0 / spectrum.lam)
    edges = np.linspace(spectrum.d_min, top, nodes + 1)
    counts = np.array([spectrum.number_density(lo, hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True)])
    return 0.5 * (edges[:-1] + edges[1:]), counts


def _capture_area(ranges: F64, target_raw: float, diameters: F64, counts: F64, reflectivity: float,
                  sensor: EchoSensor) -> F64:
    """(R,) area [m²] per m³ of particles, summed over the size bins (``diameters`` [m], ``counts`` per m³), of the
    centre positions at ``ranges`` [m] from which a particle is detected and beats a target of raw echo
    ``target_raw`` (0: none): the mean number of such particles per metre of beam."""
    im = sensor.intensity
    w = ranges * sensor.half_tan  # (R,)
    peak = im.scale * reflectivity
    need = np.maximum(sensor.floor_at(ranges) / (peak * im.gain(ranges)), target_raw * ranges ** 2 / peak)  # (R,)
    offset = offset_reaching(0.5 * diameters[None, :] / w[:, None], need[:, None])  # (R, K) beam radii
    return np.pi * w ** 2 * (offset ** 2 @ counts)


def expected_weather_echoes(target_range_m: ArrayLike, target_intensity: ArrayLike, distribution: SizeDistribution,
                            reflectivity: float, sensor: EchoSensor, diameter_nodes: int = DIAMETER_NODES,
                            range_nodes: int = RANGE_NODES, target_levels: int = TARGET_LEVELS) -> F64:
    """``λ`` per beam (shape of ``target_range_m``): the mean number of particles of ``distribution`` that the beam
    meets (any overlap of their disc with the beam's) and that are detectable and beat the beam's target (range
    ``target_range_m`` [m], ``inf`` or beyond ``max_range`` for none; clear intensity ``target_intensity``, 0..255).
    ``1 - exp(-λ)`` is the probability that the beam reports a weather echo instead of its target, or on open sky.

    Quadrature: ``diameter_nodes`` size bins, ``range_nodes`` geometric ranges from the minimum range to the
    maximum, the targets' raw echoes on ``target_levels`` geometric levels (interpolated in log between them)."""
    r0 = np.asarray(target_range_m, dtype=np.float64)
    inside = np.isfinite(r0) & (r0 <= sensor.max_range_m)
    i0 = np.where(inside, np.asarray(target_intensity, dtype=np.float64), 0.0)
    reach = np.where(i0 > 0.0, np.minimum(np.where(inside, r0, 0.0), sensor.max_range_m), sensor.max_range_m)
    raw = _target_raw(np.where(inside, r0, 1.0), i0, sensor)
    diameters, counts = _diameter_nodes(distribution, diameter_nodes)
    ranges = np.geomspace(max(sensor.min_range_m, 1e-2), sensor.max_range_m, range_nodes)
    positive = raw[raw > 0.0]
    levels = (np.geomspace(positive.min(), positive.max(), target_levels) if len(positive) and
              positive.max() > positive.min() else np.unique(positive))
    table = np.zeros((len(levels) + 1, range_nodes))  # cumulative λ along the beam; row 0: no target
    for row, level in enumerate(np.concatenate([[0.0], levels])):
        area = _capture_area(ranges, float(level), diameters, counts, reflectivity, sensor)
        table[row, 1:] = np.cumsum(0.5 * (area[1:] + area[:-1]) * np.diff(ranges))
    flat_reach, flat_raw = reach.reshape(-1), raw.reshape(-1)
    lam = np.interp(flat_reach, ranges, table[0])
    has = flat_raw > 0.0
    if has.any():
        lam_rows = np.stack([np.interp(flat_reach[has], ranges, table[1 + k]) for k in range(len(levels))])
        if len(levels) == 1:
            lam[has] = lam_rows[0]
        else:
            pos = np.interp(np.log(flat_raw[has]), np.log(levels), np.arange(len(levels)))
            k = np.minimum(pos.astype(np.int64), len(levels) - 2)
            frac = pos - k
            cols = np.arange(has.sum())
            lam[has] = (1.0 - frac) * lam_rows[k, cols] + frac * lam_rows[k + 1, cols]
    return lam.reshape(r0.shape)


def expected_weather_points(target_range_m: ArrayLike, target_intensity: ArrayLike, distribution: SizeDistribution,
                            reflectivity: float, sensor: EchoSensor) -> dict[str, float]:
    """Expected weather points of one scan: ``scattered`` (beams with a target that report a particle instead) and
    ``clutter`` (beams without a target that report one), from `expected_weather_echoes`."""
    r0 = np.asarray(target_range_m, dtype=np.float64)
    has = np.isfinite(r0) & (r0 <= sensor.max_range_m) & (np.asarray(target_intensity) > 0.0)
    p = -np.expm1(-expected_weather_echoes(r0, target_intensity, distribution, reflectivity, sensor))
    return {"scattered": float(p[has].sum()), "clutter": float(p[~has].sum())}
