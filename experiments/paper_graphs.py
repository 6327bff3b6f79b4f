"""The paper's eight model graphs as the benchmarks build them without their weights (PAPER) and the Hydra
override grammar they are passed in (`hydra_value`). No torch: read by experiments/bench_models.py (which times the
graphs and, with `--stage`, runs experiments/bench_evaluate.py on each) and by bench_evaluate.py (`--full --arch -`),
so neither script imports the other for them. Not a test."""
from __future__ import annotations

from typing import Any

SWIN = {"depths": [2, 2, 18, 2]}
# the paper's eight graphs (pairedgta/conf/experiment/paper_table.yaml), as built without their weights
PAPER: dict[str, dict[str, Any]] = {
    "segformer_b5": {"random_init": True, "arch": {"depths": [3, 6, 40, 3], "hidden_sizes": [64, 128, 320, 512],
                                                   "num_attention_heads": [1, 2, 5, 8], "decoder_hidden_size": 768}},
    "mask2former_swin_l": {"random_init": True, "arch": {"backbone": {**SWIN, "embed_dim": 192,
                                                                      "num_heads": [6, 12, 24, 48], "window_size": 12}}},
    "segformer_b2": {"random_init": True, "arch": {"depths": [3, 4, 6, 3], "hidden_sizes": [64, 128, 320, 512],
                                                   "num_attention_heads": [1, 2, 5, 8], "decoder_hidden_size": 768}},
    "mask2former_swin_s": {"random_init": True, "arch": {"backbone": {**SWIN, "embed_dim": 96,
                                                                      "num_heads": [3, 6, 12, 24], "window_size": 7}}},
    "segformer_b0": {"random_init": True, "arch": {"depths": [2, 2, 2, 2], "hidden_sizes": [32, 64, 160, 256],
                                                   "num_attention_heads": [1, 2, 5, 8], "decoder_hidden_size": 256}},
    "ddrnet_23": {"random_init": True},
    "pidnet_m": {"random_init": True},
    "deeplabv3plus_r101": {"random_init": True},
}


def hydra_value(value: Any) -> str:
    """A Python value in Hydra's override grammar (dicts and lists nest)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{hydra_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(hydra_value(v) for v in value) + "]"
    return "null" if value is None else str(value)
