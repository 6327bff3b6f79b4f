"""Evaluate stage, per model: xi per condition and class (eq. class_reference_consistency), pixel
agreement, phi per image and class (eq. prediction_mass) and rho_valid (eq. valid_spearman), with
percentile-bootstrap intervals over images; ground-truth IoU per condition where that condition's
labels exist (or the reference's, when only the reference is labelled) and xi-vs-ground-truth only
where the reference condition itself is labelled.

Streaming: per image only a few per-class counts are kept (for the bootstrap and for rho), never
predictions, so memory does not grow with the image size times the number of images.
"""
from __future__ import annotations

import csv
import logging
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES, class_id
from pairedgta.datasets import PairedDataset, load_group_images, load_label
from pairedgta.errors import ConfigError, DataError
from pairedgta.metrics.bootstrap import spearman_ci
from pairedgta.metrics import (
    SELECTIONS,
    ConfusionMatrix,
    ReferenceConsistency,
    prediction_mass_from_labels,
    ratio_ci,
    select_frames,
    spearman,
)
from pairedgta.models import build_segmenter
from pairedgta.jsonio import write_json
from pairedgta.stages.common import Context, StageResult, inference_threads, model_hash_config, run_cached, torch_threads
from pairedgta.stages.pseudolabel import label_path

log = logging.getLogger("pairedgta.evaluate")
VERSION = "1"
GT = "ground_truth"


class _Accumulator:
    """Per (reference source, condition): streaming xi plus the per-image counts the bootstrap needs."""

    def __init__(self) -> None:
        self.metric = ReferenceConsistency(NUM_CLASSES, IGNORE_INDEX)
        self.retained: list[np.ndarray] = []
        self.reference: list[np.ndarray] = []

    def update(self, ref: torch.Tensor, pred: torch.Tensor) -> None:
        retained, reference = self.metric.update(ref, pred)
        self.retained.append(retained.numpy().astype(np.int64))
        self.reference.append(reference.numpy().astype(np.int64))


def metric_settings(cfg: dict[str, Any], grid_names: list[str], reference: str) -> dict[str, Any]:
    metric = cfg["metric"]
    rho = metric.get("rho") or {}
    selections = list(rho.get("selections") or SELECTIONS)
    bad = [s for s in selections if s not in SELECTIONS]
    if bad:
        raise ConfigError(f"metric.rho.selections: unknown {bad}; use {list(SELECTIONS)}")
    classes = rho.get("classes")
    class_ids = list(range(NUM_CLASSES)) if not classes else [class_id(c) for c in classes]
    tau = float(metric.get("tau_mass", 0.9))
    if not 0.0 <= tau <= 1.0:
        raise ConfigError(f"metric.tau_mass={tau} must be in [0, 1]")
    m = int(rho.get("m", 25))
    if m < 1:
        raise ConfigError(f"metric.rho.m={m} must be >= 1")
    ref_mode = metric.get("reference", "both")
    if ref_mode not in ("pseudo_label", "ground_truth", "both"):
        raise ConfigError(f"metric.reference={ref_mode!r}; use pseudo_label, ground_truth or both")
    boot = metric.get("bootstrap") or {}
    clean = rho.get("clean_condition") or reference
    if clean not in grid_names:
        raise ConfigError(f"metric.rho.clean_condition={clean!r} is not a condition; known: {', '.join(grid_names)}")
    return {
        "tau_mass": tau, "m": m, "selections": selections, "class_ids": class_ids, "reference_mode": ref_mode,
        "resamples": int(boot.get("resamples", 1000)), "confidence": float(boot.get("confidence", 0.95)),
        "seed": int(boot.get("seed", 0)), "clean": clean,
    }


