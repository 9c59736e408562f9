"""Vehicle trajectories: CSV ``time,x,y,z[,roll,pitch,yaw]`` and sensor positions at any GPS time."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from lidarmap.core import Trajectory
from lidarmap.errors import InputError
from lidarmap.io.atomic import write_text_atomic

REQUIRED = ("time", "x", "y", "z")
ANGLES = ("roll", "pitch", "yaw")


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory CSV (header row required; extra columns are ignored); validated."""
    path = Path(path)
    if not path.exists():
        raise InputError("file not found", path)
    text = path.read_text(encoding="utf-8", errors="replace")
    if not text.strip():
        raise InputError("empty trajectory file", path)
    rows = list(csv.reader(io.StringIO(text)))
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise InputError(f"trajectory CSV lacks column(s) {', '.join(missing)} (header: {','.join(header)})", path)
    body = [r for r in rows[1:] if r and any(cell.strip() for cell in r)]
    if len(body) < 2:
        raise InputError("trajectory needs at least two rows", path)
    try:
        data = np.array([[float(r[header.index(c)]) for c in header if c in REQUIRED + ANGLES] for r in body])
    except (ValueError, IndexError) as exc:
        raise InputError(f"unreadable trajectory row ({exc})", path) from None
    cols = [c for c in header if c in REQUIRED + ANGLES]
    if not np.all(np.isfinite(data)):
        raise InputError("NaN or infinite values in trajectory", path)
    time = data[:, cols.index("time")]
    if np.any(np.diff(time) <= 0):
        raise InputError("trajectory times are not strictly increasing", path)
    xyz = data[:, [cols.index(c) for c in ("x", "y", "z")]]
    rpy = data[:, [cols.index(c) for c in ANGLES]] if all(c in cols for c in ANGLES) else None
    return Trajectory(time=time, xyz=xyz, rpy=rpy, source=str(path))


def write_trajectory(path: str | Path, traj: Trajectory) -> Path:
    """Write a trajectory CSV atomically (full float precision)."""
    cols = list(REQUIRED) + (list(ANGLES) if traj.rpy is not None else [])
    data = np.column_stack([traj.time, traj.xyz] + ([traj.rpy] if traj.rpy is not None else []))
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in data]
    return write_text_atomic(path, "\n".join(lines) + "\n")
