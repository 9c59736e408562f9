"""Per-point input features, built by ONE code path for training and for inference.

Two steps, both used unchanged by training (:mod:`lidarmap.segment.blocks`) and prediction
(:mod:`lidarmap.segment.predict`):

* :func:`point_features` -- block-independent values per point, once per file: coordinates in metres in a local
  frame, height above ground, robustly normalised intensity, return flags, local shape at full density
  (planarity, scattering, verticality, roughness of the ``geometry_k`` nearest neighbours: the network sees a
  subsample of each block, so fine roughness -- tree crowns against roofs -- would be lost otherwise), colour
  (+ presence flag).
* :func:`block_input` -- the network input of one block: block-centred xyz (metres, for neighbourhoods) and the
  channel matrix ``[x, y, z (block-centred / half block), hag, intensity, returns..., shape..., (rgb,
  rgb_present)]``.

The :class:`FeatureSpec` lists the channels and every parameter that changes them; it is stored in the model file
and a model whose spec differs from what this code computes is refused (:func:`check_spec`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from lidarmap.core import PointCloud
from lidarmap.errors import LidarmapError
from lidarmap.frame import LocalFrame
from lidarmap.segment.ground import GroundGrid, estimate_ground, ground_from_points

#: Bumped whenever the meaning of a channel changes; models made with another version are refused.
FEATURE_VERSION = 2
GROUND_CLASS = 2
BUILDING_CLASS = 6
#: Classes that carry no label: excluded from the loss and from scores.
UNLABELLED_CLASSES = (0, 1)
#: Neighbourhood features of :func:`eigen_features`, in column order.
EIGEN_NAMES = ("linearity", "planarity", "scattering", "verticality", "normal_z", "roughness", "z_range",
               "z_above_min", "kth_distance")
#: Points per KD-tree query batch of :func:`eigen_features` (bounded memory).
CHUNK = 100_000


class ModelSpecError(LidarmapError):
    """A model file whose feature spec or format does not fit this version of lidarmap."""


@dataclasses.dataclass(frozen=True)
class FeatureSpec:
    """What the network is fed; stored in the model file.

    version: feature code version (:data:`FEATURE_VERSION`).
    use_rgb: add red, green, blue (0..1 minus 0.5) and an ``rgb_present`` flag; files without colour, or with
        all-zero colour (IGN LiDAR HD), get zeros and flag 0.
    ground: ``"auto"`` = class 2 when the file has at least ``min_ground_points`` of them, else estimated;
        ``"estimate"`` = always the morphological filter.
    min_ground_points: class-2 points needed to trust the file's ground.
    ground_cell, ground_max_window, ground_slope, ground_threshold: grid cell (m), widest removed object (m),
        steepest kept terrain (m/m) and always-allowed step (m) of the ground filter (:mod:`.ground`).
    hag_scale: height above ground is divided by this (m) and clipped to [-1, 5].
    geometry_k: neighbours (at full density) of the shape channels; roughness (plane residual, m) is divided by
        ``roughness_scale`` and clipped to [0, 3].
    block_size: block edge (m); xyz channels are divided by half of it.
    """

    version: int = FEATURE_VERSION
    use_rgb: bool = False
    ground: str = "auto"
    min_ground_points: int = 500
    ground_cell: float = 1.0
    ground_max_window: float = 40.0
    ground_slope: float = 0.12
    ground_threshold: float = 0.4
    hag_scale: float = 10.0
    geometry_k: int = 16
    roughness_scale: float = 0.1
    block_size: float = 32.0

    def __post_init__(self) -> None:
        if self.ground not in ("auto", "estimate"):
            raise ValueError(f"ground must be 'auto' or 'estimate', not {self.ground!r}")

    @property
    def channels(self) -> list[str]:
        names = ["x", "y", "z", "hag", "intensity", "single_return", "last_return", "return_fraction",
                 "planarity", "scattering", "verticality", "roughness"]
        return names + (["red", "green", "blue", "rgb_present"] if self.use_rgb else [])

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "channels": self.channels}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FeatureSpec":
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in fields})


def check_spec(stored: dict[str, Any], source: str | None = None) -> FeatureSpec:
    """The spec a model was trained with, refused when this code would compute different channels."""
    version = stored.get("version")
    if version != FEATURE_VERSION:
        raise ModelSpecError(f"model was trained with feature spec version {version}; this lidarmap computes "
                             f"version {FEATURE_VERSION} (retrain with `lidarmap segment train`)", source)
    try:
        spec = FeatureSpec.from_dict(stored)
    except (TypeError, ValueError) as exc:
        raise ModelSpecError(f"invalid feature spec in model ({exc})", source) from None
    if list(stored.get("channels", [])) != spec.channels:
        raise ModelSpecError(f"model expects feature channels {stored.get('channels')} but this lidarmap computes "
                             f"{spec.channels}", source)
    return spec


@dataclasses.dataclass
class PointFeatures:
    """Block-independent per-point values of one cloud (see :func:`point_features`)."""

    xyz: np.ndarray  # float64 (N, 3), metres, in ``frame``
    ground_z: np.ndarray  # float64 (N,), ground height under each point, same frame
    values: np.ndarray  # float32 (N, C - 4): channels after x, y, z, hag
    frame: LocalFrame
    ground_source: str  # "class 2" or "estimated"
    channels: tuple[str, ...] = ()  # names of the columns of ``values`` (the spec's channels after x, y, z, hag)
    geometry_k: int = 0  # neighbours of the shape channels (the spec's geometry_k)

    def __len__(self) -> int:
        return len(self.xyz)


def metre_factors(cloud: PointCloud) -> np.ndarray:
    """Factors that turn the cloud's CRS units into metres (1 when the CRS is unknown: metres are assumed)."""
    crs = cloud.crs
    if crs is None:
        return np.ones(3)
    subs = crs.sub_crs_list if crs.is_compound and crs.sub_crs_list else [crs]
    horizontal = subs[0].axis_info[0].unit_conversion_factor if subs[0].axis_info else 1.0
    vertical = horizontal
    for sub in subs[1:]:
        if sub.is_vertical and sub.axis_info:
            vertical = sub.axis_info[0].unit_conversion_factor
    return np.array([horizontal, horizontal, vertical], dtype=np.float64)


