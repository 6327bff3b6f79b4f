"""DeepGTAV client against the protocol test server over loopback, on both transports."""
from __future__ import annotations

import json
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from pairedgta.conditions import Condition
from pairedgta.configs import CONFIG_DIR
from pairedgta.errors import ConfigError, RendererError
from pairedgta.render import build_renderer
from pairedgta.render.deepgtav import DeepGTAVRenderer
from pairedgta.render.deepgtav_protocol import (
    FrameSizeError,
    MessageError,
    decode_frame,
    encode_message,
    frame_nbytes,
    ped_model,
    row_stride,
    validate_message,
)
from pairedgta.testing.deepgtav_server import DeepGTAVTestServer, SyntheticView, encode_bgr_padded
from pairedgta.scene.descriptor import CameraPose, DynamicObject, Location, SceneDescriptor
from pairedgta.scene.validation import joaat, object_world_xy, validate_group

ROOT = Path(__file__).resolve().parents[1]
TRANSPORTS = ["zmq", "tcp"]

DESCRIPTOR = SceneDescriptor(
    scene_id="s0001",
    seed=7,
    location=Location(x=215.5, y=-810.25, z=30.0, heading=30.0),
    camera=CameraPose(x=0.0, y=0.5, z=1.6, rot_x=-2.0, rot_y=0.0, rot_z=0.0),
    objects=(
        DynamicObject("car", "blista", forward=14.0, right=-2.5, heading=0.0, color=(200, 20, 30)),
        DynamicObject("motorcycle", "bati", forward=22.0, right=1.5, heading=10.0),
        DynamicObject("person", "a_m_y_hipster_01", forward=9.0, right=5.0, heading=90.0),
    ),
)
CONDITIONS = [
    Condition("Day-Sunny", "Day", "EXTRASUNNY", clock_hour=12),
    Condition("Sunset-Foggy", "Sunset", "FOGGY", clock_hour=19, clock_minute=30, visibility_m=300.0),
    Condition("Night-Rain", "Night", "RAIN", clock_hour=23, rain_mm_h=30.0),
]


@pytest.fixture(params=TRANSPORTS)
def transport(request) -> str:
    return request.param  # pyzmq is a dependency: both transports always run


@pytest.fixture
def server(transport):
    with DeepGTAVTestServer(transport) as srv:
        yield srv


def make_renderer(srv: DeepGTAVTestServer, **overrides) -> DeepGTAVRenderer:
    kwargs = {
        "width": 64, "height": 36, "port": srv.port, "transport": srv.transport, "timeout_s": 0.3, "retries": 2,
        "backoff_s": 0.01, "settle_s": 0.01, "settle_frames": 1, "rate": 200.0,
    }
    kwargs.update(overrides)
    return DeepGTAVRenderer(**kwargs)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------- full scene


