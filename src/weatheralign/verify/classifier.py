"""Training the auxiliary weather classifier on fused inputs, its held-out accuracy and confusion matrix, the fused
features it gives, and the sensitivity control's broken pairs (`verify`).

Inputs are (N, 6, h, w) float32 stacks of `weatheralign.verify.features.fused_input`, one per frame and camera,
labelled with class indices. The held-out frames are drawn per stratum (`held_out_split`: the reference level in
`verify`, whose MMDs compare only them) and never trained on; horizontal flips (all six channels together, so that the
sensors stay registered) are the only augmentation. Deterministic for a seed on the CPU. `train_fitted_classifiers`
keeps each finished training in a folder when given one (`stored_training`), so that a rerun or an interrupted
verify loads it instead of training it again.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from sklearn.metrics import confusion_matrix
from tqdm import tqdm

from weatheralign import atomic
from weatheralign.code_closure import closure_digest
from weatheralign.verify.features import FUSED_CHANNELS, LIDAR_CHANNELS, WeatherClassifier


@dataclass(frozen=True)
class ClassifierReport:
    """Held-out ``accuracy``, ``confusion`` (C, C) counts (rows: true class, columns: predicted, in ``classes``
    order), the held-out frame indices, the last training loss, and the accuracy on the frames it trained on
    (``train_accuracy``: how well the optimisation fit them)."""

    classes: tuple[str, ...]
    accuracy: float
    confusion: NDArray[np.int64]
    held_out: NDArray[np.int64]
    final_loss: float
    train_accuracy: float


@dataclass(frozen=True)
class RejectedTraining:
    """A classifier training that did not fit its own training frames: its ``seed`` and ``train_accuracy``."""

    seed: int
    train_accuracy: float


def _check(inputs: NDArray, labels: NDArray, classes: Sequence[str]) -> None:
    if inputs.ndim != 4 or inputs.shape[1] != FUSED_CHANNELS:
        raise ValueError(f"inputs must be (N, {FUSED_CHANNELS}, h, w) fused stacks, got {inputs.shape}")
    if len(labels) != len(inputs) or labels.min(initial=0) < 0 or labels.max(initial=0) >= len(classes):
        raise ValueError(f"labels must be {len(inputs)} class indices in 0..{len(classes) - 1}")


def held_out_split(strata: NDArray, fraction: float, seed: int = 0) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(train, held-out) indices (sorted) of ``len(strata)`` frames: of each stratum, ``round(fraction n)`` frames
    drawn at random (seeded), but at least two (an unbiased MMD needs two per set) and at most ``n - 1`` (the
    classifier must see every stratum); so each stratum needs three frames or more."""
    strata = np.asarray(strata)
    rng = np.random.default_rng(seed)
    held = []
    for value in np.unique(strata):
        members = np.flatnonzero(strata == value)
        if len(members) < 3:
            raise ValueError(f"stratum {value!r} has {len(members)} frames: holding two out for the MMD and training "
                             f"on the rest needs three or more")
        count = min(max(2, int(round(fraction * len(members)))), len(members) - 1)
        held.append(rng.choice(members, size=count, replace=False))
    held_idx = np.sort(np.concatenate(held)).astype(np.int64)
    return np.setdiff1d(np.arange(len(strata)), held_idx).astype(np.int64), held_idx


