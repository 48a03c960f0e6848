"""Pictures people can read and formats that do not lie: pipeline.map_figures (axes, scale bar,
colour bar, legend), `quicklook --annotate` (floor layers and route panoramas), the diff's
overlay and diff.html (side by side, region links), regions.json / regions.geojson and the
map's geo_reference (mapstore.grid.GeoReference), and diff.html in a real headless Chromium."""

from __future__ import annotations

import copy
import json
import os
import re
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import zarr
from zarr.storage import MemoryStore

from mapstore.grid import GeoReference, MapGrid
from mapstore.layout import GEO_ATTR, read_floor, read_geo_reference, write_geo_reference
from mapstore.repository import MapRepository
from mapstore.routes import RouteRecord, write_route
from pipeline import map_figures as mf
from pipeline.config import load_config
from pipeline.diff_report import BLUE, GREEN, MAGENTA, ORANGE, OVERLAY_LEGEND, RED
from pipeline.importers.geotagged import local_east_north
from pipeline.stages.publish import _record_geo, geo_reference_of
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn
from conftest import invoke

GRID = MapGrid(0.0, 2.0, 0.0025, 800, 800)  # 2 x 2 m
STAIN = Patch(0.4, 1.2, 0.6, 1.4, shift_px=(0, 0), delta=-40.0)
GEO = GeoReference(47.3769, 8.5417)  # the map's origin on Earth (version "three")
CHROMIUM = "/usr/bin/chromium"


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A map: version "one" (texture, no data right of column 512), "two" (a dark stain,
    the right part covered), "three" (two's floor, a geo_reference and a route panorama)."""
    root = tmp_path_factory.mktemp("pictures")
    cfg = copy.deepcopy(load_config(None))
    cfg["map"].update(chunk_px=64, shard_px=256)
    url = str(root / "map")
    tex = periodic_texture(2, 512)
    full = texture_tile_fn(tex, GRID)

    def left(r0, r1, c0, c1):
        out = full(r0, r1, c0, c1)
        out[:, max(512 - c0, 0):] = 0
        return out

    publish_raster(url, GRID, left, cfg=cfg, tag="one")
    shards = shards_for_box(GRID, 256, STAIN.x0, STAIN.y0, STAIN.x1, STAIN.y1) | {
        (i, j) for i in range(4) for j in (2, 3)}
    publish_raster(url, GRID, texture_tile_fn(tex, GRID, [STAIN]), cfg=cfg, tag="two", shards=shards)
    repo = MapRepository.open(url)
    session = repo.writable()
    group = zarr.open_group(session.store, mode="a")
    write_geo_reference(group, GEO)
    rng = np.random.default_rng(3)
    lines = cv2.GaussianBlur(rng.integers(0, 256, (203, 360), dtype=np.uint8), (0, 0), 2.0)
    poses = np.column_stack([np.linspace(0.2, 1.8, 203), np.full(203, 1.0), np.zeros(203)])
    write_route(group, "loop", RouteRecord(lines, poses, s0_m=0.0, spacing_m=0.1, samples_per_degree=1.0))
    repo.repo.create_tag("three", repo.commit(session, "geo reference and a route"))
    return {"root": root, "url": url, "lines": lines}


# --- map_figures ------------------------------------------------------------------------------


def test_magnification_and_nice_length():
    assert mf.magnification((94, 86)) == 7  # the 94 x 86 px layer: 658 px on the long side
    assert mf.magnification((800, 10)) == 1 and mf.magnification((599, 1)) == 2
    assert [mf.nice_length(s) for s in (2.0, 5.0, 3.2, 0.7, 140.0)] == [0.5, 1.0, 1.0, 0.2, 20.0]
    for span in np.geomspace(0.01, 5000, 40):
        v = mf.nice_length(span)
        mant = v / 10 ** np.floor(np.log10(v) + 1e-9)
        assert v <= span / 2 and min(abs(mant - m) for m in (1, 2, 5)) < 1e-9, (span, v)


def test_annotated_map_draws_every_stored_pixel_as_a_square_where_the_axes_are():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    grid = MapGrid(1.0, 2.0, 0.05, 30, 20)
    out = mf.annotated_map(img, grid, title="t")
    z = mf.magnification(img.shape)
    assert z == 20 and out.shape == (mf.TOP + 20 * z + mf.BOTTOM, mf.LEFT + 30 * z + mf.RIGHT, 3)
    drawn = out[mf.TOP:mf.TOP + 20 * z, mf.LEFT:mf.LEFT + 30 * z, 0].astype(int)
    big = np.kron(img, np.ones((z, z), np.uint8)).astype(int)
    inner = (slice(100, 300), slice(100, 450))  # clear of the scale bar and the north arrow
    assert np.abs(drawn[inner] - big[inner]).max() <= 1
    # a colour bar takes room right of the raster, a legend below it, and shows its colours
    scale = mf.ColourScale("viridis", 0.0, 1.0, "v")
    legend = [mf.LegendKey((220, 30, 30), "a"), mf.LegendKey((40, 200, 60), "b")]
    both = mf.annotated_map(img, grid, title="t", colour_scale=scale, legend=legend)
    assert both.shape[1] == out.shape[1] + mf.COLOURBAR_GAP + mf.COLOURBAR_W + mf.COLOURBAR_LABELS
    assert both.shape[0] == out.shape[0] + mf.LEGEND_ROW * 2 + mf.LEGEND_PAD
    below = both[mf.TOP + 20 * z + mf.BOTTOM:]
    for key in legend:
        assert (below == key.colour).all(axis=2).sum() > 20, key
    with pytest.raises(ValueError, match="does not match its grid"):
        mf.annotated_map(img, MapGrid(1.0, 2.0, 0.05, 31, 20), title="t")


# --- quicklook --annotate ---------------------------------------------------------------------


@pytest.mark.parametrize("layer, coloured", [("uniqueness", True), ("coverage", True), ("intensity", False)])
def test_quicklook_annotate_is_readable(site, tmp_path, layer, coloured):
    plain, fig = tmp_path / "plain.png", tmp_path / "fig.png"
    r = invoke("quicklook", site["url"], "--version", "two", "--layer", layer, "--out", plain)
    assert r.exit_code == 0, r.output
    r = invoke("quicklook", site["url"], "--version", "two", "--layer", layer, "--annotate", "--out", fig)
    assert r.exit_code == 0, r.output
    small, big = _read_rgb(plain), _read_rgb(fig)
    rows, cols = small.shape[:2]
    z = mf.magnification((rows, cols))
    assert max(rows, cols) * z >= 600 and big.ndim == 3
    bar = mf.COLOURBAR_GAP + mf.COLOURBAR_W + mf.COLOURBAR_LABELS if coloured else 0
    assert big.shape[:2] == (mf.TOP + rows * z + mf.BOTTOM, mf.LEFT + cols * z + mf.RIGHT + bar)
    # the raster is the plain image magnified (the middle, clear of scale bar and arrow)
    drawn = big[mf.TOP:mf.TOP + rows * z, mf.LEFT:mf.LEFT + cols * z].astype(int)
    want = np.repeat(np.repeat(small if small.ndim == 3 else small[..., None], z, 0), z, 1).astype(int)
    h, w = rows * z, cols * z
    mid = (slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))
    assert np.abs(drawn[mid] - want[mid]).max() <= 1
    assert "annotated" in r.output


