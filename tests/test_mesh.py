"""Meshes (lidarmap.aerial.mesh) and their scores (lidarmap.aerial.eval): watertight voxel meshes for any voxel set, 2.5D
surface meshes, float64 PLY/OBJ files, surface/solid voxels of a mesh, IoU, Chamfer and Hausdorff distances.

The simulated scene (2 buildings, no mobile campaign) gives ALS points and the truth solids to score against.
"""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import trimesh
from shapely.affinity import rotate, translate
from shapely.geometry import Polygon, box

from lidarmap.aerial.eval import (
    chamfer_hausdorff,
    voxel_iou,
    voxel_scores,
    voxelize_mesh,
)
from lidarmap.aerial.mesh import MeshParams, outline_polygon, surface_mesh, voxel_mesh
from lidarmap.aerial.voxel import VoxelParams, fill_columns, voxelize
from lidarmap.core import VoxelGrid
from lidarmap.errors import ConfigError, InputError
from lidarmap.io.las import read_las
from lidarmap.io.meshfile import write_mesh
from lidarmap.sim import SimParams, load_truth, simulate
from lidarmap.sim.distance import MeshDistance

UTM = np.array([500123.0, 5800456.0, 87.0])


def _grid(ijk, size=0.5, rgb=None) -> VoxelGrid:
    ijk = np.asarray(ijk)
    return VoxelGrid(origin=UTM + 0.25, size=size, ijk=ijk, label=np.ones(len(ijk)), rgb=rgb,
                     count=np.ones(len(ijk)))


# ----------------------------------------------------------------------------------------------------------------------
# Voxel mesh


@pytest.mark.parametrize("seed", range(40))
def test_voxel_mesh_is_watertight_for_any_voxels(seed):
    rng = np.random.default_rng(seed)
    occupied = rng.random((6, 6, 6)) < rng.uniform(0.2, 0.8)  # many edge- and corner-only contacts
    grid = _grid(np.argwhere(occupied))
    mesh = voxel_mesh(grid, MeshParams(voxel_fill="none"))
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
    assert mesh.volume == pytest.approx(len(grid) * 0.125, abs=1e-6)
    lattice = (mesh.vertices - grid.origin) / 0.5
    np.testing.assert_allclose(lattice, np.round(lattice), atol=1e-6)  # corners on the lattice, in the CRS


@pytest.mark.parametrize("cells, bodies", [
    ([[0, 0, 0], [1, 1, 0]], 2),  # touching along an edge only
    ([[0, 0, 0], [1, 1, 1]], 2),  # touching at a corner only
    # two voxels diagonal around an edge, joined by full layers above and below: one body, two tunnels meet
    ([[i, j, k] for i in range(2) for j in range(2) for k in (0, 2)] + [[0, 0, 1], [1, 1, 1]], 1),
])
def test_voxel_mesh_splits_edge_and_corner_contacts(cells, bodies):
    mesh = voxel_mesh(_grid(cells), MeshParams(voxel_fill="none"))
    assert mesh.is_volume
    parts = mesh.split(only_watertight=True)
    assert len(parts) == bodies
    assert sum(p.volume for p in parts) == pytest.approx(len(cells) * 0.125)


def test_voxel_mesh_carries_colours_and_fills_columns():
    shell = [[i, j, 3] for i in range(4) for j in range(3)] + [[0, 0, k] for k in range(3)]  # a roof and one pillar
    rgb = np.tile([[200, 30, 30]], (len(shell), 1)).astype(np.uint8)
    rgb[-3:] = [20, 20, 220]
    grid = _grid(shell, rgb=rgb)
    hollow = voxel_mesh(grid, MeshParams(voxel_fill="none"))
    solid = voxel_mesh(grid)
    assert hollow.volume == pytest.approx(15 * 0.125) and solid.volume == pytest.approx(4 * 3 * 4 * 0.125)
    colours = {tuple(c) for c in hollow.visual.face_colors[:, :3]}
    assert colours == {(200, 30, 30), (20, 20, 220)}
    with pytest.raises(InputError, match="no voxels to mesh"):
        voxel_mesh(grid.subset(np.zeros(len(grid), bool)))


