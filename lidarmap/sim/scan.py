"""Traced returns to LiDAR points: range noise, intensity, colour, per-point truth; and conversion to a PointCloud."""

from __future__ import annotations

import dataclasses

import numpy as np

from lidarmap.core import PointCloud
from lidarmap.frame import LocalFrame
from lidarmap.sim.mesh import LABEL_FIELDS
from lidarmap.sim.raycast import Returns, Tracer


@dataclasses.dataclass
class Scan:
    """Simulated points in the local frame with LAS attributes and their truth (aligned, one row per point)."""

    xyz: np.ndarray
    gps_time: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    scan_angle: np.ndarray
    point_source_id: np.ndarray
    intensity: np.ndarray
    rgb: np.ndarray  # (N, 3) uint16
    classification: np.ndarray  # as delivered (not the truth)
    truth: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.xyz)

    @staticmethod
    def concatenate(scans: list["Scan"]) -> "Scan":
        fields = {f.name: np.concatenate([getattr(s, f.name) for s in scans])
                  for f in dataclasses.fields(Scan) if f.name != "truth"}
        truth = {k: np.concatenate([s.truth[k] for s in scans]) for k in LABEL_FIELDS}
        return Scan(truth=truth, **fields)

    def take(self, index: np.ndarray) -> Scan:
        """The points at ``index`` (in that order), truth included."""
        fields = {f.name: getattr(self, f.name)[index] for f in dataclasses.fields(Scan) if f.name != "truth"}
        return Scan(truth={k: v[index] for k, v in self.truth.items()}, **fields)

    def to_cloud(self, frame: LocalFrame, crs, transform=None) -> PointCloud:
        """A PointCloud in the CRS; ``transform`` (CRS points -> CRS points) applies a campaign's misregistration."""
        xyz = frame.to_crs(self.xyz)
        if transform is not None:
            xyz = transform(xyz)
        attrs = {
            "intensity": self.intensity, "return_number": self.return_number,
            "number_of_returns": self.number_of_returns, "classification": self.classification,
            "scan_angle": self.scan_angle.astype(np.float32), "point_source_id": self.point_source_id,
            "gps_time": self.gps_time, "red": self.rgb[:, 0], "green": self.rgb[:, 1], "blue": self.rgb[:, 2],
        }
        return PointCloud(xyz=xyz, attrs=attrs, crs=crs)


def optics(tracer: Tracer, ret: Returns, origins: np.ndarray, dirs: np.ndarray, rng: np.random.Generator,
           range_noise: float, times: np.ndarray, angle: np.ndarray, source_id: int) -> Scan:
    """Points of traced returns: noisy range along the pulse, intensity from reflectance and incidence, colour.

    Later returns of a pulse carry less energy (the leaves before them took their share).
    """
    scene = tracer.scene
    n = len(ret.ray)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    d = dirs[ret.ray]
    rng_noisy = ret.range + rng.normal(0.0, range_noise, n)
    xyz = origins[ret.ray] + rng_noisy[:, None] * d
    cos_inc = np.abs(np.einsum("ij,ij->i", tracer.normal[ret.tri], d))
    energy = scene.reflectance[ret.tri] * (0.25 + 0.75 * cos_inc) * 0.55 ** (ret.return_number.astype(float) - 1)
    intensity = np.clip(65535 * energy * (1 + rng.normal(0, 0.05, n)), 0, 65535).astype(np.uint16)
    rgb8 = np.clip(scene.rgb[ret.tri] + rng.normal(0, 6.0, (n, 3)), 0, 255)
    rgb = (np.round(rgb8) * 257).astype(np.uint16)
    truth = {"classification": scene.classification[ret.tri], "building_id": scene.building_id[ret.tri],
             "facade_id": scene.facade_id[ret.tri], "element_id": scene.element_id[ret.tri],
             "kind": scene.kind[ret.tri]}
    return Scan(xyz=xyz, gps_time=times[ret.ray], return_number=ret.return_number,
                number_of_returns=ret.number_of_returns, scan_angle=angle[ret.ray].astype(np.float32),
                point_source_id=np.full(n, source_id, np.uint16), intensity=intensity, rgb=rgb,
                classification=scene.classification[ret.tri].copy(), truth=truth)
