"""The statistics that judge the label-free estimators (pairedgta/metrics/estimators.py): the permutation
test under the joint null, and what issue 49 asks of the comparison. Simulations with fixed seeds and
hand computations; each test runs in seconds."""
from __future__ import annotations

import numpy as np
import pytest

from pairedgta.metrics.estimator_study import permutation_pvalue
from pairedgta.metrics.validity import spearman_rows


def _per_condition_pvalue(x: np.ndarray, y: np.ndarray, permutations: int, rng: np.random.Generator) -> float:
    """The test this module replaced: each condition's models shuffled on their own."""
    observed = spearman_rows(x, y).mean()
    n_cond, n_models = x.shape
    order = np.argsort(rng.random((permutations, n_cond, n_models)), -1)
    xp = np.take_along_axis(np.broadcast_to(x, (permutations, n_cond, n_models)), order, -1)
    yp = np.broadcast_to(y, (permutations, n_cond, n_models))
    means = spearman_rows(xp.reshape(-1, n_models), yp.reshape(-1, n_models)).reshape(permutations, n_cond).mean(1)
    return (1 + (means >= observed - 1e-12).sum()) / (1 + permutations)


def test_the_permutation_test_holds_its_level_under_shared_model_effects_and_no_association():
    """11 models under 8 conditions; each model has its own level of the target and, independently, of the
    estimator, shared by every condition (the zoo's situation), plus a little noise per condition: no
    association. Permuting the model labels once for all conditions rejects at about the nominal 5 %;
    shuffling each condition on its own (the old test) rejects several times as often."""
    rng = np.random.default_rng(49)
    sims, n_models, n_cond, permutations = 400, 11, 8, 99
    joint, separate = [], []
    for s in range(sims):
        a, b = rng.normal(size=n_models), rng.normal(size=n_models)
        y = a + 0.3 * rng.normal(size=(n_cond, n_models))
        x = b + 0.3 * rng.normal(size=(n_cond, n_models))
        joint.append(permutation_pvalue(x, y, permutations, seed=s))
        separate.append(_per_condition_pvalue(x, y, permutations, rng))
    joint_rate, separate_rate = np.mean(np.array(joint) <= 0.05), np.mean(np.array(separate) <= 0.05)
    assert joint_rate <= 0.07
    assert separate_rate >= 0.15  # the inflation the joint null removes (23 % in the simulation)


def test_the_joint_permutation_test_is_exact_for_a_few_models():
    """4 models, 2 conditions: all 24 orders enumerated by hand. x = y in both conditions: only the identity
    reaches a mean Spearman of 1, p = 1/24. x reversed in one condition and equal in the other: the observed
    mean is 0; an order reaches >= 0 exactly where its Spearman with condition 0 is >= minus that with
    condition 1, counted here from the 24 orders."""
    import itertools

    y = np.array([[1.0, 2, 3, 4], [4.0, 1, 3, 2]])
    assert permutation_pvalue(y.copy(), y, 24) == pytest.approx(1 / 24)
    x = np.stack([y[0][::-1], y[1]])
    hits = sum(spearman_rows(x[:, list(o)], y).mean() >= -1e-12 for o in itertools.permutations(range(4)))
    assert permutation_pvalue(x, y, 1000) == pytest.approx(hits / 24)
    assert permutation_pvalue(x, y, 0) != permutation_pvalue(x, y, 0)  # no permutations: NaN


def test_holm_by_hand():
    from pairedgta.metrics.inference import holm

    # sorted 0.005, 0.01, 0.03, 0.04 of m = 4: x4 = 0.02, x3 = 0.03, x2 = 0.06, x1 = 0.04 -> monotone 0.06
    got = holm([0.01, 0.04, 0.03, np.nan, 0.005])
    np.testing.assert_allclose(got, [0.03, 0.06, 0.06, np.nan, 0.02], equal_nan=True)
    assert np.isnan(holm([np.nan, np.nan])).all() and holm([0.6, 0.7]).tolist() == [1.0, 1.0]


