"""The building map as CityJSON 2.0 (one ``Building`` city object per map building).

Mapping (docs/map.md has the full table):

* ``transform``: scale 0.001 (mm) and a whole-metre translate; vertices are integers, so every exported coordinate
  is within 0.5 mm of the map's float64 value. ``metadata.referenceSystem`` is
  ``https://www.opengis.net/def/crs/EPSG/0/<code>`` when the map's CRS has an EPSG code.
* A building with façades or roof planes gets a ``MultiSurface`` at ``lod "2"`` (walls without openings or
  structures, roofs) and, when it has windows, doors or structures, first one at ``lod "3"`` (openings are an LoD 3
  concept) with semantic surfaces:

  - each façade: a ``WallSurface`` (``lidarmap_kind: "facade"``) covering its extent at the main layer's depth,
    at LoD 3 with the window/door openings cut out as holes; attributes: façade id, depth σ of the plane, points,
    campaigns, footprint edge, frame (origin, u, normal), extent, layers, and the façade's unknown regions;
  - windows and doors: ``Window`` / ``Door`` surfaces whose ``parent`` is that WallSurface (listed in its
    ``children``), at their layer's depth; attributes ``lidarmap_uncertainty`` (ε), ``lidarmap_depth``,
    ``lidarmap_depth_sigma`` (the layer's σ), layer id, points, campaigns;
  - structures (balconies, extrusions): ``WallSurface`` with ``lidarmap_kind: "structure"`` at their layer depth,
    with ε (eq. 1-2) and the layer's σ;
  - unknown regions (occlusions, unexplained holes; ε = ∞): no geometry of their own (the wall already covers
    them), listed in the WallSurface attribute ``lidarmap_unknown_regions``: element id, kind, ``uncertainty:
    null`` (∞ has no JSON number), area (m²), points, campaigns and ``outlines`` (exterior and holes in CRS
    coordinates, mm-rounded, at the wall's depth);
  - roof planes: ``RoofSurface`` polygons (outline lifted onto the plane) with the fit σ as ``lidarmap_depth_sigma``.
* A building without façades or roofs: a LoD1 block (``Solid``; ``MultiSurface`` for a multi-part footprint) from
  the footprint extruded by its height attribute (``measuredHeight``/``height``/``h``), from its ground height
  attribute (``ground_z``/``base_z``, else 0); without a height only the footprint at ``lod "0"``.

Every surface is made valid in its plane before its vertices are registered (:mod:`lidarmap.export.geomcheck`):
no repeated vertex, no self-touching ring (split into two surfaces with the same semantics), no sliver, no unused
vertex, so tools that triangulate (cjio's OBJ export) accept the file.

Building attributes are the map's (footprint properties; NaN/∞ become null) plus ``lidarmap_*`` counts
(:func:`lidarmap.export.summary.count_buildings`) and the campaigns that observed it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS
from shapely.geometry import Polygon, box
from shapely.geometry.polygon import orient

from lidarmap.export.geomcheck import MIN_AREA, valid_polygons
from lidarmap.export.planar import PlanarParams, planar_faces
from lidarmap.export.summary import COUNT_KEYS, count_buildings
from lidarmap.facade.model import Element, ElementKind, Facade
from lidarmap.io.atomic import atomic_path, write_text_atomic
from lidarmap.map.model import Building, BuildingMap

__all__ = ["CITYJSON_VERSION", "SCALE", "map_to_cityjson", "write_cityjson", "reference_system",
           "HEIGHT_ATTRIBUTES", "GROUND_ATTRIBUTES", "AerialBuilding", "write_aerial_cityjson"]

CITYJSON_VERSION = "2.0"
#: Vertex quantum (CRS units, metres): integer vertices times SCALE plus translate give the coordinates.
SCALE = 0.001
#: Building attributes read as the LoD1 block height (first one that is a positive number).
HEIGHT_ATTRIBUTES = ("measuredHeight", "height", "h", "building_height")
#: Building attributes read as the block's ground height (else 0).
GROUND_ATTRIBUTES = ("ground_z", "base_z", "groundHeight", "z_ground")


def reference_system(crs_wkt: str) -> str | None:
    """``https://www.opengis.net/def/crs/EPSG/0/<code>`` for the map's CRS, ``None`` without an EPSG code."""
    if not crs_wkt:
        return None
    try:
        crs = CRS.from_user_input(crs_wkt)
    except Exception:  # noqa: BLE001
        return None
    code = crs.to_epsg()
    if code is None:
        for sub in crs.sub_crs_list or []:
            code = sub.to_epsg()
            if code is not None:
                break
    return None if code is None else f"https://www.opengis.net/def/crs/EPSG/0/{code}"


