"""Model check, per model: is it set up right? (scope "check", run alone)

    python -m pairedgta +experiment=model_check model=onnx model.path=net.onnx
    python -m pairedgta +experiment=model_check task=detection model=python model.target=mydets:build

The run's task's work scores the model on a few labelled clean images of the run's dataset, as configured and under
each one-key alternative of its input contract, and says the one-line diagnosis (segmentation: clean GT mIoU,
pairedgta/evaluation/model_check.py; detection: clean GT AP50, pairedgta/detection/model_check.py). No
pseudo-labels, no evaluation of other models. It reads the generated dataset (`needs` generate: rendered here when
not cached yet, the main job's renders), or `dataset.root` when the run names a paired dataset that labels its clean
images. The table is printed and kept in the cache entry as CSV and markdown; the run's summary gets `model_check`."""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from pairedgta.datasets import DATASETS, open_dataset
from pairedgta.errors import ConfigError
from pairedgta.models import is_source
from pairedgta.stages import generate
from pairedgta.stages.common import Check, Context, run_checks

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

STAGE = "model_check"


@dataclasses.dataclass
class ModelCheck(Check):
    """The model check (pairedgta.stages.common.Stage): one model's set-up table on the dataset's clean images."""

    name: str = STAGE


def open_data(ctx: Context, p: PassResult, state: RunState) -> None:
    """The pass's dataset: rendered by the generate stage (cached with the main job's) when `dataset.root` is null,
    else the paired dataset it names."""
    dcfg = dict(ctx.cfg["dataset"])
    if dcfg.get("root") is None:
        own = dataclasses.replace(ctx, stages=[*ctx.stages, generate.Generate.name])  # may render: it is read here
        if generate.will_compute(own):
            from pairedgta.models.availability import check_available

            check_available([m for m in state.models.evaluated if not is_source(m)])  # sources: loaded already
        generate.step(own, p, state)
        if p.dataset is None:  # a generate shard job: the dataset is not complete yet
            raise ConfigError(f"{STAGE}: generate.shard is set; render every shard first, then run the check without it")
        return
    if not DATASETS.meta(dcfg.get("kind")).get("paired"):
        raise ConfigError(f"{STAGE} checks models on a paired dataset's labelled clean images; dataset="
                          f"{dcfg.get('name')} is not one (leave dataset=generated for the embedded town)")
    dataset = open_dataset(dcfg, ctx.grid)
    p.dataset, p.dataset_key = dataset, f"external:{dataset.fingerprint()}"


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step (scope "check", run alone): the dataset, then every evaluated model's check, each in a nested
    MLflow run; the run's summary gets `model_check`: {model: ...}."""
    open_data(ctx, p, state)
    with p.reading():
        run_checks(ctx, state, ModelCheck, p.dataset, str(p.dataset_key))
