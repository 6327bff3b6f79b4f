"""Same numbers across formats, on the main job's images (issue 56, item 5). Not a test: tests/test_same_numbers_
across_formats.py checks the same on the synthetic backend's images, within the suite.

Two trained zoo members, each in every format that can hold it, against the zoo model itself:
- demo_segformer (a transformers folder): `model=hf` on the same folder, `model=python` (a factory below building
  SegFormer from the folder's config, the weights as `checkpoint_path`), `model=onnx` and `model=export` of its graph;
- demo_ddrnet (an in-project network): `model=python` (the project's DDRNet graph from a factory below), `model=onnx`
  and `model=export`.
Per format: the share of pixels whose label equals the zoo model's on every image of the main job (8 scenes x 9
conditions, 512x256), the largest probability difference; then the whole pipeline for each ONNX graph (its xi per
condition and class against demo_segformer's pseudo-labels) against the zoo model's xi.csv: within 1e-3?

    python experiments/check_formats.py [--cache outputs/cache] [--out experiments/results/formats.md]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # model.target=check_formats:<factory>

from pairedgta.models import build_model, model_config  # noqa: E402
from pairedgta.models.hf_common import PACKAGE_DIR  # noqa: E402

SEGFORMER = PACKAGE_DIR / "models" / "weights" / "demo_segformer"
DDRNET_KEYS = ("layers", "planes", "spp_planes", "head_planes")


def segformer_net():
    """A user's own code building demo_segformer's graph from its config.json (weights: checkpoint_path)."""
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    return SegformerForSemanticSegmentation(SegformerConfig.from_pretrained(str(SEGFORMER)))


def ddrnet_net():
    """The project's DDRNet graph at demo_ddrnet's widths, as a user's factory would build it."""
    from pairedgta.models.ddrnet import architecture

    cfg = model_config("demo_ddrnet")
    return architecture("demo_ddrnet", False, **{k: cfg[k] for k in DDRNET_KEYS})


class Logits(torch.nn.Module):
    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(pixel_values=x).logits


def formats(tmp: Path) -> dict[str, dict[str, dict]]:
    """zoo member -> format -> model config."""
    example = torch.rand(2, 3, 256, 512)
    seg_zoo = build_model("demo_segformer")
    seg_logits = Logits(seg_zoo.module).eval()
    ddr_zoo = build_model("demo_ddrnet")
    ddr = ddr_zoo.module.eval()
    from safetensors.torch import save_file

    save_file({k: v.contiguous() for k, v in seg_zoo.module.state_dict().items()}, str(tmp / "segformer.safetensors"))
    processor = json.loads((SEGFORMER / "preprocessor_config.json").read_text())
    contract = {"mean": processor["image_mean"], "std": processor["image_std"]}
    out: dict[str, dict[str, dict]] = {"demo_segformer": {}, "demo_ddrnet": {}}
    for name, module, step, extra in (("demo_segformer", seg_logits, 32, contract),
                                       ("demo_ddrnet", ddr, 32, {"pad_multiple": 32})):
        dims = {0: torch.export.Dim("batch"), 2: step * torch.export.Dim("h"), 3: step * torch.export.Dim("w")}
        torch.export.save(torch.export.export(module, (example,), dynamic_shapes={"x": dims}), str(tmp / f"{name}.pt2"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(module, (example,), str(tmp / f"{name}.onnx"), dynamo=False, input_names=["image"],
                              output_names=["scores"], dynamic_axes={"image": {0: "b", 2: "h", 3: "w"}})
        out[name]["export"] = {"family": "export", "path": str(tmp / f"{name}.pt2"), **extra}
        out[name]["onnx"] = {"family": "onnx", "path": str(tmp / f"{name}.onnx"), **extra}
    out["demo_segformer"]["hf"] = {"family": "hf", "path": str(SEGFORMER)}
    out["demo_segformer"]["python"] = {"family": "python", "target": "check_formats:segformer_net",
                                       "checkpoint_path": str(tmp / "segformer.safetensors"), **contract}
    out["demo_ddrnet"]["python"] = {"family": "python", "target": "check_formats:ddrnet_net",
                                    "checkpoint_path": model_config("demo_ddrnet")["checkpoint_path"], "pad_multiple": 32}
    return out


def main_job(cache: Path, *extra: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "pairedgta", f"cache_dir={cache}", "tracking.enabled=false", *extra]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**__import__("os").environ,
                                                                               "PYTHONPATH": str(Path(__file__).parent)})


