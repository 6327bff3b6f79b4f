"""The paper's pseudo-label distribution figure (fig. distribution_pseudo_labels): dataset-level pixel mass
per class of the pseudo-labels (histogram.csv of the pseudolabel stage), with one reference image and
its pseudo-label in the Cityscapes palette below."""
from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.gridspec import GridSpec

from pairedgta.cityscapes import colorize
from pairedgta.datasets import PairedDataset, load_image, load_label
from pairedgta.errors import DataError
from pairedgta.figures.common import (
    CLASS_COLORS,
    COLUMN_WIDTH,
    class_short,
    markdown_table,
    model_display,
    paper_style,
    save,
)


def pixel_mass(pseudo_dir: Path) -> pd.DataFrame:
    """histogram.csv in Cityscapes order with the share of valid pixels in percent."""
    hist = pd.read_csv(pseudo_dir / "histogram.csv").sort_values("class_id").reset_index(drop=True)
    hist["percent_of_valid"] = 100 * hist["share_of_valid"]
    return hist


def example_group(pseudo_dir: Path, wanted: str | None) -> str:
    """The configured group, else the group whose pseudo-label keeps the most pixels (ties: first id)."""
    index = pd.read_csv(pseudo_dir / "index.csv", dtype={"group_id": str})
    if wanted is not None:
        if str(wanted) not in set(index["group_id"]):
            raise DataError(f"plot.distribution_example={wanted!r} is not a group of this dataset")
        return str(wanted)
    index = index.sort_values(["valid_pixels", "group_id"], ascending=[False, True], kind="stable")
    return str(index["group_id"].iloc[0])


def distribution_figure(dataset: PairedDataset, pseudo_dir: Path, reference_model: str, tau: float, out: Path,
                        formats: list[str], dpi: int, example: str | None = None,
                        stem: str = "pseudo_label_distribution") -> tuple[list[Path], str]:
    from pairedgta.stages.pseudolabel import label_path

    hist = pixel_mass(pseudo_dir)
    gid = example_group(pseudo_dir, example)
    group = next(g for g in dataset.groups if g.group_id == gid)
    image = load_image(group.images[dataset.reference])
    labels = load_label(label_path(pseudo_dir, gid))
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


def distribution_table(pseudo_dir: Path, out: Path, stem: str = "pixel_mass") -> list[Path]:
    hist = pixel_mass(pseudo_dir)
    hist.to_csv(out / f"{stem}.csv", index=False)
    rows = [[c, f"{int(p):d}", f"{v:.2f}"] for c, p, v in zip(hist["class_name"], hist["pixels"], hist["percent_of_valid"])]
    (out / f"{stem}.md").write_text("# Pseudo-label pixel mass per class\n\n"
                                    + markdown_table(["Class", "Pixels", "% of valid"], rows))
    return [out / f"{stem}.csv", out / f"{stem}.md"]
