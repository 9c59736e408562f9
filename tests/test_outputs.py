"""Outputs the GIS tool chain accepts: polygons valid in their plane, planar LoD 2.2 faces, LoD 3 for map buildings
with openings, footprint coverage (partial buildings are not completed by invention), cjio conversion."""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import Polygon, box
from test_store import map_v1, with_campaigns

from lidarmap.aerial.coverage import CoverageParams, footprint_coverage
from lidarmap.aerial.mesh import surface_mesh
from lidarmap.aerial.pipeline import PipelineConfig, RunParams, run_pipeline
from lidarmap.errors import ParameterError
from lidarmap.export.cityjson import (
    AerialBuilding,
    map_to_cityjson,
    write_aerial_cityjson,
    write_cityjson,
)
from lidarmap.export.geomcheck import surface_problems, valid_polygons
from lidarmap.export.planar import PlanarParams, planar_faces
from lidarmap.export.snap import snap_to_planes
from lidarmap.export.validate import validate_cityjson
from lidarmap.facade.model import Element, ElementKind
from lidarmap.io.footprints import read_footprints
from lidarmap.io.las import read_las, write_las
from lidarmap.sim import SimParams, simulate

# ----------------------------------------------------------------------------------------------------------------------
# Polygons valid in their plane


def _wall(points_2d: list[tuple[float, float]]) -> np.ndarray:
    """A ring in the vertical plane y = 5 (x, z from the 2D points), integer millimetres."""
    return np.array([[x * 1000, 5000, z * 1000] for x, z in points_2d], dtype=np.int64)


def test_a_self_touching_ring_is_split_into_two_valid_polygons_without_new_vertices() -> None:
    # the shape cjio could not triangulate: one ring through the same vertex twice (two squares meeting at a corner)
    ring = _wall([(0, 0), (1, 0), (1, 1), (2, 1), (2, 2), (1, 2), (1, 1), (0, 1)])
    problems = surface_problems([ring * 0.001])
    assert problems[0] == "a ring repeats a vertex" and problems[1].startswith("not valid in its plane (Ring Self")
    parts = valid_polygons([ring])
    assert len(parts) == 2
    for (exterior,) in parts:
        assert not surface_problems([exterior * 0.001]) and len(exterior) == 4
        assert {tuple(v) for v in exterior} <= {tuple(v) for v in ring}  # the input's vertices, nothing made up
    # both parts keep the input's orientation (normal -y for this ring)
    normals = [np.cross(p[0][1] - p[0][0], p[0][2] - p[0][0]) for p in parts]
    assert all(n[1] < 0 and n[0] == 0 and n[2] == 0 for n in normals)


def test_repeated_vertices_slivers_and_bow_ties() -> None:
    square = _wall([(0, 0), (1, 0), (1, 0), (1, 1), (0, 1), (0, 0)])  # consecutive repeat and closing vertex
    (cleaned,) = valid_polygons([square])[0]
    assert len(cleaned) == 4 and not surface_problems([cleaned * 0.001])
    assert valid_polygons([_wall([(0, 0), (5, 0), (5, 0.00001), (0, 0.00001)])]) == []  # collapses at 1 mm
    assert valid_polygons([_wall([(0, 0), (0.005, 0), (0.005, 0.005), (0, 0.005)])], min_area=100) == []  # sliver
    bow_tie = _wall([(0, 0), (2, 2), (2, 0), (0, 2)])
    assert surface_problems([bow_tie * 0.001])
    parts = valid_polygons([bow_tie])
    assert len(parts) == 2 and sum(shapely.Polygon(p[0][:, [0, 2]]).area for p in parts) == pytest.approx(2e6)
    crossing = {tuple(v) for p in parts for v in p[0]} - {tuple(v) for v in bow_tie}
    assert crossing == {(1000, 5000, 1000)}  # the crossing point, lifted back onto the wall's plane


# ----------------------------------------------------------------------------------------------------------------------
# The map: LoD 3 with openings, LoD 2 without; every surface valid; cjio converts it


