"""One model placed against a population of models (the figure `model_report`): its rank and percentile per
condition, and how well label-free xi tracks ground truth across the models on the same scenes.

Rank: 1 is the best; models tied with the subject (within TIE) share the better rank, so a rank of k of n says that
k - 1 models did strictly better. Percentile: the share of the population the subject beats, ties counted half
(scipy's `percentileofscore(kind="mean")`): 100 is above every member, 50 in the middle; NaN where the subject's
value or every member's is undefined. `higher_is_better=False` ranks losses (a drop of GT mIoU): then the subject
beats the members that lose more.

Whether xi tracks ground truth is asked within each condition (Spearman of mean xi against GT mIoU across the
models), never over the cells of every condition pooled, which would mostly order the conditions by severity and
flatter xi. Each correlation has two percentile intervals: over scenes (the groups resampled, every model's values
recomputed on the same draw) and over models (the models drawn with replacement, a draw of fewer than MIN_MODELS
distinct models undefined). An interval is given only where at least half the resamples define the statistic and
they vary (`pairedgta.metrics.validity._interval`): a zero-width interval would claim a certainty the data cannot
give. The mean over conditions is taken over the conditions where the correlation is defined, on every resample."""
from __future__ import annotations

import math
import warnings
from typing import Sequence

import numpy as np

from pairedgta.metrics.validity import _interval, spearman_rows

TIE = 1e-12
MIN_MODELS = 3  # two models always rank-correlate at +1 or -1: no evidence either way


