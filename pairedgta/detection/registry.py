"""Detection's metrics, listed once: each turns the stored detections (pairedgta/detection/inputs.py `Inputs`, built
by pairedgta/detection/evaluate.py) into its tables and its summary values. The stage's version, its files and the
MLflow view follow from METRICS; the math stays in pairedgta/metrics/ (detection_xi, coco_ap, corruption,
per_object)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import pandas as pd

from pairedgta import work
from pairedgta.detection.boxes import INSTANCE_CLASSES, NUM_INSTANCE_CLASSES, coco_categories
from pairedgta.metrics import bootstrap, coco_ap, corruption, detection_xi, per_object, ranking

if TYPE_CHECKING:
    from pairedgta.detection.inputs import Inputs

XI, GT_AP, ROBUSTNESS = "detection_xi.csv", "detection_ap.csv", "detection_robustness.csv"
OBJECTS, OBJECTS_FOUND = "detection_objects.csv", "detection_objects_found.csv"
FRAME_COUNTS, RHO_VALID = "detection_frame_counts.csv", "detection_rho_valid.csv"
ESTIMATORS = "detection_estimators.csv"  # per group and condition: BoS, pre-NMS consistency (detection.estimators)
GROUP_COUNTS = "detection_group_counts.csv"  # per group, condition and class: what scene resamples recompute xi from
Tables = tuple[dict[str, pd.DataFrame], dict[str, Any]]


@dataclass(frozen=True)
class DetectionMetric:
    name: str
    version: str
    files: tuple[str, ...]
    compute: Callable[["Inputs"], Tables]


def _pseudo_ground_truth(inputs: "Inputs") -> dict[str, Any]:
    """The reference's confident clean boxes as COCO ground truth (pseudo-AP)."""
    images, anns = [], []
    for g in inputs.groups:
        h, w = g.sizes.get(inputs.clean) or next(iter(g.sizes.values()))
        iid = inputs.image_ids[g.group_id]
        images.append({"id": iid, "width": w, "height": h})
        p = inputs.pseudo.get(g.group_id)
        for b, lab in zip(p.boxes if p is not None else [], p.labels if p is not None else []):
            anns.append({"id": len(anns) + 1, "image_id": iid, "category_id": int(lab) + 1, "iscrowd": 0,
                         "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
                         "area": float((b[2] - b[0]) * (b[3] - b[1]))})
    return {"images": images, "annotations": anns, "categories": coco_categories()}


