"""Particle size distributions of snow and rain, and their bulk optics (``docs/physics.md`` 3.1-3.2).

Both media use a truncated exponential number spectrum ``N(D) = n0 exp(-lam D)`` for ``d_min <= D <= d_max``
[particles per m³ per m of diameter], held by `ExponentialSizeDistribution`. The physical parameterisations build one:

- `SnowSizeDistribution` (Hahner et al. 2022): snowfall rate S [mm/h water equivalent] and terminal velocity v [m/s]
  give the occupied volume fraction ``occ = S / (3.6e6 · rho_s · v)`` (snow density rho_s = 0.1 g/cm³) and an
  "equivalent rain rate" ``R = (S / (487 · rho_s · 0.003 · v))^1.5`` [mm/h] (both exactly as in Hahner's
  ``compute_occupancy`` / ``snowfall_rate_to_rainfall_rate``); R sets the slope, Gunn–Marshall
  ``lam = 25.5 R^-0.48`` /cm or Sekhon–Srivastava ``lam = 22.9 R^-0.45`` /cm; diameters are capped at 20 mm; and
  ``n0`` is fixed by Hahner's occupancy relation ``∫ (π/6) D³ N(D) dD = occ``.
  (Hahner applies ``occ`` as an area fraction of 2-D cross-sections; for a statistically homogeneous medium the
  area fraction of a plane section equals the volume fraction, so the 3-D normalisation is the same number.)
- `RainSizeDistribution` (LISA, Marshall–Palmer): ``N(D) = 8000 exp(-lam D)`` m⁻³ mm⁻¹, ``lam = 4.1 R^-0.21`` /mm,
  for ``D >= 0.05 mm`` (LISA's minimum) up to 6 mm (larger drops break up).

Bulk optics: ``extinction = ∫ Q_ext (π/4) D² N(D) dD`` with ``Q_ext = 2``, the geometric-optics (large-particle)
limit of Mie theory, valid for D >> wavelength (905 nm LiDAR, visible camera): a particle removes twice its
cross-section from the forward beam (absorption/reflection + diffraction). Diffraction is scattered into a narrow
forward lobe, so this is the extinction of a narrow beam, which is what a LiDAR and a camera pixel see.

All lengths in metres unless a name says otherwise (rates in mm/h, as meteorology gives them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.special import gamma as gamma_fn
from scipy.special import gammaincc

F64 = NDArray[np.float64]

SNOW_REFLECTIVITY = 0.9
"""Snowflake reflectivity at the LiDAR wavelength (Hahner et al. 2022: 90 %)."""

RAIN_REFLECTIVITY = 0.02
"""Raindrop reflectance: water's normal-incidence Fresnel reflectance ((n - 1) / (n + 1))² with n = 1.33."""

Q_EXT_GEOMETRIC = 2.0
"""Extinction efficiency of particles much larger than the wavelength (geometric-optics limit)."""

Q_IMAGING = 1.0
"""Extinction efficiency of snowflakes and raindrops for a camera pixel: their geometric shadow. The other half of
`Q_EXT_GEOMETRIC` is light diffracted into a lobe of ``λ / D`` (~0.5 mrad for a 1 mm particle in visible light),
narrower than a pixel (~0.8 mrad at nuScenes' f ≈ 1266 px): the pixel keeps it. (A LiDAR beam of 3 mrad keeps it
too: `weatheralign.lidar.particles` counts the shadow once as well.)"""

SnowModel = Literal["gunn_marshall", "sekhon_srivastava"]


def _positive(name: str, value: float, unit: str, allow_zero: bool = False) -> float:
    v = float(value)
    ok = math.isfinite(v) and (v >= 0.0 if allow_zero else v > 0.0)
    if not ok:
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} = {value!r} [{unit}] is invalid: must be finite and {bound}")
    return v


def gunn_marshall_lambda(rain_rate: float) -> float:
    """Gunn–Marshall (1958) exponential slope [1/m] for precipitation rate ``rain_rate`` [mm/h]: 25.5 R^-0.48 /cm."""
    return 25.5 * _positive("rain_rate", rain_rate, "mm/h") ** -0.48 * 100.0


def sekhon_srivastava_lambda(rain_rate: float) -> float:
    """Sekhon–Srivastava (1970) exponential slope [1/m] for ``rain_rate`` [mm/h]: 22.9 R^-0.45 /cm."""
    return 22.9 * _positive("rain_rate", rain_rate, "mm/h") ** -0.45 * 100.0


