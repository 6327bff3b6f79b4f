"""Table 1 from the authors' released per-class results (their `results_class_retention_by_condition.csv`):
one row per (model, reference_model, sec_condition, class) with columns model, reference_model,
sec_condition, class_id, class_name, retention_masked, mass_clean_masked, mass_reference_masked,
metric_type, conf_threshold.

The rows become the project's xi.csv schema under a metric convention (a class whose reference mass
`mass_reference_masked` is 0 is absent: xi = 0 under the paper's convention, NaN under the strict
one), and the same writers as the plot stage's xi_table make the CSV, Markdown and LaTeX tables and the
heatmap, so a table from the authors' numbers and one from this project's evaluation are comparable
cell by cell. Nothing is generated or evaluated: registered as the figure `authors_table`, drawn
alone when plot.table_csv is set (`python -m pairedgta +experiment=paper_table stages=[plot]
plot.table_csv=PATH`)."""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pairedgta.schema import as_dict
from pairedgta.cityscapes import CLASS_NAMES, NUM_CLASSES
from pairedgta.errors import ConfigError, DataError
from pairedgta.figures import FigureOptions
from pairedgta.figures.common import MODEL_DISPLAY, read_checked_csv, slug
from pairedgta.figures.inputs import Passes
from pairedgta.filehash import sha256_file
from pairedgta.metrics.conventions import Convention, convention_from_config
from pairedgta.metrics.reference_consistency import class_mean

log = logging.getLogger("pairedgta.plot")

COLUMNS = ("model", "reference_model", "sec_condition", "class_id", "class_name", "retention_masked",
           "mass_clean_masked", "mass_reference_masked", "metric_type", "conf_threshold")
FILTERS = ("reference_model", "metric_type", "conf_threshold")
REFERENCE = "Day-EXTRASUNNY"  # the paper's clean reference; sec_condition is every other condition
TIMES = ("Day", "Sunset", "Night")
WEATHERS = {"extrasunny": "EXTRASUNNY", "sunny": "EXTRASUNNY", "clear": "EXTRASUNNY", "rain": "RAIN",
            "rainy": "RAIN", "foggy": "FOGGY", "fog": "FOGGY"}
GRID_ORDER = [f"{t}-{w}" for t in TIMES for w in ("EXTRASUNNY", "RAIN", "FOGGY")]


def condition_name(raw: str) -> str:
    """The authors' condition label -> the project's grid name (Day-EXTRASUNNY ...) when it names one
    time of day and one weather (any case, any separator); otherwise unchanged."""
    tokens = [t for t in re.split(r"[^a-z]+", str(raw).lower()) if t]
    times = [t.capitalize() for t in tokens if t.capitalize() in TIMES]
    weathers = [WEATHERS[t] for t in tokens if t in WEATHERS]
    if len(times) == 1 and len(weathers) == 1 and len(tokens) == 2:
        return f"{times[0]}-{weathers[0]}"
    return str(raw)


def model_name(raw: str) -> str:
    """The authors' model label -> the project's model key (segformer_b5 ...) when it is one of the
    paper's models written as key or display name (SegFormer-B5, DeepLabV3+ R101); otherwise unchanged."""
    lookup = {slug(k): k for k in MODEL_DISPLAY}
    lookup |= {slug(v.replace("+", "plus")): k for k, v in MODEL_DISPLAY.items()}
    return lookup.get(slug(str(raw).replace("+", "plus")), str(raw))