def xi_tables(inputs: "Inputs") -> Tables:
    """Detection xi per class and condition with bootstrap intervals over groups, the support rule (NaN, marked),
    the precision side and pseudo-AP50; the mean over the supported classes."""
    s = inputs.settings
    boot = s["bootstrap"]
    pseudo_gt = _pseudo_ground_truth(inputs)
    rows, xi_mean, pap, prec, support = [], {}, {}, {}, {}
    for cond in inputs.conditions:
        counts = np.stack([g.counts[cond] for g in inputs.groups if cond in g.counts]) if inputs.groups else \
            np.zeros((0, 4, NUM_INSTANCE_CLASSES), np.int64)
        refs, found, conf, matched = (counts[:, i] for i in range(4)) if len(counts) else \
            (np.zeros((0, NUM_INSTANCE_CLASSES)),) * 4
        xi = detection_xi.ratio(found, refs)
        precision = detection_xi.ratio(matched, conf)
        ok = detection_xi.supported(refs, s["min_boxes"], s["min_images"]) if len(refs) else \
            np.zeros(NUM_INSTANCE_CLASSES, bool)
        blind = np.array([n in inputs.blind for n in INSTANCE_CLASSES])
        ok = ok & ~blind  # a class the model cannot predict is NaN with that reason, never 0
        lo, hi = bootstrap.ratio_ci(found, refs, boot["resamples"], boot["confidence"], boot["seed"])
        lo, hi = bootstrap.drop_zero_width(lo, hi)
        ap = coco_ap.average_precision(pseudo_gt, inputs.coco_results(cond), s["max_detections"],
                                       inputs.scored_categories())
        for c, name in enumerate(INSTANCE_CLASSES):
            rows.append({"model": inputs.model, "reference_model": inputs.reference_model, "condition": cond,
                         "class_name": name, "xi": xi[c] if ok[c] else math.nan, "xi_unsupported": xi[c],
                         "ci_low": lo[c] if ok[c] else math.nan, "ci_high": hi[c] if ok[c] else math.nan,
                         "boxes": int(refs[:, c].sum()) if len(refs) else 0,
                         "images": int((refs[:, c] > 0).sum()) if len(refs) else 0, "supported": bool(ok[c]),
                         "precision": precision[c], "confident_boxes": int(conf[:, c].sum()) if len(conf) else 0,
                         "pseudo_ap50": ap["per_class"][c + 1][1],
                         "reason": "" if ok[c] else inputs.blind_reason() if blind[c] else
                         f"fewer than {s['min_boxes']} reference boxes or {s['min_images']} images"})
        mean = float(np.nanmean(xi[ok])) if ok.any() else math.nan
        mlo, mhi = bootstrap.class_mean_ci(found, refs, ok, boot["resamples"], boot["confidence"], boot["seed"]) \
            if ok.any() else (math.nan, math.nan)
        mlo, mhi = bootstrap.drop_zero_width(mlo, mhi)
        total_conf = conf.sum() if len(conf) else 0
        prec[cond] = float(matched.sum() / total_conf) if total_conf else math.nan
        pap[cond] = ap["ap50"]
        xi_mean[cond] = mean
        support[cond] = int(refs[:, ok].sum()) if len(refs) else 0  # the boxes the mean rests on (its classes)
        rows.append({"model": inputs.model, "reference_model": inputs.reference_model, "condition": cond,
                     "class_name": "mean", "xi": mean, "xi_unsupported": math.nan, "ci_low": mlo, "ci_high": mhi,
                     "boxes": int(refs.sum()) if len(refs) else 0, "images": len(refs), "supported": bool(ok.any()),
                     "precision": prec[cond], "confident_boxes": int(total_conf), "pseudo_ap50": ap["ap50"],
                     "reason": "" if ok.any() else ap.get("reason", "no class with enough reference boxes")})
    per_group = [{"group_id": g.group_id, "condition": cond, "class_name": name, "reference_boxes": int(c[0, k]),
                  "found": int(c[1, k]), "confident": int(c[2, k]), "matched": int(c[3, k])}
                 for g in inputs.groups for cond, c in g.counts.items() for k, name in enumerate(INSTANCE_CLASSES)]
    groups = pd.DataFrame(per_group, columns=["group_id", "condition", "class_name", "reference_boxes", "found",
                                              "confident", "matched"])
    return {XI: pd.DataFrame(rows), GROUP_COUNTS: groups}, {"xi_mean": xi_mean, "xi_support": support,
                                                              "pseudo_ap50": pap, "precision": prec}


def gt_tables(inputs: "Inputs") -> Tables:
    """COCO AP / AP50 / AP75 and per-class AP per condition against the renderer's boxes; P / mPC / rPC."""
    if not inputs.ground_truth:
        return {}, {}
    rows, ap, ap50 = [], {}, {}
    for cond in inputs.conditions:
        gt = inputs.ground_truth.get(cond)
        if gt is None:
            continue
        r = coco_ap.average_precision(gt, inputs.coco_results(cond), inputs.settings["max_detections"],
                                      inputs.scored_categories())
        ap[cond], ap50[cond] = r["ap"], r["ap50"]
        rows.append({"model": inputs.model, "condition": cond, "class_name": "all", "ap": r["ap"], "ap50": r["ap50"],
                     "ap75": r["ap75"], "reason": r.get("reason", "")})
        for c, name in enumerate(INSTANCE_CLASSES):
            a, a50 = r["per_class"][c + 1]
            rows.append({"model": inputs.model, "condition": cond, "class_name": name, "ap": a, "ap50": a50,
                         "ap75": math.nan, "reason": "" if math.isfinite(a) else inputs.blind_reason()
                         if name in inputs.blind else "no object of this class"})
    rob = []
    for subset, conds in corruption.subsets([c for c in inputs.adverse if c in ap], inputs.clean).items():
        for metric, perf in (("ap", ap), ("ap50", ap50)):
            rob.append({"model": inputs.model, "metric": metric, "conditions": subset, "n_conditions": len(conds),
                        **corruption.corruption_scores(perf, inputs.clean, conds)})
    headline = corruption.corruption_scores(ap, inputs.clean, [c for c in inputs.adverse if c in ap])
    return ({GT_AP: pd.DataFrame(rows), ROBUSTNESS: pd.DataFrame(rob)},
            {"gt_ap": ap, "gt_ap50": ap50, "robustness": headline})


