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
from pairedgta.render.deepgtav_protocol import MessageError, parse_bbox2d, validate_message
from pairedgta.scene.descriptor import CameraPose, DynamicObject, Location, SceneDescriptor
from pairedgta.testing.deepgtav_server import DeepGTAVTestServer, SyntheticView, bbox2d_type

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
    ),
)
DAY = Condition("Day-Sunny", "Day", "EXTRASUNNY", clock_hour=12)
# the plugin's class of each object the stand-in draws (its type through parse_bbox2d's mapping)
CLASS_OF_TYPE = {"Car": "car", "Bus": "bus", "Truck": "truck", "Motorbike": "motorcycle", "Cyclist": "rider",
                 "Pedestrian": "person"}

# one frame's bbox2d as DeepGTAV-PreSIL writes it (23 fields: KITTI's 15, then entity_id points_2d points_3d
# speed roll pitch model v_ped_is_in), for a 1920x1080 frame
TAIL = "1.5 2 4.5 -2.5 2.1 13.5 -1.57"
BBOX2D = "".join(f"{line}\n" for line in [
    f"Car 0 0 -1.5 100 200 299 349 {TAIL} 4354 221 0 0 0 0 BLISTA 0",        # car [100, 200, 300, 350]
    f"Van 0.25 0.3 0 0 400 99 479 {TAIL} 4610 50 0 0 0 0 SPEEDO 0",           # car, truncated, partly occluded
    f"Truck 0 0.75 0 500 100 899 399 {TAIL} 4866 50 0 0 0 0 MULE 0",          # truck, largely occluded
    f"Bus 0 0 0 1500 300 1919 1079 {TAIL} 5122 50 0 0 0 0 BUS 0",             # bus, at the border: truncated
    f"Motorbike 0 0 0 1000 500 1039 579 {TAIL} 5378 50 0 0 0 0 BATI 0",       # motorcycle
    f"Moterbike 0 0 0 1050 500 1059 519 {TAIL} 5634 50 0 0 0 0 FAGGIO 0",     # the plugin's spelling: motorcycle
    f"Cyclist 0 0 0 1100 500 1129 589 {TAIL} 5890 50 0 0 0 0 BMX 0",          # rider (bicycle + its rider)
    f"Railed 0 0 0 0 0 99 99 {TAIL} 6146 50 0 0 0 0 FREIGHT 0",               # train
    f"Trailer 0 0 0 10 10 20 20 {TAIL} 6402 50 0 0 0 0 TRAILERS 0",           # no Cityscapes class: dropped
    f"Boat 0 0 0 10 10 20 20 {TAIL} 6658 50 0 0 0 0 DINGHY 0",                # dropped
    f"Car 0 1 0 1920 1080 0 0 {TAIL} 6914 0 0 0 0 0 ASEA 0",                  # nothing visible: not a box
    f"Pedestrian 0 0 0 1200 300 1219 379 {TAIL} 7170 80 0 0 0 0 587703123 0",  # person
    f"Person_sitting 0 -1 0 1300 300 1309 339 {TAIL} 7426 40 0 0 0 0 1 0",    # person, occlusion unknown (3)
    f"Pedestrian 0 0 0 1000 470 1039 560 {TAIL} 7682 90 0 0 0 0 2 5378",      # on the motorbike 5378: rider
    f"Pedestrian 0 0 0 110 210 130 240 {TAIL} 7938 10 0 0 0 0 3 4354",        # in the car 4354: dropped
    "DontCare -1 -1 -10 1500 600 1600 700 -1 -1 -1 -1000 -1000 -1000 -10",    # KITTI's own: dropped
])
EXPECTED = [  # (class, bbox, instance, truncated, occluded), checked by hand against the lines above
    ("car", [100.0, 200.0, 300.0, 350.0], 4354, False, 0),
    ("car", [0.0, 400.0, 100.0, 480.0], 4610, True, 1),
    ("truck", [500.0, 100.0, 900.0, 400.0], 4866, False, 2),
    ("bus", [1500.0, 300.0, 1920.0, 1080.0], 5122, True, 0),
    ("motorcycle", [1000.0, 500.0, 1040.0, 580.0], 5378, False, 0),
    ("motorcycle", [1050.0, 500.0, 1060.0, 520.0], 5634, False, 0),
    ("rider", [1100.0, 500.0, 1130.0, 590.0], 5890, False, 0),
    ("train", [0.0, 0.0, 100.0, 100.0], 6146, True, 0),
    ("person", [1200.0, 300.0, 1220.0, 380.0], 7170, False, 0),
    ("person", [1300.0, 300.0, 1310.0, 340.0], 7426, False, 3),
    ("rider", [1000.0, 470.0, 1040.0, 561.0], 7682, False, 0),
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
    assert half[3]["bbox"] == [750.0, 150.0, 960.0, 540.0]
    # KITTI's 15 fields (no entity id): the line's number is the instance; blank lines are no lines
    kitti = ("\nCar 0.00 0 -1.58 10 20 29 39 1.5 1.6 3.7 -3 1.7 20 -1.6\n"
             "\nPedestrian 0 0 0 40 10 49 39 1.8 0.6 0.5 1 2 8 0\n")
    assert as_tuples(parse_bbox2d(kitti, where="frame 1", box_size=(64, 48))) == [
        ("car", [10.0, 20.0, 30.0, 40.0], 2, False, 0), ("person", [40.0, 10.0, 50.0, 40.0], 4, False, 0)]
    assert parse_bbox2d("", where="frame 1", box_size=(64, 48)) == []


@pytest.mark.parametrize("line,why", [
    ("Car 0 0 -1.5 100 200 299", "7 fields, at least 8 needed"),
    ("Car 0 0 -1.5 100 top 299 349", "top 'top' is not a number"),
    ("Car 0 0 -1.5 100 200 nan 349", "right 'nan' is not finite"),
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
    by_handle = {e.handle: e for e in state.entities}
    assert len(by_handle) == len(DESCRIPTOR.objects) and set(expected) == set(by_handle)  # every object is seen
    got = {b["instance"]: b for b in result.boxes}
    assert set(got) == set(by_handle)
    for handle, b in got.items():
        assert b["bbox"] == expected[handle]
        assert b["class"] == CLASS_OF_TYPE[bbox2d_type(by_handle[handle])]
    classes = sorted(b["class"] for b in result.boxes)
    assert classes == ["bus", "car", "car", "person", "rider"]  # the bmx is the plugin's Cyclist: a rider
    # the far asea is partly hidden behind the blista, the others are not
    asea = next(e.handle for e in state.entities if e.model == "asea")
    assert got[asea]["occluded"] >= 1 and [b["occluded"] for h, b in got.items() if h != asea] == [0] * 4


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
    assert len(lines.splitlines()) == 3 and [e["class"] for e in expected] == ["bus", "bus"]  # the mule is hidden
    handles = {e.handle for e in state.entities}
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
