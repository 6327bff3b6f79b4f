"""SegFormer (transformers): hub ids of the paper, a local directory, or a tiny random-init config."""
from __future__ import annotations

from typing import Any

import torch

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.models.base import Segmenter
from pairedgta.models.hf_common import Preprocessor, load_pretrained, preprocess_params
from pairedgta.models.runtime import RuntimeOptions


class SegFormerSegmenter(Segmenter):
    def __init__(self, name: str, model: torch.nn.Module, params: dict[str, Any], runtime: RuntimeOptions) -> None:
        super().__init__(name, model, runtime)
        self.pre = Preprocessor(params)

    def _logits(self, images: torch.Tensor) -> torch.Tensor:
        return self.module(pixel_values=self.pre(images)).logits


def build(
    *, name: str, family: str, hub_id: str | None = None, path: str | None = None,
    preprocess: str = "processor", random_init: bool = False, init_seed: int = 0, arch: dict | None = None,
    mean: list | None = None, std: list | None = None, resize: Any = None, size_divisor: int | None = None,
    runtime: RuntimeOptions,
) -> Segmenter:
    """Keyword arguments = the architecture keys of a pairedgta/conf/model YAML of this family; how it runs
    (device, batch_size, amp, ...) comes parsed in `runtime` (pairedgta/models/runtime.py)."""
    cfg = dict(locals())
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    if random_init:
        torch.manual_seed(int(init_seed))
        config = SegformerConfig(
            num_labels=len(CLASS_NAMES),
            id2label=dict(enumerate(CLASS_NAMES)),
            label2id={n: i for i, n in enumerate(CLASS_NAMES)},
            **dict(arch or {}),
        )
        model = SegformerForSemanticSegmentation(config)
    else:
        model = load_pretrained(SegformerForSemanticSegmentation, cfg)
    return SegFormerSegmenter(
        cfg["name"], model, preprocess_params(cfg), runtime)