def robust_unit(values: np.ndarray) -> np.ndarray:
    """Centre on the median and scale by the 5-95 % spread, clipped to [-3, 3]: comparable across sensors."""
    values = values.astype(np.float64)
    if len(values) == 0:
        return values.astype(np.float32)
    lo, mid, hi = np.percentile(values, [5, 50, 95])
    if hi - lo <= 0:
        return np.zeros(len(values), np.float32)
    return np.clip((values - mid) / (hi - lo), -3.0, 3.0).astype(np.float32)


def ground_grid(xyz: np.ndarray, classification: np.ndarray | None, spec: FeatureSpec) -> tuple[GroundGrid, str]:
    """The ground surface the features use, and where it came from."""
    if spec.ground == "auto" and classification is not None:
        is_ground = classification == GROUND_CLASS
        if is_ground.sum() >= spec.min_ground_points:
            return ground_from_points(xyz[is_ground, :2], xyz[is_ground, 2], spec.ground_cell), "class 2"
    grid = estimate_ground(xyz[:, :2], xyz[:, 2], spec.ground_cell, spec.ground_max_window, spec.ground_slope,
                           spec.ground_threshold)
    return grid, "estimated"


def _returns(cloud: PointCloud) -> np.ndarray:
    n = len(cloud)
    rn = cloud.attrs.get("return_number", np.ones(n, np.uint8)).astype(np.float32)
    nr = cloud.attrs.get("number_of_returns", np.ones(n, np.uint8)).astype(np.float32)
    rn, nr = np.maximum(rn, 1), np.maximum(nr, 1)  # 0 = unknown in some files: treat as a single return
    nr = np.maximum(nr, rn)
    return np.column_stack([nr == 1, rn == nr, rn / nr]).astype(np.float32)


def _colour(cloud: PointCloud) -> np.ndarray:
    rgb = cloud.rgb8()
    if rgb is None or not rgb.any():
        return np.zeros((len(cloud), 4), np.float32)
    return np.column_stack([rgb.astype(np.float32) / 255.0 - 0.5, np.ones(len(cloud), np.float32)])


