"""`task=detection model=export`: a torch.export program (.pt2 from torch.export.save) whose one input is a
B x 3 x H x W batch and whose outputs are a dict of named tensors (or a tuple, named output0, output1, ... in
order), decoded by `model.layout`.

Loading a .pt2 unpickles parts of it, so it runs code stored in the file: naming `model=export` is the user's choice
to do that. The file is identified by its zip entries first (pairedgta/models/sources/files.py): any other format is
one line naming the source that reads it, and is never unpickled."""
from __future__ import annotations

from typing import Any

from pairedgta.models.detector_contract import DetectorNetwork
from pairedgta.errors import ModelError


def _module(graph: Any, names: list[str] | None):
    import torch

    class ExportedDetector(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            object.__setattr__(self, "graph", graph)  # an exported module refuses .eval(); it runs as exported

        def train(self, mode: bool = True) -> "ExportedDetector":
            self.training = mode
            return self

        def forward(self, x: torch.Tensor) -> Any:
            return self.graph(x)

    return ExportedDetector()


def load(name: str, device: str, /, *, path: str | None = None) -> DetectorNetwork:
    from pairedgta.models.sources.export import _training_ops, load_program

    where = f"model ({name})"
    program, file = load_program(path, where)
    if len(program.graph_signature.user_inputs) != 1:
        raise ModelError(f"{where}: the program {file} takes {len(program.graph_signature.user_inputs)} inputs; "
                         "export it with one image batch: torch.export.export(model, (x,))")
    training = _training_ops(program)
    if training:
        raise ModelError(f"{where}: the program {file} was exported in training mode ({', '.join(training)}); call "
                         "model.eval() before torch.export.export")
    node = next(n for n in program.graph.nodes if n.op == "placeholder"
                and n.name == program.graph_signature.user_inputs[0])
    shape = tuple(getattr(node.meta.get("val"), "shape", ()))
    if len(shape) != 4:
        raise ModelError(f"{where}: the program {file} takes input of shape {list(shape)}, not B x 3 x H x W")
    h, w = shape[2], shape[3]
    fixed = (int(h), int(w)) if isinstance(h, int) and isinstance(w, int) else None
    return DetectorNetwork(_module(program.module(), None), fixed_size=fixed,
                           executes="code stored in the .pt2 (torch.export.load unpickles parts of it): model=export")
