"""The input/output contract every detector source shares (`task=detection model=<source>`), and their one builder.

A source (pairedgta/models/sources/det_*.py) only *loads* a network: it returns a `DetectorNetwork` whose module maps a
prepared batch to raw outputs, with what the file declares (a processor's mean/std and size, a graph's output names
and fixed size, the checkpoint's class names, its layout). Everything between the project's images (uint8 RGB, any
size) and `Detections` (xyxy pixels of the image, scores, Cityscapes instance classes) is here, the same for every
source:

  channel order -> resize (none, short side, fixed size stretched or letterboxed) -> scale (0-1 or 0-255) ->
  (x - mean) / std -> the network -> its layout decoded (pairedgta/models/detector_layouts.py; NMS where the graph has
  none) -> boxes back to the image's pixels -> the label space (pairedgta/models/detector_labels.py).

A network that takes torchvision's input (a list of C x H x W images in 0-1, normalising and resizing inside) gets
them as they are. A probe forward on a test image checks the outputs against the layout and the label space before
any stage writes."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from pairedgta.models import detector_labels as label_spaces
from pairedgta.models import detector_layouts as layouts
from pairedgta.cityscapes import INSTANCE_CLASSES
from pairedgta.models.detectors import KIND, Detections, image_batch
from pairedgta.errors import ConfigError, ModelError
from pairedgta.lazy import lazy_module
from pairedgta.models.contract import DEFAULT_SCORE_THRESHOLD, DETECTOR_OPTIONS, InputContract, probed
from pairedgta.models.runtime import RuntimeOptions

torch = lazy_module("torch")
F = lazy_module("torch.nn.functional")
log = logging.getLogger("pairedgta.detection")

# the keys every detector source has (model.<key>=, pairedgta.models.contract.DETECTOR_OPTIONS); null: what the file
# declares, else DEFAULTS
DEFAULTS: dict[str, Any] = {"mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0], "scale": 1, "channels": "rgb",
                            "resize": None, "letterbox": False, "layout": None, "labels": None,
                            "score_threshold": DEFAULT_SCORE_THRESHOLD, "nms_iou": 0.5, "max_detections": 100}
PROBE_SIZE = (256, 512)
LETTERBOX_FILL = 114 / 255  # the grey YOLO pads with


@dataclass
class DetectorNetwork:
    """What a source's loader returns. `module(x)`: a prepared B x 3 x h x w batch (or, with `takes_list`, a list of
    3 x h x w images in 0-1) -> raw outputs: per-image dicts, or a mapping name -> batched tensor."""

    module: Any
    declared: dict[str, Any] = field(default_factory=dict)  # contract keys the file sets (processor, layout, labels)
    id2label: Mapping[int, str] | None = None
    fixed_size: tuple[int, int] | None = None
    output_names: list[str] | None = None  # a graph's named outputs, checked against the layout
    # torchvision's detection input (a list of images in 0-1, normalised and resized inside); None: as the layout
    # says (per-image dicts out: a torchvision-style network)
    takes_list: bool | None = False
    executes: str = "nothing: weights only"


@dataclass(frozen=True)
class DetectionContract(InputContract):
    letterbox: bool
    layout: layouts.Layout
    score_threshold: float
    nms_iou: float
    max_detections: int

    def describe(self) -> str:
        size = ("native size" if self.resize is None else f"short side {self.resize}" if isinstance(self.resize, int)
                else f"{'letterboxed' if self.letterbox else 'resized'} to {self.resize[0]}x{self.resize[1]}")
        return (f"{self.channels.upper()} x{self.scale:g}, mean {list(self.mean)}, std {list(self.std)}, {size}; "
                f"layout {self.layout.describe()}; threshold {self.score_threshold:g}")


def _number(value: Any, key: str, where: str, low: float, high: float, example: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= float(value) <= high:
        raise ConfigError(f"{where}: {key}={value!r} must be a number in [{low:g}, {high:g}], e.g. {key}={example}")
    return float(value)


def make_contract(cfg: Mapping[str, Any], declared: Mapping[str, Any] | None = None,
                  where: str = "model") -> DetectionContract:
    from pairedgta.models.contract import _triple, image_keys, picker

    pick = picker(cfg, declared, DEFAULTS)
    scale, channels, resize = image_keys(pick, where)
    letterbox = pick("letterbox")
    if not isinstance(letterbox, bool):
        raise ConfigError(f"{where}: letterbox={letterbox!r} must be true or false")
    layout = pick("layout")
    layout = layout if isinstance(layout, layouts.Layout) else layouts.parse_layout(layout, where)
    max_det = pick("max_detections")
    if isinstance(max_det, bool) or not isinstance(max_det, int) or max_det < 1:
        raise ConfigError(f"{where}: max_detections={max_det!r} must be a whole number >= 1, e.g. 100")
    mean, std = (_triple(pick(k), k, where) for k in ("mean", "std"))
    return DetectionContract(mean, std, scale, channels, resize, letterbox, layout,
                             _number(pick("score_threshold"), "score_threshold", where, 0.0, 1.0, str(DEFAULT_SCORE_THRESHOLD)),
                             _number(pick("nms_iou"), "nms_iou", where, 0.0, 1.0, "0.5"), max_det)


def check_contract(cfg: Mapping[str, Any], where: str = "model", layout_default: str | None = None) -> None:
    """The contract keys and the label space, before any stage writes (no torch, no file but a label TSV)."""
    declared = {"layout": layout_default} if layout_default and cfg.get("layout") is None else {}
    if cfg.get("layout") is not None or declared:
        make_contract(cfg, declared, where)
    if cfg.get("labels") is not None:
        label_spaces.resolve(cfg.get("labels"), None, where)


class ContractDetector:
    """Any detector under the shared contract: uint8 RGB images in, `Detections` of the instance classes out."""

    kind = KIND

    def __init__(self, name: str, network: DetectorNetwork, contract: DetectionContract,
                 labels: label_spaces.DetectionLabels, runtime: RuntimeOptions, source: str) -> None:
        from pairedgta.models.base import resolve_device

        self.name, self.network, self.contract, self.labels, self.source = name, network, contract, labels, source
        self.runtime = runtime
        self.device = resolve_device(runtime.device)
        module = network.module
        if hasattr(module, "to"):
            module = module.to(self.device)
        if hasattr(module, "eval"):
            module = module.eval()
        self.module = module
        self.score_threshold = contract.score_threshold
        self.blind = labels.blind  # the instance classes it cannot predict: NaN with the reason, never 0

    def prepare(self, x: "torch.Tensor") -> tuple["torch.Tensor", Callable[[np.ndarray], np.ndarray]]:
        """A B x 3 x H x W batch in 0-1 -> the network's input and the map of its pixel boxes back to the image's."""
        c = self.contract
        h, w = x.shape[-2:]
        if c.channels == "bgr":
            x = x.flip(1)
        size = self.network.fixed_size or _size(c.resize, h, w)
        back: Callable[[np.ndarray], np.ndarray] = lambda b: b  # noqa: E731
        if tuple(size) != (h, w):
            if c.letterbox and not isinstance(c.resize, int):
                x, back = _letterbox(x, size)
            else:
                x = F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False, antialias=True)
                sy, sx = h / size[0], w / size[1]
                back = lambda b: b * np.array([sx, sy, sx, sy])  # noqa: E731
        if self.network.takes_list:
            return x, back
        if c.scale != 1:
            x = x * c.scale
        if tuple(c.mean) == (0.0, 0.0, 0.0) and tuple(c.std) == (1.0, 1.0, 1.0):
            return x, back  # YOLO's and most exports' input: two whole-batch passes saved
        mean = torch.tensor(c.mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        std = torch.tensor(c.std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        return (x - mean) / std, back

    def forward(self, x: "torch.Tensor") -> list[layouts.Raw]:
        """Raw detections (the model's class ids, the image's pixels) of a batch in 0-1."""
        c = self.contract
        h, w = x.shape[-2:]
        y, back = self.prepare(x)
        with torch.inference_mode():
            out = self.module(list(y) if self.network.takes_list else y)
        if c.layout.kind == "tensors" and not isinstance(out, Mapping):
            out = named_outputs(out, self.where)
        if isinstance(out, Mapping):
            layouts.check_outputs(c.layout, [str(k) for k in out], self.where)
        raws = layouts.decode(out, c.layout, tuple(y.shape[-2:]), self.where, self.labels.num_classes, c.nms_iou,
                              c.max_detections)
        return [self._checked(layouts.Raw(back(r.boxes), r.scores, r.labels), h, w) for r in raws]

    @property
    def where(self) -> str:
        return f"model ({self.name})"

    def _checked(self, raw: layouts.Raw, h: int, w: int) -> layouts.Raw:
        """Boxes must be finite and near the image: else the layout (normalised or pixels, box format) is wrong."""
        if not (np.isfinite(raw.boxes).all() and np.isfinite(raw.scores).all()):
            raise ModelError(f"{self.where}: the model gave non-finite boxes or scores; check the input contract "
                             "(model.mean / model.std / model.scale) and model.layout")
        if len(raw.boxes):
            far = (raw.boxes[:, [0, 2]].min() < -0.5 * w or raw.boxes[:, [0, 2]].max() > 1.5 * w
                   or raw.boxes[:, [1, 3]].min() < -0.5 * h or raw.boxes[:, [1, 3]].max() > 1.5 * h)
            if far:
                raise ModelError(
                    f"{self.where}: the model's boxes lie far outside the {w}x{h} image (e.g. "
                    f"{np.round(raw.boxes[0], 1).tolist()}); model.layout={self.contract.layout.name} reads them as "
                    f"{self.contract.layout.box_format} {'normalised' if self.contract.layout.normalized else 'pixels'}"
                    ": set model.layout.normalized / box_format to what the model gives")
        boxes = raw.boxes.copy()
        boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, w)
        boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, h)
        return layouts.Raw(boxes, raw.scores, raw.labels)

    def detect(self, images: np.ndarray) -> list[Detections]:
        images = image_batch(images, self.name)
        out: list[Detections] = []
        for i in range(0, len(images), self.runtime.batch_size):
            chunk = np.ascontiguousarray(images[i:i + self.runtime.batch_size])
            x = torch.from_numpy(chunk if chunk.flags.writeable else chunk.copy()).to(self.device)
            for raw in self.forward(x.permute(0, 3, 1, 2).float().div_(255.0)):
                mapped = self.labels.apply(raw.labels) if len(raw.labels) else raw.labels
                keep = mapped >= 0
                order = np.argsort(-raw.scores[keep], kind="stable")
                out.append(Detections(raw.boxes[keep][order].astype(np.float32),
                                      raw.scores[keep][order].astype(np.float32), mapped[keep][order]))
        return out

    def probe(self) -> None:
        """One forward on a test image: the outputs fit the layout and the label space, the boxes are sane."""
        yy, xx = np.mgrid[0:PROBE_SIZE[0], 0:PROBE_SIZE[1]]
        image = np.stack([(xx * 255 // PROBE_SIZE[1]), (yy * 255 // PROBE_SIZE[0]),
                          ((xx + yy) % 64) * 4], axis=-1).astype(np.uint8)
        self.detect(image[None])

    def __repr__(self) -> str:
        return f"ContractDetector({self.name}, {self.source}, {self.contract.describe()})"


def named_outputs(out: Any, where: str) -> dict[str, Any]:
    """A network's outputs by name: a dict as it is; a tensor is `output0`, a tuple `output0`, `output1`, ... in order
    (the names ONNX exporters give by default), which model.layout.outputs can then name."""
    if isinstance(out, Mapping):
        return dict(out)
    if isinstance(out, torch.Tensor):
        return {"output0": out}
    if isinstance(out, (list, tuple)) and all(isinstance(o, torch.Tensor) for o in out):
        return {f"output{i}": o for i, o in enumerate(out)}
    raise ModelError(f"{where}: the network returned {type(out).__name__}, not tensors; return a dict of named "
                     "tensors, a tensor or a tuple of them (named output0, output1, ... for model.layout.outputs)")


def _size(resize: int | tuple[int, int] | None, h: int, w: int) -> tuple[int, int]:
    from pairedgta.models.contract import resized_size

    return resized_size(resize, h, w)


def _letterbox(x: "torch.Tensor", size: tuple[int, int]):
    """Fit the image into `size` keeping its aspect ratio, centred on YOLO's grey; the map of boxes back."""
    h, w = x.shape[-2:]
    r = min(size[0] / h, size[1] / w)
    nh, nw = max(1, round(h * r)), max(1, round(w * r))
    top, left = (size[0] - nh) // 2, (size[1] - nw) // 2
    canvas = x.new_full((x.shape[0], 3, *size), LETTERBOX_FILL)
    canvas[..., top:top + nh, left:left + nw] = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False,
                                                              antialias=True)
    return canvas, lambda b: (b - np.array([left, top, left, top])) / r


