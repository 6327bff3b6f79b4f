"""Is xi the best label-free judge of robustness? The estimators of pairedgta/metrics/estimators.py compared
against the embedded renderer's ground truth.

Statistics lead with the within-condition view: per adverse condition, Spearman and Kendall (tau-b)
across the ranked models (every model but the reference, which would grade itself), and their mean over
the conditions (`within_mean`) with a paired bootstrap interval over scenes (the zoo held fixed), a BCa
interval over scenes and models drawn together (`pairedgta.metrics.inference`), and a permutation p-value
against a random model order (one order of the model labels for every condition: the joint null). The
difference of every two estimators (to xi in `stats`, all pairs in `pairs`) is paired on the same scene
and model draws, with a BCa interval and p-value, Holm-adjusted over the estimators of one target. Beside
it, the correlation over every cell pooled (which mostly orders the conditions) and the mean absolute error
of a linear map from estimator to target fitted on the other conditions: leave one condition out, and
leave one illumination out (Day / Sunset / Night: no sibling condition of the same time of day in the fit,
the honest transfer test), each MAE with a BCa interval over scenes and models."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np

from pairedgta.metrics.bootstrap import resample_weights
from pairedgta.metrics.inference import bca_interval, bca_pvalue, holm
from pairedgta.metrics.validity import (GroupCounts, _interval, defined_models, spearman_rows)
from pairedgta.metrics.estimators import (ATC_FOLDS, COLUMNS, COUNT_ARRAYS, ESTIMATORS, EstimatorCounts, MIN_RANKED,
                                          PROBIT_EPS, STATS, TARGETS, USES_CLEAN_LABELS, _ratio, aline, atc,
                                          atc_held_out, atc_threshold, average_confidence, committee_agreement,
                                          concat_counts, entropy_score, estimator_values, model_values, twin_indices,
                                          pairwise_agreement, pixel_accuracy, relative, self_agreement)


def ranked_models(names: Sequence[str], reference: Iterable[str]) -> list[str]:
    """The models that are ranked: every one but the reference model(s), whose pseudo-labels xi counts."""
    ref = set(reference)
    return [n for n in names if n not in ref]


def model_draws(n_models: int, resamples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """-> (R x M model indices drawn with replacement, R bools: at least 3 distinct models drawn)."""
    idx = np.random.default_rng([int(seed), 1]).integers(0, n_models, size=(resamples, n_models))
    distinct = (np.diff(np.sort(idx, axis=1), axis=1) != 0).sum(axis=1) + 1 if n_models else np.zeros(resamples, int)
    return idx, distinct >= 3


def within_condition(x: np.ndarray, y: np.ndarray, stat: Callable = spearman_rows,
                     draws: np.ndarray | None = None) -> np.ndarray:
    """x, y: M x R x C' (models, resamples, conditions) -> R x C': the rank correlation across models per
    resample and condition; with `draws` (R x M model indices) across the models each resample drew."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    out = []
    for i in range(x.shape[-1]):
        xi, yi = x[..., i].T, y[..., i].T                   # R x M
        if draws is not None:
            xi, yi = np.take_along_axis(xi, draws, axis=1), np.take_along_axis(yi, draws, axis=1)
        out.append(stat(xi, yi))
    return np.stack(out, axis=-1)


