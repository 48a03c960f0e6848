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
  the top), columns = azimuth (degrees, counter-clockwise from the vehicle's +x); several
  panels of one route grid side by side (:func:`annotated_route_panels`: e.g. the diff's
  FROM, TO and their difference) share the path axis, each with its colour scale, marks
  (:class:`RouteMark`: path ranges, azimuth sectors) and a legend.

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

__all__ = ["ColourScale", "LegendKey", "RoutePanel", "RouteMark", "RouteLayout", "GREY_LEVELS", "MIN_PX",
           "magnification", "nice_length", "annotated_map", "annotated_route", "annotated_route_panels",
           "route_panels_figure", "route_panels_layout"]

MIN_PX = 600  # long side of the drawn raster (px) a small raster is magnified to
DPI = 100
# Margins around the raster, pixels (at DPI): room for tick labels, axis labels, title.
LEFT, RIGHT, BOTTOM, TOP = 78, 24, 56, 36
COLOURBAR_W, COLOURBAR_GAP, COLOURBAR_LABELS = 18, 14, 84
LEGEND_ROW, LEGEND_PAD = 22, 12
PANEL_GAP = 14  # between route panels side by side (px; the shared path axis is labelled on the first only)
PANEL_TITLE = 20  # extra room above route panels that carry labels (the figure's title goes above them)
MARK_BAR_PX = 6  # width of a path-range bar (RouteMark without azimuth) at a panel's left edge
MIN_PANEL_H = 300  # a route panel's least height (px): rows of a short route are drawn taller (room for the bars)


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


GREY_LEVELS = ColourScale("gray", 0, 255, "grey level at the horizon")  # a route panorama's own lines


@dataclass(frozen=True)
class RoutePanel:
    """One panel of a route figure: ``values`` ``(rows, azimuths)`` (or RGB already
    coloured) drawn through ``scale`` (its colour bar), headed ``label``."""

    values: np.ndarray
    label: str
    scale: ColourScale


@dataclass(frozen=True)
class RouteMark:
    """A mark on route panels. ``s_m``: path length of its top and bottom edges (metres);
    ``azimuth_deg``: its left and right edges (degrees, right > left; a right edge past the
    panel's last azimuth wraps through 0), outlined in ``colour`` (RGB 0..255); None: a
    filled bar :data:`MARK_BAR_PX` wide at the panel's left edge. ``panels``: indices of the
    panels it is drawn on (empty: every panel)."""

    s_m: tuple[float, float]
    azimuth_deg: tuple[float, float] | None
    colour: tuple[int, int, int]
    panels: tuple[int, ...] = ()


@dataclass(frozen=True)
class RouteLayout:
    """Where a route figure's parts are (pixels): ``z`` the magnification of each stored
    value (each azimuth sample ``scale_x * z`` wide), ``z_rows`` of each row (``z`` or
    more: at least :data:`MIN_PANEL_H` high panels); ``boxes`` per
    panel (top, left, height, width) of its raster in the figure; ``raster_px`` (width,
    height) of the panels with their gaps; ``size`` (width, height) of the figure;
    ``top_px`` / ``bottom_px`` the room added above (panel labels) and below (legend);
    ``scales`` the colour bars, left to right."""

    z: int
    z_rows: int
    scale_x: int
    boxes: tuple[tuple[int, int, int, int], ...]
    raster_px: tuple[int, int]
    size: tuple[int, int]
    top_px: int
    bottom_px: int
    scales: tuple[ColourScale, ...]


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


def _canvas(width_px: int, height_px: int):
    """An Agg figure of exactly (``width_px``, ``height_px``) pixels at :data:`DPI`; returns (plt, fig)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt, plt.figure(figsize=(width_px / DPI, height_px / DPI), dpi=DPI)


def _figure(raster_px: tuple[int, int], *, right_px: int, bottom_px: int):
    """A figure holding an axes of exactly ``raster_px`` (width, height) pixels, with
    ``right_px`` / ``bottom_px`` extra room; returns (plt, fig, ax, (W, H) of the figure)."""
    w, h = raster_px
    W, H = LEFT + w + RIGHT + right_px, TOP + h + BOTTOM + bottom_px
    plt, fig = _canvas(W, H)
    ax = fig.add_axes([LEFT / W, (BOTTOM + bottom_px) / H, w / W, h / H])
    return plt, fig, ax, (W, H)


def _rgb_of(plt, fig) -> np.ndarray:
    fig.canvas.draw()
    out = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return out


def _show(fig, ax, img: np.ndarray, z: int, extent: tuple[float, float, float, float], bottom_px: int,
          left_px: int = LEFT, z_rows: int | None = None) -> None:
    """The raster magnified ``z`` times (each stored pixel a z x z square; ``z_rows`` x z
    when given) placed pixel for pixel under the axes (no resampling: ``figimage`` at the
    axes' integer offset ``left_px``, ``BOTTOM + bottom_px``), the axes' limits ``extent``
    (left, right, bottom, top) in the raster's units, row 0 on top."""
    big = np.repeat(np.repeat(img, z if z_rows is None else z_rows, axis=0), z, axis=1)
    kw = {"cmap": "gray", "vmin": 0, "vmax": 255} if img.ndim == 2 else {}
    fig.figimage(big, xo=left_px, yo=BOTTOM + bottom_px, origin="upper", zorder=-1, **kw)
    ax.patch.set_alpha(0.0)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])