def marshall_palmer_lambda(rain_rate: float) -> float:
    """Marshall–Palmer (1948) slope [1/m] for ``rain_rate`` [mm/h]: 4.1 R^-0.21 /mm."""
    return 4.1 * _positive("rain_rate", rain_rate, "mm/h") ** -0.21 * 1000.0


def snow_occupancy(snowfall_rate: float, terminal_velocity: float, snow_density: float = 0.1) -> float:
    """Volume fraction occupied by snow (Hahner): ``S / (3.6e6 · rho_s · v)``.

    Args:
        snowfall_rate: S [mm/h liquid-water equivalent], > 0.
        terminal_velocity: v [m/s], > 0.
        snow_density: rho_s [g/cm³] of the flakes, in (0, 1].
    Returns:
        dimensionless volume fraction (S/3.6e6 is the water flux in m/s; times 1/rho_s the snow volume flux; / v the
        snow volume per m³ of air).
    """
    s = _positive("snowfall_rate", snowfall_rate, "mm/h")
    v = _positive("terminal_velocity", terminal_velocity, "m/s")
    rho = _snow_density(snow_density)
    return s / (3.6e6 * rho * v)


def snow_equivalent_rain_rate(snowfall_rate: float, terminal_velocity: float, snow_density: float = 0.1,
                              reference_diameter: float = 0.003) -> float:
    """Hahner's equivalent rain rate [mm/h] that sets the snow size slope: ``(S / (487 rho_s d v))^1.5``.

    ``d = 0.003`` is Hahner's fixed "snowflake_diameter" (passed in metres, as in his code). For S = 2 mm/h and
    v = 1.5 m/s this is 27.6 mm/h, ~14x the water-equivalent rate that Gunn–Marshall and Sekhon–Srivastava
    define their slopes with; kept as published because the resulting flakes (mean diameter 1.9 mm, ~166 per m³
    at that rate) are plausible snowflake sizes, whereas R = S would describe melted-drop sizes.
    """
    s = _positive("snowfall_rate", snowfall_rate, "mm/h")
    v = _positive("terminal_velocity", terminal_velocity, "m/s")
    rho = _snow_density(snow_density)
    d = _positive("reference_diameter", reference_diameter, "m")
    return (s / (487.0 * rho * d * v)) ** 1.5


def _snow_density(snow_density: float) -> float:
    rho = float(snow_density)
    if not (math.isfinite(rho) and 0.0 < rho <= 1.0):
        raise ValueError(f"snow_density = {snow_density!r} [g/cm³] is invalid: must be in (0, 1]")
    return rho


def rain_terminal_velocity(diameter: NDArray | float) -> F64:
    """Terminal fall speed [m/s] of raindrops of ``diameter`` [m] (any shape): Atlas et al. (1973) fit to
    Gunn–Kinzer, ``9.65 - 10.3 exp(-600 D)``, clipped at 0 (the fit is negative below D ≈ 0.1 mm)."""
    d = np.asarray(diameter, dtype=np.float64)
    return np.maximum(9.65 - 10.3 * np.exp(-600.0 * d), 0.0)


MEDIAN_VOLUME_FACTOR = 3.67
"""``Λ D0`` of an exponential spectrum: the median of the volume-weighted spectrum ``D³ exp(-ΛD)`` (a Gamma(4)
distribution, whose median is 3.672), the standard median-volume diameter ``D0 = 3.67 / Λ``."""


def rain_median_volume_diameter(rain_rate: float) -> float:
    """Median-volume diameter D0 [m] of Marshall–Palmer rain of ``rain_rate`` [mm/h]: ``3.67 / Λ``, ``Λ = 4.1
    R^-0.21`` /mm (1.25 / 2.04 / 2.35 mm at 5 / 50 / 100 mm/h; the spectrum's 6 mm cap would lower it by 0.3 % at 50
    and 1 % at 100 mm/h)."""
    return MEDIAN_VOLUME_FACTOR / marshall_palmer_lambda(rain_rate)


