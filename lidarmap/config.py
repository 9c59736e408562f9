"""Parameters: one dataclass per stage, filled from defaults < TOML config < command-line flags.

A config file has one table per stage, named after the dataclass's ``section``; a stage with many parameters groups
them in nested dataclasses, which are TOML sub-tables::

    [prep]
    buffer = 5.0

    [facade.planes]
    ransac_threshold = 0.04

Unknown tables or keys are errors (a typo must not be silently ignored). A key that moved into a group keeps working
at its old place (``[facade] ransac_threshold``) with a warning naming the new one (``[facade.planes]``).

Constraints are declared, not coded: each parameter class lists them in its ``constraints`` class attribute
(``{"cell": "> 0", "Ta": "(0, 1]", "plane_method": "in ransac, region"}``) and :func:`check_params` checks every
declared one (its ``__post_init__`` calls it), so a bad value from a file, a flag or Python fails the same way.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import re
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from lidarmap.errors import ConfigError, ParameterError

P = TypeVar("P")
log = logging.getLogger(__name__)


def load_toml(path: str | Path | None) -> dict[str, Any]:
    """Read a TOML config file; ``None`` gives an empty config."""
    if path is None:
        return {}
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError("config file not found", path) from None
    except IsADirectoryError:
        raise ConfigError("config path is a folder, not a TOML file", path) from None
    except UnicodeDecodeError:
        raise ConfigError("config file is not UTF-8 text", path) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"invalid TOML: {exc}", path) from None


# ----------------------------------------------------------------------------------------------------------------------
# Declared constraints


_INTERVAL = re.compile(r"^([\[(])\s*(\S+)\s*,\s*(\S+)\s*([\])])$")
_COMPARE = re.compile(r"^(>=|<=|>|<)\s*(\S+)$")


@functools.lru_cache(maxsize=None)
def _rule(spec: str) -> typing.Callable[[Any], bool]:
    """A predicate for one constraint spec: ``> 0``, ``>= 1``, ``(0, 1]``, ``[0, inf)``, ``in a, b, c``."""
    if spec.startswith("in "):
        choices = {c.strip() for c in spec[3:].split(",")}
        return lambda v: str(v) in choices
    match = _COMPARE.match(spec)
    if match:
        op, bound = match.group(1), float(match.group(2))
        return {">": lambda v: v > bound, ">=": lambda v: v >= bound,
                "<": lambda v: v < bound, "<=": lambda v: v <= bound}[op]
    match = _INTERVAL.match(spec)
    if match:
        lo, hi = float(match.group(2)), float(match.group(3))
        low_ok = (lambda v: v >= lo) if match.group(1) == "[" else (lambda v: v > lo)
        high_ok = (lambda v: v <= hi) if match.group(4) == "]" else (lambda v: v < hi)
        return lambda v: low_ok(v) and high_ok(v)
    raise ValueError(f"bad constraint spec {spec!r}")


def _numeric(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_params(params: Any) -> None:
    """Check every constraint declared in ``type(params).constraints`` (ParameterError naming the parameter).

    Numbers must be finite whatever is declared; nested parameter groups check themselves when built.
    """
    declared: dict[str, str] = getattr(type(params), "constraints", {})
    for field in dataclasses.fields(params):
        value = getattr(params, field.name)
        if _numeric(value) and not math.isfinite(value):
            raise ParameterError(f"{field.name} must be a finite number, not {value!r}")
        spec = declared.get(field.name)
        if spec is not None and value is not None and not _rule(spec)(value):
            raise ParameterError(f"{field.name} must be {_wording(spec)}, not {value!r}")


def _wording(spec: str) -> str:
    """A constraint spec as the error message says it: 'one of a, b', 'in (0, 1]', '> 0'."""
    if spec.startswith("in "):
        return "one of " + spec[3:]
    return f"in {spec}" if _INTERVAL.match(spec) else spec


def undeclared(params_cls: type) -> list[str]:
    """Numeric parameters of ``params_cls`` (and of its groups) without a declared constraint (free-text strings such
    as paths and field names need none; strings with a fixed set of values declare it)."""
    declared = getattr(params_cls, "constraints", {})
    missing = []
    for name, hint in _hints(params_cls).items():
        if _group(hint) is not None:
            missing += [f"{name}.{m}" for m in undeclared(_group(hint))]
        elif hint in (int, float) and name not in declared:
            missing.append(name)
    return missing


# ----------------------------------------------------------------------------------------------------------------------
# Building parameters from a config table


@functools.lru_cache(maxsize=None)
def _hints(params_cls: type) -> dict[str, Any]:
    """The fields' types, resolved from their annotations (the standard resolver; no ``eval`` of our own)."""
    hints = typing.get_type_hints(params_cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(params_cls)}


