"""Models compared at a glance: mean xi per model (rows) and condition (columns) as one heatmap, the
numbers in a CSV, and the parent MLflow run's metrics `compare/xi_mean/<condition>/<model>` (and
`compare/gt_miou/...` where labels exist), so one chart of the parent shows every model.

The reference model, when it is evaluated too, is scored against its own pseudo-labels: it is not
ranked. Its row comes last in the heatmap, named the reference, and its xi is left out of the
`compare/xi_mean` metrics (its GT mIoU, which is no self-grading, stays)."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
import seaborn as sns

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, model_display, paper_style, save
from pairedgta.figures.inputs import Passes

GT = "ground_truth"


def mean_table(passes: Passes, label: str | None = None) -> pd.DataFrame:
    """Long table: pass, model, condition, xi_mean (vs the pseudo-labels), gt_miou (NaN without labels),
    is_reference (the model whose pseudo-labels its xi counts)."""
    rows = []
    for p in passes:
        if label is not None and p.label != label:
            continue
        for e in p.evaluations:
            summary = e.summary()
            own = str(summary.get("reference_model")) == str(e.model)
            for cond, xi in summary.get("xi_mean", {}).items():
                gt = summary.get("gt_miou", {}).get(cond)
                rows.append({"pass": p.label, "model": e.model, "condition": cond,
                             "xi_mean": math.nan if xi is None else float(xi),
                             "gt_miou": math.nan if gt is None else float(gt), "is_reference": own})
    return pd.DataFrame(rows, columns=["pass", "model", "condition", "xi_mean", "gt_miou", "is_reference"])


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        table = mean_table([p])
        reference = p.grid.reference
        table = table[table["condition"] != reference]
        if table.empty or table["model"].nunique() < 1:
            continue
        conds = list(dict.fromkeys(table["condition"]))
        # the ranked models ordered by their mean over the adverse conditions, the most robust on top; the
        # reference (graded on its own pseudo-labels) below them
        own = set(table.loc[table["is_reference"].astype(bool), "model"])
        means = table.groupby("model")["xi_mean"].mean().sort_values(ascending=False)
        order = [m for m in means.index if m not in own] + [m for m in means.index if m in own]
        wide = table.pivot_table(index="model", columns="condition", values="xi_mean", aggfunc="first")
        wide = wide.reindex(index=order, columns=conds)
        stem = opts.stem("xi_models", p.label)
        csv = out / f"{stem}.csv"
        table.to_csv(csv, index=False)
        files.append(csv)
        shown = wide.copy()
        shown.index = [model_display(m) + (" (reference, own pseudo-labels)" if m in own else "") for m in wide.index]
        shown.columns = [condition_display(c) for c in wide.columns]
        with paper_style():
            height = 0.9 + 0.32 * len(shown)
            fig, ax = plt.subplots(figsize=(TEXT_WIDTH, height))
            sns.heatmap(shown, ax=ax, vmin=0, vmax=1, cmap="viridis", annot=True, fmt=".2f", linewidths=0.4,
                        cbar_kws={"label": f"mean ξ vs {model_display(p.pseudo.reference_model()) if p.pseudo else 'reference'}"
                                  " pseudo-labels"}, annot_kws={"size": 6})
            ax.set_xlabel(f"{condition_display(reference)} →")
            ax.set_ylabel("")
            ax.set_title("Mean ξ per model and condition (rows: most robust first"
                         + ("; the reference, not ranked, last)" if own and len(own) < len(shown) else ")"))
            if own and len(own) < len(shown):
                ax.axhline(len(shown) - len(own), color="white", lw=2.5)
            ax.tick_params(axis="x", rotation=30)
            for t in ax.get_xticklabels():
                t.set_ha("right")
            files += save(fig, out, stem, opts.formats, opts.dpi)
        prefix = "compare" if not opts.multi else f"compare/{p.label}"
        for row in table.itertuples():
            if not math.isnan(row.xi_mean) and not row.is_reference:
                metrics[f"{prefix}/xi_mean/{row.condition}/{row.model}"] = row.xi_mean
            if not math.isnan(row.gt_miou):
                metrics[f"{prefix}/gt_miou/{row.condition}/{row.model}"] = row.gt_miou
    return files, metrics
