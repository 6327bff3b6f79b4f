"""The typed config (pairedgta/schema.py) and the YAML under pairedgta/conf must say the same thing: one default per
key. A key added to one and not the other, or a default changed in one place only, fails here."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import pytest
import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from pairedgta import schema
from pairedgta.errors import ConfigError

CONF = Path(schema.__file__).parent / "conf"
# nodes that only experiments set: their one default is the schema's (an experiment that sets them says so)
EXPERIMENT_ONLY = {"cost", "plot.ablation", "photometry", "acdc"}


def _composed(*overrides: str) -> dict[str, Any]:
    with initialize_config_module(config_module="pairedgta.conf", version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    out = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(out, dict)
    return out


def _leaves(obj: Any, prefix: str = "") -> dict[str, Any]:
    """dotted key -> default of every key of a schema node (nested nodes walked, mappings kept whole)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_leaves(value, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def _lookup(tree: dict[str, Any], dotted: str) -> tuple[bool, Any]:
    node: Any = tree
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return False, None
        node = node[part]
    return True, node


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(a, b)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def test_every_schema_default_is_the_yaml_default():
    yaml_tree = _composed()
    leaves = _leaves(schema.defaults())
    checked = 0
    for dotted, default in leaves.items():
        if dotted.split(".")[0] in schema.GROUP_NODES or dotted == "model_overrides":
            continue  # the chosen options' own files own these
        present, value = _lookup(yaml_tree, dotted)
        if not present:
            assert any(dotted == e or dotted.startswith(e + ".") for e in EXPERIMENT_ONLY), (
                f"{dotted} has a schema default but no line in pairedgta/conf/config.yaml or metric/strict.yaml")
            continue
        assert _same(value, default), f"{dotted}: YAML says {value!r}, pairedgta/schema.py says {default!r}"
        checked += 1
    assert checked > 80  # the walk reached the nested nodes


@pytest.mark.slow  # composes every experiment (~1 s each)
def test_every_yaml_key_has_an_owner():
    """The default config and every experiment parse: no key in the YAML that the schema does not own."""
    for path in [None, *sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))]:
        cfg = _composed(*([f"+experiment={path}"] if path else []))
        run = schema.parse(cfg)
        assert run.name == cfg["name"]


def test_metric_paper_parses_to_its_own_values():
    run = schema.parse(_composed("metric=paper"))
    assert run.metric.convention == "paper" and run.metric.absent == "zero"
    assert run.metric.mean_exclude == ["bus", "train"] and run.metric.rho.headline == "nonzero"


def test_parse_types_and_numbers():
    run = schema.parse({"generate": {"num_scenes": "12", "camera": {"fov": 70}}, "threads": 3})
    assert run.generate.num_scenes == 12 and isinstance(run.generate.camera.fov, float)
    assert run.generate.objects.max == 3  # untouched keys keep their defaults
    assert dataclasses.is_dataclass(run.generate.validation)
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.threads = 4  # type: ignore[misc]


@pytest.mark.parametrize("given, message", [
    ({"generate": {"num_scene": 3}}, "generate.num_scene is not a key of generate; did you mean generate.num_scenes?"),
    ({"generate": {"num_scenes": 0}}, "generate.num_scenes=0 is out of range; use an integer from 1 to 10,000,000"),
    ({"generate": {"num_scenes": None}}, "generate.num_scenes is not set"),
    ({"generate": {"num_scenes": "many"}}, "generate.num_scenes='many' is not a number"),
    ({"generate": {"objects": {"min": 5, "max": 2}}}, "generate.objects.min=5 is above generate.objects.max=2"),
    ({"generate": {"objects": {"d_min": -1}}}, "generate.objects.d_min=-1 is out of range"),
    ({"generate": {"validation": {"structure_threshold": 5}}}, "generate.validation.structure_threshold=5 is out of range"),
    ({"generate": {"num_shards": 2, "shard": 3}}, "generate.shard=3 is outside 0..1"),
    ({"evaluate": {"num_workers": -1}}, "evaluate.num_workers=-1 is out of range"),
    ({"evaluate": {"num_workers": "many"}}, "evaluate.num_workers='many' is out of range"),
    ({"evaluate": {"sampling": "some"}}, "evaluate.sampling='some'; use one of all, random_one"),
    ({"pseudolabel": {"tau": 1.5}}, "pseudolabel.tau=1.5 is out of range; use a softmax threshold in [0, 1]"),
    ({"metric": {"bootstrap": {"confidence": 1.0}}}, "metric.bootstrap.confidence=1.0 is out of range"),
    ({"metric": {"absent": "maybe"}}, "metric.absent='maybe'"),
    ({"metric": {"reference": "oracle"}}, "metric.reference='oracle'; use one of pseudo_label, ground_truth, both"),
    ({"plot": {"formats": ["gif89"]}}, "plot.formats=['gif89']: unknown format(s) ['gif89']"),
    ({"plot": {"dpi": "high"}}, "plot.dpi='high' is not a number"),
    ({"cache": {"verify": "sometimes"}}, "cache.verify='sometimes'; use stat (trust size + mtime"),
    ({"tracking": {"enabled": "maybe"}}, "tracking.enabled='maybe' must be true or false"),
    ({"stages": []}, "stages=[] runs nothing"),
    ({"colour": "red"}, "colour is not a key of pairedgta"),
    ({"plot": 3}, "plot=3 must be a mapping"),
])
def test_bad_values_are_one_line_naming_the_key(given, message):
    with pytest.raises(ConfigError) as err:
        schema.parse(given)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_variants_key_is_named_with_its_prefix():
    with pytest.raises(ConfigError, match=r"^variants\[1\]\.pseudolabel\.tau=2"):
        schema.parse({"pseudolabel": {"tau": 2}}, where="variants[1].")


def test_yaml_lists_no_key_twice_within_the_defaults():
    """config.yaml's keys are the schema's: a stray top-level key there would be one more unowned default."""
    tree = yaml.safe_load((CONF / "config.yaml").read_text())
    names = {f.name for f in dataclasses.fields(schema.RunConfig)} | {"defaults", "hydra"}
    assert set(tree) <= names


def test_the_table_filter_keys_are_the_columns_the_figure_filters_by():
    from pairedgta.figures.paper_table import FILTERS

    assert tuple(f.name for f in dataclasses.fields(schema.TableFilterConfig)) == FILTERS
