"""Building footprints: GeoJSON (RFC 7946 WGS84, or a legacy ``crs`` member) read here; GeoPackage, Shapefile and
FlatGeobuf through pyogrio (the optional ``gis`` extra), CRS from the file; all reprojected to the points' CRS."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS
from shapely.geometry import MultiPolygon, Polygon, mapping, shape

from lidarmap.core import Footprints
from lidarmap.errors import CRSError, InputError
from lidarmap.io.atomic import write_text_atomic

WGS84 = CRS.from_epsg(4326)


def _legacy_crs(doc: dict[str, Any], path: Path) -> CRS | None:
    member = doc.get("crs")
    if not member:
        return None
    name = (member.get("properties") or {}).get("name") if isinstance(member, dict) else None
    if not name:
        raise CRSError("GeoJSON 'crs' member has no properties.name", path)
    match = re.search(r"EPSG:+(\d+)", str(name), re.IGNORECASE)
    try:
        return CRS.from_epsg(int(match.group(1))) if match else CRS.from_user_input(name)
    except Exception:  # noqa: BLE001
        raise CRSError(f"unknown CRS {name!r} in the GeoJSON 'crs' member", path) from None


#: Footprint formats read through pyogrio (GDAL), by file suffix.
OGR_SUFFIXES = {".gpkg": "GeoPackage", ".shp": "Shapefile", ".fgb": "FlatGeobuf"}
GIS_EXTRA_HINT = "pip install 'lidarmap[gis]'"


def read_footprints(path: str | Path, id_field: str = "id", crs: CRS | None = None) -> Footprints:
    """Read building footprints: GeoJSON, GeoPackage (first layer), Shapefile or FlatGeobuf (Multi)Polygons.

    GeoJSON's CRS is the legacy ``crs`` member when present, else WGS84 (RFC 7946); the others carry theirs. The
    building id comes from property ``id_field`` (or a GeoJSON feature's ``id``), falling back to the feature index.
    With ``crs`` the footprints are reprojected to it.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", path)
    if path.suffix.lower() in OGR_SUFFIXES:
        geoms, props, source_crs = _read_ogr(path)
        features = [{"geometry": g, "properties": p} for g, p in zip(geoms, props)]
    else:
        doc = _read_geojson(path)
        features = doc["features"]
        source_crs = _legacy_crs(doc, path) or WGS84
    result = _footprints(features, id_field, source_crs, path)
    return result.to_crs(crs) if crs is not None else result


def _read_geojson(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("features"), list):
        raise InputError("not a GeoJSON FeatureCollection", path)
    return doc


def _pyogrio(path: Path) -> Any:
    try:
        import pyogrio
    except ImportError:
        raise InputError(f"reading {OGR_SUFFIXES[path.suffix.lower()]} footprints needs pyogrio: "
                         f"{GIS_EXTRA_HINT} (or convert to GeoJSON)", path) from None
    return pyogrio


def _read_ogr(path: Path) -> tuple[list[Any], list[dict[str, Any]], CRS]:
    """Geometries (shapely or None), attribute rows and CRS of the first layer of a GDAL vector file."""
    pyogrio = _pyogrio(path)
    try:
        meta, _, wkb, columns = pyogrio.raw.read(path, force_2d=True)
    except Exception as exc:  # noqa: BLE001 - GDAL raises DataSourceError, DataLayerError, ... on bad files
        raise InputError(f"cannot read as {OGR_SUFFIXES[path.suffix.lower()]} ({_one_line(exc)})", path) from None
    if not meta.get("crs"):
        raise CRSError("footprint file has no CRS (a .prj file beside a Shapefile, or a layer SRS)", path)
    try:
        source_crs = CRS.from_user_input(meta["crs"])
    except Exception:  # noqa: BLE001
        raise CRSError(f"unknown CRS {str(meta['crs'])[:80]!r} in the footprint file", path) from None
    geoms = [None if g is None else shapely.from_wkb(g) for g in (wkb if wkb is not None else [])]
    names = [str(n) for n in meta["fields"]]
    rows = [dict(zip(names, (_plain(col[i]) for col in columns))) for i in range(len(geoms))]
    return geoms, rows, source_crs


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python value JSON and the rest of the pipeline expect (NaN as None)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:160] or type(exc).__name__


