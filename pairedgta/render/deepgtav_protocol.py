"""DeepGTAV wire protocol: the messages the plugin reads, the frames it streams, and their checks.

Facts of the plugin (DeepGTAV and its v2 fork with scene-control messages): every message is a
JSON object with exactly one key; the plugin reads its fields with typed getters (a float field
sent as a string, or a missing field, is dropped silently or crashes it), so `validate_message`
checks every field's JSON type and range before anything is sent. A frame is 8-bit BGR rows
padded to 4 bytes followed by a JSON state document; `decode_frame` returns RGB and
`parse_state` the document; with `dataset.exportBBox2D` the document carries the objects' 2D
boxes as KITTI-like text lines, which `parse_bbox2d` turns into Cityscapes-class boxes. The
transports that carry these bytes are in pairedgta/render/deepgtav_transport.py; the test server
(pairedgta/testing/deepgtav_server.py) shares the constants below.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from pairedgta.errors import DataError, RendererError
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



def _last_member_wins(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object whose repeated member keeps its last value: DeepGTAV-PreSIL writes a `null` placeholder for
    every export it was asked for and, while recording, the same key again with the value (rapidjson AddMember
    does not replace), so `"bbox2d": null, ..., "bbox2d": "Car ..."` means the string."""
    return dict(pairs)


def parse_state(raw: bytes) -> dict[str, Any]:
    """A frame's JSON document as the state dict; ReplyError, worded as what the server sent, otherwise."""
    try:
        doc = json.loads(raw.decode("utf-8"), object_pairs_hook=_last_member_wins)
    except (UnicodeDecodeError, ValueError):
        raise ReplyError(f"sent a frame whose JSON document is not valid JSON ({raw[:24]!r}...)") from None
    except RecursionError:  # hostile or broken nesting ([[[[...]]]]): not a state document
        raise ReplyError(f"sent a frame whose JSON document nests too deeply to parse ({raw[:24]!r}...)") from None
    if not isinstance(doc, dict):
        raise ReplyError(f"sent a JSON document that is a {type(doc).__name__}, not an object")
    return doc


# --------------------------------------------------------------------------- 2D boxes (dataset.exportBBox2D)

# The plugin's bbox2d (DeepGTAV-PreSIL, ObjectDetection::exportEntity through exportDetectionsString): one line per
# vehicle, then per pedestrian, fields separated by single spaces, in the order of its augmented KITTI labels
# (dataformat-augmented.txt): type truncated occluded alpha left top right bottom height width length x y z
# rotation_y, then entity_id points_2d points_3d speed roll pitch model v_ped_is_in. left..bottom are whole pixels of
# the `dataset.frame` size: the first and last column and row of the object's visible pixels (its segmentation; with
# DISTINGUISH_PEDS_IN_VEHICLES a rider's pixels are the rider's, not the vehicle's); an object with none keeps
# "width height 0 0" (left > right), which is not a box. `truncated` is 1 - inside/total of the object's projected
# 3D box, printed unguarded (an MSVC build writes NaN as -nan(ind)); `occluded` the fraction of its points hidden.
# `model` is a vehicle's display name (lower case, letters only) or a ped's model hash; v_ped_is_in is the entity id
# of the vehicle a ped is in, 0 when it is in none.
BBOX2D_FIELDS = ("type", "truncated", "occluded", "alpha", "left", "top", "right", "bottom")
BBOX2D_AUGMENTED_FIELDS = 23  # the 15 KITTI fields and the 8 augmented ones
_ENTITY, _MODEL, _PED_IN = 15, 21, 22  # their places in an augmented line
# the plugin's types (KITTI's and those of its GTA vehicle table) -> Cityscapes instance classes; any other type
# (Misc, DontCare, Trailer, Industrial, Utility, Boat, Airplane, Animal, ...) is not a Cityscapes instance: dropped.
# Cyclist is the bicycle alone and Motorbike the motorcycle alone, their riders are Pedestrian lines (Cityscapes
# labels both: the two-wheeler and its rider); "Moterbike" is the plugin's own spelling for bikes and quads missing
# from its vehicle table. Truck lines of SUVs (BBOX2D_SUVS) are cars.
BBOX2D_CLASSES = {
    "car": "car", "van": "car", "truck": "truck", "bus": "bus",
    "pedestrian": "person", "person_sitting": "person",
    "cyclist": "bicycle", "bicycle": "bicycle",
    "motorbike": "motorcycle", "motorcycle": "motorcycle", "moterbike": "motorcycle",
    "train": "train", "tram": "train", "railed": "train",
}
_TWO_WHEELERS = frozenset({"cyclist", "bicycle", "motorbike", "motorcycle", "moterbike"})
_PEDESTRIANS = frozenset({"pedestrian", "person_sitting"})
# how a C++ stream prints a non-finite float: glibc nan/inf, MSVC -nan(ind) and its older 1.#QNAN/1.#IND/1.#INF
_NON_FINITE = re.compile(r"[+-]?(?:nan(?:\([^)]*\))?|inf(?:inity)?|1\.#(?:qnan|snan|ind|inf)\d*)", re.IGNORECASE)


def model_key(model: str) -> str:
    """A vehicle model as the plugin writes it in bbox2d: lower case, letters only (cavalcade2 -> cavalcade)."""
    return "".join(c for c in model.lower() if "a" <= c <= "z")


