"""`detect` stage: the paper's perception check with a small BEVFusion-style detector trained here.

``python -m flows.detect`` reads the world's manifest (the clean dataroot) and the weather copies of the `simulate`
matrix (``<paths.data>/simulate/<condition>-<aligned|unaligned>``), caches each split it needs once
(`weatheralign.detect.data.build_cache`: downsized cameras with their frozen ImageNet features, the keyframe and
``simulate.sweeps`` sweeps), then

1. pretrains one model per seed of ``detect.seeds`` on the clean train split (learning curve: val mAP / NDS every
   ``detect.eval_every`` steps);
2. evaluates each on the clean val split and on the val split of every weather copy, aligned and unaligned (the
   paper's Table 2); LiDAR-only, camera-only and with every sample's images swapped for another sample's on clean val
   (the modality ablation and the shuffled-image control); and on clean LiDAR with each weather copy's cameras (the
   cameras' share of the weather);
3. finetunes the first seed's model on each of ``detect.finetune_conditions``: the aligned train split, the unaligned
   one, and the aligned one mixed 30/70 with clean at the data-loader level, each evaluated on clean val and on its
   weather's aligned and unaligned val (Table 3);
4. writes ``reports/detect/details.json`` (models -> evaluation sets -> mAP / NDS averaged over the seeds, with
   seed x scene-block bootstrap intervals, and RA = NDS_weather / NDS_clean), paired differences with the same
   intervals; ``metrics.json`` its `headline`), ``table_alignment.md`` and ``table_finetune.md`` (the paper's
   figures beside ours, labelled), ``learning_curve.png`` and ``predictions_bev.png``; and every evaluation's detections
   as a nuScenes results file,
   ``<paths.data>/detect/results/seed<k>/<model>/<evaluation set>.json`` (score others with ``flows.score``).

Every training and evaluation is an MLflow child run tagged ``model``, ``seed``, ``weather``, ``alignment``. Finished
models (``<paths.data>/detect/models/seed<k>/<model>.pt``) and evaluations (``<paths.data>/detect/evals/``) are kept
with the fingerprint of the detector's code (`weatheralign.detect.protocol.DETECTOR_MODULES`, not the weather's: a
change of the simulators retrains only what a changed copy feeds), params and the data each was made from (the cache
keys of its training or evaluation split, which change with any file of it, and the model it started from): an
interrupted run resumes after the last finished one, a training stopped midway from its last saved state, and a
weather copy simulated again retrains and re-evaluates what used it. Checkpoints are read as tensors and plain data
only.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from prefect import flow  # noqa: E402

from flows.common import gather, parse_stage_args, run_stage, threads_per_task  # noqa: E402
from tasks.detect import paired_task, predict_task, train_task  # noqa: E402
from tasks.detector_model import detector_pyfunc, input_example  # noqa: E402
from tasks.tracking import REGISTERED_MODEL_PREFIX, ChildRun, LoggedDetector, StageTracker  # noqa: E402
from weatheralign import atomic  # noqa: E402
from weatheralign.code_closure import closure_fingerprint  # noqa: E402
from weatheralign.conditions import CONDITIONS, condition_tags, variant_name  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.data.errors import DataFormatError  # noqa: E402
from weatheralign.data.nuscenes import open_nuscenes  # noqa: E402
from weatheralign.detect import protocol  # noqa: E402
from weatheralign.detect.data import (  # noqa: E402
    DetectionDataset,
    build_cache,
    cache_path,
    derangement,
    load_cached_sample,
    scene_split,
    stale_caches,
)
from weatheralign.detect.evaluate import ego_positions, ground_truth, resistance_ability, scene_blocks  # noqa: E402
from weatheralign.detect.figures import (  # noqa: E402
    detections_bev_figure,
    learning_curve_figure,
    learning_curve_rows,
    per_class_rows,
)
from weatheralign.detect.model import BEVFusionDetector, count_parameters  # noqa: E402
from weatheralign.detect.results import write_submission  # noqa: E402
from weatheralign.manifest import manifest_path, read_manifest  # noqa: E402
from weatheralign.simulate.media import media_path, read_media  # noqa: E402

CLEAN = "clean"
SUMMARY_KEYS = ("map", "nds", "map_present", "map_ci", "nds_ci", "map_present_ci", "mate", "mase", "maoe", "mave",
                "maae", "per_class_ap", "classes_present")


def weather_roots(params: Params, version: str) -> dict[str, Path]:
    """Every weather copy of the simulate matrix, by variant name, from its manifest; a missing one is an error naming
    its stage."""
    roots = {}
    for condition in CONDITIONS:
        for aligned in (True, False):
            name = variant_name(condition, aligned)
            path = manifest_path(params.paths.data, f"simulate-{name}")
            if not path.is_file():
                raise DataFormatError(f"{path}: no weather copy (run the stage simulate@{name} first: "
                                      f"dvc repro simulate@{name})")
            manifest = read_manifest(path)
            if manifest.version != version:
                raise DataFormatError(f"{path}: version {manifest.version!r}; expected the world's {version!r} "
                                      f"(rerun dvc repro simulate@{name})")
            roots[name] = Path(manifest.dataroot)
    return roots


def input_digests(params: Params, variants: list[str]) -> dict[str, str]:
    """Manifest name -> content digest of every dataset the stage reads (the world and the weather copies), recorded in
    details.json so that a report can tell detect's figures from copies simulated again since."""
    names = ["world"] + [f"simulate-{v}" for v in variants]
    return {name: read_manifest(manifest_path(params.paths.data, name)).content_digest for name in names}


MODALITY_LABELS = {"fused": "", "lidar": "-lidar_only", "camera": "-camera_only"}
SHUFFLED_LABEL = "-shuffled_images"


CAMERA_WEATHER_PREFIX = "clean_lidar_with_"


