"""Throughput of the model families with random weights (the cost of a forward does not depend on them). Not a test.

Times the bare forward, the model's prediction (`Segmenter.predict_maps(entropy=False)`: normalise, pad, network,
upsample, softmax, label map and max probability, left on the device) on images already on the device, in the layout
evaluate hands them over; with `--stage` also the evaluate stage on PNGs read from disk (experiments/bench_evaluate.py),
so the two can be compared graph by graph.

    python experiments/bench_models.py                      # the in-project families, tiny + full, batch 1 and 4
    python experiments/bench_models.py --graphs full --device cuda --amp fp32 bf16 --batches 8
    python experiments/bench_models.py --graphs full --models ddrnet_23 --device cuda --stage --csv out.csv
    python experiments/bench_models.py --sources [--height 256 --width 512 --batches 4 --rounds 7]
    python experiments/bench_models.py --detector-sources   # task=detection's sources (experiments/bench_detector_sources.py)

`--sources`: each model source (docs/models.md) against the same network run natively in torch (its normalisation,
the network, upsampling and softmax written out by hand), on the same images: torchvision's LR-ASPP as
`model=torchvision`, `python`, `export` (.pt2) and `onnx`; an SMP Unet as `model=smp`; a SegFormer-B0 graph as
`model=hf`. Timings interleave the variants round by round, so a machine that speeds up or slows down during the run
moves them together; it prints the median per call, the ratio source / native (target <= 1.10 on the CPU; ONNX
may be faster) and the spread of the per-round ratios.

`--graphs full` are the paper's eight graphs (PAPER, experiments/paper_graphs.py): the in-project ones with random
weights, the transformers ones random-initialised with the published widths (no hub access, and no image processor:
they run at the input's size, where the hub's processor may resize first).
"""
from __future__ import annotations

import argparse
import csv
import datetime
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a checkout without the package installed
sys.path.insert(0, str(Path(__file__).resolve().parent))  # paper_graphs.py beside it, however this file is loaded

from pairedgta.models import build_model, model_config  # noqa: E402
from paper_graphs import PAPER, hydra_value  # noqa: E402

TINY = {"deeplabv3plus": "tiny_deeplabv3plus", "pidnet": "tiny_pidnet", "ddrnet": "tiny_ddrnet",
        "segformer": "tiny_segformer", "mask2former": "tiny_mask2former"}
IN_PROJECT = ("deeplabv3plus", "pidnet", "ddrnet")


def family(name: str) -> str:
    return str(model_config(name)["family"])


def graphs(kinds: list[str], families: list[str], names: list[str] | None) -> list[tuple[str, str, dict[str, Any]]]:
    """(graph kind, model name, overrides) to time."""
    out = []
    if names:
        return [("full" if n in PAPER else "tiny", n, dict(PAPER.get(n, {}))) for n in names]
    for kind in kinds:
        if kind == "tiny":
            out += [("tiny", TINY[f], {}) for f in TINY if f in families]
        else:
            out += [("full", n, dict(o)) for n, o in PAPER.items() if family(n) in families]
    return out


def model_overrides(options: dict[str, Any]) -> list[str]:
    """`++model.<key>=<value>` for the stage (bench_evaluate) from a graph's build overrides."""
    return [f"++model.{k}={hydra_value(v)}" for k, v in options.items()]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def seconds_per_call(seg: Any, images: torch.Tensor, warmup: int, iters: int) -> float:
    with torch.inference_mode():
        for _ in range(warmup):
            seg.predict_maps(images, entropy=False)
        _sync(seg.device)
        start = time.perf_counter()
        for _ in range(iters):
            seg.predict_maps(images, entropy=False)
        _sync(seg.device)
    return (time.perf_counter() - start) / iters


