"""Parameters of the simulator (``[simulate]`` table of a config file)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from lidarmap.config import check_params
from lidarmap.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class SimParams:
    """Every knob of ``lidarmap simulate``; defaults give the standard scene (8 buildings, 3 campaigns).

    Scene
        seed (0): seeds every random draw; the same seed gives byte-identical outputs.
        buildings (8): existing buildings (one extra "under construction" lot is always added).
        campaigns (3): mobile campaigns (``mls_<i>.laz`` + ``trajectory_<i>.csv``); 0 writes none.
        streets (0): parallel streets lined with buildings; 0 = automatic (1 up to 10 buildings, else 2).
        trees_per_100m (7.0): street trees per 100 m of sidewalk (both sides counted separately).
        trees_touching (0): trees against the walls of existing buildings, crowns over the roof edges
            (:mod:`lidarmap.sim.trees`).
        leaf_off (False): bare crowns (twigs: fewer, smaller scatterers) instead of leaf-on ones.
        parking_occupancy (0.5): probability that a parking slot holds a car, drawn anew for every acquisition.
    Aerial scan (als.laz)
        als_density (12.0): mean pulse (first-return) density over the scene in points/m², strip overlap included.
        als_altitude (300.0): flying height above the highest terrain point, metres.
        als_scan_angle (20.0): half field of view of the oscillating mirror, degrees (scan angle in ±this).
        als_overlap (0.3): side overlap of adjacent flight strips, as a fraction of the swath width.
        als_speed (60.0): aircraft ground speed, m/s.
        als_range_noise (0.025): standard deviation of the range error, metres.
        als_min_separation (1.0): two returns of one pulse closer than this (metres) cannot be told apart.
        als_wall_unlabelled (0.8): fraction of façade points the delivered classification leaves at class 1.
        als_roof_unlabelled (0.12): fraction of roof area (3 m patches) the delivered classification leaves at 1.
    Mobile scans (mls_<i>.laz)
        mls_rate (100.0): profiles per second (rotation rate of the profiler), also the trajectory rate.
        mls_angular_step (0.4): angle between pulses within a profile, degrees.
        mls_speed (6.0): vehicle speed, m/s (each campaign varies it by up to ±10 %).
        mls_sensor_height (2.5): sensor height above the road, metres.
        mls_max_range (60.0): no returns beyond this range, metres.
        mls_range_noise (0.01): standard deviation of the range error, metres.
        mls_min_separation (0.5): minimal distance between two returns of one pulse, metres.
        mls_tilt (0.0): yaw of the profile plane away from "across the driving direction", degrees.
        mls_label_error (0.01): fraction of points the simulated classifier labels wrongly.
        mls_misregistration (0.04): largest horizontal shift (metres) of a campaign's rigid misregistration;
            the vertical shift is at most half of it, the rotation about z at most 0.01°. 0 disables it.
        mls_format ("laz"): how the campaigns are written: "laz" (``mls_<i>.laz``), "ply" (binary little-endian
            ``mls_<i>.ply``, double coordinates) or "ply_ascii" (ASCII PLY) as public MLS data sets deliver them
            (docs/mls.md); the trajectory CSV is written in every case.
        mls_origins (False): PLY only: every point carries its pulse's sensor origin (x_origin, y_origin, z_origin,
            misregistered like the point).
        mls_gps_time (True): PLY only: every point carries its GPS time (gps_time).
    Truth
        visibility_cell (0.1): cell size (metres) of the per-façade visibility grids.
    Family (docs/simulator.md, "Hard family")
        family ("standard"): "standard" (the scene above) or "hard" (randomised façades, grazing side walls, glass,
            vans, per-campaign lane/speed/height/rate/scanner, GPS drift; lidarmap/sim/hard.py). The knobs below
            are read by the hard family only.
        glass_return_min (0.15), glass_return_max (0.6): bounds of the share of pulses a glass pane returns (each
            pane draws its own share in these bounds).
        gps_drift_horizontal (0.12), gps_drift_vertical (0.05): largest smooth GPS drift (metres) of a campaign's
            trajectory and points.
        visibility_max_incidence (80.0): a cell counts as seen (truth visibility) only where the line of sight
            meets the wall at most this far from its normal, degrees (grazing cells are unobservable).
        visibility_max_spacing (0.3): ... and only where the expected distance between samples there (between
            neighbouring profiles' stripes, and between pulses of one profile) is at most this, metres.
    """

    section = "simulate"
    constraints: ClassVar[dict[str, str]] = {
        "seed": ">= 0",
        "buildings": ">= 0",
        "campaigns": ">= 0",
        "streets": ">= 0",
        "trees_per_100m": ">= 0",
        "trees_touching": ">= 0",
        "parking_occupancy": ">= 0",
        "als_density": ">= 0",
        "als_altitude": ">= 0",
        "als_scan_angle": ">= 0",
        "als_overlap": ">= 0",
        "als_speed": ">= 0",
        "als_range_noise": ">= 0",
        "als_min_separation": ">= 0",
        "als_wall_unlabelled": ">= 0",
        "als_roof_unlabelled": ">= 0",
        "mls_rate": ">= 0",
        "mls_angular_step": ">= 0",
        "mls_speed": ">= 0",
        "mls_sensor_height": ">= 0",
        "mls_max_range": ">= 0",
        "mls_range_noise": ">= 0",
        "mls_min_separation": ">= 0",
        "mls_tilt": "[-60, 60]",
        "mls_label_error": ">= 0",
        "mls_misregistration": ">= 0",
        "visibility_cell": ">= 0",
        "family": "in standard, hard",
        "glass_return_min": "[0, 1]",
        "glass_return_max": "[0, 1]",
        "gps_drift_horizontal": "[0, 1]",
        "gps_drift_vertical": "[0, 1]",
        "visibility_max_incidence": "(0, 90]",
        "visibility_max_spacing": "> 0",
        "mls_format": "in laz, ply, ply_ascii",
    }

    seed: int = 0
    buildings: int = 8
    campaigns: int = 3
    streets: int = 0
    trees_per_100m: float = 7.0
    trees_touching: int = 0
    leaf_off: bool = False
    parking_occupancy: float = 0.5
    als_density: float = 12.0
    als_altitude: float = 300.0
    als_scan_angle: float = 20.0
    als_overlap: float = 0.3
    als_speed: float = 60.0
    als_range_noise: float = 0.025
    als_min_separation: float = 1.0
    als_wall_unlabelled: float = 0.8
    als_roof_unlabelled: float = 0.12
    mls_rate: float = 100.0
    mls_angular_step: float = 0.4
    mls_speed: float = 6.0
    mls_sensor_height: float = 2.5
    mls_max_range: float = 60.0
    mls_range_noise: float = 0.01
    mls_min_separation: float = 0.5
    mls_tilt: float = 0.0
    mls_label_error: float = 0.01
    mls_misregistration: float = 0.04
    visibility_cell: float = 0.1
    family: str = "standard"
    glass_return_min: float = 0.15
    glass_return_max: float = 0.6
    gps_drift_horizontal: float = 0.12
    gps_drift_vertical: float = 0.05
    visibility_max_incidence: float = 80.0
    visibility_max_spacing: float = 0.3
    mls_format: str = "laz"
    mls_origins: bool = False
    mls_gps_time: bool = True

    def __post_init__(self) -> None:
        check_params(self)
        checks = [
            (0 <= self.seed < 2**63, "seed must be a non-negative integer"),
            (1 <= self.buildings <= 40, "buildings must be between 1 and 40"),
            (0 <= self.campaigns <= 20, "campaigns must be between 0 and 20"),
            (self.streets in (0, 1, 2), "streets must be 0 (automatic), 1 or 2"),
            (self.trees_per_100m >= 0, "trees_per_100m must be >= 0"),
            (0 <= self.parking_occupancy <= 1, "parking_occupancy must be in [0, 1]"),
            (0 < self.als_density <= 200, "als_density must be in (0, 200] points/m²"),
            (50 <= self.als_altitude <= 3000, "als_altitude must be in [50, 3000] m"),
            (1 <= self.als_scan_angle <= 40, "als_scan_angle must be in [1, 40] degrees"),
            (0 <= self.als_overlap < 0.9, "als_overlap must be in [0, 0.9)"),
            (self.als_speed > 0 and self.mls_speed > 0, "speeds must be > 0"),
            (self.als_range_noise >= 0 and self.mls_range_noise >= 0, "range noise must be >= 0"),
            (self.als_min_separation > 0 and self.mls_min_separation > 0, "min separations must be > 0"),
            (0 <= self.als_wall_unlabelled <= 1 and 0 <= self.als_roof_unlabelled <= 1,
             "unlabelled fractions must be in [0, 1]"),
            (1 <= self.mls_rate <= 1000, "mls_rate must be in [1, 1000] Hz"),
            (0.02 <= self.mls_angular_step <= 10, "mls_angular_step must be in [0.02, 10] degrees"),
            (0.5 <= self.mls_sensor_height <= 10, "mls_sensor_height must be in [0.5, 10] m"),
            (5 <= self.mls_max_range <= 1000, "mls_max_range must be in [5, 1000] m"),
            (-60 <= self.mls_tilt <= 60, "mls_tilt must be in [-60, 60] degrees"),
            (0 <= self.mls_label_error < 0.5, "mls_label_error must be in [0, 0.5)"),
            (0 <= self.mls_misregistration <= 1, "mls_misregistration must be in [0, 1] m"),
            (0.02 <= self.visibility_cell <= 1, "visibility_cell must be in [0.02, 1] m"),
            (self.glass_return_min <= self.glass_return_max, "glass_return_min must be <= glass_return_max"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"simulate parameters: {message}")
