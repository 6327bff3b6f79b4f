"""The tasks the paired method runs, one declaration each: its model kind, its work for each task-neutral stage
(pseudo-labeller, evaluation, checks), its metrics, figures, zoo, reference and the words its messages use.
`task=<name>` chooses one (pairedgta/conf/task/); the stage graph, its cache, shards, sweeps and MLflow record are
the same for every task: each stage of pairedgta/stages/ calls `Task.work_for(stage)` (a pairedgta.work protocol)
and names no task. No code outside this module and pairedgta/conf/task/ names a task or branches on one.

Adding a task: its work classes (below the stages: they import pairedgta.entries, never pairedgta.stages), one
`Task` entry in TASKS and its option file pairedgta/conf/task/<name>.yaml (docs/contributing.md, "Add a task").
This module imports no stage and no torch (the schema reads it)."""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Mapping

from pairedgta.errors import ConfigError


@dataclass(frozen=True)
class Task:
    name: str
    model_kind: str  # what its models build: pairedgta.models.model_kind ("segmenter", "detector")
    work: Mapping[str, str] = field(default_factory=dict)  # stage -> "module:Class", built with the task
    figures: tuple[str, ...] = ()  # the figure families (plot.figures) that draw this task's results
    metrics: str = ""  # "module:ATTR", the metrics its evaluate work computes, listed once
    what: str = ""  # one phrase for messages: what its models predict
    phi: tuple[str, str] = ("pixels", "pixels predicted with\nconfidence ≥ τ_mass")  # what its prediction mass counts
    title: str = "mean xi"  # the terminal table's title (pairedgta/report.py)
    support: str = ""  # what its summaries' `xi_support` counts per condition (a row of that table), e.g. boxes
    example: str = ""  # a model of this task for messages, e.g. "model=demo_segformer"
    zoo: str = ""  # the option file (under pairedgta/conf/) whose `models` list its offline zoo
    report_figure: str = ""  # its model report (+experiment=model_report): the figure family that draws it

    def work_for(self, stage: str) -> Any:
        """This task's work for `stage` (a pairedgta.work protocol), built once per task."""
        key = (self.name, stage, self.work.get(stage))
        if key not in _WORK:
            if stage not in self.work:
                raise ConfigError(f"task={self.name} does no {stage}: its stages are {', '.join(self.work)}; run "
                                  f"{stage} with task={' or task='.join(t.name for t in TASKS.values() if stage in t.work)}")
            module, attr = self.work[stage].split(":")
            _WORK[key] = getattr(importlib.import_module(module), attr)(self)
        return _WORK[key]

    def metric_list(self) -> tuple[Any, ...]:
        module, attr = self.metrics.split(":")
        return tuple(getattr(importlib.import_module(module), attr))


_WORK: dict[tuple[str, str, str | None], Any] = {}
SEGMENTATION_FIGURES = ("xi_models", "xi_table", "ranking", "qualitative", "contact_sheet", "robustness",
                        "distribution", "cost", "ablation", "estimators", "metric_validity", "model_report",
                        "authors_table", "authors_ranking", "photometry", "corruptions",
                        "corruption_study")
DEFAULT = "segmentation"  # the paper's task
TASKS: dict[str, Task] = {
    "segmentation": Task(
        "segmentation", "segmenter",
        {"pseudolabel": "pairedgta.evaluation.pseudolabel:SegmentationPseudolabels",
         "evaluate": "pairedgta.evaluation.work:SegmentationEvaluate",
         "cityscapes_val": "pairedgta.evaluation.cityscapes_val:SegmentationCityscapesVal",
         "model_check": "pairedgta.evaluation.model_check:SegmentationModelCheck"},
        SEGMENTATION_FIGURES, "pairedgta.evaluation.registry:METRICS", "label maps",
        example="model=demo_segformer", zoo="experiment/zoo.yaml", report_figure="model_report"),
    "detection": Task(
        "detection", "detector",
        {"pseudolabel": "pairedgta.detection.pseudolabel:DetectionPseudolabels",
         "evaluate": "pairedgta.detection.evaluate:DetectionEvaluate",
         "cityscapes_val": "pairedgta.detection.cityscapes_val:DetectionCityscapesVal",
         "model_check": "pairedgta.detection.model_check:DetectionModelCheck"},
        ("det_xi", "det_robustness", "det_objects", "det_qualitative", "contact_sheet", "ranking",
         "det_model_report", "det_estimators", "corruptions", "corruption_study"),
        "pairedgta.detection.registry:METRICS", "boxes", ("boxes", "boxes scored ≥ the\nmodel's threshold"),
        title="mean detection xi", support="reference boxes", example="model=demo_det_reference",
        zoo="experiment/det_zoo.yaml", report_figure="det_model_report"),
}
NAMES = TASKS.keys()  # a live view: a task declared later (a plug-in, a test's toy task) is a choice too


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
                f"({task.what}); choose a {task.model_kind} (e.g. {task.example}) or run it with task={other.name}")


def check_figures(task: Task, figures: list[str]) -> None:
    bad = [f for f in figures if f not in task.figures]
    if bad:
        raise ConfigError(f"plot.figures={bad} draw(s) another task's results; task={task.name} draws "
                          f"{', '.join(task.figures)}")


def of_entry(summary: Mapping[str, Any]) -> Task:
    """The task an entry's summary.json was written by (its `task` key; the default task's entries have none)."""
    return TASKS.get(str(summary.get("task") or DEFAULT), TASKS[DEFAULT])


def report_figures() -> tuple[str, ...]:
    return tuple(t.report_figure for t in TASKS.values() if t.report_figure)


__all__ = ["DEFAULT", "NAMES", "TASKS", "Task", "check_figures", "check_models", "get", "of_entry", "report_figures"]
