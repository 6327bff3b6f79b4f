"""Scene construction: the procedural town, one scene's entities, its camera and which lights it uses.

The town is built once per town parameter set; a scene adds one mesh object per (label, instance),
so every pixel's label is fixed by data, and picks the street lamps and head-lights that get a spot
light from the fixed pools of shading.py.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.errors import ConfigError, RendererError
from pairedgta.render.blender.geometry import OBJECT_MATERIAL, TOWN_MATERIAL, mesh_object
from pairedgta.render.blender.labels import label_code
from pairedgta.render.blender.models import model_parts
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.town import ProceduralTownRegion


def resolve_town(town_cfg: Mapping[str, Any], descriptor: SceneDescriptor) -> dict[str, Any]:
    """The town parameters of one scene: renderer.town, overridden by the town the descriptor names."""
    extra = dict(descriptor.extra)
    params = dict(town_cfg)
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


def build_town(bpy, collection, materials: Mapping[str, Any], params: dict[str, Any], fog_model: str,
               fog_extent: float, fog_height: float) -> ProceduralTownRegion:
    """Replace the town in `collection` by the one `params` describe: one mesh per (material, label)."""
    for obj in list(collection.objects):
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
        mesh_object(bpy, f"town_{bmat}_{label}", [(s, r, 0) for s, r in parts], [materials[bmat]],
                    label_code(label), collection)
    # volume fog: one box over the whole town, built with it. Per-scene boxes would be rebuilt
    # between scenes, and Cycles' volume acceleration data then depends on the scene rendered before
    if fog_model == "volume":
        e = layout.road_half_length + fog_extent
        row = np.array([[0.0, 0.0, -1.0, 2 * e, 2 * e, fog_height, 0, 1, 1, 1, 0]])
        mesh_object(bpy, "fog", [("box", row, 0)], [materials["fog"]], 0, collection)
    return town


def clear_entities(bpy, collection, meshes: list[Any]) -> None:
    """Remove the previous scene's objects and the meshes nothing else uses."""
    for obj in list(collection.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    for me in meshes:
        if me.users == 0:
            bpy.data.meshes.remove(me)


def place_camera(camera, d: SceneDescriptor) -> np.ndarray:
    """Put the camera object at the descriptor's ego pose plus camera offsets; returns its position."""
    loc, cam = d.location, d.camera
    h = math.radians(loc.heading)
    fwd = np.array([-math.sin(h), math.cos(h), 0.0])
    right = np.array([math.cos(h), math.sin(h), 0.0])
    pos = np.array([loc.x, loc.y, loc.z]) + right * cam.x + fwd * cam.y + np.array([0, 0, cam.z])
    if not (0.0 < cam.fov < 179.0):
        raise RendererError(f"descriptor.camera.fov={cam.fov} is invalid; use a horizontal FOV in (0, 179) degrees")
    camera.location = tuple(pos)
    # Blender cameras look down -z: +90 deg about x looks along +y, then heading/yaw about z
    camera.rotation_euler = (
        math.radians(90.0 + cam.rot_x), math.radians(cam.rot_y), math.radians(loc.heading + cam.rot_z))
    camera.data.angle = math.radians(cam.fov)
    return pos


def add_entity(bpy, collection, materials: Mapping[str, Any], meshes: list[Any], name: str, instance: int,
               parts, spots, xy, z: float, yaw: float) -> list[tuple]:
    """Mesh objects of one entity (one per label, all with its instance id) placed at (xy, z)
    facing `yaw`, their meshes appended to `meshes`; returns its head-light spots in world coordinates."""
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
        obj = mesh_object(bpy, f"{name}_{label}", mesh_parts, [materials[m] for m in slots],
                          label_code(label, instance), collection)
        meshes.append(obj.data)
    return [((xy[0] + sx * c - sy * s, xy[1] + sx * s + sy * c, z + sz), (math.radians(84.0), 0.0, math.radians(yaw)))
            for sx, sy, sz in spots]


def place_entities(bpy, collection, materials: Mapping[str, Any], meshes: list[Any], descriptor: SceneDescriptor,
                   town: ProceduralTownRegion, cam_pos: np.ndarray, headlight_radius: float,
                   max_headlights: int) -> tuple[list[dict[str, Any]], list[tuple[tuple, tuple]]]:
    """The descriptor's dynamic objects (instances 1..n, on the ground relative to the ego) and its
    ambient population; returns the placed objects (for the render state) and the head-light spots
    that get a light, the objects' first, then moving traffic nearest the camera."""
    loc = descriptor.location
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
        heads += add_entity(bpy, collection, materials, meshes, f"obj{k}", k, parts, spots, xy, z, yaw)
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
        world_spots = add_entity(bpy, collection, materials, meshes, f"amb{j:03d}", first + j, parts, spots, xy,
                                 town.ground_height(*xy), e.heading)
        if world_spots:
            lit_ambient.append((float(np.hypot(*(xy - cam_pos[:2]))), j, world_spots))
    for dist, _, spots in sorted(lit_ambient, key=lambda t: (t[0], t[1])):
        if dist < headlight_radius:
            heads += spots
    return placed, heads[:max_headlights]  # beyond the pool, further vehicles stay unlit


def nearby_lamps(lamps: np.ndarray, cam_pos: np.ndarray, heading: float, lamp_radius: float,
                 max_lamps: int) -> list[int]:
    """Street lamps that get a light: near the camera and not far behind it, nearest first. Farther
    lamps light nothing that is visible (their glowing heads stay, as geometry), and each light costs
    time at every shading point."""
    if not len(lamps):
        return []
    h = math.radians(heading)
    fwd = np.array([-math.sin(h), math.cos(h)])
    dist = np.hypot(lamps[:, 0] - cam_pos[0], lamps[:, 1] - cam_pos[1])
    behind = (lamps[:, 0] - cam_pos[0]) * fwd[0] + (lamps[:, 1] - cam_pos[1]) * fwd[1]
    near = np.flatnonzero((dist < lamp_radius) & (behind > -25.0))
    return near[np.argsort(dist[near], kind="stable")][:max_lamps].tolist()


__all__ = ["add_entity", "build_town", "clear_entities", "nearby_lamps", "place_camera", "place_entities",
           "resolve_town"]
