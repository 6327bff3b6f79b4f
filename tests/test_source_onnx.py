"""model=onnx (pairedgta/models/sources/onnx.py): an ONNX export under the shared contract agrees with the torch
network (dynamic and fixed size); external data outside the model's folder, a 1-channel input and files of other
formats are one line, and a refused model is never handed to onnxruntime."""
from __future__ import annotations

import logging
import os
import sys
import warnings
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from pairedgta.errors import ConfigError, ModelError
from pairedgta.models import build_model
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD

import onnx  # noqa: E402  (the onnx extra, in dev)
import onnxruntime as ort  # noqa: E402
TESTS = str(Path(__file__).parent)


class TinyNet(torch.nn.Module):
    """Stride 2, batch norm with non-trivial statistics, 19 channels at half resolution (the contract upsamples)."""

    def __init__(self, channels: int = 3) -> None:
        super().__init__()
        self.a = torch.nn.Conv2d(channels, 8, 3, stride=2, padding=1)
        self.bn = torch.nn.BatchNorm2d(8)
        self.b = torch.nn.Conv2d(8, 16, 3, padding=1)
        self.head = torch.nn.Conv2d(16, 19, 1)
        with torch.no_grad():
            self.bn.running_mean.uniform_(-0.5, 0.5)
            self.bn.running_var.uniform_(0.5, 2.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(F.relu(self.b(F.relu(self.bn(self.a(x))))))


def tiny_net(seed: int = 0, channels: int = 3) -> TinyNet:
    """The factory model=python builds (model.target=test_source_onnx:tiny_net)."""
    torch.manual_seed(seed)
    return TinyNet(channels).eval()


def export_onnx(module: torch.nn.Module, path: Path, example: torch.Tensor, dynamic: bool) -> Path:
    """The TorchScript exporter (dynamo=False): the dynamo one needs onnxscript, which the onnx extra leaves out."""
    axes = {"image": {0: "batch", 2: "height", 3: "width"}, "scores": {0: "batch", 2: "h", 3: "w"}} if dynamic else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, (example,), str(path), dynamo=False, input_names=["image"],
                          output_names=["scores"], dynamic_axes=axes)
    return path


@pytest.fixture
def net(tmp_path, monkeypatch):
    """The torch network, its weights as safetensors, and its dynamic-size ONNX export."""
    monkeypatch.syspath_prepend(TESTS)
    module = tiny_net(seed=2)
    weights = tmp_path / "weights.safetensors"
    save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(weights))
    return module, weights, export_onnx(module, tmp_path / "net.onnx", torch.rand(1, 3, 64, 128), dynamic=True)


def from_onnx(path: Path, **extra):
    return build_model({"name": "n", "family": "onnx", "path": str(path), **extra})


def one_line_error(cfg: dict, error: type = ModelError) -> str:
    with pytest.raises(error) as info:
        build_model(cfg)
    text = str(info.value)
    assert "\n" not in text
    return text


def agree(got: torch.Tensor, want: torch.Tensor) -> None:
    assert got.shape == want.shape
    assert (got - want).abs().max().item() <= 1e-4
    assert (got.argmax(1) == want.argmax(1)).float().mean().item() >= 0.999


def test_a_dynamic_export_agrees_with_torch(net):
    module, weights, path = net
    seg = from_onnx(path)
    assert seg.network.fixed_size is None and seg.network.module.batch is None
    assert seg.network.executes == "onnxruntime graph, no Python code"
    assert seg.network.module.session.get_providers() == ["CPUExecutionProvider"]
    assert seg.network.module.session.get_session_options().intra_op_num_threads == torch.get_num_threads()
    reference = build_model({"name": "n", "family": "python", "target": "test_source_onnx:tiny_net",
                                 "checkpoint_path": str(weights)})
    for shape in [(3, 3, 70, 130), (1, 3, 63, 101)]:
        images = torch.rand(shape, generator=torch.Generator().manual_seed(shape[2]))
        agree(seg.predict_proba(images), reference.predict_proba(images))


