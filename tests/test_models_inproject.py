"""In-project DeepLabV3+ / PIDNet / DDRNet: official checkpoint layouts, strict loading, tiny forwards.

Everything runs offline on CPU; shape checks build the full graphs on the meta device (no memory, no init).
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml

from pairedgta.cityscapes import NUM_CLASSES
from pairedgta.errors import ModelError
from pairedgta.configs import CONFIG_DIR
from pairedgta.models import build_model, model_config
from pairedgta.models import ddrnet, deeplabv3plus, pidnet
from pairedgta.models.checkpoint import build_network

# names/shapes of the official training graphs (a copy of the shared reference, kept with the tests)
KEYS_FILE = Path(__file__).parent / "data" / "official_checkpoint_keys.json"
LOSS_BUFFER = "criterion.weight"  # class weights of the training loss, saved by the training wrappers

# family -> (architecture module, full config, tiny config, prefix of its entry in the key file)
FAMILIES = {
    "pidnet": (pidnet, "pidnet_m", "tiny_pidnet", "pidnet_m"),
    "ddrnet": (ddrnet, "ddrnet_23", "tiny_ddrnet", "ddrnet_23"),
    "deeplabv3plus": (deeplabv3plus, "deeplabv3plus_r101", "tiny_deeplabv3plus", "deeplabv3plus"),
}
# per family: a whole residual block / branch to delete, and a tensor whose shape to corrupt (tiny graphs)
BREAKAGE = {
    "pidnet": ("layer3.1.", "final_layer.conv2.weight"),
    "ddrnet": ("layer4_.1.", "final_layer.conv2.weight"),
    "deeplabv3plus": ("classifier.aspp.convs.2.", "classifier.classifier.3.weight"),
}
# a parameter that is in every checkpoint and read at inference
PROBE = {
    "pidnet": "final_layer.conv2.weight",
    "ddrnet": "final_layer.conv2.weight",
    "deeplabv3plus": "classifier.classifier.3.weight",
}


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """These graphs are tiny; with 2 cores shared by other jobs, a second intra-op thread only adds stalls."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def official_keys() -> dict[str, dict[str, list[int]]]:
    raw = json.loads(KEYS_FILE.read_text())
    out = {}
    for family, (_, _, _, prefix) in FAMILIES.items():
        (entry,) = [v for k, v in raw.items() if k.startswith(prefix)]
        out[family] = {name: list(shape) for name, shape in entry.items()}
    return out


def shapes_of(module: torch.nn.Module) -> dict[str, list[int]]:
    return {name: list(t.shape) for name, t in module.state_dict().items()}


def meta_graph(family: str, *, augment: bool) -> torch.nn.Module:
    arch, full, _, _ = FAMILIES[family]
    with torch.device("meta"):
        return build_network(arch.architecture, model_config(full), augment=augment)


def diff_report(got: dict, expected: dict) -> str:
    missing = sorted(set(expected) - set(got))
    extra = sorted(set(got) - set(expected))
    wrong = sorted(k for k in set(got) & set(expected) if got[k] != expected[k])
    return f"missing {missing[:5]} extra {extra[:5]} wrong shapes {[(k, got[k], expected[k]) for k in wrong[:5]]}"


def fake_weights(shapes: dict[str, list[int]], seed: int) -> dict[str, torch.Tensor]:
    """Random but well-scaled tensors (He-scaled convs, near-identity BN), so a forward stays finite."""
    g = torch.Generator().manual_seed(seed)
    out: dict[str, torch.Tensor] = {}
    for name, shape in shapes.items():
        if name.endswith("num_batches_tracked"):
            out[name] = torch.tensor(1000, dtype=torch.long)
        elif name.endswith("running_var"):
            out[name] = 1.0 + 0.1 * torch.rand(shape, generator=g)
        elif len(shape) == 4:
            fan_in = max(1, math.prod(shape[1:]))
            out[name] = torch.randn(shape, generator=g) * math.sqrt(1.0 / fan_in)
        elif name.endswith(".weight"):
            out[name] = 1.0 + 0.1 * torch.randn(shape, generator=g)
        else:
            out[name] = 0.1 * torch.randn(shape, generator=g)
    return out


