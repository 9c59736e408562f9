"""Scores of aerial voxels and meshes against a truth mesh (e.g. the simulator's building solids).

    voxelize_mesh(mesh, size, origin, solid=False, skip_downward=True, ground=None) -> (K, 3) int64 voxel indices
    voxel_iou(a_ijk, b_ijk) -> float
    voxel_scores(pred_ijk, truth_ijk) -> dict       # IoU, precision, recall, counts
    chamfer_hausdorff(a, b, n_samples=20000, seed=0) -> dict
    sample_surface(mesh, n, rng) -> (n, 3) points

**Like with like.** Voxels made from points are a *surface shell*: a scanner only returns points from surfaces. So
the default truth voxels are the truth mesh's *surface* voxels (every voxel the surface passes through, in the same
half-open cells as :func:`lidarmap.aerial.voxel.voxelize` uses), without the faces no scanner sees: downward faces (the
floor of a solid) and, given ``ground``, everything below the terrain (the buried wall foot). Solids can be compared
too: ``voxelize_mesh(..., solid=True)`` against :func:`lidarmap.aerial.voxel.fill_columns` of the voxels.

**Mesh distances.** Chamfer and Hausdorff distances are estimated from ``n_samples`` points spread uniformly (by
area) over each surface, seeded; each sample's distance to the other mesh is exact (point-to-triangle). Chamfer is
the mean of the two directed mean distances; Hausdorff the larger of the two directed maxima (a lower bound of the
true Hausdorff distance that converges as ``n_samples`` grows).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from lidarmap.errors import InputError

__all__ = ["voxelize_mesh", "voxel_iou", "voxel_scores", "chamfer_hausdorff", "sample_surface"]

#: Pairs of (triangle, candidate voxel) tested per batch in :func:`voxelize_mesh`.
_BATCH = 1_000_000
#: Cells are half-open [c, c + 1): tested as the closed box [c, c + 1 - _EPS] (lattice units).
_EPS = 1e-9


def voxelize_mesh(mesh: trimesh.Trimesh, size: float, origin: np.ndarray, solid: bool = False,
                  skip_downward: bool = True, ground: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Voxels (K, 3) of the lattice ``origin + ijk * size`` that a mesh occupies, unique and sorted by (i, j, k).

    solid=False: the voxels its surface passes through (exact triangle/box overlap tests), skipping triangles that
    face down (normal z < -0.7) when ``skip_downward``. solid=True: those (all triangles) plus the voxels enclosed
    by them; needs a closed mesh. ground: a function of (N, 2) CRS xy giving the terrain height (e.g.
    ``SimTruth.terrain_height``); voxels whose top lies below it are dropped.
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    if not size > 0:
        raise InputError(f"voxel size must be > 0, got {size!r}")
    triangles = (np.asarray(mesh.triangles, dtype=np.float64) - origin) / size  # lattice units
    if skip_downward and not solid:
        normals = np.asarray(mesh.face_normals)
        triangles = triangles[normals[:, 2] >= -0.7]
    ijk = _surface_cells(triangles)
    if solid and len(ijk):
        ijk = _fill_enclosed(ijk)
    if ground is not None and len(ijk):
        centres = origin[:2] + (ijk[:, :2] + 0.5) * size
        ijk = ijk[origin[2] + (ijk[:, 2] + 1) * size >= np.asarray(ground(centres))]
    return ijk


def _surface_cells(triangles: np.ndarray) -> np.ndarray:
    """Unique cells (lattice units) that the triangles overlap, in batches of triangle x candidate-cell pairs."""
    lo = np.floor(triangles.min(axis=1)).astype(np.int64)
    hi = np.floor(triangles.max(axis=1)).astype(np.int64)
    extent = hi - lo + 1
    n_cells = extent.prod(axis=1)
    found = []
    start = 0
    while start < len(triangles):
        stop = start + max(1, int(np.searchsorted(np.cumsum(n_cells[start:]), _BATCH, side="right")))
        tri = np.repeat(np.arange(start, stop), n_cells[start:stop])
        offset = np.arange(len(tri)) - np.repeat(np.cumsum(n_cells[start:stop]) - n_cells[start:stop],
                                                 n_cells[start:stop])
        e = extent[tri]
        cells = lo[tri] + np.column_stack([offset // (e[:, 1] * e[:, 2]), (offset // e[:, 2]) % e[:, 1],
                                           offset % e[:, 2]])
        hit = _overlaps(triangles[tri], cells)
        found.append(cells[hit])
        start = stop
    cells = np.concatenate(found) if found else np.zeros((0, 3), np.int64)
    return np.unique(cells, axis=0)


def _overlaps(tri: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Separating-axis test of triangles (P, 3, 3) against unit cells (P, 3) (Akenine-Möller's 13 axes)."""
    h = 0.5 * (1.0 - _EPS)
    v = tri - (cells + h)[:, None, :]  # triangle relative to the box centre
    ok = np.all(v.min(axis=1) <= h, axis=1) & np.all(v.max(axis=1) >= -h, axis=1)  # the 3 box axes
    edges = np.stack([v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]], axis=1)
    normal = np.cross(edges[:, 0], edges[:, 1])
    ok &= np.abs(np.einsum("ij,ij->i", normal, v[:, 0])) <= h * np.abs(normal).sum(axis=1)
    for f in range(3):  # the 9 axes e_j x edge_f
        fx, fy, fz = edges[:, f, 0], edges[:, f, 1], edges[:, f, 2]
        zero = np.zeros_like(fx)
        for axis in (np.stack([zero, -fz, fy], 1), np.stack([fz, zero, -fx], 1), np.stack([-fy, fx, zero], 1)):
            p = np.einsum("pkj,pj->pk", v, axis)
            r = h * np.abs(axis).sum(axis=1)
            ok &= (p.min(axis=1) <= r) & (p.max(axis=1) >= -r)
    return ok


