"""The synthetic reference's camera: clear radiance of the world and fog by per-pixel integration along the ray.

Radiative transfer in a homogeneous fog of extinction α [1/m] (single scattering of an ambient airlight radiance
``A``, absorption-free droplets): along a pixel's ray of length ``ℓ`` [m] to the surface of clear radiance ``J``

    I = J exp(-α ℓ) + ∫_0^ℓ α A exp(-α s) ds.

The in-scattered term is integrated numerically per pixel (not by Koschmieder's closed form, which the fast camera
fog uses): in optical depth ``τ = α s``, over panels of ``PANEL_TAU`` with 5-point Gauss-Legendre, up to
``min(α ℓ, TAU_CUTOFF)`` (beyond ``τ = 40`` the integrand is below 1e-17 of its start). Sky pixels (no surface) are
integrated out to a finite ``sky_distance`` [m] with the clear sky's radiance behind it; for the reference's fog
levels (α >= 0.006 /m, 2 km: ``α ℓ >= 12``) the sky is fully fogged to 6e-6. Everything is in linear light; the
result is encoded to sRGB and the sensor noise (in encoded units, as the world's cameras) added before rounding.

Clear radiance ``J`` is the synthetic world's shading (`weatheralign.world.shading.camera_radiance`): the same textures,
sun, sky and shadows as the world's cameras, kept in linear light here instead of being encoded.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.camera.fog import linear_to_srgb

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

PANEL_TAU = 0.5
"""Optical thickness of one quadrature panel."""

TAU_CUTOFF = 40.0
"""Optical depth beyond which the in-scattered integrand (``e^{-τ}`` < 5e-18) is negligible."""

_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)


@njit(cache=True, nogil=True)
def _fog_kernel(J, ell, alpha, A, sky_distance, gl_x, gl_w, out):  # pragma: no cover
    for i in range(J.shape[0]):
        length = ell[i]
        if not math.isfinite(length):
            length = sky_distance
        tau_end = alpha * length
        trans = math.exp(-tau_end)
        upper = min(tau_end, TAU_CUTOFF)
        n_panels = int(math.ceil(upper / PANEL_TAU)) if upper > 0.0 else 0
        scatter = 0.0
        for p in range(n_panels):
            lo = p * upper / n_panels
            hi = (p + 1) * upper / n_panels
            mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            acc = 0.0
            for k in range(gl_x.shape[0]):
                acc += gl_w[k] * math.exp(-(mid + half * gl_x[k]))
            scatter += half * acc  # ∫ e^{-τ} dτ over the panel (= ∫ α e^{-α s} ds)
        for c in range(3):
            out[i, c] = J[i, c] * trans + A[c] * scatter


def fog_radiance(J: NDArray, ray_length: NDArray, alpha: float, airlight: NDArray,
                 sky_distance: float = 2000.0) -> F64:
    """Linear radiance (N, 3) through homogeneous fog, by numerical integration along each ray.

    Args:
        J: (N, 3) clear linear radiance of each pixel.
        ray_length: (N,) ray length [m] to the surface, ``inf`` for sky.
        alpha: extinction [1/m] (>= 0).
        airlight: (3,) linear airlight radiance ``A``.
        sky_distance: length [m] a sky ray is integrated over (its clear radiance lies behind it).

    Raises:
        ValueError: bad shapes, ``alpha`` < 0, negative ray lengths, ``sky_distance`` <= 0.
    """
    J = np.ascontiguousarray(J, dtype=np.float64)
    ell = np.ascontiguousarray(ray_length, dtype=np.float64).ravel()
    A = np.ascontiguousarray(np.broadcast_to(np.asarray(airlight, dtype=np.float64), (3,)))
    if J.ndim != 2 or J.shape[1] != 3 or ell.shape != (J.shape[0],):
        raise ValueError(f"fog_radiance: J must be (N, 3) and ray_length (N,), got {J.shape} and {ell.shape}")
    if not (math.isfinite(alpha) and alpha >= 0.0):
        raise ValueError(f"fog_radiance: alpha = {alpha!r}; expected a finite extinction >= 0 [1/m]")
    if np.any(ell < 0.0):
        raise ValueError("fog_radiance: negative ray lengths")
    if not (math.isfinite(sky_distance) and sky_distance > 0.0):
        raise ValueError(f"fog_radiance: sky_distance = {sky_distance!r}; expected > 0 m")
    out = np.empty_like(J)
    _fog_kernel(J, ell, float(alpha), A, float(sky_distance), _GL_X, _GL_W, out)
    return out


def encode_with_noise(linear: NDArray, noise_std: float, rng: np.random.Generator) -> NDArray[np.uint8]:
    """uint8 sRGB of linear RGB (..., 3): exact sRGB encoding, plus Gaussian noise of ``noise_std`` in encoded units
    [0, 1] (drawn for every value, standard normal x std), rounded and clipped to 0..255."""
    encoded = linear_to_srgb(linear)
    if noise_std > 0.0:
        encoded = encoded + noise_std * rng.standard_normal(encoded.shape)
    return np.clip(np.rint(encoded * 255.0), 0, 255).astype(np.uint8)
