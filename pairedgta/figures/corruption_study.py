"""The corruptions-vs-rendered study's figure and tables (`+experiment=corruptions_vs_rendered`, either task; the
statistics in pairedgta/metrics/corruption_study.py): across the ranked models (every model but the reference), Spearman
between their robustness under each rendered adverse condition and under each 2D corruption, with intervals over
scenes and models; the best stand-in per rendered condition; the corruptions' mean against the rendered conditions'.

The ground-truth score per scene resample: a segmentation evaluation's GT mIoU from its per-group confusion matrices
(group_counts.npz, as the estimator study); a detection evaluation's COCO AP from pycocotools' per-image matching
re-accumulated with scene weights (pairedgta/metrics/coco_resample.py) against the pseudo-label entry's ground truth."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.corruptions import parse_name
from pairedgta.errors import ConfigError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.metrics import corruption_study as study
from pairedgta.metrics.estimator_study import ranked_models

MIN_RANKED = 3


def _segmentation_scores(evaluations: list[Any], conditions: list[str], clean: str, weights: np.ndarray) -> np.ndarray:
    from pairedgta.metrics.validity import GroupCounts, cell_measures

    out = []
    for e in evaluations:
        g = GroupCounts.from_arrays(e.model, e.group_counts())
        include = np.ones(g.cm.shape[-1], bool)
        gt = cell_measures(g, weights, clean, include, "nan")["gt_miou"]  # (1 + R) x C'
        out.append(gt[:, [g.conditions.index(c) for c in conditions]])
    return np.stack(out, axis=1)


def _detection_scores(evaluations: list[Any], pseudo: Any, conditions: list[str], weights: np.ndarray,
                      max_detections: int) -> np.ndarray:
    from pairedgta.metrics import coco_resample

    out = np.full((weights.shape[0], len(evaluations), len(conditions)), np.nan)
    for j, c in enumerate(conditions):
        gt = pseudo.coco(c)
        if gt is None:
            continue
        order = [im["id"] for im in gt["images"]]
        for m, e in enumerate(evaluations):
            match = coco_resample.match(gt, e.detections(c), max_detections)
            w = weights[:, [order.index(i) for i in match.images]]
            out[:, m, j] = coco_resample.average_precision(match, w)
    return out


def scores_of(p: Any, models: list[str], resamples: int, seed: int, max_detections: int
              ) -> tuple[np.ndarray, list[str], str]:
    """(1 + R) x M x C ground-truth scores of pass `p` for `models`, its conditions and the score's name."""
    by = {e.model: e for e in p.evaluations}
    evaluations = [by[m] for m in models]
    conditions = list(p.grid.names)
    clean = p.dataset.reference
    n = len(p.dataset.groups)
    weights = study.scene_weights(n, resamples, seed)
    if all(hasattr(e, "group_counts") for e in evaluations):
        return _segmentation_scores(evaluations, conditions, clean, weights), conditions, "GT mIoU"
    if all(hasattr(e, "detections") for e in evaluations) and p.pseudo is not None:
        return _detection_scores(evaluations, p.pseudo, conditions, weights, max_detections), conditions, "COCO AP"
    raise ConfigError("plot.figures: corruption_study needs evaluations with ground truth under every condition "
                      "(the embedded renderer's labels); run it on the generated dataset")


