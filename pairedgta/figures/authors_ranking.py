"""The ranking figure and rho_valid from the authors' released per-frame counts (their
`ranking_consistency_results/framewise_target_class_counts.csv`: dataset_name, model, target_class,
pair_id, clean_count, adv_count, clean_path, adv_path), so the paper's four published values (0.991 and
0.824 for car on their dataset, 0.300 and 0.259 for person on ACDC, the non-zero selection) come out of
the same code as this project's own evaluations. Registered as the figure `authors_ranking`, drawn alone
when plot.frame_counts_csv is set (`python -m pairedgta +experiment=night_vs_acdc stages=[plot]
plot.frame_counts_csv=PATH`)."""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import pandas as pd

from pairedgta.schema import as_dict
from pairedgta.errors import ConfigError, DataError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import read_checked_csv
from pairedgta.figures.inputs import Passes
from pairedgta.figures.ranking import RankingInput, ranking_figure, rho_table
from pairedgta.filehash import sha256_file
from pairedgta.metrics.conventions import convention_from_config
from pairedgta.metrics.ranking import SELECTIONS, rho_rows

log = logging.getLogger("pairedgta.plot")

COLUMNS = ("dataset_name", "model", "target_class", "pair_id", "clean_count", "adv_count")
KEY = "plot.frame_counts_csv"
GTA = re.compile(r"_(Day|Sunset|Night)_([A-Za-z]+)\.[A-Za-z]+$")
ACDC = re.compile(r"/rgb_anon/(fog|night|rain|snow)/")


def read_counts(path: str | Path) -> pd.DataFrame:
    """The CSV, checked: the columns, counts that are non-negative integers, one row per frame."""
    path = Path(path)
    df = read_checked_csv(path, KEY, "framewise_target_class_counts.csv", COLUMNS, dtype={"pair_id": str})
    for col in ("clean_count", "adv_count"):
        values = pd.to_numeric(df[col], errors="coerce")
        bad = values.isna() | (values < 0) | (values != values.round())
        if bad.any():
            raise DataError(f"{path}: {col} {df.loc[bad, col].iloc[0]!r} in row {int(bad.idxmax()) + 2} is not a pixel "
                            "count (an integer >= 0)")
        df[col] = values.astype("int64")
    dup = df.duplicated(["dataset_name", "model", "target_class", "pair_id"], keep=False)
    if dup.any():
        r = df[dup].iloc[0]
        raise DataError(f"{path}: several rows for dataset {r.dataset_name}, model {r.model}, class {r.target_class}, "
                        f"frame {r.pair_id}; each frame must appear once")
    return df


def adverse_condition(adv_paths: pd.Series) -> str:
    """The adverse condition a dataset's frames show, from the image paths: `..._Night_EXTRASUNNY.png`
    (the authors' GTA V release) -> Night-EXTRASUNNY, `rgb_anon/night/` (ACDC) -> ACDC-night."""
    names = set()
    for p in adv_paths.dropna().astype(str):
        if m := GTA.search(p):
            names.add(f"{m.group(1)}-{m.group(2).upper()}")
        elif m := ACDC.search(p.replace("\\", "/")):
            names.add(f"ACDC-{m.group(1)}")
    return names.pop() if len(names) == 1 else "adverse"


def inputs_from_counts(df: pd.DataFrame, selections: list[str], m: int, resamples: int, confidence: float, seed: int,
                       headline: str, convention: str, min_frames: int = 0) -> list[RankingInput]:
    """One RankingInput per dataset_name: the frames in the plot stage's frame_counts schema and the
    rho_valid rows (every selection, bootstrap interval over the selected frames)."""
    inputs = []
    for dataset, part in df.groupby("dataset_name", sort=False):
        cond = adverse_condition(part["adv_path"]) if "adv_path" in part else "adverse"
        counts = pd.DataFrame({"dataset": dataset, "model": part["model"], "class_name": part["target_class"],
                               "pair_id": part["pair_id"], "condition": cond, "clean_count": part["clean_count"],
                               "adv_count": part["adv_count"]})
        rows = []
        for (model, cls), g in counts.groupby(["model", "class_name"], sort=False):
            for r in rho_rows(g["clean_count"], g["adv_count"], selections, m, resamples, confidence, seed, headline,
                              min_frames):
                rows.append({"dataset": dataset, "model": model, "class_name": cls, "condition": cond, **r,
                             "convention": convention})
        inputs.append(RankingInput(str(dataset), cond, counts.reset_index(drop=True), pd.DataFrame(rows)))
    return inputs


def _options(opts: FigureOptions) -> tuple[Path, dict[str, Any]]:
    plot = opts.plot
    if not plot.frame_counts_csv:
        raise ConfigError("plot.figures: authors_ranking draws rho_valid from the authors' per-frame counts; "
                          f"set {KEY}=PATH (their framewise_target_class_counts.csv)")
    metric = as_dict(opts.run.metric)
    rho = metric.get("rho") or {}
    selections = list(rho.get("selections") or SELECTIONS)
    conv = convention_from_config(metric, selections)
    boot = metric.get("bootstrap") or {}
    settings = {"selections": selections, "m": int(rho.get("m", 25)), "resamples": int(boot.get("resamples", 1000)),
                "confidence": float(boot.get("confidence", 0.95)), "seed": int(boot.get("seed", 0)),
                "headline": conv.rho_headline, "convention": conv.name, "min_frames": conv.rho_min_frames,
                "classes": list(plot.ranking.classes), "window": plot.ranking.window}
    return Path(str(plot.frame_counts_csv)), settings


def cache_key(passes: Passes, opts: FigureOptions) -> tuple[dict[str, Any], dict[str, str]]:
    """The plot entry depends on the file's content (not its path) and the rho settings."""
    path, settings = _options(opts)
    if not path.is_file():
        raise ConfigError(f"{KEY}={path}: no such file; give the authors' framewise_target_class_counts.csv")
    return settings, {"frame_counts_csv": sha256_file(path)[:16]}


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """The ranking figure and rho_valid.csv/.md from plot.frame_counts_csv; metrics
    `rho_valid/<dataset>/<model>/<selection>/<class>`."""
    path, s = _options(opts)
    df = read_counts(path)
    present = list(dict.fromkeys(df["target_class"]))
    classes = s["classes"] or present
    unknown = [c for c in classes if c not in present]
    if unknown:
        raise ConfigError(f"plot.ranking.classes: {unknown} not in {path.name}, which holds {present}; "
                          f"set plot.ranking.classes={present}")
    inputs = inputs_from_counts(df[df["target_class"].isin(classes)], s["selections"], s["m"], s["resamples"],
                                s["confidence"], s["seed"], s["headline"], s["convention"], s["min_frames"])
    files = ranking_figure(inputs, classes, s["window"], out, opts.formats, opts.dpi, stem="ranking",
                           selections=tuple(s["selections"]))
    files += rho_table(inputs, classes, out)
    metrics: dict[str, float] = {}
    for inp in inputs:
        for r in inp.rho.itertuples():
            metrics[f"rho_valid/{inp.label}/{r.model}/{r.selection}/{r.class_name}"] = r.rho
    log.info("rho_valid from %s (%s convention, headline %s): %d datasets x %d models x %d classes", path.name,
             s["convention"], s["headline"], len(inputs), df["model"].nunique(), len(classes))
    return files, metrics
