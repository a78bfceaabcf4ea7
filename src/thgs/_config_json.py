"""Config dataclasses from JSON documents, every value checked against its annotated type.

The inverse of ``json.loads(json.dumps(dataclasses.asdict(config)))``: nested dataclasses from
objects, tuples from lists, ``Literal`` choices, and ``bool`` / ``int`` / ``float`` / ``str``
kept apart (``true`` is not an int, ``1`` is a float). A key the dataclass does not have is an
error; a missing key takes the dataclass's default.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Literal, TypeVar

from thgs.errors import InputError

__all__ = ["config_from_json"]

T = TypeVar("T")


def config_from_json(cls: type[T], document: Any, where: str) -> T:
    """An instance of the dataclass ``cls`` from a JSON ``document``.

    Args:
        cls: a (frozen) dataclass whose fields are dataclasses, tuples, Literals, bool, int,
            float or str.
        document: the parsed JSON object.
        where: how errors name the document and its keys, e.g. ``"field.thgs: config"``.

    Raises:
        InputError: naming the key: not an object, an unknown key, a value of the wrong type or
            outside its choices.
    """
    if not isinstance(document, dict):
        raise InputError(where, f"must be a JSON object, got {type(document).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {field.name: field for field in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(document) - set(fields))
    if unknown:
        raise InputError(where, f"unknown setting {unknown[0]!r}; known: {', '.join(fields)}")
    values = {
        name: _value(hints[name], document[name], f"{where}.{name}")
        for name in fields
        if name in document
    }
    return cls(**values)


def _value(kind: Any, value: Any, where: str) -> Any:
    if dataclasses.is_dataclass(kind):
        return config_from_json(kind, value, where)  # type: ignore[arg-type]
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is Literal:
        if isinstance(value, bool) or value not in args:
            raise InputError(where, f"must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(where, f"must be a list, got {type(value).__name__}")
        items = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(items) != len(value):
            raise InputError(where, f"must hold {len(items)} values, got {len(value)}")
        return tuple(
            _value(item, v, f"{where}[{i}]") for i, (item, v) in enumerate(zip(items, value))
        )
    if kind is bool:
        if not isinstance(value, bool):
            raise InputError(where, f"must be true or false, got {value!r}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(where, f"must be an integer, got {value!r}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(where, f"must be a number, got {value!r}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise InputError(where, f"must be a string, got {value!r}")
        return value
    raise TypeError(f"{where}: unsupported config type {kind!r}")
