"""Ground-truth 2D boxes over the DeepGTAV protocol: the bbox2d lines of DeepGTAV-PreSIL parsed into Cityscapes
instance classes, the request that asks for them, the stand-in server's boxes of the objects it draws, and the
generate stage's `<condition>_boxes.json` read back by the detection reader."""
from __future__ import annotations

import json
import logging
import time

import numpy as np
import pytest

from pairedgta.conditions import Condition
from pairedgta.detection.boxes import INSTANCE_CLASSES, read_box_file
from pairedgta.detection.ground_truth import read_ground_truth
from pairedgta.errors import DataError
from pairedgta.render.base import RenderResult
from pairedgta.render.deepgtav import DeepGTAVRenderer
from pairedgta.errors import ConfigError
from pairedgta.render.deepgtav_protocol import BBOX2D_SUVS, MessageError, parse_bbox2d, parse_state, validate_message
from pairedgta.scene.descriptor import CameraPose, DynamicObject, Location, SceneDescriptor
from pairedgta.testing.deepgtav_server import (
    DeepGTAVTestServer,
    GameState,
    Plugin,
    SyntheticView,
    bbox2d_type,
    encode_state,
)

DESCRIPTOR = SceneDescriptor(
    scene_id="s0002",
    seed=3,
    location=Location(x=215.5, y=-810.25, z=30.0, heading=30.0),
    camera=CameraPose(x=0.0, y=0.5, z=1.6, rot_x=-2.0, rot_y=0.0, rot_z=0.0),
    objects=(
        DynamicObject("car", "blista", forward=14.0, right=-2.5, heading=0.0),
        DynamicObject("bus", "bus", forward=30.0, right=3.0, heading=0.0),
        DynamicObject("bicycle", "bmx", forward=12.0, right=1.5, heading=0.0),
        DynamicObject("person", "a_m_y_hipster_01", forward=9.0, right=-0.5, heading=90.0),
        DynamicObject("car", "asea", forward=40.0, right=-2.0, heading=0.0),  # behind the blista: partly hidden
        DynamicObject("car", "granger", forward=20.0, right=4.5, heading=0.0),  # an SUV the plugin types Truck
    ),
)
DAY = Condition("Day-Sunny", "Day", "EXTRASUNNY", clock_hour=12)
# the Cityscapes class of each plugin type the stand-in sends (None: not a Cityscapes instance); a Pedestrian on a
# two-wheeler is a rider, a Truck of an SUV model a car
CLASS_OF_TYPE = {"Car": "car", "Bus": "bus", "Truck": "truck", "Motorbike": "motorcycle", "Cyclist": "bicycle",
                 "Pedestrian": "person", "Animal": None, "Trailer": None, "Boat": None}

