"""Renderer backends, one module each, built through one registry from the `renderer` config."""
from __future__ import annotations

from typing import Any, Mapping

from pairedgta.registry import Registry
from pairedgta.render.base import Renderer, RenderResult

# modules import lazily so bpy / pyzmq are only needed by the backend that uses them
RENDERERS = Registry("renderer", "renderer.backend")
RENDERERS.register("synthetic", "pairedgta.render.synthetic:SyntheticRenderer")
# versions: "module:function" returning the versions of the software a backend draws its pixels with (part of
# what a render is: the generate stage hashes them and its manifest records them). None for the synthetic backend
# (this package's own code, versioned by the generate stage's VERSION) and for deepgtav (GTA V runs on another
# machine and its plugin reports no version)
RENDERERS.register("blender", "pairedgta.render.blender:BlenderRenderer",
                   versions="pairedgta.render.blender.cycles:renderer_versions")
RENDERERS.register("deepgtav", "pairedgta.render.deepgtav:DeepGTAVRenderer")


def renderer_versions(backend: str | None) -> dict[str, str]:
    """The backend's own versions by name, e.g. {"blender_version": "5.0.1"}; {} where it has none. Raises
    ConfigError (one line) where the backend's software is not installed."""
    import importlib

    if backend not in RENDERERS:
        return {}
    target = RENDERERS.meta(backend).get("versions")
    if not target:
        return {}
    module, attr = target.split(":")
    return dict(getattr(importlib.import_module(module), attr)())


def build_renderer(cfg: Mapping[str, Any]) -> Renderer:
    cfg = dict(cfg)
    return RENDERERS.build(cfg.pop("backend", None), cfg, where="renderer")


__all__ = ["RENDERERS", "RenderResult", "Renderer", "build_renderer", "renderer_versions"]