def test_mesh_params_validation():
    with pytest.raises(ConfigError, match="voxel_fill must be one of columns, none, not 'full'"):
        MeshParams(voxel_fill="full")
    with pytest.raises(ConfigError, match="cell must be a finite number > 0"):
        MeshParams(cell=0)


# ----------------------------------------------------------------------------------------------------------------------
# Surface mesh on synthetic roofs


def _gable_points(polygon: Polygon, ridge_z: float, eave_z: float, ground_z: float, rng, spacing=0.3):
    """Points on a gabled roof over ``polygon`` (ridge along x through the centroid) plus sparse wall points."""
    minx, miny, maxx, maxy = polygon.bounds
    x, y = np.meshgrid(np.arange(minx, maxx, spacing), np.arange(miny, maxy, spacing))
    x, y = x.ravel() + rng.uniform(0, spacing, x.size), y.ravel() + rng.uniform(0, spacing, x.size)
    inside = shapely.contains_xy(polygon, x, y)
    x, y = x[inside], y[inside]
    cy, half = polygon.centroid.y, (maxy - miny) / 2
    z = ridge_z - (ridge_z - eave_z) * np.abs(y - cy) / half
    walls = shapely.get_coordinates(shapely.line_interpolate_point(polygon.exterior,
                                                                   rng.uniform(0, polygon.exterior.length, 300)))
    wall_z = rng.uniform(ground_z, eave_z, len(walls))
    return np.concatenate([np.column_stack([x, y, z]), np.column_stack([walls, wall_z])])


@pytest.mark.parametrize("shape", ["rectangle", "L", "courtyard"])
def test_surface_mesh_is_watertight_and_follows_the_roof(shape):
    rng = np.random.default_rng(1)
    outline = {"rectangle": box(0, 0, 16, 10),
               "L": Polygon([(0, 0), (16, 0), (16, 10), (8, 10), (8, 18), (0, 18)]),
               "courtyard": box(0, 0, 20, 20).difference(box(7, 7, 13, 13))}[shape]
    outline = translate(rotate(outline, 23.0, origin=(0, 0)), UTM[0], UTM[1])
    pts = _gable_points(outline, UTM[2] + 14.0, UTM[2] + 10.0, UTM[2], rng)
    mesh = surface_mesh(pts, MeshParams(), footprint=outline, ground_z=UTM[2])
    assert mesh.is_volume
    assert mesh.vertices.dtype == np.float64 and mesh.bounds[0, 2] == UTM[2]
    # the roof passes through the roof points (flattened points lie on planes)
    roof = pts[:-300]
    residual = MeshDistance(mesh.triangles - UTM)(roof - UTM)[0]
    assert np.median(residual) < 0.02 and np.percentile(residual, 99) < 0.2  # ridge rounding within a cell
    # volume of the prism up to the roof: footprint area x mean roof height above the ground
    expected = outline.area * np.mean(roof[:, 2] - UTM[2])
    assert mesh.volume == pytest.approx(expected, rel=0.02)


def test_outline_from_points_follows_an_l_shape():
    rng = np.random.default_rng(2)
    l_shape = Polygon([(0, 0), (16, 0), (16, 10), (8, 10), (8, 18), (0, 18)])
    pts = _gable_points(l_shape, 14.0, 10.0, 0.0, rng)
    outline = outline_polygon(pts[:, :2])
    iou = outline.intersection(l_shape).area / outline.union(l_shape).area
    assert iou > 0.93
    assert len(outline.exterior.coords) < 30  # simplified, not one vertex per point
    mesh = surface_mesh(pts, MeshParams())
    assert mesh.is_volume
    with pytest.raises(InputError, match="need an \\(N >= 3, 3\\) array"):
        surface_mesh(pts[:2])