def test_a_fixed_size_export_runs_at_any_size_image_by_image(net, tmp_path):
    """Exported at 1 x 3 x 64 x 128 with no dynamic axes: images of another size are resized to it and the scores
    back, three images run one at a time."""
    module, _, _ = net
    seg = from_onnx(export_onnx(module, tmp_path / "fixed.onnx", torch.rand(1, 3, 64, 128), dynamic=False))
    assert seg.network.fixed_size == (64, 128) and seg.network.module.batch == 1
    images = torch.rand(3, 3, 48, 80, generator=torch.Generator().manual_seed(4))
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        y = F.interpolate((images - mean) / std, size=(64, 128), mode="bilinear", align_corners=False)
        want = F.interpolate(module(y), size=(48, 80), mode="bilinear", align_corners=False).softmax(dim=1)
    agree(seg.predict_proba(images), want)


def test_the_bound_run_gives_the_plain_runs_output(net):
    """The IO-binding path (the CUDA one: torch's memory in, DLPack out), here on the CPU provider."""
    _, _, path = net
    module = from_onnx(path).network.module
    x = torch.rand(2, 3, 40, 72)
    torch.testing.assert_close(module.run_bound(x), module.run(x), atol=0, rtol=0)


def save_external(tmp_path: Path, location_of) -> Path:
    """The tiny network with every initializer in one external file; `location_of(folder, data)` moves that file
    and returns the location the graph then names."""
    folder = tmp_path / "model"
    folder.mkdir()
    plain = export_onnx(tiny_net(), tmp_path / "plain.onnx", torch.rand(1, 3, 32, 32), dynamic=True)
    path = folder / "net.onnx"
    onnx.save_model(onnx.load(str(plain)), str(path), save_as_external_data=True, all_tensors_to_one_file=True,
                    location="net.data", size_threshold=0)
    location = location_of(folder, folder / "net.data")
    proto = onnx.load(str(path), load_external_data=False)
    count = 0
    for tensor in proto.graph.initializer:
        for entry in tensor.external_data:
            if entry.key == "location":
                entry.value, count = location, count + 1
    assert count == len(proto.graph.initializer) > 0
    onnx.save_model(proto, str(path))
    return path