def markdown(pairs: pd.DataFrame, means: pd.DataFrame, best: pd.DataFrame, score: str, n_models: int,
             n_scenes: int, confidence: float) -> str:
    level = f"{confidence:.0%}"
    lines = [f"# Corruptions vs rendered conditions ({score}, {n_models} ranked models, {n_scenes} scenes)", "",
             f"Spearman between the models' robustness (score / clean score) under a rendered condition and under a "
             f"corruption (mean over its severities); {level} intervals resample scenes and models.", ""]
    rel = pairs[(pairs["measure"] == "relative") & (pairs["severity"] == "mean")]
    if not rel.empty:
        table = rel.pivot(index="corruption", columns="rendered", values="spearman")
        lines += ["| corruption | " + " | ".join(table.columns) + " |", "|---|" + "---:|" * len(table.columns)]
        for name, row in table.iterrows():
            lines.append(f"| {name} | " + " | ".join("–" if not math.isfinite(v) else f"{v:.2f}" for v in row) + " |")
    lines += ["", "Best stand-in per rendered condition (paired difference to the runner-up):", ""]
    for r in best[best["measure"] == "relative"].itertuples():
        ci = "–" if not math.isfinite(r.diff_ci_low) else f"[{r.diff_ci_low:.2f}, {r.diff_ci_high:.2f}]"
        lines.append(f"- {r.rendered}: {r.best} {r.spearman:.2f} (runner-up {r.runner_up} {r.runner_up_spearman:.2f}; "
                     f"difference {r.difference:+.2f} {ci}{', clear' if r.clear else ', not separated'})")
    for r in means.itertuples():
        ci = "–" if not math.isfinite(r.ci_low) else f"[{r.ci_low:.2f}, {r.ci_high:.2f}]"
        lines.append(f"- means ({r.measure}): the corruptions' mean against the rendered conditions' mean "
                     f"{r.spearman:.2f} {ci}")
    return "\n".join(lines) + "\n"


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    boot = opts.run.metric.bootstrap
    for p in passes:
        if p.dataset is None or not p.evaluations:
            continue
        reference = p.pseudo.reference_model() if p.pseudo is not None else None
        models = ranked_models(sorted(e.model for e in p.evaluations), [reference] if reference else [])
        if len(models) < MIN_RANKED:
            raise ConfigError(f"plot.figures: corruption_study ranks the models other than the reference and found "
                              f"{len(models)} ({', '.join(models) or 'none'}); evaluate at least {MIN_RANKED}")
        if not any(parse_name(c) for c in p.grid.names):
            raise ConfigError("plot.figures: corruption_study compares 2D corruptions with rendered conditions; run it "
                              "with conditions=paper_corruptions (or +conditions.corruptions.names=common)")
        scores, conditions, score = scores_of(p, models, boot.resamples, boot.seed, opts.run.detection.max_detections)
        pairs, means, best = study.compare(scores, conditions, p.dataset.reference, parse_name, boot.confidence,
                                           boot.seed)
        pairs_df, means_df, best_df = pd.DataFrame(pairs), pd.DataFrame(means), pd.DataFrame(best)
        stem = opts.stem("corruption_study", p.label)
        for name, df in (("pairs", pairs_df), ("means", means_df), ("stand_ins", best_df)):
            df.to_csv(out / f"{stem}_{name}.csv", index=False)
            files.append(out / f"{stem}_{name}.csv")
        (out / f"{stem}.md").write_text(markdown(pairs_df, means_df, best_df, score, len(models),
                                                 len(p.dataset.groups), boot.confidence))
        files.append(out / f"{stem}.md")
        rel = pairs_df[(pairs_df["measure"] == "relative") & (pairs_df["severity"] == "mean")]
        table = rel.pivot(index="rendered", columns="corruption", values="spearman")
        with paper_style():
            fig, ax = plt.subplots(figsize=(TEXT_WIDTH * 1.5, 0.35 * len(table) + 1.2))
            im = ax.imshow(table.to_numpy(float), vmin=-1, vmax=1, cmap="RdBu_r", aspect="auto")
            ax.set_xticks(range(len(table.columns)), table.columns, rotation=45, ha="right", fontsize=5)
            ax.set_yticks(range(len(table.index)), [condition_display(c) for c in table.index], fontsize=5)
            for (i, j), v in np.ndenumerate(table.to_numpy(float)):
                if math.isfinite(v):
                    ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=4)
            fig.colorbar(im, ax=ax, label=f"Spearman (models' {score} / clean)")
            ax.set_title(f"Which corruption ranks {len(models)} models as each rendered condition does", fontsize=7)
            files += save(fig, out, stem, opts.formats, opts.dpi)
        for r in means:
            if math.isfinite(r["spearman"]):
                metrics[f"corruption_study/means/{r['measure']}"] = float(r["spearman"])
    return files, metrics
