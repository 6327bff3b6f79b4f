"""Photometric conditions: backend-neutral physical parameters built from the `conditions` config group.

The grid is `times x weathers` (the paper's 3 x 3) plus optional explicit `extra` conditions, so a
severity ladder (fog visibility 1000 -> 75 m, rain 2.5 -> 100 mm/h, the sun through twilight) is
expressible without code. Parameters carry the units this field speaks in: fog as meteorological
visibility (Koschmieder: extinction = 3.912 / V, Foggy Cityscapes' 600/300/150 m), rain as a rate in
mm/h, light as the sun's elevation; the unitless levels the renderers need are derived here, once.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

from pairedgta.errors import ConfigError

_FRACTIONS = ("cloud_cover", "wetness")
CORRUPTION_FIELDS = ("corruption", "severity", "source")  # set by pairedgta/corruptions.py, not by a condition's keys
KOSCHMIEDER = 3.912  # -ln(0.02): visibility is the distance at which contrast falls to 2 %
# extinction of rain drops in the visible band, alpha = 1.076 R^0.67 dB/km (Carbonneau's relation for
# free-space optics), in 1/m: 1.076 / (10 log10 e) / 1000
RAIN_EXTINCTION_COEF, RAIN_EXTINCTION_EXP = 1.076 / 4.3429 / 1000.0, 0.67
RAIN_FULL_MM_H = 50.0  # the rate at which streaks, wetness and cloud saturate (upper end of heavy rain)
# keys of the unitless model the physical ones replaced: a config that still uses them is told how to convert
REPLACED_KEYS = {
    "fog_density": "visibility_m (meteorological visibility in m; the old Blender fog_density d had "
                   "visibility 3.912 / (0.06 d) m, e.g. 0.7 -> 93 m)",
    "rain_intensity": "rain_mm_h (rain rate in mm/h; the old rain_intensity r is about 50 r^2 mm/h, e.g. 0.7 -> 25)",
}


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
    wetness: float = 0.0
    visibility_m: float | None = None  # meteorological visibility of fog or mist; None = clear air
    rain_mm_h: float = 0.0
    # a 2D corruption of the clean condition `source` (pairedgta/corruptions.py): the same light, nothing rendered
    corruption: str | None = None
    severity: int | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        if not (0 <= self.clock_hour <= 23 and 0 <= self.clock_minute <= 59):
            raise ConfigError(
                f"conditions: '{self.name}' has clock {self.clock_hour}:{self.clock_minute}; "
                "set clock_hour in 0..23 and clock_minute in 0..59"
            )
        for key in _FRACTIONS:
            value = getattr(self, key)
            if not 0.0 <= float(value) <= 1.0:
                raise ConfigError(
                    f"conditions: '{self.name}'.{key}={value} is outside [0, 1]; set it between 0 and 1"
                )
        if self.visibility_m is not None and not 1.0 <= float(self.visibility_m) < float("inf"):
            raise ConfigError(f"conditions: '{self.name}'.visibility_m={self.visibility_m}; use a visibility in metres "
                              ">= 1 (Foggy Cityscapes: 600, 300, 150), or null for clear air")
        if not 0.0 <= float(self.rain_mm_h) <= 500.0:
            raise ConfigError(f"conditions: '{self.name}'.rain_mm_h={self.rain_mm_h}; use a rain rate in mm/h "
                              "in 0..500 (light 2.5, heavy 25, violent 100)")
        if not -90.0 <= self.sun_elevation_deg <= 90.0:
            raise ConfigError(
                f"conditions: '{self.name}'.sun_elevation_deg={self.sun_elevation_deg}; use -90..90"
            )

    @property
    def fog_extinction(self) -> float:
        """1/m, from the visibility (Koschmieder)."""
        return 0.0 if self.visibility_m is None else KOSCHMIEDER / float(self.visibility_m)

    @property
    def rain_extinction(self) -> float:
        """1/m scattered by the drops themselves; a rain condition's mist is its visibility_m."""
        return RAIN_EXTINCTION_COEF * float(self.rain_mm_h) ** RAIN_EXTINCTION_EXP if self.rain_mm_h > 0 else 0.0

    @property
    def extinction_per_m(self) -> float:
        """Total extinction of the air: what the renderers attenuate with and the transmittance maps record."""
        return self.fog_extinction + self.rain_extinction

    @property
    def effective_visibility_m(self) -> float:
        ext = self.extinction_per_m
        return KOSCHMIEDER / ext if ext > 0 else float("inf")

    @property
    def rain_level(self) -> float:
        """Unitless 0..1 rain strength for what has no physical model here (streaks, wet darkening,
        cloud): sqrt(R / 50 mm/h), so 25 mm/h (heavy) gives 0.71 and 100 mm/h saturates."""
        return min(1.0, (float(self.rain_mm_h) / RAIN_FULL_MM_H) ** 0.5)

    @property
    def fog_level(self) -> float:
        """Unitless 0..1 fog strength (drivers' lights, haze colour): 150 m / visibility, capped at 1."""
        return 0.0 if self.visibility_m is None else min(1.0, 150.0 / float(self.visibility_m))

    def transmittance(self, distance_m):
        """exp(-extinction * distance): 1 in clear air (also toward the sky), 0 for the sky in fog; NaN for a
        corruption condition (a 2D filter has no depth, so no transmittance)."""
        import numpy as np

        d = np.asarray(distance_m, dtype=np.float64)
        if self.corruption is not None:
            return np.full(d.shape, np.nan)
        ext = self.extinction_per_m
        if ext == 0.0:
            return np.ones(d.shape, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            return np.exp(-ext * np.where(np.isfinite(d), d, np.inf))

    def to_dict(self) -> dict[str, Any]:
        """Its fields; a rendered condition's without the corruption fields, so its dataset hashes as before."""
        d = dataclasses.asdict(self)
        if self.corruption is None:
            for key in CORRUPTION_FIELDS:
                d.pop(key)
        return d


@dataclass(frozen=True)
class ConditionGrid:
    """The ordered set C_photo and the name of the clean reference condition."""

    conditions: tuple[Condition, ...]
    reference: str
    ladder: Ladder | None = None  # set for a severity ladder: the order of `conditions` is the severity

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

    @property
    def corrupted(self) -> list[Condition]:
        """The corruption conditions (pairedgta/corruptions.py), made from their clean condition, not rendered."""
        return [c for c in self.conditions if c.corruption is not None]

    @property
    def rendered(self) -> list[Condition]:
        return [c for c in self.conditions if c.corruption is None]

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
        orphans = [c.name for c in picked if c.source is not None and c.source not in wanted]
        if orphans:
            raise ConfigError(f"conditions.only={wanted} keeps {orphans[0]} but leaves out {self[orphans[0]].source}, "
                              "the clean condition it corrupts; add it")
        return ConditionGrid(picked, self.reference, self.ladder)


# The paper's headline adverse condition: the one whose rho_valid is logged without a condition in its
# name, and the one the ranking figure shows, unless plot.ranking.condition names another.
HEADLINE = "Night-EXTRASUNNY"


def headline_condition(conditions: Iterable[str], wanted: str | None, reference: str | None = None) -> str | None:
    """`wanted` (plot.ranking.condition) when it is among the adverse `conditions`, else HEADLINE, else the first
    adverse one (None when there is none)."""
    adverse = [c for c in conditions if c != reference]
    if wanted and wanted in adverse:
        return str(wanted)
    if HEADLINE in adverse:
        return HEADLINE
    return adverse[0] if adverse else None


def condition_name(time: str, weather: str) -> str:
    return f"{time}-{weather}"


# The one mapping between the grid's names (GTA V weathers: files, CSVs, metric keys, MLflow) and the
# paper's wording (every figure, table caption and contact sheet title): Day-EXTRASUNNY <-> Day-Sunny.
WEATHER_DISPLAY = {"EXTRASUNNY": "Sunny", "RAIN": "Rain", "FOGGY": "Foggy", "CLEAR": "Clear"}


def condition_display(name: str) -> str:
    """Day-EXTRASUNNY -> Day-Sunny; names outside the mapping (a fog sweep's `fog_0.5`) stay as they are."""
    return "-".join(WEATHER_DISPLAY.get(part, part) for part in str(name).split("-"))


def _check_keys(where: str, params: Mapping[str, Any], fields: set[str]) -> None:
    unknown = set(params) - fields
    for key in sorted(unknown & set(REPLACED_KEYS)):
        raise ConfigError(f"{where}: {key} is no longer a condition key; use {REPLACED_KEYS[key]}")
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(fields - {'name', 'time', 'weather'})}")


