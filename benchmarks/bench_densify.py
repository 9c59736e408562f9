"""Densification: distance to the true surface, window openings, noise amplification, seams and speed.

``python benchmarks/bench_densify.py`` (about 3 minutes on 2 cores). Prints one markdown section.

Data: a simulated city (``SIM``: not one of the training scenes of scripts/train_upsampler.py) scanned from the air;
each building's airborne points (true building id) are the clean input, the truth is the exact surface the lasers
were traced against (walls with window holes, reveals, rooms, roofs) and the window rectangles. The noisy input adds
segmentation errors: ``SPECKLE`` of the other points within ``NOISE_BAND`` of the footprint (ground by the walls,
trees, cars), ``BLOBS`` clusters of them (radius ``BLOB_RADIUS``) and ``STRAYS`` random points in the building's
box grown by 2 m. Speed and a second seam check run on a real building: the largest class-6 component of the
held-out part of AHN3 Delft (lidarmap.segment.recipe).

Named baseline: **the paper's scheme** -- Algorithm 1 with independent leaves (no halo, no outlier removal, every
leaf upsampled to 2x its own points, outputs merged) -- run with the learned SAPCU-like upsampler (the paper used
SAPCU) and with the geometric one (so that the seam check compares split schemes with the same upsampler).

Targets: new points as close to the true surface as the input points; no more new points in window openings than
the input's own share; noise amplification well below the 2x of the paper; seam ratios within 10 % of 1.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "2")
os.environ.setdefault("MKL_NUM_THREADS", "2")

import numpy as np  # noqa: E402
import shapely  # noqa: E402
import torch  # noqa: E402
from scipy.sparse import coo_matrix  # noqa: E402
from scipy.sparse.csgraph import connected_components  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from shapely.geometry import Polygon  # noqa: E402

from lidarmap.aerial.densify import (
    DensifyParams,
    DensifyResult,
    GeometricUpsampler,
    Upsampler,
    densify,
    median_split,
    noise_amplification,
    seam_ratios,
)
from lidarmap.aerial.upsampler import load_upsampler  # noqa: E402
from lidarmap.frame import LocalFrame  # noqa: E402
from lidarmap.io.las import read_las  # noqa: E402
from lidarmap.segment import recipe  # noqa: E402
from lidarmap.sim import SimParams, build_city, load_truth, simulate  # noqa: E402
from lidarmap.sim.distance import MeshDistance  # noqa: E402
from lidarmap.sim.mesh import ABSORBER  # noqa: E402

torch.set_num_threads(2)

SIM = SimParams(seed=7, buildings=6, campaigns=0)
TAU = 0.25  # a point farther than this from the true surface is noise
WINDOW_INSET, WINDOW_D = 0.1, (-1.0, 0.5)  # "inside an opening": rectangle shrunk by the inset, d in this range
SPECKLE, NOISE_BAND, BLOBS, BLOB_RADIUS, STRAYS = 0.05, 2.0, 2, 1.0, 0.005
SEAM_LEAF, SEAM_BAND = 1000, 0.5  # sim buildings hold < 5000 points: smaller leaves so that there are split planes
RATIO = 2.0


# ----------------------------------------------------------------------------------------------------------------------
# The methods


def paper_scheme(xyz: np.ndarray, upsampler: Upsampler, max_leaf: int = 5000, seed: int = 0) -> DensifyResult:
    """The baseline: Algorithm 1 with independent leaves, ``RATIO`` x each leaf's points, no halo, no outliers."""
    started = time.perf_counter()
    frame = LocalFrame.around(xyz)
    pts = frame.to_local(xyz)
    new = [np.zeros((0, 3))]
    leaves = median_split(pts, max_leaf, 100, 0.0)
    for number, leaf in enumerate(leaves):
        if leaf.upsample:
            rng = np.random.default_rng([seed, 1, number])
            extra = RATIO - 1.0
            counts = (np.floor(extra) + (rng.random(len(leaf.core)) < extra % 1)).astype(np.int64)
            new.append(upsampler.upsample(pts[leaf.core], counts, rng))
    new_local = np.concatenate(new)
    nearest = cKDTree(pts).query(new_local)[1] if len(new_local) else np.zeros(0, np.int64)
    return DensifyResult(xyz=np.concatenate([xyz, frame.to_crs(new_local)]), rgb=None,
                         is_new=np.r_[np.zeros(len(xyz), bool), np.ones(len(new_local), bool)],
                         source_index=np.r_[np.arange(len(xyz)), nearest],
                         stats={"leaves": len(leaves), "seconds": {"total": time.perf_counter() - started}})


