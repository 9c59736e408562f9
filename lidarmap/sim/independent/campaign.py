"""One survey campaign: what it draws (scanner, drive, GNSS drift, parked cars...) and its simulation, run in
chunks of pulses over worker processes (each chunk has its own random stream, so results do not depend on the
number of workers)."""

from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from .furniture import campaign_objects
from .geometry import REVEAL, VAN, WALL, Materials
from .observe import ObsFacade, empty_grids, observe
from .physics import build_trace_scene, simulate_pulses
from .scanners import (Motion, Scanner, blocked_by_vehicle, draw_drift, draw_scanner, fit_budget, in_sectors,
                       pulse_pattern, sensor_pose, simulate_drive)
from .scene import World, rng_for

CHUNK = 96_000  # pulses per task (a multiple of 2 x 500 and of 384)
MULTIBEAM_SHARE = 0.5  # of the pulse budget, so that its point count matches the profile scanners
DEFAULT_BUDGET = 7.0e6  # emitted pulses per campaign (before the vehicle-body mask)


@dataclass
class Campaign:
    id: int
    kind: str
    direction: int
    lane_offset: float
    speed: float
    stop_duration: float
    classified: bool
    traj_rate: float
    t0: float  # GPS time (adjusted standard) of tau = 0
    drift: dict
    scanner: Scanner
    motion: Motion
    n_pulses: int
    hide: dict | None = None


def draw_campaign(world: World, cid: int, scanner: str | None = None, budget: float = DEFAULT_BUDGET,
                  hide: dict | None = None) -> Campaign:
    rng = rng_for(world.seed, "campaign", cid)
    kind = scanner or str(rng.choice(["profile", "x_pair", "multibeam"]))
    direction = int(rng.choice([1, -1]))
    lane = float(rng.uniform(1.5, min(4.0, world.terrain.road_half - 3.2)))
    speed, stop_frac, stop_dur = float(rng.uniform(3.0, 12.0)), float(rng.uniform(0.2, 0.8)), float(rng.uniform(3, 15))
    acc, dec = float(rng.uniform(0.8, 2.0)), float(rng.uniform(1.0, 2.5))
    classified = bool(rng.random() >= 0.4)
    traj_rate = float(rng.choice([50.0, 100.0, 125.0, 200.0]))
    drift = draw_drift(rng)
    sc = draw_scanner(rng, kind)
    if kind == "multibeam":  # most of its pulses hit the road nearby: more returns per pulse
        budget = budget * MULTIBEAM_SHARE
    for _ in range(10):  # the pulse budget: coarser pattern first, then a faster drive with a shorter stop
        motion = simulate_drive(rng_for(world.seed, "campaign", cid, 1), world.length, direction, lane, speed,
                                stop_frac, stop_dur, acc, dec)
        if fit_budget(sc, motion.t_fire, budget) or (speed >= 12.0 and stop_dur <= 3.0):
            break
        speed, stop_dur = min(12.0, speed * 1.2), max(3.0, stop_dur * 0.75)
    base = rng_for(world.seed, "time").uniform(3.0e8, 3.9e8)
    t0 = float(np.round(base + (cid - 1) * rng.uniform(2, 40) * 86400.0 + rng.uniform(0, 3600), 3))
    n = int(np.ceil(motion.t_fire * sc.pulse_rate))
    return Campaign(cid, kind, direction, lane, speed, stop_dur, classified, traj_rate, t0, drift, sc, motion, n, hide)


def campaign_scene(world: World, camp: Campaign):
    """Static triangles plus this campaign's vehicles, people and bicycles; material arrays to match."""
    mats = Materials()
    mats.rows = list(world.mats.rows)
    mb = campaign_objects(rng_for(world.seed, "objects", camp.id), world.terrain, mats, world.strip, camp.hide,
                          world.furniture)
    tris, tri_mat = mb.arrays()
    return np.concatenate([world.tris, tris]), np.concatenate([world.tri_mat, tri_mat]), mats.arrays()


