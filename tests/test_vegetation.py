"""Trees are not buildings: the tree-like rule, the predict-time vegetation filter, the scores on every point, the
densification seeds of the pipeline, and where the training recipe finds its data."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lidarmap.aerial.pipeline import densify_seeds
from lidarmap.core import PointCloud
from lidarmap.errors import ParameterError
from lidarmap.io.las import read_las
from lidarmap.segment import recipe
from lidarmap.segment.blocks import hide_labels
from lidarmap.segment.features import FeatureSpec, point_features
from lidarmap.segment.metrics import combine_tree_scores, evaluate_classes, tree_scores
from lidarmap.segment.modelfile import load_model
from lidarmap.segment.predict import (
    PredictParams,
    model_probability,
    predict,
    segmented_cloud,
    without_vegetation,
)
from lidarmap.segment.vegetation import (
    TreeLikeParams,
    scattering_at,
    tree_like,
    vegetation_filter,
)


def ground_grid(size: float = 40.0, step: float = 0.5) -> np.ndarray:
    g = np.arange(0.0, size, step)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def crown(rng: np.random.Generator, centre: tuple[float, float, float], radius: float, n: int) -> np.ndarray:
    """Points filling a sphere (a porous crown: a LiDAR sees into it)."""
    d = rng.normal(size=(n, 3))
    d *= (radius * rng.random(n) ** (1 / 3) / np.linalg.norm(d, axis=1))[:, None]
    return np.asarray(centre) + d


# ----------------------------------------------------------------------------------------------------------------
# The tree-like rule (labelled clouds)
# ----------------------------------------------------------------------------------------------------------------


def test_tree_like_rule_keeps_each_condition() -> None:
    rng = np.random.default_rng(0)
    ground = ground_grid()
    roof = np.column_stack([rng.uniform(0, 8, 300), rng.uniform(0, 8, 300), np.full(300, 6.0)])
    far_tree = crown(rng, (30, 30, 6), 2.0, 200)  # class 1, multi-return, high, far from the building
    near_tree = crown(rng, (9.5, 4, 6), 1.0, 100)  # within 3 m of the roof (x = 8): not counted
    bush = crown(rng, (30, 10, 1.0), 0.5, 100)  # multi-return but low
    single = crown(rng, (20, 30, 6), 1.0, 100)  # high but single returns (a wire, a car roof's echo...)
    xyz = np.vstack([ground, roof, far_tree, near_tree, bush, single])
    parts = [len(ground), len(roof), len(far_tree), len(near_tree), len(bush), len(single)]
    classes = np.repeat([2, 6, 1, 1, 1, 1], parts).astype(np.uint8)
    returns = np.repeat([1, 1, 2, 3, 2, 1], parts).astype(np.uint8)
    mask = tree_like(xyz, classes, returns)
    expected = np.repeat([False, False, True, False, False, False], parts)
    np.testing.assert_array_equal(mask, expected)
    # class 5 counts as well (IGN labels its trees), and the thresholds are the parameters
    classes5 = classes.copy()
    classes5[classes == 1] = 5
    np.testing.assert_array_equal(tree_like(xyz, classes5, returns), expected)
    low = tree_like(xyz, classes, returns, TreeLikeParams(min_height=0.5, building_clearance=0.5))
    np.testing.assert_array_equal(low, np.repeat([False, False, True, True, True, False], parts))
    assert not tree_like(xyz, classes, None).any()
    with pytest.raises(ParameterError, match="ground_neighbours must be > 0"):
        TreeLikeParams(ground_neighbours=0)


def test_tree_scores_count_every_point() -> None:
    truth = np.array([1, 1, 1, 1, 6, 6, 2, 1])
    trees = np.array([1, 1, 1, 1, 0, 0, 0, 0], bool)
    predicted = np.array([1, 0, 0, 0, 1, 1, 0, 1], bool)
    s = tree_scores(trees, truth, predicted)
    assert s == {"tree_like_points": 4, "tree_like_false_positive_rate": 0.25, "added_points": 2,
                 "added_tree_like_share": 0.5}
    both = combine_tree_scores([s, tree_scores(trees[:2], truth[:2], np.array([True, True]))])
    assert both["tree_like_points"] == 6 and both["tree_like_false_positive_rate"] == pytest.approx(3 / 6)
    assert both["added_points"] == 4 and both["added_tree_like_share"] == pytest.approx(3 / 4)


# ----------------------------------------------------------------------------------------------------------------
# The predict-time filter (unlabelled clouds)
# ----------------------------------------------------------------------------------------------------------------


def test_vegetation_filter_takes_crowns_not_roofs_or_their_edges() -> None:
    rng = np.random.default_rng(1)
    g = np.arange(0.0, 20.0, 0.25)
    x, y = np.meshgrid(g, g)
    roof = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 8.0)])
    edge = (x.ravel() < 0.5) | (x.ravel() > 19.5) | (y.ravel() < 0.5) | (y.ravel() > 19.5)
    tree = crown(rng, (30.0, 10.0, 7.0), 3.0, 3000)
    xyz = np.vstack([roof, tree])
    returns = np.concatenate([np.where(edge, 2, 1), np.full(len(tree), 3)]).astype(np.uint8)
    candidates = np.arange(len(xyz))
    veg = vegetation_filter(xyz, returns, candidates, 3.5, 0.75, 0.03, 0.7)
    assert veg[len(roof):].mean() > 0.95
    assert not veg[:len(roof)].any()  # the multi-return roof edge too
    assert not vegetation_filter(xyz, None, candidates, 3.5, 0.75, 0.03, 0.7).any()
    only_roof = vegetation_filter(xyz, returns, candidates[:len(roof)], 3.5, 0.75, 0.03, 0.7)
    assert len(only_roof) == len(roof) and not only_roof.any()
    # the network's scattering channel, when given, stands in for the filter's own computation
    given = scattering_at(cKDTree(xyz), xyz, 16)
    np.testing.assert_array_equal(vegetation_filter(xyz, returns, candidates, 3.5, 0.75, 0.03, 0.7,
                                                    scattering=given), veg)
    flat = np.zeros(len(xyz))
    assert not vegetation_filter(xyz, returns, candidates, 3.5, 0.75, 0.03, 0.7, scattering=flat).any()


def test_filter_keeps_low_last_returns_under_a_crown() -> None:
    """A wall's foot inside a crown that hangs to the ground: its pulses end there (last returns, below 2.5 m), so
    the filter leaves it building while it takes the crown; with ``vegetation_keep_below = 0`` it takes both."""
    rng = np.random.default_rng(4)
    ground = ground_grid()
    tree = crown(rng, (20.0, 20.0, 3.0), 2.8, 2500)
    foot = np.column_stack([np.full(60, 20.0), rng.uniform(18.5, 21.5, 60), rng.uniform(0.3, 2.0, 60)])
    xyz = np.vstack([ground, tree, foot])
    parts = [len(ground), len(tree), len(foot)]
    attrs = {"classification": np.repeat([2, 1, 1], parts).astype(np.uint8),
             "return_number": np.repeat([1, 1, 2], parts).astype(np.uint8),
             "number_of_returns": np.repeat([1, 3, 2], parts).astype(np.uint8)}
    cloud = PointCloud(xyz, attrs)
    prob = np.repeat([0.0, 1.0, 1.0], parts).astype(np.float32)
    is_tree, is_foot = np.repeat([False, True, False], parts), np.repeat([False, False, True], parts)
    for features in (None, point_features(cloud, FeatureSpec())):  # own ground and scattering, or the network's
        kept = without_vegetation(cloud, prob, PredictParams(), features=features) >= 0.5
        assert kept[is_foot].all()
        assert kept[is_tree].mean() < 0.05
    taken_all = without_vegetation(cloud, prob, PredictParams(vegetation_keep_below=0.0)) >= 0.5
    assert taken_all[is_foot].mean() < 0.2  # the crown would take the foot: the rule is what keeps it
    high = dataclasses.replace(cloud, xyz=xyz + np.where(is_foot, 3.0, 0.0)[:, None] * [0, 0, 1])
    assert (without_vegetation(high, prob, PredictParams()) >= 0.5)[is_foot].mean() < 0.2  # only LOW returns


def test_vegetation_parameters_are_checked() -> None:
    with pytest.raises(ParameterError, match="vegetation_share must be in \\[0, 1\\], not 1.5"):
        PredictParams(vegetation_share=1.5)
    with pytest.raises(ParameterError, match="vegetation_radius must be > 0"):
        PredictParams(vegetation_radius=0.0)


#: A 40 m square of the AHN3 Delft tile inside the recipe's held-out strip (x >= min + 150 m), never seen in
#: training nor used to choose the filter's parameters: row houses with trees in their gardens and along the street.
DELFT_CROP = (150.0, 110.0, 40.0)
#: Bounds on that crop. Measured with the weights shipped on 2026-11-26 (training seed 1): 1,951 tree-like points,
#: FP 0.329 without the filter, 0.051 with it, building IoU 0.9876 with; the weights before them (seed 0): FP 0.695
#: / 0.030, IoU 0.9756. The seed-1 weights call fewer of these crowns building on their own and are better on the
#: whole held-out strip (0.0121 against 0.0191, the test below), worse on this square by 42 points: the bound is 0.06.
#: The weights shipped since round 7 (seed 1 + 12 averaged epochs): FP 0.609 without the filter, 0.053 with it,
#: IoU 0.9892; 0.0124 on the whole strip.
CROP_TREE_FP_MAX = 0.06
CROP_BUILDING_IOU_MIN = 0.90
#: The issue's target on every held-out part (docs/segmentation.md): tree-like points predicted building.
HELD_OUT_TREE_FP_MAX = 0.03


def test_shipped_model_with_the_filter_leaves_real_trees_alone(delft_laz: Path) -> None:
    cloud = read_las(delft_laz, crs="EPSG:28992")
    rel = cloud.xyz - cloud.xyz.min(axis=0)
    x0, y0, size = DELFT_CROP
    crop = cloud.subset((rel[:, 0] >= x0) & (rel[:, 0] < x0 + size) & (rel[:, 1] >= y0) & (rel[:, 1] < y0 + size))
    classes = crop.attrs["classification"]
    trees = tree_like(crop.xyz, classes, crop.attrs["number_of_returns"])
    assert trees.sum() > 1000 and (classes == 6).sum() > 3000  # a crop with both
    hidden = hide_labels(crop)
    params = PredictParams(threads=2)
    raw, features = model_probability(hidden, load_model(), dataclasses.replace(params, vegetation=False))
    filtered = without_vegetation(hidden, raw, params)
    # predict's path reuses the network's height above the ground and scattering: the same answer
    np.testing.assert_array_equal(without_vegetation(hidden, raw, params, features=features), filtered)
    before = tree_scores(trees, classes, raw >= 0.5)["tree_like_false_positive_rate"]
    after = tree_scores(trees, classes, filtered >= 0.5)["tree_like_false_positive_rate"]
    assert before > 0.25  # the network alone calls a third (seed 1) to three fifths (round 7) of them building
    assert after <= CROP_TREE_FP_MAX, (before, after)
    assert evaluate_classes(classes, filtered >= 0.5)["iou"]["building"] >= CROP_BUILDING_IOU_MIN
    # class 5 only behind the flag; what it writes is crowns, not the houses (measured: 2,370 points, 0.13 %
    # labelled 6, 73 % tree-like -- the rest crowns nearer than 3 m to a house --, 89 % of the tree-like reached)
    assert not (segmented_cloud(hidden, filtered, params).attrs["classification"] == 5).any()
    written = segmented_cloud(hidden, filtered, dataclasses.replace(params, write_vegetation=True)
                              ).attrs["classification"] == 5
    assert written.sum() > 1000
    assert (classes[written] == 6).mean() <= 0.01
    assert trees[written].mean() >= 0.5 and written[trees].mean() >= 0.8


def test_shipped_model_meets_the_tree_like_target_on_the_held_out_delft_strip(delft_laz: Path) -> None:
    """The whole held-out AHN3 strip (x >= min + 150 m, about 0.1 M points), labels removed before predicting: the
    issue's target, not a crop's bound (measured 0.0124 with the filter, 0.294 without, round-7 weights;
    docs/segmentation.md)."""
    cloud = read_las(delft_laz, crs="EPSG:28992")
    x = cloud.xyz[:, 0]
    strip = cloud.subset(x >= x.min() + recipe.HOLDOUT_STRIPS[recipe.DELFT])
    classes = strip.attrs["classification"]
    trees = tree_like(strip.xyz, classes, strip.attrs["number_of_returns"])
    building = predict(hide_labels(strip), load_model(), PredictParams(threads=2)) >= 0.5
    fp = tree_scores(trees, classes, building)["tree_like_false_positive_rate"]
    assert trees.sum() > 10_000 and fp <= HELD_OUT_TREE_FP_MAX, (int(trees.sum()), fp)
    assert evaluate_classes(classes, building)["iou"]["building"] >= CROP_BUILDING_IOU_MIN


# ----------------------------------------------------------------------------------------------------------------
# The pipeline: densification does not multiply what the pulse went through
# ----------------------------------------------------------------------------------------------------------------


def test_densify_seeds_leave_out_added_points_a_pulse_went_through() -> None:
    classes_in = np.array([6, 6, 1, 1, 1, 2], np.uint8)
    cloud = PointCloud(np.zeros((7, 3)), {
        "classification": np.array([6, 6, 6, 6, 6, 2, 6], np.uint8),  # the 7th: a point added by a stage
        "return_number": np.array([1, 1, 1, 2, 1, 1, 1], np.uint8),
        "number_of_returns": np.array([2, 1, 2, 2, 1, 1, 2], np.uint8)})
    # input 6 stays whatever its returns; added: first of two (dropped), last of two and single (kept)
    np.testing.assert_array_equal(densify_seeds(cloud, classes_in), [1, 1, 0, 1, 1, 0, 1])
    no_returns = PointCloud(np.zeros((7, 3)), {"classification": cloud.attrs["classification"]})
    np.testing.assert_array_equal(densify_seeds(no_returns, classes_in), [1, 1, 1, 1, 1, 0, 1])


# ----------------------------------------------------------------------------------------------------------------
# Where the recipe finds the real data
# ----------------------------------------------------------------------------------------------------------------


def test_recipe_data_folder_from_argument_environment_or_beside_the_working_directory(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(recipe.DATA_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    assert recipe.data_dir().resolve() == (tmp_path.parent / "shared" / "data").resolve()
    monkeypatch.setenv(recipe.DATA_ENV, str(tmp_path / "env"))
    assert recipe.data_dir() == tmp_path / "env"
    assert recipe.data_dir(tmp_path / "given") == tmp_path / "given"
    with pytest.raises(Exception, match="ahn3_cropped_1.laz"):
        recipe.read(recipe.DELFT)  # the environment's folder, which does not exist: an error naming the file


# ----------------------------------------------------------------------------------------------------------------
# A tree overhanging a roof: the building's voxels and mesh do not grow into the crown
# ----------------------------------------------------------------------------------------------------------------


def house_with_overhanging_tree(seed: int = 0) -> tuple[PointCloud, np.ndarray]:
    """A 10 m x 10 m flat-roofed house (roof at 6 m, delivered class 6; walls unlabelled) and a porous crown
    (centre x = 11 m, radius 2.5 m) hanging 1.5 m over its roof edge; the pulses through the crown end on the roof
    or the ground (last of several returns). Returns the cloud (metres, no CRS) and the crown mask."""
    rng = np.random.default_rng(seed)
    g = np.arange(0.15, 10.0, 0.3)
    x, y = np.meshgrid(g, g)
    roof = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 6.0)])
    s, z = np.meshgrid(np.arange(0.15, 10.0, 0.5), np.arange(0.25, 6.0, 0.5))
    s, z = s.ravel(), z.ravel()
    walls = np.vstack([np.column_stack([s, np.zeros_like(s), z]), np.column_stack([s, np.full_like(s, 10.0), z]),
                       np.column_stack([np.zeros_like(s), s, z]), np.column_stack([np.full_like(s, 10.0), s, z])])
    ground = ground_grid(24.0, 0.4) - np.array([6.0, 6.0, 0.0])
    ground = ground[~((ground[:, 0] > 0) & (ground[:, 0] < 10) & (ground[:, 1] > 0) & (ground[:, 1] < 10))]
    tree = crown(rng, (11.0, 5.0, 7.5), 2.5, 2500)
    xyz = np.vstack([roof, walls, ground, tree])
    parts = [len(roof), len(walls), len(ground), len(tree)]
    under = np.hypot(xyz[:, 0] - 11.0, xyz[:, 1] - 5.0) < 2.5  # pulses through the crown end below it
    is_tree = np.repeat([False, False, False, True], parts)
    count = np.where(is_tree | under, 3, 1).astype(np.uint8)  # returns of the pulse
    order = np.where(is_tree, rng.integers(1, 3, len(xyz)), count).astype(np.uint8)  # crown: 1st/2nd, below: last
    attrs = {"classification": np.repeat([6, 1, 2, 1], parts).astype(np.uint8),
             "number_of_returns": count, "return_number": order,
             "intensity": np.full(len(xyz), 100, np.uint16)}
    return PointCloud(xyz, attrs), is_tree


def test_a_tree_overhanging_a_roof_does_not_grow_the_building() -> None:
    from shapely.geometry import box

    from lidarmap.aerial.pipeline import PipelineConfig, RunParams, process_building
    from lidarmap.aerial.prep import BuildingPoints

    cloud, is_tree = house_with_overhanging_tree()
    # the worst case: the network calls everything above the ground building, crown included
    raw = np.where(cloud.attrs["classification"] == 2, 0.0, 1.0).astype(np.float32)
    filtered = without_vegetation(cloud, raw, PredictParams())
    assert (filtered[is_tree] < 0.5).mean() > 0.95
    bp = BuildingPoints(id="house", cloud=cloud, footprint=box(0, 0, 10, 10), properties={}, height=6.0,
                        height_source="footprint", ground_z=0.0, points_inside=int((~is_tree).sum()))
    config = PipelineConfig(run=RunParams(stages=("densify",)))

    def extent(probability: np.ndarray) -> tuple[float, float, float]:
        out = process_building(bp, probability, config)
        centres = out.voxels.origin + (out.voxels.ijk + 0.5) * out.voxels.size
        surface = out.meshes["surface"].bounds
        return float(centres[:, 0].max()), float(centres[:, 2].max()), float(surface[1, 2])

    x_max, z_max, mesh_top = extent(filtered)
    assert x_max <= 10.0 + 1.0 and z_max <= 6.0 + 1.0 and mesh_top <= 6.5, (x_max, z_max, mesh_top)
    x_raw, z_raw, _ = extent(raw)
    assert x_raw > 12.0 and z_raw > 8.0  # without the filter the building would take the crown


# ----------------------------------------------------------------------------------------------------------------
# Simulated trees that touch buildings, leaf-on and leaf-off
# ----------------------------------------------------------------------------------------------------------------


def test_touching_trees_stand_outside_and_hang_over_the_roof_edge() -> None:
    from shapely.geometry import Point, Polygon

    from lidarmap.sim.trees import OVERHANG, touching_spots

    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    ell = np.array([[20.0, 0.0], [30.0, 0.0], [30.0, 4.0], [24.0, 4.0], [24.0, 9.0], [20.0, 9.0]])
    spots = touching_spots(np.random.default_rng(3), [square, ell], [6.0, 9.0], [1, 2], 6)
    assert len(spots) == 6 and {s.building_id for s in spots} == {1, 2}
    for s in spots:
        polygon = Polygon(square if s.building_id == 1 else ell)
        trunk = Point(s.x, s.y)
        assert not polygon.contains(trunk)
        reach = s.crown_radius - polygon.exterior.distance(trunk)  # how far the crown reaches over the wall
        assert OVERHANG[0] - 1e-9 <= reach <= OVERHANG[1] + 1e-9
        assert s.crown_centre_z == (6.0 if s.building_id == 1 else 9.0)
    assert touching_spots(np.random.default_rng(3), [square], [6.0], [1], 0) == []


def test_city_with_touching_leaf_off_trees_keeps_the_rest_of_the_city() -> None:
    from lidarmap.sim import SimParams
    from lidarmap.sim.city import build_city
    from lidarmap.sim.mesh import KIND, LEAF

    plain = build_city(SimParams(seed=5, buildings=2, campaigns=0))
    touched = build_city(SimParams(seed=5, buildings=2, campaigns=0, trees_touching=2))
    bare = build_city(SimParams(seed=5, buildings=2, campaigns=0, trees_touching=2, leaf_off=True))
    assert len(touched.trees) == len(plain.trees) + 2
    assert touched.trees[:len(plain.trees)] == plain.trees  # the same city, plus the touching trees
    assert [b.ring.tolist() for b in touched.buildings] == [b.ring.tolist() for b in plain.buildings]
    def leaf_area(city) -> float:
        tri = city.static.triangles[(city.static.kind == KIND["tree"]) & (city.static.behaviour == LEAF)]
        return float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() / 2)

    assert leaf_area(bare) < leaf_area(touched) / 3  # bare crowns: a pulse meets far less


def test_recipe_labels_tree_like_training_points_as_vegetation() -> None:
    rng = np.random.default_rng(2)
    ground = ground_grid(30.0, 0.5)
    tree = crown(rng, (20.0, 20.0, 6.0), 2.0, 200)
    xyz = np.vstack([ground, tree])
    classes = np.repeat([2, 1], [len(ground), len(tree)]).astype(np.uint8)
    cloud = PointCloud(xyz, {"classification": classes, "number_of_returns": np.full(len(xyz), 2, np.uint8)})
    labelled = recipe.label_vegetation(cloud)
    expected = np.repeat([2, recipe.VEGETATION_LABEL], [len(ground), len(tree)])
    np.testing.assert_array_equal(labelled.attrs["classification"], expected)
    np.testing.assert_array_equal(cloud.attrs["classification"], classes)  # the input is left alone


def test_cli_writes_high_vegetation_only_behind_the_flag(tmp_path: Path) -> None:
    from conftest import run_cli_in_process
    from pyproj import CRS

    from lidarmap.io.las import write_las

    cloud, is_tree = house_with_overhanging_tree()
    cloud = dataclasses.replace(cloud, xyz=cloud.xyz + np.array([85000.0, 446000.0, 0.0]), crs=CRS.from_epsg(28992))
    tile = write_las(tmp_path / "house.laz", cloud)
    classes = {}
    for flag in ("--no-write-vegetation", "--write-vegetation"):
        out = tmp_path / flag.strip("-")
        code, _, err = run_cli_in_process("segment", "predict", str(tile), "-o", str(out), "--method", "baseline",
                                          flag)
        assert code == 0, err
        classes[flag] = read_las(out / "house.laz").attrs["classification"]
    assert not (classes["--no-write-vegetation"] == 5).any()
    written = classes["--write-vegetation"] == 5
    assert written[is_tree].mean() >= 0.8  # the crown, most of it
    assert not written[~is_tree].any()  # never the house or the ground under the crown
