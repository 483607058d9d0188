"""nuScenes detection metrics (mAP, NDS, TP errors) for custom boxes, without the devkit's database-bound loaders,
and frame-bootstrap intervals.

Scoring follows nuscenes-devkit 1.2.0's ``DetectionEval`` with ``config_factory('detection_cvpr_2019')``:

* boxes are `nuscenes.eval.common.data_classes.EvalBoxes` of devkit ``DetectionBox`` in the global frame;
  `ground_truth` builds them from a dataroot as the devkit's ``load_gt`` + ``add_center_dist`` do,
  `predictions_to_eval_boxes` from LiDAR-frame `SampleDetections`;
* filtering as the devkit's ``filter_eval_boxes`` (per-class range on the xy distance to the ego, GT boxes without
  LiDAR/radar points dropped) EXCEPT the bike-rack filter (bicycles/motorcycles inside a ``bicycle_rack`` annotation
  are dropped by the devkit; that needs the database and is skipped here, as is right for data without bike racks
  such as the synthetic world);
* matching, AP and TP errors: an exact vectorised equivalent of ``nuscenes.eval.detection.algo.accumulate``
  (tested equal to it and to ``DetectionEval`` to 1e-9), whose per-sample greedy matches are computed once so that
  bootstrap replicates only re-sort and re-accumulate; ``calc_ap``, ``calc_tp`` and ``DetectionMetrics`` are the
  devkit's own.

Why the matching can be precomputed: the devkit matches predictions in descending score order (ties: later
prediction first) to the closest not-yet-taken GT box *of the same sample*, so a prediction's match depends only on
its own sample's boxes; resampling samples changes only the global order and the counts, not who matches whom.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from nuscenes.eval.common.config import config_factory
from nuscenes.eval.common.data_classes import EvalBoxes
from nuscenes.eval.detection.algo import calc_ap, calc_tp
from nuscenes.eval.detection.constants import TP_METRICS
from nuscenes.eval.detection.data_classes import DetectionBox, DetectionConfig, DetectionMetricData, DetectionMetrics
from nuscenes.eval.detection.utils import category_to_detection_name
from nuscenes.nuscenes import NuScenes

from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import (
    IS_COUNT,
    IS_LIST,
    IS_STRING,
    channel_token,
    checked_field,
    checked_get,
    checked_vector,
    table_path,
)
from weatheralign.detect.types import ATTRIBUTES, DETECTION_CLASSES, SampleDetections
from weatheralign.geometry import NonRigidTransformError, check_rigid

F64 = NDArray[np.float64]
Metric = Literal["map", "nds", "map_present"]

CONFIG_NAME = "detection_cvpr_2019"
DEFAULT_BOOTSTRAP = 1000
"""Default number of bootstrap replicates for the percentile intervals: affordable because the boxes are matched
once and a replicate only rescores (`bootstrap_intervals`)."""
#: short names of the devkit's TP metrics, in ``TP_METRICS`` order
TP_SHORT: dict[str, str] = {"trans_err": "ate", "scale_err": "ase", "orient_err": "aoe", "vel_err": "ave",
                            "attr_err": "aae"}
_NO_TP: dict[str, tuple[str, ...]] = {"traffic_cone": ("attr_err", "vel_err", "orient_err"),
                                      "barrier": ("attr_err", "vel_err")}
_ERRORS = ("trans_err", "vel_err", "scale_err", "orient_err", "attr_err")  # DetectionMetricData's order
_ATTR_INDEX = {name: i for i, name in enumerate(ATTRIBUTES)}
_CLASS_INDEX = {name: i for i, name in enumerate(DETECTION_CLASSES)}


def detection_config() -> DetectionConfig:
    """The devkit's ``detection_cvpr_2019`` configuration (ranges, thresholds 0.5/1/2/4 m, TP threshold 2 m)."""
    cfg = config_factory(CONFIG_NAME)
    if tuple(cfg.class_names) != DETECTION_CLASSES:
        raise RuntimeError(f"the devkit's {CONFIG_NAME} classes {tuple(cfg.class_names)} differ from "
                           f"DETECTION_CLASSES {DETECTION_CLASSES}")
    return cfg


# ------------------------------------------------------------------------------------------------ building boxes


def _floats(values: Iterable[Any]) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def ego_positions(nusc: NuScenes, sample_tokens: Sequence[str]) -> dict[str, F64]:
    """Global ego position (3,) [m] of each sample: the ego pose of its keyframe LIDAR_TOP sample_data (the point
    the devkit's ``add_center_dist`` measures ranges from).

    Raises:
        DataFormatError: an unknown sample token, a sample without LIDAR_TOP, a missing or malformed pose.
    """
    out: dict[str, F64] = {}
    for token in sample_tokens:
        sample = checked_get(nusc, "sample", token, "ego_positions")
        sd_token = channel_token(nusc, sample, "LIDAR_TOP")
        sd = checked_get(nusc, "sample_data", sd_token, f"sample {token}.data.LIDAR_TOP")
        pose_token = checked_field(nusc, "sample_data", sd, "ego_pose_token", IS_STRING)
        pose = checked_get(nusc, "ego_pose", pose_token, f"sample_data {sd_token}.ego_pose_token")
        out[token] = checked_vector(nusc, "ego_pose", pose, "translation", 3)
    return out


