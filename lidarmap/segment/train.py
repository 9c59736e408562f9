"""Training the PointNet++ building segmenter (building = class 6 vs labelled not-building; class 0/1 ignored)."""

from __future__ import annotations

import dataclasses
import datetime
import math
import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import torch
from torch.nn import functional as F

from lidarmap.config import check_params
from lidarmap.core import PointCloud
from lidarmap.errors import InputError
from lidarmap.segment.blocks import (
    IGNORE,
    TrainingSource,
    binary_labels,
    class_weights,
    hide_labels,
    make_source,
    spatial_split,
    training_block,
)
from lidarmap.segment.features import FeatureSpec, Transform, point_features
from lidarmap.segment.metrics import confusion_matrix, scores
from lidarmap.segment.modelfile import SegmentModel
from lidarmap.segment.pointnet2 import Arch, PointNet2Seg
from lidarmap.segment.predict import (
    PredictParams,
    pick_device,
    predict_pointnet2,
    torch_threads,
)

#: Area cells (m) used to measure how much ground the training data covers (for the automatic epoch size).
AREA_CELL = 4.0


@dataclasses.dataclass(frozen=True)
class TrainParams:
    """Training of ``lidarmap segment train`` (``[segment_train]`` table). Defaults follow the paper (sec. 3.2).

    seed (0): seeds block sampling, augmentation, weight initialisation, dropout and the validation split.
    split_seed (-1): seeds the validation split instead of ``seed`` when >= 0, so that models trained with
        different seeds are validated on the same squares (and can be compared on validation, not on held-out data).
    epochs (64): passes; an epoch is ``blocks_per_epoch`` random blocks.
    batch_size (32): blocks per optimiser step.
    learning_rate (0.01), weight_decay (1e-4): Adam.
    lr_step (10), lr_gamma (0.7): the learning rate is multiplied by lr_gamma every lr_step epochs (StepLR).
    block_size (32.0): block edge, metres.
    block_points (4096): points per block fed to the network (subsampled, or padded by repeats).
    blocks_per_epoch (0): blocks per epoch; 0 = ``coverage`` times the training area over one block's area.
    coverage (4.0): see blocks_per_epoch.
    building_centres (0.3): fraction of blocks centred on a building point (the others on any labelled point);
        keeps buildings frequent in areas dominated by ground and trees.
    estimated_ground (0.5): fraction of blocks whose height above ground comes from the estimated ground instead
        of class 2, so the model also works on files without a ground class (and on hidden labels).
    rotate (True): random rotation about z.
    scale_min (0.9), scale_max (1.1): random uniform scaling of xyz and height above ground.
    jitter (0.02): standard deviation (m) of Gaussian noise added to xyz (clipped at 3 sigma).
    val_fraction (0.3): when no validation data is given, this fraction of ``split_cell`` squares (seeded) is
        held out of every training file (at least one square of a file with two or more; 0 = none).
    split_cell (32.0): square size (m) of that spatial split.
    val_every (8): validate every this many epochs (and after the last one); 0 = only after the last.
    use_rgb (False): feed colour (+ presence flag) to the network; the default model is trained without, so it
        works on files without colour.
    device ("auto"): "cpu", "cuda" or "auto".
    threads (0): torch CPU threads; 0 = one per core.
    swa_epochs (0): after the last epoch, this many more at the last learning rate, and the model returned is the
        average of the weights at the end of each of them (stochastic weight averaging: a flatter minimum, the
        same network cost at inference); 0 = the last epoch's weights.
    swa_bn_batches (16): batches run through the averaged network to recompute its BatchNorm statistics (the
        averaged weights' own; the running statistics of any single epoch do not fit them).
    """

    section = "segment_train"
    constraints: ClassVar[dict[str, str]] = {
        "seed": ">= 0",
        "split_seed": ">= -1",
        "epochs": ">= 0",
        "batch_size": ">= 0",
        "learning_rate": ">= 0",
        "weight_decay": ">= 0",
        "lr_step": ">= 0",
        "lr_gamma": ">= 0",
        "block_size": ">= 0",
        "block_points": ">= 0",
        "blocks_per_epoch": ">= 0",
        "coverage": ">= 0",
        "building_centres": ">= 0",
        "estimated_ground": ">= 0",
        "scale_min": ">= 0",
        "scale_max": ">= 0",
        "jitter": ">= 0",
        "val_fraction": ">= 0",
        "split_cell": ">= 0",
        "val_every": ">= 0",
        "device": "in auto, cpu, cuda",
        "threads": ">= 0",
        "swa_epochs": ">= 0",
        "swa_bn_batches": ">= 0",
    }

    seed: int = 0
    split_seed: int = -1
    epochs: int = 64
    batch_size: int = 32
    learning_rate: float = 0.01
    weight_decay: float = 1e-4
    lr_step: int = 10
    lr_gamma: float = 0.7
    block_size: float = 32.0
    block_points: int = 4096
    blocks_per_epoch: int = 0
    coverage: float = 4.0
    building_centres: float = 0.3
    estimated_ground: float = 0.5
    rotate: bool = True
    scale_min: float = 0.9
    scale_max: float = 1.1
    jitter: float = 0.02
    val_fraction: float = 0.3
    split_cell: float = 32.0
    val_every: int = 8
    use_rgb: bool = False
    device: str = "auto"
    threads: int = 0
    swa_epochs: int = 0
    swa_bn_batches: int = 16

    def __post_init__(self) -> None:
        check_params(self)
        positive = ("epochs", "batch_size", "learning_rate", "lr_step", "block_size", "block_points", "coverage",
                    "split_cell")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive")
        for name in ("building_centres", "estimated_ground"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1]")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError("val_fraction must be in [0, 1)")
        if not 0 < self.scale_min <= self.scale_max:
            raise ValueError("need 0 < scale_min <= scale_max")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError("device must be auto, cpu or cuda")

    @property
    def spec(self) -> FeatureSpec:
        return FeatureSpec(use_rgb=self.use_rgb, block_size=self.block_size)


