"""benchmarks/cityjson_scores.py: the end-to-end scorer that judges a CityJSON export against a scene's truth
(the figures of benchmarks/bench_independent.py are read from it)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def cs():
    spec = importlib.util.spec_from_file_location("cityjson_scores", BENCH / "cityjson_scores.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["cityjson_scores"] = module
    spec.loader.exec_module(module)
    return module


ORIGIN = np.array([1000.0, 2000.0, 50.0])
U = np.array([0.6, 0.8, 0.0])
N = np.array([0.8, -0.6, 0.0])  # u x z


def _truth(tmp_path: Path, observed_door: float = 1.0) -> Path:
    doc = {"format": "lidarmap-independent-truth", "version": 1, "campaigns": [{"id": 1}],
           "facades": [{"id": 7, "building_id": 1, "origin": ORIGIN.tolist(), "u": U.tolist(), "normal": N.tolist(),
                        "width": 12.0, "height": 9.0, "observed_wall_area": {"1": 80.0}}],
           "openings": [{"id": 1, "facade_id": 7, "kind": "window", "rect": [1.0, 2.2, 1.0, 2.5],
                         "observed": {"1": 1.0}},
                        {"id": 2, "facade_id": 7, "kind": "door", "rect": [5.0, 6.0, 0.0, 2.1],
                         "observed": {"1": observed_door}},
                        {"id": 3, "facade_id": 7, "kind": "window", "rect": [8.0, 9.0, 4.0, 5.5],
                         "observed": {"1": 0.9}}]}
    path = tmp_path / "truth.json"
    path.write_text(json.dumps(doc))
    return path


def _ring(s0, s1, t0, t1, d=0.0):
    corners = [(s0, t0), (s1, t0), (s1, t1), (s0, t1)]  # counter-clockwise seen from outside
    return [ORIGIN + s * U + t * np.array([0, 0, 1.0]) + d * N for s, t in corners]


def _export(openings: list[tuple[str, tuple]]) -> dict:
    """A CityJSON document (mm integer vertices) with one LoD 3 MultiSurface: a wall and the given openings."""
    rings = [_ring(0, 12, 0, 9)] + [_ring(*rect) for _, rect in openings]
    translate = np.floor(ORIGIN)
    vertices, boundaries = [], []
    for ring in rings:
        start = len(vertices)
        vertices += [np.round((p - translate) / 0.001).astype(int).tolist() for p in ring]
        boundaries.append([list(range(start, start + 4))])
    surfaces = [{"type": "WallSurface"}] + [{"type": kind, "parent": 0} for kind, _ in openings]
    geometry = {"type": "MultiSurface", "lod": "3", "boundaries": boundaries,
                "semantics": {"surfaces": surfaces, "values": list(range(len(surfaces)))}}
    return {"type": "CityJSON", "version": "2.0", "transform": {"scale": [0.001] * 3, "translate": translate.tolist()},
            "CityObjects": {"1": {"type": "Building", "geometry": [geometry]}}, "vertices": vertices}


def test_exact_openings_score_one_and_an_unobserved_truth_is_not_asked_for(cs, tmp_path):
    truth = cs.load_truth(_truth(tmp_path, observed_door=0.2))
    doc = _export([("Window", (1.0, 2.2, 1.0, 2.5)), ("Window", (8.0, 9.0, 4.0, 5.5))])
    score = cs.score_export(doc, truth, "1", observed_min=0.6)
    assert (score.all.tp, score.all.fp, score.all.fn) == (2, 0, 0)
    assert score.all.f1 == 1.0


def test_wrong_kind_is_a_miss_and_a_false_opening_but_found_whatever_its_kind(cs, tmp_path):
    truth = cs.load_truth(_truth(tmp_path))
    doc = _export([("Window", (1.0, 2.2, 1.0, 2.5)), ("Window", (5.0, 6.0, 0.0, 2.1)),
                   ("Window", (8.0, 9.0, 4.0, 5.5))])
    score = cs.score_export(doc, truth, "1")
    assert (score.door.tp, score.door.fn) == (0, 1)
    assert (score.window.tp, score.window.fp) == (2, 1)
    assert score.false_blank == 0  # it lies on a truth opening
    assert (score.any_kind.tp, score.any_kind.fp, score.any_kind.fn) == (3, 0, 0)
    assert score.missed == [2]


def test_low_iou_and_blank_wall_openings_are_false(cs, tmp_path):
    truth = cs.load_truth(_truth(tmp_path))
    doc = _export([("Window", (1.0, 1.7, 1.0, 2.5)),  # IoU 0.58: found
                   ("Door", (5.55, 6.55, 0.0, 2.1)),  # IoU 0.45 / 1.55: too far
                   ("Window", (10.5, 11.5, 1.0, 2.0))])  # on no truth opening
    score = cs.score_export(doc, truth, "1")
    assert (score.all.tp, score.all.fp, score.all.fn) == (1, 2, 2)  # door and window 3 missed
    assert score.false_blank == 1
    assert score.false_blank_per_500m2 == pytest.approx(500 / 80.0)


def test_a_prediction_over_an_unobserved_opening_counts_neither_way(cs, tmp_path):
    truth = cs.load_truth(_truth(tmp_path, observed_door=0.3))
    score = cs.score_export(_export([("Window", (5.0, 6.0, 1.0, 2.1))]), truth, "1")
    assert (score.all.fp, score.all.fn) == (0, 2)  # windows 1 and 3 missed, nothing false


def test_alignment_removes_a_common_shift_only(cs, tmp_path):
    truth = cs.load_truth(_truth(tmp_path))
    shifted = [("Window", (1.45, 2.65, 1.0, 2.5)), ("Door", (5.45, 6.45, 0.0, 2.1)),
               ("Window", (8.45, 9.45, 4.0, 5.5))]
    delivered = cs.score_export(_export(shifted), truth, "1")
    aligned = cs.score_export(_export(shifted), truth, "1", aligned=True)
    assert delivered.all.tp == 0
    assert (aligned.all.tp, aligned.all.fp, aligned.all.fn) == (3, 0, 0)


def test_openings_off_the_plane_belong_to_no_facade(cs, tmp_path):
    truth = cs.load_truth(_truth(tmp_path))
    far = [("Window", (1.0, 2.2, 1.0, 2.5, 3.0))]  # 3 m in front of the wall
    score = cs.score_export(_export(far), truth, "1")
    assert score.off_facade == 1 and score.all.fp == 1 and score.window.tp == 0
