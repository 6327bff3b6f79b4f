"""The contract every model source shares (pairedgta/models/contract.py) and the label map
(pairedgta/models/labels.py), by hand: each preprocessing step, the sliding window, the output checks and how
probabilities of several source classes add up."""
from __future__ import annotations

import pytest
import torch

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ConfigError, ModelError
from pairedgta.models.contract import ContractSegmenter, Network, make_contract, resized_size
from pairedgta.models.labels import LabelMap, fit_outputs, read_table, resolve_labels
from pairedgta.models.runtime import RuntimeOptions


class Record(torch.nn.Module):
    """Returns fixed logits and remembers the input it saw."""

    def __init__(self, channels: int = 19, factor: int = 1) -> None:
        super().__init__()
        self.channels, self.factor, self.seen = channels, factor, []

    def forward(self, x):
        self.seen.append(x.clone())
        b, _, h, w = x.shape
        g = torch.arange(self.channels, dtype=torch.float32).view(1, -1, 1, 1)
        return {"out": g.expand(b, self.channels, h // self.factor, w // self.factor).clone(),
                "aux": torch.zeros(1)}


def seg(module, labels="cityscapes", **keys):
    contract = make_contract(keys)
    return ContractSegmenter("m", Network(module), contract, resolve_labels(labels), RuntimeOptions(), "python")


def test_preprocessing_steps_in_order():
    net = Record()
    s = seg(net, channels="bgr", scale=255, mean=[1.0, 2.0, 3.0], std=[2.0, 2.0, 2.0], pad_multiple=8)
    x = torch.rand(1, 3, 10, 13)
    probs = s.predict_proba(x)
    seen = net.seen[-1]
    assert seen.shape == (1, 3, 16, 16)  # padded to a multiple of 8, bottom/right
    expect = (x.flip(1) * 255 - torch.tensor([1.0, 2.0, 3.0]).view(1, 3, 1, 1)) / 2.0
    torch.testing.assert_close(seen[..., :10, :13], expect)
    assert torch.count_nonzero(seen[..., 10:, :]) == 0
    assert probs.shape == (1, 19, 10, 13)
    torch.testing.assert_close(probs.sum(1), torch.ones(1, 10, 13))


def test_resize_short_side_and_fixed():
    assert resized_size(512, 256, 512) == (512, 1024)
    assert resized_size((128, 64), 256, 512) == (128, 64)
    assert resized_size(None, 5, 7) == (5, 7)
    net = Record(factor=4)
    s = seg(net, resize=64)
    assert s.predict_proba(torch.rand(2, 3, 32, 80)).shape == (2, 19, 32, 80)  # back at input size
    assert net.seen[-1].shape == (2, 3, 64, 160)


def test_probabilities_output_is_renormalised_not_softmaxed():
    class Probs(torch.nn.Module):
        def forward(self, x):
            p = torch.zeros(x.shape[0], 19, *x.shape[-2:])
            p[:, 13] = 3.0
            p[:, 0] = 1.0
            return p

    probs = seg(Probs(), output="probabilities").predict_proba(torch.rand(1, 3, 8, 8))
    assert torch.allclose(probs[0, 13], torch.full((8, 8), 0.75)) and torch.allclose(probs[0, 0], torch.full((8, 8), 0.25))


def test_slide_covers_every_pixel_and_averages():
    class Position(torch.nn.Module):  # logits = the crop-local column index: overlaps average
        def forward(self, x):
            b, _, h, w = x.shape
            col = torch.arange(w, dtype=torch.float32).view(1, 1, 1, w).expand(b, 19, h, w).clone()
            col[:, 1:] = 0
            return col

    s = seg(Position(), inference="slide", crop=[8, 8], stride=[8, 4], mean=[0, 0, 0], std=[1, 1, 1])
    scores = s.scores(torch.rand(1, 3, 8, 16))
    # windows start at columns 0, 4, 8: column 5 is local 5 (window 0) and 1 (window 4): mean 3
    assert scores[0, 0, 0, 5].item() == pytest.approx(3.0)
    assert scores[0, 0, 0, 15].item() == pytest.approx(7.0)
    # an image smaller than the crop is one padded window
    assert s.scores(torch.rand(1, 3, 5, 6)).shape == (1, 19, 5, 6)


def test_contract_errors_are_one_line():
    for keys, text in [({"scale": 3}, "scale=3"), ({"channels": "rgba"}, "channels"), ({"resize": [0, 3]}, "resize"),
                       ({"pad_multiple": 0}, "pad_multiple"), ({"inference": "slide"}, "crop"),
                       ({"output": "softmax"}, "output"), ({"mean": [1, 2]}, "mean"), ({"std": [1, 0, 1]}, "std")]:
        with pytest.raises(ConfigError, match=text) as exc:
            make_contract(keys)
        assert "\n" not in str(exc.value)


def test_output_checks():
    class Flat(torch.nn.Module):
        def forward(self, x):
            return torch.zeros(x.shape[0], 19)

    with pytest.raises(ModelError, match="not B x C x H x W"):
        seg(Flat()).probe()
    with pytest.raises(ModelError, match="150 classes|outputs 18 channels") as exc:
        seg(Record(channels=18), labels="ade20k").probe()
    assert "\n" not in str(exc.value)
    with pytest.raises(ModelError, match="set model.labels=ade20k"):
        seg(Record(channels=150)).probe()

    class NaNs(torch.nn.Module):
        def forward(self, x):
            return torch.full((x.shape[0], 19, *x.shape[-2:]), float("nan"))

    with pytest.raises(ModelError, match="not finite"):
        seg(NaNs()).probe()


def test_label_map_adds_maps_and_renormalises():
    m = LabelMap("t", ("a", "b", "c", "d"), (0, 0, 13, -1))
    p = torch.tensor([0.1, 0.2, 0.3, 0.4]).view(1, 4, 1, 1)
    out = m.apply(p)
    assert out.shape == (1, 19, 1, 1)
    assert out[0, 0].item() == pytest.approx(0.3 / 0.6) and out[0, 13].item() == pytest.approx(0.3 / 0.6)
    assert out.sum().item() == pytest.approx(1.0)
    assert "road" not in m.unpredictable and "car" not in m.unpredictable and "sky" in m.unpredictable
    assert m.dropped == ("d",)


def test_cityscapes_names_matched_in_any_order():
    order = list(reversed(CLASS_NAMES))
    m = resolve_labels("cityscapes", id2label={i: n.replace(" ", "_").upper() for i, n in enumerate(order)})
    p = torch.eye(19).view(19, 19, 1, 1)  # image i: all mass on channel i
    out = m.apply(p)
    for i, name in enumerate(order):
        assert out[i, CLASS_NAMES.index(name)].item() == 1.0
    # transformers' placeholder names say nothing: the channel order is Cityscapes'
    assert resolve_labels("cityscapes", id2label={i: f"LABEL_{i}" for i in range(19)}).identity
    with pytest.raises(ModelError, match="model.labels="):
        resolve_labels("cityscapes", id2label={0: "wall", 1: "bed"})


def test_user_tsv(tmp_path):
    table = tmp_path / "mine.tsv"
    table.write_text("# my classes\nlane\troad\ncurb\tsidewalk\nego car\t-\nauto\tcar\n")
    m = read_table(table)
    assert m.target == (0, 1, -1, 13) and m.source_classes[2] == "ego car"
    m2 = resolve_labels(str(table))
    assert m2.target == m.target
    header = tmp_path / "header.tsv"
    header.write_text("source_class\tcityscapes_class\nlane\troad\n")
    assert read_table(header).target == (0,)
    bad = tmp_path / "bad.tsv"
    bad.write_text("lane\troad\nauto\tautomobile\n")
    with pytest.raises(ConfigError, match=r"line 2: 'automobile' is not a Cityscapes class") as exc:
        resolve_labels(str(bad))
    assert "\n" not in str(exc.value)
    with pytest.raises(ConfigError, match="no such file"):
        resolve_labels(str(tmp_path / "missing.tsv"))
    with pytest.raises(ConfigError, match="unknown"):
        resolve_labels("kitti")


def test_vistas_65_class_head_accepted():
    vistas = resolve_labels("mapillary_vistas_v1.2")
    assert vistas.num_outputs == 66 and vistas.source_classes[-1] == "Unlabeled"
    assert fit_outputs(vistas, 65, "m").num_outputs == 65
    with pytest.raises(ModelError, match="64 channels"):
        fit_outputs(vistas, 64, "m")
    assert vistas.unpredictable == ()
    assert set(resolve_labels("ade20k").unpredictable) == {"traffic sign", "rider", "train"}
    assert set(resolve_labels("coco_panoptic").unpredictable) == {"pole", "rider"}


def test_shipped_table_read_against_the_checkpoint_names(caplog):
    ade = resolve_labels("ade20k")
    names = dict(enumerate(ade.source_classes))
    assert resolve_labels("ade20k", id2label=names).target == ade.target
    shuffled = dict(enumerate(reversed(ade.source_classes)))  # another channel order: matched by name
    assert resolve_labels("ade20k", id2label=shuffled).target == tuple(reversed(ade.target))
    names[0] = "walls"  # a name that differs: said, and the table's order kept
    with caplog.at_level("WARNING", logger="pairedgta.models"):
        assert resolve_labels("ade20k", id2label=names).target == ade.target
    assert "'walls' vs 'wall'" in caplog.text
    with pytest.raises(ModelError, match="set model.labels=ade20k"):
        resolve_labels("cityscapes", id2label=dict(enumerate(ade.source_classes)))
