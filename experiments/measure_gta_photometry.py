"""Photometric statistics of GTA V conditions, measured on the authors' released qualitative figures.

The PairedGTA repository (github.com/Spearton/PairedGTA) ships, under
`out_cityscapes_final/qualitative_segformer/`, matplotlib figures named `qual_*clean_vs_<Condition>.png`
and `qual_*worst*_<Condition>.png`: a grid with one group (scene) per row and, per row, the clean
image (Day-EXTRASUNNY), its SegFormer prediction, the same scene under <Condition> and its prediction.
This script finds the panels, keeps the two photographs of each row and writes, per condition, the median
(and range) over groups of the adverse/clean ratios of mean luma and RMS contrast:

    python experiments/measure_gta_photometry.py --figures DIR --out pairedgta/data/gta_photometry.csv \
        [--groups per_group.csv]

Panels are located from the figure itself: a pixel is background when all its channels are >= 245 (RGBA is
composited over white first); the horizontal bands of panels are the runs of rows in which at least half of the
pixels are not background (a title line never reaches that), the panels of a band are the runs of columns with
any non-background pixel inside the band, and runs shorter than half the longest one are dropped. A panel is a
label (prediction) panel when most of its pixels are exactly Cityscapes palette colours; each row must then hold
exactly two photographs: the left one is the clean image, the right one the adverse image. Statistics skip a
`--border` (3 px) frame of each panel, where matplotlib's resampling mixes in the white background.

Luma is Rec. 709 on the sRGB-encoded values scaled to 0-1 (Y' = 0.2126 R' + 0.7152 G' + 0.0722 B'), RMS
contrast its population standard deviation over the panel. Only numpy and Pillow are used.
"""
from __future__ import annotations

import argparse
import csv
import re
import sys
from pathlib import Path

import numpy as np
from PIL import Image

WHITE = 245            # a pixel is background when all channels are >= this
ROW_FILL = 0.5         # a row belongs to a panel band when at least this fraction of it is not background
COL_FILL = 0.05        # a column belongs to a panel when at least this fraction of the band's rows is not background
MIN_RUN = 0.5          # runs shorter than this fraction of the longest run are text or specks, not panels
LABEL_FRACTION = 0.5   # a panel is a label map when at least this fraction of its pixels are palette colours
BORDER = 3             # pixels skipped on each side of a panel
LUMA = np.array([0.2126, 0.7152, 0.0722])
CONDITION = re.compile(r"([A-Za-z]+-[A-Za-z]+)\.png$")

# the Cityscapes train-id colours (and black for void): what the prediction panels are drawn with
PALETTE = np.array([
    (128, 64, 128), (244, 35, 232), (70, 70, 70), (102, 102, 156), (190, 153, 153), (153, 153, 153),
    (250, 170, 30), (220, 220, 0), (107, 142, 35), (152, 251, 152), (70, 130, 180), (220, 20, 60),
    (255, 0, 0), (0, 0, 142), (0, 0, 70), (0, 60, 100), (0, 80, 100), (0, 0, 230), (119, 11, 32), (0, 0, 0),
], dtype=np.int64)

GROUP_COLUMNS = ["file", "row", "condition", "clean_luma", "adverse_luma", "luma_ratio", "clean_contrast",
                 "adverse_contrast", "contrast_ratio", "adverse_r", "adverse_g", "adverse_b", "clean_r", "clean_g",
                 "clean_b", "clean_box", "adverse_box", "same_scene_as"]
SUMMARY_COLUMNS = ["condition", "n_groups", "luma_ratio_median", "luma_ratio_min", "luma_ratio_max",
                   "contrast_ratio_median", "contrast_ratio_min", "contrast_ratio_max", "adverse_luma_median",
                   "clean_luma_median", "adverse_r_median", "adverse_g_median", "adverse_b_median", "source_files",
                   "method"]
METHOD = ("panels cropped from the released qualitative figures (grid found from the white gutters); "
          "Rec.709 luma of sRGB values; median over groups")


