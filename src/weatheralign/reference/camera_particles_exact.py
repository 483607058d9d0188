"""The synthetic reference's camera through snow and rain: per-pixel ray tracing of the particles with supersampling
over the pixel and over the exposure (motion blur), and the unresolved particles as a continuous medium.

This is the reference's "real world" that the fast Gaussian-splatting camera simulator is compared against, so it
shares no method with it: no Gaussians, no splatting, no projection of covariances. Each pixel is estimated by
Monte-Carlo integration over its area and the exposure, each sample an exact ray–sphere test.

Geometry (units: metres, seconds, pixels; OpenCV optical axes x right, y down, z forward). The pinhole camera has
intrinsics ``K`` (no skew; pixel ``(col, row)`` has its centre at ``u = col``, ``v = row`` and covers
``[col - 1/2, col + 1/2] x [row - 1/2, row + 1/2]``) and camera-to-world pose ``T_world_cam`` at the frame time
``t``; during the exposure it translates with the linear ego velocity ``v_cam`` (world frame) and does not rotate.
Pixel ``p`` gets ``S`` samples ``k``: a sub-pixel position and a time ``τ_k = t + (ut_k - 1/2) T_e`` in
``[t - T_e/2, t + T_e/2]``, stratified and jittered deterministically from ``seed`` (`sample_pattern`):

- positions: a jittered ``√S x √S`` grid when ``S`` is a square, else ``S`` rooks (one sample per column stratum
  and per row stratum, rows permuted per pixel);
- times: one sample per ``1/S`` of the exposure, the strata permuted per pixel (so time and position decorrelate);
- jitter: SplitMix64 hashes of ``(seed, pixel, sample)``; permutations: a seeded table of 1024 (Fisher–Yates on the
  same hash), one picked per pixel by its hash.

Particle ``i`` is a sphere of its diameter ``D_i`` centred at ``P_i(τ) = P_i(t) + V_i (τ - t)``: ``P_i(t)`` is the
field's position at the frame time (`weatheralign.medium.field.ParticleField.materialize`), ``V_i`` the field's
velocity (snow) or, with ``per_diameter_fall``, the field's horizontal wind and the drop's own terminal fall
``rain_terminal_velocity(D_i)`` (rain). In the camera frame of time ``t`` the camera stays at the origin and the
centre moves linearly, ``c_i(τ) = Rᵀ(P_i(t) - o) + Rᵀ(V_i - v_cam)(τ - t)``. Sample ``k`` of pixel ``(col, row)``
casts the ray of direction ``d = ((u - c_x)/f_x, (v - c_y)/f_y, 1)``, ``u = col - 1/2 + ux_k``,
``v = row - 1/2 + uy_k``, and meets sphere ``i`` (exactly) at distance

    s = (d·c - sqrt((d·c)² - |d|² (|c|² - D²/4))) / |d|        (when the root is real, d·c > 0),

``c = c_i(τ_k)``. The sample sees the nearest particle it meets if that is nearer than the scene (the pixel's
``ray_length`` ``ℓ``, taken along every sample ray of the pixel; ``inf`` = sky, which no particle is behind); else it
sees the scene. Particles whose sphere comes nearer than ``near_clip`` (z-depth, default 0.3 m) at any time of the
exposure are ignored (a lens-hugging flake is not imaged).

Radiance. Every resolved particle has the caller's radiance ``L`` (3,) (snow: albedo x its illumination; rain: the
environment a drop refracts). The unresolved particles (below) are a medium that, in single scattering of the same
particles, has the same radiance: along a path with optical depth ``τ`` it transmits ``e^{-τ}`` and adds the veil
``L (1 - e^{-τ})``. A sample that meets a particle at ``s`` therefore sees ``L e^{-τ(s)} + L (1 - e^{-τ(s)}) = L``
(exactly: the medium in front of a particle is invisible), and a scene sample sees

    I_scene = J_b e^{-τ(ℓ)} + L (1 - e^{-τ(ℓ)}),

``J_b`` the pixel's clear linear radiance ``J`` (sky pixels: ``J`` or ``sky_radiance_behind``, at ``ℓ = sky_distance``,
default 2000 m). The pixel is the mean of its samples: ``I = (1 - c) I_scene + c L``, ``c`` the fraction of samples
that met a particle (`ParticleImage.coverage`).

Resolved and unresolved particles. A particle at distance ``r`` (from the camera centre, at ``t``) is resolved, i.e.
traced, when its image diameter ``f D / r`` (``f = max(f_x, f_y)``) is at least ``resolve_px`` pixels and ``r <=
max_distance``: ``D >= D_res(r) = k r``, ``k = resolve_px / f``. The others, at every distance ``s`` along a ray, are
the medium of extinction (their geometric shadow, ``Q = Q_IMAGING = 1``: half of `ParticleField.unresolved_extinction`'s
``Q_ext = 2``, whose other half is light diffracted into a lobe of ``λ / D`` ≈ 0.5 mrad, under a pixel, which the
pixel keeps; a traced sphere blocks its geometric area too, so both count the same)

    α_u(s) = (π/4) ∫_{d_min}^{min(D_res(s), d_max)} D² N(D) dD   (s <= max_distance),   α_u(s) = α (s > max_distance)

with ``N(D) = n0 e^{-λD}`` on ``[d_min, d_max]`` and ``α`` the field's bulk geometric extinction. The medium exists only
in the field's layer ``z_min <= z <= z_max`` (world z): a pixel's optical depth is ``τ = G(s_b) - G(s_a)`` over the part
``[s_a, s_b]`` of its ray ``[0, ℓ]`` inside the layer, with the closed form (swap the order of integration)

    G(s) = ∫_0^s α_u = (π/4) n0 / k · [Y M_2(d_min, m) - M_3(d_min, m)],  Y = k min(s, R),  m = min(Y, d_max)
           (+ α (s - R) for s > R = max_distance),   M_j(a, b) = ∫_a^b D^j e^{-λD} dD (elementary for integer j).

What is exact: the sphere geometry and occlusion per sample, the particles' and the camera's linear motion during the
exposure, the resolved/unresolved split (by each particle's own distance, and by each distance along the ray for the
medium, so nothing is counted twice or missed), the medium's optical depth. What is approximated: the pixel integral
by ``S`` stratified samples (the estimator's error, not a bias); particles as uniformly bright spheres (no shading
across a flake, no refracted image inside a drop, no specular glints); the medium's optical depth taken along the
pixel-centre ray at ``t`` for all of the pixel's samples (the scene's ray length is per pixel anyway; only a sky ray's
exit from the layer moves across the pixel, by ~``cot(elevation) / f`` relative, and the camera's 6 cm during an
exposure are negligible against the path); single scattering; the camera's rotation during the exposure is
neglected. Linear radiance in, linear radiance out (the caller encodes).

Efficiency: the resolved particles are materialised in z-depth slabs of the view frustum (each slab with its own
``min_diameter = k z``, an axis-aligned world box around the slab widened by the particles' and the camera's motion
during the exposure and the largest radius, the field clipping it to its layer), then traced particle-major in numba:
each particle's swept sphere (both end spheres' exact projected extents; the projection of their convex hull is the
hull of their projections) bounds the pixels whose samples are tested, keeping per sample the nearest hit distance
(a streak that is long and diagonal in the image is cut into up to 32 parts of the exposure, each with the box of its
own swept sphere, and a sample is tested only in the part that holds its time). The result does not depend on these
boxes: the tests compare it with every sample against every particle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.medium.distributions import Q_EXT_GEOMETRIC, Q_IMAGING, rain_terminal_velocity
from weatheralign.medium.field import ParticleField, Particles, splitmix64, splitmix64_py
from weatheralign.reference.records import CameraMedium, PixelRays, PixelScene

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

SKY_DISTANCE = 2000.0
"""Length [m] of a sky pixel's path through the medium (the clear sky's radiance behind it)."""

NEAR_CLIP = 0.3
"""Particles whose sphere comes nearer than this z-depth [m] during the exposure are ignored."""

N_PERMUTATIONS = 1024
"""Size of the table of stratum permutations a pixel picks its own from (10 bits of its hash)."""

MAX_SAMPLES = 1024
"""Largest number of samples per pixel accepted."""

_PERM_SHIFT = np.uint64(64 - 10)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_TAG_T = np.uint64(0x7A3C5D1E9B2F4861)
_TAG_Y = np.uint64(0x1F6B8E2D4C9A7305)
_TAG_PERM = np.uint64(0x5EED0F9E12A3B4C7)
_SH11 = np.uint64(11)
_UNIT = 2.0 ** -53
_BBOX_EPS_PX = 1e-4
"""Pixel margin added to each particle's exact projected extent (covers rounding of the tangent evaluation)."""


