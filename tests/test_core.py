"""Config resolution, local frames, atomic writes, one-line errors."""

from __future__ import annotations

import dataclasses
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from lidarmap.config import check_sections, load_toml, resolve
from lidarmap.errors import ConfigError, InputError
from lidarmap.frame import LocalFrame
from lidarmap.io.atomic import atomic_dir, atomic_path, write_text_atomic


@dataclasses.dataclass
class DemoParams:
    """Test parameters."""

    section = "demo_stage"
    buffer: float = 5.0
    iterations: int = 3
    method: str = "fast"
    flag: bool = False
    bounds: tuple[float, float] | None = None


def test_defaults_config_and_flags_override_in_order(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[demo_stage]\nbuffer = 2\nmethod = 'slow'\nbounds = [1.0, 2.5]\n")
    params = resolve(DemoParams, load_toml(cfg), iterations=7, method=None)
    assert params == DemoParams(buffer=2.0, iterations=7, method="slow", bounds=(1.0, 2.5))
    assert isinstance(params.buffer, float)
    assert resolve(DemoParams, load_toml(cfg), method="cli").method == "cli"


def test_config_errors(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[demo_stage]\nbufer = 2\n")
    with pytest.raises(ConfigError, match="unknown option 'bufer' in \\[demo_stage\\]"):
        resolve(DemoParams, load_toml(cfg))
    cfg.write_text("[demo_stage]\niterations = 'many'\n")
    with pytest.raises(ConfigError, match="iterations"):
        resolve(DemoParams, load_toml(cfg))
    cfg.write_text("[demo_stage\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_toml(cfg)
    with pytest.raises(ConfigError, match="not found"):
        load_toml(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="unknown config table"):
        check_sections({"demo_stage": {}, "oops": {}}, {"demo_stage"})


def test_local_frame_round_trip_exact() -> None:
    rng = np.random.default_rng(1)
    xyz = rng.uniform([500000, 5800000, 0], [501000, 5801000, 50], size=(1000, 3))
    frame = LocalFrame.around(xyz, rotation_deg=28.0)
    local = frame.to_local(xyz)
    assert np.abs(local[:, :2]).max() < 2000  # small numbers: float32 keeps millimetres
    np.testing.assert_allclose(frame.to_crs(local), xyz, rtol=0, atol=1e-9)
    again = LocalFrame.from_json(frame.to_json())
    assert again == frame
    # float32 storage of local coordinates still maps back within a millimetre
    np.testing.assert_allclose(frame.to_crs(local.astype(np.float32)), xyz, atol=1e-3)


def test_atomic_write_leaves_nothing_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    write_text_atomic(target, "first")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert target.read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_error_message_is_one_line_with_file() -> None:
    err = InputError("bad\nthing   happened", "/data/x.laz")
    assert str(err) == "/data/x.laz: bad thing happened"


def test_atomic_write_gives_the_mode_of_a_plain_open(tmp_path: Path) -> None:
    # mkstemp makes 0600 files: outputs must be readable by others like any file the user writes (umask applies)
    old = os.umask(0o022)
    try:
        target = write_text_atomic(tmp_path / "shared.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE(target.stat().st_mode) == 0o644


def test_atomic_dir_replaces_whole_or_not_at_all(tmp_path: Path) -> None:
    target = tmp_path / "building"
    with atomic_dir(target) as tmp:
        (tmp / "a.txt").write_text("v1")
    assert (target / "a.txt").read_text() == "v1"
    with pytest.raises(RuntimeError):
        with atomic_dir(target) as tmp:
            (tmp / "a.txt").write_text("half")
            raise RuntimeError("crash while filling the folder")
    assert (target / "a.txt").read_text() == "v1"
    with atomic_dir(target) as tmp:
        (tmp / "b.txt").write_text("v2")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]  # replaced, not merged
    assert sorted(p.name for p in tmp_path.iterdir()) == ["building"]  # no temporary folders left


# ----------------------------------------------------------------------------------------------------------------------
# Parameters: declared constraints, nested groups, old flat keys


def _params_classes():
    from lidarmap.aerial.pipeline import PipelineConfig
    from lidarmap.facade.params import FacadeParams
    from lidarmap.map.refine import RefineParams
    from lidarmap.map.update import UpdateParams
    from lidarmap.segment.baseline import BaselineParams
    from lidarmap.segment.train import TrainParams
    from lidarmap.sim.params import SimParams

    stages = [type(getattr(PipelineConfig(), f.name)) for f in dataclasses.fields(PipelineConfig)]
    return [*stages, FacadeParams, RefineParams, UpdateParams, BaselineParams, TrainParams, SimParams]


@pytest.mark.parametrize("params_cls", _params_classes(), ids=lambda c: c.__name__)
def test_every_numeric_parameter_declares_its_constraint(params_cls):
    from lidarmap.config import undeclared

    assert undeclared(params_cls) == []
    # and the defaults satisfy them
    params_cls()


def test_nested_facade_tables_flat_keys_and_one_line_errors(caplog):
    from lidarmap.config import resolve
    from lidarmap.facade.params import FacadeParams

    nested = resolve(FacadeParams, {"facade": {"planes": {"ransac_threshold": 0.04}, "layers": {"cell": 0.2}}})
    assert nested.planes.ransac_threshold == 0.04 and nested.layers.cell == 0.2
    assert nested.openings == FacadeParams().openings  # untouched groups keep their defaults
    with caplog.at_level("WARNING", logger="lidarmap.config"):
        flat = resolve(FacadeParams, {"facade": {"ransac_threshold": 0.04, "cell": 0.2}})
    assert flat == nested
    assert "[facade] ransac_threshold is now [facade.planes] ransac_threshold" in caplog.text
    with pytest.raises(ConfigError, match=r"\[facade.openings\]: Ta must be in \(0, 1\], not 1.5"):
        resolve(FacadeParams, {"facade": {"openings": {"Ta": 1.5}}})
    with pytest.raises(ConfigError, match=r"ransac_threshold must be > 0"):
        resolve(FacadeParams, {"facade": {"planes": {"ransac_threshold": -1}}})
    with pytest.raises(ConfigError, match="unknown option 'ransac_treshold'"):
        resolve(FacadeParams, {"facade": {"planes": {"ransac_treshold": 0.1}}})
    with pytest.raises(ConfigError, match=r"plane_method must be one of ransac, region, not .hough."):
        resolve(FacadeParams, {"facade": {"plane_method": "hough"}})
    # command-line flags keep flat names and land in their group
    assert resolve(FacadeParams, {}, cell=0.3).layers.cell == 0.3
    assert FacadeParams().updated(cell=0.3, Ta=0.9) == resolve(FacadeParams, {}, cell=0.3, Ta=0.9)


def test_constraints_refuse_non_finite_numbers():
    from lidarmap.aerial.densify import DensifyParams
    from lidarmap.config import resolve

    with pytest.raises(ConfigError, match="halo must be a finite number"):
        resolve(DensifyParams, {"densify": {"halo": float("nan")}})


def test_point_cloud_takes_a_crs_as_users_write_it_and_refuses_an_unknown_one(tmp_path: Path) -> None:
    from pyproj import CRS

    from lidarmap.core import PointCloud
    from lidarmap.errors import CRSError
    from lidarmap.io.las import read_las, write_las

    xyz = np.array([[85000.0, 446000.0, 1.0], [85001.0, 446001.0, 2.0]])
    for given in ("EPSG:28992", "28992", 28992, CRS.from_epsg(28992)):
        cloud = PointCloud(xyz, crs=given)
        assert isinstance(cloud.crs, CRS) and cloud.crs.to_epsg() == 28992
    back = read_las(write_las(tmp_path / "a.laz", PointCloud(xyz, crs="EPSG:28992")))  # failed with a string
    assert back.crs.to_epsg() == 28992
    with pytest.raises(CRSError, match=r"^cloud.laz: unknown CRS 'EPSG:999999'$"):
        PointCloud(xyz, crs="EPSG:999999", source="cloud.laz")
