"""Pseudo-label stage: the weak ground truth of each pass's dataset from the reference model's clean predictions,
cached per dataset and reference. What the labels are is the run's task's work (pairedgta/tasks.py `Task.work`:
segmentation's label maps in pairedgta/evaluation/pseudolabel.py, detection's boxes in
pairedgta/detection/pseudolabel.py); this module keys, caches and records them the same way for every task."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pairedgta.models.runtime import torch_threads
from pairedgta.stages.common import Context, TaskStage, Unsharded, run_cached

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState


@dataclass
class Pseudolabel(Unsharded, TaskStage):
    """The pseudo-label stage (pairedgta.stages.common.Stage) of one dataset and reference model (`model_cfg`: the
    run's `reference_model`), its work a pairedgta.work.PseudolabelWork."""

    name: str = field(default="pseudolabel", kw_only=True)

    def hash_config(self) -> dict[str, Any]:
        return self.work.hash_config(self.ctx, self.dataset, self.model_cfg)

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
