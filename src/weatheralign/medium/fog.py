"""Fog: a homogeneous medium with extinction ``alpha`` and backscatter ``beta`` (``docs/physics.md`` section 2.1).

Visibility (meteorological optical range, the distance at which the contrast of a black target falls to 5 %) is
``MOR = ln(20) / alpha`` (≈ 2.996 / alpha). The paper writes ``MOR = 3 / alpha`` when it states its beta grid; this
module uses ``ln(20) / alpha`` everywhere, so its beta values differ from the paper's printed ones by 0.14 %
(e.g. alpha = 0.04: beta = 0.023·2.0/MOR = 6.14e-4 here, 6.13e-4 in the paper).

In fog (MOR below ~1 km) extinction is practically wavelength-independent from the visible to 905 nm, so the camera
sees the same medium: its one-way extinction coefficient equals ``alpha`` (the LiDAR's two-way attenuation
``exp(-2 alpha R)`` is the pulse model's business, not a second medium).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

LN20 = math.log(20.0)
"""``ln(20)``: MOR = LN20 / alpha (5 % contrast threshold)."""

DEFAULT_BETA_MOR = 0.046
"""Default backscatter times MOR (Hahner 2021): ``beta = 0.046 / MOR`` [1/(m sr)]."""

PAPER_BETA_FACTORS = (1.0, 1.2, 1.4, 1.6, 1.8, 2.0)
"""The paper's beta grid: ``beta = 0.023 * factor / MOR``."""


def _check_alpha(alpha: float) -> float:
    a = float(alpha)
    if not math.isfinite(a) or a < 0.0:
        raise ValueError(f"alpha = {alpha!r} [1/m] is invalid: must be finite and >= 0 (0 means no fog)")
    return a


def mor_from_alpha(alpha: float) -> float:
    """Meteorological optical range [m] of extinction ``alpha`` [1/m]: ``ln(20) / alpha``; ``inf`` for alpha = 0."""
    a = _check_alpha(alpha)
    return math.inf if a == 0.0 else LN20 / a


def alpha_from_mor(mor: float) -> float:
    """Extinction [1/m] of a visibility ``mor`` [m] (> 0; ``inf`` gives 0, no fog)."""
    m = float(mor)
    if math.isnan(m) or m <= 0.0:
        raise ValueError(f"mor = {mor!r} [m] is invalid: must be > 0 (inf means no fog)")
    return 0.0 if math.isinf(m) else LN20 / m


def default_beta(alpha: float) -> float:
    """Hahner's default backscatter [1/(m sr)]: ``0.046 / MOR`` (= 0.046 alpha / ln 20); 0 for alpha = 0."""
    a = _check_alpha(alpha)
    return DEFAULT_BETA_MOR * a / LN20


def paper_beta_grid(alpha: float) -> NDArray[np.float64]:
    """The paper's backscatter grid (6,) [1/(m sr)]: ``0.023 * {1.0, 1.2, ..., 2.0} / MOR`` with MOR = ln(20)/alpha."""
    a = _check_alpha(alpha)
    return 0.023 * np.asarray(PAPER_BETA_FACTORS) * a / LN20


@dataclass(frozen=True)
class FogMedium:
    """Homogeneous fog.

    Attributes:
        alpha: extinction coefficient [1/m], >= 0 (0 = no fog). Same for the LiDAR (905 nm) and the camera.
        beta: backscatter coefficient [1/(m sr)], >= 0 (the LiDAR's soft-target reflectivity).
    """

    alpha: float
    beta: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "alpha", _check_alpha(self.alpha))
        b = float(self.beta)
        if not math.isfinite(b) or b < 0.0:
            raise ValueError(f"beta = {self.beta!r} [1/(m sr)] is invalid: must be finite and >= 0")
        object.__setattr__(self, "beta", b)

    @classmethod
    def with_default_beta(cls, alpha: float) -> FogMedium:
        """Fog of extinction ``alpha`` [1/m] with Hahner's default ``beta = 0.046 / MOR``."""
        return cls(alpha=alpha, beta=default_beta(alpha))

    @classmethod
    def from_mor(cls, mor: float, beta: float | None = None) -> FogMedium:
        """Fog of visibility ``mor`` [m]; ``beta`` [1/(m sr)] defaults to ``0.046 / mor``."""
        alpha = alpha_from_mor(mor)
        return cls(alpha=alpha, beta=default_beta(alpha) if beta is None else beta)

    @property
    def mor(self) -> float:
        """Visibility [m]: ``ln(20) / alpha`` (inf without fog)."""
        return mor_from_alpha(self.alpha)

    @property
    def camera_extinction(self) -> float:
        """One-way extinction [1/m] for the camera's Koschmieder transmittance ``exp(-alpha * ray_length)``."""
        return self.alpha

    def transmittance(self, path_length: NDArray | float) -> NDArray[np.float64]:
        """One-way transmittance ``exp(-alpha * path_length)`` of path lengths [m] (any shape, >= 0)."""
        return np.exp(-self.alpha * np.asarray(path_length, dtype=np.float64))
