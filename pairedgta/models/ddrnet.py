"""DDRNet-23 (Hong et al. 2021) as an in-project module whose state-dict layout equals the released graph.

The residual blocks, segmentation head and DAPPM here are shared with PIDNet, whose official code uses the same
layout. Module attribute names and Sequential indices are load-bearing: they are the checkpoint keys.
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.errors import ConfigError

# The released weights (pairedgta/models/checkpoint.py: build_inproject names them when a config gives none).
TRAINING_ONLY_PREFIXES = ("seghead_extra.",)
CHECKPOINT_FILE = "the DDRNet_23 Cityscapes weights, val mIoU 79.5"
CHECKPOINT_SOURCE = "github.com/ydhongHIT/DDRNet, README section Pretrained models / Cityscapes (Google Drive)"
# The input they expect, where it differs from the shared input options' defaults (build_inproject's signature),
# as timm's pretrained_cfg. upsample_align_corners keeps the shared false: the authors keep align_corners=False
# everywhere for their weights.
PRETRAINED = {"pad_multiple": 32}


def resize(x: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    return F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False)


def conv_bn(cin: int, cout: int, kernel: int = 1, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=False), nn.BatchNorm2d(cout)
    )


def bn_relu_conv(cin: int, cout: int, kernel: int = 1, *, groups: int = 1, pool: nn.Module | None = None) -> nn.Sequential:
    """Pre-activation unit; the optional pooling comes first, so indices shift by one (as in the released files)."""
    layers: list[nn.Module] = [] if pool is None else [pool]
    layers += [
        nn.BatchNorm2d(cin),
        nn.ReLU(inplace=True),
        nn.Conv2d(cin, cout, kernel, padding=kernel // 2, groups=groups, bias=False),
    ]
    return nn.Sequential(*layers)


def stem(planes: int) -> nn.Sequential:
    """Two stride-2 3x3 convolutions (with bias) to 1/4 resolution."""
    return nn.Sequential(
        nn.Conv2d(3, planes, 3, stride=2, padding=1),
        nn.BatchNorm2d(planes),
        nn.ReLU(inplace=True),
        nn.Conv2d(planes, planes, 3, stride=2, padding=1),
        nn.BatchNorm2d(planes),
        nn.ReLU(inplace=True),
    )


class BasicBlock(nn.Module):
    expansion = 1
    default_relu_out = True

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None,
                 relu_out: bool | None = None) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample
        self.relu_out = self.default_relu_out if relu_out is None else relu_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        out = self.bn2(self.conv2(out))
        out = out + (x if self.downsample is None else self.downsample(x))
        return F.relu(out, inplace=True) if self.relu_out else out


class Bottleneck(nn.Module):
    """Expansion 2 (not ResNet's 4); by default the output is left without ReLU, as in the released graphs."""

    expansion = 2
    default_relu_out = False

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None,
                 relu_out: bool | None = None) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * self.expansion, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.downsample = downsample
        self.relu_out = self.default_relu_out if relu_out is None else relu_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        out = F.relu(self.bn2(self.conv2(out)), inplace=True)
        out = self.bn3(self.conv3(out))
        out = out + (x if self.downsample is None else self.downsample(x))
        return F.relu(out, inplace=True) if self.relu_out else out


def make_stage(block: type, inplanes: int, planes: int, blocks: int, stride: int = 1) -> nn.Sequential:
    """First block keeps the block's default output activation, the last of several has none, middle ones ReLU."""
    outplanes = planes * block.expansion
    downsample = conv_bn(inplanes, outplanes, 1, stride) if stride != 1 or inplanes != outplanes else None
    layers = [block(inplanes, planes, stride, downsample)]
    for i in range(1, blocks):
        layers.append(block(outplanes, planes, 1, None, relu_out=i < blocks - 1))
    return nn.Sequential(*layers)


def make_single_block(block: type, inplanes: int, planes: int, stride: int = 1) -> nn.Module:
    outplanes = planes * block.expansion
    downsample = conv_bn(inplanes, outplanes, 1, stride) if stride != 1 or inplanes != outplanes else None
    return block(inplanes, planes, stride, downsample, relu_out=False)


