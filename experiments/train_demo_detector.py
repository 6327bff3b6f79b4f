"""Train the shipped demo detectors (the detection zoo) on the embedded renderer's daytime scenes.

    python experiments/train_demo_detector.py                              # demo_det_reference: render (cached), train
    python experiments/train_demo_detector.py detector_zoo=demo_fcos_noaug  # another member (conf/detector_zoo/)
    python experiments/train_demo_detector.py train.steps=50 data.train_towns=2    # a quick try

`detector_zoo=<name>` picks the member: its family (`arch.family`: fcos, retinanet or fasterrcnn, the heads of
pairedgta/models/detectors.py on a MobileNetV3-Large trunk + FPN), its widths, training scale (`arch.min_size`) and
any recipe change (photometric distortion off, adverse-condition training towns).

Data: Day-EXTRASUNNY scenes of many towns (one `town_seed` per group of scenes), rendered once through the cached
generate stage exactly as experiments/train_demo_model.py renders them (the same cache entries), and their ground
truth boxes from the renderer's instance masks (pairedgta/detection/boxes.py). Validation: held-out town seeds.
Objects with fewer than `data.min_area` (100) visible pixels are ignore regions at evaluation; in training their
pixels are painted the ImageNet mean colour (`augment.mask_small`), so the network is taught neither to find them
nor to call them background.
Recipe: the render is scaled to the network's scale (`arch.min_size` / 256) times a random factor
(`augment.scale_range`), a random crop (`augment.crop`, half of them around a random object), horizontal flip,
photometric distortion (MMSegmentation's PhotoMetricDistortion, as the segmentation zoo); AdamW or SGD with linear
warm-up and cosine decay, gradient clipping. Every `checkpoint_every` steps the training state goes to
<work_dir>/<hash>/checkpoint.pt and a rerun with the same recipe continues from it. At the end: float16 safetensors
weights, a model card (README.md, model_card.json) in zoo/detection/pairedgta_detection_zoo/<name>/ (the detection
zoo's distribution, pairedgta-detection-zoo) and the model config
pairedgta/conf/model/<name>.yaml; held-out AP by pycocotools (ignore regions as iscrowd).
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from pairedgta.cache import StageCache, canonical_json
from pairedgta.conditions import build_condition_grid
from pairedgta.detection.boxes import INSTANCE_CLASSES, Box, coco_ground_truth
from pairedgta.detection.ground_truth import read_ground_truth
from pairedgta.models.detectors import build_network

log = logging.getLogger("train_demo_detector")
ROOT = Path(__file__).resolve().parents[1]
# the detection zoo's weights: a distribution of their own (zoo/detection/pyproject.toml), so that neither wheel passes
# a package index's 100 MB; the model configs keep `pkg://models/weights/<name>/...` (pairedgta/models/hf_common.py)
ZOO_DIR = "zoo/detection/pairedgta_detection_zoo"
RENDER_HEIGHT = 256  # the renders' short side: arch.min_size / this is the network's scale


def _segmentation_trainer():
    """experiments/train_demo_model.py as a module (its photometric distortion, float16 writer, checks)."""
    name = "train_demo_model"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name("train_demo_model.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


seg = _segmentation_trainer()


# -- data ---------------------------------------------------------------------------------------------
class Sample:
    """One training or validation image: uint8 H x W x 3, its scored boxes (xyxy pixels, labels 0..7 of
    INSTANCE_CLASSES) and all its ground truth (ignore regions included, for COCO)."""

    def __init__(self, image: np.ndarray, boxes: list[Box], small_mask: np.ndarray | None = None):
        self.image = image
        self.gt = boxes
        scored = [b for b in boxes if not b.ignore]
        self.xyxy = np.array([b.xyxy for b in scored], np.float32).reshape(-1, 4)
        self.labels = np.array([b.label for b in scored], np.int64)
        self.small_mask = small_mask


def load_samples(groups, condition: str, min_area: int) -> list[Sample]:
    from PIL import Image

    from pairedgta.datasets import load_image

    out = []
    for g in groups:
        boxes = read_ground_truth(g.instances[condition], g.labels[condition], min_area=min_area)
        small = [b.instance for b in boxes if b.ignore]
        mask = None
        if small:
            with Image.open(g.instances[condition]) as im:
                mask = np.isin(np.array(im), small)
        out.append(Sample(load_image(g.images[condition]), boxes, mask))
    return out


def render_towns(cfg: dict, grid, towns: range, scenes_per_town: int, scene_seed: int) -> tuple[list[Sample], float]:
    """Scenes of each town under the grid's one condition through the generate stage (the config
    experiments/train_demo_model.py builds, so the cache entries are shared), with their boxes."""
    import pandas as pd

    from pairedgta.datasets import open_dataset
    from pairedgta.stages import generate
    from pairedgta.stages.common import Context

    samples, seconds = [], 0.0
    for town in tqdm(towns, desc="render towns", unit="town"):
        gcfg = json.loads(json.dumps(cfg))
        gcfg["region"] = {**cfg["region"], "town_seed": int(town)}
        gcfg["renderer"] = {**cfg["renderer"], "town": gcfg["region"]}
        gcfg["generate"] = {
            "num_scenes": scenes_per_town, "seed": scene_seed + int(town), "workers": cfg["data"]["workers"],
            "endpoints": [], "drop_invalid": False, "validation": {"enabled": False},
            "objects": cfg["data"]["objects"], "camera": cfg["data"]["camera"],
        }
        run_cfg = {k: gcfg[k] for k in ("region", "renderer", "generate", "conditions") if k in gcfg}
        ctx = Context(cfg=run_cfg, grid=grid, cache=StageCache(cfg["cache_dir"]), stages=["generate"], force=set())
        result = generate.run(ctx)
        seconds += float(pd.read_csv(result.timings_csv)["total_time"].sum())
        ds = open_dataset({"kind": "generated", "name": "train_demo_detector"}, grid, root=result.path)
        samples += load_samples(ds.groups, grid.reference, cfg["data"]["min_area"])
    return samples, seconds


def render_adverse(cfg: dict) -> tuple[list[Sample], float]:
    """`data.adverse`: extra training towns, each rendered in one non-Day condition (seg.adverse_towns)."""
    ad = cfg["data"].get("adverse") or {}
    samples, seconds = [], 0.0
    for town, condition in seg.adverse_towns(cfg):
        grid = build_condition_grid({**cfg["conditions"], "reference": condition, "only": [condition]})
        s, t = render_towns(cfg, grid, range(town, town + 1), ad["scenes_per_town"], cfg["data"]["scene_seed"])
        samples += s
        seconds += t
    return samples, seconds


def mask_small(sample: Sample) -> np.ndarray:
    """The image with the pixels of objects below min_area painted the ImageNet mean colour."""
    if sample.small_mask is None:
        return sample.image
    img = sample.image.copy()
    img[sample.small_mask] = np.array([124, 116, 104], np.uint8)
    return img


def augment_sample(sample: Sample, rng: np.random.Generator, a: dict, scale: float) -> tuple[torch.Tensor, dict]:
    """Resize by scale x U(scale_range), crop (around a random object half of the time), flip, photometric
    distortion; boxes scaled, clipped to the crop and kept where >= `a.min_visible` of their area stays in it."""
    h, w = a["crop"]
    image = mask_small(sample) if a.get("mask_small", True) else sample.image
    img = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float().div(255)[None]
    s = scale * float(rng.uniform(*a["scale_range"]))
    H, W = img.shape[-2:]
    nh, nw = max(1, round(H * s)), max(1, round(W * s))
    img = F.interpolate(img, size=(nh, nw), mode="bilinear", align_corners=False, antialias=s < 1)[0]
    boxes = sample.xyxy * np.array([nw / W, nh / H, nw / W, nh / H], np.float32)
    if nh < h or nw < w:
        img = F.pad(img, (0, max(0, w - nw), 0, max(0, h - nh)), value=0.0)
        nh, nw = img.shape[-2:]
    if len(boxes) and rng.random() < a.get("object_crop_p", 0.5):
        x0b, y0b, x1b, y1b = boxes[int(rng.integers(len(boxes)))]
        cx, cy = (x0b + x1b) / 2, (y0b + y1b) / 2
        x0 = int(np.clip(cx - rng.uniform(0.1, 0.9) * w, 0, nw - w))
        y0 = int(np.clip(cy - rng.uniform(0.1, 0.9) * h, 0, nh - h))
    else:
        y0, x0 = int(rng.integers(nh - h + 1)), int(rng.integers(nw - w + 1))
    img = img[:, y0:y0 + h, x0:x0 + w]
    labels = sample.labels
    if len(boxes):
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        c = boxes - np.array([x0, y0, x0, y0], np.float32)
        c[:, [0, 2]] = c[:, [0, 2]].clip(0, w)
        c[:, [1, 3]] = c[:, [1, 3]].clip(0, h)
        cw, ch = c[:, 2] - c[:, 0], c[:, 3] - c[:, 1]
        keep = (cw >= 2) & (ch >= 2) & (cw * ch >= a.get("min_visible", 0.3) * area)
        boxes, labels = c[keep], labels[keep]
    if rng.random() < a["flip"]:
        img = img.flip(-1)
        boxes = boxes.copy()
        boxes[:, [0, 2]] = w - boxes[:, [2, 0]]
    if a.get("photometric"):
        img = seg.photometric(img, rng, a["photometric"])
    target = {"boxes": torch.from_numpy(np.ascontiguousarray(boxes, np.float32)).reshape(-1, 4),
              "labels": torch.from_numpy(np.asarray(labels, np.int64) + 1)}
    return img.contiguous(), target


def draw_batch(samples: list[Sample], rng: np.random.Generator, a: dict, size: int, scale: float):
    pairs = [augment_sample(samples[i], rng, a, scale) for i in rng.integers(len(samples), size=size)]
    return [x for x, _ in pairs], [t for _, t in pairs]


# -- model --------------------------------------------------------------------------------------------
def network_config(cfg: dict) -> dict:
    """The keys build_network / build_detector read: name and the architecture (family excluded)."""
    return {"name": cfg["model_name"], **{k: v for k, v in cfg["arch"].items() if k != "family"}}


@contextlib.contextmanager
def input_size(module, min_size: int, max_size: int):
    """The module's own resize set to (min_size, max_size) for a while (training crops at scale 1)."""
    t = module.transform
    old = (t.min_size, t.max_size)
    t.min_size, t.max_size = (int(min_size),), int(max_size)
    try:
        yield
    finally:
        t.min_size, t.max_size = old


