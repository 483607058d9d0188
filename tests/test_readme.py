"""The README is reference documentation: short, navigable, and true to the code and the committed reports."""

from __future__ import annotations

import re
from pathlib import Path

from weatheralign.config import params_tree

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()


def _anchor(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_is_short_with_a_table_of_contents_that_resolves() -> None:
    assert len(README.encode()) <= 15_000
    headings = {_anchor(h) for h in re.findall(r"^##+ (.+)$", README, flags=re.M)}
    contents = README.split("## Contents", 1)[1].split("\n## ", 1)[0]
    anchors = re.findall(r"\]\(#([\w-]+)\)", contents)
    assert len(anchors) >= 8 and set(anchors) <= headings, set(anchors) - headings
    for required in ("quickstart", "your-own-data", "the-pipeline", "limits"):
        assert required in anchors


def test_every_linked_file_exists() -> None:
    links = re.findall(r"\]\(((?!https?:|#)[^)\s]+)\)", README)
    assert links, "the README links its figure and its guides"
    missing = [link for link in links if not (REPO / link).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_quoted_run_cost_matches_the_committed_summary() -> None:
    """The time and disk quoted for `make reproduce` are the committed `reports/summary.md`'s totals."""
    summary = (REPO / "reports" / "summary.md").read_text()
    total = re.search(r"^\| \*\*total\*\* \| ([\d.]+) min \| ([\d.]+) GB \|$", summary, flags=re.M)
    assert total, "reports/summary.md has no cost total"
    quoted = re.search(r"took \*\*([\d.]+) min\*\* and its outputs take \*\*([\d.]+) GB\*\*", README)
    assert quoted, "the README quotes the run's time and disk"
    assert quoted.groups() == total.groups()


def test_commands_modules_and_make_targets_exist() -> None:
    for module in set(re.findall(r"python -m ((?:flows|benchmarks)\.\w+)", README)):
        assert (REPO / (module.replace(".", "/") + ".py")).exists(), module
    for name in set(re.findall(r"`(bench_\w+)`", README)):
        assert (REPO / "benchmarks" / f"{name}.py").exists(), name
    makefile = (REPO / "Makefile").read_text()
    targets = set(re.findall(r"^([\w-]+):", makefile, flags=re.M))
    for target in set(re.findall(r"\bmake ([\w-]+)", README)):
        assert target in targets, f"make {target}"


def test_every_quoted_params_key_exists() -> None:
    """Every ``section.key`` the README quotes is a key of params.yaml or of a setup file it names (configs/)."""
    params = params_tree(REPO / "params.yaml")
    keys = [k.rstrip(".") for k in re.findall(r"`(?:-S )?((?:" + "|".join(params) + r")\.[\w.]+)", README)]
    assert len(keys) >= 10
    for key in keys:
        node = params
        for part in key.split("."):
            assert isinstance(node, dict) and part in node, f"README quotes params key {key!r}, not in params.yaml " \
                                                            f"or configs/"
            node = node[part]
