"""task=detection model=<source> (pairedgta/models/detector_contract.py, layouts.py, label_spaces.py, sources/): the output
layouts decode hand-made outputs as their exporters mean them; one detector in several formats gives the same
detections and the same detection xi; label spaces map to the instance classes (COCO has no rider: NaN with the
reason); bad layouts, boxes and class counts are one line before any stage writes."""
from __future__ import annotations

import json
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from detector_nets import ssdlite, street, tiny_detr_dir, tiny_yolo, zoo_fcos
from pairedgta.models import detector_labels as label_spaces
from pairedgta.models import detector_layouts as layouts
from pairedgta.detection.boxes import INSTANCE_CLASSES
from pairedgta.errors import ConfigError, ModelError
from pairedgta.metrics import detection_xi
from pairedgta.models import build_model, with_defaults
from pairedgta.models.checkpoint import load_checkpoint_strict, resolve_checkpoint_path

ZOO = "pkg://models/weights/demo_det_reference/model.safetensors"


def build(**cfg):
    return build_model(with_defaults({"name": "mine", **cfg}))


# -- layouts ----------------------------------------------------------------------------------------------------
def test_presets_decode_what_their_exporters_mean():
    size = (100, 200)
    # yolov8: (1, 4 + C, N) cxcywh pixels, class scores, no objectness
    y8 = np.zeros((1, 4 + 3, 2), np.float32)
    y8[0, :4, 0] = (50, 40, 20, 10)
    y8[0, 4:, 0] = (0.1, 0.9, 0.2)
    y8[0, :4, 1] = (150, 60, 30, 30)
    y8[0, 4:, 1] = (0.7, 0.1, 0.0)
    (r,) = layouts.decode({"output0": y8}, layouts.PRESETS["yolov8"], size, "m", 3)
    np.testing.assert_allclose(r.boxes, [[40, 35, 60, 45], [135, 45, 165, 75]])
    np.testing.assert_allclose(r.scores, [0.9, 0.7], rtol=1e-6)
    assert r.labels.tolist() == [1, 0]
    # yolov5: (1, N, 5 + C) with objectness: score = obj x class
    y5 = np.swapaxes(y8, 1, 2).copy()
    y5 = np.concatenate([y5[..., :4], np.array([[[0.5], [1.0]]], np.float32), y5[..., 4:]], axis=2)
    (r,) = layouts.decode({"output0": y5}, layouts.PRESETS["yolov5"], size, "m", 3)
    np.testing.assert_allclose(r.scores, [0.7, 0.45], rtol=1e-6)
    assert r.labels.tolist() == [0, 1]
    # detr: softmax logits with the no-object slot last, cxcywh normalised boxes
    logits = np.log(np.array([[[0.1, 0.6, 0.3]]], np.float32))  # 2 classes + no object
    (r,) = layouts.decode({"logits": logits, "pred_boxes": np.array([[[0.5, 0.5, 0.2, 0.4]]], np.float32)},
                          layouts.PRESETS["detr"], size, "m", 2)
    np.testing.assert_allclose(r.boxes, [[80, 30, 120, 70]], rtol=1e-6)
    assert r.labels.tolist() == [1] and r.scores[0] == pytest.approx(0.6)
    # efficientnms: only the first num_dets rows count
    out = {"num_dets": np.array([[1]]), "det_boxes": np.array([[[1, 2, 3, 4], [5, 6, 7, 8]]], np.float32),
           "det_scores": np.array([[0.8, 0.9]], np.float32), "det_classes": np.array([[2, 0]])}
    (r,) = layouts.decode(out, layouts.PRESETS["efficientnms"], size, "m", 3)
    assert r.boxes.tolist() == [[1, 2, 3, 4]] and r.labels.tolist() == [2]
    # torchvision: per-image dicts, background id 0 dropped, ids shifted by one
    d = {"boxes": np.array([[0, 0, 10, 10], [5, 5, 9, 9]], np.float32), "scores": np.array([0.9, 0.8]),
         "labels": np.array([3, 0])}
    (r,) = layouts.decode([d], layouts.PRESETS["torchvision"], size, "m", 90)
    assert r.labels.tolist() == [2] and label_spaces.COCO91[2] == "car"


