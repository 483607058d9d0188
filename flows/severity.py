"""Severity sweeps with DVC experiments: ``python -m flows.severity levels | queue | curve``.

A weather's severity is a parameter of params.yaml: the snow rate (``particles.snow.rate_mm_h`` with
``simulate.precipitation_rates: params``), the rain rate (``particles.rain.rate_mm_h``, likewise) or the dense fog's
extinction (``simulate.fog_alpha_dense`` with ``simulate.fog_levels: params``; the light level at a third of it).
`LEVELS` names five nuScenes-C-style levels of each (1 lightest, 5 heaviest; level 3 of snow and 4 of rain are the
paper's 2 and 50 mm/h); any other value works the same through ``-S``.

- ``levels``: the table of named levels and the ``-S`` overrides each sets.
- ``queue --weather snow [--levels 1 3 5] [--targets simulate@snow-aligned ...] [--run]``: one
  ``dvc exp run --queue -n severity-<weather>-<level> -S ...`` per level (``--run``: then ``dvc exp run --run-all``).
  A queued experiment runs in a fresh copy of the repository, and the generated datasets are not in the DVC cache
  (``cache: false``), so it runs every stage its targets need from the world on; to reuse this workspace's world and
  calibration run the levels one at a time in the workspace with ``dvc exp run -S ...`` (printed by ``levels``).
- ``curve --weather snow``: reads the finished experiments through `dvc.api` (``exp_show``, ``params_show``,
  ``metrics_show``) and writes ``reports/severity/<weather>.json`` and ``<weather>.png``: per experiment (and the
  workspace) the severity value against the LiDAR points lost and scattered per keyframe
  (``reports/simulate/<condition>-aligned/metrics.json``) and the pretrained detector's mAP on the aligned and
  unaligned copy (``reports/detect/metrics.json``, where the experiment ran detect). The report stage shows the figure
  when it is there, and ``dvc plots show`` draws the JSON (dvc.yaml's severity plots). ``dvc metrics diff`` /
  ``dvc plots diff`` compare any two experiments' declared metrics and figures stage by stage.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class SeverityLevel:
    """One named level: the weather, its number (1..5), its value in ``unit`` and the params overrides it sets."""

    weather: str
    level: int
    value: float
    unit: str
    overrides: tuple[str, ...]


def _fog(level: int, mor_m: float) -> SeverityLevel:
    alpha = math.log(20.0) / mor_m  # Koschmieder: MOR = ln(20) / alpha
    return SeverityLevel("fog", level, mor_m, "m MOR", (
        "simulate.fog_levels=params", f"simulate.fog_alpha_dense={alpha:.6g}",
        f"simulate.fog_alpha_light={alpha / 3.0:.6g}"))


LEVELS: dict[str, tuple[SeverityLevel, ...]] = {
    "snow": tuple(SeverityLevel("snow", k, r, "mm/h", (f"particles.snow.rate_mm_h={r:g}",
                                                        "simulate.precipitation_rates=params"))
                  for k, r in enumerate((0.5, 1.0, 2.0, 4.0, 8.0), start=1)),
    "rain": tuple(SeverityLevel("rain", k, r, "mm/h", (f"particles.rain.rate_mm_h={r:g}",
                                                        "simulate.precipitation_rates=params"))
                  for k, r in enumerate((5.0, 10.0, 25.0, 50.0, 100.0), start=1)),
    "fog": tuple(_fog(k, m) for k, m in enumerate((1000.0, 500.0, 250.0, 100.0, 50.0), start=1)),
}
"""Five named levels per weather (1 lightest). Fog's value is the dense level's visibility (MOR)."""

CONDITION = {"snow": "snow", "rain": "rain", "fog": "fog_dense"}
"""The condition whose weather copies a weather's curve reads."""


def named_level(weather: str, level: int) -> SeverityLevel:
    """``LEVELS[weather][level - 1]``, or a ValueError naming the known weathers and levels."""
    if weather not in LEVELS:
        raise ValueError(f"weather {weather!r}: expected one of {sorted(LEVELS)}")
    levels = LEVELS[weather]
    if not 1 <= level <= len(levels):
        raise ValueError(f"{weather} level {level}: expected 1..{len(levels)}")
    return levels[level - 1]


