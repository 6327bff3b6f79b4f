"""Materials: the shader-node trees of every surface, built once per session.

Each material's output switches between its real shader and, in the label pass, an emission of the
object's label code and distance (labels.py); wetness, puddles and emission strengths are knobs
(nodes.py) that a condition sets, so no material is rebuilt between conditions.
"""
from __future__ import annotations

from typing import Any

from pairedgta.render.blender.nodes import Knobs, math_node, mix_node, set_input, vertex_colour


def _label_switch(knobs: Knobs, mat, surface) -> None:
    """Material output = the real shader, or in the label pass an emission of the object's
    pass index. A value switch (constant-folded by Cycles) rather than a material override:
    Cycles' persistent shaders miss edits made while an override hides the materials."""
    nt = mat.node_tree
    info = nt.nodes.new("ShaderNodeObjectInfo")
    em = nt.nodes.new("ShaderNodeEmission")
    # red: the pass index; green: the distance from the camera, for the transmittance maps
    # (View Distance, not Ray Length: a ray through the volume box's transparent surface restarts there)
    rgb = nt.nodes.new("ShaderNodeCombineColor")
    nt.links.new(info.outputs["Object Index"], rgb.inputs["Red"])
    nt.links.new(nt.nodes.new("ShaderNodeCameraData").outputs["View Distance"], rgb.inputs["Green"])
    rgb.inputs["Blue"].default_value = 0.0
    nt.links.new(rgb.outputs[0], em.inputs["Color"])
    em.inputs["Strength"].default_value = 1.0
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(knobs.value(nt, "label_mode", 0.0), mix.inputs[0])
    nt.links.new(surface, mix.inputs[1])
    nt.links.new(em.outputs[0], mix.inputs[2])
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(mix.outputs[0], out.inputs["Surface"])
    # emitters are drawn, not sampled as lights: thousands of window quads (or, in the label
    # pass, every triangle) in the light tree would cost more than the lights themselves
    mat.cycles.emission_sampling = "NONE"


def _principled(bpy, knobs: Knobs, name: str, base, roughness, metallic=0.0, specular=0.5, coat=0.0,
                emission=None, emission_strength=None):
    """One Principled-BSDF material; any input may be a constant or a function building its nodes."""
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    nt.nodes.clear()
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    _label_switch(knobs, mat, bsdf.outputs[0])
    base = base(nt) if callable(base) else base
    roughness = roughness(nt) if callable(roughness) else roughness
    set_input(nt, bsdf.inputs["Base Color"], base)
    set_input(nt, bsdf.inputs["Roughness"], roughness)
    set_input(nt, bsdf.inputs["Metallic"], metallic)
    set_input(nt, bsdf.inputs["Specular IOR Level"], specular)
    set_input(nt, bsdf.inputs["Coat Weight"], coat)
    if emission is not None:
        emission = emission(nt) if callable(emission) else emission
        strength = emission_strength(nt) if callable(emission_strength) else emission_strength
        set_input(nt, bsdf.inputs["Emission Color"], emission)
        set_input(nt, bsdf.inputs["Emission Strength"], strength)
    return mat


