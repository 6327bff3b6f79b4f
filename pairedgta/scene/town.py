"""Procedural town: a deterministic street grid that the Blender backend renders, as a region.

This module answers what a region answers (lane sampling, surface, ground height and obstacle
queries, the parameters that rebuild the town) for scene sampling, placement, the population and the
renderer. Its layout, the primitives the renderer turns into meshes, is built on first use by
pairedgta/scene/town_geometry.py out of the shapes of pairedgta/scene/town_primitives.py. Pure
Python + numpy so that sampling and placement work without bpy.

Coordinates: metres, x east, y north, z up; ground and road surface at z=0, sidewalks raised by
`kerb_height`. Roads run along x and y through `road centres` spaced by one pitch
(block + 2 sidewalks + road). Traffic keeps right.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from pairedgta.errors import ConfigError
from pairedgta.scene.descriptor import Location
from pairedgta.scene.population import PopulationConfig
from pairedgta.scene.town_geometry import build_layout
from pairedgta.scene.town_primitives import TownLayout


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

    def road_centre_distance(self, v: float) -> float:
        """Distance from coordinate `v` (x or y) to the nearest road centre line."""
        c = self.road_centres
        return float(np.min(np.abs(c - v)))

    def surface_at(self, x: float, y: float) -> str:
        """'road', 'sidewalk' or 'other' (lots, parks, countryside)."""
        hw = self.road_width / 2
        length = self.road_half_length
        dx = self.road_centre_distance(x)  # distance to the nearest north-south road
        dy = self.road_centre_distance(y)
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
            self._layout = build_layout(self)
        return self._layout


__all__ = ["ProceduralTownRegion"]