# One frame's bbox2d as DeepGTAV-PreSIL writes it, for a 1920x1080 dataset.frame: the 23 fields of
# ObjectDetection::exportEntity (ObjectDet/ObjectDetection.cpp in David0tt/DeepGTAV, the augmented branch that
# exportDetectionsString asks for): objType truncation occlusion alpha (int)left (int)top (int)right (int)bottom
# height width length x y z rotation_y, then entityID pointsHit2D pointsHit3D speed roll pitch modelString
# vPedIsIn (0 unless isPedInV). modelString is a vehicle's display name lower-cased with its non-letters removed
# (ObjectDetection::setVehiclesList: cavalcade2 -> cavcade) and a ped's model hash in decimal (setPedsList);
# types come from the plugin's vehicle table (DeepGTAVvehicle_labels.csv: Truck for granger and cavalcade too),
# its fallbacks ("Moterbike", "Railed", "Boat") and setPedsList ("Pedestrian", "Animal"). Truncation is
# 1 - areaInside / areaTotal (BBox2DFrom3DObject), which an MSVC build prints as -nan(ind) when it is NaN.
TAIL = "1.5 2 4.5 -2.5 2.1 13.5 -1.57"
BBOX2D = "".join(f"{line}\n" for line in [
    f"Car 0 0 -1.5 100 200 299 349 {TAIL} 4354 221 0 0 0 0 blista 0",          # car [100, 200, 300, 350]
    f"Van 0.25 0.3 0 0 400 99 479 {TAIL} 4610 50 0 0 0 0 speedo 0",             # car, truncated, partly occluded
    f"Truck 0 0.75 0 500 100 899 399 {TAIL} 4866 50 0 0 0 0 mule 0",            # truck, largely occluded
    f"Truck 0 0 0 700 600 799 699 {TAIL} 8194 50 0 0 0 0 granger 0",            # an SUV: car
    f"Truck 0 0 0 800 600 849 649 {TAIL} 8450 50 0 0 0 0 cavcade 0",            # cavalcade2, as spelt: car
    f"Bus 0 0 0 1500 300 1919 1079 {TAIL} 5122 50 0 0 0 0 bus 0",               # bus, at the border: truncated
    f"Motorbike 0 0 0 1000 500 1039 579 {TAIL} 5378 50 0 0 0 0 bati 0",         # motorcycle (without its rider)
    f"Moterbike 0 0 0 1050 500 1059 519 {TAIL} 5634 50 0 0 0 0 faggio 0",       # the plugin's spelling: motorcycle
    f"Cyclist 0 0 0 1100 500 1129 589 {TAIL} 5890 50 0 0 0 0 bmx 0",            # the bicycle alone: bicycle
    f"Railed 0 0 0 0 0 99 99 {TAIL} 6146 50 0 0 0 0 freight 0",                 # train
    f"Trailer -nan(ind) 0 0 10 10 20 20 {TAIL} 6402 50 0 0 0 0 trailers 0",     # no Cityscapes class: dropped
    f"Boat inf 0 nan 10 10 20 20 {TAIL} 6658 50 0 0 0 0 dinghy 0",              # dropped, its non-finite fields too
    f"Car 0 1 0 1920 1080 0 0 {TAIL} 6914 0 0 0 0 0 asea 0",                    # nothing visible: not a box
    f"Pedestrian 0 0 0 1200 300 1219 379 {TAIL} 7170 80 0 0 0 0 587703123 0",   # person
    f"Person_sitting 0 -1 0 1300 300 1309 339 {TAIL} 7426 40 0 0 0 0 1 0",      # person, occlusion unknown (3)
    f"Pedestrian 0 0 0 1000 470 1039 560 {TAIL} 7682 90 0 0 0 0 2 5378",        # on the motorbike 5378: rider
    f"Pedestrian 0 0 0 1105 440 1124 560 {TAIL} 8706 90 0 0 0 0 4 5890",        # on the bicycle 5890: rider
    f"Pedestrian 0 0 0 110 210 130 240 {TAIL} 7938 10 0 0 0 0 3 4354",          # in the car 4354: dropped
    f"Pedestrian -nan(ind) nan 0 1400 300 1409 339 {TAIL} 8962 40 0 0 0 0 5 0",  # unknown truncation, occlusion
    f"Animal -nan(ind) 0 0 600 700 639 729 {TAIL} 9218 40 0 0 0 0 1318032802 0",  # a dog: dropped
    "DontCare -1 -1 -10 1500 600 1600 700 -1 -1 -1 -1000 -1000 -1000 -10",      # KITTI's own: dropped
])
EXPECTED = [  # (class, bbox, instance, truncated, occluded), checked by hand against the lines above
    ("car", [100.0, 200.0, 300.0, 350.0], 4354, False, 0),
    ("car", [0.0, 400.0, 100.0, 480.0], 4610, True, 1),
    ("truck", [500.0, 100.0, 900.0, 400.0], 4866, False, 2),
    ("car", [700.0, 600.0, 800.0, 700.0], 8194, False, 0),
    ("car", [800.0, 600.0, 850.0, 650.0], 8450, False, 0),
    ("bus", [1500.0, 300.0, 1920.0, 1080.0], 5122, True, 0),
    ("motorcycle", [1000.0, 500.0, 1040.0, 580.0], 5378, False, 0),
    ("motorcycle", [1050.0, 500.0, 1060.0, 520.0], 5634, False, 0),
    ("bicycle", [1100.0, 500.0, 1130.0, 590.0], 5890, False, 0),
    ("train", [0.0, 0.0, 100.0, 100.0], 6146, True, 0),
    ("person", [1200.0, 300.0, 1220.0, 380.0], 7170, False, 0),
    ("person", [1300.0, 300.0, 1310.0, 340.0], 7426, False, 3),
    ("rider", [1000.0, 470.0, 1040.0, 561.0], 7682, False, 0),
    ("rider", [1105.0, 440.0, 1125.0, 561.0], 8706, False, 0),
    ("person", [1400.0, 300.0, 1410.0, 340.0], 8962, False, 3),
]


