"""Route panoramas (/routes/<id>, issue 7) in export bundles, deltas, verify and diff
(mapstore.export, mapstore.bundle, mapstore.diff, pipeline.cli.export, pipeline.cli.diff), on
a small synthetic floor (pipeline.testing.synthmap) with synthetic routes written by
mapstore.routes.write_route in later versions."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr

from mapstore.bundle import BundleWriter, apply_delta, open_bundle, read_manifest, verify_bundle
from mapstore.diff import DiffParams, RouteDiffParams, diff_maps, diff_route
from mapstore.export import Extract, export_extract, make_selection
from mapstore.grid import MapGrid
from mapstore.layout import read_floor, set_version
from mapstore.repository import MapRepository
from mapstore.routes import RouteRecord, delete_route, read_route, write_route
from pipeline.config import load_config
from pipeline.testing.synthmap import periodic_texture, publish_raster, texture_tile_fn
from conftest import invoke

GRID = MapGrid(0.0, 1.0, 0.0025, 400, 400)  # a 1 x 1 m floor, x 0..0.9975, y 1.0..0.0025
SPACING = 0.01
LOOP_X0, LOOP_Y, LOOP_ROWS = -1.0, 0.55, 401  # the loop route: y = 0.55, x -1.0 .. 3.0 m
CHUNK_ROWS = 100
CHANGED_ROWS = (150, 200)  # version 3 changes these rows of the loop (x 0.5 .. 0.99 m) ...
SECTORS_DEG = ((40, 70), (200, 215))  # ... in these azimuth sectors (a moved object)
LAYERS = "intensity,texture,uniqueness"
SMALL = """
[export]
route_margin_m = 0.1
"""


def _lines(seed: int, rows: int, shift: int = 0) -> np.ndarray:
    """Synthetic horizon lines: a periodic texture (360 x 360, 1 sample/degree), rows
    repeating every 360 rows; ``shift`` moves it along azimuth."""
    tex = periodic_texture(seed, 360, mean=120.0, std=40.0)
    return np.clip(np.rint(np.roll(tex[np.arange(rows) % 360], shift, axis=1)), 1, 255).astype(np.uint8)


def _loop(lines: np.ndarray | None = None, poses: np.ndarray | None = None) -> RouteRecord:
    x = LOOP_X0 + SPACING * np.arange(LOOP_ROWS)
    p = np.column_stack([x, np.full(LOOP_ROWS, LOOP_Y), np.zeros(LOOP_ROWS)]).astype(np.float32)
    return RouteRecord(_lines(5, LOOP_ROWS) if lines is None else lines, p if poses is None else poses, s0_m=0.0,
                       spacing_m=SPACING, samples_per_degree=1.0, sources=[{"log_id": "omni-1", "frames": 401}],
                       meta={"runs": 1})


def _aisle() -> RouteRecord:
    """A route far from the floor (y = 5 m): a region on the floor leaves it out."""
    m = 120
    p = np.column_stack([np.linspace(0, 1.19, m), np.full(m, 5.0), np.full(m, np.pi / 2)]).astype(np.float32)
    return RouteRecord(_lines(9, m, 17), p, s0_m=3.0, spacing_m=SPACING, samples_per_degree=1.0)


def _commit_routes(url: str, routes: dict[str, RouteRecord | None], tag: str) -> str:
    """A new map version writing (or deleting, None) routes; the floor is untouched."""
    repo = MapRepository.open(url)
    with repo.commit_lock():
        session = repo.writable()
        root = zarr.open_group(session.store, mode="a")
        version = read_floor(root).version + 1
        set_version(root, version)
        for rid, rec in routes.items():
            if rec is None:
                delete_route(root, rid)
            else:
                rec.version = version
                write_route(root, rid, rec, rows_per_chunk=CHUNK_ROWS)
        sid = repo.commit(session, f"routes: version {version}", metadata={"version": version, "tag": tag})
        repo.tag(sid, tag)
    return sid


def _changed_loop(gain: float = 1.0, noise: float = 0.0, pose_dy: float = 0.0) -> RouteRecord:
    """The loop with SECTORS_DEG of CHANGED_ROWS replaced (another texture, brighter);
    optionally every row under another gain with noise (a re-rendered route) and the
    changed rows' poses moved sideways by ``pose_dy`` metres."""
    lines = _lines(5, LOOP_ROWS).astype(np.float32)
    other = _lines(23, LOOP_ROWS).astype(np.float32) + 30.0
    r0, r1 = CHANGED_ROWS
    for a0, a1 in SECTORS_DEG:
        lines[r0:r1, a0:a1] = other[r0:r1, a0:a1]
    if gain != 1.0 or noise:
        lines = lines * gain + np.random.default_rng(3).normal(0.0, noise, lines.shape)
    rec = _loop(np.clip(np.rint(lines), 1, 255).astype(np.uint8))
    if pose_dy:
        rec.poses[r0:r1, 1] += pose_dy
    return rec


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """v1: the floor alone; v2: + routes loop and aisle; v3: the loop changed in two sectors
    over 0.5 m, aisle removed, route "spur" added; v4: v3's loop re-rendered (darker, noisy)
    with the changed rows' poses moved 2 cm."""
    root = tmp_path_factory.mktemp("routes")
    cfg = load_config(None)
    cfg["map"].update({"chunk_px": 64, "shard_px": 256, "layer_cell_px": 16})
    url = str(root / "map")
    sids = {"v1": publish_raster(url, GRID, texture_tile_fn(periodic_texture(7, 256), GRID), cfg=cfg, tag="v1")}
    sids["v2"] = _commit_routes(url, {"loop": _loop(), "aisle": _aisle()}, "v2")
    spur = RouteRecord(_lines(31, 50), np.column_stack([np.full(50, 0.3), np.linspace(0.1, 0.59, 50),
                                                        np.full(50, 1.0)]), spacing_m=SPACING)
    sids["v3"] = _commit_routes(url, {"loop": _changed_loop(), "aisle": None, "spur": spur}, "v3")
    sids["v4"] = _commit_routes(url, {"loop": _changed_loop(0.8, 2.0, 0.02)}, "v4")
    small = root / "small.toml"
    small.write_text(SMALL)
    return {"root": root, "url": url, "sids": sids, "cfg": small}


