"""The package's shape: no import cycles, data flowing one way, complete package data, the README's first command."""

from __future__ import annotations

import ast
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "lidarmap"


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _imports() -> dict[str, set[str]]:
    """Every lidarmap module and the lidarmap modules it imports (lazy imports inside functions included)."""
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets |= {resolve(a.name) for a in node.names if a.name.startswith("lidarmap")}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("lidarmap"):
                targets |= {resolve(f"{node.module}.{a.name}") for a in node.names}
        graph[name] = {t for t in targets if t and t != name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(root: str) -> None:
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    out.append(sorted(component))

    for name in sorted(graph):
        if name not in index:
            visit(name)
    return out


def test_no_import_cycles():
    assert _cycles(_imports()) == []


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]


# (importer prefix, prefix it must not import): data flows io -> prep -> segment -> densify/flatten -> voxel/mesh
# and facade (one campaign's observation) -> map (fusion, store); the simulator never uses what it judges.
FORBIDDEN = [
    ("lidarmap.facade", "lidarmap.map"),
    ("lidarmap.facade", "lidarmap.aerial"),
    ("lidarmap.io", "lidarmap.aerial"),
    ("lidarmap.io", "lidarmap.facade"),
    ("lidarmap.io", "lidarmap.map"),
    ("lidarmap.io", "lidarmap.segment"),
    ("lidarmap.io", "lidarmap.cli"),
    ("lidarmap.core", "lidarmap.aerial"),
    ("lidarmap.segment", "lidarmap.aerial"),
    ("lidarmap.segment", "lidarmap.map"),
    ("lidarmap.aerial", "lidarmap.map"),
    ("lidarmap.aerial", "lidarmap.facade"),
    ("lidarmap.map", "lidarmap.aerial.pipeline"),
    ("lidarmap.sim", "lidarmap.aerial"),
    ("lidarmap.sim", "lidarmap.map"),
    ("lidarmap.sim", "lidarmap.io.meshfile"),
]


@pytest.mark.parametrize("importer,imported", FORBIDDEN)
def test_data_flows_one_way(importer, imported):
    bad = sorted(f"{m} -> {t}" for m, targets in _imports().items() if m.startswith(importer)
                 for t in targets if t == imported or t.startswith(imported + "."))
    assert bad == []


def test_only_the_cli_and_pipelines_write_files_stages_take_arrays():
    """Stage modules hold no file writers: their public functions take no path arguments."""
    stages = ["lidarmap/aerial/prep.py", "lidarmap/aerial/densify.py", "lidarmap/aerial/flatten.py",
              "lidarmap/aerial/voxel.py", "lidarmap/aerial/mesh.py", *map(str, (PACKAGE / "facade").glob("*.py"))]
    offenders = []
    for rel in stages:
        path = ROOT / rel
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
                for arg in node.args.args:
                    # work_dir: scratch space for bounded memory (a spool), not an output
                    if arg.annotation is not None and "Path" in ast.unparse(arg.annotation) and arg.arg != "work_dir":
                        offenders.append(f"{rel}: {node.name}({arg.arg})")
    assert offenders == []


# ----------------------------------------------------------------------------------------------------------------------
# Packaging


@pytest.mark.slow
def test_wheel_holds_the_shipped_weights_and_schemas(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                           str(tmp_path), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    wheel = next(tmp_path.glob("lidarmap-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {str(p.relative_to(ROOT)).replace("\\", "/") for p in PACKAGE.rglob("*")
               if p.is_file() and p.suffix in (".pt", ".joblib", ".json") and "__pycache__" not in p.parts}
    assert shipped and shipped <= names, sorted(shipped - names)
    assert "lidarmap/py.typed" in names
    viewer = {"lidarmap/viewer/static/viewer.bundle.js", "lidarmap/viewer/templates/viewer.html",
              "lidarmap/viewer/THREE_LICENSE", "lidarmap/viewer/src/viewer.js"}  # the page's script, its licence
    assert viewer <= names, sorted(viewer - names)
    modules = {str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py")}
    assert modules <= names, sorted(modules - names)[:5]


# ----------------------------------------------------------------------------------------------------------------------
# The README's first command, on a reduced scene


@pytest.mark.slow
def test_demo_runs_end_to_end_on_a_reduced_scene(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "lidarmap", "demo", "-o", str(out), "--buildings", "3",
                           "--campaigns", "2", "--seed", "11"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (proc.stdout[-2000:], proc.stderr[-2000:])
    assert "demo done" in proc.stdout
    assert (out / "city.lmap").is_file() and (out / "city.city.json").is_file()
    buildings = [p for p in (out / "aerial" / "buildings").iterdir() if (p / "mesh.ply").is_file()]
    assert len(buildings) >= 2
    # run's glb: one node per reconstructed building; the demo's viewer page, its path printed
    from lidarmap.export.gltf import glb_building_ids

    assert sorted(glb_building_ids((out / "aerial" / "buildings.glb").read_bytes())) == sorted(p.name for p in buildings)
    assert f"viewer page: {(out / 'view.html').resolve()}" in proc.stdout.replace("\n", "")
    # the façade table scores every campaign against the truth: two rows with a window F1 of at least 0.8
    lines = proc.stdout.splitlines()
    table = lines[next(i for i, line in enumerate(lines) if "window F1" in line):]
    rows = [line.split("│") for line in table[:next(i for i, line in enumerate(table) if line.startswith("└"))]
            if line.startswith("│")]
    f1 = [float(cells[2]) for cells in rows]
    assert len(f1) == 2 and min(f1) >= 0.8, proc.stdout[-3000:]
