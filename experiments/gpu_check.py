"""Every GPU measurement of issue 48 in one run, for a lent GPU machine with a few minutes of device time.

    python experiments/gpu_check.py prepare            # here: gpu_bundle/ (git-ignored): wheels, main job, CPU reference
    bash experiments/gpu_check.sh                      # there: installs the wheels, runs `run` below
    python experiments/gpu_check.py run --device cpu --tiny   # the same end to end on the CPU, tiny (a rehearsal)

`run` measures, most important first, and skips what its time budget (--budget, seconds) leaves no room for:
  1. check     the device reductions against numpy on this machine's numpy (the order of the float sums) and the
               same maps reduced on the CPU (counts and sums equal), on random probabilities;
  2. mainjob   the main job's pseudolabel + evaluate on the device, against the CPU outputs of the same commit
               (gpu_bundle/mainjob/cpu): how far CUDA and CPU results differ, per file and column;
  3. ratio     the evaluate stage reading PNGs over the bare forward on the same images on the device, DDRNet-23 and
               DeepLabV3+-R101 in fp32 and bf16 and SegFormer-B5 in bf16 and fp32, at --size (2048x1024), 9 conditions
               a group, batch 9 (one forward per group);
  4. forward   the bare forward of the paper's eight graphs in fp32 and bf16 at --size, batch 8, and peak GPU memory;
  5. eta       the stage (bf16) of the eight at --eta-size (1920x1080): images/s, and the time for 1,000 groups x 9
               conditions with all eight on this card (plus pseudo-labelling with SegFormer-B5).
  6. sources   the model sources of issue 56 on the device: Mask2Former-Swin-S saved as a user's save_pretrained
               folder through `model=hf` (the universal auto class, bf16), and demo_ddrnet exported to ONNX here
               (gpu_bundle/demo_ddrnet.onnx) through `model=onnx` with the CUDA provider, where the machine's
               onnxruntime has one (a row says which providers it has).
Rows go to <out>/gpu_<date>_<card>.csv as they are measured and a summary to <out>/gpu_<date>_<card>.md after each
step; <out> is $OUT when set (the lent machine sends back what is written there), else experiments/results.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "experiments")]

MAIN_MODELS = ("demo_segformer", "demo_segformer_noaug", "demo_ddrnet", "demo_pidnet")
MAIN_FILES = ("xi.csv", "pixel_agreement.csv", "gt_iou.csv", "estimators.csv", "rho_valid.csv", "frame_counts.csv",
              "summary.json", "predictions.npz")
RATIO = [("ddrnet_23", "fp32"), ("ddrnet_23", "bf16"), ("deeplabv3plus_r101", "fp32"), ("deeplabv3plus_r101", "bf16"),
         ("segformer_b5", "bf16"), ("segformer_b5", "fp32")]
# groups of 9 per stage measurement: a few seconds of forward each on an H100 (fast graphs need more groups)
GROUPS = {"ddrnet_23": 24, "pidnet_m": 24, "segformer_b0": 24, "segformer_b2": 12, "deeplabv3plus_r101": 8,
          "segformer_b5": 6, "mask2former_swin_s": 6, "mask2former_swin_l": 4}
TINY = {"ddrnet_23": "tiny_ddrnet", "pidnet_m": "tiny_pidnet", "deeplabv3plus_r101": "tiny_deeplabv3plus",
        "segformer_b5": "tiny_segformer", "segformer_b2": "tiny_segformer", "segformer_b0": "tiny_segformer",
        "mask2former_swin_s": "tiny_mask2former", "mask2former_swin_l": "tiny_mask2former"}
FIELDS = ["step", "model", "dtype", "batch", "width", "height", "groups", "images", "forward_ips", "stage_ips",
          "stage_steady_ips", "bare_ips", "ratio", "steady_ratio", "forward_share", "other_share", "write_share",
          "peak_gpu_mb", "stage_peak_gpu_mb", "workers", "file", "column", "max_abs_diff", "differing", "value",
          "note", "wait_share", "staging_share", "launch_share", "result_share"]


# -- prepare (on the development machine) ---------------------------------------------------------------------------
def compose(overrides: list[str]) -> Any:
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from pairedgta.configs import CONFIG_DIR

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return hydra_compose("config", overrides=overrides)


def run_main_job(cache: Path, dataset_root: Path | None, device: str, stages: str) -> dict[str, Any]:
    from pairedgta.app import run

    args = [f"cache_dir={cache}", "tracking.enabled=false", f"stages=[{stages}]", f"device={device}"]
    if dataset_root is not None:
        args.append(f"dataset.root={dataset_root}")
    return run(compose(args))


def prepare(bundle: Path, cache: Path | None) -> None:
    """gpu_bundle/: the wheels the lent machine lacks (hydra-core, omegaconf, antlr4 runtime; it has scipy, whose
    wheel would not fit beside the rest in one call's 64 MiB), the main job's generated dataset, this machine's CPU
    outputs of it (pseudolabel + evaluate of the four models) and demo_ddrnet as ONNX."""
    import hydra
    import omegaconf

    wheels = bundle / "wheels"
    shutil.rmtree(bundle, ignore_errors=True)
    wheels.mkdir(parents=True)
    pip = [sys.executable, "-m", "pip"]
    subprocess.run(pip + ["download", "--no-deps", "-d", str(wheels), f"hydra-core=={hydra.__version__}",
                          f"omegaconf=={omegaconf.__version__}"], check=True)
    subprocess.run(pip + ["wheel", "--no-deps", "-w", str(wheels), "antlr4-python3-runtime==4.9.3"], check=True)
    cache = cache or Path(tempfile.mkdtemp(prefix="gpu-prepare-"))
    summary = run_main_job(cache, None, "cpu", "generate")
    entry = Path(summary.get("generate") or next((cache / "generate").iterdir()))
    main = bundle / "mainjob"
    shutil.copytree(entry, main / "generate")
    summary = run_main_job(cache / "reference", main / "generate", "cpu", "pseudolabel,evaluate")
    for name, path in summary["evaluate"].items():
        (main / "cpu" / name).mkdir(parents=True)
        for f in MAIN_FILES:
            shutil.copy2(Path(path) / f, main / "cpu" / name / f)
    shutil.copytree(Path(summary["pseudolabel"]) / "labels", main / "cpu" / "pseudolabel")
    export_onnx(bundle / "demo_ddrnet.onnx")
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    commit += "+uncommitted changes" if dirty else ""
    (main / "meta.json").write_text(json.dumps({"commit": commit, "date": datetime.date.today().isoformat(),
                                                "cpu": platform.processor() or platform.machine(),
                                                "models": sorted(summary["evaluate"])}, indent=1))
    size = sum(p.stat().st_size for p in bundle.rglob("*") if p.is_file()) / 2**20
    print(f"{bundle}: {size:.1f} MiB (carry it: run(carry=['{bundle.relative_to(ROOT)}']))")


def export_onnx(path: Path) -> None:
    """demo_ddrnet as a user would hand it over: an ONNX graph with dynamic batch and size (multiples of 32)."""
    import warnings

    import torch

    from pairedgta.models import build_model

    module = build_model("demo_ddrnet").module.eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, (torch.rand(2, 3, 256, 512),), str(path), dynamo=False, input_names=["image"],
                          output_names=["scores"], dynamic_axes={"image": {0: "b", 2: "h", 3: "w"}})


# -- run (on the lent machine) --------------------------------------------------------------------------------------
class Report:
    """Rows in a CSV as they come, a markdown summary rewritten after each step."""

    def __init__(self, out: Path, device: str, tag: str = "") -> None:
        import torch

        self.card = torch.cuda.get_device_name() if device.startswith("cuda") else (platform.processor() or "cpu")
        stamp = datetime.date.today().isoformat()
        slug = "".join(ch if ch.isalnum() else "-" for ch in self.card).strip("-").lower()[:40] + tag
        out.mkdir(parents=True, exist_ok=True)
        self.csv, self.md = out / f"gpu_{stamp}_{slug}.csv", out / f"gpu_{stamp}_{slug}.md"
        self.rows: list[dict[str, Any]] = []
        self.env = {"date": stamp, "card": self.card, "torch": torch.__version__,
                    "numpy": __import__("numpy").__version__, "python": platform.python_version(),
                    "cpus": os.cpu_count(), "cuda": torch.version.cuda}
        with open(self.csv, "w", newline="") as f:
            csv.DictWriter(f, fieldnames=FIELDS).writeheader()

    def add(self, step: str, **row: Any) -> None:
        row = {"step": step, **{k: (round(v, 6) if isinstance(v, float) else v) for k, v in row.items()}}
        self.rows.append(row)
        with open(self.csv, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore").writerow(row)
        print(json.dumps(row, default=str), flush=True)

    def write_md(self) -> None:
        lines = [f"# GPU check, {self.env['date']}, {self.card}", "",
                 f"torch {self.env['torch']} (CUDA {self.env['cuda']}), numpy {self.env['numpy']}, Python "
                 f"{self.env['python']}, {self.env['cpus']} CPUs. Written by experiments/gpu_check.py; rows in "
                 f"{self.csv.name}.", ""]
        for step, title, cols in SECTIONS:
            rows = [r for r in self.rows if r["step"] == step]
            if not rows:
                continue
            lines += [f"## {title}", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
            lines += ["| " + " | ".join(_cell(r.get(c)) for c in cols) + " |" for r in rows] + [""]
        self.md.write_text("\n".join(lines))


SECTIONS = [
    ("check", "Device reductions: numpy's order and CPU equality", ["model", "file", "value", "note"]),
    ("mainjob", "Main job: device against CPU (same commit)", ["model", "file", "column", "max_abs_diff", "differing",
                                                               "value", "note"]),
    ("ratio", "Evaluate stage (PNGs from disk) / bare forward on the device", [
        "model", "dtype", "batch", "width", "height", "images", "stage_ips", "stage_steady_ips", "bare_ips", "ratio",
        "steady_ratio", "forward_share", "other_share", "write_share", "wait_share", "staging_share", "launch_share",
        "result_share", "stage_peak_gpu_mb", "workers", "note"]),
    ("sources", "Model sources on the device (model=hf, model=onnx)", [
        "model", "dtype", "batch", "width", "height", "images", "stage_ips", "stage_steady_ips", "bare_ips", "ratio",
        "steady_ratio", "forward_share", "other_share", "write_share", "stage_peak_gpu_mb", "value", "note"]),
    ("forward", "Bare forward of the paper's graphs", ["model", "dtype", "batch", "width", "height", "forward_ips",
                                                       "peak_gpu_mb", "note"]),
    ("eta", "Evaluate stage of the paper's graphs, and 1,000 groups x 9 conditions", [
        "model", "dtype", "batch", "width", "height", "images", "stage_ips", "stage_steady_ips", "bare_ips",
        "steady_ratio", "stage_peak_gpu_mb", "value", "note"]),
]


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.3g}" if 0 < abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.3f}".rstrip("0").rstrip(".")
    return str(v).replace("|", "\\|")


def step_check(rep: Report, device: str) -> None:
    """The reductions of one random group on the device and on the CPU, and their float sums against numpy."""
    import numpy as np
    import torch

    from pairedgta.evaluation import reductions, registry
    from pairedgta.models.base import max_and_label, normalised_entropy_

    g = torch.Generator().manual_seed(0)
    n, k, h, w = 9, 19, 256, 512
    probs = (torch.randn(n, k, h, w, generator=g) * 6).softmax(1)
    pseudo = torch.randint(0, k, (h, w), generator=g).to(torch.uint8)
    visible = torch.rand(n, h, w, generator=g) < 0.9

    def reduce(dev: str) -> dict[str, Any]:
        p = probs.to(dev)
        conf, labels = max_and_label(p)
        entropy = normalised_entropy_(p.clone())
        out = registry.group_reductions(labels, conf, entropy, 0, pseudo.to(dev), None, visible.to(dev), 0.5,
                                          None, True)
        return {"labels": labels.cpu(), "conf": conf.cpu(), "entropy": entropy.cpu(),
                **{key: v.cpu() for key, v in out.items()}}

    here, cpu = reduce(device), reduce("cpu")
    counts = [key for key in cpu if key not in ("conf", "entropy", "conf_blocks", "entropy_blocks")]
    equal = [key for key in counts if torch.equal(here[key], cpu[key])]
    rep.add("check", model="random", file="counts", value=f"{len(equal)}/{len(counts)} equal",
            note="labels, xi, agreement, phi, histogram: device vs CPU from the same probabilities")
    rep.add("check", model="random", file="max prob", value=float((here["conf"] - cpu["conf"]).abs().max()),
            note="max |device - CPU|")
    rep.add("check", model="random", file="entropy", value=float((here["entropy"] - cpu["entropy"]).abs().max()),
            note="max |device - CPU| of the per-pixel entropy (its class sum and log run on the device)")
    x = torch.rand(3, 1080, 1920, generator=g) ** 9
    ok = reductions.image_sums(x.to(device)) == [float(np.sum(x[i].numpy(), dtype=np.float64)) for i in range(3)]
    rep.add("check", model="random", file="float sums", value="equal" if ok else "DIFFERENT",
            note=f"device block sums + host order vs np.sum (numpy {np.__version__}), 1920x1080")


def step_mainjob(rep: Report, bundle: Path, device: str, tmp: Path) -> None:
    """The main job on the device against the CPU outputs carried in the bundle."""
    import numpy as np
    import pandas as pd
    from PIL import Image

    main = bundle / "mainjob"
    meta = json.loads((main / "meta.json").read_text())
    start = time.perf_counter()
    summary = run_main_job(tmp / "mainjob", main / "generate", device, "pseudolabel,evaluate")
    rep.add("mainjob", model="all", file="run", value=round(time.perf_counter() - start, 1),
            note=f"seconds, pseudolabel + evaluate of {len(summary['evaluate'])} models on {device}; CPU reference "
                 f"from commit {meta['commit'][:10]}{'+' if '+' in meta['commit'] else ''} on {meta['cpu']}, "
                 f"{meta['date']}")
    ref_labels = sorted((main / "cpu" / "pseudolabel").glob("*.png"))
    diff = total = 0
    for p in ref_labels:
        a = np.asarray(Image.open(p))
        b = np.asarray(Image.open(Path(summary["pseudolabel"]) / "labels" / p.name))
        diff, total = diff + int((a != b).sum()), total + a.size
    rep.add("mainjob", model="pseudolabel", file="labels", differing=diff / max(total, 1),
            note=f"share of pseudo-label pixels that differ ({diff} of {total})")
    for name, path in sorted(summary["evaluate"].items()):
        ref = main / "cpu" / name
        for f in MAIN_FILES:
            a, b = ref / f, Path(path) / f
            if f.endswith(".csv"):
                x, y = pd.read_csv(a), pd.read_csv(b)
                if x.shape != y.shape:
                    rep.add("mainjob", model=name, file=f, note=f"shapes differ: {x.shape} vs {y.shape}")
                    continue
                for col in x.columns:
                    if pd.api.types.is_numeric_dtype(x[col]) and pd.api.types.is_numeric_dtype(y[col]):
                        d = (x[col].astype(float) - y[col].astype(float)).abs()
                        nan = int((x[col].isna() != y[col].isna()).sum())
                        if d.max(skipna=True) > 0 or nan:
                            rep.add("mainjob", model=name, file=f, column=col, max_abs_diff=float(d.max(skipna=True)),
                                    differing=float(((d > 0) | (x[col].isna() != y[col].isna())).mean()),
                                    note=f"{nan} NaN where the other is a number" if nan else None)
                    elif not x[col].equals(y[col]):
                        rep.add("mainjob", model=name, file=f, column=col, note="text differs")
            elif f == "predictions.npz":
                with np.load(a) as za, np.load(b) as zb:
                    keys = [key for key in za.files if key != "group_id"]
                    diff = sum(int((za[key] != zb[key]).sum()) for key in keys)
                    total = sum(za[key].size for key in keys)
                rep.add("mainjob", model=name, file=f, column="labels", differing=diff / max(total, 1),
                        note=f"share of predicted pixels that differ ({diff} of {total})")
        rep.add("mainjob", model=name, file="(all)", note="every other column identical")


def stage(rep: Report, step: str, be: Any, root: Path, name: str, model: str, dtype: str, device: str,
          batch: int, tmp: Path, options: dict[str, Any], workers: str, extra: tuple[str, ...] = ()
          ) -> dict[str, Any] | None:
    from bench_models import model_overrides

    try:
        r = be.measure(root, tmp / f"cache-{step}-{name}-{dtype}", model, workers, batch, "-", device,
                       None if dtype == "fp32" else dtype, full=False, conditions=9,
                       extra=model_overrides(options) + list(extra))
    except Exception as exc:  # noqa: BLE001 - a row that says so, the next measurement goes on
        rep.add(step, model=name, dtype=dtype, batch=batch, note=failed(exc))
        free()
        return None
    rep.add(step, model=name, dtype=dtype, batch=batch, width=r["width"], height=r["height"], groups=r["groups"],
            images=r["images"], stage_ips=r["eval_ips"], stage_steady_ips=r["stage_steady_ips"], bare_ips=r["bare_ips"],
            ratio=r["ratio"], steady_ratio=r["steady_ratio"], forward_share=r["forward_share"],
            other_share=r["other_share"], write_share=r["write_share"], stage_peak_gpu_mb=r.get("stage_peak_gpu_mb"),
            peak_gpu_mb=r.get("bare_peak_gpu_mb"), workers=workers, note=None if model == name else f"as {model}",
            **{f"{k}_share": r.get(f"{k}_share") for k in ("wait", "staging", "launch", "result")})
    return r


def step_sources(rep: Report, be: Any, bundle: Path, root: Path, device: str, tmp: Path, workers: str,
                 tiny: bool) -> None:
    """Issue 57 item 5: a universal HF model through `model=hf` and an ONNX graph through `model=onnx`, each the
    stage against its own bare forward on the same images."""
    from transformers import Mask2FormerImageProcessor

    from bench_models import PAPER
    from pairedgta.models import build_model

    name = "tiny_mask2former" if tiny else "mask2former_swin_s"
    zoo = build_model(name, device="cpu", **({} if tiny else dict(PAPER[name])))
    folder = tmp / "hf-mask2former"
    zoo.module.save_pretrained(folder)  # the random-init graph with Cityscapes' id2label, as save_pretrained writes it
    Mask2FormerImageProcessor(do_resize=False, size_divisor=32, ignore_index=255).save_pretrained(folder)
    del zoo
    free()
    # the pseudo-labels come from a zoo model (a source's model.path does not reach reference_model=hf)
    reference = ("reference_model=demo_ddrnet",)
    stage(rep, "sources", be, root, f"hf:{name}", "hf", "bf16", device, 9, tmp, {"path": str(folder)}, workers,
          reference)
    rep.write_md()
    try:
        import onnxruntime as ort
    except ImportError as exc:
        rep.add("sources", model="onnx:demo_ddrnet", note=failed(exc))
        return
    have = ort.get_available_providers()
    rep.add("sources", model="onnx:demo_ddrnet", value=f"onnxruntime {ort.__version__}",
            note=f"providers: {', '.join(have)}")
    graph = bundle / "demo_ddrnet.onnx"
    if not graph.is_file():
        rep.add("sources", model="onnx:demo_ddrnet", note=f"skipped: no {graph} (run `gpu_check.py prepare`)")
    elif device.startswith("cuda") and "CUDAExecutionProvider" not in have:
        rep.add("sources", model="onnx:demo_ddrnet", note="skipped: this onnxruntime has no CUDA provider "
                "(onnxruntime-gpu is not on the machine, and its wheel is larger than what a call may carry)")
    else:
        stage(rep, "sources", be, root, "onnx:demo_ddrnet", "onnx", "fp32", device, 9, tmp,
              {"path": str(graph), "pad_multiple": 32}, workers, reference)
    rep.write_md()


def failed(exc: BaseException) -> str:
    return f"failed: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"


def free() -> None:
    import gc

    import torch

    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def guarded(rep: Report, step: str, fn: Any, *args: Any) -> None:
    """A step whose failure is a row of the report, not the end of the run."""
    try:
        fn(*args)
    except Exception as exc:  # noqa: BLE001
        import traceback

        traceback.print_exc()
        rep.add(step, model="all", note=failed(exc))
        free()


def dataset(root: Path, groups: int, unique: Path) -> Path:
    """`groups` groups in the released layout, as links to the files of the few rendered ones (decoding a file costs
    the same whichever group it belongs to)."""
    if root.is_dir():
        return root
    rendered = sorted(p for p in unique.rglob("*.png"))
    per = {}
    for p in rendered:
        per.setdefault(p.name.split("_", 1)[0], []).append(p)
    ids = sorted(per)
    for k in range(groups):
        for p in per[ids[k % len(ids)]]:
            (root / p.parent.name).mkdir(parents=True, exist_ok=True)
            os.symlink(p, root / p.parent.name / f"{k}_{p.name.split('_', 1)[1]}")
    return root


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["prepare", "run"])
    ap.add_argument("--bundle", default=str(ROOT / "gpu_bundle"))
    ap.add_argument("--cache", default=None, help="prepare: a cache holding the main job already")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=os.environ.get("OUT") or str(ROOT / "experiments" / "results"))
    ap.add_argument("--budget", type=float, default=480.0, help="seconds; later steps are skipped past it")
    ap.add_argument("--size", default="2048x1024")
    ap.add_argument("--eta-size", default="1920x1080")
    ap.add_argument("--workers", default="auto")
    ap.add_argument("--steps", nargs="+", default=["check", "mainjob", "ratio", "sources", "forward", "eta"])
    ap.add_argument("--tiny", action="store_true", help="tiny models and groups (a CPU rehearsal of the whole run)")
    ap.add_argument("--only", nargs="+", default=None, help="ratio/forward/eta: only these graphs (e.g. ddrnet_23)")
    ap.add_argument("--tag", default="", help="appended to the result files' names (a second run the same day)")
    args = ap.parse_args()
    if args.what == "prepare":
        prepare(Path(args.bundle), Path(args.cache) if args.cache else None)
        return
    t0 = time.perf_counter()
    import bench_evaluate as be
    from bench_models import PAPER, time_forward

    rep = Report(Path(args.out), args.device, args.tag)
    wanted = lambda name: args.only is None or name in args.only  # noqa: E731
    tmp = Path(tempfile.mkdtemp(prefix="gpu-check-"))
    left = lambda: args.budget - (time.perf_counter() - t0)  # noqa: E731
    width, height = (int(v) for v in args.size.split("x"))
    eta_w, eta_h = (int(v) for v in args.eta_size.split("x"))
    groups = (lambda name: 2) if args.tiny else GROUPS.get
    model = (lambda name: TINY[name]) if args.tiny else (lambda name: name)
    options = (lambda name: {}) if args.tiny else (lambda name: dict(PAPER[name]))
    # seconds a unit of each step may take
    cost = {"check": 5, "mainjob": 40, "ratio": 25, "sources": 40, "forward": 12, "eta": 25}

    def skip(step: str, what: str) -> bool:
        if left() < cost[step]:
            rep.add(step, model=what, note=f"skipped: {left():.0f} s of the {args.budget:.0f} s budget left")
            return True
        return False

    if "check" in args.steps and not skip("check", "all"):
        guarded(rep, "check", step_check, rep, args.device)
        rep.write_md()
    if "mainjob" in args.steps and not skip("mainjob", "all"):
        if (Path(args.bundle) / "mainjob" / "meta.json").is_file():
            guarded(rep, "mainjob", step_mainjob, rep, Path(args.bundle), args.device, tmp)
        else:
            rep.add("mainjob", model="all", note=f"skipped: no {args.bundle}/mainjob (run `gpu_check.py prepare`)")
        rep.write_md()
    unique = {}
    for size in {(width, height), (eta_w, eta_h)}:
        unique[size] = tmp / f"unique-{size[0]}x{size[1]}"
        be.make_release_dataset(unique[size], 2, size[0], size[1], conditions=9, jobs=min(18, os.cpu_count() or 1))
    if "ratio" in args.steps:
        for name, dtype in RATIO:
            if not wanted(name) or skip("ratio", name):
                continue
            root = dataset(tmp / f"ds-{width}x{height}-{groups(name)}", groups(name), unique[(width, height)])
            stage(rep, "ratio", be, root, name, model(name), dtype, args.device, 9, tmp, options(name), args.workers)
            rep.write_md()
    if "sources" in args.steps and not skip("sources", "all"):
        root = dataset(tmp / f"ds-{width}x{height}-{groups('mask2former_swin_s')}", groups("mask2former_swin_s"),
                       unique[(width, height)])
        guarded(rep, "sources", step_sources, rep, be, Path(args.bundle), root, args.device, tmp, args.workers,
                args.tiny)
        rep.write_md()
    if "forward" in args.steps:
        from pairedgta.models import build_model

        for name in PAPER:
            if not wanted(name) or skip("forward", name):
                continue
            try:
                seg = build_model(model(name), device=args.device, **options(name))
            except Exception as exc:  # noqa: BLE001
                rep.add("forward", model=name, note=failed(exc))
                continue
            for dtype in ("fp32", "bf16"):
                r = time_forward(seg, 8 if not args.tiny else 2, height, width, dtype, 1, 3 if not args.tiny else 1)
                rep.add("forward", model=name, dtype=dtype, batch=r["batch"], width=width, height=height,
                        forward_ips=r.get("forward_ips"), peak_gpu_mb=r.get("peak_gpu_mb"), note=r.get("error"))
            del seg
            free()
            rep.write_md()
    if "eta" in args.steps:
        seconds: dict[str, float] = {}
        for name in PAPER:
            if not wanted(name) or skip("eta", name):
                continue
            root = dataset(tmp / f"ds-{eta_w}x{eta_h}-{groups(name)}", groups(name), unique[(eta_w, eta_h)])
            r = stage(rep, "eta", be, root, name, model(name), "bf16", args.device, 9, tmp, options(name), args.workers)
            if r is not None:
                seconds[name] = 9000 / r["stage_steady_ips"] + (1000 / r["bare_ips"] if name == "segformer_b5" else 0)
            rep.write_md()
        if len(seconds) == len(PAPER):
            rep.add("eta", model="all eight", dtype="bf16", value=round(sum(seconds.values()) / 60, 1),
                    note="minutes for 1,000 groups x 9 conditions: 9,000 images per model at its steady stage rate, "
                         "plus 1,000 pseudo-labels by segformer_b5 at its bare rate")
        rep.write_md()
    rep.add("done", model="all", value=round(time.perf_counter() - t0, 1), note="seconds")
    rep.write_md()
    shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {rep.csv} and {rep.md}")


if __name__ == "__main__":
    main()
