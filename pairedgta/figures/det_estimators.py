"""Is detection xi the best label-free judge? (+experiment=metric_validity task=detection): detection xi and the
label-free estimators of the detection field ranked against ground truth (COCO AP, rPC) across the ranked detectors
(every one but the reference), the statistics in pairedgta/metrics/detection_study.py. Writes
`det_estimators.csv` (estimator x target x scope), `det_estimator_cells.csv` (every estimator and target per
detector and condition), `det_estimators.md` and `det_estimators.png` (the within-condition mean Spearman with its
interval over scenes and detectors, per target); MLflow metrics `det_validity/<estimator>/<target>/spearman`."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.errors import ConfigError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, markdown_table, paper_style, save
from pairedgta.figures.inputs import FigurePass, Passes
from pairedgta.metrics import detection_study as ds

LABELS = {"det_xi": "detection ξ", "det_precision": "ξ's precision side", "det_xi_f": "F(ξ, precision)",
          "pseudo_ap50": "pseudo-AP50", "relative_det_xi": "relative detection ξ", "ac": "AC (mean score)",
          "relative_ac": "relative AC", "atc": "ATC-style (relative) *", "self_agreement": "self-agreement",
          "committee": "committee agreement", "bos": "BoS (box stability)", "relative_bos": "relative BoS",
          "pcr": "pre-NMS consistency (PCR-style)", "clean_ap": "clean GT AP *"}
TARGET_LABELS = {"rpc": "rPC (AP adverse / clean)", "ap": "adverse COCO AP"}


def _pseudo_gt(p: FigurePass, images: list[dict[str, Any]]) -> dict[str, Any]:
    from pairedgta.detection.boxes import coco_categories
    from pairedgta.detection.inputs import image_ids

    ids = image_ids(p.dataset)
    anns = []
    for gid, d in p.pseudo.boxes().items():
        for b, lab in zip(d.boxes, d.labels):
            anns.append({"id": len(anns) + 1, "image_id": ids[gid], "category_id": int(lab) + 1, "iscrowd": 0,
                         "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
                         "area": float((b[2] - b[0]) * (b[3] - b[1]))})
    return {"images": images, "annotations": anns, "categories": coco_categories()}


def detector(e: Any, groups: list[str], conditions: list[str], min_boxes: int, min_images: int) -> ds.Detector:
    """One evaluation's detections and per-group sums, in `groups`' order."""
    from pairedgta.detection.boxes import INSTANCE_CLASSES
    from pairedgta.metrics.detection_xi import supported

    s = e.summary()
    counts = e.box_counts()
    est = e.estimators()  # group ids as written ("00000"), not read back as numbers
    d = ds.Detector(e.model, float(s["score_threshold"]), {c: e.detections(c) for c in conditions}, {}, {}, {}, {}, {})
    for c in conditions:
        sub = counts[counts["condition"] == c]
        if sub.empty:
            continue

        def wide(col: str) -> np.ndarray:
            t = sub.pivot_table(index="group_id", columns="class_name", values=col, aggfunc="sum")
            return t.reindex(index=groups, columns=list(INSTANCE_CLASSES)).fillna(0).to_numpy()

        d.found[c], d.refs[c] = wide("found"), wide("reference_boxes")
        d.supported[c] = supported(d.refs[c], min_boxes, min_images)
        d.matched[c], d.confident[c] = wide("matched").sum(1), wide("confident").sum(1)
        if not est.empty:
            rows = est[est["condition"] == c].set_index("group_id").reindex(groups)
            d.bos[c], d.pcr[c] = rows["bos"].to_numpy(float), rows["pcr"].to_numpy(float)
    return d


def study(p: FigurePass, opts: FigureOptions) -> tuple[list[dict], list[dict], list[str]]:
    reference = p.pseudo.reference_model()
    evals = [e for e in p.evaluations if e.model != reference]
    if len(evals) < ds.MIN_RANKED:
        raise ConfigError(f"plot.figures: det_estimators needs at least {ds.MIN_RANKED} ranked detectors besides the "
                          f"reference {reference}; it has {len(evals)} ({', '.join(e.model for e in evals)})")
    conditions = list(evals[0].summary()["conditions"])
    clean = p.grid.reference
    gt = {c: coco for c in conditions if (coco := p.pseudo.coco(c)) is not None}
    if clean not in gt or len(gt) < 3:
        raise ConfigError("plot.figures: det_estimators needs ground-truth boxes under the clean and at least 2 adverse "
                          "conditions (the embedded renderer's instance masks)")
    groups = [g.group_id for g in p.dataset.groups]
    run = opts.run
    detectors = [detector(e, groups, conditions, run.detection.min_boxes, run.metric.min_images) for e in evals]
    data = ds.prepare(detectors, gt, _pseudo_gt(p, gt[clean]["images"]), conditions, clean, len(groups),
                      run.detection.iou, run.detection.max_detections)
    boot = run.metric.bootstrap
    cells, stats = ds.compare(data, boot.resamples, boot.confidence, boot.seed, run.metric.validity.permutations)
    missing = [k for k in ds.NEEDS_FORWARDS if not data.reachable.get(k)]
    return cells, stats, missing


def _fmt(v: float, f: str = "{:.2f}") -> str:
    return "–" if v is None or not math.isfinite(v) else f.format(v)


def markdown(stats: pd.DataFrame, cells: pd.DataFrame, missing: list[str]) -> str:
    mean = stats[stats["scope"] == "within_mean"]
    loio = stats[stats["scope"] == "loio"].set_index(["estimator", "target"])
    rows = []
    for e in dict.fromkeys(mean["estimator"]):
        r = {t: mean[(mean["estimator"] == e) & (mean["target"] == t)].iloc[0] for t in ds.TARGETS}
        cols = [LABELS.get(e, e)]
        for t in ds.TARGETS:
            x = r[t]
            cols += [_fmt(x.spearman), f"[{_fmt(x.spearman_ci_low)}, {_fmt(x.spearman_ci_high)}]",
                     "–" if e == "det_xi" else f"{_fmt(x.spearman_minus_xi, '{:+.2f}')} "
                     f"[{_fmt(x.spearman_minus_xi_ci_low)}, {_fmt(x.spearman_minus_xi_ci_high)}]",
                     "–" if e == "det_xi" else _fmt(x.p_minus_xi_holm, "{:.3f}"), _fmt(x.p_permutation_holm, "{:.4f}"),
                     _fmt(loio.loc[(e, t)].mae, "{:.3f}") if (e, t) in loio.index else "–"]
        rows.append(cols)
    header = ["estimator"] + [f"{TARGET_LABELS[t]}: {h}" for t in ds.TARGETS for h in (
        "within mean", "scene+detector CI", "− detection ξ [CI]", "p Holm of − ξ", "perm. p Holm", "LOIO MAE")]
    n_models = ", ".join(f"{int(mean[mean['target'] == t]['n_models'].iloc[0])} for {TARGET_LABELS[t]}"
                         for t in ds.TARGETS if (mean["target"] == t).any())
    text = ("# Is detection ξ the best label-free judge?\n\n"
            f"Within-condition Spearman across the ranked detectors ({n_models}: those whose target is defined in every "
            "condition; the reference is not ranked), mean over "
            f"{int(mean['n_conditions'].iloc[0]) if len(mean) else 0} adverse conditions, on "
            f"{int(mean['n_groups'].iloc[0]) if len(mean) else 0} scenes. CI: BCa over scenes and detectors drawn "
            "together; − ξ: the paired difference to detection ξ, Holm over the estimators; perm. p: the joint null "
            "(one permutation of the detectors for every condition). LOIO MAE: a line fitted on the other "
            "illuminations' cells. * uses the clean ground truth.\n\n")
    text += markdown_table(header, rows)
    if missing:
        text += (f"\n\nNot computed: {', '.join(missing)} (they need detection.estimators=true and torch detectors "
                 "with a backbone and a suppression threshold).\n")
    return text


def _plot(stats: pd.DataFrame, out: Path, opts: FigureOptions) -> list[Path]:
    mean = stats[stats["scope"] == "within_mean"]
    with paper_style():
        fig, axes = plt.subplots(1, len(ds.TARGETS), figsize=(TEXT_WIDTH * 1.4, 0.6 + 0.22 * mean["estimator"].nunique()),
                                 sharey=True)
        for ax, t in zip(np.atleast_1d(axes), ds.TARGETS):
            sub = mean[mean["target"] == t].reset_index(drop=True)
            y = np.arange(len(sub))
            v = sub["spearman"].to_numpy(float)
            lo, hi = sub["spearman_ci_low"].to_numpy(float), sub["spearman_ci_high"].to_numpy(float)
            has = np.isfinite(lo) & np.isfinite(hi) & np.isfinite(v)
            colors = ["#d62728" if e == "det_xi" else ("0.55" if e in ds.USES_CLEAN_LABELS else "#1f77b4")
                      for e in sub["estimator"]]
            ax.scatter(v, y, c=colors, s=14, zorder=3)
            ax.errorbar(v[has], y[has], xerr=[v[has] - lo[has], hi[has] - v[has]], fmt="none", ecolor="0.3", lw=0.7,
                        capsize=1.5)
            bare = np.isfinite(v) & ~has
            ax.scatter(v[bare], y[bare], facecolors="none", edgecolors="0.3", s=20, zorder=4)
            ax.axvline(0, color="0.7", lw=0.6)
            ax.set_xlim(-1.05, 1.05)
            ax.set_yticks(y)
            ax.set_yticklabels([LABELS.get(e, e) for e in sub["estimator"]])
            ax.set_ylim(len(y) - 0.5, -0.5)
            ax.set_title(f"target: {TARGET_LABELS[t]}", loc="left")
            ax.set_xlabel("within-condition Spearman, mean (BCa CI)")
        return save(fig, out, "det_estimators", opts.formats, opts.dpi)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if not p.evaluations or p.pseudo is None or p.dataset is None:
            continue
        cells, stats, missing = study(p, opts)
        stats_df, cells_df = pd.DataFrame(stats), pd.DataFrame(cells)
        stem = opts.stem("det_estimators", p.label)
        stats_df.to_csv(out / f"{stem}.csv", index=False)
        cells_df.to_csv(out / f"{opts.stem('det_estimator_cells', p.label)}.csv", index=False)
        (out / f"{stem}.md").write_text(markdown(stats_df, cells_df, missing), encoding="utf-8")
        files += [out / f"{stem}.csv", out / f"{opts.stem('det_estimator_cells', p.label)}.csv", out / f"{stem}.md"]
        files += _plot(stats_df, out, opts)
        for r in stats:
            if r["scope"] == "within_mean" and math.isfinite(r["spearman"]):
                metrics[f"det_validity/{r['estimator']}/{r['target']}/spearman"] = float(r["spearman"])
    if not files:
        raise ConfigError("plot.figures: det_estimators found no evaluation to draw; run it with stages=[evaluate,plot]")
    return files, metrics


__all__ = ["draw", "markdown", "study"]
