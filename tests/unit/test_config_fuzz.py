"""Issue 16, the config loaders under fuzzing: every shipped config (companion, bridge, SITL, teleop, vehicle, the
scenarios) with one leaf replaced by a hostile value, a key added or removed, or its bytes damaged, read through
its real loader from a file. The property: a config either loads with every number in it finite, or the loader
raises one ConfigError whose message names the file; never another exception, never a NaN that passes.

CI runs a bounded number of examples; ``scripts/fuzz.sh -k config`` soaks it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from fuzzing import FUZZ
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.config import load_companion_config
from firmware_bridge.daemon import BridgeConfig
from quadlink.config import CONFIG_DIR, load_config, to_dict
from quadlink.errors import ConfigError
from quadlink.vehicle import load_vehicle
from sim_sitl.config import load_scenario, load_sitl_config
from teleop.config import load_teleop_config

pytestmark = pytest.mark.fuzz

LOADERS: dict[str, Callable[[Path], Any]] = {
    "companion.yaml": load_companion_config,
    "bridge.yaml": lambda p: load_config(p, BridgeConfig),
    "sitl.yaml": load_sitl_config,
    "teleop.yaml": load_teleop_config,
    "vehicle.yaml": load_vehicle,
    "scenarios/paper-arena.yaml": lambda p: load_scenario(str(p)),
    "scenarios/office.yaml": lambda p: load_scenario(str(p)),
}
SHIPPED = {name: yaml.safe_load((CONFIG_DIR / name).read_text()) for name in LOADERS}

hostile_leaf = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0, -1, 0.0, -1e-300, 1e308, 10**400, -(10**400), True, None,
                     "", "fast", "nan", "1e999", [], {}, [math.nan], {"x": 1}, 2**63, -(2**63)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(),
    st.text(max_size=8),
)


def _paths(tree: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every path to a leaf or a container in ``tree``."""
    out = [prefix] if prefix else []
    if isinstance(tree, dict):
        for k, v in tree.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            out += _paths(v, (*prefix, i))
    return out


def _replace(tree: Any, path: tuple[Any, ...], value: Any, mode: str) -> Any:
    tree = yaml.safe_load(yaml.safe_dump(tree))   # a deep copy
    parent = tree
    for k in path[:-1]:
        parent = parent[k]
    key = path[-1]
    if mode == "replace":
        parent[key] = value
    elif mode == "delete":
        del parent[key]
    elif isinstance(parent, dict):              # "add": an unknown key beside this one
        parent[f"{key}_typo"] = value
    else:
        parent.append(value)
    return tree


def _dump(tree: Any) -> str:
    # yaml.safe_dump writes NaN and inf as .nan / .inf and big ints in full: the loaders read what a user writes
    return yaml.safe_dump(tree, allow_unicode=True)


def _numbers(tree: Any) -> list[float]:
    if isinstance(tree, dict):
        return [x for v in tree.values() for x in _numbers(v)]
    if isinstance(tree, (list, tuple)):
        return [x for v in tree for x in _numbers(v)]
    return [tree] if isinstance(tree, float) else []


def _load(name: str, path: Path) -> Any:
    try:
        return LOADERS[name](path)
    except ConfigError as exc:
        assert str(path) in str(exc) or path.name in str(exc), f"the error does not name the file: {exc}"
        return None


@settings(FUZZ, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(name=st.sampled_from(sorted(LOADERS)), data=st.data(), mode=st.sampled_from(["replace", "delete", "add"]),
       value=hostile_leaf)
def test_a_damaged_config_loads_finite_or_fails_with_one_clear_error(tmp_path: Path, name: str, data: st.DataObject,
                                                                     mode: str, value: Any) -> None:
    tree = SHIPPED[name]
    path_in_tree = data.draw(st.sampled_from(_paths(tree)))
    path = tmp_path / Path(name).name
    path.write_text(_dump(_replace(tree, path_in_tree, value, mode)))
    cfg = _load(name, path)
    if cfg is not None:
        bad = [x for x in _numbers(to_dict(cfg)) if not math.isfinite(x)]
        # an optional limit may be infinite by design ("no limit"); a NaN never
        assert not any(math.isnan(x) for x in bad), f"{name}: NaN accepted at {path_in_tree}"


@settings(FUZZ, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(LOADERS)), cut=st.integers(min_value=0), junk=st.binary(max_size=64))
def test_truncated_or_non_utf8_config_bytes_fail_with_one_clear_error(tmp_path: Path, name: str, cut: int,
                                                                       junk: bytes) -> None:
    text = (CONFIG_DIR / name).read_bytes()
    cut %= len(text) + 1
    path = tmp_path / Path(name).name
    path.write_bytes(text[:cut] + junk + text[cut:])
    cfg = _load(name, path)
    if cfg is not None:
        assert not any(math.isnan(x) for x in _numbers(to_dict(cfg)))


@pytest.mark.parametrize("entry", [1.3407807929942597e+154, 1e308, -1e200])
def test_a_huge_rotation_entry_is_a_config_error_not_an_overflow(tmp_path: Path, entry: float) -> None:
    """Found by the soak: 1.3e154 in vehicle.yaml's camera.R_qc overflowed R R^T (a RuntimeWarning escaped)."""
    path = tmp_path / "vehicle.yaml"
    path.write_text(_dump(_replace(SHIPPED["vehicle.yaml"], ("camera", "R_qc", 0, 0), entry, "replace")))
    with pytest.raises(ConfigError, match="R_qc"):
        load_vehicle(path)
