"""Figure families of the plot stage, one module each, all drawn the same way.

Every family is a function `draw(passes, out, opts) -> (files, metrics)` declared by one `FigureSpec` in
`FIGURES` below: the stage whose outputs it reads (`needs`), the config key of a user-given file that
replaces that stage (`unless`), or of the only file it is drawn from (`source`, e.g. Table 1 from the
authors' per-class CSV at plot.table_csv: when that key is set it is the run's only figure and reads no
stage), and `key`, the function that puts the figure's own input files into the plot stage's cache key.
The spec is all the plot stage reads before drawing, so a cached run imports no figure module but those
with a `key` (seaborn alone costs ~0.5 s). A pass gives the figures its dataset, grid and the results of its stages
(`pairedgta.figures.inputs.FigurePass`), whose readers belong to the stages (`p.evaluations[i].xi()`,
`p.pseudo.labels.load(group)`, ...): figures never name a stage's files and import no stage.

Adding a figure: a module with `draw`, and one line in `FIGURES`."""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from pairedgta.errors import ConfigError

if TYPE_CHECKING:
    from pairedgta.figures.inputs import Passes

Drawn = tuple[list[Path], dict[str, float]]  # the files a figure wrote and the numbers it logs
Keyed = tuple[dict[str, Any], dict[str, str]]  # (config, input hashes) a figure adds to the plot key


