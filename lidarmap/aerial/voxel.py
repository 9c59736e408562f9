"""Voxelization (paper §1-2, §4.2-4.3): points -> voxels with a true majority label and a mean colour.

A :class:`VoxelGrid` maps back to the CRS exactly: voxel ``(i, j, k)`` is the half-open box
``origin + [i, i+1) x [j, j+1) x [k, k+1) * size`` with ``origin`` in float64 CRS coordinates, and the grid carries
the CRS as WKT. Voxels from points are a *surface shell* (roofs and walls one voxel thick), never filled.

Stage API (arrays and small dataclasses, no files)::

    voxelize(xyz, labels=None, rgb=None, params=VoxelParams(), origin=None, crs=None) -> VoxelGrid
    voxelize_naive(xyz, classification, rgb=None, size=1.0, building_class=6, crs=None) -> VoxelGrid
    default_origin(xyz, size) -> (3,) float64

Files (the only functions here that touch files; all written atomically)::

    write_voxels(path, grid) / read_voxels(path) -> VoxelGrid   # .npz + JSON header: size, origin, CRS (exact)
    write_vox(path, grid)                                       # MagicaVoxel .vox, split in 256^3 models
    write_voxel_ply(path, grid)                                 # PLY of voxel cubes, float64 CRS corners

``voxelize`` takes every point of the building (building and non-building labels alike) and gives each voxel the
label most of its points carry (ties: the smallest label code), so isolated mislabelled points do not make voxels of
their own; ``params.keep_labels`` then keeps the building voxels. ``voxelize_naive`` is the MinecraftUBC baseline the
paper compares against: only points already classified as building, 1 m floor truncation, voxels with at most one
point dropped, label = median of class codes, colour = mean RGB.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import numpy as np
from pyproj import CRS
from scipy import ndimage

from lidarmap.config import check_params
from lidarmap.core import VoxelGrid
from lidarmap.errors import ConfigError, InputError

__all__ = ["VoxelParams", "VoxelGrid", "voxelize", "voxelize_naive", "default_origin", "fill_columns",
           "describe_voxels"]


#: Largest grid, in cells of the bounding box, that the flat int64 voxel keys can address.
_MAX_CELLS = 2 ** 62


@dataclasses.dataclass(frozen=True)
class VoxelParams:
    """Parameters of ``lidarmap voxelize`` (``[voxel]`` table of a config file).

    size (1.0): voxel edge length in CRS units (metres). 1 m is the paper's baseline (MinecraftUBC); use 0.25-0.5 m
        for meshes.
    min_points (1): voxels with fewer points than this are dropped (the naive baseline drops voxels with <= 1 point,
        i.e. ``min_points = 2``).
    keep_labels (()): after the majority vote keep only voxels whose label is in this list, e.g. ``[1]`` (building
        in a building / not-building segmentation) or ``[6]`` (ASPRS building); empty keeps every voxel.
    colour_majority_only (True): a voxel's colour is the mean RGB of the points that carry its majority label (so
        ground or tree points in a wall voxel do not tint it); False averages all its points.
    """

    section = "voxel"
    constraints: ClassVar[dict[str, str]] = {
        "size": ">= 0",
        "min_points": ">= 0",
    }

    size: float = 1.0
    min_points: int = 1
    keep_labels: tuple[int, ...] = ()
    colour_majority_only: bool = True

    def __post_init__(self) -> None:
        check_params(self)
        if not (isinstance(self.size, (int, float)) and math.isfinite(self.size) and self.size > 0):
            raise ConfigError(f"voxel parameters: size must be a finite number > 0, got {self.size!r}")
        if not (isinstance(self.min_points, int) and self.min_points >= 1):
            raise ConfigError(f"voxel parameters: min_points must be an integer >= 1, got {self.min_points!r}")
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in self.keep_labels):
            raise ConfigError(f"voxel parameters: keep_labels must be integers, got {self.keep_labels!r}")


# ----------------------------------------------------------------------------------------------------------------------
# Voxelization


def default_origin(xyz: np.ndarray, size: float) -> np.ndarray:
    """The points' minimum corner rounded down to a multiple of ``size``: grids of the same size share a lattice."""
    return np.floor(np.asarray(xyz, dtype=np.float64).min(axis=0) / size) * size


