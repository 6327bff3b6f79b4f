"""Train the shipped demo model: a compact SegFormer on the embedded renderer's daytime scenes.

    python experiments/train_demo_model.py [train.steps=1500 data.train_scenes=64 ...]

It renders Day-EXTRASUNNY scenes with exact labels through the generate stage (cached, seeds disjoint
from evaluation), trains with geometric augmentation only (so the evaluated photometric shifts stay
unseen), and writes safetensors weights, the config, a preprocessor config and a model card.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf

from pairedgta.cache import StageCache
from pairedgta.cityscapes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from pairedgta.conditions import build_condition_grid
from pairedgta.datasets import load_image, load_label, open_dataset
from pairedgta.metrics import ConfusionMatrix
from pairedgta.stages import generate
from pairedgta.stages.common import Context

log = logging.getLogger("train_demo")
ROOT = Path(__file__).resolve().parents[1]
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def render_split(cfg: dict, grid, num: int, seed: int):
    """Day-only scenes through the generate stage (cached like any other run)."""
    gcfg = json.loads(json.dumps(cfg))
    gcfg["generate"] = {
        "num_scenes": num, "seed": seed, "workers": 1, "endpoints": [], "drop_invalid": False,
        "validation": {"enabled": False}, "objects": cfg["data"]["objects"], "camera": cfg["data"]["camera"],
    }
    ctx = Context(cfg=gcfg, grid=grid, cache=StageCache(cfg["cache_dir"]), stages=["generate"], force=set())
    result = generate.run(ctx)
    ds = open_dataset({"kind": "generated", "name": "train_demo"}, grid, root=result.path)
    images = np.stack([load_image(g.images[grid.reference]) for g in ds.groups])
    labels = np.stack([load_label(g.labels[grid.reference]) for g in ds.groups])
    return images, labels


def batch(images, labels, rng, cfg):
    """Random scale + crop + horizontal flip: geometry only."""
    h, w = cfg["crop"]
    xs, ys = [], []
    for _ in range(cfg["batch_size"]):
        i = int(rng.integers(len(images)))
        img = torch.from_numpy(images[i]).permute(2, 0, 1).float().div(255)[None]
        lab = torch.from_numpy(labels[i].astype(np.int64))[None, None].float()
        s = float(rng.uniform(*cfg["scale_range"]))
        H, W = img.shape[-2:]
        nh, nw = max(h, round(H * s)), max(w, round(W * s))
        img = F.interpolate(img, size=(nh, nw), mode="bilinear", align_corners=False, antialias=True)
        lab = F.interpolate(lab, size=(nh, nw), mode="nearest")
        y0, x0 = int(rng.integers(nh - h + 1)), int(rng.integers(nw - w + 1))
        img, lab = img[..., y0 : y0 + h, x0 : x0 + w], lab[..., y0 : y0 + h, x0 : x0 + w]
        if rng.random() < 0.5:
            img, lab = img.flip(-1), lab.flip(-1)
        xs.append(img)
        ys.append(lab.long()[:, 0])
    return torch.cat(xs), torch.cat(ys)


@torch.inference_mode()
def evaluate(model, images, labels) -> ConfusionMatrix:
    model.eval()
    cm = ConfusionMatrix(NUM_CLASSES)
    for img, lab in zip(images, labels):
        x = torch.from_numpy(img).permute(2, 0, 1).float().div(255)[None]
        logits = model(pixel_values=(x - MEAN) / STD).logits
        logits = F.interpolate(logits, size=x.shape[-2:], mode="bilinear", align_corners=False)
        cm.update(lab, logits.argmax(1)[0].numpy())
    model.train()
    return cm


@hydra.main(version_base="1.3", config_path="../conf", config_name="train_demo")
def main(dcfg: DictConfig) -> None:
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    cfg = OmegaConf.to_container(dcfg, resolve=True)
    torch.set_num_threads(int(cfg["train"]["threads"]))
    grid = build_condition_grid({**cfg["conditions"], "only": [cfg["condition"]]})
    t0 = time.perf_counter()
    train_x, train_y = render_split(cfg, grid, cfg["data"]["train_scenes"], cfg["data"]["train_seed"])
    val_x, val_y = render_split(cfg, grid, cfg["data"]["val_scenes"], cfg["data"]["val_seed"])
    render_s = time.perf_counter() - t0
    log.info("data: %d train / %d val images (%.0f s)", len(train_x), len(val_x), render_s)

    torch.manual_seed(cfg["seed"])
    config = SegformerConfig(num_labels=NUM_CLASSES, id2label=dict(enumerate(CLASS_NAMES)),
                             label2id={n: i for i, n in enumerate(CLASS_NAMES)}, **cfg["arch"])
    model = SegformerForSemanticSegmentation(config)
    if tcfg_init := cfg["train"].get("init_from"):
        # continue from earlier weights (e.g. the shipped model) instead of a random init
        model = SegformerForSemanticSegmentation.from_pretrained(str(ROOT / tcfg_init))
    n_params = sum(p.numel() for p in model.parameters())
    if n_params > 4_000_000:
        raise SystemExit(f"arch has {n_params} parameters; the demo model must stay <= 4 M")
    tcfg = cfg["train"]
    opt = torch.optim.AdamW(model.parameters(), lr=tcfg["lr"], weight_decay=tcfg["weight_decay"])
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / tcfg["warmup"]) * 0.5 * (1 + math.cos(math.pi * min(s, tcfg["steps"]) / tcfg["steps"])))
    rng = np.random.default_rng(cfg["seed"])
    model.train()
    history = []
    t1 = time.perf_counter()
    for step in range(1, tcfg["steps"] + 1):
        x, y = batch(train_x, train_y, rng, tcfg)
        logits = model(pixel_values=(x - MEAN) / STD).logits
        logits = F.interpolate(logits, size=y.shape[-2:], mode="bilinear", align_corners=False)
        loss = F.cross_entropy(logits, y, ignore_index=IGNORE_INDEX)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if step % 50 == 0:
            log.info("step %d loss %.3f (%.2f s/step)", step, loss.item(), (time.perf_counter() - t1) / step)
        if step % tcfg["eval_every"] == 0 or step == tcfg["steps"]:
            cm = evaluate(model, val_x, val_y)
            history.append({"step": step, "loss": float(loss), "val_miou": cm.miou()})
            log.info("step %d val mIoU %.3f", step, cm.miou())
    train_s = time.perf_counter() - t1
    cm = evaluate(model, val_x, val_y)
    iou = cm.iou().numpy()
    present = cm.mat.sum(1).numpy() > 0
    out = ROOT / cfg["out_dir"]
    out.mkdir(parents=True, exist_ok=True)
    previous = None
    if cfg["train"].get("init_from") and (ROOT / cfg["train"]["init_from"] / "model_card.json").is_file():
        old = json.loads((ROOT / cfg["train"]["init_from"] / "model_card.json").read_text())
        previous = {k: old.get(k) for k in ("train", "val_miou", "train_seconds", "previous_card")}
    model.save_pretrained(out, safe_serialization=True)
    from transformers import SegformerImageProcessor

    SegformerImageProcessor(do_resize=False, image_mean=MEAN.flatten().tolist(), image_std=STD.flatten().tolist()).save_pretrained(out)
    floor = max(0.0, cm.miou() - cfg["miou_floor_margin"])
    card = {
        "model": "demo_segformer", "parameters": n_params, "arch": cfg["arch"],
        "data": {"renderer": cfg["renderer"]["backend"], "region": cfg["region"]["name"], "condition": cfg["condition"],
                 "resolution": [cfg["renderer"]["height"], cfg["renderer"]["width"]],
                 "train_scenes": cfg["data"]["train_scenes"], "train_seed": cfg["data"]["train_seed"],
                 "val_scenes": cfg["data"]["val_scenes"], "val_seed": cfg["data"]["val_seed"]},
        "train": tcfg, "seed": cfg["seed"], "previous_card": previous, "val_miou": cm.miou(), "val_pixel_accuracy": cm.accuracy(),
        "val_iou": {CLASS_NAMES[c]: float(iou[c]) for c in range(NUM_CLASSES) if present[c]},
        "test_floor_miou": floor, "history": history, "render_seconds": render_s, "train_seconds": train_s,
    }
    from pairedgta.jsonio import write_json

    write_json(out / "model_card.json", card)
    lines = [
        "# demo_segformer", "",
        "A compact SegFormer (%.2f M parameters) trained by `experiments/train_demo_model.py` only on synthetic"
        % (n_params / 1e6),
        "daytime (Day-EXTRASUNNY) scenes of the embedded Blender renderer, with exact labels and geometric",
        "augmentation only. It exists to demonstrate the method offline; it is not a Cityscapes model.", "",
        f"- data: {cfg['data']['train_scenes']} train scenes (seed {cfg['data']['train_seed']}+), "
        f"{cfg['data']['val_scenes']} validation scenes (seed {cfg['data']['val_seed']}+), "
        f"{cfg['renderer']['width']}x{cfg['renderer']['height']}",
        f"- training: {tcfg['steps']} steps, batch {tcfg['batch_size']}, crops {tcfg['crop']}, AdamW lr {tcfg['lr']}",
        f"- validation mIoU (held-out Day-EXTRASUNNY scenes): {cm.miou():.3f}; test floor {floor:.3f}",
        f"- time: {render_s:.0f} s rendering, {train_s:.0f} s training on {tcfg['threads']} CPU threads", "",
        "| class | IoU |", "|---|---|",
        *[f"| {CLASS_NAMES[c]} | {iou[c]:.3f} |" for c in range(NUM_CLASSES) if present[c]],
    ]
    (out / "README.md").write_text("\n".join(lines) + "\n")
    print(f"demo model: val mIoU {cm.miou():.3f}, {n_params} parameters -> {out}")


if __name__ == "__main__":
    main()
