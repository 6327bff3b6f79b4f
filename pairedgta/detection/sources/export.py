"""`task=detection model=export`: a torch.export program (.pt2 from torch.export.save) whose one input is a
B x 3 x H x W batch and whose outputs are a dict of named tensors (or a tuple, named output0, output1, ... in
order), decoded by `model.layout`.

Loading a .pt2 unpickles parts of it, so it runs code stored in the file: naming `model=export` is the user's choice
to do that. The file is identified by its zip entries first (pairedgta/models/sources/files.py): any other format is
one line naming the source that reads it, and is never unpickled."""
from __future__ import annotations

import logging
from typing import Any

from pairedgta.detection.contract import DetectorNetwork
from pairedgta.errors import ModelError, reason


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
    import torch

    from pairedgta.models.sources.export import _training_ops
    from pairedgta.models.sources.files import identify, model_file, wrong_format

    where = f"model ({name})"
    file = model_file(path, where, "export", "<file.pt2 from torch.export.save>")
    kind = identify(file)
    if kind != "pt2":
        raise wrong_format(file, kind, where, "a torch.export program (a .pt2 zip from torch.export.save)")
    quiet = logging.getLogger("torch.export")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    try:
        program = torch.export.load(str(file))
    except Exception as exc:
        raise ModelError(f"{where}: torch {torch.__version__} cannot load the program {file} ({reason(exc)[:300]}); "
                         "save it again with torch.export.save from this torch version") from None
    finally:
        quiet.setLevel(level)
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
