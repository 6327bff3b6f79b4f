"""Shared loading and preprocessing for the transformers families (SegFormer, Mask2Former) and `model=hf`."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ModelError, reason
from pairedgta.lazy import lazy_module
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD

torch = lazy_module("torch")  # the weights fingerprint of a cached run reads paths here, not tensors
F = lazy_module("torch.nn.functional")

log = logging.getLogger(__name__)

PACKAGE_DIR = Path(__file__).resolve().parents[1]


def _load_error_types() -> tuple[type[BaseException], ...]:
    """What a damaged or hostile weights folder raises inside from_pretrained: I/O and format errors,
    safetensors' header errors, a truncated or refused pickle (weights_only), a bad config.json."""
    import pickle

    types: list[type[BaseException]] = [OSError, ValueError, EOFError, RuntimeError, KeyError, TypeError,
                                        pickle.UnpicklingError]
    try:
        from safetensors import SafetensorError

        types.append(SafetensorError)
    except ImportError:  # pragma: no cover - safetensors ships with transformers
        pass
    return tuple(types)


_LOAD_ERRORS = _load_error_types()


# the detection zoo ships as a distribution of its own (zoo/detection): both zoos in one wheel pass 100 MB
DETECTION_ZOO = "pairedgta-detection-zoo"
DETECTION_ZOO_SOURCE = "zoo/detection/pairedgta_detection_zoo"  # its package in a checkout, beside pairedgta/
DETECTION_ZOO_INSTALL = (f"pip install {DETECTION_ZOO}, or from a checkout pip install -e ./zoo/detection (README's "
                         "install line installs both)")


def detection_zoo_dir() -> Path | None:
    """The detection zoo's member folders: the source tree's beside a checkout's package (so a checkout runs
    without installing it, and never another checkout's), else the installed companion distribution's."""
    checkout = PACKAGE_DIR.parent / DETECTION_ZOO_SOURCE
    if checkout.is_dir():
        return checkout
    import importlib.util

    spec = importlib.util.find_spec("pairedgta_detection_zoo")
    return Path(spec.origin).parent if spec is not None and spec.origin else None


def resolve_checkpoint_path(path: str | Path) -> Path:
    """`pkg://models/weights/<name>/...` is a zoo member's file: inside the package (the segmentation zoo), else
    in the detection zoo's distribution (`detection_zoo_dir`); the path strings, and so the cache keys, are the
    same for both. Torch-free: the stage keys fingerprint such files on every run, a cached one included."""
    text = str(path)
    if not text.startswith("pkg://"):
        return Path(text).expanduser()
    rel = Path(text[len("pkg://"):])
    inside = PACKAGE_DIR / rel
    if inside.exists() or rel.parts[:2] != ("models", "weights") or len(rel.parts) < 3:
        return inside
    zoo = detection_zoo_dir()
    elsewhere = zoo / Path(*rel.parts[2:]) if zoo is not None else None
    return elsewhere if elsewhere is not None and elsewhere.exists() else inside


def check_zoo_path(path: str | Path, model_name: str | None) -> None:
    """A `pkg://` zoo file that is nowhere: one line naming the detection zoo's distribution and how to install
    it (the usual cause: the package installed without its companion), instead of a bare missing path."""
    text = str(path)
    if text.startswith("pkg://models/weights/") and not resolve_checkpoint_path(text).exists():
        raise ModelError(
            f"model '{model_name}': {text} is in neither the pairedgta package nor an installed {DETECTION_ZOO} "
            f"(the detection zoo's weights, a distribution of their own); install it: {DETECTION_ZOO_INSTALL}"
        )


def pretrained_source(cfg: dict[str, Any]) -> str:
    path = cfg.get("path")
    if path and str(path).startswith("pkg://"):
        # weights shipped with the package (the demo models): no network, no cache
        check_zoo_path(path, cfg.get("name"))
        path = str(resolve_checkpoint_path(path))
    if path:
        if not Path(path).is_dir():
            raise ModelError(
                f"model.path={path} is not a directory; point it at a folder with config.json and the weights"
            )
        return str(path)
    hub_id = cfg.get("hub_id")
    if not hub_id:
        raise ModelError(f"model '{cfg.get('name')}' has neither model.hub_id nor model.path; set one of them")
    return str(hub_id)


def guarded_pretrained(cfg: dict[str, Any], load: Callable[[str], Any]) -> Any:
    """`load(source)` (a from_pretrained) with a damaged folder or an unreachable hub id as one line that names
    model.path or the hub id and the fix; shared by the transformers families and `model=hf`."""
    source = pretrained_source(cfg)
    try:
        return load(source)
    except _LOAD_ERRORS as exc:
        if cfg.get("path"):
            # a local folder whose files are corrupt, truncated or a refused pickle: say which, whole
            raise ModelError(
                f"model '{cfg.get('name')}': cannot load the weights in model.path={source} ({reason(exc)}); "
                "replace them with an intact safetensors export of the model"
            ) from None
        revision = f" --revision {cfg['revision']}" if cfg.get("revision") else ""
        raise ModelError(
            f"model '{cfg.get('name')}': cannot load '{source}' ({reason(exc)}); offline, download the hub id "
            f"'{cfg.get('hub_id')}' elsewhere (huggingface-cli download {cfg.get('hub_id')}{revision} --local-dir DIR) "
            "and pass model.path=DIR"
        ) from None


