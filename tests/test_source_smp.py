"""`model=smp`: a segmentation_models_pytorch save_pretrained folder, built from its config.json without fetching an
encoder (offline: HF_HUB_OFFLINE), its weights loaded strictly as data, padded to the encoder's output stride; bad
folders are one line."""
from __future__ import annotations

import json
import pickle
import shutil

import pytest
import torch
import torch.nn.functional as F

from pairedgta.errors import ModelError
from pairedgta.models import build_model

import segmentation_models_pytorch as smp  # noqa: E402  (the smp extra, in dev)
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def tiny(arch="Unet", seed=0, **kwargs):
    torch.manual_seed(seed)
    options = {"encoder_depth": 3, "classes": 19, **kwargs}
    if arch == "Unet":
        options.setdefault("decoder_channels", (32, 16, 8))
    return getattr(smp, arch)("resnet18", encoder_weights=None, **options).eval()


def smp_seg(path, **keys):
    return build_model({"name": "x", "family": "smp", "path": str(path), **keys})


def by_hand(model, x, multiple):
    """ImageNet normalisation, zero padding to `multiple` (bottom, right), the network's logits cropped, softmax."""
    h, w = x.shape[-2:]
    y = F.pad((x - MEAN) / STD, (0, -w % multiple, 0, -h % multiple))
    with torch.no_grad():
        return model(y)[..., :h, :w].softmax(1)


@pytest.fixture(scope="module")
def unet_dir(tmp_path_factory):
    """A Unet saved as a trained model is: its config.json says encoder_weights=imagenet and a softmax activation."""
    folder = tmp_path_factory.mktemp("unet")
    model = tiny("Unet", activation="softmax2d")
    model.save_pretrained(folder)
    config = json.loads((folder / "config.json").read_text())
    config["encoder_weights"] = "imagenet"  # smp.from_pretrained would download the encoder for this
    (folder / "config.json").write_text(json.dumps(config))
    model.segmentation_head[-1] = torch.nn.Identity()  # the logits, as the source builds it (activation=None)
    return folder, model


def test_smp_folder_gives_the_networks_numbers_offline(unet_dir):
    folder, model = unet_dir
    seg = smp_seg(folder)
    assert seg.contract.pad_multiple == model.encoder.output_stride == 8
    assert seg.contract.output == "logits" and seg.contract.mean == (0.485, 0.456, 0.406)
    x = torch.rand(2, 3, 45, 83)  # not a multiple of 8: padded, then cropped
    probs = seg.predict_proba(x)
    assert probs.shape == (2, 19, 45, 83)
    torch.testing.assert_close(probs.sum(1), torch.ones(2, 45, 83), atol=1e-5, rtol=0)
    torch.testing.assert_close(probs, by_hand(model, x, 8), atol=1e-5, rtol=1e-4)
    assert "encoder_weights=None" in seg.network.executes and "safetensors" in seg.network.executes


def test_an_architecture_that_checks_its_input_size_gets_it_padded(tmp_path):
    model = tiny("PSPNet")
    assert model.requires_divisible_input_shape
    with pytest.raises(RuntimeError, match="divisible by 8"):
        model(torch.rand(1, 3, 45, 83))
    model.save_pretrained(tmp_path)
    seg = smp_seg(tmp_path)
    x = torch.rand(1, 3, 45, 83)
    torch.testing.assert_close(seg.predict_proba(x), by_hand(model, x, 8), atol=1e-5, rtol=1e-4)


def test_bad_folders_are_one_line(unet_dir, tmp_path):
    folder, _ = unet_dir

    def variant(name, edit=None, weights=None):
        out = tmp_path / name
        shutil.copytree(folder, out)
        if edit is not None:
            config = json.loads((out / "config.json").read_text())
            edit(config)
            (out / "config.json").write_text(json.dumps(config))
        if weights is not None:
            (out / "model.safetensors").write_bytes(weights)
        return str(out)

    (tmp_path / "file.safetensors").write_bytes(b"x")
    (tmp_path / "empty").mkdir()
    cases = [
        (None, "needs its folder; set model.path=DIR"),
        (str(tmp_path / "nowhere"), "does not exist"),
        (str(tmp_path / "file.safetensors"), "is a file, not a folder"),
        (str(tmp_path / "empty"), "has no config.json"),
        (variant("arch", lambda c: c.update(_model_class="Transformer")), "_model_class='Transformer', not a"),
        (variant("channels", lambda c: c.update(in_channels=1)), "in_channels=1"),
        (variant("encoder", lambda c: c.update(encoder_name="no-such-encoder")), "smp.Unet(**config.json) fails"),
        (variant("narrow", lambda c: c.update(decoder_channels=[16, 8, 4])), "does not fit the model config.json"),
        (variant("corrupt", weights=(folder / "model.safetensors").read_bytes()[:300]), "cannot read checkpoint"),
    ]
    for path, text in cases:
        with pytest.raises(ModelError) as exc:
            build_model({"name": "x", "family": "smp", "path": path})
        msg = str(exc.value)
        assert "\n" not in msg and text in msg, (path, msg)
    (tmp_path / "empty" / "config.json").write_text(json.dumps({"_model_class": "Unet"}))
    with pytest.raises(ModelError, match="has no weights") as exc:
        smp_seg(tmp_path / "empty")
    assert "\n" not in str(exc.value)


def test_a_pickle_weights_file_executes_nothing(unet_dir, tmp_path):
    folder, _ = unet_dir
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    evil = tmp_path / "evil"
    evil.mkdir()
    shutil.copy(folder / "config.json", evil / "config.json")
    (evil / "pytorch_model.bin").write_bytes(pickle.dumps({"encoder.conv1.weight": Evil()}))
    with pytest.raises(ModelError, match="cannot read checkpoint") as exc:
        smp_seg(evil)
    assert "\n" not in str(exc.value) and not marker.exists()
    # the same folder with pytorch_model.bin a plain state dict loads (torch.load(weights_only=True))
    _, model = unet_dir
    torch.save(model.state_dict(), evil / "pytorch_model.bin")
    seg = smp_seg(evil)
    x = torch.rand(1, 3, 32, 40)
    torch.testing.assert_close(seg.predict_proba(x), by_hand(model, x, 8), atol=1e-5, rtol=1e-4)
    assert "weights_only" in seg.network.executes


@pytest.mark.slow
def test_smp_folder_through_the_cli(unet_dir, tmp_path):
    from pairedgta.testing.cli import report_overrides, report_page, run_cli

    folder = tmp_path / "my_unet"
    shutil.copytree(unet_dir[0], folder)
    r = run_cli(report_overrides(tmp_path) + ["model=smp", f"model.path={folder}"], tmp_path)
    assert r.returncode == 0, r.stderr
    report_page(r, "my_unet")
    evals = {json.loads((p / "manifest.json").read_text())["config"]["model"]["name"]: p
             for p in (tmp_path / "cache" / "evaluate").iterdir() if not p.name.startswith(".")}
    assert "my_unet" in evals and (evals["my_unet"] / "xi.csv").is_file()
