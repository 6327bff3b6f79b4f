"""Model check, per model: is it set up right? Its clean ground-truth mIoU and per-class IoU on a few labelled clean
images of the run's dataset (the embedded town the main job renders, cached with it), under the configured input
contract and label space and under each alternative (pairedgta/evaluation/setup_check.py), printed as a table and
kept in the cache entry as CSV and markdown, with the one-line diagnosis: the alternative that clearly beats the
configured set-up (pairedgta/evaluation/alternatives.py's rule), kept in the entry's summary.json as `better` and
in the run's summary, or the domain gap.

    python -m pairedgta +experiment=model_check model=onnx model.path=net.onnx

A check of the models themselves (scope "check", run alone): no pseudo-labels, no evaluation of other models. It
reads the generated dataset (`needs` generate: rendered here when not cached yet), or `dataset.root` when the run
names a paired dataset that labels its clean images. A zoo model (`model=demo_ddrnet`) gets its configured row only:
its input is the project's own, the alternatives are a model source's contract keys."""
from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pairedgta.datasets import DATASETS, PairedDataset, open_dataset
from pairedgta.errors import ConfigError, DataError
from pairedgta.evaluation import setup_check
from pairedgta.jsonio import write_json
from pairedgta.models import is_source, shared_segmenter
from pairedgta.models.runtime import torch_threads
from pairedgta.stages import generate
from pairedgta.stages.common import Context, StageResult, Unsharded, model_hash_config, run_cached
from pairedgta.tracking import bundle, dataset_label, run_name

if TYPE_CHECKING:  # planning reads this module's spec, not the module
    from pairedgta.stages.planning import PassResult, RunState

log = logging.getLogger("pairedgta.model_check")
STAGE = "model_check"
VERSION = "2"  # 2: `better` and `rule` in summary.json (the trial of pairedgta/evaluation/alternatives.py)
TABLE_CSV, TABLE_MD, SUMMARY = "model_check.csv", "model_check.md", "summary.json"


class ModelCheckResult(StageResult):
    """One model's check entry and the readers of its files."""

    def table(self) -> Any:
        return setup_check.read_table(self.path / TABLE_CSV)

    def markdown(self) -> str:
        return (self.path / TABLE_MD).read_text()

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / SUMMARY).read_text())

    def artifacts(self) -> list[Path]:
        return [self.path / f for f in (TABLE_CSV, TABLE_MD, SUMMARY)]


def compute(ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any], out: Path) -> dict[str, Any]:
    model = str(model_cfg["name"])
    samples = setup_check.clean_samples(dataset)
    if not samples:
        raise DataError(f"{STAGE}: dataset {dataset.name} labels no clean ({dataset.reference}) image; the check needs "
                        "ground truth (the embedded town's renderers write it: leave dataset.root unset)")
    segmenter = shared_segmenter(model_cfg, device=ctx.run.device)
    with torch_threads(ctx.run.threads):
        rows = setup_check.check(segmenter, samples)
    where = setup_check.place(ctx.cfg, dataset_key, dataset.name)
    df = setup_check.table(rows)
    df.to_csv(out / TABLE_CSV, index=False)
    md = setup_check.markdown(df)
    warning = setup_check.diagnose(model, rows, where)
    best = setup_check.best_alternative(rows)
    (out / TABLE_MD).write_text(f"# {STAGE}: {model} on {where}\n\n{md}\n\n{warning or 'Set up right: no warning.'}\n")
    ratio, margin = setup_check.CLEARLY_BETTER
    summary = {"model": model, "dataset": dataset.name, "where": where, "condition": dataset.reference,
               "n_images": len(samples), "clean_miou": rows[0].miou,
               "threshold": setup_check.SETUP_MIN_MIOU, "rule": {"ratio": ratio, "margin": margin},
               "best_alternative": None if best is None else {"setup": best.change, "clean_miou": best.miou},
               "better": setup_check.better_record(rows), "alternatives": len(rows) - 1, "warning": warning}
    write_json(out / SUMMARY, summary)
    return summary


@dataclasses.dataclass
class ModelCheck(Unsharded):
    """The model check (pairedgta.stages.common.Stage): one model's set-up table on the dataset's clean images."""

    ctx: Context
    dataset: PairedDataset
    dataset_key: str
    model_cfg: dict[str, Any]
    name: str = STAGE
    version: str = VERSION
    resumable: bool = False
    result_cls: type[StageResult] = ModelCheckResult

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def hash_config(self) -> dict[str, Any]:
        return {"model": model_hash_config(self.model_cfg), "images": setup_check.CHECK_IMAGES,
                "threshold": setup_check.SETUP_MIN_MIOU, "rule": list(setup_check.CLEARLY_BETTER),
                "check": setup_check.VERSION, "threads": self.ctx.run.threads}

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        return compute(self.ctx, self.dataset, self.dataset_key, self.model_cfg, out)


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


def check_model(ctx: Context, dataset: PairedDataset, dataset_key: str, model_cfg: dict[str, Any]) -> ModelCheckResult:
    own = dataclasses.replace(ctx, stages=[*ctx.stages, STAGE])  # a check of its own: it always may compute
    result = run_cached(own, ModelCheck(own, dataset, dataset_key, model_cfg))
    assert isinstance(result, ModelCheckResult)
    return result


def step(ctx: Context, p: PassResult, state: RunState) -> None:
    """The app's step (scope "check", run alone): the dataset, then every evaluated model's table, printed, with its
    warning line, each model in a nested MLflow run; the run's summary gets `model_check`: {model: ...}."""
    open_data(ctx, p, state)
    dataset, dataset_key = p.dataset, str(p.dataset_key)
    tracker, summary = state.recorder, state.summary
    summary["dataset"] = str(dataset.root)
    summary[STAGE] = {}
    with p.reading():
        for model_cfg in state.models.evaluated:
            name = model_cfg["name"]
            with tracker.run(run_name(tracker.experiment, [name], [dataset_label(dataset.name, dataset_key)]), nested=True):
                result = check_model(ctx, dataset, dataset_key, model_cfg)
                s = result.summary()
                tracker.params({"model": model_cfg})
                tracker.tags({f"{STAGE}_hash": result.key, "cache_hit": str(result.hit), "model": name})
                tracker.metrics({f"{STAGE}/clean_miou": s["clean_miou"]} if s["clean_miou"] is not None else {})
                tracker.stage_files(bundle(STAGE, result.key), result.hit, result.artifacts(), STAGE)
            log.info("%s [%s]: clean GT mIoU on %d %s image(s) of %s, as configured and with each alternative "
                     "(%s):\n%s", STAGE, name, s["n_images"], s["condition"], s["where"], result.path / TABLE_CSV,
                     setup_check.markdown(result.table()))
            if s["warning"]:
                log.warning("%s", s["warning"])
            elif s["clean_miou"] is not None:
                log.info("%s [%s]: clean GT mIoU %.2f >= %.2f, and no alternative clearly beats it: set up right",
                         STAGE, name, s["clean_miou"], setup_check.SETUP_MIN_MIOU)
            summary["evaluate"][name] = str(result.path)
            summary[STAGE][name] = {"clean_miou": s["clean_miou"], "best_alternative": s["best_alternative"],
                                    "better": s.get("better"), "warning": s["warning"], "path": str(result.path)}