def _gt_box(nusc: NuScenes, ann_token: str, sample_token: str, ego: F64) -> DetectionBox | None:
    """One annotation as the devkit's ``load_gt`` builds it (None for categories outside the detection classes),
    with ``ego_translation`` = centre - ego position as ``add_center_dist`` sets it."""
    table = "sample_annotation"
    ann = checked_get(nusc, table, ann_token, f"sample {sample_token}.anns")
    inst_token = checked_field(nusc, table, ann, "instance_token", IS_STRING)
    inst = checked_get(nusc, "instance", inst_token, f"{table} {ann_token}.instance_token")
    cat = checked_get(nusc, "category", checked_field(nusc, "instance", inst, "category_token", IS_STRING),
                      f"instance {inst_token}.category_token")
    name = category_to_detection_name(checked_field(nusc, "category", cat, "name", IS_STRING))
    if name is None:
        return None
    attr_tokens = checked_field(nusc, table, ann, "attribute_tokens", IS_LIST)
    if len(attr_tokens) > 1:
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {ann_token}: {len(attr_tokens)} attribute_tokens; "
                              f"the nuScenes detection evaluation allows at most one")
    attribute = (checked_field(nusc, "attribute",
                               checked_get(nusc, "attribute", attr_tokens[0], f"{table} {ann_token}.attribute_tokens"),
                               "name", IS_STRING) if attr_tokens else "")
    center = checked_vector(nusc, table, ann, "translation", 3)
    size = checked_vector(nusc, table, ann, "size", 3)
    rotation = checked_vector(nusc, table, ann, "rotation", 4)
    num_pts = (int(checked_field(nusc, table, ann, "num_lidar_pts", IS_COUNT))
               + int(checked_field(nusc, table, ann, "num_radar_pts", IS_COUNT)))
    try:
        velocity = np.asarray(nusc.box_velocity(ann_token), dtype=np.float64)[:2]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {ann_token}: cannot derive its velocity from "
                              f"its prev/next annotations ({type(exc).__name__}: {exc})") from None
    if not (size > 0).all():
        raise DataFormatError(f"{table_path(nusc, table)}: {table} {ann_token}: field 'size' = {size.tolist()}; "
                              f"expected three positive numbers [m]")
    return DetectionBox(sample_token=sample_token, translation=_floats(center), size=_floats(size),
                        rotation=_floats(rotation), velocity=_floats(velocity), ego_translation=_floats(center - ego),
                        num_pts=num_pts, detection_name=name, detection_score=-1.0, attribute_name=attribute)


def ground_truth(nusc: NuScenes, sample_tokens: Sequence[str]) -> EvalBoxes:
    """The samples' annotations as devkit ``DetectionBox`` es (global frame), as ``load_gt`` + ``add_center_dist``
    build them: detection name via ``category_to_detection_name`` (other categories dropped), the attribute name
    ('' for none), velocity (2,) [m/s] from ``nusc.box_velocity`` (NaN where it cannot be estimated),
    ``num_pts = num_lidar_pts + num_radar_pts``, ``ego_translation`` = centre - keyframe LIDAR_TOP ego position [m].
    Every sample gets an entry, possibly empty.

    Raises:
        DataFormatError: an unknown sample token, or a missing or malformed record or field (naming table, token,
            field); an annotation with more than one attribute.
    """
    egos = ego_positions(nusc, sample_tokens)
    out = EvalBoxes()
    for token in sample_tokens:
        sample = checked_get(nusc, "sample", token, "ground_truth")
        boxes = [_gt_box(nusc, a, token, egos[token]) for a in checked_field(nusc, "sample", sample, "anns", IS_LIST)]
        out.add_boxes(token, [b for b in boxes if b is not None])
    return out


def _rigid(T: Any, what: str) -> F64:
    try:
        return check_rigid(T, what)
    except NonRigidTransformError as err:
        raise ValueError(str(err)) from None


def _check_detections(det: SampleDetections) -> int:
    k = len(det.scores)
    shapes = {"boxes": (np.shape(det.boxes), (k, 9)), "labels": (np.shape(det.labels), (k,)),
              "attributes": (np.shape(det.attributes), (k,)), "scores": (np.shape(det.scores), (k,))}
    for name, (got, want) in shapes.items():
        if got != want:
            raise ValueError(f"detections of sample {det.token}: {name} has shape {got}; expected {want}")
    if not (np.isfinite(det.boxes[:, :7]).all() and np.isfinite(det.scores).all()):
        raise ValueError(f"detections of sample {det.token}: NaN or inf in the box centres/sizes/yaws or scores")
    if k and (np.min(det.scores) < 0 or np.max(det.scores) > 1):
        raise ValueError(f"detections of sample {det.token}: scores must lie in [0, 1]")
    if k and not (det.boxes[:, 3:6] > 0).all():
        raise ValueError(f"detections of sample {det.token}: box sizes must be positive [m]")
    bad = [int(v) for v in det.labels if not 0 <= int(v) < len(DETECTION_CLASSES)]
    if bad:
        raise ValueError(f"detections of sample {det.token}: labels {bad} outside 0..{len(DETECTION_CLASSES) - 1}")
    bad = [int(v) for v in det.attributes if not -1 <= int(v) < len(ATTRIBUTES)]
    if bad:
        raise ValueError(f"detections of sample {det.token}: attributes {bad} outside -1..{len(ATTRIBUTES) - 1}")
    return k


