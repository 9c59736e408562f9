"""The folder ``lidarmap prep`` writes: ``buildings/<id>.laz``, ``buildings.csv`` (the index), ``frame.json`` and
``prep.json``; written whole (temporary folder renamed at the end) and read back by ``segment``."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lidarmap.errors import InputError
from lidarmap.io.atomic import atomic_dir, write_text_atomic
from lidarmap.io.crs import describe_crs
from lidarmap.io.las import write_las

INDEX_COLUMNS = ["id", "file", "points", "points_inside", "height", "height_source", "ground_z",
                 "xmin", "ymin", "zmin", "xmax", "ymax", "zmax", "status"]


_MARKER = "prep.json"


def building_file_name(building_id: str, taken: set[str] | None = None) -> str:
    """A safe file name ``<id>.laz`` (characters other than letters, digits, ``.-_`` become ``_``; unique)."""
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", str(building_id)).strip(".") or "building"
    name, k = f"{stem}.laz", 1
    while taken is not None and name.lower() in taken:
        k += 1
        name = f"{stem}_{k}.laz"
    if taken is not None:
        taken.add(name.lower())
    return name


def check_out_dir(out_dir: str | Path) -> Path:
    """Refuse an output path that is a file or a non-empty folder other than an earlier prep output."""
    out = Path(out_dir)
    if out.exists():
        if not out.is_dir():
            raise InputError("output exists and is not a folder", out)
        if any(out.iterdir()) and not (out / _MARKER).exists():
            raise InputError("output folder is not empty and holds no earlier prep output; choose another -o", out)
    return out


def _fmt(value: float) -> str:
    return f"{value:.3f}" if math.isfinite(value) else ""


def write_prep(out_dir: str | Path, result: Any,
               progress: Callable[[int], None] | None = None) -> Path:
    """Write ``buildings/<id>.laz`` (CRS coordinates), ``buildings.csv``, ``frame.json`` and ``prep.json`` of a
    :class:`lidarmap.aerial.prep.PrepResult` (read by its attributes: this module knows no stage).

    Everything goes to a temporary folder beside ``out_dir`` that is renamed onto it at the end, so an error never
    leaves a half-written output. An earlier prep output at ``out_dir`` is replaced; any other non-empty folder is
    refused.
    """
    out = check_out_dir(out_dir)
    with atomic_dir(out) as tmp:
        (tmp / "buildings").mkdir()
        rows, taken = [], set()
        for building in result.buildings:
            name = building_file_name(building.id, taken)
            write_las(tmp / "buildings" / name, building.cloud)
            lo, hi = building.cloud.xyz.min(axis=0), building.cloud.xyz.max(axis=0)
            rows.append([building.id, f"buildings/{name}", len(building), building.points_inside,
                         _fmt(building.height), building.height_source, _fmt(building.ground_z),
                         *(_fmt(v) for v in (lo[0], lo[1], lo[2], hi[0], hi[1], hi[2])), building.status or ""])
            if progress is not None:
                progress(1)
        text = io.StringIO()
        writer = csv.writer(text, lineterminator="\n")
        writer.writerow(INDEX_COLUMNS)
        writer.writerows(rows)
        write_text_atomic(tmp / "buildings.csv", text.getvalue())
        frame = json.loads(result.frame.to_json())
        if result.crs is not None:
            frame["crs"] = result.crs.to_wkt()
        write_text_atomic(tmp / "frame.json", json.dumps(frame, indent=2))
        summary = {
            "tiles": result.sources, "footprints": result.footprint_source,
            "crs": describe_crs(result.crs), "params": dataclasses.asdict(result.params),
            "points_read": result.points_read, "points_kept": result.points_kept,
            "footprint_count": result.footprints, "buildings": len(result.buildings),
            "dropped": result.dropped, "seconds": round(result.seconds, 3),
        }
        write_text_atomic(tmp / _MARKER, json.dumps(summary, indent=2))
    return out


def read_prep_index(out_dir: str | Path) -> list[dict[str, Any]]:
    """The rows of ``buildings.csv`` (numbers parsed; ``path`` is the building file's full path)."""
    out = Path(out_dir)
    index = out / "buildings.csv"
    if not index.exists():
        raise InputError("no buildings.csv: not a prep output folder", out)
    rows = []
    with index.open(encoding="utf-8", newline="") as fh:
        for row in csv.DictReader(fh):
            parsed: dict[str, Any] = dict(row)
            for key in ("points", "points_inside"):
                parsed[key] = int(row[key])
            for key in ("height", "ground_z", "xmin", "ymin", "zmin", "xmax", "ymax", "zmax"):
                parsed[key] = float(row[key]) if row[key] else float("nan")
            parsed["path"] = out / row["file"]
            rows.append(parsed)
    return rows
