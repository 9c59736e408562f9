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
