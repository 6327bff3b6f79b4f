"""The input/output contract every model source shares, in one place, and the one builder of the sources.

A source (pairedgta/models/source_*.py, one registry line each in pairedgta/models/__init__.py) only *loads* a
network: it returns a `Network`, a torch module that maps a prepared input batch to the model's raw output, with what
the file itself declares (an image processor's mean/std, a checkpoint's class names, an ONNX graph's fixed size).
Everything between the project's images (RGB in [0, 1], any size) and the metrics' 19 Cityscapes probabilities at
that size is here, the same for every source:

  channel order (rgb/bgr) -> resize (none, short side, fixed) -> scale (0-1 or 0-255) -> (x - mean) / std ->
  pad to a multiple -> whole image or sliding window (crop, stride; MMSegmentation's `slide`) -> crop the padding
  -> upsample to the input size -> softmax of logits (or the model's probabilities) -> the label map.

A key left null takes what the file declares, else the contract's default (DEFAULTS). Torch-free at import: the
config check (`check_contract`) runs before anything is built."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from pairedgta.errors import ConfigError, ModelError, reason
from pairedgta.lazy import lazy_module
from pairedgta.models.base import Segmenter, logsumexp_classes
from pairedgta.models.labels import LabelMap, fit_outputs, resolve_labels
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD, RuntimeOptions

torch = lazy_module("torch")
F = lazy_module("torch.nn.functional")
log = logging.getLogger("pairedgta.models")

# The keys every source has (model.<key>=), with their defaults where neither the config nor the file says.
CONTRACT_OPTIONS = ("mean", "std", "scale", "channels", "resize", "pad_multiple", "inference", "crop", "stride",
                    "output", "labels")
DEFAULTS: dict[str, Any] = {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD), "scale": 1, "channels": "rgb",
                            "resize": None, "pad_multiple": 1, "inference": "whole", "crop": None, "stride": None,
                            "output": "logits", "labels": "cityscapes"}
# A detector source's keys (pairedgta/models/detector_contract.py reads them): the input keys, its output layout and
# label space, and its operating point; declared here so the model registry lists them without importing detection.
DETECTOR_OPTIONS = ("mean", "std", "scale", "channels", "resize", "letterbox", "layout", "labels", "score_threshold",
                    "nms_iou", "max_detections")
DEFAULT_SCORE_THRESHOLD = 0.5  # a detector's operating point where its config gives none (sources and zoo alike)
PROBE_SIZE = (256, 512)  # the probe forward's image (height, width): the main job's (a program may guard smaller sizes)


@dataclass
class Network:
    """What a source's loader returns: `module(x)` maps a prepared B x 3 x h x w float batch to the raw output (a
    tensor, a dict with `out` or `logits`, or an object with `.logits`)."""

    module: "torch.nn.Module"
    declared: dict[str, Any] = field(default_factory=dict)  # contract keys the file itself sets (processor, graph)
    id2label: Mapping[int, str] | None = None               # the checkpoint's own class names, by channel
    fixed_size: tuple[int, int] | None = None               # an input size the network only accepts (ONNX)
    executes: str = "nothing: weights only"                 # what loading it ran, for the log and docs


@dataclass(frozen=True)
class InputContract:
    """How an image becomes a network's input, for every model source of either kind (segmenters here, detectors in
    pairedgta/models/detector_contract.py add their letterbox, layout and operating point)."""

    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    scale: float
    channels: str
    resize: int | tuple[int, int] | None


@dataclass(frozen=True)
class Contract(InputContract):
    pad_multiple: int
    inference: str
    crop: tuple[int, int] | None
    stride: tuple[int, int] | None
    output: str

    def describe(self) -> str:
        size = ("native size" if self.resize is None else f"short side {self.resize}" if isinstance(self.resize, int)
                else f"resized to {self.resize[0]}x{self.resize[1]}")
        how = "whole image" if self.inference == "whole" else f"sliding {self.crop} crops, stride {self.stride}"
        return (f"{self.channels.upper()} x{self.scale:g}, mean {list(self.mean)}, std {list(self.std)}, {size}, "
                f"pad to {self.pad_multiple}, {how}, {self.output}")


# -- the config check ------------------------------------------------------------------------------------------
def _pair(value: Any, key: str, where: str) -> tuple[int, int] | None:
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool):
        value = [value, value]
    if (isinstance(value, (list, tuple)) and len(value) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)):
        return int(value[0]), int(value[1])
    raise ConfigError(f"{where}: {key}={value!r} must be a size in pixels, one number or [height, width], "
                      f"e.g. {key}=[512,1024]")


def _triple(value: Any, key: str, where: str) -> tuple[float, float, float]:
    ok = (isinstance(value, (list, tuple)) and len(value) == 3
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value))
    if not ok or (key == "std" and min(value) <= 0):
        raise ConfigError(f"{where}: {key}={value!r} must be 3 numbers{' > 0' if key == 'std' else ''}, one per "
                          f"channel in model.scale's units, e.g. {key}={DEFAULTS[key]}")
    return float(value[0]), float(value[1]), float(value[2])


def picker(cfg: Mapping[str, Any], declared: Mapping[str, Any] | None, defaults: Mapping[str, Any]) -> Any:
    """key -> the config's value, else what the file declares, else the default (segmenters' and detectors')."""
    declared = declared or {}

    def pick(key: str) -> Any:
        value = cfg.get(key)
        return value if value is not None else declared.get(key, defaults[key])
    return pick


