"""Resume fingerprints: the code digest and the input-file stamps change exactly when they must."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from weatheralign.config import params_from_dict
from weatheralign.provenance import file_stamps, source_digest, stage_fingerprint, stage_params


def _tree(root: Path) -> Path:
    (root / "pkg" / "sub").mkdir(parents=True)
    (root / "pkg" / "a.py").write_text("x = 1\n")
    (root / "pkg" / "sub" / "b.py").write_text("y = 2\n")
    (root / "pkg" / "notes.txt").write_text("not code\n")
    return root / "pkg"


def test_source_digest_follows_code_edits_only(tmp_path: Path) -> None:
    pkg = _tree(tmp_path)
    whole, sub = source_digest(root=pkg), source_digest("sub", root=pkg)
    assert source_digest(root=pkg) == whole and len(whole) == 16
    (pkg / "notes.txt").write_text("edited\n")
    assert source_digest(root=pkg) == whole  # not code
    (pkg / "a.py").write_text("x = 2\n")
    assert source_digest(root=pkg) != whole
    assert source_digest("sub", root=pkg) == sub  # a.py is outside the part
    (pkg / "sub" / "b.py").rename(pkg / "sub" / "c.py")  # same bytes, other name
    assert source_digest("sub", root=pkg) != sub
    with pytest.raises(FileNotFoundError, match="missing_module"):
        source_digest("missing_module", root=pkg)


def test_file_stamps_follow_size_mtime_and_presence(tmp_path: Path) -> None:
    f = tmp_path / "samples" / "x.bin"
    f.parent.mkdir()
    f.write_bytes(b"1234")
    stamp = file_stamps(tmp_path, ["samples/x.bin"])
    assert file_stamps(tmp_path, ["samples/x.bin"]) == stamp
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    touched = file_stamps(tmp_path, ["samples/x.bin"])
    assert touched != stamp
    f.write_bytes(b"12345")
    assert file_stamps(tmp_path, ["samples/x.bin"]) not in (stamp, touched)
    f.unlink()
    assert file_stamps(tmp_path, ["samples/x.bin"]) not in (stamp, touched)


def test_resume_record_verifies_what_it_keeps(tmp_path: Path) -> None:
    from weatheralign.provenance import read_resume_record, write_resume_record

    (tmp_path / "a.bin").write_bytes(b"abc" * 100)
    rec = tmp_path / ".progress" / "job.json"
    written = write_resume_record(rec, "fp1", tmp_path, ["a.bin"], {"result": 7})
    assert read_resume_record(rec, "fp1", tmp_path) == written and written["result"] == 7
    assert read_resume_record(rec, "fp2", tmp_path) is None  # another fingerprint
    (tmp_path / "a.bin").write_bytes(b"abc" * 50)  # truncated
    assert read_resume_record(rec, "fp1", tmp_path) is None
    (tmp_path / "a.bin").write_bytes(b"abd" * 100)  # same size, other bytes
    assert read_resume_record(rec, "fp1", tmp_path) is None
    rec.write_text("{broken")
    assert read_resume_record(rec, "fp1", tmp_path) is None


def test_a_stage_fingerprint_follows_its_declared_params_and_setup_files() -> None:
    """What a resume record must match: the keys the stage declares in dvc.yaml (whole sections or dotted keys) and
    every key of the setup files it declares as deps, and nothing else."""
    keys = stage_params("detect")
    assert "detect" in keys and "simulate.sweeps" in keys and "detect.batch_size" in keys  # a section, a key, a file's
    assert all("." in k or k == "detect" for k in keys)
    simulate = stage_params("simulate")
    assert "simulate.jpeg_quality" in simulate and "simulate.rain_appearance" in simulate
    base = params_from_dict({})
    fingerprint = stage_fingerprint("simulate", base, "world")
    for changed in ({"simulate": {"jpeg_quality": 80}}, {"simulate": {"rain_appearance": "rain_weather_edit"}},
                    {"simulate": {"sweeps": 1}}):
        assert stage_fingerprint("simulate", params_from_dict(changed), "world") != fingerprint, changed
    assert stage_fingerprint("simulate", params_from_dict({"detect": {"lr": 0.1}}), "world") == fingerprint
    assert stage_fingerprint("simulate", base, "another world") != fingerprint
    assert stage_fingerprint("detect", params_from_dict({"detect": {"batch_size": 4}})) != stage_fingerprint(
        "detect", base)


def _imported_modules(package_root: Path, parts: tuple[str, ...]) -> set[str]:
    """Every ``weatheralign`` module the modules of ``parts`` import, transitively (read from their ``import``
    statements, not by importing them)."""
    import ast

    def source(module: str) -> Path | None:
        path = package_root.parent / Path(*module.split("."))
        return path / "__init__.py" if (path / "__init__.py").is_file() else (
            path.with_suffix(".py") if path.with_suffix(".py").is_file() else None)

    todo = []
    for part in parts:
        files = [package_root / part] if part.endswith(".py") else sorted((package_root / part).rglob("*.py"))
        todo += [".".join(("weatheralign", *f.relative_to(package_root).with_suffix("").parts)).removesuffix(
            ".__init__") for f in files]
    seen: set[str] = set()
    while todo:
        module = todo.pop()
        if module in seen or (path := source(module)) is None:
            continue
        seen.add(module)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("weatheralign"):
                todo += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                todo += [a.name for a in node.names if a.name.startswith("weatheralign")]
    return seen


def test_the_detectors_fingerprint_covers_all_the_code_it_runs_and_none_of_the_weathers() -> None:
    """A finished detector model is kept while `DETECTOR_CODE` is unchanged: that code must be everything the
    detector's modules import (but the modules that change no result), and none of the simulators'."""
    from weatheralign.detect.protocol import DETECTOR_CODE
    from weatheralign.provenance import PACKAGE_ROOT

    def inside(module: str) -> bool:
        rel = module.removeprefix("weatheralign.").replace(".", "/")
        return any(rel == p.removesuffix(".py") or rel.startswith(p + "/") or rel == p for p in DETECTOR_CODE)

    imported = _imported_modules(PACKAGE_ROOT, DETECTOR_CODE)
    assert "weatheralign.detect.model" in imported and "weatheralign.data.nuscenes" in imported
    outside = {m for m in imported if not inside(m)}
    assert outside <= {"weatheralign", "weatheralign.atomic", "weatheralign.config", "weatheralign.provenance"}, outside


def test_a_weather_code_edit_keeps_the_detectors_fingerprint(tmp_path: Path) -> None:
    """The detector's code digest over a copy of the package: an edit of the ground's or the simulator's code keeps
    it, an edit of the detector's or of the readers it goes through changes it."""
    import shutil

    from weatheralign.detect.protocol import DETECTOR_CODE
    from weatheralign.provenance import PACKAGE_ROOT

    package = tmp_path / "weatheralign"
    shutil.copytree(PACKAGE_ROOT, package, ignore=shutil.ignore_patterns("__pycache__"))
    digest = source_digest(*DETECTOR_CODE, root=package)
    for weather in ("ground/edit.py", "simulate/observe.py", "lidar/__init__.py", "camera/overcast.py"):
        with (package / weather).open("a") as f:
            f.write("# edited\n")
        assert source_digest(*DETECTOR_CODE, root=package) == digest, weather
    for detector in ("detect/model.py", "data/nuscenes.py", "geometry.py"):
        before = source_digest(*DETECTOR_CODE, root=package)
        with (package / detector).open("a") as f:
            f.write("# edited\n")
        assert source_digest(*DETECTOR_CODE, root=package) != before, detector
    base = params_from_dict({})
    assert stage_fingerprint("detect", base, "world", code=DETECTOR_CODE) != stage_fingerprint(
        "detect", params_from_dict({"detect": {"batch_size": 4}}), "world", code=DETECTOR_CODE)