# ------------------------------------------------------------------------------------------------------------ samples
@njit(cache=True, nogil=True, inline="always")
def _unit(key: np.uint64, counter: np.uint64) -> float:  # pragma: no cover - numba
    """Uniform in [0, 1) (53 bits) from hash stream ``key`` at ``counter``."""
    return float(splitmix64(key + (counter + np.uint64(1)) * _GOLD) >> _SH11) * _UNIT


@njit(cache=True, nogil=True, inline="always")
def _pixel_key(seed_key: np.uint64, pixel: np.int64) -> np.uint64:  # pragma: no cover - numba
    return splitmix64(seed_key ^ splitmix64(np.uint64(pixel) * _GOLD + _GOLD))


@njit(cache=True, nogil=True)
def _permutation_table(seed_key: np.uint64, n: int, s: int) -> NDArray:  # pragma: no cover - numba
    """(n, s) int64: ``n`` permutations of ``0..s-1`` (Fisher–Yates on hashed uniforms)."""
    out = np.empty((n, s), dtype=np.int64)
    for r in range(n):
        key = splitmix64(seed_key ^ splitmix64(np.uint64(r) * _GOLD + _TAG_PERM))
        for i in range(s):
            out[r, i] = i
        for i in range(s - 1, 0, -1):
            j = int(_unit(key, np.uint64(i)) * (i + 1))
            if j > i:
                j = i
            tmp = out[r, i]
            out[r, i] = out[r, j]
            out[r, j] = tmp
    return out


@njit(cache=True, nogil=True, inline="always")
def _sample_time(key: np.uint64, k: int, s: int, perms: NDArray, row_t: int) -> float:  # pragma: no cover - numba
    """Exposure fraction ut in [0, 1] of sample ``k`` of the pixel with hash ``key``."""
    return (float(perms[row_t, k]) + _unit(key, np.uint64(3 * k + 2))) / s


