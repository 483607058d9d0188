"""The `calibrate_fog` flow end to end on a Seeing Through Fog-layout tree built from the shared real frame.

The tree holds the real HDL-64 scan and stereo-left image as the clear split, and light / dense splits made from them
with known fog (`simulate_fog` on the scan, intensities rounded like a real sensor's; `fog_image` on the image with
dense depth from the scan). The flow reads it through ``reference.source: stf`` and must recover each level's
extinction within one step of the paper's grid, write ``fog_levels.json`` and the metrics. The fog is made and
calibrated through the same LiDAR: the flow estimates the reference's sensor from the clear scans
(`weatheralign.reference.reference_lidar_model`); the facts the fog was made with (detector floor 1.0, the fog model's
τ_H = 20 ns pulse) are given to it as ``reference.sensor_overrides``. Skips without ``../shared``.
"""

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

from flows.calibrate_fog import HEADLINE as CALIBRATE_FOG_HEADLINE
from weatheralign.camera.depth import dense_depth
from weatheralign.camera.fog import estimate_airlight, fog_image
from weatheralign.data.stf import load_stf_frame
from weatheralign.lidar.fog import simulate_fog
from weatheralign.medium.fog import mor_from_alpha
from weatheralign.sensors import PulseSensor

from .conftest import REPO, make_lidar

pytestmark = pytest.mark.usefixtures("shared_prefect_api")  # stages in subprocesses share one Prefect server

STF = REPO.parent / "shared" / "data" / "real" / "stf"
STF_ID = "2019-09-11_19-13-44_00960"
LEVELS = {"light": 0.012, "dense": 0.05}  # hidden extinctions [1/m], off the grid
NOISE_FLOOR = 1.0  # detector floor of the fogged scans (0..255)
PULSE = PulseSensor()  # the fog model's pulse: τ_H = 20 ns


def _stf_tree(root: Path) -> Path:
    frame = load_stf_frame(STF, STF_ID)
    view = frame.cameras["cam_stereo_left"]
    image = view.load_image()
    depth = dense_depth(frame.lidar, view, image).range
    airlight = estimate_airlight([image], [depth])
    for d in ("lidar_hdl64_strongest", "cam_stereo_left_lut", "calib", "splits"):
        (root / d).mkdir(parents=True)
    for name in ("calib_cam_stereo_left.json", "calib_tf_tree_full.json"):
        shutil.copy(STF / name, root / "calib" / name)
    splits = {"clear": [], "light": [], "dense": []}
    for level in splits:
        for k in range(2):
            sample_id = f"2019-09-11_19-13-44_{1000 * (1 + list(splits).index(level)) + k:05d}"
            scan, img = frame.lidar.points, image
            if level != "clear":
                alpha = LEVELS[level]
                lidar = make_lidar(pulse=PULSE, noise_floor=NOISE_FLOOR, range_noise_std_m=0.02)
                fogged = simulate_fog(frame.lidar, alpha, 0.023 * 1.5 / mor_from_alpha(alpha),
                                      lidar=lidar).apply_to(frame.lidar).points.copy()
                fogged[:, 3] = np.rint(fogged[:, 3])
                scan = fogged[fogged[:, 3] >= 1.0]
                img = fog_image(image, depth, alpha, airlight)
            scan.astype("<f4").tofile(root / "lidar_hdl64_strongest" / f"{sample_id}.bin")
            Image.fromarray(img).save(root / "cam_stereo_left_lut" / f"{sample_id}.png")
            splits[level].append(sample_id)
    for level, name in (("clear", "clear"), ("light", "light_fog"), ("dense", "dense_fog")):
        (root / "splits" / f"{name}.txt").write_text(
            "".join(f"{i.rsplit('_', 1)[0]},{i.rsplit('_', 1)[1]}\n" for i in splits[level]))
    return root


@pytest.mark.slow
@pytest.mark.flow
def test_calibrate_fog_flow_on_an_stf_layout_tree(tmp_path: Path) -> None:
    if not STF.exists():
        pytest.skip(f"real sample not available: {STF}")
    root = _stf_tree(tmp_path / "stf")
    data, reports = tmp_path / "data", tmp_path / "reports"
    run = subprocess.run(
        [sys.executable, "-m", "flows.calibrate_fog", "--set", "reference.source=stf", "--set",
         f"reference.stf_root={root}", "--set", f"paths.data={data}", "--set", f"paths.reports={reports}",
         "--set", "tracking.enabled=false", "--set", "run.show_progress=false", "--set",
         "calibrate_fog.num_bootstrap=100", "--set", f"reference.sensor_overrides.noise_floor={NOISE_FLOOR}",
         "--set", f"reference.sensor_overrides.pulse_half_width_s={PULSE.tau_h}"],
        cwd=REPO, capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO), "PREFECT_LOGGING_LEVEL": "WARNING"})
    assert run.returncode == 0, run.stderr[-3000:]
    levels = json.loads((data / "calibrate_fog" / "fog_levels.json").read_text())
    metrics = json.loads((reports / "calibrate_fog" / "details.json").read_text())
    grid = (0.001, 0.005, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1)
    for level, alpha in LEVELS.items():
        lo = max(g for g in grid if g < alpha)
        hi = min(g for g in grid if g > alpha)
        assert lo <= levels[level]["alpha"] <= hi, (level, levels[level])
        m = metrics[level]
        assert m["ks"] < 0.05 and 0.0 <= m["ks_ci_low"] <= m["ks_ci_high"]  # (the percentile band may sit above a ~0 D)
        for key in ("alpha", "beta", "mor", "camera_visibility_ratio", "kid", "kid_backbone"):
            assert key in m
        assert m["kid_backbone"] == "efficientnet_lite0"
        ecdf = json.loads((reports / "calibrate_fog" / f"ecdf_{level}.json").read_text())  # the DVC plot's data
        assert len(ecdf) == 256 and ecdf[-1]["reference"] == ecdf[-1]["simulated"] == ecdf[-1]["clear"] == 1.0
        for key in ("reference", "simulated", "clear"):
            assert all(a[key] <= b[key] for a, b in zip(ecdf, ecdf[1:]))
        # the foggy images' sky is the airlight the tree was fogged with, the clear image's sky's luminance: gain 1
        assert len(levels[level]["airlight_gains"]) == m["airlight_frames"] == 2
        assert levels[level]["airlight_gains"] == pytest.approx([1.0, 1.0], abs=0.02)
    headline = json.loads((reports / "calibrate_fog" / "metrics.json").read_text())
    assert headline == {level: {k: metrics[level][k] for k in CALIBRATE_FOG_HEADLINE} for level in LEVELS}
    assert levels["dense"]["alpha"] > levels["light"]["alpha"]
    for name in ("ecdf_light.png", "ks_grid_dense.png", "camera_dense.png"):
        assert (reports / "calibrate_fog" / name).is_file()
