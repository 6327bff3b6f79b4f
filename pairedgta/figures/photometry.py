"""Photometric calibration: this renderer's conditions against GTA V's, with the statistic measured on the
authors' frames (pairedgta/metrics/photometry.py, pairedgta/data/gta_photometry.md). Writes the per-condition
table (photometry.csv), the per-group one, the checks (calibration bands and physics) and one figure."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from pairedgta.cityscapes import CLASS_NAMES  # noqa: E402
from pairedgta.conditions import condition_display  # noqa: E402
from pairedgta.datasets import load_image, load_label  # noqa: E402
from pairedgta.figures import FigureOptions  # noqa: E402
from pairedgta.figures.common import markdown_table, paper_style, save  # noqa: E402
from pairedgta.figures.inputs import Passes
from pairedgta.metrics.photometry import band_checks, group_rows, ladder_checks, physics_checks, summarise  # noqa: E402

DEFAULTS = {"bands": {}, "night_max_luma_ratio": 0.35, "night_sky_max_luma": 0.15, "ladder_max_rise": 0.02}


def settings(opts: FigureOptions) -> dict[str, Any]:
    return {**DEFAULTS, **opts.run.photometry}


def reference_table() -> pd.DataFrame:
    from pairedgta.data import GTA_PHOTOMETRY

    return pd.read_csv(GTA_PHOTOMETRY)


def cache_key(passes: Passes, opts: FigureOptions) -> tuple[dict[str, Any], dict[str, str]]:
    """The settings and the shipped GTA V table's content (the plot stage's cache key)."""
    from pairedgta.data import GTA_PHOTOMETRY

    return json.loads(json.dumps(settings(opts))), {
        "photometry/gta": hashlib.sha256(GTA_PHOTOMETRY.read_bytes()).hexdigest()[:16]}


def measure(dataset: Any, reference: str) -> list[dict[str, Any]]:
    sky = CLASS_NAMES.index("sky")

    def groups():
        for g in dataset.groups:
            labels = load_label(g.labels[reference]) if reference in g.labels else None
            yield g.group_id, {name: load_image(path) for name, path in g.images.items()}, labels

    return group_rows(groups(), reference, sky)


def figure(summary: pd.DataFrame, gta: pd.DataFrame, bands: dict, out: Path, stem: str, formats: list[str],
           dpi: int, label: str) -> list[Path]:
    """Per adverse condition: the median ratio over groups with its range, GTA V's beside it (median and
    range over its 12 groups) and the calibration band."""
    rows = summary[summary["luma_ratio_median"].notna()].reset_index(drop=True)
    x = np.arange(len(rows))
    with paper_style():
        fig, axes = plt.subplots(1, 2, figsize=(7.0, 2.6), sharey=True)
        for ax, stat, title in zip(axes, ("luma_ratio", "contrast_ratio"), ("mean luma", "RMS contrast")):
            med = rows[f"{stat}_median"].to_numpy()
            err = np.stack([med - rows[f"{stat}_min"].to_numpy(), rows[f"{stat}_max"].to_numpy() - med])
            ax.errorbar(x - 0.12, med, yerr=err, fmt="o", ms=3.5, capsize=2, color="#1f77b4", label=label)
            for i, name in enumerate(rows["condition"]):
                ref = gta[gta["condition"] == name]
                if len(ref):
                    r = ref.iloc[0]
                    ax.errorbar([i + 0.12], [r[f"{stat}_median"]],
                                yerr=[[r[f"{stat}_median"] - r[f"{stat}_min"]], [r[f"{stat}_max"] - r[f"{stat}_median"]]],
                                fmt="s", ms=3.5, capsize=2, color="#d62728",
                                label="GTA V (authors' frames)" if i == rows.index[rows["condition"].isin(gta["condition"])][0] else None)
                band = (bands.get(name) or {}).get(stat)
                if band:
                    ax.fill_between([i - 0.35, i + 0.35], band[0], band[1], color="#d62728", alpha=0.12, lw=0,
                                    label="calibration band" if ax is axes[0] and not ax.get_legend_handles_labels()[1].count("calibration band") else None)
            ax.axhline(1.0, color="grey", lw=0.6, ls=":")
            ax.set_xticks(x, [condition_display(n) for n in rows["condition"]], rotation=45, ha="right")
            ax.set_title(f"{title} / clean (median, range over groups)")
        top = float(np.nanmax(rows[["luma_ratio_max", "contrast_ratio_max"]].to_numpy()))
        axes[0].set_ylim(0, max(1.3, top * 1.05))
        axes[0].set_ylabel("ratio to Day-Sunny")
        axes[0].legend(loc="upper right", fontsize=6)
        fig.tight_layout()
        return save(fig, out, stem, formats, dpi)


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    s = settings(opts)
    gta = reference_table()
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if p.dataset is None or p.generate is None:
            continue
        reference = p.grid.reference
        rows = measure(p.dataset, reference)
        order = [n for n in p.grid.names if n != reference]
        summary = summarise(rows, [reference, *order])
        conditions = {c.name: c for c in p.grid.conditions}
        checks = band_checks(summary, s["bands"]) + physics_checks(
            summary, conditions, reference, float(s["night_max_luma_ratio"]), float(s["night_sky_max_luma"]))
        if p.grid.ladder is not None and p.grid.ladder.parameter == "sun_elevation_deg":  # the light ladder
            checks += ladder_checks(summary, [reference, *order], float(s["ladder_max_rise"]),
                                    float(s["night_max_luma_ratio"]))
        stem = opts.stem("photometry", p.label)
        table = pd.DataFrame(summary)
        for col in ("luma_ratio_median", "contrast_ratio_median"):
            ref = gta.set_index("condition")[col] if col in gta else None
            if ref is not None:
                table[f"gta_{col}"] = table["condition"].map(ref)
        _write(out / f"{stem}.csv", table.to_csv(index=False, float_format="%.4f"))
        _write(out / f"{stem}_groups.csv", pd.DataFrame(rows).to_csv(index=False, float_format="%.4f"))
        _write(out / f"{stem}_checks.csv", pd.DataFrame(checks, columns=["check", "value", "ok"]).to_csv(index=False))
        md = markdown_table(
            ["condition", "luma ratio (range)", "GTA V", "contrast ratio (range)", "GTA V", "luma", "sky luma", "R, G, B"],
            [[condition_display(r["condition"]),
              f"{r['luma_ratio_median']:.3f} ({r['luma_ratio_min']:.3f}-{r['luma_ratio_max']:.3f})",
              _gta(gta, r["condition"], "luma_ratio"),
              f"{r['contrast_ratio_median']:.3f} ({r['contrast_ratio_min']:.3f}-{r['contrast_ratio_max']:.3f})",
              _gta(gta, r["condition"], "contrast_ratio"), f"{r['luma_median']:.3f}", f"{r['sky_luma_median']:.3f}",
              f"{r['r_median']:.3f}, {r['g_median']:.3f}, {r['b_median']:.3f}"] for r in summary])
        md += "\n" + markdown_table(["check", "value", "ok"],
                                    [[c["check"], f"{c['value']:.4f}", "yes" if c["ok"] else "**no**"] for c in checks],
                                    ["l", "r", "l"])
        _write(out / f"{stem}.md", md)
        files += [out / f"{stem}.csv", out / f"{stem}_groups.csv", out / f"{stem}_checks.csv", out / f"{stem}.md"]
        files += figure(table, gta, s["bands"], out, stem, opts.formats, opts.dpi, f"this run ({p.label})")
        prefix = "photometry" if not opts.multi else f"photometry/{p.label}"
        for r in summary:
            for stat in ("luma_ratio", "contrast_ratio", "luma", "sky_luma"):
                v = r[f"{stat}_median"]
                if np.isfinite(v):
                    metrics[f"{prefix}/{r['condition']}/{stat}"] = float(v)
        metrics[f"{prefix}/checks_failed"] = float(sum(not c["ok"] for c in checks))
    return files, metrics


def _gta(gta: pd.DataFrame, name: str, stat: str) -> str:
    ref = gta[gta["condition"] == name]
    if not len(ref):
        return "—"
    r = ref.iloc[0]
    return f"{r[f'{stat}_median']:.3f} ({r[f'{stat}_min']:.3f}-{r[f'{stat}_max']:.3f})"
