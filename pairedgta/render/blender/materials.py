"""Materials, world, lights and conditions: everything a condition changes.

`lighting(cond)` maps a condition to render parameters (pure numpy, continuous in every physical
field). `Shading` builds the materials, sky and light pools once per session and exposes every
condition-dependent value as a named knob; applying a condition sets values only, never which
objects or lights exist, so Cycles' scene (and its sampling sequence) stays fixed.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from pairedgta.conditions import Condition

FOG_MODELS = ("analytic", "volume")
FOG_ALBEDO = 0.92
# weights of the in-scattered light of the analytic fog, matched to the volume model's far field
FOG_SKY, FOG_SUN = 0.7, 0.2
# m; the mist pass is distance / this, 1 for the sky: the camera's clip distance, so that only the sky
# (behind which nothing lies) reaches 1 and is fully replaced by the fog, as the transmittance map says
FOG_MIST_DEPTH = 5000.0
# Artificial light, relative to the sun (strength 4.5): a street-lit road is thousands of times darker than
# a sunlit one (10-30 lx against 50,000 lx and more), and a camera undoes only part of that
# (render/camera.py). The light sources themselves (lamp heads, head-lights) stay bright: they are what a
# night image shows and what fog glows around. Lit windows glow as dimly as interiors do from outside.
LAMP_POWER = 40.0        # W per street-lamp spot light
HEADLIGHT_POWER = 30.0   # W per head-light spot light
WINDOW_EMISSION = 0.08   # emission strength of a lit window
FOG_GLOW = 10.0  # glare strength per unit extinction (1/m), at most 1
FOG_GLOW_SPREAD = 25.0  # glare size (0.5 in clear air) per unit extinction, at most 1


def _smoothstep(a: float, b: float, x: float) -> float:
    t = min(max((x - a) / (b - a), 0.0), 1.0)
    return t * t * (3 - 2 * t)


def sun_vector(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector towards the sun; azimuth clockwise from north (+y), east is +x."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])


def sun_transmittance(elevation_deg: float) -> np.ndarray:
    """RGB transmittance through the atmosphere (Kasten-Young air mass, Rayleigh-like optical
    depths): white at noon, orange near the horizon."""
    e = max(elevation_deg, -1.0)
    airmass = 1.0 / (math.sin(math.radians(max(e, 0.0))) + 0.50572 * (e + 6.07995) ** -1.6364)
    return np.exp(-np.array([0.06, 0.11, 0.24]) * airmass)


def lighting(cond: Condition) -> dict[str, Any]:
    """All condition-dependent render parameters; continuous in every physical field. The extinction
    is the condition's own (visibility and rain rate, conditions.py), so the image and the
    transmittance map written beside it attenuate alike. `light_level` is what the camera meters
    (render/camera.py): the light falling on the scene from the sun, the sky and, at night, the lamps."""
    el = float(cond.sun_elevation_deg)
    rain = cond.rain_level
    cloud = max(float(cond.cloud_cover), rain)
    wet = max(float(cond.wetness), rain)
    fog = cond.fog_level
    trans = sun_transmittance(el)
    sun_vis = _smoothstep(-1.0, 2.0, el)
    sun_strength = 4.5 * sun_vis * float(trans.max()) * (1.0 - 0.92 * cloud)
    sun_color = trans / trans.max()
    sky = min(max((el + 6.0) / 36.0, 0.0), 1.0) ** 1.3  # daylight sky brightness
    warm = (1.0 - _smoothstep(0.0, 22.0, el)) * _smoothstep(-7.0, -1.0, el)
    night = 1.0 - _smoothstep(-8.0, 2.0, el)
    zenith = sky * ((1 - warm) * np.array([0.10, 0.24, 0.62]) + warm * np.array([0.08, 0.13, 0.34]))
    horizon = sky * ((1 - warm) * np.array([0.55, 0.64, 0.78]) + warm * np.array([1.1, 0.55, 0.28]))
    city_glow = np.array([0.012, 0.008, 0.005]) * night
    zenith = zenith + np.array([0.0015, 0.0025, 0.006]) * night
    horizon = horizon + city_glow
    glow = (0.9 * warm + 0.15) * sky * sun_color * (1 - cloud)
    # rain clouds are dark, and heavy rain's haze hides the city's glow from their base
    grey = np.array([0.50, 0.52, 0.56]) * (sky * (1.0 - 0.85 * rain) + 0.006) + city_glow * (1.0 - 0.8 * rain)
    moon = 0.05 * night * (1.0 - 0.9 * cloud)  # a moonlit clear night is brighter than an overcast one
    lamps = 1.0 - _smoothstep(-3.0, 6.0, el)
    vehicle_lights = max(lamps, _smoothstep(0.2, 0.6, max(rain, fog)))
    sky_light = 2.6 * float(np.mean(zenith + horizon) / 2 * (1 - cloud) + np.mean(grey) * cloud)
    extinction = cond.extinction_per_m  # 1/m
    # radiance that fog and rain haze scatter toward the camera everywhere (renderer.fog_model=analytic):
    # albedo times the light arriving from the sky (cloud-grey as cover grows) and the sun (isotropic
    # share). Lamp and head-light light is scattered where it is: the compositor's glare gives each its
    # halo, so the night's fog stays dark away from the lights instead of glowing uniformly.
    ambient = (zenith + horizon) / 2 * (1 - cloud) + grey * cloud
    fog_color = FOG_ALBEDO * (FOG_SKY * ambient + FOG_SUN * sun_strength * sun_color / (4 * math.pi))
    light_level = sun_strength * max(math.sin(math.radians(el)), 0.0) + sky_light + 0.04 * lamps
    return {
        "sun_dir": sun_vector(el, cond.sun_azimuth_deg), "sun_strength": sun_strength, "sun_color": sun_color,
        "sun_angle_deg": 0.53 + 25.0 * cloud,
        "moon_dir": sun_vector(38.0, (cond.sun_azimuth_deg + 180.0) % 360.0), "moon_strength": moon,
        "zenith": zenith, "horizon": horizon, "glow": glow, "cloud_color": grey,
        "cloud_cover": cloud, "overcast": _smoothstep(0.55, 0.95, cloud),
        "wetness": wet, "puddle_threshold": 1.0 - 0.42 * wet,
        "fog": fog, "rain": rain, "extinction": extinction, "fog_color": fog_color,
        "lamps": lamps, "vehicle_lights": vehicle_lights,
        "window_lit": lamps, "light_level": light_level,
    }


class Shading:
    """Materials, world and lights of one bpy session, with their condition knobs."""

    def __init__(self, bpy, max_lamps: int, max_headlights: int, fog_model: str = "analytic") -> None:
        self._bpy = bpy
        self.fog_model = fog_model
        self.max_lamps = int(max_lamps)
        self.max_headlights = int(max_headlights)
        self._knobs: dict[str, list[Any]] = {}
        self._materials: dict[str, Any] = {}

    @property
    def materials(self) -> dict[str, Any]:
        return self._materials

    def build(self) -> None:
        self._build_materials()
        self._build_world()
        self._build_lights()
        if self.fog_model == "analytic":
            self._build_compositor()

    def set(self, name: str, value) -> None:
        for socket in self._knobs.get(name, []):
            if isinstance(value, (np.ndarray, tuple, list)):
                socket.default_value = (*[float(v) for v in value], 1.0)
            else:
                socket.default_value = float(value)

    def get(self, name: str) -> float:
        return self._knobs[name][0].default_value

    def _knob(self, nt, name: str, default: float):
        node = nt.nodes.new("ShaderNodeValue")
        node.outputs[0].default_value = default
        self._knobs.setdefault(name, []).append(node.outputs[0])
        return node.outputs[0]

    def _color_knob(self, nt, name: str, default):
        node = nt.nodes.new("ShaderNodeRGB")
        node.outputs[0].default_value = (*default, 1.0)
        self._knobs.setdefault(name, []).append(node.outputs[0])
        return node.outputs[0]

    @staticmethod
    def _set_input(nt, socket, value) -> None:
        if hasattr(value, "is_output"):
            nt.links.new(value, socket)
        elif isinstance(value, (tuple, list)) and len(value) == 3:
            socket.default_value = (*value, 1.0)
        else:
            socket.default_value = value

    def _math(self, nt, op: str, a, b=None, clamp: bool = False):
        node = nt.nodes.new("ShaderNodeMath")
        node.operation = op
        node.use_clamp = clamp
        self._set_input(nt, node.inputs[0], a)
        if b is not None:
            self._set_input(nt, node.inputs[1], b)
        return node.outputs[0]

    def _mix(self, nt, kind: str, fac, a, b, blend: str = "MIX"):
        node = nt.nodes.new("ShaderNodeMix")
        node.data_type = kind
        if kind == "RGBA":
            node.blend_type = blend
        suffix = {"RGBA": "Color", "FLOAT": "Float", "VECTOR": "Vector"}[kind]
        ins = {s.identifier: s for s in node.inputs}
        self._set_input(nt, ins["Factor_Float"], fac)
        self._set_input(nt, ins[f"A_{suffix}"], a)
        self._set_input(nt, ins[f"B_{suffix}"], b)
        return {s.identifier: s for s in node.outputs}[f"Result_{suffix}"]

    def _principled(self, name: str, base, roughness, metallic=0.0, specular=0.5, coat=0.0,
                    emission=None, emission_strength=None):
        bpy = self._bpy
        mat = bpy.data.materials.new(name)
        nt = mat.node_tree
        nt.nodes.clear()
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        self._output_with_label_switch(mat, bsdf.outputs[0])
        base = base(nt) if callable(base) else base
        roughness = roughness(nt) if callable(roughness) else roughness
        self._set_input(nt, bsdf.inputs["Base Color"], base)
        self._set_input(nt, bsdf.inputs["Roughness"], roughness)
        self._set_input(nt, bsdf.inputs["Metallic"], metallic)
        self._set_input(nt, bsdf.inputs["Specular IOR Level"], specular)
        self._set_input(nt, bsdf.inputs["Coat Weight"], coat)
        if emission is not None:
            emission = emission(nt) if callable(emission) else emission
            strength = emission_strength(nt) if callable(emission_strength) else emission_strength
            self._set_input(nt, bsdf.inputs["Emission Color"], emission)
            self._set_input(nt, bsdf.inputs["Emission Strength"], strength)
        self._materials[name] = mat
        return mat

    def _output_with_label_switch(self, mat, surface) -> None:
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
        nt.links.new(self._knob(nt, "label_mode", 0.0), mix.inputs[0])
        nt.links.new(surface, mix.inputs[1])
        nt.links.new(em.outputs[0], mix.inputs[2])
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(mix.outputs[0], out.inputs["Surface"])
        # emitters are drawn, not sampled as lights: thousands of window quads (or, in the label
        # pass, every triangle) in the light tree would cost more than the lights themselves
        mat.cycles.emission_sampling = "NONE"

    def _attr(self, nt, output: str = "Color"):
        node = nt.nodes.new("ShaderNodeAttribute")
        node.attribute_name = "col"
        return node.outputs[output]

    def _build_materials(self) -> None:
        bpy = self._bpy

        def pavement_parts(nt):
            col = self._attr(nt)
            pos = nt.nodes.new("ShaderNodeNewGeometry").outputs["Position"]
            noise = nt.nodes.new("ShaderNodeTexNoise")
            noise.inputs["Scale"].default_value = 0.11
            noise.inputs["Detail"].default_value = 3.0
            nt.links.new(pos, noise.inputs["Vector"])
            grain = nt.nodes.new("ShaderNodeTexNoise")
            grain.inputs["Scale"].default_value = 3.0
            nt.links.new(pos, grain.inputs["Vector"])
            thr = self._knob(nt, "puddle_threshold", 1.0)
            mr = nt.nodes.new("ShaderNodeMapRange")
            mr.clamp = True
            nt.links.new(noise.outputs["Fac"], mr.inputs["Value"])
            nt.links.new(thr, mr.inputs["From Min"])
            nt.links.new(self._math(nt, "ADD", thr, 0.04), mr.inputs["From Max"])
            puddle = mr.outputs["Result"]
            wet = self._knob(nt, "wetness", 0.0)
            shade = self._math(nt, "ADD", self._math(nt, "MULTIPLY", grain.outputs["Fac"], 0.35), 0.82)
            def one_minus(x, k):
                return self._math(nt, "SUBTRACT", 1.0, self._math(nt, "MULTIPLY", x, k))

            dark = self._math(nt, "MULTIPLY", shade, one_minus(wet, 0.45))
            dark = self._math(nt, "MULTIPLY", dark, one_minus(puddle, 0.6))
            base = self._mix(nt, "RGBA", self._math(nt, "SUBTRACT", 1.0, dark), col, (0, 0, 0))  # col * dark
            rough = self._math(nt, "SUBTRACT", 0.88, self._math(nt, "MULTIPLY", wet, 0.55))
            rough = self._mix(nt, "FLOAT", puddle, rough, 0.03)
            return base, rough

        mat = bpy.data.materials.new("pavement")
        nt = mat.node_tree
        nt.nodes.clear()
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        self._output_with_label_switch(mat, bsdf.outputs[0])
        base, rough = pavement_parts(nt)
        nt.links.new(base, bsdf.inputs["Base Color"])
        nt.links.new(rough, bsdf.inputs["Roughness"])
        self._materials["pavement"] = mat

        def wet_base(nt, amount):
            wet = self._knob(nt, "wetness", 0.0)
            f = self._math(nt, "MULTIPLY", wet, amount)
            return self._mix(nt, "RGBA", f, self._attr(nt), (0, 0, 0))

        def wet_rough(nt, dry, wet_value):
            wet = self._knob(nt, "wetness", 0.0)
            return self._mix(nt, "FLOAT", wet, dry, wet_value)

        self._principled("matte", lambda nt: wet_base(nt, 0.3), lambda nt: wet_rough(nt, 0.9, 0.55))
        self._principled("metal", lambda nt: self._attr(nt), 0.45, metallic=0.6)
        self._principled("sign", lambda nt: self._attr(nt), 0.35,
                         emission=lambda nt: self._attr(nt),
                         emission_strength=lambda nt: self._knob(nt, "sign_emit", 0.0))

        def window_emission(nt):
            a = self._attr(nt, "Alpha")
            tone = self._math(nt, "LESS_THAN", self._math(nt, "FRACT", self._math(nt, "MULTIPLY", a, 7.0)), 0.3)
            return self._mix(nt, "RGBA", tone, (1.0, 0.72, 0.42), (0.85, 0.92, 1.0))

        def window_strength(nt):
            a = self._attr(nt, "Alpha")
            lit = self._math(nt, "LESS_THAN", a, self._knob(nt, "window_fraction", 0.0))
            return self._math(nt, "MULTIPLY", lit, self._knob(nt, "window_emit", 0.0))

        self._principled("window", lambda nt: self._mix(nt, "RGBA", 0.7, self._attr(nt), (0.02, 0.025, 0.03)),
                         0.08, specular=0.9, emission=window_emission, emission_strength=window_strength)
        self._principled("lamp", (0.85, 0.85, 0.8), 0.3, emission=(1.0, 0.78, 0.52),
                         emission_strength=lambda nt: self._knob(nt, "lamp_emit", 0.0))
        for colour, rgb in (("red", (1.0, 0.05, 0.02)), ("amber", (1.0, 0.45, 0.0)), ("green", (0.1, 1.0, 0.45))):
            self._principled(f"signal_{colour}", (0.05, 0.05, 0.05), 0.2, emission=rgb,
                             emission_strength=lambda nt: self._knob(nt, "signal_emit", 4.0))
        self._principled("signal_off", (0.03, 0.03, 0.03), 0.2)
        self._principled("paint", lambda nt: self._attr(nt), 0.35, metallic=0.35, coat=1.0)
        self._principled("glass", (0.015, 0.018, 0.022), 0.04, specular=1.0)
        self._principled("rubber", (0.025, 0.025, 0.025), 0.85)
        self._principled("headlight", (0.8, 0.8, 0.8), 0.1, emission=(1.0, 0.94, 0.82),
                         emission_strength=lambda nt: self._knob(nt, "headlight_emit", 0.0))
        self._principled("taillight", (0.45, 0.02, 0.02), 0.2, emission=(1.0, 0.04, 0.02),
                         emission_strength=lambda nt: self._knob(nt, "taillight_emit", 0.0))
        self._principled("lens_clear", (0.75, 0.75, 0.72), 0.1, specular=0.9)
        self._principled("lens_red", (0.4, 0.02, 0.02), 0.15, specular=0.8)
        # bounded fog: a volume-only box (its surface is a transparent boundary)
        mat = bpy.data.materials.new("fog")
        nt = mat.node_tree
        nt.nodes.clear()
        scat = nt.nodes.new("ShaderNodeVolumeScatter")
        scat.inputs["Color"].default_value = (0.92, 0.93, 0.95, 1)
        scat.inputs["Anisotropy"].default_value = 0.3
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(self._knob(nt, "fog_density", 0.0), scat.inputs["Density"])
        # a zero density still costs a full volume integration; a constant switch that Cycles folds
        # away leaves an empty, transparent box instead (and keeps the scene's object set fixed)
        switch = nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(self._knob(nt, "fog_on", 0.0), switch.inputs[0])
        nt.links.new(scat.outputs[0], switch.inputs[2])
        nt.links.new(switch.outputs[0], out.inputs["Volume"])
        # a transparent surface: without one the switched-off box is an empty shader, which Cycles'
        # shadow rays treat as opaque (clear skies then lost the sun)
        clear = nt.nodes.new("ShaderNodeBsdfTransparent")
        nt.links.new(clear.outputs[0], out.inputs["Surface"])
        self._materials["fog"] = mat

    def _build_world(self) -> None:
        bpy = self._bpy
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
        up = self._math(nt, "MAXIMUM", sep.outputs["Z"], 0.0)
        t = self._math(nt, "POWER", up, 0.45)
        horizon = self._color_knob(nt, "horizon", (0.5, 0.6, 0.8))
        sky = self._mix(nt, "RGBA", t, horizon, self._color_knob(nt, "zenith", (0.1, 0.2, 0.6)))
        # sun halo
        dot = nt.nodes.new("ShaderNodeVectorMath")
        dot.operation = "DOT_PRODUCT"
        nt.links.new(d, dot.inputs[0])
        sun_dir = nt.nodes.new("ShaderNodeCombineXYZ")
        for axis, name in zip("XYZ", ("sun_x", "sun_y", "sun_z")):
            nt.links.new(self._knob(nt, name, 0.0), sun_dir.inputs[axis])
        nt.links.new(sun_dir.outputs[0], dot.inputs[1])
        c = self._math(nt, "MAXIMUM", dot.outputs["Value"], 0.0)
        aureole = self._math(nt, "MULTIPLY", self._math(nt, "POWER", c, 60.0), 2.0)
        halo = self._math(nt, "ADD", self._math(nt, "POWER", c, 5.0), aureole)
        halo = self._math(nt, "MULTIPLY", halo, self._math(nt, "SUBTRACT", 1.0, self._math(nt, "MULTIPLY", up, 0.6)))
        glow = self._mix(nt, "RGBA", 1.0, self._color_knob(nt, "glow", (0, 0, 0)), self._combine_grey(nt, halo),
                         "MULTIPLY")
        sky = self._mix(nt, "RGBA", 1.0, sky, glow, "ADD")
        # clouds: noise on the plane z=1 seen along the view ray
        proj = nt.nodes.new("ShaderNodeVectorMath")
        proj.operation = "SCALE"
        nt.links.new(d, proj.inputs[0])
        nt.links.new(self._math(nt, "DIVIDE", 1.0, self._math(nt, "ADD", up, 0.06)), proj.inputs["Scale"])
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 0.9
        noise.inputs["Detail"].default_value = 4.0
        noise.inputs["Roughness"].default_value = 0.55
        nt.links.new(proj.outputs[0], noise.inputs["Vector"])
        cover = self._knob(nt, "cloud_cover", 0.0)
        lo = self._math(nt, "SUBTRACT", 0.64, self._math(nt, "MULTIPLY", cover, 0.42))
        mr = nt.nodes.new("ShaderNodeMapRange")
        mr.clamp = True
        nt.links.new(noise.outputs["Fac"], mr.inputs["Value"])
        nt.links.new(lo, mr.inputs["From Min"])
        nt.links.new(self._math(nt, "ADD", lo, 0.14), mr.inputs["From Max"])
        fade = self._math(nt, "MINIMUM", self._math(nt, "MULTIPLY", up, 8.0), 1.0)
        patches = self._math(nt, "MULTIPLY", mr.outputs["Result"], fade)
        amount = self._math(nt, "ADD", patches, self._knob(nt, "overcast", 0.0), clamp=True)
        cloud_col = self._color_knob(nt, "cloud_color", (0.5, 0.5, 0.5))
        sky = self._mix(nt, "RGBA", amount, sky, cloud_col)
        nt.links.new(sky, bg.inputs["Color"])
        bg.inputs["Strength"].default_value = 1.0

    def _build_compositor(self) -> None:
        """Analytic fog: transmittance exp(-sigma * d) from the mist pass (ray distance, averaged over
        the samples, so silhouettes stay antialiased) blends the image toward the in-scattered
        radiance, and a fog-glow glare gives lamps and head-lights their halo. A homogeneous medium
        needs no path-traced volume: this is what the volume model computes, without its noise at
        2 samples (timings of both: experiments/bench_render.py --sweep)."""
        bpy = self._bpy
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
        self._knobs.setdefault("fog_optical_depth", []).append(depth.inputs[1])  # sigma * FOG_MIST_DEPTH
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
        self._knobs.setdefault("fog_color", []).append(colour.outputs[0])
        mix = ng.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        ng.links.new(seen.outputs[0], mix.inputs["Factor"])
        ng.links.new(colour.outputs[0], mix.inputs[6])  # A: the fog, where the transmittance is 0
        ng.links.new(layers.outputs["Image"], mix.inputs[7])  # B: the scene, where it is 1
        glare = ng.nodes.new("CompositorNodeGlare")
        glare.inputs["Type"].default_value = "Fog Glow"
        glare.inputs["Quality"].default_value = "Medium"
        glare.inputs["Threshold"].default_value = 1.0
        self._knobs.setdefault("fog_glow", []).append(glare.inputs["Strength"])
        self._knobs.setdefault("fog_glow_size", []).append(glare.inputs["Size"])
        ng.links.new(mix.outputs[2], glare.inputs["Image"])
        out = ng.nodes.new("NodeGroupOutput")
        ng.links.new(glare.outputs["Image"], out.inputs[0])
        sc.compositing_node_group = ng
        sc.render.use_compositing = False  # switched on by `apply` for fogged conditions only

    def _combine_grey(self, nt, value):
        comb = nt.nodes.new("ShaderNodeCombineXYZ")
        for axis in "XYZ":
            nt.links.new(value, comb.inputs[axis])
        return comb.outputs[0]

    def _build_lights(self) -> None:
        bpy = self._bpy
        sc = bpy.context.scene
        self._sun = bpy.data.lights.new("sun", "SUN")
        self._sun_obj = bpy.data.objects.new("sun", self._sun)
        self._moon = bpy.data.lights.new("moon", "SUN")
        self._moon.color = (0.75, 0.82, 1.0)
        self._moon.angle = math.radians(0.6)
        self._moon_obj = bpy.data.objects.new("moon", self._moon)
        for o in (self._sun_obj, self._moon_obj):
            sc.collection.objects.link(o)
        # fixed pools of spot lights, created once and only moved per scene: Cycles' light list
        # order (and so the sampling sequence) would otherwise depend on the scenes rendered before
        self._lamp_pool = [self._pool_light(f"lamp_{i:03d}", 150, 0.6, 0.2, (1.0, 0.78, 0.52))
                           for i in range(self.max_lamps)]
        self._head_pool = [self._pool_light(f"headlight_{i:03d}", 70, 0.5, 0.1, (1.0, 0.95, 0.85))
                           for i in range(self.max_headlights)]
        self._lamps_used = self._heads_used = 0

    def _pool_light(self, name: str, cone_deg: float, blend: float, radius: float, color) -> Any:
        bpy = self._bpy
        data = bpy.data.lights.new(name, "SPOT")
        data.spot_size = math.radians(cone_deg)
        data.spot_blend = blend
        data.shadow_soft_size = radius
        data.color = color
        data.energy = 0.0
        obj = bpy.data.objects.new(name, data)
        obj.visible_camera = False
        obj.location = (0.0, 0.0, -50.0)
        bpy.context.scene.collection.objects.link(obj)
        return obj


    # ---- conditions -----------------------------------------------------------------------
    def apply(self, p: dict[str, Any], lamps_used: int, heads_used: int, lit_window_fraction: float) -> None:
        """Set every condition-dependent value from `lighting(...)` output `p`."""
        from mathutils import Vector

        sun = Vector(tuple(p["sun_dir"]))
        self._sun_obj.rotation_euler = sun.to_track_quat("Z", "Y").to_euler()
        self._sun.energy = p["sun_strength"]
        self._sun.color = tuple(p["sun_color"])
        self._sun.angle = math.radians(p["sun_angle_deg"])
        self._moon_obj.rotation_euler = Vector(tuple(p["moon_dir"])).to_track_quat("Z", "Y").to_euler()
        self._moon.energy = p["moon_strength"]
        for axis, v in zip(("sun_x", "sun_y", "sun_z"), p["sun_dir"]):
            self.set(axis, v)
        for key in ("zenith", "horizon", "glow", "cloud_color"):
            self.set(key, p[key])
        self.set("cloud_cover", p["cloud_cover"])
        self.set("overcast", p["overcast"])
        self.set("wetness", p["wetness"])
        self.set("puddle_threshold", p["puddle_threshold"])
        lamps, vlights = p["lamps"], p["vehicle_lights"]
        for i, obj in enumerate(self._lamp_pool):
            obj.data.energy = LAMP_POWER * lamps if i < lamps_used else 0.0
        self.set("lamp_emit", 25.0 * lamps)
        self.set("window_fraction", lit_window_fraction * p["window_lit"])
        self.set("window_emit", WINDOW_EMISSION * p["window_lit"])
        self.set("signal_emit", 3.0 + 5.0 * lamps)
        self.set("sign_emit", 0.0)
        for i, obj in enumerate(self._head_pool):
            obj.data.energy = HEADLIGHT_POWER * vlights if i < heads_used else 0.0
        self.set("headlight_emit", 30.0 * vlights)
        self.set("taillight_emit", 0.3 + 10.0 * vlights)
        density = p["extinction"]
        volume = self.fog_model == "volume"
        self.set("fog_density", density if volume else 0.0)
        self.set("fog_on", 1.0 if volume and density > 0.0 else 0.0)
        # clear air skips the compositor: a clear image is the plain render
        self._bpy.context.scene.render.use_compositing = not volume and density > 0.0
        self.set("fog_optical_depth", density * FOG_MIST_DEPTH)
        self.set("fog_color", p["fog_color"])
        self.set("fog_glow", min(1.0, FOG_GLOW * density))
        # halos spread farther in denser air
        self.set("fog_glow_size", min(1.0, 0.5 + FOG_GLOW_SPREAD * density))

    def place_pools(self, lamps: list[tuple], heads: list[tuple]) -> None:
        """Move the light pools: lamps[i] = location, heads[i] = (location, rotation); the rest park
        under the ground (switched off by `apply`, never removed)."""
        parked = ((0.0, 0.0, -50.0), (0.0, 0.0, 0.0))
        for i, obj in enumerate(self._lamp_pool):
            obj.location = lamps[i] if i < len(lamps) else parked[0]
            obj.rotation_euler = parked[1]
        for i, obj in enumerate(self._head_pool):
            obj.location, obj.rotation_euler = heads[i] if i < len(heads) else parked


__all__ = ["FOG_MODELS", "Shading", "lighting", "sun_transmittance", "sun_vector"]