def build_materials(bpy, knobs: Knobs) -> dict[str, Any]:
    """Every Blender material of the town and the object models (geometry.py maps names to them), built
    once per session: conditions change their knobs (wetness, emission strengths, fog density) only."""
    materials: dict[str, Any] = {}

    def principled(name: str, base, roughness, **params) -> None:
        materials[name] = _principled(bpy, knobs, name, base, roughness, **params)

    def pavement_parts(nt):
        col = vertex_colour(nt)
        pos = nt.nodes.new("ShaderNodeNewGeometry").outputs["Position"]
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 0.11
        noise.inputs["Detail"].default_value = 3.0
        nt.links.new(pos, noise.inputs["Vector"])
        grain = nt.nodes.new("ShaderNodeTexNoise")
        grain.inputs["Scale"].default_value = 3.0
        nt.links.new(pos, grain.inputs["Vector"])
        thr = knobs.value(nt, "puddle_threshold", 1.0)
        mr = nt.nodes.new("ShaderNodeMapRange")
        mr.clamp = True
        nt.links.new(noise.outputs["Fac"], mr.inputs["Value"])
        nt.links.new(thr, mr.inputs["From Min"])
        nt.links.new(math_node(nt, "ADD", thr, 0.04), mr.inputs["From Max"])
        puddle = mr.outputs["Result"]
        wet = knobs.value(nt, "wetness", 0.0)
        shade = math_node(nt, "ADD", math_node(nt, "MULTIPLY", grain.outputs["Fac"], 0.35), 0.82)
        def one_minus(x, k):
            return math_node(nt, "SUBTRACT", 1.0, math_node(nt, "MULTIPLY", x, k))

        dark = math_node(nt, "MULTIPLY", shade, one_minus(wet, 0.45))
        dark = math_node(nt, "MULTIPLY", dark, one_minus(puddle, 0.6))
        base = mix_node(nt, "RGBA", math_node(nt, "SUBTRACT", 1.0, dark), col, (0, 0, 0))  # col * dark
        rough = math_node(nt, "SUBTRACT", 0.88, math_node(nt, "MULTIPLY", wet, 0.55))
        rough = mix_node(nt, "FLOAT", puddle, rough, 0.03)
        return base, rough

    mat = bpy.data.materials.new("pavement")
    nt = mat.node_tree
    nt.nodes.clear()
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    _label_switch(knobs, mat, bsdf.outputs[0])
    base, rough = pavement_parts(nt)
    nt.links.new(base, bsdf.inputs["Base Color"])
    nt.links.new(rough, bsdf.inputs["Roughness"])
    materials["pavement"] = mat

    def wet_base(nt, amount):
        wet = knobs.value(nt, "wetness", 0.0)
        f = math_node(nt, "MULTIPLY", wet, amount)
        return mix_node(nt, "RGBA", f, vertex_colour(nt), (0, 0, 0))

    def wet_rough(nt, dry, wet_value):
        wet = knobs.value(nt, "wetness", 0.0)
        return mix_node(nt, "FLOAT", wet, dry, wet_value)

    principled("matte", lambda nt: wet_base(nt, 0.3), lambda nt: wet_rough(nt, 0.9, 0.55))
    principled("metal", lambda nt: vertex_colour(nt), 0.45, metallic=0.6)
    principled("sign", lambda nt: vertex_colour(nt), 0.35,
               emission=lambda nt: vertex_colour(nt),
               emission_strength=lambda nt: knobs.value(nt, "sign_emit", 0.0))

    def window_emission(nt):
        a = vertex_colour(nt, "Alpha")
        tone = math_node(nt, "LESS_THAN", math_node(nt, "FRACT", math_node(nt, "MULTIPLY", a, 7.0)), 0.3)
        return mix_node(nt, "RGBA", tone, (1.0, 0.72, 0.42), (0.85, 0.92, 1.0))

    def window_strength(nt):
        a = vertex_colour(nt, "Alpha")
        lit = math_node(nt, "LESS_THAN", a, knobs.value(nt, "window_fraction", 0.0))
        return math_node(nt, "MULTIPLY", lit, knobs.value(nt, "window_emit", 0.0))

    principled("window", lambda nt: mix_node(nt, "RGBA", 0.7, vertex_colour(nt), (0.02, 0.025, 0.03)),
               0.08, specular=0.9, emission=window_emission, emission_strength=window_strength)
    principled("lamp", (0.85, 0.85, 0.8), 0.3, emission=(1.0, 0.78, 0.52),
               emission_strength=lambda nt: knobs.value(nt, "lamp_emit", 0.0))
    for colour, rgb in (("red", (1.0, 0.05, 0.02)), ("amber", (1.0, 0.45, 0.0)), ("green", (0.1, 1.0, 0.45))):
        principled(f"signal_{colour}", (0.05, 0.05, 0.05), 0.2, emission=rgb,
                   emission_strength=lambda nt: knobs.value(nt, "signal_emit", 4.0))
    principled("signal_off", (0.03, 0.03, 0.03), 0.2)
    principled("paint", lambda nt: vertex_colour(nt), 0.35, metallic=0.35, coat=1.0)
    principled("glass", (0.015, 0.018, 0.022), 0.04, specular=1.0)
    principled("rubber", (0.025, 0.025, 0.025), 0.85)
    principled("headlight", (0.8, 0.8, 0.8), 0.1, emission=(1.0, 0.94, 0.82),
               emission_strength=lambda nt: knobs.value(nt, "headlight_emit", 0.0))
    principled("taillight", (0.45, 0.02, 0.02), 0.2, emission=(1.0, 0.04, 0.02),
               emission_strength=lambda nt: knobs.value(nt, "taillight_emit", 0.0))
    principled("lens_clear", (0.75, 0.75, 0.72), 0.1, specular=0.9)
    principled("lens_red", (0.4, 0.02, 0.02), 0.15, specular=0.8)
    # bounded fog: a volume-only box (its surface is a transparent boundary)
    mat = bpy.data.materials.new("fog")
    nt = mat.node_tree
    nt.nodes.clear()
    scat = nt.nodes.new("ShaderNodeVolumeScatter")
    scat.inputs["Color"].default_value = (0.92, 0.93, 0.95, 1)
    scat.inputs["Anisotropy"].default_value = 0.3
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(knobs.value(nt, "fog_density", 0.0), scat.inputs["Density"])
    # a zero density still costs a full volume integration; a constant switch that Cycles folds
    # away leaves an empty, transparent box instead (and keeps the scene's object set fixed)
    switch = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(knobs.value(nt, "fog_on", 0.0), switch.inputs[0])
    nt.links.new(scat.outputs[0], switch.inputs[2])
    nt.links.new(switch.outputs[0], out.inputs["Volume"])
    # a transparent surface: without one the switched-off box is an empty shader, which Cycles'
    # shadow rays treat as opaque (clear skies then lost the sun)
    clear = nt.nodes.new("ShaderNodeBsdfTransparent")
    nt.links.new(clear.outputs[0], out.inputs["Surface"])
    materials["fog"] = mat
    return materials


__all__ = ["build_materials"]
