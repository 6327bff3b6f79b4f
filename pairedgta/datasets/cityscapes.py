"""Reader of the Cityscapes layout, for the ground-truth check of the model zoo:

    <root>/leftImg8bit/<split>/<city>/<city>_<seq>_<frame>_leftImg8bit.png         image
    <root>/gtFine/<split>/<city>/<city>_<seq>_<frame>_gtFine_labelTrainIds.png     train ids (preferred)
    <root>/gtFine/<split>/<city>/<city>_<seq>_<frame>_gtFine_labelIds.png          label ids (fallback, mapped)
    <root>/gtFine/<split>/<city>/<city>_<seq>_<frame>_gtFine_instanceIds.png       instance ids (detection, optional)

Every problem a run would hit later (no images, an image without ground truth, a label map whose size
differs from its image) is found when the split is opened, before any model runs; only file headers
are read for that.
"""
from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from PIL import Image

from pairedgta.cityscapes import IGNORE_INDEX, NUM_CLASSES, label_ids_to_train_ids
from pairedgta.datasets.base import image_size, load_image, load_label
from pairedgta.errors import ConfigError, DataError

log = logging.getLogger(__name__)
IMAGE_SUFFIX = "_leftImg8bit.png"
TRAIN_IDS_SUFFIX = "_gtFine_labelTrainIds.png"
LABEL_IDS_SUFFIX = "_gtFine_labelIds.png"
INSTANCE_IDS_SUFFIX = "_gtFine_instanceIds.png"
FRAME = re.compile(r"^(?P<city>.+)_(?P<seq>[^_]+)_(?P<frame>[^_]+)$")


@dataclass(frozen=True)
class CityscapesSample:
    frame_id: str          # <city>_<seq>_<frame>
    image: Path
    label: Path
    label_kind: str        # "trainIds" or "labelIds"
    size: tuple[int, int]  # (width, height) of image and label
    instances: Path | None = None  # its *_gtFine_instanceIds.png where present (detection/real_boxes.py)


@dataclass
class CityscapesSplit:
    name: str
    root: Path
    split: str
    samples: list[CityscapesSample]
    scale: float = 1.0

    def __len__(self) -> int:
        return len(self.samples)

    def fingerprint(self) -> str:
        """Identity for the cache: relative path, size and sha256 (memoised on path, size and mtime) of
        every used file, not where root lives."""
        from pairedgta.filehash import default

        memo = default()
        h = hashlib.sha256()
        for s in self.samples:
            for p in (s.image, s.label):
                st = p.stat()
                h.update(f"{p.relative_to(self.root).as_posix()}|{st.st_size}|{memo.sha256(p, st)}\n".encode())
        return h.hexdigest()[:16]

    def label_kinds(self) -> dict[str, int]:
        out = {"trainIds": 0, "labelIds": 0}
        for s in self.samples:
            out[s.label_kind] += 1
        return out

    def load(self, sample: CityscapesSample) -> tuple[np.ndarray, np.ndarray]:
        """-> (RGB uint8 H x W x 3, train ids uint8 H x W), downscaled when `scale` < 1."""
        image = load_image(sample.image)
        label = load_ground_truth(sample)
        if image.shape[:2] != label.shape:
            raise DataError(
                f"{sample.label}: label map is {label.shape[1]}x{label.shape[0]} but its image {sample.image} is "
                f"{image.shape[1]}x{image.shape[0]}; use the gtFine file of the same frame at full resolution"
            )
        if self.scale != 1.0:
            image, label = rescale(image, label, self.scale)
        return image, label


def load_ground_truth(sample: CityscapesSample) -> np.ndarray:
    """Train ids (0..18, 255 = ignore) from either label file; a file that is not what its name says is a DataError."""
    raw = load_label(sample.label, train_ids=sample.label_kind != "labelIds")
    if sample.label_kind == "labelIds":
        return label_ids_to_train_ids(raw)
    bad = (raw >= NUM_CLASSES) & (raw != IGNORE_INDEX)
    if bad.any():
        values = sorted(int(v) for v in np.unique(raw[bad]))[:5]
        raise DataError(
            f"{sample.label}: values {values} are not train ids (0..{NUM_CLASSES - 1}, {IGNORE_INDEX}); "
            "regenerate it with cityscapesscripts' createTrainIdLabelImgs or delete it to use the labelIds file"
        )
    return raw


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return max(1, int(round(size[0] * scale))), max(1, int(round(size[1] * scale)))


