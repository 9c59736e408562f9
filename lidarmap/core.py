"""The in-memory point cloud that every stage passes around."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import shapely
from pyproj import CRS, Transformer

from lidarmap.errors import CRSError, InputError
from lidarmap.io.crs import horizontal_crs, parse_crs, same_crs

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
        if self.crs is not None and not isinstance(self.crs, CRS):
            self.crs = parse_crs(self.crs, self.source)  # "EPSG:28992", a WKT, an EPSG code: what users pass
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


@dataclasses.dataclass
class Footprints:
    """Footprint polygons (shapely, in ``crs``) with their ids and original properties; ``rejected`` (id -> reason)
    lists the features of the file that gave no usable polygon, ``repaired`` the ids of invalid polygons repaired."""

    ids: list[str]
    polygons: np.ndarray  # object array of shapely Polygon/MultiPolygon
    properties: list[dict[str, Any]]
    crs: CRS
    source: str | None = None
    rejected: dict[str, str] = dataclasses.field(default_factory=dict)
    repaired: list[str] = dataclasses.field(default_factory=list)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(shapely.total_bounds(self.polygons))  # type: ignore[return-value]

    def meets(self, bounds: tuple[float, float, float, float], margin: float = 0.0) -> bool:
        """Whether the footprints' bounding box overlaps the box ``bounds`` (x0, y0, x1, y1) grown by ``margin``."""
        fx0, fy0, fx1, fy1 = self.bounds
        x0, y0, x1, y1 = bounds
        return fx1 >= x0 - margin and fx0 <= x1 + margin and fy1 >= y0 - margin and fy0 <= y1 + margin

    def subset(self, index: np.ndarray) -> "Footprints":
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        return dataclasses.replace(self, ids=[self.ids[i] for i in index], polygons=self.polygons[index],
                                   properties=[self.properties[i] for i in index])

    def to_crs(self, crs: CRS) -> "Footprints":
        """The same footprints reprojected to ``crs`` (2D, always x=easting/lon, y=northing/lat)."""
        target = horizontal_crs(crs)
        if same_crs(self.crs, target):
            return self
        transformer = Transformer.from_crs(self.crs, target, always_xy=True)

        def project(coords: np.ndarray) -> np.ndarray:
            x, y = transformer.transform(coords[:, 0], coords[:, 1])
            return np.column_stack([x, y])

        polygons = shapely.transform(self.polygons, project)
        if not np.all(np.isfinite(shapely.total_bounds(polygons))):
            raise CRSError(f"footprints cannot be reprojected to {target.name!r}", self.source)
        return dataclasses.replace(self, polygons=polygons, crs=target)


@dataclasses.dataclass
class Trajectory:
    """Sensor positions (CRS) over GPS time; ``rpy`` are roll, pitch, yaw in radians when known."""

    time: np.ndarray
    xyz: np.ndarray
    rpy: np.ndarray | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=np.float64)
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        if self.rpy is not None:
            self.rpy = np.asarray(self.rpy, dtype=np.float64).reshape(-1, 3)

    def __len__(self) -> int:
        return len(self.time)

    def position_at(self, t: np.ndarray, tolerance: float = 0.05) -> np.ndarray:
        """Sensor positions (M, 3) at GPS times ``t`` by linear interpolation.

        Times more than ``tolerance`` seconds outside the trajectory are an error: extrapolating a vehicle's path
        would silently put the sensor in the wrong place.
        """
        t = np.asarray(t, dtype=np.float64)
        if t.size:
            self.check_covers(float(t.min()), float(t.max()), self.count_outside(t, tolerance))
        return np.column_stack([np.interp(t, self.time, self.xyz[:, k]) for k in range(3)])

    def count_outside(self, t: np.ndarray, tolerance: float = 0.05) -> int:
        """How many of the times ``t`` lie more than ``tolerance`` seconds outside the trajectory."""
        t = np.asarray(t, dtype=np.float64)
        return int(np.count_nonzero((t < self.time[0] - tolerance) | (t > self.time[-1] + tolerance)))

    def check_covers(self, t_min: float, t_max: float, outside: int) -> None:
        """Refuse point times in [t_min, t_max] of which ``outside`` lie outside the trajectory (InputError naming
        the trajectory file); a streamed campaign counts them chunk by chunk and calls this once."""
        if outside:
            raise InputError(
                f"{outside} point time(s) in [{t_min:.3f}, {t_max:.3f}] lie outside the trajectory's "
                f"[{self.time[0]:.3f}, {self.time[-1]:.3f}]", self.source)


#: Colours of voxels without RGB, by rank of their label among the grid's distinct labels (tab10).
LABEL_PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                          [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)


@dataclasses.dataclass
class VoxelGrid:
    """Occupied voxels of a regular grid in a CRS.

    origin: (3,) float64 CRS coordinates of voxel (0, 0, 0)'s minimum corner.
    size: voxel edge length (CRS units).
    ijk: (M, 3) int64 voxel indices, unique, sorted lexicographically by (i, j, k); voxel (i, j, k) is the half-open
        box ``origin + [i, i+1) x [j, j+1) x [k, k+1) * size``.
    label: (M,) int32 label of each voxel (the majority label of its points; 1 when no labels were given).
    rgb: (M, 3) uint8 mean colour, or None.
    count: (M,) int64 number of points in each voxel.
    crs_wkt: the CRS as WKT, or None when unknown.
    """

    origin: np.ndarray
    size: float
    ijk: np.ndarray
    label: np.ndarray
    rgb: np.ndarray | None
    count: np.ndarray
    crs_wkt: str | None = None

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.size = float(self.size)
        self.ijk = np.asarray(self.ijk, dtype=np.int64).reshape(-1, 3)
        m = len(self.ijk)
        self.label = np.asarray(self.label, dtype=np.int32).reshape(m)
        self.count = np.asarray(self.count, dtype=np.int64).reshape(m)
        if self.rgb is not None:
            self.rgb = np.asarray(self.rgb, dtype=np.uint8).reshape(m, 3)
        if not (math.isfinite(self.size) and self.size > 0) or not np.isfinite(self.origin).all():
            raise ValueError("voxel grid: size must be > 0 and the origin finite")

    def __len__(self) -> int:
        return len(self.ijk)

    @property
    def crs(self) -> CRS | None:
        return None if self.crs_wkt is None else CRS.from_wkt(self.crs_wkt)

    def centers(self) -> np.ndarray:
        """(M, 3) float64 CRS coordinates of the voxel centres."""
        return self.origin + (self.ijk + 0.5) * self.size

    def corners(self) -> np.ndarray:
        """(M, 3) float64 CRS coordinates of the voxel minimum corners."""
        return self.origin + self.ijk * self.size

    def subset(self, index: np.ndarray) -> "VoxelGrid":
        """The voxels selected by a boolean mask or an index array (order kept)."""
        return dataclasses.replace(self, ijk=self.ijk[index], label=self.label[index], count=self.count[index],
                                   rgb=None if self.rgb is None else self.rgb[index])

    def colours(self) -> np.ndarray:
        """(M, 3) uint8 display colours: the voxel RGB, else a colour per label (:func:`label_colours`)."""
        return self.rgb if self.rgb is not None else label_colours(self.label)


def label_colours(labels: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 colour per voxel from its label: the k-th smallest distinct label gets palette colour k."""
    values, rank = np.unique(np.asarray(labels), return_inverse=True)
    return LABEL_PALETTE[rank.reshape(-1) % len(LABEL_PALETTE)]


#: Corners of the unit cube (x, y, z) and its six faces as corner indices, counter-clockwise seen from outside.
CUBE_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])


CUBE_QUADS = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])
