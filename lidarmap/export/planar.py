"""LoD 2.2 as planar faces: a building's closed triangle mesh merged into one polygon per roof / wall / floor face.

3DBAG and roofer store one planar polygon per face; a triangle soup (one semantic surface per triangle) is the same
shape but unusable for per-face analysis (roof area and slope per face, solar potential) and 10-20x larger.

Region growing over the mesh's triangles (adjacent = sharing an edge):

1. seed: the largest triangle not in a face yet; its plane (normal, point) is the face's plane;
2. grow: add neighbouring triangles whose normal is within ``angle`` degrees of the plane's and whose three vertices
   lie within ``distance`` m of it (the 0.15 m default is what the surface mesh's height field puts between points of
   one roof plane after flattening, see docs/voxel_mesh.md);
3. faces smaller than ``min_area`` m² (step edges, chimney stubs), and faces whose normal is within ``angle`` of an
   adjacent face's (one plane split by the noise of the seeds), join the adjacent face whose plane is within
   ``merge_distance`` m of all their vertices, the one with most shared edges first;
4. each face's polygon is the union of its triangles projected onto the face's plane (``shapely.coverage_union``:
   holes kept, e.g. a roof around a dormer), with the mesh's own vertices (not projected), so neighbouring faces
   share their edges exactly and the solid stays closed.

Semantics per face by its area-weighted normal: RoofSurface above ``ROOF_NZ``, GroundSurface below ``-ROOF_NZ``,
WallSurface otherwise. The mesh (and hence Chamfer distance, volume) does not change: only its representation.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np
import shapely
import trimesh

from lidarmap.config import check_params

__all__ = ["ROOF_NZ", "PlanarFace", "PlanarParams", "face_kind", "planar_faces"]

#: A face whose unit normal has a z component above this is roof, below minus this ground, else wall.
ROOF_NZ = 0.3


@dataclasses.dataclass(frozen=True)
class PlanarParams:
    """``[lod22]``: merging mesh triangles into planar faces (the LoD 2.2 solids of ``buildings.city.json``).

    angle (10.0): a triangle joins a face when its normal is within this angle (degrees) of the face's plane normal.
    distance (0.15): ... and its vertices lie within this distance (m) of the face's plane.
    min_area (1.0): faces smaller than this (m²), and larger faces whose normal is within ``angle`` of an adjacent
        face's, are merged into that face ...
    merge_distance (0.3): ... when its plane is within this distance (m) of all their vertices.
    """

    section = "lod22"
    constraints: ClassVar[dict[str, str]] = {"angle": "(0, 90)", "distance": ">= 0", "min_area": ">= 0",
                                             "merge_distance": ">= 0"}

    angle: float = 10.0
    distance: float = 0.15
    min_area: float = 1.0
    merge_distance: float = 0.3

    def __post_init__(self) -> None:
        check_params(self)


@dataclasses.dataclass
class PlanarFace:
    """One face: its triangles (indices into the mesh's faces), plane (unit normal, a point), semantic kind, area
    (m²), the polygons (exterior then holes, (n, 3) CRS coordinates of mesh vertices) and ``planarity``: the largest
    distance (m) of those vertices to the plane."""

    triangles: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    kind: str
    area: float
    polygons: list[list[np.ndarray]]
    planarity: float


def face_kind(nz: float) -> str:
    """RoofSurface / GroundSurface / WallSurface for a unit normal's z component."""
    return "RoofSurface" if nz > ROOF_NZ else "GroundSurface" if nz < -ROOF_NZ else "WallSurface"


def _neighbours(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Triangle adjacency (sharing an edge) as CSR arrays: the neighbours of t are ``indices[indptr[t]:indptr[t+1]]``."""
    pairs = mesh.face_adjacency
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    return np.searchsorted(both[:, 0], np.arange(len(mesh.faces) + 1)), both[:, 1]


def _region(seed: int, n: np.ndarray, p: np.ndarray, free: np.ndarray, tri: np.ndarray, normals: np.ndarray,
            adjacency: tuple[np.ndarray, np.ndarray], cos_max: float, distance: float) -> np.ndarray:
    """The triangles reachable from ``seed`` through free triangles that fit the plane (n, p); breadth first, one
    ring of neighbours per numpy step."""
    indptr, indices = adjacency
    taken = np.zeros(len(tri), dtype=bool)
    taken[seed] = True
    frontier = np.array([seed])
    while len(frontier):
        counts = indptr[frontier + 1] - indptr[frontier]
        offsets = np.repeat(indptr[frontier] - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
        cand = np.unique(indices[offsets])
        cand = cand[~taken[cand] & free[cand]]
        fits = (normals[cand] @ n >= cos_max) & (np.abs((tri[cand] - p) @ n).max(axis=1) <= distance)
        frontier = cand[fits]
        taken[frontier] = True
    return np.flatnonzero(taken)


def _fit(members: np.ndarray, tri: np.ndarray, normals: np.ndarray, areas: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted normal (unit) and centroid of triangles."""
    w = areas[members][:, None]
    n = (normals[members] * w).sum(axis=0)
    length = np.linalg.norm(n)
    n = n / length if length > 1e-12 else normals[members[0]]
    return n, (tri[members].mean(axis=1) * w).sum(axis=0) / max(float(w.sum()), 1e-12)


#: Region growing passes per face: the seed triangle's plane is noisy (a 2 cm error over a 0.5 m triangle tilts it
#: by ~3°, 0.6 m over 12 m), so the region is grown again from the seed with the plane fitted to the last pass.
GROW_PASSES = 3


def _grow(tri: np.ndarray, normals: np.ndarray, areas: np.ndarray, adjacency: tuple[np.ndarray, np.ndarray],
          params: PlanarParams) -> np.ndarray:
    """Face label of every triangle (region growing from the largest unassigned triangle, plane refitted)."""
    label = np.full(len(tri), -1, dtype=np.int64)
    cos_max = np.cos(np.radians(params.angle))
    n_faces = 0
    for seed in np.argsort(-areas, kind="stable"):
        if label[seed] >= 0:
            continue
        free = label < 0
        n, p = normals[seed], tri[seed].mean(axis=0)
        members = np.array([seed])
        for _ in range(GROW_PASSES):
            grown = _region(seed, n, p, free, tri, normals, adjacency, cos_max, params.distance)
            settled = len(grown) == len(members) and len(grown) > 1
            members = grown
            if settled or len(grown) < 3:  # a few triangles' fit is no better than the seed's
                break
            n, p = _fit(members, tri, normals, areas)
        label[members] = n_faces
        n_faces += 1
    return label


def _merge_small(label: np.ndarray, tri: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 pairs: np.ndarray, params: PlanarParams) -> np.ndarray:
    """Faces joined to an adjacent face (most shared edges first) whose plane is within ``merge_distance`` of all
    their vertices, when they are under ``min_area`` or their normals agree within ``angle`` (one plane that growing
    split: noise around a seed); smallest faces first, one pass."""
    n_faces = int(label.max()) + 1
    face_area = np.bincount(label, weights=areas, minlength=n_faces)
    planes = _planes(label, normals, areas, tri, n_faces)
    a, b = label[pairs[:, 0]], label[pairs[:, 1]]
    cross = a != b
    edges = np.concatenate([np.column_stack([a[cross], b[cross]]), np.column_stack([b[cross], a[cross]])])
    target = np.arange(n_faces)
    cos_max = np.cos(np.radians(params.angle))
    edges = edges[np.argsort(edges[:, 0], kind="stable")]
    edge_start = np.searchsorted(edges[:, 0], np.arange(n_faces + 1))
    by_face = np.argsort(label, kind="stable")
    tri_start = np.searchsorted(label[by_face], np.arange(n_faces + 1))
    for face in np.argsort(face_area, kind="stable"):
        small = face_area[face] < params.min_area
        others, counts = np.unique(target[edges[edge_start[face]:edge_start[face + 1], 1]], return_counts=True)
        corners = tri[by_face[tri_start[face]:tri_start[face + 1]]].reshape(-1, 3)
        for other in others[np.argsort(-counts, kind="stable")]:
            if other == target[face]:
                continue
            n, p = planes[other]
            if not small and planes[face][0] @ n < cos_max:
                continue
            if np.max(np.abs((corners - p) @ n)) <= params.merge_distance:
                target[target == face] = other
                break
    return np.unique(target[label], return_inverse=True)[1].reshape(-1)


#: Rounds of merging (each with the planes refitted); merging stops earlier when a round merges nothing.
MERGE_ROUNDS = 4


def _planes(label: np.ndarray, normals: np.ndarray, areas: np.ndarray, tri: np.ndarray,
            n_faces: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per face: area-weighted mean normal (unit) and area-weighted centroid."""
    weighted = np.zeros((n_faces, 3))
    np.add.at(weighted, label, normals * areas[:, None])
    centre = np.zeros((n_faces, 3))
    np.add.at(centre, label, tri.mean(axis=1) * areas[:, None])
    total = np.maximum(np.bincount(label, weights=areas, minlength=n_faces), 1e-12)
    out = []
    for k in range(n_faces):
        n = weighted[k]
        length = np.linalg.norm(n)
        out.append((n / length if length > 1e-12 else np.array([0.0, 0.0, 1.0]), centre[k] / total[k]))
    return out


def _face_polygons(vertices: np.ndarray, faces: np.ndarray, normal: np.ndarray, point: np.ndarray
                   ) -> list[list[np.ndarray]]:
    """The union of the triangles in the plane's 2D frame, mapped back to the mesh's 3D vertices."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    used = np.unique(faces)
    st = np.column_stack([(vertices[used] - point) @ u, (vertices[used] - point) @ v])
    lookup = {(float(s), float(t)): vertices[i] for (s, t), i in zip(st.tolist(), used.tolist())}
    local = np.searchsorted(used, faces)
    triangles = shapely.polygons(st[local])
    try:
        union = shapely.coverage_union_all(triangles)
        valid = union.is_valid
    except shapely.errors.GEOSException:
        valid = False
    if not valid:  # triangles overlapping or touching mid-edge in projection: the general (slower) union
        union = shapely.make_valid(shapely.union_all(triangles))
    out = []
    for part in getattr(union, "geoms", [union]):
        if not isinstance(part, shapely.Polygon) or part.is_empty:
            continue
        part = shapely.geometry.polygon.orient(part, 1.0)  # counter-clockwise around the normal: outward
        rings = []
        for ring in [part.exterior, *part.interiors]:
            coords = np.asarray(ring.coords)[:-1]
            rings.append(np.array([lookup.get((float(s), float(t)), point + s * u + t * v) for s, t in coords]))
        out.append(rings)
    return out


def planar_faces(vertices: np.ndarray, faces: np.ndarray, params: PlanarParams = PlanarParams()
                 ) -> list[PlanarFace]:
    """The mesh's planar faces (see the module docstring), largest first."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(faces):
        return []
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cross, axis=1)
    areas = length / 2
    normals = cross / np.maximum(length, 1e-12)[:, None]
    keep = areas > 0
    label = _grow(tri, normals, areas, _neighbours(mesh), params)
    for _ in range(MERGE_ROUNDS):  # planes refitted after each round: a merge can bring a face within reach
        merged = _merge_small(label, tri, normals, areas, mesh.face_adjacency, params)
        if merged.max() == label.max():
            break
        label = merged
    n_faces = int(label.max()) + 1
    planes = _planes(label, normals, areas, tri, n_faces)
    out = []
    for k in np.argsort(-np.bincount(label, weights=areas, minlength=n_faces), kind="stable"):
        members = np.flatnonzero((label == k) & keep)
        if not len(members):
            continue
        n, p = planes[k]
        polygons = _face_polygons(vertices, faces[members], n, p)
        if not polygons:
            continue
        corners = np.concatenate([r for poly in polygons for r in poly])
        out.append(PlanarFace(triangles=members, normal=n, point=p, kind=face_kind(float(n[2])),
                              area=float(areas[members].sum()), polygons=polygons,
                              planarity=float(np.max(np.abs((corners - p) @ n)))))
    return out
