"""Cycles backend: a procedural town rendered through `bpy`, with exact per-pixel labels.

Pairing: `prepare` builds geometry once (scene.py); `render` changes only values (light energies and
directions, world, fog density, material parameters: shading.py), never which objects or lights exist,
so the BVH is reused (persistent data), labels cannot drift between conditions, and an image depends on
(descriptor, condition) alone: Cycles' sampling sequence follows its light list, which is why
lamps and head lights come from fixed pools and switched-off things get zero values, not hidden.
Labels come from a separate 1-sample pass (labels.py). Fog and rain haze are analytic by default
(the compositor blends toward the in-scattered light by exp(-extinction * distance), atmosphere.py);
`fog_model=volume` path-traces a scattering box instead (light beams, noisier at 2 samples).

bpy is imported lazily (cycles.py) so this package (and the numpy mesh helpers) import without it. bpy
keeps one global scene per process, so only one BlenderRenderer owns it at a time; another instance
that is used later re-opens and rebuilds.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta import interrupt
from pairedgta.conditions import Condition
from pairedgta.errors import ConfigError, RendererError
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.render.blender.atmosphere import FOG_MODELS
from pairedgta.render.blender.cycles import configure_cycles, image_pixels, import_bpy, quiet_stdout
from pairedgta.render.blender.illumination import NIGHT, SUNSET, NightLight, SunsetLight, lighting
from pairedgta.render.blender.labels import MAX_INSTANCES, render_label_pass
from pairedgta.render.blender.scene import (
    build_town,
    clear_entities,
    nearby_lamps,
    place_camera,
    place_entities,
    resolve_town,
)
from pairedgta.render.blender.shading import Shading
from pairedgta.render.camera import Camera
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.town import ProceduralTownRegion

_OWNER: BlenderRenderer | None = None
_SESSIONS = 0


class BlenderRenderer(Renderer):
    """Cycles renderer of the procedural town (CPU by default)."""

    name = "blender"
    gives_labels = True

    def __init__(self, width: int = 512, height: int = 256, samples: int = 2, device: str = "CPU",
                 denoise: bool = True, denoiser_quality: str = "FAST", max_bounces: int = 2,
                 fast_gi: bool = True, town: Mapping[str, Any] | None = None, seed: int = 0,
                 camera: Mapping[str, Any] | None = None, threads: int = 0, fog_extent: float = 220.0,
                 fog_height: float = 45.0, volume_step_rate: float = 4.0,
                 filter_width: float = 1.5,
                 labels_per_condition: bool = False, light_tree: bool = False, lamp_radius: float = 120.0,
                 max_lamps: int = 48, max_headlights: int = 24, headlight_radius: float = 45.0,
                 fog_model: str = "analytic", night: Mapping[str, Any] | None = None,
                 sunset: Mapping[str, Any] | None = None) -> None:
        super().__init__(width, height)
        checks = (
            ("width", self.width >= 8, ">= 8"), ("height", self.height >= 8, ">= 8"),
            ("samples", int(samples) >= 1, ">= 1"), ("max_bounces", int(max_bounces) >= 0, ">= 0"),
            ("device", str(device).upper() in ("CPU", "GPU"), "CPU or GPU"),
            ("denoiser_quality", str(denoiser_quality).upper() in ("FAST", "BALANCED", "HIGH"),
             "FAST, BALANCED or HIGH"),
            ("threads", int(threads) >= 0, ">= 0 (0 = all cores)"),
            ("fog_model", str(fog_model) in FOG_MODELS, " or ".join(FOG_MODELS)),
        )
        for key, ok, want in checks:
            if not ok:
                raise ConfigError(f"renderer.{key} is invalid; set it {want}")
        self.samples = int(samples)
        self.device = str(device).upper()
        self.denoise = bool(denoise)
        self.denoiser_quality = str(denoiser_quality).upper()
        self.max_bounces = int(max_bounces)
        self.fast_gi = bool(fast_gi)
        self.town_cfg = dict(town or {})
        if self.town_cfg.get("type", "procedural_town") != "procedural_town":
            raise ConfigError(
                f"renderer=blender renders the procedural town but region.type is '{self.town_cfg['type']}'; "
                "use region=procedural_town (renderer.town follows the region config)"
            )
        self.seed = int(seed)
        self.camera = Camera.from_cfg(camera)
        self.night = NightLight.from_cfg(night) if night is not None else NIGHT
        self.sunset = SunsetLight.from_cfg(sunset) if sunset is not None else SUNSET
        self.threads = int(threads)
        self.fog_model = str(fog_model)
        self.fog_extent = float(fog_extent)
        self.fog_height = float(fog_height)
        self.volume_step_rate = float(volume_step_rate)
        self.filter_width = float(filter_width)
        self.labels_per_condition = bool(labels_per_condition)
        self.light_tree = bool(light_tree)
        self.lamp_radius = float(lamp_radius)
        self.max_lamps = int(max_lamps)
        self.max_headlights = int(max_headlights)
        self.headlight_radius = float(headlight_radius)
        self.timings: dict[str, float] = {}
        self._bpy: Any = None
        self._tmp: str | None = None
        self._reset_state()

    def _reset_state(self) -> None:
        self._town: ProceduralTownRegion | None = None
        self._town_key: tuple | None = None
        self._prepared: SceneDescriptor | None = None
        self._labels: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._shading: Shading | None = None
        self._scene_meshes: list[Any] = []
        self._scene_state: dict[str, Any] = {}

    # ---- lifecycle ------------------------------------------------------------------------
    def open(self) -> None:
        global _OWNER
        bpy = self._import_bpy()
        if _OWNER is not None and _OWNER is not self:
            _OWNER._reset_state()
        _OWNER = self
        self._reset_state()
        self._free_persistent_data()
        bpy.ops.wm.read_factory_settings(use_empty=True)
        # a fresh scene name per session: Blender keeps a render engine per scene name, and Cycles'
        # persistent data keyed by datablock addresses would otherwise meet new datablocks at old
        # addresses and keep stale shaders
        global _SESSIONS
        _SESSIONS += 1
        bpy.context.scene.name = f"pairedgta_{os.getpid()}_{_SESSIONS}"
        self._tmp = self._tmp or tempfile.mkdtemp(prefix="pairedgta_blender_")
        self._setup_scene()

    def _restart_cycles_session(self) -> None:
        render = self._bpy.context.scene.render
        render.use_persistent_data = False  # frees the kept render engine and its synced scene
        render.use_persistent_data = True

    def _free_persistent_data(self) -> None:
        for scene in self._bpy.data.scenes:
            if scene.render.use_persistent_data:
                scene.render.use_persistent_data = False  # frees the kept render engine

    def close(self) -> None:
        global _OWNER
        if _OWNER is self and self._bpy is not None:
            self._free_persistent_data()
            self._bpy.ops.wm.read_factory_settings(use_empty=True)
            _OWNER = None
        self._reset_state()
        if self._tmp:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def _import_bpy(self):
        if self._bpy is None:
            self._bpy = import_bpy()
        return self._bpy

    def _ensure_open(self) -> None:
        if _OWNER is not self or self._bpy is None:
            self.open()

    # ---- scene setup ----------------------------------------------------------------------
    def _setup_scene(self) -> None:
        bpy = self._bpy
        configure_cycles(
            bpy, width=self.width, height=self.height, samples=self.samples, device=self.device,
            denoise=self.denoise, denoiser_quality=self.denoiser_quality, max_bounces=self.max_bounces,
            fast_gi=self.fast_gi, light_tree=self.light_tree, seed=self.seed, filter_width=self.filter_width,
            volume_step_rate=self.volume_step_rate, threads=self.threads,
            view_transform=self.camera.view_transform, look=self.camera.look)
        sc = bpy.context.scene
        self._coll_town = bpy.data.collections.new("town")
        self._coll_scene = bpy.data.collections.new("scene")
        sc.collection.children.link(self._coll_town)
        sc.collection.children.link(self._coll_scene)
        self._shading = Shading(bpy, self.max_lamps, self.max_headlights, self.fog_model)
        self._shading.build()
        self._lamps_used = self._heads_used = 0
        cam = bpy.data.cameras.new("camera")
        cam.sensor_fit = "HORIZONTAL"
        cam.clip_start, cam.clip_end = 0.1, 5000.0
        self._camera = bpy.data.objects.new("camera", cam)
        sc.collection.objects.link(self._camera)
        sc.camera = self._camera

    # ---- geometry -------------------------------------------------------------------------
    def _build_town(self, params: dict[str, Any]) -> None:
        key = tuple(sorted((k, repr(v)) for k, v in params.items()))
        if self._town_key == key:
            return
        t0 = time.perf_counter()
        self._town = build_town(self._bpy, self._coll_town, self._shading.materials, params, self.fog_model,
                                self.fog_extent, self.fog_height)
        self._town_key = key
        self.timings["town_build"] = time.perf_counter() - t0

    def prepare(self, descriptor: SceneDescriptor) -> None:
        self._ensure_open()
        t0 = time.perf_counter()
        self.timings = {"town_build": 0.0, "label_pass": 0.0}
        self._prepared = None  # a failure below leaves no half-built scene that looks prepared
        params = resolve_town(self.town_cfg, descriptor)
        self._build_town(params)
        town = self._town
        assert town is not None
        loc = descriptor.location
        surface = town.surface_at(loc.x, loc.y)
        if surface != "road":
            raise RendererError(
                f"scene {descriptor.scene_id}: ego at ({loc.x:.1f}, {loc.y:.1f}) is on '{surface}', not a road of "
                f"procedural town seed {town.town_seed}; sample locations with region procedural_town using the "
                "same town parameters as renderer.town"
            )
        t1 = time.perf_counter()
        # a new scene starts from a full sync, as in a fresh process: Cycles' persistent data, updated
        # incrementally from the previous scene's objects, gives slightly different images (a resumed
        # run would then differ from an uninterrupted one). Conditions of one scene still share it.
        self._restart_cycles_session()
        clear_entities(self._bpy, self._coll_scene, self._scene_meshes)
        self._scene_meshes = []
        cam_pos = place_camera(self._camera, descriptor)
        if town.obstacle_at(*cam_pos):
            raise RendererError(
                f"scene {descriptor.scene_id}: camera at "
                f"({cam_pos[0]:.1f}, {cam_pos[1]:.1f}, {cam_pos[2]:.1f}) is inside "
                "a building; move the ego onto a lane (region.sample_location) or reduce camera offsets"
            )
        if len(descriptor.objects) + len(descriptor.ambient) > MAX_INSTANCES:
            raise RendererError(
                f"scene {descriptor.scene_id}: {len(descriptor.objects)} objects + {len(descriptor.ambient)} ambient "
                f"entities; at most {MAX_INSTANCES} are supported; lower generate.objects.max or "
                "region.population.max_entities")
        placed, heads = place_entities(self._bpy, self._coll_scene, self._shading.materials, self._scene_meshes,
                                       descriptor, town, cam_pos, self.headlight_radius, self.max_headlights)
        lamps = town.layout().lamps
        chosen = nearby_lamps(lamps, cam_pos, loc.heading, self.lamp_radius, self.max_lamps)
        self._shading.place_pools([tuple(float(v) for v in lamps[i]) for i in chosen], heads)
        self._lamps_used, self._heads_used = len(chosen), len(heads)
        self._scene_state = {
            "camera": [round(float(v), 3) for v in cam_pos], "objects": placed,
            "ambient": dict(sorted(Counter(e.category for e in descriptor.ambient).items())),
            "town": town.params(), "surface": surface,
        }
        self.timings["scene_build"] = time.perf_counter() - t1
        self._prepared = descriptor
        self._labels = None
        if not self.labels_per_condition:
            t2 = time.perf_counter()
            self._labels = self._render_labels()
            self.timings["label_pass"] = time.perf_counter() - t2
        self.timings["prepare"] = time.perf_counter() - t0

    # ---- conditions -----------------------------------------------------------------------
    def _apply_condition(self, cond: Condition) -> dict[str, Any]:
        p = lighting(cond, self.night, self.sunset)
        p["exposure"] = self.camera.exposure(cond, p["light_level"])
        self._shading.apply(p, self._lamps_used, self._heads_used,
                            self._town.lit_window_fraction if self._town else 0.0)
        return p

    # ---- capture --------------------------------------------------------------------------
    def _render_to(self, path: str) -> None:
        sc = self._bpy.context.scene
        sc.render.filepath = path
        # Ctrl-C or SIGTERM during the render would be raised inside Cycles' Python callback, where
        # Blender prints it and renders on: recorded instead, and raised once the image is done
        with quiet_stdout(), interrupt.deferred():  # Blender prints a "Saved: ..." line per render
            self._bpy.ops.render.render(write_still=True)
        if not os.path.exists(path):
            raise RendererError(f"Cycles wrote no image to {path}; check free space in {self._tmp}")

    def _render_labels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return render_label_pass(self._bpy, self._shading.knobs, self._render_to, self._tmp or tempfile.gettempdir())

    def _render_beauty(self, ev: float, noise_seed: int) -> np.ndarray:
        """Scene-referred render (float EXR), then the camera: noise on the exposed signal, and the
        exposure and view transform applied by Blender's colour management on saving as 8-bit sRGB
        (the same OpenColorIO path as a direct 8-bit render: identical within one grey level)."""
        from PIL import Image

        bpy = self._bpy
        sc = bpy.context.scene
        img = sc.render.image_settings
        img.file_format, img.color_mode, img.color_depth, img.exr_codec = "OPEN_EXR", "RGB", "32", "NONE"
        tmp = self._tmp or tempfile.gettempdir()
        linear_path, path = os.path.join(tmp, "beauty.exr"), os.path.join(tmp, "beauty.png")
        self._render_to(linear_path)
        frame = bpy.data.images.load(linear_path, check_existing=False)
        try:
            if self.camera.noisy:
                px = image_pixels(frame)
                px[..., :3] = self.camera.add_noise(px[..., :3], ev, noise_seed)
                frame.pixels.foreach_set(px.ravel())
            sc.view_settings.exposure = ev
            img.file_format, img.color_mode, img.color_depth, img.compression = "PNG", "RGB", "8", 0
            frame.save_render(path, scene=sc)
        finally:
            bpy.data.images.remove(frame)
        if not os.path.exists(path):
            raise RendererError(f"the camera wrote no image to {path}; check free space in {tmp}")
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB")).copy()

    # ---- calibration (experiments/fit_night_light.py, fit_sunset_light.py) ---------------------------
    def render_linear(self, descriptor: SceneDescriptor, condition: Condition, night: NightLight | None = None,
                      atmosphere: bool = True, sunset: SunsetLight | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """The scene-referred image (H x W x 3 float32, top row first) of `descriptor` under `condition` with the
        night light `night` and the sunset light `sunset` (default: the renderer's), before the camera, and the
        condition's render parameters (lighting(), with the camera's `exposure`). `atmosphere=False` leaves out the
        analytic fog's compositor. Cycles is linear in every light's power, so images rendered with one light term
        at a time add up to the image with all of them (up to the denoiser): what the light fits rely on."""
        if _OWNER is not self or self._prepared is None or self._prepared != descriptor:
            self.prepare(descriptor)
        saved = self.night, self.sunset
        self.night, self.sunset = night or self.night, sunset or self.sunset
        try:
            p = self._apply_condition(condition)
        finally:
            self.night, self.sunset = saved
        bpy = self._bpy
        sc = bpy.context.scene
        if not atmosphere:
            sc.render.use_compositing = False
        img = sc.render.image_settings
        img.file_format, img.color_mode, img.color_depth, img.exr_codec = "OPEN_EXR", "RGB", "32", "NONE"
        path = os.path.join(self._tmp or tempfile.gettempdir(), "linear.exr")
        self._render_to(path)
        frame = bpy.data.images.load(path, check_existing=False)
        try:
            px = image_pixels(frame)
        finally:
            bpy.data.images.remove(frame)
        return px[::-1, :, :3].copy(), p

    def develop(self, linear: np.ndarray, ev: float) -> np.ndarray:
        """The camera's development of a scene-referred image (render_linear's): exposure `ev` and the view
        transform, to the 8-bit sRGB image `render` stores (identical for the same linear image; no sensor noise).
        Images stacked along the rows develop in one call."""
        from PIL import Image

        bpy = self._bpy
        sc = bpy.context.scene
        h, w = linear.shape[:2]
        frame = bpy.data.images.new("develop", w, h, alpha=False, float_buffer=True)
        path = os.path.join(self._tmp or tempfile.gettempdir(), "develop.png")
        try:
            rgba = np.ones((h, w, 4), dtype=np.float32)
            rgba[..., :3] = linear[::-1]
            frame.pixels.foreach_set(rgba.ravel())
            sc.view_settings.exposure = ev
            img = sc.render.image_settings
            img.file_format, img.color_mode, img.color_depth, img.compression = "PNG", "RGB", "8", 0
            frame.save_render(path, scene=sc)
        finally:
            bpy.data.images.remove(frame)
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB")).copy()

    def render(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        if _OWNER is not self or self._prepared is None or self._prepared != descriptor:
            self.prepare(descriptor)
        t0 = time.perf_counter()
        p = self._apply_condition(condition)
        image = self._render_beauty(p["exposure"], self.camera.seed_for(descriptor.seed, condition.name))
        t1 = time.perf_counter()
        if self.labels_per_condition or self._labels is None:
            labels, instances, distance = self._render_labels()
            if not self.labels_per_condition:
                self._labels = (labels, instances, distance)
        else:
            labels, instances, distance = self._labels
        t2 = time.perf_counter()
        self.timings["render"] = t1 - t0
        self.timings["labels"] = t2 - t1
        state = {
            **self._scene_state, "backend": "blender", "condition": condition.name,
            "exposure_ev": round(float(p["exposure"]), 4), "camera": self.camera.name,
            "light_level": round(float(p["light_level"]), 5), "samples": self.samples,
            "sun_strength": round(float(p["sun_strength"]), 4), "extinction_per_m": round(float(p["extinction"]), 5),
            "fog_model": self.fog_model,
            "seconds": round(t2 - t0, 4),
        }
        return RenderResult(image=image, labels=labels.copy(), instances=instances.copy(), state=state,
                            distance=distance.copy())



__all__ = ["BlenderRenderer"]
