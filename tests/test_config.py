"""Every option of every config group composes, and the condition grid is the paper's."""
from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from pairedgta.conditions import Condition, ConditionGrid, build_condition_grid
from pairedgta.config_checks import group_option_keys
from pairedgta.errors import ConfigError
from pairedgta.testing.cli import CONF, compose_cfg

GROUPS = ["conditions", "region", "renderer", "model", "metric", "dataset"]


@pytest.mark.parametrize("group", GROUPS)
def test_every_option_of_every_group_composes(group):
    for path in sorted((CONF / group).glob("*.yaml")):
        cfg = compose_cfg([f"{group}={path.stem}"])
        # resolve everything but mandatory-missing values (dataset.root of release datasets)
        node = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)[group]
        # its own keys and those of the same group's options its defaults list starts from (conditions=paper_corruptions)
        assert set(node) == group_option_keys(group, path.stem), path


def _options(group):
    return [(p.stem, OmegaConf.to_container(OmegaConf.load(p))) for p in sorted((CONF / group).glob("*.yaml"))]


# (group, registry, the key that picks the target, keys given at run time rather than by the YAML)
REGISTRIES = [
    ("region", "pairedgta.scene.sampling:REGIONS", "type", ()),
    ("dataset", "pairedgta.datasets:DATASETS", "kind", ("grid",)),
    ("renderer", "pairedgta.render:RENDERERS", "backend", ()),
]


@pytest.mark.parametrize("group,registry,choice,runtime", REGISTRIES)
def test_config_keys_are_exactly_what_the_code_reads(group, registry, choice, runtime):
    """None defined and never read (the target rejects unknown keys), none read and never defined (every
    keyword the target takes is in the YAML)."""
    import importlib

    from pairedgta.registry import accepted_keys

    module, attr = registry.split(":")
    reg = getattr(importlib.import_module(module), attr)
    for name, cfg in _options(group):
        target = reg.resolve(cfg[choice])
        keys = accepted_keys(target)
        assert keys is not None, f"{target} takes **kwargs: its keys cannot be checked"
        assert set(cfg) - {choice} == keys - set(runtime), f"{group}/{name}"


def test_camera_options_name_exactly_the_keys_the_camera_reads():
    """The camera group is checked against its option files (a `+camera.x` they do not name is refused before
    any stage runs): so every option, with the option its defaults list starts from, names every field."""
    import dataclasses

    from pairedgta.config_checks import group_option_keys
    from pairedgta.render.camera import Camera

    fields = {f.name for f in dataclasses.fields(Camera)}
    for path in sorted((CONF / "camera").glob("*.yaml")):
        assert group_option_keys("camera", path.stem) == fields, path


def test_keys_added_to_a_group_are_checked_against_the_chosen_option():
    from pairedgta.config_checks import check_added_keys

    fine = ["+region.town_seeds=[1,2]", "+renderer.town.blocks=3", "renderer.width=3", "++renderer.width=3",
            "+model_overrides.x.path=/w", "+experiment=smoke", "+metric.rho.m=3", "+camera=dashcam"]
    check_added_keys(fine, {"renderer": "blender", "region": "procedural_town", "camera": "gta", "metric": "strict"})
    check_added_keys(["+renderer.port=1"], {"renderer": "deepgtav"})  # a key of the chosen option: Hydra's to refuse
    with pytest.raises(ConfigError, match=r"^renderer.port is not a key of renderer=blender; its keys are backend, camera"):
        check_added_keys(["+renderer.port=1"], None)  # config.yaml's choice: blender
    with pytest.raises(ConfigError, match=r"^renderer.sample is not a key of renderer=blender; did you mean renderer.samples\?$"):
        check_added_keys(["++renderer.sample=4"], {"renderer": "blender"})


def test_camera_overrides_take_the_condition_and_time_names_of_the_run(tmp_path):
    """camera.overrides is an open mapping (EV per condition or time name): typed with `+`, `++` or neither it
    composes and passes the checks for a name of the run's grid, and one line lists the names otherwise."""
    from pairedgta.__main__ import _open_mapping_overrides, mistyped_key
    from pairedgta.config_checks import check_added_keys, check_run_config

    only = "conditions.only=[Day-EXTRASUNNY,Night-RAIN]"
    for typed in ("camera.overrides.Night=1.0", "+camera.overrides.Night-RAIN=1.0", "++camera.overrides.Day=0.5"):
        argv = _open_mapping_overrides([typed, only, f"cache_dir={tmp_path}"])
        assert mistyped_key(argv) is None
        check_added_keys(argv, None)
        cfg = OmegaConf.to_container(compose_cfg(argv), resolve=True)
        assert list(cfg["camera"]["overrides"]) == [typed.split("=")[0].rsplit(".", 1)[1]]
        check_run_config(cfg)
    for name in ("Noon", "Night-FOGGY"):  # not a name at all; a condition conditions.only leaves out
        cfg = OmegaConf.to_container(compose_cfg([f"+camera.overrides.{name}=1.0", only, f"cache_dir={tmp_path}"]),
                                     resolve=True)
        with pytest.raises(ConfigError, match=rf"^camera.overrides.{name} is not a condition or time of this run, so "
                                              r"no image would use it; use one of Day-EXTRASUNNY, Night-RAIN, Day, Night$"):
            check_run_config(cfg)