def test_nms_runs_where_the_graph_has_none():
    y8 = np.zeros((1, 5, 3), np.float32)
    y8[0, :, 0] = (50, 50, 20, 20, 0.9)
    y8[0, :, 1] = (51, 50, 20, 20, 0.8)  # overlaps the first: suppressed
    y8[0, :, 2] = (150, 50, 20, 20, 0.7)
    (r,) = layouts.decode({"output0": y8}, layouts.PRESETS["yolov8"], (100, 200), "m", 1)
    np.testing.assert_allclose(r.scores, [0.9, 0.7], rtol=1e-6)
    parts = layouts.parse_layout({"preset": "yolov8", "nms": True}, "m")
    (r,) = layouts.decode({"output0": y8}, parts, (100, 200), "m", 1)
    assert len(r.scores) == 3 and parts.name == "yolov8+"


def test_layout_and_label_space_errors_are_one_line():
    with pytest.raises(ConfigError, match="model.layout='yolo' is unknown; use one of torchvision, detr"):
        layouts.parse_layout("yolo", "m")
    with pytest.raises(ConfigError, match=r"model.layout.box_format='xyzw'; use one of xyxy, xywh, cxcywh"):
        layouts.parse_layout({"box_format": "xyzw"}, "m")
    with pytest.raises(ConfigError, match="unknown role"):
        layouts.parse_layout({"outputs": {"bbox": "x"}}, "m")
    with pytest.raises(ModelError, match=r"outputs are 'dets', 'labels', but model.layout=efficientnms reads"):
        layouts.check_outputs(layouts.PRESETS["efficientnms"], ["dets", "labels"], "m")
    with pytest.raises(ModelError, match=r"has 12 values per box, model.layout=yolov8 .* needs 4 \+ 80"):
        layouts.decode({"output0": np.zeros((1, 12, 5), np.float32)}, layouts.PRESETS["yolov8"], (10, 10), "m", 80)
    with pytest.raises(ConfigError, match="not a detection label space; use one of coco, coco91, cityscapes"):
        label_spaces.resolve("ade20k", None, "m")


def test_label_spaces_map_onto_the_instance_classes(tmp_path):
    coco = label_spaces.resolve("coco", None, "m")
    assert coco.blind == ("rider",) and coco.num_classes == 80
    assert [INSTANCE_CLASSES[t] for t in coco.target[:8] if t >= 0] == ["person", "bicycle", "car", "motorcycle",
                                                                        "bus", "train", "truck"]
    c91 = label_spaces.resolve("coco91", None, "m")
    assert c91.num_classes == 90 and c91.source_classes[2] == "car" and c91.source_classes[11] == "N/A"
    vistas = label_spaces.resolve("mapillary_vistas_v1.2", None, "m")
    assert "rider" not in vistas.blind and "person" not in vistas.blind
    tsv = tmp_path / "mine.tsv"
    tsv.write_text("pedestrian\tperson\ncyclist\trider\nvan\tcar\ntree\t-\n")
    mine = label_spaces.resolve(str(tsv), None, "m")
    assert mine.target == (0, 1, 2, -1) and set(mine.blind) == {"truck", "bus", "train", "motorcycle", "bicycle"}
    own = label_spaces.resolve(None, {0: "N/A", 1: "person", 2: "car"}, "m")
    assert own.target == (-1, 0, 2)
    with pytest.raises(ConfigError, match="none of the checkpoint's 2 class names"):
        label_spaces.resolve(None, {0: "cat", 1: "dog"}, "m")


# -- the same detector in every format --------------------------------------------------------------------------
def _export(module, path: Path, example, names, axes=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, example, str(path), opset_version=17, input_names=["image"], output_names=names,
                          dynamo=False, dynamic_axes=axes)
    return path


def _xi(dets, ref):
    counts = sum(detection_xi.image_counts(r.boxes, r.labels, d.boxes, d.scores, d.labels, 0.5, 0.5, 8)
                 for d, r in zip(dets, ref))
    return counts[1].sum() / max(counts[0].sum(), 1)


