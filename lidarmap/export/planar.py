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
4. each face's polygon is traced along the boundary edges of its triangles (holes kept, e.g. a roof around a
   dormer), with the mesh's own vertices, so neighbouring faces share their edges exactly and the solid stays
   closed;
5. with ``snap`` (the default), those vertices are moved onto the planes of all the faces they belong to
   (:mod:`lidarmap.export.snap`), vertices of only two faces are dropped (they lie on the straight edge between two
   corners), and a face the move leaves non-planar beyond ``tolerance`` or invalid in its plane is split into
   planar triangles: every exported polygon is planar within ``tolerance`` and the solid stays closed.

Semantics per face by its area-weighted normal: RoofSurface above ``ROOF_NZ``, GroundSurface below ``-ROOF_NZ``,
WallSurface otherwise. The mesh files do not change: only their CityJSON representation (snapping moves its
vertices, by the amounts docs/benchmarks.md measures).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np
import shapely
import trimesh

from lidarmap.config import check_params
from lidarmap.export.geomcheck import MIN_AREA, plane_basis, valid_polygons
from lidarmap.export.snap import snap_to_planes

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
    snap (true): move the faces' vertices onto their planes (:mod:`lidarmap.export.snap`: every vertex one position
        on the planes of all its faces, the solid stays closed); false: faces keep the mesh's vertices and are planar
        only within about ``distance``.
    tolerance (0.01): with ``snap``, the largest distance (m) of a face's vertex to the face's plane (val3dity's
        default planarity tolerance); a face left beyond it, or made invalid in its plane by the move, is exported
        as planar triangles (same semantic surface).
    """

    section = "lod22"
    constraints: ClassVar[dict[str, str]] = {"angle": "(0, 90)", "distance": ">= 0", "min_area": ">= 0",
                                             "merge_distance": ">= 0", "tolerance": "> 0"}

    angle: float = 10.0
    distance: float = 0.15
    min_area: float = 1.0
    merge_distance: float = 0.3
    snap: bool = True
    tolerance: float = 0.01

    def __post_init__(self) -> None:
        check_params(self)


@dataclasses.dataclass
class PlanarFace:
    """One face: its triangles (indices into the mesh's faces), plane (unit normal, a point), semantic kind, area
    (m²) of its mesh triangles, the polygons (exterior then holes, (n, 3) CRS coordinates: the mesh's vertices,
    moved onto the planes when snapping), ``planarity``: the largest distance (m) of a polygon's vertex to that
    polygon's own plane, and ``split``: whether snapping could not keep it one polygon (then its polygons are
    planar triangles)."""

    triangles: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    kind: str
    area: float
    polygons: list[list[np.ndarray]]
    planarity: float
    split: bool = False


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


def _merge_enclosed(label: np.ndarray, areas: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Faces with fewer than three neighbouring faces joined to the neighbour they share most edges with, smallest
    first, until none is left. Such a face cannot be planar with its vertices on its neighbours' planes: bounded by
    one other face (a bump of the height field inside a roof) or two (a lens between them), all its edges lie on one
    or two lines through the same corners, so snapping would flatten it to nothing."""
    while True:
        n_faces = int(label.max()) + 1
        a, b = label[pairs[:, 0]], label[pairs[:, 1]]
        cross = a != b
        edges = np.concatenate([np.column_stack([a[cross], b[cross]]), np.column_stack([b[cross], a[cross]])])
        links, shared = np.unique(edges, axis=0, return_counts=True)
        degree = np.bincount(links[:, 0], minlength=n_faces)
        few = np.flatnonzero(degree < 3)
        if not len(few) or n_faces < 4:
            return label
        face = few[np.argmin(np.bincount(label, weights=areas, minlength=n_faces)[few])]
        rows = np.flatnonzero(links[:, 0] == face)
        if not len(rows):
            return label
        label = np.where(label == face, links[rows[np.argmax(shared[rows])], 1], label)
        label = np.unique(label, return_inverse=True)[1].reshape(-1)


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


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane of a unit normal (u x v = normal)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed loops of vertex indices along the boundary of a set of consistently oriented triangles: their directed
    edges whose reverse is not one of them, chained head to tail (at a vertex the boundary passes twice, the first
    edge out that is left)."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    inner = {(int(a), int(b)) for a, b in directed}
    out_edges: dict[int, list[int]] = {}
    for a, b in directed.tolist():
        if (b, a) not in inner:
            out_edges.setdefault(a, []).append(b)
    loops = []
    for start in list(out_edges):
        while out_edges.get(start):
            loop, at = [start], out_edges[start].pop()
            while at != start and out_edges.get(at):
                loop.append(at)
                at = out_edges[at].pop()
            loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def _face_rings(vertices: np.ndarray, faces: np.ndarray, normal: np.ndarray) -> list[list[np.ndarray]]:
    """A face's polygon as rings of mesh vertex indices: its triangles' boundary loops, the one enclosing most area
    around the normal the exterior (counter-clockwise around the outward normal, as the mesh's triangles run), the
    others its holes (clockwise). Built from the mesh's edges, so neighbouring faces list the same vertices along
    their shared boundary."""
    loops = [loop for loop in _boundary_loops(faces) if len(loop) >= 3]
    if not loops:
        return []
    u, v = _plane_axes(normal)
    signed = []
    for loop in loops:
        x, y = vertices[loop] @ u, vertices[loop] @ v
        signed.append(0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))
    first = int(np.argmax(signed))
    return [[loops[first], *(loop for i, loop in enumerate(loops) if i != first)]]


