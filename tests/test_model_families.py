"""One shared builder for the in-project model families (pairedgta/models/checkpoint.py: build_inproject, registered
`via` it in pairedgta/models/__init__.py): a family is its module's `architecture` arguments plus one registry line,
and every default is written once."""
from __future__ import annotations

import ast
import hashlib
import importlib
import inspect
import json
import sys
import textwrap

import pytest
import torch

from pairedgta.errors import ConfigError, ModelError
from pairedgta.models import FAMILIES, IN_PROJECT, available_models, model_config, with_defaults
from pairedgta.models.checkpoint import NormalizedSegmenter, build_inproject, build_network
from pairedgta.models.runtime import IMAGENET_MEAN, RuntimeOptions
from pairedgta.registry import Registry, accepted_keys

# sha256 (first 16 hex digits) of json.dumps(with_defaults(model_config(name)), sort_keys=True), computed before the
# families shared one builder (commit 16fbf1c): the model config every stage hashes. A model YAML edited on
# purpose changes its line; a change of the builders or the registry must change none.
HASHED_MODEL_CONFIGS = {
    # the model sources (docs/models.md): their configs as shipped, contract keys filled with null
    "export": "c6195b09685bd9e8",
    "hf": "6f138c5f26699973",
    "onnx": "b3d621a3dac2cd39",
    "python": "ac3745d90dac34a0",
    "smp": "60138f30bf1323c3",
    "torchvision": "81f1897c8a18e126",  # num_classes: null (19 for segmentation, 91 for a detector), detection release
    "ddrnet_23": "8c297ab3cc1d718e",
    "deeplabv3plus_r101": "23d7eed2184ff292",
    "demo_ddrnet": "62e76832938c7849",
    "demo_ddrnet_short": "091af96fec32e423",
    "demo_ddrnet_short_seed1": "e9a13d1f6d8c63d7",
    "demo_deeplabv3plus": "321eb61d4815dfc1",
    "demo_deeplabv3plus_adverse": "542c97b294d0eb0d",
    "demo_deeplabv3plus_lowres": "0ce7ecd274d50134",
    "demo_deeplabv3plus_night": "1c64d2d9ad8a63e7",
    "demo_deeplabv3plus_night_seed1": "d9b2e00f7c200195",
    "demo_deeplabv3plus_noaug": "c7e1227acbc6f4f3",
    "demo_deeplabv3plus_short": "daa64f0b6b728322",
    "demo_deeplabv3plus_strong": "4e4fe685b09e6d0f",
    "demo_deeplabv3plus_towns": "f907cbfafc135b32",
    "demo_pidnet": "6ff0b27bf6ca2f28",
    "demo_pidnet_partial": "aeb4079cb9acf3ea",
    "demo_segformer": "efd33c1b329c119b",
    "demo_segformer_adverse": "9b3bdd94f7631ba6",
    "demo_segformer_noaug": "9c8fc6657f50ab16",
    "demo_segformer_noaug_adverse": "2ca98bfdfa10155c",
    "demo_segformer_small": "24d3d713503a64f4",
    "demo_segformer_small_adverse": "d1fb665a229a291c",
    "demo_segformer_small_adverse_seed1": "fb95766aa3a899a4",
    "demo_segformer_small_noaug": "7dd4dda38fa64762",
    "mask2former_swin_l": "e846e7f1b019c811",
    "mask2former_swin_s": "a96c265dda40f79e",
    "pidnet_m": "f255bf06b94cd13b",
    "segformer_b0": "17c044b7ba6081e6",
    "segformer_b2": "eb58db86a0c765fc",
    "segformer_b5": "e602876c7a2af488",
    "tiny_ddrnet": "701c74b44119675f",
    # the detection zoo (task=detection; demo_det_reference retrained, the weights it had are demo_fcos)
    "demo_det_reference": "17f35203c4807fc6",
    "demo_fasterrcnn": "e96caac53293c3c5",
    "demo_fcos": "6544383d63e8990d",
    "demo_fcos_adverse": "21d2b19db2c27799",
    "demo_fcos_allweather": "dce81f96a5c03e0c",
    "demo_fcos_fog": "2a1653955753ff17",
    "demo_fcos_ft": "a0c6c6b6dfef0326",
    "demo_fcos_ft_seed1": "2bef0b11bdf96edb",
    "demo_fcos_hires": "c4d69b378f6b8c78",
    "demo_fcos_long": "fad8b192810add71",
    "demo_fcos_lowres": "1cda533119fd3e5c",
    "demo_fcos_night": "87243566602f7d64",
    "demo_fcos_noaug": "d0352d7096b67a9f",
    "demo_fcos_plain": "19c6be8a79d989fb",
    "demo_fcos_rain": "17f859a4f8847f5c",
    "demo_fcos_small": "7d7e278349927bcc",
    "demo_fcos_strongaug": "d574bfa09a29e0eb",
    "demo_fcos_towns": "143fd88d7ebea677",
    "demo_retinanet": "dffe63fa5a6931f5",
    "demo_retinanet_adverse": "be4c37cf39ffebb4",
    "demo_retinanet_long": "e4afc04b07eddeb5",
    "demo_retinanet_lowres": "23321c28a1fa591b",
    # task=detection's test-sized detectors (pairedgta/models/detectors.py)
    "tiny_fasterrcnn": "08ff9c0778ee59eb",
    "tiny_fcos": "9ee88cb2ec619e47",
    "tiny_retinanet": "09c01f7f5f407355",
    "tiny_deeplabv3plus": "b604139f0d8a4b97",
    "tiny_mask2former": "85292c6cf1b75e3d",
    "tiny_pidnet": "82e484b088ddb6b1",
    "tiny_segformer": "abcd87fcac366b74",
}

