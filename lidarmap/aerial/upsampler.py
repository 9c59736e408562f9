"""The learned upsampler: a small implicit patch model in the spirit of SAPCU (Zhao et al., CVPR 2022).

SAPCU draws seed points around a shape and moves each onto the surface along a predicted direction by a predicted
distance. Here the same idea is local and metric-free, so it runs on buildings of any size and density on a CPU:

* seeds are drawn around the input points that should get new neighbours and lie on a flat local surface
  (isotropic Gaussian, sigma = ``seed_sigma`` x the local sample spacing);
* for a seed the model sees its ``k`` nearest input points, as coordinates relative to the seed divided by the local
  spacing (float32, z stays up: gravity is meaningful for buildings), and predicts its move onto the surface (in
  spacing units; SAPCU's projection direction and distance are its direction and length);
* a moved seed is kept only when an input point lies within ``reach`` x the spacing (nothing far from the data).

:class:`PatchProjector` is a two-stage PointNet over the patch (shared MLP, max-pooled context fed back, max + mean
pooling, MLP head), about 20 k weights. It is trained self-supervised by ``scripts/train_upsampler.py`` (sparse
input -> dense surface: simulated airborne scans against dense samples of the simulator's exact building surfaces,
windows included, and real class-6 points thinned against all of them); the shipped weights are
``lidarmap/weights/upsampler.pt``.

Model file: ``torch.save`` of a plain dict (``format``, ``version``, ``arch``, ``state_dict``, ``inference``,
``training``), loadable with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn
from torch.nn import functional as F

from lidarmap.aerial.surface import flat_points, knn, local_spacing
from lidarmap.errors import InputError
from lidarmap.io.atomic import atomic_path
from lidarmap.io.torchfile import read_torch_file
from lidarmap.weights import WEIGHTS_DIR

__all__ = ["UpsamplerArch", "PatchProjector", "LearnedUpsampler", "patch_inputs", "load_upsampler",
           "save_upsampler", "DEFAULT_WEIGHTS", "FORMAT"]

FORMAT = "lidarmap-upsampler"
FORMAT_VERSION = 1
DEFAULT_WEIGHTS = WEIGHTS_DIR / "upsampler.pt"


@dataclasses.dataclass(frozen=True)
class UpsamplerArch:
    """k: input points per patch; width: channels of the first shared MLP (the rest scale with it)."""

    k: int = 16
    width: int = 64

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "UpsamplerArch":
        return cls(k=int(data["k"]), width=int(data["width"]))


class PatchProjector(nn.Module):
    """Patch (B, k, 3) relative to the seed, in spacing units -> the seed's move onto the surface (B, 3).

    The move is predicted as one vector (its direction and length are SAPCU's projection direction and distance):
    a unit direction times a separate non-negative distance has a dead start -- with random directions the best
    distance is 0, and then the directions get no gradient.
    """

    def __init__(self, arch: UpsamplerArch = UpsamplerArch()):
        super().__init__()
        self.arch = arch
        w = arch.width
        self.local = nn.Sequential(nn.Linear(4, w), nn.ReLU(), nn.Linear(w, w), nn.ReLU())
        self.mix = nn.Sequential(nn.Linear(2 * w, 2 * w), nn.ReLU(), nn.Linear(2 * w, 2 * w), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(4 * w, 2 * w), nn.ReLU(), nn.Linear(2 * w, w), nn.ReLU(),
                                  nn.Linear(w, 3))

    def forward(self, rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.local(torch.cat([rel, rel.norm(dim=2, keepdim=True)], dim=2))
        context = h.max(dim=1, keepdim=True).values.expand_as(h)  # every point sees the whole patch
        h = self.mix(torch.cat([h, context], dim=2))
        return self.head(torch.cat([h.max(dim=1).values, h.mean(dim=1)], dim=1))

    def offset(self, rel: torch.Tensor) -> torch.Tensor:
        """The predicted move of each seed (B, 3), in spacing units."""
        return self(rel)

    def direction_distance(self, rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The move as SAPCU states it: unit direction (B, 3) and distance (B,)."""
        move = self(rel)
        return F.normalize(move, dim=1, eps=1e-9), move.norm(dim=1)


def patch_inputs(xyz: np.ndarray, tree: cKDTree, seeds: np.ndarray, scale: np.ndarray, k: int) -> np.ndarray:
    """Network input for seeds: their k nearest points of ``xyz`` minus the seed, divided by ``scale`` (float32,
    (M, k, 3)). With fewer than k points the nearest ones repeat (max pooling does not change)."""
    kk = min(k, len(xyz))
    _, nb = tree.query(seeds, k=kk)
    nb = nb.reshape(len(seeds), kk)
    if kk < k:
        nb = nb[:, np.arange(k) % kk]
    return ((xyz[nb] - seeds[:, None]) / scale[:, None, None]).astype(np.float32)


@dataclasses.dataclass
class LearnedUpsampler:
    """:class:`~lidarmap.aerial.densify.Upsampler` around a trained :class:`PatchProjector` (see the module docstring).

    seed_sigma (0.5): seeds ~ N(point, (seed_sigma x spacing)²) per axis; reach (1.0): a moved seed is kept only
    with an input point within reach x spacing; batch (8192): seeds per forward pass; spacing_k (8): neighbours of
    the local spacing (as in the geometric upsampler); flat_only (True): seed only around points on a flat local
    surface (:func:`lidarmap.aerial.surface.flat_points`, default thresholds), as the geometric upsampler does -- without
    it, seeds around segmentation noise are projected onto whatever surface is near and multiply the noise.
    ``training``: what the weights were trained on.
    """

    net: PatchProjector
    seed_sigma: float = 0.5
    reach: float = 1.0
    batch: int = 8192
    spacing_k: int = 8
    flat_only: bool = True
    training: dict = dataclasses.field(default_factory=dict)
    name: typing.ClassVar[str] = "learned"

    def upsample(self, xyz: np.ndarray, n_new: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        xyz = np.asarray(xyz, dtype=np.float64)
        n_new = np.asarray(n_new, dtype=np.int64)
        if len(xyz) < 3 or n_new.sum() == 0:
            return np.zeros((0, 3))
        if self.flat_only:  # like the geometric upsampler: no seeds around clutter and noise
            n_new = np.where(flat_points(xyz), n_new, 0)
        dist, idx = knn(xyz, self.spacing_k + 1)
        spacing = np.maximum(local_spacing(dist, idx, self.spacing_k), 1e-3)
        owner = np.repeat(np.arange(len(xyz)), np.maximum(n_new, 0))
        scale = spacing[owner]
        seeds = xyz[owner] + rng.normal(size=(len(owner), 3)) * (self.seed_sigma * scale)[:, None]
        tree = cKDTree(xyz)
        moved = np.empty_like(seeds)
        with torch.inference_mode():
            for a in range(0, len(seeds), self.batch):
                sl = slice(a, a + self.batch)
                rel = patch_inputs(xyz, tree, seeds[sl], scale[sl], self.net.arch.k)
                step = self.net.offset(torch.from_numpy(rel)).numpy().astype(np.float64)
                moved[sl] = seeds[sl] + step * scale[sl, None]
        near = tree.query(moved)[0] <= self.reach * scale
        return moved[near]


def save_upsampler(path: str | Path, net: PatchProjector, training: dict[str, Any],
                   inference: dict[str, Any] | None = None) -> Path:
    """Write a model file atomically (byte-identical for identical weights and metadata). ``training`` and
    ``inference`` are stored as plain JSON types, so ``torch.load(weights_only=True)`` reads the file."""
    plain = json.loads(json.dumps({"inference": inference or {}, "training": training}, default=float))
    data = {"format": FORMAT, "version": FORMAT_VERSION, "arch": net.arch.to_dict(),
            "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}, **plain}
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return path


def load_upsampler(path: str | Path | None = None) -> LearnedUpsampler:
    """Load a model file (the shipped weights when ``path`` is None); problems are one-line InputErrors."""
    path, data = read_torch_file(path, DEFAULT_WEIGHTS, "upsampler weights", "scripts/train_upsampler.py")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} model file", path)
    if data.get("version") != FORMAT_VERSION:
        raise InputError(f"upsampler file version {data.get('version')} is not supported (expected "
                         f"{FORMAT_VERSION})", path)
    try:
        net = PatchProjector(UpsamplerArch.from_dict(data["arch"]))
        net.load_state_dict(data["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"weights do not fit the architecture ({str(exc).splitlines()[0]})", path) from None
    inference = {k: v for k, v in dict(data.get("inference") or {}).items()
                 if k in ("seed_sigma", "reach", "spacing_k", "flat_only")}
    return LearnedUpsampler(net.eval(), training=dict(data.get("training") or {}), **inference)
