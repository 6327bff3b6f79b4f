"""Ground-truth boxes from what the renderer knows: every object's visible pixels (its instance id), its class
(the label map under those pixels) and, under fog, how much of it the camera could see (the transmittance).

The rules, written down once (docs/detection.md "Ground truth"):
- an object is an instance id > 0 whose pixels are mostly one of Cityscapes' eight instance classes
  (person, rider, car, truck, bus, train, motorcycle, bicycle); traffic lights and signs have no instances, in
  Cityscapes as here, and are not detection classes;
- its box is the tight box of its *visible* pixels (occluded parts are not in the box, as Cityscapes' and
  MMDetection's converters do); a box cut by the image border is kept, the visible part, and flagged `truncated`;
- an object with fewer visible pixels than `min_area` (Cityscapes: 100) is an ignore region, not a miss;
- with `min_transmittance` > 0, an object whose pixels are mostly (more than half) below that fog transmittance
  is an ignore region: the camera could not see it, so a model that misses it is not wrong.
Ignore regions go to COCO JSON as `iscrowd: 1` (pycocotools then lets detections on them cost nothing)."""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, INSTANCE_CLASSES, NUM_INSTANCE_CLASSES
from pairedgta.errors import DataError

_TRAIN_TO_INSTANCE = np.full(256, -1, dtype=np.int64)
for _i, _n in enumerate(INSTANCE_CLASSES):
    _TRAIN_TO_INSTANCE[CLASS_NAMES.index(_n)] = _i
CITYSCAPES_MIN_AREA = 100
RULES_VERSION = "1"  # bumped when a rule below changes the boxes (it keys the labels stage)
IGNORE_SMALL, IGNORE_FOG, IGNORE_CROWD = "small", "fog", "crowd"


def category_id(label: int) -> int:
    """COCO category id of an instance class index (1..8, in INSTANCE_CLASSES' order)."""
    return int(label) + 1


def coco_categories() -> list[dict[str, Any]]:
    return [{"id": category_id(i), "name": n, "supercategory": "cityscapes"} for i, n in enumerate(INSTANCE_CLASSES)]


@dataclass(frozen=True)
class Box:
    """One ground-truth object in one image: xyxy in pixels (right/bottom exclusive), visible area in pixels."""

    instance: int
    label: int  # index into INSTANCE_CLASSES
    xyxy: tuple[float, float, float, float]
    area: float
    ignore: str = ""  # "" (scored) or why it is an ignore region: small, fog, crowd
    truncated: bool = False
    # mean fog transmittance over its pixels (nan: no map); a measurement of the box, not part of its identity (and
    # NaN never equals NaN: dataclass equality compares fields one by one from Python 3.13 on)
    transmittance: float = field(default=math.nan, compare=False)

    @property
    def height(self) -> float:
        return self.xyxy[3] - self.xyxy[1]

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> "Box":
        return Box(int(d["instance"]), int(d["label"]), tuple(float(v) for v in d["xyxy"]), float(d["area"]),
                   str(d.get("ignore", "")), bool(d.get("truncated", False)), float(d.get("transmittance", math.nan)))


