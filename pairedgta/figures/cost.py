"""The paper's cost figure (fig. time_analysis): per-scene boxplots of pipeline, overhead and total time,
and the average pipeline time split into the three phases of Algorithm 1; one row per timing source
(the paper's CSV beside this project's own generate run)."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import seaborn as sns

from pairedgta.schema import as_dict
from pairedgta.errors import DataError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import TEXT_WIDTH, markdown_table, paper_style, save, slug
from pairedgta.figures.inputs import Passes

log = logging.getLogger("pairedgta.plot")

PHASES = {
    "scene_sampling_time": "Phase 1\nscene sampling",
    "semantic_scene_construction_time": "Phase 2\nscene construction",
    "condition_wise_rendering_time": "Phase 3\nrendering",
}
TIMES = {"pipeline_time": "pipeline", "overhead_time": "overhead", "total_time": "total"}


@dataclass
class Timings:
    label: str
    frame: pd.DataFrame  # one row per scene with PHASES and TIMES columns (NaN where underivable)
    notes: list[str] = field(default_factory=list)


def load_timings(path: str | Path, label: str) -> Timings:
    """Read a timing CSV: the generate stage's timings.csv, or any CSV with the paper's columns.

    Phases and pipeline_time are required. When overhead_time / total_time are absent but the paper's
    global_time (wall clock since the session started) is there, total = its increment per scene (a
    session restarts where it decreases; the first scene of a session counts from the session start,
    so connecting is part of its overhead) and overhead = total - pipeline. Without either, overhead
    and total are left empty and a note says so."""
    path = Path(path)
    try:
        df = pd.read_csv(path)
    except FileNotFoundError:
        raise DataError(f"cost.csv={path} does not exist; give a CSV with the paper's timing columns") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not a readable CSV ({type(exc).__name__})") from None
    missing = [c for c in [*PHASES, "pipeline_time"] if c not in df.columns]
    if missing:
        raise DataError(f"{path}: missing timing column(s) {missing}; need {[*PHASES, 'pipeline_time']}")
    notes: list[str] = []
    if "total_time" not in df.columns and "global_time" in df.columns:
        g = df["global_time"].to_numpy(dtype=float)
        first = np.r_[True, np.diff(g) < 0]
        df["total_time"] = np.where(first, g, g - np.r_[0.0, g[:-1]])
        notes.append(f"total = increment of global_time per scene ({int(first.sum())} session(s); a session's "
                     "first scene counts from its start); overhead = total - pipeline")
    if "overhead_time" not in df.columns:
        if "total_time" in df.columns:
            df["overhead_time"] = df["total_time"] - df["pipeline_time"]
        else:
            df["overhead_time"] = math.nan
            df["total_time"] = math.nan
            notes.append("no overhead_time, total_time or global_time column: overhead and total not derivable")
    return Timings(label, df[[*PHASES, *TIMES]].astype(float), notes)


def summary(t: Timings) -> dict[str, float]:
    f = t.frame
    phase_means = {k: float(f[k].mean()) for k in PHASES}
    phase_sum = sum(phase_means.values())
    out: dict[str, float] = {"scenes": float(len(f))}
    for k, name in TIMES.items():
        col = f[k].dropna()
        out[f"{name}_mean_s"] = float(col.mean()) if len(col) else math.nan
        out[f"{name}_median_s"] = float(col.median()) if len(col) else math.nan
        out[f"{name}_std_s"] = float(col.std(ddof=1)) if len(col) > 1 else math.nan
    for k, v in phase_means.items():
        short = k.replace("_time", "")
        out[f"{short}_mean_s"] = v
        out[f"{short}_share"] = v / phase_sum if phase_sum > 0 else math.nan
    return out


def cost_figure(sources: list[Timings], out: Path, formats: list[str], dpi: int, stem: str = "cost") -> list[Path]:
    with paper_style():
        fig, axes = plt.subplots(len(sources), 2, figsize=(TEXT_WIDTH, 2.0 * len(sources)), squeeze=False,
                                 gridspec_kw={"width_ratios": [1.2, 1]})
        colors = sns.color_palette("colorblind", 6)
        for i, t in enumerate(sources):
            f = t.frame
            long = f[list(TIMES)].rename(columns=TIMES).melt(var_name="what", value_name="seconds").dropna()
            ax = axes[i, 0]
            if not long.empty:
                palette = dict(zip(TIMES.values(), colors[:3]))
                sns.boxplot(data=long, x="what", y="seconds", hue="what", ax=ax, palette=palette, width=0.5,
                            fliersize=2, linewidth=0.7, legend=False, order=[w for w in TIMES.values() if w in set(long["what"])])
            ax.set_xlabel("")
            ax.set_ylabel("time per scene (s)")
            ax.set_title(f"{t.label}: {len(f)} scenes")
            s = summary(t)
            ax2 = axes[i, 1]
            means = [s[f"{k.replace('_time', '')}_mean_s"] for k in PHASES]
            bars = ax2.bar(range(3), means, color=colors[3:6], width=0.6)
            for b, k in zip(bars, PHASES):
                share = s[f"{k.replace('_time', '')}_share"]
                ax2.annotate(f"{b.get_height():.3g} s\n({100 * share:.1f}%)", (b.get_x() + b.get_width() / 2, b.get_height()),
                             ha="center", va="bottom", fontsize=5)
            ax2.set_xticks(range(3), list(PHASES.values()))
            ax2.set_ylabel("mean time (s)")
            ax2.set_ylim(0, max(means) * 1.35 if max(means) > 0 else 1)
            ax2.set_title(f"pipeline {s['pipeline_mean_s']:.3g} s = phases 1\u20133")
            sns.despine(fig)
        fig.tight_layout()
        return save(fig, out, stem, formats, dpi)


def cost_table(sources: list[Timings], out: Path, stem: str = "cost_summary") -> list[Path]:
    rows = [{"source": t.label, **summary(t), "notes": " | ".join(t.notes)} for t in sources]
    pd.DataFrame(rows).to_csv(out / f"{stem}.csv", index=False)
    header = ["Source", "Scenes", "Pipeline (s)", "Overhead (s)", "Total (s)", "Phase 1 (s)", "Phase 2 (s)",
              "Phase 3 (s)", "Phase 2 share", "Phase 3 share"]

    def f(v: float, pct: bool = False) -> str:
        return "–" if v is None or math.isnan(v) else (f"{100 * v:.1f}%" if pct else f"{v:.3g}")

    md = [[r["source"], str(int(r["scenes"])), f(r["pipeline_mean_s"]), f(r["overhead_mean_s"]), f(r["total_mean_s"]),
           f(r["scene_sampling_mean_s"]), f(r["semantic_scene_construction_mean_s"]),
           f(r["condition_wise_rendering_mean_s"]), f(r["semantic_scene_construction_share"], True),
           f(r["condition_wise_rendering_share"], True)] for r in rows]
    notes = "".join(f"\n- {r['source']}: {n}" for r in rows for n in r["notes"].split(" | ") if n)
    (out / f"{stem}.md").write_text("# Generation cost per scene (means)\n\n" + markdown_table(header, md)
                                    + (f"\nDerived values:{notes}\n" if notes else ""))
    return [out / f"{stem}.csv", out / f"{stem}.md"]


def sources(passes: Passes, opts: FigureOptions) -> list[tuple[str, str, Path]]:
    """(metric key, label, CSV) of every timing source: the paper's CSV (cost.paper), then cost.csv or
    each generated pass's own timings."""
    from pairedgta.data import PAPER_GENERATION_TIMES

    ccfg = as_dict(opts.run.cost)
    listed: list[tuple[str, str, Path]] = []
    if ccfg.get("paper", True):
        listed.append(("paper", str(ccfg.get("paper_label") or "paper (GTA V, RTX 2080)"), PAPER_GENERATION_TIMES))
    if ccfg.get("csv"):
        path = Path(str(ccfg["csv"]))
        listed.append((slug(str(ccfg.get("label") or path.stem)), str(ccfg.get("label") or path.stem), path))
        return listed
    for p in passes:
        if p.generate is not None:
            backend = p.run.renderer.get("backend", "renderer")
            label = str(ccfg.get("label") or f"this run ({backend})")
            key = "run" if len(passes) == 1 else f"run_{slug(p.label)}"
            listed.append((key, label if len(passes) == 1 else f"{label} {p.label}", p.generate.timings_csv))
    return listed


def cache_key(passes: Passes, opts: FigureOptions) -> tuple[dict[str, Any], dict[str, str]]:
    """The cost settings, and the content hash of every timing CSV read (the plot stage's cache key)."""
    import hashlib

    inputs = {f"cost/{key}": hashlib.sha256(path.read_bytes()).hexdigest()[:16]
              for key, _, path in sources(passes, opts) if path.is_file()}
    return as_dict(opts.run.cost), inputs


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    listed = sources(passes, opts)
    timings = [load_timings(path, label) for _, label, path in listed]
    if not timings:
        return [], {}
    files = cost_figure(timings, out, opts.formats, opts.dpi) + cost_table(timings, out)
    metrics: dict[str, float] = {}
    for (key, _, _), t in zip(listed, timings):
        for k, v in summary(t).items():
            metrics[f"cost/{key}/{k}"] = v
        for note in t.notes:
            log.info("cost, %s: %s", t.label, note)
    return files, metrics
