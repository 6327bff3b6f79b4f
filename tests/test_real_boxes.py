"""Ground-truth boxes from real datasets' labels (pairedgta/detection/real_boxes.py): tiny Cityscapes and ACDC trees in
their documented layouts and file naming, boxes against hand-computed values, crowd and small ignores, the readers'
`instances` paths, and bad files as one-line DataErrors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pairedgta.datasets.acdc import open_acdc
from pairedgta.datasets.cityscapes import open_cityscapes
from pairedgta.detection.boxes import INSTANCE_CLASSES, Box, coco_ground_truth
from pairedgta.detection.real_boxes import (LABEL_ID_TO_INSTANCE, acdc_boxes, acdc_image_file_name, acdc_panoptic_json,
                                            cityscapes_boxes, read_acdc_boxes, read_cityscapes_boxes, read_real_boxes)
from pairedgta.errors import DataError

W, H = 64, 32
PERSON, RIDER, CAR, TRUCK, BUS, TRAIN, MOTORCYCLE, BICYCLE = range(8)


def test_label_ids_of_the_instance_classes():
    assert LABEL_ID_TO_INSTANCE == {24: PERSON, 25: RIDER, 26: CAR, 27: TRUCK, 28: BUS, 31: TRAIN, 32: MOTORCYCLE,
                                    33: BICYCLE}
    assert INSTANCE_CLASSES[CAR] == "car"


# ---------------------------------------------------------------- Cityscapes

def cityscapes_instance_ids() -> np.ndarray:
    ids = np.full((H, W), 7, dtype=np.uint16)  # road
    ids[:3] = 23  # sky
    ids[10:20, 5:20] = 26001  # car: 10 x 15 = 150 px, then partly hidden by the next car
    ids[15:25, 15:30] = 26002  # car in front: 10 x 15 = 150 px, hides 5 x 5 of the first
    ids[20:32, 60:64] = 24002  # person cut by the right and bottom borders: 12 x 4 = 48 px < 100
    ids[4:8, 30:36] = 24  # a group of persons, two separate regions: 4 x 6 = 24 px ...
    ids[25:29, 40:50] = 24  # ... and 4 x 10 = 40 px
    ids[0:4, 55:60] = 29001  # caravan: an instance id, but not a detection class
    ids[5:9, 50:54] = 20  # traffic sign: no instances
    ids[26:32, 2:4] = 33  # a bicycle group cut by the bottom border: 6 x 2 = 12 px
    return ids


CITYSCAPES_EXPECTED = [
    Box(24, PERSON, (30.0, 4.0, 36.0, 8.0), 24.0, "crowd", False),
    Box(24, PERSON, (40.0, 25.0, 50.0, 29.0), 40.0, "crowd", False),
    Box(33, BICYCLE, (2.0, 26.0, 4.0, 32.0), 12.0, "crowd", True),
    Box(24002, PERSON, (60.0, 20.0, 64.0, 32.0), 48.0, "small", True),
    Box(26001, CAR, (5.0, 10.0, 20.0, 20.0), 125.0, "", False),
    Box(26002, CAR, (15.0, 15.0, 30.0, 25.0), 150.0, "", False),
]


def test_cityscapes_boxes_by_hand():
    assert cityscapes_boxes(cityscapes_instance_ids()) == CITYSCAPES_EXPECTED


def test_cityscapes_min_area_and_diagonal_regions():
    boxes = cityscapes_boxes(cityscapes_instance_ids(), min_area=130)
    assert [(b.instance, b.ignore) for b in boxes if b.instance > 1000] == [(24002, "small"), (26001, "small"),
                                                                             (26002, "")]
    ids = np.zeros((H, W), dtype=np.uint16)
    ids[3, 3] = ids[4, 4] = 28  # diagonal neighbours: one group region (8-connectivity)
    ids[10, 10] = 28
    assert [b.xyxy for b in cityscapes_boxes(ids)] == [(3.0, 3.0, 5.0, 5.0), (10.0, 10.0, 11.0, 11.0)]
    assert cityscapes_boxes(np.zeros((H, W), dtype=np.uint16)) == []
    with pytest.raises(ValueError, match="H x W"):
        cityscapes_boxes(np.zeros((H, W, 3), dtype=np.uint16))


def write_cityscapes(root: Path) -> Path:
    """Two val frames in Cityscapes' layout; only the first has its instanceIds file. Returns that file."""
    gt_dir = root / "gtFine" / "val" / "frankfurt"
    img_dir = root / "leftImg8bit" / "val" / "frankfurt"
    gt_dir.mkdir(parents=True)
    img_dir.mkdir(parents=True)
    for frame in ("000294", "000576"):
        fid = f"frankfurt_000000_{frame}"
        Image.fromarray(np.zeros((H, W, 3), dtype=np.uint8)).save(img_dir / f"{fid}_leftImg8bit.png")
        Image.fromarray(np.zeros((H, W), dtype=np.uint8)).save(gt_dir / f"{fid}_gtFine_labelTrainIds.png")
    path = gt_dir / "frankfurt_000000_000294_gtFine_instanceIds.png"
    Image.fromarray(cityscapes_instance_ids()).save(path)
    return path