@njit(cache=True, nogil=True, inline="always")
def _sample_position(key: np.uint64, k: int, s: int, grid: int, perms: NDArray,
                     row_y: int) -> tuple[float, float]:  # pragma: no cover - numba
    """Sub-pixel offsets (ux, uy) in [0, 1] of sample ``k`` of the pixel with hash ``key``."""
    c = np.uint64(3 * k)
    h1 = _unit(key, c)
    h2 = _unit(key, c + np.uint64(1))
    if grid > 0:
        return (float(k % grid) + h1) / grid, (float(k // grid) + h2) / grid
    return (float(k) + h1) / s, (float(perms[row_y, k]) + h2) / s


@njit(cache=True, nogil=True, inline="always")
def _sample(key: np.uint64, k: int, s: int, grid: int, perms: NDArray, row_t: int,
            row_y: int) -> tuple[float, float, float]:  # pragma: no cover - numba
    """Sample ``k`` of a pixel with hash ``key``: sub-pixel offsets (ux, uy) in [0, 1] and exposure fraction ut."""
    ux, uy = _sample_position(key, k, s, grid, perms, row_y)
    return ux, uy, _sample_time(key, k, s, perms, row_t)


@njit(cache=True, nogil=True, inline="always")
def _pixel_rows(key: np.uint64) -> tuple[int, int]:  # pragma: no cover - numba
    """The pixel's rows of the permutation table (time strata, row strata)."""
    return int(splitmix64(key ^ _TAG_T) >> _PERM_SHIFT), int(splitmix64(key ^ _TAG_Y) >> _PERM_SHIFT)


@njit(cache=True, nogil=True)
def _pattern_kernel(height: int, width: int, s: int, grid: int, seed_key: np.uint64, perms: NDArray,
                    out: NDArray) -> None:  # pragma: no cover - numba
    for row in range(height):
        for col in range(width):
            key = _pixel_key(seed_key, np.int64(row * width + col))
            row_t, row_y = _pixel_rows(key)
            for k in range(s):
                ux, uy, ut = _sample(key, k, s, grid, perms, row_t, row_y)
                out[row, col, k, 0] = ux
                out[row, col, k, 1] = uy
                out[row, col, k, 2] = ut


def _seed_key(seed: int) -> np.uint64:
    return np.uint64(splitmix64_py(splitmix64_py(int(seed) ^ 0xCA3E7A5A3B1E) + 0x9E3779B97F4A7C15))


def _grid_of(samples: int) -> int:
    g = math.isqrt(samples)
    return g if g * g == samples else 0


def _check_samples(samples: int, who: str) -> int:
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or not 1 <= samples <= MAX_SAMPLES:
        raise ValueError(f"{who}: samples = {samples!r} is invalid: expected an integer in [1, {MAX_SAMPLES}] "
                         "(samples per pixel)")
    return int(samples)


def _check_seed(seed: int, who: str) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise ValueError(f"{who}: seed = {seed!r} is invalid: expected an integer in [0, 2^63)")
    return int(seed)


def _permutations(seed: int, samples: int) -> I64:
    return _permutation_table(_seed_key(seed), N_PERMUTATIONS, samples)


def sample_pattern(height: int, width: int, samples: int = 16, seed: int = 0) -> F64:
    """The sub-pixel positions and exposure times of every sample, exactly as `particle_image` and `trace_particles`
    draw them: (H, W, S, 3) float64 ``(ux, uy, ut)`` in [0, 1]; sample ``k`` of pixel ``(row, col)`` lies at
    ``u = col - 1/2 + ux``, ``v = row - 1/2 + uy`` [px] and time ``t + (ut - 1/2) T_e``.

    Raises:
        ValueError: non-positive image size, ``samples`` outside [1, 1024], bad ``seed``.
    """
    if min(int(height), int(width)) < 1:
        raise ValueError(f"sample_pattern: height = {height!r}, width = {width!r}; expected positive pixel counts")
    s = _check_samples(samples, "sample_pattern")
    seed = _check_seed(seed, "sample_pattern")
    out = np.empty((int(height), int(width), s, 3))
    _pattern_kernel(int(height), int(width), s, _grid_of(s), _seed_key(seed), _permutations(seed, s), out)
    return out


# ------------------------------------------------------------------------------------------------------------ tracing
@njit(cache=True, nogil=True, inline="always")
def _tangent_extent(a: float, z: float, rho: float) -> tuple[float, float]:  # pragma: no cover - numba
    """Range of ``a'/z'`` over the disc of radius ``rho`` centred at ``(a, z)`` (``z > rho``): the slopes of the two
    tangents from the origin."""
    r = math.sqrt(a * a + z * z)
    theta = math.atan2(a, z)
    delta = math.asin(min(rho / r, 1.0))
    return math.tan(theta - delta), math.tan(theta + delta)


@njit(cache=True, nogil=True, inline="always")
def _sphere_box(x: float, y: float, z: float, rho: float, fx: float, fy: float, cx: float,
                cy: float) -> tuple[float, float, float, float]:  # pragma: no cover - numba
    """Exact pixel-coordinate extent (u_lo, u_hi, v_lo, v_hi) of the image of a sphere in front of the camera."""
    lo, hi = _tangent_extent(x, z, rho)
    a, b = _tangent_extent(y, z, rho)
    return fx * lo + cx, fx * hi + cx, fy * a + cy, fy * b + cy


@njit(cache=True, nogil=True, inline="always")
def _pixel_span(lo: float, hi: float, n: int) -> tuple[int, int]:  # pragma: no cover - numba
    """Pixels (first, last) whose samples ``[p - 1/2, p + 1/2]`` can fall in ``[lo, hi]`` (with the margin)."""
    return (max(0, int(math.ceil(lo - _BBOX_EPS_PX - 0.5))), min(n - 1, int(math.floor(hi + _BBOX_EPS_PX + 0.5))))


@njit(cache=True, nogil=True)
def _trace_kernel(centers: NDArray, vels: NDArray, radii: NDArray, fx: float, fy: float, cx: float, cy: float,
                  width: int, height: int, s: int, grid: int, exposure: float, seed_key: np.uint64, perms: NDArray,
                  inverse: NDArray, near: float, ray_len: NDArray, depth: NDArray,
                  hit: NDArray) -> tuple[int, int]:  # pragma: no cover
    """Particle-major: for each particle the pixels its swept sphere can cover, each of their samples tested exactly;
    ``depth`` (H*W*S,) keeps the nearest hit distance (initialised to the pixel's ray length). Returns (particles
    traced, sample tests).

    A streak that is diagonal in the image is cut into ``M`` equal parts of the exposure, each with the pixel box of
    its own swept sphere, and a sample is tested only in the part that holds its time (its time stratum found through
    ``inverse``, the inverse permutations): the same tests where they matter, without the empty corners of one box."""
    half = 0.5 * exposure
    traced = 0
    tests = 0
    for n in range(centers.shape[0]):
        rho = radii[n]
        c0x, c0y, c0z = centers[n, 0], centers[n, 1], centers[n, 2]
        wx, wy, wz = vels[n, 0], vels[n, 1], vels[n, 2]
        if min(c0z - wz * half, c0z + wz * half) - rho < near:
            continue
        ua0, ua1, va0, va1 = _sphere_box(c0x - wx * half, c0y - wy * half, c0z - wz * half, rho, fx, fy, cx, cy)
        ub0, ub1, vb0, vb1 = _sphere_box(c0x + wx * half, c0y + wy * half, c0z + wz * half, rho, fx, fy, cx, cy)
        col0, col1 = _pixel_span(min(ua0, ub0), max(ua1, ub1), width)
        row0, row1 = _pixel_span(min(va0, vb0), max(va1, vb1), height)
        if col0 > col1 or row0 > row1:
            continue
        traced += 1
        # parts of the exposure: about one per sphere width along the shorter side of the streak's box
        du = abs(0.5 * (ub0 + ub1) - 0.5 * (ua0 + ua1))
        dv = abs(0.5 * (vb0 + vb1) - 0.5 * (va0 + va1))
        size = max(1.0, min(ua1 - ua0, va1 - va0, ub1 - ub0, vb1 - vb0))
        parts = min(32, max(1, int(min(du, dv) / size)))
        rho2 = rho * rho
        for m in range(parts):
            if parts > 1:
                t_a = -half + exposure * m / parts
                t_b = -half + exposure * (m + 1) / parts
                ua0, ua1, va0, va1 = _sphere_box(c0x + wx * t_a, c0y + wy * t_a, c0z + wz * t_a, rho, fx, fy, cx, cy)
                ub0, ub1, vb0, vb1 = _sphere_box(c0x + wx * t_b, c0y + wy * t_b, c0z + wz * t_b, rho, fx, fy, cx, cy)
                col0, col1 = _pixel_span(min(ua0, ub0), max(ua1, ub1), width)
                row0, row1 = _pixel_span(min(va0, vb0), max(va1, vb1), height)
                # time strata that can hold a sample of this part (one more each side for rounding at the edges)
                j0 = max(0, (m * s) // parts - 1)
                j1 = min(s - 1, ((m + 1) * s + parts - 1) // parts)
            else:
                j0, j1 = 0, s - 1
            for row in range(row0, row1 + 1):
                for col in range(col0, col1 + 1):
                    pix = row * width + col
                    scene = ray_len[pix]
                    key = _pixel_key(seed_key, np.int64(pix))
                    row_t, row_y = _pixel_rows(key)
                    base = pix * s
                    for j in range(j0, j1 + 1):
                        k = j if parts == 1 else inverse[row_t, j]
                        ut = _sample_time(key, k, s, perms, row_t)
                        if parts > 1 and min(int(ut * parts), parts - 1) != m:
                            continue
                        tests += 1
                        ux, uy = _sample_position(key, k, s, grid, perms, row_y)
                        u = (float(col) - 0.5) + ux
                        v = (float(row) - 0.5) + uy
                        dt = (ut - 0.5) * exposure
                        px = c0x + wx * dt
                        py = c0y + wy * dt
                        pz = c0z + wz * dt
                        dx = (u - cx) / fx
                        dy = (v - cy) / fy
                        dc = dx * px + dy * py + pz
                        if dc <= 0.0:
                            continue
                        n2 = dx * dx + dy * dy + 1.0
                        cc = px * px + py * py + pz * pz - rho2
                        disc = dc * dc - n2 * cc
                        if disc < 0.0:
                            continue
                        dist = (dc - math.sqrt(disc)) / math.sqrt(n2)
                        if dist < scene:
                            hit[n] = True
                            if dist < depth[base + k]:
                                depth[base + k] = dist
    return traced, tests


@dataclass(frozen=True, eq=False)
class SampleHits:
    """What every sample of an image met (`trace_particles`).

    Attributes:
        depth: (H, W, S) float64 distance [m] along the sample ray to the nearest particle met in front of the
            scene, ``inf`` where the sample sees the scene.
        traced: particles whose swept sphere reaches the image (after the near clip).
        particles_hit: particles met by at least one sample in front of the scene.
        tests: sample-sphere tests made.
    """

    depth: F64
    traced: int
    particles_hit: int
    tests: int

    @property
    def coverage(self) -> F32:
        """(H, W) float32 fraction of each pixel's samples that met a particle."""
        s = self.depth.shape[2]
        return (np.count_nonzero(np.isfinite(self.depth), axis=2) / s).astype(np.float32)


def _intrinsics(K: NDArray, who: str) -> tuple[float, float, float, float]:
    k = np.asarray(K, dtype=np.float64)
    ok = (k.shape == (3, 3) and bool(np.all(np.isfinite(k))) and k[0, 0] > 0.0 and k[1, 1] > 0.0
          and k[0, 1] == 0.0 and k[1, 0] == 0.0 and k[2, 0] == 0.0 and k[2, 1] == 0.0 and k[2, 2] == 1.0)
    if not ok:
        raise ValueError(f"{who}: K = {K!r} is invalid: expected a (3, 3) pinhole matrix [[fx, 0, cx], [0, fy, cy], "
                         "[0, 0, 1]] with fx, fy > 0 [px] (no skew)")
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])


def _ray_lengths(ray_length: NDArray, who: str) -> F64:
    ell = np.asarray(ray_length, dtype=np.float64)
    if ell.ndim != 2 or min(ell.shape) < 1 or np.isnan(ell).any() or (ell < 0.0).any():
        raise ValueError(f"{who}: ray_length must be an (H, W) array of distances >= 0 [m] along each pixel's ray "
                         f"(inf = sky, no NaN), got shape {ell.shape}")
    return ell


def _nonneg(who: str, name: str, value: float, unit: str, positive: bool = False) -> float:
    v = float(value)
    if not (math.isfinite(v) and (v > 0.0 if positive else v >= 0.0)):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{who}: {name} = {value!r} [{unit}] is invalid: expected a finite number {bound}")
    return v


def trace_particles(centers: NDArray, velocities: NDArray, diameters: NDArray, K: NDArray, ray_length: NDArray, *,
                    exposure_s: float = 0.006, samples: int = 16, seed: int = 0,
                    near_clip: float = NEAR_CLIP) -> SampleHits:
    """Trace every sample of an image against explicit spheres (the geometry core of `particle_image`).

    Args:
        centers: (N, 3) sphere centres [m] at the frame time, in the camera frame of the frame time (OpenCV axes).
        velocities: (N, 3) velocities [m/s] relative to the camera, camera frame (``Rᵀ (V_i - v_cam)``).
        diameters: (N,) sphere diameters [m], > 0.
        K: (3, 3) pinhole intrinsics (no skew).
        ray_length: (H, W) distance [m] to the scene along each pixel's rays (``inf`` = sky); sets the image size.
        exposure_s: exposure time T_e [s] (>= 0) centred on the frame time.
        samples: samples per pixel S.
        seed: seed of the sample pattern (`sample_pattern`).
        near_clip: spheres nearer than this z-depth [m] at any time of the exposure are ignored (> 0).

    Raises:
        ValueError: bad shapes or values (the message names the argument).
    """
    who = "trace_particles"
    c = np.ascontiguousarray(np.asarray(centers, dtype=np.float64))
    w = np.ascontiguousarray(np.asarray(velocities, dtype=np.float64))
    d = np.ascontiguousarray(np.asarray(diameters, dtype=np.float64))
    if c.ndim != 2 or c.shape[1] != 3 or not np.isfinite(c).all():
        raise ValueError(f"{who}: centers must be an (N, 3) array of finite positions [m], got shape {c.shape}")
    if w.shape != c.shape or not np.isfinite(w).all():
        raise ValueError(f"{who}: velocities must be an (N, 3) array of finite velocities [m/s] like centers "
                         f"{c.shape}, got shape {w.shape}")
    if d.shape != (c.shape[0],) or not np.isfinite(d).all() or (d <= 0.0).any():
        raise ValueError(f"{who}: diameters must be an (N,) array of finite diameters > 0 [m] (N = {c.shape[0]}), "
                         f"got shape {d.shape}")
    fx, fy, cx, cy = _intrinsics(K, who)
    ell = _ray_lengths(ray_length, who)
    exposure = _nonneg(who, "exposure_s", exposure_s, "s")
    s = _check_samples(samples, who)
    seed = _check_seed(seed, who)
    near = _nonneg(who, "near_clip", near_clip, "m", positive=True)
    height, width = ell.shape
    flat = np.ascontiguousarray(ell.ravel())
    depth = np.repeat(flat, s)
    hit = np.zeros(c.shape[0], dtype=np.bool_)
    perms = _permutations(seed, s)
    inverse = np.empty_like(perms)
    np.put_along_axis(inverse, perms, np.broadcast_to(np.arange(s), perms.shape), axis=1)
    traced, tests = _trace_kernel(c, w, 0.5 * d, fx, fy, cx, cy, width, height, s, _grid_of(s), exposure,
                                  _seed_key(seed), perms, inverse, near, flat, depth, hit)
    depth = depth.reshape(height, width, s)
    depth[~(depth < ell[:, :, None])] = np.inf
    return SampleHits(depth, int(traced), int(np.count_nonzero(hit)), int(tests))


# ------------------------------------------------------------------------------------------------------------ medium
@dataclass(frozen=True)
class UnresolvedMedium:
    """The unresolved particles as a medium (see the module docstring): optical depth along a ray from the camera.

    Attributes:
        n0, lam, d_min, d_max: the field's spectrum ``N(D) = n0 e^{-lam D}`` on ``[d_min, d_max]`` [1/m⁴, 1/m, m].
        k: ``D_res(s) = k s`` [m of diameter per m of distance] (``resolve_px / f``).
        max_distance: beyond this distance [m] every particle is unresolved.
        alpha_total: the field's bulk extinction [1/m].
        z_min, z_max: the layer [m] (world z) that holds the medium.
    """

    n0: float
    lam: float
    d_min: float
    d_max: float
    k: float
    max_distance: float
    alpha_total: float
    z_min: float
    z_max: float

    @classmethod
    def of(cls, field: ParticleField, resolve_px: float, focal_px: float, max_distance: float) -> UnresolvedMedium:
        """The medium of ``field``'s particles that a camera of focal length ``focal_px`` does not resolve."""
        spec = field.spectrum
        return cls(spec.n0, spec.lam, spec.d_min, spec.d_max, resolve_px / focal_px, max_distance,
                   field.extinction() * Q_IMAGING / Q_EXT_GEOMETRIC, field.z_min, field.z_max)

    def alpha(self, s: float) -> float:
        """Extinction ``α_u(s)`` [1/m] at distance ``s`` [m] (``= field.unresolved_extinction(k s) · Q_IMAGING /
        Q_EXT_GEOMETRIC`` up to ``max_distance``, the bulk geometric extinction beyond)."""
        if s > self.max_distance:
            return self.alpha_total
        a = self.d_min
        m = min(max(self.k * s, a), self.d_max)
        return Q_IMAGING * math.pi / 4.0 * self.n0 * (_prim(2, a, self.lam) - _prim(2, m, self.lam))

    def optical_depth_to(self, s: NDArray | float) -> F64:
        """``G(s) = ∫_0^s α_u`` [1] (any shape), ignoring the layer."""
        s = np.asarray(s, dtype=np.float64)
        out = np.empty(s.shape)
        flat = out.reshape(-1)
        medium = self.record()
        for i, v in enumerate(s.reshape(-1)):
            flat[i] = _G(float(v), medium)
        return out

    def record(self) -> CameraMedium:
        """The medium as the kernels take it."""
        return CameraMedium(self.n0, self.lam, self.d_min, self.d_max, self.k, self.max_distance, self.alpha_total,
                            self.z_min, self.z_max)


@njit(cache=True, nogil=True)
def _prim(j: int, d: float, lam: float) -> float:  # pragma: no cover - numba
    """``∫_d^∞ D^j e^{-lam D} dD`` for j = 2, 3 (elementary)."""
    e = math.exp(-lam * d)
    if j == 2:
        return e * (d * d / lam + 2.0 * d / lam ** 2 + 2.0 / lam ** 3)
    return e * (d * d * d / lam + 3.0 * d * d / lam ** 2 + 6.0 * d / lam ** 3 + 6.0 / lam ** 4)


@njit(cache=True, nogil=True)
def _G(s: float, medium: CameraMedium) -> float:  # pragma: no cover - numba
    """``∫_0^s α_u(x) dx`` of the unresolved ``medium`` (closed form, see the module docstring), ignoring its layer."""
    n0, lam, a, b, k = medium.n0, medium.lam, medium.d_min, medium.d_max, medium.k
    big_r, alpha_total = medium.max_distance, medium.alpha_total
    if s <= 0.0 or n0 == 0.0:
        return 0.0
    g = 0.0
    sr = min(s, big_r)
    if k > 0.0 and sr > 0.0:
        y = k * sr
        if y > a:
            m = min(y, b)
            m2 = _prim(2, a, lam) - _prim(2, m, lam)
            m3 = _prim(3, a, lam) - _prim(3, m, lam)
            g = Q_IMAGING * math.pi / 4.0 * n0 / k * (y * m2 - m3)
    if s > big_r:
        g += alpha_total * (s - big_r)
    return g


@njit(cache=True, nogil=True)
def _compose_kernel(scene: PixelScene, rays: PixelRays, medium: CameraMedium, out: NDArray,
                    trans_out: NDArray) -> None:  # pragma: no cover
    """Per pixel of ``scene``: what it sees through the unresolved ``medium`` (layer-clipped optical depth on the
    pixel-centre ray of ``rays``), mixed with the particle radiance by the fraction of samples that met a particle;
    radiance ``out`` (N, 3), transmittance ``trans_out`` (N,)."""
    J, behind, ray_len, counts, s = scene.J, scene.behind, scene.ray_len, scene.counts, scene.samples
    L, sky_distance = scene.radiance, scene.sky_distance
    R, origin_z, width = rays.R, rays.origin_z, rays.width
    fx, fy, cx, cy = rays.fx, rays.fy, rays.cx, rays.cy
    z_min, z_max = medium.z_min, medium.z_max
    for pix in range(J.shape[0]):
        row = pix // width
        col = pix - row * width
        x = (col - cx) / fx
        y = (row - cy) / fy
        inv = 1.0 / math.sqrt(x * x + y * y + 1.0)
        dz = (R[2, 0] * x + R[2, 1] * y + R[2, 2]) * inv
        length = ray_len[pix]
        sky = not math.isfinite(length)
        if sky:
            length = sky_distance
        if dz == 0.0:
            s_a, s_b = (0.0, length) if z_min <= origin_z <= z_max else (0.0, 0.0)
        else:
            t1 = (z_min - origin_z) / dz
            t2 = (z_max - origin_z) / dz
            s_a = max(0.0, min(t1, t2))
            s_b = min(length, max(t1, t2))
        tau = 0.0
        if s_b > s_a:
            tau = _G(s_b, medium) - _G(s_a, medium)
        trans = math.exp(-tau)
        veil = -math.expm1(-tau)
        trans_out[pix] = trans
        f_hit = counts[pix] / s
        f_scene = (s - counts[pix]) / s
        for ch in range(3):
            jb = behind[pix, ch] if sky else J[pix, ch]
            scene = jb * trans + L[ch] * veil
            out[pix, ch] = scene * f_scene + L[ch] * f_hit


# ------------------------------------------------------------------------------------------------------------ particles
@dataclass(frozen=True, eq=False)
class ResolvedParticles:
    """The particles a camera resolves at a frame (`resolved_particles`).

    Attributes:
        particles: the field's `Particles` (world positions at ``t``, diameters, ids).
        velocities: (N, 3) world velocities [m/s] during the exposure.
        materialized: particles the slab queries returned (before the per-particle resolution test).
    """

    particles: Particles
    velocities: F64
    materialized: int

    def __len__(self) -> int:
        return len(self.particles)


def _pose(T_world_cam: NDArray, who: str) -> tuple[F64, F64]:
    T = np.asarray(T_world_cam, dtype=np.float64)
    ok = T.shape == (4, 4) and bool(np.all(np.isfinite(T)))
    if ok:
        R = T[:3, :3]
        ok = (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1.0) < 1e-6
              and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]))
    if not ok:
        raise ValueError(f"{who}: T_world_cam must be a (4, 4) camera-to-world rigid transform (rotation, "
                         f"translation, last row 0 0 0 1), got {T_world_cam!r}")
    return np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])


