"""The shipped label-space tables (pairedgta/data/labels/*.tsv), checked by hand against their public sources.

Class lists: Mapillary Vistas v1.2 config.json, ADE20K objectInfo150 (transformers id2label short names), COCO panoptic
categories (detectron2 COCO_CATEGORIES order). Mappings: MSeg's MSeg_master.tsv. The expected rows below were read off
those sources; a change to a table that moves one of them, or changes which Cityscapes classes a table can reach,
fails here."""
from __future__ import annotations

from pathlib import Path

import pytest

import pairedgta
from pairedgta.cityscapes import CLASS_NAMES

LABELS = Path(pairedgta.__file__).parent / "data" / "labels"
HEADER = "index\tsource_class\tcityscapes_class\tfollows"
MSEG = "MSeg master table"
TABLES = {"mapillary_vistas_v1.2": 66, "ade20k": 150, "coco_panoptic": 133}


def read(name: str) -> tuple[list[str], list[tuple[int, str, str, str]]]:
    """(comment lines, rows) of a table; fails on anything that is not the documented format."""
    text = (LABELS / f"{name}.tsv").read_text(encoding="utf-8")
    assert text.endswith("\n")
    lines = text.split("\n")[:-1]
    comments = []
    while lines and lines[0].startswith("#"):
        comments.append(lines.pop(0))
    assert lines and lines[0] == HEADER, f"{name}: the header must follow the comments"
    rows = []
    for line in lines[1:]:
        assert not line.startswith("#"), f"{name}: comments only at the top"
        fields = line.split("\t")
        assert len(fields) == 4, f"{name}: {line!r} is not 4 tab-separated fields"
        index, source, target, follows = fields
        assert index.isdigit(), line
        assert source == source.strip() and follows == follows.strip() and target == target.strip(), line
        rows.append((int(index), source, target, follows))
    return comments, rows


def targets(name: str) -> dict[str, str]:
    return {source: target for _, source, target, _ in read(name)[1]}


def reached(name: str) -> set[str]:
    return {target for _, _, target, _ in read(name)[1]} - {"-"}


@pytest.mark.parametrize("name,count", TABLES.items())
def test_table_format(name, count):
    comments, rows = read(name)
    assert len(rows) == count
    assert [r[0] for r in rows] == list(range(count))
    sources = [r[1] for r in rows]
    assert all(sources) and len(set(sources)) == count, "source class names must be non-empty and unique"
    assert all(r[2] in CLASS_NAMES or r[2] == "-" for r in rows)
    assert all(r[3] for r in rows), "every row says which source its mapping follows"
    # a row that maps to a Cityscapes class follows MSeg or says why not; a row that maps to nothing does not cite MSeg
    assert all(r[3] != MSEG for r in rows if r[2] == "-")
    # the comments say what the table is and where the classes and the mapping come from
    head = "\n".join(comments)
    assert len(comments) >= 3 and "MSeg_master.tsv" in head and "Cityscapes" in head


def test_no_row_departs_from_mseg():
    # every mapped row follows MSeg's master table; a judgement row added later must be listed here
    judged = {name: [(r[1], r[2], r[3]) for r in read(name)[1] if r[2] != "-" and r[3] != MSEG] for name in TABLES}
    assert judged == {name: [] for name in TABLES}


def test_mapillary_vistas_rows():
    _, rows = read("mapillary_vistas_v1.2")
    assert rows[0][:3] == (0, "Bird", "-")
    assert rows[13][:3] == (13, "Road", "road")
    assert rows[19][:3] == (19, "Person", "person")
    assert rows[65][:3] == (65, "Unlabeled", "-")
    assert rows[64][1] == "Ego Vehicle"
    t = targets("mapillary_vistas_v1.2")
    expected = {
        "Curb": "sidewalk", "Sidewalk": "sidewalk", "Pedestrian Area": "sidewalk", "Curb Cut": "sidewalk",
        "Service Lane": "road", "Bike Lane": "road", "Parking": "road", "Pothole": "road",
        "Crosswalk - Plain": "road", "Lane Marking - General": "road", "Lane Marking - Crosswalk": "road",
        "Bicyclist": "rider", "Motorcyclist": "rider", "Other Rider": "rider",
        "Traffic Sign (Front)": "traffic sign", "Traffic Sign (Back)": "traffic sign",
        "Traffic Sign Frame": "traffic sign", "Traffic Light": "traffic light",
        "Pole": "pole", "Utility Pole": "pole", "Street Light": "-",
        "Building": "building", "Phone Booth": "building", "Wall": "wall", "Fence": "fence", "Guard Rail": "-",
        "Vegetation": "vegetation", "Terrain": "terrain", "Sand": "terrain", "Sky": "sky",
        "Car": "car", "Caravan": "car", "Truck": "truck", "Bus": "bus", "On Rails": "train",
        "Motorcycle": "motorcycle", "Bicycle": "bicycle", "Trailer": "-", "Other Vehicle": "-",
        "Rail Track": "-", "Manhole": "-", "Catch Basin": "-", "Car Mount": "-", "Ego Vehicle": "-",
    }
    assert {k: t[k] for k in expected} == expected


def test_ade20k_rows():
    _, rows = read("ade20k")
    assert [r[1] for r in rows[:8]] == ["wall", "building", "sky", "floor", "tree", "ceiling", "road", "bed"]
    assert rows[0][2] == "wall" and rows[2][2] == "sky"
    assert rows[20][1:3] == ("car", "car")
    assert rows[149][1:3] == ("flag", "-")
    t = targets("ade20k")
    expected = {
        "road": "road", "sidewalk": "sidewalk", "path": "sidewalk", "building": "building", "house": "building",
        "skyscraper": "building", "tree": "vegetation", "palm": "vegetation", "plant": "-", "grass": "terrain",
        "earth": "terrain", "car": "car", "van": "car", "truck": "truck", "bus": "bus", "person": "person",
        "bicycle": "bicycle", "minibike": "motorcycle", "pole": "pole", "streetlight": "-",
        "traffic light": "traffic light", "signboard": "-", "fence": "fence", "railing": "-", "bed": "-",
        "floor": "-", "ceiling": "-",
    }
    assert {k: t[k] for k in expected} == expected


def test_coco_panoptic_rows():
    _, rows = read("coco_panoptic")
    assert rows[0][1:3] == ("person", "person")
    assert rows[2][1:3] == ("car", "car")
    assert rows[9][1:3] == ("traffic light", "traffic light")
    assert rows[79][1] == "toothbrush" and rows[80][1] == "banner" and rows[81][1] == "blanket"
    assert rows[132][1:3] == ("rug-merged", "-")
    t = targets("coco_panoptic")
    expected = {
        "bicycle": "bicycle", "motorcycle": "motorcycle", "bus": "bus", "train": "train", "truck": "truck",
        "stop sign": "traffic sign", "road": "road", "pavement-merged": "sidewalk",
        "building-other-merged": "building", "house": "building", "roof": "building", "wall-brick": "wall",
        "wall-other-merged": "wall", "fence-merged": "fence", "tree-merged": "vegetation", "flower": "vegetation",
        "grass-merged": "terrain", "dirt-merged": "terrain", "sky-other-merged": "sky", "railroad": "-",
        "potted plant": "-", "airplane": "-",
    }
    assert {k: t[k] for k in expected} == expected


def test_reachable_cityscapes_classes():
    everything = set(CLASS_NAMES)
    assert reached("mapillary_vistas_v1.2") == everything
    assert everything - reached("ade20k") == {"traffic sign", "rider", "train"}
    assert everything - reached("coco_panoptic") == {"pole", "rider"}
