"""Bad nuScenes-format input gives clear errors naming the file/record and what is wrong."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import derived_time_offsets, load_frame, open_nuscenes


def _clone(tiny_world, tmp_path: Path) -> Path:
    """A dataroot with its own copy of the tables and links to the sensor folders of the tiny world."""
    root = tmp_path / "root"
    root.mkdir()
    version = tiny_world.params.world.version
    shutil.copytree(tiny_world.dataroot / version, root / version)
    for folder in ("samples", "sweeps", "extras", "maps"):
        os.symlink(tiny_world.dataroot / folder, root / folder)
    return root


def _edit(root: Path, version: str, table: str, edit) -> None:
    path = root / version / f"{table}.json"
    records = json.loads(path.read_text())
    edit(records)
    path.write_text(json.dumps(records))


def _lidar_record(root: Path, version: str) -> tuple[str, dict]:
    samples = json.loads((root / version / "sample.json").read_text())
    sds = json.loads((root / version / "sample_data.json").read_text())
    key = next(sd for sd in sds if sd["sample_token"] == samples[0]["token"] and sd["is_key_frame"]
               and sd["filename"].startswith("samples/LIDAR_TOP"))
    return samples[0]["token"], key


def test_missing_table_is_named(tiny_world, tmp_path):
    root = _clone(tiny_world, tmp_path)
    (root / tiny_world.params.world.version / "ego_pose.json").unlink()
    with pytest.raises(DataFormatError, match="missing nuScenes tables ego_pose.json"):
        open_nuscenes(root, tiny_world.params.world.version)
    with pytest.raises(DataFormatError, match="no table folder v9"):
        open_nuscenes(root, "v9")


@pytest.mark.parametrize("case, match", [
    ("missing", "missing sensor file"),
    ("escape", "escapes the dataroot"),
    ("absolute", "is absolute"),
    ("truncated", "not a multiple of the record size 20"),
    ("nan", "NaN/inf coordinates"),
    ("empty", r"empty scan \(0 points\)"),
])
def test_bad_lidar_files(tiny_world, tmp_path, case, match):
    version = tiny_world.params.world.version
    root = _clone(tiny_world, tmp_path)
    sample_token, key = _lidar_record(root, version)
    good = np.fromfile(tiny_world.dataroot / key["filename"], dtype=np.float32)
    bad_dir = root / "bad"
    bad_dir.mkdir()
    target = {"missing": "samples/LIDAR_TOP/nope.pcd.bin", "escape": "../../etc/passwd",
              "absolute": "/etc/passwd", "truncated": "bad/trunc.pcd.bin", "nan": "bad/nan.pcd.bin",
              "empty": "bad/empty.pcd.bin"}[case]
    if case == "truncated":
        good[:-2].tofile(bad_dir / "trunc.pcd.bin")
    if case == "empty":
        (bad_dir / "empty.pcd.bin").write_bytes(b"")
    if case == "nan":
        pts = good.reshape(-1, 5).copy()
        pts[7, 1] = np.nan
        pts.tofile(bad_dir / "nan.pcd.bin")
    _edit(root, version, "sample_data",
          lambda recs: [r.update(filename=target) for r in recs if r["token"] == key["token"]])
    nusc = open_nuscenes(root, version)
    with pytest.raises(DataFormatError, match=match) as err:
        load_frame(nusc, sample_token)
    if case in ("truncated", "nan", "empty"):
        assert target.split("/")[-1] in str(err.value)
    if case == "nan":
        assert "row 7" in str(err.value)


def test_missing_camera_image(tiny_world, tmp_path):
    version = tiny_world.params.world.version
    root = _clone(tiny_world, tmp_path)
    sample_token, _ = _lidar_record(root, version)
    _edit(root, version, "sample_data", lambda recs: [r.update(filename="samples/CAM_BACK/gone.jpg") for r in recs
                                                     if r["sample_token"] == sample_token
                                                     and r["filename"].startswith("samples/CAM_BACK/")])
    with pytest.raises(DataFormatError, match="missing sensor file .*gone.jpg"):
        load_frame(open_nuscenes(root, version), sample_token)


@pytest.mark.parametrize("rotation, match", [
    ([1.0, 0.2, 0.0, 0.0], "norm 1.019804"),
    ([1.0, 0.0, 0.0], "expected a finite rotation"),
    ([float("nan"), 0.0, 0.0, 0.0], "expected a finite rotation"),
])
def test_non_rigid_calibration(tiny_world, tmp_path, rotation, match):
    version = tiny_world.params.world.version
    root = _clone(tiny_world, tmp_path)
    sample_token, _ = _lidar_record(root, version)
    sensors = {s["token"]: s["channel"] for s in json.loads((root / version / "sensor.json").read_text())}
    _edit(root, version, "calibrated_sensor", lambda recs: [r.update(rotation=rotation) for r in recs
                                                           if sensors[r["sensor_token"]] == "LIDAR_TOP"])
    with pytest.raises(DataFormatError, match=f"calibrated_sensor of samples/LIDAR_TOP/.*{match}"):
        load_frame(open_nuscenes(root, version), sample_token)


def test_bad_intrinsics(tiny_world, tmp_path):
    version = tiny_world.params.world.version
    root = _clone(tiny_world, tmp_path)
    sample_token, _ = _lidar_record(root, version)
    _edit(root, version, "calibrated_sensor", lambda recs: [r.update(camera_intrinsic=[[1, 0], [0, 1]])
                                                           for r in recs if r["camera_intrinsic"]])
    with pytest.raises(DataFormatError, match=r"camera_intrinsic must be 3x3, got shape \(2, 2\)"):
        load_frame(open_nuscenes(root, version), sample_token)


def test_derived_firing_times_follow_the_clockwise_sweep():
    """Without per-point times (real nuScenes) they come from the azimuth: left first, then front, right, back."""
    pts = np.array([[0, 10, 0], [10, 0, 0], [0, -10, 0], [-10, 0, 0]], np.float32)
    off = derived_time_offsets(np.column_stack([pts, np.zeros((4, 2), np.float32)]), np.eye(4))
    assert np.allclose(off, [-0.05, -0.0375, -0.025, -0.0125])
    # a LiDAR mounted rotated by 90 deg (as in real nuScenes) gives the same times for the same ego directions
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R
    pts_sensor = pts @ R  # R^T p: the same ego directions seen in the rotated sensor frame
    off2 = derived_time_offsets(np.column_stack([pts_sensor, np.zeros((4, 2), np.float32)]), T)
    assert np.allclose(off, off2)