def predictions_to_eval_boxes(detections: Sequence[SampleDetections], T_global_lidar: Mapping[str, Any],
                              ego_position: Mapping[str, Any] | None = None) -> EvalBoxes:
    """LiDAR-frame detections as devkit ``DetectionBox`` es in the global frame.

    Centre ``T @ c``; yaw: the heading vector (cos yaw, sin yaw, 0) rotated by ``T``'s rotation, its global azimuth
    as a quaternion about global z; velocity (vx, vy, 0) rotated, its x/y kept; size as is; class and attribute
    names ('' for attribute -1); ``detection_score`` as a Python float; ``ego_translation`` = global centre - the
    sample's ego position [m].

    Args:
        detections: per-sample detections (box rows (K, 9), see `weatheralign.detect.types`).
        T_global_lidar: sample token -> (4, 4) keyframe LiDAR frame -> global. Every token here gets an entry in
            the output (empty where it has no detections): pass one for every evaluated sample.
        ego_position: sample token -> ego position (3,) [m] in the global frame, e.g. `ego_positions`; by default
            the LiDAR's position ``T_global_lidar[:3, 3]``, which differs from the devkit's range reference (the ego
            pose, used by `ground_truth`) by the LiDAR's horizontal mounting offset (~1 m on nuScenes): pass
            `ego_positions` to apply exactly the devkit's range cut to predictions.

    Raises:
        ValueError: a detection token without a transform (or ego position), a non-rigid transform, duplicate
            detection tokens, malformed arrays (naming the sample).
    """
    out = EvalBoxes()
    for token in T_global_lidar:
        out.add_boxes(token, [])
    seen: set[str] = set()
    for det in detections:
        if det.token in seen:
            raise ValueError(f"detections: sample {det.token} appears more than once")
        seen.add(det.token)
        if det.token not in T_global_lidar:
            raise ValueError(f"detections of sample {det.token}: no T_global_lidar for it "
                             f"({len(T_global_lidar)} transforms given)")
        T = _rigid(T_global_lidar[det.token], f"T_global_lidar[{det.token}]")
        if ego_position is None:
            ego = T[:3, 3]
        elif det.token in ego_position:
            ego = np.asarray(ego_position[det.token], dtype=np.float64).reshape(3)
        else:
            raise ValueError(f"detections of sample {det.token}: no ego_position for it")
        if _check_detections(det) == 0:
            continue
        rows = np.asarray(det.boxes, dtype=np.float64)
        R = T[:3, :3]
        centers = rows[:, :3] @ R.T + T[:3, 3]
        heading = np.column_stack([np.cos(rows[:, 6]), np.sin(rows[:, 6]), np.zeros(len(rows))]) @ R.T
        yaw = np.arctan2(heading[:, 1], heading[:, 0])
        vel = (np.column_stack([rows[:, 7:9], np.zeros(len(rows))]) @ R.T)[:, :2]
        boxes = []
        for i in range(len(rows)):
            attr = int(det.attributes[i])
            boxes.append(DetectionBox(
                sample_token=det.token, translation=_floats(centers[i]), size=_floats(rows[i, 3:6]),
                rotation=(math.cos(yaw[i] / 2), 0.0, 0.0, math.sin(yaw[i] / 2)), velocity=_floats(vel[i]),
                ego_translation=_floats(centers[i] - ego), detection_name=DETECTION_CLASSES[int(det.labels[i])],
                detection_score=float(det.scores[i]), attribute_name=ATTRIBUTES[attr] if attr >= 0 else ""))
        out.add_boxes(det.token, boxes)
    return out


# ------------------------------------------------------------------------------------------ flat representation


@dataclass(frozen=True)
class _Flat:
    """The boxes of an ``EvalBoxes`` as arrays (N boxes; sample order as in the EvalBoxes, boxes in list order).

    sample (N,) index into the sample order; label (N,) into `DETECTION_CLASSES`; xy (N, 2) [m]; yaw (N,) [rad]
    as the devkit's ``quaternion_yaw``; size (N, 3) [m]; vel (N, 2) [m/s]; attr (N,) into `ATTRIBUTES` (-1: '');
    score (N,); keep (N,) bool: survives the range and num_pts filters.
    """

    tokens: tuple[str, ...]
    sample: NDArray[np.int64]
    label: NDArray[np.int64]
    xy: F64
    yaw: F64
    size: F64
    vel: F64
    attr: NDArray[np.int64]
    score: F64
    keep: NDArray[np.bool_]


