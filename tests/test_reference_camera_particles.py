"""The synthetic reference's exact camera through snow and rain (`weatheralign.reference.camera_particles_exact`):
no particles is the identity, coverage is the projected disc's area (static and motion-blurred), the unresolved medium
is the closed form, the fast particle-major tracer equals a brute-force (every sample x every particle) numpy
reference, the frustum slabs miss no particle, determinism and argument errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from weatheralign.geometry import camera_rotation_from_yaw
from weatheralign.medium.distributions import (
    ExponentialSizeDistribution,
    RainSizeDistribution,
    SnowSizeDistribution,
    rain_terminal_velocity,
)
from weatheralign.medium.field import ParticleField
from weatheralign.reference.camera_particles_exact import (
    ParticleImage,
    UnresolvedMedium,
    particle_image,
    resolved_particles,
    sample_pattern,
    trace_particles,
)

CAM_HEIGHT = 1.25


def _pose(yaw: float = 0.0, height: float = CAM_HEIGHT) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = camera_rotation_from_yaw(yaw)
    T[:3, 3] = (0.0, 0.0, height)
    return T


def _K(f: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def _ground_scene(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat ground under a horizontal camera (sky above the horizon): clear radiance and ray length."""
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    n = np.sqrt(x * x + y * y + 1.0)
    ell = np.where(y > 0, CAM_HEIGHT * n / np.where(y > 0, y, 1.0), np.inf)
    J = np.where(np.isfinite(ell)[..., None], np.array([0.12, 0.11, 0.10]) * (1 + 0.3 * np.sin(u / 3.0))[..., None],
                 np.array([0.5, 0.6, 0.8]))
    return J, ell


def _disc_fractions(width: int, height: int, cu: float, cv: float, r: float, n: int = 1000) -> np.ndarray:
    """(H, W) exact-to-1e-5 fraction of each pixel's square inside the circle (midpoint rule over u of the chord)."""
    u = np.arange(width)[:, None] - 0.5 + (np.arange(n) + 0.5) / n  # (W, n)
    half = np.sqrt(np.maximum(r * r - (u - cu) ** 2, 0.0))
    rows = np.arange(height)[:, None, None]
    top = np.minimum(rows + 0.5, cv + half[None])
    bottom = np.maximum(rows - 0.5, cv - half[None])
    return np.clip(top - bottom, 0.0, None).mean(axis=2)


# ------------------------------------------------------------------------------------------------ 1. identity
def test_no_particles_is_the_clear_image_exactly() -> None:
    K = _K(60.0, 19.5, 14.2)
    J, ell = _ground_scene(K, 40, 30)
    empty = ParticleField(seed=3, distribution=ExponentialSizeDistribution(0.0, 500.0, 0.0, 0.02))
    assert empty.extinction() == 0.0
    img = particle_image(J, ell, K, _pose(), 0.0, empty, np.array([0.9, 0.9, 0.9]), v_cam=(10.0, 0.0, 0.0))
    assert isinstance(img, ParticleImage)
    assert img.radiance.dtype == np.float64 and img.radiance.shape == (30, 40, 3)
    assert np.array_equal(img.radiance, J)
    assert not img.coverage.any() and img.resolved == 0 and img.hit_samples == 0
    assert np.all(img.transmittance == 1.0) and np.all(np.isinf(img.nearest_hit))


# ------------------------------------------------------------------------------------------------ 2. static disc
def test_static_sphere_covers_its_projected_disc() -> None:
    f, cx, cy, width, height = 400.0, 31.3, 30.8, 64, 64
    z, rho = 5.0, 0.2
    r_px = f * rho / math.sqrt(z * z - rho * rho)  # image of a sphere on the axis: radius f tan(asin(rho / z))
    hits = trace_particles(np.array([[0.0, 0.0, z]]), np.zeros((1, 3)), np.array([2 * rho]), _K(f, cx, cy),
                           np.full((height, width), np.inf), exposure_s=0.0, samples=16, seed=5)
    cov = hits.coverage.astype(np.float64)
    exact = _disc_fractions(width, height, cx, cy, r_px)
    assert np.all(cov[exact == 1.0] == 1.0)  # pixels wholly inside: every sample
    assert np.all(cov[exact == 0.0] == 0.0)  # pixels wholly outside: none
    edge = (exact > 0.0) & (exact < 1.0)
    err = cov[edge] - exact[edge]
    assert np.abs(err).max() <= 0.5
    assert np.sqrt(np.mean(err ** 2)) < 0.08  # 4x4 jittered strata: an edge crosses a few of the 16
    assert cov.sum() == pytest.approx(math.pi * r_px ** 2, rel=0.01)
    assert exact.sum() == pytest.approx(math.pi * r_px ** 2, rel=1e-4)
    assert hits.traced == 1 and hits.particles_hit == 1
    # the hit distance is the sphere's near surface along each sample ray
    met = hits.depth[np.isfinite(hits.depth)]
    assert met.min() >= z - rho - 1e-12 and met.min() == pytest.approx(z - rho, abs=1e-4)
    assert met.max() <= math.sqrt(z * z - rho * rho) + 1e-12  # the tangent rays' length