TOY_SOURCE = '''
"""A toy in-project family: its weights, the input they expect, its architecture arguments; nothing else."""
from torch import nn

from pairedgta.cityscapes import NUM_CLASSES

TRAINING_ONLY_PREFIXES = ("aux.",)
CHECKPOINT_FILE = "toy.pt"
CHECKPOINT_SOURCE = "the toy's README"
PRETRAINED = {"pad_multiple": 4}


def architecture(name, augment, *, width: int = 3, depth: int = 1):
    """A 1x1-convolution stack."""
    layers = [nn.Conv2d(3, width, 1)] + [nn.Conv2d(width, width, 1) for _ in range(depth - 1)]
    net = nn.Sequential(*layers, nn.Conv2d(width, NUM_CLASSES, 1))
    if augment:
        net.aux = nn.Conv2d(width, 1, 1)
    return net
'''


def test_every_model_config_hashes_as_before():
    got = {name: hashlib.sha256(json.dumps(with_defaults(model_config(name)), sort_keys=True).encode()).hexdigest()[:16]
           for name in available_models()}
    assert got == HASHED_MODEL_CONFIGS


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """A family declared in two places: its module (written here) and one registry line."""
    module = f"toy_family_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent(TOY_SOURCE))
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    registry = Registry("model family", "model.family")
    registry.register("toy", f"{module}:architecture", **IN_PROJECT)
    yield registry, module
    sys.modules.pop(module, None)


