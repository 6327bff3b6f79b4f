"""Cityscapes 19-train-id label space shared by every model in the zoo."""
from __future__ import annotations

import numpy as np

CLASS_NAMES = (
    "road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign",
    "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train",
    "motorcycle", "bicycle",
)
NUM_CLASSES = len(CLASS_NAMES)
IGNORE_INDEX = 255

PALETTE = np.array(
    [
        (128, 64, 128), (244, 35, 232), (70, 70, 70), (102, 102, 156), (190, 153, 153),
        (153, 153, 153), (250, 170, 30), (220, 220, 0), (107, 142, 35), (152, 251, 152),
        (70, 130, 180), (220, 20, 60), (255, 0, 0), (0, 0, 142), (0, 0, 70), (0, 60, 100),
        (0, 80, 100), (0, 0, 230), (119, 11, 32),
    ],
    dtype=np.uint8,
)

# Cityscapes labelId -> trainId (labels that are not evaluated map to 255)
LABEL_ID_TO_TRAIN_ID = {
    7: 0, 8: 1, 11: 2, 12: 3, 13: 4, 17: 5, 19: 6, 20: 7, 21: 8, 22: 9, 23: 10, 24: 11, 25: 12,
    26: 13, 27: 14, 28: 15, 31: 16, 32: 17, 33: 18,
}


def class_id(name: str) -> int:
    try:
        return CLASS_NAMES.index(name)
    except ValueError:
        from pairedgta.errors import ConfigError

        raise ConfigError(f"unknown class '{name}'; classes are: {', '.join(CLASS_NAMES)}") from None


def label_ids_to_train_ids(label_ids: np.ndarray) -> np.ndarray:
    lut = np.full(256, IGNORE_INDEX, dtype=np.uint8)
    for lid, tid in LABEL_ID_TO_TRAIN_ID.items():
        lut[lid] = tid
    return lut[label_ids.astype(np.int64).clip(0, 255)]


# The classes with instances (Cityscapes' "hasInstances"): what a detector finds and a box is drawn around, in
# train-id order; traffic lights and signs are not instanced.
INSTANCE_CLASSES = ("person", "rider", "car", "truck", "bus", "train", "motorcycle", "bicycle")
NUM_INSTANCE_CLASSES = len(INSTANCE_CLASSES)


def colorize(labels: np.ndarray) -> np.ndarray:
    """Train-id map -> RGB with the Cityscapes palette (void is black)."""
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[:NUM_CLASSES] = PALETTE
    return lut[labels.astype(np.int64).clip(0, 255)]
