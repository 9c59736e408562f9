"""Buildings as glTF 2.0 binary (``.glb``): the aerial run's meshes and the façade map, for viewers.

Layout of the scene (docs/viewer.md has the full table)::

    lidarmap_crs_to_yup          rotation: CRS z-up (x east, y north) -> glTF y-up (x, z, -y)
      lidarmap_origin            translation = the CRS offset (float64 in the JSON), also in asset.extras
        <building id>            one node per building; extras = its attributes (heights, coverage, windows, ε, ...)
          <building id>/roof     one mesh per surface kind: roof, wall, ground, window, door, unknown
          ...

Vertex positions are float32 *relative to the origin* (the centre of the buildings' bounds, rounded to the metre),
so a city a few kilometres across keeps sub-millimetre steps (float32 in CRS coordinates: 1-8 mm in RD, up to
half a metre in UTM northings). Materials are shared by kind; window (and door) triangles carry vertex colours
from their uncertainty ε (green ε = 0 -> red ε >= :data:`EPSILON_FULL`). Unknown regions of a façade (ε = ∞) are
drawn :data:`UNKNOWN_OFFSET` in front of their wall, translucent.

The writer takes plain arrays (:class:`GlbBuilding`); :func:`aerial_glb_building` and :func:`map_glb_buildings` make
them from the aerial pipeline's buildings and from the map's CityJSON document (one mapping of the map to surfaces,
see :mod:`lidarmap.export.cityjson`). Packing and buffers are trimesh's.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from trimesh.exchange.gltf import export_glb

from lidarmap.export.cityjson import (
    AerialBuilding,
    _json_safe,
    map_to_cityjson,
)
from lidarmap.export.planar import ROOF_NZ
from lidarmap.io.atomic import write_bytes_atomic

__all__ = ["EPSILON_FULL", "KINDS", "ORIGIN_NODE", "ROOT_NODE", "UNKNOWN_OFFSET", "GlbBuilding", "aerial_glb_building",
           "epsilon_colours", "glb_building_ids", "glb_bytes", "map_glb_buildings", "map_to_glb",
           "planar_faces_mesh", "read_glb_json", "triangulate_rings", "write_glb"]

#: Surface kinds, one mesh (and one material) each.
KINDS = ("roof", "wall", "ground", "window", "door", "unknown")
#: RGBA (0-1) of each kind's material; windows and doors are multiplied by their ε vertex colours.
KIND_COLOURS = {
    "roof": (0.72, 0.33, 0.25, 1.0),
    "wall": (0.86, 0.84, 0.80, 1.0),
    "ground": (0.35, 0.35, 0.35, 1.0),
    "window": (1.0, 1.0, 1.0, 1.0),
    "door": (0.85, 0.75, 0.6, 1.0),
    "unknown": (0.85, 0.2, 0.85, 0.55),
}
#: ε at and above which a window is drawn fully red (ε_w of eq. 3 lies in [0, 1]; the façade stage rejects > 0.5).
EPSILON_FULL = 0.5
#: Unknown regions are drawn this far (m) in front of their wall so that they do not z-fight with it.
UNKNOWN_OFFSET = 0.02
#: Names of the two transform nodes above the buildings.
ROOT_NODE, ORIGIN_NODE = "lidarmap_crs_to_yup", "lidarmap_origin"
#: CRS (x east, y north, z up) to glTF (y up): x -> x, z -> y, y -> -z (a proper rotation, -90° about x).
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


@dataclasses.dataclass
class GlbBuilding:
    """One building for the glb: per kind CRS vertices (V, 3) float64, triangles (F, 3) and optional RGBA vertex
    colours (V, 4) uint8; attributes (JSON-able) become the node's extras."""

    id: str
    parts: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]]
    attributes: dict[str, Any]


def epsilon_colours(epsilon: np.ndarray) -> np.ndarray:
    """RGBA uint8 per ε: green (0) -> yellow -> red (>= :data:`EPSILON_FULL`); grey for ε unknown (NaN/∞)."""
    eps = np.asarray(epsilon, dtype=np.float64)
    t = np.clip(np.nan_to_num(eps, nan=0.0, posinf=0.0) / EPSILON_FULL, 0.0, 1.0)
    red = np.clip(2 * t, 0, 1)
    green = np.clip(2 - 2 * t, 0, 1)
    rgba = np.column_stack([red, green, np.full_like(t, 0.1), np.ones_like(t)])
    rgba[~np.isfinite(eps)] = (0.5, 0.5, 0.5, 1.0)
    return np.rint(rgba * 255).astype(np.uint8)


