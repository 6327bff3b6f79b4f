"""A stand-in for the DeepGTAV plugin that speaks its wire protocol, for tests and benchmarks.

It is not a renderer: it keeps the game state the plugin would change (ego pose, camera, clock,
weather, spawned vehicles and peds) and streams, like the plugin, one frame every 1/rate seconds
after ``start``: padded BGR bytes of a deterministic synthetic street view plus a JSON document
reporting the state. The picture depends on the scene (ego pose, camera, entities) and its
brightness/tint/haze on clock and weather, so conditions differ and repeats are identical.

Plugin behaviour it reproduces (the client side is described in pairedgta/render/deepgtav.py; the
constants both sides share are pairedgta/render/deepgtav_protocol.py's):
* transports: ``zmq`` (PAIR socket bound by the server; a frame is two messages, raw bytes then
  JSON) and ``tcp`` (4-byte little-endian length prefix on every message and frame part);
* one top-level key per message, checked in the plugin's order; fields are read with typed
  getters: a float accepts any JSON number, an int only a JSON integer in int32 range, a bool
  only true/false, a string only a string. A message that fails to parse or has a wrong/missing
  field is dropped (recorded in ``dropped``); ``on_bad_message="close"`` drops the connection
  instead, like a plugin that crashes on it;
* ``start`` is ignored while a session runs, ``config`` and ``stop`` while none does; ``config``
  rebuilds the scenario (ego re-created at the location) but keeps spawned entities, which
  disappear after ``spawnedEntitiesDespawnSeconds``; CreateVehicle/CreatePed place entities
  relative to the ego pose with absolute headings.

Extensions: the JSON also reports ``"weather"`` and the spawned entities under ``"vehicles"`` /
``"peds"`` (``"spawned": true``), which the client uses to check that a condition was applied.

2D boxes as DeepGTAV-PreSIL gives them: with ``dataset.exportBBox2D`` the JSON has ``"bbox2d": null`` (the
plugin's placeholder) and, while recording (``StartRecording`` until ``StopRecording``), a second ``"bbox2d"``
member holding the string, as the plugin writes it (the duplicate key is real). The string has one augmented KITTI
line per entity within ``REPORT_RADIUS_M`` (vehicles, then peds, by entity id): its type from the model (the
plugin's vehicle table: Car, Truck, Bus, Motorbike, Cyclist, Trailer, Boat; Pedestrian, Animal), the first and
last column and row of its visible pixels in ``dataset.frame`` pixels (``width height 0 0`` when none is visible),
the hidden fraction of its drawn box as ``occluded``, 1 - inside/total of that box as ``truncated`` (NaN,
written ``-nan(ind)`` as an MSVC build does, for a box it does not draw), the model as the plugin spells it, the
vehicle a ped rides in as ``v_ped_is_in``, and a made-up but plausible 3D part. Besides the spawned entities it
keeps ambient traffic around the ego (``AMBIENT``: a cyclist and a motorcyclist with their riders, a dog, a
trailer, a boat behind the camera), drawn but not listed under ``"vehicles"``/``"peds"``. The picture has the
``screenResolution`` size (the plugin captures the screen), the boxes the ``dataset.frame`` size, and a frame
above ``BOXES_MAX_FRAME`` gets no boxes (the plugin's buffers do not match it). ``SyntheticView.instance_map``
gives the pixels.

Fault injection (for the first ``fault_sessions`` sessions, or all when None):
``silent`` (never send a frame), ``close_mid_frame`` (send half a frame, then drop the
connection), ``garbage`` (correct-size frame, undecodable JSON), ``wrong_size`` (frame without
row padding and one row short).

Run by hand::

    python -m pairedgta.testing.deepgtav_server --transport zmq --port 8000
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import random
import select
import signal
import socket
import struct
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Self

import numpy as np

from pairedgta.render.deepgtav_protocol import INT32, WEATHERS, model_key, row_stride
from pairedgta.scene.validation import joaat

log = logging.getLogger(__name__)

FAULTS = ("silent", "close_mid_frame", "garbage", "wrong_size")
_MAX_TCP_MESSAGE = 1 << 20  # the plugin reads messages into a fixed buffer
REPORT_RADIUS_M = 150.0  # classic DeepGTAV lists vehicles/peds within 150 m of the ego
FIRST_HANDLE = 4098  # entity ids: FIRST_HANDLE + 256 * n for the n-th entity created (like GTA's script handles)
BOXES_MAX_FRAME = (1920, 1080)  # a larger dataset.frame: the plugin's buffers differ from it and no bbox2d is sent

# GTA bicycle and motorcycle model names, for the classic DeepGTAV classID in the state JSON
_BICYCLES = frozenset(["bmx", "cruiser", "fixter", "scorcher", "tribike", "tribike2", "tribike3"])
_BUSES = frozenset(["airbus", "bus", "coach", "pbus", "rentalbus", "tourbus"])
# the plugin's table types these SUVs Truck too (pairedgta/data/deepgtav_suvs.csv)
_TRUCKS = frozenset(["benson", "mule", "mule2", "mule3", "packer", "phantom", "pounder",
                     "cavalcade", "cavalcade2", "contender", "dubsta3", "fbi2", "granger"])
_TRAILERS = frozenset(["boattrailer", "trailers", "trailers2", "trailersmall", "tanker", "tvtrailer"])
_BOATS = frozenset(["dinghy", "dinghy2", "jetmax", "marquis", "seashark", "speeder", "squalo", "suntrap", "tropic"])
_MOTORCYCLES = frozenset(
    ["akuma", "avarus", "bagger", "bati", "bati2", "bf400", "carbonrs", "chimera", "cliffhanger", "daemon", "daemon2", "defiler", "diablous", "double", "enduro", "esskey", "faggio", "faggio2", "faggio3", "fcr", "gargoyle", "hakuchou", "hexer", "innovation", "lectro", "manchez", "nemesis", "nightblade", "pcj", "policeb", "ratbike", "ruffian", "sanchez", "sanchez2", "sovereign", "thrust", "vader", "vindicator", "vortex", "wolfsbane", "zombiea", "zombieb"]
)


def encode_bgr_padded(rgb: np.ndarray) -> bytes:
    """RGB HxWx3 uint8 -> BGR bytes, rows top to bottom, each padded to a multiple of 4 bytes."""
    h, w, _ = rgb.shape
    buf = np.zeros((h, row_stride(w)), dtype=np.uint8)
    buf[:, : w * 3] = np.ascontiguousarray(rgb[..., ::-1]).reshape(h, w * 3)
    return buf.tobytes()


# --------------------------------------------------------------------------- game state


@dataclass
class Entity:
    kind: str  # "vehicle" | "ped"
    model: str
    x: float
    y: float
    z: float
    heading: float
    spawned_at: float
    color: tuple[int, int] = (-1, -1)
    handle: int = 0  # the game's entity id (bbox2d's entity_id)
    ped_in: int = 0  # the handle of the vehicle a ped rides (bbox2d's v_ped_is_in)
    size: tuple[float, float, float] | None = None  # (drawn width, height, depth) when not the kind's default


def _object_or_null(value: Any, name: str) -> dict[str, Any]:
    """A start/config section as the plugin reads it: null means empty, anything but an object is refused."""
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise BadMessage(f"{name} is not an object or null")
    return value


@dataclass
class GameState:
    running: bool = False
    # scenario
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    heading: float = 0.0
    hour: int = 16
    minute: int = 0
    second: int = 0
    weather: str = "CLEAR"
    vehicle: str = "blista"
    driving_mode: int = -1
    despawn_s: float = 60.0
    # dataset
    rate: float = 10.0
    width: int = 1920
    height: int = 1080
    report: dict[str, bool] = field(
        default_factory=lambda: {"vehicles": True, "peds": True, "location": True, "time": True}
    )
    screen: tuple[int, int] | None = None  # dataset.screenResolution: the picture's size (None: the frame's)
    traffic: bool = True  # the AMBIENT entities around the ego
    stationary: bool = False
    export_bbox2d: bool = False
    recording: bool = False  # StartRecording/StopRecording: the plugin keeps it across sessions
    # camera relative to the ego vehicle: x right, y forward, z up; degrees
    camera: tuple[float, float, float, float, float, float] = (0.0, 0.5, 1.6, 0.0, 0.0, 0.0)
    commands: tuple[float, float, float] = (0.0, 0.0, 0.0)
    entities: list[Entity] = field(default_factory=list)
    index: int = 0

    def forward_right(self) -> tuple[tuple[float, float], tuple[float, float]]:
        h = math.radians(self.heading)
        return (-math.sin(h), math.cos(h)), (math.cos(h), math.sin(h))

    def sends_boxes(self) -> bool:
        """Whether a frame carries its bbox2d string: asked for, recording, and a frame the plugin's buffers match."""
        fits = self.width <= BOXES_MAX_FRAME[0] and self.height <= BOXES_MAX_FRAME[1]
        return self.export_bbox2d and self.recording and fits

    def picture_size(self) -> tuple[int, int]:
        """The screen the plugin captures (screenResolution), else the frame."""
        return self.screen or (self.width, self.height)

    def ambient(self) -> list[Entity]:
        """The ambient traffic at its place around the ego (none with ``traffic=False``)."""
        if not self.traffic:
            return []
        (fx, fy), (rx, ry) = self.forward_right()
        return [Entity(kind, model, self.x + fwd * fx + right * rx, self.y + fwd * fy + right * ry, self.z,
                       self.heading + 90.0, 0.0, handle=handle, ped_in=ped_in, size=size)
                for kind, model, fwd, right, size, handle, ped_in in AMBIENT]


