"""Cycles backend: a procedural town rendered through `bpy`, with exact per-pixel labels.

Pairing: `prepare` builds geometry once; `render` changes only values (light energies and
directions, world, fog density, material parameters), never which objects or lights exist, so the
BVH is reused (persistent data), labels cannot drift between conditions, and an image depends on
(descriptor, condition) alone: Cycles' sampling sequence follows its light list, which is why
lamps and head lights come from fixed pools and switched-off things get zero values, not hidden.
Labels come from a separate 1-sample pass in which every surface emits its object's pass index
(class + 32 * instance, switched on by a material value), read back exactly from a float EXR.

bpy is imported lazily so this module (and the numpy mesh helpers) import without it. bpy keeps one
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
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX
from pairedgta.conditions import Condition
from pairedgta.errors import ConfigError, RendererError
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.scene.descriptor import SceneDescriptor
from pairedgta.scene.town import ProceduralTownRegion

LABEL_CODE_VOID = 31  # class code for surfaces that are not one of the 19 classes
MAX_INSTANCES = 32767 // 32

# ---------------------------------------------------------------------------------------------
# numpy mesh templates (local frame: x right, y forward, z up; base centre at the origin)


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
    """Primitive rows -> (verts (V,3), loop vertex indices, loop starts, face material slots,
    vertex colours (V,4) linear RGB + the free scalar)."""
    verts, loops, starts, mats, cols = [], [], [], [], []
    v_off = l_off = 0
    for shape, rows, slot in parts:
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, 11)
        if not len(rows):
            continue
        tv, tf = TEMPLATES[shape]
        local = tv[None, :, :] * rows[:, None, 3:6]
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


# ---------------------------------------------------------------------------------------------
# dynamic object models: rows in the object's local frame, real-world dimensions


def _row(shape, material, c, s, yaw=0.0, color=(1, 1, 1), a=0.0):
    return shape, material, (*c, *s, yaw, *color, a)


def _rgb(c) -> tuple[float, float, float]:
    return tuple(float(v) / 255.0 for v in c)  # type: ignore[return-value]


def _car(p, s):
    rows = [
        _row("box", "paint", (0, 0, 0.22), (1.8, 4.5, 0.62), color=p),
        _row("box", "paint", (0, -0.25, 0.84), (1.56, 2.3, 0.56), color=p),
        _row("panel", "glass", (0, 0.905, 0.9), (1.4, 0, 0.44)),
        _row("panel", "glass", (0, -1.405, 0.9), (1.4, 0, 0.42), 180),
        _row("panel", "glass", (0.785, -0.25, 0.9), (2.0, 0, 0.42), 270),
        _row("panel", "glass", (-0.785, -0.25, 0.9), (2.0, 0, 0.42), 90),
        _row("box", "trim", (0, 2.25, 0.2), (1.82, 0.12, 0.28), color=s),
        _row("box", "trim", (0, -2.25, 0.2), (1.82, 0.12, 0.28), color=s),
        _row("panel", "headlight", (0.6, 2.255, 0.58), (0.35, 0, 0.14)),
        _row("panel", "headlight", (-0.6, 2.255, 0.58), (0.35, 0, 0.14)),
        _row("panel", "taillight", (0.62, -2.255, 0.6), (0.3, 0, 0.14), 180),
        _row("panel", "taillight", (-0.62, -2.255, 0.6), (0.3, 0, 0.14), 180),
    ]
    rows += [_row("xcyl", "rubber", (x, y, 0), (0.24, 0.66, 0.66)) for x in (-0.8, 0.8) for y in (-1.38, 1.38)]
    return rows, [(0.0, 2.4, 0.6)]


def _truck(p, s):
    rows = [
        _row("box", "paint", (0, 2.6, 0.55), (2.4, 2.3, 2.3), color=p),
        _row("panel", "glass", (0, 3.755, 1.75), (2.1, 0, 0.85)),
        _row("panel", "glass", (1.205, 2.9, 1.75), (1.0, 0, 0.75), 270),
        _row("panel", "glass", (-1.205, 2.9, 1.75), (1.0, 0, 0.75), 90),
        _row("box", "matte", (0, -1.1, 0.95), (2.45, 5.1, 2.75), color=s),
        _row("box", "rubber", (0, 0, 0.45), (1.2, 7.4, 0.35)),
        _row("box", "trim", (0, 3.8, 0.35), (2.4, 0.12, 0.35), color=(0.3, 0.3, 0.3)),
        _row("panel", "headlight", (0.85, 3.755, 0.8), (0.35, 0, 0.18)),
        _row("panel", "headlight", (-0.85, 3.755, 0.8), (0.35, 0, 0.18)),
        _row("panel", "taillight", (0.95, -3.655, 0.62), (0.25, 0, 0.15), 180),
        _row("panel", "taillight", (-0.95, -3.655, 0.62), (0.25, 0, 0.15), 180),
    ]
    rows += [_row("xcyl", "rubber", (x, y, 0), (0.35, 1.0, 1.0)) for x in (-1.05, 1.05) for y in (2.6, -1.8, -3.0)]
    return rows, [(0.0, 3.9, 0.8)]


def _bus(p, s):
    rows = [
        _row("box", "paint", (0, 0, 0.3), (2.55, 12.0, 2.9), color=p),
        _row("panel", "glass", (1.28, -0.3, 1.3), (10.6, 0, 1.25), 270),
        _row("panel", "glass", (-1.28, -0.3, 1.3), (10.6, 0, 1.25), 90),
        _row("panel", "trim", (1.28, 0, 0.75), (11.8, 0, 0.3), 270, color=s),
        _row("panel", "trim", (-1.28, 0, 0.75), (11.8, 0, 0.3), 90, color=s),
        _row("panel", "glass", (0, 6.005, 1.05), (2.3, 0, 1.9)),
        _row("panel", "glass", (0, -6.005, 1.9), (2.1, 0, 0.9), 180),
        _row("panel", "headlight", (0.95, 6.005, 0.55), (0.4, 0, 0.2)),
        _row("panel", "headlight", (-0.95, 6.005, 0.55), (0.4, 0, 0.2)),
        _row("panel", "taillight", (1.0, -6.005, 0.7), (0.25, 0, 0.35), 180),
        _row("panel", "taillight", (-1.0, -6.005, 0.7), (0.25, 0, 0.35), 180),
    ]
    rows += [_row("xcyl", "rubber", (x, y, 0), (0.35, 1.0, 1.0)) for x in (-1.1, 1.1) for y in (4.0, -3.6)]
    return rows, [(0.0, 6.1, 0.6)]


def _motorcycle(p, s):
    rows = [
        _row("xcyl", "rubber", (0, 0.72, 0), (0.13, 0.62, 0.62)),
        _row("xcyl", "rubber", (0, -0.72, 0), (0.13, 0.62, 0.62)),
        _row("box", "paint", (0, 0.05, 0.5), (0.32, 0.9, 0.38), color=p),
        _row("box", "metal", (0, 0.0, 0.26), (0.3, 0.5, 0.26), color=(0.3, 0.3, 0.32)),
        _row("box", "rubber", (0, -0.45, 0.78), (0.3, 0.65, 0.1)),
        _row("box", "paint", (0, -0.72, 0.64), (0.2, 0.5, 0.06), color=s),
        _row("box", "metal", (0, 0.68, 0.3), (0.08, 0.08, 0.75), color=(0.6, 0.6, 0.62)),
        _row("box", "metal", (0, 0.62, 1.0), (0.75, 0.05, 0.05), color=(0.6, 0.6, 0.62)),
        _row("box", "paint", (0, 0.7, 0.8), (0.2, 0.12, 0.2), color=p),
        _row("panel", "headlight", (0, 0.765, 0.83), (0.15, 0, 0.14)),
        _row("panel", "taillight", (0, -0.975, 0.64), (0.12, 0, 0.06), 180),
    ]
    return rows, [(0.0, 0.85, 0.9)]


def _bicycle(p, s):
    frame = p
    rows = [
        _row("xring", "rubber", (0, 0.53, 0), (0.04, 0.68, 0.68)),
        _row("xring", "rubber", (0, -0.53, 0), (0.04, 0.68, 0.68)),
        _row("box", "paint", (0, 0.05, 0.76), (0.04, 0.6, 0.04), color=frame),
        _row("box", "paint", (0, 0.06, 0.44), (0.04, 0.56, 0.04), color=frame),
        _row("box", "paint", (0, -0.22, 0.34), (0.04, 0.04, 0.44), color=frame),
        _row("box", "paint", (0, 0.35, 0.42), (0.04, 0.04, 0.4), color=frame),
        _row("box", "paint", (0, -0.38, 0.33), (0.03, 0.32, 0.03), color=frame),
        _row("box", "metal", (0, 0.5, 0.34), (0.03, 0.03, 0.28), color=(0.6, 0.6, 0.62)),
        _row("box", "metal", (0, 0.35, 0.82), (0.03, 0.03, 0.16), color=(0.6, 0.6, 0.62)),
        _row("box", "metal", (0, 0.35, 0.97), (0.56, 0.03, 0.03), color=(0.2, 0.2, 0.2)),
        _row("box", "metal", (0, -0.22, 0.78), (0.03, 0.03, 0.08), color=(0.6, 0.6, 0.62)),
        _row("box", "rubber", (0, -0.24, 0.85), (0.12, 0.26, 0.05)),
    ]
    return rows, []


_SKIN = ((0.94, 0.78, 0.66), (0.80, 0.60, 0.45), (0.58, 0.40, 0.28), (0.36, 0.24, 0.17))
_HAIR = ((0.10, 0.08, 0.06), (0.35, 0.22, 0.12), (0.70, 0.58, 0.35), (0.25, 0.25, 0.25))


def _person(p, s, model):
    h = zlib.crc32(model.encode())
    skin, hair = _SKIN[h % 4], _HAIR[(h // 4) % 4]
    rows = [
        _row("box", "matte", (0.1, 0, 0.05), (0.15, 0.18, 0.83), color=s),
        _row("box", "matte", (-0.1, 0, 0.05), (0.15, 0.18, 0.83), color=s),
        _row("box", "rubber", (0.1, 0.04, 0), (0.14, 0.27, 0.07)),
        _row("box", "rubber", (-0.1, 0.04, 0), (0.14, 0.27, 0.07)),
        _row("box", "matte", (0, 0, 0.86), (0.42, 0.24, 0.6), color=p),
        _row("box", "matte", (0.27, 0, 0.88), (0.1, 0.12, 0.58), color=p),
        _row("box", "matte", (-0.27, 0, 0.88), (0.1, 0.12, 0.58), color=p),
        _row("box", "matte", (0.27, 0, 0.78), (0.08, 0.09, 0.1), color=skin),
        _row("box", "matte", (-0.27, 0, 0.78), (0.08, 0.09, 0.1), color=skin),
        _row("box", "matte", (0, 0, 1.45), (0.1, 0.1, 0.07), color=skin),
        _row("sphere", "matte", (0, 0, 1.5), (0.21, 0.24, 0.25), color=skin),
        _row("sphere", "matte", (0, -0.015, 1.615), (0.22, 0.25, 0.14), color=hair),
    ]
    return rows, []


def _rider_body(p, s, model, seat_y, hip, reach, helmet):
    h = zlib.crc32(model.encode())
    skin = _SKIN[h % 4]
    rows = [
        _row("box", "matte", (x, seat_y + 0.2, hip - 0.12), (0.14, 0.42, 0.16), color=s) for x in (-0.12, 0.12)
    ] + [
        _row("box", "matte", (x, seat_y + 0.4, 0.22), (0.13, 0.14, hip - 0.3), color=s) for x in (-0.13, 0.13)
    ] + [
        _row("box", "matte", (0, seat_y + 0.08, hip), (0.4, 0.24, 0.58), color=p),
        _row("box", "matte", (0.24, seat_y + 0.08 + reach / 2, hip + 0.4), (0.09, reach, 0.09), color=p),
        _row("box", "matte", (-0.24, seat_y + 0.08 + reach / 2, hip + 0.4), (0.09, reach, 0.09), color=p),
        _row("box", "matte", (0, seat_y + 0.08, hip + 0.58), (0.1, 0.1, 0.07), color=skin),
        _row("sphere", "matte", (0, seat_y + 0.08, hip + 0.63), (0.21, 0.24, 0.25), color=skin),
    ]
    if helmet:
        rows.append(_row("sphere", "paint", (0, seat_y + 0.07, hip + 0.68), (0.29, 0.32, 0.25), color=s))
    return rows


def model_parts(category: str, model: str, color, secondary) -> tuple[list[tuple[str, str, str, tuple]], list[tuple]]:
    """Parts (label, shape, material, row) and head-light spots of one dynamic object."""
    p, s = _rgb(color), _rgb(secondary)
    if category == "car":
        rows, spots = _car(p, s)
    elif category == "truck":
        rows, spots = _truck(p, s)
    elif category == "bus":
        rows, spots = _bus(p, s)
    elif category == "motorcycle":
        rows, spots = _motorcycle(p, s)
    elif category == "bicycle":
        rows, spots = _bicycle(p, s)
    elif category == "person":
        rows, spots = _person(p, s, model)
    elif category == "rider":
        # a rider is drawn on the vehicle it rides (bicycle unless the model names a motorbike);
        # the vehicle keeps its own class and shares the rider's instance id
        moto = "motor" in model.lower() or "bike" == model.lower()
        vehicle, spots = (_motorcycle if moto else _bicycle)((0.2, 0.2, 0.22), (0.1, 0.1, 0.1))
        vlabel = "motorcycle" if moto else "bicycle"
        body = _rider_body(p, s, model, -0.3 if moto else -0.24, 0.86 if moto else 0.9, 0.55 if moto else 0.5, moto)
        parts = [(vlabel, *r) for r in vehicle] + [("rider", *r) for r in body]
        return parts, spots
    else:
        raise RendererError(
            f"dynamic object category '{category}' has no Blender model; use one of "
            "car, truck, bus, motorcycle, bicycle, person, rider"
        )
    return [(category, *r) for r in rows], spots


def decode_labels(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label-pass values -> (train ids uint8, instance ids uint16). 0 is sky."""
    code = np.rint(code).astype(np.int64)
    cls = code % 32
    train = np.where((cls >= 1) & (cls <= len(CLASS_NAMES)), cls - 1, IGNORE_INDEX)
    train = np.where(code == 0, CLASS_NAMES.index("sky"), train)
    return train.astype(np.uint8), (code // 32).astype(np.uint16)


def label_code(label: str, instance: int = 0) -> int:
    cls = CLASS_NAMES.index(label) + 1 if label in CLASS_NAMES else LABEL_CODE_VOID
    return instance * 32 + cls


# ---------------------------------------------------------------------------------------------
# light and sky model (pure numpy so it is testable and continuous in the condition)


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


def lighting(cond: Condition, exposure_override: float | None = None, exposure_bias: float = 0.0,
             fog_max_density: float = 0.06, rain_haze: float = 0.006) -> dict[str, Any]:
    """All condition-dependent render parameters; continuous in every physical field."""
    el = float(cond.sun_elevation_deg)
    rain = float(cond.rain_intensity)
    cloud = max(float(cond.cloud_cover), rain)
    wet = max(float(cond.wetness), rain)
    fog = float(cond.fog_density)
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
    grey = np.array([0.50, 0.52, 0.56]) * (sky * (1.0 - 0.45 * rain) + 0.006) + city_glow
    moon = 0.012 * night * (1.0 - 0.9 * cloud)
    lamps = 1.0 - _smoothstep(-3.0, 6.0, el)
    vehicle_lights = max(lamps, _smoothstep(0.2, 0.6, max(rain, fog)))
    # exposure: partial compensation of the estimated scene illuminance (real cameras keep night dark)
    sky_light = 2.6 * float(np.mean(zenith + horizon) / 2 * (1 - cloud) + np.mean(grey) * cloud)
    extinction = fog_max_density * fog + rain_haze * rain  # 1/m
    # lamp light scattered by fog and rain lights the air itself: less exposure is needed
    illum = sun_strength * max(math.sin(math.radians(el)), 0.0) + sky_light + lamps * (0.2 + 25.0 * extinction)
    reference = 4.5 * 0.82 + 2.6 * 0.33
    ev = 0.3 + float(np.clip(0.5 * math.log2(reference / max(illum, 1e-4)), -0.5, 2.0))
    if exposure_override is not None:
        ev = float(exposure_override)
    return {
        "sun_dir": sun_vector(el, cond.sun_azimuth_deg), "sun_strength": sun_strength, "sun_color": sun_color,
        "sun_angle_deg": 0.53 + 25.0 * cloud,
        "moon_dir": sun_vector(38.0, (cond.sun_azimuth_deg + 180.0) % 360.0), "moon_strength": moon,
        "zenith": zenith, "horizon": horizon, "glow": glow, "cloud_color": grey,
        "cloud_cover": cloud, "overcast": _smoothstep(0.55, 0.95, cloud),
        "wetness": wet, "puddle_threshold": 1.0 - 0.42 * wet,
        "fog": fog, "rain": rain, "extinction": extinction,
        "lamps": lamps, "vehicle_lights": vehicle_lights,
        "window_lit": lamps, "exposure": ev + exposure_bias,
    }


# ---------------------------------------------------------------------------------------------


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

_TOWN_MATERIAL = {
    "asphalt": "pavement", "marking": "pavement", "sidewalk": "pavement", "kerb": "pavement",
    "grass": "matte", "lot": "matte", "facade": "matte", "roof": "matte", "wall": "matte",
    "fence": "matte", "hedge": "matte", "foliage": "matte", "bark": "matte", "sign_back": "matte",
    "metal": "metal", "housing": "metal", "window": "window", "lamp": "lamp", "sign": "sign",
    "signal_red": "signal_red", "signal_amber": "signal_amber", "signal_green": "signal_green",
    "signal_off": "signal_off",
}
_OBJECT_MATERIAL = {
    "paint": "paint", "glass": "glass", "rubber": "rubber", "trim": "metal", "metal": "metal",
    "matte": "matte", "headlight": "headlight", "taillight": "taillight",
}


class BlenderRenderer(Renderer):
    """Cycles renderer of the procedural town (CPU by default)."""

    name = "blender"
    gives_labels = True

    def __init__(self, width: int = 512, height: int = 256, samples: int = 2, device: str = "CPU",
                 denoise: bool = True, denoiser_quality: str = "FAST", max_bounces: int = 2,
                 fast_gi: bool = True, town: Mapping[str, Any] | None = None, seed: int = 0,
                 exposure: Mapping[str, float] | None = None, exposure_bias: float = 0.0,
                 threads: int = 0, fog_max_density: float = 0.06, fog_extent: float = 220.0,
                 fog_height: float = 45.0, rain_haze: float = 0.006, volume_step_rate: float = 4.0,
                 view_transform: str = "AgX", look: str = "None", filter_width: float = 1.5,
                 labels_per_condition: bool = False, light_tree: bool = False, lamp_radius: float = 120.0,
                 max_lamps: int = 48, max_headlights: int = 24, **unknown: Any) -> None:
        if unknown:
            raise ConfigError(
                f"renderer.{min(unknown)} is not a blender renderer option; remove it "
                "(options: width, height, samples, device, denoise, denoiser_quality, max_bounces, fast_gi, "
                "town, seed, exposure, exposure_bias, threads, fog_max_density, fog_extent, fog_height, "
                "rain_haze, volume_step_rate, view_transform, look, filter_width, labels_per_condition, light_tree, "
                "lamp_radius, max_lamps, max_headlights)"
            )
        super().__init__(width, height)
        checks = (
            ("width", self.width >= 8, ">= 8"), ("height", self.height >= 8, ">= 8"),
            ("samples", int(samples) >= 1, ">= 1"), ("max_bounces", int(max_bounces) >= 0, ">= 0"),
            ("device", str(device).upper() in ("CPU", "GPU"), "CPU or GPU"),
            ("denoiser_quality", str(denoiser_quality).upper() in ("FAST", "BALANCED", "HIGH"),
             "FAST, BALANCED or HIGH"),
            ("fog_max_density", float(fog_max_density) >= 0, ">= 0 (1/m)"),
            ("threads", int(threads) >= 0, ">= 0 (0 = all cores)"),
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
        self.exposure = {str(k): float(v) for k, v in dict(exposure or {}).items()}
        self.exposure_bias = float(exposure_bias)
        self.threads = int(threads)
        self.fog_max_density = float(fog_max_density)
        self.fog_extent = float(fog_extent)
        self.fog_height = float(fog_height)
        self.rain_haze = float(rain_haze)
        self.volume_step_rate = float(volume_step_rate)
        self.view_transform = str(view_transform)
        self.look = str(look)
        self.filter_width = float(filter_width)
        self.labels_per_condition = bool(labels_per_condition)
        self.light_tree = bool(light_tree)
        self.lamp_radius = float(lamp_radius)
        self.max_lamps = int(max_lamps)
        self.max_headlights = int(max_headlights)
        self.timings: dict[str, float] = {}
        self._bpy: Any = None
        self._tmp: str | None = None
        self._reset_state()

    def _reset_state(self) -> None:
        self._town: ProceduralTownRegion | None = None
        self._town_key: tuple | None = None
        self._prepared: SceneDescriptor | None = None
        self._labels: tuple[np.ndarray, np.ndarray] | None = None
        self._knobs: dict[str, list[Any]] = {}
        self._materials: dict[str, Any] = {}
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
            sc.view_settings.view_transform = self.view_transform
            sc.view_settings.look = self.look
        except TypeError as exc:
            raise ConfigError(f"renderer.view_transform/look: {exc}; use e.g. view_transform=AgX look=None") from None
        self._coll_town = bpy.data.collections.new("town")
        self._coll_scene = bpy.data.collections.new("scene")
        sc.collection.children.link(self._coll_town)
        sc.collection.children.link(self._coll_scene)
        self._build_materials()
        self._build_world()
        self._build_lights()
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

    # ---- materials ------------------------------------------------------------------------
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
        em.inputs["Color"].default_value = (1, 1, 1, 1)
        nt.links.new(info.outputs["Object Index"], em.inputs["Strength"])
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

    # ---- geometry -------------------------------------------------------------------------
    def _mesh_object(self, name: str, parts: list[tuple[str, np.ndarray, int]], materials: list[Any],
                     pass_index: int, collection) -> Any:
        bpy = self._bpy
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

    def _resolve_town(self, descriptor: SceneDescriptor) -> dict[str, Any]:
        extra = dict(descriptor.extra)
        params = dict(self.town_cfg)
        town_extra = extra.get("town")
        if isinstance(town_extra, Mapping):
            params.update(town_extra)
        elif "town_seed" in extra:
            params["town_seed"] = extra["town_seed"]
        kind = params.pop("type", "procedural_town")
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
            bmat = _TOWN_MATERIAL.get(material)
            if bmat is None:
                raise RendererError(f"town material '{material}' has no Blender material; add it to _TOWN_MATERIAL")
            by_object.setdefault((bmat, label), []).append((shape, rows))
        for (bmat, label), parts in sorted(by_object.items()):
            self._mesh_object(f"town_{bmat}_{label}", [(s, r, 0) for s, r in parts], [self._materials[bmat]],
                              label_code(label), self._coll_town)
        # fog: one box over the whole town, built with it. Per-scene boxes would be rebuilt between
        # scenes, and Cycles' volume acceleration data then depends on the scene rendered before
        e = layout.road_half_length + self.fog_extent
        row = np.array([[0.0, 0.0, -1.0, 2 * e, 2 * e, self.fog_height, 0, 1, 1, 1, 0]])
        self._fog = self._mesh_object("fog", [("box", row, 0)], [self._materials["fog"]], 0, self._coll_town)
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
        self._clear_scene_objects()
        cam_pos = self._place_camera(descriptor)
        if town.obstacle_at(*cam_pos):
            raise RendererError(
                f"scene {descriptor.scene_id}: camera at "
                f"({cam_pos[0]:.1f}, {cam_pos[1]:.1f}, {cam_pos[2]:.1f}) is inside "
                "a building; move the ego onto a lane (region.sample_location) or reduce camera offsets"
            )
        if len(descriptor.objects) > MAX_INSTANCES:
            raise RendererError(
                f"scene {descriptor.scene_id}: {len(descriptor.objects)} objects; "
                f"at most {MAX_INSTANCES} are supported; lower generate.objects.max")
        h = math.radians(loc.heading)
        fwd = np.array([-math.sin(h), math.cos(h)])
        right = np.array([math.cos(h), math.sin(h)])
        ground_ego = town.ground_height(loc.x, loc.y)
        placed = []
        heads: list[tuple[tuple, tuple]] = []
        for k, ob in enumerate(descriptor.objects, start=1):
            parts, spots = model_parts(ob.category, ob.model, ob.color, ob.secondary_color)
            xy = np.array([loc.x, loc.y]) + fwd * ob.forward + right * ob.right
            z = loc.z + ob.up + town.ground_height(*xy) - ground_ego
            yaw = loc.heading + ob.heading
            c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
            by_label: dict[str, list[tuple[str, str, tuple]]] = {}
            for label, shape, material, row in parts:
                by_label.setdefault(label, []).append((shape, material, row))
            for label, items in by_label.items():
                slots = sorted({_OBJECT_MATERIAL[m] for _, m, _ in items})
                grouped: dict[tuple[str, int], list[tuple]] = {}
                for shape, material, row in items:
                    grouped.setdefault((shape, slots.index(_OBJECT_MATERIAL[material])), []).append(row)
                mesh_parts = []
                for (shape, slot), rows in grouped.items():
                    arr = np.array(rows, dtype=np.float64)
                    lx, ly = arr[:, 0].copy(), arr[:, 1].copy()
                    arr[:, 0] = xy[0] + lx * c - ly * s
                    arr[:, 1] = xy[1] + lx * s + ly * c
                    arr[:, 2] += z
                    arr[:, 6] += yaw
                    mesh_parts.append((shape, arr, slot))
                obj = self._mesh_object(f"obj{k}_{label}", mesh_parts, [self._materials[m] for m in slots],
                                        label_code(label, k), self._coll_scene)
                self._scene_meshes.append(obj.data)
            for sx, sy, sz in spots:
                if len(heads) < len(self._head_pool):  # beyond the pool, further vehicles stay unlit
                    heads.append(((xy[0] + sx * c - sy * s, xy[1] + sx * s + sy * c, z + sz),
                                  (math.radians(84.0), 0.0, math.radians(yaw))))
            placed.append({"instance": k, "category": ob.category, "x": round(float(xy[0]), 3),
                           "y": round(float(xy[1]), 3), "z": round(float(z), 3), "heading": round(yaw % 360.0, 3)})
        # street-lamp lights near the camera only: farther lamps light nothing that is visible
        # (their glowing heads stay, as geometry), and each light costs time at every shading point
        lamps = town.layout().lamps
        chosen: list[int] = []
        if len(lamps):
            dist = np.hypot(lamps[:, 0] - cam_pos[0], lamps[:, 1] - cam_pos[1])
            behind = (lamps[:, 0] - cam_pos[0]) * fwd[0] + (lamps[:, 1] - cam_pos[1]) * fwd[1]
            near = np.flatnonzero((dist < self.lamp_radius) & (behind > -25.0))
            chosen = near[np.argsort(dist[near], kind="stable")][: len(self._lamp_pool)].tolist()
        parked = ((0.0, 0.0, -50.0), (0.0, 0.0, 0.0))
        for i, obj in enumerate(self._lamp_pool):
            obj.location = tuple(float(v) for v in lamps[chosen[i]]) if i < len(chosen) else parked[0]
            obj.rotation_euler = parked[1]
        for i, obj in enumerate(self._head_pool):
            obj.location, obj.rotation_euler = heads[i] if i < len(heads) else parked
        self._lamps_used, self._heads_used = len(chosen), len(heads)
        self._scene_state = {
            "camera": [round(float(v), 3) for v in cam_pos], "objects": placed,
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
    def _set(self, name: str, value) -> None:
        for socket in self._knobs.get(name, []):
            if isinstance(value, (np.ndarray, tuple, list)):
                socket.default_value = (*[float(v) for v in value], 1.0)
            else:
                socket.default_value = float(value)

    def _apply_condition(self, cond: Condition) -> dict[str, Any]:
        from mathutils import Vector

        p = lighting(cond, self.exposure.get(cond.name, self.exposure.get(cond.time)), self.exposure_bias,
                     self.fog_max_density, self.rain_haze)
        sun = Vector(tuple(p["sun_dir"]))
        self._sun_obj.rotation_euler = sun.to_track_quat("Z", "Y").to_euler()
        self._sun.energy = p["sun_strength"]
        self._sun.color = tuple(p["sun_color"])
        self._sun.angle = math.radians(p["sun_angle_deg"])
        self._moon_obj.rotation_euler = Vector(tuple(p["moon_dir"])).to_track_quat("Z", "Y").to_euler()
        self._moon.energy = p["moon_strength"]
        for axis, v in zip(("sun_x", "sun_y", "sun_z"), p["sun_dir"]):
            self._set(axis, v)
        for key in ("zenith", "horizon", "glow", "cloud_color"):
            self._set(key, p[key])
        self._set("cloud_cover", p["cloud_cover"])
        self._set("overcast", p["overcast"])
        self._set("wetness", p["wetness"])
        self._set("puddle_threshold", p["puddle_threshold"])
        lamps, vlights = p["lamps"], p["vehicle_lights"]
        for i, obj in enumerate(self._lamp_pool):
            obj.data.energy = 350.0 * lamps if i < self._lamps_used else 0.0
        self._set("lamp_emit", 25.0 * lamps)
        self._set("window_fraction", self._town.lit_window_fraction * p["window_lit"] if self._town else 0.0)
        self._set("window_emit", 2.5 * p["window_lit"])
        self._set("signal_emit", 3.0 + 5.0 * lamps)
        self._set("sign_emit", 0.0)
        for i, obj in enumerate(self._head_pool):
            obj.data.energy = 250.0 * vlights if i < self._heads_used else 0.0
        self._set("headlight_emit", 30.0 * vlights)
        self._set("taillight_emit", 0.3 + 10.0 * vlights)
        density = p["extinction"]
        self._set("fog_density", density)
        self._set("fog_on", 1.0 if density > 0.0 else 0.0)
        self._bpy.context.scene.view_settings.exposure = p["exposure"]
        return p

    # ---- capture --------------------------------------------------------------------------
    def _render_to(self, path: str) -> None:
        sc = self._bpy.context.scene
        sc.render.filepath = path
        with _quiet_stdout():  # Blender prints a "Saved: ..." line per render
            self._bpy.ops.render.render(write_still=True)
        if not os.path.exists(path):
            raise RendererError(f"Cycles wrote no image to {path}; check free space in {self._tmp}")

    def _render_labels(self) -> tuple[np.ndarray, np.ndarray]:
        bpy = self._bpy
        sc = bpy.context.scene
        vl = sc.view_layers[0]
        cy = sc.cycles
        saved = (cy.samples, cy.filter_width, cy.use_denoising)
        fog = self._knobs["fog_on"][0].default_value
        img = sc.render.image_settings
        self._set("label_mode", 1.0)
        self._set("fog_on", 0.0)  # values only: toggling visibility would reorder Cycles' scene
        vl.use_sky = False
        cy.samples, cy.filter_width, cy.use_denoising = 1, 0.01, False  # one centred sample per pixel
        img.file_format = "OPEN_EXR"
        img.color_depth = "32"
        img.exr_codec = "NONE"
        path = os.path.join(self._tmp or tempfile.gettempdir(), "labels.exr")
        try:
            self._render_to(path)
        finally:
            self._set("label_mode", 0.0)
            self._set("fog_on", fog)
            vl.use_sky = True
            cy.samples, cy.filter_width, cy.use_denoising = saved
        image = bpy.data.images.load(path, check_existing=False)
        try:
            w, h = image.size
            px = np.empty(w * h * image.channels, dtype=np.float32)
            image.pixels.foreach_get(px)
        finally:
            bpy.data.images.remove(image)
        code = px.reshape(h, w, -1)[::-1, :, 0]
        return decode_labels(code)

    def _render_beauty(self) -> np.ndarray:
        from PIL import Image

        img = self._bpy.context.scene.render.image_settings
        img.file_format = "PNG"
        img.color_mode = "RGB"
        img.color_depth = "8"
        img.compression = 0
        path = os.path.join(self._tmp or tempfile.gettempdir(), "beauty.png")
        self._render_to(path)
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB")).copy()

    def render(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        if _OWNER is not self or self._prepared is None or self._prepared != descriptor:
            self.prepare(descriptor)
        t0 = time.perf_counter()
        p = self._apply_condition(condition)
        image = self._render_beauty()
        t1 = time.perf_counter()
        if self.labels_per_condition or self._labels is None:
            labels, instances = self._render_labels()
            if not self.labels_per_condition:
                self._labels = (labels, instances)
        else:
            labels, instances = self._labels
        t2 = time.perf_counter()
        self.timings["render"] = t1 - t0
        self.timings["labels"] = t2 - t1
        state = {
            **self._scene_state, "backend": "blender", "condition": condition.name,
            "exposure_ev": round(float(p["exposure"]), 4), "samples": self.samples,
            "sun_strength": round(float(p["sun_strength"]), 4), "fog_density_per_m": round(float(p["extinction"]), 5),
            "seconds": round(t2 - t0, 4),
        }
        return RenderResult(image=image, labels=labels.copy(), instances=instances.copy(), state=state)


__all__ = ["BlenderRenderer", "decode_labels", "label_code", "lighting", "mesh_arrays", "model_parts"]
