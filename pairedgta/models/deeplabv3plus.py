"""DeepLabV3+ with a dilated ResNet backbone (output stride 16), laid out like the released VainF checkpoints.

The backbone is timm's ResNet (same parameter names as torchvision's; with `output_stride=16` the first block of
layer4 keeps dilation 1 and the others use 2, as torchvision's `replace_stride_with_dilation` does).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from timm.models.resnet import Bottleneck, ResNet
from torch import nn

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.errors import ConfigError

# The released weights (pairedgta/models/checkpoint.py: build_inproject names them when a config gives none); the
# input they expect is the shared input options' defaults (no padding, align_corners=False): no PRETRAINED here.
TRAINING_ONLY_PREFIXES: tuple[str, ...] = ()
CHECKPOINT_FILE = "best_deeplabv3plus_resnet101_cityscapes_os16.pth"
CHECKPOINT_SOURCE = "github.com/VainF/DeepLabV3Plus-Pytorch, README section Cityscapes pretrained models"


def _conv_bn_relu(cin: int, cout: int, kernel: int = 1, dilation: int = 1) -> list[nn.Module]:
    pad = dilation * (kernel // 2)
    return [nn.Conv2d(cin, cout, kernel, padding=pad, dilation=dilation, bias=False), nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True)]


class ASPPPooling(nn.Sequential):
    """Image-level branch: global average, 1x1 conv, broadcast back to the feature size."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(nn.AdaptiveAvgPool2d(1), *_conv_bn_relu(cin, cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(super().forward(x), size=x.shape[-2:], mode="bilinear", align_corners=False)


class ASPP(nn.Module):
    def __init__(self, cin: int, rates: Sequence[int], channels: int) -> None:
        super().__init__()
        branches: list[nn.Module] = [nn.Sequential(*_conv_bn_relu(cin, channels))]
        branches += [nn.Sequential(*_conv_bn_relu(cin, channels, 3, rate)) for rate in rates]
        branches.append(ASPPPooling(cin, channels))
        self.convs = nn.ModuleList(branches)
        self.project = nn.Sequential(*_conv_bn_relu(len(branches) * channels, channels), nn.Dropout(0.1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.project(torch.cat([branch(x) for branch in self.convs], dim=1))


class DeepLabV3PlusHead(nn.Module):
    """ASPP on the deep features, concatenated with a 1x1 projection of the stride-4 features, then 3x3 + 1x1."""

    def __init__(self, in_channels: int, low_level_in: int, num_classes: int, rates: Sequence[int], aspp_channels: int,
                 low_level_channels: int, decoder_channels: int) -> None:
        super().__init__()
        self.project = nn.Sequential(*_conv_bn_relu(low_level_in, low_level_channels))
        self.aspp = ASPP(in_channels, rates, aspp_channels)
        self.classifier = nn.Sequential(
            *_conv_bn_relu(low_level_channels + aspp_channels, decoder_channels, 3),
            nn.Conv2d(decoder_channels, num_classes, 1),
        )

    def forward(self, low_level: torch.Tensor, deep: torch.Tensor) -> torch.Tensor:
        low_level = self.project(low_level)
        deep = F.interpolate(self.aspp(deep), size=low_level.shape[-2:], mode="bilinear", align_corners=False)
        return self.classifier(torch.cat([low_level, deep], dim=1))


class DeepLabV3Plus(nn.Module):
    """Returns stride-4 logits; `backbone.*` and `classifier.*` are the released checkpoint's key prefixes."""

    def __init__(self, *, layers: Sequence[int], channels: Sequence[int], output_stride: int, rates: Sequence[int],
                 aspp_channels: int, low_level_channels: int, decoder_channels: int,
                 num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        self.backbone = ResNet(
            Bottleneck, tuple(layers), channels=tuple(channels), output_stride=output_stride, num_classes=0, global_pool="",
        )
        expansion = Bottleneck.expansion
        self.classifier = DeepLabV3PlusHead(
            channels[3] * expansion, channels[0] * expansion, num_classes, rates, aspp_channels,
            low_level_channels, decoder_channels,
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = self.backbone
        x = b.maxpool(b.act1(b.bn1(b.conv1(x))))
        low_level = b.layer1(x)
        deep = b.layer4(b.layer3(b.layer2(low_level)))
        return self.classifier(low_level, deep)


def architecture(name: str | None, augment: bool, *, layers: list = (3, 4, 23, 3),
                 backbone_channels: list = (64, 128, 256, 512), output_stride: int = 16, aspp_rates: list = (6, 12, 18),
                 aspp_channels: int = 256, low_level_channels: int = 48, decoder_channels: int = 256) -> DeepLabV3Plus:
    """The keyword-only arguments are this family's architecture keys in a pairedgta/conf/model YAML, with their
    one default (ResNet-101, output stride 16); the input options and the weights come from the shared builder
    (pairedgta/models/checkpoint.py: build_inproject, build_network). `augment` is accepted for symmetry with the
    other families: this graph has no training-only heads."""
    layers, channels, rates = list(layers), list(backbone_channels), list(aspp_rates)
    if len(layers) != 4 or len(channels) != 4:
        raise ConfigError(f"model '{name}': layers and backbone_channels must each list 4 values")
    if len(rates) != 3:
        raise ConfigError(f"model '{name}': aspp_rates must list 3 dilation rates, got {rates}")
    output_stride = int(output_stride)
    if output_stride not in (8, 16, 32):
        raise ConfigError(f"model '{name}': output_stride must be 8, 16 or 32, got {output_stride}")
    return DeepLabV3Plus(layers=layers, channels=channels, output_stride=output_stride, rates=rates,
                         aspp_channels=int(aspp_channels), low_level_channels=int(low_level_channels),
                         decoder_channels=int(decoder_channels))
