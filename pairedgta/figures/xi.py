"""Table 1 of the paper: xi per class (reference -> each adverse condition) for every model, as CSV,
Markdown and a LaTeX booktabs table with the best value per column in bold, plus a heatmap per model."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
import seaborn as sns

from pairedgta.figures import FigureOptions
from pairedgta.figures.common import (
    TEXT_WIDTH,
    concat_tables,
    class_short,
    condition_display,
    latex_escape,
    markdown_table,
    model_display,
    ordered_classes,
    paper_style,
    save,
    slug,
)
from pairedgta.figures.inputs import Passes

GT = "ground_truth"


def table_columns(xi: pd.DataFrame) -> list[str]:
    """The classes the class-wise mean covers for some model (xi.csv's `in_mean`: under the paper
    convention the 17 classes of Table 1, absent ones as 0; under the strict one the classes with
    reference pixels), in Cityscapes order, then `mean`. Older outputs without `in_mean`: the defined ones."""
    rows = xi[xi["class_name"] != "mean"]
    if "in_mean" not in rows:
        shown = rows[rows["xi"].notna()]
    elif "supported" in rows:  # defined classes too thin for the mean are shown, marked (see `unsupported`)
        shown = rows[rows["in_mean"].astype(bool) | (rows["xi"].notna() & ~rows["supported"].astype(bool))]
    else:
        shown = rows[rows["in_mean"].astype(bool)]
    return ordered_classes(shown["class_name"]) + ["mean"]


def unsupported(part: pd.DataFrame, rows: str, index: list, columns: list) -> pd.DataFrame:
    """True where a shown cell's class has too little support for the mean (xi.csv `supported`: the
    strict convention's metric.min_images / min_pixels rule); all False for outputs without that column.
    rows: the column that indexes the table (model or condition)."""
    if "supported" not in part:
        return pd.DataFrame(False, index=index, columns=columns)
    flag = part[part["class_name"] != "mean"]
    flag = flag.assign(unsupported=(~flag["supported"].astype(bool) & flag["xi"].notna()).astype(float))
    wide = flag.pivot_table(index=rows, columns="class_name", values="unsupported", aggfunc="max")
    return wide.reindex(index=index, columns=columns).fillna(0).astype(bool)


MARK = "\u2020"  # dagger: too little support, shown but left out of the mean
MARK_NOTE = f"{MARK} too little support (metric.min_images / min_pixels): shown, left out of the mean"


def printed_mean(part: pd.DataFrame) -> pd.Series:
    """Per model, the mean of the class cells as printed (percent, one decimal) over the classes in the
    mean, in [0, 1]. The authors averaged the rounded cells: this reproduces all 24 Means of Table 1,
    where the mean of the raw values misses two by 0.1."""
    cells = part[(part["class_name"] != "mean") & part["in_mean"].astype(bool)]
    tenths = cells.assign(t=(cells["xi"] * 1000).round().astype("int64")).groupby("model")["t"].agg(["sum", "count"])
    # in integer tenths of a percent, rounded half up: 51.35 prints 51.4 whatever the float sum gives
    printed = (2 * tenths["sum"] + tenths["count"]) // (2 * tenths["count"])
    return printed / 1000


def xi_tables(xi: pd.DataFrame, reference: str) -> dict[str, pd.DataFrame]:
    """One wide table per adverse condition: rows = models (sorted by display name), columns =
    `table_columns`, values = xi in [0, 1]. The Mean is evaluate's, under the run's metric convention;
    under the paper's it is the mean of the printed cells (`printed_mean`), the raw mean stays in the
    long CSV."""
    xi = xi[(xi["reference_model"] != GT) & (xi["condition"] != reference)]
    tables: dict[str, pd.DataFrame] = {}
    for cond in dict.fromkeys(xi["condition"]):
        part = xi[xi["condition"] == cond]
        wide = part.pivot_table(index="model", columns="class_name", values="xi", dropna=False, aggfunc="first")
        wide = wide.reindex(columns=table_columns(part))
        if "convention" in part and "in_mean" in part and (part["convention"] == "paper").all():
            wide["mean"] = printed_mean(part).reindex(wide.index)
        wide = wide.loc[sorted(wide.index, key=lambda m: model_display(m).lower())]
        wide.columns.name = None
        tables[cond] = wide
    return tables


def xi_marks(xi: pd.DataFrame, reference: str) -> dict[str, pd.DataFrame]:
    """Per table of `xi_tables`, which cells to mark as unsupported."""
    tables = xi_tables(xi, reference)
    xi = xi[(xi["reference_model"] != GT) & (xi["condition"] != reference)]
    return {cond: unsupported(xi[xi["condition"] == cond], "model", list(t.index), list(t.columns))
            for cond, t in tables.items()}


def display_values(table: pd.DataFrame) -> pd.DataFrame:
    """Percent with one decimal: what the Markdown and LaTeX tables show, and what `bold` compares."""
    return (table * 100).round(1)


def bold_mask(table: pd.DataFrame, marks: pd.DataFrame | None = None, own: frozenset[str] = frozenset()) -> pd.DataFrame:
    """True where a shown value is the column maximum (every tie is bold; a column of NaN has none);
    marked (unsupported) cells and the rows of `own` (the reference model, graded on its own pseudo-labels)
    neither win nor count."""
    shown = display_values(table)
    if marks is not None:
        shown = shown.mask(marks.reindex_like(shown).fillna(False).astype(bool))
    shown = shown.mask(pd.Series(shown.index.isin(list(own)), index=shown.index), axis=0)
    return shown.eq(shown.max(axis=0, skipna=True), axis=1) & shown.notna()


REFERENCE_ROW = " (reference, not ranked)"


def self_graded(xi: pd.DataFrame) -> frozenset[str]:
    """The models scored against their own pseudo-labels (xi.csv rows whose model is the reference model):
    shown as the reference, never as the best of a column."""
    if xi.empty or "reference_model" not in xi:
        return frozenset()
    return frozenset(str(m) for m in xi.loc[xi["model"].astype(str) == xi["reference_model"].astype(str), "model"])


def _row_name(model: str, own: frozenset[str]) -> str:
    return model_display(model) + (REFERENCE_ROW if model in own else "")


def _cell(value: float, bold: bool, fmt: str, marked: bool = False) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–" if fmt == "md" else "--"
    text = f"{value:.1f}"
    if bold:
        text = f"**{text}**" if fmt == "md" else rf"\textbf{{{text}}}"
    if marked:
        text += MARK if fmt == "md" else r"$^\dagger$"
    return text


def write_csv(tables: dict[str, pd.DataFrame], reference: str, path: Path) -> Path:
    frames = []
    for cond, t in tables.items():
        f = t.copy()
        f.insert(0, "model", f.index)
        f.insert(0, "condition", cond)
        f.insert(0, "reference", reference)
        frames.append(f.reset_index(drop=True))
    pd.concat(frames, ignore_index=True).to_csv(path, index=False) if frames else path.write_text("")
    return path


def _marks(marks: dict[str, pd.DataFrame] | None, cond: str, t: pd.DataFrame) -> pd.DataFrame:
    m = (marks or {}).get(cond)
    return pd.DataFrame(False, index=t.index, columns=t.columns) if m is None else m.reindex_like(t).fillna(False)


def to_markdown(tables: dict[str, pd.DataFrame], reference: str, marks: dict[str, pd.DataFrame] | None = None,
                own: frozenset[str] = frozenset()) -> str:
    parts = [f"# \u03be per class (%): {condition_display(reference)} \u2192 each condition; best per column in bold"
             + (" among the models other than the reference, which grades its own pseudo-labels" if own else "") + "\n"]
    if any(m.to_numpy().any() for m in (marks or {}).values()):
        parts.append(f"\n{MARK_NOTE}\n")
    for cond, t in tables.items():
        mk = _marks(marks, cond, t)
        shown, bold = display_values(t), bold_mask(t, mk, own)
        header = ["Model"] + [class_short(c) if c != "mean" else "Mean" for c in t.columns]
        rows = [[_row_name(m, own)] + [_cell(shown.at[m, c], bool(bold.at[m, c]), "md", bool(mk.at[m, c]))
                                      for c in t.columns] for m in t.index]
        parts.append(f"\n## {condition_display(reference)} \u2192 {condition_display(cond)}\n\n")
        parts.append(markdown_table(header, rows))
    return "".join(parts)


def to_latex(tables: dict[str, pd.DataFrame], reference: str, marks: dict[str, pd.DataFrame] | None = None,
             own: frozenset[str] = frozenset()) -> str:
    """A table* of subtables like the paper's Table 1 (needs booktabs, subcaption, graphicx)."""
    out = [
        "% generated by pairedgta (plot stage); \\usepackage{booktabs,subcaption,graphicx}",
        "\\begin{table*}[t]", "\\centering", "\\renewcommand{\\arraystretch}{0.9}",
    ]
    any_mark = any(m.to_numpy().any() for m in (marks or {}).values())
    for cond, t in tables.items():
        mk = _marks(marks, cond, t)
        shown, bold = display_values(t), bold_mask(t, mk, own)
        n = len(t.columns) - 1
        head = " & ".join(["Model"] + [latex_escape(class_short(c)) if c != "mean" else "Mean" for c in t.columns])
        out += [
            "\\begin{subtable}[t]{0.95\\textwidth}", "\\centering",
            f"\\caption{{{latex_escape(condition_display(reference))} $\\rightarrow$ {latex_escape(condition_display(cond))}.}}",
            "\\scriptsize", "\\setlength{\\tabcolsep}{3pt}", "\\resizebox{\\linewidth}{!}{%",
            f"\\begin{{tabular}}{{l{'c' * n}|c}}", "\\toprule", head + " \\\\", "\\midrule",
        ]
        for m in t.index:
            cells = [_cell(shown.at[m, c], bool(bold.at[m, c]), "tex", bool(mk.at[m, c])) for c in t.columns]
            out.append(" & ".join([latex_escape(_row_name(m, own))] + cells) + " \\\\")
        out += ["\\bottomrule", "\\end{tabular}", "}", "\\end{subtable}"]
    out += [
        ("\\caption{Class-wise reference consistency $\\xi$ (\\%) across environmental conditions; the last column "
         "is the class-wise mean, the best value per column is in bold"
         + (" (the reference model, graded on its own pseudo-labels, is not ranked)" if own else "") + "."
         + (" $^\\dagger$: too little support, left out of the mean." if any_mark else "") + "}"),
        "\\label{tab:retention_conditions}", "\\end{table*}", "",
    ]
    return "\n".join(out)


