"""`task=detection model=python`: a factory in the user's own code (`model.target=package.module:function`, called
with `model.kwargs`) returning an `nn.Module`. By default it is a torchvision-style detector: it takes a list of
3 x H x W images in 0-1 and returns per image a dict of `boxes` (xyxy pixels), `scores`, `labels` (0 = background);
with another `model.layout` (e.g. detr) it takes the prepared batch and returns named outputs.

Naming `model=python` is the user's choice to run that code: it is imported and called, nothing else is. The weights
(`model.checkpoint_path`) load as data only (safetensors, or torch.load(weights_only=True)), keys matched exactly."""
from __future__ import annotations

from pairedgta.models.detector_contract import DetectorNetwork


def load(name: str, device: str, /, *, target: str | None = None, kwargs: dict | None = None,
         checkpoint_path: str | None = None) -> DetectorNetwork:
    from pairedgta.models.sources.python import build_module

    return DetectorNetwork(build_module(name, target, kwargs, checkpoint_path), declared={"layout": "torchvision"},
                           takes_list=None, executes=f"the user's code {target} (model=python)")
