"""What a task supplies to each task-neutral stage (pairedgta/stages/): the stage owns the graph -- its cache key,
lookup, shards, MLflow record and step -- and calls its task's work through one of these protocols. A task names its
work per stage in its declaration (pairedgta/tasks.py: `Task.work`, "module:Class", built with the task), so the
stages never branch on a task and a new task is a declaration plus these classes (docs/contributing.md).

The work lives below the stages (pairedgta/evaluation/ for segmentation, pairedgta/detection/ for detection) and
imports no stage: its entry type and context come from pairedgta/entries.py."""
from __future__ import annotations

from pathlib import Path
from dataclasses import dataclass
from typing import Any, ClassVar, Iterable, Protocol, runtime_checkable

from pairedgta.entries import Context, StageResult


@runtime_checkable
class TaskMetric(Protocol):
    """What the stages and the record read of any task's metric, whatever it computes (segmentation's counting
    metrics, pairedgta/evaluation/metric.py; detection's table metrics, pairedgta/detection/registry.py): its name and
    version join the evaluate entry's version, its files are the entry's tables."""

    name: str
    version: str
    files: tuple[str, ...]


def declaration(metrics: Iterable[TaskMetric]) -> tuple[str, ...]:
    """`name@version` of each metric, in registry order: the part of an evaluate entry's version its metrics make."""
    return tuple(f"{m.name}@{m.version}" for m in metrics)


def result_files(metrics: Iterable[TaskMetric]) -> tuple[str, ...]:
    """The tables the metrics write, in registry order."""
    return tuple(f for m in metrics for f in m.files)


@dataclass(frozen=True)
class Work:
    """The common part of a task's work class: built with its task (`Task.work_for`), its entry's version one
    constant (`ENTRY_VERSION`) unless it depends on the model (an evaluation's metrics, a source's check)."""

    task: Any
    ENTRY_VERSION: ClassVar[str] = ""

    def version(self, model_cfg: dict[str, Any]) -> str:
        return self.ENTRY_VERSION


class PseudolabelWork(Protocol):
    """The weak ground truth of one dataset from the reference model's clean predictions (stage `pseudolabel`)."""

    result_cls: type[StageResult]     # the typed reader of its entry (`reference_model()`, `tau()`, `artifacts()`)

    def version(self, model_cfg: dict[str, Any]) -> str:
        """The entry's version for this task."""

    def hash_config(self, ctx: Context, dataset: Any, model_cfg: dict[str, Any]) -> dict[str, Any]:
        """What of the config decides the labels."""

    def compute(self, ctx: Context, dataset: Any, out: Path, model_cfg: dict[str, Any]) -> dict[str, Any]:
        """Write the entry into `out`; returns the result's extra values."""


class EvaluateWork(Protocol):
    """One model's evaluation against the pseudo-labels (stage `evaluate`), split over groups for shard jobs."""

    result_cls: type[StageResult]     # with `model`, `summary()`, `metrics()`, `artifacts()`, `xi()`

    def version(self, model_cfg: dict[str, Any]) -> str:
        """The entry's version: the task's framework and its registered metrics (and a source model's check)."""

    def settings(self, ctx: Context, dataset: Any) -> dict[str, Any]:
        """The metric settings the entry is keyed by (also how cached entries of other models are matched)."""

    def hash_config(self, model_cfg: dict[str, Any], settings: dict[str, Any], conditions: list[str],
                    threads: int) -> dict[str, Any]:
        """The entry's key config; every key but `model` and `threads` must match to collect another model's."""

    def compute(self, ctx: Context, dataset: Any, dataset_key: str, pseudo: Any, model_cfg: dict[str, Any],
                conditions: list[str], settings: dict[str, Any], out: Path, parts: Path) -> dict[str, Any]:
        """Every group (merging what shard jobs left in `parts`) into the entry `out`."""

    def groups(self, ctx: Context, dataset: Any, pseudo: Any, model_cfg: dict[str, Any], conditions: list[str],
               groups: list[Any], settings: dict[str, Any]) -> list[Any]:
        """A shard job's groups, as `write_part` stores them."""

    def read_parts(self, parts: Path) -> dict[str, Any]:
        """group id -> the result a shard job stored."""

    def write_part(self, parts: Path, shard: int, num: int, results: list[Any]) -> None:
        ...

    def said(self, result: Any, model_cfg: dict[str, Any]) -> None:
        """What a run says of an entry every time, computed now or read from the cache (a set-up line)."""

    def record(self, ctx: Context, result: Any, model_cfg: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str],
                                                                                     dict[str, Any]]:
        """The nested MLflow run's extra params, extra tags and tables."""


class CheckWork(Protocol):
    """A check of the models themselves, outside the paired graph (stages `cityscapes_val`, `model_check`)."""

    result_cls: type[StageResult]

    def version(self, model_cfg: dict[str, Any]) -> str:
        ...

    def hash_config(self, ctx: Context, dataset: Any, model_cfg: dict[str, Any]) -> dict[str, Any]:
        ...

    def compute(self, ctx: Context, dataset: Any, dataset_key: str, model_cfg: dict[str, Any],
                out: Path) -> dict[str, Any]:
        ...

    def report(self, result: StageResult, model_cfg: dict[str, Any]) -> tuple[dict[str, float], dict[str, Any]]:
        """Says the model's line(s) in the log; -> (its MLflow metrics, its entry in the run's summary)."""

    def files(self, result: StageResult) -> list[Path]:
        """The entry's files the MLflow record keeps."""


__all__ = ["CheckWork", "EvaluateWork", "PseudolabelWork", "TaskMetric", "Work", "declaration", "result_files"]
