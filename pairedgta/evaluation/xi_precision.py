"""xi's precision counterpart as a registered metric (its class here, one line in `registry.METRICS`; issue 64).

xi is a recall: per class c, the share of the reference's valid pixels of class c (the pseudo-label's confident
clean pixels, or the true labels) that the model still predicts as c. A model that paints one class everywhere keeps
every reference pixel of that class and scores xi_c = 1 there. Its precision counterpart sees that side: among the
pixels the model predicts as c under the condition *and* that are valid reference pixels (the same mask xi counts),
the share whose reference is c. `xi_f` is their harmonic mean per class, from the counts 2 retained / (reference +
predicted) (`pairedgta.metrics.reference_consistency.f_from_counts`): 0 where nothing of c is retained.

Per group it keeps one more count per (reference source, condition, class), the pixels predicted as c on valid
reference pixels, in group_counts.npz (`pseudo_label_predicted`, `ground_truth_predicted`) beside xi's retained and
reference pixels, so shard jobs, the bootstrap over scenes and the estimator study resample it with them. It writes
`xi_precision.csv` (xi.csv's rows: per source, condition and class, then the class-wise mean) and the summary's
`xi_precision_mean`, `xi_f_mean` (against the pseudo-labels; `_gt` against the true labels). xi.csv is not touched.

Conventions, as xi's (`metric.absent`, `metric.min_images`, `metric.min_pixels`, `metric.mean_exclude`):
  * the F's mean is over exactly xi's mean classes (`in_mean` of xi.csv: the convention's classes with enough
    reference support, those the model can predict);
  * the precision of a class the model never predicts on valid pixels is undefined: NaN under the strict convention
    (0 under absent="zero"), with its `reason`; its mean is over xi's mean classes whose predicted pixels have the
    same support a class's reference pixels need (>= min_images images, >= min_pixels pixels), each row saying why it
    is left out;
  * percentile-bootstrap intervals over images (groups), as xi.csv's, with no interval for a class seen in one image
    and none of zero width."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.evaluation import reductions
from pairedgta.evaluation.metric import GT, PSEUDO_LABEL, Group, GroupContext, Metric, ModelEvaluation
from pairedgta.metrics import class_mean, f_from_counts, mean_mask, precision_from_counts, ratio_ci, xi_from_counts
from pairedgta.metrics.bootstrap import class_mean_ci, drop_zero_width
from pairedgta.metrics.conventions import support_mask

XI_PRECISION = "xi_precision.csv"
SOURCES = ((PSEUDO_LABEL, "pl"), (GT, "gt"))


def _interval(numer: np.ndarray, denom: np.ndarray, images: np.ndarray, s: dict[str, Any], absent: str):
    """xi.csv's per-class interval of sum(numer) / sum(denom) over the groups: none for a class seen in one image
    (under absent="nan") and none of zero width."""
    lo, hi = ratio_ci(numer, denom, s["resamples"], s["confidence"], s["seed"], absent)
    if absent == "nan":
        lo, hi = np.where(images < 2, np.nan, lo), np.where(images < 2, np.nan, hi)
    return drop_zero_width(lo, hi)


def precision_rows(retained: np.ndarray, reference: np.ndarray, predicted: np.ndarray, s: dict[str, Any],
                   blind: np.ndarray | None = None, blind_reason: str = "cannot predict") -> dict[str, Any]:
    """G x K per-group counts of one (source, condition) -> per class `xi`, `precision`, `f` with intervals, the
    supports, which classes each mean covers (`xi_in_mean`: xi.csv's `in_mean`; `precision_in_mean`), the `reason`
    a class is out of the precision's mean, and the two class-wise means with their intervals."""
    conv = s["convention"]
    absent = conv["absent"]
    blind = np.zeros(NUM_CLASSES, bool) if blind is None else np.asarray(blind, bool)
    ref_total, ret_total, pred_total = reference.sum(axis=0), retained.sum(axis=0), predicted.sum(axis=0)
    ref_images, pred_images = (reference > 0).sum(axis=0), (predicted > 0).sum(axis=0)
    xi = xi_from_counts(ret_total, ref_total, absent)
    precision = precision_from_counts(ret_total, pred_total, absent)
    f = f_from_counts(ret_total, ref_total, pred_total, absent)
    p_lo, p_hi = _interval(retained, predicted, pred_images, s, absent)
    f_lo, f_hi = _interval(2 * retained, reference + predicted, ((reference + predicted) > 0).sum(axis=0), s, absent)
    if blind.any():  # no output for these classes: not a measured 0 (as xi.csv)
        for a in (xi, precision, f, p_lo, p_hi, f_lo, f_hi):
            a[blind] = np.nan
    in_mean = mean_mask(NUM_CLASSES, CLASS_NAMES, conv["mean_exclude"])
    ref_supported = support_mask(ref_images, ref_total, conv["min_images"], conv["min_pixels"])
    xi_in = in_mean & ~np.isnan(xi) & ref_supported          # xi.csv's in_mean: the F's mean covers these
    pred_supported = support_mask(pred_images, pred_total, conv["min_images"], conv["min_pixels"])
    p_in = xi_in & ~np.isnan(precision) & pred_supported
    f_in = xi_in & ~np.isnan(f)
    reason = []
    for k in range(NUM_CLASSES):
        if blind[k]:
            why = blind_reason
        elif not xi_in[k]:
            why = "not in xi's mean"
        elif np.isnan(precision[k]):
            why = "not predicted on valid reference pixels"
        elif not pred_supported[k]:
            why = (f"predicted on too few pixels ({int(pred_total[k])} in {int(pred_images[k])} image(s); the mean "
                   f"needs >= {conv['min_pixels']} in >= {conv['min_images']})")
        else:
            why = ""
        reason.append(why)
    means = {}
    for key, values, numer, denom, include in (("precision", precision, retained, predicted, p_in),
                                               ("f", f, 2 * retained, reference + predicted, f_in)):
        lo, hi = drop_zero_width(*class_mean_ci(numer, denom, include, s["resamples"], s["confidence"], s["seed"],
                                                absent))
        means[key] = (class_mean(values, include), lo, hi, int(include.sum()))
    means["xi"] = (class_mean(xi, xi_in), np.nan, np.nan, int(xi_in.sum()))  # xi.csv's mean, for reading beside them
    return {"xi": xi, "precision": precision, "precision_ci": (p_lo, p_hi), "f": f, "f_ci": (f_lo, f_hi),
            "reference_pixels": ref_total, "retained_pixels": ret_total, "predicted_pixels": pred_total,
            "images": ref_images, "predicted_images": pred_images, "predicted_supported": pred_supported,
            "xi_in_mean": xi_in, "precision_in_mean": p_in, "reason": reason, "means": means}


def write_xi_precision(out: Path, e: ModelEvaluation, summary: dict[str, Any]) -> None:
    """xi_precision.csv: per (reference source, condition, class) xi (as xi.csv), its precision and their F with
    intervals, the counts behind them and which classes each mean covers; then per (source, condition) a `mean`
    row (`precision_classes`, `xi_f_classes`: how many classes each mean covers; its `xi` is xi.csv's mean). A class
    the model cannot predict is NaN with that `reason`, as in xi.csv."""
    s, conv = e.settings, e.settings["convention"]
    blind = e.blind()
    counts: dict[tuple[str, str], list[tuple[Any, Any, Any]]] = {}
    for r in e.groups:
        predicted = r.get("xi_precision") or {}
        for key, (retained, reference) in r["xi"].items():
            if key in predicted:
                source, cond = key.split("|", 1)
                counts.setdefault((source, cond), []).append((retained, reference, predicted[key]))
    rows = []
    for (source, cond), per_group in sorted(counts.items(), key=lambda kv: (kv[0][0], e.conditions.index(kv[0][1]))):
        retained, reference, predicted = (np.asarray([g[j] for g in per_group], dtype=np.int64) for j in range(3))
        t = precision_rows(retained, reference, predicted, s, blind, e.blind_reason())
        common = {"model": e.model, "reference_model": e.reference_model if source == PSEUDO_LABEL else GT,
                  "condition": cond}
        for k in range(NUM_CLASSES):
            rows.append({
                **common, "class_id": k, "class_name": CLASS_NAMES[k], "xi": t["xi"][k],
                "precision": t["precision"][k], "precision_ci_low": t["precision_ci"][0][k],
                "precision_ci_high": t["precision_ci"][1][k], "xi_f": t["f"][k], "xi_f_ci_low": t["f_ci"][0][k],
                "xi_f_ci_high": t["f_ci"][1][k], "reference_pixels": int(t["reference_pixels"][k]),
                "predicted_pixels": int(t["predicted_pixels"][k]), "retained_pixels": int(t["retained_pixels"][k]),
                "images": int(t["images"][k]), "predicted_images": int(t["predicted_images"][k]),
                "predicted_supported": bool(t["predicted_supported"][k]), "xi_in_mean": bool(t["xi_in_mean"][k]),
                "precision_in_mean": bool(t["precision_in_mean"][k]), "reason": t["reason"][k],
                "precision_classes": int(t["precision_in_mean"][k]), "xi_f_classes": int(t["xi_in_mean"][k]),
                "n_pairs": len(per_group), "convention": conv["name"], "min_transmittance": s["min_transmittance"],
            })
        (p, p_lo, p_hi, p_n), (f, f_lo, f_hi, f_n) = t["means"]["precision"], t["means"]["f"]
        rows.append({
            **common, "class_id": -1, "class_name": "mean", "xi": t["means"]["xi"][0], "precision": p,
            "precision_ci_low": p_lo, "precision_ci_high": p_hi, "xi_f": f, "xi_f_ci_low": f_lo, "xi_f_ci_high": f_hi,
            "reference_pixels": int(t["reference_pixels"].sum()), "predicted_pixels": int(t["predicted_pixels"].sum()),
            "retained_pixels": int(t["retained_pixels"].sum()), "images": len(per_group),
            "predicted_images": len(per_group), "predicted_supported": bool(p_n), "xi_in_mean": False,
            "precision_in_mean": False, "reason": "", "precision_classes": p_n, "xi_f_classes": f_n,  # the means cover
            "n_pairs": len(per_group), "convention": conv["name"], "min_transmittance": s["min_transmittance"],
        })
        suffix = "" if source == PSEUDO_LABEL else "_gt"
        summary[f"xi_precision_mean{suffix}"][cond] = p
        summary[f"xi_f_mean{suffix}"][cond] = f
    if rows:
        pd.DataFrame(rows).to_csv(out / XI_PRECISION, index=False)


class XiPrecision(Metric):
    """Per (reference source, condition, class) the pixels predicted as the class on the reference's valid pixels:
    with xi's retained and reference pixels, xi's precision and their F (module docstring)."""

    name, version, files = "xi_precision", "1", (XI_PRECISION,)
    summary_keys = ("xi_precision_mean", "xi_f_mean", "xi_precision_mean_gt", "xi_f_mean_gt")

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        out = {}
        if ctx.use_pl:
            out["pl"] = reductions.predicted_counts(ctx.pseudo_seen, ctx.labels, ctx.num_classes)
        if ctx.gt is not None:
            out["gt"] = reductions.predicted_counts(ctx.hide(ctx.gt.to(ctx.pseudo.dtype)), ctx.labels, ctx.num_classes)
        return out

    def record(self, host: dict[str, np.ndarray], group: Group) -> dict[str, list[int]]:
        """Per "<source>|<condition>" (the keys of xi's record) the predicted pixels per class."""
        out = {}
        for i, c in enumerate(group.conditions):
            for source, key in SOURCES:
                if key in host:
                    out[f"{source}|{c}"] = host[key][i].tolist()
        return out

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        """Per source `<source>_predicted[g, i, c]`, beside xi's `<source>_retained` and `<source>_reference`."""
        arrays = {f"{source}_predicted": np.zeros((len(groups), len(conditions), NUM_CLASSES), np.int64)
                  for source, _ in SOURCES}
        index = {c: i for i, c in enumerate(conditions)}
        for g, r in enumerate(groups):
            for key, predicted in (r.get(self.name) or {}).items():
                source, cond = key.split("|", 1)
                if cond in index:
                    arrays[f"{source}_predicted"][g, index[cond]] = predicted
        return arrays

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        write_xi_precision(out, e, summary)


__all__ = ["XI_PRECISION", "XiPrecision", "precision_rows", "write_xi_precision"]
