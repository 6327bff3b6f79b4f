"""Dataset readers, one module per layout, built through one registry from the `dataset` config.

Every reader is called as `open_<kind>(root=..., grid=..., **dataset keys)`; a paired reader returns a
`PairedDataset` that carries the condition grid it is evaluated over."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from pairedgta.conditions import ConditionGrid
from pairedgta.datasets.base import (Group, LabelMaps, PairedDataset, image_notes, load_group_images, load_image,
                                     load_label, load_transmittance)
from pairedgta.registry import Registry

DATASETS = Registry("dataset", "dataset.kind")
DATASETS.register("generated", "pairedgta.datasets.generated:open_generated", paired=True)
DATASETS.register("paired_gta", "pairedgta.datasets.paired_gta:open_paired_gta", paired=True)
# root_hint: what to do when the dataset's root is unset or missing ({key}: the config key that names it),
# declared here so that the message needs no import of the reader
DATASETS.register("acdc", "pairedgta.datasets.acdc:open_acdc", paired=True,
                  root_hint="ACDC is not available: register and download it (rgb_anon + gt) from "
                            "https://acdc.vision.ee.ethz.ch, then set {key}=/path/to/ACDC (the folder that holds "
                            "rgb_anon/ and gt/)")
DATASETS.register("cityscapes", "pairedgta.datasets.cityscapes:open_cityscapes", paired=False)


def open_dataset(cfg: Mapping[str, Any], grid: ConditionGrid | None = None, root: str | Path | None = None,
                 where: str = "dataset") -> Any:
    cfg = dict(cfg)
    kind = cfg.pop("kind", None)
    if root is not None:
        cfg["root"] = root
    return DATASETS.build(kind, cfg, where=where, grid=grid)


def root_hint(kind: Any, key: str) -> str | None:
    """The `root_hint` of dataset kind `kind`'s registry entry for config key `key`, if it declares one."""
    hint = DATASETS.meta(kind).get("root_hint") if kind in DATASETS else None
    return hint.format(key=key) if hint else None


def missing_root_message(cfg: Mapping[str, Any], key: str) -> str:
    """What to do when `key` (the dataset's root) is unset: the kind's root_hint, else the key to set."""
    return root_hint(cfg.get("kind"), key) or f"{key} is required for dataset={cfg.get('name')}; set {key}=PATH"


__all__ = ["DATASETS", "Group", "LabelMaps", "PairedDataset", "open_dataset", "missing_root_message", "root_hint",
           "load_image", "load_label", "load_group_images", "load_transmittance", "image_notes"]
