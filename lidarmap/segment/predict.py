"""Building probabilities for every point of a cloud, and the classes written back.

PointNet++ inference runs on overlapping windows (stride ``block_size * (1 - overlap)``); each window feeds the
network ``block_points`` of its points (all of them, padded by repeats, when it has fewer). A point's probability
is the mean over every window that fed it; points that no window happened to feed (dense data: a window holds more
points than the network takes) get the inverse-distance mean of their 3 nearest fed neighbours. Every point gets a
probability, also in areas smaller than one block (one window covers them all).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import math
import os
import weakref
from collections.abc import Callable, Iterator
from typing import ClassVar

import numpy as np
import torch
from scipy.spatial import cKDTree

from lidarmap.config import check_params
from lidarmap.core import PointCloud
from lidarmap.segment.blocks import column_members, sample_indices, window_centres
from lidarmap.segment.features import (
    BUILDING_CLASS,
    FeatureSpec,
    PointFeatures,
    Transform,
    block_input,
    ground_grid,
    metre_factors,
    point_features,
)
from lidarmap.segment.modelfile import SegmentModel
from lidarmap.segment.vegetation import vegetation_filter

#: Class given to input building points that the model calls not-building (they are no longer trusted as 6).
DEMOTED_CLASS = 1
#: Class written for confident vegetation (``write_vegetation``): ASPRS high vegetation.
VEGETATION_CLASS = 5
#: Output classes that ``write_vegetation`` may turn into :data:`VEGETATION_CLASS` (unclassified, demoted
#: buildings, vegetation already): ground, water, bridges and the other labelled classes are never touched.
VEGETATION_REWRITABLE = (0, 1, VEGETATION_CLASS)
#: Neighbours of the vegetation filter's scattering test (:func:`lidarmap.segment.vegetation.vegetation_filter`).
VEGETATION_K = 16
#: Extra dimension (float32) of predicted files holding each point's building probability.
PROBABILITY_DIM = "building_probability"
METHODS = ("pointnet2", "baseline")

Report = Callable[[int, int], None]


@dataclasses.dataclass(frozen=True)
class PredictParams:
    """How ``lidarmap segment predict`` runs (``[segment]`` table).

    overlap (0.25): fraction by which neighbouring windows overlap (0.25 = stride of three quarters of a block,
        each point seen by about 1.8 windows); 0 <= overlap < 1. Chosen on the training recipe's validation split:
        0.25 scored OA 0.9861 / building IoU 0.9541 against 0.9858 / 0.9530 at 0.5, in 56 % of the time.
    batch_size (32): windows per network call (larger batches spread the per-step cost of the sampling loop).
    threshold (0.5): building probability at or above which a point becomes class 6.
    union (False): keep input class-6 points as building whatever the model says.
    seed (0): seeds the choice of points inside dense windows (same input + seed = same output).
    rotations (1): test-time augmentation: every window is also fed turned by 360/rotations degrees about z
        (rotations - 1 more times) and the probabilities are averaged; costs that many times the network time.
    window_weight ("tent"): how the windows that saw a point are averaged: "tent" weighs each by how central the
        point lies in it ((1 - |dx|/half)(1 - |dy|/half)), "uniform" equally.
    threads (0): torch CPU threads; 0 = one per core.
    keep_memory (True): while ``predict`` runs (features, network, filter), freed memory stays with the process
        (glibc: no separate mapping for large blocks, no trimming; restored and trimmed afterwards;
        :func:`kept_memory`), so the network's large temporaries (64-128 MB per batch of 32 windows) are not
        page-faulted in afresh at every layer. Same output; measured on the held-out parts in docs/segmentation.md
        ("Memory"). No effect where the C library has no ``mallopt`` (macOS, Windows).
    device ("auto"): "cpu", "cuda" or "auto" (a GPU when there is one).
    vegetation (True): after the model, points it calls building that look like vegetation get probability 0
        (:func:`lidarmap.segment.vegetation.vegetation_filter`): at least ``vegetation_share`` of the points within
        ``vegetation_radius`` m belong to multi-return pulses and their 16 nearest points scatter (scattering >=
        ``vegetation_scattering``), and at least ``vegetation_vote`` of the 24 nearest building points passed too.
        Defaults chosen on the recipe's training parts (docs/segmentation.md).
    vegetation_radius (3.5), vegetation_share (0.75), vegetation_scattering (0.03), vegetation_vote (0.7): see
        vegetation.
    vegetation_keep_below (2.5): metres above the ground under which the filter keeps the last returns of their
        pulse (single returns included) as the model called them: a pulse that ends low under a crown hit something
        solid there (a wall's foot, a low roof, a fence), not the crown. 0 = the filter judges every point. Chosen
        on the recipe's training parts (docs/segmentation.md): on the Delft training strip it gives back 31 % of
        the labelled building points the filter took, and 1 of its 31,488 removed tree-like points.
    write_vegetation (False): also write class 5 (high vegetation) for the points the model calls not-building that
        the same vegetation test accepts, that stand at least ``vegetation_min_height`` m above the ground, after
        which their pulse went on (not single or last returns), and whose output class would be 0, 1 or 5
        (:func:`confident_vegetation`); class 6 stays the contract, every other class is kept. Off by default: the
        test was tuned to remove crowns from building, not to map every tree (it reaches 3-6 % of IGN's high
        vegetation; docs/segmentation.md).
    vegetation_min_height (2.0): metres above the ground (class 2 when the file has enough, else estimated) a point
        needs to be written class 5 (high vegetation, as in ASPRS/AHN practice).
    """

    section = "segment"
    constraints: ClassVar[dict[str, str]] = {
        "overlap": ">= 0",
        "batch_size": ">= 0",
        "threshold": ">= 0",
        "seed": ">= 0",
        "rotations": ">= 0",
        "window_weight": "in tent, uniform",
        "threads": ">= 0",
        "device": "in auto, cpu, cuda",
        "vegetation_radius": "> 0",
        "vegetation_share": "[0, 1]",
        "vegetation_scattering": "[0, 1]",
        "vegetation_vote": "[0, 1]",
        "vegetation_keep_below": ">= 0",
        "vegetation_min_height": ">= 0",
    }

    overlap: float = 0.25
    batch_size: int = 32
    threshold: float = 0.5
    union: bool = False
    seed: int = 0
    rotations: int = 1
    window_weight: str = "tent"
    threads: int = 0
    keep_memory: bool = True
    device: str = "auto"
    vegetation: bool = True
    vegetation_radius: float = 3.5
    vegetation_share: float = 0.75
    vegetation_scattering: float = 0.03
    vegetation_vote: float = 0.7
    vegetation_keep_below: float = 2.5
    write_vegetation: bool = False
    vegetation_min_height: float = 2.0

    def __post_init__(self) -> None:
        check_params(self)
        if self.window_weight not in ("tent", "uniform"):
            raise ValueError("window_weight must be tent or uniform")
        if self.rotations < 1:
            raise ValueError("rotations must be at least 1")
        if not 0.0 <= self.overlap < 1.0:
            raise ValueError("overlap must be in [0, 1)")
        if self.batch_size < 1:
            raise ValueError("batch_size must be at least 1")
        if not 0.0 <= self.threshold <= 1.0:
            raise ValueError("threshold must be in [0, 1]")
        if self.threads < 0:
            raise ValueError("threads must be >= 0")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError("device must be auto, cpu or cuda")


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


#: glibc ``mallopt`` parameters (malloc.h) and their defaults, restored after :func:`kept_memory`.
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
DEFAULT_TRIM_THRESHOLD, DEFAULT_MMAP_MAX = 128 * 1024, 65536


@functools.cache
def _libc() -> object | None:
    """The C library when it has glibc's ``mallopt`` and ``malloc_trim`` (None elsewhere)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None


@contextlib.contextmanager
def kept_memory(enabled: bool = True) -> Iterator[None]:
    """Inside the block, glibc keeps freed memory for reuse: blocks of any size come from the heap (no mmap per
    allocation) and the heap is not trimmed. Every batch of the network allocates and frees tensors of 64-128 MB;
    by default glibc maps each one afresh and the kernel zero-fills it page by page (hundreds of thousands of page
    faults per tile). Afterwards the defaults are restored and the free memory handed back (``malloc_trim``).
    Process-wide while it lasts (other threads allocate the same way meanwhile); nested blocks restore only at the
    outermost; a no-op without glibc."""
    libc = _libc() if enabled else None
    if libc is None:
        yield
        return
    if _KEPT[0] == 0:
        libc.mallopt(M_MMAP_MAX, 0)
        libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    _KEPT[0] += 1
    try:
        yield
    finally:
        _KEPT[0] -= 1
        if _KEPT[0] == 0:
            libc.mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
            libc.mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
            libc.malloc_trim(0)


#: Depth of nested :func:`kept_memory` blocks (the settings are restored when the outermost ends).
_KEPT = [0]


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Use ``count`` torch CPU threads inside the block (0 = one per core), then restore the previous setting."""
    previous = torch.get_num_threads()
    torch.set_num_threads(count or os.cpu_count() or 1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def rotation(angle_deg: float) -> Transform | None:
    """A turn of the block about z (None for 0 degrees)."""
    if angle_deg % 360 == 0:
        return None
    a = math.radians(angle_deg)
    matrix = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                      np.float32)
    return lambda xyz, hag: ((xyz @ matrix.T).astype(np.float32), hag)


def window_weight(offset: np.ndarray, half: float, how: str) -> np.ndarray:
    """Weight of a window's prediction for points at ``offset`` (N, 2) from its centre.

    A point near a window's edge lacks half of its context; "tent" weights (1 - |dx|/half)(1 - |dy|/half) let the
    windows in which the point lies centrally decide. "uniform" gives every window the same say.
    """
    if how == "uniform":
        return np.ones(len(offset))
    tent = np.clip(1.0 - np.abs(offset) / half, 1e-3, 1.0)
    return tent[:, 0] * tent[:, 1]


Window = tuple[np.ndarray, np.ndarray]  # (centre (2,), member indices)


def plan_windows(pf: PointFeatures, model: SegmentModel, params: PredictParams,
                 targets: np.ndarray | None = None) -> list[Window]:
    """The non-empty windows (centre, member indices) that cover every point (or every point of ``targets``; the
    windows still hold every point in them, the others being context)."""
    spec = model.spec
    cover = pf.xyz[:, :2] if targets is None else pf.xyz[targets, :2]
    centres = window_centres(cover, spec.block_size, params.overlap)
    members = column_members(cKDTree(pf.xyz[:, :2]), centres, spec.block_size / 2)
    return [(c, m) for c, m in zip(centres, members) if len(m)]


def windows_per_batch(params: PredictParams) -> int:
    """Windows per network call (each is fed ``rotations`` times)."""
    return max(1, params.batch_size // params.rotations)


def window_batches(pf: PointFeatures, model: SegmentModel, params: PredictParams, windows: list[Window],
                   rng: np.random.Generator) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(indices (B, P), weights (B, P), xyz (B, P, 3), channels (B, P, C)) of successive batches of windows (each
    window once per test-time rotation, with the same points)."""
    spec = model.spec
    turns = [rotation(360.0 * k / params.rotations) for k in range(params.rotations)]
    per_batch = windows_per_batch(params)
    for start in range(0, len(windows), per_batch):
        batch = windows[start:start + per_batch]
        index = [sample_indices(m, model.block_points, rng) for _, m in batch]
        inputs = [block_input(pf, i, c, spec, turn) for i, (c, _) in zip(index, batch) for turn in turns]
        weight = [window_weight(pf.xyz[i, :2] - c, spec.block_size / 2, params.window_weight)
                  for i, (c, _) in zip(index, batch)]
        index = np.repeat(np.stack(index), len(turns), axis=0)
        weight = np.repeat(np.stack(weight), len(turns), axis=0)
        yield index, weight, np.stack([x for x, _ in inputs]), np.stack([f for _, f in inputs])


def spread_to_all(xyz: np.ndarray, fed: np.ndarray, prob: np.ndarray, targets: np.ndarray | None = None
                  ) -> np.ndarray:
    """Probabilities of points not fed to the network (of ``targets`` only, when given): inverse-square-distance
    mean of the 3 nearest fed points."""
    missing = np.flatnonzero(~fed if targets is None else ~fed & targets)
    if len(missing) == 0:
        return prob
    known = np.flatnonzero(fed)
    k = min(3, len(known))
    dist, near = cKDTree(xyz[known]).query(xyz[missing], k=k, workers=-1)
    dist, near = dist.reshape(len(missing), k), near.reshape(len(missing), k)
    weight = 1.0 / (dist**2 + 1e-4)
    out = prob.copy()
    out[missing] = (prob[known[near]] * weight).sum(1) / weight.sum(1)
    return out


_FUSED: weakref.WeakKeyDictionary[torch.nn.Module, tuple[tuple, torch.device, torch.nn.Module]] = \
    weakref.WeakKeyDictionary()


def inference_net(model: SegmentModel, device: torch.device) -> torch.nn.Module:
    """The model's network with batch norms fused, on ``device``; cached (a city runs one small prediction per
    building), and rebuilt when the weights changed since (training validates as it goes)."""
    version = tuple(p._version for p in model.net.parameters())
    cached = _FUSED.get(model.net)
    if cached is not None and cached[0] == version and cached[1] == device:
        return cached[2]
    net = model.net.fused().to(device)
    _FUSED[model.net] = (version, device, net)
    return net


def predict_pointnet2(cloud: PointCloud, model: SegmentModel, params: PredictParams = PredictParams(),
                      report: Report | None = None, targets: np.ndarray | None = None) -> np.ndarray:
    """Building probability (float32) of every point of ``cloud``, or of the points of the boolean mask
    ``targets`` only (the windows cover them; the other points are context)."""
    return pointnet2_with_features(cloud, model, params, report, targets)[0]


def pointnet2_with_features(cloud: PointCloud, model: SegmentModel, params: PredictParams = PredictParams(),
                            report: Report | None = None, targets: np.ndarray | None = None
                            ) -> tuple[np.ndarray, PointFeatures | None]:
    """:func:`predict_pointnet2` and the point features it computed (every point of ``cloud``: height above the
    ground, scattering of the 16 nearest points), which the vegetation filter reuses instead of computing them
    again (None for an empty cloud)."""
    if len(cloud) == 0 or (targets is not None and not targets.any()):
        return np.zeros(0 if targets is None else int(targets.sum()), np.float32), None
    pf = point_features(cloud, model.spec)
    rng = np.random.default_rng(params.seed)
    device = pick_device(params.device)
    net = inference_net(model, device)
    total = np.zeros(len(cloud))
    count = np.zeros(len(cloud))
    windows = plan_windows(pf, model, params, targets)
    n_batches = math.ceil(len(windows) / windows_per_batch(params))
    with torch_threads(params.threads), torch.inference_mode(), kept_memory(params.keep_memory):
        for done, (index, weight, xyz, channels) in enumerate(window_batches(pf, model, params, windows, rng), 1):
            logits = net(torch.from_numpy(xyz).to(device), torch.from_numpy(channels).to(device))
            prob = torch.softmax(logits.float(), dim=-1)[..., 1].cpu().numpy()
            # add.at touches only the batch's points (a bincount over all N points per batch is quadratic)
            np.add.at(total, index.ravel(), (prob * weight).ravel())
            np.add.at(count, index.ravel(), weight.ravel())
            if report:
                report(done, n_batches)
    fed = count > 0
    prob = spread_to_all(pf.xyz, fed, np.divide(total, count, out=np.zeros(len(cloud)), where=fed), targets)
    return (prob if targets is None else prob[targets]).astype(np.float32), pf


def predict(cloud: PointCloud, model: object, params: PredictParams = PredictParams(),
            report: Report | None = None, targets: np.ndarray | None = None) -> np.ndarray:
    """Building probabilities (float32) from a PointNet++ :class:`SegmentModel` or a baseline model: of every
    point, or of the points of the boolean mask ``targets`` (the others are context)."""
    with kept_memory(params.keep_memory):
        prob, features = model_probability(cloud, model, params, report, targets)
        return without_vegetation(cloud, prob, params, targets, features) if params.vegetation else prob


def model_probability(cloud: PointCloud, model: object, params: PredictParams = PredictParams(),
                      report: Report | None = None, targets: np.ndarray | None = None
                      ) -> tuple[np.ndarray, PointFeatures | None]:
    """The model's building probabilities (of every point, or of ``targets``) before the vegetation filter, and
    the point features of every point where the model computed them (PointNet++; else None), for
    :func:`without_vegetation`."""
    from lidarmap.segment.baseline import BaselineModel, predict_baseline

    if isinstance(model, BaselineModel):
        with torch_threads(params.threads):
            prob = predict_baseline(cloud, model)
        return (prob if targets is None else prob[targets]), None
    if isinstance(model, SegmentModel):
        return pointnet2_with_features(cloud, model, params, report, targets)
    raise TypeError(f"not a segmentation model: {type(model).__name__}")


def without_vegetation(cloud: PointCloud, probability: np.ndarray, params: PredictParams,
                       targets: np.ndarray | None = None, features: PointFeatures | None = None) -> np.ndarray:
    """``probability`` (of every point, or of ``targets``) with 0 for the points above the threshold that the
    vegetation filter calls vegetation (their neighbourhoods include every point of ``cloud``), except the low
    last returns of :func:`solid_low_returns`. ``features``: the PointNet++ features of every point of ``cloud``
    (:func:`model_probability`), whose height above the ground and scattering are reused; without them both are
    computed here."""
    index = np.arange(len(cloud)) if targets is None else np.flatnonzero(targets)
    above = np.flatnonzero(probability >= params.threshold)
    if len(above) == 0:
        return probability
    xyz = cloud.xyz * metre_factors(cloud)
    veg = vegetation_filter(xyz, cloud.attrs.get("number_of_returns"), index[above], params.vegetation_radius,
                            params.vegetation_share, params.vegetation_scattering, params.vegetation_vote,
                            scattering=feature_channel(features, "scattering", VEGETATION_K))
    height = None if features is None else features.xyz[:, 2] - features.ground_z
    taken = index[above[veg]]
    if params.vegetation_keep_below > 0 and len(taken):
        veg[veg] = ~solid_low_returns(cloud, xyz, taken, params.vegetation_keep_below, height)
    out = np.array(probability, np.float32, copy=True)
    out[above[veg]] = 0.0
    return out


def feature_channel(features: PointFeatures | None, name: str, k: int) -> np.ndarray | None:
    """One per-point shape channel of ``features`` computed from ``k`` neighbours (None without features, when
    the spec has no such channel or used another neighbour count)."""
    if features is None or name not in features.channels or features.geometry_k != k:
        return None
    return features.values[:, features.channels.index(name)]


def solid_low_returns(cloud: PointCloud, xyz: np.ndarray, index: np.ndarray, below: float,
                      height: np.ndarray | None = None) -> np.ndarray:
    """Which points of ``index`` end their pulse (last or single return) less than ``below`` metres above the
    ground: under a crown such a pulse hit something solid -- a wall's foot, a low roof, a fence -- and the crown
    around it should not take it. ``height`` (every point of the cloud) or else the estimated ground (class 2 when
    the file has enough)."""
    number, count = cloud.attrs.get("return_number"), cloud.attrs.get("number_of_returns")
    if number is None or count is None:
        return np.zeros(len(index), bool)
    last = np.asarray(number)[index] >= np.asarray(count)[index]
    if height is None:
        grid, _ = ground_grid(xyz, cloud.attrs.get("classification"), FeatureSpec())
        low = xyz[index, 2] - grid.height_at(xyz[index, :2]) < below
    else:
        low = np.asarray(height)[index] < below
    return last & low


def apply_classes(classification: np.ndarray, probability: np.ndarray, threshold: float = 0.5,
                  union: bool = False) -> np.ndarray:
    """Output classes: building where ``probability >= threshold``; other points keep their class, except input
    buildings the model rejects, which become :data:`DEMOTED_CLASS` (1) -- unless ``union`` keeps them as 6."""
    building = probability >= threshold
    if union:
        building |= classification == BUILDING_CLASS
    out = classification.copy()
    out[(classification == BUILDING_CLASS) & ~building] = DEMOTED_CLASS
    out[building] = BUILDING_CLASS
    return out


def segmented_cloud(cloud: PointCloud, probability: np.ndarray, params: PredictParams = PredictParams()) -> PointCloud:
    """The input cloud (every point, same order, every attribute) with the classes of :func:`apply_classes` and
    the extra dimension :data:`PROBABILITY_DIM`. A cloud without classification counts as class 0."""
    classification = cloud.attrs.get("classification")
    if classification is None:
        classification = np.zeros(len(cloud), np.uint8)
    classes = apply_classes(classification, probability, params.threshold, params.union)
    if params.write_vegetation:
        classes[confident_vegetation(cloud, classes, params)] = VEGETATION_CLASS
    attrs = {**cloud.attrs, "classification": classes, PROBABILITY_DIM: np.asarray(probability, np.float32)}
    extra = [*cloud.extra_dims, *([] if PROBABILITY_DIM in cloud.extra_dims else [PROBABILITY_DIM])]
    return PointCloud(cloud.xyz, attrs, cloud.crs, extra, cloud.source)


def confident_vegetation(cloud: PointCloud, classes: np.ndarray, params: PredictParams) -> np.ndarray:
    """Boolean mask of the points to write as high vegetation: output class in :data:`VEGETATION_REWRITABLE`, at
    least ``vegetation_min_height`` above the ground, and accepted by the vegetation test of the filter (porous,
    scattered, voted by their neighbours) and a return after which the pulse went on (not its last): a porous
    crown splits pulses; a single or last return is as often the wall, roof or ground next to or behind a crown (on
    the held-out Delft crop this costs 6 % of the tree-like points and keeps walls beside crowns out). Files
    without return numbers have none."""
    from lidarmap.segment.features import FeatureSpec, ground_grid

    out = np.zeros(len(cloud), bool)
    candidates = np.flatnonzero(np.isin(classes, VEGETATION_REWRITABLE))
    if len(candidates) == 0 or cloud.attrs.get("number_of_returns") is None:
        return out
    xyz = cloud.xyz * metre_factors(cloud)
    grid, _ = ground_grid(xyz, cloud.attrs.get("classification"), FeatureSpec())
    high = xyz[candidates, 2] - grid.height_at(xyz[candidates, :2]) >= params.vegetation_min_height
    candidates = candidates[high & pulse_went_on(cloud, candidates)]
    veg = vegetation_filter(xyz, cloud.attrs.get("number_of_returns"), candidates, params.vegetation_radius,
                            params.vegetation_share, params.vegetation_scattering, params.vegetation_vote)
    out[candidates[veg]] = True
    return out


def pulse_went_on(cloud: PointCloud, index: np.ndarray) -> np.ndarray:
    """Whether each point of ``index`` is a return after which its pulse went on (return number < number of
    returns); False when the file has no return numbers."""
    number, count = cloud.attrs.get("return_number"), cloud.attrs.get("number_of_returns")
    if number is None or count is None:
        return np.zeros(len(index), bool)
    return np.asarray(number)[index] < np.asarray(count)[index]
