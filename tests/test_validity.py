"""The label-free metric checked against ground truth (pairedgta/metrics/validity.py, experiment metric_validity)."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import kendalltau, spearmanr

from pairedgta.app import run
from pairedgta.errors import ConfigError
from pairedgta.metrics import ConfusionMatrix
from pairedgta.metrics.validity import GroupCounts, kendall_rows, miou, spearman_rows, validity
from pairedgta.testing.cli import compose_cfg, fast_overrides

K = 19


def test_rank_correlations_match_scipy_with_ties_and_say_nan_when_undefined():
    rng = np.random.default_rng(0)
    for n in (3, 4, 7, 12):
        x = rng.integers(0, 4, size=(20, n)).astype(float)  # many ties
        y = rng.integers(0, 4, size=(20, n)).astype(float)
        for r in range(20):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # scipy warns on a constant row, where both say NaN
                want_s = spearmanr(x[r], y[r]).statistic
                want_k = kendalltau(x[r], y[r]).statistic
            np.testing.assert_allclose(spearman_rows(x[r], y[r])[0], want_s, equal_nan=True)
            np.testing.assert_allclose(kendall_rows(x[r], y[r])[0], want_k, equal_nan=True)
    assert np.isnan(spearman_rows([1, 1, 1], [1, 2, 3])[0]) and np.isnan(kendall_rows([1, np.nan, 2], [1, 2, 3])[0])


def test_miou_is_the_cityscapes_mean_of_the_confusion_matrix():
    rng = np.random.default_rng(1)
    for _ in range(5):
        mat = rng.integers(0, 50, size=(K, K)) * (rng.random((K, K)) < 0.3)
        cm = ConfusionMatrix(K)
        cm.update_counts(mat)
        assert miou(mat) == pytest.approx(cm.miou())


def _counts(model: str, keep: list[float], iou: list[float], n: int = 10, seed: int = 0) -> GroupCounts:
    """n groups, conditions [clean, A, B]: under condition i the model keeps keep[i] of each class's
    reference pixels and its confusion matrices give IoU iou[i] for every class (noise per group)."""
    rng = np.random.default_rng(seed)
    conds = ("clean", "A", "B")
    ref = rng.integers(100, 200, size=(n, 3, K))
    ret = np.stack([np.floor(ref[:, i] * keep[i]) for i in range(3)], axis=1).astype(np.int64)
    cm = np.zeros((n, 3, K, K), dtype=np.int64)
    for i in range(3):
        tp = np.round(1000 * iou[i]).astype(int)
        for k in range(K):
            cm[:, i, k, k] = tp
            cm[:, i, k, (k + 1) % K] = 1000 - tp  # each class loses (1 - iou) to its neighbour
    return GroupCounts(model, conds, ret, ref, ret, ref, cm)


def test_validity_finds_the_known_order_and_its_reversal():
    include = np.ones(K, bool)
    # three models: xi and rPC in the same order under both adverse conditions
    agree = [_counts("a", [1, .9, .8], [.8, .7, .6], seed=1), _counts("b", [1, .7, .5], [.8, .5, .4], seed=2),
             _counts("c", [1, .4, .3], [.8, .3, .2], seed=3)]
    cells, corr = validity(agree, "clean", include, resamples=200)
    c = pd.DataFrame(corr).set_index(["scope", "target"])
    assert c.loc[("A", "rpc"), "spearman"] == pytest.approx(1.0) and c.loc[("pooled", "rpc"), "kendall"] == pytest.approx(1.0)
    cell = pd.DataFrame(cells).set_index(["model", "condition"])
    assert cell.loc[("a", "A"), "xi_mean"] == pytest.approx(0.9, abs=0.01)
    assert cell.loc[("b", "B"), "rpc"] == pytest.approx((0.4 / 1.6) / (0.8 / 1.2))  # IoU = t / (2 - t) here
    # every model degrades alike per group: the bootstrap of a perfect ranking cannot vary -> no interval
    assert np.isnan(c.loc[("A", "rpc"), "spearman_ci_low"])
    # reversed: the model that keeps most of the pseudo-labels loses most against ground truth
    flip = [_counts("a", [1, .9, .8], [.8, .3, .2], seed=1), _counts("b", [1, .7, .5], [.8, .5, .4], seed=2),
            _counts("c", [1, .4, .3], [.8, .7, .6], seed=3)]
    _, corr = validity(flip, "clean", include, resamples=50)
    c = pd.DataFrame(corr).set_index(["scope", "target"])
    assert c.loc[("B", "rpc"), "spearman"] == pytest.approx(-1.0) and c.loc[("B", "rpc"), "kendall"] == pytest.approx(-1.0)


def test_validity_refuses_models_evaluated_on_other_groups():
    include = np.ones(K, bool)
    with pytest.raises(ValueError, match="other groups"):
        validity([_counts("a", [1, .9, .8], [.8, .7, .6]), _counts("b", [1, .9, .8], [.8, .7, .6], n=5)], "clean", include)


def test_validity_checks_the_group_ids_not_only_their_number():
    import dataclasses

    include = np.ones(K, bool)
    a = dataclasses.replace(_counts("a", [1, .9, .8], [.8, .7, .6]), group_ids=tuple(f"{g:05d}" for g in range(10)))
    b = dataclasses.replace(_counts("b", [1, .7, .5], [.8, .5, .4]), group_ids=tuple(f"{g:05d}" for g in range(1, 11)))
    with pytest.raises(ValueError, match="group '00001' where a has '00000'"):
        validity([a, b], "clean", include, resamples=20)
    validity([a, dataclasses.replace(b, group_ids=a.group_ids)], "clean", include, resamples=20)  # same groups: fine


@pytest.mark.slow
def test_metric_validity_from_the_pipeline_agrees_with_each_models_own_evaluation(tmp_path):
    """Point estimates of the validity table are the evaluate stage's own numbers, per model and condition."""
    base = fast_overrides(tmp_path) + ["models=[tiny_segformer,tiny_ddrnet,tiny_pidnet,tiny_deeplabv3plus]",
                                       "generate.num_scenes=4", "plot.figures=[metric_validity,xi_models]"]
    summary = run(compose_cfg(base))
    out = tmp_path / "cache" / "plot"
    plot_dir = next(p for p in out.iterdir() if (p / "metric_validity.csv").is_file())
    cells = pd.read_csv(plot_dir / "metric_validity_cells.csv")
    corr = pd.read_csv(plot_dir / "metric_validity.csv")
    # the reference model (tiny_segformer, the pseudo-label source) is evaluated but not ranked
    assert set(cells["model"]) == {"tiny_ddrnet", "tiny_pidnet", "tiny_deeplabv3plus"}
    assert set(corr["scope"]) == {"Day-RAIN", "Night-EXTRASUNNY", "pooled"} and (corr["n_groups"] == 4).all()
    for model, path in summary["evaluate"].items():
        s = json.loads((Path(path) / "summary.json").read_text())
        for row in cells[cells["model"] == model].itertuples():
            assert row.xi_mean == pytest.approx(s["xi_mean"][row.condition], nan_ok=True)
            assert row.gt_miou == pytest.approx(s["gt_miou"][row.condition], nan_ok=True)
            assert row.gt_miou_clean == pytest.approx(s["gt_miou"]["Day-EXTRASUNNY"], nan_ok=True)
    metrics = json.loads((plot_dir / "metrics.json").read_text())
    assert any(k.startswith("validity/rpc/spearman/") for k in metrics) or corr["spearman"].isna().all()
    assert "compare/xi_mean/Day-RAIN/tiny_ddrnet" in metrics
    assert (plot_dir / "metric_validity.png").is_file() and (plot_dir / "xi_models.png").is_file()

    with pytest.raises(ConfigError, match="at least 3"):
        run(compose_cfg(base[:-2] + ["models=[tiny_segformer,tiny_ddrnet,tiny_pidnet]", "plot.figures=[metric_validity]"]))