def as_tuples(boxes):
    assert all(set(b) == {"class", "bbox", "instance", "truncated", "occluded"} for b in boxes)
    return [(b["class"], b["bbox"], b["instance"], b["truncated"], b["occluded"]) for b in boxes]


def test_parse_bbox2d_maps_types_to_cityscapes_classes():
    boxes = parse_bbox2d(BBOX2D, where="frame 7", box_size=(1920, 1080))
    assert as_tuples(boxes) == EXPECTED
    assert {b["class"] for b in boxes} <= set(INSTANCE_CLASSES)


def test_parse_bbox2d_scales_to_the_delivered_frame_and_numbers_plain_kitti_lines():
    half = parse_bbox2d(BBOX2D, where="frame 7", box_size=(1920, 1080), image_size=(960, 540))
    assert as_tuples(half)[0] == ("car", [50.0, 100.0, 150.0, 175.0], 4354, False, 0)
    assert half[5]["bbox"] == [750.0, 150.0, 960.0, 540.0]
    # KITTI's 15 fields (no entity id): the line's number is the instance; blank lines are no lines
    kitti = ("\nCar 0.00 0 -1.58 10 20 29 39 1.5 1.6 3.7 -3 1.7 20 -1.6\n"
             "\nPedestrian 0 0 0 40 10 49 39 1.8 0.6 0.5 1 2 8 0\n")
    assert as_tuples(parse_bbox2d(kitti, where="frame 1", box_size=(64, 48))) == [
        ("car", [10.0, 20.0, 30.0, 40.0], 2, False, 0), ("person", [40.0, 10.0, 50.0, 40.0], 4, False, 0)]
    assert parse_bbox2d("", where="frame 1", box_size=(64, 48)) == []


@pytest.mark.parametrize("line,why", [
    ("Car 0 0 -1.5 100 200 299", "7 fields, at least 8 needed"),
    ("Car 0 0 -1.5 100 top 299 349", "top 'top' is not a number"),
    ("Car 0 0 -1.5 100 200 nan(x 349", "right 'nan(x' is not a number"),
    (f"Car 0 0 -1.5 100 200 299 349 {TAIL} id4354 221 0 0 0 0 BLISTA 0", "entity_id 'id4354' is not an integer"),
])
def test_a_malformed_line_is_one_line_naming_the_frame_and_the_line(line, why):
    text = f"Car 0 0 -1.5 1 2 3 4 {TAIL} 1 1 0 0 0 0 X 0\n{line}\n"
    with pytest.raises(DataError) as err:
        parse_bbox2d(text, where="frame 12 (scene 00003, condition Night-RAIN)", box_size=(1920, 1080))
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("DeepGTAV frame 12 (scene 00003, condition Night-RAIN): bbox2d line 2 ")
    assert repr(line) in msg and why in msg and "renderer.boxes=false" in msg


def test_non_finite_fields_are_unknown_never_a_stopped_frame():
    # every spelling a C++ stream may print for NaN and infinity, in a kept and in a dropped line
    for nan in ("nan", "-nan", "-nan(ind)", "nan(snan)", "inf", "-inf", "1.#QNAN", "-1.#IND", "1.#INF"):
        text = (f"Boat {nan} {nan} {nan} 1 1 5 5 {TAIL} 1 1 0 0 0 0 dinghy 0\n"
                f"Car {nan} {nan} {nan} 1 1 5 5 {TAIL} 2 1 0 0 0 0 blista 0\n")
        assert as_tuples(parse_bbox2d(text, where="f", box_size=(64, 48))) == [
            ("car", [1.0, 1.0, 6.0, 6.0], 2, False, 3)], nan
    # unknown truncation: the image border alone says it; a box edge that is not finite: nowhere to put it
    text = (f"Car -nan(ind) 0 0 0 10 9 19 {TAIL} 3 1 0 0 0 0 blista 0\n"
            f"Car 0 0 0 nan 10 9 19 {TAIL} 4 1 0 0 0 0 blista 0\n")
    assert as_tuples(parse_bbox2d(text, where="f", box_size=(64, 48))) == [
        ("car", [0.0, 10.0, 10.0, 20.0], 3, True, 0)]


