"""The Cityscapes-val check through the real CLI on a tiny tree with the real file naming: IoU against an
independent numpy computation, MLflow nested runs, the cache, and bad input as one-line errors."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from pairedgta.cityscapes import CLASS_NAMES
from pairedgta.errors import ConfigError
from pairedgta.models import build_model
from pairedgta.testing.cli import mlflow_store, run_cli

# (city, seq, frame, which ground-truth files exist)
FRAMES = [
    ("frankfurt", "000000", "000294", "both"),      # labelTrainIds wins; its labelIds file holds garbage
    ("frankfurt", "000001", "007973", "trainIds"),
    ("lindau", "000000", "000019", "labelIds"),     # only labelIds: mapped to train ids
]
SIZE = (64, 32)
# the Cityscapes label ids of the 19 train ids, and label ids that are not evaluated
TRAIN_TO_LABEL = [7, 8, 11, 12, 13, 17, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 31, 32, 33]
VOID_LABEL_IDS = [0, 1, 3, 4, 5, 6, 9, 10, 14, 15, 16, 18, 29, 30]
BAD_CASES = {
    "missing_root": "does not exist",
    "no_images": "holds no",
    "missing_gt": "lindau_000000_000019_leftImg8bit.png has no ground truth",
    "size_mismatch": "label map is 32x16 but its image",
}


def frame_id(city, seq, frame):
    return f"{city}_{seq}_{frame}"


def write_tree(root: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random images; labels = the tiny model's prediction with some pixels changed and some void, so
    every IoU is somewhere between 0 and 1. Returns (image, train ids) per frame in sorted order."""
    model = build_model("tiny_segformer")
    rng = np.random.default_rng(0)
    truth = []
    for city, seq, frame, gt in FRAMES:
        fid = frame_id(city, seq, frame)
        img_dir, gt_dir = root / "leftImg8bit" / "val" / city, root / "gtFine" / "val" / city
        img_dir.mkdir(parents=True, exist_ok=True)
        gt_dir.mkdir(parents=True, exist_ok=True)
        image = rng.integers(0, 256, size=(SIZE[1], SIZE[0], 3), dtype=np.uint8)
        Image.fromarray(image).save(img_dir / f"{fid}_leftImg8bit.png")
        train_ids = model.predict(image[None])[0][0].numpy().astype(np.uint8)
        noise = rng.random(train_ids.shape)
        train_ids[noise < 0.3] = rng.integers(0, 19, size=int((noise < 0.3).sum()))
        train_ids[noise > 0.9] = 255
        if gt in ("both", "trainIds"):
            Image.fromarray(train_ids).save(gt_dir / f"{fid}_gtFine_labelTrainIds.png")
        if gt == "both":
            garbage = rng.integers(0, 34, size=train_ids.shape, dtype=np.uint8)
            Image.fromarray(garbage).save(gt_dir / f"{fid}_gtFine_labelIds.png")
        if gt == "labelIds":
            label_ids = np.array(TRAIN_TO_LABEL, dtype=np.uint8)[np.minimum(train_ids, 18)]
            void = train_ids == 255
            label_ids[void] = rng.choice(VOID_LABEL_IDS, size=int(void.sum()))
            Image.fromarray(label_ids).save(gt_dir / f"{fid}_gtFine_labelIds.png")
        # the other gtFine files of a real download are ignored
        Image.new("RGBA", SIZE).save(gt_dir / f"{fid}_gtFine_color.png")
        (gt_dir / f"{fid}_gtFine_polygons.json").write_text("{}")
        truth.append((image, train_ids))
    return truth


def args_for(root: Path, tmp: Path, tracking: bool) -> list[str]:
    args = ["+experiment=cityscapes_val_check", f"dataset.root={root}", "models=[tiny_segformer]",
            f"cache_dir={tmp / 'cache'}"]
    return args + ([f"tracking.uri={mlflow_store(tmp / 'mlflow.db')}"] if tracking else ["tracking.enabled=false"])


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("cityscapes")
    return root, write_tree(root)


@pytest.fixture(scope="module")
def bad_runs(tree, tmp_path_factory):
    """Every bad-input case through the CLI's entry point (in-process: the errors come before any model
    runs, so a fresh interpreter would only add its start-up)."""
    good, _ = tree
    runs = {}
    for case in BAD_CASES:
        tmp = tmp_path_factory.mktemp(case)
        root = tmp / "cityscapes"
        if case != "missing_root":
            shutil.copytree(good, root)
        if case == "no_images":
            shutil.rmtree(root / "leftImg8bit" / "val")
        if case == "missing_gt":
            (root / "gtFine" / "val" / "lindau" / "lindau_000000_000019_gtFine_labelIds.png").unlink()
        if case == "size_mismatch":
            gt_dir = root / "gtFine" / "val" / "frankfurt"
            Image.new("L", (32, 16)).save(gt_dir / "frankfurt_000001_007973_gtFine_labelTrainIds.png")
        runs[case] = (tmp, run_cli(args_for(root, tmp, tracking=False), tmp))
    return runs


