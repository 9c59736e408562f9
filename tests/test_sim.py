"""The simulator: geometry, labels, determinism, densities, truth files and the CLI, on small scenes."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from pyproj import CRS
from shapely.geometry import Point
from typer.testing import CliRunner

from lidarmap.cli.main import app
from lidarmap.errors import ConfigError
from lidarmap.io.footprints import read_footprints
from lidarmap.io.las import read_las
from lidarmap.io.trajectory import read_trajectory
from lidarmap.sim import SimParams, build_city, load_truth, simulate
from lidarmap.sim.buildings import Facade
from lidarmap.sim.city import BUILDING_LINE
from lidarmap.sim.distance import MeshDistance
from lidarmap.sim.family import DEV_SEEDS, EVAL_SEEDS
from lidarmap.sim.hard import build_hard_city, campaign_setup
from lidarmap.sim.mesh import GLASS, KIND, Labels, Soup, boxes, quads
from lidarmap.sim.raycast import Tracer
from lidarmap.sim.visibility import pulse_spacing, seen_grid, visible_fraction

SEED = 7
PARAMS = SimParams(seed=SEED, buildings=2, campaigns=2)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("sim") / "scene"
    result = simulate(out, PARAMS)
    return result, load_truth(out)


@pytest.fixture(scope="module")
def city():
    return build_city(PARAMS)


@pytest.fixture(scope="module")
def scene_distance(city):
    return MeshDistance(city.static.triangles)


def _registered_mls(truth, campaign):
    cloud = read_las(campaign.laz)
    return cloud, campaign.register(cloud.xyz), truth.labels(f"mls_{campaign.id}")


# --- geometry ----------------------------------------------------------------------------------------------------

def test_als_points_lie_on_true_surfaces(sim, city, scene_distance):
    _, truth = sim
    cloud = read_las(truth.als)
    labels = truth.labels("als")
    keep = np.flatnonzero(labels.kind != KIND["car"])  # cars differ per acquisition; the static scene has none
    pick = np.random.default_rng(0).choice(keep, 4000, replace=False)
    dist, tri = scene_distance(city.frame.to_local(cloud.xyz[pick]))
    sigma = PARAMS.als_range_noise
    assert np.median(dist) < sigma
    assert dist.max() < 6 * sigma
    assert np.mean(city.static.kind[tri] == labels.kind[pick]) > 0.98


def test_mls_points_lie_on_true_surfaces_after_undoing_misregistration(sim, city, scene_distance):
    _, truth = sim
    campaign = truth.campaigns[0]
    cloud, xyz, labels = _registered_mls(truth, campaign)
    keep = np.flatnonzero(labels.kind != KIND["car"])
    pick = np.random.default_rng(1).choice(keep, 4000, replace=False)
    dist, _ = scene_distance(city.frame.to_local(xyz[pick]))
    sigma = PARAMS.mls_range_noise
    assert np.median(dist) < sigma
    assert dist.max() < 6 * sigma
    raw, _ = scene_distance(city.frame.to_local(cloud.xyz[pick]))  # the file itself is off by the misregistration
    assert np.median(raw) > np.median(dist)


def test_no_points_on_the_wall_plane_inside_openings(sim):
    _, truth = sim
    for campaign in truth.campaigns:
        _, xyz, labels = _registered_mls(truth, campaign)
        checked = 0
        for facade in truth.facades.values():
            openings = [e for e in facade.elements if e.kind in ("window", "door")]
            if not openings:
                continue
            std = facade.to_facade(xyz)
            near_plane = np.abs(std[:, 2]) < 0.03
            for e in openings:
                s0, s1, t0, t1 = e.rect
                inside = (std[:, 0] > s0 + 0.05) & (std[:, 0] < s1 - 0.05) & (std[:, 1] > t0 + 0.05) \
                    & (std[:, 1] < t1 - 0.05)
                assert not np.any(inside & near_plane), f"points on the wall plane inside element {e.id}"
                checked += 1
            wall = labels.facade_id == facade.id
            wall &= labels.kind == KIND["wall"]
            assert np.all(np.abs(std[wall, 2]) < 6 * PARAMS.mls_range_noise + 1e-6)
        assert checked > 10


def test_window_points_are_recessed_and_rooms_lie_behind(sim):
    _, truth = sim
    campaign = truth.campaigns[0]
    _, xyz, labels = _registered_mls(truth, campaign)
    elements = truth.elements
    interior = np.flatnonzero(labels.is_kind("window_interior"))
    door = np.flatnonzero(labels.is_kind("door"))
    assert len(interior) > 100 and len(door) > 10
    for idx, expect in ((interior, "room"), (door, "leaf")):
        for eid in np.unique(labels.element_id[idx])[:20]:
            e = elements[int(eid)]
            f = truth.facades[e.facade_id]
            d = f.to_facade(xyz[idx[labels.element_id[idx] == eid]])[:, 2]
            if expect == "leaf":
                assert np.allclose(d, e.depth, atol=5 * PARAMS.mls_range_noise)
            else:
                assert e.has_interior and np.all(d < e.depth + 0.05) and np.all(d > e.room[4] - 0.05)


def test_truth_labels_match_geometry(sim):
    _, truth = sim
    cloud = read_las(truth.als)
    labels = truth.labels("als")
    sigma = PARAMS.als_range_noise
    ground = labels.classification == 2
    dz = cloud.xyz[ground, 2] - truth.terrain_height(cloud.xyz[ground, :2])
    assert np.abs(dz).max() < 6 * sigma
    for b in truth.buildings:
        mine = labels.building_id == b.id
        surface = mine & (labels.is_kind("wall") | labels.is_kind("roof"))
        assert surface.sum() > 50
        dist, _ = MeshDistance(b.mesh().triangles)(cloud.xyz[surface])
        assert dist.max() < 6 * sigma, f"building {b.id}"
    _, xyz, mls = _registered_mls(truth, truth.campaigns[0])
    inside = mls.is_kind("window_interior") | mls.is_kind("door")
    for b in truth.buildings:
        sel = inside & (mls.building_id == b.id)
        if sel.any():
            assert b.mesh().contains(xyz[sel]).mean() > 0.99
    trees = truth.doc["trees"]
    veg = np.flatnonzero(labels.classification == 5)
    pos = np.array([t["position"] for t in trees])
    reach = np.array([t["crown_radius"] for t in trees]) + 0.3
    near = np.hypot(cloud.xyz[veg, 0][:, None] - pos[:, 0], cloud.xyz[veg, 1][:, None] - pos[:, 1]) < reach
    assert near.any(axis=1).all()


def test_facade_frames_follow_the_convention(sim):
    _, truth = sim
    streets = [np.array(s["axis"]) for s in truth.doc["streets"]]
    for b in truth.buildings:
        assert b.polygon.exterior.is_ccw
        for f in b.facades:
            assert abs(np.linalg.norm(f.u) - 1) < 1e-12 and abs(f.u[2]) < 1e-12
            assert np.allclose(f.normal, np.cross(f.u, [0, 0, 1]))
            start, end = b.footprint[f.edge], b.footprint[(f.edge + 1) % len(b.footprint)]
            assert np.allclose(f.origin[:2], start, atol=1e-6)
            assert np.allclose(f.origin[:2] + f.width * f.u[:2], end, atol=1e-6)
            along = start + np.linspace(0, 1, 50)[:, None] * (end - start)
            assert truth.terrain_height(along).min() == pytest.approx(f.origin[2], abs=0.02)
            mid = (start + end) / 2
            assert b.polygon.contains(Point(mid - 0.1 * f.normal[:2]))  # the normal points away from the building
            assert not b.polygon.contains(Point(mid + 0.1 * f.normal[:2]))
            if f.street_facing:
                a, c = streets[0]
                foot = a + np.clip((f.origin[:2] - a) @ (c - a) / ((c - a) @ (c - a)), 0, 1) * (c - a)
                assert (foot - f.origin[:2]) @ f.normal[:2] > 5.0
        assert sum(f.street_facing for f in b.facades) == 1


def test_truth_meshes_are_watertight_in_crs(sim):
    _, truth = sim
    for b in truth.buildings:
        mesh = b.mesh()
        assert mesh.is_watertight and mesh.volume > 50
        assert mesh.vertices.dtype == np.float64 and mesh.vertices[:, 0].min() > 500000
        assert np.allclose(mesh.vertices[:, :2].min(axis=0), b.footprint.min(axis=0), atol=1e-6)
        assert mesh.vertices[:, 2].max() == pytest.approx(b.top_z, abs=1e-6)


# --- acquisition properties ----------------------------------------------------------------------------------------

def test_als_density_strips_and_attributes(sim, city):
    _, truth = sim
    cloud = read_las(truth.als)
    local = city.frame.to_local(cloud.xyz)
    x0, y0, x1, y1 = city.terrain.bounds
    inner = (local[:, 0] > x0 + 10) & (local[:, 0] < x1 - 10) & (local[:, 1] > y0 + 10) & (local[:, 1] < y1 - 10)
    first = inner & (cloud.attrs["return_number"] == 1)
    density = first.sum() / ((x1 - x0 - 20) * (y1 - y0 - 20))
    assert density == pytest.approx(PARAMS.als_density, rel=0.15)
    strips = cloud.attrs["point_source_id"]
    assert len(np.unique(strips)) >= 2
    for s in np.unique(strips):
        assert np.all(np.diff(cloud.attrs["gps_time"][strips == s]) >= 0)
    assert np.abs(cloud.attrs["scan_angle"]).max() <= PARAMS.als_scan_angle + 0.01
    assert cloud.attrs["red"].max() > 255  # 16-bit colour
    assert cloud.crs.to_epsg() == 32632


def test_als_multiple_returns_in_trees(sim):
    _, truth = sim
    cloud = read_las(truth.als)
    labels = truth.labels("als")
    rn, nr = cloud.attrs["return_number"], cloud.attrs["number_of_returns"]
    assert np.all((rn >= 1) & (rn <= nr) & (nr <= 5))
    assert nr.max() >= 3
    multi = nr > 1
    assert labels.classification[multi & (rn == 1)].tolist().count(5) > 0.9 * np.sum(multi & (rn == 1))
    # every pulse (one GPS time) numbers its returns 1..n
    time = cloud.attrs["gps_time"][multi]
    order = np.lexsort((rn[multi], time))
    counts = np.unique(time[order], return_counts=True)[1]
    assert np.array_equal(np.sort(counts), np.sort(nr[multi][rn[multi] == 1]))


def test_als_classification_is_partial(sim):
    _, truth = sim
    cloud = read_las(truth.als)
    labels = truth.labels("als")
    delivered = cloud.attrs["classification"]
    assert np.all(delivered[labels.classification == 2] == 2)
    assert np.all(delivered[labels.classification == 5] == 5)
    wall = labels.is_kind("wall")
    assert np.mean(delivered[wall] == 1) == pytest.approx(PARAMS.als_wall_unlabelled, abs=0.1)
    roof = labels.is_kind("roof")
    assert 0.6 < np.mean(delivered[roof] == 6) < 0.99


def test_mls_campaigns_differ(sim):
    _, truth = sim
    one, two = truth.campaigns
    t1, t2 = read_trajectory(one.trajectory), read_trajectory(two.trajectory)
    lateral = np.abs(one.lane_offset * one.direction - two.lane_offset * two.direction)
    assert lateral > 2.0 and one.direction != two.direction
    yaw_gap = np.angle(np.exp(1j * (np.median(t1.rpy[:, 2]) - np.median(t2.rpy[:, 2]))))
    assert abs(abs(yaw_gap) - np.pi) < 0.2
    cars = [truth.doc["campaigns"][i]["cars"] for i in range(2)]
    assert cars[0] != cars[1]
    v1, v2 = truth.visibility(1), truth.visibility(2)
    street = [f.id for f in truth.facades.values() if f.street_facing]
    assert any(not np.array_equal(v1[i]["seen"], v2[i]["seen"]) for i in street)
    assert not np.allclose(one.translation, two.translation)


def test_mls_density_and_labels(sim):
    _, truth = sim
    campaign = truth.campaigns[0]
    cloud, xyz, labels = _registered_mls(truth, campaign)
    assert 100_000 < len(cloud) < 2_000_000
    assert np.mean(cloud.attrs["classification"] == labels.classification) > 0.97
    assert set(np.unique(cloud.attrs["classification"])) <= {1, 2, 5, 6}
    assert np.all(np.diff(cloud.attrs["gps_time"]) >= 0)
    for f in (f for f in truth.facades.values() if f.street_facing):
        wall = (labels.facade_id == f.id) & labels.is_kind("wall")
        st = f.to_facade(xyz[wall])
        low = (st[:, 1] > 0.5) & (st[:, 1] < 4.5)
        density = low.sum() / (f.width * 4.0 * 0.8)  # about 80 % of that band is wall, not openings
        assert 60 < density < 500


def test_trajectory_interpolation_puts_the_sensor_on_the_street(sim):
    _, truth = sim
    for campaign in truth.campaigns:
        traj = read_trajectory(campaign.trajectory)
        cloud = read_las(campaign.laz)
        pick = np.random.default_rng(2).choice(len(cloud), 2000, replace=False)
        sensor = traj.position_at(cloud.attrs["gps_time"][pick])
        a, c = np.array(truth.doc["streets"][0]["axis"])
        axis = (c - a) / np.linalg.norm(c - a)
        offset = sensor[:, :2] - a
        lateral = np.abs(offset[:, 0] * axis[1] - offset[:, 1] * axis[0])
        assert lateral.max() < 3.0
        height = sensor[:, 2] - truth.terrain_height(sensor[:, :2])
        assert np.allclose(height, PARAMS.mls_sensor_height, atol=0.1)
        ranges = np.linalg.norm(cloud.xyz[pick] - sensor, axis=1)
        assert ranges.max() < PARAMS.mls_max_range + 0.1
        # angles follow the motion: yaw is the heading (CCW from CRS +x), positive pitch is nose down
        step = np.gradient(traj.xyz, axis=0)[5:-5]
        heading = np.arctan2(step[:, 1], step[:, 0])
        assert np.abs(np.angle(np.exp(1j * (heading - traj.rpy[5:-5, 2])))).max() < 1e-3
        climb = np.arctan2(step[:, 2], np.hypot(step[:, 0], step[:, 1]))
        assert np.abs(climb + traj.rpy[5:-5, 1]).max() < 5e-3


def test_windows_have_visibility_per_campaign(sim):
    _, truth = sim
    street_windows = [e for f in truth.facades.values() if f.street_facing for e in f.elements if e.kind == "window"]
    assert street_windows
    for e in street_windows:
        assert set(e.visible_fraction) == {1, 2}
    seen = np.array([e.visible_fraction[1] for e in street_windows])
    assert np.median(seen) > 0.8
    vis = truth.visibility(1)
    cell = truth.visibility_cell
    front = {f.building_id: f for f in truth.facades.values() if f.street_facing}
    for f in truth.facades.values():
        grid = vis[f.id]["seen"]
        assert grid.shape == (int(np.ceil(f.t_top / cell)), int(np.ceil(f.width / cell)))
        if f.normal @ front[f.building_id].normal < -0.9:
            assert not grid.any()  # a back wall cannot be seen from the street


# --- files ---------------------------------------------------------------------------------------------------------

def test_footprints_reproject_to_the_crs_within_a_millimetre(sim):
    result, truth = sim
    doc = json.loads(result.footprints.read_text())
    assert "crs" not in doc  # RFC 7946: WGS84 lon/lat
    fps = read_footprints(result.footprints, crs=CRS.from_epsg(32632))
    assert len(fps) == len(truth.buildings)
    by_id = {int(p["id"]): (poly, p) for poly, p in zip(fps.polygons, fps.properties)}
    for b in truth.buildings:
        poly, props = by_id[b.id]
        ring = np.asarray(poly.exterior.coords)[:-1]
        assert np.abs(ring - b.footprint).max() < 1e-3
        assert props["status"] == b.status
    statuses = [p["status"] for p in fps.properties]
    assert statuses.count("under construction") == 1
    assert all(6.0 <= p["height"] <= 30.0 for p in fps.properties)


def test_same_seed_gives_identical_bytes_and_another_seed_differs(sim, tmp_path):
    result, _ = sim
    again = simulate(tmp_path / "again", PARAMS)
    first = sorted(p.relative_to(result.out_dir) for p in result.out_dir.rglob("*") if p.is_file())
    second = sorted(p.relative_to(again.out_dir) for p in again.out_dir.rglob("*") if p.is_file())
    assert first == second
    for rel in first:
        assert (result.out_dir / rel).read_bytes() == (again.out_dir / rel).read_bytes(), rel
    other = simulate(tmp_path / "again", SimParams(seed=SEED + 1, buildings=2, campaigns=1))
    assert other.als.read_bytes() != result.als.read_bytes()
    assert other.footprints.read_text() != result.footprints.read_text()
    assert not (other.out_dir / "mls_2.laz").exists()  # outputs of the earlier, larger run are removed
    assert not (other.out_dir / "truth" / "visibility_2.npz").exists()


def test_default_city_has_the_variety_the_stages_need():
    city = build_city(SimParams(seed=3))
    existing = [b for b in city.buildings if b.status == "existing"]
    assert len(existing) == 8 and len(city.buildings) == 9
    assert {b.shape for b in existing} == {"rectangle", "L"}
    roofs = {b.roof_type for s in range(4) for b in build_city(SimParams(seed=s)).buildings}
    assert {"flat", "gabled", "hipped"} <= roofs
    elements = [e for f in city.facades for e in f.elements]
    kinds = {e.kind for e in elements}
    assert kinds == {"window", "door", "structure"}
    windows = [e for e in elements if e.kind == "window"]
    assert any(e.has_interior for e in windows) and not all(e.has_interior for e in windows)
    assert all(-0.3 <= e.depth <= -0.15 for e in elements if e.kind in ("window", "door"))
    assert all(0.1 <= e.depth <= 0.6 for e in elements if e.kind == "structure")
    assert all(6.0 <= b.height <= 30.0 for b in existing)
    angle = city.frame.rotation_deg % 90
    assert 5 < angle < 85  # façades are not aligned with the CRS axes
    assert len(city.trees) > 5


def test_two_streets_for_many_buildings():
    city = build_city(SimParams(seed=1, buildings=12))
    assert len(city.streets) == 2
    polys = [b.polygon for b in city.buildings]
    assert not any(p.intersects(q) for i, p in enumerate(polys) for q in polys[i + 1:])


def test_params_are_validated():
    with pytest.raises(ConfigError):
        SimParams(buildings=0)
    with pytest.raises(ConfigError):
        SimParams(mls_angular_step=0.0)


# --- CLI -----------------------------------------------------------------------------------------------------------

def test_cli_simulate(tmp_path: Path):
    runner = CliRunner()
    out = tmp_path / "cli"
    result = runner.invoke(app, ["simulate", str(out), "--seed", "5", "--buildings", "1", "--campaigns", "1"])
    assert result.exit_code == 0, result.output
    for name in ("als.laz", "mls_1.laz", "trajectory_1.csv", "footprints.geojson", "truth/scene.json",
                 "truth/als_labels.npz", "truth/mls_1_labels.npz", "truth/visibility_1.npz",
                 "truth/meshes/building_1.ply", "truth/meshes/building_2.ply"):
        assert (out / name).is_file(), name
    assert "mls_1.laz" in result.output
    assert read_trajectory(out / "trajectory_1.csv").rpy is not None
    bad = runner.invoke(app, ["simulate", str(tmp_path / "bad"), "--buildings", "0"])
    assert bad.exit_code == 2
    assert "buildings must be between" in bad.output and "Traceback" not in bad.output


# ---------------------------------------------------------------- ray engines (embreex is x86-64 only)
def test_trimesh_ray_tracer_gives_the_same_returns_as_embree() -> None:
    pytest.importorskip("embreex", reason="the comparison needs Embree (x86-64)")
    from lidarmap.sim.raycast import Tracer

    scene = build_city(SimParams(seed=3, buildings=2, campaigns=0)).scene([])
    corners = scene.triangles.reshape(-1, 3)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    rng = np.random.default_rng(11)
    n = 800
    origins = np.column_stack([rng.uniform(lo[0], hi[0], n), rng.uniform(lo[1], hi[1], n), np.full(n, hi[2] + 50)])
    dirs = np.column_stack([rng.normal(0, 0.3, n), rng.normal(0, 0.3, n), -np.ones(n)])
    fast, slow = (Tracer(scene, engine=engine).trace(origins, dirs, max_range=500) for engine in ("embree", "triangle"))
    assert len(fast.ray) > n // 2 and np.any(fast.number_of_returns > 1)  # trees give multiple returns
    assert np.array_equal(fast.ray, slow.ray) and np.array_equal(fast.tri, slow.tri)
    assert np.array_equal(fast.range, slow.range)  # ranges come from the triangle's plane in float64 either way
    assert np.array_equal(fast.stop_tri, slow.stop_tri)


def test_ray_engine_falls_back_without_embree(monkeypatch: pytest.MonkeyPatch) -> None:
    from lidarmap.sim import raycast

    monkeypatch.setattr(raycast, "_embree_available", lambda: False)
    monkeypatch.delenv(raycast.ENGINE_ENV, raising=False)
    assert raycast.ray_engine() == "triangle"
    monkeypatch.setenv(raycast.ENGINE_ENV, "embree")
    with pytest.raises(ConfigError, match="LIDARMAP_RAY_ENGINE=embree but embreex is not installed"):
        raycast.ray_engine()
    monkeypatch.setenv(raycast.ENGINE_ENV, "optix")
    with pytest.raises(ConfigError, match=r"LIDARMAP_RAY_ENGINE='optix': use one of auto, embree, triangle"):
        raycast.ray_engine()
    monkeypatch.setenv(raycast.ENGINE_ENV, "triangle")
    box = build_city(SimParams(seed=3, buildings=2, campaigns=0)).scene([])
    tracer = raycast.Tracer(box)
    assert tracer.engine == "triangle"
    tri, rng = tracer.first_hit(np.array([[0.0, 0.0, 500.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert tri[0] >= 0 and 380 < rng[0] < 420  # the ground (z ~ 84-112) seen from z = 500


# --- hard family ---------------------------------------------------------------------------------------------------

HARD = SimParams(seed=DEV_SEEDS[1], family="hard", buildings=2, campaigns=1)


@pytest.fixture(scope="module")
def hard(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("hard") / "scene"
    return simulate(out, HARD), load_truth(out)


def _setbacks_sills_glass(seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    city = build_hard_city(SimParams(seed=seed, family="hard"))
    houses = [b for b in city.buildings if b.status == "existing"]
    setbacks = np.array([np.min(np.abs(b.ring[:, 1] - city.streets[0].y)) - BUILDING_LINE for b in houses])
    sills = np.array([e.t0 - (b.floor_z - f.origin[2]) for b in houses for f in b.facades for e in f.elements
                      if e.kind == "window" and e.subtype == "window" and e.t0 < b.floor_z - f.origin[2] + 2.0])
    windows = [e for b in houses for f in b.facades for e in f.elements if e.kind == "window"]
    return setbacks, sills, float(np.mean([e.glazing == "glass" for e in windows]))


def test_hard_family_is_randomised_across_seeds():
    stats = [_setbacks_sills_glass(seed) for seed in DEV_SEEDS]
    for setbacks, sills, glass in stats:
        assert setbacks.min() >= -1e-9 and setbacks.max() <= 5.0 + 1e-9
        assert len(sills) > 3 and sills.min() >= 0.1 - 1e-9 and sills.max() <= 1.2 + 1e-9
        assert 0.2 < glass < 0.8
    assert len({round(float(np.mean(s)), 2) for s, _, _ in stats}) == len(stats)  # set-backs differ per seed
    assert len({round(float(np.mean(s)), 2) for _, s, _ in stats}) == len(stats)  # and so do sills
    assert len({round(g, 3) for _, _, g in stats}) == len(stats)  # and the share of glazed windows
    assert np.ptp(np.concatenate([s for s, _, _ in stats])) > 2.5


def test_hard_family_content(hard):
    _, truth = hard
    elements = list(truth.elements.values())
    glazings = {e.subtype: set() for e in elements}
    for e in truth.doc["buildings"]:
        for f in e["facades"]:
            for el in f["elements"]:
                glazings[el["subtype"]].add(el.get("glazing", ""))
    assert {"glass", "curtain", "open"} <= glazings["window"]
    fractions = [el["return_fraction"] for b in truth.doc["buildings"] for f in b["facades"]
                 for el in f["elements"] if el.get("glazing") == "glass"]
    assert fractions and min(fractions) >= HARD.glass_return_min and max(fractions) <= HARD.glass_return_max
    blank_sides = [f for f in truth.facades.values() if not f.street_facing and not f.elements]
    assert blank_sides  # some side walls have no opening at all
    labels = truth.labels("mls_1")
    cloud = read_las(truth.campaigns[0].laz)
    glass = labels.is_kind("glass")
    assert glass.sum() > 100  # panes return part of the pulses ...
    wall = labels.is_kind("wall")
    assert np.median(cloud.attrs["intensity"][glass]) < 0.3 * np.median(cloud.attrs["intensity"][wall])  # weakly


def test_a_window_behind_a_balcony_parapet_is_not_seen_but_the_parapet_is():
    """A line of sight ending on a balcony's parapet sees the parapet (``seen``), not the window behind it
    (``wall_seen``, which the openings are scored by); above the parapet both see the wall."""
    f = Facade(id=1, building_id=1, origin=np.zeros(3), u=np.array([1.0, 0, 0]), width=4.0, t_bottom=0.0,
               t_eave=6.0, t_top=6.0, street_facing=True)
    soup = Soup()
    soup.add(f.to_local(quads(np.array([[[0, 0, 0], [4, 0, 0], [4, 6, 0], [0, 6, 0]]], float))),
             Labels(classification=6, kind=KIND["wall"], facade_id=f.id))
    parapet, _ = boxes(np.array([[1.0, 2.85, 0.0]]), np.array([[3.0, 4.0, 1.0]]))  # s, t, d: 1 m out, 1.15 m high
    soup.add(f.to_local(parapet), Labels(classification=6, kind=KIND["structure"], facade_id=f.id))
    s = np.linspace(-2.0, 6.0, 161)
    sensors = f.to_local(np.column_stack([s, np.full_like(s, 2.5), np.full_like(s, 8.0)]))  # 8 m out, 2.5 m up
    seen, wall_seen = seen_grid(Tracer(soup.build(), seed=0), f, sensors, np.tile(f.u, (len(s), 1)), 0.1, 50.0)
    window = (1.3, 2.7, 3.0, 4.0)  # wholly behind the parapet seen from 2.5 m
    assert visible_fraction(seen, window, 0.1) == 1.0 and visible_fraction(wall_seen, window, 0.1) == 0.0
    above = (1.3, 2.7, 4.8, 5.8)  # the sight lines pass over the parapet's top (at most 4.0 + 0.3 m there)
    assert visible_fraction(seen, above, 0.1) == 1.0 and visible_fraction(wall_seen, above, 0.1) == 1.0
    assert np.array_equal(wall_seen, seen & wall_seen) and wall_seen.sum() < seen.sum()


def test_glass_returns_its_fraction_of_pulses():
    """A pane returning 30 % of pulses in front of an opaque wall: 30 % glass returns, the rest from the wall."""
    soup = Soup()
    pane = quads(np.array([[[0, -1, -1], [0, 1, -1], [0, 1, 1], [0, -1, 1]]], float))
    soup.add(pane, Labels(classification=6, kind=KIND["glass"], behaviour=GLASS, return_fraction=0.3))
    soup.add(pane + [2.0, 0, 0], Labels(classification=6, kind=KIND["wall"]))
    scene = soup.build()
    n = 20000
    dirs = np.column_stack([np.ones(n), np.random.default_rng(0).uniform(-0.12, 0.12, (n, 2))])
    returns = Tracer(scene, seed=5).trace(np.tile([-5.0, 0, 0], (n, 1)), dirs, max_range=50.0)
    assert len(returns.ray) == n and len(np.unique(returns.ray)) == n  # one return per pulse
    share = np.mean(scene.kind[returns.tri] == KIND["glass"])
    assert abs(share - 0.3) < 0.015
    again = Tracer(scene, seed=5).trace(np.tile([-5.0, 0, 0], (n, 1)), dirs, max_range=50.0)
    assert np.array_equal(again.tri, returns.tri)  # the draws come from the seed


def test_hard_openings_are_scored_by_what_the_parapets_leave_seen(hard):
    """Windows and doors count as seen by ``wall_seen``, structures by ``seen`` (their own surfaces)."""
    from lidarmap.facade.eval import union_visibility

    _, truth = hard
    vis, cell = truth.visibility(1), truth.visibility_cell
    hidden = 0
    for f in truth.facades.values():
        for e in f.elements:
            grid = vis[f.id]["seen" if e.kind == "structure" else "wall_seen"]
            assert e.visible_fraction[1] == pytest.approx(visible_fraction(grid, e.rect, cell))
            behind = visible_fraction(vis[f.id]["seen"], e.rect, cell) > e.visible_fraction[1]
            hidden += e.kind != "structure" and behind
    assert hidden > 0  # some windows of this scene stand behind a balcony's parapet
    new, old = union_visibility(truth, [1]), union_visibility(truth, [1], parapets_hide=False)
    assert all(new[i] <= old[i] for i in new) and sum(new.values()) < sum(old.values())


def test_hard_gps_drift_is_bounded_and_smooth(hard):
    _, truth = hard
    campaign = truth.campaigns[0]
    doc = truth.doc["campaigns"][0]
    samples = np.array(doc["gps_drift"]["samples"])
    horizontal = np.linalg.norm(samples[:, 1:3], axis=1)
    assert 0.5 * HARD.gps_drift_horizontal - 1e-9 <= horizontal.max() <= HARD.gps_drift_horizontal + 1e-9
    assert np.abs(samples[:, 3]).max() <= HARD.gps_drift_vertical + 1e-9
    assert np.abs(np.diff(samples[:, 1:], axis=0)).max() < 0.05  # smooth: < 5 cm per second
    traj = read_trajectory(campaign.trajectory)
    drift = np.column_stack([np.interp(traj.time, samples[:, 0], samples[:, k]) for k in (1, 2, 3)])
    height = doc["setup"]["sensor_height"]
    undone = campaign.register(traj.xyz - drift)
    assert np.abs(undone[:, 2] - truth.terrain_height(undone[:, :2]) - height).max() < 1e-6
    kept = campaign.register(traj.xyz)  # the delivered trajectory is off by the drift
    assert np.abs(kept[:, 2] - truth.terrain_height(kept[:, :2]) - height).max() > 0.02


def test_hard_outputs_have_the_standard_formats(hard, sim):
    result, truth = hard
    std_cloud = read_las(sim[1].campaigns[0].laz)
    cloud = read_las(truth.campaigns[0].laz)
    assert set(cloud.attrs) == set(std_cloud.attrs) and cloud.crs == std_cloud.crs
    assert np.all(np.diff(cloud.attrs["gps_time"]) >= 0)
    traj = read_trajectory(truth.campaigns[0].trajectory)
    assert traj.rpy is not None and traj.time[0] <= cloud.attrs["gps_time"].min()
    fps = read_footprints(result.footprints, crs=CRS.from_epsg(32632))
    assert len(fps) == len(truth.buildings)
    assert {e.kind for e in truth.elements.values()} == {"window", "door", "structure"}
    assert truth.doc["family"] == "hard" and truth.doc["params"]["family"] == "hard"


def test_hard_family_is_deterministic(hard, tmp_path):
    result, _ = hard
    again = simulate(tmp_path / "again", HARD)
    for path in (result.mls[0], result.trajectories[0], result.truth_dir / "scene.json",
                 result.truth_dir / "mls_1_labels.npz", result.truth_dir / "visibility_1.npz"):
        rel = path.relative_to(result.out_dir)
        assert path.read_bytes() == (again.out_dir / rel).read_bytes(), rel


def test_tests_never_use_the_evaluation_seeds():
    from lidarmap.sim.independent import EVAL_SEEDS as INDEPENDENT_EVAL_SEEDS

    for seeds in (EVAL_SEEDS, INDEPENDENT_EVAL_SEEDS):  # our hard family's and the independent generator's
        reserved = {str(s) for s in seeds}
        naming_the_range = re.compile(rf"\b{seeds[0]}\s*[-–]\s*{seeds[-1]}\b")  # "reserved: 70..-70.."
        for path in Path(__file__).parent.glob("*.py"):
            text = naming_the_range.sub("", path.read_text(encoding="utf-8"))
            assert not set(re.findall(r"\b\d{4}\b", text)) & reserved, path.name


def test_cli_simulate_rejects_an_unknown_family(tmp_path: Path):
    bad = CliRunner().invoke(app, ["simulate", str(tmp_path / "bad"), "--family", "easy"])
    assert bad.exit_code == 2
    assert "family must be one of standard, hard" in bad.output and "Traceback" not in bad.output
    assert not (tmp_path / "bad" / "als.laz").exists()


def test_hard_campaigns_differ_in_lane_speed_height_rate_and_scanner():
    setups = [campaign_setup(SimParams(seed=seed, family="hard"), i) for seed in DEV_SEEDS for i in (1, 2, 3)]
    for s in setups:
        assert 0.6 <= abs(s.lane_offset) <= 3.2 and 4.0 <= s.params.mls_speed <= 10.0
        assert 1.9 <= s.params.mls_sensor_height <= 3.4 and 60 <= s.params.mls_rate <= 140
        yaws = np.abs(s.yaws)
        assert (len(yaws) == 1 and 5 <= yaws[0] <= 20) or (len(yaws) == 2 and s.yaws[0] == -s.yaws[1]
                                                            and 30 <= yaws[0] <= 45)
    assert {len(s.yaws) for s in setups} == {1, 2}  # both scanner set-ups occur
    for name in ("mls_speed", "mls_sensor_height", "mls_rate"):
        assert len({getattr(s.params, name) for s in setups}) >= len(setups) - 2  # rates are whole Hz
    assert len({np.sign(s.lane_offset) for s in setups}) == 2


def test_pulse_spacing_on_a_wall_matches_neighbouring_pulses():
    """The observability rule's in-profile spacing equals the distance between two traced neighbouring pulses."""
    rng = np.random.default_rng(3)
    n = np.array([1.0, 0.0, 0.0])  # wall x = 0, seen from x < 0
    for _ in range(20):
        yaw, elev, step = rng.uniform(-1.2, 1.2), rng.uniform(-0.6, 0.6), np.radians(0.4)
        h = np.array([np.sin(yaw), np.cos(yaw), 0.0])  # a vertical profile plane
        r = np.cos(elev) * np.array([np.cos(yaw), -np.sin(yaw), 0.0]) + np.sin(elev) * np.array([0.0, 0.0, 1.0])
        origin = np.array([-5.0, 0.0, 0.0])
        hit = origin + (-origin[0] / r[0]) * r
        c, s = np.cos(step), np.sin(step)
        r2 = r * c + np.cross(h, r) * s  # the next pulse of the profile
        hit2 = origin + (-origin[0] / r2[0]) * r2
        dist = np.linalg.norm(hit - origin)
        expected = pulse_spacing(r[None], h[None], n, np.array([dist]), step)[0]
        assert np.linalg.norm(hit2 - hit) == pytest.approx(expected, rel=0.02)