def test_quicklook_route_annotate_has_azimuth_and_path_axes(site, tmp_path):
    out = tmp_path / "orp.png"
    r = invoke("quicklook", site["url"], "--version", "three", "--route", "loop", "--annotate", "--out", out)
    assert r.exit_code == 0, r.output
    img = _read_rgb(out)
    z = mf.magnification((203, 360))
    assert z == 2 and img.shape[1] == (mf.LEFT + 360 * z + mf.RIGHT + mf.COLOURBAR_GAP + mf.COLOURBAR_W
                                       + mf.COLOURBAR_LABELS)
    assert img.shape[0] == mf.TOP + 203 * z + mf.BOTTOM
    drawn = img[mf.TOP:mf.TOP + 203 * z, mf.LEFT:mf.LEFT + 360 * z, 0].astype(int)
    want = np.kron(site["lines"], np.ones((z, z), np.uint8)).astype(int)
    assert np.abs(drawn[20:-20, 20:-20] - want[20:-20, 20:-20]).max() <= 1
    r = invoke("quicklook", site["url"], "--version", "three", "--route", "loop", "--out", tmp_path / "plain.png")
    assert r.exit_code == 0 and cv2.imread(str(tmp_path / "plain.png"), cv2.IMREAD_UNCHANGED).shape == (203, 360)