def _quaternion_yaw(q: F64) -> F64:
    """(N, 4) (w, x, y, z) -> (N,) yaw as ``nuscenes.eval.common.utils.quaternion_yaw`` (of the normalised
    quaternion's rotation matrix, the azimuth of its x axis)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def _flatten(boxes: EvalBoxes, cfg: DetectionConfig, what: str, apply_filters: bool = True) -> _Flat:
    tokens = tuple(boxes.sample_tokens)
    rows: list[DetectionBox] = []
    sample: list[int] = []
    for s, token in enumerate(tokens):
        for box in boxes[token]:
            if not isinstance(box, DetectionBox):
                raise TypeError(f"{what}: sample {token} holds a {type(box).__name__}; expected DetectionBox")
            if box.sample_token != token:
                raise ValueError(f"{what}: a box under sample {token} has sample_token {box.sample_token!r}")
            rows.append(box)
            sample.append(s)
    n = len(rows)
    label = np.array([_CLASS_INDEX[b.detection_name] for b in rows], dtype=np.int64)
    attr = np.array([_ATTR_INDEX[b.attribute_name] if b.attribute_name else -1 for b in rows], dtype=np.int64)
    xyz = np.array([b.translation for b in rows], dtype=np.float64).reshape(n, 3)
    size = np.array([b.size for b in rows], dtype=np.float64).reshape(n, 3)
    if n and not (size > 0).all():
        bad = rows[int(np.flatnonzero(~(size > 0).all(axis=1))[0])]
        raise ValueError(f"{what}: a {bad.detection_name} box of sample {bad.sample_token} has size {bad.size}; "
                         f"expected positive sizes [m]")
    rot = np.array([b.rotation for b in rows], dtype=np.float64).reshape(n, 4)
    vel = np.array([b.velocity for b in rows], dtype=np.float64).reshape(n, 2)
    ego = np.array([b.ego_translation for b in rows], dtype=np.float64).reshape(n, 3)
    ego_dist = np.sqrt(np.sum(ego[:, :2] ** 2, axis=1))
    max_dist = np.array([cfg.class_range[c] for c in DETECTION_CLASSES], dtype=np.float64)
    num_pts = np.array([b.num_pts for b in rows], dtype=np.int64)
    keep = (ego_dist < max_dist[label]) & (num_pts != 0)  # filter_eval_boxes without the bike-rack filter
    if not apply_filters:
        keep = np.ones(n, dtype=bool)
    return _Flat(tokens=tokens, sample=np.array(sample, dtype=np.int64), label=label, xy=xyz[:, :2],
                 yaw=_quaternion_yaw(rot) if n else np.zeros(0), size=size, vel=vel, attr=attr,
                 score=np.array([b.detection_score for b in rows], dtype=np.float64), keep=keep)


# --------------------------------------------------------------------------------------------------- matching


def _angle_diff(x: F64, y: F64, period: float) -> F64:
    """``nuscenes.eval.common.utils.angle_diff``, vectorised."""
    diff = (x - y + period / 2) % period - period / 2
    return np.where(diff > np.pi, diff - 2 * np.pi, diff)


@dataclass(frozen=True)
class _ClassMatches:
    """The predictions of one class (kept by the filters), grouped by GT sample index, in each sample in its
    list order, and their greedy matches at every threshold.

    start, count (S,): slice of each sample's predictions; score (P,); tp (T, P) bool; err (T, 5, P) the five
    errors of ``_ERRORS`` of matched predictions (NaN otherwise and where the devkit gives NaN).
    """

    start: NDArray[np.int64]
    count: NDArray[np.int64]
    score: F64
    tp: NDArray[np.bool_]
    err: F64


@dataclass(frozen=True)
class _Prepared:
    """GT and predictions reduced to what accumulating any resampling of the samples needs.

    tokens: the GT sample order; pred_order (S,): GT index of each prediction sample in the predictions' order;
    npos (S, C): filtered GT boxes per sample and class; classes: C `_ClassMatches`.
    """

    cfg: DetectionConfig
    tokens: tuple[str, ...]
    pred_order: NDArray[np.int64]
    npos: NDArray[np.int64]
    classes: tuple[_ClassMatches, ...]


def _greedy(dist: F64, order: NDArray[np.int64], th: float) -> NDArray[np.int64]:
    """The devkit's greedy matching in one sample: predictions in ``order`` each take the closest untaken GT
    (first on ties), a match if closer than ``th``. dist (P, G) [m]. Returns (P,) GT index or -1."""
    match = np.full(dist.shape[0], -1, dtype=np.int64)
    free = np.ones(dist.shape[1], dtype=bool)
    n_free = dist.shape[1]
    for p in order:
        if n_free == 0:
            break
        row = np.where(free, dist[p], np.inf)
        g = int(np.argmin(row))
        if row[g] < th:
            match[p] = g
            free[g] = False
            n_free -= 1
    return match


def _match_class(gt: _Flat, pred: _Flat, c: int, cfg: DetectionConfig, n_samples: int,
                 pred_to_gt: NDArray[np.int64]) -> _ClassMatches:
    ths = list(cfg.dist_ths)
    gsel = np.flatnonzero(gt.keep & (gt.label == c))
    psel = np.flatnonzero(pred.keep & (pred.label == c))
    psample = pred_to_gt[pred.sample[psel]]
    # group predictions by GT sample index, keeping list order within a sample (stable sort)
    psel = psel[np.argsort(psample, kind="stable")]
    psample = pred_to_gt[pred.sample[psel]]
    count = np.bincount(psample, minlength=n_samples).astype(np.int64)
    start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
    n = len(psel)
    tp = np.zeros((len(ths), n), dtype=bool)
    err = np.full((len(ths), len(_ERRORS), n), np.nan)
    gsample = gt.sample[gsel]
    period = np.pi if DETECTION_CLASSES[c] == "barrier" else 2 * np.pi
    for s in np.flatnonzero(count):
        p_idx = psel[start[s]:start[s] + count[s]]
        g_idx = gsel[gsample == s]
        if len(g_idx) == 0:
            continue
        dist = np.linalg.norm(pred.xy[p_idx][:, None, :] - gt.xy[g_idx][None, :, :], axis=-1)
        scores = pred.score[p_idx]
        local = np.arange(len(p_idx))
        order = np.lexsort((-local, -scores))  # descending score, ties: later prediction first (as the devkit)
        for t, th in enumerate(ths):
            match = _greedy(dist, order, th)
            m = np.flatnonzero(match >= 0)
            if len(m) == 0:
                continue
            pi, gi = p_idx[m], g_idx[match[m]]
            cols = start[s] + m
            tp[t, cols] = True
            err[t, 0, cols] = dist[m, match[m]]
            err[t, 1, cols] = np.linalg.norm(pred.vel[pi] - gt.vel[gi], axis=1)
            inter = np.prod(np.minimum(pred.size[pi], gt.size[gi]), axis=1)
            union = np.prod(gt.size[gi], axis=1) + np.prod(pred.size[pi], axis=1) - inter
            err[t, 2, cols] = 1 - inter / union
            err[t, 3, cols] = np.abs(_angle_diff(gt.yaw[gi], pred.yaw[pi], period))
            gattr = gt.attr[gi]
            err[t, 4, cols] = np.where(gattr < 0, np.nan, 1.0 - (gattr == pred.attr[pi]))
    return _ClassMatches(start=start, count=count, score=pred.score[psel], tp=tp, err=err)


def _prepare(gt: EvalBoxes, pred: EvalBoxes, cfg: DetectionConfig, apply_filters: bool = True) -> _Prepared:
    """Check that ``pred`` covers exactly the GT samples, filter both (unless not ``apply_filters``), and match
    every class once."""
    gtf = _flatten(gt, cfg, "ground truth", apply_filters)
    pf = _flatten(pred, cfg, "predictions", apply_filters)
    index = {t: i for i, t in enumerate(gtf.tokens)}
    unknown = [t for t in pf.tokens if t not in index]
    if unknown:
        raise ValueError(f"predictions for {len(unknown)} sample(s) not in the ground truth, e.g. {unknown[0]!r}")
    missing = set(gtf.tokens) - set(pf.tokens)
    if missing:
        raise ValueError(f"{len(missing)} ground-truth sample(s) have no prediction entry (give an empty one), e.g. "
                         f"{sorted(missing)[0]!r}")
    counts = np.bincount(pf.sample, minlength=len(pf.tokens))
    if len(counts) and counts.max() > cfg.max_boxes_per_sample:
        worst = int(np.argmax(counts))
        raise ValueError(f"sample {pf.tokens[worst]} has {counts[worst]} predictions; the nuScenes evaluation allows "
                         f"at most {cfg.max_boxes_per_sample} per sample")
    pred_to_gt = np.array([index[t] for t in pf.tokens], dtype=np.int64)
    n = len(gtf.tokens)
    npos = np.zeros((n, len(DETECTION_CLASSES)), dtype=np.int64)
    np.add.at(npos, (gtf.sample[gtf.keep], gtf.label[gtf.keep]), 1)
    classes = tuple(_match_class(gtf, pf, c, cfg, n, pred_to_gt) for c in range(len(DETECTION_CLASSES)))
    return _Prepared(cfg=cfg, tokens=gtf.tokens, pred_order=pred_to_gt, npos=npos, classes=classes)


def _gather(cm: _ClassMatches, draws: NDArray[np.int64]) -> NDArray[np.int64]:
    """Indices of the class's predictions of the drawn samples, sample after sample in draw order."""
    counts = cm.count[draws]
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    offsets = np.cumsum(counts) - counts
    return np.repeat(cm.start[draws] - offsets, counts) + np.arange(total)


