"""Outputs of ``mosaicmap diff``: the JSON report, a GeoJSON of the regions, a PNG overlay and
one self-contained HTML page.

Files written into ``--out DIR`` (each atomically: temporary name, then rename):

- ``diff.json``: the report (:func:`report_dict`; the same as ``--report FILE``).
- the regions, one of (:func:`regions_document`; the other name is removed from DIR):

  - ``regions.geojson`` when the map has a geographic reference (a map of geotagged logs:
    root attribute ``geo_reference``, :class:`mapstore.grid.GeoReference`): an RFC 7946
    FeatureCollection, one Polygon per region in WGS 84 longitude, latitude (degrees), as
    GIS tools read it; each feature's properties are the report's region (``bbox_m``,
    ``centroid_m`` in the map's metres) plus ``polygon_m``;
  - ``regions.json`` otherwise: the same regions in the map's local floor frame (x, y
    metres, :mod:`mapstore.grid`), ``{"format": "mosaicmap-regions", "crs": "local metres",
    "frame", "units": "metre", "map_id", "from_snapshot", "to_snapshot", "grid", "regions":
    [{...the report's region..., "polygon_m": rings of [x, y]}]}``: deliberately not GeoJSON,
    which GIS tools would read as degrees of WGS 84.
- ``overlay.png``: the whole TO map at a coarse pyramid level (``[diff.report]
  overview_max_px``), drawn to be read (:mod:`pipeline.map_figures`: axes in metres, scale
  bar, north arrow, legend): compared (changed) tiles tinted blue, new-coverage tiles
  green (added), coverage TO lost magenta (removed), regions filled red (orange:
  localization at risk) with their ids (:data:`OVERLAY_LEGEND`).
- ``diff.html``: FROM, TO and the overlay side by side (a CSS grid: three columns on a
  wide screen, wrapping on a narrow one), the region table (each region with crops links
  to them, anchor ``region-<id>``) and, per region, FROM / TO / overlay crops at the
  finest level that fits ``crop_max_px`` (level 0 for regions up to that size); every
  image embedded as a base64 PNG data URI, no network access. With ``--truth``, the
  per-change table and the false regions.

Images are read from the two versions' pyramids (a few small windows), never whole levels
beyond the overview's.

Report keys (``diff.json`` / ``--report``; units: metres, m^2, grey levels of 0..255):

- ``repository``, ``map_id``, ``from`` / ``to``: ``version`` (as given), ``snapshot``,
  ``publish_version``; ``frame`` (the coordinates' frame), ``grid`` (TO's level-0
  MapGrid), ``grown`` (TO's grid larger than FROM's).
- ``tiles``: ``tile_px``, ``shards_changed`` (icechunk diff of floor/0), ``rewritten``
  (tiles of those shards whose ``updated`` is newer than FROM), ``identical`` (rewritten,
  same bytes), ``changed`` (compared), ``new_coverage`` (FROM had no data), and the
  ``changed_list`` / ``new_coverage_list`` of (row, col) tile indices.
- ``coverage``: ``new_m2`` (pixels TO covers and FROM did not, in rewritten tiles),
  ``lost_m2``, ``compared_m2`` (both cover, in changed tiles), ``observed_m2`` (of those,
  rewritten by TO's frames: values differ).
- ``detection``: ``noise_grey``, ``threshold_grey`` (medians over ``windows``),
  ``ignored_smooth``: candidates dropped for soft edges (``area_m2``, ``part_of_region``,
  ``edge_step_grey``, ``mean_abs_residual_grey``, ``bbox_px``).
- ``summary``: ``regions``, ``changed_m2``, ``at_risk``, ``ignored_smooth`` (counts).
- ``regions``: per region ``id``, ``area_m2``, ``area_cm2``, ``bbox_m`` (xmin, ymin, xmax,
  ymax), ``centroid_m``, ``bbox_px`` (row0, row1, col0, col1 at level 0), ``contrast_grey``
  (mean TO - g FROM), ``mean_abs_residual_grey``, ``texture_before`` / ``_after``,
  ``uniqueness_before`` / ``_after`` (medians of the layer cells under it),
  ``layer_cells``, ``risk`` ("at_risk", "already_poor", "ok", "unknown"), ``at_risk``,
  ``reasons``.
- ``truth`` (with ``--truth``): ``mask``, ``alignment`` (``source`` "ground_truth" or
  "identity", ``frames``, ``rms_m``, ``rotation_rad``, ``translation_m``, ``note``),
  ``definitions``, ``changes`` (``id``, ``kinds``, ``area_m2``, ``bbox_m``,
  ``observed_fraction``, ``status`` detected/missed/unobserved, ``recall``, ``iou``,
  ``regions``), ``false_regions`` (``id``, ``area_m2``, ``bbox_m``, ``centroid_m``),
  ``summary`` (``changes``, ``observed``, ``detected``, ``missed``, ``unobserved``,
  ``min_iou_observed``, ``false_regions``, ``max_false_area_cm2``).
- ``routes`` (the route panoramas, :func:`mapstore.diff.diff_routes`; metres, degrees,
  grey levels): ``from`` / ``to`` (ids each version holds), ``added`` / ``removed``
  (``id``, ``rows``, ``s0_m``, ``length_m``, ``spacing_m``, ``samples_per_degree``,
  ``version``), ``unchanged`` (ids), ``changed`` (per route: ``id``, ``from_version``,
  ``to_version``, ``rows_from``, ``rows_to``, ``step_m`` and ``rows_compared`` of the common
  path-length grid, ``s_compared_m`` [first, last], ``s_only_from_m`` / ``s_only_to_m``
  (ranges one version holds alone), ``azimuth_resampled``, ``azimuth_threshold`` (applied
  to the averaged difference of the normalized lines), ``score_median``,
  ``score_max`` (1 - NCC of the normalized lines per row), ``mad_median_grey``,
  ``mad_max_grey`` (mean absolute difference per row), ``changed_rows``,
  ``changed_length_m``, ``ranges`` (``s_m`` [first, last row], ``length_m``, ``rows``,
  ``score_max``, ``score_mean``, ``mad_mean_grey``, ``sectors``: ``start_deg``,
  ``end_deg`` (counter-clockwise from the vehicle's +x; end < start when the sector wraps
  through 0), ``width_deg``, ``row_fraction``, ``mean_abs_grey``),
  ``pose_move_max_m``, ``pose_move_max_deg``, ``pose_move_at_s_m``, ``pose_moved``, and
  with ``[diff.routes] profile`` a ``profile`` {``s0_m``, ``step_m``, ``score``,
  ``mad_grey``} per row), ``summary`` (``from``, ``to``, ``added``, ``removed``,
  ``unchanged``, ``changed``, ``changed_ranges``, ``changed_length_m``, ``sectors``,
  ``pose_moved``).
- ``parameters`` (``config_hash``, the ``[diff]`` table), ``seconds`` (``chunks``,
  ``read``, ``detect``, ``regions``, ``routes``, ``total``, ``truth``, ``outputs``,
  ``command``), ``outputs`` (name -> path, with ``--out``; ``route_<id>`` for each route
  figure; ``regions`` is the path of regions.geojson or regions.json), ``geo_reference``
  (with ``--out``: TO's geographic reference, :meth:`mapstore.grid.GeoReference.to_attrs`, or
  null).

Route figures (``route-<id>.png`` and in ``diff.html``, for the changed routes holding a
changed range or moved poses, at most ``[diff.report] max_route_figures``; drawn by
:func:`pipeline.map_figures.annotated_route_panels`, as quicklook draws a route): FROM's
lines, TO's lines and the absolute difference of the normalized lines (inferno, 0 .. 1.5
and more) side by side, with axes (azimuth in degrees under each panel, path length s in
metres left), a colour bar for the grey levels and one for the difference, a title naming
the two versions and a legend (:data:`ROUTE_LEGEND`); rows = path length downward over the
common grid (averaged in blocks of rows to at most ``route_figure_rows``), columns = azimuth
0..360 deg (counter-clockwise from the vehicle's forward); changed ranges are marked by a
red bar at each panel's left edge, changed sectors by cyan boxes.
"""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path

