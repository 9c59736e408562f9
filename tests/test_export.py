"""Exports of the building map (lidarmap.export): CityJSON 2.0 (schema + references, semantics, attributes,
coordinates back to the façade frames) and the façade renders.

The map is test_store's synthetic one: building A with a window, a recessed door, a structure, an unknown region,
a bare second façade and a roof plane; building "B/2 ü" with a two-part footprint and no height.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from shapely.geometry import box
from test_store import map_v1, with_campaigns

from lidarmap.export.cityjson import SCALE, map_to_cityjson, write_cityjson
from lidarmap.export.render import MARGINS, facade_image_size, render_map
from lidarmap.export.summary import count_map
from lidarmap.export.validate import validate_cityjson
from lidarmap.map.model import Building, BuildingMap

HALF_MM = 0.5 * SCALE + 1e-9


@pytest.fixture(scope="module")
def building_map() -> BuildingMap:
    m = with_campaigns(map_v1(), 1)
    m.buildings["C"] = Building("C", box(500300, 5800300, 500310, 5800306), {"height": 9.0, "ground_z": 40.0})
    return m


@pytest.fixture(scope="module")
def doc(building_map: BuildingMap) -> dict:
    return json.loads(json.dumps(map_to_cityjson(building_map), allow_nan=False))  # strict JSON


def _xyz(doc: dict, ring: list[int]) -> np.ndarray:
    t = doc["transform"]
    return np.asarray([doc["vertices"][i] for i in ring], dtype=np.float64) * t["scale"] + t["translate"]


def _semantics(doc: dict, bid: str) -> tuple[list[dict], list, list]:
    geom = doc["CityObjects"][bid]["geometry"][0]
    return geom["semantics"]["surfaces"], geom["semantics"]["values"], geom["boundaries"]


def _surfaces_of(doc: dict, bid: str, **match) -> list[tuple[dict, list]]:
    """(semantic, surface boundary) pairs whose semantic has all of ``match``."""
    surfaces, values, boundaries = _semantics(doc, bid)
    return [(surfaces[v], b) for v, b in zip(values, boundaries)
            if v is not None and all(surfaces[v].get(k) == x for k, x in match.items())]


# ----------------------------------------------------------------------------------------------------------------------
# CityJSON


def test_cityjson_is_valid_and_the_checker_catches_broken_documents(doc: dict) -> None:
    assert doc["type"] == "CityJSON" and doc["version"] == "2.0"
    assert validate_cityjson(doc) == []
    broken = {
        "no transform": lambda d: d.pop("transform"),
        "bad lod": lambda d: d["CityObjects"]["A"]["geometry"][0].update(lod="5"),
        "missing vertex": lambda d: d["CityObjects"]["A"]["geometry"][0]["boundaries"][0][0].append(10 ** 6),
        "untyped semantic": lambda d: d["CityObjects"]["A"]["geometry"][0]["semantics"]["surfaces"][0].pop("type"),
        "one-way parent": lambda d: d["CityObjects"]["A"]["geometry"][0]["semantics"]["surfaces"][0].pop("children"),
        "short values": lambda d: d["CityObjects"]["A"]["geometry"][0]["semantics"]["values"].pop(),
        "duplicate vertex": lambda d: d["vertices"].append(list(d["vertices"][0])),
    }
    for name, damage in broken.items():
        bad = copy.deepcopy(doc)
        damage(bad)
        assert validate_cityjson(bad), name


def test_windows_and_doors_are_children_of_their_wall_surface(doc: dict, building_map: BuildingMap) -> None:
    surfaces, _, _ = _semantics(doc, "A")
    walls = [i for i, s in enumerate(surfaces) if s["type"] == "WallSurface" and s["lidarmap_kind"] == "facade"]
    assert [surfaces[i]["lidarmap_facade_id"] for i in walls] == [0, 1]
    openings = [i for i, s in enumerate(surfaces) if s["type"] in ("Window", "Door")]
    assert sorted(surfaces[i]["type"] for i in openings) == ["Door", "Window"]
    for i in openings:
        assert surfaces[i]["parent"] == walls[0] and i in surfaces[walls[0]]["children"]
    assert sorted(surfaces[walls[0]]["children"]) == sorted(openings)
    assert "children" not in surfaces[walls[1]]  # the bare façade has no openings


def test_opening_geometry_maps_back_to_the_facade_frame(doc: dict, building_map: BuildingMap) -> None:
    facade = building_map.buildings["A"].facades[0]
    frame = facade.frame
    for kind, element_id, depth in (("Window", 0, 0.0), ("Door", 1, -0.3)):
        [(semantic, surface)] = _surfaces_of(doc, "A", type=kind)
        element = facade.elements[element_id]
        expected = frame.polygon_to_crs(element.polygon, depth=depth)
        got = _xyz(doc, surface[0])
        assert len(got) == len(expected) == 4
        # same corners (the ring may start elsewhere), each within half a millimetre of the map's float64 value
        distance = np.linalg.norm(got[:, None, :] - expected[None, :, :], axis=2).min(axis=1)
        assert distance.max() <= HALF_MM * math.sqrt(3)
        std = frame.to_facade(got)
        assert np.allclose(std[:, 2], depth, atol=HALF_MM * math.sqrt(3))
        # counter-clockwise seen from outside: the ring's normal is the façade's outward normal
        normal = np.cross(got[1] - got[0], got[2] - got[1])
        assert normal @ frame.normal > 0
    # the wall (extent from t = -0.5) has the window and the door as holes at d = 0, clockwise seen from outside
    [(_, wall)] = _surfaces_of(doc, "A", lidarmap_kind="facade", lidarmap_facade_id=0)
    assert len(wall) == 3
    holes = sorted(tuple(np.round(frame.to_facade(_xyz(doc, ring))[:, :2].min(axis=0), 3)) for ring in wall[1:])
    assert holes == [(1.5, 3.5), (16.5, 0.0)]
    ring = _xyz(doc, wall[1])
    assert np.cross(ring[1] - ring[0], ring[2] - ring[1]) @ frame.normal < 0


def test_uncertainties_depth_sigma_and_unknown_regions_are_attributes(doc: dict, building_map: BuildingMap) -> None:
    facade = building_map.buildings["A"].facades[0]
    [(window, _)] = _surfaces_of(doc, "A", type="Window")
    [(door, _)] = _surfaces_of(doc, "A", type="Door")
    [(structure, _)] = _surfaces_of(doc, "A", lidarmap_kind="structure")
    assert (window["lidarmap_uncertainty"], window["lidarmap_depth_sigma"]) == (0.0762, 0.009)
    assert (door["lidarmap_uncertainty"], door["lidarmap_depth"], door["lidarmap_depth_sigma"]) == (0.1353, -0.3, 0.011)
    assert structure["type"] == "WallSurface" and structure["lidarmap_uncertainty"] == 0.998
    assert structure["lidarmap_depth"] == 0.95 and structure["lidarmap_depth_sigma"] is None  # NaN σ -> null
    # the unknown region has no surface of its own; it is listed on its wall with ε = ∞ as null
    assert not _surfaces_of(doc, "A", lidarmap_element_id=3)
    [(wall, _)] = _surfaces_of(doc, "A", lidarmap_kind="facade", lidarmap_facade_id=0)
    [unknown] = wall["lidarmap_unknown_regions"]
    assert unknown["element_id"] == 3 and unknown["uncertainty"] is None and unknown["kind"] == "unknown"
    assert unknown["area"] == pytest.approx(2.2 * 2.7, abs=1e-12)
    outline = facade.frame.to_facade(np.asarray(unknown["outlines"][0]["exterior"]))
    assert np.allclose(sorted(outline[:, 0]), [4.0, 4.0, 6.2, 6.2], atol=1e-3) and np.allclose(outline[:, 2], 0, atol=1e-3)
    assert wall["lidarmap_depth_sigma"] == 0.0123
    assert [la["main"] for la in wall["lidarmap_layers"]] == [False, True, False]
    assert np.allclose(wall["lidarmap_frame"]["origin"], facade.frame.origin, rtol=0, atol=0)
    attributes = doc["CityObjects"]["A"]["attributes"]
    assert {k: attributes[f"lidarmap_{k}"] for k in ("facades", "windows", "doors", "structures", "unknown", "roofs")} \
        == {"facades": 2, "windows": 1, "doors": 1, "structures": 1, "unknown": 1, "roofs": 1}
    assert attributes["missing"] is None and attributes["status"] == "existing"


def test_roof_planes_footprints_and_blocks(doc: dict, building_map: BuildingMap) -> None:
    roof = building_map.buildings["A"].roofs[0]
    [(semantic, surface)] = _surfaces_of(doc, "A", type="RoofSurface")
    xyz = _xyz(doc, surface[0])
    assert np.abs(xyz @ roof.normal + roof.offset).max() < 1e-3
    assert semantic["lidarmap_depth_sigma"] == 0.02
    two_parts = doc["CityObjects"]["B/2 ü"]["geometry"][0]  # no height: the footprint at LoD0
    assert (two_parts["type"], two_parts["lod"], len(two_parts["boundaries"])) == ("MultiSurface", "0", 2)
    block = doc["CityObjects"]["C"]["geometry"][0]
    assert (block["type"], block["lod"]) == ("Solid", "1")
    [shell] = block["boundaries"]
    types = [block["semantics"]["surfaces"][v]["type"] for v in block["semantics"]["values"][0]]
    assert types == ["GroundSurface", "RoofSurface"] + ["WallSurface"] * 4
    # outward-oriented closed shell: the divergence theorem gives the block's volume 10 x 6 x 9
    volume = 0.0
    for surface in shell:
        ring = _xyz(doc, surface[0])
        for k in range(1, len(ring) - 1):
            volume += np.dot(ring[0], np.cross(ring[k], ring[k + 1])) / 6.0
    assert volume == pytest.approx(540.0, abs=1e-3)
    assert _xyz(doc, shell[0][0])[:, 2] == pytest.approx(40.0) and _xyz(doc, shell[1][0])[:, 2] == pytest.approx(49.0)


def test_metadata_crs_extent_and_date(doc: dict) -> None:
    meta = doc["metadata"]
    assert meta["referenceSystem"] == "https://www.opengis.net/def/crs/EPSG/0/32632"
    assert meta["referenceDate"] == "2024-05-01"
    xyz = np.asarray(doc["vertices"], dtype=np.float64) * doc["transform"]["scale"] + doc["transform"]["translate"]
    assert np.allclose(meta["geographicalExtent"], [*xyz.min(axis=0), *xyz.max(axis=0)])
    assert all(isinstance(c, int) for v in doc["vertices"] for c in v)


def test_write_cityjson_is_strict_and_atomic(tmp_path: Path, building_map: BuildingMap) -> None:
    out = tmp_path / "city.city.json"
    write_cityjson(out, map_to_cityjson(building_map))
    first = out.read_bytes()
    assert validate_cityjson(json.loads(first)) == []
    with pytest.raises(ValueError):
        write_cityjson(out, {"type": "CityJSON", "bad": float("nan")})
    assert out.read_bytes() == first and sorted(p.name for p in tmp_path.iterdir()) == ["city.city.json"]
    write_cityjson(tmp_path / "again.city.json", map_to_cityjson(building_map))
    assert (tmp_path / "again.city.json").read_bytes() == first  # deterministic


def test_empty_map_exports_a_valid_document() -> None:
    doc = map_to_cityjson(BuildingMap(crs_wkt=""))
    assert doc["CityObjects"] == {} and doc["vertices"] == [] and validate_cityjson(doc) == []


# ----------------------------------------------------------------------------------------------------------------------
# Renders


def _plot_pixels(path: Path) -> np.ndarray:
    """RGB pixels inside the plot area (margins with title, labels, legend and the axes' frame cut off)."""
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    left, right, top, bottom = (m + 8 for m in MARGINS)
    return image[top:image.shape[0] - bottom, left:image.shape[1] - right]


def test_render_writes_one_png_per_facade_with_windows_red_and_unknown_white(tmp_path: Path,
                                                                            building_map: BuildingMap) -> None:
    calls = []
    written = render_map(building_map, tmp_path / "renders", width_px=600, progress=lambda *a: calls.append(a))
    assert [p.name for p in written] == ["A_facade00.png", "A_facade01.png"]
    assert calls == [(1, 2), (2, 2)]
    for path, facade in zip(written, building_map.buildings["A"].facades):
        assert Image.open(path).size == facade_image_size(facade, 600)
    red = [int(np.sum(np.abs(_plot_pixels(p) - [227, 32, 27]).max(axis=2) < 12)) for p in written]
    white = [int(np.sum(_plot_pixels(p).min(axis=2) >= 250)) for p in written]
    assert red[0] > 100 and red[1] == 0  # the window and the door outlines, none on the bare façade
    assert white[0] > 50 and white[1] == 0  # the unknown region


def test_render_file_names_are_safe_and_unique(tmp_path: Path, building_map: BuildingMap) -> None:
    facade = building_map.buildings["A"].facades[1]
    m = BuildingMap(crs_wkt="", buildings={
        "a b": Building("a b", box(0, 0, 1, 1), facades=[facade]),
        "a_b": Building("a_b", box(0, 0, 1, 1), facades=[facade]),
        "../x": Building("../x", box(0, 0, 1, 1), facades=[facade]),
    })
    names = [p.name for p in render_map(m, tmp_path, width_px=400)]
    assert names == ["a_b_facade01.png", "a_b_facade01-2.png", "x_facade01.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)


def test_counts_treat_infinite_uncertainty_as_unknown(building_map: BuildingMap) -> None:
    m = copy.deepcopy(building_map)
    m.buildings["A"].facades[0].elements[0].uncertainty = math.inf  # a window nobody could confirm
    before, after = count_map(building_map), count_map(m)
    assert (before["windows"], before["unknown"]) == (1, 1) and (after["windows"], after["unknown"]) == (0, 2)
    assert before["buildings"] == 3 and before["facades"] == 2 and before["layers"] == 3 and before["roofs"] == 1