def train_step(module, opt, sched, images: list[torch.Tensor], targets: list[dict], crop: list[int],
               grad_clip: float | None) -> dict[str, float]:
    """One optimisation step on a batch of crops (the network sees them at scale 1): the loss dict's values."""
    module.train()
    with input_size(module, min(crop), max(crop)):
        losses = module(images, targets)
    loss = sum(losses.values())
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip:
        torch.nn.utils.clip_grad_norm_(module.parameters(), grad_clip)
    opt.step()
    sched.step()
    return {"loss": float(loss.detach()), **{k: float(v.detach()) for k, v in losses.items()}}


def make_optimizer(module, t: dict):
    decay, no_decay = [], []
    for n, p in module.named_parameters():
        (no_decay if p.ndim <= 1 else decay).append(p)
    groups = [{"params": decay, "weight_decay": t["weight_decay"]}, {"params": no_decay, "weight_decay": 0.0}]
    if t.get("optimizer", "adamw") == "sgd":
        opt = torch.optim.SGD(groups, lr=t["lr"], momentum=0.9, nesterov=True)
    else:
        opt = torch.optim.AdamW(groups, lr=t["lr"])
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, t))


def lr_factor(step: int, t: dict) -> float:
    """Linear warm-up from 0.1, then cosine decay to `min_lr_ratio` at `steps`."""
    if step < t["warmup"]:
        return 0.1 + 0.9 * step / max(1, t["warmup"])
    p = min(1.0, (step - t["warmup"]) / max(1, t["steps"] - t["warmup"]))
    lo = t.get("min_lr_ratio", 0.01)
    return lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * p))