def _vec3(who: str, name: str, value: NDArray, unit: str) -> F64:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"{who}: {name} = {value!r} is invalid: expected 3 finite numbers [{unit}]")
    return v


def _slab_edges(near: float, z_end: float, lam_k: float) -> list[float]:
    """z-depth slab boundaries from ``near`` to ``z_end``: 1/4 of the depth near the camera (at least 0.25 m), at
    most ``0.3 / (λ k)`` (so the slab's own ``min_diameter`` lets through at most ~35 % more particles than the
    per-particle threshold at its far end)."""
    cap = 0.3 / lam_k if lam_k > 0.0 else np.inf
    edges = [near]
    while edges[-1] < z_end:
        z = edges[-1]
        edges.append(min(z_end, z + max(0.25, min(0.25 * z, cap))))
    return edges


def resolved_particles(field: ParticleField, K: NDArray, T_world_cam: NDArray, width: int, height: int, t: float, *,
                       v_cam: NDArray = (0.0, 0.0, 0.0), exposure_s: float = 0.006, resolve_px: float = 0.25,
                       max_distance: float = 100.0, near_clip: float = NEAR_CLIP,
                       per_diameter_fall: bool = False) -> ResolvedParticles:
    """The particles of ``field`` a camera traces at time ``t``: those with ``D >= resolve_px r / f`` and
    ``r <= max_distance`` (``r`` their distance from the camera centre at ``t``) whose sphere can reach the view
    frustum during the exposure, with z-depth >= ``near_clip`` at ``t``, and their velocities.

    Materialised in z-depth slabs (each with ``min_diameter = resolve_px z / f``, a world box around the slab
    widened by the largest motion during the exposure and the largest radius); a particle belongs to the slab that
    holds its z-depth, so none is listed twice. Arguments as `particle_image`.
    """
    who = "resolved_particles"
    if not isinstance(field, ParticleField):
        raise ValueError(f"{who}: field = {field!r} is invalid: expected a weatheralign.medium.field.ParticleField")
    fx, fy, cx, cy = _intrinsics(K, who)
    R, o = _pose(T_world_cam, who)
    t = float(t)
    if not math.isfinite(t):
        raise ValueError(f"{who}: t = {t!r} [s] is invalid: expected a finite time")
    v_cam = _vec3(who, "v_cam", v_cam, "m/s")
    exposure = _nonneg(who, "exposure_s", exposure_s, "s")
    resolve = _nonneg(who, "resolve_px", resolve_px, "px", positive=True)
    big_r = _nonneg(who, "max_distance", max_distance, "m")
    near = _nonneg(who, "near_clip", near_clip, "m", positive=True)
    spec = field.spectrum
    k = resolve / max(fx, fy)
    wind = field.velocity_array.copy()
    if per_diameter_fall:
        wind[2] = 0.0
        v_max = float(np.linalg.norm(wind + np.array([0.0, 0.0, float(rain_terminal_velocity(spec.d_max))])))
    else:
        v_max = float(np.linalg.norm(wind))
    margin = (v_max + float(np.linalg.norm(v_cam))) * 0.5 * exposure + 0.5 * spec.d_max + 1e-6
    z_end = min(big_r, spec.d_max / k)
    empty = Particles(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), t, k * near)
    if spec.n0 == 0.0 or z_end <= near:
        return ResolvedParticles(empty, np.zeros((0, 3)), 0)
    edges = _slab_edges(near, z_end, spec.lam * k)
    # frustum corners (image border) on the plane z = 1 of the camera frame
    xs = np.array([(-0.5 - cx) / fx, (width - 0.5 - cx) / fx])
    ys = np.array([(-0.5 - cy) / fy, (height - 0.5 - cy) / fy])
    unit_corners = np.array([[x, y, 1.0] for x in xs for y in ys])
    parts: list[Particles] = []
    materialized = 0
    for i in range(len(edges) - 1):
        z0, z1 = edges[i], edges[i + 1]
        zs = np.array([max(z0 - margin, 0.0), z1 + margin])
        corners = (unit_corners[None, :, :] * zs[:, None, None]).reshape(-1, 3) @ R.T + o
        lo, hi = corners.min(0) - margin, corners.max(0) + margin
        if hi[2] < field.z_min or lo[2] > field.z_max:
            continue
        p = field.materialize(lo, hi, t, min_diameter=k * z0)
        materialized += len(p)
        if len(p) == 0:
            continue
        zc = (p.positions - o) @ R[:, 2]
        last = i == len(edges) - 2
        own = (zc >= z0) & ((zc <= z1) if last else (zc < z1))
        parts.append(p.select(own))
    if not parts:
        return ResolvedParticles(empty, np.zeros((0, 3)), materialized)
    pos = np.concatenate([p.positions for p in parts])
    dia = np.concatenate([p.diameters for p in parts])
    ids = np.concatenate([p.ids for p in parts])
    r = np.linalg.norm(pos - o, axis=1)
    keep = (dia >= k * r) & (r <= big_r)
    pos, dia, ids = pos[keep], dia[keep], ids[keep]
    order = np.argsort(ids, kind="stable")
    pos, dia, ids = pos[order], dia[order], ids[order]
    vel = np.tile(field.velocity_array, (len(ids), 1))
    if per_diameter_fall:
        vel[:, 2] = -rain_terminal_velocity(dia)
    return ResolvedParticles(Particles(pos, dia, ids, t, k * near), vel, materialized)