def build_detector_source(loader: Callable[..., DetectorNetwork], /, *, name: str | None = None, family: str,
                          mean: list | None = None, std: list | None = None, scale: int | None = None,
                          channels: str | None = None, resize: Any = None, letterbox: bool | None = None,
                          layout: Any = None, labels: str | None = None, score_threshold: float | None = None,
                          nms_iou: float | None = None, max_detections: int | None = None,
                          runtime: RuntimeOptions, **own: Any) -> ContractDetector:
    """The one builder of the detector sources (registered `via` it): the source's `load(name, device, **own)` gives
    the network, the contract and the label space are made here, and a probe forward checks them."""
    name = str(name or family)
    where = f"model ({name})"
    source = family.removeprefix("det_")
    try:
        network = loader(name, str(runtime.device), **own)
    except ImportError as exc:
        raise ConfigError(f"model={source} needs the Python package '{exc.name}', which is not installed; "
                          f"pip install -e \".[{source}]\"") from None
    cfg = {"mean": mean, "std": std, "scale": scale, "channels": channels, "resize": resize, "letterbox": letterbox,
           "layout": layout, "score_threshold": score_threshold, "nms_iou": nms_iou, "max_detections": max_detections}
    contract = make_contract(cfg, network.declared, where)
    if network.takes_list is None:
        network.takes_list = contract.layout.kind == "dicts"
    space = label_spaces.resolve(labels, network.id2label, where, network.declared.get("labels"))
    if len(space.blind) == len(INSTANCE_CLASSES):
        raise ConfigError(f"{where}: none of the classes of model.labels={space.space} is a Cityscapes instance class "
                          f"({', '.join(INSTANCE_CLASSES)}); is model.labels the space the model was trained on?")
    det = ContractDetector(name, network, contract, space, runtime, source)
    log.info("model %s (task=detection model=%s): loading ran %s; %s; labels: %s", name, source, network.executes,
             contract.describe(), space.describe())
    probed(det, where, "model.resize")
    return det


__all__ = ["DETECTOR_OPTIONS", "ContractDetector", "DEFAULTS", "DetectionContract", "DetectorNetwork",
           "build_detector_source", "check_contract", "make_contract"]
