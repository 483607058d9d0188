"""Stage contracts: dvc.yaml's matrix equals the conditions dict, every stage declares the code its flow imports,
each simulate stage depends only on its condition's media, and a no-op rerun leaves downstream stages up to date."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from weatheralign.conditions import ALIGNMENTS, CONDITIONS
from weatheralign.data.nuscenes import open_nuscenes
from weatheralign.provenance import stage_code

from .conftest import HANG_GUARD_S

REPO = Path(__file__).resolve().parents[1]
DVC = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
PROJECT_PACKAGES = ("weatheralign", "flows", "tasks")


def _module_file(module: str) -> Path | None:
    parts = module.split(".")
    base = REPO / "src" if parts[0] == "weatheralign" else REPO
    path = base.joinpath(*parts)
    if (path / "__init__.py").is_file():
        return path / "__init__.py"
    if path.with_suffix(".py").is_file():
        return path.with_suffix(".py")
    return None


def _imports(path: Path) -> set[str]:
    """Project modules imported anywhere in ``path`` (module level or inside functions), with their parents."""
    tree = ast.parse(path.read_text())
    package = ".".join(path.relative_to(REPO / "src" if "src" in path.parts else REPO).with_suffix("").parts[:-1])
    out: set[str] = set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for name in names:
            if name.split(".")[0] in PROJECT_PACKAGES:
                parts = name.split(".")
                out.update(".".join(parts[:k]) for k in range(1, len(parts) + 1))
    return out


def import_closure(module: str) -> set[Path]:
    """Every project source file that importing ``module`` can execute."""
    seen: set[Path] = set()
    todo = [module]
    while todo:
        path = _module_file(todo.pop())
        if path is None or path in seen:
            continue
        seen.add(path)
        todo.extend(_imports(path))
    return seen


NOT_DEPS = {REPO / "src/weatheralign/__init__.py", REPO / "flows/__init__.py", REPO / "tasks/__init__.py",
            REPO / "flows/prefect_server.py"}
"""Code a stage runs that is no dependency: the packages' empty roots and the Prefect API server's start-up (it
writes no output)."""


def _covered(path: Path, deps: list[str]) -> bool:
    rel = path.relative_to(REPO).as_posix()
    return any(rel == d or rel.startswith(d.rstrip("/") + "/") for d in deps)


@pytest.mark.parametrize("stage", sorted(DVC))
def test_stage_declares_the_code_its_flow_imports(stage: str) -> None:
    cmd = DVC[stage]["cmd"]
    module = re.search(r"python -m ([\w.]+)", cmd).group(1)
    deps = stage_code(stage)
    missing = sorted(p.relative_to(REPO).as_posix() for p in import_closure(module) - NOT_DEPS
                     if not _covered(p, deps))
    assert not missing, f"dvc.yaml stage {stage!r} runs code it does not declare as deps: {missing}"


@pytest.mark.parametrize("stage", sorted(DVC))
def test_stage_declares_no_code_its_flow_does_not_run(stage: str) -> None:
    """An extra code dep reruns the stage (and everything after it) whenever unrelated code changes."""
    module = re.search(r"python -m ([\w.]+)", DVC[stage]["cmd"]).group(1)
    closure = {p.relative_to(REPO).as_posix() for p in import_closure(module)}
    unused = [d for d in stage_code(stage) if not any(f == d or f.startswith(d.rstrip("/") + "/") for f in closure)]
    assert not unused, f"dvc.yaml stage {stage!r} declares code deps its flow never imports: {unused}"


def test_import_closure_sees_lazy_imports() -> None:
    """The closure follows imports inside functions (a check that could not fail otherwise is worthless)."""
    files = {p.relative_to(REPO).as_posix() for p in import_closure("flows.world")}
    assert "src/weatheralign/world/dataset.py" in files and "src/weatheralign/sensors.py" in files
    assert not any(f.startswith("src/weatheralign/calibrate/") for f in files)


def test_simulate_matrix_equals_the_conditions_dict() -> None:
    matrix = DVC["simulate"]["matrix"]
    assert list(matrix["condition"]) == list(CONDITIONS)
    assert tuple(matrix["alignment"]) == ALIGNMENTS


def test_summary_and_media_enumerate_every_condition() -> None:
    """The summary depends on the folder that holds every variant's details (and nothing of its own); the media stage
    writes one file per condition."""
    assert "${paths.reports}/simulate" in DVC["simulate_summary"]["deps"]
    summary_outs = [next(iter(o)) if isinstance(o, dict) else o for o in DVC["simulate_summary"]["outs"]]
    assert not any(o.startswith("${paths.reports}/simulate/") for o in summary_outs)
    variant_outs = [next(iter(o)) if isinstance(o, dict) else o for o in DVC["simulate"]["outs"]]
    assert "${paths.reports}/simulate/${item.condition}-${item.alignment}/details.json" in variant_outs
    media_outs = [next(iter(o)) if isinstance(o, dict) else o for o in DVC["media"]["outs"]]
    expected_outs = [f"${{paths.data}}/media/{c}.json" for c in CONDITIONS] + ["${paths.reports}/media/details.json"]
    assert media_outs == expected_outs


def test_simulate_depends_only_on_its_condition_media() -> None:
    data_deps = [d for d in DVC["simulate"]["deps"] if d.startswith("${paths.data}")]
    assert sorted(data_deps) == ["${paths.data}/manifests/world.json", "${paths.data}/media/${item.condition}.json"]
    # their job is to summarise the other stages' figures (verify: Table 1's re-projection rows are simulate's)
    summaries = ("simulate_summary", "verify", "report")
    assert not any(d.endswith(("metrics.json", "details.json")) for name, s in DVC.items() if name not in summaries
                   for d in s.get("deps", [])), "a stage hands data on through metrics"
    assert not any(d.endswith("metrics.json") for s in DVC.values() for d in s.get("deps", [])), \
        "a stage reads another's headline metrics (read its details.json)"


def test_datasets_are_handed_on_by_manifest_not_by_folder() -> None:
    """The dataset stages' DVC outputs are their manifests (DVC would hash every file of every weather copy and of the
    world: ~10 s per copy, 40 s for the world); `detect` depends on the folder of the manifests, which holds the
    world's and every copy's and nothing else."""
    def outs(stage: str) -> list[str]:  # the data outputs (the reports' details.json aside)
        return [p for o in DVC[stage].get("outs", []) for p in [next(iter(o)) if isinstance(o, dict) else o]
                if not p.startswith("${paths.reports}")]

    assert outs("world") == ["${paths.data}/manifests/world.json"]
    assert outs("simulate") == ["${paths.data}/manifests/simulate-${item.condition}-${item.alignment}.json"]
    detect_data = [d for d in DVC["detect"]["deps"] if d.startswith("${paths.data}")]
    assert detect_data == ["${paths.data}/manifests"]
    in_folder = [p for s in DVC.values() for o in s.get("outs", []) for p in [next(iter(o)) if isinstance(o, dict)
                                                                                else o]
                 if p.startswith("${paths.data}/manifests/")]
    assert sorted(in_folder) == sorted(outs("world") + outs("simulate"))


def _dvc(repo: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}",
           "PYTHONPATH": f"{repo / 'src'}:{repo}", "PREFECT_LOGGING_LEVEL": "WARNING",
           "MLFLOW_TRACKING_URI": f"sqlite:///{repo / 'mlflow.db'}"}
    return subprocess.run([str(Path(sys.executable).parent / "dvc"), *args], cwd=repo, capture_output=True,
                          text=True, timeout=HANG_GUARD_S, env=env)


def _project_repo(repo: Path, params: dict) -> None:
    """A git + DVC project at ``repo``: the code, dvc.yaml and ``params`` (tracking and progress bars off)."""
    repo.mkdir()
    for name in ("src", "flows", "tasks", "configs"):
        shutil.copytree(REPO / name, repo / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("dvc.yaml", ".dvcignore"):  # .dvcignore: numba's caches under __pycache__ are not code changes
        shutil.copy(REPO / name, repo / name)
    params["tracking"]["enabled"] = False
    params["run"]["show_progress"] = False
    (repo / "params.yaml").write_text(yaml.safe_dump(params))
    (repo / ".gitignore").write_text("/data\n/reports\n/mlflow.db\n/mlartifacts\n/.prefect\n")
    for cmd in (["git", "init", "-q"], ["git", "config", "user.email", "t@t"], ["git", "config", "user.name", "t"]):
        subprocess.run(cmd, cwd=repo, check=True)
    assert _dvc(repo, "init", "-q").returncode == 0


@pytest.mark.slow
@pytest.mark.flow
def test_noop_rerun_leaves_downstream_up_to_date(tmp_path: Path) -> None:
    """A forced rerun of `world` that renders nothing rewrites an identical manifest: `dvc status` stays clean for
    the stages after it (they read the manifest, not the world's run-time metrics). A changed world does not."""
    repo = tmp_path / "repo"
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["world"].update({"num_train_scenes": 1, "num_val_scenes": 1, "samples_per_scene": 2,
                            "sweeps_per_sample": 0})
    params["world"]["camera"] = {"image_scale": 0.1}  # over configs/world_rig.yaml's camera
    _project_repo(repo, params)
    run = _dvc(repo, "repro", "particles")
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    manifest = (repo / "data" / "manifests" / "world.json").read_bytes()
    run = _dvc(repo, "repro", "-f", "-s", "world")  # the no-op rerun: every sample resumes
    assert run.returncode == 0, run.stderr[-3000:]
    assert (repo / "data" / "manifests" / "world.json").read_bytes() == manifest
    status = _dvc(repo, "status", "particles")
    assert status.returncode == 0 and "changed" not in status.stdout, status.stdout
    # the check can fail: a different world changes the manifest and particles is out of date
    params["world"]["seed"] = 7
    (repo / "params.yaml").write_text(yaml.safe_dump(params))
    assert _dvc(repo, "repro", "-s", "world").returncode == 0
    status = _dvc(repo, "status", "particles")
    assert "manifests/world.json" in status.stdout and "modified" in status.stdout, status.stdout
    # a failed world run leaves no handoff behind: the next stage cannot run on the previous dataset
    params["world"].update({"source": "nuscenes", "nuscenes_dataroot": str(tmp_path / "absent")})
    (repo / "params.yaml").write_text(yaml.safe_dump(params))
    assert _dvc(repo, "repro", "-s", "world").returncode != 0
    assert not (repo / "data" / "manifests" / "world.json").exists()


@pytest.mark.slow
@pytest.mark.flow
def test_your_own_dataset_through_dvc_repro_and_exp_run(tiny_world, tmp_path: Path) -> None:
    """``world.source: nuscenes`` goes through the same stage graph: `dvc repro` and `dvc exp run -S ...` run the world
    stage on a real-layout nuScenes dataroot (the tiny world without its extras, as a real dataset has none), its
    output folder names the dataset instead of copying it, particles runs on the manifest, then `dvc repro` goes on to
    every weather copy (a small embedded reference for the calibrations): each copy is handed on by its manifest and
    loads in the devkit with the dataset's samples and weather in its scans; the dataset is untouched."""
    import hashlib
    import json

    real = tmp_path / "my_nuscenes"
    shutil.copytree(tiny_world.dataroot, real, ignore=shutil.ignore_patterns("extras", ".progress", ".weatheralign*"))
    before = {str(p.relative_to(real)): hashlib.sha256(p.read_bytes()).hexdigest() for p in real.rglob("*")
              if p.is_file()}
    repo = tmp_path / "repo"
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["world"]["version"] = tiny_world.params.world.version
    params["reference"].update({"frames_per_split": 2})  # as the severity test: a small reference, quick calibrations
    params["reference"].update({"lidar": {"firings_per_ring": 360}, "camera": {"image_scale": 0.25}})
    params["calibrate_fog"].update({"num_bootstrap": 20, "max_nelder_mead": 5, "fine_points": [3, 3],
                                    "camera_frames": 2})
    params["particles"].update({"validation_regions": 1, "validation_max_particles": 20000})
    _project_repo(repo, params)
    subprocess.run(["git", "add", "-A"], cwd=repo, check=True)
    subprocess.run(["git", "commit", "-q", "-m", "init"], cwd=repo, check=True)
    own = ["-S", "world.source=nuscenes", "-S", f"world.nuscenes_dataroot={real}"]
    run = _dvc(repo, "exp", "run", "-s", "world", *own)  # the README's route for a user's dataset
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    manifest = json.loads((repo / "data" / "manifests" / "world.json").read_text())
    assert Path(manifest["dataroot"]).resolve() == real.resolve() and manifest["source"] == "nuscenes"
    assert not (repo / "data" / "world").exists()  # read in place, not copied
    run = _dvc(repo, "repro", "-s", "particles")
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    fields = json.loads((repo / "data" / "particles" / "fields.json").read_text())
    assert sorted(f["scene"] for f in fields["snow"]) == sorted(manifest["scenes"])
    status = _dvc(repo, "status", "world", "particles")
    assert status.returncode == 0 and "changed" not in status.stdout, status.stdout
    run = _dvc(repo, "repro", "simulate_summary")  # on to every weather copy
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    clear = open_nuscenes(real, manifest["version"])
    for condition in CONDITIONS:
        for alignment in ALIGNMENTS:
            handoff = json.loads((repo / "data" / "manifests" / f"simulate-{condition}-{alignment}.json").read_text())
            root = Path(handoff["dataroot"])
            root = root if root.is_absolute() else repo / root
            assert handoff["source"] == "simulate" and root == repo / "data" / "simulate" / f"{condition}-{alignment}"
            copy = open_nuscenes(root, manifest["version"])
            assert [s["token"] for s in copy.sample] == [s["token"] for s in clear.sample]
            lidar = copy.get("sample_data", copy.sample[0]["data"]["LIDAR_TOP"])["filename"]
            assert (root / lidar).read_bytes() != (real / lidar).read_bytes(), (condition, alignment)
    status = _dvc(repo, "status", "simulate_summary")
    assert status.returncode == 0 and "changed" not in status.stdout, status.stdout
    after = {str(p.relative_to(real)): hashlib.sha256(p.read_bytes()).hexdigest() for p in real.rglob("*")
             if p.is_file()}
    assert after == before