def eigen_features(xyz: np.ndarray, k: int) -> np.ndarray:
    """(N, 9) neighbourhood features of every point among ``xyz`` (see :data:`EIGEN_NAMES`)."""
    k = min(k, len(xyz))
    tree = cKDTree(xyz)
    out = np.empty((len(xyz), len(EIGEN_NAMES)), np.float32)
    for start in range(0, len(xyz), CHUNK):
        query = xyz[start:start + CHUNK]
        dist, idx = tree.query(query, k=k, workers=-1)
        dist, idx = dist.reshape(len(query), k), idx.reshape(len(query), k)
        nb = xyz[idx]
        l1, l2, l3, normal_z = covariance_eigen(neighbourhood_covariance(nb, query))
        l1 = l1 + 1e-12
        z = np.ascontiguousarray(nb[..., 2])
        z_min = z.min(axis=1)
        block = out[start:start + CHUNK]  # written column by column: no (N, 9) float64 temporary
        block[:, 0] = (l1 - l2) / l1
        block[:, 1] = (l2 - l3) / l1
        block[:, 2] = l3 / l1
        block[:, 3] = 1.0 - normal_z
        block[:, 4] = normal_z
        block[:, 5] = np.sqrt(l3)
        block[:, 6] = z.max(axis=1) - z_min
        block[:, 7] = query[:, 2] - z_min
        block[:, 8] = dist[:, -1]
    return out


def neighbourhood_covariance(nb: np.ndarray, query: np.ndarray) -> np.ndarray:
    """(N, 6) covariance ``xx, yy, zz, xy, xz, yz`` of each neighbourhood ``nb`` (N, k, 3).

    Offsets from the query point keep the values small, so mean-of-products minus product-of-means loses nothing
    that matters (1e-15 m^2 against the centred product), at the cost of six sums instead of a batched 3x3 product.
    """
    d = nb - query[:, None, :]
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    mx, my, mz = x.mean(axis=1), y.mean(axis=1), z.mean(axis=1)
    return np.column_stack([(x * x).mean(axis=1) - mx * mx, (y * y).mean(axis=1) - my * my,
                            (z * z).mean(axis=1) - mz * mz, (x * y).mean(axis=1) - mx * my,
                            (x * z).mean(axis=1) - mx * mz, (y * z).mean(axis=1) - my * mz])


#: Eigenvalue gap (relative to the largest) under which the closed form's normal is not trusted and ``eigh`` decides.
EIGEN_GAP = 1e-6


