"""Resume fingerprints: the code digest and the input-file stamps change exactly when they must."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from weatheralign.provenance import file_stamps, source_digest


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
