"""Ambient population of the procedural town: parked cars along the kerbs, vehicles standing in the
lanes, pedestrians on sidewalks and zebra crossings, cyclists and motorcyclists, occasional buses and
trucks.

The population is part of the scene, not of the condition: it is drawn once per scene (from the
scene seed alone, so the location and the paper's 0-3 dynamic `objects` keep their draws), stored
in the descriptor's `ambient` list and rendered identically under every condition. Densities come
from `region.population` (conf/region/procedural_town.yaml). Placement rejects every footprint that
overlaps another entity, a dynamic object, the ego vehicle, a pole or a tree trunk.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Mapping

import numpy as np

from pairedgta.errors import ConfigError
from pairedgta.scene.descriptor import AmbientEntity, SceneDescriptor

# model name -> (length, width, height) in metres; the Blender models are built from these sizes
CAR_MODELS: dict[str, tuple[float, float, float]] = {
    "blista": (3.9, 1.72, 1.45), "issi": (3.7, 1.68, 1.5),            # compact hatchbacks
    "asea": (4.55, 1.78, 1.42), "premier": (4.7, 1.8, 1.44), "sultan": (4.6, 1.8, 1.4),  # saloons
    "regina": (4.85, 1.82, 1.5),                                       # estate
    "baller": (4.85, 1.95, 1.78), "granger": (5.1, 2.0, 1.85),         # SUVs
    "speedo": (5.2, 2.0, 2.15), "burrito": (5.0, 1.98, 2.05),          # vans (Cityscapes: car)
}
CAR_DEFAULT = (4.6, 1.8, 1.45)
FOOTPRINT: dict[str, tuple[float, float]] = {  # category -> (length, width)
    "truck": (7.6, 2.5), "bus": (12.1, 2.6), "motorcycle": (2.0, 0.8), "bicycle": (1.8, 0.6),
    "rider": (2.0, 0.8), "person": (0.55, 0.6),
}
TRUCK_MODELS = ("mule", "benson")
BUS_MODELS = ("bus", "coach")
MOTORCYCLE_MODELS = ("bati", "akuma", "faggio")
BICYCLE_MODELS = ("bmx", "cruiser", "tribike")
PEDESTRIAN_MODELS = ("a_m_y_business_01", "a_f_y_tourist_01", "a_m_m_skater_01", "a_f_m_bevhills_01",
                     "a_m_y_hipster_01", "a_f_y_hipster_02", "a_m_o_soucent_01", "a_f_y_runner_01")
CYCLIST_MODELS = ("a_m_y_cyclist_01", "a_m_y_roadcyc_01")
MOTORCYCLIST_MODELS = ("a_m_y_motox_01", "a_m_y_motox_02")

# paints in proportion to what streets show (white, black, greys and silver dominate), sRGB 0-255
PAINTS = ((235, 235, 232), (20, 20, 22), (150, 152, 155), (95, 97, 100), (190, 192, 195), (30, 45, 90),
          (140, 20, 20), (25, 70, 40), (200, 170, 120), (60, 30, 25), (220, 120, 20), (40, 110, 170))
PAINT_WEIGHTS = (0.22, 0.2, 0.14, 0.1, 0.1, 0.07, 0.06, 0.03, 0.03, 0.02, 0.01, 0.02)
CLOTHES = ((25, 25, 30), (60, 62, 70), (30, 45, 85), (150, 150, 150), (235, 235, 230), (120, 30, 35),
           (40, 80, 50), (180, 140, 90), (70, 50, 40), (200, 90, 40), (90, 60, 120), (50, 110, 160))
TROUSERS = ((30, 32, 40), (40, 50, 80), (25, 25, 25), (90, 85, 75), (150, 130, 100), (60, 70, 90))
BUS_PAINTS = ((235, 235, 230), (220, 180, 30), (30, 90, 160), (170, 30, 30))


@dataclass(frozen=True)
class PopulationConfig:
    """Densities of the ambient population (all counts are Poisson means)."""

    radius: float = 75.0                  # entities within this distance (m) of the ego vehicle
    behind: float = 8.0                   # ... and at most this far behind it (the camera looks ahead)
    parked_cars_per_100m: float = 0.0     # per kerb (each side of each street)
    lane_vehicles_per_100m: float = 0.0   # cars, buses and trucks standing in each lane
    heavy_share: float = 0.0              # share of lane vehicles that are buses or trucks
    pedestrians_per_100m: float = 0.0     # per sidewalk (each side of each street)
    standing_share: float = 0.3           # pedestrians standing instead of walking
    crossing_pedestrians: float = 0.0     # per zebra crossing in range
    cyclists_per_100m: float = 0.0        # riders on bicycles, per lane
    motorcyclists_per_100m: float = 0.0   # riders on motorcycles, per lane
    parked_two_wheelers_per_100m: float = 0.0  # bicycles and motorcycles standing on each sidewalk
    ego_clearance: float = 7.0            # free lane (m) ahead of the ego vehicle
    max_entities: int = 400

    @classmethod
    def from_cfg(cls, cfg: Mapping[str, Any] | None) -> "PopulationConfig":
        cfg = dict(cfg or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ConfigError(f"region.population: unknown keys {unknown}; known: {sorted(known)}")
        try:
            pc = cls(**{k: (int(v) if k == "max_entities" else float(v)) for k, v in cfg.items()})
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"region.population: {exc}; every value is a number") from None
        for f in fields(pc):
            v = getattr(pc, f.name)
            if not math.isfinite(v) or v < 0:
                raise ConfigError(f"region.population.{f.name}={v} is invalid; set it to a number >= 0")
        for key in ("heavy_share", "standing_share"):
            if getattr(pc, key) > 1:
                raise ConfigError(f"region.population.{key}={getattr(pc, key)} is invalid; set it in [0, 1]")
        if pc.max_entities > 1000:
            raise ConfigError("region.population.max_entities must be <= 1000 (instance ids are 10 bits)")
        return pc

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def empty(self) -> bool:
        d = self.to_dict()
        return not any(v > 0 for k, v in d.items() if k.endswith("_100m") or k == "crossing_pedestrians")


def footprint(category: str, model: str) -> tuple[float, float]:
    """(length, width) in metres of a model, as the renderer draws it."""
    if category == "car":
        length, width, _ = CAR_MODELS.get(model, CAR_DEFAULT)
        return length, width
    return FOOTPRINT[category]


def _half_extents(length: float, width: float, heading: float) -> tuple[float, float]:
    """World axis-aligned half extents of a length x width footprint (length along the heading)."""
    h = math.radians(heading)
    c, s = abs(math.cos(h)), abs(math.sin(h))
    return c * width / 2 + s * length / 2, s * width / 2 + c * length / 2


class _Occupancy:
    """Axis-aligned boxes already taken; a candidate must keep `gap` metres from every one."""

    def __init__(self, gap: float = 0.35) -> None:
        self.boxes: list[tuple[float, float, float, float]] = []  # cx, cy, hx, hy
        self.gap = gap

    def free(self, cx, cy, hx, hy) -> bool:
        if not self.boxes:
            return True
        b = np.asarray(self.boxes)
        clash = (np.abs(b[:, 0] - cx) < b[:, 2] + hx + self.gap) & (np.abs(b[:, 1] - cy) < b[:, 3] + hy + self.gap)
        return not bool(clash.any())

    def add(self, cx, cy, hx, hy) -> None:
        self.boxes.append((float(cx), float(cy), float(hx), float(hy)))


def _heading(axis: int, direction: int) -> float:
    """Heading (deg, ccw from +y) of travel along +/- the road's axis (0: north-south, 1: east-west)."""
    if axis == 0:
        return 0.0 if direction > 0 else 180.0
    return 270.0 if direction > 0 else 90.0


