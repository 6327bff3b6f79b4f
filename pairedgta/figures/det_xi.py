"""task=detection, the models at a glance: mean detection xi per model (rows) and condition (columns) beside its
precision side (pseudo-AP50 against the reference's clean boxes), one heatmap each, the numbers in a CSV and the
parent MLflow run's `compare/det_xi_mean/<condition>/<model>` and `compare/det_ap/<condition>/<model>`. The reference,
graded on its own pseudo-labels, comes last and is not ranked."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
import seaborn as sns

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, model_display, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.figures.palette import detector_colors


def table(passes: Passes, label: str | None = None) -> pd.DataFrame:
    rows = []
    for p in passes:
        if label is not None and p.label != label:
            continue
        for e in p.evaluations:
            s = e.summary()
            own = str(s.get("reference_model")) == str(e.model)
            for cond, xi in (s.get("xi_mean") or {}).items():
                def get(key: str) -> float:
                    v = (s.get(key) or {}).get(cond)
                    return math.nan if v is None else float(v)
                rows.append({"pass": p.label, "model": e.model, "condition": cond,
                             "xi_mean": math.nan if xi is None else float(xi), "pseudo_ap50": get("pseudo_ap50"),
                             "precision": get("precision"), "gt_ap": get("gt_ap"), "gt_ap50": get("gt_ap50"),
                             "is_reference": own})
    return pd.DataFrame(rows, columns=["pass", "model", "condition", "xi_mean", "pseudo_ap50", "precision", "gt_ap",
                                       "gt_ap50", "is_reference"])


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        t = table([p])
        if t.empty:
            continue
        stem = opts.stem("det_xi_models", p.label)
        t.to_csv(out / f"{stem}.csv", index=False)
        files.append(out / f"{stem}.csv")
        adverse = t[t["condition"] != p.grid.reference]
        conds = list(dict.fromkeys(adverse["condition"]))
        own = set(t.loc[t["is_reference"].astype(bool), "model"])
        order = adverse.groupby("model")["xi_mean"].mean().sort_values(ascending=False).index
        order = [m for m in order if m not in own] + [m for m in order if m in own]
        panels = [("xi_mean", "mean detection ξ (share of the reference's clean boxes still found)"),
                  ("pseudo_ap50", "pseudo-AP50 (the reference's clean boxes as ground truth)")]
        colors = detector_colors([*(e.model for e in p.evaluations), *order])  # a model's colour in every figure
        with paper_style():
            fig, axes = plt.subplots(1, 2, figsize=(TEXT_WIDTH * 1.6, 1.0 + 0.32 * len(order)))
            for ax, (col, title) in zip(axes, panels):
                wide = adverse.pivot_table(index="model", columns="condition", values=col, aggfunc="first")
                wide = wide.reindex(index=order, columns=conds)
                wide.index = [model_display(m) + (" (reference)" if m in own else "") for m in wide.index]
                wide.columns = [condition_display(c) for c in wide.columns]
                sns.heatmap(wide, ax=ax, vmin=0, vmax=1, cmap="viridis", annot=True, fmt=".2f", linewidths=0.4,
                            annot_kws={"size": 6}, cbar=ax is axes[-1])
                ax.set_title(title)
                ax.set_xlabel(f"{condition_display(p.grid.reference)} →")
                ax.set_ylabel("")
                ax.tick_params(axis="x", rotation=30)
                for tick, model in zip(ax.get_yticklabels(), order):  # each row's name in the model's colour
                    tick.set_color(colors[model])
                if own and len(own) < len(wide):
                    ax.axhline(len(wide) - len(own), color="white", lw=2.5)
            files += save(fig, out, stem, opts.formats, opts.dpi)
        prefix = "compare" if not opts.multi else f"compare/{p.label}"
        for row in t.itertuples():
            if math.isfinite(row.xi_mean) and not row.is_reference:
                metrics[f"{prefix}/det_xi_mean/{row.condition}/{row.model}"] = row.xi_mean
            if math.isfinite(row.gt_ap):
                metrics[f"{prefix}/det_ap/{row.condition}/{row.model}"] = row.gt_ap
    return files, metrics