def rescale(image: np.ndarray, label: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Images bilinear (PIL, antialiased), labels nearest, to round(size * scale)."""
    size = scaled_size((image.shape[1], image.shape[0]), scale)
    image = np.asarray(Image.fromarray(image).resize(size, Image.BILINEAR))
    label = np.asarray(Image.fromarray(label).resize(size, Image.NEAREST))
    return image, label


def check_options(cfg: Mapping[str, Any]) -> tuple[str, int | None, float]:
    split = cfg.get("split") or "val"
    if not isinstance(split, str) or "/" in split or split in (".", ".."):
        raise ConfigError(f"dataset.split={split!r}; use a Cityscapes split name such as val or train")
    max_images = cfg.get("max_images")
    if max_images is not None:
        if isinstance(max_images, bool) or not isinstance(max_images, int) or max_images < 1:
            raise ConfigError(f"dataset.max_images={max_images!r}; use a positive integer or null for all images")
    scale = cfg.get("scale")
    scale = 1.0 if scale is None else scale
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0.0 < float(scale) <= 1.0:
        raise ConfigError(
            f"dataset.scale={scale!r}; use a factor in (0, 1] (e.g. 0.5 on CPU) or null for full resolution"
        )
    return split, max_images, float(scale)


def _ground_truth(gt_dir: Path, frame_id: str) -> tuple[Path, str] | None:
    train_ids = gt_dir / f"{frame_id}{TRAIN_IDS_SUFFIX}"
    if train_ids.is_file():
        return train_ids, "trainIds"
    label_ids = gt_dir / f"{frame_id}{LABEL_IDS_SUFFIX}"
    if label_ids.is_file():
        return label_ids, "labelIds"
    return None


def open_cityscapes(
    *, root: str | Path, grid: Any = None, name: str = "cityscapes", split: str = "val",
    max_images: int | None = None, scale: float | None = None,
) -> CityscapesSplit:
    """The images of one split (sorted by city, then frame; the first `max_images` of them) with their labels.
    Not a paired dataset (`grid` is unused): it feeds the cityscapes_val model check only."""
    split, max_images, scale = check_options({"split": split, "max_images": max_images, "scale": scale})
    root = Path(root)
    name = str(name or "cityscapes")
    if not root.is_dir():
        raise DataError(
            f"dataset.root={root} does not exist; "
            "set dataset.root to the Cityscapes folder holding leftImg8bit/ and gtFine/"
        )
    image_dir = root / "leftImg8bit" / split
    frames: list[tuple[str, Path]] = []
    if image_dir.is_dir():
        for city_dir in sorted(p for p in image_dir.iterdir() if p.is_dir()):
            for path in sorted(city_dir.glob(f"*{IMAGE_SUFFIX}")):
                frame_id = path.name[: -len(IMAGE_SUFFIX)]
                m = FRAME.match(frame_id)
                if not m or m["city"] != city_dir.name:
                    log.info("ignoring %s: not named <city>_<seq>_<frame>%s", path, IMAGE_SUFFIX)
                    continue
                frames.append((frame_id, path))
    if not frames:
        parent = root / "leftImg8bit"
        splits = sorted(p.name for p in parent.iterdir() if p.is_dir()) if parent.is_dir() else []
        hint = f"splits present: {', '.join(splits)}; set dataset.split" if splits else (
            "point dataset.root at the folder where leftImg8bit_trainvaltest.zip was extracted")
        raise DataError(f"{image_dir} holds no <city>/<city>_<seq>_<frame>{IMAGE_SUFFIX} images; {hint}")
    total = len(frames)
    if max_images is not None:
        frames = frames[:max_images]
    samples = []
    for frame_id, image in frames:
        gt_dir = root / "gtFine" / split / image.parent.name
        found = _ground_truth(gt_dir, frame_id)
        if found is None:
            raise DataError(
                f"{image} has no ground truth ({gt_dir / (frame_id + TRAIN_IDS_SUFFIX)} or {LABEL_IDS_SUFFIX} "
                f"missing); extract gtFine_trainvaltest.zip into {root} or remove the image"
            )
        label, kind = found
        size, label_size = image_size(image), image_size(label)
        if size != label_size:
            raise DataError(
                f"{label}: label map is {label_size[0]}x{label_size[1]} but its image {image} is {size[0]}x{size[1]}; "
                "use the gtFine file of the same frame at full resolution"
            )
        instances = gt_dir / f"{frame_id}{INSTANCE_IDS_SUFFIX}"
        samples.append(CityscapesSample(frame_id, image, label, kind, size, instances if instances.is_file() else None))
    ds = CityscapesSplit(name, root, split, samples, scale)
    kinds = ds.label_kinds()
    log.info(
        "cityscapes %s: %d of %d images (%d labelTrainIds, %d labelIds mapped to train ids)%s",
        split, len(samples), total, kinds["trainIds"], kinds["labelIds"], f", scale {scale}" if scale != 1.0 else "",
    )
    return ds
