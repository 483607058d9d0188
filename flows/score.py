"""Score any detector's nuScenes results files on a dataroot (a weatheralign weather copy, the clean world, real
nuScenes), with the same metrics and intervals as the `detect` stage.

    python -m flows.score --dataroot data/simulate/snow-aligned --results my_bevfusion.json
    python -m flows.score --dataroot data/simulate/snow-aligned --results seed0.json seed1.json seed2.json \\
        --minus unaligned_seed0.json unaligned_seed1.json unaligned_seed2.json

``--results``: one file per training seed of the model (the devkit's submission format, every sample of the split);
the estimate is the mean over them with a seed x scene-block bootstrap interval. ``--minus``: the same for a second
model (or the same model on another copy: aligned vs unaligned), paired sample by sample: the difference and its
interval. Scoring equals the devkit's ``DetectionEval`` (``detection_cvpr_2019``); on a dataroot with bike-rack
annotations (real nuScenes) the devkit's bike-rack filter is applied to the ground truth and the predictions as well.
The weather copies share the clean world's annotations, so one results file per copy is scored against the same
boxes. Errors end in one line naming the file and the field.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from contextlib import redirect_stdout
from io import StringIO
from pathlib import Path
from typing import Any

from weatheralign import atomic
from weatheralign.data.errors import DataFormatError
from weatheralign.data.nuscenes import open_nuscenes
from weatheralign.detect.data import scene_split
from weatheralign.detect.evaluate import (
    detection_config,
    ego_positions,
    ground_truth,
    scene_blocks,
    seed_block_bootstrap,
)
from weatheralign.detect.results import read_submission

BIKE_RACK = "static_object.bicycle_rack"


def has_bike_racks(nusc: Any) -> bool:
    """Whether any annotation of the dataset is a bicycle rack (then the devkit's bike-rack filter matters)."""
    racks = {c["token"] for c in nusc.category if c["name"] == BIKE_RACK}
    return bool(racks) and any(i["category_token"] in racks for i in nusc.instance)


def devkit_filter(nusc: Any, boxes: Any) -> Any:
    """The devkit's ``filter_eval_boxes`` (class ranges, boxes without points, bikes in bike racks)."""
    from nuscenes.eval.common.loaders import filter_eval_boxes

    with redirect_stdout(StringIO()):
        return filter_eval_boxes(nusc, boxes, detection_config().class_range, verbose=False)


def score_files(dataroot: Path, version: str, split: str, results: Sequence[Path], minus: Sequence[Path] | None,
                block: int, n_boot: int, seed: int, confidence: float) -> dict[str, Any]:
    """mAP and NDS of ``results`` (one file per seed) on ``split`` of ``dataroot`` (or their difference from
    ``minus``) with seed x scene-block bootstrap intervals; the dict printed and written by `main`."""
    nusc = open_nuscenes(dataroot, version)
    tokens = scene_split(nusc, dataroot, version, split)
    gt = ground_truth(nusc, tokens)
    ego = ego_positions(nusc, tokens)
    racks = has_bike_racks(nusc)
    if racks:
        gt = devkit_filter(nusc, gt)

    def load(paths: Sequence[Path]) -> list[Any]:
        preds = [read_submission(p, tokens, ego)[0] for p in paths]
        return [devkit_filter(nusc, p) for p in preds] if racks else preds

    blocks = scene_blocks([nusc.get("sample", t)["scene_token"] for t in tokens], block)
    estimates = seed_block_bootstrap(gt, load(results), load(minus) if minus else None, blocks, ("map", "nds"),
                                     n_boot, seed, confidence)
    return {"dataroot": str(dataroot), "split": split, "samples": len(tokens), "results": [str(p) for p in results],
            "minus": [str(p) for p in minus] if minus else None, "bike_rack_filter": racks,
            "confidence": confidence, "bootstrap": n_boot, "scene_block": block,
            **{m: e.as_dict() for m, e in estimates.items()}}


def render(report: dict[str, Any]) -> str:
    what = "difference" if report["minus"] else "value"
    lines = [f"{report['dataroot']} ({report['split']}, {report['samples']} samples, "
             f"{len(report['results'])} seed(s)):",
             f"| metric | {what} | {report['confidence']:.0%} interval | per seed |",
             "| --- | ---: | --- | --- |"]
    for m in ("map", "nds"):
        e = report[m]
        lines.append(f"| {m} | {e['value']:+.4f} | [{e['ci'][0]:+.4f}, {e['ci'][1]:+.4f}] | "
                     f"{', '.join(f'{v:.4f}' for v in e['per_seed'])} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flows.score", description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataroot", type=Path, required=True, help="nuScenes-format dataroot (e.g. a weather copy)")
    parser.add_argument("--results", type=Path, nargs="+", required=True, help="results file(s), one per seed")
    parser.add_argument("--minus", type=Path, nargs="+", help="results file(s) subtracted, paired per seed")
    parser.add_argument("--version", default="v1.0-mini")
    parser.add_argument("--split", default="val", choices=["train", "val"])
    parser.add_argument("--block", type=int, default=8, help="consecutive frames of a scene resampled together")
    parser.add_argument("--bootstrap", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0, help="the bootstrap's seed")
    parser.add_argument("--confidence", type=float, default=0.95)
    parser.add_argument("--out", type=Path, help="also write the scores as JSON here")
    args = parser.parse_args(argv)
    if args.minus and len(args.minus) not in (1, len(args.results)):
        parser.error(f"--minus: {len(args.minus)} files; expected 1 or as many as --results ({len(args.results)})")
    try:
        report = score_files(args.dataroot, args.version, args.split, args.results, args.minus, args.block,
                             args.bootstrap, args.seed, args.confidence)
    except (DataFormatError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(render(report))
    if args.out:
        atomic.write_text(args.out, json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
