"""What every figure shares: paper sizes and style, class order and palette, model and condition names."""
from __future__ import annotations

import contextlib
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pairedgta.cityscapes import CLASS_NAMES, PALETTE
from pairedgta import conditions
# model names and colours live where the MLflow record reads them without matplotlib
from pairedgta.figures.model_colors import MODEL_DISPLAY, model_color_hex

condition_display = conditions.condition_display  # the one naming of conditions, re-exported

# paper widths (inches): one column of a two-column layout, and the full text width
COLUMN_WIDTH = 3.4
TEXT_WIDTH = 7.0
FONT_SIZE = 7

# the class order of every table and figure (Cityscapes train ids) and its colours
CLASS_ORDER: tuple[str, ...] = CLASS_NAMES
CLASS_COLORS = {name: tuple(PALETTE[i] / 255.0) for i, name in enumerate(CLASS_NAMES)}


def class_legend_handles(label_maps) -> list:
    """Cityscapes-colour swatches for the classes present in the given label maps (train ids; void
    ignored), in Cityscapes order: the key a reader needs to read a colourised prediction."""
    import numpy as np
    from matplotlib.patches import Patch

    present = set()
    for m in label_maps:
        ids = np.unique(np.asarray(m))
        present |= {int(k) for k in ids if 0 <= k < len(CLASS_NAMES)}
    return [Patch(facecolor=CLASS_COLORS[CLASS_NAMES[k]], edgecolor="0.5", linewidth=0.3, label=CLASS_NAMES[k])
            for k in sorted(present)]
CLASS_SHORT = {"traffic light": "T. light", "traffic sign": "T. sign", "motorcycle": "motor."}


def concat_tables(results: Iterable[Any], table: str) -> pd.DataFrame:
    """One table (`xi`, `rho`, `frame_counts`, `agreement`) over several evaluations, through each
    evaluation's own reader (`result.xi()`, ...)."""
    frames = [f for f in (getattr(r, table)() for r in results) if not f.empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def model_display(name: str) -> str:
    return MODEL_DISPLAY.get(name, name)


def model_color(name: str) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    return to_rgb(model_color_hex(name))


def class_short(name: str) -> str:
    return CLASS_SHORT.get(name, name)


def ordered_classes(names: Iterable[str]) -> list[str]:
    present = set(names)
    return [c for c in CLASS_ORDER if c in present]


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower() or "x"


@contextlib.contextmanager
def paper_style() -> Iterator[None]:
    """Small fonts that stay readable when the figure is printed at column or text width."""
    rc = {
        "font.size": FONT_SIZE, "axes.titlesize": FONT_SIZE + 1, "axes.labelsize": FONT_SIZE,
        "xtick.labelsize": FONT_SIZE - 1, "ytick.labelsize": FONT_SIZE - 1, "legend.fontsize": FONT_SIZE - 1,
        "axes.linewidth": 0.6, "lines.linewidth": 1.0, "pdf.fonttype": 42, "ps.fonttype": 42,
        "savefig.bbox": "tight", "savefig.pad_inches": 0.02,
    }
    with plt.style.context("seaborn-v0_8-ticks"), plt.rc_context(rc):
        yield


def save(fig: plt.Figure, out: Path, stem: str, formats: list[str], dpi: int) -> list[Path]:
    paths = []
    for fmt in formats:
        path = out / f"{stem}.{fmt}"
        fig.savefig(path, dpi=dpi, bbox_inches="tight")
        paths.append(path)
    plt.close(fig)
    return paths


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average with shrinking windows at the ends (the paper's trend line)."""
    import pandas as pd

    k = max(1, min(int(window), len(values)))
    return pd.Series(values, dtype=float).rolling(k, min_periods=1, center=True).mean().to_numpy()


def markdown_table(header: list[str], rows: list[list[str]], align: list[str] | None = None) -> str:
    align = align or ["l"] + ["r"] * (len(header) - 1)
    sep = ["---" if a == "l" else "---:" for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


_LATEX = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
          "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\^{}"}


def latex_escape(text: str) -> str:
    return "".join(_LATEX.get(ch, ch) for ch in text)


def read_checked_csv(path: Path, key: str, expected: str, columns: tuple[str, ...], **read: Any) -> pd.DataFrame:
    """A CSV the user gives to a figure (the authors' released files): present, readable, with every
    column and a row; each failure one line naming the key or the file. `expected` names the file."""
    from pairedgta.errors import ConfigError, DataError

    if not path.is_file():
        raise ConfigError(f"{key}={path}: no such file; give the authors' {expected}")
    try:
        df = pd.read_csv(path, **read)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not a readable CSV ({exc.__class__.__name__}); expected columns {', '.join(columns)}") from None
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {missing}; expected {', '.join(columns)}")
    if df.empty:
        raise DataError(f"{path}: no rows")
    return df