def test_cityscapes_reader_finds_instance_ids(tmp_path):
    path = write_cityscapes(tmp_path)
    assert Image.open(path).mode.startswith("I")  # a 16-bit PNG, as Cityscapes ships them
    split = open_cityscapes(root=tmp_path)
    assert [s.instances for s in split.samples] == [path, None]
    assert read_cityscapes_boxes(path) == CITYSCAPES_EXPECTED
    assert read_real_boxes(split.samples[0].instances) == CITYSCAPES_EXPECTED


def one_line_error(call, *needles: str) -> str:
    with pytest.raises(DataError) as info:
        call()
    text = str(info.value)
    assert "\n" not in text
    for needle in needles:
        assert needle in text
    return text


def test_cityscapes_bad_files(tmp_path):
    path = write_cityscapes(tmp_path)
    one_line_error(lambda: read_cityscapes_boxes(tmp_path / "nope_gtFine_instanceIds.png"), "not found",
                   "gtFine_trainvaltest.zip")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    one_line_error(lambda: read_cityscapes_boxes(path), str(path), "not a readable", "gtFine_trainvaltest.zip")
    Image.fromarray(np.zeros((H, W), dtype=np.uint8)).save(path)
    one_line_error(lambda: read_cityscapes_boxes(path), str(path), "a L image", "16-bit", "_gtFine_instanceIds.png")
    Image.fromarray(np.zeros((H, W, 3), dtype=np.uint8)).save(path)
    one_line_error(lambda: read_cityscapes_boxes(path), "a RGB image")
    one_line_error(lambda: read_real_boxes(tmp_path / "x_labelIds.png"), "neither")


# ---------------------------------------------------------------- ACDC

