"""`model=torchvision`: a builder of torchvision.models.segmentation with the user's weights (weights only).

The builders' outputs are a dict whose `out` is already at input size; the auxiliary head (`aux`) is a training
head: its weights are dropped from the checkpoint and its output never computed."""
from __future__ import annotations

from pairedgta.errors import ConfigError, ModelError
from pairedgta.models.contract import Network

ARCHS = ("deeplabv3_resnet50", "deeplabv3_resnet101", "deeplabv3_mobilenet_v3_large", "fcn_resnet50", "fcn_resnet101",
         "lraspp_mobilenet_v3_large")


def load(name: str, device: str, /, *, arch: str | None = None, num_classes: int | None = None,
         checkpoint_path: str | None = None) -> Network:
    """Build `arch` without any download (no pretrained backbone), then load `checkpoint_path` strictly."""
    num_classes = 19 if num_classes is None else num_classes
    if arch not in ARCHS:
        raise ConfigError(f"model ({name}): arch={arch!r} is not a torchvision segmentation builder; "
                          f"choose one of {', '.join(ARCHS)}, e.g. model.arch=deeplabv3_resnet50")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise ConfigError(f"model ({name}): num_classes={num_classes!r} must be the checkpoint's number of classes")
    if not checkpoint_path:
        raise ModelError(f"model ({name}): model=torchvision needs its weights; set model.checkpoint_path=<.pth or "
                         ".safetensors state dict>")
    import torchvision.models.segmentation as seg

    from pairedgta.models.checkpoint import load_checkpoint_strict

    kwargs = {"weights": None, "weights_backbone": None, "num_classes": num_classes}
    if arch != "lraspp_mobilenet_v3_large":
        kwargs["aux_loss"] = False
    module = getattr(seg, arch)(**kwargs)
    load_checkpoint_strict(module, checkpoint_path, training_only_prefixes=("aux_classifier.",), model_name=name)
    return Network(module)
