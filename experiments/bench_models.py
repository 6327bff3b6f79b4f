"""Throughput of the in-project families (DeepLabV3+, PIDNet, DDRNet) with random weights. Not a test.

Times `Segmenter.predict_proba` end to end (normalise, pad, forward, upsample, softmax, copy to CPU), which is
what an evaluation run pays per image.

    python experiments/bench_models.py                      # all families, tiny + full, batch 1 and 4
    python experiments/bench_models.py --graphs full --device cuda --amp bf16
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import torch

if importlib.util.find_spec("pairedgta") is None:  # run from a checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pairedgta.models import build_segmenter

GRAPHS = {
    "deeplabv3plus": {"tiny": "tiny_deeplabv3plus", "full": "deeplabv3plus_r101"},
    "pidnet": {"tiny": "tiny_pidnet", "full": "pidnet_m"},
    "ddrnet": {"tiny": "tiny_ddrnet", "full": "ddrnet_23"},
}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def seconds_per_call(seg, images: torch.Tensor, warmup: int, iters: int) -> float:
    for _ in range(warmup):
        seg.predict_proba(images)
    _sync(seg.device)
    start = time.perf_counter()
    for _ in range(iters):
        seg.predict_proba(images)
    _sync(seg.device)
    return (time.perf_counter() - start) / iters


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(GRAPHS), choices=list(GRAPHS))
    parser.add_argument("--graphs", nargs="+", default=["tiny", "full"], choices=["tiny", "full"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--width", type=int, default=1024)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--amp", default=None, choices=["bf16", "fp16"])
    args = parser.parse_args()

    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, input {args.height}x{args.width}")
    print(f"{'family':<14}{'graph':<6}{'model':<20}{'batch':>6}{'images/s':>11}{'ms/image':>11}")
    for family in args.families:
        for graph in args.graphs:
            name = GRAPHS[family][graph]
            seg = build_segmenter(name, random_init=True, checkpoint_path=None, init_seed=0,
                                  device=args.device, amp=args.amp)
            for batch in args.batches:
                seg.batch_size = batch  # one forward per call
                images = torch.rand(batch, 3, args.height, args.width)
                per_image = seconds_per_call(seg, images, args.warmup, args.iters) / batch
                print(f"{family:<14}{graph:<6}{name:<20}{batch:>6}{1.0 / per_image:>11.2f}{per_image * 1e3:>11.1f}",
                      flush=True)
            del seg


if __name__ == "__main__":
    main()