def _changed_route_pair(rows: int, changed_rows: tuple[int, int], sector_deg: tuple[int, int]):
    """FROM and TO of one route (1 sample/degree, 1 cm rows): TO's lines another texture,
    brighter, in ``sector_deg`` over ``changed_rows`` (an object moved)."""
    lines = periodic_texture(5, 360, mean=120.0, std=40.0)[np.arange(rows) % 360]
    poses = np.column_stack([0.01 * np.arange(rows), np.zeros(rows), np.zeros(rows)]).astype(np.float32)
    to = lines.copy()
    (r0, r1), (a0, a1) = changed_rows, sector_deg
    to[r0:r1, a0:a1] = periodic_texture(23, 360, mean=150.0, std=40.0)[r0:r1, a0:a1]
    return [RouteRecord(np.clip(np.rint(x), 1, 255).astype(np.uint8), poses, s0_m=0.0, spacing_m=0.01,
                        samples_per_degree=1.0) for x in (lines, to)]


def test_diff_route_figure_has_axes_colour_bars_legend_and_marks():
    """The diff's route figure (FROM, TO, |difference|) is drawn as quicklook draws a route:
    each panel's lines pixel for pixel where its axes are, azimuth (deg) and path length (m)
    axes, a colour bar per scale, the legend's colours, the changed range as a red bar at
    each panel's left edge over exactly its rows, the changed sector as a cyan box."""
    from mapstore.diff import RouteDiffParams, diff_route
    from pipeline.diff_report import ROUTE_DIFF_SCALE, ROUTE_LEGEND, ROUTE_RANGE_COLOUR, ROUTE_SECTOR_COLOUR, \
        route_figure

    ch = diff_route("loop", *_changed_route_pair(320, (100, 150), (200, 240)), RouteDiffParams())
    (rng,) = ch.ranges
    assert abs(rng.i0 - 100) <= 2 and abs(rng.i1 - 150) <= 2 and len(rng.sectors) == 1
    fig = route_figure(ch, from_label="one", to_label="two")
    panels = [mf.RoutePanel(np.zeros((320, 360), np.uint8), "FROM one", mf.GREY_LEVELS),
              mf.RoutePanel(np.zeros((320, 360), np.uint8), "TO two", mf.GREY_LEVELS),
              mf.RoutePanel(np.zeros((320, 360)), "|difference| of the normalized lines", ROUTE_DIFF_SCALE)]
    lay = mf.route_panels_layout(panels, legend=ROUTE_LEGEND)
    assert fig.shape == (lay.size[1], lay.size[0], 3) and lay.z == lay.z_rows == 1  # 3 x 360 columns, 320 rows
    assert lay.scales == (mf.GREY_LEVELS, ROUTE_DIFF_SCALE) and lay.top_px == mf.PANEL_TITLE
    assert fig.shape[1] == (mf.LEFT + 3 * 360 + 2 * mf.PANEL_GAP + mf.RIGHT
                            + 2 * (mf.COLOURBAR_GAP + mf.COLOURBAR_W + mf.COLOURBAR_LABELS))
    assert fig.shape[0] == mf.TOP + mf.PANEL_TITLE + 320 + mf.BOTTOM + 2 * mf.LEGEND_ROW + mf.LEGEND_PAD
    (t, l0, h, w), (_, l1, _, _), (_, l2, _, _) = lay.boxes
    want = np.clip(ch.lines_from, 0, 255).astype(np.uint8)
    clear = (slice(10, 90), slice(l0 + 20, l0 + 190))  # rows 10..90, azimuth 20..190 deg: no mark
    got = fig[t:t + h, :, 0].astype(int)
    assert np.abs(got[clear] - want[10:90, 20:190]).max() <= 1  # FROM pixel for pixel
    assert np.abs(got[10:90, l1 + 20:l1 + 190] - np.clip(ch.lines_to, 0, 255)[10:90, 20:190]).max() <= 1

    def is_colour(img, colour, tol=1):
        return (np.abs(img.astype(int) - colour) <= tol).all(axis=-1)

    for left in (l0, l1, l2):  # the range bar: the changed rows only, at every panel's left edge
        bar = is_colour(fig[t:t + h, left + 2:left + mf.MARK_BAR_PX - 1], ROUTE_RANGE_COLOUR).all(axis=1)
        assert bar[rng.i0 + 1:rng.i1 - 1].all() and not bar[:rng.i0 - 1].any() and not bar[rng.i1 + 1:].any()
    box = is_colour(fig[t:t + h, l2:l2 + w], ROUTE_SECTOR_COLOUR, 40)  # the sector's outline (antialiased)
    rows, cols = np.nonzero(box)
    sec = rng.sectors[0]
    assert abs(rows.min() - rng.i0) <= 1 and abs(rows.max() - (rng.i1 - 1)) <= 1
    assert abs(cols.min() - sec["start_deg"]) <= 1 and abs(cols.max() - sec["end_deg"]) <= 1
    below = fig[t + h + mf.BOTTOM:]
    for key in ROUTE_LEGEND:
        assert is_colour(below, key.colour).sum() > 20, key
    # tick labels and axis labels: dark text under every panel and left of the first
    for left in (l0, l1, l2):
        assert (fig[t + h + 4:t + h + mf.BOTTOM, left:left + w] < 80).all(axis=-1).sum() > 200
    assert (fig[t:t + h, :l0 - 4] < 80).all(axis=-1).sum() > 200


