"""LAS/LAZ reading (whole or in chunks), writing (LAS 1.4, atomic) and ``info`` summaries, with laspy + lazrs.

Every failure to read becomes an :class:`~lidarmap.errors.InputError` naming the file and the problem.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS

from lidarmap._version import __version__
from lidarmap.core import STANDARD_ATTRS, PointCloud
from lidarmap.errors import CRSError, InputError
from lidarmap.io.atomic import atomic_path
from lidarmap.io.crs import parse_crs, same_crs

#: Largest coordinate a header's scale and offset may reach (m or degrees): beyond any CRS on Earth.
MAX_COORDINATE = 1e12
#: Default number of points per chunk when streaming.
CHUNK_POINTS = 2_000_000
#: The header's "generating software" (32 bytes at most).
GENERATING_SOFTWARE = f"lidarmap {__version__}"[:32]
#: Extra dimensions lidarmap writes: LAS description (32 bytes at most) and no-data value (None: every value is data).
#: Names are spelled out (not imported from the stages) because io imports no stage.
EXTRA_DIMS: dict[str, tuple[str, float | int | None]] = {
    "plane_id": ("flatten plane id, -1: none", -1),
    "building_probability": ("P(building) from segmentation", None),
    "footprint_distance": ("m to the footprint, 0 inside", None),
}


def _open(path: Path) -> laspy.LasReader:
    if not path.exists():
        raise InputError("file not found", path)
    if path.is_dir():
        raise InputError("is a folder, not a LAS/LAZ file", path)
    if path.stat().st_size == 0:
        raise InputError("empty file", path)
    try:
        reader = laspy.open(path)
    except (laspy.errors.LaspyException, ValueError, OSError, EOFError) as exc:
        raise InputError(f"not a valid LAS/LAZ file ({_short(exc)})", path) from None
    header = reader.header
    try:
        _check_laz_chunk_table(path, header)
    except InputError:
        reader.close()
        raise
    if not (np.all(np.isfinite(header.scales)) and np.all(np.isfinite(header.offsets))):
        reader.close()
        raise InputError("header has NaN/inf scale or offset", path)
    if np.any(np.asarray(header.scales) == 0):
        reader.close()
        raise InputError("header has a zero scale factor", path)
    reach = max(abs(float(o)) + abs(float(s)) * 2.0**31 for o, s in zip(header.offsets, header.scales))
    if not reach < MAX_COORDINATE:  # Python floats: an absurd scale gives inf here, not numpy overflow warnings
        reader.close()
        raise InputError(f"header scale {list(map(float, header.scales))} / offset {list(map(float, header.offsets))} "
                         f"give coordinates beyond ±{MAX_COORDINATE:g} (damaged header?)", path)
    return reader


def _check_laz_chunk_table(path: Path, header: laspy.LasHeader) -> None:
    """Refuse a LAZ file whose chunk table cannot be right, before lazrs reads it.

    lazrs sizes its chunk table from the count stored in the file: a damaged count makes it allocate tens of GB and
    abort the whole process (no Python exception). A LAZ file stores, right after the header, the offset of the chunk
    table (-1: look in the file's last 8 bytes); the table starts with a version (0) and the number of chunks, which
    cannot exceed the number of points (nor, with fixed-size chunks, ceil(points / chunk size)).
    """
    vlr = next((v for v in header.vlrs if v.user_id == "laszip encoded" and v.record_id == 22204), None)
    if vlr is None:
        return  # not compressed
    size = path.stat().st_size
    points = int(header.point_count)
    with path.open("rb") as fh:
        fh.seek(header.offset_to_point_data)
        raw = fh.read(8)
        if len(raw) < 8:
            raise InputError("truncated LAZ file: no chunk table offset after the header", path)
        (table_at,) = struct.unpack("<q", raw)
        if table_at == -1:  # written by a streaming compressor: the offset is in the last 8 bytes
            fh.seek(size - 8)
            (table_at,) = struct.unpack("<q", fh.read(8))
        if not header.offset_to_point_data + 8 <= table_at <= size - 8:
            raise InputError(f"corrupt or truncated LAZ file: chunk table offset {table_at} lies outside the file "
                             f"({size} bytes)", path)
        fh.seek(table_at)
        version, chunks = struct.unpack("<II", fh.read(8))
    chunk_size = struct.unpack_from("<I", vlr.record_data_bytes(), 12)[0]
    most = points if chunk_size == 0xFFFFFFFF else -(-points // max(chunk_size, 1))
    if version != 0 or chunks > max(most, 1):
        raise InputError(f"corrupt LAZ file: chunk table (version {version}, {chunks} chunks) does not fit "
                         f"{points} points", path)


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:160]


def _file_crs(header: laspy.LasHeader, path: Path) -> CRS | None:
    try:
        return header.parse_crs()
    except Exception as exc:  # noqa: BLE001 - laspy/pyproj raise many kinds on broken CRS records
        raise CRSError(f"unreadable CRS record ({_short(exc)})", path) from None


def resolve_crs(file_crs: CRS | None, user_crs: str | CRS | None, path: Path) -> CRS | None:
    """The CRS to use: the file's, or ``--crs`` when the file has none; a conflict is an error."""
    user = parse_crs(user_crs, str(path))
    if user is None:
        return file_crs
    if file_crs is not None and not same_crs(file_crs, user):
        raise CRSError(f"file declares CRS {file_crs.name!r} but --crs is {user.name!r}", path)
    return file_crs or user


def _check_bounds(xyz: np.ndarray, header: laspy.LasHeader, path: Path) -> None:
    """Points far outside the header's bounding box mean corrupt point data (LAZ decodes garbage silently)."""
    if not len(xyz):
        return
    lo, hi = np.asarray(header.mins, dtype=np.float64), np.asarray(header.maxs, dtype=np.float64)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.all(lo == hi):
        return  # writers that leave the bounds unset: nothing to check against
    slack = (hi - lo) * 0.01 + np.asarray(header.scales) * 2
    bad = np.any((xyz < lo - slack) | (xyz > hi + slack), axis=1)
    if bad.any():
        raise InputError(f"corrupt point data: {int(bad.sum())} point(s) outside the header bounds", path)


def _points_to_cloud(points: laspy.ScaleAwarePointRecord, crs: CRS | None, path: Path,
                     header: laspy.LasHeader | None = None) -> PointCloud:
    xyz = np.column_stack([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)]).astype(np.float64)
    if not np.all(np.isfinite(xyz)):
        raise InputError("NaN or infinite coordinates", path)
    if header is not None:
        _check_bounds(xyz, header, path)
    names = set(points.point_format.dimension_names)
    attrs: dict[str, np.ndarray] = {}
    for name, dtype in STANDARD_ATTRS.items():
        if name == "scan_angle":
            continue
        if name in names:
            attrs[name] = np.asarray(points[name]).astype(dtype)
    if "scan_angle" in names:  # formats 6-10 store 0.006 degree units
        attrs["scan_angle"] = (np.asarray(points["scan_angle"], dtype=np.float32) * np.float32(0.006))
    elif "scan_angle_rank" in names:
        attrs["scan_angle"] = np.asarray(points["scan_angle_rank"], dtype=np.float32)
    extra = list(points.point_format.extra_dimension_names)
    for name in extra:
        attrs[name] = np.asarray(points[name])
    return PointCloud(xyz=xyz, attrs=attrs, crs=crs, extra_dims=extra, source=str(path))


