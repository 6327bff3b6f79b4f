"""experiments/train_demo_detector.py: the training step on a tiny random network and a synthetic batch (no Blender),
float16 weights that build_detector loads back, resuming from a checkpoint, the augmentation's boxes and the
held-out AP by pycocotools."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
import train_demo_detector as tdd  # noqa: E402

from pairedgta.detection.boxes import INSTANCE_CLASSES, Box  # noqa: E402

ARCH = {"width": 0.25, "fpn_channels": 32, "min_size": 64, "max_size": 128}
TRAIN = {"steps": 4, "warmup": 1, "lr": 1e-3, "weight_decay": 0.01, "optimizer": "adamw", "min_lr_ratio": 0.01}
CAR, PERSON = INSTANCE_CLASSES.index("car"), INSTANCE_CLASSES.index("person")


def tiny():
    torch.manual_seed(0)
    return tdd.build_network("fcos", {"name": "tiny_fcos", **ARCH})


def synthetic_batch():
    """Two 64 x 128 images, each a bright car-box and a dark person-box on grey."""
    images, targets = [], []
    for shift in (0, 20):
        img = torch.full((3, 64, 128), 0.5)
        img[:, 20:40, 10 + shift:50 + shift] = 0.9
        img[:, 10:50, 80:92] = 0.1
        images.append(img)
        targets.append({"boxes": torch.tensor([[10.0 + shift, 20, 50 + shift, 40], [80, 10, 92, 50]]),
                        "labels": torch.tensor([CAR + 1, PERSON + 1])})
    return images, targets


# 4 s on the 2-core machine beside a training job (three network builds, five steps): the fast tier
def test_two_steps_fp16_weights_load_in_build_detector_and_resume(tmp_path):
    from safetensors import safe_open

    from pairedgta.models import build_model
    torch.set_num_threads(2)
    images, targets = synthetic_batch()
    module = tiny()
    opt, sched = tdd.make_optimizer(module, TRAIN)
    rng = np.random.default_rng(0)
    losses = [tdd.train_step(module, opt, sched, images, targets, [64, 128], 10.0) for _ in range(2)]
    assert all(np.isfinite(v) for l in losses for v in l.values())
    assert {"classification", "bbox_regression", "bbox_ctrness"} <= set(losses[0])
    ckpt = tmp_path / "checkpoint.pt"
    tdd.save_checkpoint(ckpt, module, opt, sched, 2, rng, [{"step": 2}], 1.5)

    weights = tmp_path / "model.safetensors"
    tdd.seg.save_half(module.state_dict(), weights, {"family": "fcos", "model": "tiny_fcos"})
    with safe_open(str(weights), framework="pt") as f:
        assert {f.get_tensor(k).dtype for k in f.keys()} <= {torch.float16, torch.int64}
    det = build_model({"name": "tiny_fcos", "family": "fcos", "checkpoint_path": str(weights), **ARCH})
    assert det.kind == "detector"
    for k, v in module.state_dict().items():
        assert torch.allclose(det.module.state_dict()[k].float(), v.float().half().float()), k
    out = det.detect(np.zeros((2, 64, 128, 3), np.uint8))
    assert len(out) == 2 and out[0].boxes.shape[1] == 4

    # resume: a fresh network and optimiser continue from the checkpoint as the uninterrupted run does
    expected = tdd.train_step(module, opt, sched, images, targets, [64, 128], 10.0)
    fresh = tiny()
    opt2, sched2 = tdd.make_optimizer(fresh, TRAIN)
    rng2 = np.random.default_rng(123)
    step, history, elapsed = tdd.load_checkpoint(ckpt, fresh, opt2, sched2, rng2)
    assert (step, history, elapsed) == (2, [{"step": 2}], 1.5)
    assert rng2.bit_generator.state == np.random.default_rng(0).bit_generator.state
    assert sched2.last_epoch == sched.last_epoch - 1
    resumed = tdd.train_step(fresh, opt2, sched2, images, targets, [64, 128], 10.0)
    assert resumed["loss"] == pytest.approx(expected["loss"], rel=1e-4)


def test_augment_keeps_boxes_on_their_objects():
    image = np.zeros((64, 128, 3), np.uint8)
    image[20:40, 10:50] = 255
    sample = tdd.Sample(image, [Box(1, CAR, (10.0, 20.0, 50.0, 40.0), 800.0),
                                Box(2, PERSON, (100.0, 5.0, 104.0, 10.0), 20.0, ignore="small")],
                        small_mask=np.zeros((64, 128), bool))
    assert len(sample.xyxy) == 1  # the ignore region is not a training box
    a = {"crop": [64, 128], "scale_range": [1.0, 1.0], "flip": 1.0, "photometric": None, "mask_small": True}
    img, target = tdd.augment_sample(sample, np.random.default_rng(0), a, 2.0)
    assert img.shape == (3, 64, 128)
    for (x0, y0, x1, y1) in target["boxes"].round().int().tolist():
        inside = img[0, y0:y1, x0:x1]
        assert inside.numel() and float(inside.mean()) > 0.95  # the box covers the (flipped, scaled) white car
    assert target["labels"].tolist() == [CAR + 1] * len(target["boxes"])


def test_mask_small_paints_only_the_small_objects():
    image = np.full((8, 8, 3), 200, np.uint8)
    mask = np.zeros((8, 8), bool)
    mask[1:3, 1:3] = True
    out = tdd.mask_small(tdd.Sample(image, [], mask))
    assert (out[1, 1] == [124, 116, 104]).all() and (out[5, 5] == 200).all() and (image[1, 1] == 200).all()


def test_coco_eval_and_threshold_of_perfect_detections():
    image = np.zeros((64, 128, 3), np.uint8)
    gt = [Box(1, CAR, (10.0, 20.0, 50.0, 40.0), 800.0), Box(2, PERSON, (80.0, 10.0, 92.0, 50.0), 480.0),
          Box(3, CAR, (100.0, 5.0, 104.0, 10.0), 20.0, ignore="small")]
    samples = [tdd.Sample(image, gt)]
    dets = [{"boxes": np.array([[10, 20, 50, 40], [80, 10, 92, 50], [100, 5, 104, 10], [0, 50, 20, 60]], np.float32),
             "scores": np.array([0.9, 0.8, 0.7, 0.3], np.float32),
             "labels": np.array([CAR + 1, PERSON + 1, CAR + 1, CAR + 1])}]
    r = tdd.coco_eval(samples, dets)
    assert r["ap50_per_class"] == {"person": pytest.approx(1.0), "car": pytest.approx(1.0)}
    assert r["gt_per_class"] == {"person": 1, "car": 1}
    assert r["ap"] == pytest.approx(1.0)
    threshold, f1 = tdd.best_threshold(samples, dets)
    assert f1 == pytest.approx(1.0) and 0.3 < threshold <= 0.8  # the detection on the ignore region costs nothing


def test_model_yaml_names_the_architecture():
    cfg = {"model_name": "demo_x", "arch": {"family": "fcos", **ARCH}}
    text = tdd.model_yaml(cfg, 0.35)
    import yaml

    y = yaml.safe_load(text)
    assert y == {"name": "demo_x", "family": "fcos", "checkpoint_path": "pkg://models/weights/demo_x/model.safetensors",
                 **ARCH, "score_threshold": 0.35}
    default = yaml.safe_load(tdd.model_yaml({"model_name": "demo_x", "arch": {**cfg["arch"], "min_size": 512,
                                                                              "max_size": 1024}}, 0.35))
    assert "min_size" not in default and "max_size" not in default  # build_detector's defaults are not repeated


def test_model_yaml_keeps_only_the_family_s_keys():
    import yaml

    cfg = {"model_name": "demo_r", "arch": {"family": "retinanet", **ARCH, "center_sampling_radius": 1.5,
                                            "smallest_anchor": 16}}
    y = yaml.safe_load(tdd.model_yaml(cfg, 0.5))
    assert "center_sampling_radius" not in y and y["smallest_anchor"] == 16 and y["family"] == "retinanet"


RECIPES = sorted(p.stem for p in (ROOT / "pairedgta" / "conf" / "detector_zoo").glob("*.yaml"))
ZOO = ROOT / "zoo" / "detection" / "pairedgta_detection_zoo"


@pytest.mark.parametrize("member", RECIPES)
def test_recipes_compose_and_the_shipped_weights_load_strictly_into_them(member):
    """Every recipe of pairedgta/conf/detector_zoo composes and passes the training script's checks; its network
    takes the member's shipped weights strictly (the recipe is the one they were trained with), its model
    config names the same architecture, and the card the same recipe: seed, steps, data and starting point."""
    import json

    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from pairedgta.models import model_config

    with initialize_config_module("pairedgta.conf", version_base="1.3"):
        cfg = OmegaConf.to_container(compose("train_detector", overrides=[f"detector_zoo={member}"]), resolve=True)
    assert cfg["model_name"] == member and cfg["out_dir"] == f"zoo/detection/pairedgta_detection_zoo/{member}"
    tdd.check_config(cfg)
    torch.manual_seed(0)
    module = tdd.build_network(cfg["arch"]["family"], tdd.network_config(cfg))
    assert sum(p.numel() for p in module.parameters()) < 6_000_000
    assert (ZOO / member / "model.safetensors").is_file(), f"{member}: a recipe without its trained member"
    tdd.init_weights(module, ZOO / member)  # strict: every key, every shape
    card = json.loads((ZOO / member / "model_card.json").read_text())
    assert card["model"] == member and card["arch"] == cfg["arch"] and card["seed"] == cfg["seed"]
    assert card["train"]["steps"] == cfg["train"]["steps"] and card["train"]["init_from"] == cfg["train"]["init_from"]
    assert card["data"]["adverse"] == cfg["data"]["adverse"] and card["augment"] == cfg["augment"]
    model = model_config(member)
    assert model["family"] == cfg["arch"]["family"]
    assert all(model[k] == v for k, v in cfg["arch"].items() if k in model), (model, cfg["arch"])
    if cfg["train"]["init_from"]:  # fine-tuned from a member of the zoo, which has its own recipe
        assert Path(cfg["train"]["init_from"]).name in RECIPES
    # the README is the card's (a paragraph written by hand may come beside it), a fine-tune's with its whole cost
    readme = (ZOO / member / "README.md").read_text().splitlines()
    assert [line for line in tdd.card_readme(card).splitlines() if line not in readme] == [], member
    chain = [name for name, _ in tdd.chain_seconds(card)]
    assert chain[-1] == member and (len(chain) > 1) == bool(cfg["train"]["init_from"])
    if member == "demo_det_reference":
        assert chain == ["demo_fcos", "demo_fcos_long", "demo_det_reference"]


def test_state_key_ignores_how_long_and_how_fast():
    cfg = {"model_name": "m", "data": {"adverse": {"conditions": [], "towns": 0}}, "arch": {"family": "fcos"},
           "augment": {}, "seed": 0, "renderer": {}, "region": {},
           "train": {"steps": 10, "threads": 2, "eval_every": 5, "checkpoint_every": 5, "lr": 1e-3,
                     "roi_batch_per_image": 128}}
    other = {**cfg, "train": {**cfg["train"], "steps": 20, "threads": 1, "roi_batch_per_image": 64}}
    assert tdd.state_key(cfg) == tdd.state_key(other)  # RoIs per image only matter to Faster R-CNN
    assert tdd.state_key(cfg) != tdd.state_key({**cfg, "train": {**cfg["train"], "lr": 2e-3}})