def test_riders_and_suvs_follow_the_plugin_lines():
    # a rider needs its two-wheeler's line in the same frame (wherever its box is); other occupants are dropped
    bike = f"Cyclist 0 0 0 1920 1080 0 0 {TAIL} 5890 0 0 0 0 0 tribike 0"  # the bicycle unseen: no box
    rider = f"Pedestrian 0 0 0 10 10 19 39 {TAIL} 8706 90 0 0 0 0 4 5890"
    bus = f"Bus 0 0 0 40 10 59 39 {TAIL} 5122 50 0 0 0 0 bus 0"
    passenger = f"Pedestrian 0 0 0 45 12 49 20 {TAIL} 8962 9 0 0 0 0 5 5122"
    classes = lambda *lines: [b["class"] for b in parse_bbox2d("\n".join(lines), where="f", box_size=(64, 48))]
    assert classes(bike, rider, bus, passenger) == ["rider", "bus"]
    assert classes(rider) == []  # its vehicle is not in the frame: not a person walking either
    # SUVs by the plugin's spelling of their names; a Car line of the same name and other trucks stay as they are
    assert {"granger", "cavalcade", "cavcade", "dubsta", "fbi"} <= BBOX2D_SUVS
    truck = lambda model, kind="Truck": f"{kind} 0 0 0 1 1 5 5 {TAIL} 1 1 0 0 0 0 {model} 0"
    assert classes(truck("granger"), truck("dubsta"), truck("FBI2"), truck("mule"), truck("dubsta", "Car"),
                   truck("sandking")) == ["car", "car", "car", "truck", "car", "truck"]


def test_the_plugin_state_json_with_its_null_placeholder_and_second_bbox2d():
    lines = f"Car 0 0 -1.5 100 200 299 349 {TAIL} 4354 221 0 0 0 0 blista 0\n"
    raw = encode_state({"index": 3, "bbox2d": None, "CameraAngle": None}, lines)
    assert raw.count(b'"bbox2d"') == 2 and raw.index(b'"bbox2d": null') < raw.rindex(b'"bbox2d": "Car')
    assert parse_state(raw) == {"index": 3, "bbox2d": lines, "CameraAngle": None}
    assert parse_state(encode_state({"index": 3, "bbox2d": None}, None)) == {"index": 3, "bbox2d": None}
    # the stand-in's message before recording, and after: the same shape
    plugin = Plugin()
    plugin.handle(b'{"start": {"scenario": null, "dataset": {"exportBBox2D": true}}}')
    assert parse_state(encode_state(plugin.message(), None))["bbox2d"] is None


def test_frame_other_than_the_screen_is_scaled_or_refused():
    r = DeepGTAVRenderer(width=2560, height=1440, frame=[1920, 1080])
    dataset = r.session_message(DESCRIPTOR)["start"]["dataset"]
    assert dataset["frame"] == [1920, 1080] and dataset["screenResolution"] == [2560, 1440]
    image = np.zeros((1440, 2560, 3), np.uint8)
    line = f"Car 0 0 0 300 150 599 449 {TAIL} 4354 221 0 0 0 0 blista 0\n"
    assert r.frame_boxes(RenderResult(image, state={"bbox2d": line}), "f")[0]["bbox"] == [400.0, 200.0, 800.0, 600.0]
    assert DeepGTAVRenderer(width=64, height=36).frame == (64, 36)  # null: the screen
    for kw, why in [
        (dict(width=2560, height=1440), r"renderer\.frame=\[2560, 1440\] \(the plugin's dataset\.frame\) is too large"
                                        r".*set renderer\.frame=\[1920, 1080\].*or renderer\.boxes=false"),
        (dict(width=1280, height=720, frame=[1024, 768]), r"dataset\.frame\) has another aspect ratio"),
        (dict(frame=[1920]), r"renderer\.frame=\[1920\] is invalid; use null .* dataset\.frame"),
    ]:
        with pytest.raises(ConfigError, match=why) as err:
            DeepGTAVRenderer(**kw)
        assert "\n" not in str(err.value)
    assert DeepGTAVRenderer(width=2560, height=1440, boxes=False).frame == (2560, 1440)  # no boxes: any size
    # the stand-in, as the plugin, sends no boxes for a frame above 1920x1080
    plugin = Plugin()
    plugin.handle(b'{"start": {"scenario": null, "dataset": {"exportBBox2D": true, "frame": [2560, 1440]}}}')
    plugin.handle(b'{"StartRecording": null}')
    assert plugin.state.picture_size() == (2560, 1440) and not plugin.state.sends_boxes()
    plugin.handle(b'{"config": {"scenario": null, "dataset": {"frame": [1920, 1080], '
                  b'"screenResolution": [2560, 1440]}}}')
    assert plugin.state.picture_size() == (2560, 1440) and plugin.state.sends_boxes()