# Forward semantics pinned to the official implementations: per-class mean and std of the raw logits of small
# graphs (same code paths as the full ones) for seeded weights and input, computed once by running the official
# PIDNet / DDRNet / VainF code on exactly these weights.
GOLDEN_SEED = 2024
GOLDEN_CFG = {
    "pidnet": {"planes": 8, "ppm_planes": 8, "head_planes": 16},
    "ddrnet": {"layers": [1, 1, 1, 1], "planes": 8, "spp_planes": 8, "head_planes": 16},
    "deeplabv3plus": {"layers": [1, 1, 1, 2]},  # full widths; two layer4 blocks exercise the dilation change
}
GOLDEN_STATS = {
    "pidnet": [
        0.527773, 0.483123, -0.260869, -0.253841, 0.406524, -0.0205316, -0.309207, -0.208619, 0.0666309, 0.145734,
        0.109795, -0.204421, -0.115033, -0.00747275, -0.115122, -0.0669134, -0.239574, -0.176339, 0.0101898, 0.0684608,
        0.138395, 0.0950977, 0.136482, 0.125553, 0.211749, 0.129367, 0.0784077, 0.0847892, 0.0970566, 0.0792923,
        0.126766, 0.0556394, 0.149092, 0.113975, 0.113674, 0.112218, 0.089839, 0.103181,
    ],
    "ddrnet": [
        -2.02014, -0.503611, -0.631865, 2.16722, 1.10125, -0.692413, 1.23488, 1.40582, 0.313891, -1.42852,
        0.906143, -0.532107, 1.76422, 0.461912, 1.21401, -0.891977, 1.61301, -0.530112, 0.187456, 0.644656,
        0.333787, 0.335812, 0.667688, 0.410815, 0.317554, 0.368887, 0.50205, 0.365128, 0.518424, 0.401978,
        0.341824, 0.521024, 0.254581, 0.396599, 0.468077, 0.530437, 0.301229, 0.181972,
    ],
    "deeplabv3plus": [
        -0.370911, -0.617378, 0.317362, -0.416149, -0.00902242, 0.000284289, 0.152928, 0.1897, 0.276028, -0.0867565,
        -0.000977952, -0.168195, 0.14139, -0.0544089, 0.217347, 0.294314, -0.0830751, -0.656898, -0.012308, 0.108159,
        0.0923025, 0.0850088, 0.0990797, 0.08265, 0.067878, 0.097438, 0.100559, 0.0940789, 0.0991452, 0.0900322,
        0.082975, 0.0961228, 0.0804464, 0.0808266, 0.0919703, 0.0742311, 0.132841, 0.0858564,
    ],
}


def golden_input() -> torch.Tensor:
    return torch.randn(2, 3, 64, 96, generator=torch.Generator().manual_seed(GOLDEN_SEED))


def tiny_training_weights(family: str, seed: int = 123) -> dict[str, torch.Tensor]:
    arch, _, tiny, _ = FAMILIES[family]
    return fake_weights(shapes_of(build_network(arch.architecture, model_config(tiny), augment=True)), seed)


# --------------------------------------------------------------------------------------------------------------
# Architecture layout == the official graphs


@pytest.mark.parametrize("family", FAMILIES)
def test_training_graph_matches_official_keys(family, official_keys):
    got = shapes_of(meta_graph(family, augment=True))
    assert got == official_keys[family], diff_report(got, official_keys[family])


@pytest.mark.parametrize("family", FAMILIES)
def test_inference_graph_is_official_minus_training_heads(family, official_keys):
    prefixes = FAMILIES[family][0].TRAINING_ONLY_PREFIXES
    if family != "deeplabv3plus":  # the documented training-only heads really are in the released layout
        assert all(any(k.startswith(p) for k in official_keys[family]) for p in prefixes)
    expected = {k: v for k, v in official_keys[family].items() if not k.startswith(prefixes)}
    got = shapes_of(meta_graph(family, augment=False))
    assert got == expected, diff_report(got, expected)


