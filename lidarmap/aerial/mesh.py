"""Meshes of buildings: a watertight mesh of the voxels and a 2.5D surface reconstruction from the points.

Stage API (arrays and small dataclasses in, ``trimesh.Trimesh`` in CRS coordinates out, no files)::

    voxel_mesh(grid, params=MeshParams()) -> Trimesh           # merged cube faces, watertight, exact lattice corners
    surface_mesh(xyz, params=MeshParams(), footprint=None, ground_z=None, rgb=None) -> Trimesh
    outline_polygon(xy, params=MeshParams()) -> shapely Polygon  # the building outline when no footprint is given

Files (written atomically, vertices as float64 so UTM coordinates keep sub-millimetre detail)::

    write_mesh(path, mesh)                 # .ply (binary, double x/y/z, colours) or .obj (text, shortest exact repr)
    write_ply_arrays(path, vertices, faces, vertex_colors=None, face_colors=None, comment=None)

**Voxel mesh.** Every voxel face that has no occupied neighbour becomes a quad (two triangles), wound
counter-clockwise seen from outside. Where two voxels touch only along an edge or at a corner, the lattice corner is
split into one vertex per sheet of surface through it (connected components of the face corners, glued across the
edges they share), so every edge belongs to exactly two triangles: the mesh is watertight and consistently oriented
(``trimesh`` ``is_volume``) for any set of voxels, and its volume is exactly ``voxels x size^3``. Vertices are
``origin + lattice corner x size`` in float64. By default the voxel shell is first filled column by column
(:func:`lidarmap.aerial.voxel.fill_columns`, ``voxel_fill = "columns"``), so the mesh is the building's outer surface and
not a two-sided shell.

**Surface mesh.** Airborne LiDAR sees roofs densely and walls sparsely, so the reconstruction is 2.5D: the roof is a
triangulated height field over the outline (heights interpolated linearly between the highest points of small
cells, which drops wall points and keeps flattened roof planes, ridges and eaves), the walls are vertical from the
outline down to the ground, and a flat floor closes the solid. Unlike Poisson-type reconstruction it needs no
normals and no wall coverage, keeps sharp eaves, and is watertight by construction; it cannot represent overhangs,
balconies or recesses (use the voxel mesh at a fine voxel size for those).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import numpy as np
import shapely
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree
from shapely import affinity
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

from lidarmap.aerial.voxel import fill_columns
from lidarmap.config import check_params
from lidarmap.core import CUBE_CORNERS, CUBE_QUADS, VoxelGrid
from lidarmap.errors import ConfigError, InputError

__all__ = ["MeshParams", "voxel_mesh", "surface_mesh", "outline_polygon"]


#: Largest bounding box (in voxels) meshed at once: the dense occupancy arrays take ~20 bytes per voxel.
_MAX_MESH_CELLS = 2 ** 28

#: Outward direction (axis, sign) of each quad of ``CUBE_QUADS``.
_QUAD_DIRECTIONS = ((2, -1), (2, 1), (1, -1), (0, 1), (1, 1), (0, -1))


@dataclasses.dataclass(frozen=True)
class MeshParams:
    """Parameters of ``lidarmap mesh`` (``[mesh]`` table of a config file).

    Voxel mesh
        voxel_fill ("columns"): "columns" fills each voxel column from the lowest voxel layer up to its highest
            voxel before meshing (:func:`lidarmap.aerial.voxel.fill_columns`: a closed 2.5D solid, the outer surface only);
            "none" meshes the voxels as they are (a shell gives a two-sided mesh, one voxel thick).
        fill_gaps (1.0): with "columns", gaps in the voxel outline up to this wide (metres) are closed and take the
            height of the nearest column (holes inside the outline are always filled).
    Surface mesh
        cell (0.5): spacing (metres) of the roof triangulation: grid nodes inside the outline and points along it.
        top_cell (0.25): the roof height field interpolates the highest point of each cell of this size (metres),
            about the point spacing ...
        max_roof_slope (60.0): ... except points that have a higher point within 1 m seen steeper than this
            (degrees): wall points under the eaves. Roofs steeper than this lose points near their ridge.
        concave_ratio (0.1): without a footprint, the outline is the concave hull of the points (``shapely``
            ``concave_hull``; 0 = most concave, 1 = convex hull).
        simplify (0.25): the outline is simplified with this tolerance (metres; 0 keeps it as is).
    """

    section = "mesh"
    constraints: ClassVar[dict[str, str]] = {
        "voxel_fill": "in columns, none",
        "fill_gaps": ">= 0",
        "cell": ">= 0",
        "top_cell": ">= 0",
        "max_roof_slope": ">= 0",
        "concave_ratio": ">= 0",
        "simplify": ">= 0",
    }

    voxel_fill: str = "columns"
    fill_gaps: float = 1.0
    cell: float = 0.5
    top_cell: float = 0.25
    max_roof_slope: float = 60.0
    concave_ratio: float = 0.1
    simplify: float = 0.25

    def __post_init__(self) -> None:
        check_params(self)
        checks = [
            (self.voxel_fill in ("columns", "none"),
             f"voxel_fill must be 'columns' or 'none', got {self.voxel_fill!r}"),
            (math.isfinite(self.fill_gaps) and self.fill_gaps >= 0, f"fill_gaps must be >= 0, got {self.fill_gaps!r}"),
            (_positive(self.cell), f"cell must be a finite number > 0, got {self.cell!r}"),
            (_positive(self.top_cell), f"top_cell must be a finite number > 0, got {self.top_cell!r}"),
            (0 < self.max_roof_slope < 90, f"max_roof_slope must be in (0, 90) degrees, got {self.max_roof_slope!r}"),
            (0.0 <= self.concave_ratio <= 1.0, f"concave_ratio must be in [0, 1], got {self.concave_ratio!r}"),
            (math.isfinite(self.simplify) and self.simplify >= 0, f"simplify must be >= 0, got {self.simplify!r}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"mesh parameters: {message}")


def _positive(value: float) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


# ----------------------------------------------------------------------------------------------------------------------
# Voxel mesh


def voxel_mesh(grid: VoxelGrid, params: MeshParams = MeshParams()) -> trimesh.Trimesh:
    """A watertight, outward-oriented triangle mesh of the voxels (CRS coordinates, voxel colours on the faces)."""
    if len(grid) == 0:
        raise InputError("no voxels to mesh")
    if params.voxel_fill == "columns":
        grid = fill_columns(grid, close_gaps=int(round(params.fill_gaps / grid.size)))
    lo = grid.ijk.min(axis=0) - 1  # one empty voxel of padding on every side
    cells = grid.ijk - lo
    dims = cells.max(axis=0) + 2
    if float(np.prod(dims.astype(np.float64))) > _MAX_MESH_CELLS:
        raise InputError(f"voxel grid too large to mesh at once ({' x '.join(map(str, dims.tolist()))} voxels): "
                         f"mesh one building at a time or use larger voxels")
    voxel_id = np.full(tuple(dims), -1, np.int32)
    voxel_id[tuple(cells.T)] = np.arange(len(cells))
    occupied = voxel_id >= 0
    quads, solid, empty = _exposed_quads(occupied)
    vertex_of, corners = _split_corners(occupied, quads, solid, empty)
    faces = np.concatenate([vertex_of[:, [0, 1, 2]], vertex_of[:, [0, 2, 3]]])
    colours = grid.colours()[voxel_id[tuple(solid.T)]]
    mesh = trimesh.Trimesh(vertices=grid.origin + (corners + lo) * grid.size, faces=faces, process=False,
                           face_colors=np.concatenate([colours, colours]))
    return mesh


def _exposed_quads(occupied: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel faces between an occupied and an empty voxel: corners (Q, 4, 3), solid voxel (Q, 3), empty voxel (Q, 3)."""
    quads, solid, empty = [], [], []
    for quad, (axis, sign) in zip(CUBE_QUADS, _QUAD_DIRECTIONS):
        neighbour = np.roll(occupied, -sign, axis=axis)  # neighbour[c] = occupied[c + sign * e_axis] (padded grid)
        cells = np.argwhere(occupied & ~neighbour)
        step = np.zeros(3, np.int64)
        step[axis] = sign
        quads.append(cells[:, None, :] + CUBE_CORNERS[quad][None])
        solid.append(cells)
        empty.append(cells + step)
    return np.concatenate(quads), np.concatenate(solid), np.concatenate(empty)


