"""`model=hf`: any transformers segmentation checkpoint from a save_pretrained folder, through the shared contract.
Tiny random-init models are written in the tests: the semantic source gives the segformer family's numbers and the
universal one the mask2former family's on the same folder; the image processor's input is the contract's (checked
against the processor's own pixel_values); class names from id2label drive the label map; bad folders are one line."""
from __future__ import annotations

import json
import logging
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ModelError
from pairedgta.models import build_model, model_config
from pairedgta.models.labels import TABLES, read_table, resolve_labels
from pairedgta.models.sources.hf import ONEFORMER_TASK, processor_contract

TINY_SWIN = {"embed_dim": 16, "depths": [1, 1, 1, 1], "num_heads": [1, 1, 1, 1], "window_size": 4,
             "out_features": ["stage1", "stage2", "stage3", "stage4"]}
CITYSCAPES = {"id2label": dict(enumerate(CLASS_NAMES)), "label2id": {n: i for i, n in enumerate(CLASS_NAMES)}}


def hf(path, **keys):
    return build_model({"name": "x", "family": "hf", "path": str(path), **keys})


def one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    return msg


def tiny_segformer(num_labels=19, seed=0, **config):
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    torch.manual_seed(seed)
    arch = model_config("tiny_segformer")["arch"]
    return SegformerForSemanticSegmentation(SegformerConfig(num_labels=num_labels, **arch, **config)).eval()


@pytest.fixture(scope="module")
def segformer_dir(tmp_path_factory):
    """The tiny SegFormer of the zoo with a processor that keeps the size and normalises with its own mean/std."""
    from transformers import SegformerImageProcessor

    folder = tmp_path_factory.mktemp("segformer")
    build_model("tiny_segformer").module.save_pretrained(folder)
    processor = SegformerImageProcessor(do_resize=False, image_mean=[0.5, 0.4, 0.3], image_std=[0.25, 0.2, 0.3])
    processor.save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def mask2former_dir(tmp_path_factory):
    from transformers import Mask2FormerImageProcessor

    folder = tmp_path_factory.mktemp("mask2former")
    build_model("tiny_mask2former").module.save_pretrained(folder)
    Mask2FormerImageProcessor(do_resize=False, size_divisor=32).save_pretrained(folder)
    return folder


def test_semantic_source_gives_the_segformer_familys_numbers(segformer_dir):
    seg = hf(segformer_dir)
    x = torch.rand(2, 3, 45, 83)
    probs = seg.predict_proba(x)
    assert probs.shape == (2, 19, 45, 83)
    torch.testing.assert_close(probs.sum(1), torch.ones(2, 45, 83), atol=1e-5, rtol=0)
    family = build_model("segformer_b5", path=str(segformer_dir))
    torch.testing.assert_close(probs, family.predict_proba(x), atol=1e-5, rtol=0)
    # the processor's mean/std, the checkpoint's class names, and what loading ran
    assert seg.contract.mean == (0.5, 0.4, 0.3) and seg.contract.std == (0.25, 0.2, 0.3)
    assert seg.contract.output == "logits" and seg.contract.resize is None and seg.contract.pad_multiple == 1
    assert seg.network.id2label == dict(enumerate(CLASS_NAMES)) and seg.labels.identity
    assert "from_pretrained of safetensors weights" in seg.network.executes


def test_universal_source_gives_the_mask2former_familys_numbers(mask2former_dir):
    seg = hf(mask2former_dir)
    assert seg.contract.output == "probabilities" and seg.contract.pad_multiple == 32
    x = torch.rand(2, 3, 45, 83)
    probs = seg.predict_proba(x)
    assert probs.shape == (2, 19, 45, 83)
    torch.testing.assert_close(probs.sum(1), torch.ones(2, 45, 83), atol=1e-5, rtol=0)
    family = build_model("mask2former_swin_s", path=str(mask2former_dir))
    torch.testing.assert_close(probs, family.predict_proba(x), atol=1e-5, rtol=0)


def by_hand_queries(model, x, size_divisor, **inputs):
    """Mask2Former's semantic inference written out: ImageNet normalisation, padding, softmax without no-object x
    sigmoid masks summed over queries, upsampled, cropped, renormalised."""
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    h, w = x.shape[-2:]
    y = F.pad((x - mean) / std, (0, -w % size_divisor, 0, -h % size_divisor))
    with torch.no_grad():
        out = model(pixel_values=y, **inputs)
    cls = out.class_queries_logits.softmax(-1)[..., :-1]
    sem = (cls[..., None, None] * out.masks_queries_logits.sigmoid()[:, :, None]).sum(1)
    sem = F.interpolate(sem, size=y.shape[-2:], mode="bilinear", align_corners=False)[..., :h, :w]
    return sem / sem.sum(1, keepdim=True)


