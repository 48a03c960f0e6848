"""The relocalization index built at export time and stored in the bundle
(``floor/reloc/features``; tracker.reloc.tile_features via mapstore.export.TileDerived,
pipeline.cli.export) and loaded on the vehicle (tracker.bundle_map.TrackerMap.feature_index)."""

from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr

from mapstore.bundle import BundleWriter, read_manifest, verify_bundle
from mapstore.export import Extract, export_extract, make_selection
from mapstore.grid import MapGrid
from mapstore.layout import read_floor
from mapstore.repository import MapRepository
from pipeline.reloc_export import reloc_index_array
from pipeline.config import load_config
from pipeline.testing.synthmap import Patch, periodic_texture, publish_repainted, texture_tile_fn
from tracker.bundle_map import RelocIndexMissing, _read_tile_records, open_bundle
from tracker.reloc import INDEX_PATH, RelocParams, build_index
from conftest import invoke

REPO_DIR = Path(__file__).resolve().parents[1]
PX = 0.0025
N = 1024
GRID = MapGrid(0.0, (N - 1) * PX, PX, N, N)  # 2.56 x 2.56 m, 4 x 4 tiles of 256 px
# version 2 repaints this box: it crosses the tile boundary at x = 1.28 m (column 512) and ends
# 7 px above row 512 (y = 1.2775 m): the features of the tiles below may change too
PATCH = Patch(1.18, 1.295, 1.36, 1.45, delta=50.0)
FRAME = (240, 320)
LAYERS = "intensity,texture,uniqueness"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("reloc")
    cfg = copy.deepcopy(load_config(None))
    url = str(root / "map")
    tex = periodic_texture(11, 1024)
    v1, v2 = publish_repainted(url, GRID, tex, PATCH, cfg=cfg)
    out = {"root": root, "url": url, "v1": v1, "v2": v2, "tex": tex}
    for v in ("v1", "v2"):
        path = root / f"full_{v}.zip"
        r = invoke("export", url, path, "--version", v, "--layers", LAYERS, "--report", path.with_suffix(".json"))
        assert r.exit_code == 0, r.output
        out[v + "_zip"] = path
    return out


def _pixels(site, patches=()):
    return np.clip(np.rint(texture_tile_fn(site["tex"], GRID, patches)(0, N, 0, N)), 1, 255).astype(np.uint8)


