"""Output layouts of detectors: how a network's raw outputs say boxes, scores and classes (`model.layout`).

No two export formats agree (docs/detection.md, "Detectors a researcher brings"), so a detector source declares its
layout, a named preset or its parts, and one decoder here turns the outputs into per-image boxes (xyxy, pixels of
the network's input), scores in [0, 1] and the model's own class ids; NMS (torchvision.ops.batched_nms) runs here
where the graph has none. Outputs are matched by name, never by shape (with 3 classes, classes + 1 = 4 equals a
box's size).

Presets:
  torchvision   per image a dict boxes (xyxy pixels) / scores / labels, NMS inside; class id 0 is background
                (a graph's flat outputs: `boxes`, `scores`, `labels`, one image per run)
  detr          `logits` (B, Q, C + 1, softmax, the last slot "no object") and `pred_boxes` (B, Q, 4, cxcywh
                normalised to the input); every query is a box, no NMS
  yolov5        `output0` (B, N, 5 + C): cxcywh pixels, objectness, class probabilities (sigmoid applied in the
                export); score = objectness x class probability; NMS here
  yolov8        `output0` (B, 4 + C, N): cxcywh pixels, class scores (sigmoid applied), no objectness; NMS here
  efficientnms  TensorRT's EfficientNMS outputs `num_dets` (B, 1), `det_boxes` (B, K, 4 xyxy pixels),
                `det_scores`, `det_classes`; NMS inside
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any, Mapping

import numpy as np

from pairedgta.errors import ConfigError, ModelError

BOX_FORMATS = ("xyxy", "xywh", "cxcywh")
ACTIVATIONS = ("none", "sigmoid", "softmax")
BACKGROUND = ("none", "first", "last")
KINDS = ("dicts", "tensors")  # per-image dicts (torchvision) or batched tensors with a query/anchor axis
ROLES = ("boxes", "scores", "labels", "logits", "objectness", "count", "combined")


@dataclass(frozen=True)
class Layout:
    name: str
    kind: str = "tensors"
    box_format: str = "xyxy"
    normalized: bool = False  # boxes in [0, 1] of the network's input (else its pixels)
    activation: str = "none"  # applied to the class scores: none (already probabilities), sigmoid, softmax
    background: str = "none"  # a class slot meaning "no object": the first (torchvision's id 0) or the last (DETR's)
    objectness: bool = False  # YOLOv5: score = objectness x class probability
    nms: bool = False  # the graph already suppresses overlapping boxes
    transposed: bool = False  # the combined output is (B, values, N) instead of (B, N, values): YOLOv8
    outputs: Mapping[str, str] = field(default_factory=dict)  # role -> output name

    def describe(self) -> str:
        parts = [self.name, self.box_format + (" normalised" if self.normalized else " pixels")]
        if self.activation != "none":
            parts.append(self.activation)
        if self.objectness:
            parts.append("objectness")
        if self.background != "none":
            parts.append(f"background {self.background}")
        parts.append("NMS inside" if self.nms else "NMS here")
        return ", ".join(parts)


PRESETS: dict[str, Layout] = {
    "torchvision": Layout("torchvision", kind="dicts", background="first", nms=True,
                          outputs={"boxes": "boxes", "scores": "scores", "labels": "labels"}),
    "detr": Layout("detr", box_format="cxcywh", normalized=True, activation="softmax", background="last",
                   nms=True, outputs={"logits": "logits", "boxes": "pred_boxes"}),
    "yolov5": Layout("yolov5", box_format="cxcywh", objectness=True, outputs={"combined": "output0"}),
    "yolov8": Layout("yolov8", box_format="cxcywh", transposed=True, outputs={"combined": "output0"}),
    "efficientnms": Layout("efficientnms", nms=True, outputs={"count": "num_dets", "boxes": "det_boxes",
                                                              "scores": "det_scores", "labels": "det_classes"}),
}


def parse_layout(spec: Any, where: str, default: str | None = None) -> Layout:
    """`model.layout`: a preset's name, or a mapping of parts on top of a `preset` (or of plain tensors)."""
    if spec is None:
        if default is None:
            raise ConfigError(f"{where}: model.layout is not set; name the output layout: one of "
                              f"{', '.join(PRESETS)}, or its parts (model.layout={{preset: yolov8, normalized: true}})")
        spec = default
    if isinstance(spec, str):
        if spec not in PRESETS:
            raise ConfigError(f"{where}: model.layout={spec!r} is unknown; use one of {', '.join(PRESETS)} or give its "
                              "parts (box_format, normalized, activation, background, objectness, nms, outputs)")
        return PRESETS[spec]
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: model.layout must be a preset name or a mapping of its parts, got {spec!r}")
    parts = dict(spec)
    base = PRESETS[parse_layout(parts.pop("preset"), where).name] if parts.get("preset") else Layout("custom")
    known = {f.name for f in fields(Layout)} - {"name"}
    unknown = sorted(set(parts) - known)
    if unknown:
        raise ConfigError(f"{where}: model.layout has unknown part(s) {unknown}; its parts are preset, "
                          f"{', '.join(sorted(known))}")
    checks = {"box_format": BOX_FORMATS, "activation": ACTIVATIONS, "background": BACKGROUND, "kind": KINDS}
    for key, allowed in checks.items():
        if key in parts and parts[key] not in allowed:
            raise ConfigError(f"{where}: model.layout.{key}={parts[key]!r}; use one of {', '.join(allowed)}")
    for key in ("normalized", "objectness", "nms", "transposed"):
        if key in parts and not isinstance(parts[key], bool):
            raise ConfigError(f"{where}: model.layout.{key}={parts[key]!r} must be true or false")
    if "outputs" in parts:
        outputs = parts["outputs"]
        bad = sorted(set(outputs) - set(ROLES)) if isinstance(outputs, Mapping) else ["(not a mapping)"]
        if bad:
            raise ConfigError(f"{where}: model.layout.outputs has unknown role(s) {bad}; roles are {', '.join(ROLES)} "
                              "(role: output name), e.g. {boxes: det_boxes, scores: det_scores}")
        parts["outputs"] = {**dict(base.outputs), **{str(k): str(v) for k, v in outputs.items()}}
    name = f"{base.name}+" if base.name != "custom" else "custom"
    return replace(base, name=name if parts else base.name, **parts)