def _same(a, b, size, threshold: float = 0.3) -> None:
    """The confident detections agree: as many, and each box of `a` has one of `b` of its class within 1e-3 of the
    image size (boxes whose scores tie may come in another order)."""
    tol = 1e-3 * max(size)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        xa, ya = x.above(threshold), y.above(threshold)
        assert len(xa.boxes) == len(ya.boxes)
        used = np.zeros(len(ya.boxes), bool)
        for box, label in zip(xa.boxes, xa.labels):
            diff = np.abs(ya.boxes - box).max(axis=1) if len(ya.boxes) else np.zeros(0)
            ok = np.flatnonzero((diff <= tol) & (ya.labels == label) & ~used)
            assert len(ok), f"no match for {box} ({label})"
            used[ok[0]] = True


@pytest.mark.slow
def test_one_detector_in_every_format_gives_the_same_boxes_and_xi(tmp_path):
    images = np.stack([street(0), street(1)])
    size = images.shape[1:3]
    reference = build_model("demo_det_reference").detect(images)
    # a trained torchvision-style detector: as the user's factory with its weights, and as torchvision's ONNX export
    fcos = zoo_fcos()
    load_checkpoint_strict(fcos, resolve_checkpoint_path(ZOO))
    onnx_path = _export(fcos, tmp_path / "fcos.onnx", ([torch.rand(3, *size)],), ["boxes", "scores", "labels"],
                        {"image": {1: "h", 2: "w"}})
    by_python = build(family="det_python", target="detector_nets:zoo_fcos", checkpoint_path=ZOO,
                      labels="cityscapes", score_threshold=0.55).detect(images)
    by_onnx = build(family="det_onnx", path=str(onnx_path), labels="cityscapes", score_threshold=0.55).detect(images)
    _same(reference, by_python, size)
    _same(by_python, by_onnx, size)
    assert sum(len(d.boxes) for d in by_python) > 10
    # a YOLOv8-style head: the factory, its torch.export program and its ONNX export
    yolo = tiny_yolo()
    x = torch.rand(2, 3, *size)
    program = torch.export.export(yolo, (x,), dynamic_shapes=({0: torch.export.Dim("batch", max=64)},))
    torch.export.save(program, tmp_path / "yolo.pt2")
    _export(yolo, tmp_path / "yolo.onnx", (x,), ["output0"], {"image": {0: "batch"}})
    keys = {"labels": "cityscapes", "score_threshold": 0.5}
    formats = [build(family="det_python", target="detector_nets:tiny_yolo", layout="yolov8", **keys),
               build(family="det_export", path=str(tmp_path / "yolo.pt2"),
                     layout={"preset": "yolov8", "outputs": {"combined": "output0"}}, **keys),
               build(family="det_onnx", path=str(tmp_path / "yolo.onnx"), layout="yolov8", **keys)]
    found = [f.detect(images) for f in formats]
    assert sum(len(d.boxes) for d in found[0]) > 10
    for other in found[1:]:
        _same(found[0], other, size)
    xis = [_xi(f, found[0]) for f in found] + [_xi(by_python, reference), _xi(by_onnx, reference)]
    assert max(xis[:3]) - min(xis[:3]) <= 1e-3 and abs(xis[3] - xis[4]) <= 1e-3


@pytest.mark.slow
def test_torchvision_builder_loads_released_style_checkpoints(tmp_path):
    """torchvision's released checkpoints hold FrozenBatchNorm2d (no num_batches_tracked); one trained without them
    holds BatchNorm2d: both load strictly, and give what the same network built by the user's factory gives."""
    torch.manual_seed(0)
    net = ssdlite().eval()
    state = net.state_dict()
    save_file({k: v.contiguous() for k, v in state.items()}, tmp_path / "bn.safetensors")
    save_file({k: v.contiguous() for k, v in state.items() if not k.endswith("num_batches_tracked")},
              tmp_path / "frozen.safetensors")
    image = street(2, (160, 320))[None]
    expected = build(family="det_python", target="detector_nets:ssdlite", checkpoint_path=str(tmp_path / "bn.safetensors"),
                     labels="coco91", score_threshold=0.0).detect(image)
    for file in ("bn", "frozen"):
        det = build(family="det_torchvision", arch="ssdlite320_mobilenet_v3_large",
                    checkpoint_path=str(tmp_path / f"{file}.safetensors"), score_threshold=0.0)
        assert det.labels.space == "coco91" and det.blind == ("rider",)
        _same(expected, det.detect(image), (160, 320), threshold=0.0)
    with pytest.raises(ConfigError, match="arch='yolo11' is not a torchvision detection builder"):
        build(family="det_torchvision", arch="yolo11", checkpoint_path=str(tmp_path / "bn.safetensors"))


