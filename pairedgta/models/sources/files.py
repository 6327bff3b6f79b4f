"""The model file a file-based source (model=export, model=onnx) is given: that it exists, what format it really is
(by its first bytes and a zip's entry names; nothing is unpickled), the one line naming the source that reads it, and
running a graph whose batch size is fixed."""
from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any, Callable

import torch

from pairedgta.errors import ModelError
from pairedgta.models.contract import raw_output

# What a model file that one source was given is, by its first bytes and (for a zip) its entry names; the values
# say which source reads it.
KINDS = {
    "pt2": "a torch.export program: load it with model=export model.path={file}",
    "onnx": "an ONNX model: load it with model=onnx model.path={file}",
    "safetensors": "a safetensors state dict: give it as model.checkpoint_path of model=python or model=torchvision",
    "torch.save": "a torch.save file: a state dict goes in model.checkpoint_path of model=python or model=torchvision "
                  "(read weights-only); a pickled model is not loaded",
    "pickle": "a pickle: a state dict goes in model.checkpoint_path of model=python or model=torchvision (read "
              "weights-only); a pickled model is not loaded",
    "torchscript": "a TorchScript archive (torch.jit.save), which no source loads: save the model with "
                   "torch.export.save (model=export) or torch.onnx.export (model=onnx)",
    "zip": "a zip without a model format pairedgta reads (damaged, or of another kind)",
}
_LEGACY_PT2 = {"serialized_exported_program.json", "version"}  # torch.export.save before the pt2 archive (torch < 2.7)


def model_file(path: Any, where: str, family: str, example: str) -> Path:
    """model.path as an existing file, or the one-line error that says how to set it."""
    if not path:
        raise ModelError(f"{where}: model={family} needs its file; set model.path={example}")
    file = Path(str(path)).expanduser()
    if not file.is_file():
        what = "is a folder" if file.is_dir() else "does not exist"
        raise ModelError(f"{where}: model.path={file} {what}; set model.path={example}")
    return file


def identify(file: Path) -> str | None:
    """Which of KINDS `file` is, from its first bytes and a zip's entry names only (nothing is unpickled or
    decompressed beyond pt2's 3-byte `archive_format` entry); None when none of them."""
    with open(file, "rb") as f:
        head = f.read(16)
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        try:
            with zipfile.ZipFile(file) as archive:
                infos = archive.infolist()
                names = {i.filename for i in infos}
                if _LEGACY_PT2 <= names:
                    return "pt2"
                root = infos[0].filename.split("/")[0] if infos else ""
                fmt = archive.getinfo(f"{root}/archive_format") if f"{root}/archive_format" in names else None
                if fmt is not None and fmt.file_size <= 16 and archive.read(fmt).strip() == b"pt2":
                    return "pt2"
        except Exception:  # a damaged zip (zipfile raises several kinds): not one torch could load either
            return "zip"
        if any(n.split("/", 1)[-1].startswith("code/") or n.endswith("/constants.pkl") for n in names):
            return "torchscript"
        if any(n == "data.pkl" or n.endswith("/data.pkl") for n in names):
            return "torch.save"
        return "zip"
    if len(head) >= 9 and head[8:9] == b"{" and int.from_bytes(head[:8], "little") < file.stat().st_size:
        return "safetensors"  # an 8-byte header length, then the JSON header
    if len(head) > 1 and head[0] == 0x80 and 2 <= head[1] <= 5:
        return "pickle"  # a pickle's PROTO opcode (torch.save's legacy format starts with one too)
    if len(head) > 1 and head[0] == 0x08 and 0 < head[1] < 0x80:
        return "onnx"  # ModelProto field 1 (ir_version), a one-byte varint: how every ONNX writer starts
    return None


def wrong_format(file: Path, kind: str | None, where: str, expected: str) -> ModelError:
    """The one line for a file of another format than the source's."""
    found = KINDS.get(kind or "", "no model format pairedgta reads").format(file=file)
    return ModelError(f"{where}: {file} is not {expected}; it is {found}")


def in_batches(run: Callable[[torch.Tensor], Any], x: torch.Tensor, batch: int, where: str) -> torch.Tensor:
    """A graph with a static batch: `batch` images per call, the last call filled up by repeating its last image
    (the repeats' outputs are dropped)."""
    outs = []
    for start in range(0, x.shape[0], batch):
        chunk = x[start:start + batch]
        n = chunk.shape[0]
        if n < batch:
            chunk = torch.cat([chunk, chunk[-1:].expand(batch - n, *chunk.shape[1:])])
        outs.append(raw_output(run(chunk), where)[:n])
    return outs[0] if len(outs) == 1 else torch.cat(outs)
