"""One model's evaluate entry from its groups' counts: the counts summed through the metrics' own
update_counts/compute, percentile-bootstrap intervals over images, and every file of the entry. The
file names live here (`EvaluateResult` reads the entry by them), so no other module names them."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.datasets import PairedDataset
from pairedgta.evaluation.counting import CONF_BINS, GT, PSEUDO_LABEL
from pairedgta.evaluation.inputs import sampled_conditions
from pairedgta.jsonio import write_json
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

log = logging.getLogger("pairedgta.evaluate")

XI, AGREEMENT, FRAME_COUNTS, RHO_VALID, GT_IOU = ("xi.csv", "pixel_agreement.csv", "frame_counts.csv", "rho_valid.csv",
                                                  "gt_iou.csv")
SUMMARY, GROUP_COUNTS, PREDICTIONS, ESTIMATORS = "summary.json", "group_counts.npz", "predictions.npz", "estimators.csv"
RESULT_FILES = (XI, AGREEMENT, FRAME_COUNTS, RHO_VALID, GT_IOU, SUMMARY, GROUP_COUNTS, ESTIMATORS)  # the entry's tables


@dataclass(frozen=True)
class ModelEvaluation:
    """What one model's entry is written from: its groups' counts (`counting.group_counts`, in dataset
    order) and what names and settles the numbers."""

    dataset: str
    model: str
    reference_model: str  # the pseudo-labels' model
    conditions: list[str]
    settings: dict[str, Any]  # evaluation.settings.metric_settings
    groups: list[dict[str, Any]]
    coverage: dict[str, Any]  # `coverage`: how many groups each condition averages over


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


def write_outputs(out: Path, e: ModelEvaluation) -> dict[str, Any]:
    """Every file of the entry into `out`; returns the build's extra result (the mean xi per condition)."""
    s, conv = e.settings, e.settings["convention"]
    arrays = write_group_counts(out / GROUP_COUNTS, e.groups, e.conditions)
    write_predictions(out / PREDICTIONS, e.groups, e.conditions)
    estimators = write_estimators(out, e.model, e.conditions, s, arrays)
    summary: dict[str, Any] = {"model": e.model, "reference_model": e.reference_model, "dataset": e.dataset,
                               "convention": conv, "sampling": s["sampling"], "min_transmittance": s["min_transmittance"],
                               "xi_mean": {}, "xi_mean_gt": {}, "rho_valid": {}, "rho_valid_headline": {},
                               "gt_miou": {}, "agreement": {}, "n_pairs": {}, **e.coverage, "estimators": estimators}
    if s["sampling"] == "random_one":
        summary["sampling_seed"] = s["sampling_seed"]
    write_xi(out, e, summary)
    write_agreement(out, e, summary)
    write_rho_valid(out, e, summary)
    write_gt_iou(out, e, summary)
    write_json(out / SUMMARY, summary)
    return {"xi_mean": summary["xi_mean"]}


def write_xi(out: Path, e: ModelEvaluation, summary: dict[str, Any]) -> None:
    """xi.csv: xi per (reference source, condition, class) pooled over images, its interval, and the
    class-wise mean under the convention with its own interval."""
    s, conv = e.settings, e.settings["convention"]
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
    when none has)."""
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
        for k in range(NUM_CLASSES):
            rows.append({"model": e.model, "condition": cond, "class_id": k, "class_name": CLASS_NAMES[k], "iou": iou[k]})
        miou = confusion[cond].miou()
        rows.append({"model": e.model, "condition": cond, "class_id": -1, "class_name": "mean", "iou": miou})
        summary["gt_miou"][cond] = miou
    pd.DataFrame(rows).to_csv(out / GT_IOU, index=False)


def write_estimators(out: Path, model: str, conditions: list[str], s: dict[str, Any],
                     arrays: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """estimators.csv: per condition the label-free estimators of this model (pairedgta.metrics.estimators;
    the committee agreement and ALine need the other models and are computed where they meet, the `estimators`
    figure) beside xi and the
    ground-truth targets where labels exist. AC, entropy and plain agreement use no label; DoC, ATC and the
    clean mIoU use the clean condition's ground truth, as their methods use labelled source data."""
    from pairedgta.metrics.estimators import EstimatorCounts, model_values
    from pairedgta.metrics.validity import GroupCounts

    clean, conv = s["clean"], s["convention"]
    n = len(arrays["group_id"])
    if clean not in conditions or not n:
        return {}
    g, c = GroupCounts.from_arrays(model, arrays), EstimatorCounts.from_arrays(model, arrays)
    include = mean_mask(NUM_CLASSES, CLASS_NAMES, conv["mean_exclude"])
    values = model_values(g, c, np.ones((1, n)), clean, include, conv["absent"], conv["min_images"], conv["min_pixels"],
                          conv.get("rpc_min_clean_miou", 0.0))
    rows = {cond: {"model": model, "condition": cond,
                   **{k: float(v[0, i]) for k, v in values.items() if k != "atc_threshold"},
                   "atc_threshold": float(values["atc_threshold"][0])} for i, cond in enumerate(conditions)}
    pd.DataFrame(list(rows.values())).to_csv(out / ESTIMATORS, index=False)
    return {cond: {k: v for k, v in r.items() if k not in ("model", "condition")} for cond, r in rows.items()}