def _resolve_origin(xyz: np.ndarray, size: float, origin: np.ndarray | None) -> np.ndarray:
    if origin is None:
        return default_origin(xyz, size) if len(xyz) else np.zeros(3)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    if not np.isfinite(origin).all():
        raise InputError(f"voxel origin must be finite, got {origin.tolist()}")
    return origin


def _check_points(xyz: np.ndarray, n_expected: int | None = None, what: str = "points") -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"{what}: expected an (N, 3) array of coordinates, got shape {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise InputError(f"{what}: coordinates must be finite (found NaN or inf)")
    return xyz


def _check_per_point(values: np.ndarray | None, n: int, name: str, columns: int | None = None) -> np.ndarray | None:
    if values is None:
        return None
    values = np.asarray(values)
    shape = (n,) if columns is None else (n, columns)
    if values.shape != shape:
        raise InputError(f"{name}: expected shape {shape} (one per point), got {values.shape}")
    return values


def _cells(xyz: np.ndarray, origin: np.ndarray, size: float) -> np.ndarray:
    """Integer voxel index of each point (floor, so a point on a voxel face belongs to the voxel above it)."""
    return np.floor((xyz - origin) / size).astype(np.int64)


def _group(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique voxels (sorted by i, j, k), each point's voxel number and the points per voxel.

    One sort of flat int64 keys (``np.unique`` on rows would sort structured records, several times slower).
    """
    lo = cells.min(axis=0)
    dims = cells.max(axis=0) - lo + 1
    if float(np.prod(dims.astype(np.float64))) >= _MAX_CELLS:
        raise InputError(f"voxel grid too large: {dims.tolist()} voxels along x, y, z (use a larger voxel size)")
    rel = cells - lo
    flat = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
    keys, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    ijk = np.column_stack([keys // (dims[1] * dims[2]), (keys // dims[2]) % dims[1], keys % dims[2]]) + lo
    return ijk, inverse.reshape(-1), counts


def _majority(inverse: np.ndarray, n_voxels: int, labels: np.ndarray) -> np.ndarray:
    """The most frequent label of each voxel; ties go to the smallest label."""
    values, codes = np.unique(labels, return_inverse=True)
    n_values = len(values)
    if n_voxels * n_values <= 8 * len(labels) + 4096:
        # few distinct labels (the usual case): a dense voxel x label count table; argmax takes the first maximum
        table = np.bincount(inverse * n_values + codes, minlength=n_voxels * n_values).reshape(n_voxels, n_values)
        return values[np.argmax(table, axis=1)]
    # many distinct labels: count (voxel, label) pairs, then per voxel the pair with the highest count
    pairs, pair_counts = np.unique(inverse * n_values + codes, return_counts=True)
    voxel, code = pairs // n_values, pairs % n_values
    order = np.lexsort((code, -pair_counts, voxel))
    first = order[np.r_[True, voxel[order][1:] != voxel[order][:-1]]]
    return values[code[first]]


def _mean_colour(inverse: np.ndarray, n_voxels: int, rgb: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """Mean RGB per voxel (rounded) over the points with ``weight`` True (all points when None)."""
    if weight is not None:
        inverse, rgb = inverse[weight], rgb[weight]
    n = np.bincount(inverse, minlength=n_voxels).astype(np.float64)
    sums = np.stack([np.bincount(inverse, weights=rgb[:, c].astype(np.float64), minlength=n_voxels)
                     for c in range(3)], axis=1)
    return np.clip(np.rint(sums / np.maximum(n, 1)[:, None]), 0, 255).astype(np.uint8)


def _crs_wkt(crs: CRS | str | None) -> str | None:
    if crs is None:
        return None
    return crs.to_wkt() if isinstance(crs, CRS) else CRS.from_user_input(crs).to_wkt()


def _empty_grid(origin: np.ndarray, size: float, with_rgb: bool, crs_wkt: str | None) -> VoxelGrid:
    return VoxelGrid(origin=origin, size=size, ijk=np.zeros((0, 3), np.int64), label=np.zeros(0, np.int32),
                     rgb=np.zeros((0, 3), np.uint8) if with_rgb else None, count=np.zeros(0, np.int64),
                     crs_wkt=crs_wkt)


def voxelize(xyz: np.ndarray, labels: np.ndarray | None = None, rgb: np.ndarray | None = None,
             params: VoxelParams = VoxelParams(), origin: np.ndarray | None = None,
             crs: CRS | str | None = None) -> VoxelGrid:
    """Voxels of a point set with the true majority label and the mean colour of each voxel.

    xyz: (N, 3) float64 CRS coordinates. labels: (N,) integer labels (1 building / 0 not building, or ASPRS classes);
    None gives every voxel the label 1. rgb: (N, 3) uint8 colours or None. origin: the grid's origin (CRS); default
    :func:`default_origin` (a multiple of ``params.size``). crs: stored with the grid as WKT.
    """
    xyz = _check_points(xyz)
    labels = _check_per_point(labels, len(xyz), "labels")
    rgb = _check_per_point(rgb, len(xyz), "rgb", 3)
    if labels is not None and not (np.issubdtype(labels.dtype, np.integer) or labels.dtype == bool):
        raise InputError(f"labels: expected integer labels, got {labels.dtype}")
    size = float(params.size)
    origin = _resolve_origin(xyz, size, origin)
    wkt = _crs_wkt(crs)
    if len(xyz) == 0:
        return _empty_grid(origin, size, rgb is not None, wkt)
    ijk, inverse, counts = _group(_cells(xyz, origin, size))
    n_voxels = len(ijk)
    if labels is None:
        label = np.ones(n_voxels, np.int32)
        colour_weight = None
    else:
        labels = labels.astype(np.int64)
        label = _majority(inverse, n_voxels, labels)
        colour_weight = labels == label[inverse] if params.colour_majority_only else None
    colours = None if rgb is None else _mean_colour(inverse, n_voxels, rgb, colour_weight)
    keep = counts >= params.min_points
    if params.keep_labels:
        keep &= np.isin(label, np.asarray(params.keep_labels, dtype=np.int64))
    grid = VoxelGrid(origin=origin, size=size, ijk=ijk, label=label, rgb=colours, count=counts, crs_wkt=wkt)
    return grid if keep.all() else grid.subset(keep)


def voxelize_naive(xyz: np.ndarray, classification: np.ndarray, rgb: np.ndarray | None = None, size: float = 1.0,
                   building_class: int = 6, crs: CRS | str | None = None,
                   origin: np.ndarray | None = None) -> VoxelGrid:
    """The MinecraftUBC baseline: voxels of the points *classified* ``building_class``, nothing else.

    Floor truncation to ``size`` voxels (1 m in the paper), voxels with at most one point dropped, label = the median
    class code of the voxel's points (the lower median; with one class selected it is that class), colour = mean RGB
    of all its points. Unlabelled walls (class 1) are lost, which is the baseline's main failure (paper Fig. 2).
    """
    xyz = _check_points(xyz)
    classification = _check_per_point(classification, len(xyz), "classification")
    rgb = _check_per_point(rgb, len(xyz), "rgb", 3)
    if classification is None:
        raise InputError("classification: the naive baseline needs per-point classes")
    chosen = classification == building_class
    xyz, classes = xyz[chosen], classification[chosen].astype(np.int64)
    rgb = None if rgb is None else rgb[chosen]
    origin = _resolve_origin(xyz, size, origin)
    if len(xyz) == 0:
        return _empty_grid(origin, size, rgb is not None, _crs_wkt(crs))
    ijk, inverse, counts = _group(_cells(xyz, origin, size))
    # lower median of the class codes: sort points by (voxel, class) and take the middle one of each voxel
    order = np.lexsort((classes, inverse))
    start = np.r_[0, np.cumsum(counts)[:-1]]
    label = classes[order[start + (counts - 1) // 2]]
    colours = None if rgb is None else _mean_colour(inverse, len(ijk), rgb)
    grid = VoxelGrid(origin=origin, size=size, ijk=ijk, label=label, rgb=colours, count=counts, crs_wkt=_crs_wkt(crs))
    return grid.subset(counts > 1)


def fill_columns(grid: VoxelGrid, base_k: int | None = None, close_gaps: int = 0) -> VoxelGrid:
    """A 2.5D solid from a surface shell: every (i, j) column is filled from ``base_k`` up to its highest voxel.

    ``base_k`` defaults to the grid's lowest voxel layer (a flat floor, like a solid that stands on the lowest
    ground). Columns without a voxel that are enclosed by occupied columns (holes in the roof where no point fell,
    common when the voxels are smaller than the point spacing) are filled too, and so are notches of about
    ``close_gaps`` columns at the outline (a 2D closing with a disk of radius ``close_gaps + 0.5``); such a column
    takes the height of the nearest occupied one. Added voxels have ``count`` 0 and take the label and colour of the
    nearest original voxel at or above them (in their column, or in the nearest occupied column). Airborne buildings
    are 2.5D, so this is the solid an ALS shell describes (overhangs get filled).
    """
    if len(grid) == 0:
        return grid
    base = int(grid.ijk[:, 2].min() if base_k is None else base_k)
    pad = close_gaps + 1
    lo2 = grid.ijk[:, :2].min(axis=0) - pad
    cells2 = grid.ijk[:, :2] - lo2
    shape = tuple(cells2.max(axis=0) + pad + 1)
    top = np.full(shape, np.iinfo(np.int64).min)
    np.maximum.at(top, (cells2[:, 0], cells2[:, 1]), grid.ijk[:, 2])
    occupied = top > np.iinfo(np.int64).min
    region = occupied
    if close_gaps > 0:
        disk = np.hypot(*np.mgrid[-close_gaps:close_gaps + 1, -close_gaps:close_gaps + 1]) <= close_gaps + 0.5
        region = ndimage.binary_closing(region, structure=disk) | occupied
    region = ndimage.binary_fill_holes(region)
    # every region column copies the nearest occupied column (itself when occupied): its top and its voxels
    nearest = ndimage.distance_transform_edt(~occupied, return_distances=False, return_indices=True)
    ci, cj = np.nonzero(region)
    si, sj = nearest[0][ci, cj], nearest[1][ci, cj]
    heights = np.maximum(top[si, sj] - base + 1, 0)
    col = np.repeat(np.arange(len(ci)), heights)
    k = base + np.arange(len(col)) - np.repeat(np.cumsum(heights) - heights, heights)
    # the original voxel at or above each new one in its source column: search (column, k) among sorted originals
    k_min = min(base, int(grid.ijk[:, 2].min()))
    span = int(grid.ijk[:, 2].max()) - k_min + 1
    orig_key = (cells2[:, 0] * shape[1] + cells2[:, 1]) * span + (grid.ijk[:, 2] - k_min)
    order = np.argsort(orig_key, kind="stable")
    source = order[np.searchsorted(orig_key[order], (si[col] * shape[1] + sj[col]) * span + (k - k_min))]
    new_ijk = np.column_stack([ci[col] + lo2[0], cj[col] + lo2[1], k])
    count = np.where(np.all(grid.ijk[source] == new_ijk, axis=1), grid.count[source], 0)
    # keep the original voxels below base_k too (a base_k above the lowest layer only fills, never removes)
    below = np.flatnonzero(grid.ijk[:, 2] < base)
    ijk = np.concatenate([new_ijk, grid.ijk[below]])
    src = np.concatenate([source, below])
    count = np.concatenate([count, grid.count[below]])
    order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    return VoxelGrid(origin=grid.origin, size=grid.size, ijk=ijk[order], label=grid.label[src][order],
                     rgb=None if grid.rgb is None else grid.rgb[src][order], count=count[order],
                     crs_wkt=grid.crs_wkt)


# ----------------------------------------------------------------------------------------------------------------------
# The voxel file: .npz with a JSON header


# ----------------------------------------------------------------------------------------------------------------------
# Viewer formats


def describe_voxels(grid: VoxelGrid) -> dict[str, Any]:
    """A JSON-ready summary (voxel count, size, origin, extent, voxels per label, points) for reports."""
    lo = grid.ijk.min(axis=0) if len(grid) else np.zeros(3, np.int64)
    hi = grid.ijk.max(axis=0) + 1 if len(grid) else np.zeros(3, np.int64)
    return {"voxels": len(grid), "size": grid.size, "origin": grid.origin.tolist(), "extent_voxels": (hi - lo).tolist(),
            "labels": {int(v): int(c) for v, c in zip(*np.unique(grid.label, return_counts=True))},
            "points": int(grid.count.sum())}
