"""Train the shipped demo models (the offline zoo) the way real Cityscapes models are trained, on daytime scenes only.

    python experiments/train_demo_model.py                      # demo_segformer: render (cached) + train, resumable
    python experiments/train_demo_model.py zoo=demo_ddrnet      # another zoo member (pairedgta/conf/zoo/)
    python experiments/train_demo_model.py train.steps=500 data.train_towns=4   # a quick try

`zoo=<name>` picks the model: its family (`arch.family`: segformer from transformers, or the
project's own ddrnet / pidnet / deeplabv3plus), its widths and any recipe change (the brittle control
`demo_segformer_noaug` drops the photometric distortion).

Data: Day-EXTRASUNNY scenes of the embedded renderer over many towns (one `town_seed` per group of
scenes), rendered once through the cached generate stage; validation on held-out town seeds. The
model never sees rain, fog, sunset or night. Recipe: random resize 0.5-2.0, random crop (with the
category-ratio re-draw), horizontal flip, photometric distortion as MMSegmentation's
PhotoMetricDistortion (brightness, contrast, saturation, hue), OHEM cross-entropy, AdamW with warm-up
and poly decay.
Every `checkpoint_every` steps the full training state goes to <work_dir>/<hash>/checkpoint.pt,
and a rerun with the same settings continues from it. Progress is a tqdm bar; MLflow records params,
loss, learning rate and validation IoU. The result: safetensors weights, config, preprocessor config,
model card (per-class IoU, wall times) and README in pairedgta/models/weights/<model_name>.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from pathlib import Path

import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from pairedgta.cache import StageCache, canonical_json
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


# -- data ---------------------------------------------------------------------------------------------
def render_towns(cfg: dict, grid, towns: range, scenes_per_town: int, scene_seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Day-only scenes of each town through the generate stage (one cached entry per town), and the
    seconds their generation took (from the entries' timings.csv, so a cached rerun still reports it)."""
    import pandas as pd

    images, labels, seconds = [], [], 0.0
    for town in tqdm(towns, desc="render towns", unit="town"):
        gcfg = json.loads(json.dumps(cfg))
        gcfg["region"] = {**cfg["region"], "town_seed": int(town)}
        gcfg["renderer"] = {**cfg["renderer"], "town": gcfg["region"]}
        gcfg["generate"] = {
            "num_scenes": scenes_per_town, "seed": scene_seed + int(town), "workers": cfg["data"]["workers"],
            "endpoints": [], "drop_invalid": False, "validation": {"enabled": False},
            "objects": cfg["data"]["objects"], "camera": cfg["data"]["camera"],
        }
        run_cfg = {k: gcfg[k] for k in ("region", "renderer", "generate", "conditions") if k in gcfg}  # a run's keys
        ctx = Context(cfg=run_cfg, grid=grid, cache=StageCache(cfg["cache_dir"]), stages=["generate"], force=set())
        result = generate.run(ctx)
        seconds += float(pd.read_csv(result.timings_csv)["total_time"].sum())
        ds = open_dataset({"kind": "generated", "name": "train_demo"}, grid, root=result.path)
        images += [load_image(g.images[grid.reference]) for g in ds.groups]
        labels += [load_label(g.labels[grid.reference]) for g in ds.groups]
    return np.stack(images), np.stack(labels), seconds


def adverse_towns(cfg: dict) -> list[tuple[int, str]]:
    """`data.adverse`: (town seed, condition) of the extra training towns, the conditions in turn, so the
    model sees each of them on its own towns (never the Day renders of the same scenes)."""
    ad = cfg["data"].get("adverse") or {}
    conditions = list(ad.get("conditions") or [])
    if not conditions:
        return []
    return [(ad["town_seed"] + i, conditions[i % len(conditions)]) for i in range(ad["towns"])]


