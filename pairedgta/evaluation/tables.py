"""The evaluate entry's built-in metrics, one class each (`pairedgta/evaluation/metric.py` says what a metric
declares; `registry.METRICS` lists them): xi, pixel agreement, phi and rho_valid, ground-truth IoU and the
label-free estimators' sums. Per metric its device reduction (`update`), its per-group record, its arrays of
group_counts.npz and its tables, computed through the metrics' own update_counts/compute with
percentile-bootstrap intervals over images. The file names live here (`EvaluateResult` reads the entry through
the registry), so no other module names them."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.evaluation import reductions
from pairedgta.evaluation.metric import GT, PSEUDO_LABEL, Group, GroupContext, Metric, ModelEvaluation, per_condition
from pairedgta.evaluation.reductions import CONF_BINS
from pairedgta.lazy import lazy_module
from pairedgta.metrics import (
    ConfusionMatrix,
    ReferenceConsistency,
    aggregate_agreement,
    class_mean,
    mean_mask,
    ratio_ci,
)
from pairedgta.metrics.bootstrap import class_mean_ci, drop_zero_width
from pairedgta.metrics.conventions import support_mask
from pairedgta.metrics.ranking import rho_rows as rho_valid_rows

torch = lazy_module("torch")  # imported on first use: a cached run needs none

XI, AGREEMENT, FRAME_COUNTS, RHO_VALID, GT_IOU = ("xi.csv", "pixel_agreement.csv", "frame_counts.csv", "rho_valid.csv",
                                                  "gt_iou.csv")
ESTIMATORS = "estimators.csv"


class ConsistencyCounts:
    """xi of one (reference source, condition): the metric, fed through its own `update_counts`, and the
    per-image counts its bootstrap resamples."""

    def __init__(self, absent: str) -> None:
        self.metric = ReferenceConsistency(NUM_CLASSES, IGNORE_INDEX, absent)
        self.retained: list[np.ndarray] = []
        self.reference: list[np.ndarray] = []

    def add(self, retained: Any, reference: Any) -> None:
        retained, reference = np.asarray(retained, dtype=np.int64), np.asarray(reference, dtype=np.int64)
        self.metric.update_counts(retained, reference)
        self.retained.append(retained)
        self.reference.append(reference)


def write_xi(out: Path, e: ModelEvaluation, summary: dict[str, Any]) -> None:
    """xi.csv: xi per (reference source, condition, class) pooled over images, its interval, and the
    class-wise mean under the convention with its own interval.

    A class the model cannot predict (`e.unpredictable`: its label space maps no output channel to it) has xi
    and interval NaN, not the 0 its reference pixels would give, `in_mean` False and `reason`
    `cannot predict (label space <space>)` (the column exists only in such an entry, empty on the other rows):
    the mean and its interval are over the classes the model can predict (summary.json's
    `unpredictable_classes` names the ones left out)."""
    s, conv = e.settings, e.settings["convention"]
    blind = e.blind()
    xi_counts: dict[tuple[str, str], ConsistencyCounts] = {}
    for r in e.groups:
        for key, (retained, reference) in r["xi"].items():
            source, cond = key.split("|", 1)
            xi_counts.setdefault((source, cond), ConsistencyCounts(conv["absent"])).add(retained, reference)
    in_mean = mean_mask(NUM_CLASSES, CLASS_NAMES, conv["mean_exclude"])
    rows = []
    for (source, cond), a in sorted(xi_counts.items(), key=lambda kv: (kv[0][0], e.conditions.index(kv[0][1]))):
        xi = a.metric.compute().numpy()
        retained, reference = np.stack(a.retained), np.stack(a.reference)
        ref_total, ret_total = reference.sum(axis=0), retained.sum(axis=0)
        lo, hi = ratio_ci(retained, reference, s["resamples"], s["confidence"], s["seed"], conv["absent"])
        images = (reference > 0).sum(axis=0)
        if conv["absent"] == "nan":
            # a class seen in one image: every resample that defines it gives the same ratio, so the
            # bootstrap cannot vary and a zero-width interval would claim certainty
            lo, hi = np.where(images < 2, np.nan, lo), np.where(images < 2, np.nan, hi)
        lo, hi = drop_zero_width(lo, hi)
        if blind.any():  # not a measured 0: the model has no output for these classes
            xi, lo, hi = np.array(xi), np.array(lo), np.array(hi)
            xi[blind], lo[blind], hi[blind] = np.nan, np.nan, np.nan
        supported = support_mask(images, ref_total, conv["min_images"], conv["min_pixels"])
        ref_name = e.reference_model if source == PSEUDO_LABEL else GT
        # which classes the mean covers: the convention's classes, minus the undefined (NaN) and unsupported ones
        included = in_mean & ~np.isnan(xi) & supported
        common = {"model": e.model, "reference_model": ref_name, "condition": cond}
        for k in range(NUM_CLASSES):
            rows.append({
                **common, "class_id": k, "class_name": CLASS_NAMES[k], "xi": xi[k], "ci_low": lo[k], "ci_high": hi[k],
                "reference_pixels": int(ref_total[k]), "retained_pixels": int(ret_total[k]),
                "images": int(images[k]), "supported": bool(supported[k]),
                "in_mean": bool(included[k]), "n_pairs": len(a.retained), "convention": conv["name"],
                "min_transmittance": s["min_transmittance"], "classes": 1 if included[k] else 0,
                **({"reason": e.blind_reason() if blind[k] else ""} if blind.any() else {}),
            })
        mean = class_mean(xi, included)
        mlo, mhi = drop_zero_width(*class_mean_ci(retained, reference, included, s["resamples"], s["confidence"],
                                                  s["seed"], conv["absent"]))
        rows.append({
            **common, "class_id": -1, "class_name": "mean", "xi": mean, "ci_low": mlo, "ci_high": mhi,
            "reference_pixels": int(ref_total.sum()), "retained_pixels": int(ret_total.sum()),
            "images": len(a.retained), "supported": bool(included.any()), "in_mean": False, "n_pairs": len(a.retained),
            "convention": conv["name"], "min_transmittance": s["min_transmittance"],
            "classes": int(included.sum()),  # how many classes the mean covers
            **({"reason": ""} if blind.any() else {}),
        })
        summary["xi_mean" if source == PSEUDO_LABEL else "xi_mean_gt"][cond] = mean
        if source == PSEUDO_LABEL or not summary["n_pairs"].get(cond):
            summary["n_pairs"][cond] = len(a.retained)
    pd.DataFrame(rows).to_csv(out / XI, index=False)


def write_agreement(out: Path, e: ModelEvaluation, summary: dict[str, Any]) -> None:
    """pixel_agreement.csv: per image the agreement with the pseudo-label and with the clean prediction,
    and per condition an ALL row aggregated per the convention."""
    mode, name = e.settings["convention"]["agreement"], e.settings["convention"]["name"]
    rows = []
    for r in e.groups:
        for row in r["agreement"]:
            n = row["valid_pixels"]
            rows.append({**row, "agreement_reference": row["agree_reference_pixels"] / n if n else math.nan,
                         "agreement_clean": row["agree_clean_pixels"] / n if n else math.nan})
    agree = pd.DataFrame(rows)
    totals = []
    for cond, g in agree.groupby("condition", sort=False):
        n = g["valid_pixels"].sum()
        totals.append({
            "model": e.model, "condition": cond, "pair_id": "ALL", "valid_pixels": int(n),
            "agree_reference_pixels": int(g["agree_reference_pixels"].sum()),
            "agree_clean_pixels": int(g["agree_clean_pixels"].sum()),
            "agreement_reference": aggregate_agreement(g["agree_reference_pixels"], g["valid_pixels"], mode),
            "agreement_clean": aggregate_agreement(g["agree_clean_pixels"], g["valid_pixels"], mode),
        })
        summary["agreement"][cond] = totals[-1]["agreement_reference"]
    agree = pd.concat([agree, pd.DataFrame(totals)], ignore_index=True)
    # per-image rows are ratios of one image; the ALL row aggregates them per the convention
    agree["aggregation"] = np.where(agree["pair_id"] == "ALL", mode, "image")
    agree["convention"] = name
    agree.to_csv(out / AGREEMENT, index=False)


def write_rho_valid(out: Path, e: ModelEvaluation, summary: dict[str, Any]) -> None:
    """frame_counts.csv (phi per class, image and condition, clean and adverse) and rho_valid.csv (per
    class and condition, each frame selection, with its interval)."""
    s, conv = e.settings, e.settings["convention"]
    counts = pd.DataFrame([row for r in e.groups for row in r["counts"]],
                          columns=["dataset", "model", "class_name", "pair_id", "condition", "clean_count", "adv_count"])
    counts.to_csv(out / FRAME_COUNTS, index=False)
    rows = []
    for (cls, cond), g in counts.groupby(["class_name", "condition"], sort=False):
        for r in rho_valid_rows(g["clean_count"].to_numpy(), g["adv_count"].to_numpy(), s["selections"], s["m"],
                                s["resamples"], s["confidence"], s["seed"], conv["rho_headline"],
                                conv.get("rho_min_frames", 0)):
            rows.append({"dataset": e.dataset, "model": e.model, "class_name": cls, "condition": cond, **r,
                         "convention": conv["name"]})
            summary["rho_valid"].setdefault(cond, {}).setdefault(r["selection"], {})[cls] = r["rho"]
            if r["headline"]:
                summary["rho_valid_headline"].setdefault(cond, {})[cls] = r["rho"]
    pd.DataFrame(rows, columns=["dataset", "model", "class_name", "condition", "selection", "m", "n_frames", "rho",
                                "ci_low", "ci_high", "headline", "min_frames", "convention"]).to_csv(out / RHO_VALID, index=False)


def write_gt_iou(out: Path, e: ModelEvaluation, summary: dict[str, Any]) -> None:
    """gt_iou.csv: IoU per condition and class and the mIoU, where the condition has ground truth (no file
    when none has). A class the model cannot predict (`e.unpredictable`) has IoU NaN, not 0, with its
    `reason` (a column only such an entry has), and the mIoU is over the classes the model can predict."""
    blind = e.blind()
    confusion: dict[str, ConfusionMatrix] = {}
    for r in e.groups:
        for cond, mat in r["cm"].items():
            confusion.setdefault(cond, ConfusionMatrix(NUM_CLASSES)).update_counts(mat)
    if not confusion:
        return
    rows = []
    for cond in e.conditions:
        if cond not in confusion:
            continue
        iou = confusion[cond].iou().numpy()
        miou = confusion[cond].miou()
        reason = {}
        if blind.any():
            iou = iou.copy()
            iou[blind] = np.nan
            defined = ~np.isnan(iou)  # as ConfusionMatrix.miou: over TP + FP + FN > 0, here of the predictable
            miou = float(iou[defined].mean()) if defined.any() else math.nan
            reason = {k: e.blind_reason() if blind[k] else "" for k in range(NUM_CLASSES)}
            reason[-1] = ""  # the mean row
        for k in range(NUM_CLASSES):
            rows.append({"model": e.model, "condition": cond, "class_id": k, "class_name": CLASS_NAMES[k], "iou": iou[k],
                         **({"reason": reason[k]} if reason else {})})
        rows.append({"model": e.model, "condition": cond, "class_id": -1, "class_name": "mean", "iou": miou,
                     **({"reason": reason[-1]} if reason else {})})
        summary["gt_miou"][cond] = miou
    pd.DataFrame(rows).to_csv(out / GT_IOU, index=False)


ADDED_ESTIMATORS = ("xi_precision", "xi_f")  # estimators.csv's last columns (issue 64: xi's precision and F)


def write_estimators(out: Path, model: str, conditions: list[str], s: dict[str, Any],
                     arrays: dict[str, np.ndarray], blind: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """estimators.csv: per condition the label-free estimators of this model (pairedgta.metrics.estimators;
    the committee agreement and ALine need the other models and are computed where they meet, the `estimators`
    figure) beside xi (its class-wise mean without the classes in `blind`, those the model cannot predict,
    as xi.csv's) and the ground-truth targets where labels exist. AC, entropy and plain agreement use no label; DoC, ATC and the
    clean mIoU use the clean condition's ground truth, as their methods use labelled source data."""
    from pairedgta.metrics.estimators import EstimatorCounts, model_values
    from pairedgta.metrics.validity import GroupCounts

    clean, conv = s["clean"], s["convention"]
    n = len(arrays["group_id"])
    if clean not in conditions or not n:
        return {}
    g, c = GroupCounts.from_arrays(model, arrays), EstimatorCounts.from_arrays(model, arrays)
    include = mean_mask(NUM_CLASSES, CLASS_NAMES, conv["mean_exclude"])
    if blind is not None and np.any(blind):
        include = include & ~np.asarray(blind, bool)
    values = model_values(g, c, np.ones((1, n)), clean, include, conv["absent"], conv["min_images"], conv["min_pixels"],
                          conv.get("rpc_min_clean_miou", 0.0))
    later = ("atc_threshold", *ADDED_ESTIMATORS)  # after the columns of evaluate VERSION 8, as they were
    rows = {cond: {"model": model, "condition": cond,
                   **{k: float(v[0, i]) for k, v in values.items() if k not in later},
                   "atc_threshold": float(values["atc_threshold"][0])} for i, cond in enumerate(conditions)}
    # energy needs logits: a family whose output is already a distribution (Mask2Former) has none
    logits = {cond: bool(np.isfinite(values["energy"][0, i])) for i, cond in enumerate(conditions)}
    added = {cond: {k: float(values[k][0, i]) for k in ADDED_ESTIMATORS if "pseudo_label_predicted" in arrays}
             for i, cond in enumerate(conditions)}  # xi's precision and F where the entry counts what they need
    for cond, r in rows.items():
        r.update(added[cond])
    pd.DataFrame([{**{k: v for k, v in r.items() if k not in ADDED_ESTIMATORS}, "has_logits": logits[cond], **added[cond]}
                  for cond, r in rows.items()]).to_csv(out / ESTIMATORS, index=False)
    return {cond: {k: v for k, v in r.items() if k not in ("model", "condition")} for cond, r in rows.items()}


def _zeros(groups: list[dict[str, Any]], conditions: list[str], *shape: int, dtype: Any = np.int64) -> np.ndarray:
    return np.zeros((len(groups), len(conditions), *shape), dtype=dtype)


class Xi(Metric):
    """xi per (reference source, condition, class): retained and reference pixels per class and image."""

    name, version, files, summary_keys = "xi", "8", (XI,), ("xi_mean", "xi_mean_gt", "n_pairs")

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        out = {}
        if ctx.use_pl:
            out["xi_pl"] = reductions.xi_counts(ctx.pseudo_seen, ctx.labels, ctx.num_classes)
        if ctx.gt is not None:
            out["xi_gt"] = reductions.xi_counts(ctx.hide(ctx.gt.to(ctx.pseudo.dtype)), ctx.labels, ctx.num_classes)
        return out

    def record(self, host: dict[str, np.ndarray], group: Group) -> dict[str, list[list[int]]]:
        """Per "<source>|<condition>" [retained, reference] pixels per class."""
        out = {}
        for i, c in enumerate(group.conditions):
            for source, key, on in ((PSEUDO_LABEL, "xi_pl", group.use_pl), (GT, "xi_gt", group.has_gt)):
                if on:
                    counts = host[key][i]
                    out[f"{source}|{c}"] = [counts[:, 1].tolist(), counts.sum(axis=1).tolist()]
        return out

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        """`present[g, i]` and per source `<source>_retained[g, i, c]`, `<source>_reference[g, i, c]`."""
        arrays = {"present": _zeros(groups, conditions, dtype=bool)}
        for source in (PSEUDO_LABEL, GT):
            arrays[f"{source}_retained"] = _zeros(groups, conditions, NUM_CLASSES)
            arrays[f"{source}_reference"] = _zeros(groups, conditions, NUM_CLASSES)
        index = {c: i for i, c in enumerate(conditions)}
        for g, r in enumerate(groups):
            for key, (retained, reference) in r["xi"].items():
                source, cond = key.split("|", 1)
                if cond in index:
                    arrays["present"][g, index[cond]] = True
                    arrays[f"{source}_retained"][g, index[cond]] = retained
                    arrays[f"{source}_reference"][g, index[cond]] = reference
        return arrays

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        write_xi(out, e, summary)


class Agreement(Metric):
    """Per image the pseudo-label's valid pixels and those agreeing with it and with the clean prediction."""

    name, version, files, summary_keys = "agreement", "8", (AGREEMENT,), ("agreement",)

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        valid = ctx.valid
        return {"agreement": torch.stack([valid.sum((1, 2)), ((ctx.labels == ctx.pseudo_seen) & valid).sum((1, 2)),
                                          (ctx.same_clean & valid).sum((1, 2))], dim=1)}  # valid, agree ref, agree clean

    def record(self, host: dict[str, np.ndarray], group: Group) -> list[dict[str, Any]]:
        rows = []
        for i, c in enumerate(group.conditions):
            valid, agree_ref, agree_clean = (int(v) for v in host["agreement"][i])
            rows.append({"model": group.model, "condition": c, "pair_id": group.group_id, "valid_pixels": valid,
                         "agree_reference_pixels": agree_ref, "agree_clean_pixels": agree_clean})
        return rows

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        write_agreement(out, e, summary)


class RhoValid(Metric):
    """phi per (image, adverse condition, class) of the condition's and the clean prediction, and rho_valid."""

    name, version, field = "rho_valid", "8", "counts"
    files, summary_keys = (FRAME_COUNTS, RHO_VALID), ("rho_valid", "rho_valid_headline")

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        """phi of condition c over the pixels visible in c: of c's prediction and of the clean prediction."""
        confident = ctx.confidence >= ctx.tau
        clean_confident = confident[ctx.clean].unsqueeze(0).expand_as(confident)
        if ctx.visible is not None:
            confident, clean_confident = confident & ctx.visible, clean_confident & ctx.visible
        return {"adv_mass": reductions.class_counts(ctx.labels, confident, ctx.num_classes),
                "clean_mass": reductions.class_counts(ctx.clean_labels.expand_as(ctx.labels), clean_confident,
                                                      ctx.num_classes)}

    def record(self, host: dict[str, np.ndarray], group: Group) -> list[dict[str, Any]]:
        rows = []
        for i, c in enumerate(group.conditions):
            if i == group.clean:
                continue
            clean_mass, adv_mass = host["clean_mass"][i], host["adv_mass"][i]
            for k in group.settings["class_ids"]:
                rows.append({"dataset": group.dataset, "model": group.model, "class_name": CLASS_NAMES[k],
                             "pair_id": group.group_id, "condition": c, "clean_count": int(clean_mass[k]),
                             "adv_count": int(adv_mass[k])})
        return rows

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        write_rho_valid(out, e, summary)


class GtIoU(Metric):
    """The confusion matrix of each condition with ground truth, against it: IoU and mIoU."""

    name, version, field, files, summary_keys = "gt_iou", "8", "cm", (GT_IOU,), ("gt_miou",)

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        if ctx.targets is None:
            return {}
        targets = ctx.targets if ctx.visible is None else torch.where(ctx.visible, ctx.targets, ctx.void)
        return {"cm": reductions.confusion(targets, ctx.labels, ctx.num_classes)}

    def record(self, host: dict[str, np.ndarray], group: Group) -> dict[str, list]:
        return {c: host["cm"][i].tolist() for i, c in enumerate(group.conditions) if group.has_target[i]}

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        """`cm[g, i, truth, prediction]` against the condition's own labels, with `cm_present[g, i]`."""
        arrays = {"cm_present": _zeros(groups, conditions, dtype=bool),
                  "cm": _zeros(groups, conditions, NUM_CLASSES, NUM_CLASSES)}
        for g, i, mat in per_condition(groups, "cm", conditions):
            arrays["cm_present"][g, i] = True
            arrays["cm"][g, i] = np.asarray(mat, dtype=np.int64)
        return arrays

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        write_gt_iou(out, e, summary)


EST_KEYS = ("pixels", "conf_sum", "entropy_sum", "conf_hist", "agree_clean")


class Estimators(Metric):
    """The label-free estimators' sums per image (pairedgta.metrics.estimators) and estimators.csv."""

    # 10: xi_precision, xi_f columns (from xi_precision's counts); 9: ATC over labelled pixels
    name, version, files, summary_keys = "estimators", "10", (ESTIMATORS,), ("estimators",)

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        out = {"conf_hist": reductions.confidence_histogram(ctx.confidence), "agree_clean": ctx.same_clean.sum((1, 2)),
               "conf_blocks": reductions.block_sums(ctx.confidence), "entropy_blocks": reductions.block_sums(ctx.entropy)}
        if ctx.labelled is not None:  # ATC's share over the pixels its accuracy counts
            out["conf_hist_labelled"] = reductions.confidence_histogram(ctx.confidence, ctx.labelled)
        return out

    def record(self, host: dict[str, np.ndarray], group: Group) -> dict[str, dict[str, Any]]:
        h, w = group.shape
        out = {c: {"pixels": int(h * w), "conf_sum": reductions.ordered_sum(host["conf_blocks"][i]),
                   "entropy_sum": reductions.ordered_sum(host["entropy_blocks"][i]),
                   "conf_hist": host["conf_hist"][i].tolist(), "agree_clean": int(host["agree_clean"][i])}
               for i, c in enumerate(group.conditions)}
        if "conf_hist_labelled" in host:
            for i, c in enumerate(group.conditions):
                out[c]["conf_hist_labelled"] = host["conf_hist_labelled"][i].tolist()
        return out

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        """The sums `est_*[g, i]` (the histograms `est_conf_hist[g, i, bin]`, and of the labelled pixels
        `est_conf_hist_labelled` where there is ground truth)."""
        arrays = {"est_pixels": _zeros(groups, conditions), "est_conf_sum": _zeros(groups, conditions, dtype=float),
                  "est_entropy_sum": _zeros(groups, conditions, dtype=float),
                  "est_conf_hist": _zeros(groups, conditions, CONF_BINS), "est_agree_clean": _zeros(groups, conditions),
                  "est_conf_hist_labelled": _zeros(groups, conditions, CONF_BINS)}
        for g, i, e in per_condition(groups, "estimators", conditions):
            for k in (*EST_KEYS, "conf_hist_labelled"):
                if k in e:
                    arrays[f"est_{k}"][g, i] = e[k]
        if not any("conf_hist_labelled" in e for _, _, e in per_condition(groups, "estimators", conditions)):
            del arrays["est_conf_hist_labelled"]  # no ground truth: ATC has no accuracy to fit to
        return arrays

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        summary["estimators"] = write_estimators(out, e.model, e.conditions, e.settings, arrays, e.blind())
