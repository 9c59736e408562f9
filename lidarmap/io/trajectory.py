"""Vehicle trajectories: CSV ``time,x,y,z[,roll,pitch,yaw]`` and sensor positions at any GPS time."""

from __future__ import annotations

import csv
import io
import logging
from pathlib import Path

import numpy as np

from lidarmap.core import Trajectory
from lidarmap.errors import InputError
from lidarmap.io.atomic import write_text_atomic

log = logging.getLogger(__name__)

REQUIRED = ("time", "x", "y", "z")
#: Default longest hole (s) between trajectory rows interpolated without a warning (``[update] trajectory_warn_gap``).
WARN_GAP_S = 1.0
#: Default longest hole (s) between trajectory rows accepted at all (``[update] trajectory_max_gap``): positions
#: interpolated over half a minute of driving are guesses, and the façades seen then would be misplaced.
MAX_GAP_S = 30.0
ANGLES = ("roll", "pitch", "yaw")


def read_trajectory(path: str | Path, warn_gap: float = WARN_GAP_S, max_gap: float = MAX_GAP_S) -> Trajectory:
    """Read a trajectory CSV (header row required; extra columns are ignored); validated.

    A hole between two rows longer than ``warn_gap`` seconds is interpolated with a warning (one log line naming the
    file); one longer than ``max_gap`` is refused.
    """
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
    _check_gaps(time, warn_gap, max_gap, path)
    xyz = data[:, [cols.index(c) for c in ("x", "y", "z")]]
    rpy = data[:, [cols.index(c) for c in ANGLES]] if all(c in cols for c in ANGLES) else None
    return Trajectory(time=time, xyz=xyz, rpy=rpy, source=str(path))


def _check_gaps(time: np.ndarray, warn_gap: float, max_gap: float, path: Path) -> None:
    steps = np.diff(time)
    worst = int(np.argmax(steps))
    where = f"{steps[worst]:.1f} s hole in the trajectory after time {time[worst]:.3f}"
    if steps[worst] > max_gap:
        raise InputError(f"{where} (longest accepted: {max_gap:g} s, [update] trajectory_max_gap)", path)
    if steps[worst] > warn_gap:
        log.warning("%s: %s (%d hole(s) over %g s): positions there are interpolated", path, where,
                    int(np.sum(steps > warn_gap)), warn_gap)


def write_trajectory(path: str | Path, traj: Trajectory) -> Path:
    """Write a trajectory CSV atomically (full float precision)."""
    cols = list(REQUIRED) + (list(ANGLES) if traj.rpy is not None else [])
    data = np.column_stack([traj.time, traj.xyz] + ([traj.rpy] if traj.rpy is not None else []))
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in data]
    return write_text_atomic(path, "\n".join(lines) + "\n")
