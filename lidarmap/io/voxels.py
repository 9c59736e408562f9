"""Voxel grids on disk: the lossless ``.voxels.npz`` (voxel size, origin, CRS kept), MagicaVoxel ``.vox`` and a PLY
of coloured cubes."""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lidarmap.core import CUBE_CORNERS, CUBE_QUADS, VoxelGrid
from lidarmap.errors import InputError
from lidarmap.io.atomic import write_bytes_atomic
from lidarmap.io.npz import write_npz

VOXEL_FORMAT = "lidarmap-voxels"


VOXEL_VERSION = 1


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


def write_voxel_ply(path: str | Path, grid: VoxelGrid) -> Path:
    """Write every voxel as a closed cube (8 float64 CRS corners, 6 quads, the voxel colour on its corners)."""
    from lidarmap.io.meshfile import (
        write_ply_arrays,  # mesh.py builds on this module; import here to avoid a cycle
    )

    corners = grid.corners()[:, None, :] + CUBE_CORNERS[None, :, :] * grid.size
    quads = (np.arange(len(grid))[:, None, None] * 8 + CUBE_QUADS[None]).reshape(-1, 4)
    colours = np.repeat(grid.colours(), 8, axis=0)
    return write_ply_arrays(path, corners.reshape(-1, 3), quads, vertex_colors=colours,
                            comment=f"lidarmap voxel cubes, size {grid.size!r}, CRS coordinates")
