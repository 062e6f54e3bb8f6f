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


# Fuzzing (issue 16): property tests marked ``fuzz`` take their example count from the active hypothesis
# profile. CI runs the default below; a soak is `QUADLINK_FUZZ_EXAMPLES=200000 scripts/fuzz.sh`.
def _register_fuzz_profile() -> None:
    import os

    from hypothesis import HealthCheck, settings

    examples = int(os.environ.get("QUADLINK_FUZZ_EXAMPLES", "150"))
    settings.register_profile("quadlink", max_examples=examples, deadline=None,
                              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    settings.load_profile("quadlink")


_register_fuzz_profile()
