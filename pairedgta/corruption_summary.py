"""The field's summaries of the corruption conditions (C-<corruption>-<severity>, pairedgta/corruptions.py), from the
per-condition tables evaluate writes:

- Cityscapes-C (Kamann & Rother 2020), segmentation: per corruption the mean over its severities of a score (GT mIoU
  from gt_iou.csv, mean xi from xi.csv), and that mean relative to the clean image's score;
- Michaelis et al. 2019 (COCO-C, Cityscapes-C), detection: P = AP on the clean images, mPC = the mean AP over every
  corruption x severity, rPC = mPC / P (from detection_ap.csv; also any per-condition score, e.g. detection xi).

One long table, a row per (model, corruption) and a row `all` per model: `clean` (P), `mean` (mPC over the
corruption's severities, or over everything for `all`), `relative` (rPC). A mean over a condition whose score is
undefined (NaN) is NaN, as a benchmark with a missing cell has no mPC; `complete` says whether the row covers the 15
common corruptions at all 5 severities (the published protocol) or a subset.

Terminal: `python -m pairedgta.corruption_summary ENTRY [ENTRY ...] [--csv PATH]` with evaluate entries. A module of
its own, not in pairedgta.metrics: it reads both tasks' tables, whose names pairedgta.evaluation and .detection own,
and metrics is imported by both."""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Iterable

import pandas as pd

from pairedgta.corruptions import COMMON, SEVERITIES, parse_name

COLUMNS = ["model", "score", "corruption", "severities", "n_conditions", "clean", "mean", "relative", "complete"]


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values and all(math.isfinite(v) for v in values) else math.nan


def summarise(scores: pd.DataFrame, clean: str, score: str = "score") -> pd.DataFrame:
    """`scores` (columns model, condition, value): the Cityscapes-C / Michaelis summary of its corruption conditions
    against `clean` (see the module's doc). Conditions that are not corruptions (rendered ones) are left out."""
    rows = []
    for model, table in scores.groupby("model", sort=False):
        values = {str(c): float(v) for c, v in zip(table["condition"], table["value"])}
        p = values.get(clean, math.nan)
        by: dict[str, dict[int, float]] = {}
        for cond, v in values.items():
            parsed = parse_name(cond)
            if parsed:
                by.setdefault(parsed[0], {})[parsed[1]] = v
        if not by:
            continue

        def row(name: str, cells: list[float], severities: Iterable[int], complete: bool) -> dict:
            mean = _mean(cells)
            rel = mean / p if math.isfinite(mean) and math.isfinite(p) and p > 0 else math.nan
            return {"model": model, "score": score, "corruption": name,
                    "severities": ",".join(str(s) for s in sorted(set(severities))), "n_conditions": len(cells),
                    "clean": p, "mean": mean, "relative": rel, "complete": complete}

        for name, sev in by.items():
            rows.append(row(name, [sev[s] for s in sorted(sev)], sev, set(sev) == set(SEVERITIES)))
        every = [v for sev in by.values() for v in sev.values()]
        full = set(by) == set(COMMON) and all(set(by[c]) == set(SEVERITIES) for c in COMMON)
        rows.append(row("all", every, [s for sev in by.values() for s in sev], full))
    return pd.DataFrame(rows, columns=COLUMNS)


