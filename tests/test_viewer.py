"""glTF export (lidarmap.export.gltf), the viewer page (lidarmap.viewer, ``lidarmap view``) and the page in a real
headless Chromium (lidarmap.browser).

Meshes sit at UTM coordinates (northing 5.8e6 m: float32 steps of 0.5 m there), so only the local origin keeps the
round trip within a millimetre. The map is test_store's synthetic one (window, door, structure, unknown region, a
bare façade, a roof plane) with its roof moved to a plausible height.
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import shapely
import trimesh
from conftest import run_cli_in_process as run
from test_store import CRS_WKT, _roof, map_v1, with_campaigns

from lidarmap.aerial.pipeline import building_dir, write_run_glb
from lidarmap.browser import find_chromium
from lidarmap.export.cityjson import map_to_cityjson
from lidarmap.export.gltf import (
    KINDS,
    ORIGIN_NODE,
    ROOT_NODE,
    UNKNOWN_OFFSET,
    epsilon_colours,
    glb_building_ids,
    map_to_glb,
    read_glb_json,
)
from lidarmap.io.meshfile import write_mesh
from lidarmap.map.store import MapStore
from lidarmap.viewer import viewer_page

MM = 1e-3
UTM = np.array([500123.4567, 5800321.8912, 41.25])


#: Building id -> its folder under OUT/buildings (a run makes ids safe for file names; summary.json's "folders").
STEMS = {"h1": "h1", "h 2/ü": "h_2_ü", "h3": "h3"}


def _houses() -> dict[str, trimesh.Trimesh]:
    """Three closed gabled-ish meshes (boxes with a random float64 jitter) at UTM coordinates."""
    rng = np.random.default_rng(5)
    out = {}
    for k, name in enumerate(["h1", "h 2/ü", "h3"]):
        mesh = trimesh.creation.box(extents=(8 + k, 10, 6 + 2 * k))
        mesh.vertices = mesh.vertices + UTM + [15.0 * k, 3.0 * k, 3 + k] + rng.uniform(-1e-4, 1e-4, (8, 3))
        out[name] = mesh
    return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A run folder as `lidarmap run` leaves it (mesh.ply per building, float64) plus its buildings.glb."""
    out = tmp_path_factory.mktemp("run")
    records = []
    for name, mesh in _houses().items():
        folder = building_dir(out, STEMS[name])
        folder.mkdir(parents=True)
        write_mesh(folder / "mesh.ply", mesh)
        records.append({"id": name, "output_points": 100, "planes": 6})
    folders = {r["id"]: f"buildings/{STEMS[r['id']]}" for r in records}
    (out / "summary.json").write_text(json.dumps({"crs": CRS_WKT, "records": records, "folders": folders}),
                                      encoding="utf-8")
    write_run_glb(out, records, STEMS, (), CRS_WKT)
    return out