def render_adverse(cfg: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """The extra non-Day training images of `data.adverse` (each town rendered in its one condition, labelled
    exactly as the Day renders are): the zoo members whose robustness comes from their data, not augmentation."""
    ad = cfg["data"].get("adverse") or {}
    images, labels, seconds = [], [], 0.0
    for town, condition in adverse_towns(cfg):
        grid = build_condition_grid({**cfg["conditions"], "reference": condition, "only": [condition]})
        x, y, s = render_towns(cfg, grid, range(town, town + 1), ad["scenes_per_town"], cfg["data"]["scene_seed"])
        images.append(x)
        labels.append(y)
        seconds += s
    if not images:
        return np.zeros((0,), np.uint8), np.zeros((0,), np.uint8), 0.0
    return np.concatenate(images), np.concatenate(labels), seconds


DATA_FORMAT = 1


def data_fingerprint(cfg: dict) -> str:
    """What makes two exported data folders the same: the data section (but where it is read from) and the
    renderer, region, camera and condition that drew the scenes."""
    keep = {k: cfg.get(k) for k in ("renderer", "region", "camera", "condition")}
    keep["data"] = {k: v for k, v in cfg["data"].items() if k not in ("from_dir", "export_to", "workers")
                    and not (k == "adverse" and not adverse_towns(cfg))}  # Day-only recipes keep their fingerprint
    return hashlib.sha256(canonical_json(keep).encode()).hexdigest()[:16]


def export_data(cfg: dict, out: Path, splits: dict, render_s: float) -> None:
    """The rendered training set as a portable folder (lossless WebP images, PNG labels, a manifest), so a
    machine without Blender, a GPU node say, trains on exactly these pixels (`data.from_dir`). Written under a
    temporary name and renamed when complete."""
    from PIL import Image

    from pairedgta.jsonio import write_json

    if out.exists():
        raise SystemExit(f"data.export_to={out} exists; remove it or name another folder")
    tmp = out.with_name(out.name + ".tmp")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    for split, (images, labels) in splits.items():
        (tmp / split).mkdir(parents=True)
        for i, (img, lab) in enumerate(zip(images, labels)):
            Image.fromarray(img).save(tmp / split / f"{i:05d}.webp", lossless=True, quality=100, method=4)
            Image.fromarray(lab.astype(np.uint8)).save(tmp / split / f"{i:05d}_labels.png", optimize=True)
    write_json(tmp / "manifest.json", {"format": DATA_FORMAT, "fingerprint": data_fingerprint(cfg), "render_seconds": render_s,
                                       "counts": {k: len(v[0]) for k, v in splits.items()}})
    os.replace(tmp, out)
    print(f"exported {', '.join(f'{len(v[0])} {k}' for k, v in splits.items())} images -> {out}")


def import_data(cfg: dict, folder: Path) -> tuple[dict, float]:
    """Read a folder written by `data.export_to`; refuse one drawn with other data settings."""
    from PIL import Image

    manifest = folder / "manifest.json"
    if not manifest.is_file():
        raise SystemExit(f"data.from_dir={folder}: no manifest.json; write the folder with data.export_to=<dir> first")
    m = json.loads(manifest.read_text())
    if m.get("format") != DATA_FORMAT or m.get("fingerprint") != data_fingerprint(cfg):
        raise SystemExit(f"data.from_dir={folder} was exported with other data/renderer/camera settings "
                         f"(fingerprint {m.get('fingerprint')}, these settings {data_fingerprint(cfg)}); export it again")
    splits = {}
    for split, n in m["counts"].items():
        images, labels = [], []
        for i in range(n):
            try:
                images.append(np.asarray(Image.open(folder / split / f"{i:05d}.webp").convert("RGB")))
                labels.append(np.asarray(Image.open(folder / split / f"{i:05d}_labels.png")))
            except OSError as e:
                raise SystemExit(f"data.from_dir={folder}: {split}/{i:05d} is missing or corrupt ({e}); export it again") from e
        splits[split] = (np.stack(images), np.stack(labels))
    return splits, float(m["render_seconds"])


def photometric(img: torch.Tensor, rng: np.random.Generator, p: dict) -> torch.Tensor:
    """MMSegmentation's PhotoMetricDistortion on a 3 x H x W image in [0, 1]: additive brightness,
    contrast (before or after the colour steps, at random), saturation and hue in HSV; each step with
    probability 0.5. MMSegmentation's contrast multiplies the pixels (a brightness scale);
    `contrast_mode: blend` blends toward the image's mean grey instead (torchvision's definition), which
    is what lowers contrast. `grayscale_p` then turns the image grey with that probability."""
    from torchvision.transforms.v2 import functional as TF

    def contrast(x: torch.Tensor) -> torch.Tensor:
        if rng.random() < 0.5:
            alpha = float(rng.uniform(*p["contrast_range"]))
            x = TF.adjust_contrast(x, alpha) if p.get("contrast_mode", "multiply") == "blend" else (x * alpha).clamp(0, 1)
        return x

    if rng.random() < 0.5:
        img = (img + float(rng.uniform(-p["brightness_delta"], p["brightness_delta"])) / 255.0).clamp(0, 1)
    contrast_first = rng.random() < 0.5
    if contrast_first:
        img = contrast(img)
    if rng.random() < 0.5:
        img = TF.adjust_saturation(img, float(rng.uniform(*p["saturation_range"])))
    if rng.random() < 0.5:
        img = TF.adjust_hue(img, float(rng.uniform(-p["hue_delta"], p["hue_delta"])) / 360.0)
    if not contrast_first:
        img = contrast(img)
    if p.get("grayscale_p", 0.0) > 0 and rng.random() < p["grayscale_p"]:
        img = TF.rgb_to_grayscale(img, num_output_channels=3)
    return img


def sample(image: np.ndarray, label: np.ndarray, rng: np.random.Generator, a: dict,
           focus: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Random resize, crop (re-drawn while one class dominates; around a random pixel of `focus`
    when rare-class sampling chose that class and the resized image still shows it), flip,
    photometric distortion."""
    h, w = a["crop"]
    img = torch.tensor(image).permute(2, 0, 1).float().div(255)[None]
    lab = torch.tensor(label.astype(np.int64))[None, None].float()
    s = float(rng.uniform(*a["scale_range"]))
    H, W = img.shape[-2:]
    nh, nw = max(1, round(H * s)), max(1, round(W * s))
    img = F.interpolate(img, size=(nh, nw), mode="bilinear", align_corners=False, antialias=s < 1)
    lab = F.interpolate(lab, size=(nh, nw), mode="nearest")
    if nh < h or nw < w:  # pad: image with 0, labels with ignore
        img = F.pad(img, (0, max(0, w - nw), 0, max(0, h - nh)), value=0.0)
        lab = F.pad(lab, (0, max(0, w - nw), 0, max(0, h - nh)), value=float(IGNORE_INDEX))
        nh, nw = img.shape[-2:]
    where = (lab[0, 0] == focus).nonzero() if focus is not None else []
    if len(where):
        py, px = (int(v) for v in where[int(rng.integers(len(where)))])
        y0 = int(rng.integers(max(0, py - h + 1), min(py, nh - h) + 1))
        x0 = int(rng.integers(max(0, px - w + 1), min(px, nw - w) + 1))
    else:
        for _ in range(10):
            y0, x0 = int(rng.integers(nh - h + 1)), int(rng.integers(nw - w + 1))
            crop = lab[0, 0, y0 : y0 + h, x0 : x0 + w].long()
            counts = torch.bincount(crop[crop != IGNORE_INDEX].flatten(), minlength=NUM_CLASSES)
            if counts.sum() == 0 or counts.max() / counts.sum() < a["cat_max_ratio"]:
                break
    img, lab = img[0, :, y0 : y0 + h, x0 : x0 + w], lab[0, 0, y0 : y0 + h, x0 : x0 + w].long()
    if rng.random() < a["flip"]:
        img, lab = img.flip(-1), lab.flip(-1)
    return (photometric(img, rng, a["photometric"]) if a.get("photometric") else img), lab


class RareClassSampler:
    """Rare-class sampling (DAFormer, Hoyer et al. 2022): draw a class c with probability
    proportional to exp((1 - f_c) / T), f_c its share of the training pixels, then an image that shows
    at least `min_pixels` of it. Fences, signs, bicycles and riders cover < 0.3 % of the pixels but
    appear in a third to three quarters of the scenes; uniform image sampling shows them too seldom
    (and, with the crop, too small) for a small model to learn them. T -> infinity is uniform over the
    classes present."""

    def __init__(self, labels: np.ndarray, temperature: float, min_pixels: int):
        counts = np.stack([np.bincount(lab[lab != IGNORE_INDEX].ravel(), minlength=NUM_CLASSES)[:NUM_CLASSES]
                           for lab in labels])
        share = counts.sum(0) / max(1, counts.sum())
        self.images = [np.flatnonzero(counts[:, c] >= min_pixels) for c in range(NUM_CLASSES)]
        self.classes = np.array([c for c in range(NUM_CLASSES) if len(self.images[c])])
        logit = (1.0 - share[self.classes]) / temperature
        self.prob = np.exp(logit - logit.max())
        self.prob /= self.prob.sum()

    def draw(self, rng: np.random.Generator) -> tuple[int, int]:
        c = int(self.classes[rng.choice(len(self.classes), p=self.prob)])
        return int(self.images[c][rng.integers(len(self.images[c]))]), c


def batch(images, labels, rng, a: dict, size: int, rcs: RareClassSampler | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    if rcs is None:
        pairs = [sample(images[i], labels[i], rng, a) for i in rng.integers(len(images), size=size)]
    else:
        pairs = [sample(images[i], labels[i], rng, a, focus=c) for i, c in (rcs.draw(rng) for _ in range(size))]
    return torch.stack([x for x, _ in pairs]), torch.stack([y for _, y in pairs])


class StepBatches(torch.utils.data.Dataset):
    """Batch number `step` drawn from its own generator (seed, step), so loader workers can build batches in
    parallel and a resumed run draws the same batches. `train.loader_workers: 0` keeps the single sequential
    stream of the CPU recipe instead."""

    def __init__(self, images, labels, a: dict, size: int, rcs, seed: int):
        self.images, self.labels, self.a, self.size, self.rcs, self.seed = images, labels, a, size, rcs, seed

    def __len__(self) -> int:
        return 1 << 30

    def __getitem__(self, step: int):
        torch.set_num_threads(1)
        return batch(self.images, self.labels, np.random.default_rng([self.seed, step]), self.a, self.size, self.rcs)


def batches(train_x, train_y, rng, a: dict, t: dict, rcs, seed: int, start: int):
    """(step, x, y) from step start + 1 to t['steps']."""
    steps = range(start + 1, t["steps"] + 1)
    if not t.get("loader_workers"):
        for step in steps:
            yield (step, *batch(train_x, train_y, rng, a, t["batch_size"], rcs))
        return
    loader = torch.utils.data.DataLoader(StepBatches(train_x, train_y, a, t["batch_size"], rcs, seed), batch_size=None,
                                         sampler=list(steps), num_workers=t["loader_workers"], prefetch_factor=4,
                                         pin_memory=torch.cuda.is_available(), persistent_workers=False)
    for step, (x, y) in zip(steps, loader):
        yield step, x, y


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SystemExit("train.device=cuda but torch sees no CUDA device; use train.device=cpu or auto")
    return torch.device(name)


# -- models -------------------------------------------------------------------------------------------
IN_PROJECT = ("ddrnet", "pidnet", "deeplabv3plus")


def build_network(cfg: dict) -> torch.nn.Module:
    """The untrained network of `arch.family` with the zoo member's widths (<= 4 M parameters)."""
    arch = {k: v for k, v in cfg["arch"].items() if k != "family"}
    family = cfg["arch"].get("family", "segformer")
    if family == "segformer":
        from transformers import SegformerConfig, SegformerForSemanticSegmentation

        config = SegformerConfig(num_labels=NUM_CLASSES, id2label=dict(enumerate(CLASS_NAMES)),
                                 label2id={n: i for i, n in enumerate(CLASS_NAMES)}, **arch)
        return SegformerForSemanticSegmentation(config)
    import importlib

    from pairedgta.models import checkpoint

    architecture = importlib.import_module(f"pairedgta.models.{family}").architecture
    return checkpoint.build_network(architecture, {"name": cfg["model_name"], **arch})


def logits_of(model: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """Normalised B x 3 x H x W -> logits at the network's output stride (1/4 SegFormer, 1/8 DDRNet/PIDNet)."""
    out = model(pixel_values=x) if hasattr(model, "config") else model(x)
    return out.logits if hasattr(out, "logits") else out


def init_weights(cfg: dict, model: torch.nn.Module, source: str) -> torch.nn.Module:
    """`train.init_from`: a zoo folder of the same family (transformers folder or model.safetensors)."""
    if cfg["arch"].get("family", "segformer") == "segformer":
        from transformers import SegformerForSemanticSegmentation

        return SegformerForSemanticSegmentation.from_pretrained(source)
    from safetensors.torch import load_file

    model.load_state_dict(load_file(str(Path(source) / "model.safetensors")), strict=True)
    return model


@torch.inference_mode()
def validate(model, images, labels) -> ConfusionMatrix:
    model.eval()
    cm = ConfusionMatrix(NUM_CLASSES)
    dev = next(model.parameters()).device
    for img, lab in zip(images, labels):
        x = torch.from_numpy(img).permute(2, 0, 1).float().div(255)[None].to(dev)
        logits = logits_of(model, (x - MEAN.to(dev)) / STD.to(dev))
        logits = F.interpolate(logits, size=x.shape[-2:], mode="bilinear", align_corners=False)
        cm.update(lab, logits.argmax(1)[0].cpu().numpy())
    model.train()
    return cm


def miou(cm: ConfusionMatrix) -> float:
    """Cityscapes convention: the mean over classes with TP + FP + FN > 0."""
    iou = cm.iou().numpy()
    return float(np.nanmean(iou)) if not np.isnan(iou).all() else math.nan


# -- training -----------------------------------------------------------------------------------------
def ohem_cross_entropy(logits: torch.Tensor, target: torch.Tensor, thresh: float | None, min_kept: int) -> torch.Tensor:
    """Online hard example mining as the real-time Cityscapes recipes (BiSeNet, DDRNet, PIDNet) train:
    the mean loss over pixels whose true-class probability is below `thresh`, and at least the
    `min_kept` hardest labelled pixels, so thin and rare classes are not drowned by road and sky."""
    loss = F.cross_entropy(logits, target, ignore_index=IGNORE_INDEX, reduction="none").flatten()
    valid = target.flatten() != IGNORE_INDEX
    if not valid.any():
        return loss.sum() * 0.0  # zero, but still part of the graph
    loss = loss[valid]
    if thresh is None:
        return loss.mean()
    prob = torch.exp(-loss.detach())  # the softmax probability of the true class
    keep = prob < thresh
    if int(keep.sum()) < min(min_kept, loss.numel()):
        keep = torch.zeros_like(keep)
        keep[torch.topk(loss.detach(), min(min_kept, loss.numel())).indices] = True
    return loss[keep].mean()


def lr_factor(step: int, t: dict) -> float:
    warm = min(1.0, (step + 1) / max(1, t["warmup"]))
    return warm * (1 - min(step, t["steps"]) / (t["steps"] + 1)) ** t["poly_power"]


def _number(v, lo: float, hi: float, integer: bool = False) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
        return False
    return lo <= v <= hi


def check_config(cfg: dict) -> None:
    """Every recipe value a typo could break, checked before minutes of rendering: one line naming the key."""
    inf = float("inf")
    d, t, a, lo = cfg["data"], cfg["train"], cfg["augment"], cfg.get("loss") or {}
    ph = a.get("photometric") or {}
    family = (cfg.get("arch") or {}).get("family", "segformer")
    contrast_mode, grayscale_p = ph.get("contrast_mode", "multiply"), ph.get("grayscale_p", 0.0)
    rcs = a.get("rare_class_sampling") or {}
    rcs_t, rcs_min = rcs.get("temperature"), rcs.get("min_pixels", 16)
    checks = [
        (f"data.{k}", d.get(k), _number(d.get(k), 1, inf, True), "an integer >= 1")
        for k in ("train_towns", "train_scenes_per_town", "val_towns", "val_scenes_per_town", "workers")
    ] + [
        ("train.steps", t.get("steps"), _number(t.get("steps"), 1, inf, True), "an integer >= 1"),
        ("train.batch_size", t.get("batch_size"), _number(t.get("batch_size"), 1, inf, True), "an integer >= 1"),
        ("train.lr", t.get("lr"), _number(t.get("lr"), 1e-12, 10.0), "a learning rate > 0"),
        ("train.weight_decay", t.get("weight_decay"), _number(t.get("weight_decay"), 0.0, inf), ">= 0"),
        ("train.warmup", t.get("warmup"), _number(t.get("warmup"), 0, inf, True), "an integer >= 0"),
        ("train.poly_power", t.get("poly_power"), _number(t.get("poly_power"), 1e-6, inf), "> 0"),
        ("train.checkpoint_every", t.get("checkpoint_every"), _number(t.get("checkpoint_every"), 1, inf, True), "an integer >= 1"),
        ("train.eval_every", t.get("eval_every"), _number(t.get("eval_every"), 1, inf, True), "an integer >= 1"),
        ("train.threads", t.get("threads"), _number(t.get("threads"), 1, inf, True), "an integer >= 1"),
        ("train.device", t.get("device", "auto"), t.get("device", "auto") in ("auto", "cpu", "cuda"), "auto, cpu or cuda"),
        ("train.loader_workers", t.get("loader_workers", 0), _number(t.get("loader_workers", 0), 0, 64, True),
         "an integer >= 0 (0: batches built in the training process, one sequential random stream)"),
        ("loss.ohem_thresh", lo.get("ohem_thresh"), lo.get("ohem_thresh") is None or _number(lo.get("ohem_thresh"), 1e-6, 1.0),
         "null (plain cross-entropy) or a probability in (0, 1]"),
        ("loss.ohem_min_kept", lo.get("ohem_min_kept"), _number(lo.get("ohem_min_kept", 0), 0, inf, True), "an integer >= 0"),
        ("augment.flip", a.get("flip"), _number(a.get("flip"), 0.0, 1.0), "a probability in [0, 1]"),
        ("augment.photometric.contrast_mode", contrast_mode, contrast_mode in ("multiply", "blend"),
         "multiply (MMSegmentation) or blend (toward the mean grey)"),
        ("augment.photometric.grayscale_p", grayscale_p, _number(grayscale_p, 0.0, 1.0), "a probability in [0, 1]"),
        ("augment.rare_class_sampling.temperature", rcs_t, rcs_t is None or _number(rcs_t, 1e-4, inf),
         "null (images drawn uniformly) or a temperature > 0 (DAFormer uses 0.01)"),
        ("augment.rare_class_sampling.min_pixels", rcs_min, _number(rcs_min, 1, inf, True), "an integer >= 1"),
        ("augment.cat_max_ratio", a.get("cat_max_ratio"), _number(a.get("cat_max_ratio"), 1e-6, 1.0), "in (0, 1]"),
        ("augment.scale_range", a.get("scale_range"), isinstance(a.get("scale_range"), list) and len(a["scale_range"]) == 2
         and all(_number(v, 0.05, 8.0) for v in a["scale_range"]) and a["scale_range"][0] <= a["scale_range"][1],
         "[low, high] with 0.05 <= low <= high <= 8"),
        ("augment.crop", a.get("crop"), isinstance(a.get("crop"), list) and len(a["crop"]) == 2
         and all(_number(v, 16, 4096, True) for v in a["crop"]), "[height, width] in pixels, each 16..4096"),
        ("arch.family", family, family in ("segformer",) + IN_PROJECT,
         "segformer, " + ", ".join(IN_PROJECT) + " (pairedgta/models/<family>.py)"),
        ("model_name", cfg.get("model_name"), isinstance(cfg.get("model_name"), str)
         and cfg["model_name"].replace("_", "").isalnum(), "a name of letters, digits and _ (the model config's name)"),
        ("work_dir", cfg.get("work_dir"), isinstance(cfg.get("work_dir"), str) and cfg["work_dir"].strip() != "",
         "a directory for the resumable checkpoint"),
        ("out_dir", cfg.get("out_dir"), isinstance(cfg.get("out_dir"), str) and cfg["out_dir"].strip() != "",
         "a directory for the trained model"),
    ]
    ad = d.get("adverse") or {}
    known = [c.name for c in build_condition_grid({**cfg["conditions"], "only": None})]
    conds = ad.get("conditions") or []
    checks += [
        ("data.adverse.conditions", conds, isinstance(conds, list) and all(c in known for c in conds),
         f"a list of conditions of the grid ({', '.join(known)})"),
        ("data.adverse.towns", ad.get("towns", 0), _number(ad.get("towns", 0), 0 if not conds else 1, inf, True),
         "an integer >= 1 (the extra towns, each rendered in one of the conditions)" if conds else "an integer >= 0"),
    ]
    if conds:
        checks.append(("data.adverse.scenes_per_town", ad.get("scenes_per_town"),
                       _number(ad.get("scenes_per_town"), 1, inf, True), "an integer >= 1"))
        mine = {t for t, _ in adverse_towns(cfg)} if all(_number(ad.get(k), 0, inf, True) for k in ("town_seed", "towns")) else set()
        taken = set(range(d["train_town_seed"], d["train_town_seed"] + d["train_towns"])) | set(
            range(d["val_town_seed"], d["val_town_seed"] + d["val_towns"]))
        checks.append(("data.adverse.town_seed", ad.get("town_seed"), bool(mine) and not (mine & taken),
                       "an integer whose data.adverse.towns seeds miss the training and validation towns"))
    for key, value, ok, want in checks:
        if not ok:
            raise SystemExit(f"train_demo config: {key}={value!r} is invalid; set it to {want}")


def state_key(cfg: dict) -> str:
    """Checkpoints belong to one recipe: everything but how long and how fast it runs."""
    keep = {k: cfg[k] for k in ("model_name", "data", "arch", "augment", "loss", "seed", "renderer", "region")}
    keep["data"] = {k: v for k, v in cfg["data"].items() if k not in ("from_dir", "export_to")
                    and not (k == "adverse" and not adverse_towns(cfg))}  # Day-only recipes keep their checkpoints
    keep["train"] = {k: v for k, v in cfg["train"].items()
                     if k not in ("steps", "threads", "eval_every", "checkpoint_every", "device", "loader_workers")}
    if cfg["train"].get("loader_workers"):  # another batch stream: seeded per step
        keep["train"]["per_step_batches"] = True
    return hashlib.sha256(canonical_json(keep).encode()).hexdigest()[:12]


def save_checkpoint(path: Path, model, opt, sched, step: int, rng: np.random.Generator, history: list, elapsed: float) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(), "step": step,
                "rng": json.dumps(rng.bit_generator.state), "torch_rng": torch.get_rng_state(),
                "history": json.dumps(history), "elapsed": elapsed}, tmp)
    os.replace(tmp, path)


@hydra.main(version_base="1.3", config_path="pkg://pairedgta.conf", config_name="train_demo")
def main(dcfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    cfg = OmegaConf.to_container(dcfg, resolve=True)
    assert isinstance(cfg, dict)
    check_config(cfg)
    cfg["command"] = " ".join(["python experiments/train_demo_model.py", *HydraConfig.get().overrides.task])
    torch.set_num_threads(int(cfg["train"]["threads"]))
    grid = build_condition_grid({**cfg["conditions"], "only": [cfg["condition"]]})
    d, t, a = cfg["data"], cfg["train"], cfg["augment"]
    device = pick_device(t.get("device", "auto"))
    if device.type == "cuda":
        t["device_name"] = torch.cuda.get_device_name(device)
    if d.get("from_dir"):
        splits, render_s = import_data(cfg, ROOT / d["from_dir"])
        (train_x, train_y), (val_x, val_y) = splits["train"], splits["val"]
    else:
        train_x, train_y, train_render_s = render_towns(cfg, grid, range(d["train_town_seed"], d["train_town_seed"] + d["train_towns"]),
                                                        d["train_scenes_per_town"], d["scene_seed"])
        val_x, val_y, val_render_s = render_towns(cfg, grid, range(d["val_town_seed"], d["val_town_seed"] + d["val_towns"]),
                                                  d["val_scenes_per_town"], d["scene_seed"] + 100_000)
        extra_x, extra_y, extra_render_s = render_adverse(cfg)
        if len(extra_x):
            train_x, train_y = np.concatenate([train_x, extra_x]), np.concatenate([train_y, extra_y])
        render_s = train_render_s + val_render_s + extra_render_s
    if d.get("export_to"):
        export_data(cfg, ROOT / d["export_to"], {"train": (train_x, train_y), "val": (val_x, val_y)}, render_s)
        return
    log.info("data: %d train / %d held-out-town val images (%.0f s of rendering)", len(train_x), len(val_x), render_s)

    torch.manual_seed(cfg["seed"])
    model = build_network(cfg)
    if t.get("init_from"):
        model = init_weights(cfg, model, str(ROOT / t["init_from"]))
    n_params = sum(p.numel() for p in model.parameters())
    if n_params > 4_000_000:
        raise SystemExit(f"arch has {n_params} parameters; the demo model must stay <= 4 M")
    model.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=t["lr"], weight_decay=t["weight_decay"])
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, t))
    rng = np.random.default_rng(cfg["seed"])
    work = ROOT / cfg["work_dir"] / state_key(cfg)
    work.mkdir(parents=True, exist_ok=True)
    ckpt = work / "checkpoint.pt"
    start, history, elapsed = 0, [], 0.0
    if ckpt.is_file():
        state = torch.load(ckpt, map_location="cpu", weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        rng.bit_generator.state = json.loads(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        start, history, elapsed = int(state["step"]), json.loads(state["history"]), float(state["elapsed"])
        log.info("resuming from %s at step %d", ckpt, start)

    tracking = cfg.get("tracking") or {}
    if tracking.get("enabled", True):
        import mlflow

        mlflow.set_tracking_uri(tracking.get("uri"))
        mlflow.set_experiment("train_demo")
        mlflow.start_run(run_name=f"{cfg['model_name']}-{state_key(cfg)}")
        mlflow.log_params({"n_params": n_params, "train_images": len(train_x), "val_images": len(val_x),
                           **{f"train.{k}": v for k, v in t.items()}, **{f"augment.{k}": str(v) for k, v in a.items()}})
    r = a.get("rare_class_sampling") or {}
    rcs = RareClassSampler(train_y, r["temperature"], r.get("min_pixels", 16)) if r.get("temperature") else None
    model.train()
    t1 = time.perf_counter() - elapsed
    mean, std = MEAN.to(device), STD.to(device)
    bar = tqdm(batches(train_x, train_y, rng, a, t, rcs, cfg["seed"], start), initial=start, total=t["steps"],
               desc="train", unit="step", mininterval=5.0)
    for step, x, y in bar:
        x, y = x.to(device, non_blocking=True), y.to(device, non_blocking=True)
        logits = logits_of(model, (x - mean) / std)
        logits = F.interpolate(logits, size=y.shape[-2:], mode="bilinear", align_corners=False)
        loss = ohem_cross_entropy(logits, y, cfg["loss"]["ohem_thresh"], cfg["loss"]["ohem_min_kept"])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        bar.set_postfix(loss=f"{loss.item():.3f}", lr=f"{sched.get_last_lr()[0]:.2e}")
        if tracking.get("enabled", True) and step % 20 == 0:
            mlflow.log_metrics({"loss": loss.item(), "lr": sched.get_last_lr()[0]}, step=step)
        if step % t["eval_every"] == 0 or step == t["steps"]:
            m = miou(validate(model, val_x, val_y))
            history.append({"step": step, "loss": loss.item(), "val_miou": m})
            log.info("step %d val mIoU %.3f (%.2f s/step)", step, m, (time.perf_counter() - t1) / max(1, step))
            if tracking.get("enabled", True):
                mlflow.log_metric("val_miou", m, step=step)
        if step % t["checkpoint_every"] == 0 or step == t["steps"]:
            save_checkpoint(ckpt, model, opt, sched, step, rng, history, time.perf_counter() - t1)
    train_s = time.perf_counter() - t1
    model.to("cpu")
    write_model(cfg, model, n_params, validate(model, val_x, val_y), history, render_s, train_s, len(train_x), len(val_x))
    if tracking.get("enabled", True):
        mlflow.log_artifact(str(ROOT / cfg["out_dir"] / "model_card.json"))
        mlflow.end_run()


FAMILY_TEXT = {
    "segformer": "SegFormer (transformers)", "ddrnet": "DDRNet (the project's pairedgta/models/ddrnet.py)",
    "pidnet": "PIDNet (the project's pairedgta/models/pidnet.py)",
    "deeplabv3plus": "DeepLabV3+ (the project's pairedgta/models/deeplabv3plus.py)",
}


WEIGHTS_LINE = "- weights: float16 (model.safetensors; loaded as float32)"  # the model card README's line


def save_half(state: dict[str, torch.Tensor], path: Path, metadata: dict[str, str]) -> None:
    """A state dict as safetensors with its floating tensors in float16: the package's weights stay small
    (every loader computes in float32; a SegFormer folder's config keeps dtype float32, so transformers upcasts
    on load). Written under a temporary name and renamed."""
    from safetensors.torch import save_file

    state = {k: (v.detach().half() if v.is_floating_point() else v.detach()).contiguous() for k, v in state.items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(state, str(tmp), metadata=metadata)
    os.replace(tmp, path)


def halve_safetensors(path: Path) -> None:
    """Rewrite a safetensors file in float16 (`save_half`), its metadata kept."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        metadata = dict(f.metadata() or {})
        state = {k: f.get_tensor(k) for k in f.keys()}
    save_half(state, path, metadata)


def save_weights(cfg: dict, model: torch.nn.Module, out: Path) -> None:
    """SegFormer: a transformers folder (config, safetensors, preprocessor). The project's families: the
    state dict as model.safetensors, loaded strictly by the model config's `checkpoint_path`. Both in
    float16 (`save_half`)."""
    if cfg["arch"].get("family", "segformer") == "segformer":
        from transformers import SegformerImageProcessor

        model.save_pretrained(out, safe_serialization=True)
        SegformerImageProcessor(do_resize=False, image_mean=MEAN.flatten().tolist(),
                                image_std=STD.flatten().tolist()).save_pretrained(out)
        halve_safetensors(out / "model.safetensors")
        return
    save_half(model.state_dict(), out / "model.safetensors", {"family": cfg["arch"]["family"], "model": cfg["model_name"]})


def recipe_text(cfg: dict) -> str:
    a, t = cfg["augment"], cfg["train"]
    ohem = (cfg.get("loss") or {}).get("ohem_thresh")
    parts = [f"{t['steps']} steps, batch {t['batch_size']}, crops {a['crop']}, AdamW lr {t['lr']}, poly decay",
             f"OHEM cross-entropy (thresh {ohem})" if ohem is not None else "cross-entropy"]
    rcs_t = (a.get("rare_class_sampling") or {}).get("temperature")
    if rcs_t:
        parts.append(f"rare-class sampling (T = {rcs_t})")
    ph = a.get("photometric")
    if not ph:
        parts.append("no photometric distortion, contrast or greyscale augmentation (resize, crop and flip only)")
    else:
        parts.append(f"photometric distortion (contrast {ph.get('contrast_mode', 'multiply')}"
                     + (f", {ph['grayscale_p']:.0%} greyscale" if ph.get("grayscale_p") else "") + ")")
    text = ", ".join(parts)
    return text + (f"; started from the weights in `{t['init_from']}`" if t.get("init_from") else "")


def seen_text(cfg: dict, n_train: int) -> list[str]:
    towns = adverse_towns(cfg)
    if not towns:
        return ["only on synthetic daytime (Day-EXTRASUNNY) scenes of the embedded Blender renderer, with exact labels.",
                "It never saw rain, fog, sunset or night."]
    ad = cfg["data"]["adverse"]
    n_extra = len(towns) * ad["scenes_per_town"]
    return [f"on synthetic scenes of the embedded Blender renderer, with exact labels: {n_train - n_extra} daytime "
            f"(Day-EXTRASUNNY) scenes and {n_extra} ({n_extra / n_train:.0%}) scenes of {len(towns)} other towns under "
            + ", ".join(ad["conditions"]) + " (each town in one condition)."]


def trained_on(t: dict) -> str:
    if t.get("device_name"):
        return f"{t['device_name']} ({t.get('loader_workers', 0)} batch workers)"
    return f"{t['threads']} CPU thread{'s' if t['threads'] != 1 else ''}"


def write_model(cfg: dict, model, n_params: int, cm: ConfusionMatrix, history: list, render_s: float, train_s: float,
                n_train: int, n_val: int) -> None:
    d, t = cfg["data"], cfg["train"]
    iou = cm.iou().numpy()
    m = miou(cm)
    name, family = cfg["model_name"], cfg["arch"].get("family", "segformer")
    out = ROOT / cfg["out_dir"]
    out.mkdir(parents=True, exist_ok=True)
    save_weights(cfg, model, out)
    floor = max(0.0, m - cfg["miou_floor_margin"])
    card = {
        "model": name, "family": family, "parameters": n_params, "arch": cfg["arch"],
        "weights_dtype": "float16",
        "data": {"renderer": cfg["renderer"]["backend"], "region": cfg["region"]["name"], "condition": cfg["condition"],
                 "resolution": [cfg["renderer"]["height"], cfg["renderer"]["width"]], "train_images": n_train,
                 "val_images": n_val, **{k: v for k, v in d.items() if k not in ("objects", "camera", "workers")}},
        "augment": cfg["augment"], "loss": cfg["loss"], "train": t, "seed": cfg["seed"],
        "command": cfg.get("command"),
        "val_miou": m, "val_miou_convention": "mean over classes with TP+FP+FN > 0 (cityscapesScripts)",
        "val_pixel_accuracy": cm.accuracy(),
        "val_iou": {CLASS_NAMES[c]: float(iou[c]) for c in range(NUM_CLASSES) if not np.isnan(iou[c])},
        "test_floor_miou": floor, "history": history, "render_seconds": render_s, "train_seconds": train_s,
    }
    from pairedgta.jsonio import write_json

    write_json(out / "model_card.json", card)
    lines = [
        f"# {name}", "",
        f"A compact {FAMILY_TEXT[family]} ({n_params / 1e6:.2f} M parameters) trained by `experiments/train_demo_model.py`",
        *seen_text(cfg, n_train),
        "It demonstrates the method offline; it is not a Cityscapes model.", "",
        f"- command: `{cfg.get('command') or 'python experiments/train_demo_model.py'}`",
        f"- data: {n_train} training scenes from {d['train_towns']} towns"
        + (f" (and {len(adverse_towns(cfg))} adverse-condition towns)" if adverse_towns(cfg) else "")
        + f", {n_val} validation scenes from "
        f"{d['val_towns']} held-out towns, {cfg['renderer']['width']}x{cfg['renderer']['height']}",
        f"- training: {recipe_text(cfg)}",
        f"- validation mIoU (held-out towns, Cityscapes convention): {m:.3f}; test floor {floor:.3f}",
        WEIGHTS_LINE,
        f"- wall time: {render_s / 60:.0f} min rendering, {train_s / 60:.0f} min training on {trained_on(t)}", "",
        "| class | IoU |", "|---|---|",
        *[f"| {CLASS_NAMES[c]} | {iou[c]:.3f} |" for c in range(NUM_CLASSES) if not np.isnan(iou[c])],
    ]
    (out / "README.md").write_text("\n".join(lines) + "\n")
    for f in out.iterdir():  # shipped in the wheel: readable by every user (temp files are written 0600)
        f.chmod(0o644)
    print(f"{name}: val mIoU {m:.3f}, {n_params} parameters -> {out}")


if __name__ == "__main__":
    main()
