"""Every stage of the run, declared once: one `StageSpec` line in `STAGES` below.

The rest follows from that list: the names `stages=[...]` and `force=[...]` accept and the default
graph (pairedgta/schema.py), the cache's stage folders (pairedgta/config_checks.py), what a plan runs and
in which order (pairedgta/stages/planning.py `Plan.steps`), the result slots of a pass (`PassResult.results`),
the plot stage's inputs and the app's loop (pairedgta/app.py). A stage module gives its
pairedgta.stages.common.Stage class and `step(ctx, p, state)`; the spec names both by string, so the schema
reads this list without importing a stage (torch, the renderers). Adding a stage: its module, one line here.

This module sits below pairedgta.schema and pairedgta.stages and imports neither (tests/test_architecture.py)."""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable, Iterable

from pairedgta.errors import ConfigError

SCOPES = ("dataset", "pass", "run", "check")
# dataset: opens a pass's dataset (per pass, before any pass's data is read: generate renders it)
# pass:    per pass, over its open dataset
# run:     once over every pass of the run (the figures)
# check:   a check of the models themselves, outside the paired graph: run alone


@dataclass(frozen=True)
class StageSpec:
    """One stage: its name (also its cache folder), where its code is, what it reads and where its result goes."""

    name: str
    module: str  # holds `step(ctx, p, state)` and the Stage class `stage`
    stage: str  # its pairedgta.stages.common.Stage implementation, whose `version` is the stage's VERSION
    scope: str = "pass"
    needs: tuple[str, ...] = ()  # upstream stages it reads: they run whenever it runs
    node: str | None = None  # the RunConfig node of its options (pairedgta/schema.py), if any
    slot: str | None = None  # the attribute of the pass (PassResult) that holds its result
    many: bool = False  # the slot holds a list (one result per model), not one result
    config_needs: str | None = None  # "module:function", (cfg) -> the stages the run's config makes it read

    def __post_init__(self) -> None:
        if self.scope not in SCOPES:
            raise ValueError(f"stage {self.name}: scope {self.scope!r} is not one of {', '.join(SCOPES)}")

    def load(self) -> Any:
        return importlib.import_module(self.module)

    @property
    def step(self) -> Callable[..., None]:
        """The app's entry point: `step(ctx, p, state)` (pairedgta.stages.planning.Step)."""
        return self.load().step

    @property
    def stage_class(self) -> type:
        return getattr(self.load(), self.stage)

    @property
    def version(self) -> str:
        """The stage class's declared version (evaluate adds its metrics' past VERSION 8 when it hashes)."""
        return str(self.stage_class.__dataclass_fields__["version"].default)

    def needs_of(self, cfg: dict[str, Any]) -> set[str]:
        """The upstream stages `cfg` makes this stage read beyond its fixed `needs` (the figures' for plot)."""
        if not self.config_needs:
            return set()
        module, attr = self.config_needs.split(":")
        return set(getattr(importlib.import_module(module), attr)(cfg))


STAGES: tuple[StageSpec, ...] = (
    StageSpec("generate", "pairedgta.stages.generate", "Generate", scope="dataset", node="generate", slot="generate"),
    StageSpec("pseudolabel", "pairedgta.stages.pseudolabel", "Pseudolabel", needs=("generate",), node="pseudolabel",
              slot="pseudo"),
    StageSpec("evaluate", "pairedgta.stages.evaluate", "Evaluate", needs=("pseudolabel",), node="evaluate",
              slot="evaluations", many=True),
    StageSpec("plot", "pairedgta.stages.plot", "Plot", scope="run", node="plot",
              config_needs="pairedgta.figures:needed_stages"),
    StageSpec("cityscapes_val", "pairedgta.stages.cityscapes_val", "CityscapesVal", scope="check"),
    StageSpec("model_check", "pairedgta.stages.model_check", "ModelCheck", scope="check", needs=("generate",)),
)


# -- what the rest of the package reads: always through these, so a spec added to STAGES is seen everywhere ----
def names() -> tuple[str, ...]:
    return tuple(s.name for s in STAGES)


def spec(name: str) -> StageSpec:
    for s in STAGES:
        if s.name == name:
            return s
    raise ConfigError(f"stage {name!r} is unknown; stages are {', '.join(names())}")


def in_scope(*scopes: str) -> list[StageSpec]:
    """The specs of these scopes, in the order they run."""
    return [s for s in STAGES if s.scope in scopes]


def graph() -> list[str]:
    """The paired graph, every stage but the checks: the default of `stages`."""
    return [s.name for s in STAGES if s.scope != "check"]


def with_upstream(requested: Iterable[str]) -> set[str]:
    """The requested stages and every stage they read, transitively (`needs`)."""
    out: set[str] = set()
    todo = list(requested)
    while todo:
        name = todo.pop()
        if name not in out:
            out.add(name)
            todo += spec(name).needs
    return out


def slotted() -> list[StageSpec]:
    """The stages whose result a pass holds, in graph order."""
    return [s for s in STAGES if s.slot]


def empty_slots() -> dict[str, Any]:
    """A fresh pass's results: None per slot, an empty list for a stage with one result per model."""
    return {s.slot: [] if s.many else None for s in slotted()}


__all__ = ["SCOPES", "STAGES", "StageSpec", "names", "spec", "in_scope", "graph", "with_upstream", "slotted",
           "empty_slots"]