def test_route_panels_figure_names_its_axes():
    """What the figure says in words: axis labels in degrees and metres (the path axis
    shared, labelled once), each panel's heading, the title, the colour bars' labels."""
    import matplotlib.pyplot as plt

    scale = mf.ColourScale("inferno", 0.0, 1.5, "|d|")
    panels = [mf.RoutePanel(np.zeros((30, 360), np.uint8), "FROM 1", mf.GREY_LEVELS),
              mf.RoutePanel(np.ones((30, 360)), "diff", scale)]
    lay = mf.route_panels_layout(panels)
    assert lay.z == 1 and lay.z_rows == 10 and lay.boxes[0][2] == mf.MIN_PANEL_H  # a short route's rows drawn taller
    fig = mf.route_panels_figure(panels, s0_m=2.0, spacing_m=0.1, samples_per_degree=1.0, title="route r: 1 -> 2",
                                 marks=[mf.RouteMark((2.5, 2.8), (350.0, 370.0), (0, 220, 255), (1,))])
    try:
        main = [ax for ax in fig.axes if ax.get_title(loc="left") in ("FROM 1", "diff")]
        assert [ax.get_title(loc="left") for ax in main] == ["FROM 1", "diff"]
        assert all(ax.get_xlabel().startswith("azimuth (deg") for ax in main)
        assert main[0].get_ylabel() == "path length s (m)" and main[1].get_ylabel() == ""
        assert main[0].get_ylim() == pytest.approx((2.0 + 29.5 * 0.1, 2.0 - 0.05))  # s downward, row edges
        assert main[0].get_xlim() == pytest.approx((-0.5, 359.5))
        assert [t.get_text() for t in fig.texts] == ["route r: 1 -> 2"]
        bars = [ax.get_ylabel() for ax in fig.axes if ax not in main]
        assert bars == [mf.GREY_LEVELS.label, "|d|"]
        # a sector through 0 deg: two boxes on panel 1 only
        assert len(main[0].patches) == 0 and len(main[1].patches) == 2
    finally:
        plt.close(fig)


# --- the diff's pictures, page and regions ----------------------------------------------------


@pytest.fixture(scope="module")
def diff_out(site, tmp_path_factory):
    out = tmp_path_factory.mktemp("diff") / "out"
    r = invoke("diff", site["url"], "one", "two", "--out", out)
    assert r.exit_code == 0, r.output
    return out


