"""Training the weather classifier on fused inputs (weatheralign.verify.classifier): held-out accuracy and confusion
matrix on separable toy weather, seeded determinism, the fused features, and the control's broken pairs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from weatheralign.verify.classifier import (
    broken_pairs,
    ensemble_report,
    fused_features,
    held_out_split,
    mismatched_pairs,
    predict_classes,
    train_fitted_classifiers,
    train_weather_classifier,
)
from weatheralign.verify.features import FUSED_CHANNELS
from weatheralign.verify.mmd import mmd_test


def toy_weather(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Clear: a textured scene seen by both sensors; fog: its image washed towards grey and the far LiDAR returns gone;
    snow: bright flakes in the image with LiDAR echoes on the same cells."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, FUSED_CHANNELS, 16, 16), np.float32)
    labels = np.arange(n) % 3
    for i in range(n):
        scene = rng.uniform(0.1, 0.6, (3, 16, 16))
        depth = rng.uniform(0.02, 0.5, (16, 16))
        x[i, :3], x[i, 3], x[i, 5] = scene, depth, 1.0
        if labels[i] == 1:
            x[i, :3] = 0.3 * scene + 0.7 * 0.8
            x[i, 3] = np.where(depth < 0.1, 0.0, depth)
        elif labels[i] == 2:
            for _ in range(6):
                r, c = rng.integers(0, 16, 2)
                x[i, :3, r, c], x[i, 3, r, c], x[i, 4, r, c] = 1.0, 0.8, 0.9
    return x, labels


def test_classifier_learns_toy_weather_and_reports_held_out_frames() -> None:
    torch.set_num_threads(1)
    x, y = toy_weather(240)
    model, report = train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=150, width=8, embedding=16)
    assert report.accuracy > 0.9, report
    assert report.confusion.shape == (3, 3) and report.confusion.sum() == len(report.held_out) == 60
    assert (report.confusion.sum(axis=1) == 20).all()  # stratified: a quarter of every class held out
    assert fused_features(model, x[:5]).shape == (5, 16)
    _, again = train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=150, width=8, embedding=16)
    assert again.accuracy == report.accuracy and (again.confusion == report.confusion).all()
    with pytest.raises(ValueError, match="labels"):
        train_weather_classifier(x, y + 5, ("clear", "fog", "snow"), steps=1)


def test_the_training_accuracy_is_measured_on_the_training_frames_alone() -> None:
    torch.set_num_threads(1)
    x, y = toy_weather(60, seed=1)
    held = held_out_split(y, 0.25, seed=0)[1]
    model, report = train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=5, width=8, embedding=8,
                                             held_out=held)
    train = np.setdiff1d(np.arange(len(y)), held)
    assert report.train_accuracy == pytest.approx(float(np.mean(predict_classes(model, x[train]) == y[train])))


def test_trainings_that_do_not_fit_their_training_frames_are_replaced_by_the_next_seeds() -> None:
    torch.set_num_threads(1)
    x, y = toy_weather(90, seed=2)
    held = held_out_split(y, 0.25, seed=0)[1]
    kw = dict(steps=40, width=8, embedding=8, held_out=held)  # short: some starts fit the toy weather, some do not
    accuracy = {seed: train_weather_classifier(x, y, ("clear", "fog", "snow"), seed=seed, **kw)[1].train_accuracy
                for seed in range(3, 9)}
    bar = sorted(accuracy.values())[3]  # three of the six trainings reach it (ties aside)
    expected_kept = [s for s in range(3, 9) if accuracy[s] >= bar][:2]
    expected_rejected = [s for s in range(3, expected_kept[-1]) if accuracy[s] < bar]
    assert expected_rejected, "the toy trainings must include poor fits for this test to test anything"
    kept, rejected = train_fitted_classifiers(x, y, ("clear", "fog", "snow"), 2, seed=3, min_train_accuracy=bar,
                                              max_rejected=len(expected_rejected), **kw)
    assert [r.train_accuracy for _, r in kept] == [accuracy[s] for s in expected_kept]
    assert [(r.seed, r.train_accuracy) for r in rejected] == [(s, accuracy[s]) for s in expected_rejected]
    with pytest.raises(ValueError, match=f"{len(expected_rejected)} classifier trainings"):  # one rejection too many
        train_fitted_classifiers(x, y, ("clear", "fog", "snow"), 2, seed=3, min_train_accuracy=bar,
                                 max_rejected=len(expected_rejected) - 1, **kw)



def test_a_stored_training_is_loaded_instead_of_trained_again(tmp_path, monkeypatch) -> None:
    """With a store, a rerun loads every finished training (kept and rejected) with the same weights and report; a
    change of the inputs or of a setting trains again; an unreadable file is trained again, not trusted."""
    import weatheralign.verify.classifier as classifier

    torch.set_num_threads(1)
    x, y = toy_weather(90, seed=2)
    classes = ("clear", "fog", "snow")
    kw = dict(steps=40, width=8, embedding=8, held_out=held_out_split(y, 0.25, seed=0)[1])
    first, _ = train_fitted_classifiers(x, y, classes, 4, seed=0, min_train_accuracy=0.0, max_rejected=0,
                                        store=tmp_path, **kw)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"seed{s}.pt" for s in range(4)]
    accuracy = [r.train_accuracy for _, r in first]
    bar = sorted(accuracy)[2]  # two of the four reach it (ties aside): the others are rejected on the rerun
    trained: list[int] = []
    original = classifier.train_weather_classifier

    def counting(*args, **kwargs):
        trained.append(kwargs["seed"])
        return original(*args, **kwargs)

    monkeypatch.setattr(classifier, "train_weather_classifier", counting)
    again, rejected = train_fitted_classifiers(x, y, classes, 2, seed=0, min_train_accuracy=bar, max_rejected=2,
                                               store=tmp_path, **kw)
    assert trained == []
    kept = [s for s in range(4) if accuracy[s] >= bar][:2]
    assert [(r.seed, r.train_accuracy) for r in rejected] == [(s, accuracy[s]) for s in range(kept[-1])
                                                               if accuracy[s] < bar]
    for s, (model, report) in zip(kept, again, strict=True):
        np.testing.assert_array_equal(fused_features(first[s][0], x), fused_features(model, x))
        r1 = first[s][1]
        assert (r1.classes, r1.accuracy, r1.final_loss, r1.train_accuracy) == (
            report.classes, report.accuracy, report.final_loss, report.train_accuracy)
        np.testing.assert_array_equal(r1.confusion, report.confusion)
        np.testing.assert_array_equal(r1.held_out, report.held_out)
    changed = x.copy()
    changed[0, 0, 0, 0] += 0.5
    once = dict(min_train_accuracy=0.0, max_rejected=0, store=tmp_path)
    train_fitted_classifiers(changed, y, classes, 1, seed=0, **once, **kw)
    train_fitted_classifiers(x, y, classes, 1, seed=0, **once, **{**kw, "steps": 41})
    (tmp_path / "seed0.pt").write_bytes(b"not a checkpoint")
    train_fitted_classifiers(x, y, classes, 1, seed=0, **once, **kw)
    assert trained == [0, 0, 0]

def test_an_ensemble_report_averages_class_probabilities_on_the_shared_held_out_frames() -> None:
    torch.set_num_threads(1)
    x, y = toy_weather(120, seed=3)
    held = held_out_split(y, 0.25, seed=0)[1]
    trained = [train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=40, width=8, embedding=8, seed=k,
                                        held_out=held) for k in range(2)]
    models, reports = [m for m, _ in trained], [r for _, r in trained]
    report = ensemble_report(models, reports, x, y)
    probs = np.mean([torch.softmax(m.eval()(torch.from_numpy(x[held])), dim=1).detach().numpy() for m in models],
                    axis=0)
    assert (report.held_out == held).all() and report.confusion.sum() == len(held)
    assert report.accuracy == pytest.approx(float(np.mean(probs.argmax(axis=1) == y[held])))
    assert report.final_loss == pytest.approx(np.mean([r.final_loss for r in reports]))
    assert report.train_accuracy == pytest.approx(np.mean([r.train_accuracy for r in reports]))
    other = train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=2, width=8, embedding=8, seed=5)
    with pytest.raises(ValueError, match="same held-out"):
        ensemble_report([*models, other[0]], [*reports, other[1]], x, y)


def test_held_out_split_holds_out_a_share_of_every_stratum_and_the_classifier_never_trains_on_it() -> None:
    strata = np.repeat([0, 1, 2, 3], [40, 3, 10, 7])
    train, held = held_out_split(strata, 0.5, seed=3)
    assert np.array_equal(np.sort(np.concatenate([train, held])), np.arange(len(strata)))
    assert [int(np.sum(strata[held] == s)) for s in range(4)] == [20, 2, 5, 4]  # round(n/2), at least 2, at most n-1
    assert np.array_equal(held_out_split(strata, 0.5, seed=3)[1], held)  # seeded
    assert not np.array_equal(held_out_split(strata, 0.5, seed=4)[1], held)
    with pytest.raises(ValueError, match="stratum 1 has 2 frames"):
        held_out_split(np.repeat([0, 1], [5, 2]), 0.5)

    torch.set_num_threads(1)
    x, y = toy_weather(60)
    _, report = train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=5, width=4, embedding=4,
                                         held_out=np.array([7, 3, 3, 50]))
    assert report.held_out.tolist() == [3, 7, 50] and report.confusion.sum() == 3
    for bad in (np.array([60]), np.arange(60), np.array([], dtype=np.int64)):
        with pytest.raises(ValueError, match="held_out must name some but not all"):
            train_weather_classifier(x, y, ("clear", "fog", "snow"), steps=1, held_out=bad)


def test_broken_pairs_keep_both_marginals_and_move_every_lidar() -> None:
    x, _ = toy_weather(30, seed=1)
    broken = broken_pairs(x, seed=3)
    assert np.array_equal(broken[:, :3], x[:, :3])
    lidar_rows = {x[i, 3:].tobytes(): i for i in range(len(x))}
    partners = [lidar_rows[broken[i, 3:].tobytes()] for i in range(len(x))]
    assert sorted(partners) == list(range(len(x))) and all(p != i for i, p in enumerate(partners))
    assert np.array_equal(broken_pairs(x, seed=3), broken)
    two = broken_pairs(x[:2])
    assert np.array_equal(two[0, 3:], x[1, 3:]) and np.array_equal(two[1, 3:], x[0, 3:])


def registered_scenes(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two weather classes (image brightness) over random blob scenes whose LiDAR depth marks the image's blobs:
    the weather label needs only the image; the LiDAR-camera registration is there to be learnt or ignored."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, FUSED_CHANNELS, 16, 24), np.float32)
    labels = np.arange(n) % 2
    for i in range(n):
        for _ in range(3):
            r, c = rng.integers(1, 15), rng.integers(1, 23)
            x[i, :3, r - 1:r + 2, c - 1:c + 2] = 0.8
            x[i, 3, r - 1:r + 2, c - 1:c + 2], x[i, 5, r - 1:r + 2, c - 1:c + 2] = 0.5, 1.0
        x[i, :3] += 0.1 + 0.1 * labels[i]
    return x, labels


def test_mismatched_pairs_keep_the_camera_and_move_every_lidar() -> None:
    x, _ = registered_scenes(8)
    out = mismatched_pairs(torch.from_numpy(x), np.random.default_rng(0)).numpy()
    assert np.array_equal(out[:, :3], x[:, :3])
    assert np.array_equal(out[:4, 3:], x[[7, 0, 1, 2], 3:])  # the first half: the previous frame's LiDAR
    for i in range(4, 8):  # the rest: their own LiDAR shifted sideways
        assert not np.array_equal(out[i, 3:], x[i, 3:])
        assert any(np.array_equal(out[i, 3:], np.roll(x[i, 3:], s, axis=-1)) for s in range(-6, 7) if abs(s) >= 3)


def test_the_correspondence_objective_makes_the_fused_feature_see_broken_pairs() -> None:
    torch.set_num_threads(1)
    x, y = registered_scenes(160)
    control = broken_pairs(x, seed=1)
    p_values = {}
    for weight in (0.0, 1.0):
        model, report = train_weather_classifier(x, y, ("dim", "bright"), steps=200, width=8, embedding=16,
                                                 correspondence_weight=weight)
        assert report.accuracy > 0.9, (weight, report)
        p_values[weight] = mmd_test(fused_features(model, x[:60]), fused_features(model, control[:60]),
                                    permutations=200, resamples=10).p_value
        if weight > 0:
            with torch.no_grad():
                true = model.correspondence(torch.from_numpy(x[:60]))
                broken = model.correspondence(torch.from_numpy(control[:60]))
            assert (true > 0).float().mean() > 0.9 and (broken < 0).float().mean() > 0.9
    assert p_values[0.0] > 0.05 and p_values[1.0] < 0.01, p_values  # weather labels alone: blind to the pairing