# -- bad input ------------------------------------------------------------------------------------------------
class Payload:
    def __reduce__(self):
        return (Path.touch, (Path(__file__).parent / "PWNED_DETECTOR",))


def test_bad_detectors_are_one_line_before_anything_runs(tmp_path):
    yolo = tiny_yolo()
    x = torch.rand(1, 3, 64, 128)
    onnx_path = _export(yolo, tmp_path / "y.onnx", (x,), ["output0"], {"image": {0: "b"}})
    with pytest.raises(ModelError, match=r"outputs are 'output0', but model.layout=detr reads"):
        build(family="det_onnx", path=str(onnx_path), layout="detr", labels="cityscapes")
    with pytest.raises(ModelError, match=r"has 12 values per box, model.layout=yolov8 with the label space needs 4 \+ 80"):
        build(family="det_onnx", path=str(onnx_path), layout="yolov8", labels="coco")
    with pytest.raises(ModelError, match="boxes lie far outside the 512x256 image.*normalized"):
        build(family="det_onnx", path=str(onnx_path), layout={"preset": "yolov8", "normalized": True},
              labels="cityscapes", score_threshold=0.0)
    with pytest.raises(ConfigError, match="model.layout is not set"):
        build(family="det_onnx", path=str(onnx_path), labels="cityscapes")
    bad = tmp_path / "evil.pth"
    bad.write_bytes(pickle.dumps({"w": Payload()}))
    with pytest.raises(ModelError, match="cannot read checkpoint"):
        build(family="det_python", target="detector_nets:tiny_yolo", layout="yolov8", labels="cityscapes",
              checkpoint_path=str(bad))
    assert not (Path(__file__).parent / "PWNED_DETECTOR").exists()

    class NaNNet(torch.nn.Module):
        def forward(self, x):
            out = tiny_yolo()(x)
            return out * float("nan")

    import detector_nets
    detector_nets.nan_net = lambda: NaNNet()
    with pytest.raises(ModelError, match="non-finite boxes or scores"):
        build(family="det_python", target="detector_nets:nan_net", layout="yolov8", labels="cityscapes")


