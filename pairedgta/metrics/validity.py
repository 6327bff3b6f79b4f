"""Is the label-free metric right? Label-free mean xi against ground-truth robustness, across models.

The paper scores models by how much of a reference model's pseudo-labels they keep under a shift,
because GTA V gives no labels under adverse conditions. The embedded renderer labels every condition,
so each (model, adverse condition) cell also has ground-truth measures: GT mIoU, the relative
robustness rPC = mIoU(adverse) / mIoU(clean) (the ratio MMDetection's robustness benchmark reports) and
xi against the true labels. Whether xi ranks models as ground truth does is a rank correlation
(Spearman, Kendall) between the two across models within each condition, and over all cells pooled.
Its uncertainty comes from a paired percentile bootstrap over scenes: one resample of the groups is
applied to every model and condition at once, so the intervals keep the pairing that makes the
comparison fair. Inputs are the per-group counts of evaluate (`group_counts.npz`)."""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from pairedgta.metrics.conventions import support_mask
from pairedgta.metrics.bootstrap import resample_weights
from pairedgta.metrics.reference_consistency import xi_from_counts

MEASURES = ("xi_mean", "xi_gt_mean", "gt_miou", "gt_miou_clean", "rpc")
TARGETS = ("rpc", "gt_miou", "xi_gt_mean")  # what the label-free xi is checked against


@dataclass(frozen=True)
class GroupCounts:
    """One model's per-group counts over the same groups and conditions as every other model's."""

    model: str
    conditions: tuple[str, ...]
    pl_retained: np.ndarray   # G x C x K
    pl_reference: np.ndarray  # G x C x K
    gt_retained: np.ndarray   # G x C x K
    gt_reference: np.ndarray  # G x C x K
    cm: np.ndarray            # G x C x K x K (truth, prediction)
    group_ids: tuple[str, ...] = ()  # which groups, in order: the pairing across models is checked on them
    # G x C x K pixels predicted as each class on the pseudo-label's valid pixels (xi's precision); None where the
    # entry predates it (evaluate's `pseudo_label_predicted`, pairedgta/evaluation/xi_precision.py)
    pl_predicted: np.ndarray | None = None

    @classmethod
    def from_arrays(cls, model: str, a: Mapping[str, np.ndarray]) -> "GroupCounts":
        ids = tuple(str(g) for g in a["group_id"]) if "group_id" in a else ()
        return cls(model, tuple(str(c) for c in a["conditions"]), a["pseudo_label_retained"], a["pseudo_label_reference"],
                   a["ground_truth_retained"], a["ground_truth_reference"], a["cm"], ids,
                   a["pseudo_label_predicted"] if "pseudo_label_predicted" in a else None)


def stack_passes(parts: list, fields: tuple[str, ...]) -> tuple[list[np.ndarray], tuple[str, ...]]:
    """Per-group arrays of one model over several passes, stacked along the groups, and the group ids made
    unique per pass (`<pass>:<group>`): the bootstrap then resamples all of them."""
    if len({p.conditions for p in parts}) != 1:
        raise ValueError("the passes were evaluated on different conditions")
    ids = tuple(f"{i}:{g}" for i, p in enumerate(parts) for g in p.group_ids) if all(p.group_ids for p in parts) else ()
    return [np.concatenate([getattr(p, f) for p in parts]) for f in fields], ids


def concat_groups(parts: Iterable[GroupCounts]) -> GroupCounts:
    """Groups of several datasets (passes) of one model, stacked."""
    parts = list(parts)
    arrays, ids = stack_passes(parts, ("pl_retained", "pl_reference", "gt_retained", "gt_reference", "cm"))
    predicted = (stack_passes(parts, ("pl_predicted",))[0][0] if all(p.pl_predicted is not None for p in parts)
                 else None)  # only where every pass has it
    return GroupCounts(parts[0].model, parts[0].conditions, *arrays, ids, predicted)


