"""The detector as an MLflow pyfunc model, so that ``mlflow.pyfunc.load_model("models:/<name>@latest")`` predicts in
any process with the project's code shipped beside it.

Input (one sample, a dict of arrays; `INPUT_FIELDS`): ``points`` (P, 5) float32 ``x, y, z [m], intensity / 255,
time lag [s]`` in the keyframe LiDAR frame (sweeps aggregated and ego-motion compensated); ``features_s8`` (C, 40,
h, w) and ``features_s16`` (C, 112, h / 2, w / 2) float32 frozen image features of the C cameras
(`weatheralign.detect.image_features`); ``intrinsics`` (C, 3, 3) float32 pinhole matrices of the feature maps'
images [px]; ``cam_to_lidar`` (C, 4, 4) float32 camera -> LiDAR transforms. Output: one row per detection
(`OUTPUT_COLUMNS`): the box ``x, y, z, w, l, h, yaw, vx, vy`` in the LiDAR frame (`weatheralign.detect.types`), its
score, class name and attribute name ("" where none).

The model's weights travel as the stage's checkpoint (tensors only, loaded with ``weights_only``) and its sizes as
JSON: loading runs the shipped code, never unpickles an object.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from mlflow.pyfunc import PythonModel

from tasks.tracking import PyfuncModel
from weatheralign.detect.head import LossWeights
from weatheralign.detect.model import BEVFusionDetector, DetectorConfig
from weatheralign.detect.types import ATTRIBUTES, DETECTION_CLASSES, POINT_DIM, DetectionBatch

PROJECT = Path(__file__).resolve().parents[1]
"""The project's folder: ``src/weatheralign`` and ``tasks/`` ship with each logged detector."""

INPUT_FIELDS: dict[str, int] = {"points": 2, "features_s8": 4, "features_s16": 4, "intrinsics": 3, "cam_to_lidar": 3}
"""The input arrays and their number of dimensions."""
OUTPUT_COLUMNS: tuple[str, ...] = ("x", "y", "z", "w", "l", "h", "yaw", "vx", "vy", "score", "label", "attribute")
EXAMPLE_POINTS = 2048
EXAMPLE_CELLS = (4, 8)  # (rows, cols) of the stride-8 feature map kept in the input example


def config_to_json(config: DetectorConfig) -> str:
    """The detector's sizes as JSON (`config_from_json` reads them back)."""
    return json.dumps(dataclasses.asdict(config), sort_keys=True)


def config_from_json(text: str) -> DetectorConfig:
    """The inverse of `config_to_json`. A model logged before ``pillar_keyframe_only`` existed ran its pillar network
    on every sweep's points, and keeps doing so."""
    fields = json.loads(text)
    fields.setdefault("pillar_keyframe_only", False)
    fields["loss_weights"] = LossWeights(**fields["loss_weights"])
    fields["z_range_m"] = tuple(fields["z_range_m"])
    return DetectorConfig(**fields)


