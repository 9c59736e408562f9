"""The in-memory point cloud that every stage passes around."""

from __future__ import annotations

import dataclasses

import numpy as np
from pyproj import CRS

#: Standard per-point attributes, by laspy dimension name, with the dtype lidarmap keeps them in.
STANDARD_ATTRS: dict[str, np.dtype] = {
    "intensity": np.dtype(np.uint16),
    "return_number": np.dtype(np.uint8),
    "number_of_returns": np.dtype(np.uint8),
    "classification": np.dtype(np.uint8),
    "synthetic": np.dtype(np.uint8),  # the LAS "synthetic" flag: 1 = created by processing (e.g. densification)
    "scan_angle": np.dtype(np.float32),  # degrees, whatever the point format stores
    "user_data": np.dtype(np.uint8),
    "point_source_id": np.dtype(np.uint16),
    "gps_time": np.dtype(np.float64),
    "red": np.dtype(np.uint16),
    "green": np.dtype(np.uint16),
    "blue": np.dtype(np.uint16),
    "nir": np.dtype(np.uint16),
}


@dataclasses.dataclass
class PointCloud:
    """Points in a CRS with their attributes.

    ``xyz`` is float64 (N, 3) in CRS units. ``attrs`` maps attribute names to (N,) arrays: the standard LAS
    dimensions present in the source (names as in :data:`STANDARD_ATTRS`) plus any extra dimensions, listed in
    ``extra_dims``. ``crs`` is ``None`` when unknown.
    """

    xyz: np.ndarray
    attrs: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    crs: CRS | None = None
    extra_dims: list[str] = dataclasses.field(default_factory=list)
    source: str | None = None

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.xyz)
        for name, values in self.attrs.items():
            if len(values) != n:
                raise ValueError(f"attribute {name!r} has {len(values)} values for {n} points")

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def has_rgb(self) -> bool:
        return all(c in self.attrs for c in ("red", "green", "blue"))

    def rgb8(self) -> np.ndarray | None:
        """Colour as uint8 (N, 3), quantised from 16 bits when the values need it; ``None`` without colour."""
        if not self.has_rgb:
            return None
        rgb = np.stack([self.attrs[c] for c in ("red", "green", "blue")], axis=1)
        if rgb.size and rgb.max() > 255:
            return (rgb // 257).astype(np.uint8)  # 65535 -> 255 exactly
        return rgb.astype(np.uint8)

    def subset(self, index: np.ndarray) -> "PointCloud":
        """A new cloud with the points selected by a boolean mask or an index array (attributes follow)."""
        return PointCloud(
            xyz=self.xyz[index],
            attrs={k: v[index] for k, v in self.attrs.items()},
            crs=self.crs,
            extra_dims=list(self.extra_dims),
            source=self.source,
        )

    @classmethod
    def concatenate(cls, clouds: list["PointCloud"]) -> "PointCloud":
        """Join clouds that share a CRS; attributes missing from some clouds are dropped."""
        if not clouds:
            raise ValueError("nothing to concatenate")
        common = set(clouds[0].attrs)
        for c in clouds[1:]:
            common &= set(c.attrs)
        extra = [d for d in clouds[0].extra_dims if d in common]
        return cls(
            xyz=np.concatenate([c.xyz for c in clouds]),
            attrs={k: np.concatenate([c.attrs[k] for c in clouds]) for k in clouds[0].attrs if k in common},
            crs=clouds[0].crs,
            extra_dims=extra,
            source=clouds[0].source,
        )
