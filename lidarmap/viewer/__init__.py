"""The viewer page: one self-contained HTML file (no server, no network) showing a glb of buildings in 3D.

The page inlines the glb (base64), a small JSON block (title, campaigns) and ``static/viewer.bundle.js``: our
``src/viewer.js`` bundled with three.js (MIT licence in ``THREE_LICENSE``), its GLTFLoader and OrbitControls by
``scripts/build_viewer.sh``. The page sets ``window.lidarmapViewerReady = true`` once the scene is drawn (or
``window.lidarmapViewerError``), shows the building count in ``#building-count`` and the picked building in
``#building-panel`` (``#picked-id``); ``window.lidarmapViewer.screenPointOf(id)`` gives a pixel where a click hits a
building (for tests). See docs/viewer.md.
"""

from __future__ import annotations

import base64
import html
import json
import re
from importlib import resources
from typing import Any

from lidarmap._version import __version__

__all__ = ["THREE_VERSION", "bundle_text", "viewer_page"]

#: three.js release bundled in static/viewer.bundle.js (pinned in scripts/build_viewer.sh).
THREE_VERSION = "0.170.0"


def _resource(*parts: str) -> str:
    return resources.files(__name__).joinpath(*parts).read_text(encoding="utf-8")


def bundle_text() -> str:
    """The bundled viewer script (package data)."""
    return _resource("static", "viewer.bundle.js")


def _script_safe(text: str) -> str:
    """Text that cannot end the ``<script>`` element it is inlined in (``</`` -> ``<\\/``, valid in JSON and JS
    strings)."""
    return text.replace("</", "<\\/")


def viewer_page(glb: bytes, title: str, campaigns: list[dict[str, Any]] | None = None) -> str:
    """The HTML of a viewer page for ``glb`` (see the module docstring); ``campaigns``: the map's campaigns (dicts
    with campaign_id, kind, source, created), listed in the page."""
    from lidarmap.export.gltf import EPSILON_FULL

    data = {"title": title, "campaigns": campaigns or [], "lidarmap": __version__}
    values = {
        "VERSION": html.escape(__version__),
        "TITLE": html.escape(title),
        "EPSILON_FULL": f"{EPSILON_FULL:g}",
        "DATA": _script_safe(json.dumps(data, ensure_ascii=False, allow_nan=False)),
        "GLB": base64.b64encode(glb).decode("ascii"),
        "BUNDLE": _script_safe(bundle_text()),
    }
    # one pass: inserted text (the bundle) is never scanned for placeholders again
    return re.sub(r"\{\{([A-Z_]+)\}\}", lambda m: values[m.group(1)], _resource("templates", "viewer.html"))
