"""Trees are not buildings: the tree-like rule (scoring, training labels) and the predict-time vegetation filter.

Two different tools, because they may use different information:

* :func:`tree_like` -- a rule on a LABELLED cloud, for scores and for training labels. A point is tree-like when it
  is unlabelled or high vegetation (class 1 or 5), belongs to a pulse with several returns (``number_of_returns >
  1``), lies more than ``min_height`` above the median height of its ``ground_neighbours`` nearest ground points
  (class 2) and more than ``building_clearance`` horizontally from every building point (class 6). In AHN3, class 1
  is where the trees are; the clearance keeps unlabelled walls and roof edges out of the count.
* :func:`vegetation_filter` -- what ``segment predict`` can use on an UNLABELLED cloud, after the network: among the
  points the model calls building, those in a porous, scattered neighbourhood (most points of the neighbourhood
  belong to multi-return pulses, the neighbourhood is not planar) well above the ground. Roof edges also give
  multi-return pulses, but their neighbourhood is mostly single returns on a plane; tree crowns are neither.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from lidarmap.config import check_params
from lidarmap.core import PointCloud
from lidarmap.segment.features import BUILDING_CLASS, GROUND_CLASS

#: Classes a tree-like point may carry: 1 (unclassified: AHN3's trees) and 5 (high vegetation: IGN's trees).
CANDIDATE_CLASSES = (1, 5)
#: The vegetation filter counts multi-return shares on every SHARE_STRIDE-th point (see multi_return_share).
SHARE_STRIDE = 4
#: ... once per SHARE_CELL (m) cube of query points.
SHARE_CELL = 1.0
#: A candidate farther than this (m) from every candidate that passed the tests cannot be voted vegetation.
VOTE_REACH = 1.5


@dataclasses.dataclass(frozen=True)
class TreeLikeParams:
    """The tree-like rule (scores and training labels; see the module doc).

    min_height (2.5): metres above the median height of the nearest ground points.
    ground_neighbours (8): ground points (class 2) whose median height is the ground under a point.
    building_clearance (3.0): metres; points closer (horizontally) to a class-6 point are not counted.
    """

    constraints: ClassVar[dict[str, str]] = {"min_height": ">= 0", "ground_neighbours": "> 0",
                                             "building_clearance": ">= 0"}

    min_height: float = 2.5
    ground_neighbours: int = 8
    building_clearance: float = 3.0

    def __post_init__(self) -> None:
        check_params(self)


def multi_return(attrs: dict[str, np.ndarray], n: int) -> np.ndarray:
    """Points of pulses with several returns (files without return counts: none)."""
    returns = attrs.get("number_of_returns")
    return np.zeros(n, bool) if returns is None else np.asarray(returns) > 1


def height_above_ground_points(xyz: np.ndarray, ground_xyz: np.ndarray, k: int) -> np.ndarray:
    """Height of each point above the median height of its ``k`` horizontally nearest ground points."""
    if len(ground_xyz) == 0:
        return np.full(len(xyz), np.nan)
    k = min(k, len(ground_xyz))
    _, near = cKDTree(ground_xyz[:, :2]).query(xyz[:, :2], k=k, workers=-1)
    near = np.asarray(near).reshape(len(xyz), k)
    return xyz[:, 2] - np.median(ground_xyz[near, 2], axis=1)


def horizontal_clearance(xyz: np.ndarray, others: np.ndarray, bound: float) -> np.ndarray:
    """Horizontal distance of each point to the nearest of ``others`` (inf beyond ``bound`` or when none)."""
    if len(others) == 0:
        return np.full(len(xyz), np.inf)
    dist, _ = cKDTree(others[:, :2]).query(xyz[:, :2], k=1, distance_upper_bound=bound, workers=-1)
    return np.asarray(dist, np.float64)


def tree_like(xyz: np.ndarray, classification: np.ndarray, number_of_returns: np.ndarray | None,
              params: TreeLikeParams = TreeLikeParams()) -> np.ndarray:
    """Boolean mask of the tree-like points of a labelled cloud (xyz in metres; see the module doc). A cloud
    without ground points (class 2) or without return counts has none."""
    classification = np.asarray(classification)
    n = len(classification)
    candidate = np.isin(classification, CANDIDATE_CLASSES)
    if number_of_returns is None:
        return np.zeros(n, bool)
    candidate &= np.asarray(number_of_returns) > 1
    index = np.flatnonzero(candidate)
    ground = xyz[classification == GROUND_CLASS]
    if len(index) == 0 or len(ground) == 0:
        return np.zeros(n, bool)
    height = height_above_ground_points(xyz[index], ground, params.ground_neighbours)
    clear = horizontal_clearance(xyz[index], xyz[classification == BUILDING_CLASS], params.building_clearance)
    out = np.zeros(n, bool)
    out[index[(height > params.min_height) & (clear > params.building_clearance)]] = True
    return out


def tree_like_cloud(cloud: PointCloud, params: TreeLikeParams = TreeLikeParams()) -> np.ndarray:
    """:func:`tree_like` of a :class:`~lidarmap.core.PointCloud` (its labels; coordinates assumed in metres)."""
    classification = cloud.attrs.get("classification")
    if classification is None:
        return np.zeros(len(cloud), bool)
    return tree_like(cloud.xyz, classification, cloud.attrs.get("number_of_returns"), params)


def multi_return_share(xyz: np.ndarray, multi: np.ndarray, query: np.ndarray, radius: float,
                       stride: int = SHARE_STRIDE, cell: float = SHARE_CELL) -> np.ndarray:
    """Share of the points within ``radius`` (3D) of each query point that belong to multi-return pulses.

    A share over a few metres is a smooth field, so it is counted once per ``cell`` cube of query points (around
    their mean), on every ``stride``-th point of ``xyz``: a ball of a few metres holds hundreds of points, a share
    needs far fewer, and the count costs time in proportion."""
    sample, sample_multi = xyz[::stride], multi[::stride]
    if not sample_multi.any() or len(query) == 0:
        return np.zeros(len(query))
    ijk = np.floor(query / cell).astype(np.int64)
    ijk -= ijk.min(axis=0)
    span = ijk.max(axis=0) + 1
    _, inverse, count = np.unique((ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2], return_inverse=True,
                                  return_counts=True)
    centre = np.column_stack([np.bincount(inverse, query[:, d]) for d in range(3)]) / count[:, None]
    total = cKDTree(sample).query_ball_point(centre, r=radius, workers=-1, return_length=True)
    hits = cKDTree(sample[sample_multi]).query_ball_point(centre, r=radius, workers=-1, return_length=True)
    return (np.asarray(hits, np.float64) / np.maximum(np.asarray(total, np.float64), 1.0))[inverse]


def scattering_at(tree: cKDTree, query: np.ndarray, k: int) -> np.ndarray:
    """Scattering (smallest / largest eigenvalue of the covariance) of the ``k`` nearest points of each query."""
    k = min(k, tree.n)
    if k < 3 or len(query) == 0:
        return np.zeros(len(query))
    _, near = tree.query(query, k=k, workers=-1)
    nb = tree.data[np.asarray(near).reshape(len(query), k)]
    centred = nb - nb.mean(axis=1, keepdims=True)
    values = np.linalg.eigvalsh(np.matmul(centred.transpose(0, 2, 1), centred) / k)
    return np.maximum(values[:, 0], 0.0) / (values[:, 2] + 1e-12)


def vegetation_filter(xyz: np.ndarray, number_of_returns: np.ndarray | None, candidates: np.ndarray,
                      radius: float, min_share: float, min_scattering: float, vote: float,
                      k: int = 16, vote_k: int = 24, scattering: np.ndarray | None = None) -> np.ndarray:
    """Which of the ``candidates`` (indices into ``xyz``, metres) look like vegetation to a LiDAR: at least
    ``min_share`` of the points within ``radius`` belong to multi-return pulses (a porous crown; a roof edge's
    sphere is mostly single returns on the roof) and the ``k`` nearest points scatter (scattering >=
    ``min_scattering``: not a plane); then a vote smooths the answer: a candidate is vegetation when at least
    ``vote`` of its ``vote_k`` nearest candidates passed (thin lines of roof edges are outvoted by their roofs,
    single crown points that missed are carried by their crown). Boolean mask over ``candidates``; none without
    return counts. ``scattering``: the scattering of the ``k`` nearest points of every point of ``xyz`` when the
    caller has it already (the network's shape channel), else computed here."""
    candidates = np.asarray(candidates, np.int64)
    if number_of_returns is None or len(candidates) == 0:
        return np.zeros(len(candidates), bool)
    multi = np.asarray(number_of_returns) > 1
    query = xyz[candidates]
    porous = multi_return_share(xyz, multi, query, radius) >= min_share
    passed = np.zeros(len(candidates), bool)
    if scattering is None:
        passed[porous] = scattering_at(cKDTree(xyz), query[porous], k) >= min_scattering
    else:
        passed[porous] = np.asarray(scattering)[candidates[porous]] >= min_scattering
    if not passed.any():
        return passed
    return vote_vegetation(query, passed, vote, vote_k)


def vote_vegetation(xyz: np.ndarray, passed: np.ndarray, vote: float, k: int) -> np.ndarray:
    """Points at least ``vote`` of whose ``k`` nearest points (among ``xyz``) passed; only points within
    :data:`VOTE_REACH` of a passed point are asked (the others have no passed neighbour to speak of)."""
    k = min(k, len(xyz))
    near_passed, _ = cKDTree(xyz[passed]).query(xyz, k=1, distance_upper_bound=VOTE_REACH, workers=-1)
    ask = np.flatnonzero(np.isfinite(near_passed))
    _, near = cKDTree(xyz).query(xyz[ask], k=k, workers=-1)
    out = np.zeros(len(xyz), bool)
    out[ask] = passed[np.asarray(near).reshape(len(ask), k)].mean(axis=1) >= vote
    return out
