"""Label-free estimators of robustness compared as judges of ground truth (pairedgta/metrics/estimators.py,
figure `estimators` of the experiment metric_validity). Hand-made numbers with known answers."""
from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pairedgta import schema
from pairedgta.errors import ConfigError
from pairedgta.metrics.estimators import (ESTIMATORS, TARGETS, EstimatorCounts, atc, atc_threshold, estimator_values,
                                          committee_agreement, pairwise_agreement)
from pairedgta.metrics.estimator_study import compare, loco_mae, model_draws, permutation_pvalue, ranked_models
from pairedgta.metrics.validity import GroupCounts

K, B = 19, 1000
CONDS = ("clean", "A", "B")


def _hist(bins_per_condition: list[list[int]]) -> np.ndarray:
    """1 x C x B histogram: one pixel in each listed bin."""
    h = np.zeros((1, len(bins_per_condition), B), np.int64)
    for c, bins in enumerate(bins_per_condition):
        for b in bins:
            h[0, c, b] += 1
    return h


def _cm(pairs: dict[tuple[int, int], int]) -> np.ndarray:
    m = np.zeros((K, K), np.int64)
    for (t, p), n in pairs.items():
        m[t, p] = n
    return m


def test_atc_threshold_is_the_smallest_edge_where_the_clean_share_above_it_is_the_clean_accuracy():
    # clean confidences 0.95, 0.85, 0.75, 0.65 (one pixel each); accuracy 3/4
    hist = _hist([[950, 850, 750, 650], [700, 600, 500, 900]])
    cm = np.zeros((1, 2, K, K), np.int64)
    cm[0, 0] = _cm({(0, 0): 3, (1, 0): 1})  # clean: 3 of 4 right
    score, t = atc(hist, cm, 0, np.ones((1, 1)))
    # share >= e is 1 up to e = 0.650 (bin 650 holds [0.650, 0.651)); 3/4 from 0.651 on
    assert t[0] == pytest.approx(0.651)
    assert score[0, 1] == pytest.approx(0.5)  # adverse pixels in bins 700 and 900 are >= 0.651
    assert score[0, 0] == pytest.approx(0.75)  # on the clean data ATC is the accuracy
    # the threshold follows the accuracy: 1/2 -> 0.751, 1 -> 0 (every pixel), 0 -> above the highest bin
    clean = hist[0, 0].astype(float)
    assert list(atc_threshold(np.stack([clean] * 3), np.array([0.5, 1.0, 0.0]))) == [751, 0, 951]
    assert atc_threshold(np.zeros(B), np.array(0.5)) == -1  # an empty histogram has no threshold
    # three pixels at 0.010..0.011, one at 0.999..1: accuracy 1/4 keeps the top one from the edge 0.011 on;
    # below 1/4 no edge but B/B = 1 keeps a share that small
    h1 = _hist([[999, 10, 10, 10]])[0, 0]
    assert list(atc_threshold(np.stack([h1, h1]), np.array([0.25, 0.2]))) == [11, B]


def test_atc_weights_pick_the_groups():
    hist = np.concatenate([_hist([[950, 850, 750, 650], [700, 600, 500, 900]]),
                           _hist([[950, 950, 950, 950], [100, 100, 100, 960]])])
    cm = np.zeros((2, 2, K, K), np.int64)
    cm[0, 0] = _cm({(0, 0): 3, (1, 0): 1})
    cm[1, 0] = _cm({(0, 0): 2, (1, 0): 2})
    w = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    score, t = atc(hist, cm, 0, w)
    # group 2 alone: accuracy 1/2 but every clean pixel at 0.95: the share drops to 0 at 0.951
    assert t[1] == pytest.approx(0.951) and score[1, 1] == pytest.approx(0.25)
    # both: accuracy 5/8; clean confidences 0.95 x5, 0.85, 0.75, 0.65: share <= 5/8 from 0.851 on
    assert t[2] == pytest.approx(0.851) and score[2, 1] == pytest.approx(2 / 8)
    assert t[0] == pytest.approx(0.651)