def train_weather_classifier(inputs: NDArray, labels: NDArray, classes: Sequence[str], *,
                             held_out_fraction: float = 0.25, steps: int = 300, batch_size: int = 32,
                             lr: float = 3e-3, seed: int = 0, device: str = "cpu", width: int = 16, embedding: int = 64,
                             correspondence_weight: float = 1.0, displaced: NDArray | None = None,
                             held_out: NDArray | None = None,
                             progress: bool = False) -> tuple[WeatherClassifier, ClassifierReport]:
    """Train a `WeatherClassifier` on all frames but a held-out share, report on the held-out ones: the indices
    ``held_out`` when given, else a ``held_out_fraction`` of each class (`held_out_split`).

    Loss per step: cross-entropy of the weather classes on the batch's true pairs, plus ``correspondence_weight`` x
    the binary cross-entropy of the correspondence logit on the true pairs (label 1) and as many mismatched ones
    (label 0, `mismatched_pairs`): the weather label alone never needs the LiDAR and the camera to agree, so without
    this term the fused feature is blind to their alignment (measured: the sensitivity control was not detected).
    ``displaced``: optional (N, 3, h, w) LiDAR channels of each frame with its particle echoes moved elsewhere
    (`weatheralign.verify.frames.displaced_particle_channels`; NaN for a frame without particles): the hardest
    mismatch, the right scene with the wrong particles, which half the negatives of such a frame become.
    ``progress``: a progress bar over the steps with the running loss."""
    inputs, labels = np.asarray(inputs, dtype=np.float32), np.asarray(labels, dtype=np.int64)
    _check(inputs, labels, classes)
    if held_out is None:
        train_idx, test_idx = held_out_split(labels, held_out_fraction, seed)
    else:
        test_idx = np.unique(np.asarray(held_out, dtype=np.int64))
        if len(test_idx) == 0 or test_idx[0] < 0 or test_idx[-1] >= len(inputs) or len(test_idx) == len(inputs):
            raise ValueError(f"held_out must name some but not all of the {len(inputs)} frames")
        train_idx = np.setdiff1d(np.arange(len(inputs)), test_idx)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = WeatherClassifier(len(classes), width, embedding).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    x = torch.from_numpy(inputs)
    y = torch.from_numpy(labels)
    hard = None if displaced is None else torch.from_numpy(np.asarray(displaced, dtype=np.float32))
    if hard is not None and hard.shape != (len(x), LIDAR_CHANNELS, *x.shape[2:]):
        raise ValueError(f"displaced must be (N, {LIDAR_CHANNELS}, h, w) like the inputs' LiDAR, "
                         f"got {tuple(hard.shape)}")
    loss = torch.zeros(())
    model.train()
    bar = tqdm(range(steps), desc="verify: weather classifier", unit="step", disable=not progress)
    for step in bar:
        pick = torch.from_numpy(rng.choice(train_idx, size=min(batch_size, len(train_idx)), replace=False))
        xb = x[pick]
        flip = torch.from_numpy(rng.random(len(pick)) < 0.5)
        xb = torch.where(flip[:, None, None, None], xb.flip(-1), xb)
        hb = None if hard is None else torch.where(flip[:, None, None, None], hard[pick].flip(-1), hard[pick])
        xb = xb.to(device)
        if correspondence_weight > 0.0 and len(pick) >= 2:  # one pass over true and mismatched pairs (one BN batch)
            negatives = mismatched_pairs(xb, rng, None if hb is None else hb.to(device))
            embedded = model.embed(torch.cat([xb, negatives]))
            target = torch.cat([torch.ones(len(xb)), torch.zeros(len(xb))]).to(device)
            loss = F.cross_entropy(model.logits(embedded[:len(xb)]), y[pick].to(device)) + correspondence_weight * \
                F.binary_cross_entropy_with_logits(model.pair(embedded)[:, 0], target)
        else:
            loss = F.cross_entropy(model(xb), y[pick].to(device))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if progress and step % 20 == 0:
            bar.set_postfix(loss=f"{float(loss.detach()):.3f}")
    predicted = predict_classes(model, inputs[test_idx], device=device)
    confusion = confusion_matrix(labels[test_idx], predicted, labels=np.arange(len(classes))).astype(np.int64)
    accuracy = float(np.trace(confusion) / max(confusion.sum(), 1))
    train_accuracy = float(np.mean(predict_classes(model, inputs[train_idx], device=device) == labels[train_idx]))
    return model, ClassifierReport(tuple(classes), accuracy, confusion, np.sort(test_idx).astype(np.int64),
                                   float(loss.detach()), train_accuracy)


def training_key(inputs: NDArray, labels: NDArray, classes: Sequence[str], training: dict[str, object]) -> str:
    """16 hex digits over everything a training's result follows but its seed: this module's code and what it
    imports, the ``inputs`` and ``labels`` (values, shapes, dtypes), the ``classes``, every argument of ``training``
    (`train_weather_classifier`'s; arrays by their values; ``progress`` aside) and torch's CPU threads."""
    h = hashlib.sha256(closure_digest(__name__).encode())
    settings: dict[str, object] = {"classes": list(classes), "threads": torch.get_num_threads()}
    for name, value in sorted({"inputs": inputs, "labels": labels, **training}.items()):
        if name == "progress":
            continue
        if isinstance(value, np.ndarray | list | tuple) or value is None:
            array = np.ascontiguousarray(np.asarray(value)) if value is not None else None
            settings[name] = None if array is None else [array.shape, str(array.dtype)]
            h.update(b"" if array is None else array.tobytes())
        else:
            settings[name] = value
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def stored_training(folder: Path, key: str, seed: int, device: str = "cpu"
                    ) -> tuple[WeatherClassifier, ClassifierReport] | None:
    """The training of ``seed`` kept in ``folder`` (``seed<k>.pt``) when it was made with ``key`` (`training_key`),
    else None (also for a file this module did not write). Read as tensors and plain data only: a received file
    cannot run code."""
    path = Path(folder) / f"seed{seed}.pt"
    if not path.is_file():
        return None
    try:
        stored = torch.load(path, map_location=device, weights_only=True)
        meta = stored["meta"]
    except Exception:  # noqa: BLE001 - not a training this module wrote (unreadable, foreign): train it again
        return None
    if not isinstance(meta, dict) or meta.get("key") != key:
        return None
    model = WeatherClassifier(len(meta["classes"]), meta["width"], meta["embedding"]).to(device)
    model.load_state_dict(stored["state"])
    model.eval()
    return model, ClassifierReport(tuple(meta["classes"]), meta["accuracy"], np.asarray(meta["confusion"], np.int64),
                                   np.asarray(meta["held_out"], np.int64), meta["final_loss"], meta["train_accuracy"])