def compute(
    ctx: Context, dataset: PairedDataset, pseudo_dir: Path, model_cfg: dict[str, Any], conditions: list[str],
    reference_model: str, out: Path,
) -> dict[str, Any]:
    s = metric_settings(ctx.cfg, ctx.grid.names, dataset.reference)
    segmenter = build_segmenter(model_cfg)
    model = segmenter.name
    clean = s["clean"]
    order = [clean] + [c for c in conditions if c != clean]
    use_pl = s["reference_mode"] in ("pseudo_label", "both")
    use_gt = s["reference_mode"] in ("ground_truth", "both")
    acc: dict[tuple[str, str], _Accumulator] = {}
    gt_cm: dict[str, ConfusionMatrix] = {}
    agreement_rows: list[dict[str, Any]] = []
    count_rows: list[dict[str, Any]] = []
    batch = int(ctx.cfg["evaluate"].get("batch_size", 4))
    groups = {c: 0 for c in conditions}  # groups each condition's numbers average over
    without_clean = 0
    for group in tqdm(dataset.groups, desc=f"evaluate [{model}]", unit="group"):
        present = [c for c in order if c in group.images]
        if clean not in present:
            without_clean += 1
            continue
        for c in present:
            groups[c] = groups.get(c, 0) + 1
        images = load_group_images(group, present)
        shape = images[clean].shape[:2]
        pl_path = label_path(pseudo_dir, group.group_id)
        pseudo = load_label(pl_path)
        if pseudo.shape != shape:
            raise DataError(
                f"{pl_path}: pseudo-label is {pseudo.shape[1]}x{pseudo.shape[0]} but the images of group "
                f"{group.group_id} are {shape[1]}x{shape[0]}; rerun with force=[pseudolabel]"
            )
        pseudo_t = pseudo.astype(np.int64)
        gt_t = None
        if use_gt and dataset.reference in group.labels:
            gt = load_label(group.labels[dataset.reference])
            if gt.shape != shape:
                raise DataError(f"{group.labels[dataset.reference]}: label map size differs from its image")
            gt_t = gt.astype(np.int64)
        preds: dict[str, np.ndarray] = {}
        masses: dict[str, np.ndarray] = {}
        for start in range(0, len(present), batch):
            names = present[start : start + batch]
            labels, conf = segmenter.predict(np.stack([images[c] for c in names]))
            mass = prediction_mass_from_labels(labels, conf, NUM_CLASSES, s["tau_mass"]).numpy()
            labels = labels.numpy()
            for i, c in enumerate(names):
                preds[c] = labels[i]
                masses[c] = mass[i]
        for c in present:
            pred = preds[c]
            if use_pl:
                acc.setdefault(("pseudo_label", c), _Accumulator()).update(pseudo_t, pred)
            if gt_t is not None:
                acc.setdefault((GT, c), _Accumulator()).update(gt_t, pred)
            # IoU of condition c needs c's own truth; the reference's truth stands in only where the
            # dataset's labels are those of the reference frame (e.g. ACDC labels the adverse frame
            # only: they are never used as reference truth nor for the reference image)
            own = group.labels.get(c) if use_gt else None
            if own is not None:
                target = load_label(own).astype(np.int64)
                if target.shape != shape:
                    raise DataError(f"{own}: label map size differs from its image")
            else:
                target = gt_t
            if target is not None:
                gt_cm.setdefault(c, ConfusionMatrix(NUM_CLASSES)).update(target, pred)
            valid = pseudo_t != IGNORE_INDEX
            n_valid = int(valid.sum())
            agree_ref = int(((pred == pseudo_t) & valid).sum())
            agree_clean = int(((pred == preds[clean]) & valid).sum())
            agreement_rows.append({
                "model": model, "condition": c, "pair_id": group.group_id, "valid_pixels": n_valid,
                "agree_reference_pixels": agree_ref, "agree_clean_pixels": agree_clean,
                "agreement_reference": agree_ref / n_valid if n_valid else math.nan,
                "agreement_clean": agree_clean / n_valid if n_valid else math.nan,
            })
            if c != clean:
                for k in s["class_ids"]:
                    count_rows.append({
                        "dataset": dataset.name, "model": model, "class_name": CLASS_NAMES[k],
                        "pair_id": group.group_id, "condition": c,
                        "clean_count": int(masses[clean][k]), "adv_count": int(masses[c][k]),
                    })
        del images, preds
    coverage = {"groups_per_condition": groups, "groups_without_clean": without_clean}
    if without_clean or len(set(groups.values())) > 1:
        log.warning("evaluate [%s]: conditions are averaged over different groups: %s%s (a missing image "
                    "leaves its group out of that condition only; see summary.json groups_per_condition)",
                    model, ", ".join(f"{c} {n}" for c, n in groups.items()),
                    f"; {without_clean} group(s) without the clean image {clean} skipped" if without_clean else "")
    return write_outputs(out, dataset, model, reference_model, conditions, s, acc, gt_cm, agreement_rows, count_rows,
                         coverage)


