"""The detection zoo (task=detection): every member ships float16 weights with a model card and a model config,
loads strictly and detects on a render; task=detection runs all of them against the reference."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from safetensors import safe_open

from pairedgta.models import build_model, model_config, model_kind
from pairedgta.testing.cli import compose_cfg

WEIGHTS = Path(__file__).resolve().parents[1] / "pairedgta" / "models" / "weights"


def members() -> list[str]:
    return sorted(d.name for d in WEIGHTS.iterdir() if d.is_dir() and not d.name.startswith(("_", "."))
                  and model_kind(model_config(d.name)) == "detector")


def test_every_member_is_float16_carded_loaded_and_run_by_the_task():
    names = members()
    assert len(names) >= 8 and len({model_config(n)["family"] for n in names}) >= 3
    cfg = compose_cfg(["task=detection"])
    assert sorted(cfg.models) == names and cfg.reference_model == "demo_det_reference"
    image = np.random.default_rng(0).integers(0, 256, (1, 256, 512, 3), dtype=np.uint8)
    for name in names:
        folder = WEIGHTS / name
        with safe_open(str(folder / "model.safetensors"), "pt") as f:
            assert {str(f.get_tensor(k).dtype) for k in f.keys()} <= {"torch.float16", "torch.int64"}, name
        card = json.loads((folder / "model_card.json").read_text())
        assert card and (folder / "README.md").read_text().strip(), name
        detector = build_model(name)
        (d,) = detector.detect(image)
        assert d.boxes.shape[1:] == (4,) and len(d.scores) == len(d.labels) <= 100, name
        assert 0.0 < detector.score_threshold < 1.0
