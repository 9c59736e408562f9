"""Screenshots of the viewer for docs/viewer.md: ``python scripts/viewer_screenshots.py DELFT_RUN DEMO_OUT``.

DELFT_RUN: a ``lidarmap run`` folder of ../shared/data/ahn3_delft (see docs/pipeline.md); DEMO_OUT: a ``lidarmap
demo`` folder (its façade map ``city.lmap``). Writes docs/images/viewer_delft.png and docs/images/viewer_demo_map.png:
``lidarmap view`` pages opened in headless Chromium, one building picked (the panel shows its attributes).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

from lidarmap.browser import open_viewer
from lidarmap.export.gltf import glb_building_ids, read_glb_json

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"


def page_of(source: Path, page: Path) -> None:
    subprocess.run([sys.executable, "-m", "lidarmap", "view", str(source), "-o", str(page)], check=True)


def glb_of(page: Path) -> bytes:
    import base64
    import re

    text = page.read_text(encoding="utf-8")
    return base64.b64decode(re.search(r'id="lidarmap-glb"[^>]*>([^<]*)<', text).group(1))


def busiest_building(glb: bytes) -> str:
    """The building with the most windows (map) or the first one (run)."""
    tree = read_glb_json(glb)
    by_id = {n.get("extras", {}).get("id"): n.get("extras", {}) for n in tree["nodes"]}
    ids = glb_building_ids(glb)
    return max(ids, key=lambda i: by_id[i].get("lidarmap_windows") or 0)


def main(delft_run: Path, demo: Path) -> None:
    IMAGES.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for source, name in [(delft_run, "viewer_delft.png"), (demo / "city.lmap", "viewer_demo_map.png")]:
            page = Path(tmp) / "view.html"
            page_of(source, page)
            pick = busiest_building(glb_of(page))
            result = open_viewer(page, screenshot=IMAGES / name, pick=pick, size=(1280, 800))
            print(f"{IMAGES / name}: {result.count_shown} buildings, picked {result.picked}, drawn after "
                  f"{result.timings.get('drawn', float('nan')) / 1000:.2f} s")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
