"""A headless Chromium for the viewer page: find it, open a page, wait for the scene, screenshot it.

Used by the tests, the benchmark and the docs' screenshots (never by the pipeline). The browser is the system's
(``chromium`` from the distribution; ``LIDARMAP_CHROMIUM`` names another executable) driven by playwright
(``pip install playwright``; no browser download needed). WebGL runs on the CPU with SwiftShader.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from pathlib import Path
from typing import Any

__all__ = ["CHROMIUM_ARGS", "CHROMIUM_NAMES", "PageResult", "find_chromium", "open_viewer"]

#: Executables tried in this order (after ``LIDARMAP_CHROMIUM``).
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
#: Software WebGL (no GPU in CI containers).
CHROMIUM_ARGS = ("--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                 "--no-sandbox", "--disable-gpu-watchdog")


def find_chromium() -> str | None:
    """Path of a Chromium executable (``LIDARMAP_CHROMIUM`` first, then :data:`CHROMIUM_NAMES` on PATH), or None."""
    named = os.environ.get("LIDARMAP_CHROMIUM")
    if named:
        return shutil.which(named) or (named if Path(named).is_file() else None)
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclasses.dataclass
class PageResult:
    """What a viewer page showed: seconds to the first drawn frame (navigation start to ``lidarmapViewerReady``),
    the building count it displayed, the picked id (if a pick was asked), an error text, the browser console and
    the page's own timings (ms from navigation start: script, decoded, parsed, drawn)."""

    ready_seconds: float
    count_shown: str
    picked: str | None
    error: str | None
    console: list[str]
    timings: dict[str, float]


def open_viewer(page_path: str | Path, screenshot: str | Path | None = None, pick: str | None = None,
                size: tuple[int, int] = (1200, 800), timeout_s: float = 60.0, hide: tuple[str, ...] = (),
                hidden_screenshot: str | Path | None = None) -> PageResult:
    """Open a viewer page from file:// in headless Chromium, wait for its scene, optionally click on building
    ``pick`` (at a pixel the page says hits it) and save a PNG screenshot; then untick the ``hide`` toggles
    ("roofs", "walls", "openings", "unknown") and save ``hidden_screenshot``. RuntimeError without a browser."""
    from playwright.sync_api import sync_playwright

    chromium = find_chromium()
    if chromium is None:
        raise RuntimeError("no Chromium found (install the 'chromium' package or set LIDARMAP_CHROMIUM)")
    url = Path(page_path).resolve().as_uri()
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=list(CHROMIUM_ARGS))
        try:
            page = browser.new_page(viewport={"width": size[0], "height": size[1]})
            console: list[str] = []
            page.on("console", lambda msg: console.append(f"{msg.type}: {msg.text}"))
            page.on("pageerror", lambda exc: console.append(f"pageerror: {exc}"))
            started = time.perf_counter()
            page.goto(url, wait_until="load", timeout=timeout_s * 1000)
            page.wait_for_function("window.lidarmapViewerReady === true || window.lidarmapViewerError !== undefined",
                                   timeout=timeout_s * 1000, polling=50)
            ready = time.perf_counter() - started
            error = page.evaluate("window.lidarmapViewerError ?? null")
            timings = page.evaluate("window.lidarmapViewerTimings ?? {}")
            picked = _pick(page, pick) if pick is not None and error is None else None
            count = page.inner_text("#building-count")
            if screenshot is not None:
                page.screenshot(path=str(screenshot))
            for name in hide:
                page.uncheck(f"#toggle-{name}")
            if hidden_screenshot is not None:
                page.screenshot(path=str(hidden_screenshot))
            if error is None and page.evaluate("window.lidarmapViewer.renderer.getContext().isContextLost()"):
                error = "the page lost its WebGL context (its screenshots may be blank)"
            return PageResult(ready, count, picked, error, console, timings)
        finally:
            browser.close()


def _pick(page: Any, building_id: str) -> str | None:
    """Click where the page says building ``building_id`` is; the id the panel then shows (None: not visible)."""
    point = page.evaluate("id => window.lidarmapViewer.screenPointOf(id)", building_id)
    if point is None:
        return None
    box = page.locator("#view canvas").bounding_box()
    page.mouse.click(box["x"] + point["x"], box["y"] + point["y"])
    page.wait_for_selector("#picked-id", timeout=5000)
    return page.inner_text("#picked-id")