def standing_rows(subject: np.ndarray, population: np.ndarray, higher_is_better: bool = True
                  ) -> dict[str, np.ndarray]:
    """subject: R, population: R x M (NaN: a member without a value) -> per row `rank` (1 = best), `n` (the models
    ranked: the defined members and the subject), `percentile` (0-100) and `n_population` (the defined members)."""
    s = np.atleast_1d(np.asarray(subject, float))
    p = np.asarray(population, float).reshape(len(s), -1)
    sign = 1.0 if higher_is_better else -1.0
    defined = np.isfinite(p)
    ties = defined & (np.abs(p - s[:, None]) <= TIE)
    better = defined & ~ties & (sign * p > sign * s[:, None])
    worse = defined & ~ties & (sign * p < sign * s[:, None])
    n_pop = defined.sum(axis=1)
    ok = np.isfinite(s) & (n_pop > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        percentile = 100.0 * (worse.sum(1) + 0.5 * ties.sum(1)) / n_pop
    return {"rank": np.where(ok, 1.0 + better.sum(1), np.nan), "n": (n_pop + 1).astype(float),
            "percentile": np.where(ok, percentile, np.nan), "n_population": n_pop.astype(float)}


def standing(subject: float, population: Sequence[float], higher_is_better: bool = True) -> dict[str, float]:
    """The subject's rank, n, percentile and n_population among one set of values (see `standing_rows`)."""
    rows = standing_rows(np.array([subject], float), np.asarray(population, float)[None, :], higher_is_better)
    return {k: float(v[0]) for k, v in rows.items()}


def standing_interval(subject: np.ndarray, population: np.ndarray, confidence: float,
                      higher_is_better: bool = True) -> tuple[float, float]:
    """Percentile interval of the subject's percentile over resamples (subject: R, population: R x M); NaN where
    fewer than half the resamples define it or it does not vary."""
    lo, hi, _ = _interval(standing_rows(subject, population, higher_is_better)["percentile"], confidence)
    return lo, hi


def spearman_masked(x: np.ndarray, y: np.ndarray, draws: np.ndarray | None = None) -> np.ndarray:
    """Spearman per row of R x M over the models defined in both (finite x and y); NaN where fewer than MIN_MODELS
    distinct models are defined (`draws`: R x M model indices, a model drawn twice counts once) or a row is constant."""
    x, y = np.atleast_2d(np.asarray(x, float)), np.atleast_2d(np.asarray(y, float))
    valid = np.isfinite(x) & np.isfinite(y)
    ids = np.broadcast_to(np.arange(x.shape[1]), x.shape) if draws is None else np.asarray(draws)
    marked = np.sort(np.where(valid, ids, -1), axis=1)
    distinct = ((np.diff(marked, axis=1) != 0) & (marked[:, 1:] >= 0)).sum(1) + (marked[:, :1] >= 0).sum(1)
    if valid.all():
        rho = spearman_rows(x, y)
    else:
        rho = np.array([spearman_rows(x[r, valid[r]], y[r, valid[r]])[0] if valid[r].sum() >= 2 else np.nan
                        for r in range(x.shape[0])])
    return np.where(distinct >= MIN_MODELS, rho, np.nan)


def model_draws(n_models: int, resamples: int, seed: int) -> np.ndarray:
    """R x M model indices drawn with replacement (seeded apart from the scene draws)."""
    return np.random.default_rng([int(seed), 1]).integers(0, n_models, size=(resamples, n_models))


def tracking(xi: np.ndarray, gt: np.ndarray, conditions: Sequence[str], scene_xi: np.ndarray | None = None,
             scene_gt: np.ndarray | None = None, resamples: int = 1000, confidence: float = 0.95, seed: int = 0,
             n_scenes: int | None = None) -> list[dict]:
    """xi, gt: M x C' (the ranked models' mean xi and GT mIoU per adverse condition); scene_xi, scene_gt: M x R x C'
    (the same on R scene resamples), or None for no scene interval. -> one row per condition and one `mean` row:
    `spearman`, its `scene_ci_*` and `model_ci_*`, `n_models` (defined in the condition; for the mean: the models),
    `n_conditions` (the mean's defined conditions), `n_scenes`, `resamples`."""
    xi, gt = np.asarray(xi, float), np.asarray(gt, float)
    n_models, n_cond = xi.shape
    point = np.array([spearman_masked(xi[None, :, c], gt[None, :, c])[0] for c in range(n_cond)], float)
    draws = model_draws(n_models, resamples, seed) if resamples > 0 and n_models else None
    by_model = (np.stack([spearman_masked(xi[:, c][draws], gt[:, c][draws], draws) for c in range(n_cond)], axis=1)
                if draws is not None and n_cond else None)                                      # R x C'
    by_scene = (np.stack([spearman_masked(scene_xi[:, :, c].T, scene_gt[:, :, c].T) for c in range(n_cond)], axis=1)
                if scene_xi is not None and scene_gt is not None and n_cond else None)          # R x C'
    rows = []
    for c, name in enumerate(conditions):
        row = {"condition": name, "spearman": float(point[c]),
               "n_models": int((np.isfinite(xi[:, c]) & np.isfinite(gt[:, c])).sum()), "n_conditions": 1}
        for kind, boot in (("scene", by_scene), ("model", by_model)):
            lo, hi = (_interval(boot[:, c], confidence)[:2] if boot is not None and math.isfinite(point[c])
                      else (math.nan, math.nan))
            row.update({f"{kind}_ci_low": lo, f"{kind}_ci_high": hi})
        rows.append(row)
    defined = np.isfinite(point)
    mean = {"condition": "mean", "spearman": float(point[defined].mean()) if defined.any() else math.nan,
            "n_models": n_models, "n_conditions": int(defined.sum())}
    for kind, boot in (("scene", by_scene), ("model", by_model)):
        lo = hi = math.nan
        if boot is not None and defined.any():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                # undefined (NaN) where one of the point's defined conditions is not: the same conditions every time
                lo, hi, _ = _interval(boot[:, defined].mean(axis=1), confidence)
        mean.update({f"{kind}_ci_low": lo, f"{kind}_ci_high": hi})
    rows.append(mean)
    for row in rows:
        row.update({"n_scenes": n_scenes, "resamples": resamples, "confidence": confidence})
    return rows


__all__ = ["TIE", "MIN_MODELS", "standing", "standing_rows", "standing_interval", "spearman_masked", "model_draws",
           "tracking"]
