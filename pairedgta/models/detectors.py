"""Detectors: torchvision's detection heads (FCOS, RetinaNet, Faster R-CNN) on a small MobileNetV3 trunk with an
FPN from stride 8, built without any download (no ImageNet weights exist offline; the zoo is trained here), and one
wrapper that runs them under the project's contract: uint8 RGB images in, per image xyxy pixel boxes, scores and
Cityscapes instance classes (pairedgta/cityscapes.py INSTANCE_CLASSES) out.

Each head is a model family registered `via` `build_detector` (pairedgta/models/__init__.py, kind "detector"):
the keyword-only arguments of `fcos`, `retinanet`, `fasterrcnn` are its architecture keys in a
pairedgta/conf/model YAML, `build_detector`'s are the ones every detector has. The renders are 512x256, where the
main job's people and cars are 20 px tall at the median: `min_size` (512 by default) makes the network see them
twice as large, at the forward's cost and not the renderer's (docs/detection.md "Render size")."""
from __future__ import annotations

import logging
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np

from pairedgta.cityscapes import INSTANCE_CLASSES, NUM_INSTANCE_CLASSES
from pairedgta.lazy import lazy_module
from pairedgta.models.contract import DEFAULT_SCORE_THRESHOLD
from pairedgta.models.runtime import RuntimeOptions

torch = lazy_module("torch")
log = logging.getLogger("pairedgta.detection")
NUM_CLASSES = NUM_INSTANCE_CLASSES + 1  # torchvision's convention: label 0 is background, 1..8 the classes
IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]
KIND = "detector"


class Detections(NamedTuple):
    """One image's detections: boxes (K, 4) xyxy pixels of the input image, scores (K,), labels (K,) indices of
    INSTANCE_CLASSES; sorted by score, highest first."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray

    @staticmethod
    def empty() -> "Detections":
        return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))

    def above(self, threshold: float) -> "Detections":
        keep = self.scores >= threshold
        return Detections(self.boxes[keep], self.scores[keep], self.labels[keep])


def _trunk(width: float) -> Any:
    """MobileNetV3-Large's features at `width`, returning strides 8, 16 and 32 to an FPN."""
    from torchvision.models import mobilenet_v3_large

    features = mobilenet_v3_large(weights=None, width_mult=float(width)).features
    ends, stride, size = [], 1, 64
    x = torch.zeros(1, 3, size, size)
    with torch.no_grad():
        for i, block in enumerate(features):
            x = block(x)
            s = size // x.shape[-1]
            if s != stride and i > 0:
                ends.append((stride, i - 1))
            stride = s
        ends.append((stride, len(features) - 1))
    picked = [(i, s) for s, i in ends if s in (8, 16, 32)]
    channels = []
    x = torch.zeros(1, 3, size, size)
    with torch.no_grad():
        for i, block in enumerate(features):
            x = block(x)
            if any(i == j for j, _ in picked):
                channels.append(int(x.shape[1]))
    return features, {str(i): str(k) for k, (i, _) in enumerate(picked)}, channels


def _backbone(width: float, fpn_channels: int, extra: str) -> Any:
    from torchvision.models.detection.backbone_utils import BackboneWithFPN
    from torchvision.ops.feature_pyramid_network import LastLevelMaxPool, LastLevelP6P7

    features, returns, channels = _trunk(width)
    blocks = LastLevelP6P7(fpn_channels, fpn_channels) if extra == "p6p7" else LastLevelMaxPool()
    return BackboneWithFPN(features, returns, channels, fpn_channels, extra_blocks=blocks)


def fcos(name: str | None, num_classes: int, min_size: int, max_size: int, /, *, width: float = 0.5,
         fpn_channels: int = 64, center_sampling_radius: float = 1.5) -> Any:
    """FCOS (anchor-free, one stage) on P3-P7; its head's GroupNorm needs fpn_channels in multiples of 32."""
    from pairedgta.errors import ConfigError

    if int(fpn_channels) % 32:
        raise ConfigError(f"model ({name}): fpn_channels={fpn_channels} must be a multiple of 32 for fcos (its head's "
                          "GroupNorm has 32 groups), e.g. fpn_channels=64")
    from torchvision.models.detection import FCOS
    from torchvision.models.detection.anchor_utils import AnchorGenerator

    anchors = AnchorGenerator(sizes=((8,), (16,), (32,), (64,), (128,)), aspect_ratios=((1.0,),) * 5)
    return FCOS(_backbone(width, fpn_channels, "p6p7"), num_classes, min_size=min_size, max_size=max_size,
                image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD, anchor_generator=anchors,
                center_sampling_radius=float(center_sampling_radius), score_thresh=0.05, detections_per_img=100)


