"""Strict YAML configs: a mapping into a (nested) dataclass, one-line errors naming file and key.

Unknown keys and wrong types are errors (``"<file>: <key path>: <problem>"``); field types may be
``bool``, ``int``, ``float`` (finite), ``str``, ``tuple[T, ...]`` (a YAML list) and dataclasses.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any


def _convert(tp: Any, value: Any, src: str, key: str) -> Any:
    def bad(msg: str) -> ValueError:
        return ValueError(f"{src}: {key}: {msg}")

    if dataclasses.is_dataclass(tp):
        return config_from_dict(tp, value, src, key)
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
    if typing.get_origin(tp) is tuple:
        (item, *_rest) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise bad(f"expected a list, got {value!r}")
        return tuple(_convert(item, v, src, f"{key}[{i}]") for i, v in enumerate(value))
    raise TypeError(f"{key}: unsupported field type {tp!r}")  # a bug in the dataclass, not input


def config_from_dict(cls: type, data: Any, src: str = "config", key: str = "") -> Any:
    """Build dataclass ``cls`` from a mapping, rejecting unknown keys and wrong types.

    Raises:
        ValueError: one line, ``"<src>: <key path>: <problem>"``.
    """
    here = key or "(top level)"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(f"{src}: {here}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init]
    for k in data:
        if k not in names:
            path = f"{key}.{k}" if key else str(k)
            raise ValueError(f"{src}: {path}: unknown key (known: {', '.join(sorted(names))})")
    kwargs = {k: _convert(hints[k], v, src, f"{key}.{k}" if key else str(k)) for k, v in data.items()}
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{src}: {here}: {exc}") from None
