"""Location sampling: uniform by area over valid polygons minus excluded ones, seeded.

`build_region(cfg)` dispatches on `region.type`; every region answers `sample_location(rng)` and
`surface_at(x, y)` so object placement works the same for every backend.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Protocol

import numpy as np
from matplotlib.path import Path as MplPath

from pairedgta.errors import ConfigError, DataError
from pairedgta.registry import Registry
from pairedgta.scene.descriptor import Location


class Region(Protocol):
    name: str

    def sample_location(self, rng: np.random.Generator) -> Location: ...

    def surface_at(self, x: float, y: float) -> str: ...


class PolygonRegion:
    """Valid areas minus excluded areas in world coordinates (GTA V map metres).

    The road network is the game's, not ours, so `surface_at` says "unknown" and the backend's own
    placement keeps vehicles on roads."""

    def __init__(
        self,
        name: str,
        valid: list,
        excluded: list | None = None,
        z: float = 0.0,
        max_tries: int = 100_000,
    ) -> None:
        if not valid:
            raise ConfigError(f"region '{name}': `valid` has no polygons; add at least one [[x, y], ...] list")
        self.name = name
        self.z = float(z)
        self.max_tries = int(max_tries)
        self.valid = [self._path(p, name, "valid") for p in valid]
        self.excluded = [self._path(p, name, "excluded") for p in (excluded or [])]
        verts = np.concatenate([p.vertices for p in self.valid])
        self.lo = verts.min(axis=0)
        self.hi = verts.max(axis=0)

    @staticmethod
    def _path(points: Any, name: str, key: str) -> MplPath:
        arr = np.asarray(points, dtype=float)
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 3:
            raise ConfigError(f"region '{name}'.{key}: each polygon needs >= 3 [x, y] points, got shape {arr.shape}")
        return MplPath(np.vstack([arr, arr[:1]]), closed=True)

    def contains(self, xy: np.ndarray) -> np.ndarray:
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        inside = np.zeros(len(xy), dtype=bool)
        for p in self.valid:
            inside |= p.contains_points(xy)
        for p in self.excluded:
            inside &= ~p.contains_points(xy)
        return inside

    def sample_location(self, rng: np.random.Generator) -> Location:
        # rejection sampling from the bounding box is exactly uniform by area over the valid set
        drawn = 0
        while drawn < self.max_tries:
            xy = rng.uniform(self.lo, self.hi, size=(256, 2))
            drawn += len(xy)
            ok = np.flatnonzero(self.contains(xy))
            if len(ok):
                x, y = xy[ok[0]]
                heading = float(rng.uniform(0.0, 360.0))
                return Location(x=float(x), y=float(y), z=self.z, heading=heading)
        raise DataError(
            f"region '{self.name}': no valid location after {self.max_tries} draws; "
            "check that `excluded` does not cover all of `valid`"
        )

    def surface_at(self, x: float, y: float) -> str:
        return "unknown" if bool(self.contains([[x, y]])[0]) else "other"


class RectangleRegion(PolygonRegion):
    """An axis-aligned box, handy for tests and the synthetic backend."""

    def __init__(self, name: str, x_range: list, y_range: list, z: float = 0.0, max_tries: int = 100_000) -> None:
        (x0, x1), (y0, y1) = x_range, y_range
        super().__init__(name=name, valid=[[[x0, y0], [x1, y0], [x1, y1], [x0, y1]]], z=z, max_tries=max_tries)

    def surface_at(self, x: float, y: float) -> str:
        # the synthetic world is an endless straight road along the ego heading: no global layout
        return "unknown"


REGIONS = Registry("region", "region.type")
REGIONS.register("polygons", "pairedgta.scene.sampling:PolygonRegion")
REGIONS.register("rectangle", "pairedgta.scene.sampling:RectangleRegion")
REGIONS.register("procedural_town", "pairedgta.scene.town:ProceduralTownRegion")


class TownCycle:
    """`region.town_seeds: [a, b, ...]`: scene k is drawn in town `town_seeds[k % n]`, so one dataset
    spans several towns (a held-out test set that no single layout dominates). Each town answers the
    Region interface; `for_scene(k)` picks it."""

    def __init__(self, regions: list[Any]) -> None:
        self.regions = regions
        self.name = regions[0].name

    def for_scene(self, k: int) -> Any:
        return self.regions[int(k) % len(self.regions)]

    def order(self, indices: list[int]) -> list[int]:
        """Scenes grouped by town: the renderer builds each town once, not once per scene."""
        return sorted(indices, key=lambda k: (int(k) % len(self.regions), int(k)))


def build_region(cfg: Mapping[str, Any]) -> Region:
    cfg = dict(cfg)
    seeds = cfg.pop("town_seeds", None)
    kind = cfg.pop("type", None)
    if seeds is not None:
        if kind != "procedural_town":
            raise ConfigError(f"region.town_seeds is for region=procedural_town, not region.type={kind!r}; remove it")
        if (not isinstance(seeds, (list, tuple)) or not seeds
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in seeds)):
            raise ConfigError(f"region.town_seeds={seeds!r} is invalid; set it to a non-empty list of integer town seeds "
                              "(or null for region.town_seed alone)")
        return TownCycle([REGIONS.build(kind, {**cfg, "town_seed": int(v)}, where="region") for v in seeds])  # type: ignore[return-value]
    return REGIONS.build(kind, cfg, where="region")


def region_for_scene(region: Any, k: int) -> Any:
    return region.for_scene(k) if hasattr(region, "for_scene") else region


def world_offset(location: Location, forward: float, right: float) -> tuple[float, float]:
    """Relative (forward, right) metres -> world (x, y); heading is CCW from +y as in GTA V."""
    h = math.radians(location.heading)
    fx, fy = -math.sin(h), math.cos(h)
    rx, ry = math.cos(h), math.sin(h)
    return location.x + forward * fx + right * rx, location.y + forward * fy + right * ry