def retinanet(name: str | None, num_classes: int, min_size: int, max_size: int, /, *, width: float = 0.5,
              fpn_channels: int = 64, smallest_anchor: int = 16) -> Any:
    """RetinaNet (anchors, focal loss, one stage) on P3-P7, anchors from `smallest_anchor` px."""
    from torchvision.models.detection import RetinaNet
    from torchvision.models.detection.anchor_utils import AnchorGenerator

    base = [int(smallest_anchor) * 2 ** k for k in range(5)]
    anchors = AnchorGenerator(sizes=tuple((s, int(s * 2 ** (1 / 3)), int(s * 2 ** (2 / 3))) for s in base),
                              aspect_ratios=((0.5, 1.0, 2.0),) * 5)
    return RetinaNet(_backbone(width, fpn_channels, "p6p7"), num_classes, min_size=min_size, max_size=max_size,
                     image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD, anchor_generator=anchors, score_thresh=0.05,
                     detections_per_img=100)


def fasterrcnn(name: str | None, num_classes: int, min_size: int, max_size: int, /, *, width: float = 0.5,
               fpn_channels: int = 64, smallest_anchor: int = 16) -> Any:
    """Faster R-CNN (region proposals, two stages) on P3-P5 and a max-pooled level."""
    from torchvision.models.detection import FasterRCNN
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.ops import MultiScaleRoIAlign

    base = [int(smallest_anchor) * 2 ** k for k in range(4)]
    anchors = AnchorGenerator(sizes=tuple((s,) for s in base), aspect_ratios=((0.5, 1.0, 2.0),) * 4)
    pool = MultiScaleRoIAlign(featmap_names=["0", "1", "2"], output_size=7, sampling_ratio=2)
    return FasterRCNN(_backbone(width, fpn_channels, "maxpool"), num_classes, min_size=min_size, max_size=max_size,
                      image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD, rpn_anchor_generator=anchors,
                      box_roi_pool=pool, box_score_thresh=0.05, box_detections_per_img=100,
                      representation_size=256 if fpn_channels >= 64 else 128)


def image_batch(images: Any, name: str) -> np.ndarray:
    """N x H x W x 3 uint8 (one image gets its batch axis); anything else is a ValueError naming the detector."""
    images = np.asarray(images)
    if images.ndim == 3:
        images = images[None]
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"detector {name}: expected uint8 images N x H x W x 3, got {images.dtype} {images.shape}")
    return images


class Detector:
    """A detector under the project's contract; `detect` runs batches of `runtime.batch_size` in eval mode."""

    kind = KIND

    def __init__(self, name: str, module: Any, score_threshold: float, runtime: RuntimeOptions | None = None) -> None:
        from pairedgta.models.base import resolve_device

        self.name = name
        self.runtime = runtime or RuntimeOptions()
        self.device = resolve_device(self.runtime.device)
        self.module = module.to(self.device).eval()
        self.score_threshold = float(score_threshold)  # the operating threshold of detection xi

    def raw(self, images: np.ndarray) -> list[dict[str, Any]]:
        """torchvision's output dicts for a batch of uint8 HxWx3 images (no threshold beyond the head's own)."""
        arr = np.ascontiguousarray(images)
        x = torch.from_numpy(arr if arr.flags.writeable else arr.copy()).to(self.device)
        x = x.permute(0, 3, 1, 2).float().div_(255.0)
        with torch.inference_mode():
            return self.module(list(x))

    def detect(self, images: np.ndarray) -> list[Detections]:
        images = image_batch(images, self.name)
        out: list[Detections] = []
        for i in range(0, len(images), self.runtime.batch_size):
            for d in self.raw(images[i:i + self.runtime.batch_size]):
                scores = d["scores"].float().cpu().numpy()
                order = np.argsort(-scores, kind="stable")
                labels = d["labels"].cpu().numpy().astype(np.int64) - 1  # background 0 -> classes 0..7
                keep = order[(labels[order] >= 0) & (labels[order] < NUM_INSTANCE_CLASSES)]
                out.append(Detections(d["boxes"].float().cpu().numpy()[keep].astype(np.float32),
                                      scores[keep].astype(np.float32), labels[keep]))
        return out

    def __repr__(self) -> str:
        return f"Detector({self.name}, {type(self.module).__name__}, threshold {self.score_threshold})"