def _read_suvs() -> frozenset[str]:
    from pairedgta.data import DEEPGTAV_SUVS

    rows = [line for line in DEEPGTAV_SUVS.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return frozenset(model_key(row.split(",")[0]) for row in rows[1:])


BBOX2D_SUVS = _read_suvs()  # pairedgta/data/deepgtav_suvs.csv, in the plugin's spelling


def _number(token: str) -> float | None:
    """A numeric field; None when the plugin printed a non-finite value (its 'unknown'); ValueError otherwise."""
    if _NON_FINITE.fullmatch(token):
        return None
    value = float(token)
    return value if math.isfinite(value) else None


def _occlusion_level(value: float | None) -> int:
    """KITTI's occlusion level (0 fully visible, 1 partly, 2 largely occluded, 3 unknown) of the plugin's hidden
    fraction (0..1; a negative or non-finite value is unknown); a KITTI level above 1 (2, 3) is kept as it is."""
    if value is None or value < 0:
        return 3
    if value == 0:
        return 0
    if value < 0.5:
        return 1
    return 2 if value <= 1 else min(int(value), 3)


def parse_bbox2d(text: str, *, where: str, box_size: tuple[int, int],
                 image_size: tuple[int, int] | None = None) -> list[dict[str, Any]]:
    """The Cityscapes-class boxes of one frame's bbox2d string: [{"class", "bbox": [x0, y0, x1, y1], "instance",
    "truncated", "occluded"}], bbox in pixels of the delivered image (`image_size`, default `box_size`: the boxes
    come in `dataset.frame` pixels and are scaled when the image differs), right/bottom one past the object's
    last column/row (as boxes from instance masks) and clipped to the image. `instance` is the plugin's entity
    id (augmented lines), else the line's 1-based number. A Cyclist/Motorbike line is the two-wheeler; a pedestrian
    whose v_ped_is_in is a two-wheeler of the same frame is a rider, one in any other vehicle is left out (Cityscapes
    labels the vehicle, not its occupants); a Truck line of an SUV is a car (BBOX2D_SUVS). Types that are no
    Cityscapes instance class, and objects without visible pixels, are left out. A non-finite number (the plugin
    prints NaN as nan or -nan(ind)) is ignored in a dropped line; in a kept one it is unknown: truncation then
    follows the image border, occlusion is level 3, and a box edge that is not finite leaves the object out.
    A line that is not a box line raises DataError naming `where` (the frame) and the line."""
    bw, bh = box_size
    iw, ih = image_size or box_size
    sx, sy = iw / bw, ih / bh
    # (line number, type, numbers, entity id, model, ped in)
    rows: list[tuple[int, str, list[float | None], int, str, int]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue

        def bad(why: str) -> DataError:
            shown = line if len(line) <= 100 else line[:97] + "..."
            return DataError(f"DeepGTAV {where}: bbox2d line {n} {shown!r} is not a 2D box line ({why}); expected "
                             "'type truncated occluded alpha left top right bottom ...' (DeepGTAV-PreSIL's "
                             "augmented KITTI labels): check the plugin build, or set renderer.boxes=false")

        if len(tokens) < len(BBOX2D_FIELDS):
            raise bad(f"{len(tokens)} fields, at least {len(BBOX2D_FIELDS)} needed")
        numbers = []
        for name, token in zip(BBOX2D_FIELDS[1:], tokens[1:len(BBOX2D_FIELDS)]):
            try:
                numbers.append(_number(token))
            except ValueError:
                raise bad(f"{name} {token!r} is not a number") from None
        entity, model, ped_in = n, "", 0
        if len(tokens) >= BBOX2D_AUGMENTED_FIELDS:
            for name, token in (("entity_id", tokens[_ENTITY]), ("v_ped_is_in", tokens[_PED_IN])):
                if not re.fullmatch(r"-?\d+", token):
                    raise bad(f"{name} {token!r} is not an integer")
            entity, model, ped_in = int(tokens[_ENTITY]), tokens[_MODEL], int(tokens[_PED_IN])
        rows.append((n, tokens[0].lower(), numbers, entity, model, ped_in))
    two_wheelers = {entity for _, kind, _, entity, _, _ in rows if kind in _TWO_WHEELERS}
    boxes: list[dict[str, Any]] = []
    for n, kind, (truncated, occluded, _alpha, left, top, right, bottom), entity, model, ped_in in rows:
        cls = BBOX2D_CLASSES.get(kind)
        if cls is None:  # not a Cityscapes instance: whatever its numbers are
            continue
        if left is None or top is None or right is None or bottom is None or right < left or bottom < top:
            continue  # not seen, or nowhere to put it
        if kind in _PEDESTRIANS and ped_in:
            if ped_in not in two_wheelers:
                continue
            cls = "rider"
        elif kind == "truck" and model_key(model) in BBOX2D_SUVS:
            cls = "car"
        x0, y0 = min(max(left * sx, 0.0), iw), min(max(top * sy, 0.0), ih)
        x1, y1 = min(max((right + 1) * sx, 0.0), iw), min(max((bottom + 1) * sy, 0.0), ih)
        if x1 <= x0 or y1 <= y0:
            continue
        edge = x0 <= 0 or y0 <= 0 or x1 >= iw or y1 >= ih
        boxes.append({"class": cls, "bbox": [x0, y0, x1, y1], "instance": entity,
                      "truncated": bool((truncated is not None and truncated > 0) or edge),
                      "occluded": _occlusion_level(occluded)})
    return boxes


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
    "stationaryScene", "collectTracking", "recordScenario", "positionScenario", "exportBBox2D",
    "exportBBox2DUnprocessed",
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
    "BBOX2D_CLASSES",
    "BBOX2D_SUVS",
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
    "parse_bbox2d",
    "parse_state",
    "model_key",
    "ped_model",
    "row_stride",
    "validate_message",
    "wire_float",
    "wire_int",
]
