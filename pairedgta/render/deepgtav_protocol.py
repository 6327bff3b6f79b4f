"""DeepGTAV wire protocol: the messages the plugin reads, the frames it streams, and their checks.

Facts of the plugin (DeepGTAV and its v2 fork with scene-control messages): every message is a
JSON object with exactly one key; the plugin reads its fields with typed getters (a float field
sent as a string, or a missing field, is dropped silently or crashes it), so `validate_message`
checks every field's JSON type and range before anything is sent. A frame is 8-bit BGR rows
padded to 4 bytes followed by a JSON state document; `decode_frame` returns RGB and
`parse_state` the document. The transports that carry these bytes are in
pairedgta/render/deepgtav_transport.py; the test server (pairedgta/testing/deepgtav_server.py)
shares the constants below.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from pairedgta.errors import RendererError
from pairedgta.scene.validation import joaat

WEATHERS = frozenset(
    ["CLEAR", "EXTRASUNNY", "CLOUDS", "OVERCAST", "RAIN", "CLEARING", "THUNDER", "SMOG", "FOGGY", "XMAS", "SNOWLIGHT", "BLIZZARD", "NEUTRAL", "SNOW"]
)
INT32 = (-(2**31), 2**31 - 1)  # range of the plugin's GetInt

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


class ReplyError(ValueError):
    """A frame's JSON document that is not a state object (a corrupted or out-of-step reply)."""


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



def parse_state(raw: bytes) -> dict[str, Any]:
    """A frame's JSON document as the state dict; ReplyError, worded as what the server sent, otherwise."""
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise ReplyError(f"sent a frame whose JSON document is not valid JSON ({raw[:24]!r}...)") from None
    except RecursionError:  # hostile or broken nesting ([[[[...]]]]): not a state document
        raise ReplyError(f"sent a frame whose JSON document nests too deeply to parse ({raw[:24]!r}...)") from None
    if not isinstance(doc, dict):
        raise ReplyError(f"sent a JSON document that is a {type(doc).__name__}, not an object")
    return doc


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
        return isinstance(value, int) and not isinstance(value, bool) and INT32[0] <= value <= INT32[1]
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


def wire_float(value: Any) -> Any:
    """Floats for float fields (ints become floats; anything else is left for validation)."""
    if isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool):
        return float(value)
    return value


def wire_int(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    return value


__all__ = [
    "INT32",
    "MESSAGE_FIELDS",
    "WEATHERS",
    "FrameSizeError",
    "MessageError",
    "ReplyError",
    "decode_frame",
    "encode_message",
    "frame_nbytes",
    "paint_index",
    "parse_state",
    "ped_model",
    "row_stride",
    "validate_message",
    "wire_float",
    "wire_int",
]
