"""`model=python`: a factory in the user's own code, `model.target=package.module:function`, called with
`model.kwargs`; it returns an `nn.Module` whose output is a tensor or a dict (`out` / `logits`).

Naming `model=python` is the user's choice to run that code: it is imported and called, nothing else is. The
weights (`model.checkpoint_path`) load as data only: safetensors, or torch.load(weights_only=True); a `module.` /
`model.` prefix is stripped and the keys must match exactly (pairedgta/models/checkpoint.py)."""
from __future__ import annotations

import importlib
from typing import Any

from pairedgta.errors import ConfigError, ModelError, reason
from pairedgta.models.contract import Network


def import_target(target: Any, where: str) -> Any:
    """`package.module:function` -> the function; a target that does not import is one line."""
    if not isinstance(target, str) or target.count(":") != 1 or not all(target.split(":")):
        raise ConfigError(f"{where}: target={target!r} must be 'package.module:function', e.g. "
                          "model.target=mypackage.models:build_net")
    module_name, attr = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # ImportError, or the user's module failing while it imports
        raise ConfigError(f"{where}: model.target={target} does not import ({reason(exc)[:200]}); is its package "
                          "installed or on PYTHONPATH?") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ConfigError(f"{where}: model.target={target}: {module_name} has no callable '{attr}'")
    return factory


def build_module(name: str, target: str | None, kwargs: dict | None, checkpoint_path: str | None) -> Any:
    """The factory's module with its weights (as data); shared with the detector source."""
    import torch

    where = f"model ({name})"
    factory = import_target(target, where)
    try:
        module = factory(**dict(kwargs or {}))
    except Exception as exc:
        raise ModelError(f"{where}: {target}(**model.kwargs) failed ({reason(exc)[:200]}); check model.kwargs") from None
    if not isinstance(module, torch.nn.Module):
        raise ModelError(f"{where}: {target} returned {type(module).__name__}, not a torch.nn.Module")
    if checkpoint_path:
        from pairedgta.models.checkpoint import load_checkpoint_strict

        load_checkpoint_strict(module, checkpoint_path, model_name=name)
    return module


def load(name: str, device: str, /, *, target: str | None = None, kwargs: dict | None = None,
         checkpoint_path: str | None = None) -> Network:
    return Network(build_module(name, target, kwargs, checkpoint_path),
                   executes=f"the user's code {target} (model=python)")