def queue_command(level: SeverityLevel, targets: tuple[str, ...] = ()) -> list[str]:
    """The ``dvc exp run --queue`` command line of one level (experiment ``severity-<weather>-<level>``)."""
    cmd = ["dvc", "exp", "run", "--queue", "-n", f"severity-{level.weather}-{level.level}"]
    for override in level.overrides:
        cmd += ["-S", override]
    return cmd + list(targets)


def severity_value(weather: str, params: dict[str, Any]) -> float | None:
    """The severity of ``weather`` in an experiment's params.yaml (its `LEVELS` unit); None where not set there."""
    try:
        if weather == "fog":
            alpha = float(params["simulate"]["fog_alpha_dense"])
            return math.log(20.0) / alpha if params["simulate"]["fog_levels"] == "params" else None
        if params.get("simulate", {}).get("precipitation_rates", "params") != "params":
            return None  # the tuned rate is in force, not the params one
        return float(params["particles"][weather]["rate_mm_h"])
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return None


@dataclass(frozen=True)
class ExperimentFigures:
    """One row of ``dvc exp show`` (the workspace, a commit or an experiment) read through `dvc.api`: its name, rev,
    params.yaml and the two metrics files a severity curve needs (empty where the experiment did not write them)."""

    name: str
    rev: str
    params: dict[str, Any]
    simulate: dict[str, Any]
    detect: dict[str, Any]


UNFINISHED = ("Queued", "Running", "Failed")
"""``dvc exp show`` states whose experiments have no figures to read."""


def _metrics_file(path: str, rev: str | None) -> dict[str, Any]:
    """The metrics file ``path`` at ``rev`` (None: the workspace) as written, or {} where that revision lacks it."""
    import dvc.api

    try:
        return dvc.api.metrics_show(path, rev=rev)
    except Exception:  # noqa: BLE001 - a revision without the file (or unreadable) has no figures for the curve
        return {}


def experiment_figures(weather: str) -> list[ExperimentFigures]:
    """Every finished experiment of ``dvc exp show`` (`dvc.api.exp_show`) with its params and the metrics of
    ``weather``'s aligned simulate variant and of the detect stage (`dvc.api.params_show`, `dvc.api.metrics_show`)."""
    import dvc.api

    condition = CONDITION[weather]
    out = []
    for row in dvc.api.exp_show():
        if row.get("State") in UNFINISHED:
            continue
        rev = row["rev"]
        at = None if rev == "workspace" else rev
        try:
            params = dvc.api.params_show(rev=at)
        except Exception:  # noqa: BLE001 - a revision whose params cannot be read has no severity
            continue
        out.append(ExperimentFigures(row.get("Experiment") or rev, rev, params,
                                     _metrics_file(f"reports/simulate/{condition}-aligned/metrics.json", at),
                                     _metrics_file("reports/detect/metrics.json", at)))
    return out


def curve_rows(experiments: list[ExperimentFigures], weather: str) -> list[dict[str, Any]]:
    """Per experiment with metrics of ``weather``'s condition: its name, rev, severity value, LiDAR points lost and
    scattered per keyframe, and the pretrained detector's mAP on the aligned and unaligned copy (None where the
    experiment has no detect metrics), sorted by severity (lightest first)."""
    condition = CONDITION[weather]
    rows = []
    for e in experiments:
        value = severity_value(weather, e.params)
        if value is None or e.simulate.get("points_lost_per_keyframe") is None:
            continue
        maps = e.detect.get("map") or {}
        rows.append({"experiment": e.name, "rev": e.rev, "severity": value,
                     "points_lost_per_keyframe": e.simulate["points_lost_per_keyframe"],
                     "points_scattered_per_keyframe": e.simulate["points_scattered_per_keyframe"],
                     "map_aligned": maps.get(f"{condition}-aligned"),
                     "map_unaligned": maps.get(f"{condition}-unaligned")})
    unique = {(r["severity"], r["rev"]): r for r in rows}
    return sorted(unique.values(), key=lambda r: (-r["severity"] if weather == "fog" else r["severity"], r["rev"]))