# ------------------------------------------------------------------------------------------------ 3. motion blur
def _profile_variance(cov: np.ndarray) -> float:
    col = cov.astype(np.float64).sum(axis=0)
    x = np.arange(len(col))
    mean = (col * x).sum() / col.sum()
    return float((col * (x - mean) ** 2).sum() / col.sum())


def test_motion_blur_streak_length_and_energy() -> None:
    f, cx, cy, width, height = 400.0, 40.2, 20.7, 96, 48
    z, rho, speed, exposure = 5.0, 0.1, 40.0, 0.01
    K = _K(f, cx, cy)
    sky = np.full((height, width), np.inf)
    centre, diam = np.array([[0.0, 0.0, z]]), np.array([2 * rho])
    r_px = f * rho / math.sqrt(z * z - rho * rho)
    static = trace_particles(centre, np.zeros((1, 3)), diam, K, sky, exposure_s=exposure, samples=16, seed=1)
    moving = trace_particles(centre, np.array([[speed, 0.0, 0.0]]), diam, K, sky, exposure_s=exposure, samples=16,
                             seed=1)
    area = math.pi * r_px ** 2
    assert static.coverage.sum() == pytest.approx(area, rel=0.01)
    assert moving.coverage.sum() == pytest.approx(area, rel=0.02)  # energy: the same disc, spread over the streak
    assert moving.coverage.max() < 0.6  # every pixel sees it only part of the exposure
    streak = speed * exposure * f / z  # 32 px
    length = math.sqrt(12.0 * (_profile_variance(moving.coverage) - _profile_variance(static.coverage)))
    assert length == pytest.approx(streak, rel=0.03)
    cols = np.flatnonzero(moving.coverage.sum(axis=0) > 0)
    # the covered columns span the streak plus the disc (the end columns are met only a small part of the time)
    assert streak + 2 * r_px - 3.0 <= cols[-1] - cols[0] + 1 <= streak + 2 * r_px + 1.0
    rows = np.flatnonzero(moving.coverage.sum(axis=1) > 0)
    assert rows[-1] - rows[0] + 1 <= math.ceil(2 * r_px) + 1  # a horizontal motion does not widen it


# ------------------------------------------------------------------------------------------------ 4. medium
def _snow_field(rate: float = 4.0, **kw: float) -> ParticleField:
    return ParticleField(seed=21, distribution=SnowSizeDistribution(rate, 1.5), velocity=(0.0, 0.0, -1.5),
                         cell_size=2.0, z_min=-2.0, z_max=30.0, **kw)