def _json_safe(value: Any) -> Any:
    """Attributes as strict JSON: numpy scalars to Python, NaN/inf to null, keys to strings."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_json_safe(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def _num(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _parts(geom: Any) -> list[Polygon]:
    """Non-empty polygons of a (Multi)Polygon / collection."""
    if geom is None or geom.is_empty:
        return []
    if isinstance(geom, Polygon):
        return [geom]
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]


class _Vertices:
    """Quantised, de-duplicated vertices shared by every city object of the document."""

    def __init__(self, translate: np.ndarray, scale: float, base: int = 0):
        self.translate = translate
        self.scale = scale
        self.base = base  # index of this list's first vertex in the document (streamed documents)
        self.index: dict[tuple[int, int, int], int] = {}
        self.list: list[list[int]] = []

    def polygons(self, rings_xyz: Sequence[np.ndarray]) -> list[list[list[int]]]:
        """Vertex indices of a surface (exterior ring, then holes; CRS xyz, closing vertex optional) made valid in its
        plane at the export's quantum (:func:`lidarmap.export.geomcheck.valid_polygons`): ``[]`` when it collapses,
        several polygons when the repair splits it. Only the vertices of what is kept are registered."""
        quantised = [np.rint((np.asarray(r, dtype=np.float64) - self.translate) / self.scale).astype(np.int64)
                     for r in rings_xyz]
        return [[self._register(ring) for ring in polygon]
                for polygon in valid_polygons(quantised, MIN_AREA / self.scale ** 2)]

    def _register(self, ring: np.ndarray) -> list[int]:
        out = []
        for v in map(tuple, ring.tolist()):
            i = self.index.get(v)  # type: ignore[arg-type]
            if i is None:
                i = self.index[v] = self.base + len(self.list)  # type: ignore[index]
                self.list.append(list(v))
            out.append(i)
        return out


class _Surfaces:
    """A MultiSurface under construction: boundaries, semantic objects and per-surface semantic values."""

    def __init__(self, vertices: _Vertices):
        self.v = vertices
        self.boundaries: list[list[list[int]]] = []
        self.semantics: list[dict[str, Any]] = []
        self.values: list[int | None] = []

    def add(self, parts: list[list[np.ndarray]], semantic: dict[str, Any]) -> int | None:
        """Add the surfaces ``parts`` (each: exterior ring, then holes, CRS xyz) under one semantic object.

        Returns the semantic object's index, or ``None`` (nothing registered) when every part is degenerate at the
        export's millimetre quantum.
        """
        surfaces = [polygon for rings_xyz in parts for polygon in self.v.polygons(rings_xyz)]
        if not surfaces:
            return None
        self.semantics.append(semantic)
        index = len(self.semantics) - 1
        self.boundaries.extend(surfaces)
        self.values.extend([index] * len(surfaces))
        return index

    def geometry(self, lod: str) -> dict[str, Any] | None:
        if not self.boundaries:
            return None
        return {"type": "MultiSurface", "lod": lod, "boundaries": self.boundaries,
                "semantics": {"surfaces": self.semantics, "values": self.values}}


def _facade_rings(facade: Facade, polygon: Polygon, depth: float) -> list[np.ndarray]:
    """Rings of a façade-plane polygon in CRS (exterior counter-clockwise seen from outside, holes clockwise)."""
    polygon = orient(polygon, 1.0)
    out = []
    for ring in [polygon.exterior, *polygon.interiors]:
        st = np.asarray(ring.coords, dtype=np.float64)[:, :2]
        out.append(facade.frame.to_crs(np.column_stack([st, np.full(len(st), depth)])))
    return out


def _element_depth(facade: Facade, element: Element, main_depth: float) -> tuple[float, float]:
    """Depth (d) and its σ for an element: its layer's Gaussian, else the main layer's depth and the plane's σ."""
    layer = facade.layer(element.layer_id) if element.layer_id is not None else None
    if layer is not None and not element.is_unknown:
        return float(layer.mu), float(layer.sigma)
    return main_depth, float(facade.sigma)