def read_header(path: str | Path) -> laspy.LasHeader:
    """The header of a LAS/LAZ file (validated)."""
    path = Path(path)
    with _open(path) as reader:
        return reader.header


def read_header_crs(path: str | Path, crs: str | CRS | None = None) -> tuple[laspy.LasHeader, CRS | None]:
    """The validated header of a LAS/LAZ file and the CRS its points will have (:func:`resolve_crs`), without
    reading any point: what a streaming reader needs to know first."""
    path = Path(path)
    with _open(path) as reader:
        return reader.header, resolve_crs(_file_crs(reader.header, path), crs, path)


def read_las(path: str | Path, crs: str | CRS | None = None) -> PointCloud:
    """Read a whole LAS/LAZ file. ``crs`` sets the CRS when the file has none (a conflicting one is an error)."""
    return PointCloud.concatenate(list(iter_las(path, crs=crs))) if _count(path) else _empty(path, crs)


def _count(path: str | Path) -> int:
    return read_header(path).point_count


def _empty(path: str | Path, crs: str | CRS | None) -> PointCloud:
    path = Path(path)
    with _open(path) as reader:
        file_crs = resolve_crs(_file_crs(reader.header, path), crs, path)
        points = laspy.ScaleAwarePointRecord.zeros(0, header=reader.header)
        return _points_to_cloud(points, file_crs, path)


