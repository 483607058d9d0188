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
