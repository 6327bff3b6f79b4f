"""Throughput of the detector sources (task=detection model=<source>) against the same network run natively in torch.
Not a test; `python experiments/bench_models.py --detector-sources` runs it.

Networks, on the same street images (256x512 by default):
- the zoo's reference FCOS (trained weights: real boxes to decode) as `model=python` (its factory, weights as
  checkpoint_path) and `model=onnx` (torchvision's ONNX export); native: the module on a list of images, boxes
  mapped to the instance classes and sorted by score as the contract does;
- a YOLOv8-style head (tests/detector_nets.py) as `model=python`, `model=export` (.pt2) and `model=onnx`, all with
  model.layout=yolov8; native: the head, cxcywh -> xyxy and torchvision's batched_nms written out by hand;
- torchvision's SSDlite as `model=torchvision` and `model=python`; native: the module on a list of images;
- a small DETR (random weights, ResNet backbone) as `model=hf`; native: the model and its processor's
  post_process_object_detection.
Both sides start from the same uint8 batch: the native callables convert it to a 0-1 float tensor inside their timing,
as any caller must (the sources do it in `detect`). Timings interleave the variants round by round; it prints the
median per image, the ratio source / native (target <= 1.10 on the CPU; ONNX may be faster), the source's cost
beyond the native in ms an image, and the spread of the per-round ratios."""
from __future__ import annotations

import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from pairedgta.models import build_model, with_defaults  # noqa: E402

ZOO = "pkg://models/weights/demo_det_reference/model.safetensors"


def _onnx(module: Any, path: Path, example: Any, names: list[str], axes: dict) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, example, str(path), opset_version=17, input_names=["image"], output_names=names,
                          dynamo=False, dynamic_axes=axes)
    return str(path)


def _build(batch: int, **cfg: Any) -> Any:
    return build_model(with_defaults({"name": cfg.get("family", "m"), "batch_size": batch, **cfg}))


def variants(root: Path, images: np.ndarray, batch: int) -> list[tuple[str, str, Callable, Any]]:
    """(network, source, native callable on the uint8 batch, detector)."""
    from torchvision.ops import batched_nms

    import detector_nets as dn
    from pairedgta.models.detector_labels import COCO91, from_names
    from pairedgta.models.checkpoint import load_checkpoint_strict, resolve_checkpoint_path

    h, w = images.shape[1:3]
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    out = []
    fcos = dn.zoo_fcos()
    load_checkpoint_strict(fcos, resolve_checkpoint_path(ZOO))
    onnx_fcos = _onnx(fcos, root / "fcos.onnx", ([x[0]],), ["boxes", "scores", "labels"], {"image": {1: "h", 2: "w"}})

    def fcos_native(batch_images: torch.Tensor) -> list:
        res = fcos(list(batch_images))
        return [(r["boxes"].numpy(), r["scores"].numpy(), r["labels"].numpy() - 1) for r in res]

    keys = {"labels": "cityscapes", "score_threshold": 0.55}
    out += [("zoo fcos", "python", fcos_native, _build(batch, family="det_python", target="detector_nets:zoo_fcos",
                                                       checkpoint_path=ZOO, **keys)),
            ("zoo fcos", "onnx", fcos_native, _build(batch, family="det_onnx", path=onnx_fcos, **keys))]
    yolo = dn.tiny_yolo()
    program = torch.export.export(yolo, (x[:2],), dynamic_shapes=({0: torch.export.Dim("batch", max=64)},))
    torch.export.save(program, root / "yolo.pt2")
    onnx_yolo = _onnx(yolo, root / "yolo.onnx", (x[:2],), ["output0"], {"image": {0: "batch"}})

    def yolo_native(batch_images: torch.Tensor) -> list:
        res = []
        for y in yolo(batch_images).transpose(1, 2):
            scores, labels = y[:, 4:].max(1)
            keep = scores > 1e-4
            b = y[keep, :4]
            boxes = torch.cat([b[:, :2] - b[:, 2:] / 2, b[:, :2] + b[:, 2:] / 2], 1)
            kept = batched_nms(boxes, scores[keep], labels[keep], 0.5)[:100]
            res.append((boxes[kept].numpy(), scores[keep][kept].numpy(), labels[keep][kept].numpy()))
        return res

    keys = {"labels": "cityscapes", "layout": "yolov8"}
    out += [("yolo head", "python", yolo_native, _build(batch, family="det_python", target="detector_nets:tiny_yolo",
                                                        **keys)),
            ("yolo head", "export", yolo_native, _build(batch, family="det_export", path=str(root / "yolo.pt2"),
                                                        **{**keys, "layout": {"preset": "yolov8",
                                                                              "outputs": {"combined": "output0"}}})),
            ("yolo head", "onnx", yolo_native, _build(batch, family="det_onnx", path=onnx_yolo, **keys))]
    from safetensors.torch import save_file

    torch.manual_seed(0)
    ssd = dn.ssdlite().eval()
    save_file({k: v.contiguous() for k, v in ssd.state_dict().items()}, root / "ssd.safetensors")
    coco91 = np.asarray(from_names("coco91", COCO91).target)

    def ssd_native(batch_images: torch.Tensor) -> list:
        return [(r["boxes"].numpy(), r["scores"].numpy(), coco91[r["labels"].numpy() - 1]) for r in ssd(list(batch_images))]

    out += [("ssdlite", "torchvision", ssd_native, _build(batch, family="det_torchvision",
                                                          arch="ssdlite320_mobilenet_v3_large",
                                                          checkpoint_path=str(root / "ssd.safetensors"))),
            ("ssdlite", "python", ssd_native, _build(batch, family="det_python", target="detector_nets:ssdlite",
                                                     checkpoint_path=str(root / "ssd.safetensors"), labels="coco91"))]
    from detector_nets import tiny_detr_dir
    from transformers import DetrForObjectDetection, DetrImageProcessor

    folder = tiny_detr_dir(root / "detr", {0: "person", 1: "car", 2: "dog"})
    detr, proc = DetrForObjectDetection.from_pretrained(folder).eval(), DetrImageProcessor.from_pretrained(folder)
    hf_det = _build(batch, family="det_hf", path=str(folder))
    size = hf_det.contract.resize
    mean = torch.tensor(proc.image_mean).view(1, 3, 1, 1)
    std = torch.tensor(proc.image_std).view(1, 3, 1, 1)

    def detr_native(batch_images: torch.Tensor) -> list:
        s = size / min(h, w)
        y = torch.nn.functional.interpolate(batch_images, size=(round(h * s), round(w * s)), mode="bilinear",
                                            align_corners=False, antialias=True)
        res = proc.post_process_object_detection(detr(pixel_values=(y - mean) / std), threshold=0.0,
                                                 target_sizes=[(h, w)] * len(y))
        return [(r["boxes"].numpy(), r["scores"].numpy(), r["labels"].numpy()) for r in res]

    out.append(("detr", "hf", detr_native, hf_det))
    return out