def _footprints(features: list[Any], id_field: str, source_crs: CRS, path: Path) -> Footprints:
    """Usable (Multi)Polygon footprints with unique ids; unusable features listed in ``rejected`` with the reason,
    repaired self-intersecting polygons in ``repaired`` (prep and run report both)."""
    ids, polys, props = [], [], []
    rejected: dict[str, str] = {}
    repaired: list[str] = []
    seen: set[str] = set()
    for index, feature in enumerate(features):
        feature = feature if isinstance(feature, dict) else {}
        properties = dict(feature.get("properties") or {})
        raw_id = properties.get(id_field, feature.get("id") if id_field == "id" else None)
        fid = str(raw_id) if raw_id is not None else str(index)
        geom, problem = _polygon_of(feature.get("geometry"), index, path)
        if geom is None:
            rejected[fid if fid not in rejected else f"{fid}_{index}"] = problem
            continue
        if fid in seen:
            fid = f"{fid}_{index}"
        seen.add(fid)
        if problem:
            repaired.append(fid)
        ids.append(fid)
        polys.append(geom)
        props.append(properties)
    if not ids:
        first = f" ({len(rejected)} feature(s) unusable, e.g. {next(iter(rejected.values()))})" if rejected else ""
        raise InputError(f"no polygon footprints in file{first}", path)
    return Footprints(ids, np.array(polys, dtype=object), props, source_crs, str(path), rejected, repaired)


def _polygon_of(geom_doc: Any, index: int, path: Path) -> tuple[Polygon | MultiPolygon | None, str]:
    """A feature's usable (Multi)Polygon and "" / "repaired ..." , or ``None`` and why it cannot be used: null, empty
    or non-polygon geometry, a NaN or infinite vertex, zero area. A self-intersecting polygon is repaired with
    ``shapely.make_valid`` (its polygonal parts kept) and reported as repaired."""
    if geom_doc is None or (isinstance(geom_doc, dict) and not geom_doc):
        return None, "null geometry"
    if not isinstance(geom_doc, dict):  # a shapely geometry read through pyogrio
        return _usable_polygon(geom_doc, geom_doc.geom_type)
    kind = geom_doc.get("type")
    if kind not in ("Polygon", "MultiPolygon"):
        return None, f"{kind or 'unknown'} geometry, not a polygon"
    if not geom_doc.get("coordinates"):
        return None, "empty geometry"
    try:
        with warnings.catch_warnings():  # NaN vertices: numpy warns before we can say which feature
            warnings.simplefilter("ignore", RuntimeWarning)
            geom = shape(geom_doc)
    except Exception as exc:  # noqa: BLE001 - shapely raises several kinds for malformed coordinates
        raise InputError(f"feature {index}: invalid geometry ({exc})", path) from None
    return _usable_polygon(geom, kind)


def _usable_polygon(geom: Any, kind: str) -> tuple[Polygon | MultiPolygon | None, str]:
    if kind not in ("Polygon", "MultiPolygon"):
        return None, f"{kind or 'unknown'} geometry, not a polygon"
    if geom.is_empty:
        return None, "empty geometry"
    if not np.all(np.isfinite(shapely.get_coordinates(geom))):
        return None, "NaN or infinite vertex"
    problem = ""
    if not geom.is_valid:
        problem = f"repaired ({shapely.is_valid_reason(geom)})"
        fixed = shapely.make_valid(geom)
        parts = [g for g in getattr(fixed, "geoms", [fixed]) if isinstance(g, (Polygon, MultiPolygon))]
        parts = [p for g in parts for p in getattr(g, "geoms", [g])]
        geom = parts[0] if len(parts) == 1 else MultiPolygon(parts)
    if geom.is_empty or not geom.area > 0:
        return None, "zero area"
    return geom, problem


def check_overlap(footprints: Footprints, bounds: tuple[float, float, float, float], points_name: str) -> None:
    """Refuse footprints whose bounding box misses the points' bounding box (wrong CRS, wrong file)."""
    fx0, fy0, fx1, fy1 = footprints.bounds
    px0, py0, px1, py1 = bounds
    if not footprints.meets(bounds):
        raise InputError(
            f"footprints do not overlap the points of {points_name}: footprints bbox "
            f"[{fx0:.2f}, {fy0:.2f}, {fx1:.2f}, {fy1:.2f}] vs points bbox [{px0:.2f}, {py0:.2f}, {px1:.2f}, {py1:.2f}]"
            f" ({footprints.crs.name})", footprints.source)


def write_geojson_wgs84(path: str | Path, polygons: list[Polygon], properties: list[dict[str, Any]],
                        crs: CRS) -> Path:
    """Write footprints as RFC 7946 GeoJSON (reprojected from ``crs`` to WGS84 lon/lat), atomically."""
    fp = Footprints([str(i) for i in range(len(polygons))], np.array(polygons, dtype=object), properties, crs)
    wgs = fp.to_crs(WGS84)
    features = [{"type": "Feature", "properties": props, "geometry": mapping(geom)}
                for geom, props in zip(wgs.polygons, properties)]
    doc = {"type": "FeatureCollection", "features": features}
    return write_text_atomic(path, json.dumps(doc, indent=None))
