"""Qualitative grids: for each adverse condition the worst and best groups by per-image agreement with
the pseudo-label (pixel_agreement.csv), as clean image | clean prediction | adverse image | adverse
prediction | adverse confidence | disagreement overlay, in the Cityscapes palette.

The label maps and the max probability are evaluate's own (its entry's predictions.npz, the confidence at half
resolution, what a sixth of the page shows); an entry written before it kept the confidence has the shown images
predicted again. The agreement recomputed from the shown maps is written next to evaluate's, which checks that
the figure shows the images evaluate scored: to within AGREEMENT_TOL, as a batch of another size (evaluate predicts
evaluate.batch_size conditions at once, a re-prediction the image alone) may flip a few boundary pixels."""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Patch
import pandas as pd
from PIL import Image

from pairedgta.cityscapes import IGNORE_INDEX, colorize
from pairedgta.datasets import LabelMaps, PairedDataset, load_group_images
from pairedgta.evaluation.entry import PREDICTIONS, read_prediction
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import (
    TEXT_WIDTH,
    class_legend_handles,
    condition_display,
    model_display,
    paper_style,
    save,
    slug,
)
from pairedgta.figures.inputs import Passes

log = logging.getLogger("pairedgta.plot")
COLUMNS = ("clean image", "clean\nprediction", "adverse image", "adverse\nprediction", "adverse\nconfidence",
           "disagreement with\npseudo-label")
RED, GREEN = np.array([230, 25, 25]), np.array([40, 200, 60])
DISAGREE, AGREE = 0.65, 0.3  # how much of the colour is mixed into the dimmed image
AGREEMENT_TOL = 1e-3  # a tenth of a percent of the valid pixels (131 of a 512x256 image)
MID_GREY = np.full(3, 64.0)  # a typical dimmed pixel, for the legend's swatches
LEGEND = (("disagrees with the pseudo-label", (1 - DISAGREE) * MID_GREY + DISAGREE * RED),
          ("agrees with the pseudo-label", (1 - AGREE) * MID_GREY + AGREE * GREEN),
          ("void: no pseudo-label (confidence < \u03c4)", MID_GREY))


def select_groups(agreement: pd.DataFrame, conditions: list[str], n: int) -> list[dict[str, Any]]:
    """Per condition the ceil(n/2) worst and floor(n/2) best groups by agreement_reference
    (groups without valid pixels are left out; ties break by group id; a group is shown once)."""
    picks = []
    per = agreement[(agreement["pair_id"] != "ALL") & agreement["agreement_reference"].notna()]
    n_worst, n_best = math.ceil(n / 2), n // 2
    for cond in conditions:
        g = per[per["condition"] == cond].sort_values(["agreement_reference", "pair_id"], kind="stable")
        if g.empty:
            continue
        worst = g.head(n_worst)
        best = g[~g["pair_id"].isin(worst["pair_id"])].tail(n_best).iloc[::-1]
        for kind, rows in (("worst", worst), ("best", best)):
            for row in rows.itertuples():
                picks.append({"condition": cond, "kind": kind, "pair_id": str(row.pair_id),
                              "agreement": float(row.agreement_reference)})
    return picks


def disagreement_overlay(image: np.ndarray, pred: np.ndarray, pseudo: np.ndarray) -> np.ndarray:
    """The image dimmed to grey; red where the prediction differs from a valid pseudo-label, green where
    it agrees; void pixels stay grey."""
    grey = image.astype(float).mean(axis=-1, keepdims=True).repeat(3, axis=-1) * 0.5
    valid = pseudo != IGNORE_INDEX
    out = grey.copy()
    out[valid & (pred != pseudo)] = (1 - DISAGREE) * grey[valid & (pred != pseudo)] + DISAGREE * RED
    out[valid & (pred == pseudo)] = (1 - AGREE) * grey[valid & (pred == pseudo)] + AGREE * GREEN
    return np.clip(out, 0, 255).astype(np.uint8)


