"""Shading: the materials, sky, fog and light pools of one bpy session, and how a condition sets them.

`build` creates every node tree and light once; `apply` sets values only (knobs, light energies and
directions), never which objects or lights exist, so Cycles' scene (and its sampling sequence) stays
fixed between conditions and an image depends on (scene, condition) alone.
"""
from __future__ import annotations

import math
from typing import Any

from pairedgta.render.blender.atmosphere import (
    FOG_GLOW,
    FOG_GLOW_SPREAD,
    FOG_MIST_DEPTH,
    build_fog_compositor,
    build_sky,
)
from pairedgta.render.blender.materials import build_materials
from pairedgta.render.blender.nodes import Knobs


class Shading:
    """Materials, world and lights of one bpy session, with their condition knobs."""

    def __init__(self, bpy, max_lamps: int, max_headlights: int, fog_model: str = "analytic") -> None:
        self._bpy = bpy
        self.fog_model = fog_model
        self.max_lamps = int(max_lamps)
        self.max_headlights = int(max_headlights)
        self.knobs = Knobs()
        self.materials: dict[str, Any] = {}

    def build(self) -> None:
        self.materials = build_materials(self._bpy, self.knobs)
        build_sky(self._bpy, self.knobs)
        self._build_lights()
        if self.fog_model == "analytic":
            build_fog_compositor(self._bpy, self.knobs)

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
        """Set every condition-dependent value from `p`, the output of illumination.lighting."""
        from mathutils import Vector

        sun = Vector(tuple(p["sun_dir"]))
        self._sun_obj.rotation_euler = sun.to_track_quat("Z", "Y").to_euler()
        self._sun.energy = p["sun_strength"]
        self._sun.color = tuple(p["sun_color"])
        self._sun.angle = math.radians(p["sun_angle_deg"])
        self._moon_obj.rotation_euler = Vector(tuple(p["moon_dir"])).to_track_quat("Z", "Y").to_euler()
        self._moon.energy = p["moon_strength"]
        for axis, v in zip(("sun_x", "sun_y", "sun_z"), p["sun_dir"]):
            self.knobs.set(axis, v)
        for key in ("zenith", "horizon", "glow", "cloud_color"):
            self.knobs.set(key, p[key])
        self.knobs.set("cloud_cover", p["cloud_cover"])
        self.knobs.set("overcast", p["overcast"])
        self.knobs.set("wetness", p["wetness"])
        self.knobs.set("puddle_threshold", p["puddle_threshold"])
        lamps = p["lamps"]
        for i, obj in enumerate(self._lamp_pool):
            obj.data.energy = p["lamp_power"] if i < lamps_used else 0.0
        self.knobs.set("lamp_emit", p["lamp_emit"])
        self.knobs.set("window_fraction", lit_window_fraction * p["window_lit"])
        self.knobs.set("window_emit", p["window_emit"])
        self.knobs.set("signal_emit", 3.0 + 5.0 * lamps)
        self.knobs.set("sign_emit", 0.0)
        for i, obj in enumerate(self._head_pool):
            obj.data.energy = p["headlight_power"] if i < heads_used else 0.0
        self.knobs.set("headlight_emit", p["headlight_emit"])
        self.knobs.set("taillight_emit", p["taillight_emit"])
        self.knobs.set("fill", p["fill"])
        density = p["extinction"]
        volume = self.fog_model == "volume"
        self.knobs.set("fog_density", density if volume else 0.0)
        self.knobs.set("fog_on", 1.0 if volume and density > 0.0 else 0.0)
        # clear air skips the compositor: a clear image is the plain render
        self._bpy.context.scene.render.use_compositing = not volume and density > 0.0
        self.knobs.set("fog_optical_depth", density * FOG_MIST_DEPTH)
        self.knobs.set("fog_color", p["fog_color"])
        self.knobs.set("fog_glow", min(1.0, FOG_GLOW * density))
        # halos spread farther in denser air
        self.knobs.set("fog_glow_size", min(1.0, 0.5 + FOG_GLOW_SPREAD * density))

    def place_pools(self, lamps: list[tuple], heads: list[tuple]) -> None:
        """Move the light pools: lamps[i] = location, heads[i] = (location, rotation); the rest park
        under the ground (switched off by `apply`, never removed)."""
        parked = ((0.0, 0.0, -50.0), (0.0, 0.0, 0.0))
        for i, obj in enumerate(self._lamp_pool):
            obj.location = lamps[i] if i < len(lamps) else parked[0]
            obj.rotation_euler = parked[1]
        for i, obj in enumerate(self._head_pool):
            obj.location, obj.rotation_euler = heads[i] if i < len(heads) else parked


__all__ = ["Shading"]
