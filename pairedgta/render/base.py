"""Renderer backend interface (Kubric-style): a descriptor plus a condition in, layers out.

Backends share everything above this line: the generate stage, the dataset layout, validation.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pairedgta.conditions import Condition
from pairedgta.scene.descriptor import SceneDescriptor


@dataclass
class RenderResult:
    """Layers of one rendered image: RGB uint8 HxWx3, optional Cityscapes train-id labels HxW uint8
    (255 = unlabeled), optional instance ids HxW uint16, the backend-reported entity state, and the
    optional distance from the camera along each pixel's ray in metres (float32, inf where the ray
    leaves the scene): the generate stage turns it into the condition's transmittance map. `boxes`: a
    backend's own 2D boxes where it gives no instance ids (DeepGTAV's bbox2d), each {"class": a Cityscapes
    instance class, "bbox": [x0, y0, x1, y1] pixels, "instance": int, "truncated": bool, "occluded": int};
    the generate stage writes them to <condition>_boxes.json (pairedgta.detection.boxes.read_box_file)."""

    image: np.ndarray
    labels: np.ndarray | None = None
    instances: np.ndarray | None = None
    state: dict[str, Any] = field(default_factory=dict)
    distance: np.ndarray | None = None
    boxes: list[dict[str, Any]] | None = None


class Renderer(abc.ABC):
    """R(S_k, c_i). `prepare` builds the scene once (semantic scene construction); `render` applies a
    condition and captures (condition-wise rendering), so the two phases are timed separately."""

    name: str = "renderer"
    gives_labels: bool = False

    def __init__(self, width: int, height: int, **_: Any) -> None:
        self.width = int(width)
        self.height = int(height)

    def open(self) -> None:
        """Connect / start the backend. Default: nothing to do."""

    def close(self) -> None:
        """Release the backend. Default: nothing to do."""

    def __enter__(self) -> "Renderer":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abc.abstractmethod
    def prepare(self, descriptor: SceneDescriptor) -> None:
        """Initialise ego, camera and dynamic objects of `descriptor`."""

    @abc.abstractmethod
    def render(self, descriptor: SceneDescriptor, condition: Condition) -> RenderResult:
        """Re-initialise the scene from `descriptor`, apply `condition`, capture."""