def _group(hint: Any) -> type | None:
    """The parameter-group dataclass a field holds, if it is one."""
    return hint if isinstance(hint, type) and dataclasses.is_dataclass(hint) else None


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Check a config value against the field's type (ints are accepted for floats)."""
    origin = typing.get_origin(hint)
    allowed = typing.get_args(hint) if origin in (typing.Union, types.UnionType) else (hint,)
    for typ in allowed:
        if typ is type(None) and value is None:
            return None
        if typ is float and _numeric(value):
            return float(value)
        if typ is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if typ is bool and isinstance(value, bool):
            return value
        if typ is str and isinstance(value, str):
            return value
        if typing.get_origin(typ) in (tuple, list) and isinstance(value, (list, tuple)):
            return tuple(value) if typing.get_origin(typ) is tuple else list(value)
    raise ConfigError(f"{where}: expected {getattr(hint, '__name__', hint)}, got {value!r}")


def _moved_key(params_cls: type, name: str) -> str | None:
    """The group that holds ``name`` when it is no field of ``params_cls`` itself (a key from before the groups)."""
    for group_name, hint in _hints(params_cls).items():
        group = _group(hint)
        if group is not None and name in _hints(group):
            return group_name
    return None


def _table_values(params_cls: type, table: dict[str, Any], section: str) -> dict[str, Any]:
    """Field values from one config table; sub-tables fill the nested groups; old flat keys find their group."""
    hints = _hints(params_cls)
    values: dict[str, Any] = {}
    moved: dict[str, dict[str, Any]] = {}
    for key, value in table.items():
        name = key.replace("-", "_")
        if name in hints and _group(hints[name]) is not None:
            if not isinstance(value, dict):
                raise ConfigError(f"config: [{section}.{key}] must be a table")
            moved.setdefault(name, {}).update(value)
        elif name in hints:
            values[name] = _coerce(value, hints[name], f"config [{section}] {key}")
        elif (group := _moved_key(params_cls, name)) is not None:
            log.warning("config: [%s] %s is now [%s.%s] %s", section, key, section, group, key)
            moved.setdefault(group, {})[key] = value
        else:
            raise ConfigError(f"config: unknown option '{key}' in [{section}] (known: {', '.join(sorted(hints))})")
    for group, sub in moved.items():
        values[group] = _build(_group(hints[group]), _table_values(_group(hints[group]), sub, f"{section}.{group}"),
                               f"{section}.{group}")
    return values


def _build(params_cls: type[P], values: dict[str, Any], section: str) -> P:
    try:
        return params_cls(**values)
    except (TypeError, ValueError, ConfigError) as exc:
        problem = getattr(exc, "problem", str(exc))
        raise ConfigError(problem if problem.startswith("[") else f"[{section}]: {problem}") from None


def _apply_override(params_cls: type, values: dict[str, Any], key: str, value: Any, section: str) -> None:
    """A command-line value: a field of the class itself, or of one of its groups (flags keep flat names)."""
    hints = _hints(params_cls)
    if key in hints:
        values[key] = value
        return
    group = _moved_key(params_cls, key)
    if group is None:
        raise ConfigError(f"unknown option '{key}' for {section}")
    current = values.get(group, getattr(params_cls(), group))
    values[group] = _build(type(current), {**_as_values(current), key: value}, f"{section}.{group}")


def _as_values(params: Any) -> dict[str, Any]:
    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}


def resolve(params_cls: type[P], config: dict[str, Any] | None = None, section: str | None = None,
            **overrides: Any) -> P:
    """Build ``params_cls`` from its defaults, the config table ``section`` and non-``None`` overrides."""
    section = section or getattr(params_cls, "section", params_cls.__name__.lower())
    table = (config or {}).get(section, {})
    if not isinstance(table, dict):
        raise ConfigError(f"config: [{section}] must be a table")
    values = _table_values(params_cls, table, section)
    for key, value in overrides.items():
        if value is not None:
            _apply_override(params_cls, values, key, value, section)
    return _build(params_cls, values, section)


#: Every config table some command reads: one config file may serve every command, so a command accepts the tables
#: of the others, but a table no command knows (a typo: ``[prepp]``) is an error. A new parameter class adds its
#: ``section`` here.
KNOWN_TABLES = frozenset({"prep", "run", "segment", "segment_train", "segment_baseline", "baseline", "densify",
                          "flatten", "voxel", "mesh", "coverage", "lod22", "facade", "discover", "sensors", "refine",
                          "update", "simulate"})


def check_sections(config: dict[str, Any], known: set[str] | frozenset[str] = KNOWN_TABLES,
                   path: str | Path | None = None) -> None:
    """Refuse config tables that no stage knows."""
    unknown = sorted(set(config) - set(known))
    if unknown:
        raise ConfigError(f"unknown config table(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})", path)
