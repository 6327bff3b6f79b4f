"""Shader-node helpers and the condition knobs.

Every condition-dependent value of a material, the sky or the fog compositor is a named knob (a
value or colour node, or a compositor socket) registered here when the node trees are built, so that
a condition sets values only and never rebuilds a node tree (Cycles' shaders stay synced).
"""
from __future__ import annotations

from typing import Any

import numpy as np


class Knobs:
    """Named sockets that a condition sets; one name may drive several sockets (one per node tree)."""

    def __init__(self) -> None:
        self._sockets: dict[str, list[Any]] = {}

    def set(self, name: str, value) -> None:
        for socket in self._sockets.get(name, []):
            if isinstance(value, (np.ndarray, tuple, list)):
                socket.default_value = (*[float(v) for v in value], 1.0)
            else:
                socket.default_value = float(value)

    def get(self, name: str) -> float:
        return self._sockets[name][0].default_value

    def add(self, name: str, socket) -> None:
        """Register an existing socket (compositor inputs, which have no value node)."""
        self._sockets.setdefault(name, []).append(socket)

    def value(self, nt, name: str, default: float):
        node = nt.nodes.new("ShaderNodeValue")
        node.outputs[0].default_value = default
        self.add(name, node.outputs[0])
        return node.outputs[0]

    def colour(self, nt, name: str, default):
        node = nt.nodes.new("ShaderNodeRGB")
        node.outputs[0].default_value = (*default, 1.0)
        self.add(name, node.outputs[0])
        return node.outputs[0]


def set_input(nt, socket, value) -> None:
    """Link an output socket, or set a constant (an RGB triple gets alpha 1)."""
    if hasattr(value, "is_output"):
        nt.links.new(value, socket)
    elif isinstance(value, (tuple, list)) and len(value) == 3:
        socket.default_value = (*value, 1.0)
    else:
        socket.default_value = value


def math_node(nt, op: str, a, b=None, clamp: bool = False):
    node = nt.nodes.new("ShaderNodeMath")
    node.operation = op
    node.use_clamp = clamp
    set_input(nt, node.inputs[0], a)
    if b is not None:
        set_input(nt, node.inputs[1], b)
    return node.outputs[0]


def mix_node(nt, kind: str, fac, a, b, blend: str = "MIX"):
    node = nt.nodes.new("ShaderNodeMix")
    node.data_type = kind
    if kind == "RGBA":
        node.blend_type = blend
    suffix = {"RGBA": "Color", "FLOAT": "Float", "VECTOR": "Vector"}[kind]
    ins = {s.identifier: s for s in node.inputs}
    set_input(nt, ins["Factor_Float"], fac)
    set_input(nt, ins[f"A_{suffix}"], a)
    set_input(nt, ins[f"B_{suffix}"], b)
    return {s.identifier: s for s in node.outputs}[f"Result_{suffix}"]


def vertex_colour(nt, output: str = "Color"):
    """The mesh's "col" attribute: each primitive's colour row (r, g, b, a); windows keep their lit-at-night draw in a."""
    node = nt.nodes.new("ShaderNodeAttribute")
    node.attribute_name = "col"
    return node.outputs[output]


def grey_vector(nt, value):
    comb = nt.nodes.new("ShaderNodeCombineXYZ")
    for axis in "XYZ":
        nt.links.new(value, comb.inputs[axis])
    return comb.outputs[0]


__all__ = ["Knobs", "grey_vector", "math_node", "mix_node", "set_input", "vertex_colour"]