def _point(axis: int, road: float, along: float, across: float) -> tuple[float, float]:
    return (road + across, along) if axis == 0 else (along, road + across)


def _right_sign(axis: int, direction: int) -> float:
    """Sign of the across-road offset on the right-hand side of travel."""
    h = math.radians(_heading(axis, direction))
    return math.copysign(1.0, math.cos(h) if axis == 0 else math.sin(h))


def _pick(rng: np.random.Generator, options, weights=None):
    if weights is not None:
        w = np.asarray(weights, float)
        return options[int(rng.choice(len(options), p=w / w.sum()))]
    return options[int(rng.integers(len(options)))]


def populate(town, descriptor: SceneDescriptor) -> SceneDescriptor:
    """`descriptor` with the town's ambient population around its ego location."""
    pop: PopulationConfig = town.population
    if pop.empty:
        return replace(descriptor, ambient=())
    rng = np.random.default_rng(np.random.SeedSequence([int(descriptor.seed), 0xA3B1E7]))
    loc = descriptor.location
    h = math.radians(loc.heading)
    fwd, right = np.array([-math.sin(h), math.cos(h)]), np.array([math.cos(h), math.sin(h)])
    ego = np.array([loc.x, loc.y])
    occ = _Occupancy()
    # the ego vehicle and the free lane ahead of it
    cx, cy = ego + fwd * (pop.ego_clearance / 2 - 1.0)
    occ.add(cx, cy, *_half_extents(pop.ego_clearance + 4.8, 2.2, loc.heading))
    # the paper's dynamic objects keep their places
    for ob in descriptor.objects:
        xy = ego + fwd * ob.forward + right * ob.right
        length, width = footprint(ob.category, ob.model)
        if ob.category == "person":  # any heading: a circle
            length = width = max(length, width)
        occ.add(*xy, *_half_extents(length, width, loc.heading + ob.heading))
    # poles, trunks and other street furniture on the sidewalks
    layout = town.layout()
    for key in (("cylinder", "metal", "pole"), ("cylinder", "bark", "vegetation")):
        rows = layout.groups.get(key)
        if rows is not None:
            for r in rows:
                if math.hypot(r[0] - loc.x, r[1] - loc.y) < pop.radius + 10:
                    occ.add(r[0], r[1], r[3] / 2, r[4] / 2)
    for r in layout.solids:  # buildings and walls
        if math.hypot(r[0] - loc.x, r[1] - loc.y) < pop.radius + 60:
            occ.add(r[0], r[1], r[3] / 2, r[4] / 2)

    entities: list[AmbientEntity] = []

    def in_range(x: float, y: float) -> bool:
        d = np.array([x, y]) - ego
        return float(np.hypot(*d)) <= pop.radius and float(d @ fwd) >= -pop.behind

    def place(category, model, x, y, heading, color, color2, role, scale=1.0, pose=0.0) -> bool:
        if len(entities) >= pop.max_entities or not in_range(x, y):
            return False
        length, width = footprint(category, model)
        if category == "person":  # a walker's stride reaches ~0.4 m ahead and behind the hips
            length = width = (max(length, width) + 0.75 * abs(pose)) * scale
        hx, hy = _half_extents(length, width, heading)
        if not occ.free(x, y, hx, hy):
            return False
        occ.add(x, y, hx, hy)
        entities.append(AmbientEntity(
            category=category, model=model, x=round(float(x), 3), y=round(float(y), 3),
            heading=round(float(heading) % 360.0, 3), color=tuple(int(v) for v in color),  # type: ignore[arg-type]
            secondary_color=tuple(int(v) for v in color2), scale=round(float(scale), 3),  # type: ignore[arg-type]
            pose=round(float(pose), 3), role=role))
        return True

    def person_look():
        return (_pick(rng, CLOTHES), _pick(rng, TROUSERS), float(rng.normal(1.0, 0.055)).__round__(3))

    c = town.road_centres
    hw, sw = town.road_width / 2, town.sidewalk_width
    length = town.road_half_length
    segments = [(c[k] + hw + sw, c[k + 1] - hw - sw) for k in range(len(c) - 1)]
    segments = [(-length, c[0] - hw - sw), *segments, (c[-1] + hw + sw, length)]
    for axis in (0, 1):
        for road in c:
            for s0, s1 in segments:
                # nearest point of this street segment to the ego: skip segments out of range
                px, py = _point(axis, road, float(np.clip(loc.y if axis == 0 else loc.x, s0, s1)), 0.0)
                if math.hypot(px - loc.x, py - loc.y) > pop.radius + hw + sw:
                    continue
                lo, hi = max(s0, (loc.y if axis == 0 else loc.x) - pop.radius - 5), min(
                    s1, (loc.y if axis == 0 else loc.x) + pop.radius + 5)
                span = hi - lo
                if span <= 1.0:
                    continue
                for direction in (1, -1):
                    heading = _heading(axis, direction)
                    side = _right_sign(axis, direction)
                    _street_side(rng, pop, place, person_look, axis, road, (s0, s1), lo, hi, span, heading, side,
                                 hw, sw)
    # pedestrians on the zebra crossings in range
    for axis, road, a0, a1, o0, o1 in layout.crossings:
        axis = int(axis)
        mid = _point(axis, road, (a0 + a1) / 2, 0.0)
        if not in_range(*mid):
            continue
        for _ in range(int(rng.poisson(pop.crossing_pedestrians))):
            along = rng.uniform(a0 + 0.4, a1 - 0.4)
            across = rng.uniform(o0 + 0.3, o1 - 0.3)
            x, y = _point(axis, road, along, across)
            # walking across the road: perpendicular to its axis
            heading = _heading(1 - axis, 1 if rng.random() < 0.5 else -1) + rng.normal(0, 6)
            top, bottom, scale = person_look()
            place("person", _pick(rng, PEDESTRIAN_MODELS), x, y, heading, top, bottom, "crossing", scale,
                  rng.uniform(-1, 1))
    return replace(descriptor, ambient=tuple(entities))