def test_maskformer_through_the_universal_source(tmp_path):
    from transformers import DetrConfig, MaskFormerConfig, MaskFormerForInstanceSegmentation, MaskFormerImageProcessor
    from transformers import SwinConfig

    torch.manual_seed(1)
    decoder = DetrConfig(d_model=32, encoder_layers=1, decoder_layers=1, encoder_ffn_dim=64, decoder_ffn_dim=64,
                         encoder_attention_heads=2, decoder_attention_heads=2, num_queries=8)
    model = MaskFormerForInstanceSegmentation(MaskFormerConfig(
        backbone_config=SwinConfig(**TINY_SWIN), decoder_config=decoder, mask_feature_size=32, fpn_feature_size=32,
        num_queries=8, num_labels=19, **CITYSCAPES)).eval()
    model.save_pretrained(tmp_path)
    MaskFormerImageProcessor(do_resize=False, size_divisor=32).save_pretrained(tmp_path)
    seg = hf(tmp_path)
    x = torch.rand(1, 3, 40, 70)
    torch.testing.assert_close(seg.predict_proba(x), by_hand_queries(model, x, 32), atol=1e-5, rtol=0)


def write_clip_tokenizer(folder):
    """A CLIP BPE vocabulary of the task sentence's words: enough for OneFormer's task input, offline."""
    vocab, merges = {"<|startoftext|>": 0, "<|endoftext|>": 1}, []
    for word in ONEFORMER_TASK.split():
        parts = list(word[:-1]) + [word[-1] + "</w>"]
        for p in parts:
            vocab.setdefault(p, len(vocab))
        while len(parts) > 1:
            merges.append(f"{parts[0]} {parts[1]}")
            parts = [parts[0] + parts[1]] + parts[2:]
            vocab.setdefault(parts[0], len(vocab))
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n")
    (folder / "tokenizer_config.json").write_text(json.dumps({"tokenizer_class": "CLIPTokenizer"}))


def test_oneformer_gets_the_semantic_task_input(tmp_path):
    from transformers import (AutoTokenizer, OneFormerConfig, OneFormerForUniversalSegmentation,
                              OneFormerImageProcessor, OneFormerProcessor, SwinConfig)

    torch.manual_seed(2)
    config = OneFormerConfig(backbone_config=SwinConfig(**TINY_SWIN), num_labels=19, **CITYSCAPES, num_queries=8,
                             conv_dim=32, mask_dim=32, hidden_dim=32, encoder_feedforward_dim=64, encoder_layers=1,
                             decoder_layers=2, num_attention_heads=2, dim_feedforward=64, text_encoder_width=32,
                             text_encoder_num_layers=1, text_encoder_context_length=16, task_seq_len=16,
                             text_encoder_n_ctx=2, query_dec_layers=1)
    model = OneFormerForUniversalSegmentation(config).eval()
    model.save_pretrained(tmp_path)
    OneFormerImageProcessor(do_resize=False, class_info_file=None).save_pretrained(tmp_path)
    # without its tokenizer the task input cannot be made: one line, not an empty tokenizer's unknown words
    with pytest.raises(ModelError, match="OneFormer needs its task input") as exc:
        hf(tmp_path)
    assert "processor.save_pretrained" in one_line(exc)
    write_clip_tokenizer(tmp_path)
    seg = hf(tmp_path)
    # the task input is the one OneFormerProcessor makes for task "semantic"
    processor = OneFormerProcessor(image_processor=OneFormerImageProcessor(do_resize=False, class_info_file=None),
                                   tokenizer=AutoTokenizer.from_pretrained(tmp_path), task_seq_length=16)
    image = np.zeros((32, 32, 3), np.uint8)
    task = processor(images=[image], task_inputs=["semantic"], return_tensors="pt")["task_inputs"]
    assert torch.equal(seg.network.module.task_inputs, task) and int((task > 1).sum()) == 4  # four known words
    x = torch.rand(2, 3, 40, 70)
    expect = by_hand_queries(model, x, 1, task_inputs=task.expand(2, -1).float())
    torch.testing.assert_close(seg.predict_proba(x), expect, atol=1e-5, rtol=0)
    assert "task input" in seg.network.executes


