"""Benchmark of the evaluate stage: is it bound by the model forward, not by decoding, reductions or writing?

It renders a small dataset in the released layout (PNG files on disk), runs the pseudolabel and evaluate stages
of one model on it (`models=null`: only that model) and, on the same images already decoded and on the device,
the bare forward: the model's prediction and nothing else (`Segmenter.predict_maps(entropy=False)`: network,
upsampling, softmax, label map and max probability, left on the device; the bench's bare forward was always
`predict`, labels and confidence; timed before and after the stage, the mean). It prints images/s of
both and their ratio (target: >= 0.9 on the CPU, >= 0.7 on a GPU), and splits the stage's time into columns
that add up to 100 %: the forward, the rest of the counting (decoding not hidden by the workers, the reductions,
copies), and writing the entry's tables. On a GPU the forward is the GPU time between CUDA events around each
forward (the host only queues it), the other columns the wall time around it; and the peak GPU memory. Last, the
forward evaluate runs (the prediction and the estimators' maps: entropy, the logits' logsumexp, the Gram matrices)
and the stage against it ("vs maps"): what the stage's own work costs beside the estimators' arithmetic.

    python experiments/bench_evaluate.py [--groups 24] [--width 512 --height 256] [--workers 2] [--batch 4]
    python experiments/bench_evaluate.py --memory 50 500 --width 128 --height 64 --model tiny_segformer
    python experiments/bench_evaluate.py --device cuda --amp bf16 --model ddrnet_23 --arch - --full \\
        --width 2048 --height 1024 --conditions 9 --batch 9 --groups 8 --workers 12

`--full` builds a paper graph with random weights (the cost of a forward does not depend on them; offline).
Each measurement runs in a fresh process (peak RSS, thread pools and the CUDA context are its own); `measure`
runs one in this process (experiments/gpu_check.py, the tests).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a checkout without the package installed

CONDITIONS = ("Day-EXTRASUNNY", "Day-RAIN", "Night-EXTRASUNNY")
# SegFormer-B0 (MiT-b0 encoder, 256-wide decoder): the smallest of the paper's models, so the one where
# decoding is the largest share of the time
B0 = ("{depths:[2,2,2,2],hidden_sizes:[32,64,160,256],num_attention_heads:[1,2,5,8],mlp_ratios:[4,4,4,4],"
      "decoder_hidden_size:256}")


def _conditions(n: int) -> list[Any]:
    """The first 3 (clean, Day-RAIN, Night-EXTRASUNNY) or all 9 conditions of the paper's grid."""
    import yaml

    from pairedgta.conditions import build_condition_grid
    from pairedgta.configs import CONFIG_DIR

    grid = build_condition_grid(yaml.safe_load((Path(CONFIG_DIR) / "conditions" / "paper.yaml").read_text()))
    if n >= len(grid.conditions):
        return list(grid.conditions)
    by_name = {c.name: c for c in grid.conditions}
    return [by_name[c] for c in CONDITIONS[:n]]


def _render_one(job: tuple[str, int, int, int, int]) -> None:
    from pairedgta.datasets.base import save_png_atomic
    from pairedgta.render.synthetic import SyntheticRenderer
    from pairedgta.scene import Location, SceneDescriptor

    root, k, width, height, n_cond = job
    r = SyntheticRenderer(width=width, height=height)
    d = SceneDescriptor(scene_id=str(k), seed=k, location=Location(0, 0))
    for c in _conditions(n_cond):
        (Path(root) / c.time).mkdir(parents=True, exist_ok=True)
        save_png_atomic(r.render(d, c).image, Path(root) / c.time / f"{k}_{c.time}_{c.weather}.png")


def make_release_dataset(root: Path, n: int, width: int, height: int, conditions: int = 3, jobs: int = 1) -> None:
    """n groups x 3 (or 9) conditions in the released layout, rendered by the synthetic backend (`jobs` processes)."""
    todo = [(str(root), k, width, height, conditions) for k in range(n)]
    if jobs > 1 and n > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(min(jobs, n)) as pool:
            pool.map(_render_one, todo)
    else:
        for job in todo:
            _render_one(job)