def _decorate(fig, size: tuple[int, int], raster_px: tuple[int, int], colour_scales: Sequence[ColourScale],
              legend: Sequence[LegendKey], top_px: int = 0) -> None:
    """Colour bars right of the raster (side by side, in order) and legend below it, in the
    room :func:`_extra` asked for (``top_px``: extra room above the raster)."""
    import matplotlib as mpl
    from matplotlib.patches import Patch

    W, H = size
    w, h = raster_px
    x = LEFT + w + RIGHT
    for scale in colour_scales:
        cax = fig.add_axes([(x + COLOURBAR_GAP) / W, (H - TOP - top_px - h) / H, COLOURBAR_W / W, h / H])
        norm = mpl.colors.Normalize(vmin=scale.vmin, vmax=scale.vmax)
        cb = fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=scale.cmap), cax=cax)
        cb.set_label(scale.label, fontsize=9)
        cb.ax.tick_params(labelsize=8)
        x += COLOURBAR_GAP + COLOURBAR_W + COLOURBAR_LABELS
    if legend:
        handles = [Patch(facecolor=np.array(k.colour) / 255.0, edgecolor="black", linewidth=0.5, label=k.label)
                   for k in legend]
        fig.legend(handles=handles, loc="lower left", bbox_to_anchor=(LEFT / W, LEGEND_PAD / 2 / H), fontsize=9,
                   frameon=False, ncol=1, handlelength=1.6, borderaxespad=0.0)


def _extra(colour_scales: Sequence[ColourScale], legend: Sequence[LegendKey]) -> tuple[int, int]:
    """(right, bottom) room in pixels the colour bars and the legend take."""
    right = len(colour_scales) * (COLOURBAR_GAP + COLOURBAR_W + COLOURBAR_LABELS)
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
    scales = [colour_scale] if colour_scale is not None else []
    right, bottom = _extra(scales, legend)
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
    _decorate(fig, size, raster, scales, legend)
    return _rgb_of(plt, fig)


def annotated_route(lines: np.ndarray, *, s0_m: float, spacing_m: float, samples_per_degree: float, title: str,
                    min_px: int = MIN_PX) -> np.ndarray:
    """A route panorama (``(rows, azimuths)`` uint8, row i at path length ``s0_m + i *
    spacing_m``, column j at azimuth ``j / samples_per_degree`` degrees) with axes azimuth
    (degrees, ticks every 45) and path length (metres), a grey-level colour bar. RGB out."""
    return annotated_route_panels([RoutePanel(lines, "", GREY_LEVELS)], s0_m=s0_m, spacing_m=spacing_m,
                                  samples_per_degree=samples_per_degree, title=title, min_px=min_px)


