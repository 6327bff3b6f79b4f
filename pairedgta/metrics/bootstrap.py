"""Percentile bootstrap over images, seeded, vectorised with multinomial resampling weights."""
from __future__ import annotations

import math
import warnings
import numpy as np

from pairedgta.metrics.reference_consistency import xi_from_counts


def resample_weights(n: int, resamples: int, seed: int) -> np.ndarray:
    """resamples x n counts: how often each image is drawn in each bootstrap sample."""
    rng = np.random.default_rng(seed)
    return rng.multinomial(n, np.full(n, 1.0 / n), size=resamples) if n else np.zeros((resamples, 0))


def ratio_ci(numer: np.ndarray, denom: np.ndarray, resamples: int = 1000, confidence: float = 0.95, seed: int = 0,
             absent: str = "nan") -> tuple[np.ndarray, np.ndarray]:
    """CI of sum(numer)/sum(denom) per column (N images x C classes). A resample without the class
    gives NaN and is ignored (absent="nan"; a column never defined has a NaN interval) or scores 0
    (absent="zero", the authors' clamp; a column never defined has [0, 0])."""
    numer, denom = np.asarray(numer, float), np.asarray(denom, float)
    nan = np.full(numer.shape[1:], np.nan)
    if numer.shape[0] == 0 or resamples <= 0:
        return nan, nan.copy()
    w = resample_weights(numer.shape[0], resamples, seed)
    alpha = (1 - confidence) / 2
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: classes never in the reference
        boot = xi_from_counts(w @ numer, w @ denom, absent)
        lo = np.nanquantile(boot, alpha, axis=0)
        hi = np.nanquantile(boot, 1 - alpha, axis=0)
    undefined = denom.sum(axis=0) == 0
    fill = 0.0 if absent == "zero" else np.nan
    return np.where(undefined, fill, lo), np.where(undefined, fill, hi)


def spearman_ci(x: np.ndarray, y: np.ndarray, resamples: int = 1000, confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile CI of Spearman's rho over frames resampled with replacement, vectorised:
    average ranks per resample (ties as scipy), then Pearson of the ranks. Constant draws are dropped."""
    from scipy.stats import rankdata

    x, y = np.asarray(x, float), np.asarray(y, float)
    n = len(x)
    if n < 2 or resamples <= 0:
        return math.nan, math.nan
    idx = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    rx = rankdata(x[idx], axis=1)
    ry = rankdata(y[idx], axis=1)
    rx -= rx.mean(axis=1, keepdims=True)
    ry -= ry.mean(axis=1, keepdims=True)
    den = np.sqrt((rx * rx).sum(axis=1) * (ry * ry).sum(axis=1))
    ok = den > 0
    if not ok.any():
        return math.nan, math.nan
    rho = (rx * ry).sum(axis=1)[ok] / den[ok]
    alpha = (1 - confidence) / 2
    return float(np.quantile(rho, alpha)), float(np.quantile(rho, 1 - alpha))


def class_mean_ci(numer: np.ndarray, denom: np.ndarray, include: np.ndarray, resamples: int = 1000,
                  confidence: float = 0.95, seed: int = 0, absent: str = "nan") -> tuple[float, float]:
    """Percentile CI of the class-wise mean of xi (N images x C classes, over the `include`d columns),
    resampling images; each resample's mean follows the same absent-class convention as the estimate."""
    numer, denom = np.asarray(numer, float), np.asarray(denom, float)
    include = np.asarray(include, bool)
    if numer.shape[0] == 0 or resamples <= 0 or not include.any():
        return math.nan, math.nan
    w = resample_weights(numer.shape[0], resamples, seed)
    alpha = (1 - confidence) / 2
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        boot = xi_from_counts(w @ numer[:, include], w @ denom[:, include], absent)
        means = np.nanmean(boot, axis=1)  # absent="nan": a class missing from a resample drops out of its mean
        if np.all(np.isnan(means)):
            return math.nan, math.nan
        return float(np.nanquantile(means, alpha)), float(np.nanquantile(means, 1 - alpha))


def drop_zero_width(lo, hi):
    """An interval of width 0 from resampling says the data could not vary (one class, one frame, a constant
    image), not that the value is certain: it is reported as no interval (NaN)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    degenerate = np.isfinite(lo) & np.isfinite(hi) & (hi - lo <= 1e-12)
    lo, hi = np.where(degenerate, np.nan, lo), np.where(degenerate, np.nan, hi)
    return (float(lo), float(hi)) if lo.ndim == 0 else (lo, hi)
