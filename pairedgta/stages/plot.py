"""Plot stage: the paper's figures and tables from the cached stage outputs of one or more passes (a pass
= one dataset variant: the generated dataset, ACDC, a pairing level ...). `plot.figures` picks the
families registered in pairedgta.figures (xi_table, ranking, qualitative, ablation, distribution,
contact_sheet, cost); each draws itself from the passes.

With plot.table_csv=PATH (and stages=[plot]) the stage draws only Table 1, from the authors' released
per-class results CSV (`run_table_csv`, logic in pairedgta.figures.paper_table).

Every output is written into the stage's cache directory; `metrics.json` holds the numbers the run logs
to MLflow (so a cache hit logs them too) and `owners.json` which figures show one model alone (those
go to that model's MLflow run)."""
from __future__ import annotations

import inspect
import json
import logging
import math
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pairedgta.cache import require_intact
from pairedgta.errors import ConfigError
from pairedgta.filehash import sha256_file
from pairedgta.figures import FIGURES, FigureOptions, lookup
from pairedgta.jsonio import write_json
from pairedgta.stages.common import Context, StageResult, run_cached

log = logging.getLogger("pairedgta.plot")
VERSION = "5"  # 5: the ranking figure says why a class has no rho_valid in terms of phi
DEFAULT_FIGURES = ("xi_table", "ranking", "qualitative")


class Figures(StageResult):
    """The plot stage's entry: figure files and the numbers they show."""

    def files(self) -> list[Path]:
        return sorted(q for q in self.path.iterdir() if q.suffix in (".png", ".pdf", ".csv", ".md", ".tex"))

    def owners(self) -> dict[str, dict[str, str]]:
        path = self.path / "owners.json"
        return json.loads(path.read_text()) if path.is_file() else {}

    def files_of(self, model: str, label: str | None = None) -> list[Path]:
        """The figures that show `model` alone (of pass `label`, when given)."""
        return [self.path / name for name, o in sorted(self.owners().items())
                if o["model"] == model and (label is None or o["pass"] == label) and (self.path / name).is_file()]

    def files_except(self, models: set[tuple[str, str]]) -> list[Path]:
        """Every file but the figures of the given (model, pass) pairs, which go to those models' own
        records: the run-level artifacts (a model collected from the cache has no run of its own)."""
        owners = self.owners()
        return [q for q in self.files()
                if q.name not in owners or (owners[q.name]["model"], owners[q.name]["pass"]) not in models]

    def metrics(self) -> dict[str, float]:
        path = self.path / "metrics.json"
        return json.loads(path.read_text()) if path.is_file() else {}


def figures_of(cfg: dict[str, Any]) -> list[str]:
    figures = list((cfg.get("plot") or {}).get("figures") or DEFAULT_FIGURES)
    for f in figures:
        FIGURES.meta(f)  # unknown names: one line listing the known ones
    return figures


def needed_stages(cfg: dict[str, Any]) -> set[str]:
    """Which upstream stages the requested figures read (a figure given its own input file needs none)."""
    needs = set()
    for f in figures_of(cfg):
        meta = FIGURES.meta(f)
        if meta.get("unless") and lookup(cfg, meta["unless"]):
            continue
        needs.add(meta["needs"])
    return needs


def options(cfg: dict[str, Any], passes: list[Any]) -> FigureOptions:
    pcfg = cfg.get("plot") or {}
    return FigureOptions(list(pcfg.get("formats", ["png"])), int(pcfg.get("dpi", 150)), cfg, multi=len(passes) > 1)