def _fill_enclosed(ijk: np.ndarray) -> np.ndarray:
    """Surface cells plus the cells they enclose (background connected through faces to the outside stays empty)."""
    lo = ijk.min(axis=0) - 1
    dense = np.zeros(tuple(ijk.max(axis=0) - lo + 2), bool)
    dense[tuple((ijk - lo).T)] = True
    return np.argwhere(ndimage.binary_fill_holes(dense)) + lo


def _keys(ijk: np.ndarray) -> np.ndarray:
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    return np.ascontiguousarray(ijk).view([("i", np.int64), ("j", np.int64), ("k", np.int64)]).reshape(-1)


def voxel_scores(pred_ijk: np.ndarray, truth_ijk: np.ndarray) -> dict[str, float | int]:
    """IoU, precision (share of predicted voxels in the truth) and recall (share of truth voxels predicted).

    Both sets must be indices on the same lattice (same origin and size); duplicates count once.
    """
    pred, truth = np.unique(_keys(pred_ijk)), np.unique(_keys(truth_ijk))
    both = len(np.intersect1d(pred, truth, assume_unique=True))
    union = len(pred) + len(truth) - both
    return {"iou": both / union if union else float("nan"),
            "precision": both / len(pred) if len(pred) else float("nan"),
            "recall": both / len(truth) if len(truth) else float("nan"),
            "predicted": len(pred), "truth": len(truth), "intersection": both}


def voxel_iou(a_ijk: np.ndarray, b_ijk: np.ndarray) -> float:
    """Intersection over union of two voxel index sets on the same lattice (NaN when both are empty)."""
    return float(voxel_scores(a_ijk, b_ijk)["iou"])


