"""Every stage implements one contract (pairedgta.stages.common.Stage), so the runner alone hashes, shards and
reads the cache: a stage missing a member, or with a member of another shape, fails here, not in a user's run."""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from pairedgta import schema, stage_registry
from pairedgta.stages.common import Stage, StageResult
from pairedgta.stages.planning import Step

SPECS = list(stage_registry.STAGES)
STAGE_CLASSES = [spec.stage_class for spec in SPECS]
PACKAGE = Path(stage_registry.__file__).resolve().parent


def _members(proto: type) -> dict[str, object]:
    return {n: v for n, v in vars(proto).items() if not n.startswith("_")}


@pytest.mark.parametrize("cls", STAGE_CLASSES, ids=lambda c: c.__name__)
def test_each_stage_has_every_member_of_the_contract(cls):
    names = set(_members(Stage)) | set(Stage.__annotations__)
    for name in names:
        assert hasattr(cls, name) or name in cls.__dataclass_fields__ or name in getattr(cls, "__annotations__", {}), (
            f"{cls.__name__} lacks Stage.{name}")
    for name, proto in _members(Stage).items():
        if callable(proto):
            want = list(inspect.signature(proto).parameters)
            have = list(inspect.signature(getattr(cls, name)).parameters)
            assert have == want, f"{cls.__name__}.{name}{have} differs from Stage.{name}{want}"


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_each_stage_names_its_result_and_folder(spec):
    """The Stage class hashes and stores under the name its registry line declares."""
    fields = spec.stage_class.__dataclass_fields__
    assert issubclass(fields["result_cls"].default, StageResult)
    assert fields["name"].default == spec.name
    assert isinstance(fields["version"].default, str) and spec.version == fields["version"].default


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_each_stage_has_the_one_step_signature(spec):
    """The app calls every stage the same way: `step(ctx: Context, p: PassResult, state: RunState) -> None`."""
    want = inspect.signature(Step.__call__)
    have = inspect.signature(spec.step)
    assert [(p.name, p.annotation) for p in have.parameters.values()] == \
        [(p.name, p.annotation) for p in list(want.parameters.values())[1:]], f"{spec.module}.step{have}"
    assert have.return_annotation == want.return_annotation


def test_each_registry_line_is_consistent():
    """Upstream stages come first, a pass holds each slot once, and a stage's options node is a node of the run's
    config (pairedgta/schema.py) with its YAML in pairedgta/conf/config.yaml."""
    import yaml

    seen: list[str] = []
    conf = yaml.safe_load((PACKAGE / "conf" / "config.yaml").read_text())
    nodes = {f.name for f in schema.RunConfig.__dataclass_fields__.values() if f.metadata.get("node")}
    for spec in SPECS:
        assert set(spec.needs) <= set(seen), f"{spec.name} needs {spec.needs}, listed after it"
        assert spec.node is None or (spec.node in nodes and spec.node in conf), spec
        assert spec.slot is None or spec.scope in ("dataset", "pass"), spec
        seen.append(spec.name)
    slots = [s.slot for s in SPECS if s.slot]
    assert len(slots) == len(set(slots))
    assert schema.STAGES == tuple(seen) and schema.RunConfig().stages == stage_registry.graph() == conf["stages"]


def test_only_the_runner_hashes_a_stage():
    """stage_hash is called in pairedgta/stages/common.py alone (two stages hashing on their own once drifted)."""
    callers = [p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py")
               if "stage_hash(" in p.read_text() and p.name != "cache.py"]
    assert callers == ["stages/common.py"]
