"""An independent street-scene mobile-mapping LiDAR simulator (docs/independent_scenes.md).

Written apart from the façade extraction it judges: it imports nothing else from lidarmap. ``generate`` draws a
street with terraced and detached houses (windows, doors, balconies, oriels...), street furniture and parked
vehicles, drives 1..n survey campaigns through it with profile, X-pair or rotating multi-beam scanners, traces
every pulse (glass, leaves, mixed pixels, ghosts, noise) and writes LAZ, trajectories, cadastre footprints and
the truth.

Seeds 9001-9150 (``EVAL_SEEDS``) are reserved for evaluation figures; develop and test with ``DEV_SEEDS``.
"""

from __future__ import annotations

import os
from pathlib import Path

# 9051-9150 added 2026-12-07 (issue 18 round 37) with 9049-9050 left unmeasured: no development run used them
EVAL_SEEDS = tuple(range(9001, 9151))
DEV_SEEDS = tuple(range(1, 1000))

_OPTIONS = {"street_length", "scanner", "pulse_budget", "furniture", "hide_opening", "n_jobs"}


def generate(out_dir, seed: int, campaigns: int = 3, buildings: int = 8, **options) -> dict:
    """Generate one scene into ``out_dir``; returns {name: path} of the files written.

    options: ``street_length`` (m, default drawn 100-160), ``scanner`` (force "profile" | "x_pair" | "multibeam"
    for every campaign), ``pulse_budget`` (emitted pulses per campaign, default 7e6), ``furniture`` (False: no
    street furniture, parked vehicles, people or bicycles), ``hide_opening`` (True: a 6.5 m long, 2.8 m tall van
    parked in every campaign in front of a ground-floor window, named in meta.json), ``n_jobs`` (worker
    processes, default min(2, cpu count)).
    """
    from .campaign import DEFAULT_BUDGET, classify, draw_campaign, run_campaigns
    from .scene import build_world
    from .truth import truth_document
    from .write import cadastre, write_footprints, write_json, write_laz, write_trajectory

    unknown = set(options) - _OPTIONS
    if unknown:
        raise TypeError(f"unknown options: {sorted(unknown)}")
    if campaigns < 1 or buildings < 1:
        raise ValueError("campaigns and buildings must be >= 1")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    furniture = bool(options.get("furniture", True))
    world = build_world(int(seed), int(buildings), options.get("street_length"), furniture)
    hide = _hidden(world) if options.get("hide_opening") else None
    camps = [draw_campaign(world, i, options.get("scanner"), float(options.get("pulse_budget", DEFAULT_BUDGET)),
                           hide) for i in range(1, campaigns + 1)]
    n_jobs = int(options.get("n_jobs", min(2, os.cpu_count() or 1)))
    results = run_campaigns(world, camps, n_jobs)
    paths, counts, grids = {}, {}, {}
    for c in camps:
        pts, g = results[c.id]
        counts[c.id] = write_laz(out / f"mls_{c.id}.laz", world, c, pts, classify(world, c, pts))
        write_trajectory(out / f"trajectory_{c.id}.csv", world, c)
        paths[f"mls_{c.id}"] = out / f"mls_{c.id}.laz"
        paths[f"trajectory_{c.id}"] = out / f"trajectory_{c.id}.csv"
        grids[c.id] = g
    cad = cadastre(world)
    write_footprints(out / "footprints.geojson", world, cad)
    write_json(out / "truth.json", truth_document(world, camps, counts, grids, cad))
    write_json(out / "meta.json", _meta(world, camps, hide))
    paths.update(footprints=out / "footprints.geojson", truth=out / "truth.json", meta=out / "meta.json")
    return paths


def _hidden(world) -> dict:
    """The ground-floor window a test van will hide, and an unobstructed upper window for comparison."""
    import numpy as np

    def low(op):  # a window whose top a 2.8 m van can cover from a scanner ~2.4 m high
        f = next(f for f in world.facades if f.id == op.facade_id)
        return f.street_facing and op.rect[3] - f.ground_max(op.rect[0], op.rect[1]) <= 2.6

    cands = [op for op in world.openings if op.kind == "window" and op.subtype == "window" and op.storey == 0
             and op.width <= 1.6 and low(op)]
    if not cands:
        raise ValueError("hide_opening: this scene has no ground-floor window on a street façade")
    op = cands[0]
    f = next(f for f in world.facades if f.id == op.facade_id)
    x = float(f.frame.xyz(np.mean(op.rect[:2]), 1.0, 0.0)[0])
    return {"x": x, "side": f.house.side, "opening": op.id}


def _meta(world, camps, hide) -> dict:
    import numpy as np

    vis = [op for op in world.openings if op.kind == "window" and op.storey == 1 and op.clear
           and next(f for f in world.facades if f.id == op.facade_id).street_facing]
    return {"seed": world.seed, "crs": f"EPSG:{world.epsg}", "origin": [round(float(v), 3) for v in world.origin],
            "azimuth_deg": round(float(np.degrees(world.azimuth)), 4),
            "street_length": round(world.length, 3), "road_half_width": round(world.terrain.road_half, 3),
            "curb": round(world.terrain.curb, 4), "slope": round(world.terrain.slope, 5),
            "sidewalks": {str(k): round(v, 3) for k, v in world.terrain.sidewalk.items()},
            "cross_street": None if world.terrain.cross is None else [round(float(v), 3) for v in world.terrain.cross],
            "triangles": int(len(world.tris)),
            "campaigns": [{"id": c.id, "scanner": c.kind, "rate": round(c.scanner.rate, 3),
                           "step_deg": round(c.scanner.step_deg, 4), "keep_frac": round(c.scanner.keep_frac, 3),
                           "pulses": c.n_pulses, "sigma": round(c.scanner.sigma, 4),
                           "max_range": round(c.scanner.max_range, 2), "divergence": c.scanner.divergence,
                           "min_sep": round(c.scanner.min_sep, 3), "trajectory_rate": c.traj_rate,
                           "lever": [round(float(v), 3) for v in c.scanner.lever], **c.scanner.params,
                           "duration": round(c.motion.t_fire, 3), "gps_t0": c.t0} for c in camps],
            "checks": {"hidden_opening": hide["opening"] if hide else None,
                       "visible_opening": vis[0].id if vis else None}}
