"""Optics of a water film over a diffuse pavement: what a wet road returns to a LiDAR and shows to a camera.

The pavement is Lambertian with reflectivity ``rho`` (at the sensor's wavelength); a flat water layer of refractive
index ``n`` lies on it. A collimated beam arriving at incidence ``theta`` (from the surface normal):

1. is partly reflected by the air-water surface (Fresnel, `fresnel_reflectance`); the rest, ``T(theta)``, enters;
2. is scattered by the pavement (Lambertian, albedo ``rho``); the upwelling light meets the water-air surface at
   every angle, and the part reflected back down, the hemispherical internal reflectance ``r_i``
   (`hemispherical_reflectance` from inside, total internal reflection included), is scattered again:
   ``1 / (1 - rho r_i)`` in all;
3. leaves towards direction ``theta`` with ``T(theta)``, its radiance divided by ``n^2`` (the solid angle widens
   on the way out: radiance / n^2 is conserved across a surface).

Radiance towards a monostatic LiDAR, wet over dry (`wet_lidar_factor`, Lekner & Dorf 1988, Appl. Opt. 27(7)):

    W(theta) = T(theta)^2 exp(-2 a h / cos theta_w) / (n^2 (1 - rho r_i))

with ``theta_w`` the refracted angle, ``a`` water's absorption coefficient and ``h`` the film's thickness (the
absorption along the specular path in and out). Under diffuse sky light the wet pavement's albedo is
``(1 - r_e)(1 - r_i) rho / (1 - rho r_i)`` (`wet_albedo`), ``r_e`` the hemispherical reflectance from outside;
reciprocity ties the two: ``n^2 (1 - r_i) = 1 - r_e`` (tested). A LiDAR's glint (the mirror reflection straight
back) needs normal incidence, which a car-mounted LiDAR never has on the road (its lowest ring meets the ground
60 degrees or more from the normal), so it is left out.

`wet_lidar_factor_naive` traces photons through the film (Fresnel at every crossing, total internal reflection,
Lambertian re-emission) and counts those leaving towards ``theta``: the closed form's oracle.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

WATER_INDEX = 1.33
"""Refractive index of water at visible and near-infrared wavelengths (1.333 at 589 nm, 1.328 at 905 nm)."""
WATER_ABSORPTION_905_PER_M = 6.8
"""Absorption coefficient of water at 905 nm [1/m] (Hale & Querry 1973: k = 4.9e-7, a = 4 pi k / lambda)."""


def fresnel_reflectance(theta: ArrayLike, n1: float, n2: float) -> F64:
    """Unpolarised Fresnel power reflectance of a flat surface from medium ``n1`` into ``n2`` at incidence
    ``theta`` [rad] (the mean of s and p); 1 beyond the critical angle (total internal reflection)."""
    theta = np.asarray(theta, dtype=np.float64)
    cos_i = np.cos(theta)
    sin_t = n1 / n2 * np.sin(theta)
    total = sin_t >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin_t**2, 0.0, None))
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return np.where(total, 1.0, 0.5 * (rs + rp))


def refraction_angle(theta: ArrayLike, n1: float, n2: float) -> F64:
    """Snell's law: the angle [rad] of the ray refracted from ``n1`` into ``n2`` (``n1 sin theta <= n2``)."""
    return np.arcsin(np.clip(n1 / n2 * np.sin(np.asarray(theta, dtype=np.float64)), -1.0, 1.0))


