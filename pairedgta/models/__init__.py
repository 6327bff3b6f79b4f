"""Model zoo: one registry of families, one factory, configs in conf/model/<name>.yaml.

`build_segmenter(name, **overrides)` reads the model's YAML, applies overrides and hands the result to
the family's builder; architecture modules know nothing about Hydra.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Callable, Mapping

from omegaconf import OmegaConf

from pairedgta.errors import ConfigError
from pairedgta.models.base import Segmenter, resolve_device

CONF_DIR = Path(__file__).resolve().parents[2] / "conf" / "model"

# family -> "module:builder"; builder(cfg: dict, device, **runtime) -> Segmenter
FAMILIES: dict[str, str] = {
    "segformer": "pairedgta.models.segformer:build",
    "mask2former": "pairedgta.models.mask2former:build",
    "deeplabv3plus": "pairedgta.models.deeplabv3plus:build",
    "pidnet": "pairedgta.models.pidnet:build",
    "ddrnet": "pairedgta.models.ddrnet:build",
}


def available_models() -> list[str]:
    return sorted(p.stem for p in CONF_DIR.glob("*.yaml"))


def model_config(name: str, **overrides: Any) -> dict[str, Any]:
    path = CONF_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(
            f"unknown model '{name}' (no {path}); choose one of: {', '.join(available_models())}"
        )
    cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    assert isinstance(cfg, dict)
    cfg.update({k: v for k, v in overrides.items()})
    return cfg


def build_segmenter(name: str | Mapping[str, Any], **overrides: Any) -> Segmenter:
    """Build a segmenter by model name (or from an already composed model config mapping)."""
    if isinstance(name, Mapping):
        cfg = dict(name)
        cfg.update(overrides)
    else:
        cfg = model_config(name, **overrides)
    family = cfg.get("family")
    if family not in FAMILIES:
        raise ConfigError(
            f"model '{cfg.get('name')}': family {family!r} is unknown; known: {', '.join(sorted(FAMILIES))}"
        )
    module_name, fn_name = FAMILIES[family].split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise ConfigError(f"model family '{family}' is not available here ({exc})") from None
    builder: Callable[..., Segmenter] = getattr(module, fn_name)
    return builder(cfg)


__all__ = ["Segmenter", "build_segmenter", "model_config", "available_models", "resolve_device", "FAMILIES"]
