"""The tasks the paired method runs, one declaration each: which stages do the task's own work (its pseudo-labeller,
its evaluation), the kind of model it runs, and its figures. `task=<name>` chooses one (pairedgta/conf/task/); the
stage graph, its cache, shards, sweeps and MLflow record are the same for every task: the plan hands each stage
spec of pairedgta/stage_registry.py to the app resolved for the run's task (`resolve`), and no stage branches on it.

Adding a task: its stage modules (each with `step(ctx, p, state)` and its Stage class), its figures
(pairedgta/figures/__init__.py), one `Task` line in TASKS and its option file pairedgta/conf/task/<name>.yaml.
This module sits beside pairedgta/stage_registry.py and imports no stage (the schema reads it without torch)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping

from pairedgta.errors import ConfigError


@dataclass(frozen=True)
class Task:
    name: str
    model_kind: str  # what its models build: pairedgta.models.model_kind ("segmenter", "detector")
    stages: Mapping[str, str] = field(default_factory=dict)  # stage name -> "module:StageClass" doing this task's work
    figures: tuple[str, ...] = ()  # the figure families (plot.figures) that draw this task's results
    metrics: str = ""  # "module:ATTR", the metrics its evaluate stage computes, listed once
    what: str = ""  # one phrase for messages: what its models predict
    phi: tuple[str, str] = ("pixels", "pixels predicted with\nconfidence ≥ τ_mass")  # what its prediction mass counts

    def resolve(self, spec: Any) -> Any:
        """The stage spec (pairedgta.stage_registry.StageSpec) as this task runs it."""
        if spec.name not in self.stages:
            return spec
        module, stage = self.stages[spec.name].split(":")
        return dataclasses.replace(spec, module=module, stage=stage)

    def metric_list(self) -> tuple[Any, ...]:
        import importlib

        module, attr = self.metrics.split(":")
        return tuple(getattr(importlib.import_module(module), attr))


SEGMENTATION_FIGURES = ("xi_models", "xi_table", "ranking", "qualitative", "contact_sheet", "robustness",
                        "distribution", "cost", "ablation", "estimators", "metric_validity", "model_report",
                        "authors_table", "authors_ranking", "photometry")
TASKS: dict[str, Task] = {
    "segmentation": Task("segmentation", "segmenter", {}, SEGMENTATION_FIGURES, "pairedgta.evaluation.registry:METRICS",
                         "label maps"),
    "detection": Task("detection", "detector",
                      {"pseudolabel": "pairedgta.stages.detection_pseudolabel:DetectionPseudolabel",
                       "evaluate": "pairedgta.stages.detection_evaluate:DetectionEvaluate",
                       "cityscapes_val": "pairedgta.stages.detection_cityscapes_val:DetectionCityscapesVal"},
                      ("det_xi", "det_robustness", "det_objects", "det_qualitative", "contact_sheet", "ranking",
                       "det_model_report", "det_estimators"),
                      "pairedgta.detection.registry:METRICS", "boxes",
                      ("boxes", "boxes scored ≥ the\nmodel's threshold")),
}
NAMES = tuple(TASKS)


def get(name: str) -> Task:
    try:
        return TASKS[name]
    except KeyError:
        raise ConfigError(f"task={name!r} is unknown; use one of {', '.join(NAMES)}") from None


def check_models(task: Task, models: list[tuple[str, Mapping[str, Any]]]) -> None:
    """A model of the other kind (a segmenter asked for detection xi, a detector for label maps): one line, before
    any stage writes. `models`: (where, composed config)."""
    from pairedgta.models import model_kind

    for where, cfg in models:
        kind = model_kind(cfg)
        if kind != task.model_kind:
            other = next(t for t in TASKS.values() if t.model_kind == kind)
            raise ConfigError(
                f"{where}={cfg.get('name')} is a {kind} ({other.what}), but task={task.name} needs a {task.model_kind} "
                f"({task.what}); choose a {task.model_kind} (e.g. {_example(task)}) or run it with task={other.name}")


def _example(task: Task) -> str:
    return {"detection": "model=demo_det_reference", "segmentation": "model=demo_segformer"}.get(task.name, "")


def check_figures(task: Task, figures: list[str]) -> None:
    bad = [f for f in figures if f not in task.figures]
    if bad:
        raise ConfigError(f"plot.figures={bad} draw(s) another task's results; task={task.name} draws "
                          f"{', '.join(task.figures)}")


__all__ = ["NAMES", "TASKS", "Task", "check_figures", "check_models", "get"]
