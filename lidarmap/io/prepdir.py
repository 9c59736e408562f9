"""The folder ``lidarmap prep`` writes: ``buildings/<id>.laz``, ``buildings.csv`` (the index), ``frame.json`` and
``prep.json``; written whole (temporary folder published at the end, :mod:`lidarmap.io.outdir`) and read back by ``segment``."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import re
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from lidarmap.errors import InputError
from lidarmap.io.atomic import write_text_atomic
from lidarmap.io.crs import describe_crs
from lidarmap.io.las import write_las
from lidarmap.io.outdir import atomic_out_dir, claim_out_dir

INDEX_COLUMNS = ["id", "file", "points", "points_inside", "height", "height_source", "ground_z",
                 "xmin", "ymin", "zmin", "xmax", "ymax", "zmax", "status"]


#: The summary of a prep output (its marker is :data:`lidarmap.io.outdir.MARKER`).
SUMMARY = "prep.json"
#: Kind of the output-folder marker that prep writes.
KIND = "prep"
#: Longest file-name stem made from a building id (file systems allow 255 bytes; suffixes and ``_2`` need room).
MAX_STEM = 100


def safe_stem(building_id: str) -> str:
    """A file-name stem for a building id: characters other than letters, digits, ``.-_`` become ``_``; a stem
    that is empty or only dots becomes ``building``; one longer than :data:`MAX_STEM` is cut and ends with a hash of
    the whole id (two long ids that share a beginning stay apart)."""
    return shorten_stem(re.sub(r"[^A-Za-z0-9._-]", "_", str(building_id)).strip(".") or "building", building_id)


def shorten_stem(stem: str, building_id: str) -> str:
    """``stem`` cut to :data:`MAX_STEM` characters when longer, ending with a hash of the whole id (so that two long
    ids that share a beginning stay apart)."""
    if len(stem) <= MAX_STEM:
        return stem
    digest = hashlib.sha256(str(building_id).encode("utf-8", "surrogatepass")).hexdigest()[:12]
    return f"{stem[:MAX_STEM - 13]}_{digest}"


def unique_stems(building_ids: Iterable[str]) -> dict[str, str]:
    """File-safe stems, unique without regard to case, for ids in order: id -> stem (``a/b`` and ``a_b`` give
    ``a_b`` and ``a_b_2``). The same ids in the same order always give the same stems."""
    taken: set[str] = set()
    stems: dict[str, str] = {}
    for building_id in building_ids:
        base = safe_stem(building_id)
        stem, k = base, 1
        while stem.lower() in taken:
            k += 1
            stem = f"{base}_{k}"
        taken.add(stem.lower())
        stems[building_id] = stem
    return stems


def check_out_dir(out_dir: str | Path) -> Path:
    """Refuse an output path prep may not write (see :func:`lidarmap.io.outdir.claim_out_dir`): a file, a
    non-empty folder lidarmap did not write, another command's output."""
    return claim_out_dir(out_dir, KIND)


def _fmt(value: float) -> str:
    return f"{value:.3f}" if math.isfinite(value) else ""


def write_prep(out_dir: str | Path, result: Any,
               progress: Callable[[int], None] | None = None) -> Path:
    """Write ``buildings/<id>.laz`` (CRS coordinates), ``buildings.csv``, ``frame.json`` and ``prep.json`` of a
    :class:`lidarmap.aerial.prep.PrepResult` (read by its attributes: this module knows no stage).

    Everything goes to a temporary folder beside ``out_dir`` whose entries are moved in at the end, so an error never
    leaves a half-written output. An earlier prep output at ``out_dir`` is replaced (only what its marker lists: files
    the user added stay); a non-empty folder lidarmap did not write is refused (:mod:`lidarmap.io.outdir`).
    """
    out = Path(out_dir)
    with atomic_out_dir(out, KIND) as tmp:
        (tmp / "buildings").mkdir()
        rows = []
        stems = unique_stems(b.id for b in result.buildings)
        for building in result.buildings:
            name = f"{stems[building.id]}.laz"
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
            "dropped": result.dropped, "repaired": list(result.repaired), "seconds": round(result.seconds, 3),
        }
        write_text_atomic(tmp / SUMMARY, json.dumps(summary, indent=2))
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