def covariance_eigen(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues ``l1 >= l2 >= l3 >= 0`` and |z| of the smallest one's eigenvector of each (N, 6) covariance.

    Closed form (trigonometric solution of the characteristic cubic; the eigenvector as the longest cross product
    of two rows of ``A - l3 I``): five times faster than batched ``eigh`` and equal to it within 1e-12. Rows where
    the two smallest eigenvalues (nearly) coincide -- lines, single points -- have no well-defined normal in closed
    form; ``eigh`` answers for them.
    """
    xx, yy, zz, xy, xz, yz = cov.T
    mean = (xx + yy + zz) / 3.0
    bxx, byy, bzz = xx - mean, yy - mean, zz - mean
    p = (bxx * bxx + byy * byy + bzz * bzz + 2.0 * (xy * xy + xz * xz + yz * yz)) / 6.0
    det = bxx * (byy * bzz - yz * yz) - xy * (xy * bzz - yz * xz) + xz * (xy * yz - byy * xz)
    root = np.sqrt(p)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.arccos(np.clip(np.nan_to_num(det / (2.0 * p * root)), -1.0, 1.0)) / 3.0
    l1 = mean + 2.0 * root * np.cos(phi)
    l3 = mean + 2.0 * root * np.cos(phi + 2.0 * np.pi / 3.0)
    l2 = 3.0 * mean - l1 - l3
    rows = [np.column_stack([xx - l3, xy, xz]), np.column_stack([xy, yy - l3, yz]), np.column_stack([xz, yz, zz - l3])]
    crosses = [np.cross(rows[0], rows[1]), np.cross(rows[0], rows[2]), np.cross(rows[1], rows[2])]
    lengths = np.column_stack([(c * c).sum(axis=1) for c in crosses])
    best = lengths.argmax(axis=1)
    longest = lengths[np.arange(len(best)), best]
    with np.errstate(divide="ignore", invalid="ignore"):
        normal_z = np.abs(np.choose(best, [c[:, 2] for c in crosses])) / np.sqrt(longest)
    unsure = ~((l2 - l3) > EIGEN_GAP * np.abs(l1)) | ~np.isfinite(normal_z)
    if unsure.any():
        l1[unsure], l2[unsure], l3[unsure], normal_z[unsure] = covariance_eigen_eigh(cov[unsure])
    return np.maximum(l1, 0.0), np.maximum(l2, 0.0), np.maximum(l3, 0.0), normal_z


def covariance_eigen_eigh(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`covariance_eigen` by numpy's batched ``eigh`` (the general solver; slower, defined everywhere)."""
    values, vectors = np.linalg.eigh(cov[:, [0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(-1, 3, 3))  # ascending
    values = np.maximum(values, 0.0)
    return values[:, 2], values[:, 1], values[:, 0], np.abs(vectors[:, 2, 0])


def shape_channels(xyz: np.ndarray, spec: FeatureSpec) -> np.ndarray:
    """(N, 4) planarity, scattering, verticality and scaled roughness of each point's neighbourhood."""
    if len(xyz) < 3:
        return np.zeros((len(xyz), 4), np.float32)
    eig = eigen_features(xyz, spec.geometry_k)
    pick = [EIGEN_NAMES.index(n) for n in ("planarity", "scattering", "verticality", "roughness")]
    out = eig[:, pick]
    out[:, 3] = np.clip(out[:, 3] / spec.roughness_scale, 0.0, 3.0)
    return out


def point_features(cloud: PointCloud, spec: FeatureSpec) -> PointFeatures:
    """Block-independent features of every point of ``cloud`` (see the module doc)."""
    metres = cloud.xyz * metre_factors(cloud)
    frame = LocalFrame.around(metres) if len(cloud) else LocalFrame()
    xyz = frame.to_local(metres)
    grid, source = ground_grid(xyz, cloud.attrs.get("classification"), spec)
    ground_z = grid.height_at(xyz[:, :2])
    intensity = cloud.attrs.get("intensity")
    columns = [robust_unit(intensity) if intensity is not None else np.zeros(len(cloud), np.float32)]
    values = np.column_stack(columns + [_returns(cloud), shape_channels(xyz, spec)]
                             + ([_colour(cloud)] if spec.use_rgb else []))
    return PointFeatures(xyz, ground_z, values.astype(np.float32), frame, source, tuple(spec.channels[4:]),
                         spec.geometry_k)


#: An augmentation: (xyz_local float32 (P, 3), hag float32 (P,)) -> the same, transformed.
Transform = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def block_input(pf: PointFeatures, index: np.ndarray, centre: np.ndarray, spec: FeatureSpec,
                transform: Transform | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Network input of the points ``index`` of a block centred (x, y) at ``centre`` (frame metres).

    Returns block-centred xyz in metres (float32, z relative to the block's median ground) and the channel
    matrix (float32, ``spec.channels``). ``transform`` (training augmentation) acts on xyz and height above ground
    before the channels are assembled, so augmented and plain blocks go through the same code.
    """
    xyz = pf.xyz[index]
    ground = pf.ground_z[index]
    ref = np.array([centre[0], centre[1], np.median(ground) if len(ground) else 0.0])
    local = (xyz - ref).astype(np.float32)
    hag = (xyz[:, 2] - ground).astype(np.float32)
    if transform is not None:
        local, hag = transform(local, hag)
    half = np.float32(spec.block_size / 2)
    hag_channel = np.clip(hag / np.float32(spec.hag_scale), -1.0, 5.0)
    channels = np.column_stack([local / half, hag_channel, pf.values[index]]).astype(np.float32)
    return local, channels