def test_atc_fits_its_threshold_on_held_out_clean_scenes():
    """Group 0: clean confidences 0.95, 0.85, 0.75, 0.65 with accuracy 3/4 (threshold 0.651 on its own);
    group 1: four clean pixels at 0.95 with accuracy 1/2 (threshold 0.951). Adverse: group 0 at 0.70, 0.60,
    0.50, 0.90; group 1 at 0.10 three times and 0.96. Held out, group 0 is scored with group 1's threshold
    (nothing >= 0.951) and group 1 with group 0's (0.96 >= 0.651): ATC = (0 + 1) / 8; on the clean images
    (0 + 4) / 8, so relative ATC 1/4. Fitted on the test scenes themselves (accuracy 5/8, threshold 0.851)
    it would be 2/8."""
    from pairedgta.metrics.estimators import atc_held_out

    hist = np.concatenate([_hist([[950, 850, 750, 650], [700, 600, 500, 900]]),
                           _hist([[950, 950, 950, 950], [100, 100, 100, 960]])])
    cm = np.zeros((2, 2, K, K), np.int64)
    cm[0, 0] = _cm({(0, 0): 3, (1, 0): 1})
    cm[1, 0] = _cm({(0, 0): 2, (1, 0): 2})
    score, t = atc_held_out(hist, cm, 0, np.ones((1, 2)))
    np.testing.assert_allclose(score[0], [0.5, 0.125])
    assert t[0] == pytest.approx((0.651 + 0.951) / 2)
    assert atc(hist, cm, 0, np.ones((1, 2)))[0][0, 1] == pytest.approx(0.25)  # in-sample, for contrast
    # one group: no held-out scene to fit on
    assert np.isnan(atc_held_out(hist[:1], cm[:1], 0, np.ones((1, 1)))[0]).all()


def _counts(model: str = "m", clean_cm: np.ndarray | None = None) -> tuple[GroupCounts, EstimatorCounts]:
    """Two groups, conditions clean, A, B; every sum hand-chosen (see the test below)."""
    cm = np.zeros((2, 3, K, K), np.int64)
    cm[:, 0] = _cm({(0, 0): 3, (0, 1): 1, (1, 0): 1, (1, 1): 3}) if clean_cm is None else clean_cm  # IoU 3/5 each
    cm[:, 1] = _cm({(0, 0): 2, (0, 1): 2, (1, 0): 2, (1, 1): 2})                                      # IoU 1/3 each
    cm[:, 2] = _cm({(0, 0): 1, (0, 1): 3, (1, 0): 3, (1, 1): 1})                                      # IoU 1/7 each
    ref = np.zeros((2, 3, K), np.int64)
    ref[..., 0] = 10
    ret = ref.copy()
    ret[:, 1, 0], ret[:, 2, 0] = 8, 5
    g = GroupCounts(model, CONDS, ret, ref, ret, ref, cm, ("g0", "g1"))
    hist = np.zeros((2, 3, B), np.int64)
    hist[0, :, 900], hist[1, :, 900] = 10, 30
    c = EstimatorCounts(model, CONDS, pixels=np.array([[10, 10, 10], [30, 30, 30]]),
                        conf_sum=np.array([[9.0, 8, 5], [27, 21, 15]]),
                        entropy_sum=np.array([[1.0, 2, 3], [3, 6, 9]]), conf_hist=hist,
                        agree_clean=np.array([[10, 7, 5], [30, 21, 15]]), group_ids=("g0", "g1"))
    return g, c


def _values(models, counts, w):
    m = len(models)
    agree = np.zeros((w.shape[1], 3, m, m), np.int64)
    return estimator_values(models, counts, agree, agree + 1, w, "clean", np.ones(K, bool))


def test_ac_entropy_doc_self_agreement_and_clean_miou_by_hand():
    g, c = _counts()
    v = _values([g], [c], np.array([[1.0, 1.0], [1.0, 0.0]]))
    # AC: clean 36/40, A 29/40, B 20/40; group 0 alone: 9/10, 8/10, 5/10
    np.testing.assert_allclose(v["ac"][0], [[0.9, 0.725, 0.5], [0.9, 0.8, 0.5]])
    # 1 - entropy: 1 - 4/40, 1 - 8/40, 1 - 12/40
    np.testing.assert_allclose(v["entropy"][0, 0], [0.9, 0.8, 0.7])
    np.testing.assert_allclose(v["self_agreement"][0, 0], [1.0, 0.7, 0.5])
    # clean GT mIoU: classes 0 and 1, IoU 3 / (4 + 4 - 3) = 0.6 each
    np.testing.assert_allclose(v["clean_miou"][0, 0], [0.6, 0.6, 0.6])
    # DoC: 0.6 + AC(adverse) - AC(clean)
    np.testing.assert_allclose(v["doc"][0, 0], [0.6, 0.6 - 0.175, 0.6 - 0.4])
    np.testing.assert_allclose(v["gt_miou"][0, 0], [0.6, 1 / 3, 1 / 7])
    np.testing.assert_allclose(v["rpc"][0, 0], [1.0, (1 / 3) / 0.6, (1 / 7) / 0.6])
    np.testing.assert_allclose(v["xi"][0, 0], [1.0, 0.8, 0.5])
    # relative versions: divided by the clean value (xi 1.0 clean here; AC 0.9)
    np.testing.assert_allclose(v["xi_rel"][0, 0], [1.0, 0.8, 0.5])
    np.testing.assert_allclose(v["ac_rel"][0, 0], [1.0, 0.725 / 0.9, 0.5 / 0.9])
    # the baseline: clean GT mIoU 0.6 times the self-agreement
    np.testing.assert_allclose(v["clean_miou_x_self_agreement"][0, 0], [0.6, 0.6 * 0.7, 0.6 * 0.5])
    # ATC: accuracy 6/8 in each group, every pixel at 0.90x: each group's threshold, fitted on the other
    # group's clean image, lies above them, nothing is above it. Group 0 alone has no other group to fit on.
    np.testing.assert_allclose(v["atc_threshold"][0], [0.901, np.nan])
    np.testing.assert_allclose(v["atc"][0, 0], [0.0, 0.0, 0.0])
    assert np.isnan(v["atc"][0, 1]).all()