def test_unresolved_medium_on_one_pixel_is_the_closed_form() -> None:
    field = _snow_field()
    alpha = field.extinction() / 2.0  # the camera keeps the diffracted half: geometric shadow only (Q_IMAGING = 1)
    J, L = np.array([[[0.2, 0.1, 0.05]]]), np.array([0.8, 0.82, 0.85])
    for ell in (0.0, 7.5, 50.0):
        img = particle_image(J, np.array([[ell]]), _K(100.0, 0.0, 0.0), _pose(), 0.0, field, L, max_distance=0.0)
        expected = J[0, 0] * math.exp(-alpha * ell) + L * (1.0 - math.exp(-alpha * ell))
        np.testing.assert_allclose(img.radiance[0, 0], expected, rtol=1e-12, atol=1e-15)
        assert img.resolved == 0 and img.materialized == 0
    # a sky ray 45° upwards leaves the layer (z_max = 30 m) after (30 - 1.25) √2 m; the sky is behind
    sky_behind = np.array([0.3, 0.4, 0.6])
    img = particle_image(J, np.array([[np.inf]]), _K(100.0, 0.0, 100.0), _pose(), 0.0, field, L, max_distance=0.0,
                         sky_radiance_behind=sky_behind)
    tr = math.exp(-alpha * (30.0 - CAM_HEIGHT) * math.sqrt(2.0))
    np.testing.assert_allclose(img.radiance[0, 0], sky_behind * tr + L * (1.0 - tr), rtol=1e-12)
    # a horizontal sky ray stays in the layer for sky_distance
    img = particle_image(J, np.array([[np.inf]]), _K(100.0, 0.0, 0.0), _pose(), 0.0, field, L, max_distance=0.0,
                         sky_distance=1234.0)
    assert img.transmittance[0, 0] == pytest.approx(math.exp(-alpha * 1234.0), rel=1e-6)


def test_range_dependent_threshold_integrates_the_field_extinction() -> None:
    field = ParticleField(seed=4, distribution=RainSizeDistribution(50.0), velocity=(0.0, 0.0, -4.0), cell_size=1.0)
    f, resolve, big_r = 1177.86, 0.25, 20.0
    med = UnresolvedMedium.of(field, resolve, f, big_r)
    k = resolve / f
    for s in (0.5, 3.0, 19.0, 60.0):
        direct, _ = quad(lambda x: 0.5 * (field.unresolved_extinction(k * x) if x <= big_r else field.extinction()),
                         0.0, s, points=[big_r] if s > big_r else None, limit=200, epsabs=0.0, epsrel=1e-11)
        assert float(med.optical_depth_to(s)) == pytest.approx(direct, rel=1e-8)
        assert med.alpha(min(s, big_r) * 0.999) == pytest.approx(
            0.5 * field.unresolved_extinction(k * min(s, big_r) * 0.999), rel=1e-10)
    # on an image: a pixel's transmittance is exp(-G(ℓ)) whatever the resolved particles do
    J = np.full((1, 1, 3), 0.2)
    img = particle_image(J, np.array([[15.0]]), _K(f, 0.0, 0.0), _pose(), 0.0, field, np.full(3, 0.5),
                         resolve_px=resolve, max_distance=big_r)
    assert img.transmittance[0, 0] == pytest.approx(math.exp(-float(med.optical_depth_to(15.0))), rel=1e-6)


# ------------------------------------------------------------------------------------------------ 5. brute force
def _brute_force_depth(centers: np.ndarray, vels: np.ndarray, diameters: np.ndarray, K: np.ndarray,
                       ell: np.ndarray, exposure: float, samples: int, seed: int,
                       near: float) -> tuple[np.ndarray, int]:
    """Every sample against every sphere, in numpy: nearest hit distance in front of the scene, inf otherwise."""
    height, width = ell.shape
    pat = sample_pattern(height, width, samples, seed)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rows, cols = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    u = (cols[..., None] - 0.5) + pat[..., 0]
    v = (rows[..., None] - 0.5) + pat[..., 1]
    dt = (pat[..., 2] - 0.5) * exposure
    dx = (u - cx) / fx
    dy = (v - cy) / fy
    n2 = dx * dx + dy * dy + 1.0
    scene = np.broadcast_to(ell[..., None], dx.shape)
    best = np.full(dx.shape, np.inf)
    hit_any = 0
    for c, w, d in zip(centers, vels, diameters):
        rho = 0.5 * d
        if min(c[2] - w[2] * 0.5 * exposure, c[2] + w[2] * 0.5 * exposure) - rho < near:
            continue
        px, py, pz = c[0] + w[0] * dt, c[1] + w[1] * dt, c[2] + w[2] * dt
        dc = dx * px + dy * py + pz
        cc = px * px + py * py + pz * pz - rho * rho
        disc = dc * dc - n2 * cc
        ok = (dc > 0.0) & (disc >= 0.0)
        dist = np.full(dx.shape, np.inf)
        dist[ok] = (dc[ok] - np.sqrt(disc[ok])) / np.sqrt(n2[ok])
        ok &= dist < scene
        hit_any += bool(ok.any())
        best = np.where(ok & (dist < best), dist, best)
    return best, hit_any


