"""Mesh templates and the numpy -> bpy mesh conversion shared by the town and the scene objects.

Templates live in a local frame (x right, y forward, z up; base centre at the origin). A primitive
row is (cx, cy, cz, sx, sy, sz, yaw, r, g, b, a) as in pairedgta.scene.town_primitives.COLUMNS; the renderer
turns groups of rows into one mesh per (label, instance), so every surface's label is fixed by data.
"""
from __future__ import annotations

from typing import Any

import numpy as np

# town material name (pairedgta.scene.town_geometry, town_primitives) -> Blender material
TOWN_MATERIAL = {
    "asphalt": "pavement", "marking": "pavement", "sidewalk": "pavement", "kerb": "pavement",
    "grass": "matte", "lot": "matte", "facade": "matte", "roof": "matte", "wall": "matte",
    "fence": "matte", "hedge": "matte", "foliage": "matte", "bark": "matte", "sign_back": "matte",
    "metal": "metal", "housing": "metal", "window": "window", "lamp": "lamp", "sign": "sign",
    "signal_red": "signal_red", "signal_amber": "signal_amber", "signal_green": "signal_green",
    "signal_off": "signal_off",
}
# object-model material name (models.py) -> Blender material
OBJECT_MATERIAL = {
    "paint": "paint", "glass": "glass", "rubber": "rubber", "trim": "metal", "metal": "metal",
    "matte": "matte", "headlight": "headlight", "taillight": "taillight",
    "headlight_off": "lens_clear", "taillight_off": "lens_red",  # parked vehicles: lights off
}


def _ring(n: int, radius: float = 0.5) -> np.ndarray:
    a = np.arange(n) * 2 * np.pi / n
    return np.stack([np.cos(a) * radius, np.sin(a) * radius], 1)


def _templates() -> dict[str, tuple[np.ndarray, list[list[int]]]]:
    t: dict[str, tuple[np.ndarray, list[list[int]]]] = {}
    box = np.array([[x, y, z] for z in (0, 1) for y in (-0.5, 0.5) for x in (-0.5, 0.5)], float)
    # vertex k: x bit 0, y bit 1, z bit 2
    t["box"] = (box, [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
    t["plane"] = (np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], float), [[0, 1, 2, 3]])
    t["panel"] = (np.array([[-0.5, 0, 0], [0.5, 0, 0], [0.5, 0, 1], [-0.5, 0, 1]], float), [[0, 3, 2, 1]])
    r = _ring(12)
    disc = np.stack([r[:, 0], np.zeros(12), r[:, 1] + 0.5], 1)
    t["disc"] = (disc, [list(range(12))])
    t["triangle"] = (np.array([[-0.5, 0, 0], [0.5, 0, 0], [0, 0, 1]], float), [[0, 2, 1]])
    n = 8
    r = _ring(n)
    cyl = np.concatenate([np.c_[r, np.zeros(n)], np.c_[r, np.ones(n)]])
    faces = [[k, (k + 1) % n, n + (k + 1) % n, n + k] for k in range(n)]
    faces += [list(range(n - 1, -1, -1)), list(range(n, 2 * n))]
    t["cylinder"] = (cyl, faces)
    # wheel: cylinder whose axis is local x, touching the ground
    n = 12
    r = _ring(n)
    wheel = np.concatenate([np.c_[np.full(n, x), r[:, 0], r[:, 1] + 0.5] for x in (-0.5, 0.5)])
    faces = [[k, n + k, n + (k + 1) % n, (k + 1) % n] for k in range(n)]
    faces += [list(range(n)), list(range(2 * n - 1, n - 1, -1))]
    t["xcyl"] = (wheel, faces)
    # bicycle wheel: a ring (square section) around local x
    outer, inner = _ring(n, 0.5), _ring(n, 0.43)
    verts = []
    for k in range(n):
        for ring in (outer, inner):
            for x in (-0.5, 0.5):
                verts.append([x, ring[k, 0], ring[k, 1] + 0.5])
    faces = []
    for k in range(n):
        a, b = 4 * k, 4 * ((k + 1) % n)  # a+0 outer-, a+1 outer+, a+2 inner-, a+3 inner+
        faces += [[a, a + 1, b + 1, b], [a + 2, b + 2, b + 3, a + 3],
                  [a, b, b + 2, a + 2], [a + 1, a + 3, b + 3, b + 1]]
    t["xring"] = (np.array(verts, float), faces)
    # ellipsoid
    seg, rings = 8, 6
    verts = [[0, 0, 0.0]]
    for i in range(1, rings):
        th = np.pi * i / rings
        for k in range(seg):
            ph = 2 * np.pi * k / seg
            verts.append([0.5 * np.sin(th) * np.cos(ph), 0.5 * np.sin(th) * np.sin(ph), 0.5 - 0.5 * np.cos(th)])
    verts.append([0, 0, 1.0])
    faces = [[0, 1 + (k + 1) % seg, 1 + k] for k in range(seg)]
    for i in range(rings - 2):
        base = 1 + i * seg
        faces += [[base + k, base + (k + 1) % seg, base + seg + (k + 1) % seg, base + seg + k] for k in range(seg)]
    top = len(verts) - 1
    base = 1 + (rings - 2) * seg
    faces += [[base + k, base + (k + 1) % seg, top] for k in range(seg)]
    t["sphere"] = (np.array(verts, float), faces)
    return t


