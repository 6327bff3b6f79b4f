"""The paper's metrics against independent computations (numpy loops, scipy) on random data."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from pairedgta.errors import ConfigError
from pairedgta.metrics import (
    ConfusionMatrix,
    ReferenceConsistency,
    aggregate_agreement,
    class_mean,
    mean_mask,
    pixel_agreement,
    prediction_mass,
    prediction_mass_from_labels,
    ratio_ci,
    rho_valid,
    select_frames,
    spearman_ci,
    xi_from_counts,
)
from pairedgta.metrics.bootstrap import class_mean_ci
from pairedgta.metrics.conventions import convention_from_config

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
    # fewer frames than M: the frames that show the class, never padded with frames of count 0
    assert rho_valid(clean, adverse, m=25) == pytest.approx(spearmanr(clean[nz], adverse[nz]).statistic)
    assert select_frames(clean, m=25).tolist() == [2, 3, 4, 5, 7]
    # the case: 3 informative frames in fully reversed order among 25 empty ones is -1, not 0.99
    few = np.zeros(28)
    few[:3] = [30, 20, 10]
    rev = np.zeros(28)
    rev[:3] = [10, 20, 30]
    assert rho_valid(few, rev, m=25) == pytest.approx(-1.0)
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


def test_pixel_agreement_of_arrays_equals_that_of_tensors():
    rng = np.random.default_rng(7)
    a, b, ref = (rng.integers(0, 4, size=(5, 6)) for _ in range(3))
    ref[0] = 255
    assert pixel_agreement(a, b, ref) == pixel_agreement(*(torch.from_numpy(x) for x in (a, b, ref)))
    assert pixel_agreement(a, b, ref) == (int(((a == b) & (ref != 255)).sum()), 24)


def test_metrics_fed_per_image_counts_equal_the_streaming_update():
    """evaluate sums per-image counts (counted in a worker or a shard job) through `update_counts`: the
    result must be what `update` on the label maps themselves gives."""
    from pairedgta.metrics import reference_consistency_counts
    from pairedgta.metrics.segmentation import confusion_counts

    rng = np.random.default_rng(8)
    refs, preds = random_maps(rng, 4)
    streamed, summed = ReferenceConsistency(C, 255), ReferenceConsistency(C, 255)
    cm_streamed, cm_summed = ConfusionMatrix(C), ConfusionMatrix(C)
    for r, p in zip(refs, preds):
        streamed.update(torch.from_numpy(r), torch.from_numpy(p))
        summed.update_counts(*(x.tolist() for x in reference_consistency_counts(r, p, C, 255)))
        cm_streamed.update(r, p)
        cm_summed.update_counts(confusion_counts(r, p, C, 255).tolist())
    np.testing.assert_array_equal(summed.compute().numpy(), streamed.compute().numpy())
    assert torch.equal(summed.reference, streamed.reference) and torch.equal(cm_summed.mat, cm_streamed.mat)
    assert cm_summed.miou() == cm_streamed.miou() and int(cm_summed.mat.sum()) == sum(int((r != 255).sum()) for r in refs)
    with pytest.raises(ValueError, match="19 classes"):
        summed.update_counts([1, 2], [3, 4])
    with pytest.raises(ValueError, match="confusion matrix"):
        cm_summed.update_counts(np.zeros((4, 4), int))


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


def test_xi_absent_zero_is_the_authors_clamp_and_the_mean_keeps_the_zeros():
    rng = np.random.default_rng(5)
    refs, preds = random_maps(rng, 4)
    nan_metric, zero_metric = ReferenceConsistency(C, 255, absent="nan"), ReferenceConsistency(C, 255, absent="zero")
    for r, p in zip(refs, preds):
        nan_metric.update(torch.from_numpy(r), torch.from_numpy(p))
        zero_metric.update(torch.from_numpy(r), torch.from_numpy(p))
    want, num, den = xi_loop(refs, preds)
    clamp = num / np.maximum(den, 1)  # the authors' code
    np.testing.assert_allclose(zero_metric.compute().numpy(), clamp)
    assert zero_metric.compute()[1].item() == 0.0 and math.isnan(nan_metric.compute()[1].item())
    # the paper's Mean: 17 classes (bus, train dropped), absent ones as 0; the strict mean: defined of 19
    keep = mean_mask(C, None, ())
    assert keep.all()
    names = [str(k) for k in range(C)]
    paper17 = mean_mask(C, names, ("15", "16"))
    assert zero_metric.mean(paper17) == pytest.approx(clamp[[k for k in range(C) if k not in (15, 16)]].sum() / 17)
    assert nan_metric.mean() == pytest.approx(np.nanmean(want))
    assert nan_metric.mean() > zero_metric.mean(paper17)  # 5 present classes out of 17: the zeros pull it down
    with pytest.raises(ValueError, match="absent-class policy"):
        ReferenceConsistency(C, 255, absent="skip")
    with pytest.raises(ValueError, match="unknown class"):
        mean_mask(C, names, ("bus",))


def test_xi_from_counts_and_class_mean():
    got = xi_from_counts([3, 0, 0], [4, 0, 2], "zero")
    np.testing.assert_allclose(got, [0.75, 0.0, 0.0])
    got = xi_from_counts([3, 0, 0], [4, 0, 2], "nan")
    assert got[0] == 0.75 and math.isnan(got[1]) and got[2] == 0.0
    assert class_mean(got) == pytest.approx(0.375)
    assert class_mean(got, [False, True, True]) == 0.0
    assert math.isnan(class_mean(got, [False, True, False]))


def test_pixel_agreement_pooled_vs_per_image():
    agree, valid = np.array([90, 1, 0, 5]), np.array([100, 10, 0, 5])
    assert aggregate_agreement(agree, valid, "pooled") == pytest.approx(96 / 115)
    # every image with valid pixels weighs the same; the empty one drops out
    assert aggregate_agreement(agree, valid, "per_image") == pytest.approx((0.9 + 0.1 + 1.0) / 3)
    assert math.isnan(aggregate_agreement([0], [0], "per_image")) and math.isnan(aggregate_agreement([0], [0], "pooled"))
    with pytest.raises(ValueError):
        aggregate_agreement(agree, valid, "median")


def test_bootstrap_follows_the_absent_convention():
    rng = np.random.default_rng(6)
    den = rng.integers(0, 50, size=(30, 4)).astype(float)
    den[:25, 1] = 0  # class 1 only in 5 images: many resamples lack it
    den[:, 3] = 0    # class 3 never present
    num = np.floor(den * 0.7)
    lo_n, hi_n = ratio_ci(num, den, resamples=300, seed=2, absent="nan")
    lo_z, hi_z = ratio_ci(num, den, resamples=300, seed=2, absent="zero")
    assert np.isnan(lo_n[3]) and (lo_z[3], hi_z[3]) == (0.0, 0.0)
    assert lo_z[1] <= lo_n[1]  # resamples without class 1 score 0 under the clamp
    include = np.array([True, True, True, True])
    point_z = class_mean(xi_from_counts(num.sum(0), den.sum(0), "zero"), include)
    mlo, mhi = class_mean_ci(num, den, include, resamples=300, seed=2, absent="zero")
    assert mlo <= point_z <= mhi
    defined = den.sum(0) > 0
    point_n = class_mean(xi_from_counts(num.sum(0), den.sum(0), "nan"), defined)
    mlo, mhi = class_mean_ci(num, den, defined, resamples=300, seed=2, absent="nan")
    assert mlo <= point_n <= mhi and point_n > point_z


def test_convention_configs_parse_and_bad_values_name_the_key():
    from pairedgta.testing.cli import compose_cfg
    from omegaconf import OmegaConf

    paper = convention_from_config(OmegaConf.to_container(compose_cfg(["metric=paper"]).metric, resolve=True))
    assert (paper.name, paper.absent, paper.mean_exclude, paper.agreement, paper.rho_headline) == (
        "paper", "zero", ("bus", "train"), "per_image", "nonzero")
    assert paper.mean_classes().sum() == 17
    strict = convention_from_config(OmegaConf.to_container(compose_cfg(["metric=strict"]).metric, resolve=True))
    assert (strict.absent, strict.mean_exclude, strict.agreement, strict.rho_headline) == ("nan", (), "pooled", "top_m")
    assert strict.mean_classes().sum() == 19
    with pytest.raises(ConfigError, match="metric.absent='skip'"):
        convention_from_config({"absent": "skip"})
    with pytest.raises(ConfigError, match="metric.mean_exclude"):
        convention_from_config({"mean_exclude": ["buss"]})
    with pytest.raises(ConfigError, match="metric.agreement"):
        convention_from_config({"agreement": "mean"})
    with pytest.raises(ConfigError, match="metric.rho.headline"):
        convention_from_config({"rho": {"selections": ["top_m"], "headline": "nonzero"}})


def test_miou_averages_classes_with_tp_fp_or_fn():
    # class 0 and 1 in the truth; class 2 only predicted (IoU 0, counts); class 3 nowhere (left out)
    t = np.array([0, 0, 0, 1, 1, 1, 255, 255])
    p = np.array([0, 0, 2, 1, 1, 1, 3, 3])  # predictions on void pixels count nowhere
    cm = ConfusionMatrix(num_classes=4)
    cm.update(torch.from_numpy(t), torch.from_numpy(p))
    iou = cm.iou().numpy()
    assert iou[0] == pytest.approx(2 / 3) and iou[1] == 1.0 and iou[2] == 0.0 and math.isnan(iou[3])
    assert cm.miou() == pytest.approx((2 / 3 + 1.0 + 0.0) / 3)  # not (2/3 + 1) / 2: the GT-present mean


def _cityscapes_label_ids():
    from cityscapesscripts.helpers.labels import trainId2label

    lut = np.zeros(256, np.uint8)  # train id 255 (void) -> label id 0 (unlabeled, ignored in evaluation)
    for train_id in range(C):
        lut[train_id] = trainId2label[train_id].id
    return lut


def test_miou_matches_cityscapesscripts_on_the_same_predictions(tmp_path):
    """cityscapesscripts' own evaluator on label-id PNGs written here vs ConfusionMatrix on the train ids."""
    from PIL import Image
    import copy

    from cityscapesscripts.evaluation import evalPixelLevelSemanticLabeling as cs_eval

    rng = np.random.default_rng(7)
    lut = _cityscapes_label_ids()
    cm = ConfusionMatrix(C, 255)
    gts, preds = [], []
    for i in range(4):
        # the truth uses a few classes; the model predicts those plus others (FP-only classes)
        truth = rng.choice([0, 1, 2, 8, 10, 13, 255], size=(24, 32)).astype(np.uint8)
        pred = np.where(rng.random(truth.shape) < 0.7, truth, rng.choice([0, 5, 11, 13, 18], size=truth.shape))
        pred = np.where(pred == 255, 0, pred).astype(np.uint8)
        cm.update(torch.from_numpy(truth.astype(np.int64)), torch.from_numpy(pred.astype(np.int64)))
        gt_file = tmp_path / f"city_000000_{i:06d}_gtFine_labelIds.png"
        pred_file = tmp_path / f"pred_{i}.png"
        Image.fromarray(lut[truth]).save(gt_file)
        Image.fromarray(lut[pred]).save(pred_file)
        gts.append(str(gt_file))
        preds.append(str(pred_file))
    args = copy.copy(cs_eval.args)
    args.evalInstLevelScore = False
    args.JSONOutput = False
    args.quiet = True
    args.exportFile = str(tmp_path / "result.json")
    result = cs_eval.evaluateImgLists(preds, gts, args)
    want = result["averageScoreClasses"]
    assert cm.miou() == pytest.approx(want, abs=1e-12)
    iou = cm.iou().numpy()
    for k in range(C):
        from cityscapesscripts.helpers.labels import trainId2label

        cs = result["classScores"][trainId2label[k].name]
        assert (math.isnan(cs) and math.isnan(iou[k])) or iou[k] == pytest.approx(cs)
    # the ground-truth-present mean would differ: classes 5, 11, 18 are predicted but never true
    present = cm.mat.sum(1) > 0
    assert abs(float(cm.iou()[present].mean()) - want) > 1e-3


def test_zero_width_intervals_are_no_interval():
    from pairedgta.metrics.bootstrap import drop_zero_width
    from pairedgta.metrics.ranking import rho_rows

    assert all(math.isnan(v) for v in drop_zero_width(1.0, 1.0))
    assert drop_zero_width(0.2, 0.4) == (0.2, 0.4)
    lo, hi = drop_zero_width(np.array([0.5, 1.0, np.nan]), np.array([0.7, 1.0, np.nan]))
    assert lo[0] == 0.5 and np.isnan(lo[1]) and np.isnan(hi[1]) and np.isnan(lo[2])
    # perfectly monotone frames: every resample gives rho 1, which is no evidence of certainty
    row, = rho_rows(np.arange(1, 9), np.arange(1, 9) * 2, ["nonzero"], resamples=200)
    assert row["rho"] == pytest.approx(1.0) and math.isnan(row["ci_low"]) and math.isnan(row["ci_high"])
