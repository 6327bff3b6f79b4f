"""Robustness curves of a severity ladder (conditions=fog_ladder, rain_ladder, light_ladder): mean xi and,
where the dataset has labels, GT mIoU and rPC = mIoU(step) / mIoU(clean) against the physical severity,
one line per model; per class on request (plot.robustness.classes). The breaking point, the first step
whose mean xi falls below plot.robustness.break_below (0.5), goes to a table and to MLflow
(`breaking_point/<model>` in the ladder's unit), so "where does this model stop seeing" is one number
with a unit rather than a condition name. Passes whose grid is not a ladder draw nothing."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import (TEXT_WIDTH, markdown_table, model_color, model_display, paper_style, save)
from pairedgta.figures.inputs import Passes

GT = "ground_truth"


def curve_table(p: Any) -> pd.DataFrame:
    """Long table: model, step (ladder order), condition, value, unit, xi_mean, gt_miou, rpc."""
    ladder, grid = p.grid.ladder, p.grid
    rows = []
    for e in p.evaluations:
        s = e.summary()
        xi, miou = s.get("xi_mean", {}), s.get("gt_miou", {})
        clean = miou.get(grid.reference)
        for step, cond in enumerate(grid.conditions):
            if cond.name not in xi:
                continue
            m = miou.get(cond.name)
            rows.append({
                "model": e.model, "step": step, "condition": cond.name, "parameter": ladder.parameter,
                "value": ladder.value(cond), "unit": ladder.unit, "tick": ladder.tick(cond),
                "xi_mean": _num(xi.get(cond.name)), "gt_miou": _num(m),
                "rpc": _num(m) / clean if m is not None and clean else math.nan,
            })
    return pd.DataFrame(rows, columns=["model", "step", "condition", "parameter", "value", "unit", "tick",
                                       "xi_mean", "gt_miou", "rpc"])


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def breaking_points(curves: pd.DataFrame, reference: str, below: float) -> pd.DataFrame:
    """Per model: the first step (in order of growing severity, the reference left out) whose mean xi < `below`."""
    rows = []
    for model, g in curves.groupby("model", sort=False):
        g = g[g["condition"] != reference].sort_values("step")
        hit = g[g["xi_mean"] < below]
        first = hit.iloc[0] if len(hit) else None
        rows.append({
            "model": model, "parameter": g["parameter"].iloc[0] if len(g) else "", "below": below,
            "condition": first["condition"] if first is not None else "none",
            "value": float(first["value"]) if first is not None else math.nan,
            "unit": g["unit"].iloc[0] if len(g) else "",
            "xi_mean": float(first["xi_mean"]) if first is not None else math.nan,
            "last_step_xi_mean": float(g["xi_mean"].iloc[-1]) if len(g) else math.nan,
        })
    return pd.DataFrame(rows, columns=["model", "parameter", "below", "condition", "value", "unit", "xi_mean",
                                       "last_step_xi_mean"])


def class_curves(p: Any, classes: list[str]) -> pd.DataFrame:
    """Per-class xi (vs the pseudo-labels) along the ladder, supported cells only (NaN otherwise)."""
    order = {c.name: i for i, c in enumerate(p.grid.conditions)}
    rows = []
    for e in p.evaluations:
        xi = e.xi()
        xi = xi[(xi["reference_model"] != GT) & xi["class_name"].isin(classes)]
        for r in xi.itertuples():
            if r.condition in order:
                ok = bool(getattr(r, "supported", True))
                rows.append({"model": e.model, "class_name": r.class_name, "condition": r.condition,
                             "step": order[r.condition], "xi": float(r.xi) if ok else math.nan})
    return pd.DataFrame(rows, columns=["model", "class_name", "condition", "step", "xi"])


def _axes_style(ax, steps: list[int], ticks: list[str], ladder: Any) -> None:
    ax.set_xticks(steps)
    ax.set_xticklabels(ticks, rotation=30, ha="right")
    ax.set_xlabel(f"{ladder.label} ({ladder.unit}) →  more severe")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(True, linewidth=0.3, alpha=0.5)


def _legend(fig, ax) -> None:
    """One legend row above the panels, where it hides no curve."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=max(1, len(labels)), fontsize=6, frameon=False,
               bbox_to_anchor=(0.5, 1.0 - 0.25 / fig.get_figheight()))


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    below = opts.plot.robustness.break_below
    classes = list(opts.plot.robustness.classes or [])
    for p in passes:
        ladder = p.grid.ladder
        if ladder is None or not p.evaluations:
            continue
        curves = curve_table(p)
        if curves.empty:
            continue
        stem = opts.stem("robustness", p.label)
        curves.to_csv(out / f"{stem}.csv", index=False)
        breaks = breaking_points(curves, p.grid.reference, below)
        breaks.to_csv(out / f"{stem}_breaking_points.csv", index=False)
        (out / f"{stem}_breaking_points.md").write_text(markdown_table(
            ["model", f"breaking point ({ladder.label}, mean ξ < {below:g})", "condition", "mean ξ there",
             "mean ξ at the last step"],
            [[model_display(r.model), "none" if math.isnan(r.value) else f"{r.value:g} {r.unit}", r.condition,
              "" if math.isnan(r.xi_mean) else f"{r.xi_mean:.3f}", f"{r.last_step_xi_mean:.3f}"]
             for r in breaks.itertuples()], ["l", "r", "l", "r", "r"]) + "\n")
        files += [out / f"{stem}.csv", out / f"{stem}_breaking_points.csv", out / f"{stem}_breaking_points.md"]
        prefix = "" if not opts.multi else f"{p.label}/"
        for r in breaks.itertuples():
            if not math.isnan(r.value):
                metrics[f"{prefix}breaking_point/{r.model}"] = float(r.value)
        steps = sorted(curves["step"].unique())
        ticks = [curves[curves["step"] == s]["tick"].iloc[0] for s in steps]
        panels = [("xi_mean", f"mean ξ vs {model_display(p.pseudo.reference_model()) if p.pseudo else 'reference'}")]
        if curves["gt_miou"].notna().any():
            panels += [("gt_miou", "GT mIoU"), ("rpc", "rPC = mIoU / mIoU(clean)")]
        with paper_style():
            fig, axes = plt.subplots(1, len(panels), figsize=(TEXT_WIDTH, 2.5), squeeze=False)
            for ax, (col, title) in zip(axes[0], panels):
                for model, g in curves.groupby("model", sort=False):
                    g = g.sort_values("step")
                    ax.plot(g["step"], g[col], marker="o", markersize=3, linewidth=1.1, color=model_color(model),
                            label=model_display(model))
                    if col == "xi_mean":
                        b = breaks[breaks["model"] == model]
                        if len(b) and not math.isnan(b["value"].iloc[0]):
                            at = g[g["condition"] == b["condition"].iloc[0]]
                            ax.plot(at["step"], at[col], marker="x", markersize=7, color=model_color(model))
                if col == "xi_mean":
                    ax.axhline(below, color="0.4", linestyle="--", linewidth=0.7)
                    ax.text(steps[0], below + 0.02, f"breaking point: mean ξ < {below:g} (×)", fontsize=5.5,
                            color="0.3")
                _axes_style(ax, steps, ticks, ladder)
                if col == "rpc":
                    ax.set_ylim(-0.02, max(1.05, float(np.nanmax(curves[col])) + 0.05))
                ax.set_title(title)
            _legend(fig, axes[0][0])
            fig.suptitle(f"Robustness along the {ladder.label} ladder (reference {p.grid.reference}, "
                         f"{int(p.evaluations[0].summary().get('n_pairs', {}).get(p.grid.reference, 0)) or '?'} scenes)",
                         fontsize=7, y=0.99)
            fig.tight_layout(rect=(0, 0, 1, 0.9))
            files += save(fig, out, stem, opts.formats, opts.dpi)
        if classes:
            files += _draw_classes(p, classes, steps, ticks, ladder, below, out, opts)
    return files, metrics