def _map(site, version: str) -> zarr.Group:
    return zarr.open_group(MapRepository.open(site["url"]).readonly(version).store, mode="r")


def _export(site, out: Path, *args) -> dict:
    r = invoke("export", site["url"], out, "--layers", LAYERS, "--report", out.with_suffix(".json"), *args)
    assert r.exit_code == 0, r.output
    return json.loads(out.with_suffix(".json").read_text())


def _same_record(a: RouteRecord, b: RouteRecord) -> None:
    np.testing.assert_array_equal(a.lines, b.lines)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert (a.s0_m, a.spacing_m, a.samples_per_degree, a.horizon_band_deg, a.version) == (
        b.s0_m, b.spacing_m, b.samples_per_degree, b.horizon_band_deg, b.version)
    assert a.sources == b.sources and a.meta == b.meta


# --- export ------------------------------------------------------------------------------------


def test_all_routes_read_from_the_bundle_as_from_the_map(site, tmp_path):
    out = tmp_path / "all.zip"
    rep = _export(site, out, "--version", "v2")
    m = read_manifest(out)
    assert [r["id"] for r in m["routes"]] == ["aisle", "loop"] and m["selection"]["routes"] == "all"
    loop = next(r for r in m["routes"] if r["id"] == "loop")
    assert loop["rows"] == LOOP_ROWS and loop["s0_m"] == 0.0 and not loop["cropped"] and loop["version"] == 2
    # the map's keys, unsharded, one member per chunk of rows
    assert {f"routes/loop/lines/c/{i}/0" for i in range(5)} | {"routes/loop/poses/c/4/0", "routes/zarr.json",
                                                              "routes/loop/zarr.json"} <= set(m["members"])
    assert {r["id"]: r["chunks"] for r in rep["routes"]} == {"aisle": 4, "loop": 10}
    assert rep["tiles_by_array"]["routes/loop/lines"] == 5
    src = _map(site, "v2")
    with open_bundle(out) as b:
        assert b.routes() == ["aisle", "loop"]
        for rid in ("aisle", "loop"):
            _same_record(b.read_route(rid), read_route(src, rid))
        arr = b.root["routes/loop/lines"]
        assert arr.shards is None and arr.chunks == (CHUNK_ROWS, 360)
        with pytest.raises(KeyError, match="no route"):
            b.read_route("spur")
    # any zarr reader: read_route over zarr's ZipStore
    zs = zarr.open_group(zarr.storage.ZipStore(out, mode="r"), mode="r")
    _same_record(read_route(zs, "loop"), read_route(src, "loop"))
    assert verify_bundle(out) == []


