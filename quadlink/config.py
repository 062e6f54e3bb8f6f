"""Typed YAML configuration (STYLE.md rule 8).

Every part of the stack describes its configuration as a frozen dataclass tree with defaults;
:func:`load_config` reads a YAML file into that tree and rejects, with one line naming the file and
the dotted key, anything that does not fit: an unknown key, a wrong type, a missing required key,
an unreadable file. Values are converted strictly: an ``int`` is accepted where a ``float`` is
expected, nothing else is coerced (``"1.0"`` is not a float, ``1`` is not a bool).

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``, ``X | None``,
``list[X]``, ``tuple[X, ...]``, fixed ``tuple[X, Y]``, ``dict[str, X]`` and nested dataclasses.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml

from quadlink import CONFIG_DIR
from quadlink.errors import ConfigError

T = TypeVar("T")


def load_config(path: str | Path, cls: type[T]) -> T:
    """Read the YAML file at ``path`` into the dataclass ``cls`` (validated, defaults filled)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read YAML: {str(exc).splitlines()[0]}") from exc
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


def _fail(source: str, key: str, message: str) -> ConfigError:
    return ConfigError(f"{source}: key '{key or '<top>'}': {message}")


def _convert(tp: Any, value: Any, source: str, key: str) -> Any:
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise _fail(source, key, f"expected a mapping for {tp.__name__}, got {type(value).__name__}")
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init}
        unknown = sorted(set(value) - set(fields))
        if unknown:
            child = f"{key}.{unknown[0]}" if key else str(unknown[0])
            raise _fail(source, child, f"unknown key (allowed: {', '.join(sorted(fields))})")
        kwargs = {}
        for name, field in fields.items():
            child = f"{key}.{name}" if key else name
            if name in value:
                kwargs[name] = _convert(hints[name], value[name], source, child)
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
        raise _fail(source, key, f"expected {_type_name(tp)}, got {value!r}")
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise _fail(source, key, f"must be one of {', '.join(map(repr, allowed))}, got {value!r}")
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
        return {str(k): _convert(vt, v, source, f"{key}.{k}") for k, v in value.items()}
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(source, key, f"expected true/false, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(source, key, f"expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(source, key, f"expected an integer, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise _fail(source, key, f"expected a string, got {value!r}")
        return value
    raise _fail(source, key, f"unsupported config type {_type_name(tp)}")
