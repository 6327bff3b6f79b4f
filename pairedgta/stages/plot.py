"""Plot stage: the xi table heatmap (models x classes, a panel per condition) and the paper's ranking
figure (frames sorted by clean count, clean/adverse heatmap, difference and its moving average)."""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import seaborn as sns  # noqa: E402

from pairedgta.cityscapes import CLASS_NAMES  # noqa: E402
from pairedgta.stages.common import Context, StageResult, run_cached  # noqa: E402

log = logging.getLogger("pairedgta.plot")
VERSION = "1"


def save(fig: plt.Figure, out: Path, stem: str, formats: list[str], dpi: int) -> list[Path]:
    paths = []
    for fmt in formats:
        path = out / f"{stem}.{fmt}"
        fig.savefig(path, dpi=dpi, bbox_inches="tight")
        paths.append(path)
    plt.close(fig)
    return paths


def xi_table_figure(xi: pd.DataFrame, reference: str, out: Path, formats: list[str], dpi: int) -> list[Path]:
    xi = xi[xi["condition"] != reference]
    conditions = list(dict.fromkeys(xi["condition"]))
    if not conditions:
        return []
    classes = [c for c in CLASS_NAMES if c in set(xi["class_name"])] + ["mean"]
    n = len(conditions)
    fig, axes = plt.subplots(n, 1, figsize=(10, 0.45 * xi["model"].nunique() * n + 1.2 * n), squeeze=False)
    for ax, cond in zip(axes[:, 0], conditions):
        table = xi[xi["condition"] == cond].pivot_table(index="model", columns="class_name", values="xi", dropna=False)
        table = table.reindex(columns=classes) * 100
        sns.heatmap(table, ax=ax, annot=True, fmt=".1f", vmin=0, vmax=100, cmap="viridis", cbar=False,
                    annot_kws={"fontsize": 6}, mask=table.isna())
        ax.set_title(f"{reference} \u2192 {cond}: \u03be (%)", fontsize=9)
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return save(fig, out, "xi_table", formats, dpi)


def ranking_figure(counts: pd.DataFrame, rho: pd.DataFrame, condition: str, classes: list[str], window: int,
                   out: Path, formats: list[str], dpi: int) -> list[Path]:
    counts = counts[(counts["condition"] == condition) & counts["class_name"].isin(classes)]
    models = list(dict.fromkeys(counts["model"]))
    if counts.empty:
        return []
    panels = [(m, c) for m in models for c in classes if not counts[(counts["model"] == m) & (counts["class_name"] == c)].empty]
    fig, axes = plt.subplots(2, len(panels), figsize=(4 * len(panels), 4), squeeze=False,
                             gridspec_kw={"height_ratios": [1, 1.2]})
    for j, (model, cls) in enumerate(panels):
        g = counts[(counts["model"] == model) & (counts["class_name"] == cls)].sort_values("clean_count", ascending=False, kind="stable")
        heat = np.vstack([g["clean_count"].to_numpy(), g["adv_count"].to_numpy()]).astype(float)
        sns.heatmap(heat, ax=axes[0, j], cmap="magma", cbar=j == len(panels) - 1, yticklabels=["clean", "adverse"], xticklabels=False)
        r = rho[(rho["model"] == model) & (rho["class_name"] == cls) & (rho["condition"] == condition)]
        label = ", ".join(f"{row.selection}: {row.rho:.3f}" for row in r.itertuples() if not math.isnan(row.rho))
        axes[0, j].set_title(f"{model} / {cls}\n\u03c1_valid {label or 'n/a'}", fontsize=8)
        diff = g["clean_count"].to_numpy() - g["adv_count"].to_numpy()
        x = np.arange(len(diff))
        axes[1, j].plot(x, diff, color="tab:blue", lw=0.8, label="clean \u2212 adverse")
        if len(diff) >= 2:
            k = max(1, min(window, len(diff)))
            axes[1, j].plot(x, pd.Series(diff).rolling(k, min_periods=1, center=True).mean(), color="tab:orange", lw=1.5, label=f"moving avg ({k})")
        axes[1, j].axhline(0, color="grey", lw=0.5)
        axes[1, j].set_xlabel("frames sorted by clean count", fontsize=7)
        axes[1, j].tick_params(labelsize=6)
        if j == 0:
            axes[1, j].legend(fontsize=6)
    fig.suptitle(f"clean vs {condition}", fontsize=9)
    fig.tight_layout()
    return save(fig, out, "ranking", formats, dpi)


def make_plots(ctx: Context, evaluations: list[StageResult], out: Path) -> dict[str, Any]:
    pcfg = ctx.cfg["plot"]
    formats, dpi = list(pcfg.get("formats", ["png"])), int(pcfg.get("dpi", 150))
    xi = pd.concat([pd.read_csv(e.path / "xi.csv") for e in evaluations], ignore_index=True)
    counts = pd.concat([pd.read_csv(e.path / "frame_counts.csv") for e in evaluations], ignore_index=True)
    rho = pd.concat([pd.read_csv(e.path / "rho_valid.csv") for e in evaluations], ignore_index=True)
    reference = ctx.grid.reference
    files: list[Path] = []
    pl = xi[xi["reference_model"] != "ground_truth"]
    files += xi_table_figure(pl, reference, out, formats, dpi)
    ranking = pcfg.get("ranking") or {}
    condition = ranking.get("condition") or ("Night-EXTRASUNNY" if "Night-EXTRASUNNY" in set(counts["condition"]) else next(iter(counts["condition"]), None))
    if condition is not None:
        files += ranking_figure(counts, rho, condition, list(ranking.get("classes") or ["person", "car"]),
                                int(ranking.get("window", 5)), out, formats, dpi)
    pl.to_csv(out / "xi_all_models.csv", index=False)
    return {"figures": [str(p.name) for p in files]}


def run(ctx: Context, evaluations: list[StageResult]) -> StageResult:
    config = {"plot": ctx.cfg["plot"], "reference": ctx.grid.reference}
    inputs = {f"evaluate/{i}": e.key for i, e in enumerate(sorted(evaluations, key=lambda e: e.key))}
    return run_cached(ctx, "plot", VERSION, config, inputs, lambda out: make_plots(ctx, evaluations, out))
