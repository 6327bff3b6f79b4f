"""Readers of the released PairedGTA layout and of the project's own layout."""
from __future__ import annotations

import pytest
from omegaconf import OmegaConf
from PIL import Image

from pairedgta.conditions import build_condition_grid
from pairedgta.datasets import load_group_images, load_image, open_dataset
from pairedgta.errors import DataError
from pairedgta.testing.cli import compose_cfg
from pairedgta.testing.datasets import write_release



@pytest.fixture
def grid():
    return build_condition_grid(OmegaConf.to_container(compose_cfg([]).conditions))


def test_release_layout_groups_and_missing_reference(tmp_path, grid, caplog):
    write_release(tmp_path, [3, 10, 7], missing={(7, "Day-EXTRASUNNY"), (3, "Night-RAIN")})
    (tmp_path / "Day" / "notes.txt").write_text("x")
    Image.new("RGB", (64, 32)).save(tmp_path / "Day" / "5_Day_SNOW.png")  # condition outside the grid
    ds = open_dataset({"kind": "paired_gta", "name": "paired_gta"}, grid, root=tmp_path)
    assert [g.group_id for g in ds.groups] == ["3", "10"]
    assert ds.skipped_without_reference == 1
    assert "Night-RAIN" not in ds.groups[0].images and len(ds.groups[1].images) == 9
    assert "skipped 1 group" in caplog.text
    fp = ds.fingerprint()
    assert fp == open_dataset({"kind": "paired_gta"}, grid, root=tmp_path).fingerprint()


def test_release_layout_errors(tmp_path, grid):
    with pytest.raises(DataError, match="does not exist"):
        open_dataset({"kind": "paired_gta"}, grid, root=tmp_path / "nope")
    with pytest.raises(DataError, match="holds no"):
        open_dataset({"kind": "paired_gta"}, grid, root=tmp_path)


def test_corrupt_and_mismatched_images(tmp_path, grid):
    write_release(tmp_path, [1])
    ds = open_dataset({"kind": "paired_gta"}, grid, root=tmp_path)
    bad = tmp_path / "Day" / "1_Day_RAIN.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(DataError, match="1_Day_RAIN.png: not a readable image"):
        load_image(bad)
    Image.new("RGB", (20, 32)).save(bad)
    with pytest.raises(DataError, match="differ in size"):
        load_group_images(ds.groups[0], grid.names)


def test_wide_images_and_out_of_range_label_ids(tmp_path):
    """A 16-bit greyscale image is scaled to 8 bits (PIL's convert would clip it to white); label values
    that are not train ids are one line (16-bit ids used to wrap modulo 256; labelIds gave mIoU 0.005)."""
    import numpy as np
    import pytest
    from PIL import Image

    from pairedgta.datasets import load_image, load_label
    from pairedgta.errors import DataError

    grey = np.array([[0, 257 * 128, 65535]], dtype=np.uint16)
    Image.fromarray(grey).save(tmp_path / "g16.png")
    img = load_image(tmp_path / "g16.png")
    assert img.shape == (1, 3, 3) and img[0, :, 0].tolist() == [0, 128, 255] and (img[..., 0] == img[..., 2]).all()
    Image.fromarray(np.array([[0, 18, 255]], dtype=np.uint8)).save(tmp_path / "ok.png")
    assert load_label(tmp_path / "ok.png").tolist() == [[0, 18, 255]]
    Image.fromarray(np.array([[7, 26, 0]], dtype=np.uint8)).save(tmp_path / "labelids.png")
    with pytest.raises(DataError, match=r"labelids.png: label values \[26\] are not Cityscapes train ids.*labelIds"):
        load_label(tmp_path / "labelids.png")
    Image.fromarray(np.array([[1, 256 + 13]], dtype=np.uint16)).save(tmp_path / "wide.png")
    with pytest.raises(DataError, match=r"label values \[269\] are not Cityscapes train ids.*re-export"):
        load_label(tmp_path / "wide.png")


def test_a_generated_index_with_wrong_types_is_one_line(tmp_path):
    import json

    import pytest
    from omegaconf import OmegaConf

    from pairedgta.conditions import build_condition_grid
    from pairedgta.configs import CONFIG_DIR
    from pairedgta.datasets.generated import open_generated
    from pairedgta.errors import DataError

    grid = build_condition_grid(OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "conditions" / "paper.yaml")))
    for index in ({"scenes": "abc"}, {"scenes": [{"scene_id": 1, "dir": 5}]}, [1, 2],
                  {"scenes": [{"scene_id": "00000", "dir": "../../etc"}]}):
        (tmp_path / "index.json").write_text(json.dumps(index))
        with pytest.raises(DataError, match="index.json: not a generated dataset's index"):
            open_generated(root=tmp_path, grid=grid)


def _blank(path, colour=(0, 0, 0), size=(64, 32)):
    import numpy as np

    Image.fromarray(np.full((size[1], size[0], 3), colour, np.uint8)).save(path)


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]