def read_results(path: str | Path) -> pd.DataFrame:
    """The CSV, checked: every column present, class ids 0..18 with matching names, numbers numeric."""
    path = Path(path)
    df = read_checked_csv(path, "plot.table_csv", "results_class_retention_by_condition.csv", COLUMNS)
    for col in ("class_id", "retention_masked", "mass_reference_masked"):
        values = pd.to_numeric(df[col], errors="coerce")
        bad = values.isna() & df[col].notna()
        if bad.any():
            raise DataError(f"{path}: column {col} has a non-number {df.loc[bad, col].iloc[0]!r} (row {int(bad.idxmax()) + 2})")
        df[col] = values
    if df["class_id"].isna().any() or df["mass_reference_masked"].isna().any():
        col = "class_id" if df["class_id"].isna().any() else "mass_reference_masked"
        raise DataError(f"{path}: column {col} is empty in row {int(df[col].isna().idxmax()) + 2}")
    ids = df["class_id"].astype(int)
    out_of_range = (ids < 0) | (ids >= NUM_CLASSES) | (ids != df["class_id"])
    if out_of_range.any():
        raise DataError(f"{path}: class_id {df.loc[out_of_range, 'class_id'].iloc[0]} is not a Cityscapes train id 0..{NUM_CLASSES - 1}")
    df["class_id"] = ids
    negative = df["mass_reference_masked"] < 0
    if negative.any():
        raise DataError(f"{path}: mass_reference_masked {df.loc[negative, 'mass_reference_masked'].iloc[0]:g} in row "
                        f"{int(negative.idxmax()) + 2} is negative; a pixel mass is >= 0")
    conds = df["sec_condition"].astype(str)
    unknown = sorted({c for c in conds if condition_name(c) not in GRID_ORDER})
    if unknown:
        raise DataError(f"{path}: sec_condition {unknown[0]!r} is not one of the paper's conditions (a time of day "
                        f"Day/Sunset/Night and a weather Sunny/Rain/Foggy, e.g. Day-Rain)")
    retention = df["retention_masked"].dropna()
    fractions, percents = retention[(retention > 0) & (retention <= 1)], retention[retention > 1]
    if len(percents) and len(fractions) > len(percents):
        row = int(percents.index[0]) + 2
        raise DataError(f"{path}: retention_masked mixes fractions and percentages ({percents.iloc[0]:g} in row {row} "
                        "among values in [0, 1]); give every value in one scale")
    names = df["class_name"].astype(str).str.lower().str.replace("_", " ").str.strip()
    wrong = names != ids.map(lambda k: CLASS_NAMES[k])
    if wrong.any():
        r = df[wrong].iloc[0]
        raise DataError(f"{path}: class_id {r.class_id} is named {r.class_name!r}, but train id {r.class_id} is "
                        f"{CLASS_NAMES[r.class_id]!r}; the table needs Cityscapes train ids")
    return df


def select_rows(df: pd.DataFrame, filters: dict[str, Any] | None, source: str = "") -> tuple[pd.DataFrame, dict[str, Any]]:
    """Keep one reference model, metric type and confidence threshold: the one given in
    plot.table_filter, or the only one the CSV holds. Returns the rows and the values used."""
    filters = filters or {}
    used: dict[str, Any] = {}
    for col in FILTERS:
        present = list(dict.fromkeys(df[col].dropna().tolist()))
        wanted = filters.get(col)
        if wanted is not None:
            if col == "conf_threshold":
                keep = np.isclose(pd.to_numeric(df[col], errors="coerce"), float(wanted))
            else:
                keep = df[col].astype(str) == str(wanted)
            if not keep.any():
                raise ConfigError(f"plot.table_filter.{col}={wanted!r} matches no row of {source or 'the CSV'}; it holds {present}")
            df = df[keep]
            used[col] = wanted
        elif len(present) > 1:
            raise ConfigError(f"plot.table_filter.{col}: {source or 'the CSV'} holds several values {present}; "
                              f"pick one, e.g. plot.table_filter.{col}={present[0]!r}")
        else:
            used[col] = present[0] if present else None
    dup = df.duplicated(["model", "sec_condition", "class_id"], keep=False)
    if dup.any():
        r = df[dup].iloc[0]
        raise DataError(f"{source or 'the CSV'}: several rows for model {r.model}, condition {r.sec_condition}, class "
                        f"{r.class_name} after filtering by {used}; the per-class results must be unique")
    return df, used


