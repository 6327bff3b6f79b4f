"""The set-up check's trial of alternatives for every source model (pairedgta/evaluation/alternatives.py and
setup_check.py) and the bad-input lines around it: a network "trained" on BGR (its weights built by hand: the
nearest base colour of the synthetic street, compared in B, G, R order) run under the default RGB contract is named
in one line with `model.channels=bgr` although its clean mIoU is above the 0.10 line, and the same network set up
right says nothing; the trial prints nothing about the label spaces it tries; a 150-class checkpoint's error shows
the Cityscapes names; `model.labels=ade20k` on 19 outputs and a `.pt2` as `model.checkpoint_path` name their real
cause."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ModelError
from pairedgta.evaluation import alternatives, setup_check
from pairedgta.models import build_model
from pairedgta.models.contract import ContractSegmenter, Network, make_contract
from pairedgta.models.labels import resolve_labels
from pairedgta.models.runtime import IMAGENET_MEAN, IMAGENET_STD, RuntimeOptions

# the synthetic renderer's base colours (pairedgta/render/synthetic.py; the sky: its day gradient's horizon), RGB
COLOURS = {"road": (90, 88, 92), "sidewalk": (170, 160, 150), "building": (150, 120, 100), "pole": (110, 110, 115),
           "vegetation": (60, 110, 40), "terrain": (120, 150, 70), "traffic sign": (230, 210, 30),
           "sky": (150, 190, 240)}


class BgrColourNet(torch.nn.Module):
    """Scores each pixel by its distance to each class's base colour, in chromaticity (x 400) and log brightness
    (x 4), after undoing ImageNet's normalisation: its weights, the colours, are in B, G, R order, so it sees the
    street right only when fed BGR. Classes without a colour (the objects) are never predicted."""

    def __init__(self) -> None:
        super().__init__()
        rgb = torch.tensor(list(COLOURS.values()), dtype=torch.float32) / 255
        self.colours = torch.nn.Parameter(rgb.flip(1))  # B, G, R
        place = torch.zeros(19, len(COLOURS))  # colour k -> its class's channel; the other channels score -1e4
        place[[CLASS_NAMES.index(n) for n in COLOURS], range(len(COLOURS))] = 1
        self.register_buffer("place", place)
        self.register_buffer("rest", (place.sum(1) == 0).float().view(1, 19, 1, 1) * -1e4)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))

    def forward(self, x):
        pixel = (x * self.std + self.mean).clamp_min(1e-3)
        bright = pixel.sum(1, keepdim=True)
        ref = self.colours.sum(1)
        chroma = ((pixel / bright)[:, None] - (self.colours / ref[:, None])[None, :, :, None, None]).pow(2).sum(2)
        score = -400 * chroma - 4 * (bright.log() - ref.log().view(1, -1, 1, 1)).pow(2)
        return torch.einsum("bkhw,ck->bchw", score, self.place) + self.rest


class Wide(torch.nn.Module):
    """150 outputs, a fixed random 1x1 convolution: ADE20K's width."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 150, 1)

    def forward(self, x):
        return self.conv(x)


def colour_net() -> BgrColourNet:  # model=python model.target=test_setup_check:colour_net
    return BgrColourNet()


def segmenter(module, labels="cityscapes", id2label=None, **keys) -> ContractSegmenter:
    seg = ContractSegmenter("net", Network(module, id2label=id2label), make_contract(keys),
                            resolve_labels(labels, id2label=id2label), RuntimeOptions(), "python")
    seg.probe()
    return seg


# -- the rule and the trial, for any task ----------------------------------------------------------------------
def test_the_rule_is_both_a_ratio_and_a_margin():
    beats = alternatives.clearly_beats
    assert beats(0.26, 0.17)                          # the reported LR-ASPP: 1.53x, +0.09
    assert not beats(0.48, 0.40) and beats(0.50, 0.40)  # 1.2x is not enough; 1.25x and +0.10 is
    assert not beats(0.04, 0.02)                      # 2x, but +0.02: noise on a few images
    assert beats(0.11, 0.06) and not beats(0.10, 0.06)  # +0.05 exactly counts, whatever the floats' last bits
    assert not beats(math.nan, 0.1) and not beats(0.5, math.nan)