def _element_semantic(kind: str, facade: Facade, element: Element, depth: float, sigma: float) -> dict[str, Any]:
    return {
        "type": kind,
        "lidarmap_kind": ElementKind(element.kind).value,
        "lidarmap_facade_id": int(facade.facade_id),
        "lidarmap_element_id": int(element.element_id),
        "lidarmap_uncertainty": _num(element.uncertainty),
        "lidarmap_depth": _num(depth),
        "lidarmap_depth_sigma": _num(sigma),
        "lidarmap_layer_id": None if element.layer_id is None else int(element.layer_id),
        "lidarmap_n_points": int(element.n_points),
        "lidarmap_campaigns": [int(c) for c in element.campaigns],
    }


def _rounded(xyz: np.ndarray) -> list[list[float]]:
    return np.round(np.asarray(xyz, dtype=np.float64), 3).tolist()


def _unknown_region(facade: Facade, element: Element, depth: float) -> dict[str, Any] | None:
    """An unknown region as a WallSurface attribute: its outline(s) in CRS at the wall's depth, ε = ∞ as null."""
    parts = _parts(shapely.make_valid(element.polygon)) if element.polygon is not None else []
    if not parts:
        return None
    outlines = []
    for part in parts:
        rings = _facade_rings(facade, part, depth)
        outlines.append({"exterior": _rounded(rings[0][:-1]), "holes": [_rounded(r[:-1]) for r in rings[1:]]})
    return {
        "element_id": int(element.element_id),
        "kind": ElementKind(element.kind).value,
        "uncertainty": None,
        "area": float(sum(p.area for p in parts)),
        "n_points": int(element.n_points),
        "campaigns": [int(c) for c in element.campaigns],
        "outlines": outlines,
    }


def _wall_semantic(facade: Facade, main_depth: float, unknown: list[dict[str, Any]]) -> dict[str, Any]:
    frame = facade.frame
    return {
        "type": "WallSurface",
        "lidarmap_kind": "facade",
        "lidarmap_facade_id": int(facade.facade_id),
        "lidarmap_depth": _num(main_depth),
        "lidarmap_depth_sigma": _num(facade.sigma),
        "lidarmap_n_points": int(facade.n_points),
        "lidarmap_campaigns": [int(c) for c in facade.campaigns],
        "lidarmap_footprint_edge": None if facade.footprint_edge is None else int(facade.footprint_edge),
        "lidarmap_frame": {"origin": [float(x) for x in frame.origin], "u": [float(x) for x in frame.u],
                           "normal": [float(x) for x in frame.normal]},
        "lidarmap_extent": [_num(x) for x in facade.extent],
        "lidarmap_layers": [{"layer_id": int(la.layer_id), "mu": _num(la.mu), "sigma": _num(la.sigma),
                             "weight": _num(la.weight), "n_points": int(la.n_points),
                             "main": la.layer_id == facade.main_layer} for la in facade.layers],
        "lidarmap_unknown_regions": unknown,
    }


def _is_opening(element: Element) -> bool:
    return element.kind in (ElementKind.WINDOW, ElementKind.DOOR) and not element.is_unknown


def _has_elements(building: Building) -> bool:
    """Whether the building has openings or structures: what LoD 3 shows and LoD 2 does not."""
    return any(not e.is_unknown for f in building.facades for e in f.elements)


