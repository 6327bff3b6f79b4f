"""The paper's metrics against independent computations (numpy loops, scipy) on random data."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from pairedgta.metrics import (
    ConfusionMatrix,
    ReferenceConsistency,
    pixel_agreement,
    prediction_mass,
    prediction_mass_from_labels,
    ratio_ci,
    rho_valid,
    select_frames,
    spearman_ci,
)

C = 19


def xi_loop(refs, preds, num_classes=C, ignore=255):
    num = np.zeros(num_classes)
    den = np.zeros(num_classes)
    for ref, pred in zip(refs, preds):
        for r, p in zip(ref.ravel(), pred.ravel()):
            if r == ignore:
                continue
            den[r] += 1
            num[r] += p == r
    return np.array([num[c] / den[c] if den[c] else math.nan for c in range(num_classes)]), num, den


def random_maps(rng, n, shape=(6, 7), classes=(0, 2, 5, 11, 13), void=0.3):
    refs, preds = [], []
    for _ in range(n):
        ref = rng.choice(classes, size=shape)
        ref[rng.random(shape) < void] = 255
        pred = np.where(rng.random(shape) < 0.6, ref, rng.integers(0, C, size=shape))
        pred[pred == 255] = 0
        refs.append(ref)
        preds.append(pred)
    return refs, preds


def test_xi_matches_loop_with_absent_classes_and_void():
    rng = np.random.default_rng(0)
    refs, preds = random_maps(rng, 5)
    refs.append(np.full((6, 7), 255))  # an all-void image contributes nothing
    preds.append(rng.integers(0, C, size=(6, 7)))
    metric = ReferenceConsistency(num_classes=C, ignore_index=255)
    for r, p in zip(refs, preds):
        metric.update(torch.from_numpy(r), torch.from_numpy(p))
    got = metric.compute().numpy()
    want, num, den = xi_loop(refs, preds)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)])
    assert np.isnan(got[1]) and np.isnan(got[18])  # never in the reference -> undefined, not 0
    assert metric.mean() == pytest.approx(np.nanmean(want))
    # pooled over images, not a mean of per-image ratios
    assert metric.reference.sum().item() == den.sum()


def test_xi_is_one_for_identical_and_zero_for_disjoint():
    ref = torch.tensor([[0, 1], [2, 255]])
    m = ReferenceConsistency(C, 255)
    m.update(ref, torch.tensor([[0, 1], [2, 7]]))
    assert m.compute()[[0, 1, 2]].tolist() == [1.0, 1.0, 1.0]
    m2 = ReferenceConsistency(C, 255)
    m2.update(ref, torch.tensor([[3, 3], [3, 3]]))
    assert m2.compute()[[0, 1, 2]].tolist() == [0.0, 0.0, 0.0]


def test_prediction_mass_matches_loop():
    rng = np.random.default_rng(1)
    logits = torch.from_numpy(rng.normal(size=(3, C, 9, 8)) * 3).float()
    probs = logits.softmax(1)
    for tau in (0.3, 0.6, 0.9):
        for c in (0, 5, 13):
            want = [
                sum(1 for y in range(9) for x in range(8)
                    if int(probs[b, :, y, x].argmax()) == c and float(probs[b, c, y, x]) >= tau)
                for b in range(3)
            ]
            assert prediction_mass(probs, c, tau).tolist() == want
        allc = prediction_mass(probs, None, tau)
        assert allc.shape == (3, C)
        assert allc[:, 13].tolist() == prediction_mass(probs, 13, tau).tolist()
        conf, labels = probs.max(1)
        assert torch.equal(prediction_mass_from_labels(labels, conf, C, tau), allc)
    assert int(prediction_mass(probs[0], 0, 0.5)) == int(prediction_mass(probs, 0, 0.5)[0])


def test_rho_valid_top_m_matches_scipy_on_the_top_frames():
    rng = np.random.default_rng(2)
    clean = rng.integers(0, 1000, size=60)
    adverse = clean + rng.integers(-300, 300, size=60)
    top = np.argsort(-clean, kind="stable")[:25]
    want = spearmanr(clean[top], adverse[top]).statistic
    assert rho_valid(clean, adverse, m=25, selection="top_m") == pytest.approx(want)


def test_rho_valid_ties_nonzero_and_fewer_frames_than_m():
    clean = np.array([0, 0, 5, 5, 9, 3, 0, 7])
    adverse = np.array([1, 0, 4, 6, 9, 3, 2, 2])
    nz = clean > 0
    assert rho_valid(clean, adverse, selection="nonzero") == pytest.approx(spearmanr(clean[nz], adverse[nz]).statistic)
    # fewer frames than M: all frames are used
    assert rho_valid(clean, adverse, m=25) == pytest.approx(spearmanr(clean, adverse).statistic)
    # the top-M boundary tie breaks by frame order, deterministically
    assert select_frames(np.array([5, 3, 5, 5]), m=2).tolist() == [0, 2]
    # undefined cases are NaN, never a number
    assert math.isnan(rho_valid([0, 0, 0], [1, 2, 3], selection="nonzero"))
    assert math.isnan(rho_valid([4, 4, 4], [1, 2, 3]))
    with pytest.raises(ValueError):
        rho_valid([1, 2], [1, 2], selection="best")


def test_pixel_agreement_masks_void():
    ref = torch.tensor([[0, 255], [1, 1]])
    agree, valid = pixel_agreement(torch.tensor([[0, 3], [1, 2]]), torch.tensor([[0, 9], [1, 1]]), ref)
    assert (agree, valid) == (2, 3)


def test_bootstrap_intervals_are_seeded_and_bracket_the_estimate():
    rng = np.random.default_rng(3)
    den = rng.integers(10, 100, size=(40, 3)).astype(float)
    num = np.floor(den * rng.uniform(0.3, 0.9, size=(40, 3)))
    den[:, 2] = 0
    num[:, 2] = 0
    lo, hi = ratio_ci(num, den, resamples=300, seed=7)
    lo2, hi2 = ratio_ci(num, den, resamples=300, seed=7)
    assert np.array_equal(lo[:2], lo2[:2]) and np.array_equal(hi[:2], hi2[:2])
    point = num.sum(0) / np.where(den.sum(0) > 0, den.sum(0), np.nan)
    assert np.all(lo[:2] <= point[:2]) and np.all(point[:2] <= hi[:2]) and np.all(lo[:2] < hi[:2])
    assert np.isnan(lo[2]) and np.isnan(hi[2])
    x = rng.normal(size=30)
    y = x + rng.normal(scale=0.5, size=30)
    rlo, rhi = spearman_ci(x, y, resamples=400, seed=1)
    r = spearmanr(x, y).statistic
    assert rlo <= r <= rhi and rhi - rlo < 0.6


def test_confusion_matrix_iou_matches_loop():
    rng = np.random.default_rng(4)
    t = rng.integers(0, 4, size=(50,))
    t[:5] = 255
    p = rng.integers(0, 4, size=(50,))
    cm = ConfusionMatrix(num_classes=4)
    cm.update(torch.from_numpy(t), torch.from_numpy(p))
    iou = cm.iou().numpy()
    for c in range(4):
        valid = t != 255
        inter = np.sum((t == c) & (p == c) & valid)
        union = np.sum(((t == c) | (p == c)) & valid)
        assert iou[c] == pytest.approx(inter / union)