def test_full_scene_three_conditions(server):
    with make_renderer(server) as r:
        r.prepare(DESCRIPTOR)
        results = {c.name: r.render(DESCRIPTOR, c) for c in CONDITIONS}
        again = r.render(DESCRIPTOR, CONDITIONS[0])

    for c in CONDITIONS:
        res = results[c.name]
        assert res.image.shape == (36, 64, 3) and res.image.dtype == np.uint8
        assert res.labels is None and res.instances is None
        assert res.state["weather"] == c.weather
        assert res.state["time"][:2] == [c.clock_hour, c.clock_minute]
        assert len(res.state["vehicles"]) == 2 and len(res.state["peds"]) == 1
    means = [float(results[c.name].image.mean()) for c in CONDITIONS]
    assert means[0] > means[1] > means[2]  # day brighter than sunset fog brighter than night rain
    np.testing.assert_array_equal(again.image, results["Day-Sunny"].image)  # repeat = identical

    group = validate_group(
        {k: v.image for k, v in results.items()}, "Day-Sunny", DESCRIPTOR, {k: v.state for k, v in results.items()}
    )
    assert group.ok, group.reasons
    assert all(s > 0.9 for s in group.structure.values())

    # the server holds what the scene construction asked for
    state = server.snapshot()
    assert (state.x, state.y, state.z, state.heading) == (215.5, -810.25, 30.0, 30.0)
    assert state.camera == (0.0, 0.5, 1.6, -2.0, 0.0, 0.0)
    assert (state.width, state.height, state.rate, state.stationary) == (64, 36, 200.0, True)
    by_model = {e.model: e for e in state.entities}
    assert set(by_model) == {"blista", "bati", ped_model("a_m_y_hipster_01")}
    for obj in DESCRIPTOR.objects:
        e = by_model[obj.model if obj.category != "person" else ped_model(obj.model)]
        ex, ey = object_world_xy(DESCRIPTOR, obj)
        assert (e.x, e.y) == pytest.approx((ex, ey), abs=1e-6)
        assert e.heading == pytest.approx((DESCRIPTOR.location.heading + obj.heading) % 360)
    assert by_model["blista"].color == (27, 4)  # red and grey descriptor colours -> paint indices
    assert server.dropped == []
    assert wait_for(lambda: len(server.received) == 18)
    received = server.received
    assert received[:8] == [  # StartRecording: the plugin exports the 2D boxes only while recording
        "stop", "start", "StartRecording", "TeleportToLocation", "SetCameraPositionAndRotation", "CreateVehicle",
        "CreateVehicle", "CreatePed",
    ]
    assert received[8:-2] == ["SetClockTime", "SetWeather"] * 4
    assert received[-2:] == ["StopRecording", "stop"]  # close() ends the recording and the session


def test_physical_parameters_are_mapped_to_gta_and_collapsed_steps_are_named(server, caplog):
    """GTA V has weathers and a clock only: each condition says what it asks GTA for and which physical
    parameters it cannot honour; two fog steps asking for the same FOGGY noon are a warning."""
    fog = [Condition(f"Day-FOG-{v}m", "Day", "FOGGY", clock_hour=12, visibility_m=float(v)) for v in (300, 150)]
    with caplog.at_level("INFO", logger="pairedgta.render.deepgtav"), make_renderer(server) as r:
        r.prepare(DESCRIPTOR)
        first, second = (r.render(DESCRIPTOR, c) for c in fog)
    assert first.state["gta_mapping"] == {"gta_weather": "FOGGY", "gta_clock": "12:00",
                                          "not_rendered": {"visibility_m": 300.0, "sun_elevation_deg": 55.0}}
    info = [m for m in caplog.messages if "is rendered as GTA weather" in m]
    assert len(info) == 2 and "visibility_m=300" in info[0]
    warned = [r for r in caplog.records if r.levelname == "WARNING" and "same weather and clock" in r.getMessage()]
    assert len(warned) == 1 and "Day-FOG-150m" in warned[0].getMessage() and "Day-FOG-300m" in warned[0].getMessage()


def test_render_builds_scene_and_switches_with_config(server):
    other = SceneDescriptor(
        "s0002", 8, Location(-900.0, 300.0, 40.0, 270.0),
        objects=(DynamicObject("bus", "bus", forward=18.0, right=0.0),),
    )
    with make_renderer(server) as r:
        first = r.render(DESCRIPTOR, CONDITIONS[0])  # no prepare: render builds the scene
        second = r.render(other, CONDITIONS[0])
    assert server.received.count("start") == 1 and server.received.count("config") == 1
    # entities of the first scene are far away and not reported next to the second ego
    assert [v["model"] for v in second.state["vehicles"]] == ["bus"] and second.state["peds"] == []
    assert validate_group({"a": second.image}, "a", other, {"a": second.state}).ok
    assert not np.array_equal(first.image, second.image)


def test_build_renderer_from_conf():
    cfg = yaml.safe_load((CONFIG_DIR / "renderer" / "deepgtav.yaml").read_text())
    r = build_renderer(cfg)
    assert isinstance(r, DeepGTAVRenderer)
    assert (r.width, r.height, r.transport, r.settle_s) == (1280, 720, "zmq", 1.0)
    with pytest.raises(ConfigError, match=r"renderer: unknown key\(s\) timeout; known keys: .*timeout_s"):
        build_renderer({**cfg, "timeout": 5})
    with pytest.raises(ConfigError, match=r"renderer\.transport"):
        build_renderer({**cfg, "transport": "udp"})
    with pytest.raises(ConfigError, match=r"renderer\.timeout_s.*frame interval"):
        build_renderer({**cfg, "rate": 2.0, "timeout_s": 0.3})


