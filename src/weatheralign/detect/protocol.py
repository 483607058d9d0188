"""The paper's detection protocol, library side of the `detect` stage: train the detector on a cached dataroot (or
a 30/70 weather/clean mix of two), predict a val split, score it with intervals, keep checkpoints.

Nothing here knows about Prefect, DVC or MLflow; the stage (`flows/detect.py`) decides what to train and evaluate,
resumes finished work and reports. The paper's own figures (BEVFusion on real nuScenes-mini weather) are kept here,
labelled as the paper's, only to be printed beside ours.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from nuscenes.eval.common.data_classes import EvalBoxes
from torch import nn
from torch.utils.data import DataLoader, Dataset, Sampler
from tqdm import tqdm

from weatheralign import atomic
from weatheralign.config import DetectConfig
from weatheralign.detect.data import Augmentation, DetectionDataset, collate, mixed_dataset
from weatheralign.detect.evaluate import bootstrap_intervals, predictions_to_eval_boxes, score
from weatheralign.detect.model import BEVFusionDetector, DetectorConfig, Modality, train_step
from weatheralign.detect.types import SampleDetections

DETECTOR_MODULES: tuple[str, ...] = ("weatheralign.detect.protocol", "weatheralign.detect.data")
"""The modules that cache the data, train, predict and score, with what they import
(`weatheralign.code_closure.imported_modules`): the code a finished model or evaluation is kept for. The weather's
code is not in it: a weather copy reaches a model only through its files, which the cache keys stamp."""

#: The paper's Table 2, BEV-F (BEVFusion) rows: (mAP, NDS) of the pretrained model on real nuScenes-mini with the
#: paper's simulated weather, unaligned vs aligned. The paper's figures, for comparison only.
PAPER_TABLE2: dict[str, dict[str, tuple[float, float]]] = {
    "snow": {"unaligned": (0.4034, 0.4828), "aligned": (0.3943, 0.4752)},
    "rain": {"unaligned": (0.4933, 0.4384), "aligned": (0.4649, 0.5192)},
}
#: The paper's Table 3: (mAP, NDS) on clean nuScenes-mini and on its weather copy, per model. The paper's figures.
PAPER_TABLE3: dict[str, dict[str, tuple[tuple[float, float], tuple[float, float]]]] = {
    "snow": {"pretrained": ((0.5758, 0.5835), (0.3943, 0.4752)), "finetuned": ((0.5394, 0.5618), (0.5161, 0.5471)),
             "finetuned-mix": ((0.5606, 0.5756), (0.5103, 0.5472))},
    "rain": {"pretrained": ((0.5758, 0.5835), (0.4646, 0.5192)), "finetuned": ((0.5468, 0.5685), (0.4909, 0.5287)),
             "finetuned-mix": ((0.5590, 0.5765), (0.4710, 0.5201))},
    "fog": {"pretrained": ((0.5758, 0.5835), (0.4314, 0.4991)), "finetuned": ((0.4448, 0.5129), (0.5018, 0.5407)),
            "finetuned-mix": ((0.5515, 0.5725), (0.4861, 0.5301))},
}
#: Our condition beside each of the paper's weather columns (the paper simulates one fog level).
PAPER_WEATHER_OF: dict[str, str] = {"snow": "snow", "rain": "rain", "fog_dense": "fog", "fog_light": "fog"}


def detector_config(cfg: DetectConfig) -> DetectorConfig:
    """The detector's sizes from the stage's params (grid, modality dropout); the rest are `DetectorConfig`'s."""
    return DetectorConfig(bev_range_m=cfg.bev_range_m, bev_cell_m=cfg.bev_cell_m,
                          modality_dropout=cfg.modality_dropout, lidar_drop_share=cfg.lidar_drop_share,
                          camera_only_loss=cfg.camera_only_loss, depth_loss_weight=cfg.depth_loss_weight)


def point_range(cfg: DetectConfig) -> tuple[float, ...]:
    """(x_min, y_min, z_min, x_max, y_max, z_max) [m] of the points and box centres the detector sees."""
    z0, z1 = DetectorConfig().z_range_m
    r = cfg.bev_range_m
    return (-r, -r, z0, r, r, z1)


