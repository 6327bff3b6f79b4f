"""experiments/train_demo_model.py: the recipe's pieces, and a tiny run from the CLI that resumes."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pairedgta.cityscapes import IGNORE_INDEX
from pairedgta.testing.cli import run_app_in_process

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
import train_demo_model as tdm  # noqa: E402

IDENTITY = {"brightness_delta": 0, "contrast_range": [1.0, 1.0], "saturation_range": [1.0, 1.0], "hue_delta": 0}


def test_ohem_keeps_the_hard_pixels_and_at_least_min_kept():
    target = torch.tensor([[[0, 1, 2, IGNORE_INDEX]]])  # 1 x 1 x 4
    logits = torch.full((1, 3, 1, 4), -10.0)
    logits[0, 0, 0, 0] = 10.0  # pixel 0: confident and right (easy)
    logits[0, 0, 0, 1] = 10.0  # pixel 1: confident and wrong (hard)
    logits[0, :, 0, 2] = 0.0   # pixel 2: uniform, p = 1/3 (hard)
    per_pixel = F.cross_entropy(logits, target, ignore_index=IGNORE_INDEX, reduction="none")[0, 0]
    plain = tdm.ohem_cross_entropy(logits, target, None, 0)
    assert plain == pytest.approx(float(per_pixel[:3].mean()))
    assert plain == pytest.approx(float(F.cross_entropy(logits, target, ignore_index=IGNORE_INDEX)))
    hard = tdm.ohem_cross_entropy(logits, target, 0.7, 1)
    assert hard == pytest.approx(float(per_pixel[1:3].mean()))  # the easy pixel and the ignored one are out
    only_hardest = tdm.ohem_cross_entropy(logits, target, 1e-12, 1)  # nothing under thresh: the min_kept hardest
    assert only_hardest == pytest.approx(float(per_pixel[1]))
    everything = tdm.ohem_cross_entropy(logits, target, 0.7, 10)  # min_kept above the labelled count: all of them
    assert everything == pytest.approx(float(per_pixel[:3].mean()))
    empty = tdm.ohem_cross_entropy(logits.requires_grad_(), torch.full_like(target, IGNORE_INDEX), 0.7, 1)
    assert float(empty.detach()) == 0.0 and empty.requires_grad  # an all-ignore batch still backpropagates (zero)


def test_sample_crops_flips_and_pads_with_ignore():
    rng = np.random.default_rng(0)
    h, w = 32, 64
    label = np.repeat((np.arange(w) // 16).astype(np.uint8)[None], h, axis=0)  # 4 vertical bands 0..3
    image = np.stack([label * 60, label * 0, label * 0], axis=-1).astype(np.uint8)  # red encodes the band
    aug = {"scale_range": [1.0, 1.0], "crop": [16, 32], "cat_max_ratio": 1.0, "flip": 0.5, "photometric": IDENTITY}
    for _ in range(10):
        x, y = tdm.sample(image, label, rng, aug)
        assert x.shape == (3, 16, 32) and y.shape == (16, 32)
        assert torch.equal((x[0] * 255 / 60).round().long(), y)  # image and label stay aligned through the flip
    small = {**aug, "scale_range": [0.5, 0.5], "crop": [24, 48]}
    x, y = tdm.sample(image, label, rng, small)
    assert x.shape == (3, 24, 48) and (y[16:] == IGNORE_INDEX).all() and (x[:, 16:] == 0).all()


def test_rare_class_sampling_favours_rare_classes_and_crops_around_them():
    labels = np.zeros((4, 32, 64), dtype=np.uint8)  # road everywhere
    labels[1, 5:10, 40:44] = 7     # 20 px of traffic sign, in image 1 only
    labels[2, 0:2, 0:3] = 7        # 6 px of sign: below min_pixels, so image 2 does not count for it
    labels[3, 20:, :] = 2          # building, common
    rcs = tdm.RareClassSampler(labels, temperature=0.01, min_pixels=16)
    assert list(rcs.classes) == [0, 2, 7] and rcs.prob[2] > 0.99  # the sign dominates at a low temperature
    rng = np.random.default_rng(0)
    draws = [rcs.draw(rng) for _ in range(200)]
    assert all(i == 1 for i, c in draws if c == 7) and sum(c == 7 for _, c in draws) > 190
    flat = tdm.RareClassSampler(labels, temperature=1e4, min_pixels=16)
    assert np.allclose(flat.prob, 1 / 3, atol=1e-3)  # a high temperature is uniform over the classes present
    image = np.zeros((32, 64, 3), dtype=np.uint8)
    aug = {"scale_range": [1.0, 1.0], "crop": [8, 16], "cat_max_ratio": 0.75, "flip": 0.5, "photometric": IDENTITY}
    for _ in range(20):  # an 8 x 16 crop of a 32 x 64 image shows the 5 x 4 px sign only when aimed at it
        _, y = tdm.sample(image, labels[1], rng, aug, focus=7)
        assert (y == 7).any()
    _, y = tdm.sample(image, labels[0], rng, aug, focus=7)  # class absent: an ordinary random crop
    assert y.shape == (8, 16) and not (y == 7).any()


def test_photometric_distortion_stays_in_range_and_changes_colour():
    rng = np.random.default_rng(1)
    img = torch.rand(3, 8, 8)
    p = {"brightness_delta": 32, "contrast_range": [0.5, 1.5], "saturation_range": [0.5, 1.5], "hue_delta": 18}
    outs = [tdm.photometric(img.clone(), rng, p) for _ in range(20)]
    assert all(o.min() >= 0 and o.max() <= 1 for o in outs)
    assert sum(not torch.allclose(o, img) for o in outs) >= 15  # each step with p = 0.5: almost never all four off
    assert torch.allclose(tdm.photometric(img.clone(), rng, IDENTITY), img, atol=1e-5)


def test_contrast_blend_lowers_contrast_and_grayscale_removes_colour():
    img = torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(0))
    base = {"brightness_delta": 0, "contrast_range": [0.3, 0.3], "saturation_range": [1.0, 1.0], "hue_delta": 0}
    # MMSegmentation's contrast scales the pixels: the image gets darker, its spread shrinks with its mean
    outs = {mode: [tdm.photometric(img.clone(), np.random.default_rng(s), {**base, "contrast_mode": mode})
                   for s in range(12)] for mode in ("multiply", "blend")}
    # the hue step (delta 0) round-trips through HSV and moves pixels by ~1e-7: that is not the contrast step
    changed = [i for i, o in enumerate(outs["blend"]) if not torch.allclose(o, img, atol=1e-4)]
    assert changed  # the contrast step ran for some seeds (probability 0.5)
    for i in changed:
        m, b_ = outs["multiply"][i], outs["blend"][i]
        assert torch.allclose(m, img * 0.3, atol=1e-6)
        assert abs(float(b_.mean()) - float(img.mean())) < 0.02 < abs(float(m.mean()) - float(img.mean()))
        assert float(b_.std()) < 0.35 * float(img.std())
    grey = tdm.photometric(img.clone(), np.random.default_rng(0), {**IDENTITY, "grayscale_p": 1.0})
    assert torch.allclose(grey[0], grey[1]) and torch.allclose(grey[1], grey[2])
    # off by default: the draws (and hence a recipe's images) are those of the original distortion
    assert torch.equal(tdm.photometric(img.clone(), np.random.default_rng(5), {**base, "grayscale_p": 0.0}),
                       tdm.photometric(img.clone(), np.random.default_rng(5), base))


def test_learning_rate_warms_up_then_decays_to_zero():
    t = {"steps": 100, "warmup": 10, "poly_power": 1.0}
    f = [tdm.lr_factor(s, t) for s in range(101)]
    assert f[0] == pytest.approx(0.1, abs=0.01) and max(f) == f[9]
    assert all(a >= b for a, b in zip(f[9:], f[10:])) and f[100] < 0.01


def test_state_key_ignores_run_length_but_not_the_recipe():
    cfg = {"model_name": "demo_a", "data": {"a": 1}, "arch": {}, "augment": {}, "loss": {"ohem_thresh": 0.7},
           "seed": 0, "renderer": {}, "region": {},
           "train": {"steps": 10, "lr": 1e-3, "threads": 2, "eval_every": 5, "checkpoint_every": 1}}
    longer = {**cfg, "train": {**cfg["train"], "steps": 20, "threads": 1}}
    plain = {**cfg, "loss": {"ohem_thresh": None}}
    other = {**cfg, "model_name": "demo_b"}  # two zoo members never share a checkpoint
    assert tdm.state_key(cfg) == tdm.state_key(longer) != tdm.state_key(plain)
    assert tdm.state_key(other) != tdm.state_key(cfg)


def test_recipe_values_are_checked_up_front_with_the_key_named():
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module("pairedgta.conf", version_base=None):
        cfg = OmegaConf.to_container(compose("train_demo"), resolve=True)
    tdm.check_config(cfg)  # the shipped recipe passes
    bad = [
        ("loss", "ohem_thresh", "high", "loss.ohem_thresh='high' is invalid"),
        ("loss", "ohem_min_kept", -1, "loss.ohem_min_kept=-1"),
        ("train", "steps", 0, "train.steps=0 is invalid; set it to an integer >= 1"),
        ("train", "lr", "1e-3x", "train.lr='1e-3x'"),
        ("augment", "scale_range", [2.0, 0.5], "augment.scale_range=[2.0, 0.5]"),
        ("augment", "crop", [128], "augment.crop=[128]"),
        ("data", "train_towns", 2.5, "data.train_towns=2.5"),
        ("augment", "rare_class_sampling", {"temperature": -1, "min_pixels": 16},
         "augment.rare_class_sampling.temperature=-1 is invalid"),
        ("augment", "rare_class_sampling", {"temperature": 0.05, "min_pixels": 0},
         "augment.rare_class_sampling.min_pixels=0"),
        ("augment", "photometric", {**cfg["augment"]["photometric"], "contrast_mode": "hsv"},
         "augment.photometric.contrast_mode='hsv' is invalid; set it to multiply (MMSegmentation) or blend"),
    ]
    for section, key, value, message in bad:
        broken = {**cfg, section: {**cfg[section], key: value}}
        with pytest.raises(SystemExit, match=re.escape(message)):
            tdm.check_config(broken)
    with pytest.raises(SystemExit, match="arch.family='unet' is invalid; set it to segformer, ddrnet"):
        tdm.check_config({**cfg, "arch": {**cfg["arch"], "family": "unet"}})
    with pytest.raises(SystemExit, match="model_name='../x'"):
        tdm.check_config({**cfg, "model_name": "../x"})
    with pytest.raises(SystemExit, match="work_dir=''"):
        tdm.check_config({**cfg, "work_dir": ""})
    adverse = {"conditions": ["Night-EXTRASUNNY", "Day-RAIN"], "towns": 4, "scenes_per_town": 8, "town_seed": 1100}
    tdm.check_config({**cfg, "data": {**cfg["data"], "adverse": adverse}})
    assert tdm.adverse_towns({**cfg, "data": {**cfg["data"], "adverse": adverse}}) == [
        (1100, "Night-EXTRASUNNY"), (1101, "Day-RAIN"), (1102, "Night-EXTRASUNNY"), (1103, "Day-RAIN")]
    for change, message in ((dict(conditions=["Night-SNOW"]), "data.adverse.conditions=['Night-SNOW'] is invalid"),
                            (dict(towns=0), "data.adverse.towns=0 is invalid"),
                            (dict(town_seed=1040), "data.adverse.town_seed=1040 is invalid; set it to an integer whose"),
                            (dict(town_seed=5000), "data.adverse.town_seed=5000 is invalid"),
                            (dict(scenes_per_town=0), "data.adverse.scenes_per_town=0")):
        with pytest.raises(SystemExit, match=re.escape(message)):
            tdm.check_config({**cfg, "data": {**cfg["data"], "adverse": {**adverse, **change}}})
    # a Day-only recipe keeps its checkpoint key and data fingerprint with the (empty) adverse section
    day_only = {**cfg, "data": {k: v for k, v in cfg["data"].items() if k != "adverse"}}
    assert tdm.state_key(day_only) == tdm.state_key(cfg) and tdm.data_fingerprint(day_only) == tdm.data_fingerprint(cfg)
    assert tdm.state_key({**cfg, "data": {**cfg["data"], "adverse": adverse}}) != tdm.state_key(cfg)
    tdm.check_config({**cfg, "loss": {**cfg["loss"], "ohem_thresh": None}})  # plain cross-entropy is allowed
    tdm.check_config({**cfg, "augment": {**cfg["augment"], "rare_class_sampling": {"temperature": 0.05, "min_pixels": 16}}})


@pytest.mark.slow
def test_a_tiny_run_from_the_cli_writes_a_loadable_model_and_resumes(tmp_path):
    """Two towns, three steps, then a longer rerun that continues from the checkpoint."""
    out = tmp_path / "model"
    args = [sys.executable, str(ROOT / "experiments" / "train_demo_model.py"),
            f"cache_dir={tmp_path / 'cache'}", f"out_dir={out}", f"work_dir={tmp_path / 'work'}",
            f"hydra.run.dir={tmp_path / 'run'}", "tracking.enabled=false",
            "renderer.width=128", "renderer.height=64", "renderer.samples=1", "renderer.denoise=false",
            "data.train_towns=2", "data.train_scenes_per_town=1", "data.val_towns=1", "data.val_scenes_per_town=1",
            "augment.crop=[32,64]", "arch.hidden_sizes=[8,8,16,16]", "arch.num_attention_heads=[1,1,1,1]",
            "arch.depths=[1,1,1,1]", "arch.decoder_hidden_size=16", "loss.ohem_min_kept=100",
            "train.batch_size=2", "train.warmup=1", "train.eval_every=2", "train.checkpoint_every=1"]
    # both runs in this process, through the script's Hydra entry with the argv a user types (a fresh
    # interpreter would add only its ~8 s of imports)
    first = run_app_in_process(tdm.main, [*args[1:], "train.steps=3"], tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    card = json.loads((out / "model_card.json").read_text())
    assert card["train"]["steps"] == 3 and card["data"]["train_images"] == 2 and card["loss"]["ohem_thresh"] == 0.7
    assert [h["step"] for h in card["history"]] == [2, 3] and 0.0 <= card["val_miou"] <= 1.0
    assert (out / "model.safetensors").stat().st_size > 0 and (out / "README.md").is_file()
    render_s = card["render_seconds"]
    assert render_s > 0
    # the rerun continues from the checkpoint on disk
    second = run_app_in_process(tdm.main, [*args[1:], "train.steps=5"], tmp_path)
    assert second.returncode == 0, second.stderr[-2000:]
    assert "at step 3" in second.stderr + second.stdout
    card = json.loads((out / "model_card.json").read_text())
    assert [h["step"] for h in card["history"]] == [2, 3, 4, 5]
    assert card["render_seconds"] == pytest.approx(render_s)  # read from the cache: still the rendering cost

    from pairedgta.models import build_model

    model = build_model("demo_segformer", path=str(out))
    probs = model.predict_proba(np.zeros((1, 64, 128, 3), dtype=np.uint8))
    assert probs.shape[-2:] == (64, 128) and probs.shape[-3] == 19
    # shipped in float16 (the package stays small), computed in float32
    assert _dtypes(out / "model.safetensors") == {"F16"} and card["weights_dtype"] == "float16"
    assert {p.dtype for p in model.module.parameters()} == {torch.float32}


def _dtypes(path: Path) -> set[str]:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return {f.get_slice(k).get_dtype() for k in f.keys() if f.get_slice(k).get_dtype().startswith("F")}


def test_every_zoo_member_composes_builds_within_4m_parameters_and_matches_its_model_config():
    """The training recipe (pairedgta/conf/zoo/) and the shipped model config (pairedgta/conf/model/) name
    the same widths: the weights load strictly, so a drift would fail at the first run."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from pairedgta.models import model_config

    with initialize_config_module("pairedgta.conf", version_base=None):
        for name in ("demo_segformer", "demo_segformer_noaug", "demo_ddrnet", "demo_pidnet"):
            cfg = OmegaConf.to_container(compose("train_demo", overrides=[f"zoo={name}"]), resolve=True)
            tdm.check_config(cfg)
            assert cfg["model_name"] == name and cfg["out_dir"].endswith(f"weights/{name}")
            net = tdm.build_network(cfg)
            assert sum(p.numel() for p in net.parameters()) <= 4_000_000
            mcfg = model_config(name)
            assert mcfg["family"] == cfg["arch"]["family"]
            for key, value in cfg["arch"].items():
                if key != "family" and cfg["arch"]["family"] != "segformer":
                    assert mcfg[key] == value, (name, key)
    noaug = OmegaConf.to_container(compose_zoo("demo_segformer_noaug"), resolve=True)
    full = OmegaConf.to_container(compose_zoo("demo_segformer"), resolve=True)
    assert noaug["augment"]["photometric"] is None and full["augment"]["photometric"]
    assert noaug["arch"] == full["arch"] and noaug["data"] == full["data"]