def obs_facades(world: World) -> list[ObsFacade]:
    return [ObsFacade(f.id, f.frame.o, f.frame.u, f.frame.n, f.width, f.height, f.style.get("wall_refl", 0.5))
            for f in world.facades]


# ----------------------------------------------------------------------------------------------------------------------
# Workers: the state is set before the pool forks and read by the children.

_STATE: dict = {}
_SCENES: dict = {}


def _work(task):
    cid, chunk, k0, k1 = task
    st = _STATE[cid]
    if cid not in _SCENES:
        _SCENES.clear()  # one campaign's scene at a time keeps memory low
        _SCENES[cid] = build_trace_scene(st["tris"], st["tri_mat"], st["mat"])
    ts = _SCENES[cid]
    sc, m = st["scanner"], st["motion"]
    k = np.arange(k0, k1, dtype=np.int64)
    tau, d_body, _ = pulse_pattern(sc, k)
    keep = ~blocked_by_vehicle(sc.lever, d_body) & in_sectors(sc, d_body) & (tau <= m.t_fire)
    k, tau, d_body = k[keep], tau[keep], d_body[keep]
    O, R, _ = sensor_pose(m, st["terrain"], sc, tau)
    D = np.einsum("nij,nj->ni", R, d_body)
    rng = np.random.default_rng([st["seed"], 8, cid, chunk])
    pts, first_t = simulate_pulses(ts, O, D, rng, sc)
    grids = empty_grids(st["obs"])
    observe(O, D, first_t, st["obs"], sc.max_range, grids)
    pts["tau"] = tau[pts["pid"]]
    del pts["pid"]
    return cid, pts, grids


def run_campaigns(world: World, camps: list[Campaign], n_jobs: int = 2) -> dict:
    """Simulate every campaign; per campaign id: (points dict, per-façade (fine, coarse) observation grids)."""
    obs = obs_facades(world)
    tasks = []
    for c in camps:
        tris, tri_mat, mat = campaign_scene(world, c)
        _STATE[c.id] = {"tris": tris, "tri_mat": tri_mat, "mat": mat, "scanner": c.scanner, "motion": c.motion,
                        "terrain": world.terrain, "obs": obs, "seed": world.seed}
        tasks += [(c.id, i, k0, min(k0 + CHUNK, c.n_pulses)) for i, k0 in enumerate(range(0, c.n_pulses, CHUNK))]
    try:
        if n_jobs > 1:
            with ProcessPoolExecutor(n_jobs, mp_context=mp.get_context("fork")) as ex:
                results = list(ex.map(_work, tasks, chunksize=1))
        else:
            results = [_work(t) for t in tasks]
    finally:
        _STATE.clear()
        _SCENES.clear()
    out = {}
    for c in camps:
        parts = [(p, g) for cid, p, g in results if cid == c.id]
        pts = {k: np.concatenate([p[k] for p, _ in parts]) for k in parts[0][0]}
        grids = empty_grids(obs)
        for _, g in parts:
            for (fa, ca), (fb, cb) in zip(grids, g):
                fa |= fb
                ca |= cb
        out[c.id] = (pts, grids)
    return out


def classify(world: World, camp: Campaign, pts: dict) -> np.ndarray:
    """LAS classes: all 1 for raw campaigns; otherwise the true class with the errors of an automatic
    classifier: the lowest 0.3 m of walls called ground, van roofs called building, 2-4 % random labels."""
    n = len(pts["cls"])
    if not camp.classified:
        return np.ones(n, np.uint8)
    rng = rng_for(world.seed, "classes", camp.id)
    cls = pts["cls"].copy()
    xyz = pts["xyz"]
    above = xyz[:, 2] - world.terrain.z(xyz[:, 0], xyz[:, 1])
    cls[np.isin(pts["label"], (WALL, REVEAL)) & (above < 0.3) & ~pts["ghost"]] = 2
    cls[(pts["label"] == VAN) & (np.abs(pts["nz"]) > 0.8)] = 6
    wrong = rng.random(n) < rng.uniform(0.02, 0.04)
    cls[wrong] = rng.choice(np.array([1, 2, 5, 6], np.uint8), int(wrong.sum()))
    return cls
