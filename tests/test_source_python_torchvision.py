"""`model=python` (the user's own factory) and `model=torchvision` (a builder of torchvision.models.segmentation):
the real loading path on weights written in the test, strict keys in one line, checkpoints as data only, the model's
files in the stage keys, and both through the CLI."""
from __future__ import annotations

import json
import pickle

import pytest
import torch
from safetensors.torch import save_file

from pairedgta.errors import ConfigError, ModelError
from pairedgta.models import build_model, with_defaults
from pairedgta.stages.common import model_hash_config
from source_nets import tiny_net


def save(module, path):
    save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(path))
    return str(path)


def python_cfg(**keys):
    return {"name": "mine", "family": "python", "target": "source_nets:tiny_net", **keys}


def test_python_factory_with_weights_matches_the_network(tmp_path):
    net = tiny_net(seed=3).eval()
    ckpt = save(net, tmp_path / "w.safetensors")
    seg = build_model(python_cfg(checkpoint_path=ckpt, mean=[0, 0, 0], std=[1, 1, 1]))
    x = torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        expect = torch.nn.functional.interpolate(net(x), size=(32, 48), mode="bilinear", align_corners=False).softmax(1)
    torch.testing.assert_close(seg.predict_proba(x), expect)
    # a dict output (out / aux), torch.load weights with DataParallel prefixes: the same numbers
    torch.save({"state_dict": {f"module.{k}": v for k, v in net.state_dict().items()}}, tmp_path / "w.pth")
    seg2 = build_model(python_cfg(target="source_nets:dict_net", checkpoint_path=str(tmp_path / "w.pth"),
                                      mean=[0, 0, 0], std=[1, 1, 1]))
    torch.testing.assert_close(seg2.predict_proba(x), expect)


def test_python_source_errors_are_one_line(tmp_path):
    cases = [
        (python_cfg(target="no_such_module_xyz:build"), ConfigError, "does not import"),
        (python_cfg(target="source_nets"), ConfigError, "package.module:function"),
        (python_cfg(target="source_nets:missing"), ConfigError, "no callable 'missing'"),
        (python_cfg(target="source_nets:not_a_module"), ModelError, "not a torch.nn.Module"),
        (python_cfg(kwargs={"depth": 3}), ModelError, "model.kwargs"),
        (python_cfg(checkpoint_path=str(tmp_path / "none.safetensors")), ModelError, "does not exist"),
        (python_cfg(kwargs={"classes": 7}), ModelError, "outputs 7 channels"),
    ]
    for cfg, error, text in cases:
        with pytest.raises(error, match=text) as exc:
            build_model(cfg)
        assert "\n" not in str(exc.value), str(exc.value)
    wrong = save(tiny_net(width=4), tmp_path / "narrow.safetensors")
    with pytest.raises(ModelError, match="shape mismatches") as exc:
        build_model(python_cfg(checkpoint_path=wrong))
    assert "\n" not in str(exc.value)


