"""Baseline: geometric features + gradient boosting (scikit-learn ``HistGradientBoostingClassifier``).

Per point: height above ground, intensity and return flags (the same :func:`~lidarmap.segment.features.point_features`
as the network) plus, at three scales, the eigen features of the covariance of the k nearest neighbours --
linearity, planarity, scattering, verticality, |normal z|, roughness (plane residual, m) -- the neighbourhood's height range, the point's height
above the neighbourhood's lowest point and the distance to the k-th neighbour (density). Scale 0 uses every point;
coarser scales use voxel centroids (1 m, 3 m), whose features every point of the voxel inherits: wide context for the
cost of few points. Plus the depth below the highest point of the point's 2 m column (walls have a roof above).

Model files are ``joblib`` pickles: load only files you trust (the shipped one, your own).
"""

from __future__ import annotations

import dataclasses
import datetime
import pickle
import time
from pathlib import Path
from typing import Any, ClassVar

import joblib
import numpy as np
from sklearn.ensemble import HistGradientBoostingClassifier

from lidarmap.config import check_params
from lidarmap.core import PointCloud
from lidarmap.errors import InputError
from lidarmap.io.atomic import atomic_path
from lidarmap.segment.blocks import IGNORE, binary_labels, class_weights, hide_labels
from lidarmap.segment.features import (
    EIGEN_NAMES,
    FeatureSpec,
    ModelSpecError,
    PointFeatures,
    check_spec,
    eigen_features,
    point_features,
)
from lidarmap.segment.modelfile import MODELS_DIR

FORMAT = "lidarmap-segment-baseline"
FORMAT_VERSION = 1
DEFAULT_BASELINE = MODELS_DIR / "segment_baseline.joblib"


@dataclasses.dataclass(frozen=True)
class BaselineParams:
    """The geometric baseline (``[segment_baseline]`` table).

    scales ((0.0, 1.0, 3.0)): voxel sizes (m) of the neighbourhood scales; 0 = every point.
    k (16): neighbours per scale.
    column_cell (2.0): cell size (m) of the column-depth feature.
    max_iter (200), learning_rate (0.1), max_leaf_nodes (31): gradient boosting.
    max_samples (400000): training points drawn (seeded) from all labelled points.
    seed (0): seeds the draw and the classifier.
    """

    section = "segment_baseline"
    constraints: ClassVar[dict[str, str]] = {
        "k": ">= 0",
        "column_cell": ">= 0",
        "max_iter": ">= 0",
        "learning_rate": ">= 0",
        "max_leaf_nodes": ">= 0",
        "max_samples": ">= 0",
        "seed": ">= 0",
    }

    scales: tuple[float, ...] = (0.0, 1.0, 3.0)
    k: int = 16
    column_cell: float = 2.0
    max_iter: int = 200
    learning_rate: float = 0.1
    max_leaf_nodes: int = 31
    max_samples: int = 400_000
    seed: int = 0

    def __post_init__(self) -> None:
        check_params(self)


@dataclasses.dataclass
class BaselineModel:
    classifier: HistGradientBoostingClassifier
    spec: FeatureSpec
    params: BaselineParams
    feature_names: list[str]
    class_weights: list[float]
    training: dict[str, Any] = dataclasses.field(default_factory=dict)
    source: str | None = None


def _cell_ids(xyz: np.ndarray, size: float) -> np.ndarray:
    """Dense ids 0..M-1 of the ``size`` cells (over as many axes as ``xyz`` has) holding each point."""
    keys = np.floor(xyz / size).astype(np.int64)
    keys -= keys.min(axis=0)
    flat = np.ravel_multi_index(keys.T, tuple(keys.max(axis=0) + 1))  # one int64 key: a fast 1-D unique
    return np.unique(flat, return_inverse=True)[1].ravel()


