"""Configuration files: every tunable of the config dataclasses in TOML, read and written.

A file has one table per configuration class (the Python names, nested tables for nested
configs); only the values that differ from the defaults need to be there::

    [reconstruction]                 # ReconstructionConfig: reconstruct, masks, demo
    scale = 0.8
    [reconstruction.dense_config]    # DenseConfig
    max_planes = 160

    [runtime]                        # RuntimeConfig: run, demo (and reconstruct --split's
    deadline_s = 2.0                 # [runtime.foreground] / [runtime.split])
    golden_timeout_s = 1.5
    [runtime.foreground.background]  # BackgroundConfig of the scene model
    ...

    [controller]                     # ControllerConfig (its deadline is [runtime]'s)
    margin_s = 0.5
    r_min = 0.4
    adjust_window = 8

Unknown tables and keys are errors that name the closest known one; values are checked
against the field's type and then by the class's own validation (``ValueError`` naming the
field). A value ``"none"`` stands for Python's None where a field allows it (TOML has no
null). Options given on the command line win over the file.

``dump_toml`` writes the *effective* configuration of a command (every field, with its
docstring as a comment) next to its outputs (``config.toml``); it loads again with
``--config``, so a run can be repeated or varied.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import inspect
import itertools
import json
import math
import os
import textwrap
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from edgerecon.types import DataError

T = TypeVar("T")

#: Tables a configuration file may hold, and the class each describes.
SECTIONS: dict[str, str] = {
    "reconstruction": "edgerecon.config.ReconstructionConfig",
    "runtime": "edgerecon.runtime.config.RuntimeConfig",
    "controller": "edgerecon.optimize.controller.ControllerConfig",
    "run": "",  # options of `edgerecon run` recorded with a run (frames, policy, engine)
}
#: Fields a table may not set (they come from elsewhere).
DERIVED = {"controller": {"deadline_s"}}


class ConfigError(DataError):
    """A configuration file that cannot be used; the message names the file and key."""


def load_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The tables of a configuration file (checked against ``SECTIONS``)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"configuration file not found: {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    for key, value in data.items():
        if key not in SECTIONS:
            raise ConfigError(f"{path}: unknown table [{key}]{_did_you_mean(key, SECTIONS)}")
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: {key} must be a table ([{key}])")
    return data


def _did_you_mean(word: str, known: typing.Iterable[str]) -> str:
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.5)
    return f"; did you mean {close[0]!r}?" if close else f" (known: {', '.join(sorted(known))})"


def section(data: Mapping[str, Any], *names: str) -> dict[str, Any]:
    """The nested table ``data[names[0]][names[1]]...`` ({} when absent)."""
    out: Any = data
    for n in names:
        out = out.get(n, {}) if isinstance(out, Mapping) else {}
    return dict(out) if isinstance(out, Mapping) else {}


def build(
    cls: type[T],
    values: Mapping[str, Any],
    *,
    base: T | None = None,
    where: str = "",
    overrides: Mapping[str, Any] | None = None,
    exclude: typing.Collection[str] = (),
) -> T:
    """An instance of the dataclass ``cls`` from a TOML table: ``base`` (or the defaults)
    with the table's values, then ``overrides`` (command-line options) on top."""
    hints = _hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        here = f"{where}.{key}" if where else key
        if key not in fields or key in exclude:
            known = [k for k in fields if k not in exclude]
            raise ConfigError(f"unknown setting {here!r}{_did_you_mean(key, known)}")
        current = getattr(base, key) if base is not None else _default(fields[key])
        kwargs[key] = _convert(hints[key], value, here, current)
    for key, value in (overrides or {}).items():
        if value is not None:
            kwargs[key] = value
    try:
        if base is not None:
            return dataclasses.replace(base, **kwargs)  # type: ignore[type-var]
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"{where or cls.__name__}: {exc}") from None


def _default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


