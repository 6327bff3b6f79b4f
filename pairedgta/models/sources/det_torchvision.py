"""`task=detection model=torchvision`: a torchvision detection builder with the user's weights (weights only).

Built without any download (`weights=None, weights_backbone=None`). Without pretrained weights torchvision builds
plain BatchNorm2d where its released (and most fine-tuned) checkpoints hold FrozenBatchNorm2d, whose state has no
`num_batches_tracked`: a checkpoint without those buffers gets frozen batch norms, so its keys match exactly (both
compute the same in eval mode). Input: images in 0-1, normalised and resized inside the network; output: per image
boxes (xyxy pixels), scores, labels of `num_classes` ids with 0 the background (COCO's 91 by default)."""
from __future__ import annotations

from typing import Any

from pairedgta.models.detector_contract import DetectorNetwork
from pairedgta.errors import ConfigError, ModelError

ARCHS = ("fasterrcnn_resnet50_fpn", "fasterrcnn_resnet50_fpn_v2", "fasterrcnn_mobilenet_v3_large_fpn",
         "fasterrcnn_mobilenet_v3_large_320_fpn", "retinanet_resnet50_fpn", "retinanet_resnet50_fpn_v2",
         "fcos_resnet50_fpn", "ssd300_vgg16", "ssdlite320_mobilenet_v3_large")
FIXED_SIZE = ("ssd300_vgg16", "ssdlite320_mobilenet_v3_large")  # resize to 300 / 320 inside; no min/max size


def freeze_batch_norms(module: Any) -> Any:
    """Every BatchNorm2d replaced by torchvision's FrozenBatchNorm2d with the same statistics (eval-equivalent)."""
    import torch
    from torchvision.ops.misc import FrozenBatchNorm2d

    for name, child in list(module.named_children()):
        if isinstance(child, torch.nn.BatchNorm2d):
            frozen = FrozenBatchNorm2d(child.num_features, eps=child.eps)
            with torch.no_grad():
                for key in ("weight", "bias", "running_mean", "running_var"):
                    getattr(frozen, key).copy_(getattr(child, key))
            setattr(module, name, frozen)
        else:
            freeze_batch_norms(child)
    return module


def build(arch: Any, num_classes: Any, name: str, min_size: int | None = None, max_size: int | None = None) -> Any:
    if arch not in ARCHS:
        raise ConfigError(f"model ({name}): arch={arch!r} is not a torchvision detection builder; choose one of "
                          f"{', '.join(ARCHS)}, e.g. model.arch=fasterrcnn_mobilenet_v3_large_fpn")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 2:
        raise ConfigError(f"model ({name}): num_classes={num_classes!r} must be the checkpoint's number of classes, "
                          "background included (COCO: 91)")
    import torchvision.models.detection as det

    kwargs: dict[str, Any] = {"weights": None, "weights_backbone": None, "num_classes": num_classes}
    for key, value in (("min_size", min_size), ("max_size", max_size)):
        if value is not None:
            if arch in FIXED_SIZE:
                raise ConfigError(f"model ({name}): {arch} has a fixed input size; leave model.{key} unset")
            kwargs[key] = int(value)
    return getattr(det, arch)(**kwargs)


def load(name: str, device: str, /, *, arch: str | None = None, num_classes: int | None = None,
         checkpoint_path: str | None = None, min_size: int | None = None, max_size: int | None = None
         ) -> DetectorNetwork:
    """Build `arch` without any download, then load `checkpoint_path` strictly (weights only)."""
    num_classes = 91 if num_classes is None else num_classes
    if not checkpoint_path:
        raise ModelError(f"model ({name}): model=torchvision needs its weights; set model.checkpoint_path=<.pth or "
                         ".safetensors state dict>")
    from pairedgta.models.checkpoint import load_checkpoint_strict, read_state_dict

    module = build(arch, num_classes, name, min_size, max_size)
    state = read_state_dict(checkpoint_path, model_name=name)
    if not any(k.endswith("num_batches_tracked") for k in state):
        freeze_batch_norms(module)
    load_checkpoint_strict(module, checkpoint_path, model_name=name)
    return DetectorNetwork(module, declared={"layout": "torchvision", "labels": "coco91" if num_classes == 91 else None},
                           takes_list=True)