def write_tables(xi: pd.DataFrame, reference: str, out: Path, stem: str = "table1_xi",
                 own: frozenset[str] = frozenset()) -> list[Path]:
    """`own`: the rows shown as the reference (`self_graded`), never bold; the authors' Table 1 passes none."""
    tables = xi_tables(xi, reference)
    if not tables:
        return []
    marks = xi_marks(xi, reference)
    paths = [write_csv(tables, reference, out / f"{stem}.csv")]
    (out / f"{stem}.md").write_text(to_markdown(tables, reference, marks, own))
    (out / f"{stem}.tex").write_text(to_latex(tables, reference, marks, own))
    return paths + [out / f"{stem}.md", out / f"{stem}.tex"]


def heatmap_figures(xi: pd.DataFrame, reference: str, out: Path, formats: list[str], dpi: int,
                    stem: str = "xi_table") -> dict[str, list[Path]]:
    """Per model one conditions x classes heatmap of xi (%) with a colour bar, on one 0-100 scale and with
    the tables' columns, so the models' figures compare side by side. Returns the files per model."""
    xi = xi[(xi["reference_model"] != GT) & (xi["condition"] != reference)]
    if xi.empty:
        return {}
    columns = table_columns(xi)
    conditions = list(dict.fromkeys(xi["condition"]))
    files: dict[str, list[Path]] = {}
    for model in sorted(dict.fromkeys(xi["model"]), key=lambda m: model_display(m).lower()):
        part = xi[xi["model"] == model]
        wide = part.pivot_table(index="condition", columns="class_name", values="xi", dropna=False, aggfunc="first")
        shown = display_values(wide.reindex(index=conditions, columns=columns))
        marked = unsupported(part, "condition", conditions, columns).to_numpy()
        labels = [[("" if pd.isna(v) else f"{v:.1f}" + (MARK if mk else "")) for v, mk in zip(row, mrow)]
                  for row, mrow in zip(shown.to_numpy(), marked)]
        shown.index = [condition_display(c) for c in shown.index]
        shown.columns = [class_short(c) if c != "mean" else "Mean" for c in columns]
        with paper_style():
            fig, ax = plt.subplots(figsize=(TEXT_WIDTH, 0.24 * len(conditions) + 0.9))
            sns.heatmap(shown, ax=ax, annot=labels, fmt="", vmin=0, vmax=100, cmap="viridis", mask=shown.isna(),
                        annot_kws={"fontsize": 5}, linewidths=0.3, linecolor="white",
                        cbar_kws={"label": "\u03be (%)", "pad": 0.01, "fraction": 0.04})
            title = f"{model_display(model)}: \u03be (%) from {condition_display(reference)}, per condition and class"
            if model in self_graded(part):
                title += " (the reference: its own pseudo-labels)"
            if marked.any():
                title += f"\n({MARK_NOTE})"
            ax.set_title(title)
            ax.set_xlabel("")
            ax.set_ylabel("")
            ax.tick_params(length=0)
            ax.set_xticklabels(ax.get_xticklabels(), rotation=45, ha="right")
            ax.set_yticklabels(ax.get_yticklabels(), rotation=0)
            fig.tight_layout()
            files[model] = save(fig, out, f"{stem}_{slug(model)}", formats, dpi)
    return files


def draw(passes: Passes, out: Path, opts: FigureOptions) -> tuple[list[Path], dict[str, float]]:
    """Table 1 (CSV/Markdown/LaTeX) + heatmap per evaluated pass, xi against the pseudo-labels."""
    files: list[Path] = []
    metrics: dict[str, float] = {}
    for p in passes:
        if not p.evaluations:
            continue
        xi = concat_tables(p.evaluations, "xi")
        pl = xi[xi["reference_model"] != GT]
        for model, paths in heatmap_figures(pl, p.grid.reference, out, opts.formats, opts.dpi,
                                            stem=opts.stem("xi_table", p.label)).items():
            files += opts.own(paths, model, p.label)
        files += write_tables(pl, p.grid.reference, out, stem=opts.stem("table1_xi", p.label), own=self_graded(pl))
        path = out / f"{opts.stem('xi_all_models', p.label)}.csv"
        pl.to_csv(path, index=False)
        files.append(path)
        for r in pl[pl["class_name"] == "mean"].itertuples():
            metrics[f"table/{p.label}/xi_mean/{r.condition}/{r.model}"] = r.xi
    return files, metrics