def test_routes_none_and_one_id(site, tmp_path):
    none, one = tmp_path / "none.zip", tmp_path / "one.zip"
    rep = _export(site, none, "--version", "v2", "--routes", "none")
    m = read_manifest(none)
    assert m["routes"] == [] and rep["routes"] == [] and m["selection"]["routes"] == []
    assert not any(n.startswith("routes/") for n in m["members"])
    with open_bundle(none) as b:
        assert b.routes() == []
    _export(site, one, "--version", "v2", "--routes", "aisle")
    m = read_manifest(one)
    assert [r["id"] for r in m["routes"]] == ["aisle"] and m["selection"]["routes"] == ["aisle"]
    assert not any(n.startswith("routes/loop") for n in m["members"])
    with open_bundle(one) as b:
        assert b.routes() == ["aisle"]
        _same_record(b.read_route("aisle"), read_route(_map(site, "v2"), "aisle"))
    r = invoke("export", site["url"], tmp_path / "x.zip", "--version", "v2", "--routes", "loop,nope")
    assert r.exit_code == 2 and "--routes: no route 'nope'" in r.output, r.output
    r = invoke("export", site["url"], tmp_path / "x.zip", "--routes", "a/b")
    assert r.exit_code == 2 and "--routes" in r.output and "route id" in r.output, r.output
    assert not (tmp_path / "x.zip").exists()


def test_region_crops_routes_to_their_rows_inside(site, tmp_path):
    out = tmp_path / "region.zip"
    box = (0.2, 0.3, 0.7, 0.9)
    rep = _export(site, out, "--version", "v2", "--region", ",".join(map(str, box)), "--config", site["cfg"])
    m = read_manifest(out)
    assert m["selection"]["route_margin_m"] == 0.1
    assert [r["id"] for r in m["routes"]] == ["loop"]  # aisle (y = 5 m) has no row inside
    # rows whose x lies in [0.1, 0.8] (the box grown by the 0.1 m margin; y = 0.55 inside)
    x = _loop().poses[:, 0].astype(float)  # as stored (float32)
    inside = np.nonzero((x >= box[0] - 0.1) & (x <= box[2] + 0.1))[0]
    i0, i1 = int(inside[0]), int(inside[-1]) + 1
    entry = m["routes"][0]
    assert (entry["row0"], entry["rows"], entry["rows_in_map"], entry["cropped"]) == (i0, i1 - i0, LOOP_ROWS, True)
    assert entry["s0_m"] == pytest.approx(i0 * SPACING)
    full = read_route(_map(site, "v2"), "loop")
    with open_bundle(out) as b:
        got = b.read_route("loop")
    np.testing.assert_array_equal(got.lines, full.lines[i0:i1])
    np.testing.assert_array_equal(got.poses, full.poses[i0:i1])
    assert got.s0_m == pytest.approx(full.s[i0]) and got.meta == full.meta and got.version == 2
    assert "cut" in invoke("export", site["url"], tmp_path / "r2.zip", "--version", "v2", "--region",
                           ",".join(map(str, box)), "--config", site["cfg"]).output
    assert rep["routes"][0]["rows"] == i1 - i0
    # a corridor across the loop keeps the rows near it
    csv = tmp_path / "path.csv"
    csv.write_text("x,y\n0.4,0.1\n0.4,0.9\n")
    corr = tmp_path / "corr.zip"
    _export(site, corr, "--version", "v2", "--corridor", csv, "--width", "0.2", "--config", site["cfg"])
    entry = read_manifest(corr)["routes"][0]
    assert entry["s0_m"] == pytest.approx(0.4 - 0.2 - LOOP_X0, abs=0.011) and entry["rows"] in (40, 41)


