"""One image's ground-truth boxes from whatever the dataset has: the renderer's instance map (+ label map, + fog
transmittance), a renderer's own box file (DeepGTAV), or a real dataset's instance labels (Cityscapes, ACDC)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pairedgta.detection.boxes import CITYSCAPES_MIN_AREA, Box, boxes_from_instances, read_box_file
from pairedgta.detection.real_boxes import read_real_boxes
from pairedgta.errors import DataError


def read_ground_truth(instances: Path, labels: Path | None, *, min_area: int = CITYSCAPES_MIN_AREA,
                      transmittance: Path | None = None, min_transmittance: float = 0.0) -> list[Box]:
    """One image's boxes from its instance map (+ label map, + transmittance map) or its box file."""
    from pairedgta.datasets.base import load_label, load_transmittance
    from PIL import Image

    if instances.suffix == ".json":
        return read_box_file(instances, min_area)
    if instances.name.endswith(("_gtFine_instanceIds.png", "_gt_panoptic.png")):  # real labels name their classes
        return read_real_boxes(instances, min_area)
    if labels is None:
        raise DataError(f"{instances}: no label map beside it (the objects' classes); regenerate the dataset")
    try:
        with Image.open(instances) as im:
            inst = np.array(im)
    except FileNotFoundError:
        raise DataError(f"{instances}: instance map not found; regenerate the dataset") from None
    except OSError as exc:
        raise DataError(f"{instances}: not a readable instance map ({type(exc).__name__}); regenerate it") from None
    if inst.ndim != 2:
        raise DataError(f"{instances}: instance map has {inst.ndim} dimensions; expected a 16-bit single-channel PNG")
    lab = load_label(labels)
    if lab.shape != inst.shape:
        raise DataError(f"{instances}: size {inst.shape[::-1]} differs from its label map {labels} "
                        f"{lab.shape[::-1]}; regenerate the dataset")
    t = load_transmittance(transmittance) if transmittance is not None and min_transmittance > 0 else None
    if t is None and transmittance is not None:
        t = load_transmittance(transmittance)
    return boxes_from_instances(inst, lab, min_area=min_area, transmittance=t, min_transmittance=min_transmittance)


def group_ground_truth(group: Any, condition: str, reference: str, *, min_area: int,
                       min_transmittance: float) -> list[Box] | None:
    """The boxes of one group's image under `condition`: its own instance map, else the reference's (the objects
    are the same in every condition; the label map of that condition then names their classes); None where the
    dataset has no instance ids for the group."""
    cond = condition if condition in group.instances else reference
    if cond not in group.instances:
        return None
    labels = group.labels.get(cond) or group.labels.get(reference)
    return read_ground_truth(group.instances[cond], labels, min_area=min_area,
                             transmittance=group.transmittance.get(condition), min_transmittance=min_transmittance)




__all__ = ["group_ground_truth", "read_ground_truth"]
