"""What every stage shares: the runner that hashes, shards and reads the cache (the entry and context types are
pairedgta/entries.py's, below the stages, so a task's work can use them)."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from pairedgta.cache import stage_hash
from pairedgta.entries import (  # noqa: F401 - the stages' names for them
    HASH_ONLY_MODEL_KEYS,
    Context,
    StageResult,
    model_config_from_hash,
    model_files,
    model_hash_config,
)
from pairedgta.errors import ConfigError, PairedGTAError

log = logging.getLogger("pairedgta")


class Stage(Protocol):
    """One cacheable unit of a stage's work (the dataset, the pseudo-labels, one model's evaluation, the figures):
    what `run_cached` needs to hash it, find it, shard it and build it. Every stage module implements it, so the
    runner below is the only place that hashes, shards and reads the cache."""

    name: str                       # the stage, also its folder in the cache
    version: str                    # bumped when the stage's outputs change for the same config
    label: str                      # the unit in log lines, e.g. "[demo_segformer]"
    resumable: bool                 # builds in a work folder that survives a crash (and the shards' work)
    result_cls: type[StageResult]   # the typed reader of its entry

    def hash_config(self) -> dict[str, Any]:
        """What of the config decides the outputs (never what decides only speed or where it runs)."""

    def inputs(self) -> dict[str, str]:
        """The upstream entries it reads: name -> key."""

    def build(self, out: Path, key: str) -> dict[str, Any] | None:
        """Write the entry `key` into `out` (a temporary folder the runner swaps in when complete)."""

    def shards(self) -> tuple[int, int]:
        """(num_shards, shard): shard i of N does items i, i+N, ...; (1, 0) when not split over jobs."""

    def build_shard(self, key: str) -> Path | None:
        """This shard's part of the work, stored where the unsharded build finds it; the folder that holds the
        parts while other shards' are missing, None when every part is there (then the runner builds)."""


class Unsharded:
    """The two Stage members of a stage that is never split over jobs."""

    def shards(self) -> tuple[int, int]:
        return 1, 0

    def build_shard(self, key: str) -> Path | None:
        raise AssertionError("run_cached asks for shards only where shards() says N > 1")


def _hit(ctx: Context, stage: str, key: str, label: str, what: str, result_cls: type[StageResult]) -> StageResult:
    log.info("%s: cache hit %s (skipped; force=[%s] recomputes)", what, ctx.cache.path(stage, key), stage)
    ctx.cache.use(stage, key)
    ctx.results.setdefault("stages", []).append({"stage": stage, "label": label, "key": key, "hit": True})
    return result_cls(stage, key, ctx.cache.path(stage, key), hit=True)


def _not_cached(ctx: Context, stage: str, what: str, key: str, problem: str | None) -> PairedGTAError:
    again = f"e.g. stages=[{stage},{','.join(ctx.stages)}]"
    if problem not in (None, "missing"):
        return PairedGTAError(f"{what}: the cached output {ctx.cache.path(stage, key)} is damaged ({problem}); "
                              f"recompute it, {again}")
    return PairedGTAError(f"{what}: no cached output for this configuration ({ctx.cache.path(stage, key)}); "
                          f"run it first, {again}")


def stage_key(stage: Stage) -> str:
    return stage_hash(stage.name, stage.version, stage.hash_config(), stage.inputs())


def run_cached(ctx: Context, stage: Stage) -> StageResult:
    """Hit -> skip and say so; miss, damaged entry or force -> build beside it and swap it in on success
    (a failed recompute leaves the previous result). A stage not listed in `stages` must already be
    cached: then the error names the stage to run. A shard job (stage.shards() = (N > 1, i)) does its part
    and returns an incomplete result until every shard's part is there; then the entry is built from them."""
    name, label = stage.name, stage.label
    config, inputs = stage.hash_config(), stage.inputs()
    key = stage_hash(name, stage.version, config, inputs)
    what = f"{name}{' ' + label if label else ''}"
    num, _ = stage.shards()
    if num > 1 and not ctx.cache.is_hit(name, key):
        if name in ctx.force:
            raise ConfigError(f"force=[{name}] with {name}.shard set would discard other shards' work; "
                              f"force the unsharded run (no {name}.shard/num_shards) instead")
        if name not in ctx.stages:
            raise _not_cached(ctx, name, what, key, None)
        work = stage.build_shard(key)
        if work is not None:
            return stage.result_cls(name, key, work, hit=False, complete=False)
    # force= recomputes once per run: a later pass reaching the same hash reuses this run's result
    forced = name in ctx.force and (name, key) not in ctx.cache.built
    ctx.cache.sweep_once()
    problem = None if forced else ctx.cache.problem(name, key)
    if not forced and problem is None:
        return _hit(ctx, name, key, label, what, stage.result_cls)
    if name not in ctx.stages:
        raise _not_cached(ctx, name, what, key, problem)
    with ctx.cache.lock(name, key):
        if not forced:
            problem = ctx.cache.problem(name, key)
            if problem is None:  # another job finished it while we waited
                return _hit(ctx, name, key, label, what, stage.result_cls)
            if problem != "missing":
                log.warning("%s: cached output %s is damaged (%s); rebuilding it", what, ctx.cache.path(name, key), problem)
        elif stage.resumable:
            import shutil

            shutil.rmtree(ctx.cache.partial_path(name, key), ignore_errors=True)  # forced: start afresh
        log.info("%s: computing -> %s%s", what, ctx.cache.path(name, key),
                 " (the previous result stays until this one is complete)" if forced else "")
        manifest = {"version": stage.version, "config": config, "inputs": inputs}
        work_dir = ctx.cache.partial_path(name, key) if stage.resumable else None
        with ctx.cache.build(name, key, manifest, work_dir=work_dir, replace=forced) as tmp:
            extra = stage.build(tmp, key) or {}
    ctx.cache.use(name, key)
    ctx.results.setdefault("stages", []).append({"stage": name, "label": label, "key": key, "hit": False})
    return stage.result_cls(name, key, ctx.cache.path(name, key), hit=False, extra=extra)