# ----------------------------------------------------------------------------------------------------------------------
# Files


def test_write_mesh_keeps_double_precision(tmp_path):
    vertices = UTM + np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) + 0.000123456789  # sub-mm detail
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    colours = np.array([[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255], [9, 9, 9, 255]], np.uint8)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, process=False)
    for name in ("t.ply", "t.obj"):
        back = trimesh.load(write_mesh(tmp_path / name, mesh), process=False)
        np.testing.assert_array_equal(back.vertices, vertices)  # bit for bit, at UTM magnitudes
        np.testing.assert_array_equal(back.faces, faces)
        np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], colours[:, :3])
    assert b"property double x" in (tmp_path / "t.ply").read_bytes()[:300]
    voxels = voxel_mesh(_grid([[0, 0, 0], [1, 0, 0]], rgb=np.array([[1, 2, 3], [4, 5, 6]], np.uint8)))
    back = trimesh.load(write_mesh(tmp_path / "v.ply", voxels), process=False)
    np.testing.assert_array_equal(back.visual.face_colors[:, :3], voxels.visual.face_colors[:, :3])
    assert back.is_volume
    with pytest.raises(InputError, match=r"t\.stl: unknown mesh format '\.stl'"):
        write_mesh(tmp_path / "t.stl", mesh)
    (tmp_path / "blocker").write_text("a file, not a folder")
    with pytest.raises(OSError):
        write_mesh(tmp_path / "blocker" / "t.ply", mesh)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker", "t.obj", "t.ply", "v.ply"]


# ----------------------------------------------------------------------------------------------------------------------
# Evaluation


def test_voxelize_mesh_of_a_box():
    size, origin = 0.5, UTM
    cube = trimesh.creation.box(extents=[3.0, 2.0, 1.5])
    cube.apply_translation(UTM + [1.5, 1.0, 0.75])  # [0, 3] x [0, 2] x [0, 1.5] from the origin: on voxel faces
    every = voxelize_mesh(cube, size, origin, skip_downward=False)
    # half-open cells: the faces at 3, 2, 1.5 belong to the voxels above them, like points on them would
    lattice = np.argwhere(np.ones((7, 5, 4), bool))
    on_surface = np.any((lattice == 0) | (lattice == [6, 4, 3]), axis=1)
    assert {tuple(v) for v in every} == {tuple(v) for v in lattice[on_surface]}
    no_floor = voxelize_mesh(cube, size, origin)
    floor_only = {tuple(v) for v in every} - {tuple(v) for v in no_floor}
    assert floor_only == {(i, j, 0) for i in range(1, 6) for j in range(1, 4)}
    solid = voxelize_mesh(cube, size, origin, solid=True)
    assert len(solid) == 7 * 5 * 4
    below = voxelize_mesh(cube, size, origin, skip_downward=False, ground=lambda xy: np.full(len(xy), UTM[2] + 1.0))
    assert below[:, 2].min() == 1  # voxels whose top is below the ground (z < 1 m) are dropped


def test_voxelize_mesh_matches_dense_surface_samples():
    tilted = trimesh.creation.box(extents=[4.0, 3.0, 2.0])
    tilted.apply_transform(trimesh.transformations.euler_matrix(0.3, 0.2, 0.7))
    tilted.apply_translation(UTM + 5.0)
    exact = {tuple(v) for v in voxelize_mesh(tilted, 0.5, UTM, skip_downward=False)}
    samples = trimesh.sample.sample_surface_even(tilted, 200000, seed=0)[0]
    sampled = {tuple(v) for v in np.floor((samples - UTM) / 0.5).astype(int)}
    assert sampled <= exact  # every voxel a surface point falls in is found ...
    assert len(exact - sampled) < 0.05 * len(exact)  # ... and the rest are only clipped at a corner


