"""Snow and rain in a camera: the shared particle field splatted as 3-D Gaussians (EWA, front to back).

Every particle of the medium's `ParticleField` that the camera can resolve is one 3-D Gaussian at the particle's
world position at the camera's own timestamp (taken as the middle of the exposure), projected with the EWA
approximation ``Σ2D = J W Σ Wᵀ Jᵀ + 0.3 I`` and composited front to back in ray-length order against the scene's
per-pixel ray length (``docs/physics.md`` section 4). On top of Weather-edit's recipe:

- exposure streaks: during the exposure ``T_e`` a particle moves ``s = (v - v_camera) T_e`` relative to the
  camera, ``v`` the field's velocity or the particle's own (rain drops fall at their own diameter's terminal speed
  within the exposure, `weatheralign.medium.conditions.FieldSpec.drop_velocities`; translation only; the camera's
  rotation during 5 ms is neglected); its 3-D covariance gains the covariance
  of a uniform segment, ``s sᵀ / 12``, and its opacity is scaled by ``sqrt(det Σ2D / det Σ'2D)`` so that its
  integrated alpha (the "energy" ``o · 2π sqrt(det Σ2D)``) stays that of the still particle;
- photometric rain (Garg & Nayar 2004, 2007): a drop is an opaque sphere whose radiance is what it refracts from
  a wide cone of its environment, ``0.94 (½ mean of the background image + ½ airlight)`` (`environment_radiance`,
  the synthetic reference's exact camera counts the same); with ``σ = D/2`` an opacity of 1/2 gives the drop's
  projected area as integrated alpha, so each pixel's alpha along a streak is the fraction of the exposure the drop
  covers it and the streak changes a pixel by that fraction of (drop radiance - background): it brightens a dark
  background and darkens a bright sky (`RAIN`; Weather-edit's translucent grey drops are `RAIN_WEATHER_EDIT`);
- pre-fogged colour: a particle at ray length ℓ is composited with ``c t(ℓ) + A (1 - t(ℓ))``,
  ``t(ℓ) = exp(-fog_alpha ℓ - τ_u(ℓ))``. Composited over the *fogged* background ``J t(R) + A (1 - t(R))`` this is
  exact Koschmieder for a particle inside the medium;
- opacities in (0, 1) (alpha additionally ``min(0.99, ·)``);
- resolution: a particle of diameter D at ray length ℓ has a projected standard deviation of about
  ``f k D / ℓ`` pixels (``k = appearance.sigma_per_diameter``, ``f = sqrt(fx fy)``). Below the 0.3 px² dilation
  (``f k D / ℓ < sqrt(0.3)``) a splat would be mostly dilation, i.e. a ~1 px blob far more opaque than the particle
  really covers; such particles are not splatted but folded into the medium's extinction and veiling.

Contract with the caller (the ``simulate`` stage):

1. Materialise per camera only what it resolves: `materialize_for_camera` runs nested `ParticleField.materialize`
   queries in range shells with the per-range threshold `min_splat_diameter` (``D ≥ sqrt(0.3) ℓ / (f k)``), keeping
   exactly the particles with ``D ≥ min_splat_diameter(ℓ)`` inside the frustum (plus the footprint margin).
2. Everything else is unresolved: at ray length r the particles with ``D < min_splat_diameter(r)`` (all of them
   nearer than ``near_clip`` or beyond ``max_range``) contribute their geometric shadow, the extinction
   ``field.unresolved_extinction(min_splat_diameter(r)) · Q_IMAGING / Q_EXT_GEOMETRIC`` (half the beam extinction:
   the diffracted half stays inside the pixel, `weatheralign.medium.distributions.Q_IMAGING`; the synthetic
   reference's exact camera counts the same). `unresolved_extinction_profile` integrates it into an optical depth
   ``τ_u(ℓ)`` (`UnresolvedExtinction`). The camera fog must use the transmission
   ``t(ℓ) = exp(-fog_alpha ℓ - τ_u(ℓ))`` on the scene's ray length ℓ (`UnresolvedExtinction.transmission`), with
   the same scene airlight, and `render_particles` must get the same ``fog_alpha``, ``airlight`` and ``unresolved``
   so that the particles' pre-fogged colours match; the veiling of the unresolved particles is the airlight term
   ``A (1 - t)``. Where a fog model only takes a constant coefficient, use ``fog_alpha +
   UnresolvedExtinction.total_extinction`` (this double-counts the splatted particles' own shadow, an optical depth
   of `UnresolvedExtinction.resolved_optical_depth`: 0.006 for the paper's snow, 0.003 for its rain at f = 1266 px).
   Build the profile with the same ``appearance``, ``near_clip`` and ``max_range`` as the materialisation (once per
   camera and field: it does not depend on time). With nuScenes' f ≈ 1266 px nothing is resolvable beyond
   `max_splat_range`: ~23 m for snow (20 mm flakes), ~7 m for rain (6 mm drops).
3. Pass the fogged background image (linear RGB) and the scene's exact ray-length map (inf = sky) to
   `render_particles` at the camera's timestamp; composite nothing else on top.

The streak is symmetric about the position at the timestamp, so the rasterised centroid of a particle (returned per
particle for the re-projection check) is its pinhole projection. Kernels are serial numba (``nogil``): callers run
cameras in a thread pool. Results are deterministic: the order of
compositing is (ray length, id), per-particle attributes are functions of the id, and every per-particle quantity
is computed by scalar code, so the bytes do not depend on the input order or on threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.camera.records import Canvas, FootprintRules, Footprints, FootprintSums, Gaussians, PinholeView
from weatheralign.geometry import invert
from weatheralign.medium.distributions import Q_EXT_GEOMETRIC, Q_IMAGING, ExponentialSizeDistribution
from weatheralign.medium.field import DEFAULT_MAX_PARTICLES, ParticleField, Particles

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

DILATION_PX2 = 0.3
"""EWA low-pass dilation added to every projected covariance [px²]."""
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
"""A pixel whose transmittance fell below this takes no further particle."""
CENTROID_Q = 16.0
"""Mahalanobis² radius (4 σ) of the window over which a particle's rasterised centroid is taken. The centroid is
alpha-weighted over every pixel of ``q <= max(CENTROID_Q, qmax)`` in front of the scene, including pixels fainter
than the 1/255 that is composited: a window cut at 1/255 would depend on the opacity, and for a faint streak (opacity
~0.01) that cut leaves a thin, grid-asymmetric sliver whose centroid is off by up to ~0.8 px."""
OPACITY_RANGE = (0.01, 0.99)
"""Per-particle base opacities are clipped into this interval (inside (0, 1))."""
RadianceSource = Literal["grey", "environment"]
"""Where a particle's radiance comes from: a constant ``grey`` or its environment (`environment_radiance`)."""

_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_M53 = 2.0**-53


