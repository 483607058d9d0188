"""The frames of the fused-feature check (weatheralign.verify.frames): the media a clear reference frame is simulated
through (aligned vs unaligned, as `simulate` builds them) and the simulated pair on the shared real Seeing Through
Fog frame: one LiDAR for both copies, the cameras seeing the field or its twin, the particles re-projected onto the
pixels that drew them. Skips without ``../shared``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from weatheralign.camera.overcast import Overcast
from weatheralign.conditions import CONDITIONS
from weatheralign.config import ParticlesConfig, load_params
from weatheralign.reference import open_reference
from weatheralign.simulate.media import FogLevels, configured_precipitation_rates, resolve_overcast
from weatheralign.verify.frames import Severity, reference_fused_input, scene_media, simulated_pair

from .conftest import REPO, make_lidar

STF = REPO.parent / "shared" / "data" / "real" / "stf"
STF_ID = "2019-09-11_19-13-44_00960"
LEVELS = FogLevels({"light": 0.01, "dense": 0.05}, {"light": 0.001, "dense": 0.004}, "params")


def severity(snow: float = 2.0, rain: float = 50.0) -> Severity:
    return Severity(LEVELS, snow, rain, ParticlesConfig())


def test_fog_media_align_the_camera_with_the_lidar_or_draw_it_between_the_levels() -> None:
    for name in ("fog_light", "fog_dense"):
        level = CONDITIONS[name].fog.level
        aligned = scene_media(CONDITIONS[name], True, "rec_00001", severity(), seed=3)
        assert aligned.lidar_alpha == aligned.camera_alpha == LEVELS.alpha[level]
        assert aligned.lidar_beta == LEVELS.beta[level] and aligned.field is None
        cams = {scene_media(CONDITIONS[name], False, f"rec_{k:05d}", severity(), seed=3).camera_alpha
                for k in range(20)}
        assert len(cams) == 20 and all(0.01 <= a <= 0.05 for a in cams)
        unaligned = scene_media(CONDITIONS[name], False, "rec_00001", severity(), seed=3)
        assert unaligned.lidar_alpha == LEVELS.alpha[level]  # the LiDAR sees the condition's own fog either way
        assert unaligned.camera_alpha == scene_media(CONDITIONS[name], False, "rec_00001", severity(), 3).camera_alpha


def test_particle_media_take_the_severity_rate_and_a_field_per_frame() -> None:
    snow = scene_media(CONDITIONS["snow"], True, "rec_00001", severity(snow=3.5), seed=0)
    assert snow.field.rate_mm_h == 3.5 and snow.field.condition == "snow" and snow.lidar_alpha == 0.0
    other = scene_media(CONDITIONS["snow"], True, "rec_00002", severity(snow=3.5), seed=0)
    assert other.field.seed != snow.field.seed
    rain = scene_media(CONDITIONS["rain"], False, "rec_00001", severity(rain=20.0), seed=0)
    assert rain.field.rate_mm_h == 20.0 and not rain.aligned
    assert rain.field.field(True).seed != rain.field.field(False).seed  # the unaligned cameras see the twin
    mixed = scene_media(CONDITIONS["fog_snow"], True, "rec_00001", severity(), seed=0)
    assert mixed.field is not None and mixed.lidar_alpha == LEVELS.alpha["light"]


def test_snow_and_rain_media_fall_under_the_severity_overcast_and_fog_under_the_clear_day() -> None:
    light = {"snow": Overcast(0.3, 2.4, 0.9).to_dict(), "rain": Overcast(0.2, 2.2, 0.8).to_dict()}
    lit = replace(severity(), overcast=light)
    for name, split in (("snow", "snow"), ("rain", "rain"), ("fog_snow", "snow")):
        for aligned in (True, False):  # the day's light: the unaligned cameras see it too
            assert scene_media(CONDITIONS[name], aligned, "rec_00001", lit, seed=0).overcast == Overcast(**light[split])
        assert scene_media(CONDITIONS[name], True, "rec_00001", severity(), seed=0).overcast is None
    assert scene_media(CONDITIONS["fog_dense"], True, "rec_00001", lit, seed=0).overcast is None


def test_verify_severity_takes_the_overcast_simulate_resolves(tmp_path) -> None:
    from flows.verify import severity_of  # the flow module: Prefect and torch on import

    params = load_params(REPO / "params.yaml", [f"paths.data={tmp_path}", "simulate.precipitation_rates=params",
                                                "simulate.fog_levels=params"])
    severity_on, _ = severity_of(params)
    rates = configured_precipitation_rates(params.simulate, params.particles, tmp_path)
    assert severity_on.overcast == {name: resolve_overcast(CONDITIONS[name], params.simulate, rates)
                                    for name in ("snow", "rain")}
    assert all(light is not None for light in severity_on.overcast.values())
    off = load_params(REPO / "params.yaml", [f"paths.data={tmp_path}", "simulate.precipitation_rates=params",
                                             "simulate.fog_levels=params", "simulate.overcast=false"])
    assert severity_of(off)[0].overcast == {}


@pytest.fixture(scope="module")
def stf_reference(tmp_path_factory: pytest.TempPathFactory):
    if not STF.exists():
        pytest.skip(f"real sample not available: {STF}")
    root = tmp_path_factory.mktemp("stf")
    (root / "clear.txt").write_text(f"{STF_ID.rsplit('_', 1)[0]},{STF_ID.rsplit('_', 1)[1]}\n")
    for name in ("calib_cam_stereo_left.json", "calib_tf_tree_full.json"):
        (root / name).write_bytes((STF / name).read_bytes())
    (root / "lidar_hdl64_strongest").mkdir()
    (root / "cam_stereo_left_lut").mkdir()
    (root / "lidar_hdl64_strongest" / f"{STF_ID}.bin").write_bytes(
        (STF / f"lidar_hdl64_strongest_{STF_ID}.bin").read_bytes())
    (root / "cam_stereo_left_lut" / f"{STF_ID}.png").write_bytes(
        (STF / f"cam_stereo_left_lut_{STF_ID}.png").read_bytes())
    return open_reference(root, {"clear": "clear.txt"}, intensity_max=255.0)


@pytest.mark.parametrize("condition", ["snow", "rain", "fog_dense"])
def test_simulated_pair_on_a_real_frame(stf_reference, condition: str) -> None:
    ds = stf_reference
    lidar = make_lidar(noise_floor=1.0)
    pair = simulated_pair(ds, STF_ID, CONDITIONS[condition], severity(), lidar, 0.006, (64, 120), seed=0)
    clear = reference_fused_input(ds, STF_ID, (64, 120))
    assert pair.aligned.shape == pair.unaligned.shape == clear.shape == (6, 64, 120)
    assert np.array_equal(pair.aligned[3:], pair.unaligned[3:])  # one LiDAR scan for both copies
    assert not np.array_equal(pair.aligned[:3], pair.unaligned[:3])  # the cameras see other media
    assert not np.array_equal(pair.aligned[:3], clear[:3]) and not np.array_equal(pair.aligned[3:], clear[3:])
    assert pair.image.shape == (*pair.range_map.shape, 3) and pair.image.dtype == np.uint8
    assert pair.intensity_counts.shape == (256,)
    assert pair.intensity_counts.sum() == sum(v for k, v in pair.counts.items() if k != "LOST")
    if condition == "fog_dense":
        assert len(pair.reprojection_px) == 0
    else:
        assert pair.counts["SCATTERED"] + pair.counts["CLUTTER"] > 0
        assert len(pair.reprojection_px) > 0 or condition == "rain"  # few drops echo, fewer inside the camera's view
        assert pair.reprojection_px.max(initial=0.0) < 0.05  # [px]
    again = simulated_pair(ds, STF_ID, CONDITIONS[condition], severity(), lidar, 0.006, (64, 120), seed=0)
    assert np.array_equal(again.aligned, pair.aligned) and np.array_equal(again.unaligned, pair.unaligned)
    assert pair.unaligned_positions is None  # no rate spread: the unaligned camera already is the positions-only one


def test_unaligned_particles_misalign_rate_and_positions_and_keep_the_positions_only_variant(stf_reference) -> None:
    spread = replace(severity(snow=2.0), unaligned_rate_factor=3.0)
    media = scene_media(CONDITIONS["snow"], False, STF_ID, spread, seed=0)
    assert media.field.rate_mm_h == 2.0 and 2.0 / 3.0 <= media.camera_rate_mm_h <= 6.0
    assert media.camera_rate_mm_h != 2.0
    twin = media.camera_field()
    assert twin.seed != media.field.field().seed
    assert twin.distribution.snowfall_rate == pytest.approx(media.camera_rate_mm_h)
    pair = simulated_pair(stf_reference, STF_ID, CONDITIONS["snow"], spread, make_lidar(noise_floor=1.0), 0.006,
                          (64, 120), seed=0)
    assert pair.unaligned_positions is not None and pair.unaligned_positions.shape == pair.unaligned.shape
    assert np.array_equal(pair.unaligned_positions[3:], pair.aligned[3:])
    assert not np.array_equal(pair.unaligned_positions[:3], pair.unaligned[:3])
    same_rate = simulated_pair(stf_reference, STF_ID, CONDITIONS["snow"], severity(snow=2.0),
                               make_lidar(noise_floor=1.0), 0.006, (64, 120), seed=0)
    assert np.array_equal(pair.unaligned_positions, same_rate.unaligned)  # the old definition, exactly


def test_displaced_particle_channels_move_only_the_particle_echoes(stf_reference) -> None:
    from weatheralign.camera.fog import estimate_airlight
    from weatheralign.lidar.clutter import isolated_mask
    from weatheralign.reference.frames import reference_frame
    from weatheralign.sensors import CameraModel, SensorRig
    from weatheralign.simulate.observe import observe
    from weatheralign.verify.frames import displaced_particle_channels, frame_fused_input

    ds = stf_reference
    frame, image, depth = reference_frame(ds, STF_ID)
    step = 2 * np.pi / 1800
    assert displaced_particle_channels(frame, frame.lidar.points, 255.0, (64, 120), step, seed=0) is None  # clear
    view = frame.cameras["cam_stereo_left"]
    rig = SensorRig(lidar=make_lidar(noise_floor=1.0), cameras={"cam_stereo_left": CameraModel(
        "cam_stereo_left", tuple(tuple(r) for r in view.K), view.width, view.height, 0.006)})
    media = scene_media(CONDITIONS["snow"], True, STF_ID, severity(snow=3.0), seed=0)
    snow = observe(frame, {"cam_stereo_left": image}, {"cam_stereo_left": depth}, media, rig,
                   estimate_airlight([image], [depth])).lidar.scan.points
    moved = displaced_particle_channels(frame, snow, 255.0, (64, 120), step, seed=0)
    true = frame_fused_input(frame, image, snow, 255.0, (64, 120))[3:]
    assert moved is not None and moved.shape == true.shape
    changed = (moved != true).any(axis=0)
    keep = ~isolated_mask(snow[:, :3], azimuth_step_rad=step)
    scene_only = frame_fused_input(frame, image, snow[keep], 255.0, (64, 120))[3:]
    assert changed.sum() > 20
    # every cell that changed holds a particle echo before or after the move: the scene's own cells are untouched
    assert ((moved != scene_only).any(axis=0) | (true != scene_only).any(axis=0))[changed].all()
    again = displaced_particle_channels(frame, snow, 255.0, (64, 120), step, seed=0)
    assert np.array_equal(again, moved)


def test_ground_media_take_the_severity_depth_and_a_twin_for_unaligned_cameras() -> None:
    grounded = replace(severity(), ground_depth_m={"rain": 0.0004, "snow": 0.06}, unaligned_rate_factor=2.0)
    for name, kind, depth in (("rain", "wet", 0.0004), ("snow", "snow", 0.06), ("fog_snow", "snow", 0.06)):
        aligned = scene_media(CONDITIONS[name], True, "rec_00001", grounded, seed=0).ground
        assert aligned.kind == kind and aligned.amount_m == aligned.camera_amount_m == depth
        assert aligned.camera_seed == aligned.seed
        unaligned = scene_media(CONDITIONS[name], False, "rec_00001", grounded, seed=0).ground
        assert unaligned.amount_m == depth and unaligned.seed == aligned.seed  # the LiDAR's ground either way
        assert unaligned.camera_seed != aligned.seed and depth / 2 <= unaligned.camera_amount_m <= 2 * depth
        other = scene_media(CONDITIONS[name], True, "rec_00002", grounded, seed=0).ground
        assert other.seed != aligned.seed  # a field per frame
    assert scene_media(CONDITIONS["fog_dense"], True, "rec_00001", grounded, seed=0).ground is None
    assert scene_media(CONDITIONS["snow"], True, "rec_00001", severity(), seed=0).ground is None  # none given