@pytest.mark.parametrize("samples,speed", [(16, 4.0), (6, 4.0), (16, 40.0), (5, 40.0)])
def test_fast_tracer_equals_brute_force(samples: int, speed: float) -> None:
    """Slow and fast particles (at 40 m/s most streaks are long and diagonal: the tracer cuts their exposure into
    parts with boxes of their own), jittered grid (16) and rooks (5, 6) patterns, sky and occluding scene pixels."""
    rng = np.random.default_rng(7)
    width, height, n = 24, 16, 400
    K = _K(30.0, 11.7, 7.4)
    z = rng.uniform(0.1, 8.0, n)
    centers = np.column_stack([rng.uniform(-0.5, 0.5, n) * z * 1.1, rng.uniform(-0.35, 0.35, n) * z * 1.1, z])
    vels = rng.normal(0.0, speed, (n, 3))
    diameters = rng.uniform(0.005, 0.25, n)
    ell = rng.uniform(1.0, 9.0, (height, width))
    ell[:5] = np.inf
    fast = trace_particles(centers, vels, diameters, K, ell, exposure_s=0.02, samples=samples, seed=9)
    slow, slow_hit = _brute_force_depth(centers, vels, diameters, K, ell, 0.02, samples, 9, 0.3)
    assert np.array_equal(fast.depth, slow)
    assert fast.particles_hit == slow_hit > 50
    assert 0.02 < np.isfinite(slow).mean() < 0.98
    assert fast.tests < height * width * samples * n / 5  # the pixel boxes skip most of the work


# ------------------------------------------------------------------------------------------------ slabs
@pytest.mark.parametrize("rain", [False, True])
def test_frustum_slabs_miss_no_particle(rain: bool) -> None:
    """particle_image's slab queries give exactly the image that tracing every particle of one big box gives."""
    width, height, f = 48, 32, 40.0
    K = _K(f, 23.6, 15.1)
    T = _pose(yaw=0.4)
    J, ell = _ground_scene(K, width, height)
    resolve, big_r, v_cam = 0.02, (4.0 if rain else 10.0), np.array([9.0, 4.0, 0.0])
    if rain:
        field = ParticleField(seed=8, distribution=RainSizeDistribution(10.0), velocity=(1.0, 0.5, -4.0),
                              cell_size=1.0)
    else:
        field = _snow_field(2.0, t_ref=-3.0)
    t, L = 0.25, np.array([0.7, 0.7, 0.75])
    img = particle_image(J, ell, K, T, t, field, L, v_cam=v_cam, exposure_s=0.01, resolve_px=resolve,
                         max_distance=big_r, per_diameter_fall=rain, seed=2)
    res = resolved_particles(field, K, T, width, height, t, v_cam=v_cam, exposure_s=0.01, resolve_px=resolve,
                             max_distance=big_r, per_diameter_fall=rain)
    # one box around everything within max_distance of the camera
    o, R = T[:3, 3], T[:3, :3]
    k = resolve / f
    everything = field.materialize(o - big_r - 1.0, o + big_r + 1.0, t, min_diameter=k * 0.3)
    r = np.linalg.norm(everything.positions - o, axis=1)
    keep = (everything.diameters >= k * r) & (r <= big_r)
    pos, dia = everything.positions[keep], everything.diameters[keep]
    vel = np.tile(field.velocity_array, (len(dia), 1))
    if rain:
        vel[:, 2] = -rain_terminal_velocity(dia)
    brute = trace_particles((pos - o) @ R, (vel - v_cam) @ R, dia, K, ell, exposure_s=0.01, samples=16, seed=2)
    assert np.array_equal(img.coverage, brute.coverage)
    assert np.array_equal(img.nearest_hit, brute.depth.min(axis=2).astype(np.float32))
    assert img.particles_hit == brute.particles_hit > 20
    assert set(res.particles.ids) <= set(everything.ids[keep])
    np.testing.assert_array_equal(res.velocities, np.tile(field.velocity_array, (len(res), 1)) if not rain else
                                  np.column_stack([np.tile(field.velocity_array[:2], (len(res), 1)),
                                                   -rain_terminal_velocity(res.particles.diameters)]))
    # each pixel: (1 - c) (J T + L (1 - T)) + c L, sky pixels included
    c = img.coverage.astype(np.float64)[..., None]
    tr = img.transmittance.astype(np.float64)[..., None]
    np.testing.assert_allclose(img.radiance, (1 - c) * (J * tr + L * (1 - tr)) + c * L, rtol=1e-6)