def overrides(root: Path, cache: Path, model: str, workers: int | str, batch: int, arch: str, device: str = "cpu",
              amp: str | None = None, model_batch: int | None = None, full: bool = False, conditions: int = 3,
              extra: list[str] | None = None) -> list[str]:
    """The app's overrides for one measurement: only `model` (models=null), pseudolabel + evaluate."""
    names = [c.name for c in _conditions(conditions)]
    out = ["dataset=paired_gta", f"dataset.root={root}", f"cache_dir={cache}", "stages=[pseudolabel,evaluate]",
           "tracking.enabled=false", f"model={model}", "models=null", f"reference_model={model}",
           f"evaluate.num_workers={workers}", f"evaluate.batch_size={batch}", f"pseudolabel.batch_size={batch}",
           f"conditions.only=[{','.join(names)}]", "metric.bootstrap.resamples=100", f"device={device}"]
    if arch != "-":
        out.append(f"++model.arch={arch}")
    if amp:
        out.append(f"++model.amp={amp}")
    out.append(f"++model.batch_size={model_batch or batch}")
    if full:
        out.append("++model.random_init=true")
        if arch == "-":  # the paper graph's widths: without them a family builds its default (SegFormer's is B0)
            sys.path.insert(0, str(Path(__file__).resolve().parent))
            from paper_graphs import PAPER, hydra_value

            if "arch" in PAPER.get(model, {}):
                out.append(f"++model.arch={hydra_value(PAPER[model]['arch'])}")
    return out + list(extra or [])


@contextlib.contextmanager
def _timers(device_type: str) -> Iterator[dict[str, Any]]:
    """Times the forward (only inside evaluate's count_groups: the pseudolabel stage runs forwards of its own),
    count_groups and the writing of the tables; undone on exit."""
    import pairedgta.evaluation.work as ev
    import torch

    from pairedgta.evaluation import counting, entry
    from pairedgta.models.base import Segmenter

    t: dict[str, Any] = {"forward": 0.0, "count": 0.0, "write": 0.0, "events": [], "steady": 0.0, "wait": 0.0,
                         "result": 0.0, "staging": 0.0, "launch": 0.0}
    inside = [False]
    forward, count_groups, write_outputs = Segmenter._forward, ev.count_groups, entry.write_outputs
    load_groups = counting.load_groups
    first: list[float] = []

    def timed_load(*a: Any, **k: Any) -> Iterator[Any]:
        """Notes when the first group is decoded (the workers started): the steady state runs from there; and
        the time the stage waits for decoded groups (`wait`: after the first)."""
        items = iter(load_groups(*a, **k))
        while True:
            s = time.perf_counter()
            try:
                item = next(items)
            except StopIteration:
                return
            if first:
                t["wait"] += time.perf_counter() - s
            else:
                first.append(time.perf_counter())
            yield item

    def timed(key: str, fn: Any) -> Any:
        def run(*a: Any, **k: Any) -> Any:
            if not inside[0]:
                return fn(*a, **k)
            s = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                t[key] += time.perf_counter() - s
        return run

    def timed_forward(self: Any, chunk: Any, *a: Any, **k: Any) -> Any:
        if not inside[0]:
            return forward(self, chunk, *a, **k)
        if device_type == "cuda":  # the host only queues the forward: GPU time between events
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            out = forward(self, chunk, *a, **k)
            end.record()
            t["events"].append((start, end))
            return out
        s = time.perf_counter()
        out = forward(self, chunk, *a, **k)
        t["forward"] += time.perf_counter() - s
        return out

    def timed_count(*a: Any, **k: Any) -> Any:
        inside[0] = True
        first.clear()
        s = time.perf_counter()
        try:
            return count_groups(*a, **k)
        finally:
            if device_type == "cuda":
                torch.cuda.synchronize()
            end = time.perf_counter()
            t["count"] += end - s
            t["steady"] += end - (first[0] if first else s)
            inside[0] = False

    def timed_write(*a: Any, **k: Any) -> Any:
        s = time.perf_counter()
        try:
            return write_outputs(*a, **k)
        finally:
            t["write"] += time.perf_counter() - s

    result, stage_inputs, launch = counting.GroupJob.result, counting.stage_inputs, counting.GroupJob.__init__
    Segmenter._forward, ev.count_groups, entry.write_outputs = timed_forward, timed_count, timed_write
    counting.load_groups = timed_load
    counting.GroupJob.result, counting.stage_inputs = timed("result", result), timed("staging", stage_inputs)
    counting.GroupJob.__init__ = timed("launch", launch)
    try:
        yield t
    finally:
        Segmenter._forward, ev.count_groups, entry.write_outputs = forward, count_groups, write_outputs
        counting.load_groups = load_groups
        counting.GroupJob.result, counting.stage_inputs, counting.GroupJob.__init__ = result, stage_inputs, launch
        t["forward"] += sum(a.elapsed_time(b) for a, b in t.pop("events")) / 1000.0


