"""The corruption conditions of a dataset given by dataset.root (the released PairedGTA layout): its clean frames
corrupted into a generate entry of their own, keyed by the dataset's content and the corruptions, and the pass's
dataset extended with them. Generate's step calls it; the frames themselves stay where they are."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pairedgta import corruptions
from pairedgta.cache import SHARED_WORK
from pairedgta.conditions import ConditionGrid
from pairedgta.datasets.base import PairedDataset, share_clean_truth
from pairedgta.datasets.generated import INDEX, scene_files
from pairedgta.errors import ConfigError
from pairedgta.jsonio import write_json
from pairedgta.render.corruptions import DONE, corrupt_groups
from pairedgta.stages.common import Context, StageResult, run_cached

VERSION = "1"


@dataclass
class CorruptExisting:
    """The corruption conditions of a dataset given by dataset.root (the released PairedGTA layout): a generate entry
    of its own, keyed by that dataset's content and the corruptions, holding only the corrupted images."""

    ctx: Context
    dataset: Any  # PairedDataset
    dataset_key: str
    name: str = "generate"
    version: str = VERSION
    label: str = "[corruptions]"
    resumable: bool = True
    result_cls: type[StageResult] = StageResult

    def hash_config(self) -> dict[str, Any]:
        grid = self.ctx.grid
        return {"corrupt": self.dataset_key, "seed": self.ctx.run.generate.seed,
                "conditions": [c.to_dict() for c in grid.corrupted], **corruptions.hash_config(grid)}

    def inputs(self) -> dict[str, str]:
        return {}

    def build(self, out: Path, key: str) -> dict[str, Any]:
        corrupt_groups(self.dataset, self.ctx.grid, self.ctx.run.generate, out, list(range(len(self.dataset))))
        (out / SHARED_WORK).unlink(missing_ok=True)
        write_json(out / INDEX, {"corrupts": self.dataset_key, "root": str(self.dataset.root),
                                 "conditions": [c.name for c in self.ctx.grid.corrupted],
                                 "groups": [str(g.group_id) for g in self.dataset.groups],
                                 **corruptions.hash_config(self.ctx.grid)})
        return {"num_groups": len(self.dataset)}

    def shards(self) -> tuple[int, int]:
        return self.ctx.run.generate.num_shards, self.ctx.run.generate.shard

    def build_shard(self, key: str) -> Path | None:
        """As Generate.build_shard: shard i of N corrupts groups i, i+N, ... into the entry's work folder."""
        num, shard = self.shards()
        n = len(self.dataset)
        work = self.ctx.cache.partial_path(self.name, key)
        work.mkdir(parents=True, exist_ok=True)
        (work / SHARED_WORK).touch()
        corrupt_groups(self.dataset, self.ctx.grid, self.ctx.run.generate, work, list(range(shard, n, num)))
        have = sum((work / "scenes" / str(g.group_id) / DONE).is_file() for g in self.dataset.groups)
        return None if have == n else work


def with_corruptions(dataset: Any, grid: ConditionGrid, entry: Path, key: str) -> Any:
    """`dataset` with the corrupted images of `entry` added to its groups, each with its clean condition's truth."""
    groups = []
    for g in dataset.groups:
        images = dict(g.images)
        for c in grid.corrupted:
            path = scene_files(entry / "scenes" / str(g.group_id), c.name)[0]
            if path.is_file():
                images[c.name] = path
        groups.append(share_clean_truth(replace(g, images=images), grid))
    return CorruptedDataset(dataset.name, dataset.root, dataset.reference, grid.names, groups,
                            dataset.skipped_without_reference, grid=grid, key=key)


@dataclass
class CorruptedDataset(PairedDataset):
    """An existing dataset and its corruption conditions (images in a generate entry outside its root)."""

    key: str = ""

    def fingerprint(self) -> str:
        return self.key


def corrupt_existing(ctx: Context, p: Any, plan: Any) -> None:
    """The pass `p` (its dataset opened from dataset.root) with its corruption conditions, built or from the cache."""
    entry = run_cached(ctx, CorruptExisting(ctx, p.dataset, str(p.dataset_key)))
    if not entry.complete:
        if plan.steps("pass", "run"):
            raise ConfigError("generate.shard is set and other shards' groups are still to be corrupted: run "
                              "the remaining shards, then the later stages without generate.shard/num_shards")
        return
    key = f"{p.dataset_key}+corruptions:{entry.key}"
    p.dataset, p.dataset_key = with_corruptions(p.dataset, ctx.grid, entry.path, key), key
    p.grid = p.dataset.grid
