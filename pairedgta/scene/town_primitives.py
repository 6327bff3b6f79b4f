"""Primitives of the procedural town: the rows a layout is made of, the builder that collects them
(with the compound street objects: trees, fences, lamps, traffic lights, signs) and the town's palette.

A layout is a list of primitive groups (box, plane, panel, cylinder, sphere, ...) keyed by shape,
material and Cityscapes class; the Blender backend turns each group into one mesh, so the label of
every surface is fixed here. Coordinates as in pairedgta/scene/town.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

# columns of one primitive row
COLUMNS = ("cx", "cy", "cz", "sx", "sy", "sz", "yaw", "r", "g", "b", "a")
SHAPES = ("box", "plane", "panel", "disc", "triangle", "cylinder", "sphere")

_ASPHALT = (0.21, 0.21, 0.22)
_PAVING = (0.58, 0.56, 0.53)
_KERB = (0.70, 0.69, 0.66)
_GRASS = (0.30, 0.42, 0.18)
_MARKING = (0.92, 0.92, 0.90)
# sign kind -> (shape, plate size w, 0, h in metres, face colour); sizes of European street signs
SIGNS = {
    "disc": ("disc", (0.75, 0.0, 0.75), (0.80, 0.10, 0.10)),        # prohibitions, speed limits
    "triangle": ("triangle", (0.9, 0.0, 0.8), (0.95, 0.95, 0.95)),  # warnings
    "panel": ("panel", (0.65, 0.0, 0.85), (0.10, 0.30, 0.75)),      # information, parking
    "square": ("panel", (0.75, 0.0, 0.75), (0.12, 0.35, 0.78)),     # crossings, one-way
    "plate": ("panel", (0.6, 0.0, 0.3), (0.95, 0.95, 0.92)),        # supplementary plate below another
    "direction": ("panel", (1.9, 0.0, 1.05), (0.10, 0.42, 0.22)),   # destinations at a junction
}


@dataclass
class TownLayout:
    """Geometry of one town. `groups[(shape, material, label)]` is an (N, 11) float32 array whose
    rows are base centre, size, yaw (deg, ccw) and an sRGB colour plus one free scalar `a`
    (windows: lit-at-night draw; lamps: unused)."""

    params: dict[str, Any]
    groups: dict[tuple[str, str, str], np.ndarray]
    lamps: np.ndarray  # (M, 3) light positions of street lamps (spots pointing down)
    crossings: np.ndarray  # (C, 6) zebra crossings: axis, road centre, along a0, a1, across o0, o1
    solids: np.ndarray  # (K, 7) boxes cx, cy, cz, sx, sy, sz, yaw that a camera must not be in
    half_extent: float  # town square half size incl. outer sidewalks
    road_half_length: float  # roads run from -L to L


class Builder:
    """Collects primitive rows by (shape, material, label), the lamps and the solids; its compound
    objects (tree, fence, lamp, traffic light, sign) are the street furniture the layout places."""

    def __init__(self) -> None:
        self.rows: dict[tuple[str, str, str], list[tuple[float, ...]]] = {}
        self.lamps: list[tuple[float, float, float]] = []
        self.solids: list[tuple[float, ...]] = []
        self.crossings: list[tuple[float, ...]] = []

    def add(self, shape: str, material: str, label: str, center, size, yaw=0.0,
            color=(1.0, 1.0, 1.0), a=0.0) -> None:
        row = (*map(float, center), *map(float, size), float(yaw), *map(float, color), float(a))
        self.rows.setdefault((shape, material, label), []).append(row)

    def box(self, material, label, x0, x1, y0, y1, z0, z1, color=(1, 1, 1), a=0.0, solid=False):
        c = ((x0 + x1) / 2, (y0 + y1) / 2, z0)
        s = (abs(x1 - x0), abs(y1 - y0), z1 - z0)
        self.add("box", material, label, c, s, 0.0, color, a)
        if solid:
            self.solids.append((*c, *s, 0.0))

    def plane(self, material, label, x0, x1, y0, y1, z, color=(1, 1, 1)):
        self.add("plane", material, label, ((x0 + x1) / 2, (y0 + y1) / 2, z),
                 (abs(x1 - x0), abs(y1 - y0), 0.0), 0.0, color)

    def build(self, params, half_extent, road_half_length) -> TownLayout:
        groups = {k: np.asarray(v, dtype=np.float32).reshape(-1, len(COLUMNS)) for k, v in sorted(self.rows.items())}
        return TownLayout(
            params=params,
            groups=groups,
            lamps=np.asarray(self.lamps, dtype=np.float32).reshape(-1, 3),
            crossings=np.asarray(self.crossings, dtype=np.float64).reshape(-1, 6),
            solids=np.asarray(self.solids, dtype=np.float32).reshape(-1, 7),
            half_extent=half_extent,
            road_half_length=road_half_length,
        )

    def tree(self, rng: np.random.Generator, x: float, y: float, z: float, scale: float = 1.0) -> None:
        h = rng.uniform(2.2, 3.2) * scale
        self.add("cylinder", "bark", "vegetation", (x, y, z), (0.32 * scale, 0.32 * scale, h + 0.5), 0.0,
                 (0.30, 0.22, 0.15))
        r = rng.uniform(1.6, 2.6) * scale
        green = jitter(rng, (0.20, 0.34, 0.11), 0.05)
        self.add("sphere", "foliage", "vegetation", (x, y, z + h - 0.3 * r), (2 * r, 2 * r, 2.2 * r),
                 rng.uniform(0, 360), green)

    def fence(self, rng, x0, x1, y0, y1, z0, height, style: str, colour, solid=True) -> None:
        """A fence along the long side of [x0, x1] x [y0, y1]: `boards` (wooden, narrow gaps) or
        `railing` (metal posts, rails and thin bars); both labelled fence. A solid box would read as a
        wall, which Cityscapes labels differently."""
        along_x = (x1 - x0) >= (y1 - y0)
        a0, a1 = (x0, x1) if along_x else (y0, y1)
        mid = ((y0 + y1) / 2) if along_x else ((x0 + x1) / 2)
        length = a1 - a0
        if length < 0.5:
            return

        def piece(a, w, z, h, d=0.06):
            cx, cy = (a, mid) if along_x else (mid, a)
            size = (w, d, h) if along_x else (d, w, h)
            self.add("box", "fence", "fence", (cx, cy, z), size, 0.0, colour)

        if style == "boards":
            pitch = float(rng.uniform(0.13, 0.2))
            board = pitch * 0.8
            for a in np.arange(a0 + pitch / 2, a1, pitch):
                piece(a, board, z0, height, 0.03)
            piece((a0 + a1) / 2, length, z0 + 0.25, 0.1, 0.08)  # cross rails behind the boards
            piece((a0 + a1) / 2, length, z0 + height - 0.3, 0.1, 0.08)
        else:
            for a in np.linspace(a0 + 0.05, a1 - 0.05, max(2, int(length / 2.0) + 1)):
                piece(a, 0.06, z0, height, 0.06)
            for z in (z0 + 0.12, z0 + height - 0.06):
                piece((a0 + a1) / 2, length, z, 0.05, 0.05)
            for a in np.arange(a0 + 0.12, a1, 0.12):
                piece(a, 0.02, z0 + 0.12, height - 0.18, 0.02)
        if solid:  # keeps pedestrians and parked bicycles out of it
            cx, cy = ((a0 + a1) / 2, mid) if along_x else (mid, (a0 + a1) / 2)
            size = (length, 0.3, height) if along_x else (0.3, length, height)
            self.solids.append((cx, cy, z0, *size, 0.0))

    def lamp(self, axis, rc, along, offset, side, kh, metal) -> None:
        x, y = (rc + offset, along) if axis == 0 else (along, rc + offset)
        ux, uy = (-side, 0.0) if axis == 0 else (0.0, -side)  # unit vector towards the road centre
        height = 7.5
        self.add("cylinder", "metal", "pole", (x, y, kh), (0.18, 0.18, height), 0.0, metal)
        arm = 1.6
        self.add("box", "metal", "pole", (x + ux * arm / 2, y + uy * arm / 2, kh + height - 0.12),
                 (arm, 0.1, 0.1) if axis == 0 else (0.1, arm, 0.1), 0.0, metal)
        hx, hy = x + ux * arm, y + uy * arm
        head, glass = ((0.7, 0.3, 0.18), (0.55, 0.22, 0.0)) if axis == 0 else ((0.3, 0.7, 0.18), (0.22, 0.55, 0.0))
        self.add("box", "metal", "pole", (hx, hy, kh + height - 0.2), head, 0.0, metal)
        self.add("plane", "lamp", "pole", (hx, hy, kh + height - 0.205), glass, 0.0, (1, 1, 1))
        self.lamps.append((hx, hy, kh + height - 0.3))

    def traffic_light(self, x, y, kh, facing, green, metal) -> None:
        self.add("cylinder", "metal", "pole", (x, y, kh), (0.14, 0.14, 3.9), 0.0, metal)
        fx, fy = facing_vec(facing)
        hx, hy = x + fx * 0.2, y + fy * 0.2
        self.add("box", "housing", "traffic light", (hx, hy, kh + 2.7), (0.34, 0.26, 1.0), facing, (0.08, 0.08, 0.08))
        for k, colour in enumerate(("red", "amber", "green")):
            lit = (colour == "green") == green and colour != "amber"
            material = f"signal_{colour}" if lit else "signal_off"
            self.add("disc", material, "traffic light", (hx + fx * 0.135, hy + fy * 0.135, kh + 3.43 - k * 0.31),
                     (0.22, 0.0, 0.22), facing, (1, 1, 1))

    def sign(self, x, y, kh, facing, kind, metal, below: str | None = None) -> None:
        """A sign on its own post; its back is labelled traffic sign too, as in Cityscapes. `below`: a
        second plate under the first (a supplementary plate, or two signs on one post)."""
        shape, size, colour = SIGNS[kind]
        top = kh + (2.9 if kind == "direction" else 2.3)  # plate centre; direction signs clear pedestrians
        fx, fy = facing_vec(facing)
        plates = [(kind, top)]
        if below is not None:
            plates.append((below, top - size[2] / 2 - SIGNS[below][1][2] / 2 - 0.08))
        self.add("cylinder", "metal", "pole", (x, y, kh), (0.08, 0.08, top + size[2] / 2 - kh - 0.05), 0.0, metal)
        for k, z in plates:
            shape, size, colour = SIGNS[k]
            z0 = z - size[2] / 2  # shapes stand on their base
            self.add(shape, "sign", "traffic sign", (x + fx * 0.06, y + fy * 0.06, z0), size, facing, colour)
            self.add(shape, "sign_back", "traffic sign", (x + fx * 0.05, y + fy * 0.05, z0), size, facing + 180.0,
                     (0.6, 0.6, 0.6))


def jitter(rng: np.random.Generator, color, amount=0.06):
    return tuple(float(np.clip(c + rng.uniform(-amount, amount), 0.0, 1.0)) for c in color)


def _lerp(a, b, f: float) -> tuple[float, float, float]:
    return tuple(float(x + (y - x) * f) for x, y in zip(a, b))  # type: ignore[return-value]


def town_palette(town_seed: int, variation: float) -> dict[str, Any]:
    """Ground materials of one town. Real cities differ in asphalt age, paving and verge colour; one
    fixed asphalt grey for every town lets a model learn road = that grey, which breaks as soon as
    rain or dusk changes it. `variation` 0 gives the reference palette, 1 the full range. Drawn
    from its own stream so the geometry of a town does not depend on it."""
    rng = np.random.default_rng([int(town_seed), 7919])
    f = float(variation)
    grey = rng.uniform(0.12, 0.42)  # fresh black asphalt .. sun-bleached, concrete-like
    tint = rng.uniform(-0.02, 0.02)
    asphalt = (grey + tint, grey, grey - tint + 0.01)
    family = int(rng.choice(4, p=[0.45, 0.25, 0.15, 0.15]))  # buff, grey, pale, brick-red paving
    base = [(0.58, 0.56, 0.53), (0.45, 0.45, 0.46), (0.72, 0.70, 0.64), (0.56, 0.38, 0.32)][family]
    paving = tuple(float(np.clip(c * rng.uniform(0.8, 1.15), 0, 1)) for c in base)
    kerb = tuple(float(np.clip(c * rng.uniform(0.8, 1.1), 0, 1)) for c in _KERB)
    grass = _lerp((0.20, 0.40, 0.12), (0.46, 0.46, 0.22), float(rng.uniform(0.0, 1.0)))  # lush .. dry
    marking = tuple(float(c * rng.uniform(0.78, 1.0)) for c in _MARKING)  # fresh .. worn paint
    wear = float(rng.uniform(0.5, 6.0))  # patches of repaired road per 100 m of road
    return {
        "asphalt": _lerp(_ASPHALT, asphalt, f), "paving": _lerp(_PAVING, paving, f),
        "kerb": _lerp(_KERB, kerb, f), "grass": _lerp(_GRASS, grass, f), "marking": _lerp(_MARKING, marking, f),
        "wear": wear * f,
    }


def facing_vec(facing: float) -> tuple[float, float]:
    h = math.radians(facing)
    return -math.sin(h), math.cos(h)


__all__ = ["COLUMNS", "SHAPES", "SIGNS", "Builder", "TownLayout", "facing_vec", "jitter", "town_palette"]