def methods(learned: Upsampler) -> dict:
    geometric = GeometricUpsampler()
    return {
        "ours, geometric": lambda xyz, **kw: densify(xyz, params=DensifyParams(**kw), upsampler=geometric),
        "ours, geometric, proportional": lambda xyz, **kw: densify(
            xyz, params=DensifyParams(distribution="proportional", **kw), upsampler=geometric),
        "ours, learned": lambda xyz, **kw: densify(xyz, params=DensifyParams(**kw), upsampler=learned),
        "paper scheme, learned (baseline)": lambda xyz, max_leaf=5000, **kw: paper_scheme(xyz, learned, max_leaf),
        "paper scheme, geometric": lambda xyz, max_leaf=5000, **kw: paper_scheme(xyz, geometric, max_leaf),
    }


# ----------------------------------------------------------------------------------------------------------------------
# Data


class SimBuilding:
    """One simulated building: clean and noisy airborne input (CRS), true surface distances, window test."""

    def __init__(self, truth, city, cloud_xyz, labels, b, rng):
        self.id, self.frame = b.id, city.frame
        self.facades = truth.building(b.id).facades
        static = city.static
        tris = static.triangles[(static.building_id == b.id) & (static.behaviour != ABSORBER)]
        self.surface = MeshDistance(tris, spacing=0.5)
        self.clean = cloud_xyz[labels.building_id == b.id]
        poly = Polygon(truth.building(b.id).footprint)
        others = np.flatnonzero(labels.building_id != b.id)
        near = others[shapely.distance(shapely.points(cloud_xyz[others, :2]), poly) < NOISE_BAND]
        wrong = near[rng.random(len(near)) < SPECKLE]
        tree = cKDTree(cloud_xyz[near])
        for centre in rng.choice(len(near), BLOBS, replace=False):
            wrong = np.union1d(wrong, near[tree.query_ball_point(cloud_xyz[near[centre]], BLOB_RADIUS)])
        lo, hi = self.clean.min(axis=0) - 2.0, self.clean.max(axis=0) + 2.0
        strays = lo + rng.random((max(1, int(STRAYS * len(self.clean))), 3)) * (hi - lo)
        self.noisy = np.concatenate([self.clean, cloud_xyz[wrong], strays])

    def distance(self, xyz_crs: np.ndarray) -> np.ndarray:
        return self.surface(self.frame.to_local(xyz_crs))[0]

    def in_windows(self, xyz_crs: np.ndarray) -> np.ndarray:
        inside = np.zeros(len(xyz_crs), bool)
        for f in self.facades:
            s, t, d = f.to_facade(xyz_crs).T
            for e in f.elements:
                if e.kind == "window":
                    s0, s1, t0, t1 = e.rect
                    m = WINDOW_INSET
                    inside |= ((s > s0 + m) & (s < s1 - m) & (t > t0 + m) & (t < t1 - m)
                               & (d > WINDOW_D[0]) & (d < WINDOW_D[1]))
        return inside


def sim_buildings(workdir: Path) -> list[SimBuilding]:
    result = simulate(workdir / "sim", SIM)
    truth, city = load_truth(result.out_dir), build_city(SIM)
    labels = truth.labels("als")
    xyz = read_las(result.als).xyz
    rng = np.random.default_rng(0)
    return [SimBuilding(truth, city, xyz, labels, b, rng) for b in city.buildings if b.shape != "shell"]


