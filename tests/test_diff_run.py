"""The library under ``mosaicmap diff`` (pipeline.diff_run), called directly as a program
would (no click), on a small synthetic map whose second version has a stain on the floor
and a changed stretch of its route panorama."""

from __future__ import annotations

import copy
import json
import time

import numpy as np
import pytest
import zarr

from mapstore.grid import MapGrid
from mapstore.layout import read_floor, set_version
from mapstore.repository import MapRepository
from mapstore.routes import RouteRecord, write_route
from pipeline.config import load_config
from pipeline.diff_run import DEFAULT_CONFIG_NAME, diff_summary_lines, diff_versions
from pipeline.errors import BadInput
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn

GRID = MapGrid(0.0, 1.0, 0.0025, 400, 400)  # 1 x 1 m
STAIN = Patch(0.3, 0.4, 0.45, 0.55, shift_px=(0, 0), delta=-40.0)
ROWS, SPACING = 200, 0.01  # the route: 2 m, a line every cm, 1 sample per degree
CHANGED_ROWS, SECTOR_DEG = (80, 120), (100, 140)  # what the second version changes on the route


def route(changed: bool) -> RouteRecord:
    """The route "loop" along y = 0.5 m; ``changed``: another texture, brighter, in
    SECTOR_DEG over CHANGED_ROWS (an object moved)."""
    lines = periodic_texture(5, 360, mean=120.0, std=40.0)[np.arange(ROWS) % 360]
    if changed:
        (r0, r1), (a0, a1) = CHANGED_ROWS, SECTOR_DEG
        lines[r0:r1, a0:a1] = periodic_texture(23, 360, mean=150.0, std=40.0)[r0:r1, a0:a1]
    poses = np.column_stack([SPACING * np.arange(ROWS) - 0.5, np.full(ROWS, 0.5), np.zeros(ROWS)])
    return RouteRecord(np.clip(np.rint(lines), 1, 255).astype(np.uint8), poses.astype(np.float32), s0_m=0.0,
                       spacing_m=SPACING, samples_per_degree=1.0)


def commit_route(url: str, rec: RouteRecord, tag: str) -> None:
    """A new map version writing route "loop" (the floor untouched), tagged ``tag``."""
    repo = MapRepository.open(url)
    with repo.commit_lock():
        session = repo.writable()
        root = zarr.open_group(session.store, mode="a")
        rec.version = read_floor(root).version + 1
        set_version(root, rec.version)
        write_route(root, "loop", rec)
        repo.tag(repo.commit(session, "route"), tag)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """Versions "one" (texture and the route) and "two" (a dark stain, the route changed)."""
    root = tmp_path_factory.mktemp("diff_run")
    cfg = copy.deepcopy(load_config(None))
    cfg["map"].update(chunk_px=64, shard_px=128)
    url = str(root / "map")
    tex = periodic_texture(2, 256)
    publish_raster(url, GRID, texture_tile_fn(tex, GRID), cfg=cfg)
    commit_route(url, route(False), "one")
    shards = shards_for_box(GRID, 128, STAIN.x0, STAIN.y0, STAIN.x1, STAIN.y1)
    publish_raster(url, GRID, texture_tile_fn(tex, GRID, [STAIN]), cfg=cfg, shards=shards)
    commit_route(url, route(True), "two")
    return {"url": url, "cfg": load_config(None)}


def test_diff_versions_finds_the_stain_and_the_route_change_and_writes_the_outputs(site, tmp_path):
    out = tmp_path / "out"
    started = time.perf_counter() - 100.0  # the command started 100 s ago (config loading, ...)
    run = diff_versions(site["url"], "one", "two", cfg=site["cfg"], out_dir=out, started=started)
    rep = run.report
    assert run.regions == len(rep["regions"]) == rep["summary"]["regions"] == 1
    x0, y0, x1, y1 = rep["regions"][0]["bbox_m"]
    assert abs(x0 - STAIN.x0) < 0.01 and abs(y1 - STAIN.y1) < 0.01
    assert rep["from"]["version"] == "one" and rep["to"]["version"] == "two"
    assert rep["seconds"]["command"] >= 100.0 and rep["seconds"]["outputs"] > 0
    # the route: one changed range over CHANGED_ROWS, in SECTOR_DEG
    (ch,) = rep["routes"]["changed"]
    (rng,) = ch["ranges"]
    assert abs(rng["s_m"][0] - CHANGED_ROWS[0] * SPACING) <= 0.03
    assert abs(rng["s_m"][1] - (CHANGED_ROWS[1] - 1) * SPACING) <= 0.03
    (sec,) = rng["sectors"]
    assert abs(sec["start_deg"] - SECTOR_DEG[0]) <= 5 and abs(sec["end_deg"] - SECTOR_DEG[1]) <= 5
    # every output written, diff.json the report as returned
    assert json.loads((out / "diff.json").read_text()) == json.loads(json.dumps(rep))
    for name in ("regions.json", "overlay.png", "diff.html", "route-loop.png"):
        assert (out / name).is_file(), name
    assert rep["outputs"]["route_loop"] == str(out / "route-loop.png")
    lines = diff_summary_lines(run)
    assert lines[0].startswith("diff one (") and "regions: 1," in "\n".join(lines)
    assert lines[-2] == f"outputs: {', '.join(rep['outputs'].values())}"
    assert lines[-1].startswith(f"seconds: {rep['seconds']['command']:.2f} (diff ")


def test_diff_versions_without_out_dir_writes_nothing(site, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = diff_versions(site["url"], "two", "two", cfg=site["cfg"])
    assert run.regions == 0 and "outputs" not in run.report and "outputs" not in run.report["seconds"]
    assert not any(tmp_path.iterdir())
    assert not any(line.startswith("outputs:") for line in diff_summary_lines(run))


def test_diff_versions_refuses_naming_the_culprit(site, tmp_path):
    url, cfg = site["url"], site["cfg"]
    with pytest.raises(BadInput, match="not an ancestor") as e:
        diff_versions(url, "two", "one", cfg=cfg)
    assert e.value.where == url
    with pytest.raises(BadInput, match="unknown version") as e:
        diff_versions(url, "one", "nope", cfg=cfg)
    assert e.value.where == url
    bad = copy.deepcopy(cfg)
    bad["diff"]["window_core_px"] = 0
    with pytest.raises(BadInput, match="window_core_px") as e:
        diff_versions(url, "one", "two", cfg=bad)
    assert e.value.where == DEFAULT_CONFIG_NAME
    with pytest.raises(BadInput) as e:
        diff_versions(url, "one", "two", cfg=bad, config_file=tmp_path / "mine.toml")
    assert e.value.where == str(tmp_path / "mine.toml")
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(BadInput, match="cannot write"):
        diff_versions(url, "one", "two", cfg=cfg, out_dir=blocker / "out")


def test_a_routes_only_map_is_refused_saying_why(tmp_path):
    """A map of route panoramas alone (what a build of omni logs without the floor stages
    publishes): one line saying diff needs a floor, not "not a mosaicmap map"."""
    url = str(tmp_path / "routes")
    repo = MapRepository.create(url)
    with repo.commit_lock():
        session = repo.writable()
        write_route(zarr.open_group(session.store, mode="a"), "loop", route(False))
        sid = session.commit("routes only")
    with pytest.raises(BadInput, match="route panoramas only, no floor") as e:
        diff_versions(url, sid, sid, cfg=load_config(None))
    assert e.value.where == url and sid in e.value.what