def sample_surface(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly distributed over the mesh surface (triangles drawn by area)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    if len(tri) == 0:
        raise InputError("cannot sample an empty mesh")
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    which = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1  # reflect into the triangle: uniform barycentric coordinates
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[which]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def chamfer_hausdorff(a: trimesh.Trimesh | np.ndarray, b: trimesh.Trimesh, n_samples: int = 20000,
                      seed: int = 0) -> dict[str, float | int]:
    """Symmetric Chamfer (mean) and Hausdorff distances between ``a`` (a mesh or (N, 3) points) and the mesh ``b``.

    Keys: ``chamfer`` = (a_to_b_mean + b_to_a_mean) / 2, ``hausdorff`` = max(a_to_b_max, b_to_a_max), the directed
    means, 95th percentiles and maxima (``a_to_b``: accuracy of a; ``b_to_a``: completeness of a when b is the
    truth), and ``samples``. Points given as ``a``: a random ``n_samples`` of them (all if fewer) are measured
    against ``b``, and ``b``'s samples against all of them.
    """
    from lidarmap.sim.distance import (
        MeshDistance,  # exact point-to-mesh distances (importing lidarmap.sim is slow)
    )

    rng = np.random.default_rng(seed)
    if isinstance(a, trimesh.Trimesh):
        pa = sample_surface(a, n_samples, rng)
    else:
        points = np.asarray(a, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            raise InputError("no points to compare")
        pa = points[np.sort(rng.choice(len(points), n_samples, replace=False))] if len(points) > n_samples else points
    pb = sample_surface(b, n_samples, rng)
    centre = pb.mean(axis=0)  # distances in a frame near the data (UTM magnitudes do not matter, but cheap)
    d_ab = MeshDistance(np.asarray(b.triangles) - centre)(pa - centre)[0]
    if isinstance(a, trimesh.Trimesh):
        d_ba = MeshDistance(np.asarray(a.triangles) - centre)(pb - centre)[0]
    else:
        d_ba = cKDTree(points - centre).query(pb - centre)[0]
    return {"chamfer": float((d_ab.mean() + d_ba.mean()) / 2), "hausdorff": float(max(d_ab.max(), d_ba.max())),
            "a_to_b_mean": float(d_ab.mean()), "b_to_a_mean": float(d_ba.mean()),
            "a_to_b_p95": float(np.percentile(d_ab, 95)), "b_to_a_p95": float(np.percentile(d_ba, 95)),
            "a_to_b_max": float(d_ab.max()), "b_to_a_max": float(d_ba.max()), "samples": int(len(pa))}


def score_building_voxels(voxel_grids: dict[str, Any], truth: Any, delivered: Any = None,
                          footprints: Any = None, buffer: float = 5.0) -> dict[str, dict[str, float]]:
    """Voxel scores of reconstructed buildings against the simulator's truth, and of the naive baseline.

    voxel_grids: building id -> :class:`~lidarmap.core.VoxelGrid` (e.g. each ``voxels.npz`` of ``lidarmap run``).
    truth: a :class:`~lidarmap.sim.SimTruth`; every grid is compared with the surface voxels of its building's
    true mesh on the grid's own lattice (terrain and downward faces left out, as our voxels are a shell).
    delivered + footprints (optional): the aerial cloud as delivered (PointCloud with its partial classification)
    and the footprints; the naive MinecraftUBC voxels of each building's points (nearest footprint within
    ``buffer``, as prep assigns them) are scored too, on the same lattice. Returns
    ``{id: {"iou", "precision", "recall", "naive_iou"?}}``.
    """
    from lidarmap.aerial.prep import assign_points
    from lidarmap.aerial.voxel import voxelize_naive

    owner = None
    if delivered is not None and footprints is not None:
        owner, _ = assign_points(delivered.xyz, footprints, buffer)
        index_of = {bid: i for i, bid in enumerate(footprints.ids)}
    out: dict[str, dict[str, float]] = {}
    for bid, grid in voxel_grids.items():
        true_ijk = voxelize_mesh(truth.building(int(bid)).mesh(), grid.size, grid.origin,
                                 ground=truth.terrain_height)
        scores = voxel_scores(grid.ijk, true_ijk)
        row = {k: float(scores[k]) for k in ("iou", "precision", "recall")}
        if owner is not None:
            mine = owner == index_of[str(bid)]
            rgb = delivered.rgb8()
            naive = voxelize_naive(delivered.xyz[mine], delivered.attrs["classification"][mine],
                                   None if rgb is None else rgb[mine], size=grid.size, origin=grid.origin)
            row["naive_iou"] = float(voxel_scores(naive.ijk, true_ijk)["iou"])
        out[str(bid)] = row
    return out
