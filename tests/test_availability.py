"""Models a run cannot build are refused before a new dataset is rendered, not after (issue: offline,
+experiment=paper_table rendered for 16 min, then failed on the hub)."""
from __future__ import annotations

import pytest

from pairedgta.errors import ModelError
from pairedgta.models import availability
from pairedgta.models import model_config


def test_each_kind_of_model_source_is_checked(tmp_path, monkeypatch):
    monkeypatch.setattr(availability, "_hub_cached", lambda hub_id: False)
    monkeypatch.setattr(availability, "_hub_answers", lambda hub_id, timeout: "ConnectError: no network")
    # the zoo ships its weights, tiny models are random-init: nothing to fetch
    availability.check_available([model_config(n) for n in ("demo_segformer", "demo_ddrnet", "tiny_segformer")])
    with pytest.raises(ModelError, match="model 'segformer_b5': 'nvidia/segformer-b5.*' is not in the local Hugging "
                                         "Face cache and the hub does not answer \\(ConnectError: no network\\); "
                                         "download it elsewhere .*model_overrides.segformer_b5.path=DIR"):
        availability.check_available([model_config("segformer_b5")])
    with pytest.raises(ModelError, match="model 'pidnet_m' needs its checkpoint \\(PIDNet_M_Cityscapes_val.pt"):
        availability.check_available([model_config("pidnet_m")])
    with pytest.raises(ModelError, match="checkpoint file .*nope.pt does not exist"):
        availability.check_available([{**model_config("pidnet_m"), "checkpoint_path": str(tmp_path / "nope.pt")}])
    with pytest.raises(ModelError, match="model.path=.*missing is not a directory"):
        availability.check_available([{**model_config("segformer_b5"), "path": str(tmp_path / "missing")}])
    # a hub model in the local cache, or a hub that answers, passes
    monkeypatch.setattr(availability, "_hub_cached", lambda hub_id: True)
    availability.check_available([model_config("segformer_b5")])
    monkeypatch.setattr(availability, "_hub_cached", lambda hub_id: False)
    monkeypatch.setattr(availability, "_hub_answers", lambda hub_id, timeout: None)
    availability.check_available([model_config("segformer_b5")])


def test_offline_hub_env_is_refused_without_a_network_call(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    assert availability._hub_answers("nvidia/x", 0.1) == "HF_HUB_OFFLINE is set"


@pytest.mark.slow
def test_the_cli_refuses_before_rendering_and_a_cached_dataset_is_not_refused(tmp_path):
    from pairedgta.app import run
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    base = fast_overrides(tmp_path)
    official = base + ["models=[tiny_segformer,pidnet_m]"]  # pidnet_m without its official checkpoint file
    with pytest.raises(ModelError, match="model 'pidnet_m' needs its checkpoint.*checked before rendering"):
        run(compose_cfg(official))
    generated = tmp_path / "cache" / "generate"
    assert not (generated.exists() and [p for p in generated.iterdir() if not p.name.startswith(".")])
    # once the dataset is rendered (stages=[generate] builds no model) the check is not asked: a run with
    # its pseudo-labels and evaluations cached never builds a model, so it must not be refused offline
    run(compose_cfg(base + ["stages=[generate]"]))
    with pytest.raises(ModelError, match="pidnet_m") as info:
        run(compose_cfg(official))
    assert "checked before rendering" not in str(info.value)