def store_training(folder: Path, key: str, seed: int, model: WeatherClassifier, report: ClassifierReport) -> None:
    """Keep a finished training in ``folder`` (``seed<k>.pt``: weights and its report), written atomically."""
    meta = {"key": key, "classes": list(report.classes), "accuracy": report.accuracy,
            "confusion": report.confusion.tolist(), "held_out": report.held_out.tolist(),
            "final_loss": report.final_loss, "train_accuracy": report.train_accuracy,
            "width": model.features[0][0].out_channels, "embedding": model.logits.in_features}
    buf = io.BytesIO()
    torch.save({"state": {k: v.cpu() for k, v in model.state_dict().items()}, "meta": meta}, buf)
    Path(folder).mkdir(parents=True, exist_ok=True)
    atomic.write_bytes(Path(folder) / f"seed{seed}.pt", buf.getvalue())


def train_fitted_classifiers(inputs: NDArray, labels: NDArray, classes: Sequence[str], count: int, *, seed: int,
                             min_train_accuracy: float, max_rejected: int, store: Path | None = None,
                             **training: object
                             ) -> tuple[list[tuple[WeatherClassifier, ClassifierReport]], list[RejectedTraining]]:
    """``count`` classifiers (`train_weather_classifier` with ``training``) from seeds ``seed``, ``seed + 1``, ...,
    and the trainings rejected on the way: a training whose accuracy on its own training frames stays under
    ``min_train_accuracy`` did not optimise (a start that stalls on a few classes while others from the same data fit
    them), so its features are noise, not a view of the data; the next unused seed replaces it. The test uses only the
    training frames, never the held-out ones the MMDs compare. More than ``max_rejected`` rejections raise ValueError
    (the setup, not the start, is then at fault). ``store``: a folder where every training, rejected ones too, is
    kept and from which one made from the same code, inputs and settings (`training_key`) is loaded instead."""
    kept: list[tuple[WeatherClassifier, ClassifierReport]] = []
    rejected: list[RejectedTraining] = []
    key = training_key(inputs, labels, classes, training) if store is not None else ""
    device = str(training.get("device", "cpu"))
    next_seed = seed
    while len(kept) < count:
        finished = stored_training(store, key, next_seed, device) if store is not None else None
        if finished is None:
            finished = train_weather_classifier(inputs, labels, classes, seed=next_seed, **training)
            if store is not None:
                store_training(store, key, next_seed, *finished)
        model, report = finished
        if report.train_accuracy >= min_train_accuracy:
            kept.append((model, report))
        else:
            rejected.append(RejectedTraining(next_seed, report.train_accuracy))
            if len(rejected) > max_rejected:
                raise ValueError(f"{len(rejected)} classifier trainings stayed under the training accuracy "
                                 f"{min_train_accuracy} (seed: accuracy "
                                 f"{', '.join(f'{r.seed}: {r.train_accuracy:.3f}' for r in rejected)}); more steps "
                                 f"or another lr in configs/verify.yaml")
        next_seed += 1
    return kept, rejected


