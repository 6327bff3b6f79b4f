"""`torch = lazy_module("torch")`: the module imported on first attribute use. A cached rerun builds no
model and computes no metric, so it never pays torch's ~1.2 s import (the stages, metrics and the model
interface all name torch at module level)."""
from __future__ import annotations

import importlib
import types
from typing import Any


class LazyModule(types.ModuleType):
    def __init__(self, name: str) -> None:
        super().__init__(name)

    def __getattr__(self, attr: str) -> Any:
        module = importlib.import_module(self.__name__)
        self.__dict__.update(module.__dict__)  # later lookups are plain attribute reads
        return getattr(module, attr)


def lazy_module(name: str) -> Any:
    return LazyModule(name)