@pytest.mark.slow
def test_a_detector_source_through_the_cli_with_coco_classes(tmp_path):
    """task=detection model=onnx: the run builds it as a detector, ranks it against the reference's boxes, and a
    class COCO lacks (rider) is NaN with its reason in every table."""
    from pairedgta.testing.cli import base_overrides, run_cli

    yolo = tiny_yolo(classes=80)
    onnx_path = _export(yolo, tmp_path / "coco.onnx", (torch.rand(1, 3, 48, 96),), ["output0"], {"image": {0: "b"}})
    args = base_overrides(tmp_path, store=False) + [
        "task=detection", "renderer=synthetic", "region=synthetic_street", "renderer.width=96", "renderer.height=48",
        "generate.num_scenes=2", "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]", "model=onnx",
        f"model.path={onnx_path}", "model.layout=yolov8", "model.labels=coco", "reference_model=tiny_fcos",
        "metric.bootstrap.resamples=20", "plot.figures=[det_xi]", "plot.formats=[png]", "plot.dpi=40",
        "tracking.enabled=false", "threads=1"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    (entry,) = [p for p in (tmp_path / "cache" / "evaluate").iterdir() if not p.name.startswith(".")]
    import pandas as pd

    xi = pd.read_csv(entry / "detection_xi.csv")
    rider = xi[xi.class_name == "rider"]
    assert rider.xi.isna().all() and rider.reason.str.contains("has no rider").all()
    summary = json.loads((entry / "summary.json").read_text())
    assert summary["model"] == "coco" and summary["score_threshold"] == 0.5
    # the set-up check ran on the clean images (a random head: nothing does better, and AP50 ~ 0 is the domain line)
    assert "configured" in summary["setup_tried"] and "model.channels=bgr" in summary["setup_tried"]
    line = summary["setup_line"]
    assert line is None or "clean GT AP50" in line and line in proc.stderr + proc.stdout
    manifest = json.loads((entry / "manifest.json").read_text())
    assert manifest["config"]["model"]["family"] == "det_onnx"
    # the same file as a segmentation model is the other task's: one line, nothing written
    seg = run_cli(base_overrides(tmp_path / "seg", store=False) + [
        "renderer=synthetic", "region=synthetic_street", "model=onnx", f"model.path={onnx_path}",
        "model.layout=yolov8", "tracking.enabled=false"], tmp_path)
    errors = [line for line in seg.stderr.splitlines() if line.startswith("error:")]
    assert seg.returncode == 2 and len(errors) == 1 and "task=detection" in errors[0], seg.stderr[-2000:]
    assert not (tmp_path / "seg" / "cache" / "generate").exists()


# -- transformers ---------------------------------------------------------------------------------------------
def test_a_transformers_detector_with_its_processor_and_class_names(tmp_path):
    from transformers import DetrForObjectDetection, DetrImageProcessor

    folder = tiny_detr_dir(tmp_path / "detr", {0: "person", 1: "car", 2: "dog"})
    det = build(family="det_hf", path=str(folder), score_threshold=0.0)
    assert det.labels.target == (0, 2, -1) and "rider" in det.blind and det.contract.resize == 96
    image = street(4, (96, 192))
    (got,) = det.detect(image[None])
    # by hand: the processor's own preprocessing and decoding of the same model
    model, proc = DetrForObjectDetection.from_pretrained(folder).eval(), DetrImageProcessor.from_pretrained(folder)
    with torch.no_grad():
        out = model(**proc(images=image, return_tensors="pt"))
    (ref,) = proc.post_process_object_detection(out, threshold=0.0, target_sizes=[(96, 192)])
    keep = ref["labels"].numpy() != 2  # the dog is no instance class
    want = ref["boxes"].numpy()[keep]
    assert len(got.boxes) == keep.sum() > 0
    order = np.argsort(-ref["scores"].numpy()[keep], kind="stable")
    np.testing.assert_allclose(got.boxes, want[order], atol=1e-3 * 192)
    np.testing.assert_allclose(got.scores, ref["scores"].numpy()[keep][order], atol=1e-4)
    # a segmentation checkpoint is the other task's model: one line
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    SegformerForSemanticSegmentation(SegformerConfig(num_labels=19, hidden_sizes=[8, 8, 8, 8], depths=[1, 1, 1, 1],
                                                     decoder_hidden_size=8, num_attention_heads=[1, 1, 1, 1])
                                     ).save_pretrained(tmp_path / "seg")
    with pytest.raises(ModelError, match="'segformer' model, which AutoModelForObjectDetection does not load.*"
                                         "task=segmentation"):
        build(family="det_hf", path=str(tmp_path / "seg"))


@pytest.mark.slow
def test_a_detector_placed_against_the_zoo_through_model_report(tmp_path):
    """+experiment=model_report task=detection model=python: the page, its markdown and tables; the subject's AP rank
    is the one its and the population's summaries give."""
    import pandas as pd

    from pairedgta.testing.cli import base_overrides, run_cli

    args = base_overrides(tmp_path, store=False) + [
        "+experiment=model_report", "task=detection", "model=python", "model.target=detector_nets:tiny_yolo",
        "model.layout=yolov8", "model.labels=cityscapes", "report.population=[tiny_fcos,tiny_retinanet]",
        "reference_model=tiny_fasterrcnn", "renderer=synthetic", "region=synthetic_street", "renderer.width=128",
        "renderer.height=64", "generate.num_scenes=2", "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY]",
        "metric.bootstrap.resamples=20", "plot.formats=[png]", "plot.dpi=40", "tracking.enabled=false", "threads=1"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    (plot,) = [p for p in (tmp_path / "cache" / "plot").iterdir() if not p.name.startswith(".")]
    names = {p.name for p in plot.iterdir()}
    assert {"det_model_report.png", "det_model_report.md", "det_model_report.csv", "det_model_report_tracking.csv",
            "det_model_report_objects.csv"} <= names
    md = (plot / "det_model_report.md").read_text()
    assert md.startswith("# Detector report: tiny_yolo") and "tiny_fcos, tiny_retinanet" in md
    rows = pd.read_csv(plot / "det_model_report.csv")
    summaries = {}
    for entry in (tmp_path / "cache" / "evaluate").iterdir():
        if not entry.name.startswith("."):
            s = json.loads((entry / "summary.json").read_text())
            summaries[s["model"]] = s
    assert set(summaries) == {"tiny_yolo", "tiny_fcos", "tiny_retinanet"}
    ap = {m: s["gt_ap"]["Night-EXTRASUNNY"] for m, s in summaries.items()}
    night = rows[(rows.condition == "Night-EXTRASUNNY") & (rows.measure == "gt_ap")].iloc[0]
    assert night.subject == pytest.approx(ap["tiny_yolo"])
    assert night["rank"] == 1 + sum(ap[m] > ap["tiny_yolo"] + 1e-12 for m in ("tiny_fcos", "tiny_retinanet"))


# -- the set-up check -------------------------------------------------------------------------------------------
def red_block_dataset(tmp_path: Path, n: int = 4):
    """n clean images with one red car each, their COCO ground truth, as the detection stages see them."""
    from PIL import Image

    from pairedgta.conditions import Condition, ConditionGrid
    from pairedgta.datasets.base import Group, PairedDataset
    from pairedgta.detection.boxes import coco_categories

    rng = np.random.default_rng(0)
    groups, images, annotations = [], [], []
    for i in range(n):
        img = np.full((64, 128, 3), 110, np.uint8)
        x, y = int(rng.integers(5, 80)), int(rng.integers(5, 30))
        img[y:y + 20, x:x + 30] = (240, 10, 10)
        path = tmp_path / f"g{i}.png"
        Image.fromarray(img).save(path)
        groups.append(Group(f"g{i}", {"Day-EXTRASUNNY": path}, {}))
        images.append({"id": i + 1, "width": 128, "height": 64, "file_name": path.name})
        annotations.append({"id": i + 1, "image_id": i + 1, "category_id": 3, "bbox": [x, y, 30, 20], "area": 600,
                            "iscrowd": 0})
    grid = ConditionGrid((Condition(name="Day-EXTRASUNNY", time="Day", weather="EXTRASUNNY"),), "Day-EXTRASUNNY")
    dataset = PairedDataset("red", tmp_path, "Day-EXTRASUNNY", grid.names, groups, 0, grid=grid)
    return dataset, {"images": images, "annotations": annotations, "categories": coco_categories()}


def test_the_set_up_check_names_what_a_detector_was_trained_with(tmp_path):
    from pairedgta.detection import setup_check

    dataset, coco = red_block_dataset(tmp_path)
    rgb = build(family="det_python", target="detector_nets:red_car_bgr", labels="coco91")
    found = setup_check.run(rgb, dataset, coco, "Day-EXTRASUNNY", "the test images")
    assert found["setup_clean_ap50"] == pytest.approx(0.0)
    assert found["setup_better"]["setup"] == "model.channels=bgr" and found["setup_better"]["clean_ap50"] == 1.0
    assert found["setup_line"].startswith("mine: clean GT AP50 0.00 on the test images (4 labelled clean images); "
                                          "with model.channels=bgr it would be 1.00")
    bgr = build(family="det_python", target="detector_nets:red_car_bgr", labels="coco91", channels="bgr")
    right = setup_check.run(bgr, dataset, coco, "Day-EXTRASUNNY", "the test images")
    assert right["setup_clean_ap50"] == 1.0 and right["setup_better"] is None and right["setup_line"] is None
    # a layout read with the wrong box format: the format it gives is named
    xyxy = build(family="det_python", target="detector_nets:red_car_center", labels="cityscapes",
                 layout={"preset": "yolov8", "box_format": "xyxy"})
    found = setup_check.run(xyxy, dataset, coco, "Day-EXTRASUNNY", "the test images")
    assert found["setup_better"]["setup"] == "model.layout.box_format=cxcywh"
    assert found["setup_tried"]["configured"] < 0.5