def ensemble_report(models: Sequence[WeatherClassifier], reports: Sequence[ClassifierReport], inputs: NDArray,
                    labels: NDArray, device: str = "cpu") -> ClassifierReport:
    """The held-out report of classifiers trained on one split (their ``reports`` share the held-out frames): class
    probabilities averaged over ``models``; the final loss and the training accuracy are their means."""
    held = reports[0].held_out
    if any(not np.array_equal(r.held_out, held) for r in reports) or len(models) != len(reports) or not models:
        raise ValueError("an ensemble report needs one report per model, all on the same held-out frames")
    x = np.asarray(inputs, dtype=np.float32)[held]
    probs = np.mean([torch.softmax(torch.from_numpy(_batches(m, x, "forward", 64, device)), dim=1).numpy()
                     for m in models], axis=0)
    classes = reports[0].classes
    confusion = confusion_matrix(np.asarray(labels)[held], probs.argmax(axis=1),
                                 labels=np.arange(len(classes))).astype(np.int64)
    return ClassifierReport(classes, float(np.trace(confusion) / max(confusion.sum(), 1)), confusion, held,
                            float(np.mean([r.final_loss for r in reports])),
                            float(np.mean([r.train_accuracy for r in reports])))


def mismatched_pairs(x: torch.Tensor, rng: np.random.Generator, displaced: torch.Tensor | None = None
                     ) -> torch.Tensor:
    """(B, 6, h, w) fused inputs (B >= 2) with their LiDAR channels mismatched: the first half take the LiDAR of the
    next frame in the batch (another scene), the rest their own LiDAR shifted sideways by 3..w/4 cells (the right
    scene, misregistered). ``displaced`` (B, 3, h, w), optional: each frame's LiDAR with its particle echoes moved
    (NaN: a frame without particles); a frame that has one takes it instead with probability 1/2 (the right scene,
    the wrong particles). Camera channels unchanged."""
    lidar = FUSED_CHANNELS - LIDAR_CHANNELS
    out = x.clone()
    half = len(x) // 2
    out[:half, lidar:] = torch.roll(x[:, lidar:], shifts=1, dims=0)[:half]
    width = x.shape[-1]
    for i in range(half, len(x)):
        shift = int(rng.integers(3, max(4, width // 4 + 1))) * (1 if rng.random() < 0.5 else -1)
        out[i, lidar:] = torch.roll(x[i, lidar:], shifts=shift, dims=-1)
    if displaced is not None:
        use = torch.from_numpy(rng.random(len(x)) < 0.5).to(x.device) & ~torch.isnan(displaced).any(dim=(1, 2, 3))
        out[use, lidar:] = displaced[use]
    return out


@torch.no_grad()
def _batches(model: WeatherClassifier, inputs: NDArray, fn: str, batch_size: int, device: str) -> NDArray:
    model.eval()
    out = [getattr(model, fn)(torch.from_numpy(np.asarray(inputs[i:i + batch_size], dtype=np.float32)).to(device))
           for i in range(0, len(inputs), batch_size)]
    return torch.cat(out).cpu().numpy()


def predict_classes(model: WeatherClassifier, inputs: NDArray, batch_size: int = 64, device: str = "cpu"
                    ) -> NDArray[np.int64]:
    """(N,) predicted class indices of (N, 6, h, w) fused inputs."""
    return _batches(model, inputs, "forward", batch_size, device).argmax(axis=1).astype(np.int64)


def fused_features(model: WeatherClassifier, inputs: NDArray, batch_size: int = 64, device: str = "cpu"
                   ) -> NDArray[np.float64]:
    """(N, embedding) fused features (the classifier's penultimate layer) of (N, 6, h, w) fused inputs."""
    return _batches(model, inputs, "embed", batch_size, device).astype(np.float64)


def broken_pairs(inputs: NDArray, seed: int = 0) -> NDArray[np.float32]:
    """The sensitivity control: every frame's camera channels with the LiDAR channels of another frame (a random
    derangement), so each sensor's marginal is unchanged and only their alignment is broken. (N >= 2.)"""
    n = len(inputs)
    if n < 2:
        raise ValueError("broken pairs need two frames or more")
    order = np.random.default_rng(seed).permutation(n)
    partner = np.empty(n, dtype=np.int64)
    partner[order] = np.roll(order, -1)  # one random cycle through all frames: nobody keeps its own LiDAR
    out = np.array(inputs, dtype=np.float32, copy=True)
    out[:, FUSED_CHANNELS - LIDAR_CHANNELS:] = np.asarray(inputs)[partner, FUSED_CHANNELS - LIDAR_CHANNELS:]
    return out


__all__ = ["ClassifierReport", "RejectedTraining", "broken_pairs", "ensemble_report", "fused_features",
           "held_out_split", "mismatched_pairs", "predict_classes", "store_training", "stored_training",
           "train_fitted_classifiers", "train_weather_classifier", "training_key"]
