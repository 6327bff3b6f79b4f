"""Shared fixtures. Helpers that tests import live in pairedgta.testing (tests import no test module)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

# tests never reach a model hub
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


@pytest.fixture
def tmp(tmp_path: Path) -> Path:
    return tmp_path
