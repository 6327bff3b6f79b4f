"""Procedural town: a deterministic street grid that the Blender backend renders.

Pure Python + numpy so that sampling and placement work without bpy. The layout is a list of
primitive groups (box, plane, panel, cylinder, sphere, ...) keyed by shape, material and Cityscapes
class; the renderer turns each group into one mesh, so the label of every surface is fixed here.

Coordinates: metres, x east, y north, z up; ground and road surface at z=0, sidewalks raised by
`kerb_height`. Roads run along x and y through `road centres` spaced by one pitch
(block + 2 sidewalks + road). Traffic keeps right.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.errors import ConfigError
from pairedgta.scene.descriptor import Location
from pairedgta.scene.population import PopulationConfig

# columns of one primitive row
COLUMNS = ("cx", "cy", "cz", "sx", "sy", "sz", "yaw", "r", "g", "b", "a")
SHAPES = ("box", "plane", "panel", "disc", "triangle", "cylinder", "sphere")

_FACADES = (
    (0.70, 0.70, 0.68), (0.80, 0.72, 0.58), (0.55, 0.30, 0.24), (0.86, 0.85, 0.82),
    (0.42, 0.43, 0.45), (0.76, 0.60, 0.38), (0.62, 0.68, 0.74), (0.80, 0.56, 0.46),
    (0.60, 0.52, 0.44), (0.35, 0.30, 0.28),
)
_WALLS = ((0.62, 0.60, 0.56), (0.55, 0.36, 0.30), (0.74, 0.72, 0.66))  # concrete, brick, render
_FENCES = ((0.45, 0.40, 0.35), (0.30, 0.22, 0.15), (0.25, 0.28, 0.26), (0.62, 0.62, 0.60))  # wood, painted, metal
_ASPHALT = (0.21, 0.21, 0.22)
_PAVING = (0.58, 0.56, 0.53)
_KERB = (0.70, 0.69, 0.66)
_GRASS = (0.30, 0.42, 0.18)
_MARKING = (0.92, 0.92, 0.90)
# sign kind -> (shape, plate size w, 0, h in metres, face colour); sizes of European street signs
_SIGNS = {
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


class _Builder:
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


def _jitter(rng: np.random.Generator, color, amount=0.06):
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


class ProceduralTownRegion:
    """Region interface over a procedural town: lane sampling, surface queries and the layout."""

    def __init__(self, name: str = "procedural_town", town_seed: int = 0, blocks: int = 4,
                 block_size: float = 60.0, road_width: float = 7.0, sidewalk_width: float = 3.0,
                 kerb_height: float = 0.15, floor_height: float = 3.2, min_floors: int = 2, max_floors: int = 9,
                 park_fraction: float = 0.15, lamp_spacing: float = 28.0, street_tree_fraction: float = 0.6,
                 lit_window_fraction: float = 0.45, countryside_trees: int = 60,
                 material_variation: float = 1.0, signs_per_100m: float = 2.0, junction_sign_fraction: float = 0.6,
                 railing_fraction: float = 0.2, front_boundary_fraction: float = 0.6,
                 population: Mapping[str, Any] | None = None) -> None:
        # population: ambient traffic and pedestrians (pairedgta/scene/population.py); None = none
        self.name = str(name)
        self.town_seed = int(town_seed)
        self.blocks = int(blocks)
        self.block_size = float(block_size)
        self.road_width = float(road_width)
        self.sidewalk_width = float(sidewalk_width)
        self.kerb_height = float(kerb_height)
        self.floor_height = float(floor_height)
        self.min_floors = int(min_floors)
        self.max_floors = int(max_floors)
        self.park_fraction = float(park_fraction)
        self.lamp_spacing = float(lamp_spacing)
        self.street_tree_fraction = float(street_tree_fraction)
        self.lit_window_fraction = float(lit_window_fraction)
        self.countryside_trees = int(countryside_trees)
        self.material_variation = float(material_variation)
        self.signs_per_100m = float(signs_per_100m)
        self.junction_sign_fraction = float(junction_sign_fraction)
        self.railing_fraction = float(railing_fraction)
        self.front_boundary_fraction = float(front_boundary_fraction)
        self.population = PopulationConfig.from_cfg(population)
        checks = (
            ("blocks", self.blocks >= 1, "an integer >= 1"),
            ("block_size", self.block_size >= 30.0, ">= 30 (metres)"),
            ("road_width", 5.0 <= self.road_width <= 20.0, "between 5 and 20 (metres, two lanes)"),
            ("sidewalk_width", 1.0 <= self.sidewalk_width <= 8.0, "between 1 and 8 (metres)"),
            ("min_floors", 1 <= self.min_floors <= self.max_floors, "1 <= min_floors <= max_floors"),
            ("park_fraction", 0.0 <= self.park_fraction <= 1.0, "in [0, 1]"),
            ("lamp_spacing", self.lamp_spacing >= 5.0, ">= 5 (metres)"),
            ("material_variation", 0.0 <= self.material_variation <= 1.0, "in [0, 1] (0 = one palette for all towns)"),
            ("signs_per_100m", 0.0 <= self.signs_per_100m <= 20.0, "between 0 and 20 (signs per 100 m of kerb)"),
            ("junction_sign_fraction", 0.0 <= self.junction_sign_fraction <= 1.0, "in [0, 1]"),
            ("railing_fraction", 0.0 <= self.railing_fraction <= 1.0, "in [0, 1]"),
            ("front_boundary_fraction", 0.0 <= self.front_boundary_fraction <= 1.0, "in [0, 1]"),
        )
        for key, ok, want in checks:
            if not ok:
                raise ConfigError(f"region procedural_town: {key}={getattr(self, key)!r} is invalid; set it {want}")
        self._layout: TownLayout | None = None

    # ---- geometry of the grid -------------------------------------------------------------
    @property
    def pitch(self) -> float:
        return self.block_size + 2 * self.sidewalk_width + self.road_width

    @property
    def road_centres(self) -> np.ndarray:
        return (np.arange(self.blocks + 1) - self.blocks / 2.0) * self.pitch

    @property
    def half_extent(self) -> float:
        return float(self.road_centres[-1] + self.road_width / 2 + self.sidewalk_width)

    @property
    def road_half_length(self) -> float:
        return self.half_extent + 0.5 * self.pitch

    def params(self) -> dict[str, Any]:
        """Everything that defines the town; the renderer rebuilds the same town from this."""
        return {
            "town_seed": self.town_seed, "blocks": self.blocks, "block_size": self.block_size,
            "road_width": self.road_width, "sidewalk_width": self.sidewalk_width,
            "kerb_height": self.kerb_height, "floor_height": self.floor_height,
            "min_floors": self.min_floors, "max_floors": self.max_floors,
            "park_fraction": self.park_fraction, "lamp_spacing": self.lamp_spacing,
            "street_tree_fraction": self.street_tree_fraction,
            "lit_window_fraction": self.lit_window_fraction,
            "countryside_trees": self.countryside_trees,
            "material_variation": self.material_variation,
            "signs_per_100m": self.signs_per_100m,
            "junction_sign_fraction": self.junction_sign_fraction,
            "railing_fraction": self.railing_fraction,
            "front_boundary_fraction": self.front_boundary_fraction,
            "population": self.population.to_dict(),
        }

    def _nearest_centre_dist(self, v: float) -> float:
        c = self.road_centres
        return float(np.min(np.abs(c - v)))

    def surface_at(self, x: float, y: float) -> str:
        """'road', 'sidewalk' or 'other' (lots, parks, countryside)."""
        hw = self.road_width / 2
        length = self.road_half_length
        dx = self._nearest_centre_dist(x)  # distance to the nearest north-south road
        dy = self._nearest_centre_dist(y)
        if (dx <= hw and abs(y) <= length) or (dy <= hw and abs(x) <= length):
            return "road"
        sw = hw + self.sidewalk_width
        if (dx <= sw and abs(y) <= length) or (dy <= sw and abs(x) <= length):
            return "sidewalk"
        return "other"

    def ground_height(self, x: float, y: float) -> float:
        surface = self.surface_at(x, y)
        if surface == "road":
            return 0.0
        if surface == "sidewalk" or max(abs(x), abs(y)) <= self.half_extent:
            return self.kerb_height
        return 0.0

    def obstacle_at(self, x: float, y: float, z: float) -> bool:
        """True when (x, y, z) is inside a building or wall of the layout."""
        solids = self.layout().solids
        if len(solids) == 0:
            return False
        inside = (
            (np.abs(x - solids[:, 0]) < solids[:, 3] / 2)
            & (np.abs(y - solids[:, 1]) < solids[:, 4] / 2)
            & (z >= solids[:, 2])
            & (z <= solids[:, 2] + solids[:, 5])
        )
        return bool(inside.any())

    def sample_location(self, rng: np.random.Generator) -> Location:
        """A right-hand lane position between two junctions, heading along the lane, with a
        stretch of street ahead before the next junction."""
        c = self.road_centres
        hw = self.road_width / 2
        clear = hw + self.sidewalk_width
        axis = int(rng.integers(2))  # 0: road along y (north-south), 1: road along x
        road = float(c[int(rng.integers(len(c)))])
        seg = int(rng.integers(len(c) - 1))
        sign = 1.0 if rng.random() < 0.5 else -1.0  # travel direction along the axis
        if len(c) > 2 and ((sign > 0 and seg == len(c) - 2) or (sign < 0 and seg == 0)):
            sign = -sign  # on an outermost segment, look into the town rather than out of it
        lo, hi = c[seg] + clear, c[seg + 1] - clear
        ahead = min(15.0, 0.5 * (hi - lo))
        if sign > 0:
            along = float(rng.uniform(lo + 1.0, hi - ahead))
        else:
            along = float(rng.uniform(lo + ahead, hi - 1.0))
        lane = hw / 2
        if axis == 0:
            heading = 0.0 if sign > 0 else 180.0
            x, y = road + sign * lane, along
        else:
            heading = 270.0 if sign > 0 else 90.0
            x, y = along, road - sign * lane
        return Location(x=round(x, 3), y=round(y, 3), z=0.0, heading=heading)

    def populate(self, descriptor):
        """The descriptor with this town's ambient population around its ego location, drawn from
        its seed alone (the scene's other draws are untouched); see pairedgta/scene/population.py."""
        from pairedgta.scene.population import populate

        return populate(self, descriptor)

    # ---- layout ---------------------------------------------------------------------------
    def layout(self) -> TownLayout:
        if self._layout is None:
            self._layout = _build_layout(self)
        return self._layout


def _build_layout(t: ProceduralTownRegion) -> TownLayout:
    rng = np.random.default_rng(t.town_seed)
    pal = town_palette(t.town_seed, t.material_variation)
    b = _Builder()
    c = t.road_centres
    n = len(c)
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    length = t.road_half_length
    half = t.half_extent

    # terrain reaching the horizon, then lot ground inside the town
    far = length + 1500.0
    b.plane("grass", "terrain", -far, far, -far, far, -0.02, color=pal["grass"])

    # roads: east-west roads run the full length, north-south ones are cut at the junctions
    for cj in c:
        b.plane("asphalt", "road", -length, length, cj - hw, cj + hw, 0.0, pal["asphalt"])
    ns_spans = _spans(c, hw, length)
    for ci in c:
        for y0, y1 in ns_spans:
            b.plane("asphalt", "road", ci - hw, ci + hw, y0, y1, 0.0, pal["asphalt"])

    # sidewalks: north-south strips run through the corners, east-west strips fill between them
    ew_spans = _spans(c, hw + sw, length)
    for ci in c:
        for y0, y1 in ns_spans:
            for side in (-1, 1):
                x0, x1 = sorted((ci + side * hw, ci + side * (hw + sw)))
                b.box("sidewalk", "sidewalk", x0, x1, y0, y1, 0.0, kh, pal["paving"])
                kx0, kx1 = sorted((ci + side * hw, ci + side * (hw + 0.25)))
                b.box("kerb", "sidewalk", kx0, kx1, y0, y1, 0.0, kh + 0.01, pal["kerb"])
    for cj in c:
        for x0, x1 in ew_spans:
            for side in (-1, 1):
                y0, y1 = sorted((cj + side * hw, cj + side * (hw + sw)))
                b.box("sidewalk", "sidewalk", x0, x1, y0, y1, 0.0, kh, pal["paving"])
                ky0, ky1 = sorted((cj + side * hw, cj + side * (hw + 0.25)))
                b.box("kerb", "sidewalk", x0, x1, ky0, ky1, 0.0, kh + 0.01, pal["kerb"])

    _road_wear(t, b, pal)
    _markings(t, b, rng, pal["marking"])
    _street_furniture(t, b, rng)
    for i in range(n - 1):
        for j in range(n - 1):
            x0, x1 = c[i] + hw + sw, c[i + 1] - hw - sw
            y0, y1 = c[j] + hw + sw, c[j + 1] - hw - sw
            b.box("lot", "terrain", x0, x1, y0, y1, 0.0, kh, color=pal["grass"])
            if rng.random() < t.park_fraction:
                _park(t, b, rng, x0, x1, y0, y1)
            else:
                _urban_block(t, b, rng, x0, x1, y0, y1)
    _countryside(t, b, rng, half, length)
    return b.build(t.params(), half, length)


def _road_wear(t: ProceduralTownRegion, b: _Builder, pal) -> None:
    """Repair patches and resurfaced lanes in a darker or lighter asphalt, still labelled road."""
    rate = pal["wear"]
    if rate <= 0:
        return
    rng = np.random.default_rng([t.town_seed, 104729])
    hw = t.road_width / 2
    length = t.road_half_length
    spans = _spans(t.road_centres, hw + t.sidewalk_width, length)
    for axis in (0, 1):
        for rc in t.road_centres:
            for s0, s1 in spans:
                for _ in range(int(rng.poisson(rate * (s1 - s0) / 100.0))):
                    size = rng.uniform(1.5, 14.0)
                    a0 = rng.uniform(s0, max(s0, s1 - size))
                    lane = rng.uniform(0.6, 1.0) * hw
                    o0 = rng.uniform(-hw, hw - lane)
                    shade = rng.uniform(0.65, 1.5)
                    colour = tuple(float(np.clip(c * shade, 0, 1)) for c in pal["asphalt"])
                    z = float(rng.uniform(0.001, 0.003))  # below the markings (0.004), apart from each other
                    if axis == 0:
                        b.plane("asphalt", "road", rc + o0, rc + o0 + lane, a0, min(s1, a0 + size), z, colour)
                    else:
                        b.plane("asphalt", "road", a0, min(s1, a0 + size), rc + o0, rc + o0 + lane, z, colour)


def _markings(t: ProceduralTownRegion, b: _Builder, rng: np.random.Generator, white) -> None:
    c = t.road_centres
    hw, sw = t.road_width / 2, t.sidewalk_width
    length = t.road_half_length
    z = 0.004
    spans = _spans(c, hw + sw, length)
    for axis in (0, 1):
        for rc in c:
            for s0, s1 in spans:
                # dashed centre line, solid edge lines
                for d0 in np.arange(s0 + 1.5, s1 - 3.0, 9.0):
                    _strip(b, axis, rc, d0, d0 + 3.0, -0.075, 0.075, z, white)
                for e in (-1, 1):
                    _strip(b, axis, rc, s0, s1, e * (hw - 0.35), e * (hw - 0.23), z, white)
    # stop lines and zebra crossings at the junction mouths, right-hand lanes
    for xi in c:
        for yj in c:
            zebra = rng.random() < 0.6
            for axis in (0, 1):
                road, cross = (xi, yj) if axis == 0 else (yj, xi)
                for direction in (-1, 1):
                    mouth = cross + direction * (hw + sw)
                    if zebra:
                        b.crossings.append((axis, road, min(mouth, mouth - direction * 3.0),
                                            max(mouth, mouth - direction * 3.0), -hw + 0.6, hw - 0.1))
                        for k in np.arange(-hw + 0.6, hw - 0.4, 1.0):
                            _strip(b, axis, road, min(mouth, mouth - direction * 3.0),
                                   max(mouth, mouth - direction * 3.0), k, k + 0.5, z, white)
                    stop = mouth + direction * (3.6 if zebra else 0.3)
                    lane_sign = 1 if direction < 0 else -1  # traffic approaching this mouth keeps right
                    if axis == 1:
                        lane_sign = -lane_sign
                    _strip(b, axis, road, min(stop, stop + direction * 0.4), max(stop, stop + direction * 0.4),
                           *sorted((lane_sign * 0.15, lane_sign * (hw - 0.3))), z, white)


def _spans(c: np.ndarray, inset: float, length: float) -> list[tuple[float, float]]:
    """Intervals along a road between the junction bands (half width `inset`) and out to +-length."""
    inner = [(c[k] + inset, c[k + 1] - inset) for k in range(len(c) - 1)]
    return [(-length, c[0] - inset), *inner, (c[-1] + inset, length)]


def _strip(b: _Builder, axis: int, road: float, a0: float, a1: float, o0: float, o1: float, z: float, color) -> None:
    """A marking rectangle spanning [a0, a1] along a road and [o0, o1] across it."""
    if a1 - a0 <= 0.01:
        return
    if axis == 0:  # north-south road at x=road
        b.plane("marking", "road", road + o0, road + o1, a0, a1, z, color)
    else:
        b.plane("marking", "road", a0, a1, road + o0, road + o1, z, color)


def _tree(b: _Builder, rng: np.random.Generator, x: float, y: float, z: float, scale: float = 1.0) -> None:
    h = rng.uniform(2.2, 3.2) * scale
    b.add("cylinder", "bark", "vegetation", (x, y, z), (0.32 * scale, 0.32 * scale, h + 0.5), 0.0, (0.30, 0.22, 0.15))
    r = rng.uniform(1.6, 2.6) * scale
    green = _jitter(rng, (0.20, 0.34, 0.11), 0.05)
    b.add("sphere", "foliage", "vegetation", (x, y, z + h - 0.3 * r), (2 * r, 2 * r, 2.2 * r),
          rng.uniform(0, 360), green)


def _street_furniture(t: ProceduralTownRegion, b: _Builder, rng: np.random.Generator) -> None:
    c = t.road_centres
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    half = t.half_extent
    metal = (0.35, 0.36, 0.38)
    for axis in (0, 1):
        for rc in c:
            trees = rng.random() < t.street_tree_fraction
            for side in (-1, 1):
                offset = side * (hw + 0.6)
                phase = rng.uniform(0, t.lamp_spacing) if side > 0 else 0.0
                for s0, s1 in [(c[k] + hw + sw + 1.0, c[k + 1] - hw - sw - 1.0) for k in range(len(c) - 1)]:
                    start = s0 + (phase % t.lamp_spacing) * 0.5 + 2.0
                    for along in np.arange(start, s1 - 1.0, t.lamp_spacing):
                        _lamp(b, axis, rc, along, offset, side, kh, metal)
                        mid = along + t.lamp_spacing / 2
                        if trees and mid < s1 - 2.0:
                            across = rc + side * (hw + sw * 0.55)
                            tx, ty = (across, mid) if axis == 0 else (mid, across)
                            _tree(b, rng, tx, ty, kh, 0.7)
    # traffic lights and signs at every junction corner, facing the traffic that approaches it
    for xi in c:
        for yj in c:
            phase = int(rng.integers(2))  # 0: north-south green
            for dx, dy in ((1, -1), (-1, 1), (-1, -1), (1, 1)):
                px, py = xi + dx * (hw + 0.5), yj + dy * (hw + 0.5)
                # (1,-1) near-right corner for northbound traffic, (-1,1) for southbound,
                # (-1,-1) for westbound... pick the approach whose right-hand side this corner is
                if (dx, dy) == (1, -1):
                    facing, ns = 180.0, True     # faces south (-y), northbound traffic
                elif (dx, dy) == (-1, 1):
                    facing, ns = 0.0, True
                elif (dx, dy) == (1, 1):
                    facing, ns = 270.0, False    # faces east (+x), westbound traffic
                else:
                    facing, ns = 90.0, False
                if max(abs(px), abs(py)) > half:
                    continue
                green = (phase == 0) == ns
                _traffic_light(b, px, py, kh, facing, green, metal)
                if rng.random() < t.junction_sign_fraction:
                    kind = ("disc", "triangle", "panel", "square", "direction", "direction")[int(rng.integers(6))]
                    sx_, sy_ = px + dx * 1.6 * (0 if ns else 1), py + dy * 1.6 * (1 if ns else 0)
                    _sign(b, sx_, sy_, kh, facing, kind, metal)
    _street_signs(t, b, metal)
    _guard_railings(t, b)


def _facing_vec(facing: float) -> tuple[float, float]:
    h = math.radians(facing)
    return -math.sin(h), math.cos(h)


def _lamp(b, axis, rc, along, offset, side, kh, metal) -> None:
    x, y = (rc + offset, along) if axis == 0 else (along, rc + offset)
    ux, uy = (-side, 0.0) if axis == 0 else (0.0, -side)  # unit vector towards the road centre
    height = 7.5
    b.add("cylinder", "metal", "pole", (x, y, kh), (0.18, 0.18, height), 0.0, metal)
    arm = 1.6
    b.add("box", "metal", "pole", (x + ux * arm / 2, y + uy * arm / 2, kh + height - 0.12),
          (arm, 0.1, 0.1) if axis == 0 else (0.1, arm, 0.1), 0.0, metal)
    hx, hy = x + ux * arm, y + uy * arm
    head, glass = ((0.7, 0.3, 0.18), (0.55, 0.22, 0.0)) if axis == 0 else ((0.3, 0.7, 0.18), (0.22, 0.55, 0.0))
    b.add("box", "metal", "pole", (hx, hy, kh + height - 0.2), head, 0.0, metal)
    b.add("plane", "lamp", "pole", (hx, hy, kh + height - 0.205), glass, 0.0, (1, 1, 1))
    b.lamps.append((hx, hy, kh + height - 0.3))


def _traffic_light(b, x, y, kh, facing, green, metal) -> None:
    b.add("cylinder", "metal", "pole", (x, y, kh), (0.14, 0.14, 3.9), 0.0, metal)
    fx, fy = _facing_vec(facing)
    hx, hy = x + fx * 0.2, y + fy * 0.2
    b.add("box", "housing", "traffic light", (hx, hy, kh + 2.7), (0.34, 0.26, 1.0), facing, (0.08, 0.08, 0.08))
    for k, colour in enumerate(("red", "amber", "green")):
        lit = (colour == "green") == green and colour != "amber"
        material = f"signal_{colour}" if lit else "signal_off"
        b.add("disc", material, "traffic light", (hx + fx * 0.135, hy + fy * 0.135, kh + 3.43 - k * 0.31),
              (0.22, 0.0, 0.22), facing, (1, 1, 1))


def _sign(b, x, y, kh, facing, kind, metal, below: str | None = None) -> None:
    """A sign on its own post; its back is labelled traffic sign too, as in Cityscapes. `below`: a
    second plate under the first (a supplementary plate, or two signs on one post)."""
    shape, size, colour = _SIGNS[kind]
    top = kh + (2.9 if kind == "direction" else 2.3)  # plate centre; direction signs clear pedestrians
    fx, fy = _facing_vec(facing)
    plates = [(kind, top)]
    if below is not None:
        plates.append((below, top - size[2] / 2 - _SIGNS[below][1][2] / 2 - 0.08))
    b.add("cylinder", "metal", "pole", (x, y, kh), (0.08, 0.08, top + size[2] / 2 - kh - 0.05), 0.0, metal)
    for k, z in plates:
        shape, size, colour = _SIGNS[k]
        z0 = z - size[2] / 2  # shapes stand on their base
        b.add(shape, "sign", "traffic sign", (x + fx * 0.06, y + fy * 0.06, z0), size, facing, colour)
        b.add(shape, "sign_back", "traffic sign", (x + fx * 0.05, y + fy * 0.05, z0), size, facing + 180.0,
              (0.6, 0.6, 0.6))


def _street_signs(t: ProceduralTownRegion, b: _Builder, metal) -> None:
    """Signs along every street, at the kerb and facing the traffic of their side: Cityscapes has
    ~0.5 % sign pixels, which junction corners alone (one sign per approach at most) cannot give.
    Their own random stream, so the rest of the town keeps its draws."""
    rng = np.random.default_rng([t.town_seed, 15485863])
    c = t.road_centres
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    poles = np.asarray(b.rows.get(("cylinder", "metal", "pole"), []), dtype=np.float64).reshape(-1, len(COLUMNS))
    kinds = ("disc", "disc", "triangle", "panel", "square")
    for axis in (0, 1):
        for rc in c:
            for side in (-1, 1):
                facing = (180.0 if side > 0 else 0.0) if axis == 0 else (270.0 if side > 0 else 90.0)
                across = rc + side * (hw + 0.45)
                for s0, s1 in [(c[k] + hw + sw + 4.0, c[k + 1] - hw - sw - 4.0) for k in range(len(c) - 1)]:
                    for along in rng.uniform(s0, s1, size=int(rng.poisson(t.signs_per_100m * (s1 - s0) / 100))):
                        x, y = (across, along) if axis == 0 else (along, across)
                        if len(poles) and np.min(np.hypot(poles[:, 0] - x, poles[:, 1] - y)) < 1.5:
                            continue  # not on top of a lamp post or another sign
                        kind = kinds[int(rng.integers(len(kinds)))]
                        below = None
                        if rng.random() < 0.35:
                            below = "plate" if rng.random() < 0.6 else kinds[int(rng.integers(len(kinds)))]
                        _sign(b, x, y, kh, facing, kind, metal, below)
                        poles = np.vstack([poles, [[x, y] + [0.0] * (len(COLUMNS) - 2)]])


def _fence(b: _Builder, rng, x0, x1, y0, y1, z0, height, style: str, colour, solid=True) -> None:
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
        b.add("box", "fence", "fence", (cx, cy, z), size, 0.0, colour)

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
        b.solids.append((cx, cy, z0, *size, 0.0))


def _guard_railings(t: ProceduralTownRegion, b: _Builder) -> None:
    """Pedestrian guard railings along the kerb after some junctions' crossings (fence)."""
    rng = np.random.default_rng([t.town_seed, 32452843])
    c = t.road_centres
    hw, sw, kh = t.road_width / 2, t.sidewalk_width, t.kerb_height
    colour = (0.30, 0.32, 0.33)
    for axis in (0, 1):
        for rc in c:
            for side in (-1, 1):
                o = rc + side * (hw + 0.3)
                for k in range(len(c) - 1):
                    for start, direction in ((c[k] + hw + sw, 1), (c[k + 1] - hw - sw, -1)):
                        if rng.random() >= t.railing_fraction:
                            continue
                        a0 = start + direction * 3.5  # beyond the zebra crossing of the junction mouth
                        a1 = a0 + direction * float(rng.uniform(6.0, 14.0))
                        a0, a1 = sorted((a0, a1))
                        if axis == 0:
                            _fence(b, rng, o - 0.03, o + 0.03, a0, a1, kh, 1.0, "railing", colour)
                        else:
                            _fence(b, rng, a0, a1, o - 0.03, o + 0.03, kh, 1.0, "railing", colour)


def _split(rng: np.random.Generator, lo: float, hi: float, smin: float, smax: float) -> list[float]:
    """Random cut positions from lo to hi with pieces in [smin, smax] (the last one absorbs slack)."""
    cuts = [lo]
    while hi - cuts[-1] > smax:
        cuts.append(cuts[-1] + rng.uniform(smin, smax))
        if hi - cuts[-1] < smin:
            cuts.pop()
            cuts.append((cuts[-1] + hi) / 2)
            break
    cuts.append(hi)
    return cuts


def _urban_block(t, b: _Builder, rng, x0, x1, y0, y1) -> None:
    kh = t.kerb_height
    depth = min(18.0, (x1 - x0) / 2 - 4.0, (y1 - y0) / 2 - 4.0)
    xs = _split(rng, x0, x1, 9.0, 22.0)
    ys = _split(rng, y0, y1, 9.0, 22.0)
    floors_hi = int(rng.integers(t.min_floors, t.max_floors + 1))
    cells = []
    # perimeter parcels: south and north rows span full width, west/east columns fill between
    for k in range(len(xs) - 1):
        cells.append((xs[k], xs[k + 1], y0, y0 + depth, "s"))
        cells.append((xs[k], xs[k + 1], y1 - depth, y1, "n"))
    for k in range(len(ys) - 1):
        a, c_ = max(ys[k], y0 + depth), min(ys[k + 1], y1 - depth)
        if c_ - a > 4.0:
            cells.append((x0, x0 + depth, a, c_, "w"))
            cells.append((x1 - depth, x1, a, c_, "e"))
    for cx0, cx1, cy0, cy1, side in cells:
        if rng.random() < 0.85:
            setback = float(rng.choice([0.0, 0.0, 0.5, 1.5, 3.0]))
            gap = float(rng.choice([0.0, 0.0, 0.6]))
            bx0, bx1, by0, by1 = cx0 + gap / 2, cx1 - gap / 2, cy0 + gap / 2, cy1 - gap / 2
            if side == "s":
                by0 += setback
            elif side == "n":
                by1 -= setback
            elif side == "w":
                bx0 += setback
            else:
                bx1 -= setback
            floors = int(np.clip(floors_hi + rng.integers(-2, 3), t.min_floors, t.max_floors))
            _building(t, b, rng, bx0, bx1, by0, by1, kh, floors, side)
            if setback >= 1.5 and rng.random() < t.front_boundary_fraction:
                _front_boundary(b, rng, cx0, cx1, cy0, cy1, kh, side)
        else:
            _yard(b, rng, cx0, cx1, cy0, cy1, kh, side)
    # courtyard trees
    for _ in range(int(rng.integers(0, 5))):
        _tree(b, rng, rng.uniform(x0 + depth + 2, x1 - depth - 2), rng.uniform(y0 + depth + 2, y1 - depth - 2), kh)


def _building(t, b: _Builder, rng, x0, x1, y0, y1, z0, floors, street_side) -> None:
    fh = t.floor_height
    height = floors * fh + 0.6
    colour = _jitter(rng, _FACADES[int(rng.integers(len(_FACADES)))], 0.04)
    b.box("facade", "building", x0, x1, y0, y1, z0, z0 + height, color=colour, solid=True)
    b.box("roof", "building", x0 + 0.2, x1 - 0.2, y0 + 0.2, y1 - 0.2, z0 + height, z0 + height + 0.5,
          color=_jitter(rng, (0.35, 0.34, 0.33), 0.05))
    # windows on every face (street side gets a shop-front ground floor)
    faces = {
        "s": ((x0 + x1) / 2, y0, x1 - x0, 180.0),
        "n": ((x0 + x1) / 2, y1, x1 - x0, 0.0),
        "w": (x0, (y0 + y1) / 2, y1 - y0, 90.0),
        "e": (x1, (y0 + y1) / 2, y1 - y0, 270.0),
    }
    spacing = float(rng.uniform(2.8, 3.6))
    win_w = float(rng.uniform(1.1, 1.6))
    win_h = float(rng.uniform(1.3, 1.8))
    frame = _jitter(rng, (0.25, 0.27, 0.30), 0.05)
    for side, (fx, fy, width, facing) in faces.items():
        nx, ny = _facing_vec(facing)
        tx, ty = -ny, nx  # along the face
        cols = int((width - 1.0) // spacing)
        if cols < 1:
            continue
        offsets = (np.arange(cols) - (cols - 1) / 2) * spacing
        first = 0
        if side == street_side:
            first = 1
            shop = _jitter(rng, (0.20, 0.22, 0.25), 0.04)
            for o in offsets:
                px, py = fx + tx * o + nx * 0.04, fy + ty * o + ny * 0.04
                b.add("panel", "window", "building", (px, py, z0 + 0.4), (min(spacing - 0.5, 2.6), 0, 2.3), facing,
                      shop,
                      a=float(rng.random()))
        for f in range(first, floors):
            zf = z0 + f * fh + 0.9
            for o in offsets:
                px, py = fx + tx * o + nx * 0.04, fy + ty * o + ny * 0.04
                b.add("panel", "window", "building", (px, py, zf), (win_w, 0, win_h), facing, frame,
                      a=float(rng.random()))


def _street_edge(x0, x1, y0, y1, side: str, thickness: float) -> tuple[float, float, float, float]:
    """The strip of a parcel along its street side ('s', 'n', 'w' or 'e'), `thickness` metres deep."""
    return {"s": (x0, x1, y0, y0 + thickness), "n": (x0, x1, y1 - thickness, y1),
            "w": (x0, x0 + thickness, y0, y1), "e": (x1 - thickness, x1, y0, y1)}[side]


def _yard(b: _Builder, rng, x0, x1, y0, y1, kh, side) -> None:
    kind = int(rng.choice(3, p=[0.4, 0.3, 0.3]))  # wall, fence, hedge
    edge = _street_edge(x0, x1, y0, y1, side, 0.3)
    if kind == 0:
        b.box("wall", "wall", *edge, kh, kh + rng.uniform(1.4, 2.4), color=_jitter(rng, _WALLS[int(rng.integers(3))]),
              solid=True)
    elif kind == 1:
        _fence(b, rng, *edge, kh, float(rng.uniform(1.2, 1.9)), ("boards", "railing")[int(rng.integers(2))],
               _jitter(rng, _FENCES[int(rng.integers(len(_FENCES)))]))
    else:
        ex0, ex1, ey0, ey1 = edge
        cx, cy = (ex0 + ex1) / 2, (ey0 + ey1) / 2
        if side in "sn":
            b.box("hedge", "vegetation", ex0, ex1, cy - 0.5, cy + 0.5, kh, kh + rng.uniform(1.0, 1.6),
                  color=_jitter(rng, (0.18, 0.32, 0.10), 0.04))
        else:
            b.box("hedge", "vegetation", cx - 0.5, cx + 0.5, ey0, ey1, kh, kh + rng.uniform(1.0, 1.6),
                  color=_jitter(rng, (0.18, 0.32, 0.10), 0.04))
    for _ in range(int(rng.integers(0, 3))):
        _tree(b, rng, rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), kh)


def _front_boundary(b: _Builder, rng, x0, x1, y0, y1, kh, side) -> None:
    """A low garden wall or a fence along the street edge of a set-back building, with a gate."""
    ex0, ex1, ey0, ey1 = _street_edge(x0, x1, y0, y1, side, 0.25)
    along_x = side in "sn"
    a0, a1 = (ex0, ex1) if along_x else (ey0, ey1)
    gate = float(rng.uniform(a0 + 1.5, a1 - 2.7)) if a1 - a0 > 5.0 else None
    spans = [(a0, a1)] if gate is None else [(a0, gate), (gate + 1.2, a1)]
    wall = rng.random() < 0.55
    colour = _jitter(rng, (_WALLS if wall else _FENCES)[int(rng.integers(3))])
    height = float(rng.uniform(0.6, 1.2)) if wall else float(rng.uniform(0.9, 1.5))
    style = ("boards", "railing")[int(rng.integers(2))]
    for s0, s1 in spans:
        px0, px1, py0, py1 = (s0, s1, ey0, ey1) if along_x else (ex0, ex1, s0, s1)
        if wall:
            b.box("wall", "wall", px0, px1, py0, py1, kh, kh + height, color=colour, solid=True)
        else:
            _fence(b, rng, px0, px1, py0, py1, kh, height, style, colour)


def _park(t, b: _Builder, rng, x0, x1, y0, y1) -> None:
    kh = t.kerb_height
    hedge = _jitter(rng, (0.18, 0.32, 0.10), 0.04)
    edges = ((x0, x1, y0, y0 + 0.9), (x0, x1, y1 - 0.9, y1), (x0, x0 + 0.9, y0 + 0.9, y1 - 0.9),
             (x1 - 0.9, x1, y0 + 0.9, y1 - 0.9))
    railing = rng.random() < 0.35  # a metal railing on a low wall instead of a hedge
    colour = _jitter(rng, _FENCES[2 + int(rng.integers(2))])
    for (ax0, ax1, ay0, ay1) in edges:
        # hedge or railing with an entrance gap in the middle
        if ax1 - ax0 > ay1 - ay0:
            mid = (ax0 + ax1) / 2
            pieces = ((ax0, mid - 2, ay0 + 0.3, ay1 - 0.3), (mid + 2, ax1, ay0 + 0.3, ay1 - 0.3))
        else:
            mid = (ay0 + ay1) / 2
            pieces = ((ax0 + 0.3, ax1 - 0.3, ay0, mid - 2), (ax0 + 0.3, ax1 - 0.3, mid + 2, ay1))
        for px0, px1, py0, py1 in pieces:
            if railing:
                b.box("wall", "wall", px0, px1, py0, py1, kh, kh + 0.45, color=_jitter(rng, _WALLS[0]), solid=True)
                _fence(b, rng, px0, px1, py0, py1, kh + 0.45, 1.1, "railing", colour, solid=False)
            else:
                b.box("hedge", "vegetation", px0, px1, py0, py1, kh, kh + 1.2, color=hedge)
    for _ in range(int(rng.integers(8, 18))):
        _tree(b, rng, rng.uniform(x0 + 3, x1 - 3), rng.uniform(y0 + 3, y1 - 3), kh, float(rng.uniform(0.9, 1.4)))


def _countryside(t, b: _Builder, rng, half, length) -> None:
    placed = 0
    tries = 0
    while placed < t.countryside_trees and tries < 20 * max(1, t.countryside_trees):
        tries += 1
        x, y = rng.uniform(-length - 60, length + 60, size=2)
        if max(abs(x), abs(y)) < half + 4 or t.surface_at(x, y) != "other":
            continue
        keep_off = t.road_width / 2 + t.sidewalk_width + 3
        if t._nearest_centre_dist(x) < keep_off or t._nearest_centre_dist(y) < keep_off:
            continue
        _tree(b, rng, x, y, 0.0, float(rng.uniform(1.0, 1.6)))
        placed += 1


__all__ = ["COLUMNS", "SHAPES", "ProceduralTownRegion", "TownLayout", "town_palette"]