def _frame_at(m, pose, rng, noise=6.0, gain=0.85):
    a = GRID.frame_to_grid_affine(pose, FRAME, PX)
    f = cv2.warpAffine(m, a, FRAME[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP).astype(np.float32)
    return np.clip(gain * f + rng.normal(0, noise, f.shape), 0, 255).astype(np.uint8)


def _index_members(manifest: dict) -> dict[str, str]:
    return {n: v["sha256"] for n, v in manifest["members"].items() if n.startswith(INDEX_PATH + "/c/")}


def _tile(name: str) -> tuple[int, int]:
    i, j = name[len(INDEX_PATH) + 3:].split("/")[:2]
    return int(i), int(j)


def _assert_same_index(a, b):
    assert len(a) == len(b) > 0
    np.testing.assert_array_equal(a.xy, b.xy)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    np.testing.assert_array_equal(a.angle, b.angle)


def test_stored_index_equals_built_index(site, tmp_path):
    rep = json.loads(site["v1_zip"].with_suffix(".json").read_text())["reloc_index"]
    m = read_manifest(site["v1_zip"])
    assert m["derived"][INDEX_PATH]["kind"] == "reloc_index" and m["derived"][INDEX_PATH]["tile_px"] == 256
    assert rep["tiles"] == len(_index_members(m)) == 16 and rep["features"] == 16 * 48
    assert rep["bytes"] == sum(m["members"][n]["bytes"] for n in _index_members(m))
    assert verify_bundle(site["v1_zip"]) == []
    with open_bundle(site["v1_zip"], insecure=True) as tm, warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning
        stored = tm.feature_index()
        assert tm.index_source == "stored" and tm.feature_index() is stored
        built = build_index(tm.tiles, tm.grid, RelocParams(tile_px=tm.bundle.tile_px))
        _assert_same_index(stored, built)
        # the fast read (zstd frames straight from the zip) = zarr's read of the array
        rc, rec = _read_tile_records(tm.bundle, tm.bundle.root[INDEX_PATH])
        full = tm.bundle.root[INDEX_PATH][...]
        assert rc.shape == (16, 2) and np.array_equal(rec, full[rc[:, 0], rc[:, 1]])
        x0, y0, x1, y1 = GRID.bounds
        assert (stored.xy[:, 0] > x0).all() and (stored.xy[:, 0] < x1).all()
    # a region: features of the exported (masked) pixels only, still equal to the built ones
    reg = tmp_path / "region.zip"
    box = (0.3, 0.4, 1.9, 2.1)
    assert invoke("export", site["url"], reg, "--region", ",".join(map(str, box)), "--levels", "0").exit_code == 0
    with open_bundle(reg, insecure=True) as tm:
        stored = tm.stored_index()
        _assert_same_index(stored, build_index(tm.tiles, tm.grid, RelocParams(tile_px=256)))
        # every feature is 16 px inside the region's kept pixels (its 33 x 33 neighbourhood covered)
        h = 16 * PX - 1e-9
        assert (stored.xy[:, 0] >= box[0] + h).all() and (stored.xy[:, 0] <= box[2] - h).all()
        assert (stored.xy[:, 1] >= box[1] + h).all() and (stored.xy[:, 1] <= box[3] - h).all()


def test_kidnapped_frame_relocalizes_from_the_stored_index(site):
    m = _pixels(site)
    rng = np.random.default_rng(21)
    with open_bundle(site["v1_zip"], insecure=True) as tm:
        rl = tm.relocalizer(PX)
        assert tm.index_source == "stored"
        ok = 0
        for _ in range(6):
            gt = np.array([rng.uniform(0.5, 2.06), rng.uniform(0.5, 2.06), rng.uniform(-np.pi, np.pi)])
            f = rl.locate(_frame_at(m, gt, rng))
            if f.ok:
                ok += 1
                assert np.hypot(*(f.pose[:2] - gt[:2])) / PX < 0.5 and abs(f.pose[2] - gt[2]) < 2e-3
        assert ok >= 5
        other = np.clip(np.rint(periodic_texture(99, 512)), 1, 255).astype(np.uint8)[:240, :320]
        f = rl.locate(other)  # another floor: never a fix
        assert f.status == "lost" and np.isnan(f.pose).all()


def test_delta_carries_the_changed_index_chunks(site, tmp_path):
    delta, patched = tmp_path / "delta.zip", tmp_path / "patched.zip"
    r = invoke("export", site["url"], delta, "--since", "v1", "--layers", LAYERS, "--report",
               tmp_path / "delta.json")
    assert r.exit_code == 0, r.output
    dm = read_manifest(delta)
    m1, m2 = read_manifest(site["v1_zip"]), read_manifest(site["v2_zip"])
    i1, i2 = _index_members(m1), _index_members(m2)
    differ = {n for n in set(i1) | set(i2) if i1.get(n) != i2.get(n)}
    carried = {n for n in dm["changed"] if n.startswith(INDEX_PATH + "/c/")}
    assert differ and carried == {n for n in differ if n in i2} and set(dm["removed"]) == differ - set(i2)
    # the changed index chunks are those of the repainted tiles (the patch crosses columns 512)
    c0, r0 = GRID.world_to_pixel(PATCH.x0, PATCH.y1)
    c1, r1 = GRID.world_to_pixel(PATCH.x1, PATCH.y0)
    patch_tiles = {(i, j) for i in range(int(r0) // 256, int(r1) // 256 + 1)
                   for j in range(int(c0) // 256, int(c1) // 256 + 1)}
    assert len(patch_tiles) >= 2 and {_tile(n) for n in carried} <= {
        (i + a, j + b) for i, j in patch_tiles for a in (-1, 0, 1) for b in (-1, 0, 1)}
    assert {_tile(n) for n in carried} >= patch_tiles
    # a tile whose pixels did not change but whose features read the patch (margin 32 px)
    assert {_tile(n) for n in carried} - patch_tiles
    assert not {n for n in dm["changed"] if n.startswith("floor/0/c/")} - {f"floor/0/c/{i}/{j}" for i, j in patch_tiles}
    rep = json.loads((tmp_path / "delta.json").read_text())["reloc_index"]
    assert rep["tiles"] == len(carried) and rep["features"] == 48 * len(carried)
    # apply-delta = the full export of version 2, byte for byte (same creation time)
    assert invoke("apply-delta", site["v1_zip"], delta, patched).exit_code == 0
    assert read_manifest(patched)["members"] == m2["members"]
    root = zarr.open_group(MapRepository.open(site["url"]).readonly("v2").store, mode="r")
    sel = make_selection(read_floor(root), levels=None, layers=LAYERS.split(","))
    api = tmp_path / "api.zip"
    export_extract(Extract(root, sel, 3, [reloc_index_array(None, 256)]), BundleWriter(api), snapshot=site["v2"],
                   tags=["v2"], created=dm["result"]["created"])
    assert api.read_bytes() == patched.read_bytes()
    with open_bundle(patched, insecure=True) as tm:
        _assert_same_index(tm.stored_index(), build_index(tm.tiles, tm.grid, RelocParams(tile_px=256)))


def test_export_without_index_and_vehicle_fallback(site, tmp_path):
    out = tmp_path / "noidx.zip"
    r = invoke("export", site["url"], out, "--version", "v1", "--layers", LAYERS, "--no-reloc-index",
               "--report", tmp_path / "r.json")
    assert r.exit_code == 0, r.output
    m = read_manifest(out)
    assert not any(n.startswith("floor/reloc") for n in m["members"]) and "derived" not in m
    assert json.loads((tmp_path / "r.json").read_text())["reloc_index"] is None
    assert out.stat().st_size < site["v1_zip"].stat().st_size
    with open_bundle(out, insecure=True) as tm, open_bundle(site["v1_zip"], insecure=True) as stored:
        assert tm.stored_index() is None
        with pytest.warns(RelocIndexMissing, match="no relocalization index"):
            built = tm.feature_index()
        assert tm.index_source == "built"
        _assert_same_index(built, stored.feature_index())
    # [export] reloc_index = false in a configuration file; a delta without the index
    conf = tmp_path / "c.toml"
    conf.write_text("[export]\nreloc_index = false\n")
    base = tmp_path / "base.zip"
    assert invoke("export", site["url"], base, "--version", "v1", "--config", conf).exit_code == 0
    delta = tmp_path / "d.zip"
    assert invoke("export", site["url"], delta, "--since", "v1", "--config", conf).exit_code == 0
    assert not any(n.startswith("floor/reloc") for n in read_manifest(delta)["members"])
    # a delta with the index does not fit a base bundle without it
    delta2 = tmp_path / "d2.zip"
    assert invoke("export", site["url"], delta2, "--since", "v1").exit_code == 0
    r = invoke("apply-delta", base, delta2, tmp_path / "x.zip")
    assert r.exit_code == 2 and "floor/reloc" in r.output, r.output
    # no level 0: no index by default; asked for explicitly: bad input
    lv = tmp_path / "lv.zip"
    assert invoke("export", site["url"], lv, "--levels", "1,2").exit_code == 0
    assert "derived" not in read_manifest(lv)
    r = invoke("export", site["url"], tmp_path / "y.zip", "--levels", "1", "--reloc-index")
    assert r.exit_code == 2 and "--reloc-index" in r.output and "level 0" in r.output, r.output
    assert not (tmp_path / "y.zip").exists()


def test_mapstore_imports_neither_tracker_nor_pipeline():
    from conftest import modules_pulled_in

    assert modules_pulled_in(["mapstore.export", "mapstore.bundle"], ("tracker", "pipeline", "click")) == []