"""xi's precision counterpart and their F (issue 64): xi is a recall, so a model that paints one class everywhere keeps
every reference pixel of that class (xi_c = 1); the precision (of the valid reference pixels it predicts as c, the
share whose reference is c) and the F (their harmonic mean) see it. Counted by hand on tiny label maps, through the
device reduction, the evaluate entry (xi_precision.csv beside an unchanged xi.csv) and the estimator study."""
from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.evaluation import counting, entry, reductions, registry, shards, tables
from pairedgta.evaluation.xi_precision import XI_PRECISION, XiPrecision, precision_rows
from pairedgta.metrics import (f_from_counts, precision_from_counts, predicted_counts, reference_consistency_counts,
                               xi_from_counts)
from pairedgta.metrics.validity import GroupCounts, cell_measures, precision_measures

K = NUM_CLASSES
ROAD, SKY, CAR, PERSON = (CLASS_NAMES.index(n) for n in ("road", "sky", "car", "person"))
V = IGNORE_INDEX
# the pseudo-label: sky 4, car 2, road 8 valid pixels, 2 void (below the confidence threshold)
REF = np.array([[SKY, SKY, SKY, SKY],
                [CAR, CAR, V, V],
                [ROAD, ROAD, ROAD, ROAD],
                [ROAD, ROAD, ROAD, ROAD]])
GOOD = np.array([[SKY, SKY, SKY, ROAD],        # one sky pixel called road
                 [CAR, ROAD, CAR, CAR],        # one car pixel called road; the void pixels' "car" is not counted
                 [ROAD, ROAD, ROAD, ROAD],
                 [ROAD, ROAD, CAR, ROAD]])     # one road pixel called car
COLLAPSED = np.full((4, 4), SKY)               # paints sky everywhere


def _by_hand(pred):
    retained, reference = (t.numpy() for t in reference_consistency_counts(REF, pred, K))
    predicted = predicted_counts(REF, pred, K)
    return retained, reference, predicted


def test_precision_and_f_by_hand_and_a_collapsed_model():
    retained, reference, predicted = _by_hand(GOOD)
    assert (retained[[SKY, CAR, ROAD]].tolist(), reference[[SKY, CAR, ROAD]].tolist()) == ([3, 1, 7], [4, 2, 8])
    assert predicted[[SKY, CAR, ROAD]].tolist() == [3, 2, 9] and predicted.sum() == 14  # valid pixels only
    p, f = precision_from_counts(retained, predicted), f_from_counts(retained, reference, predicted)
    assert p[[SKY, CAR, ROAD]] == pytest.approx([1.0, 0.5, 7 / 9])
    assert f[[SKY, CAR, ROAD]] == pytest.approx([6 / 7, 0.5, 14 / 17])
    xi = xi_from_counts(retained, reference)
    assert f[ROAD] == pytest.approx(2 * xi[ROAD] * p[ROAD] / (xi[ROAD] + p[ROAD]))  # the harmonic mean
    assert np.isnan(p[PERSON]) and np.isnan(f[PERSON])  # on neither side: undefined, not 0

    retained, reference, predicted = _by_hand(COLLAPSED)
    xi = xi_from_counts(retained, reference)
    p, f = precision_from_counts(retained, predicted), f_from_counts(retained, reference, predicted)
    assert xi[SKY] == 1.0                                     # xi cannot see it: every sky pixel kept
    assert p[SKY] == pytest.approx(4 / 14) and f[SKY] == pytest.approx(8 / 18)   # both low
    assert xi[ROAD] == 0 and np.isnan(p[ROAD]) and f[ROAD] == 0   # never predicted: F 0, precision undefined
    assert precision_from_counts(retained, predicted, "zero")[ROAD] == 0.0       # the authors' convention: 0


