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
from pairedgta.models import build_model
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
                   tmp_path)  # the CLI's entry in-process (tests/test_packaging.py runs it in a fresh interpreter)
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
    model = build_model("tiny_mask2former")
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
    # the decoding workers' fork server already running, started before this run (by an earlier run of the same
    # process): its workers inherit its environment, not the run's, and once lost their notes (2 of 18 said)
    from pairedgta.evaluation.inputs import start_workers_server

    start_workers_server(2)
    proc = run_cli(args, tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    blank = [line for line in out.splitlines() if "one flat colour" in line]
    assert len(blank) == 1, out[-3000:]
    assert "dataset paired_gta: 18 image(s) are one flat colour (blank): " in blank[0] and "and 15 more" in blank[0]
    assert f"{root / 'Day' / '1_Day_EXTRASUNNY.png'} (all black)" in blank[0]
    converted = [line for line in out.splitlines() if "not 8-bit RGB" in line]
    assert len(converted) == 1 and f"1 image(s) are not 8-bit RGB and were converted on reading: {wide} (I;16" in converted[0]


def _read_only_dir(path: Path) -> None:
    """A directory nobody may write into, even root: immutable where chattr works, else mode 555."""
    import os
    import subprocess

    path.mkdir()
    if os.geteuid() == 0:
        subprocess.run(["chattr", "+i", str(path)], check=True, capture_output=True)
    else:
        path.chmod(0o555)


def _writable_again(path: Path) -> None:
    import os
    import subprocess

    if path.exists():
        if os.geteuid() == 0:
            subprocess.run(["chattr", "-i", str(path)], capture_output=True)
        path.chmod(0o755)


BAD_CONFIG = {
    # case: (overrides, text the one error line must hold)
    "cache_dir_is_a_file": (["cache_dir={tmp}/afile"], "is a file, not a directory"),
    "cache_dir_under_a_file": (["cache_dir={tmp}/afile/cache"], "is a file, not a directory"),
    "cache_dir_under_proc": (["cache_dir=/proc/pairedgta-cache"], "cache_dir=/proc/pairedgta-cache is under /proc"),
    "cache_dir_read_only": (["cache_dir={tmp}/ro/cache"], "is not writable"),
    "unknown_added_key": (["+bogus_key=3"], "+bogus_key: no part of pairedgta reads this key"),
    "unknown_added_nested_key": (["+generate.num_scene=3"], "+generate.num_scene: no part of pairedgta reads this key"),
    "stage_folder_is_a_file": (["cache_dir={tmp}/filled"], "filled/evaluate is a file, but the evaluate stage keeps"),
    "width_zero": (["renderer.width=0"], "renderer.width=0 is out of range"),
    "height_negative": (["renderer.height=-3"], "renderer.height=-3 is out of range"),
    "num_scenes_not_a_number": (["generate.num_scenes=abc"], "generate.num_scenes='abc' is not a number"),
    "num_scenes_zero": (["generate.num_scenes=0"], "generate.num_scenes=0 is out of range"),
    "dpi_zero": (["plot.dpi=0"], "plot.dpi=0 is out of range"),
    "unknown_format": (["plot.formats=[bmpx]"], "plot.formats=['bmpx']: unknown format(s) ['bmpx']"),
    "confidence_above_one": (["metric.bootstrap.confidence=1.5"], "metric.bootstrap.confidence=1.5 is out of range"),
    "negative_resamples": (["metric.bootstrap.resamples=-5"], "metric.bootstrap.resamples=-5 is out of range"),
    "batch_size_zero": (["evaluate.batch_size=0"], "evaluate.batch_size=0 is out of range"),
    "tau_above_one": (["pseudolabel.tau=1.5"], "pseudolabel.tau=1.5 is out of range"),
    "unknown_reference_model": (["reference_model=segformer_b9"], "reference_model: unknown model 'segformer_b9'"),
    "unknown_qualitative_condition": (["plot.qualitative_conditions=[Night-HAIL]"],
                                      "plot.qualitative_conditions: unknown condition(s) ['Night-HAIL']"),
    "unknown_ranking_condition": (["plot.ranking.condition=Dusk-RAIN"], "plot.ranking.condition='Dusk-RAIN' is not a condition"),
    "zero_threads": (["threads=0"], "threads=0 is out of range"),
    "unknown_sampling": (["evaluate.sampling=one"], "evaluate.sampling='one'; use one of all, random_one"),
    "sampling_seed_not_a_number": (["evaluate.sampling_seed=abc"], "evaluate.sampling_seed='abc' is not a number"),
    "unknown_convention": (["metric.convention=lenient"], "metric.convention='lenient'; use one of paper, strict"),
    "unknown_absent_policy": (["metric.absent=skip"], "metric.absent='skip'; use one of nan, zero"),
    "unknown_agreement": (["metric.agreement=median"], "metric.agreement='median'; use one of pooled, per_image"),
    "unknown_mean_exclude_class": (["metric.mean_exclude=[tram]"], "metric.mean_exclude: unknown class(es) ['tram']"),
    "headline_not_selected": (["metric.rho.headline=nonzero", "metric.rho.selections=[top_m]"],
                              "metric.rho.headline='nonzero' is not among metric.rho.selections=['top_m']"),
    "num_scenes_astronomical": (["generate.num_scenes=1e20"], "generate.num_scenes=1e+20 is out of range"),
    "fov_zero": (["generate.camera.fov=0"], "generate.camera.fov=0 is out of range; use a horizontal field of view"),
    "fov_wider_than_a_half_turn": (["generate.camera.fov=270"], "generate.camera.fov=270 is out of range"),
    "negative_noise": (["renderer.noise_std=-5"], "renderer.noise_std=-5 is out of range"),
    "zero_trace_distance": (["renderer.max_distance=0"], "renderer.max_distance=0 is out of range"),
    "no_stages": (["stages=[]"], "stages=[] runs nothing"),
    "only_without_the_reference": (["conditions.only=[Day-RAIN,Night-EXTRASUNNY]"],
                                   "leaves out the reference condition Day-EXTRASUNNY"),
    "unknown_ranking_class": (["plot.ranking.classes=[unicorn]"], "plot.ranking.classes: unknown class(es) ['unicorn']"),
    "unknown_rho_class": (["metric.rho.classes=[unicorn]"], "metric.rho.classes: unknown class(es) ['unicorn']"),
    "negative_min_images": (["metric.min_images=-1"], "metric.min_images=-1 is invalid"),
    "two_channel_mean": (["model.mean=[0.5,0.5]"], "mean=[0.5, 0.5] must be 3 numbers, one per RGB channel"),
    "zero_std": (["model.std=[0.2,0,0.2]"], "must be 3 numbers > 0"),
    "cache_verify": (["cache.verify=sha"], "cache.verify='sha'; use stat"),
    "min_transmittance_out_of_range": (["metric.min_transmittance=1.5"], "metric.min_transmittance=1.5 is out of range"),
    "min_transmittance_without_maps": (["metric.min_transmittance=0.1", "renderer=deepgtav", "region=los_santos"],
                                       "metric.min_transmittance>0 needs transmittance maps, which renderer=deepgtav"),
    "min_transmittance_on_a_release": (["metric.min_transmittance=0.1", "dataset=paired_gta", "dataset.root={tmp}"],
                                       "which dataset=paired_gta does not have"),
    "unknown_robustness_class": (["plot.robustness.classes=[unicorn]"], "plot.robustness.classes: unknown class(es) ['unicorn']"),
    "break_below_zero": (["plot.robustness.break_below=0"], "plot.robustness.break_below=0 is out of range"),
    "unitless_fog_key": (["+conditions.weathers.FOGGY.fog_density=0.7"], "fog_density is no longer a condition key"),
    "bad_visibility": (["conditions.weathers.FOGGY.visibility_m=-3"], "'Day-FOGGY'.visibility_m=-3"),
    "unknown_tracking_scheme": (["tracking.enabled=true", "tracking.uri=nosuchscheme://x"],
                                "tracking.uri=nosuchscheme://x: unknown scheme 'nosuchscheme'"),
    "tracking_enabled_not_a_boolean": (["tracking.enabled=maybe"], "tracking.enabled='maybe' must be true or false"),
    "tracking_background_not_a_boolean": (["tracking.background=1"], "tracking.background=1 must be true or false"),
    "tracking_class_metrics_not_a_boolean": (["tracking.class_metrics=all"],
                                             "tracking.class_metrics='all' must be true or false"),
    # issue 39's battery: each of these once failed only after generate (and pseudolabel) had written
    "rho_clean_condition_unknown": (["metric.rho.clean_condition=Noon-SNOW"],
                                    "metric.rho.clean_condition='Noon-SNOW' is not a condition"),
    "renderer_backend_unknown": (["renderer.backend=unreal"], "renderer.backend='unreal'; use one of blender"),
    "evaluate_conditions_unknown": (["evaluate.conditions=[Day-SNOW]"], "evaluate.conditions: unknown condition(s) ['Day-SNOW']"),
    "num_workers_negative": (["evaluate.num_workers=-1"], "evaluate.num_workers"),
    "num_workers_words": (["evaluate.num_workers=many"], "evaluate.num_workers"),
    "shard_outside": (["evaluate.num_shards=2", "evaluate.shard=3"], "evaluate.shard=3 is outside 0..1"),
    "objects_min_above_max": (["generate.objects.min=5", "generate.objects.max=2"],
                              "generate.objects.min=5 is above generate.objects.max=2"),
    "objects_negative_distance": (["generate.objects.d_min=-1"], "generate.objects.d_min=-1 is out of range"),
    "impossible_structure_threshold": (["generate.validation.structure_threshold=5"],
                                       "generate.validation.structure_threshold=5 is out of range"),
    "camera_compensation": (["renderer=blender", "region=procedural_town", "camera.compensation=3"],
                            "camera.compensation=3.0 is invalid"),
    # a key added to a group that its option's file does not name once failed (or was ignored) only when
    # generate built the renderer, region or dataset, after it had written to the cache
    "unknown_renderer_key": (["+renderer.colour=red"],
                             "renderer.colour is not a key of renderer=synthetic; its keys are backend, height, max_distance"),
    "unknown_blender_key": (["renderer=blender", "region=procedural_town", "+renderer.colour=red"],
                            "renderer.colour is not a key of renderer=blender; its keys are backend, camera, denoise"),
    "misspelt_renderer_key_forced": (["++renderer.noise_sdt=1"],
                                     "renderer.noise_sdt is not a key of renderer=synthetic; did you mean renderer.noise_std?"),
    "key_of_another_renderer": (["+renderer.port=9000"], "renderer.port is not a key of renderer=synthetic"),
    "misspelt_camera_key": (["camera=dashcam", "+camera.read_nois=0.1"],
                            "camera.read_nois is not a key of camera=dashcam; did you mean camera.read_noise?"),
    "misspelt_metric_key": (["+metric.tau_mas=0.5"], "metric.tau_mas is not a key of metric=strict; did you mean metric.tau_mass?"),
    "unknown_region_key": (["+region.colour=red"], "region.colour is not a key of region=synthetic_street"),
    "unknown_dataset_key": (["+dataset.spilt=val"], "dataset.spilt is not a key of dataset=generated"),
    "misspelt_plot_key": (["+plot.dpii=3"], "+plot.dpii: no part of pairedgta reads this key, so it would be ignored; "
                                            "did you mean plot.dpi?"),
    # the same keys without `+` (Hydra alone: five lines of "not in struct"), checked against the chosen option
    "unknown_renderer_key_unprefixed": (["renderer.colour=red"],
                                        "renderer.colour is not a key of renderer=synthetic; its keys are backend, height"),
    "key_of_another_renderer_unprefixed": (["renderer.samples=4"], "renderer.samples is not a key of renderer=synthetic; "
                                           "its keys are backend, height, max_distance, noise_std, road_half_width, "
                                           "sidewalk_width, width (renderer.samples is a key of renderer=blender)"),
    "key_no_model_reads_unprefixed": (["model.colour=red"], "model.colour is not a key of model=tiny_segformer; its keys are"),
    "unknown_top_level_key": (["colour=red"], "colour is not a key of pairedgta; its top-level keys are cache, cache_dir"),
    "unknown_nested_key_unprefixed": (["metric.bootstrap.sead=3"],
                                      "metric.bootstrap.sead is not a key of pairedgta; did you mean metric.bootstrap.seed?"),
    "unknown_generate_key_unprefixed": (["generate.validation.strict=1"], "generate.validation.strict is not a key of "
                                        "pairedgta; the keys of generate.validation are enabled, structure_threshold"),
    # camera.overrides is open (EV per condition or time name), for the names of the run's grid only
    "camera_override_not_a_condition": (["+camera.overrides.Noon=1.0"], "camera.overrides.Noon is not a condition or "
                                        "time of this run, so no image would use it; use one of Day-EXTRASUNNY, Day-RAIN"),
    "camera_override_left_out_unprefixed": (["camera.overrides.Night-FOGGY=1.0"],
                                            "camera.overrides.Night-FOGGY is not a condition or time of this run"),
}


# The cases the command line itself decides (a key added with `+`, or one Hydra cannot compose: __main__
# reads argv before Hydra does) run through the CLI, with a few value checks to show the CLI's one `error:`
# line and exit code 2 for them too. The other value checks are the run's own (pairedgta.app.run, which the
# CLI calls once Hydra has composed): they run there directly, a third of a CLI run's time (Hydra composes
# twice per run), 57 times.
CLI_CASES = {
    "unknown_added_key", "unknown_added_nested_key", "unknown_renderer_key", "unknown_blender_key",
    "misspelt_renderer_key_forced", "key_of_another_renderer", "misspelt_camera_key", "misspelt_metric_key",
    "unknown_region_key", "unknown_dataset_key", "misspelt_plot_key", "unknown_renderer_key_unprefixed",
    "key_of_another_renderer_unprefixed", "key_no_model_reads_unprefixed", "unknown_top_level_key",
    "unknown_nested_key_unprefixed", "unknown_generate_key_unprefixed", "camera_override_left_out_unprefixed",
    # value checks of the run, through the CLI as well
    "width_zero", "cache_dir_read_only", "rho_clean_condition_unknown", "num_workers_words",
}
# a misspelt name here would never run through the CLI: the module refuses to load instead
assert CLI_CASES <= set(BAD_CONFIG), f"CLI_CASES names no bad-config case: {sorted(CLI_CASES - set(BAD_CONFIG))}"


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(BAD_CONFIG))
def test_bad_config_value_is_one_line_before_any_stage(tmp_path, case):
    """Each bad value stops the run before generation (nothing is computed first), with one line that
    names the key and the value."""
    from pairedgta.app import run
    from pairedgta.errors import ConfigError
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    overrides, expect = BAD_CONFIG[case]
    overrides = [o.format(tmp=tmp_path) for o in overrides]
    keys = {o.split("=", 1)[0] for o in overrides}
    args = [o for o in fast_overrides(tmp_path) if o.split("=", 1)[0] not in keys] + overrides
    (tmp_path / "afile").write_text("not a directory")
    (tmp_path / "filled").mkdir()
    (tmp_path / "filled" / "evaluate").write_text("not a stage folder")
    ro = tmp_path / "ro"
    _read_only_dir(ro)
    try:
        if case in CLI_CASES:
            proc = run_cli(args, tmp_path)
            assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
            lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
        else:
            with pytest.raises(ConfigError) as info:
                run(compose_cfg(args))
            lines = str(info.value).splitlines()
    finally:
        _writable_again(ro)
    assert len(lines) == 1 and expect in lines[0], lines
    cache = Path(next(o for o in args if o.startswith("cache_dir=")).split("=", 1)[1])
    # no stage ran: no stage folder in the cache (a cache_dir that is no folder holds none)
    stage_dirs = [p.name for p in cache.iterdir() if p.is_dir() and not p.name.startswith(".")] if cache.is_dir() else []
    assert stage_dirs == [], stage_dirs


@pytest.mark.slow
def test_corrupt_hf_weights_from_the_cli_are_one_line(tmp_path):
    from pairedgta.testing.cli import fast_overrides

    weights = tmp_path / "weights"
    build_model("tiny_segformer").module.save_pretrained(weights)
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
