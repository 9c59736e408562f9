"""Polygons that GIS tools accept: every exported surface valid in its own plane.

A CityJSON file can pass the schema and still break the tools that triangulate it (cjio's OBJ/glTF/STL export,
QGIS, FME): a ring that touches itself at a vertex, a ring that repeats a vertex, a face with no area at the file's
millimetre quantum, vertices listed but used by no surface. The writers pass every surface through
:func:`valid_polygons` before its vertices are registered, and :func:`surface_problems` lets
:func:`lidarmap.export.validate.validate_cityjson` find such surfaces in any document.

"Valid in its plane": the surface's rings are projected onto the plane of the exterior ring (Newell normal) and the
2D polygon must be valid in the OGC sense (``shapely`` ``is_valid``: no self-intersection, no self-touching ring,
holes inside the shell), every ring with at least 3 distinct vertices and no vertex twice. An invalid surface is
repaired with ``shapely.make_valid`` (a self-touching ring becomes two polygons, a bow-tie two triangles); vertices
that the repair creates (crossing points) are lifted back onto the plane. Parts smaller than ``min_area`` are slivers
and are dropped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

__all__ = ["MIN_AREA", "dedupe_ring", "plane_basis", "surface_problems", "valid_polygons"]

#: Surfaces (or repaired parts) smaller than this (m²) are slivers and are left out of the exports: 1 cm², well below
#: any façade element or roof face, above what millimetre rounding leaves of a collapsed triangle.
MIN_AREA = 1e-4


def dedupe_ring(ring: np.ndarray) -> np.ndarray:
    """The ring without its closing vertex and without consecutive repeated vertices (rows)."""
    ring = np.asarray(ring)
    if len(ring) == 0:
        return ring
    keep = np.ones(len(ring), dtype=bool)
    keep[1:] = np.any(ring[1:] != ring[:-1], axis=1)
    ring = ring[keep]
    while len(ring) > 1 and np.array_equal(ring[0], ring[-1]):
        ring = ring[:-1]
    return ring


def plane_basis(exterior: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(origin, u, v, n) of the exterior ring's plane (Newell normal n, u x v = n), ``None`` for a ring without area.

    A ring that runs counter-clockwise around n is counter-clockwise in (u, v).
    """
    p = np.asarray(exterior, dtype=np.float64)
    origin = p.mean(axis=0)
    q, r = p - origin, np.roll(p - origin, -1, axis=0)
    n = np.array([np.sum((q[:, 1] - r[:, 1]) * (q[:, 2] + r[:, 2])),
                  np.sum((q[:, 2] - r[:, 2]) * (q[:, 0] + r[:, 0])),
                  np.sum((q[:, 0] - r[:, 0]) * (q[:, 1] + r[:, 1]))])
    length = np.linalg.norm(n)
    if not length > 1e-12:  # no net area: a bow-tie's halves cancel, or all on a line; fit the points' plane
        _, sigma, vt = np.linalg.svd(q, full_matrices=False)
        if len(sigma) < 2 or not sigma[1] > 1e-9 * max(sigma[0], 1e-300):
            return None
        n, length = vt[-1] if len(sigma) == 3 else np.cross(vt[0], vt[1]), 1.0
    n = n / np.linalg.norm(n)
    helper = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    return origin, u, np.cross(n, u), n


def _polygon_2d(rings: Sequence[np.ndarray], basis: tuple) -> Polygon:
    origin, u, v, _ = basis
    flat = [np.column_stack([(r - origin) @ u, (r - origin) @ v]) for r in rings]
    return Polygon(flat[0], flat[1:])


def _has_repeats(rings: Sequence[np.ndarray]) -> bool:
    return any(len(np.unique(r, axis=0)) != len(r) for r in rings)


def valid_polygons(rings: Sequence[np.ndarray], min_area: float = MIN_AREA) -> list[list[np.ndarray]]:
    """A surface (exterior ring, then holes; (n, 3) coordinates, already rounded to the file's quantum; ``min_area``
    in the coordinates' unit squared) as valid
    polygons in its plane: ``[]`` when nothing of it is left (a collapsed ring, a sliver), ``[rings]`` when it was
    valid, several polygons when the repair split it. Rings come back without closing vertex; the exterior keeps the
    input's orientation (its normal), holes run the other way. Coordinates the repair creates are lifted onto the
    plane and rounded like the input (integers stay integers).
    """
    cleaned = [dedupe_ring(r) for r in rings]
    if len(cleaned[0]) < 3:
        return []
    holes = [h for h in cleaned[1:] if len(h) >= 3]
    basis = plane_basis(cleaned[0])
    if basis is None:
        return []
    polygon = _polygon_2d([cleaned[0], *holes], basis)
    if polygon.is_valid and not _has_repeats([cleaned[0], *holes]):
        return [[cleaned[0], *holes]] if polygon.area >= min_area else []
    return _repaired(polygon, [cleaned[0], *holes], basis, min_area)


def _repaired(polygon: Polygon, rings: list[np.ndarray], basis: tuple, min_area: float) -> list[list[np.ndarray]]:
    """make_valid's polygons, their vertices mapped back to the input's (new ones lifted onto the plane)."""
    origin, u, v, _ = basis
    is_int = np.issubdtype(rings[0].dtype, np.integer)
    known = {}
    for ring in rings:
        for xyz in ring:
            d = xyz - origin
            known[(round(float(d @ u), 6), round(float(d @ v), 6))] = xyz
    out = []
    for part in _polygon_parts(shapely.make_valid(polygon)):
        part = orient(part, 1.0)
        if part.area < min_area:
            continue
        lifted = []
        for ring in [part.exterior, *part.interiors]:
            xy = np.asarray(ring.coords)[:-1]
            pts = []
            for s, t in xy:
                xyz = known.get((round(float(s), 6), round(float(t), 6)))
                if xyz is None:  # a crossing point made by the repair: on the plane, rounded like the input
                    xyz = origin + s * u + t * v
                    xyz = np.rint(xyz).astype(rings[0].dtype) if is_int else xyz
                pts.append(xyz)
            lifted.append(dedupe_ring(np.asarray(pts)))
        if len(lifted[0]) >= 3 and not _has_repeats(lifted):
            out.append([r for r in lifted if len(r) >= 3])
    return out


def _polygon_parts(geom) -> list[Polygon]:
    if isinstance(geom, Polygon):
        return [] if geom.is_empty else [geom]
    return [p for g in getattr(geom, "geoms", []) for p in _polygon_parts(g)]


def surface_problems(rings: Sequence[np.ndarray], min_area: float = MIN_AREA) -> list[str]:
    """Why a surface (rings of (n, 3) coordinates, no closing vertex) is not valid in its plane; empty if it is."""
    rings = [np.asarray(r, dtype=np.float64) for r in rings]
    problems = []
    if any(len(np.unique(r, axis=0)) != len(r) for r in rings):
        problems.append("a ring repeats a vertex")
    if any(len(np.unique(r, axis=0)) < 3 for r in rings):
        return problems + ["a ring has fewer than 3 distinct vertices"]
    basis = plane_basis(rings[0])
    if basis is None:
        return problems + ["the exterior ring has no area"]
    polygon = _polygon_2d(rings, basis)
    if not polygon.is_valid:
        problems.append(f"not valid in its plane ({shapely.is_valid_reason(polygon)})")
    elif polygon.area < min_area:
        problems.append(f"a sliver of {polygon.area:.2g} m² (< {min_area:g})")
    return problems
