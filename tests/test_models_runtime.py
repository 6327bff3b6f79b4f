"""The options every model family shares have one owner (pairedgta/models/runtime.py) and a family declares only
its own arguments: model YAMLs name only what differs from a default, and the stage hashes do not change."""
from __future__ import annotations

import hashlib
import inspect
import subprocess
import sys

import pytest
import yaml

from pairedgta.cache import canonical_json
from pairedgta.configs import CONFIG_DIR
from pairedgta.errors import ConfigError
from pairedgta.models import (FAMILIES, IN_PROJECT_OPTIONS, RuntimeOptions, available_models, build_model,
                              check_model_config, model_config, with_defaults)
from pairedgta.models.runtime import MODEL_KEYS, runtime_defaults
from pairedgta.stages.common import model_hash_config
from pairedgta.stages.planning import run_models

# canonical_json(model_hash_config(model_config(name))) hashed, recorded on main before the model YAMLs dropped
# their repeated defaults (pairedgta/conf/model/*.yaml, commit 9b7d028): every stage key of every model must stay
# (the zoo's demo_* lines since: their weights halved to float16, and the in-package checkpoint_path weights
# of the project's families fingerprinted like a model.path folder's, so retrained weights are no cache hit)
MAIN_MODEL_HASHES = {
    "ddrnet_23": "e1c069512e12e3e3",
    "deeplabv3plus_r101": "add489c5a39054ff",
    "demo_ddrnet": "c8011817c9ad6e0f",
    "demo_ddrnet_short": "33d7cb8a67395932",
    "demo_ddrnet_short_seed1": "5cc41e471375ecbc",
    "demo_deeplabv3plus": "bbef99b06f640c07",
    "demo_deeplabv3plus_adverse": "32dd86e99991e5c5",
    "demo_deeplabv3plus_lowres": "83b419c159b2b899",
    "demo_deeplabv3plus_night": "ed15593aa64da59b",
    "demo_deeplabv3plus_night_seed1": "8393bf3c6911eba3",
    "demo_deeplabv3plus_noaug": "a64807336bb5f6f9",
    "demo_deeplabv3plus_short": "db6ca88c734d4372",
    "demo_deeplabv3plus_strong": "20ae9211b8795b77",
    "demo_deeplabv3plus_towns": "9f244e0397ebd19d",
    "demo_pidnet": "485cabc40fb1f5e2",
    "demo_pidnet_partial": "59d918fcb385a623",
    "demo_segformer": "30c8c666235562eb",
    "demo_segformer_adverse": "0ac254ba8225e06b",
    "demo_segformer_noaug": "cba8d7279ef566af",
    "demo_segformer_noaug_adverse": "b20563f7938a3061",
    "demo_segformer_small": "67c80f7c5a7bf18b",
    "demo_segformer_small_adverse": "ec7fe86d9db796b1",
    "demo_segformer_small_adverse_seed1": "46db1d344902a7b7",
    "demo_segformer_small_noaug": "fc3ed0662d830802",
    "mask2former_swin_l": "ec9ca293df9bda9f",
    "mask2former_swin_s": "19e1dc4bb6cf533e",
    "pidnet_m": "0ca204edc2f9552e",
    "segformer_b0": "d6a06bb4afe1a85e",
    "segformer_b2": "cfd50e8917887a9f",
    "segformer_b5": "7c2c97210e80dbcc",
    "tiny_ddrnet": "83e04c1f9b0d36a2",
    "tiny_deeplabv3plus": "8c383185385acfa3",
    "tiny_mask2former": "6dc63c1219e1a4ff",
    "tiny_pidnet": "cdee354f19e991cc",
    "tiny_segformer": "c85bb124633069ed",
}


def _digest(cfg: dict) -> str:
    return hashlib.sha256(canonical_json(model_hash_config(cfg)).encode()).hexdigest()[:16]