def load_rgb(path: str | Path) -> np.ndarray:
    """The figure as an HxWx3 uint8 array, transparency composited over white."""
    im = Image.open(path)
    if im.mode in ("RGBA", "LA", "P"):
        im = im.convert("RGBA")
        white = Image.new("RGBA", im.size, (255, 255, 255, 255))
        im = Image.alpha_composite(white, im)
    return np.asarray(im.convert("RGB"))


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open [start, stop) intervals where a 1-D boolean mask is True."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _long_runs(mask: np.ndarray, min_run: float) -> list[tuple[int, int]]:
    found = runs(mask)
    if not found:
        return []
    longest = max(b - a for a, b in found)
    return [(a, b) for a, b in found if b - a >= min_run * longest]


def find_panels(rgb: np.ndarray, *, white: int = WHITE, row_fill: float = ROW_FILL, col_fill: float = COL_FILL,
                min_run: float = MIN_RUN) -> list[list[tuple[int, int, int, int]]]:
    """The panel grid of a figure: one list per band (top to bottom) of (y0, y1, x0, x1) boxes (left to right),
    found from the projections of the non-background pixels (see the module docstring)."""
    ink = (rgb < white).any(axis=-1)
    grid = []
    for y0, y1 in _long_runs(ink.mean(axis=1) >= row_fill, min_run):
        cols = _long_runs(ink[y0:y1].mean(axis=0) >= col_fill, min_run)
        grid.append([(y0, y1, x0, x1) for x0, x1 in cols])
    return grid


def crop(rgb: np.ndarray, box: tuple[int, int, int, int], border: int = BORDER) -> np.ndarray:
    y0, y1, x0, x1 = box
    if y1 - y0 <= 2 * border or x1 - x0 <= 2 * border:
        raise ValueError(f"panel {box} is too small for a {border} px border")
    return rgb[y0 + border:y1 - border, x0 + border:x1 - border]


def label_fraction(panel: np.ndarray) -> float:
    """Fraction of the pixels that are exactly a Cityscapes palette colour (high for a prediction panel)."""
    code = lambda c: (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]  # noqa: E731
    return float(np.isin(code(panel.astype(np.int64)), code(PALETTE)).mean())


def photo_stats(panel: np.ndarray) -> dict[str, float]:
    """Mean Rec. 709 luma, RMS contrast (std of luma) and mean R, G, B of an sRGB uint8 panel, all on 0-1."""
    x = panel[..., :3].astype(np.float64) / 255.0
    y = x @ LUMA
    r, g, b = x.reshape(-1, 3).mean(axis=0)
    return {"luma": float(y.mean()), "contrast": float(y.std()), "r": float(r), "g": float(g), "b": float(b)}


def condition_of(name: str) -> str:
    m = CONDITION.search(name)
    if not m:
        raise ValueError(f"{name}: no <Time>-<WEATHER> condition at the end of the file name")
    return m.group(1)


def thumbnail(panel: np.ndarray) -> np.ndarray:
    """A 32x16 grey thumbnail, to recognise a scene shown in two figures."""
    return np.asarray(Image.fromarray(panel).convert("L").resize((32, 16), Image.BILINEAR), dtype=np.float64)


def measure_figure(path: str | Path, *, border: int = BORDER) -> list[dict]:
    """One dict per row (group) of a figure: the statistics of its clean and adverse photographs."""
    path = Path(path)
    rgb = load_rgb(path)
    grid = find_panels(rgb)
    if not grid:
        raise ValueError(f"{path.name}: no panels found")
    out = []
    for i, band in enumerate(grid):
        photos = [box for box in band if label_fraction(crop(rgb, box, border)) < LABEL_FRACTION]
        if len(photos) != 2:
            raise ValueError(f"{path.name} row {i}: {len(band)} panels of which {len(photos)} photographs, expected 2")
        clean_box, adverse_box = photos
        clean, adverse = crop(rgb, clean_box, border), crop(rgb, adverse_box, border)
        c, a = photo_stats(clean), photo_stats(adverse)
        row = {"file": path.name, "row": i, "condition": condition_of(path.name),
               "clean_luma": c["luma"], "adverse_luma": a["luma"], "luma_ratio": a["luma"] / c["luma"],
               "clean_contrast": c["contrast"], "adverse_contrast": a["contrast"],
               "contrast_ratio": a["contrast"] / c["contrast"],
               "adverse_r": a["r"], "adverse_g": a["g"], "adverse_b": a["b"],
               "clean_r": c["r"], "clean_g": c["g"], "clean_b": c["b"],
               "clean_box": "y{}:{} x{}:{}".format(*clean_box), "adverse_box": "y{}:{} x{}:{}".format(*adverse_box),
               "same_scene_as": "", "_thumb": thumbnail(clean)}
        out.append(row)
    return out


