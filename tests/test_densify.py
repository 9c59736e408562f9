"""Densification: median split invariants, upsamplers against known surfaces, colour, outliers, seams, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lidarmap.aerial.densify import (
    DensifyParams,
    densify,
    median_split,
    new_point_counts,
    noise_amplification,
    remove_outliers,
    seam_ratios,
    transfer_colour,
)
from lidarmap.aerial.surface import area_per_point, flat_points
from lidarmap.aerial.upsampler import DEFAULT_WEIGHTS, load_upsampler
from lidarmap.config import resolve
from lidarmap.errors import ConfigError, InputError

OFFSET = np.array([431250.0, 5467830.0, 52.0])  # CRS-like coordinates: float32 would lose centimetres here


def jittered_grid(x0, x1, y0, y1, spacing, rng):
    """A perturbed grid in the plane (like an airborne scan pattern), (N, 2)."""
    xs, ys = np.meshgrid(np.arange(x0, x1, spacing), np.arange(y0, y1, spacing), indexing="ij")
    xy = np.column_stack([xs.ravel(), ys.ravel()]) + rng.uniform(-0.3, 0.3, (xs.size, 2)) * spacing
    return np.clip(xy, [x0, y0], [x1, y1])


def box_building(rng, roof_spacing=0.3, wall_spacing=0.6, noise=0.02, size=(16.0, 10.0, 8.0)):
    """Flat-roofed box: dense roof, sparse walls (as airborne LiDAR sees them); surface distance function."""
    lx, ly, h = size
    roof = jittered_grid(0, lx, 0, ly, roof_spacing, rng)
    parts = [np.column_stack([roof, np.full(len(roof), h)])]
    for along, length, fixed, coord in ((0, lx, 0.0, 1), (0, lx, ly, 1), (1, ly, 0.0, 0), (1, ly, lx, 0)):
        st = jittered_grid(0, length, 0, h, wall_spacing, rng)
        pts = np.zeros((len(st), 3))
        pts[:, 1 - coord] = st[:, 0]
        pts[:, coord] = fixed
        pts[:, 2] = st[:, 1]
        parts.append(pts)
    xyz = np.concatenate(parts)
    xyz = xyz + rng.normal(0, noise, xyz.shape)

    def distance(p):
        # distance to the surface of the box [0, lx] x [0, ly] x [0, h] (walls and roof; no floor: z >= 0 here)
        q = np.clip(p, [0, 0, 0], [lx, ly, h])
        inside = np.all((p > 0) & (p < [lx, ly, h]), axis=1)
        outside_d = np.linalg.norm(p - q, axis=1)
        inside_d = np.min(np.column_stack([p[:, 0], lx - p[:, 0], p[:, 1], ly - p[:, 1], h - p[:, 2]]), axis=1)
        return np.where(inside, inside_d, outside_d)

    return xyz + OFFSET, lambda p: distance(np.asarray(p) - OFFSET)


def wall_with_windows(rng, spacing=0.25, noise=0.01):
    """A wall in the plane y = 0 (x 0..20 m, z 0..9 m) with a 5 x 2 grid of 1.2 m x 1.5 m window holes."""
    xz = jittered_grid(0, 20, 0, 9, spacing, rng)
    windows = [(1.5 + 4 * i, 2.7 + 4 * i, 1.5 + 4 * j, 3.0 + 4 * j) for i in range(5) for j in range(2)]
    hole = np.zeros(len(xz), bool)
    for x0, x1, z0, z1 in windows:
        hole |= (xz[:, 0] > x0) & (xz[:, 0] < x1) & (xz[:, 1] > z0) & (xz[:, 1] < z1)
    xz = xz[~hole]
    xyz = np.column_stack([xz[:, 0], rng.normal(0, noise, len(xz)), xz[:, 1]])
    return xyz + OFFSET, windows


def in_windows(xyz, windows, inset=0.1):
    p = xyz - OFFSET
    inside = np.zeros(len(p), bool)
    for x0, x1, z0, z1 in windows:
        inside |= (p[:, 0] > x0 + inset) & (p[:, 0] < x1 - inset) & (p[:, 2] > z0 + inset) & (p[:, 2] < z1 - inset)
    return inside


# ----------------------------------------------------------------------------------------------------------------------
# Median split (paper Algorithm 1) with halos


def test_median_split_loses_no_point_and_respects_halo():
    rng = np.random.default_rng(1)
    xyz = np.concatenate([rng.normal(0, [20, 8, 3], (9000, 3)), rng.uniform(-5, 5, (3000, 3))])
    halo = 1.5
    leaves = median_split(xyz, max_leaf=1000, min_leaf=100, halo=halo)
    cores = np.concatenate([leaf.core for leaf in leaves])
    assert np.array_equal(np.sort(cores), np.arange(len(xyz)))  # every point in exactly one leaf
    assert all(100 <= len(leaf.core) < 1000 for leaf in leaves)
    for leaf in leaves:
        assert leaf.contains(xyz[leaf.core]).all()
        grown = np.all((xyz >= leaf.lo - halo) & (xyz <= leaf.hi + halo), axis=1)
        expected = np.flatnonzero(grown & ~leaf.contains(xyz))
        assert np.array_equal(np.sort(leaf.halo), expected)
    # cells partition space: a random probe lies in exactly one cell
    probes = rng.uniform(-80, 80, (2000, 3))
    assert np.array_equal(sum(leaf.contains(probes).astype(int) for leaf in leaves), np.ones(len(probes), int))


def test_median_split_thresholds_and_ties():
    rng = np.random.default_rng(2)
    small = median_split(rng.random((80, 3)), max_leaf=5000, min_leaf=100, halo=1.0)
    assert len(small) == 1 and not small[0].upsample  # Algorithm 1: fewer than 100 points are returned as is
    # 3000 points share one x (a wall): the median equals the minimum and must still split, and terminate
    xyz = np.column_stack([np.r_[np.zeros(3000), rng.uniform(0, 50, 1000)], rng.random(4000), rng.random(4000)])
    leaves = median_split(xyz, max_leaf=1000, min_leaf=10, halo=0.5)
    assert np.array_equal(np.sort(np.concatenate([leaf.core for leaf in leaves])), np.arange(4000))
    # identical points cannot be split: one leaf holds them all
    same = median_split(np.ones((3000, 3)), max_leaf=1000, min_leaf=100, halo=0.5)
    assert len(same) == 1 and len(same[0].core) == 3000


# ----------------------------------------------------------------------------------------------------------------------
# Upsamplers


@pytest.fixture(scope="module")
def learned():
    return load_upsampler()


def test_geometric_new_points_lie_on_the_surface_and_keep_edges():
    rng = np.random.default_rng(3)
    xyz, distance = box_building(rng)
    result = densify(xyz, params=DensifyParams(ratio=2.0), seed=0)
    new = result.xyz[result.is_new]
    assert abs(result.stats["ratio"] - 2.0) < 0.1
    d_in, d_new = distance(xyz), distance(new)
    assert d_new.mean() < 0.6 * d_in.mean()  # projected onto local planes: less noisy than the 2 cm input
    assert np.percentile(d_new, 99) < 0.06
    # edges stay sharp: no new point beyond the outermost samples of a face (roof edge, wall corners)
    p = new - OFFSET
    assert p[:, 2].max() < 8.0 + 0.05 and p[:, :2].min() > -0.05 and (p[:, :2] - [16.0, 10.0]).max() < 0.05
    # uniform: the sparse walls are filled to the roof's density, the dense roof gets few new points
    on_roof = p[:, 2] > 7.9
    assert on_roof.mean() < 0.1


def test_learned_new_points_lie_near_the_surface(learned):
    rng = np.random.default_rng(4)
    xyz, distance = box_building(rng)
    result = densify(xyz, params=DensifyParams(ratio=2.0), seed=0, upsampler=learned)
    d_new = distance(result.xyz[result.is_new])
    assert result.stats["new_points"] > 0.6 * len(xyz)
    assert d_new.mean() < 0.08 and np.percentile(d_new, 95) < 0.2


def test_windows_stay_open():
    rng = np.random.default_rng(5)
    xyz, windows = wall_with_windows(rng)
    result = densify(xyz, params=DensifyParams(ratio=3.0, distribution="proportional"), seed=0)
    new = result.xyz[result.is_new]
    assert len(new) > 1.8 * len(xyz)
    assert in_windows(new, windows).sum() == 0


def test_learned_keeps_most_window_area_open(learned):
    rng = np.random.default_rng(6)
    xyz, windows = wall_with_windows(rng)
    result = densify(xyz, params=DensifyParams(ratio=3.0, distribution="proportional"), seed=0, upsampler=learned)
    new = result.xyz[result.is_new]
    hole_area = sum((x1 - x0 - 0.2) * (z1 - z0 - 0.2) for x0, x1, z0, z1 in windows)
    # a filler blind to holes would put (hole area / wall area) ~ 7 % of its points there
    assert in_windows(new, windows).mean() < 0.25 * hole_area / (20 * 9)


# ----------------------------------------------------------------------------------------------------------------------
# Density, seams, outliers


def test_uniform_counts_fill_the_sparse_half_first():
    rng = np.random.default_rng(7)
    sparse = jittered_grid(0, 20, 0, 20, 0.5, rng)   # 4 / m²
    dense = jittered_grid(20, 40, 0, 20, 0.25, rng)  # 16 / m²
    xyz = np.column_stack([np.r_[sparse, dense], np.zeros(len(sparse) + len(dense))])
    counts, rho = new_point_counts(area_per_point(xyz, 8), 2.0, "uniform", 16, np.random.default_rng(0))
    assert abs(counts.sum() - len(xyz)) < 0.02 * len(xyz)
    assert 17 < rho < 23  # 2 x 8000 points over 800 m²: 20 / m² everywhere
    result = densify(xyz + OFFSET, params=DensifyParams(ratio=2.0, max_leaf=3000), seed=0)
    x = result.xyz[:, 0] - OFFSET[0]
    inner = (result.xyz[:, 1] - OFFSET[1] > 1) & (result.xyz[:, 1] - OFFSET[1] < 19)
    left = np.count_nonzero(inner & (x > 1) & (x < 19)) / (18 * 18)
    right = np.count_nonzero(inner & (x > 21) & (x < 39)) / (18 * 18)
    assert abs(left / right - 1) < 0.1 and abs(left / rho - 1) < 0.15


def _plane(rng, n=16000):
    xy = rng.uniform(0, 40, (n, 2))
    return np.column_stack([xy, 0.01 * rng.normal(size=n)]) + OFFSET


@pytest.mark.parametrize("distribution", ["uniform", "proportional"])
def test_no_seams_with_halo_but_seams_without(distribution):
    rng = np.random.default_rng(8)
    xyz = _plane(rng)  # ~0.3 m spacing
    origin = xyz.min(axis=0).round()

    def new_points(**kw):
        res = densify(xyz, params=DensifyParams(distribution=distribution, outlier_k=0, **kw), seed=1)
        return res.xyz[res.is_new] - origin

    leaves = median_split(xyz - origin, 2000, 100, 2.0)
    assert len(leaves) == 16
    split, whole = new_points(max_leaf=2000), new_points(max_leaf=10**9)
    ours = seam_ratios(split, whole, leaves, band=0.5)
    assert ours["planes"] >= 16 and ours["points"] > 2000
    assert abs(ours["band"] - 1) < 0.1 and abs(ours["across"] - 1) < 0.1
    assert abs(seam_ratios(split, whole, leaves, band=0.2)["band"] - 1) < 0.1
    # independent leaves (no halo): the split lines thin out, as in paper Fig. 8
    paper = seam_ratios(new_points(max_leaf=2000, halo=0.0), new_points(max_leaf=10**9, halo=0.0), leaves, 0.2)
    assert paper["band"] < 0.85


def test_outliers_removed_but_sparse_walls_kept():
    rng = np.random.default_rng(9)
    xyz, distance = box_building(rng, roof_spacing=0.25, wall_spacing=0.9)
    strays = OFFSET + rng.uniform([-3, -3, 0], [19, 13, 11], (30, 3))
    strays = strays[distance(strays) > 1.0][:15]  # 0.5 % stray returns, at least 1 m off the surfaces
    assert len(strays) == 15
    keep = remove_outliers(np.concatenate([xyz, strays]) - OFFSET, k=12, std_ratio=3.0)
    assert keep[:len(xyz)].mean() > 0.995  # the 0.9 m wall spacing next to the 0.25 m roof is not "outlying"
    assert (~keep[len(xyz):]).mean() >= 0.6
    assert remove_outliers(xyz, k=0).all()


def test_flat_points_reject_clutter():
    rng = np.random.default_rng(12)
    plane = np.column_stack([rng.uniform(0, 10, (2000, 2)), 0.01 * rng.normal(size=2000)])
    crown = rng.normal([5.0, 5.0, 4.0], 1.0, (300, 3))  # a tree crown (or a noise blob) above it
    flat = flat_points(np.concatenate([plane, crown]))
    assert flat[:2000].mean() > 0.99 and flat[2000:].mean() < 0.05


def test_noise_amplification_counts():
    rep = noise_amplification(np.r_[np.zeros(90), np.ones(10)], np.r_[np.zeros(185), np.ones(15)], tau=0.25)
    assert (rep["noise_in"], rep["noise_out"]) == (10, 15)
    assert rep["amplification"] == pytest.approx(1.5) and rep["frac_out"] == pytest.approx(0.075)


# ----------------------------------------------------------------------------------------------------------------------
# Colour, result layout, determinism, errors


def test_colour_transfer_exact_on_constant_patch_and_idw():
    rng = np.random.default_rng(10)
    src = rng.random((500, 3))
    colour = np.array([200, 31, 7], np.uint8)
    out = transfer_colour(src, np.tile(colour, (500, 1)), rng.random((2000, 3)), k=6)
    assert out.dtype == np.uint8 and np.array_equal(out, np.tile(colour, (2000, 1)))
    two = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    rgb = np.array([[0, 0, 0], [100, 200, 50]], np.uint8)
    got = transfer_colour(two, rgb, np.array([[0.5, 0, 0], [0.25, 0, 0], [1.0, 0, 0]]), k=2, power=2.0)
    # 1/d² weights: midpoint = mean; at 0.25 the weights are 16 and 16/9 -> 10 % of the far colour
    assert np.array_equal(got, [[50, 100, 25], [10, 20, 5], [100, 200, 50]])


def test_densify_result_layout_and_determinism():
    rng = np.random.default_rng(11)
    xyz, _ = box_building(rng)
    xyz = np.concatenate([xyz, [OFFSET + [8.0, 5.0, 30.0]]])  # a stray point far above the roof
    rgb = rng.integers(0, 256, (len(xyz), 3)).astype(np.uint8)
    a = densify(xyz, rgb, DensifyParams(), seed=3)
    b = densify(xyz, rgb, DensifyParams(), seed=3)
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb)
    kept = a.source_index[~a.is_new]
    assert len(xyz) - 1 not in kept and a.stats["outliers_removed"] >= 1
    assert np.array_equal(a.xyz[~a.is_new], xyz[kept]) and np.array_equal(a.rgb[~a.is_new], rgb[kept])
    assert not a.is_new[:len(kept)].any() and a.is_new[len(kept):].all()
    new = a.xyz[a.is_new][:50]  # a new point's source is its nearest kept input point (brute force on 50)
    d_source = np.linalg.norm(xyz[a.source_index[a.is_new][:50]] - new, axis=1)
    assert np.allclose(d_source, np.linalg.norm(xyz[kept][None] - new[:, None], axis=2).min(axis=1))
    c = densify(xyz, rgb, DensifyParams(), seed=4)
    assert not np.array_equal(a.xyz[a.is_new], c.xyz[c.is_new])


def test_errors_are_one_line():
    with pytest.raises(InputError, match=r"^densify: points must be an \(N, 3\) array, got shape \(5, 2\)$"):
        densify(np.zeros((5, 2)))
    with pytest.raises(InputError, match=r"^densify: colours must be an \(4, 3\) array, got shape \(3, 3\)$"):
        densify(np.zeros((4, 3)), np.zeros((3, 3), np.uint8))
    with pytest.raises(InputError, match="NaN or infinite"):
        densify(np.array([[0.0, 0.0, np.nan]]))
    with pytest.raises(ConfigError, match=r"^densify parameters: ratio must be in \[1, 64\]$"):
        DensifyParams(ratio=0.5)
    with pytest.raises(ConfigError, match="upsampler must be one of geometric, learned"):
        resolve(DensifyParams, {"densify": {"upsampler": "sapcu"}})
    params = resolve(DensifyParams, {"densify": {"ratio": 3, "halo": 1.5}}, upsampler="learned")
    assert (params.ratio, params.halo, params.upsampler) == (3.0, 1.5, "learned")
    assert len(densify(np.zeros((0, 3))).xyz) == 0


def test_model_file_errors_and_size(tmp_path):
    with pytest.raises(InputError, match="upsampler weights not found"):
        load_upsampler(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"format": "something else"}, bad)
    with pytest.raises(InputError, match="not a lidarmap-upsampler model file"):
        load_upsampler(bad)
    assert DEFAULT_WEIGHTS.stat().st_size < 2_000_000


# ----------------------------------------------------------------------------------------------------------------------
# A simulated city: the truth is the exact surface the lasers were traced against (window holes included)


@pytest.fixture(scope="module")
def sim_city(tmp_path_factory):
    from lidarmap.io.las import read_las
    from lidarmap.sim import SimParams, build_city, load_truth, simulate

    params = SimParams(seed=3, buildings=2, campaigns=0)
    result = simulate(tmp_path_factory.mktemp("sim"), params)
    truth = load_truth(result.out_dir)
    return truth, build_city(params), read_las(result.als).xyz, truth.labels("als").building_id


def test_simulated_buildings_densified_on_the_true_surface_with_windows_open(sim_city):
    from lidarmap.sim.distance import MeshDistance
    from lidarmap.sim.mesh import ABSORBER

    truth, city, xyz, building_id = sim_city
    for b in city.buildings:
        if b.shape == "shell":
            continue
        points = xyz[building_id == b.id]
        result = densify(points, seed=0)
        new = result.xyz[result.is_new]
        assert result.stats["ratio"] > 1.8
        tris = city.static.triangles[(city.static.building_id == b.id) & (city.static.behaviour != ABSORBER)]
        d_new = MeshDistance(tris)(city.frame.to_local(new))[0]
        assert d_new.mean() < 0.03 and np.percentile(d_new, 95) < 0.1
        in_window = np.zeros(len(new), bool)
        for f in truth.building(b.id).facades:
            s, t, d = f.to_facade(new).T
            for e in f.elements:
                if e.kind == "window":
                    s0, s1, t0, t1 = e.rect
                    in_window |= (s > s0 + 0.1) & (s < s1 - 0.1) & (t > t0 + 0.1) & (t < t1 - 0.1) & (np.abs(d) < 0.5)
        # the input has no point there; the openings are 4-6 % of the wall area (what a hole-blind wall filler hits)
        assert in_window.mean() < 0.02