# Ambient traffic (kind, model, forward, right, (drawn width, height, depth), handle, v_ped_is_in), relative to the
# ego, crossing it side-on on the sidewalks: a bicycle and a motorbike, each with its rider drawn just in front of
# it (the rider's pixels are the rider's, DISTINGUISH_PEDS_IN_VEHICLES), a dog (an Animal line), a trailer, and a
# boat behind the camera (never drawn). Handles are below FIRST_HANDLE, so they never meet spawned ones.
AMBIENT: tuple[tuple[str, str, float, float, tuple[float, float, float], int, int], ...] = (
    ("vehicle", "scorcher", 24.0, 7.0, (1.8, 1.1, 0.7), 1026, 0),
    ("ped", "a_m_y_cyclist_01", 23.8, 7.0, (0.5, 1.75, 0.4), 1282, 1026),
    ("vehicle", "bati", 32.0, -7.0, (2.1, 1.2, 0.8), 1538, 0),
    ("ped", "a_m_y_motox_01", 31.8, -7.0, (0.5, 1.7, 0.4), 1794, 1538),
    ("animal", "a_c_husky", 14.0, -6.5, (0.9, 0.6, 0.3), 2050, 0),
    ("vehicle", "trailers", 60.0, 8.5, (2.6, 3.8, 12.0), 2306, 0),
    ("vehicle", "dinghy", -15.0, 3.0, (2.0, 1.5, 4.5), 2562, 0),
)


class BadMessage(Exception):
    """A field the plugin's typed getter would choke on."""


def _field(obj: Any, key: str) -> Any:
    if not isinstance(obj, dict):
        raise BadMessage(f"body is {type(obj).__name__}, not an object")
    if key not in obj:
        raise BadMessage(f"missing field '{key}'")
    return obj[key]