def route_panels_layout(panels: Sequence[RoutePanel], *, legend: Sequence[LegendKey] = (), scale_x: int = 1,
                        min_px: int = MIN_PX) -> RouteLayout:
    """Where :func:`annotated_route_panels` puts things (pixels): the panels' rasters
    magnified ``z`` times (:func:`magnification` of ``(rows, panels * azimuths * scale_x)``:
    the panels together reach ``min_px`` wide; each azimuth sample ``scale_x * z`` pixels
    wide, each row ``z`` high, or more for a panel to reach :data:`MIN_PANEL_H`), side by
    side :data:`PANEL_GAP` apart, room above them for their labels when they have any, right
    of them for one colour bar per distinct colour scale, below them for the legend."""
    if not panels:
        raise ValueError("a route figure needs at least one panel")
    shapes = {p.values.shape[:2] for p in panels}
    if len(shapes) != 1:
        raise ValueError(f"route panels differ in shape: {sorted(shapes)}")
    rows, cols = shapes.pop()
    z = magnification((rows, len(panels) * cols * scale_x), min_px)
    z_rows = max(z, -(-MIN_PANEL_H // max(rows, 1)))
    pw, ph = cols * scale_x * z, rows * z_rows
    top = PANEL_TITLE if any(p.label for p in panels) else 0
    scales = list(dict.fromkeys(p.scale for p in panels))
    right, bottom = _extra(scales, legend)
    boxes = tuple((TOP + top, LEFT + i * (pw + PANEL_GAP), ph, pw) for i in range(len(panels)))
    w = len(panels) * pw + (len(panels) - 1) * PANEL_GAP
    size = (LEFT + w + RIGHT + right, TOP + top + ph + BOTTOM + bottom)
    return RouteLayout(z, z_rows, scale_x, boxes, (w, ph), size, top, bottom, tuple(scales))


def route_panels_figure(panels: Sequence[RoutePanel], *, s0_m: float, spacing_m: float, samples_per_degree: float,
                        title: str, marks: Sequence[RouteMark] = (), legend: Sequence[LegendKey] = (),
                        scale_x: int = 1, min_px: int = MIN_PX):
    """Route panels side by side, as a matplotlib figure (Agg, open: the caller closes it).

    Every panel holds ``(rows, azimuths)`` values of the same route grid: row i at path
    length ``s0_m + i * spacing_m`` (metres, first row at the top), column j at azimuth ``j
    / samples_per_degree`` degrees (counter-clockwise from the vehicle's forward), drawn
    through its colour scale (one colour bar per distinct scale). Axes: azimuth (degrees,
    ticks every 45) under each panel, path length s (metres) left of the first (shared);
    each panel headed by its label, the figure by ``title``; ``marks`` outlined on the
    panels (:class:`RouteMark`), ``legend`` below. Layout: :func:`route_panels_layout`."""
    from matplotlib.patches import Rectangle

    lay = route_panels_layout(panels, legend=legend, scale_x=scale_x, min_px=min_px)
    W, H = lay.size
    plt, fig = _canvas(W, H)
    rows, cols = panels[0].values.shape[:2]
    half = 0.5 / samples_per_degree
    x0, x1 = -half, cols / samples_per_degree - half
    extent = (x0, x1, s0_m + (rows - 0.5) * spacing_m, s0_m - 0.5 * spacing_m)
    axes = []
    for i, (panel, (top, left, ph, pw)) in enumerate(zip(panels, lay.boxes)):
        ax = fig.add_axes([left / W, (H - top - ph) / H, pw / W, ph / H], sharey=axes[0] if axes else None)
        img = np.repeat(_panel_pixels(panel), lay.scale_x, axis=1)
        _show(fig, ax, img, lay.z, extent, lay.bottom_px, left_px=left, z_rows=lay.z_rows)
        ax.set_xticks(np.arange(0, 361, 45))
        ax.set_xlim(x0, x1)
        ax.set_xlabel("azimuth (deg, counter-clockwise from vehicle forward)", fontsize=9)
        ax.tick_params(labelsize=8)
        if i == 0:
            ax.set_ylabel("path length s (m)", fontsize=9)
        else:
            ax.tick_params(labelleft=False)
        if panel.label:
            ax.set_title(panel.label, fontsize=9, loc="left")
        axes.append(ax)
    if lay.top_px:
        fig.text(LEFT / W, 1.0 - 6 / H, title, fontsize=10, ha="left", va="top")
    else:
        axes[0].set_title(title, fontsize=10, loc="left")
    bar_w = (x1 - x0) * MARK_BAR_PX / lay.boxes[0][3]  # a bar of MARK_BAR_PX pixels, in degrees
    for mark in marks:
        top_m, bottom_m = mark.s_m
        for i in mark.panels or range(len(panels)):
            if mark.azimuth_deg is None:
                spans = [(x0, x0 + bar_w)]
                style = {"facecolor": np.array(mark.colour) / 255.0, "edgecolor": "none"}
            else:
                a0, a1 = mark.azimuth_deg
                spans = [(a0, min(a1, x1))] + ([(x0, x0 + a1 - x1)] if a1 > x1 else [])
                style = {"facecolor": "none", "edgecolor": np.array(mark.colour) / 255.0, "linewidth": 1.2}
            for b0, b1 in spans:
                axes[i].add_patch(Rectangle((b0, top_m), b1 - b0, bottom_m - top_m, **style))
    _decorate(fig, lay.size, lay.raster_px, lay.scales, legend, top_px=lay.top_px)
    return fig


def annotated_route_panels(panels: Sequence[RoutePanel], *, s0_m: float, spacing_m: float,
                           samples_per_degree: float, title: str, marks: Sequence[RouteMark] = (),
                           legend: Sequence[LegendKey] = (), scale_x: int = 1, min_px: int = MIN_PX) -> np.ndarray:
    """:func:`route_panels_figure` as an RGB uint8 array (its size: :func:`route_panels_layout`)."""
    import matplotlib.pyplot as plt

    fig = route_panels_figure(panels, s0_m=s0_m, spacing_m=spacing_m, samples_per_degree=samples_per_degree,
                              title=title, marks=marks, legend=legend, scale_x=scale_x, min_px=min_px)
    return _rgb_of(plt, fig)


def _panel_pixels(panel: RoutePanel) -> np.ndarray:
    """A panel's raster: grey uint8 as is on the 0..255 grey scale, else its values through
    its colour scale (RGB uint8; NaN black)."""
    v, sc = panel.values, panel.scale
    if v.ndim == 3:
        return v
    if sc.cmap == "gray" and (sc.vmin, sc.vmax) == (0, 255) and v.dtype == np.uint8:
        return v
    from matplotlib import colormaps

    t = (np.asarray(v, np.float64) - sc.vmin) / max(sc.vmax - sc.vmin, 1e-12)
    rgb = np.round(colormaps[sc.cmap](np.clip(np.nan_to_num(t), 0.0, 1.0))[..., :3] * 255.0).astype(np.uint8)
    rgb[~np.isfinite(v)] = 0
    return rgb
