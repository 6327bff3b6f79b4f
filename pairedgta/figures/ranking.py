"""The paper's ranking figure (fig. consistency_comparisons): per dataset x model x class, frames sorted by
their clean count phi, a two-row heatmap of clean and adverse counts, and below it the image-wise
difference (clean - adverse) with its moving average; rho_valid in each title. Plus the rho table."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import seaborn as sns

from pairedgta.conditions import headline_condition
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import (
    concat_tables,
    condition_display,
    markdown_table,
    model_display,
    moving_average,
    paper_style,
    save,
)
from pairedgta.figures.inputs import Passes

SELECTION_LABEL = {"top_m": "top-M", "nonzero": "non-zero"}


@dataclass
class RankingInput:
    """One dataset's evaluations: its label, the adverse condition shown, counts and rho of every model."""

    label: str
    condition: str
    counts: pd.DataFrame  # frame_counts.csv rows of every model
    rho: pd.DataFrame  # rho_valid.csv rows of every model


def sorted_counts(counts: pd.DataFrame, model: str, cls: str, condition: str) -> pd.DataFrame:
    """Frames of (model, class, condition) sorted by clean count, largest first (ties by frame id)."""
    g = counts[(counts["model"] == model) & (counts["class_name"] == cls) & (counts["condition"] == condition)]
    return g.sort_values(["clean_count", "pair_id"], ascending=[False, True], kind="stable").reset_index(drop=True)


def ranking_figure(inputs: list[RankingInput], classes: list[str], window: int, out: Path, formats: list[str],
                   dpi: int, stem: str = "ranking", selections: tuple[str, ...] = ("top_m", "nonzero"),
                   phi: tuple[str, str] = ("pixels", "pixels predicted with\nconfidence \u2265 \u03c4_mass")) -> list[Path]:
    """`phi`: the unit of the counts and what they count (the run's task, pairedgta/tasks.py)."""
    columns: list[tuple[str, str]] = []
    for inp in inputs:
        for model in dict.fromkeys(inp.counts["model"]):
            for cls in classes:
                if (model, cls) not in columns and not sorted_counts(inp.counts, model, cls, inp.condition).empty:
                    columns.append((model, cls))
    if not columns:
        return []
    with paper_style():
        # >= 9.5 in: >= 1200 px at the default 150 dpi once trimmed, ~2.3 in per panel so titles never collide
        width = max(9.5, 2.3 * len(columns))
        fig = plt.figure(figsize=(width, 2.5 * len(inputs)))
        outer = fig.add_gridspec(len(inputs), 1, hspace=0.55)
        for i, inp in enumerate(inputs):
            # per dataset: the heatmap row and, tight below it, the difference row (shared x)
            inner = outer[i].subgridspec(2, len(columns), height_ratios=[1, 1.4], hspace=0.08, wspace=0.65)
            for j, (model, cls) in enumerate(columns):
                top, bottom = fig.add_subplot(inner[0, j]), fig.add_subplot(inner[1, j])
                g = sorted_counts(inp.counts, model, cls, inp.condition)
                if g.empty:
                    top.axis("off")
                    bottom.axis("off")
                    continue
                r = inp.rho[(inp.rho["model"] == model) & (inp.rho["class_name"] == cls) & (inp.rho["condition"] == inp.condition)]
                vals = {row.selection: row for row in r.itertuples()}
                parts = [_rho_text(SELECTION_LABEL.get(s, s), vals[s]) for s in selections
                         if s in vals and not math.isnan(vals[s].rho)]
                if not parts:
                    # no rho_valid (too few frames with the class, or constant counts): say so in words
                    # rather than draw an all-black heatmap
                    _no_rho_panel(top, bottom, g, f"{inp.label} \u00b7 {model_display(model)}\n{cls}: \u03c1_valid n/a",
                                  phi[1])
                    continue
                heat = np.vstack([g["clean_count"].to_numpy(), g["adv_count"].to_numpy()]).astype(float)
                cax = top.inset_axes([1.02, 0.0, 0.035, 1.0])  # outside, so heat and difference align
                sns.heatmap(heat, ax=top, cbar_ax=cax, cmap="magma", xticklabels=False, yticklabels=["clean", "adverse"],
                            vmin=0, vmax=max(1.0, float(heat.max())))
                cax.tick_params(labelsize=5, length=2)
                cax.set_ylabel(f"\u03c6 ({phi[0]})", fontsize=5, labelpad=1)
                # one line per selection: two on one line run into the neighbouring panel's title
                top.set_title(f"{inp.label} \u00b7 {model_display(model)} \u00b7 {cls}\n"
                              + "\n".join(f"\u03c1_valid {p}" for p in parts), fontsize=6)
                top.tick_params(length=0, labelsize=5)
                diff = g["clean_count"].to_numpy() - g["adv_count"].to_numpy()
                x = np.arange(len(diff))
                bottom.plot(x + 0.5, diff, color="tab:blue", lw=0.7, label="clean \u2212 adverse")
                if len(diff) >= 2:
                    k = max(1, min(window, len(diff)))
                    bottom.plot(x + 0.5, moving_average(diff, k), color="tab:orange", lw=1.3, label=f"moving avg ({k})")
                bottom.axhline(0, color="grey", lw=0.4)
                bottom.set_xlim(0, len(diff))  # the heatmap's cell edges
                bottom.set_xlabel(f"frames sorted by clean \u03c6 ({condition_display(inp.condition)})", fontsize=5)
                bottom.tick_params(labelsize=5)
                if j == 0:
                    bottom.set_ylabel(f"\u0394\u03c6 ({phi[0]})", fontsize=6)
                    if i == 0:
                        bottom.legend(fontsize=5, frameon=False)
        return save(fig, out, stem, formats, dpi)


