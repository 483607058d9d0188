"""The synthetic reference's snow and rain are one medium for both sensors: the particles its exact LiDAR process
reports are the particles its exact camera process images (and those of an independent field are not), and the
rendered snow / rain splits react to the hidden rate as the physics says.
"""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.config import params_from_dict
from weatheralign.geometry import camera_rotation_from_yaw, make_transform
from weatheralign.medium.distributions import SnowSizeDistribution
from weatheralign.medium.field import ParticleField
from weatheralign.reference.camera_particles_exact import particle_image
from weatheralign.reference.lidar_exact import FOG, TARGET, ExactSensor
from weatheralign.reference.lidar_particles_exact import PARTICLE, particle_returns
from weatheralign.reference.synthetic import (
    draw_precipitation_truth,
    frame_field,
    frame_medium,
    frame_specs,
    render_frame,
)

LIDAR_ORIGIN = np.array([0.0, 0.0, 1.95])
T_WORLD_CAM = make_transform(camera_rotation_from_yaw(0.0), np.array([0.7, 0.0, 1.25]))
F_PX, WIDTH, HEIGHT = 1500.0, 640, 400
K = np.array([[F_PX, 0.0, WIDTH / 2.0], [0.0, F_PX, HEIGHT / 2.0], [0.0, 0.0, 1.0]])


def _snow(seed: int) -> ParticleField:
    return ParticleField(seed=seed, distribution=SnowSizeDistribution(4.0, 1.5), velocity=(0.0, 0.0, -1.5),
                         cell_size=2.0)


def _forward_beams() -> np.ndarray:
    """64 x 400 beams within the camera's view (±12° azimuth, -7..+7° elevation), no targets."""
    az, el = np.meshgrid(np.deg2rad(np.linspace(-12, 12, 400)), np.deg2rad(np.linspace(-7, 7, 64)))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)


def _lidar_particles(field: ParticleField) -> np.ndarray:
    """Ids of the particles whose echo is the strongest return of some beam."""
    dirs = _forward_beams()
    n = len(dirs)
    res = particle_returns(LIDAR_ORIGIN, dirs, np.full(n, np.inf), np.zeros(n), field, 0.0, 0.9, ExactSensor(),
                           noise_floor=1.0, sub_rays=32)
    ids = res.particle_id[res.returns.source == PARTICLE]
    return np.unique(ids[ids >= 0])


def _seen_fraction(ids: np.ndarray, lidar_field: ParticleField, camera_field: ParticleField) -> tuple[float, int]:
    """Share of the LiDAR's particles (in view, beyond 1 m, imaged at least 1.5 px wide) whose centre pixel the
    camera's particles cover at least a quarter of (a disc 1.5 px wide covers >= 0.3 of the pixel holding its
    centre)."""
    J = np.full((HEIGHT, WIDTH, 3), 0.2)
    img = particle_image(J, np.full((HEIGHT, WIDTH), np.inf), K, T_WORLD_CAM, 0.0, camera_field, np.full(3, 0.9),
                         exposure_s=0.0, samples=16)
    pos = lidar_field.positions_at(ids, 0.0)
    cells = np.unique(lidar_field.cell_indices(pos, 0.0), axis=0)  # the cells holding the LiDAR's particles
    held = lidar_field.materialize_cells(cells, 0.0, min_diameter=5e-4)
    diameter = dict(zip(held.ids.tolist(), held.diameters.tolist()))
    pc = (pos - T_WORLD_CAM[:3, 3]) @ T_WORLD_CAM[:3, :3]
    u = F_PX * pc[:, 0] / pc[:, 2] + WIDTH / 2.0
    v = F_PX * pc[:, 1] / pc[:, 2] + HEIGHT / 2.0
    dist = np.linalg.norm(pc, axis=1)
    d = np.array([diameter.get(i, 0.0) for i in ids.tolist()])
    ok = (pc[:, 2] > 1.0) & (u >= 1) & (u < WIDTH - 2) & (v >= 1) & (v < HEIGHT - 2) & (F_PX * d / dist >= 1.5)
    seen = img.coverage[np.round(v[ok]).astype(int), np.round(u[ok]).astype(int)] >= 0.25
    return float(np.mean(seen)), int(ok.sum())


def test_the_lidar_and_the_camera_see_the_same_particles():
    lidar_field = _snow(7)
    ids = _lidar_particles(lidar_field)
    aligned, n = _seen_fraction(ids, lidar_field, lidar_field)
    independent, _ = _seen_fraction(ids, lidar_field, _snow(8))
    assert n >= 50
    assert aligned >= 0.95  # every LiDAR echo is a flake the camera images (occlusion by nearer flakes still covers)
    assert independent <= 0.3  # another field of the same statistics does not line up


@pytest.fixture(scope="module")
def weather_params(tmp_path_factory):
    data = tmp_path_factory.mktemp("reference_weather")
    return params_from_dict({"paths": {"data": str(data)}, "tracking": {"enabled": False},
                             "reference": {"frames_per_split": 1, "lidar": {"firings_per_ring": 360},
                                           "camera": {"image_scale": 0.2}}})


