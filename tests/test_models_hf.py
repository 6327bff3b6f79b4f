"""SegFormer and Mask2Former through transformers: the real loading path on local directories,
the probability contract, and offline errors that name the hub id and `model.path=`."""
from __future__ import annotations


import pytest
import torch

from pairedgta.errors import ModelError
from pairedgta.models import build_model, model_config


@pytest.mark.parametrize("name", ["tiny_segformer", "tiny_mask2former"])
def test_tiny_models_probability_contract(name):
    seg = build_model(name)
    assert seg.num_classes == 19 and seg.class_names[13] == "car"
    x = torch.rand(3, 3, 70, 130)
    probs = seg.predict_proba(x)
    assert probs.shape == (3, 19, 70, 130)
    torch.testing.assert_close(probs.sum(1), torch.ones(3, 70, 130), atol=1e-4, rtol=0)
    labels, conf = seg.predict(x)
    assert labels.shape == (3, 70, 130) and torch.equal(conf, probs.max(1).values)
    # batching does not change results
    seg.batch_size = 1
    torch.testing.assert_close(seg.predict_proba(x), probs, atol=1e-5, rtol=0)
    # same init seed -> same weights -> same output
    torch.testing.assert_close(build_model(name).predict_proba(x[:1]), probs[:1], atol=1e-5, rtol=0)


def test_segformer_loads_a_local_directory_with_its_image_processor(tmp_path):
    from transformers import SegformerImageProcessor

    seg = build_model("tiny_segformer")
    seg.module.save_pretrained(tmp_path)
    SegformerImageProcessor(size={"height": 64, "width": 64}, image_mean=[0.5] * 3, image_std=[0.25] * 3).save_pretrained(tmp_path)
    loaded = build_model("segformer_b5", path=str(tmp_path))
    assert loaded.pre.size == {"height": 64, "width": 64}
    assert loaded.pre.mean.flatten().tolist() == [0.5] * 3
    x = torch.rand(1, 3, 40, 80)
    assert loaded.predict_proba(x).shape == (1, 19, 40, 80)
    # the weights really came from the directory
    for a, b in zip(seg.module.state_dict().values(), loaded.module.state_dict().values()):
        assert torch.equal(a, b)


def test_mask2former_loads_a_local_directory(tmp_path):
    seg = build_model("tiny_mask2former")
    seg.module.save_pretrained(tmp_path)
    loaded = build_model("mask2former_swin_s", path=str(tmp_path))
    x = torch.rand(1, 3, 48, 96)
    torch.testing.assert_close(loaded.predict_proba(x), seg.predict_proba(x), atol=1e-5, rtol=0)


def test_offline_hub_error_names_hub_id_and_model_path(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(ModelError) as exc:
        build_model("segformer_b5")
    msg = str(exc.value)
    assert "nvidia/segformer-b5-finetuned-cityscapes-1024-1024" in msg and "model.path=" in msg
    assert "\n" not in msg
    with pytest.raises(ModelError, match="model.path=.*is not a directory"):
        build_model("mask2former_swin_l", path="/nonexistent/dir")


def test_checkpoint_with_another_label_space_is_refused(tmp_path):
    from transformers import SegformerConfig, SegformerForSemanticSegmentation

    cfg = model_config("tiny_segformer")["arch"]
    SegformerForSemanticSegmentation(SegformerConfig(num_labels=150, **cfg)).save_pretrained(tmp_path)
    with pytest.raises(ModelError, match="150 classes"):
        build_model("segformer_b0", path=str(tmp_path))


def test_hub_ids_are_the_papers():
    ids = {n: model_config(n)["hub_id"] for n in ("segformer_b0", "segformer_b2", "segformer_b5", "mask2former_swin_s", "mask2former_swin_l")}
    assert ids["segformer_b2"] == "nvidia/segformer-b2-finetuned-cityscapes-1024-1024"
    assert ids["mask2former_swin_l"] == "facebook/mask2former-swin-large-cityscapes-semantic"
    assert ids == {
        "segformer_b0": "nvidia/segformer-b0-finetuned-cityscapes-1024-1024",
        "segformer_b2": "nvidia/segformer-b2-finetuned-cityscapes-1024-1024",
        "segformer_b5": "nvidia/segformer-b5-finetuned-cityscapes-1024-1024",
        "mask2former_swin_s": "facebook/mask2former-swin-small-cityscapes-semantic",
        "mask2former_swin_l": "facebook/mask2former-swin-large-cityscapes-semantic",
    }