def test_verify_names_a_flipped_byte_in_a_route_member(site, tmp_path):
    out = tmp_path / "all.zip"
    _export(site, out, "--version", "v2", "--levels", "3")
    data = bytearray(out.read_bytes())
    with zipfile.ZipFile(out) as z:
        for name in ("routes/loop/lines/c/2/0", "routes/loop/poses/c/0/0", "routes/loop/zarr.json"):
            zi = z.getinfo(name)
            bad = bytearray(data)
            bad[zi.header_offset + 30 + len(name) + 5] ^= 0x01
            path = tmp_path / "bad.zip"
            path.write_bytes(bytes(bad))
            problems = verify_bundle(path)
            assert problems and problems[0] == f"member {name}: sha256 mismatch", problems
            r = invoke("verify", path)
            assert r.exit_code == 2 and name in r.output


# --- deltas -------------------------------------------------------------------------------------


def test_delta_with_routes_applies_to_the_byte_identical_bundle(site, tmp_path):
    base, delta, patched, api = (tmp_path / n for n in ("v2.zip", "delta.zip", "patched.zip", "api.zip"))
    _export(site, base, "--version", "v2")
    rep = _export(site, delta, "--version", "v3", "--since", "v2")
    dm = read_manifest(delta)
    routes = [n for n in dm["changed"] if n.startswith("routes/")]
    # the loop: only the chunk of rows 100..199 of its lines (poses unchanged), and its group
    # attributes (version 3); spur new whole; aisle removed
    assert [n for n in routes if n.startswith("routes/loop/")] == ["routes/loop/zarr.json",
                                                                   "routes/loop/lines/c/1/0"]
    assert {n for n in routes if n.startswith("routes/spur/")} == {
        "routes/spur/zarr.json", "routes/spur/lines/zarr.json", "routes/spur/poses/zarr.json",
        "routes/spur/lines/c/0/0", "routes/spur/poses/c/0/0"}
    assert set(dm["removed"]) >= {"routes/aisle/zarr.json", "routes/aisle/lines/c/0/0", "routes/aisle/poses/c/1/0"}
    assert not any(n.startswith("floor/") and "/c/" in n for n in dm["changed"])  # the floor did not change
    assert rep["tiles_by_array"] == {"routes/loop/lines": 1, "routes/spur/lines": 1, "routes/spur/poses": 1}
    r = invoke("apply-delta", base, delta, patched)
    assert r.exit_code == 0, r.output
    # byte for byte a full export of v3 (the CLI's defaults, made with the delta's time)
    root = _map(site, "v3")
    from pipeline.reloc_export import reloc_index_array

    sel = make_selection(read_floor(root), levels=None, layers=LAYERS.split(","))
    export_extract(Extract(root, sel, 3, [reloc_index_array(None, 64)]), BundleWriter(api), snapshot=site["sids"]["v3"],
                   tags=["v3"], created=dm["result"]["created"])
    assert api.read_bytes() == patched.read_bytes()
    with open_bundle(patched) as b:
        assert b.routes() == ["loop", "spur"]
        _same_record(b.read_route("loop"), read_route(root, "loop"))
    # the same with a region: the cut routes' deltas apply too
    args = ("--region", "0.2,0.3,0.7,0.9", "--config", site["cfg"])
    rb, rd, rn, rp = (tmp_path / n for n in ("rb.zip", "rd.zip", "rn.zip", "rp.zip"))
    _export(site, rb, "--version", "v2", *args)
    _export(site, rn, "--version", "v3", *args)
    _export(site, rd, "--version", "v3", "--since", "v2", *args)
    apply_delta(rb, rd, rp)
    assert read_manifest(rp)["members"] == read_manifest(rn)["members"]
    assert read_manifest(rp)["routes"] == read_manifest(rn)["routes"]


