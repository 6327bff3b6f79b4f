"""placeholder: being written"""
from __future__ import annotations

from pairedgta.models.contract import Network


def load(name: str, device: str, /, *, path: str | None = None) -> Network:
    raise NotImplementedError
