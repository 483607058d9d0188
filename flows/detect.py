"""`detect` stage: the paper's perception check with a small BEVFusion-style detector trained here.

``python -m flows.detect`` reads the world's manifest (the clean dataroot) and the weather copies of the `simulate`
matrix (``<paths.data>/simulate/<condition>-<aligned|unaligned>``), caches each split it needs once
(`weatheralign.detect.data.build_cache`: downsized cameras, the keyframe and ``simulate.sweeps`` sweeps), then

1. pretrains on the clean train split (learning curve: val mAP / NDS every ``detect.eval_every`` steps);
2. evaluates it on the clean val split and on the val split of every weather copy, aligned and unaligned (the paper's
   Table 2), and LiDAR-only / camera-only / fused on clean val (the modality ablation);
3. finetunes it on each of ``detect.finetune_conditions``: the aligned train split, the unaligned one, and the
   aligned one mixed 30/70 with clean at the data-loader level, each evaluated on clean val and on its weather's
   aligned and unaligned val (Table 3, and whether unaligned training buys less robustness);
4. writes ``reports/detect/metrics.json`` (models -> evaluation sets -> metrics with frame-bootstrap intervals and
   RA = NDS_weather / NDS_clean), paired-bootstrap differences, ``table_alignment.md`` and ``table_finetune.md``
   (the paper's figures beside ours, labelled), ``learning_curve.png`` and ``predictions_bev.png``.

Every training and evaluation is an MLflow child run tagged ``model``, ``weather``, ``alignment``. Finished models
(``<paths.data>/detect/models/<model>.pt``) and evaluations (``<paths.data>/detect/evals/``) are kept with the
fingerprint of the code, params and the data each was made from (the cache keys of its training or evaluation split,
which change with any file of it, and the model it started from): an interrupted run resumes after the last finished
one, and a weather copy simulated again retrains and re-evaluates what used it.
"""

from __future__ import annotations

import hashlib
import json
import time
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
from tasks.tracking import REGISTERED_MODEL_PREFIX, ChildRun, StageTracker  # noqa: E402
from weatheralign import atomic  # noqa: E402
from weatheralign.conditions import CONDITIONS, condition_named, condition_tags, variant_name  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.data.errors import DataFormatError  # noqa: E402
from weatheralign.data.nuscenes import open_nuscenes  # noqa: E402
from weatheralign.detect import protocol  # noqa: E402
from weatheralign.detect.data import (DetectionDataset, build_cache, cache_path, load_cached_sample,  # noqa: E402
                                      scene_split)
from weatheralign.detect.evaluate import ego_positions, ground_truth, resistance_ability  # noqa: E402
from weatheralign.detect.figures import detections_bev_figure, learning_curve_figure  # noqa: E402
from weatheralign.detect.model import BEVFusionDetector, count_parameters  # noqa: E402
from weatheralign.simulate.media import media_path, read_media  # noqa: E402
from weatheralign.manifest import manifest_path, read_manifest  # noqa: E402
from weatheralign.provenance import stage_fingerprint  # noqa: E402

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


