"""`model=onnx`: an ONNX file run by onnxruntime (the optional extra: pip install -e ".[onnx]").

An ONNX graph is data: onnxruntime runs its operators and no Python code. Two things could still reach outside the
file, and both are closed before the session is made: a tensor's external data (`location`) must be a file inside
the model's folder (no absolute path, no `..`, no symlink out; checked on the graph read with
`load_external_data=False`, so nothing else is read before), and no custom-op library is ever registered, so an
operator of an unknown domain fails to load instead of loading native code.

The providers come from `device` (CUDA, then CPU; or CPU), the intra-op threads from torch's. The graph's one input
says the rest of the contract: a fixed height x width is `Network.fixed_size` (the contract resizes to it and back),
a fixed batch is run that many images at a time."""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pairedgta.errors import ModelError, reason
from pairedgta.models.contract import Network
from pairedgta.models.sources.files import identify, in_batches, model_file, wrong_format

log = logging.getLogger("pairedgta.models")
DTYPES = {"tensor(float)": (np.float32, torch.float32), "tensor(float16)": (np.float16, torch.float16)}


def _tensors(graph: Any):
    """Every tensor a graph or function holds: initializers (sparse ones too) and node attributes, subgraphs
    (If / Loop bodies) included."""
    yield from getattr(graph, "initializer", ())
    for sparse in getattr(graph, "sparse_initializer", ()):
        yield from (sparse.values, sparse.indices)
    for node in graph.node:
        for attr in node.attribute:
            if attr.HasField("t"):
                yield attr.t
            yield from attr.tensors
            for sparse in [*([attr.sparse_tensor] if attr.HasField("sparse_tensor") else []), *attr.sparse_tensors]:
                yield from (sparse.values, sparse.indices)
            for sub in [*([attr.g] if attr.HasField("g") else []), *attr.graphs]:
                yield from _tensors(sub)


def check_external_data(proto: Any, file: Path, where: str) -> None:
    """Each tensor stored outside the .onnx names a file inside the model's folder (after following symlinks),
    which exists; else the one-line error, before anything but the graph itself is read."""
    import onnx

    folder = file.parent.resolve()
    tensors = [t for g in (proto.graph, *proto.functions) for t in _tensors(g)]
    for tensor in tensors:
        if tensor.data_location != onnx.TensorProto.EXTERNAL:
            continue
        location = next((e.value for e in tensor.external_data if e.key == "location"), "")
        parts = re.split(r"[\\/]", location)
        try:
            target = (file.parent / location).resolve() if location else folder
        except (OSError, ValueError):  # a NUL byte, a symlink loop: no file it could name is acceptable
            target = folder
        outside = (not location or location.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", location)
                   or ".." in parts or not target.is_relative_to(folder) or target == folder)
        if outside:
            raise ModelError(f"{where}: {file}: tensor '{tensor.name}' keeps its data at {location!r}, outside the "
                             f"model's folder {folder}; refused, nothing read: external data must be a file beside "
                             f"the model (torch.onnx.export / onnx.save_model with a relative location)")
        if not target.is_file():
            raise ModelError(f"{where}: {file}: tensor '{tensor.name}' keeps its data in {location!r}, which does "
                             f"not exist in {folder}; copy the model's external data file beside it")


def providers(device: str, where: str) -> list[Any]:
    """CUDA then CPU for a cuda device (CPU alone, with one warning line, if this onnxruntime has no CUDA), CPU
    for cpu; named explicitly, so onnxruntime never picks one by itself."""
    import onnxruntime as ort

    dev = torch.device(device)
    if dev.type != "cuda":
        return ["CPUExecutionProvider"]
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        log.warning("%s: device=%s, but this onnxruntime has no CUDA provider (pip install onnxruntime-gpu): the "
                    "ONNX model runs on the CPU", where, device)
        return ["CPUExecutionProvider"]
    return [("CUDAExecutionProvider", {"device_id": dev.index or 0}), "CPUExecutionProvider"]