# --- diff ---------------------------------------------------------------------------------------


def _check_loop_change(ch, pose_dy: float) -> None:
    assert len(ch.ranges) == 1, [(r.s_m, r.sectors) for r in ch.ranges]
    rng = ch.ranges[0]
    s0, s1 = CHANGED_ROWS[0] * SPACING, (CHANGED_ROWS[1] - 1) * SPACING
    assert abs(rng.s_m[0] - s0) <= 0.03 and abs(rng.s_m[1] - s1) <= 0.03, rng.s_m
    got = [(x["start_deg"], x["end_deg"]) for x in rng.sectors]
    assert len(got) == len(SECTORS_DEG), got
    for (a0, a1), (g0, g1) in zip(SECTORS_DEG, got):
        assert abs(g0 - a0) <= 4 and abs(g1 - a1) <= 4, got  # spread by up to half normalize_deg
    assert ch.pose_move_max_m == pytest.approx(pose_dy, abs=1e-4)
    unchanged = np.ones(len(ch.s), bool)
    unchanged[rng.i0:rng.i1] = False
    assert ch.score[unchanged].max() < 0.05


def test_diff_finds_the_changed_sectors_over_the_path_range(site):
    repo = MapRepository.open(site["url"])
    sid = site["sids"]
    res = diff_maps(repo, sid["v2"], sid["v3"], DiffParams())
    rd = res.routes
    assert not res.regions and rd.from_ids == ["aisle", "loop"] and rd.to_ids == ["loop", "spur"]
    assert [a["id"] for a in rd.added] == ["spur"] and [r["id"] for r in rd.removed] == ["aisle"]
    assert [c.id for c in rd.changed] == ["loop"] and rd.unchanged == []
    _check_loop_change(rd.changed[0], 0.0)
    # against a re-rendered route: 20 % darker, noise of 2 grey levels, poses moved 2 cm
    res = diff_maps(repo, sid["v2"], sid["v4"], DiffParams())
    ch = res.routes.changed[0]
    _check_loop_change(ch, 0.02)
    assert ch.pose_moved is False and ch.pose_move_max_deg == pytest.approx(0.0, abs=1e-6)
    # v3 -> v4: the same content re-rendered: no changed range, the pose move reported
    res = diff_maps(repo, sid["v3"], sid["v4"], DiffParams())
    assert res.routes.unchanged == ["spur"] and not res.routes.changed[0].ranges


def test_diff_route_on_different_grids_resamples_path_length():
    a = _loop()
    # the same route stored from s = 0.105 m at 2 cm spacing: compared at the same path lengths
    s = 0.105 + 0.02 * np.arange(180)
    f = s / SPACING
    i0 = np.floor(f).astype(int)
    w = (f - i0)[:, None]
    lines = np.rint(a.lines[i0] * (1 - w) + a.lines[i0 + 1] * w).astype(np.uint8)
    poses = np.column_stack([LOOP_X0 + s, np.full(len(s), LOOP_Y), np.zeros(len(s))])
    b = RouteRecord(lines, poses, s0_m=0.105, spacing_m=0.02)
    ch = diff_route("loop", a, b, RouteDiffParams())
    assert ch.step_m == 0.02 and ch.s[0] == pytest.approx(0.105) and not ch.ranges
    assert ch.s_only_from == [(0.0, pytest.approx(0.105)), (pytest.approx(ch.s[-1]), 4.0)]
    assert ch.pose_move_max_m < 1e-5 and np.median(ch.score) < 0.02


