"""``lidarmap info``: a lasinfo/pdal-info style summary of a LAS/LAZ file, computed by streaming."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from lidarmap.io.crs import describe_crs
from lidarmap.io.las import CHUNK_POINTS, _file_crs, _open, iter_las, resolve_crs

#: Grid cell (CRS units) used to measure the covered area for the density figure.
DENSITY_CELL = 1.0


def las_info(path: str | Path, crs: str | CRS | None = None, chunk_size: int = CHUNK_POINTS) -> dict[str, Any]:
    """Summary of a LAS/LAZ file: header facts plus statistics over every point (streamed, bounded memory)."""
    path = Path(path)
    with _open(path) as reader:
        header = reader.header
        file_crs = resolve_crs(_file_crs(header, path), crs, path)
        info: dict[str, Any] = {
            "file": str(path),
            "las_version": f"{header.version.major}.{header.version.minor}",
            "point_format": header.point_format.id,
            "compressed": path.suffix.lower() == ".laz",
            "point_count": int(header.point_count),
            "scales": [float(v) for v in header.scales],
            "offsets": [float(v) for v in header.offsets],
            "crs": describe_crs(file_crs),
            "crs_source": "file" if _file_crs(header, path) is not None else ("--crs" if crs else None),
            "extra_dimensions": list(header.point_format.extra_dimension_names),
            "dimensions": list(header.point_format.dimension_names),
        }
    return _add_statistics(info, iter_las(path, chunk_size=chunk_size, crs=crs))


def points_info(path: str | Path, crs: str | CRS | None = None, columns: str | None = None,
                chunk_size: int = CHUNK_POINTS) -> dict[str, Any]:
    """Summary of a PLY or text point file (the same keys as :func:`las_info` where they apply; ``format``
    says what the file is)."""
    from lidarmap.io.points import iter_points, read_points_header

    path = Path(path)
    header = read_points_header(path, crs, columns)
    if header.fmt == "ply":
        from lidarmap.io.ply import read_ply_header

        ply = read_ply_header(path)
        fmt = f"PLY {ply.fmt.replace('_', ' ')}"
        crs_source = "file" if ply.crs_text() else ("--crs" if crs else None)
    else:
        fmt, crs_source = "text (" + ",".join(header.fields) + ")", "--crs" if crs else None
    info: dict[str, Any] = {"file": str(path), "format": fmt, "point_count": header.n_points,
                            "crs": describe_crs(header.crs), "crs_source": crs_source,
                            "extra_dimensions": [f for f in header.fields if f not in ("x", "y", "z")],
                            "dimensions": list(header.fields)}
    return _add_statistics(info, iter_points(path, chunk_size, crs, columns))


def _add_statistics(info: dict[str, Any], chunks) -> dict[str, Any]:
    """Bounds, density, classes, returns and GPS time span over every chunk (``point_count`` set when unknown)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    classes: dict[int, int] = {}
    returns: dict[int, int] = {}
    t_range = [np.inf, -np.inf]
    cells: set[int] = set()
    n = 0
    for chunk in chunks:
        if not len(chunk):
            continue
        n += len(chunk)
        lo, hi = np.minimum(lo, chunk.xyz.min(axis=0)), np.maximum(hi, chunk.xyz.max(axis=0))
        _count_into(classes, chunk.attrs.get("classification"))
        _count_into(returns, chunk.attrs.get("return_number"))
        if "gps_time" in chunk.attrs and len(chunk):
            t_range = [min(t_range[0], float(chunk.attrs["gps_time"].min())),
                       max(t_range[1], float(chunk.attrs["gps_time"].max()))]
        cells.update(_cell_keys(chunk.xyz).tolist())
    info["point_count"] = count = n if info["point_count"] is None else info["point_count"]
    if count:
        area_bbox = float((hi[0] - lo[0]) * (hi[1] - lo[1]))
        area_cells = len(cells) * DENSITY_CELL**2
        info["bounds"] = {"min": lo.tolist(), "max": hi.tolist()}
        info["area_bbox"] = area_bbox
        info["area_covered"] = area_cells
        info["density_bbox"] = count / area_bbox if area_bbox > 0 else None
        info["density"] = count / area_cells
    else:
        info["bounds"] = None
        info["density"] = None
    info["classes"] = {str(k): v for k, v in sorted(classes.items())}
    info["returns"] = {str(k): v for k, v in sorted(returns.items())}
    info["gps_time"] = None if not np.isfinite(t_range[0]) else {"min": t_range[0], "max": t_range[1]}
    return info


def _count_into(counts: dict[int, int], values: np.ndarray | None) -> None:
    if values is None or len(values) == 0:
        return
    keys, n = np.unique(values, return_counts=True)
    for k, c in zip(keys.tolist(), n.tolist()):
        counts[int(k)] = counts.get(int(k), 0) + int(c)


def _cell_keys(xyz: np.ndarray) -> np.ndarray:
    ij = np.floor(xyz[:, :2] / DENSITY_CELL).astype(np.int64)
    return np.unique(ij[:, 0] * 100_000_000 + ij[:, 1])
