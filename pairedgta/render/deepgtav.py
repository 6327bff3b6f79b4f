"""GTA V backend: a client of the DeepGTAV plugin (its wire protocol is reproduced, for tests
without the game, by pairedgta/testing/deepgtav_server.py).

Semantic scene construction (`prepare`): start or reconfigure a stationary session at the ego
pose, TeleportToLocation, SetCameraPositionAndRotation, then CreateVehicle/CreatePed for every
descriptor object (positions relative to the ego vehicle). Condition-wise rendering (`render`):
SetClockTime and SetWeather, wait `settle_s` while discarding the frames the plugin streams, skip
`settle_frames` more, and capture the first frame whose JSON shows the condition applied.

The plugin streams a frame every 1/rate seconds once a session runs and silently drops messages
it cannot parse, so every message is checked against the field types the plugin reads before
anything is sent, every receive has a timeout, and a failed step is retried on a fresh connection
(replaying the session and scene) with exponential backoff before one clear RendererError.

Frames arrive as 8-bit BGR rows padded to 4 bytes; `render` returns RGB HxWx3 and the plugin's
JSON document as `RenderResult.state` (ego location, clock, spawned entities when reported), for
`pairedgta.scene.validation.validate_group` to check against the descriptor.
"""
from __future__ import annotations

