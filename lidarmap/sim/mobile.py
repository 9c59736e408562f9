"""Mobile laser scanning: a vehicle with a 2D profiler drives the streets; one campaign per drive.

The profiler turns in the plane across the driving direction (optionally yawed by ``mls_tilt``), ``mls_rate``
profiles per second, one pulse every ``mls_angular_step`` degrees. Every pulse has its own GPS time and fires from
the sensor position interpolated on the trajectory at that time, so ``Trajectory.position_at(gps_time)`` gives the
exact origin of each point's pulse (before the campaign's misregistration, which moves both alike).

Trajectory angles follow ROS REP 103: body x forward, y left, z up; world = CRS east-north-up; the body-to-world
rotation is R = Rz(yaw) Ry(pitch) Rx(roll) (yaw counter-clockwise from CRS +x; positive pitch = nose down).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from lidarmap.sim.city import LANE_CENTRE, City
from lidarmap.sim.mesh import (
    CLASS_BUILDING,
    CLASS_GROUND,
    CLASS_OTHER,
    CLASS_VEGETATION,
)
from lidarmap.sim.params import SimParams
from lidarmap.sim.raycast import Tracer
from lidarmap.sim.scan import Scan, optics

PROFILES_PER_CHUNK = 400  # bounds memory: ~400 profiles x 900 pulses traced at once
CLASSES = np.array([CLASS_OTHER, CLASS_GROUND, CLASS_VEGETATION, CLASS_BUILDING], np.uint8)


@dataclasses.dataclass
class Campaign:
    """One drive: its route, lane, speed, start time and rigid misregistration (all decided from the seed)."""

    id: int
    direction: int  # +1: street 1 driven towards local +x; -1 the reverse route
    lane_offset: float  # metres right of the street axis (negative: left of it)
    speed: float
    t0: float
    shift: np.ndarray  # misregistration translation (CRS metres)
    rotation_deg: float  # misregistration rotation about z through ``pivot``
    pivot: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def misregister(self, xyz: np.ndarray) -> np.ndarray:
        """Apply this campaign's rigid misregistration to CRS points (N, 3)."""
        a = np.radians(self.rotation_deg)
        c, s = np.cos(a), np.sin(a)
        p = np.asarray(xyz, dtype=np.float64) - self.pivot
        out = np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]])
        return out + self.pivot + self.shift

    def register(self, xyz: np.ndarray) -> np.ndarray:
        """Undo :meth:`misregister` (CRS points back onto the true geometry)."""
        a = -np.radians(self.rotation_deg)
        c, s = np.cos(a), np.sin(a)
        p = np.asarray(xyz, dtype=np.float64) - self.pivot - self.shift
        out = np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]])
        return out + self.pivot

    def to_json(self) -> dict:
        return {"id": self.id, "direction": self.direction, "lane_offset": self.lane_offset, "speed": self.speed,
                "gps_time_start": self.t0,
                "misregistration": {"translation": [float(v) for v in self.shift], "rotation_deg": self.rotation_deg,
                                    "pivot": [float(v) for v in self.pivot],
                                    "formula": "p_file = Rz(rotation_deg) @ (p_true - pivot) + pivot + translation"}}


def plan_campaign(rng: np.random.Generator, index: int, params: SimParams, city: City) -> Campaign:
    """Campaigns alternate direction; every third uses the other lane; each has its own misregistration."""
    direction = 1 if index % 2 == 1 else -1
    lane = LANE_CENTRE * (-1 if index % 3 == 0 else 1) + rng.normal(0.0, 0.25)
    m = params.mls_misregistration
    heading = rng.uniform(0, 2 * np.pi)
    shift = np.array([m * rng.uniform(0.3, 1.0) * np.cos(heading), m * rng.uniform(0.3, 1.0) * np.sin(heading),
                      rng.uniform(-m / 2, m / 2)])
    rotation = float(rng.uniform(-0.01, 0.01)) if m > 0 else 0.0
    t0 = 40000.0 + 86400.0 * ((index - 1) % 6) + float(rng.integers(0, 20000))
    pivot = np.array(city.frame.offset, dtype=np.float64)
    return Campaign(id=index, direction=direction, lane_offset=float(lane),
                    speed=float(params.mls_speed * rng.uniform(0.9, 1.1)), t0=t0, shift=shift, rotation_deg=rotation,
                    pivot=pivot)