def _write_predictions(path: Path, groups: list[np.ndarray], conds=("clean", "A")) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    arrays = {"group_id": np.array([f"{i:05d}" for i in range(len(groups))]), "conditions": np.array(conds)}
    arrays.update({f"g{i:05d}": g.astype(np.uint8) for i, g in enumerate(groups)})
    np.savez_compressed(path / "predictions.npz", **arrays)
    return path / "predictions.npz"


def test_committee_agreement_is_the_mean_agreement_with_the_other_models(tmp_path):
    zeros, half, other = np.zeros((2, 2, 4)), np.zeros((2, 2, 4)), np.zeros((2, 2, 4))
    half[:, 1, :] = 1    # agrees with `zeros` on half the pixels
    other[:, 0, :] = 1   # agrees with `zeros` on the other half, with `half` nowhere
    absent = np.full((2, 2, 4), 255)
    absent[0] = 3        # group 1: condition A was not rendered; on its clean image all three predict 3
    files = [_write_predictions(tmp_path / n, [p, np.where(absent == 255, 255, a)])
             for n, p, a in (("a", zeros, 3), ("b", half, 3), ("c", other, 3))]
    sources = [np.load(f) for f in files]
    agree, scored = pairwise_agreement(sources, 2)
    assert agree.shape == (2, 2, 3, 3)
    assert agree[0, 1, 0, 1] == 4 and scored[0, 1, 0, 1] == 8 and agree[0, 1, 1, 2] == 0
    assert scored[1, 1].sum() == 0 and agree[1, 0, 0, 1] == 8  # the absent image scores nothing
    v = committee_agreement(agree, scored, np.ones((1, 2)))
    np.testing.assert_allclose(v[:, 0, 1], [0.5, 0.25, 0.25])
    # clean: group 0 as A, group 1 all agree: (4 + 8) / 16 with each other model
    np.testing.assert_allclose(v[:, 0, 0], [0.75, (12 / 16 + 8 / 16) / 2, (12 / 16 + 8 / 16) / 2])
    # a group with no image predicted has no key: it scores nothing
    agree2, scored2 = pairwise_agreement([{"g00000": zeros}, {"g00000": half}], 2)
    assert agree2.shape == (2, 2, 2, 2) and scored2[1].sum() == 0 and agree2[0, 0, 0, 1] == 4
    with pytest.raises(ValueError, match="shapes"):
        pairwise_agreement([{"g00000": zeros}, {"g00000": zeros[:, :1]}], 1)


def test_loco_mae_is_zero_on_a_line_and_known_otherwise():
    rng = np.random.default_rng(0)
    x = rng.random((5, 4))
    out = loco_mae(x, 2 * x + 1)
    assert out["mae"] == pytest.approx(0, abs=1e-12) and out["mae_baseline"] > 0.1
    # two models (x = 0, 1) under three conditions; fits per held-out condition: 0.5 + 1.5x, 0.5 + 1.5x, 2x
    x = np.array([[0.0, 0, 0], [1, 1, 1]])
    y = np.array([[0.0, 0, 1], [2, 2, 2]])
    out = loco_mae(x, y)
    assert out["mae"] == pytest.approx(2 / 6)
    np.testing.assert_allclose(out["per_condition"], [0.25, 0.25, 0.5])
    # the training mean: 1.25, 1.25, 1 -> errors (1.25, 0.75), (1.25, 0.75), (0, 1)
    assert out["mae_baseline"] == pytest.approx(5 / 6)
    np.testing.assert_allclose(out["per_condition_baseline"], [1.0, 1.0, 0.5])


