"""``mosaicmap diff``: the pixel-level numerics (mapstore/change_detect.py) on synthetic
arrays, the version diff (mapstore/diff.py) on small synthetic maps (pipeline.testing.synthmap),
and the command with its outputs and ground truth on a small simulated two-day map."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr

from mapstore.change_detect import DetectParams, detect_changes, noise_sigma
from mapstore.diff import DiffParams, diff_maps, region_polygon
from mapstore.grid import MapGrid
from mapstore.layout import read_floor, resize_floor, set_version
from mapstore.repository import MapRepository
from pipeline.config import load_config
from pipeline.images import write_image
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn
from conftest import invoke, SMALL_MAP_TOML as SMALL


# --- numerics on synthetic arrays -----------------------------------------------------------


def _shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT)


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 1, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return periodic_texture(7, 768)


def _gain(shape, lo: float, hi: float) -> np.ndarray:
    """A smooth illumination field between lo and hi (x 1) across the window."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    t = 0.5 + 0.25 * np.sin(cols / 300.0) + 0.25 * np.cos(rows / 420.0)
    return lo + (hi - lo) * t


def test_stain_under_illumination_and_shift_is_one_region_of_the_right_area(texture):
    shape = texture.shape
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    r = np.hypot((rows - 400) / 70.0, (cols - 350) / 50.0)
    w = np.clip((1.0 - r) * 50.0 / 2.0 + 0.5, 0.0, 1.0)  # soft ellipse, edge ~2 px
    a = _u8(texture)
    b = _u8(_gain(shape, 0.7, 0.9) * (_shift(texture, 0.35, -0.25) + 35.0 * w))
    det = detect_changes(a, b, DetectParams())
    n, lab = cv2.connectedComponents(det.mask.astype(np.uint8))
    truth = w >= 0.5
    assert n == 2, "one region"
    iou = (det.mask & truth).sum() / (det.mask | truth).sum()
    assert iou > 0.9 and abs(det.mask.sum() / truth.sum() - 1.0) < 0.1
    assert det.threshold >= DetectParams().min_contrast
    # the gain field found the illumination (TO / FROM), away from the stain
    g = np.exp(det.log_gain)
    far = r > 2.0
    assert np.median(np.abs(g[far] / _gain(shape, 0.7, 0.9)[far] - 1.0)) < 0.02


def test_pure_illumination_change_is_no_change(texture):
    a = _u8(texture)
    b = _u8(_gain(texture.shape, 0.65, 0.95) * texture)
    det = detect_changes(a, b, DetectParams())
    assert not det.mask.any()


def test_subpixel_shift_of_a_texture_is_no_change(texture):
    a = _u8(texture)
    for dx, dy in ((0.45, 0.0), (-0.3, 0.4)):
        det = detect_changes(a, _u8(_shift(texture, dx, dy)), DetectParams())
        assert not det.mask.any(), (dx, dy)


def test_soft_exposure_bump_is_ignored_and_listed(texture):
    """A gain error fading in over tens of pixels (frames blend over the feather width) is
    not a change, even when strong enough to pass the threshold."""
    shape = texture.shape
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    bump = cv2.GaussianBlur((np.hypot(rows - 384, cols - 384) < 150).astype(np.float32), (0, 0), 25.0)
    a = _u8(texture)
    b = _u8(texture * (1.0 - 0.15 * bump))
    det = detect_changes(a, b, DetectParams())
    assert not det.mask.any()
    assert det.candidates and not any(c["kept"] for c in det.candidates)