def rain_field_fall_speed(rain_rate: float) -> float:
    """The one fall speed [m/s] of a rain field of ``rain_rate`` [mm/h]: `rain_terminal_velocity` at the
    median-volume diameter `rain_median_volume_diameter` (4.80 / 6.61 / 7.14 m/s at 5 / 50 / 100 mm/h).

    Why D0. A particle field has one velocity (the LiDAR's particle kernels work in the frame co-moving with it), so
    the drops' spread of speeds (0 to 9.6 m/s) is replaced by the speed of one characteristic drop. The drops that
    make the visible rain are the ones to get right: a drop of diameter D draws a streak of integrated alpha ∝ its
    projected area ``D² / ℓ²`` (independent of the streak's length) and is resolved out to a ray length ∝ D
    (`weatheralign.camera.splat.max_splat_range`), so over the volume a camera resolves (``ℓ² dℓ`` per solid
    angle) the streak energy of the drops of size D is ∝ ``D³ N(D)``, whose median is exactly D0, for every focal
    length. Half of the rain a camera draws comes from drops larger than D0.

    Limits. With the camera's near clip (0.5 m) the energy median is 5-15 % larger (nuScenes' f ≈ 1266 px: 2.21 mm
    and 6.9 m/s at 50 mm/h instead of 2.04 mm and 6.6 m/s); each smaller drop falls too fast and each larger one
    too slow (a 0.5 mm drop falls at 2.0 m/s, a 4 mm one at 8.7 m/s, all here at the one speed), so individual
    streak lengths are off while their total energy and mean direction are right. The LiDAR hardly depends on it
    (a sweep lasts 50 ms).
    """
    return float(rain_terminal_velocity(rain_median_volume_diameter(rain_rate)))


@dataclass(frozen=True)
class ExponentialSizeDistribution:
    """Truncated exponential number spectrum ``N(D) = n0 exp(-lam D)`` on ``[d_min, d_max]``.

    Attributes:
        n0: intercept [1/m⁴] (particles per m³ per m of diameter; 8000 m⁻³ mm⁻¹ = 8e6 m⁻⁴), >= 0.
        lam: slope [1/m], > 0.
        d_min: smallest diameter [m], >= 0.
        d_max: largest diameter [m], > d_min.
    """

    n0: float
    lam: float
    d_min: float
    d_max: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "n0", _positive("n0", self.n0, "1/m^4", allow_zero=True))
        object.__setattr__(self, "lam", _positive("lam", self.lam, "1/m"))
        object.__setattr__(self, "d_min", _positive("d_min", self.d_min, "m", allow_zero=True))
        object.__setattr__(self, "d_max", _positive("d_max", self.d_max, "m"))
        if not self.d_max > self.d_min:
            raise ValueError(f"d_max = {self.d_max!r} [m] is invalid: must exceed d_min = {self.d_min!r}")

    def spectrum(self) -> ExponentialSizeDistribution:
        """The distribution itself (the interface the particle field consumes)."""
        return self

    def _range(self, d_lo: float | None, d_hi: float | None) -> tuple[float, float]:
        a = self.d_min if d_lo is None else min(max(float(d_lo), self.d_min), self.d_max)
        b = self.d_max if d_hi is None else min(max(float(d_hi), self.d_min), self.d_max)
        return a, max(a, b)

    def _partial_moment(self, k: int, a: float, b: float | F64) -> float | F64:
        """``∫_a^b D^k exp(-lam D) dD`` [m^(k+1)] (upper incomplete gamma, stable for any a, b; elementwise for an
        array ``b``)."""
        la, lb = self.lam * a, self.lam * np.asarray(b, dtype=np.float64)
        moment = gamma_fn(k + 1) / self.lam ** (k + 1) * (gammaincc(k + 1, la) - gammaincc(k + 1, lb))
        return float(moment) if moment.ndim == 0 else moment

    def number_density(self, d_lo: float | None = None, d_hi: float | None = None) -> float:
        """Particles per m³ with diameter in ``[d_lo, d_hi]`` ∩ support (default: the whole support)."""
        a, b = self._range(d_lo, d_hi)
        return self.n0 / self.lam * (math.exp(-self.lam * a) - math.exp(-self.lam * b))

    def pdf(self, diameter: NDArray | float) -> F64:
        """Probability density [1/m] of diameters [m] (any shape); 0 outside ``[d_min, d_max]``."""
        d = np.asarray(diameter, dtype=np.float64)
        norm = -math.expm1(-self.lam * (self.d_max - self.d_min))
        inside = (d >= self.d_min) & (d <= self.d_max)
        return np.where(inside, self.lam * np.exp(-self.lam * (d - self.d_min)) / norm, 0.0)

    def cdf(self, diameter: NDArray | float) -> F64:
        """Cumulative distribution of diameters [m] (any shape)."""
        d = np.clip(np.asarray(diameter, dtype=np.float64), self.d_min, self.d_max)
        return np.expm1(-self.lam * (d - self.d_min)) / math.expm1(-self.lam * (self.d_max - self.d_min))

    def ppf(self, q: NDArray | float) -> F64:
        """Inverse CDF: diameters [m] of quantiles ``q`` in [0, 1] (any shape)."""
        u = np.asarray(q, dtype=np.float64)
        d = self.d_min - np.log1p(u * math.expm1(-self.lam * (self.d_max - self.d_min))) / self.lam
        return np.clip(d, self.d_min, self.d_max)

    def sample_diameters(self, rng: np.random.Generator | int, n: int) -> F64:
        """``n`` diameters [m] (n,) by inverse CDF; ``rng`` is a Generator or a seed."""
        if n < 0:
            raise ValueError(f"n = {n!r} is invalid: must be >= 0")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        return self.ppf(gen.random(n))

    def moment(self, k: int) -> float:
        """``E[D^k]`` [m^k] over the support."""
        return self._partial_moment(k, self.d_min, self.d_max) / self._partial_moment(0, self.d_min, self.d_max)

    def mean_volume(self) -> float:
        """Mean particle volume ``(π/6) E[D³]`` [m³]."""
        return math.pi / 6.0 * self.moment(3)

    def volume_fraction(self) -> float:
        """Volume of particles per volume of air ``∫ (π/6) D³ N(D) dD`` (dimensionless)."""
        return self.n0 * math.pi / 6.0 * self._partial_moment(3, self.d_min, self.d_max)

    def extinction(self, d_lo: float | None = None, d_hi: float | None = None,
                   q_ext: float = Q_EXT_GEOMETRIC) -> float:
        """Extinction coefficient [1/m] of the particles with diameter in ``[d_lo, d_hi]`` ∩ support:
        ``∫ q_ext (π/4) D² N(D) dD`` (``q_ext = 2``: geometric-optics limit)."""
        a, b = self._range(d_lo, d_hi)
        return q_ext * math.pi / 4.0 * self.n0 * self._partial_moment(2, a, b)

    def extinction_below(self, d_hi: NDArray | float, q_ext: float = Q_EXT_GEOMETRIC) -> F64:
        """`extinction` of the particles with diameter at most ``d_hi`` [m], elementwise over an array (float64, shape
        of ``d_hi``): ``extinction(d_hi=x)`` for every ``x``, in one vectorised pass."""
        b = np.clip(np.asarray(d_hi, dtype=np.float64), self.d_min, self.d_max)
        return q_ext * math.pi / 4.0 * self.n0 * np.asarray(self._partial_moment(2, self.d_min, b))

    def truncated(self, min_diameter: float) -> ExponentialSizeDistribution:
        """The same spectrum restricted to ``[max(d_min, min_diameter), d_max]`` (same n0: the particles of at least
        ``min_diameter`` of this medium, exactly)."""
        m = _positive("min_diameter", min_diameter, "m", allow_zero=True)
        if m >= self.d_max:
            raise ValueError(f"min_diameter = {min_diameter!r} [m] is invalid: must be below d_max = {self.d_max}")
        return ExponentialSizeDistribution(self.n0, self.lam, max(self.d_min, m), self.d_max)


