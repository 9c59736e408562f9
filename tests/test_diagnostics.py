"""benchmarks/facade_misses.py's error classes: what ``--summary`` counts when looking for the next error to fix."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def misses():
    sys.path.insert(0, str(BENCH))  # facade_misses imports its sibling facade_scores
    try:
        spec = importlib.util.spec_from_file_location("facade_misses", BENCH / "facade_misses.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCH))


MISS_TYPED = ("  MISS façade 5 element 42 door/door s 6.48-7.47 t 0.25-2.31 depth -0.03 seen by campaign [1:1.00]; "
              "best map opening IoU 0.81 (window)")
FALSE_TYPED = "  FALSE façade 5 window s 6.53-7.39 t 0.26-2.19; best truth element IoU 0.81 (door)"
SQUARE = "  FALSE façade 2 window s 7.49-7.99 t 9.59-10.09; best truth element IoU 0.00 (window)"


def test_error_lines_are_classed_by_type_shape_and_size(misses):
    assert misses.error_class(MISS_TYPED) == "door typed window"
    assert misses.error_class(FALSE_TYPED) == "false window over a door"
    assert misses.error_class(SQUARE) == "false window, sliver"
    big = SQUARE.replace("s 7.49-7.99 t 9.59-10.09", "s 7.49-8.49 t 8.59-10.09")
    assert misses.error_class(big) == "false window, over nothing"
    assert misses.error_class(SQUARE.replace("IoU 0.00", "IoU 0.30")) == "false window, shape"
    assert misses.error_class(MISS_TYPED.replace("IoU 0.81", "IoU 0.00")) == "door missed, nothing over it"
    assert misses.error_class("  FALSE building 3 façade 7: window on no truth façade") == "false, on no truth façade"


def test_an_error_is_new_after_a_campaign_only_when_the_one_before_did_not_have_it(misses):
    """The list of what each campaign saw grows with every campaign; the same miss is not new for it."""
    later = MISS_TYPED.replace("[1:1.00]", "[1:1.00 2:0.40]")
    scene = misses.by_campaign(["seed 1 after 1: ...", MISS_TYPED, "seed 1 after 2: ...", later, SQUARE])
    assert scene == [[MISS_TYPED], [later, SQUARE]]
    assert misses.summary([scene]) == ["after 1: 1 door typed window",
                                       "after 2: 1 door typed window, 1 false window, sliver",
                                       "  new after 2: 1 false window, sliver"]
