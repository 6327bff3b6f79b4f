"""What every stage shares: the run context, stage results and cache lookups."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from pairedgta.cache import StageCache, stage_hash
from pairedgta.conditions import ConditionGrid
from pairedgta.errors import ConfigError, PairedGTAError
from pairedgta.models.runtime import SPEED_ONLY_KEYS
from pairedgta.schema import RunConfig

log = logging.getLogger("pairedgta")


@dataclass
class StageResult:
    """A stage's cache entry. Each stage subclasses it with readers of its own files, so no other stage,
    figure or the app needs to know a file name of another stage."""

    stage: str
    key: str
    path: Path
    hit: bool
    extra: dict[str, Any] = field(default_factory=dict)
    complete: bool = True  # False: a shard job's part, while other shards' parts are missing

    def manifest(self) -> dict[str, Any]:
        import json

        from pairedgta.cache import MANIFEST

        return json.loads((self.path / MANIFEST).read_text())


@dataclass
class Context:
    cfg: dict[str, Any]  # the pass's composed config: the chosen group options (renderer, region, dataset ...)
    grid: ConditionGrid
    cache: StageCache
    stages: list[str]
    force: set[str]
    results: dict[str, Any] = field(default_factory=dict)
    run: RunConfig = None  # type: ignore[assignment]  # the same config, typed (pairedgta/schema.py); parsed if not given

    def __post_init__(self) -> None:
        if self.run is None:
            from pairedgta import schema

            self.run = schema.parse(self.cfg)


WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth", ".json", ".onnx", ".pt2", ".data", ".tsv", ".txt")


def model_files(model_cfg: dict[str, Any]) -> list[Path]:
    """Every local file a model's numbers depend on: its weights folder (model.path, a folder or one file: an ONNX
    graph and its external data, a .pt2, an HF or SMP folder), model.checkpoint_path, a label TSV (model.labels) and
    the module of a `model=python` factory (model.target, found without importing it)."""
    from pairedgta.models.hf_common import resolve_checkpoint_path

    files: list[Path] = []
    path = model_cfg.get("path")
    if path:
        root = resolve_checkpoint_path(path)
        if root.is_dir():
            files += sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in WEIGHT_SUFFIXES)
        elif root.is_file():
            files.append(root)
            if root.suffix == ".onnx":  # external data lies beside the graph (pairedgta/models/sources/onnx.py)
                files += sorted(p for p in root.parent.iterdir() if p.is_file() and p != root
                                and p.name.startswith(root.stem) and p.suffix in (".data", ".bin", ".weight"))
    ckpt = model_cfg.get("checkpoint_path")
    if ckpt:  # a pkg:// file is the zoo's (package or companion): retrained weights must not be a cache hit either
        if (ckpt := resolve_checkpoint_path(ckpt)).is_file():
            files.append(ckpt)
    labels = model_cfg.get("labels")
    if isinstance(labels, str) and ("/" in labels or labels.endswith((".tsv", ".txt"))):
        if (table := Path(labels).expanduser()).is_file():
            files.append(table)
    target = model_cfg.get("target")
    if isinstance(target, str) and ":" in target:
        import importlib.util

        try:
            spec = importlib.util.find_spec(target.split(":")[0])
        except (ImportError, ValueError):
            spec = None
        if spec is not None and spec.origin and Path(spec.origin).is_file():
            files.append(Path(spec.origin))
    return files


def _weights_fingerprint(model_cfg: dict[str, Any]) -> str | None:
    """Content hash of every local file of the model (`model_files`): replacing a file behind an unchanged path must
    not be a cache hit, and restoring it is one again. Hub ids are pinned by name (and model.revision) only."""
    import hashlib

    files = model_files(model_cfg)
    if not files:
        return None
    from pairedgta.filehash import default

    memo = default()  # large weights are read once, then only when their size or mtime changes
    h = hashlib.sha256()
    for f in files:
        h.update(f"{f.name}|{memo.sha256(f)}\n".encode())
    return h.hexdigest()[:16]


HASH_ONLY_MODEL_KEYS = ("weights_sha256",)  # identify the weights in a hash; never a model option


def model_config_from_hash(hashed: dict[str, Any]) -> dict[str, Any]:
    """The buildable model config back from the one a stage hashed (runtime keys take their defaults)."""
    return {k: v for k, v in hashed.items() if k not in HASH_ONLY_MODEL_KEYS}


def model_hash_config(model_cfg: dict[str, Any]) -> dict[str, Any]:
    cfg = {k: v for k, v in model_cfg.items() if k not in SPEED_ONLY_KEYS}
    fingerprint = _weights_fingerprint(model_cfg)
    if fingerprint:
        cfg[HASH_ONLY_MODEL_KEYS[0]] = fingerprint
    return cfg


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