def permutation_pvalue(x: np.ndarray, y: np.ndarray, permutations: int, seed: int = 0,
                       stat: Callable = spearman_rows) -> float:
    """x, y: C' x M (per condition, across the same M models). One-sided p-value of the mean over conditions
    of the rank correlation under the joint null: the model labels are permuted once and that permutation
    is applied to every condition, since the same models appear under every condition and their values
    correlate across conditions (shuffling each condition on its own makes the null too narrow: a shared
    model effect and no association then rejects far more often than the nominal level).
    Every permutation when M! <= `permutations` (exact: p = #{mean >= observed} / M!, the identity among
    them); otherwise `permutations` random ones, p = (1 + #{permuted mean >= observed}) / (1 + permutations)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    observed = float(np.mean(stat(x, y)))
    if not math.isfinite(observed) or permutations <= 0:
        return math.nan
    n_cond, n_models = x.shape
    exact = math.factorial(n_models) <= permutations
    if exact:
        orders = np.array(list(itertools.permutations(range(n_models))), dtype=np.int64)
    else:
        rng = np.random.default_rng([int(seed), 2])
    total = len(orders) if exact else permutations
    hits, done = 0, 0
    chunk = max(1, 200_000 // max(1, n_cond * n_models))
    while done < total:
        n = min(chunk, total - done)
        order = orders[done : done + n] if exact else np.argsort(rng.random((n, n_models)), axis=-1)
        xp = x[:, order].transpose(1, 0, 2)             # n x C' x M: one order for every condition
        yp = np.broadcast_to(y, (n, n_cond, n_models))
        means = stat(xp.reshape(-1, n_models), yp.reshape(-1, n_models)).reshape(n, n_cond).mean(axis=1)
        hits += int(np.sum(means >= observed - 1e-12))
        done += n
    return hits / total if exact else (1 + hits) / (1 + permutations)


def illumination(condition: str) -> str | None:
    """The time of day of a grid condition (`Day-RAIN` -> `Day`), None for names of another form (a ladder's
    `fog_0.5`)."""
    time, sep, _ = str(condition).partition("-")
    return time if sep and time else None


def illumination_folds(conditions: Sequence[str]) -> dict[str, list[int]]:
    """Positions of the conditions per illumination (Day / Sunset / Night), in order of appearance; {} where
    a condition has no illumination or fewer than two illuminations are present (nothing to leave out)."""
    folds: dict[str, list[int]] = {}
    for i, c in enumerate(conditions):
        time = illumination(c)
        if time is None:
            return {}
        folds.setdefault(time, []).append(i)
    return folds if len(folds) >= 2 else {}


def holdout_mae(x: np.ndarray, y: np.ndarray, folds: Sequence[Sequence[int]]) -> dict[str, np.ndarray]:
    """x, y: R x M x C' (resamples, models, adverse conditions). For each fold (the positions of the
    conditions held out together), y = a + b x is fitted by least squares on the cells of the other
    conditions and evaluated on the held-out cells; the baseline predicts the training cells' mean target.
    -> `mae`, `mae_baseline` (R: over every held-out cell of every fold) and `per_fold`,
    `per_fold_baseline` (R x F). A fold with fewer than 2 training cells or no held-out cell is NaN and out
    of the totals; where the training x do not vary, the fit is the mean."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    n_res, n_cond = x.shape[0], x.shape[-1]
    per, per_base = np.full((n_res, len(folds)), np.nan), np.full((n_res, len(folds)), np.nan)
    err_sum, base_sum, cells = np.zeros(n_res), np.zeros(n_res), np.zeros(n_res)
    for f, held in enumerate(folds):
        train = np.setdiff1d(np.arange(n_cond), held)
        xt, yt = x[:, :, train].reshape(n_res, -1), y[:, :, train].reshape(n_res, -1)
        ok = np.isfinite(xt) & np.isfinite(yt)
        count = ok.sum(axis=1)
        xt, yt = np.where(ok, xt, 0.0), np.where(ok, yt, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mx, my = xt.sum(1) / count, yt.sum(1) / count
            dx = np.where(ok, xt - mx[:, None], 0.0)
            sxx, sxy = (dx * dx).sum(1), (dx * (yt - my[:, None])).sum(1)
            spread = np.where(ok, xt, -np.inf).max(1) - np.where(ok, xt, np.inf).min(1)
            b = np.where(spread > 1e-12, sxy / np.where(sxx > 0, sxx, 1.0), 0.0)
        a = my - b * mx
        xh, yh = x[:, :, list(held)].reshape(n_res, -1), y[:, :, list(held)].reshape(n_res, -1)
        okh = np.isfinite(xh) & np.isfinite(yh)
        nh = okh.sum(axis=1)
        err = np.where(okh, np.abs(a[:, None] + b[:, None] * np.where(okh, xh, 0) - np.where(okh, yh, 0)), 0.0).sum(1)
        base = np.where(okh, np.abs(my[:, None] - np.where(okh, yh, 0)), 0.0).sum(1)
        use = (count >= 2) & (nh > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            per[:, f] = np.where(use, err / nh, np.nan)
            per_base[:, f] = np.where(use, base / nh, np.nan)
        err_sum += np.where(use, err, 0.0)
        base_sum += np.where(use, base, 0.0)
        cells += np.where(use, nh, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mae = np.where(cells > 0, err_sum / np.where(cells > 0, cells, 1), np.nan)
        mae_base = np.where(cells > 0, base_sum / np.where(cells > 0, cells, 1), np.nan)
    return {"mae": mae, "mae_baseline": mae_base, "per_fold": per, "per_fold_baseline": per_base}


def loco_mae(x: np.ndarray, y: np.ndarray) -> dict[str, object]:
    """Leave one condition out: x, y are M x C' (cells of the ranked models under each adverse condition).
    For each held-out condition, y = a + b x is fitted by least squares on the other conditions' cells and
    evaluated on the held-out cells; the baseline predicts the training cells' mean target. -> `mae` and
    `mae_baseline` (over every held-out cell), `per_condition` and `per_condition_baseline` (C')."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    out = holdout_mae(x[None], y[None], [[i] for i in range(x.shape[1])])
    return {"mae": float(out["mae"][0]), "mae_baseline": float(out["mae_baseline"][0]),
            "per_condition": out["per_fold"][0], "per_condition_baseline": out["per_fold_baseline"][0]}


def mae_with_intervals(px: np.ndarray, py: np.ndarray, bx: np.ndarray | None, by: np.ndarray | None,
                       jx: np.ndarray | None, jy: np.ndarray | None, draws: np.ndarray | None,
                       folds: Sequence[Sequence[int]], confidence: float) -> dict[str, list[tuple[float, float, float]]]:
    """`holdout_mae` of the data with a BCa interval over scenes and models drawn together (the resample's
    scene weights give bx, by: M x R x C'; `draws`, R x M, its models) and the jackknife of both units
    (jx, jy: M x G x C', leave one scene out; and leave one model out, its cells gone from fit and test).
    -> `mae`, `mae_baseline`: [(value, low, high)]; `per_fold`, `per_fold_baseline`: one per fold."""
    point = holdout_mae(px[None], py[None], folds)
    joint = jack_scene = jack_model = None
    if bx is not None and draws is not None:
        pick = lambda a: np.take_along_axis(np.moveaxis(a, 0, 1), draws[:, :, None], axis=1)  # noqa: E731
        joint = holdout_mae(pick(bx), pick(by), folds)
    if jx is not None:
        jack_scene = holdout_mae(np.moveaxis(jx, 0, 1), np.moveaxis(jy, 0, 1), folds)
        m = px.shape[0]
        rest = np.array([np.delete(np.arange(m), i) for i in range(m)])
        jack_model = holdout_mae(px[rest], py[rest], folds)
    out: dict[str, list[tuple[float, float, float]]] = {}
    for key in ("mae", "mae_baseline", "per_fold", "per_fold_baseline"):
        values = point[key][0]
        columns = [values] if np.ndim(values) == 0 else list(values)
        rows = []
        for f, v in enumerate(columns):
            def col(r: dict | None) -> np.ndarray | None:
                return None if r is None else (r[key] if r[key].ndim == 1 else r[key][:, f])
            jks = tuple(j for j in (col(jack_scene), col(jack_model)) if j is not None)
            stat = Resampled(float(v), col(joint), jks)
            rows.append((float(v), *stat.interval(confidence)))
        out[key] = rows
    return out


def _mean_over_conditions(r: np.ndarray) -> np.ndarray:
    """R x C' -> R: the mean, undefined (NaN) where any condition's correlation is."""
    return np.mean(r, axis=-1)


def drop_one_model(x: np.ndarray, y: np.ndarray, stat: Callable = spearman_rows) -> np.ndarray:
    """x, y: M x C' (models, conditions) -> M: the mean over conditions of the rank correlation across the
    models but one, each left out in turn (the models' jackknife, for the BCa acceleration)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    m, c = x.shape
    if m < 3:
        return np.full(m, np.nan)
    rest = np.array([np.delete(np.arange(m), i) for i in range(m)])          # M x (M - 1)
    xs, ys = x[rest].transpose(0, 2, 1), y[rest].transpose(0, 2, 1)           # M x C' x (M - 1)
    return stat(xs.reshape(-1, m - 1), ys.reshape(-1, m - 1)).reshape(m, c).mean(axis=1)


@dataclass(frozen=True)
class Resampled:
    """A statistic with what its interval needs: the point value, its resamples over scenes and models
    together (one draw of each per resample, shared by every estimator) and its jackknife per unit
    (leave one scene out, leave one model out). Differences of two keep the pairing: the same resamples
    and the same jackknife deletions."""

    point: float
    joint: np.ndarray | None
    jackknives: tuple[np.ndarray, ...] = ()

    def __sub__(self, other: "Resampled") -> "Resampled":
        joint = None if self.joint is None or other.joint is None else self.joint - other.joint
        return Resampled(self.point - other.point, joint, tuple(a - b for a, b in zip(self.jackknives, other.jackknives)))

    def interval(self, confidence: float) -> tuple[float, float]:
        return (math.nan, math.nan) if self.joint is None else bca_interval(self.joint, self.point, self.jackknives, confidence)

    def pvalue(self, null: float = 0.0) -> float:
        return math.nan if self.joint is None else bca_pvalue(self.joint, self.point, self.jackknives, null)


def _mae_columns(mae: tuple[float, float, float], base: tuple[float, float, float]) -> dict[str, float]:
    return {"mae": mae[0], "mae_ci_low": mae[1], "mae_ci_high": mae[2], "mae_baseline": base[0],
            "mae_baseline_ci_low": base[1], "mae_baseline_ci_high": base[2]}


PAIR_COLUMNS = ("target", "estimator_a", "estimator_b", "n_models", "n_groups", "spearman_a", "spearman_b", "difference",
                "ci_low", "ci_high", "p", "p_holm", "resamples", "confidence")  # of compare's `pairs`


def compare(models: Sequence[GroupCounts], counts: Sequence[EstimatorCounts], agree: np.ndarray, scored: np.ndarray,
            clean: str, include: np.ndarray, reference: Iterable[str] = (), absent: str = "nan",
            resamples: int = 1000, confidence: float = 0.95, seed: int = 0, permutations: int = 10000,
            min_images: int = 0, min_pixels: int = 0, rpc_floor: float = 0.0,
            twins: Iterable[Sequence[str]] = ()) -> tuple[list[dict], list[dict], list[dict]]:
    """-> (cells, stats, pairs). `models`/`counts`: every evaluated model (in the same order); the reference
    model(s) are left out of the ranking; `agree`/`scored` (`pairwise_agreement`) cover the ranked
    models, in their order. `cells`: one row per (ranked model, adverse condition) with every estimator,
    the ATC threshold and the targets. `stats`: one row per (estimator, target, scope), scope each adverse
    condition, `within_mean`, `pooled`, `loco` (leave one condition out), `loio` (leave one illumination
    out: Day, Sunset, Night, where the grid names them) and `loio_<illumination>` (that fold alone); every
    MAE with its BCa interval over scenes and models (see the module's docstring). `pairs`: per target, the
    difference of the within-condition mean Spearman of every two estimators (PAIR_COLUMNS). `twins`: pairs of
    ranked models that are two runs of one recipe (GDE's twins); an estimator defined for some models only
    (GDE) is judged over those, and its differences to the others over the models both are defined for.

    Intervals of `within_mean` over scenes and models (`*_model_ci_*`, the paired differences to xi and
    between estimators) are BCa over resamples that draw the scenes and the models at once, the same draws
    for every estimator, with the acceleration from leaving one scene and one model out; their p-values
    invert the same interval, and Holm's adjustment is over the estimator family of one target (`_holm`
    beside each raw p). A drawn model keeps its estimator values as computed on the whole ranked set (the
    committee's other models included). A model whose target is undefined in some adverse condition (rPC
    below the clean-mIoU floor `rpc_floor`) is left out of that target's rows (`n_models`; `n_undefined`
    says how many were), its cells keep the NaN and the absolute target."""
    names = ranked_models([m.model for m in models], reference)
    if len(names) < MIN_RANKED:
        raise ValueError(f"{len(names)} ranked models ({', '.join(names) or 'none'}); at least {MIN_RANKED} are needed")
    keep = [i for i, m in enumerate(models) if m.model in names]
    models, counts = [models[i] for i in keep], [counts[i] for i in keep]
    conds = models[0].conditions
    n = models[0].cm.shape[0]
    for m in models:
        if m.conditions != conds or m.cm.shape[0] != n or (m.group_ids and models[0].group_ids
                                                            and m.group_ids != models[0].group_ids):
            raise ValueError(f"model {m.model}: evaluated on other groups or conditions than {models[0].model}")
    if clean not in conds:
        raise ValueError(f"the clean condition {clean} was not evaluated")
    adverse = [i for i, c in enumerate(conds) if c != clean]
    c0 = conds.index(clean)
    if len(adverse) < 2:
        raise ValueError("at least 2 adverse conditions are needed (the mean over conditions, leave one out)")
    args = (clean, include, absent, min_images, min_pixels, rpc_floor)
    twin = twin_indices([m.model for m in models], twins)
    point = estimator_values(models, counts, agree, scored, np.ones((1, n)), *args, twin=twin)
    w = resample_weights(n, max(resamples, 0), seed).astype(float).reshape(max(resamples, 0), n)
    boot = estimator_values(models, counts, agree, scored, w, *args, twin=twin) if len(w) else None
    # leave one scene out: the scenes' jackknife of every estimator and target
    jack = estimator_values(models, counts, agree, scored, 1.0 - np.eye(n), *args, twin=twin) if len(w) and n >= 3 else None

    cells = []
    for j, m in enumerate(models):
        for i in adverse:
            row: dict = {"model": m.model, "condition": conds[i], "n_groups": n}
            row.update({k: float(point[k][j, 0, i]) for k in ESTIMATORS})
            row["atc_threshold"] = float(point["atc_threshold"][j, 0])
            # the share of the pixels labelled in the clean ground truth, those ATC's share and accuracy count
            row["atc_labelled_share"] = float(_ratio(np.asarray(m.cm[:, c0]).sum(), np.asarray(counts[j].pixels[:, c0]).sum()))
            row.update({k: float(point[k][j, 0, i]) for k in (*TARGETS, "gt_miou_clean")})
            cells.append(row)

    def interval(b: np.ndarray | None) -> tuple[float, float]:
        return _interval(b, confidence)[:2] if b is not None and b.size else (math.nan, math.nan)

    rows_of: dict[tuple[str, str], list[dict]] = {}
    pairs: list[dict] = []
    defined = {t: np.flatnonzero(defined_models(point[t][:, 0, adverse])) for t in TARGETS}
    by_light = illumination_folds([conds[i] for i in adverse])   # leave one illumination out, where there are two
    finite = {e: defined_models(point[e][:, 0, adverse]) for e in ESTIMATORS}   # GDE: the twins only
    for t in TARGETS:
        sub = defined[t]                                                   # the models whose target is defined
        if len(sub) < 3:  # two models rank-correlate at +-1: no statistic (their NaN targets make it NaN)
            sub = np.arange(len(models))
        on = {e: sub[finite[e][sub]] if not finite[e][sub].all() else sub for e in ESTIMATORS}
        memo: dict[tuple, Resampled] = {}

        def judged(e: str, models_of: np.ndarray, fn: Callable = spearman_rows, t: str = t) -> Resampled:
            """The within-condition mean rank correlation `fn` of estimator e with the target over the models
            `models_of`, resampled with the draws of that model set (the same draws for every estimator judged
            on it: paired), with its jackknives of scenes and models."""
            key = (e, tuple(models_of), fn)
            if len(models_of) < 3:   # fewer than 3 models: no rank statistic (GDE without twins)
                return Resampled(math.nan, None, ())
            if key not in memo:
                draws, enough = model_draws(len(models_of), len(w), seed)
                px, py = point[e][models_of][:, 0][:, adverse], point[t][models_of][:, 0][:, adverse]
                joint = None
                if boot is not None:   # scenes and models drawn together
                    bx, by = boot[e][models_of][:, :, adverse], boot[t][models_of][:, :, adverse]
                    joint = np.where(enough, _mean_over_conditions(within_condition(bx, by, fn, draws)), np.nan)
                jackknives = () if jack is None else (
                    _mean_over_conditions(within_condition(jack[e][models_of][:, :, adverse], jack[t][models_of][:, :, adverse], fn)),
                    drop_one_model(px, py, fn))
                memo[key] = Resampled(float(np.mean(within_condition(px[:, None], py[:, None], fn)[0])), joint, jackknives)
            return memo[key]

        means: dict[str, dict] = {}
        for e in ESTIMATORS:
            own = on[e]
            base = {"estimator": e, "target": t, "n_models": len(own), "n_undefined": len(models) - len(own),
                    "n_groups": n, "uses_clean_labels": e in USES_CLEAN_LABELS, "resamples": len(w),
                    "confidence": confidence}
            if len(own) < 3:   # defined for too few models (GDE where the zoo has no twins): every value NaN
                means[e] = dict(base, scope="within_mean", n_conditions=len(adverse), n_cells=len(own) * len(adverse),
                                p_permutation=math.nan, permutations=permutations)
                rows_of[e, t] = [dict(base, scope=conds[i], n_conditions=1, n_cells=len(own)) for i in adverse] + [
                    means[e], dict(base, scope="pooled", n_conditions=len(adverse), n_cells=len(own) * len(adverse))] + [
                    dict(base, scope=sc, n_conditions=len(adverse), n_cells=len(own) * len(adverse))
                    for sc in (["loco", "loio"] if by_light else ["loco"])] + [
                    dict(base, scope=f"loio_{light}", n_conditions=len(held), n_cells=len(own) * len(held))
                    for light, held in by_light.items()]
                continue
            draws, _ = model_draws(len(own), len(w), seed)   # the MAE intervals' model draws
            px, py = point[e][own][:, 0][:, adverse], point[t][own][:, 0][:, adverse]    # M x C'
            bx = by = jx = jy = None
            if boot is not None:
                bx, by = boot[e][own][:, :, adverse], boot[t][own][:, :, adverse]        # M x R x C'
            if jack is not None:
                jx, jy = jack[e][own][:, :, adverse], jack[t][own][:, :, adverse]        # M x G x C'
            loco = mae_with_intervals(px, py, bx, by, jx, jy, draws, [[a] for a in range(len(adverse))], confidence)
            rows = {conds[i]: dict(base, scope=conds[i], n_conditions=1, n_cells=len(own),
                                   **_mae_columns(loco["per_fold"][a], loco["per_fold_baseline"][a]))
                    for a, i in enumerate(adverse)}
            holdouts = [dict(base, scope="loco", n_conditions=len(adverse), n_cells=len(own) * len(adverse),
                             **_mae_columns(loco["mae"][0], loco["mae_baseline"][0]))]
            if by_light:
                loio = mae_with_intervals(px, py, bx, by, jx, jy, draws, list(by_light.values()), confidence)
                holdouts.append(dict(base, scope="loio", n_conditions=len(adverse), n_cells=len(own) * len(adverse),
                                     **_mae_columns(loio["mae"][0], loio["mae_baseline"][0])))
                holdouts += [dict(base, scope=f"loio_{light}", n_conditions=len(held), n_cells=len(own) * len(held),
                                  **_mae_columns(loio["per_fold"][f], loio["per_fold_baseline"][f]))
                             for f, (light, held) in enumerate(by_light.items())]
            mean = dict(base, scope="within_mean", n_conditions=len(adverse), n_cells=len(own) * len(adverse))
            pooled = dict(base, scope="pooled", n_conditions=len(adverse), n_cells=len(own) * len(adverse))
            for name, fn in STATS:
                p = within_condition(px[:, None], py[:, None], fn)[0]                     # C'
                b = within_condition(bx, by, fn) if bx is not None else None              # R x C', scenes only
                for a, i in enumerate(adverse):
                    lo, hi = interval(None if b is None else b[:, a])
                    rows[conds[i]].update({name: float(p[a]), f"{name}_ci_low": lo, f"{name}_ci_high": hi})
                lo, hi = interval(None if b is None else _mean_over_conditions(b))
                mean.update({name: float(np.mean(p)), f"{name}_ci_low": lo, f"{name}_ci_high": hi})
                lo, hi = judged(e, own, fn).interval(confidence)
                mean.update({f"{name}_model_ci_low": lo, f"{name}_model_ci_high": hi})
                bp = None
                if bx is not None:
                    bp = fn(bx.transpose(1, 2, 0).reshape(len(w), -1), by.transpose(1, 2, 0).reshape(len(w), -1))
                lo, hi = interval(bp)
                pooled.update({name: float(fn(px.T.reshape(1, -1), py.T.reshape(1, -1))[0]),
                               f"{name}_ci_low": lo, f"{name}_ci_high": hi})
            mean["p_permutation"] = permutation_pvalue(px.T, py.T, permutations, seed)
            mean["permutations"] = permutations
            means[e] = mean
            rows_of[e, t] = [*rows.values(), mean, pooled, *holdouts]
        # the family of one target: every estimator's association (permutation p), every difference to xi
        for e, h in zip(ESTIMATORS, holm([means[e]["p_permutation"] for e in ESTIMATORS])):
            means[e]["p_permutation_holm"] = h
        for e in ESTIMATORS:
            common = np.intersect1d(on[e], on["xi"])   # on the models both are defined for: the same draws
            d = judged(e, common) - judged("xi", common)   # xi - xi: 0 on every resample, no interval and no p (not a certainty)
            lo, hi = d.interval(confidence)
            means[e].update(spearman_minus_xi=d.point, spearman_minus_xi_ci_low=lo, spearman_minus_xi_ci_high=hi,
                            p_minus_xi=d.pvalue())
        for e, h in zip(ESTIMATORS, holm([means[e]["p_minus_xi"] for e in ESTIMATORS])):
            means[e]["p_minus_xi_holm"] = h
        family = []
        for a, ea in enumerate(ESTIMATORS):
            for eb in ESTIMATORS[a + 1:]:
                common = np.intersect1d(on[ea], on[eb])
                d = judged(ea, common) - judged(eb, common)
                lo, hi = d.interval(confidence)
                family.append({"target": t, "estimator_a": ea, "estimator_b": eb, "n_models": len(common),
                               "n_groups": n, "spearman_a": judged(ea, common).point, "spearman_b": judged(eb, common).point,
                               "difference": d.point, "ci_low": lo, "ci_high": hi, "p": d.pvalue(),
                               "resamples": len(w), "confidence": confidence})
        for row, h in zip(family, holm([r["p"] for r in family])):
            row["p_holm"] = h
        pairs += [{k: r.get(k, math.nan) for k in PAIR_COLUMNS} for r in family]
    stats = [{k: r.get(k, math.nan) for k in COLUMNS} for e in ESTIMATORS for t in TARGETS for r in rows_of[e, t]]
    return cells, stats, pairs


__all__ = ["ESTIMATORS", "USES_CLEAN_LABELS", "TARGETS", "COUNT_ARRAYS", "COLUMNS", "MIN_RANKED", "EstimatorCounts", "concat_counts",
           "average_confidence", "entropy_score", "self_agreement", "pixel_accuracy", "atc_threshold", "atc", "atc_held_out", "ATC_FOLDS",
           "pairwise_agreement", "committee_agreement", "aline", "PROBIT_EPS", "relative", "model_values", "estimator_values", "ranked_models", "model_draws", "within_condition",
           "permutation_pvalue", "illumination", "illumination_folds", "holdout_mae", "loco_mae", "mae_with_intervals",
           "drop_one_model", "Resampled", "PAIR_COLUMNS", "compare"]