# ------------------------------------------------------------------------------------------------------ appearance
@dataclass(frozen=True)
class ParticleAppearance:
    """How particles of one precipitation type look (Weather-edit's attributes, sized from the real diameter).

    The 3-D Gaussian of a particle of diameter D has the horizontal standard deviation ``sh = k D`` in both
    horizontal axes and ``sv = aspect · sh`` along its symmetry axis, which is tilted from the vertical by an angle
    uniform in ``[0, tilt_max_deg]`` towards a uniform azimuth: ``Σ = sh² I + (sv² - sh²) n nᵀ`` (global frame).
    With ``k = 1/2`` and opacity ``o`` a sphere's integrated alpha is ``o · 2π (D/2)²``: at ``o = 1/2`` exactly the
    cross-section ``π D²/4`` of an opaque disc of diameter D (snow, raindrops), at ``o = 0.2`` 40 % of it
    (Weather-edit's rain). The exposure streak keeps that integral (its opacity is scaled, `render_particles`).
    Every per-particle variation is a function of ``(id, salt)`` only, never of the call order.

    Attributes:
        name: ``snow`` / ``rain`` (free text).
        sigma_per_diameter: k = sh / D (dimensionless).
        aspect, aspect_spread: sv / sh, uniform in ``aspect ± aspect_spread`` (clipped to [0.05, 1]).
        oblate_drops: if true, ``aspect`` is replaced by the raindrop axis ratio ``1.03 - 0.062 D[mm]``
            (Pruppacher & Beard 1970), clipped to [0.5, 1].
        tilt_max_deg: largest tilt [deg] of the symmetry axis from the vertical.
        opacity, opacity_spread: base opacity, uniform in ``opacity ± opacity_spread``, clipped to `OPACITY_RANGE`.
        grey, grey_spread: linear radiance (1 = white), uniform in ``grey ± grey_spread``, clipped to [0, 1]; with
            ``radiance = "environment"`` the factor on the environment's radiance instead.
        tint: (3,) RGB factors of the grey.
        radiance: ``grey`` (the particle's linear radiance is ``grey · tint``) or ``environment`` (``grey · tint ·
            environment_radiance(background, airlight)``: a refracting drop, per camera image).
        dilation_keeps_area: if true, the opacity is also scaled by ``sqrt(det Σ2D_raw / det Σ2D)`` (``Σ2D_raw``
            without the 0.3 px² dilation), so the integrated alpha is the footprint's own ``o · 2π sqrt(det
            Σ2D_raw)`` (the dilation is a pixel low-pass that keeps energy; without this a drop at the resolution
            limit, ``Σ2D_raw ≈ 0.3 I``, is drawn with twice its area).
        salt: stream of the per-id hash (different types vary independently).
    """

    name: str
    sigma_per_diameter: float = 0.5
    aspect: float = 1.0
    aspect_spread: float = 0.0
    oblate_drops: bool = False
    tilt_max_deg: float = 0.0
    opacity: float = 0.5
    opacity_spread: float = 0.0
    grey: float = 0.8
    grey_spread: float = 0.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    salt: int = 0
    radiance: RadianceSource = "grey"
    dilation_keeps_area: bool = False

    def __post_init__(self) -> None:
        checks = {"sigma_per_diameter": (self.sigma_per_diameter, 1e-3, 10.0), "aspect": (self.aspect, 0.05, 1.0),
                  "aspect_spread": (self.aspect_spread, 0.0, 1.0), "tilt_max_deg": (self.tilt_max_deg, 0.0, 90.0),
                  "opacity": (self.opacity, 1e-3, 1.0), "opacity_spread": (self.opacity_spread, 0.0, 1.0),
                  "grey": (self.grey, 0.0, 1.0), "grey_spread": (self.grey_spread, 0.0, 1.0)}
        for key, (value, lo, hi) in checks.items():
            if not (math.isfinite(float(value)) and lo <= float(value) <= hi):
                raise ValueError(f"ParticleAppearance.{key} = {value!r} is invalid: must be in [{lo}, {hi}]")
        tint = tuple(float(x) for x in self.tint)
        if len(tint) != 3 or not all(math.isfinite(x) and x >= 0.0 for x in tint):
            raise ValueError(f"ParticleAppearance.tint = {self.tint!r} is invalid: expected 3 finite values >= 0")
        object.__setattr__(self, "tint", tint)
        if not 0 <= int(self.salt) < 2**63:
            raise ValueError(f"ParticleAppearance.salt = {self.salt!r} is invalid: must be in [0, 2^63)")
        if self.radiance not in ("grey", "environment"):
            raise ValueError(f"ParticleAppearance.radiance = {self.radiance!r} is invalid: expected 'grey' or "
                             f"'environment'")


SNOW = ParticleAppearance(name="snow", sigma_per_diameter=0.5, aspect=0.6, aspect_spread=0.15, tilt_max_deg=35.0,
                          opacity=0.5, opacity_spread=0.2, grey=0.85, grey_spread=0.05, salt=0x5_0A0F)
"""Snowflakes: flattened aggregates (axis ratio 0.6 ± 0.15) fluttering up to 35° off horizontal, opacity 0.5 ± 0.2,
grey 0.85 ± 0.05 (Weather-edit's snow)."""

DROP_RADIANCE_FACTOR = 0.94
"""A raindrop's radiance relative to the environment it refracts (Garg & Nayar 2004; the synthetic reference's
exact camera uses the same factor, `weatheralign.reference.synthetic.particle_radiance`)."""

RAIN = ParticleAppearance(name="rain", sigma_per_diameter=0.5, oblate_drops=True, tilt_max_deg=5.0, opacity=0.5,
                          opacity_spread=0.0, grey=DROP_RADIANCE_FACTOR, grey_spread=0.0, radiance="environment",
                          dilation_keeps_area=True, salt=0x4A_1D)
"""Raindrops as opaque refracting spheres (Garg & Nayar 2004, 2007): small (oblate) spheres canted at most 5°,
opacity 1/2 (with ``σ = D/2`` the integrated alpha is the drop's projected area ``π D²/4``: a drop replaces the
background over its disc; the dilation keeps that area, so a drop at the resolution limit is not drawn twice as
large and the splatted drops continue the unresolved ones' geometric shadow), radiance ``0.94 x
environment_radiance`` of the camera's image (brighter than a dark road, darker than the sky). The streak is the
exposure blur of the drop's relative motion, not a fixed elongated shape: its alpha at a pixel is the fraction of
the exposure the drop covers it (Garg & Nayar's ``τ / T``)."""

RAIN_WEATHER_EDIT = ParticleAppearance(name="rain_weather_edit", sigma_per_diameter=0.5, oblate_drops=True,
                                       tilt_max_deg=5.0, opacity=0.2, opacity_spread=0.05, grey=0.7,
                                       grey_spread=0.05, salt=0x4A_1D)
"""Weather-edit's rain look: translucent drops (opacity 0.2 ± 0.05: 40 % of an opaque drop's area) of constant grey
0.7 ± 0.05, whatever the scene (invisible on bright surfaces); same geometry, ids and variation stream as `RAIN`
(Weather-edit's rain Gaussians are 2–8 cm long and tilted ~23° instead of streaked by the motion)."""

APPEARANCES: dict[str, ParticleAppearance] = {a.name: a for a in (SNOW, RAIN, RAIN_WEATHER_EDIT)}
"""The named particle appearances (a condition names its camera appearance; `APPEARANCES[name]` draws it)."""