def entry(cache: Path, model: str) -> Path:
    found = [p for p in (cache / "evaluate").iterdir() if (p / "manifest.json").is_file()
             and json.loads((p / "manifest.json").read_text())["config"]["model"]["name"] == model]
    return max(found, key=lambda p: p.stat().st_mtime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default=str(ROOT / "outputs" / "cache"))
    parser.add_argument("--out", default=str(ROOT / "experiments" / "results" / "formats.md"))
    args = parser.parse_args()
    cache = Path(args.cache)
    r = main_job(cache, "plot.figures=[]", "stages=[generate,pseudolabel,evaluate]")  # the main job's scenes
    if r.returncode:
        sys.exit(r.stderr)
    images_dir = next(p for p in (cache / "generate").iterdir() if (p / "manifest.json").is_file()
                      and (p / "scenes").is_dir() and json.loads((p / "manifest.json").read_text())["config"]
                      .get("renderer", {}).get("backend") == "blender")
    from PIL import Image

    files = sorted(f for f in (images_dir / "scenes").glob("*/*.png") if "_" not in f.stem)  # <condition>.png
    images = np.stack([np.asarray(Image.open(f).convert("RGB")) for f in files])
    rows, xi_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for zoo, variants in formats(tmp).items():
            reference = build_model(zoo)
            want = reference.predict_proba(images)
            want_labels = want.argmax(1)
            for fmt, cfg in variants.items():
                seg = build_model({"name": f"{zoo}_{fmt}", **cfg})
                got = seg.predict_proba(images)
                rows.append({"model": zoo, "format": fmt, "images": len(images),
                             "label agreement": float((got.argmax(1) == want_labels).double().mean()),
                             "max |p - p_zoo|": float((got - want).abs().max())})
                print(rows[-1], flush=True)
            cfg = variants["onnx"]
            keys = [f"model.{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in cfg.items() if k != "family"]
            r = main_job(cache, "model=onnx", f"model.name={zoo}_onnx", *keys, "stages=[generate,pseudolabel,evaluate]")
            if r.returncode:
                sys.exit(r.stderr)
            a = pd.read_csv(entry(cache, zoo) / "xi.csv")
            b = pd.read_csv(entry(cache, f"{zoo}_onnx") / "xi.csv")
            diff = (a["xi"] - b["xi"]).abs()
            xi_rows.append({"model": zoo, "rows": len(a), "max |xi_onnx - xi_zoo|": float(diff.max()),
                            "mean xi (zoo)": float(a.loc[a["class_name"] == "mean", "xi"].mean())})
            print(xi_rows[-1], flush=True)
    lines = ["# Same numbers across formats, on the main job's images", "",
             f"`python experiments/check_formats.py` ({len(images)} images of the main job, 512x256; torch "
             f"{torch.__version__}).", "", "| model | format | label agreement with the zoo model | max abs probability "
             "difference |", "|---|---|---:|---:|"]
    lines += [f"| {r['model']} | {r['format']} | {r['label agreement']:.7f} | {r['max |p - p_zoo|']:.1e} |" for r in rows]
    lines += ["", "| model | xi rows (condition x class x reference) | max abs xi difference, ONNX vs the zoo model |",
              "|---|---:|---:|"]
    lines += [f"| {r['model']} | {r['rows']} | {r['max |xi_onnx - xi_zoo|']:.1e} |" for r in xi_rows]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
