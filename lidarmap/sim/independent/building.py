"""Roofs and interiors of the houses.

Roofs are flat slabs or gables with the ridge parallel to the street; either may overhang the street and back
walls (the eaves hide the top of the wall from below). Interiors exist so that pulses through glass find
something: storey floors (which are also ceilings), a back partition 2-6 m (shops 3-8 m) behind the street
wall on every storey, a ceiling under the roof and a few furniture boxes near the windows.
"""

from __future__ import annotations

import numpy as np

from .geometry import INTERIOR, ROOF, Materials, MeshBuilder, box_corners_tris, world_box
from .layout import House


def _yy(h: House, y: float) -> float:
    """Signed local y of a distance |y| from the axis on the house's side."""
    return h.side * y


def build_roof(rng, mb: MeshBuilder, mats: Materials, h: House) -> None:
    roof = mats.add(ROOF, refl=float(rng.uniform(0.08, 0.35)), relief=0.01)
    x0, x1, ez, ov = h.x0, h.x1, h.eave_z, h.overhang
    yf, yb = h.y_front - ov, h.y_back + ov
    if h.roof == "flat":
        ring = np.array([[x0, _yy(h, yf), ez], [x1, _yy(h, yf), ez], [x1, _yy(h, yb), ez], [x0, _yy(h, yb), ez]])
        mb.add(box_corners_tris(np.vstack([ring, ring + [0, 0, 0.3]])), roof)
        return
    tan = np.tan(h.pitch)
    ym = (h.y_front + h.y_back) / 2
    zr = ez + (ym - h.y_front) * tan
    zf, zb = ez - ov * tan, ez - ov * tan
    for y_edge, z_edge in ((yf, zf), (yb, zb)):
        q = np.array([[x0, _yy(h, y_edge), z_edge], [x1, _yy(h, y_edge), z_edge], [x1, _yy(h, ym), zr],
                      [x0, _yy(h, ym), zr]])
        mb.add(np.stack([q[[0, 1, 2]], q[[0, 2, 3]]]), roof)


def build_interior(rng, mb: MeshBuilder, mats: Materials, h: House) -> None:
    inner = mats.add(INTERIOR, refl=float(rng.uniform(0.3, 0.7)))
    x0, x1 = h.x0 + 0.25, h.x1 - 0.25
    f, b = h.y_front + 0.25, h.y_back - 0.25
    floors = [h.floor_z] + list(h.levels)
    tops = floors[1:] + [h.eave_z - 0.05]
    for z in floors + [h.eave_z - 0.05]:
        q = np.array([[x0, _yy(h, f), z], [x1, _yy(h, f), z], [x1, _yy(h, b), z], [x0, _yy(h, b), z]])
        mb.add(np.stack([q[[0, 1, 2]], q[[0, 2, 3]]]), inner)
    for k, (z0, z1) in enumerate(zip(floors, tops)):
        deep = rng.uniform(3.0, 8.0) if (k == 0 and h.shop) else rng.uniform(2.0, 6.0)
        yp = min(h.y_front + deep, b - 0.1)
        q = np.array([[x0, _yy(h, yp), z0], [x1, _yy(h, yp), z0], [x1, _yy(h, yp), z1], [x0, _yy(h, yp), z1]])
        mb.add(np.stack([q[[0, 1, 2]], q[[0, 2, 3]]]), inner)
        for _ in range(int(rng.integers(2, 5))):
            size = (rng.uniform(0.5, 1.6), rng.uniform(0.4, 0.9), rng.uniform(0.45, 1.9))
            if x1 - x0 < size[0] + 0.2 or yp - h.y_front < 1.2:
                continue
            x = rng.uniform(x0 + size[0] / 2, x1 - size[0] / 2)
            y = rng.uniform(h.y_front + 0.6, max(h.y_front + 0.7, yp - 0.5))
            mb.add(world_box((x, _yy(h, y), z0), size), mats.add(INTERIOR, refl=float(rng.uniform(0.1, 0.8))))
