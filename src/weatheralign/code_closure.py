"""The code a record is made by, read from import statements: `imported_modules` (a module's import closure within
the package) and `closure_fingerprint` (a resume fingerprint over that code and the stage's params).

`weatheralign.provenance.stage_fingerprint` hashes all the code a stage declares in dvc.yaml. A stage that also
reads other stages' outputs runs code that reaches its records only through those files (`detect` reads the weather
copies and the media): there a record is keyed by the code of the modules that make it, so that an edit of the
simulators does not redo work on unchanged inputs.
"""

from __future__ import annotations

import ast
import hashlib
import json
from pathlib import Path

from weatheralign.provenance import PACKAGE_ROOT, REPO_ROOT, source_digest, stage_params


def imported_modules(*modules: str, root: Path = PACKAGE_ROOT) -> list[str]:
    """The package parts (`weatheralign.provenance.source_digest`'s, e.g. ``"detect/model.py"``) of ``modules``
    (dotted names of the package whose sources lie in ``root``, e.g. ``"weatheralign.detect.protocol"``) and of every
    module of the package they import, transitively, with the packages above each (whose ``__init__`` an import
    runs): read from their ``import`` statements (those inside functions too), not by importing them.

    Raises:
        FileNotFoundError: a module of ``modules`` has no source under ``root``.
    """
    package = Path(root).name

    def source(module: str) -> Path | None:
        path = Path(root).joinpath(*module.split(".")[1:])
        if (path / "__init__.py").is_file():
            return path / "__init__.py"
        return path.with_suffix(".py") if path.with_suffix(".py").is_file() else None

    missing = [m for m in modules if source(m) is None]
    if missing:
        raise FileNotFoundError(f"imported_modules: no source under {root} for {missing}")
    todo, seen = list(modules), {}
    while todo:
        module = todo.pop()
        if module in seen or (path := source(module)) is None:
            continue
        seen[module] = path
        todo += [module.rsplit(".", k)[0] for k in range(1, module.count(".") + 1)]  # importing runs the parents
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == package:
                todo += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                todo += [a.name for a in node.names if a.name.split(".")[0] == package]
    return sorted(str(path.relative_to(root)) for path in seen.values())


def closure_digest(*modules: str, root: Path = PACKAGE_ROOT) -> str:
    """16 hex digits over the code of ``modules`` and what they import (`imported_modules`) but ``config.py``: the
    params a record follows are hashed by value (`closure_fingerprint`), and any stage's param added there would
    otherwise redo every record."""
    return source_digest(*(p for p in imported_modules(*modules, root=root) if p != "config.py"), root=root)


def closure_fingerprint(made_by: tuple[str, ...], stage: str, params: object, *extra: str) -> str:
    """16 hex digits over the code of the modules ``made_by`` (`closure_digest`), the values of the params keys
    ``stage`` declares in dvc.yaml (`weatheralign.provenance.stage_params`) and ``extra`` strings (e.g. an input
    dataset's content digest): what a record made by those modules must match to be resumed. Outside a source tree
    (no dvc.yaml beside the package) no params are hashed, as `weatheralign.provenance.stage_fingerprint` does."""
    tree = params.model_dump(mode="json") if hasattr(params, "model_dump") else {}
    values = {}
    for key in stage_params(stage) if (REPO_ROOT / "dvc.yaml").is_file() else []:
        node = tree
        for part in key.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        values[key] = node
    blob = json.dumps({"code": closure_digest(*made_by), "params": values, "extra": list(extra)}, sort_keys=True,
                      default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


__all__ = ["closure_digest", "closure_fingerprint", "imported_modules"]
