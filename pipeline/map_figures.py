"""Pictures people can read: a raster with axes in its units, a scale bar, a north arrow,
a colour bar or a legend (matplotlib, Agg; imported inside the functions).

Two kinds of raster:

- a map raster (:func:`annotated_map`): a north-up window of the map grid
  (:class:`mapstore.grid.MapGrid`, the one owner of the convention: columns along +x, rows
  along -y, pixel centres at integers). Axes are the map frame's x and y in metres (the
  image's extent is the grid's :attr:`~mapstore.grid.MapGrid.bounds`, pixel edges
  included), the north arrow points at the map's +y (up), the scale bar is a round
  length in metres;
- a route panorama (:func:`annotated_route`): rows = path length (metres, first row at
  the top), columns = azimuth (degrees, counter-clockwise from the vehicle's +x).

Small rasters are magnified by an integer factor (nearest neighbour: every stored pixel
stays a sharp square) until the long side reaches ``min_px`` (600 by default); a raster is
never shrunk. Each function returns the figure as an RGB uint8 array (write it with
:func:`pipeline.images.write_image` or embed it), so the figure's size is known exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from mapstore.grid import MapGrid

__all__ = ["ColourScale", "LegendKey", "MIN_PX", "magnification", "nice_length", "annotated_map",
           "annotated_route"]

MIN_PX = 600  # long side of the drawn raster (px) a small raster is magnified to
DPI = 100
# Margins around the raster, pixels (at DPI): room for tick labels, axis labels, title.
LEFT, RIGHT, BOTTOM, TOP = 78, 24, 56, 36
COLOURBAR_W, COLOURBAR_GAP, COLOURBAR_LABELS = 18, 14, 84
LEGEND_ROW, LEGEND_PAD = 22, 12


@dataclass(frozen=True)
class ColourScale:
    """How values became colours: ``cmap`` (a matplotlib colormap name) from ``vmin`` to
    ``vmax`` (in the colour bar's units, ``label``; for ``log`` scales the bounds are
    log10 of the values and the label says so)."""

    cmap: str
    vmin: float
    vmax: float
    label: str


@dataclass(frozen=True)
class LegendKey:
    """One legend entry: an RGB colour (0..255) and what it marks."""

    colour: tuple[int, int, int]
    label: str


def magnification(shape: tuple[int, int], min_px: int = MIN_PX) -> int:
    """Integer factor (>= 1) that brings the long side of a ``(rows, cols)`` raster to at
    least ``min_px`` pixels."""
    long = max(int(shape[0]), int(shape[1]), 1)
    return max(1, -(-int(min_px) // long))


def nice_length(span: float, fraction: float = 0.2) -> float:
    """A round length (1, 2 or 5 x 10^k, same units as ``span``) near ``fraction`` of ``span``
    and never more than half of it."""
    target = max(float(span) * fraction, 1e-12)
    k = math.floor(math.log10(target))
    best = 10.0**k
    for m in (1.0, 2.0, 5.0, 10.0):
        v = m * 10.0**k
        if v <= max(target * 1.6, best) and v <= span / 2.0:
            best = v
    return best


def _length_text(metres: float) -> str:
    if metres >= 1.0:
        return f"{metres:g} m"
    if metres >= 0.01:
        return f"{metres * 100:g} cm"
    return f"{metres * 1000:g} mm"


def _figure(raster_px: tuple[int, int], *, right_px: int, bottom_px: int):
    """A figure holding an axes of exactly ``raster_px`` (width, height) pixels, with
    ``right_px`` / ``bottom_px`` extra room; returns (plt, fig, ax, (W, H) of the figure)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    w, h = raster_px
    W, H = LEFT + w + RIGHT + right_px, TOP + h + BOTTOM + bottom_px
    fig = plt.figure(figsize=(W / DPI, H / DPI), dpi=DPI)
    ax = fig.add_axes([LEFT / W, (BOTTOM + bottom_px) / H, w / W, h / H])
    return plt, fig, ax, (W, H)


def _rgb_of(plt, fig) -> np.ndarray:
    fig.canvas.draw()
    out = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return out


def _show(fig, ax, img: np.ndarray, z: int, extent: tuple[float, float, float, float], bottom_px: int) -> None:
    """The raster magnified ``z`` times (each stored pixel a z x z square) placed pixel for
    pixel under the axes (no resampling: ``figimage`` at the axes' integer offset), the
    axes' limits ``extent`` (left, right, bottom, top) in the raster's units, row 0 on top."""
    big = np.repeat(np.repeat(img, z, axis=0), z, axis=1)
    kw = {"cmap": "gray", "vmin": 0, "vmax": 255} if img.ndim == 2 else {}
    fig.figimage(big, xo=LEFT, yo=BOTTOM + bottom_px, origin="upper", zorder=-1, **kw)
    ax.patch.set_alpha(0.0)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])