@pytest.fixture(scope="module")
def map_doc() -> dict:
    m = with_campaigns(map_v1(), 1)
    building = next(iter(m.buildings.values()))
    facade = building.facades[0]
    # a structure whose outline touches itself (from a façade's layer segmentation): exported as two valid surfaces
    touching = Polygon([(0.5, 0.5), (1.5, 0.5), (1.5, 1.5), (2.5, 1.5), (2.5, 2.5), (1.5, 2.5), (1.5, 1.5),
                        (0.5, 1.5)])
    facade.elements.append(Element(element_id=999, kind=ElementKind.STRUCTURE, polygon=touching, uncertainty=0.1,
                                   layer_id=facade.main_layer, n_points=10, campaigns=[1]))
    return json.loads(json.dumps(map_to_cityjson(m), allow_nan=False))


def test_map_buildings_with_openings_get_lod3_and_lod2(map_doc: dict) -> None:
    assert validate_cityjson(map_doc) == []
    seen = 0
    for obj in map_doc["CityObjects"].values():
        lods = {g["lod"]: g for g in obj.get("geometry", [])}
        if "3" not in lods:
            continue
        seen += 1
        types3 = {s["type"] for s in lods["3"]["semantics"]["surfaces"]}
        types2 = {s["type"] for s in lods["2"]["semantics"]["surfaces"]}
        assert {"Window", "WallSurface"} <= types3
        assert not types2 & {"Window", "Door"}  # openings are an LoD 3 concept
        assert not any(s.get("lidarmap_kind") == "structure" for s in lods["2"]["semantics"]["surfaces"])
        walls2 = [b for b, v in zip(lods["2"]["boundaries"], lods["2"]["semantics"]["values"])
                  if lods["2"]["semantics"]["surfaces"][v]["type"] == "WallSurface"]
        assert all(len(b) == 1 for b in walls2)  # LoD 2 walls have no window holes
    assert seen >= 1
    # the self-touching structure became two surfaces under one semantic object
    geom = next(g for o in map_doc["CityObjects"].values() for g in o.get("geometry", []) if g["lod"] == "3"
                and any(s.get("lidarmap_element_id") == 999 for s in g["semantics"]["surfaces"]))
    index = next(i for i, s in enumerate(geom["semantics"]["surfaces"]) if s.get("lidarmap_element_id") == 999)
    assert geom["semantics"]["values"].count(index) == 2


def test_the_validator_finds_invalid_rings_and_unused_vertices(map_doc: dict) -> None:
    bad = copy.deepcopy(map_doc)
    bad_geom = next(g for o in bad["CityObjects"].values() for g in o.get("geometry", []) if g["lod"] == "3")
    ring = bad_geom["boundaries"][0][0]
    bad_geom["boundaries"][0][0] = [ring[0], ring[2], ring[1], ring[3], *ring[4:]]  # crossing edges
    assert any("not valid in its plane" in p for p in validate_cityjson(bad))
    unused = copy.deepcopy(map_doc)
    unused["vertices"].append([10 ** 7, 10 ** 7, 10 ** 7])
    assert validate_cityjson(unused) == [f"vertices: 1 of {len(unused['vertices'])} vertices are used by no surface"]


def _cjio_obj(src: Path, dst: Path) -> str:
    cjio = shutil.which("cjio")
    assert cjio, "cjio is in the test extra (pip install -e '.[test]')"
    proc = subprocess.run([cjio, str(src), "export", "obj", str(dst)], capture_output=True, text=True, timeout=120,
                          check=False)
    assert proc.returncode == 0 and dst.is_file(), proc.stdout + proc.stderr
    return dst.read_text()


def test_cjio_converts_the_map_to_obj(map_doc: dict, tmp_path: Path) -> None:
    write_cityjson(tmp_path / "map.city.json", map_doc)
    obj = _cjio_obj(tmp_path / "map.city.json", tmp_path / "map.obj")
    n_faces = sum(line.startswith("f ") for line in obj.splitlines())
    assert n_faces >= sum(len(g["boundaries"]) for o in map_doc["CityObjects"].values() for g in o.get("geometry", [])
                          if g["type"] == "MultiSurface")


# ----------------------------------------------------------------------------------------------------------------------
# LoD 2.2 as planar faces


def _gabled_points(rng: np.random.Generator, x0: float = 0.0, x1: float = 12.0) -> np.ndarray:
    """Points of a gabled roof (12 x 8 m, eaves 6 m, ridge 9 m along x at y = 4) and no noise beyond 2 cm."""
    xy = rng.uniform([x0, 0.0], [x1, 8.0], size=(int((x1 - x0) * 8 * 16), 2))
    z = 9.0 - 3.0 * np.abs(xy[:, 1] - 4.0) / 4.0 + rng.normal(0, 0.02, len(xy))
    return np.column_stack([xy, z])