LADDER_PARAMETERS = {"visibility_m": "m", "rain_mm_h": "mm/h", "sun_elevation_deg": "deg"}


@dataclass(frozen=True)
class Ladder:
    """A severity ladder: the grid's conditions in order of growing severity along one physical parameter."""

    parameter: str
    unit: str
    label: str

    def value(self, condition: Condition) -> float:
        v = getattr(condition, self.parameter)
        return float("inf") if v is None else float(v)

    def tick(self, condition: Condition) -> str:
        v = self.value(condition)
        if v == float("inf"):
            return "clear"
        return f"{v:g} {self.unit}"


def ladder_from_config(node: Any) -> Ladder | None:
    if not node:
        return None
    node = dict(node)
    parameter = str(node.get("parameter"))
    if parameter not in LADDER_PARAMETERS:
        raise ConfigError(f"conditions.ladder.parameter={parameter!r}; use one of {', '.join(LADDER_PARAMETERS)}")
    return Ladder(parameter, LADDER_PARAMETERS[parameter], str(node.get("label") or parameter))


def build_condition_grid(cfg: Mapping[str, Any]) -> ConditionGrid:
    """Build the grid from a `conditions` config node (times x weathers + extra)."""
    cfg = dict(cfg)
    times = dict(cfg.get("times") or {})
    weathers = dict(cfg.get("weathers") or {})
    fields = {f.name for f in dataclasses.fields(Condition)} - set(CORRUPTION_FIELDS)
    conditions: list[Condition] = []
    for time, tparams in times.items():
        for weather, wparams in weathers.items():
            params = {**dict(tparams or {}), **dict(wparams or {})}
            _check_keys(f"conditions.{time}/{weather}", params, fields)
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
        _check_keys(f"conditions.extra {extra.get('name')!r}", params, fields)
        name = extra.get("name") or condition_name(base_time, base_weather)
        conditions.append(Condition(name=name, time=base_time, weather=base_weather, **params))
    from pairedgta import corruptions

    reference = str(cfg.get("reference", ""))
    conditions += corruptions.conditions(cfg.get("corruptions"), conditions, reference)
    only = cfg.get("only")
    grid = ConditionGrid(tuple(conditions), reference, ladder_from_config(cfg.get("ladder")))
    if only:
        grid = grid.select(only)
    return grid
