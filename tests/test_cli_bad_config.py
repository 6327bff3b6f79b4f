"""Each bad config value on the command line stops the run before any stage writes, with one line naming the key
(a module of its own: its ~90 runs balance against the rest of tests/test_cli.py on the other xdist worker)."""
from __future__ import annotations

from pathlib import Path

import pytest

from pairedgta.testing.cli import run_cli


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


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(BAD_CONFIG))
def test_bad_config_value_is_one_line_before_any_stage(tmp_path, case):
    """Each bad value stops the run before generation (nothing is computed first), with one line that
    names the key and the value."""
    from pairedgta.testing.cli import fast_overrides

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
        proc = run_cli(args, tmp_path)
    finally:
        _writable_again(ro)
    assert proc.returncode == 2, proc.stderr[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and expect in errors[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    cache = Path(next(o for o in args if o.startswith("cache_dir=")).split("=", 1)[1])
    assert not (cache / "generate").exists() if cache.is_dir() else True  # no stage ran