def test_bca_reduces_to_the_percentile_interval_and_its_p_value_by_hand():
    """Resamples -0.50, -0.49, ..., 1.49 (200 values), point 0.495: half the resamples lie below it, so
    z0 = 0; no jackknife, a = 0: the interval is the percentile one and the p-value of H0: 0 is twice the
    share below 0 (50 values, and 0 itself counted half): 2 x 50.5 / 200 = 0.505."""
    from pairedgta.metrics.inference import bca_interval, bca_pvalue

    boot = np.arange(-50, 150) / 100
    lo, hi = bca_interval(boot, 0.495, (), 0.9)
    assert (lo, hi) == pytest.approx((np.quantile(boot, 0.05), np.quantile(boot, 0.95)))
    assert bca_pvalue(boot, 0.495) == pytest.approx(0.505)
    assert bca_pvalue(boot, 0.495, null=-2.0) == pytest.approx(2 * 0.5 / 200)  # beyond every resample: the floor
    # no variation, too few defined resamples or an undefined point: no interval, no p
    assert np.isnan(bca_interval(np.zeros(50), 0.0)).all() and np.isnan(bca_pvalue(np.zeros(50), 0.0))
    assert np.isnan(bca_interval(np.r_[boot[:10], np.full(190, np.nan)], 0.0)).all()
    assert np.isnan(bca_interval(boot, np.nan)).all()


def test_the_acceleration_by_hand():
    from pairedgta.metrics.inference import acceleration

    jk = np.array([1.0, 2.0, 4.0])   # mean 7/3; d = mean - jk = 4/3, 1/3, -5/3
    d = 7 / 3 - jk
    assert acceleration([jk]) == pytest.approx(np.sum(d ** 3) / (6 * np.sum(d ** 2) ** 1.5))
    # two units: U = (n - 1) d per unit, weighted by 1/n^3 and 1/n^2
    jk2 = np.array([0.0, 1.0])
    u1, u2 = 2 * d, 1 * (0.5 - jk2)
    want = (np.sum(u1 ** 3) / 27 + np.sum(u2 ** 3) / 8) / (6 * (np.sum(u1 ** 2) / 9 + np.sum(u2 ** 2) / 4) ** 1.5)
    assert acceleration([jk, jk2]) == pytest.approx(want)
    assert acceleration([np.ones(5)]) == 0.0 and acceleration([np.array([np.nan, 1.0])]) == 0.0


def test_bca_agrees_with_scipy_on_a_skewed_statistic():
    """The variance of 40 exponential draws: BCa from 20,000 resamples here and in scipy.stats.bootstrap
    (its own resamples) agree to within a few percent of the interval's width."""
    from scipy.stats import bootstrap

    from pairedgta.metrics.inference import bca_interval

    rng = np.random.default_rng(7)
    x = rng.exponential(size=40)
    idx = rng.integers(0, 40, size=(20000, 40))
    boot = x[idx].var(axis=1, ddof=1)
    jk = np.array([np.delete(x, i).var(ddof=1) for i in range(40)])
    lo, hi = bca_interval(boot, float(x.var(ddof=1)), [jk], 0.95)
    ref = bootstrap((x,), lambda s, axis=-1: np.var(s, ddof=1, axis=axis), n_resamples=20000, method="BCa",
                    confidence_level=0.95, random_state=1).confidence_interval
    width = ref.high - ref.low
    assert abs(lo - ref.low) < 0.05 * width and abs(hi - ref.high) < 0.05 * width
    # the percentile interval sits lower: BCa moves it toward the skew
    assert hi > np.quantile(boot, 0.975)


def test_differences_are_paired_on_the_same_scene_and_model_draws():
    """AC and 1 - entropy are the same numbers in this synthetic zoo (entropy sums = pixels - confidence sums):
    drawn together, their difference is 0 on every resample, so it has no interval and no p (a zero width
    would be a certainty). Any difference from independent draws would vary. The Holm columns adjust the
    family of one target: p_holm >= p, and equal to Holm of the family's raw p."""
    import sys
    from pathlib import Path

    import pandas as pd

    sys.path.insert(0, str(Path(__file__).parent))
    from test_estimators import K, _synthetic

    from pairedgta.metrics.estimators import ESTIMATORS
    from pairedgta.metrics.estimator_study import compare
    from pairedgta.metrics.inference import holm

    groups, counts, agree, scored = _synthetic([f"m{i}" for i in range(6)], n_groups=10, seed=11)
    _, stats, pairs = compare(groups, counts, agree, scored, "clean", np.ones(K, bool), resamples=200, permutations=100)
    pairs = pd.DataFrame(pairs).set_index(["target", "estimator_a", "estimator_b"])
    same = pairs.loc[("rpc", "ac", "entropy")]
    assert same["difference"] == 0 and np.isnan(same["ci_low"]) and np.isnan(same["p"])
    assert len(pairs) == 2 * len(ESTIMATORS) * (len(ESTIMATORS) - 1) // 2
    for t in ("rpc", "gt_miou"):
        part = pairs.loc[t]
        np.testing.assert_allclose(part["p_holm"], holm(part["p"]), equal_nan=True)
        s = pd.DataFrame(stats).query("scope == 'within_mean' and target == @t").set_index("estimator")
        np.testing.assert_allclose(s["p_minus_xi_holm"], holm(s["p_minus_xi"]), equal_nan=True)
        np.testing.assert_allclose(s["p_permutation_holm"], holm(s["p_permutation"]), equal_nan=True)
        assert (s["p_permutation_holm"].dropna() >= s["p_permutation"].dropna() - 1e-12).all()
        # the difference to xi is the same number as xi's pair row, with the sign of estimator - xi
        for e in ESTIMATORS[1:]:
            assert s.loc[e, "spearman_minus_xi"] == pytest.approx(-part.loc[("xi", e), "difference"], nan_ok=True)
            assert s.loc[e, "p_minus_xi"] == pytest.approx(part.loc[("xi", e), "p"], nan_ok=True)


