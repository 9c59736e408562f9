"""Coordinate reference systems: parse user input, describe, compare."""

from __future__ import annotations

from pyproj import CRS
from pyproj.exceptions import CRSError as PyprojCRSError

from lidarmap.errors import CRSError


def parse_crs(text: str | int | CRS | None, path: str | None = None) -> CRS | None:
    """A CRS from 'EPSG:2154', '2154', WKT, a pyproj CRS or ``None``; an unknown one is a one-line error."""
    if text is None or isinstance(text, CRS):
        return text
    value = str(text).strip()
    if value.isdigit():
        value = f"EPSG:{value}"
    try:
        return CRS.from_user_input(value)
    except PyprojCRSError:
        raise CRSError(f"unknown CRS {str(text)[:80]!r}", path) from None


def describe_crs(crs: CRS | None) -> dict[str, object] | None:
    """Name and EPSG code (when pyproj can identify one) for reports."""
    if crs is None:
        return None
    epsg = crs.to_epsg(min_confidence=70)
    horizontal = crs.sub_crs_list[0] if crs.is_compound and crs.sub_crs_list else crs
    units = horizontal.axis_info[0].unit_name if horizontal.axis_info else None
    return {"name": crs.name, "epsg": epsg, "units": units, "is_projected": bool(horizontal.is_projected)}


def horizontal_crs(crs: CRS) -> CRS:
    """The horizontal part of a compound CRS (footprints are 2D)."""
    if crs.is_compound and crs.sub_crs_list:
        return crs.sub_crs_list[0]
    return crs


def same_crs(a: CRS | None, b: CRS | None) -> bool:
    """True when two CRSs describe the same horizontal system (a compound CRS matches its horizontal part)."""
    if a is None or b is None:
        return a is b
    ha, hb = horizontal_crs(a), horizontal_crs(b)
    return ha == hb or (ha.to_epsg() is not None and ha.to_epsg() == hb.to_epsg())
