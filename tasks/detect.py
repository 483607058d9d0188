"""Tasks of the `detect` stage: finetuning, prediction and paired-bootstrap jobs, each run in a worker process of its
own."""

from __future__ import annotations

from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from weatheralign.detect.evaluate import seed_block_bootstrap
from weatheralign.detect.protocol import PredictJob, TrainJob, detections_to_arrays, run_predict_job, run_train_job


@task(name="detect-train", cache_policy=NO_CACHE, retries=0)
def train_task(job: TrainJob) -> dict[str, Any]:
    """Train one model (`TrainJob`) and write its checkpoint; returns the checkpoint's meta."""
    return run_train_job(job)


@task(name="detect-predict", cache_policy=NO_CACHE, retries=0)
def predict_task(job: PredictJob) -> dict[str, Any]:
    """Detections of one model on one val split (`PredictJob`), as flat arrays (`detections_to_arrays`)."""
    return detections_to_arrays(run_predict_job(job))


@task(name="detect-pooled", cache_policy=NO_CACHE, retries=0)
def paired_task(gt: Any, preds_a: list[Any], preds_b: list[Any] | None, blocks: list[Any], metrics: tuple[str, ...],
                n_boot: int, seed: int, confidence: float) -> dict[str, dict[str, Any]]:
    """`seed_block_bootstrap` of one model's evaluations over the seeds (or of their differences from another's)
    on the same val samples (devkit ``EvalBoxes``)."""
    return {m: e.as_dict() for m, e in seed_block_bootstrap(gt, preds_a, preds_b, blocks, metrics, n_boot, seed,
                                                            confidence).items()}
