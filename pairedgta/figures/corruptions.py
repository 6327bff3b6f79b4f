"""Rendered weather beside the field's 2D corruptions, for either task: per model, its score under each corruption
relative to the clean image (Cityscapes-C's and Michaelis et al.'s relative view) against severity, one line a
corruption, and each rendered adverse condition of the same run drawn at the right on the same scale. The score is the
ground truth's where the dataset has labels (segmentation's GT mIoU, detection's COCO AP), ξ where it has none. Only
a run whose conditions hold corruptions (`conditions=paper_corruptions`) draws it."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from pairedgta.corruption_summary import read_scores
from pairedgta.corruptions import parse_name
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, paper_style, save
from pairedgta.figures.inputs import Passes

PREFERRED = ("gt_miou", "ap", "xi", "detection_xi")  # the first an entry holds is drawn
LABELS = {"gt_miou": "GT mIoU", "ap": "COCO AP", "xi": "ξ", "detection_xi": "detection ξ"}


def relative_scores(entries: list[Path], clean: str) -> tuple[str, pd.DataFrame]:
    """(score name, rows model / condition / corruption / severity / value / relative) of every entry; relative is
    value / the model's clean value (NaN where that is 0 or missing)."""
    tables: dict[str, list[pd.DataFrame]] = {}
    for entry in entries:
        for name, t in read_scores(entry).items():
            tables.setdefault(name, []).append(t)
    name = next((n for n in PREFERRED if n in tables), "")
    if not name:
        return "", pd.DataFrame()
    t = pd.concat(tables[name], ignore_index=True)
    base = t[t["condition"] == clean].set_index("model")["value"]
    parsed = t["condition"].map(parse_name)
    t = t.assign(corruption=[p[0] if p else "" for p in parsed], severity=[p[1] if p else 0 for p in parsed])
    t["relative"] = [v / base[m] if m in base and base[m] and math.isfinite(base[m]) else math.nan
                     for m, v in zip(t["model"], t["value"])]
    return name, t[t["condition"] != clean].reset_index(drop=True)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if p.dataset is None or not p.evaluations:
            continue
        name, t = relative_scores([e.path for e in p.evaluations], p.dataset.reference)
        if t.empty or not (t["corruption"] != "").any():
            continue
        stem = opts.stem("corruptions", p.label)
        t.to_csv(out / f"{stem}.csv", index=False)
        files.append(out / f"{stem}.csv")
        models = list(dict.fromkeys(t["model"]))
        corruptions = list(dict.fromkeys(t.loc[t["corruption"] != "", "corruption"]))
        rendered = list(dict.fromkeys(t.loc[t["corruption"] == "", "condition"]))
        cols = min(len(models), 3)
        rows = math.ceil(len(models) / cols)
        cmap = plt.get_cmap("tab20")
        with paper_style():
            fig, axes = plt.subplots(rows, cols, figsize=(TEXT_WIDTH * 1.5, 2.4 * rows), squeeze=False, sharey=True)
            for ax, model in zip(axes.flat, models):
                m = t[t["model"] == model]
                for i, c in enumerate(corruptions):
                    line = m[m["corruption"] == c].sort_values("severity")
                    ax.plot(line["severity"], line["relative"], "o-", ms=2, lw=0.8, color=cmap(i % 20), label=c)
                top = max(m["severity"].max(), 1)
                for k, cond in enumerate(rendered):  # the rendered conditions, beside the severities
                    v = m.loc[m["condition"] == cond, "relative"]
                    x = top + 1 + k * 0.5
                    ax.plot([x], v.to_numpy()[:1], "kD", ms=3)
                    if len(v):
                        metrics[f"compare/corruptions_relative/{cond}/{model}"] = float(v.iloc[0])
                ax.set_xticks([*sorted(set(m.loc[m["corruption"] != "", "severity"])),
                               *(top + 1 + k * 0.5 for k in range(len(rendered)))],
                              [*map(str, sorted(set(m.loc[m["corruption"] != "", "severity"]))),
                               *(condition_display(c) for c in rendered)], rotation=60, ha="right", fontsize=5)
                ax.set_title(model)
                ax.axhline(1.0, color="0.7", lw=0.5)
            for ax in list(axes.flat)[len(models):]:
                ax.set_visible(False)
            axes[0, 0].set_ylabel(f"{LABELS.get(name, name)} / clean")
            axes[0, 0].legend(frameon=False, fontsize=4, ncol=2)
            fig.suptitle("2D corruptions by severity (lines) beside the rendered conditions (diamonds)", fontsize=7)
            files += save(fig, out, stem, opts.formats, opts.dpi)
    return files, metrics
