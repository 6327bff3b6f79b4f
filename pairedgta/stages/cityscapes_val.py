"""Cityscapes-val check, per model: the check the paper's authors ran to catch a wrong preprocessing, on the real
Cityscapes split (scope "check", run alone: `+experiment=cityscapes_val_check`). What is scored is the run's task's
work (segmentation's mIoU against the published one in pairedgta/evaluation/cityscapes_val.py, detection's box AP in
pairedgta/detection/cityscapes_val.py); this module opens the split, keys and caches each model's entry and records
it in its nested MLflow run."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from pairedgta.datasets import image_notes, open_dataset
from pairedgta.datasets.cityscapes import CityscapesSplit
from pairedgta.errors import ConfigError
from pairedgta.stages.common import Check, Context, run_checks

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

STAGE = "cityscapes_val"


@dataclass
class CityscapesVal(Check):
    """The Cityscapes check (pairedgta.stages.common.Stage) of one model; outside the paired graph."""

    name: str = STAGE


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step (scope "check", run alone; `p` holds no dataset): every evaluated model on the Cityscapes
    split, each in a nested MLflow run, its result in the run's summary."""
    dataset = open_dataset(ctx.cfg["dataset"])
    if not isinstance(dataset, CityscapesSplit):
        raise ConfigError(f"stages=[{STAGE}] checks models on Cityscapes; set dataset=cityscapes dataset.root=PATH")
    dataset_key = f"cityscapes:{dataset.fingerprint()}"
    state.recorder.tags({"dataset": dataset.name, "dataset_key": dataset_key, "split": dataset.split,
                         "task": ctx.run.task})
    with image_notes(f"dataset {dataset.name}"):  # a blank or converted image: one warning, after every model
        run_checks(ctx, state, CityscapesVal, dataset, dataset_key, params={"dataset": ctx.cfg["dataset"]})