class SegHead(nn.Module):
    def __init__(self, inplanes: int, interplanes: int, outplanes: int) -> None:
        super().__init__()
        self.bn1 = nn.BatchNorm2d(inplanes)
        self.conv1 = nn.Conv2d(inplanes, interplanes, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(interplanes)
        self.conv2 = nn.Conv2d(interplanes, outplanes, 1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv1(F.relu(self.bn1(x)))
        return self.conv2(F.relu(self.bn2(x)))


def pyramid_pools(inplanes: int, branch_planes: int) -> dict[str, nn.Sequential]:
    """scale1..3: strided average pools (5/2, 9/4, 17/8); scale4: global; scale0: identity."""
    pools = {
        "scale1": nn.AvgPool2d(5, stride=2, padding=2),
        "scale2": nn.AvgPool2d(9, stride=4, padding=4),
        "scale3": nn.AvgPool2d(17, stride=8, padding=8),
        "scale4": nn.AdaptiveAvgPool2d((1, 1)),
    }
    branches = {name: bn_relu_conv(inplanes, branch_planes, 1, pool=pool) for name, pool in pools.items()}
    branches["scale0"] = bn_relu_conv(inplanes, branch_planes, 1)
    return branches


class DAPPM(nn.Module):
    """Deep aggregation pyramid pooling: each coarser branch is refined after adding the previous one."""

    def __init__(self, inplanes: int, branch_planes: int, outplanes: int) -> None:
        super().__init__()
        for name, branch in pyramid_pools(inplanes, branch_planes).items():
            setattr(self, name, branch)
        for i in range(1, 5):
            setattr(self, f"process{i}", bn_relu_conv(branch_planes, branch_planes, 3))
        self.compression = bn_relu_conv(branch_planes * 5, outplanes, 1)
        self.shortcut = bn_relu_conv(inplanes, outplanes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        outs = [self.scale0(x)]
        for i in range(1, 5):
            pooled = resize(getattr(self, f"scale{i}")(x), size)
            outs.append(getattr(self, f"process{i}")(pooled + outs[-1]))
        return self.compression(torch.cat(outs, dim=1)) + self.shortcut(x)


class DDRNet(nn.Module):
    """Dual-resolution network; returns 1/8-resolution logits. `augment=True` adds the training-only head
    (`seghead_extra`) so the training layout can be compared with the released file; forward never runs it."""

    def __init__(self, *, layers: Sequence[int], planes: int, spp_planes: int, head_planes: int,
                 num_classes: int = NUM_CLASSES, augment: bool = False) -> None:
        super().__init__()
        high = planes * 2
        self.conv1 = stem(planes)
        self.layer1 = make_stage(BasicBlock, planes, planes, layers[0])
        self.layer2 = make_stage(BasicBlock, planes, planes * 2, layers[1], stride=2)
        self.layer3 = make_stage(BasicBlock, planes * 2, planes * 4, layers[2], stride=2)
        self.layer4 = make_stage(BasicBlock, planes * 4, planes * 8, layers[3], stride=2)
        self.compression3 = conv_bn(planes * 4, high)
        self.compression4 = conv_bn(planes * 8, high)
        self.down3 = conv_bn(high, planes * 4, 3, stride=2)
        self.down4 = nn.Sequential(
            nn.Conv2d(high, planes * 4, 3, stride=2, padding=1, bias=False),
            nn.BatchNorm2d(planes * 4),
            nn.ReLU(inplace=True),
            nn.Conv2d(planes * 4, planes * 8, 3, stride=2, padding=1, bias=False),
            nn.BatchNorm2d(planes * 8),
        )
        self.layer3_ = make_stage(BasicBlock, planes * 2, high, 2)
        self.layer4_ = make_stage(BasicBlock, high, high, 2)
        self.layer5_ = make_stage(Bottleneck, high, high, 1)
        self.layer5 = make_stage(Bottleneck, planes * 8, planes * 8, 1, stride=2)
        self.spp = DAPPM(planes * 16, spp_planes, planes * 4)
        if augment:
            self.seghead_extra = SegHead(high, head_planes, num_classes)
        self.final_layer = SegHead(planes * 4, head_planes, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out_size = (x.shape[-2] // 8, x.shape[-1] // 8)
        c1 = self.layer1(self.conv1(x))
        c2 = self.layer2(F.relu(c1))
        c3 = self.layer3(F.relu(c2))
        # low-resolution (context) branch: x; high-resolution (detail) branch at 1/8: hi
        hi = self.layer3_(F.relu(c2))
        x = c3 + self.down3(F.relu(hi))
        hi = hi + resize(self.compression3(F.relu(c3)), out_size)
        c4 = self.layer4(F.relu(x))
        hi = self.layer4_(F.relu(hi))
        x = c4 + self.down4(F.relu(hi))
        hi = hi + resize(self.compression4(F.relu(c4)), out_size)
        hi = self.layer5_(F.relu(hi))
        x = resize(self.spp(self.layer5(F.relu(x))), out_size)
        return self.final_layer(x + hi)


def architecture(name: str | None, augment: bool, *, layers: list = (2, 2, 2, 2), planes: int = 64,
                 spp_planes: int = 128, head_planes: int = 128) -> DDRNet:
    """The keyword-only arguments are this family's architecture keys in a pairedgta/conf/model YAML, with their
    one default (DDRNet-23); the input options and the weights come from the shared builder
    (pairedgta/models/checkpoint.py: build_inproject, build_network)."""
    layers = list(layers)
    if len(layers) != 4:
        raise ConfigError(f"model '{name}': layers must list 4 block counts, got {layers}")
    return DDRNet(layers=layers, planes=int(planes), spp_planes=int(spp_planes), head_planes=int(head_planes),
                  augment=augment)