def test_snow_and_rain_frames_react_to_the_rate(weather_params):
    cfg = weather_params.reference
    truth = draw_precipitation_truth(cfg)
    for level in ("snow", "rain"):
        spec = next(s for s in frame_specs(cfg) if s.level == level)
        field = frame_medium(spec, cfg)
        assert field == frame_field(spec, cfg) and field.t_ref == spec.time and field.number_density() > 0
        light = render_frame(spec, cfg, field)
        heavy_cfg = cfg.model_copy(update={"precipitation": cfg.precipitation.model_copy(
            update={f"{level}_rate_mm_h": (4.0 * truth[level], 4.0 * truth[level] + 1e-3)})})
        heavy = render_frame(spec, heavy_cfg, frame_field(spec, heavy_cfg))
        # more particles: more particle echoes, more of them near, and the image loses contrast to the veil
        assert heavy.stats["particle_returns"] > light.stats["particle_returns"] > 0
        assert heavy.stats["camera_particle_coverage"] > light.stats["camera_particle_coverage"] > 0
        np.testing.assert_array_equal(heavy.range, light.range)  # the same scene
        near = lambda f: int((np.linalg.norm(f.points[:, :3], axis=1) < 10.0).sum())  # noqa: E731
        assert near(heavy) > near(light)


def _hdl64_beams(columns: int) -> np.ndarray:
    from weatheralign.data.rings import HDL64E_ELEVATIONS_DEG

    el, az = np.meshgrid(np.deg2rad(np.asarray(HDL64E_ELEVATIONS_DEG)),
                         np.linspace(-np.pi, np.pi, columns, endpoint=False))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)


