"""Pseudo-label stage: the weak ground truth of each pass's dataset from the reference model's clean predictions,
cached per dataset and reference. What the labels are is the run's task's work (pairedgta/tasks.py `Task.work`:
segmentation's label maps in pairedgta/evaluation/pseudolabel.py, detection's boxes in
pairedgta/detection/pseudolabel.py); this module keys, caches and records them the same way for every task."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pairedgta import tasks
from pairedgta.datasets import PairedDataset
from pairedgta.entries import StageResult
from pairedgta.models.runtime import torch_threads
from pairedgta.stages.common import Context, Unsharded, run_cached
from pairedgta.work import PseudolabelWork

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState


@dataclass
class Pseudolabel(Unsharded):
    """The pseudo-label stage (pairedgta.stages.common.Stage) of one dataset and reference model."""

    ctx: Context
    dataset: PairedDataset
    dataset_key: str
    model_cfg: dict[str, Any]  # the reference model's composed config (the run's `reference_model`)
    work: PseudolabelWork = None  # type: ignore[assignment]  # the run's task's, when not given
    name: str = "pseudolabel"
    version: str = ""  # the task's work declares it
    resumable: bool = False
    result_cls: type[StageResult] = field(default=StageResult)

    def __post_init__(self) -> None:
        if self.work is None:
            self.work = tasks.get(self.ctx.run.task).work_for(self.name)
        self.version, self.result_cls = self.work.version, self.work.result_cls

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def hash_config(self) -> dict[str, Any]:
        return self.work.hash_config(self.ctx, self.dataset, self.model_cfg)

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        with torch_threads(self.ctx.run.threads):
            return self.work.compute(self.ctx, self.dataset, out, self.model_cfg)


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step for one pass: the reference model's pseudo-labels, their files in the run's MLflow record."""
    from pairedgta.tracking import bundle

    p.pseudo = run_cached(ctx, Pseudolabel(ctx, p.dataset, p.dataset_key, state.models.reference))
    state.summary.setdefault("pseudolabel", str(p.pseudo.path))
    state.recorder.stage_files(bundle("pseudolabel", p.pseudo.key), p.pseudo.hit, p.pseudo.artifacts(),
                               f"pseudolabel/{p.label}" if state.multi else "pseudolabel")
