"""What ``mosaicmap quicklook`` draws: a pyramid level or a layer of the floor, or a route
panorama, as an image; plain (one image pixel per stored pixel or cell) or annotated
(:mod:`pipeline.map_figures`: axes in metres, scale bar, north arrow, colour bar).

Layers other than intensity are coloured (matplotlib colormaps); no data is black:

- ``coverage``: viridis from 0 to the most frames of a cell;
- ``updated``: viridis from the oldest to the newest publish version that wrote a tile;
- ``uniqueness``: RdYlGn from 0 (red) to 1 (green);
- ``texture``: viridis over log10 of the score between its 1st and 99th percentiles.

A layer larger than ``max_px`` on a side is block-reduced by powers of 2 first (mean, or
max for the counts), on the layer's grid coarsened by that factor (:meth:`MapGrid.coarsened`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapstore.grid import MapGrid
from pipeline.map_figures import ColourScale

__all__ = ["LayerImage", "reduce_blocks", "reduction_factor", "render_layer", "annotate_layer", "annotate_route"]


@dataclass(frozen=True)
class LayerImage:
    """A layer drawn as 8-bit pixels: ``pixels`` (grey or RGB uint8), ``legend`` (one line
    of text: colormap and range) and ``scale`` (the colour bar; None for grey levels)."""

    pixels: np.ndarray
    legend: str
    scale: ColourScale | None


def reduction_factor(shape: tuple[int, int], max_px: int) -> int:
    """The smallest power of 2 that brings both sides of ``shape`` to at most ``max_px``."""
    f = 1
    while max(-(-shape[0] // f), -(-shape[1] // f)) > max_px:
        f *= 2
    return f


def reduce_blocks(a: np.ndarray, f: int, how: str) -> np.ndarray:
    """Block-reduce a 2-D array by ``f`` (``how`` "max" or "mean"; edges padded with 0 /
    NaN, so partial blocks at the right and bottom count what they hold)."""
    if f == 1:
        return a
    rows, cols = -(-a.shape[0] // f) * f, -(-a.shape[1] // f) * f
    if how == "max":
        pad = np.zeros((rows, cols), a.dtype)
        pad[: a.shape[0], : a.shape[1]] = a
        return pad.reshape(rows // f, f, cols // f, f).max(axis=(1, 3))
    pad = np.full((rows, cols), np.nan, np.float64)
    pad[: a.shape[0], : a.shape[1]] = a
    blocks = pad.reshape(rows // f, f, cols // f, f)
    finite = np.isfinite(blocks)
    n = finite.sum(axis=(1, 3))
    s = np.where(finite, blocks, 0.0).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def _colorize(values: np.ndarray, valid: np.ndarray, cmap: str) -> np.ndarray:
    """Values in [0, 1] through a matplotlib colormap to uint8 RGB; invalid pixels black."""
    from matplotlib import colormaps

    rgb = colormaps[cmap](np.clip(np.nan_to_num(values), 0.0, 1.0))[..., :3]
    img = np.round(rgb * 255.0).astype(np.uint8)
    img[~valid] = 0
    return img


def render_layer(name: str, data: np.ndarray) -> LayerImage:
    """A layer (or intensity level) as an 8-bit image; no data is black (see the module
    docstring for each layer's colours)."""
    if name == "intensity":
        return LayerImage(data.astype(np.uint8), "grey levels (0 = no data)", None)
    if name in ("coverage", "updated"):
        valid = data > 0
        top = int(data.max()) if valid.any() else 0
        if name == "coverage":
            return LayerImage(_colorize(data / max(top, 1), valid, "viridis"), f"viridis, 0 .. {top} frames",
                              ColourScale("viridis", 0, max(top, 1), "frames that saw the cell (black: none)"))
        lo = int(data[valid].min()) if valid.any() else 0
        return LayerImage(_colorize((data - lo) / max(top - lo, 1), valid, "viridis"),
                          f"viridis, publish version {lo} .. {top} (black = never written)",
                          ColourScale("viridis", lo, max(top, lo + 1), "publish version that last wrote the tile"))
    valid = np.isfinite(data)
    if name == "uniqueness":
        return LayerImage(_colorize(data, valid, "RdYlGn"), "RdYlGn, uniqueness C1 - C2 from 0 (red) to 1 (green)",
                          ColourScale("RdYlGn", 0.0, 1.0, "uniqueness C1 - C2 (< 0.2 poor)"))
    # texture: log scale between the 1st and 99th percentiles
    pos = valid & (data > 0)
    if not pos.any():
        return LayerImage(_colorize(np.zeros_like(data), valid, "viridis"), "viridis (no positive texture scores)",
                          None)
    logv = np.log10(np.where(pos, data, 1.0))
    lo, hi = np.percentile(logv[pos], [1, 99])
    scaled = (logv - lo) / max(hi - lo, 1e-9)
    return LayerImage(_colorize(np.where(pos, scaled, 0.0), valid, "viridis"),
                      f"viridis, log10 texture score {lo:.2f} .. {hi:.2f}",
                      ColourScale("viridis", float(lo), float(max(hi, lo + 1e-9)),
                                  "log10 texture score ((grey levels / px)^2)"))


def annotate_layer(layer: LayerImage, grid: MapGrid, title: str) -> np.ndarray:
    """The layer on its ``grid`` with axes in metres, scale bar, north arrow and (for
    coloured layers) a colour bar; RGB uint8."""
    from pipeline.map_figures import annotated_map

    return annotated_map(layer.pixels, grid, title=title, colour_scale=layer.scale)


def annotate_route(rec, title: str) -> np.ndarray:
    """A route panorama (:class:`mapstore.routes.RouteRecord`) with axes azimuth (degrees)
    and path length (metres); RGB uint8."""
    from pipeline.map_figures import annotated_route

    return annotated_route(rec.lines, s0_m=rec.s0_m, spacing_m=rec.spacing_m,
                           samples_per_degree=rec.samples_per_degree, title=title)