def test_noise_estimate_ignores_a_change_covering_most_of_the_window(texture):
    rng = np.random.default_rng(1)
    a = texture
    b = texture + rng.normal(0.0, 1.0, texture.shape).astype(np.float32)
    b[:, : 3 * texture.shape[1] // 5] += 40.0 * rng.standard_normal((texture.shape[0], 1)).astype(np.float32)
    where = np.ones(texture.shape, bool)
    s = noise_sigma(a, b, np.zeros_like(a), where, 64, 0.25, 0.25)
    assert 0.8 < s < 1.3


def test_region_polygon_in_metres_follows_the_grid():
    grid = MapGrid(1.0, 2.0, 0.01, 100, 100)
    mask = np.zeros((40, 60), bool)
    mask[10:30, 20:50] = True
    mask[15:20, 30:35] = False  # a hole
    rings = region_polygon(mask, 5, 7, grid, 0.5)
    assert len(rings) == 2
    ext = np.array(rings[0])
    assert np.allclose(ext[0], ext[-1])
    # through the centres of the boundary pixels: level-0 rows 15..34, cols 27..56
    x0, y0 = grid.pixel_to_world(27, 34)
    x1, y1 = grid.pixel_to_world(56, 15)
    assert np.isclose(ext[:, 0].min(), x0) and np.isclose(ext[:, 0].max(), x1)
    assert np.isclose(ext[:, 1].min(), y0) and np.isclose(ext[:, 1].max(), y1)
    area = 0.5 * np.sum(ext[:-1, 0] * ext[1:, 1] - ext[1:, 0] * ext[:-1, 1])
    assert area > 0 and np.isclose(area, (x1 - x0) * (y1 - y0))  # counter-clockwise (RFC 7946)
    hole = np.array(rings[1])
    assert 0.5 * np.sum(hole[:-1, 0] * hole[1:, 1] - hole[1:, 0] * hole[:-1, 1]) < 0


# --- version diffs of synthetic maps ----------------------------------------------------------


@pytest.fixture(scope="module")
def synth_cfg():
    c = copy.deepcopy(load_config(None))
    c["map"].update(chunk_px=64, shard_px=256)
    return c


def _half_tile_fn(tile_fn, grid: MapGrid, cols: int):
    """``tile_fn`` with no data (0) from column ``cols`` on."""
    def tile(r0, r1, c0, c1):
        out = tile_fn(r0, r1, c0, c1)
        out[:, max(cols - c0, 0) :] = 0
        return out
    return tile


def test_diff_of_synthetic_versions_finds_the_stain_and_new_coverage(tmp_path, synth_cfg):
    url = str(tmp_path / "map")
    grid = MapGrid(0.0, 2.0, 0.0025, 800, 800)
    tex = periodic_texture(2, 512)
    publish_raster(url, grid, _half_tile_fn(texture_tile_fn(tex, grid), grid, 512), cfg=synth_cfg, tag="one")
    stain = Patch(0.4, 1.2, 0.6, 1.4, shift_px=(0, 0), delta=-40.0)
    shards = shards_for_box(grid, 256, stain.x0, stain.y0, stain.x1, stain.y1) | {(i, j) for i in range(4) for j in (2, 3)}
    publish_raster(url, grid, texture_tile_fn(tex, grid, [stain]), cfg=synth_cfg, tag="two", shards=shards)
    repo = MapRepository.open(url)
    res = diff_maps(repo, repo.resolve("one"), repo.resolve("two"), DiffParams())
    assert len(res.regions) == 1
    reg = res.regions[0]
    r0, r1, c0, c1 = stain.pixel_box(grid)
    assert abs(reg.area_px / ((r1 - r0) * (c1 - c0)) - 1.0) < 0.05
    assert np.allclose(reg.bbox_m, (stain.x0 - 0.00125, stain.y0 - 0.00125, stain.x1 + 0.00125, stain.y1 + 0.00125),
                       atol=0.003)
    assert reg.contrast < -30 and reg.impact.texture_before is not None
    # the right part was not covered by version one: new coverage, not change
    assert res.tiles.tiles_new_coverage > 0 and res.tiles.new_coverage_px == 800 * (800 - 512)
    assert not res.tiles.grown and res.tiles.tiles_changed == len(res.changed_tiles) > 0
    # the same version: nothing
    same = diff_maps(repo, repo.resolve("two"), repo.resolve("two"), DiffParams())
    assert not same.regions and same.tiles.tiles_rewritten == 0


def test_diff_across_map_growth_is_new_coverage(tmp_path, synth_cfg):
    url = str(tmp_path / "map")
    grid = MapGrid(0.0, 2.0, 0.0025, 600, 500)
    tex = periodic_texture(3, 512)
    fn = texture_tile_fn(tex, grid)
    publish_raster(url, grid, fn, cfg=synth_cfg, tag="one")
    repo = MapRepository.open(url)
    # grow to the bottom by 200 rows, as an incremental build over a larger area does
    big = MapGrid(0.0, 2.0, 0.0025, 600, 700)
    session = repo.writable()
    root = zarr.open_group(session.store, mode="a")
    resize_floor(root, big)
    root["floor/0"][500:700, :] = texture_tile_fn(tex, big)(500, 700, 0, 600)
    upd = root["floor/layers/updated"]
    upd[500 // 64 :, :] = 2
    set_version(root, 2)
    repo.repo.create_tag("two", repo.commit(session, "grown"))
    res = diff_maps(repo, repo.resolve("one"), repo.resolve("two"), DiffParams())
    assert res.tiles.grown and not res.regions
    assert res.tiles.new_coverage_px == 200 * 600 and res.tiles.tiles_new_coverage > 0
    assert read_floor(zarr.open_group(repo.readonly("two").store, mode="r")).grid == big


def _write_truth(path: Path, grid: MapGrid, boxes: list[tuple[int, int, int, int]]) -> Path:
    mask = np.zeros(grid.shape, np.uint8)
    for r0, r1, c0, c1 in boxes:
        mask[r0:r1, c0:c1] = 255
    path.mkdir(parents=True, exist_ok=True)
    write_image(path / "changes.png", mask)
    (path / "grid.json").write_text(json.dumps(grid.to_attrs()))
    return path / "changes.png"


def test_truth_on_a_synthetic_map_detected_and_unobserved(tmp_path, synth_cfg):
    url = str(tmp_path / "map")
    grid = MapGrid(0.0, 2.0, 0.0025, 800, 800)
    tex = periodic_texture(4, 512)
    publish_raster(url, grid, texture_tile_fn(tex, grid), cfg=synth_cfg, tag="one")
    patch = Patch(0.5, 0.5, 0.75, 0.7)  # repainted: other texture, same brightness
    shards = shards_for_box(grid, 256, patch.x0, patch.y0, patch.x1, patch.y1)
    publish_raster(url, grid, texture_tile_fn(tex, grid, [patch]), cfg=synth_cfg, tag="two", shards=shards)
    # the truth holds the patch and a change the second version never looked at
    mask = _write_truth(tmp_path / "truth", grid, [patch.pixel_box(grid), (40, 90, 40, 100)])
    rep_path = tmp_path / "r.json"
    r = invoke("diff", url, "one", "two", "--truth", mask, "--report", rep_path, "--config", _small_cfg(tmp_path))
    assert r.exit_code == 0, r.output
    rep = json.loads(rep_path.read_text())
    t = rep["truth"]
    assert t["alignment"]["source"] == "identity" and "no pose table" in t["alignment"]["note"]
    status = {c["status"] for c in t["changes"]}
    assert status == {"detected", "unobserved"} and t["summary"]["false_regions"] == 0
    det = next(c for c in t["changes"] if c["status"] == "detected")
    assert det["iou"] > 0.8 and det["observed_fraction"] > 0.9
    # a truth without any change: every region is a false one
    empty = _write_truth(tmp_path / "empty", grid, [])
    r = invoke("diff", url, "one", "two", "--truth", empty, "--report", rep_path, "--config", _small_cfg(tmp_path))
    assert r.exit_code == 0, r.output
    t = json.loads(rep_path.read_text())["truth"]
    assert not t["changes"] and t["summary"]["false_regions"] == len(json.loads(rep_path.read_text())["regions"]) == 1


def _small_cfg(tmp: Path) -> Path:
    p = tmp / "small.toml"
    p.write_text(SMALL)
    return p


# --- the command on a simulated two-day map ---------------------------------------------------


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("diffsite")
    cfg = _small_cfg(root)
    day1, day2 = root / "day1", root / "day2"
    for args in (("simulate", "floor", day1, "--area", "1.5x1.5", "--seed", "5", "--quiet"),
                 ("simulate", "floor", day2, "--world", day1, "--changes", "2", "--seed", "6",
                  "--illumination", "0.8", "--quiet"),
                 ("build", day1, "--map", root / "map", "-w", root / "w1", "--config", cfg, "--tag", "day1", "--quiet"),
                 ("build", day2, "--map", root / "map", "-w", root / "w2", "--config", cfg, "--tag", "day2", "--quiet")):
        r = invoke(*args)
        assert r.exit_code == 0, r.output
    return {"root": root, "cfg": cfg, "repo": root / "map", "truth": day2 / "world" / "changes.png"}


def test_cli_diff_with_truth_writes_every_output(site, tmp_path):
    out = tmp_path / "out"
    r = invoke("diff", site["repo"], "day1", "day2", "--out", out, "--report", tmp_path / "rep.json",
               "--truth", site["truth"], "--config", site["cfg"])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "rep.json").read_text())
    assert rep == json.loads((out / "diff.json").read_text())
    assert rep["from"]["publish_version"] == 1 and rep["to"]["publish_version"] == 2
    assert rep["tiles"]["changed"] > 0 and rep["summary"]["regions"] == len(rep["regions"]) >= 2
    # against the simulator's truth: every observed change found, nothing false
    t = rep["truth"]
    assert t["alignment"]["source"] == "ground_truth" and t["alignment"]["rms_m"] < 0.001
    observed = [c for c in t["changes"] if c["status"] != "unobserved"]
    assert observed and all(c["status"] == "detected" and c["iou"] >= 0.7 for c in observed), t["changes"]
    assert t["summary"]["max_false_area_cm2"] <= 25.0
    # the table printed
    assert "regions:" in r.output and "truth:" in r.output and "detected" in r.output
    # a simulated map has no geographic reference: regions.json in local metres, no GeoJSON
    # (which GIS tools would read as WGS 84 degrees); one polygon per region inside the grid
    assert not (out / "regions.geojson").exists() and rep["outputs"]["regions"] == str(out / "regions.json")
    doc = json.loads((out / "regions.json").read_text())
    assert "type" not in doc and doc["crs"] == "local metres" and "floor frame" in doc["frame"]
    assert len(doc["regions"]) == len(rep["regions"])
    grid = MapGrid.from_attrs(rep["grid"])
    xmin, ymin, xmax, ymax = grid.bounds
    for reg in doc["regions"]:
        ring = np.array(reg["polygon_m"][0])
        assert np.allclose(ring[0], ring[-1]) and len(ring) >= 4 and reg["area_m2"] > 0
        assert (ring[:, 0] >= xmin).all() and (ring[:, 0] <= xmax).all()
        assert (ring[:, 1] >= ymin).all() and (ring[:, 1] <= ymax).all()
    # the overlay and the self-contained page
    assert cv2.imread(str(out / "overlay.png")).shape[2] == 3
    page = (out / "diff.html").read_text()
    assert page.count('src="data:image/png;base64,') >= 3 + 3 * len(rep["regions"])
    assert "http://" not in page and "https://" not in page and "<table>" in page


