"""Paired datasets: groups of images of one scene keyed by condition name, plus image I/O."""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from PIL import Image, UnidentifiedImageError

from pairedgta.conditions import ConditionGrid
from pairedgta.errors import DataError

log = logging.getLogger(__name__)
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class Group:
    """X_k: one scene under several conditions; `labels` holds ground truth where the source has it."""

    group_id: str
    images: dict[str, Path]
    labels: dict[str, Path] = field(default_factory=dict)
    descriptor: Path | None = None
    transmittance: dict[str, Path] = field(default_factory=dict)  # generated datasets from backends with depth
    # instance ids (uint16, one id per object, the same object the same id in every condition): detection's ground
    # truth boxes (pairedgta/detection/boxes.py); or a renderer's 2D boxes (`<condition>_boxes.json`, DeepGTAV)
    instances: dict[str, Path] = field(default_factory=dict)


def share_clean_truth(group: Group, grid: ConditionGrid | None) -> Group:
    """`group` with each corruption condition's ground truth (labels, instances or boxes) taken from the clean
    condition it corrupts: nothing moved, so the clean image's truth is exact for it (pairedgta/corruptions.py)."""
    if grid is None or not grid.corrupted:
        return group
    labels, instances = dict(group.labels), dict(group.instances)
    for c in grid.corrupted:
        if c.name in group.images:
            if c.source in group.labels:
                labels[c.name] = group.labels[c.source]
            if c.source in group.instances:
                instances[c.name] = group.instances[c.source]
    return replace(group, labels=labels, instances=instances)


@dataclass
class PairedDataset:
    name: str
    root: Path
    reference: str
    conditions: list[str]
    groups: list[Group]
    skipped_without_reference: int = 0
    grid: ConditionGrid | None = None  # the conditions it is evaluated over (ACDC brings its own)

    def __len__(self) -> int:
        return len(self.groups)

    def fingerprint(self) -> str:
        """Identity of an external dataset for the cache: relative path, size and sha256 of every used
        file (content hashes memoised on path, size and mtime under the cache dir, as DVC does), so a
        file replaced by another of the same size is not taken for the old one."""
        from pairedgta.filehash import default

        memo = default()
        h = hashlib.sha256()
        for g in self.groups:
            for kind, files in (("", g.images), ("L|", g.labels), ("T|", g.transmittance), ("I|", g.instances)):
                for cond in sorted(files):
                    p = files[cond]
                    st = p.stat()
                    h.update(f"{kind}{g.group_id}|{cond}|{p.relative_to(self.root)}|{st.st_size}|{memo.sha256(p, st)}\n".encode())
        return h.hexdigest()[:16]


