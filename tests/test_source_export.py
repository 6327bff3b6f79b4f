"""model=export (pairedgta/models/sources/export.py): a torch.export program under the shared contract gives the
eager network's probabilities; a static program runs at any size; files of other formats, a pickle above all, are
one line and never unpickled."""
from __future__ import annotations

import pickle
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from pairedgta.errors import ModelError
from pairedgta.models import build_model
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD

TESTS = str(Path(__file__).parent)


class TinyNet(torch.nn.Module):
    """Stride 2, batch norm with non-trivial statistics, 19 channels at half resolution (the contract upsamples)."""

    def __init__(self, channels: int = 3, dict_output: bool = True) -> None:
        super().__init__()
        self.a = torch.nn.Conv2d(channels, 8, 3, stride=2, padding=1)
        self.bn = torch.nn.BatchNorm2d(8)
        self.b = torch.nn.Conv2d(8, 16, 3, padding=1)
        self.head = torch.nn.Conv2d(16, 19, 1)
        self.dict_output = dict_output
        with torch.no_grad():
            self.bn.running_mean.uniform_(-0.5, 0.5)
            self.bn.running_var.uniform_(0.5, 2.0)

    def forward(self, x: torch.Tensor):
        out = self.head(F.relu(self.b(F.relu(self.bn(self.a(x))))))
        return {"out": out} if self.dict_output else out


def tiny_net(seed: int = 0, channels: int = 3, dict_output: bool = True) -> TinyNet:
    """The factory model=python builds (model.target=test_source_export:tiny_net)."""
    torch.manual_seed(seed)
    return TinyNet(channels, dict_output).eval()


