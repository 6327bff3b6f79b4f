"""GDE (Jiang et al.): the agreement of a model with its twin, a second run of the same recipe. By hand on
agreement counts, the twin pairs of the config checked, and judged over the twins only in the study, with its
difference to xi paired on the same models."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pairedgta.metrics.estimator_study import compare, within_condition
from pairedgta.metrics.estimators import gde, twin_indices
from pairedgta.metrics.validity import spearman_rows
from tests.test_estimators import K, _synthetic


def test_gde_is_the_pooled_agreement_share_with_the_twin():
    # 2 groups, 2 conditions, 3 models; model 0 and 2 are twins, model 1 has none
    agree = np.zeros((2, 2, 3, 3), np.int64)
    scored = np.full((2, 2, 3, 3), 100)
    agree[:, :, 0, 2] = agree[:, :, 2, 0] = [[90, 60], [70, 20]]   # group 0: 90 and 60 of 100; group 1: 70, 20
    agree[:, :, 0, 1] = agree[:, :, 1, 0] = 99
    out = gde(agree, scored, np.ones((1, 2)), [2, -1, 0])          # M x R x C
    np.testing.assert_allclose(out[0, 0], [(90 + 70) / 200, (60 + 20) / 200])
    np.testing.assert_allclose(out[2], out[0])
    assert np.isnan(out[1]).all()
    # a group weight of 2 on group 1 (a bootstrap draw): pooled counts, not a mean of shares
    np.testing.assert_allclose(gde(agree, scored, np.array([[1.0, 2.0]]), [2, -1, 0])[0, 0],
                               [(90 + 140) / 300, (60 + 40) / 300])


def test_twin_pairs_are_checked():
    names = ["a", "b", "c", "d"]
    np.testing.assert_array_equal(twin_indices(names, [["a", "c"], ["b", "x"]]), [2, -1, 0, -1])  # x not ranked
    with pytest.raises(ValueError, match="in two pairs"):
        twin_indices(names, [["a", "c"], ["c", "d"]])
    with pytest.raises(ValueError, match="not a pair"):
        twin_indices(names, [["a", "b", "c"]])
    with pytest.raises(ValueError, match="not a pair"):
        twin_indices(names, [["a", "a"]])


def test_gde_is_judged_over_the_twins_and_differs_from_xi_on_the_same_models():
    names = ["m0", "m1", "m2", "m3", "m4", "m5"]
    groups, counts, agree, scored = _synthetic(names)
    twins = [["m0", "m1"], ["m2", "m5"]]   # their agreement falls with the gap in quality: two GDE values
    cells, stats, pairs = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=60,
                                  permutations=100, twins=twins)
    cells, stats, pairs = pd.DataFrame(cells), pd.DataFrame(stats), pd.DataFrame(pairs)
    assert cells.loc[cells["model"].isin(["m3", "m4"]), "gde"].isna().all()
    twin_cells = cells[cells["model"].isin(["m0", "m1", "m2", "m5"])]
    assert twin_cells["gde"].notna().all()
    # m0 and m1 agree on the same share (the agreement is symmetric)
    a = cells.set_index(["model", "condition"])["gde"]
    np.testing.assert_allclose(a.loc["m0"].to_numpy(), a.loc["m1"].to_numpy())
    s = stats.set_index(["estimator", "target", "scope"])
    row = s.loc[("gde", "rpc", "within_mean")]
    assert row["n_models"] == 4 and row["n_undefined"] == 2
    # its Spearman and xi's over the same four models, by hand from the cells
    def mean_spearman(e: str, target: str = "rpc") -> float:
        pivot = lambda col: twin_cells.pivot(index="model", columns="condition", values=col).to_numpy()  # noqa: E731
        return float(np.mean(within_condition(pivot(e)[:, None], pivot(target)[:, None], spearman_rows)[0]))
    assert row["spearman"] == pytest.approx(mean_spearman("gde"))
    assert row["spearman_minus_xi"] == pytest.approx(mean_spearman("gde") - mean_spearman("xi"))
    assert np.isfinite(row["spearman_minus_xi_ci_low"]) or row["spearman_minus_xi"] == 0
    # xi itself is still judged over all six models
    assert s.loc[("xi", "rpc", "within_mean"), "n_models"] == 6
    pair = pairs[(pairs["target"] == "rpc") & (pairs["estimator_a"] == "xi") & (pairs["estimator_b"] == "gde")].iloc[0]
    assert pair["n_models"] == 4 and pair["difference"] == pytest.approx(-row["spearman_minus_xi"])
