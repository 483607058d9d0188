"""`weatheralign.api.simulate_weather`: a weather copy of a nuScenes-layout dataset in one call, no pipeline."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest

from weatheralign.api import simulate_weather
from weatheralign.config import params_from_dict
from weatheralign.data.nuscenes import open_nuscenes
from weatheralign.simulate.weather_copy import read_weather_record


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file() and ".progress" not in p.parts}


@pytest.fixture(scope="module")
def real_layout(tiny_world, tmp_path_factory) -> Path:
    """The tiny world as a user's dataset: nuScenes' files only (no extras: no exact depth, no per-point records)."""
    root = tmp_path_factory.mktemp("api") / "my_nuscenes"
    shutil.copytree(tiny_world.dataroot, root, ignore=shutil.ignore_patterns("extras", ".progress", ".weatheralign*"),
                    copy_function=os.link)
    return root


def test_a_snow_copy_in_one_call_loads_in_the_devkit_and_is_reproducible(tiny_world, real_layout, tmp_path):
    version = tiny_world.params.world.version
    params = params_from_dict({"world": {"source": "nuscenes", "nuscenes_dataroot": str(real_layout),
                                         "version": version},
                               "particles": {"snow": {"rate_mm_h": 8.0}}, "simulate": {"max_samples": 1}})
    before = _hashes(real_layout)
    summary = simulate_weather(real_layout, "snow", tmp_path / "a", version=version, params=params,
                               show_progress=False)
    assert _hashes(real_layout) == before  # the input is untouched
    clear, copy = open_nuscenes(real_layout, version), open_nuscenes(tmp_path / "a", version)
    assert [s["token"] for s in copy.sample] == [s["token"] for s in clear.sample]
    lidar = copy.get("sample_data", copy.sample[0]["data"]["LIDAR_TOP"])["filename"]
    assert (tmp_path / "a" / lidar).read_bytes() != (real_layout / lidar).read_bytes()
    points = (tmp_path / "a" / lidar).stat().st_size // 20  # nuScenes scans: 5 float32 per point
    labels = read_weather_record(tmp_path / "a", lidar, points)["label"]
    assert (labels == 2).sum() > 0  # snow echoes (label 2: scattered) in the keyframe scan
    assert summary["particles_rendered"] > 0 and summary["num_samples"] == 1
    simulate_weather(real_layout, "snow", tmp_path / "b", version=version, params=params, show_progress=False)
    assert _hashes(tmp_path / "a") == _hashes(tmp_path / "b")  # same params and seed, same bytes


def test_the_output_must_lie_outside_the_dataset(real_layout):
    with pytest.raises(ValueError, match="must lie outside the dataset"):
        simulate_weather(real_layout, "fog_dense", real_layout / "fog")
    with pytest.raises(ValueError, match="expected one of"):
        simulate_weather(real_layout, "hail", real_layout.parent / "hail")
