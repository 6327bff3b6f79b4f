"""The project's own layout, written by the generate stage:

    <root>/index.json                       conditions, reference, renderer, scenes
    <root>/scenes/<scene_id>/<condition>.png           image
    <root>/scenes/<scene_id>/<condition>_labels.png    train ids (backends with labels)
    <root>/scenes/<scene_id>/<condition>_instances.png instance ids
    <root>/scenes/<scene_id>/<condition>_transmittance.png  exp(-extinction * distance), 16-bit (backends with depth)
    <root>/scenes/<scene_id>/<condition>_boxes.json    2D boxes where a backend gives no instance ids (DeepGTAV)
    <root>/scenes/<scene_id>/descriptor.json           the replay file
A corruption condition (C-fog-3) has its image only: its labels, instances and boxes are the clean condition's.
    <root>/scenes/<scene_id>/timings.json
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pairedgta.conditions import ConditionGrid
from pairedgta.datasets.base import Group, PairedDataset, share_clean_truth
from pairedgta.errors import DataError

log = logging.getLogger(__name__)
INDEX = "index.json"


def scene_files(scene_dir: Path, condition: str) -> tuple[Path, Path, Path]:
    return scene_dir / f"{condition}.png", scene_dir / f"{condition}_labels.png", scene_dir / f"{condition}_instances.png"


def transmittance_file(scene_dir: Path, condition: str) -> Path:
    return scene_dir / f"{condition}_transmittance.png"


def boxes_file(scene_dir: Path, condition: str) -> Path:
    """A renderer's own 2D boxes where it gives no instance mask (DeepGTAV's bbox2d): detection's ground truth."""
    return scene_dir / f"{condition}_boxes.json"


TRANSMITTANCE_SCALE = 65535


def transmittance_png(transmittance: np.ndarray) -> np.ndarray:
    """Transmittance in [0, 1] as 16-bit levels (resolution 1.5e-5: a threshold near 0 stays meaningful)."""
    return np.rint(np.clip(transmittance, 0.0, 1.0) * TRANSMITTANCE_SCALE).astype(np.uint16)


def open_generated(*, root: str | Path, grid: ConditionGrid, name: str = "generated") -> PairedDataset:
    root = Path(root)
    index_path = root / INDEX
    if not root.is_dir():
        raise DataError(f"dataset.root={root} does not exist; run the generate stage or fix dataset.root")
    if not index_path.is_file():
        raise DataError(f"{index_path} is missing; {root} is not a generated PairedGTA dataset (run stage generate)")
    try:
        index = json.loads(index_path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{index_path}: corrupt index ({exc.msg}); rerun the generate stage") from None
    scenes = index.get("scenes", []) if isinstance(index, dict) else None
    if not isinstance(scenes, list) or not all(
            isinstance(sc, dict) and isinstance(sc.get("dir"), str) and isinstance(sc.get("scene_id"), (str, int))
            and not Path(sc["dir"]).is_absolute() and ".." not in Path(sc["dir"]).parts  # stays inside root
            for sc in scenes):
        raise DataError(f"{index_path}: not a generated dataset's index (expected scenes: a list of "
                        "{scene_id, dir: a folder inside the dataset}); rerun the generate stage")
    groups, skipped = [], 0
    for scene in scenes:
        scene_dir = root / scene["dir"]
        images, labels, transmittance, instances = {}, {}, {}, {}
        for cond in grid.names:
            img, lab, inst = scene_files(scene_dir, cond)
            if img.is_file():
                images[cond] = img
                if lab.is_file():
                    labels[cond] = lab
                if inst.is_file():
                    instances[cond] = inst
                elif boxes_file(scene_dir, cond).is_file():
                    instances[cond] = boxes_file(scene_dir, cond)
                if transmittance_file(scene_dir, cond).is_file():
                    transmittance[cond] = transmittance_file(scene_dir, cond)
        if grid.reference not in images:
            skipped += 1
            continue
        desc = scene_dir / "descriptor.json"
        groups.append(share_clean_truth(Group(scene["scene_id"], images, labels, desc if desc.is_file() else None,
                                              transmittance, instances), grid))
    if skipped:
        log.warning("skipped %d group(s) without the reference image %s", skipped, grid.reference)
    if not groups:
        raise DataError(f"{index_path}: the dataset has no group with the reference {grid.reference}; regenerate it")
    return PairedDataset(name, root, grid.reference, grid.names, groups, skipped, grid=grid)
