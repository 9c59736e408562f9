"""A path estimated from the cloud alone (no GPS time, no origins) under yawed and crossed profilers (issue 16):
a synthetic street (flat road, a wall either side) scanned in scan order by the simulator's profile geometry; the
estimated yaw(s) against the scanner's, the heads split, the scanner's height from the ground strip, and the pulse
clock's sensor positions against the true pulse origins."""

from __future__ import annotations

import numpy as np
import pytest

from lidarmap.facade.sensors import (
    PulseClock,
    SensorParams,
    estimate_path,
    ground_points,
    profile_slopes,
    scan_heads,
    strip_height,
    with_height,
)
from lidarmap.sim.mobile import body_to_world

SPEED, RATE, HEIGHT, STEP_DEG = 5.0, 50.0, 3.1, 0.5  # m/s, profiles/s, m, degrees between pulses
WALLS = (7.0, -9.0)  # y of the left and right walls; the road z = 0 between them, walls 8 m high
HEADING = np.radians(25.0)  # driving direction, counter-clockwise from +x


def street_scan(yaws: tuple[float, ...], length: float = 50.0, rate: float = RATE
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, their pulse origins, their head) in scan order (time, heads interleaved), CRS-like coordinates."""
    n_prof = int(length / SPEED * rate)
    angle = np.radians(-180.0 + STEP_DEG * np.arange(int(360 / STEP_DEG)))
    times = (np.arange(n_prof)[:, None] + np.arange(len(angle))[None, :] / len(angle)).ravel() / rate
    parts = []
    for h, yaw in enumerate(yaws):
        tilt = np.radians(yaw)
        body = np.column_stack([np.sin(tilt) * np.sin(angle), -np.cos(tilt) * np.sin(angle), np.cos(angle)])
        dirs = np.tile(body, (n_prof, 1))  # local frame: x along the street, y left
        origin = np.column_stack([SPEED * times, np.zeros_like(times), np.full_like(times, HEIGHT)])
        hit = np.full(len(dirs), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ground = np.where(dirs[:, 2] < 0, -HEIGHT / dirs[:, 2], np.inf)
            for y in WALLS:
                t_wall = np.where(dirs[:, 1] * y > 0, y / dirs[:, 1], np.inf)
                top = origin[:, 2] + t_wall * dirs[:, 2]
                hit = np.minimum(hit, np.where(top <= 8.0, t_wall, np.inf))
        hit = np.minimum(hit, t_ground)
        ok = np.isfinite(hit) & (hit < 60.0)
        parts.append((times[ok], origin[ok] + hit[ok, None] * dirs[ok], origin[ok], np.full(ok.sum(), h)))
    t = np.concatenate([p[0] for p in parts])
    order = np.argsort(t, kind="stable")
    pts, org, head = (np.concatenate([p[k] for p in parts])[order] for k in (1, 2, 3))
    rpy = np.tile([0.0, 0.0, HEADING], (len(pts), 1))
    shift = np.array([500_000.0, 5_800_000.0, 40.0])
    return body_to_world(pts, rpy) + shift, body_to_world(org, rpy) + shift, head


def _ground(pts: np.ndarray) -> np.ndarray:
    return np.where(pts[:, 2] < 40.05, 2, 6).astype(np.uint8)


@pytest.mark.parametrize("yaws", [(15.0,), (-20.0,), (35.0, -35.0)])
def test_profile_yaw_from_the_ground_stripes_and_the_pulse_clock_path(yaws) -> None:
    pts, origins, true_head = street_scan(yaws)
    classes = _ground(pts)
    params = SensorParams()
    path = estimate_path(pts, classes, params)
    slopes = profile_slopes(path, ground_points(pts, classes, params.cell), params)
    found = np.sort(np.degrees(np.arctan(slopes)))
    # the path's arc length may run against the driving direction: the yaw's sign is the path frame's
    s0, s1 = path.project(origins[[0, -1], :2])[0]
    expected = np.sort([y if s1 > s0 else -y for y in yaws])
    assert len(found) == len(yaws)
    np.testing.assert_allclose(found, expected, atol=2.0)
    if len(yaws) == 2:  # crossed heads: split by the stripe each return's scan line follows on the ground
        s, c = path.project(pts[:, :2])
        head = scan_heads(pts, s, c, slopes)
        assert (head >= 0).all()
        off_nadir = np.abs(c) > 1.5  # nearer, both heads' sensors are nearly the same place: either is right
        agree = np.mean(head[off_nadir] == true_head[off_nadir])  # head numbers follow the slopes' order
        assert max(agree, 1.0 - agree) > 0.98
    # the scanner's height from the ground strip's half width (the default sensor_height is 2.5 m)
    assert strip_height(path, ground_points(pts, classes, params.cell), slopes) == pytest.approx(HEIGHT, abs=0.15)
    path = with_height(path, ground_points(pts, classes, params.cell), slopes, params)
    clock = PulseClock(path, slopes)
    track = clock.trajectory([_Chunk(pts)])
    sensors = track.position_at(clock(0, _Chunk(pts)))
    s = path.project(pts[:, :2])[0]
    walls = (classes == 6) & (s > path.s[0] + 10.0) & (s < path.s[-1] - 10.0)  # the path's ends are extrapolated
    error = np.linalg.norm(sensors - origins, axis=1)
    assert np.degrees(clock.step) == pytest.approx(STEP_DEG, abs=0.05)
    # before: each point's sensor straight across the track from it, metres along the track for a yawed wall
    across = path.at(path.project(pts[:, :2])[0])
    before = np.linalg.norm(across - origins, axis=1)
    assert np.median(before[walls]) > 1.5
    assert np.median(error[walls]) < 0.35 and np.percentile(error[walls], 90) < 1.0, (
        np.median(error[walls]), np.percentile(error[walls], 90))


class _Chunk:
    def __init__(self, xyz: np.ndarray) -> None:
        self.xyz = xyz

    def __len__(self) -> int:
        return len(self.xyz)


def test_map_update_from_a_crossed_head_ply_without_time_through_the_cli(tmp_path) -> None:
    """End to end: the two-head street as a PLY with x, y, z and classes only, no footprints: the update counts
    pulses per head, finds both walls as buildings and marks the campaign as estimated."""
    from conftest import run_cli_in_process as run

    from lidarmap.map.store import MapStore
    from lidarmap.sim.plyout import write_points_ply

    pts, _, _ = street_scan((35.0, -35.0), length=40.0, rate=25.0)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "classification": _ground(pts)}
    ply = write_points_ply(tmp_path / "street.ply", cols, ["crs EPSG:32632"])
    code, _, err = run("map", "update", tmp_path / "s.lmap", "--points", ply)
    assert code == 0, err
    with MapStore.open(tmp_path / "s.lmap") as store:
        building_map = store.load()
    assert building_map.campaigns[-1].summary["sensors"] == "estimated from the cloud"
    assert sum(1 for b in building_map.buildings.values() if b.facades) == 2


def test_a_file_out_of_scan_order_gets_no_pulse_clock(tmp_path) -> None:
    """Without GPS time the pulse order is the file's: a shuffled file is recognised (few consecutive returns one
    angular step apart) and falls back to sensors straight across the track, without pulse order."""
    from lidarmap.map.mls import MIN_ADJACENT, mobile_campaign
    from lidarmap.sim.plyout import write_points_ply

    pts, _, _ = street_scan((15.0,), length=40.0, rate=25.0)
    classes = _ground(pts)
    for name, order in (("ordered", np.arange(len(pts))), ("shuffled", np.random.default_rng(0).permutation(len(pts)))):
        cols = {"x": pts[order, 0], "y": pts[order, 1], "z": pts[order, 2], "classification": classes[order]}
        ply = write_points_ply(tmp_path / f"{name}.ply", cols, ["crs EPSG:32632"])
        campaign = mobile_campaign(ply, None, None, None, 1_000_000)
        assert campaign.mode == "estimated from the cloud"
        assert campaign.pulse_times == (name == "ordered"), name
    assert MIN_ADJACENT == 0.5