class DetectRun:
    """What one run of the stage shares: params, device, caches, evaluation sets, resume folders, tracker."""

    def __init__(self, params: Params, tracker: StageTracker) -> None:
        cfg = params.detect
        self.params, self.cfg, self.tracker = params, cfg, tracker
        for name in cfg.finetune_conditions:
            condition_named(name)
        self.device = protocol.resolve_device(cfg.device)
        torch.set_num_threads(params.run.torch_threads)
        #: torch threads of each finetuning / prediction task (a worker process per core on the CPU)
        self.threads = threads_per_task(params) if self.device.type == "cpu" else params.run.torch_threads
        world = read_manifest(manifest_path(params.paths.data, "world"))
        self.version = world.version
        self.clean_root = Path(world.dataroot)
        self.roots = {CLEAN: self.clean_root, **weather_roots(params, self.version)}
        self.nusc = open_nuscenes(self.clean_root, self.version)
        self.tokens = {split: scene_split(self.nusc, self.clean_root, self.version, split) for split in ("train", "val")}
        self.out = params.paths.data / "detect"
        self.fingerprint = stage_fingerprint("detect", params, world.content_digest)
        self.model_config = protocol.detector_config(cfg)
        self.caches: dict[tuple[str, str], Path] = {}
        self.data_keys: dict[tuple[str, str], str] = {}
        self.evalsets: dict[str, protocol.EvalSet] = {}
        self.gt = ground_truth(self.nusc, self.tokens["val"])
        self.ego = ego_positions(self.nusc, self.tokens["val"])
        self.model_fingerprints: dict[str, str] = {}
        self.curves: dict[str, list[dict[str, float]]] = {}
        self.train_seconds: dict[str, float] = {}
        self.losses: dict[str, list[float]] = {}
        self.detections: dict[str, list] = {}
        self.model_versions: dict[str, str] = {}  # registry versions of the models trained by this run

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
        from, so that a weather copy simulated again is not mistaken for the one a checkpoint was trained on.
        Computed once per run (the datasets do not change while the stage runs; ~0.2 s of file stats each)."""
        key = (dataroot, split)
        if key not in self.data_keys:
            self.data_keys[key] = cache_path(self.roots[dataroot], self.version, self.tokens[split],
                                             self.out / "cache", self.cfg.image_size, self.params.simulate.sweeps).name
        return self.data_keys[key]

    def evalset(self, dataroot: str) -> protocol.EvalSet:
        if dataroot not in self.evalsets:
            folder = self.cache(dataroot, "val")
            ds = DetectionDataset(folder, None, point_range=protocol.point_range(self.cfg), min_lidar_pts=0)
            T = {t: load_cached_sample(folder, t)["T_global_lidar"] for t in ds.tokens}
            self.evalsets[dataroot] = protocol.EvalSet(dataroot, ds, self.gt, T, self.ego)
        return self.evalsets[dataroot]

    # -------------------------------------------------------------------------------------------- models

    def _model_fingerprint(self, name: str, train_on: str | tuple[str, str], init: str | None, steps: int,
                           lr: float) -> str:
        """What model ``name`` is made from: code, params, the cache keys of its training data, the model it starts
        from (`model`); remembered for its evaluations' fingerprints."""
        sources = train_on if isinstance(train_on, tuple) else (train_on,)
        fingerprint = hashlib.sha256(json.dumps([
            self.fingerprint, name, list(sources), [self.data_key(d, "train") for d in sources],
            init, self.model_fingerprints.get(init) if init else None, steps, lr]).encode()).hexdigest()[:16]
        self.model_fingerprints[name] = fingerprint
        return fingerprint

    def _finished_model(self, name: str, fingerprint: str) -> bool:
        """Whether model ``name``'s checkpoint was made from ``fingerprint`` (then its curve and losses are read)."""
        path = self.checkpoint(name)
        if not path.is_file():
            return False
        meta = torch.load(path, map_location="cpu", weights_only=False)["meta"]
        if meta.get("fingerprint") != fingerprint:
            return False
        self.curves[name], self.losses[name] = meta.get("curve", []), meta.get("losses", [])
        self.train_seconds[name] = meta.get("seconds", 0.0)
        return True

    def checkpoint(self, name: str) -> Path:
        return self.out / "models" / f"{name}.pt"

    def model(self, name: str, train_on: str, init: str | None, steps: int, lr: float, tags: dict[str, str],
              learning_curve: bool = False) -> BEVFusionDetector:
        """The trained model ``name``, trained here on ``train_on``'s train split with ``run.torch_threads`` threads
        (resumed from its checkpoint when its fingerprint matches), from model ``init`` (None: from scratch); with
        ``learning_curve``, the clean val mAP / NDS every ``detect.eval_every`` steps."""
        fingerprint = self._model_fingerprint(name, train_on, init, steps, lr)
        if self._finished_model(name, fingerprint):
            return protocol.load_checkpoint(self.checkpoint(name), self.model_config)[0].to(self.device)
        torch.manual_seed(self.cfg.seed)  # the initial weights: a function of the seed alone
        model = (protocol.load_checkpoint(self.checkpoint(init), self.model_config)[0] if init
                 else BEVFusionDetector(self.model_config))
        dataset, sampler = protocol.training_dataset([self.cache(train_on, "train")], self.cfg)
        curve: list[dict[str, float]] = []
        t0 = time.time()
        with self.tracker.child(f"train {name}", {**tags, "model": name, "kind": "train"}) as run:
            run.log_params({"train_on": str(train_on), "init": str(init), "steps": steps, "lr": lr,
                            "parameters": count_parameters(model)})

            def on_step(step: int, record: dict[str, float]) -> None:
                if step % 10 == 0 or step == steps:
                    run.log_metrics({f"loss.{k}": v for k, v in record.items()}, step)
                if curve_every and (step % curve_every == 0 or step == steps):
                    m = self.score(model, CLEAN, num_bootstrap=0)
                    point = {"step": step, "map": m["map"], "nds": m["nds"], "map_present": m["map_present"],
                             "seconds": round(time.time() - t0, 1)}
                    curve.append(point)
                    run.log_metrics({"val.map": m["map"], "val.nds": m["nds"]}, step)

            curve_every = (self.cfg.eval_every or steps) if learning_curve else 0
            history = protocol.train(model, dataset, steps, lr, self.cfg.weight_decay, self.cfg.batch_size,
                                     self.cfg.seed, self.device, sampler, f"detect: train {name}",
                                     self.params.run.show_progress, on_step)
            seconds = time.time() - t0
            losses = [round(h["total"], 5) for h in history]
            protocol.save_checkpoint(self.checkpoint(name), model, {
                "fingerprint": fingerprint, "curve": curve, "losses": losses, "seconds": seconds, "steps": steps})
            run.log_metrics({"train_seconds": seconds, "seconds_per_step": seconds / max(steps, 1)})
            run.log_artifact(self.checkpoint(name), "checkpoint")
            self.register(run, name, model)
        self.curves[name], self.losses[name], self.train_seconds[name] = curve, losses, seconds
        return model

    def register(self, run: ChildRun, name: str, model: BEVFusionDetector) -> None:
        """Log trained model ``name`` to its training run as an MLflow PyTorch model and register it (a new version
        of ``weatheralign-detector-<name>``); its evaluations tag that version with their mAP / NDS."""
        version = run.log_model(model.cpu() if self.device.type != "cpu" else model, REGISTERED_MODEL_PREFIX + name)
        if self.device.type != "cpu":
            model.to(self.device)
        if version is not None:
            self.model_versions[name] = version

    def train_job(self, name: str, train_on: str | tuple[str, str], init: str, steps: int, lr: float
                  ) -> protocol.TrainJob | None:
        """The job that trains model ``name`` from model ``init`` on ``train_on`` (one dataroot's train split, or
        ``(weather, CLEAN)`` mixed at ``detect.mix_weather_fraction``) in a worker; None when its checkpoint is
        finished. The caches it reads are built here first."""
        fingerprint = self._model_fingerprint(name, train_on, init, steps, lr)
        if self._finished_model(name, fingerprint):
            return None
        sources = train_on if isinstance(train_on, tuple) else (train_on,)
        return protocol.TrainJob(name, tuple(self.cache(d, "train") for d in sources), self.checkpoint(init), steps,
                                 lr, self.checkpoint(name), fingerprint, self.cfg, str(self.device), self.threads)

    def record_training(self, job: protocol.TrainJob, meta: dict[str, Any], tags: dict[str, str]) -> None:
        """A finished `TrainJob`'s MLflow child run (losses every 10 steps, seconds, checkpoint) and its losses."""
        with self.tracker.child(f"train {job.name}", {**tags, "model": job.name, "kind": "train"}) as run:
            run.log_params({"train_on": ",".join(c.name for c in job.caches), "init": job.init.stem if job.init
                            else "None", "steps": job.steps, "lr": job.lr})
            for step, loss in enumerate(meta["losses"], start=1):
                if step % 10 == 0 or step == job.steps:
                    run.log_metrics({"loss.total": loss}, step)
            run.log_metrics({"train_seconds": meta["seconds"], "seconds_per_step": meta["seconds"] / max(job.steps, 1)})
            run.log_artifact(job.out, "checkpoint")
            self.register(run, job.name, protocol.load_checkpoint(job.out, self.model_config)[0])
        self.curves[job.name], self.losses[job.name] = [], meta["losses"]
        self.train_seconds[job.name] = meta["seconds"]

    # -------------------------------------------------------------------------------------------- evaluation

    def score(self, model: BEVFusionDetector, dataroot: str, num_bootstrap: int | None = None,
              modality: str = "fused") -> dict[str, Any]:
        evalset = self.evalset(dataroot)
        detections = protocol.predict(model, evalset.dataset, self.cfg.batch_size, self.device,
                                      self.cfg.score_threshold, self.cfg.max_detections, modality)
        return self.scored(detections, dataroot, num_bootstrap)

    def scored(self, detections: list, dataroot: str, num_bootstrap: int | None = None) -> dict[str, Any]:
        n = self.cfg.num_bootstrap if num_bootstrap is None else num_bootstrap
        result = protocol.evaluate(detections, self.evalset(dataroot), n, self.cfg.seed, self.cfg.confidence)
        result["_detections"] = detections
        return result

    def _evaluation_files(self, model_name: str, dataroot: str, modality: str) -> tuple[str, Path, Path, str]:
        key = f"{model_name}/{dataroot}" + ("" if modality == "fused" else f"-{modality}")
        fingerprint = f"{self.model_fingerprints[model_name]}:{self.data_key(dataroot, 'val')}:{modality}"
        return key, self.out / "evals" / f"{key}.json", self.out / "evals" / f"{key}.npz", fingerprint

    def finished_evaluation(self, model_name: str, dataroot: str, modality: str = "fused") -> dict[str, Any] | None:
        """The metrics of ``model_name`` on ``dataroot``'s val split when an earlier run finished them with the same
        fingerprint (model, data, modality), its detections kept for paired differences; else None."""
        key, record_path, det_path, fingerprint = self._evaluation_files(model_name, dataroot, modality)
        if not (record_path.is_file() and det_path.is_file()):
            return None
        record = json.loads(record_path.read_text())
        if record.get("fingerprint") != fingerprint:
            return None
        with np.load(det_path) as z:
            self.detections[key] = protocol.detections_from_arrays(dict(z))
        return record["metrics"]

    def predict_job(self, model_name: str, dataroot: str, modality: str = "fused") -> protocol.PredictJob:
        return protocol.PredictJob(self.checkpoint(model_name), self.cache(dataroot, "val"), modality, self.cfg,
                                   str(self.device), self.threads)

    def record_evaluation(self, model_name: str, dataroot: str, modality: str, detections: list) -> dict[str, Any]:
        """Score ``detections`` of ``model_name`` on ``dataroot``'s val split (intervals included), keep them and
        their metrics for a resumed run, and log an MLflow child run."""
        key, record_path, det_path, fingerprint = self._evaluation_files(model_name, dataroot, modality)
        result = self.scored(detections, dataroot)
        result.pop("_detections")
        atomic.save_npz(det_path, protocol.detections_to_arrays(detections), compress=True)
        atomic.write_json(record_path, {"fingerprint": fingerprint, "metrics": result})
        self.detections[key] = detections
        with self.tracker.child(f"eval {key}", {**self.dataroot_tags(dataroot), "model": model_name,
                                                "modality": modality, "kind": "eval"}) as run:
            headline = {k: v for k, v in result.items() if k in ("map", "nds", "map_present", "mate", "mase", "maoe",
                                                                 "mave", "maae")}
            run.log_metrics(headline)
            run.log_metrics({f"ap.{c}": v for c, v in result["per_class_ap"].items()})
        if model_name in self.model_versions and modality == "fused":
            self.tracker.tag_model_version(REGISTERED_MODEL_PREFIX + model_name, self.model_versions[model_name],
                                           {f"{k}.{dataroot}": f"{v:.4f}" for k, v in headline.items()
                                            if k in ("map", "nds")})
        return result

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

    def run_jobs(self, trainings: list[tuple[str, str | tuple[str, str], dict[str, str]]],
                 evaluations: list[tuple[str, str, str]]) -> dict[tuple[str, str, str], dict[str, Any]]:
        """Finetune every ``(name, train_on, tags)`` of ``trainings`` from the pretrained model and evaluate every
        ``(model, dataroot, modality)`` of ``evaluations``, the unfinished ones as tasks on the stage's task runner
        (worker processes: one core each); results are scored and recorded here as they come in. Returns the
        metrics of every evaluation."""
        cfg = self.cfg
        jobs = {name: (self.train_job(name, train_on, "pretrained", cfg.finetune_steps, cfg.finetune_lr), tags)
                for name, train_on, tags in trainings}
        for dataroot in {d for _, d, _ in evaluations}:
            self.cache(dataroot, "val")
        trained = {name: train_task.submit(job) for name, (job, _) in jobs.items() if job is not None}
        metrics = {spec: m for spec in evaluations if (m := self.finished_evaluation(*spec)) is not None}
        pending = [spec for spec in evaluations if spec not in metrics]
        futures = [predict_task.submit(self.predict_job(*spec), wait_for=[trained[spec[0]]] if spec[0] in trained
                                       else []) for spec in pending]

        names = list(trained)

        def on_result(i: int, result: Any) -> None:
            if i < len(names):
                self.record_training(jobs[names[i]][0], result, jobs[names[i]][1])
            else:
                spec = pending[i - len(names)]
                metrics[spec] = self.record_evaluation(*spec, protocol.detections_from_arrays(result))

        gather([trained[n] for n in names] + futures, "detect: finetune and evaluate", self.params.run.show_progress,
               on_result)
        return metrics

    def paired(self, comparisons: dict[str, tuple[str, str, str, str | None]]) -> dict[str, dict[str, Any]]:
        """Per ``name: (key_a, key_b, metric, dataroot)``: ``metric(a) - metric(b)`` on the same val samples (those
        of ``dataroot``, None: ``key_a``'s) with a paired frame-bootstrap interval, and whether the interval excludes
        0. Each pair of evaluations is bootstrapped once for all its metrics, the pairs as tasks on the stage's task
        runner."""
        pairs: dict[tuple[str, str, str], list[str]] = {}
        for a, b, metric, dataroot in comparisons.values():
            pairs.setdefault((a, b, dataroot or a.split("/")[1]), []).append(metric)
        futures = []
        for (a, b, dataroot), metrics in pairs.items():
            ea = self.evalset(dataroot)
            futures.append(paired_task.submit(self.gt, protocol.eval_boxes(self.detections[a], ea),
                                              protocol.eval_boxes(self.detections[b], ea), tuple(dict.fromkeys(metrics)),
                                              self.cfg.num_bootstrap, self.cfg.seed, self.cfg.confidence))
        results = dict(zip(pairs, gather(futures, "detect: paired differences", self.params.run.show_progress)))
        out = {}
        for name, (a, b, metric, dataroot) in comparisons.items():
            diff, ci = results[(a, b, dataroot or a.split("/")[1])][metric]
            out[name] = {"a": a, "b": b, "metric": metric, "difference": diff, "ci": ci,
                         "exceeds_noise": bool(ci[0] > 0 or ci[1] < 0)}
        return out


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


