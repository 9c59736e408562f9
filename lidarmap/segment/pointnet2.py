"""PointNet++ semantic segmentation (single-scale grouping), written for metric aerial blocks.

Set abstraction (SA): farthest point sampling picks centroids, a metric ball query with a per-centroid KNN fallback
groups neighbours (:func:`lidarmap.segment.neighbors.ball_query`), a shared MLP on [relative xyz / radius, features]
and a max over the group give each centroid a feature. Feature propagation (FP): inverse-distance interpolation from
the 3 nearest coarse points, concatenated with the skip features of the finer level, then a shared MLP.

Shared MLPs are ``Linear`` layers on the last dimension (one large matrix product each on CPU); at inference
:meth:`PointNet2Seg.fused` folds the batch norms into them.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from lidarmap.segment.neighbors import ball_query, farthest_point_sampling, gather, knn


@dataclasses.dataclass(frozen=True)
class Arch:
    """Architecture hyper-parameters (stored in the model file).

    in_channels: input channels per point (``FeatureSpec.channels``).
    num_classes: output classes (2: not-building, building).
    sa_npoints: centroids per set-abstraction level (from a block of ``points`` points).
    sa_radii: ball radius per level, metres (aerial density: 1 m on 4 pts/m2 samples up to 8 m for the top level).
    sa_nsample: neighbours per centroid and level.
    sa_mlps: shared MLP widths per level.
    fp_mlps: shared MLP widths of the propagation levels, coarse to fine.
    head: width of the per-point classifier layer.
    min_in_ball: a centroid whose ball holds fewer points falls back to its nsample nearest neighbours.
    dropout: dropout before the last layer (training only).
    """

    in_channels: int
    num_classes: int = 2
    sa_npoints: tuple[int, ...] = (1024, 256, 64, 16)
    sa_radii: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
    sa_nsample: tuple[int, ...] = (16, 16, 16, 16)
    sa_mlps: tuple[tuple[int, ...], ...] = ((32, 32, 64), (64, 64, 128), (128, 128, 256), (256, 256, 256))
    fp_mlps: tuple[tuple[int, ...], ...] = ((256, 256), (256, 128), (128, 128), (128, 64))
    head: int = 64
    min_in_ball: int = 4
    dropout: float = 0.5

    def to_dict(self) -> dict[str, Any]:
        return {k: _listify(v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Arch":
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: _tuplify(v) for k, v in data.items() if k in fields})


def _listify(v: Any) -> Any:
    return [_listify(x) for x in v] if isinstance(v, (tuple, list)) else v


def _tuplify(v: Any) -> Any:
    return tuple(_tuplify(x) for x in v) if isinstance(v, (tuple, list)) else v


class SharedMLP(nn.Module):
    """Linear + BatchNorm + ReLU layers applied to the last dimension of any (..., C) tensor."""

    def __init__(self, widths: list[int]):
        super().__init__()
        self.linears = nn.ModuleList(nn.Linear(a, b, bias=False) for a, b in zip(widths[:-1], widths[1:]))
        self.norms = nn.ModuleList(nn.BatchNorm1d(b) for b in widths[1:])

    def _activate(self, x: torch.Tensor, layer: int) -> torch.Tensor:
        shape = x.shape
        return torch.relu_(self.norms[layer](x.reshape(-1, shape[-1]))).reshape(shape)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.after_first(self.linears[0](x))

    def after_first(self, x: torch.Tensor) -> torch.Tensor:
        """The MLP given the output of its first linear layer (callers that compute it more cheaply)."""
        x = self._activate(x, 0)
        for layer in range(1, len(self.linears)):
            x = self._activate(self.linears[layer](x), layer)
        return x

    def first_parts(self, split: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Weights of the first layer for input channels [:split] and [split:], and its bias."""
        first = self.linears[0]
        return first.weight[:, :split], first.weight[:, split:], first.bias

    def fuse(self) -> None:
        """Fold each (eval-mode) batch norm into its linear layer: same outputs, half the passes over memory."""
        fused = nn.ModuleList()
        for linear, norm in zip(self.linears, self.norms):
            scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
            layer = nn.Linear(linear.in_features, linear.out_features, bias=True)
            layer.weight.data = linear.weight.data * scale[:, None]
            layer.bias.data = norm.bias.data - norm.running_mean * scale
            fused.append(layer)
        self.linears = fused
        self.norms = nn.ModuleList(nn.Identity() for _ in fused)


