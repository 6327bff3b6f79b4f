"""Mask2Former (transformers) with the paper's semantic probabilities.

Per-class score = sum_q softmax(class_q)[:-1] * sigmoid(mask_q), as in Mask2Former's semantic
inference; we renormalise over the 19 classes so the result is a distribution and the paper's
confidence thresholds (tau) mean the same thing for every family.
"""
from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.models.base import Segmenter
from pairedgta.models.hf_common import Preprocessor, load_pretrained, preprocess_params, query_class_scores
from pairedgta.models.runtime import RuntimeOptions


class Mask2FormerSegmenter(Segmenter):
    def __init__(self, name: str, model: torch.nn.Module, params: dict[str, Any], runtime: RuntimeOptions) -> None:
        super().__init__(name, model, runtime)
        self.pre = Preprocessor(params)

    def _logits(self, images: torch.Tensor) -> torch.Tensor:  # pragma: no cover - not used
        raise NotImplementedError("Mask2Former produces probabilities, see _probabilities")

    def _probabilities(self, images: torch.Tensor) -> torch.Tensor:
        x = self.pre(images)
        x, (h, w) = self.pre.pad(x)
        out = self.module(pixel_values=x)
        sem = query_class_scores(out.class_queries_logits, out.masks_queries_logits)
        sem = F.interpolate(sem, size=x.shape[-2:], mode="bilinear", align_corners=False)[..., :h, :w]
        sem = F.interpolate(sem, size=images.shape[-2:], mode="bilinear", align_corners=False)
        return sem / sem.sum(dim=1, keepdim=True).clamp_min(1e-6)


def build(
    *, name: str, family: str, hub_id: str | None = None, path: str | None = None,
    preprocess: str = "processor", random_init: bool = False, init_seed: int = 0, arch: dict | None = None,
    mean: list | None = None, std: list | None = None, resize: Any = None, size_divisor: int | None = None,
    runtime: RuntimeOptions,
) -> Segmenter:
    """Keyword arguments = the architecture keys of a pairedgta/conf/model YAML of this family; how it runs
    (device, batch_size, amp, ...) comes parsed in `runtime` (pairedgta/models/runtime.py)."""
    cfg = dict(locals())
    from transformers import Mask2FormerConfig, Mask2FormerForUniversalSegmentation, SwinConfig

    if random_init:
        torch.manual_seed(int(init_seed))
        arch = dict(arch or {})
        backbone = SwinConfig(
            out_features=["stage1", "stage2", "stage3", "stage4"], **dict(arch.pop("backbone", {}) or {})
        )
        config = Mask2FormerConfig(
            backbone_config=backbone,
            num_labels=len(CLASS_NAMES),
            id2label=dict(enumerate(CLASS_NAMES)),
            label2id={n: i for i, n in enumerate(CLASS_NAMES)},
            **arch,
        )
        model = Mask2FormerForUniversalSegmentation(config)
    else:
        model = load_pretrained(Mask2FormerForUniversalSegmentation, cfg)
    params = preprocess_params(cfg)
    if not params.get("size_divisor"):
        params["size_divisor"] = 32
    return Mask2FormerSegmenter(
        cfg["name"], model, params, runtime)
