"""Detector benchmark: training step and inference time of the default detector on the default world's cache, and
what a longer training budget buys (val mAP / NDS against training steps, from the detect stage's learning curve).

Run from the repository root after the detect stage has built its caches (``dvc repro detect`` or
``python -m flows.detect``): ``.venv/bin/python -m benchmarks.bench_detect [--steps 30] [--device cpu]``.
Writes ``reports/benchmarks/detect.json``: per workload wall and CPU seconds per step (batch ``detect.batch_size``)
and per inferred sample, samples per second, the parameter count, the torch threads, and the learning curve.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import torch

from weatheralign.atomic import write_json
from weatheralign.config import load_params
from weatheralign.detect.data import Augmentation, DetectionDataset, collate
from weatheralign.detect.model import BEVFusionDetector, count_parameters, train_step
from weatheralign.detect.protocol import detector_config, point_range, resolve_device

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "detect.json"


def train_cache(data: Path) -> Path:
    """The largest cache folder under ``<data>/detect/cache`` (the clean train split after a detect run)."""
    folders = [p.parent for p in (data / "detect" / "cache").glob("*/index.json")]
    if not folders:
        raise SystemExit(f"no detector cache under {data / 'detect' / 'cache'}: run the detect stage first")
    return max(folders, key=lambda p: len(json.loads((p / "index.json").read_text())["tokens"]))


def timed(fn: Any, repeats: int) -> tuple[float, float]:
    """Mean wall and CPU seconds of ``fn()`` over ``repeats`` calls (after one warm-up call)."""
    fn()
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - w0) / repeats, (time.process_time() - c0) / repeats


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--device", default=None, help="default: detect.device of params.yaml")
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    params = load_params(REPO / "params.yaml")
    cfg = params.detect
    device = resolve_device(args.device or cfg.device)
    torch.set_num_threads(params.run.torch_threads)
    dataset = DetectionDataset(train_cache(params.paths.data), Augmentation(), point_range=point_range(cfg))
    batches = [collate([dataset[2 * i], dataset[2 * i + 1]]).to(device) for i in range(4)]
    model = BEVFusionDetector(detector_config(cfg)).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    counter = iter(range(10**9))

    def step() -> None:
        train_step(model, batches[next(counter) % len(batches)], optimizer)
        if device.type == "cuda":
            torch.cuda.synchronize()

    def infer() -> None:
        model.detect(batches[0], cfg.score_threshold, cfg.max_detections)
        if device.type == "cuda":
            torch.cuda.synchronize()

    step_wall, step_cpu = timed(step, args.steps)
    infer_wall, infer_cpu = timed(infer, max(3, args.steps // 3))
    load_wall, load_cpu = timed(lambda: collate([dataset[0], dataset[1]]), 10)
    metrics_path = params.paths.reports / "detect" / "metrics.json"
    curve = json.loads(metrics_path.read_text()).get("learning_curve", []) if metrics_path.is_file() else []
    batch = batches[0].batch_size
    result = {"device": str(device), "torch_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
              "parameters": count_parameters(model), "batch_size": batch, "image_size": list(cfg.image_size),
              "bev_cells": round(2 * cfg.bev_range_m / cfg.bev_cell_m),
              "train_step_seconds": round(step_wall, 4), "train_step_cpu_seconds": round(step_cpu, 4),
              "train_samples_per_second": round(batch / step_wall, 2),
              "inference_seconds_per_sample": round(infer_wall / batch, 4),
              "inference_cpu_seconds_per_sample": round(infer_cpu / batch, 4),
              "load_and_collate_seconds_per_batch": round(load_wall, 4),
              "load_and_collate_cpu_seconds_per_batch": round(load_cpu, 4),
              "learning_curve": curve}
    write_json(args.out, result, indent=2)
    print(json.dumps({k: v for k, v in result.items() if k != "learning_curve"}, indent=1))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
