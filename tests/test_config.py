"""Every option of every config group composes, and the condition grid is the paper's."""
from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from pairedgta.conditions import Condition, ConditionGrid, build_condition_grid
from pairedgta.errors import ConfigError
from tests.conftest import CONF, compose_cfg

GROUPS = ["conditions", "region", "renderer", "model", "metric", "dataset"]


@pytest.mark.parametrize("group", GROUPS)
def test_every_option_of_every_group_composes(group):
    for path in sorted((CONF / group).glob("*.yaml")):
        cfg = compose_cfg([f"{group}={path.stem}"])
        # resolve everything but mandatory-missing values (dataset.root of release datasets)
        OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)


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
    sweep = build_condition_grid(OmegaConf.to_container(compose_cfg(["conditions=fog_sweep"]).conditions))
    assert [c.fog_density for c in sweep] == [0.0, 0.25, 0.5, 0.75, 1.0]


def test_bad_conditions_are_one_line_errors():
    cfg = OmegaConf.to_container(compose_cfg([]).conditions)
    with pytest.raises(ConfigError, match="conditions.reference='Noon-SUNNY'"):
        build_condition_grid({**cfg, "reference": "Noon-SUNNY"})
    with pytest.raises(ConfigError, match="unknown condition 'Day-SNOW'"):
        build_condition_grid({**cfg, "only": ["Day-EXTRASUNNY", "Day-SNOW"]})
    with pytest.raises(ConfigError, match="fog_density"):
        Condition(name="x", time="Day", weather="FOGGY", fog_density=1.5)
    with pytest.raises(ConfigError, match="duplicate"):
        ConditionGrid((Condition("a", "Day", "X"), Condition("a", "Day", "X")), "a")