@dataclasses.dataclass
class TrainResult:
    model: SegmentModel
    history: list[dict[str, Any]]


def augmentation(params: TrainParams, rng: np.random.Generator) -> Transform:
    """A random z-rotation, uniform scaling and jitter, drawn once per block."""
    angle = rng.uniform(0.0, 2.0 * math.pi) if params.rotate else 0.0
    scale = rng.uniform(params.scale_min, params.scale_max)
    c, s = math.cos(angle), math.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], np.float32)
    seed = int(rng.integers(2**63))

    def transform(xyz: np.ndarray, hag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        noise = np.random.default_rng(seed).normal(0.0, params.jitter, xyz.shape)
        noise = np.clip(noise, -3 * params.jitter, 3 * params.jitter).astype(np.float32)
        out = (xyz @ rotation.T) * np.float32(scale) + noise
        return out.astype(np.float32), (hag * np.float32(scale) + noise[:, 2]).astype(np.float32)

    return transform


def covered_area(xy: np.ndarray) -> float:
    """Area (m2) of the occupied AREA_CELL squares."""
    cells = np.unique(np.floor(xy / AREA_CELL).astype(np.int64), axis=0)
    return float(len(cells) * AREA_CELL**2)


def split_clouds(clouds: list[tuple[str, PointCloud]], params: TrainParams
                 ) -> tuple[list[tuple[str, PointCloud]], list[tuple[str, PointCloud]]]:
    """Seeded spatial train/validation split of every cloud (whole ``split_cell`` squares)."""
    rng = np.random.default_rng([params.seed if params.split_seed < 0 else params.split_seed, 1])
    train, val = [], []
    for name, cloud in clouds:
        mask = spatial_split(cloud.xyz[:, :2], params.split_cell, params.val_fraction, rng)
        train.append((name, cloud.subset(~mask)))
        if mask.any():
            val.append((f"{name} (val)", cloud.subset(mask)))
    return train, val


def prepare_sources(clouds: list[tuple[str, PointCloud]], spec: FeatureSpec) -> list[TrainingSource]:
    sources = []
    for name, cloud in clouds:
        if len(cloud) == 0:
            continue
        classification = cloud.attrs.get("classification")
        if classification is None:
            raise InputError("training file has no classification", name)
        sources.append(make_source(name, point_features(cloud, spec), point_features(hide_labels(cloud), spec),
                                   classification))
    if not any(len(s.labelled) for s in sources):
        raise InputError("training data has no labelled points (all unclassified)")
    return sources


def validate(model: SegmentModel, clouds: list[tuple[str, PointCloud]], device: str, seed: int,
             threads: int = 0) -> dict[str, Any]:
    """Scores on validation clouds predicted with their labels hidden (as on an unlabelled acquisition)."""
    conf = np.zeros((2, 2), np.int64)
    for _, cloud in clouds:
        labels = binary_labels(cloud.attrs["classification"])
        keep = labels != IGNORE
        if not keep.any():
            continue
        prob = predict_pointnet2(hide_labels(cloud), model, PredictParams(device=device, seed=seed, threads=threads))
        conf += confusion_matrix(labels[keep], prob[keep] >= 0.5)
    return scores(conf)


def _batch(sources: list[TrainingSource], weights: np.ndarray, params: TrainParams, spec: FeatureSpec,
           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    blocks = []
    for _ in range(params.batch_size):
        source = sources[rng.choice(len(sources), p=weights)]
        blocks.append(training_block(source, spec, params.block_points, rng,
                                     building_centre=rng.random() < params.building_centres,
                                     estimated_ground=rng.random() < params.estimated_ground,
                                     transform=augmentation(params, rng)))
    return tuple(np.stack(parts) for parts in zip(*blocks))  # type: ignore[return-value]


@dataclasses.dataclass
class TrainingPlan:
    """What one training run works on: the sources, how blocks are drawn from them, the epoch size."""

    sources: list[TrainingSource]
    val_clouds: list[tuple[str, PointCloud]]
    split: str  # how the validation data was chosen (recorded in the model file)
    class_weights: np.ndarray  # loss weights (eq. 1)
    pick: np.ndarray  # probability of drawing a block from each source
    steps: int  # optimiser steps per epoch
    labels: np.ndarray  # every source's labels, concatenated (class frequencies)


def block_shares(sources: list[TrainingSource], clouds: list[tuple[str, PointCloud]],
                 source_weights: list[float] | None) -> np.ndarray:
    """Normalised probability of drawing a block from each source: ``source_weights`` (one per cloud; empty
    clouds made no source) or, by default, in proportion to the labelled points."""
    pick = np.array([len(s.labelled) for s in sources] if source_weights is None else
                    [w for w, (_, c) in zip(source_weights, clouds) if len(c)], np.float64)
    if len(pick) != len(sources) or not np.all(pick >= 0) or pick.sum() <= 0:
        raise ValueError("source_weights: one non-negative weight per training cloud, not all zero")
    return pick / pick.sum()


def plan_training(clouds: list[tuple[str, PointCloud]], params: TrainParams,
                  val_clouds: list[tuple[str, PointCloud]] | None, source_weights: list[float] | None
                  ) -> TrainingPlan:
    """Split off validation data (unless given), compute the features, the loss weights and the epoch size."""
    split = "given validation data" if val_clouds is not None else (
        f"spatial: {params.val_fraction:.0%} of {params.split_cell:g} m squares (seed {params.seed})")
    if val_clouds is None:
        clouds, val_clouds = split_clouds(clouds, params)
    sources = prepare_sources(clouds, params.spec)
    labels = np.concatenate([s.labels for s in sources])
    area = sum(covered_area(s.features.xyz[:, :2]) for s in sources)
    blocks = params.blocks_per_epoch or math.ceil(params.coverage * area / params.block_size**2)
    return TrainingPlan(sources, val_clouds, split, class_weights(labels),
                        block_shares(sources, clouds, source_weights), max(1, math.ceil(blocks / params.batch_size)),
                        labels)


def run_epoch(net: PointNet2Seg, optimiser: torch.optim.Optimizer, plan: TrainingPlan, params: TrainParams,
              rng: np.random.Generator, device: torch.device, loss_weight: torch.Tensor) -> float:
    """One epoch of ``plan.steps`` optimiser steps; the mean loss."""
    net.train()
    losses = []
    for _ in range(plan.steps):
        xyz, channels, labels = (torch.from_numpy(a).to(device)
                                 for a in _batch(plan.sources, plan.pick, params, params.spec, rng))
        logits = net(xyz, channels)
        loss = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), labels.reshape(-1), weight=loss_weight,
                               ignore_index=IGNORE)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
    return float(np.mean(losses))


