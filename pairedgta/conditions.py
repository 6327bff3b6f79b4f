"""Photometric conditions: backend-neutral parameters built from the `conditions` config group.

The grid is `times x weathers` (the paper's 3 x 3) plus optional explicit `extra` conditions, so a
continuous sweep (say fog density 0 -> 1 in five steps) is expressible without code.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

from pairedgta.errors import ConfigError

_PHYSICAL = ("cloud_cover", "fog_density", "rain_intensity", "wetness")


@dataclass(frozen=True)
class Condition:
    """One photometric condition c_i. `weather` is the GTA V weather name; the rest is physical."""

    name: str
    time: str
    weather: str
    clock_hour: int = 12
    clock_minute: int = 0
    sun_elevation_deg: float = 55.0
    sun_azimuth_deg: float = 135.0
    cloud_cover: float = 0.0
    fog_density: float = 0.0
    rain_intensity: float = 0.0
    wetness: float = 0.0

    def __post_init__(self) -> None:
        if not (0 <= self.clock_hour <= 23 and 0 <= self.clock_minute <= 59):
            raise ConfigError(
                f"conditions: '{self.name}' has clock {self.clock_hour}:{self.clock_minute}; "
                "set clock_hour in 0..23 and clock_minute in 0..59"
            )
        for key in _PHYSICAL:
            value = getattr(self, key)
            if not 0.0 <= float(value) <= 1.0:
                raise ConfigError(
                    f"conditions: '{self.name}'.{key}={value} is outside [0, 1]; set it between 0 and 1"
                )
        if not -90.0 <= self.sun_elevation_deg <= 90.0:
            raise ConfigError(
                f"conditions: '{self.name}'.sun_elevation_deg={self.sun_elevation_deg}; use -90..90"
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ConditionGrid:
    """The ordered set C_photo and the name of the clean reference condition."""

    conditions: tuple[Condition, ...]
    reference: str

    def __post_init__(self) -> None:
        names = [c.name for c in self.conditions]
        if len(set(names)) != len(names):
            raise ConfigError(f"conditions: duplicate condition names in {names}")
        if self.reference not in names:
            raise ConfigError(
                f"conditions.reference='{self.reference}' is not in the grid {names}; "
                "set conditions.reference to one of them"
            )

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.conditions]

    @property
    def adverse(self) -> list[str]:
        return [n for n in self.names if n != self.reference]

    def __getitem__(self, name: str) -> Condition:
        for c in self.conditions:
            if c.name == name:
                return c
        raise ConfigError(
            f"unknown condition '{name}'; known conditions: {', '.join(self.names)}"
        )

    def __iter__(self):
        return iter(self.conditions)

    def __len__(self) -> int:
        return len(self.conditions)

    def select(self, names: Iterable[str]) -> "ConditionGrid":
        wanted = list(names)
        picked = tuple(self[n] for n in wanted)
        if self.reference not in wanted:  # silently promoting e.g. a rain image to the reference would be wrong
            raise ConfigError(f"conditions.only={wanted} leaves out the reference condition {self.reference}, which every "
                              f"adverse image is compared with; add it, or set conditions.reference to one of {wanted}")
        return ConditionGrid(picked, self.reference)


def condition_name(time: str, weather: str) -> str:
    return f"{time}-{weather}"


# The one mapping between the grid's names (GTA V weathers: files, CSVs, metric keys, MLflow) and the
# paper's wording (every figure, table caption and contact sheet title): Day-EXTRASUNNY <-> Day-Sunny.
WEATHER_DISPLAY = {"EXTRASUNNY": "Sunny", "RAIN": "Rain", "FOGGY": "Foggy", "CLEAR": "Clear"}


def condition_display(name: str) -> str:
    """Day-EXTRASUNNY -> Day-Sunny; names outside the mapping (a fog sweep's `fog_0.5`) stay as they are."""
    return "-".join(WEATHER_DISPLAY.get(part, part) for part in str(name).split("-"))


def build_condition_grid(cfg: Mapping[str, Any]) -> ConditionGrid:
    """Build the grid from a `conditions` config node (times x weathers + extra)."""
    cfg = dict(cfg)
    times = dict(cfg.get("times") or {})
    weathers = dict(cfg.get("weathers") or {})
    fields = {f.name for f in dataclasses.fields(Condition)}
    conditions: list[Condition] = []
    for time, tparams in times.items():
        for weather, wparams in weathers.items():
            params = {**dict(tparams or {}), **dict(wparams or {})}
            unknown = set(params) - fields
            if unknown:
                raise ConfigError(
                    f"conditions.{time}/{weather}: unknown keys {sorted(unknown)}; "
                    f"allowed: {sorted(fields - {'name', 'time', 'weather'})}"
                )
            conditions.append(
                Condition(name=condition_name(time, weather), time=time, weather=weather, **params)
            )
    for extra in cfg.get("extra") or []:
        extra = dict(extra)
        base_time, base_weather = extra.get("time"), extra.get("weather")
        if base_time not in times or not base_weather:
            raise ConfigError(
                f"conditions.extra entry {extra.get('name')!r} needs time in {list(times)} and a weather name"
            )
        # a weather outside the grid (e.g. FOGGY in a sweep) starts from clear-sky parameters
        params = {**dict(times[base_time] or {}), **dict(weathers.get(base_weather) or {})}
        params.update({k: v for k, v in extra.items() if k not in ("time", "weather", "name")})
        unknown = set(params) - fields
        if unknown:
            raise ConfigError(f"conditions.extra {extra.get('name')!r}: unknown keys {sorted(unknown)}")
        name = extra.get("name") or condition_name(base_time, base_weather)
        conditions.append(Condition(name=name, time=base_time, weather=base_weather, **params))
    only = cfg.get("only")
    grid = ConditionGrid(tuple(conditions), str(cfg.get("reference", "")))
    if only:
        grid = grid.select(only)
    return grid
