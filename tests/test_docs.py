"""The docs' Python examples work as written; the CLI conventions a user relies on (config defaults, completion).

Every ```python block of README.md and docs/*.md must compile and its imports must resolve. A block preceded by a
``<!-- docs-example: ... -->`` line runs as written, in a temporary folder holding the files it names (prepared
below, per document).
"""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli_in_process as run
from conftest import shared_file

from lidarmap.cli.config_cmd import defaults_toml, param_classes, table_toml
from lidarmap.config import KNOWN_TABLES, resolve
from lidarmap.core import PointCloud

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"(<!-- docs-example:[^\n]*-->\n)?```python\n(.*?)```", re.DOTALL)


def python_blocks() -> list[tuple[str, int, bool, str]]:
    """(document, line, runnable, code) of every Python block."""
    blocks = []
    for doc in DOCS:
        text = doc.read_text(encoding="utf-8")
        for match in BLOCK.finditer(text):
            line = text.count("\n", 0, match.start(2))
            blocks.append((doc.relative_to(ROOT).as_posix(), line, match.group(1) is not None, match.group(2)))
    return blocks


BLOCKS = python_blocks()


def test_the_docs_have_python_examples_and_some_run() -> None:
    assert len(BLOCKS) >= 5 and any(runnable for _, _, runnable, _ in BLOCKS)


@pytest.mark.parametrize(("doc", "line", "runnable", "code"), BLOCKS, ids=[f"{d}:{n}" for d, n, _, _ in BLOCKS])
def test_every_python_example_compiles_and_its_imports_resolve(doc: str, line: int, runnable: bool,
                                                               code: str) -> None:
    tree = ast.parse(code, filename=f"{doc}:{line}")
    imports = ast.Module(body=[node for node in tree.body if isinstance(node, (ast.Import, ast.ImportFrom))],
                         type_ignores=[])
    exec(compile(imports, f"{doc}:{line}", "exec"), {})  # noqa: S102 - our own docs


def _delft_tiles(folder: Path) -> None:
    """a.laz + b.laz: the AHN3 extract (no CRS record) cut to two buildings' surroundings and split at x = 84 880 (both cut buildings 35 and 156);
    fp.geojson: the BGT footprints."""
    from lidarmap.io.las import read_las, write_las

    cloud = read_las(shared_file("ahn3_delft/ahn3_cropped_1.laz"), crs="EPSG:28992")
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    keep = (x > 84865) & (x < 84895) & (y > 447508) & (y < 447536)
    for name, part in (("a.laz", keep & (x < 84880)), ("b.laz", keep & (x >= 84880))):
        piece = cloud.subset(np.flatnonzero(part))
        write_las(folder / name, PointCloud(xyz=piece.xyz, attrs=piece.attrs, crs=None, extra_dims=piece.extra_dims))
    (folder / "fp.geojson").write_bytes(shared_file("ahn3_delft/footprints_bgt_EPSG28992.geojson").read_bytes())


#: Per document with a runnable example: what its folder needs.
PREPARE = {"docs/pipeline.md": _delft_tiles}


@pytest.mark.parametrize(("doc", "line", "code"), [(d, n, c) for d, n, r, c in BLOCKS if r],
                         ids=[f"{d}:{n}" for d, n, r, _ in BLOCKS if r])
def test_runnable_examples_run_as_written(doc: str, line: int, code: str, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    PREPARE[doc](tmp_path)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"{doc}:{line}", "exec"), {"__name__": "__docs__"})  # noqa: S102 - our own docs
    if doc == "docs/pipeline.md":
        summary = json.loads((tmp_path / "out" / "summary.json").read_text())
        assert {"35", "156"} <= set(summary["processed"])  # both buildings cut by the tile border, whole
        assert capsys.readouterr().out.startswith(f"{len(summary['records'])} ")
        assert (tmp_path / "out" / "buildings.gpkg").is_file() and (tmp_path / "out" / "buildings.city.json").is_file()


# ---------------------------------------------------------------- lidarmap config defaults
def test_config_defaults_load_back_to_the_default_parameters() -> None:
    code, out, err = run("config", "defaults")
    assert code == 0, err
    doc = tomllib.loads(out)
    classes = param_classes()
    assert sorted(doc) == sorted(classes)
    assert set(classes) == KNOWN_TABLES - {"baseline"}  # every table a config file may hold ("baseline": old name)
    for table, cls in classes.items():
        assert resolve(cls, doc, table) == cls(), table  # every key, nested groups included, round trips
    assert "[facade.planes]" in out


def test_a_parameter_without_default_value_is_a_comment() -> None:
    @dataclasses.dataclass(frozen=True)
    class Example:
        """Example.

        size (2.5): edge length.
        model (None): a file; none = the shipped one
        """

        size: float = 2.5
        names: tuple[str, ...] = ("a", "b")
        model: str | None = None

    assert table_toml(Example(), "example") == ["[example]", "size = 2.5  # edge length.", 'names = ["a", "b"]',
                                                "# model = (none: not set)  # a file; none = the shipped one …"]


def test_config_defaults_of_one_table_and_an_unknown_table() -> None:
    code, out, _ = run("config", "defaults", "voxel")
    assert code == 0 and out == defaults_toml("voxel") and out.startswith("[voxel]\nsize = 1.0  # voxel edge")
    assert list(tomllib.loads(out)) == ["voxel"]
    code, out, err = run("config", "defaults", "voxels")
    assert code == 2 and out == "" and err.startswith("error: unknown config table 'voxels' (known: prep, segment")


def test_shell_completion_completes_commands(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("_LIDARMAP_COMPLETE", "complete_bash")
    monkeypatch.setenv("COMP_WORDS", "lidarmap con")
    monkeypatch.setenv("COMP_CWORD", "1")
    code, out, _ = run()
    assert code == 0 and out.split() == ["config"]
    assert os.environ["COMP_WORDS"] == "lidarmap con"