@njit(nogil=True, cache=True, inline="always")
def _mix(z: np.uint64) -> np.uint64:
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(nogil=True, cache=True)
def _attributes_kernel(ids: NDArray, diameters: NDArray, salt: np.uint64, k_sigma: float, aspect: float,
                       aspect_spread: float, oblate: bool, tilt_max: float, opacity: float, opacity_spread: float,
                       o_lo: float, o_hi: float, grey: float, grey_spread: float, cov: NDArray,
                       opac: NDArray, greys: NDArray) -> None:
    """Per particle: global covariance (N, 3, 3) [m²], base opacity (N,), grey (N,), from (id, diameter) alone."""
    salt_key = _mix(salt + _GAMMA)
    for n in range(ids.shape[0]):
        key = _mix(np.uint64(ids[n]) ^ salt_key)
        u_opacity = float(_mix(key + np.uint64(1) * _GAMMA) >> _S11) * _TWO_M53
        u_grey = float(_mix(key + np.uint64(2) * _GAMMA) >> _S11) * _TWO_M53
        u_aspect = float(_mix(key + np.uint64(3) * _GAMMA) >> _S11) * _TWO_M53
        u_tilt = float(_mix(key + np.uint64(4) * _GAMMA) >> _S11) * _TWO_M53
        u_azimuth = float(_mix(key + np.uint64(5) * _GAMMA) >> _S11) * _TWO_M53
        d = diameters[n]
        sh = k_sigma * d
        if oblate:
            a = min(max(1.03 - 62.0 * d, 0.5), 1.0)  # 0.062 per mm = 62 per m
        else:
            a = min(max(aspect + aspect_spread * (2.0 * u_aspect - 1.0), 0.05), 1.0)
        sv = a * sh
        theta = tilt_max * u_tilt
        phi = 2.0 * math.pi * u_azimuth
        st = math.sin(theta)
        nx, ny, nz = st * math.cos(phi), st * math.sin(phi), math.cos(theta)
        g = sv * sv - sh * sh
        cov[n, 0, 0] = sh * sh + g * nx * nx
        cov[n, 1, 1] = sh * sh + g * ny * ny
        cov[n, 2, 2] = sh * sh + g * nz * nz
        cov[n, 0, 1] = cov[n, 1, 0] = g * nx * ny
        cov[n, 0, 2] = cov[n, 2, 0] = g * nx * nz
        cov[n, 1, 2] = cov[n, 2, 1] = g * ny * nz
        opac[n] = min(max(opacity + opacity_spread * (2.0 * u_opacity - 1.0), o_lo), o_hi)
        greys[n] = min(max(grey + grey_spread * (2.0 * u_grey - 1.0), 0.0), 1.0)


def particle_attributes(ids: NDArray, diameters: NDArray,
                        appearance: ParticleAppearance) -> tuple[F64, F64, F64]:
    """The 3-D Gaussians of particles, from their ids (N,) int64 and diameters (N,) [m].

    Returns:
        cov: (N, 3, 3) float64 covariance in the global frame (z up) [m²], before any motion blur;
        opacity: (N,) base opacity in `OPACITY_RANGE`;
        grey: (N,) linear grey level in [0, 1].
    """
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    diameters = np.ascontiguousarray(diameters, dtype=np.float64)
    n = ids.shape[0]
    cov, opac, grey = np.empty((n, 3, 3)), np.empty(n), np.empty(n)
    a = appearance
    _attributes_kernel(ids, diameters, np.uint64(a.salt), a.sigma_per_diameter, a.aspect, a.aspect_spread,
                       a.oblate_drops, math.radians(a.tilt_max_deg), a.opacity, a.opacity_spread, OPACITY_RANGE[0],
                       OPACITY_RANGE[1], a.grey, a.grey_spread, cov, opac, grey)
    return cov, opac, grey


def environment_radiance(image_linear: NDArray, airlight: NDArray | tuple) -> F64:
    """(3,) linear radiance of the environment a raindrop refracts: ``½ mean(image) + ½ airlight``.

    A drop maps a ~165° cone of its surroundings into its disc, the ground and the scene in front of it as much as
    the sky above (Garg & Nayar 2004): half the mean radiance of the camera's whole image (the scene, as the camera
    sees it: already fogged by the caller) and half the sky, whose radiance the scene's airlight stands for (the
    synthetic reference's exact camera uses the mean of the clear image and of its sky's zenith and horizon).

    Args:
        image_linear: (H, W, 3) linear RGB (any float dtype; averaged in float64).
        airlight: (3,) linear RGB.
    """
    img = np.asarray(image_linear)
    # column sums first: adding whole rows is much cheaper than numpy's strided float64 mean over axis 0 of (H W, 3)
    mean = img.sum(axis=0, dtype=np.float64).sum(axis=0) / (img.shape[0] * img.shape[1])
    return 0.5 * mean + 0.5 * np.asarray(airlight, dtype=np.float64)


def particle_radiance(appearance: ParticleAppearance, grey: F64, image_linear: NDArray,
                      airlight: NDArray | tuple) -> F64:
    """(N, 3) linear RGB radiance of particles of per-particle ``grey`` (N,) (`particle_attributes`):
    ``grey · tint``, times `environment_radiance` when ``appearance.radiance == "environment"``."""
    base = np.asarray(appearance.tint, dtype=np.float64)
    if appearance.radiance == "environment":
        base = base * environment_radiance(image_linear, airlight)
    return np.asarray(grey, dtype=np.float64)[:, None] * base[None, :]


# ------------------------------------------------------------------------------------------------------ resolution
def focal_px(K: NDArray) -> float:
    """Effective focal length ``sqrt(fx fy)`` [px] of intrinsics ``K`` (3, 3)."""
    return float(math.sqrt(float(K[0, 0]) * float(K[1, 1])))


def min_splat_diameter(ray_length: NDArray | float, focal: float, appearance: ParticleAppearance,
                       near_clip: float = 0.5, max_range: float = math.inf,
                       dilation_px2: float = DILATION_PX2) -> F64:
    """Smallest diameter [m] splatted at ``ray_length`` [m] (any shape): ``sqrt(dilation) ℓ / (f k)``.

    A particle below it has a projected standard deviation under the dilation's ``sqrt(0.3)`` px and is folded into
    the medium's extinction instead. ``inf`` (nothing splatted) nearer than ``near_clip`` and beyond ``max_range``.
    Increasing in ℓ, so nested field queries apply (`materialize_for_camera`).
    """
    r = np.asarray(ray_length, dtype=np.float64)
    d = math.sqrt(dilation_px2) * r / (float(focal) * appearance.sigma_per_diameter)
    return np.where((r >= near_clip) & (r <= max_range), d, np.inf)


def max_splat_range(d_max: float, focal: float, appearance: ParticleAppearance,
                    dilation_px2: float = DILATION_PX2) -> float:
    """Ray length [m] beyond which even the largest particle (``d_max`` [m]) is unresolved."""
    return float(d_max) * float(focal) * appearance.sigma_per_diameter / math.sqrt(dilation_px2)


def _spectrum_of(medium: ParticleField | ExponentialSizeDistribution) -> ExponentialSizeDistribution:
    if isinstance(medium, ParticleField):
        return medium.spectrum
    if isinstance(medium, ExponentialSizeDistribution):
        return medium
    return medium.spectrum()


@njit(nogil=True, cache=True, inline="always")
def _tau_at(r: float, near: float, r_end: float, table: NDArray, total: float) -> float:
    """τ_u at ray length ``r`` [m] (see `UnresolvedExtinction`)."""
    if r < near:
        return total * r
    if r <= r_end:
        m = table.shape[0]
        if m == 1:
            return table[0]
        s = (r - near) / (r_end - near) * (m - 1)
        k = min(int(s), m - 2)
        return table[k] + (s - k) * (table[k + 1] - table[k])
    if total > 0.0:
        return table[table.shape[0] - 1] + total * (r - r_end)
    return table[table.shape[0] - 1]


@njit(nogil=True, cache=True)
def _optical_depth_kernel(r: NDArray, near: float, r_end: float, table: NDArray, total: float, fog: float,
                          out: NDArray) -> None:
    """``out = fog r + τ_u(r)`` for flat arrays (``fog r`` only where ``fog > 0``: 0 · inf is no extinction)."""
    for i in range(r.shape[0]):
        tau = _tau_at(r[i], near, r_end, table, total)
        if fog > 0.0:
            tau += fog * r[i]
        out[i] = tau