def running_average(average: dict[str, torch.Tensor] | None, net: torch.nn.Module,
                    count: int) -> dict[str, torch.Tensor]:
    """The mean of the network's parameters over ``count`` snapshots: ``average`` (of ``count - 1``) updated with
    the current ones. Parameters only: BatchNorm buffers are recomputed for the averaged weights."""
    current = {name: p.detach().clone() for name, p in net.named_parameters()}
    if average is None:
        return current
    return {name: average[name] + (current[name] - average[name]) / count for name in current}


def averaged_model(net: PointNet2Seg, model: SegmentModel, average: dict[str, torch.Tensor], plan: TrainingPlan,
                   params: TrainParams, rng: np.random.Generator, device: torch.device,
                   started: float) -> dict[str, Any]:
    """Load the averaged weights into ``net``, recompute its BatchNorm statistics, validate: the history entry of
    the averaged model."""
    net.load_state_dict(average, strict=False)
    recompute_batch_norm(net, plan, params, rng, device)
    entry: dict[str, Any] = {"epoch": params.epochs + params.swa_epochs, "averaged": params.swa_epochs,
                             "seconds": round(time.perf_counter() - started, 1)}
    if plan.val_clouds:
        net.eval()
        entry["val"] = validate(model, plan.val_clouds, params.device, params.seed, params.threads)
    return entry


