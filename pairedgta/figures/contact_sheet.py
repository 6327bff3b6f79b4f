"""Contact sheet: one group in every condition plus its label map, so a person can judge at a glance
whether the renderer's conditions look plausible and the pair is really aligned."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from pairedgta.cityscapes import colorize  # noqa: E402
from pairedgta.conditions import condition_display  # noqa: E402
from pairedgta.datasets import PairedDataset, load_image, load_label  # noqa: E402
from pairedgta.figures import FigureOptions  # noqa: E402
from pairedgta.figures.common import class_legend_handles, save  # noqa: E402
from pairedgta.figures.inputs import Passes


def contact_sheet(dataset: PairedDataset, conditions: list[str], out: Path, formats: list[str], dpi: int,
                  group_index: int = 0, stem: str = "contact_sheet") -> list[Path]:
    if not dataset.groups:
        return []
    group = dataset.groups[min(group_index, len(dataset.groups) - 1)]
    names = [c for c in conditions if c in group.images]
    has_labels = dataset.reference in group.labels
    tiles = len(names) + int(has_labels)
    cols = 3 if tiles > 4 else tiles
    rows = math.ceil(tiles / cols)
    first = load_image(group.images[names[0]])
    aspect = first.shape[0] / first.shape[1]
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * cols * aspect * rows / cols + 0.3 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, name in zip(axes.flat, names):
        ax.imshow(load_image(group.images[name]))
        ax.set_title(condition_display(name), fontsize=8)
    handles = []
    if has_labels:
        ax = axes.flat[len(names)]
        label = load_label(group.labels[dataset.reference])
        ax.imshow(colorize(label))
        ax.set_title("labels (identical in every condition)", fontsize=8)
        handles = class_legend_handles([label])
    fig.suptitle(f"{dataset.name} group {group.group_id}", fontsize=9)
    fig.tight_layout()
    if handles:  # the label tile's key, below the sheet
        fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncols=min(len(handles), 7),
                   fontsize=7, frameon=False, title="classes (Cityscapes colours)", title_fontsize=7)
    return save(fig, out, stem, formats, dpi)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """A contact sheet of the first group of every generated pass."""
    files: list[Path] = []
    for p in passes:
        if p.dataset is not None and p.generate is not None:
            files += contact_sheet(p.dataset, p.grid.names, out, ["png"], opts.dpi, stem=opts.stem("contact_sheet", p.label))
    return files, {}
