"""`task=detection model=onnx`: an ONNX detector run by onnxruntime (pip install -e ".[onnx]").

The graph is data, checked as segmentation's ONNX source checks it (pairedgta/models/sources/onnx.py: external
data only from the model's folder, no custom-op library, explicit providers). Its outputs keep their names, which
`model.layout` reads (never their shapes). A graph whose input is one 3 x H x W image (torchvision's ONNX export of
a detector) is run image by image on 0-1 pixels, normalising inside; a B x 3 x H x W input gets the contract's
prepared batch, at the graph's fixed size when it has one."""
from __future__ import annotations

from typing import Any

import numpy as np

from pairedgta.models.detector_contract import DetectorNetwork
from pairedgta.errors import ModelError


def _module(session: Any, input_name: str, output_names: list[str], single: bool, batch: int | None):
    import torch

    class OnnxDetector(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()

        def run(self, x: np.ndarray) -> dict[str, torch.Tensor]:
            outs = session.run(output_names, {input_name: x.astype(np.float32)})
            return {n: torch.from_numpy(np.asarray(o)) for n, o in zip(output_names, outs)}

        def forward(self, x: Any) -> Any:
            if single:  # a list of 3 x H x W images: per image its dict of outputs
                return [self.run(im.detach().cpu().numpy()) for im in x]
            arr = x.detach().cpu().numpy()
            if batch is None or arr.shape[0] == batch:
                return self.run(arr)
            parts = [self.run(arr[i:i + 1]) for i in range(arr.shape[0])] if batch == 1 else None
            if parts is None:
                raise ModelError(f"the ONNX graph takes batches of exactly {batch}; export it with a dynamic batch "
                                 "or batch 1")
            return {n: torch.cat([p[n] for p in parts]) for n in output_names}

    return OnnxDetector()


def load(name: str, device: str, /, *, path: str | None = None) -> DetectorNetwork:
    from pairedgta.models.sources.onnx import one_input, open_session

    where = f"model ({name})"
    session, file = open_session(path, device, where)
    image = one_input(session, file, where, "detector")
    shape = list(image.shape or [])
    single = len(shape) == 3
    if len(shape) not in (3, 4) or (isinstance(shape[-3], int) and shape[-3] != 3):
        raise ModelError(f"{where}: ONNX input '{image.name}' of {file} is not an RGB image (shape {shape}); "
                         "export it with a B x 3 x H x W batch (or torchvision's one 3 x H x W image)")
    h, w = shape[-2], shape[-1]
    fixed = (h, w) if isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0 else None
    batch = shape[0] if not single and isinstance(shape[0], int) and shape[0] > 0 else None
    names = [o.name for o in session.get_outputs()]
    module = _module(session, image.name, names, single, batch)
    declared = {"layout": "torchvision"} if single else {}
    return DetectorNetwork(module, declared=declared, fixed_size=None if single else fixed, output_names=names,
                           takes_list=single, executes="onnxruntime graph, no Python code")
