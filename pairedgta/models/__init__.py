"""Model zoo: one registry of families, configs in the `model` config group.

`build_segmenter(name_or_config, device=..., **overrides)` reads the model's YAML through the config
search path (or takes an already composed config), applies overrides and calls the family's builder
with the config's keys as keyword arguments; architecture modules know nothing about Hydra.

Inside `run_models()` (one run of the app) `shared_segmenter` builds each distinct model config once:
pseudo-labelling, evaluation and the qualitative figure use the same loaded model."""
from __future__ import annotations

import contextlib
import json
import logging
from typing import Any, Iterator, Mapping

from pairedgta.configs import group_option, group_options
from pairedgta.errors import ConfigError
from pairedgta.models.base import Segmenter, resolve_device
from pairedgta.registry import Registry

FAMILIES = Registry("model family", "model.family")
FAMILIES.register("segformer", "pairedgta.models.segformer:build")
FAMILIES.register("mask2former", "pairedgta.models.mask2former:build")
FAMILIES.register("deeplabv3plus", "pairedgta.models.deeplabv3plus:build")
FAMILIES.register("pidnet", "pairedgta.models.pidnet:build")
FAMILIES.register("ddrnet", "pairedgta.models.ddrnet:build")
RUNTIME_KEYS = ("device",)  # how to run, given by the run's top-level `device`, never by a model YAML
log = logging.getLogger("pairedgta.models")
_RUN_CACHE: dict[str, Segmenter] | None = None  # per run, see run_models()


def available_models() -> list[str]:
    return group_options("model")


def model_config(name: str, **overrides: Any) -> dict[str, Any]:
    """pairedgta/conf/model/<name>.yaml (through the config search path) with `overrides` applied."""
    cfg = group_option("model", name)
    cfg.update(overrides)
    return cfg


def check_model_config(cfg: Mapping[str, Any], where: str = "model") -> None:
    """Unknown keys of a model config are the same one-line error before anything is built."""
    from pairedgta.registry import check_keys

    examples = {"mean": "[0.485,0.456,0.406]", "std": "[0.229,0.224,0.225]"}
    for key, example in examples.items():  # per RGB channel: a wrong length is a reshape traceback in the model
        value = cfg.get(key)
        if value is None:
            continue
        numbers = isinstance(value, (list, tuple)) and len(value) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        if not numbers or (key == "std" and min(value) <= 0):
            need = "3 numbers > 0" if key == "std" else "3 numbers"
            raise ConfigError(f"{where} ({cfg.get('name')}): {key}={list(value) if isinstance(value, (list, tuple)) else value!r} "
                              f"must be {need}, one per RGB channel, e.g. {key}={example}")
    family = cfg.get("family")
    keys = FAMILIES.declared_keys(family)  # from the source: no torch/transformers import for a check
    check_keys(keys if keys is not None else FAMILIES.resolve(family), cfg, f"{where} ({cfg.get('name')})",
               runtime=RUNTIME_KEYS)


def build_segmenter(model: str | Mapping[str, Any], device: str | None = None, **overrides: Any) -> Segmenter:
    """Build a segmenter by model name or from a composed model config mapping."""
    cfg = dict(model) if isinstance(model, Mapping) else model_config(str(model))
    cfg.update(overrides)
    device = device or cfg.pop("device", None) or "cpu"
    return FAMILIES.build(cfg.get("family"), cfg, where=f"model ({cfg.get('name')})", device=device)


def _cache_key(cfg: Mapping[str, Any], device: str | None) -> str:
    return json.dumps({"config": dict(cfg), "device": device}, sort_keys=True, default=str)


@contextlib.contextmanager
def run_models() -> Iterator[dict[str, Segmenter]]:
    """The scope of one run: `shared_segmenter` keeps every model it builds until the scope ends
    (nested scopes share the outer one). Outside a scope it builds a fresh model each call."""
    global _RUN_CACHE
    if _RUN_CACHE is not None:
        yield _RUN_CACHE
        return
    _RUN_CACHE = {}
    try:
        yield _RUN_CACHE
    finally:
        _RUN_CACHE = None


def shared_segmenter(model: Mapping[str, Any], device: str | None = None) -> Segmenter:
    """`build_segmenter(model, device)`, built once per run for the same composed config and device."""
    if _RUN_CACHE is None:
        return build_segmenter(model, device=device)
    key = _cache_key(model, device)
    if key not in _RUN_CACHE:
        _RUN_CACHE[key] = build_segmenter(model, device=device)
    else:
        log.debug("model %s: reused within this run", model.get("name"))
    return _RUN_CACHE[key]


__all__ = ["Segmenter", "build_segmenter", "shared_segmenter", "run_models", "model_config", "check_model_config", "available_models",
           "resolve_device", "FAMILIES", "RUNTIME_KEYS"]
