"""Severity ladders in physical units: transmittance maps, visibility-aware scoring and robustness curves,
end to end on the synthetic backend (in-process CLI runs that share one rendered ladder)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from pairedgta.app import run
from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.testing.cli import compose_cfg, fast_overrides, mlflow_store

pytestmark = pytest.mark.slow  # end to end: the CLI or the stage graph on every test

SKY = CLASS_NAMES.index("sky")
LADDER = ["conditions=fog_ladder", "conditions.only=null", "generate.num_scenes=4", "renderer.width=96",
          "renderer.height=48"]


@pytest.fixture(scope="module")
def ladder(tmp_path_factory):
    """One fog ladder (6 conditions x 4 scenes) evaluated with min_transmittance 0 and 0.2."""
    tmp = tmp_path_factory.mktemp("ladder")
    mlflow_store(tmp / "mlflow.db")  # fast_overrides' store, seeded: tracking is on here
    base = fast_overrides(tmp) + LADDER + ["tracking.enabled=true", "plot.robustness.classes=[road,car]",
                                                 "plot.figures=[robustness]"]
    plain = {**run(compose_cfg(base)), "_cache": tmp / "cache"}
    masked = {**run(compose_cfg(base + ["metric.min_transmittance=0.2"])), "_cache": tmp / "cache"}
    return tmp, plain, masked


def _entry(summary, stage):
    """The cache entry of `stage` (fast_overrides put the cache under the test's folder)."""
    key = next(s["key"] for s in summary["stages"] if s["stage"] == stage)
    return summary["_cache"] / stage / key


def _means(entry: Path) -> pd.DataFrame:
    xi = pd.read_csv(entry / "xi.csv")
    return xi[(xi["class_name"] == "mean") & (xi["reference_model"] != "ground_truth")].set_index("condition")


def test_every_condition_has_a_koschmieder_transmittance_map(ladder):
    _, plain, _ = ladder
    scene = sorted((_entry(plain, "generate") / "scenes").iterdir())[0]
    t = {c: np.asarray(Image.open(scene / f"{c}_transmittance.png")) for c in
         ("Day-EXTRASUNNY", "Day-FOG-1000m", "Day-FOG-300m", "Day-FOG-150m", "Day-FOG-75m")}
    assert all(a.dtype == np.uint16 for a in t.values())
    assert (t["Day-EXTRASUNNY"] == 65535).all()  # clear air hides nothing, not even the sky
    sky = np.asarray(Image.open(scene / "Day-EXTRASUNNY_labels.png")) == SKY
    assert sky.any() and (t["Day-FOG-300m"][sky] == 0).all()  # in fog nothing lies behind the sky
    # pixel by pixel: less visibility, less transmittance; and ln T = -3.912 d / V, so halving V doubles ln T
    assert (t["Day-FOG-1000m"] >= t["Day-FOG-300m"]).all() and (t["Day-FOG-300m"] >= t["Day-FOG-150m"]).all()
    ok = (t["Day-FOG-300m"] > 6000) & (t["Day-FOG-300m"] < 65000)
    assert ok.sum() > 50
    ratio = np.log(t["Day-FOG-150m"][ok] / 65535) / np.log(t["Day-FOG-300m"][ok] / 65535)
    assert np.allclose(ratio, 2.0, atol=0.02)


def test_min_transmittance_scores_only_what_the_air_leaves_visible(ladder):
    _, plain, masked = ladder
    a, b = _means(_entry(plain, "evaluate")), _means(_entry(masked, "evaluate"))
    assert (a["min_transmittance"] == 0.0).all() and (b["min_transmittance"] == 0.2).all()  # xi.csv says which
    assert a.loc["Day-EXTRASUNNY", "reference_pixels"] == b.loc["Day-EXTRASUNNY", "reference_pixels"]
    steps = ["Day-FOG-1000m", "Day-FOG-600m", "Day-FOG-300m", "Day-FOG-150m", "Day-FOG-75m"]
    kept = [b.loc[c, "reference_pixels"] for c in steps]
    assert all(k < a.loc[c, "reference_pixels"] for k, c in zip(kept, steps))  # the sky goes at once
    assert kept == sorted(kept, reverse=True) and kept[-1] < kept[0]  # denser fog hides more
    # the generate, pseudolabel entries are shared; only the evaluation differs
    assert _entry(plain, "generate") == _entry(masked, "generate")
    assert _entry(plain, "evaluate") != _entry(masked, "evaluate")


def test_robustness_curves_breaking_points_and_mlflow(ladder):
    tmp, plain, _ = ladder
    plot = _entry(plain, "plot")
    for name in ("robustness.png", "robustness.csv", "robustness_breaking_points.csv", "robustness_breaking_points.md",
                 "robustness_classes.png", "robustness_classes.csv"):
        assert (plot / name).is_file(), name
    curves = pd.read_csv(plot / "robustness.csv")
    assert list(curves["tick"].unique()) == ["clear", "1000 m", "600 m", "300 m", "150 m", "75 m"]
    assert set(curves["parameter"]) == {"visibility_m"}
    breaks = pd.read_csv(plot / "robustness_breaking_points.csv").set_index("model")
    means = _means(_entry(plain, "evaluate"))
    steps = [c for c in curves.sort_values("step")["condition"].unique() if c != "Day-EXTRASUNNY"]
    first = next((c for c in steps if means.loc[c, "xi"] < 0.5), "none")
    row = breaks.loc["tiny_segformer"]
    assert row["condition"] == first
    metrics = json.loads((plot / "metrics.json").read_text())
    if first != "none":
        assert row["value"] == float(first.split("-")[-1].rstrip("m"))
        assert metrics["breaking_point/tiny_segformer"] == row["value"]
    else:
        assert math.isnan(row["value"]) and "breaking_point/tiny_segformer" not in metrics
    # GT exists on the synthetic backend: rPC is mIoU(step) / mIoU(clean)
    clean = curves[curves["condition"] == "Day-EXTRASUNNY"]["gt_miou"].iloc[0]
    assert np.allclose(curves["rpc"], curves["gt_miou"] / clean)
    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{tmp / 'mlflow.db'}")
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    logged = {k for r in runs for k in r.data.metrics}
    assert ("breaking_point/tiny_segformer" in logged) is (first != "none")


def test_a_break_threshold_above_every_step_breaks_at_the_first_step(ladder):
    tmp, _, _ = ladder
    summary = {**run(compose_cfg(fast_overrides(tmp) + LADDER + ["tracking.enabled=true", "plot.robustness.break_below=1.0",
                                                                "plot.figures=[robustness]"])), "_cache": tmp / "cache"}
    breaks = pd.read_csv(_entry(summary, "plot") / "robustness_breaking_points.csv")
    assert breaks["condition"].tolist() == ["Day-FOG-1000m"] and breaks["value"].tolist() == [1000.0]


def test_a_grid_that_is_no_ladder_draws_no_curve(tmp_path):
    summary = {**run(compose_cfg(fast_overrides(tmp_path) + ["plot.figures=[robustness]"])), "_cache": tmp_path / "cache"}
    assert not list(_entry(summary, "plot").glob("robustness*"))
