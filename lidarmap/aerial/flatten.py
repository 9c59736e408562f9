"""Planar flattening (LiDAR-DenseSeg §3.4, Algorithm 2): planes in one building's points, points moved onto them.

Points that lie on a plane are moved onto it along its normal, so that neighbours on one roof or wall fall into the
same voxel later instead of amplifying the scanner noise. Steps:

1. **Detection** (:func:`detect_planes`), one of two detectors (``FlattenParams.method``):

   * ``"region"`` (default): region growing on a k-NN graph, made robust for airborne data.

     a. Detection samples: one random point per ``detect_voxel`` cube (at most ``detect_max_points``: the voxel
        grows until they fit), so densified or very dense clouds cost what raw ALS costs.
     b. Every sample gets a PCA plane over its ``normal_k`` neighbours; it is *planar* when that fit's RMS is at
        most ``local_rms`` and the neighbourhood is not a line (edges, corners and clutter are not planar).
     c. Neighbouring planar samples are linked when their normals agree within ``angle_deg`` and each lies within
        ``distance`` of the other's plane; linked components are regions. A region that fits no plane (RMS above
        ``local_rms``: it leaked across a shallow edge such as a hip line) is re-cut by RANSAC inside it.
     d. Regions are refitted and samples (edges too) join the closest plane among their neighbours' within
        ``distance`` (twice); adjacent near-coplanar regions merge (``merge``); free samples join the closest plane
        among their 4 ``normal_k`` nearest samples.
     e. Vertical planes among the samples still free, by RANSAC (``leftover_walls``): ALS hits walls in sparse
        vertical scan-line stripes whose neighbourhoods give no usable normal. Wall pieces merge (``ransac_gap``).
     f. Every input point joins the closest plane of its sample's neighbourhood within ``distance``.

   * ``"paper"``: Algorithm 2 of the paper. A random unseen seed point; a RANSAC plane through it and its k nearest
     neighbours (k = 3 at first); while the fit stays good (at least ``paper_min_inliers`` of the k neighbours within
     ``distance``), k grows and the plane is fitted again; the last good plane is kept and its inliers are marked
     seen; repeat until every point is seen. The paper grows k by one; k here grows by the factor ``paper_k_growth``
     (at least by one; 1.0 is the paper's literal +1), because refitting at every k costs O(n²) per plane.
     "Good fit" is the paper's "number of points within a threshold distance", read as a share of the k points.

   Both end the same way: a point claimed by several planes goes to the closest; planes are refitted by least
   squares on their points, points farther than ``distance`` from the refitted plane are dropped, and planes with
   fewer than ``min_points`` points are discarded (corners, edges, clutter). Returned inliers are disjoint and
   every inlier lies within ``distance`` of its plane.

2. **Regularisation** (:func:`regularise_planes`, when ``regularise``): near-vertical planes (normal within
   ``vertical_tol_deg`` of horizontal) become vertical, near-horizontal ones (within ``horizontal_tol_deg``)
   horizontal, and the azimuth of every non-horizontal plane within ``axis_snap_deg`` of the building's main axes
   (:func:`main_axis_deg`: the support-weighted mean azimuth of the planes, modulo 90°) is snapped onto them:
   parallel and orthogonal walls and roof slopes share exact directions. A snapped plane is refitted along its new
   normal and keeps only the inliers within ``distance``; the snap is refused when it would lose more than
   ``snap_max_loss`` of them.

3. **Flattening** (:func:`flatten`): every inlier of a plane with at least ``min_points`` inliers moves onto the
   plane along its normal (a point claimed by several planes goes to the closest); all other points stay put.

Conventions: a :class:`Plane` is ``normal . x + offset = 0`` in the coordinates given (float64 CRS coordinates
are fine: the work is done relative to the points' centroid); normals are unit vectors pointing up for planes
flatter than 60° and, for steeper ones (walls), horizontally away from the input's centroid (outwards for convex
buildings). Planes are ordered by decreasing number of inliers. Same input, parameters and seed give the same
planes (the seed drives every random choice: sample thinning, seeds, RANSAC hypotheses).

Stage API (arrays and small dataclasses, no files)::

    detect_planes(xyz, params=FlattenParams(), seed=0) -> list[Plane]
    regularise_planes(planes, xyz, params) -> list[Plane]
    flatten(xyz, planes, params) -> FlattenResult
    flatten_points(xyz, params=FlattenParams(), seed=0) -> FlattenResult       # detect (+ regularise) + flatten
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import ClassVar

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lidarmap.config import check_params
from lidarmap.errors import InputError

__all__ = ["FlattenParams", "Plane", "FlattenResult", "METHODS", "detect_planes", "regularise_planes", "flatten",
           "flatten_points", "fit_plane", "main_axis_deg"]

#: Plane detectors known to :func:`detect_planes`.
METHODS = ("region", "paper")

#: ``progress(done, total)`` callback.
Report = Callable[[int, int], None]

_CHUNK = 200_000  # points per chunk when evaluating candidate planes (bounds the (chunk, k) temporaries)
_MIN_WALL_SAMPLES = 10  # a leftover wall needs this many detection samples: fewer say nothing about clutter


@dataclasses.dataclass(frozen=True)
class FlattenParams:
    """Parameters of planar flattening (TOML table ``[flatten]``). Lengths in metres, angles in degrees.

    Detection
        method ("region"): plane detector, "region" (k-NN region growing, fast) or "paper" (Algorithm 2 of the
            paper: k grows around random seeds while a RANSAC fit stays good). See the module docstring.
        distance (0.08): inlier distance to a plane. ALS range noise is 2-3 cm (σ) plus a few cm of roof
            roughness: 0.08 (3.2 σ) keeps 99.9 % of a 2.5 cm-noise roof and leaves window reveals, balconies
            and chimneys (≥ 0.15 m off the wall or roof) alone.
        min_points (30): n of the paper: planes with fewer inliers are not kept (corners, edges, clutter): 1-2.5 m²
            of roof at ALS densities (12-30 points/m²); raise it for densified clouds.
        normal_k (12): neighbours of the local PCA plane of every detection sample (also the k-NN graph of the
            region growing and of the merge step).
        local_rms (0.04): a sample whose neighbourhood fits a plane worse than this (RMS of the PCA residuals) is
            an edge or clutter: it starts and links no region but may join a plane later (about 1.5x ALS noise).
        angle_deg (10.0): region growing links neighbours whose normals differ by less than this.
        merge (True): merge adjacent planes whose normals differ by less than ``merge_angle_deg`` when the merged
            fit stays within ``local_rms`` (RMS; or up to twice that with 90 % of the points within ``distance``:
            walls with window reveals); applied by both detectors ("paper" without it is the paper's algorithm as
            written).
        merge_angle_deg (5.0): see ``merge``.
        detect_voxel (0.2): the region detector runs on one random point per voxel of this size (thins densified
            clouds; raw ALS at ≤ 25 points/m² is hardly thinned) ...
        detect_max_points (200000): ... and at most this many samples (the voxel grows until they fit); every
            input point is then assigned to the closest plane of its sample's neighbourhood.
        leftover_walls (True): "region": look for vertical planes among the samples no region took, by RANSAC
            (sparse walls: ALS hits them in vertical scan-line stripes whose k-NN normals are unreliable) ...
        ransac_gap (5.0): ... a wall's inliers farther apart than this are separate pieces (only the piece holding
            the hypothesis is kept; ALS wall stripes can be 4 m apart). A wall must also clearly outnumber the free
            points 1-3 x ``distance`` off it over its extent (scattered clutter such as a crown does not).
        paper_k_growth (1.5): "paper": k grows to max(k + 1, ceil(k * paper_k_growth)) after a good fit (1.0 is
            the paper's k + 1: exact, but quadratic in the plane size).
        paper_min_inliers (0.9): "paper": a fit is good while at least this share of the k neighbours lies within
            ``distance`` of the RANSAC plane.
        ransac_iterations (64): random hypotheses per RANSAC round ("paper" and re-cutting leaky regions:
            3-point planes; leftover walls: vertical planes through 2 points); the best is refined by least
            squares on its inliers.
    Regularisation
        regularise (True): snap planes (see the module docstring); False keeps the detected planes as they are.
        vertical_tol_deg (5.0): planes whose normal is within this of horizontal become exactly vertical.
        horizontal_tol_deg (2.0): planes whose normal is within this of vertical become exactly horizontal (flat
            roofs; real ones drain at 1-2°, so this stays small).
        axis_snap_deg (5.0): planes whose azimuth is within this of the building's main axes (modulo 90°) are
            rotated onto them.
        snap_max_loss (0.05): a snap is refused when more than this share of the plane's inliers would end
            farther than ``distance`` from the snapped plane.
    """

    section = "flatten"
    constraints: ClassVar[dict[str, str]] = {
        "method": "in region, paper",
        "distance": ">= 0",
        "min_points": ">= 0",
        "normal_k": ">= 0",
        "local_rms": ">= 0",
        "angle_deg": ">= 0",
        "merge_angle_deg": ">= 0",
        "detect_voxel": ">= 0",
        "detect_max_points": ">= 0",
        "ransac_gap": ">= 0",
        "paper_k_growth": ">= 0",
        "paper_min_inliers": ">= 0",
        "ransac_iterations": ">= 0",
        "vertical_tol_deg": ">= 0",
        "horizontal_tol_deg": ">= 0",
        "axis_snap_deg": ">= 0",
        "snap_max_loss": ">= 0",
    }

    method: str = "region"
    distance: float = 0.08
    min_points: int = 30
    normal_k: int = 12
    local_rms: float = 0.04
    angle_deg: float = 10.0
    merge: bool = True
    merge_angle_deg: float = 5.0
    detect_voxel: float = 0.2
    detect_max_points: int = 200_000
    leftover_walls: bool = True
    ransac_gap: float = 5.0
    paper_k_growth: float = 1.5
    paper_min_inliers: float = 0.9
    ransac_iterations: int = 64
    regularise: bool = True
    vertical_tol_deg: float = 5.0
    horizontal_tol_deg: float = 2.0
    axis_snap_deg: float = 5.0
    snap_max_loss: float = 0.05

    def __post_init__(self) -> None:
        check_params(self)
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, not {self.method!r}")
        for name in ("distance", "local_rms", "detect_voxel", "ransac_gap"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        for name in ("angle_deg", "merge_angle_deg", "vertical_tol_deg", "horizontal_tol_deg", "axis_snap_deg"):
            if not 0 <= getattr(self, name) < 90:
                raise ValueError(f"{name} must be in [0, 90) degrees")
        checks = [
            (self.min_points >= 3, "min_points must be >= 3"),
            (self.normal_k >= 3, "normal_k must be >= 3"),
            (self.detect_max_points >= 1000, "detect_max_points must be >= 1000"),
            (self.paper_k_growth >= 1.0, "paper_k_growth must be >= 1"),
            (0 < self.paper_min_inliers <= 1, "paper_min_inliers must be in (0, 1]"),
            (self.ransac_iterations >= 1, "ransac_iterations must be >= 1"),
            (0 <= self.snap_max_loss <= 1, "snap_max_loss must be in [0, 1]"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)


@dataclasses.dataclass
class Plane:
    """A detected plane: ``normal . x + offset = 0`` in the coordinates of the points it was detected in."""

    normal: np.ndarray  # (3,) unit
    offset: float
    inliers: np.ndarray  # indices into the input points, sorted
    rms: float  # RMS distance of the inliers to the plane

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        """Signed distances of points (N, 3) to the plane (positive on the normal's side)."""
        return np.asarray(xyz, dtype=np.float64) @ self.normal + self.offset

    @property
    def tilt_deg(self) -> float:
        """Angle between the plane and the horizontal (0 flat roof, 90 wall)."""
        return math.degrees(math.acos(min(1.0, abs(float(self.normal[2])))))


@dataclasses.dataclass
class FlattenResult:
    """Flattened points: ``xyz`` (N, 3) float64, the plane index of every point (-1: not planar, left where it
    was), how far each point moved (metres, ≥ 0) and the planes (``plane_id`` indexes this list)."""

    xyz: np.ndarray
    plane_id: np.ndarray  # (N,) int64
    moved: np.ndarray  # (N,) float64
    planes: list[Plane]

    @property
    def planar_fraction(self) -> float:
        return float(np.mean(self.plane_id >= 0)) if len(self.plane_id) else 0.0


# ----------------------------------------------------------------------------------------------------------------------
# Small geometry helpers


def _check_xyz(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"expected an (N, 3) array of point coordinates, got shape {xyz.shape}")
    if not np.all(np.isfinite(xyz)):
        raise InputError("NaN or infinite point coordinates")
    return xyz


def fit_plane(xyz: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares plane through points (N >= 3): unit normal, offset (n . x + offset = 0) and RMS residual."""
    xyz = np.asarray(xyz, dtype=np.float64)
    centre = xyz.mean(axis=0)
    vals, vecs = np.linalg.eigh(np.cov((xyz - centre).T, bias=True))
    normal = vecs[:, 0]
    return normal, float(-normal @ centre), float(math.sqrt(max(vals[0], 0.0)))


def _group_fit(points: np.ndarray, labels: np.ndarray, groups: int) -> tuple[np.ndarray, ...]:
    """Least-squares planes of all label groups at once from summed moments: normals (G, 3), offsets (G,),
    counts (G,), RMS (G,) and the moments (count, sums (G, 3), second moments (G, 3, 3)) for merging."""
    use = labels >= 0
    lab, p = labels[use], points[use]
    count = np.bincount(lab, minlength=groups).astype(np.float64)
    sums = np.stack([np.bincount(lab, p[:, i], groups) for i in range(3)], axis=1)
    second = np.empty((groups, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            second[:, i, j] = second[:, j, i] = np.bincount(lab, p[:, i] * p[:, j], groups)
    normals, offsets, rms = _planes_from_moments(count, sums, second)
    return normals, offsets, count, rms, (count, sums, second)


def _planes_from_moments(count: np.ndarray, sums: np.ndarray,
                         second: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals, offsets and RMS residuals of planes given point counts, coordinate sums and second moments."""
    safe = np.maximum(count, 1.0)
    mean = sums / safe[:, None]
    cov = second / safe[:, None, None] - mean[:, :, None] * mean[:, None, :]
    vals, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]
    return normals, -np.einsum("gi,gi->g", normals, mean), np.sqrt(np.maximum(vals[:, 0], 0.0))


def _neighbourhood_planes(points: np.ndarray, k: int,
                          local_rms: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA plane of every point's k-neighbourhood: unit normals, whether the neighbourhood is planar (RMS residual
    at most ``local_rms`` and not a line: its second spread at least a tenth of the first, since a line's normal is
    arbitrary) and the neighbour indices (column 0 is the point itself)."""
    n = len(points)
    k = int(min(k, n))
    _, idx = cKDTree(points).query(points, k=k, workers=-1)
    idx = idx.reshape(n, k)
    nb = points[idx]
    nb -= nb.mean(axis=1, keepdims=True)
    cov = np.empty((n, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.einsum("nk,nk->n", nb[:, :, i], nb[:, :, j]) / k
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, 0.0)
    planar = (vals[:, 0] <= local_rms ** 2) & (vals[:, 1] >= 0.01 * vals[:, 2])
    return vecs[:, :, 0], planar, idx


def _relabel(labels: np.ndarray, min_size: int) -> np.ndarray:
    """Labels 0..G-1 ordered by decreasing group size (ties: lower old label first); groups smaller than
    ``min_size`` become -1."""
    out = np.full(len(labels), -1, dtype=np.int64)
    use = labels >= 0
    if not use.any():
        return out
    counts = np.bincount(labels[use])
    keep = np.flatnonzero(counts >= min_size)
    order = keep[np.lexsort((keep, -counts[keep]))]
    new = np.full(len(counts), -1, dtype=np.int64)
    new[order] = np.arange(len(order))
    out[use] = new[labels[use]]
    return out


def _closest_owner(n: int, member: np.ndarray, owner: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Owner of every point (-1 for none) among (member, owner, |dist|) claims: the claim with the smallest
    distance (ties: the later claim)."""
    best = np.full(n, np.inf)
    np.minimum.at(best, member, dist)
    win = dist <= best[member]
    out = np.full(n, -1, dtype=np.int64)
    out[member[win]] = owner[win]
    return out


def _count_distinct(values: np.ndarray) -> int:
    """len(np.unique(values)) by a plain sort (much faster than np.unique on large int arrays)."""
    s = np.sort(values)
    return int(len(s) > 0) + int(np.count_nonzero(s[1:] != s[:-1]))


def _closest_candidate(points: np.ndarray, rows: np.ndarray, table: np.ndarray, labels: np.ndarray,
                       normals: np.ndarray, offsets: np.ndarray, distance: float) -> np.ndarray:
    """For every point, the closest plane within ``distance`` among its candidates, else -1. The candidates of point
    i are the labels ``labels[table[rows[i]]]`` (a neighbourhood; label -1 is no plane)."""
    cand_rows = labels[table]
    # most neighbourhoods lie inside one region: one candidate, one distance
    single = np.all((cand_rows == cand_rows[:, :1]) | (cand_rows < 0), axis=1)
    only = np.where(single, cand_rows.max(axis=1), -1)
    out = np.full(len(points), -1, dtype=np.int64)
    for lo in range(0, len(points), _CHUNK):
        r = rows[lo:lo + _CHUNK]
        p = points[lo:lo + _CHUNK]
        one = single[r]
        c1 = only[r[one]]
        ok = c1 >= 0
        d1 = np.abs(np.einsum("ni,ni->n", normals[np.maximum(c1, 0)], p[one]) + offsets[np.maximum(c1, 0)])
        res = np.full(len(p), -1, dtype=np.int64)
        res[np.flatnonzero(one)[ok & (d1 <= distance)]] = c1[ok & (d1 <= distance)]
        many = np.flatnonzero(~one)
        if len(many):
            cand = cand_rows[r[many]]
            q = p[many]
            valid = cand >= 0
            c = np.where(valid, cand, 0)
            d = np.abs(normals[c, 0] * q[:, :1] + normals[c, 1] * q[:, 1:2] + normals[c, 2] * q[:, 2:3] + offsets[c])
            d[~valid] = np.inf
            best = np.argmin(d, axis=1)
            at = np.arange(len(q))
            res[many] = np.where(d[at, best] <= distance, cand[at, best], -1)
        out[lo:lo + _CHUNK] = res
    return out


def _merge_pairs(points: np.ndarray, labels: np.ndarray, pairs: np.ndarray, params: FlattenParams) -> np.ndarray:
    """Merge label pairs (P, 2) whose normals differ by less than ``merge_angle_deg`` and whose union still fits
    one plane: RMS within ``local_rms``, or (a wall with many window reveals a few cm behind it: RMS up to twice
    that) 90 % of the union within ``distance`` of its plane. Transitive."""
    groups = int(labels.max()) + 1 if (labels >= 0).any() else 0
    if groups < 2 or len(pairs) == 0:
        return labels
    normals, _, _, _, (count, sums, second) = _group_fit(points, labels, groups)
    a, b = pairs[:, 0], pairs[:, 1]
    parallel = np.abs(np.einsum("pi,pi->p", normals[a], normals[b])) >= math.cos(math.radians(params.merge_angle_deg))
    a, b = a[parallel], b[parallel]
    union_n, union_d, rms = _planes_from_moments(count[a] + count[b], sums[a] + sums[b], second[a] + second[b])
    ok = rms <= params.local_rms
    check = np.flatnonzero(~ok & (rms <= 2 * params.local_rms))
    if len(check):
        order = np.argsort(labels, kind="stable")
        bounds = np.searchsorted(labels[order], np.arange(groups + 1))
        for i in check:
            union = np.concatenate([order[bounds[a[i]]:bounds[a[i] + 1]], order[bounds[b[i]]:bounds[b[i] + 1]]])
            ok[i] = np.mean(np.abs(points[union] @ union_n[i] + union_d[i]) <= params.distance) >= 0.9
    a, b = a[ok], b[ok]
    if len(a) == 0:
        return labels
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(groups, groups))
    _, root = connected_components(graph, directed=False)
    return np.where(labels >= 0, root[np.maximum(labels, 0)], -1)


def _touching_pairs(labels: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Label pairs (a < b) linked by at least one k-NN edge."""
    groups = int(labels.max()) + 1 if (labels >= 0).any() else 0
    a = np.repeat(labels, idx.shape[1] - 1)
    b = labels[idx[:, 1:]].ravel()
    touch = (a >= 0) & (b >= 0) & (a < b)
    pairs = np.unique(a[touch] * groups + b[touch])  # few: only edges between regions
    return np.column_stack([pairs // max(groups, 1), pairs % max(groups, 1)])


def _nearby_pairs(points: np.ndarray, labels: np.ndarray, gap: float) -> np.ndarray:
    """Label pairs (a < b) whose bounding boxes are less than ``gap`` apart."""
    use = labels >= 0
    groups = int(labels.max()) + 1 if use.any() else 0
    if groups < 2:
        return np.zeros((0, 2), dtype=np.int64)
    lo = np.full((groups, 3), np.inf)
    hi = np.full((groups, 3), -np.inf)
    np.minimum.at(lo, labels[use], points[use])
    np.maximum.at(hi, labels[use], points[use])
    out = []
    for start in range(0, groups, 512):  # bounded (512, G) temporaries
        rows = np.arange(start, min(groups, start + 512))
        apart = np.maximum(lo[None, :, :] - hi[rows, None, :], lo[rows, None, :] - hi[None, :, :]).max(axis=2)
        r, c = np.nonzero((apart < gap) & (rows[:, None] < np.arange(groups)[None, :]))
        out.append(np.column_stack([rows[r], c]))
    return np.concatenate(out)


# ----------------------------------------------------------------------------------------------------------------------
# Region growing


def _detection_samples(points: np.ndarray, params: FlattenParams,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One random point per ``detect_voxel`` cube (the voxel grows until at most ``detect_max_points`` remain):
    the sample indices and, for every input point, the index (into the samples) of its voxel's sample."""
    voxel = params.detect_voxel
    lo = points.min(axis=0)
    while True:
        keys = np.floor((points - lo) / voxel).astype(np.int64)
        dims = keys.max(axis=0) + 1
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        count = _count_distinct(flat)
        if count <= params.detect_max_points:
            break
        voxel *= 1.05 * math.sqrt(count / params.detect_max_points)  # on surfaces, samples ~ 1 / voxel²
    # the sample of a voxel: the first of its points after a seeded shuffle and a sort by voxel key
    shuffled = rng.permutation(len(points))
    order = shuffled[np.argsort(flat[shuffled])]
    key = flat[order]
    starts = np.concatenate([[True], key[1:] != key[:-1]])
    sample_of = np.empty(len(points), dtype=np.int64)
    sample_of[order] = np.cumsum(starts) - 1
    return order[starts], sample_of


def _grow_regions(points: np.ndarray, normals: np.ndarray, planar: np.ndarray, idx: np.ndarray,
                  params: FlattenParams) -> np.ndarray:
    """Connected components of planar samples linked by agreeing normals and mutual plane distance."""
    n = len(idx)
    seeds = np.flatnonzero(planar)
    nb = idx[seeds, 1:]  # (m, k - 1) neighbours of the planar samples
    n_nb = normals[nb]
    diff = points[nb] - points[seeds, None, :]
    keep = planar[nb]
    keep &= np.abs(np.einsum("mi,mki->mk", normals[seeds], n_nb)) >= math.cos(math.radians(params.angle_deg))
    keep &= np.abs(np.einsum("mi,mki->mk", normals[seeds], diff)) <= params.distance
    keep &= np.abs(np.einsum("mki,mki->mk", n_nb, diff)) <= params.distance
    rows = np.broadcast_to(seeds[:, None], nb.shape)[keep]
    graph = coo_matrix((np.ones(len(rows)), (rows, nb[keep])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return _relabel(np.where(planar, labels, -1), 3)


def _split_leaky(points: np.ndarray, labels: np.ndarray, idx: np.ndarray, params: FlattenParams,
                 rng: np.random.Generator) -> np.ndarray:
    """Regions that fit no plane (RMS above ``local_rms``: the growing leaked across a shallow edge, e.g. a hip
    line, through a chain of edge samples) are cut into planes by RANSAC inside the region: local 3-sample
    hypotheses (a random member and two of its k-NN in the region), the best refitted by least squares, its inliers
    connected to the hypothesis' member through the k-NN graph become a region; repeat on the rest while pieces of
    at least 3 samples come out (three failures in a row end it). Samples left over are free."""
    groups = int(labels.max()) + 1 if (labels >= 0).any() else 0
    if groups == 0:
        return labels
    _, _, _, rms, _ = _group_fit(points, labels, groups)
    leaky = np.flatnonzero(rms > params.local_rms)
    if len(leaky) == 0:
        return labels
    labels = labels.copy()
    label = groups
    for g in leaky:
        rest = np.flatnonzero(labels == g)
        labels[rest] = -1
        failures = 0
        while len(rest) >= 3 and failures < 3:
            inside = np.zeros(len(points), dtype=bool)
            inside[rest] = True
            first = rest[rng.integers(0, len(rest), params.ransac_iterations)]
            pick = idx[first[:, None], rng.integers(1, idx.shape[1], size=(len(first), 2))]
            a, b, c = points[first], points[pick[:, 0]], points[pick[:, 1]]
            hyp = np.cross(b - a, c - a)
            length = np.linalg.norm(hyp, axis=1)
            hyp /= np.maximum(length, 1e-12)[:, None]
            score = np.count_nonzero(np.abs((points[rest] @ hyp.T) - np.einsum("hi,hi->h", hyp, a))
                                     <= params.distance, axis=0)
            score[(length < 1e-9) | ~inside[pick[:, 0]] | ~inside[pick[:, 1]]] = -1
            best = int(np.argmax(score))
            failures += 1
            if score[best] < 3:
                continue
            member = np.abs((points[rest] - a[best]) @ hyp[best]) <= params.distance
            normal, offset, _ = fit_plane(points[rest[member]])
            member = np.abs(points[rest] @ normal + offset) <= params.distance
            piece = _connected_to(rest[member], first[best], idx)
            if len(piece) < 3:
                continue
            labels[piece] = label
            label += 1
            rest = np.setdiff1d(rest, piece, assume_unique=True)
            failures = 0
    return labels


def _connected_to(members: np.ndarray, start: int, idx: np.ndarray) -> np.ndarray:
    """The members linked to ``start`` through k-NN edges between members (empty if ``start`` is not one)."""
    if start not in members:
        return np.zeros(0, dtype=np.int64)
    local = np.full(len(idx), -1, dtype=np.int64)
    local[members] = np.arange(len(members))
    rows = np.repeat(local[members], idx.shape[1] - 1)
    cols = local[idx[members, 1:]].ravel()
    ok = cols >= 0
    graph = coo_matrix((np.ones(int(ok.sum())), (rows[ok], cols[ok])), shape=(len(members), len(members)))
    _, comp = connected_components(graph, directed=False)
    return members[comp == comp[local[start]]]


def _extend_planes(points: np.ndarray, labels: np.ndarray, params: FlattenParams) -> np.ndarray:
    """Free samples join the closest plane within ``distance`` among the labels of their ``4 normal_k`` nearest
    samples: sparse parts of a surface (wall stripes next to a found piece of the wall) reach their plane before
    the leftover RANSAC could pair them with another wall across a corner."""
    free = np.flatnonzero(labels < 0)
    groups = int(labels.max()) + 1 if (labels >= 0).any() else 0
    if len(free) == 0 or groups == 0:
        return labels
    k = min(4 * params.normal_k, len(points))
    _, near = cKDTree(points).query(points[free], k=k, workers=-1)
    normals, offsets, *_ = _group_fit(points, labels, groups)
    labels = labels.copy()
    labels[free] = _closest_candidate(points[free], np.arange(len(free)), near.reshape(len(free), k), labels,
                                      normals, offsets, params.distance)
    return labels


def _leftover_walls(points: np.ndarray, labels: np.ndarray, full: np.ndarray, sample_of: np.ndarray,
                    params: FlattenParams, rng: np.random.Generator) -> np.ndarray:
    """Vertical planes among the samples no region took (or only a region too small to keep), by RANSAC.

    Why: ALS hits walls in vertical scan-line stripes metres apart; k-NN neighbourhoods there are lines, span two
    walls across a corner or mix the wall with the roof, so their normals are unreliable and the wall grows no
    region. A hypothesis is the vertical plane through a random free sample and one of its ``4 normal_k`` nearest
    free samples at least 0.2 m away horizontally; the best (MSAC score over the free samples) is refitted by least
    squares in xy on its samples within ``distance / 2``, its inliers (within ``distance``) are cut into pieces
    farther apart than ``ransac_gap`` and the piece holding the hypothesis' sample is a wall when it has at least
    10 samples, represents at least ``min_points`` input points and stands out from the points around it
    (:func:`_stands_out`, judged on the input points ``full``, whose samples are ``sample_of``). Stops after five
    failures in a row.
    """
    weight = np.bincount(sample_of, minlength=len(points))
    labels = labels.copy()
    if (labels >= 0).any():  # regions too small to keep are free again
        small = np.bincount(labels[labels >= 0], weights=weight[labels >= 0]) < params.min_points
        labels[(labels >= 0) & small[np.maximum(labels, 0)]] = -1
    free = np.flatnonzero(labels < 0)
    if len(free) < 3:
        return labels
    on_free = np.flatnonzero(labels[sample_of] < 0)  # input points whose sample is free
    full, full_sample = full[on_free], sample_of[on_free]
    label = int(labels.max()) + 1
    # neighbours among the samples free at the start (pairs with a sample taken since are skipped); 4 k of them,
    # since the nearest ones of a stripe point are on its own stripe (same xy: no vertical plane) or across a corner
    k = min(4 * params.normal_k, len(free))
    neighbours = free[cKDTree(points[free]).query(points[free], k=k)[1].reshape(len(free), k)]
    row_of = np.full(len(points), -1, dtype=np.int64)
    row_of[free] = np.arange(len(free))
    failures = 0
    while len(free) >= 3 and failures < 5 and weight[free].sum() >= params.min_points:
        xy = points[free, :2]
        first = rng.integers(0, len(free), params.ransac_iterations)
        second_pt = neighbours[row_of[free[first]], rng.integers(1, k, size=len(first))]
        along = points[second_pt, :2] - xy[first]
        length = np.linalg.norm(along, axis=1)
        length[labels[second_pt] >= 0] = 0.0  # taken by a wall found meanwhile
        hyp = np.column_stack([-along[:, 1], along[:, 0]]) / np.maximum(length, 1e-12)[:, None]
        # MSAC score (inliers weighted by 1 - (d / distance)²): a plane through the wall beats a slightly turned
        # one that also catches window reveals a few cm behind it
        d = np.abs(xy @ hyp.T - np.einsum("hi,hi->h", hyp, xy[first])) / params.distance
        score = np.sum(np.clip(1.0 - d * d, 0.0, None), axis=0)
        score[length < 0.2] = -1
        best = int(np.argmax(score))
        failures += 1
        inliers = np.flatnonzero(d[:, best] <= 0.5)
        if len(inliers) < 3:
            continue
        centre = xy[inliers].mean(axis=0)  # least squares on the core inliers (within distance / 2)
        normal2 = np.linalg.eigh(np.cov((xy[inliers] - centre).T))[1][:, 0]
        inliers = np.flatnonzero(np.abs((xy - centre) @ normal2) <= params.distance)
        if first[best] not in inliers:
            continue
        piece = inliers[_piece_of(points[free[inliers]], int(np.searchsorted(inliers, first[best])),
                                  params.ransac_gap)]
        members = free[piece]
        if len(members) < _MIN_WALL_SAMPLES or weight[members].sum() < params.min_points or \
                not _stands_out(full[labels[full_sample] < 0], centre, normal2, points[members], params.distance):
            continue
        labels[members] = label
        label += 1
        free = np.setdiff1d(free, members, assume_unique=True)
        failures = 0
    return labels


def _stands_out(points: np.ndarray, centre: np.ndarray, normal2: np.ndarray, members: np.ndarray,
                distance: float) -> bool:
    """Whether a vertical plane (through ``centre`` with horizontal unit normal ``normal2``) stands out: over the
    extent of its inlier samples ``members``, the ``points`` lying 1-3 times ``distance`` off it are at most 3/4 of
    those within ``distance``. Scattered clutter (a crown) has 1-2 times as many in that band (it is twice as thick
    as the inlier slab); a wall has few, even with pilasters and window reveals (about 1/2)."""
    along = np.array([-normal2[1], normal2[0]])
    s, m = points[:, :2] @ along, members[:, :2] @ along
    inside = (s >= m.min()) & (s <= m.max()) & (points[:, 2] >= members[:, 2].min()) & \
        (points[:, 2] <= members[:, 2].max())
    d = np.abs((points[inside, :2] - centre) @ normal2)
    return bool(np.count_nonzero((d > distance) & (d <= 3 * distance)) <= 0.75 * np.count_nonzero(d <= distance))


def _piece_of(points: np.ndarray, start: int, gap: float) -> np.ndarray:
    """Indices of the points connected to ``points[start]`` by steps no longer than ``gap``."""
    pairs = cKDTree(points).query_pairs(gap, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    _, comp = connected_components(graph, directed=False)
    return np.flatnonzero(comp == comp[start])


def _region_labels(points: np.ndarray, params: FlattenParams, rng: np.random.Generator,
                   progress: Report | None, timings: dict) -> np.ndarray:
    """Plane label of every point (-1 none) by region growing on the detection samples."""
    t0 = time.perf_counter()
    if len(points) > 4 * params.normal_k:
        samples, sample_of = _detection_samples(points, params, rng)
    else:
        samples, sample_of = np.arange(len(points)), np.arange(len(points))
    sp = points[samples]
    t1 = time.perf_counter()
    normals, planar, idx = _neighbourhood_planes(sp, params.normal_k, params.local_rms)
    t2 = time.perf_counter()
    if progress:
        progress(1, 4)
    labels = _relabel(_split_leaky(sp, _grow_regions(sp, normals, planar, idx, params), idx, params, rng), 3)
    for _ in range(2):  # refit, then let samples (edges too) join the closest plane around them
        groups = int(labels.max()) + 1
        if groups == 0:
            break
        g_normals, g_offsets, *_ = _group_fit(sp, labels, groups)
        labels = _relabel(_closest_candidate(sp, np.arange(len(sp)), idx, labels, g_normals, g_offsets,
                                             params.distance), 3)
    if params.merge:
        labels = _relabel(_merge_pairs(sp, labels, _touching_pairs(labels, idx), params), 3)
    labels = _extend_planes(sp, labels, params)
    if params.leftover_walls:
        labels = _leftover_walls(sp, labels, points, sample_of, params, rng)
        if params.merge:  # wall pieces split by wide gaps between scan-line stripes
            labels = _relabel(_merge_pairs(sp, labels, _nearby_pairs(sp, labels, params.ransac_gap), params), 3)
    t3 = time.perf_counter()
    if progress:
        progress(2, 4)
    groups = int(labels.max()) + 1
    if groups == 0:
        return np.full(len(points), -1, dtype=np.int64)
    g_normals, g_offsets, *_ = _group_fit(sp, labels, groups)
    # every input point (samples included): the closest plane of its sample's neighbourhood
    full = _closest_candidate(points, sample_of, idx, labels, g_normals, g_offsets, params.distance)
    timings.update(samples=len(samples), sample_s=t1 - t0, normals_s=t2 - t1, grow_s=t3 - t2,
                   assign_s=time.perf_counter() - t3)
    if progress:
        progress(3, 4)
    return full


# ----------------------------------------------------------------------------------------------------------------------
# Paper, Algorithm 2


def _ransac_plane(points: np.ndarray, distance: float, iterations: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    """Best of ``iterations`` random 3-point planes (most points within ``distance``), refined by least squares on
    its inliers: normal, offset and the inlier mask after the refinement."""
    m = len(points)
    tri = rng.integers(0, m, size=(iterations, 3))
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    normals = np.cross(b - a, c - a)
    length = np.linalg.norm(normals, axis=1)
    normals /= np.maximum(length, 1e-12)[:, None]
    offsets = -np.einsum("hi,hi->h", normals, a)
    score = np.count_nonzero(np.abs(points @ normals.T + offsets) <= distance, axis=0)
    score[length < 1e-9] = -1  # collinear or repeated picks
    best = int(np.argmax(score))
    normal, offset = normals[best], offsets[best]
    inliers = np.abs(points @ normal + offset) <= distance
    if inliers.sum() >= 3:
        normal, offset, _ = fit_plane(points[inliers])
        inliers = np.abs(points @ normal + offset) <= distance
    return normal, offset, inliers


def _paper_candidates(points: np.ndarray, params: FlattenParams, rng: np.random.Generator,
                      progress: Report | None) -> list[np.ndarray]:
    """Algorithm 2: the inlier index sets of the last good plane around every seed (they may overlap)."""
    n = len(points)
    tree = cKDTree(points)
    unseen = np.ones(n, dtype=bool)
    left = n
    found: list[np.ndarray] = []
    reported = time.perf_counter()
    for seed in rng.permutation(n):
        if not unseen[seed]:
            continue
        k = 3
        best = tree.query(points[seed], k=k)[1]  # three points always fit a plane
        while k < n:
            k_next = min(n, max(k + 1, math.ceil(k * params.paper_k_growth)))
            nb = tree.query(points[seed], k=k_next)[1]
            _, _, inliers = _ransac_plane(points[nb], params.distance, params.ransac_iterations, rng)
            if inliers.mean() < params.paper_min_inliers:
                break
            best, k = nb[inliers], k_next
        newly = np.concatenate([best[unseen[best]], [seed] if unseen[seed] else []]).astype(np.int64)
        unseen[newly] = False  # the seed too, even when the RANSAC plane left it out
        left -= _count_distinct(newly)
        if len(best) >= params.min_points:
            found.append(np.sort(best))
        if progress and time.perf_counter() - reported > 0.2:
            progress(n - left, n)
            reported = time.perf_counter()
    return found


def _closest_claim(points: np.ndarray, claims: list[np.ndarray]) -> np.ndarray:
    """Label of every point: among the index sets claiming it, the one whose least-squares plane is closest."""
    if not claims:
        return np.full(len(points), -1, dtype=np.int64)
    owner = np.concatenate([np.full(len(c), i) for i, c in enumerate(claims)])
    member = np.concatenate(claims)
    normals, offsets, *_ = _group_fit(points[member], owner, len(claims))
    dist = np.abs(np.einsum("mi,mi->m", normals[owner], points[member]) + offsets[owner])
    return _closest_owner(len(points), member, owner, dist)


def _paper_labels(points: np.ndarray, params: FlattenParams, rng: np.random.Generator,
                  progress: Report | None, timings: dict) -> np.ndarray:
    t0 = time.perf_counter()
    labels = _relabel(_closest_claim(points, _paper_candidates(points, params, rng, progress)), 3)
    t1 = time.perf_counter()
    if params.merge and (labels >= 0).any():
        _, idx = cKDTree(points).query(points, k=min(params.normal_k, len(points)), workers=-1)
        pairs = _touching_pairs(labels, idx.reshape(len(points), -1))
        labels = _relabel(_merge_pairs(points, labels, pairs, params), 3)
    timings.update(seeds_s=t1 - t0, merge_s=time.perf_counter() - t1)
    return labels


# ----------------------------------------------------------------------------------------------------------------------
# Shared end of detection


def _orient(normal: np.ndarray, offset: float, plane_centre: np.ndarray,
            cloud_centre: np.ndarray) -> tuple[np.ndarray, float]:
    """Normals up for planes flatter than 60°, horizontally away from the cloud's centre for steeper ones."""
    if abs(normal[2]) >= 0.5:
        flip = normal[2] < 0
    else:
        flip = float(normal[:2] @ (plane_centre - cloud_centre)[:2]) < 0
    return (-normal, -offset) if flip else (normal, offset)


def _planes_from_labels(local: np.ndarray, labels: np.ndarray, centre: np.ndarray,
                        params: FlattenParams) -> list[Plane]:
    """Refit, drop points beyond ``distance``, refit, drop again (no refit after the last drop, so every inlier is
    within ``distance`` of its plane), keep planes with ``min_points``; offsets back to input coordinates."""
    labels = _relabel(labels, params.min_points)
    for last in (False, True):
        groups = int(labels.max()) + 1 if (labels >= 0).any() else 0
        if groups == 0:
            return []
        normals, offsets, *_ = _group_fit(local, labels, groups)
        use = np.flatnonzero(labels >= 0)
        dist = np.abs(np.einsum("ni,ni->n", normals[labels[use]], local[use]) + offsets[labels[use]])
        labels[use[dist > params.distance]] = -1
        if not last:
            labels = _relabel(labels, params.min_points)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(groups + 1))
    planes = []
    for g in range(groups):
        inliers = np.sort(order[bounds[g]:bounds[g + 1]])
        if len(inliers) < params.min_points:
            continue
        d = local[inliers] @ normals[g] + offsets[g]
        normal, offset = _orient(normals[g], float(offsets[g]), local[inliers].mean(axis=0), np.zeros(3))
        planes.append(Plane(normal=normal, offset=offset - float(normal @ centre), inliers=inliers,
                            rms=float(np.sqrt(np.mean(d * d)))))
    planes.sort(key=lambda p: (-len(p.inliers), int(p.inliers[0])))
    return planes


def detect_planes(xyz: np.ndarray, params: FlattenParams = FlattenParams(), seed: int = 0,
                  progress: Report | None = None, timings: dict | None = None) -> list[Plane]:
    """Planes in one building's points (N, 3), by ``params.method``; see the module docstring.

    Returns planes with at least ``min_points`` disjoint inliers, each inlier within ``distance`` of its plane,
    ordered by decreasing support. ``progress(done, total)`` is called as work advances; ``timings`` (a dict) receives
    the seconds of the steps.
    """
    xyz = _check_xyz(xyz)
    timings = {} if timings is None else timings
    if len(xyz) < params.min_points:
        return []
    start = time.perf_counter()
    centre = xyz.mean(axis=0)
    local = xyz - centre
    rng = np.random.default_rng(seed)
    if params.method == "region":
        labels = _region_labels(local, params, rng, progress, timings)
    else:
        labels = _paper_labels(local, params, rng, progress, timings)
    t = time.perf_counter()
    planes = _planes_from_labels(local, labels, centre, params)
    timings.update(finish_s=time.perf_counter() - t, detect_s=time.perf_counter() - start)
    if progress:
        progress(4, 4) if params.method == "region" else progress(len(xyz), len(xyz))
    return planes


# ----------------------------------------------------------------------------------------------------------------------
# Regularisation


def main_axis_deg(planes: list[Plane], inlier_deg: float = 5.0) -> float | None:
    """The building's main horizontal axis in [0, 90) degrees, or None if no plane has a horizontal component.

    The circular mean of the planes' normal azimuths modulo 90°, weighted by support x squared horizontal normal
    component (walls count fully, roof slopes partly, flat roofs not), taken twice more over the planes within
    ``inlier_deg`` of the previous estimate only, so that a few odd planes (a bay, clutter) do not tilt it.
    """
    if not planes:
        return None
    normals = np.array([p.normal for p in planes])
    weight = np.array([len(p.inliers) for p in planes]) * np.sum(normals[:, :2] ** 2, axis=1)
    four = 4.0 * np.arctan2(normals[:, 1], normals[:, 0])
    use = weight > 1e-9
    angle = None
    for _ in range(3):
        if weight[use].sum() < 1e-9:
            break
        angle = math.atan2(float(weight[use] @ np.sin(four[use])), float(weight[use] @ np.cos(four[use]))) / 4.0
        deviation = np.angle(np.exp(1j * (four - 4.0 * angle))) / 4.0  # wrapped to ±45°
        use = (weight > 1e-9) & (np.abs(deviation) <= math.radians(inlier_deg))
    return None if angle is None else math.degrees(angle) % 90.0


def _snapped_normal(normal: np.ndarray, axis_deg: float | None, params: FlattenParams) -> np.ndarray:
    n = normal.copy()
    horizontal = math.hypot(n[0], n[1])
    if horizontal <= math.sin(math.radians(params.horizontal_tol_deg)):
        return np.array([0.0, 0.0, 1.0 if n[2] >= 0 else -1.0])
    if abs(n[2]) <= math.sin(math.radians(params.vertical_tol_deg)):
        n[2] = 0.0
        horizontal = 1.0
    if axis_deg is not None:
        azimuth = math.degrees(math.atan2(n[1], n[0]))
        target = axis_deg + 90.0 * round((azimuth - axis_deg) / 90.0)
        if abs(azimuth - target) <= params.axis_snap_deg:
            a = math.radians(target)
            n[0], n[1] = horizontal * math.cos(a), horizontal * math.sin(a)
    return n / np.linalg.norm(n)


def regularise_planes(planes: list[Plane], xyz: np.ndarray, params: FlattenParams) -> list[Plane]:
    """Planes snapped to vertical / horizontal and to the building's main axes (see the module docstring).

    ``xyz`` are the points the planes were detected in. A snapped plane passes through its inliers' centroid,
    keeps the inliers within ``distance`` and its support order; a snap that would lose more than
    ``snap_max_loss`` of the inliers (or leave fewer than ``min_points``) is not made.
    """
    xyz = _check_xyz(xyz)
    axis = main_axis_deg(planes, params.axis_snap_deg)
    out = []
    for plane in planes:
        normal = _snapped_normal(plane.normal, axis, params)
        pts = xyz[plane.inliers]
        centre = pts.mean(axis=0)
        d = (pts - centre) @ normal
        keep = np.abs(d) <= params.distance
        lost = 1.0 - keep.mean()
        if np.allclose(normal, plane.normal) or lost > params.snap_max_loss or keep.sum() < params.min_points:
            out.append(plane)
            continue
        out.append(Plane(normal=normal, offset=float(-normal @ centre), inliers=plane.inliers[keep],
                         rms=float(np.sqrt(np.mean(d[keep] ** 2)))))
    return out


# ----------------------------------------------------------------------------------------------------------------------
# Flattening


def flatten(xyz: np.ndarray, planes: list[Plane], params: FlattenParams = FlattenParams()) -> FlattenResult:
    """Move every inlier of a plane with at least ``min_points`` inliers onto it along its normal.

    A point claimed by several planes (edges) goes to the closest one; points of smaller planes and points of no
    plane stay where they are (``plane_id`` -1, ``moved`` 0). ``plane_id`` indexes ``planes`` as given.
    """
    xyz = _check_xyz(xyz)
    n = len(xyz)
    out, moved = xyz.copy(), np.zeros(n)
    kept = [i for i, p in enumerate(planes) if len(p.inliers) >= params.min_points]
    if not kept:
        return FlattenResult(out, np.full(n, -1, dtype=np.int64), moved, list(planes))
    owner = np.concatenate([np.full(len(planes[i].inliers), i) for i in kept])
    member = np.concatenate([np.asarray(planes[i].inliers, dtype=np.int64) for i in kept])
    if member.min() < 0 or member.max() >= n:
        raise InputError(f"plane inlier indices out of range for {n} points")
    normals = np.array([p.normal for p in planes])
    centre = xyz.mean(axis=0)
    # offsets relative to the centroid: CRS-sized coordinates keep their precision in the products
    offsets = np.array([p.offset for p in planes]) + normals @ centre
    local = xyz - centre

    def signed(members: np.ndarray, owners: np.ndarray) -> np.ndarray:
        return np.einsum("mi,mi->m", normals[owners], local[members]) + offsets[owners]

    plane_id = _closest_owner(n, member, owner, np.abs(signed(member, owner)))
    member = np.flatnonzero(plane_id >= 0)
    dist = signed(member, plane_id[member])
    moved[member] = np.abs(dist)
    out[member] -= dist[:, None] * normals[plane_id[member]]
    return FlattenResult(out, plane_id, moved, list(planes))


def flatten_points(xyz: np.ndarray, params: FlattenParams = FlattenParams(), seed: int = 0,
                   progress: Report | None = None, timings: dict | None = None) -> FlattenResult:
    """Detect planes (:func:`detect_planes`), regularise them when ``params.regularise``, and flatten."""
    timings = {} if timings is None else timings
    planes = detect_planes(xyz, params, seed, progress=progress, timings=timings)
    if params.regularise:
        t = time.perf_counter()
        planes = regularise_planes(planes, xyz, params)
        timings["regularise_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result = flatten(xyz, planes, params)
    timings["flatten_s"] = time.perf_counter() - t
    return result
