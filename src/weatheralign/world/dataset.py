"""The synthetic dataset as a whole: the list of sample jobs, resumable rendering, tables and the summary.

A job's records are stored in ``<dataroot>/.progress/`` once all its files exist, tagged with a hash of the world
config; a rerun skips jobs whose record matches, re-renders the rest, and finally removes sensor files that the
tables no longer reference (e.g. after a config change), then the progress records.
"""

from __future__ import annotations

import hashlib
import re
import shutil
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from weatheralign import atomic
from weatheralign.config import WorldConfig
from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import extras_relpath
from weatheralign.provenance import read_resume_record, stage_code_digest, write_resume_record
from weatheralign.world.build import SampleResult, SceneSpec, render_sample, scene_specs
from weatheralign.world.rig import T_EGO_LIDAR, make_cameras
from weatheralign.world.tables import RoadFootprint, SensorCalibration, build_tables, write_dataset_tables

PROGRESS_DIR = ".progress"
SENSOR_DIRS = ("samples", "sweeps", "extras")
OWNER_FILE = ".weatheralign-world"
"""Marks a dataroot the world stage claimed (`claim_dataroot`)."""
OWN_NAME = re.compile(r"^\.?wa-\d+-synthetic-log\d+__")
"""The world's sensor files are ``wa-<seed>-synthetic-log<k>__<channel>__<timestamp>.<ext>`` (atomic temporaries
``.<name>.<random>.tmp``): a file under ``samples/``, ``sweeps/`` or ``extras/`` named otherwise is not ours."""


def _is_ours(dataroot: Path, path: Path, version: str) -> bool:
    """Whether ``path`` (a file under ``dataroot``) is one the world stage writes."""
    rel = path.relative_to(dataroot)
    top = rel.parts[0]
    if rel.as_posix() == OWNER_FILE or top == PROGRESS_DIR:
        return True
    if top in SENSOR_DIRS:
        return bool(OWN_NAME.match(path.name))
    if top == version:
        return len(rel.parts) == 2 and path.suffix == ".json"
    return top == "maps" and path.suffix == ".png"


def claim_dataroot(dataroot: Path, version: str) -> None:
    """Make sure the world stage may render into ``dataroot``: the folder must be absent, empty, or hold only files the
    stage writes (`_is_ours`: its own sensor-file names, its tables and map, its progress records); it then carries
    `OWNER_FILE`. Anything else (a real nuScenes dataroot, a user's files) is refused before a single file is written
    or removed.

    Raises:
        DataFormatError: naming the folder and up to five files that are not the stage's.
    """
    root = Path(dataroot)
    root.mkdir(parents=True, exist_ok=True)
    foreign = sorted(str(p.relative_to(root)) for p in root.rglob("*")
                     if p.is_file() and not _is_ours(root, p, version))
    if foreign:
        raise DataFormatError(
            f"{root}: holds {len(foreign)} file(s) the world stage did not write ({', '.join(foreign[:5])}"
            f"{', ...' if len(foreign) > 5 else ''}): refusing to render into it, nothing was changed. Move them "
            f"away, point paths.data elsewhere, or read a dataset of your own with world.source: nuscenes")
    if not (root / OWNER_FILE).is_file():
        atomic.write_text(root / OWNER_FILE, "written by the weatheralign world stage: it replaces and removes the "
                                             "files it wrote here (and no others)\n")


def config_hash(cfg: WorldConfig) -> str:
    """Hash of everything that changes the rendered files: the world config and the code the `world` stage declares
    in dvc.yaml (`stage_code_digest`, the one declaration of what it runs)."""
    return hashlib.sha256((cfg.model_dump_json() + stage_code_digest("world")).encode()).hexdigest()[:16]


def sample_jobs(cfg: WorldConfig) -> list[tuple[SceneSpec, int]]:
    """Every (scene, keyframe index) of the dataset, in order."""
    return [(spec, k) for spec in scene_specs(cfg) for k in range(cfg.samples_per_scene)]


def _progress_file(dataroot: Path, spec: SceneSpec, sample_index: int) -> Path:
    return dataroot / PROGRESS_DIR / f"{spec.name}_{sample_index:03d}.json"