def _voxel_reps(xyz: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centroids and each point's voxel index."""
    inverse = _cell_ids(xyz, size)
    count = np.bincount(inverse)
    reps = np.column_stack([np.bincount(inverse, weights=xyz[:, d]) / count for d in range(3)])
    return reps, inverse


def column_depth(xyz: np.ndarray, cell: float) -> np.ndarray:
    """Height of the highest point of each point's ``cell`` x ``cell`` column above the point."""
    inverse = _cell_ids(xyz[:, :2], cell)
    top = np.full(inverse.max() + 1, -np.inf)
    np.maximum.at(top, inverse, xyz[:, 2])
    return (top[inverse] - xyz[:, 2]).astype(np.float32)


def feature_names(params: BaselineParams, spec: FeatureSpec) -> list[str]:
    names = ["hag"] + spec.channels[4:] + ["column_depth"]
    return names + [f"{n}@{s:g}" for s in params.scales for n in EIGEN_NAMES]


def geometric_features(pf: PointFeatures, params: BaselineParams) -> np.ndarray:
    """The ground-independent part: column depth and eigen features at every scale, (N, 1 + 9 * scales)."""
    columns = [column_depth(pf.xyz, params.column_cell)[:, None]]
    for size in params.scales:
        if size <= 0:
            columns.append(eigen_features(pf.xyz, params.k))
        else:
            reps, inverse = _voxel_reps(pf.xyz, size)
            columns.append(eigen_features(reps, params.k)[inverse])
    return np.column_stack(columns)


def baseline_features(pf: PointFeatures, params: BaselineParams, geometric: np.ndarray | None = None) -> np.ndarray:
    """Every feature of :func:`feature_names`, (N, F) float32."""
    geometric = geometric_features(pf, params) if geometric is None else geometric
    hag = (pf.xyz[:, 2] - pf.ground_z).astype(np.float32)
    return np.column_stack([hag, pf.values, geometric]).astype(np.float32)


def train_baseline(clouds: list[tuple[str, PointCloud]], params: BaselineParams = BaselineParams(),
                   spec: FeatureSpec = FeatureSpec(), source_weights: list[float] | None = None) -> BaselineModel:
    """Fit the classifier on labelled points; each cloud contributes its features with the class-2 ground and
    with the estimated ground (half of the draws each), as the network's training does.

    ``params.max_samples`` points are drawn (seeded) from all labelled points: uniformly, or with cloud i giving
    a share ``source_weights[i]`` (normalised) of them, as the network draws its blocks.
    """

    started = time.perf_counter()
    rng = np.random.default_rng(params.seed)
    labelled = []
    for name, cloud in clouds:
        if "classification" not in cloud.attrs:
            raise InputError("training file has no classification", name)
        y = binary_labels(cloud.attrs["classification"])
        labelled.append(np.flatnonzero(y != IGNORE))
    counts = np.array([len(k) for k in labelled])
    weights = class_weights(np.concatenate([binary_labels(c.attrs["classification"]) for _, c in clouds]))
    quota = _quotas(counts, params.max_samples, source_weights)
    rows, labels = [], []
    for (name, cloud), keep, n in zip(clouds, labelled, quota):
        if n == 0:
            continue
        keep = np.sort(rng.choice(keep, n, replace=False)) if n < len(keep) else keep
        pf = point_features(cloud, spec)
        geometric = geometric_features(pf, params)
        hidden = point_features(hide_labels(cloud), spec)
        use_hidden = rng.random(len(keep)) < 0.5
        rows.append(np.where(use_hidden[:, None], baseline_features(hidden, params, geometric)[keep],
                             baseline_features(pf, params, geometric)[keep]))
        labels.append(binary_labels(cloud.attrs["classification"])[keep])
    x, y = np.concatenate(rows), np.concatenate(labels)
    classifier = HistGradientBoostingClassifier(max_iter=params.max_iter, learning_rate=params.learning_rate,
                                                max_leaf_nodes=params.max_leaf_nodes, random_state=params.seed)
    classifier.fit(x, y, sample_weight=weights[y])
    training = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "seed": params.seed, "data": [{"name": name, "labelled": int(c), "samples": int(q)}
                                              for (name, _), c, q in zip(clouds, counts, quota)],
                "samples": int(len(y)), "seconds": round(time.perf_counter() - started, 1)}
    return BaselineModel(classifier, spec, params, feature_names(params, spec), weights.tolist(), training)


def _quotas(counts: np.ndarray, total: int, shares: list[float] | None) -> np.ndarray:
    """Points to draw from each cloud: ``total`` split by ``shares`` (default: by ``counts``), capped by counts."""
    if counts.sum() <= total and shares is None:
        return counts
    share = counts.astype(np.float64) if shares is None else np.asarray(shares, np.float64)
    if len(share) != len(counts) or np.any(share < 0) or share.sum() <= 0:
        raise ValueError("source_weights: one non-negative weight per training cloud, not all zero")
    return np.minimum(np.floor(total * share / share.sum()).astype(np.int64), counts)


def predict_baseline(cloud: PointCloud, model: BaselineModel) -> np.ndarray:
    """Building probability (float32, N) of every point."""
    if len(cloud) == 0:
        return np.zeros(0, np.float32)
    pf = point_features(cloud, model.spec)
    features = baseline_features(pf, model.params)
    return model.classifier.predict_proba(features)[:, 1].astype(np.float32)


def save_baseline(path: str | Path, model: BaselineModel) -> Path:
    path = Path(path)
    data = {"format": FORMAT, "version": FORMAT_VERSION, "classifier": model.classifier,
            "features": model.spec.to_dict(), "params": dataclasses.asdict(model.params),
            "feature_names": model.feature_names, "class_weights": model.class_weights, "training": model.training}
    with atomic_path(path) as tmp:
        joblib.dump(data, tmp, compress=3)
    return path


def load_baseline(path: str | Path | None = None) -> BaselineModel:
    """Load a baseline model file (the shipped one when ``path`` is None)."""
    path = Path(path) if path is not None else DEFAULT_BASELINE
    if not path.exists():
        raise InputError("baseline model file not found", path)
    try:
        data = joblib.load(path)
    except (pickle.UnpicklingError, EOFError, OSError, ValueError, KeyError, AttributeError, ImportError) as exc:
        raise InputError(f"not a readable baseline model file ({' '.join(str(exc).split())[:160]})", path) from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ModelSpecError(f"not a {FORMAT} model file", path)
    if data.get("version") != FORMAT_VERSION:
        raise ModelSpecError(f"baseline model version {data.get('version')} is not supported", path)
    spec = check_spec(data["features"], str(path))
    params = BaselineParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in data["params"].items()})
    if list(data["feature_names"]) != feature_names(params, spec):
        raise ModelSpecError("baseline model's features differ from what this lidarmap computes", path)
    return BaselineModel(data["classifier"], spec, params, list(data["feature_names"]), data["class_weights"],
                         data.get("training", {}), str(path))