def test_the_device_reduction_counts_what_the_host_counts():
    rng = np.random.default_rng(0)
    ref = rng.integers(0, K, (3, 9, 11)).astype(np.uint8)
    ref[rng.random(ref.shape) < 0.3] = V
    pred = rng.integers(0, K, (3, 9, 11)).astype(np.uint8)
    got = reductions.predicted_counts(torch.from_numpy(ref), torch.from_numpy(pred)).numpy()
    assert [got[i].tolist() for i in range(3)] == [predicted_counts(ref[i], pred[i], K).tolist() for i in range(3)]
    shared = reductions.predicted_counts(torch.from_numpy(ref[0]), torch.from_numpy(pred)).numpy()  # one H x W reference
    assert [shared[i].tolist() for i in range(3)] == [predicted_counts(ref[0], pred[i], K).tolist() for i in range(3)]


# -- the entry: xi_precision.csv from hand-made per-group counts ---------------------------------------------------
CLEAN, ADVERSE = "Day-EXTRASUNNY", "Night-RAIN"


def _settings(absent="nan", min_images=2, min_pixels=5):
    conv = {"name": "strict" if absent == "nan" else "paper", "absent": absent, "mean_exclude": [],
            "agreement": "pooled", "rho_headline": "top_m", "min_images": min_images, "min_pixels": min_pixels}
    return {"clean": CLEAN, "tau_mass": 0.5, "class_ids": list(range(K)), "convention": conv, "sampling": "all",
            "min_transmittance": 0.0, "resamples": 50, "confidence": 0.9, "seed": 0, "selections": ["top_m"], "m": 25}


def _groups(pred_adverse):
    """Three groups of the same pseudo-label (REF); the clean prediction is GOOD, the adverse one `pred_adverse`."""
    groups = []
    for g in range(3):
        xi, predicted = {}, {}
        for cond, pred in ((CLEAN, GOOD), (ADVERSE, pred_adverse)):
            retained, reference, pred_counts = _by_hand(pred)
            xi[f"pseudo_label|{cond}"] = [retained.tolist(), reference.tolist()]
            predicted[f"pseudo_label|{cond}"] = pred_counts.tolist()
        groups.append({"group_id": f"g{g}", "xi": xi, "xi_precision": predicted})
    return groups


def _write(tmp_path, groups, **settings):
    covered = {"groups_per_condition": {CLEAN: 3, ADVERSE: 3}, "groups_without_clean": 0}
    e = entry.ModelEvaluation("d", "m", "ref", [CLEAN, ADVERSE], _settings(**settings), groups, covered)
    summary = entry.write_outputs(tmp_path, e, [tables.Xi(), XiPrecision()])
    table = pd.read_csv(tmp_path / XI_PRECISION, keep_default_na=False, na_values=[""])
    return summary, table.set_index(["condition", "class_name"])


