"""Small datasets in the layouts the readers accept, written for tests and examples."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def write_release(root: Path, locs, size=(64, 32), missing=()) -> None:
    """The released PairedGTA layout <root>/<Time>/<loc>_<Time>_<WEATHER>.png with random images;
    `missing` lists (loc, condition) pairs to leave out."""
    for loc in locs:
        for time in ("Day", "Sunset", "Night"):
            for weather in ("EXTRASUNNY", "RAIN", "FOGGY"):
                if (loc, f"{time}-{weather}") in missing:
                    continue
                d = Path(root) / time
                d.mkdir(parents=True, exist_ok=True)
                arr = np.random.default_rng(loc).integers(0, 255, size=(size[1], size[0], 3), dtype=np.uint8)
                Image.fromarray(arr).save(d / f"{loc}_{time}_{weather}.png")


def _png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


def write_acdc(root: Path, frames: int = 4, size=(64, 32), condition: str = "night",
               splits=("train", "val")) -> Path:
    """ACDC's layout and file names (rgb_anon/<cond>/<split>[_ref]/<seq>/..., gt/<cond>/<split>/...) with
    random images and labels: `frames` pairs per split. Not ACDC: for tests of the commands that read it."""
    rng = np.random.default_rng(0)
    w, h = size
    for split in splits:
        for n in range(frames):
            seq = f"GOPR{n % 2:04d}"
            stem = f"{seq}_frame_{n:06d}"
            for folder, suffix in ((split, "rgb_anon"), (f"{split}_ref", "rgb_ref_anon")):
                _png(Path(root) / "rgb_anon" / condition / folder / seq / f"{stem}_{suffix}.png",
                     rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8))
            labels = rng.integers(0, 19, size=(h, w), dtype=np.uint8)
            _png(Path(root) / "gt" / condition / split / seq / f"{stem}_gt_labelTrainIds.png", labels)
    return Path(root)


def write_cityscapes(root: Path, frames: int = 3, size=(64, 32), split: str = "val") -> Path:
    """Cityscapes' layout (leftImg8bit/<split>/<city>/..., gtFine/<split>/<city>/..._gtFine_labelTrainIds.png)
    with random images and train-id labels, some void."""
    rng = np.random.default_rng(1)
    w, h = size
    for n in range(frames):
        city = ("frankfurt", "lindau", "munster")[n % 3]
        stem = f"{city}_{n:06d}_000019"
        _png(Path(root) / "leftImg8bit" / split / city / f"{stem}_leftImg8bit.png",
             rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8))
        labels = rng.integers(0, 19, size=(h, w), dtype=np.uint8)
        labels[rng.random((h, w)) > 0.9] = 255
        _png(Path(root) / "gtFine" / split / city / f"{stem}_gtFine_labelTrainIds.png", labels)
    return Path(root)