def _add_facade(surfaces: _Surfaces, facade: Facade, lod3: bool = True) -> None:
    """The façade's WallSurface (at LoD 3: openings cut out, its Window/Door children, structures); unknown regions
    as attributes."""
    s0, s1, t0, t1 = (float(x) for x in facade.extent)
    main = facade.layer(facade.main_layer)
    main_depth = float(main.mu) if main is not None else 0.0
    extent = box(min(s0, s1), min(t0, t1), max(s0, s1), max(t0, t1))
    if not extent.area > 0:
        return
    elements = [(e, _parts(shapely.make_valid(e.polygon)) if e.polygon is not None else []) for e in facade.elements]
    if not lod3:  # LoD 2: the plain wall; openings and structures belong to LoD 3
        elements = [(e, parts) for e, parts in elements if e.is_unknown]
    openings = [p for e, parts in elements if _is_opening(e) for p in parts]
    wall_parts = [extent]
    if openings:
        try:
            wall_parts = _parts(extent.difference(shapely.union_all(openings))) or [extent]
        except shapely.errors.GEOSException:  # keep the plain wall when GEOS cannot cut the openings
            wall_parts = [extent]
    unknown = [u for e, _ in elements if e.is_unknown for u in [_unknown_region(facade, e, main_depth)] if u]
    wall = surfaces.add([_facade_rings(facade, p, main_depth) for p in wall_parts],
                        _wall_semantic(facade, main_depth, unknown))
    children: list[int] = []
    for element, parts in elements:
        if element.is_unknown or not parts:
            continue
        depth, sigma = _element_depth(facade, element, main_depth)
        if _is_opening(element) and wall is not None:
            kind = "Window" if element.kind is ElementKind.WINDOW else "Door"
            semantic = {**_element_semantic(kind, facade, element, depth, sigma), "parent": wall}
        else:  # structures (and openings of a degenerate wall) are wall parts of their own
            semantic = _element_semantic("WallSurface", facade, element, depth, sigma)
        index = surfaces.add([_facade_rings(facade, p, depth) for p in parts], semantic)
        if index is not None and "parent" in semantic:
            children.append(index)
    if children:
        surfaces.semantics[wall]["children"] = children


def _roof_rings(part: Polygon, normal: np.ndarray, offset: float) -> list[np.ndarray]:
    """An xy outline lifted onto the plane n . x + offset = 0 (counter-clockwise from above: normal up)."""
    part = orient(part, 1.0)
    rings = []
    for ring in [part.exterior, *part.interiors]:
        xy = np.asarray(ring.coords, dtype=np.float64)[:, :2]
        z = -(normal[0] * xy[:, 0] + normal[1] * xy[:, 1] + offset) / normal[2]
        rings.append(np.column_stack([xy, z]))
    return rings


def _add_roofs(surfaces: _Surfaces, building: Building) -> None:
    for roof in building.roofs:
        n = np.asarray(roof.normal, dtype=np.float64).reshape(3)
        if not abs(n[2]) >= 1e-6:
            continue  # a vertical "roof" plane has no z over its outline
        surfaces.add([_roof_rings(p, n, float(roof.offset)) for p in _parts(roof.outline)], {
            "type": "RoofSurface",
            "lidarmap_plane_id": int(roof.plane_id),
            "lidarmap_depth_sigma": _num(roof.sigma),
            "lidarmap_n_points": int(roof.n_points),
            "lidarmap_campaigns": [int(c) for c in roof.campaigns],
        })


def _number_attribute(attributes: dict, names: tuple[str, ...]) -> float | None:
    for name in names:
        value = attributes.get(name)
        if isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and math.isfinite(float(value)):
            return float(value)
    return None