def compose_zoo(name: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("pairedgta.conf", version_base=None):
        return compose("train_demo", overrides=[f"zoo={name}"])


def test_without_photometric_distortion_a_crop_keeps_its_colours():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
    label = np.zeros((64, 128), dtype=np.uint8)
    a = {"crop": [64, 128], "scale_range": [1.0, 1.0], "cat_max_ratio": 1.0, "flip": 0.0, "photometric": None}
    for seed in range(5):
        x, _ = tdm.sample(image, label, np.random.default_rng(seed), a)
        assert torch.allclose(x, torch.tensor(image).permute(2, 0, 1).float() / 255)


@pytest.mark.slow
def test_a_tiny_ddrnet_run_from_the_cli_ships_strict_safetensors_weights(tmp_path):
    """The project's own families train through the same script and load through the model config."""
    out = tmp_path / "model"
    args = [sys.executable, str(ROOT / "experiments" / "train_demo_model.py"), "zoo=demo_ddrnet",
            f"cache_dir={tmp_path / 'cache'}", f"out_dir={out}", f"work_dir={tmp_path / 'work'}",
            f"hydra.run.dir={tmp_path / 'run'}", "tracking.enabled=false",
            "renderer.width=128", "renderer.height=64", "renderer.samples=1", "renderer.denoise=false",
            "data.train_towns=1", "data.train_scenes_per_town=1", "data.val_towns=1", "data.val_scenes_per_town=1",
            "augment.crop=[32,64]", "arch.planes=4", "arch.spp_planes=4", "arch.head_planes=8",
            "train.batch_size=2", "train.warmup=1", "train.eval_every=2", "train.checkpoint_every=1", "train.steps=2",
            "data.adverse.conditions=[Night-EXTRASUNNY]", "data.adverse.towns=1", "data.adverse.scenes_per_town=1"]
    run = run_app_in_process(tdm.main, args[1:], tmp_path)  # the CLI in this process: the first test ran it fresh
    assert run.returncode == 0, run.stderr[-2000:]
    card = json.loads((out / "model_card.json").read_text())
    assert card["family"] == "ddrnet" and card["model"] == "demo_ddrnet" and "zoo=demo_ddrnet" in card["command"]
    readme = (out / "README.md").read_text()
    assert "demo_ddrnet" in readme and "1 daytime (Day-EXTRASUNNY) scenes and 1 (50%) scenes of 1 other towns under Night-EXTRASUNNY" in readme
    assert card["data"]["train_images"] == 2 and card["data"]["adverse"]["conditions"] == ["Night-EXTRASUNNY"]
    assert _dtypes(out / "model.safetensors") == {"F16"} and card["weights_dtype"] == "float16"
    # the adverse town was rendered under the night light: darker than the daytime town
    from pairedgta.datasets import load_image
    night = list((tmp_path / "cache").rglob("Night-EXTRASUNNY.png"))
    day = list((tmp_path / "cache").rglob("Day-EXTRASUNNY.png"))
    assert night and day and np.mean(load_image(night[0])) < 0.5 * np.mean(load_image(day[0]))

    from pairedgta.errors import ModelError
    from pairedgta.models import build_model

    weights = out / "model.safetensors"
    model = build_model("demo_ddrnet", checkpoint_path=str(weights), planes=4, spp_planes=4, head_planes=8)
    probs = model.predict_proba(np.zeros((1, 64, 128, 3), dtype=np.uint8))
    assert probs.shape == (1, 19, 64, 128)
    with pytest.raises(ModelError, match="does not fit the architecture"):  # the shipped widths: strict refusal
        build_model("demo_ddrnet", checkpoint_path=str(weights))
    weights.write_bytes(b"not a safetensors file")
    with pytest.raises(ModelError, match="cannot read checkpoint .*safetensors"):
        build_model("demo_ddrnet", checkpoint_path=str(weights), planes=4, spp_planes=4, head_planes=8)


def _data_cfg(**data):
    return {"renderer": {"backend": "blender"}, "region": {"name": "t"}, "camera": {"mode": "fixed"},
            "condition": "Day-EXTRASUNNY", "data": {"train_towns": 2, "workers": 1, **data}}


def test_exported_data_reads_back_pixel_exact_and_refuses_other_settings(tmp_path):
    """data.export_to / data.from_dir: a machine without Blender trains on exactly the rendered pixels."""
    rng = np.random.default_rng(0)
    splits = {"train": (rng.integers(0, 256, (3, 16, 32, 3), dtype=np.uint8), rng.integers(0, 19, (3, 16, 32), dtype=np.uint8)),
              "val": (rng.integers(0, 256, (1, 16, 32, 3), dtype=np.uint8), np.full((1, 16, 32), 255, dtype=np.uint8))}
    cfg = _data_cfg()
    tdm.export_data(cfg, tmp_path / "d", splits, 12.5)
    assert not (tmp_path / "d.tmp").exists()
    # where it is read from, or how many renderer processes drew it, does not make it other data
    back, seconds = tdm.import_data(_data_cfg(from_dir="x", workers=4), tmp_path / "d")
    assert seconds == 12.5
    for k in splits:
        assert np.array_equal(back[k][0], splits[k][0]) and np.array_equal(back[k][1], splits[k][1])
    with pytest.raises(SystemExit, match=r"data.from_dir=.*exported with other data/renderer/camera settings"):
        tdm.import_data(_data_cfg(train_towns=3), tmp_path / "d")
    with pytest.raises(SystemExit, match=r"data.export_to=.* exists"):
        tdm.export_data(cfg, tmp_path / "d", splits, 1.0)
    (tmp_path / "d" / "train" / "00001.webp").write_bytes(b"not an image")
    with pytest.raises(SystemExit, match=r"train/00001 is missing or corrupt"):
        tdm.import_data(cfg, tmp_path / "d")
    with pytest.raises(SystemExit, match=r"no manifest.json; write the folder with data.export_to"):
        tdm.import_data(cfg, tmp_path)


@pytest.mark.slow  # loader worker processes
def test_worker_batches_are_seeded_per_step_so_a_resume_draws_the_same_batches():
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, (4, 32, 64, 3), dtype=np.uint8)
    labels = rng.integers(0, 19, (4, 32, 64), dtype=np.uint8)
    a = {"crop": [16, 32], "scale_range": [0.5, 2.0], "cat_max_ratio": 1.0, "flip": 0.5,
         "photometric": {"brightness_delta": 32, "contrast_range": [0.5, 1.5], "saturation_range": [0.5, 1.5], "hue_delta": 18}}
    t = {"steps": 4, "batch_size": 2, "loader_workers": 2}
    full = list(tdm.batches(images, labels, None, a, t, None, seed=0, start=0))
    assert [s for s, _, _ in full] == [1, 2, 3, 4]
    resumed = list(tdm.batches(images, labels, None, a, {**t, "loader_workers": 1}, None, seed=0, start=2))
    for (s1, x1, y1), (s2, x2, y2) in zip(full[2:], resumed):
        assert s1 == s2 and torch.equal(x1, x2) and torch.equal(y1, y2)
    assert not torch.equal(full[0][1], full[1][1])
    other_seed = next(tdm.batches(images, labels, None, a, t, None, seed=1, start=0))
    assert not torch.equal(other_seed[1], full[0][1])
    # the in-process stream of the CPU recipe is untouched
    seq = list(tdm.batches(images, labels, np.random.default_rng(0), a, {**t, "loader_workers": 0}, None, seed=0, start=0))
    ref = tdm.batch(images, labels, np.random.default_rng(0), a, 2)
    assert torch.equal(seq[0][1], ref[0])


def test_device_and_loader_settings_are_checked():
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module("pairedgta.conf", version_base=None):
        cfg = OmegaConf.to_container(compose("train_demo"), resolve=True)
    with pytest.raises(SystemExit, match="train.device='tpu' is invalid; set it to auto, cpu or cuda"):
        tdm.check_config({**cfg, "train": {**cfg["train"], "device": "tpu"}})
    with pytest.raises(SystemExit, match="train.loader_workers=-1 is invalid"):
        tdm.check_config({**cfg, "train": {**cfg["train"], "loader_workers": -1}})
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="train.device=cuda but torch sees no CUDA device"):
            tdm.pick_device("cuda")
    assert tdm.pick_device("cpu").type == "cpu"
    # the device and the loader's worker count are not the recipe; per-step seeding is
    assert tdm.state_key({**cfg, "train": {**cfg["train"], "device": "cuda"}}) == tdm.state_key(cfg)
    assert tdm.state_key({**cfg, "train": {**cfg["train"], "loader_workers": 2}}) == \
        tdm.state_key({**cfg, "train": {**cfg["train"], "loader_workers": 8}}) != tdm.state_key(cfg)
