"""The synthetic reference's overcast light: its snow and rain splits seen under a cloud deck of hidden parameters
(``docs/physics.md`` section 4.3).

Hidden truth. Per split (snow, rain) the direct sun's transmittance through the cloud ``T`` and the overcast sky's
zenith luminance ``L_z`` (in the reference camera's linear units: its fixed exposure, the one of its clear frames),
drawn uniformly in ``reference.precipitation.overcast_sun_transmittance`` / ``overcast_zenith_luminance`` from
``reference.seed`` (`draw_overcast_truth`) and sealed beside the rates and ground depths.

Light. The sky is the CIE standard overcast sky ``L(γ) = L_z (1 + 2 sin γ) / 3`` (grey); a surface of albedo ρ and
unit normal n is lit by it (its irradiance `weatheralign.camera.overcast.irradiance_factor`: the sky it sees by
quadrature, the ground's reflection below) and by ``T`` of the world's sun beam where the sun reaches it; glass and
paint reflect the overcast sky; the clear air's aerial perspective fades to the overcast horizon ``L_z / 3``. The same
texture (`weatheralign.world.shading.texture`), sun, sun shadows and materials as the world's shading: only the light
differs. A flake is a Lambertian sphere of albedo 0.9 under the same light; a drop refracts its environment
(`particle_radiance` of `weatheralign.reference.synthetic`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.overcast import GROUND_ALBEDO, HORIZONTAL_FACTOR, REC709, irradiance_factor
from weatheralign.config import ReferenceConfig
from weatheralign.world.materials import SPECULAR, Material
from weatheralign.world.shading import CLEAR_AIR_EXTINCTION, SUN_COLOUR, texture

F64 = NDArray[np.float64]

_OVERCAST_TAG = 0x5E0C57

SUN_IRRADIANCE = 2.4
"""The world's sun term (`weatheralign.world.shading`: ``2.4 cos θ SUN_COLOUR`` on a lit surface)."""

FLAKE_ALBEDO = 0.9
"""A snowflake's visible albedo (as the clear reference's `particle_radiance`)."""


@dataclass(frozen=True)
class OvercastTruth:
    """One split's hidden overcast: ``sun_transmittance`` T and ``zenith_luminance`` L_z."""

    sun_transmittance: float
    zenith_luminance: float


def draw_overcast_truth(cfg: ReferenceConfig) -> dict[str, OvercastTruth]:
    """``{"snow": ..., "rain": ...}`` the hidden overcast of each split, uniform in
    ``cfg.precipitation.overcast_sun_transmittance`` / ``overcast_zenith_luminance``, from ``cfg.seed``;
    deterministic."""
    rng = np.random.default_rng([cfg.seed, _OVERCAST_TAG])
    pc = cfg.precipitation
    return {level: OvercastTruth(float(rng.uniform(*pc.overcast_sun_transmittance)),
                                 float(rng.uniform(*pc.overcast_zenith_luminance))) for level in ("snow", "rain")}


def clear_diffuse(layout) -> float:
    """The clear sky's horizontal irradiance over π in the reference camera's linear units (luminance of the world's
    ambient on a level surface, ``0.9 (0.55 zenith + 0.45 horizon)``)."""
    sky = 0.9 * (0.55 * np.asarray(layout.sky_zenith, float) + 0.45 * np.asarray(layout.sky_horizon, float))
    return float(np.dot(REC709, sky))


def true_diffuse_gain(layout, truth: OvercastTruth) -> float:
    """The overcast sky's horizontal irradiance over the clear sky's, ``7/9 L_z / clear_diffuse``: what the
    simulation's ``diffuse_gain`` stands for."""
    return HORIZONTAL_FACTOR * truth.zenith_luminance / clear_diffuse(layout)


def sky_radiance(d_z: NDArray, zenith_luminance: float) -> F64:
    """(N,) radiance seen along unit directions of vertical component ``d_z`` (N,): the CIE overcast sky above the
    horizon, the level ground lit by it (albedo `GROUND_ALBEDO`) below."""
    dz = np.asarray(d_z, dtype=np.float64)
    return np.where(dz >= 0.0, zenith_luminance * (1.0 + 2.0 * np.clip(dz, 0.0, 1.0)) / 3.0,
                    GROUND_ALBEDO * HORIZONTAL_FACTOR * zenith_luminance)