def id_to_rgb(ids: np.ndarray) -> np.ndarray:
    return np.stack([ids % 256, ids // 256 % 256, ids // 65536], axis=-1).astype(np.uint8)


def acdc_panoptic() -> tuple[np.ndarray, list[dict]]:
    ids = np.full((H, W), 1, dtype=np.int64)  # road, a stuff segment
    ids[5:15, 10:30] = 70001  # car: 200 px (id needs the blue channel: 70001 = 1 * 65536 + 17 * 256 + 113)
    ids[0:20, 40:45] = 300  # person: exactly 100 px, so not small; cut by the top border
    ids[25:28, 0:3] = 5  # bicycle: 9 px, small; cut by the left border
    ids[20:30, 50:60] = 24  # a crowd of persons: 100 px
    ids[28:30, 20:24] = 9  # traffic sign: not a detection class
    ids[0:3, 0:3] = 0  # unlabelled
    segments = [
        {"id": 1, "category_id": 7, "iscrowd": 0, "area": 0, "bbox": [0, 0, 0, 0]},
        {"id": 300, "category_id": 24, "iscrowd": 0, "area": 100, "bbox": [40, 0, 5, 20]},
        {"id": 70001, "category_id": 26, "iscrowd": 0, "area": 200, "bbox": [10, 5, 20, 10]},
        {"id": 5, "category_id": 33, "iscrowd": 0, "area": 9, "bbox": [0, 25, 3, 3]},
        {"id": 24, "category_id": 24, "iscrowd": 1, "area": 100, "bbox": [50, 20, 10, 10]},
        {"id": 9, "category_id": 20, "iscrowd": 0, "area": 8, "bbox": [20, 28, 4, 2]},
    ]
    return id_to_rgb(ids), segments


ACDC_EXPECTED = [
    Box(5, BICYCLE, (0.0, 25.0, 3.0, 28.0), 9.0, "small", True),
    Box(24, PERSON, (50.0, 20.0, 60.0, 30.0), 100.0, "crowd", False),
    Box(300, PERSON, (40.0, 0.0, 45.0, 20.0), 100.0, "", True),
    Box(70001, CAR, (10.0, 5.0, 30.0, 15.0), 200.0, "", False),
]


def test_acdc_boxes_by_hand():
    rgb, segments = acdc_panoptic()
    assert acdc_boxes(rgb, segments) == ACDC_EXPECTED
    assert [b.ignore for b in acdc_boxes(rgb, segments, min_area=101)] == ["small", "crowd", "small", ""]
    assert acdc_boxes(rgb, segments[:1]) == []
    with pytest.raises(ValueError, match="RGB"):
        acdc_boxes(rgb[..., 0], segments)
    coco = coco_ground_truth([(1, "x.png", W, H)], [ACDC_EXPECTED])
    assert [a["iscrowd"] for a in coco["annotations"]] == [1, 1, 0, 0]
    assert coco["annotations"][3]["bbox"] == [10.0, 5.0, 20.0, 10.0]


COND, SPLIT, SEQ = "fog", "val", "GOPR0475"


def acdc_names(n: str) -> tuple[str, str]:
    base = f"{COND}/{SPLIT}/{SEQ}/{SEQ}_frame_{n}"
    return f"{base}_rgb_anon.png", f"{base}_gt_panoptic.png"


def write_acdc(root: Path) -> tuple[Path, Path]:
    """Two fog val frames in ACDC's layout; only the first has its panoptic PNG, listed in the split's JSON with
    another frame. Returns (PNG, JSON)."""
    rgb, segments = acdc_panoptic()
    for n in ("000041", "000042"):
        image, _ = acdc_names(n)
        for path in (root / "rgb_anon" / image,
                     root / "rgb_anon" / COND / f"{SPLIT}_ref" / SEQ / f"{SEQ}_frame_{n}_rgb_ref_anon.png"):
            path.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.zeros((H, W, 3), dtype=np.uint8)).save(path)
    png = root / "gt_panoptic" / acdc_names("000041")[1]
    png.parent.mkdir(parents=True)
    Image.fromarray(rgb).save(png)
    other_image, other_png = acdc_names("000007")
    doc = {
        "images": [{"id": "other", "file_name": other_image, "width": W, "height": H},
                   {"id": "mine", "file_name": acdc_names("000041")[0], "width": W, "height": H}],
        "annotations": [{"image_id": "other", "file_name": other_png, "segments_info": []},
                        {"image_id": "mine", "file_name": acdc_names("000041")[1], "segments_info": segments}],
        "categories": [{"id": 24, "name": "person", "isthing": 1}, {"id": 26, "name": "car", "isthing": 1}],
    }
    js = root / "gt_panoptic" / COND / f"{COND}_{SPLIT}_gt_panoptic.json"
    js.write_text(json.dumps(doc))
    return png, js


def test_acdc_reader_finds_panoptic_labels(tmp_path):
    png, js = write_acdc(tmp_path)
    ds = open_acdc(root=tmp_path, condition=COND, splits=[SPLIT])
    assert [g.instances for g in ds.groups] == [{"ACDC-fog": png}, {}]  # the adverse frame's, never the reference's
    assert acdc_panoptic_json(png) == js
    assert acdc_image_file_name(png) == acdc_names("000041")[0]
    assert read_acdc_boxes(png, js, acdc_names("000041")[0]) == ACDC_EXPECTED
    assert read_acdc_boxes(png, js, Path(acdc_names("000041")[0]).name) == ACDC_EXPECTED  # by base name
    assert read_real_boxes(ds.groups[0].instances["ACDC-fog"]) == ACDC_EXPECTED


def test_acdc_bad_files(tmp_path):
    png, js = write_acdc(tmp_path)
    image = acdc_names("000041")[0]
    one_line_error(lambda: read_acdc_boxes(png, js.with_name("x.json"), image), "not found", "gt_panoptic_trainval")
    unlisted = png.with_name(f"{SEQ}_frame_000099_gt_panoptic.png")
    unlisted.write_bytes(png.read_bytes())
    one_line_error(lambda: read_acdc_boxes(unlisted, js, acdc_names("000099")[0]), str(js), "no panoptic annotation")
    # an image name the JSON does not list: its PNG's own annotation (by the PNG's name) is used
    assert read_acdc_boxes(png, js, "elsewhere/GOPR0475_frame_000041_rgb.png") == ACDC_EXPECTED
    one_line_error(lambda: read_acdc_boxes(png.with_name("x_gt_panoptic.png"), js, image), "not found")
    rgb, segments = acdc_panoptic()

    Image.fromarray(rgb[:16]).save(png)
    one_line_error(lambda: read_acdc_boxes(png, js, image), "64x16", "64x32")
    rgb[0:2, 60:62] = id_to_rgb(np.array(777))
    Image.fromarray(rgb).save(png)
    one_line_error(lambda: read_acdc_boxes(png, js, image), "[777] of the PNG are not in the JSON")
    Image.fromarray(id_to_rgb(np.ones((H, W), dtype=np.int64))).save(png)
    one_line_error(lambda: read_acdc_boxes(png, js, image), "of the JSON are not in the PNG")
    Image.fromarray(rgb[..., 0]).save(png)
    one_line_error(lambda: read_acdc_boxes(png, js, image), str(png), "a L image", "RGB")
    png.write_bytes(b"not a png")
    one_line_error(lambda: read_acdc_boxes(png, js, image), str(png), "not a readable")

    Image.fromarray(acdc_panoptic()[0]).save(png)
    doc = json.loads(js.read_text())
    doc["annotations"][1]["segments_info"][2].pop("category_id")
    js.write_text(json.dumps(doc))
    one_line_error(lambda: read_acdc_boxes(png, js, image), "segments_info", "malformed")
    js.write_text("{ truncated")
    one_line_error(lambda: read_acdc_boxes(png, js, image), str(js), "not a COCO panoptic JSON")
