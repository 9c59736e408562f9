"""Any point file by its suffix: LAS/LAZ (:mod:`lidarmap.io.las`), PLY (:mod:`lidarmap.io.ply`) or text
(:mod:`lidarmap.io.xyz`): what is known before reading the points, and their chunks (the same
:class:`~lidarmap.core.PointCloud` whatever the format)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from pyproj import CRS

from lidarmap.core import PointCloud
from lidarmap.errors import ConfigError, InputError
from lidarmap.io.ply import ORIGIN_FIELDS
from lidarmap.io.xyz import SUFFIXES as TEXT_SUFFIXES

LAS_SUFFIXES = (".las", ".laz")
PLY_SUFFIXES = (".ply",)


def point_format(path: str | Path) -> str:
    """"las", "ply" or "text" from the file's suffix; anything else is an error naming the file."""
    suffix = Path(path).suffix.lower()
    if suffix in LAS_SUFFIXES:
        return "las"
    if suffix in PLY_SUFFIXES:
        return "ply"
    if suffix in TEXT_SUFFIXES:
        return "text"
    raise InputError(f"unknown point file type {suffix or '(no suffix)'!r}: expected .las/.laz, .ply or "
                     f"{'/'.join(TEXT_SUFFIXES)}", path)


@dataclasses.dataclass
class PointsHeader:
    """A point file before its points are read: count, CRS, attribute names, and the xy box they lie in (the LAS
    header's bounds with the reader's slack; ``None`` when the format has no bounds: the caller measures them)."""

    path: Path
    fmt: str
    n_points: int | None
    crs: CRS | None
    fields: list[str]
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None

    @property
    def has_origins(self) -> bool:
        return all(f in self.fields for f in ORIGIN_FIELDS)

    @property
    def has_gps_time(self) -> bool:
        return "gps_time" in self.fields


def read_points_header(path: str | Path, crs: str | CRS | None = None, columns: str | None = None) -> PointsHeader:
    """The header facts of any point file (see :class:`PointsHeader`); ``columns``: a text file's column spec."""
    path = Path(path)
    fmt = point_format(path)
    if columns is not None and fmt != "text":
        raise ConfigError(f"--columns describes a text point file (.xyz/.txt/.csv), not {path.name}")
    if fmt == "las":
        from lidarmap.io.las import read_header_crs

        header, file_crs = read_header_crs(path, crs)
        lo, hi = np.asarray(header.mins, dtype=np.float64)[:2], np.asarray(header.maxs, dtype=np.float64)[:2]
        fields = list(header.point_format.dimension_names)
        if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.any(lo != hi):
            slack = (hi - lo) * 0.01 + np.asarray(header.scales, dtype=np.float64)[:2] * 2
            return PointsHeader(path, fmt, int(header.point_count), file_crs, fields, lo - slack, hi + slack)
        return PointsHeader(path, fmt, int(header.point_count), file_crs, fields)
    if fmt == "ply":
        from lidarmap.io.ply import _binary_layout, ply_crs, read_ply_header

        header = read_ply_header(path)
        if header.fmt != "ascii":
            _binary_layout(header, path)  # a truncated file is refused before any work
        return PointsHeader(path, fmt, header.point_count, ply_crs(header, crs, path), header.fields)
    from lidarmap.io.xyz import text_crs, text_layout

    layout = text_layout(path, columns)
    return PointsHeader(path, fmt, None, text_crs(crs, path), [c for c in layout.columns if c != "_"])


def iter_points(path: str | Path, chunk_size: int = 2_000_000, crs: str | CRS | None = None,
                columns: str | None = None) -> Iterator[PointCloud]:
    """The points of any point file in chunks of at most ``chunk_size``, in file order."""
    fmt = point_format(path)
    if fmt == "las":
        from lidarmap.io.las import iter_las

        return iter_las(path, chunk_size, crs)
    if fmt == "ply":
        from lidarmap.io.ply import iter_ply

        return iter_ply(path, chunk_size, crs)
    from lidarmap.io.xyz import iter_text

    return iter_text(path, chunk_size, crs, columns)


def read_points(path: str | Path, crs: str | CRS | None = None, columns: str | None = None) -> PointCloud:
    """A whole point file in memory."""
    chunks = [c for c in iter_points(path, crs=crs, columns=columns) if len(c)]
    if not chunks:
        raise InputError("the point cloud is empty", path)
    return PointCloud.concatenate(chunks)


def measure_bounds(path: str | Path, chunk_size: int, crs: str | CRS | None = None,
                   columns: str | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """xy min, xy max and the number of points, by one streamed pass."""
    lo, hi, n = np.full(2, np.inf), np.full(2, -np.inf), 0
    for chunk in iter_points(path, chunk_size, crs, columns):
        if len(chunk):
            lo = np.minimum(lo, chunk.xyz[:, :2].min(axis=0))
            hi = np.maximum(hi, chunk.xyz[:, :2].max(axis=0))
            n += len(chunk)
    return lo, hi, n
