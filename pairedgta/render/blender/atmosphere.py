"""The atmosphere: the sky (world shader) and the analytic fog (a compositor pass), built once per session.

`renderer.fog_model=analytic` blends the render toward the in-scattered light by the transmittance
exp(-extinction * distance) in the compositor; `volume` path-traces the scattering box of materials.py
instead. Both read their values from knobs (nodes.py) that a condition sets.
"""
from __future__ import annotations

from pairedgta.render.blender.nodes import Knobs, grey_vector, math_node, mix_node

FOG_MODELS = ("analytic", "volume")
# m; the mist pass is distance / this, 1 for the sky: the camera's clip distance, so that only the sky
# (behind which nothing lies) reaches 1 and is fully replaced by the fog, as the transmittance map says
FOG_MIST_DEPTH = 5000.0
FOG_GLOW = 10.0  # glare strength per unit extinction (1/m), at most 1
FOG_GLOW_SPREAD = 25.0  # glare size (0.5 in clear air) per unit extinction, at most 1


def build_sky(bpy, knobs: Knobs) -> None:
    """The world shader: a zenith-horizon gradient, a halo around the sun and noise clouds whose colours
    and cover are knobs, so a condition re-colours the sky without rebuilding it."""
    world = bpy.data.worlds.new("sky")
    bpy.context.scene.world = world
    world.cycles.sampling_method = "MANUAL"
    world.cycles.sample_map_resolution = 256
    world.light_settings.distance = 8.0  # fast-GI AO distance
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    nt.links.new(bg.outputs[0], out.inputs["Surface"])
    d = nt.nodes.new("ShaderNodeTexCoord").outputs["Generated"]
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(d, sep.inputs[0])
    up = math_node(nt, "MAXIMUM", sep.outputs["Z"], 0.0)
    t = math_node(nt, "POWER", up, 0.45)
    horizon = knobs.colour(nt, "horizon", (0.5, 0.6, 0.8))
    sky = mix_node(nt, "RGBA", t, horizon, knobs.colour(nt, "zenith", (0.1, 0.2, 0.6)))
    # sun halo
    dot = nt.nodes.new("ShaderNodeVectorMath")
    dot.operation = "DOT_PRODUCT"
    nt.links.new(d, dot.inputs[0])
    sun_dir = nt.nodes.new("ShaderNodeCombineXYZ")
    for axis, name in zip("XYZ", ("sun_x", "sun_y", "sun_z")):
        nt.links.new(knobs.value(nt, name, 0.0), sun_dir.inputs[axis])
    nt.links.new(sun_dir.outputs[0], dot.inputs[1])
    c = math_node(nt, "MAXIMUM", dot.outputs["Value"], 0.0)
    aureole = math_node(nt, "MULTIPLY", math_node(nt, "POWER", c, 60.0), 2.0)
    halo = math_node(nt, "ADD", math_node(nt, "POWER", c, 5.0), aureole)
    halo = math_node(nt, "MULTIPLY", halo, math_node(nt, "SUBTRACT", 1.0, math_node(nt, "MULTIPLY", up, 0.6)))
    glow = mix_node(nt, "RGBA", 1.0, knobs.colour(nt, "glow", (0, 0, 0)), grey_vector(nt, halo),
                    "MULTIPLY")
    sky = mix_node(nt, "RGBA", 1.0, sky, glow, "ADD")
    # clouds: noise on the plane z=1 seen along the view ray
    proj = nt.nodes.new("ShaderNodeVectorMath")
    proj.operation = "SCALE"
    nt.links.new(d, proj.inputs[0])
    nt.links.new(math_node(nt, "DIVIDE", 1.0, math_node(nt, "ADD", up, 0.06)), proj.inputs["Scale"])
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 0.9
    noise.inputs["Detail"].default_value = 4.0
    noise.inputs["Roughness"].default_value = 0.55
    nt.links.new(proj.outputs[0], noise.inputs["Vector"])
    cover = knobs.value(nt, "cloud_cover", 0.0)
    lo = math_node(nt, "SUBTRACT", 0.64, math_node(nt, "MULTIPLY", cover, 0.42))
    mr = nt.nodes.new("ShaderNodeMapRange")
    mr.clamp = True
    nt.links.new(noise.outputs["Fac"], mr.inputs["Value"])
    nt.links.new(lo, mr.inputs["From Min"])
    nt.links.new(math_node(nt, "ADD", lo, 0.14), mr.inputs["From Max"])
    fade = math_node(nt, "MINIMUM", math_node(nt, "MULTIPLY", up, 8.0), 1.0)
    patches = math_node(nt, "MULTIPLY", mr.outputs["Result"], fade)
    amount = math_node(nt, "ADD", patches, knobs.value(nt, "overcast", 0.0), clamp=True)
    cloud_col = knobs.colour(nt, "cloud_color", (0.5, 0.5, 0.5))
    sky = mix_node(nt, "RGBA", amount, sky, cloud_col)
    # the city's diffuse light at night (illumination.NightLight.fill) for every ray but the camera's: it lights
    # the scene and the wet road reflects it, while the sky in the image stays the night sky
    camera_ray = nt.nodes.new("ShaderNodeLightPath").outputs["Is Camera Ray"]
    fill = mix_node(nt, "RGBA", math_node(nt, "SUBTRACT", 1.0, camera_ray), (0, 0, 0), knobs.colour(nt, "fill", (0, 0, 0)))
    sky = mix_node(nt, "RGBA", 1.0, sky, fill, "ADD")
    nt.links.new(sky, bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 1.0


def build_fog_compositor(bpy, knobs: Knobs) -> None:
    """Analytic fog: transmittance exp(-sigma * d) from the mist pass (ray distance, averaged over
    the samples, so silhouettes stay antialiased) blends the image toward the in-scattered
    radiance, and a fog-glow glare gives lamps and head-lights their halo. A homogeneous medium
    needs no path-traced volume: this is what the volume model computes, without its noise at
    2 samples (timings of both: experiments/bench_render.py --sweep)."""
    sc = bpy.context.scene
    sc.view_layers[0].use_pass_mist = True
    mist = sc.world.mist_settings
    mist.start, mist.depth, mist.falloff = 0.0, FOG_MIST_DEPTH, "LINEAR"
    ng = bpy.data.node_groups.new("fog", "CompositorNodeTree")
    ng.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    layers = ng.nodes.new("CompositorNodeRLayers")
    depth = ng.nodes.new("ShaderNodeMath")
    depth.operation = "MULTIPLY"
    ng.links.new(layers.outputs["Mist"], depth.inputs[0])
    knobs.add("fog_optical_depth", depth.inputs[1])  # sigma * FOG_MIST_DEPTH
    trans = ng.nodes.new("ShaderNodeMath")
    trans.operation = "EXPONENT"
    neg = ng.nodes.new("ShaderNodeMath")
    neg.operation = "MULTIPLY"
    neg.inputs[1].default_value = -1.0
    ng.links.new(depth.outputs[0], neg.inputs[0])
    ng.links.new(neg.outputs[0], trans.inputs[0])
    # the sky (mist 1: nothing within the clip distance) lies behind an unbounded path: transmittance
    # 0, as the transmittance map (label pass distance inf) says; the fog colour replaces it
    geometry = ng.nodes.new("ShaderNodeMath")
    geometry.operation = "LESS_THAN"
    geometry.inputs[1].default_value = 1.0 - 1e-6
    ng.links.new(layers.outputs["Mist"], geometry.inputs[0])
    seen = ng.nodes.new("ShaderNodeMath")
    seen.operation = "MULTIPLY"
    ng.links.new(trans.outputs[0], seen.inputs[0])
    ng.links.new(geometry.outputs[0], seen.inputs[1])
    colour = ng.nodes.new("CompositorNodeRGB")
    knobs.add("fog_color", colour.outputs[0])
    mix = ng.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    ng.links.new(seen.outputs[0], mix.inputs["Factor"])
    ng.links.new(colour.outputs[0], mix.inputs[6])  # A: the fog, where the transmittance is 0
    ng.links.new(layers.outputs["Image"], mix.inputs[7])  # B: the scene, where it is 1
    glare = ng.nodes.new("CompositorNodeGlare")
    glare.inputs["Type"].default_value = "Fog Glow"
    glare.inputs["Quality"].default_value = "Medium"
    glare.inputs["Threshold"].default_value = 1.0
    knobs.add("fog_glow", glare.inputs["Strength"])
    knobs.add("fog_glow_size", glare.inputs["Size"])
    ng.links.new(mix.outputs[2], glare.inputs["Image"])
    out = ng.nodes.new("NodeGroupOutput")
    ng.links.new(glare.outputs["Image"], out.inputs[0])
    sc.compositing_node_group = ng
    sc.render.use_compositing = False  # switched on by Shading.apply (shading.py) for fogged conditions only


__all__ = ["FOG_GLOW", "FOG_GLOW_SPREAD", "FOG_MIST_DEPTH", "FOG_MODELS", "build_fog_compositor", "build_sky"]
