"""Planar flattening (lidarmap.aerial.flatten): plane detection, regularisation, flattening, errors.

Fixtures are analytic (a noisy tilted plane with a cloud of clutter above it; a gabled house with a chimney, in CRS
coordinates, roofs scanned densely and walls in sparse vertical scan-line stripes as airborne LiDAR sees them) plus one
small simulated city whose truth solids give the true surfaces.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lidarmap.aerial.flatten import (
    FlattenParams,
    Plane,
    detect_planes,
    flatten,
    flatten_points,
    main_axis_deg,
    regularise_planes,
)
from lidarmap.config import resolve
from lidarmap.errors import ConfigError, InputError

OFFSET = np.array([500321.0, 5800456.0, 60.0])  # CRS-sized coordinates
ANGLE = 23.0  # the house's axes against the CRS axes, degrees
STRIPE_GAP, STRIPE_STEP = 3.5, 1.3  # ALS on walls: vertical scan-line stripes metres apart, points along them


def _rot(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def noisy_plane_with_clutter(seed: int = 0):
    """A 30 m x 30 m plane z = 0.1 x + 0.05 y at 20 points/m² with 2.5 cm noise, and 600 points scattered in a
    ball of radius 2 m whose centre is 4 m above it (a crown, clutter). Returns points, true normal/offset and the
    clutter mask."""
    rng = np.random.default_rng(seed)
    n = 30 * 30 * 20
    xy = rng.uniform(0, 30, (n, 2))
    plane = np.column_stack([xy, 0.1 * xy[:, 0] + 0.05 * xy[:, 1] + rng.normal(0, 0.025, n)])
    u = rng.normal(size=(600, 3))
    ball = u / np.linalg.norm(u, axis=1, keepdims=True) * 2.0 * rng.uniform(0, 1, (600, 1)) ** (1 / 3)
    centre = np.array([15.0, 15.0, 0.1 * 15 + 0.05 * 15 + 4.0])
    xyz = np.vstack([plane, ball + centre]) + OFFSET
    normal = np.array([-0.1, -0.05, 1.0]) / np.linalg.norm([-0.1, -0.05, 1.0])
    offset = -float(normal @ OFFSET)
    clutter = np.r_[np.zeros(n, bool), np.ones(600, bool)]
    return xyz, normal, offset, clutter


def gabled_house(seed: int = 0, lean_deg: float = 0.0, stripes: bool = True, eave: float = 12.0):
    """A 14 m x 9 m house (eaves at ``eave``, ridge along local x 3.375 m higher: 36.9° slopes) with a sparsely hit
    1 m x 1 m chimney rising 1.5 m through the roof, rotated by ANGLE and moved to CRS coordinates.

    Roofs: 20 points/m² (horizontal), 2.5 cm vertical noise. Walls: ``stripes`` -> vertical scan-line stripes 1.5 m
    apart with a point every 0.4 m, as ALS sees walls (else 8 points/m² uniform), 1 cm noise along the normal.
    ``lean_deg`` tilts every wall about its foot. Returns points, the true surface of each point (0-1 roofs, 2-5
    walls, -1 chimney) and the true planes (normals (6, 3), offsets (6,)) in CRS coordinates.
    """
    rng = np.random.default_rng(seed)
    length, width, slope = 14.0, 9.0, 0.75
    parts, labels = [], []
    # roof facets (y < 4.5 rises, y > 4.5 falls), chimney footprint [9, 10] x [2, 3] cut out
    n = int(length * width * 20)
    xy = rng.uniform([0, 0], [length, width], (n, 2))
    xy = xy[~((xy[:, 0] >= 9) & (xy[:, 0] <= 10) & (xy[:, 1] >= 2) & (xy[:, 1] <= 3))]
    z = eave + slope * np.minimum(xy[:, 1], width - xy[:, 1]) + rng.normal(0, 0.025, len(xy))
    parts.append(np.column_stack([xy, z]))
    labels.append(np.where(xy[:, 1] < width / 2, 0, 1))
    # walls: (start, direction, outward normal, length)
    walls = [((0, 0), (1, 0), (0, -1), length), ((length, width), (-1, 0), (0, 1), length),
             ((length, 0), (0, 1), (1, 0), width), ((0, width), (0, -1), (-1, 0), width)]
    lean = math.tan(math.radians(lean_deg))
    for w, (start, direction, outward, wl) in enumerate(walls):
        start, direction, outward = map(np.asarray, (start, direction, outward))
        if stripes:
            at, along = np.arange(0.4, wl, STRIPE_GAP), np.arange(0.2, 16.0, STRIPE_STEP)
            s = np.repeat(at, len(along)) + rng.normal(0, 0.03, len(at) * len(along))
            t = np.tile(along, len(at))
        else:
            m = int(wl * (eave + 4) * 8)
            s, t = rng.uniform(0, wl, m), rng.uniform(0, eave + 4, m)
        s = np.clip(s, 0.05, wl - 0.05)
        p2 = start + s[:, None] * direction
        top = eave if w < 2 else eave + slope * np.minimum(p2[:, 1], width - p2[:, 1])  # gable ends
        keep = t < top - 0.05
        p2, t = p2[keep], t[keep]
        d = lean * t + rng.normal(0, 0.01, len(t))
        parts.append(np.column_stack([p2 + d[:, None] * outward, t]))
        labels.append(np.full(len(t), 2 + w))
    # chimney: four faces and the top, about 12 points each (fewer than min_points: not planes worth keeping)
    rc = rng.uniform(0, 1, (60, 2))
    zc = rng.uniform(eave + slope * 2, eave + slope * 3 + 1.5, 60)
    face = rng.integers(0, 5, 60)
    cx = np.where(face == 0, 9.0, np.where(face == 1, 10.0, 9 + rc[:, 0]))
    cy = np.where(face == 2, 2.0, np.where(face == 3, 3.0, 2 + rc[:, 1]))
    cz = np.where(face == 4, eave + slope * 3 + 1.5, zc)
    chimney = np.column_stack([cx, cy, cz])
    above = chimney[:, 2] > eave + slope * np.minimum(chimney[:, 1], width - chimney[:, 1]) + 0.2
    parts.append(chimney[above])
    labels.append(np.full(int(above.sum()), -1))
    local = np.vstack(parts)
    rot = _rot(ANGLE)
    xyz = local @ rot.T + OFFSET
    # true planes in local coordinates, then moved like the points
    c = math.cos(math.atan(slope))
    local_planes = [(np.array([0, -slope, 1]) * c, -eave * c),
                    (np.array([0, slope, 1]) * c, -(eave + slope * width) * c)]
    for start, direction, outward, _ in walls:
        nrm = np.array([outward[0], outward[1], -lean]) / math.hypot(1.0, lean)
        local_planes.append((nrm, -float(nrm[:2] @ np.asarray(start, float))))
    normals = np.array([rot @ n for n, _ in local_planes])
    offsets = np.array([d - float(rot @ n @ OFFSET) for n, d in local_planes])
    return xyz, np.concatenate(labels), normals, offsets


def _match(planes: list[Plane], normals: np.ndarray, offsets: np.ndarray, xyz: np.ndarray) -> list[int]:
    """For every true plane, the index of the detected plane within 2° and 5 cm (at the inliers), else -1."""
    found = []
    for n, d in zip(normals, offsets):
        hit = -1
        for i, p in enumerate(planes):
            angle = math.degrees(math.acos(min(1.0, abs(float(p.normal @ n)))))
            off = np.abs(xyz[p.inliers] @ n + d).mean()
            if angle < 2.0 and off < 0.05:
                hit = i
        found.append(hit)
    return found


def _true_distance(xyz, labels, normals, offsets) -> np.ndarray:
    use = labels >= 0
    centre = xyz.mean(axis=0)  # subtract before the products: CRS coordinates
    lab = labels[use]
    return np.abs(np.einsum("ni,ni->n", normals[lab], xyz[use] - centre) + (offsets + normals @ centre)[lab])


# ----------------------------------------------------------------------------------------------------------------------
# The noisy plane


@pytest.mark.parametrize("method", ["region", "paper"])
def test_flattening_reduces_plane_rms_and_leaves_clutter_alone(method):
    xyz, normal, offset, clutter = noisy_plane_with_clutter()
    result = flatten_points(xyz, FlattenParams(method=method), seed=1)
    centre = xyz.mean(axis=0)
    before = (xyz[~clutter] - centre) @ normal + offset + normal @ centre
    after = (result.xyz[~clutter] - centre) @ normal + offset + normal @ centre
    rms_before, rms_after = np.sqrt(np.mean(before ** 2)), np.sqrt(np.mean(after ** 2))
    assert 0.023 < rms_before < 0.027
    # points that were not flattened keep their noise; flattened ones sit on the fitted plane
    assert rms_after < 0.15 * rms_before
    assert np.mean(result.plane_id[~clutter] >= 0) > 0.99
    assert np.all(result.moved[clutter] == 0) and np.all(result.plane_id[clutter] == -1)
    assert np.array_equal(result.xyz[clutter], xyz[clutter])
    # points move along the plane's normal by exactly their distance to it, never beyond ``distance``
    planes = result.planes
    moved = result.plane_id >= 0
    assert np.all(result.moved[moved] <= FlattenParams().distance + 1e-9)
    step = np.linalg.norm(result.xyz - xyz, axis=1)
    assert np.allclose(step, result.moved, atol=1e-9)
    big = planes[0]
    assert math.degrees(math.acos(abs(float(big.normal @ normal)))) < 0.1
    assert big.normal[2] > 0  # roofs point up


def test_same_seed_same_output_and_crs_offset_changes_nothing():
    xyz, *_ = gabled_house()
    for method in ("region", "paper"):
        params = FlattenParams(method=method)
        a, b = flatten_points(xyz, params, seed=3), flatten_points(xyz, params, seed=3)
        assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.plane_id, b.plane_id)
    local = xyz - OFFSET
    r_crs, r_local = flatten_points(xyz, seed=0), flatten_points(local, seed=0)
    assert np.array_equal(r_crs.plane_id, r_local.plane_id)
    assert np.allclose(r_crs.moved, r_local.moved, atol=1e-6)
    assert np.allclose(r_crs.xyz - OFFSET, r_local.xyz, atol=1e-6)
    for p, q in zip(r_crs.planes, r_local.planes):
        assert np.allclose(p.normal, q.normal, atol=1e-9)
        assert abs((p.offset + float(p.normal @ OFFSET)) - q.offset) < 1e-6


# ----------------------------------------------------------------------------------------------------------------------
# The house


def test_region_growing_finds_roofs_and_striped_walls_and_flattens_onto_them():
    xyz, labels, normals, offsets = gabled_house()
    params = FlattenParams(regularise=False)
    planes = detect_planes(xyz, params)
    assert -1 not in _match(planes, normals, offsets, xyz)
    assert len(planes) == 6  # two roof slopes, four walls; the chimney's faces are too small (< min_points)
    # inliers are disjoint and lie within ``distance`` of their plane
    everyone = np.concatenate([p.inliers for p in planes])
    assert len(np.unique(everyone)) == len(everyone)
    for p in planes:
        assert np.all(np.abs(p.distance(xyz[p.inliers])) <= params.distance + 1e-9)
    # walls are found only by the leftover RANSAC: their scan-line stripes give unreliable k-NN normals
    no_leftover = detect_planes(xyz, dataclasses.replace(params, leftover_walls=False))
    assert sum(m >= 0 for m in _match(no_leftover, normals, offsets, xyz)[2:]) < 4
    result = flatten(xyz, planes, params)
    before = _true_distance(xyz, labels, normals, offsets)
    after = _true_distance(result.xyz, labels, normals, offsets)
    assert np.sqrt(np.mean(after ** 2)) < 0.3 * np.sqrt(np.mean(before ** 2))
    # the chimney (0.2 m and more above the roof) stays where it was
    assert np.all(result.moved[labels == -1] == 0)


def test_paper_algorithm_finds_the_roof_slopes():
    xyz, labels, normals, offsets = gabled_house(stripes=False)
    planes = detect_planes(xyz, FlattenParams(method="paper", regularise=False), seed=2)
    found = _match(planes, normals, offsets, xyz)
    assert found[0] >= 0 and found[1] >= 0
    # without merging, Algorithm 2 cuts a roof slope into several discs around its seeds
    literal = detect_planes(xyz, FlattenParams(method="paper", merge=False), seed=2)
    assert len(literal) > len(planes)


def test_regularisation_makes_leaning_walls_vertical_and_snaps_them_to_the_axes():
    xyz, labels, normals, offsets = gabled_house(lean_deg=0.4, stripes=False)
    params = FlattenParams()
    planes = detect_planes(xyz, dataclasses.replace(params, regularise=False))
    walls = [p for p in planes if p.tilt_deg > 80]
    assert len(walls) == 4 and all(abs(p.normal[2]) > math.sin(math.radians(0.2)) for p in walls)
    assert abs(main_axis_deg(planes) - ANGLE) < 0.2
    snapped = regularise_planes(planes, xyz, params)
    axis = main_axis_deg(snapped)
    for p in snapped:
        azimuth = math.degrees(math.atan2(p.normal[1], p.normal[0]))
        if p.tilt_deg > 80:
            assert p.normal[2] == 0.0
        assert abs((azimuth - axis + 45) % 90 - 45) < 1e-9  # exactly on the main axes
        assert np.all(np.abs(p.distance(xyz[p.inliers])) <= params.distance + 1e-9)
        assert abs(np.linalg.norm(p.normal) - 1) < 1e-12
    # a near-flat roof snaps to horizontal; a plane tilted beyond the tolerance keeps its normal, and so does one
    # within the tolerance whose snap would cost more than snap_max_loss of its inliers (1.5° over 10 m: 26 cm)
    xy = np.random.default_rng(0).uniform(0, 10, (400, 2))
    for tilt, snapped in ((0.3, True), (10.0, False), (1.5, False)):
        cloud = np.column_stack([xy, xy[:, 0] * math.tan(math.radians(tilt))])
        plane = detect_planes(cloud, dataclasses.replace(params, regularise=False))[0]
        out = regularise_planes([plane], cloud, params)[0]
        assert (out.normal[2] == 1.0) == snapped
        assert snapped or np.array_equal(out.normal, plane.normal)


def test_points_on_two_planes_go_to_the_closest_and_small_planes_stay_put():
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 5, (100, 2)), rng.normal(0, 0.01, 100)])
    xyz[:10, 2] = 0.045  # near z = 0.05 more than near z = 0
    both = np.arange(100)
    low = Plane(np.array([0.0, 0.0, 1.0]), 0.0, both, 0.0)
    high = Plane(np.array([0.0, 0.0, 1.0]), -0.05, both, 0.0)
    tiny = Plane(np.array([1.0, 0.0, 0.0]), -1.0, np.arange(20, 30), 0.0)  # 10 inliers < min_points
    result = flatten(xyz, [low, high, tiny], FlattenParams(min_points=30))
    assert np.all(result.plane_id[:10] == 1) and np.allclose(result.xyz[:10, 2], 0.05)
    closer_to_low = np.abs(xyz[:, 2]) < np.abs(xyz[:, 2] - 0.05)
    assert np.array_equal(result.plane_id, np.where(closer_to_low, 0, 1))
    assert np.allclose(result.moved, np.minimum(np.abs(xyz[:, 2]), np.abs(xyz[:, 2] - 0.05)))
    assert not np.any(result.plane_id == 2)
    assert np.array_equal(result.xyz[:, :2], xyz[:, :2])


# ----------------------------------------------------------------------------------------------------------------------
# Inputs, parameters, progress


def test_errors_and_degenerate_inputs():
    with pytest.raises(InputError, match="^NaN or infinite point coordinates$"):
        detect_planes(np.array([[0.0, 0.0, np.nan]] * 50))
    with pytest.raises(InputError, match=r"^expected an \(N, 3\) array of point coordinates, got shape \(5, 2\)$"):
        flatten_points(np.zeros((5, 2)))
    with pytest.raises(InputError, match="plane inlier indices out of range for 3 points"):
        flatten(np.zeros((3, 3)), [Plane(np.array([0, 0, 1.0]), 0.0, np.arange(40), 0.0)], FlattenParams())
    with pytest.raises(ValueError, match="method must be one of region, paper, not 'ransac'"):
        FlattenParams(method="ransac")
    with pytest.raises(ConfigError, match=r"\[flatten\]: min_points must be >= 3"):
        resolve(FlattenParams, {"flatten": {"min_points": 2}})
    with pytest.raises(ConfigError, match="unknown option 'distanse' in \\[flatten\\]"):
        resolve(FlattenParams, {"flatten": {"distanse": 0.1}})
    assert resolve(FlattenParams, {"flatten": {"method": "paper", "distance": 0.05}}).distance == 0.05
    few = np.random.default_rng(0).uniform(0, 1, (10, 3))
    result = flatten_points(few)
    assert result.planes == [] and np.all(result.plane_id == -1) and np.array_equal(result.xyz, few)
    assert detect_planes(np.zeros((0, 3))) == []


def test_progress_and_timings_are_reported():
    xyz, *_ = gabled_house()
    calls: list[tuple[int, int]] = []
    timings: dict = {}
    flatten_points(xyz, progress=lambda done, total: calls.append((done, total)), timings=timings)
    assert calls[-1][0] == calls[-1][1] and [c[0] for c in calls] == sorted(c[0] for c in calls)
    assert {"detect_s", "normals_s", "regularise_s", "flatten_s"} <= set(timings)
    assert timings["samples"] <= len(xyz)


def test_large_clouds_are_thinned_for_detection_but_every_point_is_assigned():
    xyz, normal, offset, clutter = noisy_plane_with_clutter()
    params = FlattenParams(detect_max_points=2000)  # force the voxel to grow well beyond detect_voxel
    timings: dict = {}
    planes = detect_planes(xyz, params, timings=timings)
    assert 1000 < timings["samples"] <= 2000
    assert len(planes) == 1 and len(planes[0].inliers) > 0.99 * np.count_nonzero(~clutter)
    assert not np.any(np.isin(np.flatnonzero(clutter), planes[0].inliers))


# ----------------------------------------------------------------------------------------------------------------------
# A simulated city: true surfaces from the truth solids


@pytest.fixture(scope="module")
def sim_city(tmp_path_factory):
    from lidarmap.io.las import read_las
    from lidarmap.sim import SimParams, load_truth, simulate

    out = tmp_path_factory.mktemp("flatten_sim")
    simulate(out, SimParams(seed=5, buildings=3, campaigns=0))
    truth = load_truth(out)
    return truth, read_las(truth.als).xyz, truth.labels("als")


def test_simulated_buildings_planes_match_the_truth_solids(sim_city):
    from lidarmap.sim.distance import MeshDistance

    truth, xyz_all, labels = sim_city
    surface = np.isin(labels.kind, [labels.kind_names.index("wall"), labels.kind_names.index("roof")])
    checked = 0
    for building in truth.buildings:
        if building.status != "existing":
            continue
        mask = labels.building_id == building.id
        xyz = xyz_all[mask]
        mesh = building.mesh()
        dist, tri = MeshDistance(mesh.triangles)(xyz)
        result = flatten_points(xyz, seed=0)
        after, _ = MeshDistance(mesh.triangles)(result.xyz)
        on = surface[mask] & (dist < 0.25)
        # flattening brings wall and roof points closer to the true surfaces (2.5 cm range noise)
        assert np.sqrt(np.mean(after[on] ** 2)) < 0.4 * np.sqrt(np.mean(dist[on] ** 2))
        # every well-observed facet of the solid has a detected plane within 2° holding most of its points
        for facet in mesh.facets:
            pts = on & np.isin(tri, facet)
            if pts.sum() < 60:
                continue
            n = mesh.face_normals[facet[0]]
            ids = result.plane_id[pts]
            best = np.bincount(ids[ids >= 0]).argmax()
            assert np.mean(ids == best) > 0.8
            assert math.degrees(math.acos(min(1.0, abs(float(result.planes[best].normal @ n))))) < 2.0
            checked += 1
    assert checked >= 10