def check_options(cfg: Mapping[str, Any], where: str) -> None:
    """A zoo detector's own keys, checked with the run's config before any stage computes (a wrong threshold found
    only at evaluate would come after minutes of rendering and pseudo-labelling)."""
    from pairedgta.errors import ConfigError

    threshold = cfg.get("score_threshold", DEFAULT_SCORE_THRESHOLD)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0.0 <= threshold <= 1.0:
        raise ConfigError(f"{where}: score_threshold={threshold!r} must be in [0, 1], e.g. "
                          f"model.score_threshold={DEFAULT_SCORE_THRESHOLD}")
    for key, example in (("min_size", 512), ("max_size", 1024)):
        value = cfg.get(key, example)
        if isinstance(value, bool) or not isinstance(value, int) or value < 32:
            raise ConfigError(f"{where}: {key}={value!r} must be a whole number of pixels >= 32, e.g. "
                              f"model.{key}={example}")
    if cfg.get("max_size", 1024) < cfg.get("min_size", 512):
        raise ConfigError(f"{where}: max_size={cfg.get('max_size')} is below min_size={cfg.get('min_size')}; set "
                          "model.max_size >= model.min_size")


def build_detector(network: Callable[..., Any], /, *, name: str, family: str, checkpoint_path: str | None = None,
                   random_init: bool = False, init_seed: int = 0, score_threshold: float = DEFAULT_SCORE_THRESHOLD,
                   min_size: int = 512,
                   max_size: int = 1024, runtime: RuntimeOptions, **arch: Any) -> Detector:
    """The one builder of the detector families: seeds, constructs, loads the weights strictly (safetensors,
    weights only), wraps. `score_threshold` is the model's operating point (a box at or above it counts as found)."""
    from pairedgta.errors import ModelError
    from pairedgta.models.checkpoint import load_checkpoint_strict

    name = str(name or family)
    check_options({"score_threshold": score_threshold, "min_size": min_size, "max_size": max_size}, f"model ({name})")
    if not checkpoint_path and not random_init:
        raise ModelError(f"model '{name}' has no weights: set model.checkpoint_path=<file.safetensors> "
                         "(or model.random_init=true for an untrained network)")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(init_seed))
        module = network(name, NUM_CLASSES, int(min_size), int(max_size), **arch)
    if checkpoint_path:
        check_classes(module, checkpoint_path, name)
        load_checkpoint_strict(module, checkpoint_path, model_name=name)
    return Detector(name, module, float(score_threshold), runtime)


CLASS_KEYS = ("head.classification_head.cls_logits.weight", "roi_heads.box_predictor.cls_score.weight")


def check_classes(module: Any, checkpoint_path: str, name: str) -> None:
    """A checkpoint whose class layer is of another size (COCO's 91, a head of its own) is one line naming both."""
    from pairedgta.errors import ModelError
    from pairedgta.models.checkpoint import read_state_dict
    state = read_state_dict(checkpoint_path, model_name=name)  # resolves a pkg:// path (package or detection zoo)
    expected = module.state_dict()
    for key in CLASS_KEYS:
        if key in state and key in expected and state[key].shape[0] != expected[key].shape[0]:
            per_class = expected[key].shape[0] // NUM_CLASSES
            raise ModelError(
                f"model '{name}': {checkpoint_path} predicts {state[key].shape[0] // per_class} classes "
                f"({key}), the detection task's detectors {NUM_CLASSES} (background + {', '.join(INSTANCE_CLASSES)}); "
                "train it on these classes or load it through a detector source with a label map")


def build_network(family: str, cfg: dict[str, Any]) -> Any:
    """The torch module a detector config describes (training: experiments/train_demo_detector.py)."""
    import inspect

    network = {"fcos": fcos, "retinanet": retinanet, "fasterrcnn": fasterrcnn}[family]
    keys = [p.name for p in inspect.signature(network).parameters.values()
            if p.kind is p.KEYWORD_ONLY]
    return network(cfg.get("name"), NUM_CLASSES, int(cfg.get("min_size", 512)), int(cfg.get("max_size", 1024)),
                   **{k: cfg[k] for k in keys if k in cfg})


def is_detector(obj: Any) -> bool:
    return getattr(obj, "kind", None) == KIND


__all__ = ["Detections", "Detector", "KIND", "NUM_CLASSES", "build_detector", "build_network", "fasterrcnn", "fcos",
           "is_detector", "retinanet"]