#: A polygon is kept only when no vertex is closer than this (m) to a ring segment it is not on (shapely's minimum
#: clearance): the writer's millimetre rounding moves a vertex by up to 0.9 mm and must not make it invalid.
MIN_CLEARANCE = 2e-3


def _validity(polygons: list[list[np.ndarray]], normal: np.ndarray, point: np.ndarray) -> str:
    """"valid": every polygon (rings of 3D points) OGC-valid projected onto the plane, no vertex repeated, minimum
    clearance at least ``MIN_CLEARANCE``; "thin": valid, but a vertex comes closer than that to a segment it is not
    on (rounding could fold it); "invalid" otherwise."""
    u, v = _plane_axes(normal)
    state = "valid"
    for rings in polygons:
        flat = [np.column_stack([(r - point) @ u, (r - point) @ v]) for r in rings]
        if any(len(np.unique(np.round(f, 4), axis=0)) != len(f) for f in flat):
            return "invalid"
        polygon = shapely.Polygon(flat[0], flat[1:])
        if not polygon.is_valid:
            return "invalid"
        if shapely.minimum_clearance(polygon) < MIN_CLEARANCE:
            state = "thin"
    return state


def _earcut(rings: list[np.ndarray], positions: np.ndarray, normal: np.ndarray) -> list[list[np.ndarray]]:
    """A polygon (rings of vertex indices) as triangles (one-ring polygons of the same vertices) by ear clipping in
    the plane: every triangle planar, the face's area and edges kept."""
    import mapbox_earcut

    u, v = _plane_axes(normal)
    index = np.concatenate(rings)
    flat = np.column_stack([positions[index] @ u, positions[index] @ v])
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    tri = index[mapbox_earcut.triangulate_float64(flat, ends).astype(np.int64).reshape(-1, 3)]
    corners = positions[tri]
    backwards = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]) @ normal < 0
    tri[backwards] = tri[backwards][:, ::-1]  # counter-clockwise around the normal like the face: outward
    return [[t] for t in tri]


def _partition(vertices: np.ndarray, faces: np.ndarray, params: PlanarParams
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Triangle areas, normals, face label of every triangle and the faces' planes (growing, then merging)."""
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cross, axis=1)
    areas = length / 2
    normals = cross / np.maximum(length, 1e-12)[:, None]
    label = _grow(tri, normals, areas, _neighbours(mesh), params)
    for _ in range(MERGE_ROUNDS):  # planes refitted after each round: a merge can bring a face within reach
        merged = _merge_small(label, tri, normals, areas, mesh.face_adjacency, params)
        if merged.max() == label.max():
            break
        label = merged
    if params.snap:
        label = _merge_enclosed(label, areas, mesh.face_adjacency)
    return areas, normals, label, _planes(label, normals, areas, tri, int(label.max()) + 1)


