"""GeoPackage output (OGC GeoPackage 1.3) written with the standard library's sqlite3, atomically.

A run's ``buildings.gpkg`` must not need GDAL (pyogrio is an optional extra), and a GeoPackage is a SQLite file with
three metadata tables and geometry blobs (a small header + ISO WKB), so QGIS and GDAL open it as it is.
"""

from __future__ import annotations

import math
import sqlite3
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.base import BaseGeometry

from lidarmap.io.atomic import atomic_path

APPLICATION_ID = 0x47504B47  # "GPKG"
USER_VERSION = 10300  # GeoPackage 1.3.0
#: srs_id of an undefined Cartesian CRS (table required by the standard) and of a CRS without an EPSG code.
UNDEFINED_SRS_ID = -1
CUSTOM_SRS_ID = 100000

_BASE_TABLES = """
CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY, organization TEXT NOT NULL,
  organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL, description TEXT);
CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL, identifier TEXT UNIQUE,
  description TEXT DEFAULT '', last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
  min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
  CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
  geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
  CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name),
  CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
  CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id));
INSERT INTO gpkg_spatial_ref_sys VALUES ('Undefined cartesian SRS', -1, 'NONE', -1, 'undefined', NULL);
INSERT INTO gpkg_spatial_ref_sys VALUES ('Undefined geographic SRS', 0, 'NONE', 0, 'undefined', NULL);
"""

_WGS84_WKT = CRS.from_epsg(4326).to_wkt("WKT1_GDAL")


def _sql_type(values: Sequence[Any]) -> str:
    """The column type of its values (None/NaN ignored): BOOLEAN, INTEGER, REAL or TEXT."""
    present = [_cell(v) for v in values]
    present = [v for v in present if v is not None]
    if present and all(isinstance(v, bool) for v in present):
        return "BOOLEAN"
    if present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
        return "INTEGER"
    if present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
        return "REAL"
    return "TEXT" if present else "REAL"


def _cell(value: Any) -> Any:
    """A column value as sqlite3 stores it: numpy scalars as Python numbers, NaN as NULL."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _srs(crs: CRS | None) -> tuple[int, tuple[Any, ...] | None]:
    """The srs_id for ``crs`` and its gpkg_spatial_ref_sys row (``None``: a row the base tables already hold)."""
    if crs is None:
        return UNDEFINED_SRS_ID, None
    epsg = crs.to_epsg()
    wkt = crs.to_wkt("WKT1_GDAL") or crs.to_wkt()
    if epsg is not None:
        return epsg, (crs.name, epsg, "EPSG", epsg, wkt, None)
    return CUSTOM_SRS_ID, (crs.name, CUSTOM_SRS_ID, "NONE", CUSTOM_SRS_ID, wkt, None)


def _blob(geom: BaseGeometry | None, srs_id: int) -> bytes | None:
    """GeoPackage geometry: 'GP', version 0, flags (little endian, xy envelope), srs_id, envelope, ISO WKB."""
    if geom is None:
        return None
    if geom.is_empty:
        return b"GP\x00\x11" + struct.pack("<i", srs_id) + shapely.to_wkb(geom, byte_order=1, flavor="iso")
    x0, y0, x1, y1 = geom.bounds
    return (b"GP\x00\x03" + struct.pack("<i4d", srs_id, x0, x1, y0, y1)
            + shapely.to_wkb(geom, byte_order=1, flavor="iso"))


def as_multipolygon(geom: BaseGeometry | None) -> MultiPolygon | None:
    """Polygons as one-part multipolygons, so a layer has one geometry type."""
    if isinstance(geom, Polygon):
        return MultiPolygon([geom])
    return geom


def write_gpkg_polygons(path: str | Path, layer: str, geometries: Sequence[BaseGeometry | None],
                        columns: dict[str, Sequence[Any]], crs: CRS | None) -> Path:
    """Write one MULTIPOLYGON layer (2D) with attribute ``columns`` (name -> one value per geometry), atomically."""
    geometries = [as_multipolygon(g) for g in geometries]
    for name, values in columns.items():
        if len(values) != len(geometries):
            raise ValueError(f"column {name!r} has {len(values)} values for {len(geometries)} geometries")
    srs_id, srs_row = _srs(crs)
    present = [g for g in geometries if g is not None and not g.is_empty]
    bounds = shapely.total_bounds(np.array(present, dtype=object)) if present else [None] * 4
    quoted = ", ".join(f'"{name}" {_sql_type(values)}' for name, values in columns.items())
    with atomic_path(path) as tmp:
        db = sqlite3.connect(tmp)
        try:
            db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            db.execute(f"PRAGMA user_version = {USER_VERSION}")
            db.executescript(_BASE_TABLES)
            db.execute("INSERT INTO gpkg_spatial_ref_sys VALUES ('WGS 84', 4326, 'EPSG', 4326, ?, NULL)", (_WGS84_WKT,))
            if srs_row is not None and srs_id != 4326:
                db.execute("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)", srs_row)
            db.execute(f'CREATE TABLE "{layer}" (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom MULTIPOLYGON'
                       + (f", {quoted}" if quoted else "") + ")")
            db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, max_y, "
                       "srs_id) VALUES (?, 'features', ?, ?, ?, ?, ?, ?)",
                       (layer, layer, *[_cell(b) for b in bounds], srs_id))
            db.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', 'MULTIPOLYGON', ?, 0, 0)", (layer, srs_id))
            names = list(columns)
            marks = ", ".join("?" * (len(names) + 1))
            fields = ", ".join(["geom", *[f'"{n}"' for n in names]])
            rows = ((_blob(g, srs_id), *[_cell(columns[n][i]) for n in names]) for i, g in enumerate(geometries))
            db.executemany(f'INSERT INTO "{layer}" ({fields}) VALUES ({marks})', rows)
            db.commit()
        finally:
            db.close()
    return Path(path)