def overcast_radiance(layout, origin: NDArray, dirs: NDArray, ranges: NDArray, normals: NDArray, material: NDArray,
                      albedo: NDArray, reflectivity: NDArray, lit: NDArray, truth: OvercastTruth) -> F64:
    """(N, 3) linear RGB of camera rays (arguments as `weatheralign.world.shading.camera_radiance`: global
    ``origin`` (3,), unit ``dirs`` (N, 3), ``ranges`` (N,) [m] inf = sky, hit ``normals`` (N, 3) facing the ray,
    triangle ``material`` / ``albedo`` / ``reflectivity``, ``lit`` (N,) the sun reaches the hit) under ``truth``'s
    overcast (module docstring)."""
    d = np.asarray(dirs, dtype=np.float64)
    r = np.asarray(ranges, dtype=np.float64)
    out = np.repeat(sky_radiance(d[:, 2], truth.zenith_luminance)[:, None], 3, axis=1)
    hit = np.flatnonzero(np.isfinite(r))
    if not len(hit):
        return out
    n = np.asarray(normals, dtype=np.float64)[hit]
    dh = d[hit]
    pos = np.asarray(origin, dtype=np.float64) + dh * r[hit, None]
    surf = texture(layout, pos, np.asarray(normals)[hit], np.asarray(material)[hit], np.asarray(albedo)[hit],
                   np.asarray(reflectivity)[hit])
    alb = surf.albedo.astype(np.float64)
    sun = np.asarray(layout.sun_direction, dtype=np.float64)
    lam = np.clip(n @ sun, 0.0, 1.0) * np.asarray(lit, dtype=bool)[hit]
    light = (truth.zenith_luminance * irradiance_factor(n[:, 2]))[:, None] + (
        truth.sun_transmittance * SUN_IRRADIANCE * lam)[:, None] * np.asarray(SUN_COLOUR)
    col = alb * light
    spec = SPECULAR[surf.material].astype(np.float64)
    shiny = spec > 0.0
    if shiny.any():
        dn = np.einsum("ij,ij->i", dh, n)
        reflected_z = dh[:, 2] - 2.0 * dn * n[:, 2]
        q = 1.0 - np.abs(dn)
        fresnel = np.where(shiny, spec + (1.0 - spec) * q ** 5 * 0.5, 0.0)[:, None]
        col = col * (1.0 - fresnel) + fresnel * sky_radiance(reflected_z, truth.zenith_luminance)[:, None]
    col += np.where(surf.material == Material.LAMP.value, 0.3, 0.0)[:, None] * alb
    transmit = np.exp(-CLEAR_AIR_EXTINCTION * r[hit])[:, None]
    out[hit] = col * transmit + (truth.zenith_luminance / 3.0) * (1.0 - transmit)
    return out


def visible_hemisphere(view: F64, n: int = 4096) -> tuple[F64, F64]:
    """Normals (n, 3) of the half of a sphere facing unit ``view`` (towards the camera) and their projected-area
    weights (n,) summing to 1 (a Fibonacci hemisphere, as the clear reference's flakes)."""
    k = np.arange(n) + 0.5
    z = k / n
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    rr = np.sqrt(1.0 - z * z)
    local = np.stack([rr * np.cos(phi), rr * np.sin(phi), z], 1)
    a = np.array([1.0, 0.0, 0.0]) if abs(view[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(view, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(view, e1)
    normals = local[:, :1] * e1 + local[:, 1:2] * e2 + local[:, 2:] * view
    w = normals @ view
    return normals, w / w.sum()


def flake_radiance(layout, view: NDArray, truth: OvercastTruth) -> F64:
    """(3,) linear RGB of a flake seen along unit ``view`` (camera to scene): a Lambertian sphere of albedo
    `FLAKE_ALBEDO` under the overcast sky (its irradiance averaged over the visible half) and ``T`` of the sun."""
    normals, w = visible_hemisphere(-np.asarray(view, dtype=np.float64))
    sky = truth.zenith_luminance * float(w @ irradiance_factor(normals[:, 2]))
    sun = np.asarray(layout.sun_direction, dtype=np.float64)
    lam = float(w @ np.maximum(normals @ sun, 0.0)) if sun[2] > 0.0 else 0.0
    return FLAKE_ALBEDO * (sky + truth.sun_transmittance * SUN_IRRADIANCE * lam * np.asarray(SUN_COLOUR))


def drop_radiance(J: NDArray, truth: OvercastTruth) -> F64:
    """(3,) linear RGB of a raindrop: 0.94 of the mean of the frame's radiance ``J`` (N, 3) and of the overcast sky
    (its mean over the upper hemisphere by solid angle, ``2/3 L_z``), as the clear reference's drops."""
    return 0.94 * (0.5 * np.asarray(J, float).reshape(-1, 3).mean(0) + 0.5 * (2.0 / 3.0) * truth.zenith_luminance)


__all__ = ["FLAKE_ALBEDO", "SUN_IRRADIANCE", "OvercastTruth", "clear_diffuse", "draw_overcast_truth", "drop_radiance",
           "flake_radiance", "overcast_radiance", "sky_radiance", "true_diffuse_gain", "visible_hemisphere"]