def test_voxel_iou_and_scores():
    a = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 0, 0]])
    b = np.array([[1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]])
    assert voxel_iou(a, b) == pytest.approx(2 / 5)
    s = voxel_scores(a, b)
    assert (s["precision"], s["recall"], s["intersection"]) == (pytest.approx(2 / 3), 0.5, 2)
    assert voxel_iou(a, a) == 1.0 and voxel_iou(a, b + 10) == 0.0


def test_chamfer_hausdorff_of_known_offsets():
    inner = trimesh.creation.box(extents=[10.0, 8.0, 6.0])
    outer = trimesh.creation.box(extents=[11.0, 9.0, 7.0])  # every face 0.5 m further out
    for mesh in (inner, outer):
        mesh.apply_translation(UTM)
    r = chamfer_hausdorff(inner, outer, n_samples=3000, seed=3)
    # inner -> outer: the parallel face, 0.5 m, everywhere; outer -> inner: 0.5 m, more on the 0.5 m rims, up to
    # sqrt(3) x 0.5 at the corners
    assert r["a_to_b_mean"] == pytest.approx(0.5, abs=1e-9) and r["a_to_b_max"] == pytest.approx(0.5, abs=1e-9)
    assert 0.5 < r["b_to_a_mean"] < 0.56 and 0.75 < r["b_to_a_max"] <= np.sqrt(3) * 0.5 + 1e-9
    assert r["chamfer"] == pytest.approx((r["a_to_b_mean"] + r["b_to_a_mean"]) / 2)
    assert r["hausdorff"] == r["b_to_a_max"]
    assert r == chamfer_hausdorff(inner, outer, n_samples=3000, seed=3)  # seeded: reproducible
    assert chamfer_hausdorff(inner, inner, n_samples=2000)["hausdorff"] < 1e-9
    points = trimesh.sample.sample_surface(inner, 2000, seed=1)[0]
    p = chamfer_hausdorff(points, outer, n_samples=3000)
    assert p["a_to_b_mean"] == pytest.approx(0.5, abs=1e-9) and p["samples"] == 2000


# ----------------------------------------------------------------------------------------------------------------------
# The simulated scene: meshes against the truth solids


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    simulate(out, SimParams(seed=1, buildings=2, campaigns=0))
    truth = load_truth(out)
    cloud = read_las(out / "als.laz")
    return truth, cloud, truth.labels("als")


def test_meshes_of_a_simulated_building_against_truth(scene):
    truth, cloud, labels = scene
    building = truth.buildings[0]
    pts = cloud.xyz[labels.building_id == building.id]
    true_mesh = building.mesh()
    scores = {}
    for name, mesh in {
        "voxel_1m": voxel_mesh(voxelize(pts, params=VoxelParams(size=1.0))),
        "voxel_0.5m": voxel_mesh(voxelize(pts, params=VoxelParams(size=0.5))),
        "surface_footprint": surface_mesh(pts, footprint=building.polygon, ground_z=building.base_z),
        "surface_outline": surface_mesh(pts, ground_z=building.base_z),
    }.items():
        assert mesh.is_volume, name
        scores[name] = chamfer_hausdorff(mesh, true_mesh, n_samples=2000, seed=0)
    assert scores["voxel_1m"]["chamfer"] < 0.6 and scores["voxel_1m"]["hausdorff"] < 2.0
    assert scores["voxel_0.5m"]["chamfer"] < 0.3
    assert scores["surface_footprint"]["chamfer"] < 0.02  # roofs and walls within centimetres
    assert scores["surface_outline"]["chamfer"] < 0.1  # the outline from the points costs a few centimetres
    assert scores["surface_footprint"]["chamfer"] < scores["voxel_0.5m"]["chamfer"] < scores["voxel_1m"]["chamfer"]
    # solid voxel IoU: the columns filled under the roof against the truth solid
    grid = voxelize(pts, params=VoxelParams(size=1.0))
    solid_iou = voxel_iou(fill_columns(grid, close_gaps=1).ijk, voxelize_mesh(true_mesh, 1.0, grid.origin, solid=True))
    assert solid_iou > 0.8
