"""glTF output and the viewer page on the AHN3 Delft run (125 buildings), against cjio's glb export of the same run.

``python benchmarks/bench_viewer.py [--run DIR]`` uses a finished ``lidarmap run`` folder (else runs one on
``../shared/data/ahn3_delft`` into a temporary folder: a few minutes) and measures, in the same process:

* ours: ``write_run_glb`` (reads every mesh.ply, splits by surface kind, writes OUT/buildings.glb) - what ``run`` does
  at its end; baseline: ``cjio buildings.city.json export glb`` (the route before this viewer), when cjio is installed;
* file sizes, and the vertex error against the PLY meshes (float64): every PLY vertex to the nearest vertex of the
  glb, after the glb's node transforms (ours: the local origin undone; cjio: as written);
* the viewer page (``lidarmap view``) in headless Chromium (SwiftShader WebGL): the page's own time from navigation
  start to the first drawn frame, and the driver's time from ``goto`` to ready; the building count it shows.

Targets (issue 17): glb in < 2 s, within 1 mm of the PLY meshes; the page loads and draws in < 5 s.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from lidarmap.aerial.pipeline import building_dir, run_folders, write_run_glb
from lidarmap.export.gltf import glb_building_ids
from lidarmap.viewer import viewer_page

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("LIDARMAP_DATA", ROOT.parent / "shared" / "data")) / "ahn3_delft"
Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def delft_run(work: Path) -> Path:
    out = work / "delft_run"
    subprocess.run([sys.executable, "-m", "lidarmap", "run", str(DATA / "ahn3_cropped_1.laz"), "-f",
                    str(DATA / "footprints_bgt_EPSG28992.geojson"), "--crs", "EPSG:28992", "--id-field",
                    "bag_pand_id", "-o", str(out)], check=True, capture_output=True)
    return out


def glb_world_vertices(path: Path) -> np.ndarray:
    """Every vertex of a glb with its node transforms applied (float64)."""
    scene = trimesh.load(io.BytesIO(path.read_bytes()), file_type="glb")
    parts = []
    for node in scene.graph.nodes_geometry:
        matrix, geometry = scene.graph[node]
        parts.append(trimesh.transform_points(np.asarray(scene.geometry[geometry].vertices, np.float64), matrix))
    return np.vstack(parts)


def vertex_error(run: Path, folders: list[str], glb: Path) -> float:
    """Max over the PLY vertices of the distance to the nearest glb vertex (m); the better of z-up / y-up."""
    ply = np.vstack([trimesh.load(building_dir(run, f) / "mesh.ply", process=False).vertices for f in folders])
    world = glb_world_vertices(glb)
    best = np.inf
    for to_crs in (np.eye(4), np.linalg.inv(Y_UP)):
        tree = cKDTree(trimesh.transform_points(world, to_crs))
        best = min(best, float(tree.query(ply)[0].max()))
    return best


def timed(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="a finished 'lidarmap run' folder of the Delft data")
    parser.add_argument("--cjio-timeout", type=float, default=600.0, help="stop cjio after this many seconds")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        run = args.run or delft_run(work)
        summary = json.loads((run / "summary.json").read_text())
        records, crs = summary["records"], summary.get("crs") or ""
        stems = run_folders(summary)
        copy = work / "run"  # write into a copy: the run folder is left as it is
        for r in records:
            shutil.copytree(building_dir(run, stems[r["id"]]), building_dir(copy, stems[r["id"]]))
        ours = copy / "buildings.glb"
        t_ours = timed(lambda: write_run_glb(copy, records, stems, (), crs))
        err_ours = vertex_error(run, [stems[r["id"]] for r in records], ours)
        n_ids = len(glb_building_ids(ours.read_bytes()))
        rows = [("lidarmap `write_run_glb` (what `run` does)", t_ours, ours.stat().st_size, err_ours)]
        page = work / "view.html"
        page.write_text(viewer_page(ours.read_bytes(), "Delft"), encoding="utf-8")
        browser = page_figures(page, records[0]["id"])
        cjio = shutil.which("cjio")
        if cjio and (run / "buildings.city.json").is_file():
            rows.append(cjio_row(cjio, run, [stems[r["id"]] for r in records], work / "cjio.glb", args.cjio_timeout))

    print("## bench_viewer\n")
    print(f"AHN3 Delft run: {len(records)} buildings ({sum(r['mesh_faces']['surface'] for r in records):,} mesh "
          f"triangles), {n_ids} building nodes in our glb. Vertex error: max over every PLY vertex (float64) of the "
          "distance to the nearest glb vertex after the glb's transforms. Times: median of 3 (cjio: 1 run, CityJSON with LoD1 blocks + LoD2.2 meshes).\n")
    print("| route | seconds | file MB | max vertex error (mm) |")
    print("|---|---:|---:|---:|")
    for name, seconds, size, err in rows:
        if size is None:
            print(f"| {name} | > {seconds:.0f} (stopped) | - | - |")
        else:
            print(f"| {name} | {seconds:.2f} | {size / 1e6:.2f} | {1000 * err:.3f} |")
    print(f"\nViewer page ({page_mb(browser)} MB, self-contained) in headless Chromium "
          f"({browser['version']}, SwiftShader WebGL, 1200x800), {len(browser['runs'])} loads:\n")
    print("| load | page: navigation -> first frame drawn (s) | driver: goto -> ready (s) | count shown | pick |")
    print("|---:|---:|---:|---:|---|")
    for k, r in enumerate(browser["runs"], 1):
        print(f"| {k} | {r.timings['drawn'] / 1000:.2f} | {r.ready_seconds:.2f} | {r.count_shown} | "
              f"{'ok' if r.picked == records[0]['id'] else r.picked} |")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"\nLoad average at the end (1, 5, 15 min): {load} on {os.cpu_count()} cores.")
    print("\nTargets: glb < 2 s, within 1 mm of the PLY meshes; the page draws in < 5 s.")


def cjio_row(cjio: str, run: Path, folders: list[str], theirs: Path, timeout: float) -> tuple:
    """The baseline: cjio's glb export of the run's CityJSON (one run; stopped after ``timeout`` s)."""
    started = time.perf_counter()
    try:
        subprocess.run([cjio, "--suppress_msg", str(run / "buildings.city.json"), "export", "glb", str(theirs)],
                       check=True, capture_output=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return ("baseline: `cjio buildings.city.json export glb`", timeout, None, None)
    seconds = time.perf_counter() - started
    return ("baseline: `cjio buildings.city.json export glb`", seconds, theirs.stat().st_size,
            vertex_error(run, folders, theirs))


def page_mb(browser: dict) -> str:
    return f"{browser['size'] / 1e6:.1f}"


def page_figures(page: Path, pick: str, loads: int = 2) -> dict:
    from playwright.sync_api import sync_playwright

    from lidarmap.browser import CHROMIUM_ARGS, find_chromium, open_viewer

    chromium = find_chromium()
    if chromium is None:
        raise SystemExit("no Chromium: apt-get install chromium (or set LIDARMAP_CHROMIUM)")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium, args=list(CHROMIUM_ARGS))
        version = b.version
        b.close()
    runs = [open_viewer(page, pick=pick) for _ in range(loads)]
    return {"runs": runs, "version": f"Chromium {version}", "size": page.stat().st_size}


if __name__ == "__main__":
    main()
