"""Per-pulse laser physics, vectorised over pulses.

Each pulse is split into S sub-rays on its footprint circle (exit aperture plus beam divergence), each carrying
1/S of the energy. Sub-rays are traced through the labelled triangles (embree) surface after surface:
  * leaves return part of the energy (``leafq``) and pass the rest on;
  * glass returns the whole sub-ray with probability p0 cos^k (low intensity), mirrors it with probability
    ``spec`` (the reflected hit becomes a GHOST event placed along the original ray at the total path length),
    otherwise lets it through; surfaces hit behind glass return only with the window's ``pint`` probability;
  * everything else ends the sub-ray with a return.
Events of one pulse are grouped by range: events closer than the scanner's return separation merge into one
return at their energy-weighted mean range (mixed pixels at depth edges); groups under 20 % of the pulse energy,
too weak for the range (reflectance, incidence, 1/r^2) or outside [1 m, max range] give nothing. Range noise
N(0, sigma) and 0.05 % outliers (a random range along the ray) are added last.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import CURTAIN, GLASS, LEAF

SUB_RAYS = 3
MIN_ENERGY = 0.2
MIN_RANGE = 1.0
OUTLIER_RATE = 0.0005
MAX_BOUNCES = 8
EPS = 1e-3  # restart continuing rays this far past the surface (m)


@dataclass
class TraceScene:
    scene: object
    normals: np.ndarray  # (T, 3) unit
    tri_mat: np.ndarray  # (T,)
    mat: dict  # material arrays


def build_trace_scene(tris: np.ndarray, tri_mat: np.ndarray, mat: dict) -> TraceScene:
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(tris, np.float32))
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return TraceScene(scene, nrm, tri_mat, mat)


def _intersect(ts: TraceScene, o: np.ndarray, d: np.ndarray, tmax: np.ndarray):
    res = ts.scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32),
                       dists=np.ascontiguousarray(tmax, np.float32), output=1)
    prim = np.asarray(res["primID"]).astype(np.int64)
    hit = (prim >= 0) & (np.asarray(res["geomID"]) >= 0)
    return hit, np.where(hit, prim, 0), np.asarray(res["tfar"], np.float64)


def _basis(D: np.ndarray):
    """Two unit vectors orthogonal to each direction."""
    a = np.where(np.abs(D[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(D, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(D, e1)


def sub_rays(O, D, rng, aperture: float, divergence: float):
    """S sub-rays per pulse on the footprint circle: origins on the aperture ring, directions at half divergence."""
    n = len(O)
    e1, e2 = _basis(D)
    phi = rng.uniform(0, 2 * np.pi, n)[:, None] + 2 * np.pi * np.arange(SUB_RAYS) / SUB_RAYS
    off = np.cos(phi)[..., None] * e1[:, None] + np.sin(phi)[..., None] * e2[:, None]
    so = O[:, None] + aperture / 2 * off
    sd = D[:, None] + divergence / 2 * off
    sd /= np.linalg.norm(sd, axis=2, keepdims=True)
    return so.reshape(-1, 3), sd.reshape(-1, 3)


def trace(ts: TraceScene, O, D, rng, aperture, divergence, max_range):
    """Events of every pulse: dict of arrays (pid, range, energy, mat, cos, ghost, point, normal z), and the
    first-hit distance of each pulse's sub-ray 0 (inf where nothing was hit), used for observation."""
    o, d = sub_rays(O, D, rng, aperture, divergence)
    pid = np.repeat(np.arange(len(O)), SUB_RAYS)
    e = np.full(len(o), 1.0 / SUB_RAYS)
    racc = np.zeros(len(o))
    ghost = np.zeros(len(o), bool)
    behind = np.full(len(o), -1, np.int64)
    M = ts.mat
    ev = {k: [] for k in ("pid", "range", "energy", "mat", "cos", "ghost", "point", "nz", "behind")}
    first_t = None
    for bounce in range(MAX_BOUNCES):
        if not len(o):
            break
        hit, prim, t = _intersect(ts, o, d, np.maximum(max_range * 1.05 - racc, 1e-3))
        if bounce == 0:
            first_t = np.where(hit, t, np.inf)[::SUB_RAYS]
        sel = np.flatnonzero(hit)
        o, d, pid, e, racc, ghost, behind, prim, t = (a[sel] for a in (o, d, pid, e, racc, ghost, behind, prim, t))
        mat = ts.tri_mat[prim]
        lab = M["label"][mat]
        nrm = ts.normals[prim]
        dn = np.einsum("ij,ij->i", d, nrm)
        cos = np.abs(dn)
        P = o + d * t[:, None]
        u = rng.random(len(o))
        is_leaf, is_glass = lab == LEAF, lab == GLASS
        p_ret = M["p0"][mat] * cos ** M["k"][mat]
        bmask = behind >= 0
        p_behind = np.where(bmask & (lab != CURTAIN), M["pint"][np.maximum(behind, 0)], 1.0)
        # event energy: leaves return leafq of it, glass all or nothing, others all (if not absorbed behind glass)
        e_ev = np.where(is_leaf, e * M["leafq"][mat], e)
        returns = np.where(is_glass, u < p_ret, np.where(is_leaf, True, u < p_behind))
        k = np.flatnonzero(returns)
        for name, arr in (("pid", pid[k]), ("range", racc[k] + t[k]), ("energy", e_ev[k]), ("mat", mat[k]),
                          ("cos", cos[k]), ("ghost", ghost[k]), ("point", P[k]), ("nz", nrm[k, 2]),
                          ("behind", behind[k])):
            ev[name].append(arr)
        mirror = is_glass & (u >= p_ret) & (u < p_ret + M["spec"][mat])
        through = is_glass & (u >= p_ret + M["spec"][mat])
        go = np.flatnonzero(is_leaf | mirror | through)
        d_new = d[go] - 2 * (dn[go, None] * nrm[go]) * mirror[go, None]
        e_new = np.where(is_leaf[go], e[go] * (1 - M["leafq"][mat[go]]), e[go])
        behind_new = np.where(through[go], mat[go], behind[go])
        o, d = P[go] + d_new * EPS, d_new
        pid, e, racc = pid[go], e_new, racc[go] + t[go] + EPS
        ghost, behind = ghost[go] | mirror[go], behind_new
    if first_t is None:
        first_t = np.full(len(O), np.inf)
    empty = {"point": np.zeros((0, 3)), "pid": np.zeros(0, np.int64), "mat": np.zeros(0, np.int64),
             "behind": np.zeros(0, np.int64), "ghost": np.zeros(0, bool)}
    cat = {k: (np.concatenate(v) if v else empty.get(k, np.zeros(0))) for k, v in ev.items()}
    return cat, first_t


