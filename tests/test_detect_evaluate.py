"""nuScenes detection metrics without the database: equal to the devkit's `accumulate` and official `DetectionEval`,
exact on perfect / shifted predictions, the range filter, and the frame bootstrap."""

from __future__ import annotations

import json
import math
from contextlib import redirect_stdout
from io import StringIO
from pathlib import Path

import numpy as np
import pytest
from nuscenes.eval.common.config import config_factory
from nuscenes.eval.common.data_classes import EvalBoxes
from nuscenes.eval.common.loaders import add_center_dist, load_gt_of_sample_tokens
from nuscenes.eval.common.utils import center_distance
from nuscenes.eval.detection import algo
from nuscenes.eval.detection.constants import TP_METRICS
from nuscenes.eval.detection.data_classes import DetectionBox
from nuscenes.eval.detection.evaluate import DetectionEval

from weatheralign.data.nuscenes import open_nuscenes
from weatheralign.detect.evaluate import (
    accumulate,
    bootstrap_intervals,
    ego_positions,
    ground_truth,
    paired_difference,
    paired_differences,
    predictions_to_eval_boxes,
    resample,
    resistance_ability,
    score,
)
from weatheralign.detect.types import ATTRIBUTES, DETECTION_CLASSES, SampleDetections
from weatheralign.geometry import invert, transform_from_quaternion, yaw_matrix

NO_TP = {"traffic_cone": {"attr_err", "vel_err", "orient_err"}, "barrier": {"attr_err", "vel_err"}}
CLASS_ATTR = {"car": "vehicle.parked", "truck": "vehicle.moving", "bus": "vehicle.stopped",
              "trailer": "vehicle.parked", "construction_vehicle": "vehicle.parked",
              "pedestrian": "pedestrian.standing", "motorcycle": "cycle.with_rider",
              "bicycle": "cycle.without_rider", "traffic_cone": "", "barrier": ""}


# --------------------------------------------------------------------------------------------------- helpers


def quat(yaw: float) -> tuple[float, float, float, float]:
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def box(token: str, name: str, x: float, y: float, *, yaw: float = 0.3, size=(1.9, 4.5, 1.6), vel=(1.0, -0.5),
        ego=(0.0, 0.0), score: float = -1.0, attr: str | None = None, num_pts: int = 10,
        z: float = 1.0) -> DetectionBox:
    """A global-frame box with ``ego_translation`` measured from the ego at ``ego`` (x, y) [m]."""
    return DetectionBox(sample_token=token, translation=(x, y, z), size=tuple(size), rotation=quat(yaw),
                        velocity=tuple(vel), ego_translation=(x - ego[0], y - ego[1], z), num_pts=num_pts,
                        detection_name=name, detection_score=score,
                        attribute_name=CLASS_ATTR[name] if attr is None else attr)


def boxes_of(mapping: dict[str, list[DetectionBox]]) -> EvalBoxes:
    out = EvalBoxes()
    for token, bs in mapping.items():
        out.add_boxes(token, bs)
    return out


