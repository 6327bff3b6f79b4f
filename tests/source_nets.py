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