def make_plots(ctx: Context, passes: list[Any], out: Path) -> dict[str, Any]:
    opts = options(ctx.cfg, passes)
    files: list[Path] = []
    metrics: dict[str, float] = {}
    names = figures_of(ctx.cfg)
    bar = tqdm(names, desc="plot", unit="figure")
    for name in bar:
        bar.set_postfix_str(name)
        drawn, numbers = FIGURES.resolve(name)(passes, out, opts)
        files += drawn
        metrics.update(numbers)
    clean_metrics = {k: float(v) for k, v in metrics.items() if v is not None and not math.isnan(float(v))}
    write_json(out / "metrics.json", clean_metrics, sort_keys=True)
    write_json(out / "owners.json", opts.owners, sort_keys=True)
    return {"figures": [p.name for p in files], "metrics": clean_metrics}


def run(ctx: Context, passes: list[Any]) -> Figures:
    figures = figures_of(ctx.cfg)
    for e in (e for p in passes for e in p.evaluations):
        require_intact(e.path, "evaluate")  # a collected evaluation missing a file must not drop out silently
    config: dict[str, Any] = {"plot": ctx.cfg["plot"], "reference": [p.grid.reference for p in passes],
                              "pairing": [p.pairing for p in passes]}
    inputs: dict[str, str] = {}
    for i, p in enumerate(passes):
        tag = f"{i}:{p.label}"
        if p.generate is not None:
            inputs[f"{tag}/generate"] = p.generate.key
        if p.pseudo is not None:
            inputs[f"{tag}/pseudolabel"] = p.pseudo.key
        for j, e in enumerate(sorted(p.evaluations, key=lambda e: e.key)):
            inputs[f"{tag}/evaluate/{j}"] = e.key
    for name in figures:
        # a figure that reads files of its own (cost.csv, the paper's timings) puts their hashes in the key
        cache_key = getattr(inspect.getmodule(FIGURES.resolve(name)), "cache_key", None)
        if cache_key is not None:
            config[name], extra_inputs = cache_key(passes, options(ctx.cfg, passes))
            inputs.update(extra_inputs)
    result = run_cached(ctx, "plot", VERSION, config, inputs, lambda out: make_plots(ctx, passes, out),
                        result_cls=Figures)
    assert isinstance(result, Figures)
    return result


# -- Table 1 from the authors' released per-class results (plot.table_csv) -----------------------------
def run_table_csv(ctx: Context, tracker: Any) -> Figures:
    """The plot stage on its own: Table 1 from plot.table_csv under the run's metric convention (cached
    by the file's content, the filters and the convention), logged to the open MLflow run. Logic in
    pairedgta.figures.paper_table."""
    from pairedgta.figures.paper_table import paper_table
    from pairedgta.metrics.conventions import convention_from_config

    pcfg = ctx.cfg.get("plot") or {}
    path = Path(str(pcfg["table_csv"]))
    if not path.is_file():
        raise ConfigError(f"plot.table_csv={path}: no such file; give the authors' results_class_retention_by_condition.csv")
    conv = convention_from_config(ctx.cfg.get("metric") or {})
    filters = dict(pcfg.get("table_filter") or {})
    formats, dpi = list(pcfg.get("formats", ["png"])), int(pcfg.get("dpi", 150))
    config = {"table_csv": path.name, "filter": filters, "convention": conv.as_dict(), "formats": formats, "dpi": dpi}

    def build(out: Path) -> dict[str, Any]:
        paths, xi = paper_table(path, out, conv, filters, formats, dpi)
        means = xi[xi["class_name"] == "mean"]
        metrics = {f"table/authors/xi_mean/{r.condition}/{r.model}": float(r.xi) for r in means.itertuples()
                   if not math.isnan(float(r.xi))}
        write_json(out / "metrics.json", metrics, sort_keys=True)
        return {"figures": [p.name for p in paths], "metrics": metrics}

    result = run_cached(ctx, "plot", VERSION, config, {"table_csv": sha256_file(path)[:16]}, build, label="[table_csv]",
                        result_cls=Figures)
    assert isinstance(result, Figures)
    tracker.stage_files(f"plot.{result.key}", result.hit, result.files(), "figures")
    tracker.metrics(result.metrics())
    return result