def _hash01(P: np.ndarray, cell: float) -> np.ndarray:
    """A deterministic pseudo-random value in [0, 1) per cell of a 3D grid (surface texture)."""
    q = np.floor(P / cell).astype(np.int64)
    h = (q[:, 0] * 73856093) ^ (q[:, 1] * 19349663) ^ (q[:, 2] * 83492791)
    h = (h * 2654435761) & 0xFFFFFFFF
    return ((h >> 8) & 0xFFFF) / 65536.0


def apply_relief(ev: dict, M: dict) -> None:
    """Surface relief as a range change: plaster/brick roughness (2.5 cm cells) and rustication grooves."""
    mat, P = ev["mat"], ev["point"]
    rel = M["relief"][mat]
    delta = rel * np.sqrt(3.0) * (2 * _hash01(P, 0.025) - 1)  # uniform with std = relief
    depth = M["rust_depth"][mat]
    band = (depth > 0) & (P[:, 2] < M["rust_ztop"][mat])
    phase = np.mod(P[:, 2] - M["rust_z0"][mat], np.where(depth > 0, M["rust_period"][mat], 1.0))
    delta = delta - np.where(band & (phase < M["rust_groove"][mat]), depth, 0.0)
    ev["range"] = ev["range"] - delta / np.maximum(ev["cos"], 0.2)