class OnnxNetwork(torch.nn.Module):
    """The session as a module: a torch batch in, the graph's first output out as a torch tensor on the input's
    device. On the CPU both crossings share memory (numpy views); with the CUDA provider the input and output
    stay on the GPU (IO binding on torch's memory, the output handed back through DLPack)."""

    def __init__(self, session: Any, input_name: str, dtypes: tuple[Any, Any], batch: int | None,
                 where: str) -> None:
        super().__init__()
        self.session, self.input_name, self.where, self.batch = session, input_name, where, batch
        self.output_name = session.get_outputs()[0].name
        self.np_dtype, self.torch_dtype = dtypes
        self.on_cuda = "CUDAExecutionProvider" in session.get_providers()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.batch is None or x.shape[0] == self.batch:
            return self.run(x)
        return in_batches(self.run, x, self.batch, self.where)

    def run(self, x: torch.Tensor) -> torch.Tensor:
        x = x.detach().to(self.torch_dtype).contiguous()  # no copy when it already is
        if x.is_cuda and self.on_cuda:
            return self.run_bound(x)
        out = self.session.run([self.output_name], {self.input_name: x.cpu().numpy()})[0]
        return torch.from_numpy(out).to(x.device)

    def run_bound(self, x: torch.Tensor) -> torch.Tensor:
        """One run on `x`'s own memory (IO binding), the output left where onnxruntime put it (same device)."""
        index = x.device.index or 0
        binding = self.session.io_binding()
        binding.bind_input(self.input_name, x.device.type, index, self.np_dtype, tuple(x.shape), x.data_ptr())
        binding.bind_output(self.output_name, x.device.type, index)
        if x.is_cuda:
            torch.cuda.current_stream(x.device).synchronize()  # torch's writes to x are done before onnxruntime reads
        self.session.run_with_iobinding(binding)  # returns once the provider has finished (its default)
        return torch.from_dlpack(binding.get_outputs()[0])


def open_session(path: Any, device: str, where: str) -> tuple[Any, Path]:
    """The checked file's onnxruntime session (format, external data, explicit providers); shared with the
    detector source."""
    file = model_file(path, where, "onnx", "<file.onnx>")
    kind = identify(file)
    if kind not in (None, "onnx"):
        raise wrong_format(file, kind, where, "an ONNX model")
    import onnx
    import onnxruntime as ort

    try:
        proto = onnx.load(str(file), load_external_data=False)
    except Exception as exc:
        raise wrong_format(file, None, where, f"an ONNX model ({reason(exc)[:200]})") from None
    if proto.ir_version < 1 or not proto.opset_import or not proto.graph.node or not proto.graph.output:
        raise wrong_format(file, None, where, "an ONNX model (no graph in it)")
    check_external_data(proto, file, where)
    del proto  # the session reads the file itself
    options = ort.SessionOptions()
    options.intra_op_num_threads = torch.get_num_threads()
    options.log_severity_level = 3  # errors only: onnxruntime's warnings are many lines on stderr
    # no busy-waiting between runs: torch's threads resize and softmax each batch right after onnxruntime's run
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    chosen = providers(device, where)
    try:
        session = ort.InferenceSession(str(file), sess_options=options, providers=chosen)
    except Exception as exc:
        raise ModelError(f"{where}: onnxruntime {ort.__version__} cannot load {file} ({reason(exc)[:300]}); "
                         "export it again with a standard opset (torch.onnx.export)") from None
    if len(chosen) > 1 and "CUDAExecutionProvider" not in session.get_providers():
        log.warning("%s: onnxruntime's CUDA provider did not start (CUDA or cuDNN libraries missing?): the ONNX model "
                    "runs on the CPU", where)
    return session, file


def one_input(session: Any, file: Path, where: str, what: str) -> Any:
    """The graph's one image input; a graph of several inputs is one line (export the `what` with one)."""
    inputs = session.get_inputs()
    if len(inputs) != 1:
        raise ModelError(f"{where}: {file} has {len(inputs)} inputs ({', '.join(i.name for i in inputs)}); export "
                         f"the {what} with one image input")
    return inputs[0]


def load(name: str, device: str, /, *, path: str | None = None) -> Network:
    """Check the format and the external data, make the session with explicit providers, check its one input."""
    where = f"model ({name})"
    session, file = open_session(path, device, where)
    image = one_input(session, file, where, "model")
    shape = list(image.shape) if image.shape is not None else []
    if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
        raise ModelError(f"{where}: ONNX input '{image.name}' of {file} is not 3-channel B x 3 x H x W (shape "
                         f"{shape}); export the model with an RGB image batch as its input")
    if image.type not in DTYPES:
        raise ModelError(f"{where}: ONNX input '{image.name}' of {file} is {image.type}; export the model with a "
                         "float32 (or float16) image input")
    h, w = shape[2], shape[3]
    fixed = (h, w) if isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0 else None
    if fixed is None and (isinstance(h, int) and h > 0) != (isinstance(w, int) and w > 0):
        raise ModelError(f"{where}: ONNX input '{image.name}' of {file} has one fixed and one dynamic side "
                         f"({shape}); export both sides dynamic (dynamic_axes) or both fixed")
    batch = shape[0] if isinstance(shape[0], int) and shape[0] > 0 else None
    module = OnnxNetwork(session, image.name, DTYPES[image.type], batch, where)
    return Network(module, fixed_size=fixed, executes="onnxruntime graph, no Python code")