def test_every_model_hashes_as_before_its_yaml_dropped_the_defaults():
    from pairedgta.models import is_source, model_kind

    # the model sources (model=hf, onnx, ...) are new configs with no weights of their own, and the detectors
    # (task=detection) came after this change: pinned in test_model_families
    assert sorted(m for m in available_models() if not is_source(model_config(m))
                  and model_kind(model_config(m)) == "segmenter") == sorted(MAIN_MODEL_HASHES)
    for name, expected in MAIN_MODEL_HASHES.items():
        assert _digest(model_config(name)) == expected, f"model/{name}: its stage hashes would change"


def test_a_run_fills_the_same_defaults_for_its_primary_and_its_other_models():
    """The primary model comes composed by Hydra (with the command line's `model.<key>=`), the others through
    model_config: planning.run_models completes both before any stage hashes them."""
    from omegaconf import OmegaConf

    from pairedgta import schema
    from pairedgta.__main__ import _open_mapping_overrides
    from pairedgta.testing.cli import compose_cfg

    for primary, other in (("demo_ddrnet", "tiny_pidnet"), ("segformer_b5", "mask2former_swin_l"),
                           ("tiny_deeplabv3plus", "demo_segformer")):
        argv = _open_mapping_overrides([f"model={primary}", f"models=[{primary},{other}]", "model.batch_size=2"])
        cfg = OmegaConf.to_container(compose_cfg(argv), resolve=True)
        models = run_models(schema.parse(cfg))
        assert [_digest(m) for m in models.evaluated] == [MAIN_MODEL_HASHES[primary], MAIN_MODEL_HASHES[other]]
        assert models.evaluated[0]["batch_size"] == 2 and models.evaluated[1]["amp"] is None


def test_model_yamls_never_repeat_a_default():
    for path in sorted((CONFIG_DIR / "model").glob("*.yaml")):
        raw = yaml.safe_load(path.read_text())
        filled = with_defaults({"family": raw["family"]})
        repeated = [k for k, v in raw.items() if k in filled and k != "family" and v == filled[k]
                    and type(v) is type(filled[k])]
        assert not repeated, f"{path.name} repeats the default of {repeated}"
        assert not set(raw) & {"device", "runtime"}, f"{path.name} sets the run's device"


def test_the_source_read_defaults_are_the_builders_own():
    """with_defaults reads the builders' signatures without importing torch: what it reads must be what Python
    would use when the key is left out."""
    for family in FAMILIES.names():
        builder = inspect.signature(FAMILIES.resolve(family)).parameters
        declared = FAMILIES.declared_defaults(family)
        literal = {k: p.default for k, p in builder.items() if p.default is not inspect.Parameter.empty}
        assert declared == literal, family
        for key in FAMILIES.meta(family).get("filled", ()):
            assert key in declared, f"{family}: {key} has no default in its builder"
    assert FAMILIES.declared_defaults("pidnet")["upsample_align_corners"] is True
    assert FAMILIES.declared_defaults("ddrnet")["mean"] == (0.485, 0.456, 0.406)  # imported constant, followed
    assert set(IN_PROJECT_OPTIONS) <= set(with_defaults({"family": "deeplabv3plus"}))
    assert with_defaults({"family": "segformer"}) == {"family": "segformer", **runtime_defaults()}


def test_filling_defaults_needs_no_torch():
    code = ("import sys; from pairedgta.models import model_config, check_model_config; "
            "c = model_config('demo_ddrnet'); check_model_config(c); print(c['pad_multiple'], 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["32", "False"]


@pytest.mark.parametrize("key, value, message", [
    ("batch_size", 0, "model.batch_size=0 must be a whole number >= 1, e.g. model.batch_size=4"),
    ("batch_size", "four", "model.batch_size='four' must be a whole number >= 1"),
    ("batch_size", True, "model.batch_size=True must be a whole number >= 1"),
    ("amp", "fp8", "model.amp='fp8' is not one of null, bf16, fp16; e.g. model.amp=bf16"),
    ("channels_last", "yes", "model.channels_last='yes' must be true or false"),
    ("compile", 1, "model.compile=1 must be true or false"),
])
def test_a_bad_runtime_option_is_one_line_before_anything_is_built(key, value, message):
    for cfg in (model_config("tiny_ddrnet", **{key: value}), model_config("segformer_b0", **{key: value})):
        with pytest.raises(ConfigError, match="^" + message.replace("(", r"\(").replace(")", r"\)")) as info:
            check_model_config(cfg)
        assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match=f"model.{key}="):
        RuntimeOptions(**{key: value})


