"""Bias-corrected intervals, their p-values and Holm's correction, for statistics resampled over more than one
unit at once (scenes and models).

A percentile interval is biased where the point estimate sits off the centre of its bootstrap distribution,
as a rank correlation near +-1 or a difference of two does. BCa (Efron 1987; Efron & Tibshirani 1993, ch. 14)
corrects for it with the median bias z0 and the acceleration a. The acceleration comes from jackknife values,
one array per resampled unit (leave one scene out, leave one model out), combined as Efron & Tibshirani's
multi-sample acceleration (eq. 14.15 generalised): a = sum_k sum_i U_ki^3 / n_k^3 / (6 (sum_k sum_i U_ki^2 /
n_k^2)^(3/2)), U_ki = (n_k - 1)(mean_k - theta_(ki)). The p-value of H0: theta = null inverts the same
interval: the level at which `null` is an endpoint. Pure numpy; the normal quantiles from statistics.NormalDist."""
from __future__ import annotations

import math
from statistics import NormalDist
from typing import Sequence

import numpy as np

_NORMAL = NormalDist()


def _cdf(z: float) -> float:
    return _NORMAL.cdf(z)


def _ppf(p: float) -> float:
    return _NORMAL.inv_cdf(p)


def acceleration(jackknives: Sequence[np.ndarray]) -> float:
    """BCa acceleration from one jackknife array per resampled unit (the finite values of each; a unit with
    fewer than 2 is left out). 0 where the jackknife does not vary."""
    num = den = 0.0
    for jk in jackknives:
        v = np.asarray(jk, float)
        v = v[np.isfinite(v)]
        n = v.size
        if n < 2:
            continue
        u = (n - 1) * (v.mean() - v)
        num += float(np.sum(u ** 3)) / n ** 3
        den += float(np.sum(u ** 2)) / n ** 2
    return num / (6.0 * den ** 1.5) if den > 1e-300 else 0.0


def _share_below(ok: np.ndarray, value: float) -> float:
    """Share of the bootstrap values below `value`, ties counted half (rank statistics tie often; for a
    continuous statistic this is Efron's #{theta* < theta^} / B), kept inside [1/2n, 1 - 1/2n] so that its
    normal quantile is finite."""
    n = ok.size
    share = (np.count_nonzero(ok < value) + 0.5 * np.count_nonzero(ok == value)) / n
    return min(max(share, 0.5 / n), 1 - 0.5 / n)


def _usable(boot: np.ndarray) -> np.ndarray | None:
    """The finite resamples, or None where fewer than half define the statistic or they do not vary: a
    zero-width interval would claim a certainty that the data cannot give."""
    boot = np.asarray(boot, float).ravel()
    ok = boot[np.isfinite(boot)]
    if ok.size < max(2, boot.size // 2) or np.ptp(ok) <= 1e-12:
        return None
    return ok


def bca_interval(boot: np.ndarray, point: float, jackknives: Sequence[np.ndarray] = (),
                 confidence: float = 0.95) -> tuple[float, float]:
    """BCa interval of `point` from its resamples `boot` and jackknife values per unit (none: the
    bias-corrected percentile interval, a = 0). NaN where no honest interval exists (see `_usable`, a
    non-finite point, or an acceleration so large that the adjusted level leaves (0, 1))."""
    ok = _usable(boot)
    if ok is None or not math.isfinite(point):
        return math.nan, math.nan
    z0 = _ppf(_share_below(ok, point))
    a = acceleration(jackknives)
    alpha = (1 - confidence) / 2
    ends = []
    for level in (alpha, 1 - alpha):
        t = z0 + _ppf(level)
        den = 1 - a * t
        if den <= 0:
            return math.nan, math.nan
        ends.append(float(np.quantile(ok, _cdf(z0 + t / den))))
    if ends[1] - ends[0] <= 1e-12:  # both levels fell on one value (a tie of most resamples): no certainty
        return math.nan, math.nan
    return ends[0], ends[1]


def bca_pvalue(boot: np.ndarray, point: float, jackknives: Sequence[np.ndarray] = (), null: float = 0.0) -> float:
    """Two-sided p-value of H0: theta = `null`, inverting the BCa interval: 2 min(l, 1 - l) with l the
    one-sided level at which `null` is the interval's endpoint. With z0 = a = 0 it is the percentile
    bootstrap's 2 min(share below null, share above). Its floor is 1 / resamples."""
    ok = _usable(boot)
    if ok is None or not math.isfinite(point):
        return math.nan
    z0 = _ppf(_share_below(ok, point))
    a = acceleration(jackknives)
    zu = _ppf(_share_below(ok, null)) - z0
    den = 1 + a * zu
    if den <= 0:
        return math.nan
    level = _cdf(zu / den - z0)
    return float(min(1.0, 2 * min(level, 1 - level)))


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjustment over one family (the NaN p-values are not in the family and stay NaN):
    the i-th smallest of m is multiplied by m - i + 1, then made monotone and capped at 1."""
    p = np.asarray(pvalues, float)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    if not ok.size:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    m = order.size
    adjusted = np.minimum(1.0, np.maximum.accumulate(p[order] * (m - np.arange(m))))
    out[order] = adjusted
    return out


__all__ = ["acceleration", "bca_interval", "bca_pvalue", "holm"]
