"""Scale: ``lidarmap run`` end to end on a city of real tiles: throughput for 1 and 2 local workers and a 3-process
cluster on loopback, scaling efficiency, and peak memory (main process and each worker) on a 20 M-point input.

``python benchmarks/bench_scale.py [--copies 4] [--big-copies 32] [--skip-big]`` prints one markdown section.

The city is the real AHN3 Delft extract (640,510 points, 160 BGT footprints) laid out ``copies`` times on a grid
(250 m apart, footprint ids suffixed): one LAZ tile per copy, as a national archive delivers them. The named
baseline is the serial run (``--workers 1``) in the same invocation; scaling efficiency = T(serial) / (N x T(N)).
Peak RSS is sampled every 0.2 s over the whole process tree (psutil): the ``lidarmap run`` process and every dask
worker process. Target (issue #7): peak RSS < 4 GB on a 20 M-point input.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import psutil
import shapely
from shapely.affinity import translate

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("LIDARMAP_DATA", ROOT.parent / "shared" / "data")) / "ahn3_delft"
STEP = 250.0  # m between copies (the extract spans ~192 m x 228 m)


def make_city(out: Path, copies: int) -> tuple[list[Path], Path, int]:
    """``copies`` LAZ tiles of the Delft extract on a grid + their footprints; (tiles, footprints, points)."""
    out.mkdir(parents=True, exist_ok=True)
    source = laspy.read(DATA / "ahn3_cropped_1.laz")
    doc = json.loads((DATA / "footprints_bgt_EPSG28992.geojson").read_text())
    cols = int(np.ceil(np.sqrt(copies)))
    tiles, features = [], []
    for k in range(copies):
        dx, dy = STEP * (k % cols), STEP * (k // cols)
        header = laspy.LasHeader(point_format=source.header.point_format, version=source.header.version)
        header.scales = source.header.scales
        header.offsets = np.asarray(source.header.offsets) + [dx, dy, 0.0]  # same integers, shifted coordinates
        tile = laspy.LasData(header)
        tile.points = source.points.copy()
        path = out / f"delft_{k:03d}.laz"
        tile.write(path)
        tiles.append(path)
        for f in doc["features"]:
            g = translate(shapely.geometry.shape(f["geometry"]), dx, dy)
            props = dict(f["properties"], bag_pand_id=f"{f['properties']['bag_pand_id']}_{k}")
            features.append({"type": "Feature", "properties": props, "geometry": shapely.geometry.mapping(g)})
    footprints = out / "footprints.geojson"
    footprints.write_text(json.dumps({"type": "FeatureCollection", "crs": doc["crs"], "features": features}))
    return tiles, footprints, copies * len(source.points)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_measured(cmd: list[str], env: dict | None = None) -> dict:
    """Run ``cmd``; wall time, peak RSS of the main process and of every other process of its tree."""
    started = time.perf_counter()
    log = tempfile.TemporaryFile()  # not a pipe: a full pipe would block the run (its table is long)
    proc = subprocess.Popen(cmd, stdout=log, stderr=log, env=env)
    main = psutil.Process(proc.pid)
    peaks: dict[int, int] = {}
    tree = 0
    while proc.poll() is None:
        try:
            now = 0
            for p in [main, *main.children(recursive=True)]:
                try:
                    rss = p.memory_info().rss
                except psutil.Error:
                    continue
                peaks[p.pid] = max(peaks.get(p.pid, 0), rss)
                now += rss
            tree = max(tree, now)  # the tree's simultaneous total, not the sum of peaks at different times
        except psutil.Error:
            pass
        time.sleep(0.2)
    proc.wait()
    seconds = time.perf_counter() - started
    log.seek(0)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{log.read().decode()[-2000:]}")
    others = [v for pid, v in peaks.items() if pid != proc.pid]
    return {"seconds": seconds, "main_rss": peaks.get(proc.pid, 0), "worker_rss": max(others, default=0),
            "tree_rss": tree}


def lidarmap_run(tiles: list[Path], footprints: Path, out: Path, *extra: str) -> list[str]:
    shutil.rmtree(out, ignore_errors=True)
    return [sys.executable, "-m", "lidarmap", "run", *map(str, tiles), "-f", str(footprints), "--id-field",
            "bag_pand_id", "--crs", "EPSG:28992", "-o", str(out), *extra]


def loopback_cluster(n: int) -> tuple[str, list[subprocess.Popen]]:
    """``dask scheduler`` + ``n`` x ``dask worker --nthreads 1``, as a user starts them on a cluster."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    procs = [subprocess.Popen([*dask, "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    worker = [sys.executable, "-m", "distributed.cli.dask_worker"]
    time.sleep(2)
    for _ in range(n):
        procs.append(subprocess.Popen([*worker, address, "--nthreads", "1", "--nworkers", "1"], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    from distributed import Client

    with Client(address, timeout=30) as client:
        client.wait_for_workers(n, timeout=60)
    return address, procs


def cluster_rss(procs: list[subprocess.Popen]) -> int:
    peak = 0
    for p in procs[1:]:
        for q in [psutil.Process(p.pid), *psutil.Process(p.pid).children(recursive=True)]:
            try:
                peak = max(peak, q.memory_info().rss)
            except psutil.Error:
                pass
    return peak


def same_outputs(a: Path, b: Path) -> bool:
    names = sorted(p.name for p in (a / "buildings").iterdir())
    return names == sorted(p.name for p in (b / "buildings").iterdir()) and all(
        (a / "buildings" / n / f).read_bytes() == (b / "buildings" / n / f).read_bytes()
        for n in names for f in ("points.laz", "voxels.npz"))


def gb(v: float) -> str:
    return f"{v / 2**30:.2f}"


def throughput(tmp: Path, copies: int) -> tuple[int, list[str]]:
    """Serial (baseline), 2 local workers and a 3-process loopback cluster on the same city: the table rows."""
    tiles, fps, n = make_city(tmp / "city", copies)
    runs: dict[str, tuple[dict, Path]] = {}
    for label, extra in (("serial (`--workers 1`, baseline)", ()),
                         ("`--workers 2` (LocalCluster)", ("--workers", "2"))):
        out = tmp / f"out{len(runs)}"
        runs[label] = (run_measured(lidarmap_run(tiles, fps, out, *extra)), out)
    address, procs = loopback_cluster(3)
    try:
        out = tmp / "out_cluster"
        m = run_measured(lidarmap_run(tiles, fps, out, "--scheduler", address))
        m["worker_rss"] = cluster_rss(procs)
        runs["3-process cluster on loopback (`--scheduler`)"] = (m, out)
    finally:
        for p in procs[::-1]:
            p.terminate()
    (base, base_out), rows = next(iter(runs.values())), []
    for (label, (m, out)), workers in zip(runs.items(), (1, 2, 3)):
        speedup = base["seconds"] / m["seconds"]
        worker = gb(m["worker_rss"]) if m["worker_rss"] else "–"
        rows.append(f"| {label} | {m['seconds']:.1f} | {n / m['seconds']:,.0f} | {speedup:.2f}x | "
                    f"{speedup / workers:.0%} | {gb(m['main_rss'])} | {worker} | "
                    f"{'yes' if same_outputs(base_out, out) else 'NO'} |")
    for _, out in runs.values():
        shutil.rmtree(out, ignore_errors=True)
    return n, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--copies", type=int, default=4, help="tiles of the throughput city (default 4: 2.56 M pts)")
    parser.add_argument("--big-copies", type=int, default=32, help="tiles of the memory city (32: 20.5 M points)")
    parser.add_argument("--skip-big", action="store_true", help="skip the 20 M-point memory run")
    parser.add_argument("--big-only", action="store_true", help="only the 20 M-point memory run")
    args = parser.parse_args()
    rows, big = [], None
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
        if not args.big_only:
            n, rows = throughput(Path(tmp), args.copies)
        if not args.skip_big:
            tiles, fps, n_big = make_city(Path(tmp) / "big", args.big_copies)
            big = (n_big, run_measured(lidarmap_run(tiles, fps, Path(tmp) / "out_big", "--workers", "2")))
    cpu = platform.processor() or platform.machine()
    print("## bench_scale\n")
    print(f"{time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores ({cpu}), "
          f"{psutil.virtual_memory().total / 2**30:.0f} GiB.\n")
    if rows:
        print(f"City: {args.copies} copies of AHN3 Delft ({n:,} points, {args.copies} LAZ tiles, "
              f"{160 * args.copies} footprints), default parameters.\n")
        print("| run | s | points/s end to end | speed-up | scaling efficiency | peak RSS main (GB) | "
              "peak RSS per worker (GB) | same outputs as serial |")
        print("|---|---:|---:|---:|---:|---:|---:|---|")
        print("\n".join(rows))
    if big is not None:
        n_big, m = big
        print(f"\nMemory on a {n_big / 1e6:.1f} M-point input ({args.big_copies} tiles, `--workers 2`): "
              f"{m['seconds']:.0f} s ({n_big / m['seconds']:,.0f} points/s); peak RSS of the `lidarmap run` "
              f"process {gb(m['main_rss'])} GB, of the largest worker {gb(m['worker_rss'])} GB; the whole "
              f"process tree (run, 2 workers, their nannies, the scheduler) {gb(m['tree_rss'])} GB at its peak "
              f"(target < 4 GB).")


if __name__ == "__main__":
    main()
