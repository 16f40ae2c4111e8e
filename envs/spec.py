"""Dataclasses as data: built from mappings (YAML) with errors that name the field.

:func:`from_mapping` builds a dataclass from a ``dict`` recursively, checking every key
against the fields and every value against the field's type (``float``, ``int``,
``bool``, ``str``, ``list[float]``, ``tuple[float, float]``, nested dataclasses,
``Optional`` of those, plain ``dict``), then calls the dataclass's ``validate(path)``
if it has one. :func:`to_mapping` goes back. Errors are :class:`SpecError` with the dotted
path of the field, e.g. ``scene.physics.integrator: must be one of ...``.
"""

from __future__ import annotations

import math
import types
import typing
from dataclasses import MISSING, fields, is_dataclass
from typing import Any, get_args, get_origin, get_type_hints

__all__ = ["SpecError", "from_mapping", "to_mapping", "merge", "invalid"]


class SpecError(ValueError):
    """Invalid specification data; the message starts with the field's dotted path."""


def _type_name(tp) -> str:
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin in (list, tuple):
        args = get_args(tp)
        inner = _type_name(args[0]) if args else "value"
        if origin is tuple and args and args[-1] is not Ellipsis:
            return f"{len(args)} numbers" if all(a in (float, int) for a in args) else f"a {len(args)}-tuple"
        return f"a list of {inner}"
    if tp is type(None):
        return "null"
    if is_dataclass(tp):
        return "a mapping"
    return getattr(tp, "__name__", str(tp))


def _convert(tp, value, path: str):
    """``value`` converted to type ``tp``, or :class:`SpecError`."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, path)
            except SpecError as exc:
                errors.append(str(exc))
        if len(errors) == 1 and isinstance(value, dict):  # a mapping for the one non-null type: its own error
            raise SpecError(errors[0])
        raise SpecError(f"{path}: must be {_type_name(tp)}, got {value!r}")
    if is_dataclass(tp):
        if isinstance(value, tp):
            return value
        return from_mapping(tp, value, path)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SpecError(f"{path}: must be a number, got {value!r}")
        value = float(value)
        if math.isnan(value):
            raise SpecError(f"{path}: must be a number, got NaN")
        return value
    if tp is int:
        if isinstance(value, float) and value.is_integer():
            value = int(value)  # YAML writes 1e5 as a float
        if isinstance(value, bool) or not isinstance(value, int):
            raise SpecError(f"{path}: must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise SpecError(f"{path}: must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise SpecError(f"{path}: must be a string, got {value!r}")
        return value
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise SpecError(f"{path}: must be a mapping, got {value!r}")
        args = get_args(tp)
        if not args:
            return dict(value)
        out = {}
        for k, v in value.items():  # dict[str, X]: names to values of X, each checked under its name
            if not isinstance(k, str) or not k:
                raise SpecError(f"{path}: its keys must be non-empty names, got {k!r}")
            out[k] = _convert(args[1], v, f"{path}.{k}")
        return out
    if origin in (list, tuple):
        args = get_args(tp)
        if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__iter__"):
            raise SpecError(f"{path}: must be {_type_name(tp)}, got {value!r}")
        items = list(value)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(items) != len(args):
                raise SpecError(f"{path}: must be {_type_name(tp)}, got {value!r}")
            return tuple(_convert(a, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, items)))
        inner = args[0] if args else Any
        out = [_convert(inner, v, f"{path}[{i}]") for i, v in enumerate(items)]
        return tuple(out) if origin is tuple else out
    if isinstance(tp, type) and isinstance(value, tp):
        return value
    raise SpecError(f"{path}: must be {_type_name(tp)}, got {value!r}")


def from_mapping(cls, data, path: str = ""):
    """An instance of dataclass ``cls`` from the mapping ``data`` (see the module doc)."""
    where = path or cls.__name__
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise SpecError(f"{where}: must be a mapping, got {type(data).__name__} ({data!r})")
    hints = get_type_hints(cls)
    known = [f.name for f in fields(cls) if f.init]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise SpecError(f"{where}.{unknown[0]}: unknown field (known: {', '.join(known)})")
    kwargs = {}
    for f in fields(cls):
        if not f.init:
            continue
        key = f"{where}.{f.name}"
        if f.name in data:
            kwargs[f.name] = _convert(hints[f.name], data[f.name], key)
        elif f.default is MISSING and f.default_factory is MISSING:
            raise SpecError(f"{key}: missing (required)")
    try:
        obj = cls(**kwargs)
    except SpecError as exc:
        message = str(exc)
        own = f"{cls.__name__}."
        raise SpecError(where + "." + message[len(own):] if message.startswith(own) else message) from None
    return obj


def invalid(obj, name: str, message: str) -> SpecError:
    """The error of field ``name`` of dataclass ``obj``: ``ClassName.name: message``
    (:func:`from_mapping` puts the field's path in place of the class name)."""
    return SpecError(f"{type(obj).__name__}.{name}: {message}")


def to_mapping(obj) -> Any:
    """Plain data (dicts, lists, numbers, strings) of a dataclass tree."""
    if is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in fields(obj) if f.init}
    if isinstance(obj, (list, tuple)):
        return [to_mapping(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_mapping(v) for k, v in obj.items()}
    if hasattr(obj, "tolist"):  # numpy scalars and arrays
        return obj.tolist()
    return obj


def merge(base: dict, extra: dict) -> dict:
    """``base`` updated by ``extra``, nested mappings merged key by key."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