def yaw_of(b: DetectionBox) -> float:
    w, x, y, z = np.asarray(b.rotation) / np.linalg.norm(b.rotation)
    return math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def to_lidar(gt: EvalBoxes, T_global_lidar: dict[str, np.ndarray], rng: np.random.Generator,
             noise: float = 0.0, keep: float = 1.0, flip: float = 0.0, n_fp: int = 0,
             dup: float = 0.0) -> list[SampleDetections]:
    """Detections in each sample's LiDAR frame from global GT boxes (the inverse of what the detector's output goes
    through), with optional centre noise [m], dropped boxes, class flips, false positives and, with probability
    ``dup``, a second noisy copy of a box with the same score. Scores are rounded to 0.05 where ``n_fp`` or ``dup``
    is given: ties across true and false positives and within a sample."""
    step = 0.05 if (n_fp or dup) else 0.0
    out = []
    for token in gt.sample_tokens:
        T = invert(T_global_lidar[token])
        rows, labels, attrs, scores = [], [], [], []
        for b in gt[token]:
            if rng.random() >= keep:
                continue
            name = b.detection_name if rng.random() >= flip else DETECTION_CLASSES[rng.integers(10)]
            conf = float(rng.uniform(0.05, 1.0))
            for _ in range(2 if rng.random() < dup else 1):
                c = T[:3, :3] @ np.asarray(b.translation) + T[:3, 3]
                c[:2] += rng.normal(0, noise, 2) if noise else 0.0
                yaw = yaw_of(b)
                h = T[:3, :3] @ np.array([math.cos(yaw), math.sin(yaw), 0.0])
                v = T[:3, :3] @ np.array([*np.nan_to_num(b.velocity), 0.0])
                rows.append([*c, *b.size, math.atan2(h[1], h[0]), v[0], v[1]])
                labels.append(DETECTION_CLASSES.index(name))
                attrs.append(ATTRIBUTES.index(b.attribute_name) if b.attribute_name else -1)
                scores.append(round(conf / step) * step if step else conf)
        for _ in range(n_fp):
            rows.append([*rng.uniform(-55, 55, 2), 0.5, *rng.uniform(0.5, 4, 3), rng.uniform(-3, 3),
                         *rng.normal(0, 2, 2)])
            labels.append(int(rng.integers(10)))
            attrs.append(int(rng.integers(-1, 8)))
            scores.append(round(float(rng.uniform(0, 1)) / step) * step)
        out.append(SampleDetections(token=token, boxes=np.asarray(rows, dtype=np.float64).reshape(-1, 9),
                                    scores=np.asarray(scores, dtype=np.float64),
                                    labels=np.asarray(labels, dtype=np.int64),
                                    attributes=np.asarray(attrs, dtype=np.int64)))
    return out


def nuscenes_like_pose(rng: np.random.Generator) -> np.ndarray:
    """A global <- LiDAR transform with nuScenes' x-right / y-forward mounting: 90 deg yaw on top of the ego
    heading, plus a ground offset."""
    T_global_ego = np.eye(4)
    T_global_ego[:3, :3] = yaw_matrix(rng.uniform(-np.pi, np.pi))
    T_global_ego[:3, 3] = [*rng.uniform(300, 900, 2), 0.0]
    T_ego_lidar = np.eye(4)
    T_ego_lidar[:3, :3] = yaw_matrix(np.pi / 2)
    T_ego_lidar[:3, 3] = [0.94, 0.0, 1.84]
    return T_global_ego @ T_ego_lidar


def random_world(rng: np.random.Generator, n_samples: int, n_gt: float = 12.0,
                 classes: tuple[str, ...] = ("car", "pedestrian", "truck", "barrier", "traffic_cone", "bicycle"),
                 prefix: str = "s") -> tuple[EvalBoxes, dict[str, np.ndarray]]:
    """Synthetic GT (global frame, ego at the LiDAR's position) and each sample's T_global_lidar."""
    gt: dict[str, list[DetectionBox]] = {}
    T: dict[str, np.ndarray] = {}
    for s in range(n_samples):
        token = f"{prefix}{s:03d}"
        T[token] = nuscenes_like_pose(rng)
        ego = T[token][:2, 3]
        gt[token] = []
        for _ in range(rng.poisson(n_gt)):
            name = classes[rng.integers(len(classes))]
            x, y = ego + rng.uniform(-45, 45, 2)
            vel = (math.nan, math.nan) if rng.random() < 0.1 else tuple(rng.normal(0, 2, 2))
            gt[token].append(box(token, name, float(x), float(y), yaw=float(rng.uniform(-np.pi, np.pi)),
                                 size=tuple(rng.uniform(0.5, 5, 3)), vel=vel, ego=tuple(ego),
                                 num_pts=int(rng.integers(0, 30)), attr=CLASS_ATTR[name] if rng.random() < 0.9 else ""))
    return boxes_of(gt), T


def noisy_predictions(gt: EvalBoxes, T: dict[str, np.ndarray], seed: int, noise: float = 0.6,
                      dup: float = 0.1) -> EvalBoxes:
    rng = np.random.default_rng(seed)
    return predictions_to_eval_boxes(to_lidar(gt, T, rng, noise=noise, keep=0.85, flip=0.05, n_fp=4, dup=dup), T)


