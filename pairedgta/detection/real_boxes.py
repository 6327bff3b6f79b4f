"""Ground-truth boxes from real datasets' own instance labels, as `Box`es (pairedgta/detection/boxes.py), under the
same rules as the renderer's: a tight box of each object's visible pixels (right/bottom exclusive), `area` = its
pixel count, `truncated` where the box touches the image border, objects under `min_area` pixels (Cityscapes: 100)
ignored as "small", group/crowd regions ignored as "crowd". Only Cityscapes' eight instance classes are objects;
caravan and trailer (instance ids in Cityscapes, but not evaluated) and everything else are left out.

Cityscapes, `<root>/gtFine/<split>/<city>/<city>_<seq>_<frame>_gtFine_instanceIds.png` (16-bit): a value >= 1000 is
one object, labelId = value // 1000; a value < 1000 is a bare labelId, which for an instance class is a group region
(several people, a row of parked cars) that was not split into objects.

ACDC, COCO panoptic format (ACDC's README, "Dataset Structure for detection and panoptic segmentation annotations"):
    <root>/gt_panoptic/<cond>/<split>/<seq>/<seq>_frame_<n>_gt_panoptic.png   RGB, segment id = R + 256 G + 256² B
    <root>/gt_panoptic/<cond>/<cond>_<split>_gt_panoptic.json                  images, annotations, categories
each annotation: image_id, file_name (its PNG) and segments_info [{id, category_id (a Cityscapes labelId), iscrowd,
area, bbox}]; id 0 is unlabelled. Boxes are taken from the PNG's pixels (the JSON's bbox is not trusted for
visibility), so both datasets' boxes mean the same thing.
"""
from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pairedgta.cityscapes import CLASS_NAMES, LABEL_ID_TO_TRAIN_ID
from pairedgta.detection.boxes import CITYSCAPES_MIN_AREA, IGNORE_CROWD, IGNORE_SMALL, INSTANCE_CLASSES, Box
from pairedgta.errors import DataError

# Cityscapes labelId -> index into INSTANCE_CLASSES: {24: person, 25: rider, 26: car, 27: truck, 28: bus, 31: train,
# 32: motorcycle, 33: bicycle}, derived from the label table so the two can never disagree
LABEL_ID_TO_INSTANCE: dict[int, int] = {
    lid: INSTANCE_CLASSES.index(CLASS_NAMES[tid])
    for lid, tid in sorted(LABEL_ID_TO_TRAIN_ID.items()) if CLASS_NAMES[tid] in INSTANCE_CLASSES
}
CITYSCAPES_INSTANCE_SUFFIX = "_gtFine_instanceIds.png"
ACDC_PANOPTIC_SUFFIX = "_gt_panoptic.png"
ACDC_IMAGE_SUFFIX = "_rgb_anon.png"
_WIDE_MODES = ("I;16", "I;16B", "I;16L", "I")
_EIGHT_NEIGHBOURS = np.ones((3, 3), dtype=bool)