def write_outputs(out, dataset, model, reference_model, conditions, s, acc, gt_cm, agreement_rows, count_rows,
                  coverage=None) -> dict[str, Any]:
    summary: dict[str, Any] = {"model": model, "reference_model": reference_model, "dataset": dataset.name,
                               "xi_mean": {}, "xi_mean_gt": {}, "rho_valid": {}, "gt_miou": {}, "agreement": {},
                               **(coverage or {})}
    xi_rows = []
    for (source, cond), a in sorted(acc.items(), key=lambda kv: (kv[0][0], conditions.index(kv[0][1]))):
        xi = a.metric.compute().numpy()
        lo, hi = ratio_ci(np.stack(a.retained), np.stack(a.reference), s["resamples"], s["confidence"], s["seed"])
        ref_name = reference_model if source == "pseudo_label" else GT
        for k in range(NUM_CLASSES):
            xi_rows.append({
                "model": model, "reference_model": ref_name, "condition": cond, "class_id": k,
                "class_name": CLASS_NAMES[k], "xi": xi[k], "ci_low": lo[k], "ci_high": hi[k],
                "reference_pixels": int(a.metric.reference[k]), "retained_pixels": int(a.metric.retained[k]),
            })
        # the class-wise mean over defined classes, with its own bootstrap over images
        defined = ~np.isnan(xi)
        mean = float(xi[defined].mean()) if defined.any() else math.nan
        mlo, mhi = _mean_ci(np.stack(a.retained), np.stack(a.reference), defined, s)
        xi_rows.append({
            "model": model, "reference_model": ref_name, "condition": cond, "class_id": -1, "class_name": "mean",
            "xi": mean, "ci_low": mlo, "ci_high": mhi,
            "reference_pixels": int(a.metric.reference.sum()), "retained_pixels": int(a.metric.retained.sum()),
        })
        summary["xi_mean" if source == "pseudo_label" else "xi_mean_gt"][cond] = mean
    pd.DataFrame(xi_rows).to_csv(out / "xi.csv", index=False)

    agree = pd.DataFrame(agreement_rows)
    pooled = []
    for cond, g in agree.groupby("condition", sort=False):
        n = g["valid_pixels"].sum()
        pooled.append({
            "model": model, "condition": cond, "pair_id": "ALL", "valid_pixels": int(n),
            "agree_reference_pixels": int(g["agree_reference_pixels"].sum()),
            "agree_clean_pixels": int(g["agree_clean_pixels"].sum()),
            "agreement_reference": g["agree_reference_pixels"].sum() / n if n else math.nan,
            "agreement_clean": g["agree_clean_pixels"].sum() / n if n else math.nan,
        })
        summary["agreement"][cond] = pooled[-1]["agreement_reference"]
    pd.concat([agree, pd.DataFrame(pooled)], ignore_index=True).to_csv(out / "pixel_agreement.csv", index=False)

    counts = pd.DataFrame(count_rows, columns=["dataset", "model", "class_name", "pair_id", "condition", "clean_count", "adv_count"])
    counts.to_csv(out / "frame_counts.csv", index=False)
    rho_rows = []
    for (cls, cond), g in counts.groupby(["class_name", "condition"], sort=False):
        clean_c = g["clean_count"].to_numpy()
        adv_c = g["adv_count"].to_numpy()
        for sel in s["selections"]:
            idx = select_frames(clean_c, s["m"], sel)
            x, y = clean_c[idx], adv_c[idx]
            rho = spearman(x, y)
            lo, hi = spearman_ci(x, y, s["resamples"], s["confidence"], s["seed"])
            rho_rows.append({
                "dataset": dataset.name, "model": model, "class_name": cls, "condition": cond, "selection": sel,
                "m": s["m"] if sel == "top_m" else math.nan, "n_frames": len(idx), "rho": rho, "ci_low": lo, "ci_high": hi,
            })
            summary["rho_valid"].setdefault(cond, {}).setdefault(sel, {})[cls] = rho
    pd.DataFrame(rho_rows, columns=["dataset", "model", "class_name", "condition", "selection", "m", "n_frames", "rho", "ci_low", "ci_high"]).to_csv(out / "rho_valid.csv", index=False)

    if gt_cm:
        rows = []
        for cond in conditions:
            if cond not in gt_cm:
                continue
            iou = gt_cm[cond].iou().numpy()
            for k in range(NUM_CLASSES):
                rows.append({"model": model, "condition": cond, "class_id": k, "class_name": CLASS_NAMES[k], "iou": iou[k]})
            miou = gt_cm[cond].miou()
            rows.append({"model": model, "condition": cond, "class_id": -1, "class_name": "mean", "iou": miou})
            summary["gt_miou"][cond] = miou
        pd.DataFrame(rows).to_csv(out / "gt_iou.csv", index=False)
    write_json(out / "summary.json", summary)
    return {"xi_mean": summary["xi_mean"]}


