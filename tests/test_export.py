"""Export bundles, verify, deltas and OME-Zarr extracts (mapstore.bundle, mapstore.export,
pipeline.cli.export) on small synthetic maps published with pipeline.testing.synthmap."""

from __future__ import annotations

import json
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zarr

from mapstore.bundle import (MANIFEST, SEAL_LEN, apply_delta, open_bundle, read_manifest, verify_bundle,
                             verify_bytes)
from mapstore.export import Extract, export_extract, make_selection
from mapstore.grid import MapGrid
from mapstore.layout import LAYERS, read_floor
from mapstore.repository import MapRepository
from pipeline.config import load_config
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn
from conftest import invoke

REPO_DIR = Path(__file__).resolve().parents[1]
PX = 0.0025
GRID = MapGrid(0.0, 1.5, PX, 560, 600)  # 1.4 x 1.5 m; x 0..1.3975, y 1.5..0.0025
DATA_COLS = 480  # columns >= 480 (x >= 1.2 m) hold no data: their tiles are absent from bundles
PATCH = Patch(0.5, 0.6, 0.7, 0.75, delta=40.0)  # version 2 changes this box (0.2 x 0.15 m)
PARTS = ("member ", "manifest.json", "seal", "zip structure", "truncated")


def _cut(tile_fn):
    def fn(r0, r1, c0, c1):
        out = tile_fn(r0, r1, c0, c1)
        out[:, max(0, DATA_COLS - c0):] = 0
        return out
    return fn


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A map with two versions: v1 (texture over x < 1.2 m) and v2 (PATCH repainted),
    64-px chunks in 256-px shards (several shards, 5 levels)."""
    root = tmp_path_factory.mktemp("export")
    cfg = load_config(None)
    cfg["map"].update({"chunk_px": 64, "shard_px": 256, "layer_cell_px": 16})
    url = str(root / "map")
    tex = periodic_texture(7, 256)
    v1 = publish_raster(url, GRID, _cut(texture_tile_fn(tex, GRID)), cfg=cfg, tag="v1")
    shards = shards_for_box(GRID, 256, PATCH.x0, PATCH.y0, PATCH.x1, PATCH.y1, pad_px=16)
    v2 = publish_raster(url, GRID, _cut(texture_tile_fn(tex, GRID, [PATCH])), cfg=cfg, tag="v2", shards=shards)
    full1, full2 = root / "full1.zip", root / "full2.zip"
    for v, out in (("v1", full1), ("v2", full2)):
        r = invoke("export", url, out, "--version", v, "--levels", "", "--layers", "intensity,texture,uniqueness,"
                   "coverage,updated", "--report", out.with_suffix(".json"))
        assert r.exit_code == 0, r.output
    return {"root": root, "url": url, "v1": v1, "v2": v2, "full1": full1, "full2": full2, "cfg": cfg}


def _map(site, version: str) -> zarr.Group:
    return zarr.open_group(MapRepository.open(site["url"]).readonly(version).store, mode="r")


def _flip(src: Path, dst: Path, pos: int, xor: int = 0xFF) -> None:
    data = bytearray(src.read_bytes())
    data[pos] ^= xor
    dst.write_bytes(bytes(data))


def _seg_dist(x, y, a, b):
    """Distance (m) of points to segment a-b: the test's own geometry (not the module's)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    t = np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / (d @ d), 0, 1)
    return np.hypot(x - a[0] - t * d[0], y - a[1] - t * d[1])


def _centres(grid: MapGrid):
    rows, cols = grid.shape
    c, r = np.meshgrid(np.arange(cols), np.arange(rows))
    return grid.pixel_to_world(c, r)


# --- full bundles ---------------------------------------------------------------------------


