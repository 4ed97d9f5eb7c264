"""Frozen-dataclass configs to and from JSON values, exactly and strictly.

A map stores its configuration *by value* (every field of every nested config), so reading it
back must rebuild the very same objects or fail: an unknown field, a missing field or a value of
the wrong kind is a one-line :class:`~vrs_jax.errors.VrsError` naming the file and the field.
Lists in JSON become tuples (the configs are hashable: they are static jit arguments).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import types
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from vrs_jax.errors import VrsError

_SPECIAL = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def unknown_name(kind: str, name: str, known: Iterable[str]) -> str:
    """``unknown KIND 'NAME'`` with the closest known names suggested
    (``difflib.get_close_matches``): the one wording of every unknown field, option or name."""
    close = difflib.get_close_matches(str(name), [str(k) for k in known], n=3)
    hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    return f"unknown {kind} {name!r}{hint}"


def check_fields(cls: type, keys: Iterable[str], kind: str) -> None:
    """VrsError for the first of ``keys`` that is not a field of the dataclass ``cls``,
    naming it and suggesting the closest fields (``kind``: e.g. "NeRF config field")."""
    fields = [f.name for f in dataclasses.fields(cls)]
    for key in keys:
        if key not in fields:
            raise VrsError(unknown_name(kind, key, fields))


def changed_fields(a: Any, b: Any) -> list[tuple[str, Any, Any]]:
    """[(field, value in a, value in b)] for each top-level field of two dataclasses of the
    same class whose values differ (the "name" field excepted), in field order."""
    return [(f.name, getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
            if f.name != "name" and getattr(a, f.name) != getattr(b, f.name)]


def _encode(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _encode(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_encode(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")  # strict JSON
    return v


def to_dict(cfg: Any) -> dict[str, Any]:
    """A (nested) frozen dataclass as plain strict-JSON values (inf as the string "inf")."""
    return _encode(dataclasses.asdict(cfg))


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _dataclass_in(hint: Any) -> type | None:
    """The dataclass type a field hint names (``X`` or ``X | None``), else None."""
    if dataclasses.is_dataclass(hint):
        return hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        found = [a for a in typing.get_args(hint) if dataclasses.is_dataclass(a)]
        return found[0] if found else None
    return None


def _decode(v: Any) -> Any:
    if isinstance(v, list):
        return tuple(_decode(x) for x in v)
    if isinstance(v, str) and v in _SPECIAL:
        return _SPECIAL[v]
    return v


def _fits(hint: Any, v: Any) -> bool:
    """Whether a decoded JSON value has the kind a field hint asks for."""
    if hint is Any:
        return True
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(a, v) for a in typing.get_args(hint))
    if hint is type(None):
        return v is None
    if hint is bool:
        return isinstance(v, bool)
    if hint is int:
        return isinstance(v, int) and not isinstance(v, bool)
    if hint is float:
        return isinstance(v, (int, float)) and not isinstance(v, bool)
    if hint is str:
        return isinstance(v, str)
    if origin is tuple or hint is tuple:
        args = typing.get_args(hint)
        if not isinstance(v, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(args[0], x) for x in v)
        return not args or (len(args) == len(v) and all(_fits(a, x) for a, x in
                                                          zip(args, v, strict=True)))
    return True


def from_dict(cls: type, d: Any, where: str | Path | None = None, path: str = "") -> Any:
    """Rebuild ``cls`` from :func:`to_dict`'s output; VrsError on any mismatch.

    Args:
      cls: the dataclass type.  d: its JSON dict.  where: the file it came from (for errors).
      path: dotted field prefix (for errors; used in recursion).
    """
    name = path or cls.__name__
    if not isinstance(d, dict):
        raise VrsError(f"config {name} is not an object", where)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    # fields added after files were written: such a file meant the value given here
    added = getattr(cls, "ADDED_FIELDS", {})
    d = {**{k: v for k, v in added.items() if k not in d}, **d}
    unknown = sorted(set(d) - set(fields))
    missing = sorted(set(fields) - set(d))
    if unknown:
        raise VrsError(f"config {name} has unknown fields {unknown} (written by another "
                       "vrs-jax version?)", where)
    if missing:
        raise VrsError(f"config {name} lacks fields {missing} (written by another vrs-jax "
                       "version?)", where)
    hints = _hints(cls)
    kw = {}
    for key, value in d.items():
        sub = _dataclass_in(hints[key])
        if sub is not None and value is not None:
            kw[key] = from_dict(sub, value, where, f"{name}.{key}")
        else:
            kw[key] = _decode(value)
            if not _fits(hints[key], kw[key]):
                raise VrsError(f"config {name}.{key} = {value!r} is not a {hints[key]}", where)
    try:
        return cls(**kw)
    except (TypeError, ValueError, VrsError) as e:
        msg = e.problem if isinstance(e, VrsError) else str(e)
        raise VrsError(f"config {name}: {msg}", where) from None