@lru_cache(maxsize=64)
def hemispherical_reflectance(n1: float, n2: float, nodes: int = 2048) -> float:
    """Reflectance of a flat ``n1``-``n2`` surface for Lambertian (isotropic) light arriving from the ``n1`` side:
    ``2 int_0^{pi/2} R(theta) cos theta sin theta dtheta`` (Gauss-Legendre in ``sin^2 theta``)."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    s2 = 0.5 * (x + 1.0)  # sin^2 theta in (0, 1); d(sin^2) = 2 sin cos dtheta
    if n1 > n2:  # the integrand jumps to 1 at the critical angle: integrate the two pieces separately
        critical = (n2 / n1) ** 2
        below = critical * s2
        r = fresnel_reflectance(np.arcsin(np.sqrt(below)), n1, n2)
        return float(0.5 * critical * np.sum(w * r) + (1.0 - critical))
    r = fresnel_reflectance(np.arcsin(np.sqrt(s2)), n1, n2)
    return float(0.5 * np.sum(w * r))


def wet_lidar_factor(theta: ArrayLike, rho: ArrayLike, film_m: ArrayLike = 0.0, n: float = WATER_INDEX,
                     absorption_per_m: float = WATER_ABSORPTION_905_PER_M) -> F64:
    """Radiance of water-covered over dry Lambertian pavement (reflectivity ``rho``) towards a monostatic LiDAR at
    incidence ``theta`` [rad] (broadcast), the water ``film_m`` thick [m]: ``W(theta)`` of the module docstring."""
    theta = np.asarray(theta, dtype=np.float64)
    rho = np.asarray(rho, dtype=np.float64)
    transmitted = 1.0 - fresnel_reflectance(theta, 1.0, n)
    cos_w = np.cos(refraction_angle(theta, 1.0, n))
    absorbed = np.exp(-2.0 * absorption_per_m * np.asarray(film_m, dtype=np.float64) / cos_w)
    r_i = hemispherical_reflectance(n, 1.0)
    return transmitted**2 * absorbed / (n**2 * (1.0 - rho * r_i))


def wet_albedo(rho: ArrayLike, n: float = WATER_INDEX) -> F64:
    """Albedo of Lambertian pavement ``rho`` under a water film, lit by diffuse light (Lekner & Dorf 1988):
    ``(1 - r_e)(1 - r_i) rho / (1 - rho r_i)``."""
    rho = np.asarray(rho, dtype=np.float64)
    r_e, r_i = hemispherical_reflectance(1.0, n), hemispherical_reflectance(n, 1.0)
    return (1.0 - r_e) * (1.0 - r_i) * rho / (1.0 - rho * r_i)


def wet_lidar_factor_naive(theta: float, rho: float, n: float = WATER_INDEX, photons: int = 2_000_000,
                           half_width: float = 0.02, seed: int = 0, max_bounces: int = 200) -> float:
    """`wet_lidar_factor` (no absorption) by tracing ``photons`` through the film: Fresnel reflection or
    transmission at the air-water surface, Lambertian re-emission (or absorption, ``1 - rho``) at the pavement,
    Fresnel or total internal reflection from below; the photons leaving into the band of directions ``theta +-
    half_width`` [rad] give the radiance there, divided by the dry pavement's ``rho / pi``. Slow; the test oracle."""
    rng = np.random.default_rng(seed)
    entered = rng.random(photons) >= fresnel_reflectance(theta, 1.0, n)
    alive = int(entered.sum())
    escaped_sin = []
    for _ in range(max_bounces):
        if alive == 0:
            break
        alive = int((rng.random(alive) < rho).sum())  # survive the pavement, re-emitted Lambertian
        cos_w = np.sqrt(rng.random(alive))
        theta_w = np.arccos(cos_w)
        reflected = rng.random(alive) < fresnel_reflectance(theta_w, n, 1.0)
        escaped_sin.append(n * np.sin(theta_w[~reflected]))
        alive = int(reflected.sum())
    sin_out = np.concatenate(escaped_sin)
    lo, hi = max(theta - half_width, 0.0), min(theta + half_width, np.pi / 2)
    in_band = np.count_nonzero((sin_out >= np.sin(lo)) & (sin_out < np.sin(hi)))
    projected_solid_angle = np.pi * (np.sin(hi) ** 2 - np.sin(lo) ** 2)  # int cos dOmega over the band
    radiance = in_band / photons / projected_solid_angle
    return float(radiance / (rho / np.pi))


__all__ = ["fresnel_reflectance", "hemispherical_reflectance", "refraction_angle", "WATER_ABSORPTION_905_PER_M",
           "WATER_INDEX", "wet_albedo", "wet_lidar_factor", "wet_lidar_factor_naive"]