@pytest.mark.parametrize("key, value, message", [
    ("pad_multiple", 0, "pad_multiple=0 must be a whole number >= 1, e.g. pad_multiple=32"),
    ("pad_multiple", None, "pad_multiple=None must be a whole number >= 1"),
    ("upsample_align_corners", None, "upsample_align_corners=None must be true or false"),
])
def test_a_bad_input_option_of_an_in_project_family_is_one_line_before_anything_is_built(key, value, message):
    with pytest.raises(ConfigError, match=r"^model \(demo_pidnet\): " + message):
        check_model_config(model_config("demo_pidnet", **{key: value}))
    with pytest.raises(ConfigError, match=r"^model \(tiny_pidnet\): " + message):
        build_model("tiny_pidnet", **{key: value})


def test_the_family_receives_the_parsed_runtime_options():
    assert RuntimeOptions() == RuntimeOptions.from_config({})
    assert tuple(MODEL_KEYS) == ("batch_size", "amp", "channels_last", "compile")
    assert model_config("mask2former_swin_s")["batch_size"] == 1  # a YAML value that differs from the default
    seg = build_model("tiny_pidnet")
    assert (seg.batch_size, seg.amp, seg.channels_last, str(seg.device)) == (4, None, False, "cpu")
    seg = build_model("tiny_segformer", batch_size=3, amp="bf16")
    assert seg.batch_size == 3 and seg.amp is None  # autocast is CUDA only
    with pytest.raises(ConfigError, match=r"^model \(tiny_ddrnet\): unknown key\(s\) runtime"):
        check_model_config(model_config("tiny_ddrnet", runtime={}))
    with pytest.raises(ConfigError, match=r"^model.batch_size=-2 must be"):
        build_model("tiny_ddrnet", batch_size=-2)


def test_speed_only_options_stay_out_of_the_stage_hash_and_amp_does_not():
    """The runtime options say themselves which change only speed (one list, in RuntimeOptions): a run at
    another batch size, memory layout or with torch.compile is a cache hit; one in bf16 is not."""
    from pairedgta.models.runtime import SPEED_ONLY_KEYS

    assert set(SPEED_ONLY_KEYS) == {"device", "batch_size", "channels_last", "compile"}
    base = model_hash_config(model_config("tiny_ddrnet"))
    for key, value in (("batch_size", 7), ("channels_last", True), ("compile", True)):
        assert model_hash_config(model_config("tiny_ddrnet", **{key: value})) == base, key
    assert model_hash_config({**model_config("tiny_ddrnet"), "device": "cuda"}) == base
    assert model_hash_config(model_config("tiny_ddrnet", amp="bf16")) != base


def test_a_runtime_option_is_set_on_the_command_line_without_a_plus():
    from pairedgta.__main__ import _open_mapping_overrides, mistyped_key

    argv = ["model=demo_ddrnet", "model.amp=bf16", "model.pad_multiple=16", "model.colour=1", "model_overrides.a.b=1"]
    assert _open_mapping_overrides(argv) == ["model=demo_ddrnet", "++model.amp=bf16", "++model.pad_multiple=16",
                                             "model.colour=1", "++model_overrides.a.b=1"]
    assert mistyped_key(["model.amp=bf16", "model.upsample_align_corners=true"]) is None
    assert "did you mean model.batch_size" in mistyped_key(["model.batch_sise=2"])