def test_permutation_p_value_is_small_for_the_target_itself_and_large_for_an_unrelated_order():
    y = np.array([[1.0, 2, 3, 4, 5], [5, 1, 2, 3, 4], [3, 5, 1, 2, 4]])
    n = 2000  # >= 5! = 120: every permutation of the 5 models, applied to all three conditions at once
    p = permutation_pvalue(y.copy(), y, n, seed=0)
    assert p == pytest.approx(1 / 120)  # only the identity orders every condition as the target
    assert permutation_pvalue(y.copy(), y, 100, seed=0) <= 2 / 101  # fewer than 5!: random orders
    # Spearman exactly 0 in each condition (sum of squared rank differences 20)
    x = np.stack([np.array([2.0, 5, 3, 1, 4])[np.argsort(np.argsort(row))] for row in y])
    assert permutation_pvalue(x, y, 1, 0) > 0  # defined
    p0 = permutation_pvalue(x, y, n, seed=0)
    assert 0.3 < p0 < 0.8
    assert permutation_pvalue(-y, y, n, seed=0) == pytest.approx(1.0)


def _synthetic(names: list[str], n_groups: int = 16, seed: int = 0, conds=("clean", "A", "B", "C")):
    """Models whose robustness falls with their index, with noise per group and a few swaps between
    estimator and ground truth; -> (GroupCounts, EstimatorCounts) per model, agreement arrays."""
    rng = np.random.default_rng(seed)
    C, M = len(conds), len(names)
    drop = np.linspace(0.1, 0.6, M)[:, None] * np.r_[0.0, np.linspace(0.5, 1.0, C - 1)][None]
    quality = 0.85 * (1 - drop)  # M x C: the same clean quality, robustness falling with the index
    groups, counts = [], []
    for m, name in enumerate(names):
        iou = np.clip(quality[m][None] + rng.normal(0, 0.08, (n_groups, C)), 0.05, 0.99)
        cm = np.zeros((n_groups, C, K, K), np.int64)
        for k in range(K):
            cm[:, :, k, k] = np.round(1000 * iou)
            cm[:, :, k, (k + 1) % K] = 1000 - np.round(1000 * iou)
        ref = rng.integers(100, 200, (n_groups, C, K))
        keep = np.clip(quality[m][None, :, None] + rng.normal(0, 0.1, (n_groups, C, 1)), 0, 1)
        ret = np.floor(ref * keep).astype(np.int64)
        pix = np.full((n_groups, C), 1000)
        conf = np.clip(quality[m][None] + rng.normal(0, 0.1, (n_groups, C)), 0.05, 0.99)
        hist = np.zeros((n_groups, C, B), np.int64)
        for g in range(n_groups):
            for c in range(C):
                hist[g, c] = np.bincount(np.clip((rng.normal(conf[g, c], 0.1, 1000) * B).astype(int), 0, B - 1),
                                         minlength=B)
        ids = tuple(f"{g:05d}" for g in range(n_groups))
        groups.append(GroupCounts(name, conds, ret, ref, ret, ref, cm, ids))
        counts.append(EstimatorCounts(name, conds, pix, pix * conf, pix * (1 - conf), hist,
                                      np.round(pix * keep[..., 0]).astype(np.int64), ids))
    share = 1 - np.abs(quality[:, None] - quality[None])  # M x M x C
    scored = np.full((n_groups, C, M, M), 1000)
    agree = np.round(scored * np.moveaxis(share, -1, 0)[None]).astype(np.int64)
    return groups, counts, agree, scored