class SetAbstraction(nn.Module):
    def __init__(self, npoint: int, radius: float, nsample: int, in_channels: int, widths: tuple[int, ...],
                 min_in_ball: int):
        super().__init__()
        self.npoint, self.radius, self.nsample, self.min_in_ball = npoint, radius, nsample, min_in_ball
        self.mlp = SharedMLP([in_channels + 3, *widths])

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor, backend: str) -> tuple[torch.Tensor, torch.Tensor]:
        centre_idx = farthest_point_sampling(xyz, self.npoint)
        centres = gather(xyz, centre_idx)
        idx, _ = ball_query(centres, xyz, self.radius, self.nsample, self.min_in_ball, backend)
        # first layer on [(x_j - c) / r, f_j] = (W_x x_j / r + W_f f_j) - W_x c / r: computed once per point and
        # once per centroid instead of once per (centroid, neighbour) pair -- same result, a quarter of the work
        w_xyz, w_feat, bias = self.mlp.first_parts(3)
        w_xyz = w_xyz / self.radius
        per_point = F.linear(xyz, w_xyz) + F.linear(feats, w_feat, bias)
        grouped = gather(per_point, idx) - F.linear(centres, w_xyz).unsqueeze(2)
        return centres, self.mlp.after_first(grouped).amax(dim=2)


class FeaturePropagation(nn.Module):
    def __init__(self, in_channels: int, widths: tuple[int, ...]):
        super().__init__()
        self.mlp = SharedMLP([in_channels, *widths])

    def forward(self, fine_xyz: torch.Tensor, coarse_xyz: torch.Tensor, fine_feats: torch.Tensor,
                coarse_feats: torch.Tensor, backend: str) -> torch.Tensor:
        _, idx = knn(fine_xyz, coarse_xyz, 3, backend)
        d2 = ((gather(coarse_xyz, idx) - fine_xyz.unsqueeze(2)) ** 2).sum(-1)
        weight = 1.0 / (d2 + 1e-4)  # squared-distance weights: a near coarse point dominates
        weight = weight / weight.sum(-1, keepdim=True)
        # the first layer is linear, so it is applied to the (fewer) coarse points before interpolating
        w_coarse, w_fine, bias = self.mlp.first_parts(coarse_feats.shape[-1])
        projected = F.linear(coarse_feats, w_coarse)
        out = F.linear(fine_feats, w_fine, bias)
        for k in range(idx.shape[-1]):
            out = out + weight[..., k:k + 1] * gather(projected, idx[..., k])
        return self.mlp.after_first(out)


class PointNet2Seg(nn.Module):
    """Per-point class logits (B, N, num_classes) from block xyz (B, N, 3, metres) and channels (B, N, C)."""

    def __init__(self, arch: Arch):
        super().__init__()
        self.arch = arch
        self.neighbor_backend = "auto"
        channels = [arch.in_channels]
        self.sa = nn.ModuleList()
        for npoint, radius, nsample, widths in zip(arch.sa_npoints, arch.sa_radii, arch.sa_nsample, arch.sa_mlps):
            self.sa.append(SetAbstraction(npoint, radius, nsample, channels[-1], widths, arch.min_in_ball))
            channels.append(widths[-1])
        self.fp = nn.ModuleList()
        below = channels[-1]
        for level, widths in enumerate(arch.fp_mlps):
            skip = channels[-2 - level]
            self.fp.append(FeaturePropagation(below + skip, widths))
            below = widths[-1]
        self.head = SharedMLP([below, arch.head])
        self.dropout = nn.Dropout(arch.dropout)
        self.classifier = nn.Linear(arch.head, arch.num_classes)

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        levels = [(xyz, feats)]
        for sa in self.sa:
            levels.append(sa(*levels[-1], self.neighbor_backend))
        coarse_xyz, coarse_feats = levels[-1]
        for i, fp in enumerate(self.fp):
            fine_xyz, fine_feats = levels[-2 - i]
            coarse_feats = fp(fine_xyz, coarse_xyz, fine_feats, coarse_feats, self.neighbor_backend)
            coarse_xyz = fine_xyz
        return self.classifier(self.dropout(self.head(coarse_feats)))

    def fused(self) -> "PointNet2Seg":
        """An eval-mode copy with batch norms folded into the linear layers (inference only)."""
        model = copy.deepcopy(self).eval()
        for module in model.modules():
            if isinstance(module, SharedMLP):
                module.fuse()
        return model