def _origin(buildings: list[GlbBuilding]) -> np.ndarray:
    """Centre of every vertex's bounds, rounded to the metre (zeros without vertices)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for b in buildings:
        for vertices, _, _ in b.parts.values():
            if len(vertices):
                lo = np.minimum(lo, vertices.min(axis=0))
                hi = np.maximum(hi, vertices.max(axis=0))
    return np.round((lo + hi) / 2) if np.all(np.isfinite(lo)) else np.zeros(3)


def _material(kind: str) -> dict[str, Any]:
    rgba = KIND_COLOURS[kind]
    material: dict[str, Any] = {"name": kind, "doubleSided": True,
                                "pbrMetallicRoughness": {"baseColorFactor": list(rgba), "metallicFactor": 0.0,
                                                         "roughnessFactor": 0.9}}
    if rgba[3] < 1:
        material["alphaMode"] = "BLEND"
    return material


def _postprocess(extras: dict[str, Any]):
    """Set the asset extras and one shared material per kind (by mesh name ``<id>/<kind>``)."""

    def fix(tree: dict[str, Any]) -> None:
        tree["asset"]["generator"] = f"lidarmap {extras['lidarmap']} (trimesh)"
        tree["asset"]["extras"] = extras
        tree["materials"] = [_material(kind) for kind in KINDS]
        for mesh in tree.get("meshes", []):
            kind = mesh["name"].rsplit("/", 1)[-1]
            for primitive in mesh["primitives"]:
                primitive["material"] = KINDS.index(kind)

    return fix


def glb_bytes(buildings: Iterable[GlbBuilding], crs_wkt: str = "", title: str = "lidarmap buildings",
              extras: dict[str, Any] | None = None) -> bytes:
    """The glb file's bytes (see the module docstring); ``extras`` are added to the asset's extras."""
    from lidarmap._version import __version__

    buildings = list(buildings)
    origin = _origin(buildings)
    scene = trimesh.Scene()
    scene.graph.update(frame_from=scene.graph.base_frame, frame_to=ROOT_NODE, matrix=Z_UP_TO_Y_UP)
    scene.graph.update(frame_from=ROOT_NODE, frame_to=ORIGIN_NODE,
                       matrix=trimesh.transformations.translation_matrix(origin))
    for b in buildings:
        scene.graph.update(frame_from=ORIGIN_NODE, frame_to=str(b.id),
                           metadata=_json_safe({**b.attributes, "id": str(b.id)}))  # the map id wins
        for kind in KINDS:
            if kind not in b.parts:
                continue
            vertices, faces, colours = b.parts[kind]
            if not len(faces):
                continue
            mesh = trimesh.Trimesh((np.asarray(vertices, np.float64) - origin).astype(np.float32),
                                   np.asarray(faces, np.int64), process=False, validate=False)
            if colours is not None:
                mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=colours)
            name = f"{b.id}/{kind}"
            scene.add_geometry(mesh, geom_name=name, node_name=name, parent_node_name=str(b.id))
    asset_extras = {"lidarmap": __version__, "title": title, "origin": [float(x) for x in origin],
                    "crs_wkt": crs_wkt, "up": "CRS z is glTF y; node lidarmap_origin holds the CRS offset",
                    "buildings": len(buildings), **(extras or {})}
    # trimesh.exchange directly: Scene.export refuses a scene without geometry (a run whose buildings all failed)
    return export_glb(scene, include_normals=False, tree_postprocessor=_postprocess(asset_extras))


def write_glb(path: str | Path, buildings: Iterable[GlbBuilding], crs_wkt: str = "",
              title: str = "lidarmap buildings", extras: dict[str, Any] | None = None) -> Path:
    """Write the glb atomically (temp file + rename)."""
    return write_bytes_atomic(path, glb_bytes(buildings, crs_wkt, title, extras))


def read_glb_json(data: bytes) -> dict[str, Any]:
    """The JSON chunk of a glb (for tests, the viewer's CLI and benchmarks)."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError("not a glb file (no glTF magic)")
    length = struct.unpack("<I", data[12:16])[0]
    return json.loads(data[20:20 + length])


def glb_building_ids(data: bytes) -> list[str]:
    """Ids of the building nodes (children of :data:`ORIGIN_NODE`) of a glb written by :func:`write_glb`."""
    nodes = read_glb_json(data).get("nodes", [])
    origin = next((n for n in nodes if n.get("name") == ORIGIN_NODE), {})
    return [str(nodes[k].get("extras", {}).get("id", nodes[k].get("name"))) for k in origin.get("children", [])]


# ----------------------------------------------------------------------------------------------------------------------
# The aerial run's buildings


def aerial_glb_building(b: AerialBuilding, record: dict[str, Any] | None = None) -> GlbBuilding:
    """An aerial building's mesh split into roof / wall / ground triangles by normal (as in the CityJSON export)."""
    vertices = np.asarray(b.mesh_vertices, dtype=np.float64)
    faces = np.asarray(b.mesh_faces, dtype=np.int64).reshape(-1, 3)
    tri = vertices[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = normals[:, 2] / np.maximum(np.linalg.norm(normals, axis=1), 1e-12)
    kind = np.where(nz > ROOF_NZ, 0, np.where(nz < -ROOF_NZ, 2, 1))  # 0 roof, 1 wall, 2 ground
    parts = {}
    for k, name in enumerate(("roof", "wall", "ground")):
        sub = faces[kind == k]
        if len(sub):
            used = np.zeros(len(vertices), dtype=bool)
            used[sub] = True
            new_index = np.cumsum(used) - 1  # a linear-time compaction (np.unique sorts)
            parts[name] = (vertices[used], new_index[sub], None)
    attributes = {**b.attributes, "ground_z": b.ground_z, "height": b.height,
                  "roof_z_max": float(vertices[:, 2].max()) if len(vertices) else None}
    if record:
        attributes.update({k: v for k, v in record.items() if k in ("status", "coverage") and v})
    return GlbBuilding(id=str(b.id), parts=parts, attributes=attributes)


# ----------------------------------------------------------------------------------------------------------------------
# The façade map, through its CityJSON document

_SEMANTIC_KIND = {"RoofSurface": "roof", "WallSurface": "wall", "GroundSurface": "ground", "Window": "window",
                  "Door": "door"}


def _newell_normal(ring: np.ndarray) -> np.ndarray:
    """Unit normal of a ring (counter-clockwise seen from where it points)."""
    nxt = np.roll(ring, -1, axis=0)
    normal = np.array([np.sum((ring[:, 1] - nxt[:, 1]) * (ring[:, 2] + nxt[:, 2])),
                       np.sum((ring[:, 2] - nxt[:, 2]) * (ring[:, 0] + nxt[:, 0])),
                       np.sum((ring[:, 0] - nxt[:, 0]) * (ring[:, 1] + nxt[:, 1]))])
    return normal / max(np.linalg.norm(normal), 1e-12)


def _plane_axes(normal: np.ndarray) -> np.ndarray:
    """Two orthonormal axes (3, 2) of the plane with this unit normal."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = np.cross(helper, normal)
    a /= np.linalg.norm(a)
    return np.column_stack([a, np.cross(normal, a)])


def triangulate_rings(rings: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A planar 3D polygon with holes (exterior first, rings without the closing vertex) as triangles (earcut in
    the polygon's plane, wound like the exterior ring): vertices (V, 3) and faces (F, 3)."""
    import mapbox_earcut

    rings = [np.asarray(r, dtype=np.float64) for r in rings if len(r) >= 3]
    if not rings:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    vertices = np.vstack(rings)
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    normal = _newell_normal(rings[0])
    flat = (vertices - vertices[0]) @ _plane_axes(normal)
    faces = mapbox_earcut.triangulate_float64(flat, ends).astype(np.int64).reshape(-1, 3)
    tri = vertices[faces]
    backwards = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) @ normal < 0
    faces[backwards] = faces[backwards][:, ::-1]  # wound like the exterior ring: front faces look out
    return vertices, faces


def planar_faces_mesh(faces: Iterable[Any]) -> trimesh.Trimesh:
    """The polygons of :class:`lidarmap.export.planar.PlanarFace` objects as one triangle mesh (ear clipping per
    polygon; vertices not merged): what the LoD 2.2 solid looks like, for distances to other surfaces."""
    vertices, triangles, offset = [], [], 0
    for face in faces:
        for rings in face.polygons:
            v, f = triangulate_rings(rings)
            t = v[f]
            f = f[np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1) > 1e-12]  # no slivers
            vertices.append(v)
            triangles.append(f + offset)
            offset += len(v)
    if not vertices:
        return trimesh.Trimesh()
    return trimesh.Trimesh(vertices=np.vstack(vertices), faces=np.vstack(triangles), process=False)


