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
import json
import math
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS
from scipy import ndimage
from scipy.spatial import cKDTree

from lidarmap.errors import ConfigError, InputError
from lidarmap.io.atomic import write_bytes_atomic
from lidarmap.io.npz import write_npz

__all__ = ["VoxelParams", "VoxelGrid", "voxelize", "voxelize_naive", "default_origin", "fill_columns", "write_voxels",
           "read_voxels", "write_vox", "write_voxel_ply", "label_colours", "describe_voxels", "VOXEL_FORMAT",
           "VOXEL_VERSION"]

VOXEL_FORMAT = "lidarmap-voxels"
VOXEL_VERSION = 1

#: Colours of voxels without RGB, by rank of their label among the grid's distinct labels (tab10).
LABEL_PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                          [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)

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

    size: float = 1.0
    min_points: int = 1
    keep_labels: tuple[int, ...] = ()
    colour_majority_only: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.size, (int, float)) and math.isfinite(self.size) and self.size > 0):
            raise ConfigError(f"voxel parameters: size must be a finite number > 0, got {self.size!r}")
        if not (isinstance(self.min_points, int) and self.min_points >= 1):
            raise ConfigError(f"voxel parameters: min_points must be an integer >= 1, got {self.min_points!r}")
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in self.keep_labels):
            raise ConfigError(f"voxel parameters: keep_labels must be integers, got {self.keep_labels!r}")


@dataclasses.dataclass
class VoxelGrid:
    """Occupied voxels of a regular grid in a CRS.

    origin: (3,) float64 CRS coordinates of voxel (0, 0, 0)'s minimum corner.
    size: voxel edge length (CRS units).
    ijk: (M, 3) int64 voxel indices, unique, sorted lexicographically by (i, j, k); voxel (i, j, k) is the half-open
        box ``origin + [i, i+1) x [j, j+1) x [k, k+1) * size``.
    label: (M,) int32 label of each voxel (the majority label of its points; 1 when no labels were given).
    rgb: (M, 3) uint8 mean colour, or None.
    count: (M,) int64 number of points in each voxel.
    crs_wkt: the CRS as WKT, or None when unknown.
    """

    origin: np.ndarray
    size: float
    ijk: np.ndarray
    label: np.ndarray
    rgb: np.ndarray | None
    count: np.ndarray
    crs_wkt: str | None = None

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.size = float(self.size)
        self.ijk = np.asarray(self.ijk, dtype=np.int64).reshape(-1, 3)
        m = len(self.ijk)
        self.label = np.asarray(self.label, dtype=np.int32).reshape(m)
        self.count = np.asarray(self.count, dtype=np.int64).reshape(m)
        if self.rgb is not None:
            self.rgb = np.asarray(self.rgb, dtype=np.uint8).reshape(m, 3)
        if not (math.isfinite(self.size) and self.size > 0) or not np.isfinite(self.origin).all():
            raise ValueError("voxel grid: size must be > 0 and the origin finite")

    def __len__(self) -> int:
        return len(self.ijk)

    @property
    def crs(self) -> CRS | None:
        return None if self.crs_wkt is None else CRS.from_wkt(self.crs_wkt)

    def centers(self) -> np.ndarray:
        """(M, 3) float64 CRS coordinates of the voxel centres."""
        return self.origin + (self.ijk + 0.5) * self.size

    def corners(self) -> np.ndarray:
        """(M, 3) float64 CRS coordinates of the voxel minimum corners."""
        return self.origin + self.ijk * self.size

    def subset(self, index: np.ndarray) -> "VoxelGrid":
        """The voxels selected by a boolean mask or an index array (order kept)."""
        return dataclasses.replace(self, ijk=self.ijk[index], label=self.label[index], count=self.count[index],
                                   rgb=None if self.rgb is None else self.rgb[index])

    def colours(self) -> np.ndarray:
        """(M, 3) uint8 display colours: the voxel RGB, else a colour per label (:func:`label_colours`)."""
        return self.rgb if self.rgb is not None else label_colours(self.label)


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


