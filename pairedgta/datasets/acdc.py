"""Reader of ACDC (Sakaridis et al. 2021), the coarsely paired real-world adverse-condition dataset.

    <root>/rgb_anon/<cond>/<split>/<seq>/<seq>_frame_<n>_rgb_anon.png          adverse image
    <root>/rgb_anon/<cond>/<split>_ref/<seq>/<seq>_frame_<n>_rgb_ref_anon.png   clear-daytime reference
    <root>/gt/<cond>/<split>/<seq>/<seq>_frame_<n>_gt_labelTrainIds.png          labels of the ADVERSE image
    <root>/gt_panoptic/<cond>/<split>/<seq>/<seq>_frame_<n>_gt_panoptic.png      its panoptic labels (optional; with
    <root>/gt_panoptic/<cond>/<cond>_<split>_gt_panoptic.json                     their JSON: detection/real_boxes.py)

One group = (reference, adverse) of one frame. The dataset carries its own two-condition grid,
`ACDC-reference` (the clean condition) and `ACDC-<cond>`. Ground truth describes the adverse frame only
(the reference was driven at another time: other objects, a slightly different pose), so it is stored
as `Group.labels["ACDC-<cond>"]` and never as the reference's labels; its panoptic PNG likewise as
`Group.instances["ACDC-<cond>"]` only.

Download: https://acdc.vision.ee.ethz.ch (registration required); `rgb_anon` and `gt` packages.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

from pairedgta.conditions import Condition, ConditionGrid
from pairedgta.datasets import root_hint
from pairedgta.datasets.base import Group, PairedDataset
from pairedgta.errors import ConfigError, DataError

log = logging.getLogger(__name__)
CONDITIONS = ("fog", "night", "rain", "snow")
SPLITS = ("train", "val", "test")
REFERENCE = "ACDC-reference"
ADVERSE_RE = re.compile(r"^(?P<seq>.+)_frame_(?P<n>\d+)_rgb_anon$")
# backend-neutral physical parameters of the adverse condition (descriptive only: nothing is rendered)
_PHYSICAL = {
    "fog": {"visibility_m": 150.0, "cloud_cover": 0.6},  # descriptive: dense road fog (below 1 km by definition)
    "night": {"clock_hour": 0, "sun_elevation_deg": -30.0},
    "rain": {"rain_mm_h": 10.0, "wetness": 1.0, "cloud_cover": 0.9},
    "snow": {"cloud_cover": 0.9, "wetness": 0.5},
}


def condition_label(condition: str) -> str:
    return f"ACDC-{condition}"


def acdc_grid(condition: str) -> ConditionGrid:
    """The dataset's own grid: the clear-daytime reference and the one adverse condition."""
    if condition not in CONDITIONS:
        raise ConfigError(f"dataset.condition={condition!r}; ACDC has {', '.join(CONDITIONS)}")
    return ConditionGrid(
        (
            Condition(name=REFERENCE, time="ACDC", weather="reference"),
            Condition(name=condition_label(condition), time="ACDC", weather=condition, **_PHYSICAL[condition]),
        ),
        REFERENCE,
    )


def reference_path(root: Path, cond: str, split: str, seq: str, n: str) -> Path:
    return root / "rgb_anon" / cond / f"{split}_ref" / seq / f"{seq}_frame_{n}_rgb_ref_anon.png"


def adverse_path(root: Path, cond: str, split: str, seq: str, n: str) -> Path:
    return root / "rgb_anon" / cond / split / seq / f"{seq}_frame_{n}_rgb_anon.png"


def label_path(root: Path, cond: str, split: str, seq: str, n: str) -> Path:
    return root / "gt" / cond / split / seq / f"{seq}_frame_{n}_gt_labelTrainIds.png"


def panoptic_path(root: Path, cond: str, split: str, seq: str, n: str) -> Path:
    return root / "gt_panoptic" / cond / split / seq / f"{seq}_frame_{n}_gt_panoptic.png"


def _as_list(value: Any) -> list[str]:
    if value is None:
        return list(SPLITS[:2])
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


def open_acdc(
    *, root: str | Path, grid: ConditionGrid | None = None, name: str = "acdc", condition: str = "night",
    splits: Any = ("train", "val"), max_pairs: int | None = None,
) -> PairedDataset:
    """Pairs of `dataset.condition` over `dataset.splits`, on the dataset's own two-condition grid (the run's
    `conditions` do not apply: ACDC has one reference and one adverse image per frame).

    A frame whose reference image is missing is skipped, counted in `skipped_without_reference` and
    reported; a root without the expected tree is a DataError naming the paths it looked for."""
    cond = str(condition)
    grid = acdc_grid(cond)
    splits = _as_list(splits)
    bad = [s for s in splits if s not in SPLITS]
    if bad:
        raise ConfigError(f"dataset.splits: unknown {bad}; ACDC splits are {', '.join(SPLITS)}")
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"dataset.root={root} does not exist; {root_hint('acdc', 'dataset.root')}")
    expected = [root / "rgb_anon" / cond / s for s in splits]
    missing_dirs = [p for p in expected if not p.is_dir()]
    if missing_dirs:
        example = adverse_path(root, cond, splits[0], "<seq>", "<n>")
        ref = reference_path(root, cond, splits[0], "<seq>", "<n>")
        raise DataError(
            f"dataset.root={root} is not an ACDC tree: {', '.join(str(p) for p in missing_dirs)} missing; "
            f"expected {example} and {ref}"
        )
    adverse = condition_label(cond)
    groups: list[Group] = []
    skipped: list[Path] = []
    labelled = 0
    for split in splits:
        for img in sorted((root / "rgb_anon" / cond / split).glob("*/*_rgb_anon.png")):
            m = ADVERSE_RE.match(img.name[: -len(".png")])
            if not m or img.parent.name != m["seq"]:
                continue
            seq, n = m["seq"], m["n"]
            ref = reference_path(root, cond, split, seq, n)
            if not ref.is_file():
                skipped.append(ref)
                continue
            labels: dict[str, Path] = {}
            gt = label_path(root, cond, split, seq, n)
            if gt.is_file():
                labels[adverse] = gt  # the adverse frame's truth, not the reference's
                labelled += 1
            pan = panoptic_path(root, cond, split, seq, n)
            instances = {adverse: pan} if pan.is_file() else {}  # the adverse frame's objects, as its labels
            groups.append(Group(f"{split}_{seq}_frame_{n}", {REFERENCE: ref, adverse: img}, labels,
                                instances=instances))
    if skipped:
        log.warning(
            "ACDC %s: %d adverse image(s) without their reference were skipped, e.g. %s missing",
            cond, len(skipped), skipped[0],
        )
    if max_pairs is not None:
        groups = groups[: int(max_pairs)]
    if not groups:
        raise DataError(
            f"dataset.root={root}: no ACDC pair of condition {cond} in splits {splits} "
            f"(looked for {adverse_path(root, cond, splits[0], '<seq>', '<n>')} with its reference "
            f"{reference_path(root, cond, splits[0], '<seq>', '<n>')})"
        )
    log.info("ACDC %s %s: %d pairs, %d with ground truth of the adverse image, %d without reference",
             cond, "+".join(splits), len(groups), labelled, len(skipped))
    return PairedDataset(str(name), root, REFERENCE, grid.names, groups, len(skipped), grid=grid)
