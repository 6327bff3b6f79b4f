"""Renderer backends, one module each, built through one registry from the `renderer` config."""
from __future__ import annotations

from typing import Any, Mapping

from pairedgta.registry import Registry
from pairedgta.render.base import Renderer, RenderResult

# modules import lazily so bpy / pyzmq are only needed by the backend that uses them
RENDERERS = Registry("renderer", "renderer.backend")
RENDERERS.register("synthetic", "pairedgta.render.synthetic:SyntheticRenderer")
RENDERERS.register("blender", "pairedgta.render.blender:BlenderRenderer")
RENDERERS.register("deepgtav", "pairedgta.render.deepgtav:DeepGTAVRenderer")


def build_renderer(cfg: Mapping[str, Any]) -> Renderer:
    cfg = dict(cfg)
    return RENDERERS.build(cfg.pop("backend", None), cfg, where="renderer")


__all__ = ["Renderer", "RenderResult", "build_renderer", "RENDERERS"]