def test_fail_on_change_exits_1_after_writing(site, tmp_path):
    r = invoke("diff", site["repo"], "day1", "day2", "--fail-on-change", "--report", tmp_path / "r.json",
               "--config", site["cfg"], "--quiet")
    assert r.exit_code == 1 and "--fail-on-change" in r.output
    assert json.loads((tmp_path / "r.json").read_text())["summary"]["regions"] > 0
    r = invoke("diff", site["repo"], "day2", "day2", "--fail-on-change", "--config", site["cfg"], "--quiet")
    assert r.exit_code == 0 and "regions: 0" in r.output


def test_bad_input_exits_2_naming_it(site, tmp_path):
    r = invoke("diff", site["repo"], "day1", "nosuchversion", "--config", site["cfg"])
    assert r.exit_code == 2 and "nosuchversion" in r.output
    r = invoke("diff", site["repo"], "day2", "day1", "--config", site["cfg"])
    assert r.exit_code == 2 and "not an ancestor" in r.output and "day2" in r.output
    r = invoke("diff", site["repo"], "day1", "day2", "--truth", tmp_path / "missing.png", "--config", site["cfg"])
    assert r.exit_code == 2 and "missing.png" in r.output
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "changes.png").write_bytes(site["truth"].read_bytes())
    r = invoke("diff", site["repo"], "day1", "day2", "--truth", alone / "changes.png", "--config", site["cfg"])
    assert r.exit_code == 2 and "grid.json" in r.output
    wrong = _write_truth(tmp_path / "wrong", MapGrid(0.0, 1.0, 0.0025, 30, 20), [])
    (wrong.parent / "grid.json").write_text(json.dumps(MapGrid(0.0, 1.0, 0.0025, 31, 20).to_attrs()))
    r = invoke("diff", site["repo"], "day1", "day2", "--truth", wrong, "--config", site["cfg"])
    assert r.exit_code == 2 and "changes.png" in r.output and "31 x 20" in r.output
