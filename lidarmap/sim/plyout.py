"""The simulator's own PLY point writer (mobile campaigns as published data sets deliver them).

Kept apart from the production readers it is used to test: a plain header and one structured numpy record per
point (binary little endian) or one text row per point (ASCII). Coordinates and sensor origins are ``double``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: numpy kind+size -> PLY type name.
_TYPES = {"f8": "double", "f4": "float", "u1": "uchar", "i1": "char", "u2": "ushort", "i2": "short",
          "u4": "uint", "i4": "int"}


def write_points_ply(path: str | Path, columns: dict[str, np.ndarray], comments: list[str], binary: bool = True) -> Path:
    """Write ``columns`` (name -> (N,) array, in order; x, y, z first) as the vertex element of a PLY file; the file
    appears whole (written beside it, then renamed)."""
    path = Path(path)
    names = list(columns)
    n = len(columns[names[0]])
    dtype = np.dtype([(name, "<" + np.asarray(values).dtype.str[1:]) for name, values in columns.items()])
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
             *[f"comment {c}" for c in comments], f"element vertex {n}",
             *[f"property {_TYPES[dtype[name].str[1:]]} {name}" for name in names], "end_header"]
    header = ("\n".join(lines) + "\n").encode("ascii")
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(header)
        if binary:
            records = np.empty(n, dtype=dtype)
            for name in names:
                records[name] = columns[name]
            fh.write(records.tobytes())
        else:
            formats = " ".join("%.17g" if dtype[name].kind == "f" else "%d" for name in names)
            np.savetxt(fh, np.column_stack([np.asarray(columns[name], dtype=np.float64) for name in names]),
                       fmt=formats)
    os.replace(tmp, path)
    return path
