"""Cycles backend: a procedural town rendered through `bpy`, with exact per-pixel labels.

Pairing: `prepare` builds geometry once; `render` changes only values (light energies and
directions, world, fog density, material parameters), never which objects or lights exist, so the
BVH is reused (persistent data), labels cannot drift between conditions, and an image depends on
(descriptor, condition) alone: Cycles' sampling sequence follows its light list, which is why
lamps and head lights come from fixed pools and switched-off things get zero values, not hidden.
Labels come from a separate 1-sample pass (labels.py). Fog and rain haze are analytic by default
(the compositor blends toward the in-scattered light by exp(-extinction * distance), materials.py);
`fog_model=volume` path-traces a scattering box instead (light beams, noisier at 2 samples).

bpy is imported lazily so this package (and the numpy mesh helpers) import without it. bpy keeps one
global scene per process, so only one BlenderRenderer owns it at a time; another instance that is
used later re-opens and rebuilds.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.conditions import Condition
from pairedgta import interrupt
from pairedgta.errors import ConfigError, RendererError
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.render.blender.geometry import OBJECT_MATERIAL, TOWN_MATERIAL, mesh_object
from pairedgta.render.camera import Camera
from pairedgta.render.blender.labels import MAX_INSTANCES, label_code, render_label_pass
from pairedgta.render.blender.materials import FOG_MODELS, Shading, lighting
from pairedgta.render.blender.models import model_parts
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.town import ProceduralTownRegion


@contextlib.contextmanager
def _quiet_stdout():
    """Silence C-level stdout (file descriptor 1) for the duration; errors still raise."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no usable stdout: nothing to silence
        yield
        return
    with open(os.devnull, "wb") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


_OWNER: BlenderRenderer | None = None
_SESSIONS = 0