def _split_corners(occupied: np.ndarray, quads: np.ndarray, solid: np.ndarray,
                   empty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One vertex per sheet of surface through each lattice corner: (Q, 4) vertex ids and (V, 3) lattice corners.

    Each lattice edge carries 2 quads, or 4 where two voxels touch only along it (diagonal neighbours). The quads of
    an edge are paired -- the two of the same solid voxel, or, where those two voxels are joined around both ends of
    the edge, the two of the same empty voxel (else the pairing would need the same two vertices twice) -- and the
    corners of paired quads are glued; the connected components of the glued corners are the vertices.
    """
    n_quads = len(quads)
    lattice = np.array(occupied.shape) + 1
    corner_key = (quads[..., 0] * lattice[1] + quads[..., 1]) * lattice[2] + quads[..., 2]  # (Q, 4)
    start, end = corner_key, np.roll(corner_key, -1, axis=1)
    edge_key = (np.minimum(start, end) * lattice.prod() + np.maximum(start, end)).ravel()  # (4Q,) one per quad side
    _, edge_index, edge_count = np.unique(edge_key, return_inverse=True, return_counts=True)
    shared4 = edge_count[edge_index.reshape(-1)] == 4
    side_quad = np.repeat(np.arange(n_quads), 4)
    flat = np.array([occupied.shape[1] * occupied.shape[2], occupied.shape[2], 1])
    owner = np.where(shared4, solid[side_quad] @ flat, -1)
    if shared4.any():
        sides = np.flatnonzero(shared4)
        quad_of = side_quad[sides]
        by_empty = _joined_around(occupied, quads[quad_of, sides % 4], quads[quad_of, (sides + 1) % 4])
        owner[sides[by_empty]] = empty[side_quad[sides[by_empty]]] @ flat
    order = np.lexsort((owner, edge_key))
    first, second = order[0::2], order[1::2]
    if len(order) % 2 or np.any(edge_key[first] != edge_key[second]) or np.any(owner[first] != owner[second]):
        raise AssertionError("voxel mesh: unpaired quad edge")  # cannot happen for faces of a voxel set
    # side s of quad q runs corner s -> s+1; its partner runs the other way, so s meets s'+1 and s+1 meets s'
    node = lambda sides, shift: side_quad[sides] * 4 + (sides % 4 + shift) % 4  # noqa: E731
    rows = np.concatenate([node(first, 0), node(first, 1)])
    cols = np.concatenate([node(second, 1), node(second, 0)])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(4 * n_quads, 4 * n_quads))
    _, component = connected_components(graph, directed=False)
    vertex_ids, first_node = np.unique(component, return_index=True)
    corners = quads.reshape(-1, 3)[first_node]
    return np.searchsorted(vertex_ids, component).reshape(n_quads, 4), corners


def _joined_around(occupied: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """For edges p -> q shared by 4 quads: are the two diagonal solid voxels joined through the voxels beyond *both*
    ends of the edge (the voxel layers just before min(p, q) and just after max(p, q) along the edge)?"""
    lo = np.minimum(p, q)
    axis = np.argmax(np.abs(q - p), axis=1)
    u, v = (axis + 1) % 3, (axis + 2) % 3
    rows = np.arange(len(lo))

    def cell(du: int, dv: int, da: int) -> np.ndarray:
        c = lo.copy()
        c[rows, u] += du
        c[rows, v] += dv
        c[rows, axis] += da
        return occupied[tuple(c.T)]

    # the four voxels around the edge (offsets 0/-1 along u and v); which diagonal is solid?
    diagonal_a = cell(0, 0, 0) & cell(-1, -1, 0)
    joined = np.ones(len(lo), bool)
    for da in (-1, 1):
        a00, a11, a01, a10 = cell(0, 0, da), cell(-1, -1, da), cell(0, -1, da), cell(-1, 0, da)
        joined &= np.where(diagonal_a, a00 & a11 & (a01 | a10), a01 & a10 & (a00 | a11))
    return joined


# ----------------------------------------------------------------------------------------------------------------------
# Surface mesh (2.5D)


def outline_polygon(xy: np.ndarray, params: MeshParams = MeshParams()) -> Polygon:
    """The outline of a building's points seen from above: their concave hull, simplified (the largest part)."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 3:
        raise InputError(f"need at least 3 points for a building outline, got {len(xy)}")
    hull = shapely.concave_hull(shapely.multipoints(xy), ratio=params.concave_ratio)
    if params.simplify > 0:
        hull = hull.simplify(params.simplify, preserve_topology=True)
    polygon = _largest_polygon(hull)
    if polygon is None:
        raise InputError("the points span no area seen from above (no outline)")
    return polygon


def _largest_polygon(geometry: BaseGeometry) -> Polygon | None:
    parts = [g for g in getattr(geometry, "geoms", [geometry]) if isinstance(g, Polygon) and g.area > 0]
    return max(parts, key=lambda g: g.area) if parts else None


def surface_mesh(xyz: np.ndarray, params: MeshParams = MeshParams(), footprint: BaseGeometry | None = None,
                 ground_z: float | None = None, rgb: np.ndarray | None = None) -> trimesh.Trimesh:
    """A watertight 2.5D mesh of one building from its (flattened) points, in CRS coordinates.

    xyz: (N, 3) float64 CRS points of the building. footprint: its outline (shapely Polygon/MultiPolygon, CRS);
    default :func:`outline_polygon` of the points. ground_z: height of the floor; default the lowest point.
    rgb: (N, 3) uint8 colours: each vertex then takes the colour of its nearest point.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) < 3 or not np.isfinite(xyz).all():
        raise InputError(f"surface mesh: need an (N >= 3, 3) array of finite points, got shape {xyz.shape}")
    offset = np.floor(xyz.min(axis=0))  # triangulate near the origin: UTM magnitudes cost qhull its precision
    local = xyz - offset
    if footprint is None:
        outline = outline_polygon(local[:, :2], params)
    else:
        outline = affinity.translate(footprint, -offset[0], -offset[1])
        if not outline.is_valid:
            outline = shapely.make_valid(outline)
    polygons = [g for g in getattr(outline, "geoms", [outline]) if isinstance(g, Polygon) and g.area > 0]
    if not polygons:
        raise InputError("surface mesh: the footprint has no area")
    top_xy, top_z = _top_points(local, params.top_cell, params.max_roof_slope)
    floor = float(local[:, 2].min() if ground_z is None else ground_z - offset[2])
    parts = [_extrude(poly, top_xy, top_z, floor, params.cell) for poly in polygons]
    vertices = np.concatenate([p[0] for p in parts])
    starts = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    faces = np.concatenate([p[1] + s for p, s in zip(parts, starts)])
    colours = None
    if rgb is not None:
        rgb = np.asarray(rgb, dtype=np.uint8).reshape(len(xyz), 3)
        colours = rgb[cKDTree(local).query(vertices)[1]]
    return trimesh.Trimesh(vertices=vertices + offset, faces=faces, vertex_colors=colours, process=False)


def _top_points(local: np.ndarray, cell: float, max_slope_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The roof's points: the highest point of each ``cell`` x ``cell`` column, xy (K, 2) and z (K,), without those
    that lie under a neighbour (within 1 m) seen steeper than ``max_slope_deg`` from them: wall points below the eaves
    where a column holds no roof point (a 2.5D roof has nothing above it)."""
    keys = np.floor(local[:, :2] / cell).astype(np.int64)
    order = np.lexsort((-local[:, 2], keys[:, 1], keys[:, 0]))
    k = keys[order]
    first = order[np.r_[True, np.any(k[1:] != k[:-1], axis=1)]]
    xy, z = local[first, :2], local[first, 2]
    if len(xy) > 1:
        distance, neighbour = cKDTree(xy).query(xy, k=min(12, len(xy)), distance_upper_bound=1.0)
        found = np.isfinite(distance)
        rise = np.where(found, z[np.minimum(neighbour, len(z) - 1)] - z[:, None], -np.inf)
        under = np.any(found & (rise > math.tan(math.radians(max_slope_deg)) * distance + 0.05), axis=1)
        xy, z = xy[~under], z[~under]
    return xy, z


def _extrude(polygon: Polygon, top_xy: np.ndarray, top_z: np.ndarray, floor: float,
             cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Roof height field over ``polygon``, vertical walls along its rings and a flat floor: (vertices, faces)."""
    xy, triangles, boundary = _conforming_triangulation(polygon, cell)
    z = _roof_heights(top_xy, top_z, xy)
    z = np.maximum(z, floor + 1e-3)  # a roof never below the floor (keeps the solid's orientation)
    n = len(xy)
    vertices = np.concatenate([np.column_stack([xy, z]), np.column_stack([xy, np.full(n, floor)])])
    a, b = boundary[:, 0], boundary[:, 1]  # interior on the left of a -> b: the wall faces right, outwards
    walls = np.concatenate([np.column_stack([a + n, b + n, b]), np.column_stack([a + n, b, a])])
    faces = np.concatenate([triangles, triangles[:, ::-1] + n, walls])
    return vertices, faces


def _roof_heights(top_xy: np.ndarray, top_z: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Heights at ``xy``: linear in the Delaunay triangles of the top points, the nearest top point outside them.

    matplotlib's triangle finder, not scipy's ``find_simplex``/``LinearNDInterpolator``: those compute barycentric
    transforms with one LAPACK call per triangle, which took 14 s instead of 0.01 s on a loaded machine with a
    multi-threaded OpenBLAS.
    """
    import matplotlib.tri as mtri  # imported here: matplotlib takes ~0.5 s to import

    z = np.full(len(xy), np.nan)
    if len(top_xy) >= 3:
        try:
            triangulation = mtri.Triangulation(top_xy[:, 0], top_xy[:, 1])
        except (ValueError, RuntimeError):  # collinear or otherwise degenerate top points: nearest only
            triangulation = None
        if triangulation is not None:
            values = mtri.LinearTriInterpolator(triangulation, top_z)(xy[:, 0], xy[:, 1])
            z = np.ma.filled(values.astype(np.float64), np.nan)
    missing = ~np.isfinite(z)
    if missing.any():
        z[missing] = top_z[cKDTree(top_xy).query(xy[missing])[1]]
    return z


def _conforming_triangulation(polygon: Polygon, cell: float,
                              max_rounds: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Delaunay triangles of ``polygon`` whose edges include every segment of its rings.

    Vertices: the rings split into pieces of at most ``cell`` and the ``cell`` grid nodes inside the polygon at least
    ``cell / 2`` from its rings. A ring segment that is not a Delaunay edge is split at its midpoint until all are
    (conforming Delaunay). Returns vertices (V, 2), counter-clockwise triangles (T, 3) and the boundary as directed
    edges (B, 2) with the polygon on their left.
    """
    polygon = shapely.remove_repeated_points(shapely.segmentize(orient(polygon, 1.0), cell),
                                             1e-6)
    points, segments = [], []
    for ring in [polygon.exterior, *polygon.interiors]:
        coords = np.asarray(ring.coords)[:-1]
        index = np.arange(len(coords)) + sum(len(p) for p in points)
        points.append(coords)
        segments.append(np.column_stack([index, np.roll(index, -1)]))
    minx, miny, maxx, maxy = polygon.bounds
    gx, gy = np.meshgrid(np.arange(math.floor(minx / cell), math.ceil(maxx / cell) + 1) * cell,
                         np.arange(math.floor(miny / cell), math.ceil(maxy / cell) + 1) * cell, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    inside = shapely.contains_xy(polygon, gx, gy)
    nodes = np.column_stack([gx[inside], gy[inside]])
    nodes = nodes[shapely.distance(polygon.boundary, shapely.points(nodes)) >= 0.5 * cell]
    xy = np.concatenate(points + [nodes])
    segments = np.concatenate(segments)
    for _ in range(max_rounds):
        triangles = _delaunay_inside(xy, polygon)
        missing = ~_are_edges(segments, triangles, len(xy))
        if not missing.any():
            boundary = _boundary_edges(triangles)
            if not np.array_equal(np.sort(_edge_keys(boundary, len(xy))), np.sort(_edge_keys(segments, len(xy)))):
                raise AssertionError("surface mesh: the triangulation's boundary is not the outline")
            return xy, triangles, boundary
        # split every missing segment at its midpoint (it is then two shorter, more likely Delaunay segments)
        split = segments[missing]
        mid_index = len(xy) + np.arange(len(split))
        xy = np.concatenate([xy, xy[split].mean(axis=1)])
        segments = np.concatenate([segments[~missing], np.column_stack([split[:, 0], mid_index]),
                                   np.column_stack([mid_index, split[:, 1]])])
    raise InputError(f"surface mesh: could not triangulate the outline (a ring segment stays off the Delaunay "
                     f"triangulation after {max_rounds} splits; simplify the footprint)")


def _delaunay_inside(xy: np.ndarray, polygon: Polygon) -> np.ndarray:
    """Delaunay triangles of ``xy`` whose centroid lies inside ``polygon``, counter-clockwise.

    Four far corners join the triangulation so that no ring point lies on its convex hull: qhull returns flat
    triangles along straight runs of hull points.
    """
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    margin = hi - lo + 1.0
    frame = np.array([[lo[0] - margin[0], lo[1] - margin[1]], [hi[0] + margin[0], lo[1] - margin[1]],
                      [hi[0] + margin[0], hi[1] + margin[1]], [lo[0] - margin[0], hi[1] + margin[1]]])
    triangles = Delaunay(np.concatenate([xy, frame])).simplices
    triangles = triangles[np.all(triangles < len(xy), axis=1)]
    centroid = xy[triangles].mean(axis=1)
    triangles = triangles[shapely.contains_xy(polygon, centroid[:, 0], centroid[:, 1])]
    u, v = xy[triangles[:, 1]] - xy[triangles[:, 0]], xy[triangles[:, 2]] - xy[triangles[:, 0]]
    cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    triangles[cross < 0] = triangles[cross < 0][:, ::-1]
    return triangles[np.abs(cross) > 0]


def _edge_keys(edges: np.ndarray, n: int) -> np.ndarray:
    return np.minimum(edges[:, 0], edges[:, 1]) * n + np.maximum(edges[:, 0], edges[:, 1])


def _are_edges(segments: np.ndarray, triangles: np.ndarray, n: int) -> np.ndarray:
    sides = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.isin(_edge_keys(segments, n), _edge_keys(sides, n))


def _boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Directed edges used by one triangle only (the polygon on their left, triangles being counter-clockwise)."""
    sides = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    n = int(triangles.max()) + 1
    _, index, count = np.unique(_edge_keys(sides, n), return_inverse=True, return_counts=True)
    return sides[count[index.reshape(-1)] == 1]


# ----------------------------------------------------------------------------------------------------------------------
# Files