def test_compare_excludes_the_reference_and_writes_every_scope():
    names = ["m0", "m1", "m2", "m3", "ref"]
    groups, counts, agree, scored = _synthetic(names)
    keep = [names.index(n) for n in ranked_models(names, {"ref"})]
    assert ranked_models(names, {"ref"}) == ["m0", "m1", "m2", "m3"]
    sub = np.ix_(range(agree.shape[0]), range(agree.shape[1]), keep, keep)
    cells, stats, _ = compare(groups, counts, agree[sub], scored[sub], "clean", np.ones(K, bool), reference={"ref"},
                           resamples=100, permutations=200)
    cells, stats = pd.DataFrame(cells), pd.DataFrame(stats)
    assert set(cells["model"]) == {"m0", "m1", "m2", "m3"} and len(cells) == 4 * 3
    assert set(cells.columns) >= {*ESTIMATORS, "atc_threshold", *TARGETS}
    # each estimator is judged over the models it is defined for: all four, or none where the synthetic sums
    # leave it undefined (no Grams or logits, clean agreements that do not vary, no twins for GDE)
    finite = cells.groupby("model")[list(ESTIMATORS)].apply(lambda d: np.isfinite(d).all()).sum()
    assert stats.groupby("estimator")["n_models"].unique().map(list).to_dict() == {e: [int(finite[e])] for e in ESTIMATORS}
    assert set(finite[finite == 4].index) >= {"xi", "ac", "atc", "self_agreement", "committee_agreement"}
    assert finite["gde"] == 0
    assert stats.loc[stats["estimator"] == "gde", "spearman"].isna().all()
    assert set(stats["scope"]) == {"A", "B", "C", "within_mean", "pooled", "loco"}
    assert len(stats) == len(ESTIMATORS) * len(TARGETS) * 6
    assert stats.set_index(["estimator", "target", "scope"]).loc[("doc", "rpc", "loco"), "uses_clean_labels"]
    # robustness falls with the index everywhere: the label-free xi ranks the four models as rPC does
    s = stats.set_index(["estimator", "target", "scope"])
    assert s.loc[("xi", "rpc", "within_mean"), "spearman"] > 0.5
    with pytest.raises(ValueError, match="3 ranked models"):
        compare(groups[1:], counts[1:], agree[sub][..., 1:, 1:], scored[sub][..., 1:, 1:], "clean",
                np.ones(K, bool), reference={"ref"})
    with pytest.raises(ValueError, match="pairwise agreement"):  # the reference must not be in the agreement
        compare(groups, counts, agree, scored, "clean", np.ones(K, bool), reference={"ref"}, resamples=10,
                permutations=10)


def test_resampling_models_gives_an_interval_where_the_scenes_cannot():
    """Every scene alike (group 0 copied): resampling scenes cannot move anything, so the interval that holds
    the zoo fixed is none (NaN, never a zero width), while the one that also draws the models still varies:
    it answers for models like these, not for these six alone."""
    import dataclasses

    names = [f"m{i}" for i in range(6)]
    groups, counts, agree, scored = _synthetic(names, n_groups=6, seed=3)
    same = lambda a: np.repeat(np.asarray(a)[:1], len(a), axis=0)  # noqa: E731
    groups = [dataclasses.replace(g, **{f: same(getattr(g, f)) for f in ("pl_retained", "pl_reference", "gt_retained",
                                                                        "gt_reference", "cm")}) for g in groups]
    counts = [dataclasses.replace(c, **{f: same(getattr(c, f)) for f in ("pixels", "conf_sum", "entropy_sum", "conf_hist",
                                                                        "agree_clean")}) for c in counts]
    agree, scored = same(agree), same(scored)
    _, stats, _ = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=300, permutations=50)
    s = pd.DataFrame(stats).set_index(["estimator", "target", "scope"])
    for e in ("xi", "ac", "clean_miou"):
        row = s.loc[(e, "rpc", "within_mean")]
        assert math.isnan(row["spearman_ci_low"]) and math.isnan(row["spearman_ci_high"])
        assert row["spearman_model_ci_low"] < row["spearman_model_ci_high"]
    idx, enough = model_draws(3, 2000, 0)
    assert idx.shape == (2000, 3) and 0.1 < enough.mean() < 0.5  # 3! / 27 of the draws hold all three


def _fake_pass(tmp_path: Path, names: list[str], reference: str):
    groups, counts, _, _ = _synthetic(names, n_groups=5, conds=("clean", "A", "B"))
    rng = np.random.default_rng(1)
    evaluations = []
    for g, c in zip(groups, counts):
        arrays = {"group_id": np.array(g.group_ids), "conditions": np.array(g.conditions),
                  "present": np.ones((5, 3), bool), "cm_present": np.ones((5, 3), bool), "cm": g.cm,
                  "pseudo_label_retained": g.pl_retained, "pseudo_label_reference": g.pl_reference,
                  "ground_truth_retained": g.gt_retained, "ground_truth_reference": g.gt_reference,
                  "est_pixels": c.pixels, "est_conf_sum": c.conf_sum, "est_entropy_sum": c.entropy_sum,
                  "est_conf_hist": c.conf_hist, "est_agree_clean": c.agree_clean,
                  "pseudo_label_predicted": g.pl_reference}  # errors spread evenly: as many predicted as referenced
        path = tmp_path / g.model
        if g.model != reference:  # the reference's predictions are never read
            preds = [rng.integers(0, 3, (3, 4, 6 + i)) for i in range(5)]  # sizes differ between groups
            _write_predictions(path, preds, ("clean", "A", "B"))
        evaluations.append(SimpleNamespace(model=g.model, path=path, group_counts=lambda a=arrays: a))
    return SimpleNamespace(label="fake", grid=SimpleNamespace(reference="clean"), evaluations=evaluations,
                           pseudo=SimpleNamespace(reference_model=lambda: reference))