def estimator_maps() -> dict[str, bool]:
    """What evaluate's forward computes beyond the prediction, for the registered metrics: the entropy, and what
    their `needs` ask (energy: the logits' logsumexp; gram: the Gram matrices)."""
    from pairedgta.evaluation import registry

    return {"entropy": True, **{n: True for m in registry.metrics() for n in m.needs}}


def bare_forward(seg: Any, groups: list[list[Any]], batch: int, warmup: int = 1, maps: bool = False) -> float:
    """Seconds of the bare forward (`predict_maps` without entropy: the prediction, left on the device) over
    `groups` (per group, its images in batches of `batch`, as evaluate batches them), the images decoded
    beforehand and already on the device as float in [0, 1]. With `maps`, the forward evaluate runs: the
    prediction and the estimators' maps (`estimator_maps`), without decoding, counting or writing."""
    import numpy as np
    import torch

    batches = [seg.to_device(np.stack(g[s : s + batch])) for g in groups for s in range(0, len(g), batch)]
    sync = torch.cuda.synchronize if seg.device.type == "cuda" else (lambda: None)
    kw = estimator_maps() if maps else {"entropy": False}
    for x in batches[:warmup]:
        seg.predict_maps(x, **kw)
    sync()
    start = time.perf_counter()
    for x in batches:
        seg.predict_maps(x, **kw)
    sync()
    seg.check_finite()
    return time.perf_counter() - start


def columns(t: dict[str, Any]) -> dict[str, float]:
    """The printed numbers from the raw timings: images/s of the stage's counting and of the bare forward, their
    ratio, and the stage's time (counting + writing) split into forward, the rest of the counting and writing,
    which add up to 1."""
    n, count, write = t["images"], t["count"], t["write"]
    forward = min(t["forward"], count)
    total = count + write
    eval_ips, bare_ips = n / count, n / t["bare"]
    steady_ips = n / t.get("steady", count) if t.get("steady", count) > 0 else eval_ips
    # against the forward with the estimators' maps: what the stage's own work (decoding, counting, copies) costs
    maps = {"maps_ips": n / t["maps"], "maps_ratio": eval_ips * t["maps"] / n} if t.get("maps") else {}
    return {"eval_ips": eval_ips, "bare_ips": bare_ips, "ratio": eval_ips / bare_ips, **maps,
            "forward_share": forward / total,
            "other_share": (count - forward) / total, "write_share": write / total,
            # parts of the host's time in the counting (the forward runs beside them on a GPU): waiting for decoded
            # groups, putting a group's inputs on the device, starting its forward and reductions (GroupJob(); on
            # the CPU the forward itself), reading its results back (GroupJob.result)
            **{f"{k}_share": t.get(k, 0.0) / total for k in ("wait", "staging", "launch", "result")},
            "stage_steady_ips": steady_ips, "steady_ratio": steady_ips / bare_ips}


def ready_workers_server(workers: int | str) -> None:
    """The decoding workers' fork server started and done importing before anything is timed: in the app it starts
    while the stage loads its model (seconds for a paper model), which the bench does before its timing."""
    from pairedgta.evaluation.inputs import start_workers_server, worker_context

    n = 0 if workers == "auto" else int(workers)
    ctx = worker_context() if n > 0 else None
    if ctx is not None:
        start_workers_server(n)
        p = ctx.Process(target=time.sleep, args=(0,))  # served only once the server has imported its modules
        p.start()
        p.join()


