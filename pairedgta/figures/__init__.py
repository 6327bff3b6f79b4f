"""Figure families of the plot stage, one module each, all drawn the same way.

Every family is a function `draw(passes, out, opts) -> (files, metrics)` registered here with the stage
whose outputs it reads (`needs`) and, where it can read a user-given file instead, the config key that
names it (`unless`). A figure drawn only from a file the user gives (`source`, e.g. Table 1 from the
authors' per-class CSV at plot.table_csv) reads no stage: when its key is set it is the run's only figure. A pass gives the figures its dataset, grid and the results of its stages, whose
readers belong to the stages (`p.evaluations[i].xi()`, `p.pseudo.labels.load(group)`, ...): figures
never name a stage's files and import no stage."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pairedgta.registry import Registry

FIGURES = Registry("figure", "plot.figures")
FIGURES.register("xi_table", "pairedgta.figures.xi:draw", needs="evaluate")
FIGURES.register("ranking", "pairedgta.figures.ranking:draw", needs="evaluate")
FIGURES.register("qualitative", "pairedgta.figures.qualitative:draw", needs="evaluate")
FIGURES.register("xi_models", "pairedgta.figures.comparison:draw", needs="evaluate")
FIGURES.register("metric_validity", "pairedgta.figures.validity:draw", needs="evaluate")
# keyed: metric.validity.permutations and reference_model enter the plot hash
FIGURES.register("estimators", "pairedgta.figures.estimators:draw", needs="evaluate", keyed=True)
FIGURES.register("ablation", "pairedgta.figures.ablation:draw", needs="evaluate")
FIGURES.register("distribution", "pairedgta.figures.distribution:draw", needs="pseudolabel")
FIGURES.register("contact_sheet", "pairedgta.figures.contact_sheet:draw", needs="generate")
FIGURES.register("robustness", "pairedgta.figures.robustness:draw", needs="evaluate")  # ladders only
# keyed: the module has a `cache_key(passes, opts)` (files of its own enter the plot hash); declared here
# so that a cached run imports no figure module (seaborn alone costs ~0.5 s)
FIGURES.register("cost", "pairedgta.figures.cost:draw", needs="generate", unless="cost.csv", keyed=True)
FIGURES.register("photometry", "pairedgta.figures.photometry:draw", needs="generate", keyed=True)
FIGURES.register("authors_table", "pairedgta.figures.paper_table:draw", needs=None, source="plot.table_csv", keyed=True)
FIGURES.register("authors_ranking", "pairedgta.figures.authors_ranking:draw", needs=None, source="plot.frame_counts_csv",
                 keyed=True)


@dataclass
class FigureOptions:
    formats: list[str]
    dpi: int
    cfg: dict[str, Any]  # the run's config (the first pass's): plot.*, metric.*, cost.*, device
    multi: bool = False  # several passes: file stems get the pass label
    # file name -> the model (and pass) a figure shows alone; the plot stage saves it so each model's
    # MLflow run can carry its own figures
    owners: dict[str, dict[str, str]] = field(default_factory=dict)

    def own(self, paths: list[Path], model: str, label: str) -> list[Path]:
        """Record `paths` as figures of one model of one pass; returns them."""
        for path in paths:
            self.owners[Path(path).name] = {"model": str(model), "pass": str(label)}
        return paths

    @property
    def plot(self) -> dict[str, Any]:
        return dict(self.cfg.get("plot") or {})

    def stem(self, base: str, label: str) -> str:
        from pairedgta.figures.common import slug

        return f"{base}_{slug(label)}" if self.multi else base


def lookup(cfg: dict[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


__all__ = ["FIGURES", "FigureOptions", "lookup"]