def init_weights(module, folder: Path) -> None:
    """`train.init_from`: start from a member's float16 weights (the same architecture, loaded strictly)."""
    from safetensors.torch import load_file

    state = load_file(str(folder / "model.safetensors"))
    own = module.state_dict()
    module.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=True)


def save_checkpoint(path: Path, module, opt, sched, step: int, rng: np.random.Generator, history: list,
                    elapsed: float) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": module.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(), "step": step,
                "rng": json.dumps(rng.bit_generator.state), "torch_rng": torch.get_rng_state(),
                "history": json.dumps(history), "elapsed": elapsed}, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path, module, opt, sched, rng: np.random.Generator) -> tuple[int, list, float]:
    state = torch.load(path, map_location="cpu", weights_only=True)
    module.load_state_dict(state["model"])
    opt.load_state_dict(state["opt"])
    sched.load_state_dict(state["sched"])
    rng.bit_generator.state = json.loads(state["rng"])
    torch.set_rng_state(state["torch_rng"])
    return int(state["step"]), json.loads(state["history"]), float(state["elapsed"])


# -- evaluation ---------------------------------------------------------------------------------------
@torch.inference_mode()
def detect(module, samples: list[Sample], batch_size: int = 4) -> list[dict[str, np.ndarray]]:
    module.eval()
    out = []
    for i in range(0, len(samples), batch_size):
        x = [torch.from_numpy(s.image).permute(2, 0, 1).float().div(255) for s in samples[i:i + batch_size]]
        for d in module(x):
            out.append({k: d[k].float().numpy() if k != "labels" else d[k].numpy()
                        for k in ("boxes", "scores", "labels")})
    return out