@pytest.mark.parametrize("noisy", [False, True], ids=["noise-free", "reference-detector-noise"])
@pytest.mark.parametrize("kind, rate, reflectivity", [("snow", 3.0, 0.9), ("rain", 80.0, 0.02)])
def test_fast_simulator_agrees_with_the_exact_process(kind, rate, reflectivity, noisy):
    """The fast LiDAR particle simulator (disk overlaps, closed-form pulse maxima, size thresholds by coverage, the
    unresolved particles' continuum) and the reference's exact process (Monte-Carlo sub-rays, waveform on a grid)
    see the same field through the same sensor: their weather echoes (particles, and the unresolved particles'
    continuum where it is the strongest peak) agree in number, range and on the open sky beams (HDL-64 grid over a
    flat ground, sky above), with a noise-free detector and with the reference's (0.5 + 3 % intensity noise, 1 cm
    range noise), whose noise lifts weak echoes over the floor. Measured (exact vs fast weather echoes): noise-free
    snow 9561 vs 9955 (+4 %), rain 140 vs 139; with the noise snow 10,050 vs 10,230 (+1.8 %), rain 527 vs 542 (80
    vs 109 of them the continuum's; on the sky beams 342 vs 357). Without the continuum the fast simulator gives
    rain 436 echoes, 252 on the sky, where the exact process's continuum (its peak 4 m out, intensity 0.009) hides
    faint far drops from a strongest-return receiver but is itself lifted over the floor by the noise. The targets
    both keep: noise-free snow 44,674 vs 44,244, rain 48,480 vs 48,481; with the noise snow 44,628 vs 44,276, rain
    48,402 vs 48,401. Read with its strongest peak alone, the exact process would hide 962 (883 with the noise) of
    the rain's targets behind undetectable drop echoes, 158 (112) of the snow's."""
    from weatheralign.data.rings import HDL64E_ELEVATIONS_DEG
    from weatheralign.lidar.beams import Beams
    from weatheralign.lidar.labels import WeatherLabel
    from weatheralign.lidar.particles import simulate_particles
    from weatheralign.medium.distributions import RainSizeDistribution
    from weatheralign.reference.lidar_exact import Detector, read_out
    from weatheralign.sensors import SYNTHETIC_INTENSITY, LidarModel, PulseSensor

    columns = 900
    dirs = _hdl64_beams(columns)
    n = len(dirs)
    origin = np.array([0.0, 0.0, 1.95])
    down = dirs[:, 2] < -0.01
    r0 = np.where(down, 1.95 / np.maximum(-dirs[:, 2], 1e-9), np.inf)
    r0[r0 > 110.0] = np.inf
    has = np.isfinite(r0)
    i0 = np.where(has, 255.0 * 0.2 * np.minimum(1.0, 10.0 / np.where(has, r0, 1.0)), 0.0)
    dist = SnowSizeDistribution(rate, 1.5) if kind == "snow" else RainSizeDistribution(rate)
    field = ParticleField(seed=5, distribution=dist, velocity=(0.0, 0.0, -1.5),
                          cell_size=2.0 if kind == "snow" else 1.0)
    sensor = ExactSensor()
    exact = particle_returns(origin, dirs, r0, i0, field, 0.0, reflectivity, sensor, noise_floor=1.0, sub_rays=256)
    detector = Detector() if noisy else Detector(0.0, 0.0, 1.0, 0.0)
    out = read_out(exact.returns, sensor, detector, np.random.default_rng(0))
    lidar = LidarModel(elevations_deg=tuple(HDL64E_ELEVATIONS_DEG), columns_per_ring=columns, rotation_hz=10.0,
                       clockwise=True, start_azimuth_rad=np.pi, laser_step_s=0.0, divergence_rad=3e-3,
                       max_range_m=120.0, min_range_m=1.0, noise_floor=1.0, intensity_max=255.0,
                       intensity=SYNTHETIC_INTENSITY,
                       pulse=PulseSensor(tau_h=2e-8, r1=0.9, r2=1.0, max_range=120.0), origin="params",
                       intensity_noise_std=detector.intensity_noise_std,
                       intensity_noise_rel=detector.intensity_noise_rel, range_noise_std_m=detector.range_noise_std)
    beams = Beams(np.tile(origin, (n, 1)), dirs, np.zeros(n), np.where(has, r0, 120.0), has, i0,
                  np.zeros(n, np.float32), np.where(has, np.cumsum(has) - 1, -1), 3e-3, 120.0)
    fast = simulate_particles(beams, field, lidar=lidar, reflectivity=reflectivity, intensity_max=255.0)
    weather = (out.source == PARTICLE) | (out.source == FOG)  # FOG: the exact process's unresolved continuum
    n_exact = int(weather.sum())
    scattered = fast.labels == WeatherLabel.SCATTERED
    n_fast = int(scattered.sum())
    assert n_exact > (5000 if kind == "snow" else 80)
    assert abs(n_fast / n_exact - 1.0) < (0.08 if kind == "snow" else 0.15), (n_exact, n_fast)
    sky_exact = int((weather & ~has[out.index]).sum())
    sky_fast = int((scattered & (fast.source_index < 0)).sum())
    assert abs(sky_fast / sky_exact - 1.0) < (0.08 if kind == "snow" else 0.15), (sky_exact, sky_fast)
    r_exact = np.median(out.range[weather])
    r_fast = np.median(np.linalg.norm(fast.points[scattered, :3] - origin, axis=1))
    assert abs(r_fast / r_exact - 1.0) < 0.15, (r_exact, r_fast)
    # the targets both keep: a receiver reports the strongest *detected* echo, so an undetectable drop echo in front
    # of a target does not hide it (read with the strongest peak alone, the exact process would lose those)
    kept_exact = int((out.source == TARGET).sum())
    kept_fast = int(np.isin(fast.labels[fast.source_index >= 0],
                            (WeatherLabel.ATTENUATED, WeatherLabel.UNCHANGED)).sum())
    assert abs(kept_fast / kept_exact - 1.0) < (0.02 if kind == "snow" else 0.005), (kept_exact, kept_fast)
    first_only = read_out(type(exact.returns)(exact.returns.power, exact.returns.r_peak, exact.returns.source),
                          sensor, detector, np.random.default_rng(0))
    hidden = kept_exact - int((first_only.source == TARGET).sum())
    assert hidden > (50 if kind == "snow" else 500)  # rain: 2 % of the targets, four times the tolerance above


def test_the_ground_of_the_snow_and_rain_splits(weather_params):
    """The rain split's road is wet (ground returns dimmer, the weakest lost), the snow split's raised by the hidden
    depth and brighter; the camera changes on the ground, not in the sky."""
    from weatheralign.reference.ground import draw_ground_truth

    cfg = weather_params.reference
    bare_cfg = cfg.model_copy(update={"precipitation": cfg.precipitation.model_copy(update={"ground": False})})
    depth = draw_ground_truth(cfg)
    for level in ("rain", "snow"):
        spec = next(s for s in frame_specs(cfg) if s.level == level)
        field = frame_field(spec, cfg)
        grounded, bare = render_frame(spec, cfg, field), render_frame(spec, bare_cfg, field)
        low = lambda f: f.points[(f.points[:, 2] < -1.5) & (np.linalg.norm(f.points[:, :2], axis=1) < 25.0)]  # noqa: E731
        g, b = low(grounded), low(bare)
        if level == "rain":
            assert np.median(g[:, 3]) < 0.9 * np.median(b[:, 3])
            assert len(g) <= len(b)
        else:
            lift = np.median(g[:, 2]) - np.median(b[:, 2])
            assert abs(lift - depth["snow"]) < 0.3 * depth["snow"], (lift, depth["snow"])
            assert np.median(g[:, 3]) > 2.0 * np.median(b[:, 3])
        sky = np.isinf(grounded.range)
        change = np.abs(grounded.image.astype(int) - bare.image.astype(int)).max(axis=-1)
        # in the sky only the drops change, whose radiance is the mean of the scene they refract (the road's too)
        assert np.mean(change[~sky] > 8) > 0.1 and np.mean(change[sky] > 8) < 0.01, level