PAPER_ADVERSE = ["Day-RAIN", "Day-FOGGY", "Sunset-EXTRASUNNY", "Sunset-RAIN", "Sunset-FOGGY", "Night-EXTRASUNNY",
                 "Night-RAIN", "Night-FOGGY"]


def test_illumination_folds_of_the_paper_grid():
    from pairedgta.metrics.estimator_study import illumination_folds

    assert illumination_folds(PAPER_ADVERSE) == {"Day": [0, 1], "Sunset": [2, 3, 4], "Night": [5, 6, 7]}
    assert illumination_folds(["fog_0.5", "fog_1.0"]) == {}          # a ladder: no time of day
    assert illumination_folds(["Night-RAIN", "Night-FOGGY"]) == {}   # one illumination: nothing to leave out


def test_leaving_an_illumination_out_removes_the_sibling_conditions_from_the_fit():
    """y = x under Day and Sunset, y = x - 0.5 at night. Left out with its sibling night conditions, night is
    predicted from the day/sunset line y = x: an error of exactly 0.5 on every night cell. Leaving one
    night condition out keeps its siblings in the fit, which pulls the line toward them: a smaller error."""
    from pairedgta.metrics.estimator_study import holdout_mae, illumination_folds, loco_mae

    rng = np.random.default_rng(0)
    x = rng.random((5, 8))
    night = np.array([c.startswith("Night") for c in PAPER_ADVERSE])
    y = x - 0.5 * night
    folds = list(illumination_folds(PAPER_ADVERSE).values())
    out = holdout_mae(x[None], y[None], folds)
    assert out["per_fold"][0, 2] == pytest.approx(0.5)
    loco = loco_mae(x, y)
    assert np.nanmean(loco["per_condition"][night]) < 0.5 and out["mae"][0] > loco["mae"]
    # the vectorised fit is the same as one least-squares fit per resample
    xs, ys = rng.random((3, 4, 8)), rng.random((3, 4, 8))
    got = holdout_mae(xs, ys, folds)
    for r in range(3):
        train = [i for i in range(8) if i not in folds[0]]
        b, a = np.polyfit(xs[r][:, train].ravel(), ys[r][:, train].ravel(), 1)
        want = np.abs(a + b * xs[r][:, folds[0]] - ys[r][:, folds[0]]).mean()
        assert got["per_fold"][r, 0] == pytest.approx(want)


def test_loco_and_loio_maes_come_with_intervals():
    import sys
    from pathlib import Path

    import pandas as pd

    sys.path.insert(0, str(Path(__file__).parent))
    from test_estimators import K, _synthetic

    from pairedgta.metrics.estimator_study import compare

    conds = ("Day-EXTRASUNNY", "Day-RAIN", "Sunset-EXTRASUNNY", "Sunset-RAIN", "Night-EXTRASUNNY", "Night-RAIN")
    groups, counts, agree, scored = _synthetic([f"m{i}" for i in range(6)], n_groups=10, seed=2, conds=conds)
    _, stats, _ = compare(groups, counts, agree, scored, "Day-EXTRASUNNY", np.ones(K, bool), resamples=200,
                          permutations=20)
    s = pd.DataFrame(stats).set_index(["estimator", "target", "scope"])
    assert {"loco", "loio", "loio_Day", "loio_Sunset", "loio_Night"} <= set(s.index.get_level_values("scope"))
    for scope in ("loco", "loio", "loio_Night", "Night-RAIN"):
        row = s.loc[("xi", "rpc", scope)]
        assert row["mae_ci_low"] < row["mae_ci_high"] and row["mae_baseline_ci_low"] < row["mae_baseline_ci_high"]
    assert s.loc[("xi", "rpc", "loio_Day"), "n_conditions"] == 1 and s.loc[("xi", "rpc", "loio_Night"), "n_conditions"] == 2