def coco_eval(samples: list[Sample], dets: list[dict[str, np.ndarray]]) -> dict[str, Any]:
    """Held-out AP by pycocotools: AP (0.5:0.95) and AP50 over all classes with ground truth, AP50 per class."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images = [(i + 1, f"{i:05d}", s.image.shape[1], s.image.shape[0]) for i, s in enumerate(samples)]
    gt = coco_ground_truth(images, [s.gt for s in samples])
    results = [{"image_id": i + 1, "category_id": int(lab), "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]),
                                                                     float(b[3] - b[1])], "score": float(sc)}
               for i, d in enumerate(dets) for b, sc, lab in zip(d["boxes"], d["scores"], d["labels"])]
    # torchvision label k (1..8) is INSTANCE_CLASSES[k - 1], whose COCO category id is k as well
    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO()
        coco.dataset = gt
        coco.createIndex()
        if not results:
            return {"ap": 0.0, "ap50": 0.0, "ap50_per_class": {}, "gt_per_class": {}}
        ev = COCOeval(coco, coco.loadRes(results), "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    precision = ev.eval["precision"]  # T x R x K x A x M
    per_class, counts = {}, {}
    for k, cat in enumerate(ev.params.catIds):
        n = sum(1 for a in gt["annotations"] if a["category_id"] == cat and not a["iscrowd"])
        if n == 0:
            continue
        p = precision[0, :, k, 0, -1]
        per_class[INSTANCE_CLASSES[cat - 1]] = float(p[p > -1].mean()) if (p > -1).any() else 0.0
        counts[INSTANCE_CLASSES[cat - 1]] = n
    return {"ap": float(max(ev.stats[0], 0.0)), "ap50": float(max(ev.stats[1], 0.0)), "ap50_per_class": per_class,
            "gt_per_class": counts}


def best_threshold(samples: list[Sample], dets: list[dict[str, np.ndarray]], iou: float = 0.5) -> tuple[float, float]:
    """The score threshold with the best F1 (IoU >= 0.5, same class; detections on ignore regions not counted)
    over the held-out images: the member's operating point."""
    from torchvision.ops import box_iou

    thresholds = np.round(np.arange(0.05, 0.951, 0.05), 2)
    tp, fp = np.zeros(len(thresholds)), np.zeros(len(thresholds))
    n_gt = sum(len(s.xyxy) for s in samples)
    for s, d in zip(samples, dets):
        order = np.argsort(-d["scores"])
        boxes, scores, labels = d["boxes"][order], d["scores"][order], d["labels"][order] - 1
        ign = np.array([b.xyxy for b in s.gt if b.ignore], np.float32).reshape(-1, 4)
        for ti, th in enumerate(thresholds):
            used = np.zeros(len(s.xyxy), bool)
            for b, sc, lab in zip(boxes, scores, labels):
                if sc < th:
                    break
                ious = (box_iou(torch.from_numpy(b[None]), torch.from_numpy(s.xyxy)).numpy()[0] if len(s.xyxy)
                        else np.zeros(0))
                ious = np.where((s.labels == lab) & ~used, ious, 0.0)
                if len(ious) and ious.max() >= iou:
                    used[int(ious.argmax())] = True
                    tp[ti] += 1
                    continue
                if len(ign):  # on an ignore region (>= half of the detection inside it): not counted
                    ix0, iy0 = np.maximum(ign[:, 0], b[0]), np.maximum(ign[:, 1], b[1])
                    ix1, iy1 = np.minimum(ign[:, 2], b[2]), np.minimum(ign[:, 3], b[3])
                    inter = (ix1 - ix0).clip(0) * (iy1 - iy0).clip(0)
                    if (inter >= 0.5 * max(1e-6, (b[2] - b[0]) * (b[3] - b[1]))).any():
                        continue
                fp[ti] += 1
    f1 = 2 * tp / np.maximum(1e-9, 2 * tp + fp + (n_gt - tp))
    i = int(np.argmax(f1))
    return float(thresholds[i]), float(f1[i])