def _cummean(x: F64) -> F64:
    """``nuscenes.eval.common.utils.cummean`` (NaN-ignoring running mean; all NaN -> ones) without its Python-level
    ``sum`` over the array."""
    valid = ~np.isnan(x)
    if not valid.any():
        return np.ones(len(x))
    sums = np.nancumsum(x.astype(float))
    counts = np.cumsum(valid)
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts != 0)


def _metric_data(conf: F64, tp: NDArray[np.bool_], err: F64 | None, npos: int) -> DetectionMetricData:
    """The tail of the devkit's ``accumulate``: sorted confidences (P,), TP flags (P,), errors (5, P) or None
    (errors set to 1: for thresholds whose TP errors are not used) -> interpolated metric data."""
    if npos == 0 or not tp.any():
        return DetectionMetricData.no_predictions()
    tpc = np.cumsum(tp).astype(float)
    fpc = np.cumsum(~tp).astype(float)
    prec = tpc / (fpc + tpc)
    rec = tpc / float(npos)
    rec_interp = np.linspace(0, 1, DetectionMetricData.nelem)
    prec_i = np.interp(rec_interp, rec, prec, right=0)
    conf_i = np.interp(rec_interp, rec, conf, right=0)
    errors: dict[str, F64] = {}
    if err is None:
        errors = {k: np.ones(DetectionMetricData.nelem) for k in _ERRORS}
    else:
        match_conf = conf[tp][::-1]
        for k, key in enumerate(_ERRORS):
            tmp = _cummean(err[k, tp])
            errors[key] = np.interp(conf_i[::-1], match_conf, tmp[::-1])[::-1]
    return DetectionMetricData(recall=rec_interp, precision=prec_i, confidence=conf_i, **errors)


def _class_metric_data(prep: _Prepared, c: int, draws: NDArray[np.int64],
                       thresholds: Sequence[int], with_errors: Sequence[int]) -> dict[int, DetectionMetricData]:
    """Metric data of class ``c`` at the given threshold indices for the samples ``draws`` (GT indices, in the
    order the devkit would enumerate them; duplicates allowed); errors only at ``with_errors``."""
    npos = int(prep.npos[draws, c].sum())
    if npos == 0:
        return {t: DetectionMetricData.no_predictions() for t in thresholds}
    cm = prep.classes[c]
    idx = _gather(cm, draws)
    scores = cm.score[idx]
    order = np.lexsort((-np.arange(len(idx)), -scores))  # the devkit: descending (score, position)
    idx = idx[order]
    conf = scores[order]
    return {t: _metric_data(conf, cm.tp[t, idx], cm.err[t][:, idx] if t in with_errors else None, npos)
            for t in thresholds}


def accumulate(gt: EvalBoxes, pred: EvalBoxes, class_name: str, dist_th: float) -> DetectionMetricData:
    """Equivalent of ``nuscenes.eval.detection.algo.accumulate(gt, pred, class_name, center_distance, dist_th)``:
    boxes taken as given (no range or point filter); every prediction sample must be a GT sample and vice versa;
    ``dist_th`` one of the config's thresholds [m]."""
    cfg = detection_config()
    ths = list(cfg.dist_ths)
    if dist_th not in ths:
        raise ValueError(f"dist_th {dist_th} is not one of the thresholds {ths}")
    if class_name not in _CLASS_INDEX:
        raise ValueError(f"unknown class {class_name!r}; expected one of {DETECTION_CLASSES}")
    prep = _prepare(gt, pred, cfg, apply_filters=False)
    t = ths.index(dist_th)
    return _class_metric_data(prep, _CLASS_INDEX[class_name], prep.pred_order, [t], [t])[t]


def _with(box: DetectionBox, **changes: Any) -> DetectionBox:
    """A copy of ``box`` with some constructor arguments changed."""
    args = box.serialize()
    args.update(changes)
    return DetectionBox(**args)


# ----------------------------------------------------------------------------------------------------- scoring


