"""Severity sweeps: the named levels, the queued DVC experiments and the curve read back from ``dvc exp show``."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from flows.severity import LEVELS, ExperimentFigures, curve_rows, named_level, queue_command, severity_value
from weatheralign.config import load_params

from .test_stage_contracts import _dvc, _project_repo

REPO = Path(__file__).resolve().parents[1]


def test_named_levels_are_valid_params_and_grow_in_severity(tmp_path):
    """Every level's overrides load as params (the config validates them) and set the value the level names;
    heavier levels mean more snow / rain and less visibility."""
    for weather, levels in LEVELS.items():
        assert [lv.level for lv in levels] == [1, 2, 3, 4, 5]
        values = [lv.value for lv in levels]
        assert values == sorted(values, reverse=weather == "fog")
        for lv in levels:
            params = load_params(REPO / "params.yaml", list(lv.overrides))
            got = severity_value(weather, params.model_dump(mode="json"))
            assert math.isclose(got, lv.value, rel_tol=1e-5), (weather, lv.level, got)
    assert named_level("snow", 3).value == 2.0 and named_level("rain", 4).value == 50.0  # the paper's rates
    assert queue_command(named_level("rain", 2), ("simulate@rain-aligned",)) == [
        "dvc", "exp", "run", "--queue", "-n", "severity-rain-2", "-S", "particles.rain.rate_mm_h=10", "-S",
        "simulate.precipitation_rates=params", "simulate@rain-aligned"]
    with pytest.raises(ValueError, match="expected 1..5"):
        named_level("snow", 6)
    with pytest.raises(ValueError, match="expected one of"):
        named_level("hail", 1)
    assert severity_value("fog", {"simulate": {"fog_levels": "calibrated", "fog_alpha_dense": 0.04}}) is None
    assert severity_value("snow", {"simulate": {"precipitation_rates": "calibrated"},
                                   "particles": {"snow": {"rate_mm_h": 2.0}}}) is None


def _experiment(name: str, rev: str, rate: float, lost: float, scattered: float,
                maps: tuple[float, float] | None) -> ExperimentFigures:
    return ExperimentFigures(name, rev, {"particles": {"snow": {"rate_mm_h": rate}}},
                             {"points_lost_per_keyframe": lost, "points_scattered_per_keyframe": scattered},
                             {} if maps is None else {"map": {"snow-aligned": maps[0], "snow-unaligned": maps[1]}})


def test_curve_rows_of_the_experiments():
    """The workspace, the baseline and every experiment with the condition's metrics, sorted by severity; an
    experiment without them (or without the param) is left out."""
    experiments = [
        _experiment("workspace", "workspace", 2.0, 10.0, 100.0, None),
        _experiment("main", "abc", 2.0, 10.0, 100.0, None),
        _experiment("severity-snow-5", "e5", 8.0, 50.0, 400.0, (0.2, 0.25)),
        _experiment("severity-snow-1", "e1", 0.5, 2.0, 25.0, (0.3, 0.3)),
        ExperimentFigures("broken", "e9", {"particles": {"snow": {"rate_mm_h": 4.0}}}, {}, {}),
    ]
    rows = curve_rows(experiments, "snow")
    assert [r["experiment"] for r in rows] == ["severity-snow-1", "main", "workspace", "severity-snow-5"]
    assert [r["severity"] for r in rows] == [0.5, 2.0, 2.0, 8.0]
    assert rows[0]["points_lost_per_keyframe"] == 2.0 and rows[-1]["points_scattered_per_keyframe"] == 400.0
    assert rows[-1]["map_unaligned"] == 0.25 and rows[1]["map_aligned"] is None
    assert curve_rows(experiments, "rain") == []


@pytest.mark.slow
@pytest.mark.flow
def test_queued_severity_experiments_and_their_curve(tmp_path: Path) -> None:
    """``dvc exp run --queue`` over two snow levels on a tiny world (up to ``simulate@snow-aligned``): both
    experiments run, ``dvc exp show`` carries their metrics, heavier snow scatters and loses more LiDAR points, and
    ``dvc metrics diff`` sees the difference."""
    repo = tmp_path / "repo"
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["world"].update({"num_train_scenes": 1, "num_val_scenes": 1, "samples_per_scene": 2,
                            "sweeps_per_sample": 1})
    params["world"]["camera"] = {"image_scale": 0.1}  # over configs/world_rig.yaml's camera
    params["reference"].update({"frames_per_split": 2})
    params["reference"]["lidar"] = {"firings_per_ring": 360}  # over configs/reference.yaml's
    params["reference"]["camera"] = {"image_scale": 0.25}  # the dense fog's camera check needs this much image
    params["calibrate_fog"].update({"num_bootstrap": 20, "max_nelder_mead": 5, "fine_points": [3, 3],
                                    "camera_frames": 2})
    params["particles"].update({"validation_regions": 1, "validation_max_particles": 20000})
    params["simulate"]["sweeps"] = 1
    _project_repo(repo, params)
    # the stages' metrics files are git-tracked (cache: false), so each experiment's commit carries them
    (repo / ".gitignore").write_text("/data\n/mlflow.db\n/mlartifacts\n/.prefect\n")
    for cmd in (["git", "add", "-A"], ["git", "commit", "-qm", "project"]):
        subprocess.run(cmd, cwd=repo, check=True, capture_output=True)
    env_python = Path(sys.executable).parent
    for level in (1, 5):
        cmd = queue_command(named_level("snow", level), ("simulate@snow-aligned",))
        done = _dvc(repo, *cmd[1:])
        assert done.returncode == 0, done.stderr[-3000:]
    done = _dvc(repo, "exp", "run", "--run-all")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    status = _dvc(repo, "queue", "status").stdout
    assert "Failed" not in status, status + _dvc(repo, "queue", "logs", "severity-snow-1").stdout[-3000:]
    run = subprocess.run([str(env_python / "python"), "-m", "flows.severity", "curve", "--weather", "snow"],
                         cwd=repo, capture_output=True, text=True, timeout=300,
                         env={**_env(repo), "PATH": f"{env_python}:/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr[-3000:]
    curve = json.loads((repo / "reports" / "severity" / "snow.json").read_text())
    rows = {r["experiment"]: r for r in curve["rows"]}
    assert {"severity-snow-1", "severity-snow-5"} <= set(rows)
    light, heavy = rows["severity-snow-1"], rows["severity-snow-5"]
    assert (light["severity"], heavy["severity"]) == (0.5, 8.0)
    # Hahner's snow: 16x the rate, far fewer but larger flakes (physics.md 3): more echoes and more points lost
    assert heavy["points_scattered_per_keyframe"] > light["points_scattered_per_keyframe"] > 0
    assert heavy["points_lost_per_keyframe"] > light["points_lost_per_keyframe"]
    assert (repo / "reports" / "severity" / "snow.png").stat().st_size > 10_000
    diff = _dvc(repo, "metrics", "diff", "severity-snow-1", "severity-snow-5", "--json")
    assert diff.returncode == 0, diff.stderr[-2000:]
    changed = json.loads(diff.stdout)["reports/simulate/snow-aligned/metrics.json"]
    assert changed["points_scattered_per_keyframe"]["diff"] > 0
    plots = _dvc(repo, "plots", "show", "--json")  # dvc.yaml's severity plot draws the curve's JSON
    assert '"Severity curve, snow' in plots.stdout and '"severity": 8.0' in plots.stdout


def _env(repo: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": f"{repo / 'src'}:{repo}", "PREFECT_LOGGING_LEVEL": "WARNING"}
