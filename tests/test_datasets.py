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
