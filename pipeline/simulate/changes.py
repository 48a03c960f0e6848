"""Floor changes between drive days: stains, repainted patches, new markings.

Each change blends new content into the world texture with a soft weight ``w`` in [0, 1]
(``new = old (1 - w) + content w``) inside a crop around it, then band-limits the
difference, so the texture is unchanged (bit for bit) outside the crops and stays
band-limited. The ground-truth change mask is ``w >= mask_weight``. Sizes are metres, grey
levels on the 0..255 scale, raster geometry from :class:`mapstore.grid.MapGrid`.
"""

from __future__ import annotations

import numpy as np

from mapstore.grid import MapGrid
from pipeline.simulate.texture import _soft_ellipse, _soft_polygon, band_limit, smooth_noise

__all__ = ["KINDS", "apply_changes"]

KINDS = ("stain", "repaint", "marking")


def _corners(cx: float, cy: float, lx: float, ly: float, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    local = np.array([[-lx, -ly], [lx, -ly], [lx, ly], [-lx, ly]]) / 2.0
    return np.stack([cx + c * local[:, 0] - s * local[:, 1], cy + s * local[:, 0] + c * local[:, 1]], axis=1)


def apply_changes(
    texture: np.ndarray,
    grid: MapGrid,
    area: tuple[float, float],
    n: int,
    rng: np.random.Generator,
    cfg: dict,
    band_limit_sigma_px: float,
) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Apply ``n`` random changes centred inside ``[0, area_x] x [0, area_y]``.

    Args:
        texture: float32 world texture on ``grid`` (not modified).
        cfg: the ``[simulate.floor.change_kinds]`` table.
        band_limit_sigma_px: the texture's band limit (pixels), applied to each change.

    Returns:
        ``(new_texture, mask, changes)``: float32 texture, uint8 mask (0/255) on ``grid``,
        and per change ``{"kind", "bbox_m": [xmin, ymin, xmax, ymax], "area_m2"}`` (bbox of
        the region where the texture may differ, area of the masked pixels).
    """
    s = grid.pixel_size
    h, w = grid.shape
    tex = texture.astype(np.float32, copy=True)
    mask = np.zeros(grid.shape, np.uint8)
    weights = np.asarray(cfg["weights"], float)
    edge_px = cfg["edge_m"] / s
    pad = int(np.ceil(3 * max(edge_px, 0.5) + 4 * band_limit_sigma_px)) + 2
    changes: list[dict] = []
    for _ in range(n):
        kind = KINDS[int(rng.choice(len(KINDS), p=weights / weights.sum()))]
        cx_m, cy_m = rng.uniform(0, area[0]), rng.uniform(0, area[1])
        ccol, crow = grid.world_to_pixel(cx_m, cy_m)
        a = float(rng.uniform(0, np.pi))
        if kind == "stain":
            d = rng.uniform(*cfg["stain_size_m"]) / s
            axes = (d / 2, d / 2 * rng.uniform(0.5, 1.0))
            half = max(axes)
        elif kind == "repaint":
            area_px = rng.uniform(*cfg["repaint_area_m2"]) / s**2
            aspect = rng.uniform(0.6, 1.6)
            lx, ly = np.sqrt(area_px * aspect), np.sqrt(area_px / aspect)
            half = 0.5 * np.hypot(lx, ly)
        else:
            length = rng.uniform(*cfg["marking_length_m"]) / s
            width = rng.uniform(*cfg["marking_width_m"]) / s
            half = 0.5 * np.hypot(length, width)
        x0, y0 = max(0, int(np.floor(ccol - half)) - pad), max(0, int(np.floor(crow - half)) - pad)
        x1, y1 = min(w, int(np.ceil(ccol + half)) + pad + 1), min(h, int(np.ceil(crow + half)) + pad + 1)
        shape = (y1 - y0, x1 - x0)
        lc, lr = ccol - x0, crow - y0
        old = tex[y0:y1, x0:x1]
        if kind == "stain":
            wgt = _soft_ellipse(shape, (lc, lr), axes, np.degrees(a), edge_px)
            c = rng.uniform(*cfg["stain_contrast"]) * (1 if rng.random() < 0.5 else -1)
            content = old + np.float32(c)
        elif kind == "repaint":
            wgt = _soft_polygon(shape, _corners(lc, lr, lx, ly, a), edge_px)
            grain = smooth_noise(rng, shape, 1.0)
            content = np.float32(rng.uniform(*cfg["repaint_mean"])) + np.float32(cfg["repaint_std"]) * grain
        else:
            wgt = _soft_polygon(shape, _corners(lc, lr, length, width, a), edge_px)
            content = np.full(shape, np.float32(rng.uniform(*cfg["marking_level"])))
        delta = band_limit(wgt * (content - old), band_limit_sigma_px)
        tex[y0:y1, x0:x1] = np.clip(old + delta, 0.0, 255.0)
        m = wgt >= cfg["mask_weight"]
        mask[y0:y1, x0:x1][m] = 255
        xa, ya = grid.pixel_to_world(x0 - 0.5, y1 - 0.5)
        xb, yb = grid.pixel_to_world(x1 - 0.5, y0 - 0.5)
        changes.append(
            {"kind": kind, "bbox_m": [float(xa), float(ya), float(xb), float(yb)], "area_m2": float(m.sum() * s * s)}
        )
    return tex, mask, changes