def read_scores(entry: Path) -> dict[str, pd.DataFrame]:
    """The per-condition scores an evaluate entry holds (model, condition, value), by score name: gt_miou, xi, xi_gt
    (segmentation); ap, ap50, detection_xi (detection). Missing files give no score."""
    # the tables' names and the xi source from the modules that write them (imported on use: they import torch)
    from pairedgta.detection.registry import GT_AP as DET_AP
    from pairedgta.detection.registry import XI as DET_XI
    from pairedgta.evaluation.metric import GT as GROUND_TRUTH
    from pairedgta.evaluation.tables import GT_IOU, XI

    entry = Path(entry)
    out: dict[str, pd.DataFrame] = {}

    def take(table: pd.DataFrame, column: str) -> pd.DataFrame:
        return table.rename(columns={column: "value"})[["model", "condition", "value"]].reset_index(drop=True)

    if (entry / GT_IOU).is_file():
        t = pd.read_csv(entry / GT_IOU)
        out["gt_miou"] = take(t[t["class_name"] == "mean"], "iou")
    if (entry / XI).is_file():
        t = pd.read_csv(entry / XI)
        t = t[t["class_name"] == "mean"]
        out["xi"] = take(t[t["reference_model"] != GROUND_TRUTH], "xi")
        if (t["reference_model"] == GROUND_TRUTH).any():
            out["xi_gt"] = take(t[t["reference_model"] == GROUND_TRUTH], "xi")
    if (entry / DET_AP).is_file():
        t = pd.read_csv(entry / DET_AP)
        t = t[t["class_name"] == "all"]
        out["ap"], out["ap50"] = take(t, "ap"), take(t, "ap50")
    if (entry / DET_XI).is_file():
        t = pd.read_csv(entry / DET_XI)
        out["detection_xi"] = take(t[t["class_name"] == "mean"], "xi")
    return out


def entry_summary(entry: Path, clean: str) -> pd.DataFrame:
    """Every score of an evaluate entry summarised (one table, the `score` column says which)."""
    parts = [summarise(t, clean, name) for name, t in read_scores(entry).items()]
    parts = [p for p in parts if len(p)]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=COLUMNS)


def write_csv(table: pd.DataFrame, path: Path) -> Path:
    """Under a temporary name, renamed when complete."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    table.to_csv(tmp, index=False)
    os.replace(tmp, path)
    return path


SUMMARY = "corruption_summary.csv"


def write_entry(entry: Path, clean: str) -> Path | None:
    """Write SUMMARY beside an evaluate entry's tables when they hold corruption conditions (a hook for the evaluate
    stages' build, while the entry is still its temporary folder); None when there are none."""
    table = entry_summary(entry, clean)
    return write_csv(table, Path(entry) / SUMMARY) if len(table) else None


def terminal_summary(entries: Iterable[Path], clean: str) -> str:
    """The lines a run prints after its xi table: per model the `all` rows (mPC, rPC) of each score, or "" when
    no entry has corruption conditions."""
    parts = [entry_summary(e, clean) for e in entries]
    table = pd.concat([p for p in parts if len(p)], ignore_index=True) if any(len(p) for p in parts) else None
    if table is None:
        return ""
    head = table[table["corruption"] == "all"]
    return "corruptions (clean = P, mean over corruption x severity = mPC, relative = rPC):\n" + format_table(head)


def format_table(table: pd.DataFrame, score: str | None = None) -> str:
    """A terminal table: a row per model and corruption, `clean` (P), `mean` (mPC) and `relative` (rPC)."""
    t = table if score is None else table[table["score"] == score]
    if not len(t):
        return "(no corruption conditions)"
    lines = [f"{'model':24} {'score':12} {'corruption':18} {'sev':9} {'clean':>7} {'mean':>7} {'relative':>8}"]
    for r in t.itertuples(index=False):
        flag = " (subset)" if r.corruption == "all" and not r.complete else ""
        lines.append(f"{str(r.model)[:24]:24} {r.score:12} {r.corruption:18} {r.severities:9} {r.clean:7.3f} "
                     f"{r.mean:7.3f} {r.relative:8.3f}{flag}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pairedgta.corruption_summary",
                                     description="Cityscapes-C / COCO-C summaries (P, mPC, rPC) of evaluate entries")
    parser.add_argument("entries", nargs="+", type=Path, help="evaluate cache entries (outputs/cache/evaluate/<hash>)")
    parser.add_argument("--clean", default="Day-EXTRASUNNY", help="the clean condition (default Day-EXTRASUNNY)")
    parser.add_argument("--csv", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    table = pd.concat([entry_summary(e, args.clean) for e in args.entries], ignore_index=True)
    print(format_table(table))
    if args.csv:
        write_csv(table, args.csv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