def _block_shell(v: _Vertices, polygon: Polygon, base: float, top: float) -> tuple[list, list[int]]:
    """Surfaces (boundaries) and semantic values (0 ground, 1 roof, 2 wall) of an extruded footprint polygon."""
    polygon = orient(polygon, 1.0)
    rings = [np.asarray(r.coords, dtype=np.float64)[:, :2] for r in [polygon.exterior, *polygon.interiors]]
    surfaces, values = [], []
    ground = v.polygons([np.column_stack([r[::-1], np.full(len(r), base)]) for r in rings])  # clockwise: down
    roof = v.polygons([np.column_stack([r, np.full(len(r), top)]) for r in rings])
    for kind, polygons in ((0, ground), (1, roof)):
        surfaces.extend(polygons)
        values.extend([kind] * len(polygons))
    for ring in rings:
        for a, b in zip(ring[:-1], ring[1:]):
            quads = v.polygons([np.array([[a[0], a[1], base], [b[0], b[1], base], [b[0], b[1], top],
                                          [a[0], a[1], top]])])
            surfaces.extend(quads)
            values.extend([2] * len(quads))
    return surfaces, values


def _lod1(v: _Vertices, building: Building) -> dict[str, Any] | None:
    """The LoD1 block (or LoD0 footprint without a height) of a building without façades or roofs."""
    attrs = building.attributes or {}
    height = _number_attribute(attrs, HEIGHT_ATTRIBUTES)
    base = _number_attribute(attrs, GROUND_ATTRIBUTES) or 0.0
    parts = _parts(building.footprint)
    if not parts:
        return None
    if height is None or height <= 0:
        boundaries = []
        for part in parts:
            part = orient(part, 1.0)
            boundaries.extend(v.polygons([np.column_stack([np.asarray(r.coords)[:, :2], np.full(len(r.coords), base)])
                                          for r in [part.exterior, *part.interiors]]))
        return {"type": "MultiSurface", "lod": "0", "boundaries": boundaries} if boundaries else None
    semantics = [{"type": "GroundSurface"}, {"type": "RoofSurface"}, {"type": "WallSurface"}]
    shells = [_block_shell(v, part, base, base + height) for part in parts]
    if len(shells) == 1:
        surfaces, values = shells[0]
        return {"type": "Solid", "lod": "1", "boundaries": [surfaces],
                "semantics": {"surfaces": semantics, "values": [values]}}
    surfaces = [s for shell in shells for s in shell[0]]
    values = [x for shell in shells for x in shell[1]]
    return {"type": "MultiSurface", "lod": "1", "boundaries": surfaces,
            "semantics": {"surfaces": semantics, "values": values}}


def _metadata(vertices: _Vertices, crs_wkt: str, title: str) -> dict[str, Any]:
    metadata: dict[str, Any] = {"title": title}
    ref = reference_system(crs_wkt)
    if ref is not None:
        metadata["referenceSystem"] = ref
    if vertices.list:
        q = np.asarray(vertices.list, dtype=np.float64) * vertices.scale + vertices.translate
        lo, hi = q.min(axis=0), q.max(axis=0)
        metadata["geographicalExtent"] = [float(x) for x in (*lo, *hi)]
    return metadata


def _document(vertices: _Vertices, objects: dict[str, Any], metadata: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "CityJSON",
        "version": CITYJSON_VERSION,
        "transform": {"scale": [float(vertices.scale)] * 3, "translate": [float(x) for x in vertices.translate]},
        "metadata": metadata,
        "CityObjects": objects,
        "vertices": vertices.list,
    }


def _extent_points(building_map: BuildingMap) -> np.ndarray:
    """Sample coordinates of everything exported (to choose the translate)."""
    pts = []
    for b in building_map.buildings.values():
        if b.footprint is not None and not b.footprint.is_empty:
            xy = shapely.get_coordinates(b.footprint)
            pts.append(np.column_stack([xy, np.zeros(len(xy))]))
        for f in b.facades:
            pts.append(np.asarray(f.frame.origin, dtype=np.float64).reshape(1, 3))
    return np.vstack(pts) if pts else np.zeros((0, 3))