def write_voxels(path: str | Path, grid: VoxelGrid) -> Path:
    """Write ``grid`` to a compressed ``.npz`` (atomically); :func:`read_voxels` gives it back exactly.

    Arrays: ``header`` (JSON text: format, version, size, origin, crs_wkt, voxels, has_rgb), ``origin`` (3,) float64,
    ``ijk`` (M, 3) int32 (int64 when an index does not fit), ``label`` (M,) int32, ``count`` (M,) int64 and, with
    colour, ``rgb`` (M, 3) uint8. Readable with ``numpy.load`` alone.
    """
    fits = len(grid) == 0 or (np.abs(grid.ijk).max() < 2 ** 31)
    header = {"format": VOXEL_FORMAT, "version": VOXEL_VERSION, "size": grid.size,
              "origin": [float(v) for v in grid.origin], "crs_wkt": grid.crs_wkt, "voxels": len(grid),
              "has_rgb": grid.rgb is not None,
              "index": "voxel (i, j, k) is origin + [i, i+1) x [j, j+1) x [k, k+1) * size, CRS units"}
    arrays: dict[str, np.ndarray] = {"header": np.array(json.dumps(header)), "origin": grid.origin,
                                     "ijk": grid.ijk.astype(np.int32 if fits else np.int64), "label": grid.label,
                                     "count": grid.count}
    if grid.rgb is not None:
        arrays["rgb"] = grid.rgb
    return write_npz(path, arrays)


def read_voxels(path: str | Path) -> VoxelGrid:
    """Read a voxel file written by :func:`write_voxels`; problems are one-line :class:`InputError` s."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such voxel file", path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"not a lidarmap voxel file ({type(exc).__name__})", path) from None
    try:
        header = json.loads(str(arrays["header"]))
    except (KeyError, json.JSONDecodeError):
        raise InputError("not a lidarmap voxel file (no JSON header)", path) from None
    if header.get("format") != VOXEL_FORMAT:
        raise InputError(f"not a lidarmap voxel file (format {header.get('format')!r})", path)
    if header.get("version") != VOXEL_VERSION:
        raise InputError(f"unsupported voxel file version {header.get('version')!r} (this lidarmap reads "
                         f"{VOXEL_VERSION})", path)
    missing = [name for name in ("origin", "ijk", "label", "count") if name not in arrays]
    if missing:
        raise InputError(f"voxel file lacks array(s) {', '.join(missing)}", path)
    m = len(arrays["ijk"])
    rgb = arrays.get("rgb")
    if arrays["ijk"].shape != (m, 3) or len(arrays["label"]) != m or len(arrays["count"]) != m or (
            rgb is not None and rgb.shape != (m, 3)) or m != header.get("voxels"):
        raise InputError(f"voxel file arrays disagree in length (header says {header.get('voxels')} voxels)", path)
    try:
        return VoxelGrid(origin=arrays["origin"], size=header["size"], ijk=arrays["ijk"], label=arrays["label"],
                         rgb=rgb, count=arrays["count"], crs_wkt=header.get("crs_wkt"))
    except (ValueError, TypeError, KeyError) as exc:
        raise InputError(f"invalid voxel file: {exc}", path) from None


# ----------------------------------------------------------------------------------------------------------------------
# Viewer formats


def label_colours(labels: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 colour per voxel from its label: the k-th smallest distinct label gets palette colour k."""
    values, rank = np.unique(np.asarray(labels), return_inverse=True)
    return LABEL_PALETTE[rank.reshape(-1) % len(LABEL_PALETTE)]