# ----------------------------------------------------------------------------------- equality with the devkit


def test_accumulate_equals_devkit_on_random_data():
    """The vectorised accumulate == nuscenes.eval.detection.algo.accumulate (ties in scores, NaN velocities, boxes
    without attributes, wrong-class and far predictions), every class and threshold, to 1e-9."""
    rng = np.random.default_rng(7)
    gt, T = random_world(rng, 12, n_gt=14, classes=DETECTION_CLASSES)
    pred = noisy_predictions(gt, T, seed=8, noise=1.0, dup=0.5)
    # plus exact distance ties: a car midway between two GT cars of different sizes (the first GT wins)
    tie_gt = [box("tie", "car", 0.0, 0.0, size=(2, 4, 1.5)), box("tie", "car", 2.0, 0.0, size=(1, 3, 1))]
    gt.add_boxes("tie", tie_gt)
    pred.add_boxes("tie", [box("tie", "car", 1.0, 0.0, size=(1, 3, 1), score=0.5)])
    for name in DETECTION_CLASSES:
        for th in (0.5, 1.0, 2.0, 4.0):
            ref = algo.accumulate(gt, pred, name, center_distance, th)
            ours = accumulate(gt, pred, name, th)
            for key, value in ref.serialize().items():
                a, b = np.asarray(value, dtype=float), np.asarray(getattr(ours, key), dtype=float)
                np.testing.assert_allclose(b, a, rtol=0, atol=1e-9, err_msg=f"{name} @ {th} m: {key}")
    only_tie = boxes_of({"tie": tie_gt}), boxes_of({"tie": pred["tie"]})
    ref, ours = algo.accumulate(*only_tie, "car", center_distance, 2.0), accumulate(*only_tie, "car", 2.0)
    assert ref.scale_err[0] > 0.1 and ours.scale_err[0] == pytest.approx(ref.scale_err[0], abs=1e-12)


@pytest.fixture(scope="module")
def tiny_nusc(tiny_world):
    return open_nuscenes(tiny_world.dataroot, tiny_world.params.world.version)


def _T_global_lidar(nusc, token: str) -> np.ndarray:
    sd = nusc.get("sample_data", nusc.get("sample", token)["data"]["LIDAR_TOP"])
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    pose = nusc.get("ego_pose", sd["ego_pose_token"])
    return (transform_from_quaternion(pose["rotation"], pose["translation"])
            @ transform_from_quaternion(cs["rotation"], cs["translation"]))


def test_ground_truth_equals_devkit_loader(tiny_nusc):
    """ground_truth() on a nuScenes-format dataroot == the devkit's load_gt_of_sample_tokens + add_center_dist."""
    tokens = [s["token"] for s in tiny_nusc.sample]
    ours = ground_truth(tiny_nusc, tokens)
    with redirect_stdout(StringIO()):
        ref = add_center_dist(tiny_nusc, load_gt_of_sample_tokens(tiny_nusc, tokens, DetectionBox))
    assert ours.sample_tokens == tokens
    assert sum(len(ours[t]) for t in tokens) > 20
    for token in tokens:
        assert len(ours[token]) == len(ref[token])
        for a, b in zip(ours[token], ref[token]):
            assert (a.detection_name, a.attribute_name, a.num_pts) == (b.detection_name, b.attribute_name, b.num_pts)
            assert type(a.num_pts) is int and type(a.detection_score) is float
            for key in ("translation", "size", "rotation", "velocity", "ego_translation"):
                np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=0, atol=1e-9, err_msg=key)