def evaluate(module, samples: list[Sample]) -> dict[str, Any]:
    dets = detect(module, samples)
    result = coco_eval(samples, dets)
    result["score_threshold"], result["f1"] = best_threshold(samples, dets)
    return result


# -- outputs ------------------------------------------------------------------------------------------
FAMILY_TEXT = {"fcos": "FCOS", "retinanet": "RetinaNet", "fasterrcnn": "Faster R-CNN"}


def arch_keys(arch: dict) -> dict:
    """The architecture keys the family's builder takes (pairedgta/models/detectors.py), and min/max size."""
    import inspect

    from pairedgta.models import detectors as models

    taken = [p.name for p in inspect.signature(getattr(models, arch["family"])).parameters.values()
             if p.kind is p.KEYWORD_ONLY] + ["min_size", "max_size"]
    common = inspect.signature(models.build_detector).parameters  # min/max size only where not the default
    return {k: v for k, v in arch.items() if k in taken and v is not None
            and not (k in ("min_size", "max_size") and v == common[k].default)}


def model_yaml(cfg: dict, score_threshold: float) -> str:
    name, arch = cfg["model_name"], cfg["arch"]
    lines = [f"# A detection zoo member shipped with the package: {FAMILY_TEXT[arch['family']]} on a MobileNetV3-Large",
             "# trunk + FPN (pairedgta/models/detectors.py), trained by experiments/train_demo_detector.py",
             f"# detector_zoo={name}",
             f"# on the embedded renderer's scenes (model card: {ZOO_DIR}/{name}/README.md).",
             f"name: {name}", f"family: {arch['family']}",
             f"checkpoint_path: pkg://models/weights/{name}/model.safetensors",
             f"# architecture: must match pairedgta/conf/detector_zoo/{name}.yaml (loaded strictly)"]
    lines += [f"{k}: {json.dumps(v)}" for k, v in arch_keys(arch).items()]
    from pairedgta.models.contract import DEFAULT_SCORE_THRESHOLD

    if score_threshold != DEFAULT_SCORE_THRESHOLD:  # the default is not repeated (tests/test_models_runtime.py)
        lines += [f"score_threshold: {score_threshold}   # the best-F1 threshold on the held-out towns"]
    else:
        lines += [f"# score_threshold: the default {DEFAULT_SCORE_THRESHOLD} is the best-F1 threshold on the held-out "
                  "towns"]
    return "\n".join(lines) + "\n"


def recipe_text(cfg: dict) -> str:
    a, t, arch = cfg["augment"], cfg["train"], cfg["arch"]
    opt = "SGD (momentum 0.9)" if t.get("optimizer", "adamw") == "sgd" else "AdamW"
    parts = [f"{t['steps']} steps, batch {t['batch_size']}, crops {a['crop']} of the render scaled "
             f"{arch['min_size'] / RENDER_HEIGHT:g}x (min_size {arch['min_size']}) x {a['scale_range']}",
             f"{opt} lr {t['lr']}, weight decay {t['weight_decay']}, {t['warmup']} warm-up steps, cosine decay",
             "horizontal flip"]
    parts.append("photometric distortion" if a.get("photometric") else "no photometric distortion")
    text = ", ".join(parts)
    return text + (f"; started from the weights in `{t['init_from']}`" if t.get("init_from")
                   else "; random initialisation")  # cfg or a model card: the keys read here are in both


def chain_seconds(card: dict) -> list[tuple[str, float]]:
    """(member, training seconds) from random initialisation to this member: the card's own training after the
    cards of the members it started from (`train.init_from`), so a fine-tune's card states its whole cost."""
    chain, seen = [(card["model"], float(card["train_seconds"]))], {card["model"]}
    parent = card["train"].get("init_from")
    while parent and (ROOT / parent / "model_card.json").is_file():
        up = json.loads((ROOT / parent / "model_card.json").read_text())
        if up["model"] in seen:
            break
        seen.add(up["model"])
        chain.insert(0, (up["model"], float(up["train_seconds"])))
        parent = up["train"].get("init_from")
    return chain


