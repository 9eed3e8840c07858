"""Strict YAML configs: a mapping into a (nested) dataclass, one-line errors naming file and key.

Unknown keys and wrong types are errors (``"<file>: <key path>: <problem>"``); field types may be
``bool``, ``int``, ``float`` (finite), ``str``, ``X | None``, tuples (``tuple[T, ...]`` or fixed
length; a YAML list) and dataclasses. Used by every config of ``blsm`` and ``synth``.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, TypeVar

T = TypeVar("T")


def _convert(tp: Any, value: Any, src: str, key: str) -> Any:
    def bad(msg: str) -> ValueError:
        return ValueError(f"{src}: {key}: {msg}")

    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return config_from_dict(tp, value, src, key)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(tp):
            return None
        (inner,) = [a for a in typing.get_args(tp) if a is not type(None)]
        return _convert(inner, value, src, key)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise bad(f"expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            args = (args[0],) * len(value)
        if len(value) != len(args):
            raise bad(f"expected {len(args)} values, got {len(value)}")
        return tuple(
            _convert(a, v, src, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if tp is bool:
        if not isinstance(value, bool):
            raise bad(f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad(f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad(f"expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise bad(f"expected a string, got {value!r}")
        return value
    raise TypeError(f"{key}: unsupported field type {tp!r}")  # a bug in the dataclass, not input


def config_from_dict(cls: type[T], data: Any, src: str = "config", key: str = "") -> T:
    """Build dataclass ``cls`` from a mapping, rejecting unknown keys and wrong types.

    Args:
        cls: a dataclass type (nested dataclasses are built recursively).
        data: a mapping (from YAML), or None for all defaults.
        src: the file (or other source) named in errors.
        key: the key path of ``data`` inside the file ("" at the top).

    Raises:
        ValueError: one line, ``"<src>: <key path>: <problem>"``.
    """
    here = key or "(top level)"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(f"{src}: {here}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = [f.name for f in dataclasses.fields(cls) if f.init]
    for k in data:
        if k not in fields:
            path = f"{key}.{k}" if key else str(k)
            raise ValueError(f"{src}: {path}: unknown key (known: {', '.join(sorted(fields))})")
    kwargs = {k: _convert(hints[k], v, src, f"{key}.{k}" if key else k) for k, v in data.items()}
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{src}: {here}: {exc}") from None
