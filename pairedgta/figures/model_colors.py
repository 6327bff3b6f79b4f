"""Model names and colours, without matplotlib: the MLflow record colours a model's run as the figures
draw it, and must not pay ~1 s of plotting imports for it."""
from __future__ import annotations

import zlib

MODEL_DISPLAY = {
    "segformer_b0": "SegFormer-B0", "segformer_b2": "SegFormer-B2", "segformer_b5": "SegFormer-B5",
    "mask2former_swin_s": "Mask2Former Swin-S", "mask2former_swin_l": "Mask2Former Swin-L",
    "deeplabv3plus_r101": "DeepLabV3+ R101", "pidnet_m": "PIDNet-M", "ddrnet_23": "DDRNet-23",
    # the offline zoo (pairedgta/models/weights)
    "demo_segformer": "demo SegFormer", "demo_segformer_noaug": "demo SegFormer no-aug",
    "demo_ddrnet": "demo DDRNet", "demo_pidnet": "demo PIDNet",
    "demo_deeplabv3plus": "demo DeepLabV3+", "demo_deeplabv3plus_noaug": "demo DeepLabV3+ no-aug",
    "demo_ddrnet_short": "demo DDRNet short", "demo_pidnet_partial": "demo PIDNet partial-aug",
    "demo_ddrnet_short_seed1": "demo DDRNet short seed 1", "demo_deeplabv3plus_adverse": "demo DeepLabV3+ adverse data",
    "demo_deeplabv3plus_towns": "demo DeepLabV3+ other towns", "demo_deeplabv3plus_night": "demo DeepLabV3+ night-tuned",
    "demo_deeplabv3plus_night_seed1": "demo DeepLabV3+ night-tuned seed 1",
    "demo_deeplabv3plus_lowres": "demo DeepLabV3+ low-res", "demo_segformer_adverse": "demo SegFormer adverse-tuned",
    "demo_segformer_small_adverse": "demo SegFormer small adverse-tuned",
    "demo_segformer_small_adverse_seed1": "demo SegFormer small adverse-tuned seed 1",
    "demo_segformer_noaug_adverse": "demo SegFormer no-aug adverse-tuned",
}
# a fixed colour per model, so a model has the same colour in every figure of every run
# (the zoo's members added later come after the tiny test models, so that no earlier model changes colour)
_LATER = list(MODEL_DISPLAY)[list(MODEL_DISPLAY).index("demo_ddrnet_short_seed1"):]
MODEL_ORDER = ([m for m in MODEL_DISPLAY if m not in _LATER]
               + ["tiny_segformer", "tiny_mask2former", "tiny_deeplabv3plus", "tiny_pidnet", "tiny_ddrnet"] + _LATER)
# matplotlib's (and seaborn's) "tab10" then "Dark2" qualitative palettes, as hex; tests/test_figures.py
# checks them against matplotlib's
MODEL_PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
    "#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666",
)


def model_color_hex(name: str) -> str:
    """A model's colour: its place in MODEL_ORDER, or (a model of the user's) a hash of its name."""
    idx = MODEL_ORDER.index(name) if name in MODEL_ORDER else zlib.crc32(name.encode())
    return MODEL_PALETTE[idx % len(MODEL_PALETTE)]