def camera_weather_set(variant: str) -> str:
    """The evaluation set of clean LiDAR with the cameras of weather copy ``variant`` (e.g. ``snow-aligned``)."""
    return f"{CAMERA_WEATHER_PREFIX}{variant}_cameras"


@dataclass(frozen=True)
class Evaluation:
    """One evaluation: model ``model`` of training seed ``seed`` on the val split ``evalset`` (`CLEAN`, a weather
    variant, or `camera_weather_set`) with ``modality``, the images shuffled between samples when ``shuffled``."""

    model: str
    seed: int
    evalset: str
    modality: str = "fused"
    shuffled: bool = False

    @property
    def label(self) -> str:
        """The evaluated model's name in tables and results files, e.g. ``pretrained-camera_only``."""
        return self.model + MODALITY_LABELS[self.modality] + (SHUFFLED_LABEL if self.shuffled else "")

    @property
    def key(self) -> str:
        """``seed<k>/<label>/<evalset>``: its files under ``evals/`` and ``results/``."""
        return f"seed{self.seed}/{self.label}/{self.evalset}"

    @property
    def checkpoint_name(self) -> str:
        return f"seed{self.seed}/{self.model}"


class DetectRun:
    """What one run of the stage shares: params, device, caches, evaluation sets, resume folders, tracker."""

    def __init__(self, params: Params, tracker: StageTracker) -> None:
        cfg = params.detect
        self.params, self.cfg, self.tracker = params, cfg, tracker
        self.device = protocol.resolve_device(cfg.device)
        torch.set_num_threads(params.run.torch_threads)
        #: torch threads of each training / prediction task (a worker process per core on the CPU)
        self.threads = threads_per_task(params) if self.device.type == "cpu" else params.run.torch_threads
        world = read_manifest(manifest_path(params.paths.data, "world"))
        self.version = world.version
        self.clean_root = Path(world.dataroot)
        self.roots = {CLEAN: self.clean_root, **weather_roots(params, self.version)}
        self.nusc = open_nuscenes(self.clean_root, self.version)
        self.tokens = {split: scene_split(self.nusc, self.clean_root, self.version, split)
                       for split in ("train", "val")}
        self.out = params.paths.data / "detect"
        self.fingerprint = closure_fingerprint(protocol.DETECTOR_MODULES, "detect", params, world.content_digest)
        self.model_config = protocol.detector_config(cfg)
        self.caches: dict[tuple[str, str], Path] = {}
        self.data_keys: dict[tuple[str, str], str] = {}
        self.evalsets: dict[str, protocol.EvalSet] = {}
        self.gt = ground_truth(self.nusc, self.tokens["val"])
        self.ego = ego_positions(self.nusc, self.tokens["val"])
        scenes = [self.nusc.get("sample", t)["scene_token"] for t in self.tokens["val"]]
        self.blocks = scene_blocks(scenes, cfg.scene_block)
        self.model_fingerprints: dict[str, str] = {}
        self.metas: dict[str, dict[str, Any]] = {}  # checkpoint name -> its meta (curve, losses, seconds)
        self.detections: dict[str, list] = {}  # evaluation key -> detections
        self.pred_boxes: dict[str, Any] = {}  # evaluation key -> its detections as devkit EvalBoxes (`eval_boxes`)
        self.logged_models: dict[str, LoggedDetector] = {}  # MLflow logged models of the models trained by this run
        self._input_example: dict[str, Any] | None = None

    # -------------------------------------------------------------------------------------------- data

    def cache(self, dataroot: str, split: str) -> Path:
        """The cache folder of ``split`` of dataroot ``dataroot`` (`CLEAN` or a weather variant), built if needed."""
        key = (dataroot, split)
        if key not in self.caches:
            self.caches[key] = build_cache(self.roots[dataroot], self.version, self.tokens[split],
                                           self.out / "cache", self.cfg.image_size, self.params.simulate.sweeps,
                                           self.params.run.show_progress, self.params.run.max_workers)
        return self.caches[key]

    def data_key(self, dataroot: str, split: str) -> str:
        """The cache folder name of ``split`` of ``dataroot`` (`cache_path`: a digest over the size and mtime of every
        file the samples read), computed without building the cache: what a finished model or evaluation was made
        from, so that a weather copy simulated again is not mistaken for the one a checkpoint was trained on."""
        key = (dataroot, split)
        if key not in self.data_keys:
            self.data_keys[key] = cache_path(self.roots[dataroot], self.version, self.tokens[split],
                                             self.out / "cache", self.cfg.image_size, self.params.simulate.sweeps).name
        return self.data_keys[key]

    def prune_caches(self) -> list[Path]:
        """Delete the cache folders of this stage's datasets that none of their splits is keyed by now
        (`weatheralign.detect.data.stale_caches`: left by an earlier version of a weather copy or of the world, which
        nothing reads again); returns them."""
        current = {self.data_key(root, split) for root in self.roots for split in self.tokens}
        stale = stale_caches(self.out / "cache", self.roots.values(), current)
        for folder in stale:
            shutil.rmtree(folder)
        return stale

    def evalset_key(self, evalset: str) -> str:
        """The data keys an evaluation set is made from (its LiDAR's and its cameras' val caches)."""
        lidar, cameras = self.evalset_roots(evalset)
        return self.data_key(lidar, "val") + ("" if cameras == lidar else "+" + self.data_key(cameras, "val"))

    @staticmethod
    def evalset_roots(evalset: str) -> tuple[str, str]:
        """(dataroot of the LiDAR and boxes, dataroot of the cameras) of an evaluation set."""
        if evalset.startswith("clean_lidar_with_"):
            return CLEAN, evalset.removeprefix("clean_lidar_with_").removesuffix("_cameras")
        return evalset, evalset

    def evalset(self, evalset: str) -> protocol.EvalSet:
        if evalset not in self.evalsets:
            lidar, cameras = self.evalset_roots(evalset)
            folder = self.cache(lidar, "val")
            ds = DetectionDataset(folder, None, point_range=protocol.point_range(self.cfg), min_lidar_pts=0,
                                  camera_cache=None if cameras == lidar else self.cache(cameras, "val"))
            T = {t: load_cached_sample(folder, t)["T_global_lidar"] for t in ds.tokens}
            self.evalsets[evalset] = protocol.EvalSet(evalset, ds, self.gt, T, self.ego)
        return self.evalsets[evalset]

    # -------------------------------------------------------------------------------------------- models

    def _model_fingerprint(self, name: str, train_on: str | tuple[str, str], init: str | None, steps: int,
                           lr: float) -> str:
        """What model ``name`` is made from: code, params, the cache keys of its training data, the model it starts
        from; remembered for its evaluations' fingerprints."""
        sources = train_on if isinstance(train_on, tuple) else (train_on,)
        fingerprint = hashlib.sha256(json.dumps([
            self.fingerprint, name, list(sources), [self.data_key(d, "train") for d in sources],
            init, self.model_fingerprints.get(init) if init else None, steps, lr]).encode()).hexdigest()[:16]
        self.model_fingerprints[name] = fingerprint
        return fingerprint

    def _finished_model(self, name: str, fingerprint: str) -> bool:
        """Whether model ``name``'s checkpoint was made from ``fingerprint`` (then its meta is kept). The checkpoint
        is read as tensors and plain data only: a received file cannot run code."""
        path = self.checkpoint(name)
        if not path.is_file():
            return False
        meta = torch.load(path, map_location="cpu", weights_only=True)["meta"]
        if meta.get("fingerprint") != fingerprint:
            return False
        self.metas[name] = meta
        return True

    def checkpoint(self, name: str) -> Path:
        return self.out / "models" / f"{name}.pt"

    def register(self, run: ChildRun, name: str, model: BEVFusionDetector, checkpoint: Path) -> None:
        """Log trained model ``name`` (``seed<k>/<model>``) to its training run as an MLflow logged model and register
        it as a new version of ``weatheralign-detector-<model>`` with the alias ``seed<k>`` (MLflow's own ``@latest``
        is the newest version); its evaluations link their metrics to it and tag the version with their mAP / NDS."""
        seed = name.split("/", 1)[0]
        with tempfile.TemporaryDirectory() as workdir:
            pyfunc = detector_pyfunc(model.cpu().eval(), checkpoint, self.input_example(), Path(workdir))
            logged = run.log_model(pyfunc, registered_name(name), (seed,))
        if logged is not None:
            self.logged_models[name] = logged

    def input_example(self) -> dict[str, Any]:
        """The registered models' input example: cut from the first clean val sample (`input_example`)."""
        if self._input_example is None:
            sample = DetectionDataset(self.cache(CLEAN, "val"), None, point_range=protocol.point_range(self.cfg),
                                      min_lidar_pts=0)[0]
            self._input_example = input_example(sample)
        return self._input_example

    def train_job(self, name: str, train_on: str | tuple[str, str], init: str | None, steps: int, lr: float,
                  seed: int, learning_curve: bool = False) -> protocol.TrainJob | None:
        """The job that trains model ``name`` (a checkpoint name ``seed<k>/<model>``) from model ``init`` (None:
        from scratch with ``seed``) on ``train_on`` (one dataroot's train split, or ``(weather, CLEAN)`` mixed at
        ``detect.mix_weather_fraction``) in a worker; None when its checkpoint is finished. The caches it reads are
        built here first."""
        fingerprint = self._model_fingerprint(name, train_on, init, steps, lr)
        if self._finished_model(name, fingerprint):
            return None
        sources = train_on if isinstance(train_on, tuple) else (train_on,)
        return protocol.TrainJob(name, tuple(self.cache(d, "train") for d in sources),
                                 self.checkpoint(init) if init else None, steps, lr, self.checkpoint(name),
                                 fingerprint, self.cfg.model_copy(update={"seed": seed}), str(self.device),
                                 self.threads, self.evalset(CLEAN) if learning_curve else None,
                                 self.cfg.eval_every if learning_curve else 0)

    def record_training(self, job: protocol.TrainJob, meta: dict[str, Any], tags: dict[str, str]) -> None:
        """A finished `TrainJob`'s MLflow child run (losses every 10 steps, the learning curve, seconds, checkpoint)
        and its meta."""
        with self.tracker.child(f"train {job.name}", {**tags, "model": job.name, "kind": "train"}) as run:
            run.log_params({"train_on": ",".join(c.name for c in job.caches), "init": job.init.stem if job.init
                            else "None", "steps": job.steps, "lr": job.lr, "seed": job.cfg.seed})
            for step, loss in enumerate(meta["losses"], start=1):
                if step % 10 == 0 or step == job.steps:
                    run.log_metrics({"loss.total": loss}, step)
            for point in meta["curve"]:
                run.log_metrics({"val.map": point["map"], "val.nds": point["nds"]}, point["step"])
            run.log_metrics({"train_seconds": meta["seconds"], "seconds_per_step": meta["seconds"] / max(job.steps, 1)})
            run.log_artifact(job.out, "checkpoint")
            self.register(run, job.name, protocol.load_checkpoint(job.out, self.model_config)[0], job.out)
        self.metas[job.name] = meta

    # -------------------------------------------------------------------------------------------- evaluation

    def _evaluation_files(self, e: Evaluation) -> tuple[Path, Path, Path, str]:
        fingerprint = (f"{self.model_fingerprints[e.checkpoint_name]}:{self.evalset_key(e.evalset)}:{e.modality}:"
                       f"{e.shuffled}")
        return (self.out / "evals" / f"{e.key}.json", self.out / "evals" / f"{e.key}.npz",
                self.out / "results" / f"{e.key}.json", fingerprint)

    def finished_evaluation(self, e: Evaluation) -> dict[str, Any] | None:
        """The metrics of evaluation ``e`` when an earlier run finished it with the same fingerprint (model, data,
        modality), its detections kept for the intervals; else None."""
        record_path, det_path, results_path, fingerprint = self._evaluation_files(e)
        if not (record_path.is_file() and det_path.is_file() and results_path.is_file()):
            return None
        record = json.loads(record_path.read_text())
        if record.get("fingerprint") != fingerprint:
            return None
        with np.load(det_path) as z:
            self.detections[e.key] = protocol.detections_from_arrays(dict(z))
        return record["metrics"]

    def predict_job(self, e: Evaluation) -> protocol.PredictJob:
        lidar, cameras = self.evalset_roots(e.evalset)
        n = len(self.tokens["val"])
        return protocol.PredictJob(self.checkpoint(e.checkpoint_name), self.cache(lidar, "val"), e.modality, self.cfg,
                                   str(self.device), self.threads,
                                   None if cameras == lidar else self.cache(cameras, "val"),
                                   tuple(derangement(n, self.cfg.seed)) if e.shuffled else None)

    def record_evaluation(self, e: Evaluation, detections: list) -> dict[str, Any]:
        """Score ``detections`` of evaluation ``e`` (point estimates; the intervals pool the seeds later), keep them,
        their metrics and their nuScenes results file for a resumed run and for other scorers, and log an MLflow
        child run."""
        record_path, det_path, results_path, fingerprint = self._evaluation_files(e)
        evalset = self.evalset(e.evalset)
        self.detections[e.key] = detections
        pred = self.eval_boxes(e.key, e.evalset)
        result = protocol.evaluate(detections, evalset, 0, self.cfg.seed, self.cfg.confidence)
        write_submission(results_path, pred, use_camera=e.modality != "lidar", use_lidar=e.modality != "camera")
        atomic.save_npz(det_path, protocol.detections_to_arrays(detections), compress=True)
        atomic.write_json(record_path, {"fingerprint": fingerprint, "metrics": result})
        lidar, cameras = self.evalset_roots(e.evalset)
        model_tag = e.label if cameras == lidar else f"{e.label}-clean_lidar"  # weather on the cameras only
        tags = {**self.dataroot_tags(cameras), "model": model_tag, "seed": str(e.seed), "modality": e.modality,
                "kind": "eval", "evalset": e.evalset}
        logged = self.logged_models.get(e.checkpoint_name)
        link = {"model_id": logged.model_id if logged else None,
                "dataset": (f"{cameras}/val", self.data_key(cameras, "val").rsplit("-", 1)[-1])}
        with self.tracker.child(f"eval {e.key}", tags) as run:
            headline = {k: v for k, v in result.items() if k in ("map", "nds", "map_present", "mate", "mase", "maoe",
                                                                 "mave", "maae")}
            run.log_metrics(headline, **link)
            run.log_metrics({f"ap.{c}": v for c, v in result["per_class_ap"].items()}, **link)
            run.log_artifact(results_path, "results")
        if logged is not None and e.label == e.model:
            self.tracker.tag_model_version(registered_name(e.checkpoint_name), logged.version,
                                           {f"{k}.{e.evalset}": f"{v:.4f}" for k, v in headline.items()
                                            if k in ("map", "nds")})
        return result

    def eval_boxes(self, key: str, evalset: str) -> Any:
        """The detections of evaluation ``key`` on ``evalset`` as devkit ``EvalBoxes``, converted once (the pooled
        intervals use each evaluation in several comparisons)."""
        if key not in self.pred_boxes:
            self.pred_boxes[key] = protocol.eval_boxes(self.detections[key], self.evalset(evalset))
        return self.pred_boxes[key]

    def dataroot_tags(self, dataroot: str) -> dict[str, str]:
        """``weather``, ``alignment`` and ``severity`` tags of a dataroot (`CLEAN` or a weather variant)."""
        weather, alignment = split_variant(dataroot)
        if dataroot == CLEAN:
            return {"weather": weather, "alignment": alignment, "severity": "none"}
        media = media_path(self.params.paths.data, weather)
        rates = read_media(media).rates(self.params.particles) if media.is_file() else \
            (self.params.particles.snow.rate_mm_h, self.params.particles.rain.rate_mm_h)
        return condition_tags(weather, alignment == "aligned", *rates)

    def log_inputs(self, evaluated: list[str], trained_on: list[str]) -> None:
        """The datasets this run reads as MLflow dataset inputs: each dataroot's val split (``evaluation``) and
        train split (``training``), digests over their files' sizes and times (`data_key`)."""
        for context, split, dataroots in (("evaluation", "val", evaluated), ("training", "train", trained_on)):
            for d in dict.fromkeys(dataroots):
                digest = self.data_key(d, split).rsplit("-", 1)[-1]
                self.tracker.log_dataset(f"{d}/{split}", digest, str(self.roots[d]), context)

    def run_jobs(self, trainings: list[tuple[protocol.TrainJob | None, dict[str, str]]],
                 evaluations: list[Evaluation]) -> dict[str, dict[str, Any]]:
        """Train every unfinished job of ``trainings`` and evaluate every unfinished evaluation, as tasks on the
        stage's task runner (worker processes: one core each; an evaluation waits for the training of its model);
        results are scored and recorded here as they come in. Returns the metrics of every evaluation by key."""
        jobs = [(job, tags) for job, tags in trainings if job is not None]
        for evalset in {e.evalset for e in evaluations}:
            self.evalset(evalset)
        trained: dict[str, Any] = {}
        for job, _ in jobs:  # a finetuning waits for the training of the model it starts from
            init = job.init.relative_to(self.out / "models").with_suffix("").as_posix() if job.init else None
            trained[job.name] = train_task.with_options(task_run_name=f"train/{job.name}").submit(
                job, wait_for=[trained[init]] if init in trained else [])
        metrics = {e.key: m for e in evaluations if (m := self.finished_evaluation(e)) is not None}
        pending = [e for e in evaluations if e.key not in metrics]
        futures = [predict_task.with_options(task_run_name=f"predict/{e.key}").submit(
            self.predict_job(e), wait_for=[trained[e.checkpoint_name]] if e.checkpoint_name in trained else [])
            for e in pending]

        def on_result(i: int, result: Any) -> None:
            if i < len(jobs):
                self.record_training(jobs[i][0], result, jobs[i][1])
            else:
                e = pending[i - len(jobs)]
                metrics[e.key] = self.record_evaluation(e, protocol.detections_from_arrays(result))

        gather([trained[job.name] for job, _ in jobs] + futures, "detect: train and evaluate",
               self.params.run.show_progress, on_result)
        return metrics

    def pooled(self, comparisons: dict[str, tuple[list[str], list[str] | None]]) -> dict[str, dict[str, Any]]:
        """Per ``name: (keys_a, keys_b)``: mAP and NDS of the evaluations ``keys_a`` (one per training seed), or
        their differences from ``keys_b`` on the same val samples, averaged over the seeds with seed x scene-block
        bootstrap intervals (`seed_block_bootstrap`), as tasks on the stage's task runner."""
        futures = []
        for keys_a, keys_b in comparisons.values():
            evalset = keys_a[0].rsplit("/", 1)[1]
            preds = [[self.eval_boxes(k, evalset) for k in keys] for keys in (keys_a, keys_b or [])]
            futures.append(paired_task.submit(self.gt, preds[0], preds[1] if keys_b else None, self.blocks,
                                              ("map", "nds"), self.cfg.num_bootstrap, self.cfg.seed,
                                              self.cfg.confidence))
        results = gather(futures, "detect: seed x block intervals", self.params.run.show_progress)
        return dict(zip(comparisons, results))