def write_group_counts(path: Path, results: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
    """What a paired bootstrap over groups needs, per group g and condition i: `present[g, i]`; for each
    reference source (`pseudo_label`, `ground_truth`) the retained and reference pixels per class
    (`<source>_retained[g, i, c]`, `<source>_reference[g, i, c]`); the confusion matrix against the
    condition's own labels (`cm[g, i, truth, prediction]`, with `cm_present[g, i]`); and the label-free
    estimators' sums (`est_*`). No pickle is needed to read it back."""
    G, C = len(results), len(conditions)
    arrays: dict[str, np.ndarray] = {
        "group_id": np.array([str(r["group_id"]) for r in results], dtype=str),
        "conditions": np.array(conditions, dtype=str),
        "present": np.zeros((G, C), dtype=bool), "cm_present": np.zeros((G, C), dtype=bool),
        "cm": np.zeros((G, C, NUM_CLASSES, NUM_CLASSES), dtype=np.int64),
    }
    for source in (PSEUDO_LABEL, GT):
        arrays[f"{source}_retained"] = np.zeros((G, C, NUM_CLASSES), dtype=np.int64)
        arrays[f"{source}_reference"] = np.zeros((G, C, NUM_CLASSES), dtype=np.int64)
    arrays.update({"est_pixels": np.zeros((G, C), dtype=np.int64), "est_conf_sum": np.zeros((G, C)),
                   "est_entropy_sum": np.zeros((G, C)), "est_conf_hist": np.zeros((G, C, CONF_BINS), dtype=np.int64),
                   "est_agree_clean": np.zeros((G, C), dtype=np.int64)})
    index = {c: i for i, c in enumerate(conditions)}
    for g, r in enumerate(results):
        for cond, e in (r.get("estimators") or {}).items():
            if cond in index:
                for k in ("pixels", "conf_sum", "entropy_sum", "conf_hist", "agree_clean"):
                    arrays[f"est_{k}"][g, index[cond]] = e[k]
        for key, (retained, reference) in r["xi"].items():
            source, cond = key.split("|", 1)
            if cond in index:
                arrays["present"][g, index[cond]] = True
                arrays[f"{source}_retained"][g, index[cond]] = retained
                arrays[f"{source}_reference"][g, index[cond]] = reference
        for cond, mat in r["cm"].items():
            if cond in index:
                arrays["cm_present"][g, index[cond]] = True
                arrays["cm"][g, index[cond]] = np.asarray(mat, dtype=np.int64)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return arrays


def write_predictions(path: Path, results: list[dict[str, Any]], conditions: list[str]) -> None:
    """Every group's predicted label maps (`g<index>`: C x H x W uint8, 255 where the condition's image is
    absent), so that estimators comparing models pixel by pixel (agreement between models, ALine) need no
    second inference pass. Label maps compress well: a few kB per image."""
    arrays: dict[str, np.ndarray] = {"group_id": np.array([str(r["group_id"]) for r in results], dtype=str),
                                     "conditions": np.array(conditions, dtype=str)}
    for g, r in enumerate(results):
        maps = r.get("pred") or {}
        if not maps:
            continue
        shape = next(iter(maps.values())).shape
        stack = np.full((len(conditions), *shape), IGNORE_INDEX, dtype=np.uint8)
        for i, cond in enumerate(conditions):
            if cond in maps:
                stack[i] = maps[cond]
        arrays[f"g{g:05d}"] = stack
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def coverage(dataset: PairedDataset, conditions: list[str], clean: str, model: str, sampling: str = "all",
             sampling_seed: int = 0) -> dict[str, Any]:
    """How many groups each condition's numbers average over (under evaluate.sampling=random_one, the
    groups that drew it); a warning when missing images make the conditions' groups differ."""
    groups = {c: 0 for c in conditions}
    available = dict(groups)
    without_clean = 0
    for g in dataset.groups:
        if clean not in g.images:
            without_clean += 1
            continue
        present = [c for c in conditions if c in g.images]
        for c in present:
            available[c] += 1
        for c in sampled_conditions(g.group_id, [clean] + [c for c in present if c != clean], clean, sampling, sampling_seed):
            groups[c] += c in groups
    if without_clean or len(set(available.values())) > 1:
        log.warning("evaluate [%s]: conditions are averaged over different groups: %s%s (a missing image "
                    "leaves its group out of that condition only; see summary.json groups_per_condition)",
                    model, ", ".join(f"{c} {n}" for c, n in groups.items()),
                    f"; {without_clean} group(s) without the clean image {clean} skipped" if without_clean else "")
    return {"groups_per_condition": groups, "groups_without_clean": without_clean}
