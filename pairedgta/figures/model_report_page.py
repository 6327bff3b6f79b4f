"""The model report's page (pairedgta/figures/model_report.py computes its numbers): panels (a) and (b), the
subject's standing per condition beside the population's box and points; (c) where it loses most; (d) its worst
images as image | pseudo-label | prediction | disagreement strips; (e) xi against GT mIoU within each condition with
its intervals, and the subject's xi rank against its GT rank."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from pairedgta.cityscapes import colorize
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, model_display, paper_style, save
from pairedgta.figures.model_report_numbers import Report, pct_text, rank_text, row
from pairedgta.figures.qualitative import disagreement_overlay, draw_strip, strip_geometry

SUBJECT_COLOR, POPULATION_COLOR = "#d62728", "0.55"
CASE_COLUMNS = ("adverse image", "pseudo-label\n(reference, clean)", "prediction", "disagreement with\npseudo-label")


def standing_panel(ax: Any, r: Report, values: np.ndarray, measure: str, title: str) -> None:
    y = np.arange(len(r.conditions))
    rng = np.random.default_rng(0)
    for i in y:
        pop = values[1:, i][np.isfinite(values[1:, i])]
        if pop.size:
            ax.boxplot([pop], positions=[i], vert=False, widths=0.55, showfliers=False, patch_artist=True,
                       boxprops={"facecolor": "0.92", "edgecolor": "0.5", "linewidth": 0.6},
                       medianprops={"color": "0.3", "linewidth": 0.8}, whiskerprops={"color": "0.5", "linewidth": 0.6},
                       capprops={"color": "0.5", "linewidth": 0.6})
            ax.scatter(pop, i + rng.uniform(-0.18, 0.18, pop.size), s=5, color=POPULATION_COLOR, zorder=3, linewidth=0)
        if math.isfinite(values[0, i]):
            ax.scatter([values[0, i]], [i], marker="D", s=22, color=SUBJECT_COLOR, edgecolor="black", linewidth=0.4,
                       zorder=4)
        d = row(r, r.conditions[i], measure)
        ax.text(1.02, i, f"{rank_text(d)} · {pct_text(d)}%", transform=ax.get_yaxis_transform(), va="center",
                fontsize=5.5)
    ax.text(1.02, 1.0, "rank/n · pct", transform=ax.transAxes, va="bottom", fontsize=5.5, color="0.3")
    ax.set_yticks(y)
    ax.set_yticklabels([condition_display(c) for c in r.conditions])
    ax.set_ylim(len(y) - 0.5, -0.5)
    ax.set_xlim(left=0)
    ax.set_title(title, loc="left")
    ax.grid(axis="x", color="0.9", lw=0.5)


def _loss_panel(ax: Any, r: Report) -> None:
    conds = r.conditions
    y = np.arange(len(conds))
    loss = (r.gt_clean[:, None] - r.gt) if r.has_gt else 1.0 - r.xi
    worst = {d["condition"] for d in r.worst}
    ax.barh(y, np.nan_to_num(loss[0]), height=0.6, color=[SUBJECT_COLOR if c in worst else "0.75" for c in conds],
            edgecolor="black", linewidth=0.3, label=r.subject)
    for i in y:
        pop = loss[1:, i][np.isfinite(loss[1:, i])]
        if pop.size:
            ax.plot([pop.min(), pop.max()], [i, i], color="black", lw=0.6, zorder=3)
            ax.plot([np.median(pop)], [i], marker="|", color="black", ms=7, mew=1.2, zorder=3)
        d = next((w for w in r.worst if w["condition"] == conds[i]), None) or {
            "percentile": row(r, conds[i], "gt_miou_drop" if r.has_gt else "xi_mean")["percentile"]}
        ax.text(1.02, i, f"{pct_text(d)}%", transform=ax.get_yaxis_transform(), va="center", fontsize=5.5)
    ax.text(1.02, 1.0, "pct", transform=ax.transAxes, va="bottom", fontsize=5.5, color="0.3")
    ax.axvline(0, color="0.5", lw=0.5)
    ax.set_yticks(y)
    ax.set_yticklabels([condition_display(c) for c in conds])
    ax.set_ylim(len(y) - 0.5, -0.5)
    ax.set_xlabel(("GT mIoU lost from the clean image" if r.has_gt else "1 − ξ (no ground truth)")
                  + "\nbars: it; lines: the population's range, | median;"
                  + "\npct: the share of the population losing more")
    ax.set_title(f"(c) where it loses most (the {len(worst)} worst in red)", loc="left")


def tracking_panel(ax: Any, r: Report) -> None:
    rows = r.track
    y = np.arange(len(rows))
    level = f"{r.confidence:.0%}"
    for offset, kind, color, label in ((-0.15, "scene", "black", f"{level} over {r.n_scenes} scenes"),
                                       (0.15, "model", "tab:blue", f"{level} over the {len(r.models)} models")):
        v = np.array([t["spearman"] for t in rows], float)
        lo = np.array([t[f"{kind}_ci_low"] for t in rows], float)
        hi = np.array([t[f"{kind}_ci_high"] for t in rows], float)
        has = np.isfinite(v) & np.isfinite(lo) & np.isfinite(hi)
        ax.errorbar(v[has], (y + offset)[has], xerr=[np.maximum(v[has] - lo[has], 0), np.maximum(hi[has] - v[has], 0)],
                    fmt="o", color=color, ms=3, capsize=1.5, lw=0.8, label=label)
        # no interval (undefined, or the resamples did not vary): a hollow marker, never a dot that looks certain
        bare = np.isfinite(v) & ~has
        ax.plot(v[bare], (y + offset)[bare], "o", mfc="none", mec=color, ms=3.5, mew=0.8,
                label="no interval" if bare.any() else None)
    if not np.isfinite([t["spearman"] for t in rows]).any():
        ax.text(0, len(rows) / 2 - 0.5, "undefined: fewer than 3 models,\nor constant values", ha="center", fontsize=6)
    ax.axvline(0, color="0.6", lw=0.6)
    ax.set_xlim(-1.05, 1.05)
    ax.set_yticks(y)
    ax.set_yticklabels([f"{condition_display(t['condition'])} (n={t['n_models']})" if t["condition"] != "mean"
                        else f"mean of {t['n_conditions']}" for t in rows])
    ax.set_ylim(len(y) - 0.5, -0.5)
    ax.set_xlabel("Spearman(ξ, GT mIoU) across models")
    ax.set_title("(e) Spearman(ξ, GT) per condition", loc="left")
    ax.legend(fontsize=5, loc="lower left", frameon=False)


def _rank_panel(ax: Any, r: Report) -> None:
    n = len(r.models)
    pts = [(row(r, c, "gt_miou")["rank"], row(r, c, "xi_mean")["rank"], c) for c in r.conditions]
    pts = [t for t in pts if math.isfinite(t[0]) and math.isfinite(t[1])]
    ax.plot([1, n], [1, n], color="0.7", lw=0.6, ls="--")
    at: dict[tuple[float, float], list[str]] = {}
    for gx, xy, c in pts:
        at.setdefault((gx, xy), []).append(c)
    for (gx, xy), conds in at.items():  # conditions that place it alike share one marker
        ax.scatter([gx], [xy], color=SUBJECT_COLOR, s=10 + 6 * len(conds), edgecolor="black", linewidth=0.3, zorder=3)
        text = condition_display(conds[0]) if len(conds) == 1 else f"{len(conds)} conditions"
        ax.annotate(text, (gx, xy), fontsize=4.5, xytext=(3, -6), textcoords="offset points")
    from matplotlib.ticker import MaxNLocator

    for axis in (ax.xaxis, ax.yaxis):  # whole ranks, few enough not to overlap (the points carry their labels)
        axis.set_major_locator(MaxNLocator(nbins=5, integer=True, min_n_ticks=2))
    ax.set_xlim(n + 0.5, 0.5)
    ax.set_ylim(n + 0.5, 0.5)
    ax.set_xlabel("its GT mIoU rank")
    ax.set_ylabel("its ξ rank")
    ax.set_title(f"its ranks (of {n})", loc="right", fontsize=6.5)


def _case_panels(fig: Any, r: Report, dpi: int) -> None:
    axes = fig.subplots(len(r.cases), 1, squeeze=False)[:, 0]
    geometry = strip_geometry(r.cases[0]["image"].shape[:2], len(CASE_COLUMNS), dpi)
    for i, (ax, c) in enumerate(zip(axes, r.cases)):
        shown = [c["image"], colorize(c["pseudo"]), colorize(c["prediction"]),
                 disagreement_overlay(c["image"], c["prediction"], c["pseudo"])]
        draw_strip(ax, shown, [j > 0 for j in range(len(shown))], geometry, CASE_COLUMNS if i == 0 else None,
                   fontsize=5.5)
        ax.set_ylabel(f"{condition_display(c['condition'])}\n{c['pair_id']}\nagreement {c['agreement']:.2f}",
                      fontsize=5)
    fig.suptitle(f"(d) its {len(r.cases)} worst images (lowest pixel agreement with the pseudo-labels)", x=0.02,
                 ha="left", fontsize=8)


def page(r: Report, out: Path, stem: str, opts: FigureOptions) -> list[Path]:
    n_cond = max(1, len(r.conditions))
    top_h = 0.28 * n_cond + 0.9
    case_h = 0.0
    if r.cases:  # each case a strip of its columns across the page, at the images' aspect
        h0, w0 = r.cases[0]["image"].shape[:2]
        case_h = len(r.cases) * (0.9 * TEXT_WIDTH * h0 / w0 / len(CASE_COLUMNS) + 0.08) + 0.45
    with paper_style():
        fig = plt.figure(figsize=(TEXT_WIDTH, 2 * top_h + case_h + 0.5), layout="constrained")
        parts = fig.subfigures(3 if r.cases else 2, 1, height_ratios=[top_h, top_h] + ([case_h] if r.cases else []))
        a, b = parts[0].subplots(1, 2, sharey=True)
        standing_panel(a, r, r.xi, "xi_mean", f"(a) mean ξ vs {r.reference}'s pseudo-labels")
        standing_panel(b, r, r.gt, "gt_miou", "(b) GT mIoU")
        a.set_xlabel("mean ξ (rank/n · percentile at right)")
        b.set_xlabel("GT mIoU (rank/n · percentile at right)")
        c, e, k = parts[1].subplots(1, 3, gridspec_kw={"width_ratios": [1.0, 1.1, 0.55]})
        _loss_panel(c, r)
        tracking_panel(e, r)
        _rank_panel(k, r)
        if r.cases:
            _case_panels(parts[2], r, opts.dpi)
        fig.suptitle(f"{model_display(r.subject)} against {len(r.population)} model(s) · {r.n_scenes} scenes · "
                     f"{r.reference}'s pseudo-labels (diamond: {r.subject}; box and points: the population)",
                     fontsize=8)
        return save(fig, out, stem, opts.formats, opts.dpi)
