"""Dynamic-object placement in the bounded region R_k in front of the camera, with d_min spacing."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from pairedgta.errors import ConfigError
from pairedgta.scene.descriptor import CATEGORIES, DynamicObject, Location
from pairedgta.scene.population import footprint
from pairedgta.scene.sampling import Region, world_offset

VEHICLES = ("car", "truck", "bus", "motorcycle", "bicycle", "rider")
# riders sit on two-wheelers, so they go where vehicles go
SURFACE = {c: ("road" if c in VEHICLES else "sidewalk") for c in CATEGORIES}

DEFAULT_MODELS = {
    "car": ["blista", "sultan", "asea", "premier"],
    "truck": ["mule", "benson"],
    "bus": ["bus", "coach"],
    "motorcycle": ["bati", "akuma"],
    "bicycle": ["bmx", "cruiser"],
    "person": ["a_m_y_business_01", "a_f_y_tourist_01", "a_m_m_skater_01"],
    "rider": ["a_m_y_motox_01"],
}


# the ego vehicle in the camera frame: forward from its rear to its bonnet, half width; and the gap kept
EGO_FORWARD = (-3.0, 2.6)
EGO_HALF_WIDTH = 1.0
EGO_GAP = 0.5


def clear_of_ego(category: str, model: str, forward: float, right: float) -> bool:
    """False when the object's footprint reaches into the ego vehicle: a bus whose centre is 6 m ahead
    would otherwise enclose the camera and fill the frame with one class."""
    length, width = footprint(category, model)
    if category == "person":
        half_f = half_r = max(length, width) / 2  # any heading
    else:
        half_f, half_r = length / 2, width / 2  # vehicles stand along the lane (heading 0 or 180)
    return (forward - half_f >= EGO_FORWARD[1] + EGO_GAP or forward + half_f <= EGO_FORWARD[0] - EGO_GAP
            or abs(right) >= half_r + EGO_HALF_WIDTH + EGO_GAP)


@dataclass(frozen=True)
class PlacementConfig:
    min: int = 0
    max: int = 3
    d_min: float = 4.0
    forward_range: tuple[float, float] = (6.0, 30.0)
    lateral_range: tuple[float, float] = (-6.0, 6.0)
    categories: tuple[str, ...] = CATEGORIES
    weights: tuple[float, ...] | None = None
    max_tries: int = 200

    @classmethod
    def from_cfg(cls, cfg: Mapping[str, Any]) -> "PlacementConfig":
        cfg = dict(cfg)
        for key in ("forward_range", "lateral_range", "categories", "weights"):
            if cfg.get(key) is not None:
                cfg[key] = tuple(cfg[key])
        known = set(cls.__dataclass_fields__)
        unknown = set(cfg) - known
        if unknown:
            raise ConfigError(f"generate.objects: unknown keys {sorted(unknown)}; known: {sorted(known)}")
        pc = cls(**cfg)
        if not 0 <= pc.min <= pc.max:
            raise ConfigError(f"generate.objects.min={pc.min}, max={pc.max}: need 0 <= min <= max")
        if pc.d_min < 0:
            raise ConfigError(f"generate.objects.d_min={pc.d_min} must be >= 0")
        bad = [c for c in pc.categories if c not in CATEGORIES]
        if bad:
            raise ConfigError(f"generate.objects.categories: unknown {bad}; use {', '.join(CATEGORIES)}")
        if pc.weights is not None and len(pc.weights) != len(pc.categories):
            raise ConfigError("generate.objects.weights must have one weight per category")
        for key in ("forward_range", "lateral_range"):
            lo, hi = getattr(pc, key)
            if lo > hi:
                raise ConfigError(f"generate.objects.{key}=[{lo}, {hi}] must be [low, high]")
        return pc


def place_objects(
    rng: np.random.Generator,
    location: Location,
    region: Region,
    cfg: PlacementConfig,
    models: Mapping[str, Sequence[str]] = DEFAULT_MODELS,
) -> tuple[tuple[DynamicObject, ...], int]:
    """Draw M_k ~ U{min..max} objects; returns (objects, requested M_k).

    Each object is rejection-sampled in R_k on its category's surface with pairwise distance >= d_min,
    clear of the ego vehicle;
    when R_k cannot hold the count within `max_tries`, fewer objects are placed (the caller records it)."""
    requested = int(rng.integers(cfg.min, cfg.max + 1))
    probs = None
    if cfg.weights is not None:
        w = np.asarray(cfg.weights, dtype=float)
        probs = w / w.sum()
    placed: list[DynamicObject] = []
    positions: list[tuple[float, float]] = []
    for _ in range(requested):
        category = str(rng.choice(list(cfg.categories), p=probs))
        for _try in range(cfg.max_tries):
            # round before the spacing check so the stored descriptor satisfies d_min exactly
            # (and clip, so rounding never leaves R_k)
            forward = float(np.clip(round(float(rng.uniform(*cfg.forward_range)), 3), *cfg.forward_range))
            right = float(np.clip(round(float(rng.uniform(*cfg.lateral_range)), 3), *cfg.lateral_range))
            if any((forward - f) ** 2 + (right - r) ** 2 < cfg.d_min**2 for f, r in positions):
                continue
            surface = region.surface_at(*world_offset(location, forward, right))
            if surface not in (SURFACE[category], "unknown"):
                continue
            names = list(models.get(category) or [category])
            model = str(rng.choice(names))
            if not clear_of_ego(category, model, forward, right):
                continue
            heading = float(rng.choice([0.0, 180.0])) if category in VEHICLES else float(rng.uniform(0, 360))
            color = tuple(int(v) for v in rng.integers(0, 256, size=3))
            color2 = tuple(int(v) for v in rng.integers(0, 256, size=3))
            placed.append(
                DynamicObject(
                    category=category,
                    model=model,
                    forward=forward,
                    right=right,
                    up=0.0,
                    heading=heading,
                    color=color,  # type: ignore[arg-type]
                    secondary_color=color2,  # type: ignore[arg-type]
                )
            )
            positions.append((forward, right))
            break
    return tuple(placed), requested
