"""Parameters: one dataclass per stage, filled from defaults < TOML config < command-line flags.

A config file has one table per stage, named after the dataclass's ``section``::

    [prep]
    buffer = 5.0

    [segment]
    block_size = 32.0

Unknown tables or keys are errors (a typo must not be silently ignored).
"""

from __future__ import annotations

import dataclasses
import tomllib
import typing
from pathlib import Path
from typing import Any, TypeVar

from lidarmap.errors import ConfigError

P = TypeVar("P")


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
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"invalid TOML: {exc}", path) from None


def _coerce(value: Any, field: dataclasses.Field, where: str) -> Any:
    """Check a config value against the field's annotated type (ints are accepted for floats)."""
    hint = field.type if not isinstance(field.type, str) else eval(field.type, {"typing": typing})  # noqa: S307
    origin = typing.get_origin(hint)
    allowed = typing.get_args(hint) if origin in (typing.Union, getattr(__import__("types"), "UnionType", ())) else (hint,)
    for typ in allowed:
        if typ is type(None) and value is None:
            return None
        if typ is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if typ is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if typ is bool and isinstance(value, bool):
            return value
        if typ is str and isinstance(value, str):
            return value
        if typing.get_origin(typ) in (tuple, list) and isinstance(value, (list, tuple)):
            return tuple(value) if typing.get_origin(typ) is tuple else list(value)
    raise ConfigError(f"{where}: expected {hint}, got {value!r}")


def resolve(params_cls: type[P], config: dict[str, Any] | None = None, section: str | None = None,
            **overrides: Any) -> P:
    """Build ``params_cls`` from its defaults, the config table ``section`` and non-``None`` overrides."""
    section = section or getattr(params_cls, "section", params_cls.__name__.lower())
    fields = {f.name: f for f in dataclasses.fields(params_cls)}
    values: dict[str, Any] = {}
    table = (config or {}).get(section, {})
    if not isinstance(table, dict):
        raise ConfigError(f"config: [{section}] must be a table")
    for key, value in table.items():
        name = key.replace("-", "_")
        if name not in fields:
            raise ConfigError(f"config: unknown option '{key}' in [{section}] (known: {', '.join(sorted(fields))})")
        values[name] = _coerce(value, fields[name], f"config [{section}] {key}")
    for key, value in overrides.items():
        if value is None:
            continue
        if key not in fields:
            raise ConfigError(f"unknown option '{key}' for {section}")
        values[key] = value
    try:
        return params_cls(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"[{section}]: {exc}") from None


def check_sections(config: dict[str, Any], known: set[str], path: str | Path | None = None) -> None:
    """Refuse config tables that no stage knows."""
    unknown = sorted(set(config) - known)
    if unknown:
        raise ConfigError(f"unknown config table(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})", path)
