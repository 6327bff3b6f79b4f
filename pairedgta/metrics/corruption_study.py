"""Do the field's 2D corruptions rank models as rendered light and weather do? (`+experiment=corruptions_vs_rendered`)

Input: a score per (resample, model, condition) with resample 0 the data itself and resamples 1.. scene bootstraps
(the same scene draw for every model and condition: the scores are paired), the clean condition among the conditions.
Per model the robustness under a condition is its relative score (score / clean score, Michaelis et al.'s rPC of one
condition) or its adverse score itself. For every rendered adverse condition and every corruption (each severity, and
the mean over the severities as Cityscapes-C reports it), Spearman's rho between the models' robustness under the two;
the interval resamples scenes and models together (resample r: scene draw r and a model draw r, as the estimator study
does; draws with fewer than three distinct models are left out). Also the mean over the corruptions against the mean
over the rendered conditions (the published question: Agnihotri et al. 2025 compare the means of real and synthetic
shifts), and per rendered condition the corruption that ranks models closest to it, with the paired difference to the
runner-up: a best stand-in is claimed only where that difference's interval excludes 0."""
from __future__ import annotations

import contextlib
import math
import warnings
from typing import Callable, Iterator, Sequence

import numpy as np

from pairedgta.metrics.estimator_study import model_draws
from pairedgta.metrics.validity import _interval, spearman_rows

MEASURES = ("relative", "score")  # robustness as score / clean score (rPC of one condition), or the adverse score


def robustness(scores: np.ndarray, clean: int, measure: str) -> np.ndarray:
    """R x M x C scores -> R x M x C robustness: relative to the model's clean score (NaN where that is <= 0)."""
    if measure == "score":
        return scores
    base = scores[:, :, clean : clean + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(base > 0, scores / np.where(base > 0, base, 1.0), np.nan)


def _rho(x: np.ndarray, y: np.ndarray, draws: np.ndarray, ok: np.ndarray) -> tuple[float, np.ndarray]:
    """x, y: R x M (resample 0 the data) -> (rho on the data, rho per bootstrap resample r >= 1 on its model draw)."""
    point = float(spearman_rows(x[:1], y[:1])[0])
    xb = np.take_along_axis(x[1:], draws, axis=1)
    yb = np.take_along_axis(y[1:], draws, axis=1)
    boot = spearman_rows(xb, yb)
    return point, np.where(ok, boot, np.nan)


def compare(scores: np.ndarray, conditions: Sequence[str], clean: str, parse: Callable[[str], tuple[str, int] | None],
            confidence: float = 0.95, seed: int = 0) -> tuple[list[dict], list[dict], list[dict]]:
    """scores: (1 + R) x M x C. -> (pairs, means, stand_ins) as rows (see the module docstring)."""
    conditions = list(conditions)
    ci = conditions.index(clean)
    parsed = [parse(c) for c in conditions]
    rendered = [i for i, p in enumerate(parsed) if p is None and i != ci]
    corrupted = [i for i, p in enumerate(parsed) if p is not None]
    names = sorted({parsed[i][0] for i in corrupted})
    resamples, n_models = scores.shape[0] - 1, scores.shape[1]
    draws, ok = model_draws(n_models, resamples, seed)
    pairs, means, stand_ins = [], [], []
    for measure in MEASURES:
        rob = robustness(scores, ci, measure)  # (1 + R) x M x C
        columns: dict[tuple[str, str], np.ndarray] = {}  # (corruption, severity label) -> (1 + R) x M
        for i in corrupted:
            columns[(parsed[i][0], str(parsed[i][1]))] = rob[:, :, i]
        for name in names:
            cols = [rob[:, :, i] for i in corrupted if parsed[i][0] == name]
            with _quiet():
                columns[(name, "mean")] = np.nanmean(np.stack(cols), axis=0)
        for r in rendered:
            per: dict[str, tuple[float, np.ndarray]] = {}
            for (name, severity), col in columns.items():
                point, boot = _rho(rob[:, :, r], col, draws, ok)
                lo, hi, n = _interval(boot, confidence)
                pairs.append({"measure": measure, "rendered": conditions[r], "corruption": name, "severity": severity,
                              "spearman": point, "ci_low": lo, "ci_high": hi, "resamples": n, "models": n_models})
                if severity == "mean":
                    per[name] = (point, boot)
            ranked = sorted(per, key=lambda k: -per[k][0] if math.isfinite(per[k][0]) else math.inf)
            if len(ranked) >= 2:
                best, second = ranked[0], ranked[1]
                lo, hi, _ = _interval(per[best][1] - per[second][1], confidence)
                stand_ins.append({"measure": measure, "rendered": conditions[r], "best": best,
                                  "spearman": per[best][0], "runner_up": second, "runner_up_spearman": per[second][0],
                                  "difference": per[best][0] - per[second][0], "diff_ci_low": lo, "diff_ci_high": hi,
                                  "clear": bool(math.isfinite(lo) and lo > 0)})
        if rendered and corrupted:
            with _quiet():
                x = np.nanmean(rob[:, :, rendered], axis=2)
                y = np.nanmean(rob[:, :, corrupted], axis=2)
            point, boot = _rho(x, y, draws, ok)
            lo, hi, n = _interval(boot, confidence)
            means.append({"measure": measure, "rendered": "mean of the rendered", "corruption": "mean of the corruptions",
                          "spearman": point, "ci_low": lo, "ci_high": hi, "resamples": n, "models": n_models})
    return pairs, means, stand_ins


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """A mean over an all-NaN slice (a model without a clean score) is NaN, said once in the tables, not warned."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def scene_weights(n_scenes: int, resamples: int, seed: int) -> np.ndarray:
    """(1 + R) x N: a row of ones (the data), then R bootstrap draws of the scenes as counts."""
    rng = np.random.default_rng([int(seed), 2])
    idx = rng.integers(0, n_scenes, size=(resamples, n_scenes))
    w = np.zeros((resamples, n_scenes))
    np.add.at(w, (np.arange(resamples)[:, None], idx), 1.0)
    return np.vstack([np.ones((1, n_scenes)), w])


__all__ = ["MEASURES", "compare", "robustness", "scene_weights"]
