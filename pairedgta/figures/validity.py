"""Does label-free xi rank models as ground truth does? (experiment metric_validity)

Pools every pass's groups per model (a held-out set may span several datasets), computes per (model,
adverse condition) the label-free mean xi and the ground-truth measures (GT mIoU, rPC, xi against the
true labels), and the rank correlation of xi with each ground-truth measure across models, within each
condition and over all cells, with paired bootstrap intervals over groups (pairedgta.metrics.validity).
Writes metric_validity_cells.csv, metric_validity.csv (the correlations) and a figure: the scatter of
xi against rPC (a colour per model, a marker per condition) beside the correlations with their intervals."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.schema import as_dict
from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.errors import ConfigError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, model_color, model_display, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.metrics import mean_mask
from pairedgta.metrics.conventions import convention_from_config
from pairedgta.metrics.validity import GroupCounts, concat_groups, validity

MARKERS = "os^Dv<>Pp*Xh"
TARGET_TEXT = {"rpc": "rPC", "gt_miou": "GT mIoU", "xi_gt_mean": "ξ vs GT"}
FIX = "rerun with force=[evaluate]"


def references(passes: Passes, opts: FigureOptions) -> set[str]:
    """The pseudo-label source of every pass (the run's reference_model where a pass has none): not ranked,
    it would grade itself."""
    refs = {p.pseudo.reference_model() for p in passes if p.pseudo is not None}
    return refs or ({opts.run.reference_model} if opts.run.reference_model else set())


def evaluated_on_every_pass(passes: Passes, figure: str,
                            arrays: tuple[str, ...] = ()) -> dict[str, list[tuple[dict[str, np.ndarray], Path]]]:
    """Per model evaluated on every pass (sorted by name): each pass's group counts (`e.group_counts()`) and
    the entry's folder. The one reader of the figures that rank models against ground truth: every entry
    needs the counts with labels under every condition, and the `arrays` beyond xi's that `figure` reads."""
    per: dict[str, list[tuple[dict[str, np.ndarray], Path]]] = {}
    for p in passes:
        for e in p.evaluations:
            counts = e.group_counts()
            if not counts:
                raise ConfigError(f"plot.figures: {figure} needs evaluate's group_counts.npz, which {e.path} lacks "
                                  f"(written before evaluate VERSION 4); {FIX}")
            missing = [k for k in arrays if k not in counts]
            if missing:
                raise ConfigError(f"plot.figures: {figure} needs {', '.join(missing)} in "
                                  f"{Path(e.path) / 'group_counts.npz'}, written by a newer evaluate; {FIX}")
            if not counts["cm_present"].any():
                raise ConfigError(f"plot.figures: {figure} needs ground-truth labels under every condition; dataset "
                                  f"{p.label} has none (use the generated dataset of the embedded renderer)")
            per.setdefault(e.model, []).append((counts, Path(e.path)))
    return {model: parts for model, parts in sorted(per.items()) if len(parts) == len(passes)}


def group_counts(passes: Passes) -> list[GroupCounts]:
    """Per model, its groups of every pass (only models evaluated on every pass, with labels)."""
    return [concat_groups(GroupCounts.from_arrays(model, counts) for counts, _ in parts)
            for model, parts in evaluated_on_every_pass(passes, "metric_validity").items()]


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    refs = references(passes, opts)
    models = [m for m in group_counts(passes) if m.model not in refs]
    if len(models) < 3:  # two models always rank-correlate at +1 or -1: no evidence either way
        raise ConfigError(f"plot.figures: metric_validity ranks models and found {len(models)} evaluated on every pass "
                          f"besides the reference model {', '.join(sorted(refs))}; evaluate at least 3 (models=[...])")
    metric, boot = opts.run.metric, opts.run.metric.bootstrap
    conv = convention_from_config(as_dict(metric))
    clean = metric.rho.clean_condition or passes[0].grid.reference
    include = mean_mask(NUM_CLASSES, CLASS_NAMES, conv.mean_exclude)
    cells, corr = validity(models, clean, include, conv.absent, boot.resamples,
                           boot.confidence, boot.seed, conv.min_images,
                           conv.min_pixels, conv.rpc_min_clean_miou)
    cells_df, corr_df = pd.DataFrame(cells), pd.DataFrame(corr)
    cells_df["convention"] = corr_df["convention"] = conv.name
    files = []
    for df, name in ((cells_df, "metric_validity_cells.csv"), (corr_df, "metric_validity.csv")):
        df.to_csv(out / name, index=False)
        files.append(out / name)
    files += _figure(cells_df, corr_df, out, opts)
    metrics: dict[str, float] = {}
    for row in corr_df.itertuples():
        for stat in ("spearman", "kendall"):
            v = getattr(row, stat)
            if not math.isnan(v):
                metrics[f"validity/{row.target}/{stat}/{row.scope}"] = v
    for row in cells_df.itertuples():
        for k in ("xi_mean", "rpc", "gt_miou", "xi_gt_mean"):
            v = getattr(row, k)
            if not math.isnan(v):
                metrics[f"validity_cell/{k}/{row.condition}/{row.model}"] = v
    return files, metrics


def _figure(cells: pd.DataFrame, corr: pd.DataFrame, out: Path, opts: FigureOptions) -> list[Path]:
    conds = list(dict.fromkeys(cells["condition"]))
    with paper_style():
        fig, (ax, bx) = plt.subplots(1, 2, figsize=(TEXT_WIDTH, 3.0), gridspec_kw={"width_ratios": [1, 1.25]})
        for model, part in cells.groupby("model", sort=False):
            for row in part.itertuples():
                ax.scatter(row.rpc, row.xi_mean, color=model_color(model), marker=MARKERS[conds.index(row.condition) % len(MARKERS)],
                           s=22, edgecolor="black", linewidth=0.3, zorder=3)
        lim = [0, max(1.0, float(np.nanmax(cells[["rpc", "xi_mean"]].to_numpy())) * 1.05)]
        ax.plot(lim, lim, color="0.7", lw=0.6, ls="--", zorder=1)
        ax.set_xlim(lim)
        ax.set_ylim(0, lim[1])
        ax.set_xlabel("rPC = GT mIoU(adverse) / GT mIoU(clean)")
        ax.set_ylabel("label-free mean ξ")
        ax.set_title("Each (model, condition) cell")
        handles = [plt.Line2D([], [], color=model_color(m), marker="o", ls="", markersize=4, label=model_display(m))
                   for m in dict.fromkeys(cells["model"])]
        handles += [plt.Line2D([], [], color="0.3", marker=MARKERS[i % len(MARKERS)], ls="", markersize=4,
                               label=condition_display(c)) for i, c in enumerate(conds)]
        ax.legend(handles=handles, fontsize=5, loc="upper left", frameon=False, ncol=2)
        part = corr[corr["target"] == "rpc"]
        scopes = list(part["scope"])
        y = np.arange(len(scopes))
        level = opts.run.metric.bootstrap.confidence
        for offset, stat, color in ((-0.17, "spearman", "tab:blue"), (0.17, "kendall", "tab:orange")):
            vals = part[stat].to_numpy(float)
            lo, hi = part[f"{stat}_ci_low"].to_numpy(float), part[f"{stat}_ci_high"].to_numpy(float)
            has = np.isfinite(lo) & np.isfinite(hi)
            bx.errorbar(vals[has], (y + offset)[has], xerr=[vals[has] - lo[has], hi[has] - vals[has]], fmt="o",
                        color=color, ms=3, capsize=1.5, lw=0.8, label=f"{stat.capitalize()} ({level:.0%} bootstrap)")
            # no interval (the resamples could not vary): a hollow marker, never a dot that looks certain
            bx.plot(vals[~has], (y + offset)[~has], "o", mfc="none", mec=color, ms=3.5, mew=0.8,
                    label=f"{stat.capitalize()}, no interval" if (~has).any() else None)
        bx.axvline(0, color="0.6", lw=0.6)
        bx.set_xlim(-1.05, 1.05)
        bx.set_yticks(y)
        n_models = int(part["n_models"].iloc[0]) if len(part) else 0
        bx.set_yticklabels([("all cells pooled" if s == "pooled" else condition_display(s)) for s in scopes])
        bx.invert_yaxis()
        bx.set_xlabel("rank correlation of ξ with rPC")
        bx.set_title(f"Across {n_models} models (n = {int(part['n_groups'].iloc[0]) if len(part) else 0} scenes)")
        bx.legend(fontsize=5, loc="lower left", frameon=False)
        fig.tight_layout()
        return save(fig, out, opts.stem("metric_validity", "all"), opts.formats, opts.dpi)