def test_model_keys_are_exactly_what_the_families_read():
    from pairedgta.models import FAMILIES, RUNTIME_KEYS, check_model_config, with_defaults
    from pairedgta.models.runtime import MODEL_KEYS
    from pairedgta.registry import accepted_keys

    by_family: dict[str, set[str]] = {}
    for name, cfg in _options("model"):
        check_model_config(cfg)  # no key a family does not read
        assert not set(cfg) & set(RUNTIME_KEYS), f"model/{name} sets a runtime key"
        by_family.setdefault(cfg["family"], set()).update(with_defaults(cfg))  # as the stages see it
    for family, defined in by_family.items():
        read = (accepted_keys(FAMILIES.resolve(family)) - {"runtime"} | set(MODEL_KEYS)) - set(RUNTIME_KEYS)
        assert read == defined, f"{family}: read but never defined {sorted(read - defined)}"


def test_unknown_keys_are_rejected_the_same_way_everywhere():
    from pairedgta.datasets import open_dataset
    from pairedgta.models import build_model
    from pairedgta.render import build_renderer
    from pairedgta.scene.sampling import build_region

    cases = [
        (lambda: build_renderer({"backend": "synthetic", "width": 8, "height": 8, "colour": 1}), "renderer: unknown key(s) colour"),
        (lambda: build_region({"type": "rectangle", "name": "r", "x_range": [0, 1], "y_range": [0, 1], "hight": 2}),
         "region: unknown key(s) hight"),
        (lambda: open_dataset({"kind": "paired_gta", "root": "/x", "spilt": "val"}), "dataset: unknown key(s) spilt"),
        (lambda: build_model("tiny_segformer", widht=3), "model (tiny_segformer): unknown key(s) widht"),
    ]
    for make, message in cases:
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
            make()
    with pytest.raises(ConfigError, match="renderer.backend='povray' is unknown; choose one of: blender, deepgtav, synthetic"):
        build_renderer({"backend": "povray"})