@pytest.mark.parametrize("family", FAMILIES)
def test_forward_matches_the_official_implementation(family):
    module = build_network(FAMILIES[family][0].architecture, GOLDEN_CFG[family]).eval()
    module.load_state_dict(fake_weights(shapes_of(module), seed=GOLDEN_SEED), strict=True)
    with torch.inference_mode():
        logits = module(golden_input())
    stats = torch.cat([logits.mean(dim=(0, 2, 3)), logits.std(dim=(0, 2, 3))])
    torch.testing.assert_close(stats, torch.tensor(GOLDEN_STATS[family]), rtol=1e-3, atol=1e-4)


def test_dilated_timm_backbone_matches_torchvision_semantics():
    """VainF's backbone is torchvision's ResNet with replace_stride_with_dilation=[F, F, T]; the timm backbone
    with output_stride=16 must compute the same function from the same weights (layer4 needs >1 block)."""
    from torchvision.models.resnet import Bottleneck as TvBottleneck, ResNet as TvResNet

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        reference = TvResNet(TvBottleneck, [1, 1, 1, 2], replace_stride_with_dilation=[False, False, True]).eval()
        x = torch.randn(1, 3, 80, 96)
    mine = build_network(deeplabv3plus.architecture, {"layers": [1, 1, 1, 2]}).backbone.eval()
    mine.load_state_dict({k: v for k, v in reference.state_dict().items() if not k.startswith("fc.")}, strict=True)
    with torch.no_grad():
        ref = reference.layer4(reference.layer3(reference.layer2(reference.layer1(
            reference.maxpool(reference.relu(reference.bn1(reference.conv1(x))))))))
        out = mine.layer4(mine.layer3(mine.layer2(mine.layer1(mine.maxpool(mine.act1(mine.bn1(mine.conv1(x))))))))
    assert out.shape == ref.shape == (1, 2048, 5, 6)
    torch.testing.assert_close(out, ref)


# --------------------------------------------------------------------------------------------------------------
# Loading released files


def official_layout(family: str, weights: dict[str, torch.Tensor]) -> dict:
    """The container each project publishes (see docs/datasets-and-models.md)."""
    if family == "pidnet":  # bare dict of the training wrapper: `model.` prefix, aux heads, loss weights
        out = {f"model.{k}": v for k, v in weights.items()}
        out[f"sem_loss.{LOSS_BUFFER}"] = torch.rand(NUM_CLASSES)
        return out
    if family == "ddrnet":  # HRNet-style trainer under DataParallel, wrapped in `state_dict`
        out = {f"module.model.{k}": v for k, v in weights.items()}
        out[f"module.loss.{LOSS_BUFFER}"] = torch.rand(NUM_CLASSES)
        return {"state_dict": out, "epoch": 484}
    return {  # VainF save_ckpt(): numpy best_score, optimiser and scheduler state next to `model_state`
        "cur_itrs": 30000,
        "model_state": weights,
        "optimizer_state": {"state": {}, "param_groups": [{"lr": 0.01, "momentum": 0.9, "params": [0, 1]}]},
        "scheduler_state": {"last_epoch": 30000, "base_lrs": [0.01]},
        "best_score": np.float64(0.7621),
    }


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_full_model_loads_released_layout(family, official_keys, tmp_path, caplog):
    arch, full, _, _ = FAMILIES[family]
    weights = fake_weights(official_keys[family], seed=7)
    path = tmp_path / "released.pt"
    torch.save(official_layout(family, weights), path)

    with caplog.at_level(logging.INFO, logger="pairedgta.models.checkpoint"):
        seg = build_model(full, checkpoint_path=str(path), device="cpu")
    state = seg.module.state_dict()
    assert set(state) == {k for k in official_keys[family] if not k.startswith(arch.TRAINING_ONLY_PREFIXES)}
    for key in (PROBE[family], next(k for k in state if k.endswith("running_var"))):
        assert torch.equal(state[key], weights[key]), key
    notes = [r.getMessage() for r in caplog.records if "training-only" in r.getMessage()]
    if family == "deeplabv3plus":
        assert notes == []
    else:  # one line naming the aux heads and the loss buffer
        assert len(notes) == 1 and "\n" not in notes[0]
        assert all(p.rstrip(".") in notes[0] for p in arch.TRAINING_ONLY_PREFIXES) and "loss" in notes[0]

    probs = seg.predict_proba(torch.rand(1, 3, 64, 96))
    assert probs.shape == (1, NUM_CLASSES, 64, 96)
    assert torch.isfinite(probs).all()
    torch.testing.assert_close(probs.sum(1), torch.ones(1, 64, 96))