# ------------------------------------------------------------------------------------------------------------ image
def _clear_radiance(J: NDArray, shape: tuple[int, int], who: str) -> F64:
    """``J`` as an (H, W, 3) float64 array of finite linear radiances, ``shape`` (H, W) the ray lengths'."""
    Jl = np.asarray(J, dtype=np.float64)
    if Jl.shape != (*shape, 3) or not np.isfinite(Jl).all():
        raise ValueError(f"{who}: J must be an (H, W, 3) array of finite linear radiances matching ray_length "
                         f"{shape}, got shape {Jl.shape}")
    return Jl


def _radiance_behind_sky(sky_radiance_behind: NDArray | None, J: F64, who: str) -> F64:
    """(H, W, 3) the clear radiance behind each sky pixel's path: ``J`` (H, W, 3) when ``sky_radiance_behind`` is
    None, else that (3,) or (H, W, 3) linear radiance."""
    if sky_radiance_behind is None:
        return J
    height, width = J.shape[:2]
    b = np.asarray(sky_radiance_behind, dtype=np.float64)
    if b.shape not in ((3,), (height, width, 3)) or not np.isfinite(b).all():
        raise ValueError(f"{who}: sky_radiance_behind must be None, (3,) or (H, W, 3) = {(height, width, 3)} "
                         f"finite linear radiance, got shape {b.shape}")
    return np.broadcast_to(b, (height, width, 3))