def get_float(obj: Any, key: str) -> float:
    v = _field(obj, key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BadMessage(f"'{key}' is {json.dumps(v)}, GetFloat needs a number")
    return float(v)


def get_int(obj: Any, key: str) -> int:
    v = _field(obj, key)
    if isinstance(v, bool) or not isinstance(v, int) or not INT32[0] <= v <= INT32[1]:
        raise BadMessage(f"'{key}' is {json.dumps(v)}, GetInt needs a JSON integer")
    return v


def get_bool(obj: Any, key: str) -> bool:
    v = _field(obj, key)
    if not isinstance(v, bool):
        raise BadMessage(f"'{key}' is {json.dumps(v)}, GetBool needs true/false")
    return v


def get_string(obj: Any, key: str) -> str:
    v = _field(obj, key)
    if not isinstance(v, str):
        raise BadMessage(f"'{key}' is {json.dumps(v)}, GetString needs a string")
    return v


def _opt(obj: dict, key: str) -> Any:
    """rapidjson's operator[] on a missing member yields null (release build)."""
    return obj.get(key) if isinstance(obj, dict) else None


def _num(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BadMessage(f"{what} is {json.dumps(v)}, GetFloat needs a number")
    return float(v)


def _int(v: Any, what: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not INT32[0] <= v <= INT32[1]:
        raise BadMessage(f"{what} is {json.dumps(v)}, GetInt needs a JSON integer")
    return v


def _bool(v: Any, what: str) -> bool:
    if not isinstance(v, bool):
        raise BadMessage(f"{what} is {json.dumps(v)}, GetBool needs true/false")
    return v


def _str(v: Any, what: str) -> str:
    if not isinstance(v, str):
        raise BadMessage(f"{what} is {json.dumps(v)}, GetString needs a string")
    return v


class Plugin:
    """Message handling and state of the plugin, independent of the transport."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.state = GameState()
        self.clock = clock
        self.sessions = 0
        self.received: list[str] = []  # keys of messages that were applied or ignored
        self.dropped: list[tuple[str, str]] = []  # (raw text, reason)
        self.spawned = 0  # entities created so far (their handles follow from it)

    # ------------------------------------------------------------ dispatch (plugin order)
    def handle(self, raw: bytes) -> bool:
        """Apply one client message. False when the plugin would have choked on it."""
        text = raw.decode("utf-8", errors="replace")
        try:
            doc = json.loads(text)
        except ValueError:
            return self._drop(text, "not valid JSON")
        if not isinstance(doc, dict):
            return self._drop(text, "top level is not an object")
        handlers = (
            ("commands", self._commands),
            ("config", self._config),
            ("start", self._start),
            ("stop", self._stop),
            ("StartRecording", lambda body: self._record(True)),
            ("StopRecording", lambda body: self._record(False)),
            ("GoToLocation", self._go_to),
            ("TeleportToLocation", self._teleport),
            ("SetCameraPositionAndRotation", self._camera),
            ("CreatePed", self._create_ped),
            ("CreateVehicle", self._create_vehicle),
            ("SetWeather", self._weather),
            ("SetClockTime", self._clock),
        )
        for key, fn in handlers:
            if key in doc:
                try:
                    fn(doc[key])
                except BadMessage as exc:
                    return self._drop(text, f"{key}: {exc}")
                self.received.append(key)
                return True
        return self._drop(text, "no known message key")

    def _drop(self, text: str, reason: str) -> bool:
        log.warning("dropped message (%s): %.200s", reason, text)
        self.dropped.append((text, reason))
        return False

    # ------------------------------------------------------------ handlers
    def _commands(self, body: Any) -> None:
        self.state.commands = (
            get_float(body, "throttle"), get_float(body, "brake"), get_float(body, "steering")
        )

    def _start(self, body: Any) -> None:
        sc, dc = _opt(body, "scenario"), _opt(body, "dataset")
        if self.state.running:
            return  # Scenario::start returns at once while running
        parsed_sc = self._parse_scenario(sc, defaults=True)
        parsed_ds = self._parse_dataset(dc, defaults=True)
        self.state.running = True
        self.sessions += 1
        self._apply(parsed_sc, parsed_ds)

    def _config(self, body: Any) -> None:
        sc, dc = _opt(body, "scenario"), _opt(body, "dataset")
        if not self.state.running:
            return
        parsed_sc = self._parse_scenario(sc, defaults=False)
        parsed_ds = self._parse_dataset(dc, defaults=False)
        self._apply(parsed_sc, parsed_ds)

    def _stop(self, body: Any) -> None:
        self.state.running = False
        self.state.commands = (0.0, 0.0, 0.0)

    def _record(self, on: bool) -> None:
        self.state.recording = on

    def _go_to(self, body: Any) -> None:
        for key in ("x", "y", "z", "speed"):
            get_float(body, key)

    def _teleport(self, body: Any) -> None:
        x, y, z = get_float(body, "x"), get_float(body, "y"), get_float(body, "z")
        self.state.x, self.state.y, self.state.z = x, y, z

    def _camera(self, body: Any) -> None:
        self.state.camera = tuple(  # type: ignore[assignment]
            get_float(body, k) for k in ("x", "y", "z", "rot_x", "rot_y", "rot_z")
        )

    def _create_ped(self, body: Any) -> None:
        model = get_string(body, "model")
        fwd, right = get_float(body, "relativeForward"), get_float(body, "relativeRight")
        up, heading = get_float(body, "relativeUp"), get_float(body, "heading")
        on_ground = get_bool(body, "placeOnGround")
        get_string(body, "animDict")
        get_string(body, "animName")
        self._spawn("ped", model, fwd, right, 0.0 if on_ground else up, heading, (-1, -1))

    def _create_vehicle(self, body: Any) -> None:
        model = get_string(body, "model")
        fwd, right = get_float(body, "relativeForward"), get_float(body, "relativeRight")
        heading = get_float(body, "heading")
        color, color2 = get_int(body, "color"), get_int(body, "color2")
        get_bool(body, "placeOnGround")
        get_bool(body, "withLifeJacketPed")
        self._spawn("vehicle", model, fwd, right, 0.0, heading, (color, color2))

    def _weather(self, body: Any) -> None:
        name = get_string(body, "weather")
        if name in WEATHERS:  # SET_WEATHER_TYPE_NOW_PERSIST ignores unknown names
            self.state.weather = name

    def _clock(self, body: Any) -> None:
        h, m, s = get_int(body, "hour"), get_int(body, "minute"), get_int(body, "second")
        # SET_CLOCK_TIME wraps out-of-range values
        total = (h * 3600 + m * 60 + s) % 86400
        self.state.hour, self.state.minute, self.state.second = total // 3600, total // 60 % 60, total % 60

    # ------------------------------------------------------------ start/config parsing
    def _parse_scenario(self, sc: Any, defaults: bool) -> dict[str, Any]:
        out: dict[str, Any] = {}
        sc = _object_or_null(sc, "scenario")
        loc = sc.get("location")
        if isinstance(loc, list):
            if len(loc) < 2:
                raise BadMessage("scenario.location needs [x, y, z?, heading?]")
            for i, key in enumerate(("x", "y", "z", "heading")):
                if i < len(loc) and loc[i] is not None:
                    out[key] = _num(loc[i], f"scenario.location[{i}]")
                elif defaults:
                    out[key] = 0.0
        elif loc is not None:
            raise BadMessage("scenario.location is not an array")
        elif defaults:
            out.update(x=0.0, y=0.0, z=0.0, heading=0.0)
        t = sc.get("time")
        if isinstance(t, list):
            if len(t) < 2:
                raise BadMessage("scenario.time needs [hour, minute]")
            if t[0] is not None:
                out["hour"] = _int(t[0], "scenario.time[0]") % 24
            if t[1] is not None:
                out["minute"] = _int(t[1], "scenario.time[1]") % 60
        elif t is not None:
            raise BadMessage("scenario.time is not an array")
        elif defaults:
            out.update(hour=16, minute=0)
        for key, attr, default in (("weather", "weather", "CLEAR"), ("vehicle", "vehicle", "blista")):
            v = sc.get(key)
            if v is not None:
                out[attr] = _str(v, f"scenario.{key}")
            elif defaults:
                out[attr] = default
        dm = sc.get("drivingMode")
        if isinstance(dm, list) and dm and dm[0] is not None:
            out["driving_mode"] = _int(dm[0], "scenario.drivingMode[0]")
        elif dm is not None and not isinstance(dm, list):
            raise BadMessage("scenario.drivingMode is not an array")
        elif defaults:
            out["driving_mode"] = -1
        ds = sc.get("spawnedEntitiesDespawnSeconds")
        if ds is not None:
            out["despawn_s"] = _num(ds, "scenario.spawnedEntitiesDespawnSeconds")
        elif defaults:
            out["despawn_s"] = 60.0
        return out

    def _parse_dataset(self, dc: Any, defaults: bool) -> dict[str, Any]:
        out: dict[str, Any] = {}
        dc = _object_or_null(dc, "dataset")
        if dc.get("rate") is not None:
            rate = _num(dc["rate"], "dataset.rate")
            if rate <= 0:
                raise BadMessage("dataset.rate must be positive")
            out["rate"] = rate
        elif defaults:
            out["rate"] = 10.0
        frame = dc.get("frame")
        if isinstance(frame, list):
            if len(frame) < 2:
                raise BadMessage("dataset.frame needs [width, height]")
            if frame[0] is not None:
                out["width"] = _int(frame[0], "dataset.frame[0]")
            if frame[1] is not None:
                out["height"] = _int(frame[1], "dataset.frame[1]")
            for key in ("width", "height"):
                if key in out and not 1 <= out[key] <= 16384:
                    raise BadMessage(f"dataset.frame {key} {out[key]} is not a usable size")
        elif frame is not None:
            raise BadMessage("dataset.frame is not an array")
        elif defaults:
            out.update(width=1920, height=1080)
        screen = dc.get("screenResolution")
        if isinstance(screen, list) and len(screen) >= 2 and all(v is not None for v in screen[:2]):
            out["screen"] = (_int(screen[0], "dataset.screenResolution[0]"),
                             _int(screen[1], "dataset.screenResolution[1]"))
            if not all(1 <= v <= 16384 for v in out["screen"]):
                raise BadMessage(f"dataset.screenResolution {list(out['screen'])} is not a usable size")
        elif screen is not None and not isinstance(screen, list):
            raise BadMessage("dataset.screenResolution is not an array")
        elif defaults:
            out["screen"] = None
        report = {}
        for key in ("vehicles", "peds", "location", "time"):
            if dc.get(key) is not None:
                report[key] = _bool(dc[key], f"dataset.{key}")
            elif defaults:
                report[key] = False
        out["report"] = report
        for key in ("trafficSigns", "speed", "offscreen", "showBoxes", "collectTracking", "exportBBox2DUnprocessed"):
            if dc.get(key) is not None:
                _bool(dc[key], f"dataset.{key}")
        if dc.get("exportBBox2D") is not None:
            out["export_bbox2d"] = _bool(dc["exportBBox2D"], "dataset.exportBBox2D")
        elif defaults:
            out["export_bbox2d"] = False
        if dc.get("stationaryScene") is not None:
            out["stationary"] = _bool(dc["stationaryScene"], "dataset.stationaryScene")
        elif defaults:
            out["stationary"] = False
        return out

    def _apply(self, sc: dict[str, Any], ds: dict[str, Any]) -> None:
        s = self.state
        report = ds.pop("report", {})
        for key, value in {**sc, **ds}.items():
            setattr(s, key, value)
        s.report = {**s.report, **report}
        s.second = 0

    # ------------------------------------------------------------ world
    def _spawn(self, kind: str, model: str, fwd: float, right: float, up: float, heading: float,
               color: tuple[int, int]) -> None:
        s = self.state
        (fx, fy), (rx, ry) = s.forward_right()
        self.spawned += 1
        s.entities.append(
            Entity(kind, model, s.x + fwd * fx + right * rx, s.y + fwd * fy + right * ry,
                   s.z + up, heading % 360.0, self.clock(), color, handle=FIRST_HANDLE + 256 * self.spawned)
        )

    def tick(self) -> None:
        """Per-game-tick housekeeping: despawn entities older than spawnedEntitiesDespawnSeconds."""
        now = self.clock()
        s = self.state
        if s.entities:
            s.entities = [e for e in s.entities if now - e.spawned_at <= s.despawn_s]

    def message(self) -> dict[str, Any]:
        """The JSON document sent after each frame (its bbox2d string, while recording, is added by encode_state)."""
        s = self.state
        s.index += 1
        (fx, fy), (rx, ry) = s.forward_right()
        cx, cy, cz, crx, cry, crz = s.camera
        doc: dict[str, Any] = {
            "index": s.index,
            "HeightAboveGround": 0.5,
            "CameraPosition": [s.x + cy * fx + cx * rx, s.y + cy * fy + cx * ry, s.z + cz],
            "CameraAngle": [crx, cry, (s.heading + crz) % 360.0],
            "weather": s.weather,
        }
        if s.report.get("location"):
            doc["location"] = [s.x, s.y, s.z]
        if s.report.get("time"):
            doc["time"] = [s.hour, s.minute, s.second]
        near = [e for e in s.entities if math.hypot(e.x - s.x, e.y - s.y) < REPORT_RADIUS_M]
        if s.report.get("vehicles"):
            doc["vehicles"] = [
                {"model": e.model, "classID": _class_id(e.model), "position": [e.x, e.y, e.z],
                 "heading": e.heading, "speed": 0.0, "spawned": True}
                for e in near if e.kind == "vehicle"
            ]
        if s.report.get("peds"):
            doc["peds"] = [
                {"model": e.model, "position": [e.x, e.y, e.z], "heading": e.heading,
                 "speed": 0.0, "spawned": True}
                for e in near if e.kind == "ped"
            ]
        if s.export_bbox2d:  # the plugin's placeholder; the string follows as a second member (encode_state)
            doc["bbox2d"] = None
        return doc


def encode_state(doc: dict[str, Any], bbox2d: str | None) -> bytes:
    """The frame's JSON as the plugin writes it: with a bbox2d string, a second "bbox2d" member after the null
    placeholder (rapidjson's AddMember appends, so the key appears twice; a JSON reader keeps the last)."""
    text = json.dumps(doc)
    if bbox2d is not None and "bbox2d" in doc:
        text = text[:-1] + ", " + json.dumps("bbox2d") + ": " + json.dumps(bbox2d) + "}"
    return text.encode()


def _class_id(model: str) -> int:
    m = model.lower()
    return 2 if m in _BICYCLES else 1 if m in _MOTORCYCLES else 0


def bbox2d_type(e: Entity) -> str:
    """The plugin's object type of an entity (its vehicle table for vehicles; Pedestrian or Animal for peds)."""
    if e.kind != "vehicle":
        return "Animal" if e.kind == "animal" else "Pedestrian"
    m = e.model.lower()
    for names, kind in ((_BUSES, "Bus"), (_TRUCKS, "Truck"), (_TRAILERS, "Trailer"), (_BOATS, "Boat")):
        if m in names:
            return kind
    return {0: "Car", 1: "Motorbike", 2: "Cyclist"}[_class_id(m)]


def _msvc_float(v: float) -> str:
    """A float as the plugin's stream writes it in an MSVC build (%g-like; NaN as -nan(ind))."""
    return "-nan(ind)" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else f"{v:g}"


def _model_string(e: Entity) -> str:
    """The plugin's model field: a vehicle's name in lower case, letters only (as it spells display names); a ped's
    model hash in decimal."""
    if e.kind == "vehicle":
        return model_key(e.model)
    text = e.model.strip()
    return str(int(text, 16) if text.lower().startswith("0x") else joaat(text))


# --------------------------------------------------------------------------- synthetic picture

_WEATHER_LIGHT = {
    "EXTRASUNNY": 1.0, "CLEAR": 0.95, "NEUTRAL": 0.9, "CLOUDS": 0.8, "CLEARING": 0.75, "SMOG": 0.75,
    "OVERCAST": 0.65, "FOGGY": 0.7, "RAIN": 0.55, "THUNDER": 0.45, "SNOWLIGHT": 0.85, "SNOW": 0.8,
    "BLIZZARD": 0.7, "XMAS": 0.85,
}
_WEATHER_FOG = {
    "FOGGY": 0.7, "SMOG": 0.35, "BLIZZARD": 0.55, "RAIN": 0.2, "THUNDER": 0.25, "OVERCAST": 0.05,
    "SNOW": 0.2, "SNOWLIGHT": 0.1, "XMAS": 0.15,
}


def _geometry_key(s: GameState) -> tuple:
    ents = tuple(
        (e.kind, e.model, round(e.x, 2), round(e.y, 2), round(e.heading, 1), e.handle) for e in s.entities
    )
    return (s.width, s.height, s.picture_size(), s.traffic, round(s.x, 2), round(s.y, 2), round(s.z, 2),
            round(s.heading, 2),
            tuple(round(c, 3) for c in s.camera), ents)


class SyntheticView:
    """Albedo and depth of a procedural street view, cached per geometry; lit per condition."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._albedo: np.ndarray | None = None
        self._depth: np.ndarray | None = None
        self._owner: np.ndarray | None = None  # entity handle per pixel (0: none)
        self._drawn: dict[int, tuple[int, int, int, int]] = {}  # handle -> its drawn box, before clipping
        self._lit: dict[tuple, np.ndarray] = {}
        self._boxes: str | None = None

    def _ensure(self, s: GameState) -> None:
        key = _geometry_key(s)
        if key != self._key:
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                self._albedo, self._depth, self._owner, self._drawn = self._geometry(s)
            self._key = key
            self._lit.clear()
            self._boxes = None

    def instance_map(self, s: GameState) -> np.ndarray:
        """The entity handle of every pixel of the picture of `s` (0 where no entity is seen), int32 HxW."""
        self._ensure(s)
        assert self._owner is not None
        return self._owner

    def bbox2d(self, s: GameState) -> str:
        """The plugin's bbox2d string for the picture of `s` (see the module docstring)."""
        self._ensure(s)
        if self._boxes is None:
            self._boxes = self._bbox2d(s)
        return self._boxes

    def _bbox2d(self, s: GameState) -> str:
        owner, (w, h) = self.instance_map(s), s.picture_size()
        fw, fh = s.width, s.height  # the boxes' pixels: dataset.frame
        near = [e for e in [*s.entities, *s.ambient()] if math.hypot(e.x - s.x, e.y - s.y) < REPORT_RADIUS_M]
        (fx, fy), (rx, ry) = s.forward_right()
        cam_x, cam_y, cam_z = s.camera[:3]
        lines = []
        for e in sorted(near, key=lambda e: (e.kind != "vehicle", e.handle)):
            rows, cols = np.nonzero(owner == e.handle)
            if len(rows):  # first and last pixel, in frame pixels
                left, top = int(cols.min()) * fw // w, int(rows.min()) * fh // h
                right, bottom = (int(cols.max()) + 1) * fw // w - 1, (int(rows.max()) + 1) * fh // h - 1
            else:  # the plugin's untouched box: nothing of it on screen
                left, top, right, bottom = fw, fh, 0, 0
            u0, v0, u1, v1 = self._drawn.get(e.handle, (0, 0, 0, 0))
            full = max(u1 - u0, 0) * max(v1 - v0, 0)
            inside = max(min(u1, w) - max(u0, 0), 0) * max(min(v1, h) - max(v0, 0), 0)
            truncated = 1.0 - inside / full if full else math.nan  # the plugin's 1 - inside/total, unguarded
            occluded = 1.0 - len(rows) / inside if inside else 1.0
            width, height, length = _entity_size(e)
            dx, dy = e.x - s.x, e.y - s.y
            x, z = dx * rx + dy * ry - cam_x, dx * fx + dy * fy - cam_y  # KITTI camera frame: x right, z ahead
            y = cam_z + 0.5  # y down, from the camera to the object's bottom
            ry_cam = math.remainder(math.radians(e.heading - s.heading) - math.pi / 2, 2 * math.pi)
            alpha = math.remainder(ry_cam - math.atan2(x, z), 2 * math.pi)
            values = [bbox2d_type(e), truncated, occluded, alpha, left, top, right, bottom, height, width, length,
                      x, y, z, ry_cam, e.handle, len(rows), 0, 0.0, 0.0, 0.0, _model_string(e), e.ped_in]
            lines.append(" ".join(v if isinstance(v, str) else str(v) if isinstance(v, int) else _msvc_float(v)
                                  for v in values) + "\n")
        return "".join(lines)

    def render(self, s: GameState) -> np.ndarray:
        """The picture of `s` at the screen's size (dataset.screenResolution, else dataset.frame)."""
        self._ensure(s)
        assert self._albedo is not None and self._depth is not None
        light_key = (s.hour, s.minute, s.weather)
        if light_key not in self._lit:
            self._lit[light_key] = self._light(self._albedo, self._depth, *light_key)
        return self._lit[light_key]

    @staticmethod
    def _geometry(s: GameState) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, tuple[int, int, int, int]]]:
        w, h = s.picture_size()
        seed = zlib.crc32(repr((round(s.x, 1), round(s.y, 1), round(s.heading, 1))).encode())
        rng = np.random.default_rng(seed)
        cam_x, cam_y, cam_h, rot_x, _, rot_z = s.camera
        cam_h = max(cam_h + 0.5, 0.3)  # camera height above the road
        focal = (w / 2.0) / math.tan(math.radians(30.0))
        cx = w / 2.0 - focal * math.tan(math.radians(rot_z))
        horizon = h * 0.45 + focal * math.tan(math.radians(rot_x))
        albedo = np.empty((h, w, 3), dtype=np.float32)
        depth = np.full((h, w), np.inf, dtype=np.float32)
        owner = np.zeros((h, w), dtype=np.int32)
        drawn: dict[int, tuple[int, int, int, int]] = {}
        rows = np.arange(h, dtype=np.float32)[:, None] + 0.5
        cols = np.arange(w, dtype=np.float32)[None, :] + 0.5
        # sky: vertical gradient
        t = np.clip(rows / max(horizon, 1.0), 0.0, 1.0)
        albedo[:] = (np.array([0.45, 0.62, 0.9]) * (1 - t) + np.array([0.78, 0.84, 0.9]) * t)[:, None, :]
        # ground: sidewalk, road, lane marks, by ground distance per row
        below = rows > horizon + 0.5
        dist = np.where(below, focal * cam_h / np.maximum(rows - horizon, 1e-3), np.inf)
        lateral = (cols - cx) * dist / focal + cam_x  # metres right of the ego centre line
        ground = np.broadcast_to(below, (h, w))
        depth[ground] = np.broadcast_to(dist, (h, w))[ground]
        road = ground & (np.abs(lateral) < 5.5)
        walk = ground & ~road
        dashes = np.broadcast_to(np.where(below, np.mod(np.where(below, dist, 0.0), 8.0) < 4.0, False), (h, w))
        lane = road & (np.abs(lateral) < 0.12) & dashes
        edge = road & (np.abs(np.abs(lateral) - 5.3) < 0.15)
        albedo[walk] = (0.62, 0.6, 0.56)
        albedo[road] = (0.28, 0.28, 0.3)
        albedo[lane | edge] = (0.92, 0.9, 0.8)
        # buildings on both sides, far to near (painter's order)
        blocks = []
        for side in (-1.0, 1.0):
            d = 6.0 + float(rng.uniform(0, 6))
            while d < 160.0:
                length = float(rng.uniform(8, 25))
                blocks.append((d, side, float(rng.uniform(7.5, 11)), length,
                               float(rng.uniform(6, 40)), rng.uniform(0.25, 0.85, 3)))
                d += length + float(rng.uniform(1, 6))
        for d, side, offset, length, height, colour in sorted(blocks, key=lambda b: -b[0]):
            _box(albedo, depth, focal, cx, horizon, cam_h, cam_x, d, side * (offset + 2.5), 5.0, height,
                 colour, windows=True)
        # entities relative to the ego pose, far to near
        (fx, fy), (rx, ry) = s.forward_right()
        items = []
        for e in [*s.entities, *s.ambient()]:
            dx, dy = e.x - s.x, e.y - s.y
            fwd = dx * fx + dy * fy - cam_y
            right = dx * rx + dy * ry
            if fwd > 1.0:
                items.append((fwd, right, e))
        for fwd, right, e in sorted(items, key=lambda it: -it[0]):
            size = _entity_size(e)
            hue = zlib.crc32(e.model.encode()) & 0xFFFFFF
            colour = np.array([(hue >> 16) & 255, (hue >> 8) & 255, hue & 255], np.float32) / 255 * 0.7 + 0.15
            drawn[e.handle] = _box(albedo, depth, focal, cx, horizon, cam_h, cam_x, fwd, right, size[0], size[1],
                                   colour, owner=owner, ident=e.handle)
        return albedo, depth, owner, drawn

    @staticmethod
    def _light(albedo: np.ndarray, depth: np.ndarray, hour: int, minute: int, weather: str) -> np.ndarray:
        t = hour + minute / 60.0
        elev = math.sin(math.pi * (t - 6.0) / 12.0)  # 1 at noon, 0 at 6:00/18:00
        daylight = min(max((elev + 0.35) / 1.35, 0.0), 1.0)  # some light until well after sunset
        light = (0.15 + 0.85 * daylight) * _WEATHER_LIGHT.get(weather, 0.9)
        tint = np.array([1.0, 1.0, 1.0], np.float32)
        warm = max(0.0, 1.0 - abs(elev) / 0.35)
        tint = tint * (1 - warm) + np.array([1.0, 0.72, 0.5], np.float32) * warm
        if elev < 0:
            tint = tint * np.array([0.75, 0.85, 1.0], np.float32)
        img = albedo * (light * tint)
        fog = _WEATHER_FOG.get(weather, 0.0)
        if fog > 0:
            f = fog * (1.0 - np.exp(-np.minimum(depth, 1e4) / 40.0))[..., None]
            fog_colour = np.array([0.72, 0.74, 0.76], np.float32) * light
            img = img * (1 - f) + fog_colour * f
        return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _entity_size(e: Entity) -> tuple[float, float, float]:
    """(width, height, length) in metres of an entity's stand-in box."""
    if e.size is not None:
        return e.size
    if e.kind != "vehicle":
        return 0.6, 1.8, 0.5
    if e.model.lower() in _BUSES:
        return 2.6, 3.2, 12.0
    return {0: (2.0, 1.5, 4.5), 1: (0.8, 1.4, 2.1), 2: (0.7, 1.3, 1.8)}[_class_id(e.model)]


def _box(albedo, depth, focal, cx, horizon, cam_h, cam_x, dist, lateral, width, height, colour,
         windows: bool = False, owner: np.ndarray | None = None, ident: int = 0) -> tuple[int, int, int, int]:
    """Paint a front-facing box at ground distance `dist`, centred `lateral` metres right (its pixels get `ident`
    in `owner`); returns the box in pixels (u0, v0, u1, v1) before clipping to the picture."""
    h, w = depth.shape
    u0 = round(cx + focal * (lateral - cam_x - width / 2) / dist)
    u1 = round(cx + focal * (lateral - cam_x + width / 2) / dist)
    v1 = round(horizon + focal * cam_h / dist)
    v0 = round(horizon - focal * (height - cam_h) / dist)
    full = (u0, v0, u1, v1)
    u0, u1, v0, v1 = max(u0, 0), min(u1, w), max(v0, 0), min(v1, h)
    if u0 >= u1 or v0 >= v1:
        return full
    region = depth[v0:v1, u0:u1]
    closer = region > dist
    if owner is not None:
        owner[v0:v1, u0:u1][closer] = ident
    patch = albedo[v0:v1, u0:u1]
    patch[closer] = colour
    if windows and (u1 - u0) > 4 and (v1 - v0) > 4:
        step = max(int(focal * 3.0 / dist), 3)
        vv, uu = np.mgrid[v0:v1, u0:u1]
        win = (((vv - v0) % step) < step // 2) & (((uu - u0) % step) < step // 2) & closer
        patch[win] = np.asarray(colour) * 0.45
    region[closer] = dist
    return full


# --------------------------------------------------------------------------- transports


class _TcpEndpoint:
    """Classic transport: non-blocking like the plugin, one client at a time."""

    def __init__(self, host: str, port: int) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((host, port))
        self.listener.listen(1)
        self.listener.setblocking(False)
        self.port = self.listener.getsockname()[1]
        self.conn: socket.socket | None = None
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.on_disconnect: Callable[[], None] = lambda: None

    def poll(self, timeout: float) -> list[bytes]:
        rlist = [self.listener] + ([self.conn] if self.conn else [])
        wlist = [self.conn] if self.conn and self.outbuf else []
        try:
            readable, writable, _ = select.select(rlist, wlist, [], max(timeout, 0.0))
        except (OSError, ValueError):
            self.disconnect()
            return []
        if self.listener in readable:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                conn = None
            if conn is not None:
                if self.conn is not None:
                    self.disconnect()  # a new client replaces a stale one
                conn.setblocking(False)
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self.conn = conn
                return []
        messages: list[bytes] = []
        if self.conn is not None and self.conn in readable:
            try:
                chunk = self.conn.recv(1 << 16)
            except (BlockingIOError, InterruptedError):
                chunk = None
            except OSError:
                chunk = b""
            if chunk == b"":
                self.disconnect()
                return []
            if chunk:
                self.inbuf += chunk
            while len(self.inbuf) >= 4:
                (n,) = struct.unpack("<I", self.inbuf[:4])
                if n > _MAX_TCP_MESSAGE:
                    log.warning("client sent a %d-byte message; dropping the connection", n)
                    self.disconnect()
                    return messages
                if len(self.inbuf) < 4 + n:
                    break
                messages.append(bytes(self.inbuf[4 : 4 + n]))
                del self.inbuf[: 4 + n]
        if self.conn is not None and writable:
            self.flush()
        return messages

    def ready(self) -> bool:
        """A new frame may be queued: connected and the previous one fully sent."""
        return self.conn is not None and not self.outbuf

    def send_frame(self, frame: bytes, doc: bytes) -> bool:
        self.outbuf += struct.pack("<I", len(frame)) + frame + struct.pack("<I", len(doc)) + doc
        self.flush()
        return True

    def send_raw_and_close(self, data: bytes) -> None:
        if self.conn is None:
            return
        self.outbuf += data
        deadline = time.monotonic() + 1.0
        while self.outbuf and self.conn is not None and time.monotonic() < deadline:
            self.flush()
            time.sleep(0.001)
        self.disconnect()

    def hang_up(self) -> None:
        self.disconnect()

    def flush(self) -> None:
        if self.conn is None or not self.outbuf:
            return
        try:
            sent = self.conn.send(self.outbuf)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.disconnect()
            return
        del self.outbuf[:sent]

    def disconnect(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None
            self.inbuf.clear()
            self.outbuf.clear()
            self.on_disconnect()

    def close(self) -> None:
        self.disconnect()
        self.listener.close()


class _ZmqEndpoint:
    """v2 transport: a PAIR socket bound by the server; frame = two messages (bytes, JSON)."""

    def __init__(self, host: str, port: int) -> None:
        import zmq

        self.zmq = zmq
        self.ctx = zmq.Context()
        self.host = host
        self.sock = self._bind(port)
        self.on_disconnect: Callable[[], None] = lambda: None

    def _bind(self, port: int):
        zmq = self.zmq
        sock = self.ctx.socket(zmq.PAIR)
        sock.setsockopt(zmq.LINGER, 0)
        if port == 0:
            self.port = sock.bind_to_random_port(f"tcp://{self.host}")
        else:
            deadline = time.monotonic() + 2.0
            while True:
                try:
                    sock.bind(f"tcp://{self.host}:{port}")
                    break
                except zmq.ZMQError:
                    if time.monotonic() > deadline:
                        sock.close()
                        raise
                    time.sleep(0.01)
            self.port = port
        return sock

    def poll(self, timeout: float) -> list[bytes]:
        zmq = self.zmq
        messages = []
        if self.sock.poll(int(max(timeout, 0.0) * 1000), zmq.POLLIN):
            while True:
                try:
                    messages.append(self.sock.recv(zmq.NOBLOCK))
                except zmq.Again:
                    break
        return messages

    def ready(self) -> bool:
        return True

    def send_frame(self, frame: bytes, doc: bytes) -> bool:
        zmq = self.zmq
        try:
            self.sock.send(frame, zmq.NOBLOCK)
        except zmq.Again:
            return False  # no peer: nothing is queued (the plugin would block here)
        try:
            self.sock.send(doc, zmq.NOBLOCK)
        except zmq.Again:
            pass
        return True

    def send_raw_and_close(self, data: bytes) -> None:
        """Send `data` as the frame message, then drop the connection (close and re-bind)."""
        zmq = self.zmq
        try:
            self.sock.send(data, zmq.NOBLOCK)
        except zmq.Again:
            pass
        time.sleep(0.02)
        self._rebind(linger_ms=200)  # let the frame reach the client before the hang-up

    def hang_up(self) -> None:
        self._rebind(linger_ms=0)

    def _rebind(self, linger_ms: int) -> None:
        port = self.port
        self.sock.close(linger=linger_ms)
        self.sock = self._bind(port)
        self.on_disconnect()

    def close(self) -> None:
        self.sock.close(linger=0)
        self.ctx.term()


# --------------------------------------------------------------------------- server


class DeepGTAVTestServer:
    """The plugin stand-in, run in a background thread (``start``/``stop``) or in the foreground
    (``serve_forever``). ``port=0`` picks a free port; read it back from ``port`` after start."""

    def __init__(
        self,
        transport: str = "zmq",
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        fault: str | None = None,
        fault_sessions: int | None = None,
        on_bad_message: str = "drop",
        traffic: bool = True,
    ) -> None:
        if transport not in ("zmq", "tcp"):
            raise ValueError(f"transport must be 'zmq' or 'tcp', not {transport!r}")
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"fault must be one of {FAULTS}, not {fault!r}")
        if on_bad_message not in ("drop", "close"):
            raise ValueError("on_bad_message must be 'drop' or 'close'")
        self.transport = transport
        self.host = host
        self.port = port
        self.fault = fault
        self.fault_sessions = fault_sessions
        self.on_bad_message = on_bad_message
        self.plugin = Plugin()
        self.plugin.state.traffic = traffic  # the AMBIENT entities (False: only what the client spawns)
        self.view = SyntheticView()
        self.frames_sent = 0
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._endpoint: _TcpEndpoint | _ZmqEndpoint | None = None
        self._last_sent = -math.inf
        self._session_frames = 0
        self._random = random.Random(1234)
        self._encoded: tuple[np.ndarray, bytes] | None = None

    # ------------------------------------------------------------ observability
    @property
    def received(self) -> list[str]:
        with self.lock:
            return list(self.plugin.received)

    @property
    def dropped(self) -> list[tuple[str, str]]:
        with self.lock:
            return list(self.plugin.dropped)

    @property
    def sessions(self) -> int:
        with self.lock:
            return self.plugin.sessions

    def snapshot(self) -> GameState:
        import copy

        with self.lock:
            return copy.deepcopy(self.plugin.state)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> Self:
        self._thread = threading.Thread(target=self._run, name=f"deepgtav-{self.transport}", daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError("DeepGTAV test server did not start within 10 s")
        if self._error is not None:
            raise RuntimeError(f"DeepGTAV test server failed to start: {self._error}") from self._error
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def serve_forever(self) -> None:
        self._run()

    def _run(self) -> None:
        try:
            self._endpoint = _ZmqEndpoint(self.host, self.port) if self.transport == "zmq" else _TcpEndpoint(
                self.host, self.port
            )
        except BaseException as exc:  # noqa: BLE001 - reported by start()
            self._error = exc
            self._ready.set()
            return
        self.port = self._endpoint.port
        self._endpoint.on_disconnect = self._on_disconnect
        self._ready.set()
        try:
            while not self._stop.is_set():
                self._tick()
        finally:
            self._endpoint.close()

    def _on_disconnect(self) -> None:
        if self.transport == "tcp":  # the classic plugin stops the scenario when the client goes
            self.plugin.state.running = False

    def _encode(self, rgb: np.ndarray) -> bytes:
        if self._encoded is None or self._encoded[0] is not rgb:
            self._encoded = (rgb, encode_bgr_padded(rgb))
        return self._encoded[1]

    # ------------------------------------------------------------ one game tick
    def _faulty(self) -> str | None:
        if self.fault is None:
            return None
        if self.fault_sessions is not None and self.plugin.sessions > self.fault_sessions:
            return None
        return self.fault

    def _tick(self) -> None:
        ep = self._endpoint
        assert ep is not None
        with self.lock:
            running, rate = self.plugin.state.running, self.plugin.state.rate
        # a game tick is at most 5 ms; sooner when the next frame is due
        wait = min(max(self._last_sent + 1.0 / rate - time.monotonic(), 0.0), 0.005) if running else 0.005
        for raw in ep.poll(wait):
            with self.lock:
                sessions_before = self.plugin.sessions
                ok = self.plugin.handle(raw)
                if self.plugin.sessions != sessions_before:
                    self._session_frames = 0
            if not ok and self.on_bad_message == "close":
                ep.hang_up()  # like a plugin that crashed on the message
                return
        with self.lock:
            self.plugin.tick()
            state = self.plugin.state
            if not state.running or time.monotonic() - self._last_sent < 1.0 / state.rate or not ep.ready():
                return
            fault = self._faulty()
            if fault == "silent":
                self._last_sent = time.monotonic()
                return
            frame = self._encode(self.view.render(state))
            boxes = self.view.bbox2d(state) if state.sends_boxes() else None
            doc = encode_state(self.plugin.message(), boxes)
            width, height = state.picture_size()
        self._last_sent = time.monotonic()
        self._session_frames += 1
        if fault == "close_mid_frame":
            if self.transport == "tcp":  # length prefix and half the pixels, then hang up
                ep.send_raw_and_close(struct.pack("<I", len(frame)) + frame[: len(frame) // 2])
            else:  # zmq messages are atomic: hang up between the pixels and the JSON
                ep.send_raw_and_close(frame)
            return
        if fault == "garbage":
            doc = bytes(self._random.getrandbits(8) for _ in range(64)) + b"\xff{not json"
        elif fault == "wrong_size":
            frame = frame[: (height - 1) * width * 3]
        if ep.send_frame(frame, doc):
            self.frames_sent += 1


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="DeepGTAV protocol test server (no game needed).")
    parser.add_argument("--transport", choices=("zmq", "tcp"), default="zmq")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--fault", choices=FAULTS, default=None)
    parser.add_argument("--fault-sessions", type=int, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    server = DeepGTAVTestServer(args.transport, args.host, args.port, fault=args.fault,
                                fault_sessions=args.fault_sessions)
    signal.signal(signal.SIGTERM, lambda *_: server._stop.set())
    print(f"DeepGTAV test server ({args.transport}) on {args.host}:{args.port}; Ctrl-C to stop", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