def test_external_data_beside_the_model_loads(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = save_external(tmp_path, lambda folder, data: data.rename(folder / "weights.bin").name)
    assert from_onnx(path).predict_proba(torch.rand(1, 3, 32, 48)).shape == (1, 19, 32, 48)


def escape_parent(folder: Path, data: Path) -> str:
    data.rename(folder.parent / "outside.bin")
    return "../outside.bin"


def escape_absolute(folder: Path, data: Path) -> str:
    return str(data.rename(folder.parent / "outside.bin"))


def escape_symlink(folder: Path, data: Path) -> str:
    outside = data.rename(folder.parent / "outside.bin")
    os.symlink(outside, folder / "link.bin")
    return "link.bin"


@pytest.mark.parametrize("escape", [escape_parent, escape_absolute, escape_symlink])
def test_external_data_outside_the_models_folder_is_refused_unread(tmp_path, monkeypatch, escape):
    """The data is intact, only elsewhere: refused before onnxruntime sees the model (onnxruntime >= 1.2x refuses
    such paths too; the versions the onnx extra allows before that read them)."""
    path = save_external(tmp_path, escape)
    made = []
    monkeypatch.setattr(ort, "InferenceSession", lambda *a, **k: made.append(a) or pytest.fail("session made"))
    message = one_line_error({"name": "n", "family": "onnx", "path": str(path)})
    assert "outside the model's folder" in message and "nothing read" in message, message
    assert made == []


def test_a_missing_external_data_file_is_one_line(tmp_path):
    path = save_external(tmp_path, lambda folder, data: data.unlink() or "net.data")
    message = one_line_error({"name": "n", "family": "onnx", "path": str(path)})
    assert "keeps its data in 'net.data', which does not exist" in message


def test_a_one_channel_input_is_one_line(tmp_path):
    path = export_onnx(tiny_net(channels=1), tmp_path / "gray.onnx", torch.rand(1, 1, 32, 32), dynamic=True)
    message = one_line_error({"name": "n", "family": "onnx", "path": str(path)})
    assert "ONNX input 'image'" in message and "is not 3-channel" in message


@pytest.mark.parametrize("kind,expect", [
    ("pt2", "it is a torch.export program: load it with model=export model.path="),
    ("safetensors", "it is a safetensors state dict: give it as model.checkpoint_path"),
    ("pickle", "it is a pickle: a state dict goes in model.checkpoint_path"),
    ("bytes", "it is no model format pairedgta reads"),
    ("text", "it is no model format pairedgta reads"),
])
def test_another_format_given_to_model_onnx_is_one_line_naming_its_source(tmp_path, kind, expect):
    path = tmp_path / "model.onnx"
    if kind == "pt2":
        torch.export.save(torch.export.export(tiny_net(), (torch.rand(1, 3, 32, 32),)), str(path))
    elif kind == "safetensors":
        save_file({"w": torch.zeros(2)}, str(path))
    elif kind == "pickle":
        import pickle

        path.write_bytes(pickle.dumps({"w": [1.0]}, protocol=2))
    elif kind == "bytes":
        path.write_bytes(bytes(range(256)) * 4)
    else:
        path.write_text("ir_version: 8\n")
    message = one_line_error({"name": "n", "family": "onnx", "path": str(path)})
    assert f"{path} is not an ONNX model" in message and expect in message, message


def test_without_onnxruntime_the_error_names_the_extra(net, monkeypatch):
    _, _, path = net
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    message = one_line_error({"name": "n", "family": "onnx", "path": str(path)}, ConfigError)
    assert "'onnxruntime'" in message and 'pip install -e ".[onnx]"' in message


def test_cuda_without_a_cuda_onnxruntime_is_one_warning_line(monkeypatch, caplog):
    from pairedgta.models.sources import onnx as source

    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    with caplog.at_level(logging.WARNING, logger="pairedgta.models"):
        assert source.providers("cuda", "model (n)") == ["CPUExecutionProvider"]
    assert [r.getMessage().count("\n") for r in caplog.records] == [0]
    assert "pip install onnxruntime-gpu" in caplog.text
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert source.providers("cuda:1", "model (n)") == [("CUDAExecutionProvider", {"device_id": 1}),
                                                       "CPUExecutionProvider"]
    assert source.providers("cpu", "model (n)") == ["CPUExecutionProvider"]


def cli_args(tmp_path: Path, path: Path) -> list[str]:
    from pairedgta.testing.cli import fast_overrides

    return [o for o in fast_overrides(tmp_path) if not o.startswith("model=")] + [
        "model=onnx", f"model.path={path}", "reference_model=tiny_segformer"]


@pytest.mark.slow
def test_model_onnx_from_the_cli(net, tmp_path):
    from pairedgta.testing.cli import report_overrides, report_page, run_cli

    _, _, path = net
    r = run_cli(report_overrides(tmp_path) + ["model=onnx", f"model.path={path}"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    report_page(r, path.stem)


@pytest.mark.slow
def test_a_bad_file_from_the_cli_is_one_line_and_writes_nothing(tmp_path):
    from pairedgta.testing.cli import run_cli

    path = save_external(tmp_path, escape_parent)
    r = run_cli(cli_args(tmp_path, path), tmp_path)
    assert r.returncode == 2, r.stderr[-3000:]
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "outside the model's folder" in errors[0], r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    evaluate = tmp_path / "cache" / "evaluate"
    assert not evaluate.exists() or not list(evaluate.glob("[!.]*"))