def load_image(path: Path) -> np.ndarray:
    """RGB uint8 H x W x 3; a corrupt or missing file is a one-line DataError naming it. An image that reads
    but deserves a word (one flat colour; not 8-bit RGB and converted) is noted (see `image_notes`)."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode.startswith("I"):  # 16/32-bit greyscale: PIL's convert("RGB") clips it to white
                arr, done = _wide_grey_to_rgb(path, np.asarray(im))
                note_image(path, CONVERTED, f"{im.mode} greyscale {done}, copied into R, G and B")
            elif im.mode == "F":
                raise DataError(f"{path}: a floating-point image; export it as 8-bit (or 16-bit) RGB or greyscale PNG")
            elif im.mode == "RGB":
                arr = np.asarray(im)
            else:
                done = _conversion(im)
                arr = np.asarray(im.convert("RGB"))
                if done:
                    note_image(path, CONVERTED, done)
    except FileNotFoundError:
        raise DataError(f"{path}: image not found; regenerate the dataset or fix dataset.root") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise DataError(f"{path}: not a readable image ({type(exc).__name__}); re-export or delete the file") from None
    if is_flat(arr):
        colour = "black" if not arr[0, 0].any() else f"RGB {tuple(int(v) for v in arr[0, 0])}"
        note_image(path, BLANK, f"all {colour}")
    return arr


def _wide_grey_to_rgb(path: Path, arr: np.ndarray) -> tuple[np.ndarray, str]:
    """A 16-bit (or 32-bit int) greyscale image as 8-bit RGB, scaled from its bit depth; and what was done."""
    top = int(arr.max()) if arr.size else 0
    if top > 65535 or int(arr.min()) < 0:
        raise DataError(f"{path}: greyscale values {int(arr.min())}..{top} fit no 8- or 16-bit range; re-export the image")
    grey = arr if top <= 255 else arr / 257.0  # 65535 -> 255
    grey = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    done = "read as 8 bits (its values are 0..255)" if top <= 255 else "scaled from 16 to 8 bits (divided by 257)"
    return np.repeat(grey[..., None], 3, axis=2), done


def _conversion(im: Image.Image) -> str | None:
    """What reading `im` (not RGB, not wide greyscale) as 8-bit RGB changes, or None when nothing is lost
    (a palette image, an alpha channel that is opaque everywhere)."""
    mode = im.mode
    alpha = mode in ("RGBA", "LA", "PA") and im.getchannel("A").getextrema()[0] < 255
    if mode == "P":
        return "palette with transparency: transparency dropped" if "transparency" in im.info else None
    if mode in ("RGBA", "RGBX", "PA"):
        return f"{mode}: its alpha channel (not opaque everywhere) dropped" if alpha else None
    if mode in ("L", "LA", "1"):
        grey = "1-bit black-and-white" if mode == "1" else "8-bit greyscale"
        return f"{mode}: {grey} copied into R, G and B" + (", its alpha channel dropped" if alpha else "")
    return f"{mode}: converted to RGB by Pillow"


def is_flat(arr: np.ndarray) -> bool:
    """Whether every pixel has one colour (a blank image). A strided sample first, so an ordinary image
    costs a few thousand comparisons; only a flat sample is confirmed on the whole array."""
    if arr.size == 0:
        return False
    step = max(1, min(arr.shape[:2]) // 32)
    sample = arr[::step, ::step]
    if not (sample == sample[0, 0]).all():
        return False
    rows = arr.reshape(arr.shape[0], -1)
    return bool((rows == rows[0]).all()) and bool((arr[0] == arr[0, 0]).all())


# -- what a run should hear about the images it read ------------------------------------------------------
# A blank image or one converted on reading is no error, but a result built on it should say so: once per
# dataset (a few files named, and the count), not once per image. `image_notes` opens a scope for that; the
# images may be decoded in DataLoader worker processes (evaluate.num_workers), so notes go to a file that the
# scope names in the environment, which forked and spawned workers both inherit.
BLANK, CONVERTED = "blank", "converted"
NOTES_ENV = "PAIREDGTA_IMAGE_NOTES"
SHOWN = 3  # files a warning names; the rest are counted
_SCOPES: list[tuple[str, set[tuple[str, str]]]] = []  # this process's open scopes: (notes file, notes warned)
_warned: set[tuple[str, str]] = set()  # (kind, file) warned about in this process: not again outside a scope


def note_image(path: Path, kind: str, detail: str) -> None:
    """Record that `path` read with a note of `kind` (BLANK, CONVERTED): warned when the open scope ends, or at
    once outside any scope (once per file and process, e.g. a figure reading images a stage warned about)."""
    where = os.environ.get(NOTES_ENV)
    if where:
        try:  # no O_CREAT: a scope that has ended takes no more notes
            fd = os.open(where, os.O_WRONLY | os.O_APPEND)
        except OSError:
            fd = -1
        if fd >= 0:
            try:
                os.write(fd, (json.dumps([kind, str(path), detail]) + "\n").encode())
            finally:
                os.close(fd)
            return
    if (kind, str(path)) not in _warned:
        _warned.add((kind, str(path)))
        log.warning("%s", _message("reading images", kind, [(str(path), detail)], 1))


def _message(what: str, kind: str, notes: list[tuple[str, str]], count: int) -> str:
    named = ", ".join(f"{p} ({d})" for p, d in notes[:SHOWN])
    more = f" and {count - SHOWN} more" if count > SHOWN else ""
    if kind == BLANK:
        return (f"{what}: {count} image(s) are one flat colour (blank): {named}{more}; blank images agree with each "
                "other perfectly, so xi and the pixel agreement on them (up to 1.0) mean nothing: re-render or "
                "re-export them, or remove their groups")
    return (f"{what}: {count} image(s) are not 8-bit RGB and were converted on reading: {named}{more}; export "
            "8-bit RGB images to have them read as they are")


@contextlib.contextmanager
def image_notes(what: str) -> Iterator[None]:
    """Collect the notes of the images read inside, in this process and its workers; at the end, one warning
    per kind of note (blank, converted) naming a few files and the count, `what` (e.g. "dataset paired_gta")
    saying who read them. Scopes nest: an inner one warns about what was read inside it, and the outermost
    warns about nothing twice."""
    if _SCOPES:
        path, said = _SCOPES[0]
        start = os.path.getsize(path) if os.path.isfile(path) else 0
        owner, previous = False, None
    else:
        fd, path = tempfile.mkstemp(prefix="pairedgta-image-notes-", suffix=".jsonl")
        os.close(fd)
        said, start, owner = set(), 0, True
        previous = os.environ.get(NOTES_ENV)
        os.environ[NOTES_ENV] = path
    _SCOPES.append((path, said))
    try:
        yield
    finally:
        _SCOPES.pop()
        try:
            with open(path, "rb") as f:
                f.seek(start)
                lines = f.read().decode("utf-8", "replace").splitlines()
        except OSError:
            lines = []
        if owner:
            if previous is None:
                os.environ.pop(NOTES_ENV, None)
            else:
                os.environ[NOTES_ENV] = previous
            with contextlib.suppress(OSError):
                os.unlink(path)
        by_kind: dict[str, dict[str, str]] = {}
        for line in lines:
            try:
                kind, file, detail = json.loads(line)
            except ValueError:  # a worker killed mid-write
                continue
            if (kind, file) not in said:
                by_kind.setdefault(kind, {}).setdefault(file, detail)
        for kind in sorted(by_kind):
            notes = sorted(by_kind[kind].items())
            said.update((kind, file) for file, _ in notes)
            _warned.update((kind, file) for file, _ in notes)
            log.warning("%s", _message(what, kind, notes, len(notes)))


def load_label(path: Path, train_ids: bool = True) -> np.ndarray:
    """uint8 label map. train_ids: values must be 0-18 or 255 (void); else any 8-bit id (Cityscapes
    labelIds, mapped by their reader)."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode not in ("L", "P", "I;16", "I;16B", "I;16L", "I"):
                raise DataError(f"{path}: label map has mode {im.mode}; expected a single-channel PNG of train ids")
            arr = np.asarray(im)
    except FileNotFoundError:
        raise DataError(f"{path}: label map not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise DataError(f"{path}: not a readable label map ({type(exc).__name__}); regenerate it") from None
    # anything but 0..18 and 255 would wrap (16-bit) or count as a class no model predicts (labelIds)
    bad = (arr > 18) & (arr != 255) if train_ids else arr > 255
    if bad.any():
        found = sorted(int(v) for v in np.unique(arr[bad]))[:6]
        hint = ("these look like Cityscapes labelIds (road = 7, car = 26): use the *_labelTrainIds.png files or convert "
                "them with cityscapesscripts" if max(found) <= 33 else "re-export it with train ids")
        if not train_ids:
            raise DataError(f"{path}: label values {found} do not fit 8 bits; re-export the label map")
        raise DataError(f"{path}: label values {found} are not Cityscapes train ids (0-18, 255 = void); {hint}")
    return arr.astype(np.uint8)


def load_transmittance(path: Path) -> np.ndarray:
    """float32 in [0, 1] from a 16-bit transmittance map (generate stage: 65535 = fully visible)."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise DataError(f"{path}: transmittance map has mode {im.mode}; expected a 16-bit greyscale PNG "
                                "(regenerate the dataset)")
            arr = np.asarray(im)
    except FileNotFoundError:
        raise DataError(f"{path}: transmittance map not found; regenerate the dataset or set metric.min_transmittance=0") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise DataError(f"{path}: not a readable transmittance map ({type(exc).__name__}); regenerate it") from None
    if arr.size and (int(arr.min()) < 0 or int(arr.max()) > 65535):
        raise DataError(f"{path}: transmittance values outside 0..65535; regenerate the dataset")
    return (arr / 65535.0).astype(np.float32)


def image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DataError(f"{path}: image not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise DataError(f"{path}: not a readable image ({type(exc).__name__}); re-export or delete the file") from None


def load_group_images(group: Group, conditions: Sequence[str]) -> dict[str, np.ndarray]:
    """All images of a group for `conditions` (those present); sizes must agree within the group."""
    images = {c: load_image(group.images[c]) for c in conditions if c in group.images}
    shapes = {c: im.shape for c, im in images.items()}
    if len(set(shapes.values())) > 1:
        detail = ", ".join(f"{group.images[c].name}={s[1]}x{s[0]}" for c, s in shapes.items())
        raise DataError(f"group {group.group_id}: images differ in size ({detail}); re-render or remove the group")
    return images


@dataclass(frozen=True)
class LabelMaps:
    """A per-group layer of label maps that a stage derives from a dataset (the pseudo-labels): one
    single-channel PNG of train ids per group under `<root>/labels/`. The layout lives here, with the
    datasets, so the stage that writes it and every reader agree without naming files themselves."""

    root: Path

    def path(self, group_id: str) -> Path:
        return Path(self.root) / "labels" / f"{group_id}.png"

    def load(self, group_id: str) -> np.ndarray:
        return load_label(self.path(group_id))

    def save(self, group_id: str, labels: np.ndarray) -> None:
        path = self.path(group_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        save_png_atomic(labels, path)


def save_png_atomic(array: np.ndarray, path: Path) -> None:
    """Under a temporary name, renamed when complete; a failed write (a full disk) leaves nothing behind."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        Image.fromarray(array).save(tmp, format="PNG")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


