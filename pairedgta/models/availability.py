"""Can every model of a run be built here, checked before a long render rather than after it.

A hub model needs its files in the local Hugging Face cache or a hub that answers; an in-project model
needs its checkpoint file; a `model.path` needs its folder. Only a run that is about to render a new
dataset asks (`planning.open_pass`): an offline rerun whose pseudo-labels and evaluations are cached
never builds a model, so it is never refused."""
from __future__ import annotations

import os
from typing import Any, Iterable

from pairedgta.errors import ModelError, reason


def _hub_cached(hub_id: str) -> bool:
    from huggingface_hub import try_to_load_from_cache

    return isinstance(try_to_load_from_cache(hub_id, "config.json"), str)


def _hub_answers(hub_id: str, timeout: float) -> str | None:
    """None when the hub answers for hub_id, else why not."""
    if os.environ.get("HF_HUB_OFFLINE", "").lower() in ("1", "true", "yes") or \
            os.environ.get("TRANSFORMERS_OFFLINE", "").lower() in ("1", "true", "yes"):
        return "HF_HUB_OFFLINE is set"
    try:
        from huggingface_hub import HfApi

        HfApi().model_info(hub_id, timeout=timeout)
    except Exception as exc:  # no network, DNS, HTTP 401/404: every way the later download would fail
        return reason(exc)
    return None


def check_available(models: Iterable[dict[str, Any]], timeout: float = 10.0) -> None:
    """Raise one ModelError for the first model whose weights cannot be had here."""
    from pairedgta.models.hf_common import check_zoo_path, resolve_checkpoint_path
    from pairedgta.models.hf_common import pretrained_source

    from pairedgta.models import is_source

    for cfg in models:
        name = cfg.get("name")
        if cfg.get("random_init") or is_source(cfg):  # a source model was loaded and probed before (app.preflight)
            continue
        if "checkpoint_path" in cfg or "checkpoint_file" in cfg:  # an in-project family
            path = cfg.get("checkpoint_path")
            if not path:
                raise ModelError(f"model '{name}' needs its checkpoint ({cfg.get('checkpoint_file')}, from "
                                 f"{cfg.get('checkpoint_source')}); set model_overrides.{name}.checkpoint_path=FILE "
                                 "(or model.checkpoint_path= for the model you chose) — checked before rendering")
            check_zoo_path(path, name)  # a detector's weights without their distribution: how to install it
            if not resolve_checkpoint_path(path).is_file():
                raise ModelError(f"model '{name}': checkpoint file {path} does not exist; fix its checkpoint_path "
                                 "— checked before rendering")
            continue
        if cfg.get("path"):
            pretrained_source(cfg)  # the folder must exist: one line naming model.path
            continue
        hub_id = cfg.get("hub_id")
        if not hub_id or _hub_cached(str(hub_id)):
            continue
        why = _hub_answers(str(hub_id), timeout)
        if why is not None:
            raise ModelError(f"model '{name}': '{hub_id}' is not in the local Hugging Face cache and the hub does not "
                             f"answer ({why}); download it elsewhere (huggingface-cli download {hub_id} --local-dir DIR) "
                             f"and pass model_overrides.{name}.path=DIR (or model.path=DIR for the model you chose) "
                             "— checked before rendering")


__all__ = ["check_available"]