def test_the_support_rule_nan_with_its_reason_and_the_means(tmp_path):
    # the adverse prediction: GOOD with one more pixel called person (a road pixel), so person is predicted on 3
    # pixels in 3 images: under min_pixels = 5 (per class, over the images) its precision is out of the mean
    adverse = GOOD.copy()
    adverse[3, 0] = PERSON
    summary, t = _write(tmp_path, _groups(adverse), min_images=2, min_pixels=5)
    person, road, car = t.loc[(ADVERSE, "person")], t.loc[(ADVERSE, "road")], t.loc[(ADVERSE, "car")]
    assert person.predicted_pixels == 3 and person.precision == 0 and not person.predicted_supported
    assert not person.precision_in_mean and person.reason == "not in xi's mean"   # no person in the pseudo-label
    assert (road.retained_pixels, road.reference_pixels, road.predicted_pixels) == (18, 24, 24)
    assert road.precision == pytest.approx(18 / 24) and road.xi_f == pytest.approx(36 / 48)
    assert road.xi_in_mean and road.precision_in_mean and pd.isna(road.reason)
    # car: predicted 6 times in 3 images (>= 5 pixels, >= 2 images): in both means
    assert car.precision == pytest.approx(0.5) and car.precision_in_mean
    mean = t.loc[(ADVERSE, "mean")]
    p = [1.0, 0.5, 18 / 24]            # sky, car, road
    f = [6 / 7, 0.5, 36 / 48]
    assert mean.precision == pytest.approx(np.mean(p)) == summary["xi_precision_mean"][ADVERSE]
    assert mean.xi_f == pytest.approx(np.mean(f)) == summary["xi_f_mean"][ADVERSE]
    assert (mean.precision_classes, mean.xi_f_classes) == (3, 3)
    assert mean.xi == pytest.approx(summary["xi_mean"][ADVERSE])              # xi.csv's mean beside them
    assert mean.precision_ci_low <= mean.precision <= mean.precision_ci_high or math.isnan(mean.precision_ci_low)

    # the collapsed model: road and car never predicted (precision NaN with its reason), their F 0 in the F's mean
    summary, t = _write(tmp_path, _groups(COLLAPSED))
    road, sky, mean = t.loc[(ADVERSE, "road")], t.loc[(ADVERSE, "sky")], t.loc[(ADVERSE, "mean")]
    assert math.isnan(road.precision) and road.reason == "not predicted on valid reference pixels"
    assert math.isnan(road.precision_ci_low) and road.xi_f == 0 and road.xi_in_mean and not road.precision_in_mean
    assert sky.xi == 1.0 and sky.precision == pytest.approx(4 / 14) and sky.xi_f == pytest.approx(8 / 18)
    assert mean.precision == pytest.approx(4 / 14) and mean.precision_classes == 1
    assert mean.xi_f == pytest.approx((8 / 18) / 3) and mean.xi_f_classes == 3
    assert summary["xi_mean"][ADVERSE] == pytest.approx(1 / 3)

    # too little support for xi itself (min_images above the 3 images): out of both means, as in xi.csv
    _, t = _write(tmp_path, _groups(GOOD), min_images=4)
    assert not t["xi_in_mean"].any() and math.isnan(t.loc[(ADVERSE, "mean")].xi_f)
    # the authors' convention: a class never predicted scores 0 and counts, as xi's absent classes do
    _, t = _write(tmp_path, _groups(COLLAPSED), absent="zero", min_images=0, min_pixels=0)
    assert t.loc[(ADVERSE, "road")].precision == 0.0
    assert t.loc[(ADVERSE, "mean")].precision == pytest.approx((4 / 14) / K)


def test_a_collapsed_model_passes_a_weak_one_by_xi_and_not_by_f():
    """Three equal classes of N pixels. The weak model keeps 30 % of each, its errors spread evenly (precision 0.3
    too); the collapsed one paints the first class everywhere: mean xi 1/3 > 0.3, mean F 1/6 < 0.3."""
    n = 1000
    cls = [ROAD, SKY, CAR]
    reference = np.zeros(K, int)
    reference[cls] = n
    weak_ret, weak_pred = np.zeros(K, int), np.zeros(K, int)
    weak_ret[cls], weak_pred[cls] = 300, n
    col_ret, col_pred = np.zeros(K, int), np.zeros(K, int)
    col_ret[ROAD], col_pred[ROAD] = n, 3 * n
    s = _settings(min_images=0, min_pixels=0)
    weak = precision_rows(weak_ret[None], reference[None], weak_pred[None], s)["means"]
    collapsed = precision_rows(col_ret[None], reference[None], col_pred[None], s)["means"]
    assert (collapsed["xi"][0], weak["xi"][0]) == pytest.approx((1 / 3, 0.3))
    assert (collapsed["f"][0], weak["f"][0]) == pytest.approx(((2 * n / (4 * n)) / 3, 0.3))
    assert (collapsed["precision"][0], weak["precision"][0]) == pytest.approx((1 / 3, 0.3))  # one class predicted


