"""`model=export`: a `torch.export` program, saved with `torch.export.save` (a .pt2 zip), loaded with
`torch.export.load(path).module()`.

Loading a .pt2 unpickles parts of it (torch.load(weights_only=False) of its pickled weights and constants), so it
runs code stored in the file: naming `model=export` is the user's choice to do that. Before torch sees the file,
its zip structure is checked (the archive's `archive_format` entry says `pt2`): an ONNX, safetensors, torch.save or
plain pickle file given here is a one-line error naming the source that reads it, and is never unpickled.

What the program itself says becomes the contract's: static height/width -> `Network.fixed_size`, a dynamic size
exported as a multiple (`2 * Dim(...)`) -> `pad_multiple`, a static batch -> that many images per call. A program
exported in training mode (batch norm on batch statistics, active dropout) is refused: its outputs would depend on
the other images of a batch."""
from __future__ import annotations

import logging
import math
from typing import Any

import torch

from pairedgta.errors import ModelError, reason
from pairedgta.models.contract import Network
from pairedgta.models.sources.files import identify, in_batches, model_file, wrong_format

def _training_ops(program: Any) -> list[str]:
    """The ops that run in training mode (a `training`/`train` argument set true: batch norm, dropout) and the
    buffers the program updates on each call (a batch norm's running statistics)."""
    found = set(program.graph_signature.buffers_to_mutate.values())
    for node in program.graph.nodes:
        schema = getattr(node.target, "_schema", None) if node.op == "call_function" else None
        for i, arg in enumerate(schema.arguments if schema is not None else ()):
            if arg.name in ("training", "train"):
                value = node.args[i] if i < len(node.args) else node.kwargs.get(arg.name, False)
                if value is True:
                    found.add(str(node.target).split(".")[1] if str(node.target).count(".") else str(node.target))
    return sorted(found)


def _multiple(dim: Any) -> int:
    """The step of a dynamic size exported as `k * Dim(...)` (1 for a plain Dim)."""
    expr = getattr(getattr(dim, "node", None), "expr", None)
    coeff = expr.as_coeff_Mul()[0] if expr is not None and hasattr(expr, "as_coeff_Mul") else 1
    return int(coeff) if getattr(coeff, "is_Integer", False) and int(coeff) > 0 else 1


class ExportedNetwork(torch.nn.Module):
    """The program's module held outside `_modules`: an exported module refuses `.train()` / `.eval()` (the
    program runs in the mode it was exported in, checked to be inference), and `.to(device)` moves the
    program with torch's pass (`torch.export.passes.move_to_device_pass`, which also moves the devices
    written into its ops), not module by module."""

    def __init__(self, program: Any, batch: int | None, where: str) -> None:
        super().__init__()
        self.batch, self.where = batch, where
        self._place(program)

    def _place(self, program: Any) -> None:
        state = list(program.state_dict.values()) + list(program.constants.values())
        device = next((t.device for t in state if isinstance(t, torch.Tensor)), torch.device("cpu"))
        object.__setattr__(self, "program", program)
        object.__setattr__(self, "graph", program.module())
        object.__setattr__(self, "device", device)

    def train(self, mode: bool = True) -> "ExportedNetwork":
        self.training = mode
        return self

    def to(self, *args: Any, **kwargs: Any) -> "ExportedNetwork":
        """Only the device counts: the program's dtypes are fixed, and the contract hands it contiguous input."""
        device = kwargs.get("device", next((a for a in args if isinstance(a, (str, torch.device))), None))
        if device is not None and torch.device(device) != self.device:
            from torch.export.passes import move_to_device_pass

            self._place(move_to_device_pass(self.program, torch.device(device)))
        return self

    def forward(self, x: "torch.Tensor") -> Any:
        if self.batch is None or x.shape[0] == self.batch:
            return self.graph(x)
        return in_batches(self.graph, x, self.batch, self.where)


def load_program(path: Any, where: str) -> tuple[Any, Any]:
    """The checked .pt2's program (identified by its zip entries before torch sees it); shared with the detector
    source."""
    file = model_file(path, where, "export", "<file.pt2 from torch.export.save>")
    kind = identify(file)
    if kind != "pt2":
        raise wrong_format(file, kind, where, "a torch.export program (a .pt2 zip from torch.export.save)")
    quiet = logging.getLogger("torch.export")  # a failed load logs a traceback before raising: the error says it
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    try:
        return torch.export.load(str(file)), file
    except Exception as exc:
        raise ModelError(f"{where}: torch {torch.__version__} cannot load the program {file} ({reason(exc)[:300]}); "
                         "save it again with torch.export.save from this torch version (a program of a CPU model "
                         "loads on any machine)") from None
    finally:
        quiet.setLevel(level)


def load(name: str, device: str, /, *, path: str | None = None) -> Network:
    """Check the file is a .pt2 archive, load it, read its input's shape and check its mode; `device` is applied by
    the segmenter (`.to(device)`)."""
    where = f"model ({name})"
    program, file = load_program(path, where)
    inputs = list(program.graph_signature.user_inputs)
    if len(inputs) != 1:
        raise ModelError(f"{where}: the program {file} takes {len(inputs)} inputs ({', '.join(map(str, inputs))}); "
                         "export it with one image input: torch.export.export(model, (x,))")
    node = next(n for n in program.graph.nodes if n.op == "placeholder" and n.name == inputs[0])
    shape = tuple(getattr(node.meta.get("val"), "shape", ()))
    if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
        raise ModelError(f"{where}: the program {file} takes input of shape {list(shape)}, not B x 3 x H x W; "
                         "export it with an RGB image batch as its one input")
    training = _training_ops(program)
    if training:
        raise ModelError(f"{where}: the program {file} was exported in training mode ({', '.join(training)}: "
                         "its output would depend on the batch); call model.eval() before torch.export.export")
    h, w = shape[2], shape[3]
    if isinstance(h, int) != isinstance(w, int):
        raise ModelError(f"{where}: the program {file} has a static {'height' if isinstance(h, int) else 'width'} "
                         "and a dynamic other side; export both dynamic (dynamic_shapes) or both static")
    fixed = (h, w) if isinstance(h, int) else None
    declared = {}
    if fixed is None:
        step = math.lcm(_multiple(h), _multiple(w))
        if step > 1:
            declared["pad_multiple"] = step
    batch = shape[0] if isinstance(shape[0], int) else None
    try:
        module = ExportedNetwork(program, batch, where)
    except Exception as exc:  # the program's graph does not make a module: a file torch saved wrongly
        raise ModelError(f"{where}: the program {file} does not make a module ({reason(exc)[:300]}); save it again "
                         "with torch.export.save(torch.export.export(model.eval(), (x,)), path)") from None
    return Network(module, declared=declared, fixed_size=fixed,
                   executes="code stored in the .pt2 (torch.export.load unpickles parts of it): model=export")