_HINTS: dict[Any, dict[str, Any]] = {}


def _hints(cls: Any) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _convert(tp: Any, value: Any, where: str, current: Any) -> Any:
    """``value`` (from TOML) as the field type ``tp``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in args if a is not type(None)]
        if type(None) in args and isinstance(value, str) and value.lower() == "none":
            return None
        errors = []
        for opt in options:
            try:
                return _convert(opt, value, where, current)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where} must be a table ([{where}])")
        return build(typing.cast(type, tp), value, base=current, where=where)
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where} must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(f"{where} must be an array, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, where, None) for v in value)
        if len(args) != len(value):
            raise ConfigError(f"{where} must have {len(args)} entries, got {len(value)}")
        return tuple(_convert(a, v, where, None) for a, v in zip(args, value, strict=True))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    return value


# ============================================================================== writing
_DOCS: dict[Any, dict[str, str]] = {}


def field_docs(cls: Any) -> dict[str, str]:
    """The docstring under each field of a dataclass (read from its source)."""
    if cls not in _DOCS:
        _DOCS[cls] = _read_field_docs(cls)
    return _DOCS[cls]


def _read_field_docs(cls: Any) -> dict[str, str]:
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    tree = ast.parse(source)
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for stmt, nxt in itertools.pairwise(body):
        if (
            isinstance(stmt, ast.AnnAssign)
            and isinstance(stmt.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[stmt.target.id] = " ".join(nxt.value.value.split())
    return docs


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, tuple | list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def _table(name: str, obj: Any, lines: list[str], comments: bool, skip: set[str]) -> None:
    cls = type(obj)
    docs = field_docs(cls) if comments else {}
    nested = []
    lines.append(f"[{name}]")
    if comments and cls.__doc__:
        lines.append(f"# {cls.__name__}: {' '.join(cls.__doc__.split())}")
    for f in dataclasses.fields(obj):
        if f.name in skip:
            continue
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            nested.append((f.name, v))
            continue
        if comments and f.name in docs:
            for chunk in textwrap.wrap(docs[f.name], 96):
                lines.append(f"# {chunk}")
        if v is None:
            default = _default(f)
            lines.append(f'{f.name} = "none"' if default is not None else f"# {f.name} = none")
        else:
            lines.append(f"{f.name} = {_value(v)}")
    lines.append("")
    for key, v in nested:
        _table(f"{name}.{key}", v, lines, comments, set())


def dump_toml(
    sections: Mapping[str, Any], *, comments: bool = True, header: str | None = None
) -> str:
    """TOML text of ``{table: dataclass instance or dict}`` (every field, docstrings as
    comments); ``load_config_file`` + ``build`` read it back to equal instances."""
    lines: list[str] = []
    if header:
        lines += [f"# {ln}" for ln in header.splitlines()] + [""]
    for name, obj in sections.items():
        if obj is None:
            continue
        if dataclasses.is_dataclass(obj):
            _table(name, obj, lines, comments, DERIVED.get(name, set()))
        else:
            lines.append(f"[{name}]")
            tables = []
            for k, v in obj.items():
                if dataclasses.is_dataclass(v):
                    tables.append((k, v))
                elif v is None:
                    lines.append(f"# {k} = none")
                else:
                    lines.append(f"{k} = {_value(v)}")
            lines.append("")
            for k, v in tables:
                _table(f"{name}.{k}", v, lines, comments, set())
    return "\n".join(lines).rstrip() + "\n"


def write_config(
    path: str | os.PathLike[str], sections: Mapping[str, Any], header: str | None = None
) -> Path:
    """Write the effective configuration (atomically)."""
    from edgerecon.io.ply import atomic_write_text

    return atomic_write_text(path, dump_toml(sections, header=header))


__all__ = [
    "SECTIONS",
    "ConfigError",
    "build",
    "dump_toml",
    "field_docs",
    "load_config_file",
    "section",
    "write_config",
]
