"""Typed settings from YAML and ``--set``: the one strict loader both packages use.

A settings object is a dataclass (nested dataclasses for sections). :func:`from_dict` builds one from a mapping
strictly: an unknown key is an error that suggests the nearest known one, and a value of the wrong type is an
error naming its key; ints widen to floats, a list may also be given as ``"a,b"``, a tuple needs its exact length.
:func:`to_dict` is the inverse (plain lists, for YAML, JSON and checkpoints). ``--set KEY=VALUE`` options
(:func:`parse_sets`, the value parsed as YAML) change one dotted key each (:func:`set_dotted`), and
:func:`apply_sets` rebuilds the object. ``argen.config`` (templates) and ``detector`` (training and two-stage
configs, model presets) load through here. Errors are :class:`argen.errors.ArgenError` (``detector`` re-raises
them as its own in ``detector.errors``).
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from argen.errors import ArgenError

#: Called on every dataclass object built, with (obj, where): range checks that raise on a bad value.
Check = Callable[[Any, str], None]


def _did_you_mean(key: str, known) -> str:
    """`` (did you mean 'K'?)`` for the known name nearest to ``key``, or "" when none is near."""
    close = difflib.get_close_matches(str(key), list(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def from_dict(cls: type, data: Any, where: str = "config", check: Check | None = None) -> Any:
    """Build dataclass ``cls`` from a mapping, strictly (see the module docstring); ``check`` validates each
    dataclass object built, nested ones first."""
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ArgenError(f"{where}: expected a mapping for {cls.__name__}, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in fields:
            raise ArgenError(f"{where}: unknown key '{key}'" + _did_you_mean(key, fields))
        kwargs[key] = _coerce(hints[key], value, f"{where}: {key}", check)
    obj = cls(**kwargs)
    if check is not None:
        check(obj, where)
    return obj


def _coerce(tp: Any, value: Any, where: str, check: Check | None) -> Any:
    """``value`` checked against type hint ``tp`` (ints widened to float, "a,b" split for a list)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where, check)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _coerce(next(a for a in args if a is not type(None)), value, where, check)
    if origin is tuple:
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ArgenError(f"{where}: expected a list of {len(args)} values, got {value!r}")
        return tuple(_coerce(a, v, where, check) for a, v in zip(args, value))
    if origin is list or tp is list:
        if isinstance(value, str):
            value = [v for v in value.split(",") if v]
        if not isinstance(value, (list, tuple)):
            raise ArgenError(f"{where}: expected a list, got {value!r}")
        return [_coerce(args[0], v, where, check) for v in value] if args else list(value)
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ArgenError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ArgenError(f"{where}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ArgenError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ArgenError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, (str, int)):
            raise ArgenError(f"{where}: expected a string, got {value!r}")
        return str(value)
    return value


def to_dict(cfg: Any) -> dict:
    """Plain nested dict of a settings dataclass (tuples as lists), for YAML, JSON and checkpoints."""

    def conv(v: Any) -> Any:
        if isinstance(v, (tuple, list)):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v

    return conv(dataclasses.asdict(cfg))


def parse_sets(pairs: list[str] | None) -> dict[str, Any]:
    """``["camera.distance=[0.5, 1.0]", "lr=1e-3"]`` -> ``{"camera.distance": [0.5, 1.0], "lr": 0.001}``: the
    ``--set KEY=VALUE`` syntax of both command lines (values parsed as YAML)."""
    out = {}
    for pair in pairs or []:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip():
            raise ArgenError(f"--set expects KEY=VALUE, got '{pair}'")
        try:
            out[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ArgenError(f"--set {key.strip()}: cannot parse value '{text}'") from None
    return out


def set_dotted(data: dict, key: str, value: Any, open_sections: tuple[str, ...] = ()) -> None:
    """Set ``data["camera"]["distance"] = value`` for key ``"camera.distance"``; an unknown key is an error with a
    suggestion, except inside a section named in ``open_sections`` (whose keys the next :func:`from_dict` checks)."""
    parts = key.split(".")
    node = data
    for p in parts[:-1]:
        if not isinstance(node.get(p), dict):
            raise ArgenError(f"unknown option '{key}'")
        node = node[p]
    if parts[-1] not in node and parts[0] not in open_sections:
        raise ArgenError(f"unknown option '{key}'" + _did_you_mean(parts[-1], node))
    node[parts[-1]] = list(value) if isinstance(value, tuple) else value


def apply_sets(cfg: Any, dotted: dict[str, Any], where: str = "options", check: Check | None = None,
               open_sections: tuple[str, ...] = ()) -> Any:
    """A copy of the settings object ``cfg`` with the dotted overrides applied, rebuilt and checked."""
    data = to_dict(cfg)
    for key, value in dotted.items():
        set_dotted(data, key, value, open_sections)
    return from_dict(type(cfg), data, where, check)


def load_yaml(path: str | Path, what: str = "config file") -> dict:
    """The mapping in a YAML file ({} for an empty file); a missing file or bad YAML is a one-line error."""
    path = Path(path)
    if not path.is_file():
        raise ArgenError(f"{what} not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ArgenError(f"{path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise ArgenError(f"{path}: expected a mapping at the top, got {type(data).__name__}")
    return data