def test_stand_in_boxes_come_in_frame_pixels_of_a_larger_frame():
    s = GameState(width=192, height=108, screen=(96, 54), camera=(0.0, 0.5, 1.6, -2.0, 0.0, 0.0))
    view = SyntheticView()
    assert view.render(s).shape == (54, 96, 3)
    owner = view.instance_map(s)
    expected = tight_boxes(owner)
    boxes = parse_bbox2d(view.bbox2d(s), where="s", box_size=(192, 108), image_size=(96, 54))
    assert boxes and all(b["bbox"] == expected[b["instance"]] for b in boxes)


def test_the_session_asks_for_the_boxes():
    r = DeepGTAVRenderer(width=64, height=36)
    dataset = r.session_message(DESCRIPTOR)["start"]["dataset"]
    assert dataset["exportBBox2D"] is True
    validate_message(r.session_message(DESCRIPTOR, "config"))
    assert DeepGTAVRenderer(width=64, height=36, boxes=False).session_message(DESCRIPTOR)["start"]["dataset"][
        "exportBBox2D"] is False
    bad = {"start": {"scenario": None, "dataset": {"exportBBox2D": "yes"}}}
    with pytest.raises(MessageError, match=r"start\.dataset\.exportBBox2D='yes' must be true, false or null"):
        validate_message(bad)


def renderer(srv: DeepGTAVTestServer, **kw) -> DeepGTAVRenderer:
    return DeepGTAVRenderer(width=96, height=54, port=srv.port, transport=srv.transport, timeout_s=0.5, retries=1,
                            backoff_s=0.01, settle_s=0.0, settle_frames=0, rate=200.0, **kw)


def tight_boxes(owner: np.ndarray) -> dict[int, list[float]]:
    """handle -> the tight box of its pixels, right/bottom exclusive"""
    out = {}
    for handle in np.unique(owner[owner > 0]):
        rows, cols = np.nonzero(owner == handle)
        out[int(handle)] = [float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1)]
    return out


@pytest.mark.parametrize("transport", ["zmq", "tcp"])
def test_renderer_boxes_are_the_server_objects_visible_pixels(transport):
    with DeepGTAVTestServer(transport) as srv:
        with renderer(srv) as r:
            result = r.render(DESCRIPTOR, DAY)
        state = srv.snapshot()
        received = srv.received
    assert state.export_bbox2d and "StartRecording" in received
    assert isinstance(result.state["bbox2d"], str)
    owner = SyntheticView().instance_map(state)
    expected = tight_boxes(owner)
    spawned = {e.handle: e for e in state.entities}
    by_handle = {**spawned, **{e.handle: e for e in state.ambient()}}
    assert len(spawned) == len(DESCRIPTOR.objects) and set(spawned) <= set(expected)  # every object is seen
    boat = next(e for e in state.ambient() if bbox2d_type(e) == "Boat")
    assert set(expected) == set(by_handle) - {boat.handle}  # the boat is behind the camera
    assert "Boat -nan(ind) " in SyntheticView().bbox2d(state)  # the plugin's unguarded truncation
    got = {b["instance"]: b for b in result.boxes}
    # every Cityscapes instance the picture shows, and only those
    assert set(got) == {h for h in expected if CLASS_OF_TYPE[bbox2d_type(by_handle[h])]}
    for handle, b in got.items():
        e = by_handle[handle]
        assert b["bbox"] == expected[handle]
        cls = "rider" if e.ped_in else "car" if e.model == "granger" else CLASS_OF_TYPE[bbox2d_type(e)]
        assert b["class"] == cls, e.model
    assert sorted(b["class"] for h, b in got.items() if h in spawned) == [
        "bicycle", "bus", "car", "car", "car", "person"]  # the bmx is the plugin's Cyclist, the granger a Truck
    # the ambient traffic: a bicycle and a motorcycle, each with its rider (v_ped_is_in), and no dog or trailer
    assert sorted(b["class"] for h, b in got.items() if h not in spawned) == [
        "bicycle", "motorcycle", "rider", "rider"]
    # the far asea is partly hidden behind the blista, the other spawned objects are not
    asea = next(e.handle for e in state.entities if e.model == "asea")
    assert got[asea]["occluded"] >= 1 and [b["occluded"] for h, b in got.items() if h in spawned and h != asea] == [
        0] * 5


