"""Airborne laser scanning: parallel flight strips with side overlap, an oscillating (zig-zag) mirror, multiple
returns, and the partial classification a public data set typically ships with."""

from __future__ import annotations

import dataclasses

import numpy as np

from lidarmap.sim.city import Car, City
from lidarmap.sim.mesh import (
    CLASS_BUILDING,
    CLASS_GROUND,
    CLASS_OTHER,
    CLASS_VEGETATION,
    KIND,
)
from lidarmap.sim.params import SimParams
from lidarmap.sim.raycast import Tracer
from lidarmap.sim.scan import Scan, optics

RUN_IN = 20.0  # metres flown before and after the scene on each strip
TURN_TIME = 90.0  # seconds between strips


@dataclasses.dataclass
class Strip:
    """One flight line in the CRS-aligned frame (x east, y north, centred on the local origin)."""

    id: int
    y: float
    direction: int  # +1 flies east, -1 west
    x_start: float
    x_end: float
    altitude: float
    pulse_rate: float
    line_rate: float
    t0: float

    def to_json(self, frame_offset: tuple[float, float, float]) -> dict:
        return {"id": self.id, "direction_deg": 0.0 if self.direction > 0 else 180.0,
                "y_crs": self.y + frame_offset[1], "x_start_crs": self.x_start + frame_offset[0],
                "x_end_crs": self.x_end + frame_offset[0], "altitude": self.altitude, "pulse_rate_hz": self.pulse_rate,
                "scan_lines_per_s": self.line_rate, "gps_time_start": self.t0}


def plan_strips(city: City, params: SimParams, t0: float) -> list[Strip]:
    """Strips over the terrain with the configured side overlap; pulse rate set for the requested mean density."""
    corners = _terrain_corners_aligned(city)
    z_top = float(city.terrain.node_z().max())
    altitude = z_top + params.als_altitude
    swath = 2 * params.als_altitude * np.tan(np.radians(params.als_scan_angle))
    spacing = (1 - params.als_overlap) * swath
    y_lo, y_hi = corners[:, 1].min(), corners[:, 1].max()
    n = max(2, int(np.ceil((y_hi - y_lo - swath) / spacing)) + 1)
    centres = (y_lo + y_hi) / 2 + (np.arange(n) - (n - 1) / 2) * spacing
    coverage = _mean_coverage(city, centres, swath)
    density = params.als_density / coverage  # per strip, so that the overlapped total averages to the request
    x_lo, x_hi = corners[:, 0].min() - RUN_IN, corners[:, 0].max() + RUN_IN
    pulse_rate = density * params.als_speed * swath
    line_rate = np.sqrt(pulse_rate * params.als_speed / swath)  # equal along- and across-track spacing at nadir
    strips, t = [], t0
    for i, y in enumerate(centres):
        direction = 1 if i % 2 == 0 else -1
        start, end = (x_lo, x_hi) if direction > 0 else (x_hi, x_lo)
        strips.append(Strip(id=i + 1, y=float(y), direction=direction, x_start=float(start), x_end=float(end),
                            altitude=float(altitude), pulse_rate=float(pulse_rate), line_rate=float(line_rate),
                            t0=float(t)))
        t += (x_hi - x_lo) / params.als_speed + TURN_TIME
    return strips


def _terrain_corners_aligned(city: City) -> np.ndarray:
    """Terrain corners in the CRS-aligned frame (local rotated by the layout angle, not shifted)."""
    x0, y0, x1, y1 = city.terrain.bounds
    local = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    return _rot(city.frame.rotation_deg, local)[:, :2]


def _rot(angle_deg: float, xyz: np.ndarray) -> np.ndarray:
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.column_stack([c * xyz[:, 0] - s * xyz[:, 1], s * xyz[:, 0] + c * xyz[:, 1], xyz[:, 2]])


def _mean_coverage(city: City, centres: np.ndarray, swath: float) -> float:
    """How many strips see an average point of the terrain."""
    verts, _ = city.terrain.mesh()
    y = _rot(city.frame.rotation_deg, verts)[:, 1]
    return float(np.mean(np.sum(np.abs(y[:, None] - centres[None]) <= swath / 2, axis=1)))


def strip_pulses(strip: Strip, params: SimParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pulse times, origins, directions (CRS-aligned frame) and scan angles (degrees) of a strip."""
    duration = abs(strip.x_end - strip.x_start) / params.als_speed
    n = int(duration * strip.pulse_rate)
    t = np.arange(n) / strip.pulse_rate
    phase = (t * strip.line_rate) % 2.0
    angle = params.als_scan_angle * (1.0 - 2.0 * np.abs(phase - 1.0))  # triangle wave: one line per sweep
    x = strip.x_start + strip.direction * params.als_speed * t
    origins = np.column_stack([x, np.full(n, strip.y), np.full(n, strip.altitude)])
    a = np.radians(angle)
    right = np.array([0.0, -strip.direction, 0.0])  # right of the flight direction (LAS: positive scan angle)
    dirs = np.sin(a)[:, None] * right[None] + np.column_stack([np.zeros(n), np.zeros(n), -np.cos(a)])
    return strip.t0 + t, origins, dirs, angle


def scan_aerial(city: City, params: SimParams, rng: np.random.Generator,
                t0: float) -> tuple[Scan, list[Strip], list[Car]]:
    """Simulate all strips over the city with the aerial acquisition's own parked cars."""
    cars = city.draw_cars(rng)
    tracer = Tracer(city.scene(cars), seed=[params.seed, 2, 6])
    strips = plan_strips(city, params, t0)
    parts = []
    for strip in strips:
        times, origins, dirs, angle = strip_pulses(strip, params)
        origins, dirs = _rot(-city.frame.rotation_deg, origins), _rot(-city.frame.rotation_deg, dirs)
        ret = tracer.trace(origins, dirs, max_range=3 * params.als_altitude, min_separation=params.als_min_separation)
        parts.append(optics(tracer, ret, origins, dirs, rng, params.als_range_noise, times, angle,
                            source_id=strip.id))
    scan = Scan.concatenate(parts)
    scan.classification = delivered_classes(scan, city, params, rng)
    return scan, strips, cars


def delivered_classes(scan: Scan, city: City, params: SimParams, rng: np.random.Generator) -> np.ndarray:
    """Classification as a partially labelled public data set ships it: ground and vegetation labelled, roofs
    mostly 6 with 3 m patches left at 1, most wall points left at 1, cars and other objects 1."""
    truth = scan.truth["classification"]
    kind = scan.truth["kind"]
    out = np.full(len(truth), CLASS_OTHER, np.uint8)
    out[truth == CLASS_GROUND] = CLASS_GROUND
    out[truth == CLASS_VEGETATION] = CLASS_VEGETATION
    x0, y0, x1, y1 = city.terrain.bounds
    cell = 3.0
    patches = rng.random((int((y1 - y0) / cell) + 2, int((x1 - x0) / cell) + 2)) < params.als_roof_unlabelled
    ix = np.clip(((scan.xyz[:, 0] - x0) / cell).astype(int), 0, patches.shape[1] - 1)
    iy = np.clip(((scan.xyz[:, 1] - y0) / cell).astype(int), 0, patches.shape[0] - 1)
    roof = (truth == CLASS_BUILDING) & (kind == KIND["roof"])
    out[roof & ~patches[iy, ix]] = CLASS_BUILDING
    other_building = (truth == CLASS_BUILDING) & ~roof
    labelled_wall = rng.random(len(truth)) >= params.als_wall_unlabelled
    out[other_building & labelled_wall] = CLASS_BUILDING
    return out