@dataclass(frozen=True)
class DetectionScores:
    """nuScenes detection metrics of one evaluation.

    Attributes:
        map, nds: the standard mAP and NDS over all ten classes (absent classes count AP 0 and error 1).
        map_present: mAP over `classes_present` (NaN if none), the classes with at least one GT box after
            filtering: with 8 of 10 classes present the standard mAP is capped at 0.8.
        tp_errors: mean TP errors over classes (devkit names ``trans_err`` ... ``attr_err``).
        per_class_ap: class -> AP averaged over the four thresholds; per_class_ap_by_threshold: class ->
            threshold [m] -> AP.
        per_class_tp: class -> devkit TP metric name -> error (NaN where the metric does not apply).
        metrics: the devkit's ``DetectionMetrics``.
    """

    map: float
    nds: float
    map_present: float
    classes_present: tuple[str, ...]
    tp_errors: dict[str, float]
    per_class_ap: dict[str, float]
    per_class_ap_by_threshold: dict[str, dict[float, float]]
    per_class_tp: dict[str, dict[str, float]]
    metrics: DetectionMetrics = field(repr=False, compare=False)

    def as_dict(self) -> dict[str, Any]:
        """JSON-able form: ``map``, ``nds``, ``map_present`` (None if NaN), ``classes_present``, ``mate``, ``mase``,
        ``maoe``, ``mave``, ``maae``, ``per_class_ap`` {class: AP}, ``per_class_ap_by_threshold`` {class:
        {"0.5": AP, ...}}, ``per_class_tp`` {class: {"ate": err, ..., "aae": err}} (None where not applicable)."""
        def num(v: float) -> float | None:
            return None if math.isnan(v) else float(v)

        out: dict[str, Any] = {"map": self.map, "nds": self.nds, "map_present": num(self.map_present),
                               "classes_present": list(self.classes_present)}
        out.update({"m" + TP_SHORT[k]: self.tp_errors[k] for k in TP_METRICS})
        out["per_class_ap"] = dict(self.per_class_ap)
        out["per_class_ap_by_threshold"] = {c: {str(th): ap for th, ap in d.items()}
                                            for c, d in self.per_class_ap_by_threshold.items()}
        out["per_class_tp"] = {c: {TP_SHORT[k]: num(v) for k, v in d.items()} for c, d in self.per_class_tp.items()}
        return out


def _scores(prep: _Prepared, draws: NDArray[np.int64]) -> DetectionScores:
    """Scores of the samples ``draws`` (GT indices, devkit enumeration order, duplicates allowed)."""
    cfg = prep.cfg
    ths = list(cfg.dist_ths)
    t_tp = ths.index(cfg.dist_th_tp)
    metrics = DetectionMetrics(cfg)
    per_class_tp: dict[str, dict[str, float]] = {}
    for c, name in enumerate(DETECTION_CLASSES):
        mds = _class_metric_data(prep, c, draws, range(len(ths)), [t_tp])
        for t, th in enumerate(ths):
            metrics.add_label_ap(name, th, calc_ap(mds[t], cfg.min_recall, cfg.min_precision))
        for metric in TP_METRICS:
            tp = np.nan if metric in _NO_TP.get(name, ()) else calc_tp(mds[t_tp], cfg.min_recall, metric)
            metrics.add_label_tp(name, metric, tp)
        per_class_tp[name] = {m: float(metrics.get_label_tp(name, m)) for m in TP_METRICS}
    present = tuple(name for c, name in enumerate(DETECTION_CLASSES) if prep.npos[draws, c].sum() > 0)
    per_class_ap = {name: float(v) for name, v in metrics.mean_dist_aps.items()}
    map_present = float(np.mean([per_class_ap[c] for c in present])) if present else math.nan
    return DetectionScores(map=float(metrics.mean_ap), nds=float(metrics.nd_score), map_present=map_present,
                           classes_present=present, tp_errors=dict(metrics.tp_errors), per_class_ap=per_class_ap,
                           per_class_ap_by_threshold={c: {th: float(metrics.get_label_ap(c, th)) for th in ths}
                                                      for c in DETECTION_CLASSES},
                           per_class_tp=per_class_tp, metrics=metrics)


def _summary(prep: _Prepared, draws: NDArray[np.int64]) -> tuple[float, float, float]:
    """(mAP, NDS, mAP over present classes) of the samples ``draws``: `_scores` without building the devkit's
    ``DetectionMetricData`` / ``DetectionMetrics`` objects (the same arithmetic as its ``accumulate`` tail,
    ``calc_ap``, ``calc_tp`` and ``DetectionMetrics.mean_ap`` / ``nd_score``, in the same order; tested equal), for
    the thousands of bootstrap replicates, where the objects' construction was most of the time."""
    cfg = prep.cfg
    ths = list(cfg.dist_ths)
    t_tp = ths.index(cfg.dist_th_tp)
    first = round(100 * cfg.min_recall) + 1
    rec_interp = np.linspace(0, 1, DetectionMetricData.nelem)
    n_classes = len(DETECTION_CLASSES)
    aps = np.zeros((n_classes, len(ths)))
    tps = np.ones((n_classes, len(TP_METRICS)))
    for c, name in enumerate(DETECTION_CLASSES):
        npos = int(prep.npos[draws, c].sum())
        if npos > 0:
            cm = prep.classes[c]
            idx = _gather(cm, draws)
            scores = cm.score[idx]
            order = np.lexsort((-np.arange(len(idx)), -scores))
            idx, conf = idx[order], scores[order]
            for t in range(len(ths)):
                tp = cm.tp[t, idx]
                if not tp.any():
                    continue  # the devkit's no_predictions(): AP 0, TP errors 1
                tpc = np.cumsum(tp).astype(float)
                fpc = np.cumsum(~tp).astype(float)
                rec = tpc / float(npos)
                prec = np.interp(rec_interp, rec, tpc / (fpc + tpc), right=0)[first:] - cfg.min_precision
                prec[prec < 0] = 0
                aps[c, t] = float(np.mean(prec)) / (1.0 - cfg.min_precision)
                if t != t_tp:
                    continue
                conf_i = np.interp(rec_interp, rec, conf, right=0)
                nonzero = np.nonzero(conf_i)[0]
                last = nonzero[-1] if len(nonzero) else 0
                if last < first:
                    continue
                match_conf, err = conf[tp][::-1], cm.err[t][:, idx]
                for k, key in enumerate(_ERRORS):
                    curve = np.interp(conf_i[::-1], match_conf, _cummean(err[k, tp])[::-1])[::-1]
                    tps[c, TP_METRICS.index(key)] = float(np.mean(curve[first: last + 1]))
        for metric in _NO_TP.get(name, ()):
            tps[c, TP_METRICS.index(metric)] = np.nan
    per_class = [np.mean(aps[c]) for c in range(n_classes)]
    mean_ap = float(np.mean(per_class))
    tp_scores = [max(0.0, 1.0 - float(np.nanmean(np.ascontiguousarray(tps[:, m])))) for m in range(len(TP_METRICS))]
    nds = float(cfg.mean_ap_weight * mean_ap + np.sum(tp_scores)) / float(cfg.mean_ap_weight + len(TP_METRICS))
    present = [float(per_class[c]) for c in range(n_classes) if prep.npos[draws, c].sum() > 0]
    return mean_ap, nds, float(np.mean(present)) if present else math.nan


