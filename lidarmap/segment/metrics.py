"""Scores of a building / not-building segmentation on labelled points."""

from __future__ import annotations

from typing import Any

import numpy as np

from lidarmap.segment.features import BUILDING_CLASS, UNLABELLED_CLASSES

CLASS_NAMES = ("not-building", "building")


def confusion_matrix(truth: np.ndarray, predicted: np.ndarray, num_classes: int = 2) -> np.ndarray:
    """Counts ``[t, p]`` of points of true class t predicted as p (integer labels in [0, num_classes))."""
    flat = truth.astype(np.int64) * num_classes + predicted.astype(np.int64)
    return np.bincount(flat, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def scores(confusion: np.ndarray, names: tuple[str, ...] = CLASS_NAMES) -> dict[str, Any]:
    """Overall accuracy, per-class IoU, mean IoU, precision and recall of the building class, and the matrix."""
    confusion = np.asarray(confusion, dtype=np.int64)
    total = int(confusion.sum())
    tp = np.diag(confusion).astype(np.float64)
    union = confusion.sum(0) + confusion.sum(1) - tp
    iou = np.divide(tp, union, out=np.full(len(tp), np.nan), where=union > 0)
    predicted, actual = confusion.sum(0), confusion.sum(1)
    return {
        "points": total,
        "overall_accuracy": float(tp.sum() / total) if total else float("nan"),
        "iou": {name: float(v) for name, v in zip(names, iou)},
        "miou": float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan"),
        "building_precision": float(tp[-1] / predicted[-1]) if predicted[-1] else float("nan"),
        "building_recall": float(tp[-1] / actual[-1]) if actual[-1] else float("nan"),
        "confusion": {"rows": "truth", "columns": "predicted", "classes": list(names),
                      "matrix": confusion.tolist()},
    }


def evaluate_classes(truth_classes: np.ndarray, predicted_building: np.ndarray) -> dict[str, Any]:
    """Scores on the points whose true class is labelled (not 0/1): building = class 6, else not-building."""
    labelled = ~np.isin(truth_classes, UNLABELLED_CLASSES)
    truth = truth_classes[labelled] == BUILDING_CLASS
    return scores(confusion_matrix(truth, np.asarray(predicted_building, bool)[labelled]))


def tree_scores(tree_like: np.ndarray, truth_classes: np.ndarray, predicted_building: np.ndarray) -> dict[str, Any]:
    """Scores on every point, where labelled scores are blind (class 1 holds AHN3's trees): the share of the
    ``tree_like`` points (:func:`lidarmap.segment.vegetation.tree_like`) predicted building, and the share of the
    points the model adds to class 6 (predicted building, not labelled 6) that are tree-like."""
    predicted = np.asarray(predicted_building, bool)
    tree_like = np.asarray(tree_like, bool)
    added = predicted & (np.asarray(truth_classes) != BUILDING_CLASS)
    n_tree, n_added = int(tree_like.sum()), int(added.sum())
    return {
        "tree_like_points": n_tree,
        "tree_like_false_positive_rate": float((predicted & tree_like).sum() / n_tree) if n_tree else float("nan"),
        "added_points": n_added,
        "added_tree_like_share": float((added & tree_like).sum() / n_added) if n_added else float("nan"),
    }


def combine_tree_scores(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`tree_scores` of several parts together (weighted by their counts)."""
    n_tree = sum(p["tree_like_points"] for p in parts)
    n_added = sum(p["added_points"] for p in parts)
    fp = sum(p["tree_like_false_positive_rate"] * p["tree_like_points"] for p in parts if p["tree_like_points"])
    added = sum(p["added_tree_like_share"] * p["added_points"] for p in parts if p["added_points"])
    return {"tree_like_points": n_tree,
            "tree_like_false_positive_rate": fp / n_tree if n_tree else float("nan"),
            "added_points": n_added, "added_tree_like_share": added / n_added if n_added else float("nan")}