def test_a_pickle_checkpoint_executes_nothing(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    bad = tmp_path / "evil.pth"
    bad.write_bytes(pickle.dumps({"state_dict": Evil()}))
    for cfg in (python_cfg(checkpoint_path=str(bad)),
                {"name": "tv", "family": "torchvision", "arch": "lraspp_mobilenet_v3_large", "checkpoint_path": str(bad)}):
        with pytest.raises(ModelError, match="cannot read checkpoint") as exc:
            build_model(cfg)
        assert "\n" not in str(exc.value)
        assert not marker.exists()


@pytest.fixture(scope="module")
def lraspp(tmp_path_factory):
    import torchvision.models.segmentation as tv

    torch.manual_seed(0)
    net = tv.lraspp_mobilenet_v3_large(weights=None, weights_backbone=None, num_classes=19).eval()
    return net, save(net, tmp_path_factory.mktemp("tv") / "lraspp.safetensors")


def test_torchvision_builder_matches_the_network(lraspp):
    net, ckpt = lraspp
    seg = build_model({"name": "tv", "family": "torchvision", "arch": "lraspp_mobilenet_v3_large",
                           "checkpoint_path": ckpt})
    x = torch.rand(1, 3, 64, 96)
    mean, std = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    with torch.no_grad():
        expect = net((x - mean) / std)["out"].softmax(1)
    torch.testing.assert_close(seg.predict_proba(x), expect, atol=1e-5, rtol=1e-4)


def test_torchvision_errors(lraspp, tmp_path):
    _, ckpt = lraspp
    base = {"name": "tv", "family": "torchvision", "checkpoint_path": ckpt}
    for cfg, error, text in [({**base, "arch": "unet"}, ConfigError, "not a torchvision segmentation builder"),
                             ({**base, "arch": "lraspp_mobilenet_v3_large", "checkpoint_path": None}, ModelError,
                              "model.checkpoint_path"),
                             ({**base, "arch": "lraspp_mobilenet_v3_large", "num_classes": 21}, ModelError,
                              "shape mismatches"),
                             ({**base, "arch": "lraspp_mobilenet_v3_large", "labels": "ade20k"}, ModelError,
                              "outputs 19 channels")]:
        with pytest.raises(error, match=text) as exc:
            build_model(cfg)
        assert "\n" not in str(exc.value)


def test_model_files_are_in_the_stage_keys(tmp_path):
    """Replacing a file recomputes, restoring it is a cache hit again: weights, label TSV, the factory's module."""
    ckpt = tmp_path / "w.safetensors"
    save(tiny_net(seed=1), ckpt)
    table = tmp_path / "labels.tsv"
    table.write_text("\n".join(f"c{i}\troad" for i in range(19)))
    cfg = with_defaults(python_cfg(checkpoint_path=str(ckpt), labels=str(table)))
    first = json.dumps(model_hash_config(cfg), sort_keys=True)
    original = ckpt.read_bytes()
    save(tiny_net(seed=2), ckpt)
    assert json.dumps(model_hash_config(cfg), sort_keys=True) != first
    ckpt.write_bytes(original)
    assert json.dumps(model_hash_config(cfg), sort_keys=True) == first
    table.write_text("\n".join(f"c{i}\tcar" for i in range(19)))
    assert json.dumps(model_hash_config(cfg), sort_keys=True) != first
    assert with_defaults({"family": "onnx", "path": "/x/my_net.onnx"})["name"] == "my_net"


@pytest.mark.slow
def test_python_and_torchvision_through_the_cli(tmp_path, lraspp):
    from pairedgta.testing.cli import fast_overrides, report_overrides, report_page, run_cli

    ckpt = save(tiny_net(seed=5), tmp_path / "mine.safetensors")
    r = run_cli(report_overrides(tmp_path) + ["model=python", "model.target=source_nets:tiny_net",
                                              f"model.checkpoint_path={ckpt}"], tmp_path)
    assert r.returncode == 0, r.stderr
    report_page(r, "mine")
    r = run_cli(report_overrides(tmp_path) + ["model=torchvision", "model.arch=lraspp_mobilenet_v3_large",
                                              f"model.checkpoint_path={lraspp[1]}"], tmp_path)
    assert r.returncode == 0, r.stderr
    report_page(r, "lraspp")
    assert "evaluate [tiny_ddrnet]: cache hit" in r.stdout + r.stderr  # the population's, from the first run
    # a bad file: one line, exit 2, nothing of the run's stages written
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not safetensors at all")
    (tmp_path / "b").mkdir()
    r = run_cli(fast_overrides(tmp_path / "b") + ["model=python", "model.target=source_nets:tiny_net",
                                                  f"model.checkpoint_path={bad}"], tmp_path / "b")
    assert r.returncode == 2
    assert "cannot read checkpoint" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "b" / "cache" / "generate").exists()