def resolve_device(name: str) -> torch.device:
    """``name`` as a torch device, or a ValueError saying it is not present here."""
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"detect.device = {name!r}, but torch sees no CUDA device here (use cpu)")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(f"detect.device = {name!r}, but torch sees {torch.cuda.device_count()} CUDA device(s)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"detect.device = {name!r}, but MPS is not available here (use cpu)")
    return device


# ------------------------------------------------------------------------------------------------------ training


def epoch_batches(n_samples: int, batch_size: int, seed: int, epoch: int, sampler: Sampler | None
                  ) -> list[list[int]]:
    """The sample indices of each full batch of ``epoch``: a seeded shuffle of ``range(n_samples)`` (or the draws of
    ``sampler`` after its ``set_epoch``), cut into batches of ``batch_size`` (the last partial batch dropped)."""
    if sampler is not None:
        if hasattr(sampler, "set_epoch"):
            sampler.set_epoch(epoch)
        order = list(iter(sampler))
    else:
        order = torch.randperm(n_samples, generator=torch.Generator().manual_seed(seed * 100_003 + epoch)).tolist()
    return [order[i:i + batch_size] for i in range(0, len(order) - batch_size + 1, batch_size)]


def _batches(dataset: Dataset, batch_size: int, seed: int, sampler: Sampler | None, skip: int = 0
             ) -> Iterator[Any]:
    """Batches of ``dataset`` epoch after epoch (`epoch_batches`; the augmentation draws of each epoch selected with
    ``set_epoch``), the first ``skip`` batches passed over without loading them (a resumed training)."""
    epoch = 0
    while True:
        batches = epoch_batches(len(dataset), batch_size, seed, epoch, sampler)
        if not batches:
            raise ValueError(f"no full batch of {batch_size} in a dataset of {len(dataset)} samples")
        if skip >= len(batches):
            skip -= len(batches)
            epoch += 1
            continue
        if hasattr(dataset, "set_epoch"):
            dataset.set_epoch(epoch)
        yield from DataLoader(dataset, batch_sampler=batches[skip:], collate_fn=collate)
        skip = 0
        epoch += 1


@dataclass(frozen=True)
class Resume:
    """Where a training keeps its state every ``every`` steps (model, optimiser, schedule, random generator, losses;
    written atomically, tensors and plain data only) and the ``key`` that state must carry to be resumed (the
    model's fingerprint): a training stopped midway continues from its last saved step with the same result."""

    path: Path
    key: str
    every: int = 100


def _save_state(resume: Resume, step: int, model: nn.Module, optimizer: torch.optim.Optimizer,
                scheduler: torch.optim.lr_scheduler.LRScheduler, history: list[dict[str, float]]) -> None:
    buf = io.BytesIO()
    torch.save({"key": resume.key, "step": step, "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
                "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                "rng": torch.get_rng_state(), "history": history}, buf)
    atomic.write_bytes(resume.path, buf.getvalue())


def _load_state(resume: Resume | None) -> dict[str, Any] | None:
    """The saved state of ``resume`` when it exists and carries its key (tensors and plain data only)."""
    if resume is None or not resume.path.is_file():
        return None
    state = torch.load(resume.path, map_location="cpu", weights_only=True)
    return state if state.get("key") == resume.key else None


def train(model: BEVFusionDetector, dataset: Dataset, steps: int, lr: float, weight_decay: float, batch_size: int,
          seed: int, device: torch.device, *, sampler: Sampler | None = None, desc: str = "train",
          show_progress: bool = True, on_step: Callable[[int, dict[str, float]], dict[str, float] | None] | None = None,
          resume: Resume | None = None) -> list[dict[str, float]]:
    """``steps`` steps of AdamW with a one-cycle LR (peak ``lr``, 30 % warm-up) on ``dataset`` (or the draws of
    ``sampler``), with a progress bar. Deterministic for a seed on the CPU. Returns each step's losses;
    ``on_step(step, record)`` after each step (1-based), under a fork of the random generators: what it draws (a
    data loader's base seed, say) leaves the training unchanged, so a learning curve does not change the model; what
    it returns is added to the step's record. With ``resume``, the state is saved every ``resume.every`` steps and a
    saved state with the same key is continued (same final weights as an uninterrupted run on the CPU); the state
    file is removed at the end."""
    torch.manual_seed(seed)
    model.to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=lr, total_steps=max(steps, 2), pct_start=0.3)
    history: list[dict[str, float]] = []
    state = _load_state(resume)
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["rng"])
        history = list(state["history"])
    done = len(history)
    batches = _batches(dataset, batch_size, seed, sampler, skip=done)
    with tqdm(total=steps, initial=done, desc=desc, disable=not show_progress, unit="step") as bar:
        for step in range(done + 1, steps + 1):
            record = train_step(model, next(batches).to(device), optimizer, scheduler)
            bar.update()
            bar.set_postfix(loss=f"{record['total']:.3f}")
            if on_step is not None:  # an evaluation there must not shift the training's random draws
                with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
                    extra = on_step(step, record)
                if isinstance(extra, dict):
                    record.update(extra)
            history.append(record)
            if resume is not None and step % resume.every == 0 and step < steps:
                _save_state(resume, step, model, optimizer, scheduler, history)
    if resume is not None:
        resume.path.unlink(missing_ok=True)
    return history


def save_checkpoint(path: Path, model: BEVFusionDetector, meta: dict[str, Any]) -> None:
    """The model's weights and ``meta`` (fingerprint, history...) in one file, written atomically."""
    buf = io.BytesIO()
    torch.save({"state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}, "meta": meta}, buf)
    atomic.write_bytes(path, buf.getvalue())


def load_checkpoint(path: Path, config: DetectorConfig) -> tuple[BEVFusionDetector, dict[str, Any]]:
    """A detector of ``config`` with the weights of ``path``, and the checkpoint's meta."""
    blob = torch.load(path, map_location="cpu", weights_only=True)  # tensors and plain data only: never code
    model = BEVFusionDetector(config)
    model.load_state_dict(blob["state_dict"])
    return model, blob["meta"]


@dataclass(frozen=True)
class TrainJob:
    """One training run that a worker process can do on its own (everything in it pickles): ``steps`` steps at peak
    ``lr`` from the checkpoint ``init`` (None: from scratch, seeded by ``cfg.seed``) on the train cache ``caches[0]``,
    or on the weather cache ``caches[0]`` mixed with the clean cache ``caches[1]`` at ``cfg.mix_weather_fraction``;
    the result is written to ``out`` with ``fingerprint`` in its meta. With ``curve_set``, the val mAP / NDS every
    ``curve_every`` steps (the learning curve). The training state is saved beside ``out`` every
    ``resume_every`` steps and resumed after an interruption."""

    name: str
    caches: tuple[Path, ...]
    init: Path | None
    steps: int
    lr: float
    out: Path
    fingerprint: str
    cfg: DetectConfig
    device: str = "cpu"
    threads: int = 1
    curve_set: EvalSet | None = None
    curve_every: int = 0
    resume_every: int = 100

    @property
    def state_path(self) -> Path:
        return self.out.with_name(self.out.stem + ".state.pt")


def training_dataset(caches: Sequence[Path], cfg: DetectConfig) -> tuple[Dataset, Sampler | None]:
    """The augmented train set of one cache folder, or of a weather cache mixed with a clean one (and its
    sampler)."""
    sets = [DetectionDataset(c, Augmentation(), seed=cfg.seed, point_range=point_range(cfg)) for c in caches]
    if len(sets) == 1:
        return sets[0], None
    return mixed_dataset(sets[0], sets[1], cfg.mix_weather_fraction, None, cfg.seed)


def run_train_job(job: TrainJob, show_progress: bool = False) -> dict[str, Any]:
    """Do ``job`` (`TrainJob`) with ``job.threads`` torch threads; returns the checkpoint's meta (``fingerprint``,
    ``curve`` (step, map, nds, map_present, seconds), ``losses`` per step, ``seconds``, ``steps``, ``seed``)."""
    torch.set_num_threads(job.threads)
    config = detector_config(job.cfg)
    device = resolve_device(job.device)
    torch.manual_seed(job.cfg.seed)  # the initial weights: a function of the seed alone
    model = load_checkpoint(job.init, config)[0] if job.init else BEVFusionDetector(config)
    dataset, sampler = training_dataset(job.caches, job.cfg)
    t0 = time.time()

    def on_step(step: int, record: dict[str, float]) -> dict[str, float] | None:
        if job.curve_set is None or not job.curve_every or not (step % job.curve_every == 0 or step == job.steps):
            return None
        detections = predict(model, job.curve_set.dataset, job.cfg.batch_size, device, job.cfg.score_threshold,
                             job.cfg.max_detections)
        m = evaluate(detections, job.curve_set, 0, 0, job.cfg.confidence)
        return {"val.map": m["map"], "val.nds": m["nds"], "val.map_present": m["map_present"],
                "val.seconds": time.time() - t0}

    history = train(model, dataset, job.steps, job.lr, job.cfg.weight_decay, job.cfg.batch_size, job.cfg.seed,
                    device, sampler=sampler, desc=f"detect: train {job.name}", show_progress=show_progress,
                    on_step=on_step, resume=Resume(job.state_path, job.fingerprint, job.resume_every))
    curve = [{"step": i, "map": h["val.map"], "nds": h["val.nds"], "map_present": h["val.map_present"],
              "seconds": round(h["val.seconds"], 1)} for i, h in enumerate(history, start=1) if "val.map" in h]
    meta = {"fingerprint": job.fingerprint, "curve": curve, "losses": [round(h["total"], 5) for h in history],
            "depth_losses": [round(h.get("depth", float("nan")), 5) for h in history],
            "seconds": time.time() - t0, "steps": job.steps, "seed": job.cfg.seed}
    save_checkpoint(job.out, model.cpu(), meta)
    return meta


@dataclass(frozen=True)
class PredictJob:
    """Detections of the model in ``checkpoint`` on the val cache ``cache`` with ``modality`` (pickles); the camera
    images and features from ``camera_cache`` (a weather copy's: clean LiDAR + weather cameras) and / or of the
    samples ``image_source`` (the shuffled-image control) when given (see `DetectionDataset`)."""

    checkpoint: Path
    cache: Path
    modality: str
    cfg: DetectConfig
    device: str = "cpu"
    threads: int = 1
    camera_cache: Path | None = None
    image_source: tuple[int, ...] | None = None


def run_predict_job(job: PredictJob) -> list[SampleDetections]:
    """Do ``job`` (`PredictJob`) with ``job.threads`` torch threads."""
    torch.set_num_threads(job.threads)
    model = load_checkpoint(job.checkpoint, detector_config(job.cfg))[0]
    dataset = DetectionDataset(job.cache, None, point_range=point_range(job.cfg), min_lidar_pts=0,
                               camera_cache=job.camera_cache, image_source=job.image_source)
    return predict(model, dataset, job.cfg.batch_size, resolve_device(job.device), job.cfg.score_threshold,
                   job.cfg.max_detections, job.modality)


# ---------------------------------------------------------------------------------------------------- evaluation


@dataclass(frozen=True)
class EvalSet:
    """One val split to evaluate on: its cached samples and the ground truth they are scored against (the same
    annotations in every weather copy: the copies hard-link the clean tables)."""

    name: str
    dataset: DetectionDataset
    gt: EvalBoxes
    T_global_lidar: dict[str, np.ndarray]
    ego_position: dict[str, np.ndarray]


@torch.no_grad()
def predict(model: BEVFusionDetector, dataset: DetectionDataset, batch_size: int, device: torch.device,
            score_threshold: float, max_detections: int, modality: Modality = "fused") -> list[SampleDetections]:
    """Detections of every sample of ``dataset`` (no augmentation), in order."""
    model.to(device)
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, collate_fn=collate)
    out: list[SampleDetections] = []
    for batch in loader:
        out.extend(model.detect(batch.to(device), score_threshold, max_detections, modality))
    return out


def evaluate(detections: Sequence[SampleDetections], evalset: EvalSet, num_bootstrap: int, seed: int,
             confidence: float) -> dict[str, Any]:
    """nuScenes metrics of ``detections`` on ``evalset`` (`weatheralign.detect.evaluate.score`), with frame-bootstrap
    intervals ``map_ci``, ``nds_ci``, ``map_present_ci``; 0 resamples: point estimates only."""
    pred = eval_boxes(detections, evalset)
    result = score(evalset.gt, pred).as_dict()
    if num_bootstrap > 0:
        map_ci, nds_ci, present_ci = bootstrap_intervals(evalset.gt, pred, num_bootstrap, seed, confidence)
        result.update(map_ci=map_ci, nds_ci=nds_ci, map_present_ci=present_ci)
    return result


def eval_boxes(detections: Sequence[SampleDetections], evalset: EvalSet) -> EvalBoxes:
    """``detections`` as global-frame devkit boxes, ranges measured from the ego as the devkit does."""
    return predictions_to_eval_boxes(detections, evalset.T_global_lidar, evalset.ego_position)


def detections_to_arrays(detections: Sequence[SampleDetections]) -> dict[str, np.ndarray]:
    """Detections as flat arrays (``token``, ``boxes``, ``scores``, ``labels``, ``attributes``) for an .npz file."""
    counts = np.array([len(d.scores) for d in detections], np.int64)
    return {"tokens": np.array([d.token for d in detections]), "counts": counts,
            "boxes": np.concatenate([d.boxes for d in detections]) if detections else np.zeros((0, 9)),
            "scores": np.concatenate([d.scores for d in detections]) if detections else np.zeros(0),
            "labels": np.concatenate([d.labels for d in detections]) if detections else np.zeros(0, np.int64),
            "attributes": np.concatenate([d.attributes for d in detections]) if detections else np.zeros(0, np.int64)}


def detections_from_arrays(arrays: dict[str, np.ndarray]) -> list[SampleDetections]:
    """The inverse of `detections_to_arrays`."""
    ends = np.cumsum(arrays["counts"])
    starts = ends - arrays["counts"]
    return [SampleDetections(str(t), arrays["boxes"][a:b], arrays["scores"][a:b], arrays["labels"][a:b],
                             arrays["attributes"][a:b]) for t, a, b in zip(arrays["tokens"], starts, ends)]


__all__ = ["DETECTOR_MODULES", "EvalSet", "PAPER_TABLE2", "PAPER_TABLE3", "PAPER_WEATHER_OF", "PredictJob", "TrainJob",
           "detections_from_arrays", "detections_to_arrays", "detector_config", "eval_boxes", "evaluate",
           "epoch_batches", "load_checkpoint", "point_range", "predict", "resolve_device", "Resume", "run_predict_job",
           "run_train_job", "save_checkpoint", "train", "training_dataset"]