@dataclass
class TaskStage:
    """A stage whose work is the run's task's (pairedgta/work.py): one model's entry on one dataset. The stage keys,
    caches and records it; `work` (the task's, unless given) computes it. Each such stage subclasses it with its
    `name`; the work declares the entry's `version(model_cfg)` and `result_cls`."""

    ctx: Context
    dataset: Any
    dataset_key: str
    model_cfg: dict[str, Any]
    work: Any = field(default=None, kw_only=True)
    name: str = field(default="", kw_only=True)
    version: str = field(default="", kw_only=True)  # the task's work declares it
    resumable: bool = field(default=False, kw_only=True)
    result_cls: type[StageResult] = field(default=StageResult, kw_only=True)

    def __post_init__(self) -> None:
        if self.work is None:
            from pairedgta import tasks

            self.work = tasks.get(self.ctx.run.task).work_for(self.name)
        self.version, self.result_cls = self.work.version(self.model_cfg), self.work.result_cls

    @property
    def label(self) -> str:
        return f"[{self.model_cfg['name']}]"

    def inputs(self) -> dict[str, str]:
        return {"dataset": self.dataset_key}


@dataclass
class Check(Unsharded, TaskStage):
    """A check of the models themselves (scope "check"), its work a pairedgta.work.CheckWork."""

    def hash_config(self) -> dict[str, Any]:
        return self.work.hash_config(self.ctx, self.dataset, self.model_cfg)

    def build(self, out: Path, key: str) -> dict[str, Any]:
        from pairedgta.models.runtime import torch_threads

        with torch_threads(self.ctx.run.threads):
            return self.work.compute(self.ctx, self.dataset, self.dataset_key, self.model_cfg, out)


def run_checks(ctx: Context, state: Any, stage: type[Check], dataset: Any, dataset_key: str,
               params: dict[str, Any] | None = None) -> None:
    """Every evaluated model through the check `stage`, each in a nested MLflow run: its entry (a check of its own:
    it always may compute), the lines its work says, its metrics and files; the run's summary gets
    `<stage>`: {model: ...} and `evaluate`: {model: path}."""
    import dataclasses

    from pairedgta.tracking import bundle, dataset_label, run_name

    name = stage.__dataclass_fields__["name"].default
    own = dataclasses.replace(ctx, stages=[*ctx.stages, name])
    tracker, summary = state.recorder, state.summary
    summary["dataset"] = str(dataset.root)
    summary[name] = {}
    for model_cfg in state.models.evaluated:
        model = model_cfg["name"]
        with tracker.run(run_name(tracker.experiment, [model], [dataset_label(dataset.name, dataset_key)]), nested=True):
            check = stage(own, dataset, dataset_key, model_cfg)
            result = run_cached(own, check)
            metrics, entry = check.work.report(result, model_cfg)
            tracker.params({"model": model_cfg, **(params or {})})
            tracker.tags({f"{name}_hash": result.key, "cache_hit": str(result.hit), "model": model})
            tracker.metrics(metrics)
            tracker.dataset(dataset.name, dataset.root, dataset_key.split(":", 1)[-1],
                            {"split": dataset.split} if hasattr(dataset, "split") else {"dataset_key": dataset_key})
            tracker.config({**{k: v for k, v in ctx.cfg.items() if k not in ("hydra", "variants")}, "model": model_cfg})
            tracker.stage_files(bundle(name, result.key), result.hit, check.work.files(result), name)
        summary["evaluate"][model] = str(result.path)
        summary[name][model] = entry