def test_cli_diff_reports_routes_with_a_figure(site, tmp_path):
    out = tmp_path / "out"
    r = invoke("diff", site["url"], "v2", "v4", "--out", out, "--report", tmp_path / "rep.json")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "rep.json").read_text())
    rt = rep["routes"]
    assert rt["from"] == ["aisle", "loop"] and rt["to"] == ["loop", "spur"]
    assert rt["summary"] == {"from": 2, "to": 2, "added": 1, "removed": 1, "unchanged": 0, "changed": 1,
                             "changed_ranges": 1, "changed_length_m": pytest.approx(0.49, abs=0.06), "sectors": 2,
                             "pose_moved": 0}
    c = rt["changed"][0]
    assert c["id"] == "loop" and c["rows_compared"] == LOOP_ROWS and c["step_m"] == SPACING
    assert len(c["profile"]["score"]) == LOOP_ROWS and c["pose_move_max_m"] == pytest.approx(0.02, abs=1e-4)
    assert [x["width_deg"] for x in c["ranges"][0]["sectors"]] == [pytest.approx(30, abs=8), pytest.approx(15, abs=8)]
    assert "routes: 2 -> 2: 1 added (spur), 1 removed (aisle)" in r.output and "sectors 3" in r.output, r.output
    fig = cv2.imread(str(out / "route-loop.png"))
    from pipeline import map_figures as mf  # drawn with axes, colour bars and a legend (two keys); one row a pixel

    assert fig is not None and fig.shape[1] > mf.LEFT + 3 * 360 + mf.RIGHT
    assert fig.shape[0] == mf.TOP + mf.PANEL_TITLE + LOOP_ROWS + mf.BOTTOM + 2 * mf.LEGEND_ROW + mf.LEGEND_PAD
    assert rep["outputs"]["route_loop"] == str(out / "route-loop.png")
    page = (out / "diff.html").read_text()
    assert "Route panoramas" in page and "Route loop" in page


def _routes_only_repo(url: str) -> list[str]:
    """A map of route panoramas only (as a routes-only build publishes it: /routes, no
    /floor): version 1 the loop and the aisle, version 2 the loop extended by 1 m at its
    end (rows appended, the old rows unchanged). Returns the two snapshots."""
    repo = MapRepository.create(url)
    snaps = []
    for version in (1, 2):
        with repo.commit_lock():
            session = repo.writable()
            root = zarr.open_group(session.store, mode="a")
            loop = _loop()
            if version == 2:
                n = LOOP_ROWS + 100
                x = LOOP_X0 + SPACING * np.arange(n)
                loop = _loop(_lines(5, n), np.column_stack([x, np.full(n, LOOP_Y), np.zeros(n)]).astype(np.float32))
            loop.version = version
            write_route(root, "loop", loop, rows_per_chunk=CHUNK_ROWS)
            if version == 1:
                aisle = _aisle()
                aisle.version = 1
                write_route(root, "aisle", aisle, rows_per_chunk=CHUNK_ROWS)
            snaps.append(session.commit(f"routes v{version}"))
    return snaps