def score(gt: EvalBoxes, pred: EvalBoxes) -> DetectionScores:
    """nuScenes detection scores (``detection_cvpr_2019``) of ``pred`` against ``gt``, both global-frame
    ``DetectionBox`` es with ``ego_translation`` set (`ground_truth`, `predictions_to_eval_boxes`).

    Equal to the devkit's ``DetectionEval.evaluate`` except that the bike-rack filter is not applied. Neither
    input is modified.

    Raises:
        ValueError: a prediction sample not in ``gt`` or a GT sample without a prediction entry (naming one), more
            than 500 predictions in a sample, non-positive sizes.
    """
    prep = _prepare(gt, pred, detection_config())
    return _scores(prep, prep.pred_order)


def resample(boxes: EvalBoxes, tokens: Sequence[str]) -> EvalBoxes:
    """The samples ``tokens`` (repeats allowed) of ``boxes`` as a new ``EvalBoxes``: the k-th occurrence (k >= 1) of a
    token is renamed ``<token>#k`` (boxes copied with the new ``sample_token``), so that duplicates are distinct
    samples. The definition of a bootstrap replicate (`bootstrap_intervals` computes the same without copying)."""
    out = EvalBoxes()
    seen: dict[str, int] = {}
    for token in tokens:
        if token not in boxes.boxes:
            raise ValueError(f"resample: sample {token!r} not in the boxes")
        k = seen.get(token, 0)
        seen[token] = k + 1
        name = token if k == 0 else f"{token}#{k}"
        out.add_boxes(name, [b if k == 0 else _with(b, sample_token=name) for b in boxes[token]])
    return out


def _metric(s: DetectionScores, metric: str) -> float:
    return float(getattr(s, metric))


def _percentile_interval(values: F64, confidence: float) -> list[float]:
    """[lo, hi] percentiles of the finite ``values`` (NaN where none) enclosing ``confidence`` of them."""
    finite = values[np.isfinite(values)]
    if len(finite) == 0:
        return [math.nan, math.nan]
    lo, hi = np.percentile(finite, [50 * (1 - confidence), 50 * (1 + confidence)])
    return [float(lo), float(hi)]


def _check_bootstrap(n_boot: int, confidence: float) -> None:
    if n_boot < 1:
        raise ValueError(f"n_boot {n_boot} must be >= 1")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence {confidence} must lie in (0, 1)")


def _draws(n_samples: int, n_boot: int, seed: int) -> NDArray[np.int64]:
    """(n_boot, n_samples) sample indices drawn with replacement."""
    if n_samples == 0:
        raise ValueError("no samples to bootstrap")
    return np.random.default_rng(seed).integers(0, n_samples, size=(n_boot, n_samples))


def bootstrap_intervals(gt: EvalBoxes, pred: EvalBoxes, n_boot: int = DEFAULT_BOOTSTRAP, seed: int = 0,
                        confidence: float = 0.95) -> tuple[list[float], list[float], list[float]]:
    """Frame-bootstrap percentile intervals of mAP, NDS and mAP over present classes.

    Each replicate draws the GT samples with replacement (``numpy.random.default_rng(seed)``), duplicates as
    distinct samples (as `resample`), and rescores (`_summary`); matches are computed once (see the module
    docstring), so a replicate costs only the rescoring. Replicates where no class is present are left out of the
    ``map_present`` interval.

    Returns:
        ([lo, hi] of mAP, [lo, hi] of NDS, [lo, hi] of map_present) at ``confidence``.
    """
    _check_bootstrap(n_boot, confidence)
    prep = _prepare(gt, pred, detection_config())
    values = np.array([_summary(prep, d) for d in _draws(len(prep.tokens), n_boot, seed)])
    return (_percentile_interval(values[:, 0], confidence), _percentile_interval(values[:, 1], confidence),
            _percentile_interval(values[:, 2], confidence))


def paired_difference(gt: EvalBoxes, pred_a: EvalBoxes, pred_b: EvalBoxes, metric: Metric = "map",
                      n_boot: int = DEFAULT_BOOTSTRAP, seed: int = 0,
                      confidence: float = 0.95) -> tuple[float, list[float]]:
    """``metric(pred_a) - metric(pred_b)`` on the same samples, with a paired frame-bootstrap percentile interval
    (both scored on the same resampled samples in every replicate). An interval excluding 0 says the difference
    exceeds the sampling noise of the evaluation set.

    Args:
        metric: "map", "nds" or "map_present".

    Returns:
        (difference, [lo, hi]).
    """
    return paired_differences(gt, pred_a, pred_b, (metric,), n_boot, seed, confidence)[metric]


def paired_differences(gt: EvalBoxes, pred_a: EvalBoxes, pred_b: EvalBoxes,
                       metrics: Sequence[Metric] = ("map", "nds"), n_boot: int = DEFAULT_BOOTSTRAP, seed: int = 0,
                       confidence: float = 0.95) -> dict[str, tuple[float, list[float]]]:
    """`paired_difference` for several metrics from one set of bootstrap replicates (each metric's result equals
    `paired_difference` of that metric alone: the draws depend on the seed only)."""
    for metric in metrics:
        if metric not in ("map", "nds", "map_present"):
            raise ValueError(f"unknown metric {metric!r}; expected 'map', 'nds' or 'map_present'")
    _check_bootstrap(n_boot, confidence)
    cfg = detection_config()
    prep_a, prep_b = _prepare(gt, pred_a, cfg), _prepare(gt, pred_b, cfg)
    scores_a, scores_b = _scores(prep_a, prep_a.pred_order), _scores(prep_b, prep_b.pred_order)
    # replicates enumerate samples in draw order for both models (the point estimate in each model's own order)
    reps = np.array([np.subtract(_summary(prep_a, d), _summary(prep_b, d))
                     for d in _draws(len(prep_a.tokens), n_boot, seed)], dtype=np.float64).reshape(n_boot, 3)
    out = {}
    for metric in metrics:
        column = ("map", "nds", "map_present").index(metric)
        diff = _metric(scores_a, metric) - _metric(scores_b, metric)
        out[metric] = (float(diff), _percentile_interval(reps[:, column], confidence))
    return out


