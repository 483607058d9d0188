"""Shared fixtures: a tiny synthetic world rendered once per test session."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from weatheralign.config import SETUP_FILES, Params, params_from_dict
from weatheralign.sensors import LidarModel
from weatheralign.world.build import SampleResult
from weatheralign.world.dataset import finalize, render_or_resume, sample_jobs

REPO = Path(__file__).resolve().parents[1]
# Limit on a whole pipeline run inside a test (dvc repro of several stages): a guard against a hang, not a speed
# check: 2-core machines here differ by up to 2x in speed, and 900 s was hit once beside other work.
HANG_GUARD_S = 2400
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


@pytest.fixture(scope="session")
def shared_prefect_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """One Prefect API server for the stages the tests run in subprocesses (``PREFECT_API_URL`` in the environment
    they inherit), on a database of the test session's own: each stage would otherwise start a server of its own.
    A test that needs a stage to start its own server removes ``PREFECT_API_URL`` from the child's environment."""
    if os.environ.get("PREFECT_API_URL"):
        yield os.environ["PREFECT_API_URL"]
        return
    from flows.prefect_server import ApiServer

    home = os.environ.get("PREFECT_HOME")
    os.environ["PREFECT_HOME"] = str(tmp_path_factory.mktemp("prefect_api"))
    server = ApiServer()
    try:
        url = server.start()
    finally:
        if home is None:
            os.environ.pop("PREFECT_HOME")
        else:
            os.environ["PREFECT_HOME"] = home
    os.environ["PREFECT_API_URL"] = url
    try:
        yield url
    finally:
        os.environ.pop("PREFECT_API_URL", None)
        server.stop()


@pytest.fixture(scope="session")
def prefect_home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Prefect home of the test session's own (not the project's ``.prefect``), shared by the tests that run a
    stage in a subprocess on Prefect's ephemeral server: its database is created and migrated once, by the first."""
    return tmp_path_factory.mktemp("prefect_home")


def make_lidar(**overrides: object) -> LidarModel:
    """An HDL-32E-like `LidarModel` for physics tests: 3 mrad divergence, τ_H = 10 ns, 120 m, a constant noise floor
    0.5 on 0..255, a noise-free detector (the published models have none), the intensity model ``255 ρ min(1, 10 m /
    R)`` (the reference's) and the world's firing grid (1085 columns, per-point columns stored). ``overrides``: any
    `LidarModel` field (``floor_range_m`` for a raw-power detector); ``pulse_half_width_s`` / ``pulse`` set the pulse;
    ``max_range_m`` moves the pulse's maximum range too."""
    from weatheralign.config import LidarConfig
    from weatheralign.sensors import lidar_model_from_params, with_overrides

    base = lidar_model_from_params(LidarConfig(
        max_range_m=120.0, range_noise_std_m=0.0, min_detectable_intensity=0.5, floor_range_m=None,
        intensity_scale=255.0, intensity_r_ref_m=10.0, intensity_falloff=1.0))
    pulse = overrides.pop("pulse", None)
    model = with_overrides(base, dict(overrides))
    if pulse is not None:
        from dataclasses import replace

        model = replace(model, pulse=replace(pulse, max_range=model.max_range_m))
    return model


def write_params_file(path: Path, updates: dict) -> Path:
    """The repository's params.yaml with ``updates`` merged in (nested dicts merge key by key), written to ``path``:
    a complete params file (the loader refuses files missing a section) that names the repository's setup files
    (configs/) by their absolute paths; ``updates`` may hold their keys too (they win over the files)."""
    import yaml

    def merge(base: dict, new: dict) -> dict:
        for k, v in new.items():
            base[k] = merge(dict(base.get(k) or {}), v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
        return base

    tree = merge(yaml.safe_load((REPO / "params.yaml").read_text()), updates)
    for section, key in SETUP_FILES:  # a relative path (the repository's, or a dumped section's default): the repo's
        if not Path(tree[section][key]).is_absolute():
            tree[section][key] = str(REPO / tree[section][key])
    path.write_text(yaml.safe_dump(tree))
    return path
