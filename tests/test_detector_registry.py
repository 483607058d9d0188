"""The detector as an MLflow logged model: the pyfunc's input checks, and a registered version that loads by alias in
a fresh process and predicts exactly what the checkpoint's detector predicts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from tasks.detector_model import (
    OUTPUT_COLUMNS,
    config_from_json,
    config_to_json,
    detector_pyfunc,
    input_example,
    predict_frame,
    sample_batch,
)
from weatheralign.detect.model import BEVFusionDetector, DetectorConfig


def _sample(seed: int = 0) -> dict[str, torch.Tensor]:
    """A dataset-like sample: 6 cameras of 128 x 352 px (features 16 x 44 and 8 x 22), 5000 points around the car
    with cars' worth of structure, identity-ish camera poses looking along x."""
    g = torch.Generator().manual_seed(seed)
    points = torch.cat([torch.zeros(5000, 1), (torch.rand(5000, 2, generator=g) - 0.5) * 60,
                        torch.rand(5000, 1, generator=g) * 2 - 1.5, torch.rand(5000, 1, generator=g),
                        torch.randint(0, 3, (5000, 1), generator=g) * 0.05], dim=1)
    intrinsics = torch.tensor([[280.0, 0, 176], [0, 280, 64], [0, 0, 1]]).expand(6, 3, 3).clone()
    cam_to_lidar = torch.eye(4).expand(6, 4, 4).clone()
    cam_to_lidar[:, :3, :3] = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera z along LiDAR x
    cam_to_lidar[:, 2, 3] = 1.5
    return {"points": points, "features_s8": torch.rand(6, 40, 16, 44, generator=g),
            "features_s16": torch.rand(6, 112, 8, 22, generator=g), "intrinsics": intrinsics,
            "cam_to_lidar": cam_to_lidar}


def _detector(seed: int = 0) -> BEVFusionDetector:
    torch.manual_seed(seed)
    model = BEVFusionDetector(DetectorConfig())
    with torch.no_grad():  # a freshly initialised head scores every cell ~0.1: lift it so that boxes come out
        model.head.heatmap.bias.fill_(0.5)
    return model.eval()


def test_config_json_round_trip():
    config = DetectorConfig(motion_sweeps=2, depth_bins=32)
    assert config_from_json(config_to_json(config)) == config
    # a model logged before the option ran its pillar network on every sweep: it keeps doing so
    old = json.loads(config_to_json(config))
    del old["pillar_keyframe_only"]
    assert config.pillar_keyframe_only and not config_from_json(json.dumps(old)).pillar_keyframe_only


def test_input_example_is_a_valid_smaller_input_with_the_crop_in_the_intrinsics():
    sample = _sample()
    example = input_example(sample)
    assert example["points"].shape == (2048, 5) and example["features_s8"].shape == (6, 40, 4, 8)
    assert example["features_s16"].shape == (6, 112, 2, 4)
    r0, c0 = 6, 18  # the centre crop, even offsets
    assert np.array_equal(example["features_s8"], sample["features_s8"][:, :, r0:r0 + 4, c0:c0 + 8].numpy())
    assert np.array_equal(example["features_s16"], sample["features_s16"][:, :, 3:5, 9:13].numpy())
    assert example["intrinsics"][0, 0, 2] == 176 - 8 * c0 and example["intrinsics"][0, 1, 2] == 64 - 8 * r0
    batch = sample_batch(example)
    assert batch.points.shape == (2048, 6) and (batch.points[:, 0] == 0).all()
    frame = predict_frame(_detector(), example)
    assert list(frame.columns) == list(OUTPUT_COLUMNS) and len(frame) > 0


def test_bad_input_is_named():
    example = input_example(_sample())
    with pytest.raises(ValueError, match=r"missing \['cam_to_lidar'\]"):
        sample_batch({k: v for k, v in example.items() if k != "cam_to_lidar"})
    with pytest.raises(ValueError, match=r"'points': shape \(2048, 4\), expected \(P, 5\)"):
        sample_batch({**example, "points": example["points"][:, :4]})
    with pytest.raises(ValueError, match=r"'features_s16': shape \(6, 112, 3, 4\), expected \(6, 112, 2, 4\)"):
        sample_batch({**example, "features_s16": np.zeros((6, 112, 3, 4), np.float32)})


@pytest.mark.flow
def test_a_registered_detector_loads_by_alias_in_a_fresh_process_and_predicts_as_its_checkpoint(tmp_path: Path):
    from mlflow.tracking import MlflowClient

    from tasks.tracking import ChildRun

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    experiment = client.create_experiment("registry-test", artifact_location=(tmp_path / "mlartifacts").as_uri())
    model = _detector()
    checkpoint = tmp_path / "pretrained.pt"
    torch.save({"state_dict": model.state_dict(), "meta": {}}, checkpoint)
    example = input_example(_sample())
    with ChildRun(client, client.create_run(experiment).info.run_id) as run:
        logged = run.log_model(detector_pyfunc(model, checkpoint, example, tmp_path),
                               "weatheralign-detector-pretrained", ("seed0",))
        run.log_metrics({"map": 0.25}, model_id=logged.model_id, dataset=("clean/val", "0123abcd"))
    assert logged is not None and logged.version == "1"
    version = client.get_model_version_by_alias("weatheralign-detector-pretrained", "seed0")
    assert str(version.version) == "1" and version.source == f"models:/{logged.model_id}"
    logged_model = client.get_logged_model(logged.model_id)
    assert logged_model.source_run_id == version.run_id
    assert [(m.key, m.value, m.dataset_name, m.dataset_digest) for m in logged_model.metrics] == [
        ("map", 0.25, "clean/val", "0123abcd")]  # the evaluation, linked to the model and the data it scored

    np.savez(tmp_path / "example.npz", **example)
    script = (
        "import json, sys, numpy as np, mlflow\n"
        f"mlflow.set_tracking_uri({uri!r})\n"
        "model = mlflow.pyfunc.load_model('models:/weatheralign-detector-pretrained@latest')\n"
        "assert model.metadata.signature is not None and model.metadata.saved_input_example_info is not None\n"
        f"example = dict(np.load({str(tmp_path / 'example.npz')!r}))\n"
        "assert len(model.predict(model.input_example)) > 0\n"
        "print(model.predict(example, params={'score_threshold': 0.05}).to_json(orient='split'))\n")
    # a fresh interpreter outside the project: what it imports comes from the model's own code
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    payload = json.loads(proc.stdout.strip().splitlines()[-1])
    loaded = pd.DataFrame(payload["data"], columns=payload["columns"])
    expected = predict_frame(model, example)
    assert len(loaded) == len(expected) > 0 and list(loaded.columns) == list(OUTPUT_COLUMNS)
    assert np.allclose(loaded[list(OUTPUT_COLUMNS[:10])].to_numpy(), expected[list(OUTPUT_COLUMNS[:10])].to_numpy(),
                       atol=1e-5)
    assert list(loaded["label"]) == list(expected["label"])