def required_roles(layout: Layout) -> tuple[str, ...]:
    if "combined" in layout.outputs:
        return ("combined",)
    roles = ["boxes"]
    roles += ["logits"] if "logits" in layout.outputs else ["scores", "labels"]
    if "count" in layout.outputs:
        roles.append("count")
    return tuple(roles)


def check_outputs(layout: Layout, names: list[str], where: str) -> None:
    """Every output the layout reads exists under its name; else one line naming what the graph has."""
    missing = [f"{role}={layout.outputs.get(role)!r}" for role in required_roles(layout)
               if layout.outputs.get(role) not in names]
    if missing:
        raise ModelError(f"{where}: the network's outputs are {', '.join(map(repr, names)) or 'unnamed'}, but "
                         f"model.layout={layout.name} reads {', '.join(missing)}; choose the preset of its "
                         "exporter or name its outputs: model.layout={preset: ..., outputs: {boxes: <name>, ...}}")


def to_xyxy(boxes: np.ndarray, fmt: str) -> np.ndarray:
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    if fmt == "xyxy":
        return b.copy()
    if fmt == "xywh":
        return np.concatenate([b[:, :2], b[:, :2] + b[:, 2:]], axis=1)
    half = b[:, 2:] / 2.0
    return np.concatenate([b[:, :2] - half, b[:, :2] + half], axis=1)


def _activate(scores: np.ndarray, activation: str) -> np.ndarray:
    if activation == "sigmoid":
        return 1.0 / (1.0 + np.exp(-scores))
    if activation == "softmax":
        e = np.exp(scores - scores.max(axis=-1, keepdims=True))
        return e / e.sum(axis=-1, keepdims=True)
    return scores