def _box(mask: np.ndarray, sl: tuple[slice, slice], width: int, height: int) -> tuple[tuple[float, ...], float, bool]:
    """(xyxy, pixel count, truncated) of the True pixels of `mask`, a crop of the image at `sl`."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    y0, y1 = sl[0].start + int(rows[0]), sl[0].start + int(rows[-1]) + 1
    x0, x1 = sl[1].start + int(cols[0]), sl[1].start + int(cols[-1]) + 1
    truncated = x0 == 0 or y0 == 0 or x1 == width or y1 == height
    return (float(x0), float(y0), float(x1), float(y1)), float(mask.sum()), truncated


def cityscapes_boxes(instance_ids: np.ndarray, min_area: int = CITYSCAPES_MIN_AREA) -> list[Box]:
    """Every object and crowd region of one Cityscapes `*_gtFine_instanceIds.png` (values as read, H x W).

    An object (value >= 1000 of an instance class) gets one box, `instance` = its value, ignored as "small" under
    `min_area` pixels. A group region (a bare labelId of an instance class) gets one box per 8-connected region,
    ignored as "crowd" whatever its size, `instance` = its labelId (shared by that class's regions). Ordered by
    value, then (crowd regions) top to bottom by their first row."""
    from scipy import ndimage

    arr = np.asarray(instance_ids)
    if arr.ndim != 2:
        raise ValueError(f"instance ids must be H x W, got shape {arr.shape}")
    if arr.size and int(arr.min()) < 0:
        raise ValueError(f"instance ids must be >= 0, found {int(arr.min())}")
    h, w = arr.shape
    values = arr.astype(np.int64, copy=False)
    out: list[Box] = []
    for value, sl in enumerate(ndimage.find_objects(values), start=1):
        if sl is None:
            continue
        label_id = value // 1000 if value >= 1000 else value
        label = LABEL_ID_TO_INSTANCE.get(label_id)
        if label is None:
            continue
        mine = values[sl] == value
        if value >= 1000:
            xyxy, area, truncated = _box(mine, sl, w, h)
            out.append(Box(value, label, xyxy, area, IGNORE_SMALL if area < min_area else "", truncated))
            continue
        regions, _ = ndimage.label(mine, structure=_EIGHT_NEIGHBOURS)
        for k, rsl in enumerate(ndimage.find_objects(regions), start=1):
            whole = (slice(sl[0].start + rsl[0].start, sl[0].start + rsl[0].stop),
                     slice(sl[1].start + rsl[1].start, sl[1].start + rsl[1].stop))
            xyxy, area, truncated = _box(regions[rsl] == k, whole, w, h)
            out.append(Box(value, label, xyxy, area, IGNORE_CROWD, truncated))
    return out


def _read_png(path: Path, what: str, fix: str):
    """The opened and loaded PIL image at `path`; a missing or unreadable file is a one-line DataError."""
    from PIL import Image, UnidentifiedImageError

    try:
        im = Image.open(path)
        im.load()
        return im
    except FileNotFoundError:
        raise DataError(f"{path}: {what} not found; {fix}") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataError(f"{path}: not a readable {what} ({type(exc).__name__}); {fix}") from None


def read_cityscapes_boxes(path: str | Path, min_area: int = CITYSCAPES_MIN_AREA) -> list[Box]:
    """`cityscapes_boxes` of one `*_gtFine_instanceIds.png`; a missing, corrupt or not 16-bit single-channel file is
    a one-line DataError naming it and the fix."""
    path = Path(path)
    fix = "extract gtFine_trainvaltest.zip (its *_gtFine_instanceIds.png files) into the Cityscapes root again"
    im = _read_png(path, "Cityscapes instance-id map", fix)
    with im:
        if im.mode not in _WIDE_MODES:
            raise DataError(
                f"{path}: a {im.mode} image; Cityscapes instance ids are a 16-bit single-channel PNG (labelId * 1000 "
                f"+ instance): use the frame's {CITYSCAPES_INSTANCE_SUFFIX}, not its labelIds or color file")
        arr = np.asarray(im)
    if arr.size and int(arr.min()) < 0:
        raise DataError(f"{path}: negative values (down to {int(arr.min())}) in an instance-id map; {fix}")
    return cityscapes_boxes(arr, min_area)


def panoptic_ids(rgb: np.ndarray) -> np.ndarray:
    """COCO panoptic segment ids (R + 256 G + 256² B) of an H x W x 3 PNG's pixels."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"a panoptic PNG must be H x W x 3 (RGB), got shape {rgb.shape}")
    c = rgb.astype(np.int64)
    return c[..., 0] + 256 * c[..., 1] + 65536 * c[..., 2]


def acdc_boxes(panoptic_png_rgb: np.ndarray, segments_info: Sequence[Mapping[str, Any]],
               min_area: int = CITYSCAPES_MIN_AREA) -> list[Box]:
    """Every object and crowd segment of one ACDC (COCO panoptic) annotation: the PNG's pixels (H x W x 3) and its
    `segments_info`. A segment whose category_id is an instance class's Cityscapes labelId gets the tight box of its
    pixels, `instance` = its segment id; iscrowd segments are ignored as "crowd", others under `min_area` pixels as
    "small". Segments without pixels in the PNG are left out (`read_acdc_boxes` refuses such a pair). Ordered by id."""
    from scipy import ndimage

    ids = panoptic_ids(panoptic_png_rgb)
    h, w = ids.shape
    wanted = sorted((int(s["id"]), LABEL_ID_TO_INSTANCE[int(s["category_id"])], bool(s.get("iscrowd", 0)))
                    for s in segments_info if int(s["category_id"]) in LABEL_ID_TO_INSTANCE)
    if not wanted:
        return []
    present, inverse = np.unique(ids, return_inverse=True)
    inverse = inverse.reshape(ids.shape)
    slices = ndimage.find_objects(inverse + 1)
    out: list[Box] = []
    for seg_id, label, crowd in wanted:
        k = int(np.searchsorted(present, seg_id))
        if k == len(present) or present[k] != seg_id or seg_id == 0:
            continue
        sl = slices[k]
        xyxy, area, truncated = _box(inverse[sl] == k, sl, w, h)
        ignore = IGNORE_CROWD if crowd else IGNORE_SMALL if area < min_area else ""
        out.append(Box(seg_id, label, xyxy, area, ignore, truncated))
    return out


@functools.lru_cache(maxsize=4)
def _panoptic_json(path: str, mtime_ns: int, size: int) -> tuple[dict, dict]:
    """A split's panoptic JSON (tens of MB for ACDC's train split), parsed once per version of the file: its
    images by file name and by base name, and its annotations by image id."""
    raw = json.loads(Path(path).read_text())
    images: dict[str, Any] = {}
    for im in raw["images"]:
        images[str(im["file_name"])] = im
        images.setdefault(Path(str(im["file_name"])).name, im)
    annotations: dict[Any, Any] = {("image", a["image_id"]): a for a in raw["annotations"]}
    for a in raw["annotations"]:
        annotations.setdefault(("png", Path(str(a["file_name"])).name), a)
    return images, annotations


def read_acdc_boxes(png_path: str | Path, json_path: str | Path, image_file_name: str,
                    min_area: int = CITYSCAPES_MIN_AREA) -> list[Box]:
    """`acdc_boxes` of the image `image_file_name` (its `file_name` in the JSON, e.g. fog/val/GOPR0475/
    GOPR0475_frame_000041_rgb_anon.png, or just its base name) from its panoptic PNG and the split's panoptic JSON;
    where the JSON lists no such image, the annotation whose file_name has the PNG's base name is used. Missing or
    corrupt files, a frame the JSON does not annotate, a PNG of another size than its image, and a PNG and JSON that
    do not belong together (a listed segment absent from the PNG, a segment of the PNG not listed: panopticapi's
    checks) are one-line DataErrors."""
    png_path, json_path = Path(png_path), Path(json_path)
    fix_json = ("extract gt_panoptic_trainval.zip into the ACDC root again (expected "
                "<root>/gt_panoptic/<cond>/<cond>_<split>_gt_panoptic.json)")
    try:
        st = json_path.stat()
        images, annotations = _panoptic_json(str(json_path), st.st_mtime_ns, st.st_size)
    except FileNotFoundError:
        raise DataError(f"{json_path}: ACDC panoptic annotations not found; {fix_json}") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{json_path}: not a COCO panoptic JSON ({type(exc).__name__}: {exc}); {fix_json}") from None
    image = images.get(str(image_file_name)) or images.get(Path(str(image_file_name)).name)
    ann = annotations.get(("image", image["id"]) if image is not None else ("png", png_path.name))
    if ann is None:
        raise DataError(f"{json_path}: no panoptic annotation of {image_file_name}; use the JSON of the image's own "
                        "condition and split (<cond>_<split>_gt_panoptic.json)")
    im = _read_png(png_path, "ACDC panoptic PNG", "extract gt_panoptic_trainval.zip into the ACDC root again")
    with im:
        if im.mode != "RGB":
            raise DataError(f"{png_path}: a {im.mode} image; ACDC panoptic labels are RGB PNGs (segment id = R + 256 G "
                            f"+ 256² B): use the frame's {ACDC_PANOPTIC_SUFFIX}")
        rgb = np.asarray(im)
    h, w = rgb.shape[:2]
    if image is not None and (image.get("width", w), image.get("height", h)) != (w, h):
        raise DataError(f"{png_path}: {w}x{h}, but {json_path} says its image is {image.get('width')}x"
                        f"{image.get('height')}; use the panoptic PNG and JSON of the same frame at full resolution")
    try:
        segments = list(ann["segments_info"])
        listed = {int(s["id"]) for s in segments}
        boxes = acdc_boxes(rgb, segments, min_area)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{json_path}: segments_info of {image_file_name} is malformed ({type(exc).__name__}: "
                        f"{exc}); {fix_json}") from None
    in_png = {int(v) for v in np.unique(panoptic_ids(rgb))} - {0}
    absent, unlisted = sorted(listed - in_png), sorted(in_png - listed)
    if absent or unlisted:
        what = (f"segments {absent[:5]} of the JSON are not in the PNG" if absent else
                f"segments {unlisted[:5]} of the PNG are not in the JSON")
        raise DataError(f"{png_path}: {what} ({json_path}); the PNG and the JSON are not of the same frame and "
                        "release: extract both from one gt_panoptic_trainval.zip")
    return boxes


def acdc_panoptic_json(png_path: str | Path) -> Path:
    """The split's panoptic JSON of a PNG in ACDC's layout: <root>/gt_panoptic/<cond>/<cond>_<split>_gt_panoptic.json
    for <root>/gt_panoptic/<cond>/<split>/<seq>/<name>_gt_panoptic.png."""
    png_path = Path(png_path)
    split, cond_dir = png_path.parents[1].name, png_path.parents[2]
    return cond_dir / f"{cond_dir.name}_{split}_gt_panoptic.json"


def acdc_image_file_name(png_path: str | Path) -> str:
    """The image's name relative to <root>/rgb_anon (<cond>/<split>/<seq>/<seq>_frame_<n>_rgb_anon.png) of a PNG
    in ACDC's layout; `read_acdc_boxes` also matches it by its base name."""
    png_path = Path(png_path)
    name = png_path.name[: -len(ACDC_PANOPTIC_SUFFIX)] + ACDC_IMAGE_SUFFIX
    return "/".join((png_path.parents[2].name, png_path.parents[1].name, png_path.parent.name, name))


def read_real_boxes(path: str | Path, min_area: int = CITYSCAPES_MIN_AREA) -> list[Box]:
    """The boxes of one real dataset's instance file as its reader puts it in `Group.instances` (or
    `CityscapesSample.instances`): a Cityscapes `*_gtFine_instanceIds.png` or an ACDC `*_gt_panoptic.png` (its JSON
    and image name found from ACDC's layout)."""
    path = Path(path)
    if path.name.endswith(CITYSCAPES_INSTANCE_SUFFIX):
        return read_cityscapes_boxes(path, min_area)
    if path.name.endswith(ACDC_PANOPTIC_SUFFIX):
        return read_acdc_boxes(path, acdc_panoptic_json(path), acdc_image_file_name(path), min_area)
    raise DataError(f"{path}: neither a Cityscapes {CITYSCAPES_INSTANCE_SUFFIX} nor an ACDC {ACDC_PANOPTIC_SUFFIX} "
                    "file; point the dataset at the instance labels of its own release")


__all__ = ["ACDC_PANOPTIC_SUFFIX", "CITYSCAPES_INSTANCE_SUFFIX", "LABEL_ID_TO_INSTANCE", "acdc_boxes",
           "acdc_image_file_name", "acdc_panoptic_json", "cityscapes_boxes", "panoptic_ids", "read_acdc_boxes",
           "read_cityscapes_boxes", "read_real_boxes"]