def _frame_time(t: float, who: str) -> float:
    """``t`` [s] as a finite float."""
    try:
        t = float(t)
    except (TypeError, ValueError):
        t = math.nan
    if not math.isfinite(t):
        raise ValueError(f"{who}: t is invalid: expected a finite frame time [s]")
    return t


@dataclass(frozen=True, eq=False)
class ParticleImage:
    """A camera image through snow or rain (`particle_image`).

    Attributes:
        radiance: (H, W, 3) float64 linear radiance.
        coverage: (H, W) float32 fraction of each pixel's samples that met a resolved particle.
        nearest_hit: (H, W) float32 nearest particle distance [m] met by any of the pixel's samples (``inf``: none).
        transmittance: (H, W) float32 transmittance ``e^{-τ}`` of the unresolved medium along the pixel's ray to the
            scene (sky: over ``sky_distance``).
        resolved: resolved particles whose swept sphere reaches the image (traced).
        particles_hit: particles met by at least one sample in front of the scene.
        hit_samples: samples that met a particle (of ``H W S``).
        materialized: particles the field's slab queries returned.
        samples: samples per pixel S.
    """

    radiance: F64
    coverage: F32
    nearest_hit: F32
    transmittance: F32
    resolved: int
    particles_hit: int
    hit_samples: int
    materialized: int
    samples: int