class _Fixed:
    """A stand-in segmenter: the left half of each image class 0 at probability 0.875, the right half class 0 on the
    bright (clean) image and class 1 on the dark one, at 0.625 (as tests/test_evaluate_estimators.py's)."""

    name = "fixed"

    def predict_with_entropy(self, images):
        from pairedgta.models.base import normalised_entropy

        b, h, w, _ = images.shape
        probs = torch.full((b, K, h, w), 0.125 / 18)
        probs[:, 0, :, : w // 2] = 0.875
        for i in range(b):
            cls, p = (0, 0.875) if images[i].mean() > 100 else (1, 0.625)
            probs[i, :, :, w // 2 :] = (1 - p) / 18
            probs[i, cls, :, w // 2 :] = p
        conf, labels = probs.max(1)
        return labels, conf, normalised_entropy(probs)


def _fixed_groups():
    """Records of two groups counted by `counting.group_counts` with a stand-in model (every metric's update)."""
    images = {CLEAN: np.full((4, 6, 3), 200, np.uint8), ADVERSE: np.full((4, 6, 3), 20, np.uint8)}
    pseudo = np.zeros((4, 6), np.uint8)
    pseudo[0, :] = V
    s = {**_settings(min_images=1, min_pixels=1), "class_ids": [0, 1]}
    return s, [counting.group_counts({"group_id": f"g{i}", "present": [CLEAN, ADVERSE], "images": images,
                                      "pseudo": pseudo, "own": {CLEAN: pseudo}}, _Fixed(), s, CLEAN, True, 2, "fixed", "d")
               for i in range(2)]


def test_xi_and_the_other_tables_are_byte_for_byte_what_they_were(tmp_path):
    """The entry with the new metric against the entry without it (the registry before issue 64): xi.csv and every
    other table the same bytes, estimators.csv and summary.json only gain their last columns / keys, group_counts.npz
    its `*_predicted` arrays; the per-group record survives a shard job's round trip."""
    s, groups = _fixed_groups()
    # _Fixed at night: the right half turns from class 0 to class 1, the top row void in the pseudo-label
    pred = groups[0]["xi_precision"][f"pseudo_label|{ADVERSE}"]
    assert (pred[0], pred[1]) == (9, 9)  # 18 valid pixels: 9 kept as road, 9 called class 1
    covered = {"groups_per_condition": {CLEAN: 2, ADVERSE: 2}, "groups_without_clean": 0}
    old = [m for m in registry.metrics() if not isinstance(m, XiPrecision)]
    before, after = tmp_path / "before", tmp_path / "after"
    for out, ms in ((before, old), (after, registry.metrics())):
        out.mkdir()
        e = entry.ModelEvaluation("d", "fixed", "ref", [CLEAN, ADVERSE], s, groups, covered)
        entry.write_outputs(out, e, ms)
    for name in (tables.XI, tables.AGREEMENT, tables.FRAME_COUNTS, tables.RHO_VALID):
        assert (before / name).read_bytes() == (after / name).read_bytes(), name
    assert {p.name for p in after.iterdir()} - {p.name for p in before.iterdir()} == {XI_PRECISION}
    old_est, new_est = pd.read_csv(before / tables.ESTIMATORS), pd.read_csv(after / tables.ESTIMATORS)
    assert list(new_est.columns) == [*old_est.columns, "xi_precision", "xi_f"]
    pd.testing.assert_frame_equal(new_est[old_est.columns], old_est)
    assert new_est.set_index("condition").loc[ADVERSE, "xi_precision"] == pytest.approx(1.0)  # road: 9 of 9
    assert new_est.set_index("condition").loc[ADVERSE, "xi_f"] == pytest.approx(2 * 9 / (18 + 9))
    s_old, s_new = (json.loads((d / entry.SUMMARY).read_text()) for d in (before, after))
    assert list(s_new)[: len(s_old)] == list(s_old) and {k: s_new[k] for k in s_old if k != "estimators"} == {
        k: v for k, v in s_old.items() if k != "estimators"}
    assert s_new["xi_precision_mean"][ADVERSE] == pytest.approx(1.0) and s_new["xi_f_mean"][ADVERSE] == pytest.approx(2 / 3)
    z_old, z_new = (np.load(d / entry.GROUP_COUNTS) for d in (before, after))
    assert set(z_new.files) - set(z_old.files) == {"pseudo_label_predicted", "ground_truth_predicted"}
    for k in z_old.files:  # NaN where the stand-in gives no Grams or logits: equal as NaN
        np.testing.assert_array_equal(z_old[k], z_new[k])
    # evaluate's estimators.csv and the study read the same numbers from the counts
    g = GroupCounts.from_arrays("fixed", dict(z_new))
    include = np.ones(K, bool)
    m = precision_measures(g, np.ones((1, 2)), include, "nan", 1, 1)
    assert m["xi_precision_mean"][0, 1] == pytest.approx(1.0) and m["xi_f_mean"][0, 1] == pytest.approx(2 / 3)
    assert cell_measures(g, np.ones((1, 2)), CLEAN, include, "nan", 1, 1)["xi_mean"][0, 1] == pytest.approx(0.5)
    parts = tmp_path / "parts"
    shards.write_part(parts, 0, 1, groups)
    assert shards.read_parts(parts)["g1"]["xi_precision"] == groups[1]["xi_precision"]


def test_the_study_ranks_xi_precision_and_xi_f_beside_the_others():
    """Five models on hand-made counts: the collapsed one (m4) is third by xi, last by xi_f; both new estimators
    get every statistic of the study (the within-condition mean, its intervals, the paired difference to xi)."""
    from pairedgta.metrics.estimators import EstimatorCounts
    from pairedgta.metrics.estimator_study import compare

    rng = np.random.default_rng(0)
    conds = ("clean", "A", "B")
    cls = [ROAD, SKY, CAR]
    n_groups, n = 6, 200
    quality = {"m0": 0.9, "m1": 0.7, "m2": 0.5, "m3": 0.25, "m4": None}   # m4 paints road everywhere
    groups, counts = [], []
    for name, q in quality.items():
        ref = np.zeros((n_groups, 3, K), np.int64)
        ref[:, :, cls] = n
        ret, pred = np.zeros_like(ref), np.zeros_like(ref)
        cm = np.zeros((n_groups, 3, K, K), np.int64)
        for c in range(3):
            for g in range(n_groups):
                keep = 0.95 if c == 0 else (q if q is not None else 0.0)
                if q is None and c > 0:   # collapsed: every valid pixel called road
                    ret[g, c, ROAD], pred[g, c, ROAD] = n, 3 * n
                    cm[g, c, cls, ROAD] = n
                    continue
                k = int(round(n * np.clip(keep + rng.normal(0, 0.02), 0, 1)))
                ret[g, c, cls], pred[g, c, cls] = k, n          # errors spread evenly over the other classes
                for t in cls:
                    cm[g, c, t, t] = k
                    for o in cls:
                        if o != t:
                            cm[g, c, t, o] = (n - k) // 2
        ids = tuple(f"{g}" for g in range(n_groups))
        groups.append(GroupCounts(name, conds, ret, ref, ret, ref, cm, ids, pred))
        pix = np.full((n_groups, 3), 3 * n)
        counts.append(EstimatorCounts(name, conds, pix, pix * 0.8, pix * 0.2, np.zeros((n_groups, 3, 1000), np.int64),
                                      pix // 2, ids))
    scored = np.full((n_groups, 3, 5, 5), 3 * n)
    agree = scored // 2
    cells, stats, _ = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=40, permutations=50)
    cells, stats = pd.DataFrame(cells), pd.DataFrame(stats)
    adverse = cells[cells["condition"] == "A"].set_index("model")
    assert adverse["xi"].rank(ascending=False)["m4"] == 4                     # 1/3: above m3's 0.25
    assert adverse["xi_f"].idxmin() == "m4" and adverse["xi_f"]["m4"] == pytest.approx((2 * n / (4 * n)) / 3)
    assert adverse["xi_precision"]["m4"] == pytest.approx(1 / 3)
    s = stats.set_index(["estimator", "target", "scope"])
    for e in ("xi_precision", "xi_f"):
        for t in ("rpc", "gt_miou"):
            row = s.loc[(e, t, "within_mean")]
            assert row["n_models"] == 5 and math.isfinite(row["spearman"]) and math.isfinite(row["spearman_minus_xi"])
    assert s.loc[("xi_f", "gt_miou", "within_mean"), "spearman"] > s.loc[("xi", "gt_miou", "within_mean"), "spearman"]
