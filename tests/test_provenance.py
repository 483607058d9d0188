"""Resume fingerprints: the code digest and the input-file stamps change exactly when they must."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from weatheralign.config import params_from_dict
from weatheralign.provenance import (
    file_stamps,
    imported_modules,
    source_digest,
    stage_fingerprint,
    stage_params,
)


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



def test_imported_modules_follows_the_imports_transitively(tmp_path: Path) -> None:
    """A module's import closure within its package: direct, transitive, ``from package import module``, imports
    inside functions, the packages above each; not the modules nothing imports, nor other packages."""
    pkg = tmp_path / "weatheralign"
    for rel, text in {"__init__.py": "", "a.py": "from weatheralign.b import f\n", "b.py": "import numpy\n\n"
                      "def f():\n    from weatheralign import c\n", "c.py": "import weatheralign.sub.d\n",
                      "sub/__init__.py": "", "sub/d.py": "x = 1\n", "unused.py": "import weatheralign.a\n"}.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    assert imported_modules("weatheralign.a", root=pkg) == ["__init__.py", "a.py", "b.py", "c.py", "sub/__init__.py",
                                                              "sub/d.py"]
    assert imported_modules("weatheralign.sub.d", root=pkg) == ["__init__.py", "sub/__init__.py", "sub/d.py"]
    with pytest.raises(FileNotFoundError, match="weatheralign.nothing"):
        imported_modules("weatheralign.nothing", root=pkg)


def test_a_weather_code_edit_keeps_the_detectors_fingerprint(tmp_path: Path) -> None:
    """detect's models are kept for the code of `DETECTOR_MODULES` and their imports: on a copy of the package an
    edit of the ground's, the LiDAR's or the simulator's code keeps that code's digest, an edit of the detector's or
    of the readers it goes through changes it; the params still count."""
    import shutil

    from weatheralign.detect.protocol import DETECTOR_MODULES
    from weatheralign.provenance import PACKAGE_ROOT

    package = tmp_path / "weatheralign"
    shutil.copytree(PACKAGE_ROOT, package, ignore=shutil.ignore_patterns("__pycache__"))
    parts = imported_modules(*DETECTOR_MODULES, root=package)
    assert {"detect/model.py", "detect/image_features.py", "data/nuscenes.py"} <= set(parts)
    assert not any(p.startswith(("ground/", "simulate/", "lidar/", "camera/", "medium/")) for p in parts)

    def digest() -> str:
        return source_digest(*imported_modules(*DETECTOR_MODULES, root=package), root=package)

    before = digest()
    for weather in ("ground/edit.py", "simulate/observe.py", "lidar/__init__.py", "camera/overcast.py", "viz.py"):
        with (package / weather).open("a") as f:
            f.write("# edited\n")
        assert digest() == before, weather
    for detector in ("detect/model.py", "data/nuscenes.py", "geometry.py"):
        before = digest()
        with (package / detector).open("a") as f:
            f.write("# edited\n")
        assert digest() != before, detector
    base = params_from_dict({})
    fingerprint = stage_fingerprint("detect", base, "world", made_by=DETECTOR_MODULES)
    assert stage_fingerprint("detect", params_from_dict({"detect": {"batch_size": 4}}), "world",
                             made_by=DETECTOR_MODULES) != fingerprint  # the params' values count, not config.py
    assert stage_fingerprint("detect", params_from_dict({"simulate": {"jpeg_quality": 80}}), "world",
                             made_by=DETECTOR_MODULES) == fingerprint
    assert stage_fingerprint("detect", base, "world") != fingerprint  # the whole stage's code
