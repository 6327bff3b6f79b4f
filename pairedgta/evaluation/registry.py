"""The evaluate entry's metrics, in one ordered list: adding a metric is its class (`metric.Metric`) and one line
here. Everything else is derived from the list: the device reductions and per-group records of
`counting.group_counts`, the arrays of group_counts.npz, the tables `entry.write_outputs` writes, the entry's
files (`result_files`), the readers (`reader`) and the evaluate stage's version (`stage_version`)."""
from __future__ import annotations

from typing import Any

from pairedgta import work
from pairedgta.cityscapes import NUM_CLASSES

from pairedgta.evaluation import estimator_sums, tables, xi_precision
from pairedgta.evaluation.entry_files import OWN_FILES
from pairedgta.evaluation.metric import GroupContext, Metric

METRICS: list[Metric] = [tables.Xi(), tables.Agreement(), tables.RhoValid(), tables.GtIoU(), tables.Estimators(),
                         estimator_sums.NuclearNorm(), estimator_sums.Energy(), xi_precision.XiPrecision()]

# The metrics evaluate VERSION 8 was declared with. For exactly this list the stage's version stays the bare
# VERSION, so no cached entry moved when the metrics became a registry; any other list (a metric added, removed,
# reordered or with another version) appends its declaration, and the cache key moves by itself.
VERSION_8_METRICS = ("xi@8", "agreement@8", "rho_valid@8", "gt_iou@8", "estimators@8")


def metrics() -> list[Metric]:
    """The registered metrics, read at call time (a test may extend the list)."""
    return list(METRICS)


def declaration(ms: list[Metric] | None = None) -> tuple[str, ...]:
    return work.declaration(metrics() if ms is None else ms)


def stage_version(version: str, ms: list[Metric] | None = None) -> str:
    """The evaluate stage's version: its own `version` (the framework's), plus the metrics' declaration unless
    it is the one VERSION 8 had."""
    decl = declaration(ms)
    return version if decl == VERSION_8_METRICS else f"{version}+{','.join(decl)}"


def result_files(ms: list[Metric] | None = None) -> tuple[str, ...]:
    """Every table of an entry: the metrics' files in registry order, then the entry's own."""
    return work.result_files(metrics() if ms is None else ms) + OWN_FILES


def group_reductions(labels: Any, confidence: Any, entropy: Any, clean: int, pseudo: Any, targets: Any, visible: Any,
                     tau: float, gt: Any, use_pl: bool, num_classes: int = NUM_CLASSES) -> dict[str, Any]:
    """Every registered metric's device tensors of one group (`metric.GroupContext` says what the arguments
    are), in one dict: what `counting.GroupJob` copies to the host, for a check outside the stage
    (experiments/gpu_check.py)."""
    ctx = GroupContext(labels, confidence, entropy, clean, pseudo, targets, visible, tau, gt, use_pl, num_classes)
    return {k: v for m in metrics() for k, v in m.update(ctx).items()}


def reader(file: str) -> Any:
    """The metric that writes `file` (its `read` reads it)."""
    for m in metrics():
        if file in m.files:
            return m
    raise KeyError(f"no registered metric writes {file!r}; registered: {', '.join(declaration())}")


__all__ = ["METRICS", "VERSION_8_METRICS", "metrics", "declaration", "stage_version", "result_files", "reader", "group_reductions"]
