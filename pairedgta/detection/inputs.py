"""What the detection stages and metrics share: detections as JSON, the COCO image ids of a dataset's groups, one
group's results (what a shard job stores) and the metrics' inputs (pairedgta/detection/registry.py)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from pairedgta.models.detectors import Detections

if TYPE_CHECKING:
    from pairedgta.datasets import PairedDataset


def detections_json(d: Detections) -> dict[str, Any]:
    return {"boxes": np.round(d.boxes, 3).tolist(), "scores": np.round(d.scores, 6).tolist(),
            "labels": d.labels.tolist()}


def detections_from_json(d: dict[str, Any]) -> Detections:
    return Detections(np.asarray(d["boxes"], np.float32).reshape(-1, 4), np.asarray(d["scores"], np.float32),
                      np.asarray(d["labels"], np.int64))


def image_ids(dataset: PairedDataset) -> dict[str, int]:
    """COCO image ids of the groups (1-based, dataset order): the same id for a group in every condition's file."""
    return {g.group_id: i for i, g in enumerate(dataset.groups, start=1)}


@dataclass
class GroupResult:
    """One group's detections and counts under every condition (what a shard job stores)."""

    group_id: str
    detections: dict[str, Detections]
    counts: dict[str, np.ndarray]  # condition -> 4 x C (detection_xi.image_counts)
    objects: list[dict[str, Any]]
    sizes: dict[str, tuple[int, int]]  # condition -> (height, width)
    estimators: dict[str, dict[str, float]] = field(default_factory=dict)  # condition -> bos, pcr (detection.estimators)

    def to_json(self) -> dict[str, Any]:
        return {"group_id": self.group_id, "detections": {c: detections_json(d) for c, d in self.detections.items()},
                "counts": {c: v.tolist() for c, v in self.counts.items()}, "objects": self.objects,
                "sizes": {c: list(s) for c, s in self.sizes.items()},
                "estimators": {c: {k: None if math.isnan(v) else v for k, v in e.items()}
                               for c, e in self.estimators.items()}}

    @staticmethod
    def from_json(d: dict[str, Any]) -> "GroupResult":
        return GroupResult(d["group_id"], {c: detections_from_json(v) for c, v in d["detections"].items()},
                           {c: np.asarray(v, np.int64) for c, v in d["counts"].items()},
                           [{**o, "transmittance": math.nan if o["transmittance"] is None else o["transmittance"],
                             "luma": math.nan if o["luma"] is None else o["luma"]} for o in d["objects"]],
                           {c: (int(s[0]), int(s[1])) for c, s in d["sizes"].items()},
                           {c: {k: math.nan if v is None else float(v) for k, v in e.items()}
                            for c, e in (d.get("estimators") or {}).items()})


@dataclass
class Inputs:
    """What the metrics read: the groups' results, the reference's boxes, the ground truth, the settings."""

    model: str
    reference_model: str
    conditions: list[str]
    clean: str
    groups: list[GroupResult]
    image_ids: dict[str, int]
    pseudo: dict[str, Detections]
    ground_truth: dict[str, Any]  # condition -> COCO dict (pycocotools' input), only where it exists
    threshold: float
    settings: dict[str, Any]
    blind: tuple[str, ...] = ()  # the instance classes the model's label space lacks (COCO: rider)

    def blind_reason(self) -> str:
        return f"the model's label space has no {'/'.join(self.blind)}: it cannot predict it"

    def scored_categories(self) -> list[int]:
        """The COCO category ids the model can predict (its AP averages over these)."""
        from pairedgta.detection.boxes import INSTANCE_CLASSES

        return [k + 1 for k, n in enumerate(INSTANCE_CLASSES) if n not in self.blind]

    @property
    def adverse(self) -> list[str]:
        return [c for c in self.conditions if c != self.clean]

    def coco_results(self, condition: str) -> list[dict[str, Any]]:
        from pairedgta.metrics.coco_ap import results_format

        out: list[dict[str, Any]] = []
        for g in self.groups:
            d = g.detections.get(condition)
            if d is not None:
                out += results_format(self.image_ids[g.group_id], d.boxes, d.scores, d.labels + 1,
                                      self.settings["max_detections"])
        return out