# --------------------------------------------------------------------------- frames


def test_decode_frame_removes_row_padding_and_swaps_channels():
    width, height = 33, 5
    assert row_stride(width) == 100 and frame_nbytes(width, height) == 500
    rgb = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    rows = np.full((height, 100), 0xEE, dtype=np.uint8)  # padding bytes hold junk
    rows[:, :99] = rgb[..., ::-1].reshape(height, 99)
    np.testing.assert_array_equal(decode_frame(rows.tobytes(), width, height), rgb)
    np.testing.assert_array_equal(decode_frame(encode_bgr_padded(rgb), width, height), rgb)
    with pytest.raises(FrameSizeError, match="expected 500"):
        decode_frame(rgb[..., ::-1].tobytes(), width, height)  # unpadded rows
    assert issubclass(FrameSizeError, RendererError)


@pytest.mark.parametrize("width", [33, 34, 35, 36])
def test_odd_widths_over_the_wire(server, width):
    with make_renderer(server, width=width, height=7) as r:
        res = r.render(DESCRIPTOR, CONDITIONS[0])
    assert res.image.shape == (7, width, 3)
    expected = SyntheticView().render(server.snapshot())  # the picture the server encoded
    np.testing.assert_array_equal(res.image, expected)


def test_wrong_frame_size_is_an_immediate_error(transport):
    with DeepGTAVTestServer(transport, fault="wrong_size") as srv:
        r = make_renderer(srv, width=33, height=9)
        with pytest.raises(FrameSizeError, match=r"expected 900 for 33x9"):
            r.prepare(DESCRIPTOR)
        r.close()
        assert srv.sessions == 1  # a size mismatch is not retried


# --------------------------------------------------------------------------- message validation


@pytest.mark.parametrize(
    "message, match",
    [
        ({"SetClockTime": {"hour": 12.0, "minute": 0, "second": 0}}, r"SetClockTime\.hour=12\.0 .*JSON integer"),
        ({"SetClockTime": {"hour": 24, "minute": 0, "second": 0}}, r"0\.\.23"),
        ({"SetClockTime": {"hour": True, "minute": 0, "second": 0}}, r"SetClockTime\.hour"),
        ({"SetWeather": {"weather": "SUNNY"}}, r"SetWeather\.weather='SUNNY'.*EXTRASUNNY"),
        ({"TeleportToLocation": {"x": "1.0", "y": 2.0, "z": 0.0}}, r"TeleportToLocation\.x='1\.0'.*number"),
        ({"TeleportToLocation": {"x": 1.0, "y": 2.0}}, r"lacks field 'z'"),
        ({"TeleportToLocation": {"x": float("nan"), "y": 2.0, "z": 0.0}}, r"finite"),
        ({"CreateVehicle": {"model": "blista", "relativeForward": 5.0, "relativeRight": 0.0, "heading": 0.0,
                            "color": 0, "color2": 0, "placeOnGround": 1, "withLifeJacketPed": False}},
         r"CreateVehicle\.placeOnGround=1 .*true or false"),
        ({"CreatePed": {"model": "a_m_y_hipster_01", "relativeForward": 5.0, "relativeRight": 0.0, "relativeUp": 0.0,
                        "heading": 0.0, "placeOnGround": True, "animDict": "", "animName": "", "task": 0}},
         r"hex model hash"),
        ({"SetWeather": {"weather": "RAIN"}, "SetClockTime": {"hour": 1, "minute": 0, "second": 0}}, r"exactly one key"),
        ({"ClearArea": {}}, r"unknown to the plugin"),
        ({"stop": {}}, r"stop=\{\} must be null"),
        ({"start": {"scenario": {"location": [1.0, 2.0]}, "dataset": None}}, r"scenario lacks"),
    ],
)
def test_validate_message_rejects(message, match):
    with pytest.raises(MessageError, match=match):
        validate_message(message)