def table_alignment(metrics: dict[str, Any], conditions: list[str]) -> str:
    """Table 2: the pretrained model on every weather, aligned vs unaligned (ours with intervals; the paper's
    BEVFusion figures beside, labelled)."""
    pre = metrics["models"]["pretrained"]
    lines = ["# Pretrained detector on aligned vs unaligned weather (the paper's Table 2)", "",
             f"Clean val: mAP {_fmt(pre[CLEAN], 'map')}, NDS {_fmt(pre[CLEAN], 'nds')}; intervals: "
             f"{metrics['confidence']:.0%} frame bootstrap. The paper's figures are BEVFusion on real nuScenes-mini "
             "with the paper's simulations, for comparison only.", "",
             *modality_lines(metrics), "",
             "| weather | unaligned mAP | unaligned NDS | aligned mAP | aligned NDS | unaligned - aligned mAP "
             "| RA aligned | paper unaligned (mAP, NDS) | paper aligned (mAP, NDS) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in conditions:
        u, a = pre[f"{c}-unaligned"], pre[f"{c}-aligned"]
        d = metrics["differences"].get(f"pretrained:{c}:unaligned-aligned:map")
        dtxt = f"{d['difference']:+.3f} [{d['ci'][0]:+.3f}, {d['ci'][1]:+.3f}]" if d else "—"
        paper = protocol.PAPER_TABLE2.get(c)
        ptxt = (f"{paper['unaligned'][0]:.4f}, {paper['unaligned'][1]:.4f}",
                f"{paper['aligned'][0]:.4f}, {paper['aligned'][1]:.4f}") if paper else ("—", "—")
        lines.append(f"| {c} | {_fmt(u, 'map')} | {_fmt(u, 'nds')} | {_fmt(a, 'map')} | {_fmt(a, 'nds')} | {dtxt} "
                     f"| {'—' if a['ra'] is None else format(a['ra'], '.3f')} | {ptxt[0]} | {ptxt[1]} |")
    return "\n".join(lines) + "\n"


def modality_lines(metrics: dict[str, Any]) -> list[str]:
    """The modality ablation of the pretrained model on clean val, and what each sensor adds to the other (paired
    frame-bootstrap differences of mAP)."""
    ablation, differences = metrics["modality_ablation"], metrics["differences"]
    parts = [f"{m} {_fmt(ablation[m], 'map')}" for m in ("fused", "lidar_only", "camera_only") if m in ablation]
    adds = []
    for other, sensor in (("lidar", "camera"), ("camera", "LiDAR")):
        d = differences.get(f"pretrained:clean:fused-{other}:map")
        if d:
            adds.append(f"the {sensor} adds {d['difference']:+.3f} [{d['ci'][0]:+.3f}, {d['ci'][1]:+.3f}]"
                        + ("" if d["exceeds_noise"] else " (within the noise)"))
    return [f"Modality ablation, clean val mAP: {', '.join(parts)}" + (f"; {'; '.join(adds)}." if adds else ".")]


def table_finetune(metrics: dict[str, Any], conditions: list[str]) -> str:
    """Table 3: pretrained / finetuned / finetuned-mix / finetuned-unaligned on clean and on the weather."""
    lines = ["# Finetuning on simulated weather (the paper's Table 3)", "",
             f"mAP and NDS with {metrics['confidence']:.0%} frame-bootstrap intervals. `paper` columns: BEVFusion on "
             "real nuScenes-mini (the paper's figures; its fog column beside our fog conditions).", ""]
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
        pretrained = run.model("pretrained", CLEAN, None, cfg.pretrain_steps, cfg.lr,
                               run.dataroot_tags(CLEAN), learning_curve=True)
        trainings: list[tuple[str, str | tuple[str, str], dict[str, str]]] = []
        evaluations = [("pretrained", d, "fused") for d in [CLEAN, *variants]]
        evaluations += [("pretrained", CLEAN, m) for m in ("lidar", "camera")]
        for c in conditions:
            for suffix, train_on, alignment in (("", f"{c}-aligned", "aligned"),
                                                ("-unaligned", f"{c}-unaligned", "unaligned"),
                                                ("-mix", (f"{c}-aligned", CLEAN), "aligned")):
                trainings.append((f"finetuned-{c}{suffix}", train_on, run.dataroot_tags(f"{c}-{alignment}")))
                evaluations += [(f"finetuned-{c}{suffix}", d, "fused") for d in (CLEAN, f"{c}-aligned",
                                                                                 f"{c}-unaligned")]
        run.log_inputs([d for _, d, _ in evaluations], [CLEAN] + [d for _, t, _ in trainings
                                                                  for d in ((t,) if isinstance(t, str) else t)])
        results = run.run_jobs(trainings, evaluations)
        models: dict[str, dict[str, Any]] = {}
        for name, dataroot, modality in evaluations:
            if modality == "fused":
                models.setdefault(name, {})[dataroot] = results[(name, dataroot, modality)]
        ablation = {f"{m}_only": results[("pretrained", CLEAN, m)] for m in ("lidar", "camera")}
        ablation["fused"] = models["pretrained"][CLEAN]

        for name, evals in models.items():
            for d, m in evals.items():
                m["ra"] = resistance_ability(m["nds"], evals[CLEAN]["nds"]) if evals[CLEAN]["nds"] > 0 else None
        comparisons: dict[str, tuple[str, str, str, str | None]] = {}  # name: (a, b, metric, dataroot)
        for c in [v.rsplit("-", 1)[0] for v in variants if v.endswith("-aligned")]:
            for metric in ("map", "nds"):
                comparisons[f"pretrained:{c}:unaligned-aligned:{metric}"] = (
                    f"pretrained/{c}-unaligned", f"pretrained/{c}-aligned", metric, None)
        for metric in ("map", "nds"):  # does each sensor add to the other?
            for other in ("lidar", "camera"):
                comparisons[f"pretrained:clean:fused-{other}:{metric}"] = (
                    f"pretrained/{CLEAN}", f"pretrained/{CLEAN}-{other}", metric, CLEAN)
        for c in conditions:
            for metric in ("map", "nds"):
                comparisons[f"finetuned-{c}-vs-pretrained:{c}-aligned:{metric}"] = (
                    f"finetuned-{c}/{c}-aligned", f"pretrained/{c}-aligned", metric, None)
                comparisons[f"finetuned-{c}-mix-vs-pretrained:clean:{metric}"] = (
                    f"finetuned-{c}-mix/{CLEAN}", f"pretrained/{CLEAN}", metric, None)
                comparisons[f"finetuned-{c}-aligned-vs-unaligned:{c}-aligned:{metric}"] = (
                    f"finetuned-{c}/{c}-aligned", f"finetuned-{c}-unaligned/{c}-aligned", metric, None)
        differences = run.paired(comparisons)

        metrics = {
            "models": {n: {d: {k: m.get(k) for k in (*SUMMARY_KEYS, "ra")} for d, m in e.items()}
                       for n, e in models.items()},
            "modality_ablation": {m: {"map": v["map"], "nds": v["nds"], "map_ci": v.get("map_ci"),
                                      "nds_ci": v.get("nds_ci")} for m, v in ablation.items()},
            "differences": differences, "confidence": cfg.confidence, "num_bootstrap": cfg.num_bootstrap,
            "learning_curve": run.curves.get("pretrained", []),
            "train_seconds": {k: round(v, 1) for k, v in run.train_seconds.items()},
            "parameters": count_parameters(pretrained), "device": str(run.device),
            "val_samples": len(run.tokens["val"]), "train_samples": len(run.tokens["train"]),
            "sweeps": params.simulate.sweeps, "seconds": round(time.time() - t_stage, 1)}
        reports = tracker.reports
        atomic.write_text(reports / "table_alignment.md", table_alignment(metrics, [
            v.rsplit("-", 1)[0] for v in variants if v.endswith("-aligned")]))
        atomic.write_text(reports / "table_finetune.md", table_finetune(metrics, conditions))
        fig = learning_curve_figure(run.curves.get("pretrained", []), run.losses.get("pretrained", []))
        fig.savefig(reports / "learning_curve.png", dpi=110)
        plt.close(fig)
        first = conditions[0] if conditions else variants[0].rsplit("-", 1)[0]
        fig = detections_bev_figure([run.evalset(CLEAN), run.evalset(f"{first}-aligned")],
                                    [run.detections[f"pretrained/{CLEAN}"],
                                     run.detections[f"pretrained/{first}-aligned"]], cfg.bev_range_m)
        fig.savefig(reports / "predictions_bev.png", dpi=110)
        plt.close(fig)
        for name in ("table_alignment.md", "table_finetune.md", "learning_curve.png", "predictions_bev.png"):
            tracker.log_artifact(reports / name, "detect")
        tracker.finish(metrics, logged={k: v for k, v in metrics.items() if k in (
            "parameters", "val_samples", "train_samples", "sweeps", "seconds")}, children={
            key: difference_run(key, d) for key, d in differences.items()})
    return metrics


def main(argv: list[str] | None = None) -> dict:
    """Finetuning and evaluation tasks run on worker processes (one core each: two one-thread trainings do 1.26x the
    steps of one two-thread training on two cores) on the CPU, on threads of this process on a GPU."""
    params = parse_stage_args("detect", argv)
    on_cpu = torch.device(params.detect.device).type == "cpu"
    return run_stage(detect_flow, params, runner="processes" if on_cpu else "threads")


if __name__ == "__main__":
    main()
