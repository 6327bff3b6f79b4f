"""task=detection, per object: the share of the renderer's objects each model still finds (its operating
threshold, IoU >= detection.iou) against the object's height in pixels, the fog transmittance over its pixels and
the light on it (mean luma of its box) -- where each model stops seeing a pedestrian or a car."""
from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.figures.palette import detector_colors, detector_label, detector_order

PANELS = (("height", "object height (px)"), ("transmittance", "fog transmittance over the object"),
          ("luma", "mean luma of its box (0-1)"))


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    files: list[Path] = []
    for p in passes:
        found = pd.concat([e.objects_found() for e in p.evaluations] or [pd.DataFrame()], ignore_index=True)
        if found.empty:
            continue
        stem = opts.stem("det_objects", p.label)
        found.to_csv(out / f"{stem}.csv", index=False)
        files.append(out / f"{stem}.csv")
        classes = [c for c in ("all", "person", "car") if c in set(found["class_name"])]
        colors = detector_colors([*(e.model for e in p.evaluations), *found["model"]])  # one per model, every figure
        with paper_style():
            fig, axes = plt.subplots(len(classes), len(PANELS), figsize=(TEXT_WIDTH * 1.4, 1.9 * len(classes)),
                                     squeeze=False)
            for r, cls in enumerate(classes):
                for c, (var, xlabel) in enumerate(PANELS):
                    ax = axes[r][c]
                    rows = found[(found["class_name"] == cls) & (found["variable"] == var)]
                    adverse = rows[rows["condition"] != p.grid.reference]
                    for model in detector_order(adverse["model"]):
                        m = adverse[adverse["model"] == model]
                        pooled = m.assign(hits=m["found"] * m["objects"]).groupby("bin_low")[["hits", "objects"]].sum()
                        ax.plot(pooled.index, pooled["hits"] / pooled["objects"], "o-", ms=3, color=colors[model],
                                label=detector_label(model))
                    ax.set_ylim(0, 1.02)
                    ax.set_xlabel(xlabel + " (bin start)")
                    if c == 0:
                        ax.set_ylabel(f"{cls}: share found\n(adverse conditions pooled)")
                    if var == "height":
                        ax.set_xscale("symlog", linthresh=16)
            axes[0][0].legend(frameon=False)
            files += save(fig, out, stem, opts.formats, opts.dpi)
    return files, {}
