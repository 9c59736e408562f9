"""PLY point clouds as mobile-mapping data sets publish them (Paris-Lille-3D, Toronto-3D, KITTI-360 exports, ...).

Binary (little or big endian) and ASCII PLY; the ``vertex`` element's scalar properties become the points: ``x``,
``y``, ``z`` (any numeric type, kept as float64) and every other property as an attribute (:func:`field_name`
maps the usual spellings to lidarmap's names: ``scalar_Intensity`` -> ``intensity``, ``GPSTime`` -> ``gps_time``,
...). Binary files are streamed through a memory map with one structured dtype (no per-point Python); ASCII files
through ``numpy.loadtxt`` on blocks of lines. A header comment ``comment crs EPSG:N`` (or WKT) gives the CRS;
otherwise ``--crs``.

Every problem is an :class:`~lidarmap.errors.InputError` naming the file: no x/y/z, a count the data does not
hold (truncated or lying header), list properties in the vertex element, values that are not of their declared
type, NaN/inf coordinates.
"""

from __future__ import annotations

import dataclasses
import io
import itertools
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from pyproj import CRS

from lidarmap.core import STANDARD_ATTRS, PointCloud
from lidarmap.errors import InputError
from lidarmap.io.crs import parse_crs

#: Default number of points per chunk when streaming.
CHUNK_POINTS = 2_000_000
#: The header must end within this many bytes (a binary file without ``end_header`` is not PLY).
MAX_HEADER_BYTES = 1 << 20

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}

#: Usual property spellings of published data sets -> lidarmap attribute names (after lower-casing and dropping a
#: ``scalar_`` prefix, as CloudCompare writes them).
ALIASES = {
    "gpstime": "gps_time", "gps_time": "gps_time", "time": "gps_time", "timestamp": "gps_time",
    "reflectance": "intensity", "intensity": "intensity", "r": "red", "g": "green", "b": "blue",
    "scanangle": "scan_angle", "scanangle_rank": "scan_angle", "scan_angle_rank": "scan_angle",
    "returnnumber": "return_number", "numberofreturns": "number_of_returns",
    "pointsourceid": "point_source_id", "x_origin": "x_origin", "y_origin": "y_origin", "z_origin": "z_origin",
}
#: Per-point sensor origin fields (metres, the points' CRS): the pulse's origin, used as ray origin.
ORIGIN_FIELDS = ("x_origin", "y_origin", "z_origin")


def field_name(prop: str) -> str:
    """lidarmap's name of a PLY property or text column (``scalar_GPSTime`` -> ``gps_time``)."""
    key = prop.strip().lower()
    key = key.removeprefix("scalar_")
    return ALIASES.get(key, key)


@dataclasses.dataclass
class PlyElement:
    name: str
    count: int
    props: list[tuple[str, str]]  # (name, numpy type code)
    has_list: bool = False


@dataclasses.dataclass
class PlyHeader:
    """What a PLY header says: its format, elements, the vertex element's properties and where data starts."""

    fmt: str
    elements: list[PlyElement]
    data_offset: int
    comments: list[str]

    @property
    def vertex(self) -> PlyElement:
        return next(e for e in self.elements if e.name == "vertex")

    @property
    def point_count(self) -> int:
        return self.vertex.count

    @property
    def fields(self) -> list[str]:
        """lidarmap names of the vertex properties, in file order."""
        return [field_name(p) for p, _ in self.vertex.props]

    def dtype(self) -> np.dtype:
        order = FORMATS[self.fmt] or "<"
        return np.dtype([(p, order + t) for p, t in self.vertex.props])

    def crs_text(self) -> str | None:
        """The CRS a ``comment crs ...`` line declares."""
        for c in self.comments:
            if c.lower().startswith("crs "):
                return c[4:].strip()
        return None


def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputError("file not found", path)
    if path.is_dir():
        raise InputError("is a folder, not a PLY file", path)
    if path.stat().st_size == 0:
        raise InputError("empty file", path)


