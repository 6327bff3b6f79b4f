"""Model zoo: one registry of families, configs in the `model` config group.

`build_model(name_or_config, device=..., **overrides)` reads the model's YAML through the config
search path (or takes an already composed config), applies overrides, parses the options every family
shares once (`RuntimeOptions`: device, batch_size, amp, channels_last, compile) and calls the family's
builder with the remaining keys as keyword arguments plus `runtime`; as in timm, a family declares only
its own arguments, with their defaults in its builder's signature. The in-project families share one
builder (pairedgta/models/checkpoint.py: build_inproject, timm's build_model_with_cfg): such a family's
module declares only its `architecture` arguments (and its PRETRAINED defaults of the shared input options),
and one registry line below names it. Architecture modules know nothing about Hydra.

It builds either kind a config names (`model_kind`): a segmenter (label maps) or a detector (boxes), typed
`Model`. Inside `run_models()` (one run of the app) `shared_model` builds each distinct model config once:
pseudo-labelling, evaluation and the qualitative figure use the same loaded model."""
from __future__ import annotations

import contextlib
import json
import logging
from typing import Any, Iterator, Mapping

from pairedgta.configs import group_option, group_options
from pairedgta.models.contract import CONTRACT_OPTIONS, DETECTOR_OPTIONS, check_contract
from pairedgta.errors import ConfigError
from pairedgta.models.base import BoxModel, Model, Segmenter, resolve_device
from pairedgta.models.runtime import MODEL_KEYS as RUNTIME_OPTION_KEYS
from pairedgta.models.runtime import RuntimeOptions, runtime_defaults, split_runtime
from pairedgta.registry import Registry, accepted_keys

# The input options of the in-project families (pairedgta/models/checkpoint.py: build_inproject); like the
# runtime options, every config of such a family has them (its YAML only where it differs from the default).
IN_PROJECT_OPTIONS = ("random_init", "init_seed", "mean", "std", "pad_multiple", "upsample_align_corners")
# An in-project family: its module's `architecture`, built through the shared builder (pairedgta/registry.py: via).
IN_PROJECT = {"via": "pairedgta.models.checkpoint:build_inproject", "filled": IN_PROJECT_OPTIONS}
FAMILIES = Registry("model family", "model.family")
FAMILIES.register("segformer", "pairedgta.models.segformer:build")
FAMILIES.register("mask2former", "pairedgta.models.mask2former:build")
FAMILIES.register("deeplabv3plus", "pairedgta.models.deeplabv3plus:architecture", **IN_PROJECT)
FAMILIES.register("pidnet", "pairedgta.models.pidnet:architecture", **IN_PROJECT)
FAMILIES.register("ddrnet", "pairedgta.models.ddrnet:architecture", **IN_PROJECT)
# Model sources: a researcher's own model in one format (`model=<source>`), loaded by the source's module and run
# under the one input/output contract and label map of pairedgta/models/contract.py (its `build_source`).
SOURCE = {"via": "pairedgta.models.contract:build_source", "filled": CONTRACT_OPTIONS, "source": True}
# Under a task of detectors the same `model=<source>` loads a detector: its twin family `det_<source>`
# (pairedgta/models/sources/det_*.py), under the detectors' contract, layout and label space
# (pairedgta/models/detector_contract.py, detector_layouts.py, detector_labels.py).
FAMILIES.register("hf", "pairedgta.models.sources.hf:load", **SOURCE, detector="det_hf")
FAMILIES.register("torchvision", "pairedgta.models.sources.torchvision:load", **SOURCE, detector="det_torchvision")
FAMILIES.register("smp", "pairedgta.models.sources.smp:load", **SOURCE)
FAMILIES.register("export", "pairedgta.models.sources.export:load", **SOURCE, detector="det_export")
FAMILIES.register("onnx", "pairedgta.models.sources.onnx:load", **SOURCE, detector="det_onnx")
FAMILIES.register("python", "pairedgta.models.sources.python:load", **SOURCE, detector="det_python")
DETECTOR_SOURCE = {"via": "pairedgta.models.detector_contract:build_detector_source", "kind": "detector", "source": True,
                   "check": "pairedgta.models.detector_contract:check_contract", "filled": DETECTOR_OPTIONS}
for _source in ("hf", "torchvision", "export", "onnx", "python"):
    FAMILIES.register(f"det_{_source}", f"pairedgta.models.sources.det_{_source}:load", **DETECTOR_SOURCE)