def _processors():
    from transformers import (DPTImageProcessor, MobileViTImageProcessor, SegformerImageProcessor)

    return {
        "normalises": SegformerImageProcessor(do_resize=False, image_mean=[0.3, 0.5, 0.7], image_std=[0.2, 0.3, 0.4]),
        "bgr_no_normalise": MobileViTImageProcessor(do_resize=False, do_center_crop=False, do_flip_channel_order=True),
        "minus_one_to_one": SegformerImageProcessor(do_resize=False, rescale_factor=1 / 127.5, image_mean=[1, 1, 1],
                                                    image_std=[1, 1, 1]),
        "no_rescale": DPTImageProcessor(do_resize=False, do_rescale=False, image_mean=[120, 110, 100],
                                        image_std=[60, 50, 40]),
    }


@pytest.mark.parametrize("case", list(_processors()))
def test_the_contract_prepares_what_the_processor_would(case, segformer_dir, tmp_path):
    """Whatever the processor's rescale / normalise / channel flip, the contract's input equals its pixel_values."""
    import shutil

    proc = _processors()[case]
    for f in ("config.json", "model.safetensors"):
        shutil.copy(segformer_dir / f, tmp_path / f)
    proc.save_pretrained(tmp_path)
    seg = hf(tmp_path)
    image = np.random.default_rng(0).integers(0, 256, (24, 40, 3), dtype=np.uint8)
    expect = proc(images=[image], return_tensors="pt")["pixel_values"]
    x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
    torch.testing.assert_close(seg.prepare(x), expect, atol=1e-4, rtol=1e-5)


def test_processor_sizes_become_the_contracts_resize_and_padding(segformer_dir, tmp_path, caplog):
    import shutil

    from transformers import DPTImageProcessor, Mask2FormerImageProcessor, SegformerImageProcessor

    assert processor_contract(SegformerImageProcessor(size={"height": 64, "width": 96}))["resize"] == [64, 96]
    with caplog.at_level(logging.WARNING, logger="pairedgta.models"):
        m2f = processor_contract(Mask2FormerImageProcessor())  # shortest_edge 800, longest_edge 1333, divisor 32
    assert m2f["resize"] == 800 and m2f["pad_multiple"] == 32 and "1333" in caplog.text
    dpt = processor_contract(DPTImageProcessor(size={"height": 384, "width": 384}, keep_aspect_ratio=True,
                                               do_pad=False, size_divisor=32))
    assert dpt["resize"] == 384 and "pad_multiple" not in dpt  # DPT pads only with do_pad
    assert "resize" not in processor_contract(SegformerImageProcessor(do_resize=False))
    # a processor's size reaches the segmenter; no processor at all: the contract's defaults
    for f in ("config.json", "model.safetensors"):
        shutil.copy(segformer_dir / f, tmp_path / f)
    seg = hf(tmp_path)
    assert seg.contract.mean == (0.485, 0.456, 0.406) and seg.contract.resize is None
    SegformerImageProcessor(size={"height": 64, "width": 64}).save_pretrained(tmp_path)
    seg = hf(tmp_path)
    assert seg.contract.resize == (64, 64)
    assert seg.predict_proba(torch.rand(1, 3, 40, 90)).shape == (1, 19, 40, 90)


def test_an_ade20k_model_needs_its_label_space(tmp_path):
    ade = read_table(TABLES / "ade20k.tsv").source_classes
    model = tiny_segformer(150, id2label=dict(enumerate(ade)), label2id={n: i for i, n in enumerate(ade)})
    model.save_pretrained(tmp_path)
    seg = hf(tmp_path, labels="ade20k")
    probs = seg.predict_proba(torch.rand(1, 3, 32, 48))
    assert probs.shape == (1, 19, 32, 48)
    torch.testing.assert_close(probs.sum(1), torch.ones(1, 32, 48), atol=1e-5, rtol=0)
    assert seg.labels.num_outputs == 150
    assert seg.labels.unpredictable == resolve_labels("ade20k").unpredictable and seg.labels.unpredictable
    assert probs[:, [CLASS_NAMES.index(c) for c in seg.labels.unpredictable]].max() == 0
    with pytest.raises(ModelError, match="model.labels=") as exc:
        hf(tmp_path)
    assert "ade20k" in one_line(exc) and "150 classes" in str(exc.value)


