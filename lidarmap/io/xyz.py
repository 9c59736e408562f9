"""Text point clouds: XYZ / TXT / CSV / PTS, one point per row, streamed in blocks of rows.

The columns come from, in this order:

1. a column spec (``--columns x,y,z,intensity,gps_time``): one name per value in a row, ``_`` skips a column; names
   follow :func:`lidarmap.io.ply.field_name` (``GPSTime`` -> ``gps_time``, ``x_origin`` ... are sensor origins);
2. a header line (the first row, when any of its values is not a number): the same names;
3. the number of values in a row: 3 -> ``x,y,z``; 4 -> ``x,y,z,intensity``; 6 -> ``x,y,z,red,green,blue``;
   7 -> ``x,y,z,intensity,red,green,blue`` (Semantic3D); any other count needs a spec.

Values are separated by commas, semicolons or white space (detected on the first data row). Lines starting with
``#`` or ``//`` are comments. Coordinates are float64. A row with another number of values than the columns, a value
that is not a number, NaN coordinates, a spec without x, y, z: one-line :class:`~lidarmap.errors.InputError` naming
the file.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator
from pathlib import Path

from pyproj import CRS

from lidarmap.core import PointCloud
from lidarmap.errors import InputError
from lidarmap.io.crs import parse_crs
from lidarmap.io.ply import _cloud, _parse_rows, field_name

#: Rows per block when streaming.
CHUNK_POINTS = 2_000_000
SUFFIXES = (".xyz", ".txt", ".csv", ".pts", ".asc")
DEFAULT_COLUMNS = {3: "x,y,z", 4: "x,y,z,intensity", 6: "x,y,z,red,green,blue",
                   7: "x,y,z,intensity,red,green,blue"}
SKIP = "_"


@dataclasses.dataclass
class TextLayout:
    """Where a text cloud's columns are and what they hold."""

    columns: list[str]  # lidarmap names; "_" = skipped
    delimiter: str | None  # None: white space
    skip_lines: int  # header line(s) and leading comments before the first data row


def _is_comment(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith(("#", "//"))


def _split(line: str, delimiter: str | None) -> list[str]:
    return [w.strip() for w in (line.split(delimiter) if delimiter else line.split())]


def _numeric(words: list[str]) -> bool:
    try:
        [float(w) for w in words]
    except ValueError:
        return False
    return True


def parse_columns(spec: str, path: Path | None = None) -> list[str]:
    """``"x,y,z,GPSTime"`` -> lidarmap names; x, y and z must be there, once each."""
    names = [field_name(w) if w.strip() != SKIP else SKIP for w in spec.replace(" ", ",").split(",") if w.strip()]
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise InputError(f"column spec {spec!r} lacks {', '.join(missing)}", path)
    named = [n for n in names if n != SKIP]
    if len(set(named)) != len(named):
        raise InputError(f"column spec {spec!r} names a column twice", path)
    return names


def text_layout(path: str | Path, columns: str | None = None) -> TextLayout:
    """Read the first lines: delimiter, header, columns (see the module doc); the spec must fit the rows."""
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", path)
    if path.is_dir():
        raise InputError("is a folder, not a point file", path)
    skip, first = 0, None
    with path.open("r", encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if not _is_comment(line):
                first = line
                break
            skip += 1
        second = next((line for line in fh if not _is_comment(line)), None)
    if first is None:
        raise InputError("no points in the file", path)
    delimiter = "," if "," in first else (";" if ";" in first else None)
    words = _split(first, delimiter)
    header = None
    if not _numeric(words):
        header, skip = words, skip + 1
        if second is None:
            raise InputError("no points in the file (a header line only)", path)
        data_words = _split(second, delimiter)
    else:
        data_words = words
    if columns is not None:
        names = parse_columns(columns, path)
    elif header is not None:
        names = parse_columns(",".join(header), path)
    elif len(data_words) in DEFAULT_COLUMNS:
        names = parse_columns(DEFAULT_COLUMNS[len(data_words)], path)
    else:
        raise InputError(f"rows hold {len(data_words)} values and there is no header line: give the columns, e.g. "
                         f"--columns x,y,z,intensity,...", path)
    if len(names) != len(data_words):
        raise InputError(f"column spec names {len(names)} columns ({','.join(names)}) but rows hold "
                         f"{len(data_words)} values", path)
    return TextLayout(names, delimiter, skip)


def text_crs(user_crs: str | CRS | None, path: Path) -> CRS | None:
    """Text files carry no CRS: ``--crs`` gives it."""
    return parse_crs(user_crs, str(path))


def iter_text(path: str | Path, chunk_size: int = CHUNK_POINTS, crs: str | CRS | None = None,
              columns: str | None = None) -> Iterator[PointCloud]:
    """Stream a text cloud in chunks of at most ``chunk_size`` points (see the module doc for the columns)."""
    path = Path(path)
    layout = text_layout(path, columns)
    file_crs = text_crs(crs, path)
    seen = 0
    with path.open("rb") as fh:
        for _ in range(layout.skip_lines):
            fh.readline()
        while True:
            lines = list(itertools.islice(fh, chunk_size))
            if not lines:
                break
            table = _parse_rows(lines, len(layout.columns), path, seen, layout.delimiter, (b"#", b"//"))
            if not len(table):
                continue
            cols = {name: table[:, k] for k, name in enumerate(layout.columns) if name != SKIP}
            yield _cloud(cols, file_crs, path, seen)
            seen += len(table)
    if not seen:
        raise InputError("no points in the file", path)