def real_building() -> tuple[str, np.ndarray]:
    """Largest class-6 component (1.5 m links in xy) of the held-out part of AHN3 Delft."""
    name = recipe.DELFT
    cloud = recipe.read(name)
    x = cloud.xyz[:, 0]
    xyz = cloud.xyz[(x >= x.min() + recipe.HOLDOUT_STRIPS[name]) & (cloud.attrs["classification"] == 6)]
    pairs = cKDTree(xyz[:, :2]).query_pairs(1.5, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xyz), len(xyz)))
    _, comp = connected_components(graph, directed=False)
    return f"{name} held-out part, largest building", xyz[comp == np.bincount(comp).argmax()]


# ----------------------------------------------------------------------------------------------------------------------
# Measurements


def surface_and_windows(buildings: list[SimBuilding], run) -> dict:
    new_d, in_win, new_win, n_in = [], 0, 0, 0
    for b in buildings:
        res = run(b.clean)
        new = res.xyz[res.is_new]
        new_d.append(b.distance(new))
        in_win += int(b.in_windows(b.clean).sum())
        n_in += len(b.clean)
        new_win += int(b.in_windows(new).sum())
    d = np.concatenate(new_d)
    return {"new": len(d), "mean": d.mean(), "p95": np.percentile(d, 95), "win_new": new_win / max(len(d), 1),
            "win_in": in_win / n_in}


def noise(buildings: list[SimBuilding], run, **kw) -> dict:
    totals = np.zeros(4)
    strays_removed = true_removed = 0
    for b in buildings:
        res = run(b.noisy, **kw)
        rep = noise_amplification(b.distance(b.noisy), b.distance(res.xyz), TAU)
        totals += [rep["noise_in"], rep["noise_out"], len(b.noisy), len(res.xyz)]
        kept = np.zeros(len(b.noisy), bool)
        kept[res.source_index[~res.is_new]] = True
        true_removed += int((~kept[:len(b.clean)]).sum())
        strays_removed += int((~kept[len(b.noisy) - max(1, int(STRAYS * len(b.clean))):]).sum())
    return {"in": totals[0], "out": totals[1], "amp": totals[1] / totals[0], "frac_in": totals[0] / totals[2],
            "frac_out": totals[1] / totals[3], "true_removed": true_removed, "strays_removed": strays_removed}


def seam(cases: list[np.ndarray], run, max_leaf: int, halo: float) -> dict:
    """Seam ratios pooled over the inputs: split run vs one-leaf run, same seed."""
    sums, planes = np.zeros(4), 0
    for xyz in cases:
        split, whole = run(xyz, max_leaf=max_leaf), run(xyz, max_leaf=10**9)
        frame = LocalFrame.around(xyz)
        kept = frame.to_local(split.xyz[~split.is_new])
        leaves = median_split(kept, max_leaf, 100, halo)
        r = seam_ratios(frame.to_local(split.xyz[split.is_new]), frame.to_local(whole.xyz[whole.is_new]), leaves,
                        SEAM_BAND)
        sums += r["counts"]
        planes += r["planes"]
    return {"band": (sums[0] + sums[1]) / (sums[2] + sums[3]), "across": (sums[0] / sums[2]) / (sums[1] / sums[3]),
            "planes": planes, "points": int(sums[2] + sums[3])}


def speed(xyz: np.ndarray, run, repeats: int = 2) -> dict:
    best, res = np.inf, None
    for _ in range(repeats):
        started = time.perf_counter()
        res = run(xyz)
        best = min(best, time.perf_counter() - started)
    return {"seconds": best, "in_per_s": len(xyz) / best, "new_per_s": int(res.is_new.sum()) / best,
            "new": int(res.is_new.sum()), "leaves": res.stats.get("leaves")}


