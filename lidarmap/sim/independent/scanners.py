"""The survey vehicle: its drive (speed profile with a stop), its attitude, its scanners and its GNSS drift.

Body frame: x forward, y left, z up. Attitude R = Rz(yaw) . Ry(pitch) . Rx(roll) maps body vectors to the
local frame (positive pitch lowers the nose; positive roll raises the left side). Scanners fire pulses at
known times; each pulse's origin is the scanner's optical centre at that time, its direction the scan pattern
rotated by the mount and the vehicle attitude. Local time tau is seconds since the first pulse; GPS time =
t0 + tau (adjusted standard GPS time).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .terrain import Terrain

VEHICLE_BOX = np.array([[-2.4, -0.95, 0.0], [2.0, 0.95, 1.75]])  # body-frame box the pulses cannot leave through
DT = 0.005  # motion table step (s)
HDL_ORDER = np.array([i // 2 + (16 if i % 2 else 0) for i in range(32)])  # firing order interleaves low/high beams


@dataclass
class Scanner:
    kind: str  # profile | x_pair | multibeam
    rate: float  # profiles/s per head (profile, x_pair) or rotations/s (multibeam)
    step_deg: float  # angular step within a profile / between azimuth firings
    lever: np.ndarray  # optical centre in the body frame
    mounts: list  # one rotation (3x3) per head: scanner frame -> body frame
    sigma: float  # range noise (m)
    max_range: float
    divergence: float  # full beam divergence (rad)
    aperture: float = 0.01  # exit aperture diameter (m)
    min_sep: float = 0.8  # returns closer than this merge into one (mixed) return
    max_returns: int = 5
    packet: int = 500  # pulses per delivered packet
    keep_frac: float = 1.0  # multibeam: share of azimuths delivered (two side sectors) when the budget needs it
    params: dict = field(default_factory=dict)

    @property
    def n_per(self) -> int:
        """Pulses per profile (profile heads) or azimuth firings per rotation (multibeam)."""
        return int(round(360.0 / self.step_deg))

    @property
    def pulse_rate(self) -> float:
        if self.kind == "multibeam":
            return 32 * self.n_per * self.rate
        return self.n_per * self.rate * len(self.mounts)


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rpy_matrices(roll, pitch, yaw) -> np.ndarray:
    """(n, 3, 3) = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    R = np.empty(np.shape(roll) + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def draw_scanner(rng, kind: str) -> Scanner:
    common = {"sigma": float(rng.uniform(0.005, 0.015)), "max_range": float(rng.uniform(50.0, 120.0)),
              "divergence": float(rng.uniform(0.3e-3, 0.5e-3)), "min_sep": float(rng.uniform(0.5, 1.2))}
    if kind == "profile":
        yaw = np.radians(rng.uniform(-10, 10))
        return Scanner(kind, float(rng.uniform(100, 250)), float(rng.uniform(0.1, 0.4)),
                       np.array([-2.2, 0.0, rng.uniform(2.2, 2.6)]), [rot_z(yaw)], **common,
                       params={"mount_yaw_deg": float(np.degrees(yaw))})
    if kind == "x_pair":
        psi, tilt = np.radians(rng.uniform(35, 45)), np.radians(rng.uniform(5, 20))
        mounts = [rot_z(psi) @ rot_y(tilt), rot_z(-psi) @ rot_y(tilt)]
        return Scanner(kind, float(rng.uniform(100, 250)), float(rng.uniform(0.1, 0.4)),
                       np.array([-2.2, 0.0, rng.uniform(2.2, 2.6)]), mounts, **common,
                       params={"yaw_deg": float(np.degrees(psi)), "tilt_deg": float(np.degrees(tilt))})
    tilt = np.radians(rng.uniform(0, 25)) * rng.choice([-1, 1])
    sc = Scanner(kind, float(rng.uniform(10, 20)), float(rng.uniform(0.1, 0.4)),
                 np.array([rng.uniform(0.0, 0.5), 0.0, rng.uniform(1.8, 2.4)]), [rot_x(tilt)], **common)
    sc.max_returns, sc.packet = 2, 384
    sc.params = {"tilt_deg": float(np.degrees(tilt)), "elevations_deg": [-30.0, 10.0]}
    return sc


def fit_budget(sc: Scanner, duration: float, budget: float) -> bool:
    """Coarsen the pattern within its ranges (step up to 0.4 deg, rate down to its minimum; multibeam: deliver
    two side sectors only, at least 40 % of the turn) until the pulses fit the budget; False if they still do not."""
    def total():
        return sc.pulse_rate * duration * sc.keep_frac

    if total() > budget:
        sc.step_deg = float(min(0.4, max(sc.step_deg, sc.step_deg * total() / budget)))
    low = 10.0 if sc.kind == "multibeam" else 100.0
    if total() > budget:
        sc.rate = float(max(low, sc.rate * budget / total()))
    if sc.kind == "multibeam" and total() > budget:
        sc.keep_frac = float(max(0.4, budget / (sc.pulse_rate * duration)))
    return total() <= budget * 1.0001


# ----------------------------------------------------------------------------------------------------------------------
# Motion


@dataclass
class Motion:
    tau: np.ndarray
    p: np.ndarray  # distance driven since the path start
    v: np.ndarray
    x_start: float
    direction: int
    lane_y: float
    stop: tuple  # (tau0, tau1)
    t_fire: float  # pulses are fired for tau in [0, t_fire]
    wander: tuple  # lateral wander (amplitude, period in metres, phase)
    vib: dict  # roll/pitch vibration


def simulate_drive(rng, length: float, direction: int, lane_offset: float, speed: float, stop_frac: float,
                   stop_dur: float, acc: float, dec: float) -> Motion:
    """Speed profile: enters moving, accelerates to cruise (+-8 % variation), brakes to a stop, waits, goes on."""
    total = length + 10.0
    p_stop = stop_frac * total
    period, phase = rng.uniform(5.0, 15.0), rng.uniform(0, 2 * np.pi)
    taus, ps, vs = [], [], []
    tau, p, v = -1.0, -speed * 0.7, speed * rng.uniform(0.5, 1.0)
    stop = None
    while p < total + speed:
        cruise = speed * (1 + 0.08 * np.sin(2 * np.pi * tau / period + phase))
        if stop is None:
            target = min(cruise, np.sqrt(2 * dec * max(p_stop - p, 0.0)))
            if p_stop - p < 0.02 and v < 0.3:
                stop = (tau, tau + stop_dur)
                v = 0.0
        elif tau < stop[1]:
            target = 0.0
        else:
            target = cruise
        if stop is not None and stop[0] <= tau < stop[1]:
            v = 0.0
        else:
            v = float(np.clip(target, v - dec * DT, v + acc * DT))
        taus.append(tau), ps.append(p), vs.append(v)
        p += v * DT
        tau += DT
    tau_a, p_a = np.array(taus), np.array(ps)
    t_fire = float(np.interp(total, p_a, tau_a)) if p_a[-1] >= total else float(tau_a[-1] - 1.0)
    x_start = -5.0 if direction > 0 else length + 5.0
    vib = {"amp": np.radians(rng.uniform(0.1, 0.3)), "freq": rng.uniform(1.5, 12.0, (2, 3)),
           "phase": rng.uniform(0, 2 * np.pi, (2, 3)), "w": rng.dirichlet(np.ones(3), 2)}
    return Motion(tau_a, p_a, np.array(vs), x_start, direction, -direction * lane_offset, stop or (0.0, 0.0), t_fire,
                  (rng.uniform(0.02, 0.15), rng.uniform(30.0, 80.0), rng.uniform(0, 2 * np.pi)), vib)


def vehicle_pose(m: Motion, terrain: Terrain, tau: np.ndarray):
    """Ground reference point (n, 3), rotation (n, 3, 3) and (roll, pitch, yaw) of the vehicle at times tau."""
    p = np.interp(tau, m.tau, m.p)
    v = np.interp(tau, m.tau, m.v)
    amp, per, ph = m.wander
    x = m.x_start + m.direction * p
    y = m.lane_y + amp * np.sin(2 * np.pi * p / per + ph)
    dy = amp * 2 * np.pi / per * np.cos(2 * np.pi * p / per + ph)
    yaw = np.arctan2(dy, m.direction)
    z = terrain.z(x, y)
    fx, fy = np.cos(yaw), np.sin(yaw)
    g_fwd = (terrain.z(x + fx, y + fy) - terrain.z(x - fx, y - fy)) / 2.0
    g_left = (terrain.z(x - 0.8 * fy, y + 0.8 * fx) - terrain.z(x + 0.8 * fy, y - 0.8 * fx)) / 1.6
    moving = 0.3 + 0.7 * np.clip(v / 3.0, 0.0, 1.0)
    vib = m.vib
    shake = [vib["amp"] * moving * sum(vib["w"][i, j] * np.sin(2 * np.pi * vib["freq"][i, j] * tau + vib["phase"][i, j])
                                       for j in range(3)) for i in range(2)]
    roll = np.arctan(g_left) + shake[0]
    pitch = -np.arctan(g_fwd) + shake[1]
    R = rpy_matrices(roll, pitch, yaw)
    return np.stack([x, y, z], -1), R, np.stack([roll, pitch, yaw], -1)


def sensor_pose(m: Motion, terrain: Terrain, sc: Scanner, tau: np.ndarray):
    """Laser origin (n, 3) and vehicle rotation (n, 3, 3), (roll, pitch, yaw) (n, 3)."""
    ground, R, rpy = vehicle_pose(m, terrain, tau)
    return ground + R @ sc.lever, R, rpy


# ----------------------------------------------------------------------------------------------------------------------
# Pulses


def pulse_pattern(sc: Scanner, k: np.ndarray):
    """Firing time (tau) and body-frame direction of pulses with global indices k (acquisition order)."""
    k = k.astype(np.int64)
    if sc.kind == "multibeam":
        block, laser = k // 32, k % 32
        dt_block = 1.0 / (sc.n_per * sc.rate)
        tau = block * dt_block + laser * min(1.152e-6, dt_block / 32)
        beam = HDL_ORDER[laser]
        elev = np.radians(np.linspace(-30.0, 10.0, 32))[beam]
        az = np.pi / 2 - 2 * np.pi * sc.rate * block * dt_block  # clockwise seen from above
        d = np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], -1)
        return tau, d @ sc.mounts[0].T, beam
    heads = len(sc.mounts)
    packet, head = k // sc.packet, (k // sc.packet) % heads
    q = (packet // heads) * sc.packet + k % sc.packet  # index within its own head's pulse train
    per_head = sc.n_per * sc.rate
    tau = q / per_head + head * 0.5 / per_head
    alpha = 2 * np.pi * (q % sc.n_per) / sc.n_per
    d = np.stack([np.zeros_like(alpha), np.cos(alpha), np.sin(alpha)], -1)
    out = np.empty_like(d)
    for h, M in enumerate(sc.mounts):
        sel = head == h
        out[sel] = d[sel] @ M.T
    return tau, out, head


def blocked_by_vehicle(lever: np.ndarray, d_body: np.ndarray) -> np.ndarray:
    """Pulses whose ray from the optical centre enters the vehicle body box (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d_body
        t1 = (VEHICLE_BOX[0] - lever) * inv
        t2 = (VEHICLE_BOX[1] - lever) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax >= np.maximum(tmin, 0.0)) & (tmax > 0)


def in_sectors(sc: Scanner, d_body: np.ndarray) -> np.ndarray:
    """Multibeam sector crop: keep azimuths within keep_frac * 90 deg of the left and right directions."""
    if sc.kind != "multibeam" or sc.keep_frac >= 1.0:
        return np.ones(len(d_body), bool)
    az = np.degrees(np.arctan2(d_body[:, 1], d_body[:, 0]))
    return np.abs(np.abs(az) - 90.0) <= 90.0 * sc.keep_frac


def drift(params: dict, tau: np.ndarray) -> np.ndarray:
    """GNSS/INS position error (n, 3) at tau: sums of sinusoids bounded by the horizontal/vertical amplitudes."""
    tau = np.asarray(tau, float)
    out = []
    for axis, amp in zip(range(3), (params["horizontal"] / np.sqrt(2),) * 2 + (params["vertical"],)):
        w, per, ph = params["w"][axis], params["period"][axis], params["phase"][axis]
        out.append(amp * sum(w[i] * np.sin(2 * np.pi * tau / per[i] + ph[i]) for i in range(3)))
    return np.stack(out, -1)


def draw_drift(rng) -> dict:
    return {"horizontal": float(rng.uniform(0.05, 0.25)), "vertical": float(rng.uniform(0.03, 0.10)),
            "w": rng.dirichlet(np.ones(3), 3), "period": rng.uniform(20.0, 200.0, (3, 3)),
            "phase": rng.uniform(0, 2 * np.pi, (3, 3))}
