"""Reproduce the shipped learned upsampler: ``python scripts/train_upsampler.py [--out FILE] [--check]``.

Self-supervised: sparse input points, dense surface targets, no labels beyond "building".

* Simulated: small cities (``SIM_SCENES``, scanned from the air by :func:`lidarmap.sim.simulate`); input = a
  building's airborne points (true building id), target surface = dense samples (``DENSE_PER_M2``) of the exact
  triangles the lasers were traced against (walls with their window holes, reveals, rooms, doors, structures,
  roofs), so seeds in a window opening learn to go to its edges, not to fill it.
* Real: class 6 points of the training part of the real data (:mod:`lidarmap.segment.recipe`; the held-out areas
  are never read); input = a random ``REAL_KEEP`` share of them, target surface = all of them.

Seeds are drawn around input points like at inference (:class:`LearnedUpsampler`: N(point, (sigma x local
spacing)²)), with the wider sigma ``TRAIN_SEED_SIGMA``; the target of a seed is the nearest target-surface point,
the loss a Huber loss on the predicted move (spacing units). Buildings / clouds listed in ``VALIDATION`` are held
out of the fit and report the mean distance of the seeds to the target surface before and after the move.

Same data, seed and thread count (``THREADS``, fixed) give byte-identical weights; ``--check`` trains and compares
against the shipped file instead of writing it. About 8 minutes on 2 busy CPU cores.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.nn import functional as F

from lidarmap.aerial.surface import _knn, local_spacing
from lidarmap.aerial.upsampler import (
    DEFAULT_WEIGHTS,
    PatchProjector,
    UpsamplerArch,
    patch_inputs,
    save_upsampler,
)
from lidarmap.frame import LocalFrame
from lidarmap.segment import recipe
from lidarmap.sim import SimParams, build_city, load_truth, simulate
from lidarmap.sim.mesh import ABSORBER

SEED = 0
THREADS = 2
SIM_SCENES = [SimParams(seed=s, buildings=6, campaigns=0) for s in (2001, 2002)]  # seeds no one else uses
DENSE_PER_M2 = 150.0
REAL_KEEP = 0.35
SEEDS_PER_POINT = {"sim": 2, "real": 1}
MAX_SEEDS = 10000  # per building / cloud
VALIDATION = {"sim 2001 building 6", "real ign_montpellier/test_data_77055_627760_LA93_IGN69.laz"}
ARCH = UpsamplerArch(k=16, width=32)
TRAIN_SEED_SIGMA = 0.5  # training seeds: N(point, (0.5 x spacing)²) ...
# ... at inference seeds start closer (0.3, chosen on the tuning scene, simulated seed 1: new points nearer the true
# surface, fewer in windows, less noise amplification) and only around flat points
INFERENCE = {"seed_sigma": 0.3, "reach": 1.0, "spacing_k": 8, "flat_only": True}
EPOCHS = 8
BATCH = 512
LR = 2e-3
LR_STEP, LR_GAMMA = 3, 0.5
HUBER = 0.2


def log(text: str) -> None:
    print(text, flush=True)


def sample_triangles(tris: np.ndarray, per_m2: float, rng: np.random.Generator) -> np.ndarray:
    """Points spread uniformly over triangles (T, 3, 3), ``per_m2`` per square metre on average."""
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    n = int(np.ceil(area.sum() * per_m2))
    pick = rng.choice(len(tris), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tris[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def sim_sets(workdir: Path, rng: np.random.Generator) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, sparse input, dense target surface) per simulated building, in the city's local frame."""
    from lidarmap.io.las import read_las

    sets = []
    for params in SIM_SCENES:
        result = simulate(workdir / f"sim{params.seed}", params)
        truth, city = load_truth(result.out_dir), build_city(params)
        ids = truth.labels("als").building_id
        local = city.frame.to_local(read_las(result.als).xyz)
        static = city.static
        for b in city.buildings:
            tris = static.triangles[(static.building_id == b.id) & (static.behaviour != ABSORBER)]
            sparse = local[ids == b.id]
            if len(sparse) >= 50 and len(tris):
                sets.append((f"sim {params.seed} building {b.id}", sparse, sample_triangles(tris, DENSE_PER_M2, rng)))
    return sets


