"""Shared pytest setup: paths to the shared data and a deterministic random generator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"
TUM_HEAD = SHARED / "data" / "tum_fr1_xyz_head"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261123)


@pytest.fixture
def tum_head() -> Path:
    if not (TUM_HEAD / "rgb.txt").is_file():
        pytest.skip(f"shared test data not found at {TUM_HEAD}")
    return TUM_HEAD