def scene_blocks(scene_of_sample: Sequence[str], block: int) -> list[NDArray[np.int64]]:
    """The val samples (in their order, each scene's frames consecutive and in time order) cut into blocks of at most
    ``block`` consecutive frames of one scene: the units a block bootstrap resamples (neighbouring frames of a scene
    share objects and weather, so they are not independent draws)."""
    if block < 1:
        raise ValueError(f"block = {block}; expected >= 1 frame")
    blocks: list[NDArray[np.int64]] = []
    start = 0
    for i in range(1, len(scene_of_sample) + 1):
        if i == len(scene_of_sample) or scene_of_sample[i] != scene_of_sample[start] or i - start == block:
            blocks.append(np.arange(start, i, dtype=np.int64))
            start = i
    return blocks


def _block_draws(blocks: Sequence[NDArray[np.int64]], n_boot: int, rng: np.random.Generator
                 ) -> list[NDArray[np.int64]]:
    """``n_boot`` replicates of ``len(blocks)`` blocks drawn with replacement, concatenated into sample indices."""
    return [np.concatenate([blocks[b] for b in rng.integers(0, len(blocks), len(blocks))]) for _ in range(n_boot)]


@dataclass(frozen=True)
class SeedBlockEstimate:
    """A metric averaged over training seeds with its seed x block bootstrap interval: ``value`` the mean over the
    seeds, ``per_seed`` each seed's value, ``ci`` [lo, hi] at the confidence asked."""

    value: float
    per_seed: list[float]
    ci: list[float]

    def as_dict(self) -> dict[str, Any]:
        return {"value": self.value, "per_seed": self.per_seed, "ci": self.ci}


def seed_block_bootstrap(gt: EvalBoxes, preds_a: Sequence[EvalBoxes], preds_b: Sequence[EvalBoxes] | None,
                         blocks: Sequence[NDArray[np.int64]], metrics: Sequence[Metric] = ("map", "nds"),
                         n_boot: int = DEFAULT_BOOTSTRAP, seed: int = 0, confidence: float = 0.95
                         ) -> dict[str, SeedBlockEstimate]:
    """``metric(a)`` (or ``metric(a) - metric(b)`` on the same samples) averaged over training seeds, with an
    interval that holds both the training noise and the evaluation set's sampling noise: each replicate draws the
    seeds with replacement and the scene blocks (`scene_blocks`) with replacement, and averages the drawn seeds'
    values on the drawn samples (a two-level bootstrap).

    Args:
        preds_a: one prediction set per training seed; preds_b: None (the metric of a), or the seeds' predictions
            of the model subtracted, paired seed by seed (same length as ``preds_a``, or one: subtracted from each).
        blocks: sample indices (into ``gt``'s sample order) of each block.
    """
    _check_bootstrap(n_boot, confidence)
    if not preds_a or (preds_b is not None and len(preds_b) not in (1, len(preds_a))):
        raise ValueError(f"seed_block_bootstrap: {len(preds_a)} prediction sets of a and "
                         f"{len(preds_b or [])} of b; expected b to have as many as a, or one")
    cfg = detection_config()
    prep_a = [_prepare(gt, p, cfg) for p in preds_a]
    prep_b = None if preds_b is None else [_prepare(gt, p, cfg) for p in preds_b]
    columns = [("map", "nds", "map_present").index(m) for m in metrics]

    def value(k: int, draws: NDArray[np.int64] | None) -> NDArray[np.float64]:
        a = prep_a[k]
        va = np.array(_summary(a, a.pred_order if draws is None else draws))
        if prep_b is None:
            return va
        b = prep_b[k if len(prep_b) > 1 else 0]
        return va - np.array(_summary(b, b.pred_order if draws is None else draws))

    per_seed = np.array([value(k, None) for k in range(len(prep_a))])
    rng = np.random.default_rng(seed)
    reps = np.array([np.mean([value(k, draws) for k in rng.integers(0, len(prep_a), len(prep_a))], axis=0)
                     for draws in _block_draws(blocks, n_boot, rng)])
    return {m: SeedBlockEstimate(float(np.mean(per_seed[:, c])), [float(v) for v in per_seed[:, c]],
                                 _percentile_interval(reps[:, c], confidence)) for m, c in zip(metrics, columns)}


def resistance_ability(nds_weather: float, nds_clean: float) -> float:
    """MultiCorrupt's resistance ability ``RA = NDS_weather / NDS_clean`` (1: no loss under the weather).

    Raises:
        ValueError: ``nds_clean`` not positive, or a value outside [0, 1] or NaN.
    """
    for name, v in (("nds_weather", nds_weather), ("nds_clean", nds_clean)):
        if not (0.0 <= v <= 1.0):
            raise ValueError(f"{name} = {v}; expected an NDS in [0, 1]")
    if nds_clean <= 0:
        raise ValueError("nds_clean = 0: the resistance ability is undefined")
    return float(nds_weather / nds_clean)


__all__ = ["DEFAULT_BOOTSTRAP", "DetectionScores", "accumulate", "bootstrap_intervals", "detection_config",
           "ego_positions", "ground_truth", "paired_difference", "paired_differences", "predictions_to_eval_boxes",
           "resample", "resistance_ability", "scene_blocks", "score", "seed_block_bootstrap", "SeedBlockEstimate"]