def _palette(colours: np.ndarray, max_colours: int = 255) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_colours`` palette entries and each voxel's entry (0-based).

    Exact when the voxels have few distinct colours; otherwise the mean colours of the most populated cells of a
    16-level-per-channel colour cube, and each voxel takes the nearest of them.
    """
    unique, index = np.unique(colours, axis=0, return_inverse=True)
    if len(unique) <= max_colours:
        return unique, index.reshape(-1)
    bins = (colours.astype(np.int64) >> 4) @ np.array([256, 16, 1])
    bin_ids, bin_index, bin_counts = np.unique(bins, return_inverse=True, return_counts=True)
    top = np.argsort(-bin_counts, kind="stable")[:max_colours]
    sums = np.stack([np.bincount(bin_index.reshape(-1), weights=colours[:, c].astype(np.float64))
                     for c in range(3)], axis=1)
    palette = np.rint(sums[top] / bin_counts[top, None]).astype(np.uint8)
    _, nearest = cKDTree(palette.astype(np.float64)).query(colours.astype(np.float64))
    return palette, nearest


def _chunk(tag: bytes, content: bytes, children: bytes = b"") -> bytes:
    return tag + struct.pack("<ii", len(content), len(children)) + content + children


def _vox_dict(items: dict[str, str]) -> bytes:
    out = struct.pack("<i", len(items))
    for key, value in items.items():
        for text in (key.encode(), value.encode()):
            out += struct.pack("<i", len(text)) + text
    return out


def write_vox(path: str | Path, grid: VoxelGrid, max_model: int = 256) -> Path:
    """Write a MagicaVoxel ``.vox`` (version 150 with the scene graph of the format's extension), atomically.

    MagicaVoxel models hold at most 256 voxels per axis, so the grid is cut into blocks of ``max_model``^3 voxels,
    one model each, placed by a transform node (``_t`` = the block's centre) under one group: the models tile the
    grid exactly. Colours: the voxel RGB (or :func:`label_colours`) in a palette of at most 255 entries
    (:func:`_palette`). Voxel (0, 0, 0) of the file is the grid's minimum voxel; .vox keeps neither the voxel size nor
    the origin or the CRS (use :func:`write_voxels` for that). z is up in both.
    """
    if not 1 <= max_model <= 256:
        raise ValueError("max_model must be in 1..256")
    if len(grid) == 0:
        raise InputError("no voxels to write", path)
    palette, colour_index = _palette(grid.colours())
    shifted = grid.ijk - grid.ijk.min(axis=0)
    blocks, block_of = np.unique(shifted // max_model, axis=0, return_inverse=True)
    block_of = block_of.reshape(-1)
    local = shifted % max_model
    models, nodes = [], []
    child_ids = []
    for b, block in enumerate(blocks):  # one iteration per 256^3 block: a handful per building
        members = np.flatnonzero(block_of == b)
        dims = local[members].max(axis=0) + 1
        xyzi = np.column_stack([local[members], colour_index[members] + 1]).astype(np.uint8)
        models.append(_chunk(b"SIZE", struct.pack("<iii", *dims.tolist())))
        models.append(_chunk(b"XYZI", struct.pack("<i", len(members)) + xyzi.tobytes()))
        # a model's voxel v sits at _t - floor(dims / 2) + v, so _t = block corner + floor(dims / 2)
        t = block * max_model + dims // 2
        trn_id, shp_id = 2 + 2 * b, 3 + 2 * b
        child_ids.append(trn_id)
        nodes.append(_chunk(b"nTRN", struct.pack("<i", trn_id) + _vox_dict({}) + struct.pack("<iiii", shp_id, -1, 0, 1)
                            + _vox_dict({"_t": " ".join(str(int(v)) for v in t)})))
        nodes.append(_chunk(b"nSHP", struct.pack("<i", shp_id) + _vox_dict({}) + struct.pack("<ii", 1, b)
                            + _vox_dict({})))
    root = _chunk(b"nTRN", struct.pack("<i", 0) + _vox_dict({}) + struct.pack("<iiii", 1, -1, -1, 1) + _vox_dict({}))
    group = _chunk(b"nGRP", struct.pack("<i", 1) + _vox_dict({}) + struct.pack("<i", len(child_ids))
                   + struct.pack(f"<{len(child_ids)}i", *child_ids))
    rgba = np.zeros((256, 4), np.uint8)  # entry e is palette index e + 1; index 0 means "empty"
    rgba[:len(palette), :3] = palette
    rgba[:len(palette), 3] = 255
    body = b"".join(models) + root + group + b"".join(nodes) + _chunk(b"RGBA", rgba.tobytes())
    return write_bytes_atomic(path, b"VOX " + struct.pack("<i", 150) + _chunk(b"MAIN", b"", body))


#: Corners of the unit cube (x, y, z) and its six faces as corner indices, counter-clockwise seen from outside.
CUBE_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
CUBE_QUADS = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])


def write_voxel_ply(path: str | Path, grid: VoxelGrid) -> Path:
    """Write every voxel as a closed cube (8 float64 CRS corners, 6 quads, the voxel colour on its corners)."""
    from lidarmap.mesh import write_ply_arrays  # mesh.py builds on this module; import here to avoid a cycle

    corners = grid.corners()[:, None, :] + CUBE_CORNERS[None, :, :] * grid.size
    quads = (np.arange(len(grid))[:, None, None] * 8 + CUBE_QUADS[None]).reshape(-1, 4)
    colours = np.repeat(grid.colours(), 8, axis=0)
    return write_ply_arrays(path, corners.reshape(-1, 3), quads, vertex_colors=colours,
                            comment=f"lidarmap voxel cubes, size {grid.size!r}, CRS coordinates")


def describe_voxels(grid: VoxelGrid) -> dict[str, Any]:
    """A JSON-ready summary (voxel count, size, origin, extent, voxels per label, points) for reports."""
    lo = grid.ijk.min(axis=0) if len(grid) else np.zeros(3, np.int64)
    hi = grid.ijk.max(axis=0) + 1 if len(grid) else np.zeros(3, np.int64)
    return {"voxels": len(grid), "size": grid.size, "origin": grid.origin.tolist(), "extent_voxels": (hi - lo).tolist(),
            "labels": {int(v): int(c) for v, c in zip(*np.unique(grid.label, return_counts=True))},
            "points": int(grid.count.sum())}