def load_pretrained(model_cls: Any, cfg: dict[str, Any]) -> Any:
    model = guarded_pretrained(cfg, model_cls.from_pretrained)
    check_label_space(model.config, cfg)
    return model


def query_class_scores(class_logits: torch.Tensor, mask_logits: torch.Tensor) -> torch.Tensor:
    """Mask2Former's semantic inference, for every query-based model (Mask2Former, MaskFormer, OneFormer):
    sum_q softmax(class_q)[:-1] * sigmoid(mask_q), B x K x h x w at the masks' resolution, float32. The last class
    is "no object"; the caller renormalises over the K classes after upsampling (the result is no distribution)."""
    cls = class_logits.float().softmax(dim=-1)[..., :-1]
    masks = mask_logits.float().sigmoid()
    # under model.amp the einsum runs in bf16/fp16; the distribution is upsampled and normalised in float32
    return torch.einsum("bqk,bqhw->bkhw", cls, masks).float()


def check_label_space(config: Any, cfg: dict[str, Any]) -> None:
    """A checkpoint with another label space would silently produce meaningless class ids."""
    num = int(getattr(config, "num_labels", len(getattr(config, "id2label", {}) or {})))
    if num != len(CLASS_NAMES):
        raise ModelError(
            f"model '{cfg.get('name')}' predicts {num} classes, not the 19 Cityscapes train ids; "
            "use a Cityscapes-finetuned checkpoint"
        )


def preprocess_params(cfg: dict[str, Any]) -> dict[str, Any]:
    """mean/std/resize/size_divisor from the model's image processor, overridable in the config."""
    params: dict[str, Any] = {
        "mean": IMAGENET_MEAN, "std": IMAGENET_STD, "size": None, "size_divisor": cfg.get("size_divisor"),
    }
    if not cfg["random_init"] and cfg["preprocess"] == "processor":  # cfg: a family builder's arguments
        try:
            from transformers import AutoImageProcessor

            proc = AutoImageProcessor.from_pretrained(pretrained_source(cfg))
            params["mean"] = tuple(getattr(proc, "image_mean", IMAGENET_MEAN))
            params["std"] = tuple(getattr(proc, "image_std", IMAGENET_STD))
            if getattr(proc, "do_resize", False):
                params["size"] = dict(getattr(proc, "size", {}) or {}) or None
            if getattr(proc, "size_divisor", None):
                params["size_divisor"] = int(proc.size_divisor)
        except (OSError, ValueError) as exc:
            log.warning("model %s: no image processor found (%s); using ImageNet mean/std", cfg.get("name"), exc)
    if cfg.get("mean") is not None:
        params["mean"] = tuple(cfg["mean"])
    if cfg.get("std") is not None:
        params["std"] = tuple(cfg["std"])
    resize = cfg.get("resize")
    if resize is False or resize == "none":
        params["size"] = None
    elif isinstance(resize, (list, tuple)):
        params["size"] = {"height": int(resize[0]), "width": int(resize[1])}
    elif isinstance(resize, dict):
        params["size"] = dict(resize)
    return params


def target_size(size: dict[str, Any] | None, h: int, w: int) -> tuple[int, int]:
    if not size:
        return h, w
    if "height" in size and "width" in size:
        return int(size["height"]), int(size["width"])
    if "shortest_edge" in size:
        scale = size["shortest_edge"] / min(h, w)
        if size.get("longest_edge"):
            scale = min(scale, size["longest_edge"] / max(h, w))
        return max(1, round(h * scale)), max(1, round(w * scale))
    raise ModelError(f"unsupported image-processor size {size}; set model.resize=[H, W] or model.resize=none")


class Preprocessor:
    """RGB [0,1] -> resized, normalised tensor, as the image processor would (done in torch, batched)."""

    def __init__(self, params: dict[str, Any]) -> None:
        self.mean = torch.tensor(params["mean"]).view(1, 3, 1, 1)
        self.std = torch.tensor(params["std"]).view(1, 3, 1, 1)
        self.size = params["size"]
        self.size_divisor = params.get("size_divisor")

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        h, w = images.shape[-2:]
        th, tw = target_size(self.size, h, w)
        if (th, tw) != (h, w):
            images = F.interpolate(images, size=(th, tw), mode="bilinear", align_corners=False, antialias=True)
        if self.mean.device != images.device or self.mean.dtype != images.dtype:
            # once, not per batch: a copy from pageable host memory would wait for the GPU's queue
            self.mean, self.std = self.mean.to(images), self.std.to(images)
        return (images - self.mean) / self.std

    def pad(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        h, w = x.shape[-2:]
        d = self.size_divisor
        if not d:
            return x, (h, w)
        ph, pw = (-h) % d, (-w) % d
        return F.pad(x, (0, pw, 0, ph)), (h, w)