def sample_batch(inputs: dict[str, Any]) -> DetectionBatch:
    """One sample's input arrays (see the module docstring) as a `DetectionBatch` of one.

    Raises:
        ValueError: a missing field or an array of the wrong shape, named.
    """
    missing = [name for name in INPUT_FIELDS if name not in inputs]
    if missing:
        raise ValueError(f"detector input: missing {missing}; expected the arrays {list(INPUT_FIELDS)}")
    arrays = {name: np.asarray(inputs[name], dtype=np.float32) for name in INPUT_FIELDS}
    for name, ndim in INPUT_FIELDS.items():
        if arrays[name].ndim != ndim:
            raise ValueError(f"detector input {name!r}: {arrays[name].ndim} dimensions {arrays[name].shape}, "
                             f"expected {ndim}")
    points, s8, s16 = arrays["points"], arrays["features_s8"], arrays["features_s16"]
    cameras = s8.shape[0]
    if points.shape[1] != POINT_DIM - 1:
        raise ValueError(f"detector input 'points': shape {points.shape}, expected (P, {POINT_DIM - 1}): x, y, z, "
                         "intensity / 255, time lag")
    expected = {"features_s16": (cameras, s16.shape[1], (s8.shape[2] + 1) // 2, (s8.shape[3] + 1) // 2),
                "intrinsics": (cameras, 3, 3), "cam_to_lidar": (cameras, 4, 4)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise ValueError(f"detector input {name!r}: shape {arrays[name].shape}, expected {shape}")
    with_index = np.concatenate([np.zeros((len(points), 1), np.float32), points], axis=1)
    empty = [torch.zeros(0, 9)]
    return DetectionBatch(torch.from_numpy(with_index), torch.zeros(1, cameras, 3, 1, 1),
                          torch.from_numpy(s8)[None], torch.from_numpy(s16)[None],
                          torch.from_numpy(arrays["intrinsics"])[None], torch.from_numpy(arrays["cam_to_lidar"])[None],
                          empty, [torch.zeros(0, dtype=torch.long)], [torch.zeros(0, dtype=torch.long)], ["input"])


def input_example(sample: dict[str, Any]) -> dict[str, np.ndarray]:
    """A small valid input cut from a dataset sample (`weatheralign.detect.data.DetectionDataset` item): every
    k-th point (at most `EXAMPLE_POINTS`) and the centre `EXAMPLE_CELLS` of each camera's feature maps, the
    intrinsics' principal point moved to that crop."""
    points = sample["points"].numpy()[:, :POINT_DIM - 1]
    points = points[::max(1, len(points) // EXAMPLE_POINTS)][:EXAMPLE_POINTS]
    s8, s16 = sample["features_s8"].numpy(), sample["features_s16"].numpy()
    rows, cols = EXAMPLE_CELLS
    r0, c0 = (s8.shape[2] - rows) // 4 * 2, (s8.shape[3] - cols) // 4 * 2  # even: the stride-16 cells align
    intrinsics = sample["intrinsics"].numpy().copy()
    intrinsics[:, 0, 2] -= 8 * c0
    intrinsics[:, 1, 2] -= 8 * r0
    return {"points": np.ascontiguousarray(points, np.float32),
            "features_s8": np.ascontiguousarray(s8[:, :, r0:r0 + rows, c0:c0 + cols], np.float32),
            "features_s16": np.ascontiguousarray(s16[:, :, r0 // 2:(r0 + rows) // 2, c0 // 2:(c0 + cols) // 2],
                                                 np.float32),
            "intrinsics": intrinsics.astype(np.float32),
            "cam_to_lidar": sample["cam_to_lidar"].numpy().astype(np.float32)}


def detections_frame(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, attributes: np.ndarray
                     ) -> pd.DataFrame:
    """Detections (K, 9) boxes, (K,) scores, labels and attributes (-1: none) as rows of `OUTPUT_COLUMNS`."""
    frame = pd.DataFrame(np.asarray(boxes, np.float64).reshape(-1, 9), columns=list(OUTPUT_COLUMNS[:9]))
    frame["score"] = np.asarray(scores, np.float64)
    frame["label"] = [DETECTION_CLASSES[i] for i in labels]
    frame["attribute"] = [ATTRIBUTES[i] if i >= 0 else "" for i in attributes]
    return frame


def predict_frame(model: BEVFusionDetector, inputs: dict[str, Any], params: dict[str, Any] | None = None
                  ) -> pd.DataFrame:
    """``model``'s detections on one sample's ``inputs`` as rows of `OUTPUT_COLUMNS` (params: see
    `DetectorPyfunc`)."""
    params = params or {}
    detections = model.detect(sample_batch(inputs), float(params.get("score_threshold", 0.05)),
                              int(params.get("max_detections", 200)), params.get("modality", "fused"))[0]
    return detections_frame(detections.boxes, detections.scores, detections.labels, detections.attributes)


def detector_pyfunc(model: BEVFusionDetector, checkpoint: Path, example: dict[str, Any], workdir: Path
                    ) -> PyfuncModel:
    """What `tasks.tracking.ChildRun.log_model` logs for a trained detector: `DetectorPyfunc` from code
    (``tasks/detector_pyfunc.py``) with the weights of ``checkpoint`` and ``model``'s sizes (written to
    ``workdir``, which must outlive the logging), the project's code beside it, ``example`` and the model's output
    on it, pinned torch / numpy / pandas / mlflow."""
    import mlflow

    config = workdir / "detector_config.json"
    config.write_text(config_to_json(model.config))
    params = {"score_threshold": 0.05, "max_detections": 200, "modality": "fused"}
    requirements = tuple(f"{name}=={version.split('+')[0]}" for name, version in (
        ("torch", torch.__version__), ("numpy", np.__version__), ("pandas", pd.__version__),
        ("mlflow", mlflow.__version__)))
    return PyfuncModel("detector", PROJECT / "tasks" / "detector_pyfunc.py",
                       {"checkpoint": str(checkpoint), "config": str(config)},
                       (str(PROJECT / "src" / "weatheralign"), str(PROJECT / "tasks")), requirements, example,
                       predict_frame(model, example, params), params,
                       "weatheralign's BEVFusion-style detector; versions are trainings (their run and seed alias)")


class DetectorPyfunc(PythonModel):
    """`weatheralign.detect.model.BEVFusionDetector` behind MLflow's pyfunc interface (see the module docstring).
    Artifacts: ``checkpoint`` (the stage's .pt) and ``config`` (`config_to_json`). Params: ``score_threshold``
    (default 0.05), ``max_detections`` (200), ``modality`` (fused, lidar or camera)."""

    def load_context(self, context: Any) -> None:
        config = config_from_json(Path(context.artifacts["config"]).read_text())
        self.model = BEVFusionDetector(config).eval()
        blob = torch.load(context.artifacts["checkpoint"], map_location="cpu", weights_only=True)  # never code
        self.model.load_state_dict(blob["state_dict"])

    # model_input (one sample's arrays, see the module docstring) carries no type hint: MLflow reads a hint as the
    # input schema and accepts only list[...] there; the signature logged with the model describes it instead
    def predict(self, context: Any, model_input, params: dict[str, Any] | None = None  # noqa: ANN001
                ) -> pd.DataFrame:
        return predict_frame(self.model, model_input, params)