def mark_repeats(groups: list[dict], tol: float = 2.0) -> None:
    """Fill `same_scene_as` for a group whose clean image (and condition) already appeared in an earlier group:
    the figures of one condition may show the same scene twice."""
    for j, g in enumerate(groups):
        for h in groups[:j]:
            if h["condition"] == g["condition"] and np.abs(h["_thumb"] - g["_thumb"]).mean() < tol:
                g["same_scene_as"] = f"{h['file']}:{h['row']}"
                break


def summarize(groups: list[dict]) -> list[dict]:
    """Per condition: median (and min, max) over groups, the figures it came from and the method."""
    out = []
    for cond in sorted({g["condition"] for g in groups}):
        gs = [g for g in groups if g["condition"] == cond]
        col = lambda k: np.array([g[k] for g in gs], dtype=np.float64)  # noqa: E731
        out.append({
            "condition": cond, "n_groups": len(gs),
            "luma_ratio_median": np.median(col("luma_ratio")), "luma_ratio_min": col("luma_ratio").min(),
            "luma_ratio_max": col("luma_ratio").max(),
            "contrast_ratio_median": np.median(col("contrast_ratio")),
            "contrast_ratio_min": col("contrast_ratio").min(), "contrast_ratio_max": col("contrast_ratio").max(),
            "adverse_luma_median": np.median(col("adverse_luma")), "clean_luma_median": np.median(col("clean_luma")),
            "adverse_r_median": np.median(col("adverse_r")), "adverse_g_median": np.median(col("adverse_g")),
            "adverse_b_median": np.median(col("adverse_b")),
            "source_files": ";".join(sorted({g["file"] for g in gs})), "method": METHOD,
        })
    return out


def write_csv(path: str | Path, rows: list[dict], columns: list[str], digits: int = 4) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = lambda v: f"{float(v):.{digits}f}" if isinstance(v, (float, np.floating)) else v  # noqa: E731
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow([fmt(r[c]) for c in columns])


def figures_in(folder: str | Path) -> list[Path]:
    """The clean_vs_<condition> and worst_<condition> figures of a folder, by name."""
    return sorted(p for p in Path(folder).glob("*.png")
                  if ("clean_vs" in p.name or "worst" in p.name) and CONDITION.search(p.name))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--figures", required=True, help="folder holding the qual_*clean_vs_*/qual_*worst* PNGs")
    ap.add_argument("--out", required=True, help="per-condition summary CSV")
    ap.add_argument("--groups", help="also write the per-group CSV here (it is printed either way)")
    ap.add_argument("--border", type=int, default=BORDER, help="pixels skipped on each side of a panel")
    args = ap.parse_args(argv)
    files = figures_in(args.figures)
    if not files:
        ap.error(f"no clean_vs/worst figures in {args.figures}")
    groups = [g for f in files for g in measure_figure(f, border=args.border)]
    mark_repeats(groups)
    if args.groups:
        write_csv(args.groups, groups, GROUP_COLUMNS)
    w = csv.writer(sys.stdout, lineterminator="\n")
    w.writerow(GROUP_COLUMNS)
    for g in groups:
        w.writerow([f"{g[c]:.4f}" if isinstance(g[c], float) else g[c] for c in GROUP_COLUMNS])
    summary = summarize(groups)
    write_csv(args.out, summary, SUMMARY_COLUMNS)
    print(f"\n{len(groups)} groups from {len(files)} figures -> {args.out}")
    for s in summary:
        print(f"{s['condition']}: n={s['n_groups']} luma ratio {s['luma_ratio_median']:.3f} "
              f"({s['luma_ratio_min']:.3f}-{s['luma_ratio_max']:.3f}), contrast ratio "
              f"{s['contrast_ratio_median']:.3f} ({s['contrast_ratio_min']:.3f}-{s['contrast_ratio_max']:.3f}), "
              f"adverse luma {s['adverse_luma_median']:.3f} vs clean {s['clean_luma_median']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