def test_the_estimators_figure_writes_its_tables_and_metrics(tmp_path):
    from pairedgta.figures import FigureOptions
    from pairedgta.figures.estimators import draw

    names = ["demo_ddrnet", "demo_pidnet", "demo_segformer", "demo_segformer_noaug", "m4"]
    p = _fake_pass(tmp_path / "eval", names, "demo_segformer")
    out = tmp_path / "plot"
    out.mkdir()
    cfg = {"reference_model": "something_else", "metric": {
           "convention": "strict", "absent": "nan", "min_images": 0, "min_pixels": 0,  # no support rule on 4 groups
           "bootstrap": {"resamples": 40, "confidence": 0.9, "seed": 0}, "validity": {"permutations": 100}}}
    files, metrics = draw([p], out, FigureOptions(["png"], 40, schema.parse(cfg)))
    assert {f.name for f in files} == {"estimators.csv", "estimators.md", "estimator_cells.csv", "estimator_pairs.csv",
                                       "estimators.png"}
    cells = pd.read_csv(out / "estimator_cells.csv")
    assert "demo_segformer" not in set(cells["model"]) and len(cells) == 4 * 2  # the pass's reference is left out
    md = (out / "estimators.md").read_text()
    assert "pooled over conditions (mostly orders the conditions)" in md and "demo_segformer is excluded" in md
    assert "Intervals at 90%: the percentile bootstrap over scenes" in md and "BCa over scenes and models" in md
    assert "validity/xi/rpc/spearman/within_mean" in metrics and "validity/committee_agreement/gt_miou/mae/loco" in metrics
    assert "validity/atc/rpc/p_permutation/within_mean" in metrics and "validity/ac/rpc/kendall/A" in metrics
    assert "validity/xi_f/gt_miou/spearman/within_mean" in metrics and "validity/xi_precision/rpc/spearman/A" in metrics
    assert not any(k.endswith("/p_permutation/pooled") for k in metrics)
    assert all(k.count("/") == 4 and math.isfinite(v) for k, v in metrics.items())
    # the committee agreement from the predictions files is in the cells
    assert cells["committee_agreement"].between(0, 1).all()

    assert cells["gde"].isna().all() and "GDE" in md  # no twins configured: GDE undefined, its row says so
    # twins: GDE is their agreement with each other, from the same predictions files
    twin_cfg = {**cfg, "metric": {**cfg["metric"], "validity": {"permutations": 100,
                                                                 "twins": [["demo_ddrnet", "m4"], ["demo_pidnet", "demo_segformer_noaug"]]}}}
    draw([p], out, FigureOptions(["png"], 40, schema.parse(twin_cfg)))
    cells = pd.read_csv(out / "estimator_cells.csv").set_index(["model", "condition"])
    assert cells["gde"].between(0, 1).all()
    np.testing.assert_allclose(cells.loc["demo_ddrnet", "gde"].to_numpy(), cells.loc["m4", "gde"].to_numpy())
    stats = pd.read_csv(out / "estimators.csv").set_index(["estimator", "target", "scope"])
    assert stats.loc[("gde", "rpc", "within_mean"), "n_models"] == 4
    bad = {**cfg, "metric": {**cfg["metric"], "validity": {"permutations": 100, "twins": [["demo_ddrnet", "m5"]]}}}
    with pytest.raises(ConfigError, match=r"metric.validity.twins names m5, not among the ranked models"):
        draw([p], out, FigureOptions(["png"], 40, schema.parse(bad)))

    # a model evaluated before the estimator sums, or without predictions: one line naming the fix
    (tmp_path / "eval" / "m4" / "predictions.npz").unlink()
    with pytest.raises(ConfigError, match=r"predictions.npz.*force=\[evaluate\]"):
        draw([p], out, FigureOptions(["png"], 40, schema.parse(cfg)))
    old = dict(p.evaluations[0].group_counts())
    del old["est_conf_hist"]
    p.evaluations[0].group_counts = lambda: old
    with pytest.raises(ConfigError, match=r"est_conf_hist.*group_counts.npz.*force=\[evaluate\]"):
        draw([p], out, FigureOptions(["png"], 40, schema.parse(cfg)))
    # three models besides the reference: too few to rank
    p3 = _fake_pass(tmp_path / "eval3", names[1:], "demo_segformer")
    with pytest.raises(ConfigError, match="at least 4"):
        draw([p3], out, FigureOptions(["png"], 40, schema.parse(cfg)))


