"""Tiny networks for the model-source tests: a user's own code, as `model=python model.target=source_nets:<fn>`
(the tests directory is on sys.path under pytest) and the same network exported to every other format."""
from __future__ import annotations

import torch


class TinyNet(torch.nn.Module):
    """Conv, stride-2 conv, 1x1 head: logits at half resolution (the contract upsamples), like most heads."""

    def __init__(self, width: int = 8, classes: int = 19) -> None:
        super().__init__()
        self.stem = torch.nn.Conv2d(3, width, 3, padding=1)
        self.down = torch.nn.Conv2d(width, width, 3, stride=2, padding=1)
        self.head = torch.nn.Conv2d(width, classes, 1)

    def forward(self, x):
        return self.head(torch.relu(self.down(torch.relu(self.stem(x)))))


class DictNet(TinyNet):
    """The same network answering as torchvision's do: a dict with `out` (and an `aux` to ignore)."""

    def forward(self, x):
        out = super().forward(x)
        return {"out": out, "aux": out[:, :1]}


def tiny_net(width: int = 8, classes: int = 19, seed: int = 0) -> TinyNet:
    torch.manual_seed(seed)
    return TinyNet(width, classes)


def dict_net(width: int = 8, classes: int = 19, seed: int = 0) -> DictNet:
    torch.manual_seed(seed)
    return DictNet(width, classes)


def not_a_module() -> str:
    return "a string"


def smp_unet(seed: int = 0):
    """A small segmentation_models_pytorch Unet (the smp source's network, as a user's own factory)."""
    import segmentation_models_pytorch as smp

    torch.manual_seed(seed)
    return smp.Unet("resnet18", encoder_weights=None, encoder_depth=3, decoder_channels=(32, 16, 8), classes=19)


def lraspp(seed: int = 0):
    """torchvision's smallest segmentation builder, answering with its dict (`out`)."""
    import torchvision.models.segmentation as tv

    torch.manual_seed(seed)
    return tv.lraspp_mobilenet_v3_large(weights=None, weights_backbone=None, num_classes=19)


def segformer(**arch):
    """A transformers SegFormer built from its config, as code of one's own would (output: `.logits`)."""
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    return SegformerForSemanticSegmentation(SegformerConfig(num_labels=19, **arch))


class Logits(torch.nn.Module):
    """A transformers model whose forward returns the logits tensor alone (what torch.export and ONNX hold)."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, x):
        return self.model(pixel_values=x).logits