def card_readme(card: dict) -> str:
    """The model card's README, from model_card.json alone (experiments/detection_zoo_table.py reads the same card);
    a card's `note` (written by hand: how a run went that the recipe does not say) follows the recipe."""
    name, family, d, arch, t = card["model"], card["family"], card["data"], card["arch"], card["train"]
    result, ap50 = card["val"], card["val"]["ap50_per_class"]
    ad = d.get("adverse") or {}
    towns = seg.adverse_towns({"data": d})
    height, width = d["resolution"]
    if not towns:
        seen = "daytime (Day-EXTRASUNNY) scenes only; it never saw rain, fog, sunset or night"
        extra = ""
    elif list(ad["conditions"]) == [d["condition"]]:
        seen = (f"daytime ({d['condition']}) scenes only, of {d['train_towns'] + len(towns)} towns; it never saw "
                "rain, fog, sunset or night")
        extra = f" and {len(towns)} more daytime towns"
    else:
        seen = (f"daytime (Day-EXTRASUNNY) scenes and {len(towns) * ad['scenes_per_town']} scenes of {len(towns)} "
                f"other towns under {', '.join(ad['conditions'])} (each town in one condition)")
        extra = f" and {len(towns)} adverse-condition towns"
    start = (f"started from `{Path(t['init_from']).name}`'s weights" if t.get("init_from")
             else "random initialisation")
    chain = chain_seconds(card)
    threads = t["threads"]
    lines = [
        f"# {name}", "",
        f"A compact {FAMILY_TEXT[family]} detector (torchvision head on a MobileNetV3-Large trunk at width "
        f"{arch['width']}, FPN {arch['fpn_channels']} channels; {card['parameters'] / 1e6:.2f} M parameters, "
        f"{start}) trained by `experiments/train_demo_detector.py` on synthetic scenes of the embedded "
        f"Blender renderer with exact boxes from its instance masks: {seen}.",
        "It demonstrates detection evaluation offline; it is not a Cityscapes or COCO model.", "",
        f"- command: `{card.get('command') or 'python experiments/train_demo_detector.py'}`",
        f"- data: {d['train_images']} training images ({d['train_boxes']} boxes of >= {d['min_area']} visible "
        f"pixels) from {d['train_towns']} towns{extra}, {d['val_images']} validation images from {d['val_towns']} "
        f"held-out towns, {width}x{height}; objects below {d['min_area']} px painted out in training (ignore "
        "regions at evaluation)",
        f"- training: {recipe_text(card)}" + (f" ({card['note']})" if card.get("note") else ""),
        f"- held-out AP50 car {ap50.get('car', float('nan')):.3f}, person {ap50.get('person', float('nan')):.3f}; "
        f"AP50 over all classes {result['ap50']:.3f}, AP (0.5:0.95) {result['ap']:.3f} (pycocotools, ignore regions "
        "as iscrowd)",
        f"- score_threshold {result['score_threshold']} (best F1 {result['f1']:.3f} on the held-out towns)",
        "- weights: float16 (model.safetensors; loaded as float32)",
        f"- wall time: {card['render_seconds'] / 60:.0f} min rendering, {card['train_seconds'] / 60:.1f} min "
        f"training (resumed runs summed) on a 2-core CPU shared with other jobs, {threads} "
        f"thread{'s' if threads != 1 else ''} (the last run)",
    ]
    if len(chain) > 1:
        lines.append(f"- training from random initialisation: {sum(s for _, s in chain) / 60:.1f} min over "
                     + " -> ".join(f"`{m}` {s / 60:.1f} min" for m, s in chain))
    lines += ["", "| class | held-out ground-truth boxes | AP50 |", "|---|---|---|",
              *[f"| {c} | {result['gt_per_class'][c]} | {v:.3f} |" for c, v in ap50.items()]]
    return "\n".join(lines) + "\n"