def test_a_toy_family_declares_its_architecture_and_one_registry_line(toy, tmp_path):
    registry, module = toy
    shared = {p.name for p in inspect.signature(build_inproject).parameters.values() if p.kind is p.KEYWORD_ONLY}
    # read from the sources: the toy's module (which imports torch) stays unimported
    assert registry.declared_keys("toy") == shared | {"width", "depth"}
    declared = registry.declared_defaults("toy")
    assert module not in sys.modules
    assert (declared["width"], declared["depth"], declared["pad_multiple"]) == (3, 1, 4)  # its own, its PRETRAINED
    assert declared["mean"] == IMAGENET_MEAN and declared["upsample_align_corners"] is False  # the builder's
    # ... and they are what the imported, combined builder uses
    target = registry.resolve("toy")
    assert accepted_keys(target) == registry.declared_keys("toy")
    assert declared == {k: p.default for k, p in inspect.signature(target).parameters.items()
                        if p.default is not inspect.Parameter.empty}

    cfg = {"name": "toy_a", "family": "toy", "random_init": True, "init_seed": 0, "width": 5}
    seg = registry.build("toy", cfg, runtime=RuntimeOptions())
    assert isinstance(seg, NormalizedSegmenter) and seg.name == "toy_a"
    assert seg.pad_multiple == 4 and seg.module[0].out_channels == 5 and len(seg.module) == 2
    again = registry.build("toy", cfg, runtime=RuntimeOptions()).module.state_dict()
    assert all(torch.equal(v, again[k]) for k, v in seg.module.state_dict().items())  # init_seed
    probs = seg.predict_proba(torch.rand(1, 3, 10, 13))  # padded to 12 x 16, cropped back
    assert probs.shape == (1, 19, 10, 13)

    # released weights: the training-only head of its module's TRAINING_ONLY_PREFIXES is dropped
    weights = build_network(sys.modules[module].architecture, {"depth": 2}, augment=True).state_dict()
    assert any(k.startswith("aux.") for k in weights)
    torch.save(weights, tmp_path / "toy.pt")
    loaded = registry.build("toy", {"name": "t", "family": "toy", "depth": 2, "checkpoint_path": str(tmp_path / "toy.pt")},
                            runtime=RuntimeOptions())
    assert torch.equal(loaded.module[1].weight, weights["1.weight"])

    with pytest.raises(ModelError, match=r"^model 't' needs its released weights \(toy.pt; published at the toy's README\)"):
        registry.build("toy", {"name": "t", "family": "toy"}, runtime=RuntimeOptions())
    with pytest.raises(ConfigError, match=r"^model: unknown key\(s\) widht; known keys: .*depth.*width"):
        registry.build("toy", {"name": "t", "family": "toy", "widht": 2}, runtime=RuntimeOptions())


def test_the_model_functions_take_a_registered_family(toy, monkeypatch):
    from pairedgta.models import build_model, check_model_config, family_keys

    registry, _ = toy
    monkeypatch.setitem(FAMILIES._targets, "toy", registry._targets["toy"])
    monkeypatch.setitem(FAMILIES._meta, "toy", registry._meta["toy"])
    filled = with_defaults({"name": "t", "family": "toy"})
    assert filled["pad_multiple"] == 4 and filled["init_seed"] is None and "width" not in filled  # hashed as declared
    assert {"width", "depth", "batch_size"} <= family_keys("toy")
    check_model_config({"name": "t", "family": "toy", "width": 2})
    seg = build_model({"name": "t", "family": "toy", "random_init": True, "width": 2}, batch_size=2)
    assert seg.module[0].out_channels == 2 and seg.batch_size == 2


def test_a_family_cannot_redeclare_a_shared_option(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    for i, (change, message) in enumerate([
        ('PRETRAINED = {"pad_multiple": 4}', 'PRETRAINED = {"pad_multple": 4}'),
        ("*, width: int = 3,", "*, mean: list = (0.5, 0.5, 0.5), width: int = 3,"),
    ]):
        module = f"bad_family_{i}_{tmp_path.name.replace('-', '_')}"
        (tmp_path / f"{module}.py").write_text(textwrap.dedent(TOY_SOURCE).replace(change, message))
        importlib.invalidate_caches()
        registry = Registry("model family", "model.family")
        registry.register("bad", f"{module}:architecture", **IN_PROJECT)
        with pytest.raises(ValueError, match="pad_multple, which the builder does not take" if i == 0
                           else "mean is the builder's argument"):
            registry.resolve("bad")
        sys.modules.pop(module, None)


@pytest.mark.parametrize("family", ["ddrnet", "pidnet", "deeplabv3plus"])
def test_an_in_project_family_writes_each_default_once(family):
    """Its module declares its architecture arguments with their defaults and nothing the shared builder has;
    no `.get(key, default)` repeats one, and the network classes take the values the architecture passes."""
    module = importlib.import_module(f"pairedgta.models.{family}")
    tree = ast.parse(inspect.getsource(module))
    shared = {p.name for p in inspect.signature(build_inproject).parameters.values() if p.kind is p.KEYWORD_ONLY}
    arch = {p.name for p in inspect.signature(module.architecture).parameters.values() if p.kind is p.KEYWORD_ONLY}
    assert arch and not arch & shared
    assert set(getattr(module, "PRETRAINED", {})) <= shared
    gets = [ast.unparse(n) for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
            and n.func.attr == "get" and len(n.args) == 2]
    assert not gets, gets
    assert "build" not in vars(module)  # the family builder is the shared one
    with torch.device("meta"):
        assert isinstance(build_network(module.architecture, {}), torch.nn.Module)