def to_xi(df: pd.DataFrame, convention: Convention, source: str = "") -> tuple[pd.DataFrame, int]:
    """The rows in xi.csv's schema (values in [0, 1], a `mean` row per model and condition under the
    convention). Retention above 1 means the file holds percentages. A (model, condition, class) the
    CSV lacks counts as absent (no reference pixels). Returns the frame and the number of such rows."""
    retention = df["retention_masked"].astype(float)
    if (retention < 0).any() or (retention > 100).any():
        raise DataError(f"{source or 'the CSV'}: retention_masked outside [0, 1] (or [0, 100] in percent)")
    scale = 100.0 if (retention > 1.0).any() else 1.0
    include = convention.mean_classes()
    rows, missing = [], 0
    conditions = list(dict.fromkeys(df["sec_condition"]))
    for model, part in df.groupby("model", sort=False):
        ref_model = str(part["reference_model"].iloc[0])
        for cond in conditions:
            cells = part[part["sec_condition"] == cond].set_index("class_id")
            if cells.empty:
                continue
            xi = np.full(NUM_CLASSES, np.nan)
            reference = np.zeros(NUM_CLASSES)
            for k in range(NUM_CLASSES):
                if k not in cells.index:
                    missing += 1
                    continue
                reference[k] = float(cells.at[k, "mass_reference_masked"])
                if reference[k] > 0:
                    value = float(cells.at[k, "retention_masked"])
                    if np.isnan(value):
                        raise DataError(f"{source or 'the CSV'}: retention_masked is empty for {model}, {cond}, "
                                        f"{CLASS_NAMES[k]} although its reference mass is {reference[k]:g}")
                    xi[k] = value / scale
            absent = reference <= 0
            xi[absent] = 0.0 if convention.absent == "zero" else np.nan
            included = include & ~np.isnan(xi)
            name, condition = model_name(str(model)), condition_name(str(cond))
            for k in range(NUM_CLASSES):
                rows.append({"model": name, "reference_model": ref_model, "condition": condition, "class_id": k,
                             "class_name": CLASS_NAMES[k], "xi": xi[k], "reference_pixels": reference[k],
                             "in_mean": bool(included[k]), "convention": convention.name})
            rows.append({"model": name, "reference_model": ref_model, "condition": condition, "class_id": -1,
                         "class_name": "mean", "xi": class_mean(xi, included), "reference_pixels": reference.sum(),
                         "in_mean": False, "convention": convention.name})
    frame = pd.DataFrame(rows)
    order = {c: i for i, c in enumerate(GRID_ORDER)}
    first_seen = {c: len(order) + i for i, c in enumerate(dict.fromkeys(frame["condition"]))}
    frame["_order"] = frame["condition"].map(lambda c: order.get(c, first_seen[c]))
    frame = frame.sort_values("_order", kind="stable").drop(columns="_order").reset_index(drop=True)
    return frame, missing


def paper_table(csv_path: str | Path, out: Path, convention: Convention, filters: dict[str, Any] | None = None,
                formats: list[str] | tuple[str, ...] = (), dpi: int = 150, stem: str = "table1_xi") -> tuple[list[Path], pd.DataFrame]:
    """Write Table 1 (all models x all conditions of the CSV) as `<stem>.csv/.md/.tex`, the long
    `<stem>_long.csv` (xi.csv schema), and with `formats` the heatmap. Returns (paths, long frame)."""
    csv_path = Path(csv_path)
    source = str(csv_path)
    rows, used = select_rows(read_results(csv_path), filters, source)
    xi, missing = to_xi(rows, convention, source)
    if missing:
        log.warning("%s: %d (model, condition, class) rows missing; counted as classes without reference pixels", source, missing)
    out.mkdir(parents=True, exist_ok=True)
    from pairedgta.figures import xi as xi_fig  # seaborn: only when a table is drawn (config checks read FILTERS)

    paths = xi_fig.write_tables(xi, REFERENCE, out, stem=stem)
    md = out / f"{stem}.md"
    digest = sha256_file(csv_path)[:16]
    excluded = ", ".join(convention.mean_exclude) or "none"
    md.write_text(md.read_text() + (
        f"\nSource: `{csv_path.name}` (sha256 {digest}), rows {used}. Convention `{convention.name}`: a class without "
        f"reference pixels scores {'0' if convention.absent == 'zero' else 'NaN (left out of the Mean)'}; "
        f"Mean over the classes shown (excluded: {excluded}). {missing} missing rows counted as absent.\n"
    ))
    long_path = out / f"{stem}_long.csv"
    xi.to_csv(long_path, index=False)
    paths.append(long_path)
    if formats:
        for files in xi_fig.heatmap_figures(xi, REFERENCE, out, list(formats), dpi, stem=f"{stem}_heatmap").values():
            paths += files  # one conditions x classes heatmap per model
    log.info("Table 1 from %s (%s convention): %d models x %d conditions", csv_path.name, convention.name,
             xi["model"].nunique(), xi.loc[xi["condition"] != REFERENCE, "condition"].nunique())
    return paths, xi


