"""task=detection, the robustness figure of Michaelis et al. 2019 on real light and weather: COCO AP per condition
for every model against the renderer's boxes (left) and rPC = mPC / P (right), over the adverse conditions and per
time of day and weather (or a ladder's steps)."""
from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.figures.palette import detector_colors, detector_label, detector_order


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        ap = pd.concat([e.gt_ap() for e in p.evaluations] or [pd.DataFrame()], ignore_index=True)
        rob = pd.concat([e.robustness() for e in p.evaluations] or [pd.DataFrame()], ignore_index=True)
        if ap.empty:
            continue
        stem = opts.stem("det_robustness", p.label)
        rob.to_csv(out / f"{stem}.csv", index=False)
        files.append(out / f"{stem}.csv")
        ap = ap[ap["class_name"] == "all"]
        conds = list(dict.fromkeys(ap["condition"]))
        colors = detector_colors([*(e.model for e in p.evaluations), *ap["model"]])  # one per model, every figure
        with paper_style():
            fig, (a1, a2) = plt.subplots(1, 2, figsize=(TEXT_WIDTH * 1.5, 2.6), gridspec_kw={"width_ratios": [3, 2]})
            for model in detector_order(ap["model"]):
                rows = ap[ap["model"] == model].set_index("condition").reindex(conds)
                a1.plot(range(len(conds)), rows["ap"], "o-", color=colors[model], label=detector_label(model), ms=3)
            a1.set_xticks(range(len(conds)), [condition_display(c) for c in conds], rotation=30, ha="right")
            a1.set_ylabel("COCO AP@[.5:.95] (renderer's boxes)")
            a1.set_ylim(bottom=0)
            a1.legend(frameon=False)
            a1.set_title("AP per condition")
            r = rob[rob["metric"] == "ap"] if not rob.empty else rob
            if not r.empty:
                subsets = list(dict.fromkeys(r["conditions"]))
                models = detector_order(r["model"])
                width = 0.8 / max(len(models), 1)
                for i, m in enumerate(models):
                    rows = r[r["model"] == m].set_index("conditions").reindex(subsets)
                    a2.bar([k + i * width for k in range(len(subsets))], rows["rPC"], width, color=colors[m],
                           label=detector_label(m))
                    for s, v in rows["rPC"].items():
                        if pd.notna(v):
                            metrics[f"compare/det_rpc/{s}/{m}".replace("*", "any")] = float(v)
                a2.set_xticks([k + 0.4 - width / 2 for k in range(len(subsets))], subsets, rotation=30, ha="right")
                a2.set_ylabel("rPC = mPC / P")
                a2.set_title("relative performance under the conditions")
            files += save(fig, out, stem, opts.formats, opts.dpi)
    return files, metrics
