"""Is a model set up right? (pairedgta/evaluation/setup_check.py, the model_check stage, the evaluate stage's check
of a model source.) Networks whose answer is known by construction: one that reads the class off the first input
channel, on images whose truth follows the blue channel (right only with model.channels=bgr), one whose output
ignores its input (nothing helps: the domain-gap line), one that always says `train`."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.evaluation import setup_check
from pairedgta.models.contract import ContractSegmenter, Network, make_contract
from pairedgta.models.labels import resolve_labels
from pairedgta.models.runtime import RuntimeOptions

TRAIN = CLASS_NAMES.index("train")


class FirstChannel(torch.nn.Module):
    """road where the first input channel, as prepared, is above 0, else sidewalk."""

    def forward(self, x):
        first = x[:, :1]
        rest = torch.full((x.shape[0], 17, *x.shape[2:]), -100.0)
        return torch.cat([4 * first, -4 * first, rest], dim=1)


class Noise(torch.nn.Module):
    """The same random scores whatever the input (and wherever in a batch): no set-up changes what it predicts."""

    def forward(self, x):
        g = torch.Generator().manual_seed(0)
        return torch.randn((1, 19, *x.shape[2:]), generator=g).expand(x.shape[0], -1, -1, -1)


class Constant(torch.nn.Module):
    """`train` everywhere (a class the synthetic street never shows): clean mIoU 0 under every set-up."""

    def __init__(self) -> None:
        super().__init__()
        self.bias = torch.nn.Parameter(torch.zeros(1))  # a module with weights, as a user's would be

    def forward(self, x):
        out = torch.zeros((x.shape[0], 19, *x.shape[2:])) + self.bias
        out[:, TRAIN] = 10.0
        return out


def constant_net() -> Constant:  # model=python model.target=test_model_check:constant_net
    return Constant()


def segmenter(module, labels="cityscapes", **keys) -> ContractSegmenter:
    seg = ContractSegmenter("net", Network(module), make_contract(keys), resolve_labels(labels), RuntimeOptions(),
                            "python")
    seg.probe()
    return seg


def blue_samples(n: int = 3) -> list[tuple[np.ndarray, np.ndarray]]:
    """Left half blue (R 25, B 230): road; right half red (R 230, B 25): sidewalk; a void row."""
    out = []
    for _ in range(n):
        image = np.zeros((8, 16, 3), dtype=np.uint8)
        image[:, :8] = (25, 128, 230)
        image[:, 8:] = (230, 128, 25)
        label = np.zeros((8, 16), dtype=np.uint8)
        label[:, 8:] = 1
        label[0] = 255
        out.append((image, label))
    return out


def test_the_alternatives_are_each_one_change_as_typed():
    names = [s.change for s in setup_check.setups(segmenter(FirstChannel()))]
    assert names == ["configured", "model.channels=bgr", "model.mean=[0.5,0.5,0.5] model.std=[0.5,0.5,0.5]",
                     "model.mean=[0,0,0] model.std=[1,1,1]", "model.scale=255",
                     "model.scale=255 model.mean=[0,0,0] model.std=[1,1,1]"]
    # in 0-255 units: ImageNet's mean/std scaled (scale=1 with them is the same set-up, left out)
    names = [s.change for s in setup_check.setups(segmenter(FirstChannel(), scale=255, mean=[0, 0, 0], std=[1, 1, 1]))]
    assert "model.mean=[123.675,116.28,103.53] model.std=[58.395,57.12,57.375]" in names
    assert "model.scale=1" in names and not any("model.scale=1 model.mean=[0.485" in n for n in names)


def test_a_label_space_is_tried_only_where_its_table_fits_the_outputs(tmp_path):
    class Wide(torch.nn.Module):
        def forward(self, x):
            return torch.zeros((x.shape[0], 150, *x.shape[2:]))

    tsv = tmp_path / "mine.tsv"
    tsv.write_text("".join(f"c{i}\t{'road' if i == 0 else '-'}\n" for i in range(150)))
    names = [s.change for s in setup_check.setups(segmenter(Wide(), labels=str(tsv)))]
    assert "model.labels=ade20k" in names and not [n for n in names if "vistas" in n or "coco" in n]
    assert not [n for n in setup_check.setups(segmenter(FirstChannel())) if n.change.startswith("model.labels")]


def test_the_wrong_channel_order_is_named():
    seg = segmenter(FirstChannel())
    rows = setup_check.check(seg, blue_samples())
    by = {r.change: r for r in rows}
    assert by["configured"].miou == 0.0 and by["model.channels=bgr"].miou == 1.0
    assert by["model.channels=bgr"].iou[:2] == (1.0, 1.0) and all(math.isnan(v) for v in by["configured"].iou[2:])
    warning = setup_check.diagnose("net", rows)
    assert warning == ("net: clean GT mIoU 0.00 on the embedded town (3 labelled clean images); with "
                       "model.channels=bgr it would be 1.00: check the model's input contract (docs/models.md)")
    assert "\n" not in warning
    assert seg.contract.channels == "rgb" and seg._mean.flatten().tolist() == pytest.approx([0.485, 0.456, 0.406])
    assert by["model.channels=bgr"].overrides == {"channels": "bgr"}
    assert setup_check.better_record(rows) == {"setup": "model.channels=bgr", "overrides": {"channels": "bgr"},
                                               "clean_miou": 1.0}
    # set up right: every alternative tried, none named
    good = setup_check.check(segmenter(FirstChannel(), channels="bgr"), blue_samples())
    assert len(good) == len(rows) and good[0].miou == 1.0
    assert setup_check.diagnose("net", good) is None and setup_check.better_record(good) is None


def test_nothing_helps_a_model_that_does_not_see_the_images():
    rows = setup_check.check(segmenter(Noise()), blue_samples())
    assert len({round(r.miou, 9) for r in rows}) == 1 and rows[0].miou < setup_check.SETUP_MIN_MIOU
    warning = setup_check.diagnose("noise", rows)
    assert "does not recognise the embedded town (a domain gap, not a robustness result)" in warning
    assert "renderer=deepgtav" in warning and "dataset=paired_gta dataset.root=" in warning and "\n" not in warning


def test_only_a_clearly_better_alternative_is_named():
    row = lambda change, miou: setup_check.Row(change, miou, (miou,) * 19, 4)  # noqa: E731
    # above the line too (>= 1.25x and >= +0.05): the user's LR-ASPP, 0.17 as configured and 0.26 in BGR
    assert "with model.channels=bgr it would be 0.26" in setup_check.diagnose(
        "m", [row("configured", 0.17), row("model.channels=bgr", 0.26)])
    assert setup_check.diagnose("m", [row("configured", 0.40), row("model.channels=bgr", 0.48)]) is None  # 1.2x
    assert setup_check.diagnose("m", [row("configured", 0.12), row("model.channels=bgr", 0.16)]) is None  # +0.04
    assert "model.channels=bgr it would be 0.11" in setup_check.diagnose(
        "m", [row("configured", 0.06), row("model.channels=bgr", 0.11)])
    assert "domain gap" in setup_check.diagnose("m", [row("configured", 0.06), row("model.channels=bgr", 0.10)])
    assert "domain gap" in setup_check.diagnose("m", [row("configured", 0.02), row("model.channels=bgr", 0.09)])
    assert "with model.scale=255 it would be 0.30" in setup_check.diagnose(
        "m", [row("configured", 0.05), row("model.channels=bgr", 0.2), row("model.scale=255", 0.3)])
    assert "zoo model" in setup_check.diagnose("m", [row("configured", 0.05)])


def test_the_table_and_its_markdown():
    rows = setup_check.check(segmenter(FirstChannel()), blue_samples())
    df = setup_check.table(rows)
    assert list(df.columns[:3]) == ["setup", "clean_miou", "n_images"] and len(df) == len(rows)
    md = setup_check.markdown(df).splitlines()
    assert md[0] == "| set-up | clean mIoU | road | sidewalk |"
    assert md[2].startswith("| as configured | 0.00 |") and md[3] == "| `model.channels=bgr` | 1.00 | 1.00 | 1.00 |"


# -- through the app --------------------------------------------------------------------------------------------
def python_model(target: str) -> list[str]:
    return ["model=python", f"model.target=test_model_check:{target}", "reference_model=tiny_segformer"]


@pytest.mark.slow
def test_model_check_prints_and_writes_the_table(tmp_path):
    from pairedgta.testing.cli import fast_overrides, run_cli

    proc = run_cli(["+experiment=model_check", *fast_overrides(tmp_path), *python_model("constant_net")], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    assert "model_check [constant_net]: clean GT mIoU on 3 Day-EXTRASUNNY image(s) of the embedded town" in out
    assert "| as configured | 0.00 |" in out and "| `model.channels=bgr` | 0.00 |" in out
    assert ("constant_net: clean GT mIoU 0.00 on the embedded town (3 labelled clean images), and no other channel "
            "order, scale, mean/std or label space does better: the model does not recognise the embedded town") in out
    (entry,) = [p for p in (tmp_path / "cache" / "model_check").iterdir() if not p.name.startswith(".")]
    table = setup_check.read_table(entry / "model_check.csv")
    assert table["setup"].tolist()[:2] == ["configured", "model.channels=bgr"] and (table["clean_miou"] == 0).all()
    assert (table["train"] == 0).all()
    assert (entry / "model_check.md").read_text().startswith("# model_check: constant_net on the embedded town")
    assert not (tmp_path / "cache" / "pseudolabel").exists() and not (tmp_path / "cache" / "evaluate").exists()
    # a zoo model: its configured row only; the scenes are the cached ones
    zoo = run_cli(["+experiment=model_check", *fast_overrides(tmp_path)], tmp_path)
    assert zoo.returncode == 0, zoo.stderr[-3000:]
    assert "generate: cache hit" in zoo.stdout + zoo.stderr
    entries = [p for p in (tmp_path / "cache" / "model_check").iterdir() if not p.name.startswith(".") and p != entry]
    assert len(setup_check.read_table(entries[0] / "model_check.csv")) == 1


@pytest.mark.slow
def test_the_first_evaluation_of_a_source_model_checks_its_set_up(tmp_path, caplog):
    from pairedgta.app import run
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    weights = tmp_path / "constant.pt"  # a user's weights file (a python model without one is refused before
    torch.save(Constant().state_dict(), weights)  # rendering by models/availability.py, as if it were a zoo model)
    cfg = compose_cfg(fast_overrides(tmp_path) + python_model("constant_net")
                      + [f"model.checkpoint_path={weights}", "stages=[generate,pseudolabel,evaluate]"])
    with caplog.at_level(logging.WARNING, logger="pairedgta.setup_check"):
        summary = run(cfg, ["model=python"])
    lines = [r.getMessage() for r in caplog.records if r.name == "pairedgta.setup_check"]
    assert len(lines) == 1 and "constant: clean GT mIoU 0.00 on the embedded town" in lines[0]  # named by its file
    assert "domain gap" in lines[0]
    entry = tmp_path / "cache" / "evaluate"
    (path,) = [p for p in entry.iterdir() if not p.name.startswith(".")]
    assert str(path) == summary["evaluate"]["constant"]
    import json

    stored = json.loads((path / "summary.json").read_text())
    assert stored["clean_miou_check"] == 0.0 and stored["setup_warning"] == lines[0]
    assert stored["setup_better"] is None
    assert len(setup_check.read_table(path / "setup_check.csv")) > 1  # every alternative
    # a cache hit re-reads the stored line
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pairedgta.setup_check"):
        run(cfg, ["model=python"])
    assert [r.getMessage() for r in caplog.records if r.name == "pairedgta.setup_check"] == lines