def iter_las(path: str | Path, chunk_size: int = CHUNK_POINTS, crs: str | CRS | None = None) -> Iterator[PointCloud]:
    """Stream a LAS/LAZ file in chunks of at most ``chunk_size`` points (bounded memory for any file size)."""
    path = Path(path)
    with _open(path) as reader:
        file_crs = resolve_crs(_file_crs(reader.header, path), crs, path)
        expected = reader.header.point_count
        seen = 0
        try:
            for points in reader.chunk_iterator(chunk_size):
                if len(points) == 0:
                    break
                seen += len(points)
                yield _points_to_cloud(points, file_crs, path, reader.header)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - lazrs/laspy raise various errors on corrupt data
            raise InputError(f"corrupt or truncated point data after {seen} points ({_short(exc)})", path) from None
        if seen < expected:
            raise InputError(f"truncated: header promises {expected} points, file holds {seen}", path)


def _point_format_for(cloud: PointCloud) -> int:
    if "nir" in cloud.attrs:
        return 8
    return 7 if cloud.has_rgb else 6


def _extra_bytes(name: str, dtype: np.dtype) -> laspy.ExtraBytesParams:
    """An extra dimension with its description and no-data value when lidarmap knows them (kept short: LAS allows
    32 bytes)."""
    description, no_data = EXTRA_DIMS.get(name, ("", None))
    return laspy.ExtraBytesParams(name=name, type=dtype, description=description,
                                  no_data=None if no_data is None else [no_data])


def _add_crs_wkt1(header: laspy.LasHeader, crs: CRS) -> None:
    """The CRS as an OGC WKT VLR in WKT1 (the LAS 1.4 spec cites OGC 01-009, WKT1; WKT2 when WKT1 cannot express
    it), which older GIS readers parse too."""
    wkt = crs.to_wkt("WKT1_GDAL") or crs.to_wkt()
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(wkt))
    header.global_encoding.wkt = True


def write_las(path: str | Path, cloud: PointCloud, scale: float = 0.001) -> Path:
    """Write LAS 1.4 (LAZ when the suffix is .laz) with the CRS record (WKT1) and described extra dimensions,
    atomically.

    Point format 6 (7 with RGB, 8 with NIR). Coordinates are stored at ``scale`` (default 1 mm).
    """
    path = Path(path)
    if not np.all(np.isfinite(cloud.xyz)):
        raise InputError("refusing to write NaN or infinite coordinates", path)
    header = laspy.LasHeader(point_format=_point_format_for(cloud), version="1.4")
    header.generating_software = GENERATING_SOFTWARE
    for name in cloud.extra_dims:
        header.add_extra_dim(_extra_bytes(name, cloud.attrs[name].dtype))
    lo = cloud.xyz.min(axis=0) if len(cloud) else np.zeros(3)
    header.offsets = np.floor(lo)
    header.scales = np.array([scale, scale, scale])
    if cloud.crs is not None:
        _add_crs_wkt1(header, cloud.crs)
    record = laspy.ScaleAwarePointRecord.zeros(len(cloud), header=header)
    record.x, record.y, record.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    for name, values in cloud.attrs.items():
        if name == "scan_angle":
            record["scan_angle"] = np.round(np.asarray(values, dtype=np.float64) / 0.006).astype(np.int16)
        elif name in record.point_format.dimension_names:
            record[name] = values
    compress = path.suffix.lower() == ".laz"
    with atomic_path(path) as tmp, laspy.open(tmp, mode="w", header=header, do_compress=compress) as writer:
        writer.write_points(record)
    return path