def write_outputs(cfg: dict, module, n_params: int, result: dict, history: list, render_s: float, train_s: float,
                  n_train: int, n_val: int, n_boxes: int) -> None:
    from pairedgta.jsonio import write_json

    name, family, d = cfg["model_name"], cfg["arch"]["family"], cfg["data"]
    out = ROOT / cfg["out_dir"]
    out.mkdir(parents=True, exist_ok=True)
    seg.save_half(module.state_dict(), out / "model.safetensors", {"family": family, "model": name})
    ap50 = result["ap50_per_class"]
    card = {"model": name, "family": family, "parameters": n_params, "arch": cfg["arch"], "weights_dtype": "float16",
            "data": {"renderer": cfg["renderer"]["backend"], "region": cfg["region"]["name"],
                     "condition": cfg["condition"], "resolution": [cfg["renderer"]["height"], cfg["renderer"]["width"]],
                     "train_images": n_train, "train_boxes": n_boxes, "val_images": n_val,
                     **{k: v for k, v in d.items() if k not in ("objects", "camera", "workers")}},
            "augment": cfg["augment"], "train": cfg["train"], "seed": cfg["seed"], "command": cfg.get("command"),
            "val": result, "history": history, "render_seconds": render_s, "train_seconds": train_s}
    write_json(out / "model_card.json", card)
    (out / "README.md").write_text(card_readme(card))
    for f in out.iterdir():
        f.chmod(0o644)
    # a member shipped in the detection zoo gets its model config (`model=<name>`); a try elsewhere gets it beside its
    # weights
    shipped = Path(cfg["out_dir"]).parent == Path(ZOO_DIR)
    model_conf = ROOT / "pairedgta" / "conf" / "model" / f"{name}.yaml" if shipped else out / "model.yaml"
    model_conf.write_text(model_yaml(cfg, result["score_threshold"]))
    print(f"{name}: held-out AP50 car {ap50.get('car', float('nan')):.3f} "
          f"person {ap50.get('person', float('nan')):.3f} "
          f"AP {result['ap']:.3f}, {n_params} parameters, {train_s / 60:.1f} min -> {out}")


# -- main ---------------------------------------------------------------------------------------------
def state_key(cfg: dict) -> str:
    """Checkpoints belong to one recipe: everything but how long and how fast it runs."""
    keep = {k: cfg[k] for k in ("model_name", "data", "arch", "augment", "seed", "renderer", "region")}
    keep["data"] = {k: v for k, v in cfg["data"].items() if not (k == "adverse" and not seg.adverse_towns(cfg))}
    keep["train"] = {k: v for k, v in cfg["train"].items()
                     if k not in ("steps", "threads", "eval_every", "checkpoint_every")
                     and not (k == "roi_batch_per_image" and cfg["arch"]["family"] != "fasterrcnn")}
    return hashlib.sha256(canonical_json(keep).encode()).hexdigest()[:12]


def check_config(cfg: dict) -> None:
    arch, t, a = cfg.get("arch") or {}, cfg["train"], cfg["augment"]
    checks = [
        ("arch.family", arch.get("family"), arch.get("family") in FAMILY_TEXT, "fcos, retinanet or fasterrcnn"),
        ("train.steps", t.get("steps"), seg._number(t.get("steps"), 1, math.inf, True), "an integer >= 1"),
        ("train.batch_size", t.get("batch_size"), seg._number(t.get("batch_size"), 1, math.inf, True),
         "an integer >= 1"),
        ("train.lr", t.get("lr"), seg._number(t.get("lr"), 1e-12, 10.0), "a learning rate > 0"),
        ("train.optimizer", t.get("optimizer"), t.get("optimizer") in ("adamw", "sgd"), "adamw or sgd"),
        ("train.checkpoint_every", t.get("checkpoint_every"), seg._number(t.get("checkpoint_every"), 1, math.inf, True),
         "an integer >= 1"),
        ("augment.crop", a.get("crop"), isinstance(a.get("crop"), list) and len(a["crop"]) == 2
         and all(seg._number(v, 32, 4096, True) and v % 32 == 0 for v in a["crop"]),
         "[height, width], multiples of 32"),
        ("model_name", cfg.get("model_name"), isinstance(cfg.get("model_name"), str)
         and cfg["model_name"].replace("_", "").isalnum(), "a name of letters, digits and _"),
    ]
    for key, value, ok, want in checks:
        if not ok:
            raise SystemExit(f"train_detector config: {key}={value!r} is invalid; set it to {want}")