def test_validate_message_accepts_built_messages():
    r = DeepGTAVRenderer(width=33, height=9)
    for m in [r.session_message(DESCRIPTOR), r.session_message(DESCRIPTOR, "config"), *r.scene_messages(DESCRIPTOR),
              *r.condition_messages(CONDITIONS[1]), {"stop": None},
              {"commands": {"throttle": 0.5, "brake": 0, "steering": -1}}]:
        validate_message(m)
        assert json.loads(encode_message(m)) == m
    assert ped_model("a_m_y_hipster_01") == f"0x{joaat('a_m_y_hipster_01'):08x}" == "0x2307a353"
    assert ped_model("0x0B4A6862") == "0x0b4a6862"


def test_bad_descriptor_or_condition_raises_before_sending(server):
    bad_scene = SceneDescriptor("bad", 1, Location(float("nan"), 0.0))
    bad_object = SceneDescriptor("bad2", 1, Location(0.0, 0.0), objects=(DynamicObject("car", "", 5.0, 0.0),))
    r = make_renderer(server)
    with pytest.raises(MessageError, match=r"start\.scenario\.location\[0\]=nan"):
        r.prepare(bad_scene)
    with pytest.raises(MessageError, match=r"CreateVehicle\.model=''"):
        r.prepare(bad_object)
    with pytest.raises(MessageError, match=r"SetWeather\.weather='Sunny'"):
        r.render(DESCRIPTOR, Condition("Day-Sunny", "Day", "Sunny"))
    # nothing reached the server: a valid scene sent afterwards on the same renderer is the first
    # thing the server sees (messages arrive in order, so earlier ones would come before it)
    r.prepare(DESCRIPTOR)
    assert wait_for(lambda: "CreatePed" in server.received)
    assert server.received[:8] == [
        "stop", "start", "StartRecording", "TeleportToLocation", "SetCameraPositionAndRotation", "CreateVehicle",
        "CreateVehicle", "CreatePed",
    ]
    assert server.dropped == []
    r.close()


class RawClient:
    """Sends raw bytes the way a client would, to watch how the server treats them."""

    def __init__(self, srv: DeepGTAVTestServer) -> None:
        self.transport = srv.transport
        if srv.transport == "zmq":
            import zmq

            self.sock = zmq.Context.instance().socket(zmq.PAIR)
            self.sock.setsockopt(zmq.LINGER, 0)
            self.sock.connect(f"tcp://127.0.0.1:{srv.port}")
        else:
            self.sock = socket.create_connection(("127.0.0.1", srv.port), timeout=1.0)

    def send(self, text: str) -> None:
        data = text.encode()
        if self.transport == "zmq":
            self.sock.send(data)
        else:
            self.sock.sendall(struct.pack("<I", len(data)) + data)

    def close(self) -> None:
        self.sock.close()