def recompute_batch_norm(net: PointNet2Seg, plan: TrainingPlan, params: TrainParams, rng: np.random.Generator,
                         device: torch.device) -> None:
    """BatchNorm running statistics of the (averaged) network, from ``swa_bn_batches`` training batches: a
    cumulative mean over them (momentum None), as the averaged weights never ran forward before."""
    norms = [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None
    net.train()
    with torch.no_grad():
        for _ in range(params.swa_bn_batches):
            xyz, channels, _ = (torch.from_numpy(a).to(device)
                                for a in _batch(plan.sources, plan.pick, params, params.spec, rng))
            net(xyz, channels)
    for m, momentum in zip(norms, momenta):
        m.momentum = momentum


def training_record(plan: TrainingPlan, params: TrainParams, history: list[dict[str, Any]], seconds: float,
                    device: torch.device, threads: int) -> dict[str, Any]:
    """What the model file says about its training (data, parameters, history, validation scores)."""
    labels = plan.labels
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "seed": params.seed,
        "params": dict(dataclasses.asdict(params).items()),
        "data": [{"name": s.name, "points": len(s.labels), "labelled": len(s.labelled),
                  "buildings": len(s.buildings), "block_share": float(w)}
                 for s, w in zip(plan.sources, plan.pick)],
        "validation": [{"name": n, "points": len(c)} for n, c in plan.val_clouds or []],
        "split": plan.split,
        "epochs": params.epochs,
        "steps_per_epoch": plan.steps,
        "class_frequencies": (np.bincount(labels[labels != IGNORE], minlength=2) /
                              max(1, int((labels != IGNORE).sum()))).tolist(),
        "history": [{k: v for k, v in h.items() if k != "val"} for h in history],
        "metrics": next((h["val"] for h in reversed(history) if "val" in h), None),
        "seconds": round(seconds, 1),
        "device": str(device),
        "threads": threads,
        "torch": str(torch.__version__),
    }


def train(clouds: list[tuple[str, PointCloud]], params: TrainParams = TrainParams(),
          val_clouds: list[tuple[str, PointCloud]] | None = None, arch: Arch | None = None,
          source_weights: list[float] | None = None,
          report: Callable[[dict[str, Any]], None] | None = None) -> TrainResult:
    """Train on ``clouds`` (name, cloud); validate on ``val_clouds`` or on a seeded spatial split of ``clouds``.

    Blocks are drawn from cloud i with probability ``source_weights[i]`` (normalised; default: in proportion to
    its labelled points). The model of the last epoch is returned (no selection on the validation data, so its
    scores stay honest).
    """
    started = time.perf_counter()
    plan = plan_training(clouds, params, val_clouds, source_weights)
    arch = arch or Arch(in_channels=len(params.spec.channels))
    rng = np.random.default_rng([params.seed, 0])
    device = pick_device(params.device)
    history: list[dict[str, Any]] = []
    cuda = [device.index or 0] if device.type == "cuda" else []
    with torch_threads(params.threads), torch.random.fork_rng(devices=cuda):
        threads = torch.get_num_threads()
        torch.manual_seed(params.seed)
        net = PointNet2Seg(arch).to(device)
        model = SegmentModel(net, params.spec, params.block_points, plan.class_weights.tolist())
        optimiser = torch.optim.Adam(net.parameters(), lr=params.learning_rate, weight_decay=params.weight_decay)
        scheduler = torch.optim.lr_scheduler.StepLR(optimiser, step_size=params.lr_step, gamma=params.lr_gamma)
        loss_weight = torch.tensor(plan.class_weights, dtype=torch.float32, device=device)
        average: dict[str, torch.Tensor] | None = None
        for epoch in range(1, params.epochs + params.swa_epochs + 1):
            entry: dict[str, Any] = {"epoch": epoch,
                                     "loss": run_epoch(net, optimiser, plan, params, rng, device, loss_weight),
                                     "lr": optimiser.param_groups[0]["lr"],
                                     "seconds": round(time.perf_counter() - started, 1)}
            if epoch < params.epochs:
                scheduler.step()  # the averaging epochs keep the last learning rate
            elif epoch > params.epochs:
                average = running_average(average, net, epoch - params.epochs)
                entry["swa"] = True
            due = epoch == params.epochs or (params.val_every and epoch % params.val_every == 0
                                             and epoch < params.epochs)
            if due and plan.val_clouds:
                net.eval()
                entry["val"] = validate(model, plan.val_clouds, params.device, params.seed, params.threads)
            history.append(entry)
            if report:
                report(entry)
        if average is not None:
            history.append(averaged_model(net, model, average, plan, params, rng, device, started))
            if report:
                report(history[-1])
    net.eval().cpu()
    model.net = net
    model.training = training_record(plan, params, history, time.perf_counter() - started, device, threads)
    return TrainResult(model, history)