class SizeDistribution(Protocol):
    """Anything that yields an `ExponentialSizeDistribution` (the particle field's input)."""

    def spectrum(self) -> ExponentialSizeDistribution: ...


class _SpectrumMethods:
    """Statistics of a physical parameterisation, forwarded to its `ExponentialSizeDistribution`."""

    def spectrum(self) -> ExponentialSizeDistribution:  # pragma: no cover - overridden
        raise NotImplementedError

    def number_density(self, d_lo: float | None = None, d_hi: float | None = None) -> float:
        """Particles per m³ (optionally only diameters in ``[d_lo, d_hi]`` [m])."""
        return self.spectrum().number_density(d_lo, d_hi)

    def pdf(self, diameter: NDArray | float) -> F64:
        """Probability density [1/m] of diameters [m]."""
        return self.spectrum().pdf(diameter)

    def cdf(self, diameter: NDArray | float) -> F64:
        """Cumulative distribution of diameters [m]."""
        return self.spectrum().cdf(diameter)

    def sample_diameters(self, rng: np.random.Generator | int, n: int) -> F64:
        """``n`` diameters [m] (n,), inverse CDF of the truncated exponential."""
        return self.spectrum().sample_diameters(rng, n)

    def moment(self, k: int) -> float:
        """``E[D^k]`` [m^k]."""
        return self.spectrum().moment(k)

    def mean_volume(self) -> float:
        """Mean particle volume [m³]."""
        return self.spectrum().mean_volume()

    def volume_fraction(self) -> float:
        """Particle volume per air volume (dimensionless)."""
        return self.spectrum().volume_fraction()

    def extinction(self, d_lo: float | None = None, d_hi: float | None = None,
                   q_ext: float = Q_EXT_GEOMETRIC) -> float:
        """Extinction coefficient [1/m] (``Q_ext = 2``), optionally of diameters in ``[d_lo, d_hi]`` only."""
        return self.spectrum().extinction(d_lo, d_hi, q_ext)