import json
import logging
import math
import re
import select
import socket
import struct
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from pairedgta.conditions import Condition
from pairedgta.errors import ConfigError, RendererError
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.scene.descriptor import DynamicObject, SceneDescriptor
from pairedgta.scene.validation import (
    PED_CATEGORIES,
    VEHICLE_CATEGORIES,
    entity_mismatches,
    joaat,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

WEATHERS = frozenset(
    ["CLEAR", "EXTRASUNNY", "CLOUDS", "OVERCAST", "RAIN", "CLEARING", "THUNDER", "SMOG", "FOGGY", "XMAS", "SNOWLIGHT", "BLIZZARD", "NEUTRAL", "SNOW"]
)
TRANSPORTS = ("zmq", "tcp")
_INT32 = (-(2**31), 2**31 - 1)
_MAX_JSON_BYTES = 64 << 20

# A few GTA vehicle paint indices with their approximate colour, for descriptor RGB colours
_PAINTS: tuple[tuple[int, tuple[int, int, int]], ...] = (
    (0, (13, 17, 22)),  # metallic black
    (3, (69, 75, 79)),  # metallic dark silver
    (4, (153, 157, 160)),  # metallic silver
    (27, (192, 14, 26)),  # metallic red
    (38, (247, 134, 22)),  # metallic orange
    (88, (255, 204, 0)),  # metallic taxi yellow
    (53, (21, 92, 45)),  # metallic green
    (64, (71, 95, 126)),  # metallic blue
    (70, (11, 156, 241)),  # metallic bright blue
    (97, (101, 63, 35)),  # metallic golden brown
    (111, (255, 255, 255)),  # metallic white
)


class MessageError(RendererError):
    """A message the plugin would drop or crash on; raised before anything is sent."""


class FrameSizeError(RendererError):
    """The plugin sent a frame whose byte count does not match the requested frame size."""


class _Transient(Exception):
    """A failure that a fresh connection may cure (timeout, hang-up, corrupted reply)."""


# --------------------------------------------------------------------------- frames


def row_stride(width: int) -> int:
    """Bytes per BGR row, padded to a multiple of 4 (Windows bitmap scanlines)."""
    return ((width * 3 + 3) // 4) * 4


def frame_nbytes(width: int, height: int) -> int:
    return row_stride(width) * height


def decode_frame(buf: bytes | bytearray | memoryview, width: int, height: int) -> np.ndarray:
    """Padded BGR bytes -> RGB uint8 HxWx3. A buffer of the wrong size raises FrameSizeError."""
    stride = row_stride(width)
    if len(buf) != stride * height:
        raise FrameSizeError(
            f"DeepGTAV frame has {len(buf)} bytes, expected {stride * height} for {width}x{height} BGR "
            f"with rows padded to 4 bytes ({stride} per row); make the plugin's frame size equal "
            "renderer.width x renderer.height"
        )
    rows = np.frombuffer(buf, dtype=np.uint8).reshape(height, stride)
    return np.ascontiguousarray(rows[:, : width * 3].reshape(height, width, 3)[..., ::-1])


# --------------------------------------------------------------------------- message schemas

# field kinds as the plugin reads them: float = GetFloat (any JSON number), int = GetInt (JSON
# integer, int32), bool = GetBool, str = GetString
MESSAGE_FIELDS: dict[str, dict[str, str]] = {
    "commands": {"throttle": "float", "brake": "float", "steering": "float"},
    "TeleportToLocation": {"x": "float", "y": "float", "z": "float"},
    "GoToLocation": {"x": "float", "y": "float", "z": "float", "speed": "float"},
    "SetCameraPositionAndRotation": {
        "x": "float", "y": "float", "z": "float", "rot_x": "float", "rot_y": "float", "rot_z": "float",
    },
    "CreatePed": {
        "model": "str", "relativeForward": "float", "relativeRight": "float", "relativeUp": "float",
        "heading": "float", "placeOnGround": "bool", "animDict": "str", "animName": "str", "task": "int",
    },
    "CreateVehicle": {
        "model": "str", "relativeForward": "float", "relativeRight": "float", "heading": "float",
        "color": "int", "color2": "int", "placeOnGround": "bool", "withLifeJacketPed": "bool",
    },
    "SetWeather": {"weather": "str"},
    "SetClockTime": {"hour": "int", "minute": "int", "second": "int"},
}
_NULL_BODY = ("stop", "StartRecording", "StopRecording")
_SCENARIO_FIELDS = ("location", "time", "weather", "vehicle", "drivingMode", "spawnedEntitiesDespawnSeconds")
_DATASET_BOOLS = (
    "vehicles", "peds", "trafficSigns", "direction", "reward", "throttle", "brake", "steering", "speed",
    "yawRate", "drivingMode", "location", "time", "offscreen", "showBoxes", "pointclouds",
    "stationaryScene", "collectTracking", "recordScenario", "positionScenario",
)


def _type_ok(kind: str, value: Any) -> bool:
    if kind == "float":
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool) and _INT32[0] <= value <= _INT32[1]
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "str":
        return isinstance(value, str)
    raise AssertionError(kind)


_KIND_HINT = {
    "float": "a finite JSON number",
    "int": "a JSON integer (no decimal point)",
    "bool": "true or false",
    "str": "a string",
}


def _bad(where: str, value: Any, kind_or_text: str) -> MessageError:
    want = _KIND_HINT.get(kind_or_text, kind_or_text)
    shown = repr(value)
    if len(shown) > 60:
        shown = shown[:57] + "..."
    return MessageError(f"DeepGTAV message field {where}={shown} must be {want}; fix the value before sending")


def validate_message(message: Any) -> None:
    """Raise MessageError unless `message` has exactly one known key and every field the plugin
    reads is present with the JSON type its getter needs (plus range checks that would otherwise
    silently produce a wrong scene)."""
    if not isinstance(message, dict) or len(message) != 1:
        raise MessageError(
            f"DeepGTAV message must be a JSON object with exactly one key, got {message!r:.80}"
        )
    ((key, body),) = message.items()
    if key in _NULL_BODY:
        if body is not None:
            raise _bad(key, body, "null")
        return
    if key in ("start", "config"):
        _validate_session(key, body)
        return
    fields = MESSAGE_FIELDS.get(key)
    if fields is None:
        raise MessageError(
            f"DeepGTAV message key '{key}' is unknown to the plugin; use one of "
            f"{', '.join(sorted([*MESSAGE_FIELDS, *_NULL_BODY, 'start', 'config']))}"
        )
    if not isinstance(body, dict):
        raise _bad(key, body, "an object")
    for name, kind in fields.items():
        if name not in body:
            raise MessageError(f"DeepGTAV message {key} lacks field '{name}' ({_KIND_HINT[kind]}); send every field")
        if not _type_ok(kind, body[name]):
            raise _bad(f"{key}.{name}", body[name], kind)
    if key == "SetWeather" and body["weather"] not in WEATHERS:
        raise _bad("SetWeather.weather", body["weather"], f"one of {', '.join(sorted(WEATHERS))}")
    if key == "SetClockTime":
        for name, hi in (("hour", 23), ("minute", 59), ("second", 59)):
            if not 0 <= body[name] <= hi:
                raise _bad(f"SetClockTime.{name}", body[name], f"an integer in 0..{hi}")
    if key in ("CreatePed", "CreateVehicle") and not body["model"].strip():
        raise _bad(f"{key}.model", body["model"], "a non-empty model name")
    if key == "CreatePed" and not re.fullmatch(r"0x[0-9a-f]{1,8}", body["model"]):
        raise _bad("CreatePed.model", body["model"], "a hex model hash string like '0x2307a353'")
    if key == "CreateVehicle":
        for name in ("color", "color2"):
            if not -1 <= body[name] <= 255:
                raise _bad(f"CreateVehicle.{name}", body[name], "a paint index in -1..255")
    if key == "commands":
        for name, lo in (("throttle", 0.0), ("brake", 0.0), ("steering", -1.0)):
            if not lo <= body[name] <= 1.0:
                raise _bad(f"commands.{name}", body[name], f"a number in {lo:g}..1")


def _validate_session(key: str, body: Any) -> None:
    if not isinstance(body, dict) or set(body) != {"scenario", "dataset"}:
        raise MessageError(f"DeepGTAV message {key} must be {{\"scenario\": ..., \"dataset\": ...}}, got {body!r:.80}")
    sc, dc = body["scenario"], body["dataset"]
    if sc is not None:
        if not isinstance(sc, dict):
            raise _bad(f"{key}.scenario", sc, "an object or null")
        missing = [f for f in _SCENARIO_FIELDS if f not in sc]
        if missing:
            raise MessageError(f"DeepGTAV message {key}.scenario lacks {missing}; send every field (null = default)")
        _opt_list(sc["location"], f"{key}.scenario.location", ["float"] * 4, min_len=2)
        _opt_list(sc["time"], f"{key}.scenario.time", ["int", "int"])
        if sc["time"] is not None and not (0 <= sc["time"][0] <= 23 and 0 <= sc["time"][1] <= 59):
            raise _bad(f"{key}.scenario.time", sc["time"], "[hour 0..23, minute 0..59]")
        if sc["weather"] is not None and sc["weather"] not in WEATHERS:
            raise _bad(f"{key}.scenario.weather", sc["weather"], f"null or one of {', '.join(sorted(WEATHERS))}")
        if sc["vehicle"] is not None and not (isinstance(sc["vehicle"], str) and sc["vehicle"].strip()):
            raise _bad(f"{key}.scenario.vehicle", sc["vehicle"], "null or a vehicle model name")
        _opt_list(sc["drivingMode"], f"{key}.scenario.drivingMode", ["int", "float"])
        dsec = sc["spawnedEntitiesDespawnSeconds"]
        if dsec is not None and not (_type_ok("float", dsec) and dsec > 0):
            raise _bad(f"{key}.scenario.spawnedEntitiesDespawnSeconds", dsec, "null or a positive number")
    if dc is not None:
        if not isinstance(dc, dict):
            raise _bad(f"{key}.dataset", dc, "an object or null")
        rate = dc.get("rate")
        if rate is not None and not (_type_ok("float", rate) and rate > 0):
            raise _bad(f"{key}.dataset.rate", rate, "null or a positive number of frames per second")
        for name in ("frame", "screenResolution"):
            _opt_list(dc.get(name), f"{key}.dataset.{name}", ["int", "int"])
            if dc.get(name) is not None and min(dc[name]) < 1:
                raise _bad(f"{key}.dataset.{name}", dc[name], "[width >= 1, height >= 1]")
        for name in _DATASET_BOOLS:
            if dc.get(name) is not None and not isinstance(dc[name], bool):
                raise _bad(f"{key}.dataset.{name}", dc[name], "true, false or null")
        vtc = dc.get("vehiclesToCreate")
        if vtc is not None:
            if not isinstance(vtc, list):
                raise _bad(f"{key}.dataset.vehiclesToCreate", vtc, "null or a list")
            for i, item in enumerate(vtc):
                _opt_list(item, f"{key}.dataset.vehiclesToCreate[{i}]", ["str", "float", "float", "float", "int", "int"])
        ptc = dc.get("pedsToCreate")
        if ptc is not None:
            if not isinstance(ptc, list):
                raise _bad(f"{key}.dataset.pedsToCreate", ptc, "null or a list")
            for i, item in enumerate(ptc):
                _opt_list(item, f"{key}.dataset.pedsToCreate[{i}]", ["int", "float", "float", "float"])


def _opt_list(value: Any, where: str, kinds: Sequence[str], min_len: int | None = None) -> None:
    if value is None:
        return
    lo = len(kinds) if min_len is None else min_len
    if not isinstance(value, list) or not lo <= len(value) <= len(kinds):
        raise _bad(where, value, f"null or a list of {len(kinds)} values")
    for i, item in enumerate(value):
        if item is not None and not _type_ok(kinds[i], item):
            raise _bad(f"{where}[{i}]", item, kinds[i])


def encode_message(message: dict[str, Any]) -> bytes:
    """Validate and serialise one message (UTF-8 JSON, NaN/Infinity rejected)."""
    validate_message(message)
    return json.dumps(message, allow_nan=False, separators=(",", ":")).encode("utf-8")


# --------------------------------------------------------------------------- message builders


def ped_model(model: str) -> str:
    """CreatePed's model: the plugin parses a hex hash string, so names are hashed (joaat)."""
    text = str(model).strip()
    if re.fullmatch(r"0x[0-9a-fA-F]{1,8}", text):
        return text.lower()
    if not text:
        return text  # rejected by validate_message
    return f"0x{joaat(text):08x}"


def paint_index(rgb: Sequence[int]) -> int:
    """Nearest GTA paint index (of a small palette) to an RGB colour."""
    r, g, b = (float(c) for c in rgb)
    return min(_PAINTS, key=lambda p: (p[1][0] - r) ** 2 + (p[1][1] - g) ** 2 + (p[1][2] - b) ** 2)[0]


def _f(value: Any) -> Any:
    """Floats for float fields (ints become floats; anything else is left for validation)."""
    if isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool):
        return float(value)
    return value