def object_tables(inputs: "Inputs") -> Tables:
    """Every ground-truth object in every condition, found or not; the found share by height, fog transmittance
    and luma."""
    rows = [dict(o, model=inputs.model) for g in inputs.groups for o in g.objects]
    objects = pd.DataFrame(rows, columns=["model", "group_id", "condition", "instance", "class_name", "height", "area",
                                          "transmittance", "luma", "ignore", "truncated", "found"])
    objects["ignore"] = objects["ignore"].fillna("")
    shares = [per_object.found_share(objects, "height", per_object.HEIGHT_BINS),
              per_object.found_share(objects, "transmittance", per_object.TRANSMITTANCE_BINS),
              per_object.found_share(objects, "luma", per_object.LUMA_BINS)]
    found = pd.concat([f for f in shares if not f.empty] or shares[:1], ignore_index=True)
    found.insert(0, "model", inputs.model)
    return {OBJECTS: objects, OBJECTS_FOUND: found}, {"objects": int((objects["ignore"] == "").sum())}


def ranking_tables(inputs: "Inputs") -> Tables:
    """The paper's ranking analysis (eq. valid_spearman) for boxes: phi per image, class and condition is the number
    of the model's boxes of the class scored >= its operating threshold (the third row of detection_xi.image_counts),
    clean vs adverse; rho_valid^c is their Spearman over the frames that show the class (top-M or non-zero), with a
    bootstrap interval over frames. No matching is involved, so it runs on coarsely paired data such as ACDC."""
    s, r = inputs.settings, inputs.settings["rho"]
    boot = s["bootstrap"]
    classes = r["classes"] or list(INSTANCE_CLASSES)
    counts, rho, summary = [], [], {}
    for cond in inputs.adverse:
        both = [g for g in inputs.groups if cond in g.counts and inputs.clean in g.counts]
        for name in classes:
            c = INSTANCE_CLASSES.index(name)
            clean = np.array([int(g.counts[inputs.clean][2, c]) for g in both], np.int64)
            adverse = np.array([int(g.counts[cond][2, c]) for g in both], np.int64)
            counts += [{"model": inputs.model, "class_name": name, "pair_id": g.group_id, "condition": cond,
                        "clean_count": int(a), "adv_count": int(b)} for g, a, b in zip(both, clean, adverse)]
            for row in ranking.rho_rows(clean, adverse, r["selections"], r["m"], boot["resamples"], boot["confidence"],
                                        boot["seed"], r["headline"], r["min_frames"]):
                rho.append({"model": inputs.model, "class_name": name, "condition": cond, **row})
                if row["headline"]:
                    summary.setdefault(cond, {})[name] = row["rho"]
    return ({FRAME_COUNTS: pd.DataFrame(counts, columns=["model", "class_name", "pair_id", "condition", "clean_count",
                                                         "adv_count"]),
             RHO_VALID: pd.DataFrame(rho, columns=["model", "class_name", "condition", "selection", "m", "n_frames",
                                                   "rho", "ci_low", "ci_high", "headline", "min_frames"])},
            {"rho_valid_headline": summary})


def estimator_tables(inputs: "Inputs") -> Tables:
    """BoS and the pre-NMS consistency per group and condition, where detection.estimators computed them
    (pairedgta/metrics/box_stability.py); their means per condition in the summary."""
    rows = [{"model": inputs.model, "group_id": g.group_id, "condition": c, **e}
            for g in inputs.groups for c, e in g.estimators.items()]
    if not rows:
        return {}, {}
    t = pd.DataFrame(rows, columns=["model", "group_id", "condition", "bos", "pcr"])
    means = {k: {c: (float(v) if np.isfinite(v) else None) for c, v in t.groupby("condition", sort=False)[k].mean().items()}
             for k in ("bos", "pcr")}
    return {ESTIMATORS: t}, {"bos": means["bos"], "pcr": means["pcr"]}


METRICS: tuple[DetectionMetric, ...] = (
    DetectionMetric("detection_xi", "3", (XI, GROUP_COUNTS), xi_tables),
    DetectionMetric("coco_ap", "1", (GT_AP, ROBUSTNESS), gt_tables),
    DetectionMetric("per_object", "1", (OBJECTS, OBJECTS_FOUND), object_tables),
    DetectionMetric("box_ranking", "1", (FRAME_COUNTS, RHO_VALID), ranking_tables),
    DetectionMetric("estimators", "2", (ESTIMATORS,), estimator_tables),
)


def metrics() -> tuple[DetectionMetric, ...]:
    return METRICS


def versions() -> list[str]:
    return list(work.declaration(METRICS))


def result_files() -> tuple[str, ...]:
    return work.result_files(METRICS)


__all__ = ["ESTIMATORS", "FRAME_COUNTS", "GROUP_COUNTS", "GT_AP", "METRICS", "OBJECTS", "OBJECTS_FOUND", "RHO_VALID", "ROBUSTNESS", "XI", "DetectionMetric", "metrics",
           "result_files", "versions"]