def image_keys(pick: Any, where: str) -> tuple[float, str, int | tuple[int, int] | None]:
    """(scale, channels, resize), checked: the input keys every source shares, segmenter or detector."""
    scale = pick("scale")
    if scale not in (1, 255, 1.0, 255.0) or isinstance(scale, bool):
        raise ConfigError(f"{where}: scale={scale!r} must be 1 (input in 0-1) or 255 (input in 0-255)")
    channels = str(pick("channels")).lower()
    if channels not in ("rgb", "bgr"):
        raise ConfigError(f"{where}: channels={channels!r} must be rgb or bgr")
    resize = pick("resize")
    if isinstance(resize, str) and resize.lower() == "none":
        resize = None
    if resize is not None:
        if isinstance(resize, int) and not isinstance(resize, bool) and resize > 0:
            resize = int(resize)
        else:
            resize = _pair(resize, "resize", where)
    return float(scale), channels, resize


def make_contract(cfg: Mapping[str, Any], declared: Mapping[str, Any] | None = None, where: str = "model") -> Contract:
    """The effective contract: the config's key, else what the file declares, else DEFAULTS; each checked."""
    pick = picker(cfg, declared, DEFAULTS)
    scale, channels, resize = image_keys(pick, where)
    pad = pick("pad_multiple")
    if isinstance(pad, bool) or not isinstance(pad, int) or pad < 1:
        raise ConfigError(f"{where}: pad_multiple={pad!r} must be a whole number >= 1, e.g. pad_multiple=32")
    inference = str(pick("inference"))
    if inference not in ("whole", "slide"):
        raise ConfigError(f"{where}: inference={inference!r} must be whole or slide (with crop and stride)")
    crop, stride = _pair(pick("crop"), "crop", where), _pair(pick("stride"), "stride", where)
    if inference == "slide" and crop is None:
        raise ConfigError(f"{where}: inference=slide needs the crop the model was trained on, e.g. crop=[512,1024]")
    if inference == "slide" and stride is None:
        stride = (max(1, crop[0] * 2 // 3), max(1, crop[1] * 2 // 3))  # MMSegmentation's usual overlap of a third
    output = str(pick("output"))
    if output not in ("logits", "probabilities"):
        raise ConfigError(f"{where}: output={output!r} must be logits or probabilities")
    return Contract(_triple(pick("mean"), "mean", where), _triple(pick("std"), "std", where), scale, channels,
                    resize, pad, inference, crop, stride, output)


def check_contract(cfg: Mapping[str, Any], where: str = "model") -> None:
    """Every contract key and the label space, before any stage writes (no torch, no file but a label TSV)."""
    make_contract(cfg, None, where)
    resolve_labels(cfg.get("labels"), where=where)


# -- the segmenter ------------------------------------------------------------------------------------------------
def resized_size(resize: int | tuple[int, int] | None, h: int, w: int) -> tuple[int, int]:
    if resize is None:
        return h, w
    if isinstance(resize, int):
        s = resize / min(h, w)
        return max(1, round(h * s)), max(1, round(w * s))
    return resize


def raw_output(out: Any, where: str) -> "torch.Tensor":
    """The score tensor of a forward's output: a tensor, `out` / `logits` of a dict, `.logits`, or the first of a
    tuple (torchvision's `aux` and a training head's extra outputs are ignored)."""
    if isinstance(out, Mapping):
        for key in ("out", "logits"):
            if key in out:
                return raw_output(out[key], where)
        raise ModelError(f"{where}: the model returned a dict without 'out' or 'logits' (keys: {', '.join(map(str, out))}); "
                         "return the score tensor, or a dict with 'out'")
    if hasattr(out, "logits") and not isinstance(out, torch.Tensor):
        return raw_output(out.logits, where)
    if isinstance(out, (tuple, list)) and out:
        return raw_output(out[0], where)
    if not isinstance(out, torch.Tensor):
        raise ModelError(f"{where}: the model returned {type(out).__name__}, not a tensor; return B x C x H x W scores")
    return out


class ContractSegmenter(Segmenter):
    """Any network under the shared contract and label map: RGB [0, 1] in, 19 Cityscapes probabilities out."""

    def __init__(self, name: str, network: Network, contract: Contract, labels: LabelMap,
                 runtime: RuntimeOptions, source: str) -> None:
        super().__init__(name, network.module, runtime)
        self.network, self.contract, self.labels, self.source = network, contract, labels, source
        self._mean = torch.tensor(contract.mean, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(contract.std, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    # the steps, each its own method so that the model check can try alternatives on one of them
    def prepare(self, images: "torch.Tensor") -> "torch.Tensor":
        c = self.contract
        x = images.float()
        if c.channels == "bgr":
            x = x.flip(1)
        size = resized_size(c.resize, *x.shape[-2:])
        if size != tuple(x.shape[-2:]):
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
        if c.scale != 1:
            x = x * c.scale
        return (x - self._mean) / self._std

    def _run(self, x: "torch.Tensor") -> "torch.Tensor":
        """One forward on a prepared batch (padded to pad_multiple, or to the network's fixed size) -> raw scores at
        x's size, checked: 4-D, finite shape, one channel per class of the label space."""
        h, w = x.shape[-2:]
        fixed = self.network.fixed_size
        if fixed is not None and (h, w) != tuple(fixed):
            y = F.interpolate(x, size=fixed, mode="bilinear", align_corners=False)  # the graph's only size
        else:
            m = self.contract.pad_multiple
            y = F.pad(x, (0, -w % m, 0, -h % m)) if m > 1 else x
        if self.channels_last:
            y = y.contiguous(memory_format=torch.channels_last)
        out = raw_output(self.module(y), self.name)
        if out.ndim != 4:
            raise ModelError(f"{self.name}: the model's output has shape {tuple(out.shape)}, not B x C x H x W; "
                             "return per-pixel class scores")
        out = fit_check(self, out)
        if fixed is not None and (h, w) != tuple(fixed):
            return F.interpolate(out.float(), size=(h, w), mode="bilinear", align_corners=False)
        ph, pw = y.shape[-2:]
        if tuple(out.shape[-2:]) != (ph, pw):
            out = F.interpolate(out.float(), size=(ph, pw), mode="bilinear", align_corners=False)
        return out[..., :h, :w]

    def _slide(self, x: "torch.Tensor") -> "torch.Tensor":
        """MMSegmentation's sliding window: crops of `crop` every `stride` (the last one flush with the border), the
        scores of overlapping crops averaged; an image smaller than a crop is one padded window."""
        (ch, cw), (sh, sw) = self.contract.crop, self.contract.stride
        h, w = x.shape[-2:]
        rows = max(h - ch + sh - 1, 0) // sh + 1
        cols = max(w - cw + sw - 1, 0) // sw + 1
        total = count = None
        for r in range(rows):
            for c in range(cols):
                y1, x1 = r * sh, c * sw
                y2, x2 = min(y1 + ch, h), min(x1 + cw, w)
                y1, x1 = max(y2 - ch, 0), max(x2 - cw, 0)
                crop = x[..., y1:y2, x1:x2]
                ph, pw = ch - crop.shape[-2], cw - crop.shape[-1]
                out = self._run(F.pad(crop, (0, max(pw, 0), 0, max(ph, 0))) if ph > 0 or pw > 0 else crop)
                out = out[..., : y2 - y1, : x2 - x1].float()
                if total is None:
                    total = x.new_zeros((x.shape[0], out.shape[1], h, w))
                    count = x.new_zeros((1, 1, h, w))
                total[..., y1:y2, x1:x2] += out
                count[..., y1:y2, x1:x2] += 1
        return total / count

    def scores(self, images: "torch.Tensor") -> "torch.Tensor":
        """The network's raw scores (logits or probabilities, as many channels as its label space) at input size."""
        return self.scores_prepared(self.prepare(images), tuple(images.shape[-2:]))

    def scores_prepared(self, x: "torch.Tensor", size: tuple[int, int]) -> "torch.Tensor":
        """`scores` of a batch `prepare` made (the set-up check stacks several contracts' preparations of an image)."""
        out = self._slide(x) if self.contract.inference == "slide" else self._run(x)
        if tuple(out.shape[-2:]) != tuple(size):
            out = F.interpolate(out.float(), size=size, mode="bilinear", align_corners=False)
        return out.float()

    def distribution(self, out: "torch.Tensor") -> "torch.Tensor":
        """Raw scores -> probabilities over the model's own classes (before the label map)."""
        if self.contract.output == "logits":
            return out.softmax(dim=1)
        probs = out.clamp_min(0)
        return probs / probs.sum(dim=1, keepdim=True).clamp_min(1e-12)

    def _scores(self, images: "torch.Tensor", energy: bool = False):
        out = self.scores(images)
        lse = logsumexp_classes(out) if energy and self.contract.output == "logits" else None
        return self.labels.apply(self.distribution(out)), lse

    def _logits(self, images: "torch.Tensor") -> "torch.Tensor":  # pragma: no cover - _scores replaces it
        return self.scores(images)

    def _probabilities(self, images: "torch.Tensor") -> "torch.Tensor":
        return self._scores(images)[0]

    def probe(self) -> None:
        """One forward on a small image before any stage writes: a wrong output (not 4-D, another channel count
        than the label space, not finite) is the one-line error now, not after the scenes are rendered."""
        h, w = self.network.fixed_size or PROBE_SIZE
        if self.contract.inference == "slide":
            h, w = max(h, self.contract.crop[0]), max(w, self.contract.crop[1])
        x = torch.linspace(0, 1, 3 * h * w).view(1, 3, h, w)
        probs = self.predict_proba(x)  # raises ModelError on a non-finite output
        if probs.shape != (1, 19, h, w):
            raise ModelError(f"{self.name}: probe output {tuple(probs.shape)}, expected (1, 19, {h}, {w})")


def fit_check(seg: ContractSegmenter, out: "torch.Tensor") -> "torch.Tensor":
    """The channel count against the label space, once (Vistas' 65-class head is fitted then)."""
    if out.shape[1] != seg.labels.num_outputs:
        seg.labels = fit_outputs(seg.labels, int(out.shape[1]), seg.name)
    return out


def probed(model: Any, where: str, keys: str) -> None:
    """A source model's probe forward (either kind): a forward that fails on any input means the network or its
    contract is wrong, one line naming the contract `keys` to check; the project's own errors pass as they are."""
    try:
        model.probe()
    except (ModelError, ConfigError):
        raise
    except Exception as exc:
        raise ModelError(f"{where}: a forward on a {PROBE_SIZE[1]}x{PROBE_SIZE[0]} test image failed "
                         f"({reason(exc)[:300]}); check {keys} and the input the model expects") from None


def build_source(loader, /, *, name: str | None = None, family: str, mean: list | None = None, std: list | None = None,
                 scale: int | None = None, channels: str | None = None, resize: Any = None,
                 pad_multiple: int | None = None, inference: str | None = None, crop: Any = None, stride: Any = None,
                 output: str | None = None, labels: str | None = None, runtime: RuntimeOptions, **own: Any
                 ) -> ContractSegmenter:
    """The one builder of the model sources (registered `via` it): the source's `load(name, device, **own)` gives the
    network, then the contract and the label map are made here, the same for every source, and checked by a probe."""
    name = str(name or family)
    where = f"model ({name})"
    try:
        network = loader(name, str(runtime.device), **own)
    except ImportError as exc:
        raise ConfigError(f"model={family} needs the Python package '{exc.name}', which is not installed; "
                          f"pip install -e \".[{family}]\"") from None
    cfg = {"mean": mean, "std": std, "scale": scale, "channels": channels, "resize": resize,
           "pad_multiple": pad_multiple, "inference": inference, "crop": crop, "stride": stride, "output": output}
    contract = make_contract(cfg, network.declared, where)
    label_map = resolve_labels(labels, id2label=network.id2label, where=where)
    seg = ContractSegmenter(name, network, contract, label_map, runtime, family)
    log.info("model %s (model=%s): loading ran %s; input %s; labels: %s", name, family, network.executes,
             contract.describe(), label_map.describe())
    probed(seg, where, "model.resize / model.pad_multiple")
    return seg


__all__ = ["Network", "Contract", "ContractSegmenter", "build_source", "probed", "make_contract", "check_contract",
           "CONTRACT_OPTIONS", "DEFAULTS", "InputContract", "DEFAULT_SCORE_THRESHOLD", "DETECTOR_OPTIONS"]
