"""Pairing ablation (beyond the paper): the same scenes generated with perfect pairing and with increasingly
coarse pairing (generate.pairing), and how mean xi, rho_valid and the measured structure agreement of the
pairs fall as the pairing degrades."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import (
    TEXT_WIDTH,
    concat_tables,
    condition_display,
    markdown_table,
    model_color,
    model_display,
    paper_style,
    save,
)
from pairedgta.figures.inputs import Passes

PAIRING_COLUMNS = ("camera_jitter_m", "camera_jitter_deg", "object_resample_prob", "object_move_m")


@dataclass
class Level:
    label: str
    pairing: dict[str, float]
    xi: pd.DataFrame  # xi.csv rows of every model of this level
    rho: pd.DataFrame  # rho_valid.csv rows of every model
    validation: pd.DataFrame | None  # the generate stage's validation.csv


def ablation_frame(levels: list[Level], reference: str, classes: list[str], selection: str) -> pd.DataFrame:
    """One row per (level, model, adverse condition): pairing parameters, mean xi, rho_valid per class
    (the given selection) and the mean structure agreement of that condition's images with the reference."""
    rows = []
    for order, lv in enumerate(levels):
        xi = lv.xi[(lv.xi["reference_model"] != "ground_truth") & (lv.xi["class_name"] == "mean") & (lv.xi["condition"] != reference)]
        for r in xi.itertuples():
            row = {"level": order, "label": lv.label, **{k: lv.pairing.get(k, 0.0) for k in PAIRING_COLUMNS},
                   "model": r.model, "condition": r.condition, "xi_mean": r.xi}
            for cls in classes:
                v = lv.rho[(lv.rho["model"] == r.model) & (lv.rho["condition"] == r.condition)
                           & (lv.rho["class_name"] == cls) & (lv.rho["selection"] == selection)]["rho"]
                row[f"rho_{selection}_{cls}"] = float(v.iloc[0]) if len(v) else math.nan
                n = lv.rho.loc[v.index, "n_frames"] if "n_frames" in lv.rho else ()  # what each rho rests on
                row[f"n_frames_{selection}_{cls}"] = float(n.iloc[0]) if len(n) else math.nan
            col = f"structure/{r.condition}"
            row["structure_agreement"] = (float(lv.validation[col].mean()) if lv.validation is not None
                                          and col in lv.validation.columns else math.nan)
            rows.append(row)
    return pd.DataFrame(rows)


def ablation_figure(frame: pd.DataFrame, classes: list[str], selection: str, out: Path, formats: list[str], dpi: int,
                    stem: str = "pairing_ablation") -> list[Path]:
    if frame.empty:
        return []
    labels = list(dict.fromkeys(frame.sort_values("level")["label"]))
    x = np.arange(len(labels))
    conditions = list(dict.fromkeys(frame["condition"]))
    markers = "osD^vP*X"
    panels = [("xi_mean", "mean \u03be")] + [(f"rho_{selection}_{c}", f"\u03c1_valid ({c})") for c in classes]
    panels.append(("structure_agreement", "structure agreement\nof the pairs"))
    with paper_style():
        fig, axes = plt.subplots(1, len(panels), figsize=(TEXT_WIDTH, 2.1), squeeze=False)
        for ax, (col, title) in zip(axes[0], panels):
            for model, gm in frame.groupby("model", sort=False):
                for k, cond in enumerate(conditions):
                    g = gm[gm["condition"] == cond].sort_values("level")
                    if g.empty:
                        continue
                    structure = col == "structure_agreement"  # a property of the images: one grey line per condition
                    ax.plot(g["level"], g[col], marker=markers[k % len(markers)], ms=3,
                            color="0.35" if structure else model_color(str(model)),
                            label=None if structure else f"{model_display(str(model))} \u00b7 {condition_display(cond)}")
                if col == "structure_agreement":
                    break  # a property of the images, the same for every model
            ax.set_title(title)
            ax.set_xticks(x, labels, rotation=30, ha="right")
            ax.set_ylim(-1.05 if col.startswith("rho") else 0, 1.05)
            ax.axhline(0, color="grey", lw=0.3)
        axes[0, 0].set_ylabel("value")
        handles, names = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, names, loc="lower center", ncol=min(4, len(names)), frameon=False, fontsize=5,
                   bbox_to_anchor=(0.5, -0.02))
        fig.tight_layout(rect=(0, 0.08 + 0.03 * (len(names) // 4), 1, 1))
        return save(fig, out, stem, formats, dpi)


def ablation_table(frame: pd.DataFrame, classes: list[str], selection: str, out: Path, stem: str = "pairing_ablation") -> list[Path]:
    frame.to_csv(out / f"{stem}.csv", index=False)

    def f(v: float) -> str:
        return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"

    def n_text(n: float | None) -> str:  # how many frames a rho_valid rests on
        return "" if n is None or (isinstance(n, float) and math.isnan(n)) else f" (n={int(n)})"

    header = ["Level", "jitter (m)", "jitter (°)", "resample p", "move (m)", "Model", "Condition", "mean ξ"]
    header += [f"ρ_valid {c}" for c in classes] + ["structure"]
    rows = [[r["label"], f"{r['camera_jitter_m']:g}", f"{r['camera_jitter_deg']:g}", f"{r['object_resample_prob']:g}",
             f"{r['object_move_m']:g}", model_display(r["model"]), condition_display(r["condition"]), f(r["xi_mean"])]
            + [f(r[f"rho_{selection}_{c}"]) + n_text(r.get(f"n_frames_{selection}_{c}")) for c in classes]
            + [f(r["structure_agreement"])]
            for r in frame.to_dict("records")]
    (out / f"{stem}.md").write_text(
        f"# Pairing ablation: mean \u03be, \u03c1_valid ({selection}) and pair structure agreement per pairing level\n\n"
        + markdown_table(header, rows, ["l"] * 1 + ["r"] * 4 + ["l", "l"] + ["r"] * (len(header) - 7)))
    return [out / f"{stem}.csv", out / f"{stem}.md"]


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """Mean xi, rho_valid and structure agreement per pairing level (one evaluated pass per level)."""
    evaluated = [p for p in passes if p.evaluations]
    if not evaluated:
        return [], {}
    classes = list(opts.plot.ranking.classes)
    selections = list(opts.run.metric.rho.selections)
    selection = opts.plot.ablation.selection or selections[0]
    levels = [Level(p.label, p.pairing, concat_tables(p.evaluations, "xi"), concat_tables(p.evaluations, "rho"),
                    p.generate.validation() if p.generate is not None else None) for p in evaluated]
    frame = ablation_frame(levels, evaluated[0].grid.reference, classes, selection)
    files = ablation_figure(frame, classes, selection, out, opts.formats, opts.dpi)
    files += ablation_table(frame, classes, selection, out)
    metrics: dict[str, float] = {}
    for r in frame.to_dict("records"):
        base = f"ablation/{r['label']}/{r['model']}/{r['condition']}"
        metrics[f"{base}/xi_mean"] = r["xi_mean"]
        for c in classes:
            metrics[f"{base}/rho_valid/{selection}/{c}"] = r[f"rho_{selection}_{c}"]
        metrics[f"{base}/structure_agreement"] = r["structure_agreement"]
    return files, metrics