def test_overlay_has_axes_legend_and_every_mark(diff_out):
    rep = json.loads((diff_out / "diff.json").read_text())
    assert rep["summary"]["regions"] >= 1 and rep["tiles"]["new_coverage"] > 0
    img = _read_rgb(diff_out / "overlay.png")
    k = _level(rep)
    rows, cols = MapGrid.from_attrs(rep["grid"]).level(k).shape
    z = mf.magnification((rows, cols))
    legend_h = mf.LEGEND_ROW * len(OVERLAY_LEGEND) + mf.LEGEND_PAD
    assert img.shape[:2] == (mf.TOP + rows * z + mf.BOTTOM + legend_h, mf.LEFT + cols * z + mf.RIGHT)
    below = img[mf.TOP + rows * z + mf.BOTTOM:]
    for key in OVERLAY_LEGEND:  # every key of the legend is drawn with its colour
        assert (below == key.colour).all(axis=2).sum() > 20, key.label
    assert {k.colour for k in OVERLAY_LEGEND} == {RED, ORANGE, BLUE, GREEN, MAGENTA}
    labels = " ".join(k.label for k in OVERLAY_LEGEND)
    assert "added" in labels and "removed" in labels and "changed" in labels


def _level(rep: dict) -> int:
    grid = MapGrid.from_attrs(rep["grid"])
    k = 0
    while max(grid.level(k).shape) > 1024:  # [diff.report] overview_max_px
        k += 1
    return k


def test_diff_page_side_by_side_with_region_links(diff_out):
    rep = json.loads((diff_out / "diff.json").read_text())
    page = (diff_out / "diff.html").read_text()
    assert "<div class='maps' id='overview'>" in page
    assert re.search(r"\.maps\{display:grid;grid-template-columns:repeat\(auto-fit,minmax\(", page)
    for fid in ("fig-from", "fig-to", "fig-overlay"):
        assert page.count(f'<figure id="{fid}">') == 1
    for reg in rep["regions"]:
        assert f"<a href='#region-{reg['id']}'>{reg['id']}</a>" in page
        assert page.count(f"id='region-{reg['id']}'") == 1


def test_regions_json_in_local_metres_without_a_geo_reference(site, diff_out):
    rep = json.loads((diff_out / "diff.json").read_text())
    assert not (diff_out / "regions.geojson").exists()
    doc = json.loads((diff_out / "regions.json").read_text())
    assert "type" not in doc and doc["crs"] == "local metres" and doc["units"] == "metre"
    assert [r["id"] for r in doc["regions"]] == [r["id"] for r in rep["regions"]]
    assert rep["outputs"]["regions"] == str(diff_out / "regions.json") and rep["geo_reference"] is None
    r = invoke("show", site["url"], "--version", "two")
    assert r.exit_code == 0 and "no geographic reference" in r.output
    assert "no geographic reference" in (diff_out / "diff.html").read_text()