def registered_name(checkpoint_name: str) -> str:
    """The MLflow registered-model name of a checkpoint name, its seed left to an alias (``seed0/pretrained`` ->
    ``weatheralign-detector-pretrained``, ``seed0/finetuned-snow-aligned`` ->
    ``weatheralign-detector-finetuned-snow-aligned``)."""
    return REGISTERED_MODEL_PREFIX + checkpoint_name.split("/", 1)[1].replace("/", "-")


def difference_run(key: str, d: dict[str, Any]) -> tuple[dict[str, str], dict[str, float]]:
    """The tags and metrics of a paired difference's MLflow run: ``model``, ``weather``, ``alignment`` (of the
    dataroot it is measured on), ``comparison`` and ``metric`` tags; ``difference``, ``ci_low``, ``ci_high`` and
    ``exceeds_noise`` (0 / 1), named the same in every difference's run."""
    parts = key.split(":")
    if len(parts) == 4:  # model:condition:comparison:metric (measured on the condition's weather copies or clean)
        model, weather, comparison, metric = parts
        alignment = "none"
    else:  # comparison:dataroot:metric
        comparison, dataroot, metric = parts
        model = comparison.split("-vs-")[0].removesuffix("-aligned")
        weather, alignment = split_variant(dataroot)
    tags = {"kind": "difference", "model": model, "weather": weather, "alignment": alignment,
            "comparison": comparison, "metric": metric}
    return tags, {"difference": d["difference"], "ci_low": d["ci"][0], "ci_high": d["ci"][1],
                  "exceeds_noise": float(d["exceeds_noise"])}


