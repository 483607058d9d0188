"""`verify` stage: is the simulated weather the real weather, and does aligning the sensors make it more so?

``python -m flows.verify`` opens the reference of the `reference` stage (every split it has: clear, light and dense
fog, snow, rain) and, for each condition with a reference split (`VERIFIED`: fog_light -> light, fog_dense -> dense,
snow, rain):

1. simulates the reference's clear frames through the condition with the fast simulator (`simulated_pair`: the
   observation core of `simulate`, the reference's LiDAR and stereo-left camera), aligned and unaligned, at the
   severity the simulation uses (the fog levels ``simulate.fog_levels`` selects, the snow / rain rates
   ``simulate.precipitation_rates`` selects: the calibrate_precipitation stage's or the particles params');
2. compares the simulated LiDAR's intensity ECDF with the reference's weather split (D_KS with a frame-bootstrap
   interval) and the simulated images with the reference's (KID on the calibrate_fog backbone; the visibility
   estimated from image + depth, `camera_visibility_ratio`);
3. trains the auxiliary weather classifier (clear / fog / snow / rain) on the reference's real frames, early fusion of
   the image and the LiDAR projected into it, with the correspondence objective (`train_weather_classifier`: true
   pairs against another frame's LiDAR, the frame's own LiDAR shifted, and, for snow and rain frames with particle
   echoes in view, the frame's LiDAR with its particle echoes displaced); its penultimate layer is the fused feature.
   ``verify.classifiers`` classifiers train alike from consecutive seeds; every MMD below uses the mean of their
   kernels (`pooled_kernel`), so that no single training draw decides a verdict (the control's p-value and the
   MMD^2 of each classifier alone are reported beside it), and the bootstrap intervals resample the classifiers as
   well as the frames (`member_weights`: the training noise is in the intervals);
   every training is kept in ``<paths.data>/verify/classifiers`` with a key over its code, inputs and settings, so
   that a rerun or an interrupted run loads the finished ones instead of training them again;
   ``verify.held_out_fraction`` of every reference level (at least two frames) is held out of its training
   (`held_out_split`): the classifier's accuracy is measured on them, and the MMDs below compare only held-out
   reference frames and simulations of held-out clear frames. (Measured: with the MMD's reference frames among the
   training frames, the features told trained-on frames from everything else, and the control's verdict flipped
   between reference sizes: detected at 20 frames per split, p 0.92 at 40.);
4. per condition, on one kernel (Gaussian, median heuristic on the pooled standardised reference, aligned and
   unaligned features): MMD^2 (unbiased) of the reference's weather frames against the aligned and against the
   unaligned simulation with permutation p-values and bootstrap intervals (frames and classifiers), the paired test of
   their difference, and the **sensitivity control**: the reference weather frames against themselves with every
   LiDAR paired with another frame's camera (`paired_mmd_test`: row i of both sets holds frame i's camera, so the
   null swaps within frames and the statistic leaves each frame's own cross term out; an unpaired permutation test
   sees a frame's two rows as near-duplicates). Unaligned snow and rain misalign severity and positions
   (`ParticlePart.camera_rate`); the same tests also run against the unaligned camera at the LiDAR's rate
   (``mmd_*_positions``: positions alone misaligned).

Writes ``reports/verify/details.json`` (``conditions: {<condition>: {...}}`` plus ``classifier_accuracy``,
``control_mmd``, ``control_p``), ``reports/verify/table.md`` (the paper's Table 1 regenerated beside the paper's
real-data figures) and figures (ECDFs, embeddings, permutation histograms, confusion matrix), also logged to MLflow
with one child run per condition. The synthetic reference's sealed truth is never read here.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from prefect import flow  # noqa: E402

from flows.common import gather, parse_stage_args, run_stage  # noqa: E402
from tasks.tracking import StageTracker  # noqa: E402
from tasks.verify import reference_frame_task, simulated_pair_task  # noqa: E402
from weatheralign import atomic  # noqa: E402
from weatheralign.calibrate.camera import camera_visibility_ratio  # noqa: E402
from weatheralign.calibrate.histograms import IntensityHistograms, bootstrap_ks, frame_counts  # noqa: E402
from weatheralign.calibrate.kid import feature_extractor, kid_from_features  # noqa: E402
from weatheralign.conditions import CONDITIONS, variant_name  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.data.errors import DataFormatError  # noqa: E402
from weatheralign.reference import PRECIPITATION_LEVELS, ReferenceDataset, configured_reference, reference_lidar_model  # noqa: E402
from weatheralign.simulate.media import configured_fog_levels, configured_precipitation_rates, resolve_overcast  # noqa: E402
from weatheralign.verify.classifier import (  # noqa: E402
    broken_pairs,
    ensemble_report,
    fused_features,
    held_out_split,
    train_fitted_classifiers,
)
from weatheralign.verify.figures import (  # noqa: E402
    confusion_figure,
    confusion_rows,
    ecdf_figure,
    embedding_figure,
    permutation_figure,
)
from weatheralign.verify.frames import Severity, SimulatedPair  # noqa: E402
from weatheralign.verify.mmd import mmd_test, paired_mmd_difference, paired_mmd_test  # noqa: E402
from weatheralign.verify.table import table_markdown  # noqa: E402

VERIFIED: dict[str, str] = {"fog_light": "light", "fog_dense": "dense", "snow": "snow", "rain": "rain"}
"""Condition -> the reference split holding its real weather (conditions without one, e.g. fog_snow, are not
verified)."""

CLASSES: tuple[str, ...] = ("clear", "fog", "snow", "rain")
CLASS_OF_LEVEL: dict[str, int] = {"clear": 0, "light": 1, "dense": 1, "snow": 2, "rain": 3}


def severity_of(params: Params) -> tuple[Severity, dict[str, str]]:
    """The severity `simulate` uses — the fog levels of ``simulate.fog_levels``, the snow / rain rates and the
    ground of ``simulate.precipitation_rates`` (the ground's params depths where none was calibrated; none with
    ``simulate.ground`` off), the overcast light of each sky (`resolve_overcast`) — and where each rate came from."""
    cfg = params.simulate
    rates = configured_precipitation_rates(cfg, params.particles, params.paths.data)
    ground = {} if not cfg.ground else {"rain": rates.ground_depth_m.get("rain", cfg.wet_film_depth_m),
                                         "snow": rates.ground_depth_m.get("snow", cfg.snow_depth_m)}
    overcast = {c.sky.split: light for c in CONDITIONS.values() if c.sky is not None
                for light in [resolve_overcast(c, cfg, rates)] if light is not None}
    return Severity(configured_fog_levels(cfg, params.paths.data), rates.rate_mm_h["snow"], rates.rate_mm_h["rain"],
                    params.particles, cfg.unaligned_rate_factor, ground, cfg.wet_puddle_share,
                    cfg.ground_seed, overcast), rates.source


def verified_conditions(ds: ReferenceDataset) -> dict[str, str]:
    """The conditions of `VERIFIED` whose reference split ``ds`` has (at least two frames each).

    Raises:
        DataFormatError: no clear split or no weather split to verify against.
    """
    if "clear" not in ds.splits or len(ds.ids("clear")) < 2:
        raise DataFormatError(f"reference {ds.root}: verify needs a clear split of two frames or more")
    out = {c: level for c, level in VERIFIED.items() if level in ds.splits and len(ds.ids(level)) >= 2}
    if not out:
        raise DataFormatError(f"reference {ds.root}: no weather split of two frames or more among "
                              f"{sorted(set(VERIFIED.values()))}")
    return out


def simulate_reports(params: Params, condition: str) -> dict:
    """The aligned simulate stage's figures of ``condition`` (its re-projection errors), or {} when not run."""
    path = params.paths.reports / "simulate" / variant_name(condition, True) / "details.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _figure(fig, path: Path, tracker: StageTracker) -> None:
    fig.savefig(path, dpi=100)
    plt.close(fig)
    tracker.log_artifact(path, "figures")


