"""Deterministic ``.npz`` files: the same arrays give the same bytes (numpy's writer stamps the current time)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from lidarmap.io.atomic import atomic_path

#: Zip member timestamp of every file we write (the earliest a zip file can hold).
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def write_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Compressed ``.npz`` readable by ``numpy.load``, byte-identical for identical arrays; written atomically."""
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for name, value in arrays.items():
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
                info = zipfile.ZipInfo(f"{name}.npy", date_time=ZIP_EPOCH)
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())
    return Path(path)