def bench(batch: int = 4, height: int = 256, width: int = 512, rounds: int = 7) -> None:
    from detector_nets import street

    images = np.stack([street(i, (height, width)) for i in range(batch)])
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    with tempfile.TemporaryDirectory() as tmp:
        runs = variants(Path(tmp), images, batch)
        times: dict[tuple[str, str], list[float]] = {}
        natives: dict[str, list[float]] = {}
        with torch.inference_mode():
            for net, source, native, det in runs:  # warm-up, and the same boxes
                got, want = det.detect(images), native(x)
                n = [len(g.boxes) for g in got]
                print(f"{net:<12}{source:<13} boxes per image {n} (native {[len(wb[0]) for wb in want]})")
            for _ in range(rounds):
                done = set()
                for net, source, native, det in runs:
                    if net not in done:
                        start = time.perf_counter()
                        native(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0)
                        natives.setdefault(net, []).append(time.perf_counter() - start)
                        done.add(net)
                    start = time.perf_counter()
                    det.detect(images)
                    times.setdefault((net, source), []).append(time.perf_counter() - start)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, batch {batch} of {height}x{width}, "
          f"{rounds} interleaved rounds")
    print(f"{'network':<12}{'source':<13}{'native ms/img':>14}{'source ms/img':>14}{'ratio':>8}{'+ms/img':>9}"
          f"{'per-round range':>18}")
    for (net, source), ts in times.items():
        per_round = [t / n for t, n in zip(ts, natives[net])]
        native_ms, source_ms = (statistics.median(v) / batch * 1e3 for v in (natives[net], ts))
        print(f"{net:<12}{source:<13}{native_ms:>14.1f}{source_ms:>14.1f}{source_ms / native_ms:>8.3f}"
              f"{source_ms - native_ms:>9.1f}{f'{min(per_round):.3f}-{max(per_round):.3f}':>18}")


if __name__ == "__main__":
    bench()