def mean_xi(retained: np.ndarray, reference: np.ndarray, include: np.ndarray, absent: str) -> np.ndarray:
    """Class-wise mean of pooled xi (... x K counts -> ...), as evaluate's mean: NaN classes skipped."""
    xi = xi_from_counts(retained, reference, absent)
    xi = np.where(include, xi, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(xi, axis=-1)


def miou(cm: np.ndarray) -> np.ndarray:
    """Cityscapes mIoU of pooled confusion matrices (... x K x K -> ...): classes with TP + FP + FN > 0."""
    cm = np.asarray(cm, float)
    tp = np.diagonal(cm, axis1=-2, axis2=-1)
    union = cm.sum(-1) + cm.sum(-2) - tp
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(np.where(union > 0, tp / np.maximum(union, 1), np.nan), axis=-1)


def supported(reference: np.ndarray, min_images: int = 0, min_pixels: int = 0) -> np.ndarray:
    """C x K: which classes have the support the class-wise mean asks for (metric.min_images/min_pixels),
    judged on the data itself (G x C x K counts) and kept fixed across resamples, as evaluate's mean is."""
    reference = np.asarray(reference)
    return support_mask((reference > 0).sum(axis=0), reference.sum(axis=0), min_images, min_pixels)


def cell_measures(g: GroupCounts, weights: np.ndarray, clean: str, include: np.ndarray,
                  absent: str, min_images: int = 0, min_pixels: int = 0, rpc_floor: float = 0.0) -> dict[str, np.ndarray]:
    """Every measure per (resample, condition) for group weights R x G (a row of ones = the data itself).
    rPC is undefined (NaN) where the clean GT mIoU is below `rpc_floor` (metric.validity.rpc_min_clean_miou):
    a model that predicts one class everywhere keeps its tiny mIoU under any shift, and its rPC of 1.0
    would call it the most robust of all."""
    w = np.asarray(weights, float)
    ci = g.conditions.index(clean)
    cm = np.einsum("rg,gcij->rcij", w, g.cm)
    inc_pl = np.asarray(include, bool) & supported(g.pl_reference, min_images, min_pixels)
    inc_gt = np.asarray(include, bool) & supported(g.gt_reference, min_images, min_pixels)
    out = {
        "xi_mean": mean_xi(np.einsum("rg,gck->rck", w, g.pl_retained), np.einsum("rg,gck->rck", w, g.pl_reference),
                           inc_pl, absent),
        "xi_gt_mean": mean_xi(np.einsum("rg,gck->rck", w, g.gt_retained), np.einsum("rg,gck->rck", w, g.gt_reference),
                              inc_gt, absent),
        "gt_miou": miou(cm),
    }
    out["gt_miou_clean"] = np.repeat(out["gt_miou"][:, ci : ci + 1], len(g.conditions), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rpc = out["gt_miou"] / out["gt_miou_clean"]
    out["rpc"] = np.where(out["gt_miou_clean"] >= rpc_floor, rpc, np.nan) if rpc_floor > 0 else rpc
    return out


def precision_measures(g: GroupCounts, weights: np.ndarray, include: np.ndarray, absent: str,
                       min_images: int = 0, min_pixels: int = 0) -> dict[str, np.ndarray]:
    """xi's precision and F class-wise means per (resample, condition) for group weights R x G, as evaluate's
    xi_precision.csv computes them (pairedgta/evaluation/xi_precision.py): the F over xi's mean classes (`include`
    and the pseudo-label's support), the precision over those of them whose predicted pixels have the same support
    (judged on the data and kept fixed across resamples, as xi's), a class never predicted in a resample skipped.
    NaN where the counts have no predicted pixels (an entry written before them)."""
    w = np.asarray(weights, float)
    if g.pl_predicted is None:
        nan = np.full((len(w), len(g.conditions)), np.nan)
        return {"xi_precision_mean": nan, "xi_f_mean": nan.copy()}
    retained = np.einsum("rg,gck->rck", w, g.pl_retained)
    reference = np.einsum("rg,gck->rck", w, g.pl_reference)
    predicted = np.einsum("rg,gck->rck", w, g.pl_predicted)
    inc_xi = np.asarray(include, bool) & supported(g.pl_reference, min_images, min_pixels)   # C x K
    inc_p = inc_xi & supported(g.pl_predicted, min_images, min_pixels)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {"xi_precision_mean": mean_xi(retained, predicted, inc_p, absent),
                "xi_f_mean": mean_xi(2.0 * retained, reference + predicted, inc_xi, absent)}


def defined_models(values: np.ndarray) -> np.ndarray:
    """M x C' point values (one resample) -> which models have a defined value in every cell: a target
    undefined for a model (rPC below the clean-mIoU floor) leaves that model out of the correlations with
    it, rather than making every correlation undefined."""
    return np.isfinite(np.asarray(values, float)).all(axis=-1)


def _rank(x: np.ndarray) -> np.ndarray:
    from scipy.stats import rankdata

    return rankdata(x, axis=-1)


def spearman_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Spearman's rho per row of R x N (average ranks for ties); NaN where a row is constant or has NaN."""
    x, y = np.atleast_2d(x).astype(float), np.atleast_2d(y).astype(float)
    bad = np.isnan(x).any(-1) | np.isnan(y).any(-1)
    rx, ry = _rank(np.nan_to_num(x)), _rank(np.nan_to_num(y))
    rx -= rx.mean(-1, keepdims=True)
    ry -= ry.mean(-1, keepdims=True)
    den = np.sqrt((rx * rx).sum(-1) * (ry * ry).sum(-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = (rx * ry).sum(-1) / den
    return np.where(bad | (den == 0), np.nan, rho)


def kendall_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Kendall's tau-b per row of R x N (as scipy.stats.kendalltau); NaN where undefined."""
    x, y = np.atleast_2d(x).astype(float), np.atleast_2d(y).astype(float)
    bad = np.isnan(x).any(-1) | np.isnan(y).any(-1)
    i, j = np.triu_indices(x.shape[-1], k=1)
    x, y = np.nan_to_num(x), np.nan_to_num(y)  # rows with NaN are NaN anyway (`bad`)
    sx, sy = np.sign(x[:, j] - x[:, i]), np.sign(y[:, j] - y[:, i])
    concord = (sx * sy).sum(-1)
    n0x, n0y = (sx != 0).sum(-1), (sy != 0).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = concord / np.sqrt(n0x * n0y)
    return np.where(bad | (n0x == 0) | (n0y == 0), np.nan, tau)


def _interval(boot: np.ndarray, confidence: float) -> tuple[float, float, int]:
    """Percentile interval of the defined resamples, and how many were defined. None is given (NaN)
    where fewer than half the resamples define the statistic or they do not vary: a zero-width
    interval would claim a certainty that the data cannot give."""
    ok = boot[np.isfinite(boot)]
    if ok.size < max(2, boot.size // 2) or np.ptp(ok) <= 1e-12:
        return math.nan, math.nan, int(ok.size)
    alpha = (1 - confidence) / 2
    return float(np.quantile(ok, alpha)), float(np.quantile(ok, 1 - alpha)), int(ok.size)


def validity(models: list[GroupCounts], clean: str, include: np.ndarray, absent: str = "nan",
             resamples: int = 1000, confidence: float = 0.95, seed: int = 0, min_images: int = 0,
             min_pixels: int = 0, rpc_floor: float = 0.0) -> tuple[list[dict], list[dict]]:
    """-> (cells, correlations). `cells`: one row per (model, adverse condition) with every measure and
    its bootstrap interval. `correlations`: Spearman and Kendall between label-free mean xi and each
    target (rPC, GT mIoU, xi against GT) across models within each adverse condition, and over every
    cell pooled, each with a paired bootstrap interval over groups; over the models whose target is defined
    in the scope's cells (`n_models`; `n_undefined` left out, e.g. rPC below `rpc_floor`)."""
    if not models:
        return [], []
    conds = models[0].conditions
    n = models[0].pl_retained.shape[0]
    for m in models:
        if m.conditions != conds or m.pl_retained.shape[0] != n:
            raise ValueError(f"model {m.model}: evaluated on other groups or conditions than {models[0].model}")
        # the same number of groups is not the same groups: a paired bootstrap needs group g to be one scene
        if m.group_ids and models[0].group_ids and m.group_ids != models[0].group_ids:
            first = next(i for i, (a, b) in enumerate(zip(m.group_ids, models[0].group_ids)) if a != b)
            raise ValueError(f"model {m.model}: group {m.group_ids[first]!r} where {models[0].model} has "
                             f"{models[0].group_ids[first]!r} (position {first}): the models were evaluated on other groups")
    if clean not in conds:
        raise ValueError(f"the clean condition {clean} was not evaluated")
    adverse = [i for i, c in enumerate(conds) if c != clean]
    support = (min_images, min_pixels, rpc_floor)
    point = [cell_measures(m, np.ones((1, n)), clean, include, absent, *support) for m in models]
    w = resample_weights(n, resamples, seed).astype(float)
    boot = [cell_measures(m, w, clean, include, absent, *support) for m in models]
    cells = []
    for m, p, b in zip(models, point, boot):
        for i in adverse:
            row: dict = {"model": m.model, "condition": conds[i], "n_groups": n}
            for k in MEASURES:
                lo, hi, _ = _interval(b[k][:, i], confidence)
                row.update({k: float(p[k][0, i]), f"{k}_ci_low": lo, f"{k}_ci_high": hi})
            cells.append(row)
    # model x resample x condition arrays of each measure
    stack = {k: np.stack([b[k] for b in boot]) for k in MEASURES}
    pstack = {k: np.stack([p[k] for p in point]) for k in MEASURES}
    corr = []
    scopes = [(conds[i], [i]) for i in adverse] + [("pooled", adverse)]
    for scope, idx in scopes:
        for target in TARGETS:
            keep = defined_models(pstack[target][:, 0, idx])
            n_defined = int(keep.sum())
            if n_defined < 3:  # two models rank-correlate at +-1: no statistic (their NaN targets make it NaN)
                keep = np.ones_like(keep)
            x = pstack["xi_mean"][keep][:, 0, idx].T.reshape(1, -1)   # condition-major: cells of the scope
            y = pstack[target][keep][:, 0, idx].T.reshape(1, -1)
            bx = stack["xi_mean"][keep][:, :, idx].transpose(1, 2, 0).reshape(len(w), x.shape[1])
            by = stack[target][keep][:, :, idx].transpose(1, 2, 0).reshape(len(w), x.shape[1])
            row = {"scope": scope, "target": target, "n_models": n_defined, "n_undefined": len(models) - n_defined,
                   "n_cells": x.shape[1], "n_groups": n}
            for name, fn in (("spearman", spearman_rows), ("kendall", kendall_rows)):
                lo, hi, defined = _interval(fn(bx, by), confidence)
                row.update({name: float(fn(x, y)[0]), f"{name}_ci_low": lo, f"{name}_ci_high": hi,
                            f"{name}_defined_resamples": defined})
            row["resamples"] = len(w)
            corr.append(row)
    return cells, corr


__all__ = ["GroupCounts", "concat_groups", "stack_passes", "cell_measures", "precision_measures", "validity", "spearman_rows", "kendall_rows", "miou",
           "mean_xi", "supported", "defined_models", "MEASURES", "TARGETS"]