def _i(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    return value


# --------------------------------------------------------------------------- transports


class _TcpClient:
    """Classic transport: 4-byte little-endian length prefix on each message and frame part."""

    def __init__(self, host: str, port: int, timeout_s: float, max_frame: int) -> None:
        self.where = f"{host}:{port}"
        self.max_frame = max_frame
        try:
            self.sock = socket.create_connection((host, port), timeout=timeout_s)
        except TimeoutError:
            raise _Transient(f"connecting timed out after {timeout_s:g} s") from None
        except OSError as exc:
            raise _Transient(f"cannot connect ({exc.strerror or exc})") from None
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send(self, payload: bytes) -> None:
        try:
            self.sock.sendall(struct.pack("<I", len(payload)) + payload)
        except OSError as exc:
            raise _Transient(f"sending failed ({exc.strerror or exc})") from None

    def pending(self) -> bool:
        try:
            readable, _, _ = select.select([self.sock], [], [], 0)
        except (OSError, ValueError):
            return True  # let the next read report the problem
        return bool(readable)

    def wait(self, timeout: float) -> bool:
        try:
            readable, _, _ = select.select([self.sock], [], [], max(timeout, 0.0))
        except (OSError, ValueError):
            return True
        return bool(readable)

    def _read(self, n: int, deadline: float, what: str, started: bool) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise _Transient(f"timed out waiting for the {what}" + (" (mid-frame)" if started or got else ""))
            self.sock.settimeout(remaining)
            try:
                k = self.sock.recv_into(view[got:], n - got)
            except TimeoutError:
                continue
            except OSError as exc:
                where = " mid-frame" if started or got else ""
                raise _Transient(f"dropped the connection{where} ({exc.strerror or exc})") from None
            if k == 0:
                raise _Transient("closed the connection" + (" mid-frame" if started or got else ""))
            got += k
        return bytes(buf)

    def recv_frame(self, timeout: float) -> tuple[bytes, bytes]:
        deadline = time.monotonic() + timeout
        (n,) = struct.unpack("<I", self._read(4, deadline, "frame length", False))
        if n > self.max_frame:
            raise _Transient(f"sent an implausible frame length prefix ({n} bytes): garbage on the stream")
        frame = self._read(n, deadline, "frame bytes", True)
        (m,) = struct.unpack("<I", self._read(4, deadline, "JSON length", True))
        if m > _MAX_JSON_BYTES:
            raise _Transient(f"sent an implausible JSON length prefix ({m} bytes): garbage on the stream")
        doc = self._read(m, deadline, "JSON document", True)
        return frame, doc

    def close(self, linger_s: float = 0.0) -> None:
        try:
            self.sock.close()  # sendall already handed everything to the kernel
        except OSError:
            pass


class _ZmqClient:
    """v2 transport: PAIR socket, client connects; a frame is two messages (bytes, JSON)."""

    def __init__(self, host: str, port: int, timeout_s: float, max_frame: int) -> None:
        try:
            import zmq
        except ImportError:
            raise ConfigError(
                "renderer.transport=zmq needs pyzmq; install it (pip install pyzmq) or set renderer.transport=tcp"
            ) from None
        self.zmq = zmq
        self.ctx = zmq.Context.instance()
        self.sock = self.ctx.socket(zmq.PAIR)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.SNDTIMEO, max(int(timeout_s * 1000), 1))
        self.sock.connect(f"tcp://{host}:{port}")

    def send(self, payload: bytes) -> None:
        try:
            self.sock.send(payload)
        except self.zmq.Again:
            raise _Transient("sending timed out (no peer accepted the message)") from None
        except self.zmq.ZMQError as exc:
            raise _Transient(f"sending failed ({exc})") from None

    def pending(self) -> bool:
        return bool(self.sock.poll(0, self.zmq.POLLIN))

    def wait(self, timeout: float) -> bool:
        return bool(self.sock.poll(max(int(timeout * 1000), 0), self.zmq.POLLIN))

    def recv_frame(self, timeout: float) -> tuple[bytes, bytes]:
        deadline = time.monotonic() + timeout
        if not self.wait(timeout):
            raise _Transient("timed out waiting for a frame")
        frame = self.sock.recv(self.zmq.NOBLOCK)
        if not self.wait(deadline - time.monotonic()):
            raise _Transient("timed out waiting for the frame's JSON document (mid-frame)")
        doc = self.sock.recv(self.zmq.NOBLOCK)
        return frame, doc

    def close(self, linger_s: float = 0.0) -> None:
        self.sock.close(linger=int(linger_s * 1000))