def map_to_cityjson(building_map: BuildingMap, scale: float = SCALE, title: str | None = None) -> dict[str, Any]:
    """A CityJSON 2.0 document (a dict ready for ``json.dumps``) of the map; see the module docstring."""
    pts = _extent_points(building_map)
    translate = np.floor(pts.min(axis=0)) if len(pts) else np.zeros(3)
    vertices = _Vertices(translate, float(scale))
    objects: dict[str, Any] = {}
    for bid, building in building_map.buildings.items():
        attributes = _json_safe(dict(building.attributes or {}))
        counts = count_buildings([building])
        attributes.update({f"lidarmap_{key}": counts[key] for key in COUNT_KEYS if key != "buildings"})
        attributes["lidarmap_campaigns"] = sorted({int(c) for f in building.facades for c in f.campaigns}
                                                  | {int(c) for r in building.roofs for c in r.campaigns})
        geometry: list[dict[str, Any]] = []
        if building.facades or building.roofs:
            for lod in ("3", "2") if _has_elements(building) else ("2",):
                surfaces = _Surfaces(vertices)
                for facade in building.facades:
                    _add_facade(surfaces, facade, lod3=lod == "3")
                _add_roofs(surfaces, building)
                geom = surfaces.geometry(lod)
                if geom is not None:
                    geometry.append(geom)
        if not geometry:
            geom = _lod1(vertices, building)
            if geom is not None:
                geometry.append(geom)
        obj: dict[str, Any] = {"type": "Building", "attributes": attributes}
        if geometry:
            obj["geometry"] = geometry
        objects[str(bid)] = obj
    metadata = _metadata(vertices, building_map.crs_wkt, title or "lidarmap building map")
    if building_map.campaigns:
        date = str(building_map.campaigns[-1].created)[:10]
        if len(date) == 10 and date[4] == "-" and date[7] == "-":
            metadata["referenceDate"] = date
    return _document(vertices, objects, metadata)


# ----------------------------------------------------------------------------------------------------------------------
# Buildings of the aerial pipeline (lidarmap run)


@dataclasses.dataclass
class AerialBuilding:
    """One building reconstructed by the aerial pipeline: footprint, ground height and height (m, from prep), its
    closed mesh (CRS vertices (V, 3) float64, triangles (F, 3), outward normals) and attributes."""

    id: str
    footprint: Any
    ground_z: float
    height: float
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    attributes: dict[str, Any]


#: Semantic surface types of the LoD 2.2 solid, in the order of its ``semantics.surfaces``.
SOLID_SEMANTICS = ("GroundSurface", "RoofSurface", "WallSurface")


def _mesh_solid(v: _Vertices, vertices: np.ndarray, faces: np.ndarray,
                params: PlanarParams = PlanarParams()) -> dict[str, Any] | None:
    """The closed mesh as an LoD 2.2 ``Solid`` of planar faces (:func:`lidarmap.export.planar.planar_faces`), one
    semantic surface per face (Roof/Wall/GroundSurface by its normal, ``lidarmap_planarity``: the largest distance
    of a vertex of its polygons to that polygon's plane, m, at most ``params.tolerance`` when snapping); a face
    split into planar triangles (or polygons) lists them all under its one semantic surface."""
    boundaries, semantics, values = [], [], []
    for face in planar_faces(vertices, faces, params):
        polygons = [p for rings in face.polygons for p in v.polygons(rings)]
        if not polygons:  # nothing left at the millimetre quantum
            continue
        semantics.append({"type": face.kind, "lidarmap_planarity": round(face.planarity, 3)})
        boundaries.extend(polygons)
        values.extend([len(semantics) - 1] * len(polygons))
    if not boundaries:
        return None
    return {"type": "Solid", "lod": "2.2", "boundaries": [boundaries],
            "semantics": {"surfaces": semantics, "values": [values]}}


def _aerial_object(vertices: _Vertices, b: AerialBuilding, planar: PlanarParams = PlanarParams()) -> dict[str, Any]:
    """One aerial building: an LoD1 block (footprint extruded from its ground height by its height) and the
    reconstructed mesh as an LoD2.2 solid, attributes kept."""
    geometry = []
    if math.isfinite(b.ground_z) and math.isfinite(b.height) and b.height > 0:
        block = _lod1(vertices, Building(building_id=b.id, footprint=b.footprint,
                                         attributes={"height": b.height, "ground_z": b.ground_z}))
        if block is not None:
            geometry.append(block)
    solid = _mesh_solid(vertices, np.asarray(b.mesh_vertices, np.float64), np.asarray(b.mesh_faces, np.int64),
                        planar)
    if solid is not None:
        geometry.append(solid)
    obj: dict[str, Any] = {"type": "Building", "attributes": _json_safe({**b.attributes, "measuredHeight": b.height})}
    if geometry:
        obj["geometry"] = geometry
    return obj