def measure(root: Path, cache: Path, model: str, workers: int | str, batch: int, arch: str, device: str = "cpu",
            amp: str | None = None, model_batch: int | None = None, full: bool = False, conditions: int = 3,
            extra: list[str] | None = None, repeats: int = 1) -> dict[str, Any]:
    """One measurement in this process: the bare forward (and its warm-up) first, then the stages and a bare forward
    after each, `repeats` times (the median run's columns; `ratios`, `ratio_spread`: every run's)."""
    import resource

    import numpy as np
    import torch
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from pairedgta.app import run
    from pairedgta.conditions import build_condition_grid
    from pairedgta.configs import CONFIG_DIR
    from pairedgta.datasets import load_image, open_dataset
    from pairedgta.models import build_model
    from pairedgta.models.runtime import reuse_freed_memory

    reuse_freed_memory()  # as app.run does before the stages: the bare forward under the same allocator
    args = overrides(root, cache, model, workers, batch, arch, device, amp, model_batch, full, conditions, extra)
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("config", overrides=args)
    c = OmegaConf.to_container(cfg, resolve=True)
    cuda = str(device).startswith("cuda")
    threads = torch.get_num_threads()
    torch.set_num_threads(int(c["threads"]))  # as the stage runs: the same CPU threads for both
    ds = open_dataset(c["dataset"], build_condition_grid(c["conditions"]))
    clean = c["conditions"]["reference"]
    images = [[load_image(g.images[k]) for k in sorted(g.images, key=lambda k: (k != clean, k))] for g in ds.groups]
    seg = build_model(c["model"], device=device)
    ready_workers_server(workers)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    out: dict[str, Any] = {"bare": bare_forward(seg, images, batch), "images": sum(len(g) for g in images),
                           "maps": bare_forward(seg, images, batch, maps=True)}
    if cuda:
        out["bare_peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    torch.set_num_threads(threads)
    import pairedgta.models as models

    build = models.build_model  # the stages get the model just timed (built once: the paper's take seconds)
    built = {c["model"]["name"]: seg}
    models.build_model = lambda cfg, device=None, **kw: built.get(cfg.get("name")) or build(cfg, device=device, **kw)
    # the stage `repeats` times (evaluate forced after the first), a bare forward after each: every stage run is
    # compared with the bare forwards just before and after it, so a machine that speeds up or slows down within
    # the run moves both sides of that ratio together; the median run is reported, with the spread of the ratios
    bare, with_maps, runs = [out["bare"]], [out["maps"]], []
    try:
        for i in range(repeats):
            if i:
                with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
                    cfg = compose("config", overrides=args + ["force=[evaluate]"])
            torch.set_num_threads(threads)
            start = time.perf_counter()
            with _timers("cuda" if cuda else "cpu") as t:
                run(cfg)
            t["stages"] = time.perf_counter() - start
            torch.set_num_threads(int(c["threads"]))
            bare.append(bare_forward(seg, images, batch))
            with_maps.append(bare_forward(seg, images, batch, maps=True))
            t["bare_before"], t["bare_after"] = bare[-2], bare[-1]
            t["bare"], t["maps"] = (bare[-2] + bare[-1]) / 2, (with_maps[-2] + with_maps[-1]) / 2
            t["ratio"] = columns({**t, "images": out["images"]})["ratio"]
            runs.append(t)
    finally:
        models.build_model = build
    built.clear()
    torch.set_num_threads(threads)
    ratios = [t["ratio"] for t in runs]
    median = sorted(runs, key=lambda t: t["ratio"])[len(runs) // 2]
    out.update({k: v for k, v in median.items() if k != "ratio"})
    out["ratios"], out["ratio_spread"] = ratios, max(ratios) - min(ratios)
    out["load"] = [round(x, 2) for x in os.getloadavg()]
    del seg
    if cuda:
        out["stage_peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out.update(columns(out))
    out.update(model=model, device=device, amp=amp or "fp32", batch=batch, workers=workers,
               width=int(np.asarray(images[0][0]).shape[1]), height=int(np.asarray(images[0][0]).shape[0]),
               groups=len(images))
    return out


def measure_child(*args: Any, **kwargs: Any) -> dict[str, Any]:
    """`measure` in a fresh process."""
    spec = json.dumps({"args": [str(a) if isinstance(a, Path) else a for a in args], "kwargs": kwargs})
    out = subprocess.run([sys.executable, __file__, "--child", spec], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                                           os.environ.get("PYTHONPATH", "")])})
    if out.returncode != 0:
        raise SystemExit(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


# ratio: the stage's counting (evaluate's part that scales with the images) over the bare forward; steady: the
# same from the first decoded group on (without starting the decoding workers)
# maps: the stage against the forward with the estimators' maps (`bare_forward(maps=True)`)
HEADER = (f"{'workers':>7} {'eval img/s':>10} {'bare img/s':>10} {'ratio':>6} {'steady':>6} {'forward':>8} "
          f"{'decode+reduce':>13} {'writing':>8} {'maps img/s':>10} {'vs maps':>7}")


def row(workers: Any, r: dict[str, Any]) -> str:
    maps = f"{r['maps_ips']:>10.2f} {r['maps_ratio']:>7.2f}" if "maps_ips" in r else f"{'-':>10} {'-':>7}"
    return (f"{str(workers):>7} {r['eval_ips']:>10.2f} {r['bare_ips']:>10.2f} {r['ratio']:>6.2f} "
            f"{r['steady_ratio']:>6.2f} {r['forward_share']:>8.1%} {r['other_share']:>13.1%} {r['write_share']:>8.1%} "
            f"{maps}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groups", type=int, default=24)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--conditions", type=int, default=3, choices=[3, 9], help="conditions per group (9: the paper's)")
    ap.add_argument("--workers", default="2", help="DataLoader decoding processes (besides 0); or auto")
    ap.add_argument("--batch", type=int, default=4, help="evaluate.batch_size (and model.batch_size unless given)")
    ap.add_argument("--model-batch", type=int, default=None)
    ap.add_argument("--model", default="tiny_segformer")
    ap.add_argument("--arch", default=B0, help="model.arch override (default: SegFormer-B0 widths); - = the model's own")
    ap.add_argument("--full", action="store_true", help="model.random_init=true: a paper graph without its weights")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--amp", default=None, choices=["bf16", "fp16"])
    ap.add_argument("--set", nargs="*", default=[], help="more overrides, e.g. model.channels_last=true")
    ap.add_argument("--memory", type=int, nargs="*", default=[], help="also peak RSS at these dataset sizes")
    ap.add_argument("--jobs", type=int, default=1, help="processes rendering the dataset")
    ap.add_argument("--json", default=None, help="append each measurement as a JSON line to this file")
    ap.add_argument("--repeats", type=int, default=3, help="stage runs per measurement, each between two bare forwards")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        spec = json.loads(args.child)
        print(json.dumps(measure(*spec["args"], **spec["kwargs"]), default=float))
        return
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        make_release_dataset(root, args.groups, args.width, args.height, args.conditions, args.jobs)
        arch = "SegFormer-B0 widths" if args.arch == B0 else f"arch={args.arch}"
        print(f"evaluate, {args.model} {arch}, {args.width}x{args.height}, {args.groups} groups x {args.conditions} "
              f"conditions, batch {args.batch}, {args.device} {args.amp or 'fp32'}")
        print(HEADER)
        kw = dict(device=args.device, amp=args.amp, model_batch=args.model_batch, full=args.full,
                  conditions=args.conditions, extra=args.set, repeats=args.repeats)
        cuda = args.device.startswith("cuda")
        for workers in ([args.workers] if cuda else sorted({0, int(args.workers)})):
            r = measure_child(root, Path(tmp) / f"cache{workers}", args.model, workers, args.batch, args.arch, **kw)
            print(row(workers, r) + (f"  peak GPU {r['stage_peak_gpu_mb']:.0f} MB" if cuda else "")
                  + f"  (bare {r['images'] / r['bare_before']:.2f} before, {r['images'] / r['bare_after']:.2f} after; "
                  f"ratio of each of {len(r['ratios'])} runs {', '.join(f'{x:.2f}' for x in r['ratios'])}, spread "
                  f"{r['ratio_spread']:.2f}; load {r['load'][0]})", flush=True)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(r, default=float) + "\n")
        rss = []
        for n in args.memory:
            r = Path(tmp) / f"mem{n}"
            make_release_dataset(r, n, args.width, args.height, args.conditions, args.jobs)
            rss.append((n, measure_child(r, Path(tmp) / f"cmem{n}", args.model, 0, args.batch, args.arch,
                                         **{**kw, "repeats": 1})["peak_rss_mb"]))
        for n, mb in rss:
            print(f"peak RSS with {n} groups: {mb:.0f} MB")
        if len(rss) >= 2:
            print(f"peak RSS ratio {rss[-1][0]} vs {rss[0][0]} groups: {rss[-1][1] / rss[0][1]:.3f} (flat = 1.0)")


if __name__ == "__main__":
    main()
