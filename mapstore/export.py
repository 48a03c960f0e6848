"""Extracts of a map version for vehicles and viewers: selections, bundles and deltas.

What is exported (a :class:`Selection`): the whole map, a region (a world box) or a
corridor (a polyline and a width) at chosen pyramid levels and layers. A selection is
rasterised on each exported array's own grid, through :class:`mapstore.grid.MapGrid` only:
a pixel (or layer cell) of side ``s`` is kept when its square can meet the selection:

- region ``[xmin, xmax] x [ymin, ymax]`` (metres): the pixel's square overlaps the box;
- corridor of width ``w`` along a polyline: the pixel's centre lies within
  ``w / 2 + s / sqrt(2)`` of the polyline (its square may reach the corridor).

So a coarse level or a layer keeps every cell touching the corridor. The polyline is first
simplified (Douglas-Peucker, tolerance a quarter of a level-0 pixel) so that a drive log
with thousands of poses costs what its shape needs; the manifest records the simplified one.

How (see :mod:`mapstore.bundle` for the format): an :class:`Extract` of one map version
creates the bundle's zarr metadata in memory (:func:`mapstore.layout.create_floor`
unsharded, with the exported levels and layers only), then, array by array and tile row by
tile row, reads from the map only the windows of the tiles the selection reaches, sets
pixels outside the selection to the fill value, and encodes the tiles with zarr (zstd)
into members; tiles holding only fill values are not written. Memory: one tile row of one
array at a time, whatever the map's size.

A delta (``export --since V``) costs what the change costs: the repository's chunk diff
(:meth:`mapstore.repository.MapRepository.changed_chunks`, shard or chunk indices of the
map's arrays) gives the candidate tiles; each is encoded for both versions (the encoding is
deterministic, so an unchanged tile gives identical bytes) and kept when they differ.

Derived per-tile arrays (:class:`TileDerived`): an export may add arrays computed per
level-0 tile from the *exported* level-0 pixels (after the selection's mask), one chunk per
tile, e.g. the tracker's relocalization index (``floor/reloc/features``). This module only
knows them as "a function of a tile and ``margin_px`` of context around it": the caller
(``pipeline/cli/export.py``) injects the function (``tracker.reloc.tile_features``), so
mapstore depends on neither the tracker nor OpenCV's feature detector, and the vehicle
computes the very same records with the very same function when a bundle lacks them. In a
delta a derived chunk is a candidate when its tile or one of its neighbours (within the
margin) changed at level 0; it is carried when its bytes differ.

Routes (the omnidirectional route panoramas, ``/routes/<id>``, :mod:`mapstore.routes`):
the selection names them (``Selection.routes``: every route, none, or some ids); each is
read whole, cut by :func:`crop_route` to the rows whose poses lie in a region or corridor
(plus ``route_margin_m``), and written with :func:`mapstore.routes.write_route` at the
same keys as in the map (``routes/<id>/zarr.json``, ``routes/<id>/lines/c/<r>/0``, ...:
unsharded, zstd), so :func:`mapstore.routes.read_route` reads it from a bundle as from a
map. A delta encodes the routes of both versions and carries the chunks whose bytes
differ (a change over 10 m of a long route costs the one or two chunks holding it). A
delta carries a zarr.json member only when its bytes differ from the base's (or the base
lacks it).

A map of route panoramas only (no ``/floor``: an omni build without floor stages):
:func:`make_selection` takes ``info=None`` (levels and layers dropped, the region or corridor
only cuts the routes), :class:`Extract` stages the root ``zarr.json`` and the routes alone,
and the manifest says ``routes_only: true`` (:mod:`mapstore.bundle`, "Routes only").

The OME-Zarr export (:class:`OmeZarrSink`) writes the same members as plain files for
viewers: ``OUT/map.zarr`` is a zarr v3 hierarchy holding nothing but zarr's files (the
intensity pyramid ``floor``, an OME-Zarr 0.5 multiscale image; each layer an image of one
scale ``layers/<name>`` with dataset ``0`` on the layer's own grid, moved from the map's
``floor/layers/<name>`` array; the routes), and ``OUT/manifest.json`` lies beside it, its
``ome_zarr`` entry naming the images to open.

This module reads a map through zarr (an icechunk session's store); it never imports the
batch pipeline.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import zarr
from zarr.storage import MemoryStore

from mapstore.bundle import BUNDLE_FORMAT, BUNDLE_FORMAT_VERSION, MANIFEST, MemberSink, check_member_name, member_key
from mapstore.grid import MapGrid
from mapstore.layout import LAYERS, FloorInfo, LayoutSpec, create_floor, read_floor, set_version
from mapstore.routes import ROUTES_GROUP, RouteRecord, check_route_id, list_routes, read_route, route_attrs, write_route

__all__ = [
    "INTENSITY",
    "LAYER_NAMES",
    "SelectionError",
    "Selection",
    "TileDerived",
    "make_selection",
    "parse_routes",
    "crop_route",
    "simplify_polyline",
    "Extract",
    "DirectorySink",
    "OmeZarrSink",
    "OME_ZARR_ROOT",
    "HashingSink",
    "bundle_header",
    "export_extract",
    "export_delta",
]

INTENSITY = "intensity"
LAYER_NAMES = (INTENSITY, *LAYERS)  # what --layers may name
SIMPLIFY_PX = 0.25  # polyline simplification tolerance, in level-0 pixels

Progress = Callable[..., Iterable]


class SelectionError(ValueError):
    """A selection that cannot be made: ``field`` is the input at fault (region, corridor,
    width, levels, layers, since, selection), ``what`` says why."""

    def __init__(self, field: str, what: str):
        self.field, self.what = field, what
        super().__init__(f"{field}: {what}")


# --- selections ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Selection:
    """What an export holds.

    Attributes:
        levels: pyramid levels of the intensity (empty when ``intensity`` is not exported).
        layers: exported layers: ``intensity`` and/or names of :data:`mapstore.layout.LAYERS`.
        region_m: ``(xmin, ymin, xmax, ymax)`` world box in metres, or None.
        corridor_m: polyline vertices ``((x, y), ...)`` in metres (world frame), or None.
        width_m: the corridor's full width in metres (None without a corridor).
        routes: the route panoramas (``/routes/<id>``) exported: None = every route of the
            version, else these ids (empty: none).
        route_margin_m: a route row is kept when its pose lies within this distance
            (metres) of the region or the corridor (ignored for the whole map).
    """

    levels: tuple[int, ...]
    layers: tuple[str, ...]
    region_m: tuple[float, float, float, float] | None = None
    corridor_m: tuple[tuple[float, float], ...] | None = None
    width_m: float | None = None
    routes: tuple[str, ...] | None = None
    route_margin_m: float = 0.0

    @property
    def kind(self) -> str:
        return "region" if self.region_m is not None else "corridor" if self.corridor_m is not None else "all"

    @property
    def cell_layers(self) -> tuple[str, ...]:
        """The exported layers other than the intensity levels."""
        return tuple(name for name in self.layers if name != INTENSITY)

    def to_manifest(self) -> dict:
        return {"kind": self.kind,
                "region_m": list(self.region_m) if self.region_m is not None else None,
                "corridor_m": [list(p) for p in self.corridor_m] if self.corridor_m is not None else None,
                "width_m": self.width_m, "levels": list(self.levels), "layers": list(self.layers),
                "routes": "all" if self.routes is None else list(self.routes),
                "route_margin_m": None if self.kind == "all" else float(self.route_margin_m)}

    def route_ids(self, available: Sequence[str]) -> list[str]:
        """The ids of ``available`` (a version's routes) this selection exports, sorted."""
        return sorted(available) if self.routes is None else sorted(set(available) & set(self.routes))

    def rows_inside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """bool per point (x, y metres, world frame): within ``route_margin_m`` of the
        region or the corridor (every point for the whole map)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        m = float(self.route_margin_m)
        if self.region_m is not None:
            x0, y0, x1, y1 = self.region_m
            return (x >= x0 - m) & (x <= x1 + m) & (y >= y0 - m) & (y <= y1 + m)
        if self.corridor_m is None:
            return np.ones(x.shape, bool)
        reach = self.width_m / 2.0 + m
        d2 = np.full(x.shape, np.inf)
        p = np.asarray(self.corridor_m, float)
        for (ax, ay), (bx, by) in zip(p[:-1].tolist(), p[1:].tolist()):
            np.minimum(d2, _segment_dist2(x, y, ax, ay, bx, by), out=d2)
        return d2 <= reach * reach

    def box_m(self) -> tuple[float, float, float, float] | None:
        """World box (metres) holding every point of the selection; None for the whole map."""
        if self.region_m is not None:
            return self.region_m
        if self.corridor_m is not None:
            p = np.asarray(self.corridor_m)
            h = self.width_m / 2.0
            return (float(p[:, 0].min() - h), float(p[:, 1].min() - h), float(p[:, 0].max() + h),
                    float(p[:, 1].max() + h))
        return None

    def bounds_in(self, grid: MapGrid) -> list[float]:
        """The selection's box clipped to ``grid``'s bounds (metres): the manifest's bounds_m."""
        gx0, gy0, gx1, gy1 = grid.bounds
        box = self.box_m()
        if box is None:
            return [gx0, gy0, gx1, gy1]
        return [max(gx0, box[0]), max(gy0, box[1]), min(gx1, box[2]), min(gy1, box[3])]

    # --- rasterisation ---------------------------------------------------------------------

    def _reach(self, grid: MapGrid) -> float:
        """Corridor: largest centre distance (m) from the polyline of a kept pixel."""
        return self.width_m / 2.0 + grid.pixel_size * math.sqrt(0.5)

    def window_mask(self, grid: MapGrid, rows: slice, cols: slice) -> np.ndarray | None:
        """bool ``(rows, cols)`` window of ``grid``: the pixels the selection keeps;
        None when it keeps them all (the whole map)."""
        cs = np.arange(cols.start, cols.stop)
        rs = np.arange(rows.start, rows.stop)
        x, _ = grid.pixel_to_world(cs, np.zeros_like(cs))
        _, y = grid.pixel_to_world(np.zeros_like(rs), rs)
        h = grid.pixel_size / 2.0
        if self.region_m is not None:
            x0, y0, x1, y1 = self.region_m
            return ((y + h > y0) & (y - h < y1))[:, None] & ((x + h > x0) & (x - h < x1))[None, :]
        if self.corridor_m is None:
            return None
        reach = self._reach(grid)
        keep = np.zeros((len(rs), len(cs)), bool)
        for (ax, ay), (bx, by) in self._segments_near(x.min(), y.min(), x.max(), y.max(), reach):
            keep |= _segment_dist2(x[None, :], y[:, None], ax, ay, bx, by) <= reach * reach
        return keep

    def _segments_near(self, x0: float, y0: float, x1: float, y1: float, reach: float):
        p = np.asarray(self.corridor_m, float)
        a, b = p[:-1], p[1:]
        near = ((np.minimum(a[:, 0], b[:, 0]) - reach <= x1) & (np.maximum(a[:, 0], b[:, 0]) + reach >= x0)
                & (np.minimum(a[:, 1], b[:, 1]) - reach <= y1) & (np.maximum(a[:, 1], b[:, 1]) + reach >= y0))
        return zip(a[near].tolist(), b[near].tolist())

    def chunk_candidates(self, grid: MapGrid, chunk: int) -> list[tuple[int, int]]:
        """Chunks (row, col) of ``grid``'s array, ``chunk`` x ``chunk`` elements each, that
        may hold kept pixels (a superset; :meth:`window_mask` decides), row-major."""
        rows, cols = grid.shape
        n_r, n_c = -(-rows // chunk), -(-cols // chunk)
        box = self.box_m()
        if box is None:
            return [(i, j) for i in range(n_r) for j in range(n_c)]
        pad = grid.pixel_size * (math.sqrt(0.5) if self.corridor_m is not None else 0.5)
        ca, ra = grid.world_to_pixel(box[0] - pad, box[3] + pad)
        cb, rb = grid.world_to_pixel(box[2] + pad, box[1] - pad)
        i0, i1 = max(0, int(np.floor(ra)) // chunk), min(n_r - 1, int(np.ceil(rb)) // chunk)
        j0, j1 = max(0, int(np.floor(ca)) // chunk), min(n_c - 1, int(np.ceil(cb)) // chunk)
        if i0 > i1 or j0 > j1:
            return []
        ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
        ii, jj = ii.ravel(), jj.ravel()
        if self.corridor_m is not None:
            # chunk centre within reach + the chunk's half diagonal of the polyline
            cx, cy = grid.pixel_to_world((jj + 0.5) * chunk - 0.5, (ii + 0.5) * chunk - 0.5)
            limit = self._reach(grid) + chunk * grid.pixel_size * math.sqrt(0.5)
            d2 = np.full(ii.shape, np.inf)
            p = np.asarray(self.corridor_m, float)
            for (ax, ay), (bx, by) in zip(p[:-1].tolist(), p[1:].tolist()):
                np.minimum(d2, _segment_dist2(cx, cy, ax, ay, bx, by), out=d2)
            ok = d2 <= limit * limit
            ii, jj = ii[ok], jj[ok]
        return list(zip(ii.tolist(), jj.tolist()))


def _segment_dist2(px, py, ax: float, ay: float, bx: float, by: float) -> np.ndarray:
    """Squared distance of points (px, py) (broadcast) to the segment a-b (metres^2)."""
    dx, dy = bx - ax, by - ay
    n2 = dx * dx + dy * dy
    if n2 == 0.0:
        return (px - ax) ** 2 + (py - ay) ** 2
    t = np.clip(((px - ax) * dx + (py - ay) * dy) / n2, 0.0, 1.0)
    return (px - ax - t * dx) ** 2 + (py - ay - t * dy) ** 2


def simplify_polyline(points: np.ndarray, tolerance: float) -> np.ndarray:
    """Douglas-Peucker: the vertices of ``points`` (N, 2) needed to stay within
    ``tolerance`` (metres) of it; first and last kept; consecutive duplicates dropped."""
    p = np.asarray(points, float)
    if len(p) > 1:
        p = p[np.r_[True, np.any(np.diff(p, axis=0) != 0, axis=1)]]
    if len(p) <= 2:
        return p
    keep = np.zeros(len(p), bool)
    keep[[0, -1]] = True
    stack = [(0, len(p) - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        d2 = _segment_dist2(p[i + 1:j, 0], p[i + 1:j, 1], *p[i], *p[j])
        k = int(np.argmax(d2))
        if d2[k] > tolerance * tolerance:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return p[keep]


def _parse_levels(levels: Sequence[int] | None, info: FloorInfo) -> tuple[int, ...]:
    if levels is None or len(levels) == 0:
        return tuple(range(info.levels))
    bad = [k for k in levels if not 0 <= int(k) < info.levels]
    if bad:
        raise SelectionError("levels", f"level {bad[0]} does not exist (the map has levels 0..{info.levels - 1})")
    return tuple(sorted({int(k) for k in levels}))


def parse_routes(routes: str | Sequence[str] | None) -> tuple[str, ...] | None:
    """``--routes``: None or "all" -> None (every route), "none" or "" -> (), "ID[,ID...]"
    or a sequence of ids -> the sorted ids. Raises SelectionError("routes") on a bad id."""
    if routes is None:
        return None
    if isinstance(routes, str):
        text = routes.strip()
        if text == "all":
            return None
        if text in ("none", ""):
            return ()
        routes = [p.strip() for p in text.split(",") if p.strip()]
    ids = sorted(set(routes))
    for rid in ids:
        try:
            check_route_id(rid)
        except ValueError as e:
            raise SelectionError("routes", str(e)) from None
    return tuple(ids)


def make_selection(info: FloorInfo | None, *, region: Sequence[float] | None = None, corridor: np.ndarray | None = None,
                   width_m: float | None = None, levels: Sequence[int] | None = None,
                   layers: Sequence[str] = (INTENSITY,), routes: str | Sequence[str] | None = None,
                   route_ids: Sequence[str] | None = None, route_margin_m: float = 0.0) -> Selection:
    """Check the inputs against the map and build the :class:`Selection`.

    Args:
        info: the map version's layout (:func:`mapstore.layout.read_floor`); None for a
            map of route panoramas only (no floor): then ``levels`` and ``layers`` are
            ignored (nothing of a floor is exported), the region or corridor only cuts the
            routes, and a selection of no route is refused.
        region: ``(x0, y0, x1, y1)`` opposite corners in metres, or None.
        corridor: (N, 2) polyline in metres (world frame), or None; needs ``width_m``.
        width_m: corridor width in metres (> 0).
        levels: pyramid levels; None or empty = every level of the map.
        layers: ``intensity`` and/or layer names.
        routes: route panoramas exported (:func:`parse_routes`: "all", "none", ids).
        route_ids: the version's routes (:func:`mapstore.routes.list_routes`); when given,
            every id named in ``routes`` must be one of them.
        route_margin_m: metres around a region or corridor within which route rows are
            kept (>= 0; not used for the whole map).

    Raises SelectionError naming the input at fault.
    """
    rsel = parse_routes(routes)
    if rsel and route_ids is not None:
        missing = [r for r in rsel if r not in set(route_ids)]
        if missing:
            raise SelectionError("routes", f"no route {missing[0]!r} in version "
                                           f"{info.version if info is not None else '(routes only)'} "
                                           f"(routes: {', '.join(sorted(route_ids)) or 'none'})")
    if not (math.isfinite(route_margin_m) and route_margin_m >= 0):
        raise SelectionError("routes", f"route margin must be >= 0 metres, got {route_margin_m}")
    if info is None:  # a map of routes only: no floor levels or layers to export
        if rsel == () or (route_ids is not None and not route_ids):
            raise SelectionError("routes", "the map holds no floor, only route panoramas: export some routes")
        sel = _routes_only_selection(region=region, corridor=corridor, width_m=width_m)
    else:
        sel = _floor_selection(info, region=region, corridor=corridor, width_m=width_m, levels=levels, layers=layers)
    return replace(sel, routes=rsel, route_margin_m=float(route_margin_m) if sel.kind != "all" else 0.0)


def _region_box(region: Sequence[float]) -> tuple[float, float, float, float]:
    """``region`` (x0, y0, x1, y1 metres, any corner order) as (xmin, ymin, xmax, ymax);
    SelectionError unless it is four finite numbers spanning an area."""
    r = [float(v) for v in region]
    if len(r) != 4 or not all(math.isfinite(v) for v in r):
        raise SelectionError("region", "needs four finite numbers x0,y0,x1,y1 (metres)")
    box = (min(r[0], r[2]), min(r[1], r[3]), max(r[0], r[2]), max(r[1], r[3]))
    if box[0] == box[2] or box[1] == box[3]:
        raise SelectionError("region", f"box {r} has no area")
    return box


def _routes_only_selection(*, region: Sequence[float] | None, corridor: np.ndarray | None,
                           width_m: float | None) -> Selection:
    """The selection of a map without a floor (routes only): the region or corridor checked
    for itself (there is no map grid to check it against), no levels, no layers."""
    if region is not None and corridor is not None:
        raise SelectionError("region", "give a region or a corridor, not both")
    if region is not None:
        box = _region_box(region)
        return Selection((), (), region_m=box)
    if corridor is not None:
        if width_m is None or not math.isfinite(width_m) or width_m <= 0:
            raise SelectionError("width", f"corridor width must be a positive number of metres, got {width_m}")
        pts = np.asarray(corridor, float)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2 or not np.isfinite(pts).all():
            raise SelectionError("corridor", "needs at least 2 finite points (x, y)")
        pts = simplify_polyline(pts, 1e-3)
        if len(pts) < 2:
            raise SelectionError("corridor", "all its points are the same: no path")
        return Selection((), (), corridor_m=tuple((float(x), float(y)) for x, y in pts), width_m=float(width_m))
    if width_m is not None:
        raise SelectionError("width", "applies to a corridor only")
    return Selection((), ())


def _floor_selection(info: FloorInfo, *, region: Sequence[float] | None, corridor: np.ndarray | None,
                     width_m: float | None, levels: Sequence[int] | None, layers: Sequence[str]) -> Selection:
    """:func:`make_selection` without the routes."""
    layers = list(dict.fromkeys(layers))
    if not layers:
        raise SelectionError("layers", "no layer chosen")
    unknown = [name for name in layers if name not in LAYER_NAMES]
    if unknown:
        raise SelectionError("layers", f"unknown layer {unknown[0]!r} (layers: {', '.join(LAYER_NAMES)})")
    if INTENSITY in layers:
        lv = _parse_levels(levels, info)
    elif levels:
        raise SelectionError("levels", "levels apply to the intensity layer, which is not exported")
    else:
        lv = ()
    chosen = tuple(name for name in LAYER_NAMES if name in layers)
    gx0, gy0, gx1, gy1 = info.grid.bounds
    if region is not None and corridor is not None:
        raise SelectionError("region", "give a region or a corridor, not both")
    if region is not None:
        box = _region_box(region)
        if box[0] >= gx1 or box[2] <= gx0 or box[1] >= gy1 or box[3] <= gy0:
            raise SelectionError("region", f"box x {box[0]:g}..{box[2]:g}, y {box[1]:g}..{box[3]:g} m lies outside "
                                           f"the map (x {gx0:.3f}..{gx1:.3f}, y {gy0:.3f}..{gy1:.3f} m)")
        return Selection(lv, chosen, region_m=box)
    if corridor is not None:
        if width_m is None or not math.isfinite(width_m) or width_m <= 0:
            raise SelectionError("width", f"corridor width must be a positive number of metres, got {width_m}")
        pts = np.asarray(corridor, float)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
            raise SelectionError("corridor", "needs at least 2 points (x, y)")
        if not np.isfinite(pts).all():
            raise SelectionError("corridor", "holds a non-finite coordinate")
        pts = simplify_polyline(pts, SIMPLIFY_PX * info.grid.pixel_size)
        if len(pts) < 2:
            raise SelectionError("corridor", "all its points are the same: no path")
        sel = Selection(lv, chosen, corridor_m=tuple((float(x), float(y)) for x, y in pts), width_m=float(width_m))
        box = sel.box_m()
        if box[0] >= gx1 or box[2] <= gx0 or box[1] >= gy1 or box[3] <= gy0:
            raise SelectionError("corridor", f"path x {box[0]:g}..{box[2]:g}, y {box[1]:g}..{box[3]:g} m lies outside "
                                             f"the map (x {gx0:.3f}..{gx1:.3f}, y {gy0:.3f}..{gy1:.3f} m)")
        return sel
    if width_m is not None:
        raise SelectionError("width", "applies to a corridor only")
    return Selection(lv, chosen)


# --- routes -------------------------------------------------------------------------------


def crop_route(record: RouteRecord, sel: Selection) -> tuple[RouteRecord, int] | None:
    """``record`` cut to what ``sel`` keeps: ``(route, row0)`` with ``row0`` the map row of
    the kept route's row 0, or None when no row is kept.

    The whole map keeps every row. A region or corridor keeps the rows from the first to
    the last whose pose (x, y, metres) lies within ``sel.route_margin_m`` of it
    (:meth:`Selection.rows_inside`): a route is one contiguous path-length range, so rows
    between two passes through the selection stay. ``s0_m`` becomes the path length of
    the first kept row; everything else (spacing, sources, version, meta) is kept.
    """
    m = record.rows
    if sel.kind == "all":
        return record, 0
    if m == 0:
        return None
    inside = sel.rows_inside(record.poses[:, 0], record.poses[:, 1])
    if not inside.any():
        return None
    i0 = int(np.argmax(inside))
    i1 = m - int(np.argmax(inside[::-1]))
    if i0 == 0 and i1 == m:
        return record, 0
    cut = RouteRecord(record.lines[i0:i1], record.poses[i0:i1], s0_m=float(record.s0_m + i0 * record.spacing_m),
                      spacing_m=record.spacing_m, samples_per_degree=record.samples_per_degree,
                      horizon_band_deg=record.horizon_band_deg, version=record.version,
                      sources=[dict(x) for x in record.sources], meta=dict(record.meta))
    return cut, i0


# --- one version's extract ----------------------------------------------------------------


@dataclass(frozen=True)
class TileDerived:
    """An array derived per level-0 tile from the exported level-0 pixels.

    Attributes:
        path: zarr path in the bundle (e.g. ``floor/reloc/features``).
        record_shape: the per-tile record's shape (the array is ``(tile rows, tile cols,
            *record_shape)`` uint8, one chunk per tile, fill 0; an all-zero record is not
            stored).
        margin_px: level-0 pixels of context read around the tile (at most one tile).
        compute: ``(window) -> record``: ``window`` is the uint8 level-0 pixels of the tile
            and ``margin_px`` around it, ``(t + 2 m, t + 2 m)`` (0 outside the map and the
            selection; an edge tile's missing pixels are 0); must be deterministic.
        count: items in a record (e.g. features), for reports.
        attributes: the array's zarr attributes (JSON), e.g. how the records were made.
        manifest: what the manifest's ``derived`` entry says about the array (JSON),
            besides shape, chunks, dtype, tile_px and margin_px.
    """

    path: str
    record_shape: tuple[int, ...]
    margin_px: int
    compute: Callable[[np.ndarray], np.ndarray]
    count: Callable[[np.ndarray], int] = lambda rec: int(np.any(rec))
    attributes: Mapping[str, Any] = field(default_factory=dict)
    manifest: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ArrayPlan:
    """One exported array: zarr ``path`` (as in the map and the bundle), its ``grid``
    (level or layer grid; for a derived array the level-0 grid, its chunks the tiles), the
    bundle's ``chunk`` side (elements) and fill value; ``derived`` for a derived array."""

    path: str
    grid: MapGrid
    chunk: int
    fill: float | int
    derived: TileDerived | None = None


class Extract:
    """The members of one map version's bundle under a :class:`Selection`.

    Args:
        root: the map version's zarr root group (read-only).
        sel: what to export (its levels must exist in this version, else they are left out).
        zstd_level: zstd level of the bundle's chunks.
        derived: arrays derived per level-0 tile (:class:`TileDerived`); they need level 0
            in ``sel.levels`` (ValueError otherwise).
        route_chunk_rows: rows per chunk of the exported routes (0 = the map's chunks).

    After members were produced, ``derived_stats[path]`` holds ``tiles`` (records
    computed), ``seconds`` (spent computing them) and ``counts`` (member name -> items of
    each stored record).

    Routes (``/routes/<id>``, :mod:`mapstore.routes`) are staged when the extract is made
    (a route is small: 3.7 MB per km at 1 sample/degree and 10 cm before compression):
    ``routes`` lists the manifest entries of the routes held, ``route_chunks`` their
    chunk members (name -> bytes); their zarr.json members are in ``metadata``.
    """

    def __init__(self, root: zarr.Group, sel: Selection, zstd_level: int, derived: Sequence[TileDerived] = (),
                 route_chunk_rows: int = 0):
        self.root, self.sel = root, sel
        self._store: dict = {}
        staging = zarr.open_group(MemoryStore(store_dict=self._store), mode="w")
        staging.attrs.update(root.attrs.asdict())
        self.routes: list[dict] = []
        self.route_chunks: dict[str, bytes] = {}
        self._route_boxes: list[tuple[float, float, float, float]] = []
        self.derived_stats: dict[str, dict] = {}
        if "floor" not in root and ROUTES_GROUP in root:  # a map of route panoramas only
            if derived:
                raise ValueError("derived per-tile arrays need a floor; this map holds route panoramas only")
            self.info = None
            self.staging, self.plans = staging, []
            self.metadata = {k: v.to_bytes() for k, v in self._store.items()}
            self.metadata.update(self._stage_routes(int(zstd_level), int(route_chunk_rows)))
            return
        self.info = info = read_floor(root)
        spec = LayoutSpec(info.spec.chunk_px, info.spec.chunk_px, info.spec.layer_cell_px, int(zstd_level))
        levels = [k for k in sel.levels if k < info.levels]
        create_floor(staging, info.grid, spec, levels=levels, layers=sel.cell_layers, poses=False)
        set_version(staging, info.version)
        if derived and 0 not in levels:
            raise ValueError("derived per-tile arrays are computed from level 0, which this export leaves out")
        t = spec.chunk_px
        n_tiles = tuple(-(-n // t) for n in info.grid.shape)
        for d in derived:
            if not 0 <= d.margin_px <= t:
                raise ValueError(f"{d.path}: margin_px {d.margin_px} outside 0..{t} (one tile)")
            parent, name = d.path.rsplit("/", 1)
            staging.require_group(parent).create_array(
                name, shape=(*n_tiles, *d.record_shape), dtype="uint8", chunks=(1, 1, *d.record_shape),
                compressors=spec.compressor, fill_value=0,
                dimension_names=["tile_y", "tile_x", *(f"r{k}" for k in range(len(d.record_shape)))],
                attributes=dict(d.attributes))
        self.staging = staging
        self.metadata: dict[str, bytes] = {k: v.to_bytes() for k, v in self._store.items()}
        self.metadata.update(self._stage_routes(int(zstd_level), int(route_chunk_rows)))
        plans = [ArrayPlan(f"floor/{k}", info.level_grid(k), spec.chunk_px, 0) for k in levels]
        for name in sel.cell_layers:
            plans.append(ArrayPlan(f"floor/layers/{name}", info.layer_grid(name),
                                   int(staging[f"floor/layers/{name}"].chunks[0]), LAYERS[name][1]))
        plans += [ArrayPlan(d.path, info.grid, t, 0, d) for d in derived]
        self.plans = sorted(plans, key=lambda p: member_key(p.path + "/c"))
        self.derived_stats: dict[str, dict] = {d.path: {"tiles": 0, "seconds": 0.0, "counts": {}} for d in derived}

    @property
    def has_floor(self) -> bool:
        """False for a map of route panoramas only (``info`` is None, no floor arrays)."""
        return self.info is not None

    @property
    def version(self) -> int:
        """The map version number: the floor's, or (routes only) the routes' highest."""
        if self.info is not None:
            return self.info.version
        return max([0] + [int(route_attrs(self.root, rid).get("version", 0)) for rid in list_routes(self.root)])

    @property
    def map_id(self) -> str:
        return self.info.map_id if self.info is not None else str(self.root.attrs.get("map_id", ""))

    def routes_bounds(self) -> list[float] | None:
        """World box ``[xmin, ymin, xmax, ymax]`` (metres) of the exported route poses (None
        when no route is exported)."""
        if not self._route_boxes:
            return None
        b = np.asarray(self._route_boxes, float)
        return [float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())]

    def plan(self, path: str) -> ArrayPlan | None:
        return next((p for p in self.plans if p.path == path), None)

    def _stage_routes(self, zstd_level: int, chunk_rows: int) -> dict[str, bytes]:
        """Encode the selected routes (cropped by :func:`crop_route`) with
        :func:`mapstore.routes.write_route` into members: fills ``routes`` and
        ``route_chunks``, returns the routes' zarr.json members."""
        if chunk_rows < 0:
            raise ValueError(f"route_chunk_rows must be >= 0, got {chunk_rows}")
        store: dict = {}
        group = zarr.open_group(MemoryStore(store_dict=store), mode="w")
        for rid in self.sel.route_ids(list_routes(self.root)):
            record = read_route(self.root, rid)
            cut = crop_route(record, self.sel)
            if cut is None:
                continue
            out, row0 = cut
            rows = chunk_rows or int(self.root[f"{ROUTES_GROUP}/{rid}/lines"].chunks[0])
            write_route(group, rid, out, zstd_level=zstd_level, rows_per_chunk=rows)
            if out.rows:
                xy = out.poses[:, :2].astype(float)
                self._route_boxes.append((xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max()))
            self.routes.append({
                "id": rid, "rows": out.rows, "s0_m": float(out.s0_m), "spacing_m": float(out.spacing_m),
                "samples_per_degree": float(out.samples_per_degree), "length_m": float(out.length_m),
                "version": int(out.version), "row0": int(row0), "rows_in_map": record.rows,
                "cropped": out.rows != record.rows})
        meta: dict[str, bytes] = {}
        for key, buf in store.items():
            if key.startswith(ROUTES_GROUP + "/"):
                (meta if key.endswith("zarr.json") else self.route_chunks)[key] = buf.to_bytes()
        return meta

    def candidates(self, plan: ArrayPlan) -> list[tuple[int, int]]:
        """The chunks of ``plan`` the selection may reach, row-major."""
        return self.sel.chunk_candidates(plan.grid, plan.chunk)

    def rows(self, plan: ArrayPlan, ids: Iterable[tuple[int, int]]) -> Iterator[tuple[int, dict[str, bytes]]]:
        """For each chunk row of ``ids`` (ascending): ``(row, {member name: bytes})`` of the
        chunks of that row holding kept data (the others are absent from the bundle)."""
        by_row: dict[int, list[int]] = {}
        for i, j in ids:
            by_row.setdefault(int(i), []).append(int(j))
        if plan.derived is not None:
            yield from self._derived_rows(plan, by_row)
            return
        src = self.root[plan.path] if plan.path in self.root else None
        dst = self.staging[plan.path]
        rows, cols = plan.grid.shape
        ch = plan.chunk
        for i in sorted(by_row):
            out: dict[str, bytes] = {}
            for run in _runs(sorted(set(by_row[i]))):
                r0, r1 = i * ch, min((i + 1) * ch, rows)
                c0, c1 = run[0] * ch, min((run[-1] + 1) * ch, cols)
                if src is None or r0 >= src.shape[0] or c0 >= src.shape[1]:
                    continue  # beyond this version's array: no data
                data = np.full((r1 - r0, c1 - c0), plan.fill, dtype=dst.dtype)
                sr1, sc1 = min(r1, src.shape[0]), min(c1, src.shape[1])
                data[: sr1 - r0, : sc1 - c0] = src[r0:sr1, c0:sc1]
                mask = self.sel.window_mask(plan.grid, slice(r0, r1), slice(c0, c1))
                if mask is not None:
                    data[~mask] = plan.fill
                dst[r0:r1, c0:c1] = data
                for j in run:
                    buf = self._store.pop(f"{plan.path}/c/{i}/{j}", None)
                    if buf is not None:
                        out[f"{plan.path}/c/{i}/{j}"] = buf.to_bytes()
            for key in [k for k in self._store if not k.endswith("zarr.json")]:
                del self._store[key]  # (none expected: every written chunk was taken)
            yield i, out

    def level0_window(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The exported level-0 pixels ``[r0, r1) x [c0, c1)`` (uint8; the box may reach
        beyond the map): what the bundle's level 0 holds there, 0 outside the map and the
        selection."""
        out = np.zeros((r1 - r0, c1 - c0), np.uint8)
        src = self.root["floor/0"]
        a0, a1 = max(r0, 0), min(r1, self.info.grid.shape[0], src.shape[0])
        b0, b1 = max(c0, 0), min(c1, self.info.grid.shape[1], src.shape[1])
        if a0 >= a1 or b0 >= b1:
            return out
        data = src[a0:a1, b0:b1]
        mask = self.sel.window_mask(self.info.grid, slice(a0, a1), slice(b0, b1))
        if mask is not None:
            data[~mask] = 0
        out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = data
        return out

    def _derived_rows(self, plan: ArrayPlan, by_row: dict[int, list[int]]) -> Iterator[tuple[int, dict[str, bytes]]]:
        """:meth:`rows` of a derived array: each tile's record from its level-0 window."""
        d, t, m = plan.derived, plan.chunk, plan.derived.margin_px
        dst = self.staging[plan.path]
        stats = self.derived_stats[plan.path]
        tail = "/0" * len(d.record_shape)
        for i in sorted(by_row):
            out: dict[str, bytes] = {}
            for run in _runs(sorted(set(by_row[i]))):
                win = self.level0_window(i * t - m, (i + 1) * t + m, run[0] * t - m, (run[-1] + 1) * t + m)
                recs = np.zeros((1, len(run), *d.record_shape), np.uint8)
                t0 = time.perf_counter()
                for k, j in enumerate(run):
                    rec = np.asarray(d.compute(win[:, k * t:(k + 1) * t + 2 * m]), np.uint8)
                    if rec.shape != d.record_shape:
                        raise ValueError(f"{plan.path}: a record of shape {rec.shape}, expected {d.record_shape}")
                    recs[0, k] = rec
                stats["seconds"] += time.perf_counter() - t0
                stats["tiles"] += len(run)
                dst[i:i + 1, run[0]:run[-1] + 1] = recs  # one write per run (all-zero records are not stored)
                for k, j in enumerate(run):
                    name = f"{plan.path}/c/{i}/{j}{tail}"
                    buf = self._store.pop(name, None)
                    if buf is not None:
                        out[name] = buf.to_bytes()
                        stats["counts"][name] = int(d.count(recs[0, k]))
            yield i, out

    def members(self, progress: Progress | None = None) -> Iterator[tuple[str, bytes]]:
        """Every member of the full bundle but the manifest, in :func:`member_key` order."""
        yield from sorted(self.metadata.items(), key=lambda kv: member_key(kv[0]))
        work = [(plan, self.candidates(plan)) for plan in self.plans]
        total = sum(len({i for i, _ in ids}) for _, ids in work)
        rows = (row for plan, ids in work for row in self.rows(plan, ids))
        if progress is not None:
            rows = progress(rows, length=total, label="export")
        for _, chunks in rows:
            yield from chunks.items()
        yield from sorted(self.route_chunks.items(), key=lambda kv: member_key(kv[0]))


def _runs(js: list[int]) -> Iterator[list[int]]:
    """Runs of consecutive integers in a sorted list."""
    run: list[int] = []
    for j in js:
        if run and j != run[-1] + 1:
            yield run
            run = []
        run.append(j)
    if run:
        yield run


def bundle_header(ext: Extract, *, kind: str, snapshot: str, tags: Sequence[str], created: str | None = None) -> dict:
    """The manifest header of ``ext``'s bundle (every key but members and content_sha256)."""
    info = ext.info
    levels = {str(int(p.path.split("/")[1])): {"shape": list(p.grid.shape), "pixel_size_m": p.grid.pixel_size,
                                               "chunks": [p.chunk, p.chunk]}
              for p in ext.plans if not p.path.startswith("floor/layers/") and p.derived is None}
    layers = {}
    for p in ext.plans:
        if p.path.startswith("floor/layers/"):
            name = p.path.rsplit("/", 1)[1]
            layers[name] = {"shape": list(p.grid.shape), "cell_px": int(round(p.grid.pixel_size / info.grid.pixel_size)),
                            "chunks": [p.chunk, p.chunk], "dtype": LAYERS[name][0]}
    derived = {p.path: {**p.derived.manifest, "shape": list(ext.staging[p.path].shape),
                        "chunks": list(ext.staging[p.path].chunks), "dtype": "uint8", "tile_px": p.chunk,
                        "margin_px": p.derived.margin_px}
               for p in ext.plans if p.derived is not None}
    if info is None:  # route panoramas only: no grid, levels or layers; bounds of the routes
        box = ext.sel.box_m()
        return {
            "format": BUNDLE_FORMAT, "format_version": BUNDLE_FORMAT_VERSION, "kind": kind, "map_id": ext.map_id,
            "version": {"snapshot": snapshot, "tags": sorted(tags), "number": ext.version},
            "created": created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "selection": ext.sel.to_manifest(), "routes_only": True,
            "bounds_m": list(box) if box is not None else (ext.routes_bounds() or [0.0, 0.0, 0.0, 0.0]),
            "grid": None, "tile_px": None, "levels": {}, "layers": {},
            "routes": [dict(r) for r in ext.routes],
        }
    return {
        **({"derived": derived} if derived else {}),
        "format": BUNDLE_FORMAT, "format_version": BUNDLE_FORMAT_VERSION, "kind": kind, "map_id": info.map_id,
        "version": {"snapshot": snapshot, "tags": sorted(tags), "number": info.version},
        "created": created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "selection": ext.sel.to_manifest(), "bounds_m": ext.sel.bounds_in(info.grid),
        "grid": info.grid.to_attrs(), "tile_px": info.spec.chunk_px, "levels": levels, "layers": layers,
        "routes": [dict(r) for r in ext.routes],
    }


# --- writing ------------------------------------------------------------------------------


class DirectorySink(MemberSink):
    """Members as plain files under ``directory`` (a zarr v3 directory store), the manifest
    beside them as ``manifest.json``. The caller makes the directory appear atomically
    (write into a temporary one, rename)."""

    def __init__(self, directory: str | Path):
        super().__init__()
        self.directory = Path(directory)

    def _store(self, name: str, data: bytes) -> None:
        path = self.directory / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)

    def _close(self, manifest: bytes) -> None:
        (self.directory / MANIFEST).write_bytes(manifest)


OME_ZARR_ROOT = "map.zarr"  # the zarr hierarchy's directory inside an OME-Zarr export
OME_LAYERS = "layers"  # group of the layers' images in it
_LAYER_MEMBER = re.compile(r"^floor/layers/([^/]+)/(.+)$")


def ome_layer_group(name: str, array_meta: dict) -> dict:
    """The zarr.json (a dict) of layer ``name``'s OME-Zarr 0.5 image group: one dataset
    ``0`` (the layer's array) on the layer's own grid (its attributes' ``grid``; axes y, x
    in metres as the floor's, :meth:`MapGrid.ome_transformations`)."""
    attrs = array_meta.get("attributes", {})
    grid = MapGrid.from_attrs(attrs["grid"])
    return {"zarr_format": 3, "node_type": "group", "attributes": {
        "ome": {"version": "0.5", "multiscales": [{
            "name": name,
            "axes": [{"name": "y", "type": "space", "unit": "meter"}, {"name": "x", "type": "space", "unit": "meter"}],
            "datasets": [{"path": "0", "coordinateTransformations": grid.ome_transformations()}]}]},
        "mosaicmap": {"layer": name, "description": attrs.get("description", ""), "units": attrs.get("units", ""),
                      "cell_px": attrs.get("cell_px")}}}


class OmeZarrSink(DirectorySink):
    """The OME-Zarr export: ``directory/map.zarr`` is the zarr v3 hierarchy and nothing
    else (the intensity pyramid ``floor`` is an OME-Zarr 0.5 multiscale image as in the
    map; each layer is its own single-scale image ``layers/<name>`` with dataset ``0``,
    moved from the map's ``floor/layers/<name>`` array), ``directory/manifest.json`` the
    manifest beside it (its member names are keys of ``map.zarr``; its ``ome_zarr`` entry
    lists the images to open). Members arrive in bundle order; the names written are
    their OME names."""

    def __init__(self, directory: str | Path):
        super().__init__(directory)
        self.images: dict[str, str] = {}

    def add(self, name: str, data: bytes) -> None:
        if name == "floor/layers/zarr.json":
            return  # the layers leave the floor: their group there would stay empty
        m = _LAYER_MEMBER.match(name)
        if m is not None:
            layer, rest = m.groups()
            if rest == "zarr.json":
                if f"{OME_LAYERS}/zarr.json" not in self.members:
                    self._put(f"{OME_LAYERS}/zarr.json", json.dumps(
                        {"zarr_format": 3, "node_type": "group", "attributes": {"mosaicmap": {
                            "description": "the map's layers, each an OME-Zarr image of one scale"}}}).encode())
                group = ome_layer_group(layer, json.loads(data))
                self._put(f"{OME_LAYERS}/{layer}/zarr.json", json.dumps(group).encode())
                self.images[layer] = f"{OME_ZARR_ROOT}/{OME_LAYERS}/{layer}"
            name = f"{OME_LAYERS}/{layer}/0/{rest}"
        elif name == "floor/zarr.json":
            self.images["intensity"] = f"{OME_ZARR_ROOT}/floor"
        self._put(name, data)

    def _put(self, name: str, data: bytes) -> None:
        bad = check_member_name(name)
        if bad or name in self.members:
            raise ValueError(f"member {name!r}: {bad or 'repeated'}")
        self.members[name] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
        self._store(name, data)

    def _store(self, name: str, data: bytes) -> None:
        super()._store(f"{OME_ZARR_ROOT}/{name}", data)

    def finish(self, header: dict) -> dict:
        images = dict(sorted(self.images.items(), key=lambda kv: kv[0] != "intensity"))
        return super().finish({**header, "ome_zarr": {"root": OME_ZARR_ROOT, "version": "0.5", "images": images}})


class HashingSink(MemberSink):
    """Stores nothing: only the members' SHA-256 and sizes, i.e. the manifest a full export
    would write (what a signed delta's result signature is computed from)."""

    def _store(self, name: str, data: bytes) -> None:
        pass

    def _close(self, manifest: bytes) -> None:
        pass


def _count(members: Iterator[tuple[str, bytes]], stats: dict) -> Iterator[tuple[str, bytes]]:
    for name, data in members:
        if not name.endswith("zarr.json"):
            stats["tiles"] = stats.get("tiles", 0) + 1
            array = name.rsplit("/c/", 1)[0]
            stats.setdefault("tiles_by_array", {})[array] = stats["tiles_by_array"].get(array, 0) + 1
        yield name, data


def export_extract(ext: Extract, sink: MemberSink, *, snapshot: str, tags: Sequence[str] = (),
                   created: str | None = None, progress: Progress | None = None) -> dict:
    """Write ``ext``'s full bundle into ``sink``; returns the manifest plus ``stats``
    (tiles: chunk members written, tiles_by_array). Raises SelectionError("selection")
    when the selection holds no map data (the sink is aborted)."""
    header = bundle_header(ext, kind="full", snapshot=snapshot, tags=tags, created=created)
    stats: dict = {"tiles": 0, "tiles_by_array": {}}
    with sink:
        for name, data in _count(ext.members(progress), stats):
            sink.add(name, data)
        if stats["tiles"] == 0:
            raise SelectionError("selection", f"holds no map data ({_what(ext.sel)} of version "
                                              f"{ext.version})")
        manifest = sink.finish(header)
    return {**manifest, "stats": stats}


def _what(sel: Selection) -> str:
    return {"all": "the whole map", "region": f"region {list(sel.region_m or ())}",
            "corridor": f"a {sel.width_m} m corridor"}[sel.kind]


def _sha(data: bytes | None) -> str | None:
    return None if data is None else hashlib.sha256(data).hexdigest()


def _units_to_chunks(units: Iterable[tuple[int, ...]], unit: tuple[int, int], chunk: int,
                     shape: tuple[int, int]) -> set[tuple[int, int]]:
    """Bundle chunks covering the map's storage units (shards or chunks of ``unit``
    elements) ``units`` of an array of ``shape``."""
    out: set[tuple[int, int]] = set()
    for ui, uj in units:
        r0, r1 = ui * unit[0], min((ui + 1) * unit[0], shape[0])
        c0, c1 = uj * unit[1], min((uj + 1) * unit[1], shape[1])
        if r0 >= r1 or c0 >= c1:
            continue
        out.update((i, j) for i in range(r0 // chunk, (r1 - 1) // chunk + 1)
                   for j in range(c0 // chunk, (c1 - 1) // chunk + 1))
    return out


def export_delta(new: Extract, base: Extract, changed_units: dict[str, set[tuple[int, ...]]], sink: MemberSink, *,
                 snapshot: str, tags: Sequence[str] = (), base_snapshot: str, created: str | None = None,
                 progress: Progress | None = None) -> dict:
    """Write the delta from ``base``'s bundle to ``new``'s (same selection) into ``sink``.

    Args:
        new, base: the extracts of the new and the base version (base an ancestor).
        changed_units: the repository's chunk diff base -> new (array path -> shard or
            chunk indices of the map's arrays).
        snapshot, tags: the new version's; base_snapshot: the base's.

    Returns the delta's manifest plus ``stats``: tiles (chunk members carried),
    tiles_by_array, removed, candidates (tiles encoded per version), selected_tiles (chunk
    slots of the new bundle's arrays the selection reaches).
    """
    result = bundle_header(new, kind="full", snapshot=snapshot, tags=tags, created=created)
    header = {**result, "kind": "delta", "base": {"snapshot": base_snapshot, "number": base.version},
              "result": result}
    base_members: dict[str, str | None] = {}
    removed: dict[str, str] = {}
    stats: dict = {"tiles": 0, "tiles_by_array": {}, "candidates": 0, "selected_tiles": 0}
    with sink:
        for name in sorted(set(new.metadata) | set(base.metadata), key=member_key):
            if name in new.metadata:
                if new.metadata[name] == base.metadata.get(name):
                    continue  # the base's zarr.json is the new one: apply-delta keeps it
                sink.add(name, new.metadata[name])
                base_members[name] = _sha(base.metadata.get(name))
            else:
                removed[name] = _sha(base.metadata[name])
        # level-0 tiles whose bytes differ (filled below, before any derived array is reached:
        # the plans are in member order, floor/0 first)
        changed0: set[tuple[int, int]] = set()
        work = []
        for plan in new.plans:
            candidates = new.candidates(plan)
            stats["selected_tiles"] += len(candidates)
            if plan.derived is not None:
                src = new.root["floor/0"]
                units = changed_units.get("floor/0", ())
            else:
                src = new.root[plan.path]
                units = changed_units.get(plan.path, ())
            unit = tuple(src.shards or src.chunks)
            touched = _units_to_chunks(units, unit, plan.chunk, plan.grid.shape)
            if plan.derived is not None:
                touched = _dilate(touched, plan.derived.margin_px, plan.chunk)
            if base.plan(plan.path) is None:
                touched = set(candidates)  # an array the base bundle does not hold: all of it is new
            work.append((plan, candidates, sorted(set(candidates) & touched)))
        total = sum(len({i for i, _ in ids}) for _, _, ids in work)  # derived: an upper bound

        def narrowed(plan: ArrayPlan, candidates: list, ids: list) -> list[tuple[int, int]]:
            if plan.derived is None or base.plan(plan.path) is None:
                return ids
            near = _dilate(changed0, plan.derived.margin_px, plan.chunk)
            return sorted(set(ids) & near)

        def pairs():
            for plan, candidates, ids in work:
                ids = narrowed(plan, candidates, ids)  # evaluated once floor/0's rows are done
                stats["candidates"] += len(ids)
                for pair in zip(new.rows(plan, ids), _base_rows(base, plan, ids)):
                    yield plan, pair

        rows = pairs()
        if progress is not None:
            rows = progress(rows, length=total, label="delta")
        for plan, ((_, new_row), (_, old_row)) in rows:
            for name in sorted(set(new_row) | set(old_row), key=member_key):
                a, b = new_row.get(name), old_row.get(name)
                if a == b:
                    continue
                if plan.path == "floor/0":
                    i, j = name.rsplit("/", 2)[1:]
                    changed0.add((int(i), int(j)))
                if a is None:
                    removed[name] = _sha(b)
                    continue
                sink.add(name, a)
                base_members[name] = _sha(b)
                stats["tiles"] += 1
                stats["tiles_by_array"][plan.path] = stats["tiles_by_array"].get(plan.path, 0) + 1
        # routes: every chunk of both versions is encoded already (routes are small); the
        # chunks whose bytes differ are carried, those the new version lacks removed
        route_names = sorted(set(new.route_chunks) | set(base.route_chunks), key=member_key)
        stats["selected_tiles"] += len(new.route_chunks)
        stats["candidates"] += len(route_names)
        for name in route_names:
            a, b = new.route_chunks.get(name), base.route_chunks.get(name)
            if a == b:
                continue
            if a is None:
                removed[name] = _sha(b)
                continue
            sink.add(name, a)
            base_members[name] = _sha(b)
            array = name.rsplit("/c/", 1)[0]
            stats["tiles"] += 1
            stats["tiles_by_array"][array] = stats["tiles_by_array"].get(array, 0) + 1
        header.update({"changed": sorted(sink.members, key=member_key), "base_members": base_members,
                       "removed": removed})
        manifest = sink.finish(header)
    stats["removed"] = len(removed)
    return {**manifest, "stats": stats}


def _dilate(tiles: Iterable[tuple[int, int]], margin_px: int, chunk: int) -> set[tuple[int, int]]:
    """``tiles`` and their neighbours within ``margin_px`` pixels (tiles of ``chunk`` px):
    the tiles whose derived records may read a pixel of ``tiles``."""
    k = -(-int(margin_px) // int(chunk))
    return {(i + di, j + dj) for i, j in tiles for di in range(-k, k + 1) for dj in range(-k, k + 1)}


def _base_rows(base: Extract, plan: ArrayPlan, ids: list[tuple[int, int]]) -> Iterator[tuple[int, dict[str, bytes]]]:
    """The base version's chunk rows of ``ids`` (empty rows when the array is new)."""
    bplan = base.plan(plan.path)
    if bplan is None or bplan.chunk != plan.chunk:
        for i in sorted({i for i, _ in ids}):
            yield i, {}
        return
    # the new grid may have grown: keep the ids inside the base's array
    yield from base.rows(bplan, ids)