def curve_figure(rows: list[dict[str, Any]], weather: str):
    """Points lost / scattered per keyframe and the detector's mAP (where measured) against the severity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    unit = LEVELS[weather][0].unit
    x = [r["severity"] for r in rows]
    with_map = [r for r in rows if r["map_aligned"] is not None]
    fig, axes = plt.subplots(1, 2 if with_map else 1, figsize=(11 if with_map else 5.5, 4), squeeze=False)
    ax = axes[0, 0]
    ax.plot(x, [r["points_lost_per_keyframe"] for r in rows], "o-", label="lost")
    ax.plot(x, [r["points_scattered_per_keyframe"] for r in rows], "s-", label="scattered (weather echoes)")
    ax.set_xlabel(f"{weather} severity [{unit}]")
    ax.set_ylabel("LiDAR points per keyframe")
    ax.set_title(f"{CONDITION[weather]}-aligned: what the weather does to the LiDAR")
    ax.legend()
    if with_map:
        ax = axes[0, 1]
        xm = [r["severity"] for r in with_map]
        ax.plot(xm, [r["map_aligned"] for r in with_map], "o-", label="aligned copy")
        ax.plot(xm, [r["map_unaligned"] for r in with_map], "s--", label="unaligned copy")
        ax.set_xlabel(f"{weather} severity [{unit}]")
        ax.set_ylabel("mAP (pretrained on clear)")
        ax.set_title("detector under the weather")
        ax.legend()
    if weather == "fog":  # heavier fog = lower visibility: read right to left
        for a in axes[0]:
            a.invert_xaxis()
    fig.tight_layout()
    return fig


def _dvc(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["dvc", *args], cwd=Path.cwd(), capture_output=True, text=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("levels", help="print the named levels")
    q = sub.add_parser("queue", help="queue one DVC experiment per level")
    q.add_argument("--weather", required=True, choices=sorted(LEVELS))
    q.add_argument("--levels", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    q.add_argument("--targets", nargs="*", default=[], help="stages to run (default: the whole pipeline)")
    q.add_argument("--run", action="store_true", help="then run the queue (dvc exp run --run-all)")
    c = sub.add_parser("curve", help="the severity curve of the finished experiments")
    c.add_argument("--weather", required=True, choices=sorted(LEVELS))
    c.add_argument("--out", type=Path, default=Path("reports") / "severity")
    args = parser.parse_args(argv)
    try:
        if args.command == "levels":
            print("| weather | level | value | dvc exp run -S ... |\n| --- | ---: | ---: | --- |")
            for levels in LEVELS.values():
                for lv in levels:
                    print(f"| {lv.weather} | {lv.level} | {lv.value:g} {lv.unit} | "
                          f"{' '.join('-S ' + o for o in lv.overrides)} |")
            return 0
        if args.command == "queue":
            for k in args.levels:
                cmd = queue_command(named_level(args.weather, k), tuple(args.targets))
                done = _dvc(*cmd[1:])
                if done.returncode != 0:
                    print(f"{' '.join(cmd)} failed:\n{done.stderr}", file=sys.stderr)
                    return 1
                print(" ".join(cmd))
            if args.run:
                done = subprocess.run(["dvc", "exp", "run", "--run-all"], cwd=Path.cwd())
                return done.returncode
            return 0
        rows = curve_rows(experiment_figures(args.weather), args.weather)
        if not rows:
            print(f"no experiment with {CONDITION[args.weather]}-aligned metrics and a {args.weather} severity in "
                  f"dvc exp show (queue some: python -m flows.severity queue --weather {args.weather})",
                  file=sys.stderr)
            return 2
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from weatheralign import atomic

    args.out.mkdir(parents=True, exist_ok=True)
    atomic.write_json(args.out / f"{args.weather}.json", {"weather": args.weather, "unit": LEVELS[args.weather][0].unit,
                                                           "condition": CONDITION[args.weather], "rows": rows},
                      indent=2)
    fig = curve_figure(rows, args.weather)
    fig.savefig(args.out / f"{args.weather}.png", dpi=110)
    for r in rows:
        print(f"{r['experiment']:>28}  {r['severity']:>8g}  lost/keyframe {r['points_lost_per_keyframe']:9.1f}  "
              f"scattered/keyframe {r['points_scattered_per_keyframe']:9.1f}  mAP aligned {r['map_aligned']}")
    print(f"wrote {args.out / (args.weather + '.json')} and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