class Evil:
    """Unpickling it creates `path`: proof that a file was unpickled."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return open, (str(self.path), "w")


@pytest.fixture
def net(tmp_path, monkeypatch):
    """The eager network, its weights as safetensors, and the same network through model=python."""
    monkeypatch.syspath_prepend(TESTS)
    module = tiny_net(seed=1)
    weights = tmp_path / "weights.safetensors"
    save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(weights))
    return module, weights


def eager(weights: Path, **contract) -> object:
    return build_model({"name": "n", "family": "python", "target": "test_source_export:tiny_net",
                            "checkpoint_path": str(weights), **contract})


def save_program(module: torch.nn.Module, path: Path, example: torch.Tensor, dynamic_shapes=None) -> Path:
    torch.export.save(torch.export.export(module, (example,), dynamic_shapes=dynamic_shapes), str(path))
    return path


def from_export(path: Path, **extra):
    return build_model({"name": "n", "family": "export", "path": str(path), **extra})


def one_line_error(cfg: dict) -> str:
    with pytest.raises(ModelError) as info:
        build_model(cfg)
    text = str(info.value)
    assert "\n" not in text
    return text


def test_a_dynamic_program_gives_the_eager_probabilities(net, tmp_path):
    module, weights = net
    dims = {0: torch.export.Dim("batch"), 2: 2 * torch.export.Dim("h"), 3: 2 * torch.export.Dim("w")}
    path = save_program(module, tmp_path / "net.pt2", torch.rand(2, 3, 64, 96), {"x": dims})
    seg = from_export(path)
    # exported as 2 * Dim: the program declares its step, the contract pads an odd size to it
    assert seg.network.fixed_size is None and seg.contract.pad_multiple == 2
    assert "model=export" in seg.network.executes
    reference = eager(weights, pad_multiple=2)
    for shape in [(3, 3, 70, 130), (1, 3, 63, 101)]:
        images = torch.rand(shape, generator=torch.Generator().manual_seed(shape[2]))
        got, want = seg.predict_proba(images), reference.predict_proba(images)
        assert got.shape == (shape[0], 19, *shape[2:])
        torch.testing.assert_close(got, want, atol=1e-5, rtol=0)


def test_a_static_program_runs_at_its_size_and_batch(net, tmp_path):
    """Exported at 2 x 3 x 64 x 128 with no dynamic dims: images of another size are resized to it and the scores
    back; three images run as two calls of two (the last one filled up)."""
    module, _ = net
    seg = from_export(save_program(module, tmp_path / "static.pt2", torch.rand(2, 3, 64, 128)))
    assert seg.network.fixed_size == (64, 128) and seg.network.module.batch == 2
    images = torch.rand(3, 3, 48, 80, generator=torch.Generator().manual_seed(3))
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        y = F.interpolate((images - mean) / std, size=(64, 128), mode="bilinear", align_corners=False)
        out = F.interpolate(module(y)["out"], size=(48, 80), mode="bilinear", align_corners=False)
    torch.testing.assert_close(seg.predict_proba(images), out.softmax(dim=1), atol=1e-5, rtol=0)


def test_the_wrapper_takes_eval_and_to_that_the_exported_module_refuses(net, tmp_path):
    module, _ = net
    program = torch.export.load(str(save_program(module, tmp_path / "net.pt2", torch.rand(1, 3, 32, 32))))
    with pytest.raises(Exception):
        program.module().eval()  # what the wrapper exists for; if torch allows it one day, this test says so
    wrapped = from_export(tmp_path / "net.pt2").network.module
    assert wrapped.eval() is wrapped and wrapped.to("cpu") is wrapped and not wrapped.training
    assert list(wrapped.children()) == []  # the exported module is held outside _modules


def test_a_program_exported_in_training_mode_is_refused(tmp_path):
    module = tiny_net().train()
    path = save_program(module, tmp_path / "train.pt2", torch.rand(2, 3, 32, 32))
    message = one_line_error({"name": "n", "family": "export", "path": str(path)})
    assert "training mode" in message and "batch_norm" in message and "model.eval()" in message


def test_a_one_channel_program_is_refused(tmp_path):
    path = save_program(tiny_net(channels=1), tmp_path / "gray.pt2", torch.rand(1, 1, 32, 32))
    message = one_line_error({"name": "n", "family": "export", "path": str(path)})
    assert "[1, 1, 32, 32], not B x 3 x H x W" in message


def write_onnx(path: Path) -> Path:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(tiny_net(dict_output=False), (torch.rand(1, 3, 32, 32),), str(path), dynamo=False)
    return path


@pytest.mark.parametrize("kind,expect", [
    ("onnx", "it is an ONNX model: load it with model=onnx model.path="),
    ("safetensors", "it is a safetensors state dict: give it as model.checkpoint_path"),
    ("torch.save", "it is a torch.save file: a state dict goes in model.checkpoint_path"),
    ("torchscript", "it is a TorchScript archive (torch.jit.save), which no source loads"),
    ("bytes", "it is no model format pairedgta reads"),
])
def test_another_format_given_to_model_export_is_one_line_naming_its_source(tmp_path, kind, expect):
    path = tmp_path / "model.pt2"
    if kind == "onnx":
        write_onnx(path)
    elif kind == "safetensors":
        save_file({"w": torch.zeros(2)}, str(path))
    elif kind == "torch.save":
        torch.save({"w": torch.zeros(2)}, path)
    elif kind == "torchscript":
        torch.jit.save(torch.jit.script(torch.nn.Conv2d(3, 19, 1)), str(path))
    else:
        path.write_bytes(bytes(range(256)) * 4)
    message = one_line_error({"name": "n", "family": "export", "path": str(path)})
    assert f"{path} is not a torch.export program" in message and expect in message, message


def test_a_missing_file_is_one_line(tmp_path):
    message = one_line_error({"name": "n", "family": "export", "path": str(tmp_path / "none.pt2")})
    assert "does not exist; set model.path=" in message
    message = one_line_error({"name": "n", "family": "export"})
    assert "model=export needs its file; set model.path=" in message


@pytest.mark.parametrize("container", ["pickle", "torch.save"])
def test_a_pickle_is_never_unpickled(net, tmp_path, container):
    """A pickle that would create a file: refused by model=export before torch sees it (not a .pt2 archive), and by
    the weights-only reading of model=torchvision's and model=python's checkpoint_path."""
    marker = tmp_path / "marker"
    path = tmp_path / "evil.pt2"
    if container == "pickle":
        path.write_bytes(pickle.dumps({"w": Evil(marker)}, protocol=2))  # torch.save's protocol
    else:
        torch.save({"w": Evil(marker)}, path)
    assert not marker.exists()
    message = one_line_error({"name": "n", "family": "export", "path": str(path)})
    assert f"it is a {container}" in message
    assert not marker.exists()
    for cfg in ({"family": "python", "target": "test_source_export:tiny_net"},
                {"family": "torchvision", "arch": "lraspp_mobilenet_v3_large"}):
        message = one_line_error({"name": "n", "checkpoint_path": str(path), **cfg})
        assert f"cannot read checkpoint {path}" in message and "io.open" in message, message  # _io.open on 3.13
        assert not marker.exists()


def cli_args(tmp_path: Path, path: Path) -> list[str]:
    from pairedgta.testing.cli import fast_overrides

    return [o for o in fast_overrides(tmp_path) if not o.startswith("model=")] + [
        "model=export", f"model.path={path}", "reference_model=tiny_segformer"]


@pytest.mark.slow
def test_model_export_from_the_cli(net, tmp_path):
    from pairedgta.testing.cli import report_overrides, report_page, run_cli

    module, _ = net
    dims = {0: torch.export.Dim("batch"), 2: torch.export.Dim("h", min=8), 3: torch.export.Dim("w", min=8)}
    path = save_program(module, tmp_path / "net.pt2", torch.rand(2, 3, 32, 64), {"x": dims})
    r = run_cli(report_overrides(tmp_path) + ["model=export", f"model.path={path}"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    report_page(r, "net")


@pytest.mark.slow
def test_a_bad_file_from_the_cli_is_one_line_and_writes_nothing(tmp_path):
    from pairedgta.testing.cli import run_cli

    path = write_onnx(tmp_path / "net.onnx")
    r = run_cli(cli_args(tmp_path, path), tmp_path)
    assert r.returncode == 2, r.stderr[-3000:]
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "it is an ONNX model: load it with model=onnx" in errors[0], r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    evaluate = tmp_path / "cache" / "evaluate"
    assert not evaluate.exists() or not list(evaluate.glob("[!.]*"))
