"""task=detection, the worst cases with their boxes: per model, the (group, condition) images where it keeps the
smallest share of the reference's clean boxes; each row shows the clean image with the reference's boxes and the
condition's image with the model's confident boxes, the renderer's ground truth dashed in both."""
from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from pairedgta.datasets import load_image
from pairedgta.detection.boxes import INSTANCE_CLASSES, NUM_INSTANCE_CLASSES
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, condition_display, model_display, paper_style, save
from pairedgta.figures.inputs import Passes
from pairedgta.figures.palette import detector_colors
from pairedgta.metrics.detection_xi import image_counts


def _boxes(ax, boxes, labels, color, style="-", scores=None) -> None:
    for i, (b, lab) in enumerate(zip(boxes, labels)):
        x0, y0, x1, y1 = b
        ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec=color, lw=0.8, ls=style))
        if scores is not None:
            ax.text(x0, y0, f"{INSTANCE_CLASSES[lab]} {scores[i]:.2f}", color=color, fontsize=4, va="bottom")


def _from_results(results: list[dict], image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mine = [r for r in results if r["image_id"] == image_id]
    boxes = np.array([[r["bbox"][0], r["bbox"][1], r["bbox"][0] + r["bbox"][2], r["bbox"][1] + r["bbox"][3]]
                      for r in mine], np.float64).reshape(-1, 4)
    return boxes, np.array([r["score"] for r in mine]), np.array([r["category_id"] - 1 for r in mine], np.int64)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    from pairedgta.detection.inputs import image_ids

    files: list[Path] = []
    n_cases = max(1, opts.plot.qualitative_groups)
    for p in passes:
        if p.dataset is None or p.pseudo is None:
            continue
        ids = image_ids(p.dataset)
        groups = {g.group_id: g for g in p.dataset.groups}
        pseudo = p.pseudo.boxes()
        iou = p.run.detection.iou
        colors = detector_colors(e.model for e in p.evaluations)  # the model's boxes in its colour of every figure
        for e in p.evaluations:
            s = e.summary()
            if str(s.get("reference_model")) == e.model:
                continue
            threshold = float(s["score_threshold"])
            cases = []
            for cond in s["conditions"]:
                if cond == p.grid.reference:
                    continue
                results = e.detections(cond)
                for gid, ref in pseudo.items():
                    if not len(ref.labels) or cond not in groups[gid].images:
                        continue
                    boxes, scores, labels = _from_results(results, ids[gid])
                    c = image_counts(ref.boxes, ref.labels, boxes, scores, labels, threshold, iou, NUM_INSTANCE_CLASSES)
                    cases.append((c[1].sum() / c[0].sum(), gid, cond, boxes, scores, labels))
            cases.sort(key=lambda t: (t[0], t[1], t[2]))
            if not cases:
                continue
            chosen = cases[:n_cases]
            with paper_style():
                fig, axes = plt.subplots(len(chosen), 2, figsize=(TEXT_WIDTH, 1.8 * len(chosen)), squeeze=False)
                for row, (share, gid, cond, boxes, scores, labels) in zip(axes, chosen):
                    g = groups[gid]
                    gt_clean = (p.pseudo.ground_truth(p.grid.reference) or {}).get(gid, [])
                    gt_cond = (p.pseudo.ground_truth(cond) or {}).get(gid, [])
                    row[0].imshow(load_image(g.images[p.grid.reference]))
                    _boxes(row[0], [b.xyxy for b in gt_clean], [b.label for b in gt_clean], "white", "--")
                    _boxes(row[0], pseudo[gid].boxes, pseudo[gid].labels, "cyan", scores=pseudo[gid].scores)
                    row[0].set_title(f"{gid} {condition_display(p.grid.reference)}: reference boxes", fontsize=6)
                    row[1].imshow(load_image(g.images[cond]))
                    keep = scores >= threshold
                    _boxes(row[1], [b.xyxy for b in gt_cond], [b.label for b in gt_cond], "white", "--")
                    _boxes(row[1], boxes[keep], labels[keep], colors[e.model], scores=scores[keep])
                    row[1].set_title(f"{condition_display(cond)}: {model_display(e.model)} keeps {share:.0%}",
                                     fontsize=6)
                    for ax in row:
                        ax.axis("off")
                stem = opts.stem(f"det_qualitative_{e.model}", p.label)
                files += opts.own(save(fig, out, stem, opts.formats, opts.dpi), e.model, p.label)
    return files, {}