def test_score_equals_official_detection_eval(tiny_nusc, tmp_path):
    """score() == the official DetectionEval (custom split of the dataroot's splits.json, predictions read from a
    results file) on noisy predictions through the real LiDAR poses. The dataset has no bike racks, so the devkit's
    bike-rack filter (not reimplemented) changes nothing."""
    assert not any(c["name"] == "static_object.bicycle_rack" for c in tiny_nusc.category
                   if any(i["category_token"] == c["token"] for i in tiny_nusc.instance))
    splits = json.loads((Path(tiny_nusc.table_root) / "splits.json").read_text())
    compared = 0
    for split in ("weatheralign_train", "weatheralign_val"):
        scenes = {s["token"] for s in tiny_nusc.scene if s["name"] in splits[split]}
        tokens = [s["token"] for s in tiny_nusc.sample if s["scene_token"] in scenes]
        gt = ground_truth(tiny_nusc, tokens)
        T = {t: _T_global_lidar(tiny_nusc, t) for t in tokens}
        dets = to_lidar(gt, T, np.random.default_rng(3), noise=0.7, keep=0.85, flip=0.05, n_fp=6,
                        dup=0.3)
        pred = predictions_to_eval_boxes(dets, T, ego_position=ego_positions(tiny_nusc, tokens))
        path = tmp_path / f"results_{split}.json"
        path.write_text(json.dumps({"meta": {"use_lidar": True}, "results": pred.serialize()}))
        with redirect_stdout(StringIO()):
            official = DetectionEval(tiny_nusc, config_factory("detection_cvpr_2019"), str(path), eval_set=split,
                                     output_dir=str(tmp_path / split), verbose=False)
            ref, _ = official.evaluate()
        ours = score(gt, pred)
        assert abs(ours.map - ref.mean_ap) < 1e-9 and abs(ours.nds - ref.nd_score) < 1e-9
        for name in DETECTION_CLASSES:
            for th in (0.5, 1.0, 2.0, 4.0):
                assert abs(ours.per_class_ap_by_threshold[name][th] - ref.get_label_ap(name, th)) < 1e-9
            for metric in TP_METRICS:
                np.testing.assert_allclose(ours.per_class_tp[name][metric], ref.get_label_tp(name, metric),
                                           rtol=0, atol=1e-9, err_msg=f"{name} {metric}")
        for metric, value in ref.tp_errors.items():
            assert abs(ours.tp_errors[metric] - value) < 1e-9
        assert ours.map > 0.05  # a non-trivial case
        compared += 1
    assert compared == 2


