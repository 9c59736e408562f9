"""``lidarmap config defaults [TABLE]``: the TOML of every parameter's default, ready to copy into a config file.

Each table is one stage's parameter dataclass (its ``section``); nested parameter groups are sub-tables
(``[facade.planes]``). Each key carries the first line of its documentation as a comment. Parameters whose default
is "none" (e.g. ``run.model``: the shipped model) cannot be written in TOML; they appear as comments. Loading the
printed text back gives exactly the default parameters (tested).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
import re
from typing import Any

import typer

from lidarmap.cli.common import handle_errors
from lidarmap.errors import ConfigError

#: Every stage's parameter class, in pipeline order ("module:Class"), imported only when the command runs.
PARAM_CLASSES = (
    "lidarmap.aerial.prep:PrepParams",
    "lidarmap.segment.predict:PredictParams",
    "lidarmap.segment.train:TrainParams",
    "lidarmap.segment.baseline:BaselineParams",
    "lidarmap.aerial.pipeline:RunParams",
    "lidarmap.aerial.densify:DensifyParams",
    "lidarmap.aerial.flatten:FlattenParams",
    "lidarmap.aerial.voxel:VoxelParams",
    "lidarmap.aerial.mesh:MeshParams",
    "lidarmap.aerial.coverage:CoverageParams",
    "lidarmap.export.planar:PlanarParams",
    "lidarmap.facade.params:FacadeParams",
    "lidarmap.facade.sensors:SensorParams",
    "lidarmap.facade.discover:DiscoverParams",
    "lidarmap.map.refine:RefineParams",
    "lidarmap.map.update:UpdateParams",
    "lidarmap.sim.params:SimParams",
)

config_app = typer.Typer(name="config", no_args_is_help=True, add_completion=False,
                         help="Configuration files: print the defaults of every table.")


def register(app: typer.Typer) -> None:
    """Add the ``config`` command group to the app."""
    app.add_typer(config_app, name="config")


def param_classes() -> dict[str, type]:
    """Table name -> parameter class, for every stage."""
    classes = {}
    for spec in PARAM_CLASSES:
        module, name = spec.split(":")
        cls = getattr(importlib.import_module(module), name)
        classes[cls.section] = cls
    return classes


def toml_value(value: Any) -> str:
    """A TOML literal for a parameter value (bool, int, float, str, tuple/list of them)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a JSON string is a TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise ConfigError(f"no TOML form for {value!r}")


def _docs(cls: type) -> dict[str, str]:
    """First line of each parameter's documentation in the class docstring (``name (default): text``)."""
    docs = {}
    for match in re.finditer(r"^\s*(\w+) \(.*?\): (.+)$", cls.__doc__ or "", re.MULTILINE):
        text = match.group(2).strip()
        docs.setdefault(match.group(1), text if text.endswith((".", "...")) else f"{text} …")
    return docs


def table_toml(params: Any, section: str) -> list[str]:
    """The lines of ``[section]`` with the values of ``params``, then its groups as sub-tables."""
    docs = _docs(type(params))
    lines, groups = [f"[{section}]"], []
    for field in dataclasses.fields(params):
        value = getattr(params, field.name)
        if dataclasses.is_dataclass(value):
            groups.append((field.name, value))
            continue
        comment = f"  # {docs[field.name]}" if field.name in docs else ""
        if value is None:
            lines.append(f"# {field.name} = (none: not set){comment}")
        else:
            lines.append(f"{field.name} = {toml_value(value)}{comment}")
    for name, group in groups:
        lines += ["", *table_toml(group, f"{section}.{name}")]
    return lines


def defaults_toml(table: str | None = None) -> str:
    """The defaults of one table (``None``: every table) as TOML text."""
    classes = param_classes()
    if table is not None and table not in classes:
        raise ConfigError(f"unknown config table {table!r} (known: {', '.join(classes)})")
    chosen = [table] if table else list(classes)
    return "\n\n".join("\n".join(table_toml(classes[name](), name)) for name in chosen) + "\n"


@config_app.command("defaults")
@handle_errors
def defaults_command(table: str = typer.Argument(None, metavar="[TABLE]",
                                                 help="Only this table (e.g. prep, facade); default: all.")) -> None:
    """Print every parameter's default as a TOML config (copy what you change into --config FILE)."""
    typer.echo(defaults_toml(table), nl=False)