def independent_iou(truth: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, float]:
    model = build_model("tiny_segformer")
    conf = np.zeros((19, 19), dtype=np.int64)
    for image, gt in truth:
        pred = model.predict(image[None])[0][0].numpy()
        keep = gt != 255
        conf += np.bincount(gt[keep].astype(np.int64) * 19 + pred[keep], minlength=19 * 19).reshape(19, 19)
    tp = np.diag(conf).astype(float)
    union = conf.sum(0) + conf.sum(1) - tp
    iou = np.full(19, np.nan)
    iou[union > 0] = tp[union > 0] / union[union > 0]
    return iou, float(np.nanmean(iou))


@pytest.mark.slow
def test_check_matches_numpy_logs_to_mlflow_and_caches(tree, bad_runs, tmp_path):
    # bad_runs: requested so the error cases run alongside this one
    root, truth = tree
    proc = run_cli(args_for(root, tmp_path, tracking=True), tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = [p for p in (tmp_path / "cache" / "cityscapes_val").iterdir() if not p.name.startswith(".")]
    assert len(results) == 1 and f"results: {results[0]}" in proc.stdout
    out = results[0]

    iou, miou = independent_iou(truth)
    csv = pd.read_csv(out / "iou.csv")
    assert list(csv.columns) == ["model", "class_id", "class_name", "iou"]
    assert csv.class_id.tolist() == list(range(19)) + [-1] and csv.class_name.iloc[-1] == "mean"
    assert set(csv.model) == {"tiny_segformer"} and csv.class_name.iloc[11] == "person"
    np.testing.assert_allclose(csv.iou.to_numpy()[:19], iou, equal_nan=True)
    assert csv.iou.iloc[-1] == pytest.approx(miou) and 0 < miou < 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_images"] == 3 and summary["label_files"] == {"trainIds": 2, "labelIds": 1}
    assert summary["miou"] == pytest.approx(miou) and summary["published_miou"] is None
    labelled = sum(int((gt != 255).sum()) for _, gt in truth)
    assert summary["evaluated_pixels"] == labelled and 0 < summary["pixel_accuracy"] < 1

    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("cityscapes_val_check")
    nested = [r for r in client.search_runs([exp.experiment_id]) if r.data.tags.get("mlflow.parentRunId")]
    assert [r.data.tags["model"] for r in nested] == ["tiny_segformer"]
    assert nested[0].info.run_name.startswith("cityscapes_val_check \u00b7 tiny_segformer \u00b7 cityscapes")
    metrics = nested[0].data.metrics
    assert metrics["cityscapes_val/miou"] == pytest.approx(miou)
    for k, name in enumerate(CLASS_NAMES):  # NaN classes (absent from labels and predictions) are not logged
        assert metrics.get(f"cityscapes_val/iou/{name}", np.nan) == pytest.approx(iou[k], nan_ok=True)
    arts = {a.path for a in client.list_artifacts(nested[0].info.run_id, "cityscapes_val")}
    assert {"cityscapes_val/iou.csv", "cityscapes_val/summary.json"} <= arts

    # a rerun is a cache hit: nothing recomputed, the same numbers logged again
    before = (out / "iou.csv").stat().st_mtime_ns
    again = run_cli(args_for(root, tmp_path, tracking=True), tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "cityscapes_val [tiny_segformer]: cache hit" in again.stdout
    assert (out / "iou.csv").stat().st_mtime_ns == before
    entries = list((tmp_path / "cache" / "cityscapes_val").iterdir())
    assert [p for p in entries if not p.name.startswith(".")] == [out]
    assert not [p for p in entries if p.name.startswith(".tmp-")]
    runs = [r for r in client.search_runs([exp.experiment_id]) if r.data.tags.get("mlflow.parentRunId")]
    assert sorted(r.data.tags["cache_hit"] for r in runs) == ["False", "True"]
    assert all(r.data.metrics["cityscapes_val/miou"] == pytest.approx(miou) for r in runs)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_is_a_one_line_error(bad_runs, case):
    tmp, proc = bad_runs[case]
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and BAD_CASES[case] in errors[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert not (tmp / "cache" / "cityscapes_val").exists()  # found before any model ran


def test_scale_options_and_preprocessing_warning(tree):
    from pairedgta.datasets.cityscapes import open_cityscapes
    from pairedgta.evaluation.cityscapes_val import preprocessing_warning

    root, truth = tree
    ds = open_cityscapes(root=str(root), split="val", max_images=2, scale=0.5)
    assert [s.frame_id for s in ds.samples] == ["frankfurt_000000_000294", "frankfurt_000001_007973"]
    image, label = ds.load(ds.samples[1])
    assert image.shape == (16, 32, 3) and label.shape == (16, 32)
    assert set(np.unique(label)) <= set(np.unique(truth[1][1]))  # nearest: no invented label values
    full = open_cityscapes(root=str(root))
    np.testing.assert_array_equal(full.load(full.samples[2])[1], truth[2][1])  # labelIds -> train ids
    for bad in ({"scale": 2.0}, {"scale": 0}, {"max_images": 0}, {"split": "../val"}):
        with pytest.raises(ConfigError):
            open_cityscapes(root=str(root), **bad)
    assert "check preprocessing" in preprocessing_warning("segformer_b0", 0.2)
    assert preprocessing_warning("segformer_b0", 0.5) is None and preprocessing_warning("tiny_segformer", 0.0) is None