# Detectors (task=detection): torchvision's detection heads on a small trunk, one builder for what every detector has
# (pairedgta/models/detectors.py: build_detector); `kind` says which task's stages can run them (pairedgta/tasks.py).
DETECTOR = {"via": "pairedgta.models.detectors:build_detector", "kind": "detector",
            "check": "pairedgta.models.detectors:check_options",
            "filled": ("random_init", "init_seed", "score_threshold", "min_size", "max_size")}
FAMILIES.register("fcos", "pairedgta.models.detectors:fcos", **DETECTOR)
FAMILIES.register("retinanet", "pairedgta.models.detectors:retinanet", **DETECTOR)
FAMILIES.register("fasterrcnn", "pairedgta.models.detectors:fasterrcnn", **DETECTOR)
DEFAULT_KIND = "segmenter"  # a family that declares no `kind` builds label maps (the paper's models)
RUNTIME_KEYS = ("device",)  # how to run, given by the run's top-level `device`, never by a model YAML
log = logging.getLogger("pairedgta.models")
_RUN_CACHE: dict[str, Model] | None = None  # per run, see run_models()


def model_kind(cfg: Mapping[str, Any]) -> str:
    """What a model config builds: "detector" (boxes) or "segmenter" (label maps); read without building it."""
    family = cfg.get("family")
    return str(FAMILIES.meta(family).get("kind", DEFAULT_KIND)) if isinstance(family, str) and family in FAMILIES \
        else DEFAULT_KIND


def for_kind(cfg: Mapping[str, Any], kind: str) -> dict[str, Any]:
    """A source model's config for the run's task: `model=onnx` under a task of detectors is the detector source
    `det_onnx` (its registry line names its twin of that kind: `detector="det_onnx"`); anything else as it is."""
    out = dict(cfg)
    family = out.get("family")
    if isinstance(family, str) and family in FAMILIES and model_kind(out) != kind:
        twin = FAMILIES.meta(family).get(kind)
        if twin:
            out["family"] = twin
    return out


def available_models() -> list[str]:
    return group_options("model")


def model_config(name: str, **overrides: Any) -> dict[str, Any]:
    """pairedgta/conf/model/<name>.yaml (through the config search path) with `overrides` applied and the
    shared options' defaults filled in (`with_defaults`)."""
    cfg = group_option("model", name)
    cfg.update(overrides)
    return with_defaults(cfg)