class _Accumulator:
    """Triangles per kind of one building, concatenated at the end."""

    def __init__(self) -> None:
        self.parts: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]] = {}

    def add(self, kind: str, rings: list[np.ndarray], colour: np.ndarray | None = None) -> None:
        vertices, faces = triangulate_rings(rings)
        if len(faces):
            colours = None if colour is None else np.tile(colour, (len(vertices), 1))
            self.parts.setdefault(kind, []).append((vertices, faces, colours))

    def result(self) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        out = {}
        for kind, pieces in self.parts.items():
            offsets = np.cumsum([0] + [len(v) for v, _, _ in pieces[:-1]])
            colours = None if pieces[0][2] is None else np.vstack([c for _, _, c in pieces])
            out[kind] = (np.vstack([v for v, _, _ in pieces]),
                         np.vstack([f + o for (_, f, _), o in zip(pieces, offsets)]), colours)
        return out


def _surfaces(geometry: dict[str, Any]) -> list[tuple[list[list[int]], int | None]]:
    """(rings of vertex indices, semantic value) of every surface of a MultiSurface / Solid geometry."""
    boundaries, values = geometry["boundaries"], (geometry.get("semantics") or {}).get("values")
    if geometry["type"] == "Solid":
        shells = values if values is not None else [[None] * len(s) for s in boundaries]
        return [(surface, v) for shell, vals in zip(boundaries, shells) for surface, v in zip(shell, vals)]
    values = values if values is not None else [None] * len(boundaries)
    return list(zip(boundaries, values))