import cv2
import numpy as np
import zarr

from mapstore.diff import DiffResult, Region, RouteChange, RoutesDiff
from mapstore.grid import GeoReference, MapGrid
from pipeline.fsutil import write_json_atomic, write_text_atomic
from pipeline.map_figures import ColourScale, LegendKey

__all__ = ["FRAME_NOTE", "report_dict", "routes_dict", "route_change_dict", "route_figure", "geojson_dict",
           "regions_local_dict", "regions_document", "OVERLAY_LEGEND", "ROUTE_LEGEND", "overview_figures",
           "overview_images", "region_crops", "html_page", "write_outputs", "write_report_file", "summary_lines"]

FRAME_NOTE = ("map-local floor frame of the map grid: x, y in metres, x along the grid's columns, y against its "
              "rows (not geographic)")
OUTPUT_FILES = {"report": "diff.json", "regions": "regions.json", "overlay": "overlay.png", "html": "diff.html"}
GEOJSON_FILE = "regions.geojson"  # the regions' name instead of regions.json when the map has a geo_reference

RED = (220, 30, 30)
ORANGE = (255, 150, 0)
BLUE = (60, 120, 255)
GREEN = (40, 200, 60)
MAGENTA = (200, 40, 200)
# What the overlay's colours mark (its legend; the same words in diff.html).
OVERLAY_LEGEND = (
    LegendKey(RED, "changed region"),
    LegendKey(ORANGE, "changed region, localization at risk"),
    LegendKey(BLUE, "tile compared (rewritten by TO, values differ)"),
    LegendKey(GREEN, "new coverage: added (FROM had no data)"),
    LegendKey(MAGENTA, "coverage lost: removed (TO has no data)"),
)
# The route figures' marks and the colour scale of their difference panel.
ROUTE_RANGE_COLOUR = RED
ROUTE_SECTOR_COLOUR = (0, 220, 255)
ROUTE_LEGEND = (
    LegendKey(ROUTE_RANGE_COLOUR, "changed path range (bar at the left edge of each panel)"),
    LegendKey(ROUTE_SECTOR_COLOUR, "changed azimuth sector of a changed range"),
)
ROUTE_DIFF_SCALE = ColourScale("inferno", 0.0, 1.5, "|difference| of normalized lines")


def _r(v: float | None, nd: int = 6) -> float | None:
    return None if v is None else round(float(v), nd)


# --- the report ---------------------------------------------------------------------------


def region_dict(reg: Region) -> dict:
    """One region as the report and the GeoJSON properties give it."""
    imp = reg.impact
    return {
        "id": reg.id,
        "area_m2": _r(reg.area_m2, 8),
        "area_cm2": _r(reg.area_m2 * 1e4, 2),
        "bbox_m": [_r(v) for v in reg.bbox_m],
        "centroid_m": [_r(v) for v in reg.centroid_m],
        "bbox_px": [int(v) for v in reg.bbox_px],
        "contrast_grey": _r(reg.contrast, 2),
        "mean_abs_residual_grey": _r(reg.mean_abs_residual, 2),
        "texture_before": _r(imp.texture_before, 4),
        "texture_after": _r(imp.texture_after, 4),
        "uniqueness_before": _r(imp.uniqueness_before, 4),
        "uniqueness_after": _r(imp.uniqueness_after, 4),
        "layer_cells": imp.cells,
        "risk": imp.risk,
        "at_risk": imp.at_risk,
        "reasons": list(imp.reasons),
    }


def _range_list(ranges) -> list[list[float]]:
    return [[_r(a), _r(b)] for a, b in ranges]