def _rho_text(label: str, row) -> str:
    """`non-zero 0.991 [0.977, 0.996] n=40`: the value, its bootstrap interval over frames (none when the
    bootstrap could not give one) and how many frames it rests on (marked below metric.rho.min_frames)."""
    text = f"{label} {row.rho:.3f}"
    lo, hi = getattr(row, "ci_low", math.nan), getattr(row, "ci_high", math.nan)
    if lo is not None and hi is not None and not (math.isnan(float(lo)) or math.isnan(float(hi))):
        text += f" [{float(lo):.2f}, {float(hi):.2f}]"
    n = getattr(row, "n_frames", None)
    if n is not None and not pd.isna(n):
        text += f" n={int(n)}" + (FEW if _too_few(row) else "")
    return text


FEW = "\u2021"  # double dagger: fewer frames than metric.rho.min_frames, no headline


def _too_few(row) -> bool:
    """Fewer frames than the row's `min_frames` (rho_valid.csv of evaluate VERSION >= 9; older rows: never)."""
    n, least = getattr(row, "n_frames", None), getattr(row, "min_frames", None)
    return n is not None and least is not None and not pd.isna(n) and not pd.isna(least) and int(n) < int(least)


def _no_rho_panel(top, bottom, g: pd.DataFrame, title: str, what: str) -> None:
    """Both axes of a (model, class) column without rho_valid: the title and a sentence with the
    frame counts that explain why."""
    n = len(g)
    clean = int((g["clean_count"] > 0).sum())
    adverse = int((g["adv_count"] > 0).sum())
    top.set_title(title, fontsize=6)
    top.axis("off")
    top.text(0.5, 0.5, f"too few frames for \u03c1_valid:\nthe class has \u03c6 > 0 ({what})"
             f" in {clean} of {n} clean\nand {adverse} of {n} adverse frames", ha="center", va="center", fontsize=5.5,
             transform=top.transAxes, wrap=True)
    bottom.axis("off")
    bottom.text(0.5, 0.6, "needs \u2265 2 frames with differing\nclean counts (more scenes that show it)",
                ha="center", va="center", fontsize=5, color="0.35", transform=bottom.transAxes)


def rho_table(inputs: list[RankingInput], classes: list[str], out: Path, stem: str = "rho_valid") -> list[Path]:
    """Every rho_valid of the shown condition per dataset, model, class and selection: CSV (with the
    bootstrap interval and the number of frames) and a Markdown pivot, each value with its n_frames."""
    rows = []
    for inp in inputs:
        r = inp.rho[(inp.rho["condition"] == inp.condition) & inp.rho["class_name"].isin(classes)].copy()
        r.insert(0, "dataset_label", inp.label)
        rows.append(r)
    if not rows:
        return []
    table = pd.concat(rows, ignore_index=True)
    table.to_csv(out / f"{stem}.csv", index=False)
    selections = list(dict.fromkeys(table["selection"]))
    header = ["Dataset", "Adverse", "Model"] + [f"{c} ({SELECTION_LABEL.get(s, s)})" for c in classes for s in selections]
    md_rows, few = [], False
    for (label, model), g in table.groupby(["dataset_label", "model"], sort=False):
        cells = []
        for c in classes:
            for s in selections:
                v = g[(g["class_name"] == c) & (g["selection"] == s)]
                if v.empty:
                    cells.append("–")
                    continue
                row = next(v.itertuples())
                n = "" if "n_frames" not in v or pd.isna(row.n_frames) else f" (n={int(row.n_frames)}{FEW if _too_few(row) else ''})"
                few |= _too_few(row)
                cells.append(("–" if math.isnan(float(row.rho)) else f"{float(row.rho):.3f}") + n)
        md_rows.append([str(label), condition_display(str(g["condition"].iloc[0])), model_display(str(model))] + cells)
    text = ("# \u03c1_valid (Spearman of clean vs adverse \u03c6 over the valid frames)\n\n"
            "n: the frames each value rests on" + (f"; {FEW} fewer than metric.rho.min_frames, no headline" if few else "")
            + ".\n\n" + markdown_table(header, md_rows, ["l", "l", "l"] + ["r"] * (len(header) - 3)))
    (out / f"{stem}.md").write_text(text)
    return [out / f"{stem}.csv", out / f"{stem}.md"]


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """The ranking figure and rho table over every evaluated pass (its own adverse condition each)."""
    ranking = opts.plot.ranking
    classes = list(ranking.classes)
    inputs = []
    for p in passes:
        if not p.evaluations:
            continue
        counts = concat_tables(p.evaluations, "frame_counts")
        rho = concat_tables(p.evaluations, "rho")
        conds = list(dict.fromkeys(counts["condition"])) if not counts.empty else []
        cond = headline_condition(conds, p.run.plot.ranking.condition, p.grid.reference)  # plot.ranking.condition where the pass has it
        if cond is not None:
            inputs.append(RankingInput(p.label, cond, counts, rho))
    if not inputs:
        return [], {}
    selections = tuple(opts.run.metric.rho.selections)
    from pairedgta.tasks import get

    files = ranking_figure(inputs, classes, ranking.window, out, opts.formats, opts.dpi, selections=selections,
                           phi=get(opts.run.task).phi)
    files += rho_table(inputs, classes, out)
    metrics: dict[str, float] = {}
    for inp in inputs:
        r = inp.rho[(inp.rho["condition"] == inp.condition) & inp.rho["class_name"].isin(classes)]
        for row in r.itertuples():
            metrics[f"rho_valid/{inp.label}/{row.model}/{row.selection}/{row.class_name}"] = row.rho
    return files, metrics