def _draw_classes(p: Any, classes: list[str], steps: list[int], ticks: list[str], ladder: Any, below: float,
                  out: Path, opts: FigureOptions) -> list[Path]:
    table = class_curves(p, classes)
    stem = opts.stem("robustness_classes", p.label)
    table.to_csv(out / f"{stem}.csv", index=False)
    cols = min(3, len(classes))
    nrows = math.ceil(len(classes) / cols)
    with paper_style():
        fig, axes = plt.subplots(nrows, cols, figsize=(TEXT_WIDTH, 2.2 * nrows + 0.3), squeeze=False)
        for i, cls in enumerate(classes):
            ax = axes[i // cols][i % cols]
            for model, g in table[table["class_name"] == cls].groupby("model", sort=False):
                g = g.sort_values("step")
                ax.plot(g["step"], g["xi"], marker="o", markersize=3, linewidth=1.1, color=model_color(model),
                        label=model_display(model))
            ax.axhline(below, color="0.4", linestyle="--", linewidth=0.7)
            _axes_style(ax, steps, ticks, ladder)
            ax.set_title(f"ξ of {cls}")
            if table[table["class_name"] == cls]["xi"].isna().all():  # say why the panel is empty
                ax.text(0.5, 0.75, "no supported ξ:\ntoo few pseudo-label pixels", transform=ax.transAxes,
                        ha="center", va="center", fontsize=6, color="0.4")
        for j in range(len(classes), nrows * cols):
            axes[j // cols][j % cols].axis("off")
        _legend(fig, axes[0][0])
        fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()))
        return [out / f"{stem}.csv", *save(fig, out, stem, opts.formats, opts.dpi)]