def _mean_ci(retained: np.ndarray, reference: np.ndarray, defined: np.ndarray, s: dict[str, Any]) -> tuple[float, float]:
    from pairedgta.metrics.bootstrap import resample_weights

    n = retained.shape[0]
    if n == 0 or s["resamples"] <= 0 or not defined.any():
        return math.nan, math.nan
    w = resample_weights(n, s["resamples"], s["seed"])
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        boot = (w @ retained[:, defined]) / (w @ reference[:, defined])
        means = np.nanmean(boot, axis=1)  # a class absent from a resample drops out of that mean
        alpha = (1 - s["confidence"]) / 2
        return float(np.nanquantile(means, alpha)), float(np.nanquantile(means, 1 - alpha))


def run(ctx: Context, dataset: PairedDataset, dataset_key: str, pseudo: StageResult, model_cfg: dict[str, Any]) -> StageResult:
    wanted = ctx.cfg["evaluate"].get("conditions")
    if wanted:
        unknown = [c for c in wanted if c not in ctx.grid.names]
        if unknown:
            raise ConfigError(f"evaluate.conditions: unknown condition(s) {unknown}; known: {', '.join(ctx.grid.names)}")
        conditions = [c for c in ctx.grid.names if c in wanted or c == dataset.reference]
    else:
        conditions = list(ctx.grid.names)
    settings = metric_settings(ctx.cfg, ctx.grid.names, dataset.reference)
    threads = inference_threads(ctx.cfg)
    config = {"model": model_hash_config(model_cfg), "metric": settings, "conditions": conditions, "threads": threads}
    reference_model = ctx.cfg["reference_model"]

    def build(out: Path) -> dict[str, Any]:
        with torch_threads(threads):
            return compute(ctx, dataset, pseudo.path, model_cfg, conditions, reference_model, out)

    return run_cached(ctx, "evaluate", VERSION, config, {"dataset": dataset_key, "pseudolabel": pseudo.key}, build,
                      label=f"[{model_cfg['name']}]")