@pytest.mark.parametrize("experiment", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_every_experiment_composes(experiment):
    cfg = compose_cfg([f"+experiment={experiment}"])
    assert cfg.name == experiment


def test_paper_grid_and_reference_come_from_config():
    grid = build_condition_grid(OmegaConf.to_container(compose_cfg([]).conditions))
    assert len(grid) == 9
    assert grid.reference == "Day-EXTRASUNNY"
    assert set(grid.names) == {f"{t}-{w}" for t in ("Day", "Sunset", "Night") for w in ("EXTRASUNNY", "RAIN", "FOGGY")}
    assert grid["Night-FOGGY"].sun_elevation_deg < 0 < grid["Day-RAIN"].sun_elevation_deg
    # every condition in physical units: Koschmieder's extinction from the visibility, plus the rain's own
    assert grid["Day-FOGGY"].extinction_per_m == pytest.approx(3.912 / grid["Day-FOGGY"].visibility_m)
    assert grid["Day-RAIN"].rain_mm_h == 25.0 and grid["Day-RAIN"].extinction_per_m > 3.912 / grid["Day-RAIN"].visibility_m
    assert grid["Day-EXTRASUNNY"].extinction_per_m == 0.0 and grid["Day-EXTRASUNNY"].effective_visibility_m == float("inf")


@pytest.mark.parametrize("ladder, parameter, values, names", [
    ("fog_ladder", "visibility_m", [1000, 600, 300, 150, 75], ["Day-FOG-1000m", "Day-FOG-75m"]),
    ("rain_ladder", "rain_mm_h", [2.5, 10, 25, 50, 100], ["Day-RAIN-2.5mmh", "Day-RAIN-100mmh"]),
    ("light_ladder", "sun_elevation_deg", [30, 15, 5, 0, -3, -6, -12, -18], ["SUN-30deg", "SUN-minus6deg"]),
])
def test_ladders_name_their_value_and_unit_and_grow_in_severity(ladder, parameter, values, names):
    grid = build_condition_grid(OmegaConf.to_container(compose_cfg([f"conditions={ladder}"]).conditions))
    assert grid.reference == "Day-EXTRASUNNY" and grid.ladder.parameter == parameter
    assert [getattr(c, parameter) for c in grid.conditions[1:]] == values
    assert set(names) <= set(grid.names)
    assert grid.ladder.tick(grid["Day-EXTRASUNNY"]) in ("clear", "0 mm/h", "55 deg")
    if parameter == "visibility_m":  # each step hides more: the extinction grows along the ladder
        ext = [c.extinction_per_m for c in grid]
        assert ext == sorted(ext) and ext[0] == 0.0
    if parameter == "rain_mm_h":  # haze, wetness and darkening follow the rate
        assert [c.rain_level for c in grid] == sorted(c.rain_level for c in grid)
        assert [c.extinction_per_m for c in grid] == sorted(c.extinction_per_m for c in grid)


def test_transmittance_is_koschmieder_and_clear_air_hides_nothing():
    fog = Condition(name="f", time="Day", weather="FOGGY", visibility_m=300.0)
    t = fog.transmittance(np.array([0.0, 300.0, np.inf]))
    assert t == pytest.approx([1.0, 0.02, 0.0], abs=1e-3)  # at the visibility the contrast is 2 %
    assert (Condition(name="c", time="Day", weather="EXTRASUNNY").transmittance(np.array([5.0, np.inf])) == 1.0).all()


def test_bad_conditions_are_one_line_errors():
    cfg = OmegaConf.to_container(compose_cfg([]).conditions)
    with pytest.raises(ConfigError, match="conditions.reference='Noon-SUNNY'"):
        build_condition_grid({**cfg, "reference": "Noon-SUNNY"})
    with pytest.raises(ConfigError, match="unknown condition 'Day-SNOW'"):
        build_condition_grid({**cfg, "only": ["Day-EXTRASUNNY", "Day-SNOW"]})
    with pytest.raises(ConfigError, match="cloud_cover"):
        Condition(name="x", time="Day", weather="FOGGY", cloud_cover=1.5)
    with pytest.raises(ConfigError, match=r"visibility_m=0.*metres"):
        Condition(name="x", time="Day", weather="FOGGY", visibility_m=0)
    with pytest.raises(ConfigError, match=r"rain_mm_h=-1.*mm/h"):
        Condition(name="x", time="Day", weather="RAIN", rain_mm_h=-1)
    # the unitless keys of earlier versions say what replaced them and how to convert
    with pytest.raises(ConfigError, match=r"fog_density is no longer a condition key; use visibility_m.*0.7 -> 93 m"):
        build_condition_grid({**cfg, "weathers": {**cfg["weathers"], "FOGGY": {"fog_density": 0.7}}})
    with pytest.raises(ConfigError, match=r"conditions.ladder.parameter='fog'"):
        build_condition_grid({**cfg, "ladder": {"parameter": "fog"}})
    with pytest.raises(ConfigError, match="duplicate"):
        ConditionGrid((Condition("a", "Day", "X"), Condition("a", "Day", "X")), "a")


def test_no_config_file_sets_hydra_mode_so_in_process_runs_may_read_it_from_the_overrides():
    """pairedgta.testing.cli runs the CLI in-process without Hydra's get_mode, which composes the whole config once
    only to read `hydra.mode`: the overrides alone give it while no file of the package sets it. Hydra's own
    answer and the harness's agree on the main job, an experiment, a sweep and an explicit mode."""
    import yaml
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from pairedgta.configs import CONFIG_DIR
    from pairedgta.testing.cli import _mode_from_overrides

    for path in CONFIG_DIR.rglob("*.yaml"):
        tree = yaml.safe_load(path.read_text()) or {}
        assert "mode" not in (tree.get("hydra") or {}), path
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        hydra = GlobalHydra.instance().hydra
        for overrides in ([], ["+experiment=smoke"], ["model=demo_segformer,demo_ddrnet"], ["hydra.mode=MULTIRUN"],
                          ["hydra.mode=RUN", "task=detection"]):
            assert _mode_from_overrides(hydra, "config", overrides) == hydra.get_mode("config", overrides), overrides


def test_the_key_check_reads_a_config_file_again_once_it_changed(tmp_path):
    """config_checks keeps each file's parsed tree per (path, size, mtime): a process that runs the CLI many times
    parses them once, and an edited file is read anew."""
    from pairedgta.config_checks import _load_yaml

    path = tmp_path / "option.yaml"
    path.write_text("a: 1\n")
    assert _load_yaml(path) == {"a": 1} and _load_yaml(path) is _load_yaml(path)
    path.write_text("a: 1\nb: 2\n")
    assert _load_yaml(path) == {"a": 1, "b": 2}