# --- route and trajectory --------------------------------------------------------------------------------------

def route(city: City, campaign: Campaign, fillet: float = 6.0) -> np.ndarray:
    """Dense 2D route (local frame) along the street(s) in the campaign's lane, corners rounded."""
    s1 = city.streets[0]
    points = [(s1.x0, s1.y), (s1.x1, s1.y)]
    if len(city.streets) > 1:
        s2 = city.streets[1]
        points += [(s1.x1, s2.y), (s2.x0, s2.y)]
    pts = np.array(points[::campaign.direction])
    pts = _round_corners(pts, fillet)
    tangent = np.gradient(pts, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    right = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    return pts + campaign.lane_offset * right


def _round_corners(pts: np.ndarray, radius: float, iterations: int = 6) -> np.ndarray:
    """Chaikin corner cutting restricted to ``radius`` around each corner (straight parts stay straight)."""
    if len(pts) > 2:
        out = [pts[0]]
        for prev, c, nxt in zip(pts[:-2], pts[1:-1], pts[2:]):
            out += [c + radius * (prev - c) / np.linalg.norm(prev - c), c,
                    c + radius * (nxt - c) / np.linalg.norm(nxt - c)]
        out.append(pts[-1])
        pts = np.array(out)
        for _ in range(iterations):
            q = 0.75 * pts[:-1] + 0.25 * pts[1:]
            r = 0.25 * pts[:-1] + 0.75 * pts[1:]
            pts = np.concatenate([pts[:1], np.stack([q, r], 1).reshape(-1, 2), pts[-1:]])
    # densify so that later arc-length interpolation follows the curve
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    fine = np.linspace(0.0, s[-1], int(s[-1] / 0.5) + 2)
    return np.column_stack([np.interp(fine, s, pts[:, 0]), np.interp(fine, s, pts[:, 1])])


@dataclasses.dataclass
class Path:
    """Sensor pose samples (local frame) at the profile rate: times, positions and roll/pitch/yaw."""

    time: np.ndarray
    xyz: np.ndarray
    rpy: np.ndarray

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and (roll, pitch, yaw) at times ``t`` by linear interpolation (yaw is unwrapped)."""
        pos = np.column_stack([np.interp(t, self.time, self.xyz[:, k]) for k in range(3)])
        rpy = np.column_stack([np.interp(t, self.time, self.rpy[:, k]) for k in range(3)])
        return pos, rpy


def sensor_path(city: City, campaign: Campaign, params: SimParams) -> Path:
    """Poses every 1/rate s at constant speed; the vehicle sits on the terrain (pitch/roll follow its slope)."""
    pts = route(city, campaign)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    step = campaign.speed / params.mls_rate
    n = int(s[-1] / step) + 1
    along = np.arange(n) * step
    xy = np.column_stack([np.interp(along, s, pts[:, 0]), np.interp(along, s, pts[:, 1])])
    z = city.terrain.height(xy) + params.mls_sensor_height
    xyz = np.column_stack([xy, z])
    forward = np.gradient(xyz, axis=0)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    grad = city.terrain.gradient(xy, step=1.5)
    up = np.column_stack([-grad, np.ones(n)])
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    x_axis = forward - np.einsum("ij,ij->i", forward, up)[:, None] * up
    x_axis /= np.linalg.norm(x_axis, axis=1, keepdims=True)
    y_axis = np.cross(up, x_axis)
    yaw = np.unwrap(np.arctan2(x_axis[:, 1], x_axis[:, 0]))
    pitch = -np.arcsin(np.clip(x_axis[:, 2], -1, 1))
    roll = np.arctan2(y_axis[:, 2], up[:, 2])
    return Path(time=campaign.t0 + np.arange(n) / params.mls_rate, xyz=xyz, rpy=np.column_stack([roll, pitch, yaw]))


def body_to_world(vec: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """Rotate body-frame vectors (N, 3) by R = Rz(yaw) Ry(pitch) Rx(roll), one pose per row."""
    cr, sr = np.cos(rpy[:, 0]), np.sin(rpy[:, 0])
    cp, sp = np.cos(rpy[:, 1]), np.sin(rpy[:, 1])
    cy, sy = np.cos(rpy[:, 2]), np.sin(rpy[:, 2])
    x, y, z = vec[:, 0], vec[:, 1], vec[:, 2]
    y1, z1 = cr * y - sr * z, sr * y + cr * z  # Rx(roll)
    x2, z2 = cp * x + sp * z1, -sp * x + cp * z1  # Ry(pitch)
    return np.column_stack([cy * x2 - sy * y1, sy * x2 + cy * y1, z2])  # Rz(yaw)


def profile_plane_normals(path: Path, tilt_deg: float) -> np.ndarray:
    """Unit normals (local frame) of each profile's scan plane."""
    tilt = np.radians(tilt_deg)
    body = np.tile([np.cos(tilt), np.sin(tilt), 0.0], (len(path.time), 1))
    return body_to_world(body, path.rpy)


# --- scanning --------------------------------------------------------------------------------------------------

def profile_directions(params: SimParams) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame pulse directions of one profile and their angles (degrees, 0 = up, +90 = right)."""
    angle = -180.0 + params.mls_angular_step * np.arange(int(round(360.0 / params.mls_angular_step)))
    a, tilt = np.radians(angle), np.radians(params.mls_tilt)
    body = np.column_stack([np.sin(tilt) * np.sin(a), -np.cos(tilt) * np.sin(a), np.cos(a)])
    return body, angle


def scan_campaign(campaign: Campaign, params: SimParams, rng: np.random.Generator, tracer: Tracer, path: Path,
                  on_chunk: Callable | None = None, on_stops: Callable | None = None) -> Scan:
    """All profiles of a campaign (local frame, true geometry).

    ``on_chunk(done, total)`` reports progress in profiles; ``on_stops(origins, dirs, stop_tri, stop_range)``
    receives each chunk's pulses and where they ended (for the visibility truth).
    """
    body, angle = profile_directions(params)
    per_profile = len(angle)
    n_profiles = len(path.time) - 1  # the last pose only closes the trajectory
    parts = []
    for first in range(0, n_profiles, PROFILES_PER_CHUNK):
        k = np.arange(first, min(first + PROFILES_PER_CHUNK, n_profiles))
        j = np.arange(per_profile)
        times = (path.time[k][:, None] + j[None, :] / (per_profile * params.mls_rate)).ravel()
        origins, rpy = path.at(times)
        dirs = body_to_world(np.tile(body, (len(k), 1)), rpy)
        ret = tracer.trace(origins, dirs, max_range=params.mls_max_range, min_separation=params.mls_min_separation)
        parts.append(optics(tracer, ret, origins, dirs, rng, params.mls_range_noise, times,
                            np.tile(angle, len(k)), source_id=campaign.id))
        if on_stops is not None:
            on_stops(origins, dirs, ret.stop_tri, ret.stop_range)
        if on_chunk is not None:
            on_chunk(len(k), n_profiles)
    scan = Scan.concatenate(parts)
    scan.classification = classifier_labels(scan.truth["classification"], params.mls_label_error, rng)
    return scan


def classifier_labels(truth: np.ndarray, error: float, rng: np.random.Generator) -> np.ndarray:
    """Labels a good point classifier would deliver: the true class, with a fraction ``error`` swapped."""
    out = truth.astype(np.uint8).copy()
    wrong = np.flatnonzero(rng.random(len(out)) < error)
    shift = rng.integers(1, len(CLASSES), len(wrong))
    position = np.searchsorted(CLASSES, out[wrong])
    out[wrong] = CLASSES[(position + shift) % len(CLASSES)]
    return out
