"""Typed YAML configuration (STYLE.md rule 8).

Every part of the stack describes its configuration as a frozen dataclass tree with defaults;
:func:`load_config` reads a YAML file into that tree and rejects, with one line naming the file and
the dotted key, anything that does not fit: an unknown key, a wrong type, a missing required key,
an unreadable file. Values are converted strictly: an ``int`` is accepted where a ``float`` is
expected, nothing else is coerced (``"1.0"`` is not a float, ``1`` is not a bool).

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``, ``X | None``,
``list[X]``, ``tuple[X, ...]``, fixed ``tuple[X, Y]``, ``dict[str, X]`` and nested dataclasses.

Rules every file obeys, whatever its schema (a config is hostile input too, issue 16):

* a mapping may not repeat a key (YAML's last-one-wins would silently drop the first);
* the file must be UTF-8;
* numbers are finite (``.nan`` and ``.inf`` are refused: every range check is false for NaN) and
  integers fit in 64 bits (a 400-digit number is a typo, not a setting);
* a key whose unit suffix is a rate or a mass (``*_hz``, ``*_kg``) must be > 0: a zero rate is a
  division by zero at run time, a zero or negative mass is no vehicle.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml

from quadlink import CONFIG_DIR
from quadlink.errors import ConfigError

T = TypeVar("T")

#: key suffixes whose values must be strictly positive (see the module doc)
POSITIVE_SUFFIXES = ("_hz", "_kg")
INT64_MAX = 2**63 - 1


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a mapping with a repeated key."""


def _construct_unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            duplicate = key in seen
            seen.add(key)
        except TypeError:  # an unhashable key: yaml reports it below
            continue
        if duplicate:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (line {key_node.start_mark.line + 1})", key_node.start_mark)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique_mapping)


def read_yaml(path: str | Path) -> Any:
    """Parse the YAML file at ``path`` (UTF-8, no repeated keys) or raise one :class:`ConfigError` line."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.object[exc.start:exc.start + 1]!r})") \
            from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: cannot read YAML: {' '.join(str(exc).split())}") from exc
    except RecursionError as exc:
        raise ConfigError(f"{path}: cannot read YAML: nested too deeply") from exc


def load_config(path: str | Path, cls: type[T]) -> T:
    """Read the YAML file at ``path`` into the dataclass ``cls`` (validated, defaults filled)."""
    path = Path(path)
    data = read_yaml(path)
    if data is None:
        data = {}
    return from_dict(cls, data, source=str(path))


def from_dict(cls: type[T], data: Any, source: str = "<dict>", prefix: str = "") -> T:
    """Build the dataclass ``cls`` from plain data, validating every key (see module doc)."""
    return typing.cast(T, _convert(cls, data, source, prefix or ""))


def to_dict(obj: Any) -> Any:
    """Plain-data form of a config tree (for logs, reports and round trips)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def find_config(name: str, subdir: str = "") -> Path:
    """Resolve a config given as a path or as a bare name under ``configs/[subdir]``."""
    candidate = Path(name)
    if candidate.is_file():
        return candidate
    base = CONFIG_DIR / subdir if subdir else CONFIG_DIR
    for option in (base / name, base / f"{name}.yaml"):
        if option.is_file():
            return option
    known = sorted(p.stem for p in base.glob("*.yaml")) if base.is_dir() else []
    raise ConfigError(f"{name}: no such config file (known in {base}: {', '.join(known) or 'none'})")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def _check_positive(name: str, value: Any, source: str, key: str) -> None:
    if name.endswith(POSITIVE_SUFFIXES) and isinstance(value, (int, float)) and not isinstance(value, bool) \
            and not value > 0:
        raise _fail(source, key, f"must be > 0, got {value!r}")


def _fail(source: str, key: str, message: str) -> ConfigError:
    return ConfigError(f"{source}: key '{key or '<top>'}': {message}")


def _convert(tp: Any, value: Any, source: str, key: str) -> Any:
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise _fail(source, key, f"expected a mapping for {tp.__name__}, got {type(value).__name__}")
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init}
        unknown = sorted((k for k in value if k not in fields), key=str)
        if unknown:
            child = f"{key}.{unknown[0]}" if key else str(unknown[0])
            raise _fail(source, child, f"unknown key (allowed: {', '.join(sorted(fields))})")
        kwargs = {}
        for name, field in fields.items():
            child = f"{key}.{name}" if key else name
            if name in value:
                kwargs[name] = _convert(hints[name], value[name], source, child)
                _check_positive(name, kwargs[name], source, child)
            elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
                raise _fail(source, child, "required key is missing")
        try:
            return tp(**kwargs)
        except (ValueError, TypeError) as exc:  # __post_init__ range checks
            raise _fail(source, key, str(exc)) from exc
    if origin in (typing.Union, types.UnionType):
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, source, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise _fail(source, key, f"expected {_type_name(tp)}, got {_short(value)}")
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise _fail(source, key, f"must be one of {', '.join(map(repr, allowed))}, got {_short(value)}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise _fail(source, key, f"expected a list, got {type(value).__name__}")
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise _fail(source, key, f"expected {len(args)} items, got {len(value)}")
            return tuple(_convert(a, v, source, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        items = [_convert(item, v, source, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise _fail(source, key, f"expected a mapping, got {type(value).__name__}")
        _, vt = get_args(tp) or (str, Any)
        if any(not isinstance(k, str) for k in value):
            bad = next(k for k in value if not isinstance(k, str))
            raise _fail(source, f"{key}.{bad}", f"keys must be strings, got {type(bad).__name__}")
        return {k: _convert(vt, v, source, f"{key}.{k}") for k, v in value.items()}
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(source, key, f"expected true/false, got {_short(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(source, key, f"expected a number, got {_short(value)}")
        if isinstance(value, int) and abs(value) > INT64_MAX:
            raise _fail(source, key, f"number out of range ({len(str(abs(value)))} digits)")
        if not math.isfinite(value):
            raise _fail(source, key, f"expected a finite number, got {_short(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(source, key, f"expected an integer, got {_short(value)}")
        if abs(value) > INT64_MAX:
            raise _fail(source, key, f"integer out of range ({len(str(abs(value)))} digits)")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise _fail(source, key, f"expected a string, got {_short(value)}")
        return value
    raise _fail(source, key, f"unsupported config type {_type_name(tp)}")
