"""The statistics that judge the label-free estimators (pairedgta/metrics/estimators.py): the permutation
test under the joint null, and what issue 49 asks of the comparison. Simulations with fixed seeds and
hand computations; each test runs in seconds."""
from __future__ import annotations

import numpy as np
import pytest

from pairedgta.metrics.estimators import permutation_pvalue
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