def wait_for(predicate, timeout=2.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def test_server_drops_wrongly_typed_messages_like_the_plugin(server):
    raw = RawClient(server)
    try:
        raw.send('{"SetClockTime": {"hour": 7.0, "minute": 0, "second": 0}}')  # GetInt on a double
        raw.send('{"CreateVehicle": {"model": "blista", "relativeForward": "5", "relativeRight": 0, "heading": 0,'
                 ' "color": 0, "color2": 0, "placeOnGround": true, "withLifeJacketPed": false}}')
        raw.send('{"SetWeather": {}}')  # missing field
        raw.send("not json at all")
        raw.send('{"SetClockTime": {"hour": 7, "minute": 5, "second": 0}}')  # fine
        raw.send('{"TeleportToLocation": {"x": 1, "y": 2, "z": 3}}')  # ints are fine for GetFloat
        assert wait_for(lambda: len(server.received) == 2)
    finally:
        raw.close()
    reasons = [why for _, why in server.dropped]
    assert len(reasons) == 4
    assert "GetInt" in reasons[0] and "GetFloat" in reasons[1] and "missing field" in reasons[2]
    assert reasons[3] == "not valid JSON"
    state = server.snapshot()
    assert (state.hour, state.minute) == (7, 5) and state.entities == []
    assert (state.x, state.y, state.z) == (1.0, 2.0, 3.0)


def test_server_can_hang_up_on_a_bad_message_like_a_crashing_plugin():
    with DeepGTAVTestServer("tcp", on_bad_message="close") as srv:
        raw = RawClient(srv)
        try:
            raw.send('{"SetClockTime": {"hour": "7", "minute": 0, "second": 0}}')
            assert raw.sock.recv(16) == b""  # connection closed by the server
        finally:
            raw.close()
        assert len(srv.dropped) == 1
        with make_renderer(srv) as r:  # the next client is served normally
            assert r.render(DESCRIPTOR, CONDITIONS[0]).state["weather"] == "EXTRASUNNY"


# --------------------------------------------------------------------------- faults and retries


def test_silent_server_times_out_retries_and_fails_with_one_clear_line(transport):
    with DeepGTAVTestServer(transport, fault="silent") as srv:
        r = make_renderer(srv, timeout_s=0.2, retries=2)
        with pytest.raises(RendererError) as info:
            r.prepare(DESCRIPTOR)
        assert r.retries_used == 2  # gave up after exactly retries + 1 attempts, no more
        r.close()
        # each attempt starts a session on a fresh connection (a PAIR server may still be holding
        # the previous peer when the last one arrives, hence >= 2)
        assert srv.sessions >= 2
    msg = str(info.value)
    assert "\n" not in msg
    assert f"127.0.0.1:{srv.port}" in msg and "timed out" in msg
    assert "renderer.timeout_s (now 0.2)" in msg and "renderer.retries (now 2)" in msg
    assert "3 attempts" in msg


def test_transient_silence_is_cured_by_a_retry(transport):
    with DeepGTAVTestServer(transport, fault="silent", fault_sessions=1) as srv:
        with make_renderer(srv, timeout_s=0.2, retries=2) as r:
            r.prepare(DESCRIPTOR)
            assert r.retries_used == 1 and r.overhead_s > 0  # the failed attempt is booked as overhead
            res = r.render(DESCRIPTOR, CONDITIONS[2])
        assert srv.sessions == 2
    assert res.state["weather"] == "RAIN" and res.image.shape == (36, 64, 3)
    # the replayed scene did not spawn the objects twice
    assert len(res.state["vehicles"]) == 2 and len(res.state["peds"]) == 1


def test_server_closing_mid_frame(transport):
    with DeepGTAVTestServer(transport, fault="close_mid_frame") as srv:
        r = make_renderer(srv, timeout_s=0.2, retries=1)
        with pytest.raises(RendererError, match=r"mid-frame.*2 attempts"):
            r.prepare(DESCRIPTOR)
        r.close()


def test_garbage_replies(transport):
    with DeepGTAVTestServer(transport, fault="garbage") as srv:
        r = make_renderer(srv, timeout_s=0.2, retries=1)
        with pytest.raises(RendererError, match=r"not valid JSON.*renderer\.retries"):
            r.render(DESCRIPTOR, CONDITIONS[0])
        r.close()


def test_garbage_length_prefix_on_tcp():
    """A classic-transport server that sends junk instead of a length prefix."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)
    listener.settimeout(2.0)
    port = listener.getsockname()[1]
    import threading

    def serve():
        for _ in range(2):
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conn.sendall(b"\xff\xff\xff\x7f" + b"\x00" * 64)
            time.sleep(0.05)
            conn.close()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    r = DeepGTAVRenderer(width=32, height=8, port=port, transport="tcp", timeout_s=0.2, retries=1,
                         backoff_s=0.01, rate=100.0)
    with pytest.raises(RendererError, match=r"implausible frame length prefix"):
        r.prepare(DESCRIPTOR)
    r.close()
    listener.close()
    t.join(2.0)


def test_nobody_listening_tcp():
    r = DeepGTAVRenderer(width=32, height=8, port=free_port(), transport="tcp", timeout_s=0.2, retries=1,
                         backoff_s=0.01, rate=100.0)
    with pytest.raises(RendererError, match=r"cannot connect.*2 attempts.*renderer\.timeout_s") as info:
        r.open()
    assert "\n" not in str(info.value)
    assert r.retries_used == 1