def _hipped_points(rng: np.random.Generator) -> np.ndarray:
    """Points of a hipped roof on the same 12 x 8 m house: eaves 6 m, every plane rising 0.75 m per m from its
    eave (ridge 9 m from x = 4 to x = 8), 2 cm noise."""
    xy = rng.uniform([0.0, 0.0], [12.0, 8.0], size=(12 * 8 * 16, 2))
    to_eave = np.minimum(np.minimum(xy[:, 1], 8.0 - xy[:, 1]), np.minimum(xy[:, 0], 12.0 - xy[:, 0]))
    return np.column_stack([xy, 6.0 + 0.75 * to_eave + rng.normal(0, 0.02, len(xy))])


def _open_edges(faces) -> int:
    """Directed polygon edges (by vertex position) not matched by exactly one reverse edge: 0 for a closed solid."""
    edges: dict[tuple, int] = {}
    for face in faces:
        for rings in face.polygons:
            for ring in rings:
                points = [tuple(p) for p in np.round(ring, 6).tolist()]
                for a, b in zip(points, points[1:] + points[:1]):
                    edges[(a, b)] = edges.get((a, b), 0) + 1
    return sum(1 for (a, b), n in edges.items() if n != 1 or edges.get((b, a)) != 1)


def test_a_gabled_house_becomes_seven_strictly_planar_faces() -> None:
    rng = np.random.default_rng(5)
    mesh = surface_mesh(_gabled_points(rng), footprint=box(0, 0, 12, 8), ground_z=0.0)
    faces = planar_faces(mesh.vertices, mesh.faces)
    kinds = [f.kind for f in faces]
    # truth: 2 roof planes, 4 walls (the gable ends are one pentagon each), 1 floor, from 1,700 triangles (the
    # height field's 1.4 m² bump inside one roof plane joins it: a face enclosed by one other cannot be planar)
    assert len(mesh.faces) > 1000 and len(faces) == 7, [(f.kind, f.area) for f in faces]
    assert kinds.count("WallSurface") == 4 and kinds.count("GroundSurface") == 1
    roofs = [f for f in faces if f.kind == "RoofSurface"]
    assert all(abs(f.normal[2] - 0.8) < 0.02 and f.area == pytest.approx(12 * 5, rel=0.05) for f in roofs)
    assert sum(f.area for f in faces) == pytest.approx(mesh.area, rel=1e-9)  # every triangle in one face
    # one polygon per face, every vertex within the tolerance (1 cm) of the face's plane, the solid closed
    assert all(len(f.polygons) == 1 and not f.split for f in faces)
    for f in faces:
        corners = np.concatenate(f.polygons[0])
        assert np.abs((corners - f.point) @ f.normal).max() <= PlanarParams().tolerance
        assert f.planarity <= PlanarParams().tolerance
    assert _open_edges(faces) == 0
    # the roofs are rectangles meeting at the ridge: 4 corners each, the ridge a straight edge near 9 m (the
    # mesh rounds the ridge: its planes meet 9 cm low)
    assert [len(f.polygons[0][0]) for f in roofs] == [4, 4]
    ridge = [p for p in np.concatenate([f.polygons[0][0] for f in roofs]) if p[2] > 8.0]
    assert len(ridge) == 4 and all(abs(p[2] - 9.0) < 0.12 for p in ridge)
    # without snapping the faces keep the mesh's vertices: the roofs are planar only within the growing distance
    loose = planar_faces(mesh.vertices, mesh.faces, PlanarParams(snap=False))
    assert max(f.planarity for f in loose) > 0.05 and len(loose) == 8


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_a_hipped_house_becomes_planar_faces_with_the_true_large_faces(seed: int) -> None:
    rng = np.random.default_rng(seed)
    mesh = surface_mesh(_hipped_points(rng), footprint=box(0, 0, 12, 8), ground_z=0.0)
    faces = planar_faces(mesh.vertices, mesh.faces)
    # truth: 4 roof planes (2 trapezoids 12 x 5 m along the slope, 2 triangles), 4 walls, 1 floor; the height field
    # may add small facets where the hip lines meet the eaves
    large = [f for f in faces if f.area > 5.0]
    assert sorted(f.kind for f in large) == ["GroundSurface"] + ["RoofSurface"] * 4 + ["WallSurface"] * 4
    small = sum(f.area for f in faces if f.area <= 5.0)
    assert len(faces) <= 11 and small < 0.03 * sum(f.area for f in faces if f.kind == "RoofSurface")
    for f in (f for f in large if f.kind == "RoofSurface"):
        # slope 0.75: normal z = 1 / 1.25; the mesh's own triangles give 0.82-0.84 (it rounds the ridge and hips)
        assert abs(f.normal[2] - 0.8) < 0.04
    # every exported polygon planar within 1 cm of its own plane, the solid closed
    assert max(f.planarity for f in faces) <= PlanarParams().tolerance
    assert _open_edges(faces) == 0