def test_full_bundle_round_trip_and_manifest(site):
    m = read_manifest(site["full2"])
    rep = json.loads(site["full2"].with_suffix(".json").read_text())
    assert m["format"] == "mosaicmap-bundle" and m["format_version"] == 1 and m["kind"] == "full"
    src = _map(site, "v2")
    info = read_floor(src)
    assert m["map_id"] == info.map_id and m["version"] == {"snapshot": site["v2"], "tags": ["v2"], "number": 2}
    assert m["created"].endswith("+00:00") and MapGrid.from_attrs(m["grid"]) == GRID and m["tile_px"] == 64
    assert m["selection"]["kind"] == "all" and m["selection"]["levels"] == list(range(info.levels))
    assert m["bounds_m"] == pytest.approx(list(GRID.bounds))
    assert set(m["levels"]) == {str(k) for k in range(info.levels)}
    assert m["levels"]["2"]["shape"] == list(GRID.level(2).shape)
    assert set(m["layers"]) == set(LAYERS) and m["layers"]["texture"]["cell_px"] == 16
    assert rep["members"] == len(m["members"]) + 1 and rep["bytes"] == site["full2"].stat().st_size
    assert all(len(v["sha256"]) == 64 for v in m["members"].values())
    assert verify_bundle(site["full2"]) == []
    r = invoke("verify", site["full2"])
    assert r.exit_code == 0 and "OK" in r.output, r.output
    with open_bundle(site["full2"]) as b:
        assert read_floor(b.root).version == 2 and b.grid == GRID and b.tile_px == 64
        assert b.levels == tuple(range(info.levels)) and b.layers == tuple(LAYERS)
        for k in range(info.levels):
            arr = b.root[f"floor/{k}"]
            assert arr.shards is None and arr.chunks == (64, 64)
            np.testing.assert_array_equal(b.read(k), src[f"floor/{k}"][...])
        for name in LAYERS:
            np.testing.assert_array_equal(b.read_layer(name), src[f"floor/layers/{name}"][...])
        assert b.root["floor/layers/texture"].chunks == (4, 4)  # the cells of one 64-px tile
        # one tile, and tiles without data absent from the zip
        np.testing.assert_array_equal(b.read_tile(0, 2, 3), src["floor/0"][128:192, 192:256])
        assert b.has_tile(0, 0, 0) and not b.has_tile(0, 0, -(-DATA_COLS // 64))
        assert f"floor/0/c/0/{-(-DATA_COLS // 64)}" not in m["members"]
        ome = b.root["floor"].attrs["ome"]["multiscales"][0]["datasets"]
        assert [d["path"] for d in ome] == [str(k) for k in range(info.levels)]


def test_read_tile_decodes_each_chunk_as_zarr_does(site):
    """Bundle.read_tile decodes a tile's chunk itself (levels stored as mosaicmap writes
    them): every tile of every level, edge tiles (clipped) and absent ones (no data), equals
    zarr's read of the same window, and is writable like it."""
    with open_bundle(site["full2"]) as b:
        absent = 0
        for k in b.levels:
            assert b._plain_tiles(k) == (True, 0)
            rows, cols = b.tiles_shape(k)
            for r in range(rows):
                for c in range(cols):
                    a = b.read_tile(k, r, c)
                    np.testing.assert_array_equal(a, b.root[f"floor/{k}"][b.tile_slices(k, r, c)])
                    assert a.dtype == np.uint8 and a.flags.writeable
                    absent += not b.has_tile(k, r, c)
        assert absent  # tiles without data read as 0
        b._plain[0] = None  # another layout: zarr reads it, the same pixels
        np.testing.assert_array_equal(b.read_tile(0, 2, 3), b.root["floor/0"][128:192, 192:256])


def test_same_content_gives_the_same_bytes(site, tmp_path):
    root = _map(site, "v1")
    info = read_floor(root)
    sel = make_selection(info, region=(0.1, 0.2, 0.9, 1.0), levels=[0, 2], layers=["intensity", "uniqueness"])
    paths = []
    for name in ("a.zip", "b.zip"):
        from mapstore.bundle import BundleWriter

        export_extract(Extract(root, sel, 3), BundleWriter(tmp_path / name), snapshot=site["v1"], tags=["v1"],
                       created="2026-01-01T00:00:00+00:00")
        paths.append(tmp_path / name)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    with zipfile.ZipFile(paths[0]) as z:
        infos = z.infolist()
        assert infos[-1].filename == MANIFEST and all(i.compress_type == zipfile.ZIP_STORED for i in infos)
        assert all(i.date_time == (1980, 1, 1, 0, 0, 0) for i in infos)
        assert z.comment.startswith(b"mosaicmap-bundle-v1 sha256=") and len(z.comment) == SEAL_LEN


def test_region_keeps_the_pixels_meeting_the_box(site, tmp_path):
    out = tmp_path / "region.zip"
    box = (0.3, 0.4, 0.8, 0.9)
    r = invoke("export", site["url"], out, "--region", ",".join(map(str, box)), "--levels", "0,3",
               "--layers", "intensity,texture")
    assert r.exit_code == 0, r.output
    src = _map(site, "latest")
    m = read_manifest(out)
    assert m["selection"]["region_m"] == list(box) and m["bounds_m"] == pytest.approx(list(box))
    with open_bundle(out) as b:
        assert b.levels == (0, 3) and b.layers == ("texture",)
        for path, grid, got in (("floor/0", GRID.level(0), b.read(0)), ("floor/3", GRID.level(3), b.read(3)),
                                ("floor/layers/texture", GRID.coarsened(16), b.read_layer("texture"))):
            x, y = _centres(grid)
            h = grid.pixel_size / 2
            keep = (x + h > box[0]) & (x - h < box[2]) & (y + h > box[1]) & (y - h < box[3])
            want = src[path][...]
            np.testing.assert_array_equal(got[keep], want[keep])
            fill = np.isnan(got[~keep]).all() if got.dtype.kind == "f" else (got[~keep] == 0).all()
            assert fill, path
    # only the tiles meeting the box are members
    tiles = {tuple(map(int, n.split("/")[-2:])) for n in m["members"] if n.startswith("floor/0/c/")}
    c0, r0 = (int(v) // 64 for v in GRID.world_to_pixel(box[0], box[3]))
    c1, r1 = (int(v) // 64 for v in GRID.world_to_pixel(box[2], box[1]))
    assert tiles == {(i, j) for i in range(r0, r1 + 1) for j in range(c0, c1 + 1)}


def test_corridor_keeps_the_pixels_near_the_path(site, tmp_path):
    path = [(0.1, 0.2), (1.0, 0.3), (1.1, 1.3)]
    csv_xy = tmp_path / "path.csv"
    csv_xy.write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in path))
    csv_log = tmp_path / "drive.csv"  # drive-log style, with collinear points in between
    csv_log.write_text("t,x,y,theta\n0,0.1,0.2,0\n1,0.55,0.25,0\n2,1.0,0.3,1.4\n3,1.05,0.8,1.4\n4,1.1,1.3,1.4\n")
    width = 0.2
    a, b = tmp_path / "a.zip", tmp_path / "b.zip"
    for csv, out in ((csv_xy, a), (csv_log, b)):
        r = invoke("export", site["url"], out, "--corridor", csv, "--width", width, "--levels", "0,2",
                   "--layers", "intensity,uniqueness", "--report", out.with_suffix(".json"))
        assert r.exit_code == 0, r.output
    ma, mb = read_manifest(a), read_manifest(b)
    assert ma["selection"]["corridor_m"] == [list(p) for p in path] and ma["selection"]["width_m"] == width
    assert ma["members"] == mb["members"]  # the collinear points simplify away
    src = _map(site, "latest")
    with open_bundle(a) as bd:
        for path_name, grid, got in (("floor/0", GRID, bd.read(0)), ("floor/2", GRID.level(2), bd.read(2)),
                                     ("floor/layers/uniqueness", GRID.coarsened(16), bd.read_layer("uniqueness"))):
            x, y = _centres(grid)
            d = np.minimum.reduce([_seg_dist(x, y, path[i], path[i + 1]) for i in range(len(path) - 1)])
            keep = d <= width / 2 + grid.pixel_size * np.sqrt(0.5)
            want = src[path_name][...]
            np.testing.assert_array_equal(got[keep], want[keep])
            outside = got[~keep]
            assert (np.isnan(outside) if outside.dtype.kind == "f" else outside == 0).all(), path_name
            assert keep.any() and (~keep).any()
    full = json.loads(site["full2"].with_suffix(".json").read_text())
    assert json.loads(a.with_suffix(".json").read_text())["bytes"] < full["bytes"] / 2


def test_levels_and_layers_selection(site, tmp_path):
    out = tmp_path / "sel.zip"
    r = invoke("export", site["url"], out, "--levels", "1,3", "--layers", "intensity,coverage")
    assert r.exit_code == 0, r.output
    with open_bundle(out) as b:
        assert b.levels == (1, 3) and b.layers == ("coverage",)
        assert set(b.root["floor"].array_keys()) == {"1", "3"}
        assert set(b.root["floor/layers"].array_keys()) == {"coverage"}
        with pytest.raises(ValueError, match="level 0 is not in the bundle"):
            b.read_tile(0, 0, 0)
        with pytest.raises(ValueError, match="layer 'texture' is not in the bundle"):
            b.read_layer("texture")
        ome = b.root["floor"].attrs["ome"]["multiscales"][0]["datasets"]
        assert [d["path"] for d in ome] == ["1", "3"]
        assert ome[1]["coordinateTransformations"] == GRID.level(3).ome_transformations()
        assert "poses" not in b.root["floor"]
    m = read_manifest(out)
    assert set(m["levels"]) == {"1", "3"} and set(m["layers"]) == {"coverage"}
    assert all(n == "zarr.json" or n.split("/")[1] in ("1", "3", "layers", "zarr.json") for n in m["members"])


# --- tampering -----------------------------------------------------------------------------


def _small_bundle(site, tmp_path) -> Path:
    out = tmp_path / "small.zip"
    r = invoke("export", site["url"], out, "--region", "0.2,0.2,0.45,0.45", "--levels", "4",
               "--layers", "intensity,updated")
    assert r.exit_code == 0, r.output
    return out


def test_flipping_any_byte_fails_verify(site, tmp_path):
    small = _small_bundle(site, tmp_path)
    data = small.read_bytes()
    assert verify_bundle(small) == [] and len(data) < 12000
    for pos in range(len(data)):  # every byte of a small bundle, in memory (verify_bytes = verify_bundle)
        bad = bytearray(data)
        bad[pos] ^= 0x01 if pos % 2 else 0xFF
        problems = verify_bytes(bytes(bad))
        assert problems, f"flip at {pos} of {len(data)} passed"
        assert problems[0].startswith(PARTS), (pos, problems)
    # a larger bundle, through the file: positions spread evenly, with the first and last bytes
    big = site["full1"].stat().st_size
    bad_file = tmp_path / "bad.zip"
    for pos in sorted(set(np.linspace(0, big - 1, 200).astype(int).tolist()) | {0, big - 1}):
        _flip(site["full1"], bad_file, pos)
        assert verify_bundle(bad_file), f"flip at {pos} of {big} passed"


def test_verify_names_the_bad_part(site, tmp_path):
    small = _small_bundle(site, tmp_path)
    data = small.read_bytes()
    with zipfile.ZipFile(small) as z:
        infos = {i.filename: i for i in z.infolist()}
    tile = next(n for n in infos if "/c/" in n)
    bad = tmp_path / "bad.zip"
    zi = infos[tile]
    _flip(small, bad, zi.header_offset + 30 + len(tile) + 2)  # inside the tile's data
    r = invoke("verify", bad)
    assert r.exit_code == 2 and f"member {tile}: sha256 mismatch" in r.output, r.output
    _flip(small, bad, infos[MANIFEST].header_offset + 30 + len(MANIFEST) + 40)  # the manifest's text
    assert verify_bundle(bad)[0].startswith("manifest.json")
    _flip(small, bad, zi.header_offset + 10)  # the tile's local header mtime: only the seal sees it
    problems = verify_bundle(bad)
    assert problems[0].startswith("seal: sha256 mismatch while every member checks"), problems
    _flip(small, bad, len(data) - 5)  # the seal's hex
    assert verify_bundle(bad)[0].startswith("seal"), verify_bundle(bad)
    for cut in (len(data) - 1, len(data) - SEAL_LEN - 3, len(data) // 2, 10):
        bad.write_bytes(data[:cut])
        r = invoke("verify", bad)
        assert r.exit_code == 2 and "truncated" in r.output, (cut, r.output)
    bad.write_bytes(b"")
    assert invoke("verify", bad).exit_code == 2
    r = invoke("verify", tmp_path / "absent.zip")
    assert r.exit_code == 2 and "file not found" in r.output


# --- deltas --------------------------------------------------------------------------------


def test_delta_applied_to_the_old_bundle_gives_the_new_one(site, tmp_path):
    delta, patched = tmp_path / "delta.zip", tmp_path / "patched.zip"
    layers = "intensity,texture,uniqueness,coverage,updated"
    r = invoke("export", site["url"], delta, "--since", "v1", "--levels", "", "--layers", layers,
               "--report", tmp_path / "delta.json")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "delta.json").read_text())
    assert rep["kind"] == "delta" and rep["base"] == {"snapshot": site["v1"], "number": 1} and rep["removed"] == 0
    assert 0 < rep["changed_tiles"] < rep["selected_tiles"] / 4 and "changed tiles" in r.output
    dm = read_manifest(delta)
    # changed level-0 tiles lie on the patch (the layers' cells may reach a tile further)
    c0, r0 = GRID.world_to_pixel(PATCH.x0, PATCH.y1)
    c1, r1 = GRID.world_to_pixel(PATCH.x1, PATCH.y0)
    box = {(i, j) for i in range(int(r0) // 64, int(r1) // 64 + 1) for j in range(int(c0) // 64, int(c1) // 64 + 1)}
    tiles = {tuple(map(int, n.split("/")[-2:])) for n in dm["changed"] if n.startswith("floor/0/c/")}
    assert tiles and tiles <= box
    assert delta.stat().st_size < site["full2"].stat().st_size / 5
    r = invoke("apply-delta", site["full1"], delta, patched)
    assert r.exit_code == 0, r.output
    full = read_manifest(site["full2"])
    got = read_manifest(patched)
    assert got["members"] == full["members"] and got["content_sha256"] == full["content_sha256"]
    assert {k for k in full if full[k] != got[k]} <= {"created"}
    # byte for byte: a full export made with the delta's creation time
    api = tmp_path / "api.zip"
    again = tmp_path / "again.zip"
    root = _map(site, "v2")
    sel = make_selection(read_floor(root), levels=None, layers=layers.split(","))
    from mapstore.bundle import BundleWriter
    from pipeline.reloc_export import reloc_index_array

    derived = [reloc_index_array(None, 64)]  # the CLI's default: the relocalization index
    export_extract(Extract(root, sel, 3, derived), BundleWriter(api), snapshot=site["v2"], tags=["v2"],
                   created=dm["result"]["created"])
    apply_delta(site["full1"], delta, again)
    assert api.read_bytes() == again.read_bytes() == patched.read_bytes()
    with open_bundle(patched) as b:
        np.testing.assert_array_equal(b.read(0), root["floor/0"][...])


def test_corridor_delta(site, tmp_path):
    csv = tmp_path / "path.csv"
    csv.write_text("x,y\n0.2,0.7\n1.1,0.7\n")
    old, delta, new, patched = (tmp_path / n for n in ("old.zip", "delta.zip", "new.zip", "patched.zip"))
    common = ("--corridor", csv, "--width", "0.3")
    assert invoke("export", site["url"], old, "--version", "v1", *common).exit_code == 0
    assert invoke("export", site["url"], new, *common).exit_code == 0
    r = invoke("export", site["url"], delta, "--since", "v1", *common)
    assert r.exit_code == 0, r.output
    assert invoke("apply-delta", old, delta, patched).exit_code == 0
    assert read_manifest(patched)["members"] == read_manifest(new)["members"]
    # the delta does not fit the whole-map bundle (another selection)
    r = invoke("apply-delta", site["full1"], delta, tmp_path / "x.zip")
    assert r.exit_code == 2 and "selection mismatch" in r.output, r.output
    assert not (tmp_path / "x.zip").exists()


def test_delta_refused_on_a_wrong_base(site, tmp_path):
    layers = "intensity,texture,uniqueness,coverage,updated"
    delta = tmp_path / "delta.zip"
    assert invoke("export", site["url"], delta, "--since", "v1", "--levels", "", "--layers", layers).exit_code == 0
    r = invoke("apply-delta", site["full2"], delta, tmp_path / "x.zip")
    assert r.exit_code == 2 and "base version mismatch" in r.output, r.output
    bad = tmp_path / "bad1.zip"
    _flip(site["full1"], bad, site["full1"].stat().st_size // 2)
    r = invoke("apply-delta", bad, delta, tmp_path / "x.zip")
    assert r.exit_code == 2 and str(bad) in r.output, r.output
    r = invoke("apply-delta", site["full1"], site["full2"], tmp_path / "x.zip")
    assert r.exit_code == 2 and "not a delta" in r.output
    assert not (tmp_path / "x.zip").exists()
    r = invoke("export", site["url"], tmp_path / "y.zip", "--version", "v1", "--since", "v2")
    assert r.exit_code == 2 and "--since" in r.output and "not an ancestor" in r.output, r.output


# --- OME-Zarr -------------------------------------------------------------------------------


def test_ome_zarr_export_reads_in_ome_zarr(site, tmp_path):
    ome_zarr = pytest.importorskip("ome_zarr", reason="ome-zarr (test extra) not installed")
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    out = tmp_path / "ome"
    r = invoke("export", site["url"], out, "--format", "ome-zarr", "--levels", "0,1,2", "--region", "0.1,0.1,1.0,1.2",
               "--layers", "intensity,texture,coverage,updated")
    assert r.exit_code == 0, r.output
    # the manifest beside the zarr tree, nothing foreign inside it: every file is zarr's
    assert not (out.with_suffix(".zip")).exists() and (out / "manifest.json").is_file()
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "map.zarr"]
    files = [p for p in (out / "map.zarr").rglob("*") if p.is_file()]
    assert files and all(p.name == "zarr.json" or "/c/" in p.as_posix() for p in files)
    with warnings.catch_warnings():  # zarr warns of objects foreign to the hierarchy
        warnings.simplefilter("error")
        tree = zarr.open_group(str(out / "map.zarr"), mode="r")
        names = [name for name, _ in tree.members(max_depth=None)]
    assert "floor" in names and "layers/texture/0" in names and "floor/layers" not in names
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(manifest["members"]) == sorted(p.relative_to(out / "map.zarr").as_posix() for p in files)
    # the export names what to open
    images = manifest["ome_zarr"]["images"]
    assert images == {"intensity": "map.zarr/floor", "coverage": "map.zarr/layers/coverage",
                      "texture": "map.zarr/layers/texture", "updated": "map.zarr/layers/updated"}
    assert "open in an OME-Zarr viewer" in r.output and f"intensity: {out / 'map.zarr' / 'floor'}" in r.output
    nodes = list(Reader(parse_url(str(out / "map.zarr" / "floor")))())
    assert nodes, ome_zarr.__version__
    node = nodes[0]
    assert [tuple(d.shape) for d in node.data] == [GRID.level(k).shape for k in range(3)]
    tr = node.metadata["coordinateTransformations"]
    assert [t[0]["scale"] for t in tr] == [[PX * 2**k] * 2 for k in range(3)]
    src = _map(site, "latest")
    x, y = _centres(GRID)
    h = PX / 2
    keep = (x + h > 0.1) & (x - h < 1.0) & (y + h > 0.1) & (y - h < 1.2)
    np.testing.assert_array_equal(np.asarray(node.data[0])[keep], src["floor/0"][...][keep])
    # every layer is an image the reader lists, on the layer's own grid, holding the map's cells
    info = read_floor(src)
    for name in ("texture", "coverage", "updated"):
        lnodes = list(Reader(parse_url(str(out / images[name])))())
        assert lnodes, name
        ln = lnodes[0]
        lgrid = info.layer_grid(name)
        assert [tuple(d.shape) for d in ln.data] == [lgrid.shape]
        assert ln.metadata["coordinateTransformations"][0] == lgrid.ome_transformations()
        assert ln.metadata["name"] == name
        got, want = np.asarray(ln.data[0]), src[f"floor/layers/{name}"][...]
        held = np.isfinite(got) & (got != 0) if got.dtype.kind == "f" else got != 0
        assert held.any() and np.array_equal(got[held], want[held]), name


def test_ome_zarr_export_validates_against_the_spec(site, tmp_path):
    """Each image group of the export is a valid OME-Zarr 0.5 image (ome-zarr-models)."""
    models = pytest.importorskip("ome_zarr_models.v05", reason="ome-zarr-models (test extra) not installed")

    out = tmp_path / "ome"
    r = invoke("export", site["url"], out, "--format", "ome-zarr", "--levels", "0,2", "--layers",
               "intensity,uniqueness,updated")
    assert r.exit_code == 0, r.output
    images = json.loads((out / "manifest.json").read_text())["ome_zarr"]["images"]
    assert list(images) == ["intensity", "uniqueness", "updated"]
    for name, rel in images.items():
        img = models.Image.from_zarr(zarr.open_group(str(out / rel), mode="r"))
        ms = img.ome_attributes.multiscales[0]
        assert ms.name == name and [a.name for a in ms.axes] == ["y", "x"]
        assert all(a.unit == "meter" for a in ms.axes)
        assert [d.path for d in ms.datasets] == (["0", "2"] if name == "intensity" else ["0"])


# --- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize("args, csv, where, what", [
    (["--region", "5,5,6,6"], None, "--region", "outside the map"),
    (["--region", "1,2,3"], None, "--region", "4 numbers"),
    (["--region", "a,b,c,d"], None, "--region", "x0,y0,x1,y1"),
    (["--corridor", "{csv}"], "x,z\n0,0\n1,1\n", "{csv}:1", "columns x and y"),
    (["--corridor", "{csv}"], "x,y\n0,0\nnan,1\n", "{csv}:3", "must be finite"),
    (["--corridor", "{csv}"], "x,y\n0,0\n", "{csv}", "at least 2"),
    (["--corridor", "{csv}"], "x,y\n0,0\n1\n", "{csv}:3", "expected 2 fields"),
    (["--corridor", "{csv}"], "x,y\n10,10\n11,11\n", "{csv}", "outside the map"),
    (["--corridor", "{csv}", "--width", "0"], "x,y\n0,0\n1,1\n", "--width", "positive"),
    (["--width", "1"], None, "--width", "--corridor only"),
    (["--region", "0,0,1,1", "--corridor", "{csv}"], "x,y\n0,0\n1,1\n", "--region", "not both"),
    (["--levels", "0,9"], None, "--levels", "level 9 does not exist"),
    (["--levels", "x"], None, "--levels", "level numbers"),
    (["--layers", "intensity,colour"], None, "--layers", "unknown layer 'colour'"),
    (["--layers", "texture", "--levels", "1"], None, "--levels", "intensity"),
    (["--format", "ome-zarr", "--since", "v1"], None, "--since", "not with --format ome-zarr"),
    (["--region", "1.25,0.1,1.35,0.5"], None, "--region", "holds no map data"),
    (["--since", "nope"], None, "--since", "unknown version"),
    (["--version", "nope"], None, "{url}", "unknown version"),
])
def test_bad_input_exits_2(site, tmp_path, args, csv, where, what):
    path = tmp_path / "path.csv"
    if csv is not None:
        path.write_text(csv)
    fill = {"{csv}": str(path), "{url}": site["url"]}
    args = [fill.get(a, a) for a in args]
    for k, v in fill.items():
        where = where.replace(k, v)
    out = tmp_path / "out.zip"
    r = invoke("export", site["url"], out, *args)
    assert r.exit_code == 2, r.output
    line = r.output.strip().splitlines()[-1]
    assert line.startswith(f"mosaicmap: error: {where}: ") and what in line, line
    assert not out.exists()


def test_bundle_store_reads_what_zipstore_reads(site):
    """The vehicle's reader (BundleStore: no full directory parse) and zarr's ZipStore
    agree; a bundle is a plain zip."""
    zs = zarr.open_group(zarr.storage.ZipStore(site["full2"], mode="r"), mode="r")
    with open_bundle(site["full2"]) as b:
        assert sorted(b.root["floor"].array_keys()) == sorted(zs["floor"].array_keys())
        for path in ("floor/0", "floor/2", "floor/layers/uniqueness", "floor/layers/updated"):
            np.testing.assert_array_equal(b.root[path][...], zs[path][...])
        np.testing.assert_array_equal(b.read(0, slice(70, 200), slice(30, 300)), zs["floor/0"][70:200, 30:300])
        assert b.manifest["content_sha256"] == read_manifest(site["full2"])["content_sha256"]


def test_zip64_bundle_with_many_members(tmp_path):
    """More than 65535 members: the zip64 end records; the index, the seal and verify hold."""
    from mapstore.bundle import BundleWriter, ZipIndex

    out = tmp_path / "many.zip"
    w = BundleWriter(out)
    for i in range(66000):
        w.add(f"a/c/0/{i}", b"%d" % i)
    w.finish({"format": "mosaicmap-bundle", "format_version": 1, "kind": "full"})
    index = ZipIndex(out)
    assert index.read("a/c/0/65999") == b"65999" and index.read("a/c/0/7") == b"7"
    assert index.find("a/c/0/66000") is None and len(index.entries()) == 66001
    index.close()
    problems = verify_bundle(out)  # the manifest lacks the header keys; nothing else is wrong
    assert problems[0].startswith("manifest.json: lacks key(s)") and not any("seal" in p for p in problems)


def test_bundle_reader_stays_light(tmp_path):
    from conftest import modules_pulled_in

    assert modules_pulled_in(["mapstore.bundle"], ("icechunk", "click", "pipeline", "dask")) == []