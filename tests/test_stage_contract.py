"""Every stage implements one contract (pairedgta.stages.common.Stage), so the runner alone hashes, shards and
reads the cache: a stage missing a member, or with a member of another shape, fails here, not in a user's run."""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from pairedgta.stages import cityscapes_val, evaluate, generate, plot, pseudolabel
from pairedgta.stages.common import Stage, StageResult

STAGE_CLASSES = [generate.Generate, pseudolabel.Pseudolabel, evaluate.Evaluate, plot.Plot, cityscapes_val.CityscapesVal]
PACKAGE = Path(generate.__file__).resolve().parents[1]


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


@pytest.mark.parametrize("cls", STAGE_CLASSES, ids=lambda c: c.__name__)
def test_each_stage_names_its_result_and_folder(cls):
    fields = cls.__dataclass_fields__
    assert issubclass(fields["result_cls"].default, StageResult)
    assert fields["name"].default in ("generate", "pseudolabel", "evaluate", "plot", "cityscapes_val")
    assert isinstance(fields["version"].default, str)


def test_only_the_runner_hashes_a_stage():
    """stage_hash is called in pairedgta/stages/common.py alone (two stages hashing on their own once drifted)."""
    callers = [p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py")
               if "stage_hash(" in p.read_text() and p.name != "cache.py"]
    assert callers == ["stages/common.py"]
