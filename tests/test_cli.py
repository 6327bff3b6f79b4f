"""The CLI as a user runs it: the smoke experiment end to end, and bad input as one-line errors."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from pairedgta.metrics import ReferenceConsistency, prediction_mass, rho_valid
from pairedgta.models import build_segmenter
from pairedgta.testing.cli import mlflow_store, run_cli
from pairedgta.testing.datasets import write_release


def stage_dirs(cache: Path) -> set[str]:
    return {str(p.relative_to(cache)) for p in cache.glob("*/[!.]*")} if cache.exists() else set()


@pytest.mark.slow
def test_smoke_experiment_end_to_end(tmp_path):
    cache = tmp_path / "cache"
    db = tmp_path / "mlflow.db"
    proc = run_cli(["+experiment=smoke", f"cache_dir={cache}", f"tracking.uri={mlflow_store(db)}",
                    "generate.num_scenes=3", "metric.bootstrap.resamples=50",
                    # the conditions the checks below read and one more adverse one (a third of the paper's nine:
                    # a third of the rendering and inference); every figure; one condition's grid (6 s less)
                    "conditions.only=[Day-EXTRASUNNY,Night-EXTRASUNNY,Day-RAIN]",
                    "plot.qualitative_conditions=[Night-EXTRASUNNY]"],
                   tmp_path, subprocess_=True)  # true end to end
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "results: " in proc.stdout
    evals = {json.loads((p / "manifest.json").read_text())["config"]["model"]["name"]: p
             for p in (cache / "evaluate").iterdir() if not p.name.startswith(".")}
    assert set(evals) == {"tiny_segformer", "tiny_mask2former"}
    for name in ("xi.csv", "pixel_agreement.csv", "frame_counts.csv", "rho_valid.csv", "gt_iou.csv"):
        assert (evals["tiny_mask2former"] / name).is_file()
    plots = [p for p in (cache / "plot").iterdir() if not p.name.startswith(".")]
    assert {"xi_table_tiny_segformer.png", "xi_table_tiny_mask2former.pdf", "ranking.png"} <= {p.name for p in plots[0].iterdir()}

    # recompute the numbers independently from the cached dataset, pseudo-labels and the model
    gen = next(p for p in (cache / "generate").iterdir() if not p.name.startswith("."))
    pseudo = next(p for p in (cache / "pseudolabel").iterdir() if not p.name.startswith("."))
    model = build_segmenter("tiny_mask2former")
    xi_night = ReferenceConsistency(19, 255)
    clean_mass, adv_mass = [], []
    for scene in sorted((gen / "scenes").iterdir()):
        ref = np.asarray(Image.open(pseudo / "labels" / f"{scene.name}.png"))
        imgs = [np.asarray(Image.open(scene / f"{c}.png")) for c in ("Day-EXTRASUNNY", "Night-EXTRASUNNY")]
        probs = model.predict_proba(np.stack(imgs))
        xi_night.update(torch.from_numpy(ref.astype(np.int64)), probs[1].argmax(0))
        clean_mass.append(int(prediction_mass(probs[0], 13, 0.9)))
        adv_mass.append(int(prediction_mass(probs[1], 13, 0.9)))
    xi = pd.read_csv(evals["tiny_mask2former"] / "xi.csv")
    night = xi[(xi.condition == "Night-EXTRASUNNY") & (xi.reference_model == "tiny_segformer") & (xi.class_id >= 0)]
    np.testing.assert_allclose(night.xi.to_numpy(), xi_night.compute().numpy(), equal_nan=True)
    counts = pd.read_csv(evals["tiny_mask2former"] / "frame_counts.csv")
    car = counts[(counts.condition == "Night-EXTRASUNNY") & (counts.class_name == "car")].sort_values("pair_id")
    assert car.clean_count.tolist() == clean_mass and car.adv_count.tolist() == adv_mass
    rho = pd.read_csv(evals["tiny_mask2former"] / "rho_valid.csv")
    r = rho[(rho.condition == "Night-EXTRASUNNY") & (rho.class_name == "car") & (rho.selection == "top_m")].rho.item()
    np.testing.assert_equal(r, rho_valid(clean_mass, adv_mass, m=25))

    # MLflow: one parent run (with the job's Hydra config), a nested run per model holding the same numbers
    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=f"sqlite:///{db}")
    exp = client.get_experiment_by_name("smoke")
    # the results lines say where to look: the UI's runs of this experiment, not its GenAI overview
    assert (f"  mlflow: mlflow ui --backend-store-uri sqlite:///{db}, then "
            f"http://127.0.0.1:5000/#/experiments/{exp.experiment_id}?workflowType=machine_learning") in proc.stdout
    runs = client.search_runs([exp.experiment_id])
    nested = {r.data.tags["model"]: r for r in runs if r.data.tags.get("mlflow.parentRunId")}
    assert len(runs) == 3 and set(nested) == {"tiny_segformer", "tiny_mask2former"}
    dataset = f"generated@{gen.name[:8]}"
    assert nested["tiny_mask2former"].info.run_name == f"smoke \u00b7 tiny_mask2former \u00b7 {dataset}"
    (parent,) = [r for r in runs if not r.data.tags.get("mlflow.parentRunId")]
    assert parent.info.run_name == f"smoke \u00b7 tiny_segformer, tiny_mask2former \u00b7 {dataset}"
    hydra_files = {a.path for a in client.list_artifacts(parent.info.run_id, "hydra")}
    assert {"hydra/config.yaml", "hydra/overrides.yaml", "hydra/hydra.yaml"} <= hydra_files
    assert "+experiment=smoke" in parent.data.tags["pairedgta.overrides"]
    logged = nested["tiny_mask2former"].data.metrics
    supported = (night.images >= 3) & (night.reference_pixels >= 1000) & night.xi.notna()  # metric=strict's rule
    assert night.in_mean.tolist() == supported.tolist()
    mean = night[supported].xi.mean()
    assert logged["xi_mean/Night-EXTRASUNNY"] == pytest.approx(mean)
    # the headline condition's rho per class; per-condition, per-class metrics only with tracking.class_metrics
    assert logged.get("rho_valid/top_m/car", math.nan) == pytest.approx(r, nan_ok=True)  # NaN is not logged
    assert not [k for k in logged if k.startswith(("xi/", "xi_gt/")) or k.count("/") == 3]
    arts = {a.path for a in client.list_artifacts(nested["tiny_mask2former"].info.run_id, "evaluate")}
    assert "evaluate/xi.csv" in arts


@pytest.mark.slow
@pytest.mark.parametrize(
    "case",
    ["missing_root", "empty_root", "corrupt_png", "size_mismatch", "unknown_condition", "unknown_model"],
)
def test_bad_input_is_a_one_line_error_and_leaves_no_cache(tmp_path, case):
    root = tmp_path / "PairedGTA"
    args = ["+experiment=evaluate_release", f"dataset.root={root}", "model=tiny_segformer",
            "reference_model=tiny_segformer", f"cache_dir={tmp_path / 'cache'}", "tracking.enabled=false"]
    expect = {"missing_root": "does not exist", "empty_root": "holds no", "corrupt_png": "not a readable image",
              "size_mismatch": "differ in size", "unknown_condition": "unknown condition",
              "unknown_model": "unknown model 'segformer_b9'"}[case]
    if case != "missing_root":
        root.mkdir()
    if case in ("corrupt_png", "size_mismatch", "unknown_condition", "unknown_model"):
        write_release(root, [1, 2])
    if case == "corrupt_png":
        (root / "Night" / "2_Night_RAIN.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
        expect = "2_Night_RAIN.png: not a readable image"
    if case == "size_mismatch":
        Image.new("RGB", (48, 32)).save(root / "Sunset" / "2_Sunset_FOGGY.png")
    if case == "unknown_condition":
        args.append("conditions.only=[Day-EXTRASUNNY,Day-HAIL]")
    if case == "unknown_model":
        args[2] = "models=[segformer_b9]"
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and expect in errors[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    cache = tmp_path / "cache"
    # nothing half-written: no temp dirs, and no stage dir that is not complete
    assert not list(cache.glob("*/.tmp-*"))
    for d in stage_dirs(cache):
        assert (cache / d / "manifest.json").is_file()
    if case in ("corrupt_png", "size_mismatch"):
        # the failure comes while evaluating: no evaluate entry may appear
        assert not (cache / "evaluate").exists() or not list((cache / "evaluate").glob("[!.]*"))


@pytest.mark.slow
def test_a_blank_dataset_is_one_warning_naming_files_and_a_converted_image_another(tmp_path):
    """All-black images once gave xi = 1.0 and agreement 1.0 without a word; a 16-bit image was read silently.
    Now the run (images decoded in DataLoader workers here) says so once per dataset, files named."""
    root = tmp_path / "PairedGTA"
    write_release(root, [1, 2])
    for png in root.rglob("*.png"):
        Image.fromarray(np.zeros((32, 64, 3), np.uint8)).save(png)
    wide = root / "Night" / "2_Night_RAIN.png"
    Image.fromarray(np.zeros((32, 64), np.uint16)).save(wide)  # 16-bit greyscale (and blank too)
    args = ["+experiment=evaluate_release", f"dataset.root={root}", "model=tiny_segformer", "reference_model=tiny_segformer",
            f"cache_dir={tmp_path / 'cache'}", "tracking.enabled=false", "stages=[pseudolabel,evaluate]",
            "evaluate.num_workers=2", "threads=1"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    blank = [line for line in out.splitlines() if "one flat colour" in line]
    assert len(blank) == 1, out[-3000:]
    assert "dataset paired_gta: 18 image(s) are one flat colour (blank): " in blank[0] and "and 15 more" in blank[0]
    assert f"{root / 'Day' / '1_Day_EXTRASUNNY.png'} (all black)" in blank[0]
    converted = [line for line in out.splitlines() if "not 8-bit RGB" in line]
    assert len(converted) == 1 and f"1 image(s) are not 8-bit RGB and were converted on reading: {wide} (I;16" in converted[0]


@pytest.mark.slow
def test_corrupt_hf_weights_from_the_cli_are_one_line(tmp_path):
    from pairedgta.testing.cli import fast_overrides

    weights = tmp_path / "weights"
    build_segmenter("tiny_segformer").module.save_pretrained(weights)
    st = weights / "model.safetensors"
    st.write_bytes(st.read_bytes()[: st.stat().st_size // 2])  # truncated download
    args = [o for o in fast_overrides(tmp_path) if not o.startswith("model=")] + [
        "models=null", "model=segformer_b0", f"model.path={weights}"]
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and f"model.path={weights}" in errors[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert not list((tmp_path / "cache" / "evaluate").glob("[!.]*")) if (tmp_path / "cache" / "evaluate").exists() else True


def test_cuda_without_a_gpu_is_one_line(monkeypatch):
    import torch

    from pairedgta.errors import ConfigError
    from pairedgta.stages.planning import check_cuda

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match="device=cuda: no CUDA GPU is visible here.*use device=cpu"):
        check_cuda("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    check_cuda("cuda:0")
    with pytest.raises(ConfigError, match="device=cuda:3: this machine has 1 CUDA GPU"):
        check_cuda("cuda:3")
    check_cuda("cpu")


@pytest.mark.slow
def test_a_mistyped_key_is_one_line_naming_the_closest_key(tmp_path):
    """Hydra alone says "not in struct" in five lines and advises a `+`, which the tool then refuses."""
    from pairedgta.__main__ import mistyped_key

    for args, expect in ((["generate.num_scene=3"], "generate.num_scene is not a key of pairedgta; did you mean generate.num_scenes?"),
                         (["renderer.exposure.Night=0.3"], "renderer.exposure is now camera.overrides")):
        proc = run_cli(args, tmp_path)
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
        assert proc.returncode == 2 and errors == [f"error: {mistyped_key(args)}"] and expect in errors[0], proc.stderr
    # what README and the experiments type is never flagged
    for args in (["model=demo_segformer", "models=[demo_segformer,demo_ddrnet]", "cache_dir=/x", "generate.shard=range(50)",
                  "hydra/launcher=slurm", "hydra.launcher.partition=p", "model_overrides.segformer_b5.path=/w",
                  "conditions.weathers.FOGGY.visibility_m=100", "renderer.town.blocks=3", "camera=fixed",
                  "camera.compensation=0.2", "metric.rho.clean_condition=Day-RAIN", "plot.robustness.classes=[car]",
                  "cost.csv=/t.csv", "photometry.night_max_luma_ratio=0.3", "-m", "+experiment=zoo"],):
        assert mistyped_key(args) is None
