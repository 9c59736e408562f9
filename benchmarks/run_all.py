"""Run every benchmark and write docs/benchmarks.md: ``python benchmarks/run_all.py [NAME ...]``.

Each ``benchmarks/bench_*.py`` is run as its own process (so timings do not share warm caches) and prints one
markdown section to stdout: its figures next to the named baseline measured in the same run. ``delft_before_after.py``
(the whole pipeline on real AHN3 data, with a picture in ``docs/images/``) runs last. This script adds the
machine and the date, and keeps the sections of benchmarks that were not re-run.
"""

from __future__ import annotations

import datetime
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
MARK = "<!-- bench:{name} -->"


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 1024**2:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    import numpy
    import torch
    return (f"{cpu}, {os.cpu_count()} cores{mem}; Python {platform.python_version()}, numpy {numpy.__version__}, "
            f"torch {torch.__version__}")


def existing_sections() -> dict[str, str]:
    if not DOC.exists():
        return {}
    text = DOC.read_text()
    parts = re.split(r"<!-- bench:([\w-]+) -->\n", text)
    return {parts[i]: parts[i + 1].rstrip() + "\n" for i in range(1, len(parts) - 1, 2)}


#: Benchmarks scored on reserved evaluation seeds (docs/simulator.md, docs/independent_scenes.md) when run from here.
EVAL_BENCHMARKS = ("bench_facade", "bench_refine", "bench_independent")


def run(script: Path) -> str:
    started = time.perf_counter()
    flags = ["--eval"] if script.stem in EVAL_BENCHMARKS else []
    proc = subprocess.run([sys.executable, str(script), *flags], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "PYTHONHASHSEED": "0"})
    took = time.perf_counter() - started
    stamp = f"_{datetime.date.today().isoformat()}, {machine()}, {took:.0f} s_\n\n"
    if proc.returncode != 0:
        tail = "\n".join(proc.stderr.strip().splitlines()[-15:])
        return f"## {script.stem}\n\n{stamp}**failed** (exit {proc.returncode}):\n\n```\n{tail}\n```\n"
    body = proc.stdout.strip()
    if body.startswith("## "):  # put the stamp under the section title
        title, _, rest = body.partition("\n")
        return f"{title}\n\n{stamp}{rest.strip()}\n"
    return f"## {script.stem}\n\n{stamp}{body}\n"


def main(names: list[str]) -> None:
    scripts = sorted((ROOT / "benchmarks").glob("bench_*.py")) + [ROOT / "benchmarks" / "delft_before_after.py"]
    if names:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in names or s.stem in names]
    sections = existing_sections()
    for script in scripts:
        print(f"running {script.name} ...", file=sys.stderr, flush=True)
        sections[script.stem] = run(script)
    header = ("# Benchmarks\n\nFigures from `python benchmarks/run_all.py` (one section per `benchmarks/bench_*.py`; "
              "each compares against a named baseline measured in the same run). Absolute times on shared machines "
              "are noise: read the ratios.\n\n")
    body = "\n".join(f"{MARK.format(name=name)}\n{text}" for name, text in sorted(sections.items()))
    DOC.parent.mkdir(exist_ok=True)
    DOC.write_text(header + body)
    print(f"wrote {DOC}", file=sys.stderr)


if __name__ == "__main__":
    main(sys.argv[1:])
