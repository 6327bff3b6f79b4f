"""Dataset readers, one module per layout; `open_dataset` picks one by `dataset.kind`."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from pairedgta.conditions import ConditionGrid
from pairedgta.datasets.base import Group, PairedDataset, load_group_images, load_image, load_label
from pairedgta.errors import ConfigError


def open_dataset(cfg: Mapping[str, Any], grid: ConditionGrid, root: str | Path | None = None) -> PairedDataset:
    kind = cfg.get("kind")
    root = root if root is not None else cfg.get("root")
    if root is None:
        raise ConfigError(f"dataset '{cfg.get('name')}' has no root; set dataset.root=PATH")
    if kind == "generated":
        from pairedgta.datasets.generated import open_generated

        return open_generated(root, grid, cfg.get("name", "generated"))
    if kind == "paired_gta":
        from pairedgta.datasets.paired_gta import open_paired_gta

        return open_paired_gta(root, grid, cfg.get("name", "paired_gta"))
    if kind == "acdc":
        from pairedgta.datasets.acdc import open_acdc

        return open_acdc(cfg, root)[0]
    raise ConfigError(f"dataset.kind={kind!r} is unknown; use generated, paired_gta or acdc")


__all__ = ["Group", "PairedDataset", "open_dataset", "load_image", "load_label", "load_group_images"]