def test_blank_images_are_one_warning_per_dataset_naming_a_few(tmp_path, caplog):
    """An all-black (or any one-colour) image reads fine but scores xi = 1 against another blank one: one
    warning for the whole scope, with three files named and the rest counted, never one per image."""
    import numpy as np

    from pairedgta.datasets import image_notes

    blanks = [tmp_path / f"{i}_Night_RAIN.png" for i in range(5)]
    for i, p in enumerate(blanks):
        _blank(p, (0, 0, 0) if i else (90, 20, 200))
    almost = tmp_path / "almost.png"  # one pixel off: not blank
    arr = np.zeros((32, 64, 3), np.uint8)
    arr[31, 63, 2] = 1
    Image.fromarray(arr).save(almost)
    with caplog.at_level("WARNING"), image_notes("dataset paired_gta"):
        for p in [*blanks, almost, *blanks]:  # read twice, as evaluate reads a reference image per model
            assert load_image(p).shape == (32, 64, 3)
    (msg,) = _warnings(caplog)
    assert msg.startswith("dataset paired_gta: 5 image(s) are one flat colour (blank): ")
    assert f"{blanks[0]} (all RGB (90, 20, 200))" in msg and f"{blanks[1]} (all black)" in msg and "and 2 more" in msg
    assert "almost.png" not in msg and str(blanks[4]) not in msg
    caplog.clear()
    with caplog.at_level("WARNING"), image_notes("dataset again"):  # a new scope (a new run) says it again
        load_image(blanks[0])
    assert len(_warnings(caplog)) == 1 and "1 image(s)" in _warnings(caplog)[0]


def test_images_converted_on_reading_are_named_with_what_was_done(tmp_path, caplog):
    """16-bit greyscale, 8-bit greyscale and a transparent RGBA image are converted to 8-bit RGB with one warning
    naming each file and the conversion; a palette image and an opaque RGBA image lose nothing and say nothing."""
    import numpy as np

    from pairedgta.datasets import image_notes

    rng = np.random.default_rng(0)
    Image.fromarray(np.array([[0, 257 * 128, 65535]], dtype=np.uint16)).save(tmp_path / "g16.png")
    Image.fromarray(rng.integers(0, 255, (8, 8), dtype=np.uint8)).save(tmp_path / "grey.png")
    Image.fromarray(rng.integers(0, 255, (8, 8, 4), dtype=np.uint8), "RGBA").save(tmp_path / "see_through.png")
    opaque = np.dstack([rng.integers(0, 255, (8, 8, 3), dtype=np.uint8), np.full((8, 8), 255, np.uint8)])
    Image.fromarray(opaque, "RGBA").save(tmp_path / "opaque.png")
    Image.fromarray(rng.integers(0, 255, (8, 8, 3), dtype=np.uint8)).convert("P").save(tmp_path / "palette.png")
    Image.fromarray(rng.integers(0, 255, (8, 8, 3), dtype=np.uint8)).save(tmp_path / "rgb.png")
    with caplog.at_level("WARNING"), image_notes("dataset generated"):
        for name in ("g16", "grey", "see_through", "opaque", "palette", "rgb"):
            img = load_image(tmp_path / f"{name}.png")
            assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    (msg,) = _warnings(caplog)
    assert msg.startswith("dataset generated: 3 image(s) are not 8-bit RGB and were converted on reading: ")
    assert f"{tmp_path / 'g16.png'} (I;16 greyscale scaled from 16 to 8 bits (divided by 257), copied into R, G and B)" in msg
    assert f"{tmp_path / 'grey.png'} (L: 8-bit greyscale copied into R, G and B)" in msg
    assert f"{tmp_path / 'see_through.png'} (RGBA: its alpha channel (not opaque everywhere) dropped)" in msg
    assert not {"opaque.png", "palette.png", "rgb.png"} & set(msg.replace(",", " ").replace("/", " ").split())


@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_notes_made_in_worker_processes_reach_the_scope(tmp_path, caplog, start):
    """evaluate.num_workers decodes images in DataLoader workers: their notes reach the run's one warning."""
    import multiprocessing as mp

    from pairedgta.datasets import image_notes

    paths = [tmp_path / f"{i}.png" for i in range(4)]
    for p in paths:
        _blank(p, size=(8, 8))
    with caplog.at_level("WARNING"), image_notes("dataset workers"):
        with mp.get_context(start).Pool(2) as pool:
            assert len(pool.map(load_image, paths)) == 4
    (msg,) = _warnings(caplog)
    assert msg.startswith("dataset workers: 4 image(s) are one flat colour") and "and 1 more" in msg


def test_a_blank_image_read_outside_a_scope_is_warned_once(tmp_path, caplog):
    import os

    from pairedgta.datasets.base import NOTES_ENV

    assert NOTES_ENV not in os.environ  # a scope leaves no trace in the environment
    _blank(tmp_path / "b.png", (7, 7, 7))
    with caplog.at_level("WARNING"):
        load_image(tmp_path / "b.png")
        load_image(tmp_path / "b.png")
    (msg,) = _warnings(caplog)
    assert f"{tmp_path / 'b.png'} (all RGB (7, 7, 7))" in msg


def test_the_blank_check_costs_little_beside_decoding(tmp_path):
    """The check looks at a strided sample; only a one-colour sample is confirmed on the whole image."""
    import time

    import numpy as np

    from pairedgta.datasets.base import is_flat

    arr = np.random.default_rng(1).integers(0, 255, (1024, 2048, 3), dtype=np.uint8)
    t0 = time.perf_counter()
    for _ in range(20):
        assert not is_flat(arr)
    per_image = (time.perf_counter() - t0) / 20
    assert per_image < 5e-3, per_image  # decoding a PNG of this size takes ~100 ms
    flat = np.full((1024, 2048, 3), 9, np.uint8)
    assert is_flat(flat)
    flat[1023, 2047, 1] = 8  # off in the last pixel only: the sample misses it, the full check does not
    assert not is_flat(flat)