def combine(ev: dict, M: dict, n_pulses: int, max_range: float, min_sep: float, max_returns: int):
    """Group events into returns; returns per-return arrays (pid, range, energy, main event index, refl mix)."""
    order = np.lexsort((ev["range"], ev["pid"]))
    pid, rng_ = ev["pid"][order], ev["range"][order]
    energy = ev["energy"][order]
    new = np.ones(len(pid), bool)
    new[1:] = (pid[1:] != pid[:-1]) | (np.diff(rng_) > min_sep)
    gid = np.cumsum(new) - 1
    ng = int(gid[-1] + 1) if len(gid) else 0
    E = np.bincount(gid, energy, ng)
    R = np.bincount(gid, energy * rng_, ng) / np.maximum(E, 1e-12)
    mat = ev["mat"][order]
    cos = ev["cos"][order]
    glass = M["label"][mat] == GLASS
    refl = np.where(glass, 0.03, M["refl"][mat])
    mix = np.bincount(gid, energy * refl * (0.2 + 0.8 * cos), ng)
    # main event of a group: the one with the most energy (first on ties)
    by = np.lexsort((-energy, gid))
    first = np.ones(len(by), bool)
    first[1:] = gid[by][1:] != gid[by][:-1]
    main = order[by[first]]
    gpid = pid[new]
    main_glass = M["label"][ev["mat"][main]] == GLASS
    snr = mix * (max_range / np.maximum(R, 1e-6)) ** 2 / 0.8
    keep = (E >= MIN_ENERGY - 1e-9) & ((snr >= 1.0) | main_glass) & (R >= MIN_RANGE) & (R <= max_range)
    out = {"pid": gpid[keep], "range": R[keep], "energy": E[keep], "main": main[keep], "mix": mix[keep]}
    return _limit_returns(out, max_returns)


def _limit_returns(g: dict, max_returns: int) -> dict:
    """At most max_returns per pulse: the last one and the strongest others (dual-return style)."""
    pid = g["pid"]
    if not len(pid):
        return g
    last = np.ones(len(pid), bool)
    last[:-1] = pid[1:] != pid[:-1]
    counts = np.bincount(pid)
    if counts.max() > max_returns:
        idx = np.flatnonzero(~last)
        by = idx[np.lexsort((-g["energy"][idx], pid[idx]))]
        start = np.ones(len(by), bool)
        start[1:] = pid[by][1:] != pid[by][:-1]
        pos = np.arange(len(by)) - np.maximum.accumulate(np.where(start, np.arange(len(by)), 0))
        keep = last.copy()
        keep[by[pos < max_returns - 1]] = True
        g = {k: v[keep] for k, v in g.items()}
        pid = g["pid"]
    first = np.ones(len(pid), bool)
    first[1:] = pid[1:] != pid[:-1]
    start_idx = np.maximum.accumulate(np.where(first, np.arange(len(pid)), 0))
    g["return_number"] = (np.arange(len(pid)) - start_idx + 1).astype(np.uint8)
    g["number_of_returns"] = np.bincount(pid)[pid].astype(np.uint8)
    return g


def simulate_pulses(ts: TraceScene, O, D, rng, sc):
    """Returns of a batch of pulses: dict of per-point arrays, and sub-ray 0 first-hit distances."""
    ev, first_t = trace(ts, O, D, rng, sc.aperture, sc.divergence, sc.max_range)
    M = ts.mat
    if len(ev["pid"]):
        apply_relief(ev, M)
    g = combine(ev, M, len(O), sc.max_range, sc.min_sep, sc.max_returns)
    n = len(g["pid"])
    R = g["range"] + rng.normal(0.0, sc.sigma, n)
    wild = rng.random(n) < OUTLIER_RATE
    R = np.where(wild, rng.uniform(MIN_RANGE, np.maximum(R, MIN_RANGE + 1e-3)), R)
    xyz = O[g["pid"]] + D[g["pid"]] * R[:, None]
    speckle = rng.lognormal(0.0, 0.1, n)
    inten = np.clip(g["mix"] * np.minimum(1.0, 5.0 / np.maximum(R, 1e-3)) * speckle, 0, 1) * 65535
    main = g["main"].astype(np.int64)
    mat = ev["mat"][main].astype(np.int64)
    ghost = ev["ghost"][main].astype(bool)
    behind = ev["behind"][main].astype(np.int64)
    pts = {"pid": g["pid"], "xyz": xyz, "intensity": inten.astype(np.uint16),
           "return_number": g.get("return_number", np.zeros(0, np.uint8)),
           "number_of_returns": g.get("number_of_returns", np.zeros(0, np.uint8)),
           "cls": np.where(ghost, 1, M["cls"][mat]).astype(np.uint8),  # ghosts: unclassified
           "label": M["label"][mat].astype(np.uint8), "nz": ev["nz"][main].astype(np.float64),
           "ghost": ghost, "opening": M["opening"][mat],  # opening whose glass returned it
           "via": np.where(behind >= 0, M["opening"][np.maximum(behind, 0)], -1)}  # opening it came through
    return pts, first_t
