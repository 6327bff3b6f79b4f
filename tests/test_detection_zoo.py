"""The detection zoo (task=detection): every member ships float16 weights with a model card and a model config,
loads strictly and detects on a render; task=detection runs all of them against the reference."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from safetensors import safe_open

from pairedgta.models import build_model, model_config, model_kind
from pairedgta.testing.cli import compose_cfg

# the detection zoo's own distribution (zoo/detection), beside the package's segmentation zoo
WEIGHTS = Path(__file__).resolve().parents[1] / "zoo" / "detection" / "pairedgta_detection_zoo"


def members() -> list[str]:
    return sorted(d.name for d in WEIGHTS.iterdir() if d.is_dir() and not d.name.startswith(("_", "."))
                  and model_kind(model_config(d.name)) == "detector")


def test_every_member_is_float16_carded_loaded_and_run_by_the_task():
    names = members()
    assert len(names) >= 22 and len({model_config(n)["family"] for n in names}) >= 3  # 21 ranked + the reference
    cfg = compose_cfg(["+experiment=det_zoo"])  # the whole zoo; the main job runs a part of it
    assert cfg.task == "detection" and sorted(cfg.models) == names and cfg.reference_model == "demo_det_reference"
    study = compose_cfg(["+experiment=metric_validity", "task=detection"])  # the study ranks every member but one
    assert sorted(study.models) == sorted(set(names) - {"demo_det_reference"})
    assert study.reference_model == "demo_det_reference"
    corruptions = compose_cfg(["+experiment=corruptions_vs_rendered", "task=detection"])  # every member, as it says
    assert sorted(corruptions.models) == names and corruptions.reference_model == "demo_det_reference"
    main = compose_cfg(["task=detection"])
    assert set(main.models) < set(names) and main.reference_model == "demo_det_reference"
    image = np.random.default_rng(0).integers(0, 256, (1, 256, 512, 3), dtype=np.uint8)
    for name in names:
        folder = WEIGHTS / name
        with safe_open(str(folder / "model.safetensors"), "pt") as f:
            assert {str(f.get_tensor(k).dtype) for k in f.keys()} <= {"torch.float16", "torch.int64"}, name
        card = json.loads((folder / "model_card.json").read_text())
        assert card and (folder / "README.md").read_text().strip(), name
        detector = build_model(name)
        (d,) = detector.detect(image)
        assert d.boxes.shape[1:] == (4,) and len(d.scores) == len(d.labels) <= 100, name
        assert 0.0 < detector.score_threshold < 1.0


def test_members_resolve_into_the_zoo_distribution_and_without_it_one_line_says_how_to_install_it(monkeypatch):
    import pytest

    from pairedgta.errors import ModelError
    from pairedgta.models import hf_common
    from pairedgta.models.availability import check_available
    from pairedgta.models.checkpoint import read_state_dict

    for name in members():
        path = model_config(name)["checkpoint_path"]
        assert path == f"pkg://models/weights/{name}/model.safetensors"  # the string the cache keys were made with
        assert hf_common.resolve_checkpoint_path(path) == WEIGHTS / name / "model.safetensors"
    # README's one install line installs the companion, as the error below tells the user
    readme = (WEIGHTS.parents[2] / "README.md").read_text()
    assert "-e ./zoo/detection" in readme.split("## Install, run, test")[1].split("```bash\n")[1].splitlines()[0]
    # an installed pairedgta without its companion: no source tree beside it, nothing importable
    monkeypatch.setattr(hf_common, "detection_zoo_dir", lambda: None)
    small = model_config("demo_fcos_small")["checkpoint_path"]
    for call in (lambda: check_available([model_config("demo_det_reference")]),
                 lambda: read_state_dict(small, model_name="demo_fcos_small")):
        with pytest.raises(ModelError) as err:
            call()
        msg = str(err.value)
        assert "\n" not in msg and "pairedgta-detection-zoo" in msg and "pip install -e ./zoo/detection" in msg, msg
    check_available([model_config("demo_segformer"), model_config("demo_ddrnet")])  # the package's own zoo is there


def test_an_installed_package_finds_the_installed_companion(tmp_path, monkeypatch):
    """No source tree beside the package (a wheel in site-packages): the importable pairedgta_detection_zoo."""
    from pairedgta.models import hf_common

    site = tmp_path / "site"
    (site / "pairedgta_detection_zoo" / "demo_x").mkdir(parents=True)
    (site / "pairedgta_detection_zoo" / "__init__.py").write_text("")
    (site / "pairedgta_detection_zoo" / "demo_x" / "model.safetensors").write_bytes(b"x")
    monkeypatch.setattr(hf_common, "PACKAGE_DIR", site / "pairedgta")
    monkeypatch.syspath_prepend(str(site))
    assert hf_common.detection_zoo_dir() == site / "pairedgta_detection_zoo"
    assert hf_common.resolve_checkpoint_path("pkg://models/weights/demo_x/model.safetensors") == (
        site / "pairedgta_detection_zoo" / "demo_x" / "model.safetensors")
    # a file the package has itself stays the package's
    (site / "pairedgta" / "models" / "weights" / "demo_x").mkdir(parents=True)
    (site / "pairedgta" / "models" / "weights" / "demo_x" / "model.safetensors").write_bytes(b"y")
    assert hf_common.resolve_checkpoint_path("pkg://models/weights/demo_x/model.safetensors") == (
        site / "pairedgta" / "models" / "weights" / "demo_x" / "model.safetensors")
