"""Segmentation model files: ``torch.save`` of a plain dict, loadable with ``torch.load(weights_only=True)``.

Contents (all tensors, numbers, strings, lists and dicts -- nothing that needs unpickling code):

``format``/``version``; ``state_dict`` (weights); ``arch`` (:class:`~lidarmap.segment.pointnet2.Arch`);
``features`` (:class:`~lidarmap.segment.features.FeatureSpec` incl. its channel list); ``block_points``;
``class_weights`` and ``classes``; ``frame`` (coordinate conventions); ``training`` (data, split, parameters,
epochs, metrics, date, seed, time).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from lidarmap.io.atomic import atomic_path
from lidarmap.io.torchfile import read_torch_file
from lidarmap.segment.features import FeatureSpec, ModelSpecError, check_spec
from lidarmap.segment.metrics import CLASS_NAMES
from lidarmap.segment.pointnet2 import Arch, PointNet2Seg
from lidarmap.weights import WEIGHTS_DIR

FORMAT = "lidarmap-segment-pointnet2"
FORMAT_VERSION = 1
MODELS_DIR = WEIGHTS_DIR
DEFAULT_MODEL = MODELS_DIR / "segment_pointnet2.pt"

#: How block coordinates relate to the CRS (stored so that other tools can reproduce the input exactly).
FRAME_CONVENTIONS = {
    "units": "metres (CRS axis units converted with the CRS's unit factor; a file without CRS is taken as metres)",
    "xy": "x, y minus the block centre (a LocalFrame offset keeps float64 precision before the float32 cast)",
    "z": "z minus the median ground height of the block's points; z up",
    "hag": "z minus the ground surface (class 2 when present, else the morphological estimate)",
}


@dataclasses.dataclass
class SegmentModel:
    """A trained PointNet++ with everything needed to feed it."""

    net: PointNet2Seg
    spec: FeatureSpec
    block_points: int
    class_weights: list[float]
    training: dict[str, Any] = dataclasses.field(default_factory=dict)
    source: str | None = None

    @property
    def arch(self) -> Arch:
        return self.net.arch


def model_to_dict(model: SegmentModel) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.net.state_dict().items()},
        "arch": model.arch.to_dict(),
        "features": model.spec.to_dict(),
        "block_points": int(model.block_points),
        "class_weights": [float(w) for w in model.class_weights],
        "classes": list(CLASS_NAMES),
        "frame": dict(FRAME_CONVENTIONS),
        "training": model.training,
    }


def save_model(path: str | Path, model: SegmentModel) -> Path:
    """Write the model file atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(model_to_dict(model), tmp)
    return path


def model_from_dict(data: dict[str, Any], source: str | None = None,
                    expected_spec: FeatureSpec | None = None) -> SegmentModel:
    """Rebuild a model; a wrong format, another feature spec or mismatched weights are one-line errors."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ModelSpecError(f"not a {FORMAT} model file", source)
    if data.get("version") != FORMAT_VERSION:
        raise ModelSpecError(f"model file version {data.get('version')} is not supported (expected "
                             f"{FORMAT_VERSION})", source)
    spec = check_spec(data.get("features") or {}, source)
    if expected_spec is not None and spec != expected_spec:
        differ = [f.name for f in dataclasses.fields(FeatureSpec)
                  if getattr(spec, f.name) != getattr(expected_spec, f.name)]
        raise ModelSpecError(f"model's feature spec differs from the one asked for in: {', '.join(differ)}", source)
    try:
        arch = Arch.from_dict(data["arch"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelSpecError(f"invalid architecture in model file ({exc})", source) from None
    if arch.in_channels != len(spec.channels):
        raise ModelSpecError(f"model takes {arch.in_channels} input channels but its feature spec has "
                             f"{len(spec.channels)}", source)
    net = PointNet2Seg(arch)
    try:
        net.load_state_dict(data["state_dict"])
    except (KeyError, RuntimeError) as exc:
        raise ModelSpecError(f"weights do not fit the architecture ({str(exc).splitlines()[0]})", source) from None
    return SegmentModel(net.eval(), spec, int(data["block_points"]), list(data["class_weights"]),
                        dict(data.get("training") or {}), source)


def load_model(path: str | Path | None = None, expected_spec: FeatureSpec | None = None) -> SegmentModel:
    """Load a model file (the shipped default when ``path`` is None) onto the CPU."""
    path, data = read_torch_file(path, DEFAULT_MODEL, "model file", "scripts/train_segmentation.py")
    return model_from_dict(data, str(path), expected_spec)