def test_one_reader_of_the_group_counts_serves_both_figures_and_xi_needs_no_estimator_sums(tmp_path):
    """metric_validity and estimators read the entries through one reader (the same checks, the same
    models); entries written without the est_* arrays still draw metric_validity, and estimators names
    the arrays it lacks."""
    from pairedgta.figures import FigureOptions
    from pairedgta.figures import estimators as estimators_figure
    from pairedgta.figures import validity as validity_figure

    names = ["demo_ddrnet", "demo_pidnet", "demo_segformer", "demo_segformer_noaug", "m4"]
    p = _fake_pass(tmp_path / "eval", names, "demo_segformer")
    groups, _, _ = estimators_figure.load([p])
    assert [g.model for g in groups] == [g.model for g in validity_figure.group_counts([p])] == sorted(names)
    for e in p.evaluations:
        e.group_counts = lambda a={k: v for k, v in e.group_counts().items() if not k.startswith("est_")}: a
    out = tmp_path / "plot"
    out.mkdir()
    cfg = {"reference_model": "demo_segformer", "metric": {
           "convention": "strict", "absent": "nan", "min_images": 0, "min_pixels": 0,  # no support rule on 4 groups
           "bootstrap": {"resamples": 20, "confidence": 0.9, "seed": 0}}}
    files, metrics = validity_figure.draw([p], out, FigureOptions(["png"], 40, schema.parse(cfg)))
    cells = pd.read_csv(out / "metric_validity_cells.csv")
    assert "demo_segformer" not in set(cells["model"]) and cells["model"].nunique() == 4 and metrics
    with pytest.raises(ConfigError, match=r"estimators needs est_pixels, .*group_counts.npz.*force=\[evaluate\]"):
        estimators_figure.draw([p], out, FigureOptions(["png"], 40, schema.parse(cfg)))
    p.evaluations[0].group_counts = lambda: {}  # an entry from before the group counts: both say so alike
    for name, figure in (("metric_validity", validity_figure), ("estimators", estimators_figure)):
        with pytest.raises(ConfigError, match=rf"{name} needs evaluate's group_counts.npz.*force=\[evaluate\]"):
            figure.draw([p], out, FigureOptions(["png"], 40, schema.parse(cfg)))


def test_the_difference_to_xi_is_paired_on_the_same_resamples():
    """Each estimator's within-condition mean Spearman minus xi's, with an interval from the same scene
    resamples; xi minus itself is 0 and gets no interval (a zero-width interval is no certainty)."""
    names = ["m0", "m1", "m2", "m3", "m4"]
    groups, counts, agree, scored = _synthetic(names, seed=5)
    _, stats, _ = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=200, permutations=20)
    s = pd.DataFrame(stats).set_index(["estimator", "target", "scope"])
    xi = s.loc[("xi", "rpc", "within_mean")]
    assert xi["spearman_minus_xi"] == 0.0 and math.isnan(xi["spearman_minus_xi_ci_low"])
    for e in ("ac", "self_agreement", "committee_agreement"):
        row = s.loc[(e, "rpc", "within_mean")]
        assert row["spearman_minus_xi"] == pytest.approx(row["spearman"] - xi["spearman"])
        if math.isfinite(row["spearman_minus_xi_ci_low"]):
            assert row["spearman_minus_xi_ci_low"] <= row["spearman_minus_xi_ci_high"]
    assert math.isnan(s.loc[("ac", "rpc", "pooled"), "spearman_minus_xi"])  # only the headline scope has it