def _street_side(rng, pop, place, person_look, axis, road, segment, lo, hi, span, heading, side, hw, sw) -> None:
    """Everything on the right-hand side of one direction of one street segment."""
    # vehicles standing in the lane (a queue at a light, a jam): cars, some buses and trucks
    for _ in range(int(rng.poisson(pop.lane_vehicles_per_100m * span / 100))):
        along = rng.uniform(lo, hi)
        across = side * (hw / 2 + rng.normal(0, 0.12))
        x, y = _point(axis, road, along, across)
        if rng.random() < pop.heavy_share:
            bus = rng.random() < 0.5
            cat, model = ("bus", _pick(rng, BUS_MODELS)) if bus else ("truck", _pick(rng, TRUCK_MODELS))
            paint = _pick(rng, BUS_PAINTS) if bus else _pick(rng, PAINTS, PAINT_WEIGHTS)
            place(cat, model, x, y, heading, paint, _pick(rng, PAINTS, PAINT_WEIGHTS), "lane")
        else:
            place("car", _pick(rng, tuple(CAR_MODELS)), x, y, heading, _pick(rng, PAINTS, PAINT_WEIGHTS),
                  (35, 35, 38), "lane")
    # cyclists and motorcyclists riding in the lane, near its right edge
    for rate, models, offset in ((pop.cyclists_per_100m, CYCLIST_MODELS, hw - 0.8),
                                 (pop.motorcyclists_per_100m, MOTORCYCLIST_MODELS, hw / 2 + 0.5)):
        for _ in range(int(rng.poisson(rate * span / 100))):
            x, y = _point(axis, road, rng.uniform(lo, hi), side * (offset + rng.normal(0, 0.1)))
            top, bottom, scale = person_look()
            place("rider", _pick(rng, models), x, y, heading + rng.normal(0, 2), top, bottom, "lane", scale)
    # parked cars along the kerb, mostly with the traffic
    for _ in range(int(rng.poisson(pop.parked_cars_per_100m * span / 100))):
        model = _pick(rng, tuple(CAR_MODELS))
        _, width, _ = CAR_MODELS[model]
        along = rng.uniform(lo, hi)
        if not segment[0] + 6.0 < along < segment[1] - 6.0:  # no parking on crossings or in junctions
            continue
        x, y = _point(axis, road, along, side * (hw - 0.2 - width / 2))
        h = heading if rng.random() < 0.85 else heading + 180.0
        place("car", model, x, y, h, _pick(rng, PAINTS, PAINT_WEIGHTS), (35, 35, 38), "parked")
    # bicycles and motorcycles standing on the sidewalk by the kerb
    for _ in range(int(rng.poisson(pop.parked_two_wheelers_per_100m * span / 100))):
        x, y = _point(axis, road, rng.uniform(lo, hi), side * (hw + 0.75))
        moto = rng.random() < 0.3
        cat, models = ("motorcycle", MOTORCYCLE_MODELS) if moto else ("bicycle", BICYCLE_MODELS)
        place(cat, _pick(rng, models), x, y, heading + 90.0 + rng.normal(0, 10), _pick(rng, PAINTS, PAINT_WEIGHTS),
              (30, 30, 30), "parked")
    # pedestrians on the sidewalk: walking along it either way, or standing
    for _ in range(int(rng.poisson(pop.pedestrians_per_100m * span / 100))):
        across = side * (hw + 0.45 + rng.uniform(0, max(sw - 0.9, 0.1)))
        x, y = _point(axis, road, rng.uniform(lo, hi), across)
        top, bottom, scale = person_look()
        if rng.random() < pop.standing_share:
            h, pose = rng.uniform(0, 360), 0.0
        else:
            h, pose = heading + (0.0 if rng.random() < 0.5 else 180.0) + rng.normal(0, 8), rng.uniform(-1, 1)
        place("person", _pick(rng, PEDESTRIAN_MODELS), x, y, h, top, bottom, "sidewalk", scale, pose)


__all__ = ["CAR_MODELS", "PopulationConfig", "footprint", "populate"]