@njit(nogil=True, cache=True)
def _transmission_kernel(r: NDArray, near: float, r_end: float, table: NDArray, total: float, fog: float,
                         out: NDArray) -> None:
    """``out = exp(-fog r - τ_u(r))`` for flat arrays; ``table`` holds ``exp(-τ_u)`` on the grid of τ_u's table,
    interpolated linearly in between (relative error below (Δτ)²/8 per grid step: no exponential per pixel there
    unless ``fog``)."""
    m = table.shape[0]
    last = table[m - 1]
    scale = (m - 1) / (r_end - near) if m > 1 else 0.0
    for i in range(r.shape[0]):
        x = r[i]
        if x < near:
            t = math.exp(-(total + fog) * x)
        elif x <= r_end:
            if m == 1:
                t = last
            else:
                s = (x - near) * scale
                k = min(int(s), m - 2)
                t = table[k] + (s - k) * (table[k + 1] - table[k])
            if fog > 0.0:
                t *= math.exp(-fog * x)
        elif x == math.inf and (total > 0.0 or fog > 0.0):
            t = 0.0
        else:
            t = last * math.exp(-(total * (x - r_end) + fog * x))
        out[i] = t


@dataclass(frozen=True, eq=False)
class UnresolvedExtinction:
    """Optical depth of the particles a camera does not splat, along its rays.

    ``τ_u(ℓ) = ∫_0^ℓ E(r) dr`` with ``E(r) = field.unresolved_extinction(min_splat_diameter(r)) · Q_IMAGING /
    Q_EXT_GEOMETRIC`` [1/m] (the geometric shadow: see the module contract): the full ``total_extinction`` nearer
    than ``near_clip`` and beyond ``r_end`` (nothing is splatted there), tabulated on a uniform grid in between and
    linearly interpolated.

    Attributes:
        near_clip: [m]; r_end: last splatting range [m] (``min(max_range, max_splat_range)``).
        table: (M,) τ_u at ``linspace(near_clip, r_end, M)``.
        total_extinction: the geometric shadow of all particles [1/m] (``field.extinction() · Q_IMAGING /
            Q_EXT_GEOMETRIC``).
    """

    near_clip: float
    r_end: float
    table: F64
    total_extinction: float

    @property
    def resolved_optical_depth(self) -> float:
        """``total_extinction · r_end - τ_u(r_end)``: the optical depth of the splatted particles themselves (what
        a constant ``fog_alpha + total_extinction`` would count twice)."""
        return self.total_extinction * self.r_end - float(self.table[-1])

    @staticmethod
    def _flat(ray_length: NDArray | float) -> tuple[NDArray, NDArray]:
        """The ray lengths as an array and flat (float32 kept, anything else float64)."""
        r = np.asarray(ray_length)
        return r, np.ascontiguousarray(r, dtype=np.float64 if r.dtype != np.float32 else np.float32).ravel()

    def optical_depth(self, ray_length: NDArray | float, fog_alpha: float = 0.0) -> F64:
        """``fog_alpha ℓ + τ_u(ℓ)`` (float64, shape of ``ray_length`` [m]); inf for the sky when anything extincts."""
        r, flat = self._flat(ray_length)
        out = np.empty(flat.shape[0], dtype=np.float64)
        _optical_depth_kernel(flat, self.near_clip, self.r_end, self.table, self.total_extinction, float(fog_alpha),
                              out)
        return out.reshape(r.shape)

    def transmission(self, ray_length: NDArray | float, fog_alpha: float = 0.0) -> NDArray:
        """``exp(-fog_alpha ℓ - τ_u(ℓ))`` at ``ray_length`` [m] (float32 for float32 input, else float64); 0 for the
        sky (inf) when anything extincts. The transmission the camera fog must use (module contract)."""
        r, flat = self._flat(ray_length)
        out = np.empty(flat.shape[0], dtype=np.float32 if r.dtype == np.float32 else np.float64)
        _transmission_kernel(flat, self.near_clip, self.r_end, np.exp(-self.table), self.total_extinction,
                             float(fog_alpha), out)
        return out.reshape(r.shape)


def unresolved_extinction_profile(medium: ParticleField | ExponentialSizeDistribution, focal: float,
                                  appearance: ParticleAppearance, near_clip: float = 0.5,
                                  max_range: float = math.inf, samples: int = 512) -> UnresolvedExtinction:
    """`UnresolvedExtinction` of ``medium`` for a camera of focal length ``focal`` [px] (see the module contract):
    the unresolved particles' geometric shadow (extinction efficiency `Q_IMAGING`).

    Use the same ``appearance``, ``near_clip`` and ``max_range`` as `materialize_for_camera`.
    """
    spec = _spectrum_of(medium)
    shadow = Q_IMAGING / Q_EXT_GEOMETRIC  # `extinction` counts Q_EXT_GEOMETRIC
    total = shadow * spec.extinction()
    near = float(near_clip)
    r_cut = min(float(max_range), max_splat_range(spec.d_max, focal, appearance))
    if not r_cut > near:
        return UnresolvedExtinction(near, near, np.array([total * near]), total)
    r = np.linspace(near, r_cut, samples)
    m = min_splat_diameter(r, focal, appearance, near, r_cut)
    e = np.where(m < spec.d_max, shadow * spec.extinction_below(m), total)
    tau = total * near + np.concatenate([[0.0], np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(r))])
    return UnresolvedExtinction(near, float(r_cut), tau, total)