def test_a_one_class_predictor_has_no_rpc_and_leaves_only_the_rpc_rows():
    """rPC below metric.validity.rpc_min_clean_miou is undefined (a one-class predictor would get 1.0): the
    model is left out of the rPC rows (n_models 4, n_undefined 1) and kept in the adverse GT mIoU rows."""
    import dataclasses

    names = ["m0", "m1", "m2", "m3", "flat"]
    groups, counts, agree, scored = _synthetic(names, n_groups=8)
    cm = np.zeros_like(groups[-1].cm)
    cm[:, :, :5, 0] = 200  # truth classes 0-4, everything predicted as 0: mIoU 0.04 under every condition
    groups[-1] = dataclasses.replace(groups[-1], cm=cm)
    cells, stats, _ = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=20, permutations=20,
                           rpc_floor=0.1)
    s = pd.DataFrame(stats).set_index(["estimator", "target", "scope"])
    assert (s.loc[("xi", "rpc", "within_mean"), "n_models"], s.loc[("xi", "rpc", "within_mean"), "n_undefined"]) == (4, 1)
    assert s.loc[("xi", "gt_miou", "within_mean"), "n_models"] == 5
    assert s.loc[("xi", "rpc", "A"), "n_cells"] == 4
    flat = pd.DataFrame(cells).query("model == 'flat'")
    assert flat["rpc"].isna().all() and np.allclose(flat["gt_miou"], 0.04)
    _, stats, _ = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=0, permutations=0)
    assert pd.DataFrame(stats).set_index(["estimator", "target", "scope"]).loc[("xi", "rpc", "within_mean"), "n_models"] == 5


def _agreement_arrays(clean_shares: dict, adverse_shares: dict, m: int = 3, n: int = 10 ** 6):
    """1 group, conditions clean and A: pair (i, j) agrees on the given share of n pixels."""
    scored = np.full((1, 2, m, m), n, np.int64)
    agree = np.zeros_like(scored)
    for c, shares in enumerate((clean_shares, adverse_shares)):
        for i in range(m):
            agree[0, c, i, i] = n
        for (i, j), v in shares.items():
            agree[0, c, i, j] = agree[0, c, j, i] = round(v * n)
    return agree, scored


def test_aline_s_and_d_by_hand():
    """Three models. On a line (probit agr_A = 0.8 probit agr_clean - 0.3 for every pair) ALine-S and ALine-D
    both carry each clean accuracy along it: Phi(0.8 probit acc - 0.3). Off the line, ALine-D solves the three
    pair equations exactly: with r_ij = probit agr_A + a ((probit acc_i + probit acc_j) / 2 - probit
    agr_clean), u_0 = r01 + r02 - r12, u_1 = r01 - r02 + r12, u_2 = -r01 + r02 + r12 (the inverse of the
    halves matrix), a the least-squares slope of the pairs."""
    from scipy.stats import norm

    from pairedgta.metrics.estimators import aline

    acc = np.array([[0.92], [0.85], [0.80]])                      # M x R clean pixel accuracy
    clean = {(0, 1): 0.90, (0, 2): 0.80, (1, 2): 0.85}
    on_line = {k: float(norm.cdf(0.8 * norm.ppf(v) - 0.3)) for k, v in clean.items()}
    agree, scored = _agreement_arrays(clean, on_line)
    s, d = aline(agree, scored, acc, 0, np.ones((1, 1)))
    want = norm.cdf(0.8 * norm.ppf(acc[:, 0]) - 0.3)
    np.testing.assert_allclose(s[:, 0, 1], want, atol=1e-5)
    np.testing.assert_allclose(d[:, 0, 1], want, atol=1e-5)
    np.testing.assert_allclose(s[:, 0, 0], acc[:, 0], atol=1e-5)  # the clean condition: its own line, y = x

    off = {(0, 1): 0.70, (0, 2): 0.50, (1, 2): 0.66}
    agree, scored = _agreement_arrays(clean, off)
    s, d = aline(agree, scored, acc, 0, np.ones((1, 1)))
    pairs = [(0, 1), (0, 2), (1, 2)]
    x = np.array([norm.ppf(clean[p]) for p in pairs])
    y = np.array([norm.ppf(off[p]) for p in pairs])
    a, b = np.polyfit(x, y, 1)
    np.testing.assert_allclose(s[:, 0, 1], norm.cdf(a * norm.ppf(acc[:, 0]) + b), atol=1e-5)
    pa = norm.ppf(acc[:, 0])
    r = {p: norm.ppf(off[p]) + a * ((pa[p[0]] + pa[p[1]]) / 2 - norm.ppf(clean[p])) for p in pairs}
    u = [r[0, 1] + r[0, 2] - r[1, 2], r[0, 1] - r[0, 2] + r[1, 2], -r[0, 1] + r[0, 2] + r[1, 2]]
    np.testing.assert_allclose(d[:, 0, 1], norm.cdf(u), atol=1e-5)
    # every pair agreeing alike on the clean image: no line to fit, no estimate
    flat = {k: 0.9 for k in clean}
    agree, scored = _agreement_arrays(flat, off)
    s, d = aline(agree, scored, acc, 0, np.ones((1, 1)))
    assert np.isnan(s[:, 0, 1]).all() and np.isnan(d[:, 0, 1]).all()
