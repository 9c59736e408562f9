"""Shared fixtures: real data from ../shared/data (an error under CI=true when missing, a skip otherwise)."""

from __future__ import annotations

import contextlib
import io
import os
import sys
from pathlib import Path

import pytest

#: ``../shared/data`` beside the checkout; ``LIDARMAP_DATA`` points elsewhere (a clone in another folder).
SHARED_DATA = Path(os.environ.get("LIDARMAP_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def shared_file(relative: str) -> Path:
    """Path of a real data file; fails in CI and skips locally when it is missing."""
    path = SHARED_DATA / relative
    if not path.exists():
        message = f"shared data file missing: {path}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture
def delft_laz() -> Path:
    return shared_file("ahn3_delft/ahn3_cropped_1.laz")


@pytest.fixture
def delft_footprints() -> Path:
    return shared_file("ahn3_delft/footprints_bgt_EPSG28992.geojson")


@pytest.fixture
def montpellier_tiles() -> list[Path]:
    shared_file("ign_montpellier")
    return sorted((SHARED_DATA / "ign_montpellier").glob("*.laz"))


@pytest.fixture
def sample_c() -> Path:
    return shared_file("pdal_sample_c/sample_c.las")


@pytest.fixture
def stbarth_laz() -> Path:
    return shared_file("ign_stbarth/St_Barth_RGAF09_UTM20N_IGN_1988_SB_subset_100m.laz")


def run_cli_in_process(*args: object) -> tuple[int, str, str]:
    """Run ``lidarmap ARGS`` in this process (faster than a subprocess): (exit code, stdout, stderr)."""
    from lidarmap.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = ["lidarmap", *map(str, args)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = argv
    return code, out.getvalue(), err.getvalue()


def one_line_error(code: int, err: str, *needles: str) -> None:
    """A failed command printed exactly one line, no traceback, holding every needle."""
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