def _decorate(fig, size: tuple[int, int], raster_px: tuple[int, int], colour_scale: ColourScale | None,
              legend: Sequence[LegendKey]) -> None:
    """Colour bar right of the raster and legend below it, in the room :func:`_figure` left."""
    import matplotlib as mpl
    from matplotlib.patches import Patch

    W, H = size
    w, h = raster_px
    if colour_scale is not None:
        cax = fig.add_axes([(LEFT + w + RIGHT + COLOURBAR_GAP) / W, (H - TOP - h) / H, COLOURBAR_W / W, h / H])
        norm = mpl.colors.Normalize(vmin=colour_scale.vmin, vmax=colour_scale.vmax)
        cb = fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=colour_scale.cmap), cax=cax)
        cb.set_label(colour_scale.label, fontsize=9)
        cb.ax.tick_params(labelsize=8)
    if legend:
        handles = [Patch(facecolor=np.array(k.colour) / 255.0, edgecolor="black", linewidth=0.5, label=k.label)
                   for k in legend]
        fig.legend(handles=handles, loc="lower left", bbox_to_anchor=(LEFT / W, LEGEND_PAD / 2 / H), fontsize=9,
                   frameon=False, ncol=1, handlelength=1.6, borderaxespad=0.0)


def _extra(colour_scale: ColourScale | None, legend: Sequence[LegendKey]) -> tuple[int, int]:
    right = COLOURBAR_GAP + COLOURBAR_W + COLOURBAR_LABELS if colour_scale is not None else 0
    bottom = LEGEND_ROW * len(legend) + LEGEND_PAD if legend else 0
    return right, bottom


def annotated_map(img: np.ndarray, grid: MapGrid, *, title: str, colour_scale: ColourScale | None = None,
                  legend: Sequence[LegendKey] = (), min_px: int = MIN_PX) -> np.ndarray:
    """A map raster (grey ``(rows, cols)`` uint8 or RGB ``(rows, cols, 3)``) drawn on ``grid``
    (its shape must be the raster's) with axes x, y in metres of the map frame, a scale bar,
    a north arrow (the map's +y), and the optional colour bar and legend. RGB uint8 out."""
    from matplotlib import patheffects
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    if tuple(img.shape[:2]) != tuple(grid.shape):
        raise ValueError(f"raster {img.shape[:2]} does not match its grid {grid.shape}")
    z = magnification(img.shape[:2], min_px)
    raster = (img.shape[1] * z, img.shape[0] * z)
    right, bottom = _extra(colour_scale, legend)
    plt, fig, ax, size = _figure(raster, right_px=right, bottom_px=bottom)
    xmin, ymin, xmax, ymax = grid.bounds
    _show(fig, ax, img, z, (xmin, xmax, ymin, ymax), bottom)
    ax.set_xlabel("x (m, map frame)", fontsize=9)
    ax.set_ylabel("y (m, map frame)", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.set_title(title, fontsize=10, loc="left")
    bar = nice_length(xmax - xmin)
    ax.add_artist(AnchoredSizeBar(ax.transData, bar, _length_text(bar), "lower left", pad=0.4, borderpad=0.6,
                                  sep=4, color="black", frameon=True, size_vertical=(ymax - ymin) / 150.0,
                                  fontproperties={"size": 9}))
    north = ax.annotate("N\n(+y)", xy=(0.94, 0.97), xytext=(0.94, 0.86), xycoords="axes fraction", ha="center",
                        va="top", fontsize=8, fontweight="bold", color="black",
                        bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "none", "alpha": 0.85},
                        arrowprops={"arrowstyle": "-|>", "color": "black", "lw": 1.8, "mutation_scale": 14})
    north.arrow_patch.set_path_effects([patheffects.withStroke(linewidth=4, foreground="white")])
    _decorate(fig, size, raster, colour_scale, legend)
    return _rgb_of(plt, fig)


def annotated_route(lines: np.ndarray, *, s0_m: float, spacing_m: float, samples_per_degree: float, title: str,
                    min_px: int = MIN_PX) -> np.ndarray:
    """A route panorama (``(rows, azimuths)`` uint8, row i at path length ``s0_m + i *
    spacing_m``, column j at azimuth ``j / samples_per_degree`` degrees) with axes azimuth
    (degrees, ticks every 45) and path length (metres), a grey-level colour bar. RGB out."""
    rows, cols = lines.shape[:2]
    z = magnification((rows, cols), min_px)
    raster = (cols * z, rows * z)
    scale = ColourScale("gray", 0, 255, "grey level at the horizon")
    right, bottom = _extra(scale, ())
    plt, fig, ax, size = _figure(raster, right_px=right, bottom_px=bottom)
    half = 0.5 / samples_per_degree
    _show(fig, ax, lines, z, (-half, cols / samples_per_degree - half, s0_m + (rows - 0.5) * spacing_m,
                              s0_m - 0.5 * spacing_m), bottom)
    ax.set_xticks(np.arange(0, 361, 45))
    ax.set_xlabel("azimuth (deg, counter-clockwise from vehicle forward)", fontsize=9)
    ax.set_ylabel("path length s (m)", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.set_title(title, fontsize=10, loc="left")
    _decorate(fig, size, raster, scale, ())
    return _rgb_of(plt, fig)