def with_defaults(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The model config as the stages hash it: a runtime option, or an input option of an in-project family,
    that the config leaves out takes its one default (RuntimeOptions; the family's declared defaults, read from
    the sources without importing torch: pairedgta/registry.py). So a YAML that omits a default hashes exactly
    as one that spells it out."""
    out = dict(cfg)
    if not out.get("name") and is_source(out):
        out["name"] = default_name(out)
    defaults = runtime_defaults()
    family = out.get("family")
    if isinstance(family, str) and family in FAMILIES:  # an unknown one: check_model_config says so
        declared = FAMILIES.declared_defaults(family)
        defaults.update({k: declared[k] for k in FAMILIES.meta(family).get("filled", ())})
    for key, value in defaults.items():
        out.setdefault(key, list(value) if isinstance(value, tuple) else value)
    return out


def default_name(cfg: Mapping[str, Any]) -> str:
    """A source model's name when the config gives none: its file's or folder's name, the hub id's last part, the
    factory's name; so two models of a sweep (`-m model.path=a.onnx,b.onnx`) are told apart in every table."""
    import re
    from pathlib import PurePath

    for key in ("path", "checkpoint_path", "hub_id"):
        if cfg.get(key):
            stem = PurePath(str(cfg[key]).rstrip("/")).name
            stem = stem.split(".")[0] if key != "hub_id" else stem
            if stem:
                return re.sub(r"[^A-Za-z0-9_.-]+", "_", stem)
    if cfg.get("target"):
        return str(cfg["target"]).rsplit(":", 1)[-1]
    return str(cfg.get("family") or "model")


def family_keys(family: str) -> set[str]:
    """The keys a model config of `family` may set: its builder's arguments and the runtime options."""
    keys = FAMILIES.declared_keys(family)  # from the source: no torch/transformers import for a check
    keys = keys if keys is not None else accepted_keys(FAMILIES.resolve(family)) or set()
    return (keys - {"runtime"}) | set(RUNTIME_OPTION_KEYS)


def is_source(cfg: Mapping[str, Any]) -> bool:
    """Whether the config is a researcher's model through a model source (not a family of the zoo)."""
    family = cfg.get("family")
    return isinstance(family, str) and family in FAMILIES and bool(FAMILIES.meta(family).get("source"))


def check_model_config(cfg: Mapping[str, Any], where: str = "model") -> None:
    """Unknown keys of a model config are the same one-line error before anything is built."""
    from pairedgta.registry import check_keys

    if is_source(cfg):
        twin = FAMILIES.meta(cfg["family"]).get("detector")
        own = family_keys(cfg["family"]) | set(RUNTIME_KEYS)
        detector_only = sorted(k for k in cfg if k not in own and twin and k in family_keys(twin))
        if detector_only:  # e.g. model.layout on a segmentation run: the user meant the detection task
            raise ConfigError(f"{where} ({cfg.get('name')}): {', '.join(f'model.{k}' for k in detector_only)} "
                              f"configure(s) a detector; run model={cfg['family']} with task=detection, or leave "
                              f"{'it' if len(detector_only) == 1 else 'them'} out for segmentation")
        check_keys(family_keys(cfg.get("family")), cfg, f"{where} ({cfg.get('name')})", runtime=RUNTIME_KEYS)
        if not _family_check(cfg, where):  # a detector source's contract check, by its registry line
            check_contract(cfg, f"{where} ({cfg.get('name')})")
        RuntimeOptions.from_config(cfg)
        return
    if _family_check(cfg, where):  # a family of its own kind (the detectors): its registry line names its check
        check_keys(family_keys(cfg.get("family")), cfg, f"{where} ({cfg.get('name')})", runtime=RUNTIME_KEYS)
        RuntimeOptions.from_config(cfg)
        return
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
    check_keys(family_keys(cfg.get("family")), cfg, f"{where} ({cfg.get('name')})", runtime=RUNTIME_KEYS)
    pad = cfg.get("pad_multiple", 1)
    if isinstance(pad, bool) or not isinstance(pad, int) or pad < 1:
        raise ConfigError(f"{where} ({cfg.get('name')}): pad_multiple={pad!r} must be a whole number >= 1, "
                          "e.g. pad_multiple=32")
    if not isinstance(cfg.get("upsample_align_corners", False), bool):
        raise ConfigError(f"{where} ({cfg.get('name')}): upsample_align_corners={cfg['upsample_align_corners']!r} "
                          "must be true or false")
    RuntimeOptions.from_config(cfg)  # a bad model.batch_size / amp is the same one-line error before any stage


def _family_check(cfg: Mapping[str, Any], where: str) -> bool:
    """The check the family's registry line names (`check="module:function"`), run on the config; False if none."""
    family = cfg.get("family")
    check = FAMILIES.meta(family).get("check") if isinstance(family, str) and family in FAMILIES else None
    if not check:
        return False
    import importlib

    module, attr = check.split(":")
    getattr(importlib.import_module(module), attr)(cfg, f"{where} ({cfg.get('name')})")
    return True


def model_keys() -> set[str]:
    """Every key some family's model config may set (the command line's `model.<key>=`)."""
    return set().union(*(family_keys(f) for f in FAMILIES.names()))


def build_model(model: str | Mapping[str, Any], device: str | None = None, **overrides: Any) -> Model:
    """Build a model by name or from a composed model config mapping: a segmenter or a detector, as its family's
    kind says (`model_kind`)."""
    cfg = dict(model) if isinstance(model, Mapping) else model_config(str(model))
    cfg.update(overrides)
    device = device or cfg.pop("device", None) or "cpu"
    check_model_config(cfg)
    own, runtime = split_runtime(cfg, device)
    return FAMILIES.build(cfg.get("family"), own, where=f"model ({cfg.get('name')})", runtime=runtime)


def _cache_key(cfg: Mapping[str, Any], device: str | None) -> str:
    return json.dumps({"config": dict(cfg), "device": device}, sort_keys=True, default=str)


@contextlib.contextmanager
def run_models() -> Iterator[dict[str, Model]]:
    """The scope of one run: `shared_model` keeps every model it builds until the scope ends
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


def shared_model(model: Mapping[str, Any], device: str | None = None) -> Model:
    """`build_model(model, device)`, built once per run for the same composed config and device."""
    if _RUN_CACHE is None:
        return build_model(model, device=device)
    key = _cache_key(model, device)
    if key not in _RUN_CACHE:
        _RUN_CACHE[key] = build_model(model, device=device)
    else:
        log.debug("model %s: reused within this run", model.get("name"))
    return _RUN_CACHE[key]


__all__ = ["BoxModel", "Model", "Segmenter", "RuntimeOptions", "build_model", "with_defaults", "family_keys", "model_keys",
           "shared_model", "run_models", "model_config", "check_model_config", "available_models",
           "resolve_device", "FAMILIES", "RUNTIME_KEYS", "is_source", "model_kind", "for_kind"]
