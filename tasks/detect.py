"""Tasks of the `detect` stage: finetuning, prediction and paired-bootstrap jobs, each run in a worker process of its
own."""

from __future__ import annotations

from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.detect.evaluate import paired_differences
from weatheralign.detect.protocol import (PredictJob, TrainJob, detections_to_arrays, run_predict_job,
                                          run_train_job)


@task(name="detect-train", cache_policy=NO_CACHE, retries=0)
def train_task(job: TrainJob) -> dict[str, Any]:
    """Train one model (`TrainJob`) and write its checkpoint; returns the checkpoint's meta."""
    return run_train_job(job)


@task(name="detect-predict", cache_policy=NO_CACHE, retries=0)
def predict_task(job: PredictJob) -> dict[str, Any]:
    """Detections of one model on one val split (`PredictJob`), as flat arrays (`detections_to_arrays`)."""
    return detections_to_arrays(run_predict_job(job))


@task(name="detect-paired", cache_policy=NO_CACHE, retries=0)
def paired_task(gt: Any, pred_a: Any, pred_b: Any, metrics: tuple[str, ...], n_boot: int, seed: int,
                confidence: float) -> dict[str, tuple[float, list[float]]]:
    """`paired_differences` of two models' evaluation boxes on the same val samples (devkit ``EvalBoxes``)."""
    return paired_differences(gt, pred_a, pred_b, metrics, n_boot, seed, confidence)