def condition_metrics(name: str, ref_feat: np.ndarray, sims: list[SimulatedPair], al_feat: np.ndarray,
                      un_feat: np.ndarray, control_feat: np.ndarray, params: Params,
                      pos_feat: np.ndarray | None = None) -> tuple[dict, dict]:
    """The MMD tests of one condition: (metrics, tests for the figures). Features are (classifiers, n, embedding)
    (`weatheralign.verify.mmd.pooled_kernel`: the classifiers' mean kernel). ``pos_feat``: the features of the
    unaligned camera at the LiDAR's rate (positions alone misaligned), tested the same way when given."""
    cfg = params.verify
    kw = {"permutations": cfg.permutations, "resamples": cfg.resamples, "seed": cfg.seed, "confidence": cfg.confidence}
    scale = (ref_feat, al_feat, un_feat)  # one kernel for the condition: aligned - unaligned = the paired difference
    aligned, unaligned = mmd_test(ref_feat, al_feat, scale=scale, **kw), mmd_test(ref_feat, un_feat, scale=scale, **kw)
    control = paired_mmd_test(ref_feat, control_feat, scale=scale, **kw)  # row i of both: frame i's camera
    control_each = [paired_mmd_test(ref_feat[m], control_feat[m], scale=[f[m] for f in scale], **kw).p_value
                    for m in range(len(ref_feat))]  # each classifier alone: the spread over training draws
    diff = paired_mmd_difference(ref_feat, al_feat, un_feat, **kw)
    reproj = np.concatenate([s.reprojection_px for s in sims])
    metrics = {
        "mmd_aligned": aligned.mmd2, "mmd_aligned_ci": list(aligned.ci), "mmd_p_aligned": aligned.p_value,
        "mmd_unaligned": unaligned.mmd2, "mmd_unaligned_ci": list(unaligned.ci), "mmd_p_unaligned": unaligned.p_value,
        "mmd_difference": diff.difference, "mmd_difference_ci": list(diff.ci), "mmd_difference_p": diff.p_value,
        "control_mmd": control.mmd2, "control_mmd_ci": list(control.ci), "control_p": control.p_value,
        "control_p_each_classifier": control_each, "mmd_aligned_each_classifier": list(aligned.each),
        "mmd_unaligned_each_classifier": list(unaligned.each),  # each classifier's own (the intervals hold this)
        "mmd_bandwidth": aligned.bandwidth,
        "reference_reprojection_mean_px": float(reproj.mean()) if len(reproj) else None,
        "reference_reprojection_max_px": float(reproj.max()) if len(reproj) else None,
    }
    if pos_feat is not None:
        pos = mmd_test(ref_feat, pos_feat, scale=(ref_feat, al_feat, pos_feat), **kw)
        pos_diff = paired_mmd_difference(ref_feat, al_feat, pos_feat, **kw)
        metrics.update({"mmd_unaligned_positions": pos.mmd2, "mmd_unaligned_positions_ci": list(pos.ci),
                        "mmd_p_unaligned_positions": pos.p_value, "mmd_difference_positions": pos_diff.difference,
                        "mmd_difference_positions_ci": list(pos_diff.ci),
                        "mmd_difference_positions_p": pos_diff.p_value})
        print(f"verify {name}: positions alone misaligned: MMD² {pos.mmd2:.4f} (p {pos.p_value:.3g}), aligned - "
              f"it {pos_diff.difference:+.4f} (p {pos_diff.p_value:.3g})")
    print(f"verify {name}: MMD² aligned {aligned.mmd2:.4f} (p {aligned.p_value:.3g}), unaligned {unaligned.mmd2:.4f} "
          f"(p {unaligned.p_value:.3g}), difference {diff.difference:+.4f} (p {diff.p_value:.3g}); control "
          f"{control.mmd2:.4f} (p {control.p_value:.3g})")
    return metrics, {"aligned": aligned, "unaligned": unaligned, "control": control}