# --------------------------------------------------------------------------- renderer


class DeepGTAVRenderer(Renderer):
    """GTA V through the DeepGTAV plugin. Keys of conf/renderer/deepgtav.yaml are the kwargs.

    `render` re-initialises the scene only when `descriptor` differs from the scene built on the
    current connection (or after a reconnect): the protocol has no message that removes spawned
    entities, so re-spawning per condition would duplicate them. Spawned entities vanish after
    `despawn_s`; the state check (`check_state`) catches scenes whose entities were lost or moved.
    """

    name = "deepgtav"
    gives_labels = False

    def __init__(
        self,
        width: int = 1280,
        height: int = 720,
        host: str = "127.0.0.1",
        port: int = 8000,
        transport: str = "zmq",
        timeout_s: float = 10.0,
        retries: int = 3,
        backoff_s: float = 1.0,
        settle_s: float = 1.0,
        settle_frames: int = 2,
        rate: float = 10.0,
        ego_vehicle: str = "blista",
        despawn_s: float = 60.0,
        construction_weather: str = "EXTRASUNNY",
        construction_time: Sequence[int] = (12, 0),
        object_heading: str = "relative",
        place_on_ground: bool = True,
        check_state: bool = True,
        clock_tolerance_min: int = 10,
        ego_tolerance_m: float = 5.0,
    ) -> None:
        given = dict(locals())

        def need(key: str, ok: bool, fix: str) -> None:
            if not ok:
                raise ConfigError(f"renderer.{key}={given[key]!r} is invalid; {fix}")

        isnum = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)
        isint = lambda v: isinstance(v, int) and not isinstance(v, bool)
        need("width", isint(width) and 1 <= width <= 16384, "set a frame width in pixels (e.g. 1280)")
        need("height", isint(height) and 1 <= height <= 16384, "set a frame height in pixels (e.g. 720)")
        need("host", isinstance(host, str) and bool(host), "set the address of the machine running GTA V")
        need("port", isint(port) and 1 <= port <= 65535, "set the plugin's port (8000 by default)")
        need("transport", transport in TRANSPORTS, "use 'zmq' (v2 fork) or 'tcp' (classic DeepGTAV)")
        need("timeout_s", isnum(timeout_s) and timeout_s > 0, "set a positive receive timeout in seconds")
        need("retries", isint(retries) and retries >= 0, "set how many times to retry (0 or more)")
        need("backoff_s", isnum(backoff_s) and backoff_s >= 0, "set a non-negative backoff in seconds")
        need("settle_s", isnum(settle_s) and settle_s >= 0, "set a non-negative settle time in seconds")
        need("settle_frames", isint(settle_frames) and settle_frames >= 0, "set 0 or more frames to skip")
        need("rate", isnum(rate) and rate > 0, "set the plugin's frame rate in Hz (e.g. 10)")
        need("timeout_s", timeout_s > 1.0 / rate, f"it must exceed the frame interval 1/renderer.rate = {1.0 / rate:g} s")
        need("ego_vehicle", isinstance(ego_vehicle, str) and bool(ego_vehicle.strip()), "set a GTA vehicle model name")
        need("despawn_s", isnum(despawn_s) and despawn_s > 0, "set how long spawned entities live, in seconds")
        need("construction_weather", construction_weather in WEATHERS, f"use one of {', '.join(sorted(WEATHERS))}")
        ct = list(construction_time) if isinstance(construction_time, (list, tuple)) else None
        need("construction_time", ct is not None and len(ct) == 2 and all(isint(v) for v in ct)
             and 0 <= ct[0] <= 23 and 0 <= ct[1] <= 59, "use [hour, minute], e.g. [12, 0]")
        need("object_heading", object_heading in ("relative", "world"),
             "use 'relative' (object heading relative to the ego) or 'world'")
        need("clock_tolerance_min", isint(clock_tolerance_min) and clock_tolerance_min >= 0,
             "set the allowed clock drift in minutes")
        need("ego_tolerance_m", isnum(ego_tolerance_m) and ego_tolerance_m > 0, "set a distance in metres")
        super().__init__(width, height)
        self.host, self.port, self.transport = host, int(port), transport
        self.timeout_s, self.retries, self.backoff_s = float(timeout_s), int(retries), float(backoff_s)
        self.settle_s, self.settle_frames, self.rate = float(settle_s), int(settle_frames), float(rate)
        self.ego_vehicle, self.despawn_s = ego_vehicle, float(despawn_s)
        self.construction_weather, self.construction_time = construction_weather, (ct[0], ct[1])  # type: ignore[index]
        self._gta_requests: dict[str, tuple[str, int, int]] = {}  # condition -> (weather, hour, minute) asked of GTA
        self.object_heading, self.place_on_ground = object_heading, bool(place_on_ground)
        self.check_state, self.clock_tolerance_min = bool(check_state), int(clock_tolerance_min)
        self.ego_tolerance_m = float(ego_tolerance_m)
        self.frame_bytes = frame_nbytes(self.width, self.height)
        self._conn: _TcpClient | _ZmqClient | None = None
        self._session = False  # a session was started on the current connection
        self._scene: SceneDescriptor | None = None  # scene built on the current connection
        self.last_state: dict[str, Any] = {}
        # since the last prepare(): seconds spent connecting, in failed attempts and in backoff
        # (already part of the prepare/render wall time), and the number of retries
        self.overhead_s = 0.0
        self.retries_used = 0

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    # ------------------------------------------------------------------ Renderer API
    def open(self) -> None:
        self._run("connecting", lambda: None)

    def close(self) -> None:
        if self._conn is not None:
            linger = 0.0
            if self._session:
                try:
                    self._conn.send(encode_message({"stop": None}))  # back to normal gameplay
                    linger = min(self.timeout_s, 1.0)
                except _Transient:
                    pass
            self._conn.close(linger)
            self._conn = None
            self._drop_connection()

    def prepare(self, descriptor: SceneDescriptor) -> None:
        """Semantic scene construction: session at the ego pose, teleport, camera, objects."""
        self.scene_messages(descriptor)  # validate everything before anything is sent
        self.overhead_s, self.retries_used = 0.0, 0
        self._run("scene construction", lambda: self._construct(descriptor))

    def render(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        """Condition-wise rendering: clock + weather, settle, capture (builds the scene first when
        `descriptor` is not the one built on the current connection)."""
        self.scene_messages(descriptor)
        self.condition_messages(condition)
        return self._run(f"rendering of condition '{condition.name}'", lambda: self._capture(descriptor, condition))

    # ------------------------------------------------------------------ messages
    def session_message(self, descriptor: SceneDescriptor, key: str = "start") -> dict[str, Any]:
        loc = descriptor.location
        scenario = {
            "location": [_f(loc.x), _f(loc.y), _f(loc.z), _f(loc.heading)],
            "time": [self.construction_time[0], self.construction_time[1]],
            "weather": self.construction_weather,
            "vehicle": self.ego_vehicle,
            "drivingMode": None,  # default: no AI driving
            "spawnedEntitiesDespawnSeconds": self.despawn_s,
        }
        dataset = {
            "rate": self.rate,
            "frame": [self.width, self.height],
            "screenResolution": [self.width, self.height],
            "vehicles": True,
            "peds": True,
            "trafficSigns": None,
            "speed": None,
            "location": True,
            "time": True,
            "offscreen": None,
            "stationaryScene": True,
            "vehiclesToCreate": None,
            "pedsToCreate": None,
        }
        return {key: {"scenario": scenario, "dataset": dataset}}

    def scene_messages(self, descriptor: SceneDescriptor) -> list[dict[str, Any]]:
        """TeleportToLocation, SetCameraPositionAndRotation and one Create* per object, validated
        (the session message is validated too). Raises MessageError on the first bad field."""
        validate_message(self.session_message(descriptor))
        loc, cam = descriptor.location, descriptor.camera
        msgs: list[dict[str, Any]] = [
            {"TeleportToLocation": {"x": _f(loc.x), "y": _f(loc.y), "z": _f(loc.z)}},
            {"SetCameraPositionAndRotation": {
                "x": _f(cam.x), "y": _f(cam.y), "z": _f(cam.z),
                "rot_x": _f(cam.rot_x), "rot_y": _f(cam.rot_y), "rot_z": _f(cam.rot_z),
            }},
        ]
        msgs += self.object_messages(descriptor)
        for m in msgs:
            validate_message(m)
        return msgs

    def object_messages(self, descriptor: SceneDescriptor) -> list[dict[str, Any]]:
        return [self._object_message(descriptor, o) for o in descriptor.objects]

    def _object_message(self, descriptor: SceneDescriptor, obj: DynamicObject) -> dict[str, Any]:
        heading = _f(obj.heading)
        if self.object_heading == "relative" and isinstance(heading, float):
            heading = (descriptor.location.heading + heading) % 360.0  # the plugin takes world headings
        if obj.category in VEHICLE_CATEGORIES:
            return {"CreateVehicle": {
                "model": obj.model, "relativeForward": _f(obj.forward), "relativeRight": _f(obj.right),
                "heading": heading, "color": paint_index(obj.color), "color2": paint_index(obj.secondary_color),
                "placeOnGround": self.place_on_ground, "withLifeJacketPed": False,
            }}
        assert obj.category in PED_CATEGORIES, obj.category
        return {"CreatePed": {
            "model": ped_model(obj.model) if isinstance(obj.model, str) else obj.model,
            "relativeForward": _f(obj.forward), "relativeRight": _f(obj.right), "relativeUp": _f(obj.up),
            "heading": heading, "placeOnGround": self.place_on_ground, "animDict": "", "animName": "",
            "task": 0,
        }}

    def gta_mapping(self, condition: Condition) -> dict[str, Any]:
        """What GTA V is asked for, and the physical parameters it cannot honour: GTA has discrete
        weathers and a clock, no visibility, rain-rate or sun-elevation control. The config names the
        nearest weather and clock per condition (a ladder's steps say theirs); this says so once per
        condition, and warns when two conditions of the run collapse onto the same request."""
        request = (condition.weather, int(condition.clock_hour), int(condition.clock_minute))
        physical = {k: v for k, v in (("visibility_m", condition.visibility_m), ("rain_mm_h", condition.rain_mm_h),
                                      ("sun_elevation_deg", condition.sun_elevation_deg)) if v}
        seen = self._gta_requests
        if condition.name not in seen:
            twins = [n for n, r in seen.items() if r == request]
            seen[condition.name] = request
            units = ", ".join(f"{k}={v:g}" for k, v in physical.items())
            log.info("DeepGTAV: %s (%s) is rendered as GTA weather %s at %02d:%02d; GTA V has no continuous "
                     "visibility, rain-rate or sun-elevation control", condition.name, units or "clear", *request)
            if twins:
                log.warning("DeepGTAV: %s asks GTA V for the same weather and clock as %s (%s at %02d:%02d): their "
                            "images differ only by what GTA varies between captures; use renderer=blender for a "
                            "severity ladder", condition.name, ", ".join(twins), *request)
        return {"gta_weather": request[0], "gta_clock": f"{request[1]:02d}:{request[2]:02d}", "not_rendered": physical}

    def condition_messages(self, condition: Condition) -> list[dict[str, Any]]:
        msgs = [
            {"SetClockTime": {"hour": _i(condition.clock_hour), "minute": _i(condition.clock_minute), "second": 0}},
            {"SetWeather": {"weather": condition.weather}},
        ]
        for m in msgs:
            validate_message(m)
        return msgs

    # ------------------------------------------------------------------ retry machinery
    def _run(self, what: str, fn: Callable[[], T]) -> T:
        attempts = self.retries + 1
        failures: list[str] = []  # distinct reasons, in order of occurrence
        for attempt in range(attempts):
            started = time.perf_counter()
            if attempt:
                self.retries_used += 1
                time.sleep(self.backoff_s * 2 ** (attempt - 1))
            try:
                if self._conn is None:
                    self._connect()
                setup = time.perf_counter() - started  # backoff + connecting
                result = fn()
                self.overhead_s += setup
                return result
            except _Transient as exc:
                self.overhead_s += time.perf_counter() - started  # the whole failed attempt
                log.warning("DeepGTAV %s at %s, attempt %d/%d: %s", what, self.address, attempt + 1, attempts, exc)
                if str(exc) not in failures:
                    failures.append(str(exc))
                self._drop_connection()
            except BaseException:  # a non-transient error (or an interrupt) may leave the stream mid-frame
                self._drop_connection()
                raise
        raise RendererError(
            f"DeepGTAV server at {self.address} ({self.transport}) failed during {what}: {'; then '.join(failures)} "
            f"(gave up after {attempts} attempt{'s' if attempts > 1 else ''}); check that GTA V with the "
            f"plugin is running and reachable, or raise renderer.timeout_s (now {self.timeout_s:g}) / "
            f"renderer.retries (now {self.retries})"
        )

    def _connect(self) -> None:
        cls = _ZmqClient if self.transport == "zmq" else _TcpClient
        max_frame = max(4 * self.frame_bytes, 64 << 20)
        self._conn = cls(self.host, self.port, self.timeout_s, max_frame)
        self._session = False
        self._scene = None

    def _drop_connection(self) -> None:
        if self._conn is not None:
            self._conn.close()
        self._conn = None
        self._session = False
        self._scene = None

    def _send(self, message: dict[str, Any]) -> None:
        assert self._conn is not None
        self._conn.send(encode_message(message))

    # ------------------------------------------------------------------ frames
    def _next_frame(self, timeout: float | None = None) -> tuple[bytes, dict[str, Any]]:
        assert self._conn is not None
        frame, raw = self._conn.recv_frame(self.timeout_s if timeout is None else timeout)
        if len(frame) != self.frame_bytes:
            if raw[:1] == b"{" and frame[:1] == b"{":
                raise _Transient("sent two JSON documents in a row: frame stream out of step")
            decode_frame(frame, self.width, self.height)  # raises FrameSizeError
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            raise _Transient(f"sent a frame whose JSON document is not valid JSON ({raw[:24]!r}...)") from None
        except RecursionError:  # hostile or broken nesting ([[[[...]]]]): not a state document
            raise _Transient(f"sent a frame whose JSON document nests too deeply to parse ({raw[:24]!r}...)") from None
        if not isinstance(doc, dict):
            raise _Transient(f"sent a JSON document that is a {type(doc).__name__}, not an object")
        return frame, doc

    def _discard_until(self, deadline: float) -> None:
        """Read and drop frames until `deadline` (the plugin keeps streaming while we wait)."""
        assert self._conn is not None
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if self._conn.wait(remaining):
                self._next_frame()
        while self._conn.pending():
            self._next_frame()

    def _await(self, accept: Callable[[dict[str, Any]], str | None], what: str) -> tuple[bytes, dict[str, Any]]:
        """First frame whose state `accept` approves (returns None); a transient error with the
        last objection after `timeout_s`."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            frame, state = self._next_frame(max(min(self.timeout_s, deadline - time.monotonic()), 1e-3))
            objection = accept(state) if self.check_state else None
            if objection is None:
                return frame, state
            if time.monotonic() >= deadline:
                raise _Transient(f"never reported {what} within {self.timeout_s:g} s: {objection}")

    # ------------------------------------------------------------------ phases
    def _construct(self, descriptor: SceneDescriptor) -> None:
        msgs = self.scene_messages(descriptor)
        if not self._session:
            self._send({"stop": None})  # a session left over by another client ignores `start`
            self._send(self.session_message(descriptor, "start"))
            self._session = True
        else:
            self._send(self.session_message(descriptor, "config"))
        n_objects = len(descriptor.objects)
        setup, spawns = msgs[: len(msgs) - n_objects], msgs[len(msgs) - n_objects :]
        for m in setup:
            self._send(m)
        self._discard_pending()
        _, state = self._await(lambda s: self._ego_objection(descriptor, s), "the ego vehicle at the scene location")
        if spawns and not (self.check_state and self._entities_reported(state)
                           and not entity_mismatches(descriptor, state, ego_tol_m=self.ego_tolerance_m)):
            for m in spawns:
                self._send(m)
            self._await(lambda s: self._entity_objection(descriptor, s), "the descriptor's objects")
        self._scene = descriptor

    def _capture(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        if self._scene != descriptor:
            self._construct(descriptor)
        for m in self.condition_messages(condition):
            self._send(m)
        self._discard_until(time.monotonic() + self.settle_s)
        for _ in range(self.settle_frames):
            self._next_frame()
        frame, state = self._await(lambda s: self._condition_objection(condition, s), f"condition '{condition.name}'")
        self.last_state = state
        return RenderResult(image=decode_frame(frame, self.width, self.height),
                            state={**state, "gta_mapping": self.gta_mapping(condition)})

    def _discard_pending(self) -> None:
        assert self._conn is not None
        while self._conn.pending():
            self._next_frame()

    # ------------------------------------------------------------------ state checks
    @staticmethod
    def _entities_reported(state: Mapping[str, Any]) -> bool:
        return "vehicles" in state or "peds" in state

    def _ego_objection(self, descriptor: SceneDescriptor, state: Mapping[str, Any]) -> str | None:
        loc = state.get("location")
        if not isinstance(loc, list) or len(loc) < 2:
            return None
        try:
            d = math.hypot(float(loc[0]) - descriptor.location.x, float(loc[1]) - descriptor.location.y)
        except (TypeError, ValueError):
            return f"location {loc!r} is not numeric"
        return None if d <= self.ego_tolerance_m else f"ego is {d:.1f} m from ({descriptor.location.x:g}, {descriptor.location.y:g})"

    def _entity_objection(self, descriptor: SceneDescriptor, state: Mapping[str, Any]) -> str | None:
        problems = entity_mismatches(descriptor, state, ego_tol_m=self.ego_tolerance_m)
        return "; ".join(problems[:3]) if problems else None

    def _condition_objection(self, condition: Condition, state: Mapping[str, Any]) -> str | None:
        weather = state.get("weather")
        if isinstance(weather, str) and weather.upper() != condition.weather.upper():
            return f"weather is {weather}, requested {condition.weather}"
        t = state.get("time")
        if isinstance(t, list) and len(t) >= 2 and all(isinstance(v, (int, float)) for v in t[:2]):
            got, tol = int(t[0]) * 60 + int(t[1]), self.clock_tolerance_min
        elif isinstance(t, (int, float)) and not isinstance(t, bool):  # classic: hour only
            got, tol = int(t) * 60 + condition.clock_minute, max(self.clock_tolerance_min, 60)
        else:
            return None
        want = condition.clock_hour * 60 + condition.clock_minute
        diff = abs(got - want) % 1440
        if min(diff, 1440 - diff) > tol:
            return f"clock is {got // 60:02d}:{got % 60:02d}, requested {condition.clock_hour:02d}:{condition.clock_minute:02d}"
        return None


__all__ = [
    "DeepGTAVRenderer",
    "FrameSizeError",
    "MessageError",
    "decode_frame",
    "encode_message",
    "frame_nbytes",
    "paint_index",
    "ped_model",
    "row_stride",
    "validate_message",
]
