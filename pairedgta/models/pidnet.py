"""PIDNet (Xu et al. 2023), m=2 layout (PIDNet-S/M), as an in-project module matching the released state dict.

Three branches: I (context, the ResNet-like trunk), P (detail at 1/8, fused with I through pixel-attention
gates) and D (boundary at 1/8, whose sigmoid weighs P against I in the final fusion).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.errors import ConfigError
from pairedgta.models.ddrnet import (
    BasicBlock,
    Bottleneck,
    SegHead,
    bn_relu_conv,
    conv_bn,
    make_single_block,
    make_stage,
    pyramid_pools,
    resize,
    stem,
)

# The released weights (pairedgta/models/checkpoint.py: build_inproject names them when a config gives none).
TRAINING_ONLY_PREFIXES = ("seghead_p.", "seghead_d.")
CHECKPOINT_FILE = "PIDNet_M_Cityscapes_val.pt"
CHECKPOINT_SOURCE = "github.com/XuJiacong/PIDNet, README section Models / Cityscapes (PIDNet-M, val)"
# The input they expect, where it differs from the shared input options' defaults (build_inproject's signature),
# as timm's pretrained_cfg.
PRETRAINED = {
    "pad_multiple": 32,
    # the official evaluation upsamples the 1/8 logits with align_corners=True (its config default ALIGN_CORNERS)
    "upsample_align_corners": True,
}


class PagFM(nn.Module):
    """Pixel-attention-guided fusion: a per-pixel sigmoid similarity decides how much of y replaces x."""

    def __init__(self, in_channels: int, mid_channels: int) -> None:
        super().__init__()
        self.f_x = conv_bn(in_channels, mid_channels)
        self.f_y = conv_bn(in_channels, mid_channels)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        y_q = resize(self.f_y(y), size)
        sim = torch.sigmoid((self.f_x(x) * y_q).sum(dim=1, keepdim=True))
        return (1 - sim) * x + sim * resize(y, size)


class PAPPM(nn.Module):
    """Parallel variant of DAPPM: all pooled branches are refined at once by one grouped 3x3 convolution."""

    def __init__(self, inplanes: int, branch_planes: int, outplanes: int) -> None:
        super().__init__()
        for name, branch in pyramid_pools(inplanes, branch_planes).items():
            setattr(self, name, branch)
        self.scale_process = bn_relu_conv(branch_planes * 4, branch_planes * 4, 3, groups=4)
        self.compression = bn_relu_conv(branch_planes * 5, outplanes, 1)
        self.shortcut = bn_relu_conv(inplanes, outplanes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        base = self.scale0(x)
        pooled = [resize(getattr(self, f"scale{i}")(x), size) + base for i in range(1, 5)]
        refined = self.scale_process(torch.cat(pooled, dim=1))
        return self.compression(torch.cat([base, refined], dim=1)) + self.shortcut(x)


class LightBag(nn.Module):
    """Boundary-attention-guided fusion of the detail (p) and context (i) features."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv_p = conv_bn(in_channels, out_channels)
        self.conv_i = conv_bn(in_channels, out_channels)

    def forward(self, p: torch.Tensor, i: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        edge = torch.sigmoid(d)
        return self.conv_p((1 - edge) * i + p) + self.conv_i(i + edge * p)


class PIDNet(nn.Module):
    """Returns 1/8-resolution logits. `augment=True` adds the training-only heads (`seghead_p`, `seghead_d`)
    so the training layout can be compared with the released file; forward never runs them."""

    def __init__(self, *, m: int, n: int, planes: int, ppm_planes: int, head_planes: int,
                 num_classes: int = NUM_CLASSES, augment: bool = False) -> None:
        super().__init__()
        if m != 2:
            raise ValueError(f"only the m=2 layout (PIDNet-S/M) is implemented, got m={m}")
        # I branch
        self.conv1 = stem(planes)
        self.layer1 = make_stage(BasicBlock, planes, planes, m)
        self.layer2 = make_stage(BasicBlock, planes, planes * 2, m, stride=2)
        self.layer3 = make_stage(BasicBlock, planes * 2, planes * 4, n, stride=2)
        self.layer4 = make_stage(BasicBlock, planes * 4, planes * 8, n, stride=2)
        self.layer5 = make_stage(Bottleneck, planes * 8, planes * 8, 2, stride=2)
        # P branch
        self.compression3 = conv_bn(planes * 4, planes * 2)
        self.compression4 = conv_bn(planes * 8, planes * 2)
        self.pag3 = PagFM(planes * 2, planes)
        self.pag4 = PagFM(planes * 2, planes)
        self.layer3_ = make_stage(BasicBlock, planes * 2, planes * 2, m)
        self.layer4_ = make_stage(BasicBlock, planes * 2, planes * 2, m)
        self.layer5_ = make_stage(Bottleneck, planes * 2, planes * 2, 1)
        # D branch
        self.layer3_d = make_single_block(BasicBlock, planes * 2, planes)
        self.layer4_d = make_stage(Bottleneck, planes, planes, 1)
        self.diff3 = conv_bn(planes * 4, planes, 3)
        self.diff4 = conv_bn(planes * 8, planes * 2, 3)
        self.spp = PAPPM(planes * 16, ppm_planes, planes * 4)
        self.dfm = LightBag(planes * 4, planes * 4)
        self.layer5_d = make_stage(Bottleneck, planes * 2, planes * 2, 1)
        if augment:
            self.seghead_p = SegHead(planes * 2, head_planes, num_classes)
            self.seghead_d = SegHead(planes * 2, planes, 1)
        self.final_layer = SegHead(planes * 4, head_planes, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out_size = (x.shape[-2] // 8, x.shape[-1] // 8)
        x = self.layer1(self.conv1(x))
        x = F.relu(self.layer2(F.relu(x)))
        p = self.layer3_(x)
        d = self.layer3_d(x)

        x = F.relu(self.layer3(x))
        p = self.pag3(p, self.compression3(x))
        d = d + resize(self.diff3(x), out_size)

        x = F.relu(self.layer4(x))
        p = self.layer4_(F.relu(p))
        d = self.layer4_d(F.relu(d))
        p = self.pag4(p, self.compression4(x))
        d = d + resize(self.diff4(x), out_size)

        p = self.layer5_(F.relu(p))
        d = self.layer5_d(F.relu(d))
        x = resize(self.spp(self.layer5(x)), out_size)
        return self.final_layer(self.dfm(p, x, d))


def architecture(name: str | None, augment: bool, *, m: int = 2, n: int = 3, planes: int = 64, ppm_planes: int = 96,
                 head_planes: int = 128) -> PIDNet:
    """The keyword-only arguments are this family's architecture keys in a pairedgta/conf/model YAML, with their
    one default (PIDNet-M); the input options and the weights come from the shared builder
    (pairedgta/models/checkpoint.py: build_inproject, build_network)."""
    if int(m) != 2:
        raise ConfigError(f"model '{name}': m must be 2 (PIDNet-S/M layout; PIDNet-L is not implemented)")
    return PIDNet(m=int(m), n=int(n), planes=int(planes), ppm_planes=int(ppm_planes), head_planes=int(head_planes),
                  augment=augment)