def real_training_clouds(data_dir: Path):
    """The real training clouds of the recipe: its held-out strips cut off, its held-out tile skipped (the simulated
    cities the segmentation recipe adds are not used here: ours are in ``SIM_SCENES``)."""
    for name, strip in recipe.HOLDOUT_STRIPS.items():
        cloud = recipe.read(name, data_dir)
        x = cloud.xyz[:, 0]
        yield f"{name} (x < min + {strip:g} m)", cloud.subset(x < x.min() + strip)
    for name in recipe.MONTPELLIER:
        if name != recipe.HELD_OUT_TILE:
            yield name, recipe.read(name, data_dir)


def real_sets(data_dir: Path, rng: np.random.Generator) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, thinned class-6 points, all class-6 points) per real training cloud (held-out parts unread)."""
    sets = []
    for name, cloud in real_training_clouds(data_dir):
        xyz = cloud.xyz[cloud.attrs["classification"] == 6]
        if len(xyz) < 100:
            continue
        xyz = LocalFrame.around(xyz).to_local(xyz)
        sets.append((f"real {name}", xyz[rng.random(len(xyz)) < REAL_KEEP], xyz))
    return sets


def samples(sparse: np.ndarray, dense: np.ndarray, per_point: int, rng: np.random.Generator) -> tuple:
    """Network inputs (M, k, 3), target moves (M, 3) in spacing units, the scale (M,) in metres, the seeds (M, 3)
    and a KD-tree of the target surface."""
    dist, idx = _knn(sparse, INFERENCE["spacing_k"] + 1)
    spacing = np.maximum(local_spacing(dist, idx, INFERENCE["spacing_k"]), 1e-3)
    owner = np.repeat(np.arange(len(sparse)), per_point)
    if len(owner) > MAX_SEEDS:
        owner = np.sort(rng.choice(owner, MAX_SEEDS, replace=False))
    scale = spacing[owner]
    seeds = sparse[owner] + rng.normal(size=(len(owner), 3)) * (TRAIN_SEED_SIGMA * scale)[:, None]
    surface = cKDTree(dense)
    target = dense[surface.query(seeds)[1]]
    rel = patch_inputs(sparse, cKDTree(sparse), seeds, scale, ARCH.k)
    return rel, ((target - seeds) / scale[:, None]).astype(np.float32), scale, seeds, surface


def augment(rel: torch.Tensor, move: torch.Tensor, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Random rotation about z and mirror in x (z stays up), the same for a patch and its target."""
    angle = torch.rand(len(rel), generator=gen) * (2 * np.pi)
    c, s = torch.cos(angle), torch.sin(angle)
    mirror = torch.where(torch.rand(len(rel), generator=gen) < 0.5, -1.0, 1.0)
    rot = torch.zeros(len(rel), 3, 3)
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c * mirror, -s, s * mirror, c, 1.0
    return rel @ rot.transpose(1, 2), (move[:, None] @ rot.transpose(1, 2))[:, 0]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_WEIGHTS, help="model file to write")
    parser.add_argument("--data", type=Path, default=None, help="the shared real data folder (default: "
                        "$LIDARMAP_DATA, else ../shared/data from the working directory)")
    parser.add_argument("--check", action="store_true", help="compare with --out instead of writing it")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    torch.set_num_threads(THREADS)
    torch.use_deterministic_algorithms(True)
    rng = np.random.default_rng(SEED)

    with tempfile.TemporaryDirectory() as tmp:
        sets = sim_sets(Path(tmp), rng) + real_sets(args.data, rng)
    train, val = [], []
    for name, sparse, dense in sets:
        rel, move, scale, seeds, surface = samples(sparse, dense, SEEDS_PER_POINT[name.split()[0]], rng)
        if name in VALIDATION:
            val.append((name, rel, move, scale, seeds, surface))
        else:
            train.append((rel, move))
        log(f"{name}: {len(sparse):,} input, {len(dense):,} surface points, {len(rel):,} seeds"
            f"{' (validation)' if name in VALIDATION else ''}")
    train_rel, train_move = (torch.from_numpy(np.concatenate(x)) for x in zip(*train))
    log(f"{len(train_rel):,} training and {sum(len(v[1]) for v in val):,} validation seeds after "
        f"{time.perf_counter() - started:.0f} s")

    torch.manual_seed(SEED)
    gen = torch.Generator().manual_seed(SEED)
    net = PatchProjector(ARCH)
    opt = torch.optim.Adam(net.parameters(), lr=LR)
    sched = torch.optim.lr_scheduler.StepLR(opt, LR_STEP, LR_GAMMA)
    history = []
    for epoch in range(1, EPOCHS + 1):
        net.train()
        order = torch.randperm(len(train_rel), generator=gen)
        total = 0.0
        for a in range(0, len(order), BATCH):
            batch = order[a:a + BATCH]
            rel, move = augment(train_rel[batch], train_move[batch], gen)
            loss = F.huber_loss(net.offset(rel), move, delta=HUBER)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(batch)
        sched.step()
        scores = {name: evaluate(net, *data) for name, *data in val}
        history.append({"epoch": epoch, "loss": total / len(order), "val": scores})
        log(f"epoch {epoch:2d}  loss {total / len(order):.4f}  " + "  ".join(
            f"[{name}] loss {v['loss']:.4f}, seeds to surface {v['before_m']:.3f} -> {v['after_m']:.3f} m"
            for name, v in scores.items()) + f"  {time.perf_counter() - started:.0f} s")

    training = {"seed": SEED, "threads": THREADS, "torch": str(torch.__version__), "epochs": EPOCHS, "batch": BATCH,
                "lr": LR, "seed_sigma": TRAIN_SEED_SIGMA, "lr_step": LR_STEP, "lr_gamma": LR_GAMMA, "huber": HUBER,
                "sim_scenes": [p.seed for p in SIM_SCENES], "sim_buildings_per_scene": SIM_SCENES[0].buildings,
                "dense_per_m2": DENSE_PER_M2, "real_keep": REAL_KEEP, "real_data": "recipe train part, class 6",
                "validation": sorted(VALIDATION), "train_seeds": len(train_rel), "history": history}
    if args.check:
        shipped = torch.load(args.out, map_location="cpu", weights_only=True)["state_dict"]
        same = all(torch.equal(shipped[k], v) for k, v in net.state_dict().items())
        log(f"weights {'identical to' if same else 'DIFFER from'} {args.out}")
        sys.exit(0 if same else 1)
    path = save_upsampler(args.out, net, training, INFERENCE)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    log(f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB, sha256 {digest}) after "
        f"{time.perf_counter() - started:.0f} s")


def evaluate(net: PatchProjector, rel: np.ndarray, move: np.ndarray, scale: np.ndarray, seeds: np.ndarray,
             surface: cKDTree) -> dict:
    """Validation loss and the mean distance (m) of the seeds to the target surface, before and after the move."""
    net.eval()
    with torch.inference_mode():
        pred = torch.cat([net.offset(torch.from_numpy(rel[a:a + 8192])) for a in range(0, len(rel), 8192)])
    moved = seeds + pred.numpy().astype(np.float64) * scale[:, None]
    return {"loss": float(F.huber_loss(pred, torch.from_numpy(move), delta=HUBER)),
            "before_m": float(surface.query(seeds)[0].mean()), "after_m": float(surface.query(moved)[0].mean())}


if __name__ == "__main__":
    main(sys.argv[1:])