def test_a_task_supplies_its_candidates_and_one_batched_score():
    """What another task (detection) would call: its own candidates, one score callable that gets them all."""
    seen = []

    def score(candidates):
        seen.append([c.change for c in candidates])
        return [{"configured": 0.30, "a": 0.33, "b": 0.45, "c": math.nan}[c.change] for c in candidates]

    cands = [alternatives.Candidate("configured"), alternatives.Candidate("a", {"x": 1}),
             alternatives.Candidate("b", {"y": 2}), alternatives.Candidate("c", {"z": 3})]
    verdict = alternatives.trial(cands, score)
    assert seen == [["configured", "a", "b", "c"]]  # one call: the task may batch
    assert verdict.best.candidate.change == "b" and verdict.better.candidate.overrides == {"y": 2}
    assert alternatives.record(verdict.better, "ap50") == {"setup": "b", "overrides": {"y": 2}, "ap50": 0.45}
    assert alternatives.trial(cands[:2], score).better is None


# -- the network of known channel order, in the check ------------------------------------------------------------
def street(n: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """Road below, sky above, vegetation on the right, in the base colours with a little shading."""
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        label = np.full((16, 32), CLASS_NAMES.index("sky"), dtype=np.uint8)
        label[8:] = CLASS_NAMES.index("road")
        label[2:8, 20:] = CLASS_NAMES.index("vegetation")
        image = np.zeros((16, 32, 3))
        for name, rgb in COLOURS.items():
            image[label == CLASS_NAMES.index(name)] = rgb
        image *= rng.uniform(0.9, 1.1, size=(16, 32, 1))
        out.append((np.clip(image, 0, 255).astype(np.uint8), label))
    return out


def test_the_bgr_network_is_named_above_the_line_and_silent_set_up_right():
    rows = setup_check.check(segmenter(BgrColourNet()), street())
    by = {r.change: r.miou for r in rows}
    assert by["configured"] >= setup_check.SETUP_MIN_MIOU and by["model.channels=bgr"] == 1.0
    assert setup_check.diagnose("net", rows) == (
        f"net: clean GT mIoU {by['configured']:.2f} on the embedded town (2 labelled clean images); with "
        "model.channels=bgr it would be 1.00: check the model's input contract (docs/models.md)")
    right = setup_check.check(segmenter(BgrColourNet(), channels="bgr"), street())
    assert right[0].miou == 1.0 and len(right) == len(rows)
    assert setup_check.diagnose("net", right) is None and setup_check.better_record(right) is None


def test_the_batched_trial_gives_each_set_ups_own_numbers(tmp_path):
    """One batch per image (the label spaces re-map the configured output) = one set-up at a time."""
    path = tmp_path / "mine.tsv"
    path.write_text("".join(f"c{i}\t{CLASS_NAMES[i % 19] if i < 40 else '-'}\n" for i in range(150)))
    seg = segmenter(Wide(), labels=str(path))
    todo = setup_check.setups(seg)
    assert todo[-1].change == "model.labels=ade20k" and todo[-1].overrides == {"labels": "ade20k"}
    batched = setup_check.score_setups(seg, todo, street())
    single = [setup_check.score(setup_check.variant(seg, s), street(), s) for s in todo]
    assert [r.change for r in batched] == [s.change for s in todo]
    for a, b in zip(batched, single):
        np.testing.assert_allclose(a.iou, b.iou, equal_nan=True)
        assert a.overrides == b.overrides


@pytest.mark.parametrize("batch", [None, 1])
def test_the_reported_case_an_onnx_export_under_the_rgb_default(tmp_path, batch):
    """The BGR network exported to ONNX (a dynamic batch, or a graph fixed to one image: the trial's batch is then
    run an image at a time), run with the default RGB contract: named, with each set-up's own numbers."""
    pytest.importorskip("onnxruntime")
    path = tmp_path / "bgr.onnx"
    axes = {"x": {2: "h", 3: "w"} if batch else {0: "b", 2: "h", 3: "w"}}
    torch.onnx.export(BgrColourNet(), (torch.rand(1, 3, 16, 32),), str(path), input_names=["x"], dynamic_axes=axes,
                      dynamo=False)
    seg = build_model({"name": "bgr", "family": "onnx", "path": str(path)})
    rows = setup_check.check(seg, street())
    assert setup_check.better_record(rows) == {"setup": "model.channels=bgr", "overrides": {"channels": "bgr"},
                                               "clean_miou": 1.0}
    single = [setup_check.score(setup_check.variant(seg, s), street(), s) for s in setup_check.setups(seg)]
    np.testing.assert_allclose([r.miou for r in rows], [r.miou for r in single])


# -- what the trial prints: nothing about the spaces it tries ----------------------------------------------------
def test_the_trial_says_nothing_about_the_label_spaces_it_tries(caplog, tmp_path):
    ade = resolve_labels("ade20k")
    names = {i: f"{n} (mine)" for i, n in enumerate(ade.source_classes)}  # names no shipped table spells so
    tsv = tmp_path / "mine.tsv"
    tsv.write_text("".join(f"{names[i]}\t{'road' if i == 6 else '-'}\n" for i in range(150)))
    seg = segmenter(Wide(), labels=str(tsv), id2label=names)
    with caplog.at_level(logging.INFO, logger="pairedgta"):
        rows = setup_check.check(seg, street())
    assert "model.labels=ade20k" in [r.change for r in rows]
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []
    assert not [r for r in caplog.records if "label" in r.getMessage()]
    # only during the trial: the user's own choice of that space still warns
    with caplog.at_level(logging.WARNING, logger="pairedgta.models"):
        resolve_labels("ade20k", id2label=names)
    assert "class names differ from model.labels=ade20k" in caplog.text


# -- the label-space lines ----------------------------------------------------------------------------------------
def test_a_150_class_checkpoint_is_shown_the_cityscapes_names():
    ade = resolve_labels("ade20k")
    with pytest.raises(ModelError) as info:
        resolve_labels(None, id2label=dict(enumerate(ade.source_classes)))
    text = str(info.value)
    assert "the checkpoint's 150 classes (wall, building, sky, floor, tree, ...) are not the 19 Cityscapes classes " \
           "(road, sidewalk, building, wall, fence, ...); is it an ade20k model? set model.labels=ade20k" in text
    assert "floor" not in text.split("Cityscapes classes")[1] and "\n" not in text
    names = dict(enumerate(["ground", *CLASS_NAMES[1:]]))  # 19 classes, one of them no Cityscapes name
    with pytest.raises(ModelError, match=r"Cityscapes classes \(road, sidewalk, .*\): ground is no Cityscapes class"):
        resolve_labels(None, id2label=names)


def test_19_outputs_under_ade20k_name_the_label_space_not_the_image_size():
    with pytest.raises(ModelError) as info:
        build_model({"name": "net", "family": "python", "target": "test_setup_check:colour_net",
                         "labels": "ade20k"})
    text = str(info.value)
    assert "the model outputs 19 channels, but model.labels=ade20k has 150 classes" in text
    assert "set model.labels=cityscapes" in text and "image size" not in text and "\n" not in text


# -- a torch.export program as model.checkpoint_path --------------------------------------------------------------
@pytest.fixture(scope="module")
def program(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("pt2") / "net.pt2"
    module = torch.nn.Conv2d(3, 19, 1).eval()
    torch.export.save(torch.export.export(module, (torch.rand(1, 3, 8, 8),)), str(path))
    return path


def test_a_pt2_checkpoint_names_model_export(program):
    from pairedgta.models.checkpoint import load_checkpoint_strict

    expect = f"model.checkpoint_path={program} is a torch.export program: use model=export model.path={program}"
    for cfg in ({"family": "python", "target": "test_setup_check:colour_net"},
                {"family": "torchvision", "arch": "lraspp_mobilenet_v3_large"}):
        with pytest.raises(ModelError) as info:
            build_model({"name": "n", "checkpoint_path": str(program), **cfg})
        assert str(info.value) == f"n: {expect}"
    with pytest.raises(ModelError) as info:  # the in-project families' loader: the same reader
        load_checkpoint_strict(torch.nn.Conv2d(3, 19, 1), program, model_name="demo")
    assert str(info.value) == f"demo: {expect}"


# -- through the app ----------------------------------------------------------------------------------------------
def warnings_of(proc) -> list[str]:
    return [line for line in (proc.stdout + proc.stderr).splitlines() if "[WARNING]" in line]


@pytest.mark.slow
def test_a_bgr_model_under_the_rgb_default_is_named_by_the_cli(tmp_path):
    from pairedgta.testing.cli import fast_overrides, run_cli

    weights = tmp_path / "bgr.pt"
    torch.save(BgrColourNet().state_dict(), weights)
    args = ["+experiment=model_check", *fast_overrides(tmp_path), "model=python",
            "model.target=test_setup_check:colour_net", f"model.checkpoint_path={weights}"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (line,) = warnings_of(proc)
    assert "bgr: clean GT mIoU 0.15 on the embedded town (3 labelled clean images); with model.channels=bgr it " \
           "would be 0.62: check the model's input contract (docs/models.md)" in line
    def entries() -> set[Path]:
        return {p for p in (tmp_path / "cache" / "model_check").iterdir() if not p.name.startswith(".")}

    (entry,) = entries()
    summary = json.loads((entry / "summary.json").read_text())
    assert summary["better"]["setup"] == "model.channels=bgr" and summary["better"]["overrides"] == {"channels": "bgr"}
    assert summary["better"]["clean_miou"] == pytest.approx(0.62, abs=0.005)
    assert summary["clean_miou"] == pytest.approx(0.15, abs=0.005)
    assert summary["rule"] == {"ratio": 1.25, "margin": 0.05}
    # set up right: silent, nothing kept
    right = run_cli([*args, "model.channels=bgr"], tmp_path)
    assert right.returncode == 0, right.stderr[-3000:]
    assert warnings_of(right) == [] and "no alternative clearly beats it: set up right" in right.stdout + right.stderr
    (other,) = entries() - {entry}
    assert json.loads((other / "summary.json").read_text())["better"] is None


@pytest.mark.slow
def test_the_evaluate_entry_keeps_the_named_alternative(tmp_path, caplog):
    from pairedgta.app import run
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    weights = tmp_path / "bgr.pt"
    torch.save(BgrColourNet().state_dict(), weights)
    cfg = compose_cfg(fast_overrides(tmp_path) + ["model=python", "model.target=test_setup_check:colour_net",
                                                  f"model.checkpoint_path={weights}", "reference_model=tiny_segformer",
                                                  "stages=[generate,pseudolabel,evaluate]"])
    with caplog.at_level(logging.WARNING, logger="pairedgta"):
        summary = run(cfg, ["model=python"])
    lines = [r.getMessage() for r in caplog.records if r.name == "pairedgta.setup_check"]
    assert len(lines) == 1 and "with model.channels=bgr it would be 0.62" in lines[0]
    stored = json.loads((Path(summary["evaluate"]["bgr"]) / "summary.json").read_text())
    assert stored["setup_warning"] == lines[0] and stored["clean_miou_check"] == pytest.approx(0.15, abs=0.005)
    assert stored["setup_better"] == {"setup": "model.channels=bgr", "overrides": {"channels": "bgr"},
                                      "clean_miou": pytest.approx(0.62, abs=0.005)}