def route_change_dict(ch: RouteChange, profile: bool = True) -> dict:
    """One changed route as the report gives it (see the module docstring)."""
    n = len(ch.s)
    out = {
        "id": ch.id, "from_version": ch.from_version, "to_version": ch.to_version,
        "rows_from": ch.rows_from, "rows_to": ch.rows_to, "step_m": _r(ch.step_m), "rows_compared": n,
        "s_compared_m": [_r(ch.s[0]), _r(ch.s[-1])] if n else None,
        "s_only_from_m": _range_list(ch.s_only_from), "s_only_to_m": _range_list(ch.s_only_to),
        "azimuth_resampled": ch.azimuth_resampled, "azimuth_threshold": _r(ch.azimuth_threshold, 4),
        "score_median": _r(np.median(ch.score), 4) if n else None,
        "score_max": _r(ch.score.max(), 4) if n else None,
        "mad_median_grey": _r(np.median(ch.mad), 2) if n else None,
        "mad_max_grey": _r(ch.mad.max(), 2) if n else None,
        "changed_rows": int(ch.changed.sum()),
        "changed_length_m": _r(sum(r.length_m for r in ch.ranges)),
        "ranges": [{"s_m": [_r(r.s_m[0]), _r(r.s_m[1])], "length_m": _r(r.length_m), "rows": r.i1 - r.i0,
                    "score_max": _r(r.score_max, 4), "score_mean": _r(r.score_mean, 4),
                    "mad_mean_grey": _r(r.mad_mean_grey, 2), "sectors": [dict(x) for x in r.sectors]}
                   for r in ch.ranges],
        "pose_move_max_m": _r(ch.pose_move_max_m), "pose_move_max_deg": _r(ch.pose_move_max_deg, 4),
        "pose_move_at_s_m": _r(ch.pose_move_at_s_m), "pose_moved": ch.pose_moved,
    }
    if profile:
        out["profile"] = {"s0_m": _r(ch.s[0]) if n else None, "step_m": _r(ch.step_m),
                          "score": np.round(ch.score.astype(np.float64), 4).tolist(),
                          "mad_grey": np.round(ch.mad.astype(np.float64), 2).tolist()}
    return out


def routes_dict(rd: RoutesDiff, profile: bool = True) -> dict:
    """The report's ``routes`` entry (see the module docstring)."""
    changed = [route_change_dict(ch, profile) for ch in rd.changed]
    return {
        "from": list(rd.from_ids), "to": list(rd.to_ids), "added": [dict(a) for a in rd.added],
        "removed": [dict(r) for r in rd.removed], "unchanged": list(rd.unchanged), "changed": changed,
        "summary": {"from": len(rd.from_ids), "to": len(rd.to_ids), "added": len(rd.added),
                    "removed": len(rd.removed), "unchanged": len(rd.unchanged), "changed": len(rd.changed),
                    "changed_ranges": sum(len(c["ranges"]) for c in changed),
                    "changed_length_m": _r(sum(c["changed_length_m"] for c in changed)),
                    "sectors": sum(len(r["sectors"]) for c in changed for r in c["ranges"]),
                    "pose_moved": sum(c["pose_moved"] for c in changed)},
    }


def report_dict(result: DiffResult, *, repository: str, from_version: str, to_version: str, map_id: str = "",
                truth: dict | None = None, outputs: dict | None = None, params: dict | None = None,
                route_profile: bool = True) -> dict:
    """The JSON report of a diff (keys documented in docs/diff.md)."""
    from pipeline import __version__

    s2 = result.pixel_area_m2
    t = result.tiles
    regions = [region_dict(r) for r in result.regions]
    rep = {
        "mosaicmap_version": __version__,
        "repository": repository,
        "map_id": map_id,
        "from": {"version": from_version, "snapshot": result.from_snapshot, "publish_version": result.from_number},
        "to": {"version": to_version, "snapshot": result.to_snapshot, "publish_version": result.to_number},
        "frame": FRAME_NOTE,
        "grid": result.grid.to_attrs(),
        "grown": t.grown,
        "tiles": {
            "tile_px": t.tile_px,
            "shards_changed": t.shards_changed,
            "rewritten": t.tiles_rewritten,
            "identical": t.tiles_identical,
            "changed": t.tiles_changed,
            "new_coverage": t.tiles_new_coverage,
            "changed_list": result.changed_tiles.tolist(),
            "new_coverage_list": result.new_tiles.tolist(),
        },
        "coverage": {
            "new_m2": _r(t.new_coverage_px * s2, 8),
            "lost_m2": _r(t.lost_coverage_px * s2, 8),
            "compared_m2": _r(t.compared_px * s2, 8),
            "observed_m2": _r(t.observed_px * s2, 8),
        },
        "detection": {
            "noise_grey": _r(result.noise, 3),
            "threshold_grey": _r(result.threshold, 3),
            "windows": result.windows,
            "ignored_smooth": [{"area_m2": _r(c["area_m2"], 8), "part_of_region": c["part_of_region"],
                                "edge_step_grey": _r(c["edge_step"], 2),
                                "mean_abs_residual_grey": _r(c["mean_abs_residual"], 2),
                                "bbox_px": [int(v) for v in c["bbox_px"]]} for c in result.ignored],
        },
        "summary": {
            "regions": len(regions),
            "changed_m2": _r(sum(r.area_m2 for r in result.regions), 8),
            "at_risk": sum(r["at_risk"] for r in regions),
            "ignored_smooth": len(result.ignored),
        },
        "regions": regions,
        "seconds": {k: _r(v, 4) for k, v in result.seconds.items()},
    }
    if result.routes is not None:
        rep["routes"] = routes_dict(result.routes, route_profile)
    if params is not None:
        rep["parameters"] = params
    if truth is not None:
        rep["truth"] = truth
    if outputs is not None:
        rep["outputs"] = outputs
    return rep


def geojson_dict(result: DiffResult, geo: GeoReference, map_id: str = "") -> dict:
    """An RFC 7946 FeatureCollection of the regions: polygons in WGS 84 longitude, latitude
    (degrees) through the map's geographic reference ``geo``; the properties keep the
    region in the map's metres (``polygon_m`` too)."""
    features = []
    for reg in result.regions:
        props = region_dict(reg)
        props["polygon_m"] = reg.polygon_m
        rings = []
        for ring in reg.polygon_m:
            pts = np.asarray(ring, float).reshape(-1, 2)
            lat, lon = geo.to_wgs84(pts[:, 0], pts[:, 1])
            rings.append([[round(float(a), 9), round(float(b), 9)] for a, b in zip(lon, lat)])
        features.append({"type": "Feature", "id": reg.id, "geometry": {"type": "Polygon", "coordinates": rings},
                         "properties": props})
    return {"type": "FeatureCollection",
            "mosaicmap": {"map_id": map_id, "from_snapshot": result.from_snapshot, "to_snapshot": result.to_snapshot,
                          "geo_reference": geo.to_attrs(), "frame_m": FRAME_NOTE, "grid": result.grid.to_attrs()},
            "features": features}