def time_forward(seg: Any, batch: int, height: int, width: int, amp: str, warmup: int, iters: int) -> dict[str, Any]:
    """images/s of the bare forward at `amp` (fp32, bf16, fp16) and its peak GPU memory; OOM is a row too."""
    cuda = seg.device.type == "cuda"
    seg.amp = None if amp == "fp32" or not cuda else amp
    seg.batch_size = batch  # one forward per call
    row: dict[str, Any] = {"batch": batch, "dtype": amp, "height": height, "width": width}
    try:
        if cuda:
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
        # as evaluate hands images over: H x W x 3 on the host, a channels-last view of float on the device
        images = seg.to_device(torch.rand(batch, height, width, 3))
        per_image = seconds_per_call(seg, images, warmup, iters) / batch
        row.update(forward_ips=1.0 / per_image, ms_per_image=per_image * 1e3)
        if cuda:
            row["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
    except Exception as exc:  # noqa: BLE001 - a bench row, not a crash (ModelError: out of memory)
        row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
    return row


def device_name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"


def append_csv(path: str | None, row: dict[str, Any]) -> None:
    if not path:
        return
    p = Path(path)
    new = not p.is_file()
    with open(p, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        if new:
            w.writeheader()
        w.writerow(row)


FIELDS = ["date", "device", "torch", "kind", "model", "family", "graph", "dtype", "batch", "height", "width",
          "forward_ips", "ms_per_image", "peak_gpu_mb", "stage_ips", "stage_steady_ips", "bare_ips", "ratio",
          "steady_ratio", "forward_share", "other_share", "write_share", "stage_peak_gpu_mb", "images", "workers",
          "error"]


def _source_variants(root: Path, batch: int, height: int, width: int) -> list[tuple[str, str, Any, Any]]:
    """(network, variant, native callable, segmenter) per source; the native callable maps [0, 1] images to the
    probabilities the source must give."""
    import warnings

    import torch.nn.functional as F
    from safetensors.torch import save_file

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import source_nets

    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    example = torch.rand(2, 3, height, width)

    def weights(module: Any, name: str) -> str:
        save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(root / name))
        return str(root / name)

    def build(name: str, cfg: dict[str, Any]) -> Any:
        seg = build_model({"name": name, **cfg})
        seg.batch_size = batch
        return seg

    out = []
    tv = source_nets.lraspp().eval()
    ckpt = weights(tv, "lraspp.safetensors")

    def tv_native(x: torch.Tensor) -> torch.Tensor:
        return tv((x - mean) / std)["out"].softmax(1)

    class Out(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = tv

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.net(x)["out"]

    dims = {0: torch.export.Dim("batch"), 2: 8 * torch.export.Dim("h"), 3: 8 * torch.export.Dim("w")}
    torch.export.save(torch.export.export(Out().eval(), (example,), dynamic_shapes={"x": dims}), str(root / "lraspp.pt2"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(Out().eval(), (example,), str(root / "lraspp.onnx"), dynamo=False, input_names=["image"],
                          output_names=["scores"], dynamic_axes={"image": {0: "b", 2: "h", 3: "w"}})
    out += [("lraspp", "torchvision", tv_native, build("tv", {"family": "torchvision", "arch": "lraspp_mobilenet_v3_large",
                                                               "checkpoint_path": ckpt})),
            ("lraspp", "python", tv_native, build("py", {"family": "python", "target": "source_nets:lraspp",
                                                         "checkpoint_path": ckpt})),
            ("lraspp", "export", tv_native, build("ex", {"family": "export", "path": str(root / "lraspp.pt2")})),
            ("lraspp", "onnx", tv_native, build("ox", {"family": "onnx", "path": str(root / "lraspp.onnx")}))]
    import segmentation_models_pytorch as smp

    torch.manual_seed(0)
    unet = smp.Unet("resnet18", encoder_weights=None, classes=19).eval()
    unet.save_pretrained(root / "unet")

    def unet_native(x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        y = F.pad((x - mean) / std, (0, -w % 32, 0, -h % 32))
        return unet(y)[..., :h, :w].softmax(1)

    out.append(("unet", "smp", unet_native, build("smp", {"family": "smp", "path": str(root / "unet")})))
    from transformers import SegformerImageProcessor

    torch.manual_seed(0)
    b0 = source_nets.segformer(depths=[2, 2, 2, 2], hidden_sizes=[32, 64, 160, 256], num_attention_heads=[1, 2, 5, 8],
                               decoder_hidden_size=256).eval()
    b0.save_pretrained(root / "b0")
    SegformerImageProcessor(do_resize=False).save_pretrained(root / "b0")

    def b0_native(x: torch.Tensor) -> torch.Tensor:
        logits = b0(pixel_values=(x - mean) / std).logits
        return F.interpolate(logits, size=x.shape[-2:], mode="bilinear", align_corners=False).softmax(1)

    out.append(("segformer_b0", "hf", b0_native, build("hf", {"family": "hf", "path": str(root / "b0")})))
    return out


def bench_sources(batch: int, height: int, width: int, rounds: int) -> None:
    import statistics
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        variants = _source_variants(Path(tmp), batch, height, width)
        images = torch.rand(batch, 3, height, width, generator=torch.Generator().manual_seed(0))
        times: dict[tuple[str, str], list[float]] = {}
        natives: dict[str, list[float]] = {}
        with torch.inference_mode():
            for net, variant, native, seg in variants:  # warm-up, and the same numbers
                diff = (seg.probabilities(images) - native(images)).abs().max().item()
                print(f"{net:<14}{variant:<12} max |p_source - p_native| {diff:.1e}")
            for _ in range(rounds):
                done = set()
                for net, variant, native, seg in variants:
                    if net not in done:  # the native forward once per network and round, beside its sources
                        start = time.perf_counter()
                        native(images)
                        natives.setdefault(net, []).append(time.perf_counter() - start)
                        done.add(net)
                    start = time.perf_counter()
                    seg.probabilities(images)
                    times.setdefault((net, variant), []).append(time.perf_counter() - start)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, batch {batch} of {height}x{width}, "
          f"{rounds} interleaved rounds")
    print(f"{'network':<14}{'source':<12}{'native ms/img':>14}{'source ms/img':>14}{'ratio':>8}{'per-round range':>18}")
    for (net, variant), ts in times.items():
        per_round = [t / n for t, n in zip(ts, natives[net])]
        ratio = statistics.median(ts) / statistics.median(natives[net])
        print(f"{net:<14}{variant:<12}{statistics.median(natives[net]) / batch * 1e3:>14.1f}"
              f"{statistics.median(ts) / batch * 1e3:>14.1f}{ratio:>8.3f}"
              f"{f'{min(per_round):.3f}-{max(per_round):.3f}':>18}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(IN_PROJECT), choices=list(TINY))
    parser.add_argument("--graphs", nargs="+", default=["tiny", "full"], choices=["tiny", "full"])
    parser.add_argument("--models", nargs="*", default=None, help="these model names instead (PAPER's overrides)")
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--width", type=int, default=1024)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--amp", nargs="+", default=["fp32"], choices=["fp32", "bf16", "fp16"])
    parser.add_argument("--stage", action="store_true", help="also the evaluate stage (bench_evaluate) per graph")
    parser.add_argument("--stage-groups", type=int, default=4)
    parser.add_argument("--workers", default="auto")
    parser.add_argument("--csv", default=None, help="append one row per measurement")
    parser.add_argument("--sources", action="store_true", help="the model sources against native torch (above)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--detector-sources", action="store_true",
                        help="the detector sources against native torch (experiments/bench_detector_sources.py)")
    args = parser.parse_args()
    if args.detector_sources:
        import bench_detector_sources

        height, width = (args.height, args.width) if {"--height", "--width"} & set(sys.argv) else (256, 512)
        bench_detector_sources.bench(max(args.batches) if "--batches" in sys.argv else 4, height, width, args.rounds)
        return
    if args.sources:
        height, width = (args.height, args.width) if {"--height", "--width"} & set(sys.argv) else (256, 512)
        bench_sources(max(args.batches) if "--batches" in sys.argv else 4, height, width, args.rounds)
        return
    if args.graphs == ["full"] and args.families == list(IN_PROJECT) and "--families" not in sys.argv:
        args.families = list(TINY)  # --graphs full: the paper's eight, transformers families included

    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    base = {"date": datetime.date.today().isoformat(), "device": device_name(device), "torch": torch.__version__}
    print(f"torch {torch.__version__}, {base['device']}, {torch.get_num_threads()} CPU threads, "
          f"input {args.height}x{args.width}")
    print(f"{'family':<14}{'graph':<6}{'model':<20}{'dtype':>6}{'batch':>6}{'images/s':>11}{'ms/image':>11}"
          f"{'peak MB':>9}")
    stage_root = None
    for kind, name, options in graphs(args.graphs, args.families, args.models):
        fam = family(name)
        seg = build_model(name, device=str(device), **options)
        for amp in args.amp:
            for batch in args.batches:
                row = {**base, "kind": "forward", "model": name, "family": fam, "graph": kind,
                       **time_forward(seg, batch, args.height, args.width, amp, args.warmup, args.iters)}
                shown = (f"{row['forward_ips']:>11.2f}{row['ms_per_image']:>11.1f}" if "error" not in row
                         else f"  {row['error']}")
                print(f"{fam:<14}{kind:<6}{name:<20}{amp:>6}{batch:>6}{shown}"
                      + (f"{row['peak_gpu_mb']:>9.0f}" if "peak_gpu_mb" in row else ""), flush=True)
                append_csv(args.csv, row)
        del seg
        if device.type == "cuda":
            torch.cuda.empty_cache()
        if args.stage:
            import tempfile

            import bench_evaluate as be

            if stage_root is None:
                stage_root = Path(tempfile.mkdtemp()) / "ds"
                be.make_release_dataset(stage_root, args.stage_groups, args.width, args.height, conditions=9, jobs=8)
            for amp in args.amp:
                batch = max(args.batches)
                r = be.measure(stage_root, stage_root.parent / f"cache-{name}-{amp}", name, args.workers, batch, "-",
                               str(device), None if amp == "fp32" else amp, full=False, conditions=9,
                               extra=model_overrides(options))
                row = {**base, "kind": "stage", "model": name, "family": fam, "graph": kind, "dtype": amp,
                       "batch": batch, "height": args.height, "width": args.width, "stage_ips": r["eval_ips"],
                       **{k: r.get(k) for k in ("stage_steady_ips", "bare_ips", "ratio", "steady_ratio",
                                                "forward_share", "other_share", "write_share", "stage_peak_gpu_mb",
                                                "images", "workers")}}
                print(f"{fam:<14}{kind:<6}{name:<20}{amp:>6}{batch:>6}  stage {r['eval_ips']:.2f} img/s, bare "
                      f"{r['bare_ips']:.2f}, ratio {r['ratio']:.2f}", flush=True)
                append_csv(args.csv, row)


if __name__ == "__main__":
    main()
