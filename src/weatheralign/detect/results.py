"""nuScenes detection results files (the devkit's submission format), written for every evaluation of the `detect`
stage and read back to score any detector on a weather copy (`flows.score`).

Format (nuscenes-devkit ``DetectionEval``)::

    {"meta": {"use_camera": bool, "use_lidar": bool, "use_radar": false, "use_map": false, "use_external": bool},
     "results": {sample_token: [{"sample_token", "translation" [m, global], "size" [w, l, h m],
                                 "rotation" (w, x, y, z), "velocity" [vx, vy m/s], "detection_name",
                                 "detection_score", "attribute_name"}, ...], ...}}

Every sample of the evaluated split has an entry (possibly empty); at most 500 boxes a sample.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from nuscenes.eval.common.data_classes import EvalBoxes
from nuscenes.eval.detection.data_classes import DetectionBox

from weatheralign import atomic
from weatheralign.data.errors import DataFormatError
from weatheralign.detect.types import ATTRIBUTES, DETECTION_CLASSES

MAX_BOXES_PER_SAMPLE = 500
_BOX_FIELDS = ("sample_token", "translation", "size", "rotation", "velocity", "detection_name", "detection_score",
               "attribute_name")


def submission(pred: EvalBoxes, use_camera: bool, use_lidar: bool, use_external: bool = True) -> dict[str, Any]:
    """``pred`` (global-frame devkit boxes) as a results dict; ``use_external``: the camera branch starts from
    ImageNet weights, which the nuScenes challenge counts as external data."""
    results = {token: [{k: box.serialize()[k] for k in _BOX_FIELDS} for box in pred[token]]
               for token in pred.sample_tokens}
    return {"meta": {"use_camera": bool(use_camera), "use_lidar": bool(use_lidar), "use_radar": False,
                     "use_map": False, "use_external": bool(use_external)}, "results": results}


def write_submission(path: Path, pred: EvalBoxes, use_camera: bool, use_lidar: bool) -> None:
    """`submission` written atomically to ``path``."""
    atomic.write_text(path, json.dumps(submission(pred, use_camera, use_lidar)))


def _check_box(path: Path, token: str, index: int, box: Any) -> None:
    where = f"{path}: results[{token!r}][{index}]"
    if not isinstance(box, dict):
        raise DataFormatError(f"{where}: a {type(box).__name__}; expected an object with fields {_BOX_FIELDS}")
    missing = [k for k in _BOX_FIELDS if k not in box]
    if missing:
        raise DataFormatError(f"{where}: missing field(s) {missing}; expected {_BOX_FIELDS}")
    lengths = {"translation": 3, "size": 3, "rotation": 4, "velocity": 2}
    for key, n in lengths.items():
        value = box[key]
        if (not isinstance(value, list) or len(value) != n
                or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)):
            raise DataFormatError(f"{where}: field {key!r} = {value!r}; expected {n} finite numbers")
    if not all(v > 0 for v in box["size"]):
        raise DataFormatError(f"{where}: field 'size' = {box['size']}; expected three positive numbers [m]")
    if box["detection_name"] not in DETECTION_CLASSES:
        raise DataFormatError(f"{where}: detection_name {box['detection_name']!r}; expected one of "
                              f"{DETECTION_CLASSES}")
    if box["attribute_name"] not in ("", *ATTRIBUTES):
        raise DataFormatError(f"{where}: attribute_name {box['attribute_name']!r}; expected '' or one of "
                              f"{ATTRIBUTES}")
    score = box["detection_score"]
    if not isinstance(score, (int, float)) or not 0.0 <= score <= 1.0:
        raise DataFormatError(f"{where}: detection_score {score!r}; expected a number in [0, 1]")
    if box["sample_token"] != token:
        raise DataFormatError(f"{where}: sample_token {box['sample_token']!r} differs from its key {token!r}")


def read_submission(path: str | Path, sample_tokens: Sequence[str], ego_position: Mapping[str, Any]
                    ) -> tuple[EvalBoxes, dict[str, Any]]:
    """A results file as devkit boxes, checked against the evaluated split's ``sample_tokens`` (every one present,
    no other), and its meta. Each box's ``ego_translation`` is set to its centre minus the sample's ego position
    (3,) [m] (`weatheralign.detect.evaluate.ego_positions`), as the devkit's ``add_center_dist`` does: without it
    the class range filter would pass everything.

    Raises:
        DataFormatError: unreadable JSON, no ``meta`` / ``results``, missing or unknown sample tokens, a malformed box
            (naming the file, the sample and the field).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path}: cannot read the results file ({type(exc).__name__}: {exc})") from None
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}); expected the nuScenes "
                              "detection results format {'meta': {...}, 'results': {sample_token: [boxes]}}") from None
    if not isinstance(data, dict) or not isinstance(data.get("meta"), dict) or not isinstance(data.get("results"),
                                                                                              dict):
        raise DataFormatError(f"{path}: expected an object with 'meta' (use_camera, use_lidar, ...) and 'results' "
                              "(sample_token -> list of boxes)")
    results = data["results"]
    missing = [t for t in sample_tokens if t not in results]
    extra = sorted(set(results) - set(sample_tokens))
    if missing or extra:
        raise DataFormatError(f"{path}: {len(missing)} sample(s) of the evaluated split missing (e.g. {missing[:2]}) "
                              f"and {len(extra)} unknown (e.g. {extra[:2]}); expected exactly the "
                              f"{len(sample_tokens)} samples of the split, each with a (possibly empty) list")
    for token in sample_tokens:
        boxes = results[token]
        if not isinstance(boxes, list) or len(boxes) > MAX_BOXES_PER_SAMPLE:
            raise DataFormatError(f"{path}: results[{token!r}]: expected a list of at most {MAX_BOXES_PER_SAMPLE} "
                                  "boxes")
        for i, box in enumerate(boxes):
            _check_box(path, token, i, box)
    pred = EvalBoxes()
    for token in sample_tokens:
        ego = [float(v) for v in ego_position[token]]
        pred.add_boxes(token, [DetectionBox.deserialize({
            **box, "detection_score": float(box["detection_score"]),
            "ego_translation": [c - e for c, e in zip(box["translation"], ego)]}) for box in results[token]])
    return pred, data["meta"]


__all__ = ["MAX_BOXES_PER_SAMPLE", "read_submission", "submission", "write_submission"]