def read_ply_header(path: str | Path) -> PlyHeader:
    """Parse and check the header: one ``vertex`` element with scalar x, y, z; known types; a plausible size."""
    path = Path(path)
    _check_file(path)
    with path.open("rb") as fh:
        head = fh.read(MAX_HEADER_BYTES)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or no 'end_header' line)", path)
    newline = head.find(b"\n", end)
    if newline < 0:
        raise InputError("truncated PLY header (nothing after 'end_header')", path)
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements, comments = None, [], []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("obj_info",):
            continue
        if words[0] == "comment":
            comments.append(line.split(None, 1)[1] if len(words) > 1 else "")
        elif words[0] == "format":
            if len(words) < 2 or words[1] not in FORMATS:
                raise InputError(f"unknown PLY format {line.strip()!r}", path)
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"header line {number}: bad element line {line.strip()!r}", path)
            elements.append(PlyElement(words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"header line {number}: property before any element", path)
            _add_property(elements[-1], words, number, path)
        else:
            raise InputError(f"header line {number}: unknown keyword {words[0]!r}", path)
    header = PlyHeader(fmt or "", elements, newline + 1, comments)
    _check_header(header, path)
    return header


def _add_property(element: PlyElement, words: list[str], number: int, path: Path) -> None:
    if len(words) >= 2 and words[1] == "list":
        element.has_list = True
        element.props.append((words[-1], "list"))
        return
    if len(words) != 3 or words[1] not in PLY_TYPES:
        raise InputError(f"header line {number}: unknown property type in {' '.join(words)!r}", path)
    element.props.append((words[2], PLY_TYPES[words[1]]))


def _check_header(header: PlyHeader, path: Path) -> None:
    if not header.fmt:
        raise InputError("PLY header has no format line", path)
    if not any(e.name == "vertex" for e in header.elements):
        raise InputError("PLY file has no 'vertex' element", path)
    vertex = header.vertex
    if vertex.has_list:
        raise InputError("the vertex element has list properties; only scalar point properties are supported", path)
    names = [p for p, _ in vertex.props]
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise InputError(f"PLY vertex element lacks {', '.join(missing)} (properties: {', '.join(names) or 'none'})",
                         path)
    if len(set(names)) != len(names):
        raise InputError("PLY vertex element names a property twice", path)


def _binary_layout(header: PlyHeader, path: Path) -> tuple[int, np.dtype]:
    """Byte offset of the vertex data and its record dtype; the file must hold every promised vertex."""
    offset = header.data_offset
    for element in header.elements:
        if element.name == "vertex":
            break
        if element.has_list:
            raise InputError(f"element {element.name!r} with list properties comes before the vertices", path)
        offset += element.count * np.dtype([(p, t) for p, t in element.props]).itemsize
    dtype = header.dtype()
    size = path.stat().st_size
    count = header.point_count
    held = max(size - offset, 0) // dtype.itemsize
    if held < count:
        raise InputError(f"truncated: header promises {count} vertices, file holds {held}", path)
    after = header.elements[header.elements.index(header.vertex) + 1:]
    if not after and size > offset + count * dtype.itemsize:
        extra = size - offset - count * dtype.itemsize
        raise InputError(f"header says {count} vertices but the file holds {extra} more bytes after them "
                         f"(count wrong or data of another type)", path)
    return offset, dtype


def ply_crs(header: PlyHeader, user_crs: str | CRS | None, path: Path) -> CRS | None:
    """The file's ``comment crs`` or ``--crs`` (a conflict between them is an error)."""
    from lidarmap.io.las import resolve_crs

    text = header.crs_text()
    return resolve_crs(parse_crs(text, str(path)) if text else None, user_crs, path)


def _xyz(columns: dict[str, np.ndarray], records: np.ndarray | None) -> np.ndarray:
    """Coordinates (N, 3) float64: one strided copy when x, y, z are three adjacent doubles of the records."""
    if records is not None:
        from numpy.lib.recfunctions import structured_to_unstructured

        return np.ascontiguousarray(structured_to_unstructured(records[["x", "y", "z"]], dtype=np.float64))
    xyz = np.empty((len(columns["x"]), 3))
    for k, c in enumerate(("x", "y", "z")):
        xyz[:, k] = columns[c]
    return xyz


def _cloud(columns: dict[str, np.ndarray], crs: CRS | None, path: Path, first: int,
           records: np.ndarray | None = None) -> PointCloud:
    xyz = _xyz(columns, records)
    if not np.all(np.isfinite(xyz)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(xyz), axis=1))[0])
        raise InputError(f"NaN or infinite coordinates (point {first + bad})", path)
    attrs: dict[str, np.ndarray] = {}
    extra: list[str] = []
    for prop, values in columns.items():
        if prop in ("x", "y", "z"):
            continue
        name = field_name(prop)
        if name in STANDARD_ATTRS and _fits(name, values):
            attrs[name] = np.asarray(values).astype(STANDARD_ATTRS[name], copy=False)
        else:  # not a standard attribute, or values that do not fit its type (Semantic3D's signed intensity)
            name = name if name not in STANDARD_ATTRS else f"{name}_raw"
            attrs[name] = np.array(values, dtype=np.float64 if name in ORIGIN_FIELDS else values.dtype.newbyteorder("="))
            extra.append(name)
    return PointCloud(xyz=xyz, attrs=attrs, crs=crs, extra_dims=extra, source=str(path))


