"""Blocks of points: random training blocks, overlapping inference windows, and the spatial train/val split.

A block is a vertical column ``block_size`` x ``block_size`` metres around an (x, y) centre, holding all the points
of the cloud in it; the network sees ``points`` of them. Blocks with more points are subsampled without
replacement; blocks with fewer are padded by repeating points (never by looking for another centre), so sampling
always terminates, also on a small building alone in a sparse area.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from lidarmap.core import PointCloud
from lidarmap.errors import InputError
from lidarmap.segment.features import (
    BUILDING_CLASS,
    UNLABELLED_CLASSES,
    FeatureSpec,
    PointFeatures,
    Transform,
    block_input,
)

IGNORE = -1  # label of points excluded from the loss (unclassified)


def binary_labels(classification: np.ndarray) -> np.ndarray:
    """1 = building (class 6), 0 = any other labelled class, :data:`IGNORE` = unlabelled (classes 0, 1)."""
    labels = (classification == BUILDING_CLASS).astype(np.int64)
    labels[np.isin(classification, UNLABELLED_CLASSES)] = IGNORE
    return labels


def hide_labels(cloud: PointCloud) -> PointCloud:
    """The same cloud with every point unclassified (class 1): what an unlabelled acquisition looks like."""
    attrs = dict(cloud.attrs)
    attrs["classification"] = np.ones(len(cloud), np.uint8)
    return dataclasses.replace(cloud, attrs=attrs)


def sample_indices(members: np.ndarray, points: int, rng: np.random.Generator) -> np.ndarray:
    """``points`` indices drawn from ``members``: without replacement when there are enough, else all of them
    plus random repeats; shuffled, so the first point (where FPS starts) is random."""
    if len(members) >= points:
        return rng.choice(members, points, replace=False)
    extra = rng.choice(members, points - len(members), replace=True)
    return rng.permutation(np.concatenate([members, extra]))


def column_members(tree: cKDTree, centres: np.ndarray, half: float) -> list[np.ndarray]:
    """Indices of the points in the square columns of half-width ``half`` around each (x, y) centre."""
    found = tree.query_ball_point(np.atleast_2d(centres), r=half, p=np.inf, return_sorted=False)
    return [np.asarray(f, dtype=np.int64) for f in found]


def window_centres(xy: np.ndarray, block_size: float, overlap: float) -> np.ndarray:
    """Centres of windows on a regular lattice with stride ``block_size * (1 - overlap)`` covering every point.

    The lattice starts at the points' minimum corner and reaches past the maximum, so each point lies within
    half a stride of a centre, hence inside that window. An area smaller than one block gets one window at its
    middle.
    """
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    if np.all(hi - lo <= block_size):
        return ((lo + hi) / 2)[None, :]
    stride = block_size * (1.0 - overlap)
    axes = [lo[k] + stride * np.arange(int(np.ceil((hi[k] - lo[k]) / stride)) + 1) for k in range(2)]
    gx, gy = np.meshgrid(*axes, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel()])


@dataclasses.dataclass
class TrainingSource:
    """One training cloud, ready for block sampling."""

    name: str
    features: PointFeatures  # ground from class 2 (when present)
    hidden_features: PointFeatures  # ground estimated: what an unlabelled file gives
    labels: np.ndarray  # binary_labels
    tree: cKDTree  # on frame xy
    labelled: np.ndarray  # indices of labelled points
    buildings: np.ndarray  # indices of building points


def make_source(name: str, features: PointFeatures, hidden_features: PointFeatures,
                classification: np.ndarray) -> TrainingSource:
    labels = binary_labels(classification)
    return TrainingSource(name, features, hidden_features, labels, cKDTree(features.xyz[:, :2]),
                          np.flatnonzero(labels != IGNORE), np.flatnonzero(labels == 1))


def training_block(source: TrainingSource, spec: FeatureSpec, points: int, rng: np.random.Generator,
                   building_centre: bool, estimated_ground: bool,
                   transform: Transform | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One training block: (xyz (P, 3), channels (P, C), labels (P,)), centred on a random labelled point
    (a building point when ``building_centre`` and the source has any). One draw, no retries."""
    pool = source.buildings if building_centre and len(source.buildings) else source.labelled
    centre = source.features.xyz[pool[rng.integers(len(pool))], :2]
    members = column_members(source.tree, centre, spec.block_size / 2)[0]
    index = sample_indices(members, points, rng)
    pf = source.hidden_features if estimated_ground else source.features
    xyz, channels = block_input(pf, index, centre, spec, transform)
    return xyz, channels, source.labels[index]


def spatial_split(xy: np.ndarray, cell: float, val_fraction: float,
                  rng: np.random.Generator) -> np.ndarray:
    """Boolean mask of validation points: whole ``cell`` x ``cell`` squares drawn at random (seeded).

    Neighbouring points fall on the same side, so validation measures generalisation to unseen places rather than
    to unseen points of seen buildings. At least one cell goes to each side when there are two or more cells and
    ``val_fraction`` is above 0; ``val_fraction = 0`` holds nothing out (training on all of the data).
    """
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    keys, inverse = np.unique(ij[:, 0] * 1_000_003 + ij[:, 1], return_inverse=True)
    n_val = int(round(len(keys) * val_fraction))
    if len(keys) >= 2 and val_fraction > 0:
        n_val = min(max(n_val, 1), len(keys) - 1)
    chosen = np.zeros(len(keys), bool)
    chosen[rng.permutation(len(keys))[:n_val]] = True
    return chosen[inverse.ravel()]


def class_weights(labels: np.ndarray, num_classes: int = 2) -> np.ndarray:
    """Paper eq. (1): w_j = (max f / f_j)^(1/3), normalised to sum 1; f_j = relative frequency of class j.

    ``labels`` may contain :data:`IGNORE`, which is not counted. A class without any point is an error.
    """
    counts = np.bincount(labels[labels != IGNORE], minlength=num_classes)[:num_classes].astype(np.float64)
    if np.any(counts == 0):
        missing = ", ".join(str(j) for j in np.flatnonzero(counts == 0))
        raise InputError(f"training data has no labelled points of class(es) {missing} (0 = not-building, "
                         "1 = building): both are needed")
    freq = counts / counts.sum()
    raw = (freq.max() / freq) ** (1.0 / 3.0)
    return raw / raw.sum()
