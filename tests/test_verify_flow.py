"""The `verify` and `calibrate_precipitation` flows end to end on a Seeing Through Fog-layout tree with fog, snow and
rain splits, built from the shared real frame: the clear split is the real HDL-64 scan and stereo-left image; each
weather split is that frame through the condition's media (different particle fields per frame), written like a real
recording (intensities rounded, PNG images). The flow reads it through ``reference.source: stf`` and must write every
metric of the issue's list per condition, the regenerated Table 1 and the figures; the calibration must recover the
rates the snow and rain splits were made at (3 and 60 mm/h) within its interval. Skips without ``../shared``."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from weatheralign.camera.depth import dense_depth
from weatheralign.camera.fog import estimate_airlight
from weatheralign.camera.overcast import Overcast
from weatheralign.conditions import CONDITIONS
from weatheralign.config import ParticlesConfig, load_params
from weatheralign.data.stf import load_stf_frame
from weatheralign.sensors import CameraModel, SensorRig, estimate_lidar_model
from weatheralign.simulate.media import FogLevels
from weatheralign.simulate.observe import observe
from weatheralign.verify.frames import Severity, scene_media

from .conftest import HANG_GUARD_S, REPO

pytestmark = pytest.mark.usefixtures("shared_prefect_api")  # stages in subprocesses share one Prefect server

STF = REPO.parent / "shared" / "data" / "real" / "stf"
STF_ID = "2019-09-11_19-13-44_00960"
SPLITS = {"clear": ("clear", None), "light": ("light_fog", "fog_light"), "dense": ("dense_fog", "fog_dense"),
          "snow": ("snow", "snow"), "rain": ("rain", "rain")}
FRAMES = 3
_SIM = load_params(REPO / "params.yaml").simulate
PARAMS_LIGHT = Overcast(_SIM.overcast_sun_transmittance, _SIM.overcast_zenith_luminance, _SIM.overcast_diffuse_gain,
                        _SIM.overcast_zenith_over_surface).to_dict()  # the light of snow and rain without rates.json
KEYS = ("ks", "ks_ci_low", "ks_ci_high", "kid", "kid_backbone", "camera_visibility_ratio", "reprojection_mean_px",
        "reprojection_max_px", "mmd_aligned", "mmd_unaligned", "mmd_p_aligned", "mmd_p_unaligned", "mmd_difference_p",
        "control_mmd", "control_p")


def _stf_tree(root: Path) -> Path:
    frame = load_stf_frame(STF, STF_ID)
    view = frame.cameras["cam_stereo_left"]
    image = view.load_image()
    depth = dense_depth(frame.lidar, view, image).range
    airlight = estimate_airlight([image], [depth])
    camera = CameraModel("cam_stereo_left", tuple(tuple(r) for r in view.K), view.width, view.height, 0.006)
    lidar = estimate_lidar_model([frame.lidar], rotation_hz=10.0, overrides={"noise_floor": 1.0})  # as the flows do
    rig = SensorRig(lidar=lidar, cameras={"cam_stereo_left": camera})
    severity = Severity(FogLevels({"light": 0.012, "dense": 0.05}, {"light": 0.0012, "dense": 0.005}, "test"),
                        3.0, 60.0, ParticlesConfig())
    for d in ("lidar_hdl64_strongest", "cam_stereo_left_lut", "calib", "splits"):
        (root / d).mkdir(parents=True)
    for name in ("calib_cam_stereo_left.json", "calib_tf_tree_full.json"):
        shutil.copy(STF / name, root / "calib" / name)
    for n, (level, (split_name, condition)) in enumerate(SPLITS.items()):
        lines = []
        for k in range(FRAMES):
            recording, number = "2019-09-11_19-13-44", 1000 * (n + 1) + k
            sample_id = f"{recording}_{number:05d}"
            scan, img = frame.lidar.points, image
            if condition is not None:
                media = scene_media(CONDITIONS[condition], True, sample_id, severity, seed=k)
                weather = observe(frame, {"cam_stereo_left": image}, {"cam_stereo_left": depth}, media, rig, airlight)
                scan = weather.lidar.scan.points.copy()
                scan[:, 3] = np.rint(scan[:, 3])
                img = weather.cameras["cam_stereo_left"].image
            scan[:, :5].astype("<f4").tofile(root / "lidar_hdl64_strongest" / f"{sample_id}.bin")
            Image.fromarray(img).save(root / "cam_stereo_left_lut" / f"{sample_id}.png")
            lines.append(f"{recording},{number:05d}\n")
        (root / "splits" / f"{split_name}.txt").write_text("".join(lines))
    return root


@pytest.mark.slow
@pytest.mark.flow
def test_verify_and_rate_calibration_on_an_stf_layout_tree_with_snow_and_rain(tmp_path: Path) -> None:
    if not STF.exists():
        pytest.skip(f"real sample not available: {STF}")
    root = _stf_tree(tmp_path / "stf")
    data, reports = tmp_path / "data", tmp_path / "reports"
    sets = ["reference.source=stf", f"reference.stf_root={root}", f"paths.data={data}", f"paths.reports={reports}",
            "tracking.enabled=false", "run.show_progress=false", "simulate.fog_levels=params",
            "simulate.precipitation_rates=params", "verify.steps=8",
            "verify.image_hw=[32, 64]", "verify.classifiers=2", "verify.permutations=100", "verify.resamples=20",
            "verify.batch_size=4", "verify.min_train_accuracy=0",  # 8 steps fit nothing: keep every training
            "reference.sensor_overrides.noise_floor=1.0"]
    run = subprocess.run([sys.executable, "-m", "flows.verify", *[a for s in sets for a in ("--set", s)]],
                         cwd=REPO, capture_output=True, text=True, timeout=HANG_GUARD_S,
                         env={**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING"})
    assert run.returncode == 0, run.stderr[-3000:]
    metrics = json.loads((reports / "verify" / "details.json").read_text())
    assert set(metrics["conditions"]) == {"fog_light", "fog_dense", "snow", "rain"}
    headline = json.loads((reports / "verify" / "metrics.json").read_text())  # what DVC compares
    assert headline["control_detected"] == metrics["control_detected"]
    assert headline["snow"] == {k: metrics["conditions"]["snow"][k] for k in ("mmd_difference", "mmd_difference_p")}
    confusion = json.loads((reports / "verify" / "confusion.json").read_text())  # the DVC confusion plot's data
    assert len(confusion) == metrics["classifier_held_out"]
    correct = sum(r["actual"] == r["predicted"] for r in confusion)
    assert correct == round(metrics["classifier_accuracy"] * len(confusion))
    for name, m in metrics["conditions"].items():
        assert all(key in m for key in KEYS), (name, sorted(set(KEYS) - set(m)))
        assert m["frames_reference"] == m["frames_simulated"] == 2  # held out of the classifier's training
        assert 0.0 <= m["ks"] <= 1.0 and m["ks_ci_low"] <= m["ks_ci_high"]
        for key in ("mmd_p_aligned", "mmd_p_unaligned", "mmd_difference_p", "control_p"):
            assert 0.0 < m[key] <= 1.0
        assert m["kid_backbone"] == "efficientnet_lite0"
        assert m["reprojection_mean_px"] is None  # no simulate stage ran in this tree
    assert metrics["severity"] == {"fog_levels": "params", "snow_rate_mm_h": 2.0, "rain_rate_mm_h": 50.0,
                                   "rates": {"snow": "params", "rain": "params"},
                                   "ground_depth_m": {"rain": 0.0005, "snow": 0.05},  # simulate's ground params
                                   "overcast": {kind: PARAMS_LIGHT for kind in ("snow", "rain")}}  # params' light
    assert 0.0 <= metrics["classifier_accuracy"] <= 1.0 and len(metrics["classifier_confusion"]) == 4
    assert metrics["classifiers"] == 2 and len(metrics["classifier_accuracy_each"]) == 2  # the run's ensemble
    assert metrics["classifier_seeds"] == [0, 1] and metrics["classifiers_rejected"] == []
    stored = sorted(p.name for p in (data / "verify" / "classifiers").iterdir())
    assert stored == ["seed0.pt", "seed1.pt"]  # kept for a rerun (test_verify_classifier: they are loaded)
    assert all(0.0 <= a <= 1.0 for a in metrics["classifier_train_accuracy_each"])
    for m in metrics["conditions"].values():
        assert len(m["control_p_each_classifier"]) == len(m["mmd_aligned_each_classifier"]) == 2
        each = m["mmd_aligned_each_classifier"]
        assert min(each) - 1e-9 <= m["mmd_aligned"] <= max(each) + 1e-9  # the mean kernel's: the members' mean
    table = (reports / "verify" / "table.md").read_text()
    assert "| MMD² aligned |" in table and "The paper" in table and "0.2837" in table
    control_row = next(line for line in table.splitlines() if line.startswith("| control: broken pairs |"))
    assert "2 weather classifier(s)" in table and "| MMD² of each classifier alone" in table
    assert control_row.count("[") == 4  # each classifier's p per weather
    for name in ("ecdf.png", "confusion.png", "embedding_snow.png", "permutations_rain.png"):
        assert (reports / "verify" / name).is_file()

    calibrate = subprocess.run([sys.executable, "-m", "flows.calibrate_precipitation",
                                *[a for s in sets[:6] + sets[-1:] + ["calibrate_precipitation.num_bootstrap=100"]
                                  for a in ("--set", s)]],
                               cwd=REPO, capture_output=True, text=True, timeout=HANG_GUARD_S,
                               env={**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING"})
    assert calibrate.returncode == 0, calibrate.stderr[-3000:]
    rates = json.loads((data / "calibrate_precipitation" / "rates.json").read_text())
    for kind, truth in (("snow", 3.0), ("rain", 60.0)):  # the rates the tree's snow and rain were made at
        assert rates[kind]["ci_low"] <= truth <= rates[kind]["ci_high"], rates
        assert abs(rates[kind]["rate_mm_h"] / truth - 1.0) < 0.3, rates
    tuned = json.loads((reports / "calibrate_precipitation" / "details.json").read_text())
    assert tuned["kinds"] == ["snow", "rain"] and not tuned["snow"]["beyond_grid"]
    for kind, thinnest in (("snow", 0.01), ("rain", 0.0001)):  # the tree's weather has no ground: below the grid
        assert rates["ground"][kind]["depth_m"] <= thinnest and tuned[kind]["ground"]["beyond_grid"], rates
    assert (reports / "calibrate_precipitation" / "ground.png").is_file()
    assert (reports / "calibrate_precipitation" / "rates.png").is_file()