def _fits(name: str, values: np.ndarray) -> bool:
    """Whether the values fit lidarmap's dtype of a standard attribute (integers in range)."""
    dtype = STANDARD_ATTRS[name]
    if dtype.kind not in "ui" or not len(values) or np.can_cast(values.dtype, dtype):
        return True
    if values.dtype.kind == "f" and (not np.all(np.isfinite(values)) or np.any(values != np.round(values))):
        return False
    info = np.iinfo(dtype)
    return bool(values.min() >= info.min and values.max() <= info.max)


def iter_ply(path: str | Path, chunk_size: int = CHUNK_POINTS, crs: str | CRS | None = None,
             fields: list[str] | None = None) -> Iterator[PointCloud]:
    """Stream the vertices of a PLY file in chunks of at most ``chunk_size`` points.

    ``fields`` (PLY property names) limits the attributes read (x, y, z always).
    """
    path = Path(path)
    header = read_ply_header(path)
    file_crs = ply_crs(header, crs, path)
    keep = [p for p, _ in header.vertex.props if fields is None or p in ("x", "y", "z") or p in fields]
    if header.fmt == "ascii":
        yield from _iter_ascii(path, header, chunk_size, file_crs, keep)
        return
    offset, dtype = _binary_layout(header, path)
    count = header.point_count
    if count == 0:
        return
    records = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(count,))
    for first in range(0, count, chunk_size):
        part = records[first:first + chunk_size]
        yield _cloud({p: part[p] for p in keep}, file_crs, path, first, part)


def _iter_ascii(path: Path, header: PlyHeader, chunk_size: int, crs: CRS | None,
                keep: list[str]) -> Iterator[PointCloud]:
    """ASCII vertices, block by block; every row must hold one number per property, of its declared type."""
    if header.elements[0].name != "vertex":
        raise InputError("ASCII PLY with elements before the vertices is not supported", path)
    props = header.vertex.props
    count = header.point_count
    seen = 0
    with path.open("rb") as fh:
        fh.seek(header.data_offset)
        while seen < count:
            lines = list(itertools.islice(fh, min(chunk_size, count - seen)))
            if not lines:
                break
            table = _parse_rows(lines, len(props), path, first=seen)
            if not len(table):
                continue
            columns = {p: _typed(table[:, k], t, p, path, seen) for k, (p, t) in enumerate(props) if p in keep}
            yield _cloud(columns, crs, path, seen)
            seen += len(table)
        if seen < count:
            raise InputError(f"truncated: header promises {count} vertices, file holds {seen}", path)
        if len(header.elements) == 1 and any(line.strip() for line in fh):
            raise InputError(f"header says {count} vertices but the file holds more rows", path)


def _parse_rows(lines: list[bytes], n_cols: int, path: Path, first: int, delimiter: str | None = None,
                comments: tuple[bytes, ...] = ()) -> np.ndarray:
    """Rows of numbers (float64), one-line errors for a row with another number of values or a non-number.

    Fast path: the block parsed as one run of numbers (``numpy.fromstring``), accepted when it holds exactly
    ``n_cols`` numbers per line; otherwise (blank or comment lines, a bad row) ``numpy.loadtxt`` on the data lines,
    which names what is wrong."""
    block = b"".join(lines)
    if delimiter:
        block = block.replace(delimiter.encode(), b" ")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            flat = np.fromstring(block, sep=" ")
        if flat.size == len(lines) * n_cols:
            return flat.reshape(len(lines), n_cols)
    except (ValueError, DeprecationWarning):
        pass
    lines = [line for line in lines if line.strip() and not line.lstrip().startswith(comments or (b"\0",))]
    if not lines:
        return np.zeros((0, n_cols))
    try:
        table = np.loadtxt(io.BytesIO(b"".join(lines)), dtype=np.float64, ndmin=2, delimiter=delimiter,
                           comments=None)
    except ValueError as exc:
        text = " ".join(str(exc).split())[:120]
        raise InputError(f"unreadable value in rows {first + 1}-{first + len(lines)} ({text}): every column must "
                         f"hold numbers", path) from None
    if table.shape[1] != n_cols:
        raise InputError(f"rows have {table.shape[1]} values but {n_cols} columns are declared", path)
    return table


def _typed(values: np.ndarray, code: str, prop: str, path: Path, first: int) -> np.ndarray:
    """An ASCII column as its declared type: integer columns must hold integers (mixed types are an error)."""
    dtype = np.dtype(code)
    if dtype.kind in "ui":
        bad = ~np.isfinite(values) | (values != np.round(values))
        if bad.any():
            row = first + int(np.flatnonzero(bad)[0]) + 1
            raise InputError(f"mixed types: property {prop!r} is declared {dtype.name} but vertex {row} holds "
                             f"{float(values[bad][0]):g}", path)
        info = np.iinfo(dtype)
        if values.min() < info.min or values.max() > info.max:
            raise InputError(f"property {prop!r} holds values outside the {dtype.name} range", path)
    return values.astype(dtype)
