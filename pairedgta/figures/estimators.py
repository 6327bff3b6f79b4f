"""Is xi the best label-free judge of robustness? (experiment metric_validity, figure `estimators`)

Reads each model's per-group sums (`e.group_counts()`, evaluate's `est_*` arrays) and argmax predictions
(`predictions.npz`, for the agreement between models), and compares label-free estimators of robustness
(pairedgta.metrics.estimators: xi, AC, DoC, ATC, their relative versions, entropy, committee agreement,
ALine-S and ALine-D, self-agreement, clean mIoU and clean mIoU x self-agreement, xi's precision and the F of xi and
its precision) as judges of
rPC and adverse GT mIoU across the models other than the reference. Writes estimators.csv (one row per
estimator, target and scope), estimators.md (the headline tables), estimator_cells.csv (one row per model
and condition) and a figure: each estimator against rPC, and the within-condition mean Spearman of each
with its scene and scene+model intervals."""
from __future__ import annotations

import contextlib
import math
import textwrap
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.schema import as_dict
from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.errors import ConfigError
from pairedgta.evaluation.entry import PREDICTIONS
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, markdown_table, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.figures.validity import FIX, evaluated_on_every_pass, references
from pairedgta.metrics import mean_mask
from pairedgta.metrics.conventions import convention_from_config
from pairedgta.metrics.estimator_study import PAIR_COLUMNS, compare, ranked_models
from pairedgta.metrics.estimators import (COUNT_ARRAYS, ESTIMATORS, MIN_RANKED, TARGETS, USES_CLEAN_LABELS, EstimatorCounts,
                                          concat_counts, pairwise_agreement)
from pairedgta.metrics.validity import GroupCounts, concat_groups

NAMES = {"xi": "ξ (label-free)", "xi_rel": "relative ξ", "ac": "AC", "ac_rel": "relative AC", "doc": "DoC",
         "atc": "ATC", "atc_rel": "relative ATC", "entropy": "1 − entropy",
         "nuclear_norm": "nuclear norm (Deng et al.)", "energy": "energy (mean logsumexp)",
         "committee_agreement": "committee agreement (not GDE)", "gde": "GDE (agreement with its twin)", "aline_s": "ALine-S (pixel acc.)",
         "aline_d": "ALine-D (pixel acc.)", "self_agreement": "self-agreement",
         "clean_miou": "clean GT mIoU", "clean_miou_x_self_agreement": "clean GT mIoU × self-agreement",
         "xi_precision": "ξ precision (label-free)", "xi_f": "ξ F (harmonic mean of ξ and its precision)"}
TARGET_TEXT = {"rpc": "rPC", "gt_miou": "adverse GT mIoU"}
STATS = ("spearman", "kendall", "mae", "p_permutation", "p_permutation_holm", "p_minus_xi_holm")


def settings(opts: FigureOptions) -> dict[str, Any]:
    metric, boot = opts.run.metric, opts.run.metric.bootstrap
    return {"permutations": metric.validity.permutations, "resamples": boot.resamples, "confidence": boot.confidence,
            "seed": boot.seed, "reference_model": opts.run.reference_model,
            "rpc_min_clean_miou": metric.validity.rpc_min_clean_miou,
            "twins": [list(map(str, pair)) for pair in (metric.validity.twins or [])]}


def cache_key(passes: Passes, opts: FigureOptions) -> tuple[dict[str, Any], dict[str, str]]:
    """What the figure reads beyond the evaluations (the plot stage's cache key): permutations, reference."""
    return settings(opts), {}


def load(passes: Passes) -> tuple[list[GroupCounts], list[EstimatorCounts], dict[str, list[Path]]]:
    """Per model evaluated on every pass (sorted by name): its groups of every pass, and the pass's
    predictions.npz paths."""
    full = evaluated_on_every_pass(passes, "estimators", (*COUNT_ARRAYS, "pseudo_label_predicted"))  # xi's precision
    return ([concat_groups(GroupCounts.from_arrays(m, counts) for counts, _ in parts) for m, parts in full.items()],
            [concat_counts(EstimatorCounts.from_arrays(m, counts) for counts, _ in parts) for m, parts in full.items()],
            {m: [path for _, path in parts] for m, parts in full.items()})


