"""Where a frame sees map data: the frame pixels whose place on the map (under a pose) holds data.

Templates are chosen in the live frame before the map is consulted; near the edge of the
mapped area (a bundle's region or corridor, the strips where a left-out microscope tile
overlaps its neighbours, or a previous frame in relative mode) many would fall where the
map has no data. :func:`coverage_mask` tells the template selection where to look: the
map's data mask (pixels > 0) warped into the frame under the pose, shrunk by a margin that
covers the search radius and the template's half side. It costs a few lookups when the
map's tiles under the footprint are wholly covered (the common case, remembered per tile by
:meth:`tracker.tiles.TileCache.full`), one read and warp of the footprint otherwise.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from mapstore.grid import MapGrid, affine_box
from tracker.tiles import TileCache

__all__ = ["coverage_mask"]


def coverage_mask(tiles: TileCache, grid: MapGrid, pose: np.ndarray, shape: tuple[int, int], frame_pixel_size: float,
                  margin_px: int, valid: np.ndarray | None = None) -> tuple[np.ndarray | None, float]:
    """Frame pixels (``shape``, ``frame_pixel_size`` metres) that land on map data under
    ``pose`` (world frame) at least ``margin_px`` frame pixels from the data's edge, within
    ``valid``: ``(mask, fraction)``, the fraction of the valid pixels kept. ``mask`` is None
    when the map holds data under the whole footprint (nothing to exclude)."""
    h, w = shape
    m = int(margin_px)
    a = grid.frame_to_grid_affine(np.asarray(pose, float), shape, frame_pixel_size)
    # the frame padded by the margin: a template near the frame's edge searches beyond it
    u0, v0, u1, v1 = affine_box(a, -m, -m, w - 1 + m, h - 1 + m)
    c0, r0 = math.floor(u0) - 1, math.floor(v0) - 1
    c1, r1 = math.ceil(u1) + 2, math.ceil(v1) + 2
    if tiles.full(int(r0), int(r1), int(c0), int(c1)):
        return None, 1.0
    window = tiles.window(int(r0), int(r1), int(c0), int(c1))
    shifted = a.copy()
    shifted[:, 2] += a[:, :2] @ np.array([-m, -m], float) - (c0, r0)  # padded-canvas pixel -> window pixel
    mask = cv2.warpAffine((window > 0).astype(np.uint8), shifted, (w + 2 * m, h + 2 * m),
                          flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if m > 0:
        mask = cv2.erode(mask, np.ones((2 * m + 1, 2 * m + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                         borderValue=0)
    out = mask[m : m + h, m : m + w].astype(bool)
    if valid is not None:
        out &= valid
        return out, float(out.sum()) / max(int(valid.sum()), 1)
    return out, float(out.mean())