def boxes_from_instances(instances: np.ndarray, labels: np.ndarray, *, min_area: int = CITYSCAPES_MIN_AREA,
                         transmittance: np.ndarray | None = None, min_transmittance: float = 0.0) -> list[Box]:
    """Every object of one image (see the module's rules), ordered by instance id."""
    from scipy import ndimage

    if instances.shape != labels.shape:
        raise ValueError(f"instance map {instances.shape} and label map {labels.shape} differ in size")
    h, w = instances.shape
    inst = instances.astype(np.int64, copy=False)
    out: list[Box] = []
    for k, sl in enumerate(ndimage.find_objects(inst), start=1):
        if sl is None:
            continue
        mine = inst[sl] == k
        classes = _TRAIN_TO_INSTANCE[labels[sl][mine]]
        counts = np.bincount(classes[classes >= 0], minlength=NUM_INSTANCE_CLASSES)
        if counts.sum() * 2 <= mine.sum():  # mostly not an instance class (a sign, a pole, void)
            continue
        rows, cols = np.nonzero(mine)
        y0, y1 = sl[0].start + int(rows.min()), sl[0].start + int(rows.max()) + 1
        x0, x1 = sl[1].start + int(cols.min()), sl[1].start + int(cols.max()) + 1
        area = float(mine.sum())
        mean_t, ignore = math.nan, ""
        if transmittance is not None:
            t = transmittance[sl][mine]
            mean_t = float(t.mean())
            if min_transmittance > 0 and (t < min_transmittance).mean() > 0.5:
                ignore = IGNORE_FOG
        if area < min_area:
            ignore = IGNORE_SMALL
        out.append(Box(k, int(counts.argmax()), (float(x0), float(y0), float(x1), float(y1)), area, ignore,
                       x0 == 0 or y0 == 0 or x1 == w or y1 == h, mean_t))
    return out


def read_box_file(path: Path, min_area: int = CITYSCAPES_MIN_AREA) -> list[Box]:
    """A renderer's own 2D boxes (`<condition>_boxes.json`: {"boxes": [{class, bbox xyxy, instance, ...}]}, written
    by the generate stage from DeepGTAV's bbox2d): no mask, so the area is the box's and fog cannot be judged."""
    try:
        raw = json.loads(Path(path).read_text())
        items = raw["boxes"]
        out = []
        for i, b in enumerate(items, start=1):
            if b["class"] not in INSTANCE_CLASSES:
                continue
            x0, y0, x1, y1 = (float(v) for v in b["bbox"])
            area = max(0.0, x1 - x0) * max(0.0, y1 - y0)
            out.append(Box(int(b.get("instance", i)), INSTANCE_CLASSES.index(b["class"]), (x0, y0, x1, y1), area,
                           IGNORE_SMALL if area < min_area else "", bool(b.get("truncated", False))))
        return out
    except FileNotFoundError:
        raise DataError(f"{path}: box file not found; regenerate the dataset") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path}: not a boxes file ({type(exc).__name__}: {exc}); regenerate the dataset") from None


def coco_ground_truth(images: Sequence[tuple[int, str, int, int]], boxes: Iterable[Sequence[Box]]) -> dict[str, Any]:
    """COCO ground truth: `images` (id, file name, width, height) and each image's boxes; ignore regions as
    iscrowd=1, the visible pixel count as `area` (COCO's small/medium/large split reads it), extra fields kept."""
    anns, ann_id = [], 0
    for (image_id, _, _, _), image_boxes in zip(images, boxes):
        for b in image_boxes:
            ann_id += 1
            x0, y0, x1, y1 = b.xyxy
            anns.append({"id": ann_id, "image_id": image_id, "category_id": category_id(b.label),
                         "bbox": [x0, y0, x1 - x0, y1 - y0], "area": b.area, "iscrowd": int(bool(b.ignore)),
                         "ignore_reason": b.ignore, "truncated": b.truncated, "instance": b.instance,
                         **({"transmittance": b.transmittance} if math.isfinite(b.transmittance) else {})})
    return {"info": {"description": "pairedgta ground truth from the renderer's instance masks"},
            "images": [{"id": i, "file_name": f, "width": w, "height": h} for i, f, w, h in images],
            "annotations": anns, "categories": coco_categories()}


def scored(boxes: Iterable[Box]) -> list[Box]:
    return [b for b in boxes if not b.ignore]


__all__ = ["Box", "CITYSCAPES_MIN_AREA", "IGNORE_CROWD", "IGNORE_FOG", "IGNORE_SMALL", "INSTANCE_CLASSES",
           "NUM_INSTANCE_CLASSES", "boxes_from_instances", "category_id", "coco_categories", "coco_ground_truth",
           "read_box_file", "scored"]