def test_class_names_in_another_order_are_matched_by_name(tmp_path):
    model = tiny_segformer(19, seed=3, **CITYSCAPES)
    model.save_pretrained(tmp_path / "plain")
    perm = torch.randperm(19, generator=torch.Generator().manual_seed(0))
    assert not torch.equal(perm, torch.arange(19))
    head = model.decode_head.classifier
    with torch.no_grad():
        head.weight.copy_(head.weight[perm])
        head.bias.copy_(head.bias[perm])
    names = [CLASS_NAMES[int(i)] for i in perm]  # channel c now scores class perm[c]
    model.config.id2label = dict(enumerate(names))
    model.config.label2id = {n: i for i, n in enumerate(names)}
    model.save_pretrained(tmp_path / "permuted")
    x = torch.rand(1, 3, 32, 48)
    permuted, plain = hf(tmp_path / "permuted"), hf(tmp_path / "plain")
    assert permuted.labels.target == tuple(int(i) for i in perm)
    torch.testing.assert_close(permuted.predict_proba(x), plain.predict_proba(x), atol=1e-6, rtol=0)


def test_bad_folders_are_one_line(segformer_dir, tmp_path):
    import shutil

    from transformers import BertConfig, SegformerConfig, SegformerForImageClassification

    (tmp_path / "file.safetensors").write_bytes(b"x")
    (tmp_path / "empty").mkdir()
    corrupt = tmp_path / "corrupt"
    shutil.copytree(segformer_dir, corrupt)
    (corrupt / "model.safetensors").write_bytes((corrupt / "model.safetensors").read_bytes()[:200])
    SegformerForImageClassification(SegformerConfig(num_labels=19, **model_config("tiny_segformer")["arch"])
                                    ).save_pretrained(tmp_path / "classifier")
    bert = BertConfig(hidden_size=8, num_hidden_layers=1, num_attention_heads=1, intermediate_size=8)
    bert.save_pretrained(tmp_path / "bert")
    cases = [
        ({"path": str(tmp_path / "nowhere")}, "is not a directory"),
        ({"path": str(tmp_path / "file.safetensors")}, "is not a directory"),
        ({"path": None}, "neither model.hub_id nor model.path"),
        ({"path": str(tmp_path / "empty")}, "has no config.json"),
        ({"path": str(corrupt)}, "cannot load the weights in model.path="),
        ({"path": str(tmp_path / "classifier")}, "which would be random; is it a segmentation checkpoint"),
        ({"path": str(tmp_path / "bert")}, "is a 'bert' model"),
        ({"path": None, "hub_id": "nobody/no-such-model", "revision": "v1"},
         "huggingface-cli download nobody/no-such-model --revision v1 --local-dir DIR"),
    ]
    for keys, text in cases:
        with pytest.raises(ModelError) as exc:
            build_model({"name": "x", "family": "hf", **keys})
        assert text in one_line(exc), (keys, str(exc.value))


def test_a_pickle_weights_file_executes_nothing(segformer_dir, tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    folder = tmp_path / "evil"
    folder.mkdir()
    (folder / "config.json").write_bytes((segformer_dir / "config.json").read_bytes())
    (folder / "pytorch_model.bin").write_bytes(pickle.dumps({"decode_head.classifier.weight": Evil()}))
    with pytest.raises(ModelError, match="cannot load the weights") as exc:
        hf(folder)
    one_line(exc)
    assert not marker.exists()


@pytest.mark.slow
def test_hf_folder_through_the_cli(segformer_dir, tmp_path):
    import shutil

    from pairedgta.testing.cli import report_overrides, report_page, run_cli

    folder = tmp_path / "my_segformer"
    shutil.copytree(segformer_dir, folder)
    r = run_cli(report_overrides(tmp_path) + ["model=hf", f"model.path={folder}"], tmp_path)
    assert r.returncode == 0, r.stderr
    report_page(r, "my_segformer")
    assert "evaluate [my_segformer]" in r.stdout + r.stderr
    evals = {json.loads((p / "manifest.json").read_text())["config"]["model"]["name"]: p
             for p in (tmp_path / "cache" / "evaluate").iterdir() if not p.name.startswith(".")}
    assert "my_segformer" in evals and (evals["my_segformer"] / "xi.csv").is_file()