def regions_local_dict(result: DiffResult, map_id: str = "") -> dict:
    """The regions in the map's local metres (``regions.json``; not GeoJSON: see the module
    docstring)."""
    return {"format": "mosaicmap-regions", "crs": "local metres", "frame": FRAME_NOTE, "units": "metre",
            "map_id": map_id, "from_snapshot": result.from_snapshot, "to_snapshot": result.to_snapshot,
            "grid": result.grid.to_attrs(),
            "regions": [{**region_dict(reg), "polygon_m": reg.polygon_m} for reg in result.regions]}


def regions_document(result: DiffResult, geo: GeoReference | None, map_id: str = "") -> tuple[str, dict]:
    """(file name, document) of the regions: ``regions.geojson`` in WGS 84 when the map has
    a geographic reference, else ``regions.json`` in local metres."""
    if geo is not None:
        return GEOJSON_FILE, geojson_dict(result, geo, map_id)
    return OUTPUT_FILES["regions"], regions_local_dict(result, map_id)


# --- images -------------------------------------------------------------------------------


def _level_for(extent_px: int, max_px: int, levels: int) -> int:
    """The finest pyramid level at which ``extent_px`` level-0 pixels fit in ``max_px``."""
    k = 0
    while k < levels - 1 and -(-extent_px // 2**k) > max_px:
        k += 1
    return k


def _read_level(root: zarr.Group, k: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """Window (level-k pixels) of a version's level k; 0 beyond the array. A version without
    level k (an older, smaller map has fewer levels) is read at its coarsest level and
    reduced."""
    floor = root["floor"]
    if str(k) not in floor:
        have = max(int(n) for n in floor.array_keys() if n.isdigit())
        f = 2 ** (k - have)
        big = _read_level(root, have, r0 * f, r1 * f, c0 * f, c1 * f)
        return cv2.resize(big, (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA)
    arr = floor[str(k)]
    out = np.zeros((r1 - r0, c1 - c0), np.uint8)
    a0, a1, b0, b1 = max(r0, 0), min(r1, arr.shape[0]), max(c0, 0), min(c1, arr.shape[1])
    if a0 < a1 and b0 < b1:
        out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = arr[a0:a1, b0:b1]
    return out


def _rgb(grey: np.ndarray) -> np.ndarray:
    return np.repeat(grey[:, :, None], 3, axis=2)


def _poly_px(ring: list[list[float]], grid: MapGrid, k: int, r0: int, c0: int) -> np.ndarray:
    """A ring (world metres) as level-k pixel coordinates of a window at (r0, c0), for
    cv2 drawing with 4 fractional bits."""
    pts = np.asarray(ring, float)
    col, row = grid.level(k).world_to_pixel(pts[:, 0], pts[:, 1])
    return np.round(np.stack([col - c0, row - r0], axis=1) * 16).astype(np.int32)


def _draw_regions(img: np.ndarray, regions: list[Region], grid: MapGrid, k: int, r0: int, c0: int,
                  labels: bool, alpha: float = 0.35) -> np.ndarray:
    """Regions filled (alpha) and outlined on an RGB image of level-k window (r0, c0)."""
    fill = img.copy()
    polys = []
    for reg in regions:
        if not reg.polygon_m:
            continue
        colour = ORANGE if reg.impact.at_risk else RED
        rings = [_poly_px(r, grid, k, r0, c0) for r in reg.polygon_m]
        cv2.fillPoly(fill, rings, colour, lineType=cv2.LINE_AA, shift=4)
        polys.append((reg, rings, colour))
    out = cv2.addWeighted(fill, alpha, img, 1.0 - alpha, 0.0)
    for reg, rings, colour in polys:
        cv2.polylines(out, rings, True, colour, 1, lineType=cv2.LINE_AA, shift=4)
        if labels:
            x, y = rings[0][:, 0].max() / 16.0 + 2, rings[0][:, 1].min() / 16.0 + 10
            cv2.putText(out, str(reg.id), (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
    return out


def _mark_tiles(img: np.ndarray, tiles: np.ndarray, tile_px: int, k: int, colour, alpha: float) -> None:
    """Tint a set of level-0 tiles on a level-k RGB image (where it has data) and outline
    their union."""
    if not len(tiles):
        return
    f = 2**k
    m = np.zeros(img.shape[:2], np.uint8)
    for r, c in tiles:
        m[int(r) * tile_px // f : -(-(int(r) + 1) * tile_px // f), int(c) * tile_px // f : -(-(int(c) + 1) * tile_px // f)] = 1
    sel = (m > 0) & (img.max(axis=2) > 0)
    img[sel] = (img[sel] * (1 - alpha) + np.array(colour) * alpha).astype(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, colour, 1)


def _tint(img: np.ndarray, mask: np.ndarray, colour, alpha: float) -> None:
    img[mask] = (img[mask] * (1 - alpha) + np.array(colour) * alpha).astype(np.uint8)


def overview_images(result: DiffResult, from_root: zarr.Group, to_root: zarr.Group, levels: int,
                    max_px: int) -> dict[str, np.ndarray]:
    """FROM, TO and the overlay of the whole map at the finest level fitting ``max_px``
    (RGB uint8, same size; FROM is 0 where its smaller grid does not reach); the overlay
    marks what :data:`OVERLAY_LEGEND` says (coverage lost: FROM has data, TO none, drawn
    on FROM's pixels). ``grid``: the level's MapGrid."""
    grid = result.grid
    k = _level_for(max(grid.shape), max_px, levels)
    h, w = grid.level(k).shape
    a = _read_level(from_root, k, 0, h, 0, w)
    b = _read_level(to_root, k, 0, h, 0, w)
    over = _rgb(b)
    lost = (a > 0) & (b == 0)
    over[lost] = _rgb(a)[lost]
    _tint(over, lost, MAGENTA, 0.45)
    _mark_tiles(over, result.changed_tiles, result.tiles.tile_px, k, BLUE, 0.12)
    _mark_tiles(over, result.new_tiles, result.tiles.tile_px, k, GREEN, 0.3)
    over = _draw_regions(over, result.regions, grid, k, 0, 0, labels=True, alpha=0.6)
    return {"from": _rgb(a), "to": _rgb(b), "overlay": over, "level": k, "grid": grid.level(k)}


def overview_figures(overview: dict, from_label: str, to_label: str) -> dict[str, np.ndarray]:
    """The overview's FROM, TO and overlay drawn to be read (:func:`pipeline.map_figures.annotated_map`:
    axes in metres, scale bar, north arrow); the overlay with its legend (what ``overlay.png``
    holds)."""
    from pipeline.map_figures import annotated_map

    g, k = overview["grid"], overview["level"]
    return {"from": annotated_map(overview["from"], g, title=f"FROM {from_label} (level {k})"),
            "to": annotated_map(overview["to"], g, title=f"TO {to_label} (level {k})"),
            "overlay": annotated_map(overview["overlay"], g, title=f"changes {from_label} -> {to_label} on TO",
                                     legend=OVERLAY_LEGEND)}


def region_crops(result: DiffResult, reg: Region, from_root: zarr.Group, to_root: zarr.Group, levels: int,
                 max_px: int, margin_px: int) -> dict:
    """FROM, TO and overlay crops (RGB uint8) around one region, at the finest level where
    the region and ``margin_px`` level-0 pixels around it fit in ``max_px``."""
    r0, r1, c0, c1 = reg.bbox_px
    r0, r1, c0, c1 = r0 - margin_px, r1 + margin_px, c0 - margin_px, c1 + margin_px
    k = _level_for(max(r1 - r0, c1 - c0), max_px, levels)
    f = 2**k
    a0, a1, b0, b1 = r0 // f, -(-r1 // f), c0 // f, -(-c1 // f)
    a = _read_level(from_root, k, a0, a1, b0, b1)
    b = _read_level(to_root, k, a0, a1, b0, b1)
    others = [x for x in result.regions if x.id != reg.id and x.bbox_px[0] < r1 and x.bbox_px[1] > r0
              and x.bbox_px[2] < c1 and x.bbox_px[3] > c0]
    over = _draw_regions(_rgb(b), [reg] + others, result.grid, k, a0, b0, labels=False)
    return {"from": _rgb(a), "to": _rgb(b), "overlay": over, "level": k}


def _block_rows(x: np.ndarray, f: int) -> np.ndarray:
    """Mean of blocks of ``f`` rows (the last block may be shorter)."""
    if f <= 1:
        return x.astype(np.float32)
    n = len(x)
    starts = np.arange(0, n, f)
    sums = np.add.reduceat(x.astype(np.float64), starts, axis=0)
    counts = np.diff(np.append(starts, n)).reshape(-1, *([1] * (x.ndim - 1)))
    return (sums / counts).astype(np.float32)


def route_figure(ch: RouteChange, max_rows: int = 600, scale: int = 1, *, from_label: str = "",
                 to_label: str = "") -> np.ndarray:
    """FROM, TO and their difference for one changed route, drawn to be read (RGB uint8;
    :func:`pipeline.map_figures.annotated_route_panels`): three panels side by side over the
    common path-length grid, rows = path length s (metres, downward; blocks of rows
    averaged to at most ``max_rows``), columns = azimuth (degrees, each sample at least
    ``scale`` px wide); axes in metres and degrees, grey-level and difference colour bars, a
    title naming the versions (``from_label`` / ``to_label``) and the legend
    :data:`ROUTE_LEGEND`: changed ranges as a red bar at each panel's left edge, changed
    sectors as cyan boxes (see the module docstring)."""
    from pipeline.map_figures import GREY_LEVELS, RouteMark, RoutePanel, annotated_route_panels

    n, a = ch.lines_from.shape if len(ch.s) else (0, ch.lines_from.shape[1])
    f = max(1, -(-n // max(1, int(max_rows))))
    step = float(ch.step_m)
    if n:
        grey = [np.clip(_block_rows(x, f), 0, 255).astype(np.uint8) for x in (ch.lines_from, ch.lines_to)]
        diff = _block_rows(ch.diff, f)
    else:  # no common path length: empty panels
        grey, diff = [np.zeros((1, a), np.uint8)] * 2, np.zeros((1, a), np.float32)
    panels = [RoutePanel(grey[0], f"FROM {from_label}".strip(), GREY_LEVELS),
              RoutePanel(grey[1], f"TO {to_label}".strip(), GREY_LEVELS),
              RoutePanel(diff, "|difference| of the normalized lines", ROUTE_DIFF_SCALE)]
    half = 0.5 / ch.samples_per_degree
    marks = []
    for r in ch.ranges:
        s_edges = (float(ch.s[r.i0]) - step / 2, float(ch.s[r.i1 - 1]) + step / 2)
        marks.append(RouteMark(s_edges, None, ROUTE_RANGE_COLOUR))
        for sec in r.sectors:
            a0 = round(sec["start_deg"] * ch.samples_per_degree) / ch.samples_per_degree - half
            a1 = a0 + round(sec["width_deg"] * ch.samples_per_degree) / ch.samples_per_degree
            marks.append(RouteMark(s_edges, (a0, a1), ROUTE_SECTOR_COLOUR))
    s0 = float(ch.s[0]) + (f - 1) * step / 2 if n else 0.0
    block = f", rows averaged in blocks of {f} ({f * step:g} m)" if f > 1 else ""
    title = f"route {ch.id}: {from_label or 'FROM'} -> {to_label or 'TO'}{block}"
    return annotated_route_panels(panels, s0_m=s0, spacing_m=f * step, samples_per_degree=ch.samples_per_degree,
                                  title=title, marks=marks, legend=ROUTE_LEGEND, scale_x=max(1, int(scale)))


def _png_uri(img: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


# --- the HTML page ------------------------------------------------------------------------


_CSS = """
body{font-family:sans-serif;margin:1.5em;color:#222} h1{font-size:1.4em} h2{font-size:1.15em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em} td,th{border:1px solid #bbb;padding:3px 7px;text-align:right}
th{background:#eee} td.l,th.l{text-align:left} .row{display:flex;gap:10px;flex-wrap:wrap;align-items:flex-start}
figure{margin:0} figcaption{font-size:.8em;color:#555} img{image-rendering:pixelated;border:1px solid #999}
.maps{display:grid;grid-template-columns:repeat(auto-fit,minmax(min(100%,420px),1fr));gap:12px;align-items:start}
.maps img{width:100%;height:auto;image-rendering:auto} :target{background:#ffd}
.route figure{min-width:0;max-width:100%} .route img{max-width:100%;height:auto;image-rendering:auto}
.risk{color:#c60;font-weight:bold} .note{font-size:.85em;color:#555}
"""


def _fmt(v, nd: int = 3) -> str:
    return "-" if v is None else f"{v:.{nd}g}" if isinstance(v, float) else html.escape(str(v))


def _figure(img: np.ndarray, caption: str, width: int | None = None, fig_id: str = "") -> str:
    """An embedded image; ``width`` scales its display (pixels stay sharp); ``fig_id`` the
    figure element's id (for the page's layout checks and links)."""
    w = f' width="{width}"' if width else ""
    i = f' id="{fig_id}"' if fig_id else ""
    return (f'<figure{i}><img src="{_png_uri(img)}"{w} alt="{html.escape(caption)}">'
            f'<figcaption>{html.escape(caption)}</figcaption></figure>')


def _routes_html(routes: dict, figures: list[tuple[str, np.ndarray]]) -> str:
    """The page's route section: the summary, a table of the changed routes and their
    ranges and sectors, the figures."""
    e = html.escape
    s = routes["summary"]
    out = ["<h2>Route panoramas</h2>",
           f"<p>FROM holds {s['from']} route(s), TO {s['to']}: {s['added']} added "
           f"({e(', '.join(a['id'] for a in routes['added'])) or '-'}), {s['removed']} removed "
           f"({e(', '.join(r['id'] for r in routes['removed'])) or '-'}), {s['unchanged']} unchanged, "
           f"{s['changed']} changed; {s['changed_ranges']} changed range(s) over {s['changed_length_m'] or 0:.2f} m, "
           f"{s['sectors']} sector(s)</p>"]
    if routes["changed"]:
        out.append("<table><tr><th class='l'>route</th><th>rows compared</th><th>score median / max</th>"
                   "<th>changed ranges s (m)</th><th class='l'>sectors (deg)</th><th>largest pose move</th></tr>")
        for c in routes["changed"]:
            rng = "<br>".join(f"{r['s_m'][0]:.2f} .. {r['s_m'][1]:.2f}" for r in c["ranges"]) or "-"
            sec = "<br>".join(", ".join(f"{x['start_deg']:g}..{x['end_deg']:g}" for x in r["sectors"]) or "-"
                              for r in c["ranges"]) or "-"
            move = ("-" if c["pose_move_max_m"] is None else
                    f"{100 * c['pose_move_max_m']:.1f} cm, {c['pose_move_max_deg']:.2f} deg at s "
                    f"{c['pose_move_at_s_m']:.2f} m")
            out.append(f"<tr><td class='l'>{e(c['id'])}</td><td>{c['rows_compared']}</td>"
                       f"<td>{_fmt(c['score_median'])} / {_fmt(c['score_max'])}</td><td>{rng}</td>"
                       f"<td class='l'>{sec}</td><td>{move}</td></tr>")
        out.append("</table>")
    for rid, img in figures:
        out.append(f"<h3>Route {e(rid)}</h3><div class='row route'>")
        out.append(_figure(img, "FROM, TO and |difference| of the normalized lines; rows = path length s "
                                "(m, down), columns = azimuth (deg); red: changed ranges, cyan: changed sectors"))
        out.append("</div>")
    return "\n".join(out)


def html_page(report: dict, overview: dict, crops: list[tuple[int, dict]], skipped_crops: int,
              crop_display_px: int = 384, route_figures: list[tuple[str, np.ndarray]] = (),
              figures: dict | None = None) -> str:
    """The self-contained page (every image a data URI); crops displayed ``crop_display_px``
    wide at least (small crops are magnified); ``route_figures`` (route id, image) in the
    route section; ``figures``: the overview drawn to be read (:func:`overview_figures`),
    else the overview's plain pixels. FROM, TO and the overlay stand side by side on a wide
    screen (a CSS grid of columns at least 420 px wide) and wrap on a narrow one; each
    region with a crop links from the table to it (anchor ``region-<id>``)."""
    e = html.escape
    fr, to = report["from"], report["to"]
    s = report["summary"]
    cov, tiles = report["coverage"], report["tiles"]
    k = overview["level"]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>mosaicmap diff {e(str(fr['version']))} -&gt; {e(str(to['version']))}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>mosaicmap diff: {e(str(fr['version']))} &rarr; {e(str(to['version']))}</h1>",
        f"<p><b>{s['regions']}</b> changed region(s), {s['changed_m2'] * 1e4:.1f} cm<sup>2</sup>; "
        f"<b>{s['at_risk']}</b> with localization at risk; {s['ignored_smooth']} smooth difference(s) ignored "
        "(illumination/exposure). Map details below the pictures.</p>",
        "<div class='maps' id='overview'>",
        _figure((figures or overview)["from"], f"FROM (whole map, pyramid level {k})", fig_id="fig-from"),
        _figure((figures or overview)["to"], f"TO (whole map, pyramid level {k})", fig_id="fig-to"),
        _figure((figures or overview)["overlay"], "overlay on TO: " + "; ".join(
            f"{_COLOUR_NAMES[key.colour]}: {key.label}" for key in OVERLAY_LEGEND), fig_id="fig-overlay"),
        "</div>",
        "<h2>Map and comparison</h2>",
        f"<p>Repository <code>{e(report['repository'])}</code>, map {e(report.get('map_id') or '-')}<br>",
        f"FROM snapshot <code>{e(fr['snapshot'])}</code> (publish version {fr['publish_version']}), "
        f"TO snapshot <code>{e(to['snapshot'])}</code> (publish version {to['publish_version']})<br>",
        f"Tiles ({tiles['tile_px']} px): {tiles['rewritten']} rewritten, {tiles['identical']} identical, "
        f"{tiles['changed']} compared, {tiles['new_coverage']} new coverage; new coverage "
        f"{cov['new_m2']:.4f} m<sup>2</sup>, compared {cov['compared_m2']:.4f} m<sup>2</sup>, observed "
        f"{cov['observed_m2']:.4f} m<sup>2</sup>; noise {report['detection']['noise_grey']} grey levels, "
        f"threshold {report['detection']['threshold_grey']}</p>",
        f"<p class='note'>Coordinates: {e(report['frame'])}. {_geo_note(report.get('geo_reference'))}</p>",
        "<h2>Regions</h2>",
    ]
    cropped = {rid for rid, _ in crops}
    if report["regions"]:
        parts.append("<table><tr><th>id</th><th>area cm<sup>2</sup></th><th>centre x, y (m)</th>"
                     "<th>bbox x (m)</th><th>bbox y (m)</th><th>contrast</th><th>texture before &rarr; after</th>"
                     "<th>uniqueness before &rarr; after</th><th class='l'>localization</th></tr>")
        for r in report["regions"]:
            risk = r["risk"].replace("_", " ")
            cls = " class='l risk'" if r["at_risk"] else " class='l'"
            why = f": {'; '.join(r['reasons'])}" if r["reasons"] else ""
            parts.append(
                f"<tr><td>{_region_link(r['id'], cropped)}</td><td>{r['area_cm2']:.1f}</td>"
                f"<td>{r['centroid_m'][0]:.3f}, {r['centroid_m'][1]:.3f}</td>"
                f"<td>{r['bbox_m'][0]:.3f} .. {r['bbox_m'][2]:.3f}</td><td>{r['bbox_m'][1]:.3f} .. {r['bbox_m'][3]:.3f}</td>"
                f"<td>{r['contrast_grey']:+.1f}</td>"
                f"<td>{_fmt(r['texture_before'])} &rarr; {_fmt(r['texture_after'])}</td>"
                f"<td>{_fmt(r['uniqueness_before'])} &rarr; {_fmt(r['uniqueness_after'])}</td>"
                f"<td{cls}>{e(risk + why)}</td></tr>")
        parts.append("</table>")
    else:
        parts.append("<p>No changed region.</p>")
    truth = report.get("truth")
    if truth:
        parts.append(_truth_html(truth))
    if crops:
        parts.append("<h2>Changed regions, FROM / TO / overlay</h2>")
        for rid, c in crops:
            parts.append(f"<h3 id='region-{rid}'>Region {rid} (level {c['level']})</h3><div class='row'>")
            w = max(c["from"].shape[1], min(crop_display_px, 3 * c["from"].shape[1]))
            parts += [_figure(c["from"], "FROM", w), _figure(c["to"], "TO", w), _figure(c["overlay"], "overlay", w)]
            parts.append("</div>")
        if skipped_crops:
            parts.append(f"<p class='note'>{skipped_crops} smaller region(s) without crops ([diff.report] max_crops).</p>")
    if report.get("routes") and (report["routes"]["from"] or report["routes"]["to"]):
        parts.append(_routes_html(report["routes"], list(route_figures)))
    parts.append("</body></html>")
    return "\n".join(parts)


_COLOUR_NAMES = {RED: "red", ORANGE: "orange", BLUE: "blue", GREEN: "green", MAGENTA: "magenta"}


def _geo_note(geo: dict | None) -> str:
    """The page's word on where the map lies on Earth (and which regions file it got)."""
    if not geo:
        return ("The map has no geographic reference: the regions are in local metres "
                "(regions.json), not WGS 84.")
    return (f"The map's origin lies at latitude {geo['origin_latitude']:.7f}, longitude "
            f"{geo['origin_longitude']:.7f} (WGS 84; x east, y north): regions.geojson gives the regions in "
            "WGS 84.")


def _region_link(rid: int, cropped: set[int]) -> str:
    """A region id in the table: a link to its crops when the page holds them."""
    return f"<a href='#region-{rid}'>{rid}</a>" if rid in cropped else str(rid)


def _truth_html(truth: dict) -> str:
    e = html.escape
    s = truth["summary"]
    al = truth["alignment"]
    out = ["<h2>Against the ground truth</h2>",
           f"<p>{s['changes']} change(s): {s['detected']} detected, {s['missed']} missed, {s['unobserved']} "
           f"unobserved; {s['false_regions']} false region(s) (largest {s['max_false_area_cm2']:.1f} cm<sup>2</sup>); "
           f"smallest IoU of an observed change {_fmt(s['min_iou_observed'])}.<br>"
           f"<span class='note'>Frame alignment: {e(al['source'])}: {e(al['note'])}</span></p>",
           "<table><tr><th>change</th><th class='l'>kinds</th><th>area cm<sup>2</sup></th><th>observed</th>"
           "<th class='l'>status</th><th>recall</th><th>IoU</th><th class='l'>regions</th></tr>"]
    for c in truth["changes"]:
        out.append(f"<tr><td>{c['id']}</td><td class='l'>{e(', '.join(c['kinds']) or '?')}</td>"
                   f"<td>{c['area_m2'] * 1e4:.1f}</td><td>{c['observed_fraction']:.0%}</td>"
                   f"<td class='l'>{e(c['status'])}</td><td>{c['recall']:.3f}</td><td>{_fmt(c['iou'])}</td>"
                   f"<td class='l'>{e(', '.join(map(str, c['regions'])))}</td></tr>")
    out.append("</table>")
    if truth["false_regions"]:
        out.append("<p>False regions: " + ", ".join(
            f"{f['id']} ({f['area_m2'] * 1e4:.1f} cm<sup>2</sup>)" for f in truth["false_regions"]) + "</p>")
    return "\n".join(out)


# --- writing ------------------------------------------------------------------------------


def _write_png_atomic(path: Path, img: np.ndarray) -> None:
    from pipeline.images import write_image

    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        write_image(tmp, img)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_outputs(out_dir: Path, report: dict, result: DiffResult, from_root: zarr.Group, to_root: zarr.Group,
                  levels: int, cfg_report: dict, map_id: str = "") -> dict[str, str]:
    """Write the regions, the overlay and the page into ``out_dir`` (see the module
    docstring); sets ``report["outputs"]`` (name -> path, with ``diff.json``, which the
    caller writes last with :func:`write_report_file` once its timings are complete)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {k: str(out_dir / v) for k, v in OUTPUT_FILES.items()}
    report["outputs"] = paths
    overview = overview_images(result, from_root, to_root, levels, int(cfg_report["overview_max_px"]))
    ranked = sorted(result.regions, key=lambda r: -r.area_m2)[: max(int(cfg_report["max_crops"]), 0)]
    crops = [(r.id, region_crops(result, r, from_root, to_root, levels, int(cfg_report["crop_max_px"]),
                                 int(cfg_report["margin_px"]))) for r in sorted(ranked, key=lambda r: r.id)]
    from mapstore.layout import read_geo_reference

    from pipeline.errors import BadInput

    try:
        geo = read_geo_reference(to_root)
    except ValueError as e:
        raise BadInput(f"TO version {report['to']['version']}", str(e)) from None
    name, doc = regions_document(result, geo, map_id)
    paths["regions"] = str(out_dir / name)
    report["geo_reference"] = None if geo is None else geo.to_attrs()
    write_json_atomic(out_dir / name, doc)
    other = GEOJSON_FILE if name != GEOJSON_FILE else OUTPUT_FILES["regions"]
    (out_dir / other).unlink(missing_ok=True)  # a former run's regions in the other frame would contradict
    figs = overview_figures(overview, str(report["from"]["version"]), str(report["to"]["version"]))
    _write_png_atomic(out_dir / OUTPUT_FILES["overlay"], figs["overlay"])
    figures = []
    if result.routes is not None:
        shown = [c for c in result.routes.changed if c.ranges or c.pose_moved]
        shown = sorted(shown, key=lambda c: -sum(r.length_m for r in c.ranges))[: max(int(cfg_report["max_route_figures"]), 0)]
        for ch in sorted(shown, key=lambda c: c.id):
            img = route_figure(ch, int(cfg_report["route_figure_rows"]), int(cfg_report["route_figure_scale"]),
                               from_label=str(report["from"]["version"]), to_label=str(report["to"]["version"]))
            path = out_dir / f"route-{ch.id}.png"
            _write_png_atomic(path, img)
            paths[f"route_{ch.id}"] = str(path)
            figures.append((ch.id, img))
    write_text_atomic(out_dir / OUTPUT_FILES["html"],
                      html_page(report, overview, crops, len(result.regions) - len(crops), int(cfg_report["crop_max_px"]),
                                figures, figs))
    return paths


def write_report_file(out_dir: Path, report: dict) -> None:
    """``out_dir/diff.json``."""
    write_json_atomic(out_dir / OUTPUT_FILES["report"], report)


def summary_lines(report: dict) -> list[str]:
    """The short text the command prints: tiles, coverage, the region table, the truth."""
    fr, to = report["from"], report["to"]
    t, cov, det, s = report["tiles"], report["coverage"], report["detection"], report["summary"]
    lines = [
        f"diff {fr['version']} ({fr['snapshot'][:8]}, version {fr['publish_version']}) -> "
        f"{to['version']} ({to['snapshot'][:8]}, version {to['publish_version']})",
        f"tiles: {t['shards_changed']} shard(s) changed, {t['rewritten']} tile(s) rewritten, {t['identical']} "
        f"identical, {t['changed']} compared, {t['new_coverage']} new coverage"
        + (" (the map grew)" if report["grown"] else ""),
        f"area: compared {cov['compared_m2']:.4f} m^2, observed {cov['observed_m2']:.4f} m^2, new coverage "
        f"{cov['new_m2']:.4f} m^2; noise {det['noise_grey']:.2f}, threshold {det['threshold_grey']:.1f} grey levels; "
        f"{s['ignored_smooth']} smooth difference(s) ignored",
        f"regions: {s['regions']}, {s['changed_m2'] * 1e4:.1f} cm^2, {s['at_risk']} with localization at risk",
    ]
    if report["regions"]:
        lines.append(f"  {'id':>3} {'area cm^2':>10} {'centre x, y (m)':>18} {'contrast':>8} "
                     f"{'texture':>17} {'uniqueness':>13}  localization")
        for r in report["regions"]:
            tex = f"{_fmt(r['texture_before'])}->{_fmt(r['texture_after'])}"
            uni = f"{_fmt(r['uniqueness_before'], 2)}->{_fmt(r['uniqueness_after'], 2)}"
            risk = r["risk"].replace("_", " ") + (f" ({'; '.join(r['reasons'])})" if r["reasons"] else "")
            lines.append(f"  {r['id']:>3} {r['area_cm2']:>10.1f} {r['centroid_m'][0]:>8.3f}, {r['centroid_m'][1]:>8.3f} "
                         f"{r['contrast_grey']:>+8.1f} {tex:>17} {uni:>13}  {risk}")
    routes = report.get("routes")
    if routes and (routes["from"] or routes["to"]):
        rs = routes["summary"]
        lines.append(f"routes: {rs['from']} -> {rs['to']}: {rs['added']} added"
                     f"{' (' + ', '.join(a['id'] for a in routes['added']) + ')' if routes['added'] else ''}, "
                     f"{rs['removed']} removed"
                     f"{' (' + ', '.join(r['id'] for r in routes['removed']) + ')' if routes['removed'] else ''}, "
                     f"{rs['unchanged']} unchanged, {rs['changed']} changed")
        for c in routes["changed"]:
            move = ("" if c["pose_move_max_m"] is None else
                    f"; poses moved up to {100 * c['pose_move_max_m']:.1f} cm, {c['pose_move_max_deg']:.2f} deg")
            lines.append(f"  route {c['id']}: {c['rows_compared']} rows compared every {c['step_m']:g} m, score "
                         f"median {_fmt(c['score_median'])}, {len(c['ranges'])} changed range(s){move}")
            for r in c["ranges"]:
                secs = ", ".join(f"{x['start_deg']:g}..{x['end_deg']:g} deg" for x in r["sectors"]) or "no sector"
                lines.append(f"    s {r['s_m'][0]:.2f}..{r['s_m'][1]:.2f} m: score max {r['score_max']:.3f}, "
                             f"mean |diff| {r['mad_mean_grey']:.1f} grey; sectors {secs}")
    truth = report.get("truth")
    if truth:
        ts = truth["summary"]
        lines.append(f"truth: {ts['changes']} change(s): {ts['detected']} detected, {ts['missed']} missed, "
                     f"{ts['unobserved']} unobserved; {ts['false_regions']} false region(s), largest "
                     f"{ts['max_false_area_cm2']:.1f} cm^2; alignment {truth['alignment']['source']}")
        for c in truth["changes"]:
            iou = "" if c["iou"] is None else f", IoU {c['iou']:.3f}"
            lines.append(f"  change {c['id']} {'+'.join(c['kinds']) or '?'} {c['area_m2'] * 1e4:.1f} cm^2: "
                         f"observed {c['observed_fraction']:.0%}, {c['status']}{iou}")
    return lines