def test_boxes_off_and_a_plugin_without_boxes():
    with DeepGTAVTestServer("zmq") as srv:
        with renderer(srv, boxes=False) as r:
            result = r.render(DESCRIPTOR, DAY)
        assert result.boxes is None and "bbox2d" not in result.state
        assert "StartRecording" not in srv.received and not srv.snapshot().export_bbox2d


def test_a_frame_without_bbox2d_gives_no_boxes_said_once(caplog):
    r = DeepGTAVRenderer(width=4, height=2)
    image = np.zeros((2, 4, 3), np.uint8)
    with caplog.at_level(logging.WARNING, logger="pairedgta.render.deepgtav"):
        assert r.frame_boxes(RenderResult(image, state={"index": 1}), "frame 1") is None  # classic plugin
        assert r.frame_boxes(RenderResult(image, state={"index": 2}), "frame 2") is None
    assert sum("bbox2d" in rec.getMessage() for rec in caplog.records) == 1
    assert r.frame_boxes(RenderResult(image, state={"bbox2d": "Car 0 0 0 0 0 1 0 1 1 1 1 1 1 0\n"}), "f") == [
        {"class": "car", "bbox": [0.0, 0.0, 2.0, 1.0], "instance": 1, "truncated": True, "occluded": 0}]
    # the plugin's placeholder while it does not record: the capture waits for a frame with the boxes
    assert "not the boxes" in r._condition_objection(DAY, {"bbox2d": []})
    assert DeepGTAVRenderer(width=4, height=2, boxes=False)._condition_objection(DAY, {"bbox2d": []}) is None


@pytest.mark.slow  # end to end: the CLI
def test_generate_writes_box_files_that_the_detection_reader_reads(tmp_path):
    from omegaconf import OmegaConf

    from pairedgta.conditions import build_condition_grid
    from pairedgta.configs import CONFIG_DIR
    from pairedgta.datasets.generated import boxes_file, open_generated
    from pairedgta.testing.cli import run_cli

    cache = tmp_path / "cache"
    with DeepGTAVTestServer("zmq") as srv:
        args = ["renderer=deepgtav", "region=los_santos", "stages=[generate]", "generate.num_scenes=1",
                "generate.objects.min=3",  # scene 0: a coach, a bus and a mule hidden behind the coach
                f"cache_dir={cache}", "tracking.enabled=false", "renderer.width=96", "renderer.height=54",
                "renderer.settle_s=0.0", "renderer.settle_frames=0", "renderer.timeout_s=5", "renderer.rate=100",
                f"renderer.port={srv.port}", "renderer.transport=zmq"]
        t0 = time.perf_counter()
        proc = run_cli(args, tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        state = srv.snapshot()
    root = next(p for p in (cache / "generate").iterdir() if not p.name.startswith("."))
    index = json.loads((root / "index.json").read_text())
    scene = root / "scenes" / "00000"
    assert not list(scene.glob("*_instances.png"))  # GTA V gives no instance ids: the boxes stand for them
    # the server's objects as its picture shows them, through the plugin's string and the client's parser
    lines = SyntheticView().bbox2d(state)
    expected = parse_bbox2d(lines, where="server", box_size=(96, 54))
    handles = {e.handle for e in [*state.entities, *state.ambient()]}
    spawned = [e for e in expected if e["instance"] in {e.handle for e in state.entities}]
    assert len(lines.splitlines()) == 10 and [e["class"] for e in spawned] == ["bus", "bus"]  # the mule is hidden
    assert sorted(e["class"] for e in expected if e not in spawned) == ["bicycle", "motorcycle", "rider", "rider"]
    for cond in index["conditions"]:
        path = boxes_file(scene, cond)
        raw = json.loads(path.read_text())
        assert raw == {"boxes": expected}  # the same objects in every condition: the frames are paired
        boxes = read_box_file(path, min_area=0)
        assert [(INSTANCE_CLASSES[b.label], list(b.xyxy), b.instance, b.truncated) for b in boxes] == [
            (e["class"], e["bbox"], e["instance"], e["truncated"]) for e in expected]
        assert {b.instance for b in boxes} <= handles
    # the dataset reader offers the box file where the instance map would be
    grid = build_condition_grid(OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "conditions" / "paper.yaml")))
    assert grid.names == index["conditions"]
    dataset = open_generated(root=root, grid=grid)
    group = dataset.groups[0]
    assert all(group.instances[c] == boxes_file(scene, c) for c in index["conditions"])
    assert len(read_ground_truth(group.instances[index["reference"]], None)) == len(expected)
    assert time.perf_counter() - t0 < 60
