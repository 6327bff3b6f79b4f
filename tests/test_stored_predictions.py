"""The figures show evaluate's own predictions (issue 58: the qualitative grid predicted every shown group
again): predictions.npz keeps the label maps and the max probability at half resolution, the qualitative grid and
the model report read them, and an entry written before it kept the confidence is predicted again."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from pairedgta.evaluation.counting import confidence_thumbnail
from pairedgta.evaluation.entry import CONFIDENCE_STEP, PREDICTIONS, read_prediction, write_predictions


def test_confidence_thumbnail_averages_quantises_and_keeps_odd_borders():
    c = torch.tensor([[[0.0, 1.0, 0.5], [1.0, 0.0, 0.5], [0.2, 0.2, float("nan")]]])
    t = confidence_thumbnail(c)
    assert CONFIDENCE_STEP == 2 and t.dtype == torch.uint8 and t.shape == (1, 2, 2)
    # the 2x2 block's mean; a border block averages the pixels it has; NaN (reported by check_finite) reads 0
    assert t.tolist() == [[[128, 128], [51, 0]]]


def test_read_prediction(tmp_path):
    labels = np.arange(12, dtype=np.uint8).reshape(3, 4)
    conf = np.full((2, 2), 204, np.uint8)
    write_predictions(tmp_path / PREDICTIONS, [{"group_id": "a", "pred": {"Day-RAIN": labels},
                                                "conf": {"Day-RAIN": conf}},
                                               {"group_id": "b", "pred": {"Day-RAIN": labels}}],
                      ["Day-EXTRASUNNY", "Day-RAIN"])
    got, c = read_prediction(tmp_path / PREDICTIONS, "a", "Day-RAIN")
    assert np.array_equal(got, labels) and c.shape == (2, 2) and np.allclose(c, 0.8)
    assert read_prediction(tmp_path / PREDICTIONS, "a", "Day-EXTRASUNNY") is None  # the image is absent
    assert read_prediction(tmp_path / PREDICTIONS, "b", "Day-RAIN")[1] is None  # written without the confidence
    assert read_prediction(tmp_path / PREDICTIONS, "c", "Day-RAIN") is None
    assert read_prediction(tmp_path / "none.npz", "a", "Day-RAIN") is None


@pytest.mark.slow
def test_the_qualitative_grid_shows_evaluates_maps_without_predicting(tmp_path, monkeypatch):
    import pairedgta.models as models
    from pairedgta.testing.cli import fast_overrides, run_cli

    over = [a for a in fast_overrides(tmp_path) if a != "model=tiny_segformer"]  # model= would replace the list
    over += ["models=[tiny_segformer,tiny_pidnet]", "plot.figures=[qualitative]"]
    first = run_cli(over, tmp_path)
    assert first.returncode == 0, first.stderr
    built: list[str] = []
    build = models.build_model

    def counting(model, device=None, **kw):
        built.append(dict(model)["name"])
        return build(model, device=device, **kw)

    monkeypatch.setattr(models, "build_model", counting)
    r = run_cli(over + ["force=[plot]"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert built == []  # every map shown came from the evaluate entries
    plot = next(p for p in (tmp_path / "cache" / "plot").iterdir() if (p / "qualitative.csv").is_file())
    q = pd.read_csv(plot / "qualitative.csv")
    np.testing.assert_allclose(q.agreement_recomputed, q.agreement, atol=1e-6)  # the maps evaluate scored
    # an entry from before the confidence was kept: its shown images are predicted again, the same figure
    for entry in (tmp_path / "cache" / "evaluate").iterdir():
        path = entry / PREDICTIONS
        if path.is_file():
            with np.load(path) as z:
                kept = {k: z[k] for k in z.files if not (k[0] == "c" and k[1:].isdigit())}
            np.savez_compressed(path, **kept)
    r = run_cli(over + ["force=[plot]"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert sorted(set(built)) == ["tiny_pidnet", "tiny_segformer"]
    again = pd.read_csv(plot / "qualitative.csv")
    np.testing.assert_allclose(again.agreement_recomputed, q.agreement_recomputed, atol=1e-3)