@dataclass(frozen=True)
class FigureSpec:
    """What a figure reads, declared without importing it."""

    name: str
    draw: str  # "module:function", called as draw(passes, out, opts) -> (files, metrics)
    needs: str | None = None  # the upstream stage it reads: generate, pseudolabel or evaluate
    unless: str | None = None  # config key of a file of the user's that replaces `needs` (cost.csv)
    source: str | None = None  # config key of the one file it is drawn from instead of the run's data
    key: str | None = None  # "module:function", (passes, opts) -> (config, inputs): its own files in the key

    def drawer(self) -> Callable[[Passes, Path, FigureOptions], Drawn]:
        return self._load(self.draw)

    def keyer(self) -> Callable[[Passes, FigureOptions], Keyed] | None:
        return self._load(self.key) if self.key else None

    def _load(self, target: str) -> Any:
        module, attr = target.split(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as exc:  # a plotting dependency missing: the fix, not a traceback
            if exc.name and exc.name.split(".")[0] == "pairedgta":
                raise
            raise ConfigError(f"plot.figures={self.name} needs the Python package '{exc.name}', which is not "
                              "installed; install the project as the README says (pip install -e .)") from None


FIGURES: tuple[FigureSpec, ...] = (
    FigureSpec("xi_table", "pairedgta.figures.xi:draw", needs="evaluate"),
    FigureSpec("ranking", "pairedgta.figures.ranking:draw", needs="evaluate"),
    FigureSpec("qualitative", "pairedgta.figures.qualitative:draw", needs="evaluate"),
    FigureSpec("xi_models", "pairedgta.figures.comparison:draw", needs="evaluate"),
    FigureSpec("metric_validity", "pairedgta.figures.validity:draw", needs="evaluate"),
    # keyed by metric.validity.permutations and reference_model, which only this figure reads
    FigureSpec("estimators", "pairedgta.figures.estimators:draw", needs="evaluate",
               key="pairedgta.figures.estimators:cache_key"),
    FigureSpec("ablation", "pairedgta.figures.ablation:draw", needs="evaluate"),
    FigureSpec("distribution", "pairedgta.figures.distribution:draw", needs="pseudolabel"),
    FigureSpec("contact_sheet", "pairedgta.figures.contact_sheet:draw", needs="generate"),
    FigureSpec("robustness", "pairedgta.figures.robustness:draw", needs="evaluate"),  # only on a severity ladder
    # keyed by who is reported against whom (the same evaluations can hold another subject's report)
    FigureSpec("model_report", "pairedgta.figures.model_report:draw", needs="evaluate",
               key="pairedgta.figures.report_population:cache_key"),
    # keyed by the files they read besides the stages' (cost.csv, the paper's timings, the authors' CSVs)
    FigureSpec("cost", "pairedgta.figures.cost:draw", needs="generate", unless="cost.csv",
               key="pairedgta.figures.cost:cache_key"),
    FigureSpec("photometry", "pairedgta.figures.photometry:draw", needs="generate",
               key="pairedgta.figures.photometry:cache_key"),
    FigureSpec("authors_table", "pairedgta.figures.paper_table:draw", source="plot.table_csv",
               key="pairedgta.figures.paper_table:cache_key"),
    # task=detection (pairedgta/tasks.py): the detection results of the same paired scenes
    FigureSpec("det_xi", "pairedgta.figures.det_xi:draw", needs="evaluate"),
    FigureSpec("det_robustness", "pairedgta.figures.det_robustness:draw", needs="evaluate"),
    FigureSpec("det_objects", "pairedgta.figures.det_objects:draw", needs="evaluate"),
    FigureSpec("det_qualitative", "pairedgta.figures.det_qualitative:draw", needs="evaluate"),
    FigureSpec("det_estimators", "pairedgta.figures.det_estimators:draw", needs="evaluate"),
    FigureSpec("det_model_report", "pairedgta.figures.det_model_report:draw", needs="evaluate",
               key="pairedgta.figures.report_population:cache_key"),
    # either task, on a run whose conditions hold 2D corruptions (conditions=paper_corruptions)
    FigureSpec("corruptions", "pairedgta.figures.corruptions:draw", needs="evaluate"),
    FigureSpec("corruption_study", "pairedgta.figures.corruption_study:draw", needs="evaluate"),
    FigureSpec("authors_ranking", "pairedgta.figures.authors_ranking:draw", source="plot.frame_counts_csv",
               key="pairedgta.figures.authors_ranking:cache_key"),
)
_BY_NAME = {spec.name: spec for spec in FIGURES}


def figure(name: Any) -> FigureSpec:
    """The spec of a figure named in plot.figures; one line listing the known ones for any other name."""
    if name not in _BY_NAME:
        raise ConfigError(f"plot.figures={name!r} is unknown; choose one of: {', '.join(sorted(_BY_NAME))}")
    return _BY_NAME[name]


@dataclass
class FigureOptions:
    formats: list[str]
    dpi: int
    run: Any  # pairedgta.schema.RunConfig of the run (the first pass's): plot, metric, cost, photometry, device
    multi: bool = False  # several passes: file stems get the pass label
    # file name -> the model (and pass) a figure shows alone; the plot stage saves it so each model's
    # MLflow run can carry its own figures
    owners: dict[str, dict[str, str]] = field(default_factory=dict)
    # file name -> what it is, for the pages the run points to in the terminal (a model report), hit or miss
    pages: dict[str, str] = field(default_factory=dict)

    def own(self, paths: list[Path], model: str, label: str) -> list[Path]:
        """Record `paths` as figures of one model of one pass; returns them."""
        for path in paths:
            self.owners[Path(path).name] = {"model": str(model), "pass": str(label)}
        return paths

    def point(self, path: Path, what: str) -> None:
        """Record `path` as a page the run names in the terminal (`what: <path>`), on a cache hit too."""
        self.pages[Path(path).name] = str(what)

    @property
    def plot(self) -> Any:
        """pairedgta.schema.PlotConfig"""
        return self.run.plot

    def stem(self, base: str, label: str) -> str:
        from pairedgta.figures.common import slug

        return f"{base}_{slug(label)}" if self.multi else base


def lookup(cfg: dict[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


__all__ = ["FIGURES", "FigureOptions", "FigureSpec", "figure", "lookup"]


# -- what a run's figures need: read by the planner before any stage runs ---------------------------
def sourced(cfg: dict[str, Any]) -> dict[str, str]:
    """figure -> the config key of the file it is drawn from, for the figures whose key is set."""
    specs = sorted(FIGURES, key=lambda spec: spec.name)  # by name: the order they are drawn in
    return {spec.name: spec.source for spec in specs if spec.source and lookup(cfg, spec.source)}


def figures_of(cfg: dict[str, Any]) -> list[str]:
    given = sourced(cfg)
    if given:  # a user-given file replaces the run's data: only the figures drawn from it
        return list(given)
    # the default list has one owner, pairedgta/conf/config.yaml; an empty list draws nothing
    figures = list((cfg.get("plot") or {}).get("figures") or [])
    for f in figures:
        source = figure(f).source  # an unknown name: one line listing the known ones
        if source:
            raise ConfigError(f"plot.figures: {f} is drawn from a file of yours; set {source}=PATH (with stages=[plot])")
    return figures


def needed_stages(cfg: dict[str, Any]) -> set[str]:
    """Which upstream stages the requested figures read (a figure given its own input file needs none)."""
    needs = set()
    for f in figures_of(cfg):
        spec = figure(f)
        if spec.needs and not (spec.unless and lookup(cfg, spec.unless)):
            needs.add(spec.needs)
    return needs