TEMPLATES = _templates()


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def mesh_arrays(parts: list[tuple[str, np.ndarray, int]]):
    """Primitive rows (11 columns, or 12 with a pitch in degrees about the local x axis) -> (verts (V,3), loop vertex indices, loop starts, face material slots,
    vertex colours (V,4) linear RGB + the free scalar)."""
    verts, loops, starts, mats, cols = [], [], [], [], []
    v_off = l_off = 0
    for shape, rows, slot in parts:
        rows = np.asarray(rows, dtype=np.float64)
        rows = rows.reshape(-1, rows.shape[-1] if rows.ndim == 2 else 11)
        if not len(rows):
            continue
        if rows.shape[1] == 11:  # no pitch column
            rows = np.c_[rows, np.zeros(len(rows))]
        tv, tf = TEMPLATES[shape]
        local = tv[None, :, :] * rows[:, None, 3:6]
        pitch = np.radians(rows[:, 11])[:, None]  # about local x through the base centre, before yaw
        if pitch.any():
            ly, lz = local[..., 1].copy(), local[..., 2].copy()
            local[..., 1] = ly * np.cos(pitch) - lz * np.sin(pitch)
            local[..., 2] = ly * np.sin(pitch) + lz * np.cos(pitch)
        yaw = np.radians(rows[:, 6])[:, None]
        cos, sin = np.cos(yaw), np.sin(yaw)
        x = local[..., 0] * cos - local[..., 1] * sin + rows[:, None, 0]
        y = local[..., 0] * sin + local[..., 1] * cos + rows[:, None, 1]
        z = local[..., 2] + rows[:, None, 2]
        verts.append(np.stack([x, y, z], -1).reshape(-1, 3))
        colour = np.c_[srgb_to_linear(rows[:, 7:10]), rows[:, 10]]
        cols.append(np.repeat(colour, len(tv), axis=0))
        flat = np.concatenate([np.asarray(f) for f in tf])
        sizes = np.array([len(f) for f in tf])
        count = len(rows)
        loops.append((flat[None, :] + (np.arange(count) * len(tv))[:, None]).ravel() + v_off)
        local_starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        starts.append((local_starts[None, :] + (np.arange(count) * len(flat))[:, None]).ravel() + l_off)
        mats.append(np.full(count * len(tf), slot))
        v_off += count * len(tv)
        l_off += count * len(flat)
    if not verts:
        return (np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4)))
    return tuple(np.concatenate(a) for a in (verts, loops, starts, mats, cols))



def mesh_object(bpy, name: str, parts: list[tuple[str, np.ndarray, int]], materials: list[Any],
                pass_index: int, collection) -> Any:
    """One Blender mesh object from primitive rows; `pass_index` is its label code."""
    verts, loops, starts, mats, cols = mesh_arrays(parts)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts))
    me.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    me.loops.add(len(loops))
    me.loops.foreach_set("vertex_index", loops.astype(np.int32))
    me.polygons.add(len(starts))
    me.polygons.foreach_set("loop_start", starts.astype(np.int32))
    me.polygons.foreach_set("material_index", mats.astype(np.int32))
    me.update()
    attr = me.color_attributes.new("col", "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", cols.astype(np.float32).ravel())
    for m in materials:
        me.materials.append(m)
    obj = bpy.data.objects.new(name, me)
    obj.pass_index = pass_index
    collection.objects.link(obj)
    return obj


__all__ = ["OBJECT_MATERIAL", "TEMPLATES", "TOWN_MATERIAL", "mesh_arrays", "mesh_object", "srgb_to_linear"]
