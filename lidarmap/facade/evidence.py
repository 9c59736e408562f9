"""Façade extraction: ray evidence — which cells of a façade the laser went through, and how well each was sampled.

A cell without wall returns is not yet a hole: the scanner may simply have put no pulse there (the gaps between
the scan lines on a wall seen at a grazing angle, a far wall's sparse rows). A cell is an *opening* only with
positive evidence that pulses crossed the wall plane there:

* returns more than ``pass_depth`` behind the local wall (glass, curtains and door leaves a few cm to dm behind
  it; rooms and anything farther, projected along their ray onto the plane);
* pulses that crossed the plane and returned nothing. A mobile profiler fires at a fixed rate, so the returns of
  one scan line ordered by GPS time leave a gap of ``k`` pulse periods where ``k - 1`` pulses came back empty; their
  directions lie between those of the gap's two returns (:func:`missed_pulse_crossings`).

Cells with neither kind of evidence and no return are *not observed*: never a hole. Per cell the counts also give
the sampling quality of the observation (pulses per cell, incidence), from which the map weighs this campaign's
votes against another's (:func:`vote_weights`).
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from lidarmap.facade.layers import cell_index, square
from lidarmap.facade.occlusion import project_rays

if TYPE_CHECKING:  # pragma: no cover
    from lidarmap.facade.params import FacadeParams


@dataclasses.dataclass
class CellEvidence:
    """Pulse counts per cell of a façade grid (rows, cols) and the mean cosine of their incidence on the wall."""

    wall: np.ndarray  # returns on the wall plane (within pass_depth of the local wall)
    recessed: np.ndarray  # returns pass_depth .. layer_back behind it (glass, curtains, door leaves)
    through: np.ndarray  # returns farther behind, counted where their pulse crossed the plane
    missed: np.ndarray  # pulses that crossed the plane there and returned nothing
    cos_incidence: np.ndarray  # mean |cos| of the angle between those pulses and the wall normal (0: no pulse)
    pulse_order: bool = True  # whether GPS times ordered the pulses (else ``missed`` could not be counted)
    offset: np.ndarray | None = None  # mean depth of the returns near the wall relative to it (NaN: none)
    offset_n: np.ndarray | None = None  # how many returns that mean is over
    front: np.ndarray | None = None  # returns more than pass_depth in front of the wall (shutters, pilasters)
    missed_beside: np.ndarray | None = None  # missed pulses of gaps next to an occluder (no evidence; counted apart)

    @property
    def passed(self) -> np.ndarray:
        """Pulses that went through the wall plane."""
        return self.recessed + self.through + self.missed

    @property
    def pulses(self) -> np.ndarray:
        return self.wall + self.passed


def local_wall_depth(sdt: np.ndarray, s0: float, params: FacadeParams, heads: np.ndarray | None = None) -> np.ndarray:
    """The depth of the wall next to each point: the wall's robust tilted plane (:func:`wall_tilt`) plus, per
    ``wall_block`` of s, the offset of the wall from it (:func:`_block_mode` on the depths less the plane: the
    strong histogram peak of the points within ``wall_band`` nearest the façade's wall, kept near its neighbours';
    none where a block has fewer than 20 of them). A wall that leans, bows or drifts by a few cm (GPS drift along a long façade) must not read as recessed
    glass.

    With ``heads`` (the scanner head of each point, :func:`scanner_heads`) holding two heads, each head's wall is
    its own: two crossed heads see a wall point seconds apart, and the GPS drift in between puts their walls a
    few cm apart; against one depth for both, the returns of one head would lie behind the wall and read as pulses
    through it. The wall of all returns together stays where a head has fewer than 20 returns in the block."""
    sdt = np.asarray(sdt, dtype=np.float64).reshape(-1, 3)
    # a wall out of plumb (or a frame fitted a fraction of a degree off) drifts in depth with its height, which a
    # block of s cannot follow: the blocks work on the depths less the wall's robust tilt
    trend = wall_tilt(sdt, params) if params.evidence.wall_tilt else np.zeros(len(sdt))
    flat = sdt.copy()
    flat[:, 2] -= trend
    both = _block_mode(flat, s0, params, np.ones(len(flat), dtype=bool))
    if heads is not None and len(np.unique(heads)) > 1:
        for h in np.unique(heads):
            own = _block_mode(flat, s0, params, heads == h)
            take = (heads == h) & ~np.isnan(own)
            both = np.where(take, own, both)
    return np.where(np.isnan(both), 0.0, both) + trend


#: Tukey's biweight constant (95 % efficiency under Gaussian noise).
_TUKEY = 4.685


def wall_tilt(sdt: np.ndarray, params: FacadeParams, iterations: int = 6) -> np.ndarray:
    """Per point, the depth of the wall's robust plane d = a + b s + c t through the returns within ``wall_band``
    of the façade plane (iteratively reweighted least squares, Tukey weights on a MAD scale of at least 5 mm).

    Walls lean: a terraced house 0.3° out of plumb is 8 cm deeper at its eave than at its foot (independent dev
    seed 5: the whole top storey read as glass behind the wall and became one unknown region). Glass, curtains and
    proud pilasters a few cm off the wall get no weight once the scale is the wall's own; the slopes are bounded by
    ``wall_max_tilt`` so that a façade mostly of glass cannot tip the plane into it. Each point weighs one over
    the returns in its ``wall_area_cell`` square: the wall's area, not its sampling, sets the plane (the lower 2.5 m,
    nearest the scanner, hold more returns than the storeys above, and a flush double door 2.8 cm back there tipped
    the plane 1.7 cm back at the foot: the leaf measured 1 cm and voted wall; issue 18 round 39, independent dev
    seed 34)."""
    near = np.abs(sdt[:, 2]) <= params.evidence.wall_band
    if near.sum() < 50:
        return np.zeros(len(sdt))
    s, t, d = sdt[near, 0], sdt[near, 1], sdt[near, 2]
    design = np.column_stack([np.ones_like(s), s - s.mean(), t - t.mean()])
    coef = np.array([np.median(d), 0.0, 0.0])
    area = _area_weights(sdt[near, :2], params.evidence.wall_area_cell)
    for _ in range(iterations):
        resid = d - design @ coef
        scale = max(1.4826 * float(np.median(np.abs(resid - np.median(resid)))), 0.005)
        u = resid / (_TUKEY * scale)
        tukey = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if tukey.sum() < 20:
            break
        w = tukey * area
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(design * sw[:, None], d * sw, rcond=None)[0]
        coef[1:] = np.clip(coef[1:], -params.evidence.wall_max_tilt, params.evidence.wall_max_tilt)
    return coef[0] + coef[1] * (sdt[:, 0] - s.mean()) + coef[2] * (sdt[:, 1] - t.mean())


def _area_weights(st: np.ndarray, cell: float) -> np.ndarray:
    """Per point (s, t), the mean number of points per occupied ``cell`` x ``cell`` square over the number in its
    own (all ones when ``cell`` is 0): each square of wall weighs the same, however densely it was sampled."""
    if cell <= 0 or len(st) == 0:
        return np.ones(len(st))
    ij = np.floor((st - st.min(axis=0)) / cell).astype(np.int64)
    _, inverse, count = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1], return_inverse=True,
                                  return_counts=True)
    return float(np.mean(count)) / count[inverse.reshape(-1)]


def effective_pass_depth(rel: np.ndarray, params: FacadeParams) -> float:
    """How far behind the local wall a return must lie to have passed the wall plane: ``pass_depth``, or
    ``pass_noise_k`` times the wall's own depth scatter when that is larger (the robust σ, 1.4826 x MAD, of the
    returns within ``wall_band`` of the local wall; ``rel``: depths relative to it).

    A wall's scatter is its range noise and its relief: 1 cm on the simulator's smooth walls, 2-3 cm on brick or
    rough plaster scanned with 1.5 cm noise (independent dev seed 5: σ 2.4 cm, a fifth of the wall's returns lay
    2 cm behind it, and every cell with two pulses of which one fell back read as glass)."""
    ev = params.evidence
    near = rel[np.abs(rel) <= ev.wall_band]
    if len(near) < 50 or ev.pass_noise_k <= 0:
        return ev.pass_depth
    sigma = 1.4826 * float(np.median(np.abs(near - np.median(near))))
    return max(ev.pass_depth, ev.pass_noise_k * sigma)


def _wall_blocks(sdt: np.ndarray, s0: float, params: FacadeParams, members: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The ``wall_block`` index along s of every point, and which ``members`` lie within ``wall_band`` of the
    plane."""
    ev = params.evidence
    block = np.floor((sdt[:, 0] - s0) / ev.wall_block).astype(np.int64)
    return block, members & (np.abs(sdt[:, 2]) <= ev.wall_band)