def load_data(cfg: dict) -> tuple[list[Sample], list[Sample], float]:
    d = cfg["data"]
    grid = build_condition_grid({**cfg["conditions"], "only": [cfg["condition"]]})
    train, tr_s = render_towns(cfg, grid, range(d["train_town_seed"], d["train_town_seed"] + d["train_towns"]),
                               d["train_scenes_per_town"], d["scene_seed"])
    val, va_s = render_towns(cfg, grid, range(d["val_town_seed"], d["val_town_seed"] + d["val_towns"]),
                             d["val_scenes_per_town"], d["scene_seed"] + 100_000)
    extra, ex_s = render_adverse(cfg)
    return train + extra, val, tr_s + va_s + ex_s


@hydra.main(version_base="1.3", config_path="pkg://pairedgta.conf", config_name="train_detector")
def main(dcfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    cfg = OmegaConf.to_container(dcfg, resolve=True)
    assert isinstance(cfg, dict)
    check_config(cfg)
    cfg["command"] = " ".join(["python experiments/train_demo_detector.py", *HydraConfig.get().overrides.task])
    t, a = cfg["train"], cfg["augment"]
    torch.set_num_threads(int(t["threads"]))
    train, val, render_s = load_data(cfg)
    if cfg["data"].get("render_only"):
        print(f"rendered {len(train)} training and {len(val)} validation images ({render_s:.0f} s)")
        return
    n_boxes = int(sum(len(s.xyxy) for s in train))
    log.info("data: %d train images (%d boxes) / %d held-out-town val images (%.0f s of rendering)",
             len(train), n_boxes, len(val), render_s)
    torch.manual_seed(cfg["seed"])
    module = build_network(cfg["arch"]["family"], network_config(cfg))
    if t.get("init_from"):
        init_weights(module, ROOT / t["init_from"])
    if cfg["arch"]["family"] == "fasterrcnn" and t.get("roi_batch_per_image"):  # sampled RoIs per image (training only)
        module.roi_heads.fg_bg_sampler.batch_size_per_image = int(t["roi_batch_per_image"])
    n_params = sum(p.numel() for p in module.parameters())
    opt, sched = make_optimizer(module, t)
    rng = np.random.default_rng(cfg["seed"])
    work = ROOT / cfg["work_dir"] / state_key(cfg)
    work.mkdir(parents=True, exist_ok=True)
    ckpt = work / "checkpoint.pt"
    start, history, elapsed = 0, [], 0.0
    if ckpt.is_file():
        start, history, elapsed = load_checkpoint(ckpt, module, opt, sched, rng)
        log.info("resuming from %s at step %d", ckpt, start)
    scale = cfg["arch"]["min_size"] / RENDER_HEIGHT
    t1 = time.perf_counter() - elapsed
    bar = tqdm(range(start + 1, t["steps"] + 1), initial=start, total=t["steps"], desc="train", unit="step",
               mininterval=10.0)
    running = None
    for step in bar:
        images, targets = draw_batch(train, rng, a, t["batch_size"], scale)
        losses = train_step(module, opt, sched, images, targets, a["crop"], t.get("grad_clip"))
        if not math.isfinite(losses["loss"]):
            raise SystemExit(f"step {step}: loss is {losses['loss']}; lower train.lr")
        running = losses["loss"] if running is None else 0.95 * running + 0.05 * losses["loss"]
        bar.set_postfix(loss=f"{running:.3f}", lr=f"{sched.get_last_lr()[0]:.1e}", refresh=False)
        if step % t["eval_every"] == 0 and step != t["steps"]:
            r = evaluate(module, val)
            history.append({"step": step, "loss": running, "ap50": r["ap50"],
                            "ap50_car": r["ap50_per_class"].get("car"),
                            "seconds": time.perf_counter() - t1})
            log.info("step %d loss %.3f held-out AP50 %.3f car %.3f (%.2f s/step)", step, running, r["ap50"],
                     r["ap50_per_class"].get("car", math.nan), (time.perf_counter() - t1) / step)
        if step % t["checkpoint_every"] == 0 or step == t["steps"]:
            save_checkpoint(ckpt, module, opt, sched, step, rng, history, time.perf_counter() - t1)
    train_s = time.perf_counter() - t1
    result = evaluate(module, val)
    history.append({"step": t["steps"], "loss": running, "ap50": result["ap50"],
                    "ap50_car": result["ap50_per_class"].get("car"), "seconds": train_s})
    write_outputs(cfg, module, n_params, result, history, render_s, train_s, len(train), len(val), n_boxes)


if __name__ == "__main__":
    main()
