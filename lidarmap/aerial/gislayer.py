"""``OUT/buildings.gpkg``: one row per input footprint with what the run made of it, so a GIS opens the result.

Columns: ``id``; ``status`` (the building record's: "complete" or "partial" (coverage); "ok" for a record without
one; "failed" when its task failed; "dropped" when prep left it out); ``reason`` (why it failed or was dropped, else
NULL); ``coverage`` (share of the footprint the points cover, from the record; NULL when absent); ``ground_z``, ``height`` (prep's), ``z_min``,
``z_max`` (of the building's output points); ``points``, ``points_inside``, ``building_points``, ``output_points``.
The footprints are in the run's CRS, which the layer declares.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from lidarmap.core import Footprints
from lidarmap.io.gpkg import write_gpkg_polygons
from lidarmap.io.las import read_header

LAYER = "buildings"
FILE_NAME = "buildings.gpkg"
COLUMNS = ("id", "status", "reason", "coverage", "ground_z", "height", "z_min", "z_max", "points", "points_inside",
           "building_points", "output_points")


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _z_range(points_file: Path) -> tuple[float | None, float | None]:
    """z range of a building's output points from its LAS header (no point read)."""
    try:
        header = read_header(points_file)
    except Exception:  # noqa: BLE001 - a folder written by an older run: heights are optional columns
        return None, None
    return float(header.mins[2]), float(header.maxs[2])


def building_rows(result: Any, footprints: Footprints, building_dir: Any) -> tuple[list[Any], dict[str, list]]:
    """Geometries and columns of the layer: every footprint, in input order."""
    entries = {e.id: e for e in result.prep.entries}
    records = {r["id"]: r for r in result.records}
    fps = footprints.to_crs(result.prep.crs) if result.prep.crs is not None else footprints
    geometries: list[Any] = []
    columns: dict[str, list] = {name: [] for name in COLUMNS}
    for fid, polygon in zip(fps.ids, fps.polygons):
        entry, record = entries.get(fid), records.get(fid)
        if record is not None:
            status, reason = str(record.get("status") or "ok"), record.get("reason")
            z_min, z_max = _z_range(building_dir(result.out_dir, fid) / "points.laz")
        else:
            status = "failed" if fid in result.failed else "dropped"
            reason = result.failed.get(fid) or result.dropped.get(fid) or "not processed"
            z_min = z_max = None
        record = record or {}
        geometries.append(entry.footprint if entry is not None else polygon)
        row = {"id": fid, "status": status, "reason": reason, "coverage": _number(record.get("coverage")),
               "ground_z": _number(getattr(entry, "ground_z", None)), "height": _number(getattr(entry, "height", None)),
               "z_min": z_min, "z_max": z_max, "points": getattr(entry, "points", None),
               "points_inside": getattr(entry, "points_inside", None),
               "building_points": record.get("building_points"), "output_points": record.get("output_points")}
        for name in COLUMNS:
            columns[name].append(row[name])
    return geometries, columns


def write_buildings_gpkg(result: Any, footprints: Footprints, building_dir: Any) -> Path:
    """Write ``OUT/buildings.gpkg`` (atomically) for a finished run (``result``: the pipeline's RunResult, not
    imported here: the pipeline imports this module; ``building_dir(out, id)``: a building's folder)."""
    geometries, columns = building_rows(result, footprints, building_dir)
    crs = result.prep.crs if result.prep.crs is not None else footprints.crs
    return write_gpkg_polygons(result.out_dir / FILE_NAME, LAYER, geometries, columns, crs)