# ----------------------------------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    started = time.perf_counter()
    load = os.getloadavg()[0]
    learned = load_upsampler()
    runs = methods(learned)
    with tempfile.TemporaryDirectory() as tmp:
        buildings = sim_buildings(Path(tmp))
    real_name, real = real_building()
    n_clean = sum(len(b.clean) for b in buildings)
    n_noisy = sum(len(b.noisy) for b in buildings)

    out = ["## bench_densify", ""]
    out.append(f"Simulated city (seed {SIM.seed}, {len(buildings)} buildings, {n_clean:,} airborne building points; "
               f"noisy input {n_noisy:,} points) and {real_name} ({len(real):,} points). Ratio {RATIO:g}, "
               f"default parameters otherwise. Baseline: the paper's scheme (independent leaves, no halo, no outlier "
               f"removal, {RATIO:g}x per leaf). Load average at start: {load:.1f} on {os.cpu_count()} cores.")
    out += ["", "**Surface and windows** (clean input). Distance of new points to the true surface; share of points "
            f"inside true window openings (rectangle shrunk by {WINDOW_INSET} m, {WINDOW_D[0]} m < d < "
            f"{WINDOW_D[1]} m)."
            " Targets: distances like the input's, window share of new points <= the input's.", "",
            "| method | new points | mean (m) | 95 % (m) | new points in windows | input points in windows |",
            "|---|---:|---:|---:|---:|---:|"]
    in_d = np.concatenate([b.distance(b.clean) for b in buildings])
    out.append(f"| input points | {n_clean:,} | {in_d.mean():.3f} | {np.percentile(in_d, 95):.3f} | | |")
    for name, run in runs.items():
        r = surface_and_windows(buildings, run)
        out.append(f"| {name} | {r['new']:,} | {r['mean']:.3f} | {r['p95']:.3f} | {100 * r['win_new']:.2f} % | "
                   f"{100 * r['win_in']:.2f} % |")

    out += ["", f"**Noise amplification** (noisy input; noise = points > {TAU} m from the true surface; amplification "
            "= noise points out / noise points in, the paper's behaviour is the ratio, 2). Target: well below 2.", "",
            "| method | outlier removal | noise in | noise out | amplification | noise share in -> out | "
            "strays removed | true points removed |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    n_strays = sum(max(1, int(STRAYS * len(b.clean))) for b in buildings)
    for name, run in runs.items():
        for k in ((12, 0) if name.startswith("ours") else (None,)):
            r = noise(buildings, run, **({} if k is None else {"outlier_k": k}))
            label = "no" if not k else "yes"
            out.append(f"| {name} | {label} | {r['in']:.0f} | {r['out']:.0f} | {r['amp']:.2f} | "
                       f"{100 * r['frac_in']:.1f} % -> {100 * r['frac_out']:.1f} % | {r['strays_removed']}/{n_strays}"
                       f" | {r['true_removed']}/{n_clean} |")

    out += ["", "**Seam check**: new points within "
            f"{SEAM_BAND} m of the split planes, split run / the same run in one leaf (same input and seed): "
            "`band` (1 = no trace, < 1 = thinned seam lines as in paper Fig. 8) and `across` (leaf side / other "
            "side, 1 = no density jump). Target: both within 10 % of 1. Simulated buildings split with max_leaf "
            f"{SEAM_LEAF}; the real building with the default 5000.", "",
            "| method | data | planes | new points in the bands (one leaf) | band | across |",
            "|---|---|---:|---:|---:|---:|"]
    for name, run in runs.items():
        halo = DensifyParams().halo if name.startswith("ours") else 0.0
        for label, cases, leaf in (("simulated", [b.clean for b in buildings], SEAM_LEAF), ("real", [real], 5000)):
            r = seam(cases, run, leaf, halo)
            out.append(f"| {name} | {label} | {r['planes']} | {r['points']:,} | {r['band']:.3f} | {r['across']:.3f} |")

    out += ["", f"**Speed** on the real building ({len(real):,} points, best of 2, whole stage incl. outlier removal "
            "and split; no colour).", "",
            "| method | seconds | input points/s | new points/s | new points | leaves |",
            "|---|---:|---:|---:|---:|---:|"]
    for name, run in runs.items():
        r = speed(real, run)
        out.append(f"| {name} | {r['seconds']:.2f} | {r['in_per_s']:,.0f} | {r['new_per_s']:,.0f} | {r['new']:,} | "
                   f"{r['leaves']} |")
    out += ["", f"_Benchmark wall time {time.perf_counter() - started:.0f} s._"]
    print("\n".join(out))


if __name__ == "__main__":
    main(sys.argv[1:])
