"""A fast numpy ray-caster of a straight street: the offline backend for smoke runs and tests.

It renders the same descriptor under any condition with exact labels in milliseconds, so the stage
graph can be exercised end to end on machines without GTA V or Blender. Geometry (road, sidewalks,
facades, poles, trees, objects) depends only on the descriptor; conditions change light, sky, fog,
wetness and rain streaks.
"""
from __future__ import annotations

import hashlib
import math
from typing import Any

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX
from pairedgta.conditions import Condition
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.scene.descriptor import SceneDescriptor

CID = {name: i for i, name in enumerate(CLASS_NAMES)}
# width, height (m) of each category's billboard
OBJECT_SIZE = {
    "car": (1.8, 1.5), "truck": (2.4, 3.2), "bus": (2.6, 3.3), "motorcycle": (0.8, 1.2),
    "bicycle": (0.6, 1.1), "person": (0.6, 1.75), "rider": (0.7, 1.8),
}
BASE_COLOR = {
    "road": (90, 88, 92), "sidewalk": (170, 160, 150), "building": (150, 120, 100),
    "pole": (110, 110, 115), "vegetation": (60, 110, 40), "terrain": (120, 150, 70),
    "traffic sign": (230, 210, 30), "sky": (120, 170, 230),
}


def _stable_seed(*parts: Any) -> int:
    digest = hashlib.sha256("|".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little")


class SyntheticRenderer(Renderer):
    name = "synthetic"
    gives_labels = True

    def __init__(
        self,
        width: int = 256,
        height: int = 128,
        road_half_width: float = 3.5,
        sidewalk_width: float = 2.5,
        max_distance: float = 150.0,
        noise_std: float = 2.0,
    ) -> None:
        super().__init__(width, height)
        self.road_half = float(road_half_width)
        self.sidewalk = float(sidewalk_width)
        self.max_distance = float(max_distance)
        self.noise_std = float(noise_std)
        self._geometry: tuple[str, dict[str, np.ndarray]] | None = None

    # -- geometry: depends on the descriptor only ------------------------------------------------
    def prepare(self, descriptor: SceneDescriptor) -> None:
        self._geometry = (descriptor.to_json(), self._build(descriptor))

    def _build(self, d: SceneDescriptor) -> dict[str, np.ndarray]:
        W, H = self.width, self.height
        rng = np.random.default_rng(_stable_seed("geometry", d.seed, d.scene_id))
        cam = d.camera
        f = (W / 2) / math.tan(math.radians(cam.fov) / 2)
        u = (np.arange(W) + 0.5 - W / 2) / f
        v = (H / 2 - (np.arange(H) + 0.5)) / f + math.tan(math.radians(cam.rot_x))
        xr, yu = np.meshgrid(u, v)  # right and up components of the ray for forward = 1
        depth = np.full((H, W), np.inf)
        labels = np.full((H, W), CID["sky"], dtype=np.uint8)
        instances = np.zeros((H, W), dtype=np.uint16)
        shade = np.ones((H, W))
        cam_h, cam_x = cam.z, cam.x
        setback = self.road_half + self.sidewalk
        # ground plane
        with np.errstate(divide="ignore"):
            t_ground = np.where(yu < 0, cam_h / -yu, np.inf)
        lateral = cam_x + xr * t_ground
        ground = np.isfinite(t_ground) & (t_ground < self.max_distance)
        absl = np.abs(lateral)
        verge = 1.5 + rng.uniform(0, 3)
        labels[ground] = CID["terrain"]
        labels[ground & (absl < setback + verge)] = CID["sidewalk"]
        labels[ground & (absl < self.road_half)] = CID["road"]
        with np.errstate(invalid="ignore"):
            marking = ground & (np.abs(lateral) < 0.08) & (np.nan_to_num(t_ground, posinf=0.0) % 9.0 < 4.5)
        shade[marking] = 2.4
        depth[ground] = t_ground[ground]
        # facades: two side walls with per-segment heights, gaps filled by trees
        seg_len = 12.0
        n_seg = int(self.max_distance // seg_len) + 2
        wall_off = setback + verge
        for side in (-1.0, 1.0):
            heights = rng.uniform(6.0, 28.0, size=n_seg)
            kinds = rng.choice(["building", "building", "building", "vegetation"], size=n_seg)
            with np.errstate(divide="ignore", invalid="ignore"):
                t_w = (side * wall_off - cam_x) / xr
            valid = (t_w > 0) & np.isfinite(t_w) & (t_w < depth) & (t_w < self.max_distance)
            seg = np.clip((t_w / seg_len).astype(int, copy=False), 0, n_seg - 1)
            z = cam_h + yu * t_w
            top = heights[seg] * np.where(kinds[seg] == "vegetation", 0.35, 1.0)
            hit = valid & (z >= 0) & (z <= top)
            for kind in ("building", "vegetation"):
                m = hit & (kinds[seg] == kind)
                labels[m] = CID[kind]
                depth[m] = t_w[m]
            # windows: darker cells on facades
            win = hit & (kinds[seg] == "building") & ((z % 3.0) > 1.2) & ((t_w % 3.0) > 1.5)
            shade[win] = 0.55
        # poles with signs every 25 m on the right kerb
        for k, fwd in enumerate(np.arange(10.0, self.max_distance, 25.0)):
            px = self.road_half + 0.4 - cam_x
            cx = W / 2 + f * px / fwd
            half = max(0.5, f * 0.12 / fwd)
            top_v = H / 2 - f * (7.0 - cam_h) / fwd - f * math.tan(math.radians(cam.rot_x))
            bot_v = H / 2 + f * cam_h / fwd - f * math.tan(math.radians(cam.rot_x))
            cols = slice(max(0, int(cx - half)), min(W, int(math.ceil(cx + half))))
            rows = slice(max(0, int(top_v)), min(H, int(bot_v)))
            region = depth[rows, cols] > fwd
            labels[rows, cols][region] = CID["pole"]
            depth[rows, cols][region] = fwd
            if k % 2 == 0:
                sh = max(1.0, f * 0.4 / fwd)
                srows = slice(max(0, int(top_v)), min(H, int(top_v + 2 * sh)))
                scols = slice(max(0, int(cx - sh)), min(W, int(math.ceil(cx + sh))))
                region = depth[srows, scols] > fwd - 0.1
                labels[srows, scols][region] = CID["traffic sign"]
                depth[srows, scols][region] = fwd - 0.1
        # dynamic objects, far to near so nearer ones overwrite
        obj_color = np.zeros((H, W, 3))
        is_obj = np.zeros((H, W), dtype=bool)
        lights = []
        order = sorted(range(len(d.objects)), key=lambda i: -d.objects[i].forward)
        for i in order:
            o = d.objects[i]
            if o.forward <= 0.5:
                continue
            w, h = OBJECT_SIZE[o.category]
            fwd = o.forward
            cx = W / 2 + f * (o.right - cam_x) / fwd
            half = f * w / 2 / fwd
            top_v = H / 2 - f * (o.up + h - cam_h) / fwd - f * math.tan(math.radians(cam.rot_x))
            bot_v = H / 2 - f * (o.up - cam_h) / fwd - f * math.tan(math.radians(cam.rot_x))
            rows = slice(max(0, int(top_v)), max(0, min(H, int(math.ceil(bot_v)))))
            cols = slice(max(0, int(cx - half)), max(0, min(W, int(math.ceil(cx + half)))))
            if rows.start >= rows.stop or cols.start >= cols.stop:
                continue
            region = depth[rows, cols] > fwd
            labels[rows, cols][region] = CID[o.category]
            instances[rows, cols][region] = i + 1
            depth[rows, cols][region] = fwd
            obj_color[rows, cols][region] = o.color
            is_obj[rows, cols][region] = True
            if o.category in ("car", "truck", "bus", "motorcycle"):
                lights.append((int((rows.start + rows.stop) * 0.5 + (rows.stop - rows.start) * 0.2), cols))
        albedo = np.zeros((H, W, 3))
        for name, rgb in BASE_COLOR.items():
            albedo[labels == CID[name]] = rgb
        albedo[is_obj] = obj_color[is_obj]
        texture = rng.normal(1.0, 0.06, size=(H, W))
        labels[~np.isfinite(depth) & (labels != CID["sky"])] = IGNORE_INDEX
        return {
            "labels": labels, "instances": instances, "depth": depth, "albedo": albedo,
            "shade": shade * texture, "lights": np.array(lights, dtype=object), "yu": yu,
        }

    # -- condition-wise rendering: light, sky, weather ----------------------------------------
    def render(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        key = descriptor.to_json()
        if self._geometry is None or self._geometry[0] != key:
            self.prepare(descriptor)
        assert self._geometry is not None
        g = self._geometry[1]
        labels, depth = g["labels"], g["depth"]
        sky = labels == CID["sky"]
        elev = condition.sun_elevation_deg
        day = float(np.clip((elev + 6.0) / 30.0, 0.0, 1.0))
        warm = float(np.clip(1.0 - abs(elev - 4.0) / 12.0, 0.0, 1.0))
        light = 0.10 + 0.90 * day
        light *= 1.0 - 0.35 * condition.cloud_cover
        tint = np.array([1.0, 1.0, 1.0]) * (1 - warm) + np.array([1.15, 0.82, 0.55]) * warm
        if day < 0.05:
            tint = np.array([0.75, 0.8, 1.1])
        img = g["albedo"] * g["shade"][..., None] * light * tint
        # wet surfaces: darker, with sky reflections on the road
        road = (labels == CID["road"]) | (labels == CID["sidewalk"])
        wet = condition.wetness
        img[road] *= 1.0 - 0.35 * wet
        # sky model
        yu = g["yu"]
        grad = np.clip(yu * 2.0, 0, 1)[..., None]
        day_sky = np.array([150, 190, 240]) * (1 - grad) + np.array([60, 110, 200]) * grad
        sunset_sky = np.array([250, 160, 90]) * (1 - grad) + np.array([90, 90, 150]) * grad
        night_sky = np.array([15, 18, 35]) * np.ones_like(grad)
        sky_rgb = day * ((1 - warm) * day_sky + warm * sunset_sky) + (1 - day) * night_sky
        grey = sky_rgb.mean(axis=-1, keepdims=True)
        sky_rgb = (1 - condition.cloud_cover) * sky_rgb + condition.cloud_cover * grey * 0.9
        img[sky] = sky_rgb[sky]
        img[road] += wet * 0.25 * sky_rgb[road]
        # night: street lamps and vehicle lights
        if day < 0.3:
            H, W = labels.shape
            t = np.where(np.isfinite(depth), depth, 1e3)
            lamp = np.zeros((H, W))
            for fwd in np.arange(10.0, self.max_distance, 25.0):
                lamp += np.exp(-((t - fwd) ** 2) / 18.0)
            img += (0.3 - day) / 0.3 * (lamp[..., None] * np.array([255, 200, 120]) * 0.45) * (~sky)[..., None]
            for row, cols in g["lights"]:
                if 0 <= row < H:
                    img[max(0, row - 1) : row + 2, cols] = (255, 240, 200)
        # fog: exponential attenuation towards the fog colour
        if condition.extinction_per_m > 0:  # fog, mist and rain haze (conditions.py: Koschmieder)
            trans = condition.transmittance(depth)[..., None]
            fog_rgb = np.array([200, 200, 205]) * (0.12 + 0.88 * light)
            img = img * trans + fog_rgb * (1 - trans)
        rng = np.random.default_rng(_stable_seed("condition", descriptor.seed, condition.name))
        if condition.rain_level > 0:
            H, W = labels.shape
            n = int(condition.rain_level * W * H / 60)
            ys = rng.integers(0, H, n)
            xs = rng.integers(0, W, n)
            for dy in range(4):
                yy = np.clip(ys + dy, 0, H - 1)
                img[yy, xs] = img[yy, xs] * 0.6 + 0.4 * np.array([200, 200, 210]) * light
        img = img + rng.normal(0, self.noise_std, size=img.shape)
        image = np.clip(img, 0, 255).astype(np.uint8)
        state = {
            "entities": [
                {"category": o.category, "forward": o.forward, "right": o.right, "heading": o.heading}
                for o in descriptor.objects
            ],
            "weather": condition.weather,
            "clock": [condition.clock_hour, condition.clock_minute],
        }
        return RenderResult(image=image, labels=labels.copy(), instances=g["instances"].copy(), state=state,
                            distance=depth.astype(np.float32))