# -- the registered figure `authors_table` (plot.table_csv=PATH, stages=[plot]) ---------------------------
def _options(opts: FigureOptions) -> tuple[Path, Convention, dict[str, Any]]:
    plot = opts.plot
    if not plot.table_csv:
        raise ConfigError("plot.figures: authors_table draws Table 1 from the authors' per-class results; "
                          "set plot.table_csv=PATH (their results_class_retention_by_condition.csv)")
    filters = {k: v for k, v in as_dict(plot.table_filter).items() if v is not None}
    return Path(str(plot.table_csv)), convention_from_config(as_dict(opts.run.metric)), filters


def cache_key(passes: Passes, opts: FigureOptions) -> tuple[dict[str, Any], dict[str, str]]:
    """The plot entry depends on the file's content (not its path), the filters and the convention."""
    path, convention, filters = _options(opts)
    if not path.is_file():
        raise ConfigError(f"plot.table_csv={path}: no such file; give the authors' results_class_retention_by_condition.csv")
    return {"filter": filters, "convention": convention.as_dict()}, {"table_csv": sha256_file(path)[:16]}


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """Table 1 (CSV/Markdown/LaTeX, a heatmap per model) from plot.table_csv under the run's metric
    convention; the metrics are every Mean, `table/authors/xi_mean/<condition>/<model>`."""
    path, convention, filters = _options(opts)
    paths, xi = paper_table(path, out, convention, filters, opts.formats, opts.dpi)
    from pairedgta.figures import xi as xi_fig

    metrics = {}
    for cond, table in xi_fig.xi_tables(xi, REFERENCE).items():  # the Means as the table prints them
        for model, value in table["mean"].items():
            metrics[f"table/authors/xi_mean/{cond}/{model}"] = float(value)
    return paths, metrics


def printed_table_as_results(out_csv: str | Path, table: str | Path | None = None) -> Path:
    """The paper's printed Table 1 (pairedgta/data/paper_table1.csv, percent) in the authors' per-class
    CSV format, so the table pipeline can run on published numbers. The printed table holds no pixel
    masses, so presence is inferred: a class is absent (mass 0) where it is 0.0 for every model of that
    condition (the only absences the print reveals), present (mass 1) otherwise; bus and train are not
    printed and are written as absent. `mass_clean_masked` is left empty."""
    from pairedgta.data import PAPER_TABLE1

    printed = pd.read_csv(table or PAPER_TABLE1)
    classes = [c for c in printed.columns if c not in ("condition", "model", "mean")]
    unknown = [c for c in classes if c not in CLASS_NAMES]
    if unknown:
        raise DataError(f"{table or PAPER_TABLE1}: unknown class column(s) {unknown}")
    absent_cols = {cond: {c for c in classes if (g[c] == 0).all()} for cond, g in printed.groupby("condition")}
    rows = []
    for r in printed.to_dict("records"):
        for k, name in enumerate(CLASS_NAMES):
            shown = name in classes
            absent = not shown or name in absent_cols[r["condition"]]
            rows.append({"model": r["model"], "reference_model": "SegFormer-B5", "sec_condition": r["condition"],
                         "class_id": k, "class_name": name, "retention_masked": r[name] / 100 if shown else 0.0,
                         "mass_clean_masked": None, "mass_reference_masked": 0 if absent else 1,
                         "metric_type": "printed_table1", "conf_threshold": 0.6})
    out_csv = Path(out_csv)
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_csv.with_name(f".{out_csv.name}.tmp")
    pd.DataFrame(rows, columns=list(COLUMNS)).to_csv(tmp, index=False)
    tmp.replace(out_csv)
    return out_csv