def agreement(models: list[GroupCounts], paths: dict[str, list[Path]], n_passes: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise agreement of the given models per group, pass after pass (the order of concat_groups)."""
    agree, scored, start = [], [], 0
    for k in range(n_passes):
        with contextlib.ExitStack() as stack:
            sources = []
            for m in models:
                path = paths[m.model][k] / PREDICTIONS
                if not path.is_file():
                    raise ConfigError(f"plot.figures: estimators needs {path} (the argmax predictions, for the agreement between models); {FIX}")
                z = stack.enter_context(np.load(path, allow_pickle=False))
                ids = [str(g) for g in z["group_id"]]
                n = len(ids)
                want = [g.split(":", 1)[1] for g in m.group_ids[start : start + n]] if m.group_ids else ids
                conds = tuple(str(c) for c in z["conditions"])
                if ids != want or conds != m.conditions:
                    raise ConfigError(f"plot.figures: {path} holds other groups or conditions than its group_counts.npz; {FIX}")
                sources.append(z)
            a, s = pairwise_agreement(sources, n)
        agree.append(a)
        scored.append(s)
        start += n
    return np.concatenate(agree), np.concatenate(scored)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    models, counts, paths = load(passes)
    refs = references(passes, opts)
    ranked = ranked_models([m.model for m in models], refs)
    if len(ranked) < MIN_RANKED:
        raise ConfigError(f"plot.figures: estimators ranks the models other than the reference "
                          f"({', '.join(sorted(refs)) or 'none'}) evaluated on every pass and found {len(ranked)} "
                          f"({', '.join(ranked) or 'none'}); evaluate at least {MIN_RANKED} besides it (models=[...])")
    conv = convention_from_config(as_dict(opts.run.metric))
    s = settings(opts)
    unknown = sorted({m for pair in s["twins"] for m in pair} - set(ranked))
    if unknown:
        raise ConfigError(f"metric.validity.twins names {', '.join(unknown)}, not among the ranked models "
                          f"({', '.join(ranked)}); fix the name, add it to models=[...] or drop its pair")
    clean = opts.run.metric.rho.clean_condition or passes[0].grid.reference
    agree, scored = agreement([m for m in models if m.model in ranked], paths, len(passes))
    cells, stats, pairs = compare(models, counts, agree, scored, clean, mean_mask(NUM_CLASSES, CLASS_NAMES, conv.mean_exclude),
                           refs, conv.absent, s["resamples"], s["confidence"], s["seed"], s["permutations"],
                           conv.min_images, conv.min_pixels, s["rpc_min_clean_miou"], twins=s["twins"])
    cells_df, stats_df, pairs_df = pd.DataFrame(cells), pd.DataFrame(stats), pd.DataFrame(pairs, columns=PAIR_COLUMNS)
    cells_df["convention"] = stats_df["convention"] = pairs_df["convention"] = conv.name
    cells_df.to_csv(out / "estimator_cells.csv", index=False)
    stats_df.to_csv(out / "estimators.csv", index=False)
    pairs_df.to_csv(out / "estimator_pairs.csv", index=False)
    (out / "estimators.md").write_text(markdown(stats_df, refs, s["confidence"], cells_df, s["rpc_min_clean_miou"]))
    files = [out / "estimators.csv", out / "estimators.md", out / "estimator_cells.csv", out / "estimator_pairs.csv"]
    files += _figure(cells_df, stats_df, out, opts, s["confidence"])
    metrics: dict[str, float] = {}
    for row in stats_df.to_dict("records"):
        for stat in STATS:
            v = row.get(stat)
            if v is not None and not (isinstance(v, float) and math.isnan(v)):
                metrics[f"validity/{row['estimator']}/{row['target']}/{stat}/{row['scope']}"] = float(v)
    return files, metrics


def _label(e: str, n_models: float, n_all: float) -> str:
    """An estimator's name, with its model count where it is judged over fewer models than the rest (GDE)."""
    return NAMES[e] + (f" ({int(n_models)} models)" if n_models != n_all else "")


def _num(v: float, fmt: str = "{:.2f}") -> str:
    return "–" if v is None or not math.isfinite(v) else fmt.format(v)


def _atc_pixels(cells: pd.DataFrame | None) -> str:
    """Where ATC's clean accuracy (labelled pixels) and its confidence shares (every pixel) cover different
    pixels, a sentence that says by how much; nothing where they are the same pixels."""
    if cells is None or "atc_labelled_share" not in cells:
        return ""
    share = cells["atc_labelled_share"].dropna()
    if share.empty or share.min() >= 1 - 1e-9:
        return ""
    return (f" Its clean accuracy counts the labelled pixels, {share.min():.1%}–{share.max():.1%} of all, its "
            f"confidence shares every pixel: not the same pixels here.")


def _mae(row: pd.Series | None, key: str = "mae") -> str:
    """`0.052 [0.041, 0.066]`; – where the grid has no such hold-out (one illumination, a ladder)."""
    if row is None:
        return "–"
    return _num(row[key], "{:.3f}") + " " + _ci(row[f"{key}_ci_low"], row[f"{key}_ci_high"], "{:.3f}")


def _ci(lo: float, hi: float, fmt: str = "{:.2f}") -> str:
    return "–" if not (math.isfinite(lo) and math.isfinite(hi)) else f"[{fmt.format(lo)}, {fmt.format(hi)}]"


def markdown(stats: pd.DataFrame, refs: set[str], confidence: float, cells: pd.DataFrame | None = None,
             rpc_floor: float = 0.0) -> str:
    """One table per target: estimators sorted by their within-condition mean Spearman."""
    first = stats.iloc[0]
    low = [] if cells is None else sorted(set(cells.loc[cells["gt_miou_clean"] < rpc_floor, "model"]))
    text = [f"# Label-free estimators of robustness\n\nRanked: {int(first['n_models'])} models (the reference model "
            f"{', '.join(sorted(refs)) or '–'} is excluded: its pseudo-labels are what ξ counts), {int(first['n_groups'])} "
            f"scenes. Intervals at {confidence:.0%}: the percentile bootstrap over scenes (the models held fixed: a "
            f"statement about these models only), and BCa over scenes and models drawn together, the same draws for "
            f"every estimator, so that a difference of two is paired in both. p: permutation test of the model labels, "
            f"one order applied to every condition (the joint null); p of − ξ: the paired BCa interval inverted "
            f"(H0: no difference). Holm: adjusted over the estimators of one target. DoC, ATC and clean GT mIoU use "
            f"the clean condition's ground truth; no estimator uses a label of an adverse condition. Every pair of "
            f"estimators: estimator_pairs.csv. ATC's threshold is fitted on held-out clean scenes (the scenes in two "
            f"halves, each scored with the threshold of the other half's clean images). GDE is defined for the models "
            f"trained twice (metric.validity.twins) and judged over those alone, its − ξ on the same models."
            f"{_atc_pixels(cells)}\n"]
    for t in TARGETS:
        part = stats[stats["target"] == t].set_index(["estimator", "scope"])
        order = sorted(ESTIMATORS, key=lambda e: -np.nan_to_num(part.loc[(e, "within_mean"), "spearman"], nan=-9))
        rows = []
        for e in order:
            w, pooled, loco = part.loc[(e, "within_mean")], part.loc[(e, "pooled")], part.loc[(e, "loco")]
            loio = part.loc[(e, "loio")] if (e, "loio") in part.index else None
            rows.append([_label(e, w["n_models"], first["n_models"]) + (" *" if e in USES_CLEAN_LABELS else ""),
                         _num(w["spearman"]),
                         _ci(w["spearman_ci_low"], w["spearman_ci_high"]),
                         _ci(w["spearman_model_ci_low"], w["spearman_model_ci_high"]), _num(w["p_permutation"], "{:.4f}"),
                         _num(w["p_permutation_holm"], "{:.4f}"),
                         ("–" if e == "xi" else _num(w["spearman_minus_xi"], "{:+.2f}") + " "
                          + _ci(w["spearman_minus_xi_ci_low"], w["spearman_minus_xi_ci_high"])),
                         "–" if e == "xi" else _num(w["p_minus_xi"], "{:.3f}"),
                         "–" if e == "xi" else _num(w["p_minus_xi_holm"], "{:.3f}"),
                         _num(pooled["spearman"]), _mae(loco), _mae(loio)])
        undefined = ""
        if t == "rpc" and low:
            undefined = (f"rPC is undefined for {', '.join(low)} (clean GT mIoU below metric.validity.rpc_min_clean_miou = "
                         f"{rpc_floor:g}; a one-class predictor would get 1.0): left out of these rows, "
                         f"{int(part.iloc[0]['n_models'])} models ranked; the adverse GT mIoU below keeps them.\n\n")
        text.append(f"\n## Target: {TARGET_TEXT[t]}\n\n" + undefined + markdown_table(
            ["estimator", "within-condition mean Spearman", "scene CI", "scene+model BCa CI", "p", "p Holm",
             "minus ξ's [paired scene+model BCa CI]", "p", "p Holm",
             "pooled over conditions (mostly orders the conditions)", "LOCO MAE [CI]", "LOIO MAE [CI]"], rows) +
            f"\n\\* uses clean ground truth. MAE of {TARGET_TEXT[t]} predicted by a line fitted on the other "
            f"conditions: leave one condition out (LOCO; a sibling condition of the same time of day stays in the fit) "
            f"and leave one illumination out (LOIO: Day, Sunset, Night; the transfer test), each with its BCa "
            f"interval over scenes and models. No-information baseline (the training cells' mean {TARGET_TEXT[t]}): "
            f"LOCO {_mae(part.loc[(order[0], 'loco')], 'mae_baseline')}, LOIO "
            f"{_mae(part.loc[(order[0], 'loio')] if (order[0], 'loio') in part.index else None, 'mae_baseline')}.\n")
    return "".join(text)


def _figure(cells: pd.DataFrame, stats: pd.DataFrame, out: Path, opts: FigureOptions, level: float) -> list[Path]:
    conds = list(dict.fromkeys(cells["condition"]))
    colors = plt.get_cmap("tab10")
    with paper_style():
        columns = 4
        rows = -(-len(ESTIMATORS) // columns)  # a scatter per estimator; below them, the intervals
        fig = plt.figure(figsize=(TEXT_WIDTH, 1.6 * rows + 0.22 * len(ESTIMATORS) + 0.8))
        grid = fig.add_gridspec(rows + 1, columns, height_ratios=[1.0] * rows + [0.14 * len(ESTIMATORS)])
        axes = [fig.add_subplot(grid[k // columns, k % columns]) for k in range(len(ESTIMATORS))]
        for ax, e in zip(axes, ESTIMATORS):
            for i, c in enumerate(conds):
                part = cells[cells["condition"] == c]
                ax.scatter(part["rpc"], part[e], color=colors(i % 10), s=10, edgecolor="black", linewidth=0.2,
                           label=condition_display(c))
            # short lines: a long title would make tight_layout spread the columns apart
            ax.set_title(textwrap.fill(NAMES[e] + (" (clean labels)" if e in USES_CLEAN_LABELS else ""), 26), fontsize=6)
            ax.set_xlabel("rPC")
        bx = fig.add_subplot(grid[rows, :2])
        part = stats[(stats["target"] == "rpc") & (stats["scope"] == "within_mean")].sort_values("spearman")
        y = np.arange(len(part))
        for offset, kind, color, label in ((0.15, "", "black", "bootstrap over scenes"),
                                           (-0.15, "_model", "0.55", "BCa over scenes + models")):
            v = part["spearman"].to_numpy(float)
            lo, hi = part[f"spearman{kind}_ci_low"].to_numpy(float), part[f"spearman{kind}_ci_high"].to_numpy(float)
            has = np.isfinite(lo) & np.isfinite(hi) & np.isfinite(v)
            # a BCa interval need not hold the point (a strongly biased statistic): never a negative bar
            err = [np.maximum(v[has] - lo[has], 0), np.maximum(hi[has] - v[has], 0)]
            bx.errorbar(v[has], (y + offset)[has], xerr=err, fmt="o", color=color, ms=3,
                        capsize=1.5, lw=0.8, label=f"{level:.0%} {label}")
            bx.plot(v[~has], (y + offset)[~has], "o", mfc="none", mec=color, ms=3.5, mew=0.8,
                    label="no interval" if (~has).any() else None)
        bx.axvline(0, color="0.6", lw=0.6)
        bx.set_xlim(-1.05, 1.05)
        bx.set_yticks(y)
        n_all = int(part["n_models"].max())
        bx.set_yticklabels([_label(e, n, n_all) for e, n in zip(part["estimator"], part["n_models"])])
        bx.set_xlabel("mean within-condition Spearman with rPC")
        bx.set_title(f"{n_all} models, {int(part['n_groups'].iloc[0])} scenes")
        # the verdicts: each estimator minus xi, paired on the same scene and model draws (BCa), both targets
        dx = fig.add_subplot(grid[rows, 2:], sharey=bx)
        for offset, t, color in ((0.15, "rpc", "black"), (-0.15, "gt_miou", "tab:blue")):
            rows_t = stats[(stats["target"] == t) & (stats["scope"] == "within_mean")].set_index("estimator")
            rows_t = rows_t.loc[part["estimator"]]
            v = rows_t["spearman_minus_xi"].to_numpy(float)
            lo, hi = rows_t["spearman_minus_xi_ci_low"].to_numpy(float), rows_t["spearman_minus_xi_ci_high"].to_numpy(float)
            has = np.isfinite(lo) & np.isfinite(hi) & np.isfinite(v) & (part["estimator"].to_numpy() != "xi")
            dx.errorbar(v[has], (y + offset)[has], xerr=[np.maximum(v[has] - lo[has], 0), np.maximum(hi[has] - v[has], 0)],
                        fmt="s", color=color, ms=2.5, capsize=1.5, lw=0.8,
                        label=f"− ξ, {TARGET_TEXT[t]} ({level:.0%} paired BCa, scenes + models)")
        dx.axvline(0, color="0.6", lw=0.6)
        dx.tick_params(labelleft=False)
        dx.set_xlabel("difference to ξ's mean within-condition Spearman")
        dx.set_title("paired differences to ξ (0 inside: tied)")
        handles, labels = [], []
        for ax in (axes[0], bx, dx):  # the conditions' colours, then the intervals
            h, lab = ax.get_legend_handles_labels()
            handles += h
            labels += lab
        fig.tight_layout(rect=(0, 0.07, 1, 1))
        fig.legend(handles, labels, loc="lower center", ncol=min(5, len(labels)), frameon=False, fontsize=5.5)
        return save(fig, out, opts.stem("estimators", "all"), opts.formats, opts.dpi)
