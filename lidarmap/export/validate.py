"""Checks of a CityJSON 2.0 document: the bundled schema plus the rules a JSON schema cannot express.

``validate_cityjson(doc)`` returns a list of problems (empty: valid). Two layers:

1. JSON Schema (draft-07) ``lidarmap/schemas/cityjson-2.0-lidarmap-subset.schema.json``: the CityJSON 2.0.1 rules
   for what lidarmap writes (see ``lidarmap/schemas/README.md``: the official schema files were not available to
   vendor, so this restates the specification; it is stricter where 2.0.1 is, e.g. ``lod`` values, non-empty
   boundaries, a ``type`` on every semantic surface);
2. references: every vertex index exists, ``semantics.values`` has one entry per surface and points at an existing
   semantic object, ``parent``/``children`` of semantic objects point at each other, City Object ``parents`` /
   ``children`` exist, no vertex is listed twice, every vertex is used, every ring has three distinct vertices and
   repeats none;
3. geometry: every surface valid in its own plane and not a sliver (:mod:`lidarmap.export.geomcheck`), what the tools
   that triangulate CityJSON (cjio's OBJ/glTF export, QGIS) need.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterator
from importlib import resources
from typing import Any

import numpy as np

from lidarmap.errors import LidarmapError
from lidarmap.export.geomcheck import MIN_AREA, surface_problems

__all__ = ["SCHEMA_NAME", "cityjson_schema", "validate_cityjson"]

SCHEMA_NAME = "cityjson-2.0-lidarmap-subset.schema.json"


@functools.lru_cache(maxsize=1)
def cityjson_schema() -> dict[str, Any]:
    """The bundled JSON schema (parsed once)."""
    return json.loads((resources.files("lidarmap") / "schemas" / SCHEMA_NAME).read_text(encoding="utf-8"))


def _schema_problems(doc: Any) -> list[str]:
    try:
        import jsonschema  # an optional dependency (the ``test`` extra): only validation needs it
    except ImportError:
        raise LidarmapError("validating CityJSON needs the jsonschema package (pip install jsonschema)") from None

    validator = jsonschema.Draft7Validator(cityjson_schema())
    problems = []
    for error in sorted(validator.iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path]):
        where = "/".join(str(p) for p in error.absolute_path) or "(root)"
        problems.append(f"schema: at {where}: {error.message[:200]}")
    return problems


def _surfaces(geometry: dict[str, Any]) -> Iterator[tuple[tuple[int, ...], list]]:
    """(position, surface) of every surface of a MultiSurface / CompositeSurface / Solid."""
    if geometry.get("type") == "Solid":
        for i, shell in enumerate(geometry.get("boundaries", [])):
            for j, surface in enumerate(shell):
                yield (i, j), surface
    else:
        for i, surface in enumerate(geometry.get("boundaries", [])):
            yield (i,), surface


def _value_at(values: Any, position: tuple[int, ...]) -> Any:
    for index in position:
        if not isinstance(values, list) or index >= len(values):
            return KeyError
        values = values[index]
    return values


def _semantic_problems(geometry: dict[str, Any], where: str, positions: list[tuple[int, ...]]) -> list[str]:
    semantics = geometry.get("semantics")
    if not semantics:
        return []
    surfaces = semantics.get("surfaces", [])
    values = semantics.get("values")
    problems = []
    if geometry.get("type") == "Solid":
        shells = geometry.get("boundaries", [])
        if values is not None and (len(values) != len(shells)
                                   or any(v is not None and len(v) != len(s) for v, s in zip(values, shells))):
            problems.append(f"{where}: semantics.values does not match the boundaries' shape")
    elif values is not None and len(values) != len(positions):
        problems.append(f"{where}: semantics.values has {len(values)} entries for {len(positions)} surfaces")
    for position in positions if values is not None else []:
        value = _value_at(values, position)
        if value is not None and value is not KeyError and not 0 <= value < len(surfaces):
            problems.append(f"{where}: surface {list(position)} has semantic {value} of {len(surfaces)}")
    for i, sem in enumerate(surfaces):
        parent = sem.get("parent")
        if parent is not None and (not 0 <= parent < len(surfaces) or i not in surfaces[parent].get("children", [])):
            problems.append(f"{where}: semantic {i} names parent {parent}, which does not list it as a child")
        for child in sem.get("children", []):
            if not 0 <= child < len(surfaces) or surfaces[child].get("parent") != i:
                problems.append(f"{where}: semantic {i} lists child {child}, whose parent is not {i}")
    return problems


def _geometry_problems(geometry: dict[str, Any], where: str, vertices: np.ndarray, min_area: float) -> list[str]:
    problems = []
    positions = []
    for position, surface in _surfaces(geometry):
        positions.append(position)
        rings = [ring for ring in (surface if isinstance(surface, list) else []) if isinstance(ring, list)]
        missing = False
        for r, ring in enumerate(rings):
            if any(not isinstance(i, int) or not 0 <= i < len(vertices) for i in ring):
                problems.append(f"{where}: surface {list(position)} ring {r} refers to a missing vertex")
                missing = True
            elif len(set(ring)) < 3:
                problems.append(f"{where}: surface {list(position)} ring {r} has fewer than 3 distinct vertices")
                missing = True
            elif len(set(ring)) != len(ring):
                problems.append(f"{where}: surface {list(position)} ring {r} repeats a vertex")
        if rings and not missing:
            for problem in surface_problems([vertices[ring] for ring in rings], min_area):
                problems.append(f"{where}: surface {list(position)}: {problem}")
    return problems + _semantic_problems(geometry, where, positions)


def _used_vertices(boundaries: Any, used: set[int]) -> None:
    for part in boundaries:
        if isinstance(part, list):
            _used_vertices(part, used)
        elif isinstance(part, int):
            used.add(part)


def _reference_problems(doc: dict[str, Any]) -> list[str]:
    vertices = doc.get("vertices", [])
    problems = []
    if len({tuple(v) for v in vertices if isinstance(v, list)}) != len(vertices):
        problems.append("vertices: some vertices are listed more than once")
    objects = doc.get("CityObjects", {})
    scale = np.asarray(doc.get("transform", {}).get("scale", [1.0, 1.0, 1.0]), dtype=np.float64)
    coords = np.asarray(vertices, dtype=np.float64).reshape(-1, 3) * scale  # the translate changes no shape
    used: set[int] = set()
    for oid, obj in objects.items():
        for key, back in (("parents", "children"), ("children", "parents")):
            for other in obj.get(key, []):
                if other not in objects or oid not in objects[other].get(back, []):
                    problems.append(f"CityObjects/{oid}: {key} names {other!r}, which does not link back")
        for g, geometry in enumerate(obj.get("geometry", [])):
            problems += _geometry_problems(geometry, f"CityObjects/{oid}/geometry/{g}", coords, MIN_AREA)
            _used_vertices(geometry.get("boundaries", []), used)
    unused = len(vertices) - len(used & set(range(len(vertices))))
    if unused:
        problems.append(f"vertices: {unused} of {len(vertices)} vertices are used by no surface")
    return problems


def validate_cityjson(doc: Any) -> list[str]:
    """Problems of a CityJSON 2.0 document (empty list: valid); references are checked once the schema passes."""
    problems = _schema_problems(doc)
    return problems or _reference_problems(doc)