@contextlib.contextmanager
def _quiet_cuda_probe(active: bool):
    """Blender's C code prints to file descriptor 1, and Cycles' CUDA probe prints "CUEW initialization
    failed" on every machine without the CUDA driver: noise when rendering on the CPU. The block's output
    goes through a temporary file and every other line is passed on."""
    if not active:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 1)
        try:
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
            tmp.seek(0)
            kept = [line for line in tmp.read().decode(errors="replace").splitlines(keepends=True) if "CUEW" not in line]
            if kept:
                sys.stdout.write("".join(kept))
                sys.stdout.flush()

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
                 fog_model: str = "analytic") -> None:
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
            try:
                import bpy
            except ImportError as exc:
                ver = f"{sys.version_info.major}.{sys.version_info.minor}"
                hint = "" if ver == "3.11" else f" (bpy 5.0 wheels need Python 3.11; this is Python {ver})"
                raise RendererError(
                    f"renderer.backend=blender needs the bpy module ({exc}){hint}; "
                    "install it with: pip install bpy==5.0.1 'numpy<2'"
                ) from None
            self._bpy = bpy
        return self._bpy

    def _ensure_open(self) -> None:
        if _OWNER is not self or self._bpy is None:
            self.open()

    # ---- scene setup ----------------------------------------------------------------------
    def _setup_scene(self) -> None:
        bpy = self._bpy
        sc = bpy.context.scene
        sc.render.engine = "CYCLES"
        cy = sc.cycles
        if self.device == "GPU":
            self._enable_gpu()
        cy.device = self.device
        cy.samples = self.samples
        cy.use_adaptive_sampling = False
        cy.use_denoising = self.denoise
        if self.denoise:
            with _quiet_cuda_probe(self.device == "CPU"):  # choosing the denoiser probes every GPU library
                cy.denoiser = "OPENIMAGEDENOISE"
            cy.denoising_prefilter = "FAST"
            cy.denoising_quality = self.denoiser_quality
            cy.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        cy.max_bounces = self.max_bounces
        cy.diffuse_bounces = min(self.max_bounces, 1)
        cy.glossy_bounces = min(self.max_bounces, 2)
        cy.transmission_bounces = min(self.max_bounces, 1)
        cy.volume_bounces = 0
        cy.transparent_max_bounces = 4
        cy.caustics_reflective = False
        cy.caustics_refractive = False
        cy.use_fast_gi = self.fast_gi
        cy.fast_gi_method = "REPLACE"
        cy.ao_bounces_render = 1
        cy.use_light_tree = self.light_tree
        cy.seed = self.seed
        cy.use_animated_seed = False
        cy.sample_clamp_direct = 0.0
        cy.sample_clamp_indirect = 10.0
        cy.filter_width = self.filter_width
        cy.volume_step_rate = self.volume_step_rate
        cy.use_auto_tile = False
        r = sc.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = self.width, self.height, 100
        r.use_persistent_data = True
        r.threads_mode = "FIXED" if self.threads else "AUTO"
        if self.threads:
            r.threads = self.threads
        r.dither_intensity = 0.0
        r.use_file_extension = True
        try:
            sc.view_settings.view_transform = self.camera.view_transform
            sc.view_settings.look = self.camera.look
        except TypeError as exc:
            raise ConfigError(f"camera.view_transform/look: {exc}; use e.g. camera.view_transform=AgX camera.look=None") from None
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

    def _enable_gpu(self) -> None:
        prefs = self._bpy.context.preferences.addons["cycles"].preferences
        for kind in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
            try:
                prefs.compute_device_type = kind
            except TypeError:
                continue
            prefs.refresh_devices()
            devices = [d for d in prefs.devices if d.type == kind]
            if devices:
                for d in prefs.devices:
                    d.use = d.type == kind
                return
        raise ConfigError("renderer.device=GPU but Cycles finds no GPU on this machine; set renderer.device=CPU")


    # ---- geometry -------------------------------------------------------------------------
    def _mesh_object(self, name: str, parts, materials: list[Any], pass_index: int, collection) -> Any:
        return mesh_object(self._bpy, name, parts, materials, pass_index, collection)

    def _add_entity(self, name: str, instance: int, parts, spots, xy, z: float, yaw: float) -> list[tuple]:
        """Mesh objects of one entity (one per label, all with its instance id) placed at (xy, z)
        facing `yaw`; returns its head-light spots in world coordinates."""
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        by_label: dict[str, list[tuple[str, str, tuple]]] = {}
        for label, shape, material, row in parts:
            by_label.setdefault(label, []).append((shape, material, row))
        for label, items in by_label.items():
            slots = sorted({OBJECT_MATERIAL[m] for _, m, _ in items})
            grouped: dict[tuple[str, int], list[tuple]] = {}
            for shape, material, row in items:
                grouped.setdefault((shape, slots.index(OBJECT_MATERIAL[material])), []).append(row)
            mesh_parts = []
            for (shape, slot), rows in grouped.items():
                arr = np.array(rows, dtype=np.float64)
                lx, ly = arr[:, 0].copy(), arr[:, 1].copy()
                arr[:, 0] = xy[0] + lx * c - ly * s
                arr[:, 1] = xy[1] + lx * s + ly * c
                arr[:, 2] += z
                arr[:, 6] += yaw
                mesh_parts.append((shape, arr, slot))
            obj = self._mesh_object(f"{name}_{label}", mesh_parts, [self._shading.materials[m] for m in slots],
                                    label_code(label, instance), self._coll_scene)
            self._scene_meshes.append(obj.data)
        return [((xy[0] + sx * c - sy * s, xy[1] + sx * s + sy * c, z + sz), (math.radians(84.0), 0.0, math.radians(yaw)))
                for sx, sy, sz in spots]

    def _resolve_town(self, descriptor: SceneDescriptor) -> dict[str, Any]:
        extra = dict(descriptor.extra)
        params = dict(self.town_cfg)
        town_extra = extra.get("town")
        if isinstance(town_extra, Mapping):
            params.update(town_extra)
        elif "town_seed" in extra:
            params["town_seed"] = extra["town_seed"]
        kind = params.pop("type", "procedural_town")
        params.pop("town_seeds", None)  # the region's list of towns: each descriptor names its own town_seed
        if kind != "procedural_town":
            raise ConfigError(
                f"renderer=blender renders the procedural town but region.type is '{kind}'; "
                "use region=procedural_town (renderer.town follows the region config)"
            )
        return params

    def _build_town(self, params: dict[str, Any]) -> None:
        bpy = self._bpy
        key = tuple(sorted((k, repr(v)) for k, v in params.items()))
        if self._town_key == key:
            return
        t0 = time.perf_counter()
        for obj in list(self._coll_town.objects):
            data = obj.data
            bpy.data.objects.remove(obj, do_unlink=True)
            if isinstance(data, bpy.types.Mesh) and data.users == 0:
                bpy.data.meshes.remove(data)
        try:
            town = ProceduralTownRegion(**params)
        except TypeError as exc:
            raise ConfigError(f"renderer.town: {exc}; use the keys of conf/region/procedural_town.yaml") from None
        layout = town.layout()
        by_object: dict[tuple[str, str], list[tuple[str, np.ndarray]]] = {}
        for (shape, material, label), rows in layout.groups.items():
            bmat = TOWN_MATERIAL.get(material)
            if bmat is None:
                raise RendererError(f"town material '{material}' has no Blender material; add it to TOWN_MATERIAL in pairedgta/render/blender/geometry.py")
            by_object.setdefault((bmat, label), []).append((shape, rows))
        for (bmat, label), parts in sorted(by_object.items()):
            self._mesh_object(f"town_{bmat}_{label}", [(s, r, 0) for s, r in parts], [self._shading.materials[bmat]],
                              label_code(label), self._coll_town)
        # volume fog: one box over the whole town, built with it. Per-scene boxes would be rebuilt
        # between scenes, and Cycles' volume acceleration data then depends on the scene rendered before
        if self.fog_model == "volume":
            e = layout.road_half_length + self.fog_extent
            row = np.array([[0.0, 0.0, -1.0, 2 * e, 2 * e, self.fog_height, 0, 1, 1, 1, 0]])
            self._mesh_object("fog", [("box", row, 0)], [self._shading.materials["fog"]], 0, self._coll_town)
        self._town, self._town_key = town, key
        self.timings["town_build"] = time.perf_counter() - t0

    def _clear_scene_objects(self) -> None:
        bpy = self._bpy
        for obj in list(self._coll_scene.objects):
            bpy.data.objects.remove(obj, do_unlink=True)
        for me in self._scene_meshes:
            if me.users == 0:
                bpy.data.meshes.remove(me)
        self._scene_meshes = []

    def _place_camera(self, d: SceneDescriptor) -> np.ndarray:
        loc, cam = d.location, d.camera
        h = math.radians(loc.heading)
        fwd = np.array([-math.sin(h), math.cos(h), 0.0])
        right = np.array([math.cos(h), math.sin(h), 0.0])
        pos = np.array([loc.x, loc.y, loc.z]) + right * cam.x + fwd * cam.y + np.array([0, 0, cam.z])
        if not (0.0 < cam.fov < 179.0):
            raise RendererError(f"descriptor.camera.fov={cam.fov} is invalid; use a horizontal FOV in (0, 179) degrees")
        self._camera.location = tuple(pos)
        # Blender cameras look down -z: +90 deg about x looks along +y, then heading/yaw about z
        self._camera.rotation_euler = (
            math.radians(90.0 + cam.rot_x), math.radians(cam.rot_y), math.radians(loc.heading + cam.rot_z))
        self._camera.data.angle = math.radians(cam.fov)
        return pos

    def prepare(self, descriptor: SceneDescriptor) -> None:
        self._ensure_open()
        t0 = time.perf_counter()
        self.timings = {"town_build": 0.0, "label_pass": 0.0}
        self._prepared = None  # a failure below leaves no half-built scene that looks prepared
        params = self._resolve_town(descriptor)
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
        self._clear_scene_objects()
        cam_pos = self._place_camera(descriptor)
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
        h = math.radians(loc.heading)
        fwd = np.array([-math.sin(h), math.cos(h)])
        right = np.array([math.cos(h), math.sin(h)])
        ground_ego = town.ground_height(loc.x, loc.y)
        placed = []
        heads: list[tuple[tuple, tuple]] = []
        for k, ob in enumerate(descriptor.objects, start=1):
            xy = np.array([loc.x, loc.y]) + fwd * ob.forward + right * ob.right
            z = loc.z + ob.up + town.ground_height(*xy) - ground_ego
            yaw = loc.heading + ob.heading
            parts, spots = model_parts(ob.category, ob.model, ob.color, ob.secondary_color)
            heads += self._add_entity(f"obj{k}", k, parts, spots, xy, z, yaw)
            placed.append({"instance": k, "category": ob.category, "x": round(float(xy[0]), 3),
                           "y": round(float(xy[1]), 3), "z": round(float(z), 3), "heading": round(yaw % 360.0, 3)})
        # the ambient population (descriptor.ambient): instance ids after the dynamic objects;
        # moving traffic near the camera gets the remaining head-light spots, nearest first
        lit_ambient: list[tuple[float, int, list]] = []
        first = len(descriptor.objects) + 1
        for j, e in enumerate(descriptor.ambient):
            xy = np.array([e.x, e.y])
            parts, spots = model_parts(e.category, e.model, e.color, e.secondary_color, scale=e.scale, pose=e.pose,
                                       lit=e.role != "parked")
            world_spots = self._add_entity(f"amb{j:03d}", first + j, parts, spots, xy, town.ground_height(*xy),
                                           e.heading)
            if world_spots:
                lit_ambient.append((float(np.hypot(*(xy - cam_pos[:2]))), j, world_spots))
        for dist, _, spots in sorted(lit_ambient, key=lambda t: (t[0], t[1])):
            if dist < self.headlight_radius:
                heads += spots
        heads = heads[: self.max_headlights]  # beyond the pool, further vehicles stay unlit
        # street-lamp lights near the camera only: farther lamps light nothing that is visible
        # (their glowing heads stay, as geometry), and each light costs time at every shading point
        lamps = town.layout().lamps
        chosen: list[int] = []
        if len(lamps):
            dist = np.hypot(lamps[:, 0] - cam_pos[0], lamps[:, 1] - cam_pos[1])
            behind = (lamps[:, 0] - cam_pos[0]) * fwd[0] + (lamps[:, 1] - cam_pos[1]) * fwd[1]
            near = np.flatnonzero((dist < self.lamp_radius) & (behind > -25.0))
            chosen = near[np.argsort(dist[near], kind="stable")][: self.max_lamps].tolist()
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
        p = lighting(cond)
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
        with _quiet_stdout(), interrupt.deferred():  # Blender prints a "Saved: ..." line per render
            self._bpy.ops.render.render(write_still=True)
        if not os.path.exists(path):
            raise RendererError(f"Cycles wrote no image to {path}; check free space in {self._tmp}")

    def _render_labels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return render_label_pass(self._bpy, self._shading, self._render_to, self._tmp or tempfile.gettempdir())

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
                w, h = frame.size
                px = np.empty(w * h * frame.channels, dtype=np.float32)
                frame.pixels.foreach_get(px)
                px = px.reshape(h, w, frame.channels)
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
