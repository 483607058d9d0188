"""Shared fixtures: a tiny synthetic world rendered once per test session."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from weatheralign.config import Params, params_from_dict
from weatheralign.world.build import SampleResult
from weatheralign.world.dataset import finalize, render_or_resume, sample_jobs

REPO = Path(__file__).resolve().parents[1]
SHARED_REAL = REPO.parent / "shared" / "data" / "real"

# full-resolution cameras: pixel-exact cross-sensor checks need nuScenes' real pixel size
TINY_WORLD = {"num_train_scenes": 1, "num_val_scenes": 1, "samples_per_scene": 2, "sweeps_per_sample": 2}


@dataclass(frozen=True)
class TinyWorld:
    params: Params
    dataroot: Path
    results: list[SampleResult]
    summary: dict


def tiny_params(data: Path, **world: object) -> Params:
    return params_from_dict({"paths": {"data": str(data), "reports": str(data / "reports")},
                             "tracking": {"enabled": False}, "world": {**TINY_WORLD, **world}})


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory: pytest.TempPathFactory) -> TinyWorld:
    base = tmp_path_factory.mktemp("tiny_world")
    params = tiny_params(base)
    dataroot = base / "world"
    results = [render_or_resume(spec, k, params.world, dataroot)[0] for spec, k in sample_jobs(params.world)]
    summary = finalize(params.world, dataroot, results)
    return TinyWorld(params, dataroot, results, summary)