def _vertex_pairs(rings: list[list[list[np.ndarray]]], faces: np.ndarray, members: list[np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(vertex, face) pairs of the faces' polygon vertices, and of their other (interior) mesh vertices."""
    ring_pairs, interior_pairs = [], []
    for k, polygons in enumerate(rings):
        on_ring = np.unique(np.concatenate([r for poly in polygons for r in poly])) if polygons else np.zeros(0, int)
        inside = np.setdiff1d(np.unique(faces[members[k]]), on_ring)
        ring_pairs.append(np.column_stack([on_ring, np.full(len(on_ring), k)]))
        interior_pairs.append(np.column_stack([inside, np.full(len(inside), k)]))
    return (np.concatenate(ring_pairs).astype(np.int64).reshape(-1, 2),
            np.concatenate(interior_pairs).astype(np.int64).reshape(-1, 2))


def _corners(ring: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The ring's ``keep`` vertices, a vertex repeated in a row once."""
    ring = ring[keep[ring]]
    return ring[ring != np.roll(ring, 1)] if len(ring) > 1 else ring


def _signed_area(rings: list[np.ndarray], basis: tuple) -> float:
    """Area (m²) of a polygon (exterior, holes; 3D points) in the plane ``basis`` (origin, u, v, normal)."""
    origin, u, v, _ = basis
    flat = [np.column_stack([(r - origin) @ u, (r - origin) @ v]) for r in rings]
    return sum(abs(shapely.Polygon(f).area) * (1 if j == 0 else -1) for j, f in enumerate(flat))


def _split_where_touching(polygons: list[list[np.ndarray]], positions: np.ndarray
                          ) -> list[list[np.ndarray]] | None:
    """Polygons whose rings pass a vertex twice (self-touching, a hole touching the shell) split there into valid
    polygons of the same vertices (:func:`lidarmap.export.geomcheck.valid_polygons`); ``None`` when the repair
    needs a new vertex (rings that cross) or loses area: those are not just touching."""
    out = []
    for poly in polygons:
        rings = [positions[r] for r in poly]
        basis = plane_basis(rings[0])
        parts = valid_polygons(rings, min_area=0.0)
        if basis is None or not parts:
            return None
        if abs(sum(_signed_area(p, basis) for p in parts) - _signed_area(rings, basis)) > 1e-6 * max(
                _signed_area(rings, basis), 1.0):
            return None
        index = {tuple(positions[i].tolist()): i for r in poly for i in r.tolist()}
        for part in parts:
            found = [[index.get(tuple(x)) for x in r.tolist()] for r in part]
            if any(i is None for r in found for i in r):
                return None
            out.append([np.asarray(r, dtype=np.int64) for r in found])
    return out


def _unfolded(triangles: np.ndarray) -> np.ndarray:
    """Mesh triangles after corners were merged: without those that lost a corner, and without pairs on the same
    three vertices in opposite orientation (a fold that the merge made: they cancel)."""
    tri = triangles[(triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                    & (triangles[:, 0] != triangles[:, 2])]
    start = np.argmin(tri, axis=1)  # rotate each triangle to start at its smallest index: orientation kept
    rotated = np.take_along_axis(tri, (start[:, None] + np.arange(3)) % 3, axis=1)
    unique = np.unique(rotated, axis=0)
    present = {tuple(t) for t in unique.tolist()}
    return np.array([t for t in unique.tolist() if (t[0], t[2], t[1]) not in present],
                    dtype=np.int64).reshape(-1, 3)


def _folded(triangles: np.ndarray) -> bool:
    """Whether some directed edge is used by two of the triangles (they overlap)."""
    directed = triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    return len(np.unique(directed, axis=0)) < len(directed)


def _earcut_all(polygons: list[list[np.ndarray]], positions: np.ndarray, normal: np.ndarray, slivers: bool = False
                ) -> list[list[np.ndarray]] | None:
    """Every polygon ear-clipped (:func:`_earcut`), ``None`` unless the triangles cover every edge of its rings once
    and (unless ``slivers``) no triangle is a sliver under ``MIN_AREA`` (collinear corners; the writer would drop
    it): ear clipping can leave out parts of a ring that nearly touches itself."""
    out = []
    for poly in polygons:
        triangles = _earcut(poly, positions, normal)
        edges = {(int(a), int(b)) for r in poly for a, b in zip(r, np.roll(r, -1))}
        inner = [(int(a), int(b)) for (t,) in triangles for a, b in zip(t, np.roll(t, -1))]
        covered = {e for e in inner if e in edges}
        rest = [e for e in inner if e not in edges]
        corners = np.array([positions[t] for (t,) in triangles]).reshape(-1, 3, 3)
        area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1) / 2
        if (covered != edges or len(inner) != len(set(inner)) or any((b, a) not in rest for a, b in rest)
                or not len(area) or (area.min() < MIN_AREA and not slivers)):
            return None
        out.extend(triangles)
    return out


def _keep_short_rings(rings: list[list[list[np.ndarray]]], keep: np.ndarray) -> None:
    """Mark every vertex of a ring that would keep fewer than three vertices as kept (in every face that has it,
    so neighbours share them: no T-junction); repeated until no ring is short."""
    while True:
        short = [r for polygons in rings for poly in polygons for r in poly if len(_corners(r, keep)) < 3
                 and not keep[r].all()]
        if not short:
            return
        for r in short:
            keep[r] = True


def _planar_pieces(rings: list[list[list[np.ndarray]]], ring_pairs: np.ndarray, members: list[np.ndarray],
                   faces: np.ndarray, positions: np.ndarray, plane_n: np.ndarray, plane_d: np.ndarray,
                   tolerance: float) -> tuple[list[list[list[np.ndarray]]], np.ndarray]:
    """Every face's polygons (rings of vertex indices) after snapping, and whether it was split.

    A vertex of two faces only lies on the line where their planes meet, between corners of three or more faces:
    both faces drop it alike and their shared edge becomes one straight segment (a ring that would keep fewer than
    three vertices keeps all, and so do its neighbours). A face left beyond ``tolerance``, invalid in its plane
    (the move folded a ring) or thin (a vertex within ``MIN_CLEARANCE`` of another part of its ring) is split into
    planar triangles: its polygon ear-clipped when that is valid, else its own mesh triangles, whose vertices then stay in the neighbouring faces' rings too (no
    T-junction); repeated until no further face needs splitting.
    """
    keep = np.bincount(ring_pairs[:, 0], minlength=len(positions)) >= 3
    split = np.zeros(len(rings), dtype=bool)
    clipped = np.zeros(len(rings), dtype=bool)
    out: list[list[list[np.ndarray]]] = []
    while True:
        _keep_short_rings([r for k, r in enumerate(rings) if not split[k]], keep)
        out, fresh = [], []
        for k, face_rings in enumerate(rings):
            if split[k]:
                out.append([[t] for t in _unfolded(faces[members[k]])])
                continue
            pieces = [[_corners(r, keep) for r in poly] for poly in face_rings]
            points = [[positions[r] for r in poly] for poly in pieces]
            if not pieces:
                out.append([])
                continue
            corners = np.concatenate([positions[r] for poly in pieces for r in poly])
            planar = np.max(np.abs(corners @ plane_n[k] - plane_d[k])) <= tolerance
            state = _validity(points, plane_n[k], plane_n[k] * plane_d[k])
            if state == "invalid":
                repaired = _split_where_touching(pieces, positions)
                if repaired is not None:
                    state = _validity([[positions[r] for r in poly] for poly in repaired], plane_n[k],
                                      plane_n[k] * plane_d[k])
                    pieces = repaired if state != "invalid" else pieces
            if planar and state == "valid":
                out.append(pieces)
            elif state != "invalid" and (clip := _earcut_all(pieces, positions, plane_n[k])) is not None:
                out.append(clip)  # non-planar or thin, but valid: ear-clipped into triangles of its corners
                clipped[k] = True
            elif (state != "invalid" and _folded(_unfolded(faces[members[k]]))
                  and (clip := _earcut_all(pieces, positions, plane_n[k], slivers=True)) is not None):
                out.append(clip)  # the mesh triangles would fold: ear-clipped with a sliver (the writer drops it)
                clipped[k] = True
            else:
                fresh.append(k)
                out.append([])
        if not fresh:
            return out, split | clipped
        split[fresh] = True
        for k in fresh:
            keep[faces[members[k]].ravel()] = True


#: Corners closer than this (m) after snapping are one point (twice the writer's millimetre quantum).
SAME_POINT = 2e-3
#: Rounds of snapping at most; each collapses the corner pairs whose edge the previous round turned around.
COLLAPSE_ROUNDS = 5


def _aliased(rings: list[list[list[np.ndarray]]], alias: np.ndarray) -> list[list[list[np.ndarray]]]:
    """The rings with every vertex replaced by its alias, repeats of the same vertex in a row removed; a ring left
    with fewer than three vertices is dropped (a face whose exterior is dropped has nothing left)."""
    out = []
    for polygons in rings:
        kept = []
        for poly in polygons:
            rings_left = []
            for r in poly:
                r = alias[r]
                r = r[r != np.roll(r, 1)] if len(r) > 1 else r
                if len(r) >= 3:
                    rings_left.append(r)
            if rings_left and len(rings_left[0]) == len(alias[poly[0]][alias[poly[0]] != np.roll(alias[poly[0]], 1)]):
                kept.append(rings_left)
        out.append(kept)
    return out


def _inverted_edges(rings: list[list[list[np.ndarray]]], keep: np.ndarray, before: np.ndarray,
                    after: np.ndarray) -> np.ndarray:
    """(a, b) pairs of consecutive corners whose edge runs the other way after snapping than before (the planes
    order those corners differently from the mesh: two corners of four planes that do not meet in a point) or
    that snapping put on the same point (two corners of the same three planes)."""
    pairs = []
    for polygons in rings:
        for poly in polygons:
            for r in poly:
                r = _corners(r, keep) if len(_corners(r, keep)) >= 3 else r
                a, b = r, np.roll(r, -1)
                turned = ((np.einsum("ij,ij->i", after[b] - after[a], before[b] - before[a]) < 0)
                          | (np.linalg.norm(after[b] - after[a], axis=1) < SAME_POINT))
                turned &= a != b
                pairs.append(np.column_stack([a[turned], b[turned]]))
    return np.concatenate(pairs).reshape(-1, 2) if pairs else np.zeros((0, 2), dtype=np.int64)


def _root(alias: np.ndarray) -> np.ndarray:
    while True:
        nxt = alias[alias]
        if np.array_equal(nxt, alias):
            return alias
        alias = nxt


def _snapped(rings: list[list[list[np.ndarray]]], faces: np.ndarray, members: list[np.ndarray],
             vertices: np.ndarray, plane_n: np.ndarray, plane_d: np.ndarray, tolerance: float):
    """Snap the faces' vertices onto their planes (:func:`lidarmap.export.snap.snap_to_planes`); where that turns
    an edge between two corners around, the two corners become one (on all their faces' planes) and the faces are
    snapped again. Returns the faces' polygons (rings of vertex indices), which faces were split into triangles,
    the vertex positions and the planes (normals, offsets)."""
    alias = np.arange(len(vertices))
    for _ in range(COLLAPSE_ROUNDS):
        current = _aliased(rings, alias)
        mapped = alias[faces]
        ring_pairs, interior_pairs = _vertex_pairs(current, mapped, members)
        snapped = snap_to_planes(vertices, ring_pairs, interior_pairs, plane_n, plane_n * plane_d[:, None],
                                 tolerance)
        keep = np.bincount(ring_pairs[:, 0], minlength=len(vertices)) >= 3
        turned = _inverted_edges(current, keep, vertices, snapped.vertices)
        if not len(turned):
            break
        low, high = turned.min(axis=1), turned.max(axis=1)
        for a, b in zip(low.tolist(), high.tolist()):  # union of the pairs, the lower index naming each group
            ra, rb = _root(alias)[[a, b]]
            alias[max(ra, rb)] = min(ra, rb)
        alias = _root(alias)
    pieces, split = _planar_pieces(current, ring_pairs, members, mapped, snapped.vertices, snapped.normals,
                                   snapped.offsets, tolerance)
    return pieces, split, snapped.vertices, snapped.normals, snapped.offsets


def planar_faces(vertices: np.ndarray, faces: np.ndarray, params: PlanarParams = PlanarParams()
                 ) -> list[PlanarFace]:
    """The mesh's planar faces (see the module docstring), largest first."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(faces):
        return []
    areas, _, label, planes = _partition(vertices, faces, params)
    order = [k for k in np.argsort(-np.bincount(label, weights=areas), kind="stable")]
    members = [np.flatnonzero((label == k) & (areas > 0)) for k in order]
    rings = [_face_rings(vertices, faces[m], planes[k][0]) if len(m) else [] for k, m in zip(order, members)]
    positions = vertices
    plane_n = np.array([planes[k][0] for k in order])
    plane_d = np.einsum("ij,ij->i", plane_n, np.array([planes[k][1] for k in order]))
    if params.snap:
        rings, split, positions, plane_n, plane_d = _snapped(rings, faces, members, positions, plane_n, plane_d,
                                                             params.tolerance)
    else:
        split = np.zeros(len(rings), dtype=bool)
    out = []
    for k, (face_rings, m) in enumerate(zip(rings, members)):
        if not face_rings:
            continue
        polygons = [[positions[r] for r in poly] for poly in face_rings]
        out.append(PlanarFace(triangles=m, normal=plane_n[k], point=plane_n[k] * plane_d[k],
                              kind=face_kind(float(plane_n[k][2])), area=float(areas[m].sum()), polygons=polygons,
                              planarity=_planarity(polygons), split=bool(split[k])))
    return out


def _planarity(polygons: list[list[np.ndarray]]) -> float:
    """The largest distance (m) of a polygon's vertex to that polygon's own plane (Newell normal through the
    vertices' mean: what val3dity's planarity test measures with a least-squares plane)."""
    worst = 0.0
    for rings in polygons:
        basis = plane_basis(rings[0])
        if basis is not None:
            origin, _, _, n = basis
            worst = max(worst, float(np.max(np.abs((np.concatenate(rings) - origin) @ n))))
    return worst
