"""The paper's pseudo-label distribution figure (fig. distribution_pseudo_labels): dataset-level pixel mass
per class of the pseudo-labels (histogram.csv of the pseudolabel stage), with one reference image and
its pseudo-label in the Cityscapes palette below."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.gridspec import GridSpec

from pairedgta.cityscapes import colorize
from pairedgta.datasets import PairedDataset, load_image
from pairedgta.errors import DataError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import (
    CLASS_COLORS,
    COLUMN_WIDTH,
    class_short,
    markdown_table,
    model_display,
    paper_style,
    save,
)
from pairedgta.figures.inputs import Passes


def pixel_mass(pseudo: Any) -> pd.DataFrame:
    """The pseudo-labels' class histogram in Cityscapes order with the share of valid pixels in percent."""
    hist = pseudo.histogram().sort_values("class_id").reset_index(drop=True)
    hist["percent_of_valid"] = 100 * hist["share_of_valid"]
    return hist


def example_group(pseudo: Any, wanted: str | None) -> str:
    """The configured group, else the group whose pseudo-label keeps the most pixels (ties: first id)."""
    index = pseudo.index()
    if wanted is not None:
        if str(wanted) not in set(index["group_id"]):
            raise DataError(f"plot.distribution_example={wanted!r} is not a group of this dataset")
        return str(wanted)
    index = index.sort_values(["valid_pixels", "group_id"], ascending=[False, True], kind="stable")
    return str(index["group_id"].iloc[0])


def distribution_figure(dataset: PairedDataset, pseudo: Any, out: Path, formats: list[str], dpi: int,
                        example: str | None = None, stem: str = "pseudo_label_distribution") -> tuple[list[Path], str]:
    reference_model, tau = pseudo.reference_model(), pseudo.tau()
    hist = pixel_mass(pseudo)
    gid = example_group(pseudo, example)
    group = next(g for g in dataset.groups if g.group_id == gid)
    image = load_image(group.images[dataset.reference])
    labels = pseudo.labels.load(gid)
    void = 1 - float(hist["share_of_all"].sum())  # share_of_all = pixels / all pixels
    with paper_style():
        h, w = image.shape[:2]
        width = COLUMN_WIDTH * 1.4
        image_height = width / 2 * h / w + 0.2
        fig = plt.figure(figsize=(width, 1.6 + image_height))
        gs = GridSpec(2, 2, figure=fig, height_ratios=[1.6, image_height])
        ax = fig.add_subplot(gs[0, :])
        ax.bar(range(len(hist)), hist["percent_of_valid"], color=[CLASS_COLORS[c] for c in hist["class_name"]],
               edgecolor="black", linewidth=0.3)
        ax.set_xticks(range(len(hist)), [class_short(c) for c in hist["class_name"]], rotation=60, ha="right")
        ax.set_yscale("symlog", linthresh=0.1)
        ax.set_ylim(0, 100)
        ax.set_ylabel("pixel mass (% of valid)")
        ax.set_title(f"pseudo-labels of {model_display(reference_model)} (\u03c4={tau:g}); void {100 * void:.1f}% of pixels")
        for j, (img, title) in enumerate(((image, f"reference image ({gid})"), (colorize(labels), "pseudo-label"))):
            a = fig.add_subplot(gs[1, j])
            a.imshow(img, interpolation="nearest")
            a.set_title(title, fontsize=6)
            a.set_xticks([])
            a.set_yticks([])
        fig.tight_layout()
        return save(fig, out, stem, formats, dpi), gid


def distribution_table(pseudo: Any, out: Path, stem: str = "pixel_mass") -> list[Path]:
    hist = pixel_mass(pseudo)
    hist.to_csv(out / f"{stem}.csv", index=False)
    rows = [[c, f"{int(p):d}", f"{v:.2f}"] for c, p, v in zip(hist["class_name"], hist["pixels"], hist["percent_of_valid"])]
    (out / f"{stem}.md").write_text("# Pseudo-label pixel mass per class\n\n"
                                    + markdown_table(["Class", "Pixels", "% of valid"], rows))
    return [out / f"{stem}.csv", out / f"{stem}.md"]


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """Pixel mass per class of each pass's pseudo-labels, with one reference image and its pseudo-label."""
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if p.pseudo is None or p.dataset is None:
            continue
        paths, _example = distribution_figure(p.dataset, p.pseudo, out, opts.formats, opts.dpi,
                                              example=opts.plot.distribution_example,
                                              stem=opts.stem("pseudo_label_distribution", p.label))
        files += paths + distribution_table(p.pseudo, out, stem=opts.stem("pixel_mass", p.label))
        hist = p.pseudo.histogram()
        for r in hist.itertuples():
            metrics[f"pseudo_label/{p.label}/share_of_valid/{r.class_name}"] = r.share_of_valid
        metrics[f"pseudo_label/{p.label}/void_share"] = 1 - float(hist["share_of_all"].sum())
    return files, metrics