def test_routes_only_map_exports_verifies_and_applies_deltas(tmp_path):
    """A map without a floor: the bundle holds the routes only (manifest routes_only), verifies,
    reads back through open_bundle(require_floor=False), a region cuts the routes, and a
    delta (the loop grown by 1 m) applies to the byte-identical full bundle."""
    from mapstore.bundle import BundleError
    from mapstore.export import SelectionError, export_delta

    url = str(tmp_path / "routes-map")
    s1, s2 = _routes_only_repo(url)
    repo = MapRepository.open(url)
    roots = [zarr.open_group(repo.readonly(s).store, mode="r") for s in (s1, s2)]
    sel = make_selection(None, layers=("intensity",), routes="all", route_ids=["aisle", "loop"])
    assert sel.levels == () and sel.layers == ()
    with pytest.raises(SelectionError, match="no floor"):
        make_selection(None, routes="none", route_ids=["aisle", "loop"])
    paths = []
    for k, (root, sid) in enumerate(zip(roots, (s1, s2))):
        ext = Extract(root, sel, 3)
        assert not ext.has_floor and ext.version == k + 1
        out = tmp_path / f"v{k + 1}.bundle"
        m = export_extract(ext, BundleWriter(out), snapshot=sid, created="2026-01-01T00:00:00+00:00")
        assert verify_bundle(out) == []
        assert m["routes_only"] is True and m["grid"] is None and m["levels"] == {} and m["layers"] == {}
        assert {r["id"] for r in m["routes"]} == {"aisle", "loop"} and m["version"]["number"] == k + 1
        assert not any(n.startswith("floor/") for n in m["members"])
        assert m["bounds_m"][1] == pytest.approx(LOOP_Y) and m["bounds_m"][3] == pytest.approx(5.0)
        paths.append(out)
    with pytest.raises(BundleError, match="route panoramas only"):
        open_bundle(paths[1])
    with open_bundle(paths[1], require_floor=False) as b:
        assert not b.has_floor and b.levels == () and b.routes() == ["aisle", "loop"]
        _same_record(b.read_route("loop"), read_route(roots[1], "loop"))
        with pytest.raises(BundleError, match="no floor"):
            b.grid
    # a region keeps the loop's rows near it and leaves the aisle out
    reg = make_selection(None, region=(0.0, 0.0, 1.0, 1.0), routes="all", route_ids=["aisle", "loop"],
                         route_margin_m=0.1)
    m = export_extract(Extract(roots[1], reg, 3), BundleWriter(tmp_path / "r.bundle"), snapshot=s2)
    assert [r["id"] for r in m["routes"]] == ["loop"] and m["routes"][0]["cropped"]
    assert m["bounds_m"] == [0.0, 0.0, 1.0, 1.0]
    # the delta v1 -> v2 carries the loop's changed chunks and applies byte for byte
    delta = tmp_path / "d.bundle"
    dm = export_delta(Extract(roots[1], sel, 3), Extract(roots[0], sel, 3), {}, BundleWriter(delta), snapshot=s2,
                      base_snapshot=s1, created="2026-01-01T00:00:00+00:00")
    assert verify_bundle(delta) == [] and dm["base"]["number"] == 1
    changed = [n for n in dm["changed"] if "/c/" in n]
    assert changed and all(n.startswith("routes/loop/") for n in changed)
    assert len(changed) < len([n for n in read_manifest(paths[1])["members"] if "/c/" in n])
    applied = tmp_path / "applied.bundle"
    apply_delta(paths[0], delta, applied)
    assert applied.read_bytes() == paths[1].read_bytes()


def test_cli_exports_a_routes_only_map(tmp_path):
    """`mosaicmap export` (full and --since) and `verify` on a map holding routes and no floor."""
    url = str(tmp_path / "routes-map")
    s1, _ = _routes_only_repo(url)
    out = tmp_path / "r.bundle"
    r = invoke("export", url, out, "--report", tmp_path / "r.json")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "r.json").read_text())
    assert {x["id"] for x in rep["routes"]} == {"aisle", "loop"}
    assert invoke("verify", out).exit_code == 0
    r = invoke("export", url, tmp_path / "d.bundle", "--since", s1)
    assert r.exit_code == 0, r.output
    assert "loop" in r.output
    # signed, as vehicles need it: the full bundle and the delta, applied into a signed bundle
    key, pub = tmp_path / "owner.key", tmp_path / "owner.key.pub"
    assert invoke("keys", "new", key).exit_code == 0
    base = tmp_path / "base.bundle"
    assert invoke("export", url, base, "--version", s1, "--sign", key, "--quiet").exit_code == 0
    assert invoke("export", url, tmp_path / "sd.bundle", "--since", s1, "--sign", key, "--quiet").exit_code == 0
    r = invoke("apply-delta", base, tmp_path / "sd.bundle", tmp_path / "new.bundle", "--key", pub)
    assert r.exit_code == 0, r.output
    r = invoke("verify", tmp_path / "new.bundle", "--key", pub)
    assert r.exit_code == 0 and "signature verified" in r.output, r.output


def test_cli_export_refuses_a_bad_route_chunking(tmp_path):
    url = str(tmp_path / "routes-map")
    _routes_only_repo(url)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[export]\nroute_rows_per_chunk = -5\n")
    r = invoke("export", url, tmp_path / "r.bundle", "--config", cfg)
    assert r.exit_code == 2 and "[export] route_rows_per_chunk: -5 is out of range" in r.output
    assert not (tmp_path / "r.bundle").exists()
