"""SceneDescriptor S_k: everything that must stay fixed across the conditions of one group.

It is plain data saved as JSON beside every group, and it is the replay file: rendering a loaded
descriptor under a condition reproduces that image.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pairedgta.errors import DataError

CATEGORIES = ("car", "truck", "bus", "motorcycle", "bicycle", "person", "rider")
SCHEMA_VERSION = 2  # 2: ambient population


@dataclass(frozen=True)
class Location:
    """Ego-vehicle pose in world coordinates (metres, heading in degrees)."""

    x: float
    y: float
    z: float = 0.0
    heading: float = 0.0


@dataclass(frozen=True)
class CameraPose:
    """Camera pose relative to the ego vehicle (metres, degrees) and horizontal field of view."""

    x: float = 0.0
    y: float = 0.5
    z: float = 1.6
    rot_x: float = 0.0
    rot_y: float = 0.0
    rot_z: float = 0.0
    fov: float = 60.0


@dataclass(frozen=True)
class DynamicObject:
    """One object o_{k,j}: position relative to the ego vehicle (forward/right/up, metres)."""

    category: str
    model: str
    forward: float
    right: float
    up: float = 0.0
    heading: float = 0.0
    color: tuple[int, int, int] = (128, 128, 128)
    secondary_color: tuple[int, int, int] = (128, 128, 128)

    def __post_init__(self) -> None:
        if self.category not in CATEGORIES:
            raise DataError(
                f"dynamic object category '{self.category}' is unknown; use one of {', '.join(CATEGORIES)}"
            )


@dataclass(frozen=True)
class AmbientEntity:
    """One entity of a region's ambient population (parked and standing traffic, pedestrians,
    cyclists) in world coordinates: part of the static scene, distinct from the paper's dynamic
    objects. `scale` multiplies the model's size (a person's height), `pose` is a walking phase in
    [-1, 1] (0 = standing), `role` says where it was placed (parked, lane, sidewalk, crossing)."""

    category: str
    model: str
    x: float
    y: float
    heading: float = 0.0
    color: tuple[int, int, int] = (128, 128, 128)
    secondary_color: tuple[int, int, int] = (128, 128, 128)
    scale: float = 1.0
    pose: float = 0.0
    role: str = ""

    def __post_init__(self) -> None:
        if self.category not in CATEGORIES:
            raise DataError(
                f"ambient entity category '{self.category}' is unknown; use one of {', '.join(CATEGORIES)}"
            )


@dataclass(frozen=True)
class SceneDescriptor:
    scene_id: str
    seed: int
    location: Location
    camera: CameraPose = field(default_factory=CameraPose)
    objects: tuple[DynamicObject, ...] = ()
    region: str = ""
    requested_objects: int | None = None
    extra: tuple[tuple[str, Any], ...] = ()
    ambient: tuple[AmbientEntity, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["schema_version"] = SCHEMA_VERSION
        data["objects"] = [asdict(o) for o in self.objects]
        data["ambient"] = [asdict(o) for o in self.ambient]
        data["extra"] = dict(self.extra)
        return data

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    def save(self, path: str | os.PathLike) -> None:
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        try:  # a failed write (a full disk) leaves no temporary behind
            tmp.write_text(self.to_json())
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SceneDescriptor":
        try:
            objects = tuple(
                DynamicObject(
                    **{
                        **o,
                        "color": tuple(o.get("color", (128, 128, 128))),
                        "secondary_color": tuple(o.get("secondary_color", (128, 128, 128))),
                    }
                )
                for o in data.get("objects", [])
            )
            ambient = tuple(
                AmbientEntity(**{**o, "color": tuple(o.get("color", (128, 128, 128))),
                                 "secondary_color": tuple(o.get("secondary_color", (128, 128, 128)))})
                for o in data.get("ambient", [])
            )
            return cls(
                scene_id=str(data["scene_id"]),
                seed=int(data["seed"]),
                location=Location(**data["location"]),
                camera=CameraPose(**data.get("camera", {})),
                objects=objects,
                region=str(data.get("region", "")),
                requested_objects=data.get("requested_objects"),
                extra=tuple(sorted(dict(data.get("extra", {})).items())),
                ambient=ambient,
            )
        except (KeyError, TypeError) as exc:
            raise DataError(f"scene descriptor is malformed ({exc}); regenerate it with the generate stage") from exc

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SceneDescriptor":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise DataError(f"{path}: scene descriptor not found") from None
        except json.JSONDecodeError as exc:
            raise DataError(f"{path}: not valid JSON ({exc.msg}); regenerate the scene") from None
        try:
            return cls.from_dict(data)
        except DataError as exc:
            raise DataError(f"{path}: {exc}") from None