# ------------------------------------------------------------------------------------- 6. determinism, errors
def test_determinism_and_pattern_stratification() -> None:
    K = _K(300.0, 31.5, 23.5)
    J, ell = _ground_scene(K, 64, 48)
    field = ParticleField(seed=5, distribution=RainSizeDistribution(50.0), velocity=(0.0, 0.0, -4.0), cell_size=1.0)
    args = (J, ell, K, _pose(), 0.0, field, np.full(3, 0.5))
    a = particle_image(*args, v_cam=(8.0, 0.0, 0.0), per_diameter_fall=True, seed=11)
    b = particle_image(*args, v_cam=(8.0, 0.0, 0.0), per_diameter_fall=True, seed=11)
    c = particle_image(*args, v_cam=(8.0, 0.0, 0.0), per_diameter_fall=True, seed=12)
    assert a.hit_samples > 0
    assert a.radiance.tobytes() == b.radiance.tobytes() and a.coverage.tobytes() == b.coverage.tobytes()
    assert a.coverage.tobytes() != c.coverage.tobytes()
    assert a.resolved == c.resolved  # the seed moves the samples, not the particles
    pat = sample_pattern(3, 4, 16, 0)
    assert np.array_equal(pat, sample_pattern(3, 4, 16, 0)) and pat.min() >= 0.0 and pat.max() <= 1.0
    # one sample per 1/4 x 1/4 cell and per 1/16 of the exposure, in every pixel
    cells = np.floor(pat[..., 0] * 4) + 4 * np.floor(pat[..., 1] * 4)
    assert all(sorted(cells[i, j]) == list(range(16)) for i in range(3) for j in range(4))
    assert all(sorted(np.floor(pat[i, j, :, 2] * 16)) == list(range(16)) for i in range(3) for j in range(4))
    rooks = sample_pattern(2, 2, 6, 3)
    for axis in range(3):
        assert all(sorted(np.floor(rooks[i, j, :, axis] * 6)) == list(range(6)) for i in range(2) for j in range(2))


def test_bad_arguments_are_named() -> None:
    K = _K(100.0, 4.0, 3.0)
    J, ell = _ground_scene(K, 8, 6)
    field = _snow_field()
    L = np.full(3, 0.8)

    def call(**kw):
        args = dict(J=J, ray_length=ell, K=K, T_world_cam=_pose(), t=0.0, field=field, particle_radiance=L)
        args.update(kw)
        return particle_image(**args)

    cases = {
        "J": dict(J=J[..., :2]),
        "ray_length": dict(ray_length=np.where(ell > 3, np.nan, ell)),
        "K": dict(K=np.array([[100.0, 1.0, 4.0], [0.0, 100.0, 3.0], [0.0, 0.0, 1.0]])),
        "T_world_cam": dict(T_world_cam=2.0 * _pose()),
        "field": dict(field=SnowSizeDistribution(1.0, 1.5)),
        "particle_radiance": dict(particle_radiance=np.ones(4)),
        "samples": dict(samples=0),
        "exposure_s": dict(exposure_s=-0.001),
        "resolve_px": dict(resolve_px=0.0),
        "max_distance": dict(max_distance=np.inf),
        "sky_distance": dict(sky_distance=0.0),
        "sky_radiance_behind": dict(sky_radiance_behind=np.ones((2, 3))),
        "v_cam": dict(v_cam=(1.0, 2.0)),
        "seed": dict(seed=-1),
        "t is invalid": dict(t=float("nan")),
    }
    for name, kw in cases.items():
        with pytest.raises(ValueError, match=name):
            call(**kw)
    with pytest.raises(ValueError, match="ray_length"):
        call(ray_length=-ell)
    with pytest.raises(ValueError, match="diameters"):
        trace_particles(np.zeros((2, 3)), np.zeros((2, 3)), np.array([0.1, 0.0]), K, ell)
    with pytest.raises(ValueError, match="velocities"):
        trace_particles(np.zeros((2, 3)), np.zeros((3, 3)), np.array([0.1, 0.1]), K, ell)
    with pytest.raises(ValueError, match="samples"):
        sample_pattern(2, 2, 2000)
