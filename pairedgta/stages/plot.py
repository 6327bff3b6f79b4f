"""Plot stage: the paper's figures and tables from the cached stage outputs of one or more passes (a pass
= one dataset variant: the generated dataset, ACDC, a pairing level ...). `plot.figures` picks the
families declared in pairedgta.figures.FIGURES (xi_table, ranking, qualitative, ablation, distribution,
contact_sheet, cost); each draws itself from the passes.

A figure declared with a `source` key (authors_table: Table 1 from the authors' released per-class
results, plot.table_csv=PATH) is drawn from that file alone: when the key is set it is the only figure
and no stage runs before the plot (stages=[plot]).

Every output is written into the stage's cache directory; `metrics.json` holds the numbers the run logs
to MLflow (so a cache hit logs them too) and `owners.json` which figures show one model alone (those
go to that model's MLflow run)."""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tqdm import tqdm

from pairedgta import stage_registry
from pairedgta.cache import require_intact
from pairedgta.figures import FigureOptions, figure, figures_of, sourced
from pairedgta.jsonio import write_json
from pairedgta.schema import RunConfig, as_dict
from pairedgta.stages.common import Context, StageResult, Unsharded, run_cached

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

log = logging.getLogger("pairedgta.plot")
VERSION = "14"  # 14: the estimators figure draws the paired differences to xi; 13: GDE over the twins (metric.validity.twins), an estimator judged over the models it is defined for; 12: issue 49's estimator statistics (BCa over scenes and models, paired differences, Holm, leave one illumination out, ALine, held-out ATC, committee agreement, estimator_pairs.csv), n_frames in every rho table, rPC undefined below its floor; 11: the reference model is not ranked (xi_models, table1_xi), the estimators' permutation test under the joint null; 10: the photometry figure; the validity figure draws no interval as a hollow marker at the configured level; 9: robustness curves of severity ladders; 5: the ranking figure says why a class has no rho_valid in terms of phi; 6: one title line per selection
# 7: rho intervals in the ranking titles, >= 1200 px wide; unsupported xi cells marked; 8: paper Means of printed cells, half up
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

    def pages(self) -> list[tuple[Path, str]]:
        """The pages the run names in the terminal (a model report): (file, what it is)."""
        path = self.path / "pages.json"
        pages = json.loads(path.read_text()) if path.is_file() else {}
        return [(self.path / name, what) for name, what in sorted(pages.items()) if (self.path / name).is_file()]


def options(run: RunConfig, passes: list[PassResult]) -> FigureOptions:
    return FigureOptions(list(run.plot.formats), int(run.plot.dpi), run, multi=len(passes) > 1)


def make_plots(ctx: Context, passes: list[PassResult], out: Path) -> dict[str, Any]:
    opts = options(ctx.run, passes)
    files: list[Path] = []
    metrics: dict[str, float] = {}
    names = figures_of(ctx.cfg)
    bar = tqdm(names, desc="plot", unit="figure")
    for name in bar:
        bar.set_postfix_str(name)
        drawn, numbers = figure(name).drawer()(passes, out, opts)
        files += drawn
        metrics.update(numbers)
    clean_metrics = {k: float(v) for k, v in metrics.items() if v is not None and not math.isnan(float(v))}
    write_json(out / "metrics.json", clean_metrics, sort_keys=True)
    write_json(out / "owners.json", opts.owners, sort_keys=True)
    if opts.pages:
        write_json(out / "pages.json", opts.pages, sort_keys=True)
    return {"figures": [p.name for p in files], "metrics": clean_metrics}


@dataclass
class Plot(Unsharded):
    """The plot stage (pairedgta.stages.common.Stage): the requested figures of every pass of the run."""

    ctx: Context
    passes: list[Any]
    name: str = "plot"
    version: str = VERSION
    label: str = ""
    resumable: bool = False
    result_cls: type[Figures] = Figures

    def __post_init__(self) -> None:
        self._config, self._inputs = plot_key(self.ctx, self.passes)

    def hash_config(self) -> dict[str, Any]:
        return self._config

    def inputs(self) -> dict[str, str]:
        return self._inputs

    def build(self, out: Path, key: str) -> dict[str, Any]:
        return make_plots(self.ctx, self.passes, out)


def plot_key(ctx: Context, passes: list[Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """What the figures are drawn from: the plot keys, each pass's stage entries and the files figures read."""
    figures = figures_of(ctx.cfg)
    # a figure's own input file enters the key by its content (its cache_key), not by its path
    paths = {key.split(".", 1)[1] for key in sourced(ctx.cfg).values() if key.startswith("plot.")}
    config: dict[str, Any] = {"plot": {k: v for k, v in as_dict(ctx.run.plot).items() if k not in paths},
                              "reference": [p.grid.reference for p in passes], "pairing": [p.pairing for p in passes]}
    inputs: dict[str, str] = {}
    for i, p in enumerate(passes):
        tag = f"{i}:{p.label}"
        for spec in stage_registry.slotted():  # every pass stage's result, in graph order
            held = p.results[spec.slot]
            if spec.many:
                for j, e in enumerate(sorted(held, key=lambda e: e.key)):
                    inputs[f"{tag}/{spec.name}/{j}"] = e.key
            elif held is not None:
                inputs[f"{tag}/{spec.name}"] = held.key
    for name in figures:
        # a figure that reads files of its own (cost.csv, the paper's timings) puts their hashes in the key
        cache_key = figure(name).keyer()
        if cache_key is not None:
            config[name], extra_inputs = cache_key(passes, options(ctx.run, passes))
            inputs.update(extra_inputs)
    return config, inputs


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step over all passes (scope "run": called once, with the first pass and its context; every pass
    is in `state.passes`): the figures, in the run's MLflow record, and each model's own figures in that model's
    nested run."""
    from pairedgta.tracking import bundle

    passes = state.passes
    for e in (e for q in passes for e in q.evaluations):
        require_intact(e.path, "evaluate")  # a collected evaluation missing a file must not drop out silently
    figures, recorder = run_cached(ctx, Plot(ctx, passes)), state.recorder
    assert isinstance(figures, Figures)
    state.summary["plot"] = str(figures.path)
    for page, what in figures.pages():
        log.info("%s: %s", what, page)
    own_runs = {(model, label) for _, model, label in state.model_runs}
    recorder.stage_files(bundle("plot", figures.key), figures.hit, figures.files_except(own_runs), "figures")
    recorder.metrics(figures.metrics())
    for run_id, model, label in state.model_runs:
        with recorder.run(run_id=run_id, nested=True):
            recorder.stage_files(bundle("plot", figures.key, label, model), figures.hit, figures.files_of(model, label),
                                 "figures")