def load_finished(dataroot: Path, spec: SceneSpec, sample_index: int, cfg: WorldConfig) -> SampleResult | None:
    """The records of a job finished by an earlier run with the same config, if every file it wrote is still there
    with the size and SHA-256 recorded at write time."""
    record = read_resume_record(_progress_file(dataroot, spec, sample_index), config_hash(cfg), dataroot)
    return None if record is None else SampleResult.from_json(record["result"])


def _job_files(result: SampleResult) -> list[str]:
    """The files one job writes: every sensor file and its extras."""
    return [rel for rec in result.lidar + result.cameras for rel in (rec.filename, extras_relpath(rec.filename))]


def render_or_resume(spec: SceneSpec, sample_index: int, cfg: WorldConfig, dataroot: Path,
                     nthreads: int = 0) -> tuple[SampleResult, bool]:
    """Render one job unless an identical earlier run finished it. Returns (records, rendered_now)."""
    done = load_finished(dataroot, spec, sample_index, cfg)
    if done is not None:
        return done, False
    result = render_sample(spec, sample_index, cfg, dataroot, nthreads=nthreads)
    write_resume_record(_progress_file(dataroot, spec, sample_index), config_hash(cfg), dataroot, _job_files(result),
                        {"result": result.to_json()})
    return result, True


def rig_calibration(cfg: WorldConfig) -> list[SensorCalibration]:
    """LIDAR_TOP and the six cameras as calibrated_sensor entries."""
    sensors = [SensorCalibration("LIDAR_TOP", "lidar", T_EGO_LIDAR, None)]
    sensors += [SensorCalibration(c.channel, "camera", c.T_ego_cam, c.K) for c in make_cameras(cfg.camera.image_scale)]
    return sensors


def finalize(cfg: WorldConfig, dataroot: Path, results: Sequence[SampleResult]) -> dict:
    """Write the tables, the map and splits; remove unreferenced sensor files and progress records.

    Returns:
        the dataset summary: num_scenes, num_samples, num_sweeps, num_annotations, class_counts.
    """
    specs = scene_specs(cfg)
    tables = build_tables(cfg.seed, specs, results, rig_calibration(cfg))
    roads = []
    for spec in specs:
        layout = spec.layout(cfg)
        r = layout.road
        roads.append(RoadFootprint(layout.T_global_scene, r.road_half_width, r.crossing_x, r.crossing_half_width,
                                   r.x_extent))
    splits = {"weatheralign_train": [s.name for s in specs if s.split == "train"],
              "weatheralign_val": [s.name for s in specs if s.split == "val"]}
    write_dataset_tables(dataroot, cfg.version, tables, splits, roads)
    _remove_unreferenced(dataroot, tables, cfg.version)
    shutil.rmtree(dataroot / PROGRESS_DIR, ignore_errors=True)
    lidar = [sd for sd in tables["sample_data"] if sd["filename"].startswith(("samples/LIDAR", "sweeps/LIDAR"))]
    categories = {c["token"]: c["name"] for c in tables["category"]}
    inst_cat = {i["token"]: categories[i["category_token"]] for i in tables["instance"]}
    class_counts = Counter(inst_cat[a["instance_token"]] for a in tables["sample_annotation"])
    return {
        "num_scenes": len(tables["scene"]),
        "num_samples": len(tables["sample"]),
        "num_sweeps": sum(1 for sd in lidar if not sd["is_key_frame"]),
        "num_annotations": len(tables["sample_annotation"]),
        "class_counts": dict(sorted(class_counts.items())),
    }


def _remove_unreferenced(dataroot: Path, tables: dict[str, list[dict]], version: str) -> None:
    """Remove the stage's own sensor files (`_is_ours`) that no table references; files of any other name stay."""
    keep = set()
    for sd in tables["sample_data"]:
        keep.add((dataroot / sd["filename"]).resolve())
        keep.add((dataroot / extras_relpath(sd["filename"])).resolve())
    for top in SENSOR_DIRS:
        root = dataroot / top
        if not root.is_dir():
            continue
        for path in root.rglob("*"):
            if path.is_file() and path.resolve() not in keep and _is_ours(dataroot, path, version):
                path.unlink()