def _crs_vertices(glb: bytes) -> dict[str, np.ndarray]:
    """Per mesh node: its vertices back in the CRS (the scene graph's transforms undone, in float64)."""
    scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    to_yup = np.eye(4)
    to_yup[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
    out = {}
    for node in scene.graph.nodes_geometry:
        matrix, geometry = scene.graph[node]
        world = trimesh.transform_points(np.asarray(scene.geometry[geometry].vertices, np.float64), matrix)
        out[node] = trimesh.transform_points(world, np.linalg.inv(to_yup))
    return out


def test_glb_round_trip_matches_the_ply_meshes_within_a_millimetre(run_dir: Path) -> None:
    glb = (run_dir / "buildings.glb").read_bytes()
    back = _crs_vertices(glb)
    for name in _houses():
        ply = trimesh.load(building_dir(run_dir, STEMS[name]) / "mesh.ply", process=False)
        parts = np.vstack([v for node, v in back.items() if node.startswith(f"{name}/")])
        # every PLY vertex has a glb vertex within 1 mm and vice versa (the glb splits by kind, so sets compare)
        d_ply = np.min(np.linalg.norm(ply.vertices[:, None] - parts[None], axis=2), axis=1)
        d_glb = np.min(np.linalg.norm(parts[:, None] - ply.vertices[None], axis=2), axis=1)
        assert d_ply.max() < MM and d_glb.max() < MM, (name, d_ply.max(), d_glb.max())
    # the local origin is what makes this work: float32 of the CRS coordinates is off by centimetres to decimetres
    ply = trimesh.load(building_dir(run_dir, "h1") / "mesh.ply", process=False)
    assert np.abs(ply.vertices.astype(np.float32).astype(np.float64) - ply.vertices).max() > 10 * MM


def test_one_node_per_building_under_the_origin_with_ids_materials_and_extras(run_dir: Path) -> None:
    glb = (run_dir / "buildings.glb").read_bytes()
    tree = read_glb_json(glb)
    nodes = tree["nodes"]
    [root] = [nodes[k] for k in tree["scenes"][0]["nodes"]]
    assert root["name"] == ROOT_NODE and np.allclose(np.reshape(root["matrix"], (4, 4)).T[:3, :3],
                                                      [[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    origin = nodes[root["children"][0]]
    assert origin["name"] == ORIGIN_NODE
    offset = np.reshape(origin["matrix"], (4, 4)).T[:3, 3]
    assert np.allclose(offset, tree["asset"]["extras"]["origin"]) and np.abs(offset - UTM).max() < 50
    assert tree["asset"]["extras"]["crs_wkt"] == CRS_WKT
    assert glb_building_ids(glb) == ["h1", "h 2/ü", "h3"]
    assert [m["name"] for m in tree["materials"]] == list(KINDS)
    kinds = set()
    for k in origin["children"]:
        building = nodes[k]
        assert building["extras"]["points"] == 100 and building["extras"]["planes"] == 6
        for child in building["children"]:
            mesh = tree["meshes"][nodes[child]["mesh"]]
            kind = mesh["name"].rsplit("/", 1)[1]
            assert tree["materials"][mesh["primitives"][0]["material"]]["name"] == kind
            kinds.add(kind)
    assert kinds == {"roof", "wall", "ground"}  # a box: top, sides, bottom


@pytest.fixture(scope="module")
def building_map():
    m = with_campaigns(map_v1(), 1, 2)
    roof = _roof()
    centre = np.array([500107.5, 5800306.0, 53.75])
    m.buildings["A"].roofs = [_roof(offset=-float(np.dot(roof.normal, centre)))]  # roof at ~54 m, not 1e6 m
    return m


@pytest.fixture(scope="module")
def map_glb(building_map) -> bytes:
    return map_to_glb(building_map, "test map")


def _polygon_area_3d(rings: list[np.ndarray]) -> float:
    def area(r: np.ndarray) -> float:
        return 0.5 * np.linalg.norm(np.sum(np.cross(r, np.roll(r, -1, axis=0)), axis=0))
    return area(rings[0]) - sum(area(r) for r in rings[1:])


def test_map_glb_surfaces_have_the_cityjson_areas_windows_coloured_by_epsilon_unknowns_in_front(building_map,
                                                                                                  map_glb) -> None:
    doc = map_to_cityjson(building_map)
    t = doc["transform"]
    xyz = np.asarray(doc["vertices"], np.float64) * t["scale"] + t["translate"]
    geometry = max(doc["CityObjects"]["A"]["geometry"], key=lambda g: float(g["lod"]))  # the glb draws the finest
    semantics = geometry["semantics"]["surfaces"]
    expected: dict[str, float] = {}
    for surface, value in zip(geometry["boundaries"], geometry["semantics"]["values"]):
        kind = {"RoofSurface": "roof", "Window": "window", "Door": "door"}.get(semantics[value]["type"], "wall")
        expected[kind] = expected.get(kind, 0.0) + _polygon_area_3d([xyz[r] for r in surface])
    scene = trimesh.load(io.BytesIO(map_glb), file_type="glb")
    back = _crs_vertices(map_glb)
    for kind, area in expected.items():
        mesh = scene.geometry[f"A/{kind}"]
        assert abs(mesh.area - area) < 1e-3 * area + 1e-4, (kind, mesh.area, area)  # holes cut, nothing lost
    # windows: vertex colours from ε
    [window] = [s for s in semantics if s["type"] == "Window"]
    colours = np.asarray(scene.geometry["A/window"].visual.vertex_attributes["color"])  # COLOR_0
    assert (colours == epsilon_colours(np.array([window["lidarmap_uncertainty"]]))[0]).all()
    # unknown regions: UNKNOWN_OFFSET in front of their wall (along its outward normal)
    [wall] = [s for s in semantics if s.get("lidarmap_unknown_regions")]
    normal = np.asarray(wall["lidarmap_frame"]["normal"])
    origin = np.asarray(wall["lidarmap_frame"]["origin"])
    depth = (back["A/unknown"] - origin) @ normal
    assert np.allclose(depth, wall["lidarmap_depth"] + UNKNOWN_OFFSET, atol=MM)
    extras = read_glb_json(map_glb)["asset"]["extras"]
    assert extras["campaigns"] == [1, 2]


def test_epsilon_colours_run_green_to_red_and_grey_for_unknown() -> None:
    c = epsilon_colours(np.array([0.0, 0.25, 0.5, 3.0, np.inf]))
    assert c[0].tolist() == [0, 255, 26, 255] and c[1][:2].tolist() == [255, 255]
    assert c[2].tolist() == c[3].tolist() == [255, 0, 26, 255]
    assert c[4][:3].tolist() == [128, 128, 128]


def test_page_is_self_contained(map_glb) -> None:
    page = viewer_page(map_glb, "a <b>map</b>", [{"campaign_id": 1, "kind": "mobile", "source": "x</script>",
                                                  "created": "2024-01-01"}])
    assert "<title>a &lt;b&gt;map&lt;/b&gt;</title>" in page
    assert not re.search(r"<(script|link|img)[^>]+(src|href)=", page)  # nothing loaded from elsewhere
    glb = re.search(r'<script id="lidarmap-glb" type="application/octet-stream">([^<]*)</script>', page).group(1)
    assert base64.b64decode(glb) == map_glb
    data = re.search(r'<script id="lidarmap-data" type="application/json">(.*?)</script>', page, re.DOTALL).group(1)
    assert json.loads(data)["campaigns"][0]["source"] == "x</script>"  # escaped, so the element did not end early
    assert page.count("</script>") == 3


@pytest.fixture(scope="module")
def map_file(building_map, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("map") / "city.lmap"
    store = MapStore.create(path, CRS_WKT)
    try:
        first = with_campaigns(map_v1(), 1)
        store.commit(first, first.campaigns[-1])
        store.commit(building_map, building_map.campaigns[-1])
    finally:
        store.close()
    return path


def test_cli_map_export_glb_and_view_of_a_map_a_run_and_a_glb(map_file: Path, run_dir: Path, tmp_path: Path) -> None:
    code, out, err = run("map", "export", map_file, "-o", tmp_path / "m.glb", "--as-of", "1")
    assert code == 0, err
    assert glb_building_ids((tmp_path / "m.glb").read_bytes()) == ["A", "B/2 ü"] and "glTF 2.0" in out
    assert read_glb_json((tmp_path / "m.glb").read_bytes())["asset"]["extras"]["campaigns"] == [1]
    for source, n in [(map_file, 2), (run_dir, 3), (run_dir / "buildings.glb", 3)]:
        page = tmp_path / "view.html"
        code, out, err = run("view", source, "-o", page)
        assert code == 0, err
        assert f"({n} buildings" in out and "<canvas" not in page.read_text(encoding="utf-8")[:200]
    # an older run without buildings.glb: made from the meshes, the run folder left as it was
    older = tmp_path / "older"
    older.mkdir()
    (older / "summary.json").write_text((run_dir / "summary.json").read_text(encoding="utf-8"), encoding="utf-8")
    for name in _houses():
        building_dir(older, STEMS[name]).mkdir(parents=True)
        (building_dir(older, STEMS[name]) / "mesh.ply").write_bytes(
            (building_dir(run_dir, STEMS[name]) / "mesh.ply").read_bytes())
    code, out, err = run("view", older, "-o", tmp_path / "older.html")
    assert code == 0 and "(3 buildings" in out and not (older / "buildings.glb").exists(), err


def test_cli_view_bad_inputs_give_one_line_and_write_nothing(run_dir: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"not a glb at all, sorry")
    page = tmp_path / "view.html"
    cases = [((tmp_path / "missing", "-o", page), "not found"),
             ((bad, "-o", page), "not a glb file"),
             ((run_dir, "-o", page, "--as-of", "1"), "--as-of applies to a map only"),
             ((tmp_path, "-o", page), "not a 'lidarmap run' output folder"),
             ((run_dir / "summary.json", "-o", page), "not a lidarmap map")]
    for args, needle in cases:
        code, _, err = run("view", *args)
        lines = err.strip().splitlines()
        assert code != 0 and len(lines) == 1 and needle in lines[0] and "Traceback" not in err, (args, err)
        assert not page.exists()


# ----------------------------------------------------------------------------------------------------------------------
# In a real browser


def _chromium_or_skip() -> None:
    pytest.importorskip("playwright", reason="pip install playwright (no browser download needed)")
    if find_chromium() is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CI: no Chromium found (apt-get install chromium, or set LIDARMAP_CHROMIUM)")
        pytest.skip("no Chromium found: install the distribution's 'chromium' package (see README) or set "
                    "LIDARMAP_CHROMIUM")


def test_page_draws_in_headless_chromium_counts_buildings_and_picks_one(map_glb, tmp_path: Path) -> None:
    from PIL import Image

    from lidarmap.browser import open_viewer

    _chromium_or_skip()
    page = tmp_path / "view.html"
    page.write_text(viewer_page(map_glb, "test map"), encoding="utf-8")
    shot = tmp_path / "view.png"
    no_roofs = tmp_path / "no_roofs.png"
    result = open_viewer(page, screenshot=shot, pick="A", size=(900, 600), hide=("roofs",), hidden_screenshot=no_roofs)
    assert result.error is None, result.console
    assert result.count_shown == str(len(glb_building_ids(map_glb))) == "2"
    assert result.picked == "A"
    assert result.timings["drawn"] > result.timings["parsed"] > 0
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.float64)
    canvas = pixels[:, 330:]  # right of the side panel: the 3D view only
    assert canvas.std() > 10, canvas.std()  # not a blank canvas
    # the building drew: its wall colour is on screen (not just the background and the selection box)
    wall = np.array([219, 214, 204])
    assert (np.abs(canvas - wall).max(axis=2) < 60).sum() > 500
    # the roofs toggle: roof-coloured (terracotta: red well above green and blue) pixels before, none after
    def roof_pixels(png: Path) -> int:
        r, g, b = np.moveaxis(np.asarray(Image.open(png).convert("RGB"), dtype=np.float64)[:, 330:], 2, 0)
        return int(((r - g > 40) & (r - b > 50)).sum())

    assert roof_pixels(shot) > 300 and roof_pixels(no_roofs) < 0.05 * roof_pixels(shot)
    print(f"screenshot: {shot}")


def test_polygons_with_holes_are_triangulated_facing_their_ring_normal() -> None:
    from lidarmap.export.gltf import triangulate_rings

    square = shapely.Polygon([(0, 0), (4, 0), (4, 3), (0, 3)], [[(1, 1), (2, 1), (2, 2), (1, 2)]])
    rings = [np.column_stack([np.asarray(r.coords)[:-1], np.full(len(r.coords) - 1, 7.0)])
             for r in [square.exterior, *square.interiors]]
    vertices, faces = triangulate_rings(rings)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert abs(mesh.area - square.area) < 1e-9
    assert (mesh.face_normals[:, 2] > 0.999).all()  # counter-clockwise from above: every triangle faces up
    mesh = trimesh.Trimesh(*triangulate_rings([r[::-1] for r in rings]), process=False)
    assert (mesh.face_normals[:, 2] < -0.999).all()  # and down for the reversed rings


def test_a_footprint_id_attribute_does_not_replace_the_building_id() -> None:
    from lidarmap.export.gltf import GlbBuilding, glb_bytes

    glb = glb_bytes([GlbBuilding("B7", {}, {"id": 12, "height": 3.0})])
    assert glb_building_ids(glb) == ["B7"]


def test_a_run_without_buildings_still_gets_a_glb() -> None:
    """A run whose buildings all failed: the glb holds the two transform nodes and no building (no crash)."""
    from lidarmap.export.gltf import GlbBuilding, glb_bytes

    assert glb_building_ids(glb_bytes([])) == []
    assert glb_building_ids(glb_bytes([GlbBuilding("empty", {}, {})])) == ["empty"]


def test_run_folders_from_the_summary_and_for_runs_before_the_folder_map() -> None:
    from lidarmap.aerial.pipeline import run_folders

    assert run_folders({"folders": {"a/b": "buildings/a_b_2"}, "records": []}) == {"a/b": "a_b_2"}
    older = {"records": [{"id": "a/b"}, {"id": "A_B"}, {"id": "c"}]}  # no "folders": file-safe ids, made unique
    assert run_folders(older) == {"a/b": "a_b", "A_B": "A_B_2", "c": "c"}
