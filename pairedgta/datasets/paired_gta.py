"""Reader of the released PairedGTA layout: <root>/<Time>/<loc>_<Time>_<WEATHER>.<ext>."""
from __future__ import annotations

import logging
import re
from collections import defaultdict
from pathlib import Path

from pairedgta.conditions import ConditionGrid, condition_name
from pairedgta.datasets.base import IMAGE_EXTENSIONS, Group, PairedDataset
from pairedgta.errors import DataError

log = logging.getLogger(__name__)
PATTERN = re.compile(r"^(?P<loc>\d+)_(?P<time>[A-Za-z]+)_(?P<weather>[A-Za-z]+)$")


def open_paired_gta(*, root: str | Path, grid: ConditionGrid, name: str = "paired_gta") -> PairedDataset:
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"dataset.root={root} does not exist; set dataset.root to the released PairedGTA folder")
    images: dict[str, dict[str, Path]] = defaultdict(dict)
    unknown: set[str] = set()
    for time_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        for path in sorted(time_dir.iterdir()):
            if path.suffix.lower() not in IMAGE_EXTENSIONS:
                continue
            m = PATTERN.match(path.stem)
            if not m:
                continue
            cond = condition_name(m["time"], m["weather"])
            if cond not in grid.names:
                unknown.add(cond)
                continue
            images[m["loc"]][cond] = path
    if unknown:
        log.info("ignoring images of conditions outside the grid: %s", ", ".join(sorted(unknown)))
    if not images:
        raise DataError(
            f"dataset.root={root} holds no <Time>/<loc>_<Time>_<WEATHER>.png images of the condition grid; "
            "point dataset.root at the released PairedGTA folder"
        )
    groups, skipped = [], 0
    for loc in sorted(images, key=int):
        if grid.reference not in images[loc]:
            skipped += 1
            continue
        groups.append(Group(group_id=loc, images=images[loc]))
    if skipped:
        log.warning("skipped %d group(s) without the reference image %s", skipped, grid.reference)
    if not groups:
        raise DataError(f"dataset.root={root}: no group has the reference condition {grid.reference}")
    return PairedDataset(name, root, grid.reference, grid.names, groups, skipped, grid=grid)