@dataclass
class Raw:
    """One image's decoded boxes before the label map: xyxy pixels of the network's input, scores, class ids."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray


def _numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().float().cpu().numpy() if value.is_floating_point() else value.detach().cpu().numpy()
    return np.asarray(value)


def decode(outputs: Any, layout: Layout, input_size: tuple[int, int], where: str, num_classes: int | None = None,
           nms_iou: float = 0.5, max_detections: int = 100) -> list[Raw]:
    """The raw outputs of one batch -> per image `Raw`, sorted by score, at most `max_detections`."""
    if layout.kind == "dicts":
        images = outputs if isinstance(outputs, (list, tuple)) else [outputs]
        named = [{role: _numpy(d[layout.outputs[role]]) for role in ("boxes", "scores", "labels")}
                 for d in images]
        return [_finish(_plain(n["boxes"], n["scores"], n["labels"], layout, input_size, where, num_classes),
                        layout, nms_iou, max_detections, where) for n in named]
    named = {role: _numpy(outputs[layout.outputs[role]]) for role in required_roles(layout)}
    if "combined" in named:
        return _combined(named["combined"], layout, input_size, where, num_classes, nms_iou, max_detections)
    boxes = named["boxes"]
    if boxes.ndim == 2:  # one image without a batch axis
        named = {k: v[None] for k, v in named.items()}
        boxes = named["boxes"]
    out = []
    for i in range(boxes.shape[0]):
        if "logits" in named:
            raw = _from_logits(named["logits"][i], boxes[i], layout, input_size, where, num_classes)
        else:
            n = int(np.asarray(named["count"][i]).reshape(-1)[0]) if "count" in named else boxes.shape[1]
            raw = _plain(boxes[i][:n], named["scores"][i][:n], named["labels"][i][:n], layout, input_size, where,
                         num_classes)
        out.append(_finish(raw, layout, nms_iou, max_detections, where))
    return out


def _scale(boxes: np.ndarray, layout: Layout, input_size: tuple[int, int]) -> np.ndarray:
    b = to_xyxy(boxes, layout.box_format)
    if layout.normalized:
        h, w = input_size
        b *= np.array([w, h, w, h], np.float64)
    return b


def _check_classes(labels: np.ndarray, num_classes: int | None, layout: Layout, where: str) -> None:
    if num_classes is not None and len(labels) and (labels.min() < 0 or labels.max() >= num_classes):
        raise ModelError(f"{where}: the model gives class ids up to {int(labels.max())}, but its label space has "
                         f"{num_classes} classes (after the background slot of model.layout={layout.name}); set "
                         "model.labels= to the space it was trained on (coco, coco91, cityscapes or a TSV)")


def _plain(boxes, scores, labels, layout: Layout, input_size, where, num_classes) -> Raw:
    labels = np.asarray(labels).reshape(-1).astype(np.int64)
    scores = _activate(np.asarray(scores, np.float64).reshape(-1), layout.activation)
    if layout.background == "first":
        keep = labels > 0
        boxes, scores, labels = np.asarray(boxes).reshape(-1, 4)[keep], scores[keep], labels[keep] - 1
    _check_classes(labels, num_classes, layout, where)
    return Raw(_scale(boxes, layout, input_size), scores, labels)


def _from_logits(logits: np.ndarray, boxes: np.ndarray, layout: Layout, input_size, where, num_classes) -> Raw:
    probs = _activate(np.asarray(logits, np.float64), layout.activation)
    if layout.background == "last":
        probs = probs[:, :-1]
    elif layout.background == "first":
        probs = probs[:, 1:]
    if num_classes is not None and probs.shape[1] != num_classes:
        raise ModelError(f"{where}: the model scores {probs.shape[1]} classes (after the background slot of "
                         f"model.layout={layout.name}), but its label space has {num_classes}; set model.labels= to "
                         "the space it was trained on, or model.layout.background=")
    labels = probs.argmax(axis=1)
    return Raw(_scale(boxes, layout, input_size), probs[np.arange(len(labels)), labels], labels.astype(np.int64))


def _combined(out: np.ndarray, layout: Layout, input_size, where, num_classes, nms_iou, max_detections) -> list[Raw]:
    if out.ndim == 2:
        out = out[None]
    if layout.transposed:
        out = np.swapaxes(out, 1, 2)
    extra = 5 if layout.objectness else 4
    classes = out.shape[2] - extra
    if classes < 1 or (num_classes is not None and classes != num_classes):
        want = f"{extra} + {num_classes}" if num_classes is not None else f"more than {extra}"
        raise ModelError(f"{where}: the output {layout.outputs['combined']!r} has {out.shape[2]} values per box, "
                         f"model.layout={layout.name} with the label space needs {want}; check model.layout "
                         "(yolov5 has objectness, yolov8 has not) and model.labels")
    res = []
    for image in out:
        probs = _activate(image[:, extra:].astype(np.float64), layout.activation)
        if layout.objectness:
            probs = probs * _activate(image[:, 4:5].astype(np.float64), layout.activation)
        labels = probs.argmax(axis=1)
        raw = Raw(_scale(image[:, :4], layout, input_size), probs[np.arange(len(labels)), labels],
                  labels.astype(np.int64))
        res.append(_finish(raw, layout, nms_iou, max_detections, where))
    return res


def _finish(raw: Raw, layout: Layout, nms_iou: float, max_detections: int, where: str) -> Raw:
    """NMS per class where the graph has none, then the best `max_detections` by score."""
    boxes, scores, labels = raw.boxes, raw.scores, raw.labels
    if not (np.isfinite(boxes).all() and np.isfinite(scores).all()):
        raise ModelError(f"{where}: the model gave non-finite boxes or scores; check the input contract "
                         "(model.mean / model.std / model.scale) and model.layout")
    keep = scores > 1e-4  # candidates no one would rank (YOLO's thousands of anchors); COCO keeps 100 an image
    boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
    if not layout.nms and len(scores):
        import torch
        from torchvision.ops import batched_nms

        order = np.argsort(-scores, kind="stable")[: 30 * max_detections]
        boxes, scores, labels = boxes[order], scores[order], labels[order]
        kept = batched_nms(torch.from_numpy(boxes).float(), torch.from_numpy(scores).float(),
                           torch.from_numpy(labels), float(nms_iou)).numpy()
        boxes, scores, labels = boxes[kept], scores[kept], labels[kept]
    order = np.argsort(-scores, kind="stable")[:max_detections]
    return Raw(boxes[order], scores[order], labels[order])


__all__ = ["Layout", "PRESETS", "Raw", "check_outputs", "decode", "parse_layout", "required_roles", "to_xyxy"]