def _unknown_rings(wall: dict[str, Any]) -> list[list[np.ndarray]]:
    """Outlines of a wall's unknown regions, moved :data:`UNKNOWN_OFFSET` along the wall's outward normal."""
    normal = np.asarray((wall.get("lidarmap_frame") or {}).get("normal", [0.0, 0.0, 0.0]), dtype=np.float64)
    out = []
    for region in wall.get("lidarmap_unknown_regions") or []:
        for outline in region.get("outlines", []):
            rings = [outline["exterior"], *outline.get("holes", [])]
            out.append([np.asarray(r, dtype=np.float64) + UNKNOWN_OFFSET * normal for r in rings])
    return out


def _building_attributes(obj: dict[str, Any], epsilons: list[float]) -> dict[str, Any]:
    attributes = dict(obj.get("attributes") or {})
    finite = [e for e in epsilons if e is not None and math.isfinite(e)]
    attributes["epsilon_mean_windows"] = float(np.mean(finite)) if finite else None
    attributes["epsilon_max_windows"] = float(np.max(finite)) if finite else None
    return attributes


def _finest(geometries: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The geometry of the highest LoD (a map building has LoD 3 with openings and LoD 2 without: one is drawn)."""
    if not geometries:
        return []
    return [max(geometries, key=lambda g: float(g.get("lod", 0)))]


def map_glb_buildings(doc: dict[str, Any]) -> list[GlbBuilding]:
    """The buildings of a map's CityJSON document (:func:`lidarmap.export.cityjson.map_to_cityjson`) as glb
    buildings: the finest LoD's semantic surfaces triangulated by kind, windows/doors coloured by ε, unknown
    regions in front of their wall."""
    transform = doc.get("transform", {"scale": [1, 1, 1], "translate": [0, 0, 0]})
    xyz = np.asarray(doc["vertices"], dtype=np.float64).reshape(-1, 3) * transform["scale"] + transform["translate"]
    buildings = []
    for oid, obj in doc["CityObjects"].items():
        acc, epsilons = _Accumulator(), []
        for geometry in _finest(obj.get("geometry", [])):
            semantics = (geometry.get("semantics") or {}).get("surfaces", [])
            plain = "ground" if str(geometry.get("lod")) == "0" else "wall"  # a footprint, or a surface of no type
            for surface, value in _surfaces(geometry):
                semantic = semantics[value] if value is not None and value < len(semantics) else {}
                kind = _SEMANTIC_KIND.get(semantic.get("type"), plain)
                colour = None
                if kind in ("window", "door"):
                    eps = semantic.get("lidarmap_uncertainty")
                    epsilons.append(eps)
                    colour = epsilon_colours(np.array([np.inf if eps is None else eps]))[0]
                acc.add(kind, [xyz[np.asarray(ring, dtype=np.int64)] for ring in surface], colour)
            for semantic in semantics:
                for rings in _unknown_rings(semantic):
                    acc.add("unknown", rings)
        buildings.append(GlbBuilding(id=str(oid), parts=acc.result(), attributes=_building_attributes(obj, epsilons)))
    return buildings


def map_to_glb(building_map: Any, title: str) -> bytes:
    """A :class:`~lidarmap.map.model.BuildingMap` as glb bytes, through its CityJSON document (so both exports show
    the same surfaces); the map's campaign ids in the asset's extras."""
    doc = map_to_cityjson(building_map, title=title)
    campaigns = [c.campaign_id for c in building_map.campaigns]
    return glb_bytes(map_glb_buildings(doc), building_map.crs_wkt, title=title, extras={"campaigns": campaigns})