def test_exported_results_files_score_the_same_in_the_devkit_and_in_flows_score(tiny_nusc, tmp_path):
    """A results file written by the detect stage (`write_submission`) read by the official ``DetectionEval`` gives
    the project's mAP / NDS; ``python -m flows.score`` on it reports the same point estimate, and a file with a
    missing sample or a wrong class is refused in one line naming it."""
    from flows.score import main as score_main
    from weatheralign.data.errors import DataFormatError
    from weatheralign.detect.data import scene_split
    from weatheralign.detect.results import read_submission, write_submission

    root = Path(tiny_nusc.dataroot)
    version = tiny_nusc.version
    tokens = scene_split(tiny_nusc, root, version, "val")
    gt = ground_truth(tiny_nusc, tokens)
    T = {t: _T_global_lidar(tiny_nusc, t) for t in tokens}
    egos = ego_positions(tiny_nusc, tokens)
    dets = to_lidar(gt, T, np.random.default_rng(5), noise=0.5, keep=0.8, flip=0.05, n_fp=4, dup=0.2)
    pred = predictions_to_eval_boxes(dets, T, ego_position=egos)
    path = tmp_path / "seed0" / "pretrained" / "clean.json"
    write_submission(path, pred, use_camera=True, use_lidar=True)
    meta = json.loads(path.read_text())["meta"]
    assert meta["use_camera"] and meta["use_lidar"] and not meta["use_radar"]
    split = next(k for k in json.loads((Path(tiny_nusc.table_root) / "splits.json").read_text()) if k.endswith("_val"))
    with redirect_stdout(StringIO()):
        official, _ = DetectionEval(tiny_nusc, config_factory("detection_cvpr_2019"), str(path), eval_set=split,
                                    output_dir=str(tmp_path / "eval"), verbose=False).evaluate()
    ours = score(gt, pred)
    assert ours.map > 0.05 and abs(ours.map - official.mean_ap) < 1e-9 and abs(ours.nds - official.nd_score) < 1e-9
    read_back, _ = read_submission(path, tokens, egos)
    assert score(gt, read_back).map == pytest.approx(ours.map, abs=1e-12)

    out = tmp_path / "score.json"
    assert score_main(["--dataroot", str(root), "--version", version, "--results", str(path), "--bootstrap", "20",
                       "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["map"]["value"] == pytest.approx(official.mean_ap, abs=1e-9)
    assert report["nds"]["value"] == pytest.approx(official.nd_score, abs=1e-9)
    assert score_main(["--dataroot", str(root), "--version", version, "--results", str(path), "--minus", str(path),
                       "--bootstrap", "20", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["map"] == {"value": 0.0, "per_seed": [0.0], "ci": [0.0, 0.0]}

    data = json.loads(path.read_text())
    del data["results"][tokens[0]]
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match="broken.json: 1 sample"):
        read_submission(broken, tokens, egos)
    data = json.loads(path.read_text())
    first = next(t for t in tokens if data["results"][t])
    data["results"][first][0]["detection_name"] = "tram"
    broken.write_text(json.dumps(data))
    with pytest.raises(DataFormatError, match="detection_name 'tram'"):
        read_submission(broken, tokens, egos)


# ------------------------------------------------------------------------------------------- known answers


def test_perfect_predictions_through_rotated_lidar():
    """GT -> LiDAR frame (90 deg mounting yaw) -> predictions_to_eval_boxes: the boxes come back exactly, every
    present class scores AP 1 with zero TP errors, mAP = #present / 10, NDS by its formula."""
    rng = np.random.default_rng(1)
    present = ("car", "pedestrian", "truck", "barrier", "traffic_cone", "bicycle")
    gt, T = random_world(rng, 6, n_gt=10, classes=present)
    clean = {t: [DetectionBox(**{**b.serialize(), "num_pts": 5,
                                 "velocity": tuple(np.nan_to_num(b.velocity, nan=0.3)),
                                 "attribute_name": CLASS_ATTR[b.detection_name]}) for b in gt[t]]
             for t in gt.sample_tokens}
    gt = boxes_of(clean)
    pred = predictions_to_eval_boxes(to_lidar(gt, T, rng), T)
    for token in gt.sample_tokens:
        for g, p in zip(gt[token], pred[token]):
            np.testing.assert_allclose(p.translation, g.translation, atol=1e-9)
            np.testing.assert_allclose(p.velocity, g.velocity, atol=1e-9)
            np.testing.assert_allclose(p.ego_translation[:2], g.ego_translation[:2], atol=1e-9)  # xy: the ranges
            assert abs(math.remainder(yaw_of(p) - yaw_of(g), 2 * math.pi)) < 1e-9
            assert type(p.detection_score) is float and p.detection_name == g.detection_name
    s = score(gt, pred)
    seen = {b.detection_name for b in gt.all if math.hypot(*b.ego_translation[:2]) < {
        "pedestrian": 40, "bicycle": 40, "barrier": 30, "traffic_cone": 30}.get(b.detection_name, 50)}
    assert set(s.classes_present) == seen and len(seen) >= 5
    for name in DETECTION_CLASSES:
        assert s.per_class_ap[name] == pytest.approx(1.0 if name in seen else 0.0, abs=1e-12)
        for metric in TP_METRICS:
            err = s.per_class_tp[name][metric]
            if metric in NO_TP.get(name, ()):
                assert math.isnan(err)
            else:
                assert err == pytest.approx(0.0 if name in seen else 1.0, abs=1e-9), (name, metric)
    assert s.map_present == pytest.approx(1.0)
    assert s.map == pytest.approx(len(seen) / 10)
    mean_err = {m: np.mean([0.0 if c in seen else 1.0 for c in DETECTION_CLASSES if m not in NO_TP.get(c, ())])
                for m in TP_METRICS}
    assert s.nds == pytest.approx((5 * len(seen) / 10 + sum(1 - min(1, e) for e in mean_err.values())) / 10)
    d = s.as_dict()
    json.dumps(d, allow_nan=False)
    assert {"map", "nds", "map_present", "classes_present", "mate", "mase", "maoe", "mave", "maae", "per_class_ap",
            "per_class_tp"} <= set(d)
    assert d["per_class_tp"]["traffic_cone"]["aoe"] is None and d["mate"] == pytest.approx(mean_err["trans_err"])


def test_shift_of_1p5_m_keeps_only_the_2_and_4_m_thresholds():
    gt, pred = {}, {}
    for s in range(5):
        token = f"t{s}"
        cars = [(10.0 * i - 20.0, 12.0 * j - 15.0) for i in range(4) for j in range(3)]
        gt[token] = [box(token, "car", x, y) for x, y in cars]
        pred[token] = [box(token, "car", x + 1.5, y, score=0.5 + 0.01 * k) for k, (x, y) in enumerate(cars)]
    s = score(boxes_of(gt), boxes_of(pred))
    assert s.per_class_ap_by_threshold["car"] == pytest.approx({0.5: 0.0, 1.0: 0.0, 2.0: 1.0, 4.0: 1.0})
    assert s.per_class_ap["car"] == pytest.approx(0.5) and s.map_present == pytest.approx(0.5)
    assert s.per_class_tp["car"]["trans_err"] == pytest.approx(1.5)
    assert s.map == pytest.approx(0.05)


def test_range_and_point_filters():
    """A car at 60 m (> 50 m), a pedestrian at 45 m (> 40 m) and a GT box without points are ignored, GT and
    predictions alike; a car at 45 m is kept. Without ego_translation (the devkit's default 0) the far GT would
    count: the pitfall the ego translation avoids."""
    ego = (100.0, 200.0)
    g = [box("a", "car", ego[0] + 10, ego[1], ego=ego), box("a", "car", ego[0] + 45, ego[1], ego=ego),
         box("a", "car", ego[0], ego[1] + 60, ego=ego), box("a", "pedestrian", ego[0] - 45, ego[1], ego=ego),
         box("a", "car", ego[0] - 20, ego[1], ego=ego, num_pts=0)]
    p = [box("a", "car", ego[0] + 10, ego[1], ego=ego, score=0.5), box("a", "car", ego[0] + 45, ego[1], ego=ego,
                                                                      score=0.6),
         box("a", "car", ego[0] - 60, ego[1], ego=ego, score=0.9)]  # a far false positive with the top score
    s = score(boxes_of({"a": g}), boxes_of({"a": p}))
    assert s.per_class_ap["car"] == pytest.approx(1.0) and s.classes_present == ("car",)
    # the same through the LiDAR frame: a detection 60 m from the sensor is dropped
    T = {"a": np.eye(4)}
    T["a"][:3, 3] = [*ego, 1.8]
    far = SampleDetections(token="a", boxes=np.array([[0.0, 60.0, 0.0, 2, 4, 1.5, 0, 0, 0]]), scores=np.array([0.95]),
                           labels=np.array([0]), attributes=np.array([-1]))
    near = to_lidar(boxes_of({"a": g[:2]}), T, np.random.default_rng(0))[0]
    merged = SampleDetections("a", np.vstack([near.boxes, far.boxes]), np.r_[near.scores, far.scores],
                              np.r_[near.labels, far.labels], np.r_[near.attributes, far.attributes])
    assert score(boxes_of({"a": g}), predictions_to_eval_boxes([merged], T)).per_class_ap["car"] == pytest.approx(1.0)
    no_ego = [DetectionBox(**{**b.serialize(), "ego_translation": (0.0, 0.0, 0.0)}) for b in g]
    assert score(boxes_of({"a": no_ego}), boxes_of({"a": p[:2]})).per_class_ap["car"] < 0.9


def test_clear_errors():
    gt = boxes_of({"a": [box("a", "car", 1, 1)], "b": []})
    with pytest.raises(ValueError, match="'zz'"):
        score(gt, boxes_of({"a": [], "b": [], "zz": []}))
    with pytest.raises(ValueError, match="'b'.*|no prediction entry"):
        score(gt, boxes_of({"a": []}))
    det = SampleDetections("q", np.zeros((0, 9)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
    with pytest.raises(ValueError, match="sample q: no T_global_lidar"):
        predictions_to_eval_boxes([det], {"a": np.eye(4)})
    with pytest.raises(ValueError, match="T_global_lidar\\[a\\]"):
        predictions_to_eval_boxes([SampleDetections("a", *[det.boxes, det.scores, det.labels, det.attributes])],
                                  {"a": np.diag([2.0, 1, 1, 1])})
    assert predictions_to_eval_boxes([], {"a": np.eye(4), "b": np.eye(4)}).sample_tokens == ["a", "b"]
    with pytest.raises(ValueError, match="nds_clean"):
        resistance_ability(0.3, 0.0)
    assert resistance_ability(0.45, 0.6) == pytest.approx(0.75)


# ------------------------------------------------------------------------------------------------- bootstrap


def test_bootstrap_replicate_is_rescoring_renamed_samples():
    """A replicate == score() of the samples drawn (numpy default_rng(seed).integers), duplicates renamed
    <token>#k: with n_boot=1 the interval collapses onto that replicate."""
    rng = np.random.default_rng(2)
    gt, T = random_world(rng, 15)
    pred = noisy_predictions(gt, T, seed=3)
    for seed in (0, 1):
        draws = np.random.default_rng(seed).integers(0, 15, size=(1, 15))[0]
        tokens = [gt.sample_tokens[i] for i in draws]
        assert len(set(tokens)) < 15  # duplicates present
        ref = score(resample(gt, tokens), resample(pred, tokens))
        map_ci, nds_ci, present_ci = bootstrap_intervals(gt, pred, n_boot=1, seed=seed)
        assert map_ci == pytest.approx([ref.map] * 2, abs=1e-12)
        assert nds_ci == pytest.approx([ref.nds] * 2, abs=1e-12)
        assert present_ci == pytest.approx([ref.map_present] * 2, abs=1e-12)


def test_replicate_summary_equals_the_devkit_objects_path():
    """`_summary` (the bootstrap's scorer, no devkit objects) gives exactly `_scores`' mAP, NDS and mAP-present (the
    devkit's calc_ap / calc_tp / DetectionMetrics) on resampled draws, on draws missing classes, and on a model that
    finds nothing."""
    from weatheralign.detect.evaluate import _prepare, _scores, _summary, detection_config

    rng = np.random.default_rng(21)
    gt, T = random_world(rng, 30)
    cfg = detection_config()
    for pred in (noisy_predictions(gt, T, 4), noisy_predictions(gt, T, 5, noise=2.0),
                 boxes_of({t: [] for t in gt.sample_tokens})):
        prep = _prepare(gt, pred, cfg)
        draws = [prep.pred_order, *np.random.default_rng(0).integers(0, 30, size=(25, 30)), np.array([0, 0, 1])]
        for d in draws:
            full = _scores(prep, d)
            fast = _summary(prep, d)
            assert fast[:2] == (full.map, full.nds)
            assert fast[2] == full.map_present or (math.isnan(fast[2]) and math.isnan(full.map_present))


def test_bootstrap_intervals_contain_estimate_are_seeded_and_shrink():
    rng = np.random.default_rng(4)
    small, T_small = random_world(rng, 20, prefix="a")
    large, T_large = random_world(rng, 160, prefix="b")
    p_small, p_large = noisy_predictions(small, T_small, 5), noisy_predictions(large, T_large, 6)
    point = score(small, p_small)
    first = bootstrap_intervals(small, p_small, n_boot=100, seed=11)
    assert first == bootstrap_intervals(small, p_small, n_boot=100, seed=11)
    assert first != bootstrap_intervals(small, p_small, n_boot=100, seed=12)
    for (lo, hi), value in zip(first, (point.map, point.nds, point.map_present)):
        assert lo <= value <= hi and hi > lo
    wide = bootstrap_intervals(small, p_small, n_boot=100, seed=0)
    narrow = bootstrap_intervals(large, p_large, n_boot=100, seed=0)
    for (lo_w, hi_w), (lo_n, hi_n) in zip(wide, narrow):
        assert hi_n - lo_n < 0.75 * (hi_w - lo_w)


def test_paired_difference():
    rng = np.random.default_rng(9)
    gt, T = random_world(rng, 25)
    good, bad = noisy_predictions(gt, T, 1, noise=0.3), noisy_predictions(gt, T, 2, noise=1.5)
    for metric in ("map", "nds", "map_present"):
        diff, ci = paired_difference(gt, good, good, metric=metric, n_boot=30, seed=0)
        assert diff == 0.0 and ci == [0.0, 0.0]
    diff, (lo, hi) = paired_difference(gt, good, bad, metric="nds", n_boot=100, seed=0)
    assert diff == pytest.approx(score(gt, good).nds - score(gt, bad).nds, abs=1e-12)
    assert 0 < lo <= diff <= hi
    with pytest.raises(ValueError, match="metric"):
        paired_difference(gt, good, bad, metric="mAP")  # type: ignore[arg-type]
    # every metric from one set of replicates: each equal to its own paired_difference, bit for bit
    together = paired_differences(gt, good, bad, ("map", "nds", "map_present"), n_boot=50, seed=3)
    for metric, result in together.items():
        assert result == paired_difference(gt, good, bad, metric=metric, n_boot=50, seed=3)
    assert together["map"] != paired_differences(gt, good, bad, ("map",), n_boot=50, seed=4)["map"]


def test_scene_blocks_cut_each_scene_into_consecutive_frames():
    from weatheralign.detect.evaluate import scene_blocks

    blocks = scene_blocks(["a"] * 5 + ["b"] * 3, 2)
    assert [b.tolist() for b in blocks] == [[0, 1], [2, 3], [4], [5, 6], [7]]
    with pytest.raises(ValueError):
        scene_blocks(["a"], 0)


def test_seed_block_bootstrap_pools_seeds_and_holds_their_spread():
    """The estimate is the mean over seeds; two seeds far apart give an interval that covers both, wider than
    either seed's own sampling interval."""
    from weatheralign.detect.evaluate import scene_blocks, seed_block_bootstrap

    tokens = [f"s{i}" for i in range(24)]
    gt = boxes_of({t: [box(t, "car", 10.0 + i % 5, 3.0), box(t, "pedestrian", -8.0, 2.0 + i % 3, size=(0.6, 0.7, 1.7))]
                   for i, t in enumerate(tokens)})
    good = boxes_of({t: [box(t, "car", 10.0 + i % 5 + 0.1, 3.0, score=0.9),
                         box(t, "pedestrian", -8.0, 2.2 + i % 3, size=(0.6, 0.7, 1.7), score=0.8)]
                     for i, t in enumerate(tokens)})
    poor = boxes_of({t: [box(t, "car", 10.0 + i % 5 + (1.5 if i % 2 else 0.1), 3.0, score=0.5)]
                     for i, t in enumerate(tokens)})
    blocks = scene_blocks(["x"] * 12 + ["y"] * 12, 4)
    pooled = seed_block_bootstrap(gt, [good, poor], None, blocks, ("map",), n_boot=200, seed=1)["map"]
    single = [seed_block_bootstrap(gt, [p], None, blocks, ("map",), n_boot=200, seed=1)["map"] for p in (good, poor)]
    assert pooled.value == pytest.approx(np.mean([s.value for s in single]), abs=1e-12)
    assert pooled.per_seed == [s.value for s in single]
    assert pooled.ci[0] <= single[1].value + 1e-9 and single[0].value - 1e-9 <= pooled.ci[1]
    assert pooled.ci[1] - pooled.ci[0] > max(s.ci[1] - s.ci[0] for s in single)
    same = seed_block_bootstrap(gt, [good, poor], [good, poor], blocks, ("map", "nds"), n_boot=50, seed=1)
    assert same["map"].ci == [0.0, 0.0] and same["nds"].value == 0.0
