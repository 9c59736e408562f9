"""Rows of named columns grouped by an integer key, streamed in and read back key by key with bounded memory.

The scale-out stages stream their input once and need it again per building (``lidarmap run``: the points of each
footprint; ``map update``: the points of each spatial cell). :class:`ColumnSpool` buffers rows in memory and, past
``buffer_rows``, writes them to its folder as a *run*: one ``.npy`` per column with the rows sorted by key (stable),
plus the start of every key. Reading a key concatenates its rows from every run, in insertion order (one seek and
read per run), so memory holds one buffer plus what is read, never the whole input. Without a folder everything stays in
memory (small inputs, tests).

The columns are those given to the first :meth:`ColumnSpool.add`; a later add must give the same names with
castable values (:meth:`add` casts to the first dtypes). ``columns`` of a point cloud differ between tiles: the
caller normalises them (see :func:`lidarmap.aerial.prep.chunk_columns`).
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["ColumnSpool"]


class _Run:
    """One sorted batch of rows and per-key start offsets: column arrays in memory, or ``.npy`` files whose rows
    are read with a seek (not memory-mapped: mapped pages would count in the process's RSS until it ends)."""

    def __init__(self, columns: dict[str, np.ndarray | Path], starts: np.ndarray):
        self.columns = columns
        self.starts = starts  # (n_keys + 1,), rows of key k are starts[k]:starts[k + 1]
        self._layout: dict[str, tuple[int, np.dtype, tuple[int, ...]]] = {}

    def count(self, key: int) -> int:
        if key + 1 >= len(self.starts):
            return 0
        return int(self.starts[key + 1] - self.starts[key])

    def rows(self, key: int, name: str) -> np.ndarray:
        lo, hi = int(self.starts[key]), int(self.starts[key + 1])
        column = self.columns[name]
        if isinstance(column, np.ndarray):
            return column[lo:hi]
        if name not in self._layout:  # header only: the map is dropped before any data page is touched
            header = np.load(column, mmap_mode="r")
            self._layout[name] = (header.offset, header.dtype, header.shape[1:])
            del header
        start, dtype, tail = self._layout[name]
        with open(column, "rb") as fh:
            row = dtype.itemsize * int(np.prod(tail, dtype=np.int64))
            fh.seek(start + lo * row)
            return np.fromfile(fh, dtype=dtype, count=(hi - lo) * row // dtype.itemsize).reshape(-1, *tail)


class ColumnSpool:
    """Rows grouped by key (0 <= key < n_keys); see the module doc.

    ``folder`` (created; removed by :meth:`close`) holds the runs; ``None`` keeps them in memory.
    """

    def __init__(self, n_keys: int, folder: str | Path | None = None, buffer_rows: int = 2_000_000):
        if n_keys < 0:
            raise ValueError("n_keys must be >= 0")
        if buffer_rows < 1:
            raise ValueError("buffer_rows must be >= 1")
        self.n_keys = int(n_keys)
        self.folder = None if folder is None else Path(folder)
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
        self.buffer_rows = int(buffer_rows)
        self.dtypes: dict[str, np.dtype] = {}
        self.shapes: dict[str, tuple[int, ...]] = {}
        self._keys: list[np.ndarray] = []
        self._cols: list[dict[str, np.ndarray]] = []
        self._buffered = 0
        self._runs: list[_Run] = []
        self.counts = np.zeros(self.n_keys, dtype=np.int64)

    # ------------------------------------------------------------------------------------------------ writing
    def add(self, keys: np.ndarray, columns: dict[str, np.ndarray]) -> None:
        """Append rows: ``keys`` (N,) and every column (N, ...)."""
        keys = np.asarray(keys, dtype=np.int64)
        if not len(keys):
            return
        if not self.dtypes:
            self.dtypes = {k: np.asarray(v).dtype for k, v in columns.items()}
            self.shapes = {k: np.asarray(v).shape[1:] for k, v in columns.items()}
        if set(columns) != set(self.dtypes):
            raise ValueError(f"spool columns {sorted(columns)} differ from {sorted(self.dtypes)}")
        if keys.min() < 0 or keys.max() >= self.n_keys:
            raise ValueError("spool key out of range")
        cols = {k: np.asarray(columns[k]).astype(self.dtypes[k], copy=False) for k in self.dtypes}
        if any(len(v) != len(keys) for v in cols.values()):
            raise ValueError("every spool column needs one row per key")
        self._keys.append(keys)
        self._cols.append(cols)
        self._buffered += len(keys)
        self.counts += np.bincount(keys, minlength=self.n_keys)
        if self._buffered >= self.buffer_rows:
            self.flush()

    def flush(self) -> None:
        """Turn the buffered rows into a run (written to the folder when there is one)."""
        if not self._keys:
            return
        keys = np.concatenate(self._keys)
        order = np.argsort(keys, kind="stable")
        starts = np.concatenate([[0], np.cumsum(np.bincount(keys, minlength=self.n_keys))]).astype(np.int64)
        columns = {k: np.concatenate([c[k] for c in self._cols])[order] for k in self.dtypes}
        self._keys, self._cols, self._buffered = [], [], 0
        if self.folder is not None:
            where = self.folder / f"run{len(self._runs):05d}"
            where.mkdir()
            for name, values in columns.items():
                np.save(where / f"{name}.npy", values)
            columns = {name: where / f"{name}.npy" for name in self.dtypes}
        self._runs.append(_Run(columns, starts))

    # ------------------------------------------------------------------------------------------------ reading
    @property
    def names(self) -> list[str]:
        return list(self.dtypes)

    def get(self, key: int, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """Every row of ``key`` (in insertion order), as fresh in-memory arrays."""
        return self.get_many([key], names)

    def get_many(self, keys: Sequence[int], names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """The rows of several keys: key after key (in the order given), each in insertion order."""
        self.flush()
        names = list(self.dtypes) if names is None else list(names)
        out: dict[str, np.ndarray] = {}
        for name in names:
            parts = [run.rows(int(k), name) for k in keys for run in self._runs if run.count(int(k))]
            empty = np.zeros((0, *self.shapes.get(name, ())), dtype=self.dtypes.get(name, np.float64))
            out[name] = np.concatenate(parts) if parts else empty
        return out

    def close(self) -> None:
        """Drop the runs and remove the folder."""
        self._runs, self._keys, self._cols = [], [], []
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> "ColumnSpool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