LAYOUTS = {
    "bare": lambda sd: sd,
    "state_dict": lambda sd: {"state_dict": sd, "epoch": 3},
    "model_state": lambda sd: {"model_state": sd, "best_score": np.float64(0.5)},
    "model": lambda sd: {"model": sd},
    "module_prefix": lambda sd: {f"module.{k}": v for k, v in sd.items()},
    "model_prefix": lambda sd: {f"model.{k}": v for k, v in sd.items()},
    "nested_and_both_prefixes": lambda sd: {"state_dict": {f"module.model.{k}": v for k, v in sd.items()}},
}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("family", FAMILIES)
def test_checkpoint_layouts_load_strictly(family, layout, tmp_path):
    _, _, tiny, _ = FAMILIES[family]
    weights = tiny_training_weights(family)
    weights["loss.criterion.weight"] = torch.rand(NUM_CLASSES)  # training wrapper buffer: dropped, not an error
    path = tmp_path / f"{layout}.pth"
    torch.save(LAYOUTS[layout](weights), path)

    fresh = build_model(tiny).module.state_dict()
    loaded = build_model(tiny, checkpoint_path=str(path)).module.state_dict()
    assert not torch.equal(fresh[PROBE[family]], weights[PROBE[family]])
    for key, value in loaded.items():
        assert torch.equal(value, weights[key]), key


@pytest.mark.parametrize("family", FAMILIES)
def test_wrong_checkpoint_fails_with_key_list(family, tmp_path):
    _, _, tiny, _ = FAMILIES[family]
    block, reshaped = BREAKAGE[family]
    weights = tiny_training_weights(family)

    no_block = {k: v for k, v in weights.items() if not k.startswith(block)}
    assert len(no_block) < len(weights)
    torch.save(no_block, tmp_path / "no_block.pt")
    with pytest.raises(ModelError) as err:
        build_model(tiny, checkpoint_path=str(tmp_path / "no_block.pt"))
    message = str(err.value)
    assert "\n" not in message and "no_block.pt" in message
    assert f"{len(weights) - len(no_block)} missing" in message and block in message

    bad_shape = dict(weights)
    bad_shape[reshaped] = torch.zeros(NUM_CLASSES - 1, *weights[reshaped].shape[1:])
    bad_shape["extra_head.weight"] = torch.zeros(3)
    torch.save({"state_dict": bad_shape}, tmp_path / "bad_shape.pt")
    with pytest.raises(ModelError) as err:
        build_model(tiny, checkpoint_path=str(tmp_path / "bad_shape.pt"))
    message = str(err.value)
    assert "\n" not in message
    assert "1 shape mismatches" in message and reshaped in message and str(NUM_CLASSES - 1) in message
    assert "1 unexpected" in message and "extra_head.weight" in message


def test_missing_or_corrupt_file_is_one_line_model_error(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(ModelError, match="nope.pth") as err:
        build_model("tiny_pidnet", checkpoint_path=str(missing))
    assert "\n" not in str(err.value)

    corrupt = tmp_path / "corrupt.pth"
    corrupt.write_bytes(b"\x80\x02 definitely not a checkpoint" * 10)
    with pytest.raises(ModelError, match="corrupt.pth") as err:
        build_model("tiny_ddrnet", checkpoint_path=str(corrupt))
    assert "\n" not in str(err.value)

    empty = tmp_path / "empty.pth"
    torch.save({"epoch": 1}, empty)
    with pytest.raises(ModelError, match="empty.pth.*no state dict") as err:
        build_model("tiny_deeplabv3plus", checkpoint_path=str(empty))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "name,file",
    [
        ("deeplabv3plus_r101", "best_deeplabv3plus_resnet101_cityscapes_os16.pth"),
        ("pidnet_m", "PIDNet_M_Cityscapes_val.pt"),
        ("ddrnet_23", "DDRNet"),
    ],
)
def test_full_model_without_checkpoint_says_what_to_download(name, file):
    with pytest.raises(ModelError) as err:
        build_model(name)
    message = str(err.value)
    assert "\n" not in message
    assert file in message and "github.com/" in message and "model.checkpoint_path=" in message


