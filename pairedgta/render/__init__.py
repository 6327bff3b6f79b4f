"""Renderer backends, one module each; `build_renderer` picks one from the `renderer` config."""
from __future__ import annotations

import importlib
from typing import Any, Mapping

from pairedgta.errors import ConfigError
from pairedgta.render.base import Renderer, RenderResult

# backend name -> "module:Class"; modules import lazily so bpy/pyzmq are only needed when used
BACKENDS: dict[str, str] = {
    "synthetic": "pairedgta.render.synthetic:SyntheticRenderer",
    "blender": "pairedgta.render.blender:BlenderRenderer",
    "deepgtav": "pairedgta.render.deepgtav:DeepGTAVRenderer",
}


def register_backend(name: str, target: str) -> None:
    BACKENDS[name] = target


def build_renderer(cfg: Mapping[str, Any]) -> Renderer:
    cfg = dict(cfg)
    backend = cfg.pop("backend", None)
    if backend not in BACKENDS:
        raise ConfigError(
            f"renderer.backend={backend!r} is unknown; choose one of {', '.join(sorted(BACKENDS))}"
        )
    module_name, cls_name = BACKENDS[backend].split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    return cls(**cfg)


__all__ = ["Renderer", "RenderResult", "build_renderer", "register_backend", "BACKENDS"]