def _dump(value: Any) -> str:
    return json.dumps(value, ensure_ascii=False, allow_nan=False, separators=(",", ":"))


def _remap(boundaries: Any, new_index: np.ndarray) -> Any:
    """Nested boundary lists with every vertex index replaced by ``new_index[index]``."""
    if boundaries and isinstance(boundaries[0], int):
        return new_index[np.asarray(boundaries, dtype=np.int64)].tolist()
    return [_remap(part, new_index) for part in boundaries]


def write_aerial_cityjson(path: str | Path, buildings: Iterable[AerialBuilding], crs_wkt: str,
                          translate: Sequence[float], scale: float = SCALE,
                          title: str = "lidarmap aerial reconstruction", planar: PlanarParams = PlanarParams()
                          ) -> Path:
    """Stream the aerial pipeline's buildings into a CityJSON 2.0 file with bounded memory (a city of thousands of
    buildings would not fit as one document of Python objects).

    Pass 1 builds one building at a time and spills its object (JSON lines) and its quantised vertices (int64) to
    side files. Then the vertices shared between buildings (neighbouring row houses) are merged with numpy (first
    occurrence order) and pass 2 writes the objects with their indices remapped, then the vertices. Memory: one
    building plus 8 bytes x 4 per vertex of the city. ``translate`` (the transform, CRS units) is given up front,
    e.g. the buildings' minimum corner. Written atomically.
    """
    translate = np.asarray(translate, dtype=np.float64)
    head = {"type": "CityJSON", "version": CITYJSON_VERSION,
            "transform": {"scale": [float(scale)] * 3, "translate": [float(x) for x in translate]}}
    with tempfile.TemporaryFile("w+", encoding="utf-8") as objects, tempfile.TemporaryFile("w+b") as raw:
        count = 0
        for b in buildings:
            vertices = _Vertices(translate, float(scale), base=count)
            objects.write(_dump([str(b.id), _aerial_object(vertices, b, planar)]) + "\n")
            if vertices.list:
                raw.write(np.asarray(vertices.list, dtype=np.int64).tobytes())
                count += len(vertices.list)
        raw.seek(0)
        quantised = np.frombuffer(raw.read(), dtype=np.int64).reshape(-1, 3)
        unique, first, inverse = np.unique(quantised, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first, kind="stable")  # keep the order of first appearance
        rank = np.empty(len(order), dtype=np.int64)
        rank[order] = np.arange(len(order))
        new_index, unique = rank[inverse.ravel()], unique[order]
        metadata: dict[str, Any] = {"title": title}
        ref = reference_system(crs_wkt)
        if ref is not None:
            metadata["referenceSystem"] = ref
        if len(unique):
            lo, hi = unique.min(axis=0) * scale + translate, unique.max(axis=0) * scale + translate
            metadata["geographicalExtent"] = [float(x) for x in (*lo, *hi)]
        objects.seek(0)
        with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as out:
            out.write(_dump({**head, "metadata": metadata})[:-1] + ',"CityObjects":{')
            for n, line in enumerate(objects):
                oid, obj = json.loads(line)
                for geometry in obj.get("geometry", []):
                    geometry["boundaries"] = _remap(geometry["boundaries"], new_index)
                out.write(("," if n else "") + _dump(oid) + ":" + _dump(obj))
            out.write('},"vertices":[')
            for start in range(0, len(unique), 100_000):
                out.write(("," if start else "") + _dump(unique[start:start + 100_000].tolist())[1:-1])
            out.write("]}")
    return Path(path)


def write_cityjson(path: str | Path, doc: dict[str, Any]) -> Path:
    """Write a CityJSON document atomically (strict JSON: NaN or infinity is an error)."""
    text = json.dumps(doc, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
    return write_text_atomic(path, text)
