"""What a metric of the evaluate entry is: one class, listed once in `pairedgta/evaluation/registry.py`.

The torchmetrics update/compute contract, split where the stage splits it:

* `update(ctx)`: one group's per-pixel reduction, on the model's device, from the shared `GroupContext` (label
  maps, max probabilities, entropies, what the metrics' `needs` ask of the same forward, and the intermediates
  several metrics use, each computed once); returns the small tensors that cross to the host (in the one copy
  per group the stage makes);
* `record(host, group)`: those arrays as plain numbers (JSON: a shard job stores them, the merging run reads
  them back), kept per group so that a bootstrap can resample groups;
* `arrays(groups, conditions)`: what the metric adds to `group_counts.npz` (the paired comparisons across models);
* `write(out, evaluation, summary, arrays)`: compute over the groups and write its `files`, filling its
  `summary_keys` of summary.json;
* `read(path)`: the reader of one of its files.

Its `name`@`version` enters the evaluate stage's version (`registry.stage_version`), so adding a metric or
changing one moves the cache key without a hand bump."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: a cached run needs none

PSEUDO_LABEL, GT = "pseudo_label", "ground_truth"  # the reference sources xi is measured against


class GroupContext:
    """One group's N conditions on the device: `labels`, `confidence`, `entropy` N x H x W (the conditions in
    order, `clean` the index of the clean one); `pseudo` H x W the pseudo-label; `targets` N x H x W each
    condition's ground truth for its IoU (void where it has none; None: no condition has one); `visible`
    N x H x W (or None: all) the pixels visible in each condition and the clean image; `gt` H x W the
    reference's truth for xi (or None). Hidden pixels count as void in every reference. The shared
    intermediates are computed on first use and kept, so no metric recomputes another's."""

    def __init__(self, labels: Any, confidence: Any, entropy: Any, clean: int, pseudo: Any, targets: Any,
                 visible: Any, tau: float, gt: Any, use_pl: bool, num_classes: int = NUM_CLASSES,
                 energy: Any = None, gram: Any = None) -> None:
        self.labels, self.confidence, self.entropy, self.clean = labels, confidence, entropy, clean
        self.pseudo, self.targets, self.visible, self.gt = pseudo, targets, visible, gt
        self.tau, self.use_pl, self.num_classes = tau, use_pl, num_classes
        # from the same forward, where a metric `needs` them (None: not asked for, or the model has none)
        self.energy, self.gram = energy, gram  # N x H x W logsumexp of the logits; N x K x K Grams

    @cached_property
    def void(self) -> Any:
        return torch.full((), IGNORE_INDEX, dtype=self.pseudo.dtype, device=self.pseudo.device)

    def hide(self, ref: Any) -> Any:
        """The reference as condition c sees it: H x W shared by all (no masks), else N x H x W."""
        return ref if self.visible is None else torch.where(self.visible, ref, self.void)

    @cached_property
    def pseudo_seen(self) -> Any:
        """The pseudo-label with each condition's hidden pixels void."""
        return self.hide(self.pseudo)

    @cached_property
    def clean_labels(self) -> Any:
        """1 x H x W: the clean condition's label map."""
        return self.labels[self.clean].unsqueeze(0)

    @cached_property
    def same_clean(self) -> Any:
        """N x H x W: predicted as on the clean image."""
        return self.labels == self.clean_labels

    @cached_property
    def labelled(self) -> Any:
        """N x H x W: the pixels the clean condition's ground truth labels (not void), visible in each condition:
        those its accuracy counts. None without ground truth."""
        if self.targets is None:
            return None
        keep = (self.targets[self.clean] != IGNORE_INDEX).unsqueeze(0).expand_as(self.labels)
        return keep if self.visible is None else keep & self.visible

    @cached_property
    def valid(self) -> Any:
        """N x H x W: the pseudo-label's valid (not void, visible) pixels."""
        return (self.pseudo_seen != IGNORE_INDEX).expand_as(self.labels)


@dataclass(frozen=True)
class Group:
    """What a metric's `record` knows of the group besides its own arrays (on the host)."""

    group_id: str
    conditions: list[str]      # the conditions evaluated, in the order of the device tensors' first axis
    clean: int                 # index of the clean condition
    has_target: list[bool]     # per condition: ground truth for its IoU
    has_gt: bool               # the reference's ground truth (xi against it)
    use_pl: bool               # xi against the pseudo-label
    shape: tuple[int, int]     # H x W of the maps
    model: str
    dataset: str
    settings: dict[str, Any]   # evaluation.settings.metric_settings


@dataclass(frozen=True)
class ModelEvaluation:
    """What one model's entry is written from: its groups' records (`counting.group_counts`, in dataset
    order) and what names and settles the numbers."""

    dataset: str
    model: str
    reference_model: str  # the pseudo-labels' model
    conditions: list[str]
    settings: dict[str, Any]  # evaluation.settings.metric_settings
    groups: list[dict[str, Any]]
    coverage: dict[str, Any]  # `entry.coverage`: how many groups each condition averages over
    # the Cityscapes classes the model's label space cannot predict (no output channel maps to them:
    # `entry.label_space`), and that space; () for a zoo model and any model that can predict every class.
    # Their xi and IoU are NaN with that reason and the class-wise means leave them out
    unpredictable: tuple[str, ...] = ()
    label_space: str = ""

    def blind(self) -> np.ndarray:
        """Boolean mask over the 19 Cityscapes classes: those the model cannot predict."""
        return np.array([n in self.unpredictable for n in CLASS_NAMES], dtype=bool)

    def blind_reason(self) -> str:
        """The `reason` xi.csv and gt_iou.csv give such a class."""
        return f"cannot predict (label space {self.label_space})"


class Metric:
    """A metric of the evaluate entry (module docstring). `name` is its key in a group's record unless
    `field` names another; `version` changes whenever its numbers or files change for the same input."""

    name: str = ""
    version: str = "1"
    field: str = ""
    files: tuple[str, ...] = ()
    summary_keys: tuple[str, ...] = ()  # summary.json keys it fills (created empty before any metric writes)
    needs: tuple[str, ...] = ()  # what else its update reads from the forward: "energy", "gram" (`predict_maps`)

    @property
    def key(self) -> str:
        return self.field or self.name

    def update(self, ctx: GroupContext) -> dict[str, Any]:
        return {}

    def record(self, host: dict[str, np.ndarray], group: Group) -> Any:
        return {}

    def arrays(self, groups: list[dict[str, Any]], conditions: list[str]) -> dict[str, np.ndarray]:
        return {}

    def write(self, out: Path, e: ModelEvaluation, summary: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        """Compute over the groups, write `files` into `out`, fill `summary_keys`."""

    def read(self, path: Path) -> Any:
        """A CSV file of the metric as a frame (empty when the entry has none: a table written only when
        there is something to put in it)."""
        import pandas as pd

        return pd.read_csv(path, dtype={"pair_id": str}) if path.is_file() else pd.DataFrame()


def per_condition(groups: list[dict[str, Any]], key: str, conditions: list[str]):
    """(g, i, value) for each group g's record `key` (a dict by condition) at condition i of `conditions`."""
    index = {c: i for i, c in enumerate(conditions)}
    for g, r in enumerate(groups):
        for cond, value in (r.get(key) or {}).items():
            if cond in index:
                yield g, index[cond], value


__all__ = ["PSEUDO_LABEL", "GT", "GroupContext", "Group", "ModelEvaluation", "Metric", "per_condition"]