def particle_image(J: NDArray, ray_length: NDArray, K: NDArray, T_world_cam: NDArray, t: float, field: ParticleField,
                   particle_radiance: NDArray, *, v_cam: NDArray = (0.0, 0.0, 0.0), exposure_s: float = 0.006,
                   samples: int = 16, resolve_px: float = 0.25, max_distance: float = 100.0,
                   sky_distance: float = SKY_DISTANCE, sky_radiance_behind: NDArray | None = None,
                   per_diameter_fall: bool = False, near_clip: float = NEAR_CLIP, seed: int = 0) -> ParticleImage:
    """The exact camera image of a frame through the particles of ``field`` (see the module docstring).

    Args:
        J: (H, W, 3) clear linear radiance of each pixel (the sky's at sky pixels).
        ray_length: (H, W) distance [m] along each pixel's ray to the scene, ``inf`` for sky.
        K: (3, 3) pinhole intrinsics (no skew; pixel centres at integer coordinates).
        T_world_cam: (4, 4) camera-to-world pose at ``t`` (OpenCV optical axes: x right, y down, z forward).
        t: frame time [s] (the middle of the exposure).
        field: the snow or rain `ParticleField`.
        particle_radiance: (3,) linear radiance ``L`` of a particle (and of the unresolved medium's veil).
        v_cam: (3,) linear ego velocity [m/s] in the world frame during the exposure.
        exposure_s: exposure time T_e [s] (>= 0), ``[t - T_e/2, t + T_e/2]``.
        samples: samples per pixel S (1..1024).
        resolve_px: particles whose image diameter ``f D / r`` is below this [px] are the unresolved medium (> 0).
        max_distance: particles farther than this [m] are the unresolved medium (>= 0).
        sky_distance: length [m] of a sky pixel's path through the medium (> 0).
        sky_radiance_behind: the clear radiance behind a sky pixel's path: None (``J``), (3,) or (H, W, 3) linear.
        per_diameter_fall: each particle falls at ``rain_terminal_velocity(D)`` (plus the field's horizontal wind)
            during the exposure instead of moving with the field's velocity (rain).
        near_clip: particles nearer than this z-depth [m] during the exposure are ignored (> 0).
        seed: seed of the sample pattern (`sample_pattern`).

    Raises:
        ValueError: a bad argument (the message names it and the expected form).
    """
    who = "particle_image"
    ell = _ray_lengths(ray_length, who)
    height, width = ell.shape
    Jl = _clear_radiance(J, ell.shape, who)
    fx, fy, cx, cy = _intrinsics(K, who)
    R, o = _pose(T_world_cam, who)
    if not isinstance(field, ParticleField):
        raise ValueError(f"{who}: field = {field!r} is invalid: expected a weatheralign.medium.field.ParticleField")
    L = np.ascontiguousarray(_vec3(who, "particle_radiance", particle_radiance, "linear RGB"))
    if (L < 0.0).any():
        raise ValueError(f"{who}: particle_radiance = {particle_radiance!r} is invalid: expected 3 linear radiances "
                         ">= 0")
    sky_d = _nonneg(who, "sky_distance", sky_distance, "m", positive=True)
    behind = _radiance_behind_sky(sky_radiance_behind, Jl, who)
    s = _check_samples(samples, who)
    seed = _check_seed(seed, who)
    exposure = _nonneg(who, "exposure_s", exposure_s, "s")
    resolve = _nonneg(who, "resolve_px", resolve_px, "px", positive=True)
    big_r = _nonneg(who, "max_distance", max_distance, "m")
    near = _nonneg(who, "near_clip", near_clip, "m", positive=True)
    v_cam = _vec3(who, "v_cam", v_cam, "m/s")
    t = _frame_time(t, who)

    res = resolved_particles(field, K, T_world_cam, width, height, t, v_cam=v_cam, exposure_s=exposure,
                             resolve_px=resolve, max_distance=big_r, near_clip=near,
                             per_diameter_fall=bool(per_diameter_fall))
    p = res.particles
    centers = (p.positions - o) @ R
    rel = (res.velocities - v_cam) @ R
    hits = trace_particles(centers, rel, p.diameters, K, ell, exposure_s=exposure, samples=s, seed=seed,
                           near_clip=near)
    found = np.isfinite(hits.depth)
    counts = np.count_nonzero(found, axis=2)
    nearest = hits.depth.min(axis=2).astype(np.float32)

    med = UnresolvedMedium.of(field, resolve, max(fx, fy), big_r)
    out = np.empty((height * width, 3))
    trans = np.empty(height * width)
    scene = PixelScene(np.ascontiguousarray(Jl.reshape(-1, 3)), np.ascontiguousarray(behind.reshape(-1, 3)),
                       np.ascontiguousarray(ell.ravel()), np.ascontiguousarray(counts.ravel().astype(np.int64)), s, L,
                       sky_d)
    _compose_kernel(scene, PixelRays(R, float(o[2]), fx, fy, cx, cy, width), med.record(), out, trans)
    return ParticleImage(radiance=out.reshape(height, width, 3), coverage=(counts / s).astype(np.float32),
                         nearest_hit=nearest, transmittance=trans.reshape(height, width).astype(np.float32),
                         resolved=hits.traced, particles_hit=hits.particles_hit, hit_samples=int(counts.sum()),
                         materialized=res.materialized, samples=s)