def split_variant(dataroot: str) -> tuple[str, str]:
    """``snow-aligned`` -> (``snow``, ``aligned``); `CLEAN` -> (``clean``, ``none``)."""
    if dataroot == CLEAN:
        return CLEAN, "none"
    condition, _, alignment = dataroot.rpartition("-")
    return condition, alignment


def _fmt(m: dict[str, Any], key: str) -> str:
    ci = m.get(f"{key}_ci")
    return f"{m[key]:.3f}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else "")


def _fmt_difference(d: dict[str, Any] | None) -> str:
    if not d:
        return "—"
    return f"{d['difference']:+.3f} [{d['ci'][0]:+.3f}, {d['ci'][1]:+.3f}]"


def _interval_note(metrics: dict[str, Any]) -> str:
    seeds = metrics["seeds"]
    return (f"{metrics['confidence']:.0%} intervals from a two-level bootstrap: the {len(seeds)} pretraining seeds "
            f"({', '.join(map(str, seeds))}) and blocks of {metrics['scene_block']} consecutive val frames of one "
            "scene, both drawn with replacement; estimates are the mean over the seeds")


def table_alignment(metrics: dict[str, Any], conditions: list[str]) -> str:
    """Table 2: the pretrained model on every weather, aligned vs unaligned (ours with intervals; the paper's
    BEVFusion figures beside, labelled), and the clean-LiDAR + weather-camera sets."""
    pre = metrics["models"]["pretrained"]
    differences = metrics["differences"]
    lines = ["# Pretrained detector on aligned vs unaligned weather (the paper's Table 2)", "",
             f"Clean val: mAP {_fmt(pre[CLEAN], 'map')}, NDS {_fmt(pre[CLEAN], 'nds')}; {_interval_note(metrics)}. "
             "The paper's figures are BEVFusion on real nuScenes-mini with the paper's simulations, for comparison "
             "only.", "", *modality_lines(metrics), "",
             "| weather | unaligned mAP | unaligned NDS | aligned mAP | aligned NDS | unaligned - aligned mAP "
             "| RA aligned | paper unaligned (mAP, NDS) | paper aligned (mAP, NDS) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in conditions:
        u, a = pre[f"{c}-unaligned"], pre[f"{c}-aligned"]
        d = differences.get(f"pretrained:{c}:unaligned-aligned:map")
        paper = protocol.PAPER_TABLE2.get(c)
        ptxt = (f"{paper['unaligned'][0]:.4f}, {paper['unaligned'][1]:.4f}",
                f"{paper['aligned'][0]:.4f}, {paper['aligned'][1]:.4f}") if paper else ("—", "—")
        lines.append(f"| {c} | {_fmt(u, 'map')} | {_fmt(u, 'nds')} | {_fmt(a, 'map')} | {_fmt(a, 'nds')} "
                     f"| {_fmt_difference(d)} | {'—' if a['ra'] is None else format(a['ra'], '.3f')} | {ptxt[0]} "
                     f"| {ptxt[1]} |")
    lines += ["", "## The cameras' share of the weather: clean LiDAR + the weather copy's cameras", "",
              "Fused mAP on the clean val LiDAR with the cameras of each weather copy: what the weather does through "
              "the cameras alone, and whether aligned or unaligned camera weather matters to the detector.", "",
              "| weather | aligned cameras mAP | unaligned cameras mAP | clean - aligned cameras mAP "
              "| unaligned - aligned cameras mAP |", "| --- | --- | --- | --- | --- |"]
    for c in conditions:
        a, u = pre.get(camera_weather_set(f"{c}-aligned")), pre.get(camera_weather_set(f"{c}-unaligned"))
        if a is None or u is None:
            continue
        lines.append(f"| {c} | {_fmt(a, 'map')} | {_fmt(u, 'map')} "
                     f"| {_fmt_difference(differences.get(f'pretrained:{c}:clean-aligned_cameras:map'))} "
                     f"| {_fmt_difference(differences.get(f'pretrained:{c}:unaligned_cameras-aligned_cameras:map'))} |")
    return "\n".join(lines) + "\n"


def modality_lines(metrics: dict[str, Any]) -> list[str]:
    """The modality ablation of the pretrained model on clean val (per seed and pooled), the shuffled-image control,
    and what each sensor adds to the other (paired differences of mAP)."""
    ablation, differences = metrics["modality_ablation"], metrics["differences"]
    parts = [f"{m} {_fmt(ablation[m], 'map')} (seeds: {', '.join(f'{v:.3f}' for v in ablation[m]['map_per_seed'])})"
             for m in ("fused", "lidar_only", "camera_only", "shuffled_images") if m in ablation]
    adds = []
    for other, what in (("lidar", "the camera adds"), ("camera", "the LiDAR adds"),
                        ("shuffled_images", "another sample's images cost")):
        d = differences.get(f"pretrained:clean:fused-{other}:map")
        if d:
            adds.append(f"{what} {_fmt_difference(d)}" + ("" if d["exceeds_noise"] else " (within the noise)"))
    camera = ablation.get("camera_only", {}).get("car_ap_per_seed")
    car = f" Camera-only car AP per seed: {', '.join(f'{v:.3f}' for v in camera)}." if camera else ""
    return [f"Modality ablation, clean val mAP: {'; '.join(parts)}" + (f"; {'; '.join(adds)}." if adds else ".")
            + car]


def table_finetune(metrics: dict[str, Any], conditions: list[str]) -> str:
    """Table 3: pretrained / finetuned / finetuned-mix / finetuned-unaligned on clean and on the weather."""
    s0 = metrics["seeds"][0]
    lines = ["# Finetuning on simulated weather (the paper's Table 3)", "",
             f"mAP and NDS. The pretrained rows pool the {len(metrics['seeds'])} pretraining seeds "
             f"({_interval_note(metrics)}); the finetuned models are trained from seed {s0}'s pretrained model only "
             "(one finetuning seed, for the stage's time budget): their intervals hold the val frames' sampling noise "
             "but not the training noise. `paper` columns: BEVFusion on real nuScenes-mini (the paper's figures; its "
             "fog column beside our fog conditions).", ""]
    for c in conditions:
        paper = protocol.PAPER_TABLE3.get(protocol.PAPER_WEATHER_OF.get(c, ""), {})
        lines += [f"## {c}", "",
                  f"| model | clean mAP | clean NDS | {c} aligned mAP | {c} aligned NDS | {c} unaligned mAP "
                  "| paper clean (mAP, NDS) | paper weather (mAP, NDS) |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for model, paper_key in (("pretrained", "pretrained"), (f"finetuned-{c}", "finetuned"),
                                 (f"finetuned-{c}-mix", "finetuned-mix"), (f"finetuned-{c}-unaligned", None)):
            m = metrics["models"][model]
            p = paper.get(paper_key) if paper_key else None
            ptxt = (f"{p[0][0]:.4f}, {p[0][1]:.4f}", f"{p[1][0]:.4f}, {p[1][1]:.4f}") if p else ("—", "—")
            lines.append(f"| {model} | {_fmt(m[CLEAN], 'map')} | {_fmt(m[CLEAN], 'nds')} "
                         f"| {_fmt(m[f'{c}-aligned'], 'map')} | {_fmt(m[f'{c}-aligned'], 'nds')} "
                         f"| {_fmt(m[f'{c}-unaligned'], 'map')} | {ptxt[0]} | {ptxt[1]} |")
        lines.append("")
    return "\n".join(lines)


def planned_work(run: DetectRun, conditions: list[str], variants: list[str]
                 ) -> tuple[list[tuple[protocol.TrainJob | None, dict[str, str]]], list[Evaluation]]:
    """Every training (pretraining per seed with a learning curve, then the finetunings of the first seed's model)
    and every evaluation of the protocol."""
    cfg, seeds = run.cfg, list(run.cfg.seeds)
    s0 = seeds[0]
    trainings = [(run.train_job(f"seed{s}/pretrained", CLEAN, None, cfg.pretrain_steps, cfg.lr, s,
                                learning_curve=True), run.dataroot_tags(CLEAN)) for s in seeds]
    evaluations: list[Evaluation] = []
    for s in seeds:
        evaluations += [Evaluation("pretrained", s, d) for d in [CLEAN, *variants]]
        evaluations += [Evaluation("pretrained", s, CLEAN, m) for m in ("lidar", "camera")]
        evaluations += [Evaluation("pretrained", s, CLEAN, shuffled=True)]
        evaluations += [Evaluation("pretrained", s, camera_weather_set(v)) for v in variants]
    for c in conditions:
        for suffix, train_on, alignment in (("", f"{c}-aligned", "aligned"),
                                            ("-unaligned", f"{c}-unaligned", "unaligned"),
                                            ("-mix", (f"{c}-aligned", CLEAN), "aligned")):
            name = f"finetuned-{c}{suffix}"
            trainings.append((run.train_job(f"seed{s0}/{name}", train_on, f"seed{s0}/pretrained",
                                            cfg.finetune_steps, cfg.finetune_lr, s0),
                              run.dataroot_tags(f"{c}-{alignment}")))
            evaluations += [Evaluation(name, s0, d) for d in (CLEAN, f"{c}-aligned", f"{c}-unaligned")]
    return trainings, evaluations


def comparisons_of(evaluations: list[Evaluation], conditions: list[str], variants: list[str]
                   ) -> tuple[dict[str, tuple[list[str], None]], dict[str, tuple[list[str], list[str]]]]:
    """(the pooled estimate of every evaluated (model, evaluation set): its evaluation keys over the seeds; the
    paired differences, ``name: (keys_a, keys_b)``, named ``model:weather:comparison`` (the metric is appended))."""
    keys: dict[tuple[str, str], list[str]] = {}
    for e in evaluations:
        keys.setdefault((e.label, e.evalset), []).append(e.key)
    singles = {f"{label}|{evalset}": (k, None) for (label, evalset), k in keys.items()}
    pre = lambda evalset, label="pretrained": keys[(label, evalset)]  # noqa: E731
    pairs: dict[str, tuple[list[str], list[str]]] = {}
    for v in variants:
        if v.endswith("-aligned"):
            c = v.removesuffix("-aligned")
            pairs[f"pretrained:{c}:unaligned-aligned"] = (pre(f"{c}-unaligned"), pre(v))
            pairs[f"pretrained:{c}:clean-aligned_cameras"] = (pre(CLEAN), pre(camera_weather_set(v)))
            pairs[f"pretrained:{c}:unaligned_cameras-aligned_cameras"] = (pre(camera_weather_set(f"{c}-unaligned")),
                                                                         pre(camera_weather_set(v)))
    for other, label in (("lidar", "pretrained-lidar_only"), ("camera", "pretrained-camera_only"),
                         ("shuffled_images", "pretrained-shuffled_images")):
        pairs[f"pretrained:clean:fused-{other}"] = (pre(CLEAN), pre(CLEAN, label))
    for c in conditions:
        pairs[f"finetuned-{c}-vs-pretrained:{c}-aligned"] = (pre(f"{c}-aligned", f"finetuned-{c}"),
                                                             pre(f"{c}-aligned")[:1])
        pairs[f"finetuned-{c}-mix-vs-pretrained:clean"] = (pre(CLEAN, f"finetuned-{c}-mix"), pre(CLEAN)[:1])
        pairs[f"finetuned-{c}-aligned-vs-unaligned:{c}-aligned"] = (pre(f"{c}-aligned", f"finetuned-{c}"),
                                                                    pre(f"{c}-aligned", f"finetuned-{c}-unaligned"))
    return singles, pairs


def summarise(evaluations: list[Evaluation], results: dict[str, dict[str, Any]], pooled: dict[str, dict[str, Any]],
              pairs: dict[str, tuple[list[str], list[str]]]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(models -> evaluation set -> pooled metrics, differences by ``name:metric``) from the per-evaluation results
    and the seed x block estimates."""
    models: dict[str, dict[str, Any]] = {}
    by_set: dict[tuple[str, str], list[Evaluation]] = {}
    for e in evaluations:
        by_set.setdefault((e.label, e.evalset), []).append(e)
    for (label, evalset), evals in by_set.items():
        first = results[evals[0].key]
        est = pooled[f"{label}|{evalset}"]
        models.setdefault(label, {})[evalset] = {
            **{k: first.get(k) for k in SUMMARY_KEYS if k not in ("map", "nds", "map_ci", "nds_ci")},
            "map": est["map"]["value"], "nds": est["nds"]["value"], "map_ci": est["map"]["ci"],
            "nds_ci": est["nds"]["ci"], "map_per_seed": est["map"]["per_seed"], "nds_per_seed": est["nds"]["per_seed"],
            "seeds": [e.seed for e in evals],
            "car_ap_per_seed": [results[e.key]["per_class_ap"]["car"] for e in evals]}
    for label, evals in models.items():
        clean_nds = evals.get(CLEAN, {}).get("nds", 0.0)
        for m in evals.values():
            m["ra"] = resistance_ability(m["nds"], clean_nds) if clean_nds > 0 else None
    differences = {}
    for name, est in pooled.items():
        if "|" in name:
            continue
        for metric in ("map", "nds"):
            d = est[metric]
            a, b = (keys[0].split("/", 1)[1] for keys in pairs[name])  # "<model>/<evaluation set>"
            differences[f"{name}:{metric}"] = {"a": a, "b": b, "metric": metric, "difference": d["value"],
                                              "ci": d["ci"], "per_seed": d["per_seed"], "seeds": len(d["per_seed"]),
                                              "exceeds_noise": bool(d["ci"][0] > 0 or d["ci"][1] < 0)}
    return models, differences


def headline(details: dict[str, Any], finetuned: list[str]) -> dict[str, Any]:
    """reports/detect/metrics.json: the pretrained model's clean mAP and NDS, its mAP on every weather copy (Table 2's
    aligned and unaligned columns) and the finetuned models' mAP on their weather's aligned copy (Table 3); the rest
    (intervals, the modality ablation, the differences with their intervals) in details.json, the tables and MLflow."""
    models = details["models"]
    clean = models["pretrained"][CLEAN]
    return {
        "clean": {"map": clean["map"], "nds": clean["nds"]},
        "map": {evalset: m["map"] for evalset, m in models["pretrained"].items()
                if evalset != CLEAN and not evalset.startswith(CAMERA_WEATHER_PREFIX)},
        "finetuned_map": {c: models[f"finetuned-{c}"][f"{c}-aligned"]["map"] for c in finetuned}}


@flow(name="detect", log_prints=True)
def detect_flow(params: Params) -> dict:
    """Train and evaluate every model of the protocol; returns the metrics written to reports/detect/."""
    cfg = params.detect
    t_stage = time.time()
    with StageTracker(params, "detect") as tracker:
        tracker.log_params({"detect": cfg.model_dump(mode="json"), "simulate.sweeps": params.simulate.sweeps})
        run = DetectRun(params, tracker)
        conditions = list(cfg.finetune_conditions)
        variants = [v for v in run.roots if v != CLEAN]
        seeds = list(cfg.seeds)
        trainings, evaluations = planned_work(run, conditions, variants)
        run.log_inputs(list(dict.fromkeys(d for e in evaluations for d in run.evalset_roots(e.evalset))),
                       [CLEAN] + [d for c in conditions for d in (f"{c}-aligned", f"{c}-unaligned")])
        results = run.run_jobs(trainings, evaluations)
        singles, pairs = comparisons_of(evaluations, conditions, variants)
        pooled = run.pooled({**singles, **pairs})
        models, differences = summarise(evaluations, results, pooled, pairs)
        pre = models["pretrained"][CLEAN]
        ablation = {"fused": pre, **{m: models[f"pretrained-{m}"][CLEAN]
                                     for m in ("lidar_only", "camera_only", "shuffled_images")}}
        s0 = seeds[0]
        metas = {s: run.metas.get(f"seed{s}/pretrained", {}) for s in seeds}
        metrics = {
            "models": models,
            "modality_ablation": {m: {k: v.get(k) for k in ("map", "nds", "map_ci", "nds_ci", "map_per_seed",
                                                            "nds_per_seed", "car_ap_per_seed")}
                                  for m, v in ablation.items()},
            "differences": differences, "confidence": cfg.confidence, "num_bootstrap": cfg.num_bootstrap,
            "seeds": seeds, "scene_block": cfg.scene_block,
            "learning_curve": {str(s): m.get("curve", []) for s, m in metas.items()},
            "train_seconds": {k: round(m.get("seconds", 0.0), 1) for k, m in run.metas.items()},
            "parameters": count_parameters(BEVFusionDetector(run.model_config)), "device": str(run.device),
            "image_size": list(cfg.image_size), "val_samples": len(run.tokens["val"]),
            "train_samples": len(run.tokens["train"]), "sweeps": params.simulate.sweeps,
            "input_digests": input_digests(params, variants), "seconds": round(time.time() - t_stage, 1)}
        reports = tracker.reports
        atomic.write_text(reports / "table_alignment.md", table_alignment(metrics, [
            v.rsplit("-", 1)[0] for v in variants if v.endswith("-aligned")]))
        atomic.write_text(reports / "table_finetune.md", table_finetune(metrics, conditions))
        fig = learning_curve_figure(metas[s0].get("curve", []), metas[s0].get("losses", []))
        fig.savefig(reports / "learning_curve.png", dpi=110)
        plt.close(fig)
        first = conditions[0] if conditions else variants[0].rsplit("-", 1)[0]
        fig = detections_bev_figure([run.evalset(CLEAN), run.evalset(f"{first}-aligned")],
                                    [run.detections[Evaluation("pretrained", s0, CLEAN).key],
                                     run.detections[Evaluation("pretrained", s0, f"{first}-aligned").key]],
                                    cfg.bev_range_m)
        fig.savefig(reports / "predictions_bev.png", dpi=110)
        plt.close(fig)
        atomic.write_json(reports / "learning_curve.json",
                          learning_curve_rows([metas[s].get("curve", []) for s in seeds]), indent=1)
        atomic.write_json(reports / "per_class_ap.json", per_class_rows(pre["per_class_ap"]), indent=1)
        for name in ("table_alignment.md", "table_finetune.md", "learning_curve.png", "predictions_bev.png"):
            tracker.log_artifact(reports / name, "detect")
        pruned = run.prune_caches()
        if pruned:
            print(f"detect: removed {len(pruned)} caches of earlier versions of its datasets "
                  f"({', '.join(p.name for p in pruned)})")
        tracker.finish(metrics, headline(metrics, conditions), logged={k: v for k, v in metrics.items() if k in (
            "parameters", "val_samples", "train_samples", "sweeps", "seconds")}, children={
            key: difference_run(key, d) for key, d in differences.items()})
    return metrics


def main(argv: list[str] | None = None) -> dict:
    """Training and evaluation tasks run on worker processes (one core each: one-thread trainings side by side use the
    cores better than one multi-threaded training) on the CPU, on threads of this process on a GPU."""
    params = parse_stage_args("detect", argv)
    on_cpu = torch.device(params.detect.device).type == "cpu"
    return run_stage(detect_flow, params, runner="processes" if on_cpu else "threads")


if __name__ == "__main__":
    main()
