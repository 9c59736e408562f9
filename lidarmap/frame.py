"""Local coordinate frame: an offset (keeps float32 precision) and an optional rotation about z.

Projected coordinates such as UTM (x ~ 500000, y ~ 5e6) lose centimetres in float32. Every stage that works in
float32 (the networks) or wants axis-aligned buildings uses a :class:`LocalFrame`; it is stored with the outputs so that
results map back to the CRS exactly (in float64).
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class LocalFrame:
    """local = R(-rotation_deg) @ (crs - offset); crs = R(rotation_deg) @ local + offset."""

    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: float = 0.0

    @classmethod
    def around(cls, xyz: np.ndarray, rotation_deg: float = 0.0, step: float = 1.0) -> "LocalFrame":
        """A frame whose origin is the points' minimum corner, rounded down to ``step`` metres."""
        lo = np.floor(np.asarray(xyz, dtype=np.float64).min(axis=0) / step) * step
        return cls(offset=(float(lo[0]), float(lo[1]), float(lo[2])), rotation_deg=float(rotation_deg))

    def _rot(self) -> np.ndarray:
        a = math.radians(self.rotation_deg)
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        """CRS coordinates (N, 3) to local coordinates (float64)."""
        shifted = np.asarray(xyz, dtype=np.float64) - np.asarray(self.offset)
        return shifted if self.rotation_deg == 0.0 else shifted @ self._rot()

    def to_crs(self, local: np.ndarray) -> np.ndarray:
        """Local coordinates (N, 3) back to CRS coordinates (float64)."""
        local = np.asarray(local, dtype=np.float64)
        rotated = local if self.rotation_deg == 0.0 else local @ self._rot().T
        return rotated + np.asarray(self.offset)

    def to_json(self) -> str:
        return json.dumps({"offset": list(self.offset), "rotation_deg": self.rotation_deg})

    @classmethod
    def from_json(cls, text: str) -> "LocalFrame":
        data = json.loads(text)
        return cls(offset=tuple(float(v) for v in data["offset"]), rotation_deg=float(data["rotation_deg"]))