def test_regions_geojson_in_wgs84_with_a_geo_reference(site, diff_out, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(diff_out, out)  # a former run's regions.json must go: it would contradict
    r = invoke("diff", site["url"], "one", "three", "--out", out)
    assert r.exit_code == 0, r.output
    assert not (out / "regions.json").exists()
    gj = json.loads((out / "regions.geojson").read_text())
    local = json.loads((diff_out / "regions.json").read_text())["regions"]
    assert gj["type"] == "FeatureCollection" and "crs" not in gj and len(gj["features"]) == len(local) >= 1
    assert gj["mosaicmap"]["geo_reference"]["origin_latitude"] == GEO.origin_latitude
    assert json.loads((out / "diff.json").read_text())["geo_reference"] == GEO.to_attrs()
    assert f"latitude {GEO.origin_latitude:.7f}" in (out / "diff.html").read_text()
    for f, reg in zip(gj["features"], local):
        ring = np.array(f["geometry"]["coordinates"][0])  # RFC 7946: longitude, latitude
        assert np.allclose(ring[0], ring[-1]) and len(ring) >= 4
        assert (np.abs(ring[:, 0] - GEO.origin_longitude) < 0.001).all()
        assert (np.abs(ring[:, 1] - GEO.origin_latitude) < 0.001).all()
        x, y = GEO.from_wgs84(ring[:, 1], ring[:, 0])
        np.testing.assert_allclose(np.column_stack([x, y]), np.array(reg["polygon_m"][0]), atol=1e-4)
        assert f["properties"]["bbox_m"] == reg["bbox_m"]


# --- the geographic reference -------------------------------------------------------------------


def test_geo_reference_round_trip_and_the_importers_projection():
    lat = GEO.origin_latitude + np.array([0.0, 0.001, -0.002, 0.01])
    lon = GEO.origin_longitude + np.array([0.0, -0.003, 0.002, 0.01])
    x, y = GEO.from_wgs84(lat, lon)
    np.testing.assert_allclose((x, y), local_east_north(lat, lon, GEO.origin_latitude, GEO.origin_longitude))
    assert x[0] == y[0] == 0.0 and 100 < y[1] < 120 and -230 < x[1] < -220  # ~111 m per 0.001 deg north
    back = GEO.to_wgs84(x, y)
    np.testing.assert_allclose(back, (lat, lon), atol=1e-12)
    assert GeoReference.from_attrs(GEO.to_attrs()) == GEO
    for bad in ({"origin_latitude": 91, "origin_longitude": 0}, {"origin_latitude": "x", "origin_longitude": 0},
                {"origin_longitude": 0}):
        with pytest.raises(ValueError, match="geo_reference"):
            GeoReference.from_attrs(bad)


def _log(log_id: str, lat: float | None = None, lon: float | None = None):
    src = {} if lat is None else {"source": {"origin_latitude": lat, "origin_longitude": lon}}
    return SimpleNamespace(log_id=log_id, meta=src)


def test_geo_reference_of_logs_needs_one_origin_for_all(caplog):
    lat, lon = GEO.origin_latitude, GEO.origin_longitude
    assert geo_reference_of([_log("a", lat, lon), _log("b", lat, lon)]) == GEO
    assert geo_reference_of([_log("a"), _log("b")]) is None and not caplog.records
    assert geo_reference_of([_log("a", lat, lon), _log("b")]) is None
    assert "no geographic origin" in caplog.text
    assert geo_reference_of([_log("a", lat, lon), _log("b", lat + 0.001, lon)]) is None
    assert "m apart" in caplog.text


def test_publish_records_the_geo_reference_of_a_new_map_only(caplog):
    root = zarr.open_group(MemoryStore(), mode="w")
    assert read_geo_reference(root) is None
    assert _record_geo(root, GEO, new_map=True) and read_geo_reference(root) == GEO
    assert root.attrs[GEO_ATTR]["crs"] == "EPSG:4326"
    other = GeoReference(GEO.origin_latitude + 0.01, GEO.origin_longitude)
    assert not _record_geo(root, other, new_map=False) and read_geo_reference(root) == GEO
    assert "from the map's geographic origin" in caplog.text
    plain = zarr.open_group(MemoryStore(), mode="w")
    assert not _record_geo(plain, GEO, new_map=False) and read_geo_reference(plain) is None


def test_exported_bundle_keeps_the_geo_reference(site, tmp_path):
    from mapstore.bundle import open_bundle

    out = tmp_path / "b.zip"
    r = invoke("export", site["url"], out, "--version", "three", "--quiet")
    assert r.exit_code == 0, r.output
    with open_bundle(out) as b:
        assert read_geo_reference(b.root) == GEO
        assert read_floor(b.root).grid == GRID


# --- diff.html in a real browser ----------------------------------------------------------------

# Appended to a copy of the page: the boxes of the three pictures and how many images did not
# decode, as JSON in a <pre>.
_PROBE = """<script>
window.addEventListener('load', () => {
  const out = {viewport: [window.innerWidth, window.innerHeight]};
  for (const id of ['fig-from', 'fig-to', 'fig-overlay']) {
    const r = document.querySelector('#' + id + ' img').getBoundingClientRect();
    out[id] = [r.left, r.top, r.right, r.bottom];
  }
  const imgs = Array.from(document.images);
  out.images = imgs.length;
  out.broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  const p = document.createElement('pre');
  p.id = 'layout';
  p.textContent = JSON.stringify(out);
  document.body.appendChild(p);
});
</script>"""


def _chromium(tmp: Path, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """Headless Chromium on a profile of its own under ``tmp`` (nothing of the user's is read
    or written); console messages go to stderr (``--enable-logging=stderr``)."""
    return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                           "--no-first-run", f"--user-data-dir={tmp / 'chromium-profile'}",
                           "--enable-logging=stderr", "--v=0", *args], capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "HOME": str(tmp)})