# --------------------------------------------------------------------------------------------------------------
# Tiny graphs: forward, preprocessing inside the segmenter, determinism


@pytest.mark.parametrize("size", [(64, 128), (70, 130)])
@pytest.mark.parametrize("family", FAMILIES)
def test_tiny_forward_shapes_and_probabilities(family, size):
    seg = build_model(FAMILIES[family][2], batch_size=2)  # 3 images -> two chunks
    images = torch.rand(3, 3, *size)
    probs = seg.predict_proba(images)
    assert probs.shape == (3, NUM_CLASSES, *size)
    assert torch.isfinite(probs).all() and (probs >= 0).all()
    torch.testing.assert_close(probs.sum(1), torch.ones(3, *size))
    labels, confidence = seg.predict(images[:1])
    assert labels.shape == confidence.shape == (1, *size)


@pytest.mark.parametrize("size", [(64, 128), (70, 130)])
@pytest.mark.parametrize("family", FAMILIES)
def test_normalisation_and_padding_happen_inside(family, size):
    """predict_proba on [0,1] RGB == softmax of the net on ImageNet-normalised, zero-padded input, cropped."""
    cfg = model_config(FAMILIES[family][2])
    seg = build_model(cfg["name"])
    images = torch.rand(2, 3, *size)
    mean = torch.tensor(cfg["mean"]).view(1, 3, 1, 1)
    std = torch.tensor(cfg["std"]).view(1, 3, 1, 1)
    h, w = size
    ph, pw = -h % cfg["pad_multiple"], -w % cfg["pad_multiple"]
    with torch.inference_mode():
        logits = seg.module(F.pad((images - mean) / std, (0, pw, 0, ph)))
        assert logits.shape[-2:] != (h + ph, w + pw)  # the nets predict at reduced resolution
        logits = F.interpolate(logits, size=(h + ph, w + pw), mode="bilinear",
                               align_corners=cfg["upsample_align_corners"])
        expected = logits[..., :h, :w].softmax(1)
    torch.testing.assert_close(seg.predict_proba(images), expected)


@pytest.mark.parametrize("family", FAMILIES)
def test_tiny_models_are_seeded_and_leave_global_rng_alone(family):
    tiny = FAMILIES[family][2]
    rng = torch.get_rng_state()
    a = build_model(tiny).module.state_dict()
    b = build_model(tiny).module.state_dict()
    assert torch.equal(torch.get_rng_state(), rng)
    assert all(torch.equal(a[k], b[k]) for k in a)
    c = build_model(tiny, init_seed=1).module.state_dict()
    assert not torch.equal(a[PROBE[family]], c[PROBE[family]])


def test_model_configs_have_the_shared_layout():
    """The YAML names the model and its weights; the shared options come from their one default."""
    for family, (_, full, tiny, _) in FAMILIES.items():
        for name in (full, tiny):
            raw = yaml.safe_load((CONFIG_DIR / "model" / f"{name}.yaml").read_text())
            assert raw["name"] == name and raw["family"] == family
            assert "device" not in raw  # the run's top-level device, never a model's own key
            assert not {"batch_size", "amp", "channels_last", "compile", "mean", "std"} & set(raw)
            assert "checkpoint_path" in raw and raw["checkpoint_path"] is None
            cfg = model_config(name)
            assert cfg["batch_size"] == 4 and cfg["amp"] is None
            assert cfg["channels_last"] is False and cfg["compile"] is False
            assert cfg["random_init"] is (name == tiny)
            pad, align = {"pidnet": (32, True), "ddrnet": (32, False), "deeplabv3plus": (1, False)}[family]
            assert (cfg["pad_multiple"], cfg["upsample_align_corners"]) == (pad, align)


def test_a_model_with_nan_weights_stops_naming_the_model():
    import numpy as np
    import pytest
    import torch

    from pairedgta.errors import ModelError
    from pairedgta.models import build_model

    seg = build_model("tiny_ddrnet")
    with torch.no_grad():
        next(seg.module.parameters()).fill_(float("nan"))
    with pytest.raises(ModelError, match="tiny_ddrnet: the model's outputs are not finite"):
        seg.predict(np.zeros((1, 3, 64, 128), dtype=np.float32))
