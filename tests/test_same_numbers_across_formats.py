"""One network in every format that can hold it gives the same labels (issue 56, item 5): a segmentation_models_pytorch
Unet as an SMP folder, a torch.export program, an ONNX graph and the user's own factory; torchvision's LR-ASPP as its
builder, a program, a graph and a factory; a SegFormer as an HF folder, a graph and a factory. On the rendered
images (the synthetic backend here; experiments/check_formats.py does the same on the main job's Blender images),
>= 99.9 % of pixels get the same label as the network in torch, and xi through the whole pipeline is within 1e-3
(ONNX against torch)."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image
from safetensors.torch import save_file

import source_nets
from pairedgta.models import build_model
from pairedgta.testing.cli import fast_overrides, run_cli

SIZE = ["renderer.width=128", "renderer.height=64"]
ARCH = {"num_encoder_blocks": 4, "depths": [1, 1, 1, 1], "sr_ratios": [8, 4, 2, 1], "hidden_sizes": [8, 16, 24, 32],
        "num_attention_heads": [1, 1, 1, 1], "mlp_ratios": [2, 2, 2, 2], "decoder_hidden_size": 32}


def weights(module, path: Path) -> str:
    save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(path))
    return str(path)


def onnx_file(module, path: Path, example: torch.Tensor) -> str:
    axes = {"image": {0: "batch", 2: "height", 3: "width"}, "scores": {0: "batch", 2: "h", 3: "w"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, (example,), str(path), dynamo=False, input_names=["image"], output_names=["scores"],
                          dynamic_axes=axes)
    return str(path)


def program(module, path: Path, example: torch.Tensor, step: int) -> str:
    dims = {0: torch.export.Dim("batch"), 2: step * torch.export.Dim("h"), 3: step * torch.export.Dim("w")}
    torch.export.save(torch.export.export(module, (example,), dynamic_shapes={"x": dims}), str(path))
    return str(path)


@pytest.fixture(scope="module")
def formats(tmp_path_factory):
    """name -> {format: model config}; the first format of each is the network in torch."""
    root = tmp_path_factory.mktemp("formats")
    x = torch.rand(2, 3, 64, 128)  # a batch of 2: an example batch of 1 would fix the program's batch
    unet = source_nets.smp_unet(seed=1).eval()
    unet.save_pretrained(root / "unet")
    tv = source_nets.lraspp(seed=2).eval()
    torch.manual_seed(3)
    seg = source_nets.segformer(**ARCH).eval()
    seg.save_pretrained(root / "segformer")
    return {
        "unet": {
            "python": {"family": "python", "target": "source_nets:smp_unet",
                       "checkpoint_path": weights(unet, root / "unet.safetensors"), "pad_multiple": 8},
            "smp": {"family": "smp", "path": str(root / "unet")},
            "export": {"family": "export", "path": program(unet, root / "unet.pt2", x, 8)},
            "onnx": {"family": "onnx", "path": onnx_file(unet, root / "unet.onnx", x), "pad_multiple": 8},
        },
        "lraspp": {
            "python": {"family": "python", "target": "source_nets:lraspp",
                       "checkpoint_path": weights(tv, root / "lraspp.safetensors")},
            "torchvision": {"family": "torchvision", "arch": "lraspp_mobilenet_v3_large",
                            "checkpoint_path": str(root / "lraspp.safetensors")},
            "onnx": {"family": "onnx", "path": onnx_file(TorchvisionOut(tv), root / "lraspp.onnx", x)},
        },
        "segformer": {
            "python": {"family": "python", "target": "source_nets:segformer", "kwargs": ARCH,
                       "checkpoint_path": weights(seg, root / "segformer.safetensors")},
            "hf": {"family": "hf", "path": str(root / "segformer")},
            "onnx": {"family": "onnx", "path": onnx_file(source_nets.Logits(seg), root / "segformer.onnx", x)},
        },
    }


class TorchvisionOut(torch.nn.Module):
    def __init__(self, model) -> None:
        super().__init__()
        self.model = model

    def forward(self, x):
        return self.model(x)["out"]


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """The rendered images of a small generated dataset (every condition of the fast run)."""
    tmp = tmp_path_factory.mktemp("render")
    r = run_cli(fast_overrides(tmp) + SIZE + ["stages=[generate]"], tmp)
    assert r.returncode == 0, r.stderr
    files = sorted((tmp / "cache" / "generate").glob("*/scenes/*/*.png"))
    files = [f for f in files if "_" not in f.stem]  # <condition>.png; not its _labels, _instances, ...
    assert len(files) >= 9, files
    return np.stack([np.asarray(Image.open(f).convert("RGB")) for f in files])


@pytest.mark.slow
@pytest.mark.parametrize("network", ["unet", "lraspp", "segformer"])
def test_every_format_gives_the_same_labels(formats, images, network):
    variants = formats[network]
    labels = {}
    for fmt, cfg in variants.items():
        seg = build_model({"name": f"{network}_{fmt}", **cfg})
        labels[fmt] = seg.predict(images)[0].numpy()
    torch_labels = labels.pop("python")
    for fmt, got in labels.items():
        agreement = float((got == torch_labels).mean())
        assert agreement >= 0.999, (network, fmt, agreement)


@pytest.mark.slow
def test_xi_of_onnx_within_1e3_of_torch(formats, tmp_path):
    """The whole pipeline, ONNX against torch, on the same scenes and pseudo-labels."""
    xi = {}
    for fmt in ("python", "onnx"):
        cfg = formats["unet"][fmt]
        args = [f"model={cfg['family']}", f"model.name=unet_{fmt}"]
        args += [f"model.{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in cfg.items() if k != "family"]
        # the numbers under test are evaluate's: the figures drawn from them are the same code for either format
        r = run_cli(fast_overrides(tmp_path) + SIZE + args + ["stages=[generate,pseudolabel,evaluate]"], tmp_path)
        assert r.returncode == 0, r.stderr
        entry = next(p for p in (tmp_path / "cache" / "evaluate").iterdir() if (p / "manifest.json").is_file()
                     and json.loads((p / "manifest.json").read_text())["config"]["model"]["name"] == f"unet_{fmt}")
        xi[fmt] = pd.read_csv(entry / "xi.csv")
    a, b = xi["python"], xi["onnx"]
    assert len(a) == len(b) and a["xi"].notna().any()
    diff = (a["xi"] - b["xi"]).abs().max()
    assert diff <= 1e-3, diff