def _layout(page: Path, width: int, height: int, tmp: Path) -> tuple[dict, str]:
    probe = tmp / f"probe-{width}.html"
    probe.write_text(page.read_text().replace("</body>", _PROBE + "</body>"))
    r = _chromium(tmp, f"--window-size={width},{height}", "--dump-dom", probe.as_uri())
    m = re.search(r'<pre id="layout">([^<]*)</pre>', r.stdout)
    assert m, (r.returncode, r.stderr[-2000:])
    return json.loads(m.group(1)), r.stderr


@pytest.mark.skipif(not Path(CHROMIUM).is_file(), reason=f"{CHROMIUM} absent (CI installs the OS package chromium)")
def test_diff_page_in_headless_chromium(diff_out, tmp_path):
    page = diff_out / "diff.html"
    # the page as the user gets it: no console message (no error) and a screenshot kept
    shot = tmp_path / "diff-1600x1000.png"
    r = _chromium(tmp_path, "--window-size=1600,1000", f"--screenshot={shot}", page.as_uri())
    assert r.returncode == 0 and shot.is_file(), r.stderr[-2000:]
    print(f"diff.html screenshot: {shot}")
    console = [ln for ln in r.stderr.splitlines() if ":CONSOLE" in ln]
    assert not console, console
    img = _read_rgb(shot)
    assert img.shape[:2] == (1000, 1600) and img.std() > 10  # a page was drawn, not a blank
    # on a wide screen the first screen shows FROM, TO and the overlay side by side, whole
    # (the viewport is the window less what the browser keeps: measured, not assumed)
    lay, err = _layout(page, 1600, 1000, tmp_path)
    assert not [ln for ln in err.splitlines() if ":CONSOLE" in ln]
    assert lay["images"] >= 3 and lay["broken"] == 0
    vw, vh = lay["viewport"]
    boxes = [lay[k] for k in ("fig-from", "fig-to", "fig-overlay")]
    assert boxes[0][2] <= boxes[1][0] and boxes[1][2] <= boxes[2][0], boxes  # left to right
    assert len({round(b[1]) for b in boxes}) == 1, boxes  # one row
    for left, top, right, bottom in boxes:
        assert 0 <= left and right <= vw and 0 < top and bottom <= vh, (boxes, vw, vh)
        assert right - left >= 400
    # on a narrow screen they wrap: one above the other
    lay, _ = _layout(page, 700, 1000, tmp_path)
    boxes = [lay[k] for k in ("fig-from", "fig-to", "fig-overlay")]
    assert boxes[0][3] <= boxes[1][1] and boxes[1][3] <= boxes[2][1], boxes
    assert all(b[2] <= lay["viewport"][0] for b in boxes)


def test_build_of_geotagged_logs_records_the_geo_reference(tmp_path):
    """A log whose drive.toml carries import-geotagged's [source] origin gives a new map its
    geo_reference (pipeline.stages.build -> pipeline.stages.publish)."""
    cfg = tmp_path / "small.toml"
    cfg.write_text("[map]\nchunk_px = 64\nshard_px = 256\nlayer_cell_px = 16\n")
    logs = tmp_path / "day1"
    r = invoke("simulate", "floor", logs, "--area", "1x1", "--seed", "5", "--quiet")
    assert r.exit_code == 0, r.output
    with open(logs / "drive.toml", "a") as f:
        f.write(f"\n[source]\nkind = \"geotagged_images\"\norigin_latitude = {GEO.origin_latitude}\n"
                f"origin_longitude = {GEO.origin_longitude}\n")
    report = tmp_path / "report.json"
    r = invoke("build", logs, "--map", tmp_path / "map", "-w", tmp_path / "w", "--config", cfg, "--quiet",
               "--report", report)
    assert r.exit_code == 0, r.output
    root = zarr.open_group(MapRepository.open(str(tmp_path / "map")).readonly(None).store, mode="r")
    assert read_geo_reference(root) == GEO
    assert json.loads(report.read_text())["publish"]["geo_reference"] == GEO.to_attrs()
    r = invoke("show", tmp_path / "map")
    assert r.exit_code == 0 and f"origin at latitude {GEO.origin_latitude:.7f}" in r.output, r.output
