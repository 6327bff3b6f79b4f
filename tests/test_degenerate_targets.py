"""Degenerate targets and thin evidence (issue 49, item 5): rPC is undefined below a clean-mIoU floor, so a
one-class predictor is not the most robust model; a rho_valid over a few frames is no headline, and every
table says how many frames each value rests on."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pairedgta.errors import ConfigError
from pairedgta.metrics.conventions import convention_from_config
from pairedgta.metrics.ranking import rho_rows
from pairedgta.metrics.validity import GroupCounts, cell_measures, validity

K = 19
CONDS = ("clean", "A", "B")


def _one_class(n: int = 4) -> GroupCounts:
    """Truth: classes 0-4, 200 pixels each, under every condition; the model predicts class 0 everywhere.
    IoU(0) = 200 / 1000, IoU(1..4) = 0: mIoU 0.04 clean and adverse alike, so rPC would be 1.0. Of the
    reference's pseudo-labels (every class) it keeps class 0's only: mean xi 1/19."""
    cm = np.zeros((n, 3, K, K), np.int64)
    cm[:, :, :5, 0] = 200
    ref = np.full((n, 3, K), 100)
    ret = np.zeros_like(ref)
    ret[..., 0] = 100
    return GroupCounts("one_class", CONDS, ret, ref, ret, ref, cm)


def _model(name: str, iou: list[float], keep: list[float], n: int = 4, seed: int = 0) -> GroupCounts:
    """Every class at IoU iou[i] under condition i (it loses 1 - iou to its neighbour); keeps keep[i] of the
    pseudo-labels."""
    rng = np.random.default_rng(seed)
    cm = np.zeros((n, 3, K, K), np.int64)
    for i in range(3):
        tp = np.round(1000 * np.clip(iou[i] + rng.normal(0, 0.01, n), 0, 1)).astype(int)
        for k in range(K):
            cm[:, i, k, k] = tp
            cm[:, i, k, (k + 1) % K] = 1000 - tp
    ref = rng.integers(100, 200, (n, 3, K))
    ret = np.stack([np.floor(ref[:, i] * keep[i]) for i in range(3)], axis=1).astype(np.int64)
    return GroupCounts(name, CONDS, ret, ref, ret, ref, cm)


def test_rpc_of_a_one_class_predictor_is_undefined_below_the_floor():
    g = _one_class()
    include = np.ones(K, bool)
    plain = cell_measures(g, np.ones((1, 4)), "clean", include, "nan")
    np.testing.assert_allclose(plain["gt_miou"][0], [0.04, 0.04, 0.04])
    np.testing.assert_allclose(plain["rpc"][0], [1.0, 1.0, 1.0])  # "perfectly robust" without a floor
    floored = cell_measures(g, np.ones((1, 4)), "clean", include, "nan", rpc_floor=0.1)
    assert np.isnan(floored["rpc"]).all()
    np.testing.assert_allclose(floored["gt_miou"][0], [0.04, 0.04, 0.04])  # the absolute target stays
    # a model at the floor keeps its rPC: undefined strictly below
    at = cell_measures(_model("m", [0.1, 0.05, 0.05], [1, 1, 1]), np.ones((1, 4)), "clean", include, "nan", rpc_floor=0.05)
    assert np.isfinite(at["rpc"]).all()


def test_the_one_class_predictor_leaves_the_rpc_correlations_not_the_absolute_ones():
    """Three real models whose xi and rPC agree in order, plus the one-class predictor (the lowest xi).
    Without a floor its rPC of 1.0 is the best and breaks the order (Spearman -0.2 by hand: ranks 4,3,2,1
    against 3,2,1,4); with the floor it is left out of the rPC rows and stays in the GT mIoU rows."""
    models = [_model("a", [0.8, 0.7, 0.6], [1, 0.9, 0.8], seed=1), _model("b", [0.8, 0.5, 0.4], [1, 0.7, 0.5], seed=2),
              _model("c", [0.8, 0.3, 0.2], [1, 0.4, 0.3], seed=3), _one_class()]
    include = np.ones(K, bool)
    _, corr = validity(models, "clean", include, resamples=0, rpc_floor=0.1)
    c = pd.DataFrame(corr).set_index(["scope", "target"])
    assert c.loc[("A", "rpc"), "n_models"] == 3 and c.loc[("A", "rpc"), "n_undefined"] == 1
    assert c.loc[("A", "rpc"), "spearman"] == pytest.approx(1.0)
    assert c.loc[("A", "gt_miou"), "n_models"] == 4 and c.loc[("A", "gt_miou"), "n_undefined"] == 0
    cells, corr = validity(models, "clean", include, resamples=0)
    c = pd.DataFrame(corr).set_index(["scope", "target"])
    assert c.loc[("A", "rpc"), "n_models"] == 4 and c.loc[("A", "rpc"), "spearman"] == pytest.approx(-0.2)
    one = pd.DataFrame(cells).set_index(["model", "condition"]).loc[("one_class", "A")]
    assert one["rpc"] == pytest.approx(1.0)


def test_the_floor_and_the_frame_minimum_come_from_the_config():
    conv = convention_from_config({"rho": {"min_frames": 12}, "validity": {"rpc_min_clean_miou": 0.2}})
    assert (conv.rho_min_frames, conv.rpc_min_clean_miou) == (12, 0.2)
    assert convention_from_config({}).rho_min_frames == 0  # an old config: no minimum
    for metric, key in (({"rho": {"min_frames": -1}}, "min_frames"), ({"validity": {"rpc_min_clean_miou": 1.5}}, "rpc_min")):
        with pytest.raises(ConfigError, match=key):
            convention_from_config(metric)
    from pairedgta import schema

    run = schema.parse({})
    assert run.metric.rho.min_frames == 10 and run.metric.validity.rpc_min_clean_miou == 0.1


def test_a_rho_valid_over_too_few_frames_is_no_headline_but_keeps_its_n_frames():
    # two frames with the class: Spearman -1 by construction, two frames cannot say more
    clean, adverse = np.array([0, 5, 0, 9, 0]), np.array([3, 8, 1, 2, 0])
    rows = {r["selection"]: r for r in rho_rows(clean, adverse, ["nonzero", "top_m"], resamples=0, headline="nonzero",
                                                  min_frames=10)}
    assert rows["nonzero"]["rho"] == pytest.approx(-1.0) and rows["nonzero"]["n_frames"] == 2
    assert not rows["nonzero"]["headline"] and rows["nonzero"]["min_frames"] == 10
    rng = np.random.default_rng(0)
    clean, adverse = rng.integers(1, 100, 12), rng.integers(0, 100, 12)
    rows = {r["selection"]: r for r in rho_rows(clean, adverse, ["nonzero", "top_m"], resamples=0, headline="nonzero",
                                                  min_frames=10)}
    assert rows["nonzero"]["headline"] and rows["nonzero"]["n_frames"] == 12 and not rows["top_m"]["headline"]


def test_every_rho_table_shows_n_frames(tmp_path):
    from pairedgta.figures.ranking import RankingInput, rho_table

    rho = pd.DataFrame([
        {"model": "m", "class_name": "car", "condition": "Night-EXTRASUNNY", "selection": "nonzero", "rho": 0.8,
         "n_frames": 40, "min_frames": 10},
        {"model": "m", "class_name": "person", "condition": "Night-EXTRASUNNY", "selection": "nonzero", "rho": 1.0,
         "n_frames": 2, "min_frames": 10}])
    rho_table([RankingInput("d", "Night-EXTRASUNNY", pd.DataFrame(), rho)], ["car", "person"], tmp_path)
    md = (tmp_path / "rho_valid.md").read_text()
    assert "| 0.800 (n=40) | 1.000 (n=2\u2021) |" in md and "\u2021 fewer than metric.rho.min_frames" in md
    assert list(pd.read_csv(tmp_path / "rho_valid.csv")["n_frames"]) == [40, 2]
