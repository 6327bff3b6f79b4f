"""What a stage's cache entry and its context are, below the stages: a task's work (pairedgta/evaluation/,
pairedgta/detection/, a new task's module) reads and writes entries and identifies models without importing
pairedgta.stages, which orchestrates it (pairedgta/stages/common.py runs the cache)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pairedgta.cache import StageCache
from pairedgta.conditions import ConditionGrid
from pairedgta.models.runtime import SPEED_ONLY_KEYS
from pairedgta.schema import RunConfig


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


class ModelEntry(StageResult):
    """One model's entry (an evaluation, of any task): the model's composed config as this run built it, or, for an
    entry collected from the cache, rebuilt from its manifest (figures re-predict a few groups with it)."""

    def model_config(self) -> dict[str, Any]:
        if "model_config" in self.extra:
            return dict(self.extra["model_config"])
        return model_config_from_hash(self.manifest()["config"]["model"])

    @property
    def model(self) -> str:
        return str(self.model_config()["name"])


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


__all__ = ["Context", "HASH_ONLY_MODEL_KEYS", "ModelEntry", "StageResult", "model_config_from_hash", "model_files",
           "model_hash_config"]