def _group_median(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct ``keys`` (sorted), the median of the ``values`` of each, and their counts."""
    order = np.lexsort((values, keys))
    k_sorted, v_sorted = keys[order], values[order]
    uniq, start, count = np.unique(k_sorted, return_index=True, return_counts=True)
    return uniq, 0.5 * (v_sorted[start + (count - 1) // 2] + v_sorted[start + count // 2]), count


def _per_point(uniq: np.ndarray, values: np.ndarray, block: np.ndarray) -> np.ndarray:
    """``values`` (one per block of ``uniq``) at every point's ``block``; NaN for blocks not in ``uniq``."""
    pos = np.clip(np.searchsorted(uniq, block), 0, len(uniq) - 1)
    return np.where(uniq[pos] == block, values[pos], np.nan)


def _depth_histogram(keys: np.ndarray, depths: np.ndarray, n_keys: int, params: FacadeParams) -> np.ndarray:
    """Per key, the histogram of ``depths`` (within ``wall_band``) in ``wall_mode_bin`` bins, smoothed over 5 bins."""
    ev = params.evidence
    n_bins = int(np.ceil(2 * ev.wall_band / ev.wall_mode_bin)) + 1
    bins = np.clip(((depths + ev.wall_band) / ev.wall_mode_bin).astype(np.int64), 0, n_bins - 1)
    hist = np.bincount(keys * n_bins + bins, minlength=n_keys * n_bins).reshape(n_keys, n_bins)
    return ndimage.uniform_filter1d(hist.astype(np.float64), 5, axis=1, mode="constant")


def _strong_peaks(smooth: np.ndarray) -> np.ndarray:
    """Per row of histograms, its local maxima that reach half the row's highest."""
    left = np.pad(smooth, ((0, 0), (1, 0)))[:, :-1]
    right = np.pad(smooth, ((0, 0), (0, 1)))[:, 1:]
    return (smooth >= left) & (smooth >= right) & (smooth >= 0.5 * smooth.max(axis=1, keepdims=True))


def _bin_centres(params: FacadeParams, n_bins: int) -> np.ndarray:
    return -params.evidence.wall_band + (np.arange(n_bins) + 0.5) * params.evidence.wall_mode_bin


def _wall_level(sdt: np.ndarray, params: FacadeParams, members: np.ndarray) -> float:
    """The depth of the ``members``' wall over the whole façade: the front-most strong peak of their depths within
    ``wall_band`` (0 with fewer than 20 of them). Glass and curtains lie behind the wall, and one scanner head may
    see about as much shop-front glass as wall (hard seed 58: the glass peak was the higher); pilasters and pipes in
    front are a small share of a whole façade, never a strong peak."""
    near = members & (np.abs(sdt[:, 2]) <= params.evidence.wall_band)
    if near.sum() < 20:
        return 0.0
    smooth = _depth_histogram(np.zeros(int(near.sum()), dtype=np.int64), sdt[near, 2], 1, params)
    strong = _strong_peaks(smooth)[0]
    return float(_bin_centres(params, len(strong))[len(strong) - 1 - np.argmax(strong[::-1])])


def _block_mode(sdt: np.ndarray, s0: float, params: FacadeParams, members: np.ndarray) -> np.ndarray:
    """Per point, the wall depth of the ``members`` within ``wall_band`` of the plane in its ``wall_block`` of s:
    of the peaks of their smoothed depth histogram that reach half its maximum, the one nearest the members' wall
    over the whole façade (:func:`_wall_level`), refined to the median of those within ``pass_depth`` of it and kept
    near its neighbours' (:func:`_like_neighbours`); NaN where that block holds fewer than 20 of them.

    Nearest the façade's wall, not the block's front-most peak: a pilaster or drainpipe a few cm proud may be a
    strong peak of a 1 m block (independent dev seed 5: the front-most peak put a block's wall 6 cm forward, and
    the real wall beside the pilaster read as glass over the façade's whole height), and a shop front's glass a few
    cm back may be the highest one (hard seed 58)."""
    ev = params.evidence
    block, near = _wall_blocks(sdt, s0, params, members)
    if not near.any():
        return np.full(len(sdt), np.nan)
    uniq, b_idx = np.unique(block[near], return_inverse=True)
    d_near = sdt[near, 2]
    smooth = _depth_histogram(b_idx, d_near, len(uniq), params)
    centres = _bin_centres(params, smooth.shape[1])
    level = _wall_level(sdt, params, members)
    nearest = np.argmin(np.where(_strong_peaks(smooth), np.abs(centres - level)[None, :], np.inf), axis=1)
    peak = centres[nearest]
    close = np.abs(d_near - peak[b_idx]) <= ev.pass_depth
    mode = peak.copy()
    if close.any():
        groups, median, _ = _group_median(b_idx[close], d_near[close])
        mode[groups] = median
    mode[np.bincount(b_idx, minlength=len(uniq)) < 20] = np.nan
    return _per_point(uniq, _like_neighbours(uniq, mode, params), block)


def _like_neighbours(uniq: np.ndarray, mode: np.ndarray, params: FacadeParams) -> np.ndarray:
    """The block walls, each within ``wall_neighbour_tol`` of the median of the walls in the blocks within
    ``wall_neighbour_blocks`` (itself included); where one lies farther off, that median. The GPS drift moves a
    wall smoothly along the façade, so a block whose peak is off its neighbours' is not the wall:
    behind them, a door leaf a few cm back filling the block's wall band (a 2.8 m garage door under a low eave, hard
    dev seed 52: leaf 7 cm back, twice the wall's returns, read as wall on every scan line of one head); in front of
    them, a pilaster or drainpipe beside the wall (independent dev seed 5: a pilaster 6 cm proud became a block's
    wall, and the real wall beside it read as glass over the façade's whole height; on a rough wall a pilaster
    merely pulls the block's peak 2 cm forward, enough for a fifth of the wall beside it to read as glass)."""
    k = params.evidence.wall_neighbour_blocks
    if k <= 0 or len(uniq) < 2:
        return mode
    pos = np.searchsorted(uniq, uniq[:, None] + np.arange(-k, k + 1)[None, :])
    pos = np.clip(pos, 0, len(uniq) - 1)
    near = np.where(uniq[pos] == uniq[:, None] + np.arange(-k, k + 1)[None, :], mode[pos], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a block whose neighbours all lack a wall: NaN stays
        ref = np.nanmedian(near, axis=1)
    off = np.isfinite(mode) & np.isfinite(ref) & (np.abs(mode - ref) > params.evidence.wall_neighbour_tol)
    return np.where(off, ref, mode)


def _fill_sensors(sensors: np.ndarray, gps: np.ndarray) -> np.ndarray:
    """Sensor positions where unknown (NaN: ground points) interpolated in time from the known ones."""
    known = np.isfinite(sensors).all(axis=1)
    if known.all() or known.sum() < 2:
        return sensors
    order = np.argsort(gps[known], kind="stable")
    kt, ks = gps[known][order], sensors[known][order]
    out = sensors.copy()
    for k in range(3):
        out[~known, k] = np.interp(gps[~known], kt, ks[:, k])
    return out


def scanner_heads(sdt: np.ndarray, sensors_sdt: np.ndarray, gps: np.ndarray) -> np.ndarray:
    """Which scanner head fired each return (0 or 1): two crossed profilers fire at the same times and one file
    interleaves them, so their scan lines are told apart by the yaw of the profile plane each pulse lies in
    (atan(forward / sideways) of its direction, forward = the sensor's direction of travel). One head (0 for all)
    unless at least 20 % of the pulses lie in planes yawed more than 10° either way."""
    heads = np.zeros(len(gps), dtype=np.int64)
    order = np.argsort(gps, kind="stable")
    t, c = gps[order], sensors_sdt[order]
    if len(t) < 20 or t[-1] - t[0] <= 0:
        return heads
    span = max(0.05, 1e-3 * (t[-1] - t[0]))  # travel direction over +-span seconds
    lo = np.searchsorted(t, t - span)
    hi = np.clip(np.searchsorted(t, t + span, side="right") - 1, 0, len(t) - 1)
    travel = c[hi] - c[lo]
    travel[:, 1] = 0.0  # façade coordinates: t is the vertical
    travel /= np.maximum(np.linalg.norm(travel, axis=1, keepdims=True), 1e-9)
    d = sdt[order] - c
    forward = np.sum(d * travel, axis=1)
    sideways = d[:, 0] * travel[:, 2] - d[:, 2] * travel[:, 0]
    yaw = np.degrees(np.arctan(forward / np.where(np.abs(sideways) > 1e-9, sideways, 1e-9)))
    plus, minus = float(np.mean(yaw > 10.0)), float(np.mean(yaw < -10.0))
    if plus >= 0.2 and minus >= 0.2:
        heads[order] = (yaw > 0).astype(np.int64)
    return heads


def missed_pulse_crossings(sdt: np.ndarray, sensors_sdt: np.ndarray, gps: np.ndarray, max_range: float,
                           params: FacadeParams, occluder: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Where the pulses that returned nothing crossed the plane d = 0: (s, t, |cos incidence|, beside an
    occluder); ``None`` when the times do not order the pulses (most returns share their time with the next one:
    a time per scan line only).

    ``sdt`` are returns around the façade in façade coordinates (everything a pulse could hit between the sensor
    and far behind the wall, ground included), ``sensors_sdt`` their pulses' origins (NaN where unknown:
    interpolated in time) and ``gps`` their times. The returns of each scanner head (:func:`scanner_heads`) are
    ordered by time; consecutive returns ``k`` pulse periods apart (the period: the 20th percentile of the
    positive time steps) leave ``k - 1`` missed pulses when ``k`` is 2 .. ``max_missed_pulses + 1`` and the angle
    per period matches the line's angular step (0.4-1.6 x, else the two returns belong to different scan lines);
    their directions are interpolated between the two returns'. Crossings beyond ``max_range`` or at incidences
    above ``missed_max_incidence_deg`` are dropped: no return is expected there. The crossings of a run next to an
    ``occluder`` return (per return; ``missed_occluder_depth``) are flagged: those pulses may have ended on its
    edge.
    """
    empty = (np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool))
    if len(gps) < 3:
        return empty
    sensors_sdt = _fill_sensors(np.asarray(sensors_sdt, dtype=np.float64), gps)
    heads = scanner_heads(sdt, sensors_sdt, gps)
    blocked = np.zeros(len(gps), dtype=bool) if occluder is None else np.asarray(occluder, dtype=bool)
    parts = [_missed_in_line(sdt[heads == h], sensors_sdt[heads == h], gps[heads == h], max_range, params,
                             blocked[heads == h]) for h in np.unique(heads)]
    if any(p is None for p in parts):
        return None
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(4))  # type: ignore[return-value]


def _missed_in_line(sdt: np.ndarray, sensors_sdt: np.ndarray, gps: np.ndarray, max_range: float,
                    params: FacadeParams, blocked: np.ndarray) -> tuple[np.ndarray, ...] | None:
    """:func:`missed_pulse_crossings` for the returns of one scanner head."""
    ev = params.evidence
    empty = (np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool))
    if len(gps) < 3:
        return empty
    order = np.argsort(gps, kind="stable")
    p, c, g = sdt[order], sensors_sdt[order], gps[order]
    dt = np.diff(g)
    positive = dt[dt > 1e-9]
    if len(positive) < 0.5 * len(dt):
        return None  # most returns share their time with the next: no per-pulse times, no scan-line order
    if len(positive) < 10:
        return empty
    period = float(np.quantile(positive, 0.2))
    steps = np.rint(dt / period).astype(np.int64)
    sens = c[:-1]
    ok = np.isfinite(sens).all(axis=1)
    ua = p[:-1] - sens
    ub = p[1:] - sens
    ua /= np.maximum(np.linalg.norm(ua, axis=1, keepdims=True), 1e-9)
    ub /= np.maximum(np.linalg.norm(ub, axis=1, keepdims=True), 1e-9)
    angle = np.arccos(np.clip(np.sum(ua * ub, axis=1), -1.0, 1.0))
    adjacent = ok & (steps == 1)
    if adjacent.sum() < 10:
        return empty
    step_angle = float(np.median(angle[adjacent]))
    per_step = angle / np.maximum(steps, 1)
    gap = ok & (steps >= 2) & (steps <= ev.max_missed_pulses + 1)
    gap &= (per_step >= 0.4 * step_angle) & (per_step <= 1.6 * step_angle)
    idx = np.flatnonzero(gap)
    if len(idx) == 0:
        return empty
    n_missing = steps[idx] - 1
    stop = blocked[order]
    beside = np.repeat((stop[:-1] | stop[1:])[idx], n_missing)
    rep = np.repeat(idx, n_missing)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(n_missing) - n_missing, n_missing) + 1
    f = (k / np.repeat(steps[idx], n_missing))[:, None]
    dirs = (1.0 - f) * ua[rep] + f * ub[rep]
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-9)
    origin = sens[rep]
    valid = (origin[:, 2] > 0) & (dirs[:, 2] < -1e-9)
    lam = np.where(valid, -origin[:, 2] / np.where(valid, dirs[:, 2], -1.0), np.inf)
    cos_inc = np.abs(dirs[:, 2])
    valid &= (lam <= max_range) & (cos_inc >= np.cos(np.radians(ev.missed_max_incidence_deg)))
    s = origin[valid, 0] + lam[valid] * dirs[valid, 0]
    t = origin[valid, 1] + lam[valid] * dirs[valid, 1]
    return s, t, cos_inc[valid], beside[valid]


def pulse_gaps_agree(ev: CellEvidence, params: FacadeParams) -> bool:
    """Whether the missed pulses read from the gaps in the returns' time order agree with the wall's returns: on the
    cells holding at least 3 wall returns, missed pulses make at most ``missed_max_wall_ratio`` of the pulses
    (fewer than 20 such cells: no verdict, they agree).

    The gap reading assumes a profiler, whose consecutive pulses sweep one scan line. A rotating multi-beam
    scanner fires its 32 lasers in turn at interleaved elevations: consecutive returns in time belong to different
    lasers, a laser pointing at the sky leaves a "gap", and the directions interpolated across it land on the
    wall. On independent dev seed 6 such crossings made up 30-69 % of the pulses on well sampled wall and turned
    whole façades into one unknown region; a profiler's gaps put at most 0.1 % there on most façades (15 % on
    one). Where they disagree the façade keeps its other evidence, the returns behind the wall. The gaps next to an
    occluder count here too: the question is whether the gaps are missed pulses at all (dropping them would pass
    a multi-beam scanner's gaps: independent dev seed 6, 8 false windows on a far side wall)."""
    dense = ev.wall >= 3
    if dense.sum() < 20:
        return True
    gaps = ev.missed if ev.missed_beside is None else ev.missed + ev.missed_beside
    missed = float(gaps[dense].sum())
    return missed <= params.evidence.missed_max_wall_ratio * (missed + float(ev.wall[dense].sum()))


def _count(s: np.ndarray, t: np.ndarray, shape: tuple[int, int], s0: float, t0: float, cell: float,
           weights: np.ndarray | None = None) -> np.ndarray:
    row, col = cell_index(s, t, cell, s0, t0, shape)
    inside = row >= 0
    flat = row[inside] * shape[1] + col[inside]
    w = None if weights is None else weights[inside]
    return np.bincount(flat, weights=w, minlength=shape[0] * shape[1]).reshape(shape)


def cell_evidence(wall_sdt: np.ndarray, wall_sensors: np.ndarray, behind_sdt: np.ndarray, behind_sensors: np.ndarray,
                  deep: np.ndarray, missed: tuple[np.ndarray, ...], shape: tuple[int, int],
                  s0: float, t0: float, cell: float, front_sdt: np.ndarray | None = None) -> CellEvidence:
    """Count the pulses per cell: ``wall_sdt`` returns on the wall, ``behind_sdt`` returns behind it (``deep``:
    farther than layer_back, else recessed), each at the crossing of its ray with the plane, and the ``missed``
    crossings of :func:`missed_pulse_crossings` (those beside an occluder counted apart: no evidence); ``front_sdt``:
    returns in front of the wall (counted apart: no pulse through the plane, no wall either)."""
    s, t, lam = project_rays(behind_sdt, behind_sensors)
    ok = np.isfinite(lam)
    wall_dir = wall_sdt - wall_sensors
    wall_cos = np.abs(wall_dir[:, 2]) / np.maximum(np.linalg.norm(wall_dir, axis=1), 1e-9)
    back_dir = behind_sdt - behind_sensors
    back_cos = np.abs(back_dir[:, 2]) / np.maximum(np.linalg.norm(back_dir, axis=1), 1e-9)
    wall = _count(wall_sdt[:, 0], wall_sdt[:, 1], shape, s0, t0, cell)
    recessed = _count(s[ok & ~deep], t[ok & ~deep], shape, s0, t0, cell)
    through = _count(s[ok & deep], t[ok & deep], shape, s0, t0, cell)
    ms, mt, mcos, beside = missed
    missed_beside = _count(ms[beside], mt[beside], shape, s0, t0, cell)
    ms, mt, mcos = ms[~beside], mt[~beside], mcos[~beside]
    missed_n = _count(ms, mt, shape, s0, t0, cell)
    cos_sum = (_count(wall_sdt[:, 0], wall_sdt[:, 1], shape, s0, t0, cell, np.nan_to_num(wall_cos))
               + _count(s[ok], t[ok], shape, s0, t0, cell, np.nan_to_num(back_cos[ok]))
               + _count(ms, mt, shape, s0, t0, cell, mcos))
    total = wall + recessed + through + missed_n
    cos_mean = np.where(total > 0, cos_sum / np.maximum(total, 1), 0.0)
    front = None if front_sdt is None else _count(front_sdt[:, 0], front_sdt[:, 1], shape, s0, t0, cell)
    return CellEvidence(wall=wall, recessed=recessed, through=through, missed=missed_n, cos_incidence=cos_mean,
                        front=front, missed_beside=missed_beside)


def _pass_cells(ev: CellEvidence, params: FacadeParams) -> np.ndarray:
    """Cells at least ``min_pass_pulses`` pulses passed, at most ``max_wall_share`` of whose pulses returned from
    the wall (:func:`opening_cells` before its growth)."""
    p = params.evidence
    return (ev.passed >= p.min_pass_pulses) & (ev.wall <= p.max_wall_share * ev.pulses)


def opening_cells(ev: CellEvidence, params: FacadeParams) -> np.ndarray:
    """Cells the laser went through: at least ``min_pass_pulses`` pulses passed the plane there and at most
    ``max_wall_share`` of the cell's pulses returned from the wall; cells with no pulse at all within
    ``evidence_grow_cells`` of such a cell join it: the scan lines of a far façade are further apart than a cell.
    Cells with returns in front of the wall (``ev.front``: open shutters beside a window) are no such gap."""
    p = params.evidence
    pulses = ev.pulses
    hole = _pass_cells(ev, params)
    k = p.evidence_grow_cells
    if k > 0 and hole.any():  # the edge lies somewhere between the last pulse through and the first on the wall
        # a cell whose pulses stopped in front of the wall (an open shutter beside the window) is no gap
        empty = (pulses == 0) if ev.front is None else (pulses == 0) & (ev.front == 0)
        hole |= ndimage.binary_dilation(hole, structure=square(k)) & empty
    return hole


def stray_patches(cells: np.ndarray, ev: CellEvidence, params: FacadeParams,
                  keep: np.ndarray | None = None) -> np.ndarray:
    """The connected patches (8-neighbours) of opening ``cells`` that hold fewer than ``min_pass_cells`` cells
    pulses passed (:func:`opening_cells` before its growth) and none of the ``keep`` cells (door leaves): one or
    two stray pulses through an unsampled band, grown by ``evidence_grow_cells`` into a 0.5 m square, are no
    evidence of an opening (issue 18 round 17)."""
    p = params.evidence
    if p.min_pass_cells <= 1 or not cells.any():
        return np.zeros(cells.shape, dtype=bool)
    seeds = cells & _pass_cells(ev, params)
    labels, n = ndimage.label(cells, structure=np.ones((3, 3), dtype=bool))
    evidenced = np.bincount(labels[seeds], minlength=n + 1)
    if keep is not None:
        evidenced[np.unique(labels[keep & cells])] = p.min_pass_cells
    return cells & (evidenced[labels] < p.min_pass_cells)


def wall_offset(s: np.ndarray, t: np.ndarray, rel: np.ndarray, shape: tuple[int, int], s0: float, t0: float,
                cell: float, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Per cell the mean depth, relative to the local wall, of the returns within ``band`` of it (NaN: none) and
    their count. Range noise of a few mm averages out over a cell's returns: a leaf 2 cm behind the wall shows."""
    near = np.abs(rel) <= band
    n = _count(s[near], t[near], shape, s0, t0, cell)
    total = _count(s[near], t[near], shape, s0, t0, cell, rel[near])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan), n


def _mean_offset(ev: CellEvidence, cells: np.ndarray) -> float:
    """Return-weighted mean wall offset over ``cells`` (NaN without returns)."""
    n = ev.offset_n[cells]
    if n.sum() <= 0:
        return float("nan")
    return float(np.nansum(ev.offset[cells] * n) / n.sum())


def door_leaves(ev: CellEvidence, hole: np.ndarray, ground_t: np.ndarray, t0: float, cell: float,
                params: FacadeParams) -> tuple[np.ndarray, np.ndarray]:
    """Cells of door leaves nearly flush with the wall (a flush door 2-3 cm back returns most of its pulses within
    ``pass_depth`` of the wall: too few cross the plane for :func:`opening_cells`). A door leaf is told from the
    wall by geometry: a rectangle of cells whose mean return depth lies at least ``leaf_offset`` behind the wall
    (joined with the opening cells around it), door-sized (``door_min_height`` tall, ``door_min_width`` ..
    ``door_max_width`` wide), filling ``Ta`` of its bounding box, starting within ``door_leaf_tol`` of the
    ground line and lying ``leaf_offset`` behind the wall beside and above it. Other regions are left alone: a
    blank wall with range noise never forms such a rectangle, glass and rooms are :func:`opening_cells`'.

    Returns (leaves, crossed): ``crossed`` are the cells with returns a little behind the wall inside such a
    rectangle that the pulses mostly crossed: not wall (a flush door half crossed, issue 18), but no leaf either
    (glass a few cm back returns like one): the crossed cells type that opening."""
    p, op = params.evidence, params.openings
    out = np.zeros(hole.shape, dtype=bool)
    crossed = np.zeros(hole.shape, dtype=bool)
    if not p.door_leaf or ev.offset is None:
        return out, crossed
    known = (ev.offset_n >= 2) | hole  # cells whose returns tell wall from leaf
    # a cell's mean is noisy (a few returns): half the offset here, the whole region must lie leaf_offset back
    behind = ((ev.offset_n >= 2) & (ev.offset < -0.5 * p.leaf_offset)) | hole
    # the scan lines of a far wall leave rows without returns: bridge them, never across measured wall
    closed = ndimage.binary_closing(np.pad(behind, 2), structure=square(2))[2:-2, 2:-2]
    # bridged: cells without a return, or whose one return lies back too (one return on the wall is measured
    # wall: bridging those joined a sparse campaign's garage door with the whole façade, dev seed 25)
    single_back = (ev.offset_n == 1) & (np.nan_to_num(ev.offset) < -0.5 * p.leaf_offset)
    bridge = closed & ~known & ((ev.offset_n == 0) | single_back)
    behind = ndimage.binary_opening(behind | bridge, structure=square(1)) | (behind & hole)
    labels, _ = ndimage.label(behind)
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        r0, r1, c0, c1 = sl[0].start, sl[0].stop, sl[1].start, sl[1].stop
        region = labels == lab
        width, height = (c1 - c0) * cell, (r1 - r0) * cell
        if not op.door_sized(width, height):
            continue
        if (region & known).sum() < op.Ta * known[r0:r1, c0:c1].sum():
            continue  # measured wall inside the box: not one rectangle
        if t0 + r0 * cell > float(np.mean(ground_t[c0:c1])) + op.door_leaf_tol:  # a leaf: maybe up some steps
            continue
        leaf = region & ~hole & (ev.offset_n > 0)
        if leaf.sum() < 0.3 * (region & known).sum():
            # mostly crossed by the pulses: its leaf cells are not wall (without them a flush door a campaign sees
            # half crossed, half as returns 2-3 cm back, breaks into fragments and votes wall: issue 18). They only
            # complete the opening (a door up some steps as much as one on the street); its type is the typing's
            # (door_or_window: the crossed cells' passing pulses, the floor level of the façade)
            # the leaf's depth: its returns are split at pass_depth between the crossed cells and the leaf cells
            # (a mean over the leaf cells alone is biased towards the wall: seed 23 b6, -9 mm for a leaf 23 mm back)
            mark, into, depth_cells = leaf, crossed, region
        else:
            mark, into, depth_cells = region, out, leaf
        k = 3
        ring = np.zeros_like(region)
        ring[max(r0 - k, 0):r1 + k, max(c0 - k, 0):c1 + k] = True
        ring[:r0] = False  # not below the door: the ground, a step
        ring &= ~ndimage.binary_dilation(region) & ~hole
        if not (_mean_offset(ev, depth_cells) - _mean_offset(ev, ring) <= -p.leaf_offset):
            continue
        into |= mark
    return out, crossed


def recessed_share(ev: CellEvidence) -> np.ndarray:
    """Per cell, the share of the pulses through the wall plane that came back from just behind it (a door leaf, a
    curtain: 1; glass returning a share of the pulses, a room, nothing: less); NaN where no pulse passed."""
    passed = ev.passed
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(passed > 0, ev.recessed / np.maximum(passed, 1e-12), np.nan)


def vote_weights(ev: CellEvidence, occluded: np.ndarray, params: FacadeParams) -> np.ndarray:
    """How much this campaign's word on each cell counts in the map (1..4): the pulses per cell times the cosine
    of their incidence, over ``weight_pulses`` pulses per weight step; halved (at least 1) within
    ``weight_occlusion_cells`` of an occluded cell, where shadows blur what was seen."""
    p = params.evidence
    quality = ev.pulses * ev.cos_incidence / max(p.weight_pulses, 1e-9)
    weight = np.clip(np.floor(quality) + 1, 1, 4).astype(np.int32)
    if p.weight_occlusion_cells > 0 and occluded.any():
        near = ndimage.binary_dilation(occluded, structure=square(p.weight_occlusion_cells))
        weight[near] = np.maximum(1, weight[near] // 2)
    return weight