def strip_geometry(shape: tuple[int, int], columns: int, dpi: int) -> tuple[int, int, int, int]:
    """(w, h, gap, strip width) of a row of `columns` images of `shape`, each at the pixel width it gets on the page
    (at `dpi`): matplotlib would otherwise resample every full-size strip on every draw, most of a grid's time."""
    h0, w0 = shape
    w = max(8, min(w0, int(TEXT_WIDTH * dpi / columns)))
    h = max(4, round(h0 * w / w0))
    gap = max(2, w // 64)  # white between the columns, in pixels
    return w, h, gap, columns * w + (columns - 1) * gap


def draw_strip(ax: Any, shown: list[np.ndarray], exact: list[bool], geometry: tuple[int, int, int, int],
               names: list[str] | tuple[str, ...] | None, fontsize: float) -> None:
    """One row of images side by side in one axes (6x fewer axes to lay out than a grid of panels); label maps
    (`exact`) resized by nearest neighbour so their colours stay exact; `names` above the columns."""
    w, h, gap, strip_w = geometry
    strip = np.full((h, strip_w, 3), 255, dtype=np.uint8)
    for j, im in enumerate(shown):
        strip[:, j * (w + gap): j * (w + gap) + w] = fit(im, w, h, exact=exact[j])
    ax.imshow(strip, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)
    for j, name in enumerate(names or ()):
        ax.text(j * (w + gap) + w / 2, -0.04 * h, name, ha="center", va="bottom", fontsize=fontsize)


def fit(image: np.ndarray, w: int, h: int, exact: bool) -> np.ndarray:
    """`image` at w x h: area-averaged for photographs, nearest for colour-coded maps."""
    if image.shape[:2] == (h, w):
        return image
    resample = Image.Resampling.NEAREST if exact else Image.Resampling.BOX
    return np.asarray(Image.fromarray(np.ascontiguousarray(image)).resize((w, h), resample))


class Predictions:
    """The label maps (and max probability) of the shown images: evaluate's, stored in its entry's predictions.npz;
    predicted again only where the entry has none (one written before it kept the confidence)."""

    def __init__(self, stored: Path | None, model_cfg: dict[str, Any], device: str, confidence: bool = True) -> None:
        self.stored, self.model_cfg, self.device, self.confidence = stored, model_cfg, device, confidence
        self.predicted = 0  # images predicted again (none for an entry of this release)

    def __call__(self, group: Any, condition: str, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        found = read_prediction(self.stored, group.group_id, condition) if self.stored is not None else None
        if found is not None and (found[1] is not None or not self.confidence):
            return found
        from pairedgta.models import shared_model

        segmenter = shared_model(self.model_cfg, device=self.device)  # the one evaluate loaded, within a run
        labels, conf = segmenter.predict(image[None])
        self.predicted += 1
        return labels.numpy()[0], conf.numpy()[0]


def qualitative_grid(dataset: PairedDataset, pseudo_labels: LabelMaps, agreement: pd.DataFrame,
                     model_cfg: dict[str, Any], conditions: list[str], n: int, clean: str, out: Path, stem: str,
                     formats: list[str], dpi: int, title: str = "", device: str = "cpu",
                     stored: Path | None = None) -> tuple[list[Path], pd.DataFrame]:
    """`stored`: the evaluate entry's predictions.npz, whose maps the figure shows (else it predicts them again)."""
    picks = select_groups(agreement, conditions, n)
    if not picks:
        return [], pd.DataFrame()
    predictions = Predictions(stored, model_cfg, device)
    groups = {g.group_id: g for g in dataset.groups}
    rows = []
    panels = []
    clean_preds: dict[str, np.ndarray] = {}  # a group shown for several conditions: its clean image once
    for p in picks:
        group = groups.get(p["pair_id"])
        if group is None or p["condition"] not in group.images:
            continue
        images = load_group_images(group, [clean, p["condition"]])
        pseudo = pseudo_labels.load(group.group_id).astype(np.int64)
        adv_pred, adv_conf = predictions(group, p["condition"], images[p["condition"]])
        if group.group_id not in clean_preds:
            clean_preds[group.group_id] = predictions(group, clean, images[clean])[0]
        clean_pred = clean_preds[group.group_id]
        valid = pseudo != IGNORE_INDEX
        recomputed = float(((adv_pred == pseudo) & valid).sum() / valid.sum()) if valid.any() else math.nan
        if not math.isclose(recomputed, p["agreement"], abs_tol=AGREEMENT_TOL):
            log.warning("qualitative %s/%s: recomputed agreement %.4f differs from evaluate's %.4f",
                        p["condition"], group.group_id, recomputed, p["agreement"])
        rows.append({**p, "model": model_cfg["name"], "agreement_recomputed": recomputed})
        panels.append((p, images[clean], clean_pred, images[p["condition"]], adv_pred, adv_conf, pseudo))
    if not panels:
        return [], pd.DataFrame(rows)
    geometry = strip_geometry(panels[0][1].shape[:2], len(COLUMNS), dpi)
    w, h, gap, strip_w = geometry
    viridis = plt.get_cmap("viridis")
    with paper_style():
        # one image per row, its columns side by side: 6x fewer axes to lay out and draw than a grid of
        # panels, which made this figure most of the plot stage's time
        fig, axes = plt.subplots(len(panels), 1, squeeze=False, layout="constrained",
                                 figsize=(TEXT_WIDTH, len(panels) * (TEXT_WIDTH * h / strip_w + 0.12) + 0.75))
        for i, (p, clean_img, clean_pred, adv_img, adv_pred, adv_conf, pseudo) in enumerate(panels):
            shown = [clean_img, colorize(clean_pred), adv_img, colorize(adv_pred),
                     (viridis(np.clip(adv_conf, 0, 1))[..., :3] * 255).astype(np.uint8),
                     disagreement_overlay(adv_img, adv_pred, pseudo)]
            ax = axes[i, 0]
            draw_strip(ax, shown, [j in (1, 3, 5) for j in range(len(shown))], geometry,
                       COLUMNS if i == 0 else None, fontsize=6)
            ax.set_ylabel(f"{p['kind']}: {condition_display(p['condition'])}\n{p['pair_id']}\n"
                          f"agreement {p['agreement']:.2f}", fontsize=5)
        # the confidence column's scale, and what each colour of the disagreement column means
        scale = plt.cm.ScalarMappable(norm=plt.Normalize(0, 1), cmap=viridis)
        bar = fig.colorbar(scale, ax=list(axes[:, 0]), location="bottom", shrink=0.3, aspect=25, pad=0.01)
        bar.set_label("max softmax probability", fontsize=5)
        bar.ax.tick_params(labelsize=5, length=2)
        handles = [Patch(facecolor=colour / 255.0, edgecolor="none", label=text) for text, colour in LEGEND]
        fig.legend(handles=handles, loc="outside lower right", fontsize=5, frameon=False, ncols=1)
        # the key to the prediction columns: the classes they show, in Cityscapes colours
        classes = class_legend_handles([m for panel in panels for m in (panel[2], panel[4])])
        if classes:
            fig.legend(handles=classes, loc="outside lower left", fontsize=5, frameon=False,
                       ncols=min(len(classes), 5), title="predicted classes", title_fontsize=5)
        fig.suptitle(title or model_display(model_cfg["name"]), fontsize=7)
        return save(fig, out, stem, formats, dpi), pd.DataFrame(rows)


def clean_condition(p: Any) -> str:
    clean = p.run.metric.rho.clean_condition
    return clean if clean in p.grid.names else p.grid.reference


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """Worst/best groups per adverse condition for every evaluated model of every pass."""
    n = opts.plot.qualitative_groups
    wanted = opts.plot.qualitative_conditions
    files: list[Path] = []
    tables = []
    for p in passes:
        if not p.evaluations or p.dataset is None or p.pseudo is None or n < 1:
            continue
        clean = clean_condition(p)
        conditions = [c for c in p.grid.names if c != clean and (not wanted or c in wanted)]
        for e in p.evaluations:
            model_cfg = e.model_config()
            paths, table = qualitative_grid(
                p.dataset, p.pseudo.labels, e.agreement(), model_cfg, conditions, n, clean, out,
                opts.stem("qualitative", p.label) + f"_{slug(model_cfg['name'])}", opts.formats, opts.dpi,
                title=f"{p.label} \u00b7 {model_cfg['name']}" if opts.multi else "", device=opts.run.device,
                stored=e.path / PREDICTIONS,
            )
            files += opts.own(paths, model_cfg["name"], p.label)
            if not table.empty:
                table.insert(0, "dataset_label", p.label)
                tables.append(table)
    if tables:
        pd.concat(tables, ignore_index=True).to_csv(out / "qualitative.csv", index=False)
        files.append(out / "qualitative.csv")
    return files, {}