def _anchored(planes: np.ndarray, offsets: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """20 interior points on each plane (n . x = d), around (2, 2, 2)."""
    out = []
    for n, d in zip(planes, offsets):
        p = rng.uniform(1, 3, (20, 3))
        out.append(p - ((p @ n) - d)[:, None] * n)
    return np.vstack(out)


def test_snapping_moves_a_vertex_to_the_common_point_of_its_planes() -> None:
    rng = np.random.default_rng(0)
    # one vertex of three faces (the planes x = 0, y = 0, z = 0, each held by interior points)
    planes = np.eye(3)
    vertices = np.vstack([[0.1, 0.2, 0.05], _anchored(planes, np.zeros(3), rng)])
    interior = np.array([[1 + 20 * k + i, k] for k in range(3) for i in range(20)])
    result = snap_to_planes(vertices, np.array([[0, 0], [0, 1], [0, 2]]), interior, planes, np.zeros((3, 3)),
                            tolerance=0.01)
    assert np.abs(result.vertices[0]).max() < 1e-3 and result.residual.max() < 0.0025  # the planes' corner
    np.testing.assert_array_equal(result.vertices[1:], vertices[1:])  # interior vertices do not move
    # a vertex of two near-parallel faces (z = 0 and z = 0.001 x + 0.5, meeting 500 m away): not sent there (the
    # regularised step keeps it near); the planes tilt toward it, and it ends within the tolerance of both
    planes = np.array([[0, 0, 1.0], [-0.001, 0, 1.0]])
    planes /= np.linalg.norm(planes, axis=1)[:, None]
    offsets = np.array([0.0, 0.5 * planes[1, 2]])
    vertices = np.vstack([[2.0, 2.0, 0.2], _anchored(planes, offsets, rng)])
    interior = np.array([[1 + 20 * k + i, k] for k in range(2) for i in range(20)])
    result = snap_to_planes(vertices, np.array([[0, 0], [0, 1]]), interior, planes, planes * offsets[:, None],
                            tolerance=0.01)
    assert np.linalg.norm(result.vertices[0] - [2.0, 2.0, 0.2]) < 5.0
    assert result.residual.max() <= 0.01 and abs(result.normals[1] @ planes[1]) < 1.0 - 1e-9


def test_aerial_cityjson_stores_planar_faces_that_cjio_converts(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    mesh = surface_mesh(_gabled_points(rng) + [500000, 5800000, 0], footprint=box(500000, 5800000, 500012, 5800008),
                        ground_z=0.0)
    b = AerialBuilding(id="g", footprint=box(500000, 5800000, 500012, 5800008), ground_z=0.0, height=9.0,
                       mesh_vertices=np.asarray(mesh.vertices), mesh_faces=np.asarray(mesh.faces), attributes={})
    path = write_aerial_cityjson(tmp_path / "b.city.json", [b], "EPSG:32632", [500000, 5800000, 0])
    doc = json.loads(path.read_text())
    assert validate_cityjson(doc) == []
    solid = doc["CityObjects"]["g"]["geometry"][1]
    assert solid["lod"] == "2.2" and len(solid["semantics"]["surfaces"]) == 7
    # a closed solid: every edge of the faces' rings is used twice, once each way
    edges: dict[tuple[int, int], int] = {}
    for surface in solid["boundaries"][0]:
        for ring in surface:
            for a, c in zip(ring, ring[1:] + ring[:1]):
                edges[(a, c)] = edges.get((a, c), 0) + 1
    assert all(edges.get((c, a)) == 1 for (a, c) in edges) and set(edges.values()) == {1}
    # read back at the file's millimetre quantum, every polygon within 1 cm of its own plane (val3dity's default)
    vertices = np.asarray(doc["vertices"], dtype=np.float64) * doc["transform"]["scale"]
    for surface in solid["boundaries"][0]:
        ring = vertices[surface[0]]
        normal = np.linalg.svd(ring - ring.mean(axis=0))[2][-1]
        assert np.abs((ring - ring.mean(axis=0)) @ normal).max() <= 0.01
    assert max(s["lidarmap_planarity"] for s in solid["semantics"]["surfaces"]) <= 0.01
    obj = _cjio_obj(path, tmp_path / "b.obj")
    assert sum(line.startswith("f ") for line in obj.splitlines()) >= 7


# ----------------------------------------------------------------------------------------------------------------------
# Coverage


def test_coverage_share_and_outline_of_a_half_covered_footprint() -> None:
    rng = np.random.default_rng(7)
    footprint = box(0, 0, 20, 10)
    half = rng.uniform([0, 0], [10, 10], size=(1600, 2))
    cover = footprint_coverage(half, footprint)
    assert cover.partial and cover.status == "partial" and cover.share == pytest.approx(0.5, abs=0.06)
    assert cover.outline.bounds[2] <= 10 + CoverageParams().margin + 1e-9 and cover.outline.bounds[0] == 0
    full = footprint_coverage(rng.uniform([0, 0], [20, 10], size=(3200, 2)), footprint)
    assert not full.partial and full.share > 0.97 and full.outline.equals(footprint)
    assert not footprint_coverage(half, footprint, CoverageParams(min_coverage=0.4)).partial
    with pytest.raises(ParameterError, match="min_coverage must be in \\[0, 1\\]"):
        CoverageParams(min_coverage=1.5)


@pytest.fixture(scope="module")
def cut_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, float]:
    """A simulated city whose scan stops at the middle of building 1 (as a tile edge would cut it)."""
    city = tmp_path_factory.mktemp("cutcity")
    simulate(city, SimParams(seed=3, buildings=2, campaigns=0))
    cloud = read_las(city / "als.laz")
    footprints = read_footprints(city / "footprints.geojson")
    first = footprints.to_crs(cloud.crs).polygons[footprints.ids.index("1")]
    cut = (first.bounds[0] + first.bounds[2]) / 2
    gone = (cloud.xyz[:, 0] > cut) & shapely.contains_xy(first.buffer(3.0), cloud.xyz[:, 0], cloud.xyz[:, 1])
    write_las(city / "cut.laz", cloud.subset(np.flatnonzero(~gone)))
    out = tmp_path_factory.mktemp("cutrun") / "out"
    run_pipeline([city / "cut.laz"], footprints, out, PipelineConfig(run=RunParams(stages=())))  # no densify: faster
    return out, json.loads((out / "summary.json").read_text()), cut


def test_a_building_cut_at_half_its_footprint_is_partial_and_not_completed(cut_run) -> None:
    out, summary, cut = cut_run
    record = json.loads((out / "buildings" / "1" / "building.json").read_text())
    assert record["status"] == "partial" and 0.3 < record["coverage"] < 0.6
    assert summary["partial"] == ["1"]
    others = [r for r in summary["records"] if r["id"] != "1"]
    assert others and all(r["status"] == "complete" and r["coverage"] > 0.9 for r in others)
    mesh = trimesh.load(out / "buildings" / "1" / "mesh.ply", process=False)
    points = read_las(out / "buildings" / "1" / "points.laz")
    # nothing beyond the measured points but the margin of the coverage cells (1 m cell + 1 m margin)
    assert mesh.bounds[1, 0] <= points.xyz[:, 0].max() + 2.0 + 1e-6 and mesh.bounds[1, 0] <= cut + 2.0 + 1e-6
    assert mesh.is_watertight
    doc = json.loads((out / "buildings.city.json").read_text())
    assert validate_cityjson(doc) == []
    attributes = doc["CityObjects"]["1"]["attributes"]
    assert attributes["lidarmap_status"] == "partial" and attributes["lidarmap_coverage"] == record["coverage"]
    block = doc["CityObjects"]["1"]["geometry"][0]
    t = doc["transform"]
    used = {i for shell in block["boundaries"] for s in shell for r in s for i in r}
    xs = np.array([doc["vertices"][i][0] for i in used]) * t["scale"][0] + t["translate"][0]
    assert xs.max() <= cut + 2.0 + 1e-6  # the LoD 1 block stands on the covered part too


def test_aerial_faces_are_far_fewer_than_the_mesh_triangles(cut_run) -> None:
    out, summary, _ = cut_run
    doc = json.loads((out / "buildings.city.json").read_text())
    for record in summary["records"]:
        solid = doc["CityObjects"][record["id"]]["geometry"][1]
        triangles = record["mesh_faces"][record["mesh"]]
        # one surface per planar face, far fewer than the mesh's triangles
        assert len(solid["semantics"]["surfaces"]) <= triangles / 5


def test_coverage_and_lod22_tables_are_read_from_the_config(tmp_path: Path) -> None:
    from lidarmap.cli.aerial import _pipeline_config
    from lidarmap.errors import ConfigError

    options = {name: None for name in ("stages", "method", "model", "union", "voxel_size", "mesh", "workers",
                                       "scheduler", "id_field", "seed")}
    config = tmp_path / "c.toml"
    config.write_text("[coverage]\nmin_coverage = 0.3\ncell = 2.0\n[lod22]\nangle = 5.0\n")
    pipeline = _pipeline_config(config, **options)
    assert (pipeline.coverage.min_coverage, pipeline.coverage.cell, pipeline.coverage.margin) == (0.3, 2.0, 0.5)
    assert pipeline.lod22.angle == 5.0 and "coverage" in pipeline.result_params()  # part of the fingerprint
    config.write_text("[coverage]\nmin_coverag = 0.3\n")
    with pytest.raises(ConfigError, match="unknown option 'min_coverag' in \\[coverage\\]"):
        _pipeline_config(config, **options)


# ----------------------------------------------------------------------------------------------------------------------
# LoD 2.2 on real roofs: AHN3 Delft


def test_delft_roofs_become_strictly_planar_closed_faces(delft_laz: Path, delft_footprints: Path,
                                                        tmp_path: Path) -> None:
    """Four row houses of the Delft tile: raw class-6 points meshed, then planar faces; every polygon within 1 cm
    of its plane, the solid closed, the CityJSON valid (the unsnapped faces of the same meshes are not planar)."""
    cloud = read_las(delft_laz, crs="EPSG:28992")
    footprints = read_footprints(delft_footprints, id_field="bag_pand_id")
    cls = cloud.attrs["classification"]
    buildings, loose = [], []
    for polygon in footprints.polygons[:12]:
        inside = shapely.contains_xy(polygon, cloud.xyz[:, 0], cloud.xyz[:, 1])
        roof = cloud.xyz[inside & (cls == 6)]
        if len(roof) < 400:
            continue
        near = shapely.contains_xy(polygon.buffer(5.0), cloud.xyz[:, 0], cloud.xyz[:, 1]) & (cls == 2)
        mesh = surface_mesh(roof, footprint=polygon, ground_z=float(np.median(cloud.xyz[near, 2])))
        faces = planar_faces(mesh.vertices, mesh.faces)
        assert max(f.planarity for f in faces) <= PlanarParams().tolerance
        assert _open_edges(faces) == 0
        # every triangle in a face but those of the few small faces snapping flattened to nothing
        assert 0.99 * mesh.area <= sum(f.area for f in faces) <= mesh.area * (1 + 1e-9)
        loose.append(max(f.planarity for f in planar_faces(mesh.vertices, mesh.faces, PlanarParams(snap=False))))
        buildings.append(AerialBuilding(id=str(len(buildings)), footprint=polygon, ground_z=0.0, height=1.0,
                                        mesh_vertices=np.asarray(mesh.vertices), mesh_faces=np.asarray(mesh.faces),
                                        attributes={}))
        if len(buildings) == 4:
            break
    assert len(buildings) == 4 and max(loose) > 0.1
    translate = np.floor(np.min([b.mesh_vertices.min(axis=0) for b in buildings], axis=0))
    path = write_aerial_cityjson(tmp_path / "delft.city.json", buildings, "EPSG:28992", translate)
    assert validate_cityjson(json.loads(path.read_text())) == []