@flow(name="verify", log_prints=True)
def verify_flow(params: Params) -> dict:
    """The fused-feature check; returns the figures written to reports/verify/details.json."""
    cfg = params.verify
    t0 = time.time()
    with StageTracker(params, "verify") as tracker:
        torch.set_num_threads(params.run.torch_threads)
        ds = configured_reference(params)
        conditions = verified_conditions(ds)
        lidar = reference_lidar_model(params, ds)
        severity, rate_source = severity_of(params)
        hw = tuple(cfg.image_hw)
        tracker.log_params({"verify": cfg.model_dump(mode="json"), "reference.source": params.reference.source,
                            "severity": {"fog_levels": severity.levels.source, "fog_alpha": severity.levels.alpha,
                                         "snow_rate_mm_h": severity.snow_rate_mm_h,
                                         "rain_rate_mm_h": severity.rain_rate_mm_h}})
        show = params.run.show_progress
        levels = ("clear", *dict.fromkeys(conditions.values()))
        # the frames the classifier never trains on: the MMDs compare only these (and simulations of such clear
        # frames), so a feature that remembers its training frames cannot tell them from everything else
        sizes = [len(ds.ids(level)) for level in levels]
        _, held_idx = held_out_split(np.repeat(np.arange(len(levels)), sizes), cfg.held_out_fraction, cfg.seed)
        held = np.zeros(sum(sizes), dtype=bool)
        held[held_idx] = True
        held_of = dict(zip(levels, np.split(held, np.cumsum(sizes)[:-1])))
        step = 2.0 * np.pi / lidar.columns_per_ring
        real = {level: gather([reference_frame_task.submit(ds, i, hw, step if level in PRECIPITATION_LEVELS else None,
                                                           cfg.seed + k) for k, i in enumerate(ds.ids(level))],
                              f"verify: reference {level} frames", show) for level in levels}
        sims: dict[str, list[SimulatedPair]] = {}
        for name in conditions:
            sims[name] = gather([simulated_pair_task.submit(ds, i, CONDITIONS[name], severity, lidar, cfg.exposure_s,
                                                            hw, cfg.seed)
                                 for i, h in zip(ds.ids("clear"), held_of["clear"]) if h],
                                f"verify: clear frames through {name}", show)
        t_sim = time.time()
        inputs = np.concatenate([np.stack([r[0] for r in real[level]]) for level in levels])
        labels = np.concatenate([np.full(len(real[level]), CLASS_OF_LEVEL[level]) for level in levels])
        nan = np.full((3, *hw), np.nan, dtype=np.float32)
        displaced = np.stack([nan if r[3] is None else r[3] for level in levels for r in real[level]])
        trained, rejected = train_fitted_classifiers(
            inputs, labels, CLASSES, cfg.classifiers, seed=cfg.seed, min_train_accuracy=cfg.min_train_accuracy,
            max_rejected=cfg.max_rejected, held_out_fraction=cfg.held_out_fraction, steps=cfg.steps,
            batch_size=cfg.batch_size, lr=cfg.lr, device=cfg.device, correspondence_weight=cfg.correspondence_weight,
            embedding=cfg.embedding, displaced=displaced, held_out=held_idx, progress=show,
            store=params.paths.data / "verify" / "classifiers")
        models = [m for m, _ in trained]
        member_accuracy = [r.accuracy for _, r in trained]
        report = ensemble_report(models, [r for _, r in trained], inputs, labels, device=cfg.device)
        t_train = time.time()
        print(f"verify: {len(models)} weather classifiers, held-out accuracy {report.accuracy:.3f} (each "
              f"{', '.join(f'{a:.3f}' for a in member_accuracy)}) on {len(report.held_out)} frames "
              f"({t_train - t_sim:.0f} s; {int(np.isfinite(displaced).all(axis=(1, 2, 3)).sum())} frames with "
              f"displaced-particle negatives); trainings rejected (seed: training accuracy): "
              f"{', '.join(f'{r.seed}: {r.train_accuracy:.3f}' for r in rejected) or 'none'}")

        def features(x: np.ndarray) -> np.ndarray:
            """(classifiers, n, embedding): every classifier's fused features of the inputs x."""
            return np.stack([fused_features(m, x, device=cfg.device) for m in models])

        extractor = feature_extractor(params.calibrate_fog.inception_path, device=params.calibrate_fog.device)
        per_condition: dict[str, dict] = {}
        histograms: dict[str, dict[str, IntensityHistograms]] = {}
        clear_hist = IntensityHistograms.from_counts(
            np.stack([frame_counts(ds.load_scan(i).points[:, 3], ds.intensity_max) for i in ds.ids("clear")]),
            ds.intensity_max)
        for name, level in conditions.items():
            ref_inputs = np.stack([r[0] for r, h in zip(real[level], held_of[level]) if h])
            ref_feat = features(ref_inputs)
            al_feat = features(np.stack([s.aligned for s in sims[name]]))
            un_feat = features(np.stack([s.unaligned for s in sims[name]]))
            pos_feat = (None if any(s.unaligned_positions is None for s in sims[name])
                        else features(np.stack([s.unaligned_positions for s in sims[name]])))
            control_feat = features(broken_pairs(ref_inputs, seed=cfg.seed))
            metrics, tests = condition_metrics(name, ref_feat, sims[name], al_feat, un_feat, control_feat, params,
                                               pos_feat)
            ref_hist = IntensityHistograms.from_scans((ds.load_scan(i) for i in ds.ids(level)), ds.intensity_max)
            sim_hist = IntensityHistograms.from_counts(np.stack([s.intensity_counts for s in sims[name]]),
                                                       ds.intensity_max)
            ks = bootstrap_ks(sim_hist, ref_hist, num_resamples=cfg.resamples, confidence=cfg.confidence,
                              rng=cfg.seed)
            histograms[name] = {"reference": ref_hist, "simulated (aligned)": sim_hist, "clear": clear_hist}
            ref_images = [r[1] for r in real[level]]
            sim_images = [s.image for s in sims[name]]
            kid = kid_from_features(extractor(sim_images), extractor(ref_images), backbone=extractor.backbone,
                                    rng=cfg.seed)
            visibility = camera_visibility_ratio(sim_images, [s.range_map for s in sims[name]], ref_images,
                                                 [r[2] for r in real[level]])
            sim_report = simulate_reports(params, name)
            per_condition[name] = {
                "reference_split": level, "frames_reference": len(ref_inputs), "frames_simulated": len(sims[name]),
                "ks": ks.statistic, "ks_ci_low": ks.ci_low, "ks_ci_high": ks.ci_high,
                "kid": kid.mean, "kid_std": kid.std, "kid_backbone": kid.backbone,
                **visibility.metrics(),  # the ratio and each set's α̂ and visibility (None: not estimable)
                "reprojection_mean_px": sim_report.get("reprojection_mean_px"),
                "reprojection_max_px": sim_report.get("reprojection_max_px"),
                **metrics}
            _figure(embedding_figure({"reference": ref_feat[0], "aligned": al_feat[0], "unaligned": un_feat[0],
                                      "control": control_feat[0]},
                                     f"{name}: fused features (embedding of classifier 1 of {len(models)})"),
                    tracker.reports / f"embedding_{name}.png", tracker)
            _figure(permutation_figure(tests, f"{name}: MMD² permutation tests against the reference"),
                    tracker.reports / f"permutations_{name}.png", tracker)
        _figure(ecdf_figure(histograms, {n: per_condition[n]["ks"] for n in conditions}),
                tracker.reports / "ecdf.png", tracker)
        _figure(confusion_figure(report), tracker.reports / "confusion.png", tracker)
        atomic.write_json(tracker.reports / "confusion.json", confusion_rows(report), indent=1)
        control_p = max(m["control_p"] for m in per_condition.values())
        metrics = {
            "reference_root": str(ds.root), "reference_source": params.reference.source,
            "severity": {"fog_levels": severity.levels.source, "snow_rate_mm_h": severity.snow_rate_mm_h,
                         "rain_rate_mm_h": severity.rain_rate_mm_h, "rates": rate_source,
                         "ground_depth_m": dict(severity.ground_depth_m), "overcast": dict(severity.overcast)},
            "classifier_accuracy": report.accuracy, "classifier_held_out": int(len(report.held_out)),
            "classifiers": len(models), "classifier_accuracy_each": member_accuracy,
            "classifier_seeds": [s for s in range(cfg.seed, cfg.seed + len(models) + len(rejected))
                                 if s not in {r.seed for r in rejected}],
            "classifier_train_accuracy_each": [r.train_accuracy for _, r in trained],
            "classifiers_rejected": [{"seed": r.seed, "train_accuracy": r.train_accuracy} for r in rejected],
            "classifier_confusion": report.confusion.tolist(), "classes": list(CLASSES),
            "control_mmd": min(m["control_mmd"] for m in per_condition.values()),
            "control_p": control_p, "control_detected": bool(control_p < 0.01),
            "conditions": per_condition,
            "seconds": {"simulate": round(t_sim - t0, 2), "train": round(t_train - t_sim, 2),
                        "total": round(time.time() - t0, 2)},
        }
        (tracker.reports / "table.md").write_text(table_markdown(metrics))
        tracker.log_artifact(tracker.reports / "table.md")
        logged = {"classifier_accuracy": report.accuracy, "control_p": control_p,
                  "seconds": metrics["seconds"]["total"]}
        tracker.finish(metrics, headline(metrics), logged=logged, children={
            name: ({"weather": name, "reference_split": level},
                   {k: v for k, v in per_condition[name].items() if isinstance(v, (int, float))})
            for name, level in conditions.items()})
    return metrics


HEADLINE = ("mmd_difference", "mmd_difference_p")
"""Per verified condition, the figures of reports/verify/metrics.json: whether the aligned simulation is closer to
the real weather than the unaligned one (the rest, each MMD, KS, KID and the intervals, in details.json and the
MLflow child run of each condition)."""


def headline(details: dict) -> dict:
    """The classifier's accuracy, whether the control detected a difference, per condition its `HEADLINE`
    figures."""
    return {**{k: details[k] for k in ("classifier_accuracy", "control_detected")},
            **{name: {k: c.get(k) for k in HEADLINE} for name, c in details["conditions"].items()}}


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("verify", argv)
    return run_stage(verify_flow, params)


if __name__ == "__main__":
    main()
