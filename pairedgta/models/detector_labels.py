"""Label spaces of detectors (`model.labels`): a model's class ids mapped onto Cityscapes' eight instance classes.

A class id is the model's own, after the layout's background slot (pairedgta/models/detector_layouts.py): torchvision's
COCO ids 1..90 become 0..89. Names map by Cityscapes name (COCO's person, bicycle, car, motorcycle, bus, train, truck
are Cityscapes names), through a segmentation table for the spaces segmentation ships (pairedgta/models/labels.py:
Mapillary Vistas' Bicyclist / Motorcyclist are riders there), or through a user's TSV (`source class<TAB>Cityscapes
class` or `-`, one row per class id). An instance class no id maps to is one the model cannot predict (COCO has no
rider): its detection xi and AP are NaN with that reason, never 0."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.cityscapes import INSTANCE_CLASSES
from pairedgta.errors import ConfigError

# COCO 2017's 80 detection classes in their contiguous order (YOLO, most ONNX exports)
COCO80 = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow", "elephant",
    "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard",
    "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange", "broccoli",
    "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant", "bed", "dining table", "toilet",
    "tv", "laptop", "mouse", "remote", "keyboard", "cell phone", "microwave", "oven", "toaster", "sink",
    "refrigerator", "book", "clock", "vase", "scissors", "teddy bear", "hair drier", "toothbrush")
# COCO's category ids 1..90 (torchvision's detection builders, DETR): the 80 with the 10 unused ids as "N/A"
_COCO_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 27, 28, 31, 32, 33,
             34, 35, 36, 37, 38, 39, 40, 41, 42, 43, 44, 46, 47, 48, 49, 50, 51, 52, 53, 54, 55, 56, 57, 58, 59, 60, 61,
             62, 63, 64, 65, 67, 70, 72, 73, 74, 75, 76, 77, 78, 79, 80, 81, 82, 84, 85, 86, 87, 88, 89, 90)
COCO91 = tuple(dict(zip(_COCO_IDS, COCO80)).get(i, "N/A") for i in range(1, 91))
SPACES: dict[str, tuple[str, ...]] = {"coco": COCO80, "coco91": COCO91, "cityscapes": INSTANCE_CLASSES}
SEG_TABLES = ("mapillary_vistas_v1.2",)  # segmentation's shipped tables that have instance classes


def _norm(name: str) -> str:
    from pairedgta.models.labels import normalise_name

    return normalise_name(name)


_BY_NAME = {_norm(n): i for i, n in enumerate(INSTANCE_CLASSES)}


@dataclass(frozen=True)
class DetectionLabels:
    """Per class id of the model, the index into INSTANCE_CLASSES it counts as (-1: none)."""

    space: str
    source_classes: tuple[str, ...]
    target: tuple[int, ...]

    @property
    def num_classes(self) -> int:
        return len(self.target)

    @property
    def blind(self) -> tuple[str, ...]:
        """The instance classes no class id maps to: the model cannot predict them."""
        reached = set(self.target)
        return tuple(n for i, n in enumerate(INSTANCE_CLASSES) if i not in reached)

    def describe(self) -> str:
        parts = [f"{self.num_classes} classes of {self.space}"]
        if self.blind:
            parts.append(f"cannot predict: {', '.join(self.blind)}")
        return "; ".join(parts)

    def apply(self, labels: Any) -> Any:
        import numpy as np

        table = np.asarray(self.target, np.int64)
        return table[np.asarray(labels, np.int64)]


def _target(name: str) -> int:
    return _BY_NAME.get(_norm(name), -1)


def from_names(space: str, names: list[str] | tuple[str, ...]) -> DetectionLabels:
    return DetectionLabels(space, tuple(names), tuple(_target(n) for n in names))


def _from_table(path: Path, space: str) -> DetectionLabels:
    """A segmentation-style table (`source class<TAB>Cityscapes class`): its rows' Cityscapes names, kept where they
    are instance classes."""
    from pairedgta.models.labels import read_table

    table = read_table(path, space)
    target = tuple(_BY_NAME.get(_norm(CLASS_NAMES[t]), -1) if t >= 0 else -1 for t in table.target)
    return DetectionLabels(space, table.source_classes, target)


def resolve(spec: Any, id2label: Mapping[int, str] | None, where: str, default: str | None = None) -> DetectionLabels:
    """`model.labels` for a detector: a space's name, a TSV's path, or (null) the checkpoint's own class names
    (`id2label`), else `default`."""
    from pairedgta.models.labels import TABLES

    if spec is None and id2label:
        names = [str(id2label[i]) for i in sorted(id2label)]
        found = from_names("the checkpoint's id2label", names)
        if not all(t < 0 for t in found.target):
            return found
        raise ConfigError(f"{where}: none of the checkpoint's {len(names)} class names ({', '.join(names[:4])}, ...) "
                          f"is a Cityscapes instance class ({', '.join(INSTANCE_CLASSES)}); set model.labels= to its "
                          f"label space ({', '.join(SPACES)}) or to a TSV mapping its classes to Cityscapes names")
    spec = default if spec is None else str(spec)
    if spec is None:
        raise ConfigError(f"{where}: model.labels is not set and the model names no classes; set model.labels= to "
                          f"its label space ({', '.join(SPACES)}) or to a TSV of 'source class<TAB>Cityscapes class'")
    if spec in SPACES:
        return from_names(spec, SPACES[spec])
    if spec in SEG_TABLES:
        return _from_table(TABLES / f"{spec}.tsv", spec)
    if "/" in spec or spec.endswith((".tsv", ".txt")):
        return _from_table(Path(spec).expanduser(), spec)
    raise ConfigError(f"{where}: model.labels={spec!r} is not a detection label space; use one of "
                      f"{', '.join((*SPACES, *SEG_TABLES))} or a TSV of 'source class<TAB>Cityscapes class'")


__all__ = ["COCO80", "COCO91", "DetectionLabels", "SPACES", "from_names", "resolve"]
