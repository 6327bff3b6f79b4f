"""GTA V backend: a client of the DeepGTAV plugin. Its wire protocol is
pairedgta/render/deepgtav_protocol.py, the sockets and reconnects pairedgta/render/deepgtav_transport.py;
pairedgta/testing/deepgtav_server.py reproduces the plugin for tests without the game.

Semantic scene construction (`prepare`): start or reconfigure a stationary session at the ego
pose, TeleportToLocation, SetCameraPositionAndRotation, then CreateVehicle/CreatePed for every
descriptor object (positions relative to the ego vehicle). Condition-wise rendering (`render`):
SetClockTime and SetWeather, wait `settle_s` while discarding the frames the plugin streams, skip
`settle_frames` more, and capture the first frame whose JSON shows the condition applied.

Every message is checked against the field types the plugin reads before anything is sent; a step
that fails in a way a fresh connection may cure is retried on one, which replays the session and
the scene (the connection forgets both when its socket is replaced).

Frames arrive as 8-bit BGR rows padded to 4 bytes; `render` returns RGB HxWx3 and the plugin's
JSON document as `RenderResult.state` (ego location, clock, spawned entities when reported), for
`pairedgta.scene.validation.validate_group` to check against the descriptor.

Ground-truth boxes (`boxes`, default true): the session asks for `dataset.exportBBox2D` and sends
StartRecording (DeepGTAV-PreSIL fills `bbox2d` only while recording; close() sends StopRecording), and
`render` turns the frame's `bbox2d` string into `RenderResult.boxes` (deepgtav_protocol.parse_bbox2d:
Cityscapes instance classes, xyxy pixels of the frame). The plugin captures the screen (`screenResolution`,
renderer.width x renderer.height) but measures the boxes in `dataset.frame` pixels (renderer.frame, the screen by
default), so they are scaled to the picture; above 1920x1080 it sends none, which is refused at construction.
A plugin that sends no `bbox2d` at all (the classic one) gives `boxes=None`, said once.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from pairedgta.conditions import Condition
from pairedgta.errors import ConfigError
from pairedgta.render.base import Renderer, RenderResult
from pairedgta.render.deepgtav_protocol import (
    WEATHERS,
    decode_frame,
    paint_index,
    parse_bbox2d,
    ped_model,
    validate_message,
    wire_float,
    wire_int,
)
from pairedgta.render.deepgtav_transport import TRANSPORTS, Connection, Transient
from pairedgta.scene.descriptor import DynamicObject, SceneDescriptor
from pairedgta.scene.validation import PED_CATEGORIES, VEHICLE_CATEGORIES, entity_mismatches

log = logging.getLogger(__name__)
BOXES_MAX_FRAME = (1920, 1080)  # above it DeepGTAV-PreSIL's buffers do not match dataset.frame: no bbox2d


def _any_state(state: Mapping[str, Any]) -> str | None:
    return None  # renderer.check_state=false: the first frame is taken


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
        boxes: bool = True,
        frame: Sequence[int] | None = None,
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
        need("boxes", isinstance(boxes, bool), "use true (ask the plugin for its 2D boxes) or false")
        fr = list(frame) if isinstance(frame, (list, tuple)) else None
        fr_ok = fr is not None and len(fr) == 2 and all(isint(v) and 1 <= v <= 16384 for v in fr)
        need("frame", frame is None or fr_ok,
             "use null (the screen: renderer.width x renderer.height) or [width, height] of the plugin's dataset.frame")
        fw, fh = (fr[0], fr[1]) if fr is not None else (width, height)
        # the plugin's boxes come in dataset.frame pixels (its depth and stencil buffers), the picture in the screen's
        if boxes and (fw > BOXES_MAX_FRAME[0] or fh > BOXES_MAX_FRAME[1]):
            raise ConfigError(
                f"renderer.frame={[fw, fh]} (the plugin's dataset.frame) is too large for boxes: above "
                f"{BOXES_MAX_FRAME[0]}x{BOXES_MAX_FRAME[1]} DeepGTAV-PreSIL's depth and stencil buffers do not "
                f"match it and no bbox2d arrives; set renderer.frame=[{BOXES_MAX_FRAME[0]}, {BOXES_MAX_FRAME[1]}] "
                "(the boxes are scaled to the screen) or renderer.boxes=false")
        if abs(fw / fh - width / height) > 0.01 * width / height:
            raise ConfigError(
                f"renderer.frame={[fw, fh]} (the plugin's dataset.frame) has another aspect ratio than the screen "
                f"renderer.width x renderer.height = {width}x{height}, so the boxes would be stretched; set "
                "renderer.frame to the screen's shape (e.g. null) or the screen to the game's resolution")
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
        self.boxes = boxes
        self.frame = (fw, fh)  # dataset.frame: the boxes' pixels; the picture is the screen's, width x height
        self._said_no_boxes = False
        self._session = False  # a session was started on the current connection
        self._scene: SceneDescriptor | None = None  # scene built on the current connection
        self.last_state: dict[str, Any] = {}
        self.link = Connection(self.host, self.port, transport, self.timeout_s, self.retries, self.backoff_s,
                               self.width, self.height, on_fresh=self._forget_connection)

    @property
    def overhead_s(self) -> float:
        """Since the last prepare(): seconds spent connecting, in failed attempts and in backoff (already
        part of the prepare/render wall time)."""
        return self.link.overhead_s

    @property
    def retries_used(self) -> int:
        """Since the last prepare(): how many times a step was retried on a fresh connection."""
        return self.link.retries_used

    def _forget_connection(self) -> None:
        self._session = False
        self._scene = None

    # ------------------------------------------------------------------ Renderer API
    def open(self) -> None:
        self.link.run("connecting", lambda: None)

    def close(self) -> None:
        if self.link.connected:
            linger = 0.0
            if self._session:
                try:
                    if self.boxes:  # recording outlives the session in the plugin (and slows every frame)
                        self.link.send({"StopRecording": None})
                    self.link.send({"stop": None})  # back to normal gameplay
                    linger = min(self.timeout_s, 1.0)
                except Transient:
                    pass
            self.link.drop(linger)

    def prepare(self, descriptor: SceneDescriptor) -> None:
        """Semantic scene construction: session at the ego pose, teleport, camera, objects."""
        self.scene_messages(descriptor)  # validate everything before anything is sent
        self.link.overhead_s, self.link.retries_used = 0.0, 0
        self.link.run("scene construction", lambda: self._construct(descriptor))

    def render(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        """Condition-wise rendering: clock + weather, settle, capture (builds the scene first when
        `descriptor` is not the one built on the current connection)."""
        self.scene_messages(descriptor)
        self.condition_messages(condition)
        result = self.link.run(f"rendering of condition '{condition.name}'",
                               lambda: self._capture(descriptor, condition))
        result.boxes = self.frame_boxes(result, f"frame {result.state.get('index', '?')} (scene "
                                                f"{descriptor.scene_id}, condition {condition.name})")
        return result

    def frame_boxes(self, result: RenderResult, where: str) -> list[dict[str, Any]] | None:
        """The frame's boxes from its `bbox2d` string, in pixels of `result.image`; None when not asked for or
        when the plugin sends none (said once). A malformed line: DataError naming `where` and the line."""
        if not self.boxes:
            return None
        raw = result.state.get("bbox2d")
        if not isinstance(raw, str):
            if not self._said_no_boxes:
                self._said_no_boxes = True
                log.warning("DeepGTAV: the plugin sent %s for bbox2d (the classic plugin has no 2D boxes; "
                            "DeepGTAV-PreSIL sends them with dataset.exportBBox2D while recording); the frames get "
                            "no <condition>_boxes.json", "no field" if "bbox2d" not in result.state else repr(raw))
            return None
        h, w = result.image.shape[:2]
        return parse_bbox2d(raw, where=where, box_size=self.frame, image_size=(w, h))

    # ------------------------------------------------------------------ messages
    def session_message(self, descriptor: SceneDescriptor, key: str = "start") -> dict[str, Any]:
        loc = descriptor.location
        scenario = {
            "location": [wire_float(loc.x), wire_float(loc.y), wire_float(loc.z), wire_float(loc.heading)],
            "time": [self.construction_time[0], self.construction_time[1]],
            "weather": self.construction_weather,
            "vehicle": self.ego_vehicle,
            "drivingMode": None,  # default: no AI driving
            "spawnedEntitiesDespawnSeconds": self.despawn_s,
        }
        dataset = {
            "rate": self.rate,
            "frame": list(self.frame),  # the boxes' pixels (the plugin's buffers)
            "screenResolution": [self.width, self.height],  # the picture's: the plugin captures the screen
            "vehicles": True,
            "peds": True,
            "trafficSigns": None,
            "speed": None,
            "location": True,
            "time": True,
            "offscreen": None,
            "stationaryScene": True,
            "exportBBox2D": self.boxes,  # the objects' 2D boxes in each frame's JSON ("bbox2d")
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
            {"TeleportToLocation": {"x": wire_float(loc.x), "y": wire_float(loc.y), "z": wire_float(loc.z)}},
            {"SetCameraPositionAndRotation": {
                "x": wire_float(cam.x), "y": wire_float(cam.y), "z": wire_float(cam.z),
                "rot_x": wire_float(cam.rot_x), "rot_y": wire_float(cam.rot_y), "rot_z": wire_float(cam.rot_z),
            }},
        ]
        msgs += self.object_messages(descriptor)
        for m in msgs:
            validate_message(m)
        return msgs

    def object_messages(self, descriptor: SceneDescriptor) -> list[dict[str, Any]]:
        return [self._object_message(descriptor, o) for o in descriptor.objects]

    def _object_message(self, descriptor: SceneDescriptor, obj: DynamicObject) -> dict[str, Any]:
        heading = wire_float(obj.heading)
        if self.object_heading == "relative" and isinstance(heading, float):
            heading = (descriptor.location.heading + heading) % 360.0  # the plugin takes world headings
        if obj.category in VEHICLE_CATEGORIES:
            return {"CreateVehicle": {
                "model": obj.model, "relativeForward": wire_float(obj.forward), "relativeRight": wire_float(obj.right),
                "heading": heading, "color": paint_index(obj.color), "color2": paint_index(obj.secondary_color),
                "placeOnGround": self.place_on_ground, "withLifeJacketPed": False,
            }}
        assert obj.category in PED_CATEGORIES, obj.category
        return {"CreatePed": {
            "model": ped_model(obj.model) if isinstance(obj.model, str) else obj.model,
            "relativeForward": wire_float(obj.forward), "relativeRight": wire_float(obj.right),
            "relativeUp": wire_float(obj.up),
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
            {"SetClockTime": {"hour": wire_int(condition.clock_hour), "minute": wire_int(condition.clock_minute),
                              "second": 0}},
            {"SetWeather": {"weather": condition.weather}},
        ]
        for m in msgs:
            validate_message(m)
        return msgs

    # ------------------------------------------------------------------ phases
    def _construct(self, descriptor: SceneDescriptor) -> None:
        msgs = self.scene_messages(descriptor)
        if not self._session:
            self.link.send({"stop": None})  # a session left over by another client ignores `start`
            self.link.send(self.session_message(descriptor, "start"))
            if self.boxes:  # the plugin fills bbox2d only while recording
                self.link.send({"StartRecording": None})
            self._session = True
        else:
            self.link.send(self.session_message(descriptor, "config"))
        n_objects = len(descriptor.objects)
        setup, spawns = msgs[: len(msgs) - n_objects], msgs[len(msgs) - n_objects :]
        for m in setup:
            self.link.send(m)
        self.link.discard_pending()
        _, state = self._await(lambda s: self._ego_objection(descriptor, s), "the ego vehicle at the scene location")
        if spawns and not (self.check_state and self._entities_reported(state)
                           and not entity_mismatches(descriptor, state, ego_tol_m=self.ego_tolerance_m)):
            for m in spawns:
                self.link.send(m)
            self._await(lambda s: self._entity_objection(descriptor, s), "the descriptor's objects")
        self._scene = descriptor

    def _capture(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        if self._scene != descriptor:
            self._construct(descriptor)
        for m in self.condition_messages(condition):
            self.link.send(m)
        self.link.discard_until(time.monotonic() + self.settle_s)
        for _ in range(self.settle_frames):
            self.link.next_frame()
        frame, state = self._await(lambda s: self._condition_objection(condition, s), f"condition '{condition.name}'")
        self.last_state = state
        return RenderResult(image=decode_frame(frame, self.width, self.height),
                            state={**state, "gta_mapping": self.gta_mapping(condition)})

    def _await(self, accept: Callable[[dict[str, Any]], str | None], what: str) -> tuple[bytes, dict[str, Any]]:
        """First frame whose state `accept` approves (any frame when renderer.check_state is false)."""
        return self.link.await_state(accept if self.check_state else _any_state, what)

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
        if self.boxes and "bbox2d" in state and not isinstance(state["bbox2d"], str):
            return (f"its bbox2d is {state['bbox2d']!r}, not the boxes (the plugin exports them only while recording, "
                    f"and only when its depth and stencil buffers match dataset.frame = renderer.frame "
                    f"{self.frame[0]}x{self.frame[1]}: run the game at that resolution; renderer.boxes=false renders "
                    "without them)")
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


__all__ = ["DeepGTAVRenderer"]
