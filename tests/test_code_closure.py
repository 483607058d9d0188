"""The code a record is made by (weatheralign.code_closure): a module's import closure, read from its import
statements, and the fingerprint detect keys its models with, which no edit of the weather's code changes."""

from __future__ import annotations

from pathlib import Path

import pytest

from weatheralign.code_closure import closure_digest, closure_fingerprint, imported_modules
from weatheralign.config import params_from_dict
from weatheralign.provenance import PACKAGE_ROOT


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
    of the readers it goes through changes it; the stage's params count by value, config.py's code does not."""
    import shutil

    from weatheralign.detect.protocol import DETECTOR_MODULES

    package = tmp_path / "weatheralign"
    shutil.copytree(PACKAGE_ROOT, package, ignore=shutil.ignore_patterns("__pycache__"))
    parts = imported_modules(*DETECTOR_MODULES, root=package)
    assert {"detect/model.py", "detect/image_features.py", "data/nuscenes.py"} <= set(parts)
    assert not any(p.startswith(("ground/", "simulate/", "lidar/", "camera/", "medium/")) for p in parts)

    def digest() -> str:
        return closure_digest(*DETECTOR_MODULES, root=package)

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
    before = digest()
    with (package / "config.py").open("a") as f:
        f.write("# a param of another stage\n")
    assert digest() == before  # the params are hashed by value
    base = params_from_dict({})
    fingerprint = closure_fingerprint(DETECTOR_MODULES, "detect", base, "world")
    assert closure_fingerprint(DETECTOR_MODULES, "detect", base, "world") == fingerprint
    assert closure_fingerprint(DETECTOR_MODULES, "detect", params_from_dict({"detect": {"batch_size": 4}}),
                               "world") != fingerprint  # the stage's params count
    assert closure_fingerprint(DETECTOR_MODULES, "detect", params_from_dict({"simulate": {"jpeg_quality": 80}}),
                               "world") == fingerprint  # another stage's do not
    assert closure_fingerprint(DETECTOR_MODULES, "detect", base, "another world") != fingerprint