# ------------------------------------------------------------------------------------------------------ materialise
@njit(nogil=True, cache=True)
def _frustum_box(K_inv: F64, width: int, height: int, T_global_cam: F64, r0: float, r1: float,
                 margin_px: float) -> tuple[F64, F64]:
    """Axis-aligned global box (lo, hi) (3,) [m] holding every point at ray length in [r0, r1] whose projection lies
    in the image widened by ``margin_px`` (directions sampled on a 17 x 17 grid, plus 1 % slack). ``K_inv``: the
    inverse intrinsics."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    step_u = (width - 1 + 2.0 * margin_px) / 16.0
    step_v = (height - 1 + 2.0 * margin_px) / 16.0
    for a in range(17):
        v = -margin_px + a * step_v
        for b in range(17):
            u = -margin_px + b * step_u
            c = np.empty(3)
            for i in range(3):
                c[i] = K_inv[i, 0] * u + K_inv[i, 1] * v + K_inv[i, 2]
            norm = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
            for i in range(3):
                g = (T_global_cam[i, 0] * c[0] + T_global_cam[i, 1] * c[1] + T_global_cam[i, 2] * c[2]) / norm
                for r in (r0, r1):
                    p = g * r + T_global_cam[i, 3]
                    lo[i] = min(lo[i], p)
                    hi[i] = max(hi[i], p)
    slack = 0.01 * r1 + 0.01
    return lo - slack, hi + slack


def materialize_for_camera(field: ParticleField, K: NDArray, width: int, height: int, T_global_cam: NDArray,
                           t: float, appearance: ParticleAppearance, *, near_clip: float = 0.5,
                           max_range: float = math.inf, streak_m: float = 0.0, max_footprint_px: float = 128.0,
                           shell_ratio: float = 1.3,
                           max_particles: int = DEFAULT_MAX_PARTICLES) -> Particles:
    """The particles of ``field`` a camera resolves at time ``t`` [s] (its timestamp), sorted by id.

    Nested queries in range shells ``[r_k, r_k · shell_ratio)`` from ``near_clip`` to
    ``min(max_range, max_splat_range)``: shell k asks for ``D ≥ min_splat_diameter(r_k)`` in the box of its frustum
    slice, then keeps exactly the particles with ray length in the shell, ``D ≥ min_splat_diameter(ℓ)`` and a
    projection within the image widened by their largest possible footprint (3.4 σ of the largest particle plus
    half the exposure streak ``streak_m`` [m], capped at ``max_footprint_px``).

    Args:
        K: (3, 3) intrinsics [px]; width, height: image size [px]; T_global_cam: (4, 4) camera -> global at ``t``.
    """
    K = np.asarray(K, dtype=np.float64)
    T_global_cam = np.asarray(T_global_cam, dtype=np.float64)
    f = focal_px(K)
    spec = field.spectrum
    r_end = min(float(max_range), max_splat_range(spec.d_max, f, appearance))
    T_cam_global = invert(T_global_cam)
    K_inv = np.linalg.inv(K)
    pos_parts, dia_parts, id_parts = [], [], []
    r0 = float(near_clip)
    while r0 < r_end:
        r1 = min(r0 * shell_ratio, r_end)
        m = float(min_splat_diameter(r0, f, appearance, near_clip, r_end))
        if m >= spec.d_max:
            break
        sigma = math.sqrt((f * appearance.sigma_per_diameter * spec.d_max / r0) ** 2 + DILATION_PX2)
        margin = min(3.4 * sigma + 0.5 * f * streak_m / r0, max_footprint_px * 3.4 / 3.0) + 1.0
        lo, hi = _frustum_box(K_inv, width, height, T_global_cam, r0, r1, margin)
        p = field.materialize(lo, hi, t, min_diameter=m, max_particles=max_particles)
        if len(p):
            pc = p.positions @ T_cam_global[:3, :3].T + T_cam_global[:3, 3]
            ell = np.linalg.norm(pc, axis=1)
            z = pc[:, 2]
            last = r1 >= r_end
            keep = (ell >= r0) & ((ell <= r1) if last else (ell < r1)) & (z >= 0.25 * near_clip)
            keep &= p.diameters >= min_splat_diameter(ell, f, appearance, near_clip, r_end)
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (K[0, 0] * pc[:, 0] + K[0, 1] * pc[:, 1]) / z + K[0, 2]
                v = K[1, 1] * pc[:, 1] / z + K[1, 2]
            keep &= (u >= -margin) & (u <= width - 1 + margin) & (v >= -margin) & (v <= height - 1 + margin)
            pos_parts.append(p.positions[keep])
            dia_parts.append(p.diameters[keep])
            id_parts.append(p.ids[keep])
        r0 = r1
    if not id_parts:
        return Particles(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), float(t),
                         float(min_splat_diameter(near_clip, f, appearance, near_clip)))
    ids = np.concatenate(id_parts)
    order = np.argsort(ids, kind="stable")
    return Particles(np.concatenate(pos_parts)[order], np.concatenate(dia_parts)[order], ids[order], float(t),
                     float(min_splat_diameter(near_clip, f, appearance, near_clip)))


# ------------------------------------------------------------------------------------------------------ kernels
_OK, _NEAR, _FAINT, _OFFSCREEN = 0, 1, 2, 3


@njit(nogil=True, cache=True)
def _prepare_kernel(particles: Gaussians, view: PinholeView, rules: FootprintRules, out: Footprints) -> None:
    """Per particle (`Gaussians`) seen by ``view`` under ``rules``, into ``out`` (`Footprints`): camera-frame
    position, EWA conic ``(ca, cb, cc)`` of ``Σ'2D⁻¹`` (its streak ``streak[i]`` (N, 3) [m, global frame],
    dilation, cap included), opacity after the streak (with ``keep_area`` also after the dilation), the Mahalanobis²
    bound ``qmax`` of alpha >= 1/255 (off-screen test), the centroid window ``qwin = max(qmax, centroid_q)`` and its
    half extents (``rx``, ``ry``; ``in_frame``: the whole window inside the image) and a status (ok / near-clipped /
    too faint / off screen)."""
    pos, cov, opac0, streak = particles.pos, particles.cov, particles.opacity, particles.streak
    R, tr, K, width, height = view.R, view.tr, view.K, view.width, view.height
    near_clip, cap_var, dilation = rules.near_clip, rules.cap_var, rules.dilation
    keep_area, centroid_q = rules.keep_area, rules.centroid_q
    u0, v0, ca, cb, cc, opac = out.u0, out.v0, out.ca, out.cb, out.cc, out.opac
    qmax, qwin, ell, rx, ry = out.qmax, out.qwin, out.ell, out.rx, out.ry
    status, capped, in_frame = out.status, out.capped, out.in_frame
    fx, sk, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    for i in range(pos.shape[0]):
        sx, sy, sz = streak[i, 0], streak[i, 1], streak[i, 2]
        px, py, pz = pos[i, 0], pos[i, 1], pos[i, 2]
        x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + tr[0]
        y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + tr[1]
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + tr[2]
        ln = math.sqrt(x * x + y * y + z * z)
        ell[i] = ln
        capped[i] = False
        in_frame[i] = False
        if ln < near_clip or z < 0.25 * near_clip:
            status[i] = _NEAR
            continue
        iz = 1.0 / z
        j00, j01, j02 = fx * iz, sk * iz, -(fx * x + sk * y) * iz * iz
        j11, j12 = fy * iz, -fy * y * iz * iz
        # rows of J W (2 x 3): the global-frame gradients of (u, v)
        g00 = j00 * R[0, 0] + j01 * R[1, 0] + j02 * R[2, 0]
        g01 = j00 * R[0, 1] + j01 * R[1, 1] + j02 * R[2, 1]
        g02 = j00 * R[0, 2] + j01 * R[1, 2] + j02 * R[2, 2]
        g10 = j11 * R[1, 0] + j12 * R[2, 0]
        g11 = j11 * R[1, 1] + j12 * R[2, 1]
        g12 = j11 * R[1, 2] + j12 * R[2, 2]
        # (J W) Σ: 2 x 3
        m00 = g00 * cov[i, 0, 0] + g01 * cov[i, 1, 0] + g02 * cov[i, 2, 0]
        m01 = g00 * cov[i, 0, 1] + g01 * cov[i, 1, 1] + g02 * cov[i, 2, 1]
        m02 = g00 * cov[i, 0, 2] + g01 * cov[i, 1, 2] + g02 * cov[i, 2, 2]
        m10 = g10 * cov[i, 0, 0] + g11 * cov[i, 1, 0] + g12 * cov[i, 2, 0]
        m11 = g10 * cov[i, 0, 1] + g11 * cov[i, 1, 1] + g12 * cov[i, 2, 1]
        m12 = g10 * cov[i, 0, 2] + g11 * cov[i, 1, 2] + g12 * cov[i, 2, 2]
        a0 = m00 * g00 + m01 * g01 + m02 * g02 + dilation
        b0 = m10 * g00 + m11 * g01 + m12 * g02
        c0 = m10 * g10 + m11 * g11 + m12 * g12 + dilation
        det0 = a0 * c0 - b0 * b0
        if keep_area:  # the energy of the undilated footprint
            det0 = (a0 - dilation) * (c0 - dilation) - b0 * b0
        p0 = g00 * sx + g01 * sy + g02 * sz
        p1 = g10 * sx + g11 * sy + g12 * sz
        a2 = a0 + p0 * p0 / 12.0
        b2 = b0 + p0 * p1 / 12.0
        c2 = c0 + p1 * p1 / 12.0
        half = 0.5 * (a2 - c2)
        dd = math.sqrt(half * half + b2 * b2)
        l1 = 0.5 * (a2 + c2) + dd
        l2 = 0.5 * (a2 + c2) - dd
        if l1 > cap_var:
            th = 0.5 * math.atan2(2.0 * b2, a2 - c2)
            co, si = math.cos(th), math.sin(th)
            l1 = cap_var
            l2 = min(l2, cap_var)
            a2 = l1 * co * co + l2 * si * si
            b2 = (l1 - l2) * co * si
            c2 = l1 * si * si + l2 * co * co
            capped[i] = True
        det2 = a2 * c2 - b2 * b2
        o = opac0[i] * min(1.0, math.sqrt(det0 / det2))
        opac[i] = o
        u = (fx * x + sk * y) * iz + cx
        v = fy * y * iz + cy
        u0[i] = u
        v0[i] = v
        if o * 255.0 < 1.0:
            status[i] = _FAINT
            continue
        q = 2.0 * math.log(255.0 * o)
        qmax[i] = q
        ca[i] = c2 / det2
        cb[i] = -b2 / det2
        cc[i] = a2 / det2
        hx = math.sqrt(q * a2)
        hy = math.sqrt(q * c2)
        if u + hx < 0.0 or u - hx > width - 1 or v + hy < 0.0 or v - hy > height - 1:
            status[i] = _OFFSCREEN
            continue
        status[i] = _OK
        qw = max(q, centroid_q)
        qwin[i] = qw
        hx = math.sqrt(qw * a2)
        hy = math.sqrt(qw * c2)
        rx[i] = hx
        ry[i] = hy
        in_frame[i] = u - hx >= 0.0 and u + hx <= width - 1 and v - hy >= 0.0 and v + hy <= height - 1


@njit(nogil=True, cache=True)
def _splat_kernel(order: NDArray, fp: Footprints, col: NDArray, canvas: Canvas, sums: FootprintSums) -> None:
    """Front-to-back compositing of the particles ``order`` (nearest first) of colour ``col`` (N, 3) with the
    footprints ``fp`` over exact per-row ellipse spans into ``canvas``; what each particle showed into ``sums``.

    Per pixel (x, y) of particle i inside its centroid window ``q <= qwin[i]``, with ``alpha = min(0.99, o
    exp(-q/2))``: skipped (and i marked occluded) where ``ell[i] >= rng[y, x]``; else it enters the centroid sums
    (``sum_w``, ``sum_wu``, ``sum_wv``) and, if ``alpha >= 1/255``, the visible-footprint statistics (``sum_a``,
    ``max_a``) and, unless the pixel's transmittance is below `T_MIN`, the composite ``C += T alpha col``,
    ``T *= 1 - alpha``. ``out`` starts as a copy of the background ``bg`` and holds the running composite
    ``C + T bg`` (updated in place as ``out += T alpha (col - bg)``).
    """
    u0, v0, ca, cb, cc, opac, qwin, ry, ell = fp.u0, fp.v0, fp.ca, fp.cb, fp.cc, fp.opac, fp.qwin, fp.ry, fp.ell
    rng, bg, out, acc_t = canvas.rng, canvas.bg, canvas.out, canvas.acc_t
    sum_a, sum_w, sum_wu, sum_wv = sums.sum_a, sums.sum_w, sums.sum_wu, sums.sum_wv
    max_a, occluded = sums.max_a, sums.occluded
    h, w = rng.shape
    for k in range(order.shape[0]):
        i = order[k]
        u, v, a, b, c, o, q, ln = u0[i], v0[i], ca[i], cb[i], cc[i], opac[i], qwin[i], ell[i]
        r0, g0, b0 = col[i, 0], col[i, 1], col[i, 2]
        y_lo = max(0, int(math.floor(v - ry[i])) - 1)
        y_hi = min(h - 1, int(math.ceil(v + ry[i])) + 1)
        sa = 0.0
        sw = 0.0
        su = 0.0
        sv = 0.0
        ma = 0.0
        for y in range(y_lo, y_hi + 1):
            dy = y - v
            disc = b * b * dy * dy - a * (c * dy * dy - q)
            if disc < 0.0:
                continue
            sq = math.sqrt(disc)
            x_lo = max(0, int(math.floor(u + (-b * dy - sq) / a)) - 1)
            x_hi = min(w - 1, int(math.ceil(u + (-b * dy + sq) / a)) + 1)
            for x in range(x_lo, x_hi + 1):
                dx = x - u
                qp = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
                if qp > q:
                    continue
                if ln >= rng[y, x]:
                    occluded[i] = True
                    continue
                alpha = min(o * math.exp(-0.5 * qp), ALPHA_MAX)
                sw += alpha
                su += alpha * x
                sv += alpha * y
                if alpha < ALPHA_MIN:
                    continue
                sa += alpha
                if alpha > ma:
                    ma = alpha
                t = float(acc_t[y, x])
                if t < T_MIN:
                    continue
                # running composite V = C + T bg  ->  V + T alpha (c - bg)
                wt = t * alpha
                out[y, x, 0] += wt * (r0 - bg[y, x, 0])
                out[y, x, 1] += wt * (g0 - bg[y, x, 1])
                out[y, x, 2] += wt * (b0 - bg[y, x, 2])
                acc_t[y, x] = t * (1.0 - alpha)
        sum_a[i] = sa
        sum_w[i] = sw
        sum_wu[i] = su
        sum_wv[i] = sv
        max_a[i] = ma


# ------------------------------------------------------------------------------------------------------ render
@dataclass(frozen=True, eq=False)
class SplatResult:
    """Output of `render_particles`; per-particle arrays are in the input order.

    Attributes:
        image: (H, W, 3) float32 linear RGB, particles composited over the input image.
        centroids: (N, 2) float64 alpha-weighted centroid (u, v) [px] of the particle's footprint: every pixel of
            its centroid window (``q <= max(CENTROID_Q, qmax)``) in front of the scene, whether or not nearer
            particles cover it, weighted by ``min(0.99, o exp(-q/2))``; nan if not drawn.
        drawn: (N,) bool, the particle has at least one composited pixel (alpha >= 1/255 in front of the scene).
        max_alpha: (N,) float32 largest alpha over those pixels (0 if not drawn).
        alpha_sum: (N,) float64 sum of alpha over those pixels [px²] (the particle's visible "energy").
        unoccluded: (N,) bool, drawn and no pixel of its centroid window lies behind the scene depth.
        in_frame: (N,) bool, its whole centroid window lies inside the image (centroid unclipped).
        opacity: (N,) float64 opacity after the streak scaling (nan where near-clipped).
        ray_length: (N,) float64 distance [m] from the camera centre.
        counts: ``input, near_clipped, too_faint, off_screen, capped, occluded_fully, drawn``.
    """

    image: F32
    centroids: F64
    drawn: NDArray[np.bool_]
    max_alpha: F32
    alpha_sum: F64
    unoccluded: NDArray[np.bool_]
    in_frame: NDArray[np.bool_]
    opacity: F64
    ray_length: F64
    counts: dict[str, int]


def _velocities(value: NDArray | tuple, n: int) -> F64:
    """(n, 3) particle velocities [m/s] from one (3,) velocity or (n, 3) of their own."""
    v = np.asarray(value, dtype=np.float64)
    if v.shape == (3,):
        v = np.broadcast_to(v, (n, 3))
    if v.shape != (n, 3) or not np.all(np.isfinite(v)):
        raise ValueError(f"velocity_global of shape {np.shape(value)} is invalid: expected (3,) or ({n}, 3) finite "
                         f"velocities [m/s]")
    return v


def _vec(name: str, value: NDArray | tuple, n: int) -> F64:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} = {value!r} is invalid: expected {n} finite numbers")
    return v


def render_particles(image_linear: NDArray, range_map: NDArray, K: NDArray, T_cam_global: NDArray,
                     positions_global: NDArray, diameters: NDArray, ids: NDArray, velocity_global: NDArray | tuple,
                     camera_velocity_global: NDArray | tuple, *, exposure_s: float = 0.005,
                     appearance: ParticleAppearance = SNOW, fog_alpha: float = 0.0,
                     airlight: NDArray | tuple = (0.8, 0.8, 0.8), unresolved: UnresolvedExtinction | None = None,
                     near_clip: float = 0.5, max_footprint_px: float = 128.0) -> SplatResult:
    """Splat particles into one camera image (see the module docstring for the model and the caller's contract).

    Args:
        image_linear: (H, W, 3) float32 linear RGB background (already fogged by the caller).
        range_map: (H, W) ray length of the scene per pixel [m], inf = sky (no NaN).
        K: (3, 3) intrinsics [px]; pixel (u, v) is column u, row v at its centre.
        T_cam_global: (4, 4) global -> camera (OpenCV axes) at the camera timestamp.
        positions_global: (N, 3) particle positions [m] at the camera timestamp (middle of the exposure).
        diameters: (N,) [m]; ids: (N,) int64 particle ids (attributes and tie-breaks derive from them).
        velocity_global: (3,) particle velocity [m/s] (``field.velocity_array``), or (N, 3) one per particle.
        camera_velocity_global: (3,) camera (ego) velocity [m/s], for the relative motion.
        exposure_s: exposure time [s] (streak length ``|v_rel| exposure_s``); 0 = no motion blur.
        appearance: `SNOW`, `RAIN`, `RAIN_WEATHER_EDIT` or any `ParticleAppearance` (an ``environment`` radiance
            is taken from ``image_linear`` and ``airlight``: `particle_radiance`).
        fog_alpha: extinction of the fog [1/m] (0 = clear); unresolved: the particles' unresolved extinction;
            together they give each particle's transmission ``t(ℓ)`` for its pre-fogged colour.
        airlight: (3,) linear RGB airlight of the scene (the fog's, and the sky's radiance for a drop's environment).
        near_clip: particles nearer than this ray length [m] (or with z < near_clip / 4) are skipped.
        max_footprint_px: cap on the 3-σ half-axes of a footprint [px]: larger axes are shrunk to it and the
            opacity is ``o min(1, sqrt(det Σ2D / det Σ'2D))`` with the shrunk ``Σ'2D`` (never above ``o``).
    """
    img, rng, K, T = _frame_inputs(image_linear, range_map, K, T_cam_global)
    pos, dia, ids, v_rel = _particle_inputs(positions_global, diameters, ids, velocity_global, camera_velocity_global)
    air = _vec("airlight", airlight, 3)
    if not (exposure_s >= 0.0 and fog_alpha >= 0.0 and near_clip > 0.0 and max_footprint_px >= 2.0):
        raise ValueError("need exposure_s >= 0, fog_alpha >= 0, near_clip > 0, max_footprint_px >= 2")
    n = pos.shape[0]
    counts = {"input": n, "near_clipped": 0, "too_faint": 0, "off_screen": 0, "capped": 0, "occluded_fully": 0,
              "drawn": 0}
    if n == 0:
        e = np.zeros(0)
        return SplatResult(img.copy(), np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0, np.float32), e.copy(),
                           np.zeros(0, bool), np.zeros(0, bool), e, e.copy(), counts)

    cov, opac0, grey = particle_attributes(ids, dia, appearance)
    streak = np.ascontiguousarray(v_rel * float(exposure_s))  # (N, 3) global frame (the kernel projects with J W)
    h, w = img.shape[:2]
    view = PinholeView(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), K, w, h)
    rules = FootprintRules(float(near_clip), (float(max_footprint_px) / 3.0) ** 2, DILATION_PX2,
                           appearance.dilation_keeps_area, CENTROID_Q)
    fp = _empty_footprints(n)
    _prepare_kernel(Gaussians(pos, cov, opac0, streak), view, rules, fp)
    col = _prefogged_colours(appearance, grey, img, air, fp.ell, fog_alpha, unresolved)
    canvas, sums = _composite(fp, col, ids, img, rng)
    return _splat_result(fp, canvas, sums, counts)


def _frame_inputs(image_linear: NDArray, range_map: NDArray, K: NDArray,
                  T_cam_global: NDArray) -> tuple[F32, F32, F64, F64]:
    """`render_particles`' image (H, W, 3) float32, ray-length map (H, W) float32 [m], intrinsics (3, 3) and pose
    (4, 4), checked."""
    img = np.asarray(image_linear)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.float32:
        raise ValueError(f"image_linear must be float32 (H, W, 3), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    rng = np.ascontiguousarray(range_map, dtype=np.float32)
    if rng.shape != (h, w):
        raise ValueError(f"range_map shape {rng.shape} != image {(h, w)}")
    if np.isnan(rng).any():
        raise ValueError("range_map contains NaN (use inf for the sky)")
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_cam_global, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError(f"K must be (3, 3) and T_cam_global (4, 4), got {K.shape}, {T.shape}")
    return img, rng, K, T


def _particle_inputs(positions_global: NDArray, diameters: NDArray, ids: NDArray, velocity_global: NDArray | tuple,
                     camera_velocity_global: NDArray | tuple) -> tuple[F64, F64, NDArray[np.int64], F64]:
    """`render_particles`' positions (N, 3) [m], diameters (N,) [m], ids (N,) and velocities relative to the camera
    (N, 3) [m/s], checked."""
    pos = np.ascontiguousarray(positions_global, dtype=np.float64).reshape(-1, 3)
    n = pos.shape[0]
    dia = np.ascontiguousarray(diameters, dtype=np.float64)
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    if dia.shape != (n,) or ids.shape != (n,):
        raise ValueError(f"diameters {dia.shape} and ids {ids.shape} must be ({n},)")
    v_rel = _velocities(velocity_global, n) - _vec("camera_velocity_global", camera_velocity_global, 3)
    return pos, dia, ids, v_rel


def _empty_footprints(n: int) -> Footprints:
    """`Footprints` of ``n`` particles for `_prepare_kernel` to fill (opacity nan until computed)."""
    u0, v0, ca, cb, cc, qmax, qwin, rx, ry = (np.zeros(n) for _ in range(9))
    return Footprints(u0=u0, v0=v0, ca=ca, cb=cb, cc=cc, opac=np.full(n, np.nan), qmax=qmax, qwin=qwin,
                      ell=np.empty(n), rx=rx, ry=ry, status=np.empty(n, dtype=np.int8),
                      capped=np.zeros(n, dtype=np.bool_), in_frame=np.zeros(n, dtype=np.bool_))


def _prefogged_colours(appearance: ParticleAppearance, grey: F64, img: F32, air: F64, ell: F64, fog_alpha: float,
                       unresolved: UnresolvedExtinction | None) -> F64:
    """(N, 3) linear RGB of each particle at ray length ``ell`` (N,) [m] seen through the fog and the unresolved
    particles: ``c t(ℓ) + A (1 - t(ℓ))`` (``c`` from `particle_radiance`, ``A`` the airlight ``air``)."""
    if unresolved is not None:
        trans = unresolved.transmission(ell, fog_alpha)
    else:
        trans = np.exp(-float(fog_alpha) * ell)
    return particle_radiance(appearance, grey, img, air) * trans[:, None] + (1.0 - trans)[:, None] * air[None, :]


def _composite(fp: Footprints, col: F64, ids: NDArray[np.int64], img: F32,
               rng: F32) -> tuple[Canvas, FootprintSums]:
    """The particles with status ok, nearest first (ties by id), of colours ``col`` (N, 3) composited over ``img``
    (H, W, 3) in front of the scene's ray lengths ``rng`` (H, W) [m] (`_splat_kernel`)."""
    n = len(ids)
    ok = np.flatnonzero(fp.status == _OK)
    order = ok[np.lexsort((ids[ok], fp.ell[ok]))]
    bg = np.ascontiguousarray(img)
    canvas = Canvas(rng=rng, bg=bg, out=bg.copy(), acc_t=np.ones(rng.shape, dtype=np.float32))
    sum_a, sum_w, sum_wu, sum_wv, max_a = (np.zeros(n) for _ in range(5))
    sums = FootprintSums(sum_a=sum_a, sum_w=sum_w, sum_wu=sum_wu, sum_wv=sum_wv, max_a=max_a,
                         occluded=np.zeros(n, dtype=np.bool_))
    _splat_kernel(order, fp, np.ascontiguousarray(col), canvas, sums)
    return canvas, sums


def _splat_result(fp: Footprints, canvas: Canvas, sums: FootprintSums, counts: dict[str, int]) -> SplatResult:
    """The `SplatResult` of the composited ``canvas``, with ``counts`` completed."""
    status = fp.status
    drawn = sums.sum_a > 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        centroids = np.where(drawn[:, None], np.stack([sums.sum_wu, sums.sum_wv], axis=1) / sums.sum_w[:, None],
                             np.nan)
    counts.update(near_clipped=int(np.sum(status == _NEAR)), too_faint=int(np.sum(status == _FAINT)),
                  off_screen=int(np.sum(status == _OFFSCREEN)), capped=int(np.sum(fp.capped & (status == _OK))),
                  occluded_fully=int(np.sum((status == _OK) & ~drawn & sums.occluded)), drawn=int(drawn.sum()))
    return SplatResult(image=canvas.out, centroids=centroids, drawn=drawn, max_alpha=sums.max_a.astype(np.float32),
                       alpha_sum=sums.sum_a, unoccluded=drawn & ~sums.occluded, in_frame=fp.in_frame & (status == _OK),
                       opacity=fp.opac, ray_length=fp.ell, counts=counts)


# ------------------------------------------------------------------------------------------------------ reference
def _naive(image_linear: NDArray, range_map: NDArray, K: NDArray, T_cam_global: NDArray, positions_global: NDArray,
           diameters: NDArray, ids: NDArray, velocity_global: NDArray | tuple,
           camera_velocity_global: NDArray | tuple, *, exposure_s: float = 0.005,
           appearance: ParticleAppearance = SNOW, fog_alpha: float = 0.0,
           airlight: NDArray | tuple = (0.8, 0.8, 0.8), unresolved: UnresolvedExtinction | None = None,
           near_clip: float = 0.5, max_footprint_px: float = 128.0) -> tuple[F64, F64]:
    """Slow, obviously correct reference of `render_particles` for small images (tests only).

    Per particle with plain numpy matrices: ``Σ2D = J W Σ Wᵀ Jᵀ + 0.3 I``, ``Σ'2D`` with the streak, eigenvalues
    clamped to the cap, ``o' = o min(1, sqrt(det Σ2D / det Σ'2D))``, alpha evaluated at *every* pixel (centroid weights
    inside the window ``q <= max(2 ln(255 o'), CENTROID_Q)``). Per pixel:
    the particles with alpha >= 1/255 in front of the scene, sorted by (ray length, id), composited front to back
    in float64 until the transmittance drops below `T_MIN`.

    Returns:
        image (H, W, 3) float64 and the alpha-weighted centroids (N, 2) (nan where no pixel with alpha >= 1/255 is
        visible).
    """
    img = np.asarray(image_linear, dtype=np.float64)
    h, w = img.shape[:2]
    K = np.asarray(K, dtype=np.float64)
    Rm = np.asarray(T_cam_global, dtype=np.float64)[:3, :3]
    tr = np.asarray(T_cam_global, dtype=np.float64)[:3, 3]
    pos = np.asarray(positions_global, dtype=np.float64).reshape(-1, 3)
    ids = np.asarray(ids, dtype=np.int64)
    cov, opac0, grey = particle_attributes(ids, diameters, appearance)
    streaks = (np.broadcast_to(np.asarray(velocity_global, float), pos.shape)
               - np.asarray(camera_velocity_global, float)) @ Rm.T * exposure_s  # (N, 3) camera frame
    air = np.asarray(airlight, dtype=np.float64)
    radiance = np.asarray(appearance.tint, dtype=np.float64)
    if appearance.radiance == "environment":  # half the image's mean radiance, half the sky (airlight)
        radiance = radiance * (0.5 * img.reshape(-1, 3).mean(axis=0) + 0.5 * air)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    alphas: list[F64] = []
    weights: list[F64] = []
    keys: list[tuple[float, int]] = []
    colours: list[F64] = []
    lengths: list[float] = []
    owners: list[int] = []
    for i in range(len(ids)):
        p = Rm @ pos[i] + tr
        ln = float(np.linalg.norm(p))
        if ln < near_clip or p[2] < 0.25 * near_clip:
            continue
        x, y, z = p
        J = np.array([[K[0, 0] / z, K[0, 1] / z, -(K[0, 0] * x + K[0, 1] * y) / z**2],
                      [0.0, K[1, 1] / z, -K[1, 1] * y / z**2]])
        S_cam = Rm @ cov[i] @ Rm.T
        S2 = J @ S_cam @ J.T + DILATION_PX2 * np.eye(2)
        S2s = J @ (S_cam + np.outer(streaks[i], streaks[i]) / 12.0) @ J.T + DILATION_PX2 * np.eye(2)
        lam, vec = np.linalg.eigh(S2s)
        lam = np.minimum(lam, (max_footprint_px / 3.0) ** 2)
        S2s = vec @ np.diag(lam) @ vec.T
        S_energy = J @ S_cam @ J.T if appearance.dilation_keeps_area else S2
        o = opac0[i] * min(1.0, math.sqrt(np.linalg.det(S_energy) / np.linalg.det(S2s)))
        mean = (K @ p)[:2] / z
        d = np.stack([xx - mean[0], yy - mean[1]], axis=-1)
        q = np.einsum("...i,ij,...j->...", d, np.linalg.inv(S2s), d)
        weight = np.minimum(ALPHA_MAX, o * np.exp(-0.5 * q))
        q_window = max(2.0 * math.log(255.0 * o), CENTROID_Q) if o * 255.0 >= 1.0 else -1.0
        weight[q > q_window] = 0.0
        alpha = np.where(weight >= ALPHA_MIN, weight, 0.0)
        t = float(unresolved.transmission(ln, fog_alpha)) if unresolved is not None else math.exp(-fog_alpha * ln)
        alphas.append(alpha)
        weights.append(weight)
        keys.append((ln, int(ids[i])))
        colours.append(grey[i] * radiance * t + air * (1.0 - t))
        lengths.append(ln)
        owners.append(i)
    out = img.copy()
    cent_num = np.zeros((len(ids), 2))
    cent_den = np.zeros(len(ids))
    visible = np.zeros(len(ids), dtype=bool)
    rng = np.asarray(range_map, dtype=np.float64)
    for yv in range(h):
        for xv in range(w):
            for j in range(len(weights)):
                if weights[j][yv, xv] > 0.0 and lengths[j] < rng[yv, xv]:
                    cent_num[owners[j]] += weights[j][yv, xv] * np.array([xv, yv])
                    cent_den[owners[j]] += weights[j][yv, xv]
            hits = [j for j in range(len(alphas))
                    if alphas[j][yv, xv] > 0.0 and lengths[j] < rng[yv, xv]]
            for j in hits:
                visible[owners[j]] = True
            hits.sort(key=lambda j: keys[j])
            trans, acc = 1.0, np.zeros(3)
            for j in hits:
                if trans < T_MIN:
                    break
                a = alphas[j][yv, xv]
                acc += trans * a * colours[j]
                trans *= 1.0 - a
            out[yv, xv] = acc + trans * img[yv, xv]
    with np.errstate(invalid="ignore", divide="ignore"):
        cent = np.where(visible[:, None], cent_num / cent_den[:, None], np.nan)
    return out, cent
