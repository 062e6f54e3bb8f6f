"""Shared pytest setup: the test tiers, the committed real-data clips, a deterministic random generator.

Tests live in tiers, one folder each, and every test is marked with its folder's name so markers select
them (``pytest -m unit``, ``-m "not sitl"``):

* ``unit/`` — pure algorithms and state machines, in-process, no sockets or threads;
* ``protocol/`` — codecs on golden bytes and round trips through the real peer codec, property tests;
* ``integration/`` — real sockets, threads, subprocesses and CLIs, but no flight;
* ``sitl/`` — flights of the pybullet SITL with the stack's processes over their real links.

Helpers shared across tiers (``fuzzing.py``) sit beside this file, which puts this folder on the path.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
TIERS = ("unit", "protocol", "integration", "sitl")
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

REPO = TESTS.parent
# real RGB-D frames committed with the tests (scripts/make_tum_fixture.py cut them from the TUM RGB-D benchmark):
# ten frames each of a slow hand-held pass (fr3_teddy) and of the fastest rotation of fr1_rpy
TUM_DATA = TESTS / "data" / "tum"
TUM_CLIPS = ("fr3_teddy", "fr1_rpy")


@pytest.fixture(scope="session")
def firmware_lib():  # noqa: ANN201
    """The FlightCtrl firmware's pure C modules, host-built (``make -C firmware host``) and loaded with ctypes."""
    from firmware_host import load_firmware_lib

    return load_firmware_lib()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261123)


def tum_clip_path(name: str) -> Path:
    """A committed TUM clip's folder (``tests/data/tum/<name>``); missing data is an error, not a skip."""
    folder = TUM_DATA / name
    assert (folder / "rgb.txt").is_file(), f"test data missing: {folder} (scripts/make_tum_fixture.py makes it)"
    return folder


@pytest.fixture
def tum_clip() -> Path:
    """Ten real frames of TUM fr3_teddy with motion-capture truth (a slow hand-held pass)."""
    return tum_clip_path("fr3_teddy")


@pytest.fixture(params=TUM_CLIPS)
def any_tum_clip(request: pytest.FixtureRequest) -> Path:
    """Each committed TUM clip in turn: fr3_teddy (slow) and fr1_rpy (fast rotation, dropped frames)."""
    return tum_clip_path(request.param)


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


def _assert_poses_close(T_a: np.ndarray, T_b: np.ndarray, atol_m: float, atol_rad: float) -> None:
    """Two 4x4 poses in the same frame agree: translation within ``atol_m``, geodesic angle within ``atol_rad``."""
    from quadlink.lie import pose_error

    d_m, d_rad = pose_error(np.asarray(T_a, dtype=float), np.asarray(T_b, dtype=float))
    assert d_m <= atol_m, f"translation differs by {d_m:.3g} m > {atol_m:.3g} m"
    assert d_rad <= atol_rad, f"rotation differs by {d_rad:.3g} rad > {atol_rad:.3g} rad"


@pytest.fixture
def assert_poses_close():  # noqa: ANN201
    """Rotation-aware pose comparison (cflib's assertPosesAlmostEqual): ``assert_poses_close(T1, T2, atol_m,
    atol_rad)`` compares the translation and the geodesic angle of ``R1^T R2``, never matrix elements."""
    return _assert_poses_close


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark every test with its tier (the folder it lives in)."""
    for item in items:
        parts = Path(str(item.fspath)).resolve().relative_to(TESTS).parts
        if parts and parts[0] in TIERS:
            item.add_marker(getattr(pytest.mark, parts[0]))