@dataclass(frozen=True)
class SnowSizeDistribution(_SpectrumMethods):
    """Snowflakes after Hahner et al. 2022 (see the module docstring).

    Attributes:
        snowfall_rate: S [mm/h liquid-water equivalent], > 0 (light < 1, moderate 1–2.5, heavy > 2.5).
        terminal_velocity: v [m/s] used in the occupancy relation, > 0 (0.2–2 in Hahner's sweeps).
        model: ``"gunn_marshall"`` (Λ = 25.5 R^-0.48 /cm) or ``"sekhon_srivastava"`` (Λ = 22.9 R^-0.45 /cm).
        snow_density: flake density [g/cm³], in (0, 1].
        d_max: diameter cap [m] (Hahner: 20 mm).
        d_min: smallest diameter [m] (Hahner: 0).
        reference_diameter: the fixed 3 mm [m] of Hahner's equivalent-rain-rate relation.
    """

    snowfall_rate: float
    terminal_velocity: float
    model: SnowModel = "gunn_marshall"
    snow_density: float = 0.1
    d_max: float = 0.02
    d_min: float = 0.0
    reference_diameter: float = 0.003

    def __post_init__(self) -> None:
        if self.model not in ("gunn_marshall", "sekhon_srivastava"):
            raise ValueError(f"model = {self.model!r} is invalid: must be 'gunn_marshall' or 'sekhon_srivastava'")
        _positive("snowfall_rate", self.snowfall_rate, "mm/h")
        _positive("terminal_velocity", self.terminal_velocity, "m/s")
        _snow_density(self.snow_density)
        _positive("d_min", self.d_min, "m", allow_zero=True)
        if not (math.isfinite(self.d_max) and self.d_max > self.d_min):
            raise ValueError(f"d_max = {self.d_max!r} [m] is invalid: must be finite and exceed d_min = {self.d_min}")

    @property
    def occupancy(self) -> float:
        """Occupied volume fraction ``S / (3.6e6 · rho_s · v)``."""
        return snow_occupancy(self.snowfall_rate, self.terminal_velocity, self.snow_density)

    @property
    def equivalent_rain_rate(self) -> float:
        """Hahner's equivalent rain rate [mm/h] that sets the slope."""
        return snow_equivalent_rain_rate(self.snowfall_rate, self.terminal_velocity, self.snow_density,
                                         self.reference_diameter)

    @property
    def rate_parameter(self) -> float:
        """Exponential slope Λ [1/m]."""
        r = self.equivalent_rain_rate
        return gunn_marshall_lambda(r) if self.model == "gunn_marshall" else sekhon_srivastava_lambda(r)

    def spectrum(self) -> ExponentialSizeDistribution:
        """The exponential spectrum with n0 set so that the volume fraction equals `occupancy`."""
        shape = ExponentialSizeDistribution(1.0, self.rate_parameter, self.d_min, self.d_max)
        n0 = self.occupancy / shape.volume_fraction()
        return ExponentialSizeDistribution(n0, shape.lam, self.d_min, self.d_max)


@dataclass(frozen=True)
class RainSizeDistribution(_SpectrumMethods):
    """Raindrops after LISA (Kilic et al. 2021): Marshall–Palmer.

    Attributes:
        rain_rate: R [mm/h], > 0 (heavy shower 10–50, violent > 50).
        d_min: smallest drop diameter [m] (LISA: 0.05 mm).
        d_max: largest drop diameter [m] (6 mm; larger drops break up).
        n0: Marshall–Palmer intercept [1/m⁴] (8000 m⁻³ mm⁻¹).
    """

    rain_rate: float
    d_min: float = 5e-5
    d_max: float = 6e-3
    n0: float = 8.0e6

    def __post_init__(self) -> None:
        _positive("rain_rate", self.rain_rate, "mm/h")
        _positive("d_min", self.d_min, "m", allow_zero=True)
        _positive("n0", self.n0, "1/m^4")
        if not (math.isfinite(self.d_max) and self.d_max > self.d_min):
            raise ValueError(f"d_max = {self.d_max!r} [m] is invalid: must be finite and exceed d_min = {self.d_min}")

    @property
    def rate_parameter(self) -> float:
        """Marshall–Palmer slope Λ [1/m]."""
        return marshall_palmer_lambda(self.rain_rate)

    def spectrum(self) -> ExponentialSizeDistribution:
        """The Marshall–Palmer spectrum on ``[d_min, d_max]``."""
        return ExponentialSizeDistribution(self.n0, self.rate_parameter, self.d_min, self.d_max)
