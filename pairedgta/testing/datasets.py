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
